"""Compiled per-IMU-sample step of the quaternion EKF (:mod:`iotnav.engines.qekf`).

The model is stated in :mod:`iotnav.engines.qekf`'s docstring; :func:`iotnav.engines.qekf.propagate`
is its readable reference form (used by the Jacobian tests), and ``tests/test_qekf_kernel.py``
checks these kernels against it and against runs stored from the per-sample Python engine
they replaced. The engine's ``step()`` and its batch :meth:`~iotnav.engines.qekf.QekfEngine.imu_block`
call the same functions:

* :func:`predict`: the prediction (strapdown, Jacobian, process noise, ``P' = F P F^T + Q``
  symmetrised, the GNSS error states' exact transition, and the smoother's transition product);
* :func:`accumulate_gravity`: the compensated gravity and its Jacobian summed for the next
  TRIAD observation;
* :func:`write_row`: one output row (attitude, NED and geodetic position, velocity, sigmas);
* :func:`imu_run`: the three over a block of IMU samples (the engine initialised, no fallback,
  no smoothing: nothing per sample then needs Python).

The engine's scalar state lives in one float array ``st`` (indices ``S_*``), its vectors in
``vec`` (offsets ``V_*``), the constant tunables in ``prm`` (``K_*``); the engine's attributes
of the same names are views of them (:class:`iotnav.engines.qekf.QekfEngine`).
"""

from __future__ import annotations

import math

import numba
import numpy as np
import numpy.typing as npt

from iotnav.engines.base import (
    C_DOWN,
    C_EAST,
    C_HEIGHT,
    C_LAT,
    C_LON,
    C_NORTH,
    C_PITCH,
    C_ROLL,
    C_STD_EAST,
    C_STD_NORTH,
    C_T,
    C_VD,
    C_VE,
    C_VN,
    C_YAW,
    SRC_DR,
    SRC_FIX,
)
from iotnav.techniques.mount import accumulate_body

FloatArray = npt.NDArray[np.float64]

#: Navigation states (the paper's 22; the GNSS error states follow, 22-27).
N0 = 22
#: ``st``: time of the state (s), IMU seen (0/1), time and horizontal speed of the latest speed
#: epoch (s, m/s), along-track acceleration and its sigma (m/s^2), IMU samples since the latest
#: GNSS epoch, samples in the specific-force sum, gravity samples since the latest magnetometer
#: sample, sums of ``a_dyn``, ``|a_b|`` (m/s^2) and the compensation variance (m^2/s^4), time of
#: the latest accepted fix (s), ``dt`` of the cached GNSS error transition (s; NaN: none), a
#: smoothing record pending (0/1: an update since the last one), IMU rows since the last
#: record, time of the latest non-holonomic observation (s), the no-magnetometer fallback and
#: its heading known (0/1).
(
    S_T_X,
    S_HAVE_IMU,
    S_T_SPEED,
    S_V_SPEED,
    S_A_LONG,
    S_A_LONG_STD,
    S_N_INTERVAL,
    S_F_N,
    S_ACC_MAG_N,
    S_A_DYN_SUM,
    S_A_COMP_SUM,
    S_COMP_VAR_SUM,
    S_T_FIX,
    S_GE_DT,
    S_PRIOR,
    S_ROWS,
    S_T_NHC,
    S_FALLBACK,
    S_HEADING_OK,
) = range(19)
N_ST = 19
#: ``vec`` offsets (3 floats each unless said): latest raw specific force (m/s^2) and rate
#: (rad/s), specific-force sum and the previous interval's mean (m/s^2), compensated gravity
#: sum (m/s^2), ``var(e_gm)`` per NED axis (m^2), the cached GNSS error transition (12: per
#: horizontal and vertical axis ``b, c, a, Q_ee, Q_eg, Q_gg`` per unit variance), the fallback's
#: yaw-rate sum (rad/s) and count since the latest GNSS epoch (2) and since the latest
#: non-holonomic observation (2).
V_ACC, V_GYRO, V_F_SUM, V_F_REF, V_G_SUM, V_VAR_GM, V_GE, V_R_GNSS, V_R_NHC = 0, 3, 6, 9, 12, 15, 18, 30, 32
N_VEC = 34
#: ``prm``: gyro and accelerometer white-noise densities squared, bias random walks squared
#: (gyro, accelerometer), scale-factor random walk squared, cross-axis intensities ``k_w``,
#: ``k_a``, relative compensation error, TRIAD bias correction (0/1), GNSS error correlation
#: times (horizontal, vertical, s) and receiver filter (s), smoothing (0/1), IMU rows between
#: smoothing records, period of the non-holonomic observation (s; 0: none).
(
    K_VAR_G,
    K_VAR_A,
    K_RW_BG,
    K_RW_BA,
    K_RW_S,
    K_K_W,
    K_K_A,
    K_COMP_REL,
    K_CORRECTED,
    K_TE_H,
    K_TE_V,
    K_TF,
    K_SMOOTH,
    K_RECORD_EVERY,
    K_NHC_INTERVAL,
) = range(15)
N_PRM = 15
#: :func:`imu_run` return codes: block done; sample ``k`` not started, a smoothing record is
#: pending (Python records it, then runs ``k`` again); sample ``k`` predicted and accumulated,
#: a non-holonomic observation due (Python applies it, then the rest of the sample); the same
#: with a smoothing record due (Python records it and writes the row).
R_DONE, R_FLUSH, R_NHC, R_RECORD = 0, 1, 2, 3

#: Scratch of the kernels (:func:`scratch`), so that no kernel allocates per sample: ``wm``, up to
#: four (n, n) matrices of :func:`predict`; ``ws``, rows of ``W_MAX`` floats holding the small
#: vectors and matrices of :func:`_propagate` (rows ``W_PROP``), :func:`predict` (``W_PRED``),
#: :func:`accumulate_gravity` (``W_GRAV``), :func:`write_row` (``W_ROW``) and
#: :func:`fallback_accumulate` (``W_FB``).
W_MAX = 28
W_PROP, W_PRED, W_GRAV, W_ROW, W_FB = 0, 50, 68, 86, 96
N_WM, N_WS = 4, 102

