"""Strapdown step, error-state transition and covariance propagation of the ``eskf`` engine (compiled)."""

from __future__ import annotations

import numba
import numpy as np
import numpy.typing as npt

from iotnav.engines.eskf.layout import (
    ATT_0,
    BA_0,
    BG_0,
    G_STD,
    GNE_0,
    GNM_0,
    MNT_0,
    N_FULL,
    POS_0,
    SA_0,
    SG_0,
    VEL_0,
)
from iotnav.strapdown import rodrigues as _rodrigues

FloatArray = npt.NDArray[np.float64]


# ----------------------------------------------------------------------------- propagation
#: Layout of the accumulator used between covariance propagations.
ACC_T, ACC_FN, ACC_FB, ACC_WB, ACC_C = 0, slice(1, 4), slice(4, 7), slice(7, 10), slice(10, 19)
ACC_SIZE = 19


@numba.njit(cache=True)
def propagate_nominal(
    C_nb: FloatArray,
    v_n: FloatArray,
    p_n: FloatArray,
    f_b: FloatArray,
    omega_b: FloatArray,
    dt: float,
    g_n: FloatArray,
    acc: FloatArray,
) -> None:
    """One strapdown step (as :func:`iotnav.strapdown.step`) in place, plus accumulation (compiled).

    Parameters
    ----------
    C_nb, v_n, p_n : numpy.ndarray
        Attitude, velocity (m/s) and position (m), updated in place.
    f_b, omega_b : numpy.ndarray
        Compensated specific force (m/s^2) and angular rate (rad/s) in ``b``.
    dt : float
        Step, s.
    g_n : numpy.ndarray
        Gravity in ``n`` (m/s^2).
    acc : numpy.ndarray
        Accumulator (``ACC_*`` layout): interval length and time integrals of ``f_n``,
        ``f_b``, ``omega_b`` and ``C_nb``, for :func:`error_transition`.
    """
    h = 0.5 * dt
    r = _rodrigues(h * omega_b[0], h * omega_b[1], h * omega_b[2])  # R_half
    f0, f1, f2 = f_b[0], f_b[1], f_b[2]
    for i in range(3):
        c0, c1, c2 = C_nb[i, 0], C_nb[i, 1], C_nb[i, 2]
        # row i of C_half = C_nb R_half
        h0 = c0 * r[0] + c1 * r[3] + c2 * r[6]
        h1 = c0 * r[1] + c1 * r[4] + c2 * r[7]
        h2 = c0 * r[2] + c1 * r[5] + c2 * r[8]
        fn = h0 * f0 + h1 * f1 + h2 * f2
        v_old = v_n[i]
        v_new = v_old + (fn + g_n[i]) * dt
        v_n[i] = v_new
        p_n[i] += 0.5 * (v_old + v_new) * dt
        # C_nb <- C_half R_half
        C_nb[i, 0] = h0 * r[0] + h1 * r[3] + h2 * r[6]
        C_nb[i, 1] = h0 * r[1] + h1 * r[4] + h2 * r[7]
        C_nb[i, 2] = h0 * r[2] + h1 * r[5] + h2 * r[8]
        acc[1 + i] += fn * dt
        acc[4 + i] += f_b[i] * dt
        acc[7 + i] += omega_b[i] * dt
        acc[10 + 3 * i] += h0 * dt
        acc[11 + 3 * i] += h1 * dt
        acc[12 + 3 * i] += h2 * dt
    acc[0] += dt


@numba.njit(cache=True)
def _sparse_rows_product(L: FloatArray, R: FloatArray, out: FloatArray) -> None:
    """``out = L @ R``, skipping the zero elements of ``L`` (square ``n x n``)."""
    n = L.shape[0]
    for i in range(n):
        for j in range(n):
            out[i, j] = 0.0
        for k in range(n):
            a = L[i, k]
            if a != 0.0:
                for j in range(n):
                    out[i, j] += a * R[k, j]


