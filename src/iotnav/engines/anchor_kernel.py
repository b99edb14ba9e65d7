"""The anchor-node engine's compiled IMU kernel and its state layout (:mod:`iotnav.engines.anchor`).

Moved out of :mod:`iotnav.engines.anchor` unchanged; the engine imports everything from here.
"""

from __future__ import annotations

import math

import numba
import numpy as np
import numpy.typing as npt

from iotnav.engines.base import (
    C_T,
    SRC_DR,
    SRC_FIX,
    SRC_NONE,
    write_attitude,
    write_no_position,
    write_position,
)
from iotnav.engines.smoother import (
    record_size,
    write_record,
)
from iotnav.techniques.cascade import CS_C, CS_OMEGA, FrontEnd, front_end_step
from iotnav.techniques.mount import accumulate_levelled

FloatArray = npt.NDArray[np.float64]

#: State layout.
POS = slice(0, 3)
VEL = slice(3, 6)
N_STATES = 6

# Scalars shared by the compiled IMU kernel and the Python GNSS code (``AnchorEngine._st``).
(
    AT_T_IMU,
    AT_T_X,
    AT_INIT,
    AT_SIGMA_A2,
    AT_STATIC,
    AT_T_FIX,
    AT_A_LONG,
    AT_V_GNSS,
    AT_T_SPEED,
    AT_G,
    AT_HAVE_FRAME,
    AT_HAS_PRIOR,
    AT_ROWS,
    AT_N_REC,
    AT_AN,
) = range(15)
AT_SIZE = AT_AN + 3
# Kernel parameters (``AnchorEngine._prm``).
AP_QA, AP_ATT_Q, AP_SMOOTH, AP_RECORD_EVERY, AP_FIX_HOLD = range(5)
# Columns of a smoothing record (:func:`~iotnav.engines.smoother.write_record`).
REC_SIZE = record_size(N_STATES)
# Flags returned by the kernel: a static change (event), a full record buffer (drain it).
EV_STATIC = 1
EV_FULL = 4


@numba.njit(cache=True)
def anchor_flush(st: FloatArray, kf: FloatArray, prior: FloatArray, Phi: FloatArray, rec: FloatArray) -> None:
    """Write a smoothing record point into the next row of ``rec`` and restart ``Phi``.

    ``kf`` is the filter array (``x`` 6, ``P`` 36), ``prior`` its copy before the pending
    measurement updates (used when ``st[AT_HAS_PRIOR]``), ``Phi`` (36) the transition since the
    previous record point (:func:`~iotnav.engines.smoother.write_record`).
    """
    n = int(st[AT_N_REC])
    write_record(rec, n, st[AT_T_X], prior if st[AT_HAS_PRIOR] != 0.0 else kf, kf, Phi, N_STATES)
    st[AT_HAS_PRIOR] = 0.0
    st[AT_ROWS] = 0.0
    st[AT_N_REC] = n + 1


@numba.njit(cache=True)
def anchor_predict_to(
    st: FloatArray,
    prm: FloatArray,
    kf: FloatArray,
    prior: FloatArray,
    Phi: FloatArray,
    rec: FloatArray,
    t: float,
) -> None:
    """Predict the filter array ``kf`` to time ``t`` (s) with the latest control input (module docstring).

    ``x- = F x + B u``, ``P- = sym(F P F^T + Q)`` with ``F``, ``B``, ``Q`` of :func:`transition`
    written out per 3 x 3 block; ``q_a`` grows with the attitude term when ``attitude_in_q``.
    A pending record point (after a measurement update) is flushed first; ``Phi`` accumulates
    ``F`` when smoothing.
    """
    if st[AT_INIT] == 0.0 or not math.isfinite(st[AT_T_X]):
        st[AT_T_X] = t
        return
    dt = t - st[AT_T_X]
    if dt <= 0.0:
        return
    if st[AT_HAS_PRIOR] != 0.0:
        anchor_flush(st, kf, prior, Phi, rec)
    q_a = prm[AP_QA]
    if prm[AP_ATT_Q] != 0.0:
        s_f = max(0.0, st[AT_T_X] - st[AT_T_FIX]) + 0.5 * dt  # time since the last fix, mid-step
        q_a += 3.0 * st[AT_SIGMA_A2] * s_f
    h = 0.5 * dt * dt
    for i in range(3):
        u = st[AT_AN + i]
        kf[i] += dt * kf[3 + i] + h * u
        kf[3 + i] += dt * u
    # P = [[A, B], [B^T, D]] (3 x 3 blocks): A' = A + dt (B + B^T) + dt^2 D, B' = B + dt D
    q3, q2, q1 = q_a * dt**3 / 3.0, q_a * dt**2 / 2.0, q_a * dt
    for i in range(3):
        for j in range(3):
            a = kf[6 + 6 * i + j]
            b = kf[6 + 6 * i + 3 + j]
            bt = kf[6 + 6 * (3 + i) + j]
            d = kf[6 + 6 * (3 + i) + 3 + j]
            kf[6 + 6 * i + j] = a + dt * (b + bt) + dt * dt * d
            kf[6 + 6 * i + 3 + j] = b + dt * d
            kf[6 + 6 * (3 + i) + j] = bt + dt * d
        kf[6 + 7 * i] += q3
        kf[6 + 6 * i + 3 + i] += q2
        kf[6 + 6 * (3 + i) + i] += q2
        kf[6 + 7 * (3 + i)] += q1
    for i in range(6):
        for j in range(i + 1, 6):
            v = 0.5 * (kf[6 + 6 * i + j] + kf[6 + 6 * j + i])
            kf[6 + 6 * i + j] = v
            kf[6 + 6 * j + i] = v
    if prm[AP_SMOOTH] != 0.0:
        for i in range(3):
            for j in range(6):
                Phi[6 * i + j] += dt * Phi[6 * (3 + i) + j]
    st[AT_T_X] = t


