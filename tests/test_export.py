"""Track export: CSV, GeoJSON, GPX 1.1, KML parsed back independently (layer a)."""

from __future__ import annotations

import json
import xml.etree.ElementTree as ET
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from iotnav.io.export import export_track, guess_format


@pytest.fixture
def track() -> pd.DataFrame:
    return pd.DataFrame(
        {
            "utc": [1756402221.75, 1756402222.0, 1756402222.25, 1756402222.5],
            "lat": [40.0966916, 40.0966917, np.nan, 40.0966920],
            "lon": [-105.1471665, -105.1471664, -105.1471663, -105.1471662],
            "height": [1580.048, 1580.05, 1580.06, 1580.07],
        }
    )


def test_gpx(tmp_path: Path, track: pd.DataFrame) -> None:
    res = export_track(track, tmp_path / "t.gpx")
    assert (res.format, res.points, res.skipped) == ("gpx", 3, 1)
    ns = {"g": "http://www.topografix.com/GPX/1/1"}
    root = ET.parse(res.path).getroot()
    assert root.get("version") == "1.1"
    pts = root.findall(".//g:trkpt", ns)
    assert len(pts) == 3
    assert float(pts[0].get("lat")) == pytest.approx(40.0966916, abs=1e-9)
    assert pts[0].find("g:time", ns).text == "2025-08-28T17:30:21.750Z"
    assert float(pts[2].find("g:ele", ns).text) == pytest.approx(1580.07)


def test_geojson_kml_csv(tmp_path: Path, track: pd.DataFrame) -> None:
    gj = json.loads(export_track(track, tmp_path / "t.geojson").path.read_text())
    coords = gj["features"][0]["geometry"]["coordinates"]
    assert coords[0] == pytest.approx([-105.1471665, 40.0966916, 1580.048])
    assert len(coords) == 3
    kml = ET.parse(export_track(track, tmp_path / "t.kml").path).getroot()
    text = kml.find(".//{http://www.opengis.net/kml/2.2}coordinates").text
    assert text.split()[1].split(",")[:2] == ["-105.147166400", "40.096691700"]
    back = pd.read_csv(export_track(track, tmp_path / "t.csv").path)
    assert len(back) == 3
    np.testing.assert_allclose(back["lat"], track["lat"].dropna(), rtol=0, atol=1e-9)


def test_device_time_needs_offset_for_gpx_times(tmp_path: Path) -> None:
    df = pd.DataFrame({"t": [10.0, 11.0], "lat_deg": [45.0, 45.0001], "lon_deg": [7.0, 7.0]})
    root = ET.parse(export_track(df, tmp_path / "a.gpx").path).getroot()
    assert root.find(".//{http://www.topografix.com/GPX/1/1}time") is None
    root = ET.parse(export_track(df, tmp_path / "b.gpx", utc_offset_s=1.0e9).path).getroot()
    assert root.find(".//{http://www.topografix.com/GPX/1/1}time").text == "2001-09-09T01:46:50.000Z"


def test_bad_requests(tmp_path: Path) -> None:
    with pytest.raises(ValueError, match="unknown export format"):
        guess_format("x.shp")
    with pytest.raises(ValueError, match="latitude and longitude"):
        export_track(pd.DataFrame({"t": [1.0]}), tmp_path / "x.csv")
