"""State, input, parameter and record layouts of the ``fixes`` engine's compiled step.

Moved out of :mod:`iotnav.engines.fixes_kernel` unchanged (which re-exports every name, so
``fixes_kernel.I_T`` and the like still work); the model is described in
:mod:`iotnav.engines.fixes` and the state layout in :mod:`iotnav.engines.fixes_kernel`.
"""

from __future__ import annotations

from iotnav.techniques.lowpass3 import LP_HAVE, LP_N, LP_SIZE

__all__ = [
    "AX_D",
    "AX_E",
    "AX_N",
    "CAND_MAX",
    "EV_BOOT_MOVE",
    "EV_CLOCK",
    "EV_DEPART",
    "EV_FORCED",
    "EV_INIT",
    "EV_REJECT",
    "EV_RELOCATE",
    "EV_ROLLBACK",
    "EV_STATIC_END",
    "EV_STATIC_START",
    "F_DONE",
    "F_NEED_BOOT",
    "I_ACC_N",
    "I_ACC_S1",
    "I_ACC_S2",
    "I_COURSE",
    "I_COURSE_VALID",
    "I_H",
    "I_IGNITION",
    "I_LAT",
    "I_LON",
    "I_MOTION",
    "I_NSV",
    "I_PDOP",
    "I_SACC",
    "I_SIG_H",
    "I_SIG_V",
    "I_SPEED",
    "I_T",
    "I_UTC",
    "I_VALID",
    "I_VD",
    "I_VE",
    "I_VN",
    "KF_SIZE",
    "K_BOOT",
    "K_FILTER",
    "K_ROLLBACK",
    "K_SEGMENT",
    "N_INPUT",
    "PRM_SIZE",
    "P_ACCEPT_UNKNOWN_PDOP",
    "P_ACC_MOVE",
    "P_ACC_THR",
    "P_BOOT_WALK",
    "P_CLOCK_TOL",
    "P_DEP_ACC",
    "P_DEP_GATE",
    "P_EXIT_RUN",
    "P_EXIT_SPEED",
    "P_GATE",
    "P_INIT_VEL_STD",
    "P_LP_N1",
    "P_LP_N2",
    "P_LP_N3",
    "P_LP_TAU",
    "P_MAX_PDOP",
    "P_MAX_REJ",
    "P_MAX_SPEED",
    "P_MIN_COURSE_SPEED",
    "P_MIN_FIXES",
    "P_MIN_SV",
    "P_Q_H",
    "P_Q_V",
    "P_RECORD",
    "P_REJECT_QF",
    "P_RELOC_MIN_S",
    "P_RELOC_N",
    "P_ROLLBACK_S",
    "P_SOFT_GATE",
    "P_SPEED_THR",
    "P_SPREAD_Z",
    "P_STORED_STD",
    "P_USE_LOWPASS",
    "P_USE_VEL",
    "P_VEL_GATE",
    "P_VEL_SIGMA",
    "P_WINDOW_S",
    "P_ZUPT",
    "REASONS",
    "REC_KIND",
    "REC_POST",
    "REC_PRIOR",
    "REC_QF",
    "REC_SIG",
    "REC_SIZE",
    "REC_SNAP_T",
    "REC_STATIC",
    "REC_T",
    "RING_MAX",
    "R_BACKWARDS",
    "R_DUPLICATE",
    "R_FUTURE",
    "R_INVALID",
    "R_NUM_SV",
    "R_OK",
    "R_PAST",
    "R_PDOP",
    "R_PDOP_UNKNOWN",
    "R_REPEAT",
    "R_SETTLING",
    "R_ZERO",
    "SPREAD_OUT",
    "ST_SIZE",
    "ST_SIZE_V1",
    "ST_SIZE_V2",
    "S_CAND_N",
    "S_DECIDED",
    "S_DEP_D0",
    "S_DEP_N",
    "S_DEP_PE",
    "S_DEP_PN",
    "S_DEP_T",
    "S_DEP_VMAX",
    "S_FLOOR_E",
    "S_FLOOR_N",
    "S_GOOD_E",
    "S_GOOD_N",
    "S_GOOD_T",
    "S_HAVE_D",
    "S_HAVE_FRAME",
    "S_HOLD_D",
    "S_HOLD_E",
    "S_HOLD_N",
    "S_INIT",
    "S_IN_JUMP",
    "S_JUMP_E",
    "S_JUMP_N",
    "S_JUMP_T",
    "S_LAT_LAST",
    "S_LON_LAST",
    "S_LP",
    "S_LP_D",
    "S_LP_E",
    "S_LP_END",
    "S_LP_HAVE",
    "S_LP_K1",
    "S_LP_K2",
    "S_LP_K3",
    "S_LP_N",
    "S_LP_SINCE2",
    "S_LP_VAR",
    "S_N_REJ",
    "S_N_USED",
    "S_OFF_CAND",
    "S_OFF_N",
    "S_OFF_REF",
    "S_QF",
    "S_RING_N",
    "S_SNAP",
    "S_SNAP_T",
    "S_SNAP_X",
    "S_SPEED_RUN",
    "S_STATIC",
    "S_T_FIX",
    "S_T_LAST",
    "S_T_MOVE",
    "S_T_STILL",
    "S_T_X",
]

