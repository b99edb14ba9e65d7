"""OsmAnd protocol (Traccar Client and many apps): one position per HTTP request.

Source: Traccar, "OsmAnd protocol", https://www.traccar.org/osmand/ and the published test
requests of Traccar's ``OsmAndProtocolDecoderTest`` (used as test vectors, with their
source, in ``tests/test_service_protocols.py``).

Query (or form body) form
    ``id`` (or ``deviceid``) mandatory; ``lat``, ``lon`` degrees (or ``location=lat,lon``);
    ``timestamp`` as Unix seconds, Unix milliseconds (a value above 2**31 - 1 is taken as
    ms, as Traccar does), ISO 8601 or ``YYYY-MM-DD HH:MM:SS`` (UTC); ``speed`` in knots by
    default (Traccar's default unit for this form; the unit is a parameter:
    ``speed_unit="kn" | "kmh" | "mps"``); ``bearing`` or ``heading`` degrees; ``altitude`` m;
    ``accuracy`` m; ``hdop``; ``batt`` percent; ``valid`` (``true``/``1``). Every other
    parameter is kept in :attr:`Fix.attributes`.

JSON form (Traccar Client 9 and later, ``Content-Type: application/json``)
    ``{"location": {"timestamp": ISO 8601, "coords": {"latitude", "longitude", "accuracy" m,
    "speed" m/s, "heading" degrees, "altitude" m}, "battery": {"level": 0..1, ...}, "is_moving",
    "odometer", "event", "activity", ...}, "device_id": "..."}``; a negative ``speed`` or
    ``heading`` means unknown.

Answer: HTTP 200 with an empty body when a position (or a device-only report) was decoded,
400 otherwise (:attr:`Rejected.answer` holds the status as ASCII digits).
"""

from __future__ import annotations

import json
import math
from datetime import UTC, datetime
from typing import Any
from urllib.parse import parse_qsl

from iotnav.service.protocols.common import (
    KMH_MPS,
    KNOT_MPS,
    Decoded,
    Fix,
    Rejected,
    finite_or_nan,
    json_object,
    plausible_time,
    record_key,
)

SPEED_UNITS = {"kn": KNOT_MPS, "kmh": KMH_MPS, "mps": 1.0}

#: Largest request body decoded, bytes.
MAX_BODY_BYTES = 65536

_BAD = b"400"
_OK = b"200"


def parse_time(value: Any) -> float:
    """Seconds since 1970 UTC from Unix s / ms, ISO 8601 or ``YYYY-MM-DD HH:MM:SS``; NaN if unreadable.

    A naive ISO time is taken as UTC.
    """
    s = str(value).strip()
    try:
        n = int(s)
    except ValueError:
        pass
    else:
        return n / 1000.0 if n > 2**31 - 1 else float(n)
    try:
        f = float(s)
    except ValueError:
        pass
    else:
        return f if math.isfinite(f) else math.nan
    try:
        dt = datetime.fromisoformat(s.replace("Z", "+00:00"))
    except ValueError:
        return math.nan
    if dt.tzinfo is None:
        dt = dt.replace(tzinfo=UTC)
    return dt.timestamp()


def _number(params: dict[str, str], *names: str) -> float:
    for n in names:
        if n in params:
            return finite_or_nan(params[n])
    return math.nan


def _valid_position(lat: float, lon: float) -> bool:
    return -90.0 <= lat <= 90.0 and -180.0 <= lon <= 180.0


