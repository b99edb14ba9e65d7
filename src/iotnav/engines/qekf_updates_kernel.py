"""Compiled measurement updates of the quaternion EKF (:mod:`iotnav.engines.qekf`).

The prediction is compiled in :mod:`iotnav.engines.qekf_kernel`; this module compiles what
every observation of the engine ends in (GNSS position and velocity, TRIAD or magnetometer
direction, non-holonomic, quaternion norm), and the models of the norm and non-holonomic
observations that run with every update:

* :func:`update`: the Kalman update of :func:`iotnav.kalman.update` (same equations, same
  order: Cholesky factor of ``S``, NIS, gain by two triangular solves, Joseph form,
  symmetrisation), writing the innovation and ``S`` for the innovation log;
* :func:`norm_model`: the pseudo-observation ``e = 1 - |q| = 0`` (paper Eq. 9);
* :func:`nhc_model`: the lateral velocity of the no-magnetometer fallback (module docstring of
  :mod:`iotnav.engines.qekf`, fallback step 4);
* :func:`triad_model`: the improved-TRIAD attitude observation (paper Eq. 7) on the compiled
  forms of :mod:`iotnav.techniques.triad`;
* :func:`nhc_step`: the fallback's whole non-holonomic step (its gates, noise, update and the
  norm update after it) as :func:`iotnav.engines.qekf_fallback.nhc` runs it, for
  :func:`iotnav.engines.qekf_kernel.imu_run`.

The Python forms (:func:`iotnav.kalman.update`, :func:`iotnav.engines.qekf.norm_measurement`,
:func:`iotnav.engines.qekf.nhc_measurement`, :func:`iotnav.engines.qekf.triad_measurement`)
stay the references; ``tests/test_qekf_kernel.py`` checks these against them and the engine
against its stored runs.
"""

from __future__ import annotations

import math

import numba
import numpy as np
import numpy.typing as npt

from iotnav.engines.qekf_layout import (
    K_GATE_1,
    K_NHC_LEVER,
    K_NHC_MAX_YAW_RATE,
    K_NHC_MIN_SPEED,
    K_NHC_SIDESLIP,
    K_NHC_VEL_STD,
    K_NORM_STD,
    LOG_NHC,
    LOG_NORM,
    S_N_LOG,
    S_NHC_MOUNT,
    S_NHC_SIG_MU,
    S_T_NHC,
    V_R_NHC,
)
from iotnav.engines.qekf_predict_kernel import quat_to_dcm_into
from iotnav.techniques.triad import dcm_to_quat_nb, improved_triad_nb, triad_covariance_nb, triad_jacobian_nb

FloatArray = npt.NDArray[np.float64]


@numba.njit(cache=True)
def _cholesky_lower(S: FloatArray) -> FloatArray:
    """Lower Cholesky factor ``L`` of ``S`` (``S = L L^T``); NaN where ``S`` is not positive
    definite (the NIS is then NaN, as :func:`iotnav.kalman.update` reports it)."""
    m = S.shape[0]
    L = np.zeros((m, m))
    for j in range(m):
        d = S[j, j]
        for k in range(j):
            d -= L[j, k] * L[j, k]
        d = math.sqrt(d) if d > 0.0 else math.nan
        L[j, j] = d
        for i in range(j + 1, m):
            s = S[i, j]
            for k in range(j):
                s -= L[i, k] * L[j, k]
            L[i, j] = s / d
    return L


@numba.njit(cache=True)
def _cho_solve(L: FloatArray, B: FloatArray) -> FloatArray:
    """``S^-1 B`` for ``S = L L^T`` (``B`` (m, k)): forward then back substitution."""
    m, k = B.shape
    X = B.copy()
    for c in range(k):
        for i in range(m):
            s = X[i, c]
            for j in range(i):
                s -= L[i, j] * X[j, c]
            X[i, c] = s / L[i, i]
        for i in range(m - 1, -1, -1):
            s = X[i, c]
            for j in range(i + 1, m):
                s -= L[j, i] * X[j, c]
            X[i, c] = s / L[i, i]
    return X


