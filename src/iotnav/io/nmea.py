"""NMEA 0183 reader: sentences to GNSS epochs.

Sentences are decoded by `pynmeagps <https://github.com/semuconsulting/pynmeagps>`_, the
reference parser. The four sentence types that make up almost every byte of a real log (GGA,
RMC, GSA, VTG) also have a fast decoder, :func:`decode_fast`, written to give exactly what
pynmeagps gives (tested sentence by sentence on the whole gpsd corpus); it is what makes a day
of 1 Hz NMEA ingest in a few seconds. GNS, GLL and ZDA always go through pynmeagps.

Input units
-----------
The unit of accounting is the *fragment*. Each text line (split on ``\\n``; ``\\r`` and blanks
around it are stripped) is cut before every ``$`` and before every ``!`` that is followed by two
upper-case letters (AIS encapsulation, ``!AIVDM``). Then:

* a blank line is not a unit;
* a line starting with ``#`` is one unit, ignored as ``"comment"`` (gpsd log headers);
* a line holding only a number is one unit, a device timestamp (record ``"timestamp"``);
* a leading device timestamp ``12.345,`` / ``12345 `` / ``12.3<TAB>`` before the first ``$``
  is part of the line's first sentence, not a unit of its own;
* any other non-blank text before the first ``$``/``!`` is one unit, skipped as garbage;
* every piece starting at ``$``/``!`` is one unit (a sentence candidate).

So ``records + ignored + skipped == units`` where ``units`` can be counted with a regular
expression over the raw bytes (the tests do exactly that).

Sentence candidates are classified as

* ``[$!]ADDRESS,fields*hh`` with the right checksum (hex digits of either case): decoded.
  Used types (GGA, RMC, GSA, VTG, GNS, GLL, ZDA, any talker) become parts of an epoch and are
  counted under ``records`` by type without talker (``"GGA"``); types pynmeagps knows but
  iotnav does not use (GSV, TXT, GST, ``$PUBX``, ``!AIVDM`` ...) are counted under
  ``ignored`` (``"GSV"``, ``"PUBX"``, ``"VDM"``); types pynmeagps does not know are skipped as
  :attr:`SkipReason.UNKNOWN_SENTENCE`.
* wrong checksum: :attr:`SkipReason.BAD_CHECKSUM`.
* a well-formed address but no ``*hh``: :attr:`SkipReason.TRUNCATED`. Sentences without a
  checksum are *not* used: in real logs they are nearly always lines cut by a buffer overrun or
  the end of the capture, and their last field cannot be trusted.
* anything else (``$&bTXT``, binary that happens to contain ``$``): :attr:`SkipReason.GARBAGE`.
* fields that do not convert (``XXXXX`` where a number is due) or non-ASCII bytes:
  :attr:`SkipReason.MALFORMED`; latitude beyond +-90 or longitude beyond +-180:
  :attr:`SkipReason.OUT_OF_RANGE`; NaN/inf written in a number field: :attr:`SkipReason.NAN_FIELD`.

Bytes after a valid ``*hh`` up to the next ``$`` (rare; binary run-ons) do not invalidate the
sentence; their number is added to the report notes.

Epochs (fix cycles)
-------------------
:class:`NmeaEpochAssembler` groups sentences the way gpsd does: a sentence that carries a time
of day (GGA, RMC, GNS, GLL, ZDA with a non-empty time field) opens a new cycle when its time
differs from the current cycle's; a sentence without a time (GSA, VTG, or a timed type whose
time field is empty) joins the current cycle, unless that cycle already holds a sentence of the
same type (GSA excepted: one per constellation), in which case it opens a new, untimed cycle. A cycle that holds at
least one fix sentence (GGA, RMC, GNS, GLL) becomes one row of the GNSS table
(:data:`iotnav.io.schema.GNSS_COLUMNS`); cycles with no fix sentence (a lone ZDA, GSA or VTG)
give no row: ZDA still sets the date (record), the others are counted as ignored.

Field precedence inside a cycle: position from GGA, then GNS, RMC, GLL; altitude and geoid
separation from GGA then GNS (``height_m = alt_msl_m + geoid_sep_m``, NaN when the geoid
separation field is empty; iotnav applies no geoid model); speed and course from RMC, then VTG
(knots, else km/h); DOPs from the first GSA carrying them (HDOP falls back to GGA/GNS); satellites
used = GGA/GNS count, else the union of the GSA PRN lists keyed by constellation (NMEA 4.10
system id, else the talker, else the PRN range of ``GN`` sentences).
``mode`` follows gpsd: GSA's fix type when a GSA is in the cycle; else GGA (quality 0 -> 1 no
fix, else 3 with an altitude, 2 without); else GNS (all mode letters ``N`` -> 1); else RMC/GLL
(status ``V`` or mode ``N`` -> 1, else 2). ``valid`` is GGA quality > 0, else RMC/GLL status
``A`` with a mode other than ``N``, else a GNS mode other than all ``N`` -- and a position.
A cycle that is not valid keeps its row but no position (lat/lon/heights NaN): receivers fill
those fields with the last, a default or a zero position, and gpsd does not report them either.
``course_valid`` is False when the course field is empty or the receiver flags the fix invalid
(RMC status ``V``, mode ``N``).

Time
----
The date comes from RMC or ZDA. The assembler keeps the current date and moves it forward when
the time of day wraps (a time more than 12 h earlier than the previous cycle's: midnight; a time
more than 12 h later: a cycle from before midnight, the date goes back one day). ``utc`` is NaN
until a date is known. With clock ``"utc"`` (plain NMEA), ``t`` is the UTC time; cycles before
the first date get ``t`` extrapolated back from the first dated cycle over the unwrapped time of
day (their ``utc`` stays NaN); when no date is ever seen ``t`` is the unwrapped seconds of day
and the report says so. With clock ``"device"`` (timestamped logs) ``t`` is the device timestamp
of the *first* sentence of the cycle. Rows whose ``t`` does not increase past the last kept row
are dropped and their sentences counted as :attr:`SkipReason.NON_MONOTONIC`; rows with no usable
``t`` as :attr:`SkipReason.NO_TIME`.
"""

