"""Compiled prediction of the quaternion EKF (:mod:`iotnav.engines.qekf`), one IMU interval.

The model is stated in :mod:`iotnav.engines.qekf`'s docstring; :func:`iotnav.engines.qekf.propagate`
is its readable reference form, and ``tests/test_qekf_kernel.py`` checks these kernels against
it and against stored runs. Split from :mod:`iotnav.engines.qekf_kernel` (which calls it per
sample and re-exports its public names):

* :func:`propagate_into`: the strapdown step of the 22 navigation states and its Jacobian ``F``;
* :func:`gnss_error_step`: the exact discretisation of one axis of the GNSS error model;
* :func:`predict`: ``P' = sym(F P F^T + Q)`` over the rows ``F`` changes (its sparsity pattern,
  :func:`_transition_pattern`), the process noise ``Q``, the GNSS error states' transition and
  the smoother's transition product;
* :func:`quat_to_dcm_into`: ``C(q)`` without allocation (also used by the other kernels).

State layout and scratch: :mod:`iotnav.engines.qekf_layout`.
"""

from __future__ import annotations

import math

import numba
import numpy as np
import numpy.typing as npt

from iotnav.engines.qekf_layout import (
    K_K_A,
    K_K_W,
    K_RW_BA,
    K_RW_BG,
    K_RW_S,
    K_SMOOTH,
    K_TE_H,
    K_TE_V,
    K_TF,
    K_VAR_A,
    K_VAR_G,
    N0,
    S_GE_DT,
    V_GE,
    V_VAR_GM,
    W_PRED,
    W_PROP,
    scratch,
)

FloatArray = npt.NDArray[np.float64]


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
def quat_to_dcm_into(q: FloatArray, C: FloatArray) -> None:
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
    quat_to_dcm_into(q_mid, C_mid)
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
        quat_to_dcm_into(x[0:4], C)
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
