"""Reader for absolute fixes: positions (and attitudes) from image-based positioning.

In the system of Dabove et al. (2016) an image taken by the phone is localised in the cloud
(image-recognition based positioning, IRB): the answer -- a position and attitude valid at the
time the image was taken -- arrives later, and the INS bridges the latency. The ``absfix``
engine consumes such answers from this file format.

Input
-----
A text file, either CSV with a header line or JSON lines (one object per line). ``#`` lines and
blank lines are ignored (and counted). Columns / keys:

==========================  =========  =================================================
name                        required   meaning
==========================  =========  =================================================
``t_valid``                 yes        time the fix refers to (image exposure), s
``t_arrival``               yes        time the fix became available (>= ``t_valid``), s
``lat``, ``lon``            one form   geodetic latitude / longitude, degrees (WGS84)
``height``                  with lat   ellipsoidal height, m
``north``, ``east``,        or this    position in the local NED frame ``n``, m
``down``                    form
``roll``, ``pitch``,        no         attitude of ``b`` in ``n`` (ZYX Euler), rad; all
``yaw``                                three or none (``roll_deg`` ... in degrees instead)
``sigma_pos_m``             no         1-sigma position accuracy per axis, m
                                       (default :data:`DEFAULT_SIGMA_POS_M`)
``sigma_att_rad``           no         1-sigma attitude accuracy per angle, rad
                                       (default :data:`DEFAULT_SIGMA_ATT_RAD`;
                                       ``sigma_att_deg`` in degrees instead)
==========================  =========  =================================================

The aliases ``lat_deg``, ``lon_deg``, ``height_m``, ``north_m``, ``east_m``, ``down_m`` are
accepted. Times share the device clock of the IMU log they go with.

Output schema (:data:`FIX_COLUMNS`), one row per accepted fix, in file order
---------------------------------------------------------------------------------
``t_valid``, ``t_arrival`` (s); ``lat_deg``, ``lon_deg``, ``height_m`` (NaN for NED files);
``north_m``, ``east_m``, ``down_m`` (NaN for geodetic files); ``roll``, ``pitch``, ``yaw`` (rad,
yaw in [-pi, 2 pi], NaN without attitude); ``sigma_pos_m`` (m); ``sigma_att_rad`` (rad, NaN
without attitude); ``has_attitude`` (bool).

Bad rows are skipped and counted in the :class:`~iotnav.io.report.FileReport` by reason: NaN or
empty required fields (``NaN field``), ``t_arrival < t_valid``, out-of-range latitude, longitude,
angles or non-positive sigmas (``out-of-range value``), lines with fewer fields than the header or
cut-off JSON (``truncated``), unparseable values or extra fields (``malformed fields``), and
JSON keys that are not in the table above (``unknown column``). A CSV header with an unknown
column, or a file with neither a fixes header nor any fix object, raises
:class:`~iotnav.io.errors.IngestError`.

Reference: P. Dabove, G. Ghinamo, A. M. Lingua, "Inertial sensors for smartphones navigation",
SpringerPlus 4:834, 2015 (cited in this project as Dabove et al. 2016): IRB gives position and
attitude with "about 30 cm of uncertainty".
"""

from __future__ import annotations

import csv
import json
import math
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal

import numpy as np
import pandas as pd

from iotnav.io.errors import IngestError
from iotnav.io.report import FileReport, SkipReason
from iotnav.io.schema import coerce

#: Default 1-sigma position accuracy, m: the ~30 cm of image-based positioning (Dabove et al.).
DEFAULT_SIGMA_POS_M = 0.30
#: Default 1-sigma attitude accuracy, rad (1 degree; an iotnav assumption, the paper gives none).
DEFAULT_SIGMA_ATT_RAD = math.radians(1.0)

#: Output schema of :func:`read_fixes`.
FIX_COLUMNS: dict[str, str] = {
    "t_valid": "float64",
    "t_arrival": "float64",
    "lat_deg": "float64",
    "lon_deg": "float64",
    "height_m": "float64",
    "north_m": "float64",
    "east_m": "float64",
    "down_m": "float64",
    "roll": "float64",
    "pitch": "float64",
    "yaw": "float64",
    "sigma_pos_m": "float64",
    "sigma_att_rad": "float64",
    "has_attitude": "bool",
}

#: Skip reasons specific to fixes (the rest are :class:`SkipReason` values).
ARRIVAL_BEFORE_VALID = "t_arrival < t_valid"
UNKNOWN_COLUMN = "unknown column"

