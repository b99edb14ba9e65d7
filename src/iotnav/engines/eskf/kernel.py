"""The compiled IMU path of the ``eskf`` engine (one numba kernel per IMU block)."""

from __future__ import annotations

import math
from typing import Any

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
    SRC_LAST_POSITION,
    SRC_NONE,
)
from iotnav.engines.eskf import models as M
from iotnav.engines.eskf.config import DEG, G0, EskfConfig
from iotnav.engines.eskf.layout import (
    E_A_GNSS,
    E_F_N_LP,
    E_F_PEND,
    E_FIX_ACC,
    E_FIX_REACH,
    E_FIX_SIG,
    E_FIX_SV,
    E_FIX_T,
    E_FIX_V,
    E_FIX_Z,
    E_GRAV_N,
    E_GRAV_REJ,
    E_GRAV_RESETS,
    E_GRAV_SUM,
    E_H0,
    E_HAS_FRAME,
    E_HAVE_IMU,
    E_HEADING_OK,
    E_KE,
    E_KN,
    E_LAST_SPEED,
    E_LAT0,
    E_LEVEL_N,
    E_LEVEL_SUM,
    E_LEVEL_T0,
    E_LEVELLED,
    E_LON0,
    E_MOUNT_OK,
    E_N_IMU,
    E_NREC,
    E_POS_OK,
    E_SA_GNSS,
    E_SM_COUNT,
    E_SM_N,
    E_SM_ON,
    E_SM_PEND,
    E_SM_T,
    E_STATIC,
    E_STATIC_SEEN,
    E_T_A_GNSS,
    E_T_FIX,
    E_T_GRAV,
    E_T_NHC,
    E_T_PREFILT,
    E_T_SPEED,
    E_T_STATE,
    E_T_ZARU,
    E_T_ZUPT,
    E_W_PEND,
    E_ZARU_N,
    E_ZARU_SUM,
    K_DONE,
    K_FLUSH,
    K_LEVEL,
    NZ_INV_TE_H,
    NZ_INV_TE_V,
    NZ_INV_TF,
    PRM_SIZE,
    Q_COV_INTERVAL,
    Q_EST_MOUNT,
    Q_FIX_HOLD,
    Q_FIX_STD,
    Q_GATE1,
    Q_GATE2,
    Q_GATE3,
    Q_GRAV,
    Q_GRAV_INTERVAL,
    Q_GRAV_MAX_ACC,
    Q_GRAV_MAX_REJ,
    Q_GRAV_REOPEN_STD,
    Q_LEVEL_TIME,
    Q_ND_A,
    Q_ND_G,
    Q_NHC,
    Q_NHC_INTERVAL,
    Q_NHC_LAT,
    Q_NHC_MIN_SPEED,
    Q_NHC_VERT,
    Q_PREFILT_TAU,
    Q_RECORD_EVERY,
    Q_ZARU_FLOOR,
    Q_ZARU_INTERVAL,
    Q_ZUPT_INTERVAL,
    Q_ZUPT_MAX_ACC,
    Q_ZUPT_MAX_GNSS_SPEED,
    Q_ZUPT_NOISE,
    R_ACC,
    R_DOF,
    R_KIND,
    R_MEAS,
    R_NIS,
    R_RATIO,
    R_T,
    REC_STATIC_END,
    REC_STATIC_START,
    REC_UPDATE,
)
from iotnav.engines.smoother import (
    write_record,
)
from iotnav.techniques.mount import accumulate_levelled
from iotnav.techniques.static import static_step

FloatArray = npt.NDArray[np.float64]


@numba.njit(cache=True)
def _freeze_yaw_nb(P: FloatArray) -> None:
    """Before the heading is known its error is left out of the filter (zero row/column).

    A 180-degree yaw sigma would be linearised through the small horizontal specific
    force and make yaw, then tilt and accelerometer bias, spuriously observable from
    zero-velocity updates at rest.
    """
    k = M.ATT_0 + 2
    P[k, :] = 0.0
    P[:, k] = 0.0