from __future__ import annotations

import datetime as _dt
import math
import os
import re
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt
import pandas as pd
import pynmeagps.nmeatypes_core as _nmt
from pynmeagps import NMEAMessage, NMEAReader

from iotnav.io.errors import IngestError
from iotnav.io.log import Clock, Part
from iotnav.io.report import FileReport, SkipReason
from iotnav.io.schema import GNSS_COLUMNS, coerce, empty_table
from iotnav.io.timeutil import guess_time_unit, unit_scale

__all__ = [
    "KNOT_MPS",
    "NmeaEpochAssembler",
    "Sentence",
    "decode_fast",
    "decode_sentence",
    "read_nmea",
    "sentence_from_message",
]

KNOT_MPS = 1852.0 / 3600.0
"""One knot in m/s (international nautical mile)."""

_NAN = math.nan
_FIX_KINDS = ("GGA", "GNS", "RMC", "GLL")
_USED_KINDS = frozenset(("GGA", "RMC", "GSA", "VTG", "GNS", "GLL", "ZDA"))
_FAST_KINDS = frozenset(("GGA", "RMC", "GSA", "VTG"))
_HALF_DAY = 43200.0
_DAY = 86400.0

# Split a line before every '$' and every '!' followed by two capitals (AIS encapsulation).
_SPLIT_RE = re.compile(rb"\$|![A-Z]{2}")
_SENTENCE_RE = re.compile(rb"[$!]([A-Za-z0-9]{2,15})(,[^*]*)?\*([0-9A-Fa-f]{2})")
_ADDRESS_RE = re.compile(rb"[$!][A-Z0-9]{2,15}(,|\s*$)")
_TS_PREFIX_RE = re.compile(rb"\s*([+-]?\d+(?:\.\d*)?)\s*[,;\t ]\s*$")
_TS_LINE_RE = re.compile(rb"\s*[+-]?\d+(?:\.\d*)?\s*")
_HEX = frozenset(b"0123456789abcdefABCDEF")

# Constellation of a GSA PRN list, by NMEA 4.10 system id and by talker.
_SYSTEM_BY_ID = {"1": "GPS", "2": "GLONASS", "3": "Galileo", "4": "BeiDou", "5": "QZSS", "6": "NavIC"}
_SYSTEM_BY_TALKER = {"GP": "GPS", "GL": "GLONASS", "GA": "Galileo", "GB": "BeiDou", "BD": "BeiDou"}
_SYSTEM_BY_TALKER.update({"GQ": "QZSS", "QZ": "QZSS", "GI": "NavIC"})


def _system_of_prn(prn: int) -> str:
    """Constellation of a PRN in a ``GN`` GSA without system id (NMEA 4.0 numbering)."""
    if 1 <= prn <= 32:
        return "GPS"
    if 33 <= prn <= 64:
        return "SBAS"
    if 65 <= prn <= 96:
        return "GLONASS"
    return "other"


@dataclass(slots=True)
class Sentence:
    """The fields of one used sentence, in SI/degrees, normalised over sentence types.

    Missing fields are NaN (floats), -1 (integer codes) or ``""`` (letters).

    Attributes
    ----------
    kind : str
        Sentence type without talker: ``GGA``, ``RMC``, ``GSA``, ``VTG``, ``GNS``, ``GLL``, ``ZDA``.
    talker : str
        Talker id (``GP``, ``GN`` ...).
    tod : float
        UTC time of day, s (NaN when the sentence has none or it is empty).
    date_days : int
        UTC date as days since 1970-01-01 (RMC, ZDA), -1 when absent.
    lat_deg, lon_deg : float
        Geodetic latitude / longitude, degrees, signed.
    alt_msl_m, geoid_sep_m : float
        Altitude above mean sea level and geoid separation, m.
    quality : int
        GGA fix quality.
    num_sv : int
        Satellites used (GGA, GNS).
    hdop, pdop, vdop : float
        Dilutions of precision.
    status : str
        RMC/GLL status letter (``A`` valid, ``V`` invalid).
    pos_mode : str
        Mode indicator (RMC/VTG/GLL one letter, GNS one letter per constellation).
    nav_mode : int
        GSA fix type (1 no fix, 2 2D, 3 3D).
    prns : tuple of int
        GSA satellites used.
    system : str
        Constellation of the GSA PRNs (``""`` when to be inferred from the PRN).
    speed_mps : float
        Speed over ground, m/s.
    course_deg : float
        Course over ground, degrees from true North.
    """

    kind: str
    talker: str
    tod: float = _NAN
    date_days: int = -1
    lat_deg: float = _NAN
    lon_deg: float = _NAN
    alt_msl_m: float = _NAN
    geoid_sep_m: float = _NAN
    quality: int = -1
    num_sv: int = -1
    hdop: float = _NAN
    pdop: float = _NAN
    vdop: float = _NAN
    status: str = ""
    pos_mode: str = ""
    nav_mode: int = -1
    prns: tuple[int, ...] = ()
    system: str = ""
    speed_mps: float = _NAN
    course_deg: float = _NAN


