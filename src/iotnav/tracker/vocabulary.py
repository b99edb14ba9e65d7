"""The tracker's vocabulary of one engine's track: trips, stops, odometer, zones, events.

:func:`describe` takes any engine's output (a table with
:data:`iotnav.engines.base.OUTPUT_COLUMNS`: ``t``, ``lat``, ``lon``, ``vn``, ``ve``,
``static``, ``std_north``, ``std_east`` are read) and returns:

* trips and stops (:mod:`iotnav.tracker.motion`): the motion flag of
  :func:`~iotnav.tracker.motion.motion_evidence` (displacement beyond the uncertainty, the
  engine's static decision, a reported zero speed) through Traccar's documented hysteresis
  and thresholds, except that halts shorter than the parking duration do not reset a trip
  being confirmed (``bridge_halts``: Traccar's rule never confirms stop-and-go traffic whose
  runs between halts are shorter than 300 s and 500 m); boundaries are then placed where
  the position leaves or reaches the stop (:func:`refine_boundaries`);
* the odometer (:mod:`iotnav.tracker.odometer`): the engine's path from its speed (static
  rows 0, the jump at the ends of a static period counted beyond its noise) when every row
  has a velocity, else uncertainty-gated chords; counted only inside trips, so it does not grow
  while parked (the trips' "distance covered" of the hysteresis stays the gated chords:
  evidence of displacement, not a measure of it);
* geofence enter/exit (:mod:`iotnav.tracker.geofence`) with a margin of the uncertainty;
* the engine's own events a fleet user needs, passed through: ``moved_while_off`` (the
  device was carried while switched off; S1 boot) and ``fix_rejected`` with its reason
  (a refused jump; ``nis`` when the engine gave only a NIS).

Rows without a position are ignored. Positions go to one tangent plane at the first one
(:class:`iotnav.geo.LocalFrame`); the per-axis 1-sigma of a row is
``sqrt((std_north^2 + std_east^2) / 2)`` (``default_sigma_m`` when the engine gives none).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import asdict, dataclass, field
from typing import Any

import numpy as np
import numpy.typing as npt
import pandas as pd

from iotnav.geo import LocalFrame
from iotnav.tracker.geofence import Zone, geofence_events
from iotnav.tracker.motion import KNOT_MPS, Segment, TripRules, motion_evidence, segments
from iotnav.tracker.odometer import gated_increments, velocity_increments

FloatArray = npt.NDArray[np.float64]

TRIP_COLUMNS: tuple[str, ...] = (
    "kind",
    "t_start",
    "t_end",
    "duration_s",
    "distance_m",
    "max_speed_mps",
    "lat_start",
    "lon_start",
    "lat_end",
    "lon_end",
    "open",
)
"""Columns of a trips table (``trips.csv``): ``kind`` ``trip`` or ``stop``; times device s;
distance m (the odometer's growth over the period); speed m/s; positions degrees (a stop's
start and end are the median of its positions); ``open`` when the data ended before the
period's end was confirmed."""

PASSED_EVENTS = ("moved_while_off", "fix_rejected")
"""Engine event types the vocabulary passes through."""

ODOMETERS = ("velocity", "chords")
"""Odometer measures of :class:`TrackerConfig` (``odometer``)."""