@numba.njit(cache=True)
def anchor_imu_kernel(
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
    prm: FloatArray,
    frame: FloatArray,
    kf: FloatArray,
    prior: FloatArray,
    Phi: FloatArray,
    rec: FloatArray,
    fe: FrontEnd,
    mount_sums: FloatArray,
    mount_yaw: float,
    mount_known: bool,
    mount_done: bool,
) -> tuple[int, int]:
    """The IMU step of :class:`AnchorEngine` over samples ``i0 .. i1-1`` (module docstring).

    Reads device time ``t`` (s), specific force ``ax, ay, az`` (m/s^2) and rate ``gx, gy, gz``
    (rad/s) in the sensor frame; writes row ``k`` of the output columns for sample ``k``.
    Returns ``(next index, EV_* flags)``: it stops after a static change (an event for Python)
    and before a sample when ``rec`` might not hold its record points; ``(i1, 0)`` when done.
    """
    cos_mu = math.cos(mount_yaw)
    sin_mu = math.sin(mount_yaw)
    smoothing = prm[AP_SMOOTH] != 0.0
    cs = fe.cs
    C = cs[CS_C : CS_C + 9]
    for k in range(i0, i1):
        if st[AT_N_REC] + 2.0 > rec.shape[0]:
            return k, EV_FULL
        tk = t[k]
        a0, a1, a2 = ax[k], ay[k], az[k]
        dt = tk - st[AT_T_IMU] if math.isfinite(st[AT_T_IMU]) else 0.0
        st[AT_T_IMU] = tk
        # prediction to t_k with the previous sample's acceleration (mean over [t_k-1, t_k))
        anchor_predict_to(st, prm, kf, prior, Phi, rec, tk)
        g = st[AT_G]
        was = st[AT_STATIC] != 0.0
        init = st[AT_INIT] != 0.0
        v_dr = math.hypot(kf[3], kf[4]) if init else math.nan
        f0, f1, f2, static = front_end_step(
            fe,
            tk,
            a0,
            a1,
            a2,
            gx[k],
            gy[k],
            gz[k],
            dt,
            was,
            g,
            st[AT_A_LONG],
            st[AT_V_GNSS],
            st[AT_T_SPEED],
            v_dr,
        )
        st[AT_STATIC] = 1.0 if static else 0.0
        flags = EV_STATIC if static != was else 0
        if not mount_done:
            psi = math.atan2(C[3], C[0])
            cp, sp = math.cos(psi), math.sin(psi)
            r_yaw = C[6] * cs[CS_OMEGA] + C[7] * cs[CS_OMEGA + 1] + C[8] * cs[CS_OMEGA + 2]
            accumulate_levelled(mount_sums, cp * f0 + sp * f1, -sp * f0 + cp * f1, r_yaw)
        st[AT_AN] = f0
        st[AT_AN + 1] = f1
        st[AT_AN + 2] = f2 + g
        f_h2 = f0 * f0 + f1 * f1
        tilt_tr = fe.tilt_s[3] + fe.tilt_s[7] + fe.tilt_s[11]
        yaw_tr = fe.yaw_s[3] + fe.yaw_s[7] + fe.yaw_s[11]
        st[AT_SIGMA_A2] = g * g * 0.5 * tilt_tr + f_h2 * yaw_tr
        floats[C_T, k] = tk
        write_attitude(floats, k, C, cos_mu, sin_mu, mount_known)
        static_out[k] = static
        if not init or st[AT_HAVE_FRAME] == 0.0:
            write_no_position(floats, k)
            source_out[k] = SRC_NONE
        else:
            if smoothing:
                st[AT_ROWS] += 1.0
                if st[AT_HAS_PRIOR] != 0.0 or st[AT_ROWS] >= prm[AP_RECORD_EVERY]:
                    anchor_flush(st, kf, prior, Phi, rec)
            write_position(floats, k, kf[0:3], kf[3:6], math.sqrt(kf[6]), math.sqrt(kf[13]), frame)
            source_out[k] = SRC_FIX if tk - st[AT_T_FIX] <= prm[AP_FIX_HOLD] else SRC_DR
        if flags:
            return k + 1, flags
    return i1, 0