class _FieldError(ValueError):
    """A field that pynmeagps would refuse (non-numeric number)."""


# --------------------------------------------------------------------------------------------
# Conversions from pynmeagps values (the reference) to Sentence fields
# --------------------------------------------------------------------------------------------


def _num(v: Any) -> float:
    return float(v) if isinstance(v, (int, float)) and not isinstance(v, bool) else _NAN


def _int(v: Any) -> int:
    return int(v) if isinstance(v, int) and not isinstance(v, bool) else -1


def _tod_of(v: Any) -> float:
    if isinstance(v, _dt.time):
        return v.hour * 3600.0 + v.minute * 60.0 + v.second + v.microsecond * 1e-6
    return _NAN


def _days_of(v: Any) -> int:
    if isinstance(v, _dt.date):
        return v.toordinal() - _EPOCH_ORDINAL
    return -1


_EPOCH_ORDINAL = _dt.date(1970, 1, 1).toordinal()


def sentence_from_message(msg: NMEAMessage) -> Sentence | None:
    """Normalise a pynmeagps message of a used type into a :class:`Sentence`.

    Parameters
    ----------
    msg : pynmeagps.NMEAMessage
        A parsed sentence.

    Returns
    -------
    Sentence or None
        None when the type is not one iotnav uses.
    """
    kind = msg.msgID
    if kind not in _USED_KINDS or msg.talker == "P":
        return None
    g = msg.__dict__
    s = Sentence(kind=kind, talker=msg.talker)
    if kind in ("GGA", "RMC", "GNS", "GLL", "ZDA"):
        s.tod = _tod_of(g.get("time"))
    if kind in ("GGA", "RMC", "GNS", "GLL"):
        s.lat_deg = _num(g.get("lat"))
        s.lon_deg = _num(g.get("lon"))
    if kind in ("GGA", "GNS"):
        s.num_sv = _int(g.get("numSV"))
        s.hdop = _num(g.get("HDOP"))
        s.alt_msl_m = _num(g.get("alt"))
        s.geoid_sep_m = _num(g.get("sep"))
    if kind == "GGA":
        s.quality = _int(g.get("quality"))
    elif kind == "GNS":
        s.pos_mode = str(g.get("posMode", ""))
    elif kind == "RMC":
        s.status = str(g.get("status", ""))
        s.pos_mode = str(g.get("posMode", ""))
        s.speed_mps = _num(g.get("spd")) * KNOT_MPS
        s.course_deg = _num(g.get("cog"))
        s.date_days = _days_of(g.get("date"))
    elif kind == "GLL":
        s.status = str(g.get("status", ""))
        s.pos_mode = str(g.get("posMode", ""))
    elif kind == "VTG":
        s.course_deg = _num(g.get("cogt"))
        knots = _num(g.get("sogn"))
        kmh = _num(g.get("sogk"))
        s.speed_mps = knots * KNOT_MPS if knots == knots else kmh / 3.6
        s.pos_mode = str(g.get("posMode", ""))
    elif kind == "GSA":
        s.nav_mode = _int(g.get("navMode"))
        s.prns = tuple(p for i in range(1, 13) if isinstance(p := g.get(f"svid_{i:02d}"), int))
        s.pdop = _num(g.get("PDOP"))
        s.hdop = _num(g.get("HDOP"))
        s.vdop = _num(g.get("VDOP"))
        s.system = _SYSTEM_BY_ID.get(str(g.get("systemId", "")), "")
    elif kind == "ZDA":
        d, m, y = g.get("day"), g.get("month"), g.get("year")
        if isinstance(d, int) and isinstance(m, int) and isinstance(y, int):
            try:
                s.date_days = _dt.date(y, m, d).toordinal() - _EPOCH_ORDINAL
            except ValueError:
                s.date_days = -1
    if s.system == "":
        s.system = _SYSTEM_BY_TALKER.get(s.talker, "")
    return s


# --------------------------------------------------------------------------------------------
# Fast decoder of GGA/RMC/GSA/VTG (same results as pynmeagps, tested on the gpsd corpus)
# --------------------------------------------------------------------------------------------


def _dmm(v: str, hemi: str, neg: str) -> float:
    """pynmeagps ``LA``/``LN``: (d)ddmm.mmm -> degrees, missing when unparsable."""
    dp = v.find(".")
    if dp < 4:
        return _NAN
    try:
        deg = abs(float(v[: dp - 2])) + float(v[dp - 2 :]) / 60.0
    except ValueError:
        return _NAN
    deg = round(deg, 10)
    return -deg if hemi == neg else deg