@numba.njit(cache=True)
def _sm_open(st: FloatArray, nom: Any, P: FloatArray, sm: Any) -> None:
    """Open a smoothing record at ``t_state``: save the prior ``x- = 0``, ``P-``; zero the update sum.

    Also writes the record's output-attitude map (row ``E_SM_N`` of the attitude buffer):
    ``C_nb C_vb^T`` once the mount is known (the output is then the vehicle attitude), else zero.
    """
    buf, _Phi, _work, _rec, att = sm
    C_nb, _v_n, _p_n, _b_g, _b_a, _s_g, _s_a, C_vb, _e_n, _e_gm = nom
    n = P.shape[0]
    prior = buf[0]
    post = buf[1]
    for i in range(n):
        prior[i] = 0.0
        post[i] = 0.0
        for j in range(n):
            prior[n + n * i + j] = P[i, j]
    r = int(st[E_SM_N])
    mount = st[E_MOUNT_OK] != 0.0
    for i in range(3):
        for j in range(3):
            v = 0.0
            if mount:
                for k in range(3):
                    v += C_nb[i, k] * C_vb[j, k]
            att[r, 3 * i + j] = v
    st[E_SM_PEND] = 1.0
    st[E_SM_T] = st[E_T_STATE]


@numba.njit(cache=True)
def _sm_close(st: FloatArray, P: FloatArray, sm: Any) -> None:
    """Write the open record (posterior: summed ``dx`` and ``P`` now) and restart ``Phi`` at ``I``."""
    buf, Phi, _work, rec, _att = sm
    n = P.shape[0]
    post = buf[1]
    for i in range(n):
        for j in range(n):
            post[n + n * i + j] = P[i, j]
    r = int(st[E_SM_N])
    write_record(rec, r, st[E_SM_T], buf[0], post, Phi, n)
    st[E_SM_N] = r + 1
    st[E_SM_PEND] = 0.0
    st[E_SM_COUNT] = 0.0


@numba.njit(cache=True)
def _propagate_cov_nb(
    P: FloatArray,
    acc: FloatArray,
    noise: FloatArray,
    nom: Any,
    st: FloatArray,
    prm: FloatArray,
    sm: Any,
) -> None:
    """Covariance over the accumulated interval; GNSS-error decay; yaw freeze; fixed mount.

    When recording for the smoother: the open record is written first (its posterior is ``P``
    before this interval), the interval's transition is multiplied into ``Phi``, and a record
    is opened after ``record_every`` propagations.
    """
    T = acc[M.ACC_T]
    _C_nb, _v_n, _p_n, _b_g, _b_a, _s_g, _s_a, _C_vb, e_n, e_gm = nom
    smoothing = st[E_SM_ON] != 0.0
    if smoothing:
        if T <= 0.0:
            return
        if st[E_SM_PEND] != 0.0:
            _sm_close(st, P, sm)
        n = P.shape[0]
        work = sm[2]
        M.propagate_covariance_phi(P, acc, noise, work[0])
        M.accumulate_transition(work[0], sm[1].reshape((n, n)), work[1])
    elif not M.propagate_covariance_nb(P, acc, noise):
        return
    # the GNSS error is zero-mean: its estimate follows the error model without noise, exactly
    # (e_gm decays with T_e; the smoothed e follows it through the receiver's low-pass t_f)
    inv_tf = noise[NZ_INV_TF]
    for i in range(3):
        inv_te = noise[NZ_INV_TE_H] if i < 2 else noise[NZ_INV_TE_V]  # horizontal, vertical
        d = math.exp(-T * inv_te)
        if inv_tf > 0.0:
            a = math.exp(-T * inv_tf)
            den = inv_tf - inv_te
            c = inv_tf * (d - a) / den if abs(den) > 1e-12 else T * inv_tf * d
            e_n[i] = a * e_n[i] + c * e_gm[i]
            e_gm[i] *= d
        else:
            e_n[i] *= d
    acc[:] = 0.0
    if st[E_HEADING_OK] == 0.0:
        _freeze_yaw_nb(P)
    if prm[Q_EST_MOUNT] == 0.0:
        P[M.MNT_0 : M.MNT_0 + 3, :] = 0.0
        P[:, M.MNT_0 : M.MNT_0 + 3] = 0.0
        if smoothing:  # the zeroed mount is part of the transition
            n = P.shape[0]
            sm[1][M.MNT_0 * n : (M.MNT_0 + 3) * n] = 0.0
    if smoothing:
        st[E_SM_COUNT] += 1.0
        if st[E_SM_COUNT] >= prm[Q_RECORD_EVERY]:
            _sm_open(st, nom, P, sm)


