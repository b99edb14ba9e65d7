"""The departure test of a parked device, compiled, for :mod:`iotnav.engines.fixes_kernel`.

Moved out of :mod:`iotnav.engines.fixes_kernel` (its line limit) with the jump tracking added;
the test is described in :mod:`iotnav.engines.fixes` ("Leaving") and mirrored in C by
``departed`` in ``firmware/fixes.c``.
"""

from __future__ import annotations

import math

import numba
import numpy as np
import numpy.typing as npt

from iotnav.engines.fixes_layout import (
    AX_E,
    AX_N,
    P_DEP_ACC,
    P_DEP_GATE,
    P_EXIT_RUN,
    P_EXIT_SPEED,
    P_LP_TAU,
    P_SPEED_THR,
    P_VEL_SIGMA,
    S_DEP_D0,
    S_DEP_N,
    S_DEP_PE,
    S_DEP_PN,
    S_DEP_T,
    S_DEP_VMAX,
    S_GOOD_E,
    S_GOOD_N,
    S_GOOD_T,
    S_HOLD_E,
    S_HOLD_N,
    S_IN_JUMP,
    S_JUMP_E,
    S_JUMP_N,
    S_JUMP_T,
    S_LP_E,
    S_LP_HAVE,
    S_LP_N,
    S_T_STILL,
)

__all__ = ["_departed", "_not_jump"]

FloatArray = npt.NDArray[np.float64]


@numba.njit(cache=True)
def _not_jump(st: FloatArray, n: float, e: float, t: float) -> None:
    """The departure test's fix ``(n, e)`` (m) at ``t`` (s) is no jump: the reference of the next step."""
    st[S_GOOD_N], st[S_GOOD_E], st[S_GOOD_T], st[S_IN_JUMP] = n, e, t, 0.0


