"""Block 5's per-GPS-interval step, compiled: close one interval of :class:`~iotnav.techniques.mount.MountAligner`.

At every GPS epoch the aligner turns the IMU sums of the interval since the previous epoch into
one least-squares row ``[a_s x, a_s y, dv, dt, v_mean, r_mean, course, n_imu, |a_s|^2 n, v r]``
(levelled sensor-frame specific force ``a_s``, m/s^2; GPS speed change ``dv``, m/s, over ``dt``,
s; mean yaw rate ``r``, rad/s) and appends it to its buffer; with body-frame input it first
levels the interval's mean specific force against the gravity reference and refreshes that
reference from unaccelerated intervals; with matched smoothing it averages the last
``2M - 1`` rows with triangular weights. The model and its equations are in
:mod:`iotnav.techniques.mount` (Forno et al. 2020, block 5, and the ``lsq`` method designed
there); this module only moves that per-epoch arithmetic out of Python, operation for
operation (sums in the order numpy takes them for these sizes), so that the 1 Hz step costs
microseconds instead of tens of them. The buffer's evaluation (one in ``buffer_epochs``
epochs) stays in Python.
"""

from __future__ import annotations

import math

import numba
import numpy as np
import numpy.typing as npt

FloatArray = npt.NDArray[np.float64]
BoolArray = npt.NDArray[np.bool_]

#: Columns of the aligner's interval buffer (re-exported by :mod:`iotnav.techniques.mount`).
AS_X, AS_Y, DV, DT, V_MEAN, R_MEAN, COURSE, N_IMU, AS_SQ, AV_Y = range(10)
N_COLS = 10

#: Per-interval IMU sums of the aligner, one float64 array: sums of the levelled a_s x, a_s y,
#: yaw rate r, |a_s|^2, the sample count, the body-input flag, sum of f_b (3).
IMU_SX, IMU_SY, IMU_R, IMU_SQ, IMU_N, IMU_BODY, IMU_FB = range(7)
IMU_N_SUMS = IMU_FB + 3

#: Parameters of :func:`close_interval`, one float64 array (``MountConfig`` fields).
P_MAX_INTERVAL, P_MIN_SPEED, P_REF_MAX_AGE, P_REF_MAX_ACCEL, P_REF_MAX_SPREAD, P_PAPER, P_NEED_COURSE = range(
    7
)
N_PARAMS = 7

#: Status of :func:`close_interval`: the buffer is full and must be evaluated.
FULL = 1


@numba.njit(cache=True)
def levelled_xy(a0: float, a1: float, a2: float, u0: float, u1: float, u2: float) -> tuple[float, float]:
    """Horizontal components of ``a_b = (a0, a1, a2)`` in the levelled sensor frame ``s``.

    ``s`` has its z axis along the unit ``u = (u0, u1, u2)`` (down, in ``b``) and its x axis
    along the horizontal projection of the sensor x axis: ``x_s = (e_x - (e_x . u) u) / |...|``,
    ``y_s = u x x_s``, and the result is ``(x_s . a_b, y_s . a_b)`` (units of ``a_b``).
    """
    x0, x1, x2 = 1.0 - u0 * u0, -u0 * u1, -u0 * u2
    nx = math.sqrt(x0 * x0 + x1 * x1 + x2 * x2)
    x0, x1, x2 = x0 / nx, x1 / nx, x2 / nx
    y0, y1, y2 = u1 * x2 - u2 * x1, u2 * x0 - u0 * x2, u0 * x1 - u1 * x0  # u x x_s
    return x0 * a0 + x1 * a1 + x2 * a2, y0 * a0 + y1 * a1 + y2 * a2


