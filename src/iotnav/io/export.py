"""Write a track (any table with time, latitude, longitude, height) as CSV, GeoJSON, GPX 1.1 or KML.

Column names are looked up in this order: time ``utc`` (UTC Unix s) then ``t``; latitude
``lat`` then ``lat_deg``; longitude ``lon`` then ``lon_deg``; height ``height`` then
``height_m`` (optional). Rows with a non-finite latitude or longitude are left out and counted.
GPX and KML carry UTC times only when a UTC time is known (a ``utc`` column or a given
``utc_offset_s``), since both formats define their timestamps as UTC.
"""

from __future__ import annotations

import json
import math
import os
import xml.etree.ElementTree as ET
from dataclasses import dataclass
from datetime import UTC, datetime
from pathlib import Path

import numpy as np
import pandas as pd

FORMATS = ("csv", "geojson", "gpx", "kml")


@dataclass(frozen=True)
class ExportResult:
    """What :func:`export_track` wrote.

    Attributes
    ----------
    path : pathlib.Path
        The written file.
    format : str
        One of :data:`FORMATS`.
    points : int
        Points written.
    skipped : int
        Rows left out for a non-finite position.
    """

    path: Path
    format: str
    points: int
    skipped: int


def _pick(df: pd.DataFrame, *names: str) -> str | None:
    for n in names:
        if n in df.columns:
            return n
    return None


def track_columns(df: pd.DataFrame) -> tuple[str | None, str, str, str | None]:
    """Find the (time, lat, lon, height) column names of a track table.

    Raises
    ------
    ValueError
        When no latitude/longitude columns are present.
    """
    lat = _pick(df, "lat", "lat_deg", "latitude")
    lon = _pick(df, "lon", "lon_deg", "longitude")
    if lat is None or lon is None:
        raise ValueError(
            "a track needs latitude and longitude columns (lat/lon or lat_deg/lon_deg); "
            f"found {list(df.columns)[:12]}"
        )
    return _pick(df, "utc", "t"), lat, lon, _pick(df, "height", "height_m", "alt")


def _iso(utc: float) -> str:
    return datetime.fromtimestamp(utc, tz=UTC).strftime("%Y-%m-%dT%H:%M:%S.%f")[:-3] + "Z"


def _utc_series(df: pd.DataFrame, tcol: str | None, utc_offset_s: float | None) -> np.ndarray | None:
    if tcol == "utc":
        return df["utc"].to_numpy(dtype=float)
    if tcol == "t" and utc_offset_s is not None and math.isfinite(utc_offset_s):
        return df["t"].to_numpy(dtype=float) + utc_offset_s
    return None


def guess_format(path: str | os.PathLike[str]) -> str:
    """Export format from a file extension (``.csv``, ``.geojson``/``.json``, ``.gpx``, ``.kml``)."""
    ext = Path(path).suffix.lower().lstrip(".")
    if ext == "json":
        ext = "geojson"
    if ext not in FORMATS:
        raise ValueError(f"{path}: unknown export format {ext!r}; expected one of {', '.join(FORMATS)}")
    return ext


def export_track(
    df: pd.DataFrame,
    path: str | os.PathLike[str],
    fmt: str | None = None,
    *,
    name: str = "iotnav track",
    utc_offset_s: float | None = None,
) -> ExportResult:
    """Write a track table to ``path``.

    Parameters
    ----------
    df : pandas.DataFrame
        Track with time, latitude (deg), longitude (deg) and optionally ellipsoidal height (m).
    path : path-like
        Output file; parent directories are created.
    fmt : str, optional
        ``csv``, ``geojson``, ``gpx`` or ``kml``; from the extension when omitted.
    name : str
        Track name written into GeoJSON/GPX/KML.
    utc_offset_s : float, optional
        ``utc = t + utc_offset_s`` when the table has device time only.

    Returns
    -------
    ExportResult
        Path, format, points written and rows skipped.
    """
    fmt = fmt or guess_format(path)
    if fmt not in FORMATS:
        raise ValueError(f"unknown export format {fmt!r}; expected one of {', '.join(FORMATS)}")
    tcol, latc, lonc, hc = track_columns(df)
    lat = df[latc].to_numpy(dtype=float)
    lon = df[lonc].to_numpy(dtype=float)
    ok = np.isfinite(lat) & np.isfinite(lon)
    skipped = int((~ok).sum())
    sub = df.loc[ok].reset_index(drop=True)
    lat, lon = lat[ok], lon[ok]
    h = sub[hc].to_numpy(dtype=float) if hc else np.full(lat.size, np.nan)
    utc = _utc_series(sub, tcol, utc_offset_s)
    out = Path(path)
    out.parent.mkdir(parents=True, exist_ok=True)
    if fmt == "csv":
        sub.to_csv(out, index=False, float_format="%.10g")
    elif fmt == "geojson":
        coords = [
            [float(a), float(b)] + ([float(c)] if math.isfinite(c) else [])
            for a, b, c in zip(lon, lat, h, strict=False)
        ]
        props: dict[str, object] = {"name": name, "points": len(coords)}
        if utc is not None:
            props["times"] = [_iso(u) if math.isfinite(u) else None for u in utc]
        feature = {
            "type": "Feature",
            "geometry": {"type": "LineString", "coordinates": coords},
            "properties": props,
        }
        out.write_text(json.dumps({"type": "FeatureCollection", "features": [feature]}))
    elif fmt == "gpx":
        ns = "http://www.topografix.com/GPX/1/1"
        ET.register_namespace("", ns)
        gpx = ET.Element(f"{{{ns}}}gpx", {"version": "1.1", "creator": "iotnav"})
        trk = ET.SubElement(gpx, f"{{{ns}}}trk")
        ET.SubElement(trk, f"{{{ns}}}name").text = name
        seg = ET.SubElement(trk, f"{{{ns}}}trkseg")
        for i in range(lat.size):
            pt = ET.SubElement(seg, f"{{{ns}}}trkpt", {"lat": f"{lat[i]:.9f}", "lon": f"{lon[i]:.9f}"})
            if math.isfinite(h[i]):
                ET.SubElement(pt, f"{{{ns}}}ele").text = f"{h[i]:.3f}"
            if utc is not None and math.isfinite(utc[i]):
                ET.SubElement(pt, f"{{{ns}}}time").text = _iso(utc[i])
        ET.ElementTree(gpx).write(out, encoding="utf-8", xml_declaration=True)
    else:  # kml
        ns = "http://www.opengis.net/kml/2.2"
        ET.register_namespace("", ns)
        kml = ET.Element(f"{{{ns}}}kml")
        doc = ET.SubElement(kml, f"{{{ns}}}Document")
        pm = ET.SubElement(doc, f"{{{ns}}}Placemark")
        ET.SubElement(pm, f"{{{ns}}}name").text = name
        ls = ET.SubElement(pm, f"{{{ns}}}LineString")
        # Heights are ellipsoidal while KML "absolute" means above MSL: keep them as data, clamp.
        has_h = bool(np.isfinite(h).all()) and lat.size > 0
        ET.SubElement(ls, f"{{{ns}}}altitudeMode").text = "clampToGround"
        kml_coords = " ".join(
            f"{lon[i]:.9f},{lat[i]:.9f}" + (f",{h[i]:.3f}" if has_h else "") for i in range(lat.size)
        )
        ET.SubElement(ls, f"{{{ns}}}coordinates").text = kml_coords
        ET.ElementTree(kml).write(out, encoding="utf-8", xml_declaration=True)
    return ExportResult(out, fmt, int(lat.size), skipped)