PositionFrame = Literal["geodetic", "ned"]

# input name -> (canonical name, factor to SI / output unit)
_ALIASES: dict[str, tuple[str, float]] = {
    "t_valid": ("t_valid", 1.0),
    "t_arrival": ("t_arrival", 1.0),
    "lat": ("lat_deg", 1.0),
    "lat_deg": ("lat_deg", 1.0),
    "lon": ("lon_deg", 1.0),
    "lon_deg": ("lon_deg", 1.0),
    "height": ("height_m", 1.0),
    "height_m": ("height_m", 1.0),
    "north": ("north_m", 1.0),
    "north_m": ("north_m", 1.0),
    "east": ("east_m", 1.0),
    "east_m": ("east_m", 1.0),
    "down": ("down_m", 1.0),
    "down_m": ("down_m", 1.0),
    "roll": ("roll", 1.0),
    "pitch": ("pitch", 1.0),
    "yaw": ("yaw", 1.0),
    "roll_deg": ("roll", math.pi / 180.0),
    "pitch_deg": ("pitch", math.pi / 180.0),
    "yaw_deg": ("yaw", math.pi / 180.0),
    "sigma_pos_m": ("sigma_pos_m", 1.0),
    "sigma_att_rad": ("sigma_att_rad", 1.0),
    "sigma_att_deg": ("sigma_att_rad", math.pi / 180.0),
}
_GEODETIC = ("lat_deg", "lon_deg", "height_m")
_NED = ("north_m", "east_m", "down_m")
_ATT = ("roll", "pitch", "yaw")
_EPS = 1e-9


@dataclass
class Fixes:
    """What :func:`read_fixes` returns.

    Attributes
    ----------
    table : pandas.DataFrame
        Accepted fixes in the :data:`FIX_COLUMNS` schema.
    position_frame : {"geodetic", "ned"}
        Which position columns are filled.
    report : FileReport
        Lines read, ignored and skipped by reason.
    """

    table: pd.DataFrame
    position_frame: PositionFrame
    report: FileReport


class _Bad(Exception):
    """A row is unusable; carries the skip reason."""

    def __init__(self, reason: str) -> None:
        super().__init__(reason)
        self.reason = reason


def _canonical(names: list[str]) -> tuple[dict[str, str], list[str]]:
    """Map input names to canonical ones; return the mapping and the unknown names."""
    mapping = {n: _ALIASES[n][0] for n in names if n in _ALIASES}
    unknown = [n for n in names if n not in _ALIASES]
    return mapping, unknown


def _frame_of(canon: set[str]) -> PositionFrame | None:
    has_geo = bool(canon & {"lat_deg", "lon_deg"})
    has_ned = bool(canon & {"north_m", "east_m"})
    if has_geo and has_ned:
        raise _Bad(str(SkipReason.MALFORMED))
    if has_geo:
        return "geodetic"
    if has_ned:
        return "ned"
    return None


def _to_float(value: Any) -> float:
    """A field value as float; NaN for empty/None; :class:`_Bad` when not a number."""
    if value is None:
        return math.nan
    if isinstance(value, bool):
        raise _Bad(str(SkipReason.MALFORMED))
    if isinstance(value, (int, float)):
        return float(value)
    if isinstance(value, str):
        text = value.strip()
        if text == "":
            return math.nan
        try:
            return float(text)
        except ValueError:
            raise _Bad(str(SkipReason.MALFORMED)) from None
    raise _Bad(str(SkipReason.MALFORMED))