@numba.njit(cache=True)
def _levelled_body(
    sums: FloatArray,
    ring: FloatArray,
    ring_ok: BoolArray,
    f_ref_b: FloatArray,
    k_ring: int,
    t_ref: float,
    t: float,
    speed_mps: float,
    v_prev: float,
    dt: float,
    prm: FloatArray,
) -> tuple[bool, int, float]:
    """End of an interval with body-frame input (``MountAligner._close_body``).

    Levels the interval's mean specific force against ``f_ref_b`` (m/s^2, sensor frame) into
    ``sums[0:2]`` and ``sums[3]``, records the interval in the gravity-reference ring and, when
    the ring's ``w`` intervals are unaccelerated, replaces ``f_ref_b`` (in place) by their mean.
    Returns (the interval has a levelled acceleration, ``k_ring``, ``t_ref``).
    """
    n = int(sums[IMU_N])
    f0 = f1 = f2 = math.nan
    if n > 0:
        f0 = sums[IMU_FB] / n
        f1 = sums[IMU_FB + 1] / n
        f2 = sums[IMU_FB + 2] / n
    ok = n > 0 and math.isfinite(speed_mps) and math.isfinite(v_prev) and 0.0 < dt <= prm[P_MAX_INTERVAL]
    have = False
    ref_finite = math.isfinite(f_ref_b[0]) and math.isfinite(f_ref_b[1]) and math.isfinite(f_ref_b[2])
    if ok and ref_finite and t - t_ref <= prm[P_REF_MAX_AGE]:
        d0, d1, d2 = f0 - f_ref_b[0], f1 - f_ref_b[1], f2 - f_ref_b[2]
        nrm = math.sqrt(f_ref_b[0] * f_ref_b[0] + f_ref_b[1] * f_ref_b[1] + f_ref_b[2] * f_ref_b[2])
        u0, u1, u2 = -f_ref_b[0] / nrm, -f_ref_b[1] / nrm, -f_ref_b[2] / nrm
        a0, a1 = levelled_xy(d0, d1, d2, u0, u1, u2)
        sums[IMU_SX] = a0 * n
        sums[IMU_SY] = a1 * n
        sums[IMU_SQ] = (a0 * a0 + a1 * a1) * n
        have = True
    w = ring.shape[0]
    i = k_ring % w
    if ok:
        ring[i, 0] = f0
        ring[i, 1] = f1
        ring[i, 2] = f2
        ring[i, 3] = n
        ring[i, 4] = speed_mps - v_prev
        ring[i, 5] = dt
        ring[i, 6] = 0.5 * (speed_mps + v_prev) * sums[IMU_R] / n
    ring_ok[i] = ok
    k_ring += 1
    if k_ring >= w and ring_ok.all():
        T = 0.0
        s4 = 0.0
        s65 = 0.0
        sw = 0.0
        fb0 = fb1 = fb2 = 0.0
        for j in range(w):
            T += ring[j, 5]
            s4 += ring[j, 4]
            s65 += ring[j, 6] * ring[j, 5]
            sw += ring[j, 3]
            fb0 += ring[j, 0] * ring[j, 3]
            fb1 += ring[j, 1] * ring[j, 3]
            fb2 += ring[j, 2] * ring[j, 3]
        a_long = s4 / T
        a_lat = s65 / T
        fb0, fb1, fb2 = fb0 / sw, fb1 / sw, fb2 / sw
        worst = 0.0
        for j in range(w):
            e = (ring[j, 0] - fb0) ** 2 + (ring[j, 1] - fb1) ** 2 + (ring[j, 2] - fb2) ** 2
            if e > worst or j == 0:
                worst = e
        spread = math.sqrt(worst)
        if math.hypot(a_long, a_lat) < prm[P_REF_MAX_ACCEL] and spread < prm[P_REF_MAX_SPREAD]:
            f_ref_b[0] = fb0
            f_ref_b[1] = fb1
            f_ref_b[2] = fb2
            t_ref = t
    sums[IMU_FB] = 0.0
    sums[IMU_FB + 1] = 0.0
    sums[IMU_FB + 2] = 0.0
    return have, k_ring, t_ref


