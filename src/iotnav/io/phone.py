"""Smartphone logs: Android GnssLogger text files and Sensor Logger (Kelvin Choi) CSV exports.

GnssLogger (``gnss_log_*.txt``)
-------------------------------
Lines starting with ``#`` are comments; those of the form ``# Kind,field,field...`` declare the
layout of the records of that kind, and the reader takes every layout from the file itself (so
app versions with other fields work). Records used:

``Fix``
    location fixes. Only ``Provider`` ``GPS`` fixes are used when any exist (``FLP``/``NLP`` are
    fused/network positions, ignored and counted); otherwise all fixes. Fields by name:
    latitude/longitude (deg), ``AltitudeMeters`` (Android: height above the WGS84 ellipsoid),
    speed (m/s), bearing (deg -> rad), ``AccuracyMeters`` (Android: 68 % horizontal radius,
    converted to the 2D 1-sigma ``h_acc_m``, x 0.937:
    :func:`iotnav.gnss_accuracy.h_acc_from_radius`), ``VerticalAccuracyMeters``,
    ``SpeedAccuracyMps`` (68 %, about 1 sigma); time ``UnixTimeMillis``
    (the GNSS time of the fix, UTC). ``quality`` 1, ``mode`` 3 (2 without altitude), ``vn/ve``
    from speed and bearing when the bearing is given (``vd`` unknown).
``UncalAccel``/``Accel``, ``UncalGyro``/``Gyro``, ``UncalMag``/``Mag``
    Android units: m/s^2, rad/s, microtesla, in the device frame (x right, y up the screen,
    z out of the screen; at rest z reads +9.8). The **uncalibrated** kinds are preferred
    (``calibrated=False``): their measured value (``UncalGyroX...``, bias columns not subtracted)
    is what an IMU filter that estimates its own biases needs, without the operating system's
    bias steps; the other kind is counted as ignored. When only one kind exists it is used.
``Raw``, ``Status``, ``Nav``, ``NMEA``, ``OrientationDeg``, ``Agc`` ... (declared kinds)
    counted as ignored; undeclared kinds are ``UNKNOWN_SENTENCE``.

Clock: sensor records carry ``utcTimeMillis`` (phone wall clock, 1 ms steps) and
``elapsedRealtimeNanos`` (the sensor event time on the monotonic boot clock, ns). Times are taken
from ``elapsedRealtimeNanos`` for their resolution and put on UTC with one offset,
``median(UnixTimeMillis/1e3 - elapsedRealtimeNanos/1e9)`` over the GPS fixes (GNSS time), or over
the sensor records' ``utcTimeMillis`` when no fix has both. Without ``elapsedRealtimeNanos``,
``utcTimeMillis`` is used directly. The part's clock is ``"utc"``.

IMU rows: gyroscope sample times are the rows' times; the accelerometer is linearly interpolated
to them (a gyroscope sample outside the accelerometer's time span is skipped as ``NO_TIME``).

Sensor Logger (directory or ``.zip`` of CSV files)
--------------------------------------------------
Units per the app's unit reference (awesome-sensor-logger ``UNITS.md``): ``time`` ns since the
epoch (the phone's clock, taken as UTC), ``seconds_elapsed`` s; accelerations m/s^2, rates
rad/s, field uT; ``Location.csv`` latitude/longitude deg, ``altitude`` above the WGS84
ellipsoid, ``speed`` m/s, ``bearing`` deg, accuracies m (negative values mean invalid;
``horizontalAccuracy`` is read as Android's 68 % radius, as for GnssLogger; iOS states no
confidence for its radius).

``Accelerometer.csv`` is acceleration *without* gravity; ``TotalAcceleration.csv`` (Android only)
includes it and is preferred. Without it, specific force is built as ``Accelerometer +
Gravity``; on iOS without "Standardise Units & Frames" the app's acceleration and gravity have
the opposite sign of Android's (flat on a table iOS gravity reads -z), so the sum is negated.
The platform comes from ``platform=`` or, with ``"auto"``, from a ``platform`` column/value
``ios``/``android`` in ``Metadata.csv`` (an assumption about that file, noted in the report);
failing both, Android conventions are assumed and noted. Uncalibrated files are not used.
"""

from __future__ import annotations

