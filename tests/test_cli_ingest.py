"""The ingest / export / demo commands end to end on real logs (layer c)."""

from __future__ import annotations

import re
import xml.etree.ElementTree as ET
from pathlib import Path

import pandas as pd
from typer.testing import CliRunner

from iotnav.cli import app

runner = CliRunner()


def test_ingest_real_walk_writes_merged_csv(tmp_path: Path, datasets: Path) -> None:
    src = datasets / "rtklibexplorer_gnss_imu" / "walk_0827" / "gnss_1730_nmea.txt"
    out = tmp_path / "merged.csv"
    res = runner.invoke(app, ["ingest", str(src), "--out", str(out), "--report", str(tmp_path / "r.json")])
    assert res.exit_code == 0, res.output
    # Independent count: GGA sentences in the file (one per 4 Hz cycle).
    n_gga = sum(1 for line in src.read_text().splitlines() if re.match(r"^\$G[NP]GGA,", line))
    merged = pd.read_csv(out)
    assert (merged["kind"] == "gnss").sum() == n_gga == 536
    assert merged["t"].is_monotonic_increasing
    assert "GGA" in res.output and "TXT" in res.output


def test_ingest_rejects_a_non_log_with_exit_2(tmp_path: Path) -> None:
    bad = tmp_path / "photo.png"
    bad.write_bytes(b"\x89PNG\r\n\x1a\n" + bytes(range(256)) * 4)
    res = runner.invoke(app, ["ingest", str(bad)])
    assert res.exit_code == 2
    assert "photo.png" in "".join(res.output.split())  # rich wraps long paths
    empty = tmp_path / "empty.nmea"
    empty.write_bytes(b"")
    res = runner.invoke(app, ["ingest", str(empty)])
    assert res.exit_code == 2
    assert "empty" in res.output
    res = runner.invoke(app, ["ingest", str(tmp_path / "missing.nmea")])
    assert res.exit_code == 2


def test_export_gpx_from_a_log(tmp_path: Path, datasets: Path) -> None:
    src = datasets / "gpsd_nmea_corpus" / "logs" / "com-1289.log"
    res = runner.invoke(app, ["export", str(src), "--out", str(tmp_path / "t.gpx")])
    assert res.exit_code == 0, res.output
    pts = ET.parse(tmp_path / "t.gpx").getroot().findall(".//{http://www.topografix.com/GPX/1/1}trkpt")
    # Independent count: GGA sentences with fix quality > 0.
    text = src.read_text(errors="replace")
    n_fix = len(re.findall(r"\$GPGGA,[^,]*,[^,]*,[NS],[^,]*,[EW],[1-8],", text))
    assert len(pts) == n_fix > 0


def test_demo_writes_tracks_and_fuses_a_scenario(tmp_path: Path) -> None:
    res = runner.invoke(app, ["demo", "--out", str(tmp_path), "--duration", "60"])
    assert res.exit_code == 0, res.output
    for ext in ("csv", "geojson", "gpx", "kml"):
        assert (tmp_path / "real" / f"track.{ext}").stat().st_size > 1000
    fused = pd.read_csv(tmp_path / "pipeline" / "track.csv")
    imu_rows = sum(1 for _ in open(tmp_path / "sim" / "imu.csv")) - 1
    assert len(fused) == imu_rows
    assert "GNSS only" in res.output
