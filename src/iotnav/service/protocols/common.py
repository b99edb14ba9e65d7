"""Records and results shared by every decoder.

Units follow the package conventions (SI and radians inside, degrees for latitude and
longitude); each decoder converts its protocol's units (km/h, knots, degrees of course) once.
"""

from __future__ import annotations

import hashlib
import json
import math
from dataclasses import dataclass, field
from typing import Any

KNOT_MPS = 1852.0 / 3600.0
"""One knot in m/s (international nautical mile, 1852 m, per hour)."""
KMH_MPS = 1000.0 / 3600.0
"""One km/h in m/s."""


@dataclass(frozen=True)
class Fix:
    """One position report as a device sent it.

    Attributes
    ----------
    device : str
        The device's unique id (IMEI for Teltonika, ``id`` for OsmAnd, ``user/device`` or
        ``tid`` for OwnTracks).
    t : float
        Fix time, seconds since 1970-01-01 UTC.
    lat_deg, lon_deg : float
        WGS84 latitude and longitude, degrees.
    height_m : float
        Altitude as the protocol reports it (metres; NaN when absent).
    speed_mps : float
        Ground speed, m/s (NaN when absent).
    course_rad : float
        Course over ground from North towards East, rad (NaN when absent).
    h_acc_m : float
        Horizontal accuracy the device reports, m (NaN when absent).
    num_sv : int
        Satellites used (-1 when absent).
    hdop : float
        Horizontal dilution of precision (NaN when absent).
    valid : bool
        The device claims a valid fix.
    attributes : dict
        Everything else the message carried (IO elements, battery, ...), JSON-serialisable.
    key : str
        De-duplication key of this record (hex digest of the bytes that encode it and the
        device id): a record sent twice has the same key.
    """

    device: str
    t: float
    lat_deg: float
    lon_deg: float
    height_m: float = math.nan
    speed_mps: float = math.nan
    course_rad: float = math.nan
    h_acc_m: float = math.nan
    num_sv: int = -1
    hdop: float = math.nan
    valid: bool = True
    attributes: dict[str, Any] = field(default_factory=dict)
    key: str = ""


@dataclass(frozen=True)
class Decoded:
    """A message decoded: its records, the bytes to answer, the bytes of input it used."""

    records: list[Fix]
    answer: bytes
    consumed: int
    device: str | None = None


@dataclass(frozen=True)
class Incomplete:
    """A stream framing needs at least ``need`` more bytes before it can decide."""

    need: int


@dataclass(frozen=True)
class Rejected:
    """Input refused: ``reason`` is a short machine-readable tag, ``detail`` says why.

    ``answer`` is what to send back before closing (may be empty); ``close`` tells the
    transport to drop the connection.
    """

    reason: str
    detail: str
    answer: bytes = b""
    close: bool = True


Result = Decoded | Incomplete | Rejected


def record_key(device: str, data: bytes) -> str:
    """De-duplication key of a record: SHA-256 of the device id and the record's bytes, hex."""
    return hashlib.sha256(device.encode("utf-8", "replace") + b"\x00" + data).hexdigest()


def finite_or_nan(x: Any) -> float:
    """``float(x)`` if it is a finite number, else NaN (never raises)."""
    try:
        v = float(x)
    except (TypeError, ValueError, OverflowError):
        return math.nan
    return v if math.isfinite(v) else math.nan


#: Fix times accepted, s since 1970 UTC: 2000-01-01 to 2100-01-01 (anything else is a
#: corrupt or unset clock).
T_MIN = 946684800.0
T_MAX = 4102444800.0


def plausible_time(t: float) -> bool:
    """``t`` (s since 1970 UTC) lies in [:data:`T_MIN`, :data:`T_MAX`)."""
    return T_MIN <= t < T_MAX


def json_object(body: bytes, limit: int, answer: bytes) -> dict[str, Any] | Rejected:
    """``body`` parsed as a JSON object, or a :class:`Rejected` (``too_large``, ``bad_json``) with ``answer``."""
    if len(body) > limit:
        return Rejected("too_large", f"body of {len(body)} bytes (limit {limit})", answer)
    try:
        doc = json.loads(body)
    except (ValueError, RecursionError) as exc:
        return Rejected("bad_json", f"not JSON: {str(exc)[:80]}", answer)
    if not isinstance(doc, dict):
        return Rejected("bad_json", "JSON body is not an object", answer)
    return doc
