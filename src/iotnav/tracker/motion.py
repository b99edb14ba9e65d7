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


def gap_rows(t: FloatArray, min_no_data_duration_s: float) -> BoolArray:
    """Rows next to a gap of at least ``min_no_data_duration_s`` (s) in ``t`` (False when 0)."""
    out = np.zeros(t.size, dtype=bool)
    if min_no_data_duration_s > 0 and t.size > 1:
        g = np.diff(t) >= min_no_data_duration_s
        out[:-1] |= g
        out[1:] |= g
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
        first confirmed switch the device is taken as stopped.
    """
    n = t.size
    if n == 0:
        return []
    flag = np.asarray(moving, dtype=bool) & ~gap_rows(t, rules.min_no_data_duration_s)
    step = np.append(np.diff(t), 0.0)
    state = False
    pending = -1
    last_move = -1
    moved_s = 0.0
    bounds: list[int] = []
    for i, m in enumerate(flag.tolist()):
        if m == state:
            if not (bridge_halts and not state and pending >= 0):
                pending = -1
                continue
            if t[i] - t[last_move] >= rules.min_parking_duration_s:
                pending = -1
            continue
        if pending < 0:
            pending = i
            moved_s = 0.0
        if m:
            held = moved_s if bridge_halts else t[i] - t[pending]
            moved_s += step[i]
            last_move = i
            switch = held >= rules.min_trip_duration_s or (
                distance_m[i] - distance_m[pending] >= rules.min_trip_distance_m
            )
        else:
            switch = t[i] - t[pending] >= rules.min_parking_duration_s
        if switch:
            bounds.append(pending)
            state = m
            pending = -1
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
