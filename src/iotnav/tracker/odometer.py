"""Distance travelled, counted only for displacement beyond the positions' uncertainty.

Summing the distance between successive positions adds the noise: a parked receiver whose
fixes scatter by ``s`` metres per axis gains about ``1.8 s`` metres per fix (the mean of a
Rayleigh distance of scale ``sqrt(2) s``), kilometres a day. :func:`gated_increments` sums
instead the distance between *kept* points: a row is kept when it lies farther from the last
kept point than ``k_sigma * sqrt(s_last^2 + s_row^2)``, the distance between two positions of
per-axis 1-sigma ``s_last`` and ``s_row`` being Rayleigh with scale ``sqrt(s_last^2 + s_row^2)``
when nothing moved: it passes ``k_sigma`` scales with probability ``exp(-k_sigma^2 / 2)``
(``k_sigma = 4``: 3.4e-4). Moving rows are kept as soon as they clear their uncertainty (every
fix at driving speed); the noise of parked rows mostly is not. Each kept step is debiased:
two points of per-axis sigmas ``s_a``, ``s_b`` lie ``D`` apart with
``E[D^2] = d^2 + 2 (s_a^2 + s_b^2)`` (two axes), so the step counts
``sqrt(D^2 - 2 (s_a^2 + s_b^2))`` (positive: a kept step has ``D^2 > 6 (s_a^2 + s_b^2)``).
The vocabulary then counts
the increments only inside trips (:mod:`iotnav.tracker.vocabulary`), so a parked vehicle's
odometer does not move.

Chords cut corners and the gate only holds when the rows' errors are independent:

* between sparse fixes (one every 30 s at 8-15 m/s, about 300 m) a chord is shorter than the
  road (-2 to -3 % on the simulated ``sparse-drive``, turns of up to 90 degrees);
* an engine's track reports the *absolute* sigma of each row (floored at the fix's own, the
  errors being time-correlated), while the error *between* two nearby rows of a filtered
  track is far smaller: the gate of ``4 sqrt(2) sigma`` (43 m in an urban canyon of 7.6 m per
  axis) and the debiasing then count 6-10 % too little on ``stop-and-go`` (1-5 m/s).

:func:`velocity_increments` therefore measures the engine's path from its velocity: each step
between two rows counts the trapezoid of the two rows' horizontal speeds times the time
between them (the path of a constant-acceleration motion along the track; exact on any curve
at constant speed), 0 between two rows the engine flags static. A row's speed that departs
by more than ``spike_mps`` (9.81 m/s: 1 g for a second; tyre-road friction bounds a road
vehicle's braking near 1 g, its acceleration below) from the median of the non-static rows'
speeds within ``median_s / 2`` (2.5 s) of it is not a speed and takes that median: a smoother
that spreads an accepted multipath jump of 40 m over the one or two rejected fixes before it
gives those rows 25-30 m/s in 1-5 m/s traffic (the ``fixes`` engine's smoothed ``stop-and-go``,
seed 2: +3.2 % of distance with them, +0.1 % without). The median is not applied to every row:
it clips the short dips of real driving (braking, corners) and added 0.3 % on drive_0708.
Where the engine's static
state begins or ends its position may jump (the fixes engine holds the parked position until
its departure test confirms a departure, then re-initialises at the fix some metres on): that
step counts the larger of the speed trapezoid and the debiased chord
``sqrt(D^2 - 2 (s_a^2 + s_b^2))`` (0 when negative), the displacement the velocity did not
carry. A track without a speed on every row counts the gated chords above. A receiver's raw
Doppler velocity is not an engine's: in a canyon it carries the derivative of the multipath
error (a parked receiver reads 0.7 m/s, median, in the simulated canyon) and integrating it
adds 10-12 % on ``stop-and-go`` (its halts, which no static flag covers); the vocabulary of raw
fixes takes the chords (``TrackerConfig(odometer="chords")``).
"""

from __future__ import annotations

import math

import numba
import numpy as np
import numpy.typing as npt
import pandas as pd

FloatArray = npt.NDArray[np.float64]


@numba.njit(cache=True)
def _gated(north: FloatArray, east: FloatArray, sigma_m: FloatArray, k_sigma: float) -> FloatArray:
    n = north.size
    inc = np.zeros(n)
    last = -1
    nl = el = sl = 0.0
    for i in range(n):
        ni, ei, si = north[i], east[i], sigma_m[i]
        if not (math.isfinite(ni) and math.isfinite(ei)):
            continue
        if last < 0:
            last, nl, el, sl = i, ni, ei, si
            continue
        d2 = (ni - nl) ** 2 + (ei - el) ** 2
        s2 = sl * sl + si * si
        if d2 > k_sigma * k_sigma * s2:
            inc[i] = math.sqrt(d2 - 2.0 * s2)
            last, nl, el, sl = i, ni, ei, si
    return inc