import csv
import io
import math
import os
import zipfile
from collections import defaultdict
from collections.abc import Sequence
from pathlib import Path
from typing import Literal

import numpy as np
import numpy.typing as npt
import pandas as pd

from iotnav.gnss_accuracy import h_acc_from_radius
from iotnav.io.errors import IngestError
from iotnav.io.imu_csv import _Layout, _read_numeric, _sniff, split_lines
from iotnav.io.log import Part
from iotnav.io.report import FileReport, SkipReason

_SENSOR_KINDS = {
    "acc": ("UncalAccel", "Accel"),
    "gyro": ("UncalGyro", "Gyro"),
    "mag": ("UncalMag", "Mag"),
}
_KNOWN_KINDS = {"Raw", "Status", "Nav", "NMEA", "OrientationDeg", "Agc", "GameRotationVector", "Fix"}
COURSE_MIN_SPEED_MPS = 0.5


def _field(layout: Sequence[str], *names: str) -> int | None:
    low = [f.strip().lower() for f in layout]
    for n in names:
        if n.lower() in low:
            return low.index(n.lower())
    return None


def _monotonic_keep(
    t: npt.NDArray[np.float64], rows: npt.NDArray[np.float64]
) -> tuple[npt.NDArray[np.bool_], npt.NDArray[np.bool_]]:
    """``(keep, duplicate)`` masks: keep strictly increasing times; flag exact repeats."""
    n = t.size
    if n == 0:
        return np.zeros(0, bool), np.zeros(0, bool)
    prev = np.empty(n)
    prev[0] = -np.inf
    np.maximum.accumulate(t[:-1], out=prev[1:])
    back = t <= prev
    same = np.zeros(n, bool)
    if n > 1:
        same[1:] = (t[1:] == t[:-1]) & np.all(rows[1:] == rows[:-1], axis=1)
    return ~back, back & same


def _parse_kind(
    lines: list[tuple[int, str]], layout: list[str], rep: FileReport, label: str, needed: list[int]
) -> tuple[dict[int, npt.NDArray[np.float64]], npt.NDArray[np.intp]]:
    """Numeric fields of the records of one kind; returns columns and their file line numbers."""
    data = "\n".join(s for _, s in lines).encode("utf-8", errors="replace") + b"\n"
    lay = _Layout(",", 0, len(layout), None, {})
    sub = FileReport(path=label, format="gnsslogger")
    tab = _read_numeric(data, lay, needed, sub, label, len(lines) + 1)
    line_nos = np.array([ln for ln, _ in lines], dtype=np.intp)
    # translate the sub-report (line numbers of the subset) into the file's line numbers
    for reason, cnt in sub.skipped.items():
        ex = sub.examples.get(reason, [])
        for w, txt in ex:
            rep.skip(reason, int(line_nos[w - 1]) if 0 < w <= line_nos.size else -1, txt)
        if cnt > len(ex):
            rep.skip(reason, n=cnt - len(ex))
    for k, v in sub.ignored.items():
        rep.ignore(k, v)
    # subset line (1-based) of each parsed row: every subset line not consumed as a bad row
    rows = np.setdiff1d(np.arange(1, tab.n + len(tab.bad_lines) + 1), np.asarray(tab.bad_lines, np.intp))[
        : tab.n
    ]
    lines_used = line_nos[np.clip(rows - 1, 0, max(line_nos.size - 1, 0))] if tab.n else rows.astype(np.intp)
    ok = ~tab.empty
    if tab.malformed is not None:
        for j in np.flatnonzero(tab.malformed)[:3]:
            rep.skip(SkipReason.MALFORMED, int(lines_used[j]), lines[int(rows[j]) - 1][1])
        nm = int(tab.malformed.sum())
        if nm > 3:
            rep.skip(SkipReason.MALFORMED, n=nm - 3)
        ok &= ~tab.malformed
    if tab.empty.any():
        rep.ignore("empty record", int(tab.empty.sum()))
    cols = {i: tab.values[i][ok] for i in needed}
    return cols, lines_used[ok]


