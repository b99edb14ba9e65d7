"""Do no harm (issue 16): one integrity guard around every position engine.

:class:`IntegrityEngine` wraps any engine (``make_engine`` applies it by default) and has the
same ``step()``; batch (:func:`iotnav.engines.base.run_batch`), streaming and later the live
service and the firmware get it the same way. It watches the engine against the fixes and
against the vehicle's own recent motion, and never reports a solution that either disagrees
with them beyond chance. The guard itself is a small pure state machine
(:class:`IntegrityGuard`), no I/O: its fix-rate part one compiled kernel
(:func:`iotnav.engines.integrity_fix.fix_step`), its per-row part another
(:func:`guard_rows`) that ``step()`` runs on a one-row block and the batch path on the
engine's own compiled output blocks (an engine with ``imu_block`` keeps it: the guard's
decisions within a block are made on its rows, and when one asks for a re-initialisation the
rest of the block is run again by the fresh engine), so batch and streaming give the same rows.

Consistency watch (fixes present)
    At each valid fix the engine's latest output (moved to the fix time with its own velocity)
    is compared with the fix: innovation ``d = p_fix - p_eng`` (north, east), covariance
    ``S = diag(std_eng^2 + sigma_fix^2)`` with ``sigma_fix = max(h_acc / sqrt(2),
    min_sigma_m)`` per axis, ``NIS = d^T S^-1 d`` (chi-square, 2 degrees of freedom, for a
    consistent engine). The engine is *re-initialised* -- replaced by a fresh one from the same
    builder, which starts over from the next samples -- when

    * the sum of the last ``nis_window`` NIS exceeds the chi-square bound with ``2 nis_window``
      degrees of freedom at ``nis_probability`` (windowed NIS: the two disagree beyond chance),
      or
    * ``max_consecutive`` fixes in a row each exceed the 2-dof bound at ``fix_probability``
      (an engine that rejects fixes -- or ignores them -- drifts away from them and never
      comes back), or
    * its output is not finite;

    and (for the first two) its mean distance to the fixes of the window exceeds
    ``min_reinit_distance_m``. The fix that ends an outage is not a sample of this watch (it
    measures the outage's drift, which the outage guard judges).

    An engine that can re-initialise itself (``request_reinitialise(reason)``: eskf restarts
    in motion from the next fix, keeping what it knows of the sensor, and escalates to a new
    mount on its own) is asked to first (``how: engine_reset``); it is replaced by a fresh one
    (``fresh_engine``) when it was asked last time and has not agreed with the fixes since (its
    probation, below). On drive_0708 started at 220 s with 1 deg/s of gyro bias and its 30 s
    outages masked, the fresh engine was 144.8 m off at worst where eskf's own reset stays
    within 7.0 m (``tests/test_eskf_nis.py``).

    Each re-initialisation is an event ``reinitialised`` (``reason``, ``how``, the figures, the fix
    count) in ``events``; at most one per ``reinit_holdoff_s``, and not before the fresh engine
    has a position and ``nis_window`` fixes of its own. So fixes are never rejected forever.

    *Probation*: a fresh engine's rows are not reported until it has agreed with
    ``nis_window`` fixes (windowed NIS within its bound, or mean distance within
    ``min_reinit_distance_m``; event ``integrity_probation_passed``); meanwhile the output is
    the dr-velocity solution below (with fixes present: the latest fix moved on by at most one
    fix interval). An engine started in motion may need a while or never settle (a fresh eskf
    started mid-drive on drive_0708 went 1,300 km off while claiming metres); what is reported
    is then never worse than the fixes.

Outage guard (no fix for ``outage_after_s``)
    ``tau`` is the time since the last fix ``(t_f, p_f, v_f)``; the *dr-velocity* solution is
    ``p_dr = p_f + v_f tau``, the last fix moved on at its own reported velocity. What the
    vehicle did before the outage is summarised from the fixes of the last
    ``dynamics_window_s``: the largest rate of change of speed ``a_s``, of the horizontal
    velocity vector ``a_h`` and of the course ``w`` seen between fixes, each times
    ``dynamics_margin`` and at least its floor. The engine's output is kept while

    * its speed is within ``|s_f| +- (a_s tau + 3 sigma_s)``,
    * its course is within ``w tau + 3 sigma_course`` of the fix's (when both move faster than
      ``min_course_speed_mps``),
    * its position is within ``0.5 a_h tau^2 + 3 sigma_dr`` of ``p_dr``, and within
      ``dynamics_margin s_max tau + 3 sigma_f`` of the last fix, ``s_max`` the highest speed
      of the fixes of the last ``dynamics_window_s`` (the vehicle cannot have gone farther
      than its recent top speed, with the margin, allows);

    otherwise the output switches to ``p_dr`` for the rest of the outage (``source``
    ``dr_velocity``, an event ``integrity_fallback`` with the check that failed), with the
    honest 1-sigma per axis ``sqrt(sigma_f^2 + tau^2 sigma_v^2 + (a_rms tau^2 / 2)^2)``:
    the fix's error, its velocity error carried forward, and the unknown acceleration (the RMS
    of what the vehicle did before the outage, at least ``accel_floor_mps2``). The fixes'
    ``s_acc_mps`` gives ``sigma_v`` (``default_speed_acc_mps`` when absent).

    Before the engine has a position (a fresh engine after a re-initialisation, or a cold
    start), and when its output is not finite, the output is the dr-velocity solution too.

Honest sigma of a kept row (designed here)
    A row kept through an outage reports the engine's position, but its claimed horizontal
    1-sigma is raised (per axis, ``std_north`` and ``std_east``) to what the guard can justify:

    * *a claim that does not grow*: when ``hypot(std_n, std_e)`` is no larger than it was at
      the last row before the outage, the engine is not propagating a covariance (it
      extrapolates with a fixed figure, as eskf before its heading did until it claimed the
      growing sigma of that solution itself: :mod:`iotnav.engines.eskf`, "Initialisation"),
      and the floor is the dr-velocity sigma above;
    * *a departure from the dr-velocity solution*: an engine ``d`` metres from ``p_dr`` claims
      that the last fix moved on at its velocity is wrong by ``d``; nothing in an outage tells
      the guard which of the two is right, so the reported uncertainty covers the case that
      ``p_dr`` is: the floor is ``d / sqrt(2)`` per axis (``hypot(std_n, std_e) >= d``).

    The fix check above compares the engine's own claim (before this floor). Rows raised are
    counted (``sigma_raised_rows`` in the summary). Measured (``benchmarks/bench_cases.py``,
    guarded engines, windows worse than hold whose claimed sigma does not cover the error,
    before this rule -> with it; ``benchmarks/results/cases.md`` says which commit measured
    each row): pdr on walk_0827 1/2 -> 0/2 (30 s), pipeline and qekf on drive_0708 started in
    motion at 100 s with 1 deg/s of gyro bias 1/6 -> 0/6 each (30 s); eskf on the Husky 1/6
    -> 0/6 (15 s) and on walk_0827 2/2 -> 0/2 (15 and 30 s), which eskf's own claim now
    covers without the guard. Positions are not changed by this rule.

Defaults and their sources
    * ``accel_floor_mps2`` 0.5 m/s^2: median horizontal acceleration of the real drive
      (drive_0708 RTK: 0.58 m/s^2) and walk (walk_0827: 0.47 m/s^2) over 1 s; the Husky's is
      0.26.
    * ``yaw_rate_floor_rad_s`` 0.1 rad/s and ``dynamics_margin`` 1.5: the 99th percentiles
      of |d speed / dt| and of the course rate are 1.4 times their 95th on the drive (2.2 vs
      1.5 m/s^2; 0.52 vs 0.45 rad/s above 2 m/s), on the walk 1.6 / 1.3 and on the Husky 1.4 /
      2.0 (``benchmarks/bench_cases.py`` inputs; measured once on the RTK truths and fixes).
    * chi-square probabilities 0.999 (windowed) and 0.9999 (per fix): a consistent engine
      re-initialises about once in 1000 windows, once in 10^4 fixes for the run of 5.
    * ``min_sigma_m`` 0.3 m: below the scatter of a standing tracker's fixes (Husky at rest
      0.30 m N), so that a centimetre ``h_acc`` (RTK) does not make metre-level engines
      "inconsistent".
    * ``min_reinit_distance_m`` 10 m: a tracker fix's 2-D 95 % radius is about 2.45 x 2.1 m
      = 5 m per fix (``default_h_acc_m``); an engine within 10 m of the fixes on average is
      within what they can tell, and re-initialising it costs its warm-up for nothing. Without
      it the guard re-initialised drive_0708's eskf six times (it sits 1 m from RTK fixes that
      claim 1.4 cm while reporting 1 cm itself: a windowed NIS of 48 against a bound of 45).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import asdict
from typing import Any

import numba
import numpy as np
import numpy.typing as npt

from iotnav.engines import integrity_fix as fx_kernel
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
    Engine,
    FloatArray,
    GnssSample,
    ImuSample,
    Output,
    OutputBlock,
    Sample,
    TangentPlane,
    output_without_position,
)
from iotnav.engines.integrity_config import IntegrityConfig
from iotnav.engines.integrity_fix import wrap_pi
from iotnav.kalman import gate_threshold

__all__ = ["DR_VELOCITY_SOURCE", "IntegrityConfig", "IntegrityEngine", "IntegrityGuard"]

#: ``source`` of the rows where the guard reports the last fix moved on at its velocity.
DR_VELOCITY_SOURCE = "dr_velocity"


def fix_velocity(s: GnssSample) -> np.ndarray:
    """North and East velocity a fix reports (m/s): ``vn``/``ve``, else speed and course, else 0."""
    if math.isfinite(s.vn) and math.isfinite(s.ve):
        return np.array([s.vn, s.ve])
    if s.course_valid and math.isfinite(s.speed_mps) and math.isfinite(s.course_rad):
        return np.array([s.speed_mps * math.cos(s.course_rad), s.speed_mps * math.sin(s.course_rad)])
    return np.zeros(2)


# --------------------------------------------------------------------------- per-row kernel

#: Reasons a row is replaced (the kernel's codes; 0 keeps the engine's row).
REASONS: tuple[str, ...] = (
    "",
    "no_position",
    "nonfinite",
    "speed",
    "course",
    "position",
    "reach",
    "probation",
)
_R_NO_POSITION, _R_NONFINITE, _R_SPEED, _R_COURSE, _R_POSITION, _R_REACH, _R_PROBATION = range(1, 8)

# guard state array ``st`` (one float64 vector, shared by the two compiled steps, on_fix and guard_rows)
(
    S_HAVE_FIX,  # 1 once a fix is known
    S_FIX_T,  # last fix: time (s)
    S_FIX_N,  # NED position (m) about the guard's frame
    S_FIX_E,
    S_FIX_D,
    S_FIX_VN,  # north, east velocity (m/s)
    S_FIX_VE,
    S_FIX_SIG,  # per-axis position 1-sigma (m)
    S_FIX_SIGV,  # speed 1-sigma (m/s)
    S_A_S,  # dynamics bounds: speed rate, velocity rate (m/s^2), course rate (rad/s), accel RMS (m/s^2)
    S_A_H,
    S_W,
    S_A_RMS,
    S_SPEED_MAX,  # highest fix speed of the dynamics window (m/s)
    S_HAVE_FRAME,  # 1 once the guard's frame exists
    S_LAT0,  # frame constants (TangentPlane.constants)
    S_LON0,
    S_H0,
    S_KN,
    S_KE,
    S_LATCH,  # reason code of this outage's fallback (0: none yet)
    S_ROLL,  # last finite attitude (rad)
    S_PITCH,
    S_YAW,
    S_T_REINIT,  # time of the last re-initialisation (s)
    S_EVENT_T_FIX,  # fix time of the last integrity_fallback event (s)
    S_LAST_OK,  # 1 when the engine's last judged row (below) is usable by the fix check
    S_LAST_T,
    S_LAST_LAT,
    S_LAST_LON,
    S_LAST_H,
    S_LAST_VN,
    S_LAST_VE,
    S_LAST_STD_N,
    S_LAST_STD_E,
    S_ENGINE_ROWS,
    S_FALLBACK_ROWS,
    S_PROBATION,  # 1 while a fresh engine has not yet shown it agrees with the fixes
    S_SIG0,  # the engine's claimed horizontal sigma hypot(std_n, std_e) at the outage's start (m)
    S_INFLATED_ROWS,  # kept outage rows whose reported sigma the guard raised
    S_SIZE,
) = range(41)

#: ``last`` of :func:`iotnav.engines.integrity_fix.fix_step`: the engine's last judged row and the frame
_LAST_IDX = np.array(
    [
        S_LAST_T,
        S_LAST_LAT,
        S_LAST_LON,
        S_LAST_VN,
        S_LAST_VE,
        S_LAST_STD_N,
        S_LAST_STD_E,
        S_T_REINIT,
        S_PROBATION,
        S_LAT0,
        S_LON0,
        S_KN,
        S_KE,
    ]
)

# kernel parameters ``prm``
P_OUTAGE_AFTER, P_MIN_COURSE_SPEED, P_MARGIN, P_HOLDOFF, P_SIZE = range(5)

# what stopped the kernel before the block's end
FLAG_DONE, FLAG_NEED_FRAME, FLAG_EVENT, FLAG_REINIT = range(4)


@numba.njit(cache=True)
def _judge(st: FloatArray, prm: FloatArray, row: FloatArray) -> int:  # pragma: no cover (compiled)
    """Reason code (``REASONS``) why a row with a position is replaced during an outage, 0 to keep it."""
    tau = row[C_T] - st[S_FIX_T]
    if tau <= prm[P_OUTAGE_AFTER]:
        st[S_LATCH] = 0.0
        return 0
    if st[S_LATCH] != 0.0:
        return int(st[S_LATCH])
    vn, ve = row[C_VN], row[C_VE]
    if not math.isfinite(vn + ve):
        vn, ve = 0.0, 0.0
    fvn, fve = st[S_FIX_VN], st[S_FIX_VE]
    s_e, s_f = math.hypot(vn, ve), math.hypot(fvn, fve)
    sig, sig_v = st[S_FIX_SIG], st[S_FIX_SIGV]
    reason = 0
    if abs(s_e - s_f) > st[S_A_S] * tau + 3.0 * sig_v:
        reason = _R_SPEED
    elif min(s_e, s_f) > prm[P_MIN_COURSE_SPEED]:
        dpsi = abs(wrap_pi(math.atan2(ve, vn) - math.atan2(fve, fvn)))
        if dpsi > st[S_W] * tau + 3.0 * sig_v / s_f:
            reason = _R_COURSE
    if reason == 0:
        n = (row[C_LAT] - st[S_LAT0]) * st[S_KN]
        e = (row[C_LON] - st[S_LON0]) * st[S_KE]
        dev = math.hypot(n - (st[S_FIX_N] + fvn * tau), e - (st[S_FIX_E] + fve * tau))
        sig_tau = math.sqrt(sig * sig + (tau * sig_v) ** 2)
        reach = math.hypot(n - st[S_FIX_N], e - st[S_FIX_E])
        if dev > 0.5 * st[S_A_H] * tau * tau + 3.0 * sig_tau:
            reason = _R_POSITION
        elif reach > st[S_SPEED_MAX] * prm[P_MARGIN] * tau + 3.0 * sig:
            reason = _R_REACH
    st[S_LATCH] = reason
    return reason


@numba.njit(cache=True)
def _dr_sigma(st: FloatArray, tau: float) -> float:  # pragma: no cover (compiled)
    """Per-axis 1-sigma of the dr-velocity solution ``tau`` s after the last fix, m (module docstring)."""
    return math.sqrt(st[S_FIX_SIG] ** 2 + (tau * st[S_FIX_SIGV]) ** 2 + (0.5 * st[S_A_RMS] * tau * tau) ** 2)


@numba.njit(cache=True)
def _honest_sigma(st: FloatArray, prm: FloatArray, row: FloatArray) -> bool:  # pragma: no cover (compiled)
    """Raise a kept row's claimed sigma through an outage where it is not justified (module docstring).

    Returns True when the row's ``std_north``/``std_east`` were raised.
    """
    tau = row[C_T] - st[S_FIX_T]
    sig_e = math.hypot(row[C_STD_NORTH], row[C_STD_EAST])
    if tau <= prm[P_OUTAGE_AFTER]:
        st[S_SIG0] = sig_e  # the claim at the outage's start, for the growth test
        return False
    floor = 0.0
    if not sig_e > st[S_SIG0]:  # no covariance propagated through the outage: not dead reckoning
        floor = _dr_sigma(st, tau)
    # departing from the dr-velocity solution by d claims that it is wrong by d: the reported
    # uncertainty covers the case that it is right (hypot of the two sigmas >= d)
    n = (row[C_LAT] - st[S_LAT0]) * st[S_KN]
    e = (row[C_LON] - st[S_LON0]) * st[S_KE]
    d = math.hypot(n - (st[S_FIX_N] + st[S_FIX_VN] * tau), e - (st[S_FIX_E] + st[S_FIX_VE] * tau))
    floor = max(floor, d / math.sqrt(2.0))
    raised = False
    for c in (C_STD_NORTH, C_STD_EAST):
        if not row[c] >= floor:
            row[c] = floor
            raised = True
    return raised


@numba.njit(cache=True)
def guard_rows(
    floats: FloatArray,
    source: npt.NDArray[np.int8],
    i0: int,
    i1: int,
    st: FloatArray,
    prm: FloatArray,
    code_dr: int,
) -> tuple[int, int, int]:  # pragma: no cover (compiled)
    """The guard over engine output rows ``i0 .. i1-1`` of an :class:`OutputBlock`, in place.

    Each row (columns :data:`iotnav.engines.base.FLOAT_COLUMNS`; ``source`` 0 is ``none``) is
    judged (module docstring): a kept row gets the last finite attitude where its own is NaN
    and its north/east/down about the guard's frame; a replaced row becomes the dr-velocity
    solution (``source`` ``code_dr``). The same code runs for a streamed row (a one-row block)
    and a batch block.

    Returns
    -------
    k, flag, reason : int
        ``flag`` :data:`FLAG_DONE` (``k == i1``); :data:`FLAG_NEED_FRAME` (row ``k`` has a
        position but the guard has no frame yet: make it, call again from ``k``);
        :data:`FLAG_EVENT` (row ``k - 1`` started a fallback for ``reason``: record it, call
        again from ``k``); :data:`FLAG_REINIT` (row ``k - 1``'s output was not finite:
        re-initialise the engine, whose rows from ``k`` on are to be computed again).
    """
    for k in range(i0, i1):
        row = floats[:, k]
        has_pos = source[k] != 0 and math.isfinite(row[C_LAT] + row[C_LON])
        if st[S_HAVE_FRAME] == 0.0 and has_pos:
            return k, FLAG_NEED_FRAME, 0
        if source[k] == 0:
            reason = _R_NO_POSITION
        elif not has_pos:
            reason = _R_NONFINITE
        elif st[S_HAVE_FIX] == 0.0:
            reason = 0
        elif st[S_PROBATION] != 0.0:
            reason = _R_PROBATION
        else:
            reason = _judge(st, prm, row)
        # a fresh engine may not know its attitude yet: the last one known is reported meanwhile
        for c, s in ((C_ROLL, S_ROLL), (C_PITCH, S_PITCH), (C_YAW, S_YAW)):
            if math.isfinite(row[c]):
                st[s] = row[c]
        if reason == 0 or reason > _R_NONFINITE:  # the fix check compares the engine itself
            st[S_LAST_OK] = 1.0
            st[S_LAST_T], st[S_LAST_LAT], st[S_LAST_LON] = row[C_T], row[C_LAT], row[C_LON]
            st[S_LAST_H], st[S_LAST_VN], st[S_LAST_VE] = row[C_HEIGHT], row[C_VN], row[C_VE]
            st[S_LAST_STD_N], st[S_LAST_STD_E] = row[C_STD_NORTH], row[C_STD_EAST]
        if reason == 0:
            st[S_ENGINE_ROWS] += 1.0
            if st[S_HAVE_FIX] != 0.0 and st[S_HAVE_FRAME] != 0.0 and _honest_sigma(st, prm, row):
                st[S_INFLATED_ROWS] += 1.0
            row[C_ROLL], row[C_PITCH], row[C_YAW] = st[S_ROLL], st[S_PITCH], st[S_YAW]
            if st[S_HAVE_FRAME] != 0.0:
                h = row[C_HEIGHT] if math.isfinite(row[C_HEIGHT]) else st[S_H0]
                row[C_NORTH] = (row[C_LAT] - st[S_LAT0]) * st[S_KN]
                row[C_EAST] = (row[C_LON] - st[S_LON0]) * st[S_KE]
                row[C_DOWN] = st[S_H0] - h
            continue
        reinit = (
            reason == _R_NONFINITE and st[S_HAVE_FIX] != 0.0 and row[C_T] - st[S_T_REINIT] >= prm[P_HOLDOFF]
        )
        if st[S_HAVE_FIX] == 0.0 or st[S_HAVE_FRAME] == 0.0:
            if reinit:  # pragma: no cover (reinit needs a fix)
                return k + 1, FLAG_REINIT, reason
            continue  # nothing better known (no fix yet): the engine's row as it is
        st[S_FALLBACK_ROWS] += 1.0
        tau = max(row[C_T] - st[S_FIX_T], 0.0)
        fvn, fve = st[S_FIX_VN], st[S_FIX_VE]
        n, e, d = st[S_FIX_N] + fvn * tau, st[S_FIX_E] + fve * tau, st[S_FIX_D]
        sig = _dr_sigma(st, tau)
        row[C_LAT] = st[S_LAT0] + n / st[S_KN]
        row[C_LON] = st[S_LON0] + e / st[S_KE]
        row[C_HEIGHT] = st[S_H0] - d
        row[C_NORTH], row[C_EAST], row[C_DOWN] = n, e, d
        row[C_VN], row[C_VE], row[C_VD] = fvn, fve, 0.0
        row[C_ROLL], row[C_PITCH], row[C_YAW] = st[S_ROLL], st[S_PITCH], st[S_YAW]
        row[C_STD_NORTH], row[C_STD_EAST] = sig, sig
        source[k] = code_dr
        if reinit:
            return k + 1, FLAG_REINIT, reason
        if _R_NONFINITE < reason < _R_PROBATION and st[S_EVENT_T_FIX] != st[S_FIX_T]:
            st[S_EVENT_T_FIX] = st[S_FIX_T]
            return k + 1, FLAG_EVENT, reason
    return i1, FLAG_DONE, 0


# --------------------------------------------------------------------------- fix-rate guard


class IntegrityGuard:
    """The guard's state machine (pure: samples and engine outputs in, decisions out).

    The fix-rate part (:meth:`on_fix`: consistency watch, dynamics bounds) is the compiled
    :func:`iotnav.engines.integrity_fix.fix_step`, the per-row part the compiled
    :func:`guard_rows`. Both share the state vector :attr:`st`.

    Parameters
    ----------
    config : IntegrityConfig, optional
        Tunables.
    """

    def __init__(self, config: IntegrityConfig | None = None) -> None:
        c = self.config = config or IntegrityConfig()
        self.window_bound = gate_threshold(2 * c.nis_window, c.nis_probability)
        self.fix_bound = gate_threshold(2, c.fix_probability)
        self.frame: TangentPlane | None = None
        # fix-rate state of the compiled step (iotnav.engines.integrity_fix)
        self.fx, self.win, self.buf, self.qh, self.qt = fx_kernel.new_fix_state(c.nis_window)
        self.cfg = np.zeros(fx_kernel.CF_SIZE)
        for i, v in (
            (fx_kernel.CF_NIS_WINDOW, c.nis_window),
            (fx_kernel.CF_MIN_REINIT_DISTANCE, c.min_reinit_distance_m),
            (fx_kernel.CF_REINIT_HOLDOFF, c.reinit_holdoff_s),
            (fx_kernel.CF_WINDOW_BOUND, self.window_bound),
            (fx_kernel.CF_FIX_BOUND, self.fix_bound),
            (fx_kernel.CF_MAX_CONSECUTIVE, c.max_consecutive),
            (fx_kernel.CF_DYN_WINDOW, c.dynamics_window_s),
            (fx_kernel.CF_DYN_MIN_DT, c.dynamics_min_dt_s),
            (fx_kernel.CF_MIN_COURSE_SPEED, c.min_course_speed_mps),
            (fx_kernel.CF_MARGIN, c.dynamics_margin),
            (fx_kernel.CF_ACCEL_FLOOR, c.accel_floor_mps2),
            (fx_kernel.CF_YAW_RATE_FLOOR, c.yaw_rate_floor_rad_s),
            (fx_kernel.CF_OUTAGE_AFTER, c.outage_after_s),
        ):
            self.cfg[i] = v
        self._fixv = np.zeros(6)
        self._fig = np.zeros(fx_kernel.FIG_SIZE)
        self._bounds = np.zeros(4)
        self.st = np.zeros(S_SIZE)
        self.st[[S_ROLL, S_PITCH, S_YAW]] = math.nan
        self.st[S_T_REINIT] = -math.inf
        self.st[S_EVENT_T_FIX] = math.nan
        self._set_bounds((c.accel_floor_mps2,) * 2 + (c.yaw_rate_floor_rad_s, c.accel_floor_mps2), 0.0)
        self.prm = np.zeros(P_SIZE)
        self.prm[P_OUTAGE_AFTER] = c.outage_after_s
        self.prm[P_MIN_COURSE_SPEED] = c.min_course_speed_mps
        self.prm[P_MARGIN] = c.dynamics_margin
        self.prm[P_HOLDOFF] = c.reinit_holdoff_s
        self.probation_events: list[dict[str, Any]] = []
        self._reinits = 0

    @property
    def counts(self) -> dict[str, int]:
        """Fixes checked by the consistency watch and re-initialisations so far."""
        return {"fixes_checked": int(self.fx[fx_kernel.FX_CHECKED]), "reinitialised": self._reinits}

    @property
    def t_reinit(self) -> float:
        """Time of the last re-initialisation, s (-inf before any)."""
        return float(self.st[S_T_REINIT])

    def _set_bounds(self, bounds: tuple[float, float, float, float], speed_max: float) -> None:
        self.st[S_A_S : S_A_RMS + 1] = bounds
        self.st[S_SPEED_MAX] = speed_max

    def set_frame(self, lat_deg: float, lon_deg: float, height_m: float) -> None:
        """Make the guard's NED frame at a geodetic point (degrees, m; NaN height: 0)."""
        self.frame = TangentPlane(lat_deg, lon_deg, height_m if math.isfinite(height_m) else 0.0)
        self._frame_to_state()

    def _frame_to_state(self) -> None:
        assert self.frame is not None
        self.st[S_LAT0 : S_KE + 1] = self.frame.constants()
        self.st[S_HAVE_FRAME] = 1.0

    # ----------------------------------------------------------------- fixes
    def on_fix(self, s: GnssSample) -> dict[str, Any] | None:
        """Take a valid fix; a re-initialisation request (event dict) when the engine disagrees.

        The consistency watch and the dynamics bounds are the compiled
        :func:`iotnav.engines.integrity_fix.fix_step`; the frame and the fix's own figures are
        made here.
        """
        c = self.config
        st = self.st
        have_fix = st[S_HAVE_FIX] != 0.0
        if have_fix and s.t < st[S_FIX_T]:
            return None  # out of order: the engine's own input guard counts and drops it
        if self.frame is None:
            self.set_frame(s.lat_deg, s.lon_deg, s.height_m)
        assert self.frame is not None
        h = s.height_m if math.isfinite(s.height_m) else self.frame.h0_m
        p = self.frame.to_ned(s.lat_deg, s.lon_deg, h)
        if self.frame.follow(p):  # long routes: re-linearised at the fix (same coordinates)
            self._frame_to_state()
        h_acc = s.h_acc_m if math.isfinite(s.h_acc_m) and s.h_acc_m > 0 else c.default_h_acc_m
        s_acc = s.s_acc_mps if math.isfinite(s.s_acc_mps) and s.s_acc_mps > 0 else c.default_speed_acc_mps
        v = fix_velocity(s)
        sigma = max(h_acc / math.sqrt(2.0), c.min_sigma_m)
        # the fix that ends an outage measures the outage's drift, judged by the outage guard
        after_outage = have_fix and s.t - st[S_FIX_T] > c.outage_after_s
        fixv = self._fixv
        fixv[:] = (s.t, p[0], p[1], v[0], v[1], sigma)
        self.buf = fx_kernel.ensure_room(self.buf, self.qh, self.qt)
        fig = self._fig
        result, speed_max = fx_kernel.fix_step(
            self.cfg,
            self.fx,
            self.win,
            self.buf,
            self.qh,
            self.qt,
            fixv,
            st[_LAST_IDX],
            not after_outage and st[S_LAST_OK] != 0.0,
            fig,
            self._bounds,
        )
        if fig[fx_kernel.FIG_PROBATION_PASSED] != 0.0:
            st[S_PROBATION] = 0.0  # the fresh engine agrees with the fixes: its rows are used
            self.probation_events.append({"type": "integrity_probation_passed", "t": float(s.t)})
        st[S_HAVE_FIX] = 1.0
        st[S_FIX_T : S_FIX_SIGV + 1] = (s.t, p[0], p[1], p[2], v[0], v[1], sigma, s_acc)
        st[S_LATCH] = 0.0
        st[S_A_S : S_A_RMS + 1] = self._bounds
        st[S_SPEED_MAX] = speed_max
        if result == fx_kernel.RESULT_NONE:
            return None
        return {
            "type": "reinitialised",
            "t": float(s.t),
            "reason": "windowed_nis" if result == fx_kernel.RESULT_WINDOWED_NIS else "consecutive_rejections",
            "nis_window_sum": float(fig[fx_kernel.FIG_WIN]),
            "nis_window_bound": self.window_bound,
            "nis_window_fixes": int(fig[fx_kernel.FIG_N]),
            "consecutive_beyond_bound": int(fig[fx_kernel.FIG_CONSECUTIVE]),
            "fix_bound": self.fix_bound,
            "distance_m": float(fig[fx_kernel.FIG_DIST]),
            "mean_distance_m": float(fig[fx_kernel.FIG_MEAN_DIST]),
        }

    def reinitialised(self, t: float) -> None:
        """The engine was replaced at ``t`` (s): start the watch over."""
        self.st[S_T_REINIT] = t
        fx = self.fx
        fx[fx_kernel.FX_NIS_N] = fx[fx_kernel.FX_NIS_HEAD] = 0.0
        self.st[S_PROBATION] = 1.0
        fx[fx_kernel.FX_CONSECUTIVE] = 0.0
        fx[fx_kernel.FX_SINCE_REINIT] = 0.0
        self.st[S_LAST_OK] = 0.0
        self._reinits += 1


