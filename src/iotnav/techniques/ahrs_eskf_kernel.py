"""Compiled per-sample step of the error-state quaternion AHRS (:mod:`iotnav.techniques.ahrs_eskf`).

The model, its equations and references (Solà 2017, error-state kinematics with the global
attitude error; Laidig and Seel 2023, VQF's quasi-inertial accelerometer low-pass, rest and
magnetic disturbance tests) are stated in :mod:`iotnav.techniques.ahrs_eskf`; this module holds
the numba kernels (``cache=True``) that implement them on the filter's hot state array
(``S_*`` layout, angles in rad, rates in rad/s, specific force in m/s^2) and parameter vector
(``PR_*`` layout): the shared scalar logic (also callable as plain Python), the Kalman update
and covariance prediction written out as small loops, :func:`rest_update`, :func:`ahrs_step`
and the batch loop ``_run``.
"""

from __future__ import annotations

import math

import numba
import numpy as np
import numpy.typing as npt

FloatArray = npt.NDArray[np.float64]


# --------------------------------------------------------------------------------------------
# Shared scalar logic (used as plain Python by the reference path and compiled for the kernel)
# --------------------------------------------------------------------------------------------


def _dip_angle(
    C00: float,
    C01: float,
    C02: float,
    C10: float,
    C11: float,
    C12: float,
    C20: float,
    C21: float,
    C22: float,
    mx: float,
    my: float,
    mz: float,
) -> tuple[float, float, float, float]:
    """``m_n = C m_b`` and its dip angle (rad, positive when pointing down)."""
    mnx = C00 * mx + C01 * my + C02 * mz
    mny = C10 * mx + C11 * my + C12 * mz
    mnz = C20 * mx + C21 * my + C22 * mz
    norm = math.sqrt(mnx * mnx + mny * mny + mnz * mnz)
    dip = math.asin(min(1.0, max(-1.0, mnz / norm))) if norm > 0.0 else 0.0
    return mnx, mny, norm, dip


def _rest_step(
    lp: FloatArray,
    gyr: FloatArray,
    acc: FloatArray,
    alpha: float,
    th_gyr: float,
    th_acc: float,
    max_rate: float,
    rest_time: float,
    dt: float,
) -> float:
    """Advance the rest detector; ``lp[0:3]`` gyro and ``lp[3:6]`` acc low-pass (in place).

    Returns the time (s) the sensor has been continuously at rest (0 when moving).
    """
    dg = 0.0
    da = 0.0
    r = 0.0
    for i in range(3):
        lp[i] += alpha * (gyr[i] - lp[i])
        lp[3 + i] += alpha * (acc[i] - lp[3 + i])
        dg += (gyr[i] - lp[i]) ** 2
        da += (acc[i] - lp[3 + i]) ** 2
        r += lp[i] ** 2
    if math.sqrt(dg) < th_gyr and math.sqrt(da) < th_acc and math.sqrt(r) < max_rate:
        return rest_time + dt
    return 0.0


def _mag_check(ref: FloatArray, norm: float, dip: float, cfg: FloatArray, dt: float) -> bool:
    """Magnetic disturbance test and reference tracking (``ref`` updated in place).

    ``ref = [norm_ref, dip_ref, candidate_norm, candidate_dip, candidate_time, initialised]``;
    ``cfg = [norm_rel_th, dip_th, ref_tau, new_field_s]``. Returns True when the field is usable.
    """
    if ref[5] == 0.0:
        ref[0] = norm
        ref[1] = dip
        ref[5] = 1.0
        return True
    ok = abs(norm - ref[0]) < cfg[0] * ref[0] and abs(dip - ref[1]) < cfg[1]
    if ok:
        a = dt / (cfg[2] + dt)
        ref[0] += a * (norm - ref[0])
        ref[1] += a * (dip - ref[1])
        ref[4] = 0.0
        return True
    # disturbed: is it a steady new field?
    steady = abs(norm - ref[2]) < cfg[0] * ref[2] and abs(dip - ref[3]) < cfg[1]
    if ref[4] > 0.0 and steady:
        ref[4] += dt
    else:
        ref[2] = norm
        ref[3] = dip
        ref[4] = dt
    if ref[4] >= cfg[3]:
        ref[0] = ref[2]
        ref[1] = ref[3]
        ref[4] = 0.0
        return True
    return False


