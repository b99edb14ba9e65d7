"""Every real capture with NMEA, UBX or IMU data ingests into one merged timeline (layer c).

The gpsd and pynmeagps NMEA corpora are covered capture by capture in
``test_gpsd_conformance.py`` and ``test_io_nmea.py``; this file covers the GNSS + IMU
recordings and the BROAD IMU trials, with counts taken by independent routes.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pandas as pd
import pytest
from typer.testing import CliRunner

from iotnav.cli import app
from iotnav.io import ingest

runner = CliRunner()


def _pos_lines(path: Path) -> int:
    return sum(1 for ln in path.read_text().splitlines() if ln.strip() and not ln.startswith("%"))


def _imu_rows(path: Path) -> int:
    """Complete 7-field rows, less rows repeating the previous row exactly (logger duplicates)."""
    rows = [ln.strip() for ln in path.read_text(errors="replace").splitlines() if ln.count(",") == 6]
    return sum(1 for i, r in enumerate(rows) if i == 0 or r != rows[i - 1])


@pytest.mark.parametrize(
    "name", ["drive_0708/gnss_1934_sf.pos+imu_1934.csv", "walk_0827/gnss_1730_sf.pos+imu_1730.csv"]
)
def test_gnss_and_imu_recordings_merge(datasets: Path, tmp_path: Path, name: str) -> None:
    folder, files = name.split("/")
    root = datasets / "rtklibexplorer_gnss_imu" / folder
    pos, imu = (root / f for f in files.split("+"))
    out = tmp_path / "merged.parquet"
    res = runner.invoke(app, ["ingest", str(pos), str(imu), "--out", str(out)])
    assert res.exit_code == 0, res.output
    merged = pd.read_parquet(out)
    assert (merged["kind"] == "gnss").sum() == _pos_lines(pos)
    assert (merged["kind"] == "imu").sum() == _imu_rows(imu)
    assert merged["t"].is_monotonic_increasing
    # Both clocks are UTC after GPST -> UTC: the IMU span sits inside the GNSS span within 5 s.
    g = merged.loc[merged["kind"] == "gnss", "t"]
    i = merged.loc[merged["kind"] == "imu", "t"]
    assert abs(i.min() - g.min()) < 5.0 and abs(i.max() - g.max()) < 5.0


def test_walk_ubx_stream_and_pos_agree_in_time(datasets: Path) -> None:
    root = datasets / "rtklibexplorer_gnss_imu" / "walk_0827"
    log = ingest([root / "gnss_1730.ubx", root / "gnss_1730_sf.pos"])
    ubx = log.gnss[log.gnss["source"] == "ubx"]
    pos = log.gnss[log.gnss["source"] == "rtklib"]
    # NAV-PVT epochs carry sub-ms time (x.7495 s), the .pos file prints ms (x.749): pair within 5 ms.
    pairs = pd.merge_asof(pos, ubx, on="t", tolerance=0.005, direction="nearest", suffixes=("_pos", "_ubx"))
    pairs = pairs.dropna(subset=["lat_deg_ubx"])
    # Real-time RTK (receiver) and post-processed RTK at the same UTC instants agree to decimetres
    # for RTK-fixed epochs of both, which only holds if GPST -> UTC (18 s) is applied correctly
    # (the walk moves about 1 m/s, so 18 s of misalignment would be metres).
    fixed = pairs[(pairs["quality_pos"] == 4) & (pairs["quality_ubx"] == 4)]
    assert len(fixed) > 100
    dn = (fixed["lat_deg_ubx"] - fixed["lat_deg_pos"]).abs().to_numpy() * 111_000
    assert np.median(dn) < 0.5


def test_broad_npz_trials_ingest(datasets: Path) -> None:
    trials = sorted((datasets / "broad_attitude").glob("*.npz"))
    assert len(trials) == 6  # five BROAD trials and VQF's test recording
    for path in trials:
        raw = np.load(path)
        acc, gyr = (raw["imu_acc"], raw["imu_gyr"]) if "imu_acc" in raw.files else (raw["acc"], raw["gyr"])
        n_ok = int((np.isfinite(acc).all(1) & np.isfinite(gyr).all(1)).sum())
        log = ingest([path])
        assert len(log.imu) == n_ok
        np.testing.assert_allclose(log.imu["acc_x"].to_numpy()[:5], acc[:5, 0])
        assert log.imu["t"].iloc[1] == pytest.approx(1.0 / float(raw["sampling_rate"]))


def test_damaged_npz_is_a_clear_error(tmp_path: Path) -> None:
    bad = tmp_path / "x.npz"
    bad.write_bytes(b"PK\x03\x04 not really a zip")
    res = runner.invoke(app, ["ingest", str(bad)])
    assert res.exit_code == 2 and "x.npz" in res.output
    np.savez(tmp_path / "y.npz", other=np.zeros(3))
    res = runner.invoke(app, ["ingest", str(tmp_path / "y.npz")])
    assert res.exit_code == 2 and "imu_acc" in res.output