def _build_row(values: dict[str, Any], frame: PositionFrame) -> dict[str, Any]:
    """Validate one row given as ``{input name: raw value}``; return output columns."""
    row: dict[str, Any] = {}
    for name, raw in values.items():
        canon, factor = _ALIASES[name]
        row[canon] = _to_float(raw) * factor
    pos = _GEODETIC if frame == "geodetic" else _NED
    for key in ("t_valid", "t_arrival", *pos):
        if key not in row:
            raise _Bad(str(SkipReason.MALFORMED))
        if not math.isfinite(row[key]):
            raise _Bad(str(SkipReason.NAN_FIELD))
    other = _NED if frame == "geodetic" else _GEODETIC
    if any(math.isfinite(row.get(k, math.nan)) for k in other):
        raise _Bad(str(SkipReason.MALFORMED))
    if row["t_arrival"] < row["t_valid"]:
        raise _Bad(ARRIVAL_BEFORE_VALID)
    if frame == "geodetic" and not (-90.0 <= row["lat_deg"] <= 90.0 and -180.0 <= row["lon_deg"] <= 180.0):
        raise _Bad(str(SkipReason.OUT_OF_RANGE))
    att = [row.get(k, math.nan) for k in _ATT]
    n_att = sum(math.isfinite(a) for a in att)
    if n_att not in (0, 3):
        raise _Bad(str(SkipReason.NAN_FIELD))
    has_att = n_att == 3
    if has_att:
        roll, pitch, yaw = att
        pi = math.pi
        if not (-pi - _EPS <= roll <= pi + _EPS and -pi / 2 - _EPS <= pitch <= pi / 2 + _EPS):
            raise _Bad(str(SkipReason.OUT_OF_RANGE))
        if not -pi - _EPS <= yaw <= 2 * pi + _EPS:
            raise _Bad(str(SkipReason.OUT_OF_RANGE))
    sp = row.get("sigma_pos_m", math.nan)
    sp = DEFAULT_SIGMA_POS_M if math.isnan(sp) else sp
    sa = row.get("sigma_att_rad", math.nan)
    sa = DEFAULT_SIGMA_ATT_RAD if math.isnan(sa) else sa
    if not (math.isfinite(sp) and sp > 0.0 and math.isfinite(sa) and sa > 0.0):
        raise _Bad(str(SkipReason.OUT_OF_RANGE))
    out = {k: row.get(k, math.nan) for k in FIX_COLUMNS if k != "has_attitude"}
    out["sigma_pos_m"] = sp
    out["sigma_att_rad"] = sa if has_att else math.nan
    if not has_att:
        out.update(roll=math.nan, pitch=math.nan, yaw=math.nan)
    out["has_attitude"] = has_att
    return out


def _read_text(p: Path) -> list[str]:
    raw = p.read_bytes()
    if not raw.strip():
        raise IngestError(
            str(p), "the file is empty; expected absolute fixes (CSV with a header or JSON lines)"
        )
    if b"\x00" in raw[:65536]:
        raise IngestError(str(p), "binary data; expected absolute fixes as CSV or JSON lines text")
    try:
        text = raw.decode("utf-8")
    except UnicodeDecodeError:
        raise IngestError(str(p), "not UTF-8 text; expected absolute fixes as CSV or JSON lines") from None
    return text.splitlines()


def read_fixes(path: str | os.PathLike[str]) -> Fixes:
    """Read an absolute-fix file (CSV with a header, or JSON lines); see the module docstring.

    Parameters
    ----------
    path : path-like
        The file.

    Returns
    -------
    Fixes
        The table (:data:`FIX_COLUMNS`), its position frame and the ingest report.

    Raises
    ------
    IngestError
        When the file is not a fixes file (no header naming ``t_valid``, ``t_arrival`` and a
        position, no JSON fix object), or its CSV header has unknown or conflicting columns.
    FileNotFoundError
        When the file does not exist.
    """
    p = Path(path)
    if not p.is_file():
        raise FileNotFoundError(f"{p}: no such file")
    lines = _read_text(p)
    first = next((ln.strip() for ln in lines if ln.strip() and not ln.lstrip().startswith("#")), "")
    if first.startswith("{"):
        return _read_jsonl(p, lines)
    return _read_csv(p, lines)


def _finish(p: Path, rows: list[dict[str, Any]], frame: PositionFrame, report: FileReport) -> Fixes:
    table = coerce(pd.DataFrame(rows, columns=list(FIX_COLUMNS)), FIX_COLUMNS)
    if len(table) > 1 and np.any(np.diff(table["t_arrival"].to_numpy()) < 0):
        report.notes.append("t_arrival is not in increasing order in the file (kept in file order)")
    report.notes.append(f"positions are {'WGS84 lat/lon/height' if frame == 'geodetic' else 'local NED'}")
    return Fixes(table=table, position_frame=frame, report=report)


