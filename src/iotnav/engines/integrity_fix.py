"""The integrity guard's fix-rate step, compiled: consistency watch and dynamics bounds.

One numba kernel (:func:`fix_step`) per valid fix, for batch and streaming alike
(:class:`iotnav.engines.integrity.IntegrityGuard` calls it from ``on_fix`` and writes what it
returns into the guard vector ``st`` that the per-row kernel
:func:`iotnav.engines.integrity.guard_rows` reads), with its state in numpy arrays (STYLE.md
section 7): a fix-step vector ``fx`` (counters, sums,
the NIS window's ring position), the NIS and distance window ``win`` and the dynamics window's
queues ``buf`` / ``qh`` / ``qt`` (:data:`Q_SPACED` ... :data:`Q_SPEEDS`, each a run of rows
``qh[q] .. qt[q] - 1`` of ``buf[q]``). The model (what is compared, the bounds and their
sources) is the one of :mod:`iotnav.engines.integrity`'s module docstring; the arithmetic is
done in the same order as the Python step it replaces, so the outputs are the same bit for bit.

Units: SI throughout (s, m, m/s, m/s^2, rad/s); positions north/east about the guard's
tangent plane.
"""

from __future__ import annotations

import math

import numba
import numpy as np
import numpy.typing as npt

__all__ = ["fix_step", "new_fix_state"]

FloatArray = npt.NDArray[np.float64]
IntArray = npt.NDArray[np.int64]

# queues of the dynamics window (rows of buf[q]; columns as noted)
Q_SPACED = 0  # fixes at least dynamics_min_dt_s apart: t, vn, ve
Q_PAIRS = 1  # pairs of spaced fixes: t0, |dv|/dt
Q_RATE_A = 2  # largest |dv|/dt of the pairs: t0, value (decreasing values)
Q_RATE_S = 3  # largest |ds|/dt
Q_RATE_W = 4  # largest |dpsi|/dt
Q_SPEEDS = 5  # t, speed (decreasing speeds: the window's top speed first)
N_QUEUES = 6

# fix-step vector fx
(
    FX_SUM_SQ,  # sum of the pairs' (|dv|/dt)^2
    FX_CONSECUTIVE,  # fixes in a row beyond the per-fix bound
    FX_SINCE_REINIT,  # fixes checked since the last re-initialisation
    FX_CHECKED,  # fixes checked in all
    FX_NIS_N,  # NIS (and distances) in the window
    FX_NIS_HEAD,  # index of the oldest of them in win
    FX_SIZE,
) = range(7)

# configuration vector cfg
(
    CF_NIS_WINDOW,
    CF_MIN_REINIT_DISTANCE,
    CF_REINIT_HOLDOFF,
    CF_WINDOW_BOUND,
    CF_FIX_BOUND,
    CF_MAX_CONSECUTIVE,
    CF_DYN_WINDOW,
    CF_DYN_MIN_DT,
    CF_MIN_COURSE_SPEED,
    CF_MARGIN,
    CF_ACCEL_FLOOR,
    CF_YAW_RATE_FLOOR,
    CF_OUTAGE_AFTER,
    CF_SIZE,
) = range(14)

# what fix_step returns
RESULT_NONE, RESULT_WINDOWED_NIS, RESULT_CONSECUTIVE = range(3)
# the figures it writes into ``fig`` (the event's)
FIG_WIN, FIG_DIST, FIG_MEAN_DIST, FIG_N, FIG_CONSECUTIVE, FIG_PROBATION_PASSED, FIG_SIZE = range(7)

# the vector ``last`` (the guard's view of the engine's last judged row, and its frame)
L_LAT0, L_LON0, L_KN, L_KE = 9, 10, 11, 12

#: Rows of each queue at first; grown (doubled) by :func:`ensure_room` when one fills.
INITIAL_CAPACITY = 128


def new_fix_state(nis_window: int) -> tuple[FloatArray, FloatArray, FloatArray, IntArray, IntArray]:
    """Fresh fix-step state: ``fx``, ``win`` (2 x ``nis_window``), ``buf``, ``qh``, ``qt``."""
    fx = np.zeros(FX_SIZE)
    win = np.zeros((2, nis_window))
    buf = np.zeros((N_QUEUES, INITIAL_CAPACITY, 3))
    return fx, win, buf, np.zeros(N_QUEUES, np.int64), np.zeros(N_QUEUES, np.int64)


def ensure_room(buf: FloatArray, qh: IntArray, qt: IntArray) -> FloatArray:
    """``buf`` with room for one more row in every queue (compacted, or doubled); in place if it can."""
    cap = buf.shape[1]
    if int(np.max(qt)) < cap:
        return buf
    if int(np.max(qt - qh)) < cap // 2:
        new = buf
    else:
        new = np.zeros((buf.shape[0], 2 * cap, buf.shape[2]))
    for q in range(buf.shape[0]):
        n = int(qt[q] - qh[q])
        new[q, :n] = buf[q, qh[q] : qt[q]]
        qh[q], qt[q] = 0, n
    return new


