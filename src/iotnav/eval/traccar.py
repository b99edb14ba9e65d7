"""A baseline of Traccar's position rules: FilterHandler, DistanceHandler odometer, trip report.

Traccar (https://www.traccar.org, the open-source fleet server) cleans each incoming position
by comparing it with the *last stored* position only; nothing has a motion model. This module
reproduces the documented rules, written from the documentation of the configuration keys
(``org.traccar.config.Keys`` javadoc, https://www.traccar.org/configuration-file/) and the
"Trips and Stops" page (https://www.traccar.org/documentation-trips-stops/), so that raw
fixes, Traccar's rules and iotnav can be compared on the same logs. The processing order is
Traccar's handler chain: the distance handler, then the filter, then motion and reports.

Distance (``DistanceHandler``, keys ``coordinates.*``)
    ``distance`` is the great-circle (haversine) distance from the last stored position, on a
    sphere of radius 6378.137 km; ``totalDistance`` (the odometer) adds it up. With
    ``coordinates.filter`` the coordinates are replaced by the last ones (and ``distance`` is
    0) when the change is at most ``coordinates.minError`` metres, or at least
    ``coordinates.maxError`` metres for a position that is also marked invalid
    ("helps to avoid coordinates jumps during parking period or jumps to zero coordinates").
    A limit of 0 is off.

Filter (``FilterHandler``, keys ``filter.*``, all off by default; ``filter.enable`` gates them)
    A position is dropped (never stored, so the next one is compared with the same last
    position) when any enabled rule holds:

    * ``invalid``: marked invalid, or latitude / longitude out of range;
    * ``zero``: latitude and longitude both exactly 0;
    * ``duplicate``: the same fix time as the last position;
    * ``future`` / ``past``: fix time more than that many seconds after / before the
      server's time (here: the time the fix arrived, ``t_server``, default the fix time);
    * ``accuracy``: accuracy (m; here ``h_acc_m``, 0 when unknown) above the value;
    * ``static``: speed exactly 0;
    * ``distance``: ``distance`` below the value, m;
    * ``maxSpeed``: ``distance / elapsed time`` above the value, knots;
    * ``minPeriod``: less than that many seconds (and more than 0) after the last position;
    * ``skipLimit``: ``duplicate``, ``static`` and ``distance`` do not apply when more than
      that many seconds passed (server time) since the last position.

Motion and trips (keys ``event.motion.speedThreshold``, ``report.trip.*``)
    A position moves when its speed exceeds 0.01 knot. Trips and stops follow
    :func:`iotnav.tracker.motion.segments` without bridging: motion for 300 s or 500 m
    confirms a trip, 300 s without motion a stop, any fluctuation resets, a gap of 3600 s is
    a stop; a trip's distance is the growth of ``totalDistance``.

Not reproduced: device attributes and ``filter.skipAttributes``, calendars, ``dailyLimit``,
``approximate``/``outdated`` (cell and Wi-Fi positions), ``filter.relative`` (out-of-order
arrival), ignition, and the spatial "new trip logic" (``report.trip.newLogic``). Epochs
without a position are not positions for Traccar (a decoder would attach the last known
location and mark it outdated): they are counted (``no_position``) and left out.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, field
from typing import Any

import numpy as np
import numpy.typing as npt
import pandas as pd

from iotnav.tracker.motion import KNOT_MPS, TripRules, segments
from iotnav.tracker.vocabulary import segment_table

FloatArray = npt.NDArray[np.float64]

EARTH_RADIUS_M = 6378137.0
"""Sphere of Traccar's distance calculator (equatorial radius), m."""


@dataclass(frozen=True)
class TraccarFilter:
    """``filter.*`` keys (units in the names; 0 / False is off, the documented default)."""

    enable: bool = False
    invalid: bool = False
    zero: bool = False
    duplicate: bool = False
    future_s: float = 0.0
    past_s: float = 0.0
    accuracy_m: float = 0.0
    static: bool = False
    distance_m: float = 0.0
    max_speed_kn: float = 0.0
    min_period_s: float = 0.0
    skip_limit_s: float = 0.0


@dataclass(frozen=True)
class TraccarCoordinates:
    """``coordinates.filter``, ``coordinates.minError``, ``coordinates.maxError`` (m; off by default)."""

    filter: bool = False
    min_error_m: float = 0.0
    max_error_m: float = 0.0


