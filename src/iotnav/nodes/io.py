"""Files of the node-localization step: anchor tracks and RSSI logs in, node positions out.

Anchor tracks
    CSV with at least ``t, lat, lon`` (s, degrees) and optionally ``height`` (m, ellipsoidal),
    ``std_north``, ``std_east`` (m, the fusion engine's 1-sigma) and ``anchor_id``, as
    ``iotnav run`` writes them (``OUT/track.csv`` with ``t,lat,lon,height,north,east,down,...,
    std_north,std_east,source``); other columns are ignored and listed in the report's notes.
    The anchor id is, in this order: the ``ID`` of an ``ID=PATH`` argument; the file's
    ``anchor_id`` column (one file may hold several anchors); the parent directory's name when
    the file is called ``track.csv`` (so ``runs/A01/track.csv`` is anchor ``A01``); else the
    file's stem (``anchors/A01.csv`` is ``A01``).

RSSI logs
    CSV ``t,anchor_id,node_id,rssi_dbm[,snr_db]`` (s, text, text, dBm, dB).

Every line is either used, ignored on purpose (blank, ``#`` comment, header) or skipped and
counted under a reason with its line number (:class:`iotnav.io.report.FileReport`): truncated
or overlong lines, non-numeric fields, NaN, values out of physical range (latitude, standard
deviations, RSSI outside ``[-150, +30]`` dBm), time going backwards or repeated (per anchor).
A file without the required columns raises :class:`iotnav.io.errors.IngestError` naming the
file, what it has and what was expected.
"""

from __future__ import annotations

import csv
import json
import math
import os
from collections.abc import Iterable, Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from iotnav.geo import LocalFrame
from iotnav.io.errors import IngestError
from iotnav.io.report import FileReport, SkipReason
from iotnav.nodes.ranging import RSSI_MAX_DBM, RSSI_MIN_DBM

TRACK_REQUIRED = ("t", "lat", "lon")
TRACK_OPTIONAL = ("height", "std_north", "std_east", "anchor_id")
RSSI_REQUIRED = ("t", "anchor_id", "node_id", "rssi_dbm")
RSSI_OPTIONAL = ("snr_db",)

#: File names whose parent directory names the anchor (``iotnav run`` output layout).
RUN_TRACK_NAMES = ("track.csv",)


def parse_anchor_spec(spec: str | os.PathLike[str]) -> tuple[str | None, Path]:
    """Split an ``ID=PATH`` argument; a plain path gives ``(None, path)``."""
    s = os.fspath(spec)
    if "=" in s:
        left, right = s.split("=", 1)
        if left and "/" not in left and "\\" not in left and right:
            return left, Path(right)
    return None, Path(s)


def anchor_id_for(path: Path) -> str:
    """Anchor id of a track file without ``anchor_id`` column (see the module docstring)."""
    if path.name.lower() in RUN_TRACK_NAMES and path.parent.name:
        return path.resolve().parent.name
    return path.stem


def _rows(path: Path, report: FileReport) -> Iterator[tuple[int, list[str], list[str]]]:
    """Yield ``(line_number, header, fields)`` for data lines, counting the others."""
    header: list[str] | None = None
    with open(path, newline="", encoding="utf-8", errors="replace") as fh:
        for lineno, line in enumerate(fh, start=1):
            text = line.strip()
            report.units += 1
            if not text or text.startswith("#"):
                report.ignore("blank or comment")
                continue
            fields = [f.strip() for f in next(csv.reader([text]))]
            if header is None:
                header = fields
                report.ignore("header")
                continue
            yield lineno, header, fields
    if header is None:
        raise IngestError(str(path), "empty file: expected a CSV header line")


def _check_header(
    path: Path, header: list[str], required: Iterable[str], known: Iterable[str], report: FileReport
) -> None:
    missing = [c for c in required if c not in header]
    if missing:
        raise IngestError(
            str(path),
            f"missing column(s) {', '.join(missing)}; found {', '.join(header) or 'nothing'}; "
            f"expected at least {','.join(required)}",
        )
    extra = [c for c in header if c not in set(required) | set(known)]
    if extra:
        report.notes.append(f"columns not used: {', '.join(extra)}")