@numba.njit(cache=True)
def transition_into(
    C_nb: FloatArray,
    f_b: FloatArray,
    omega_b: FloatArray,
    T: float,
    noise: FloatArray,
    Phi: FloatArray,
    q: FloatArray,
    A: FloatArray,
) -> None:
    """Fill ``Phi`` and the diagonal ``q`` of ``Q_d`` of :func:`error_transition` (compiled).

    ``A T`` has its non-zeros in the POS, VEL, ATT rows and on the bias and GNSS-error
    diagonals, so ``(A T)^2`` is formed skipping zeros.

    Parameters
    ----------
    C_nb : numpy.ndarray
        Mean attitude over the interval (``b`` to ``n``).
    f_b, omega_b : numpy.ndarray
        Mean compensated specific force (m/s^2) and angular rate (rad/s) in ``b``.
    T : float
        Interval, s.
    noise : numpy.ndarray
        As in :func:`error_transition`.
    Phi : numpy.ndarray
        ``(n, n)``, receives the transition; ``n`` is :data:`N_BASE` or :data:`N_FULL`.
    q : numpy.ndarray
        ``(n,)``, receives the diagonal of ``Q_d``.
    A : numpy.ndarray
        ``(n, n)`` work array.
    """
    n = Phi.shape[0]
    A[:, :] = 0.0
    inv_tf = noise[14] if noise.shape[0] > 14 else 0.0
    fn0 = C_nb[0, 0] * f_b[0] + C_nb[0, 1] * f_b[1] + C_nb[0, 2] * f_b[2]
    fn1 = C_nb[1, 0] * f_b[0] + C_nb[1, 1] * f_b[1] + C_nb[1, 2] * f_b[2]
    fn2 = C_nb[2, 0] * f_b[0] + C_nb[2, 1] * f_b[1] + C_nb[2, 2] * f_b[2]
    # A[VEL, ATT] = -[f_n x]
    A[VEL_0, ATT_0 + 1] = fn2 * T
    A[VEL_0, ATT_0 + 2] = -fn1 * T
    A[VEL_0 + 1, ATT_0] = -fn2 * T
    A[VEL_0 + 1, ATT_0 + 2] = fn0 * T
    A[VEL_0 + 2, ATT_0] = fn1 * T
    A[VEL_0 + 2, ATT_0 + 1] = -fn0 * T
    for i in range(3):
        A[POS_0 + i, VEL_0 + i] = T
        A[BA_0 + i, BA_0 + i] = -noise[4] * T
        A[BG_0 + i, BG_0 + i] = -noise[5] * T
        # 1/T_e: horizontal, vertical (optional, else the horizontal)
        inv_te = noise[15] if (i == 2 and noise.shape[0] > 15) else noise[10]
        if inv_tf > 0.0:  # smoothed receiver: e' = (e_gm - e) / t_f, e_gm' = -e_gm / T_e + w
            A[GNM_0 + i, GNM_0 + i] = -inv_te * T
            A[GNE_0 + i, GNE_0 + i] = -inv_tf * T
            A[GNE_0 + i, GNM_0 + i] = inv_tf * T
        else:  # no smoothing: e itself is the Gauss-Markov process (GNM unused)
            A[GNE_0 + i, GNE_0 + i] = -inv_te * T
        for j in range(3):
            A[VEL_0 + i, BA_0 + j] = -C_nb[i, j] * T
            A[ATT_0 + i, BG_0 + j] = -C_nb[i, j] * T
            if n >= N_FULL:
                A[VEL_0 + i, SA_0 + j] = -C_nb[i, j] * f_b[j] * T
                A[ATT_0 + i, SG_0 + j] = -C_nb[i, j] * omega_b[j] * T
    _sparse_rows_product(A, A, Phi)
    for i in range(n):
        for j in range(n):
            Phi[i, j] = A[i, j] + 0.5 * Phi[i, j]
        Phi[i, i] += 1.0
    w2 = omega_b[0] * omega_b[0] + omega_b[1] * omega_b[1] + omega_b[2] * omega_b[2]
    # optional entries of ``noise``: accelerometer cross-axis, unestimated gyro scale factor
    k_a = noise[12] if noise.shape[0] > 12 else 0.0
    k_s = noise[13] if noise.shape[0] > 13 else 0.0
    # kinematic acceleration in b, a_b = f_b + C_nb^T g_n (g_n = (0, 0, G_STD))
    a0 = fn0
    a1 = fn1
    a2 = fn2 + G_STD
    ab0 = C_nb[0, 0] * a0 + C_nb[1, 0] * a1 + C_nb[2, 0] * a2
    ab1 = C_nb[0, 1] * a0 + C_nb[1, 1] * a1 + C_nb[2, 1] * a2
    ab2 = C_nb[0, 2] * a0 + C_nb[1, 2] * a1 + C_nb[2, 2] * a2
    a2_sum = ab0 * ab0 + ab1 * ab1 + ab2 * ab2
    q[:] = 0.0
    for i in range(3):
        ab_i = ab0 if i == 0 else (ab1 if i == 1 else ab2)
        q[VEL_0 + i] = noise[0] * T
        # gyro cross-axis (and unestimated scale factor): rate-error variance per body axis
        # k, resolved in n (diagonal of C_nb diag(.) C_nb^T)
        d_att = 0.0
        for k in range(3):
            wk2 = omega_b[k] * omega_b[k]
            d_att += C_nb[i, k] * C_nb[i, k] * (noise[11] * (w2 - wk2) + k_s * wk2)
        q[ATT_0 + i] = (noise[1] + d_att) * T
        q[BA_0 + i] = (noise[2] + k_a * (a2_sum - ab_i * ab_i)) * T
        q[BG_0 + i] = noise[3] * T
        q[MNT_0 + i] = noise[6] * T
        q[GNM_0 + i if inv_tf > 0.0 else GNE_0 + i] = (noise[8] if i < 2 else noise[9]) * T
        if n >= N_FULL:
            q[SG_0 + i] = noise[7] * T
            q[SA_0 + i] = noise[7] * T


