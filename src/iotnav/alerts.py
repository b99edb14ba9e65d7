"""Alerts: rules evaluated on each device's stream of positions and engine events (pure, streaming).

:class:`AlertEngine` keeps a small state per device, is fed positions (:meth:`~AlertEngine.position`)
and engine events (:meth:`~AlertEngine.event`) in device-time order, and is ticked with a clock
(:meth:`~AlertEngine.tick`, the caller's clock: no call to ``time`` here). Each call returns the
:class:`Alert` objects it raised. It knows no database, socket or broker; the service feeds it
and delivers what it returns (:mod:`iotnav.service.alerts_delivery`). Not a paper technique:
the rules below follow the tracker's vocabulary (:mod:`iotnav.tracker`) and Traccar's
documented events, as each says.

Kinds (:data:`ALERT_KINDS`), each rule off unless its group configures it
----------------------------------------------------------------------------
``geofence_enter`` / ``geofence_exit``
    the border rule of :func:`iotnav.tracker.geofence_events`, one position at a time
    (:func:`iotnav.tracker.border_step`): the state switches only beyond ``fence_k_sigma``
    per-axis sigmas on the other side of the border; a device's first position sets its state
    without an alert.
``overspeed``
    speed above ``overspeed_mps`` for at least ``overspeed_min_duration_s`` (Traccar's
    ``event.overspeed.minimalDuration``, default 0: the first position above the limit); once
    per overspeed period (Traccar's ``event.overspeed.notRepeat``), which ends at the first
    position at or below the limit.
``stop``
    a stop that follows a trip has lasted ``stop_max_s``: trips and stops from the tracker's
    hysteresis (:class:`iotnav.tracker.TripHysteresis`, Traccar's rules, with the
    vocabulary's ``bridge_halts``) on a per-position motion flag: not ``static`` (the engine's
    decision) and a speed above the vocabulary's ``min_speed_mps`` (0.5 m/s); without a
    reported speed, the displacement since the previous position beyond ``k_sigma`` noise
    bounds (:class:`iotnav.tracker.TrackerConfig`) at that speed. Checked at each position
    and at each tick (a parked tracker may report rarely), once per stop. A device's first
    stop after a restart of the service (no trip before it) raises none.
``silent``
    no position received for ``silent_max_s`` (server time: the clock of :meth:`tick` against
    each position's ``received_at``); once per silence.
``moved_while_off``
    ignition off and the position farther than ``moved_while_off_m`` and ``moved_k_sigma``
    combined sigmas from the position where the ignition went off (towing, theft); once per
    ignition-off period. Also the engine's own ``moved_while_off`` event (the boot rule of
    :mod:`iotnav.techniques.last_position`: the first fix after power-up far from the stored
    position).
``gnss_jump_rejected``
    the engine's gate rejected a fix (its ``fix_rejected`` event, with the NIS); rejections
    within ``gnss_jump_hold_s`` of the previous one belong to the same alert (a glitch of a
    few fixes raises one).

Positions older than the device's latest are counted (``counts["out_of_order"]``) and not
evaluated; a device whose group changes starts afresh under its new group's rules. Distances in metres, speeds m/s, times s (Unix).
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from iotnav.tracker import TrackerConfig, TripHysteresis, TripRules, Zone, border_step

ALERT_KINDS = (
    "geofence_enter",
    "geofence_exit",
    "overspeed",
    "stop",
    "silent",
    "moved_while_off",
    "gnss_jump_rejected",
)
"""The alert kinds (module docstring)."""

KMH_MPS = 1000.0 / 3600.0
"""One km/h in m/s (the configuration's speed unit)."""


@dataclass(frozen=True)
class AlertRules:
    """The rules of one device group (module docstring); ``inf`` / False / ``()`` turns a rule off.

    Attributes
    ----------
    geofences : tuple of str or None
        Names of the zones watched; None: every zone; ``()``: none.
    overspeed_mps : float
        Speed limit, m/s (TOML ``overspeed_kmh``, km/h).
    overspeed_min_duration_s : float
        Time above the limit before the alert, s (Traccar's ``minimalDuration``, default 0).
    stop_max_s : float
        Stop duration that raises ``stop``, s (TOML ``stop_minutes``).
    silent_max_s : float
        Silence that raises ``silent``, s (TOML ``silent_minutes``).
    moved_while_off_m : float
        Displacement with the ignition off that raises ``moved_while_off``, m.
    moved_k_sigma : float
        ... and beyond this many combined sigmas (4, the odometer's: noise alone passes with
        probability ``exp(-8) = 3.4e-4`` per position).
    gnss_jump : bool
        Raise ``gnss_jump_rejected`` on the engine's rejections.
    gnss_jump_hold_s : float
        Rejections closer than this to the previous one join its alert, s.
    tracker : TrackerConfig
        Trip hysteresis, motion speed, noise bounds and fence margin: the vocabulary's.
    """

    geofences: tuple[str, ...] | None = None
    overspeed_mps: float = math.inf
    overspeed_min_duration_s: float = 0.0
    stop_max_s: float = math.inf
    silent_max_s: float = math.inf
    moved_while_off_m: float = math.inf
    moved_k_sigma: float = 4.0
    gnss_jump: bool = False
    gnss_jump_hold_s: float = 60.0
    tracker: TrackerConfig = field(default_factory=TrackerConfig)


_UNITS = {"overspeed_kmh": ("overspeed_mps", KMH_MPS), "stop_minutes": ("stop_max_s", 60.0)}
_UNITS["silent_minutes"] = ("silent_max_s", 60.0)


def rules_from_dict(table: dict[str, Any], where: str = "alerts group") -> AlertRules:
    """:class:`AlertRules` of a TOML table (``overspeed_kmh``, ``stop_minutes``, ``silent_minutes``
    converted here; ``geofences`` a list of names or true/false; a ``trips`` sub-table of
    :class:`iotnav.tracker.TripRules` fields). Unknown keys raise ValueError naming them."""
    fields = {f.name for f in dataclasses.fields(AlertRules)} - {"tracker", "overspeed_mps"}
    fields -= {"stop_max_s", "silent_max_s"}
    allowed = fields | set(_UNITS) | {"trips"}
    unknown = sorted(set(table) - allowed)
    if unknown:
        raise ValueError(
            f"{where}: unknown key(s) {', '.join(unknown)}; expected {', '.join(sorted(allowed))}"
        )
    values: dict[str, Any] = {}
    for k, v in table.items():
        if k in _UNITS:
            name, scale = _UNITS[k]
            if isinstance(v, bool) or not isinstance(v, int | float) or not v > 0:
                raise ValueError(f"{where}: {k} = {v!r}: expected a positive number")
            values[name] = float(v) * scale
        elif k == "geofences":
            if isinstance(v, bool):
                values[k] = None if v else ()
            elif isinstance(v, list) and all(isinstance(x, str) for x in v):
                values[k] = tuple(v)
            else:
                raise ValueError(f"{where}: geofences = {v!r}: expected true, false or a list of zone names")
        elif k == "gnss_jump":
            if not isinstance(v, bool):
                raise ValueError(f"{where}: gnss_jump = {v!r}: expected true or false")
            values[k] = v
        elif k == "trips":
            try:
                trips = TripRules(**{n: float(x) for n, x in dict(v).items()})
            except (TypeError, ValueError) as exc:
                raise ValueError(f"{where}: trips: {exc}") from None
            values["tracker"] = TrackerConfig(trips=trips)
        else:
            if isinstance(v, bool) or not isinstance(v, int | float) or not v >= 0:
                raise ValueError(f"{where}: {k} = {v!r}: expected a number >= 0")
            values[k] = float(v)
    return AlertRules(**values)


def groups_from_dict(groups: dict[str, Any], where: str = "alerts.groups") -> dict[str, AlertRules]:
    """The rules of each group of the TOML table ``[alerts.groups.<name>]``."""
    out = {}
    for name, table in groups.items():
        if not isinstance(table, dict):
            raise ValueError(f"{where}.{name}: expected a table of rules")
        out[str(name)] = rules_from_dict(table, f"{where}.{name}")
    return out


@dataclass(frozen=True)
class Position:
    """One position of a device.

    Attributes
    ----------
    t : float
        Fix time, s (Unix).
    lat_deg, lon_deg : float
        WGS84, degrees.
    speed_mps : float
        Horizontal speed, m/s (NaN: not known).
    sigma_m : float
        Per-axis horizontal 1-sigma, m (NaN: the vocabulary's ``default_sigma_m``).
    static : bool
        The engine says the device stands still.
    ignition : bool or None
        The device's ignition flag (None: not reported).
    received_at : float
        Server time the position was received, s (NaN: ``t``).
    """

    t: float
    lat_deg: float
    lon_deg: float
    speed_mps: float = math.nan
    sigma_m: float = math.nan
    static: bool = False
    ignition: bool | None = None
    received_at: float = math.nan


@dataclass(frozen=True)
class Alert:
    """An alert: ``kind`` (:data:`ALERT_KINDS`), device, group, time ``t`` (s; device time, the
    clock's for ``silent`` and for a ``stop`` found at a tick), last known position (degrees,
    NaN when none) and the rule's ``detail`` (zone, speed, duration, distance...)."""

    kind: str
    device: str
    group: str
    t: float
    lat_deg: float
    lon_deg: float
    detail: dict[str, Any] = field(default_factory=dict)


_WGS84_A = 6378137.0
_WGS84_E2 = 6.69437999014e-3


def _distance_m(a: Position, b: Position) -> float:
    """Horizontal distance, m, on the tangent plane at the mean latitude: WGS84 meridian and
    transverse radii of curvature (Groves 2013, eq. 2.105-2.106); the flat-plane error is below
    1e-5 relative up to 10 km, and this runs per position (pymap3d takes 0.2 ms a call)."""
    lat = math.radians(0.5 * (a.lat_deg + b.lat_deg))
    w = 1.0 - _WGS84_E2 * math.sin(lat) ** 2
    r_n = _WGS84_A * (1.0 - _WGS84_E2) / w**1.5
    r_e = _WGS84_A / math.sqrt(w)
    dlon = (b.lon_deg - a.lon_deg + 180.0) % 360.0 - 180.0
    return math.hypot(math.radians(b.lat_deg - a.lat_deg) * r_n, math.radians(dlon) * r_e * math.cos(lat))


def _bounding_circle(z: Zone) -> tuple[float, float, float]:
    """Centre (degrees) and radius (m, 1 % and 1 m above the farthest vertex) of a circle
    holding the zone: positions beyond it need no exact border distance."""
    if not z.polygons:
        return z.center[0], z.center[1], z.radius_m * 1.01 + 1.0
    pts = np.concatenate([ring for poly in z.polygons for ring in poly])
    c = Position(0.0, float(pts[:, 1].mean()), float(pts[:, 0].mean()))
    far = max(_distance_m(c, Position(0.0, float(lat), float(lon))) for lon, lat in pts)
    return c.lat_deg, c.lon_deg, far * 1.01 + 1.0


@dataclass
class _Device:
    """Per-device state of :class:`AlertEngine`."""

    group: str
    hyst: TripHysteresis
    last: Position | None = None
    last_received: float = math.nan
    inside: dict[str, bool] = field(default_factory=dict)
    over_since: float | None = None
    over_fired: bool = False
    distance_m: float = 0.0
    had_trip: bool = False
    stop_since: float | None = None
    stop_fired: bool = False
    silent_fired: bool = False
    off_anchor: Position | None = None
    moved_fired: bool = False
    last_reject_t: float = -math.inf


class AlertEngine:
    """Per-device alert state fed positions, engine events and a clock (module docstring).

    Parameters
    ----------
    groups : dict of str to AlertRules
        Rules per device group; a device of a group not listed takes ``default_group``'s, and
        none when that is not listed either.
    zones : list of Zone
        Geofences (replace with :meth:`set_zones`).
    default_group : str
        The group of devices whose own is not configured.
    """

    def __init__(
        self, groups: dict[str, AlertRules], zones: list[Zone] | None = None, default_group: str = "default"
    ) -> None:
        self.groups = dict(groups)
        self.default_group = default_group
        self.devices: dict[str, _Device] = {}
        self.zones: list[Zone] = []
        self._bounds: list[tuple[float, float, float]] = []
        self.set_zones(list(zones or []))
        self.counts: dict[str, int] = {}

    def set_zones(self, zones: list[Zone]) -> None:
        """Replace the geofences (a zone no longer present is forgotten; a new one starts without alert)."""
        self.zones = list(zones)
        self._bounds = [_bounding_circle(z) for z in self.zones]
        names = {z.name for z in zones}
        for st in self.devices.values():
            st.inside = {k: v for k, v in st.inside.items() if k in names}

    def _count(self, what: str) -> None:
        self.counts[what] = self.counts.get(what, 0) + 1

    def rules(self, group: str) -> AlertRules | None:
        """The rules a device of ``group`` follows (None: no alerts)."""
        return self.groups.get(group, self.groups.get(self.default_group))

    def _state(self, device: str, group: str, rules: AlertRules) -> _Device:
        st = self.devices.get(device)
        if st is None or st.group != group:
            st = _Device(group, TripHysteresis(rules.tracker.trips, bridge_halts=True))
            self.devices[device] = st
        return st

    def _alert(self, kind: str, device: str, st: _Device, t: float, **detail: Any) -> Alert:
        p = st.last
        lat, lon = (p.lat_deg, p.lon_deg) if p is not None else (math.nan, math.nan)
        self._count(kind)
        return Alert(kind, device, st.group, t, lat, lon, detail)

    # --- positions -----------------------------------------------------------------------

    def position(self, device: str, group: str, p: Position) -> list[Alert]:
        """Evaluate one position of ``device`` (of ``group``); the alerts it raises."""
        rules = self.rules(group)
        if rules is None:
            self._count("no_rules")
            return []
        if not (math.isfinite(p.t) and math.isfinite(p.lat_deg) and math.isfinite(p.lon_deg)):
            self._count("nonfinite")
            return []
        st = self._state(device, group, rules)
        if st.last is not None and p.t < st.last.t:
            self._count("out_of_order")
            return []
        sigma = p.sigma_m if math.isfinite(p.sigma_m) else rules.tracker.default_sigma_m
        p = dataclasses.replace(p, sigma_m=sigma)
        prev, st.last = st.last, p
        st.last_received = p.received_at if math.isfinite(p.received_at) else p.t
        st.silent_fired = False
        out = self._geofences(device, st, rules, p)
        out += self._overspeed(device, st, rules, p)
        out += self._stop(device, st, rules, p, prev)
        out += self._moved_while_off(device, st, rules, p)
        return out

    def _geofences(self, device: str, st: _Device, rules: AlertRules, p: Position) -> list[Alert]:
        out = []
        watched = rules.geofences
        lat, lon = np.array([p.lat_deg]), np.array([p.lon_deg])
        margin = rules.tracker.fence_k_sigma * p.sigma_m
        for z, (c_lat, c_lon, radius) in zip(self.zones, self._bounds, strict=True):
            if watched is not None and z.name not in watched:
                continue
            was = st.inside.get(z.name)
            if not was and _distance_m(Position(0.0, c_lat, c_lon), p) - radius > margin:
                st.inside[z.name] = False  # beyond the zone's bounding circle: outside, no change
                continue
            d = float(z.signed_distance(lat, lon)[0])
            if was is None:
                st.inside[z.name] = d < 0.0
                continue
            now = border_step(was, d, margin)
            if now != was:
                st.inside[z.name] = now
                kind = "geofence_enter" if now else "geofence_exit"
                out.append(self._alert(kind, device, st, p.t, zone=z.name, border_m=d))
        return out

    def _overspeed(self, device: str, st: _Device, rules: AlertRules, p: Position) -> list[Alert]:
        if not math.isfinite(p.speed_mps) or not math.isfinite(rules.overspeed_mps):
            return []
        if p.speed_mps <= rules.overspeed_mps:
            st.over_since, st.over_fired = None, False
            return []
        if st.over_since is None:
            st.over_since = p.t
        if st.over_fired or p.t - st.over_since < rules.overspeed_min_duration_s:
            return []
        st.over_fired = True
        return [
            self._alert(
                "overspeed",
                device,
                st,
                p.t,
                speed_mps=p.speed_mps,
                limit_mps=rules.overspeed_mps,
                since=st.over_since,
            )
        ]

    def _moving(self, rules: AlertRules, p: Position, prev: Position | None) -> bool:
        cfg = rules.tracker
        if p.static:
            return False
        if math.isfinite(p.speed_mps):
            return p.speed_mps > cfg.min_speed_mps
        if prev is None or not p.t > prev.t:
            return False
        d = _distance_m(prev, p)
        gate = cfg.k_sigma * math.hypot(prev.sigma_m, p.sigma_m)
        return d > gate and d / (p.t - prev.t) > cfg.min_speed_mps

    def _stop(
        self, device: str, st: _Device, rules: AlertRules, p: Position, prev: Position | None
    ) -> list[Alert]:
        moving = self._moving(rules, p, prev)
        if moving and prev is not None:
            st.distance_m += _distance_m(prev, p)
        sw = st.hyst.push(p.t, moving, st.distance_m)
        if sw is not None:
            st.had_trip |= sw.moving
            st.stop_since = None if sw.moving or not st.had_trip else sw.t0
            st.stop_fired = False
        return self._stop_due(device, st, rules, p.t)

    def _stop_due(self, device: str, st: _Device, rules: AlertRules, now: float) -> list[Alert]:
        if st.stop_since is None or st.stop_fired or now - st.stop_since < rules.stop_max_s:
            return []
        st.stop_fired = True
        return [self._alert("stop", device, st, now, since=st.stop_since, duration_s=now - st.stop_since)]

    def _moved_while_off(self, device: str, st: _Device, rules: AlertRules, p: Position) -> list[Alert]:
        if p.ignition is None or not math.isfinite(rules.moved_while_off_m):
            return []
        if p.ignition:
            st.off_anchor, st.moved_fired = None, False
            return []
        a = st.off_anchor
        if a is None:
            st.off_anchor = p
            return []
        if st.moved_fired:
            return []
        d = _distance_m(a, p)
        if d <= max(rules.moved_while_off_m, rules.moved_k_sigma * math.hypot(a.sigma_m, p.sigma_m)):
            return []
        st.moved_fired = True
        return [self._alert("moved_while_off", device, st, p.t, distance_m=d, since=a.t, source="ignition")]

    # --- engine events and the clock -----------------------------------------------------

    def event(self, device: str, group: str, kind: str, t: float, attributes: dict[str, Any]) -> list[Alert]:
        """Evaluate one engine event (``fix_rejected``, ``moved_while_off``; others are ignored)."""
        rules = self.rules(group)
        if rules is None or not math.isfinite(t):
            return []
        st = self._state(device, group, rules)
        if kind == "fix_rejected" and rules.gnss_jump:
            first = t - st.last_reject_t >= rules.gnss_jump_hold_s
            st.last_reject_t = max(st.last_reject_t, t)
            if first:
                return [self._alert("gnss_jump_rejected", device, st, t, nis=attributes.get("nis"))]
            self._count("gnss_jump_joined")
        elif kind == "moved_while_off" and math.isfinite(rules.moved_while_off_m):
            detail = {k: v for k, v in attributes.items() if k not in ("type", "t")}
            return [self._alert("moved_while_off", device, st, t, source="engine", **detail)]
        return []

    def tick(self, now: float) -> list[Alert]:
        """Rules on the clock: ``silent`` and ``stop`` of devices that stopped reporting (``now``, s)."""
        out: list[Alert] = []
        for device, st in self.devices.items():
            rules = self.rules(st.group)
            if rules is None or st.last is None:
                continue
            if not st.silent_fired and now - st.last_received >= rules.silent_max_s:
                st.silent_fired = True
                out.append(self._alert("silent", device, st, now, last_received=st.last_received))
            out += self._stop_due(device, st, rules, now)
        return out


def alert_dict(a: Alert) -> dict[str, Any]:
    """The alert as a plain dict (JSON-ready: NaN as None)."""
    d = dataclasses.asdict(a)
    return {k: (None if isinstance(v, float) and not math.isfinite(v) else v) for k, v in d.items()}


__all__ = [
    "ALERT_KINDS",
    "Alert",
    "AlertEngine",
    "AlertRules",
    "Position",
    "alert_dict",
    "groups_from_dict",
    "rules_from_dict",
]
