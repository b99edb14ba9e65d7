"""Compiled per-IMU-sample step of the pedestrian dead reckoning engine (:mod:`iotnav.engines.pdr`).

The model is stated in :mod:`iotnav.engines.pdr`'s docstring; ``tests/test_pdr_kernel.py``
checks these kernels against runs stored from the per-sample Python engine they replaced
(main at commit 3ec104d). The engine's ``step()`` and its batch
:meth:`~iotnav.engines.pdr.PdrEngine.imu_block` run the same :func:`imu_run`; the GNSS-rate
Python code of the engine calls :func:`predict_time`, :func:`advance` and :func:`extrapolation`
too, so each piece of the model is written once:

* :func:`step_update`: the step detector of :mod:`iotnav.techniques.steps`
  (:func:`iotnav.techniques.steps.step_update`, same state layout ``S_*``, same arithmetic),
  compiled, with its settings in a float array (:func:`step_params`);
* :func:`advance`: a move along the walking heading, its Jacobian and noise,
  ``P' = sym(F P F^T + Q)``;
* :func:`imu_run`: device yaw, gravity low-pass, gyro bias while static, steps and the
  output row, over a block of IMU samples.

The engine's scalar state lives in one float array ``st`` (indices ``T_*``; the engine's
attributes of the same names are views of it), the constant tunables in ``prm`` (``K_*``).
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
    SRC_NONE,
)
from iotnav.techniques.steps import (
    S_ARMED,
    S_GRAV,
    S_LAST_T,
    S_LP1,
    S_LP2,
    S_MIN,
    S_N_MERGED,
    S_N_STEPS,
    S_N_WARM,
    S_PEAK,
    S_PEAK_D,
    S_PEAK_T,
    S_T,
    StepConfig,
)

FloatArray = npt.NDArray[np.float64]

# Scalar state ``st`` (engine attributes of the same names, lower case).
T_PSI_D = 0  # device yaw, rad (arbitrary origin)
T_GYRO_VAR = 1  # smoothed |omega - b_g|^2, (rad/s)^2 (NaN before the first sample)
T_IMU = 2  # time of the previous IMU sample, s (NaN before)
T_FIX = 3  # time of the last applied fix, s
T_PRED = 4  # time of the last KF prediction, s
T_POS = 5  # time the KF position refers to, s
T_ADV = 6  # distance advanced into the current step at GNSS epochs, m
T_SPEED = 7  # walking speed from the last step, m/s
T_L_LAST = 8  # last step length, m
T_STATIC = 9  # 1.0 while static
T_HEADING_KNOWN = 10  # 1.0 once dpsi is initialised
T_DOWN = 11  # output down, m
T_N_BIAS = 12  # static samples averaged into the gyro bias
T_HAS_FRAME = 13  # 1.0 once the tangent plane exists (first fix)
T_CAL_ON = 14  # 1.0 while the step-length calibrator has an open interval
T_CAL_R = 15  # its sum of step roots in the interval
T_CAL_N = 16  # its step count in the interval
N_ST = 17

# Constant tunables ``prm`` (from :class:`iotnav.engines.pdr.PdrConfig`).
K_GRAVITY_TAU = 0
K_BIAS_TAU = 1
K_STATIC_GYRO = 2
K_STATIC_AFTER = 3
K_MAX_IMU_GAP = 4
K_GROUP_DELAY = 5
K_WEINBERG_K = 6
K_MIN_LENGTH = 7
K_MAX_LENGTH = 8
K_MIN_INTERVAL = 9
K_FIX_HOLD = 10
K_MAX_EXTRAP = 11
K_ALONG = 12
K_CROSS = 13
K_HEADING_RW = 14
K_SCALE_RW = 15
N_PRM = 16

# Step detector settings (:func:`step_params`).
D_LOWPASS_HZ = 0
D_GRAVITY_TAU = 1
D_THRESHOLD = 2
D_RELEASE = 3
D_MIN_INTERVAL = 4
D_MAX_GAP = 5
D_WARMUP = 6
N_DET_PRM = 7

#: :func:`imu_run` flag: the last sample processed followed a gap longer than ``max_imu_gap_s``.
EV_GAP = 1

# KF state layout (as :mod:`iotnav.engines.pdr`)
_DPSI = 2
_SCALE = 3


def step_params(cfg: StepConfig) -> FloatArray:
    """The step detector's settings as the float array :func:`step_update` reads."""
    p = np.empty(N_DET_PRM)
    p[D_LOWPASS_HZ] = cfg.lowpass_hz
    p[D_GRAVITY_TAU] = cfg.gravity_tau_s
    p[D_THRESHOLD] = cfg.threshold_mps2
    p[D_RELEASE] = cfg.release_mps2
    p[D_MIN_INTERVAL] = cfg.min_interval_s
    p[D_MAX_GAP] = cfg.max_gap_s
    p[D_WARMUP] = cfg.warmup_s
    return p