@numba.njit(cache=True)
def update(
    x: FloatArray,
    P: FloatArray,
    z: FloatArray,
    H: FloatArray,
    R: FloatArray,
    h_x: FloatArray,
    gate: float,
    y: FloatArray,
    S: FloatArray,
) -> tuple[bool, float, FloatArray, FloatArray]:
    """Kalman update of ``x`` (n,), ``P`` (n, n) with ``z`` (m,), ``H`` (m, n), ``R`` (m, m).

    The equations of :func:`iotnav.kalman.update` (Bar-Shalom et al. 2001, ch. 5):
    ``y = z - h(x)``, ``S = sym(H P H^T + R)``, ``NIS = y^T S^-1 y`` (Cholesky), rejected when
    ``NIS > gate`` (``inf``: no gate), else ``K = P H^T S^-1``, ``x + K y`` and the Joseph form
    ``sym((I - K H) P (I - K H)^T + K R K^T)``.

    Parameters
    ----------
    x, P : numpy.ndarray
        Prior state and covariance (not modified).
    z, H, R : numpy.ndarray
        Measurement, its Jacobian and noise covariance.
    h_x : numpy.ndarray
        Predicted measurement ``h(x)`` (``H x`` for a linear model).
    gate : float
        NIS threshold (``inf``: none).
    y, S : numpy.ndarray
        Out: the innovation (m,) and its covariance (m, m).

    Returns
    -------
    accepted : bool
        False when gated (the returned ``x``, ``P`` are then the inputs).
    nis : float
        Normalised innovation squared.
    x_new, P_new : numpy.ndarray
        Posterior state and covariance (new arrays when accepted).
    """
    n = x.size
    m = z.size
    for i in range(m):
        y[i] = z[i] - h_x[i]
    PHt = np.zeros((n, m))  # P H^T
    for i in range(n):
        for r in range(m):
            s = 0.0
            for k in range(n):
                s += P[i, k] * H[r, k]
            PHt[i, r] = s
    M = R.copy()  # H P H^T + R
    for r in range(m):
        for c in range(m):
            s = 0.0
            for k in range(n):
                s += H[r, k] * PHt[k, c]
            M[r, c] += s
    for i in range(m):
        for j in range(m):
            S[i, j] = 0.5 * (M[i, j] + M[j, i])
    L = _cholesky_lower(S)
    w = _cho_solve(L, y.reshape((m, 1)))
    nis = 0.0
    for i in range(m):
        nis += y[i] * w[i, 0]
    if nis > gate:
        return False, nis, x, P
    Kt = _cho_solve(L, np.ascontiguousarray(PHt.T))  # K^T = S^-1 H P (m, n)
    xn = x.copy()
    IKH = np.zeros((n, n))  # I - K H
    KR = np.zeros((n, m))  # K R
    for i in range(n):
        for r in range(m):
            xn[i] += Kt[r, i] * y[r]
        for j in range(n):
            s = 0.0
            for r in range(m):
                s -= Kt[r, i] * H[r, j]
            IKH[i, j] = s
        IKH[i, i] += 1.0
        for c in range(m):
            s = 0.0
            for r in range(m):
                s += Kt[r, i] * R[r, c]
            KR[i, c] = s
    T = np.zeros((n, n))  # (I - K H) P
    for i in range(n):
        for k in range(n):
            f = IKH[i, k]
            if f != 0.0:
                for j in range(n):
                    T[i, j] += f * P[k, j]
    # the non-zero entries of each row of I - K H (its diagonal and the columns H observes):
    # the products with its zeros add nothing to the sums below, which run in column order
    nzc = np.empty((n, n), dtype=np.int64)
    nzn = np.zeros(n, dtype=np.int64)
    for j in range(n):
        for k in range(n):
            if IKH[j, k] != 0.0:
                nzc[j, nzn[j]] = k
                nzn[j] += 1
    A = np.empty((n, n))  # T (I - K H)^T + K R K^T
    for i in range(n):
        for j in range(n):
            s = 0.0
            for c in range(nzn[j]):
                k = nzc[j, c]
                s += T[i, k] * IKH[j, k]
            for r in range(m):
                s += KR[i, r] * Kt[r, j]
            A[i, j] = s
    Pn = np.empty((n, n))
    for i in range(n):
        for j in range(i, n):
            s = 0.5 * (A[i, j] + A[j, i])
            Pn[i, j] = s
            Pn[j, i] = s
    return True, nis, xn, Pn