@numba.njit(cache=True)
def _apply_nb(
    t: float,
    code: int,
    y: FloatArray,
    H: FloatArray,
    R: FloatArray,
    m: int,
    gate: float,
    P: FloatArray,
    nom: Any,
    acc: FloatArray,
    noise: FloatArray,
    st: FloatArray,
    prm: FloatArray,
    rec: FloatArray,
    sm: Any,
) -> bool:
    """Propagate the covariance to now, gate and apply one measurement, record it; True if accepted.

    When recording for the smoother the update belongs to the record open at ``t_state`` (opened
    here if none is), and its ``dx`` is added to that record's posterior.
    """
    C_nb, v_n, p_n, b_g, b_a, s_g, s_a, C_vb, e_n, e_gm = nom
    _propagate_cov_nb(P, acc, noise, nom, st, prm, sm)
    smoothing = st[E_SM_ON] != 0.0
    if smoothing:
        if st[E_SM_PEND] != 0.0 and st[E_SM_T] != st[E_T_STATE]:
            _sm_close(st, P, sm)  # time moved on without a propagation (data gap): identity transition
        if st[E_SM_PEND] == 0.0:
            _sm_open(st, nom, P, sm)
    dx = np.empty(P.shape[0])
    nis, ok, ratio = M.kalman_update(P, dx, y, H, R, m, gate)
    j = int(st[E_NREC])
    rec[j, R_KIND] = REC_UPDATE
    rec[j, R_T] = t
    rec[j, R_MEAS] = code
    rec[j, R_NIS] = nis
    rec[j, R_DOF] = m
    rec[j, R_ACC] = 1.0 if ok else 0.0
    rec[j, R_RATIO] = ratio
    st[E_NREC] = j + 1
    if not ok:
        return False
    M.inject_arrays(dx, C_nb, v_n, p_n, b_g, b_a, s_g, s_a, C_vb, e_n, e_gm)
    if smoothing:
        # several updates at one time: their corrections, each about the nominal the previous
        # one left, summed (to first order the correction about the record's prior nominal)
        post = sm[0][1]
        for i in range(P.shape[0]):
            post[i] += dx[i]
    if st[E_HEADING_OK] == 0.0:
        _freeze_yaw_nb(P)
    return True


@numba.njit(cache=True)
def _integrate_to_nb(
    t: float,
    st: FloatArray,
    prm: FloatArray,
    nom: Any,
    g_n: FloatArray,
    acc: FloatArray,
    P: FloatArray,
    noise: FloatArray,
    fw: FloatArray,
    sm: Any,
) -> None:
    """Integrate the pending IMU sample from ``t_state`` to ``t`` (``fw``: 6-element work array)."""
    if st[E_HAVE_IMU] == 0.0 or not math.isfinite(st[E_T_STATE]):
        return
    dt = t - st[E_T_STATE]
    if dt <= 0.0 or dt > 1.0:
        st[E_T_STATE] = max(st[E_T_STATE], t)
        return
    C_nb, v_n, p_n, b_g, b_a, s_g, s_a, _C_vb, _e_n, _e_gm = nom
    f = fw[0:3]
    w = fw[3:6]
    M.compensate_into(st[E_F_PEND : E_F_PEND + 3], b_a, s_a, f)
    M.compensate_into(st[E_W_PEND : E_W_PEND + 3], b_g, s_g, w)
    M.propagate_nominal(C_nb, v_n, p_n, f, w, dt, g_n, acc)
    st[E_T_STATE] = t
    if acc[M.ACC_T] >= prm[Q_COV_INTERVAL]:
        _propagate_cov_nb(P, acc, noise, nom, st, prm, sm)