@numba.njit(cache=True)
def wrap(a: float) -> float:
    """Angle wrapped to ``[-pi, pi)``, rad."""
    return (a + math.pi) % (2.0 * math.pi) - math.pi


@numba.njit(cache=True)
def step_update(st: FloatArray, t: float, a_norm: float, p: FloatArray) -> tuple[bool, float, float, float]:
    """:func:`iotnav.techniques.steps.step_update` compiled: ``(found, t_peak, root, interval_s)``.

    ``st`` the detector state (updated in place), ``t`` the sample time (s), ``a_norm`` the
    specific-force norm (m/s^2), ``p`` the settings (:func:`step_params`).
    """
    t_prev = st[S_T]
    st[S_T] = t
    if not math.isfinite(t_prev) or t - t_prev > p[D_MAX_GAP]:
        st[S_LP1] = a_norm
        st[S_LP2] = a_norm
        st[S_GRAV] = a_norm
        st[S_MIN] = a_norm
        st[S_ARMED] = 0.0
        st[S_N_WARM] = 0.0
        return False, 0.0, 0.0, 0.0
    dt = t - t_prev
    alpha = 1.0 - math.exp(-dt * 2.0 * math.pi * p[D_LOWPASS_HZ])
    st[S_LP1] += alpha * (a_norm - st[S_LP1])
    st[S_LP2] += alpha * (st[S_LP1] - st[S_LP2])
    st[S_GRAV] += (1.0 - math.exp(-dt / p[D_GRAVITY_TAU])) * (a_norm - st[S_GRAV])
    st[S_N_WARM] += dt
    y = st[S_LP2]
    d = y - st[S_GRAV]
    if st[S_ARMED] == 0.0:
        st[S_MIN] = min(st[S_MIN], y)
        if d > p[D_THRESHOLD] and st[S_N_WARM] >= p[D_WARMUP]:
            st[S_ARMED] = 1.0
            st[S_PEAK] = y
            st[S_PEAK_D] = d
            st[S_PEAK_T] = t
        return False, 0.0, 0.0, 0.0
    if d > st[S_PEAK_D]:
        st[S_PEAK] = y
        st[S_PEAK_D] = d
        st[S_PEAK_T] = t
    if d >= p[D_RELEASE]:
        return False, 0.0, 0.0, 0.0
    st[S_ARMED] = 0.0
    t_peak = st[S_PEAK_T]
    interval = t_peak - st[S_LAST_T]
    if interval < p[D_MIN_INTERVAL]:
        st[S_N_MERGED] += 1.0
        st[S_MIN] = y
        return False, 0.0, 0.0, 0.0
    a_max, a_min = st[S_PEAK], st[S_MIN]
    st[S_LAST_T] = t_peak
    st[S_N_STEPS] += 1.0
    st[S_MIN] = y
    return True, t_peak, max(a_max - a_min, 0.0) ** 0.25, interval


@numba.njit(cache=True)
def predict_time(st: FloatArray, P: FloatArray, prm: FloatArray, t: float) -> None:
    """Random walks of ``dpsi`` and ``s`` from the last prediction to ``t`` (s), ``P`` in place."""
    if math.isfinite(st[T_PRED]) and t > st[T_PRED]:
        dt = t - st[T_PRED]
        P[_DPSI, _DPSI] += prm[K_HEADING_RW] ** 2 * dt
        P[_SCALE, _SCALE] += prm[K_SCALE_RW] ** 2 * dt
    if not math.isfinite(st[T_PRED]) or t > st[T_PRED]:
        st[T_PRED] = t


