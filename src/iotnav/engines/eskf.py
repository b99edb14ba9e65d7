"""Error-state extended Kalman filter (ESKF) for low-cost GNSS + MEMS IMU (+ magnetometer).

Loosely coupled INS/GNSS in the flat-earth local NED frame of :mod:`iotnav.strapdown`
(Groves 2013, "Principles of GNSS, Inertial, and Multisensor Integrated Navigation
Systems", 2nd ed., ch. 14; Sola 2017, "Quaternion kinematics for the error-state Kalman
filter", §5-§7). The nominal state is integrated at the IMU rate with the same strapdown step
as the simulator; a 21-state (27 with scale factors) error state carries the uncertainty:
position, velocity, attitude, gyro and accelerometer biases (first-order Gauss-Markov, from
the datasheet's bias instability and correlation time), the mounting rotation ``C_vb``, the
time-correlated GNSS position error and optionally the gyro and accelerometer scale factors.
The error-state equations, the discretisation and every measurement model (with its ``H``)
are written out in :mod:`iotnav.engines.eskf_models`.

Wiring per sample
-----------------
IMU
    The previous sample (mean rate and specific force over its interval) is integrated up to
    the new sample's time; the covariance is propagated every ``cov_interval_s`` with the
    interval means (and always before a measurement). Block 3's static detector
    (:class:`iotnav.techniques.static.StaticDetector`) decides static / moving; static:
    zero-velocity and zero-angular-rate updates every ``zupt_interval_s``; moving wheeled
    vehicle with a known mount: the non-holonomic constraint every ``nhc_interval_s``
    (Shin 2005, "Estimation techniques for low-cost inertial navigation", §4.3). One
    :class:`~iotnav.engines.base.Output` is returned per IMU sample.
GNSS
    The nominal state is integrated to the fix time, then position (with lever arm) and
    velocity updates. Velocity is the receiver's NED velocity when present
    (``sample.vn/ve/vd``), else speed and course (horizontal). Noise: ``h_acc_m`` /
    ``v_acc_m`` / ``s_acc_mps`` when the receiver reports them, else DOP x ``uere_m``. The
    position error is split into a white part (``gnss_white_fraction``) and a Gauss-Markov part
    (correlation time ``gnss_corr_time_s``) carried as the ``GNE`` states, so that minutes-long
    correlated receiver errors do not make the filter over-confident.
Magnetometer
    Calibrated (``mag_hard_iron_ut``, ``mag_soft_iron``), heading update every
    ``mag_interval_s``; also gives the initial heading.

GNSS velocity noise
    A receiver that smooths its position (time constant ``gnss_receiver_filter_s``) reports a
    velocity carrying the derivative of the smoothed position error besides the Doppler
    noise of ``s_acc_mps``; that part is time-correlated and enters ``R`` inflated for its
    correlation (:meth:`EskfEngine._gnss_velocity_sigma`).

Every update is gated by its NIS (``gate_probability``); a rejected update becomes an
``update_rejected`` event (``fix_rejected`` for GNSS positions) with NIS and test ratio. After
``max_gnss_rejections`` consecutive rejected fixes the position covariance is inflated and the
next fix is accepted (event ``gate_reset``), so the filter cannot lock itself out. Covariance
updates use the Joseph form and symmetrisation of :mod:`iotnav.kalman`.

Initialisation
--------------
1. Levelling: roll and pitch from the mean accelerometer over ``level_time_s`` (gyro mean as
   the initial gyro bias when the accelerometer is quiet). Levelling absorbs the
   accelerometer bias and scale error, so the tilt covariance is that error over ``g`` and
   fully correlated with it (:func:`eskf_models.level_covariance`; an MPU-6050's 17 mg
   turn-on bias alone is a 1-degree tilt). Anything integrated before is discarded.
   When the yaw is later set, every navigation-frame error is rotated with it
   (:func:`eskf_models.heading_reset_transform`), or the tilt/bias correlation learnt at rest
   would point the wrong way and make the tilt look observable.
2. Heading: magnetometer (if any) or, without one, ``course + mount yaw`` at the first GNSS
   epoch faster than ``align_min_speed_mps`` once the mount yaw is known (``mount_rpy_rad``
   from the configuration, else the first accepted estimate of block 5,
   :class:`iotnav.techniques.mount.MountAligner`). With a magnetometer and no configured
   mount, the mount yaw is ``sensor yaw - course`` at that epoch. Mount roll and pitch are
   the sensor's at that epoch (the vehicle taken as level within ``vehicle_level_std_rad``;
   any mounting, upside down included), their error tied to the sensor tilt error
   (:meth:`EskfEngine._init_mount`); the whole mount is refined as states by the NHC
   (``estimate_mount``). The mount roll is not observable from the NHC (a rotation about
   the direction of travel); it follows the sensor roll through that correlation.
3. Before the heading is known, the output is the last fix extrapolated with the GNSS
   velocity (source ``fix``).

Limitations: flat earth (see :mod:`iotnav.strapdown`); the NHC is applied at the IMU (no
IMU-to-axle lever arm); without a magnetometer the device must move with some acceleration
or turns before the mount yaw, hence the heading, is known.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, cast

import numpy as np
import numpy.typing as npt

from iotnav import kalman
from iotnav.engines import eskf_models as M
from iotnav.engines.base import (
    GnssSample,
    ImuSample,
    MagSample,
    Output,
    Sample,
    TangentPlane,
    output_at,
    output_without_position,
)
from iotnav.engines.config import config_from_toml, dataclass_from_dict
from iotnav.geo import dcm_to_rpy, euler_to_dcm, normal_gravity, rot_z
from iotnav.techniques.mount import MountAligner, MountConfig
from iotnav.techniques.static import StaticConfig, StaticDetector

FloatArray = npt.NDArray[np.float64]

G0 = 9.80665
DEG = math.pi / 180.0
_GM_PEAK = 0.6186  # peak Allan deviation of a unit first-order Gauss-Markov process


@dataclass(frozen=True)
class EskfConfig:
    """Every tunable of the ``eskf`` engine (units in the names; datasheet defaults: MPU-6050).

    Attributes
    ----------
    acc_noise_density_ug_rthz, gyro_noise_density_mdps_rthz : float
        White-noise densities (velocity / angle random walk).
    acc_turn_on_bias_mg, gyro_turn_on_bias_dps : float
        1-sigma turn-on biases (initial bias covariance).
    acc_bias_instability_mg, gyro_bias_instability_dph : float
        Allan-deviation floors; Gauss-Markov sigma = value / 0.6186.
    bias_correlation_time_s : float
        Gauss-Markov correlation time of both biases.
    estimate_scale_factors : bool
        Add gyro and accelerometer scale-factor states (27 states instead of 21).
    acc_scale_factor_pct, gyro_scale_factor_pct : float
        1-sigma scale-factor errors (initial covariance).
    scale_factor_rw_ppm_rts : float
        Random walk of the scale factors, ppm/sqrt(s).
    gyro_misalignment_pct : float
        1-sigma gyro cross-axis coupling (not estimated; enters as rate-dependent attitude
        noise, two off-diagonal terms per axis). Default: the MPU-6050's +/-2 % cross-axis
        sensitivity read as 3-sigma, like the turn-on biases; 0 leaves the coupling out of
        ``Q`` (the 9-state ANEES on the MPU-6050 preset is then ~100 instead of ~13).
    gnss_lever_arm_b_m : tuple of float
        Antenna position relative to the IMU in ``b``, m.
    uere_m : float
        User equivalent range error used with the DOPs when the receiver gives no accuracy, m.
    default_hdop : float
        HDOP assumed when none is reported.
    gnss_white_fraction : float
        Fraction of the position sigma treated as white; the rest is a Gauss-Markov state.
    gnss_corr_time_s : float
        Correlation time of the GNSS position error, s.
    gnss_speed_noise_mps : float
        1-sigma of each GNSS velocity component when ``s_acc_mps`` is absent, m/s.
    gnss_receiver_filter_s : float
        Time constant of the receiver's own position smoothing (u-blox-class receivers
        low-pass their navigation solution), s; its velocity then carries the derivative of
        the smoothed position error on top of the Doppler noise that ``s_acc_mps`` reports
        (see :meth:`EskfEngine._gnss_velocity_sigma`); 0: Doppler noise only.
    use_gnss_velocity : bool
        Apply GNSS velocity updates.
    gnss_min_course_speed_mps : float
        Speed+course velocity is used only above this speed (course too noisy below), m/s.
    nhc : bool
        Apply the non-holonomic constraint (wheeled vehicles).
    nhc_interval_s, nhc_lateral_noise_mps, nhc_vertical_noise_mps : float
        NHC update period (s) and 1-sigma of the vehicle's lateral / vertical velocity (m/s).
    nhc_min_speed_mps : float
        NHC only above this dead-reckoned speed, m/s.
    zupt_interval_s, zupt_noise_mps : float
        Zero-velocity update period while static (s) and its 1-sigma (m/s).
    zaru_floor_dps : float
        Floor of the zero-angular-rate update sigma (quantisation, vibration, cross-axis
        errors that a white model does not cover), deg/s.
    zaru_interval_s : float
        Averaging period of the zero-angular-rate update, s.
    zupt_max_acc_mps2 : float
        Extra condition for the static updates: the low-passed, bias-compensated horizontal
        specific force stays below this (block 3 reacts late to a gentle start), m/s^2.
    zupt_max_gnss_speed_mps : float
        No static update while the latest GNSS speed (under 1.5 s old) exceeds this, m/s.
    mount_rpy_rad : tuple of float or None
        Known mounting rotation ``C_vb`` (roll, pitch, yaw of ``b`` in ``v``), rad; None: find it.
    estimate_mount : bool
        Carry the mount as states (refined by the NHC).
    mount_std_rad : float
        Initial 1-sigma of a configured mount, rad.
    mount_aligner_std_rad : float
        1-sigma of block 5's coarse mount yaw, rad.
    mount_rw_rad_rts : float
        Random walk of the mount, rad/sqrt(s).
    vehicle_level_std_rad : float
        1-sigma of the vehicle's roll and pitch when the mount is initialised from the sensor
        tilt (road crossfall and grade up to about 5 %), rad.
    align_min_speed_mps : float
        Heading (and mount yaw with a magnetometer) from the GNSS course above this speed, m/s.
    level_time_s : float
        Levelling window at start, s.
    initial_tilt_std_rad : float
        1-sigma of the levelled roll and pitch, rad.
    cov_interval_s : float
        Covariance propagation period, s.
    gate_probability : float
        Chi-square probability of the NIS gate (every measurement).
    max_gnss_rejections : int
        Consecutive rejected fixes after which the position covariance is re-opened.
    fix_hold_s : float
        Output ``source`` is ``fix`` up to this long after an accepted fix, s.
    gravity_mps2 : float
        Gravity magnitude; 0 uses WGS84 normal gravity at the NED origin.
    mag_hard_iron_ut : tuple of float
        Hard-iron offset, uT (``m_cal = inv(W) (m_raw - h)``).
    mag_soft_iron : tuple of float
        Soft-iron matrix ``W`` row by row (9 values).
    mag_declination_rad : float
        Magnetic declination (East positive), rad.
    mag_interval_s, mag_heading_noise_rad : float
        Magnetometer heading update period (s) and 1-sigma (rad).
    use_mag : bool
        Use the magnetometer when samples arrive.
    static_prefilter_tau_s : float
        Time constant of a first-order low-pass on ``C_nb f_b`` before block 3 (averages
        engine vibration out before the detector takes the norm), s; 0 disables.
    static : StaticConfig
        Block 3 static detector.
    mount : MountConfig
        Block 5 coarse mount aligner.
    """

    acc_noise_density_ug_rthz: float = 400.0
    gyro_noise_density_mdps_rthz: float = 5.0
    acc_turn_on_bias_mg: float = 50.0 / 3.0
    gyro_turn_on_bias_dps: float = 20.0 / 3.0
    acc_bias_instability_mg: float = 0.2
    gyro_bias_instability_dph: float = 30.0
    bias_correlation_time_s: float = 100.0
    estimate_scale_factors: bool = True
    acc_scale_factor_pct: float = 1.0
    gyro_scale_factor_pct: float = 1.0
    scale_factor_rw_ppm_rts: float = 1.0
    gyro_misalignment_pct: float = 2.0 / 3.0
    gnss_lever_arm_b_m: tuple[float, float, float] = (0.0, 0.0, 0.0)
    uere_m: float = 2.0
    default_hdop: float = 1.5
    gnss_white_fraction: float = 0.1
    gnss_corr_time_s: float = 120.0
    gnss_speed_noise_mps: float = 0.12
    gnss_receiver_filter_s: float = 2.0
    use_gnss_velocity: bool = True
    gnss_min_course_speed_mps: float = 1.0
    nhc: bool = True
    nhc_interval_s: float = 0.1
    nhc_lateral_noise_mps: float = 0.1
    nhc_vertical_noise_mps: float = 0.1
    nhc_min_speed_mps: float = 1.0
    zupt_interval_s: float = 0.1
    zupt_noise_mps: float = 0.02
    zaru_floor_dps: float = 0.1
    zaru_interval_s: float = 1.0
    zupt_max_acc_mps2: float = 0.08
    zupt_max_gnss_speed_mps: float = 0.3
    mount_rpy_rad: tuple[float, float, float] | None = None
    estimate_mount: bool = True
    mount_std_rad: float = 0.02
    mount_aligner_std_rad: float = 0.1
    mount_rw_rad_rts: float = 1e-5
    vehicle_level_std_rad: float = 0.05
    align_min_speed_mps: float = 3.0
    level_time_s: float = 1.0
    initial_tilt_std_rad: float = 0.02
    cov_interval_s: float = 0.05
    gate_probability: float = 0.9999
    max_gnss_rejections: int = 5
    fix_hold_s: float = 1.5
    gravity_mps2: float = 0.0
    mag_hard_iron_ut: tuple[float, float, float] = (0.0, 0.0, 0.0)
    mag_soft_iron: tuple[float, ...] = (1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0)
    mag_declination_rad: float = 0.0
    mag_interval_s: float = 1.0
    mag_heading_noise_rad: float = 0.035
    use_mag: bool = True
    static_prefilter_tau_s: float = 0.25
    static: StaticConfig = field(default_factory=StaticConfig)
    mount: MountConfig = field(default_factory=MountConfig)

    # ------------------------------------------------------------------ I/O
    def to_dict(self) -> dict[str, Any]:
        """Plain dict (for ``summary.json``)."""
        return dataclasses.asdict(self)

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> EskfConfig:
        """Build from a dict (keys: field names; ``static`` and ``mount`` as sub-tables).

        Raises
        ------
        ValueError
            For unknown keys.
        """
        return cast(EskfConfig, dataclass_from_dict(cls(), data, "eskf"))

    @classmethod
    def from_toml(cls, path: str | Path) -> EskfConfig:
        """Load ``[eskf]`` (optionally ``[eskf.static]``, ``[eskf.mount]``) from a TOML file."""
        return cast(EskfConfig, config_from_toml(path, cls(), "eskf"))

    @classmethod
    def from_imu_spec(cls, spec: Any, **changes: Any) -> EskfConfig:
        """Noise model from a datasheet record with the :class:`iotnav.sim.presets.ImuSpec` fields."""
        names = (
            "acc_noise_density_ug_rthz",
            "gyro_noise_density_mdps_rthz",
            "acc_turn_on_bias_mg",
            "gyro_turn_on_bias_dps",
            "acc_bias_instability_mg",
            "gyro_bias_instability_dph",
            "bias_correlation_time_s",
            "acc_scale_factor_pct",
            "gyro_scale_factor_pct",
            "gyro_misalignment_pct",
        )
        kw: dict[str, Any] = {k: float(getattr(spec, k)) for k in names}
        kw.update(changes)
        return cls(**kw)

    def replace(self, **changes: Any) -> EskfConfig:
        """Copy with some fields replaced."""
        return dataclasses.replace(self, **changes)


def noise_vector(c: EskfConfig) -> FloatArray:
    """SI process-noise parameters in the order of :func:`eskf_models.error_transition`."""
    nd_a = c.acc_noise_density_ug_rthz * 1e-6 * G0
    nd_g = c.gyro_noise_density_mdps_rthz * 1e-3 * DEG
    s_ba = c.acc_bias_instability_mg * 1e-3 * G0 / _GM_PEAK
    s_bg = c.gyro_bias_instability_dph * DEG / 3600.0 / _GM_PEAK
    tc = c.bias_correlation_time_s
    k_w2 = 2.0 * (c.gyro_misalignment_pct * 1e-2) ** 2
    if not c.estimate_scale_factors:
        k_w2 += (c.gyro_scale_factor_pct * 1e-2) ** 2
    return np.array(
        [
            nd_a**2,
            nd_g**2,
            2.0 * s_ba**2 / tc,
            2.0 * s_bg**2 / tc,
            # no decay of the bias *errors*: the true bias is the turn-on constant plus the
            # Gauss-Markov in-run part, and the nominal bias is held between updates, so the
            # error ``b - b_hat`` does not decay; it wanders with the in-run driving noise.
            0.0,
            0.0,
            c.mount_rw_rad_rts**2,
            (c.scale_factor_rw_ppm_rts * 1e-6) ** 2,
            0.0,  # GNSS error driving intensities: set from the fix accuracy
            0.0,
            1.0 / c.gnss_corr_time_s,
            2.0 * k_w2 * 1.0,
        ]
    )


class EskfEngine:
    """Streaming ESKF engine (see the module docstring).

    Parameters
    ----------
    config : EskfConfig, optional
        Tunables (MPU-6050 datasheet defaults).

    Attributes
    ----------
    nom : eskf_models.Nominal
        Nominal state.
    P : numpy.ndarray
        Error-state covariance (layout of :mod:`iotnav.engines.eskf_models`).
    events : list of dict
        Static transitions, alignment, mount estimates, rejected updates.
    nis_log : dict of list
        Per measurement name: ``(t, nis, dof, accepted)`` of every attempted update.
    """

    def __init__(self, config: EskfConfig | None = None) -> None:
        self.config = c = config or EskfConfig()
        self.n = M.n_states(c.estimate_scale_factors)
        self.nom = M.Nominal()
        self.P = np.eye(self.n) * 1e-6
        self.noise = noise_vector(c)
        self.lever_b = np.asarray(c.gnss_lever_arm_b_m, float)
        W = np.asarray(c.mag_soft_iron, float).reshape(3, 3)
        self.mag_Winv = np.linalg.inv(W)
        self.mag_h = np.asarray(c.mag_hard_iron_ut, float)
        self.static_det = StaticDetector(c.static)
        self.aligner = MountAligner(c.mount)
        self.events: list[dict[str, Any]] = []
        self.nis_log: dict[str, list[tuple[float, float, int, bool]]] = {}
        self.frame: TangentPlane | None = None
        self.g_n = np.array([0.0, 0.0, c.gravity_mps2 if c.gravity_mps2 > 0 else G0])
        self.acc = np.zeros(M.ACC_SIZE)
        self.t_state = math.nan
        self.f_pend = np.zeros(3)  # raw IMU sample being integrated
        self.w_pend = np.zeros(3)
        self.have_imu = False
        # initialisation flags
        self.levelled = False
        self.level_sum = np.zeros(7)  # sum f (3), sum w (3), sum |f|^2
        self.level_n = 0
        self.level_t0 = math.nan
        self.heading_ok = False
        self.pos_ok = False
        self.mount_ok = c.mount_rpy_rad is not None
        if c.mount_rpy_rad is not None:
            self.nom.C_vb[:] = euler_to_dcm(*c.mount_rpy_rad)
        self.static = False
        self.static_seen = False
        self.f_n_lp = np.zeros(3)
        self.t_speed = -math.inf
        self.last_speed = math.nan
        self.t_prefilt = -math.inf
        # scheduling
        self.t_nhc = -math.inf
        self.t_zupt = -math.inf
        self.t_mag = -math.inf
        self.zaru_sum = np.zeros(3)
        self.zaru_n = 0
        self.t_zaru = -math.inf
        self.t_fix = -math.inf
        self.n_rejected_fix = 0
        self.last_fix: tuple[float, FloatArray, FloatArray] | None = None
        self.t_prev_fix = -math.inf
        self.sigma_e = np.array([1.0, 1.0, 1.5])  # current Gauss-Markov GNSS sigma, m
        self.n_imu = 0
        self._gates = {d: kalman.gate_threshold(d, c.gate_probability) for d in (1, 2, 3)}

    # ------------------------------------------------------------------ protocol
    @property
    def mount_yaw_rad(self) -> float:
        """Mount yaw (sensor x from vehicle forward, clockwise), rad."""
        C = self.nom.C_vb
        return math.atan2(C[1, 0], C[0, 0])

    @property
    def mount_rpy_rad(self) -> tuple[float, float, float]:
        """Current mounting rotation ``C_vb`` as roll, pitch, yaw, rad."""
        return dcm_to_rpy(self.nom.C_vb)

    def summary(self) -> dict[str, Any]:
        """Configuration, final state and statistics (for ``summary.json``)."""
        counts: dict[str, int] = {}
        for e in self.events:
            counts[e["type"]] = counts.get(e["type"], 0) + 1
        nis = {
            k: {
                "count": len(v),
                "accepted": int(sum(1 for r in v if r[3])),
                "mean_nis_per_dof": float(np.mean([r[1] / r[2] for r in v])) if v else math.nan,
            }
            for k, v in self.nis_log.items()
        }
        return {
            "engine": "eskf",
            "config": self.config.to_dict(),
            "n_states": self.n,
            "mount_rpy_rad": list(self.mount_rpy_rad),
            "mount_known": self.mount_ok,
            "gyro_bias_rad_s": self.nom.b_g.tolist(),
            "acc_bias_mps2": self.nom.b_a.tolist(),
            "gyro_scale": self.nom.s_g.tolist(),
            "acc_scale": self.nom.s_a.tolist(),
            "origin": None
            if self.frame is None
            else {
                "lat_deg": self.frame.lat0_deg,
                "lon_deg": self.frame.lon0_deg,
                "height_m": self.frame.h0_m,
            },
            "event_counts": counts,
            "nis": nis,
            "imu_samples": self.n_imu,
        }

    def step(self, sample: Sample) -> Output | None:
        """Process one sample (streaming and batch share this)."""
        if isinstance(sample, ImuSample):
            return self._imu(sample)
        if isinstance(sample, GnssSample):
            self._gnss(sample)
        elif isinstance(sample, MagSample):
            self._mag(sample)
        return None

    # ------------------------------------------------------------------ propagation
    def _integrate_to(self, t: float) -> None:
        """Integrate the pending IMU sample from ``t_state`` to ``t``."""
        if not self.have_imu or not math.isfinite(self.t_state):
            return
        dt = t - self.t_state
        if dt <= 0.0 or dt > 1.0:
            self.t_state = max(self.t_state, t)
            return
        nom = self.nom
        f = M.compensate(self.f_pend, nom.b_a, nom.s_a)
        w = M.compensate(self.w_pend, nom.b_g, nom.s_g)
        M.propagate_nominal(nom.C_nb, nom.v_n, nom.p_n, f, w, dt, self.g_n, self.acc)
        self.t_state = t
        if self.acc[M.ACC_T] >= self.config.cov_interval_s:
            self._propagate_cov()

    def _propagate_cov(self) -> None:
        T = float(self.acc[M.ACC_T])
        if T <= 0.0:
            return
        C = self.acc[M.ACC_C].reshape(3, 3) / T
        f_b = self.acc[M.ACC_FB] / T
        w_b = self.acc[M.ACC_WB] / T
        Phi, Qd = M.error_transition(C, f_b, w_b, T, self.n, self.noise)
        self.P = kalman.symmetrize(Phi @ self.P @ Phi.T + Qd)
        # the GNSS error is zero-mean Gauss-Markov: its estimate decays as the error model does
        self.nom.e_n *= math.exp(-T * self.noise[10])
        self.acc[:] = 0.0
        if not self.heading_ok:
            self._freeze_yaw()
        if not self.config.estimate_mount:
            self.P[M.MNT, :] = 0.0
            self.P[:, M.MNT] = 0.0

    def _freeze_yaw(self) -> None:
        """Before the heading is known its error is left out of the filter (zero row/column).

        A 180-degree yaw sigma would be linearised through the small horizontal specific
        force and make yaw, then tilt and accelerometer bias, spuriously observable from
        zero-velocity updates at rest.
        """
        k = M.ATT.start + 2
        self.P[k, :] = 0.0
        self.P[:, k] = 0.0

    # ------------------------------------------------------------------ updates
    def _apply(self, t: float, meas: M.Meas | None, force: bool = False) -> bool:
        """Gate and apply one measurement; returns True when accepted."""
        if meas is None:
            return False
        self._propagate_cov()
        dof = meas.y.size
        gate = (
            None if force else self._gates.get(dof, kalman.gate_threshold(dof, self.config.gate_probability))
        )
        res = kalman.update(np.zeros(self.n), self.P, meas.y, meas.H, meas.R, gate=gate)
        self.nis_log.setdefault(meas.name, []).append((t, res.nis, dof, res.accepted))
        if not res.accepted:
            if meas.name != "gnss_position":
                self.events.append(
                    {
                        "type": "update_rejected",
                        "t": t,
                        "measurement": meas.name,
                        "nis": res.nis,
                        "test_ratio": res.test_ratio,
                    }
                )
            return False
        M.inject(self.nom, res.x)
        self.P = res.P
        if not self.heading_ok:
            self._freeze_yaw()
        return True

    # ------------------------------------------------------------------ IMU
    def _imu(self, s: ImuSample) -> Output:
        c = self.config
        self.n_imu += 1
        f_raw = np.asarray(s.acc_b, float)
        w_raw = np.asarray(s.gyro_b, float)
        if not self.have_imu:
            self.t_state = s.t
            self.have_imu = True
            self.level_t0 = s.t
        else:
            self._integrate_to(s.t)
        self.f_pend = f_raw
        self.w_pend = w_raw
        if not self.levelled:
            self._level(s.t, f_raw, w_raw)
        nom = self.nom
        f_n = nom.C_nb @ M.compensate(f_raw, nom.b_a, nom.s_a)
        was = self.static
        v_dr = math.hypot(nom.v_n[0], nom.v_n[1]) if self.pos_ok and self.heading_ok else math.nan
        a = (
            1.0
            if c.static_prefilter_tau_s <= 0
            else 1.0 - math.exp(-max(s.t - self.t_prefilt, 0.0) / c.static_prefilter_tau_s)
        )
        self.t_prefilt = s.t
        self.f_n_lp += a * (f_n - self.f_n_lp)
        self.static = self.static_det.step(s.t, self.f_n_lp, v_dr) if self.levelled else False
        if self.static != was:
            self.events.append({"type": "static_start" if self.static else "static_end", "t": s.t})
            self.zaru_sum[:] = 0.0
            self.zaru_n = 0
            self.t_zaru = s.t
        if self.static:
            self.static_seen = True
            self.zaru_sum += w_raw
            self.zaru_n += 1
            quiet = math.hypot(self.f_n_lp[0], self.f_n_lp[1]) < c.zupt_max_acc_mps2 and not (
                s.t - self.t_speed < 1.5 and self.last_speed > c.zupt_max_gnss_speed_mps
            )
            if s.t - self.t_zupt >= c.zupt_interval_s and self.levelled and quiet:
                self._static_updates(s.t)
        # mount aligner (block 5) while the mount yaw is unknown
        if not self.mount_ok and self.levelled:
            psi = math.atan2(nom.C_nb[1, 0], nom.C_nb[0, 0])
            cp, sp = math.cos(psi), math.sin(psi)
            a_s = np.array([cp * f_n[0] + sp * f_n[1], -sp * f_n[0] + cp * f_n[1]])
            w_c = M.compensate(w_raw, nom.b_g, nom.s_g)
            self.aligner.add_imu(a_s, float(nom.C_nb[2] @ w_c))
        if (
            c.nhc
            and self.heading_ok
            and self.pos_ok
            and self.mount_ok
            and not self.static
            and s.t - self.t_nhc >= c.nhc_interval_s
        ):
            self.t_nhc = s.t
            if math.hypot(nom.v_n[0], nom.v_n[1]) >= c.nhc_min_speed_mps:
                self._apply(s.t, M.nhc(nom, c.nhc_lateral_noise_mps, c.nhc_vertical_noise_mps, self.n))
        return self._output(s.t)

    def _level(self, t: float, f: FloatArray, w: FloatArray) -> None:
        c = self.config
        self.level_sum[:3] += f
        self.level_sum[3:6] += w
        self.level_sum[6] += float(f @ f)
        self.level_n += 1
        if t - self.level_t0 < c.level_time_s or self.level_n < 2:
            return
        n = self.level_n
        fm = self.level_sum[:3] / n
        wm = self.level_sum[3:6] / n
        var_f = max(self.level_sum[6] / n - float(fm @ fm), 0.0)
        roll = math.atan2(-fm[1], -fm[2])
        pitch = math.atan2(fm[0], math.hypot(fm[1], fm[2]))
        self.nom.C_nb[:] = euler_to_dcm(roll, pitch, 0.0)
        # what was integrated before with the unknown attitude is discarded (a sensor mounted
        # z up would otherwise have gained 2 g of vertical velocity per second)
        self.nom.v_n[:] = 0.0
        self.nom.p_n[:] = 0.0
        quiet = math.sqrt(var_f) < 0.5 and abs(float(np.linalg.norm(fm)) - G0) < 0.5
        if quiet:
            self.nom.b_g[:] = wm
        self.levelled = True
        sg = c.gyro_turn_on_bias_dps * DEG
        nd_g = c.gyro_noise_density_mdps_rthz * 1e-3 * DEG
        bg_std = math.hypot(nd_g / math.sqrt(max(t - self.level_t0, 1e-3)), 0.05 * sg) if quiet else sg
        ba_std = c.acc_turn_on_bias_mg * 1e-3 * G0
        sa_std = c.acc_scale_factor_pct * 1e-2
        d = np.zeros(self.n)
        d[M.POS] = 100.0
        d[M.VEL] = 1.0 if quiet else 10.0
        d[M.BG] = bg_std
        d[M.MNT] = c.mount_std_rad if c.mount_rpy_rad is not None else c.mount_aligner_std_rad
        d[M.GNE] = 3.0
        if self.n >= M.N_FULL:
            d[M.SG] = c.gyro_scale_factor_pct * 1e-2
        self.P = np.diag(d**2)
        # tilt = accelerometer error / g, fully correlated with it (eskf_models.level_covariance);
        # the independent part: standard error of the mean when quiet, else the configured value
        g = float(self.g_n[2])
        white = math.sqrt(var_f / n) / g if quiet else c.initial_tilt_std_rad
        full = self.n >= M.N_FULL
        Pl = M.level_covariance(
            self.nom.C_nb,
            fm,
            g,
            np.full(3, ba_std**2),
            np.full(3, sa_std**2) if full else None,
            white,
        )
        idx = np.r_[np.arange(M.ATT.start, M.ATT.stop), np.arange(M.BA.start, M.BA.stop)]
        if full:
            idx = np.r_[idx, np.arange(M.SA.start, M.SA.stop)]
        self.P[np.ix_(idx, idx)] = Pl  # yaw row stays zero until initialised (see _freeze_yaw)
        self.acc[:] = 0.0
        self.events.append({"type": "levelled", "t": t, "roll": roll, "pitch": pitch, "quiet": quiet})

    def _static_updates(self, t: float) -> None:
        c = self.config
        self.t_zupt = t
        self._apply(t, M.zupt(self.nom, c.zupt_noise_mps, self.n))
        T = t - self.t_zaru
        if self.zaru_n >= 5 and T >= c.zaru_interval_s:
            self.t_zaru = t
            nd_g = c.gyro_noise_density_mdps_rthz * 1e-3 * DEG
            sigma = math.hypot(nd_g / math.sqrt(T), c.zaru_floor_dps * DEG)
            self._apply(t, M.zaru(self.nom, self.zaru_sum / self.zaru_n, sigma, self.n))
            self.zaru_sum[:] = 0.0
            self.zaru_n = 0

    # ------------------------------------------------------------------ magnetometer
    def _mag(self, s: MagSample) -> None:
        c = self.config
        if not c.use_mag or not self.levelled:
            return
        m_b = self.mag_Winv @ (np.asarray(s.mag_b_ut, float) - self.mag_h)
        self._integrate_to(s.t)
        if not self.heading_ok:
            r, p, _ = dcm_to_rpy(self.nom.C_nb)
            C_tilt = euler_to_dcm(r, p, 0.0)
            m = C_tilt @ m_b
            yaw = c.mag_declination_rad - math.atan2(m[1], m[0])
            self._set_heading(s.t, yaw, c.mag_heading_noise_rad, "magnetometer")
            self.t_mag = s.t
            return
        if s.t - self.t_mag >= c.mag_interval_s:
            self.t_mag = s.t
            self._apply(
                s.t, M.mag_heading(self.nom, m_b, c.mag_declination_rad, c.mag_heading_noise_rad, self.n)
            )

    def _set_heading(self, t: float, yaw: float, sigma: float, how: str, mount_cov: float = 0.0) -> None:
        """Set the sensor yaw, keeping roll and pitch; reset the yaw covariance."""
        r, p, yaw_old = dcm_to_rpy(self.nom.C_nb)
        self.nom.C_nb[:] = euler_to_dcm(r, p, yaw)
        # the navigation frame turns with the yaw: rotate every n-frame error (P' = T P T^T)
        T = M.heading_reset_transform(yaw - yaw_old, self.n)
        self.P = kalman.symmetrize(T @ self.P @ T.T)
        # the yaw row/column: decorrelate, set variance (and its mount correlation)
        k = M.ATT.start + 2
        self.P[k, :] = 0.0
        self.P[:, k] = 0.0
        self.P[k, k] = sigma**2
        if mount_cov:
            km = M.MNT.start + 2
            self.P[k, km] = self.P[km, k] = mount_cov
        self.heading_ok = True
        self.events.append(
            {"type": "heading_initialised", "t": t, "yaw_rad": yaw, "source": how, "std_rad": sigma}
        )

    # ------------------------------------------------------------------ GNSS
    def _gnss_noise(self, s: GnssSample) -> tuple[FloatArray, float]:
        """Per-axis NED position sigma (m) and velocity sigma (m/s) of a fix."""
        c = self.config
        h_acc = float(getattr(s, "h_acc_m", math.nan))
        v_acc = float(getattr(s, "v_acc_m", math.nan))
        s_acc = float(getattr(s, "s_acc_mps", math.nan))
        if math.isfinite(h_acc) and h_acc > 0:
            sh = h_acc / math.sqrt(2.0)
            sv = v_acc if math.isfinite(v_acc) and v_acc > 0 else 1.6 * h_acc
        else:
            hd = s.hdop if math.isfinite(s.hdop) and s.hdop > 0 else c.default_hdop
            pd_ = s.pdop if math.isfinite(s.pdop) and s.pdop > hd else hd * math.sqrt(3.0)
            sh = c.uere_m * hd / math.sqrt(2.0)
            sv = c.uere_m * math.sqrt(pd_ * pd_ - hd * hd)
        sv_ = s_acc if math.isfinite(s_acc) and s_acc > 0 else c.gnss_speed_noise_mps
        return np.array([sh, sh, sv]), sv_

    def _gnss_velocity_sigma(self, sig_doppler: float, sigma_e: FloatArray, dt_fix: float) -> FloatArray:
        """Per-axis 1-sigma of the receiver velocity (m/s), inflated for its time correlation.

        A receiver that smooths its position with a first-order filter (time constant
        ``t_f = gnss_receiver_filter_s``) reports a velocity whose error is the Doppler noise
        plus the derivative of the smoothed Gauss-Markov position error ``y``:
        ``var(dy/dt) = sigma_e^2 / (t_f T_e)`` (first-order low-pass of a Gauss-Markov process
        of correlation time ``T_e``; Gelb 1974, §3.8). That part is correlated over about
        ``t_f``; fixes ``dt`` apart see the lag-one correlation ``rho = exp(-dt / t_f)``, and
        treating such a sequence as white is made conservative by the variance factor
        ``(1 + rho) / (1 - rho)`` (the sum of its autocorrelation; Bar-Shalom et al. 2001,
        §8.3)::

            sigma_v^2 = sigma_doppler^2 + (1 + rho) / (1 - rho) * sigma_e^2 / (t_f T_e)
        """
        c = self.config
        tf = c.gnss_receiver_filter_s
        if tf <= 0.0:
            return np.full(3, sig_doppler)
        rho = math.exp(-min(max(dt_fix, 0.05), 10.0) / tf)
        k = (1.0 + rho) / (1.0 - rho) / (tf * c.gnss_corr_time_s)
        return np.sqrt(sig_doppler**2 + k * sigma_e**2)

    def _gnss_velocity(self, s: GnssSample) -> FloatArray | None:
        c = self.config
        vn = float(getattr(s, "vn", math.nan))
        ve = float(getattr(s, "ve", math.nan))
        vd = float(getattr(s, "vd", math.nan))
        if math.isfinite(vn) and math.isfinite(ve):
            return np.array([vn, ve, vd]) if math.isfinite(vd) else np.array([vn, ve])
        if math.isfinite(s.speed_mps):
            if s.speed_mps < c.gnss_min_course_speed_mps:
                return np.zeros(2) if s.speed_mps < 0.2 else None
            if s.course_valid and math.isfinite(s.course_rad):
                return s.speed_mps * np.array([math.cos(s.course_rad), math.sin(s.course_rad)])
        return None

    def _gnss(self, s: GnssSample) -> None:
        c = self.config
        if not s.valid or not (math.isfinite(s.lat_deg) and math.isfinite(s.lon_deg)):
            self.events.append({"type": "fix_rejected", "t": s.t, "reason": "invalid"})
            self.aligner.add_gnss(s.t, math.nan, math.nan, False, self.static)
            return
        self._integrate_to(s.t)
        if self.frame is None:
            h0 = s.height_m if math.isfinite(s.height_m) else 0.0
            self.frame = TangentPlane(s.lat_deg, s.lon_deg, h0)
            if c.gravity_mps2 <= 0:
                self.g_n[2] = normal_gravity(s.lat_deg, h0)
            self.events.append({"type": "first_fix", "t": s.t, "pdop": s.pdop, "num_sv": s.num_sv})
        z = self.frame.to_ned(
            s.lat_deg, s.lon_deg, s.height_m if math.isfinite(s.height_m) else self.frame.h0_m
        )
        sig_p, sig_v = self._gnss_noise(s)
        v_meas = self._gnss_velocity(s)
        speed = (
            s.speed_mps
            if math.isfinite(s.speed_mps)
            else (math.hypot(v_meas[0], v_meas[1]) if v_meas is not None else math.nan)
        )
        self.static_det.update_speed(s.t, speed)
        if math.isfinite(speed):
            self.t_speed, self.last_speed = s.t, speed
        course = s.course_rad
        course_ok = s.course_valid and math.isfinite(course)
        if (
            v_meas is not None
            and not course_ok
            and v_meas.size >= 2
            and math.hypot(v_meas[0], v_meas[1]) > 1.0
        ):
            course, course_ok = math.atan2(v_meas[1], v_meas[0]), True
        # block 5 while the mount yaw is unknown
        if not self.mount_ok and self.levelled:
            ev = self.aligner.add_gnss(s.t, speed, course, course_ok, self.static)
            if ev is not None:
                self.events.append(ev)
        # Gauss-Markov part of the GNSS error follows the reported accuracy
        f = c.gnss_white_fraction
        self.sigma_e = math.sqrt(max(1.0 - f * f, 0.0)) * sig_p
        self.noise[8] = 2.0 * self.sigma_e[0] ** 2 / c.gnss_corr_time_s
        self.noise[9] = 2.0 * self.sigma_e[2] ** 2 / c.gnss_corr_time_s
        sig_white = np.maximum(f * sig_p, 0.05)
        self.last_fix = (s.t, z, np.zeros(3) if v_meas is None else np.pad(v_meas, (0, 3 - v_meas.size)))
        t_prev = self.t_prev_fix
        self.t_prev_fix = s.t
        if not self.levelled:
            return
        moving_fast = course_ok and math.isfinite(speed) and speed >= c.align_min_speed_mps
        if not self.heading_ok:
            if not self.mount_ok and self.aligner.known:
                self._init_mount(s.t, self.aligner.mount_yaw_rad, "block5")
            if self.mount_ok and moving_fast:
                # vehicle yaw = course; sensor yaw = vehicle yaw + mount yaw
                r, p, _ = dcm_to_rpy(self.nom.C_nb @ self.nom.C_vb.T)
                C_nv = euler_to_dcm(r, p, course)
                _, _, yaw_b = dcm_to_rpy(C_nv @ self.nom.C_vb)
                sig_c = sig_v / max(speed, 0.1)
                sm = float(np.sqrt(self.P[M.MNT.start + 2, M.MNT.start + 2]))
                self._set_heading(s.t, yaw_b, math.hypot(sig_c, sm), "gnss_course", mount_cov=sm * sm)
                self._reset_position(s.t, z, v_meas, sig_p, sig_v)
            return
        if not self.pos_ok:
            self._reset_position(s.t, z, v_meas, sig_p, sig_v)
            return
        if not self.mount_ok and moving_fast:
            # magnetometer heading known: mount yaw = sensor yaw - course
            _, _, yaw_b = dcm_to_rpy(self.nom.C_nb)
            mu = math.remainder(yaw_b - course, 2.0 * math.pi)
            self._init_mount(s.t, mu, "mag_course")
            km = M.MNT.start + 2
            self.P[km, :] = 0.0
            self.P[:, km] = 0.0
            self.P[km, km] = self.P[M.ATT.start + 2, M.ATT.start + 2] + (sig_v / speed) ** 2
        # position update (gated; re-open after repeated rejections)
        force = self.n_rejected_fix >= c.max_gnss_rejections
        if force:
            self.P[M.POS, :] = 0.0
            self.P[:, M.POS] = 0.0
            self.P[M.POS, M.POS] = np.diag((3.0 * sig_p) ** 2)
            self.events.append({"type": "gate_reset", "t": s.t, "rejected": self.n_rejected_fix})
        ok = self._apply(s.t, M.gnss_position(self.nom, z, self.lever_b, sig_white, self.n), force=force)
        if ok:
            self.n_rejected_fix = 0
            self.t_fix = s.t
        else:
            self.n_rejected_fix += 1
            rec = self.nis_log["gnss_position"][-1]
            self.events.append(
                {
                    "type": "fix_rejected",
                    "t": s.t,
                    "reason": "nis",
                    "nis": rec[1],
                    "test_ratio": rec[1] / self._gates[3],
                }
            )
        if c.use_gnss_velocity and v_meas is not None:
            sv = self._gnss_velocity_sigma(sig_v, self.sigma_e, s.t - t_prev)
            self._apply(s.t, M.gnss_velocity(self.nom, self.w_pend, v_meas, self.lever_b, sv, self.n))

    def _init_mount(self, t: float, mount_yaw: float, how: str) -> None:
        """Mount from its yaw and the level-vehicle assumption; covariance of its roll and pitch.

        The vehicle is taken as level (roll and pitch zero within ``vehicle_level_std_rad``,
        road crossfall and grade) at this epoch, so the mount's roll and pitch are the sensor's:
        ``C_vb = R_z(mu) R_y(pitch_b) R_x(roll_b)`` (works for any mounting, sensor upside down
        included). Their error is then the sensor tilt error seen in the vehicle frame plus
        the road's tilt, ``dmu_xy = [R_z(-psi_v) dth]_xy - road_xy``: the rows are rebuilt with
        that transform, ``P' = T P T^T + diag(road^2)``, keeping the correlation with the
        tilt (and through it with the accelerometer bias). With ``mount_rpy_rad`` configured
        nothing here runs.
        """
        c = self.config
        r_b, p_b, psi_b = dcm_to_rpy(self.nom.C_nb)
        self.nom.C_vb[:] = euler_to_dcm(r_b, p_b, mount_yaw)
        psi_v = psi_b - mount_yaw
        rows = np.arange(M.MNT.start, M.MNT.start + 2)
        T = np.eye(self.n)
        T[rows, :] = 0.0
        T[np.ix_(rows, np.arange(M.ATT.start, M.ATT.stop))] = rot_z(-psi_v)[:2, :]
        self.P = T @ self.P @ T.T
        self.P[rows, rows] += c.vehicle_level_std_rad**2
        self.P = kalman.symmetrize(self.P)
        self.mount_ok = True
        self.events.append(
            {
                "type": "mount_initialised",
                "t": t,
                "mount_yaw_rad": mount_yaw,
                "mount_roll_rad": r_b,
                "mount_pitch_rad": p_b,
                "source": how,
            }
        )

    def _reset_position(
        self, t: float, z: FloatArray, v_meas: FloatArray | None, sig_p: FloatArray, sig_v: float
    ) -> None:
        """Position (and velocity) from a fix; decorrelate those states."""
        nom = self.nom
        nom.p_n[:] = z - nom.C_nb @ self.lever_b
        nom.e_n[:] = 0.0
        if v_meas is not None:
            nom.v_n[: v_meas.size] = v_meas
            if v_meas.size == 2:
                nom.v_n[2] = 0.0
        for sl in (M.POS, M.VEL, M.GNE):
            self.P[sl, :] = 0.0
            self.P[:, sl] = 0.0
        self.P[M.POS, M.POS] = np.diag(sig_p**2)
        self.P[M.GNE, M.GNE] = np.diag(self.sigma_e**2)
        sv = sig_v if v_meas is not None else 5.0
        self.P[M.VEL, M.VEL] = np.diag([sv**2, sv**2, max(sv, 0.3) ** 2])
        self.pos_ok = True
        self.t_fix = t
        self.events.append({"type": "position_initialised", "t": t})

    # ------------------------------------------------------------------ output
    def _output(self, t: float) -> Output:
        c = self.config
        nom = self.nom
        C_out = nom.C_nb @ nom.C_vb.T if self.mount_ok else nom.C_nb
        nan = math.nan
        roll, pitch, yaw = dcm_to_rpy(C_out) if self.levelled else (nan, nan, nan)
        if not self.heading_ok:
            yaw = nan
        if self.frame is None:
            return output_without_position(t, (roll, pitch, yaw), self.static)
        if self.heading_ok and self.pos_ok:
            r, v = nom.p_n, nom.v_n
            std_n, std_e = math.sqrt(self.P[0, 0]), math.sqrt(self.P[1, 1])
            source = "fix" if t - self.t_fix <= c.fix_hold_s else "dr"
        else:
            assert self.last_fix is not None
            tf, z, vf = self.last_fix
            r = z + vf * (t - tf)
            v = vf
            std_n = std_e = c.uere_m * c.default_hdop
            source = "fix"
        return output_at(t, self.frame, r, v, (roll, pitch, yaw), self.static, (std_n, std_e), source)