@numba.njit(cache=True)
def wrap_pi(a: float) -> float:  # pragma: no cover (compiled)
    """Angle wrapped to ``[-pi, pi)``, rad (the guard's course differences, here and in
    :func:`iotnav.engines.integrity.guard_rows`)."""
    return (a + math.pi) % (2.0 * math.pi) - math.pi


@numba.njit(cache=True)
def _push_max(
    buf: FloatArray, qh: IntArray, qt: IntArray, q: int, t: float, x: float
) -> None:  # pragma: no cover
    """Append ``(t, x)`` to the decreasing queue ``q``, dropping the entries it dominates."""
    while qt[q] > qh[q] and buf[q, qt[q] - 1, 1] <= x:
        qt[q] -= 1
    buf[q, qt[q], 0] = t
    buf[q, qt[q], 1] = x
    qt[q] += 1


@numba.njit(cache=True)
def _expire(buf: FloatArray, qh: IntArray, qt: IntArray, q: int, t_old: float) -> None:  # pragma: no cover
    """Drop the entries of queue ``q`` older than ``t_old``."""
    while qt[q] > qh[q] and buf[q, qh[q], 0] < t_old:
        qh[q] += 1


@numba.njit(cache=True)
def _check(
    cfg: FloatArray,
    fx: FloatArray,
    win: FloatArray,
    t: float,
    n_f: float,
    e_f: float,
    sigma: float,
    fig: FloatArray,
    last: FloatArray,
) -> int:  # pragma: no cover (compiled)
    """The consistency watch at one fix (``last``: the engine's last judged row, see :func:`fix_step`)."""
    l_t, l_vn, l_ve, std_n, std_e, t_reinit, probation = (
        last[0],
        last[3],
        last[4],
        last[5],
        last[6],
        last[7],
        last[8],
    )
    if not math.isfinite(std_n + std_e):
        return RESULT_NONE
    n_e = (last[1] - last[L_LAT0]) * last[L_KN]
    e_e = (last[2] - last[L_LON0]) * last[L_KE]
    dt = t - l_t
    if math.isfinite(l_vn + l_ve) and abs(dt) < 1.0:
        n_e, e_e = n_e + l_vn * dt, e_e + l_ve * dt
    d0, d1 = n_f - n_e, e_f - e_e
    s_n = std_n**2 + sigma**2
    s_e = std_e**2 + sigma**2
    nis = d0**2 / s_n + d1**2 / s_e
    fx[FX_CHECKED] += 1.0
    fx[FX_SINCE_REINIT] += 1.0
    w = int(cfg[CF_NIS_WINDOW])
    n = int(fx[FX_NIS_N])
    head = int(fx[FX_NIS_HEAD])
    if n < w:
        slot = (head + n) % w
        n += 1
    else:
        slot = head
        head = (head + 1) % w
    dist = math.hypot(d0, d1)
    win[0, slot] = nis
    win[1, slot] = dist
    fx[FX_NIS_N] = n
    fx[FX_NIS_HEAD] = head
    fx[FX_CONSECUTIVE] = fx[FX_CONSECUTIVE] + 1.0 if nis > cfg[CF_FIX_BOUND] else 0.0
    if fx[FX_SINCE_REINIT] < cfg[CF_NIS_WINDOW]:
        return RESULT_NONE
    total = 0.0  # oldest first, as the sum over the window's deque did
    dsum = 0.0
    for i in range(n):
        j = (head + i) % w
        total += win[0, j]
        dsum += win[1, j]
    far = dsum / n > cfg[CF_MIN_REINIT_DISTANCE]
    if probation != 0.0 and not (far and total > cfg[CF_WINDOW_BOUND]):
        fig[FIG_PROBATION_PASSED] = 1.0
    if t - t_reinit < cfg[CF_REINIT_HOLDOFF] or not far:
        return RESULT_NONE
    result = RESULT_NONE
    if n == w and total > cfg[CF_WINDOW_BOUND]:
        result = RESULT_WINDOWED_NIS
    elif fx[FX_CONSECUTIVE] >= cfg[CF_MAX_CONSECUTIVE]:
        result = RESULT_CONSECUTIVE
    if result != RESULT_NONE:
        fig[FIG_WIN] = total
        fig[FIG_DIST] = dist
        fig[FIG_MEAN_DIST] = dsum / n
        fig[FIG_N] = n
        fig[FIG_CONSECUTIVE] = fx[FX_CONSECUTIVE]
    return result