def _read_csv(p: Path, lines: list[str]) -> Fixes:
    report = FileReport(path=str(p), format="fixes-csv")
    header: list[str] | None = None
    mapping: dict[str, str] = {}
    frame: PositionFrame | None = None
    rows: list[dict[str, Any]] = []
    for lineno, line in enumerate(lines, start=1):
        report.units += 1
        stripped = line.strip()
        if not stripped:
            report.ignore("blank line")
            continue
        if stripped.startswith("#"):
            report.ignore("comment")
            continue
        fields_ = [f.strip() for f in next(csv.reader([stripped]))]
        if header is None:
            names = [f.lower() for f in fields_]
            mapping, unknown = _canonical(names)
            canon = set(mapping.values())
            if not {"t_valid", "t_arrival"} <= canon:
                raise IngestError(
                    str(p),
                    f"line {lineno}: not an absolute-fix header; expected CSV columns t_valid,t_arrival,"
                    "lat,lon,height (or north,east,down)[,roll,pitch,yaw][,sigma_pos_m,sigma_att_rad] "
                    "or JSON lines",
                )
            if unknown:
                raise IngestError(
                    str(p),
                    f"line {lineno}: unknown column(s) {', '.join(unknown)}; accepted: {', '.join(_ALIASES)}",
                )
            if len(set(names)) != len(names) or len(canon) != len(names):
                raise IngestError(str(p), f"line {lineno}: a column is given twice (directly or by alias)")
            try:
                frame = _frame_of(canon)
            except _Bad:
                raise IngestError(
                    str(p), f"line {lineno}: give either lat/lon/height or north/east/down"
                ) from None
            if frame is None:
                raise IngestError(
                    str(p), f"line {lineno}: no position columns (lat,lon,height or north,east,down)"
                )
            need = _GEODETIC if frame == "geodetic" else _NED
            missing = [k for k in need if k not in canon]
            if missing:
                raise IngestError(str(p), f"line {lineno}: missing column(s) {', '.join(missing)}")
            att = canon & set(_ATT)
            if att and att != set(_ATT):
                raise IngestError(str(p), f"line {lineno}: give all of roll, pitch, yaw or none")
            header = names
            report.ignore("header")
            continue
        if len(fields_) < len(header):
            report.skip(SkipReason.TRUNCATED, lineno, line)
            continue
        if len(fields_) > len(header):
            report.skip(SkipReason.MALFORMED, lineno, line)
            continue
        assert frame is not None
        try:
            rows.append(_build_row(dict(zip(header, fields_, strict=True)), frame))
        except _Bad as bad:
            report.skip(bad.reason, lineno, line)
            continue
        report.record("fix")
    if header is None or frame is None:
        raise IngestError(
            str(p), "no header line; expected absolute fixes as CSV with a header or JSON lines"
        )
    return _finish(p, rows, frame, report)


def _read_jsonl(p: Path, lines: list[str]) -> Fixes:
    report = FileReport(path=str(p), format="fixes-jsonl")
    frame: PositionFrame | None = None
    rows: list[dict[str, Any]] = []
    seen_object = False
    for lineno, line in enumerate(lines, start=1):
        report.units += 1
        stripped = line.strip()
        if not stripped:
            report.ignore("blank line")
            continue
        if stripped.startswith("#"):
            report.ignore("comment")
            continue
        try:
            obj = json.loads(stripped)
        except json.JSONDecodeError:
            cut = stripped.startswith("{") and not stripped.endswith("}")
            report.skip(SkipReason.TRUNCATED if cut else SkipReason.MALFORMED, lineno, line)
            continue
        if not isinstance(obj, dict):
            report.skip(SkipReason.MALFORMED, lineno, line)
            continue
        names = [str(k).lower() for k in obj]
        if "t_valid" in names:
            seen_object = True
        mapping, unknown = _canonical(names)
        if unknown:
            report.skip(UNKNOWN_COLUMN, lineno, line)
            continue
        if len(set(mapping.values())) != len(names):
            report.skip(SkipReason.MALFORMED, lineno, line)
            continue
        values = {str(k).lower(): v for k, v in obj.items()}
        try:
            row_frame = _frame_of(set(mapping.values()))
            if row_frame is None:
                raise _Bad(str(SkipReason.MALFORMED))
            if frame is None:
                frame = row_frame
            elif row_frame != frame:
                raise _Bad(str(SkipReason.MALFORMED))
            rows.append(_build_row(values, frame))
        except _Bad as bad:
            report.skip(bad.reason, lineno, line)
            continue
        report.record("fix")
    if not seen_object:
        raise IngestError(
            str(p), "no JSON object with t_valid; expected absolute fixes as JSON lines or CSV with a header"
        )
    return _finish(p, rows, frame or "geodetic", report)