@numba.njit(cache=True)
def _static_updates_nb(
    t: float,
    st: FloatArray,
    prm: FloatArray,
    nom: Any,
    P: FloatArray,
    acc: FloatArray,
    noise: FloatArray,
    rec: FloatArray,
    y: FloatArray,
    H: FloatArray,
    R: FloatArray,
    sm: Any,
) -> None:
    """ZUPT, and ZARU with the mean gyro output once ``zaru_interval_s`` of static data is summed."""
    _C_nb, v_n, _p_n, b_g, _b_a, s_g, _s_a, _C_vb, _e_n, _e_gm = nom
    st[E_T_ZUPT] = t
    M.zupt_rows(v_n, y, H)
    R[:, :] = 0.0
    for i in range(3):
        R[i, i] = prm[Q_ZUPT_NOISE] ** 2
    _apply_nb(t, 0, y, H, R, 3, prm[Q_GATE3], P, nom, acc, noise, st, prm, rec, sm)
    T = t - st[E_T_ZARU]
    n = st[E_ZARU_N]
    if n >= 5 and T >= prm[Q_ZARU_INTERVAL]:
        st[E_T_ZARU] = t
        sigma = math.hypot(prm[Q_ND_G] / math.sqrt(T), prm[Q_ZARU_FLOOR])
        w_mean = np.empty(3)
        for i in range(3):
            w_mean[i] = st[E_ZARU_SUM + i] / n
        M.zaru_rows(w_mean, b_g, s_g, y, H)
        R[:, :] = 0.0
        for i in range(3):
            y[i] = -y[i]
            R[i, i] = sigma * sigma
        _apply_nb(t, 1, y, H, R, 3, prm[Q_GATE3], P, nom, acc, noise, st, prm, rec, sm)
        st[E_ZARU_SUM : E_ZARU_SUM + 3] = 0.0
        st[E_ZARU_N] = 0.0


@numba.njit(cache=True)
def _gravity_nb(
    t: float,
    fx: float,
    fy: float,
    fz: float,
    st: FloatArray,
    prm: FloatArray,
    nom: Any,
    P: FloatArray,
    acc: FloatArray,
    noise: FloatArray,
    rec: FloatArray,
    y: FloatArray,
    H: FloatArray,
    R: FloatArray,
    sm: Any,
) -> None:
    """Gravity aiding of the tilt before the heading (package docstring, "Initialisation").

    Sums the raw specific force; every ``gravity_interval_s`` its mean is a horizontal
    specific-force measurement ``(C_nb f)_NE = 0`` (:func:`~iotnav.engines.eskf.models.gravity_rows`) when the
    GNSS-derived horizontal acceleration (at most two intervals old) is at most
    ``gravity_max_acc_mps2``; that acceleration and its own error enter ``R`` per axis, with
    the accelerometer's white noise over the interval.
    """
    st[E_GRAV_SUM] += fx
    st[E_GRAV_SUM + 1] += fy
    st[E_GRAV_SUM + 2] += fz
    st[E_GRAV_N] += 1.0
    T = t - st[E_T_GRAV]
    if T < prm[Q_GRAV_INTERVAL]:
        return
    n = st[E_GRAV_N]
    a_h = st[E_A_GNSS]
    fresh = t - st[E_T_A_GNSS] <= 2.0 * prm[Q_GRAV_INTERVAL]
    if n >= 5.0 and fresh and a_h <= prm[Q_GRAV_MAX_ACC]:
        C_nb, _v_n, _p_n, _b_g, b_a, _s_g, s_a, _C_vb, _e_n, _e_gm = nom
        f_mean = np.empty(3)
        for i in range(3):
            f_mean[i] = st[E_GRAV_SUM + i] / n
        M.gravity_rows(C_nb, f_mean, b_a, s_a, y, H)
        y[0] = -y[0]
        y[1] = -y[1]
        var = prm[Q_ND_A] ** 2 / T + a_h * a_h + st[E_SA_GNSS] ** 2
        R[:, :] = 0.0
        R[0, 0] = var
        R[1, 1] = var
        gate = prm[Q_GATE2]
        if st[E_GRAV_REJ] >= prm[Q_GRAV_MAX_REJ]:
            # the tilt is further off than its covariance says (a gyro bias beyond the
            # configured turn-on bias): re-open the tilt, decorrelated, and take this update
            for i in range(2):
                P[M.ATT_0 + i, :] = 0.0
                P[:, M.ATT_0 + i] = 0.0
                P[M.ATT_0 + i, M.ATT_0 + i] = prm[Q_GRAV_REOPEN_STD] ** 2
            gate = -1.0
            st[E_GRAV_RESETS] += 1.0
        if _apply_nb(t, 6, y, H, R, 2, gate, P, nom, acc, noise, st, prm, rec, sm):
            st[E_GRAV_REJ] = 0.0
        else:
            st[E_GRAV_REJ] += 1.0
    st[E_GRAV_SUM : E_GRAV_SUM + 3] = 0.0
    st[E_GRAV_N] = 0.0
    st[E_T_GRAV] = t