@numba.njit(cache=True)
def norm_model(x: FloatArray, sigma: float, H: FloatArray, R: FloatArray, h_x: FloatArray) -> None:
    """Pseudo-observation ``e = 1 - |q| = 0`` (Eq. 9) into ``H`` (1, n), ``R`` (1, 1) and
    ``h_x`` (1,): ``H = -q^T / |q|`` on ``Q_NB``, ``R = sigma^2``, ``h_x = 1 - |q|``
    (:func:`iotnav.engines.qekf.norm_measurement`; the measurement is 0)."""
    nq = math.sqrt(x[0] * x[0] + x[1] * x[1] + x[2] * x[2] + x[3] * x[3])
    H[0, :] = 0.0
    for i in range(4):
        H[0, i] = -x[i] / nq
    R[0, 0] = sigma * sigma
    h_x[0] = 1.0 - nq


@numba.njit(cache=True)
def nhc_model(
    x: FloatArray, mount_yaw_rad: float, sigma_mps: float, H: FloatArray, R: FloatArray, h_x: FloatArray
) -> None:
    """Non-holonomic observation (lateral velocity 0, m/s) into ``H`` (1, n), ``R``, ``h_x``:
    ``h(x) = -sin(psi_v) v_N + cos(psi_v) v_E``, ``psi_v = atan2(C_10, C_00) - mount_yaw_rad``
    (:func:`iotnav.engines.qekf.nhc_measurement`, whose docstring gives ``H``)."""
    w, qx, qy, qz = x[0], x[1], x[2], x[3]
    c00 = w * w + qx * qx - qy * qy - qz * qz
    c10 = 2.0 * (qx * qy + w * qz)
    psi_v = math.atan2(c10, c00) - mount_yaw_rad
    sp, cp = math.sin(psi_v), math.cos(psi_v)
    vn, ve = x[4], x[5]
    h_x[0] = -sp * vn + cp * ve
    den = c00 * c00 + c10 * c10
    d00 = (2.0 * w, 2.0 * qx, -2.0 * qy, -2.0 * qz)
    d10 = (2.0 * qz, 2.0 * qy, 2.0 * qx, 2.0 * w)
    k = -(cp * vn + sp * ve)
    H[0, :] = 0.0
    for i in range(4):
        H[0, i] = k * ((c00 * d10[i] - c10 * d00[i]) / den)
    H[0, 4] = -sp
    H[0, 5] = cp
    H[0, 6] = 0.0
    R[0, 0] = sigma_mps * sigma_mps


#: ``triad_model`` couplings (:class:`iotnav.engines.qekf_config.QekfConfig.triad_state_coupling`).
TRIAD_JACOBIAN, TRIAD_NOISE, TRIAD_ACCELEROMETER = 0, 1, 2


@numba.njit(cache=True)
def triad_model(
    q_state: FloatArray,
    g_b: FloatArray,
    m_b: FloatArray,
    g_n: FloatArray,
    m_n: FloatArray,
    sigma_g: float,
    sigma_m: float,
    norm_std: float,
    dg_dx: FloatArray,
    P: FloatArray,
    coupling: int,
    z: FloatArray,
    H: FloatArray,
    R: FloatArray,
) -> bool:
    """The improved-TRIAD attitude observation (:func:`iotnav.engines.qekf.triad_measurement`,
    whose docstring states it) into ``z`` (4,), ``H`` (4, n >= 22; zero beyond 22) and ``R``
    (4, 4); False when gravity and field (or their references) are collinear.

    ``coupling`` (``TRIAD_*``): the state dependence ``J_x`` all in ``H`` (``jacobian``), all
    as noise ``J_x P J_x^T`` in ``R`` (``noise``; ``P`` the 22 navigation states'
    covariance), or the accelerometer's bias and scale columns in ``H`` and the rest as noise
    (``accelerometer``). Compiled with :mod:`iotnav.techniques.triad`'s compiled forms.
    """
    C, ok = improved_triad_nb(g_b, m_b, g_n, m_n, sigma_g, sigma_m)
    if not ok:
        return False
    P_th = triad_covariance_nb(g_n, m_n, sigma_g, sigma_m)
    q_obs = dcm_to_quat_nb(C)
    dot = q_obs[0] * q_state[0] + q_obs[1] * q_state[1] + q_obs[2] * q_state[2] + q_obs[3] * q_state[3]
    for i in range(4):
        z[i] = q_obs[i] if dot >= 0.0 else -q_obs[i]
    w, x, y, zz = z[0], z[1], z[2], z[3]
    Xi = np.array([[-x, -y, -zz], [w, zz, -y], [-zz, w, x], [y, -x, w]])  # M_R(z)[:, 1:]
    XiP = _small_mm(0.25 * Xi, P_th)
    for i in range(4):
        for j in range(4):
            s = 0.0
            for k in range(3):
                s += XiP[i, k] * Xi[j, k]
            R[i, j] = s + norm_std * norm_std * (z[i] * z[j])
    J_g, _J_m = triad_jacobian_nb(g_b, m_b, g_n, m_n, sigma_g, sigma_m)
    Jx = _small_mm(0.5 * _small_mm(Xi, J_g), dg_dx)  # (4, 22)
    nx = Jx.shape[1]
    H[:, :] = 0.0
    for i in range(4):
        H[i, i] = 1.0
    if coupling == TRIAD_JACOBIAN:
        for i in range(4):
            for j in range(nx):
                H[i, j] -= Jx[i, j]
        return True
    if coupling == TRIAD_ACCELEROMETER:  # b_a, s_a (13-15, 19-21) into H, the rest noise
        for i in range(4):
            for j in (13, 14, 15, 19, 20, 21):
                H[i, j] -= Jx[i, j]
                Jx[i, j] = 0.0
    JP = _small_mm(Jx, P)
    for i in range(4):
        for j in range(4):
            s = 0.0
            for k in range(nx):
                s += JP[i, k] * Jx[j, k]
            R[i, j] += s
    return True