def _acc_lp_step(C_I: FloatArray, f: FloatArray, lp: FloatArray, alpha: float, first: bool) -> None:
    """Two cascaded first-order low-passes of ``f_I = C_I f`` (``lp[0:3]``, ``lp[3:6]``, in place)."""
    for i in range(3):
        a = C_I[i, 0] * f[0] + C_I[i, 1] * f[1] + C_I[i, 2] * f[2]
        if first:
            lp[i] = a
            lp[3 + i] = a
        else:
            lp[i] += alpha * (a - lp[i])
            lp[3 + i] += alpha * (lp[i] - lp[3 + i])


def _acc_innovation(C_nb: FloatArray, C_I: FloatArray, lp: FloatArray) -> tuple[float, float, float]:
    """Horizontal components of ``a_n = C_nb C_I^T lp / |lp|`` and ``|lp|``."""
    v0, v1, v2 = lp[3], lp[4], lp[5]
    nrm = math.sqrt(v0 * v0 + v1 * v1 + v2 * v2)
    # back to b with C_I^T, then to n with C_nb
    b0 = C_I[0, 0] * v0 + C_I[1, 0] * v1 + C_I[2, 0] * v2
    b1 = C_I[0, 1] * v0 + C_I[1, 1] * v1 + C_I[2, 1] * v2
    b2 = C_I[0, 2] * v0 + C_I[1, 2] * v1 + C_I[2, 2] * v2
    ax = (C_nb[0, 0] * b0 + C_nb[0, 1] * b1 + C_nb[0, 2] * b2) / nrm
    ay = (C_nb[1, 0] * b0 + C_nb[1, 1] * b1 + C_nb[1, 2] * b2) / nrm
    return ax, ay, nrm


_acc_lp_step_nb = numba.njit(cache=True)(_acc_lp_step)
_acc_innovation_nb = numba.njit(cache=True)(_acc_innovation)
_rest_step_nb = numba.njit(cache=True)(_rest_step)
_mag_check_nb = numba.njit(cache=True)(_mag_check)
_dip_angle_nb = numba.njit(cache=True)(_dip_angle)


# --------------------------------------------------------------------------------------------
# The per-sample step (compiled; shared by the streaming class and the batch loop, STYLE §7)
# --------------------------------------------------------------------------------------------

#: Layout of the filter's hot state array (float64): nominal ``q_nb`` and ``b_g``, the
#: quasi-inertial strapdown ``q_Ib``, the two accelerometer low-passes in ``I``, the rest
#: detector's gyro/acc low-passes, the magnetic reference, the rest timer, the first-sample
#: flag of the accelerometer low-pass, the low-passed accelerometer at the start of the current
#: rest window, the low-passed squared specific-force norm deviation and the first-sample flag
#: of the rest low-passes.
S_Q, S_BG, S_QI, S_ACC_LP, S_REST_LP, S_MAG_REF = 0, 4, 7, 11, 17, 23
S_REST_T, S_ACC_FIRST, S_REST_ACC0, S_DYN, S_REST_FIRST = 29, 30, 31, 34, 35
STATE_SIZE = 36

#: Layout of the parameter vector (:func:`_params`).
(
    PR_GYRO,
    PR_BIAS_RW,
    PR_ACC,
    PR_ACC_ADAPT,
    PR_ACC_REJECT,
    PR_GRAV,
    PR_MAG,
    PR_DECL,
    PR_REST_TAU,
    PR_REST_GYR,
    PR_REST_ACC,
    PR_REST_RATE,
    PR_REST_MIN,
    PR_REST_NOISE,
    PR_MAG_NORM,
    PR_MAG_DIP,
    PR_MAG_REF_TAU,
    PR_MAG_NEW,
    PR_ACC_TAU,
    PR_REST_DRIFT,
    PR_DYN_SCALE,
    PR_DYN_TAU,
    PR_DISAGREE,
    PR_MOTION_BIAS,
) = range(24)
N_PARAMS = 24

