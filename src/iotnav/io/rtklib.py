"""RTKLIB solution files (``.pos``).

Layout
------
``%`` lines are header comments; the last ``%`` line before the data names the columns, e.g.::

    %  GPST          latitude(deg) longitude(deg)  height(m)   Q  ns   sdn(m)   sde(m)   sdu(m)
       sdne(m)  sdeu(m)  sdun(m) age(s)  ratio  vn(m/s)  ve(m/s)  vu(m/s)  sdvn  sdve  sdvu ...

Supported variants (detected from that line and from the data):

* time system ``GPST``, ``UTC`` or ``JST`` (the first label); GPST is converted to UTC with
  :func:`iotnav.io.timeutil.gpst_to_utc` (leap seconds, 18 s since 2017), JST is UTC + 9 h;
* time as ``yyyy/mm/dd hh:mm:ss.sss`` or as ``week tow`` (GPS week, seconds of week);
* position as latitude/longitude in decimal degrees (``latitude(deg)``), in degrees, minutes and
  seconds (``latitude(d'")``, three fields each, sign on the degrees), or ECEF ``x-ecef(m)
  y-ecef(m) z-ecef(m)``, converted to WGS84 geodetic with :func:`pymap3d.ecef2geodetic`;
* optional velocity: ``vn ve vu`` (ENU, m/s) or ``vx vy vz`` (ECEF, m/s, rotated to ENU at the
  epoch's position);
* a file without the column line is read as ``GPST`` + lat/lon/height (noted in the report).

Mapping to the GNSS table (:data:`iotnav.io.schema.GNSS_COLUMNS`)
-----------------------------------------------------------------
``t`` and ``utc``
    UTC seconds since 1970 (the part's clock is ``"utc"``).
``quality`` (GGA code) from RTKLIB ``Q``
    1 fix -> 4 (RTK fixed), 2 float -> 5 (RTK float), 3 SBAS -> 2 (differential),
    4 DGPS -> 2, 5 single -> 1 (autonomous GPS), 6 PPP -> 1 (GGA has no PPP code; the accuracy
    columns carry the difference), 0 -> 0, anything else -> -1. ``valid`` is ``Q in 1..6``;
    ``mode`` is 3 (RTKLIB solutions are 3D) for valid epochs and 1 otherwise.
``num_sv`` from ``ns``.
``h_acc_m`` = ``sqrt(sdn^2 + sde^2)``
    the root of the trace of the horizontal covariance (the "DRMS"), not a 1-D sigma; ``v_acc_m``
    = ``sdu``. For ECEF files the 3x3 covariance from ``sdx .. sdzx`` (RTKLIB writes the
    off-diagonals as ``sign(c) sqrt(|c|)``) is rotated to ENU first.
``vn, ve, vd``
    NED velocity: ``vd = -vu``.
``speed_mps``, ``course_rad``, ``course_valid``
    ``hypot(vn, ve)``, ``atan2(ve, vn)`` in [0, 2 pi); the course is flagged valid only when the
    horizontal speed exceeds :data:`COURSE_MIN_SPEED_MPS` (0.5 m/s): below that the direction of
    a noisy velocity is meaningless.
``s_acc_mps``
    1-sigma of the horizontal speed, ``sqrt(vn^2 sdvn^2 + ve^2 sdve^2) / speed`` (the covariance
    term ignored), or ``sqrt((sdvn^2 + sdve^2) / 2)`` at zero speed.
``alt_msl_m``, ``geoid_sep_m``, DOPs
    not in a ``.pos`` file: NaN. ``height_m`` is the ``height(m)`` column, which RTKLIB writes as
    ellipsoidal height by default (the ``out-height=geodetic`` option would make it MSL).

Bad lines are counted: a wrong number of fields is ``TRUNCATED``, a field that is not a number or a
date is ``MALFORMED``, a NaN in position ``NAN_FIELD``, an epoch not after the previous one
``NON_MONOTONIC`` (or ``DUPLICATE`` when the whole line repeats).
"""

from __future__ import annotations

import calendar
import math
import os

import numpy as np
import numpy.typing as npt
import pandas as pd
import pymap3d

