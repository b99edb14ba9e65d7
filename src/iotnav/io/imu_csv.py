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
"""

from __future__ import annotations

import bisect
import contextlib
import math
import os
import re
import sys
from collections.abc import Iterator, Mapping, Sequence
from dataclasses import dataclass
from io import BytesIO
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt
import pandas as pd
import pyarrow as pa
import pyarrow.compute as pc
import pyarrow.csv as pacsv

from iotnav.io.errors import IngestError
from iotnav.io.log import Clock, Part
from iotnav.io.report import FileReport, SkipReason
from iotnav.io.schema import IMU_COLUMNS, coerce
from iotnav.io.timefaults import describe, rebase_segments
from iotnav.io.timetag import TimeTag, read_timetag
from iotnav.io.timeutil import gpst_to_utc, guess_time_unit, unit_scale

G0 = 9.80665  # standard gravity, m/s^2

#: Unit name -> factor to SI (m/s^2, rad/s) or to microtesla.
ACC_UNITS: dict[str, float] = {"m/s^2": 1.0, "g": G0, "mg": G0 * 1e-3}
GYRO_UNITS: dict[str, float] = {"rad/s": 1.0, "deg/s": math.pi / 180.0, "mdps": math.pi / 180.0 * 1e-3}
MAG_UNITS: dict[str, float] = {"uT": 1.0, "mG": 0.1, "gauss": 100.0, "nT": 1e-3, "T": 1e6}

#: Plausibility limits in SI units (a component beyond them is ``OUT_OF_RANGE``).
ACC_LIMIT = 50.0 * G0
GYRO_LIMIT = 50.0
MAG_LIMIT_UT = 10_000.0

_ACC_ALIASES = {
    "g": "g",
    "mg": "mg",
    **dict.fromkeys(
        ["m/s^2", "m/s2", "ms2", "mps2", "m_s2", "m_s^2", "ms^-2", "ms-2", "m/s/s", "mss", "ms^2", "m/s²"],
        "m/s^2",
    ),
}
_GYRO_ALIASES = {
    **dict.fromkeys(["deg/s", "dps", "degps", "deg_s", "°/s", "degs", "degree/s", "degrees/s"], "deg/s"),
    **dict.fromkeys(["mdps", "mdeg/s", "mdeg_s"], "mdps"),
    **dict.fromkeys(["rad/s", "rads", "rad_s", "radps", "rps", "rad/sec"], "rad/s"),
}
_MAG_ALIASES = {
    **dict.fromkeys(["ut", "µt", "μt", "microtesla", "utesla"], "uT"),
    **dict.fromkeys(["mg", "mgauss", "milligauss"], "mG"),
    **dict.fromkeys(["g", "gauss", "gs"], "gauss"),
    "nt": "nT",
    **dict.fromkeys(["t", "tesla"], "T"),
}
_TIME_ALIASES = {
    **dict.fromkeys(["s", "sec", "secs", "seconds"], "s"),
    **dict.fromkeys(["ms", "msec"], "ms"),
    **dict.fromkeys(["us", "µs", "μs", "usec"], "us"),
    **dict.fromkeys(["ns", "nsec"], "ns"),
}
_ALIASES: dict[str, dict[str, str]] = {
    "acc": _ACC_ALIASES,
    "gyro": _GYRO_ALIASES,
    "mag": _MAG_ALIASES,
    "t": _TIME_ALIASES,
    "tick": _TIME_ALIASES,
}
_ALL_UNIT_TOKENS = sorted({k for d in _ALIASES.values() for k in d}, key=len, reverse=True)
_SUFFIX_RE = re.compile(r"^(.+?)[_ ](" + "|".join(re.escape(u) for u in _ALL_UNIT_TOKENS) + r")$")
_BRACKET_RE = re.compile(r"^(.*?)\s*[\[\(\{]([^\]\)\}]*)[\]\)\}]\s*$")

_FAMILY_RES = {
    "acc": re.compile(
        r"^(?:acc|accel|accl|accelerometer|acceleration|a|f|linacc|totalacc|totalacceleration)([xyz])$"
        r"|^([xyz])(?:acc|accel)$"
    ),
    "gyro": re.compile(
        r"^(?:gyro|gyr|gyroscope|g|w|omega|angvel|angularvelocity|angularrate|rot|rotationrate|rate)([xyz])$"
        r"|^([xyz])(?:gyro|gyr)$"
    ),
    "mag": re.compile(r"^(?:mag|magn|magnetometer|magneticfield|magfield|m|b)([xyz])$|^([xyz])(?:mag)$"),
}
#: Time column names, by preference (absolute times first).
_TIME_NAMES = [
    "time",
    "timestamp",
    "t",
    "ts",
    "utc",
    "unixtime",
    "unix",
    "epoch",
    "gpst",
    "gpstime",
    "gpsts",
    "timeutc",
    "sampletime",
    "secondselapsed",
    "elapsed",
    "elapsedtime",
    "seconds",
    "sec",
]
_TICK_NAMES = ["tick", "ticks", "imutick", "systick", "tickms"]
_STEM_FAMILY = {
    "accelerometer": "acc",
    "totalacceleration": "acc",
    "gyroscope": "gyro",
    "magnetometer": "mag",
}

_ROLES = (*(f"{f}_{a}" for f in ("acc", "gyro", "mag") for a in "xyz"), "t", "tick")
_SKIP_ROLES = {"", "-", "skip", "ignore", "_"}
_NUM_RE = r"^[-+]?([0-9]+\.?[0-9]*|\.[0-9]+)([eE][-+]?[0-9]+)?$"
_NANTOK_RE = r"(?i)^[-+]?(nan|inf|infinity|null|none|n/a|na)?$"


@dataclass(frozen=True)
class ImuPreset:
    """A named layout of a header-less IMU file.

    Attributes
    ----------
    column_order : tuple of str
        Role of each field (``acc_x`` ... ``gyro_z``, ``mag_x`` ..., ``t``, ``tick``, ``"-"`` to skip).
    acc_unit, gyro_unit, mag_unit, time_unit : str or None
        Units of the fields (see :data:`ACC_UNITS`, :data:`GYRO_UNITS`, :data:`MAG_UNITS`).
    description : str
        Where the layout comes from.
    """

    column_order: tuple[str, ...]
    acc_unit: str | None = None
    gyro_unit: str | None = None
    mag_unit: str | None = None
    time_unit: str | None = None
    description: str = ""


#: Named layouts usable as ``read_imu_csv(path, preset=...)``.
IMU_PRESETS: dict[str, ImuPreset] = {
    "rtklib-demo5": ImuPreset(
        column_order=("acc_x", "acc_y", "acc_z", "gyro_x", "gyro_y", "gyro_z", "tick"),
        acc_unit="g",
        gyro_unit="deg/s",
        time_unit="ms",
        description=(
            "rtklibexplorer GNSS_IMU logger: 7 fields, no header, acceleration in g, rate in deg/s, "
            "tick in ms since power-up; timed by the RTKLIB demo5 '.tag' file"
        ),
    ),
}


# --------------------------------------------------------------------------------------------
# Column names and units
# --------------------------------------------------------------------------------------------


def _canon_unit(family: str, unit: str | None) -> str | None:
    if unit is None:
        return None
    u = unit.strip().replace(" ", "")
    aliases = _ALIASES[family]
    if family == "mag" and u in ("mG", "MG"):
        return "mG"
    return aliases.get(u.lower()) if u.lower() in aliases else aliases.get(u)


def _check_unit(family: str, unit: str | None, where: str) -> str | None:
    """Validate an explicit unit (raises ValueError naming the allowed ones)."""
    if unit is None:
        return None
    table = {"acc": ACC_UNITS, "gyro": GYRO_UNITS, "mag": MAG_UNITS}.get(family)
    if table is not None and unit in table:
        return unit
    canon = _canon_unit(family, unit)
    if canon is None:
        allowed = sorted(table) if table is not None else ["s", "ms", "us", "ns"]
        raise ValueError(f"unknown {where} {unit!r}; expected one of {', '.join(allowed)}")
    return canon


def _norm(name: str) -> str:
    return re.sub(r"[^0-9a-z]", "", name.lower())


def _name_candidates(name: str) -> list[tuple[str, str | None]]:
    """``(normalised base, unit hint)`` readings of a header name, most specific first."""
    raw = name.strip().strip("\"'").strip()
    out: list[tuple[str, str | None]] = []
    m = _BRACKET_RE.match(raw)
    if m and m.group(1):
        out.append((_norm(m.group(1)), m.group(2).strip()))
    low = raw.lower()
    m2 = _SUFFIX_RE.match(low)
    if m2:
        # keep the original case of the unit (mG vs mg matters for magnetometers)
        unit = raw[len(raw) - len(m2.group(2)) :]
        out.append((_norm(m2.group(1)), unit))
    out.append((_norm(raw), None))
    return out


def _role_of(name: str, stem_family: str | None) -> tuple[str, str | None, bool] | None:
    """Role, unit hint and GPST flag of a header name, or None."""
    for base, unit in _name_candidates(name):
        if not base:
            continue
        for fam, rx in _FAMILY_RES.items():
            m = rx.match(base)
            if m:
                axis = m.group(1) or m.group(2)
                return f"{fam}_{axis}", unit, False
        if base in ("x", "y", "z") and stem_family is not None:
            return f"{stem_family}_{base}", unit, False
        if base in _TICK_NAMES:
            return "tick", unit, False
        if base in _TIME_NAMES or base.endswith("timestamp") or base in ("gpsts", "gpsttime"):
            return "t", unit, "gps" in base
    return None


def _stem_family(path: str) -> str | None:
    stem = _norm(Path(path).stem)
    for key, fam in _STEM_FAMILY.items():
        if stem.startswith(key):
            return fam
    return None


# --------------------------------------------------------------------------------------------
# Sniffing
# --------------------------------------------------------------------------------------------


def _is_number(tok: str) -> bool:
    t = tok.strip().strip("\"'")
    if not t:
        return True  # an empty field is data (missing), not a name
    try:
        float(t)
    except ValueError:
        return False
    return True


@dataclass
class _Layout:
    delimiter: str
    skip_rows: int  # physical lines before the first data line (preamble + header)
    n_fields: int
    header: list[str] | None
    preamble_ignored: dict[str, int]


_PREAMBLE = ("#", "%", "//", ";")


def _sniff(head: bytes, complete: bool, n_fields_hint: int | None) -> _Layout:
    text = head.decode("utf-8", errors="replace")
    if text.startswith("\ufeff"):
        text = text[1:]
    lines = text.splitlines()
    if not complete and lines:
        lines = lines[:-1]  # possibly cut in the middle
    i = 0
    comments: list[str] = []
    blank = 0
    while i < len(lines) and (not lines[i].strip() or lines[i].lstrip().startswith(_PREAMBLE)):
        if lines[i].strip():
            comments.append(lines[i])
        else:
            blank += 1
        i += 1
    body = [ln for ln in lines[i : i + 200] if ln.strip()]
    delim = ","
    best = -1.0
    for d in (",", ";", "\t", "|", " "):
        counts = [ln.count(d) for ln in body[:50]] or [0]
        if max(counts) == 0:
            continue
        mode = max(set(counts), key=counts.count)
        score = counts.count(mode) / len(counts) + (0.01 if d == "," else 0.0)
        if mode > 0 and score > best:
            delim, best = d, score
    field_counts = [ln.count(delim) + 1 for ln in body[:200]]
    n_mode = max(set(field_counts), key=field_counts.count) if field_counts else 0
    header: list[str] | None = None
    skip = i
    ignored = {"comment": len(comments) - 0, "blank": blank}
    first = lines[i] if i < len(lines) else ""
    toks = [t.strip().strip("\"'") for t in first.split(delim)] if first else []
    if toks and not all(_is_number(t) for t in toks):
        header = toks
        skip = i + 1
        ignored["header"] = 1
    elif comments:
        # a commented header just before the data: "# gpst_s,acc_x_g,..."
        last = comments[-1].lstrip().lstrip("#%/;").strip()
        ctoks = [t.strip().strip("\"'") for t in last.split(delim)]
        if len(ctoks) == (n_fields_hint or n_mode) and not any(_is_number(t) for t in ctoks):
            header = ctoks
            ignored["comment"] -= 1
            ignored["header"] = 1
    n_fields = n_fields_hint or (len(header) if header else n_mode)
    if header is not None and n_fields_hint is None and n_mode == len(header) + 1 and body:
        if all(ln.rstrip().endswith(delim) for ln in body[1:20] or body):
            header = [*header, ""]  # consistent trailing delimiter
            n_fields = len(header)
    return _Layout(delim, skip, max(n_fields, 1), header, {k: v for k, v in ignored.items() if v})


# --------------------------------------------------------------------------------------------
# Fast numeric reading
# --------------------------------------------------------------------------------------------


@dataclass
class _Table:
    values: dict[int, npt.NDArray[np.float64]]  # field index -> float column (NaN for missing)
    malformed: npt.NDArray[np.bool_] | None  # rows with a needed field that is not a number
    empty: npt.NDArray[np.bool_]  # rows whose needed fields are all missing
    n: int
    first_line: int  # physical line number (1-based) of the first data line
    bad_lines: list[int]  # physical line numbers consumed by the invalid-row handler

    def line_of(self, row: int) -> int:
        """Physical line number of data row ``row``."""
        k = 0
        while True:
            line = self.first_line + row + k
            k_new = bisect.bisect_right(self.bad_lines, line)
            if k_new == k:
                return line
            k = k_new


def _read_numeric(
    src: str | bytes,
    layout: _Layout,
    needed: Sequence[int],
    rep: FileReport,
    label: str,
    capacity: int,
) -> _Table:
    """Read the ``needed`` fields of every row as float64; count rows of the wrong width.

    The file is streamed block by block (:func:`pyarrow.csv.open_csv`) into preallocated NumPy
    arrays of ``capacity`` rows (the physical line count), so Arrow never holds more than one
    block. Fields are parsed as float64; if a needed field is not a number, the file is read again
    with those fields as bytes and classified by vectorised pattern matching.
    """
    names = [f"c{i}" for i in range(layout.n_fields)]
    wanted = [names[i] for i in sorted(set(needed))]
    bad_lines: list[int] = []

    def on_invalid(row: Any) -> str:
        text = row.text or ""
        where = int(row.number) if row.number is not None else -1
        bad_lines.append(where)
        if text.lstrip().startswith(_PREAMBLE):
            rep.ignore("comment")
        elif not text.strip():
            rep.ignore("empty line")
        else:
            rep.skip(SkipReason.TRUNCATED, where, text)
        return "skip"

    snapshot = (rep.skipped.copy(), rep.ignored.copy(), {k: list(v) for k, v in rep.examples.items()})

    def stream(
        col_type: pa.DataType, encoding: str
    ) -> tuple[dict[int, npt.NDArray[np.float64]], npt.NDArray[np.bool_] | None, int]:
        bad_lines.clear()
        rep.skipped, rep.ignored = snapshot[0].copy(), snapshot[1].copy()
        rep.examples = {k: list(v) for k, v in snapshot[2].items()}
        values = {int(c[1:]): np.empty(capacity, dtype=np.float64) for c in wanted}
        malformed = np.zeros(capacity, dtype=bool) if col_type == pa.binary() else None
        reader = pacsv.open_csv(
            BytesIO(src) if isinstance(src, bytes) else src,
            read_options=pacsv.ReadOptions(
                column_names=names,
                skip_rows=layout.skip_rows,
                use_threads=False,
                block_size=1 << 22,
                encoding=encoding,
            ),
            parse_options=pacsv.ParseOptions(
                delimiter=layout.delimiter,
                quote_char=False,
                ignore_empty_lines=False,
                invalid_row_handler=on_invalid,
            ),
            convert_options=pacsv.ConvertOptions(
                column_types=dict.fromkeys(wanted, col_type),
                include_columns=wanted,
                null_values=[""],
                strings_can_be_null=True,
                check_utf8=False,
            ),
        )
        pos = 0
        for batch in reader:
            m = batch.num_rows
            if pos + m > capacity:  # cannot happen with capacity = line count; be safe
                raise IngestError(label, "more rows than lines while parsing (internal error)")
            for c in wanted:
                col = batch.column(c)
                if malformed is None:
                    _fill_float(values[int(c[1:])], pos, col)
                else:
                    txt = pc.replace_substring_regex(col, r"^[ \t\r]+|[ \t\r]+$", "")
                    is_num = pc.fill_null(pc.match_substring_regex(txt, _NUM_RE), False)
                    is_nan = pc.fill_null(pc.match_substring_regex(txt, _NANTOK_RE), True)
                    num = pc.cast(pc.if_else(is_num, txt, pa.scalar(None, pa.binary())), pa.float64())
                    _fill_float(values[int(c[1:])], pos, num)
                    malformed[pos : pos + m] |= ~(
                        np.asarray(is_num.to_numpy(zero_copy_only=False), bool)
                        | np.asarray(is_nan.to_numpy(zero_copy_only=False), bool)
                    )
            pos += m
        return values, malformed, pos

    # Attempts: float columns as UTF-8; a damaged line that is not valid UTF-8 makes pyarrow fail
    # before our row handler runs ("CSV parse error"), so the file is then re-read as latin-1
    # (every byte decodes; slower); a field that is not a number switches to the bytes path.
    col_type, encoding = pa.float64(), "utf8"
    while True:
        try:
            with _quiet_row_decode_errors():
                values, malformed, n = stream(col_type, encoding)
            break
        except pa.ArrowInvalid as exc:
            msg = str(exc).lower()
            if ("conversion error" in msg or "invalid value" in msg) and col_type == pa.float64():
                col_type = pa.binary()
            elif "parse error" in msg and encoding == "utf8":
                encoding = "latin-1"
            else:
                raise IngestError(label, f"cannot parse as delimited text: {exc}") from None
        except (pa.ArrowException, OSError, UnicodeError) as exc:
            raise IngestError(label, f"cannot parse as delimited text: {exc}") from None
    values = {k: v[:n] for k, v in values.items()}
    if malformed is not None:
        malformed = malformed[:n]
    empty = np.ones(n, dtype=bool)
    for v in values.values():
        empty &= np.isnan(v)
    if malformed is not None:
        empty &= ~malformed
    return _Table(values, malformed, empty, n, layout.skip_rows + 1, sorted(b for b in bad_lines if b >= 0))


@contextlib.contextmanager
def _quiet_row_decode_errors() -> Iterator[None]:
    """Silence the 'exception ignored' report pyarrow emits when it cannot decode an invalid row's
    text for the row handler (the read then fails and is retried as latin-1)."""
    previous = sys.unraisablehook

    def hook(unraisable: Any) -> None:
        if not isinstance(unraisable.exc_value, UnicodeDecodeError):
            previous(unraisable)

    sys.unraisablehook = hook
    try:
        yield
    finally:
        sys.unraisablehook = previous


def _fill_float(out: npt.NDArray[np.float64], pos: int, col: pa.Array | pa.ChunkedArray) -> None:
    """Write an Arrow float column into ``out[pos:]``, nulls as NaN."""
    chunks = col.chunks if isinstance(col, pa.ChunkedArray) else [col]
    for c in chunks:
        if c.null_count:
            c = pc.fill_null(c, np.nan)
        out[pos : pos + len(c)] = c.to_numpy(zero_copy_only=False)
        pos += len(c)


# --------------------------------------------------------------------------------------------
# Unit guesses
# --------------------------------------------------------------------------------------------


def _sample_norm(
    cols: Sequence[npt.NDArray[np.float64]], ok: npt.NDArray[np.bool_]
) -> npt.NDArray[np.float64]:
    idx = np.flatnonzero(ok)
    if idx.size > 200_000:
        idx = idx[:: idx.size // 200_000]
    return np.sqrt(sum(c[idx] ** 2 for c in cols))  # type: ignore[return-value]


def _guess_acc(norms: npt.NDArray[np.float64]) -> str | None:
    if norms.size == 0:
        return None
    m = float(np.median(norms))
    for lo, hi, unit in ((0.5, 2.0, "g"), (5.0, 20.0, "m/s^2"), (500.0, 2000.0, "mg")):
        if lo <= m <= hi:
            return unit
    return None


def _guess_mag(norms: npt.NDArray[np.float64]) -> str | None:
    if norms.size == 0:
        return None
    m = float(np.median(norms))
    for lo, hi, unit in (
        (5.0, 150.0, "uT"),
        (150.0, 2000.0, "mG"),
        (0.05, 1.5, "gauss"),
        (5e3, 2e5, "nT"),
        (5e-6, 2e-4, "T"),
    ):
        if lo <= m <= hi:
            return unit
    return None


# --------------------------------------------------------------------------------------------
# Public reader
# --------------------------------------------------------------------------------------------


def _resolve_columns(
    layout: _Layout,
    columns: Mapping[str, str] | None,
    column_order: Sequence[str] | None,
    stem_family: str | None,
) -> tuple[dict[str, int], dict[str, str], bool, list[str]]:
    """Role -> field index, unit hints by family, GPST flag of the time column, ignored names."""
    roles: dict[str, int] = {}
    hints: dict[str, str] = {}
    gps = False
    ignored: list[str] = []
    if column_order is not None:
        for i, r in enumerate(column_order):
            rr = (r or "").strip()
            rr = "mag_" + rr[4] if rr.startswith("mag_") and rr.endswith("_ut") else rr
            rr = "t" if rr in ("time", "timestamp") else rr
            if rr.lower() in _SKIP_ROLES:
                continue
            if rr not in _ROLES:
                ignored.append(rr)
                continue
            roles[rr] = i
        return roles, hints, gps, ignored
    header = layout.header or []
    if columns is not None:
        lookup = {h: i for i, h in enumerate(header)}
        for role, col in columns.items():
            r = "mag_" + role[4] if role.startswith("mag_") and role.endswith("_ut") else role
            r = "t" if r in ("time", "timestamp") else r
            if r not in _ROLES:
                raise ValueError(f"unknown column role {role!r}; expected one of {', '.join(_ROLES)}")
            if col not in lookup:
                raise KeyError(col)
            roles[r] = lookup[col]
            got = _role_of(col, stem_family)
            if got is not None and got[1] is not None:
                hints.setdefault(r.split("_")[0] if r not in ("t", "tick") else r, got[1])
            if r == "t":
                gps = "gps" in _norm(col)
    time_rank: tuple[int, int] | None = None
    for i, h in enumerate(header):
        if i in roles.values():
            continue
        got = _role_of(h, stem_family)
        if got is None or (columns is not None and got[0] in roles):
            if h:
                ignored.append(h)
            continue
        role, unit, is_gps = got
        if role == "t":
            cands = [c for c, _ in _name_candidates(h)]
            rank = min((_TIME_NAMES.index(c) for c in cands if c in _TIME_NAMES), default=len(_TIME_NAMES))
            key = (rank, i)
            if time_rank is not None and key >= time_rank:
                ignored.append(h)
                continue
            if "t" in roles:
                ignored.append(header[roles["t"]])
            time_rank = key
            gps = is_gps
        elif role in roles:
            ignored.append(h)
            continue
        roles[role] = i
        fam = role if role in ("t", "tick") else role.split("_")[0]
        if unit is not None:
            if role in ("t", "tick"):
                hints[role] = unit
            else:
                hints.setdefault(fam, unit)
    return roles, hints, gps, ignored


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