#: Flag bits returned by :func:`ahrs_step`.
FLAG_REST, FLAG_ACC, FLAG_MAG = 1, 2, 4


@numba.njit(cache=True)
def _qmul(p: FloatArray, q: FloatArray) -> FloatArray:
    out = np.empty(4)
    out[0] = p[0] * q[0] - p[1] * q[1] - p[2] * q[2] - p[3] * q[3]
    out[1] = p[0] * q[1] + p[1] * q[0] + p[2] * q[3] - p[3] * q[2]
    out[2] = p[0] * q[2] - p[1] * q[3] + p[2] * q[0] + p[3] * q[1]
    out[3] = p[0] * q[3] + p[1] * q[2] - p[2] * q[1] + p[3] * q[0]
    return out


@numba.njit(cache=True)
def _qexp(vx: float, vy: float, vz: float) -> FloatArray:
    a = math.sqrt(vx * vx + vy * vy + vz * vz)
    out = np.empty(4)
    if a < 1e-12:
        out[0] = 1.0
        out[1] = 0.5 * vx
        out[2] = 0.5 * vy
        out[3] = 0.5 * vz
        return out / math.sqrt(out[0] ** 2 + out[1] ** 2 + out[2] ** 2 + out[3] ** 2)
    s = math.sin(0.5 * a) / a
    out[0] = math.cos(0.5 * a)
    out[1] = s * vx
    out[2] = s * vy
    out[3] = s * vz
    return out


@numba.njit(cache=True)
def _dcm(q: FloatArray) -> FloatArray:
    w, x, y, z = q[0], q[1], q[2], q[3]
    C = np.empty((3, 3))
    C[0, 0] = 1 - 2 * (y * y + z * z)
    C[0, 1] = 2 * (x * y - w * z)
    C[0, 2] = 2 * (x * z + w * y)
    C[1, 0] = 2 * (x * y + w * z)
    C[1, 1] = 1 - 2 * (x * x + z * z)
    C[1, 2] = 2 * (y * z - w * x)
    C[2, 0] = 2 * (x * z - w * y)
    C[2, 1] = 2 * (y * z + w * x)
    C[2, 2] = 1 - 2 * (x * x + y * y)
    return C


@numba.njit(cache=True)
def _kf_update(P: FloatArray, Ht: FloatArray, R: FloatArray, y: FloatArray, bias_gain: bool) -> FloatArray:
    """Kalman update of a zero error state, in place on ``P``; returns ``dx`` (6,).

    ``Ht`` is ``H^T`` (6, m), ``R`` (m, m), ``y`` the innovation (m,), m <= 3. The gain comes
    from a Cholesky solve of ``S = H P H^T + R`` (never ``inv(S)``), the covariance from the
    Joseph form, symmetrised; small loops instead of BLAS/LAPACK calls (no allocation beyond
    the few work arrays). With ``bias_gain`` False the gain rows of the gyro bias are zeroed
    (a Schmidt / consider update: the measurement corrects the attitude only and the Joseph
    form keeps the covariance honest for that suboptimal gain).
    """
    m = Ht.shape[1]
    PHt = np.zeros((6, m))
    for i in range(6):
        for j in range(m):
            acc = 0.0
            for k in range(6):
                acc += P[i, k] * Ht[k, j]
            PHt[i, j] = acc
    S = np.empty((m, m))
    for i in range(m):
        for j in range(m):
            acc = R[i, j]
            for k in range(6):
                acc += Ht[k, i] * PHt[k, j]
            S[i, j] = acc
    for i in range(m):  # symmetrise
        for j in range(i):
            v = 0.5 * (S[i, j] + S[j, i])
            S[i, j] = v
            S[j, i] = v
    L = np.zeros((m, m))  # Cholesky S = L L^T
    for i in range(m):
        for j in range(i + 1):
            acc = S[i, j]
            for k in range(j):
                acc -= L[i, k] * L[j, k]
            L[i, j] = math.sqrt(acc) if i == j else acc / L[j, j]
    K = np.zeros((6, m))  # K^T = S^-1 (P H^T)^T, row by row of K
    w = np.empty(m)
    for r in range(6):
        if not bias_gain and r >= 3:
            continue
        for i in range(m):  # L w = PHt[r]
            acc = PHt[r, i]
            for k in range(i):
                acc -= L[i, k] * w[k]
            w[i] = acc / L[i, i]
        for i in range(m - 1, -1, -1):  # L^T k = w
            acc = w[i]
            for k in range(i + 1, m):
                acc -= L[k, i] * K[r, k]
            K[r, i] = acc / L[i, i]
    dx = np.zeros(6)
    for i in range(6):
        for j in range(m):
            dx[i] += K[i, j] * y[j]
    A = np.empty((6, 6))  # I - K H
    for i in range(6):
        for j in range(6):
            acc = 1.0 if i == j else 0.0
            for k in range(m):
                acc -= K[i, k] * Ht[j, k]
            A[i, j] = acc
    AP = np.empty((6, 6))
    for i in range(6):
        for j in range(6):
            acc = 0.0
            for k in range(6):
                acc += A[i, k] * P[k, j]
            AP[i, j] = acc
    KR = np.empty((6, m))
    for i in range(6):
        for j in range(m):
            acc = 0.0
            for k in range(m):
                acc += K[i, k] * R[k, j]
            KR[i, j] = acc
    for i in range(6):
        for j in range(i + 1):
            acc = 0.0
            for k in range(6):
                acc += AP[i, k] * A[j, k]
            for k in range(m):
                acc += KR[i, k] * K[j, k]
            P[i, j] = acc
            P[j, i] = acc
    return dx