def _float(s: str) -> float:
    return float(s) if s != "" else math.nan


def read_anchor_track(
    spec: str | os.PathLike[str], default_std_m: float | None = None
) -> tuple[pd.DataFrame, FileReport]:
    """Read one anchor track file.

    Parameters
    ----------
    spec : str or path-like
        ``PATH`` or ``ID=PATH``.
    default_std_m : float, optional
        Horizontal standard deviation (m) used when the file has no ``std_north``/``std_east``
        columns; 0 (exact anchor positions) when omitted. Noted in the report either way.

    Returns
    -------
    pandas.DataFrame
        ``t, anchor_id, lat, lon, height, std_north, std_east`` (s, degrees, m).
    FileReport
        Counts of used, ignored and skipped lines.

    Raises
    ------
    FileNotFoundError
        When the file does not exist.
    IngestError
        When the header lacks ``t``, ``lat`` or ``lon``.
    """
    explicit, path = parse_anchor_spec(spec)
    if not path.is_file():
        raise FileNotFoundError(f"anchor track {path} not found")
    report = FileReport(path=str(path), format="anchor-track-csv")
    fallback_id = explicit if explicit is not None else anchor_id_for(path)
    out: dict[str, list[Any]] = {
        k: [] for k in ("t", "anchor_id", "lat", "lon", "height", "std_north", "std_east")
    }
    last_t: dict[str, float] = {}
    checked = False
    has_std = True
    for lineno, header, fields in _rows(path, report):
        if not checked:
            _check_header(path, header, TRACK_REQUIRED, (*TRACK_OPTIONAL, "north", "east", "down"), report)
            has_std = "std_north" in header and "std_east" in header
            if not has_std:
                std0 = default_std_m if default_std_m is not None else 0.0
                report.notes.append(f"no std_north/std_east columns: anchor std taken as {std0:g} m")
            if explicit is None and "anchor_id" not in header:
                report.notes.append(f"anchor id {fallback_id!r} from the file name")
            checked = True
        line = ",".join(fields)
        if len(fields) < len(header):
            report.skip(SkipReason.TRUNCATED, lineno, line)
            continue
        if len(fields) > len(header):
            report.skip(SkipReason.MALFORMED, lineno, line)
            continue
        rec = dict(zip(header, fields, strict=True))
        try:
            t = _float(rec["t"])
            lat = _float(rec["lat"])
            lon = _float(rec["lon"])
            h = _float(rec["height"]) if "height" in rec else 0.0
            if has_std:
                sn, se = _float(rec["std_north"]), _float(rec["std_east"])
            else:
                sn = se = default_std_m if default_std_m is not None else 0.0
        except ValueError:
            report.skip(SkipReason.MALFORMED, lineno, line)
            continue
        if not all(math.isfinite(v) for v in (t, lat, lon, h, sn, se)):
            report.skip(SkipReason.NAN_FIELD, lineno, line)
            continue
        if abs(lat) > 90.0 or abs(lon) > 180.0 or sn < 0.0 or se < 0.0:
            report.skip(SkipReason.OUT_OF_RANGE, lineno, line)
            continue
        aid = explicit if explicit is not None else (rec.get("anchor_id") or fallback_id)
        prev = last_t.get(aid)
        if prev is not None and t < prev:
            report.skip(SkipReason.NON_MONOTONIC, lineno, line)
            continue
        if prev is not None and t == prev:
            report.skip(SkipReason.DUPLICATE, lineno, line)
            continue
        last_t[aid] = t
        for k, v in zip(out, (t, aid, lat, lon, h, sn, se), strict=True):
            out[k].append(v)
        report.record("anchor epoch")
    return pd.DataFrame(out), report


