"""Strapdown step, error-state transition and covariance propagation of the ``eskf`` engine (compiled)."""

from __future__ import annotations

import numba
import numpy as np
import numpy.typing as npt

from iotnav.engines.eskf.layout import (
    ACC_C_0,
    ACC_FB_0,
    ACC_FN_0,
    ACC_T,
    ACC_WB_0,
    ATT_0,
    BA_0,
    BG_0,
    G_STD,
    GNE_0,
    GNM_0,
    MNT_0,
    N_FULL,
    NZ_ACC_BIAS,
    NZ_ACC_BIAS_DECAY,
    NZ_ACC_WHITE,
    NZ_GNSS_H,
    NZ_GNSS_V,
    NZ_GYRO_BIAS,
    NZ_GYRO_BIAS_DECAY,
    NZ_GYRO_WHITE,
    NZ_INV_TE_H,
    NZ_INV_TE_V,
    NZ_INV_TF,
    NZ_K_A,
    NZ_K_S,
    NZ_K_W,
    NZ_MOUNT_RW,
    NZ_SCALE_RW,
    POS_0,
    SA_0,
    SG_0,
    VEL_0,
    noise_record,
)
from iotnav.strapdown import rodrigues as _rodrigues

FloatArray = npt.NDArray[np.float64]


# ----------------------------------------------------------------------------- propagation


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
        acc[ACC_FN_0 + i] += fn * dt
        acc[ACC_FB_0 + i] += f_b[i] * dt
        acc[ACC_WB_0 + i] += omega_b[i] * dt
        acc[ACC_C_0 + 3 * i] += h0 * dt
        acc[ACC_C_0 + 3 * i + 1] += h1 * dt
        acc[ACC_C_0 + 3 * i + 2] += h2 * dt
    acc[ACC_T] += dt


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
        The full process-noise record (:data:`~iotnav.engines.eskf.layout.NOISE`).
    Phi : numpy.ndarray
        ``(n, n)``, receives the transition; ``n`` is :data:`N_BASE` or :data:`N_FULL`.
    q : numpy.ndarray
        ``(n,)``, receives the diagonal of ``Q_d``.
    A : numpy.ndarray
        ``(n, n)`` work array.
    """
    n = Phi.shape[0]
    A[:, :] = 0.0
    inv_tf = noise[NZ_INV_TF]
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
        A[BA_0 + i, BA_0 + i] = -noise[NZ_ACC_BIAS_DECAY] * T
        A[BG_0 + i, BG_0 + i] = -noise[NZ_GYRO_BIAS_DECAY] * T
        inv_te = noise[NZ_INV_TE_V] if i == 2 else noise[NZ_INV_TE_H]  # horizontal, vertical
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
    k_a = noise[NZ_K_A]  # accelerometer cross-axis
    k_s = noise[NZ_K_S]  # unestimated gyro scale factor
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
        q[VEL_0 + i] = noise[NZ_ACC_WHITE] * T
        # gyro cross-axis (and unestimated scale factor): rate-error variance per body axis
        # k, resolved in n (diagonal of C_nb diag(.) C_nb^T)
        d_att = 0.0
        for k in range(3):
            wk2 = omega_b[k] * omega_b[k]
            d_att += C_nb[i, k] * C_nb[i, k] * (noise[NZ_K_W] * (w2 - wk2) + k_s * wk2)
        q[ATT_0 + i] = (noise[NZ_GYRO_WHITE] + d_att) * T
        q[BA_0 + i] = (noise[NZ_ACC_BIAS] + k_a * (a2_sum - ab_i * ab_i)) * T
        q[BG_0 + i] = noise[NZ_GYRO_BIAS] * T
        q[MNT_0 + i] = noise[NZ_MOUNT_RW] * T
        q[GNM_0 + i if inv_tf > 0.0 else GNE_0 + i] = (noise[NZ_GNSS_H] if i < 2 else noise[NZ_GNSS_V]) * T
        if n >= N_FULL:
            q[SG_0 + i] = noise[NZ_SCALE_RW] * T
            q[SA_0 + i] = noise[NZ_SCALE_RW] * T


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
        The process-noise record (:data:`~iotnav.engines.eskf.layout.NOISE`, entries
        ``NZ_*``: white-noise densities squared, bias driving intensities and decay rates,
        mount and scale random walks, GNSS-error driving intensities and correlation times,
        the cross-axis intensities ``k_w``, ``k_a``, ``k_s`` and the receiver's ``1/t_f``; the
        model in :mod:`iotnav.engines.eskf.models`). A vector of only its first 12 to 15
        entries is completed by :func:`~iotnav.engines.eskf.layout.noise_record`.

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
        noise_record(noise),
        Phi,
        q,
        np.zeros((n, n)),
    )
    return Phi, np.diag(q)


def propagate_covariance(P: FloatArray, acc: FloatArray, noise: FloatArray) -> bool:
    """``P <- Phi P Phi^T + Q_d`` in place over the accumulated interval.

    :func:`propagate_covariance_nb` on the full noise record
    (:func:`~iotnav.engines.eskf.layout.noise_record`); see there.
    """
    return bool(propagate_covariance_nb(P, acc, noise_record(noise)))


@numba.njit(cache=True)
def propagate_covariance_nb(P: FloatArray, acc: FloatArray, noise: FloatArray) -> bool:
    """``P <- Phi P Phi^T + Q_d`` in place over the accumulated interval (compiled).

    :func:`propagate_covariance_phi` with a scratch ``Phi`` (the same arithmetic).

    Parameters
    ----------
    P : numpy.ndarray
        ``(n, n)`` error-state covariance, updated in place.
    acc : numpy.ndarray
        Accumulator (``ACC_*`` layout).
    noise : numpy.ndarray
        The full process-noise record (:data:`~iotnav.engines.eskf.layout.NOISE`).

    Returns
    -------
    bool
        False (nothing done) when the interval is empty.
    """
    if acc[ACC_T] <= 0.0:
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
        The full process-noise record (:data:`~iotnav.engines.eskf.layout.NOISE`).
    Phi : numpy.ndarray
        ``(n, n)``, receives the error-state transition over the interval (what the RTS
        smoother of :mod:`iotnav.engines.eskf` accumulates between its record points);
        untouched when the interval is empty.

    Returns
    -------
    bool
        False (nothing done) when the interval is empty.
    """
    T = acc[ACC_T]
    if T <= 0.0:
        return False
    n = P.shape[0]
    C = np.empty((3, 3))
    fb = np.empty(3)
    wb = np.empty(3)
    for i in range(3):
        fb[i] = acc[ACC_FB_0 + i] / T
        wb[i] = acc[ACC_WB_0 + i] / T
        for j in range(3):
            C[i, j] = acc[ACC_C_0 + 3 * i + j] / T
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
