"""Scenario configuration: frozen dataclasses, dotted-key overrides, JSON echo.

A scenario is one :class:`ScenarioConfig`. Its blocks (:class:`ImuConfig`,
:class:`GnssConfig`, :class:`MagConfig`, :class:`FixesConfig`, and a scenario-specific
``motion`` dataclass) are frozen; :func:`apply_overrides` returns a new configuration with
values changed by dotted keys (``"imu.preset": "mpu6050"``, ``"duration_s": 600``,
``"gnss.outages_s": "[[100, 130]]"``). Values may be given as strings (the CLI's
``--set key=value``) and are converted to the field's type; an unknown key or a value that
does not convert raises :class:`ValueError` naming the key and what was expected.

IMU error parameters of the preset (:class:`iotnav.sim.presets.ImuSpec`) are overridable
through the ``imu`` block too (``imu.gyro_noise_density_mdps_rthz=3``); they are collected in
``ImuConfig.spec`` and echoed in ``scenario.json``.
"""

from __future__ import annotations

import json
import types
import typing
from collections.abc import Mapping
from dataclasses import asdict, dataclass, field, fields, is_dataclass, replace
from typing import Any

from iotnav.sim.presets import ImuSpec

__all__ = [
    "CarMotion",
    "FixesConfig",
    "GnssConfig",
    "ImuConfig",
    "MagConfig",
    "ScenarioConfig",
    "StaticMotion",
    "TrackMotion",
    "WalkMotion",
    "apply_overrides",
    "config_to_dict",
]

Interval = tuple[float, float]


@dataclass(frozen=True)
class ImuConfig:
    """IMU sampling and error switches.

    Attributes
    ----------
    enabled : bool
        Write IMU samples.
    preset : str
        A key of :data:`iotnav.sim.presets.IMU_PRESETS`.
    rate_hz : float
        Output data rate; must divide the scenario's ``truth_rate_hz``.
    errors : bool
        False gives the true (error-free) samples, whatever the preset says.
    anti_alias : bool
        True: each output sample is the mean of the internal samples over its interval
        ("integrate and dump", stamped at the interval start). False: point sampling.
    vibration_acc_rms_mps2, vibration_gyro_rms_rads : float
        RMS of vibration (engine, scooter deck) on each accelerometer / gyro axis (z axis of
        the vehicle gets the full value, x and y half).
    vibration_freq_hz : float
        Fundamental frequency of the vibration (a second harmonic of half amplitude is added).
    vibration_speed_ref_mps : float
        > 0: vibration amplitude scales with speed / this value (deck vibration, capped at 2);
        0: constant (engine running).
    spec : tuple of (str, float or str)
        Overrides of preset error parameters (set through ``imu.<field>=value``).
    """

    enabled: bool = True
    preset: str = "lsm6ds3"
    rate_hz: float = 100.0
    errors: bool = True
    anti_alias: bool = True
    vibration_acc_rms_mps2: float = 0.0
    vibration_gyro_rms_rads: float = 0.0
    vibration_freq_hz: float = 25.0
    vibration_speed_ref_mps: float = 0.0
    spec: tuple[tuple[str, float | str], ...] = ()


