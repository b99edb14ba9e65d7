"""Layouts of the ``eskf`` arrays: error state, hot engine state ``st``, parameters ``prm``, records."""

from __future__ import annotations

import numpy as np
import numpy.typing as npt

FloatArray = npt.NDArray[np.float64]


# ----------------------------------------------------------------------------- layout
POS = slice(0, 3)
VEL = slice(3, 6)
ATT = slice(6, 9)
BG = slice(9, 12)
BA = slice(12, 15)
MNT = slice(15, 18)
GNE = slice(18, 21)
GNM = slice(21, 24)
SG = slice(24, 27)
SA = slice(27, 30)
#: Error-state size without / with scale-factor states.
N_BASE = 24
N_FULL = 30
#: Standard gravity, m/s^2 (the kinematic acceleration of the cross-axis noise; the local
#: value differs by < 0.03 m/s^2, negligible there).
G_STD = 9.80665
#: First index of each block (for the compiled kernels, which take no slices).
POS_0, VEL_0, ATT_0, BG_0, BA_0, MNT_0, GNE_0, GNM_0, SG_0, SA_0 = 0, 3, 6, 9, 12, 15, 18, 21, 24, 27


def n_states(scale_factors: bool) -> int:
    """Error-state dimension for the chosen layout."""
    return N_FULL if scale_factors else N_BASE


# ----------------------------------------------------------------------------- compiled IMU path
# Hot engine state, one float64 array ``EskfEngine.st`` (flags as 0/1, times in s); the
# engine's attributes of the same names read and write it (descriptors :class:`~iotnav.engines.base.StateSlot` and kin).
(
    E_HAVE_IMU,
    E_T_STATE,
    E_LEVELLED,
    E_LEVEL_N,
    E_LEVEL_T0,
    E_HEADING_OK,
    E_POS_OK,
    E_MOUNT_OK,
    E_STATIC,
    E_STATIC_SEEN,
    E_T_SPEED,
    E_LAST_SPEED,
    E_T_PREFILT,
    E_T_NHC,
    E_T_ZUPT,
    E_ZARU_N,
    E_T_ZARU,
    E_T_FIX,
    E_N_IMU,
    E_HAS_FRAME,
    E_LAT0,
    E_LON0,
    E_H0,
    E_KN,
    E_KE,
    E_HAS_FIX,
    E_FIX_T,
    E_NREC,
) = range(28)
#: Vectors in ``st``: last fix position (m, NED) and velocity (m/s), pending raw IMU sample,
#: low-passed ``C_nb f_b``, ZARU gyro sum, levelling sums (sum f, sum w, sum |f|^2).
E_FIX_Z, E_FIX_V, E_F_PEND, E_W_PEND, E_F_N_LP, E_ZARU_SUM, E_LEVEL_SUM = 28, 31, 34, 37, 40, 43, 46
#: RTS smoothing (module docstring): recording on, a record open (its prior saved, its updates
#: being summed), its time (s), covariance propagations since the last record, records in the buffer.
E_SM_ON, E_SM_PEND, E_SM_T, E_SM_COUNT, E_SM_N = 53, 54, 55, 56, 57
#: Gravity aiding before the heading (module docstring, "Initialisation"): raw accelerometer
#: sum over the aiding interval (3), its count, the interval's start (s); the GNSS-derived
#: horizontal acceleration (m/s^2), its 1-sigma (m/s^2) and time (s).
E_GRAV_SUM, E_GRAV_N, E_T_GRAV, E_A_GNSS, E_SA_GNSS, E_T_A_GNSS = 58, 61, 62, 63, 64, 65
#: consecutive rejected gravity updates; gravity re-openings (tilt covariance widened)
E_GRAV_REJ, E_GRAV_RESETS = 66, 67
E_SIZE = 68

# Parameters, one float64 array ``EskfEngine.prm`` (see ``_params``).
(
    Q_COV_INTERVAL,
    Q_PREFILT_TAU,
    Q_ZUPT_MAX_ACC,
    Q_ZUPT_MAX_GNSS_SPEED,
    Q_ZUPT_INTERVAL,
    Q_ZUPT_NOISE,
    Q_ZARU_INTERVAL,
    Q_ND_G,
    Q_ZARU_FLOOR,
    Q_NHC,
    Q_NHC_INTERVAL,
    Q_NHC_MIN_SPEED,
    Q_NHC_LAT,
    Q_NHC_VERT,
    Q_LEVEL_TIME,
    Q_FIX_HOLD,
    Q_FIX_STD,
    Q_EST_MOUNT,
    Q_GATE1,
    Q_GATE2,
    Q_GATE3,
    Q_RECORD_EVERY,
    Q_GRAV,
    Q_GRAV_INTERVAL,
    Q_GRAV_MAX_ACC,
    Q_ND_A,
    Q_GRAV_MAX_REJ,
    Q_GRAV_REOPEN_STD,
) = range(28)

#: Records written by the compiled code into ``EskfEngine.rec`` (one row each), turned into
#: ``events`` / ``nis_log`` entries in order by ``EskfEngine._flush``: ``kind`` (``REC_*``),
#: ``t`` (s), measurement code (index into :data:`MEAS_NAMES`), NIS, dof, accepted, test ratio.
REC_STATIC_END, REC_STATIC_START, REC_UPDATE = 0, 1, 2
R_KIND, R_T, R_MEAS, R_NIS, R_DOF, R_ACC, R_RATIO = range(7)
REC_ROWS = 256
MEAS_NAMES = ("zupt", "zaru", "nhc", "gnss_position", "gnss_velocity", "mag_heading", "gravity")
MEAS_CODES = {name: k for k, name in enumerate(MEAS_NAMES)}
#: Measurements recorded by ``EskfEngine(record_innovations=True)``.
DEFAULT_RECORDED = ("gnss_position", "gnss_velocity")
#: Kernel return codes: block done; levelling window complete at the returned sample (Python
#: finishes the levelling, then the kernel resumes that sample); record buffer full.
K_DONE, K_LEVEL, K_FLUSH = 0, 1, 2
#: Rows of the smoothing record buffer (:func:`iotnav.engines.smoother.write_record` layout,
#: 22 KB each with 30 states); the kernel returns ``K_FLUSH`` before it could overflow.
SM_ROWS = 64
