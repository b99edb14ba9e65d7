"""Geofence areas in Traccar's text form (pure parsing, no I/O).

Traccar writes areas as WKT-like text with **latitude first**: ``CIRCLE (lat lon, radius_m)``,
``POLYGON ((lat lon, lat lon, ...))`` and ``LINESTRING (lat lon, lat lon, ...)`` (Traccar
``GeofenceGeometry`` classes; a polygon's ring may or may not repeat its first point).
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass

_KIND = re.compile(r"^\s*(CIRCLE|POLYGON|LINESTRING)\s*\((.*)\)\s*$", re.IGNORECASE | re.DOTALL)


@dataclass(frozen=True)
class Area:
    """A parsed area: ``kind`` ``circle`` / ``polygon`` / ``linestring``, points (lat, lon) degrees, radius m."""

    kind: str
    points: tuple[tuple[float, float], ...]
    radius_m: float = math.nan


def _point(text: str) -> tuple[float, float]:
    parts = text.split()
    if len(parts) != 2:
        raise ValueError(f"point {text.strip()!r}: expected 'lat lon'")
    lat, lon = float(parts[0]), float(parts[1])
    if not (-90.0 <= lat <= 90.0 and -180.0 <= lon <= 180.0):
        raise ValueError(f"point {text.strip()!r} is outside latitude -90..90 / longitude -180..180")
    return lat, lon


def parse_area(text: str) -> Area:
    """The :class:`Area` of Traccar area text.

    Raises
    ------
    ValueError
        Naming what is wrong (unknown shape, a point that is not ``lat lon`` in range, a
        radius that is not positive, a polygon of fewer than 3 distinct corners or a line of
        fewer than 2 points).
    """
    m = _KIND.match(text)
    if m is None:
        raise ValueError(
            f"area {text[:60]!r}: expected CIRCLE (lat lon, r), POLYGON ((lat lon, ...)) or LINESTRING"
        )
    kind, body = m.group(1).lower(), m.group(2)
    if kind == "circle":
        centre, _, radius = body.partition(",")
        r = float(radius) if radius.strip() else math.nan
        if not r > 0.0 or not math.isfinite(r):
            raise ValueError(f"circle radius {radius.strip()!r}: expected a positive number of metres")
        return Area("circle", (_point(centre),), r)
    if kind == "polygon":
        body = body.strip()
        if not (body.startswith("(") and body.endswith(")")):
            raise ValueError("polygon: expected POLYGON ((lat lon, ...))")
        body = body[1:-1]
    pts = tuple(_point(p) for p in body.split(","))
    if len(pts) < (3 if kind == "polygon" else 2):
        raise ValueError(f"{kind} of {len(pts)} points is too short")
    if kind == "polygon" and len(set(pts)) < 3:  # e.g. a ring of two corners, closed
        raise ValueError(f"polygon of {len(set(pts))} distinct corners encloses nothing: expected 3 or more")
    return Area(kind, pts)