def read_gnsslogger(
    source: str | os.PathLike[str], *, name: str | None = None, calibrated: bool = False
) -> Part:
    """Read an Android GnssLogger text log: fixes, accelerometer, gyroscope, magnetometer.

    Parameters
    ----------
    source : str or os.PathLike
        The ``gnss_log_*.txt`` file.
    name : str, optional
        Name used in the report and error messages (default: the path).
    calibrated : bool
        Prefer the calibrated ``Accel``/``Gyro``/``Mag`` records over the ``Uncal*`` ones.

    Returns
    -------
    Part
        ``gnss`` (GPS-provider fixes, lat/lon deg, ellipsoidal height m), ``imu`` (m/s^2, rad/s,
        device frame) and ``mag`` (uT) on clock ``"utc"`` (see the module docstring).

    Raises
    ------
    IngestError
        When the file cannot be opened or declares no record layout (``# Fix,...`` etc.) and holds
        no recognisable record.
    """
    path = os.fspath(source)
    label = name or path
    try:
        with open(path, "rb") as f:
            raw = f.read()
    except OSError as exc:
        raise IngestError(label, f"cannot open file ({exc.strerror})") from None
    lines = split_lines(raw.decode("utf-8", errors="replace"))
    rep = FileReport(path=label, format="gnsslogger", units=len(lines))
    layouts: dict[str, list[str]] = {}
    by_kind: dict[str, list[tuple[int, str]]] = defaultdict(list)
    for i, line in enumerate(lines, start=1):
        s = line.strip()
        if not s:
            rep.ignore("blank")
            continue
        if s.startswith("#"):
            body = s.lstrip("#").strip()
            kind = body.split(",", 1)[0].strip()
            if "," in body and kind.isidentifier():
                layouts[kind] = [f.strip() for f in body.split(",")]
            rep.ignore("header")
            continue
        kind = s.split(",", 1)[0].strip()
        by_kind[kind].append((i, s))
    if not layouts:
        raise IngestError(
            label,
            "not a GnssLogger file: expected '# Fix,Provider,...' / '# UncalAccel,utcTimeMillis,...' "
            "layout lines followed by records",
        )
    for kind, recs in by_kind.items():
        if kind not in layouts:
            for ln, s in recs[:3]:
                rep.skip(SkipReason.UNKNOWN_SENTENCE, ln, s)
            if len(recs) > 3:
                rep.skip(SkipReason.UNKNOWN_SENTENCE, n=len(recs) - 3)

    # ---- sensors
    sensor: dict[
        str, tuple[str, npt.NDArray[np.float64], npt.NDArray[np.float64], npt.NDArray[np.float64]]
    ] = {}
    used_kinds = set()
    for fam, (uncal, cal) in _SENSOR_KINDS.items():
        order = (cal, uncal) if calibrated else (uncal, cal)
        chosen = next((k for k in order if k in layouts and by_kind.get(k)), None)
        for k in order:
            if k != chosen and by_kind.get(k) and k in layouts:
                rep.ignore(f"{k} (other calibration preferred)", len(by_kind[k]))
        if chosen is None:
            continue
        used_kinds.add(chosen)
        lay = layouts[chosen]
        i_utc = _field(lay, "utcTimeMillis")
        i_ert = _field(lay, "elapsedRealtimeNanos")
        axes = [
            next((j for j, f in enumerate(lay) if f.lower().startswith((chosen + a).lower())), None)
            for a in "XYZ"
        ]
        if any(a is None for a in axes) or (i_utc is None and i_ert is None):
            rep.notes.append(f"{chosen}: layout {lay} lacks time or X/Y/Z fields; records ignored")
            rep.ignore(chosen, len(by_kind[chosen]))
            continue
        needed = [j for j in (i_utc, i_ert, *axes) if j is not None]
        cols, _ = _parse_kind(by_kind[chosen], lay, rep, label, needed)
        xyz = np.stack([cols[j] for j in axes if j is not None], axis=1) if cols else np.zeros((0, 3))
        utc_ms = cols[i_utc] if i_utc is not None else np.full(len(xyz), np.nan)
        ert = cols[i_ert] if i_ert is not None else np.full(len(xyz), np.nan)
        sensor[fam] = (chosen, utc_ms, ert, xyz)
        rep.notes.append(f"{fam}: {chosen} records")
    for kind, recs in by_kind.items():
        if (
            kind in layouts
            and kind not in used_kinds
            and kind != "Fix"
            and not any(kind in pair for pair in _SENSOR_KINDS.values())
        ):
            rep.ignore(kind, len(recs))

    # ---- fixes
    gnss_df = None
    fix_off = np.zeros(0)
    if "Fix" in layouts and by_kind.get("Fix"):
        lay = layouts["Fix"]
        gnss_df, fix_off = _gnsslogger_fixes(by_kind["Fix"], lay, rep)

    # ---- clock
    offset = float("nan")
    if fix_off.size:
        offset = float(np.median(fix_off))
        rep.notes.append("clock: elapsedRealtimeNanos + offset from GPS fixes (UnixTimeMillis)")
    else:
        d = [s[1] / 1e3 - s[2] / 1e9 for s in sensor.values() if s[1].size]
        dd = np.concatenate(d) if d else np.zeros(0)
        dd = dd[np.isfinite(dd)]
        if dd.size:
            offset = float(np.median(dd))
            rep.notes.append("clock: elapsedRealtimeNanos + offset from sensor utcTimeMillis (no GPS fix)")

    def times(utc_ms: npt.NDArray[np.float64], ert: npt.NDArray[np.float64]) -> npt.NDArray[np.float64]:
        if math.isfinite(offset) and np.isfinite(ert).all():
            return ert / 1e9 + offset
        return utc_ms / 1e3

    streams = {}
    for fam, (kind, utc_ms, ert, xyz) in sensor.items():
        t = times(utc_ms, ert)
        fin = np.isfinite(t) & np.all(np.isfinite(xyz), axis=1)
        if (~fin).any():
            rep.skip(
                SkipReason.NAN_FIELD, text=f"{int((~fin).sum())} {kind} records with NaN", n=int((~fin).sum())
            )
        t, xyz = t[fin], xyz[fin]
        keep, dup = _monotonic_keep(t, xyz)
        if dup.any():
            rep.skip(SkipReason.DUPLICATE, text=f"{kind} repeated record", n=int(dup.sum()))
        nm = int((~keep & ~dup).sum())
        if nm:
            rep.skip(SkipReason.NON_MONOTONIC, text=f"{kind} time not increasing", n=nm)
        streams[fam] = (kind, t[keep], xyz[keep])
    imu_df, mag_df = _assemble(streams, rep)
    return Part.make(rep, "utc", gnss=gnss_df, imu=imu_df, mag=mag_df)


