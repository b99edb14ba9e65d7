"""Compiled per-IMU-sample step of the quaternion EKF (:mod:`iotnav.engines.qekf`).

The model is stated in :mod:`iotnav.engines.qekf`'s docstring; :func:`iotnav.engines.qekf.propagate`
is its readable reference form (used by the Jacobian tests), and ``tests/test_qekf_kernel.py``
checks these kernels against it and against runs stored from the per-sample Python engine
they replaced. The engine's ``step()`` and its batch :meth:`~iotnav.engines.qekf.QekfEngine.imu_block`
call the same functions:

* :func:`~iotnav.engines.qekf_predict_kernel.predict` (module
  :mod:`iotnav.engines.qekf_predict_kernel`, re-exported here): the prediction (strapdown,
  Jacobian, process noise, ``P' = F P F^T + Q`` symmetrised, the GNSS error states' exact
  transition, and the smoother's transition product);
* :func:`accumulate_gravity`: the compensated gravity and its Jacobian summed for the next
  TRIAD observation;
* :func:`write_row`: one output row (attitude, NED and geodetic position, velocity, sigmas);
* :func:`imu_run`: the three over a block of IMU samples (the engine initialised), with the
  no-magnetometer fallback's aligner sums (:func:`fallback_accumulate`) and non-holonomic step
  (:func:`iotnav.engines.qekf_updates_kernel.nhc_step`); it returns to Python for smoothing
  records and, with smoothing, for the non-holonomic observation.

The engine's scalar state lives in one float array ``st`` (indices ``S_*``), its vectors in
``vec`` (offsets ``V_*``), the constant tunables in ``prm`` (``K_*``); the engine's attributes
of the same names are views of them (:class:`iotnav.engines.qekf.QekfEngine`). That layout is
declared in :mod:`iotnav.engines.qekf_layout` and re-exported here, as are the prediction's
public names, so ``qekf_kernel.X`` reaches every compiled piece of the step.
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
from iotnav.engines.qekf_layout import (
    K_COMP_REL,
    K_CORRECTED,
    K_GATE_1,
    K_K_A,
    K_K_W,
    K_NHC_INTERVAL,
    K_NHC_LEVER,
    K_NHC_MAX_YAW_RATE,
    K_NHC_MIN_SPEED,
    K_NHC_SIDESLIP,
    K_NHC_VEL_STD,
    K_NORM_STD,
    K_RECORD_EVERY,
    K_RW_BA,
    K_RW_BG,
    K_RW_S,
    K_SMOOTH,
    K_TE_H,
    K_TE_V,
    K_TF,
    K_VAR_A,
    K_VAR_G,
    LOG_NHC,
    LOG_NORM,
    N0,
    N_LOG,
    N_PRM,
    N_ST,
    N_VEC,
    N_WM,
    N_WS,
    R_DONE,
    R_FLUSH,
    R_NHC,
    R_RECORD,
    S_A_COMP_SUM,
    S_A_DYN_SUM,
    S_A_LONG,
    S_A_LONG_STD,
    S_ACC_MAG_N,
    S_COMP_VAR_SUM,
    S_F_N,
    S_FALLBACK,
    S_GE_DT,
    S_HAVE_IMU,
    S_HEADING_OK,
    S_N_INTERVAL,
    S_N_LOG,
    S_NHC_COMPILED,
    S_NHC_MOUNT,
    S_NHC_SIG_MU,
    S_PRIOR,
    S_ROWS,
    S_T_FIX,
    S_T_NHC,
    S_T_SPEED,
    S_T_X,
    S_V_SPEED,
    V_ACC,
    V_F_REF,
    V_F_SUM,
    V_G_SUM,
    V_GE,
    V_GYRO,
    V_R_GNSS,
    V_R_NHC,
    V_VAR_GM,
    W_FB,
    W_GRAV,
    W_MAX,
    W_PRED,
    W_PROP,
    W_ROW,
    parameters,
    scratch,
)
from iotnav.engines.qekf_predict_kernel import gnss_error_step, predict, propagate_into, quat_to_dcm_into
from iotnav.engines.qekf_updates_kernel import nhc_step
from iotnav.techniques.mount import accumulate_body

FloatArray = npt.NDArray[np.float64]

#: the layout and the prediction, re-exported (module docstring)
__all__ = [
    "K_COMP_REL", "K_CORRECTED", "K_GATE_1", "K_K_A", "K_K_W", "K_NHC_INTERVAL", "K_NHC_LEVER",
    "K_NHC_MAX_YAW_RATE", "K_NHC_MIN_SPEED", "K_NHC_SIDESLIP", "K_NHC_VEL_STD", "K_NORM_STD",
    "K_RECORD_EVERY", "K_RW_BA", "K_RW_BG", "K_RW_S", "K_SMOOTH", "K_TE_H", "K_TE_V", "K_TF",
    "K_VAR_A", "K_VAR_G", "LOG_NHC", "LOG_NORM", "N0", "N_LOG", "N_PRM", "N_ST", "N_VEC", "N_WM",
    "N_WS", "R_DONE", "R_FLUSH", "R_NHC", "R_RECORD", "S_ACC_MAG_N", "S_A_COMP_SUM", "S_A_DYN_SUM",
    "S_A_LONG", "S_A_LONG_STD", "S_COMP_VAR_SUM", "S_FALLBACK", "S_F_N", "S_GE_DT", "S_HAVE_IMU",
    "S_HEADING_OK", "S_NHC_COMPILED", "S_NHC_MOUNT", "S_NHC_SIG_MU", "S_N_INTERVAL", "S_N_LOG",
    "S_PRIOR", "S_ROWS", "S_T_FIX", "S_T_NHC", "S_T_SPEED", "S_T_X", "S_V_SPEED", "V_ACC",
    "V_F_REF", "V_F_SUM", "V_GE", "V_GYRO", "V_G_SUM", "V_R_GNSS", "V_R_NHC", "V_VAR_GM", "W_FB",
    "W_GRAV", "W_MAX", "W_PRED", "W_PROP", "W_ROW", "accumulate_gravity", "ecef_to_geodetic",
    "fallback_accumulate", "gnss_error_step", "imu_run", "parameters", "predict", "propagate_into",
    "quat_to_dcm_into", "scratch", "write_row",
]  # fmt: skip

_WGS84_A = 6378137.0
_WGS84_B = 6356752.31424518  # pymap3d's WGS-84, as iotnav.geo uses


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
    quat_to_dcm_into(qn, C)
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
    quat_to_dcm_into(qn, C)
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
    quat_to_dcm_into(qn, C)
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
    nlog: FloatArray,
) -> tuple[int, int]:
    """IMU samples ``i0 .. i1-1`` of the initialised engine, row ``k`` of ``floats`` and
    ``source`` for sample ``k``; returns ``(k, code)`` (``R_*``: done, or where Python must act).

    Per sample: the prediction to ``t[k]`` (s) with the previous sample when ``dt > 0``
    (:func:`predict`; first a pending smoothing record, ``R_FLUSH``), the sample held
    (specific force ``a*`` m/s^2, rate ``w*`` rad/s), its gravity accumulated
    (:func:`accumulate_gravity`); in the fallback the aligner's sums
    (:func:`fallback_accumulate`) and, when due, the non-holonomic observation
    (:func:`iotnav.engines.qekf_updates_kernel.nhc_step` with ``st[S_NHC_COMPILED]``, its NIS
    into ``nlog`` (``N_LOG``, 4), else or with ``nlog`` full ``R_NHC``);
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
                if st[S_NHC_COMPILED] == 0.0 or st[S_N_LOG] + 2.0 > nlog.shape[0]:
                    return k, R_NHC
                nhc_step(tk, x, P, prm, vec, st, nlog)
        if smooth:
            st[S_ROWS] += 1.0
            if st[S_PRIOR] != 0.0 or st[S_ROWS] >= prm[K_RECORD_EVERY]:
                return k, R_RECORD
        write_row(k, tk, x, P, st, geo, mount_yaw, use_mount, floats, source, ws)
    return i1, R_DONE
