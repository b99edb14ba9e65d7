"""IMU (and magnetometer) samples from delimited text files.

Columns
-------
The reader needs, per row, a time and at least one complete sensor triad. Column roles:

``acc_x, acc_y, acc_z``
    accelerometer (specific force in the sensor frame ``b``); header names such as ``ax``,
    ``acc_x``, ``accel_x``, ``AccX``, ``accelerometer_x``, ``a_x``;
``gyro_x, gyro_y, gyro_z``
    gyroscope (``gyro_x``, ``gx``, ``GyroX``, ``wx``, ``omega_x`` ...);
``mag_x, mag_y, mag_z``
    magnetometer (``mag_x``, ``mx``, ``MagX``, ``magnetometer_x`` ...);
``t``
    timestamp (``t``, ``time``, ``timestamp``, ``ts``, ``seconds_elapsed``, ``gpst_s`` ...); when
    several are present the absolute one (``time``/``timestamp``) wins over elapsed seconds;
``tick``
    a logger millisecond counter (``tick``, ``imu_tick_ms``), turned into GNSS time by an RTKLIB
    time-tag file (:mod:`iotnav.io.timetag`).

Bare ``x, y, z`` columns (the Sensor Logger layout) take their sensor from the file name
(``Accelerometer*``, ``Gyroscope*``, ``Magnetometer*``). Columns can also be given explicitly:
``columns`` (role -> header name), ``column_order`` (a role per field, for header-less files; use
``"-"`` to skip a field) or a named ``preset`` from :data:`IMU_PRESETS`. Columns that match no role
are ignored and listed in the report notes.

Units (converted once, here, to m/s^2, rad/s, microtesla and seconds)
---------------------------------------------------------------------
In order of precedence: the explicit argument, the preset, a unit in the header name
(``acc_x_g``, ``ax[m/s^2]``, ``gyro_x_dps``, ``gx (deg/s)``, ``mdps``, ``mag_x_ut``, ``mG``,
``gauss``, ``nT``; ``time_ms``), then the data:

* accelerometer: median norm of the samples 0.5..2 -> g, 5..20 -> m/s^2, 500..2000 -> mg;
  anything else (e.g. gravity-free "user acceleration") raises :class:`IngestError` asking for
  ``acc_unit``;
* gyroscope: no reliable data signature, so the *companion rule* is used: loggers that write g
  write deg/s, those writing mg write mdps, those writing m/s^2 write rad/s (Android, iOS, ROS);
  without an accelerometer unit, rad/s. The guess is then checked against the data: a 99th
  percentile rate norm above 35 (2000 deg/s as rad/s) switches rad/s to deg/s. The decision is
  written to the report notes as "guessed";
* magnetometer: median norm 5..150 -> uT, 150..2000 -> mG, 0.05..1.5 -> gauss, 5e3..2e5 -> nT,
  5e-6..2e-4 -> T;
* time: ``s``/``ms``/``us``/``ns`` by :func:`iotnav.io.timeutil.guess_time_unit`.

Time and clocks
---------------
Absolute Unix times (1e9..4.2e9 s after scaling) give clock ``"utc"``; a time column whose name
contains ``gps`` (``gpst_s``) is taken as GPST written as Unix seconds and converted with
:func:`iotnav.io.timeutil.gpst_to_utc`. Relative times give clock ``"device"``. With a time-tag
file, the ``tick`` column is mapped to GPST by :meth:`iotnav.io.timetag.TimeTag.ticks_to_gpst`
using the first and last samples kept (the upstream converter's convention), then to UTC: clock
``"utc"``. A ``tick`` column without a time-tag file is used as device time (ms unless told).
``time_offset_s`` is finally added to every time (e.g. -0.125 s, the logging delay
the data author applies to the rtklibexplorer drive).

Damaged rows (each data line ends up in exactly one report bucket)
-----------------------------------------------------------------
``TRUNCATED``
    wrong number of fields (the first and last lines of a logger file are often cut);
``MALFORMED``
    a needed field that is not a number;
``NAN_FIELD``
    a needed field empty, NaN or infinite (a row whose needed fields are *all* empty is counted
    as an ignored ``"empty line"``); a row with a usable IMU triad but no magnetometer value is
    an IMU record, not a skip (mixed-rate logs);
``OUT_OF_RANGE``
    an accelerometer component beyond 50 g, a rate beyond 50 rad/s, a field beyond 10 mT;
``DUPLICATE``
    same time and same values as the previous kept row (identical values with a *different*
    time are real samples of a sensor that did not change and are kept);
``NON_MONOTONIC``
    a time not after the latest kept time: the row is dropped (not re-sorted), because a time
    going backwards in a logger file is a glitch of that row, not a late sample. (A single
    glitch *forward* in time would, by the same rule, drop the rows after it until time catches
    up; such rows are all counted, never silently lost.)

Speed: the file is parsed by :mod:`pyarrow.csv` straight into float columns (a day of 100 Hz
samples, 8.6 million rows, in a few seconds); only when a needed field is not a number is the
file re-read as text and the bad fields found with vectorised pattern matching.

Modules: the column roles, presets and units are in :mod:`iotnav.io.imu_columns`, the sniffing
and numeric parsing in :mod:`iotnav.io.imu_table`; this module classifies the rows, converts
units and times and builds the :class:`~iotnav.io.log.Part` (public names re-exported here).
"""