_WGS84_A = 6378137.0
_WGS84_B = 6356752.31424518  # pymap3d's WGS-84, as iotnav.geo uses


@numba.njit(cache=True)
def scratch() -> tuple[FloatArray, FloatArray]:
    """New scratch ``(wm, ws)`` of the kernels (``N_WM`` (``W_MAX``, ``W_MAX``) matrices and
    ``N_WS`` rows of ``W_MAX``; module constants above); contents need no initialisation."""
    return np.empty((N_WM, W_MAX, W_MAX)), np.empty((N_WS, W_MAX))


@numba.njit(cache=True)
def gnss_error_step(dt: float, corr_time_s: float, filter_s: float, out: FloatArray) -> None:
    """``[b, c, a, Q_ee, Q_eg, Q_gg]`` of :func:`iotnav.engines.qekf.gnss_error_transition` into ``out``.

    The exact discretisation of one axis of the GNSS error model (that function's docstring);
    written here once and called by it.
    """
    Te = corr_time_s
    a = math.exp(-dt / Te)
    one_aa = -math.expm1(-2.0 * dt / Te)
    if filter_s <= 0.0:
        out[0], out[1], out[2] = a, 0.0, 1.0
        out[3], out[4], out[5] = one_aa, 0.0, 0.0
        return
    tf = filter_s
    b = math.exp(-dt / tf)
    # c = T_e (a - b) / (T_e - t_f) = a (1 - exp(-dt d)) / (t_f d), d = 1/t_f - 1/T_e: no
    # cancellation as t_f -> T_e (c -> (dt / t_f) a)
    d = 1.0 / tf - 1.0 / Te
    c = a * (-math.expm1(-dt * d) / (tf * d) if d != 0.0 else dt / tf)
    I_aa = 0.5 * Te * one_aa  # int_0^dt a(s)^2 ds
    if abs(Te - tf) > 1e-3 * Te:
        k = Te / (Te - tf)
        tau = Te * tf / (Te + tf)
        I_ab = -tau * math.expm1(-dt / tau)
        I_bb = -0.5 * tf * math.expm1(-2.0 * dt / tf)
        I_ca = k * (I_aa - I_ab)
        I_cc = k * k * (I_aa - 2.0 * I_ab + I_bb)
    else:  # t_f = T_e (the e-part of Q, O(dt^3), to O(|T_e - t_f| / T_e)): c(s) = (s / T_e) a(s)
        u = dt / Te
        e2 = math.exp(-2.0 * u)
        I_ca = 0.25 * Te * (1.0 - e2 * (1.0 + 2.0 * u))
        I_cc = 0.25 * Te * (1.0 - e2 * (1.0 + 2.0 * u + 2.0 * u * u))
    q = 2.0 / Te
    out[0], out[1], out[2] = b, c, a
    out[3], out[4], out[5] = q * I_cc, q * I_ca, q * I_aa


@numba.njit(cache=True)
def _quat_to_dcm(q: FloatArray, C: FloatArray) -> None:
    """``C(q)``, the quadratic form of :func:`iotnav.techniques.triad.quat_to_dcm`, into ``C``."""
    w, x, y, z = q[0], q[1], q[2], q[3]
    C[0, 0] = w * w + x * x - y * y - z * z
    C[0, 1] = 2.0 * (x * y - w * z)
    C[0, 2] = 2.0 * (x * z + w * y)
    C[1, 0] = 2.0 * (x * y + w * z)
    C[1, 1] = w * w - x * x + y * y - z * z
    C[1, 2] = 2.0 * (y * z - w * x)
    C[2, 0] = 2.0 * (x * z - w * y)
    C[2, 1] = 2.0 * (y * z + w * x)
    C[2, 2] = w * w - x * x - y * y + z * z


@numba.njit(cache=True)
def _quat_left(q: FloatArray, M: FloatArray) -> None:
    """``M_L(q)``: ``q (x) p = M_L(q) p`` (scalar first)."""
    w, x, y, z = q[0], q[1], q[2], q[3]
    M[0, 0], M[0, 1], M[0, 2], M[0, 3] = w, -x, -y, -z
    M[1, 0], M[1, 1], M[1, 2], M[1, 3] = x, w, -z, y
    M[2, 0], M[2, 1], M[2, 2], M[2, 3] = y, z, w, -x
    M[3, 0], M[3, 1], M[3, 2], M[3, 3] = z, -y, x, w


@numba.njit(cache=True)
def _quat_right(p: FloatArray, M: FloatArray) -> None:
    """``M_R(p)``: ``q (x) p = M_R(p) q`` (scalar first)."""
    w, x, y, z = p[0], p[1], p[2], p[3]
    M[0, 0], M[0, 1], M[0, 2], M[0, 3] = w, -x, -y, -z
    M[1, 0], M[1, 1], M[1, 2], M[1, 3] = x, w, z, -y
    M[2, 0], M[2, 1], M[2, 2], M[2, 3] = y, -z, w, x
    M[3, 0], M[3, 1], M[3, 2], M[3, 3] = z, y, -x, w


@numba.njit(cache=True)
def _delta_quat(th: FloatArray, dq: FloatArray, J: FloatArray) -> None:
    """``dq(theta)`` and ``d dq / d theta`` (:func:`iotnav.engines.qekf.delta_quat`)."""
    a2 = th[0] * th[0] + th[1] * th[1] + th[2] * th[2]
    if a2 < 1e-8:
        s = 0.5 - a2 / 48.0 + a2 * a2 / 3840.0
        c = 1.0 - a2 / 8.0 + a2 * a2 / 384.0
        ds = -1.0 / 24.0 + a2 / 960.0
    else:
        a = math.sqrt(a2)
        s = math.sin(0.5 * a) / a
        c = math.cos(0.5 * a)
        ds = (0.5 * c / a - s / a) / a
    dq[0] = c
    for i in range(3):
        dq[1 + i] = s * th[i]
        J[0, i] = -0.5 * s * th[i]
        for m in range(3):
            J[1 + i, m] = (s if i == m else 0.0) + ds * th[i] * th[m]