from iotnav.io.errors import IngestError
from iotnav.io.imu_csv import split_lines
from iotnav.io.log import Part
from iotnav.io.report import FileReport, SkipReason
from iotnav.io.timeutil import GPS_EPOCH_UNIX, SECONDS_PER_WEEK, gpst_to_utc

#: Horizontal speed (m/s) above which the course derived from ``vn, ve`` is flagged valid.
COURSE_MIN_SPEED_MPS = 0.5

#: RTKLIB Q -> GGA fix quality.
Q_TO_GGA: dict[int, int] = {0: 0, 1: 4, 2: 5, 3: 2, 4: 2, 5: 1, 6: 1}

_DEFAULT_LABELS = (
    "latitude longitude height q ns sdn sde sdu sdne sdeu sdun age ratio "
    "vn ve vu sdvn sdve sdvu sdvne sdveu sdvun"
).split()


def _norm_label(tok: str) -> str:
    base = tok.split("(", 1)[0].strip().lower()
    return base.replace("-ecef", "")


def _parse_column_line(line: str) -> tuple[str, list[str], bool] | None:
    """``(time system, labels after the time, dms)`` from a ``%`` column line, or None."""
    toks = line.lstrip("%").split()
    if not toks or toks[0].upper() not in ("GPST", "UTC", "JST"):
        return None
    labels = [_norm_label(t) for t in toks[1:]]
    if not labels or not ({"latitude", "x"} & set(labels)):
        return None
    dms = any(t.lower().startswith("latitude(") and "deg" not in t.lower() for t in toks[1:])
    return toks[0].upper(), labels, dms


def _timegm_date(date: str, clock: str, cache: dict[str, float]) -> float:
    """Seconds since 1970 of ``yyyy/mm/dd`` and ``hh:mm:ss.sss`` (raises ValueError)."""
    day = cache.get(date)
    if day is None:
        y, m, d = (int(x) for x in date.split("/"))
        day = float(calendar.timegm((y, m, d, 0, 0, 0, 0, 0, 0)))
        cache[date] = day
    hh, mm, ss = clock.split(":")
    h, mi, s = int(hh), int(mm), float(ss)
    if not (0 <= h < 24 and 0 <= mi < 60 and 0.0 <= s < 61.0):
        raise ValueError(clock)
    return day + 3600.0 * h + 60.0 * mi + s


def _dms(d: str, m: str, s: str) -> float:
    deg = float(d)
    neg = d.strip().startswith("-")
    val = abs(deg) + float(m) / 60.0 + float(s) / 3600.0
    return -val if neg else val


def _signed_sq(x: npt.NDArray[np.float64]) -> npt.NDArray[np.float64]:
    """Covariance from RTKLIB's ``sign(c) sqrt(|c|)`` encoding."""
    return np.sign(x) * x * x