def _gnsslogger_fixes(
    recs: list[tuple[int, str]], lay: list[str], rep: FileReport
) -> tuple[pd.DataFrame | None, npt.NDArray[np.float64]]:
    ip = _field(lay, "Provider")
    names = {
        "lat": ("LatitudeDegrees", "Latitude"),
        "lon": ("LongitudeDegrees", "Longitude"),
        "alt": ("AltitudeMeters", "Altitude"),
        "spd": ("SpeedMps", "Speed"),
        "acc": ("AccuracyMeters", "Accuracy"),
        "brg": ("BearingDegrees", "Bearing"),
        "time": ("UnixTimeMillis", "(UTC)TimeInMs", "UTCTimeInMs", "TimeInMs", "utcTimeMillis"),
        "sacc": ("SpeedAccuracyMps",),
        "vacc": ("VerticalAccuracyMeters",),
        "ert": ("elapsedRealtimeNanos",),
    }
    idx = {k: _field(lay, *v) for k, v in names.items()}
    if idx["lat"] is None or idx["lon"] is None or idx["time"] is None:
        rep.notes.append(f"Fix layout {lay} lacks latitude/longitude/time; fixes ignored")
        rep.ignore("Fix", len(recs))
        return None, np.zeros(0)
    provs = [s.split(",")[ip].strip() if ip is not None and len(s.split(",")) > ip else "" for _, s in recs]
    use_gps = any(p.upper() == "GPS" for p in provs)
    rows: list[list[float]] = []
    for (ln, s), prov in zip(recs, provs, strict=True):
        f = s.split(",")
        if len(f) != len(lay):
            rep.skip(SkipReason.TRUNCATED, ln, s)
            continue
        if use_gps and prov.upper() != "GPS":
            rep.ignore(f"Fix {prov or '?'}")
            continue

        def num(k: str, f: list[str] = f) -> float:
            j = idx[k]
            if j is None or not f[j].strip():
                return math.nan
            return float(f[j])

        try:
            row = [num(k) for k in ("time", "lat", "lon", "alt", "spd", "acc", "brg", "sacc", "vacc", "ert")]
        except ValueError:
            rep.skip(SkipReason.MALFORMED, ln, s)
            continue
        if not all(math.isfinite(v) for v in row[:3]):
            rep.skip(SkipReason.NAN_FIELD, ln, s)
            continue
        if not (-90 <= row[1] <= 90 and -180 <= row[2] <= 180):
            rep.skip(SkipReason.OUT_OF_RANGE, ln, s)
            continue
        if rows and row[0] <= rows[-1][0]:
            rep.skip(SkipReason.NON_MONOTONIC, ln, s)
            continue
        rows.append(row)
        rep.record(f"Fix {prov}" if prov else "Fix")
    a = np.asarray(rows, dtype=float).reshape(len(rows), 10)
    t = a[:, 0] / 1e3
    spd, brg = a[:, 4], np.radians(a[:, 6])
    has_brg = np.isfinite(brg)
    course = np.where(has_brg, np.mod(brg, 2 * np.pi), np.nan)
    gnss = pd.DataFrame(
        {
            "t": t,
            "utc": t,
            "lat_deg": a[:, 1],
            "lon_deg": a[:, 2],
            "height_m": a[:, 3],
            "quality": np.ones(len(a), dtype=np.int16),
            "mode": np.where(np.isfinite(a[:, 3]), 3, 2).astype(np.int16),
            "speed_mps": spd,
            "course_rad": course,
            "course_valid": has_brg & (spd > COURSE_MIN_SPEED_MPS),
            "vn": np.where(has_brg, spd * np.cos(brg), np.nan),
            "ve": np.where(has_brg, spd * np.sin(brg), np.nan),
            "h_acc_m": h_acc_from_radius(a[:, 5]),
            "v_acc_m": a[:, 8],
            "s_acc_mps": a[:, 7],
            "valid": np.ones(len(a), dtype=bool),
            "source": "phone",
        }
    )
    off = t - a[:, 9] / 1e9
    return gnss, off[np.isfinite(off)]