@numba.njit(cache=True)
def _rotate_jacobian(q: FloatArray, f: FloatArray, Cf: FloatArray, J: FloatArray) -> None:
    """``C(q) f`` and ``d(C(q) f)/dq`` (:func:`iotnav.engines.qekf.rotate_jacobian`)."""
    w = q[0]
    v0, v1, v2 = q[1], q[2], q[3]
    f0, f1, f2 = f[0], f[1], f[2]
    x0 = v1 * f2 - v2 * f1
    x1 = v2 * f0 - v0 * f2
    x2 = v0 * f1 - v1 * f0
    vv = v0 * v0 + v1 * v1 + v2 * v2
    vf = v0 * f0 + v1 * f1 + v2 * f2
    k = w * w - vv
    Cf[0] = k * f0 + 2.0 * v0 * vf + 2.0 * w * x0
    Cf[1] = k * f1 + 2.0 * v1 * vf + 2.0 * w * x1
    Cf[2] = k * f2 + 2.0 * v2 * vf + 2.0 * w * x2
    J[0, 0] = 2.0 * (w * f0 + x0)
    J[1, 0] = 2.0 * (w * f1 + x1)
    J[2, 0] = 2.0 * (w * f2 + x2)
    v = (v0, v1, v2)
    fv = (f0, f1, f2)
    # skew(f) = [[0, -f2, f1], [f2, 0, -f0], [-f1, f0, 0]]
    sk = ((0.0, -f2, f1), (f2, 0.0, -f0), (-f1, f0, 0.0))
    for i in range(3):
        for j in range(3):
            J[i, 1 + j] = 2.0 * ((vf if i == j else 0.0) + v[i] * fv[j] - fv[i] * v[j] - w * sk[i][j])


@numba.njit(cache=True)
def _propagate(
    x: FloatArray,
    acc: FloatArray,
    gyro: FloatArray,
    dt: float,
    g_n: FloatArray,
    x_new: FloatArray,
    F: FloatArray,
    ws: FloatArray,
) -> None:
    """:func:`propagate_into` with its intermediate vectors and matrices in rows ``W_PROP``
    of the scratch ``ws`` (no allocation); ``F`` (n, n), n >= 22: zero outside the identity
    and rows 0-9."""
    r = W_PROP
    w, f, theta, th_h = ws[r, 0:3], ws[r + 1, 0:3], ws[r + 2, 0:3], ws[r + 3, 0:3]
    dq, dqh, q_mid, Cf = ws[r + 4, 0:4], ws[r + 5, 0:4], ws[r + 6, 0:4], ws[r + 7, 0:3]
    d_bg, d_sg = ws[r + 8, 0:3], ws[r + 9, 0:3]
    Jdq, Jdqh, ML = ws[r + 10 : r + 14, 0:3], ws[r + 14 : r + 18, 0:3], ws[r + 18 : r + 22, 0:4]
    Jcf, C_mid, dq_dth = ws[r + 22 : r + 25, 0:4], ws[r + 25 : r + 28, 0:3], ws[r + 28 : r + 32, 0:3]
    MJ, MRh, da_dq = ws[r + 32 : r + 36, 0:3], ws[r + 36 : r + 40, 0:4], ws[r + 40 : r + 43, 0:4]
    da_dth, MR = ws[r + 43 : r + 46, 0:3], ws[r + 46 : r + 50, 0:4]
    for i in range(3):
        w[i] = (gyro[i] - x[10 + i]) / x[16 + i]
        f[i] = (acc[i] - x[13 + i]) / x[19 + i]
    for i in range(3):
        theta[i] = w[i] * dt
        th_h[i] = 0.5 * theta[i]
    _delta_quat(theta, dq, Jdq)
    _delta_quat(th_h, dqh, Jdqh)
    _quat_left(x[0:4], ML)
    for i in range(4):
        qn = 0.0
        qm = 0.0
        for k in range(4):
            qn += ML[i, k] * dq[k]
            qm += ML[i, k] * dqh[k]
        x_new[i] = qn
        q_mid[i] = qm
    _rotate_jacobian(q_mid, f, Cf, Jcf)
    _quat_to_dcm(q_mid, C_mid)
    h2 = 0.5 * dt * dt
    for i in range(3):
        a = Cf[i] + g_n[i]
        x_new[4 + i] = x[4 + i] + a * dt
        x_new[7 + i] = x[7 + i] + x[4 + i] * dt + h2 * a
    for i in range(10, N0):
        x_new[i] = x[i]
    for m in range(3):
        d_bg[m] = -dt * (1.0 / x[16 + m])
        d_sg[m] = -dt * (w[m] / x[16 + m])
    for i in range(4):  # M_L(q) J_dq(theta), M_L(q) J_dq(theta / 2)
        for m in range(3):
            s1 = 0.0
            s2 = 0.0
            for k in range(4):
                s1 += ML[i, k] * Jdq[k, m]
                s2 += ML[i, k] * Jdqh[k, m]
            dq_dth[i, m] = s1
            MJ[i, m] = s2
    _quat_right(dqh, MRh)
    for i in range(3):
        for j in range(4):
            s = 0.0
            for k in range(4):
                s += Jcf[i, k] * MRh[k, j]
            da_dq[i, j] = s
        for m in range(3):
            s = 0.0
            for k in range(4):
                s += Jcf[i, k] * MJ[k, m]
            da_dth[i, m] = 0.5 * s
    F[:, :] = 0.0
    for i in range(N0):
        F[i, i] = 1.0
    _quat_right(dq, MR)
    for i in range(4):
        for j in range(4):
            F[i, j] = MR[i, j]
        for m in range(3):
            F[i, 10 + m] = dq_dth[i, m] * d_bg[m]
            F[i, 16 + m] = dq_dth[i, m] * d_sg[m]
    for blk in range(2):  # VEL rows (dt d a/d .), POS rows (dt^2 / 2 d a/d .)
        r0 = 4 + 3 * blk
        ks = dt if blk == 0 else h2
        for i in range(3):
            for j in range(4):
                F[r0 + i, j] = ks * da_dq[i, j]
            for m in range(3):
                F[r0 + i, 10 + m] = ks * (da_dth[i, m] * d_bg[m])
                F[r0 + i, 16 + m] = ks * (da_dth[i, m] * d_sg[m])
                F[r0 + i, 13 + m] = ks * (-C_mid[i, m] / x[19 + m])
                F[r0 + i, 19 + m] = ks * (-C_mid[i, m] * (f[m] / x[19 + m]))
    for i in range(3):
        F[7 + i, 4 + i] = dt