class IntegrityEngine:
    """Any engine behind :class:`IntegrityGuard` (module docstring), with the same ``step()``.

    An engine with a compiled block step (``imu_block``) keeps it: the wrapper's own
    ``imu_block`` runs the engine's over the block and then :func:`guard_rows` over its rows;
    when a row asks for a re-initialisation the rest of the block is run again by the fresh
    engine. ``step()`` runs the same kernel on a one-row block, so batch and streaming agree.

    Parameters
    ----------
    factory : callable
        Builds a fresh engine (called once now and at each re-initialisation).
    config : IntegrityConfig, optional
        Guard tunables.

    Attributes not defined here (``mount_rpy_rad``, ``config``, ``guard``...) are the current
    engine's.
    """

    #: The last re-initialisation was asked of the engine itself (a class default: checkpoints
    #: written before the request load with it)
    _asked: bool = False

    def __init__(self, factory: Callable[[], Engine], config: IntegrityConfig | None = None) -> None:
        self._factory = factory
        self._inner = factory()
        self._guard = IntegrityGuard(config)
        self._own_events: list[dict[str, Any]] = []
        self._past_events: list[dict[str, Any]] = []
        self._past_skipped: dict[str, int] = {}
        self._row = OutputBlock(1)
        self._row.add(output_without_position(0.0, (0.0, 0.0, 0.0), False))
        self._code_dr = self._row.codes.setdefault(DR_VELOCITY_SOURCE, len(self._row.names))
        self._row.names.append(DR_VELOCITY_SOURCE)
        self._utc_offset_s: float | None = None

    def __getattr__(self, name: str) -> Any:
        if name == "imu_block" and getattr(self._inner, "imu_block", None) is not None:
            return self._guarded_block
        # never hand out the engine's smoothing log: it would smooth rows the guard replaced
        if name.startswith("_") or name in ("imu_block", "smoothing_log"):
            raise AttributeError(name)
        return getattr(self._inner, name)

    @property
    def engine(self) -> Engine:
        """The engine currently guarded."""
        return self._inner

    @property
    def utc_offset_s(self) -> float:
        """The log's UTC offset (s) as :func:`~iotnav.engines.base.run_batch` sets it; passed on."""
        v = getattr(self._inner, "utc_offset_s", self._utc_offset_s)
        return math.nan if v is None else float(v)

    @utc_offset_s.setter
    def utc_offset_s(self, value: float) -> None:
        self._utc_offset_s = value
        if hasattr(self._inner, "utc_offset_s"):
            self._inner.utc_offset_s = value  # type: ignore[attr-defined]

    @property
    def events(self) -> list[dict[str, Any]]:
        """Events of every engine guarded so far and the guard's own, in time order."""
        evs = self._past_events + list(self._inner.events) + self._own_events + self._guard.probation_events
        return sorted(evs, key=lambda e: float(e.get("t", -math.inf)))

    @events.setter
    def events(self, value: list[dict[str, Any]]) -> None:
        self._past_events, self._own_events = [], []
        self._guard.probation_events = []
        self._inner.events = value

    @property
    def mount_yaw_rad(self) -> float:
        """The current engine's mount-yaw estimate, rad."""
        return float(self._inner.mount_yaw_rad)

    def step(self, sample: Sample) -> Output | None:
        """One sample through the engine and the guard (an output per IMU sample)."""
        if (
            isinstance(sample, GnssSample)
            and sample.valid
            and math.isfinite(sample.t + sample.lat_deg + sample.lon_deg)
        ):
            request = self._guard.on_fix(sample)
            if request is not None:
                self._reinit(request, fix=True)
        out = self._inner.step(sample)
        if out is None or not isinstance(sample, ImuSample):
            return out
        b = self._row
        b.n = 0
        b.add(out)
        self._rows(b, 0, 1, self._code_dr)
        return b.row(0)

    def _rows(self, out: OutputBlock, i0: int, i1: int, code_dr: int) -> int:
        """:func:`guard_rows` over rows ``i0 .. i1-1``; the row from which the engine must be re-run."""
        g = self._guard
        k = i0
        while k < i1:
            k, flag, reason = guard_rows(out.floats, out.source, k, i1, g.st, g.prm, code_dr)
            if flag == FLAG_NEED_FRAME:
                f = out.floats
                g.set_frame(float(f[C_LAT, k]), float(f[C_LON, k]), float(f[C_HEIGHT, k]))
            elif flag == FLAG_EVENT:
                t_fix = float(g.st[S_FIX_T])
                self._own_events.append(
                    {
                        "type": "integrity_fallback",
                        "t": float(out.floats[C_T, k - 1]),
                        "reason": REASONS[reason],
                        "t_fix": t_fix,
                    }
                )
            elif flag == FLAG_REINIT:
                t = float(out.floats[C_T, k - 1])
                self._reinit({"type": "reinitialised", "t": t, "reason": "nonfinite_output"})
                return k
        return i1

    def _guarded_block(
        self,
        t: FloatArray,
        acc: tuple[FloatArray, FloatArray, FloatArray],
        gyro: tuple[FloatArray, FloatArray, FloatArray],
        out: OutputBlock,
        i0: int,
        i1: int,
    ) -> None:
        """The engine's ``imu_block`` over samples ``i0 .. i1-1`` (units of
        :meth:`iotnav.engines.base.BlockEngine.imu_block`), then the guard over its rows."""
        code_dr = out.codes.get(DR_VELOCITY_SOURCE, len(out.names))
        k = i0
        while k < i1:
            self._inner.imu_block(t, acc, gyro, out, k, i1)  # type: ignore[attr-defined]
            k = self._rows(out, k, i1, code_dr)
        if DR_VELOCITY_SOURCE not in out.codes and bool(np.any(out.source[i0:i1] == code_dr)):
            out.codes[DR_VELOCITY_SOURCE] = code_dr
            out.names.append(DR_VELOCITY_SOURCE)

    def _reinit(self, event: dict[str, Any], fix: bool = False) -> None:
        """Re-initialise at ``event["t"]`` (event ``how``): at a fix, an engine that can reset
        itself (``request_reinitialise``: eskf, whose reset keeps what it knows of the sensor
        and escalates on its own) is asked to (``engine_reset``), unless it was asked last time
        and has not agreed with the fixes since (its probation); else a fresh engine from the
        factory (``fresh_engine``)."""
        ask = getattr(self._inner, "request_reinitialise", None)
        if fix and ask is not None and not (self._asked and self._guard.st[S_PROBATION] != 0.0):
            self._asked = True
            ask(f"integrity_{event['reason']}")
            self._guard.reinitialised(float(event["t"]))
            self._own_events.append({**event, "how": "engine_reset"})
            return
        self._asked = False
        event = {**event, "how": "fresh_engine"}
        self._past_events += list(self._inner.events)
        for k, n in dict(self._inner.summary().get("skipped", {})).items():
            self._past_skipped[k] = self._past_skipped.get(k, 0) + int(n)
        self._inner = self._factory()
        if self._utc_offset_s is not None and hasattr(self._inner, "utc_offset_s"):
            self._inner.utc_offset_s = self._utc_offset_s  # type: ignore[attr-defined]
        self._guard.reinitialised(float(event["t"]))
        self._own_events.append(event)

    def summary(self) -> dict[str, Any]:
        """The current engine's summary plus ``integrity`` (configuration and counts)."""
        out = dict(self._inner.summary())
        if self._past_skipped:  # samples skipped by the engines replaced so far count too
            skipped = dict(out.get("skipped", {}))
            for k, n in self._past_skipped.items():
                skipped[k] = skipped.get(k, 0) + n
            out["skipped"] = skipped
        g = self._guard
        counts = {
            **g.counts,
            "fallback_rows": int(g.st[S_FALLBACK_ROWS]),
            "engine_rows": int(g.st[S_ENGINE_ROWS]),
            "sigma_raised_rows": int(g.st[S_INFLATED_ROWS]),
        }
        out["integrity"] = {"config": asdict(g.config), **counts}
        return out