def _assemble(
    streams: dict[str, tuple[str, npt.NDArray[np.float64], npt.NDArray[np.float64]]], rep: FileReport
) -> tuple[pd.DataFrame | None, pd.DataFrame | None]:
    """IMU rows on the gyroscope times (accelerometer interpolated) and the magnetometer table."""
    imu_df = None
    if "gyro" in streams or "acc" in streams:
        if "gyro" in streams:
            gk, tg, wg = streams["gyro"]
            if "acc" in streams:
                ak, ta, fa = streams["acc"]
                rep.record(ak, int(ta.size))
                inside = (tg >= ta[0]) & (tg <= ta[-1]) if ta.size else np.zeros(tg.size, bool)
                if (~inside).any():
                    rep.skip(
                        SkipReason.NO_TIME,
                        text=f"{gk} samples outside the accelerometer time span (cannot interpolate)",
                        n=int((~inside).sum()),
                    )
                tg, wg = tg[inside], wg[inside]
                f = (
                    np.stack([np.interp(tg, ta, fa[:, k]) for k in range(3)], axis=1)
                    if tg.size
                    else np.zeros((0, 3))
                )
                rep.notes.append("IMU rows at gyroscope times; accelerometer linearly interpolated")
            else:
                f = np.full((tg.size, 3), np.nan)
                rep.notes.append("no accelerometer records: acc fields are NaN")
            rep.record(gk, int(tg.size))
            t, w = tg, wg
        else:
            ak, t, f = streams["acc"]
            rep.record(ak, int(t.size))
            w = np.full((t.size, 3), np.nan)
            rep.notes.append("no gyroscope records: gyro fields are NaN")
        imu_df = pd.DataFrame(
            {"t": t}
            | {f"acc_{a}": f[:, k] for k, a in enumerate("xyz")}
            | {f"gyro_{a}": w[:, k] for k, a in enumerate("xyz")}
        )
    mag_df = None
    if "mag" in streams:
        mk, tm, b = streams["mag"]
        rep.record(mk, int(tm.size))
        mag_df = pd.DataFrame({"t": tm} | {f"mag_{a}_ut": b[:, k] for k, a in enumerate("xyz")})
    return imu_df, mag_df