@numba.njit(cache=True)
def propagate_into(
    x: FloatArray,
    acc: FloatArray,
    gyro: FloatArray,
    dt: float,
    g_n: FloatArray,
    x_new: FloatArray,
    F: FloatArray,
) -> None:
    """The 22 navigation states of :func:`iotnav.engines.qekf.propagate` into ``x_new`` (22,)
    and its Jacobian into ``F`` (22, 22, identity outside rows 0-9). ``G_g = -F[:, BG]`` and
    ``G_a = -F[:, BA]`` on rows 0-9 (zero below)."""
    _propagate(x, acc, gyro, dt, g_n, x_new, F, scratch()[1])


def _transition_pattern() -> tuple[npt.NDArray[np.int64], npt.NDArray[np.int64]]:
    """The columns of the prediction's ``F`` that can be non-zero, per row that differs from the
    identity's (ascending; read from :func:`propagate_into` and :func:`gnss_error_step`):
    attitude rows ``Q_NB, BG, SG``; velocity row ``i`` ``Q_NB, v_i, BG..SA``; position row ``i``
    the same and ``r_i``; GNSS error rows ``e_i: e_i, e_gm,i`` and ``e_gm,i: e_gm,i``. Rows
    10-21 (the biases and scale factors) are ``e_i`` and have no entry."""
    nz = np.zeros((N0 + 6, 18), dtype=np.int64)
    cnt = np.zeros(N0 + 6, dtype=np.int64)
    rows: dict[int, list[int]] = {}
    for i in range(4):
        rows[i] = [0, 1, 2, 3, 10, 11, 12, 16, 17, 18]
    for i in range(3):
        rows[4 + i] = [0, 1, 2, 3, 4 + i, *range(10, N0)]
        rows[7 + i] = [0, 1, 2, 3, 4 + i, 7 + i, *range(10, N0)]
        rows[N0 + i] = [N0 + i, N0 + 3 + i]
        rows[N0 + 3 + i] = [N0 + 3 + i]
    for i, cols in rows.items():
        nz[i, : len(cols)] = cols
        cnt[i] = len(cols)
    return nz, cnt


#: :func:`_transition_pattern`, constants of the compiled prediction.
_F_NZ, _F_CNT = _transition_pattern()


@numba.njit(cache=True)
def _row_of(r: int) -> int:
    """State index of the ``r``-th row that the transition changes (0-9, then 22-27)."""
    return r if r < 10 else r + 12


@numba.njit(cache=True)
def _rows_times(Ff: FloatArray, X: FloatArray, out: FloatArray) -> None:
    """``(Ff X)[i]`` into ``out[r]`` for the rows ``i = _row_of(r)`` that ``Ff`` changes (the
    identity rows of ``Ff X`` are those of ``X``): the prediction's ``F P`` and the smoother's
    ``F Phi``. Exactly zero entries of ``Ff`` are skipped, the others summed in ascending
    column order."""
    n = X.shape[0]
    for r in range(n - 12):
        i = _row_of(r)
        for j in range(n):
            out[r, j] = 0.0
        for c in range(_F_CNT[i]):
            k = _F_NZ[i, c]
            f = Ff[i, k]
            if f != 0.0:
                for j in range(n):
                    out[r, j] += f * X[k, j]


