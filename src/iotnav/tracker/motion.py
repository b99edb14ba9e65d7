"""Trips and stops from a per-row motion flag, with Traccar's hysteresis.

A fleet report turns a stream of positions into trips (driving) and stops (parking). Two
things decide it: a per-row *motion* flag, and the hysteresis that turns that noisy flag into
long periods. This module holds both halves apart:

* :func:`segments` is the hysteresis, one formulation of the rule Traccar documents
  ("Trips and Stops", https://www.traccar.org/documentation-trips-stops/): the state switches
  from stopped to moving when the flag stays true for at least ``min_trip_duration_s`` or the
  distance covered meanwhile reaches ``min_trip_distance_m``; from moving to stopped when it
  stays false for at least ``min_parking_duration_s``; "only continuous periods can switch the
  state, any fluctuations reset the detection"; a gap of ``min_no_data_duration_s`` or more
  between two rows makes both rows stopped. The switch is dated at the first row of the
  continuous period that caused it (a trip starts when the motion that confirmed it began).
  The defaults are Traccar's documented ones (``report.trip.minimalTripDuration`` 300 s,
  ``report.trip.minimalTripDistance`` 500 m, ``report.trip.minimalParkingDuration`` 300 s,
  ``report.trip.minimalNoDataDuration`` 3600 s; ``org.traccar.config.Keys``).
* the flag: Traccar takes ``speed > event.motion.speedThreshold`` (0.01 knot) of each position
  (:mod:`iotnav.eval.traccar`); iotnav's vocabulary takes :func:`motion_evidence`, which asks
  for displacement beyond the positions' uncertainty over a window, and believes the engine's
  ``static`` decision and a reported zero speed.

Times are device seconds, distances metres, speeds m/s.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np
import numpy.typing as npt
import pandas as pd

FloatArray = npt.NDArray[np.float64]
BoolArray = npt.NDArray[np.bool_]

KNOT_MPS = 1852.0 / 3600.0
"""One knot in m/s (Traccar's speed unit)."""


@dataclass(frozen=True)
class TripRules:
    """Hysteresis of trips and stops (module docstring; defaults: Traccar's documented ones).

    Attributes
    ----------
    min_trip_duration_s : float
        Motion lasting this long (s) confirms a trip (``report.trip.minimalTripDuration``, 300).
    min_trip_distance_m : float
        Motion covering this distance (m) confirms a trip (``report.trip.minimalTripDistance``, 500).
    min_parking_duration_s : float
        No motion for this long (s) confirms a stop (``report.trip.minimalParkingDuration``, 300).
    min_no_data_duration_s : float
        A gap between rows this long (s) or longer is a stop (``report.trip.minimalNoDataDuration``,
        3600); 0 disables.
    """

    min_trip_duration_s: float = 300.0
    min_trip_distance_m: float = 500.0
    min_parking_duration_s: float = 300.0
    min_no_data_duration_s: float = 3600.0


class Segment(NamedTuple):
    """A trip or a stop: rows ``i0 .. i1`` (inclusive; a trip's last row is the next stop's first)."""

    kind: str
    i0: int
    i1: int
    open: bool
    """True for the last segment when its end was not confirmed (the data ended first)."""


class Switch(NamedTuple):
    """A confirmed change of state: ``moving`` the new state, dated at row ``i0`` (time ``t0``, s)."""

    moving: bool
    i0: int
    t0: float


class TripHysteresis:
    """The hysteresis of :func:`segments`, one row at a time (streaming; :func:`segments` loops over it).

    A row's fate depends on the time of the next row (a gap of ``min_no_data_duration_s`` after
    it makes it stopped; with ``bridge_halts`` its moving time runs to the next row), so
    :meth:`push` decides the row before the one it is given, and :meth:`flush` the last one.

    Parameters
    ----------
    rules : TripRules
        Thresholds.
    bridge_halts : bool
        As in :func:`segments`.
    """

    def __init__(self, rules: TripRules, bridge_halts: bool = False) -> None:
        self.rules = rules
        self.bridge_halts = bridge_halts
        self.moving = False
        """The confirmed state (the device is taken as stopped before the first switch)."""
        self.n = 0
        self._held: tuple[int, float, bool, float, bool] | None = None
        self._pending = -1
        self._pending_t = self._pending_d = self._last_move_t = self._moved_s = 0.0

    def push(self, t: float, moving: bool, distance_m: float) -> Switch | None:
        """Add a row (time s, motion flag, cumulative distance m); the switch the previous row caused."""
        out = None
        gap = False
        if self._held is not None:
            i, t0, m0, d0, gap_before = self._held
            nd = self.rules.min_no_data_duration_s
            gap = nd > 0 and t - t0 >= nd
            out = self.decide(i, t0, m0 and not (gap_before or gap), d0, t - t0)
        self._held = (self.n, t, bool(moving), distance_m, gap)
        self.n += 1
        return out

    def flush(self) -> Switch | None:
        """Decide the last row pushed (no next row: no gap after it, no time to the next)."""
        if self._held is None:
            return None
        i, t0, m0, d0, gap_before = self._held
        self._held = None
        return self.decide(i, t0, m0 and not gap_before, d0, 0.0)

    def decide(self, i: int, t: float, m: bool, d: float, step: float) -> Switch | None:
        """Decide row ``i`` (time s, motion flag with the gap rule applied, cumulative distance m,
        time to the next row s); the switch it causes (:meth:`push` calls it one row late)."""
        r = self.rules
        if m == self.moving:
            if not (self.bridge_halts and not self.moving and self._pending >= 0):
                self._pending = -1
            elif t - self._last_move_t >= r.min_parking_duration_s:
                self._pending = -1
            return None
        if self._pending < 0:
            self._pending, self._pending_t, self._pending_d = i, t, d
            self._moved_s = 0.0
        if m:
            held = self._moved_s if self.bridge_halts else t - self._pending_t
            self._moved_s += step
            self._last_move_t = t
            switch = held >= r.min_trip_duration_s or d - self._pending_d >= r.min_trip_distance_m
        else:
            switch = t - self._pending_t >= r.min_parking_duration_s
        if not switch:
            return None
        out = Switch(m, self._pending, self._pending_t)
        self.moving = m
        self._pending = -1
        return out


def segments(
    t: FloatArray,
    moving: BoolArray,
    distance_m: FloatArray,
    rules: TripRules,
    bridge_halts: bool = False,
) -> list[Segment]:
    """Trips and stops of a motion flag with the hysteresis of :class:`TripRules`.

    Parameters
    ----------
    t : numpy.ndarray
        Row times, s, non-decreasing.
    moving : numpy.ndarray of bool
        Per-row motion flag.
    distance_m : numpy.ndarray
        Cumulative distance at each row, m: a pending trip's "distance covered" is its growth
        since the trip's first row.
    rules : TripRules
        Thresholds.
    bridge_halts : bool
        Traccar (False): any row without motion resets a pending trip. iotnav (True): a
        pending trip is reset only by ``min_parking_duration_s`` without motion (the halts of
        stop-and-go traffic do not reset it), and its duration counts the moving rows only
        (time from each moving row to the next row).

    Returns
    -------
    list of Segment
        Alternating stops and trips covering all rows (zero-length periods left out). Before the
        first confirmed switch the device is taken as stopped. The rows go through
        :class:`TripHysteresis`, the streaming form.
    """
    n = t.size
    if n == 0:
        return []
    hyst = TripHysteresis(rules, bridge_halts)
    # what push() learns from the next row, for all rows at once: rows next to a gap, time to the next
    flag = np.asarray(moving, dtype=bool).copy()
    nd = rules.min_no_data_duration_s
    if nd > 0 and n > 1:
        gap = np.diff(t) >= nd
        flag[:-1] &= ~gap
        flag[1:] &= ~gap
    step = np.append(np.diff(t), 0.0)
    decide = hyst.decide
    bounds: list[int] = []
    rows = zip(
        t.tolist(), flag.tolist(), np.asarray(distance_m, dtype=float).tolist(), step.tolist(), strict=True
    )
    for i, (ti, m, d, dt) in enumerate(rows):
        sw = decide(i, ti, m, d, dt)
        if sw is not None:
            bounds.append(sw.i0)
    out: list[Segment] = []
    kind = "stop"
    start = 0
    for b in bounds:
        if b > start:
            out.append(Segment(kind, start, b, False))
        kind = "trip" if kind == "stop" else "stop"
        start = b
    if start < n - 1 or not out:
        out.append(Segment(kind, start, n - 1, True))
    return out


def _median_positions(t: FloatArray, x: FloatArray, window_s: float) -> FloatArray:
    """Median of ``x`` over the rows in ``(t - window_s, t]``, per row (NaN ignored)."""
    s = pd.Series(x, index=pd.to_timedelta(t, unit="s"))
    return s.rolling(pd.Timedelta(seconds=window_s), min_periods=1).median().to_numpy(float)


def motion_evidence(
    t: FloatArray,
    north: FloatArray,
    east: FloatArray,
    sigma_m: FloatArray,
    static: BoolArray,
    speed_mps: FloatArray,
    window_s: float,
    min_speed_mps: float,
    k_sigma: float,
    zero_speed_mps: float,
) -> BoolArray:
    """Per-row motion flag from displacement beyond the uncertainty (iotnav's vocabulary).

    For each row the median position of the rows in the ``W`` seconds before it and of those
    in the ``W`` seconds after it are compared (medians: a jump lasting less than half the
    window does not move them). ``W`` is ``window_s`` or three median row intervals, whichever
    is longer (sparse fixes). The row moves when that displacement ``d`` passes both

    * ``min_speed_mps * W`` (the two medians sit about ``W`` apart in time), and
    * ``k_sigma * sqrt(2) * sigma`` (the 95 % bound of the difference of two positions of
      per-axis 1-sigma ``sigma``, for ``k_sigma = 2.45 = sqrt(chi2_2(0.95))``),

    and the row is neither flagged ``static`` by the engine nor reports a speed of at most
    ``zero_speed_mps`` (a receiver or engine that says it stands still is believed).

    Parameters
    ----------
    t : numpy.ndarray
        Times, s, non-decreasing.
    north, east : numpy.ndarray
        Positions in one tangent plane, m (NaN rows never move).
    sigma_m : numpy.ndarray
        Per-axis horizontal 1-sigma, m.
    static : numpy.ndarray of bool
        The engine's static decision.
    speed_mps : numpy.ndarray
        Horizontal speed, m/s (NaN: not known).
    window_s, min_speed_mps, k_sigma, zero_speed_mps : float
        See above.

    Returns
    -------
    numpy.ndarray of bool
    """
    n = t.size
    if n == 0:
        return np.zeros(0, dtype=bool)
    dt = np.diff(t)
    w = max(window_s, 3.0 * float(np.median(dt)) if dt.size else 0.0)
    back_n = _median_positions(t, north, w)
    back_e = _median_positions(t, east, w)
    rt = t[-1] - t[::-1]  # time reversed: the "before" window of the reversed series is "after"
    fwd_n = _median_positions(rt, north[::-1], w)[::-1]
    fwd_e = _median_positions(rt, east[::-1], w)[::-1]
    d = np.hypot(fwd_n - back_n, fwd_e - back_e)
    gate = np.maximum(min_speed_mps * w, k_sigma * math.sqrt(2.0) * sigma_m)
    stands = np.isfinite(speed_mps) & (speed_mps <= zero_speed_mps)
    ok = np.isfinite(d) & np.isfinite(north) & np.isfinite(east)
    return ok & (d > gate) & ~np.asarray(static, dtype=bool) & ~stands