@numba.njit(cache=True)
def _small_mm(A: FloatArray, B: FloatArray) -> FloatArray:
    """``A @ B`` (small matrices; loops rather than a BLAS call)."""
    n, k = A.shape
    m = B.shape[1]
    out = np.zeros((n, m))
    for i in range(n):
        for j in range(m):
            s = 0.0
            for q in range(k):
                s += A[i, q] * B[q, j]
            out[i, j] = s
    return out


@numba.njit(cache=True)
def _scalar_update(
    x: FloatArray, P: FloatArray, H: FloatArray, R: FloatArray, h_x: FloatArray, gate: float
) -> float:
    """:func:`update` of a scalar observation ``z = 0``, applied to ``x``, ``P`` in place when
    accepted; returns the NIS, negated when gated (``-0.0`` and ``-nan`` included: the sign bit
    carries the decision)."""
    z = np.zeros(1)
    y, S = np.empty(1), np.empty((1, 1))
    accepted, nis, xn, Pn = update(x, P, z, H, R, h_x, gate, y, S)
    if not accepted:
        return -nis
    x[:] = xn
    P[:, :] = Pn
    return nis


@numba.njit(cache=True)
def _log(nlog: FloatArray, st: FloatArray, t: float, kind: float, nis: float) -> None:
    """One NIS log row ``(t, kind, |nis|, accepted)`` (the sign of ``nis``: :func:`_scalar_update`)."""
    i = int(st[S_N_LOG])
    nlog[i, 0] = t
    nlog[i, 1] = kind
    nlog[i, 2] = abs(nis)
    nlog[i, 3] = 0.0 if math.copysign(1.0, nis) < 0.0 else 1.0
    st[S_N_LOG] = i + 1


@numba.njit(cache=True)
def nhc_step(
    t: float, x: FloatArray, P: FloatArray, prm: FloatArray, vec: FloatArray, st: FloatArray, nlog: FloatArray
) -> None:
    """The fallback's non-holonomic step at ``t`` (s), as :func:`iotnav.engines.qekf_fallback.nhc`:
    the mean yaw rate since the last one (``vec[V_R_NHC:]``, reset), ``st[S_T_NHC] = t``; when
    the horizontal speed is at least ``prm[K_NHC_MIN_SPEED]`` and ``|r_mean|`` at most
    ``prm[K_NHC_MAX_YAW_RATE]``, :func:`nhc_model` with
    ``R = sigma_0^2 + |v_h|^2 (sigma_slip^2 + sigma_mu^2) + (r_mean L)^2`` (``sigma_mu``
    ``st[S_NHC_SIG_MU]``, mount yaw ``st[S_NHC_MOUNT]``, rad), its update (gate
    ``prm[K_GATE_1]``), then the norm update (no gate). ``x``, ``P`` in place; each update's
    ``(t, kind, NIS, accepted)`` into row ``st[S_N_LOG]`` of ``nlog`` (two rows free needed)."""
    n = x.size
    r_mean = vec[V_R_NHC] / vec[V_R_NHC + 1] if vec[V_R_NHC + 1] > 0 else 0.0
    vec[V_R_NHC] = 0.0
    vec[V_R_NHC + 1] = 0.0
    st[S_T_NHC] = t
    speed = math.hypot(x[4], x[5])
    if speed < prm[K_NHC_MIN_SPEED] or abs(r_mean) > prm[K_NHC_MAX_YAW_RATE]:
        return
    sig_mu = st[S_NHC_SIG_MU]
    var = (
        prm[K_NHC_VEL_STD] ** 2
        + speed**2 * (prm[K_NHC_SIDESLIP] ** 2 + sig_mu**2)
        + (r_mean * prm[K_NHC_LEVER]) ** 2
    )
    H, R, hx = np.empty((1, n)), np.empty((1, 1)), np.empty(1)
    nhc_model(x, st[S_NHC_MOUNT], math.sqrt(var), H, R, hx)
    _log(nlog, st, t, LOG_NHC, _scalar_update(x, P, H, R, hx, prm[K_GATE_1]))
    norm_model(x, prm[K_NORM_STD], H, R, hx)
    _log(nlog, st, t, LOG_NORM, _scalar_update(x, P, H, R, hx, math.inf))


