"""Configuration of the ``eskf`` engine and its process-noise vector."""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, cast

import numpy as np
import numpy.typing as npt

from iotnav.engines.config import config_from_toml, dataclass_from_dict
from iotnav.engines.eskf.layout import (
    NOISE_SIZE,
    NZ_ACC_BIAS,
    NZ_ACC_BIAS_DECAY,
    NZ_ACC_WHITE,
    NZ_GNSS_H,
    NZ_GNSS_V,
    NZ_GYRO_BIAS,
    NZ_GYRO_BIAS_DECAY,
    NZ_GYRO_WHITE,
    NZ_INV_TE_H,
    NZ_INV_TE_V,
    NZ_INV_TF,
    NZ_K_A,
    NZ_K_S,
    NZ_K_W,
    NZ_MOUNT_RW,
    NZ_SCALE_RW,
)
from iotnav.techniques.mount import MountConfig
from iotnav.techniques.static import StaticConfig

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
        Add gyro and accelerometer scale-factor states (30 states instead of 24).
    acc_scale_factor_pct, gyro_scale_factor_pct : float
        1-sigma scale-factor errors (initial covariance).
    scale_factor_rw_ppm_rts : float
        Random walk of the scale factors, ppm/sqrt(s).
    gyro_misalignment_pct : float
        1-sigma gyro cross-axis coupling, each off-diagonal element (not estimated; enters as
        rate-dependent attitude noise ``k_w (|omega_b|^2 - omega_b,i^2)`` per sensor axis,
        ``k_w = 2 m_g^2 tau_x``, see :mod:`iotnav.engines.eskf.models`). Default: the
        MPU-6050's +/-2 % cross-axis sensitivity read as 3-sigma, like the turn-on biases;
        0 leaves the coupling out of ``Q``.
    acc_misalignment_pct : float
        1-sigma accelerometer cross-axis coupling, each off-diagonal element (not estimated):
        its gravity part widens the turn-on bias at levelling, its kinematic part drives the
        accelerometer bias noise ``k_a (|a_b|^2 - a_b,i^2)``, ``k_a = 2 m_a^2 / tau_x`` (see
        :mod:`iotnav.engines.eskf.models`). Default: MPU-6050, +/-2 % as 3-sigma; 0 leaves
        the coupling out (``benchmarks/results/eskf_history.md``).
    cross_axis_corr_time_s : float
        Correlation time ``tau_x`` of the motion that the cross-axis errors scale (angular
        rate and kinematic acceleration: the duration of a manoeuvre, a start, a brake, a
        turn), s. Also used for the gyro scale factor when it is not estimated.
    gnss_lever_arm_b_m : tuple of float
        Antenna position relative to the IMU in ``b``, m.
    uere_m : float
        User equivalent range error used with the DOPs when the receiver gives no accuracy, m.
    default_hdop : float
        HDOP assumed when none is reported.
    gnss_white_fraction : float
        Fraction of the position sigma treated as white; the rest is the time-correlated
        error states. A smoothing receiver's output has little white content, the simulator's
        none: 0 (``benchmarks/results/eskf_history.md``, "Consistency"); raise it for a
        receiver whose fixes jitter from epoch to epoch.
    gnss_white_floor_m : float
        Floor of the white part's 1-sigma, m.
    gnss_white_from_resolution : bool
        Add the rounding of the fixes' output format to the white part, found from the fixes
        (:class:`~iotnav.engines.gnss_resolution.PositionResolution`: 4-decimal NMEA minutes
        are 0.185 m steps, 5.3 cm of white noise; 3 decimals 0.53 m), reported in
        ``summary()["gnss_resolution"]``.
    gnss_error_scales_with_accuracy : bool
        Scale the GNSS error states with the reported accuracy (package docstring, "Reported
        accuracy").
    gnss_corr_time_s : float
        Correlation time of the horizontal Gauss-Markov GNSS position error before the
        receiver's smoothing, s. Default: the horizontal value of the simulator's ``open-sky``
        receiver model (:data:`iotnav.sim.gnss_model.ENVIRONMENTS`, 120-300 s across
        environments).
    gnss_corr_time_v_s : float
        The same for the vertical error, s (the vertical error of a receiver wanders more
        slowly; the simulator's ``open-sky`` value, 180-300 s across environments). It sets
        the vertical velocity error the receiver's smoothing adds, ``sigma_v^2 / (t_f T_e)``.
    gnss_speed_noise_mps : float
        1-sigma of each GNSS velocity component when ``s_acc_mps`` is absent, m/s.
    gnss_receiver_filter_s : float
        Time constant ``t_f`` of the receiver's own position smoothing (u-blox-class receivers
        low-pass their navigation solution; the simulator's ``receiver_filter_s``, 2 s), s:
        the reported position error is the Gauss-Markov error through that first-order
        low-pass, and the velocity error its derivative ``(e_gm - e) / t_f`` on top of the
        Doppler noise that ``s_acc_mps`` reports (see :mod:`iotnav.engines.eskf.models`);
        0: no smoothing, first-order Gauss-Markov position error, Doppler noise only.
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
    mag_declination_rad : float or None
        Magnetic declination (East positive), rad. None (default): the World Magnetic Model's
        at the first good fix and the log's date (:mod:`iotnav.wmm`; the value used is in
        ``summary()["mag_reference"]``); magnetometer samples before that fix are skipped
        (counted as ``mag_before_declination``).
    mag_interval_s, mag_heading_noise_rad : float
        Magnetometer heading update period (s) and 1-sigma (rad).
    use_mag : bool
        Use the magnetometer when samples arrive (and it is calibrated).
    mag_calibrated : bool
        The magnetometer's output is calibrated already (e.g. Android's calibrated field).
        Otherwise it is used only with a configured calibration (``mag_hard_iron_ut`` or
        ``mag_soft_iron`` not the defaults): an uncalibrated magnetometer's heading is off by
        up to tens of degrees; its samples are counted in ``summary()["mag_unused"]`` and the
        heading comes from the GNSS course.
    static_prefilter_tau_s : float
        Time constant of a first-order low-pass on ``C_nb f_b`` before block 3 (averages
        engine vibration out before the detector takes the norm), s; 0 disables.
    smoothing : bool
        Keep a :class:`~iotnav.engines.smoother.SmoothingLog` for the RTS smoother (``iotnav run
        --smooth`` turns it on; package docstring, "RTS smoothing"). Off by default; the
        forward output is the same either way.
    record_every : int
        Covariance propagations (``cov_interval_s`` each) between smoothing records when there
        is no measurement; every update epoch is a record too. A record holds ``P`` twice and
        ``Phi``: ``8 (1 + 2 n + 3 n^2)`` bytes, 21.8 KB with the 30 states (13.8 KB with 24),
        stored compactly (about 8.8 KB with 30 states) and at most 32 MB of them in RAM, the
        rest in a temporary file (:mod:`iotnav.engines.smoother_records`).
    smoothing_drift_gap_s : float
        How the smoother reads a gate reset's forced fix, s. Within twice this time after a
        GNSS gap (no valid fix) longer than this, the filter has likely drifted and the fix is
        right: it is recorded against the un-widened prior, so it corrects the gap. After a
        shorter gap the disagreement more likely comes from the re-acquiring receiver's
        first fixes: the reset is recorded as a re-initialisation of the position, carrying
        nothing back.
    gravity_aiding : bool
        Before the heading is known, aid the tilt (and through it the roll / pitch gyro bias)
        with gravity while the GNSS-derived horizontal acceleration is small, as an AHRS
        does (package docstring, "Initialisation"). Without it a start in motion with a few
        deg/s of gyro bias loses the tilt before the mount, hence the heading, is known.
    gravity_interval_s : float
        Averaging period of the gravity update, s: one update per second, about the
        correlation time of the vehicle acceleration lumped into its noise (a car's speed
        changes over seconds), so successive updates are not counted as independent
        information about the same acceleration.
    gravity_max_acc_mps2 : float
        Gravity aiding only while the GNSS-derived horizontal acceleration is at most this,
        m/s^2 (12 deg of tilt; that acceleration is in the update's noise, so a larger one
        only weakens it). VQF and Madgwick-type AHRS likewise rest the accelerometer
        correction on a small deviation of ``|f|`` from ``g``.
    max_gravity_rejections : int
        Consecutive rejected gravity updates after which the tilt covariance is re-opened to
        ``gravity_reopen_std_rad`` (decorrelated) and the next update is taken (event
        ``gravity_reset`` counted in the summary): the tilt is then further off than the
        configured gyro turn-on bias allows, and gating every update out would lose it for
        good, as the GNSS gate reset does for fixes.
    gravity_reopen_std_rad : float
        1-sigma of the re-opened roll and pitch, rad (30 deg: a linear update then takes most
        of a tilt error of that size, the following ones the rest).
    gnss_accel_span_s : float
        Shortest time between the two fixes whose velocity difference gives the GNSS-derived
        acceleration, s (a 10 Hz receiver's 0.1 s difference is ten times noisier than a 1 s
        one: 1.4 m/s^2 1-sigma for 0.1 m/s velocity noise).
    moving_tilt_std_rad : float
        1-sigma of the levelled roll and pitch when the levelling window was not quiet
        (levelled in motion, where the window's mean acceleration is unknown): 0.1 rad is the
        tilt of 1 m/s^2, a brisk car acceleration (Bokare and Maurya 2017, "Acceleration-
        deceleration behaviour of various vehicle types", Transp. Res. Procedia 25: cars
        0.6-1.5 m/s^2 typical).
    mount_commit_std_rad : float
        Block 5's mount yaw is committed (and the heading set from the course) only once its
        own 1-sigma is at most this, rad (0.1 rad, the ``mount_aligner_std_rad`` the filter
        assumes for it). Until then the mount is reported ``unobservable`` and the output is
        the last fix moved on at its velocity.
    hold_accel_floor_mps2 : float
        Least 1-sigma of the unknown horizontal acceleration in the claimed sigma of the last
        fix moved on at its velocity (before the heading: package docstring,
        "Initialisation"), m/s^2. Default: the median horizontal acceleration over 1 s of the
        real drive (drive_0708 RTK: 0.58 m/s^2, :mod:`iotnav.engines.integrity`, whose
        ``accel_floor_mps2`` is the same figure), at the low end of the cars' typical 0.6-1.5
        m/s^2 (Bokare and Maurya 2017, as ``moving_tilt_std_rad``).
    hold_window_s : float
        What the vehicle did before an outage is taken from the fixes of this last span, s:
        the running RMS of the GNSS-derived horizontal acceleration that raises that 1-sigma
        above its floor (time constant), and the top fix speed of the reach bound (the
        integrity guard's ``dynamics_window_s``).
    hold_speed_margin : float
        The vehicle's speed after the fix is taken to stay below this factor times the top fix
        speed of the last ``hold_window_s`` (and that fix's own speed): a 1-sigma bound of each
        velocity component's change, ``sqrt((|v_f|^2 + s_top^2) / 2)`` (a turn to any
        direction at the top speed; a full reversal is at 2 sigma), that caps the acceleration
        term once the velocity change reaches it. Default: the integrity guard's
        ``dynamics_margin`` (the 99th percentiles of the speed rate are 1.4 times their 95th on
        the real drive, :mod:`iotnav.engines.integrity`). A vehicle at rest through the whole
        span is then claimed to stay at its fix: a drive-away within an outage before the
        heading is not covered.
    nis_monitor : bool
        The windowed NIS consistency monitor (:mod:`~iotnav.engines.eskf.consistency`): when
        the GNSS position NIS over the last ``nis_window_fixes`` fixes disagrees with the
        filter beyond chance, the filter re-initialises from GNSS (event ``reinitialised``;
        package docstring, "Consistency monitor").
    nis_window_fixes : int
        Window of the monitor, fixes (30: 30 s at 1 Hz, 3 s at 10 Hz).
    nis_min_fixes : int
        Fixes the window must hold before it is tested (after a start or a re-initialisation).
    nis_false_alarm : float
        False-alarm probability of one window test (at most: the cap only lowers it).
    nis_cap_probability : float
        Each fix's NIS enters the window capped at its chi-square quantile of this probability
        (0.99: about half the window far off is needed, not the few fixes after an outage).
    nis_tolerance : float
        The monitor tests the innovations against ``nis_tolerance`` times their covariance
        ``S``: it fires on disagreement beyond chance even allowing the filter to claim this
        much too little (3: issue 16's consistency target, NEES within a factor 3 of its band;
        the real drive's GNSS position NIS averages 1.4 per dof with the defaults, and with a
        factor 1 the test fired on it: ``benchmarks/results/eskf_nis.md``).
    reinit_min_distance_m, reinit_distance_sigmas : float
        An alarm also needs the predicted position off the fixes: their mean horizontal
        distance over the window above ``max(reinit_min_distance_m, reinit_distance_sigmas x``
        the RMS of the fixes' reported horizontal 1-sigma ``)``, m; else the filter is only
        overconfident, and a re-initialisation would throw its calibration away for nothing.
        10 m: the integrity guard's ``min_reinit_distance_m`` (a tracker fix's 2-D 95 % radius
        is about 5 m, :mod:`iotnav.engines.integrity`); 3 sigma for worse fixes. Without the
        distance condition the monitor re-initialised eskf three times on 200 s of drive_0708
        with a 60 s Gauss-Markov GNSS error of 2 m (``tests/test_eskf.py``, the filter 1-4 m
        from the RTK while rejecting 62 % of the fixes) and lost the mount.
    reinit_escalate_s : float
        A second re-initialisation within this long of the previous one also releases the
        mount (block 5 estimates it again: a wrong mount brings a wrong heading back), s.
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
    acc_misalignment_pct: float = 2.0 / 3.0
    cross_axis_corr_time_s: float = 5.0
    gnss_lever_arm_b_m: tuple[float, float, float] = (0.0, 0.0, 0.0)
    uere_m: float = 2.0
    default_hdop: float = 1.5
    gnss_white_fraction: float = 0.0
    gnss_white_floor_m: float = 0.005
    gnss_white_from_resolution: bool = True
    gnss_error_scales_with_accuracy: bool = True
    gnss_corr_time_s: float = 150.0
    gnss_corr_time_v_s: float = 200.0
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
    mag_declination_rad: float | None = None
    mag_interval_s: float = 1.0
    mag_heading_noise_rad: float = 0.035
    use_mag: bool = True
    mag_calibrated: bool = False
    static_prefilter_tau_s: float = 0.25
    smoothing: bool = False
    record_every: int = 10
    smoothing_drift_gap_s: float = 10.0
    gravity_aiding: bool = True
    gravity_interval_s: float = 1.0
    gravity_max_acc_mps2: float = 2.0
    max_gravity_rejections: int = 3
    gravity_reopen_std_rad: float = 0.5
    gnss_accel_span_s: float = 1.0
    moving_tilt_std_rad: float = 0.1
    mount_commit_std_rad: float = 0.1
    hold_accel_floor_mps2: float = 0.5
    hold_window_s: float = 60.0
    hold_speed_margin: float = 1.5
    nis_monitor: bool = True
    nis_window_fixes: int = 30
    nis_min_fixes: int = 10
    nis_false_alarm: float = 1e-6
    nis_cap_probability: float = 0.99
    nis_tolerance: float = 3.0
    reinit_min_distance_m: float = 10.0
    reinit_distance_sigmas: float = 3.0
    reinit_escalate_s: float = 120.0
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
            "acc_misalignment_pct",
        )
        kw: dict[str, Any] = {k: float(getattr(spec, k)) for k in names}
        kw.update(changes)
        return cls(**kw)

    def replace(self, **changes: Any) -> EskfConfig:
        """Copy with some fields replaced."""
        return dataclasses.replace(self, **changes)


def noise_vector(c: EskfConfig) -> FloatArray:
    """The process-noise record (:data:`~iotnav.engines.eskf.layout.NOISE`, SI) of a configuration.

    Raises
    ------
    ValueError
        For a non-positive ``cross_axis_corr_time_s``.
    """
    nd_a = c.acc_noise_density_ug_rthz * 1e-6 * G0
    nd_g = c.gyro_noise_density_mdps_rthz * 1e-3 * DEG
    s_ba = c.acc_bias_instability_mg * 1e-3 * G0 / _GM_PEAK
    s_bg = c.gyro_bias_instability_dph * DEG / 3600.0 / _GM_PEAK
    tc = c.bias_correlation_time_s
    # cross-axis (and unestimated scale-factor) errors: white noise of the intensity of a
    # process correlated over a manoeuvre, 2 sigma^2 tau, or bias noise 2 sigma^2 / tau
    tau = c.cross_axis_corr_time_s
    if not tau > 0.0:
        raise ValueError(f"eskf.cross_axis_corr_time_s must be > 0 s, got {tau}")
    k_w = 2.0 * (c.gyro_misalignment_pct * 1e-2) ** 2 * tau
    k_a = 2.0 * (c.acc_misalignment_pct * 1e-2) ** 2 / tau
    k_s = 0.0 if c.estimate_scale_factors else 2.0 * (c.gyro_scale_factor_pct * 1e-2) ** 2 * tau
    noise = np.zeros(NOISE_SIZE)
    noise[NZ_ACC_WHITE] = nd_a**2
    noise[NZ_GYRO_WHITE] = nd_g**2
    noise[NZ_ACC_BIAS] = 2.0 * s_ba**2 / tc
    noise[NZ_GYRO_BIAS] = 2.0 * s_bg**2 / tc
    # no decay of the bias *errors*: the true bias is the turn-on constant plus the
    # Gauss-Markov in-run part, and the nominal bias is held between updates, so the
    # error ``b - b_hat`` does not decay; it wanders with the in-run driving noise.
    noise[NZ_ACC_BIAS_DECAY] = 0.0
    noise[NZ_GYRO_BIAS_DECAY] = 0.0
    noise[NZ_MOUNT_RW] = c.mount_rw_rad_rts**2
    noise[NZ_SCALE_RW] = (c.scale_factor_rw_ppm_rts * 1e-6) ** 2
    noise[NZ_GNSS_H] = 0.0  # GNSS error driving intensities: set from each fix's accuracy
    noise[NZ_GNSS_V] = 0.0
    noise[NZ_INV_TE_H] = 1.0 / c.gnss_corr_time_s
    noise[NZ_K_W] = k_w
    noise[NZ_K_A] = k_a
    noise[NZ_K_S] = k_s
    noise[NZ_INV_TF] = 1.0 / c.gnss_receiver_filter_s if c.gnss_receiver_filter_s > 0.0 else 0.0
    noise[NZ_INV_TE_V] = 1.0 / c.gnss_corr_time_v_s
    return noise