@dataclass(frozen=True)
class TrackerConfig:
    """Settings of :func:`describe` (units in the names).

    Attributes
    ----------
    trips : TripRules
        Trip/stop hysteresis, Traccar's documented defaults.
    window_s : float
        Window of the motion test, s (60: a minute's median ignores any excursion shorter than
        30 s, and 0.5 m/s moves 30 m in it, above the 95 % noise bound of a receiver of
        5 m per axis).
    min_speed_mps : float
        Slowest speed counted as motion, m/s (0.5: below a slow walk, about 0.6-0.8 m/s, so
        that stop-and-go traffic at 1-5 m/s is motion).
    zero_speed_mps : float
        A row reporting this speed or less stands still, m/s (Traccar's
        ``event.motion.speedThreshold``, 0.01 knot).
    k_sigma : float
        Noise bound of a 2-D difference, in sigmas (``sqrt(chi2_2(0.95)) = 2.45``).
    odometer_k_sigma : float
        A step counts once beyond this many sigmas (4: a step of noise alone passes with
        probability ``exp(-8) = 3.4e-4``; on 1 Hz fixes of 1-5 m per axis the distance is then
        within 3 % of the truth at 1-10 m/s, straight or on bends of 50 m radius, where
        2.45 sigmas over-counts slow motion by 60 %).
    fence_k_sigma : float
        Geofence margin in sigmas normal to the border (3: the error normal to the border passes
        the margin with probability 0.13 % on each row).
    default_sigma_m : float
        Per-axis 1-sigma of rows without one, m (3: UERE 3 m, the engines' ``uere_m``, at
        HDOP 1.4, i.e. a 2-D 1-sigma of 4.2 m).
    odometer : str
        ``"velocity"`` (default): the trapezoid of the rows' speed
        (:func:`~iotnav.tracker.odometer.velocity_increments`), when every row has ``vn`` and
        ``ve``, else the chords; ``"chords"``: always the gated chords
        (:func:`~iotnav.tracker.odometer.gated_increments`; for raw fixes, whose Doppler speed
        carries the multipath error's derivative).
    odometer_median_s, odometer_spike_mps : float
        The ``"velocity"`` odometer's spike rule (:mod:`iotnav.tracker.odometer`): a speed
        farther than ``odometer_spike_mps`` (9.81 m/s: 1 g for a second) from the median of
        the speeds within ``odometer_median_s / 2`` seconds (5 s window) takes that median.
    max_rate_hz : float
        Rows closer than ``1 / max_rate_hz`` seconds to the previous kept row are left out
        (1 Hz: the rate of the fixes behind any engine's track; an engine's IMU-rate rows
        add detail far below the metres the vocabulary works in, and a day at 100 Hz would be
        8.6 M rows); 0 keeps every row.
    """

    trips: TripRules = field(default_factory=TripRules)
    window_s: float = 60.0
    min_speed_mps: float = 0.5
    zero_speed_mps: float = 0.01 * KNOT_MPS
    k_sigma: float = 2.45
    odometer_k_sigma: float = 4.0
    fence_k_sigma: float = 3.0
    default_sigma_m: float = 3.0
    odometer: str = "velocity"
    odometer_median_s: float = 5.0
    odometer_spike_mps: float = 9.81
    max_rate_hz: float = 1.0

    def __post_init__(self) -> None:
        if self.odometer not in ODOMETERS:
            raise ValueError(
                f"TrackerConfig.odometer {self.odometer!r}: expected one of {', '.join(ODOMETERS)}"
            )


@dataclass
class TrackerResult:
    """What :func:`describe` returns.

    Attributes
    ----------
    trips : pandas.DataFrame
        One row per trip and stop, :data:`TRIP_COLUMNS`.
    events : list of dict
        New events: ``trip_start``, ``trip_end``, ``geofence_enter``, ``geofence_exit``.
    engine_events : list of dict
        The engine's ``moved_while_off`` and ``fix_rejected`` events (each with ``reason``).
    odometer_m : float
        Distance over the trips, m.
    zones_initial : dict
        Zone name -> inside at the first position.
    config : TrackerConfig
    odometer : pandas.DataFrame
        ``t`` (s) and ``odometer_m`` (cumulative, m) at the rows the vocabulary used.
    odometer_measure : str
        The odometer's measure used: ``"velocity"``, or ``"chords"`` (asked for, or a row
        without a speed).
    """

    trips: pd.DataFrame
    events: list[dict[str, Any]]
    engine_events: list[dict[str, Any]]
    odometer_m: float
    zones_initial: dict[str, bool]
    config: TrackerConfig
    odometer: pd.DataFrame = field(default_factory=lambda: pd.DataFrame({"t": [], "odometer_m": []}))
    odometer_measure: str = "chords"

    def summary(self) -> dict[str, Any]:
        """Counts and the configuration, for ``summary.json``."""
        kinds = self.trips["kind"].to_numpy() if len(self.trips) else np.array([], dtype=object)
        dur = self.trips["duration_s"].to_numpy(float) if len(self.trips) else np.zeros(0)
        rejected: dict[str, int] = {}
        for e in self.engine_events:
            if e["type"] == "fix_rejected":
                rejected[e["reason"]] = rejected.get(e["reason"], 0) + 1
        return {
            "odometer_m": self.odometer_m,
            "odometer_measure": self.odometer_measure,
            "trips": int((kinds == "trip").sum()),
            "stops": int((kinds == "stop").sum()),
            "driving_s": float(dur[kinds == "trip"].sum()),
            "parked_s": float(dur[kinds == "stop"].sum()),
            "geofence_events": sum(e["type"].startswith("geofence_") for e in self.events),
            "zones_initial": self.zones_initial,
            "moved_while_off": sum(e["type"] == "moved_while_off" for e in self.engine_events),
            "fixes_rejected": rejected,
            "config": asdict(self.config),
        }


