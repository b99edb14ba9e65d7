"""Every array layout of the ``eskf`` engine, declared once.

The compiled code keeps its state in flat float64 arrays (STYLE §5, §7); each is declared
here as a :class:`Layout`, a list of named blocks in order, and the offsets are what the
declaration gives, never written by hand:

``ERROR_STATE``
    The error state ``dx`` and the rows / columns of ``P`` (the measurement models, the
    transition, the smoother's corrections). Blocks ``POS`` ... ``SA`` as slices, their first
    index as ``POS_0`` ... for the compiled code (which takes no slices).
``NOISE``
    The process-noise record :attr:`EskfEngine.noise` (``NZ_*``), built by
    :func:`~iotnav.engines.eskf.config.noise_vector`; read by the transition and the
    covariance propagation.
``ACC``
    The accumulator of the strapdown step between covariance propagations (``ACC_*``).
``ST``
    The hot scalar state :attr:`EskfEngine.st` of the IMU path (``E_*``): flags as 0/1, times
    in s, counters, small vectors.
``PRM``
    The parameters :attr:`EskfEngine.prm` of the compiled IMU path (``Q_*``), built by
    :func:`~iotnav.engines.eskf.kernel.params`.
``REC``
    A row of the event / NIS record buffer :attr:`EskfEngine.rec` (``R_*``).

:meth:`Layout.describe` prints any of them (``python -c "from iotnav.engines.eskf import
layout; print(layout.ST.describe())"``).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import numpy.typing as npt

FloatArray = npt.NDArray[np.float64]


@dataclass
class Layout:
    """Consecutive named blocks of a flat float64 array.

    Parameters
    ----------
    name : str
        What the array is (for :meth:`describe`).

    Attributes
    ----------
    size : int
        Elements declared so far.
    blocks : dict of str to (slice, str)
        Each block's elements and its description (unit and frame).
    """

    name: str
    size: int = 0
    blocks: dict[str, tuple[slice, str]] = field(default_factory=dict)

    def add(self, name: str, size: int = 1, doc: str = "") -> int:
        """Declare the next block; returns its first index."""
        if name in self.blocks:
            raise ValueError(f"{self.name}: {name} declared twice")
        start = self.size
        self.blocks[name] = (slice(start, start + size), doc)
        self.size += size
        return start

    def block(self, name: str, size: int, doc: str = "") -> slice:
        """Declare the next block; returns its slice."""
        start = self.add(name, size, doc)
        return slice(start, start + size)

    def describe(self) -> str:
        """One line per block: indices, name, description."""
        lines = [f"{self.name} ({self.size} elements)"]
        for name, (sl, doc) in self.blocks.items():
            where = f"{sl.start}" if sl.stop - sl.start == 1 else f"{sl.start}-{sl.stop - 1}"
            lines.append(f"  {where:>7}  {name:<16} {doc}")
        return "\n".join(lines)


# ----------------------------------------------------------------------------- error state
#: The error state (true = estimate (+) error; :mod:`iotnav.engines.eskf.models`).
ERROR_STATE = Layout("error state dx")
POS = ERROR_STATE.block("POS", 3, "position error dp, m, n")
VEL = ERROR_STATE.block("VEL", 3, "velocity error dv, m/s, n")
ATT = ERROR_STATE.block("ATT", 3, "attitude error dth, rad, n (C_true = exp([dth x]) C_nb)")
BG = ERROR_STATE.block("BG", 3, "gyro bias error, rad/s, b")
BA = ERROR_STATE.block("BA", 3, "accelerometer bias error, m/s^2, b")
MNT = ERROR_STATE.block("MNT", 3, "mount error dmu, rad, v (C_vb_true = exp([dmu x]) C_vb)")
GNE = ERROR_STATE.block("GNE", 3, "GNSS position error as output (smoothed), m, n")
GNM = ERROR_STATE.block("GNM", 3, "GNSS Gauss-Markov error before the receiver's filter, m, n")
#: Error-state size without the scale-factor states.
N_BASE = ERROR_STATE.size
SG = ERROR_STATE.block("SG", 3, "gyro scale-factor error (optional)")
SA = ERROR_STATE.block("SA", 3, "accelerometer scale-factor error (optional)")
#: Error-state size with the scale-factor states.
N_FULL = ERROR_STATE.size
#: First index of each block (for the compiled kernels, which take no slices).
POS_0, VEL_0, ATT_0, BG_0, BA_0, MNT_0, GNE_0, GNM_0, SG_0, SA_0 = (
    s.start for s in (POS, VEL, ATT, BG, BA, MNT, GNE, GNM, SG, SA)
)
#: Standard gravity, m/s^2 (the kinematic acceleration of the cross-axis noise; the local
#: value differs by < 0.03 m/s^2, negligible there).
G_STD = 9.80665


def n_states(scale_factors: bool) -> int:
    """Error-state dimension for the chosen layout."""
    return N_FULL if scale_factors else N_BASE


# ----------------------------------------------------------------------------- process noise
#: The process-noise record (:func:`~iotnav.engines.eskf.config.noise_vector`; the model in
#: :mod:`iotnav.engines.eskf.models`).
NOISE = Layout("process noise")
NZ_ACC_WHITE = NOISE.add("ACC_WHITE", 1, "N_a^2, accelerometer white noise, (m/s^2)^2/Hz")
NZ_GYRO_WHITE = NOISE.add("GYRO_WHITE", 1, "N_g^2, gyro white noise, (rad/s)^2/Hz")
NZ_ACC_BIAS = NOISE.add("ACC_BIAS", 1, "2 s_ba^2 / T_c, accelerometer bias driving intensity")
NZ_GYRO_BIAS = NOISE.add("GYRO_BIAS", 1, "2 s_bg^2 / T_c, gyro bias driving intensity")
NZ_ACC_BIAS_DECAY = NOISE.add("ACC_BIAS_DECAY", 1, "1/T_a, decay of the accelerometer bias error, 1/s")
NZ_GYRO_BIAS_DECAY = NOISE.add("GYRO_BIAS_DECAY", 1, "1/T_g, decay of the gyro bias error, 1/s")
NZ_MOUNT_RW = NOISE.add("MOUNT_RW", 1, "mount random-walk intensity, rad^2/s")
NZ_SCALE_RW = NOISE.add("SCALE_RW", 1, "scale-factor random-walk intensity, 1/s")
NZ_GNSS_H = NOISE.add("GNSS_H", 1, "horizontal GNSS-error driving intensity, m^2/s (set per fix)")
NZ_GNSS_V = NOISE.add("GNSS_V", 1, "vertical GNSS-error driving intensity, m^2/s (set per fix)")
NZ_INV_TE_H = NOISE.add("INV_TE_H", 1, "1/T_e, horizontal GNSS-error correlation, 1/s")
NZ_K_W = NOISE.add("K_W", 1, "k_w, gyro cross-axis attitude noise, s")
NZ_K_A = NOISE.add("K_A", 1, "k_a, accelerometer cross-axis bias noise, 1/s")
NZ_K_S = NOISE.add("K_S", 1, "k_s, unestimated gyro scale-factor attitude noise, s")
NZ_INV_TF = NOISE.add("INV_TF", 1, "1/t_f, receiver position smoothing, 1/s (0: none)")
NZ_INV_TE_V = NOISE.add("INV_TE_V", 1, "1/T_e, vertical GNSS-error correlation, 1/s")
NOISE_SIZE = NOISE.size
#: Entries a shorter (older, positional) noise vector may leave out, with the value taken then:
#: the first 12 entries are required; ``K_A``, ``K_S``, ``INV_TF`` default to 0 and ``INV_TE_V``
#: to ``INV_TE_H``.
NOISE_REQUIRED = NZ_K_A


def noise_record(noise: FloatArray) -> FloatArray:
    """The full :data:`NOISE` record from a vector of its first 12 to 16 entries.

    The compiled code reads every entry by name and takes only the full record; vectors
    written before the optional entries existed (12 to 15 entries) are completed with the
    defaults of :data:`NOISE_REQUIRED`.

    Raises
    ------
    ValueError
        For fewer than 12 or more than :data:`NOISE_SIZE` entries.
    """
    v = np.ascontiguousarray(noise, dtype=np.float64).reshape(-1)
    m = v.shape[0]
    if m == NOISE_SIZE:
        return v
    if not NOISE_REQUIRED <= m <= NOISE_SIZE:
        raise ValueError(f"eskf noise: {m} entries, expected {NOISE_REQUIRED} to {NOISE_SIZE}")
    out = np.zeros(NOISE_SIZE)
    out[:m] = v
    if m <= NZ_INV_TE_V:
        out[NZ_INV_TE_V] = v[NZ_INV_TE_H]
    return out


# ----------------------------------------------------------------------------- accumulator
#: Time integrals of the strapdown step between covariance propagations
#: (:func:`~iotnav.engines.eskf.propagation.propagate_nominal`).
ACC = Layout("strapdown accumulator")
ACC_T = ACC.add("T", 1, "interval length, s")
ACC_FN = ACC.block("FN", 3, "integral of f_n, m/s")
ACC_FB = ACC.block("FB", 3, "integral of f_b, m/s")
ACC_WB = ACC.block("WB", 3, "integral of omega_b, rad")
ACC_C = ACC.block("C", 9, "integral of C_nb (row-major), s")
ACC_FN_0, ACC_FB_0, ACC_WB_0, ACC_C_0 = ACC_FN.start, ACC_FB.start, ACC_WB.start, ACC_C.start
ACC_SIZE = ACC.size

# ----------------------------------------------------------------------------- hot engine state
#: The hot engine state ``EskfEngine.st``; the engine's attributes of the same names read and
#: write it (descriptors :class:`~iotnav.engines.base.StateSlot` and kin).
ST = Layout("hot engine state st")
E_HAVE_IMU = ST.add("HAVE_IMU", 1, "a raw IMU sample is pending (flag)")
E_T_STATE = ST.add("T_STATE", 1, "time of the nominal state, s")
E_LEVELLED = ST.add("LEVELLED", 1, "levelling done (flag)")
E_LEVEL_N = ST.add("LEVEL_N", 1, "samples in the levelling window")
E_LEVEL_T0 = ST.add("LEVEL_T0", 1, "start of the levelling window, s")
E_HEADING_OK = ST.add("HEADING_OK", 1, "heading initialised (flag)")
E_POS_OK = ST.add("POS_OK", 1, "position initialised (flag)")
E_MOUNT_OK = ST.add("MOUNT_OK", 1, "mount known (flag)")
E_STATIC = ST.add("STATIC", 1, "block 3 says static (flag)")
E_STATIC_SEEN = ST.add("STATIC_SEEN", 1, "a static period was seen (flag)")
E_T_SPEED = ST.add("T_SPEED", 1, "time of the latest GNSS speed, s")
E_LAST_SPEED = ST.add("LAST_SPEED", 1, "latest GNSS speed, m/s")
E_T_PREFILT = ST.add("T_PREFILT", 1, "time of the static prefilter, s")
E_T_NHC = ST.add("T_NHC", 1, "time of the latest NHC, s")
E_T_ZUPT = ST.add("T_ZUPT", 1, "time of the latest ZUPT, s")
E_ZARU_N = ST.add("ZARU_N", 1, "gyro samples summed for the ZARU")
E_T_ZARU = ST.add("T_ZARU", 1, "start of the ZARU sum, s")
E_T_FIX = ST.add("T_FIX", 1, "time of the latest accepted fix, s")
E_N_IMU = ST.add("N_IMU", 1, "IMU samples processed")
E_HAS_FRAME = ST.add("HAS_FRAME", 1, "NED origin set (flag)")
E_LAT0 = ST.add("LAT0", 1, "origin latitude, deg")
E_LON0 = ST.add("LON0", 1, "origin longitude, deg")
E_H0 = ST.add("H0", 1, "origin height, m")
E_KN = ST.add("KN", 1, "metres per degree of latitude at the origin")
E_KE = ST.add("KE", 1, "metres per degree of longitude at the origin")
E_HAS_FIX = ST.add("HAS_FIX", 1, "a valid fix was seen (flag)")
E_FIX_T = ST.add("FIX_T", 1, "time of the latest valid fix, s")
E_NREC = ST.add("NREC", 1, "rows used in the record buffer rec")
E_FIX_Z = ST.add("FIX_Z", 3, "latest fix position, m, NED")
E_FIX_V = ST.add("FIX_V", 3, "latest fix velocity, m/s, NED")
E_F_PEND = ST.add("F_PEND", 3, "pending raw specific force, m/s^2, b")
E_W_PEND = ST.add("W_PEND", 3, "pending raw angular rate, rad/s, b")
E_F_N_LP = ST.add("F_N_LP", 3, "low-passed C_nb f_b (block 3's input), m/s^2, n")
E_ZARU_SUM = ST.add("ZARU_SUM", 3, "raw gyro sum for the ZARU, rad/s")
E_LEVEL_SUM = ST.add("LEVEL_SUM", 7, "levelling sums: f (3), omega (3), |f|^2")
# RTS smoothing (package docstring, "RTS smoothing")
E_SM_ON = ST.add("SM_ON", 1, "smoothing records being written (flag)")
E_SM_PEND = ST.add("SM_PEND", 1, "a record is open: prior saved, updates being summed (flag)")
E_SM_T = ST.add("SM_T", 1, "time of the open record, s")
E_SM_COUNT = ST.add("SM_COUNT", 1, "covariance propagations since the latest record")
E_SM_N = ST.add("SM_N", 1, "records in the smoothing buffer")
# gravity aiding before the heading (package docstring, "Initialisation")
E_GRAV_SUM = ST.add("GRAV_SUM", 3, "raw specific-force sum over the aiding interval, m/s^2")
E_GRAV_N = ST.add("GRAV_N", 1, "samples in that sum")
E_T_GRAV = ST.add("T_GRAV", 1, "start of the aiding interval, s")
E_A_GNSS = ST.add("A_GNSS", 1, "GNSS-derived horizontal acceleration, m/s^2")
E_SA_GNSS = ST.add("SA_GNSS", 1, "its 1-sigma, m/s^2")
E_T_A_GNSS = ST.add("T_A_GNSS", 1, "its time, s")
E_GRAV_REJ = ST.add("GRAV_REJ", 1, "consecutive rejected gravity updates")
E_GRAV_RESETS = ST.add("GRAV_RESETS", 1, "gravity re-openings (tilt covariance widened)")
#: Size of the hot state before the per-fix uncertainty slots below (checkpoints written then
#: hold this many entries; :meth:`~iotnav.engines.eskf.core.EskfCore.__setstate__` completes them).
E_SIZE_V1 = ST.size
# the claimed sigma of the last fix moved on at its velocity, before the heading (package
# docstring, "Initialisation"; :func:`~iotnav.engines.eskf.kernel._output_row_nb`)
E_FIX_SIG = ST.add("FIX_SIG", 2, "latest valid fix: reported 1-sigma of its position, m, north and east")
E_FIX_SV = ST.add("FIX_SV", 1, "latest valid fix: 1-sigma of each velocity component it is moved on at, m/s")
E_FIX_ACC = ST.add("FIX_ACC", 1, "1-sigma of the unknown horizontal acceleration after that fix, m/s^2")
E_FIX_REACH = ST.add("FIX_REACH", 1, "1-sigma bound of each velocity component's change after that fix, m/s")
E_A_MS = ST.add("A_MS", 1, "running mean square of the GNSS-derived horizontal acceleration, (m/s^2)^2")
E_T_A_MS = ST.add("T_A_MS", 1, "time of that mean square, s")
E_SIZE = ST.size

# ----------------------------------------------------------------------------- parameters
#: The parameters ``EskfEngine.prm`` of the compiled IMU path (SI, from :class:`EskfConfig`).
PRM = Layout("parameters prm")
Q_COV_INTERVAL = PRM.add("COV_INTERVAL", 1, "cov_interval_s, s")
Q_PREFILT_TAU = PRM.add("PREFILT_TAU", 1, "static_prefilter_tau_s, s")
Q_ZUPT_MAX_ACC = PRM.add("ZUPT_MAX_ACC", 1, "zupt_max_acc_mps2, m/s^2")
Q_ZUPT_MAX_GNSS_SPEED = PRM.add("ZUPT_MAX_GNSS_SPEED", 1, "zupt_max_gnss_speed_mps, m/s")
Q_ZUPT_INTERVAL = PRM.add("ZUPT_INTERVAL", 1, "zupt_interval_s, s")
Q_ZUPT_NOISE = PRM.add("ZUPT_NOISE", 1, "zupt_noise_mps, m/s")
Q_ZARU_INTERVAL = PRM.add("ZARU_INTERVAL", 1, "zaru_interval_s, s")
Q_ND_G = PRM.add("ND_G", 1, "gyro noise density, rad/s/sqrt(Hz)")
Q_ZARU_FLOOR = PRM.add("ZARU_FLOOR", 1, "zaru_floor_dps, rad/s")
Q_NHC = PRM.add("NHC", 1, "nhc (flag)")
Q_NHC_INTERVAL = PRM.add("NHC_INTERVAL", 1, "nhc_interval_s, s")
Q_NHC_MIN_SPEED = PRM.add("NHC_MIN_SPEED", 1, "nhc_min_speed_mps, m/s")
Q_NHC_LAT = PRM.add("NHC_LAT", 1, "nhc_lateral_noise_mps, m/s")
Q_NHC_VERT = PRM.add("NHC_VERT", 1, "nhc_vertical_noise_mps, m/s")
Q_LEVEL_TIME = PRM.add("LEVEL_TIME", 1, "level_time_s, s")
Q_FIX_HOLD = PRM.add("FIX_HOLD", 1, "fix_hold_s, s")
Q_FIX_STD = PRM.add("FIX_STD", 1, "per-axis sigma of a fix without accuracy figures (DOP defaults), m")
Q_EST_MOUNT = PRM.add("EST_MOUNT", 1, "estimate_mount (flag)")
Q_GATE1 = PRM.add("GATE1", 1, "NIS gate, 1 dof")
Q_GATE2 = PRM.add("GATE2", 1, "NIS gate, 2 dof")
Q_GATE3 = PRM.add("GATE3", 1, "NIS gate, 3 dof")
Q_RECORD_EVERY = PRM.add("RECORD_EVERY", 1, "record_every (propagations)")
Q_GRAV = PRM.add("GRAV", 1, "gravity_aiding (flag)")
Q_GRAV_INTERVAL = PRM.add("GRAV_INTERVAL", 1, "gravity_interval_s, s")
Q_GRAV_MAX_ACC = PRM.add("GRAV_MAX_ACC", 1, "gravity_max_acc_mps2, m/s^2")
Q_ND_A = PRM.add("ND_A", 1, "accelerometer noise density, m/s^2/sqrt(Hz)")
Q_GRAV_MAX_REJ = PRM.add("GRAV_MAX_REJ", 1, "max_gravity_rejections")
Q_GRAV_REOPEN_STD = PRM.add("GRAV_REOPEN_STD", 1, "gravity_reopen_std_rad, rad")
PRM_SIZE = PRM.size

# ----------------------------------------------------------------------------- records
#: A row of the record buffer ``EskfEngine.rec``, written by the compiled code and turned into
#: ``events`` / ``nis_log`` entries in order by ``EskfEngine._flush``.
REC = Layout("record row")
R_KIND = REC.add("KIND", 1, "REC_STATIC_END, REC_STATIC_START or REC_UPDATE")
R_T = REC.add("T", 1, "time, s")
R_MEAS = REC.add("MEAS", 1, "measurement code (index into MEAS_NAMES)")
R_NIS = REC.add("NIS", 1, "normalised innovation squared")
R_DOF = REC.add("DOF", 1, "measurement size")
R_ACC = REC.add("ACC", 1, "accepted (flag)")
R_RATIO = REC.add("RATIO", 1, "NIS / gate")
REC_SIZE = REC.size
#: Record kinds.
REC_STATIC_END, REC_STATIC_START, REC_UPDATE = 0, 1, 2
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
#: Order of the nominal-state arrays handed to the compiled code (:meth:`Nominal.arrays`).
NOMINAL_ARRAYS = ("C_nb", "v_n", "p_n", "b_g", "b_a", "s_g", "s_a", "C_vb", "e_n", "e_gm")
