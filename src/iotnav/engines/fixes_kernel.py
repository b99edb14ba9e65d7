"""Compiled per-fix step of the ``fixes`` engine (:mod:`iotnav.engines.fixes`; its RTS pass in :mod:`~iotnav.engines.fixes_rts`).

One function, :func:`fixes_kernel`, processes a block of GNSS epochs (rows of an input array,
layout ``I_*``); the engine's streaming ``step()`` calls it on a one-row block and the batch
path on the whole log, so both run the same compiled code (STYLE §7). The model, the gate,
the static test and the input checks are described in :mod:`iotnav.engines.fixes`.

State layout (``kf``, 15 floats): three independent axes North, East, Down; axis ``a`` holds
``[p, v, P_pp, P_pv, P_vv]`` at ``kf[5a : 5a + 5]`` (m, m/s, m^2, m^2/s, m^2/s^2). The
constant-velocity model with white acceleration noise and a diagonal ``R`` keeps the axes
uncorrelated, so the 6-state filter is exactly three 2-state filters.
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
    SRC_LAST_POSITION,
    SRC_LOWPASS,
    write_position,
)
from iotnav.engines.fixes_departure import _departed
from iotnav.engines.fixes_layout import *  # noqa: F403  (the layouts, re-exported)
from iotnav.techniques.lowpass3 import lowpass3_n_fixes, lowpass3_push, lowpass3_reset

FloatArray = npt.NDArray[np.float64]


@numba.njit(cache=True)
def predict_axis(kf: FloatArray, a: int, dt: float, q: float) -> None:
    """Constant-velocity prediction of axis block ``a`` over ``dt`` s with acceleration PSD ``q`` (m^2/s^3).

    ``F = [[1, dt], [0, 1]]``, ``Q = q [[dt^3/3, dt^2/2], [dt^2/2, dt]]`` (white acceleration,
    Bar-Shalom, Li and Kirubarajan 2001, sec. 6.2.2); ``P- = F P F^T + Q``.
    """
    p00, p01, p11 = kf[a + 2], kf[a + 3], kf[a + 4]
    kf[a] += dt * kf[a + 1]
    kf[a + 2] = p00 + dt * (2.0 * p01 + dt * p11) + q * dt * dt * dt / 3.0
    kf[a + 3] = p01 + dt * p11 + 0.5 * q * dt * dt
    kf[a + 4] = p11 + q * dt


@numba.njit(cache=True)
def update_axis(kf: FloatArray, a: int, j: int, z: float, r: float) -> None:
    """Scalar update of axis block ``a``: component ``j`` (0 position, 1 velocity) measured as ``z``, variance ``r``.

    ``K = P H^T / S``, ``S = H P H^T + r``; Joseph form ``P+ = (I - K H) P (I - K H)^T + K r K^T``
    written out for ``H = e_j`` (symmetric by construction).
    """
    p00, p01, p11 = kf[a + 2], kf[a + 3], kf[a + 4]
    s = (p00 if j == 0 else p11) + r
    k0 = (p00 if j == 0 else p01) / s
    k1 = (p01 if j == 0 else p11) / s
    y = z - kf[a + j]
    kf[a] += k0 * y
    kf[a + 1] += k1 * y
    if j == 0:
        # A = I - K e0^T = [[1 - k0, 0], [-k1, 1]]
        a00, a10 = 1.0 - k0, -k1
        n00 = a00 * a00 * p00
        n01 = a00 * (a10 * p00 + p01)
        n11 = a10 * a10 * p00 + 2.0 * a10 * p01 + p11
    else:
        # A = I - K e1^T = [[1, -k0], [0, 1 - k1]]
        a01, a11 = -k0, 1.0 - k1
        n00 = p00 + 2.0 * a01 * p01 + a01 * a01 * p11
        n01 = a11 * (p01 + a01 * p11)
        n11 = a11 * a11 * p11
    kf[a + 2] = n00 + k0 * k0 * r
    kf[a + 3] = n01 + k0 * k1 * r
    kf[a + 4] = n11 + k1 * k1 * r


@numba.njit(cache=True)
def init_axis(kf: FloatArray, a: int, p: float, v: float, var_p: float, var_v: float) -> None:
    """Set axis block ``a`` to position ``p`` (m), velocity ``v`` (m/s), uncorrelated variances."""
    kf[a] = p
    kf[a + 1] = v
    kf[a + 2] = var_p
    kf[a + 3] = 0.0
    kf[a + 4] = var_v


@numba.njit(cache=True)
def chi2_quantile_wh(dof: float, z: float) -> float:
    """Chi-square quantile for ``dof`` degrees of freedom at normal quantile ``z`` (Wilson-Hilferty 1931).

    ``chi2_p(k) ~ k (1 - 2/(9k) + z sqrt(2/(9k)))^3``; within 1 % of the exact value for
    ``k >= 4`` at ``z = 2.326`` (p = 0.99).
    """
    c = 2.0 / (9.0 * dof)
    b = 1.0 - c + z * math.sqrt(c)
    return dof * b * b * b


@numba.njit(cache=True)
def screen_epoch(st: FloatArray, prm: FloatArray, row: FloatArray) -> int:
    """Reason code (``R_*``) of an epoch that cannot be used, or ``R_OK``; updates the time references.

    Time: earlier than the previous admitted epoch is ``backwards``; the same time and the
    same coordinates ``duplicate``, the same time otherwise ``repeat``. UTC: the offset
    ``utc - t`` of the first epoch with a UTC is the reference; an epoch whose offset differs
    by more than ``clock_tolerance_s`` is ``future`` / ``past`` until ``relocation_fixes``
    consecutive such epochs agree with each other, which then become the reference (event).
    Validity: the receiver's flag, ``(0, 0)``, then :func:`iotnav.techniques.last_position.
    fix_rejection_reason`'s PDOP and satellite rules (tested equal).
    """
    t = row[I_T]
    if t < st[S_T_LAST]:
        return R_BACKWARDS
    if t == st[S_T_LAST]:
        if row[I_LAT] == st[S_LAT_LAST] and row[I_LON] == st[S_LON_LAST]:
            return R_DUPLICATE
        return R_REPEAT
    utc = row[I_UTC]
    if math.isfinite(utc):
        off = utc - t
        if not math.isfinite(st[S_OFF_REF]):
            st[S_OFF_REF] = off
        else:
            d = off - st[S_OFF_REF]
            if abs(d) > prm[P_CLOCK_TOL]:
                if st[S_OFF_N] > 0.0 and abs(off - st[S_OFF_CAND]) <= prm[P_CLOCK_TOL]:
                    st[S_OFF_N] += 1.0
                else:
                    st[S_OFF_N] = 1.0
                    st[S_OFF_CAND] = off
                if st[S_OFF_N] < prm[P_RELOC_N]:
                    return R_FUTURE if d > 0.0 else R_PAST
                st[S_OFF_REF] = off  # consistent epochs: the reference was wrong (caller's event)
                st[S_OFF_N] = -1.0
            else:
                st[S_OFF_N] = 0.0
    st[S_T_LAST] = t
    st[S_LAT_LAST] = row[I_LAT]
    st[S_LON_LAST] = row[I_LON]
    if row[I_VALID] == 0.0 or not (math.isfinite(row[I_LAT]) and math.isfinite(row[I_LON])):
        return R_INVALID
    if row[I_LAT] == 0.0 and row[I_LON] == 0.0:
        return R_ZERO
    pdop = row[I_PDOP]
    if math.isfinite(pdop):
        if pdop > prm[P_MAX_PDOP]:
            return R_PDOP
    elif prm[P_ACCEPT_UNKNOWN_PDOP] == 0.0:
        return R_PDOP_UNKNOWN
    if prm[P_MIN_SV] > 0.0 and row[I_NSV] < prm[P_MIN_SV]:
        return R_NUM_SV
    return R_OK


@numba.njit(cache=True)
def _measured_velocity(prm: FloatArray, row: FloatArray) -> tuple[float, float, float]:
    """``(vn, ve, vd)`` of an epoch (m/s; NaN where absent): NED velocity, else speed and course."""
    vn, ve, vd = row[I_VN], row[I_VE], row[I_VD]
    if math.isfinite(vn) and math.isfinite(ve):
        return vn, ve, vd
    sp = row[I_SPEED]
    if row[I_COURSE_VALID] != 0.0 and math.isfinite(sp) and sp >= prm[P_MIN_COURSE_SPEED]:
        c = row[I_COURSE]
        if math.isfinite(c):
            return sp * math.cos(c), sp * math.sin(c), math.nan
    return math.nan, math.nan, math.nan


@numba.njit(cache=True)
def _init_filter(
    st: FloatArray, prm: FloatArray, kf: FloatArray, row: FloatArray, n: float, e: float, d: float
) -> None:
    """Initialise the three axes at a fix (NED, m) with its R and measured velocity (if any)."""
    vn, ve, vd = _measured_velocity(prm, row)
    sv = row[I_SACC] if math.isfinite(row[I_SACC]) and row[I_SACC] > 0.0 else prm[P_VEL_SIGMA]
    v0 = prm[P_INIT_VEL_STD] ** 2
    sh2 = row[I_SIG_H] ** 2
    have_v = math.isfinite(vn)
    init_axis(kf, AX_N, n, vn if have_v else 0.0, sh2, sv * sv if have_v else v0)
    init_axis(kf, AX_E, e, ve if have_v else 0.0, sh2, sv * sv if have_v else v0)
    if math.isfinite(d):
        have_vd = math.isfinite(vd)
        init_axis(kf, AX_D, d, vd if have_vd else 0.0, row[I_SIG_V] ** 2, sv * sv if have_vd else v0)
        st[S_HAVE_D] = 1.0
    else:
        init_axis(kf, AX_D, 0.0, 0.0, 1e12, v0)
        st[S_HAVE_D] = 0.0
    st[S_INIT] = 1.0
    st[S_T_X] = row[I_T]
    st[S_T_FIX] = row[I_T]
    st[S_N_REJ] = 0.0
    st[S_CAND_N] = 0.0
    st[S_RING_N] = 0.0
    st[S_STATIC] = 0.0
    st[S_SNAP] = 0.0
    st[S_FLOOR_N] = st[S_FLOOR_E] = sh2
    lowpass3_reset(st[S_LP:S_LP_END])


@numba.njit(cache=True)
def _select(a: FloatArray, k: int) -> float:
    """The ``k``-th smallest of ``a`` (0-based), reordering ``a`` in place (Hoare's quickselect):
    afterwards ``a[:k] <= a[k] <= a[k+1:]``."""
    lo, hi = 0, a.size - 1
    while lo < hi:
        pivot = a[(lo + hi) // 2]
        i, j = lo, hi
        while i <= j:
            while a[i] < pivot:
                i += 1
            while a[j] > pivot:
                j -= 1
            if i <= j:
                a[i], a[j] = a[j], a[i]
                i += 1
                j -= 1
        if k <= j:
            hi = j
        elif k >= i:
            lo = i
        else:
            break
    return a[k]


@numba.njit(cache=True)
def median_inplace(a: FloatArray) -> float:
    """Median of ``a`` (as :func:`numpy.median`), reordering ``a`` in place; O(n), no allocation."""
    n = a.size
    h = n // 2
    upper = _select(a, h)
    if n % 2:
        return upper
    lower = a[0]
    for i in range(1, h):  # the largest of the lower half
        lower = max(lower, a[i])
    return 0.5 * (lower + upper)


@numba.njit(cache=True)
def _spread_static(st: FloatArray, prm: FloatArray, ring: FloatArray, t: float, work: FloatArray) -> int:
    """Spread test on the recent fixes: 1 consistent with standing still, 0 not, -1 undecided.

    Uses the fixes of the last ``window_s`` (at least ``min_fixes`` of them; with sparser fixes
    the last ``min_fixes``) and needs them to span ``window_s``: with ``n`` fixes of per-axis
    sigma ``s_i`` about their mean, ``sum |r_i - mean|^2 / s_i^2`` is chi-square with
    ``2 (n - 1)`` degrees of freedom for a device that does not move; above its 99 % quantile
    it moved. Gross outliers (a jump while parked) do not count: a fix whose
    ``|r_i - median|^2 / s_i^2`` exceeds ``P_SPREAD_OUT`` (the 2-dof chi-square quantile at
    1 - 1e-6) is left out of the mean and the sum, and its degrees of freedom with it.
    ``work``: scratch of ``(5, RING_MAX)`` floats (no allocation per fix).
    """
    m = int(min(st[S_RING_N], RING_MAX))
    if m < 2:
        return -1
    cnt = 0
    for j in range(m):
        i = (int(st[S_RING_N]) - 1 - j) % RING_MAX
        if t - ring[i, 0] > prm[P_WINDOW_S] and cnt >= prm[P_MIN_FIXES]:
            break
        cnt += 1
    if cnt < prm[P_MIN_FIXES]:
        return -1
    # spanned: a fix older than the window is in the ring (the loop stopped at it), or the
    # oldest one counted is at least window_s old
    i_old = (int(st[S_RING_N]) - cnt) % RING_MAX
    if cnt == m and t - ring[i_old, 0] < prm[P_WINDOW_S]:
        return -1
    wn, we, sn, se, keep = work[0, :cnt], work[1, :cnt], work[2, :cnt], work[3, :cnt], work[4, :cnt]
    for j in range(cnt):
        i = (int(st[S_RING_N]) - 1 - j) % RING_MAX
        wn[j] = ring[i, 1]
        we[j] = ring[i, 2]
        sn[j] = wn[j]
        se[j] = we[j]
    cn = median_inplace(sn)
    ce = median_inplace(se)
    mn = 0.0
    me = 0.0
    used = 0
    for j in range(cnt):
        i = (int(st[S_RING_N]) - 1 - j) % RING_MAX
        dn = wn[j] - cn
        de = we[j] - ce
        keep[j] = 1.0 if (dn * dn + de * de) / (ring[i, 3] * ring[i, 3]) <= SPREAD_OUT else 0.0
        if keep[j] != 0.0:
            mn += wn[j]
            me += we[j]
            used += 1
    if used < prm[P_MIN_FIXES]:
        return 0  # most of the window far from its median: not standing still
    mn /= used
    me /= used
    chi = 0.0
    for j in range(cnt):
        if keep[j] != 0.0:
            i = (int(st[S_RING_N]) - 1 - j) % RING_MAX
            dn = wn[j] - mn
            de = we[j] - me
            chi += (dn * dn + de * de) / (ring[i, 3] * ring[i, 3])
    return 1 if chi <= chi2_quantile_wh(2.0 * (used - 1), prm[P_SPREAD_Z]) else 0


@numba.njit(cache=True)
def _write_record(
    rec: FloatArray, r: int, t: float, kind: float, static: bool, prior: FloatArray, kf: FloatArray, qf: float
) -> None:
    rec[r, REC_QF] = qf
    rec[r, REC_SIG] = math.nan
    rec[r, REC_T] = t
    rec[r, REC_KIND] = kind
    rec[r, REC_STATIC] = 1.0 if static else 0.0
    for i in range(KF_SIZE):
        rec[r, REC_PRIOR + i] = prior[i]
        rec[r, REC_POST + i] = kf[i]


@numba.njit(cache=True)
def fixes_kernel(
    inp: FloatArray,
    i0: int,
    i1: int,
    r0: int,
    st: FloatArray,
    prm: FloatArray,
    frame: FloatArray,
    kf: FloatArray,
    cand: FloatArray,
    ring: FloatArray,
    lp1: FloatArray,
    lp2: FloatArray,
    lp3: FloatArray,
    floats: FloatArray,
    static_out: npt.NDArray[np.bool_],
    source_out: npt.NDArray[np.int8],
    rec: FloatArray,
    codes: npt.NDArray[np.int8],
    ev: npt.NDArray[np.int32],
    evv: FloatArray,
) -> tuple[int, int, int]:
    """Epochs ``i0 .. i1-1`` of ``inp`` (module docstring); output rows from ``r0``.

    Returns ``(next epoch, next output row, flag)``: ``F_NEED_BOOT`` stops at an acceptable
    epoch before the first fix (the engine's Python boot logic decides, sets ``st[S_DECIDED]``
    to 1 accept or 2 refuse, and calls again from that epoch); ``F_DONE`` at ``i1``.
    """
    r = r0
    prior = np.empty(KF_SIZE)
    snap = np.empty(KF_SIZE)
    work = np.empty((5, RING_MAX))
    n1, n2, n3 = int(prm[P_LP_N1]), int(prm[P_LP_N2]), int(prm[P_LP_N3])
    record = prm[P_RECORD] != 0.0
    for k in range(i0, i1):
        row = inp[k]
        t = row[I_T]
        ev[k] = 0
        evv[k] = math.nan
        decided = st[S_DECIDED]
        st[S_DECIDED] = 0.0
        if decided == 0.0:
            off_before = st[S_OFF_REF]
            reason = screen_epoch(st, prm, row)
            if st[S_OFF_N] < 0.0:
                st[S_OFF_N] = 0.0
                ev[k] |= EV_CLOCK
                evv[k] = st[S_OFF_REF] - off_before
        else:
            reason = R_OK if decided == 1.0 else R_SETTLING
        moving_hint = (math.isfinite(row[I_SPEED]) and row[I_SPEED] > prm[P_SPEED_THR]) or row[
            I_MOTION
        ] == 1.0
        if st[S_INIT] == 0.0:
            if reason == R_OK and decided == 0.0:
                return k, r, F_NEED_BOOT
            if reason == R_OK:  # decided: initialise at this fix
                n = (row[I_LAT] - frame[0]) * frame[3]
                e = (row[I_LON] - frame[1]) * frame[4]
                d = frame[2] - row[I_H]
                _init_filter(st, prm, kf, row, n, e, d)
                ev[k] |= EV_INIT
                for i in range(KF_SIZE):
                    prior[i] = kf[i]
                codes[k] = R_OK
            else:
                codes[k] = reason
                if st[S_HAVE_FRAME] == 0.0:
                    continue
                # stored last position in use (the NED origin): a boot row
                if moving_hint and not math.isfinite(st[S_T_MOVE]):
                    st[S_T_MOVE] = t
                    ev[k] |= EV_BOOT_MOVE
                grow = prm[P_BOOT_WALK] * (t - st[S_T_MOVE]) if math.isfinite(st[S_T_MOVE]) else 0.0
                sd = prm[P_STORED_STD] + grow
                floats[C_T, r] = t
                z3 = np.zeros(3)
                write_position(floats, r, z3, z3, sd, sd, frame)
                static_out[r] = False
                source_out[r] = SRC_LAST_POSITION
                if record:
                    for i in range(KF_SIZE):
                        prior[i] = math.nan
                    _write_record(rec, r, t, K_BOOT, False, prior, prior, 1.0)
                r += 1
                continue
            kind = K_SEGMENT
            rec_kind = K_SEGMENT
            static = False
            src = SRC_FIX
            qf = 1.0
        else:
            codes[k] = reason
            if reason != R_OK:
                continue
            kind = K_FILTER
            # --- predict (q raised after rejections: manoeuvre; none while parked: hold)
            dt = t - st[S_T_X]
            qf = 1.0 + (prm[P_REJECT_QF] - 1.0) * st[S_N_REJ]
            # while parked only the departure test (or the motion flag) ends the hold: neither
            # the reported speed nor rejected fixes (a multipath jump) let the state wander
            hold = st[S_STATIC] != 0.0 and row[I_MOTION] != 1.0
            # the gate always sees the moving model's spread: leaving a parking place is not a glitch
            q_gate = prm[P_Q_H] * dt * dt * dt / 3.0 if hold and dt > 0.0 else 0.0
            if hold:
                qf = 0.0
            if dt > 0.0:
                g_n, g_e = st[S_FLOOR_N] - kf[AX_N + 2], st[S_FLOOR_E] - kf[AX_E + 2]
                predict_axis(kf, AX_N, dt, prm[P_Q_H] * qf)
                predict_axis(kf, AX_E, dt, prm[P_Q_H] * qf)
                predict_axis(kf, AX_D, dt, prm[P_Q_V] * qf)
                st[S_T_X] = t
                st[S_FLOOR_N], st[S_FLOOR_E] = kf[AX_N + 2] + g_n, kf[AX_E + 2] + g_e  # grows as P_pp
            for i in range(KF_SIZE):
                prior[i] = kf[i]
            was = st[S_STATIC] != 0.0
            n = (row[I_LAT] - frame[0]) * frame[3]
            e = (row[I_LON] - frame[1]) * frame[4]
            d = frame[2] - row[I_H]
            rh = row[I_SIG_H] * row[I_SIG_H]
            yn, ye = n - kf[AX_N], e - kf[AX_E]
            nis = yn * yn / (kf[AX_N + 2] + q_gate + rh) + ye * ye / (kf[AX_E + 2] + q_gate + rh)
            accepted = nis <= prm[P_GATE]
            rec_kind = K_FILTER
            if not was and st[S_SNAP] != 0.0 and t - st[S_SNAP_T] > prm[P_ROLLBACK_S]:
                st[S_SNAP] = 0.0  # the doubtful fixes held: the snapshot expires
            if not accepted and not was and st[S_SNAP] != 0.0:
                # rejected here, but is the fix consistent with the state before the doubtful
                # fixes? Then those were the outliers (multipath): retract them.
                for i in range(KF_SIZE):
                    snap[i] = st[S_SNAP_X + i]
                dts = t - st[S_SNAP_T]
                if dts > 0.0:
                    predict_axis(snap, AX_N, dts, prm[P_Q_H])
                    predict_axis(snap, AX_E, dts, prm[P_Q_H])
                    predict_axis(snap, AX_D, dts, prm[P_Q_V])
                sn, se = n - snap[AX_N], e - snap[AX_E]
                sn2, se2 = snap[AX_N + 2] + rh, snap[AX_E + 2] + rh
                nis_s = sn * sn / sn2 + se * se / se2
                # the snapshot must explain the fix better: larger Gaussian likelihood, whose
                # log-determinant term penalises its grown uncertainty (2-hypothesis test)
                sc2, se2c = kf[AX_N + 2] + q_gate + rh, kf[AX_E + 2] + q_gate + rh
                better = nis_s + math.log(sn2 * se2) < nis + math.log(sc2 * se2c)
                if nis_s <= prm[P_GATE] and better:
                    for i in range(KF_SIZE):
                        kf[i] = snap[i]
                        prior[i] = snap[i]
                    st[S_SNAP] = 0.0
                    accepted = True
                    rec_kind = K_ROLLBACK
                    ev[k] |= EV_ROLLBACK
                    evv[k] = nis_s
                    if record:
                        rec[r, REC_SNAP_T] = st[S_SNAP_T]
            if accepted:
                # a doubtful fix (beyond the soft gate, or after rejections; not after as many as
                # a relocation needs, when the state is lost anyway): keep the state without it,
                # to fall back on if later fixes disagree with the one it leads to
                doubtful = (nis > prm[P_SOFT_GATE] or st[S_N_REJ] > 0.0) and st[S_N_REJ] < prm[P_RELOC_N]
                # only without a measured velocity: a fix with Doppler speed/course observes the
                # velocity itself, so a position jump cannot teach the state a false one
                if doubtful and math.isfinite(_measured_velocity(prm, row)[0]):
                    doubtful = False
                # (not at a rollback: its fix is judged by the state before the doubtful ones)
                if not was and st[S_SNAP] == 0.0 and doubtful and rec_kind != K_ROLLBACK:
                    for i in range(KF_SIZE):
                        st[S_SNAP_X + i] = prior[i]
                    st[S_SNAP_T] = t
                    st[S_SNAP] = 1.0
                st[S_N_REJ] = 0.0
                st[S_CAND_N] = 0.0
            else:
                ev[k] |= EV_REJECT
                evv[k] = nis
                st[S_N_REJ] += 1.0
                # candidate relocation: consistent with the previous rejected fix?
                c = int(st[S_CAND_N])
                if c > 0:
                    j = c - 1
                    dtc = t - cand[j, 0]
                    tol = math.sqrt(prm[P_GATE] * (rh + cand[j, 4] * cand[j, 4])) + prm[P_MAX_SPEED] * dtc
                    if math.hypot(n - cand[j, 1], e - cand[j, 2]) > tol:
                        c = 0
                if c >= CAND_MAX:
                    for j in range(CAND_MAX - 1):
                        for q in range(5):
                            cand[j, q] = cand[j + 1, q]
                    c = CAND_MAX - 1
                cand[c, 0], cand[c, 1], cand[c, 2], cand[c, 3], cand[c, 4] = t, n, e, d, row[I_SIG_H]
                c += 1
                st[S_CAND_N] = c
                # while parked a relocation is a departure: the departure test decides (below)
                reloc = not was and c >= prm[P_RELOC_N] and t - cand[0, 0] >= prm[P_RELOC_MIN_S]
                forced = not was and st[S_N_REJ] >= prm[P_MAX_REJ]
                if reloc or forced:
                    jump = math.hypot(yn, ye)
                    _init_filter(st, prm, kf, row, n, e, d)
                    if reloc and c >= 2 and t > cand[0, 0]:
                        span = t - cand[0, 0]
                        kf[AX_N + 1] = (n - cand[0, 1]) / span
                        kf[AX_E + 1] = (e - cand[0, 2]) / span
                    ev[k] |= EV_RELOCATE if reloc else EV_FORCED
                    evv[k] = jump
                    kind = K_SEGMENT
                    for i in range(KF_SIZE):
                        prior[i] = kf[i]
            # --- static decision
            static = was
            # while static every fix counts for the spread test: the fixes the hold rejects are
            # the first sign of leaving (only the accepted ones would keep it parked for ever)
            if accepted or kind == K_SEGMENT or was:
                if kind != K_SEGMENT:
                    i = int(st[S_RING_N]) % RING_MAX
                    ring[i, 0], ring[i, 1], ring[i, 2], ring[i, 3] = t, n, e, row[I_SIG_H]
                    st[S_RING_N] += 1.0
                sp = row[I_SPEED]
                acc_std = math.nan
                if row[I_ACC_N] >= 2.0:
                    m1 = row[I_ACC_S1] / row[I_ACC_N]
                    acc_std = math.sqrt(max(0.0, row[I_ACC_S2] / row[I_ACC_N] - m1 * m1))
                # consecutive fixes above the entry threshold: walking pace, under the exit speed
                if math.isfinite(sp) and sp > prm[P_SPEED_THR]:
                    st[S_SPEED_RUN] += 1.0
                else:
                    st[S_SPEED_RUN] = 0.0
                moved = row[I_MOTION] == 1.0 or (math.isfinite(acc_std) and acc_std > prm[P_ACC_MOVE])
                if was and kind == K_FILTER:
                    # parked: the departure test against the held position (module docstring)
                    if _departed(st, prm, kf, n, e, rh, t, sp, row[I_SACC], dt) and not moved:
                        span = t - st[S_DEP_T] if st[S_DEP_N] > 0.0 else 0.0
                        pn, pe = st[S_DEP_PN], st[S_DEP_PE]
                        _init_filter(st, prm, kf, row, n, e, d)
                        if span > 0.0 and not math.isfinite(_measured_velocity(prm, row)[0]):
                            vn_r, ve_r = (n - pn) / span, (e - pe) / span
                            if math.isfinite(sp):
                                # no faster than the departure's reach allows (reported speeds):
                                # a jump fix ending the run must not give the track its velocity
                                sv = max(row[I_SACC] if math.isfinite(row[I_SACC]) else 0.0, prm[P_VEL_SIGMA])
                                f = (st[S_DEP_VMAX] + 3.0 * sv) / max(math.hypot(vn_r, ve_r), 1e-9)
                                if f < 1.0:
                                    vn_r, ve_r = vn_r * f, ve_r * f
                            kf[AX_N + 1], kf[AX_E + 1] = vn_r, ve_r
                        ev[k] &= ~EV_REJECT
                        evv[k] = span
                        ev[k] |= EV_DEPART
                        kind = K_SEGMENT
                        # after every departure the next static period needs more than one slow
                        # fix (below)
                        st[S_DEP_N] = -1.0
                        for i in range(KF_SIZE):
                            prior[i] = kf[i]
                    static = not moved and kind != K_SEGMENT
                elif was:
                    static = False
                else:
                    thr = prm[P_SPEED_THR]
                    veto = (math.isfinite(sp) and sp > thr) or st[S_SPEED_RUN] >= prm[P_EXIT_RUN] or moved
                    # the spread test only when the other rules leave the decision open (same result)
                    spread = -1 if veto else _spread_static(st, prm, ring, t, work)
                    veto = veto or spread == 0
                    evidence = (
                        (math.isfinite(sp) and sp < thr)
                        or row[I_MOTION] == 0.0
                        or row[I_IGNITION] == 0.0
                        or spread == 1
                        or (math.isfinite(acc_std) and acc_std < prm[P_ACC_THR])
                    )
                    static = evidence and not veto and kind != K_SEGMENT
                    if st[S_DEP_N] < 0.0:
                        # since a departure (S_DEP_N = -1 - the fixes with static evidence since):
                        # one slow fix does not park the device again, as many as leave it do
                        # (exit_speed_fixes, counted, not necessarily consecutive), or the spread
                        # test; else a departure confirmed on a jump fix would hold at that fix
                        if static:
                            st[S_DEP_N] -= 1.0
                        static = static and (spread == 1 or -st[S_DEP_N] - 1.0 >= prm[P_EXIT_RUN])
            if static != was:
                st[S_STATIC] = 1.0 if static else 0.0
                st[S_IN_JUMP] = 0.0  # the departure test's jump tracking starts afresh
                ev[k] |= EV_STATIC_START if static else EV_STATIC_END
                lowpass3_reset(st[S_LP:S_LP_END])
            # --- measurement updates
            src = SRC_DR
            if kind == K_FILTER and accepted:
                have_d = math.isfinite(d)
                if have_d and st[S_HAVE_D] == 0.0:
                    init_axis(kf, AX_D, d, 0.0, row[I_SIG_V] ** 2, prm[P_INIT_VEL_STD] ** 2)
                    st[S_HAVE_D] = 1.0
                    have_d = False  # the fix's height is in the reset
                if static:
                    src = SRC_LOWPASS
                    if not was:  # the fix that starts a static period still counts as a fix
                        update_axis(kf, AX_N, 0, n, rh)
                        update_axis(kf, AX_E, 0, e, rh)
                        if have_d:
                            update_axis(kf, AX_D, 0, d, row[I_SIG_V] ** 2)
                    for a in (AX_N, AX_E, AX_D):
                        update_axis(kf, a, 1, 0.0, prm[P_ZUPT] * prm[P_ZUPT])
                    if prm[P_USE_LOWPASS] != 0.0 and lowpass3_push(
                        st[S_LP:S_LP_END],
                        lp1,
                        lp2,
                        lp3,
                        n1,
                        n2,
                        n3,
                        n,
                        e,
                        d if math.isfinite(d) else kf[AX_D],
                    ):
                        dt_fix = t - st[S_T_FIX] if 0.0 < t - st[S_T_FIX] <= 2.5 else 1.0
                        n_eff = 1.0 + lowpass3_n_fixes(st[S_LP:S_LP_END], n1, n2, n3) * dt_fix / (
                            2.0 * prm[P_LP_TAU]
                        )
                        st[S_LP_VAR] = rh / n_eff
                        update_axis(kf, AX_N, 0, st[S_LP_N], rh / n_eff)
                        update_axis(kf, AX_E, 0, st[S_LP_E], rh / n_eff)
                        if math.isfinite(d) and st[S_HAVE_D] != 0.0:
                            update_axis(kf, AX_D, 0, st[S_LP_D], row[I_SIG_V] ** 2 / n_eff)
                else:
                    src = SRC_FIX
                    update_axis(kf, AX_N, 0, n, rh)
                    update_axis(kf, AX_E, 0, e, rh)
                    if have_d:
                        update_axis(kf, AX_D, 0, d, row[I_SIG_V] ** 2)
                    vn, ve, vd = _measured_velocity(prm, row)
                    if prm[P_USE_VEL] != 0.0 and math.isfinite(vn):
                        sv = (
                            row[I_SACC]
                            if math.isfinite(row[I_SACC]) and row[I_SACC] > 0.0
                            else prm[P_VEL_SIGMA]
                        )
                        rv = sv * sv
                        yv0, yv1 = vn - kf[AX_N + 1], ve - kf[AX_E + 1]
                        nv = yv0 * yv0 / (kf[AX_N + 4] + rv) + yv1 * yv1 / (kf[AX_E + 4] + rv)
                        if nv <= prm[P_VEL_GATE]:
                            update_axis(kf, AX_N, 1, vn, rv)
                            update_axis(kf, AX_E, 1, ve, rv)
                            if math.isfinite(vd) and st[S_HAVE_D] != 0.0:
                                update_axis(kf, AX_D, 1, vd, rv)
                st[S_T_FIX] = t
                st[S_N_USED] += 1.0
                st[S_FLOOR_N] = st[S_FLOOR_E] = rh
            elif kind == K_SEGMENT:
                src = SRC_FIX
                st[S_T_FIX] = t
                st[S_N_USED] += 1.0
            elif static:
                src = SRC_LOWPASS
            if static and not was:
                st[S_HOLD_N], st[S_HOLD_E], st[S_HOLD_D] = kf[AX_N], kf[AX_E], kf[AX_D]
                st[S_DEP_N] = 0.0
                st[S_T_STILL] = t
                st[S_DEP_VMAX] = 0.0
        if kind == K_SEGMENT and st[S_INIT] != 0.0 and ev[k] & EV_INIT:
            st[S_N_USED] += 1.0
        # --- output row
        floats[C_T, r] = t
        pos = np.empty(3)
        vel = np.empty(3)
        if static:
            if st[S_LP_HAVE] != 0.0:
                pos[0], pos[1], pos[2] = st[S_LP_N], st[S_LP_E], st[S_LP_D]
            else:
                pos[0], pos[1], pos[2] = st[S_HOLD_N], st[S_HOLD_E], st[S_HOLD_D]
            vel[:] = 0.0
        else:
            pos[0], pos[1], pos[2] = kf[AX_N], kf[AX_E], kf[AX_D]
            vel[0], vel[1], vel[2] = kf[AX_N + 1], kf[AX_E + 1], kf[AX_D + 1]
        # parked on the low-pass: no surer than its own variance (repeated updates with one
        # correlated average would shrink P without bound); and never than the last fix's own
        pv = st[S_LP_VAR] if static and st[S_LP_HAVE] != 0.0 else 0.0
        sn, se = max(kf[AX_N + 2], pv, st[S_FLOOR_N]), max(kf[AX_E + 2], pv, st[S_FLOOR_E])
        write_position(floats, r, pos, vel, math.sqrt(sn), math.sqrt(se), frame)
        if st[S_HAVE_D] == 0.0:
            floats[3, r] = math.nan  # C_HEIGHT
            floats[6, r] = math.nan  # C_DOWN
            floats[9, r] = math.nan  # C_VD
        static_out[r] = static
        source_out[r] = src
        if record:
            _write_record(rec, r, t, rec_kind if kind == K_FILTER else kind, static, prior, kf, qf)
            rec[r, REC_SIG] = row[I_SIG_H]
        r += 1
    return i1, r, F_DONE
