"""Track export: CSV, GeoJSON, GPX 1.1, KML parsed back independently (layer a)."""

from __future__ import annotations

import json
import xml.etree.ElementTree as ET
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from iotnav.io import export
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


def test_round_significant_gives_printf_digits() -> None:
    rng = np.random.default_rng(7)
    x = np.concatenate(
        [
            rng.normal(size=3000) * 10.0 ** rng.integers(-30, 30, 3000),
            [0.5, 1.25, 2.5e-7, 1234567890.5, 9.9999999995, 1e-300, 5e-324, -0.0, 0.0],
        ]
    )
    r = export.round_significant(x, 10)
    assert [float(f"{v:.10g}") for v in x] == r.tolist()


def test_fixed_decimals_as_fstrings() -> None:
    rng = np.random.default_rng(8)
    x = np.concatenate([rng.normal(size=3000) * 200.0, [0.0, -0.0, -1e-12, 0.0005, 2.0**60, np.nan]])
    assert export._fixed(x, 9) == [f"{v:.9f}" for v in x]
    assert export._fixed(x, 3) == [f"{v:.3f}" for v in x]


def test_write_csv_reads_back_as_pandas_writes(tmp_path: Path) -> None:
    rng = np.random.default_rng(9)
    n = 500
    df = pd.DataFrame(
        {
            "t": 1.7e9 + np.arange(n) * 0.01,
            "lat": 45.0 + rng.normal(size=n) * 1e-3,
            "std": np.abs(rng.normal(size=n)) * 1e-9,
            "n": np.arange(n),
            "static": rng.random(n) > 0.5,
            "source": pd.Categorical.from_codes(rng.integers(-1, 3, n), ["none", "fix", "dr"]),
            "name": ["a"] * (n - 1) + [None],
        }
    )
    df.loc[3, "lat"] = np.nan
    df.loc[4, "std"] = np.inf
    export.write_csv(df, tmp_path / "fast.csv")
    df.to_csv(tmp_path / "pandas.csv", index=False, float_format="%.10g")
    fast = pd.read_csv(tmp_path / "fast.csv")
    ref = pd.read_csv(tmp_path / "pandas.csv")
    # times in full (ten digits of 1.7e9 s are whole seconds); everything else as pandas wrote it
    np.testing.assert_array_equal(fast["t"], df["t"])
    assert ref["t"].nunique() < n / 50
    pd.testing.assert_frame_equal(fast.drop(columns="t"), ref.drop(columns="t"), check_exact=True)
    line = (tmp_path / "fast.csv").read_text().splitlines()[4]  # row 3: NaN latitude
    assert line.split(",")[1] == "" and line.split(",")[4] in ("True", "False")
    # a text field needing quotes goes through pandas: the same bytes as pandas
    df["name"] = "a,b"
    export.write_csv(df.drop(columns="t"), tmp_path / "quoted.csv")
    df.drop(columns="t").to_csv(tmp_path / "quoted_ref.csv", index=False, float_format="%.10g")
    assert (tmp_path / "quoted.csv").read_bytes() == (tmp_path / "quoted_ref.csv").read_bytes()


def test_parquet_keeps_every_bit(tmp_path: Path, track: pd.DataFrame) -> None:
    track = track.assign(source=pd.Categorical(["fix", "dr", "fix", "dr"]))
    res = export_track(track, tmp_path / "t.parquet")
    back = export.read_table(res.path)
    pd.testing.assert_frame_equal(back, track.dropna(subset=["lat"]).reset_index(drop=True), check_exact=True)


def test_decimation(tmp_path: Path) -> None:
    t = 5.0 + np.arange(1001) * 0.01  # 10 s at 100 Hz
    assert export.decimate(t, 1.0).tolist() == [*range(0, 1001, 100)]
    assert export.decimate(t, 0.0).tolist() == list(range(1001))
    df = pd.DataFrame({"t": t, "lat": 45.0 + t * 1e-5, "lon": 7.0 + t * 1e-5})
    res = export_track(df, tmp_path / "d.geojson", rate_hz=2.0)
    coords = json.loads(res.path.read_text())["features"][0]["geometry"]["coordinates"]
    assert (res.points, res.decimated, len(coords)) == (21, 980, 21)
    assert coords[1] == pytest.approx([df["lon"][50], df["lat"][50]])
    with pytest.raises(ValueError, match="time column"):
        export_track(df.drop(columns="t"), tmp_path / "x.gpx", rate_hz=1.0)


def test_iso_times_as_datetime() -> None:
    from datetime import UTC, datetime

    u = np.array([1756402221.75, 0.0, 1.0e9 + 0.0005, 1.7e9 + 0.9999996, -1.5, np.nan])
    want = [
        datetime.fromtimestamp(v, tz=UTC).strftime("%Y-%m-%dT%H:%M:%S.%f")[:-3] + "Z"
        if np.isfinite(v)
        else None
        for v in u
    ]
    assert export.iso_times(u) == want