#: Axis blocks of ``kf``: ``[p, v, P_pp, P_pv, P_vv]`` per axis.
AX_N, AX_E, AX_D = 0, 5, 10
KF_SIZE = 15

# Input columns (one row per GNSS epoch).
(
    I_T,
    I_UTC,
    I_LAT,
    I_LON,
    I_H,
    I_VALID,
    I_PDOP,
    I_NSV,
    I_SIG_H,
    I_SIG_V,
    I_SPEED,
    I_COURSE,
    I_COURSE_VALID,
    I_VN,
    I_VE,
    I_VD,
    I_SACC,
    I_MOTION,
    I_IGNITION,
    I_ACC_N,
    I_ACC_S1,
    I_ACC_S2,
) = range(22)
N_INPUT = 22

# Reason codes of skipped epochs (``codes``); names in :data:`REASONS`.
(
    R_OK,
    R_DUPLICATE,
    R_REPEAT,
    R_BACKWARDS,
    R_FUTURE,
    R_PAST,
    R_INVALID,
    R_ZERO,
    R_PDOP,
    R_PDOP_UNKNOWN,
    R_NUM_SV,
    R_SETTLING,
) = range(12)
REASONS: tuple[str, ...] = (
    "",
    "gnss_duplicate",
    "gnss_time_repeat",
    "gnss_time_backwards",
    "gnss_future",
    "gnss_past",
    "gnss_invalid",
    "gnss_zero_position",
    "gnss_pdop",
    "gnss_pdop_unknown",
    "gnss_num_sv",
    "gnss_settling",
)

# Event bits per input row (``ev``), value in ``evv``.
EV_REJECT = 1  # NIS gate rejected the fix (evv: NIS)
EV_RELOCATE = 2  # re-initialised at consistent rejected fixes (evv: jump, m)
EV_FORCED = 4  # re-initialised after too many rejections (evv: jump, m)
EV_STATIC_START = 8
EV_STATIC_END = 16
EV_CLOCK = 32  # UTC offset re-referenced after consistent fixes (evv: change, s)
EV_BOOT_MOVE = 64  # movement seen before the first fix (stored position in use)
EV_INIT = 128  # filter initialised at this fix
EV_ROLLBACK = 256  # fixes accepted since the snapshot retracted (evv: NIS of this fix at the snapshot)
EV_DEPART = 512  # parked: the departure test confirmed a departure (evv: s since its first displaced fix)

# Scalar state (``st``).
(
    S_INIT,
    S_HAVE_FRAME,
    S_DECIDED,
    S_T_LAST,
    S_LAT_LAST,
    S_LON_LAST,
    S_OFF_REF,
    S_OFF_N,
    S_OFF_CAND,
    S_T_X,
    S_HAVE_D,
    S_N_REJ,
    S_CAND_N,
    S_STATIC,
    S_T_MOVE,
    S_RING_N,
    S_HOLD_N,
    S_HOLD_E,
    S_HOLD_D,
    S_LP_HAVE,
    S_LP_N,
    S_LP_E,
    S_LP_D,
    S_LP_K1,
    S_LP_K2,
    S_LP_K3,
    S_LP_SINCE2,
    S_T_FIX,
    S_N_USED,
    S_QF,
    S_SNAP,
    S_SNAP_T,
    S_SPEED_RUN,
    S_DEP_N,
    S_DEP_T,
    S_DEP_PN,
    S_DEP_PE,
    S_DEP_VMAX,
    S_T_STILL,
    S_LP_VAR,
    S_DEP_D0,
    S_SNAP_X,
) = range(42)
#: ``st[S_SNAP_X : S_SNAP_X + KF_SIZE]`` holds the snapshot state (rollback, module docstring of
#: :mod:`iotnav.engines.fixes`). Checkpoints written before the floor slots hold ``ST_SIZE_V1``.
ST_SIZE_V1 = 42 + 15
#: Floor of the forward rows' reported variance, north and east (m^2): the last accepted fix's
#: own, grown by each prediction as ``P_pp`` is (``FixesEngine`` docstring, "Reported uncertainty").
S_FLOOR_N, S_FLOOR_E = ST_SIZE_V1, ST_SIZE_V1 + 1
#: The departure test's jump tracking (``_departed``): the last displaced-run or still fix that was
#: no jump (``S_GOOD_*``: north, east, m; time, s), the latest jump fix (``S_JUMP_*``) and whether
#: the fixes are in a jump now (``S_IN_JUMP``, 0 or 1). Checkpoints written before: ``ST_SIZE_V2``.
ST_SIZE_V2 = ST_SIZE_V1 + 2
S_GOOD_N, S_GOOD_E, S_GOOD_T, S_JUMP_N, S_JUMP_E, S_JUMP_T, S_IN_JUMP = range(ST_SIZE_V2, ST_SIZE_V2 + 7)
ST_SIZE = ST_SIZE_V2 + 7