def gated_increments(north: FloatArray, east: FloatArray, sigma_m: FloatArray, k_sigma: float) -> FloatArray:
    """Distance (m) added at each row: the debiased step from the last kept point when kept, else 0.

    Parameters
    ----------
    north, east : numpy.ndarray
        Positions in one tangent plane, m (NaN rows add nothing and are never kept).
    sigma_m : numpy.ndarray
        Per-axis horizontal 1-sigma of each row, m.
    k_sigma : float
        Multiple of the combined sigma a step must exceed.

    Returns
    -------
    numpy.ndarray
        Per-row increment, m, ``>= 0``.
    """
    f = np.ascontiguousarray
    return _gated(f(north, dtype=float), f(east, dtype=float), f(sigma_m, dtype=float), float(k_sigma))


@numba.njit(cache=True)
def _velocity(
    t: FloatArray,
    north: FloatArray,
    east: FloatArray,
    sigma_m: FloatArray,
    speed: FloatArray,
    static: npt.NDArray[np.bool_],
) -> FloatArray:
    n = t.size
    inc = np.zeros(n)
    for i in range(1, n):
        if static[i - 1] and static[i]:
            continue
        va = 0.0 if static[i - 1] else speed[i - 1]
        vb = 0.0 if static[i] else speed[i]
        step = 0.5 * (va + vb) * (t[i] - t[i - 1])
        if static[i - 1] != static[i]:
            d2 = (north[i] - north[i - 1]) ** 2 + (east[i] - east[i - 1]) ** 2
            e2 = d2 - 2.0 * (sigma_m[i - 1] ** 2 + sigma_m[i] ** 2)
            if math.isfinite(e2) and e2 > step * step:
                step = math.sqrt(e2)
        inc[i] = step
    return inc


def velocity_increments(
    t: FloatArray,
    north: FloatArray,
    east: FloatArray,
    sigma_m: FloatArray,
    speed_mps: FloatArray,
    static: npt.NDArray[np.bool_],
    median_s: float = 5.0,
    spike_mps: float = 9.81,
) -> FloatArray:
    """Distance (m) added at each row from the track's speed (module docstring).

    Parameters
    ----------
    t : numpy.ndarray
        Row times, s, non-decreasing.
    north, east : numpy.ndarray
        Positions in one tangent plane, m.
    sigma_m : numpy.ndarray
        Per-axis horizontal 1-sigma of each row, m.
    speed_mps : numpy.ndarray
        Horizontal speed of each row, m/s, finite.
    static : numpy.ndarray of bool
        The engine's static decision (a static row's speed counts as 0).
    median_s : float
        Width of the centred median a spike is replaced by, s (0: the rows' own speeds).
    spike_mps : float
        A speed farther than this from that median is a spike, m/s.

    Returns
    -------
    numpy.ndarray
        Per-row increment, m, ``>= 0`` (row ``i`` holds the step from row ``i - 1``).

    Raises
    ------
    ValueError
        A speed that is not finite, or arrays of different lengths.
    """
    f = np.ascontiguousarray
    sizes = {np.size(t), np.size(north), np.size(east), np.size(sigma_m), np.size(speed_mps), np.size(static)}
    if len(sizes) > 1:
        raise ValueError(f"velocity_increments: arrays of different lengths {sorted(sizes)}")
    if not np.all(np.isfinite(speed_mps)):
        raise ValueError("velocity_increments: every row needs a finite speed (else use gated_increments)")
    st = np.asarray(static, dtype=bool)
    sp = np.asarray(speed_mps, dtype=float)
    if median_s > 0 and sp.size:
        s = pd.Series(np.where(st, np.nan, sp), index=pd.to_timedelta(np.asarray(t, dtype=float), unit="s"))
        med = s.rolling(pd.Timedelta(seconds=median_s), center=True, min_periods=1).median().to_numpy(float)
        sp = np.where(np.isfinite(med) & (np.abs(sp - med) > spike_mps), med, sp)
    return _velocity(
        f(t, dtype=float),
        f(north, dtype=float),
        f(east, dtype=float),
        f(sigma_m, dtype=float),
        f(sp, dtype=float),
        f(st, dtype=np.bool_),
    )