def error_transition(
    C_nb: FloatArray,
    f_b: FloatArray,
    omega_b: FloatArray,
    T: float,
    n: int,
    noise: FloatArray,
) -> tuple[FloatArray, FloatArray]:
    """Discrete error-state transition ``Phi`` and process noise ``Q_d`` over ``T`` seconds.

    Parameters
    ----------
    C_nb : numpy.ndarray
        Mean attitude over the interval.
    f_b, omega_b : numpy.ndarray
        Mean compensated specific force (m/s^2) and angular rate (rad/s).
    T : float
        Interval, s.
    n : int
        Error-state dimension (:data:`N_BASE` or :data:`N_FULL`).
    noise : numpy.ndarray
        ``[N_a^2, N_g^2, q_ba, q_bg, 1/T_a, 1/T_g, q_mu, q_s, q_e_h, q_e_v, 1/T_e, k_w(, k_a,
        k_s, 1/t_f)]``: noise densities squared ((m/s^2)^2/Hz, (rad/s)^2/Hz), bias driving
        intensities, inverse correlation times (1/s), mount and scale random-walk intensities,
        GNSS-error driving intensities (m^2/s, horizontal and vertical; they drive ``GNM``, or
        ``GNE`` when ``1/t_f`` is 0 or absent), ``k_w`` (s) of the
        attitude noise ``k_w (|omega_b|^2 - omega_b,i^2)`` of the gyro cross-axis coupling,
        and optionally ``k_a`` (1/s) of the accelerometer-bias noise
        ``k_a (|a_b|^2 - a_b,i^2)`` of the accelerometer cross-axis coupling (``a_b`` the
        kinematic acceleration in ``b``) and ``k_s`` (s) of the attitude noise
        ``k_s omega_b,i^2`` of an unestimated gyro scale factor (see the module docstring),
        and the inverse time constant of the receiver's position smoothing ``1/t_f`` (1/s);
        absent: 0 (then ``GNE`` is a first-order Gauss-Markov process and ``GNM`` is inert);
        and ``1/T_e`` of the vertical GNSS error (absent: the horizontal ``1/T_e``).

    Returns
    -------
    Phi, Qd : numpy.ndarray
        ``(n, n)`` each (computed by :func:`transition_into`).
    """
    Phi = np.zeros((n, n))
    q = np.zeros(n)
    f64 = np.float64
    transition_into(
        np.ascontiguousarray(C_nb, dtype=f64),
        np.ascontiguousarray(f_b, dtype=f64),
        np.ascontiguousarray(omega_b, dtype=f64),
        float(T),
        np.ascontiguousarray(noise, dtype=f64),
        Phi,
        q,
        np.zeros((n, n)),
    )
    return Phi, np.diag(q)