def per_axis_sigma(track: pd.DataFrame, default_m: float) -> FloatArray:
    """Per-axis horizontal 1-sigma of each row, m (``default_m`` where the track gives none)."""
    if "std_north" not in track.columns or "std_east" not in track.columns:
        return np.full(len(track), default_m)
    s = np.sqrt(0.5 * (track["std_north"].to_numpy(float) ** 2 + track["std_east"].to_numpy(float) ** 2))
    return np.where(np.isfinite(s) & (s > 0), s, default_m)


def horizontal_speed(track: pd.DataFrame) -> FloatArray:
    """``hypot(vn, ve)`` of each row, m/s (NaN without velocity columns)."""
    if "vn" not in track.columns or "ve" not in track.columns:
        return np.full(len(track), np.nan)
    return np.hypot(track["vn"].to_numpy(float), track["ve"].to_numpy(float))


def segment_table(
    t: FloatArray,
    lat_deg: FloatArray,
    lon_deg: FloatArray,
    odometer_m: FloatArray,
    speed_mps: FloatArray,
    segs: Sequence[Segment],
) -> pd.DataFrame:
    """The trips table (:data:`TRIP_COLUMNS`) of segments over rows with cumulative ``odometer_m``."""
    rows: list[dict[str, Any]] = []
    for s in segs:
        sl = slice(s.i0, s.i1 + 1)
        # a stop's bounds are its trips' first and last rows: its speed is its inner rows'
        sp = speed_mps[sl] if s.kind == "trip" else speed_mps[s.i0 + 1 : s.i1]
        sp = sp[np.isfinite(sp)]
        if s.kind == "stop":
            la0 = la1 = float(np.median(lat_deg[sl]))
            lo0 = lo1 = float(np.median(lon_deg[sl]))
        else:
            la0, lo0, la1, lo1 = (
                float(lat_deg[s.i0]),
                float(lon_deg[s.i0]),
                float(lat_deg[s.i1]),
                float(lon_deg[s.i1]),
            )
        rows.append(
            {
                "kind": s.kind,
                "t_start": float(t[s.i0]),
                "t_end": float(t[s.i1]),
                "duration_s": float(t[s.i1] - t[s.i0]),
                "distance_m": float(odometer_m[s.i1] - odometer_m[s.i0]),
                "max_speed_mps": float(sp.max()) if sp.size else math.nan,
                "lat_start": la0,
                "lon_start": lo0,
                "lat_end": la1,
                "lon_end": lo1,
                "open": s.open,
            }
        )
    return pd.DataFrame(rows, columns=list(TRIP_COLUMNS))


def passed_events(events: Sequence[dict[str, Any]]) -> list[dict[str, Any]]:
    """The engine's ``moved_while_off`` and ``fix_rejected`` events, each ``fix_rejected`` with a ``reason``."""
    out = []
    for e in events:
        if e.get("type") not in PASSED_EVENTS:
            continue
        e = dict(e)
        if e["type"] == "fix_rejected" and not e.get("reason"):
            e["reason"] = "nis" if "nis" in e else "unspecified"
        out.append(e)
    return out