def _tm(v: str) -> float:
    """pynmeagps ``TM``: hhmmss[.ss] -> seconds of day, missing when invalid."""
    n = len(v)
    if n >= 6 and v[:6].isdigit() and (n == 6 or (v[6] == "." and 8 <= n <= 13 and v[7:].isdigit())):
        h, m, s = int(v[0:2]), int(v[2:4]), int(v[4:6])
        if h < 24 and m < 60 and s < 62:
            frac = 0.0 if n == 6 else int(v[7:].ljust(6, "0")) * 1e-6
            if s <= 59:
                return h * 3600.0 + m * 60.0 + s + frac
    # Anything unusual: exactly what pynmeagps does (strptime), slow but rare.
    return _tod_of(_time2utc(v))


def _time2utc(v: str) -> _dt.time | str:
    try:
        if len(v) == 6:
            v = v + ".00"
        return _dt.datetime.strptime(v, "%H%M%S.%f").time()
    except (TypeError, ValueError):
        return ""


def _dt6(v: str) -> int:
    """pynmeagps ``DT``: ddmmyy -> days since 1970 (-1 when invalid)."""
    try:
        return _dt.datetime.strptime(v, "%d%m%y").date().toordinal() - _EPOCH_ORDINAL
    except (TypeError, ValueError):
        return -1


_date_cache: dict[str, int] = {}


def _date(v: str) -> int:
    d = _date_cache.get(v)
    if d is None:
        d = _dt6(v)
        if len(_date_cache) < 4096:
            _date_cache[v] = d
    return d


def decode_fast(talker: str, kind: str, fields: list[str]) -> Sentence:
    """Decode a GGA, RMC, GSA or VTG sentence without pynmeagps.

    Gives the same :class:`Sentence` as ``sentence_from_message(NMEAReader.parse(...))``,
    including which field strings are refused.

    Parameters
    ----------
    talker : str
        Talker id.
    kind : str
        ``GGA``, ``RMC``, ``GSA`` or ``VTG``.
    fields : list of str
        The comma-separated fields after the address, checksum removed.

    Returns
    -------
    Sentence

    Raises
    ------
    ValueError
        When a numeric field does not convert (pynmeagps raises then too).
    """
    n = len(fields)
    if n < 18:
        fields = fields + [""] * (18 - n)
    f = fields
    system = _SYSTEM_BY_TALKER.get(talker, "")
    # ``float``/``int`` raise ValueError on junk, exactly where pynmeagps refuses the sentence.
    if kind == "GGA":
        if f[13]:
            int(f[13])  # diffStation: pynmeagps refuses junk there too
        if f[12]:
            float(f[12])
        return Sentence(
            kind,
            talker,
            tod=_tm(f[0]) if n > 0 else _NAN,
            lat_deg=_dmm(f[1], f[2], "S") if n > 1 else _NAN,
            lon_deg=_dmm(f[3], f[4], "W") if n > 3 else _NAN,
            quality=int(f[5]) if f[5] else -1,
            num_sv=int(f[6]) if f[6] else -1,
            hdop=float(f[7]) if f[7] else _NAN,
            alt_msl_m=float(f[8]) if f[8] else _NAN,
            geoid_sep_m=float(f[10]) if f[10] else _NAN,
            system=system,
        )
    if kind == "RMC":
        if f[9]:
            float(f[9])
        return Sentence(
            kind,
            talker,
            tod=_tm(f[0]) if n > 0 else _NAN,
            status=f[1],
            lat_deg=_dmm(f[2], f[3], "S") if n > 2 else _NAN,
            lon_deg=_dmm(f[4], f[5], "W") if n > 4 else _NAN,
            speed_mps=float(f[6]) * KNOT_MPS if f[6] else _NAN,
            course_deg=float(f[7]) if f[7] else _NAN,
            date_days=_date(f[8]) if n > 8 else -1,
            pos_mode=f[11],
            system=system,
        )
    if kind == "GSA":
        return Sentence(
            kind,
            talker,
            nav_mode=int(f[1]) if f[1] else -1,
            prns=tuple(int(x) for x in f[2:14] if x),
            pdop=float(f[14]) if f[14] else _NAN,
            hdop=float(f[15]) if f[15] else _NAN,
            vdop=float(f[16]) if f[16] else _NAN,
            system=_SYSTEM_BY_ID.get(f[17], "") or system,
        )
    # VTG
    if f[2]:
        float(f[2])
    knots = float(f[4]) if f[4] else _NAN
    kmh = float(f[6]) if f[6] else _NAN
    return Sentence(
        kind,
        talker,
        course_deg=float(f[0]) if f[0] else _NAN,
        speed_mps=knots * KNOT_MPS if knots == knots else kmh / 3.6,
        pos_mode=f[8],
        system=system,
    )


def _known_type(talker: str, msgid: str) -> bool:
    """True when pynmeagps knows the sentence type (standard or proprietary)."""
    if talker == "P":
        return msgid in _nmt.NMEA_MSGIDS_PROP or any(msgid.startswith(p) for p in _nmt.NMEA_PREFIX_PROP)
    return msgid in _nmt.NMEA_MSGIDS


def _split_address(address: str) -> tuple[str, str]:
    """(talker, type) the way pynmeagps splits them: ``P`` + rest, else 2 + rest."""
    if address[:1] == "P":
        return "P", address[1:]
    return address[:2], address[2:]


def _kind_label(talker: str, msgid: str) -> str:
    return "P" + msgid if talker == "P" else msgid