@numba.njit(cache=True)
def advance(st: FloatArray, x: FloatArray, P: FloatArray, prm: FloatArray, d: float, s: float) -> None:
    """Move ``d`` m along the walking heading (``d`` proportional to the scale ``s``); ``x``, ``P`` in place.

    ``F = I + d(north, east)/d(dpsi, s)``, ``Q = R(psi) diag((sa d)^2, (sc d)^2) R(psi)^T``,
    ``P' = sym(F P F^T + Q)``.
    """
    psi = st[T_PSI_D] + x[_DPSI]
    cp, sp = math.cos(psi), math.sin(psi)
    x[0] += d * cp
    x[1] += d * sp
    # F = I except F[0:2, DPSI] = j_psi and F[0:2, SCALE] = j_s
    j_psi = (-d * sp, d * cp)
    j_s = (d / s * cp, d / s * sp) if s > 0 else (0.0, 0.0)
    FP = P.copy()  # F P
    for i in range(2):
        for j in range(4):
            FP[i, j] += j_psi[i] * P[_DPSI, j] + j_s[i] * P[_SCALE, j]
    A = FP.copy()  # F P F^T
    for j in range(2):
        for i in range(4):
            A[i, j] += FP[i, _DPSI] * j_psi[j] + FP[i, _SCALE] * j_s[j]
    qa = (prm[K_ALONG] * d) ** 2
    qc = (prm[K_CROSS] * d) ** 2
    A[0, 0] += cp * qa * cp + sp * qc * sp
    A[0, 1] += cp * qa * sp - sp * qc * cp
    A[1, 0] += sp * qa * cp - cp * qc * sp
    A[1, 1] += sp * qa * sp + cp * qc * cp
    for i in range(4):
        for j in range(4):
            P[i, j] = 0.5 * (A[i, j] + A[j, i])


@numba.njit(cache=True)
def extrapolation(st: FloatArray, prm: FloatArray, t: float) -> float:
    """Distance walked since the position's time ``T_POS`` at the current pace, m (within one step)."""
    if st[T_STATIC] != 0.0 or st[T_HEADING_KNOWN] == 0.0 or t <= st[T_POS]:
        return 0.0
    cap = prm[K_MAX_EXTRAP] * st[T_L_LAST] - st[T_ADV]
    return max(0.0, min(st[T_SPEED] * (t - st[T_POS]), cap))


@numba.njit(cache=True)
def _on_step(
    st: FloatArray, x: FloatArray, P: FloatArray, prm: FloatArray, t: float, root: float, interval: float
) -> None:
    """A step whose peak was at ``t``: advance the position by what is left of its length."""
    if st[T_CAL_ON] != 0.0:  # StepLengthCalibrator.add_step
        st[T_CAL_R] += root
        st[T_CAL_N] += 1.0
    if st[T_HAS_FRAME] == 0.0:
        return
    predict_time(st, P, prm, t)
    s = x[_SCALE]
    L = min(max(s * prm[K_WEINBERG_K] * root, prm[K_MIN_LENGTH]), prm[K_MAX_LENGTH])
    period = min(max(interval, prm[K_MIN_INTERVAL]), 2.0)
    if st[T_HEADING_KNOWN] == 0.0:  # position moves, direction unknown
        P[0, 0] += L * L
        P[1, 1] += L * L
        st[T_SPEED] = 0.0
        return
    after = st[T_SPEED] * max(st[T_POS] - t, 0.0)
    d = L + after - st[T_ADV]
    if d > 0:
        advance(st, x, P, prm, d, s)
    st[T_ADV] = after if d > 0 else st[T_ADV] - L
    st[T_POS] = max(st[T_POS], t)
    st[T_SPEED] = L / period
    st[T_L_LAST] = L


@numba.njit(cache=True)
def _write_row(
    k: int,
    t: float,
    st: FloatArray,
    x: FloatArray,
    P: FloatArray,
    f: FloatArray,
    prm: FloatArray,
    geo: FloatArray,
    floats: FloatArray,
    static_out: npt.NDArray[np.bool_],
    source_out: npt.NDArray[np.int8],
) -> None:
    ff = f[0] * f[0] + f[1] * f[1] + f[2] * f[2]
    nan = math.nan
    floats[C_T, k] = t
    floats[C_ROLL, k] = math.atan2(-f[1], -f[2]) if ff > 0 else nan
    floats[C_PITCH, k] = math.atan2(f[0], math.hypot(f[1], f[2])) if ff > 0 else nan
    known = st[T_HEADING_KNOWN] != 0.0
    floats[C_YAW, k] = wrap(st[T_PSI_D] + x[_DPSI]) if known else nan
    static = st[T_STATIC] != 0.0
    static_out[k] = static
    if st[T_HAS_FRAME] == 0.0:
        for c in (C_LAT, C_LON, C_HEIGHT, C_NORTH, C_EAST, C_DOWN, C_VN, C_VE, C_VD, C_STD_NORTH, C_STD_EAST):
            floats[c, k] = nan
        source_out[k] = SRC_NONE
        return
    e = extrapolation(st, prm, t)
    psi = st[T_PSI_D] + x[_DPSI]
    cp, sp = math.cos(psi), math.sin(psi)
    n_, e_, d_ = x[0] + e * cp, x[1] + e * sp, st[T_DOWN]
    v = 0.0 if static or not known else st[T_SPEED]
    floats[C_LAT, k] = geo[0] + n_ / geo[3]
    floats[C_LON, k] = geo[1] + e_ / geo[4]
    floats[C_HEIGHT, k] = geo[2] - d_
    floats[C_NORTH, k] = n_
    floats[C_EAST, k] = e_
    floats[C_DOWN, k] = d_
    floats[C_VN, k] = v * cp
    floats[C_VE, k] = v * sp
    floats[C_VD, k] = 0.0
    floats[C_STD_NORTH, k] = math.sqrt(P[0, 0])
    floats[C_STD_EAST, k] = math.sqrt(P[1, 1])
    source_out[k] = SRC_FIX if t - st[T_FIX] <= prm[K_FIX_HOLD] else SRC_DR