@numba.njit(cache=True)
def _predict_cov(P: FloatArray, C: FloatArray, dt: float, q_att: float, q_bias: float) -> None:
    """``P <- F P F^T + Q`` in place, ``F = [[I, -C_nb dt], [0, I]]``, ``Q = diag(q_att I, q_bias I)``.

    Written out by blocks (``G = -C_nb dt``): ``P_aa + G P_ba + P_ab G^T + G P_bb G^T``,
    ``P_ab + G P_bb``, ``P_bb``.
    """
    G = -C * dt
    Pab = P[0:3, 3:6].copy()
    Pbb = P[3:6, 3:6].copy()
    GPbb = np.zeros((3, 3))
    for i in range(3):
        for j in range(3):
            for k in range(3):
                GPbb[i, j] += G[i, k] * Pbb[k, j]
    for i in range(3):
        for j in range(3):
            acc = 0.0
            for k in range(3):
                acc += G[i, k] * Pab[j, k] + Pab[i, k] * G[j, k] + GPbb[i, k] * G[j, k]
            P[i, j] += acc
    for i in range(3):
        for j in range(i):
            v = 0.5 * (P[i, j] + P[j, i])
            P[i, j] = v
            P[j, i] = v
        for j in range(3):
            P[i, 3 + j] = Pab[i, j] + GPbb[i, j]
            P[3 + j, i] = P[i, 3 + j]
    for i in range(3):
        P[i, i] += q_att
        P[3 + i, 3 + i] += q_bias


@numba.njit(cache=True)
def _inject(st: FloatArray, dx: FloatArray) -> None:
    """``q_nb <- Exp(dtheta) (x) q_nb``, ``b_g <- b_g + db_g`` on the state array."""
    qn = _qmul(_qexp(dx[0], dx[1], dx[2]), st[S_Q : S_Q + 4])
    qn /= math.sqrt(qn[0] ** 2 + qn[1] ** 2 + qn[2] ** 2 + qn[3] ** 2)
    st[S_Q : S_Q + 4] = qn
    for i in range(3):
        st[S_BG + i] += dx[3 + i]