@dataclass(frozen=True)
class GnssConfig:
    """GNSS receiver model (see :mod:`iotnav.sim.gnss_model`).

    Attributes
    ----------
    enabled : bool
        Simulate GNSS epochs.
    rate_hz : float
        Fix rate, 1-20 Hz; must divide ``truth_rate_hz``.
    environment : str
        ``open-sky``, ``courtyard``, ``urban-canyon`` or ``under-trees``.
    errors : bool
        False: fixes equal the truth (DOPs and satellites still reported).
    sigma_h_m, sigma_v_m, tau_h_s, tau_v_s, outliers_per_hour : float or None
        Override the environment's per-axis horizontal / vertical error sigma, their
        correlation times and the outlier rate.
    dop_variation : float
        Relative 1-sigma of the slow DOP fluctuation (correlation time 600 s).
    receiver_filter_s : float
        Time constant of the receiver's position filter that smooths the Gauss-Markov error.
    doppler_noise_mps : float
        1-sigma white noise of each Doppler velocity component.
    course_min_speed_mps : float
        Below this speed the course is reported invalid (empty NMEA field).
    cold_start : bool
        Start with no fix, then large-error, high-PDOP fixes converging to normal.
    ttff_s, converge_tau_s, initial_pdop, initial_offset_m : float
        Cold start: time to first fix, convergence time constant, PDOP and error offset at
        the first fix.
    outages_s : tuple of (start, end)
        Intervals of device time without a fix (tunnels).
    outage_output : str
        ``quality0`` (sentences keep coming with empty fields and quality 0) or ``silent``.
    reacquire_tau_s : float
        After an outage the error is inflated by ``1 + 2 exp(-dt / reacquire_tau_s)``.
    latency_s : float
        Device time of the NMEA lines minus the fix time.
    talker : str
        NMEA talker id (``GP`` or ``GN``).
    write_ubx : bool
        Also write ``gnss.ubx`` (UBX NAV-PVT).
    geoid_sep_m : float
        Geoid separation written in GGA (``height = alt_msl + geoid_sep``).
    """

    enabled: bool = True
    rate_hz: float = 1.0
    environment: str = "open-sky"
    errors: bool = True
    sigma_h_m: float | None = None
    sigma_v_m: float | None = None
    tau_h_s: float | None = None
    tau_v_s: float | None = None
    outliers_per_hour: float | None = None
    dop_variation: float = 0.08
    receiver_filter_s: float = 2.0
    doppler_noise_mps: float = 0.08
    course_min_speed_mps: float = 1.8
    cold_start: bool = False
    ttff_s: float = 30.0
    converge_tau_s: float = 30.0
    initial_pdop: float = 25.0
    initial_offset_m: float = 50.0
    outages_s: tuple[Interval, ...] = ()
    outage_output: str = "quality0"
    reacquire_tau_s: float = 5.0
    latency_s: float = 0.0
    talker: str = "GP"
    write_ubx: bool = False
    geoid_sep_m: float = 47.5


@dataclass(frozen=True)
class MagConfig:
    """Magnetometer model (see :mod:`iotnav.sim.mag_model`).

    Attributes
    ----------
    enabled : bool
        Simulate magnetometer samples (written as extra columns of ``imu.csv``).
    preset : str
        A key of :data:`iotnav.sim.presets.MAG_PRESETS`.
    rate_hz : float
        Nominal rate; each sample is taken at the IMU sample nearest its nominal time.
    errors : bool
        False: the true field in ``b``.
    field_ut, inclination_deg, declination_deg : float
        Earth field at the origin (defaults: Turin, WMM2020: 47 uT, 61.5 deg, 2.9 deg).
    disturbances : tuple of (t_start_s, t_end_s, dn_ut, de_ut, dd_ut)
        Local disturbances added in ``n`` with a raised-cosine envelope.
    """

    enabled: bool = False
    preset: str = "lis3mdl"
    rate_hz: float = 6.0
    errors: bool = True
    field_ut: float = 47.0
    inclination_deg: float = 61.5
    declination_deg: float = 2.9
    disturbances: tuple[tuple[float, float, float, float, float], ...] = ()


@dataclass(frozen=True)
class FixesConfig:
    """Absolute position + attitude fixes (image-based positioning).

    Attributes
    ----------
    enabled : bool
        Write ``fixes.csv``.
    interval_s : float
        Time between fixes (1, 2 or 5 s in the paper's study).
    latency_s : float
        ``t_arrival - t_valid``.
    sigma_pos_m : float
        1-sigma error of each position component.
    sigma_att_rad : float
        1-sigma error of each attitude angle (small rotation about each axis of ``n``).
    """

    enabled: bool = False
    interval_s: float = 1.0
    latency_s: float = 0.5
    sigma_pos_m: float = 0.3
    sigma_att_rad: float = 0.0175