@numba.njit(cache=True)
def attitude_corrections(q_filt: FloatArray, q_smooth: FloatArray, out: FloatArray) -> None:
    """Rotation vectors (rad, body frame of the quadratic form ``C_nb``) from the filtered to
    the smoothed attitude at each record, into ``out`` (K, 3): ``rotvec(C(q_s) C(q_f)^T)`` with
    both quaternions ``[w, x, y, z]`` (K, 4) normalised (``C`` of
    :func:`iotnav.techniques.triad.quat_to_dcm`), the angle from the trace, ``v / 2`` below
    1e-6 rad; the smoother's attitude correction."""
    Cf = np.empty((3, 3))
    Cs = np.empty((3, 3))
    qf = np.empty(4)
    qs = np.empty(4)
    for k in range(q_filt.shape[0]):
        nf = math.sqrt(q_filt[k, 0] ** 2 + q_filt[k, 1] ** 2 + q_filt[k, 2] ** 2 + q_filt[k, 3] ** 2)
        ns = math.sqrt(q_smooth[k, 0] ** 2 + q_smooth[k, 1] ** 2 + q_smooth[k, 2] ** 2 + q_smooth[k, 3] ** 2)
        for i in range(4):
            qf[i] = q_filt[k, i] / nf
            qs[i] = q_smooth[k, i] / ns
        quat_to_dcm_into(qf, Cf)
        quat_to_dcm_into(qs, Cs)
        # C[i, j] = sum_m Cs[i, m] Cf[j, m]
        c01 = Cs[0, 0] * Cf[1, 0] + Cs[0, 1] * Cf[1, 1] + Cs[0, 2] * Cf[1, 2]
        c02 = Cs[0, 0] * Cf[2, 0] + Cs[0, 1] * Cf[2, 1] + Cs[0, 2] * Cf[2, 2]
        c10 = Cs[1, 0] * Cf[0, 0] + Cs[1, 1] * Cf[0, 1] + Cs[1, 2] * Cf[0, 2]
        c12 = Cs[1, 0] * Cf[2, 0] + Cs[1, 1] * Cf[2, 1] + Cs[1, 2] * Cf[2, 2]
        c20 = Cs[2, 0] * Cf[0, 0] + Cs[2, 1] * Cf[0, 1] + Cs[2, 2] * Cf[0, 2]
        c21 = Cs[2, 0] * Cf[1, 0] + Cs[2, 1] * Cf[1, 1] + Cs[2, 2] * Cf[1, 2]
        c00 = Cs[0, 0] * Cf[0, 0] + Cs[0, 1] * Cf[0, 1] + Cs[0, 2] * Cf[0, 2]
        c11 = Cs[1, 0] * Cf[1, 0] + Cs[1, 1] * Cf[1, 1] + Cs[1, 2] * Cf[1, 2]
        c22 = Cs[2, 0] * Cf[2, 0] + Cs[2, 1] * Cf[2, 1] + Cs[2, 2] * Cf[2, 2]
        c = max(-1.0, min(1.0, 0.5 * ((c00 + c11 + c22) - 1.0)))
        ang = math.acos(c)
        s = 0.5 if ang < 1e-6 else ang / (2.0 * math.sin(ang))
        out[k, 0] = (c21 - c12) * s
        out[k, 1] = (c02 - c20) * s
        out[k, 2] = (c10 - c01) * s