@numba.njit(cache=True)
def close_interval(
    sums: FloatArray,
    ring: FloatArray,
    ring_ok: BoolArray,
    f_ref_b: FloatArray,
    sm: FloatArray,
    smooth_w: FloatArray,
    buf: FloatArray,
    prm: FloatArray,
    t: float,
    speed_mps: float,
    course_rad: float,
    course_valid: bool,
    static: bool,
    done: bool,
    t_prev: float,
    v_prev: float,
    v_start: float,
    k: int,
    k_ring: int,
    t_ref: float,
    k_sm: int,
) -> tuple[int, float, float, float, int, int, float, int]:
    """Close the GPS interval ending at ``t`` (s): ``MountAligner.add_gnss`` up to the evaluation.

    ``speed_mps`` GPS ground speed (m/s), ``course_rad`` course over ground (rad from North).
    The arrays are the aligner's (updated in place), ``prm`` its ``P_*`` parameters; the
    scalars ``t_prev .. k_sm`` its scalar state, returned updated after the status
    (:data:`FULL` when the buffer is full, else 0): ``(status, t_prev, v_prev, v_start, k,
    k_ring, t_ref, k_sm)``. On :data:`FULL` ``k`` is returned as the buffer's size; the caller
    evaluates the buffer and then sets ``k = 0``.
    """
    ok_prev = math.isfinite(v_prev)
    dt = t - t_prev
    have_acc = True
    if sums[IMU_BODY] != 0.0:
        have_acc, k_ring, t_ref = _levelled_body(
            sums, ring, ring_ok, f_ref_b, k_ring, t_ref, t, speed_mps, v_prev, dt, prm
        )
    paper = prm[P_PAPER] != 0.0
    n = int(sums[IMU_N])
    good = (
        have_acc
        and ok_prev
        and math.isfinite(speed_mps)
        and (course_valid or prm[P_NEED_COURSE] == 0.0)
        and not static
        and n > 0
        and 0.0 < dt <= prm[P_MAX_INTERVAL]
        and min(speed_mps, v_prev) >= prm[P_MIN_SPEED]
    )
    status = 0
    if good and not done:
        if k == 0:
            v_start = v_prev
        nc = buf.shape[1]
        m = smooth_w.size
        use_row = True
        if paper or m == 1:
            row = buf[k]
        else:
            for j in range(m - 1):
                for c in range(nc):
                    sm[j, c] = sm[j + 1, c]
            row = sm[m - 1]
        row[AS_X] = sums[IMU_SX] / n
        row[AS_Y] = sums[IMU_SY] / n
        row[DV] = speed_mps - v_prev
        row[DT] = dt
        row[V_MEAN] = 0.5 * (speed_mps + v_prev)
        row[R_MEAN] = sums[IMU_R] / n
        row[COURSE] = course_rad
        row[N_IMU] = n
        row[AS_SQ] = sums[IMU_SQ]
        row[AV_Y] = row[V_MEAN] * row[R_MEAN]
        if not (paper or m == 1):  # MountAligner._smooth: matched triangular smoothing
            k_sm += 1
            if k_sm < m:
                use_row = False
            else:
                sw = 0.0
                for j in range(m):
                    sw += smooth_w[j]
                out = buf[k]
                for c in range(nc):
                    acc = 0.0
                    for j in range(m):
                        acc += smooth_w[j] * sm[j, c]
                    out[c] = acc / sw
                out[COURSE] = sm[m - 1, COURSE]
                n_imu = 0.0
                for j in range(m):
                    n_imu += sm[j, N_IMU]
                out[N_IMU] = n_imu
                out[AS_SQ] = (out[AS_X] ** 2 + out[AS_Y] ** 2) * n_imu
        if use_row:
            k += 1
            if k == buf.shape[0]:
                status = FULL
    elif not good:
        k_sm = 0
        if paper:
            k = 0
    sums[IMU_SX] = 0.0
    sums[IMU_SY] = 0.0
    sums[IMU_R] = 0.0
    sums[IMU_SQ] = 0.0
    sums[IMU_N] = 0.0
    t_prev = t
    v_prev = speed_mps if math.isfinite(speed_mps) else math.nan
    return status, t_prev, v_prev, v_start, k, k_ring, t_ref, k_sm


def interval_params(
    max_interval_s: float,
    min_speed_mps: float,
    ref_max_age_s: float,
    ref_max_accel_mps2: float,
    ref_max_spread_mps2: float,
    paper: bool,
    need_course: bool,
) -> FloatArray:
    """The ``prm`` array of :func:`close_interval` from ``MountConfig`` values (s, m/s, m/s^2)."""
    p = np.zeros(N_PARAMS)
    p[P_MAX_INTERVAL] = max_interval_s
    p[P_MIN_SPEED] = min_speed_mps
    p[P_REF_MAX_AGE] = ref_max_age_s
    p[P_REF_MAX_ACCEL] = ref_max_accel_mps2
    p[P_REF_MAX_SPREAD] = ref_max_spread_mps2
    p[P_PAPER] = 1.0 if paper else 0.0
    p[P_NEED_COURSE] = 1.0 if need_course else 0.0
    return p