@numba.njit(cache=True)
def _dynamics(
    cfg: FloatArray,
    fx: FloatArray,
    buf: FloatArray,
    qh: IntArray,
    qt: IntArray,
    t: float,
    vn: float,
    ve: float,
    bounds: FloatArray,
) -> float:  # pragma: no cover (compiled)
    """Dynamics bounds after a fix into ``bounds`` (speed rate, velocity rate, course rate, accel
    RMS); returns the window's top speed (rates between fixes at least ``dynamics_min_dt_s``
    apart, kept incrementally; the top speed that of every fix of the window)."""
    t_old = t - cfg[CF_DYN_WINDOW]
    sp = math.hypot(vn, ve)
    _push_max(buf, qh, qt, Q_SPEEDS, t, sp)
    _expire(buf, qh, qt, Q_SPEEDS, t_old)
    s = Q_SPACED
    n_sp = qt[s] - qh[s]
    if n_sp == 0 or t - buf[s, qt[s] - 1, 0] >= cfg[CF_DYN_MIN_DT]:
        if n_sp > 0:
            f0t, f0n, f0e = buf[s, qt[s] - 1, 0], buf[s, qt[s] - 1, 1], buf[s, qt[s] - 1, 2]
            dt = t - f0t
            s0 = math.hypot(f0n, f0e)
            w = 0.0
            if min(s0, sp) > cfg[CF_MIN_COURSE_SPEED]:
                w = abs(wrap_pi(math.atan2(ve, vn) - math.atan2(f0e, f0n))) / dt
            a = math.hypot(vn - f0n, ve - f0e) / dt
            p = Q_PAIRS
            buf[p, qt[p], 0] = f0t
            buf[p, qt[p], 1] = a
            qt[p] += 1
            fx[FX_SUM_SQ] += a * a
            _push_max(buf, qh, qt, Q_RATE_A, f0t, a)
            _push_max(buf, qh, qt, Q_RATE_S, f0t, abs(sp - s0) / dt)
            _push_max(buf, qh, qt, Q_RATE_W, f0t, w)
        buf[s, qt[s], 0] = t
        buf[s, qt[s], 1] = vn
        buf[s, qt[s], 2] = ve
        qt[s] += 1
    _expire(buf, qh, qt, Q_SPACED, t_old)
    p = Q_PAIRS
    while qt[p] > qh[p] and buf[p, qh[p], 0] < t_old:
        fx[FX_SUM_SQ] -= buf[p, qh[p], 1] ** 2
        qh[p] += 1
    for q in (Q_RATE_A, Q_RATE_S, Q_RATE_W):
        _expire(buf, qh, qt, q, t_old)
    n_pairs = qt[p] - qh[p]
    if n_pairs == 0:
        fx[FX_SUM_SQ] = 0.0
    a_h = buf[Q_RATE_A, qh[Q_RATE_A], 1] if qt[Q_RATE_A] > qh[Q_RATE_A] else 0.0
    a_s = buf[Q_RATE_S, qh[Q_RATE_S], 1] if qt[Q_RATE_S] > qh[Q_RATE_S] else 0.0
    w_max = buf[Q_RATE_W, qh[Q_RATE_W], 1] if qt[Q_RATE_W] > qh[Q_RATE_W] else 0.0
    m = cfg[CF_MARGIN]
    rms = math.sqrt(max(fx[FX_SUM_SQ], 0.0) / n_pairs) if n_pairs > 0 else 0.0
    bounds[0] = max(m * a_s, cfg[CF_ACCEL_FLOOR])
    bounds[1] = max(m * a_h, cfg[CF_ACCEL_FLOOR])
    bounds[2] = max(m * w_max, cfg[CF_YAW_RATE_FLOOR])
    bounds[3] = max(rms, cfg[CF_ACCEL_FLOOR])
    return buf[Q_SPEEDS, qh[Q_SPEEDS], 1]


@numba.njit(cache=True)
def fix_step(
    cfg: FloatArray,
    fx: FloatArray,
    win: FloatArray,
    buf: FloatArray,
    qh: IntArray,
    qt: IntArray,
    fixv: FloatArray,
    last: FloatArray,
    check: bool,
    fig: FloatArray,
    bounds: FloatArray,
) -> tuple[int, float]:  # pragma: no cover (compiled)
    """One valid fix through the guard's fix-rate part (before the fix becomes the guard's last).

    Parameters
    ----------
    cfg, fx, win, buf, qh, qt : ndarray
        The guard's fix-step state (module docstring); ``buf`` has room for one more row per queue.
    fixv : ndarray
        The fix: t (s), north, east (m, guard frame), vn, ve (m/s), per-axis sigma (m).
    last : ndarray
        The engine's last judged row: t (s), lat, lon (degrees), vn, ve (m/s), std_n, std_e (m),
        the time of the last re-initialisation (s), the probation flag, and the guard frame's
        lat0, lon0 (degrees), k_n, k_e (m/degree).
    check : bool
        Run the consistency watch (a usable last row, and the fix does not end an outage).
    fig, bounds : ndarray
        Out: the event's figures (``FIG_*``); the dynamics bounds.

    Returns
    -------
    result, speed_max : int, float
        ``RESULT_*`` (a re-initialisation request and why); the window's top speed, m/s.
    """
    fig[FIG_PROBATION_PASSED] = 0.0
    result = RESULT_NONE
    if check:
        result = _check(cfg, fx, win, fixv[0], fixv[1], fixv[2], fixv[5], fig, last)
    speed_max = _dynamics(cfg, fx, buf, qh, qt, fixv[0], fixv[3], fixv[4], bounds)
    return result, speed_max