#: The 3-level low-pass state (:mod:`iotnav.techniques.lowpass3` layout ``LP_*``) inside ``st``.
S_LP = S_LP_HAVE
S_LP_END = S_LP_HAVE + LP_SIZE
assert S_LP_N == S_LP + LP_N and S_LP_SINCE2 == S_LP_END - 1 and LP_HAVE == 0

# Parameters (``prm``), built by :meth:`iotnav.engines.fixes.FixesEngine` from its config.
(
    P_Q_H,
    P_Q_V,
    P_GATE,
    P_VEL_GATE,
    P_RELOC_N,
    P_RELOC_MIN_S,
    P_MAX_REJ,
    P_MAX_SPEED,
    P_MAX_PDOP,
    P_MIN_SV,
    P_ACCEPT_UNKNOWN_PDOP,
    P_SPEED_THR,
    P_WINDOW_S,
    P_MIN_FIXES,
    P_SPREAD_Z,
    P_ACC_THR,
    P_ZUPT,
    P_LP_TAU,
    P_MIN_COURSE_SPEED,
    P_VEL_SIGMA,
    P_INIT_VEL_STD,
    P_STORED_STD,
    P_BOOT_WALK,
    P_CLOCK_TOL,
    P_RECORD,
    P_USE_VEL,
    P_LP_N1,
    P_LP_N2,
    P_LP_N3,
    P_USE_LOWPASS,
    P_REJECT_QF,
    P_ACC_MOVE,
    P_SOFT_GATE,
    P_ROLLBACK_S,
    P_EXIT_RUN,
    P_DEP_ACC,
    P_DEP_GATE,
    P_EXIT_SPEED,
) = range(38)
PRM_SIZE = 38

#: Normalised squared distance from the window's median above which a fix is a gross outlier
#: of the spread test: the 2-dof chi-square quantile at 1 - 1e-6, ``-2 ln(1e-6)``.
SPREAD_OUT = 27.631021115928547
#: Candidate buffer rows (rejected fixes that may be a relocation): ``t, n, e, d, sigma``.
CAND_MAX = 16
#: Ring of recent accepted fixes for the spread test: ``t, n, e, sigma``.
RING_MAX = 256
#: Smoothing record per output row: ``t, kind, static``, ``x-, P-`` (15), ``x+, P+`` (15) and the
#: factor on ``q`` of the prediction into the row.
#: A rollback row also keeps the time of its snapshot (``REC_SNAP_T``); every filter row the
#: fix's reported per-axis horizontal sigma (``REC_SIG``, m; NaN on boot rows), the floor of the
#: offline outputs' reported sigma (``FixesEngine`` docstring, "Reported uncertainty").
REC_T, REC_KIND, REC_STATIC, REC_PRIOR, REC_POST, REC_QF, REC_SNAP_T, REC_SIG = 0, 1, 2, 3, 18, 33, 34, 35
REC_SIZE = 36
#: Record kinds: boot row (not filtered), a filter row, the first row of a filter segment.
#: A rollback row is a filter row whose prior is not the prediction of the previous row's state: the
#: RTS recursion restarts there.
K_BOOT, K_FILTER, K_SEGMENT, K_ROLLBACK = 0.0, 1.0, 2.0, 3.0

# Kernel return flags.
F_DONE, F_NEED_BOOT = 0, 1