def decode_sentence(text: str) -> Sentence | None:
    """Decode one checksum-verified sentence of a used type through pynmeagps.

    Parameters
    ----------
    text : str
        The sentence, ``$`` to checksum inclusive.

    Returns
    -------
    Sentence or None
        None for a type iotnav does not use.

    Raises
    ------
    ValueError
        When pynmeagps refuses a field.
    """
    try:
        msg = NMEAReader.parse(text, validate=0)
    except Exception as err:  # pynmeagps raises several types; all mean "bad fields"
        raise _FieldError(str(err)) from err
    if msg is None:
        return None
    return sentence_from_message(msg)


# --------------------------------------------------------------------------------------------
# Epoch assembly
# --------------------------------------------------------------------------------------------


@dataclass(slots=True)
class _Cycle:
    tod: float
    t_device: float
    parts: dict[str, Sentence] = field(default_factory=dict)
    gsa: list[Sentence] = field(default_factory=list)
    units: list[tuple[str, int]] = field(default_factory=list)  # (kind, unit number)


class NmeaEpochAssembler:
    """Group decoded sentences into fix cycles and build GNSS epoch rows.

    Feed sentences in stream order with :meth:`add`; :meth:`finish` returns the epochs table
    and counts every sentence in the report (records, ignored, or skipped with a reason). The
    grouping, precedence and time rules are in the module docstring.

    Parameters
    ----------
    report : FileReport
        Where counts go.
    source : str
        Value of the ``source`` column.
    """

    def __init__(self, report: FileReport, source: str = "nmea") -> None:
        self.report = report
        self.source = source
        self._cur: _Cycle | None = None
        self._rows: list[dict[str, Any]] = []
        self._row_units: list[list[tuple[str, int]]] = []
        self._day_index = 0
        self._date: int | None = None
        self._last_tod: float | None = None

    # -- input ------------------------------------------------------------------------------
    def add(self, msg: Sentence | NMEAMessage, t_device: float = _NAN, unit_no: int = -1) -> None:
        """Add one sentence.

        Parameters
        ----------
        msg : Sentence or pynmeagps.NMEAMessage
            A decoded sentence (unused types are counted as ignored).
        t_device : float
            Device time of the sentence in the caller's unit (NaN when none); scaled in
            :meth:`finish`.
        unit_no : int
            Input unit number (for examples in the report).
        """
        if isinstance(msg, NMEAMessage):
            s = sentence_from_message(msg)
            if s is None:
                self.report.ignore(_kind_label(msg.talker, msg.msgID))
                return
        else:
            s = msg
        bad = self._check(s)
        if bad is not None:
            self.report.skip(bad, unit_no, f"{s.talker}{s.kind} lat={s.lat_deg} lon={s.lon_deg}")
            return
        cur = self._cur
        timed = s.tod == s.tod
        if cur is not None:
            if timed:
                if cur.tod == s.tod:
                    self._merge(cur, s, unit_no)
                    return
                if cur.tod != cur.tod and s.kind not in cur.parts:
                    cur.tod = s.tod
                    self._merge(cur, s, unit_no)
                    return
            elif s.kind == "GSA" or s.kind not in cur.parts:
                self._merge(cur, s, unit_no)
                return
            self._close(cur)
        self._cur = _Cycle(tod=s.tod, t_device=t_device)
        self._merge(self._cur, s, unit_no)

    @staticmethod
    def _check(s: Sentence) -> SkipReason | None:
        # NaN/inf written out ("nan", "inf") are refused by the framer before decoding.
        if abs(s.lat_deg) > 90.0 or abs(s.lon_deg) > 180.0:
            return SkipReason.OUT_OF_RANGE
        if (s.lat_deg != s.lat_deg) != (s.lon_deg != s.lon_deg):
            return SkipReason.NAN_FIELD  # one coordinate without the other
        return None

    @staticmethod
    def _merge(cur: _Cycle, s: Sentence, unit_no: int) -> None:
        if s.kind == "GSA":
            cur.gsa.append(s)
        elif s.kind not in cur.parts:
            cur.parts[s.kind] = s
        cur.units.append((s.kind, unit_no))

    # -- cycle to row -----------------------------------------------------------------------
    def _close(self, cur: _Cycle) -> None:
        self._cur = None
        tod = cur.tod
        explicit = -1
        for k in ("RMC", "ZDA"):
            p = cur.parts.get(k)
            if p is not None and p.date_days >= 0:
                explicit = p.date_days
                break
        if tod == tod:
            if self._last_tod is not None:
                if tod < self._last_tod - _HALF_DAY:
                    self._day_index += 1
                    if self._date is not None:
                        self._date += 1
                elif tod > self._last_tod + _HALF_DAY:
                    self._day_index -= 1
                    if self._date is not None:
                        self._date -= 1
            self._last_tod = tod
            if explicit >= 0:
                self._date = explicit
        has_fix = not cur.parts.keys().isdisjoint(_FIX_KINDS)
        if not has_fix:
            for kind, _unit in cur.units:
                if kind == "ZDA":
                    self.report.record(kind)
                else:
                    self.report.ignore(kind)
            return
        utc = self._date * _DAY + tod if (self._date is not None and tod == tod) else _NAN
        tod_unwrapped = self._day_index * _DAY + tod
        row = self._row(cur)
        row["utc"] = utc
        row["_tod_unwrapped"] = tod_unwrapped
        row["_t_device"] = cur.t_device
        self._rows.append(row)
        self._row_units.append(cur.units)

    def _row(self, cur: _Cycle) -> dict[str, Any]:
        p = cur.parts
        gga, gns, rmc, gll, vtg = p.get("GGA"), p.get("GNS"), p.get("RMC"), p.get("GLL"), p.get("VTG")
        lat = lon = _NAN
        for s in (gga, gns, rmc, gll):
            if s is not None and s.lat_deg == s.lat_deg:
                lat, lon = s.lat_deg, s.lon_deg
                break
        alt = sep = _NAN
        for s in (gga, gns):
            if s is not None and s.alt_msl_m == s.alt_msl_m:
                alt, sep = s.alt_msl_m, s.geoid_sep_m
                break
        has_pos = lat == lat
        # validity and mode
        if gga is not None and gga.quality >= 0:
            valid = gga.quality > 0
        elif rmc is not None and rmc.status:
            valid = rmc.status == "A" and rmc.pos_mode != "N"
        elif gns is not None and gns.pos_mode:
            valid = gns.pos_mode.strip("N") != ""
        elif gll is not None and gll.status:
            valid = gll.status == "A" and gll.pos_mode != "N"
        else:
            valid = False
        valid = valid and has_pos
        mode = 0
        nav = [g.nav_mode for g in cur.gsa if g.nav_mode in (1, 2, 3)]
        if nav:
            mode = max(nav)
        elif gga is not None and gga.quality >= 0:
            mode = 1 if gga.quality == 0 else (3 if alt == alt else 2)
        elif gns is not None and gns.pos_mode:
            mode = 1 if gns.pos_mode.strip("N") == "" else (3 if alt == alt else 2)
        else:
            for s in (rmc, gll):
                if s is not None and s.status:
                    mode = 1 if (s.status != "A" or s.pos_mode == "N") else 2
                    break
        # satellites and DOPs
        num_sv = -1
        for s in (gga, gns):
            if s is not None and s.num_sv >= 0:
                num_sv = s.num_sv
                break
        if num_sv < 0 and cur.gsa:
            used = {(g.system or _system_of_prn(prn), prn) for g in cur.gsa for prn in g.prns if prn > 0}
            num_sv = len(used)
        pdop = next((g.pdop for g in cur.gsa if g.pdop == g.pdop), _NAN)
        vdop = next((g.vdop for g in cur.gsa if g.vdop == g.vdop), _NAN)
        hdop = next((g.hdop for g in cur.gsa if g.hdop == g.hdop), _NAN)
        if hdop != hdop:
            for s in (gga, gns):
                if s is not None and s.hdop == s.hdop:
                    hdop = s.hdop
                    break
        # speed and course
        speed = course = _NAN
        course_valid = False
        for s in (rmc, vtg):
            if s is None:
                continue
            if speed != speed and s.speed_mps == s.speed_mps:
                speed = s.speed_mps
            if course != course and s.course_deg == s.course_deg:
                course = s.course_deg
                flagged_bad = s.pos_mode == "N" or (s.kind == "RMC" and s.status != "A")
                course_valid = not flagged_bad
        course_rad = math.radians(course % 360.0) if course == course else _NAN
        if course_rad >= 2 * math.pi:
            course_rad = 0.0
        if not valid:
            # Receivers fill the fields of a no-fix cycle with the last, a default or a zero
            # position (SkyTraq: 0 N 0 E); gpsd reports no position then, nor does iotnav.
            lat = lon = alt = sep = _NAN
        return {
            "lat_deg": lat,
            "lon_deg": lon,
            "height_m": alt + sep,
            "alt_msl_m": alt,
            "geoid_sep_m": sep,
            "quality": gga.quality if gga is not None else -1,
            "mode": mode,
            "num_sv": num_sv,
            "pdop": pdop,
            "hdop": hdop,
            "vdop": vdop,
            "speed_mps": speed,
            "course_rad": course_rad,
            "course_valid": course_valid,
            "valid": valid,
        }

    # -- output -----------------------------------------------------------------------------
    def finish(
        self,
        clock: Clock = "utc",
        t_scale: float = 1.0,
        drop_utc: npt.ArrayLike | None = None,
        drop_tol_s: float = 0.005,
        drop_label: str = "duplicate of UBX NAV-PVT",
    ) -> pd.DataFrame:
        """Close the last cycle, count every sentence and return the epochs table.

        Parameters
        ----------
        clock : {"utc", "device"}
            ``utc``: ``t`` is UTC (see module docstring); ``device``: ``t`` is the device time
            of each cycle's first sentence times ``t_scale``.
        t_scale : float
            Seconds per device-time tick given to :meth:`add`.
        drop_utc : array_like, optional
            UTC times (s) of epochs already known from a better source; cycles within
            ``drop_tol_s`` of one are dropped and their sentences counted as ignored under
            ``"<type> (<drop_label>)"``.
        drop_tol_s : float
            Tolerance of that match, s.
        drop_label : str
            Text of the ignored kind.

        Returns
        -------
        pandas.DataFrame
            GNSS epochs, :data:`iotnav.io.schema.GNSS_COLUMNS`, ``t`` strictly increasing.
        """
        if self._cur is not None:
            self._close(self._cur)
        rows, units = self._rows, self._row_units
        self._rows, self._row_units = [], []
        rep = self.report
        if not rows:
            return empty_table(GNSS_COLUMNS)
        df = pd.DataFrame(rows)
        utc = df["utc"].to_numpy(dtype=float)
        if clock == "device":
            t = df["_t_device"].to_numpy(dtype=float) * t_scale
        else:
            unwrapped = df["_tod_unwrapped"].to_numpy(dtype=float)
            dated = np.nonzero(np.isfinite(utc))[0]
            if dated.size:
                t = utc.copy()
                i0 = dated[0]
                before = np.arange(len(t)) < i0
                t[before] = utc[i0] + (unwrapped[before] - unwrapped[i0])
                # later cycles with no date known (cannot happen once a date is set) keep NaN
            else:
                t = unwrapped
                rep.notes.append(
                    "no date (RMC/ZDA) in the NMEA: t is seconds of day (unwrapped over midnight), utc is NaN"
                )
        df["t"] = t
        keep = np.ones(len(df), dtype=bool)
        drop_set = np.sort(np.asarray(drop_utc, dtype=float)) if drop_utc is not None else None
        last = -math.inf
        for i in range(len(df)):
            ti = t[i]
            # On the UTC clock, t also places cycles from before the first date.
            u = ti if clock == "utc" else utc[i]
            if drop_set is not None and drop_set.size and u == u:
                j = int(np.searchsorted(drop_set, u))
                near = [drop_set[k] for k in (j - 1, j) if 0 <= k < drop_set.size]
                if any(abs(x - u) <= drop_tol_s for x in near):
                    keep[i] = False
                    for kind, _u in units[i]:
                        rep.ignore(f"{kind} ({drop_label})")
                    continue
            if ti != ti:
                keep[i] = False
                for _kind, u in units[i]:
                    rep.skip(SkipReason.NO_TIME, u, "fix cycle without a usable time")
                continue
            if ti <= last:
                keep[i] = False
                for _kind, u in units[i]:
                    rep.skip(SkipReason.NON_MONOTONIC, u, f"cycle time {ti!r} <= previous {last!r}")
                continue
            last = ti
            for kind, _u in units[i]:
                rep.record(kind)
        df = df.loc[keep]
        df["source"] = self.source
        return coerce(df, GNSS_COLUMNS)