@numba.njit(cache=True)
def _output_row_nb(
    k: int,
    t: float,
    of: FloatArray,
    ostat: npt.NDArray[np.bool_],
    osrc: npt.NDArray[np.int8],
    st: FloatArray,
    prm: FloatArray,
    nom: Any,
    P: FloatArray,
    src_dr_velocity: int,
) -> None:
    """Row ``k``: attitude of ``C_nb C_vb^T`` (of ``C_nb`` before the mount is known), NED and geodetic position.

    ``src_dr_velocity``: the output block's ``source`` code of ``dr_velocity`` (the last fix
    moved on at its velocity, before the heading).
    """
    C_nb, v_n, p_n, _b_g, _b_a, _s_g, _s_a, C_vb, _e_n, _e_gm = nom
    nan = math.nan
    roll = pitch = yaw = nan
    if st[E_LEVELLED] != 0.0:
        if st[E_MOUNT_OK] != 0.0:
            c20 = C_nb[2, 0] * C_vb[0, 0] + C_nb[2, 1] * C_vb[0, 1] + C_nb[2, 2] * C_vb[0, 2]
            c21 = C_nb[2, 0] * C_vb[1, 0] + C_nb[2, 1] * C_vb[1, 1] + C_nb[2, 2] * C_vb[1, 2]
            c22 = C_nb[2, 0] * C_vb[2, 0] + C_nb[2, 1] * C_vb[2, 1] + C_nb[2, 2] * C_vb[2, 2]
            c10 = C_nb[1, 0] * C_vb[0, 0] + C_nb[1, 1] * C_vb[0, 1] + C_nb[1, 2] * C_vb[0, 2]
            c00 = C_nb[0, 0] * C_vb[0, 0] + C_nb[0, 1] * C_vb[0, 1] + C_nb[0, 2] * C_vb[0, 2]
        else:
            c20, c21, c22, c10, c00 = C_nb[2, 0], C_nb[2, 1], C_nb[2, 2], C_nb[1, 0], C_nb[0, 0]
        # as iotnav.geo.dcm_to_rpy
        roll = math.atan2(c21, c22)
        pitch = math.asin(max(-1.0, min(1.0, -c20)))
        yaw = math.atan2(c10, c00) if st[E_HEADING_OK] != 0.0 else nan
    of[C_T, k] = t
    of[C_ROLL, k] = roll
    of[C_PITCH, k] = pitch
    of[C_YAW, k] = yaw
    ostat[k] = st[E_STATIC] != 0.0
    if st[E_HAS_FRAME] == 0.0:
        for c in (C_LAT, C_LON, C_HEIGHT, C_NORTH, C_EAST, C_DOWN, C_VN, C_VE, C_VD, C_STD_NORTH, C_STD_EAST):
            of[c, k] = nan
        osrc[k] = SRC_NONE
        return
    if st[E_HEADING_OK] != 0.0 and st[E_POS_OK] != 0.0:
        r0, r1, r2 = p_n[0], p_n[1], p_n[2]
        of[C_VN, k] = v_n[0]
        of[C_VE, k] = v_n[1]
        of[C_VD, k] = v_n[2]
        of[C_STD_NORTH, k] = math.sqrt(P[0, 0])
        of[C_STD_EAST, k] = math.sqrt(P[1, 1])
        osrc[k] = SRC_FIX if t - st[E_T_FIX] <= prm[Q_FIX_HOLD] else SRC_DR
    else:
        # before the heading: the last fix extrapolated with the GNSS velocity, its claimed
        # sigma growing with the time since the fix (package docstring, "Initialisation")
        dt = t - st[E_FIX_T]
        r0 = st[E_FIX_Z] + st[E_FIX_V] * dt
        r1 = st[E_FIX_Z + 1] + st[E_FIX_V + 1] * dt
        r2 = st[E_FIX_Z + 2] + st[E_FIX_V + 2] * dt
        of[C_VN, k] = st[E_FIX_V]
        of[C_VE, k] = st[E_FIX_V + 1]
        of[C_VD, k] = st[E_FIX_V + 2]
        tau = max(dt, 0.0)
        a = st[E_FIX_ACC]
        v_r = st[E_FIX_REACH]
        t_r = v_r / a if a > 0.0 else math.inf  # when the velocity change a t reaches v_r
        dyn = 0.5 * a * tau * tau if tau <= t_r else v_r * (tau - 0.5 * t_r)
        grow = (st[E_FIX_SV] * tau) ** 2 + dyn * dyn
        of[C_STD_NORTH, k] = math.sqrt(st[E_FIX_SIG] ** 2 + grow)
        of[C_STD_EAST, k] = math.sqrt(st[E_FIX_SIG + 1] ** 2 + grow)
        if dt <= prm[Q_FIX_HOLD]:
            osrc[k] = SRC_FIX
        elif st[E_FIX_V] == 0.0 and st[E_FIX_V + 1] == 0.0:
            osrc[k] = SRC_LAST_POSITION  # the fix held (it gave no horizontal velocity)
        else:
            osrc[k] = src_dr_velocity  # the fix moved on at its own velocity
    of[C_NORTH, k] = r0
    of[C_EAST, k] = r1
    of[C_DOWN, k] = r2
    # TangentPlane.from_ned
    of[C_LAT, k] = st[E_LAT0] + r0 / st[E_KN]
    of[C_LON, k] = st[E_LON0] + r1 / st[E_KE]
    of[C_HEIGHT, k] = st[E_H0] - r2


