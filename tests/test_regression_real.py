"""Real-data regression (STYLE §11c): 60 s of the real drive_0708 run end to end through
``iotnav run`` and compared with a stored result.

Input, cut at test time from ``shared/datasets/rtklibexplorer_gnss_imu/drive_0708`` (a real
ICM-45686 + u-blox X20 car drive, RTK fixes at 4 Hz): GNSS epochs 60-120 s after the first one,
with those 90-100 s removed (a 10 s outage, so the stored track holds 10 s of the engine's own
dead reckoning), and the IMU samples of that window (``imu_1934_gpst.csv``, GPST stamps).
Engine ``anchor`` with its defaults. Stored: every 100th output row (about 1 Hz) of
``track.csv`` in ``tests/data/regression_drive_0708_anchor.csv``.

Tolerances: 2 cm in position and 2 cm/s in velocity and 0.05 deg in attitude (the run is
deterministic; the bounds leave room for floating-point differences between machines).
A deliberate change of the engine (here the mount angle fixed at 0 instead of estimated, through a
configuration file) moves the dead-reckoned track by far more and the comparison fails.

To regenerate after an intended change of the engine (say why in the commit)::

    IOTNAV_DATASETS=... python tests/test_regression_real.py --write
"""

from __future__ import annotations

import sys
from datetime import UTC, datetime
from pathlib import Path

import numpy as np
import pandas as pd
from typer.testing import CliRunner

from iotnav.cli import app

STORED = Path(__file__).parent / "data" / "regression_drive_0708_anchor.csv"
COLUMNS = ["t", "lat", "lon", "height", "vn", "ve", "vd", "roll", "pitch", "yaw", "source"]


def _cut(drive: Path, out: Path) -> list[Path]:
    """The 60 s window of drive_0708 with a 10 s GNSS outage, as a .pos and an IMU CSV."""
    lines = (drive / "gnss_1934_sf.pos").read_text().splitlines()
    header = [ln for ln in lines if ln.startswith("%")]
    rows = [ln for ln in lines if ln.strip() and not ln.startswith("%")]

    def gpst(ln: str) -> float:
        d, t = ln.split()[:2]
        return datetime.strptime(f"{d} {t}", "%Y/%m/%d %H:%M:%S.%f").replace(tzinfo=UTC).timestamp()

    t0 = gpst(rows[0])
    keep = [ln for ln in rows if 60.0 <= gpst(ln) - t0 < 120.0 and not 90.0 <= gpst(ln) - t0 < 100.0]
    out.mkdir(parents=True, exist_ok=True)
    (out / "gnss.pos").write_text("\n".join(header + keep) + "\n")
    imu = (drive / "imu_1934_gpst.csv").read_text().splitlines()
    sel = [ln for ln in imu[1:] if 60.0 <= float(ln.split(",", 1)[0]) - t0 < 120.5]
    (out / "imu.csv").write_text("\n".join([imu[0], *sel]) + "\n")
    return [out / "gnss.pos", out / "imu.csv"]


def _run(drive: Path, tmp: Path, config: Path | None = None) -> pd.DataFrame:
    files = _cut(drive, tmp / "in")
    args = ["run", *map(str, files), "--engine", "anchor", "--out", str(tmp / "out")]
    if config is not None:
        args += ["--config", str(config)]
    res = CliRunner().invoke(app, args)
    assert res.exit_code == 0, res.output
    track = pd.read_csv(tmp / "out" / "track.csv")
    return track.iloc[::100][COLUMNS].reset_index(drop=True)


def _differences(got: pd.DataFrame, ref: pd.DataFrame) -> dict[str, float]:
    """Largest differences: position (m), velocity (m/s), attitude (deg); inf on a shape change."""
    if len(got) != len(ref) or not np.allclose(got["t"], ref["t"], atol=1e-6, rtol=0):
        return {"rows": np.inf}
    if list(got["source"]) != list(ref["source"]):
        return {"source": np.inf}
    lat0 = np.radians(float(ref["lat"].iloc[0]))
    dn = np.radians(got["lat"] - ref["lat"]) * 6.371e6
    de = np.radians(got["lon"] - ref["lon"]) * 6.371e6 * np.cos(lat0)
    pos = np.sqrt(dn**2 + de**2 + (got["height"] - ref["height"]) ** 2)
    vel = np.abs(got[["vn", "ve", "vd"]].to_numpy() - ref[["vn", "ve", "vd"]].to_numpy())
    att = np.abs(
        np.angle(
            np.exp(1j * (got[["roll", "pitch", "yaw"]].to_numpy() - ref[["roll", "pitch", "yaw"]].to_numpy()))
        )
    )
    return {
        "position_m": float(np.nanmax(pos)),
        "velocity_mps": float(np.nanmax(vel)),
        "attitude_deg": float(np.degrees(np.nanmax(att))),
    }


TOLERANCE = {"position_m": 0.02, "velocity_mps": 0.02, "attitude_deg": 0.05}


def _within(diff: dict[str, float]) -> bool:
    return all(k in TOLERANCE and v <= TOLERANCE[k] for k, v in diff.items())


def test_drive_0708_60s_anchor_matches_the_stored_result(datasets: Path, tmp_path: Path) -> None:
    drive = datasets / "rtklibexplorer_gnss_imu" / "drive_0708"
    ref = pd.read_csv(STORED)
    got = _run(drive, tmp_path)
    assert int((got["source"] == "dr").sum()) >= 8  # the outage is in the stored rows
    diff = _differences(got, ref)
    assert _within(diff), diff
    # the comparison can fail: a deliberate change of the engine is caught
    cfg = tmp_path / "changed.toml"
    cfg.write_text("[kf]\nmount_yaw_rad = 0.0\n")
    changed = _differences(_run(drive, tmp_path / "changed", cfg), ref)
    assert not _within(changed), changed


if __name__ == "__main__" and "--write" in sys.argv:
    import os
    import tempfile

    from conftest import datasets_dir

    with tempfile.TemporaryDirectory() as d:
        base = Path(os.environ.get("IOTNAV_DATASETS", datasets_dir()))
        table = _run(base / "rtklibexplorer_gnss_imu" / "drive_0708", Path(d))
    table.to_csv(STORED, index=False)
    print(f"wrote {STORED} ({len(table)} rows)")