# --------------------------------------------------------------------------------------------
# Framing and the reader
# --------------------------------------------------------------------------------------------


def _load(source: str | os.PathLike[str] | bytes, name: str | None) -> tuple[bytes, str]:
    if isinstance(source, (bytes, bytearray, memoryview)):
        return bytes(source), name or "<bytes>"
    path = Path(source)
    try:
        data = path.read_bytes()
    except OSError as err:
        raise IngestError(name or str(path), f"cannot read file: {err.strerror or err}") from err
    return data, name or str(path)


class _Framer:
    """Line/fragment framing shared by :func:`read_nmea` and the UBX reader."""

    def __init__(self, report: FileReport, assembler: NmeaEpochAssembler) -> None:
        self.report = report
        self.asm = assembler
        self.units = 0
        self.well_formed = 0
        self.trailing = 0
        self.cumxor = b""

    def set_data(self, data: bytes) -> None:
        """Precompute ``cumxor[i] = data[0] ^ ... ^ data[i]`` for vectorised checksums."""
        if data:
            arr = np.frombuffer(data, dtype=np.uint8)
            self.cumxor = np.bitwise_xor.accumulate(arr).tobytes()

    def sentence(self, frag: bytes, t_raw: float, unit_no: int, offset: int = -1) -> None:
        """Classify and decode one ``$``/``!`` fragment (already stripped).

        ``offset`` is the fragment's position in the bytes given to :meth:`set_data`, when known:
        the checksum then comes from the cumulative XOR table instead of a Python loop.
        """
        rep = self.report
        m = _SENTENCE_RE.match(frag)
        if m is None:
            if _ADDRESS_RE.match(frag):
                rep.skip(SkipReason.TRUNCATED, unit_no, frag.decode("latin-1"))
            else:
                rep.skip(SkipReason.GARBAGE, unit_no, frag.decode("latin-1"))
            return
        self.well_formed += 1
        end = m.end()
        if end != len(frag):
            self.trailing += 1
        if offset >= 0:
            cx = self.cumxor
            ck = cx[offset + end - 4] ^ cx[offset]
        else:
            ck = 0
            for b in frag[1 : end - 3]:
                ck ^= b
        if ck != int(m.group(3), 16):
            rep.skip(SkipReason.BAD_CHECKSUM, unit_no, frag.decode("latin-1"))
            return
        try:
            text = frag[:end].decode("ascii")
        except UnicodeDecodeError:
            rep.skip(SkipReason.MALFORMED, unit_no, frag.decode("latin-1"))
            return
        address = m.group(1).decode("ascii")
        talker, msgid = _split_address(address)
        if talker != "P" and msgid in _USED_KINDS:
            low = text.lower()
            if "nan" in low or "inf" in low:  # float() would accept them
                rep.skip(SkipReason.NAN_FIELD, unit_no, text)
                return
        if talker != "P" and msgid in _FAST_KINDS:
            fields = text[len(address) + 2 : -3].split(",")
            try:
                s: Sentence | None = decode_fast(talker, msgid, fields)
            except ValueError:
                rep.skip(SkipReason.MALFORMED, unit_no, text)
                return
        elif talker != "P" and msgid in _USED_KINDS:
            try:
                s = decode_sentence(text)
            except ValueError:
                rep.skip(SkipReason.MALFORMED, unit_no, text)
                return
        elif _known_type(talker, msgid):
            rep.ignore(_kind_label(talker, msgid))
            return
        else:
            rep.skip(SkipReason.UNKNOWN_SENTENCE, unit_no, text)
            return
        if s is None:  # pragma: no cover - used kinds always decode to a Sentence
            rep.ignore(_kind_label(talker, msgid))
            return
        self.asm.add(s, t_raw, unit_no)