@numba.njit(cache=True)
def _imu_kernel(
    t: FloatArray,
    acc_b: Any,
    gyro_b: Any,
    of: FloatArray,
    ostat: npt.NDArray[np.bool_],
    osrc: npt.NDArray[np.int8],
    i0: int,
    i1: int,
    resume: bool,
    st: FloatArray,
    prm: FloatArray,
    nom: Any,
    P: FloatArray,
    acc: FloatArray,
    noise: FloatArray,
    g_n: FloatArray,
    sd_state: FloatArray,
    sd_speeds: FloatArray,
    sd_params: FloatArray,
    imu_sums: FloatArray,
    rec: FloatArray,
    sm: Any,
    src_dr_velocity: int,
) -> tuple[int, int]:
    """The ``eskf`` IMU step over samples ``i0 .. i1-1`` (see :meth:`EskfEngine.imu_block`).

    Returns the sample index and a ``K_*`` code: ``K_DONE`` (``i1``), ``K_LEVEL`` (levelling
    window complete at that sample: Python finishes it, then calls again with ``resume`` to
    run the rest of that sample), ``K_FLUSH`` (record buffer, or smoothing record buffer, full
    before that sample). ``sm``: the smoothing arrays (:attr:`EskfEngine.sm`), untouched
    unless recording. ``src_dr_velocity``: the ``source`` code of ``dr_velocity`` in ``osrc``.
    """
    C_nb, v_n, _p_n, b_g, b_a, s_g, s_a, C_vb, _e_n, _e_gm = nom
    ax, ay, az = acc_b
    gx, gy, gz = gyro_b
    n = P.shape[0]
    fw = np.empty(6)
    fc = np.empty(3)
    y = np.zeros(3)
    H = np.zeros((3, n))
    R = np.zeros((3, 3))
    for k in range(i0, i1):
        tk = t[k]
        if not (resume and k == i0):
            if st[E_NREC] > rec.shape[0] - 4 or (st[E_SM_ON] != 0.0 and st[E_SM_N] > sm[3].shape[0] - 4):
                return k, K_FLUSH
            st[E_N_IMU] += 1.0
            if st[E_HAVE_IMU] == 0.0:
                st[E_T_STATE] = tk
                st[E_HAVE_IMU] = 1.0
                st[E_LEVEL_T0] = tk
            else:
                _integrate_to_nb(tk, st, prm, nom, g_n, acc, P, noise, fw, sm)
            st[E_F_PEND] = ax[k]
            st[E_F_PEND + 1] = ay[k]
            st[E_F_PEND + 2] = az[k]
            st[E_W_PEND] = gx[k]
            st[E_W_PEND + 1] = gy[k]
            st[E_W_PEND + 2] = gz[k]
            if st[E_LEVELLED] == 0.0:
                ls = E_LEVEL_SUM
                st[ls] += ax[k]
                st[ls + 1] += ay[k]
                st[ls + 2] += az[k]
                st[ls + 3] += gx[k]
                st[ls + 4] += gy[k]
                st[ls + 5] += gz[k]
                st[ls + 6] += ax[k] * ax[k] + ay[k] * ay[k] + az[k] * az[k]
                st[E_LEVEL_N] += 1.0
                if not (tk - st[E_LEVEL_T0] < prm[Q_LEVEL_TIME] or st[E_LEVEL_N] < 2.0):
                    return k, K_LEVEL
        levelled = st[E_LEVELLED] != 0.0
        # block 3 on the low-passed C_nb f_b
        M.compensate_into(st[E_F_PEND : E_F_PEND + 3], b_a, s_a, fc)
        was = st[E_STATIC] != 0.0
        v_dr = math.hypot(v_n[0], v_n[1]) if st[E_POS_OK] != 0.0 and st[E_HEADING_OK] != 0.0 else math.nan
        tau = prm[Q_PREFILT_TAU]
        a = 1.0 if tau <= 0.0 else 1.0 - math.exp(-max(tk - st[E_T_PREFILT], 0.0) / tau)
        st[E_T_PREFILT] = tk
        fn0 = 0.0
        fn1 = 0.0
        for i in range(3):
            fni = C_nb[i, 0] * fc[0] + C_nb[i, 1] * fc[1] + C_nb[i, 2] * fc[2]
            st[E_F_N_LP + i] += a * (fni - st[E_F_N_LP + i])
            if i == 0:
                fn0 = fni
            elif i == 1:
                fn1 = fni
        static = False
        if levelled:
            static = static_step(sd_state, sd_speeds, sd_params, tk, st[E_F_N_LP], st[E_F_N_LP + 1], v_dr)
        st[E_STATIC] = 1.0 if static else 0.0
        if static != was:
            j = int(st[E_NREC])
            rec[j, R_KIND] = REC_STATIC_START if static else REC_STATIC_END
            rec[j, R_T] = tk
            st[E_NREC] = j + 1
            st[E_ZARU_SUM : E_ZARU_SUM + 3] = 0.0
            st[E_ZARU_N] = 0.0
            st[E_T_ZARU] = tk
        if static:
            st[E_STATIC_SEEN] = 1.0
            st[E_ZARU_SUM] += gx[k]
            st[E_ZARU_SUM + 1] += gy[k]
            st[E_ZARU_SUM + 2] += gz[k]
            st[E_ZARU_N] += 1.0
            quiet = math.hypot(st[E_F_N_LP], st[E_F_N_LP + 1]) < prm[Q_ZUPT_MAX_ACC] and not (
                tk - st[E_T_SPEED] < 1.5 and st[E_LAST_SPEED] > prm[Q_ZUPT_MAX_GNSS_SPEED]
            )
            if tk - st[E_T_ZUPT] >= prm[Q_ZUPT_INTERVAL] and levelled and quiet:
                _static_updates_nb(tk, st, prm, nom, P, acc, noise, rec, y, H, R, sm)
        # mount aligner (block 5) while the mount yaw is unknown
        if st[E_MOUNT_OK] == 0.0 and levelled:
            psi = math.atan2(C_nb[1, 0], C_nb[0, 0])
            cp, sp = math.cos(psi), math.sin(psi)
            M.compensate_into(st[E_W_PEND : E_W_PEND + 3], b_g, s_g, fc)
            r = C_nb[2, 0] * fc[0] + C_nb[2, 1] * fc[1] + C_nb[2, 2] * fc[2]
            accumulate_levelled(imu_sums, cp * fn0 + sp * fn1, -sp * fn0 + cp * fn1, r)
        if prm[Q_GRAV] != 0.0 and levelled and st[E_HEADING_OK] == 0.0 and st[E_STATIC_SEEN] == 0.0:
            _gravity_nb(tk, ax[k], ay[k], az[k], st, prm, nom, P, acc, noise, rec, y, H, R, sm)
        if (
            prm[Q_NHC] != 0.0
            and st[E_HEADING_OK] != 0.0
            and st[E_POS_OK] != 0.0
            and st[E_MOUNT_OK] != 0.0
            and not static
            and tk - st[E_T_NHC] >= prm[Q_NHC_INTERVAL]
        ):
            st[E_T_NHC] = tk
            if math.hypot(v_n[0], v_n[1]) >= prm[Q_NHC_MIN_SPEED]:
                M.nhc_rows(C_nb, v_n, C_vb, y, H)
                y[0] = -y[0]
                y[1] = -y[1]
                R[:, :] = 0.0
                R[0, 0] = prm[Q_NHC_LAT] ** 2
                R[1, 1] = prm[Q_NHC_VERT] ** 2
                _apply_nb(tk, 2, y, H, R, 2, prm[Q_GATE2], P, nom, acc, noise, st, prm, rec, sm)
        _output_row_nb(k, tk, of, ostat, osrc, st, prm, nom, P, src_dr_velocity)
    return i1, K_DONE


