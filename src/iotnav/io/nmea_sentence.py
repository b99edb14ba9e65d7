"""NMEA 0183 sentences: decoding one sentence into a :class:`Sentence` (part of :mod:`iotnav.io.nmea`).

Two decoders give the same fields: :func:`sentence_from_message` converts what
`pynmeagps <https://github.com/semuconsulting/pynmeagps>`_, the reference parser, returns, and
:func:`decode_fast` decodes the four types that make up almost every byte of a real log (GGA,
RMC, GSA, VTG) directly from the comma-separated fields (tested sentence by sentence against
pynmeagps on the gpsd corpus). :func:`decode_sentence` frames, checks and decodes one text
sentence. Units on the way out: degrees (WGS-84 latitude/longitude), metres, m/s (from knots
or km/h), degrees of course, seconds of the UTC day. The classification of bad sentences and
the reader's accounting are stated in :mod:`iotnav.io.nmea`.
"""

from __future__ import annotations

import datetime as _dt
import math
from dataclasses import dataclass
from typing import Any

import pynmeagps.nmeatypes_core as _nmt
from pynmeagps import NMEAMessage, NMEAReader

KNOT_MPS = 1852.0 / 3600.0
"""One knot in m/s (international nautical mile)."""

_NAN = math.nan
_USED_KINDS = frozenset(("GGA", "RMC", "GSA", "VTG", "GNS", "GLL", "ZDA"))

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