# --------------------------------------------------------------------------------------------
# Sensor Logger
# --------------------------------------------------------------------------------------------


def _sl_files(src: str) -> dict[str, bytes]:
    """CSV members of a Sensor Logger export by base name (directory or zip)."""
    out: dict[str, bytes] = {}
    if os.path.isdir(src):
        for p in sorted(Path(src).iterdir()):
            if p.suffix.lower() == ".csv" and p.is_file():
                out[p.name] = p.read_bytes()
        return out
    try:
        with zipfile.ZipFile(src) as z:
            for info in z.infolist():
                base = info.filename.rsplit("/", 1)[-1]
                if base.lower().endswith(".csv") and not info.is_dir() and base not in out:
                    out[base] = z.read(info)
    except (zipfile.BadZipFile, OSError) as exc:
        raise IngestError(src, f"not a Sensor Logger export (directory or zip of CSV files): {exc}") from None
    return out


def _sl_table(
    data: bytes, member: str, label: str, rep: FileReport, wanted: Sequence[str], required: Sequence[str]
) -> dict[str, npt.NDArray[np.float64]] | None:
    """Named numeric columns of one Sensor Logger CSV (rows with a NaN required field skipped)."""
    n_lines = data.count(b"\n") + (0 if data.endswith(b"\n") or not data else 1)
    rep.units += n_lines
    lay = _sniff(data[: 1 << 20], True, None)
    if lay.header is None:
        rep.ignore(f"{member} (no header)", n_lines)
        rep.notes.append(f"{member}: no header line; not read")
        return None
    idx = {}
    for w in wanted:
        if w in lay.header:
            idx[w] = lay.header.index(w)
    if any(r not in idx for r in required):
        rep.ignore(f"{member} (missing columns)", n_lines)
        rep.notes.append(f"{member}: lacks columns {[r for r in required if r not in idx]}; not read")
        return None
    for k, v in lay.preamble_ignored.items():
        rep.ignore(k, v)
    tab = _read_numeric(data, lay, list(idx.values()), rep, f"{label}:{member}", n_lines + 1)
    bad = tab.empty.copy()
    if tab.empty.any():
        rep.ignore("empty line", int(tab.empty.sum()))
    mal = tab.malformed if tab.malformed is not None else np.zeros(tab.n, bool)
    mal = mal & ~tab.empty
    if mal.any():
        rep.skip(SkipReason.MALFORMED, text=f"{member}: {int(mal.sum())} rows", n=int(mal.sum()))
    bad |= mal
    nan = ~bad & ~np.logical_and.reduce([np.isfinite(tab.values[idx[r]]) for r in required])
    if nan.any():
        rep.skip(SkipReason.NAN_FIELD, text=f"{member}: {int(nan.sum())} rows", n=int(nan.sum()))
    bad |= nan
    return {w: tab.values[i][~bad] for w, i in idx.items()}


def _sl_platform(files: dict[str, bytes], platform: str, rep: FileReport) -> str:
    if platform in ("android", "ios"):
        return platform
    meta = files.get("Metadata.csv")
    if meta:
        try:
            rows = list(csv.reader(io.StringIO(meta.decode("utf-8", errors="replace"))))
        except csv.Error:
            rows = []
        if len(rows) >= 2:
            head = [h.strip().lower() for h in rows[0]]
            vals = [v.strip().lower() for v in rows[1]]
            if "platform" in head and head.index("platform") < len(vals):
                p = vals[head.index("platform")]
                if p in ("ios", "android"):
                    rep.notes.append(f"platform {p} from Metadata.csv")
                    return p
            for v in vals:
                if v in ("ios", "android"):
                    rep.notes.append(f"platform {v} from a Metadata.csv value")
                    return v
    rep.notes.append("platform unknown: Android conventions assumed")
    return "android"