@numba.njit(cache=True)
def imu_run(
    t: FloatArray,
    ax: FloatArray,
    ay: FloatArray,
    az: FloatArray,
    gx: FloatArray,
    gy: FloatArray,
    gz: FloatArray,
    floats: FloatArray,
    static_out: npt.NDArray[np.bool_],
    source_out: npt.NDArray[np.int8],
    i0: int,
    i1: int,
    st: FloatArray,
    x: FloatArray,
    P: FloatArray,
    f_lp: FloatArray,
    bias_g: FloatArray,
    det: FloatArray,
    det_prm: FloatArray,
    prm: FloatArray,
    geo: FloatArray,
) -> tuple[int, int]:
    """The pdr IMU step over samples ``i0 .. i1-1``, writing row ``k`` for sample ``k``.

    ``t`` device time (s); ``ax..az`` specific force (m/s^2) and ``gx..gz`` rate (rad/s) along
    sensor x, y, z. Returns ``(k, flags)``: it stops after a sample with an event (``EV_GAP``,
    for the engine to count) with ``k`` the next sample, else ``k = i1`` and no flags.
    """
    for k in range(i0, i1):
        tk = t[k]
        a0, a1, a2 = ax[k], ay[k], az[k]
        g0, g1, g2 = gx[k], gy[k], gz[k]
        flags = 0
        dt = tk - st[T_IMU] if math.isfinite(st[T_IMU]) else 0.0
        if dt > prm[K_MAX_IMU_GAP]:
            flags = EV_GAP
            dt = 0.0
        st[T_IMU] = tk
        if f_lp[0] * f_lp[0] + f_lp[1] * f_lp[1] + f_lp[2] * f_lp[2] == 0.0:
            f_lp[0], f_lp[1], f_lp[2] = a0, a1, a2
        else:
            a = 1.0 - math.exp(-dt / prm[K_GRAVITY_TAU])
            f_lp[0] += a * (a0 - f_lp[0])
            f_lp[1] += a * (a1 - f_lp[1])
            f_lp[2] += a * (a2 - f_lp[2])
        w0, w1, w2 = g0 - bias_g[0], g1 - bias_g[1], g2 - bias_g[2]
        ww = w0 * w0 + w1 * w1 + w2 * w2
        if math.isfinite(st[T_GYRO_VAR]):
            st[T_GYRO_VAR] += (1.0 - math.exp(-dt / 0.5)) * (ww - st[T_GYRO_VAR])
        else:
            st[T_GYRO_VAR] = ww
        found, t_peak, root, interval = step_update(det, tk, math.sqrt(a0 * a0 + a1 * a1 + a2 * a2), det_prm)
        static = tk - det[S_LAST_T] > prm[K_STATIC_AFTER] and st[T_GYRO_VAR] < prm[K_STATIC_GYRO] ** 2
        st[T_STATIC] = 1.0 if static else 0.0
        if static:  # gyro bias: plain mean first, then a slow average
            st[T_N_BIAS] += 1.0
            a = max(1.0 / st[T_N_BIAS], 1.0 - math.exp(-dt / prm[K_BIAS_TAU]))
            bias_g[0] += a * (g0 - bias_g[0])
            bias_g[1] += a * (g1 - bias_g[1])
            bias_g[2] += a * (g2 - bias_g[2])
        n = math.sqrt(f_lp[0] * f_lp[0] + f_lp[1] * f_lp[1] + f_lp[2] * f_lp[2])
        if n > 0 and dt > 0:
            rate = (g0 - bias_g[0]) * f_lp[0] + (g1 - bias_g[1]) * f_lp[1] + (g2 - bias_g[2]) * f_lp[2]
            st[T_PSI_D] = wrap(st[T_PSI_D] - rate / n * dt)
        if found:
            _on_step(st, x, P, prm, t_peak - prm[K_GROUP_DELAY], root, interval)
        _write_row(k, tk, st, x, P, f_lp, prm, geo, floats, static_out, source_out)
        if flags:
            return k + 1, flags
    return i1, 0
