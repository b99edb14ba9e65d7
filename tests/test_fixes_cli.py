"""``iotnav run`` on GNSS-only logs: the ``fixes`` engine by default, --smooth / --rate, and the
zero-rows error."""

from __future__ import annotations

import json
from importlib import resources
from pathlib import Path

import pandas as pd
from typer.testing import CliRunner

from _nmea_helpers import xor_checksum
from iotnav.cli import app
from iotnav.engines.base import OUTPUT_COLUMNS

runner = CliRunner()
WALK = Path(str(resources.files("iotnav") / "data" / "walk_0827_nmea.txt"))


def test_run_defaults_to_fixes_without_imu(tmp_path: Path) -> None:
    out = tmp_path / "run"
    res = runner.invoke(app, ["run", str(WALK), "--out", str(out)])
    assert res.exit_code == 0, res.output
    assert "engine: fixes (no IMU samples: GNSS fixes alone)" in " ".join(res.output.split())
    track = pd.read_csv(out / "track.csv")
    assert list(track.columns) == list(OUTPUT_COLUMNS)
    n_fix = sum(1 for line in WALK.read_text().splitlines() if line.startswith("$GNGGA"))
    assert n_fix == 536 and len(track) == n_fix  # one row per fix, none lost
    summary = json.loads((out / "summary.json").read_text())
    assert summary["engine"] == "fixes"
    assert summary["engine_choice"] == {
        "name": "fixes",
        "reason": "no IMU samples: GNSS fixes alone",
        "default": True,
    }
    assert summary["engine_summary"]["config"]["kf"]["platform"] == "car"
    assert set(track["source"]) <= {"fix", "lowpass", "dr"}


def test_run_smooth_and_rate(tmp_path: Path) -> None:
    out = tmp_path / "run"
    res = runner.invoke(app, ["run", str(WALK), "--out", str(out), "--smooth", "--rate", "2"])
    assert res.exit_code == 0, res.output
    track = pd.read_csv(out / "track.csv")
    fwd = pd.read_csv(out / "forward" / "track.csv")
    span = fwd["t"].iloc[-1] - fwd["t"].iloc[0]
    assert abs(len(track) - 2 * span) <= 2  # 2 Hz over the fixes' span
    # (track.csv writes 10 significant digits: Unix times lose their fraction, so no spacing check)
    assert track[["lat", "lon", "std_north"]].notna().all().all()


def test_rate_needs_the_fixes_engine(tmp_path: Path) -> None:
    res = runner.invoke(app, ["run", str(WALK), "--out", str(tmp_path), "--engine", "anchor", "--rate", "1"])
    assert res.exit_code == 2 and "--rate" in res.output


def test_zero_rows_is_an_error_that_says_why(tmp_path: Path) -> None:
    # an IMU engine on a GNSS-only log
    res = runner.invoke(app, ["run", str(WALK), "--out", str(tmp_path / "a"), "--engine", "pipeline"])
    assert res.exit_code == 2
    assert "no output rows" in res.output and "IMU" in res.output
    # a log whose fixes are all flagged invalid (RMC status V, GGA quality 0)
    lines = []
    for line in WALK.read_text().splitlines()[:300]:
        body = line[1 : line.index("*")]
        f = body.split(",")
        if f[0] == "GNRMC":
            f[2] = "V"
        elif f[0] == "GNGGA":
            f[6] = "0"
        elif f[0] == "GNGLL":
            f[6] = "V"
        body = ",".join(f)
        lines.append(f"${body}*{xor_checksum(body.encode()):02X}")
    bad = tmp_path / "invalid.nmea"
    bad.write_text("\n".join(lines) + "\n")
    res = runner.invoke(app, ["run", str(bad), "--out", str(tmp_path / "b")])
    assert res.exit_code == 2
    assert "no output rows" in res.output and "gnss_invalid" in res.output
    summary = json.loads((tmp_path / "b" / "summary.json").read_text())
    assert summary["engine_summary"]["skipped"]["gnss_invalid"] == summary["counts"]["gnss_epochs_in"] > 0