def read_sensor_logger(
    source_dir_or_zip: str | os.PathLike[str],
    *,
    name: str | None = None,
    platform: Literal["auto", "android", "ios"] = "auto",
    ios_standardised: bool = False,
) -> Part:
    """Read a Sensor Logger (Kelvin Choi) CSV export: location, IMU and magnetometer.

    Parameters
    ----------
    source_dir_or_zip : str or os.PathLike
        The export directory or its ``.zip``.
    name : str, optional
        Name used in the report and error messages (default: the path).
    platform : {"auto", "android", "ios"}
        Sign conventions of ``Accelerometer``/``Gravity`` (see the module docstring).
    ios_standardised : bool
        The recording had "Standardise Units & Frames" on (iOS data already in Android conventions).

    Returns
    -------
    Part
        ``gnss`` (lat/lon deg, ellipsoidal height m), ``imu`` (specific force m/s^2, rate rad/s,
        device frame), ``mag`` (uT) on clock ``"utc"`` (the ``time`` column, ns since the epoch).

    Raises
    ------
    IngestError
        When the source is neither a directory nor a zip, or holds none of ``Location.csv``,
        ``Gyroscope.csv``, ``TotalAcceleration.csv``, ``Accelerometer.csv``, ``Magnetometer.csv``.
    """
    src = os.fspath(source_dir_or_zip)
    label = name or src
    if not os.path.exists(src):
        raise IngestError(label, "no such file or directory")
    files = _sl_files(src)
    rep = FileReport(path=label, format="sensor-logger")
    known = {
        "Location.csv",
        "Gyroscope.csv",
        "TotalAcceleration.csv",
        "Accelerometer.csv",
        "Magnetometer.csv",
    }
    if not known & files.keys():
        raise IngestError(
            label,
            "not a Sensor Logger export: expected Location.csv, Gyroscope.csv, TotalAcceleration.csv, "
            f"Accelerometer.csv or Magnetometer.csv; found {sorted(files) or 'no CSV files'}",
        )
    xyz = ["time", "x", "y", "z"]
    streams: dict[str, tuple[str, npt.NDArray[np.float64], npt.NDArray[np.float64]]] = {}

    def stream(
        member: str, fam: str, cols: dict[str, npt.NDArray[np.float64]] | None, sign: float = 1.0
    ) -> None:
        if cols is None:
            return
        t = cols["time"] * 1e-9
        v = np.stack([cols["x"], cols["y"], cols["z"]], axis=1) * sign
        keep, dup = _monotonic_keep(t, v)
        if dup.any():
            rep.skip(SkipReason.DUPLICATE, text=f"{member} repeated row", n=int(dup.sum()))
        nm = int((~keep & ~dup).sum())
        if nm:
            rep.skip(SkipReason.NON_MONOTONIC, text=f"{member} time not increasing", n=nm)
        streams[fam] = (member, t[keep], v[keep])

    if "Gyroscope.csv" in files:
        stream(
            "Gyroscope.csv", "gyro", _sl_table(files["Gyroscope.csv"], "Gyroscope.csv", label, rep, xyz, xyz)
        )
    if "TotalAcceleration.csv" in files:
        stream(
            "TotalAcceleration.csv",
            "acc",
            _sl_table(files["TotalAcceleration.csv"], "TotalAcceleration.csv", label, rep, xyz, xyz),
        )
        rep.notes.append("specific force from TotalAcceleration.csv (includes gravity)")
        if "Accelerometer.csv" in files:
            _ignore_member(files, "Accelerometer.csv", rep, "gravity-free; TotalAcceleration preferred")
        if "Gravity.csv" in files:
            _ignore_member(files, "Gravity.csv", rep, "not needed with TotalAcceleration")
    elif "Accelerometer.csv" in files and "Gravity.csv" in files:
        plat = _sl_platform(files, platform, rep)
        ua = _sl_table(files["Accelerometer.csv"], "Accelerometer.csv", label, rep, xyz, xyz)
        gr = _sl_table(files["Gravity.csv"], "Gravity.csv", label, rep, xyz, xyz)
        if ua is not None and gr is not None and ua["time"].size and gr["time"].size:
            tg = gr["time"]
            total = {"time": ua["time"]}
            for a in "xyz":
                total[a] = ua[a] + np.interp(ua["time"], tg, gr[a])
            rep.ignore("Gravity.csv rows (combined with Accelerometer.csv)", int(tg.size))
            sign = -1.0 if (plat == "ios" and not ios_standardised) else 1.0
            stream("Accelerometer.csv", "acc", total, sign)
            rep.notes.append(
                "specific force = Accelerometer + Gravity (interpolated)"
                + (" negated (iOS sign convention)" if sign < 0 else "")
            )
    elif "Accelerometer.csv" in files:
        _ignore_member(files, "Accelerometer.csv", rep, "gravity-free and no Gravity.csv: not specific force")
    if "Magnetometer.csv" in files:
        stream(
            "Magnetometer.csv",
            "mag",
            _sl_table(files["Magnetometer.csv"], "Magnetometer.csv", label, rep, xyz, xyz),
        )
    imu_df, mag_df = _assemble(streams, rep)

    gnss_df = None
    if "Location.csv" in files:
        want = [
            "time",
            "latitude",
            "longitude",
            "altitude",
            "altitudeAboveMeanSeaLevel",
            "speed",
            "bearing",
            "horizontalAccuracy",
            "verticalAccuracy",
            "speedAccuracy",
        ]
        loc = _sl_table(
            files["Location.csv"], "Location.csv", label, rep, want, ["time", "latitude", "longitude"]
        )
        if loc is not None:
            gnss_df = _sl_gnss(loc, rep)
    used = known | {"Gravity.csv"}
    other = sorted(set(files) - used)
    if other:
        rep.notes.append("files not used: " + ", ".join(other))
    return Part.make(rep, "utc", gnss=gnss_df, imu=imu_df, mag=mag_df)


