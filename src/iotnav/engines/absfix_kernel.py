"""Compiled per-IMU-sample step of the ``absfix`` engine (:mod:`iotnav.engines.absfix`).

The model is stated in :mod:`iotnav.engines.absfix`'s docstring and the latency buffer's
method in :mod:`iotnav.techniques.latency`; ``tests/test_absfix.py`` checks these kernels
against runs stored from the per-sample Python engine they replaced (main at commit 23c36cc).
The engine's ``step()``, its batch :meth:`~iotnav.engines.absfix.AbsfixEngine.imu_block` and
the re-propagation of a late fix run the same :func:`propagate`:

* :func:`propagate`: the alignment sums before the first fix, then one strapdown step
  (flat-earth NED, mid-step attitude, trapezoidal position) and the interval integrals of
  :func:`iotnav.techniques.decoupled_bias.accumulate`, same arithmetic order;
* :func:`imu_run`: over a block of IMU samples, each sample propagated, buffered in the ring
  (its time, values and the state snapshot after propagation, before any fix), its output
  row written and the ring evicted to ``max_latency_s`` (and ``capacity``); it stops at the
  first sample at which a pending fix is due (:data:`EV_DUE`), for the engine to apply it;
* :func:`replay_run`: the re-propagation from a buffered epoch after a late fix, rewriting
  the snapshots and the revised rows, up to the next epoch that holds a fix.

The fix itself (the decoupled velocity, bias and drift solution and the reset) stays in the
engine's Python code: it runs once per fix, not per sample.

Ring buffer: entry ``s`` (a serial number counting every buffered IMU sample) lives in slot
``s % size``; ``rb`` holds the first serial, the count, the latest IMU period and the number
of re-propagated samples (``RB_*``). The engine starts with a small ring and grows it (up to
``capacity + 1`` slots: the buffer holds one entry over ``capacity`` between appending and
evicting) when :func:`imu_run` reports it full.
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
from iotnav.strapdown import rodrigues
from iotnav.techniques import decoupled_bias as db

FloatArray = npt.NDArray[np.float64]

# Flat state ``x`` (the engine's layout; the engine module re-exports the slices).
X_POS = 0  # p_n, m (3)
X_VEL = 3  # v_n, m/s (3)
X_ATT = 6  # C_nb row-major (9)
X_BA = 15  # accelerometer bias, m/s^2, b (3)
X_BG = 18  # gyro drift, rad/s, b (3)
X_ACC = 21  # interval integrals (decoupled_bias.ACC_*, N_ACC)
_AL = X_ACC + db.N_ACC
X_ALIGN_T0 = _AL  # time of the first IMU sample, s
X_ALIGN_N = _AL + 1  # samples averaged for the alignment
X_ALIGN_F = _AL + 2  # sum of f_b over the alignment, m/s^2 (3)
X_GAPS = _AL + 5  # IMU gaps skipped
X_STARTED = _AL + 6  # 1.0 once the first fix is applied
X_LAST_T = _AL + 7  # time of the previous IMU sample, s (NaN before any)
X_LAST_F = _AL + 8  # its specific force, m/s^2, b (3)
X_LAST_W = _AL + 11  # its angular rate, rad/s, b (3)
X_HIST = _AL + 14  # version of the engine's fix history (the Python side's key)
N_X = _AL + 15

# Ring bookkeeping ``rb``.
RB_HEAD = 0  # serial of the oldest entry
RB_COUNT = 1  # entries buffered
RB_DT = 2  # latest positive IMU period, s (NaN before two samples)
RB_REPLAYED = 3  # samples re-propagated after late fixes
N_RB = 4

# Constant settings ``prm``.
P_ALIGN_S = 0
P_MAX_GAP = 1
P_MAX_LATENCY = 2
P_CAPACITY = 3
N_PRM = 4

#: :func:`imu_run` flag: a pending fix is due at the sample just buffered (row not written).
EV_DUE = 1
#: :func:`imu_run` flag: the ring is full; nothing done for sample ``k`` (the engine grows it).
EV_FULL = 2

_ACC_T = X_ACC + db.ACC_T
_ACC_V = X_ACC + db.ACC_V.start
_ACC_D = X_ACC + db.ACC_D.start
_ACC_W = X_ACC + db.ACC_W.start
_ACC_M = X_ACC + db.ACC_M.start
_ACC_GAMMA = X_ACC + db.ACC_GAMMA.start
_ACC_G = X_ACC + db.ACC_G.start
_ACC_GD = X_ACC + db.ACC_GD.start


@numba.njit(cache=True)
def propagate(
    x: FloatArray,
    g_n: FloatArray,
    prm: FloatArray,
    t: float,
    a0: float,
    a1: float,
    a2: float,
    w0: float,
    w1: float,
    w2: float,
) -> None:
    """Advance ``x`` to ``t`` (s) with the previous sample; the new one (m/s^2, rad/s) becomes the previous.

    Before the first fix the specific force is summed for the alignment (the first
    ``align_s`` seconds, at least one sample). Afterwards the previous sample's rates and
    force are integrated over ``dt`` (mean over its interval); a gap outside
    ``(0, max_imu_gap_s]`` is counted and not integrated.
    """
    lt = x[X_LAST_T]
    lf0, lf1, lf2 = x[X_LAST_F], x[X_LAST_F + 1], x[X_LAST_F + 2]
    lw0, lw1, lw2 = x[X_LAST_W], x[X_LAST_W + 1], x[X_LAST_W + 2]
    x[X_LAST_T] = t
    x[X_LAST_F], x[X_LAST_F + 1], x[X_LAST_F + 2] = a0, a1, a2
    x[X_LAST_W], x[X_LAST_W + 1], x[X_LAST_W + 2] = w0, w1, w2
    if x[X_STARTED] == 0.0:
        if math.isnan(x[X_ALIGN_T0]):
            x[X_ALIGN_T0] = t
        if t - x[X_ALIGN_T0] < prm[P_ALIGN_S] or x[X_ALIGN_N] == 0:
            x[X_ALIGN_N] += 1
            x[X_ALIGN_F] += a0
            x[X_ALIGN_F + 1] += a1
            x[X_ALIGN_F + 2] += a2
        return
    if math.isnan(lt):
        return
    dt = t - lt
    if not 0.0 < dt <= prm[P_MAX_GAP]:
        x[X_GAPS] += 1
        return
    h = 0.5 * dt
    R = rodrigues(h * (lw0 - x[X_BG]), h * (lw1 - x[X_BG + 1]), h * (lw2 - x[X_BG + 2]))
    C = x[X_ATT : X_ATT + 9]
    Ch = np.empty(9)  # C_half = C R_half
    Rs = np.empty(9)  # R_step = R_half R_half
    for i in range(3):
        for j in range(3):
            Ch[3 * i + j] = C[3 * i] * R[j] + C[3 * i + 1] * R[3 + j] + C[3 * i + 2] * R[6 + j]
            Rs[3 * i + j] = R[3 * i] * R[j] + R[3 * i + 1] * R[3 + j] + R[3 * i + 2] * R[6 + j]
    fb0 = lf0 - x[X_BA]
    fb1 = lf1 - x[X_BA + 1]
    fb2 = lf2 - x[X_BA + 2]
    for i in range(3):
        v_old = x[X_VEL + i]
        x[X_VEL + i] += (Ch[3 * i] * fb0 + Ch[3 * i + 1] * fb1 + Ch[3 * i + 2] * fb2 + g_n[i]) * dt
        x[X_POS + i] += (v_old + x[X_VEL + i]) * (0.5 * dt)
    for i in range(3):
        for j in range(3):
            C[3 * i + j] = Ch[3 * i] * R[j] + Ch[3 * i + 1] * R[3 + j] + Ch[3 * i + 2] * R[6 + j]
    # interval integrals (decoupled_bias.accumulate, same order of operations)
    for i in range(3):
        v_old = x[_ACC_V + i]
        x[_ACC_V + i] += (Ch[3 * i] * lf0 + Ch[3 * i + 1] * lf1 + Ch[3 * i + 2] * lf2 + g_n[i]) * dt
        x[_ACC_D + i] += (v_old + x[_ACC_V + i]) * (0.5 * dt)
    for i in range(9):
        w_old = x[_ACC_W + i]
        x[_ACC_W + i] += Ch[i] * dt
        x[_ACC_M + i] += (w_old + x[_ACC_W + i]) * (0.5 * dt)
    Gm = x[_ACC_GAMMA : _ACC_GAMMA + 9].copy()
    for i in range(3):
        for j in range(3):
            x[_ACC_GAMMA + 3 * i + j] = (
                Gm[3 * i] * Rs[j] + Gm[3 * i + 1] * Rs[3 + j] + Gm[3 * i + 2] * Rs[6 + j]
            )
    G = x[_ACC_G : _ACC_G + 9].copy()
    for i in range(3):  # R_step^T G + I dt
        for j in range(3):
            x[_ACC_G + 3 * i + j] = Rs[i] * G[j] + Rs[3 + i] * G[3 + j] + Rs[6 + i] * G[6 + j]
        x[_ACC_G + 4 * i] += dt
    gd0, gd1, gd2 = x[_ACC_GD], x[_ACC_GD + 1], x[_ACC_GD + 2]
    for i in range(3):  # R_step^T Gd + d dt
        x[_ACC_GD + i] = Rs[i] * gd0 + Rs[3 + i] * gd1 + Rs[6 + i] * gd2 + x[X_BG + i] * dt
    x[_ACC_T] += dt


@numba.njit(cache=True)
def write_row(
    floats: FloatArray,
    static_out: npt.NDArray[np.bool_],
    source_out: npt.NDArray[np.int8],
    k: int,
    t: float,
    x: FloatArray,
    geo: FloatArray,
    fixed: bool,
) -> None:
    """Output row ``k`` at ``t`` (s) of the state ``x`` (``geo``: the tangent plane's constants).

    Before the first fix everything but the time is NaN (source ``none``); afterwards the NED
    position and velocity, the geodetic position (NaN without an origin), the ZYX attitude of
    the sensor frame and NaN sigmas, source ``fix`` at an epoch with a fix, else ``dr``.
    """
    floats[C_T, k] = t
    static_out[k] = False
    nan = math.nan
    if x[X_STARTED] == 0.0:
        for c in (
            C_LAT,
            C_LON,
            C_HEIGHT,
            C_NORTH,
            C_EAST,
            C_DOWN,
            C_VN,
            C_VE,
            C_VD,
            C_ROLL,
            C_PITCH,
            C_YAW,
            C_STD_NORTH,
            C_STD_EAST,
        ):
            floats[c, k] = nan
        source_out[k] = SRC_NONE
        return
    r0, r1, r2 = x[X_POS], x[X_POS + 1], x[X_POS + 2]
    floats[C_LAT, k] = geo[0] + r0 / geo[3]
    floats[C_LON, k] = geo[1] + r1 / geo[4]
    floats[C_HEIGHT, k] = geo[2] - r2
    floats[C_NORTH, k] = r0
    floats[C_EAST, k] = r1
    floats[C_DOWN, k] = r2
    floats[C_VN, k] = x[X_VEL]
    floats[C_VE, k] = x[X_VEL + 1]
    floats[C_VD, k] = x[X_VEL + 2]
    C = X_ATT
    floats[C_ROLL, k] = math.atan2(x[C + 7], x[C + 8])
    floats[C_PITCH, k] = -math.asin(max(-1.0, min(1.0, x[C + 6])))
    floats[C_YAW, k] = math.atan2(x[C + 3], x[C])
    floats[C_STD_NORTH, k] = nan
    floats[C_STD_EAST, k] = nan
    source_out[k] = SRC_FIX if fixed else SRC_DR


@numba.njit(cache=True)
def evict(r_t: FloatArray, rb: FloatArray, prm: FloatArray) -> None:
    """Drop the entries older than ``max_latency_s`` (plus half a period) or over ``capacity``."""
    count = int(rb[RB_COUNT])
    if count == 0:
        return
    size = r_t.size
    head = int(rb[RB_HEAD])
    t_now = r_t[(head + count - 1) % size]
    half = 0.5 * rb[RB_DT] if math.isfinite(rb[RB_DT]) else 0.0
    limit = t_now - prm[P_MAX_LATENCY] - half
    cap = prm[P_CAPACITY]
    while count > 1 and (count > cap or r_t[head % size] < limit):
        head += 1
        count -= 1
    rb[RB_HEAD] = head
    rb[RB_COUNT] = count


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
    x: FloatArray,
    g_n: FloatArray,
    prm: FloatArray,
    r_t: FloatArray,
    r_imu: FloatArray,
    r_snap: FloatArray,
    rb: FloatArray,
    geo: FloatArray,
    t_due: float,
) -> tuple[int, int]:
    """The absfix IMU step over samples ``i0 .. i1-1``, writing row ``k`` of the output for sample ``k``.

    ``t`` device time (s); ``ax..az`` specific force (m/s^2) and ``gx..gz`` rate (rad/s) along
    sensor x, y, z. Each sample is propagated and buffered; when ``t_due`` (the earliest
    validity of the pending fixes, s) is within half a period of it, the kernel returns
    ``(k, EV_DUE)`` with sample ``k`` buffered but its row not written and the ring not yet
    evicted (the engine applies the fixes, then writes the row and evicts). Otherwise it
    returns ``(i1, 0)``; ``(k, EV_FULL)`` before sample ``k`` when the ring has no free slot.
    """
    size = r_t.size
    for k in range(i0, i1):
        tk = t[k]
        count = int(rb[RB_COUNT])
        head = int(rb[RB_HEAD])
        if count + 1 > size:
            return k, EV_FULL
        if count > 0:
            dt = tk - r_t[(head + count - 1) % size]
            if dt > 0.0:
                rb[RB_DT] = dt
        propagate(x, g_n, prm, tk, ax[k], ay[k], az[k], gx[k], gy[k], gz[k])
        slot = (head + count) % size
        r_t[slot] = tk
        r_imu[slot, 0] = ax[k]
        r_imu[slot, 1] = ay[k]
        r_imu[slot, 2] = az[k]
        r_imu[slot, 3] = gx[k]
        r_imu[slot, 4] = gy[k]
        r_imu[slot, 5] = gz[k]
        r_snap[slot, :] = x
        rb[RB_COUNT] = count + 1
        half = 0.5 * rb[RB_DT] if math.isfinite(rb[RB_DT]) else 0.0
        if t_due <= tk + half:
            return k, EV_DUE
        write_row(floats, static_out, source_out, k, tk, x, geo, False)
        evict(r_t, rb, prm)
    return i1, 0


@numba.njit(cache=True)
def replay_run(
    x: FloatArray,
    g_n: FloatArray,
    prm: FloatArray,
    r_t: FloatArray,
    r_imu: FloatArray,
    r_snap: FloatArray,
    rb: FloatArray,
    geo: FloatArray,
    s0: int,
    s1: int,
    write: bool,
    floats: FloatArray,
    static_out: npt.NDArray[np.bool_],
    source_out: npt.NDArray[np.int8],
    row0: int,
) -> None:
    """Re-propagate the buffered entries of serials ``s0 .. s1-1``: snapshot each, write its revised row.

    Row ``row0 + s - s0`` receives entry ``s`` (source ``dr``: these entries hold no fix);
    with ``write`` False nothing is written (the engine applies a fix at the entry first).
    """
    size = r_t.size
    for s in range(s0, s1):
        slot = s % size
        propagate(
            x,
            g_n,
            prm,
            r_t[slot],
            r_imu[slot, 0],
            r_imu[slot, 1],
            r_imu[slot, 2],
            r_imu[slot, 3],
            r_imu[slot, 4],
            r_imu[slot, 5],
        )
        r_snap[slot, :] = x
        rb[RB_REPLAYED] += 1
        if write:
            write_row(floats, static_out, source_out, row0 + s - s0, r_t[slot], x, geo, False)