@dataclass(frozen=True)
class StaticMotion:
    """The device lies still.

    Attributes
    ----------
    roll_rad, pitch_rad, yaw_rad : float
        Vehicle (resting base) attitude.
    """

    roll_rad: float = 0.0
    pitch_rad: float = 0.0
    yaw_rad: float = 0.6


@dataclass(frozen=True)
class TrackMotion:
    """Laps of a closed track: straights joined by semicircles.

    Attributes
    ----------
    laps : int
        Number of laps.
    straight_m, radius_m : float
        Length of each straight and radius of the semicircles (100 m and 31.83 m make a
        400 m track).
    mean_speed_kmh : float
        Average speed over a lap.
    straight_mode : str
        ``cruise``: constant speed everywhere; ``accel-brake``: curves at
        ``curve_speed_kmh``, each straight accelerates then brakes so that the lap average is
        ``mean_speed_kmh``.
    curve_speed_kmh : float
        Speed in the curves for ``accel-brake``.
    counter_clockwise : bool
        Direction of the laps seen from above.
    heading_rad : float
        Heading of the first straight.
    wait_start_s, wait_end_s : float
        Standing still before and after.
    accel_mps2 : float
        Mean acceleration when starting and stopping.
    """

    laps: int = 5
    straight_m: float = 100.0
    radius_m: float = 31.83
    mean_speed_kmh: float = 17.6
    straight_mode: str = "cruise"
    curve_speed_kmh: float = 15.0
    counter_clockwise: bool = True
    heading_rad: float = 0.3
    wait_start_s: float = 15.0
    wait_end_s: float = 10.0
    accel_mps2: float = 0.8


@dataclass(frozen=True)
class WalkMotion:
    """Walking laps of a rectangle with rounded corners.

    Attributes
    ----------
    length_m, width_m : float
        Sides of the rectangle walked (first side along ``heading_rad``, turning right).
    laps : int
        Number of laps.
    speed_mps : float
        Mean walking speed.
    cadence_hz : float
        Steps per second.
    vertical_amp_m, lateral_amp_m : float
        Amplitude of the vertical bob (one per step) and lateral sway (one per stride).
    turn_rate_rad_s : float
        Yaw rate at the corners.
    wait_start_s, wait_end_s : float
        Standing still before and after.
    carry : str
        ``bag``: slow random attitude of the device about the mount; ``hand``: small sway.
    bag_attitude_sigma_rad, bag_knot_s : float
        1-sigma of the bag attitude angles and spacing of their random spline knots.
    heading_rad : float
        Heading of the first side.
    """

    length_m: float = 60.0
    width_m: float = 40.0
    laps: int = 1
    speed_mps: float = 1.35
    cadence_hz: float = 1.8
    vertical_amp_m: float = 0.03
    lateral_amp_m: float = 0.02
    turn_rate_rad_s: float = 0.8
    wait_start_s: float = 60.0
    wait_end_s: float = 20.0
    carry: str = "bag"
    bag_attitude_sigma_rad: float = 0.25
    bag_knot_s: float = 3.0
    heading_rad: float = 1.2


@dataclass(frozen=True)
class CarMotion:
    """A car route of motion primitives.

    Attributes
    ----------
    route : str
        ``tunnel`` (urban streets then a motorway ring with tunnels and slopes) or ``town``
        (stop-and-go town driving with right-angle turns).
    wait_start_s : float
        Standing still at the start (static initialisation).
    urban_speed_kmh, highway_speed_kmh : float
        Cruise speeds.
    max_slope_pct : float
        Steepest grade of the slopes.
    turn_rate_dps : float
        Yaw rate in the urban right-angle turns.
    heading_rad : float
        Initial heading.
    """

    route: str = "tunnel"
    wait_start_s: float = 10.0
    urban_speed_kmh: float = 50.0
    highway_speed_kmh: float = 100.0
    max_slope_pct: float = 5.0
    turn_rate_dps: float = 15.0
    heading_rad: float = 0.5