def _ignore_member(files: dict[str, bytes], member: str, rep: FileReport, why: str) -> None:
    data = files[member]
    n = data.count(b"\n") + (0 if data.endswith(b"\n") or not data else 1)
    rep.units += n
    rep.ignore(f"{member} ({why})", n)


def _sl_gnss(loc: dict[str, npt.NDArray[np.float64]], rep: FileReport) -> pd.DataFrame:
    n = loc["time"].size
    nan = np.full(n, np.nan)

    def col(k: str) -> npt.NDArray[np.float64]:
        v = loc.get(k, nan)
        return np.where(v >= 0, v, np.nan)  # negative = invalid in Sensor Logger

    t = loc["time"] * 1e-9
    lat, lon = loc["latitude"], loc["longitude"]
    inr = (np.abs(lat) <= 90) & (np.abs(lon) <= 180)
    keep, dup = _monotonic_keep(t, np.stack([lat, lon], axis=1))
    bad = ~inr
    if bad.any():
        rep.skip(
            SkipReason.OUT_OF_RANGE, text="Location.csv latitude/longitude out of range", n=int(bad.sum())
        )
    keep &= inr
    dup &= inr
    if dup.any():
        rep.skip(SkipReason.DUPLICATE, text="Location.csv repeated row", n=int(dup.sum()))
    nm = int((~keep & ~dup & inr).sum())
    if nm:
        rep.skip(SkipReason.NON_MONOTONIC, text="Location.csv time not increasing", n=nm)
    rep.record("Location", int(keep.sum()))
    spd, brg = col("speed"), np.radians(col("bearing"))
    has_brg = np.isfinite(brg)
    alt = loc.get("altitude", nan)
    msl = loc.get("altitudeAboveMeanSeaLevel", nan)
    df = pd.DataFrame(
        {
            "t": t,
            "utc": t,
            "lat_deg": lat,
            "lon_deg": lon,
            "height_m": alt,
            "alt_msl_m": msl,
            "geoid_sep_m": alt - msl,
            "quality": np.ones(n, dtype=np.int16),
            "mode": np.where(np.isfinite(alt), 3, 2).astype(np.int16),
            "speed_mps": spd,
            "course_rad": np.where(has_brg, np.mod(brg, 2 * np.pi), np.nan),
            "course_valid": has_brg & (spd > COURSE_MIN_SPEED_MPS),
            "vn": np.where(has_brg, spd * np.cos(brg), np.nan),
            "ve": np.where(has_brg, spd * np.sin(brg), np.nan),
            "h_acc_m": h_acc_from_radius(col("horizontalAccuracy")),
            "v_acc_m": col("verticalAccuracy"),
            "s_acc_mps": col("speedAccuracy"),
            "valid": np.ones(n, dtype=bool),
            "source": "phone",
        }
    )
    return df.loc[keep]