@numba.njit(cache=True)
def predict(
    x: FloatArray,
    P: FloatArray,
    Phi: FloatArray,
    acc: FloatArray,
    gyro: FloatArray,
    dt: float,
    g_n: FloatArray,
    prm: FloatArray,
    vec: FloatArray,
    st: FloatArray,
    Ff: FloatArray,
    Qf: FloatArray,
    wm: FloatArray,
    ws: FloatArray,
) -> None:
    """One prediction over ``dt`` (s) with the held IMU sample ``acc``, ``gyro``, in place.

    ``x`` (n,) and ``P`` (n, n), n = 22 or 28 (``gnss_error_states``); with smoothing
    (``prm[K_SMOOTH]``) ``Phi <- F Phi``. The process noise (module docstring of
    :mod:`iotnav.engines.qekf`): the gyro and accelerometer white noises through
    ``G_g = -F[:, BG]``, ``G_a = -F[:, BA]`` (per-step variances ``N^2 / dt``, the gyro's raised
    by the cross-axis term ``k_w (|w|^2 - w_i^2)``), bias random walks (the accelerometer's
    raised by ``k_a (|a|^2 - a_i^2)``, ``a = f + C^T g_n``), scale-factor random walks, and on
    the GNSS error states the exact discretisation of :func:`gnss_error_step` (cached by ``dt``
    in ``vec[V_GE:]``, scaled by ``var(e_gm)``). ``P' = sym(F P F^T + Q)``; the step's ``F`` and
    ``Q`` (n, n) are left in ``Ff`` and ``Qf``. ``wm``, ``ws``: scratch (:func:`scratch`).

    ``F`` differs from the identity only on the navigation rows 0-9 and the GNSS error rows
    (the set ``N``; the biases and scale factors ``B`` are random walks), so with ``A = F P``
    (rows ``N`` computed, rows ``B`` those of ``P``) the blocks of ``M = A F^T`` are
    ``M[N, N] = A[N] F[N]^T``, ``M[N, B] = A[N, B]``, ``M[B, N] = A[N, B]^T`` and
    ``M[B, B] = P[B, B]``: only ``A[N]`` and ``M[N, N]`` are sums, over the non-zero entries of
    ``F`` (:func:`_transition_pattern`), in the order of the dense product.
    """
    n = x.size
    nn = n - 12  # the rows F changes: 0-9 and the GNSS error states
    x_new = ws[W_PRED, 0:N0]
    _propagate(x, acc, gyro, dt, g_n, x_new, Ff, ws)
    var_g, d = ws[W_PRED + 1, 0:3], ws[W_PRED + 2, 0:N0]
    for m in range(3):
        var_g[m] = prm[K_VAR_G]
    d[:] = 0.0
    for m in range(3):
        d[10 + m] = prm[K_RW_BG] * dt
        d[13 + m] = prm[K_RW_BA] * dt
    if prm[K_K_W] > 0.0 or prm[K_K_A] > 0.0:
        w, a = ws[W_PRED + 3, 0:3], ws[W_PRED + 4, 0:3]
        C = ws[W_PRED + 5 : W_PRED + 8, 0:3]
        _quat_to_dcm(x[0:4], C)
        for i in range(3):
            w[i] = (gyro[i] - x[10 + i]) / x[16 + i]
            a[i] = (acc[i] - x[13 + i]) / x[19 + i] + (C[0, i] * g_n[0] + C[1, i] * g_n[1] + C[2, i] * g_n[2])
        ww = w[0] * w[0] + w[1] * w[1] + w[2] * w[2]
        aa = a[0] * a[0] + a[1] * a[1] + a[2] * a[2]
        for m in range(3):
            var_g[m] = var_g[m] + prm[K_K_W] * (ww - w[m] * w[m])
            d[13 + m] += prm[K_K_A] * (aa - a[m] * a[m]) * dt
    for m in range(3):
        d[16 + m] = prm[K_RW_S] * dt
        d[19 + m] = prm[K_RW_S] * dt
    # F (in Ff from _propagate): rows 0-9 over the navigation columns, the rest identity; with
    # the GNSS error states rows 22-27 hold its per-axis [[b, c], [0, a]]
    ge = vec[V_GE : V_GE + 12]
    if n > N0:
        if st[S_GE_DT] != dt:  # also for NaN (none yet)
            gnss_error_step(dt, prm[K_TE_H], prm[K_TF], ge[0:6])
            gnss_error_step(dt, prm[K_TE_V], prm[K_TF], ge[6:12])
            st[S_GE_DT] = dt
        for i in range(3):
            g = ge[0:6] if i < 2 else ge[6:12]
            Ff[N0 + i, N0 + i] = g[0]
            Ff[N0 + i, N0 + 3 + i] = g[1]
            Ff[N0 + 3 + i, N0 + 3 + i] = g[2]
    A, AT, MT = wm[0], wm[1], wm[2]
    _rows_times(Ff, P, A)  # A[r] = (F P)[i], i = _row_of(r)
    for r in range(nn):
        for k in range(n):
            AT[k, r] = A[r, k]
    # MT[c, r] = M[i, j] = sum_k A[i, k] F[j, k] (i = _row_of(r), j = _row_of(c))
    for c in range(nn):
        j = _row_of(c)
        for r in range(nn):
            MT[c, r] = 0.0
        for q in range(_F_CNT[j]):
            k = _F_NZ[j, q]
            f = Ff[j, k]
            if f != 0.0:
                for r in range(nn):
                    MT[c, r] += AT[k, r] * f
    # Q: the white noises through G_g, G_a (rows 0-9), the random walks, the GNSS error block
    Qf[:, :] = 0.0
    ka = prm[K_VAR_A] / dt
    Gq = ws[W_PRED + 8 : W_PRED + 18, 0:3]  # F[i, BG] var_g / dt
    for i in range(10):
        for m in range(3):
            Gq[i, m] = Ff[i, 10 + m] * (var_g[m] / dt)
    for i in range(10):
        for j in range(10):
            s = 0.0
            for m in range(3):
                s += Gq[i, m] * Ff[j, 10 + m]
            s2 = 0.0
            for m in range(3):
                s2 += Ff[i, 13 + m] * Ff[j, 13 + m]
            Qf[i, j] = s + ka * s2
    for i in range(N0):
        Qf[i, i] += d[i]
    if n > N0:
        for i in range(3):
            g = ge[0:6] if i < 2 else ge[6:12]
            v = vec[V_VAR_GM + i]
            ie, ig = N0 + i, N0 + 3 + i
            Qf[ie, ie] = g[3] * v
            Qf[ig, ig] = g[5] * v
            Qf[ie, ig] = g[4] * v
            Qf[ig, ie] = g[4] * v
    # P' = sym(M + Q) block by block (M[B, N] = M[N, B]^T = A[N, B], Q zero off its blocks)
    for r in range(nn):
        i = _row_of(r)
        for c in range(r, nn):
            j = _row_of(c)
            s = 0.5 * ((MT[c, r] + Qf[i, j]) + (MT[r, c] + Qf[j, i]))
            P[i, j] = s
            P[j, i] = s
        for j in range(10, N0):
            s = 0.5 * ((A[r, j] + Qf[i, j]) + A[r, j])
            P[i, j] = s
            P[j, i] = s
    for i in range(10, N0):
        P[i, i] = 0.5 * ((P[i, i] + Qf[i, i]) + (P[i, i] + Qf[i, i]))
        for j in range(i + 1, N0):
            s = 0.5 * (P[i, j] + P[j, i])
            P[i, j] = s
            P[j, i] = s
    if prm[K_SMOOTH] != 0.0:  # Phi <- F Phi
        T = wm[3]
        _rows_times(Ff, Phi, T)
        for r in range(nn):
            i = _row_of(r)
            for j in range(n):
                Phi[i, j] = T[r, j]
    if n > N0:
        for i in range(3):
            e, gm = x[N0 + i], x[N0 + 3 + i]
            x[N0 + i] = Ff[N0 + i, N0 + i] * e + Ff[N0 + i, N0 + 3 + i] * gm
            x[N0 + 3 + i] = Ff[N0 + 3 + i, N0 + 3 + i] * gm
    x[:N0] = x_new