Motion = StaticMotion | TrackMotion | WalkMotion | CarMotion


@dataclass(frozen=True)
class ScenarioConfig:
    """Every parameter of a simulated scenario (echoed into ``scenario.json``).

    Attributes
    ----------
    name, description : str
        Scenario name and one-line description.
    motion : dataclass
        The scenario's motion parameters.
    duration_s : float or None
        Cut (or extend by standing still) the motion to this length; None: the motion's own.
    truth_rate_hz : float
        Internal truth rate (>= 200 Hz recommended; the IMU and GNSS rates must divide it).
    origin_lat_deg, origin_lon_deg, origin_height_m : float
        Geodetic origin of the local NED frame (ellipsoidal height).
    start_utc : str
        UTC of device time 0 (ISO 8601); ``utc = t + utc_offset_s``.
    mount_roll_rad, mount_pitch_rad, mount_yaw_rad : float
        Sensor mounting: ``C_nb = C_nv @ C_vb`` with ``C_vb = euler_to_dcm(roll, pitch, yaw)``;
        ``mount_yaw_rad`` is the angle of the sensor x axis from the vehicle forward axis,
        positive clockwise seen from above.
    last_position_error_m : float or None
        Write ``last_position.json`` with the start position displaced by this distance.
    last_position_age_s : float
        How long before the start the last position was saved.
    """

    name: str
    description: str
    motion: Motion
    duration_s: float | None = None
    truth_rate_hz: float = 200.0
    origin_lat_deg: float = 45.0628
    origin_lon_deg: float = 7.6620
    origin_height_m: float = 290.0
    start_utc: str = "2020-06-15T09:30:00Z"
    mount_roll_rad: float = 0.0
    mount_pitch_rad: float = 0.0
    mount_yaw_rad: float = 0.0
    imu: ImuConfig = field(default_factory=ImuConfig)
    gnss: GnssConfig = field(default_factory=GnssConfig)
    mag: MagConfig = field(default_factory=MagConfig)
    fixes: FixesConfig = field(default_factory=FixesConfig)
    last_position_error_m: float | None = None
    last_position_age_s: float = 3600.0


# ----------------------------------------------------------------------------- overrides


def _convert(value: Any, tp: Any, key: str) -> Any:
    """Convert ``value`` to the annotated type ``tp`` or raise ValueError naming ``key``."""
    origin = typing.get_origin(tp)
    args = typing.get_args(tp)
    if origin in (typing.Union, types.UnionType):
        if value is None or (isinstance(value, str) and value.strip().lower() in ("none", "null")):
            if type(None) in args:
                return None
        errors = []
        for a in args:
            if a is type(None):
                continue
            try:
                return _convert(value, a, key)
            except ValueError as exc:
                errors.append(str(exc))
        raise ValueError(errors[0] if errors else f"{key}: cannot convert {value!r}")
    if tp is bool:
        if isinstance(value, bool):
            return value
        if isinstance(value, str) and value.strip().lower() in (
            "true",
            "1",
            "yes",
            "on",
            "false",
            "0",
            "no",
            "off",
        ):
            return value.strip().lower() in ("true", "1", "yes", "on")
        raise ValueError(f"{key}: expected true or false, got {value!r}")
    if tp is int:
        if isinstance(value, bool):
            raise ValueError(f"{key}: expected an integer, got {value!r}")
        if isinstance(value, int):
            return value
        if isinstance(value, float) and value.is_integer():
            return int(value)
        if isinstance(value, str):
            try:
                return int(value.strip())
            except ValueError:
                pass
        raise ValueError(f"{key}: expected an integer, got {value!r}")
    if tp is float:
        if isinstance(value, bool):
            raise ValueError(f"{key}: expected a number, got {value!r}")
        if isinstance(value, int | float):
            return float(value)
        if isinstance(value, str):
            try:
                return float(value.strip())
            except ValueError:
                pass
        raise ValueError(f"{key}: expected a number, got {value!r}")
    if tp is str:
        if isinstance(value, str):
            return value
        raise ValueError(f"{key}: expected a string, got {value!r}")
    if origin is tuple:
        if isinstance(value, str):
            try:
                value = json.loads(value)
            except json.JSONDecodeError:
                raise ValueError(f"{key}: expected a JSON list such as [[100, 130]], got {value!r}") from None
        if not isinstance(value, list | tuple):
            raise ValueError(f"{key}: expected a list, got {value!r}")
        if len(args) == 2 and args[1] is Ellipsis:
            return tuple(_convert(v, args[0], key) for v in value)
        if len(value) != len(args):
            raise ValueError(f"{key}: expected {len(args)} items, got {value!r}")
        return tuple(_convert(v, a, key) for v, a in zip(value, args, strict=True))
    raise ValueError(f"{key}: unsupported parameter type {tp!r}")


