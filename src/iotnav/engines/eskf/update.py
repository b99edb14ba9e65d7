"""Error-state Kalman measurement update of the ``eskf`` engine (compiled, Joseph form, NIS gate)."""

from __future__ import annotations

import math

import numba
import numpy as np
import numpy.typing as npt

FloatArray = npt.NDArray[np.float64]


@numba.njit(cache=True)
def kalman_update(
    P: FloatArray, dx: FloatArray, y: FloatArray, H: FloatArray, R: FloatArray, m: int, gate: float
) -> tuple[float, bool, float]:
    """Error-state measurement update of ``P`` in place, Joseph form, NIS gate (compiled).

    The prior error state is zero (ESKF), so ``dx = K y``. The equations are those of
    :func:`iotnav.kalman.update` (Cholesky solve of ``S``, never an inverse), with the
    Joseph form written out, ``(I - K H) P (I - K H)^T + K R K^T = P - K A^T - A K^T + K S K^T``
    with ``A = P H^T``, ``S = H A + R`` (algebraically identical, first-order insensitive to
    errors in ``K``, ``O(n^2 m)`` instead of ``O(n^3)``); the upper triangle is formed and
    mirrored. The zeros of ``H`` are skipped.

    Parameters
    ----------
    P : numpy.ndarray
        ``(n, n)`` covariance, updated in place when accepted.
    dx : numpy.ndarray
        ``(n,)`` output: the error-state estimate (zero when rejected).
    y : numpy.ndarray
        Innovation ``z - h(x)`` in its first ``m`` elements.
    H : numpy.ndarray
        Jacobian, first ``m`` rows of an ``(>= m, n)`` array.
    R : numpy.ndarray
        Measurement noise covariance, top-left ``m x m`` block.
    m : int
        Measurement size (1 to 3).
    gate : float
        NIS threshold; ``<= 0`` or NaN: no gate.

    Returns
    -------
    nis : float
        ``y^T S^-1 y`` (inf when ``S`` is not positive definite; then rejected).
    accepted : bool
        False when gated out.
    test_ratio : float
        ``nis / gate`` (NaN without a gate).
    """
    n = P.shape[0]
    gated = gate > 0.0
    for i in range(n):
        dx[i] = 0.0
    At = np.zeros((m, n))  # A^T = H P
    for r in range(m):
        for k in range(n):
            h = H[r, k]
            if h != 0.0:
                for j in range(n):
                    At[r, j] += h * P[k, j]
    S = np.empty((m, m))
    for r in range(m):
        for c in range(m):
            s = R[r, c]
            for k in range(n):
                s += H[r, k] * At[c, k]
            S[r, c] = s
    for r in range(m):
        for c in range(r + 1, m):
            v = 0.5 * (S[r, c] + S[c, r])
            S[r, c] = v
            S[c, r] = v
    # Cholesky S = L L^T
    L = np.zeros((m, m))
    for j in range(m):
        d = S[j, j]
        for k in range(j):
            d -= L[j, k] * L[j, k]
        if not d > 0.0:
            return math.inf, False, math.inf if gated else math.nan
        L[j, j] = math.sqrt(d)
        for i in range(j + 1, m):
            v = S[i, j]
            for k in range(j):
                v -= L[i, k] * L[j, k]
            L[i, j] = v / L[j, j]
    # u = S^-1 y
    u = np.empty(m)
    for i in range(m):
        v = y[i]
        for k in range(i):
            v -= L[i, k] * u[k]
        u[i] = v / L[i, i]
    for i in range(m - 1, -1, -1):
        v = u[i]
        for k in range(i + 1, m):
            v -= L[k, i] * u[k]
        u[i] = v / L[i, i]
    nis = 0.0
    for i in range(m):
        nis += y[i] * u[i]
    ratio = nis / gate if gated else math.nan
    if gated and nis > gate:
        return nis, False, ratio
    # K^T = S^-1 A^T (column by column)
    Kt = np.empty((m, n))
    for j in range(n):
        for i in range(m):
            v = At[i, j]
            for k in range(i):
                v -= L[i, k] * Kt[k, j]
            Kt[i, j] = v / L[i, i]
        for i in range(m - 1, -1, -1):
            v = Kt[i, j]
            for k in range(i + 1, m):
                v -= L[k, i] * Kt[k, j]
            Kt[i, j] = v / L[i, i]
    for i in range(n):
        v = 0.0
        for r in range(m):
            v += Kt[r, i] * y[r]
        dx[i] = v
    KSt = np.zeros((m, n))  # (K S)^T = S K^T
    for r in range(m):
        for c in range(m):
            s = S[r, c]
            for j in range(n):
                KSt[r, j] += s * Kt[c, j]
    for i in range(n):
        for j in range(i, n):
            v = P[i, j]
            for r in range(m):
                v += KSt[r, i] * Kt[r, j] - Kt[r, i] * At[r, j] - At[r, i] * Kt[r, j]
            P[i, j] = v
    for i in range(n):
        for j in range(i + 1, n):
            P[j, i] = P[i, j]
    return nis, True, ratio