@numba.njit(cache=True)
def accumulate_gravity(
    x: FloatArray,
    acc: FloatArray,
    gyro: FloatArray,
    g_n: FloatArray,
    prm: FloatArray,
    vec: FloatArray,
    st: FloatArray,
    D: FloatArray,
    ws: FloatArray,
) -> None:
    """Gravity in ``b`` from one sample, corrected for the estimated vehicle acceleration, summed.

    ``g_b = a_b - f`` with ``f = (f~ - b_a) / s_a`` and ``a_b = w x v_b + a_l u``,
    ``w = (w~ - b_g) / s_g``, ``v_b = C^T v_n``, ``u = v_b / |v_b|``. The along-track
    acceleration is ``a_l = a_long + u . (f - f_ref)`` (zero lag,
    :meth:`iotnav.engines.qekf.QekfEngine._speed_rate`; ``f_ref`` the mean specific force over
    the last GNSS interval), or ``a_l = a_long`` when there is no ``f_ref``. The difference
    ``f - f_ref`` is free of gravity and of the bias, so ``a_l`` hardly depends on the
    direction ``u`` (a form ``u . f - mean(u . f)`` would carry ``g`` times the wobble of
    ``u``'s elevation from the vertical-velocity noise). Its Jacobian with respect to the
    estimated states, summed into ``D`` (3, 22) like ``g_b`` (for
    :func:`iotnav.engines.qekf.triad_measurement`)::

        d g_b / d b_a = diag(1 / s_a)
        d g_b / d s_a = diag(f / s_a) + u (u * (f_ref - f))^T diag(1 / s_a)
        d g_b / d b_g = [v_b x] diag(1 / s_g),   d g_b / d s_g = [v_b x] diag(w / s_g)
        d g_b / d v_n = ([w x] + (a_l I + u (f - f_ref)^T) (I - u u^T) / |v_b|) C^T

    (the terms with ``f_ref`` only when it is used; ``f_ref``, computed with the estimates of
    the interval before, taken as computed with the present ones; the dependence through ``C``
    in ``v_b`` is left out: it rotates the small vehicle acceleration, second order). Without
    the TRIAD bias correction (``prm[K_CORRECTED] == 0``) the raw accelerometer is used and the
    bias and scale columns are zero (their error then counts only in ``acc_dir_std_rad``).
    Also counts the sample in the interval and, while moving (``|v_b| > 0.5`` m/s), sums ``f``.
    ``ws``: scratch (:func:`scratch`).
    """
    corrected = prm[K_CORRECTED] != 0.0
    r = W_GRAV
    f, w, qn, v_b = ws[r, 0:3], ws[r + 1, 0:3], ws[r + 2, 0:4], ws[r + 3, 0:3]
    a_b, u, df, gb = ws[r + 4, 0:3], ws[r + 5, 0:3], ws[r + 6, 0:3], ws[r + 7, 0:3]
    C, Sv = ws[r + 8 : r + 11, 0:3], ws[r + 11 : r + 14, 0:3]
    dv, P_u = ws[r + 14 : r + 17, 0:3], ws[r + 14 : r + 17, 3:6]
    for i in range(3):
        f[i] = (acc[i] - x[13 + i]) / x[19 + i] if corrected else acc[i]
        w[i] = (gyro[i] - x[10 + i]) / x[16 + i]
    nq = math.sqrt(x[0] * x[0] + x[1] * x[1] + x[2] * x[2] + x[3] * x[3])
    for i in range(4):
        qn[i] = x[i] / nq
    _quat_to_dcm(qn, C)
    for i in range(3):
        v_b[i] = C[0, i] * x[4] + C[1, i] * x[5] + C[2, i] * x[6]
    sp = math.sqrt(v_b[0] * v_b[0] + v_b[1] * v_b[1] + v_b[2] * v_b[2])
    a_b[0] = w[1] * v_b[2] - w[2] * v_b[1]
    a_b[1] = w[2] * v_b[0] - w[0] * v_b[2]
    a_b[2] = w[0] * v_b[1] - w[1] * v_b[0]
    Sv[0, 0], Sv[0, 1], Sv[0, 2] = 0.0, -v_b[2], v_b[1]
    Sv[1, 0], Sv[1, 1], Sv[1, 2] = v_b[2], 0.0, -v_b[0]
    Sv[2, 0], Sv[2, 1], Sv[2, 2] = -v_b[1], v_b[0], 0.0
    if corrected:
        for m in range(3):
            D[m, 13 + m] += 1.0 / x[19 + m]
            D[m, 19 + m] += f[m] / x[19 + m]
    for i in range(3):
        for m in range(3):
            D[i, 10 + m] += Sv[i, m] / x[16 + m]
            D[i, 16 + m] += Sv[i, m] * (w[m] / x[16 + m])
    dv[0, 0], dv[0, 1], dv[0, 2] = 0.0, -w[2], w[1]
    dv[1, 0], dv[1, 1], dv[1, 2] = w[2], 0.0, -w[0]
    dv[2, 0], dv[2, 1], dv[2, 2] = -w[1], w[0], 0.0
    st[S_N_INTERVAL] += 1.0
    if sp > 0.5:
        for i in range(3):
            u[i] = v_b[i] / sp
        for i in range(3):
            vec[V_F_SUM + i] += f[i]
        st[S_F_N] += 1.0
        if abs(st[S_T_X] - st[S_T_SPEED]) <= 1.5:
            for i in range(3):
                for j in range(3):
                    P_u[i, j] = (1.0 if i == j else 0.0) - u[i] * u[j]
            f_ref = vec[V_F_REF : V_F_REF + 3]
            if math.isfinite(f_ref[0]):
                for i in range(3):
                    df[i] = f[i] - f_ref[i]
                a_l = st[S_A_LONG] + (u[0] * df[0] + u[1] * df[1] + u[2] * df[2])
                for i in range(3):
                    for j in range(3):
                        s = 0.0
                        for k in range(3):
                            s += (u[i] * df[k]) * P_u[k, j]
                        dv[i, j] = dv[i, j] + (a_l * P_u[i, j] + s) / sp
                if corrected:
                    for i in range(3):
                        for m in range(3):
                            D[i, 19 + m] -= u[i] * (u[m] * df[m] / x[19 + m])
            else:
                a_l = st[S_A_LONG]
                for i in range(3):
                    for j in range(3):
                        dv[i, j] = dv[i, j] + a_l * P_u[i, j] / sp
            for i in range(3):
                a_b[i] = a_b[i] + a_l * u[i]
    for i in range(3):
        for j in range(3):
            s = 0.0
            for k in range(3):
                s += dv[i, k] * C[j, k]
            D[i, 4 + j] += s
    for i in range(3):
        gb[i] = a_b[i] - f[i]  # f = a - g  ->  g = a - f
    for i in range(3):
        vec[V_G_SUM + i] += gb[i]
    st[S_ACC_MAG_N] += 1.0
    st[S_A_DYN_SUM] += abs(math.sqrt(gb[0] * gb[0] + gb[1] * gb[1] + gb[2] * gb[2]) - g_n[2])
    ab = (a_b[0] * a_b[0] + a_b[1] * a_b[1] + a_b[2] * a_b[2]) ** 0.5
    st[S_A_COMP_SUM] += ab
    st[S_COMP_VAR_SUM] += st[S_A_LONG_STD] ** 2 + (prm[K_COMP_REL] * ab) ** 2