from __future__ import annotations

import os
import re
from collections.abc import Mapping, Sequence

import numpy as np
import numpy.typing as npt
import pandas as pd

from iotnav.io.errors import IngestError
from iotnav.io.imu_columns import (
    ACC_LIMIT,
    ACC_UNITS,
    GYRO_LIMIT,
    GYRO_UNITS,
    IMU_PRESETS,
    MAG_LIMIT_UT,
    MAG_UNITS,
    _canon_unit,
    _check_unit,
    _guess_acc,
    _guess_mag,
    _resolve_columns,
    _sample_norm,
    _stem_family,
)
from iotnav.io.imu_columns import (  # re-exported
    G0 as G0,
)
from iotnav.io.imu_columns import (
    ImuPreset as ImuPreset,
)
from iotnav.io.imu_table import (  # re-exported (iotnav.io.phone reads with the same layout)
    _Layout as _Layout,
)
from iotnav.io.imu_table import (
    _read_numeric,
    _sniff,
)
from iotnav.io.log import Clock, Part
from iotnav.io.report import FileReport, SkipReason
from iotnav.io.schema import IMU_COLUMNS, coerce
from iotnav.io.timefaults import describe, rebase_segments
from iotnav.io.timetag import TimeTag, read_timetag
from iotnav.io.timeutil import gpst_to_utc, guess_time_unit, unit_scale

# --------------------------------------------------------------------------------------------
# Public reader
# --------------------------------------------------------------------------------------------


def read_imu_csv(
    source: str | os.PathLike[str],
    *,
    columns: Mapping[str, str] | None = None,
    column_order: Sequence[str] | None = None,
    acc_unit: str | None = None,
    gyro_unit: str | None = None,
    mag_unit: str | None = None,
    time_unit: str | None = None,
    timetag: str | os.PathLike[str] | TimeTag | None = None,
    time_offset_s: float = 0.0,
    preset: str | None = None,
    name: str | None = None,
) -> Part:
    """Read accelerometer, gyroscope and optional magnetometer samples from a CSV-like file.

    Parameters
    ----------
    source : str or os.PathLike
        The file (comma, semicolon, tab, ``|`` or single-space delimited).
    columns : Mapping[str, str], optional
        Role -> header name, e.g. ``{"acc_x": "AccX", ..., "t": "Time"}``. Roles: ``acc_x ..
        acc_z``, ``gyro_x .. gyro_z``, ``mag_x .. mag_z`` (``mag_x_ut`` accepted), ``t``, ``tick``.
    column_order : Sequence[str], optional
        Role of each field of a header-less file, ``"-"`` to skip a field.
    acc_unit : {"g", "mg", "m/s^2"}, optional
    gyro_unit : {"deg/s", "mdps", "rad/s"}, optional
    mag_unit : {"uT", "mG", "gauss", "nT", "T"}, optional
    time_unit : {"s", "ms", "us", "ns"}, optional
        Units of the file's fields; detected when not given (see the module docstring).
    timetag : str, os.PathLike or TimeTag, optional
        RTKLIB demo5 time-tag file mapping the ``tick`` column (ms) to GPST; the result is on UTC.
    time_offset_s : float
        Added to every sample time, s.
    preset : str, optional
        A key of :data:`IMU_PRESETS` (``"rtklib-demo5"``): column order and units of a known
        logger. Explicit arguments override it.
    name : str, optional
        Name used in the report and error messages (default: the path).

    Returns
    -------
    Part
        ``imu`` (specific force m/s^2 and angular rate rad/s in the sensor frame ``b``) and ``mag``
        (microtesla) tables, clock ``"utc"`` (absolute or tag-timed) or ``"device"``; the report
        counts every line and notes columns, units (given, from the header, or guessed) and the
        time base.

    Raises
    ------
    IngestError
        When the file cannot be read, no sensor triad or time column can be identified, or a unit
        cannot be determined.
    ValueError
        For an unknown preset, unit or column role in the arguments.
    """
    path = os.fspath(source)
    label = name or path
    if preset is not None:
        if preset not in IMU_PRESETS:
            raise ValueError(f"unknown IMU preset {preset!r}; known: {', '.join(sorted(IMU_PRESETS))}")
        pr = IMU_PRESETS[preset]
        column_order = column_order if column_order is not None else pr.column_order
        acc_unit = acc_unit or pr.acc_unit
        gyro_unit = gyro_unit or pr.gyro_unit
        mag_unit = mag_unit or pr.mag_unit
        time_unit = time_unit or pr.time_unit
    units_given = {
        "acc": _check_unit("acc", acc_unit, "accelerometer unit"),
        "gyro": _check_unit("gyro", gyro_unit, "gyroscope unit"),
        "mag": _check_unit("mag", mag_unit, "magnetometer unit"),
    }
    if time_unit is not None:
        unit_scale(time_unit)
    try:
        size = os.path.getsize(path)
        with open(path, "rb") as f:
            head = f.read(1 << 20)
    except OSError as exc:
        raise IngestError(label, f"cannot open file ({exc.strerror})") from None
    return _read_imu_bytes(
        path,
        label,
        head,
        size <= len(head),
        columns=columns,
        column_order=column_order,
        units_given=units_given,
        time_unit=time_unit,
        timetag=timetag,
        time_offset_s=time_offset_s,
        preset=preset,
    )


