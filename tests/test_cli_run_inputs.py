"""What a new user hands ``iotnav run`` and ``iotnav ingest``: phone export folders, binary streams."""

from __future__ import annotations

from pathlib import Path

import pandas as pd
from typer.testing import CliRunner

from iotnav.cli import app
from iotnav.io import ingest

runner = CliRunner()
SENSOR_LOGGER = Path(__file__).parent / "data" / "sensor_logger_android"


def test_run_reads_a_sensor_logger_folder(tmp_path: Path) -> None:
    res = runner.invoke(app, ["ingest", str(SENSOR_LOGGER)])
    assert res.exit_code == 0, res.output
    res = runner.invoke(app, ["run", str(SENSOR_LOGGER), "--out", str(tmp_path)])
    assert res.exit_code == 0, res.output
    track = pd.read_csv(tmp_path / "track.csv")
    # one output row per IMU sample that `iotnav ingest DIR` reads from the folder
    assert len(track) == len(ingest([SENSOR_LOGGER]).imu) > 0
    assert track["lat"].notna().all()


def test_run_names_what_a_folder_lacks(tmp_path: Path) -> None:
    (tmp_path / "notes.txt").write_text("nothing here\n")
    res = runner.invoke(app, ["run", str(tmp_path), "--out", str(tmp_path / "o")])
    assert res.exit_code == 2
    text = " ".join(res.output.split())
    assert "no gnss.nmea" in text and "Sensor Logger" in text


def test_sirf_binary_is_named_not_dumped(datasets: Path) -> None:
    log = datasets / "gpsd_nmea_corpus" / "logs" / "bu303-moving.log"
    for cmd in (["ingest", str(log)], ["run", "--gnss", str(log), "--out", "unused"]):
        res = runner.invoke(app, cmd)
        assert res.exit_code == 2, res.output
        text = " ".join(res.output.split())
        assert "SiRF binary" in text and "does not read" in text
        assert "\ufffd" not in res.output and "\x00" not in res.output  # no bytes in the message


def test_run_prints_what_it_could_not_read(tmp_path: Path) -> None:
    """A truncated sentence and one with a bad checksum are named and counted on the terminal."""
    good = (Path(__file__).parents[1] / "src/iotnav/data/walk_0827_nmea.txt").read_text().splitlines()
    log = tmp_path / "cut.nmea"
    # ten good lines, one cut mid-sentence, one with a wrong checksum
    log.write_text("\n".join([*good[:10], good[10][:15], "$GPGGA,garbage*00"]) + "\n")
    res = runner.invoke(app, ["run", str(log), "--out", str(tmp_path / "o")])
    assert res.exit_code == 0, res.output
    lines = {" ".join(ln.strip("│ ").split()) for ln in res.output.splitlines()}
    assert any(ln.startswith("not read (bad checksum)") and ln.endswith(" 1") for ln in lines), res.output
    assert any(ln.startswith("not read (truncated)") and ln.endswith(" 1") for ln in lines), res.output