@dataclass(frozen=True)
class TraccarConfig:
    """All rules; the defaults are Traccar's documented ones (module docstring)."""

    filter: TraccarFilter = field(default_factory=TraccarFilter)
    coordinates: TraccarCoordinates = field(default_factory=TraccarCoordinates)
    trips: TripRules = field(default_factory=TripRules)
    speed_threshold_kn: float = 0.01


@dataclass
class TraccarResult:
    """Output of :func:`traccar_rules`.

    Attributes
    ----------
    positions : pandas.DataFrame
        Stored positions: ``t`` (fix time, s), ``lat``, ``lon`` (degrees, possibly replaced by
        ``coordinates.filter``), ``valid``, ``speed_mps``, ``distance_m``,
        ``total_distance_m``, ``motion``, ``replaced`` (coordinates replaced).
    dropped : dict
        Rule name -> positions it dropped (a position dropped by two rules counts for both),
        plus ``no_position``.
    n_dropped : int
        Positions dropped (each once).
    trips : pandas.DataFrame
        Trips and stops, :data:`iotnav.tracker.TRIP_COLUMNS`.
    config : TraccarConfig
    """

    positions: pd.DataFrame
    dropped: dict[str, int]
    n_dropped: int
    trips: pd.DataFrame
    config: TraccarConfig

    @property
    def odometer_m(self) -> float:
        """Final ``totalDistance``, m."""
        return float(self.positions["total_distance_m"].iloc[-1]) if len(self.positions) else 0.0

    def track(self, t: FloatArray) -> pd.DataFrame:
        """The position Traccar shows at times ``t`` (s): the last stored one (NaN before any)."""
        p = self.positions
        lat = np.full(t.size, np.nan)
        lon = np.full(t.size, np.nan)
        if len(p):
            k = np.searchsorted(p["t"].to_numpy(float), t, side="right") - 1
            seen = k >= 0
            lat[seen] = p["lat"].to_numpy(float)[k[seen]]
            lon[seen] = p["lon"].to_numpy(float)[k[seen]]
        return pd.DataFrame({"t": t, "lat": lat, "lon": lon})

    def summary(self) -> dict[str, Any]:
        """Counts, odometer and configuration."""
        kinds = self.trips["kind"].to_numpy() if len(self.trips) else np.array([], dtype=object)
        return {
            "stored": len(self.positions),
            "dropped": self.n_dropped,
            "dropped_by_rule": dict(self.dropped),
            "odometer_m": self.odometer_m,
            "trips": int((kinds == "trip").sum()),
            "stops": int((kinds == "stop").sum()),
            "config": asdict(self.config),
        }


def haversine_m(lat1: float, lon1: float, lat2: float, lon2: float) -> float:
    """Great-circle distance on a sphere of :data:`EARTH_RADIUS_M`, m (degrees in)."""
    p1, p2 = math.radians(lat1), math.radians(lat2)
    a = (
        math.sin((p2 - p1) / 2) ** 2
        + math.cos(p1) * math.cos(p2) * math.sin(math.radians(lon2 - lon1) / 2) ** 2
    )
    return 2.0 * EARTH_RADIUS_M * math.atan2(math.sqrt(a), math.sqrt(1.0 - a))


def _col(g: pd.DataFrame, name: str, default: float) -> FloatArray:
    return g[name].to_numpy(float) if name in g.columns else np.full(len(g), default)