def _count_lines(src: str | bytes) -> int:
    """Physical lines as the CSV parser sees them (``\n``, ``\r\n`` or a lone ``\r`` end a line;
    a last line without an ending counts)."""

    def count(buf: bytes) -> int:
        n = buf.count(b"\n")
        if b"\r" in buf:
            n += buf.count(b"\r") - buf.count(b"\r\n")
        return n

    if isinstance(src, bytes):
        return count(src) + (1 if src and not src.endswith((b"\n", b"\r")) else 0)
    n, last = 0, b"\n"
    with open(src, "rb") as f:
        while chunk := f.read(1 << 24):
            n += count(chunk)
            if last == b"\r" and chunk.startswith(b"\n"):
                n -= 1  # a CRLF split across two chunks
            last = chunk[-1:]
    return n + (0 if last in (b"\n", b"\r") else 1)


def split_lines(text: str) -> list[str]:
    """Split text into lines the way :func:`_count_lines` counts them (not :meth:`str.splitlines`,
    which also breaks at form feeds and other separators)."""
    parts = re.split(r"\r\n|\r|\n", text)
    if parts and parts[-1] == "":
        parts.pop()
    return parts


def _read_imu_bytes(
    src: str | bytes,
    label: str,
    head: bytes,
    complete: bool,
    *,
    columns: Mapping[str, str] | None,
    column_order: Sequence[str] | None,
    units_given: Mapping[str, str | None],
    time_unit: str | None,
    timetag: str | os.PathLike[str] | TimeTag | None,
    time_offset_s: float,
    preset: str | None,
    fmt: str = "imu-csv",
) -> Part:
    rep = FileReport(path=label, format=fmt)
    rep.units = _count_lines(src)
    if rep.units == 0:
        raise IngestError(
            label, "empty file: expected IMU samples (accelerometer/gyroscope columns and time)"
        )
    layout = _sniff(head, complete, len(column_order) if column_order is not None else None)
    stem_family = _stem_family(label)
    if column_order is None and columns is None and layout.header is None and timetag is not None:
        if layout.n_fields == len(IMU_PRESETS["rtklib-demo5"].column_order):
            pr = IMU_PRESETS["rtklib-demo5"]
            column_order = pr.column_order
            units_given = {
                "acc": units_given["acc"] or pr.acc_unit,
                "gyro": units_given["gyro"] or pr.gyro_unit,
                "mag": units_given["mag"],
            }
            time_unit = time_unit or pr.time_unit
            preset = "rtklib-demo5"
            rep.notes.append("header-less 7-field file with a time-tag file: read as preset rtklib-demo5")
    try:
        roles, hints, gps_time, ignored_cols = _resolve_columns(layout, columns, column_order, stem_family)
    except KeyError as exc:
        raise IngestError(label, f"column {exc.args[0]!r} not in the header {layout.header}") from None
    if preset:
        rep.notes.append(f"preset {preset}: {IMU_PRESETS[preset].description}")
    families = [f for f in ("acc", "gyro", "mag") if any(f"{f}_{a}" in roles for a in "xyz")]
    for f in families:
        missing = [f"{f}_{a}" for a in "xyz" if f"{f}_{a}" not in roles]
        if missing:
            raise IngestError(label, f"incomplete {f} triad: no column for {', '.join(missing)}")
    time_role = "tick" if (timetag is not None and "tick" in roles) else ("t" if "t" in roles else None)
    if time_role is None and "tick" in roles:
        time_role = "tick"
    if not families or time_role is None:
        what = "accelerometer/gyroscope/magnetometer columns" if not families else "a time column"
        raise IngestError(
            label,
            f"not an IMU CSV: found no {what}. Expected a header naming a time column (t, time, "
            "timestamp, ts, seconds_elapsed, tick ...) and sensor triads (acc_x/acc_y/acc_z, ax/ay/az, "
            "AccX ...; gyro_x ..., gx ...; mag_x ..., mx ...), or columns=/column_order=/preset= "
            f"(header seen: {layout.header if layout.header else 'none'}, "
            f"{layout.n_fields} fields per line)",
        )
    if ignored_cols:
        rep.notes.append("ignored columns: " + ", ".join(repr(c) for c in ignored_cols))
    for k, v in layout.preamble_ignored.items():
        rep.ignore(k, v)

    field_of = {r: roles[r] for r in roles if r == time_role or r.split("_")[0] in families}
    tab = _read_numeric(src, layout, list(field_of.values()), rep, label, rep.units + 1)
    n = tab.n
    vals = {r: tab.values[i] for r, i in field_of.items()}
    tab.values = {}  # vals owns the columns now (lets them be freed one by one below)
    t_raw = vals[time_role]

    # ---- units
    scales: dict[str, float] = {}
    unit_used: dict[str, str] = {}
    for fam in families:
        cols = [vals[f"{fam}_{a}"] for a in "xyz"]
        table = {"acc": ACC_UNITS, "gyro": GYRO_UNITS, "mag": MAG_UNITS}[fam]
        unit = units_given.get(fam)
        how = "given"
        if unit is None and fam in hints:
            unit = _canon_unit(fam, hints[fam])
            how = f"from header ({hints[fam]!r})"
        if unit is None:
            ok = np.isfinite(cols[0]) & np.isfinite(cols[1]) & np.isfinite(cols[2])
            norms = _sample_norm(cols, ok)
            how = "guessed from the data"
            if fam == "acc":
                unit = _guess_acc(norms)
                if unit is None:
                    med = float(np.median(norms)) if norms.size else float("nan")
                    raise IngestError(
                        label,
                        f"cannot tell the accelerometer unit: median norm {med:.3g} matches neither g (~1), "
                        "m/s^2 (~9.8) nor mg (~1000); give acc_unit",
                    )
                how += f" (median norm {float(np.median(norms)):.3g})"
            elif fam == "mag":
                unit = _guess_mag(norms)
                if unit is None:
                    raise IngestError(label, "cannot tell the magnetometer unit from the data; give mag_unit")
                how += f" (median norm {float(np.median(norms)):.3g})"
            else:
                acc_u = unit_used.get("acc")
                unit = {"g": "deg/s", "mg": "mdps"}.get(acc_u or "", "rad/s")
                p99 = float(np.percentile(norms, 99)) if norms.size else 0.0
                if unit == "rad/s" and p99 > 35.0:
                    unit = "deg/s"
                how = f"guessed (companion of accelerometer unit {acc_u}; 99th percentile norm {p99:.3g})"
        unit_used[fam] = unit
        scales[fam] = table[unit]
        rep.notes.append(f"{fam} unit {unit}: {how}")

    # ---- row classification
    finite_t = np.isfinite(t_raw)
    fam_ok: dict[str, npt.NDArray[np.bool_]] = {}
    fam_range: dict[str, npt.NDArray[np.bool_]] = {}
    limits = {"acc": ACC_LIMIT, "gyro": GYRO_LIMIT, "mag": MAG_LIMIT_UT}
    for fam in families:
        ok = np.ones(n, dtype=bool)
        inr = np.ones(n, dtype=bool)
        lim = limits[fam] / scales[fam]
        for a in "xyz":
            fv = vals[f"{fam}_{a}"]
            ok &= np.isfinite(fv)
            with np.errstate(invalid="ignore"):
                inr &= ~(np.abs(fv) > lim)
        fam_ok[fam] = ok
        fam_range[fam] = inr
    imu_fams = [f for f in families if f != "mag"]
    if imu_fams:
        imu_ok = np.logical_and.reduce([fam_ok[f] for f in imu_fams])
        imu_in = np.logical_and.reduce([fam_range[f] for f in imu_fams])
    else:
        imu_ok = np.zeros(n, dtype=bool)
        imu_in = np.zeros(n, dtype=bool)
    mag_ok = fam_ok.get("mag", np.zeros(n, dtype=bool))
    mag_in = fam_range.get("mag", np.zeros(n, dtype=bool))
    malformed = tab.malformed if tab.malformed is not None else np.zeros(n, dtype=bool)
    empty = tab.empty
    use_imu = finite_t & imu_ok & imu_in & ~malformed & ~empty
    use_mag = finite_t & mag_ok & mag_in & ~malformed & ~empty
    cand = use_imu | use_mag
    nan_bad = ~cand & ~malformed & ~empty & (~finite_t | ~(imu_ok | mag_ok))
    oor_bad = ~cand & ~malformed & ~empty & ~nan_bad

    def skip_rows(mask: npt.NDArray[np.bool_], reason: SkipReason) -> None:
        idx = np.flatnonzero(mask)
        if idx.size == 0:
            return
        for j in idx[:3]:
            rep.skip(reason, tab.line_of(int(j)), _row_text(vals, int(j)))
        if idx.size > 3:
            rep.skip(reason, n=int(idx.size) - 3)

    if empty.any():
        rep.ignore("empty line", int(empty.sum()))
    skip_rows(malformed & ~empty, SkipReason.MALFORMED)
    skip_rows(nan_bad, SkipReason.NAN_FIELD)
    skip_rows(oor_bad, SkipReason.OUT_OF_RANGE)

    # ---- time order among candidate rows
    cidx = np.flatnonzero(cand)
    tc = t_raw[cidx]
    tc, jumps = rebase_segments(tc)  # counter wraps and device resets: segments, not losses
    if jumps:
        t_raw[cidx] = tc
        for j in jumps:
            rep.time_faults[j.kind] += 1
        rep.notes.append(describe(jumps, "file time units"))
    if tc.size:
        prev_max = np.empty_like(tc)
        prev_max[0] = -np.inf
        np.maximum.accumulate(tc[:-1], out=prev_max[1:])
        back = tc <= prev_max
        if back.any():
            same = np.zeros(tc.size, dtype=bool)
            same[1:] = tc[1:] == tc[:-1]
            for r in field_of:
                if r == time_role:
                    continue
                rv = vals[r][cidx]
                eq = np.zeros(tc.size, dtype=bool)
                eq[1:] = (rv[1:] == rv[:-1]) | (np.isnan(rv[1:]) & np.isnan(rv[:-1]))
                same &= eq
            dup = back & same
            skip_rows(_scatter(n, cidx[dup]), SkipReason.DUPLICATE)
            skip_rows(_scatter(n, cidx[back & ~dup]), SkipReason.NON_MONOTONIC)
            keep_c = ~back
            cidx = cidx[keep_c]
    use_imu_k = use_imu[cidx]
    use_mag_k = use_mag[cidx]
    if imu_fams:
        rep.record("imu", int(use_imu_k.sum()))
    if "mag" in families and imu_fams:
        rep.record("mag only", int((use_mag_k & ~use_imu_k).sum()))
    elif "mag" in families:
        rep.record("mag", int(use_mag_k.sum()))

    # ---- times
    tk = t_raw[cidx]
    clock: Clock
    if time_role == "tick" and timetag is None:
        tu = time_unit or (_canon_unit("t", hints["tick"]) if "tick" in hints else None) or "ms"
        t = tk * unit_scale(tu)
        clock = "device"
        rep.notes.append(f"logger tick ({tu}) used as device time: no time-tag file given")
    elif time_role == "tick":
        assert timetag is not None
        tag = timetag if isinstance(timetag, TimeTag) else read_timetag(timetag)
        tu = time_unit or (_canon_unit("t", hints["tick"]) if "tick" in hints else None) or "ms"
        ticks_ms = tk * (unit_scale(tu) * 1000.0)
        if ticks_ms.size:
            gpst = tag.ticks_to_gpst(ticks_ms, float(ticks_ms[0]), float(ticks_ms[-1]))
        else:
            gpst = np.empty(0)
        t = _gpst_to_utc_monotonic(gpst)
        clock = "utc"
        rep.notes.append(
            f"time: logger tick ({tu}) mapped to GPST by time-tag file {tag.path} "
            f"(start {tag.start_gpst:.3f}, end {tag.end_gpst:.3f} GPST s), then GPST -> UTC"
        )
    else:
        tunit: str | None = time_unit
        how = "given"
        if tunit is None and "t" in hints:
            tunit = _canon_unit("t", hints["t"])
            how = f"from header ({hints['t']!r})"
        if tunit is None:
            tunit = guess_time_unit(tk[:100_000])
            how = "guessed from the data"
        t = tk * unit_scale(tunit)
        absolute = tk.size > 0 and 1.0e9 <= float(np.median(t[: min(t.size, 1000)])) <= 4.2e9
        if absolute and gps_time:
            t = _gpst_to_utc_monotonic(t)
            clock = "utc"
            rep.notes.append(f"time unit {tunit} ({how}); GPST Unix seconds converted to UTC")
        elif absolute:
            clock = "utc"
            rep.notes.append(f"time unit {tunit} ({how}); absolute Unix time taken as UTC")
        else:
            clock = "device"
            rep.notes.append(f"time unit {tunit} ({how}); relative device time")
    if time_offset_s:
        t = t + float(time_offset_s)
        rep.notes.append(f"time offset {time_offset_s:+g} s added")
    del tk

    imu_df = None
    if imu_fams:
        sel = cidx[use_imu_k]
        whole = sel.size == n  # every row used: no copy needed
        data: dict[str, npt.NDArray[np.float64]] = {"t": t if use_imu_k.all() else t[use_imu_k]}
        for fam in ("acc", "gyro"):
            if fam not in imu_fams:
                rep.notes.append(f"no {fam} columns: {fam} fields are NaN")
            for a in "xyz":
                key = f"{fam}_{a}"
                if fam in imu_fams:
                    col = vals[key] if whole else vals[key][sel]
                    if not whole and "mag" not in families:
                        vals[key] = np.empty(0)
                    col *= scales[fam]
                    data[key] = col
                else:
                    data[key] = np.full(sel.size, np.nan)
        imu_df = pd.DataFrame(data, copy=False)
        del data
    mag_df = None
    if "mag" in families:
        sel = cidx[use_mag_k]
        mag_df = pd.DataFrame(
            {"t": t[use_mag_k]} | {f"mag_{a}_ut": vals[f"mag_{a}"][sel] * scales["mag"] for a in "xyz"},
            copy=False,
        )
    vals.clear()
    del t
    return _make_part(rep, clock, imu_df, mag_df)