def trip_events(table: pd.DataFrame) -> list[dict[str, Any]]:
    """``trip_start`` / ``trip_end`` events of a trips table (no end for an open trip)."""
    ev: list[dict[str, Any]] = []
    for r in table.itertuples(index=False):
        if r.kind != "trip":
            continue
        ev.append({"type": "trip_start", "t": r.t_start, "lat": r.lat_start, "lon": r.lon_start})
        if not r.open:
            ev.append(
                {
                    "type": "trip_end",
                    "t": r.t_end,
                    "lat": r.lat_end,
                    "lon": r.lon_end,
                    "distance_m": r.distance_m,
                    "duration_s": r.duration_s,
                }
            )
    return ev


def thin_mask(t: FloatArray, ok: npt.NDArray[np.bool_], min_dt_s: float) -> npt.NDArray[np.bool_]:
    """Rows of ``ok`` kept so that kept rows are at least ``min_dt_s`` apart (first and last kept)."""
    idx = np.flatnonzero(ok)
    keep = np.zeros(t.size, dtype=bool)
    if idx.size == 0:
        return keep
    tt = t[idx]
    if tt.size < 2 or float(np.min(np.diff(tt))) >= min_dt_s:
        keep[idx] = True
        return keep
    # first row of each time bin, on a grid anchored at the first row
    b = np.floor((tt - tt[0]) / min_dt_s)
    first = np.concatenate([[True], b[1:] != b[:-1]])
    first[-1] = True
    keep[idx[first]] = True
    return keep


def refine_boundaries(
    t: FloatArray,
    north: FloatArray,
    east: FloatArray,
    gate_m: FloatArray,
    segs: list[Segment],
    window_s: float,
) -> list[Segment]:
    """Trip starts and ends moved to where the position leaves / reaches the adjacent stop.

    The motion test's window flags motion up to half a window before it starts (and after it
    ends). A trip that follows a stop starts instead at the last row within ``window_s`` after
    the flagged start that lies within ``gate_m`` of the stop's median position; a trip
    followed by a stop ends at the first row within ``window_s`` before the flagged end that
    lies within ``gate_m`` of that stop's median. A lone jump inside the window cannot move
    either. The adjacent stop's bound moves with it.
    """
    out = list(segs)
    for k, s in enumerate(out):
        if s.kind != "trip":
            continue
        i0, i1 = s.i0, s.i1
        if k > 0:
            p = out[k - 1]
            an, ae = np.median(north[p.i0 : p.i1 + 1]), np.median(east[p.i0 : p.i1 + 1])
            j = np.arange(i0, i1 + 1)
            j = j[t[j] <= t[i0] + window_s]
            near = j[np.hypot(north[j] - an, east[j] - ae) <= gate_m[j]]
            if near.size:
                i0 = int(near[-1])
        if k + 1 < len(out) and not s.open:
            q = out[k + 1]
            an, ae = np.median(north[q.i0 : q.i1 + 1]), np.median(east[q.i0 : q.i1 + 1])
            j = np.arange(i0, i1 + 1)
            j = j[t[j] >= t[i1] - window_s]
            near = j[np.hypot(north[j] - an, east[j] - ae) <= gate_m[j]]
            if near.size:
                i1 = int(near[0])
        if i1 <= i0:
            continue
        out[k] = s._replace(i0=i0, i1=i1)
        if k > 0:
            out[k - 1] = out[k - 1]._replace(i1=i0)
        if k + 1 < len(out):
            out[k + 1] = out[k + 1]._replace(i0=i1)
    return out


