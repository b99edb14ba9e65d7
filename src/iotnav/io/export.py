"""Write tables (CSV, Parquet) and tracks (GeoJSON, GPX 1.1, KML), vectorised.

Tables: :func:`write_csv` writes what ``DataFrame.to_csv(index=False, float_format="%.10g")``
writes (floats to 10 significant digits, NaN as an empty field, ``True``/``False``, categories
by name) through pyarrow's CSV writer, about ten times faster; :func:`write_parquet` keeps
every bit and the column types.

Tracks: column names are looked up in this order: time ``utc`` (UTC Unix s) then ``t``;
latitude ``lat`` then ``lat_deg``; longitude ``lon`` then ``lon_deg``; height ``height``
then ``height_m`` (optional). Rows with a non-finite latitude or longitude are left out and
counted. GPX and KML carry UTC times only when a UTC time is known (a ``utc`` column or a
given ``utc_offset_s``), since both formats define their timestamps as UTC. A track can be
thinned to one point per ``1 / rate_hz`` seconds (:func:`decimate`); the points left out are
counted too.
"""

from __future__ import annotations

import csv
import io
import json
import math
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Any
from xml.sax.saxutils import escape

import numpy as np
import numpy.typing as npt
import pandas as pd
import pyarrow as pa
import pyarrow.compute as pc
import pyarrow.csv as pa_csv

from iotnav.io._floattext import ten_digit_text

FORMATS = ("csv", "parquet", "geojson", "gpx", "kml")

#: Points per second of the map files (GeoJSON, GPX) ``iotnav run`` writes by default: the 1 Hz
#: navigation rate of the GNSS modules of IoT trackers (u-blox M8/M10 and Quectel L76 ship
#: with a 1 s measurement period), so the map has the receiver's density, not the IMU's.
MAP_RATE_HZ = 1.0

FloatArray = npt.NDArray[np.float64]