def _frame_lines(data: bytes, framer: _Framer) -> list[float]:
    """Walk the lines of ``data``; return the raw device timestamps seen."""
    rep = framer.report
    stamps: list[float] = []
    t_raw = _NAN
    unit = 0
    split = _SPLIT_RE
    framer.set_data(data)
    next_off = 0
    for raw_line in data.split(b"\n"):
        off = next_off
        next_off += len(raw_line) + 1
        line = raw_line.strip()
        if not line:
            continue
        c0 = line[0]
        if c0 == 0x24 and line.count(b"$") == 1 and b"!" not in line:  # the common case
            unit += 1
            framer.sentence(line, t_raw, unit, off + len(raw_line) - len(raw_line.lstrip()))
            continue
        if c0 == 0x23:  # '#'
            unit += 1
            rep.ignore("comment")
            continue
        dollar = line.find(b"$")
        if dollar > 0 and b"!" not in line and line.count(b"$") == 1:
            # one sentence after a device timestamp (``12.345,$GPGGA...``): what the general
            # path below does for it, with the checksum from the cumulative XOR table
            pm = _TS_PREFIX_RE.fullmatch(line, 0, dollar)
            if pm is not None:
                t_raw = float(pm.group(1))
                stamps.append(t_raw)
                unit += 1
                lead = len(raw_line) - len(raw_line.lstrip())
                framer.sentence(line[dollar:], t_raw, unit, off + lead + dollar)
                continue
        starts = [m.start() for m in split.finditer(line)]
        head = line[: starts[0]] if starts else line
        if head.strip():
            if not starts and _TS_LINE_RE.fullmatch(line):
                unit += 1
                t_raw = float(line)
                stamps.append(t_raw)
                rep.record("timestamp")
                continue
            pm = _TS_PREFIX_RE.fullmatch(head) if starts else None
            if pm is not None:
                t_raw = float(pm.group(1))
                stamps.append(t_raw)
            else:
                unit += 1
                rep.skip(SkipReason.GARBAGE, unit, head.decode("latin-1"))
        for i, a in enumerate(starts):
            b = starts[i + 1] if i + 1 < len(starts) else len(line)
            unit += 1
            framer.sentence(line[a:b].strip(), t_raw, unit)
    framer.units = unit
    return stamps