def departure_starts(
    north: FloatArray,
    east: FloatArray,
    sigma_m: FloatArray,
    static: npt.NDArray[np.bool_],
    segs: list[Segment],
) -> list[Segment]:
    """Trips whose first row ends the engine's static state with a jump start one row earlier.

    An engine that holds its parked position until it confirms a departure re-initialises some
    metres on (the ``fixes`` engine: the distance covered while its departure test ran); when
    the trip's first row ``i0`` is that re-initialisation (row ``i0 - 1`` static, ``i0`` not, the
    step's chord beyond its noise: ``D^2 > 2 (s_a^2 + s_b^2)``, as
    :func:`~iotnav.tracker.odometer.velocity_increments` counts it), the trip starts at the
    held row ``i0 - 1`` so that its distance includes that displacement; the stop before ends
    there too.
    """
    out = list(segs)
    for k, s in enumerate(out):
        i = s.i0
        if s.kind != "trip" or k == 0 or i < 1 or out[k - 1].i0 >= i - 1:
            continue
        if not (static[i - 1] and not static[i]):
            continue
        d2 = (north[i] - north[i - 1]) ** 2 + (east[i] - east[i - 1]) ** 2
        if d2 > 2.0 * (sigma_m[i - 1] ** 2 + sigma_m[i] ** 2):
            out[k] = s._replace(i0=i - 1)
            out[k - 1] = out[k - 1]._replace(i1=i - 1)
    return out


def describe(
    track: pd.DataFrame,
    zones: Sequence[Zone] = (),
    config: TrackerConfig | None = None,
    engine_events: Sequence[dict[str, Any]] | None = None,
) -> TrackerResult:
    """Trips, stops, odometer, geofence events and passed-through events of a track.

    Parameters
    ----------
    track : pandas.DataFrame
        An engine's output (module docstring), rows in time order.
    zones : sequence of Zone
        Geofences (:func:`iotnav.tracker.geofence.zones_from_geojson`).
    config : TrackerConfig, optional
    engine_events : sequence of dict, optional
        The engine's events (default ``track.attrs["events"]``).

    Returns
    -------
    TrackerResult
    """
    cfg = config or TrackerConfig()
    events_in = engine_events if engine_events is not None else track.attrs.get("events", [])
    lat_all = track["lat"].to_numpy(float)
    lon_all = track["lon"].to_numpy(float)
    ok = np.isfinite(lat_all) & np.isfinite(lon_all)
    t_all = track["t"].to_numpy(float)
    if np.any(np.diff(t_all[ok]) < 0):
        raise ValueError("track: times go backwards (the vocabulary needs rows in time order)")
    if cfg.max_rate_hz > 0 and ok.any():
        ok &= thin_mask(t_all, ok, 1.0 / cfg.max_rate_hz)
    pos = track.loc[ok]
    t = t_all[ok]
    lat, lon = lat_all[ok], lon_all[ok]
    sigma = per_axis_sigma(pos, cfg.default_sigma_m)
    speed = horizontal_speed(pos)
    if t.size:
        ne = LocalFrame(float(lat[0]), float(lon[0]), 0.0).to_ned(lat, lon, np.zeros(t.size))
        north, east = ne[:, 0], ne[:, 1]
    else:
        north = east = np.zeros(0)
    static = pos["static"].to_numpy(bool) if "static" in pos.columns else np.zeros(t.size, dtype=bool)
    moving = motion_evidence(
        t, north, east, sigma, static, speed, cfg.window_s, cfg.min_speed_mps, cfg.k_sigma, cfg.zero_speed_mps
    )
    inc = gated_increments(north, east, sigma, cfg.odometer_k_sigma)
    # distance covered: the gated steps of rows with motion (a jump between two still rows adds none)
    segs = segments(t, moving, np.cumsum(np.where(moving, inc, 0.0)), cfg.trips, bridge_halts=True)
    segs = refine_boundaries(t, north, east, cfg.k_sigma * math.sqrt(2.0) * sigma, segs, cfg.window_s)
    measure = "velocity" if cfg.odometer == "velocity" and bool(np.all(np.isfinite(speed))) else "chords"
    if measure == "velocity" and t.size:
        inc = velocity_increments(
            t, north, east, sigma, speed, static, cfg.odometer_median_s, cfg.odometer_spike_mps
        )
        segs = departure_starts(north, east, sigma, static, segs)
    in_trip = np.zeros(t.size, dtype=bool)
    for s in segs:
        if s.kind == "trip":
            in_trip[s.i0 + 1 : s.i1 + 1] = True
    odo = np.cumsum(np.where(in_trip, inc, 0.0))
    table = segment_table(t, lat, lon, odo, speed, segs)
    fence, initial = geofence_events(t, lat, lon, sigma, list(zones), cfg.fence_k_sigma)
    events = sorted(trip_events(table) + fence, key=lambda e: e["t"])
    return TrackerResult(
        trips=table,
        events=events,
        engine_events=passed_events(events_in),
        odometer_m=float(odo[-1]) if odo.size else 0.0,
        zones_initial=initial,
        config=cfg,
        odometer=pd.DataFrame({"t": t, "odometer_m": odo}),
        odometer_measure=measure,
    )