def params(c: EskfConfig, gates: dict[int, float]) -> FloatArray:
    """The parameter array ``prm`` (:data:`~iotnav.engines.eskf.layout.PRM`) of the compiled IMU path."""
    prm = np.full(PRM_SIZE, math.nan)
    prm[Q_COV_INTERVAL] = c.cov_interval_s
    prm[Q_PREFILT_TAU] = c.static_prefilter_tau_s
    prm[Q_ZUPT_MAX_ACC] = c.zupt_max_acc_mps2
    prm[Q_ZUPT_MAX_GNSS_SPEED] = c.zupt_max_gnss_speed_mps
    prm[Q_ZUPT_INTERVAL] = c.zupt_interval_s
    prm[Q_ZUPT_NOISE] = c.zupt_noise_mps
    prm[Q_ZARU_INTERVAL] = c.zaru_interval_s
    prm[Q_ND_G] = c.gyro_noise_density_mdps_rthz * 1e-3 * DEG
    prm[Q_ZARU_FLOOR] = c.zaru_floor_dps * DEG
    prm[Q_NHC] = 1.0 if c.nhc else 0.0
    prm[Q_NHC_INTERVAL] = c.nhc_interval_s
    prm[Q_NHC_MIN_SPEED] = c.nhc_min_speed_mps
    prm[Q_NHC_LAT] = c.nhc_lateral_noise_mps
    prm[Q_NHC_VERT] = c.nhc_vertical_noise_mps
    prm[Q_LEVEL_TIME] = c.level_time_s
    prm[Q_FIX_HOLD] = c.fix_hold_s
    prm[Q_FIX_STD] = c.uere_m * c.default_hdop / math.sqrt(2.0)  # per axis (iotnav.gnss_accuracy)
    prm[Q_EST_MOUNT] = 1.0 if c.estimate_mount else 0.0
    prm[Q_GATE1] = gates[1]
    prm[Q_GATE2] = gates[2]
    prm[Q_GATE3] = gates[3]
    prm[Q_RECORD_EVERY] = float(c.record_every)
    prm[Q_GRAV] = 1.0 if c.gravity_aiding else 0.0
    prm[Q_GRAV_INTERVAL] = c.gravity_interval_s
    prm[Q_GRAV_MAX_ACC] = c.gravity_max_acc_mps2
    prm[Q_ND_A] = c.acc_noise_density_ug_rthz * 1e-6 * G0
    prm[Q_GRAV_MAX_REJ] = float(c.max_gravity_rejections)
    prm[Q_GRAV_REOPEN_STD] = c.gravity_reopen_std_rad
    return prm