#: Float columns :func:`write_csv` writes in full: times (device ``t``, ``utc``), whose Unix
#: seconds need 13 digits for milliseconds.
TIME_COLUMNS = ("t", "utc")


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
    decimated : int
        Rows with a position left out by the decimation (``rate_hz``).
    """

    path: Path
    format: str
    points: int
    skipped: int
    decimated: int = 0


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


def iso_times(utc: FloatArray) -> list[str | None]:
    """ISO 8601 UTC times to the millisecond (``2025-08-28T17:30:21.750Z``); None where not finite.

    The same text as ``datetime.fromtimestamp(u, UTC)`` truncated to milliseconds: rounded to
    the microsecond (half to even), then truncated.
    """
    utc = np.asarray(utc, dtype=float)
    ok = np.isfinite(utc) & (np.abs(utc) < 1.0e11)  # datetime64[ms] and datetime both cover this
    ms = np.floor_divide(np.round(np.where(ok, utc, 0.0) * 1.0e6).astype(np.int64), 1000)
    text = np.char.add(np.datetime_as_string(ms.astype("datetime64[ms]"), unit="ms"), "Z")
    return [s if k else None for s, k in zip(text.tolist(), ok.tolist(), strict=True)]


def _utc_series(df: pd.DataFrame, tcol: str | None, utc_offset_s: float | None) -> np.ndarray | None:
    if tcol == "utc":
        return df["utc"].to_numpy(dtype=float)
    if tcol == "t" and utc_offset_s is not None and math.isfinite(utc_offset_s):
        return df["t"].to_numpy(dtype=float) + utc_offset_s
    return None


def guess_format(path: str | os.PathLike[str]) -> str:
    """Export format from a file extension (``.csv``, ``.parquet``, ``.geojson``/``.json``, ``.gpx``, ``.kml``)."""
    ext = Path(path).suffix.lower().lstrip(".")
    if ext == "json":
        ext = "geojson"
    if ext not in FORMATS:
        raise ValueError(f"{path}: unknown export format {ext!r}; expected one of {', '.join(FORMATS)}")
    return ext


# ---------------------------------------------------------------------------------------------
# numbers as text, a column at a time


def _near_tie(scaled: FloatArray) -> npt.NDArray[np.bool_]:
    """Where a scaled value is too close to ``k + 0.5`` for its rounding to be sure."""
    return np.abs(scaled - np.floor(scaled) - 0.5) < 1.0e-6


def round_significant(x: npt.ArrayLike, digits: int = 10) -> FloatArray:
    """``x`` rounded to ``digits`` significant decimal digits, as the nearest doubles.

    Written with the shortest repr that reads back to the same double, the result has the
    digits ``"%.{digits}g" % x`` prints: the decimal ``k / 10^m`` is one exact division of an
    integer by an exact power of ten. Values near a rounding tie, and values whose power of
    ten is beyond ``1e22``, go through ``"%.{digits}g"`` itself. NaN, inf and zero pass through.
    """
    out = np.array(x, dtype=float, copy=True)
    ok = np.isfinite(out) & (out != 0.0)
    v = out[ok]
    k = (digits - 1) - np.floor(np.log10(np.abs(v))).astype(np.int64)
    r = v.copy()
    slow = (k > 22) | (k < -22)
    up = (k >= 0) & ~slow
    scale = 10.0 ** k[up]
    scaled = v[up] * scale
    r[up] = np.round(scaled) / scale
    slow[np.flatnonzero(up)[_near_tie(scaled)]] = True
    down = (k < 0) & ~slow
    scale = 10.0 ** (-k[down])
    scaled = v[down] / scale
    r[down] = np.round(scaled) * scale
    slow[np.flatnonzero(down)[_near_tie(scaled)]] = True
    for i in np.flatnonzero(slow):
        r[i] = float(f"{v[i]:.{digits}g}")
    out[ok] = r
    return out


def _shortest(x: FloatArray) -> pa.Array:
    """Finite floats as their shortest round-trip text (JSON numbers)."""
    return pc.cast(pa.array(np.asarray(x, dtype=float)), pa.string())


def _fixed_arrow(x: FloatArray, decimals: int) -> tuple[pa.Array, npt.NDArray[np.bool_]]:
    """The fast part of :func:`_fixed` as a pyarrow array, and where it is not to be trusted."""
    x = np.asarray(x, dtype=float)
    ax = np.abs(x)
    fast = np.isfinite(ax) & (ax < 2.0**52)
    ax = np.where(fast, ax, 0.0)
    whole = np.floor(ax)
    scaled = (ax - whole) * 10.0**decimals  # the fraction is exact; one rounding here
    fast &= ~_near_tie(scaled)
    unit = 10**decimals
    n = np.round(scaled).astype(np.int64)
    w = whole.astype(np.int64) + n // unit
    w_text = pc.cast(pa.array(w), pa.string())
    frac = pc.utf8_lpad(pc.cast(pa.array(n % unit), pa.string()), width=decimals, padding="0")
    sign = pa.array(np.where(np.signbit(x), "-", ""))
    return pc.binary_join_element_wise(sign, w_text, ".", frac, ""), ~fast


def _fixed(x: FloatArray, decimals: int) -> list[str]:
    """``f"{v:.{decimals}f}"`` for every value, vectorised (near ties and huge values via Python)."""
    x = np.asarray(x, dtype=float)
    arr, slow = _fixed_arrow(x, decimals)
    text: list[str] = arr.to_pylist()
    for i in np.flatnonzero(slow):
        text[i] = f"{x[i]:.{decimals}f}"
    return text


def _fixed_column(x: FloatArray, decimals: int) -> pa.Array:
    """``"%.{decimals}f" % v`` for every value as a pyarrow string array, NaN a null."""
    x = np.asarray(x, dtype=float)
    arr, slow = _fixed_arrow(x, decimals)
    nan = np.isnan(x)
    slow &= ~nan
    if slow.any():
        text: list[str | None] = arr.to_pylist()
        for i in np.flatnonzero(slow):
            text[i] = f"{x[i]:.{decimals}f}"
        arr = pa.array(text, pa.string())
    if nan.any():
        arr = pc.if_else(pa.array(nan), pa.scalar(None, pa.string()), arr)
    return arr


# ---------------------------------------------------------------------------------------------
# tables


def _arrow_column(s: pd.Series, digits: int | None) -> pa.Array | None:
    """A column as pyarrow writes it the way pandas' ``to_csv`` would; None when it cannot.

    Floats are rounded to ``digits`` significant digits, or kept in full when None.
    """
    dt = s.dtype
    if isinstance(dt, pd.CategoricalDtype):
        cats = s.cat.categories
        if pd.api.types.infer_dtype(cats, skipna=False) != "string":
            return None
        codes = s.cat.codes.to_numpy()
        return pa.DictionaryArray.from_arrays(
            pa.array(codes, mask=codes < 0), pa.array(np.asarray(cats, dtype=object), pa.string())
        )
    if dt == np.bool_:
        return pa.DictionaryArray.from_arrays(
            pa.array(s.to_numpy().astype(np.int8)), pa.array(["False", "True"])
        )
    if dt.kind == "f":
        v = s.to_numpy(dtype=float)
        if digits is None:
            return pa.array(v, from_pandas=True)
        r = round_significant(v, digits)
        text = ten_digit_text(r) if digits == 10 else None  # compiled, the same bytes
        return text if text is not None else pa.array(r, from_pandas=True)
    if dt.kind in "iu":
        return pa.array(s.to_numpy())
    if dt.kind == "O" and pd.api.types.infer_dtype(s, skipna=True) in ("string", "empty"):
        return pa.array(s.to_numpy(), pa.string(), from_pandas=True)
    return None


def _write_arrow_csv(out: Path, names: list[str], arrays: list[Any]) -> bool:
    """Write a header of ``names`` and the columns ``arrays`` unquoted through pyarrow.

    Returns False (the file then to be written another way) when a field would need quotes.
    """
    header = io.StringIO()
    csv.writer(header, lineterminator="\n").writerow(names)
    table = pa.table({f"c{i}": a for i, a in enumerate(arrays)})
    try:
        with out.open("wb") as f:
            f.write(header.getvalue().encode())
            if len(table):
                pa_csv.write_csv(table, f, pa_csv.WriteOptions(include_header=False, quoting_style="none"))
    except pa.ArrowInvalid:
        return False
    return True


def write_csv(
    df: pd.DataFrame,
    path: str | os.PathLike[str],
    significant_digits: int = 10,
    exact: tuple[str, ...] = TIME_COLUMNS,
) -> None:
    """Write ``df`` (no index) as ``df.to_csv(index=False, float_format="%.10g")`` would, fast.

    Floats are rounded to ``significant_digits`` (:func:`round_significant`), NaN is an empty
    field, booleans ``True``/``False``, categories their names. The float columns named in
    ``exact`` (the time columns) are written in full (shortest round-trip text), since ten
    digits of a Unix time (1.7e9 s) would round it to whole seconds. A table pyarrow cannot
    write unquoted (a text field holding a comma, quote or line break; an exotic dtype) goes
    through pandas, with the same result.
    """
    cols = {str(c): _arrow_column(df[c], None if c in exact else significant_digits) for c in df.columns}
    out = Path(path)
    arrays = list(cols.values())
    if df.columns.is_unique and all(a is not None for a in arrays):
        if _write_arrow_csv(out, list(cols), arrays):  # else a field needs quotes: pandas quotes it
            return
    full = {
        c: df[c].map(lambda v: repr(float(v))) for c in exact if c in df.columns and df[c].dtype.kind == "f"
    }
    df.assign(**{c: v.where(df[c].notna(), "") for c, v in full.items()}).to_csv(
        out, index=False, float_format=f"%.{significant_digits}g"
    )


def write_fixed_csv(df: pd.DataFrame, path: str | os.PathLike[str], decimals: int) -> None:
    """Write ``df`` (no index) as ``df.to_csv(index=False, float_format=f"%.{decimals}f", na_rep="",
    lineterminator="\n")`` would, through pyarrow (the simulator's long logs).

    Floats with ``decimals`` digits after the point, NaN an empty field, integers as they are,
    booleans ``True``/``False``. A table pyarrow cannot write the same way (another dtype, a
    text field needing quotes) goes through pandas itself.
    """
    out = Path(path)
    cols: list[pa.Array] = []
    for c in df.columns:
        s = df[c]
        if s.dtype.kind == "f":
            cols.append(_fixed_column(s.to_numpy(dtype=float), decimals))
        elif s.dtype.kind in "iu":
            cols.append(pa.array(s.to_numpy()))
        elif s.dtype == np.bool_:
            cols.append(
                pa.DictionaryArray.from_arrays(
                    pa.array(s.to_numpy().astype(np.int8)), pa.array(["False", "True"])
                )
            )
        else:
            break
    else:
        if df.columns.is_unique and _write_arrow_csv(out, [str(c) for c in df.columns], cols):
            return
    df.to_csv(out, index=False, float_format=f"%.{decimals}f", na_rep="", lineterminator="\n")


def write_parquet(df: pd.DataFrame, path: str | os.PathLike[str]) -> None:
    """Write ``df`` (no index) as Parquet (pyarrow, zstd): every bit and the column types kept."""
    df.to_parquet(path, index=False, engine="pyarrow", compression="zstd")


def write_table(df: pd.DataFrame, path: str | os.PathLike[str]) -> None:
    """:func:`write_csv` or :func:`write_parquet`, from the extension (``.csv`` / ``.parquet``)."""
    fmt = guess_format(path)
    if fmt == "csv":
        write_csv(df, path)
    elif fmt == "parquet":
        write_parquet(df, path)
    else:
        raise ValueError(f"{path}: a table is written as .csv or .parquet, not .{fmt}")


def read_table(path: str | os.PathLike[str]) -> pd.DataFrame:
    """Read what :func:`write_table` wrote (``.parquet``; anything else as CSV)."""
    if Path(path).suffix.lower() == ".parquet":
        return pd.read_parquet(path)
    return pd.read_csv(path)


# ---------------------------------------------------------------------------------------------
# tracks


def decimate(t: FloatArray, rate_hz: float) -> npt.NDArray[np.intp]:
    """Indices of one row per ``1 / rate_hz`` seconds: the first of each interval, and the last row.

    Intervals are counted from the first time; rows with a non-finite time are kept (they are
    not this function's to judge). ``rate_hz <= 0`` or NaN keeps every row.
    """
    t = np.asarray(t, dtype=float)
    if not (rate_hz > 0) or t.size == 0:
        return np.arange(t.size)
    ok = np.isfinite(t)
    keep = ~ok
    if ok.any():
        tk = t[ok]
        bins = np.floor((tk - tk.min()) * rate_hz)
        first = np.unique(bins, return_index=True)[1]
        sel = np.zeros(tk.size, bool)
        sel[first] = True
        sel[-1] = True
        keep[np.flatnonzero(ok)[sel]] = True
    return np.flatnonzero(keep)


def nearest_rows(t: FloatArray, at: FloatArray) -> npt.NDArray[np.intp]:
    """Indices of the rows of ``t`` (s, ascending) nearest to each time of ``at`` (s), first and last row included.

    Each time of ``at`` inside ``[t[0], t[-1]]`` takes the row closest in time (the earlier one
    on a tie); times outside the track, and non-finite ones, take none. Indices are unique and
    ascending. An empty ``t`` gives none.
    """
    t = np.asarray(t, dtype=float)
    if t.size <= 1:
        return np.arange(t.size, dtype=np.intp)
    a = np.asarray(at, dtype=float)
    a = a[np.isfinite(a) & (a >= t[0]) & (a <= t[-1])]
    j = np.clip(np.searchsorted(t, a), 1, t.size - 1)  # t[j - 1] <= a <= t[j]
    j = np.where(a - t[j - 1] <= t[j] - a, j - 1, j)
    return np.unique(np.concatenate([[0, t.size - 1], j])).astype(np.intp)


def _geojson(name: str, lon: FloatArray, lat: FloatArray, h: FloatArray, utc: FloatArray | None) -> str:
    has_h = np.isfinite(h)
    height = pc.if_else(
        pa.array(has_h), pc.binary_join_element_wise(",", _shortest(np.where(has_h, h, 0.0)), ""), ""
    )
    coords = pc.binary_join_element_wise("[", _shortest(lon), ",", _shortest(lat), height, "]", "")
    props: dict[str, object] = {"name": name, "points": int(lon.size)}
    if utc is not None:
        props["times"] = "@TIMES@"
    feature = {
        "type": "Feature",
        "geometry": {"type": "LineString", "coordinates": "@COORDS@"},
        "properties": props,
    }
    text = json.dumps({"type": "FeatureCollection", "features": [feature]})
    text = text.replace('"@COORDS@"', "[" + ", ".join(coords.to_pylist()) + "]")
    if utc is not None:
        text = text.replace('"@TIMES@"', json.dumps(iso_times(utc)))
    return text


def _gpx(name: str, lon: FloatArray, lat: FloatArray, h: FloatArray, utc: FloatArray | None) -> str:
    la, lo = _fixed(lat, 9), _fixed(lon, 9)
    has_h = np.isfinite(h)
    ele = _fixed(np.where(has_h, h, 0.0), 3)
    times = iso_times(utc) if utc is not None else [None] * lat.size
    pts = [
        f'<trkpt lat="{a}" lon="{b}">'
        + (f"<ele>{e}</ele>" if k else "")
        + (f"<time>{s}</time>" if s is not None else "")
        + "</trkpt>"
        for a, b, e, k, s in zip(la, lo, ele, has_h.tolist(), times, strict=True)
    ]
    return (
        "<?xml version='1.0' encoding='utf-8'?>\n"
        '<gpx xmlns="http://www.topografix.com/GPX/1/1" version="1.1" creator="iotnav">'
        f"<trk><name>{escape(name)}</name><trkseg>{''.join(pts)}</trkseg></trk></gpx>"
    )


def _kml(name: str, lon: FloatArray, lat: FloatArray, h: FloatArray) -> str:
    # Heights are ellipsoidal while KML "absolute" means above MSL: keep them as data, clamp.
    has_h = bool(np.isfinite(h).all()) and lat.size > 0
    parts = [pa.array(_fixed(lon, 9)), ",", pa.array(_fixed(lat, 9))]
    if has_h:
        parts += [",", pa.array(_fixed(h, 3))]
    coords = " ".join(pc.binary_join_element_wise(*parts, "").to_pylist()) if lat.size else ""
    return (
        "<?xml version='1.0' encoding='utf-8'?>\n"
        '<kml xmlns="http://www.opengis.net/kml/2.2"><Document><Placemark>'
        f"<name>{escape(name)}</name><LineString><altitudeMode>clampToGround</altitudeMode>"
        f"<coordinates>{coords}</coordinates></LineString></Placemark></Document></kml>"
    )


def export_track(
    df: pd.DataFrame,
    path: str | os.PathLike[str],
    fmt: str | None = None,
    *,
    name: str = "iotnav track",
    utc_offset_s: float | None = None,
    rate_hz: float | None = None,
    at_times: FloatArray | None = None,
) -> ExportResult:
    """Write a track table to ``path``.

    Parameters
    ----------
    df : pandas.DataFrame
        Track with time, latitude (deg), longitude (deg) and optionally ellipsoidal height (m).
    path : path-like
        Output file; parent directories are created.
    fmt : str, optional
        ``csv``, ``parquet``, ``geojson``, ``gpx`` or ``kml``; from the extension when omitted.
    name : str
        Track name written into GeoJSON/GPX/KML.
    utc_offset_s : float, optional
        ``utc = t + utc_offset_s`` when the table has device time only.
    rate_hz : float, optional
        Keep one point per ``1 / rate_hz`` seconds (:func:`decimate`); every point when None
        or 0.
    at_times : array of float, optional
        Keep instead the rows nearest to these times (s, the table's time column; e.g. the
        fix times of the log), and the first and last row (:func:`nearest_rows`). Not with
        ``rate_hz``.

    Returns
    -------
    ExportResult
        Path, format, points written, rows skipped and rows left out by the decimation.

    Raises
    ------
    ValueError
        An unknown format, no latitude/longitude columns, a ``rate_hz`` or ``at_times`` without
        a time column, or both given.
    """
    fmt = fmt or guess_format(path)
    if fmt not in FORMATS:
        raise ValueError(f"unknown export format {fmt!r}; expected one of {', '.join(FORMATS)}")
    tcol, latc, lonc, hc = track_columns(df)
    lat = df[latc].to_numpy(dtype=float)
    lon = df[lonc].to_numpy(dtype=float)
    ok = np.isfinite(lat) & np.isfinite(lon)
    skipped = int((~ok).sum())
    rows = np.flatnonzero(ok)
    decimated = 0
    if rate_hz and at_times is not None:
        raise ValueError("decimate a track by rate_hz or at_times, not both")
    if rate_hz or at_times is not None:
        if tcol is None:
            raise ValueError("decimating a track (rate_hz, at_times) needs a time column (t or utc)")
        tt = df[tcol].to_numpy(dtype=float)[rows]
        if at_times is not None:
            if np.any(np.diff(tt) < 0):
                raise ValueError("at_times needs a track in time order")
            rows = rows[nearest_rows(tt, at_times)]
        else:
            rows = rows[decimate(tt, rate_hz or 0.0)]
        decimated = int(ok.sum()) - rows.size
    sub = df.iloc[rows].reset_index(drop=True) if rows.size < len(df) else df.reset_index(drop=True)
    lat, lon = lat[rows], lon[rows]
    h = sub[hc].to_numpy(dtype=float) if hc else np.full(lat.size, np.nan)
    utc = _utc_series(sub, tcol, utc_offset_s)
    out = Path(path)
    out.parent.mkdir(parents=True, exist_ok=True)
    if fmt == "csv":
        write_csv(sub, out)
    elif fmt == "parquet":
        write_parquet(sub, out)
    elif fmt == "geojson":
        out.write_text(_geojson(name, lon, lat, h, utc))
    elif fmt == "gpx":
        out.write_text(_gpx(name, lon, lat, h, utc), encoding="utf-8")
    else:
        out.write_text(_kml(name, lon, lat, h), encoding="utf-8")
    return ExportResult(out, fmt, int(lat.size), skipped, decimated)
