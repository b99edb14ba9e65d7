"""Pure Kalman-filter kernels shared by every engine.

``predict`` propagates a state and covariance; ``update`` applies one measurement with a
Cholesky solve of the innovation covariance (never an explicit inverse), the Joseph-form
covariance update and explicit symmetrisation, and returns the normalised innovation squared
(NIS) so callers can gate and report; ``update_selected`` is its compiled (numba) form for a
measurement of selected state components, updating in place. ``rts_smooth`` is the Rauch-Tung-Striebel fixed-interval
smoother over stored filter results.

Equations (Bar-Shalom, Li and Kirubarajan 2001, ch. 5):

    predict:  x- = F x + B u,   P- = F P F^T + Q
    update:   y = z - H x-,   S = H P- H^T + R,   K = P- H^T S^-1
              x+ = x- + K y,   P+ = (I - K H) P- (I - K H)^T + K R K^T
              NIS = y^T S^-1 y  (chi-square with dim(z) degrees of freedom)
    RTS:      G_k = P_k F_{k+1}^T (P-_{k+1})^-1
              xs_k = x_k + G_k (xs_{k+1} - x-_{k+1}),  Ps_k = P_k + G_k (Ps_{k+1} - P-_{k+1}) G_k^T
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numba
import numpy as np
import numpy.typing as npt
from scipy.linalg import cho_factor, cho_solve
from scipy.special import gammaincinv

FloatArray = npt.NDArray[np.float64]


def symmetrize(P: FloatArray) -> FloatArray:
    """Return ``(P + P^T) / 2``."""
    return 0.5 * (P + P.T)


def predict(
    x: FloatArray,
    P: FloatArray,
    F: FloatArray,
    Q: FloatArray,
    B: FloatArray | None = None,
    u: FloatArray | None = None,
) -> tuple[FloatArray, FloatArray]:
    """Linear(ised) Kalman prediction.

    Parameters
    ----------
    x : numpy.ndarray
        State, shape ``(n,)``.
    P : numpy.ndarray
        Covariance, shape ``(n, n)``.
    F : numpy.ndarray
        Transition matrix ``(n, n)``.
    Q : numpy.ndarray
        Process noise covariance ``(n, n)`` (already discretised).
    B, u : numpy.ndarray, optional
        Control matrix ``(n, p)`` and input ``(p,)``.

    Returns
    -------
    x, P : numpy.ndarray
        Predicted state and covariance.
    """
    xp = F @ x
    if B is not None and u is not None:
        xp = xp + B @ u
    Pp = symmetrize(F @ P @ F.T + Q)
    return xp, Pp


@dataclass(frozen=True)
class UpdateResult:
    """Outcome of one measurement update.

    Attributes
    ----------
    x, P : numpy.ndarray
        Updated state and covariance (equal to the inputs when rejected).
    innovation : numpy.ndarray
        ``z - h(x)``.
    S : numpy.ndarray
        Innovation covariance.
    nis : float
        Normalised innovation squared ``y^T S^-1 y``.
    accepted : bool
        False when the gate rejected the measurement.
    test_ratio : float
        ``nis / gate`` (> 1 means rejected), NaN without a gate.
    """

    x: FloatArray
    P: FloatArray
    innovation: FloatArray
    S: FloatArray
    nis: float
    accepted: bool
    test_ratio: float


def gate_threshold(dof: int, probability: float = 0.9973) -> float:
    """Chi-square NIS gate for ``dof`` degrees of freedom at the given probability.

    The chi-square quantile ``2 * P^-1(dof / 2, probability)`` (inverse regularised lower
    incomplete gamma), which is how ``scipy.stats.chi2.ppf`` computes it, without importing
    scipy.stats (about a second of start-up).
    """
    return float(2.0 * gammaincinv(0.5 * dof, probability))


def update(
    x: FloatArray,
    P: FloatArray,
    z: FloatArray,
    H: FloatArray,
    R: FloatArray,
    h_x: FloatArray | None = None,
    gate: float | None = None,
) -> UpdateResult:
    """Kalman measurement update with Cholesky solve, Joseph form and NIS gating.

    Parameters
    ----------
    x, P : numpy.ndarray
        Prior state ``(n,)`` and covariance ``(n, n)``.
    z : numpy.ndarray
        Measurement ``(m,)``.
    H : numpy.ndarray
        Measurement matrix (or Jacobian) ``(m, n)``.
    R : numpy.ndarray
        Measurement noise covariance ``(m, m)``.
    h_x : numpy.ndarray, optional
        Predicted measurement ``h(x)`` for an EKF; ``H @ x`` when omitted.
    gate : float, optional
        NIS threshold; a measurement with larger NIS is rejected and the state left unchanged.

    Returns
    -------
    UpdateResult
        Updated state, covariance and innovation statistics.
    """
    y = z - (H @ x if h_x is None else h_x)
    PHt = P @ H.T
    S = symmetrize(H @ PHt + R)
    cf = cho_factor(S, lower=True, check_finite=False)
    nis = float(y @ cho_solve(cf, y, check_finite=False))
    ratio = nis / gate if gate is not None else float("nan")
    if gate is not None and nis > gate:
        return UpdateResult(x, P, y, S, nis, False, ratio)
    K = cho_solve(cf, PHt.T, check_finite=False).T
    xn = x + K @ y
    IKH = np.eye(P.shape[0]) - K @ H
    Pn = symmetrize(IKH @ P @ IKH.T + K @ R @ K.T)
    return UpdateResult(xn, Pn, y, S, nis, True, ratio)


def rts_smooth(
    xs: FloatArray, Ps: FloatArray, xps: FloatArray, Pps: FloatArray, Fs: FloatArray
) -> tuple[FloatArray, FloatArray]:
    """Rauch-Tung-Striebel fixed-interval smoother.

    Parameters
    ----------
    xs, Ps : numpy.ndarray
        Filtered (posterior) states ``(N, n)`` and covariances ``(N, n, n)``.
    xps, Pps : numpy.ndarray
        Predicted (prior) states and covariances at the same steps, ``xps[k]`` being the
        prediction into step ``k`` from step ``k - 1`` (``xps[0]`` is unused).
    Fs : numpy.ndarray
        Transition matrices ``(N, n, n)``, ``Fs[k]`` mapping step ``k - 1`` to ``k``.

    Returns
    -------
    x_s, P_s : numpy.ndarray
        Smoothed states and covariances.
    """
    N = xs.shape[0]
    x_s = xs.copy()
    P_s = Ps.copy()
    for k in range(N - 2, -1, -1):
        cf = cho_factor(Pps[k + 1], lower=True, check_finite=False)
        G = cho_solve(cf, (Ps[k] @ Fs[k + 1].T).T, check_finite=False).T
        x_s[k] = xs[k] + G @ (x_s[k + 1] - xps[k + 1])
        P_s[k] = symmetrize(Ps[k] + G @ (P_s[k + 1] - Pps[k + 1]) @ G.T)
    return x_s, P_s


@numba.njit(cache=True)
def update_selected(
    x: FloatArray,
    P: FloatArray,
    idx: npt.NDArray[np.int64],
    z: FloatArray,
    R: FloatArray,
    gate: float,
    y: FloatArray,
    S: FloatArray,
) -> tuple[float, bool]:
    """Compiled :func:`update` for a measurement of selected state components, in place.

    ``H`` has one unit row per measured component (``H[a, idx[a]] = 1``), so ``H x`` and
    ``P H^T`` are gathers; the rest is :func:`update`'s algebra (Cholesky of ``S``, Joseph form,
    symmetrised ``P``).

    Parameters
    ----------
    x, P : numpy.ndarray
        State ``(n,)`` and covariance ``(n, n)``, updated in place when accepted.
    idx : numpy.ndarray
        Measured state indices ``(m,)``.
    z : numpy.ndarray
        Measurement ``(m,)``, units of the selected states.
    R : numpy.ndarray
        Measurement noise covariance ``(m, m)``.
    gate : float
        NIS threshold (``inf``: no gate).
    y, S : numpy.ndarray
        Receive the innovation ``(m,)`` and its covariance ``(m, m)``.

    Returns
    -------
    nis : float
        Normalised innovation squared.
    accepted : bool
        False when ``nis > gate`` (state unchanged).
    """
    n = x.size
    m = idx.size
    for a in range(m):
        y[a] = z[a] - x[idx[a]]
    for a in range(m):
        for b in range(m):
            S[a, b] = 0.5 * ((P[idx[a], idx[b]] + R[a, b]) + (P[idx[b], idx[a]] + R[b, a]))
    L = np.zeros((m, m))
    for a in range(m):
        for b in range(a + 1):
            v = S[a, b]
            for c in range(b):
                v -= L[a, c] * L[b, c]
            L[a, b] = math.sqrt(v) if a == b else v / L[b, b]
    # K^T = S^-1 (P H^T)^T, one column of P H^T per state: solve L L^T k = row
    PHt = np.empty((n, m))
    for i in range(n):
        for a in range(m):
            PHt[i, a] = P[i, idx[a]]
    K = np.empty((n, m))
    w = np.empty(m)
    for i in range(n + 1):
        for a in range(m):  # forward substitution
            v = y[a] if i == n else PHt[i, a]
            for c in range(a):
                v -= L[a, c] * w[c]
            w[a] = v / L[a, a]
        if i == n:
            break
        for a in range(m - 1, -1, -1):  # back substitution
            v = w[a]
            for c in range(a + 1, m):
                v -= L[c, a] * K[i, c]
            K[i, a] = v / L[a, a]
    nis = 0.0
    for a in range(m):
        nis += w[a] * w[a]
    if nis > gate:
        return nis, False
    for i in range(n):
        for a in range(m):
            x[i] += K[i, a] * y[a]
    A = np.eye(n)
    for i in range(n):
        for a in range(m):
            A[i, idx[a]] -= K[i, a]
    AP = A @ P
    KR = K @ R
    Pn = AP @ A.T + KR @ K.T
    for i in range(n):
        for j in range(n):
            P[i, j] = 0.5 * (Pn[i, j] + Pn[j, i])
    return nis, True