def decode_query(
    query: str, received_at: float, speed_unit: str = "kn", body: str = ""
) -> Decoded | Rejected:
    """One OsmAnd request in query (or form-body) form.

    Parameters
    ----------
    query : str
        The URL query string (without ``?``).
    received_at : float
        Server time, s since 1970 UTC: the fix time when the request has no ``timestamp``.
    speed_unit : str
        Unit of ``speed``: ``kn`` (Traccar's default), ``kmh`` or ``mps``.
    body : str
        A form body (``application/x-www-form-urlencoded``), read when the query is empty.

    Returns
    -------
    Decoded or Rejected
        ``Rejected`` reasons: ``no_id``, ``bad_time``, ``bad_position`` (latitude / longitude
        unreadable or out of range), ``bad_unit``.
    """
    if speed_unit not in SPEED_UNITS:
        return Rejected("bad_unit", f"speed unit {speed_unit!r} (expected kn, kmh or mps)", _BAD)
    pairs = parse_qsl(query or body, keep_blank_values=True)
    params = dict(pairs)
    device = params.get("id") or params.get("deviceid") or ""
    if not device:
        return Rejected("no_id", "no id or deviceid parameter", _BAD)
    t = parse_time(params["timestamp"]) if "timestamp" in params else received_at
    if not plausible_time(t):
        return Rejected(
            "bad_time", f"timestamp {params['timestamp'][:40]!r} unreadable or out of range", _BAD
        )
    if "location" in params:
        parts = params["location"].split(",")
        lat = finite_or_nan(parts[0])
        lon = finite_or_nan(parts[1]) if len(parts) > 1 else math.nan
    else:
        lat, lon = _number(params, "lat"), _number(params, "lon")
    has_position = "lat" in params or "lon" in params or "location" in params
    if has_position and not _valid_position(lat, lon):
        return Rejected("bad_position", f"latitude {lat}, longitude {lon}", _BAD)
    known = {"id", "deviceid", "timestamp", "lat", "lon", "location", "speed", "bearing", "heading"}
    known |= {"altitude", "accuracy", "hdop", "valid", "batt"}
    attributes: dict[str, Any] = {k: v for k, v in pairs if k not in known}
    if "batt" in params:
        attributes["battery_level_pct"] = finite_or_nan(params["batt"])
    course = _number(params, "bearing", "heading")
    valid = params.get("valid", "true").lower() in ("true", "1") and has_position
    records = []
    if has_position:
        records.append(
            Fix(
                device=device,
                t=t,
                lat_deg=lat,
                lon_deg=lon,
                height_m=_number(params, "altitude"),
                speed_mps=_number(params, "speed") * SPEED_UNITS[speed_unit],
                course_rad=math.radians(course) if course >= 0.0 else math.nan,
                h_acc_m=_number(params, "accuracy"),
                hdop=_number(params, "hdop"),
                valid=valid,
                attributes=attributes,
                # a request without timestamp is a new report each time it arrives
                key=record_key(
                    device, (query or body).encode() + (b"" if "timestamp" in params else repr(t).encode())
                ),
            )
        )
    return Decoded(records, _OK, len(query or body), device=device)


def decode_json(body: bytes, received_at: float) -> Decoded | Rejected:
    """One OsmAnd request in JSON form (Traccar Client 9+).

    Returns
    -------
    Decoded or Rejected
        ``Rejected`` reasons: ``too_large``, ``bad_json``, ``no_id``, ``bad_time``,
        ``bad_position``.
    """
    doc = json_object(body, MAX_BODY_BYTES, _BAD)
    if isinstance(doc, Rejected):
        return doc
    loc = doc.get("location")
    device = doc.get("device_id")
    if not isinstance(device, str | int) or isinstance(device, bool) or str(device) == "":
        return Rejected("no_id", "no device_id", _BAD)
    device = str(device)
    if not isinstance(loc, dict):
        return Decoded([], _OK, len(body), device=device)
    coords = loc.get("coords") if isinstance(loc.get("coords"), dict) else {}
    assert isinstance(coords, dict)
    lat, lon = finite_or_nan(coords.get("latitude")), finite_or_nan(coords.get("longitude"))
    if not _valid_position(lat, lon):
        return Rejected("bad_position", f"latitude {lat}, longitude {lon}", _BAD)
    t = parse_time(loc["timestamp"]) if "timestamp" in loc else received_at
    if not plausible_time(t):
        return Rejected(
            "bad_time", f"timestamp {str(loc.get('timestamp'))[:40]!r} unreadable or out of range", _BAD
        )
    speed, heading = finite_or_nan(coords.get("speed")), finite_or_nan(coords.get("heading"))
    attributes: dict[str, Any] = {
        k: v for k, v in loc.items() if k not in ("coords", "timestamp") and _jsonable(v)
    }
    battery = loc.get("battery")
    if isinstance(battery, dict):
        level = finite_or_nan(battery.get("level"))
        if level >= 0.0:
            attributes["battery_level_pct"] = 100.0 * level
    fix = Fix(
        device=device,
        t=t,
        lat_deg=lat,
        lon_deg=lon,
        height_m=finite_or_nan(coords.get("altitude")),
        speed_mps=speed if speed >= 0.0 else math.nan,
        course_rad=math.radians(heading) if heading >= 0.0 else math.nan,
        h_acc_m=finite_or_nan(coords.get("accuracy")),
        valid=True,
        attributes=attributes,
        key=record_key(device, body + (b"" if "timestamp" in loc else repr(t).encode())),
    )
    return Decoded([fix], _OK, len(body), device=device)


def _jsonable(v: Any) -> bool:
    try:
        json.dumps(v, allow_nan=False)
    except (TypeError, ValueError, RecursionError):
        return False
    return True