def read_rtklib_pos(source: str | os.PathLike[str], *, name: str | None = None) -> Part:
    """Read an RTKLIB solution (``.pos``) file into GNSS epochs on UTC.

    Parameters
    ----------
    source : str or os.PathLike
        The ``.pos`` file.
    name : str, optional
        Name used in the report and error messages (default: the path).

    Returns
    -------
    Part
        ``gnss`` table (lat/lon deg, height m ellipsoidal, NED velocity m/s, accuracies m), clock
        ``"utc"``; the report counts epochs by RTKLIB ``Q`` (``records["Q1"]`` ...) and notes the
        time system and coordinate type found.

    Raises
    ------
    IngestError
        When the file cannot be opened or holds neither an RTKLIB column header nor any line
        that parses as an RTKLIB solution.
    """
    path = os.fspath(source)
    label = name or path
    try:
        with open(path, "rb") as f:
            raw = f.read()
    except OSError as exc:
        raise IngestError(label, f"cannot open file ({exc.strerror})") from None
    lines = split_lines(raw.decode("utf-8", errors="replace"))
    rep = FileReport(path=label, format="rtklib-pos", units=len(lines))

    timesys, labels, dms, have_header = "GPST", list(_DEFAULT_LABELS), False, False
    for line in lines:
        s = line.strip()
        if s.startswith("%"):
            parsed = _parse_column_line(s)
            if parsed is not None:
                timesys, labels, dms = parsed
                have_header = True
        elif s:
            break

    is_ecef = "x" in labels and "latitude" not in labels
    pos_labels = ("x", "y", "z") if is_ecef else ("latitude", "longitude", "height")
    # Field layout: time (2 fields) then labels; DMS latitude/longitude take 3 fields each.
    widths = [3 if (dms and lab in ("latitude", "longitude")) else 1 for lab in labels]
    n_fields = 2 + sum(widths)
    start: dict[str, int] = {}
    col = 2
    for lab, w in zip(labels, widths, strict=True):
        start.setdefault(lab, col)
        col += w
    for need in (*pos_labels, "q"):
        if need not in start:
            raise IngestError(label, f"RTKLIB column header lacks '{need}': {labels}")

    num_cols = [lab for lab in start if lab not in ("latitude", "longitude") or not dms]
    rows: list[list[float]] = []
    times: list[float] = []
    date_cache: dict[str, float] = {}
    week_tow: bool | None = None
    prev_line = None
    for i, line in enumerate(lines, start=1):
        s = line.strip()
        if not s:
            rep.ignore("blank")
            continue
        if s.startswith("%"):
            rep.ignore("header")
            continue
        toks = s.split()
        if len(toks) != n_fields:
            rep.skip(SkipReason.TRUNCATED, i, s)
            continue
        try:
            if "/" in toks[0]:
                if week_tow is True:
                    raise ValueError("time format changed")
                week_tow = False
                tt = _timegm_date(toks[0], toks[1], date_cache)
            else:
                if week_tow is False:
                    raise ValueError("time format changed")
                week_tow = True
                wk, tow = int(toks[0]), float(toks[1])
                if not (0 <= wk < 10000 and 0.0 <= tow < SECONDS_PER_WEEK + 1):
                    raise ValueError("week/tow out of range")
                tt = GPS_EPOCH_UNIX + wk * SECONDS_PER_WEEK + tow
            vals = [float(toks[start[c]]) for c in num_cols]
            if dms:
                a, b = start["latitude"], start["longitude"]
                vals += [_dms(*toks[a : a + 3]), _dms(*toks[b : b + 3])]
        except (ValueError, IndexError, OverflowError):
            rep.skip(SkipReason.MALFORMED, i, s)
            continue
        if not math.isfinite(tt) or not all(math.isfinite(v) for v in vals[: len(num_cols)]):
            rep.skip(SkipReason.NAN_FIELD, i, s)
            continue
        if times and tt <= times[-1]:
            same = s == prev_line
            rep.skip(SkipReason.DUPLICATE if same else SkipReason.NON_MONOTONIC, i, s)
            continue
        times.append(tt)
        rows.append(vals)
        prev_line = s

    if not have_header and not rows:
        raise IngestError(
            label,
            "not an RTKLIB solution file: expected '%' header lines with a column line such as "
            "'%  GPST  latitude(deg) longitude(deg) height(m) Q ns ...' and solution lines",
        )
    rep.notes.append(
        f"time system {timesys}" + (" (converted to UTC with leap seconds)" if timesys == "GPST" else "")
    )
    if not have_header:
        rep.notes.append("no RTKLIB column header: assumed GPST, lat/lon (deg), height, Q, ns, sdn ...")
    rep.notes.append(
        "coordinates: "
        + ("ECEF x/y/z (m) converted to WGS84 geodetic" if is_ecef else "lat/lon/height")
        + (" in degrees-minutes-seconds" if dms else "")
    )
    if week_tow:
        rep.notes.append("time given as GPS week and time of week")

    keys = num_cols + (["latitude", "longitude"] if dms else [])
    arr = np.asarray(rows, dtype=np.float64).reshape(len(rows), len(keys))
    c = {k: arr[:, j] for j, k in enumerate(keys)}
    n = len(rows)
    nan = np.full(n, np.nan)
    t_raw = np.asarray(times, dtype=np.float64)
    if timesys == "GPST":
        utc = gpst_to_utc(t_raw)
    elif timesys == "JST":
        utc = t_raw - 9 * 3600.0
    else:
        utc = t_raw

    def get(k: str) -> npt.NDArray[np.float64]:
        return c[k] if k in c else nan

    if is_ecef:
        lat, lon, h = pymap3d.ecef2geodetic(c["x"], c["y"], c["z"], deg=True)
        lat, lon, h = np.asarray(lat, float), np.asarray(lon, float), np.asarray(h, float)
        # Covariance rotated from ECEF to ENU at each epoch.
        sx, sy, sz = get("sdx"), get("sdy"), get("sdz")
        cxy, cyz, czx = (_signed_sq(get(k)) if k in c else np.zeros(n) for k in ("sdxy", "sdyz", "sdzx"))
        cov = np.empty((n, 3, 3))
        cov[:, 0, 0], cov[:, 1, 1], cov[:, 2, 2] = sx * sx, sy * sy, sz * sz
        cov[:, 0, 1] = cov[:, 1, 0] = cxy
        cov[:, 1, 2] = cov[:, 2, 1] = cyz
        cov[:, 0, 2] = cov[:, 2, 0] = czx
        phi, lam = np.radians(lat), np.radians(lon)
        sp, cp, sl, cl = np.sin(phi), np.cos(phi), np.sin(lam), np.cos(lam)
        r_enu_e = np.stack(
            [
                np.stack([-sl, cl, np.zeros(n)], axis=-1),
                np.stack([-sp * cl, -sp * sl, cp], axis=-1),
                np.stack([cp * cl, cp * sl, sp], axis=-1),
            ],
            axis=1,
        )
        cov_enu = r_enu_e @ cov @ np.transpose(r_enu_e, (0, 2, 1))
        var_e, var_n, var_u = cov_enu[:, 0, 0], cov_enu[:, 1, 1], cov_enu[:, 2, 2]
        if {"vx", "vy", "vz"} <= c.keys():
            ve_, vn_, vu_ = pymap3d.ecef2enuv(c["vx"], c["vy"], c["vz"], lat, lon, deg=True)
            ve, vn, vu = np.asarray(ve_, float), np.asarray(vn_, float), np.asarray(vu_, float)
            sdvn = sdve = np.sqrt((get("sdvx") ** 2 + get("sdvy") ** 2 + get("sdvz") ** 2) / 3.0)
        else:
            ve = vn = vu = sdvn = sdve = nan
        h_acc = np.sqrt(var_n + var_e)
        v_acc = np.sqrt(var_u)
    else:
        lat, lon, h = get("latitude"), get("longitude"), get("height")
        vn, ve, vu = get("vn"), get("ve"), get("vu")
        sdvn, sdve = get("sdvn"), get("sdve")
        h_acc = np.hypot(get("sdn"), get("sde"))
        v_acc = get("sdu")

    q = get("q")
    q_int = np.where(np.isfinite(q), q, -1).astype(np.int64)
    quality = np.array([Q_TO_GGA.get(int(v), -1) for v in q_int], dtype=np.int16)
    valid = (q_int >= 1) & (q_int <= 6)
    for v in np.unique(q_int):
        rep.record(f"Q{v}", int(np.sum(q_int == v)))
    speed = np.hypot(vn, ve)
    course = np.mod(np.arctan2(ve, vn), 2.0 * np.pi)
    with np.errstate(invalid="ignore", divide="ignore"):
        s_acc = np.where(
            speed > 0,
            np.sqrt(vn * vn * sdvn * sdvn + ve * ve * sdve * sdve) / speed,
            np.sqrt((sdvn * sdvn + sdve * sdve) / 2.0),
        )
    ns = get("ns")
    gnss = pd.DataFrame(
        {
            "t": utc,
            "utc": utc,
            "lat_deg": lat,
            "lon_deg": lon,
            "height_m": h,
            "quality": quality,
            "mode": np.where(valid, 3, 1).astype(np.int16),
            "num_sv": np.where(np.isfinite(ns), ns, -1).astype(np.int16),
            "speed_mps": speed,
            "course_rad": np.where(np.isfinite(course), course, np.nan),
            "course_valid": np.isfinite(speed) & (speed > COURSE_MIN_SPEED_MPS),
            "vn": vn,
            "ve": ve,
            "vd": -vu,
            "h_acc_m": h_acc,
            "v_acc_m": v_acc,
            "s_acc_mps": s_acc,
            "valid": valid,
            "source": "rtklib",
        }
    )
    return Part.make(rep, "utc", gnss=gnss)