@numba.njit(cache=True)
def propagate_covariance(P: FloatArray, acc: FloatArray, noise: FloatArray) -> bool:
    """``P <- Phi P Phi^T + Q_d`` in place over the accumulated interval (compiled).

    :func:`propagate_covariance_phi` with a scratch ``Phi`` (the same arithmetic).

    Parameters
    ----------
    P : numpy.ndarray
        ``(n, n)`` error-state covariance, updated in place.
    acc : numpy.ndarray
        Accumulator (``ACC_*`` layout).
    noise : numpy.ndarray
        As in :func:`error_transition`.

    Returns
    -------
    bool
        False (nothing done) when the interval is empty.
    """
    if acc[0] <= 0.0:
        return False
    n = P.shape[0]
    return propagate_covariance_phi(P, acc, noise, np.empty((n, n)))


@numba.njit(cache=True)
def propagate_covariance_phi(P: FloatArray, acc: FloatArray, noise: FloatArray, Phi: FloatArray) -> bool:
    """:func:`propagate_covariance`, also returning the interval's transition in ``Phi`` (compiled).

    ``Phi`` and ``Q_d`` come from :func:`transition_into` with the interval means of the
    accumulator ``acc`` (``ACC_*`` layout, from :func:`propagate_nominal`); the products skip
    the zeros of ``Phi`` (beyond the POS, VEL and ATT rows it is diagonal), and only the upper
    triangle is formed and mirrored, so ``P`` stays exactly symmetric. ``acc`` is not reset.

    Parameters
    ----------
    P : numpy.ndarray
        ``(n, n)`` error-state covariance, updated in place.
    acc : numpy.ndarray
        Accumulator (``ACC_*`` layout).
    noise : numpy.ndarray
        As in :func:`error_transition`.
    Phi : numpy.ndarray
        ``(n, n)``, receives the error-state transition over the interval (what the RTS
        smoother of :mod:`iotnav.engines.eskf` accumulates between its record points);
        untouched when the interval is empty.

    Returns
    -------
    bool
        False (nothing done) when the interval is empty.
    """
    T = acc[0]
    if T <= 0.0:
        return False
    n = P.shape[0]
    C = np.empty((3, 3))
    fb = np.empty(3)
    wb = np.empty(3)
    for i in range(3):
        fb[i] = acc[4 + i] / T
        wb[i] = acc[7 + i] / T
        for j in range(3):
            C[i, j] = acc[10 + 3 * i + j] / T
    W = np.empty((n, n))
    q = np.empty(n)
    transition_into(C, fb, wb, T, noise, Phi, q, W)
    # non-zero columns of each row of Phi
    nz = np.empty((n, n), dtype=np.int64)
    cnt = np.zeros(n, dtype=np.int64)
    for i in range(n):
        for k in range(n):
            if Phi[i, k] != 0.0:
                nz[i, cnt[i]] = k
                cnt[i] += 1
    # W = Phi P
    for i in range(n):
        for j in range(n):
            W[i, j] = 0.0
        for m in range(cnt[i]):
            k = nz[i, m]
            a = Phi[i, k]
            for j in range(n):
                W[i, j] += a * P[k, j]
    # P = W Phi^T + Q_d, upper triangle, mirrored
    for i in range(n):
        for j in range(i, n):
            s = 0.0
            for m in range(cnt[j]):
                k = nz[j, m]
                s += W[i, k] * Phi[j, k]
            P[i, j] = s
        P[i, i] += q[i]
    for i in range(n):
        for j in range(i + 1, n):
            P[j, i] = P[i, j]
    return True


@numba.njit(cache=True)
def accumulate_transition(Phi: FloatArray, Phi_acc: FloatArray, work: FloatArray) -> None:
    """``Phi_acc <- Phi @ Phi_acc`` in place, skipping the zeros of ``Phi`` (compiled).

    Parameters
    ----------
    Phi : numpy.ndarray
        ``(n, n)`` transition of the latest interval (:func:`propagate_covariance_phi`).
    Phi_acc : numpy.ndarray
        ``(n, n)`` product of the earlier transitions, updated in place.
    work : numpy.ndarray
        ``(n, n)`` scratch.
    """
    _sparse_rows_product(Phi, Phi_acc, work)
    n = Phi.shape[0]
    for i in range(n):
        for j in range(n):
            Phi_acc[i, j] = work[i, j]
