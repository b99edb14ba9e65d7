"""Configuration of the quaternion EKF (:mod:`iotnav.engines.qekf`): :class:`QekfConfig`, the
paper's form by default and :meth:`QekfConfig.consistent`, and :func:`datasheet_noises`.

Every tunable in SI units (names carry any other unit); the paper (Sec. 3) selected ``Q`` and
``R`` experimentally, the consistent form takes the IMU's datasheet values (MPU-6050,
PS-MPU-6000A-00 Rev 3.4).
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any, cast

from iotnav.engines.config import PIPELINE_MOUNT_NAV, dataclass_from_dict, read_toml
from iotnav.techniques.mount import MountConfig

__all__ = ["QekfConfig", "datasheet_noises"]

_G0 = 9.80665  # standard gravity, the datasheets' g, m/s^2


def datasheet_noises(
    acc_noise_density_ug_rthz: float = 400.0, gyro_noise_density_mdps_rthz: float = 5.0
) -> dict[str, float]:
    """:class:`QekfConfig` white noises from an IMU's datasheet densities (the units of
    ``eskf``'s configuration and the dataset profiles; defaults: the MPU-6050's).

    Parameters
    ----------
    acc_noise_density_ug_rthz : float
        Accelerometer noise density, ug/sqrt(Hz).
    gyro_noise_density_mdps_rthz : float
        Gyro noise density, mdps/sqrt(Hz).

    Returns
    -------
    dict
        ``acc_noise_mps2_rthz`` (m/s^2/sqrt(Hz)) and ``gyro_noise_rad_s_rthz`` (rad/s/sqrt(Hz)).
    """
    return {
        "acc_noise_mps2_rthz": acc_noise_density_ug_rthz / 1e6 * _G0,
        "gyro_noise_rad_s_rthz": math.radians(gyro_noise_density_mdps_rthz / 1e3),
    }


@dataclass(frozen=True)
class QekfConfig:
    """Tunables of the quaternion EKF (SI; the paper selected Q and R experimentally).

    Attributes
    ----------
    init_duration_s : float
        Static initialisation period from the first IMU sample, s (paper: 40 s).
    init_max_speed_mps, init_max_displacement_m : float
        The initialisation ends early (the device is no longer still) at the first fix more
        than ``init_max_displacement_m`` from the mean fix with a GNSS speed above
        ``init_max_speed_mps``; the averages then stop one GNSS interval before the last speed
        below it (m/s, m; 0 disables).
    gyro_noise_rad_s_rthz, acc_noise_mps2_rthz : float
        White-noise densities of gyro (rad/s/sqrt(Hz)) and accelerometer (m/s^2/sqrt(Hz)),
        including vibration and unmodelled errors.
    gyro_bias_rw_rad_s2_rthz, acc_bias_rw_mps3_rthz : float
        Bias random-walk densities.
    scale_rw_1_s_rthz : float
        Scale-factor random-walk density, 1/sqrt(s).
    gyro_bias_init_rad_s, acc_bias_init_mps2 : float
        Initial bias standard deviations (gyro bias after the static average).
    scale_init : float
        Initial scale-factor standard deviation (dimensionless).
    init_att_std_rad, init_vel_std_mps : float
        Initial attitude and velocity standard deviations.
    uere_m, default_dop : float
        UERE (m) multiplying the DOPs when the receiver gives no hAcc, and the HDOP assumed when
        it gives neither (:mod:`iotnav.gnss_accuracy`).
    vel_noise_mps : float
        GNSS velocity sigma per component when no sAcc is reported, m/s.
    min_course_speed_mps : float
        Speed and course give a velocity only above this speed, m/s.
    min_satellites : int
        Fixes need at least this many satellites.
    gate_probability : float
        Chi-square probability of the NIS gates (0 disables them).
    max_rejections : int
        After this many consecutive gated GNSS positions (or velocities) the next is accepted,
        the position (velocity) covariance first widened by its variance and by the outer
        product of its innovation
        (re-convergence in one step; adding the variance alone halved a 100 m error per
        forced fix, which took half a minute after a 60 s outage on the real drive).
    reacquire_after_s : float
        A fix that comes more than this long after the last accepted one (a GNSS outage) is
        taken the same way at once, s: the dead-reckoned position may be far off, and five
        gated epochs of it were the largest errors outside the outages on the real drive.
    acc_dir_std_rad : float
        Direction sigma of gravity from the accelerometer when quiet, rad.
    mag_dir_std_rad : float
        Direction sigma of the calibrated magnetic field, rad.
    dyn_acc_factor : float
        Gravity-direction sigma grows by ``dyn_acc_factor * a_dyn / g`` (``a_dyn`` the
        remaining dynamic acceleration ``| |g_b| - g |``, m/s^2).
    comp_rel_error : float
        Relative error of the vehicle-acceleration compensation ``|a_b|`` (speed, sideslip and
        lever arm, a priori 10 %); adds ``comp_rel_error |a_b| / g`` to the gravity-direction sigma.
    triad_max_comp_mps2 : float
        No TRIAD observation over an interval whose mean estimated vehicle acceleration
        ``|a_b|`` (the compensation removed from the accelerometer) exceeds this, m/s^2: there
        the gravity direction carries the compensation's errors (sideslip, lever arm, the
        speed-difference noise), which are systematic over a manoeuvre and so not the white
        noise the observation model assumes; the gyros carry the attitude through. Counted in
        ``summary()["triad_skipped"]``.
    mag_norm_tol, mag_dip_tol_rad : float
        Magnetometer refused when ``| |m| / |m_ref| - 1 |`` or the dip-angle error exceed these.
    quat_norm_std : float
        Sigma of the norm pseudo-observation and of the norm direction in ``R_q``.
    mag_field_n_ut : tuple of float or None
        Reference field in NED, microtesla; None: World Magnetic Model at the origin.
    wmm_year : float or None
        Decimal year for the World Magnetic Model; None (default): the log's date at the
        first fix (:func:`iotnav.wmm.log_year`; the WMM2025 epoch when the log has no date).
        The field used and where its year came from are in ``summary()["mag_reference"]``.
    mag_hard_iron_ut : tuple of float
        Hard-iron offset ``h`` (uT) of the calibration ``m = S^-1 (m~ - h)``.
    mag_soft_iron : tuple of float or None
        Soft-iron matrix ``S`` (row-major, 9 values); None: identity.
    gravity_mps2 : float
        Gravity magnitude; 0 uses WGS84 normal gravity at the origin.
    use_mag : bool
        Use the magnetometer (the TRIAD observation) after the initialisation.
    use_gnss_velocity : bool
        Use the GNSS velocity (update, and speed rate in the gravity compensation).
    triad_bias_corrected : bool
        Correct the accelerometer by the estimated bias before TRIAD (False: raw, the bias
        then counts in ``acc_dir_std_rad``; avoids feeding the bias estimate back as if the
        observation were independent of it).
    triad_state_coupling : str
        How the TRIAD observation's dependence on the estimated biases, scale factors and
        velocity enters (:mod:`iotnav.engines.qekf`): ``"accelerometer"`` (default; accelerometer bias and
        scale factor in ``H``, the compensation's states as noise), ``"noise"`` (all as noise)
        or ``"jacobian"`` (all in ``H``).
    smoothing : bool
        Keep a :class:`~iotnav.engines.smoother.SmoothingLog` for the RTS smoother (``iotnav run
        --smooth`` turns it on; 22 states: about 12 KB a record); off by default.
    record_every : int
        IMU rows between smoothing records without a measurement.
    mount : MountConfig
        Mount-yaw aligner of the no-magnetometer fallback (:mod:`iotnav.engines.qekf_fallback`).
    heading_min_speed_mps : float
        Fallback heading reset: minimum GNSS speed, m/s.
    heading_max_yaw_rate_rad_s : float
        Fallback heading reset: maximum mean yaw rate over the GNSS interval, rad/s.
    nhc_interval_s : float
        Period of the non-holonomic observation (0 disables it), s.
    nhc_min_speed_mps : float
        Minimum horizontal speed of the filter for the non-holonomic observation, m/s.
    nhc_max_yaw_rate_rad_s : float
        Maximum mean yaw rate since the previous non-holonomic observation, rad/s.
    nhc_vel_std_mps : float
        Lateral-velocity floor sigma ``sigma_0``, m/s.
    nhc_sideslip_std_rad : float
        Sideslip angle sigma (a car below 2-3 m/s^2 of lateral acceleration: about 1 deg), rad.
    nhc_lever_m : float
        Assumed distance ``L`` of the IMU from the rear axle (lateral velocity ``r L`` in turns), m.
    gnss_error_states : bool
        Carry the time-correlated GNSS position error as 6 more states (``GNE``, ``GNM``; 28 in
        all), the second-order model of :mod:`iotnav.engines.eskf_models`
        (:mod:`iotnav.engines.qekf_gnss_error`); False: the paper's 22 states, the GNSS error white in ``R``.
    gnss_corr_time_s : float
        With ``gnss_error_states``: correlation time ``T_e`` of the horizontal Gauss-Markov GNSS
        position error before the receiver's smoothing, s (the simulator's ``open-sky``
        horizontal value).
    gnss_corr_time_v_s : float
        The same for the vertical error, s (the simulator's ``open-sky`` vertical value; as
        ``eskf``'s ``gnss_corr_time_v_s``).
    gnss_receiver_filter_s : float
        With ``gnss_error_states``: time constant ``t_f`` of the receiver's first-order position
        smoothing, s (0: none, ``GNE`` is then the Gauss-Markov error itself, ``GNM`` inert).
    gnss_white_fraction : float
        With ``gnss_error_states``: fraction ``f`` of the fix's position sigma taken as white
        (in ``R``); the rest, ``sqrt(1 - f^2) sigma_p``, is the correlated error of the states.
    gnss_white_floor_m : float
        With ``gnss_error_states``: floor of the white part's sigma per axis, m (raised to the
        output rounding's sigma, :class:`~iotnav.engines.gnss_resolution.PositionResolution`).
    gnss_error_scales_with_accuracy : bool
        With ``gnss_error_states``: the correlated error's estimates and covariance follow the
        fix's reported sigma (a receiver re-acquiring after a tunnel reports a larger accuracy
        and is that much further off; :meth:`QekfEngine._scale_gnss_error`).
    mag_observation : str
        Attitude observation after the initial alignment: ``"triad"`` (the paper's improved
        TRIAD of gravity and field, Eq. 7; skipped above ``triad_max_comp_mps2``) or
        ``"direction"`` (the magnetometer's field direction alone, 2 dof, the accelerometer then
        used once, in the prediction; :mod:`iotnav.engines.qekf`, "Consistent form"). The initial
        alignment is TRIAD in both.
    gyro_misalignment, acc_misalignment : float
        1-sigma cross-axis coupling of gyro and accelerometer, each off-diagonal element,
        dimensionless (0.01 = 1 %); not estimated, it enters ``Q`` as rate-dependent gyro noise
        and acceleration-dependent accelerometer-bias noise (as in ``eskf``,
        :mod:`iotnav.engines.eskf_models`). 0: left out (the paper's form).
    cross_axis_corr_time_s : float
        Correlation time of the motion that the cross-axis errors scale (a manoeuvre), s.
    """

    init_duration_s: float = 40.0
    init_max_speed_mps: float = 0.5
    init_max_displacement_m: float = 10.0
    gyro_noise_rad_s_rthz: float = 3e-4
    acc_noise_mps2_rthz: float = 0.1
    gyro_bias_rw_rad_s2_rthz: float = 2e-5
    acc_bias_rw_mps3_rthz: float = 1e-3
    scale_rw_1_s_rthz: float = 1e-5
    gyro_bias_init_rad_s: float = 2e-3
    acc_bias_init_mps2: float = 0.2
    scale_init: float = 0.01
    init_att_std_rad: float = 0.03
    init_vel_std_mps: float = 0.1
    uere_m: float = 2.0
    default_dop: float = 2.0
    vel_noise_mps: float = 0.15
    min_course_speed_mps: float = 2.0
    min_satellites: int = 5
    gate_probability: float = 0.9999
    max_rejections: int = 5
    reacquire_after_s: float = 10.0
    acc_dir_std_rad: float = 0.02
    mag_dir_std_rad: float = 0.015
    dyn_acc_factor: float = 1.5
    comp_rel_error: float = 0.1
    triad_max_comp_mps2: float = 1.0
    mag_norm_tol: float = 0.1
    mag_dip_tol_rad: float = 0.07
    quat_norm_std: float = 1e-3
    mag_field_n_ut: tuple[float, float, float] | None = None
    wmm_year: float | None = None
    mag_hard_iron_ut: tuple[float, float, float] = (0.0, 0.0, 0.0)
    mag_soft_iron: tuple[float, ...] | None = None
    gravity_mps2: float = 0.0
    use_mag: bool = True
    use_gnss_velocity: bool = True
    triad_bias_corrected: bool = True
    triad_state_coupling: str = "accelerometer"
    smoothing: bool = False
    record_every: int = 5
    mount: MountConfig = PIPELINE_MOUNT_NAV
    heading_min_speed_mps: float = 5.0
    heading_max_yaw_rate_rad_s: float = 0.03
    nhc_interval_s: float = 1.0
    nhc_min_speed_mps: float = 5.0
    nhc_max_yaw_rate_rad_s: float = 0.1
    nhc_vel_std_mps: float = 0.05
    nhc_sideslip_std_rad: float = 0.02
    nhc_lever_m: float = 1.5
    gnss_error_states: bool = False
    gnss_corr_time_s: float = 150.0
    gnss_corr_time_v_s: float = 200.0
    gnss_receiver_filter_s: float = 2.0
    gnss_white_fraction: float = 0.0
    gnss_white_floor_m: float = 0.005
    gnss_error_scales_with_accuracy: bool = True
    mag_observation: str = "triad"
    gyro_misalignment: float = 0.0
    acc_misalignment: float = 0.0
    cross_axis_corr_time_s: float = 5.0

    def to_dict(self) -> dict[str, Any]:
        """Plain dict (for ``summary.json``)."""
        return dataclasses.asdict(self)

    @classmethod
    def consistent(cls, **overrides: Any) -> QekfConfig:
        """The consistent form (:mod:`iotnav.engines.qekf`): magnetometer direction observations, the
        IMU's datasheet noises and cross-axis coupling in ``Q``, GNSS error states.

        Defaults are the MPU-6050's datasheet values (PS-MPU-6000A-00 Rev 3.4: accelerometer
        400 ug/sqrt(Hz), gyro 5 mdps/sqrt(Hz), cross-axis +/-2 % read as 3 sigma, as ``eskf``
        reads them); put your IMU's in ``overrides``, with any other field.

        Parameters
        ----------
        **overrides
            :class:`QekfConfig` fields that replace these settings or the defaults.

        Returns
        -------
        QekfConfig
            The configuration.
        """
        settings: dict[str, Any] = {
            "mag_observation": "direction",
            **datasheet_noises(),
            "gyro_misalignment": 0.02 / 3.0,
            "acc_misalignment": 0.02 / 3.0,
            "gnss_error_states": True,
        }
        settings.update(overrides)
        return cls(**settings)

    @classmethod
    def from_toml(cls, path: str | Path) -> QekfConfig:
        """Load ``[qekf]`` (or the top-level keys) from a TOML file.

        ``form = "consistent"`` starts from :meth:`consistent` instead of the paper's form
        (``form = "paper"``, the default); the other keys replace fields of either.

        Raises
        ------
        ValueError
            For an unknown form or key, or a TOML syntax error (naming the file).
        """
        data = read_toml(path)
        raw = data.get("qekf", data)
        if not isinstance(raw, dict):
            raise ValueError(f"{path}: qekf must be a table, got {raw!r}")
        table = dict(raw)
        form = table.pop("form", "paper")
        if form not in ("paper", "consistent"):
            raise ValueError(f"{path}: qekf.form must be 'paper' or 'consistent', got {form!r}")
        base = cls.consistent() if form == "consistent" else cls()
        try:
            return cast(QekfConfig, dataclass_from_dict(base, table, "qekf"))
        except (TypeError, ValueError) as exc:
            raise ValueError(f"{path}: {exc}") from exc