def read_anchor_tracks(
    specs: Iterable[str | os.PathLike[str]], default_std_m: float | None = None
) -> tuple[pd.DataFrame, list[FileReport]]:
    """Read several anchor track files (see :func:`read_anchor_track`).

    Raises
    ------
    IngestError
        When two files claim the same anchor id.
    """
    tables = []
    reports = []
    owner: dict[str, str] = {}
    for spec in specs:
        df, rep = read_anchor_track(spec, default_std_m)
        for aid in df["anchor_id"].unique():
            if aid in owner:
                raise IngestError(
                    rep.path,
                    f"anchor id {aid!r} also comes from {owner[aid]}; name them explicitly with ID=PATH",
                )
            owner[str(aid)] = rep.path
        tables.append(df)
        reports.append(rep)
    if not tables:
        raise ValueError("no anchor track given (--anchors)")
    return pd.concat(tables, ignore_index=True), reports


def read_rssi(path: str | os.PathLike[str]) -> tuple[pd.DataFrame, FileReport]:
    """Read an RSSI log ``t,anchor_id,node_id,rssi_dbm[,snr_db]``.

    Returns
    -------
    pandas.DataFrame
        ``t, anchor_id, node_id, rssi_dbm, snr_db`` (``snr_db`` NaN when absent).
    FileReport
        Counts of used, ignored and skipped lines.

    Raises
    ------
    FileNotFoundError
        When the file does not exist.
    IngestError
        When a required column is missing.
    """
    p = Path(path)
    if not p.is_file():
        raise FileNotFoundError(f"RSSI log {p} not found")
    report = FileReport(path=str(p), format="rssi-csv")
    out: dict[str, list[Any]] = {k: [] for k in ("t", "anchor_id", "node_id", "rssi_dbm", "snr_db")}
    last_t: dict[str, float] = {}
    checked = False
    for lineno, header, fields in _rows(p, report):
        if not checked:
            _check_header(p, header, RSSI_REQUIRED, RSSI_OPTIONAL, report)
            checked = True
        line = ",".join(fields)
        if len(fields) < len(header):
            report.skip(SkipReason.TRUNCATED, lineno, line)
            continue
        if len(fields) > len(header):
            report.skip(SkipReason.MALFORMED, lineno, line)
            continue
        rec = dict(zip(header, fields, strict=True))
        try:
            t = _float(rec["t"])
            r = _float(rec["rssi_dbm"])
            snr = _float(rec["snr_db"]) if "snr_db" in rec else math.nan
        except ValueError:
            report.skip(SkipReason.MALFORMED, lineno, line)
            continue
        aid, nid = rec["anchor_id"], rec["node_id"]
        if not aid or not nid:
            report.skip(SkipReason.MALFORMED, lineno, line)
            continue
        if not (math.isfinite(t) and math.isfinite(r)):
            report.skip(SkipReason.NAN_FIELD, lineno, line)
            continue
        if not RSSI_MIN_DBM <= r <= RSSI_MAX_DBM:
            report.skip(SkipReason.OUT_OF_RANGE, lineno, line)
            continue
        prev = last_t.get(aid)
        if prev is not None and t < prev:
            report.skip(SkipReason.NON_MONOTONIC, lineno, line)
            continue
        last_t[aid] = t
        for k, v in zip(out, (t, aid, nid, r, snr), strict=True):
            out[k].append(v)
        report.record("rssi report")
    return pd.DataFrame(out), report


def local_frame_for(tracks: pd.DataFrame) -> LocalFrame:
    """A local NED frame at the median anchor position (degrees, m)."""
    return LocalFrame(
        float(np.median(tracks["lat"])), float(np.median(tracks["lon"])), float(np.median(tracks["height"]))
    )


def error_ellipse(
    std_north: float, std_east: float, cov_ne: float, probability: float = 0.95
) -> tuple[float, float, float]:
    """Semi-axes (m) and orientation (degrees from north towards east) of a 2-D confidence ellipse."""
    P = np.array([[std_north**2, cov_ne], [cov_ne, std_east**2]])
    if not np.all(np.isfinite(P)):
        return math.nan, math.nan, math.nan
    w, V = np.linalg.eigh(P)
    k = math.sqrt(-2.0 * math.log(1.0 - probability))  # chi-square 2 dof quantile, square root
    major = V[:, 1]
    return (
        k * math.sqrt(max(w[1], 0.0)),
        k * math.sqrt(max(w[0], 0.0)),
        math.degrees(math.atan2(major[1], major[0])) % 180.0,
    )