@numba.njit(cache=True)
def rest_update(st: FloatArray, gyr: FloatArray, acc: FloatArray, dt: float, prm: FloatArray) -> float:
    """Advance the rest detector on the state array (module docstring); returns the rest time, s.

    The sensor is at rest while the returned time is at least ``prm[PR_REST_MIN]``.
    """
    lp = st[S_REST_LP : S_REST_LP + 6]
    if st[S_REST_FIRST] != 0.0:  # start the rest low-passes at the first sample
        lp[0:3] = gyr
        lp[3:6] = acc
        st[S_REST_FIRST] = 0.0
    was = st[S_REST_T]
    rest_time = _rest_step_nb(
        lp,
        gyr,
        acc,
        dt / (prm[PR_REST_TAU] + dt),
        prm[PR_REST_GYR],
        prm[PR_REST_ACC],
        prm[PR_REST_RATE],
        was,
        dt,
    )
    # window test: the low-passed accelerometer must stay where it was when the window opened
    if rest_time > 0.0 and was == 0.0:
        st[S_REST_ACC0 : S_REST_ACC0 + 3] = lp[3:6]
    elif rest_time > 0.0:
        d0 = lp[3] - st[S_REST_ACC0]
        d1 = lp[4] - st[S_REST_ACC0 + 1]
        d2 = lp[5] - st[S_REST_ACC0 + 2]
        if math.sqrt(d0 * d0 + d1 * d1 + d2 * d2) > prm[PR_REST_DRIFT]:
            rest_time = 0.0
    st[S_REST_T] = rest_time
    return rest_time


@numba.njit(cache=True)
def _rest_run(
    gyr: FloatArray, acc: FloatArray, dt: float, st: FloatArray, prm: FloatArray
) -> npt.NDArray[np.bool_]:
    out = np.zeros(gyr.shape[0], dtype=np.bool_)
    for k in range(gyr.shape[0]):
        out[k] = rest_update(st, gyr[k], acc[k], dt, prm) >= prm[PR_REST_MIN]
    return out


