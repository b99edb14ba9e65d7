"""OwnTracks JSON ``_type: location`` messages (HTTP mode; MQTT carries the same payload).

Source: OwnTracks booklet, "JSON" (https://owntracks.org/booklet/tech/json/) and "HTTP"
(https://owntracks.org/booklet/tech/http/). Fields used: ``lat``, ``lon`` degrees, ``tst``
Unix seconds (mandatory), ``acc`` m (horizontal accuracy), ``alt`` m, ``vac`` m (vertical
accuracy), ``vel`` km/h, ``cog`` degrees, ``batt`` percent, ``tid`` (tracker id), ``topic``.

The device id is ``user/device`` from the MQTT topic ``owntracks/user/device`` (or the
``topic`` element, or the HTTP ``X-Limit-U`` / ``X-Limit-D`` headers), else ``tid``. Other
``_type`` values are accepted and give no record. The HTTP answer is a JSON array (``[]``)
of messages for the app.
"""

from __future__ import annotations

import math
from typing import Any

from iotnav.service.protocols.common import (
    KMH_MPS,
    Decoded,
    Fix,
    Rejected,
    finite_or_nan,
    json_object,
    plausible_time,
    record_key,
)

MAX_BODY_BYTES = 65536
_ANSWER = b"[]"


def device_from_topic(topic: str) -> str | None:
    """``user/device`` from ``owntracks/user/device[/...]``, else None."""
    parts = topic.split("/")
    if len(parts) >= 3 and parts[0] == "owntracks" and parts[1] and parts[2]:
        return f"{parts[1]}/{parts[2]}"
    return None


def decode(
    body: bytes, topic: str | None = None, user: str | None = None, device: str | None = None
) -> Decoded | Rejected:
    """One OwnTracks message.

    Parameters
    ----------
    body : bytes
        The JSON payload.
    topic : str, optional
        The MQTT topic it came on.
    user, device : str, optional
        HTTP ``X-Limit-U`` and ``X-Limit-D`` headers.

    Returns
    -------
    Decoded or Rejected
        ``Rejected`` reasons: ``too_large``, ``bad_json``, ``no_id``, ``bad_time``,
        ``bad_position``. An empty body (a deleted friend, see the booklet) decodes to no record.
    """
    if not body.strip():
        return Decoded([], _ANSWER, 0)
    doc = json_object(body, MAX_BODY_BYTES, b"")
    if isinstance(doc, Rejected):
        return doc
    ident = None
    for cand in (topic, doc.get("topic")):
        if isinstance(cand, str) and (ident := device_from_topic(cand)):
            break
    if ident is None and user and device:
        ident = f"{user}/{device}"
    if ident is None and isinstance(doc.get("tid"), str) and doc["tid"]:
        ident = doc["tid"]
    if ident is None:
        return Rejected("no_id", "no topic, X-Limit-U/D headers or tid", b"")
    if doc.get("_type") != "location":
        return Decoded([], _ANSWER, len(body), device=ident)
    lat, lon = finite_or_nan(doc.get("lat")), finite_or_nan(doc.get("lon"))
    if not (-90.0 <= lat <= 90.0 and -180.0 <= lon <= 180.0):
        return Rejected("bad_position", f"latitude {lat}, longitude {lon}", b"")
    t = finite_or_nan(doc.get("tst"))
    if not plausible_time(t):
        return Rejected("bad_time", f"tst {t} missing or out of range", b"")
    vel, cog = finite_or_nan(doc.get("vel")), finite_or_nan(doc.get("cog"))
    attributes: dict[str, Any] = {}
    for k in ("tid", "batt", "vac", "conn", "t", "bs", "m"):
        v = doc.get(k)
        if isinstance(v, str | int | float) and not isinstance(v, bool):
            attributes[k] = v if not isinstance(v, float) or math.isfinite(v) else None
    if "batt" in attributes:
        attributes["battery_level_pct"] = finite_or_nan(attributes["batt"])
    fix = Fix(
        device=ident,
        t=t,
        lat_deg=lat,
        lon_deg=lon,
        height_m=finite_or_nan(doc.get("alt")),
        speed_mps=vel * KMH_MPS if vel >= 0.0 else math.nan,
        course_rad=math.radians(cog) if cog >= 0.0 else math.nan,
        h_acc_m=finite_or_nan(doc.get("acc")),
        valid=True,
        attributes=attributes,
        key=record_key(ident, body),
    )
    return Decoded([fix], _ANSWER, len(body), device=ident)