@numba.njit(cache=True)
def ecef_to_geodetic(x: float, y: float, z: float) -> tuple[float, float, float]:
    """WGS-84 ECEF (m) to latitude, longitude (degrees) and ellipsoidal height (m).

    Bowring's iteration (Bowring 1976, "Transformation from spatial to geographical
    coordinates", Survey Review 23(181)) on the parametric latitude ``beta``:
    ``tan(lat) = (z + e'^2 b sin^3 beta) / (p - e^2 a cos^3 beta)``,
    ``tan(beta) = (1 - f) tan(lat)``, ``p = sqrt(x^2 + y^2)``, repeated until the latitude
    changes by less than 1e-15 rad (two or three iterations near the Earth's surface);
    ``h = p cos(lat) + z sin(lat) - a^2 / N`` with ``N = a / sqrt(1 - e^2 sin^2 lat)`` (no
    division by ``cos(lat)``, valid at the poles). Inverts :func:`iotnav.geo.geodetic_to_ecef` to
    1e-12 degrees and 1e-6 m, and agrees with :func:`iotnav.geo.ecef_to_geodetic` (pymap3d, off by
    up to 1e-11 degrees at 100 km) to 1e-10 degrees (``tests/test_qekf_kernel.py``).
    """
    a, b = _WGS84_A, _WGS84_B
    e2 = 1.0 - (b / a) ** 2
    ep2 = (a / b) ** 2 - 1.0
    p = math.hypot(x, y)
    lon = math.atan2(y, x)
    beta = math.atan2(z, (1.0 - e2) ** 0.5 * p)
    lat = math.atan2(z + ep2 * b * math.sin(beta) ** 3, p - e2 * a * math.cos(beta) ** 3)
    for _ in range(6):
        beta = math.atan2((b / a) * math.sin(lat), math.cos(lat))
        new = math.atan2(z + ep2 * b * math.sin(beta) ** 3, p - e2 * a * math.cos(beta) ** 3)
        done = abs(new - lat) < 1e-15
        lat = new
        if done:
            break
    sl = math.sin(lat)
    N = a / math.sqrt(1.0 - e2 * sl * sl)
    h = p * math.cos(lat) + z * sl - a * a / N
    return math.degrees(lat), math.degrees(lon), h


@numba.njit(cache=True)
def write_row(
    k: int,
    t: float,
    x: FloatArray,
    P: FloatArray,
    st: FloatArray,
    geo: FloatArray,
    mount_yaw: float,
    use_mount: bool,
    floats: FloatArray,
    source: npt.NDArray[np.int8],
    ws: FloatArray,
) -> None:
    """Output row ``k``: the attitude of ``q / |q|`` (the vehicle's, ``C_nb R_z(mu)^T``, with
    ``use_mount``), NED position and velocity, geodetic position through ECEF (``geo``: origin
    ``r_e0`` (3) and ``C_en`` row-major (9)), the north and east sigmas, and the source (a fix
    within 1.5 s, else dead reckoning). ``ws``: scratch (:func:`scratch`)."""
    r = W_ROW
    qn, r_e = ws[r, 0:4], ws[r + 1, 0:3]
    C, Rz, Cv = ws[r + 2 : r + 5, 0:3], ws[r + 5 : r + 8, 0:3], ws[r + 2 : r + 5, 3:6]
    nq = math.sqrt(x[0] * x[0] + x[1] * x[1] + x[2] * x[2] + x[3] * x[3])
    for i in range(4):
        qn[i] = x[i] / nq
    _quat_to_dcm(qn, C)
    if use_mount:
        c, s = math.cos(mount_yaw), math.sin(mount_yaw)
        Rz[0, 0], Rz[0, 1], Rz[0, 2] = c, -s, 0.0
        Rz[1, 0], Rz[1, 1], Rz[1, 2] = s, c, 0.0
        Rz[2, 0], Rz[2, 1], Rz[2, 2] = 0.0, 0.0, 1.0
        for i in range(3):
            for j in range(3):
                Cv[i, j] = C[i, 0] * Rz[j, 0] + C[i, 1] * Rz[j, 1] + C[i, 2] * Rz[j, 2]
        C = Cv
    floats[C_T, k] = t
    floats[C_ROLL, k] = math.atan2(C[2, 1], C[2, 2])
    floats[C_PITCH, k] = math.asin(max(-1.0, min(1.0, -C[2, 0])))
    floats[C_YAW, k] = math.atan2(C[1, 0], C[0, 0])
    for i in range(3):
        r_e[i] = geo[i] + (x[7] * geo[3 + 3 * i] + x[8] * geo[4 + 3 * i] + x[9] * geo[5 + 3 * i])
    lat, lon, h = ecef_to_geodetic(r_e[0], r_e[1], r_e[2])
    floats[C_LAT, k] = lat
    floats[C_LON, k] = lon
    floats[C_HEIGHT, k] = h
    floats[C_NORTH, k] = x[7]
    floats[C_EAST, k] = x[8]
    floats[C_DOWN, k] = x[9]
    floats[C_VN, k] = x[4]
    floats[C_VE, k] = x[5]
    floats[C_VD, k] = x[6]
    floats[C_STD_NORTH, k] = math.sqrt(P[7, 7])
    floats[C_STD_EAST, k] = math.sqrt(P[8, 8])
    source[k] = SRC_FIX if t - st[S_T_FIX] <= 1.5 else SRC_DR