@numba.njit(cache=True)
def ahrs_step(
    st: FloatArray,
    P: FloatArray,
    gyr: FloatArray,
    acc: FloatArray,
    mag: FloatArray,
    use_mag: bool,
    dt: float,
    prm: FloatArray,
) -> int:
    """One sample of the filter on its state array ``st`` (``S_*``) and covariance ``P`` (in place).

    Parameters
    ----------
    st : numpy.ndarray
        ``(STATE_SIZE,)`` hot state, initialised by :func:`initial_state`.
    P : numpy.ndarray
        ``(6, 6)`` error-state covariance (:data:`ATT`, :data:`BG`).
    gyr, acc, mag : numpy.ndarray
        ``(3,)`` angular rate (rad/s), specific force (m/s^2) and magnetic field (any unit) in
        ``b``; ``mag`` is ignored unless ``use_mag``.
    use_mag : bool
        Use the magnetometer for heading.
    dt : float
        Sample period, s.
    prm : numpy.ndarray
        Parameter vector (``PR_*``, :func:`_params`).

    Returns
    -------
    int
        Flag bits: :data:`FLAG_REST`, :data:`FLAG_ACC`, :data:`FLAG_MAG`.
    """
    flags = 0
    grav = prm[PR_GRAV]
    b = st[S_BG : S_BG + 3]
    # --- predict: strapdown of q_nb and of the quasi-inertial q_Ib, covariance
    dq = _qexp((gyr[0] - b[0]) * dt, (gyr[1] - b[1]) * dt, (gyr[2] - b[2]) * dt)
    q = _qmul(st[S_Q : S_Q + 4], dq)
    q /= math.sqrt(q[0] ** 2 + q[1] ** 2 + q[2] ** 2 + q[3] ** 2)
    st[S_Q : S_Q + 4] = q
    qI = _qmul(st[S_QI : S_QI + 4], dq)
    qI /= math.sqrt(qI[0] ** 2 + qI[1] ** 2 + qI[2] ** 2 + qI[3] ** 2)
    st[S_QI : S_QI + 4] = qI
    _predict_cov(P, _dcm(q), dt, prm[PR_GYRO] ** 2 * dt, prm[PR_BIAS_RW] ** 2 * dt)
    # --- rest detection and rest bias measurement
    rest_time = rest_update(st, gyr, acc, dt, prm)
    lp = st[S_REST_LP : S_REST_LP + 6]
    if rest_time >= prm[PR_REST_MIN]:
        Ht = np.zeros((6, 3))
        for i in range(3):
            Ht[3 + i, i] = 1.0
        y = lp[0:3] - b
        _inject(st, _kf_update(P, Ht, np.eye(3) * prm[PR_REST_NOISE] ** 2, y, True))
        flags |= FLAG_REST
    # --- accelerometer (tilt)
    fn = math.sqrt(acc[0] * acc[0] + acc[1] * acc[1] + acc[2] * acc[2])
    if fn > 0.0:
        dev = fn - grav
        st[S_DYN] += dt / (prm[PR_DYN_TAU] + dt) * (dev * dev - st[S_DYN])
    if fn > 0.0 and abs(fn - grav) <= prm[PR_ACC_REJECT]:
        C_I = _dcm(st[S_QI : S_QI + 4])
        acc_lp = st[S_ACC_LP : S_ACC_LP + 6]
        _acc_lp_step_nb(C_I, acc, acc_lp, dt / (prm[PR_ACC_TAU] + dt), st[S_ACC_FIRST] != 0.0)
        st[S_ACC_FIRST] = 0.0
        ax, ay, nrm = _acc_innovation_nb(_dcm(st[S_Q : S_Q + 4]), C_I, acc_lp)
        y2 = np.empty(2)
        y2[0] = ax
        y2[1] = ay
        r = prm[PR_ACC] ** 2 * (
            1.0
            + ((nrm - grav) / prm[PR_ACC_ADAPT]) ** 2
            + st[S_DYN] / prm[PR_DYN_SCALE] ** 2
            + (ax * ax + ay * ay) / prm[PR_DISAGREE] ** 2
        )
        Ht2 = np.zeros((6, 2))
        Ht2[1, 0] = 1.0
        Ht2[0, 1] = -1.0
        at_rest = (flags & FLAG_REST) != 0
        _inject(st, _kf_update(P, Ht2, np.eye(2) * r, y2, prm[PR_MOTION_BIAS] != 0.0 or at_rest))
        flags |= FLAG_ACC
    # --- magnetometer (heading only, projected update)
    if use_mag:
        C = _dcm(st[S_Q : S_Q + 4])
        mnx, mny, norm, dip = _dip_angle_nb(
            C[0, 0],
            C[0, 1],
            C[0, 2],
            C[1, 0],
            C[1, 1],
            C[1, 2],
            C[2, 0],
            C[2, 1],
            C[2, 2],
            mag[0],
            mag[1],
            mag[2],
        )
        if norm > 0.0 and _mag_check_nb(
            st[S_MAG_REF : S_MAG_REF + 6], norm, dip, prm[PR_MAG_NORM : PR_MAG_NEW + 1], dt
        ):
            sm = prm[PR_MAG]
            z = prm[PR_DECL] - math.atan2(mny, mnx)
            z = z - 2.0 * math.pi * round(z / (2.0 * math.pi))
            S = P[2, 2] + sm * sm
            kg = P[2, 2] / S
            pnew = (1.0 - kg) ** 2 * P[2, 2] + kg * kg * sm * sm
            for j in range(6):
                P[2, j] *= 1.0 - kg
                P[j, 2] *= 1.0 - kg
            P[2, 2] = pnew
            dx = np.zeros(6)
            dx[2] = kg * z
            _inject(st, dx)
            flags |= FLAG_MAG
    return flags


@numba.njit(cache=True)
def _run(
    gyr: FloatArray,
    acc: FloatArray,
    mag: FloatArray,
    dt: float,
    st: FloatArray,
    P: FloatArray,
    prm: FloatArray,
    use_mag: bool,
) -> tuple[FloatArray, FloatArray, npt.NDArray[np.int8]]:
    """The batch loop: :func:`ahrs_step` over every sample, recording ``q_nb``, ``b_g``, flags."""
    n = gyr.shape[0]
    q_out = np.empty((n, 4))
    b_out = np.empty((n, 3))
    flags = np.zeros(n, dtype=np.int8)
    for k in range(n):
        flags[k] = ahrs_step(st, P, gyr[k], acc[k], mag[k], use_mag, dt, prm)
        q_out[k] = st[S_Q : S_Q + 4]
        b_out[k] = st[S_BG : S_BG + 3]
    return q_out, b_out, flags