def traccar_rules(
    gnss: pd.DataFrame, config: TraccarConfig | None = None, t_server: FloatArray | None = None
) -> TraccarResult:
    """Traccar's rules over a GNSS table, one position at a time (module docstring).

    Parameters
    ----------
    gnss : pandas.DataFrame
        A :data:`iotnav.io.schema.GNSS_COLUMNS` table (``t``, ``lat_deg``, ``lon_deg``,
        ``valid``, ``speed_mps``, ``h_acc_m`` are read), in arrival order.
    config : TraccarConfig, optional
        Rules (default: Traccar's documented defaults).
    t_server : numpy.ndarray, optional
        Arrival (server) time of each row, s on the fix-time axis (default: the fix time).

    Returns
    -------
    TraccarResult
    """
    cfg = config or TraccarConfig()
    f, co = cfg.filter, cfg.coordinates
    t = _col(gnss, "t", math.nan)
    lat_in, lon_in = _col(gnss, "lat_deg", math.nan), _col(gnss, "lon_deg", math.nan)
    valid_in = gnss["valid"].to_numpy(bool) if "valid" in gnss.columns else np.ones(len(gnss), bool)
    speed_in = np.nan_to_num(_col(gnss, "speed_mps", 0.0), nan=0.0)
    acc_in = np.nan_to_num(_col(gnss, "h_acc_m", 0.0), nan=0.0)
    ts = t if t_server is None else np.asarray(t_server, dtype=float)
    dropped: dict[str, int] = {}
    n_dropped = 0
    rows: list[tuple[float, float, float, bool, float, float, float, bool]] = []
    last: tuple[float, float, float, bool, float, float, float, bool] | None = None
    last_ts = math.nan
    for i in range(len(gnss)):
        lat, lon, valid = float(lat_in[i]), float(lon_in[i]), bool(valid_in[i])
        if not (math.isfinite(lat) and math.isfinite(lon)):
            dropped["no_position"] = dropped.get("no_position", 0) + 1
            n_dropped += 1
            continue
        ti, speed = float(t[i]), float(speed_in[i])
        # DistanceHandler
        distance = 0.0
        total = 0.0
        replaced = False
        if last is not None:
            total = last[6]
            distance = haversine_m(lat, lon, last[1], last[2])
            if co.filter and last[1] != 0 and last[2] != 0:
                ok_min = co.min_error_m == 0 or distance > co.min_error_m
                ok_max = co.max_error_m == 0 or distance < co.max_error_m or valid
                if not (ok_min and ok_max):
                    lat, lon, valid, distance, replaced = last[1], last[2], last[3], 0.0, True
        # FilterHandler
        why: list[str] = []
        if f.enable:
            if f.invalid and (not valid or abs(lat) > 90 or abs(lon) > 180):
                why.append("invalid")
            if f.zero and lat == 0.0 and lon == 0.0:
                why.append("zero")
            if f.future_s and ti > ts[i] + f.future_s:
                why.append("future")
            if f.past_s and ti < ts[i] - f.past_s:
                why.append("past")
            if f.accuracy_m and acc_in[i] > f.accuracy_m:
                why.append("accuracy")
            if last is not None:
                skip = bool(f.skip_limit_s) and ts[i] - last_ts > f.skip_limit_s
                dt = ti - last[0]
                if f.duplicate and ti == last[0] and not skip:
                    why.append("duplicate")
                if f.static and speed == 0.0 and not skip:
                    why.append("static")
                if f.distance_m and distance < f.distance_m and not skip:
                    why.append("distance")
                if f.max_speed_kn:
                    v = distance / dt if dt > 0 else (math.inf if distance > 0 else math.nan)
                    if v / KNOT_MPS > f.max_speed_kn:
                        why.append("max_speed")
                if f.min_period_s and 0 < dt < f.min_period_s:
                    why.append("min_period")
            elif f.static and speed == 0.0:
                why.append("static")
        if why:
            n_dropped += 1
            for w in why:
                dropped[w] = dropped.get(w, 0) + 1
            continue
        last = (ti, lat, lon, valid, speed, distance, total + distance, replaced)
        last_ts = float(ts[i])
        rows.append(last)
    cols = ["t", "lat", "lon", "valid", "speed_mps", "distance_m", "total_distance_m", "replaced"]
    pos = pd.DataFrame(rows, columns=cols)
    pos["motion"] = pos["speed_mps"].to_numpy(float) / KNOT_MPS > cfg.speed_threshold_kn
    tp = pos["t"].to_numpy(float)
    segs = segments(tp, pos["motion"].to_numpy(bool), pos["total_distance_m"].to_numpy(float), cfg.trips)
    table = segment_table(
        tp,
        pos["lat"].to_numpy(float),
        pos["lon"].to_numpy(float),
        pos["total_distance_m"].to_numpy(float),
        pos["speed_mps"].to_numpy(float),
        segs,
    )
    return TraccarResult(pos, dropped, n_dropped, table, cfg)