def _hints(cls: type) -> dict[str, Any]:
    return typing.get_type_hints(cls)


def _set(obj: Any, path: list[str], value: Any, full_key: str) -> Any:
    name = path[0]
    prefix = full_key[: len(full_key) - len(".".join(path))]
    names = [f.name for f in fields(obj)]
    if len(path) == 1:
        if isinstance(obj, ImuConfig) and name not in names and name in {f.name for f in fields(ImuSpec)}:
            if name in ("name", "source"):
                raise ValueError(f"{full_key}: the preset name is set with imu.preset")
            tp = _hints(ImuSpec)[name]
            conv = _convert(value, tp, full_key)
            spec = (*tuple((k, v) for k, v in obj.spec if k != name), (name, conv))
            return replace(obj, spec=spec)
        if name not in names or name == "motion":
            raise ValueError(f"unknown parameter {full_key!r}; known: {', '.join(_keys(obj, prefix))}")
        tp = _hints(type(obj))[name]
        if is_dataclass(getattr(obj, name)):
            raise ValueError(f"{full_key} is a block; set one of its fields ({full_key}.<field>)")
        return replace(obj, **{name: _convert(value, tp, full_key)})
    if name not in names or not is_dataclass(getattr(obj, name)):
        raise ValueError(f"unknown parameter {full_key!r}; known: {', '.join(_keys(obj, prefix))}")
    return replace(obj, **{name: _set(getattr(obj, name), path[1:], value, full_key)})


def _keys(obj: Any, prefix: str = "") -> list[str]:
    out: list[str] = []
    for f in fields(obj):
        v = getattr(obj, f.name)
        if is_dataclass(v):
            out.extend(_keys(v, prefix + f.name + "."))
        elif f.name != "spec":
            out.append(prefix + f.name)
    if isinstance(obj, ImuConfig):
        out.extend(prefix + f.name for f in fields(ImuSpec) if f.name not in ("name", "source"))
    return out


def parameter_keys(config: ScenarioConfig) -> list[str]:
    """Every dotted key :func:`apply_overrides` accepts for ``config``."""
    return _keys(config)


def apply_overrides(config: ScenarioConfig, overrides: Mapping[str, object] | None) -> ScenarioConfig:
    """Return ``config`` with parameters changed by dotted keys.

    Parameters
    ----------
    config : ScenarioConfig
        The scenario's defaults.
    overrides : Mapping[str, object], optional
        ``{"imu.preset": "mpu6050", "duration_s": "600"}``; string values are converted to
        the field's type (JSON for lists).

    Returns
    -------
    ScenarioConfig
        A new configuration.

    Raises
    ------
    ValueError
        For an unknown key or a value of the wrong type.
    """
    out = config
    for key, value in (overrides or {}).items():
        if key in ("name", "description"):
            raise ValueError(f"{key!r} cannot be overridden")
        out = _set(out, key.split("."), value, key)
    return out


def config_to_dict(config: Any) -> dict[str, Any]:
    """A JSON-ready dict of a configuration dataclass (tuples as lists)."""
    d = asdict(config)
    if isinstance(config, ScenarioConfig):
        d["motion_type"] = type(config.motion).__name__
    return d