def positions_to_geodetic(positions: pd.DataFrame, frame: LocalFrame, node_down_m: float) -> pd.DataFrame:
    """Add ``lat, lon, height`` (degrees, m) and the 95 % ellipse to a positions table."""
    df = positions.copy()
    ned = np.column_stack(
        [df["north"].to_numpy(float), df["east"].to_numpy(float), np.full(len(df), node_down_m)]
    )
    lat, lon, h = frame.from_ned(ned)
    df.insert(1, "lat", lat)
    df.insert(2, "lon", lon)
    df.insert(3, "height", h)
    ell = [
        error_ellipse(a, b, c)
        for a, b, c in zip(
            df["std_north"].astype(float),
            df["std_east"].astype(float),
            df["cov_ne"].astype(float),
            strict=True,
        )
    ]
    df["semi_major_95_m"] = [e[0] for e in ell]
    df["semi_minor_95_m"] = [e[1] for e in ell]
    df["orientation_deg"] = [e[2] for e in ell]
    return df


def write_positions_csv(positions: pd.DataFrame, path: str | os.PathLike[str]) -> Path:
    """Write a positions table as CSV (``lat``/``lon`` with 9 decimals, metres with 3)."""
    p = Path(path)
    p.parent.mkdir(parents=True, exist_ok=True)
    positions.to_csv(p, index=False, float_format="%.9g")
    return p


def _json_value(v: Any) -> Any:
    if isinstance(v, float | np.floating):
        return None if not math.isfinite(float(v)) else float(v)
    if isinstance(v, np.integer):
        return int(v)
    if isinstance(v, np.bool_):
        return bool(v)
    return v


def write_positions_geojson(positions: pd.DataFrame, path: str | os.PathLike[str]) -> Path:
    """Write a geodetic positions table as a GeoJSON FeatureCollection of points.

    Nodes without a position get a ``null`` geometry; every column is a property (NaN as
    ``null``), so the uncertainty (``std_north``, ``std_east``, ``semi_major_95_m`` ...) and the
    ``status`` travel with each point.
    """
    feats = []
    for rec in positions.to_dict(orient="records"):
        lat, lon = rec.get("lat"), rec.get("lon")
        geom = None
        if lat is not None and lon is not None and math.isfinite(float(lat)) and math.isfinite(float(lon)):
            geom = {"type": "Point", "coordinates": [round(float(lon), 9), round(float(lat), 9)]}
        props = {k: _json_value(v) for k, v in rec.items()}
        feats.append({"type": "Feature", "geometry": geom, "properties": props})
    p = Path(path)
    p.parent.mkdir(parents=True, exist_ok=True)
    p.write_text(json.dumps({"type": "FeatureCollection", "features": feats}, indent=1))
    return p


def write_rssi_csv(rssi: pd.DataFrame, path: str | os.PathLike[str]) -> Path:
    """Write reports as ``t,anchor_id,node_id,rssi_dbm,snr_db``."""
    p = Path(path)
    p.parent.mkdir(parents=True, exist_ok=True)
    cols = [c for c in ("t", "anchor_id", "node_id", "rssi_dbm", "snr_db") if c in rssi]
    rssi[cols].to_csv(p, index=False, float_format="%.6g")
    return p


def write_anchor_tracks(tracks_geo: pd.DataFrame, directory: str | os.PathLike[str]) -> list[Path]:
    """Write one ``DIR/<anchor_id>/track.csv`` per anchor (``t,lat,lon,height,std_north,std_east``),
    the layout of ``iotnav run`` outputs, so the directory name carries the anchor id."""
    d = Path(directory)
    paths = []
    for aid, tr in tracks_geo.groupby("anchor_id", sort=True):
        p = d / str(aid) / "track.csv"
        p.parent.mkdir(parents=True, exist_ok=True)
        tr[["t", "lat", "lon", "height", "std_north", "std_east"]].to_csv(
            p, index=False, float_format="%.10g"
        )
        paths.append(p)
    return paths
