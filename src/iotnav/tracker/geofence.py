"""Geofences: zones from GeoJSON, enter/exit events with hysteresis against the uncertainty.

Zones
-----
:func:`zones_from_geojson` reads a GeoJSON object (RFC 7946: a FeatureCollection, a Feature or
a bare geometry; coordinates ``[lon, lat]`` in degrees): a ``Polygon`` or ``MultiPolygon``
(exterior ring and holes) is a polygon zone; a ``Point`` whose feature has a ``radius``
property (metres) is a circle. A feature's ``name`` (or ``id``) property names the zone.
Anything else is a ValueError that says which feature and what was expected.

Inside, outside, and the border
-------------------------------
Each zone has its own tangent plane at its first vertex (or centre); positions are projected
there (:class:`iotnav.geo.LocalFrame`) and tested with :class:`matplotlib.path.Path` (in the
exterior ring, in no hole). The signed distance to the border (negative inside) is the
distance to the nearest edge, or ``|p - c| - r`` for a circle.

A point-by-point test toggles at every noisy fix near the border. :func:`geofence_events`
switches state only when the position is beyond the border by more than
``margin = k_sigma * sigma`` (``sigma`` the row's per-axis 1-sigma; the vocabulary's
``k_sigma = 3``: a position error normal to the border passes the margin with probability
0.13 % on a row):
outside once ``d > margin``, inside once ``d < -margin``. The state at the first position is
taken as it is (no event).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np
import numpy.typing as npt

from iotnav.geo import LocalFrame

FloatArray = npt.NDArray[np.float64]


@dataclass(frozen=True)
class Zone:
    """A geofence.

    Attributes
    ----------
    name : str
        Zone name (the feature's ``name`` or ``id`` property, else ``zone<k>``).
    polygons : tuple
        For a polygon zone: polygons, each a tuple of rings (exterior first, then holes), each
        ring an ``(m, 2)`` array of ``[lon, lat]`` degrees. Empty for a circle.
    center : tuple of float
        Circle centre ``(lat, lon)``, degrees (NaN for polygons).
    radius_m : float
        Circle radius, m (NaN for polygons).
    """

    name: str
    polygons: tuple[tuple[FloatArray, ...], ...] = ()
    center: tuple[float, float] = (math.nan, math.nan)
    radius_m: float = math.nan

    @property
    def frame(self) -> LocalFrame:
        """The zone's tangent plane (at its first vertex or its centre)."""
        if self.polygons:
            lon0, lat0 = self.polygons[0][0][0]
            return LocalFrame(float(lat0), float(lon0), 0.0)
        return LocalFrame(self.center[0], self.center[1], 0.0)

    def signed_distance(self, lat_deg: FloatArray, lon_deg: FloatArray) -> FloatArray:
        """Distance to the border, m, negative inside (NaN for NaN positions)."""
        fr = self.frame
        ok = np.isfinite(lat_deg) & np.isfinite(lon_deg)
        out = np.full(lat_deg.size, np.nan)
        if not ok.any():
            return out
        ne = fr.to_ned(lat_deg[ok], lon_deg[ok], np.zeros(int(ok.sum())))[:, :2]
        if not self.polygons:
            out[ok] = np.hypot(ne[:, 0], ne[:, 1]) - self.radius_m
            return out
        from matplotlib.path import Path as MplPath  # here: matplotlib takes seconds to import

        inside = np.zeros(ne.shape[0], dtype=bool)
        dist = np.full(ne.shape[0], np.inf)
        for poly in self.polygons:
            rings = [fr.to_ned(r[:, 1], r[:, 0], np.zeros(len(r)))[:, :2] for r in poly]
            in_poly = MplPath(rings[0]).contains_points(ne)
            for hole in rings[1:]:
                in_poly &= ~MplPath(hole).contains_points(ne)
            inside |= in_poly
            for ring in rings:
                dist = np.minimum(dist, _distance_to_ring(ne, ring))
        out[ok] = np.where(inside, -dist, dist)
        return out


def _distance_to_ring(p: FloatArray, ring: FloatArray, chunk: int = 4096) -> FloatArray:
    """Distance (m) of each point ``p`` ``(n, 2)`` to the nearest edge of a closed ring ``(m, 2)``."""
    a = ring
    b = np.roll(ring, -1, axis=0)
    ab = b - a
    ab2 = np.maximum(np.einsum("ij,ij->i", ab, ab), 1e-18)
    out = np.empty(p.shape[0])
    for s in range(0, p.shape[0], chunk):
        q = p[s : s + chunk, None, :] - a[None, :, :]
        u = np.clip(np.einsum("nmj,mj->nm", q, ab) / ab2, 0.0, 1.0)
        r = q - u[..., None] * ab[None, :, :]
        out[s : s + chunk] = np.sqrt(np.min(np.einsum("nmj,nmj->nm", r, r), axis=1))
    return out


def _ring(coords: Any, where: str) -> FloatArray:
    try:
        r = np.asarray(coords, dtype=float)
    except (TypeError, ValueError):
        raise ValueError(f"{where}: a ring must be a list of [lon, lat] positions") from None
    if r.ndim != 2 or r.shape[1] < 2 or r.shape[0] < 4:
        raise ValueError(
            f"{where}: a ring needs at least 4 [lon, lat] positions (closed), got shape {r.shape}"
        )
    r = r[:, :2]
    if not np.all(np.isfinite(r)) or np.any(np.abs(r[:, 1]) > 90) or np.any(np.abs(r[:, 0]) > 180):
        raise ValueError(
            f"{where}: coordinates must be finite [lon, lat] degrees (|lat| <= 90, |lon| <= 180)"
        )
    if not np.array_equal(r[0], r[-1]):
        raise ValueError(f"{where}: a ring must be closed (first position equal to the last)")
    return r[:-1]


def _polygon(coords: Any, where: str) -> tuple[FloatArray, ...]:
    if not isinstance(coords, list) or not coords:
        raise ValueError(f"{where}: a Polygon's coordinates must be a non-empty list of rings")
    return tuple(_ring(c, f"{where} ring {k}") for k, c in enumerate(coords))


def _zone(geom: Any, props: dict[str, Any], name: str, where: str) -> Zone:
    if not isinstance(geom, dict) or "type" not in geom:
        raise ValueError(f"{where}: no geometry (expected a GeoJSON geometry object with a 'type')")
    kind = geom["type"]
    coords: Any = geom.get("coordinates")
    if kind == "Polygon":
        return Zone(name, polygons=(_polygon(coords, where),))
    if kind == "MultiPolygon":
        if not isinstance(coords, list) or not coords:
            raise ValueError(f"{where}: a MultiPolygon's coordinates must be a non-empty list of polygons")
        return Zone(name, polygons=tuple(_polygon(c, f"{where} polygon {k}") for k, c in enumerate(coords)))
    if kind == "Point":
        radius = props.get("radius")
        if radius is None:
            raise ValueError(f"{where}: a Point zone needs a 'radius' property in metres")
        try:
            r = float(radius)
            lon, lat = float(coords[0]), float(coords[1])
        except (TypeError, ValueError, IndexError):
            raise ValueError(f"{where}: a Point needs [lon, lat] coordinates and a numeric radius") from None
        if not (math.isfinite(r) and r > 0):
            raise ValueError(f"{where}: radius must be a positive number of metres, got {radius!r}")
        if not (math.isfinite(lat) and math.isfinite(lon) and abs(lat) <= 90 and abs(lon) <= 180):
            raise ValueError(f"{where}: Point coordinates out of range: [{lon}, {lat}]")
        return Zone(name, center=(lat, lon), radius_m=r)
    raise ValueError(f"{where}: geometry type {kind!r} is not a zone (expected Polygon, MultiPolygon, Point)")


def zones_from_geojson(obj: Any, source: str = "geofences") -> list[Zone]:
    """Zones of a parsed GeoJSON object (module docstring).

    Parameters
    ----------
    obj : object
        The parsed JSON (FeatureCollection, Feature or geometry).
    source : str
        Name of the file, for messages.

    Returns
    -------
    list of Zone

    Raises
    ------
    ValueError
        A malformed object, naming the feature and what was expected.
    """
    if not isinstance(obj, dict) or "type" not in obj:
        raise ValueError(f"{source}: not a GeoJSON object (expected a JSON object with a 'type')")
    if obj["type"] == "FeatureCollection":
        feats = obj.get("features")
        if not isinstance(feats, list):
            raise ValueError(f"{source}: a FeatureCollection needs a 'features' list")
    elif obj["type"] == "Feature":
        feats = [obj]
    else:
        feats = [{"type": "Feature", "geometry": obj, "properties": {}}]
    zones: list[Zone] = []
    for k, f in enumerate(feats):
        where = f"{source}: feature {k}"
        if not isinstance(f, dict) or f.get("type") != "Feature":
            raise ValueError(f"{where}: expected a GeoJSON Feature")
        props = f.get("properties") or {}
        if not isinstance(props, dict):
            raise ValueError(f"{where}: 'properties' must be an object")
        name = str(props.get("name", f.get("id", props.get("id", f"zone{k}"))))
        zones.append(_zone(f.get("geometry"), props, name, f"{where} ({name})"))
    if not zones:
        raise ValueError(f"{source}: no zones (the FeatureCollection is empty)")
    return zones


def border_step(inside: bool, border_m: float, margin_m: float) -> bool:
    """The zone state after a position ``border_m`` (m, negative inside) from the border.

    The hysteresis of the module docstring: the state switches only beyond ``margin_m`` (m) on
    the other side. :func:`geofence_events` (batch) and :mod:`iotnav.alerts` (streaming) share it.
    """
    if inside and border_m > margin_m:
        return False
    if not inside and border_m < -margin_m:
        return True
    return inside


def geofence_events(
    t: FloatArray,
    lat_deg: FloatArray,
    lon_deg: FloatArray,
    sigma_m: FloatArray,
    zones: list[Zone],
    k_sigma: float,
) -> tuple[list[dict[str, Any]], dict[str, bool]]:
    """Enter/exit events of each zone with hysteresis (module docstring).

    Parameters
    ----------
    t : numpy.ndarray
        Row times, s.
    lat_deg, lon_deg : numpy.ndarray
        Positions, degrees (NaN rows are skipped).
    sigma_m : numpy.ndarray
        Per-axis horizontal 1-sigma, m (0 gives the point-by-point test).
    zones : list of Zone
    k_sigma : float
        Margin in sigmas beyond the border before the state switches.

    Returns
    -------
    events : list of dict
        ``geofence_enter`` / ``geofence_exit`` with ``t``, ``zone``, ``lat``, ``lon`` and
        ``border_m`` (signed distance to the border, m), in time order.
    initial : dict
        Zone name -> inside at the first position.
    """
    events: list[dict[str, Any]] = []
    initial: dict[str, bool] = {}
    for z in zones:
        d = z.signed_distance(lat_deg, lon_deg)
        ok = np.flatnonzero(np.isfinite(d))
        if ok.size == 0:
            continue
        margin = k_sigma * np.where(np.isfinite(sigma_m), sigma_m, 0.0)
        inside = bool(d[ok[0]] < 0.0)
        initial[z.name] = inside
        for i in ok[1:].tolist():
            was, inside = inside, border_step(inside, float(d[i]), float(margin[i]))
            if inside == was:
                continue
            events.append(
                {
                    "type": "geofence_enter" if inside else "geofence_exit",
                    "t": float(t[i]),
                    "zone": z.name,
                    "lat": float(lat_deg[i]),
                    "lon": float(lon_deg[i]),
                    "border_m": float(d[i]),
                }
            )
    events.sort(key=lambda e: e["t"])
    return events, initial