def track_from_fixes(gnss: pd.DataFrame, uere_m: float = 3.0, default_hdop: float = 2.0) -> pd.DataFrame:
    """The valid fixes of a GNSS table as a track (:data:`~iotnav.engines.base.OUTPUT_COLUMNS`).

    For the vocabulary of raw fixes (no engine): ``source`` ``fix``, ``static`` False,
    ``std_north`` = ``std_east`` = the per-axis sigma of
    :func:`iotnav.gnss_accuracy.position_sigmas` (``h_acc_m``, else HDOP/PDOP x ``uere_m``,
    else ``default_hdop``; 3 m and 2.0 as the anchor engine's defaults), velocity from the
    fix's ``vn``/``ve`` or its speed and course.

    Parameters
    ----------
    gnss : pandas.DataFrame
        A :data:`iotnav.io.schema.GNSS_COLUMNS` table.
    uere_m : float
        User-equivalent range error, m.
    default_hdop : float
        HDOP of fixes that carry no accuracy figure.
    """
    from iotnav.engines.base import OUTPUT_COLUMNS
    from iotnav.gnss_accuracy import position_sigmas

    valid = gnss["valid"].to_numpy(bool) if "valid" in gnss.columns else np.ones(len(gnss), bool)
    g = gnss.loc[
        valid & np.isfinite(gnss["lat_deg"].to_numpy(float)) & np.isfinite(gnss["lon_deg"].to_numpy(float))
    ]

    def col(name: str) -> FloatArray:
        return g[name].to_numpy(float) if name in g.columns else np.full(len(g), np.nan)

    h_acc, v_acc, hdop, pdop = col("h_acc_m"), col("v_acc_m"), col("hdop"), col("pdop")
    sig = np.array(
        [
            position_sigmas(a, b, c, d, uere_m, default_hdop).north_east_m
            for a, b, c, d in zip(h_acc.tolist(), v_acc.tolist(), hdop.tolist(), pdop.tolist(), strict=True)
        ]
    )
    vn, ve = col("vn"), col("ve")
    spd, crs = col("speed_mps"), col("course_rad")
    no_v = ~(np.isfinite(vn) & np.isfinite(ve))
    vn = np.where(no_v, spd * np.cos(np.where(np.isfinite(crs), crs, 0.0)), vn)
    ve = np.where(no_v, spd * np.sin(np.where(np.isfinite(crs), crs, 0.0)), ve)
    n = len(g)
    nan = np.full(n, np.nan)
    out = pd.DataFrame(
        {
            "t": col("t"),
            "lat": col("lat_deg"),
            "lon": col("lon_deg"),
            "height": col("height_m"),
            "north": nan,
            "east": nan,
            "down": nan,
            "vn": vn,
            "ve": ve,
            "vd": col("vd"),
            "roll": nan,
            "pitch": nan,
            "yaw": nan,
            "static": np.zeros(n, dtype=bool),
            "std_north": sig if n else nan,
            "std_east": sig if n else nan,
            "source": "fix",
        },
        columns=list(OUTPUT_COLUMNS),
    )
    return out.reset_index(drop=True)