@numba.njit(cache=True)
def _departed(
    st: FloatArray,
    prm: FloatArray,
    kf: FloatArray,
    n: float,
    e: float,
    rh: float,
    t: float,
    sp: float,
    sacc: float,
    step_dt: float,
) -> bool:
    """Departure test of a parked device at a fix ``(n, e)`` (m) of variance ``rh`` (m^2 per axis).

    The fix is *displaced* when its NIS against the held position (the row output: the low-pass,
    else the position at the start of the static period) with the state's covariance exceeds the
    ``departure_probability`` quantile, bound ``b = sqrt(gate S)``. A displaced fix must be
    reachable from inside the bound in the time ``dt`` since the last fix that was not displaced:
    no farther from the held position than ``b + (v + 3 s_v) dt`` with ``v`` the largest speed
    reported since then (``s_v`` its sigma, at least ``vel_noise_mps``), or without a reported
    speed ``b + sqrt(2 a b) dt + a dt^2 / 2`` (from rest at acceleration ``a`` =
    ``departure_acc_mps2``, at most ``sqrt(2 a b)`` on leaving the bound); else it is a
    multipath jump, held; so is a displaced fix farther from the last fix that was no jump
    (``S_GOOD_*``, ``dt`` s before) than ``sqrt(2 gate rh (1 - exp(-dt / lowpass_corr_time_s))) +
    v dt`` (``v`` the reach's speed), and one within that of the latest jump fix (``S_JUMP_*``,
    ``S_IN_JUMP``: the same outlier goes on). A fix whose reported speed exceeds ``exit_speed_mps`` counts as
    displaced without the bound (a car pulls away faster than the fixes leave a canyon's bound).
    Consecutive reachable displaced fixes form a run, which is a departure
    once it has ``exit_speed_fixes`` fixes and its latest fix is farther from the held position
    than its first by ``speed_threshold_mps`` times the run's span (it moves away; a jump's
    offset stays put, wander goes either way). With fixes sparser than 1 Hz, a run as long in
    time as ``exit_speed_fixes`` fixes at 1 Hz (s) decides the same way from the last fix that
    was not displaced (unless a jump came between), and a lone fix after such a gap (``step_dt``,
    s since the previous epoch) whose reported speed is above ``exit_speed_mps`` is a departure. Displaced fixes for ``lowpass_corr_time_s`` (the
    errors' correlation time) are a departure whatever the rest. Updates ``S_DEP_*``, ``S_T_STILL``,
    ``S_GOOD_*``, ``S_JUMP_*``, ``S_IN_JUMP``.
    """
    if st[S_LP_HAVE] != 0.0:
        hn, he = st[S_LP_N], st[S_LP_E]
    else:
        hn, he = st[S_HOLD_N], st[S_HOLD_E]
    dn, de = n - hn, e - he
    sn2, se2 = kf[AX_N + 2] + rh, kf[AX_E + 2] + rh
    displaced = dn * dn / sn2 + de * de / se2 > prm[P_DEP_GATE]
    if not displaced and not (math.isfinite(sp) and sp > prm[P_EXIT_SPEED]):
        st[S_DEP_N] = 0.0
        st[S_T_STILL] = t
        st[S_DEP_VMAX] = sp if math.isfinite(sp) else 0.0
        st[S_DEP_D0] = math.hypot(dn, de)
        _not_jump(st, n, e, t)
        return False
    if not displaced:
        _not_jump(st, n, e, t)  # a fast fix inside the bound
    dt = t - st[S_T_STILL]
    if dt >= prm[P_LP_TAU]:
        return True  # displaced (or fast) for longer than the errors' correlation time
    if math.isfinite(sp):
        st[S_DEP_VMAX] = max(st[S_DEP_VMAX], sp)
    d = math.hypot(dn, de)
    if displaced:
        b = math.sqrt(prm[P_DEP_GATE] * max(sn2, se2))
        if math.isfinite(sp):
            vm = st[S_DEP_VMAX] + 3.0 * max(sacc if math.isfinite(sacc) else 0.0, prm[P_VEL_SIGMA])
            reach = b + vm * dt
        else:
            vm = math.sqrt(2.0 * prm[P_DEP_ACC] * b)
            reach = b + vm * dt + 0.5 * prm[P_DEP_ACC] * dt * dt
        jump = d > reach
        if not jump:
            # the fix's step from the last fix that was no jump, or from the latest jump fix: in
            # dt a receiver's error changes by at most sqrt(gate 2 rh (1 - exp(-dt / tau))) (a
            # Gauss-Markov error, correlation time tau) and the device moves at most vm dt
            dtj = t - st[S_JUMP_T]
            dtg = t - st[S_GOOD_T]
            lim_j = math.sqrt(2.0 * prm[P_DEP_GATE] * rh * (1.0 - math.exp(-dtj / prm[P_LP_TAU]))) + vm * dtj
            lim_g = math.sqrt(2.0 * prm[P_DEP_GATE] * rh * (1.0 - math.exp(-dtg / prm[P_LP_TAU]))) + vm * dtg
            if st[S_IN_JUMP] != 0.0 and math.hypot(n - st[S_JUMP_N], e - st[S_JUMP_E]) <= lim_j:
                jump = True  # it goes on from the jump fix before: the same outlier
            elif math.hypot(n - st[S_GOOD_N], e - st[S_GOOD_E]) > lim_g:
                jump = True  # a step off the fixes before
        if jump:
            st[S_JUMP_N], st[S_JUMP_E], st[S_JUMP_T], st[S_IN_JUMP] = n, e, t, 1.0
            st[S_DEP_N] = 0.0  # a jump: the run starts again at the next reachable fix
            st[S_DEP_D0] = math.inf  # and only a full run decides until the next still fix
            return False
        _not_jump(st, n, e, t)
    if st[S_DEP_N] == 0.0:
        st[S_DEP_T], st[S_DEP_PN], st[S_DEP_PE] = t, n, e
    st[S_DEP_N] += 1.0
    span = t - st[S_DEP_T]
    if st[S_DEP_N] >= prm[P_EXIT_RUN] and span > 0.0:
        return d - math.hypot(st[S_DEP_PN] - hn, st[S_DEP_PE] - he) >= prm[P_SPEED_THR] * span
    if dt >= prm[P_EXIT_RUN]:  # sparse fixes: as long as the run would take at 1 Hz
        if step_dt >= prm[P_EXIT_RUN] and math.isfinite(sp) and sp > prm[P_EXIT_SPEED]:
            return True  # one fix in that time, reporting a departure speed
        return d - st[S_DEP_D0] >= prm[P_SPEED_THR] * dt
    return False
