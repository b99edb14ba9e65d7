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
"""

from __future__ import annotations

import math

import numba
import numpy as np
import numpy.typing as npt

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