def _make_part(rep: FileReport, clock: Clock, imu: pd.DataFrame | None, mag: pd.DataFrame | None) -> Part:
    """:meth:`Part.make`, without copying an IMU table that is already in the schema.

    ``coerce`` copies every column (``astype``); for a day of 100 Hz data that is 0.5 GB more at
    the peak, so a table built here with exactly the schema's columns and dtypes is attached as is.
    """
    part = Part.make(rep, clock, mag=mag)
    if imu is not None:
        in_schema = list(imu.columns) == list(IMU_COLUMNS) and all(
            str(imu[c].dtype) == d for c, d in IMU_COLUMNS.items()
        )
        part.imu = imu.reset_index(drop=True) if in_schema else coerce(imu, IMU_COLUMNS)
    return part


def _gpst_to_utc_monotonic(g: npt.NDArray[np.float64]) -> npt.NDArray[np.float64]:
    """:func:`gpst_to_utc` for increasing times: one subtraction when no leap second intervenes."""
    if g.size == 0:
        return g
    ends = gpst_to_utc(np.array([g[0], g[-1]]))
    d0, d1 = g[0] - ends[0], g[-1] - ends[1]
    if d0 == d1:
        return g - d0
    return gpst_to_utc(g)


def _scatter(n: int, idx: npt.NDArray[np.intp]) -> npt.NDArray[np.bool_]:
    m = np.zeros(n, dtype=bool)
    m[idx] = True
    return m


def _row_text(vals: Mapping[str, npt.NDArray[np.float64]], j: int) -> str:
    return ", ".join(f"{k}={v[j]:g}" for k, v in vals.items() if v.size > j)