@numba.njit(cache=True)
def fallback_accumulate(
    x: FloatArray, acc: FloatArray, gyro: FloatArray, imu_sums: FloatArray, vec: FloatArray, ws: FloatArray
) -> None:
    """No-magnetometer fallback, step 1 (:mod:`iotnav.engines.qekf`): the mount aligner's sums of
    the sensor-frame specific force ``f_b`` and the yaw rate ``r = C[2] . w`` (estimated tilt,
    corrected gyro, rad/s; :func:`iotnav.techniques.mount.accumulate_body`), and ``r`` summed
    for the heading reset and the non-holonomic observation. ``ws``: scratch (:func:`scratch`)."""
    w, qn, C = ws[W_FB, 0:3], ws[W_FB + 1, 0:4], ws[W_FB + 2 : W_FB + 5, 0:3]
    for i in range(3):
        w[i] = (gyro[i] - x[10 + i]) / x[16 + i]
    nq = math.sqrt(x[0] * x[0] + x[1] * x[1] + x[2] * x[2] + x[3] * x[3])
    for i in range(4):
        qn[i] = x[i] / nq
    _quat_to_dcm(qn, C)
    r = C[2, 0] * w[0] + C[2, 1] * w[1] + C[2, 2] * w[2]
    accumulate_body(imu_sums, acc[0], acc[1], acc[2], r)
    vec[V_R_GNSS] += r
    vec[V_R_GNSS + 1] += 1.0
    vec[V_R_NHC] += r
    vec[V_R_NHC + 1] += 1.0


@numba.njit(cache=True)
def imu_run(
    t: FloatArray,
    ax: FloatArray,
    ay: FloatArray,
    az: FloatArray,
    wx: FloatArray,
    wy: FloatArray,
    wz: FloatArray,
    i0: int,
    i1: int,
    x: FloatArray,
    P: FloatArray,
    Phi: FloatArray,
    g_n: FloatArray,
    prm: FloatArray,
    vec: FloatArray,
    st: FloatArray,
    D: FloatArray,
    geo: FloatArray,
    imu_sums: FloatArray,
    mount_yaw: float,
    use_mount: bool,
    floats: FloatArray,
    source: npt.NDArray[np.int8],
    Ff: FloatArray,
    Qf: FloatArray,
    wm: FloatArray,
    ws: FloatArray,
) -> tuple[int, int]:
    """IMU samples ``i0 .. i1-1`` of the initialised engine, row ``k`` of ``floats`` and
    ``source`` for sample ``k``; returns ``(k, code)`` (``R_*``: done, or where Python must act).

    Per sample: the prediction to ``t[k]`` (s) with the previous sample when ``dt > 0``
    (:func:`predict`; first a pending smoothing record, ``R_FLUSH``), the sample held
    (specific force ``a*`` m/s^2, rate ``w*`` rad/s), its gravity accumulated
    (:func:`accumulate_gravity`); in the fallback the aligner's sums
    (:func:`fallback_accumulate`) and, when due, the non-holonomic observation (``R_NHC``);
    with smoothing a record every ``prm[K_RECORD_EVERY]`` rows (``R_RECORD``); the output row
    (:func:`write_row`; ``use_mount``: the vehicle's attitude with ``mount_yaw``, rad). ``Ff``,
    ``Qf``: the latest step's ``F`` and ``Q`` (:func:`predict`); ``wm``, ``ws``: scratch
    (:func:`scratch`).
    """
    smooth = prm[K_SMOOTH] != 0.0
    for k in range(i0, i1):
        tk = t[k]
        dt = tk - st[S_T_X]
        if st[S_HAVE_IMU] != 0.0 and dt > 0.0:
            if st[S_PRIOR] != 0.0:
                return k, R_FLUSH
            predict(
                x,
                P,
                Phi,
                vec[V_ACC : V_ACC + 3],
                vec[V_GYRO : V_GYRO + 3],
                dt,
                g_n,
                prm,
                vec,
                st,
                Ff,
                Qf,
                wm,
                ws,
            )
            st[S_T_X] = tk
        vec[V_ACC], vec[V_ACC + 1], vec[V_ACC + 2] = ax[k], ay[k], az[k]
        vec[V_GYRO], vec[V_GYRO + 1], vec[V_GYRO + 2] = wx[k], wy[k], wz[k]
        st[S_HAVE_IMU] = 1.0
        acc = vec[V_ACC : V_ACC + 3]
        gyro = vec[V_GYRO : V_GYRO + 3]
        accumulate_gravity(x, acc, gyro, g_n, prm, vec, st, D, ws)
        if st[S_FALLBACK] != 0.0:
            fallback_accumulate(x, acc, gyro, imu_sums, vec, ws)
            iv = prm[K_NHC_INTERVAL]
            if st[S_HEADING_OK] != 0.0 and iv > 0.0 and tk - st[S_T_NHC] >= iv:
                return k, R_NHC
        if smooth:
            st[S_ROWS] += 1.0
            if st[S_PRIOR] != 0.0 or st[S_ROWS] >= prm[K_RECORD_EVERY]:
                return k, R_RECORD
        write_row(k, tk, x, P, st, geo, mount_yaw, use_mount, floats, source, ws)
    return i1, R_DONE