def read_nmea(
    source: str | os.PathLike[str] | bytes,
    *,
    time_unit: str | None = None,
    name: str | None = None,
) -> Part:
    """Read an NMEA 0183 log (plain or with device timestamps) into GNSS epochs.

    Parameters
    ----------
    source : str, os.PathLike or bytes
        A file path or the raw bytes.
    time_unit : {"s", "ms", "us", "ns"}, optional
        Unit of device timestamps, when the log has them; guessed from their steps
        (:func:`iotnav.io.timeutil.guess_time_unit`) when omitted.
    name : str, optional
        Name used in the report and errors (defaults to the path, or ``"<bytes>"``).

    Returns
    -------
    Part
        ``gnss`` epochs (one row per fix cycle; see the module docstring for the rules),
        clock ``"utc"`` for plain NMEA, ``"device"`` when lines carry device timestamps
        (prefix ``12.345,$GPGGA...`` / ``12345 $GPGGA...`` / tab, or timestamp-only lines
        applying to the sentences that follow). The report counts every unit (module docstring).

    Raises
    ------
    IngestError
        When the file cannot be read or holds no NMEA sentence at all.
    """
    data, label = _load(source, name)
    rep = FileReport(path=label, format="nmea")
    asm = NmeaEpochAssembler(rep, source="nmea")
    framer = _Framer(rep, asm)
    stamps = _frame_lines(data, framer)
    rep.units = framer.units
    if framer.well_formed == 0:
        raise IngestError(
            label,
            "no NMEA 0183 sentences found; expected lines like '$GPGGA,...*hh' "
            "(optionally prefixed by a device timestamp)",
        )
    if framer.trailing:
        rep.notes.append(f"{framer.trailing} sentences had bytes after their checksum (ignored)")
    clock: Clock = "utc"
    scale = 1.0
    if stamps:
        clock = "device"
        rep.format = "nmea-timestamped"
        unit = time_unit or guess_time_unit(np.asarray(stamps, dtype=float))
        scale = unit_scale(unit)
        how = "given" if time_unit else "detected"
        rep.notes.append(f"device timestamps in {unit} ({how}); epoch t = first sentence of the cycle")
    gnss = asm.finish(clock=clock, t_scale=scale)
    return Part.make(rep, clock, gnss=gnss)
