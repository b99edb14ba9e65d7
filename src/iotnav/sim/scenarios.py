"""Named scenarios and the simulation pipeline (motion -> truth -> sensors).

Every scenario is a :class:`iotnav.sim.config.ScenarioConfig` default (see
:data:`SCENARIOS`), reproducible from a seed: independent random streams are spawned for
motion, IMU, GNSS, magnetometer and fixes, so switching one sensor off does not change the
others. Device time ``t`` starts at 0 at the first truth sample; ``utc = t + utc_offset_s``
with ``utc_offset_s`` the Unix time of ``start_utc``.

Rates: the truth is built at ``truth_rate_hz`` (200 Hz unless the scenario says otherwise);
IMU and GNSS rates must divide it. ``truth.csv`` is written at ``max(imu.rate_hz, 10)`` Hz
(10 Hz when there is no IMU), which must divide it too. A magnetometer sample is taken at the
IMU sample nearest its nominal time and shares that sample's recorded time.

Local frame: positions are in the tangent plane at the origin (:class:`iotnav.geo.LocalFrame`),
the frame of the flat-earth :mod:`iotnav.strapdown`. A level route in that plane rises above
the ellipsoid by ``d^2 / (2 R)``: 0.08 m at 1 km from the origin, 1.3 m at 4 km; the routes stay
within a few km of the origin.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field, replace
from datetime import datetime
from typing import Any

import numpy as np
import pandas as pd
from scipy.spatial.transform import Rotation

from iotnav.geo import LocalFrame, dcm_to_euler, euler_to_dcm
from iotnav.io.schema import GNSS_COLUMNS, IMU_COLUMNS, MAG_COLUMNS, coerce, empty_table
from iotnav.sim.config import (
    CarMotion,
    FixesConfig,
    GnssConfig,
    ImuConfig,
    MagConfig,
    ScenarioConfig,
    StaticMotion,
    TrackMotion,
    WalkMotion,
    apply_overrides,
)
from iotnav.sim.gnss_model import resolve_environment, simulate_gnss
from iotnav.sim.imu_model import ImuDraw, corrupt, resample
from iotnav.sim.mag_model import simulate_mag
from iotnav.sim.presets import IDEAL, ImuSpec, imu_preset, mag_preset
from iotnav.sim.trajectory import Profile, TrajectoryBuilder, Truth, add_gait, bag_carry, make_truth
from iotnav.strapdown import gravity_n

__all__ = ["SCENARIOS", "SimResult", "build", "default_config", "list_scenarios", "simulate"]

Progress = Callable[[float], None]

TRUTH_COLUMNS = (
    "t",
    "lat",
    "lon",
    "height",
    "north",
    "east",
    "down",
    "vn",
    "ve",
    "vd",
    "roll",
    "pitch",
    "yaw",
)
FIXES_COLUMNS = (
    "t_valid",
    "t_arrival",
    "lat",
    "lon",
    "height",
    "roll",
    "pitch",
    "yaw",
    "sigma_pos_m",
    "sigma_att_rad",
)


def _scenarios() -> dict[str, ScenarioConfig]:
    return {
        "static-courtyard": ScenarioConfig(
            name="static-courtyard",
            description="90 min static in a courtyard with multipath; LSM6DS3 at 4 Hz (Forno 2020 dataset A)",
            motion=StaticMotion(yaw_rad=0.6),
            duration_s=5400.0,
            imu=ImuConfig(preset="lsm6ds3", rate_hz=4.0),
            gnss=GnssConfig(
                environment="courtyard", cold_start=True, ttff_s=25.0, converge_tau_s=20.0, initial_pdop=8.0
            ),
        ),
        "scooter-laps": ScenarioConfig(
            name="scooter-laps",
            description="e-scooter laps of a 400 m track at 17.6 km/h, IMU x 90 deg clockwise of heading; "
            "LSM6DS3 at 40 Hz (Forno 2020 dataset B)",
            motion=TrackMotion(),
            mount_roll_rad=0.01,
            mount_pitch_rad=-0.015,
            mount_yaw_rad=math.radians(88.0),
            imu=ImuConfig(
                preset="lsm6ds3",
                rate_hz=40.0,
                vibration_acc_rms_mps2=0.8,
                vibration_gyro_rms_rads=0.03,
                vibration_freq_hz=17.0,
                vibration_speed_ref_mps=4.9,
            ),
            gnss=GnssConfig(environment="open-sky"),
        ),
        "walk-cold-boot": ScenarioConfig(
            name="walk-cold-boot",
            description="GPS cold boot in a courtyard, device in a bag on a walk around a parking lot; "
            "LSM6DS3 at 4 Hz, last known position stored (Forno 2020 dataset C)",
            motion=WalkMotion(),
            imu=ImuConfig(preset="lsm6ds3", rate_hz=4.0),
            gnss=GnssConfig(
                environment="courtyard",
                cold_start=True,
                ttff_s=45.0,
                converge_tau_s=40.0,
                initial_pdop=30.0,
                initial_offset_m=60.0,
            ),
            last_position_error_m=4.0,
            last_position_age_s=5400.0,
        ),
        "car-tunnel": ScenarioConfig(
            name="car-tunnel",
            description="car at urban and motorway speeds through tunnels (outages of 10-60 s); "
            "MPU-6050 at 100 Hz, GNSS 1 Hz",
            motion=CarMotion(route="tunnel"),
            duration_s=600.0,
            mount_roll_rad=0.03,
            mount_pitch_rad=-0.02,
            mount_yaw_rad=-math.pi / 2,
            imu=ImuConfig(
                preset="mpu6050",
                rate_hz=100.0,
                vibration_acc_rms_mps2=0.3,
                vibration_gyro_rms_rads=0.01,
                vibration_freq_hz=31.0,
            ),
            gnss=GnssConfig(
                environment="open-sky",
                outages_s=((150.0, 190.0), (255.0, 315.0), (380.0, 392.0), (440.0, 475.0), (530.0, 560.0)),
            ),
        ),
        "car-magnetometer": ScenarioConfig(
            name="car-magnetometer",
            description="40 s static then about 220 s of town driving with magnetometer (6 Hz), one 4 s GNSS gap "
            "and one magnetic disturbance; MPU-6050 at 50 Hz",
            motion=CarMotion(route="town", wait_start_s=40.0, urban_speed_kmh=40.0, turn_rate_dps=20.0),
            imu=ImuConfig(preset="mpu6050", rate_hz=50.0, vibration_acc_rms_mps2=0.2, vibration_freq_hz=22.0),
            gnss=GnssConfig(environment="open-sky", outages_s=((170.0, 174.0),)),
            mag=MagConfig(
                enabled=True, preset="hmc5883l", rate_hz=6.0, disturbances=((120.0, 132.0, 6.0, -12.0, 9.0),)
            ),
        ),
        "pedestrian-fixes": ScenarioConfig(
            name="pedestrian-fixes",
            description="walking a courtyard loop with image-based position+attitude fixes; "
            "Microstrain 3DM-GX3-35 class IMU at 100 Hz (or imu.preset=smartphone)",
            motion=WalkMotion(
                length_m=30.0,
                width_m=20.0,
                laps=2,
                wait_start_s=30.0,
                wait_end_s=10.0,
                carry="hand",
                heading_rad=0.4,
            ),
            mount_pitch_rad=-0.3,
            imu=ImuConfig(preset="3dm-gx3-35", rate_hz=100.0),
            gnss=GnssConfig(environment="courtyard"),
            fixes=FixesConfig(enabled=True),
        ),
        "static-imu-6h": ScenarioConfig(
            name="static-imu-6h",
            description="6 h static IMU recording for noise characterisation (Allan deviation); "
            "Microstrain 3DM-GX3-35 class at 100 Hz, no GNSS; in-run bias as flicker noise so the "
            "ADEV floor is 0.664 x the datasheet bias instability (IEEE Std 952)",
            motion=StaticMotion(yaw_rad=0.0),
            duration_s=6 * 3600.0,
            truth_rate_hz=100.0,
            imu=ImuConfig(preset="3dm-gx3-35", rate_hz=100.0, spec=(("bias_model", "flicker"),)),
            gnss=GnssConfig(enabled=False),
        ),
    }


#: Named scenarios: name -> default configuration.
SCENARIOS: dict[str, ScenarioConfig] = _scenarios()


def list_scenarios() -> list[str]:
    """Names of the named scenarios."""
    return list(SCENARIOS)


def default_config(name: str) -> ScenarioConfig:
    """The default configuration of scenario ``name``.

    Raises
    ------
    ValueError
        For an unknown name.
    """
    try:
        return SCENARIOS[name]
    except KeyError:
        raise ValueError(f"unknown scenario {name!r}; expected one of {', '.join(SCENARIOS)}") from None


# ----------------------------------------------------------------------------- motion


def _static(m: StaticMotion, rate: float, duration_s: float | None) -> Profile:
    if duration_s is None:
        raise ValueError("a static scenario needs duration_s")
    prof = TrajectoryBuilder(rate, m.yaw_rad).build(duration_s)
    prof.pitch = np.full(prof.n, m.pitch_rad)
    prof.roll = np.full(prof.n, m.roll_rad)
    return prof


def _track(m: TrackMotion, rate: float, duration_s: float | None) -> Profile:
    if m.straight_mode not in ("cruise", "accel-brake"):
        raise ValueError(f"motion.straight_mode: expected cruise or accel-brake, got {m.straight_mode!r}")
    b = TrajectoryBuilder(rate, m.heading_rad)
    b.stand(m.wait_start_s)
    sign = -1.0 if m.counter_clockwise else 1.0
    v_mean = m.mean_speed_kmh / 3.6
    L, r = m.straight_m, m.radius_m
    if m.straight_mode == "cruise":
        v_entry, gain = v_mean, 0.0
    else:
        v_entry = m.curve_speed_kmh / 3.6
        lap_t = (2 * L + 2 * math.pi * r) / v_mean
        t_straight = 0.5 * (lap_t - 2 * math.pi * r / v_entry)
        if t_straight <= 0:
            raise ValueError("motion.curve_speed_kmh is too low for mean_speed_kmh on this track")
        gain = 2.0 * (L / t_straight - v_entry)
        if gain < 0:
            raise ValueError("motion.curve_speed_kmh must be below the mean straight speed")
    d_acc = 0.5 * v_entry * (v_entry / m.accel_mps2)
    if d_acc >= L:
        raise ValueError("motion.accel_mps2 too low: the start takes longer than a straight")
    b.change_speed(v_entry, m.accel_mps2)
    for lap in range(m.laps):
        for side in range(2):
            length = L - d_acc if (lap == 0 and side == 0) else L
            if gain > 0:
                b.surge_straight(length, gain)
            else:
                b.cruise(distance_m=length)
            b.arc(sign * math.pi, r)
    b.change_speed(0.0, m.accel_mps2)
    b.stand(m.wait_end_s)
    return b.build(duration_s)


def _walk(
    m: WalkMotion, rate: float, duration_s: float | None, rng: np.random.Generator
) -> tuple[Profile, Rotation | None]:
    if m.carry not in ("bag", "hand"):
        raise ValueError(f"motion.carry: expected bag or hand, got {m.carry!r}")
    b = TrajectoryBuilder(rate, m.heading_rad)
    b.stand(m.wait_start_s)
    acc = 0.7
    d_acc = 0.5 * m.speed_mps * (m.speed_mps / acc)
    r_turn = m.speed_mps / m.turn_rate_rad_s
    b.change_speed(m.speed_mps, acc)
    sides = (m.length_m, m.width_m, m.length_m, m.width_m)
    for lap in range(m.laps):
        for i, side in enumerate(sides):
            length = side - 2 * r_turn - (d_acc if lap == 0 and i == 0 else 0.0)
            if length <= 0:
                raise ValueError("motion: the loop is too small for the walking speed and turn rate")
            b.cruise(distance_m=length)
            b.turn(math.pi / 2, m.turn_rate_rad_s)
    b.change_speed(0.0, acc)
    b.stand(m.wait_end_s)
    prof = b.build(duration_s)
    w = add_gait(prof, m.cadence_hz, m.vertical_amp_m, m.lateral_amp_m, m.speed_mps)
    carry = bag_carry(prof.t, w, m.bag_attitude_sigma_rad, m.bag_knot_s, rng) if m.carry == "bag" else None
    return prof, carry


def _car(m: CarMotion, rate: float, duration_s: float | None) -> Profile:
    b = TrajectoryBuilder(rate, m.heading_rad)
    vu, vh = m.urban_speed_kmh / 3.6, m.highway_speed_kmh / 3.6
    rate_turn = math.radians(m.turn_rate_dps)
    grade = math.atan(m.max_slope_pct / 100.0)
    b.stand(m.wait_start_s)

    def corner(angle: float, speed_factor: float = 0.4) -> None:
        b.change_speed(vu * speed_factor, 2.0)
        b.turn(angle, rate_turn)
        b.change_speed(vu, 1.5)

    if m.route == "tunnel":
        target = 600.0 if duration_s is None else duration_s
        b.change_speed(vu, 1.5)
        b.cruise(15.0)
        corner(math.pi / 2)
        b.cruise(20.0)
        corner(-math.pi / 2)
        b.slope(grade * 0.6, 5.0).cruise(8.0).slope(0.0, 5.0)
        b.change_speed(vh, 1.2)
        k = 0
        while b.duration_s < target - 45.0:
            g = grade if k % 2 == 0 else -grade
            b.slope(g, 6.0).cruise(12.0).slope(0.0, 6.0)
            b.arc(math.pi / 2, 600.0)
            k += 1
        b.change_speed(vu, 1.5)
        corner(math.pi / 2)
        b.cruise(5.0)
        b.change_speed(0.0, 2.0)
        b.stand(5.0)
    elif m.route == "town":
        b.change_speed(vu, 1.5)
        b.cruise(20.0)
        corner(math.pi / 2)
        b.cruise(15.0)
        b.change_speed(0.0, 2.5)
        b.stand(8.0)  # traffic light
        b.change_speed(vu, 1.5)
        b.slope(grade, 4.0).cruise(10.0).slope(0.0, 4.0)
        corner(-math.pi / 2)
        b.cruise(18.0)
        corner(-math.pi / 2)
        b.cruise(12.0)
        b.change_speed(vu * 0.6, 1.5).cruise(6.0).change_speed(vu, 1.5)  # roundabout approach
        b.turn(math.pi, rate_turn)  # around the roundabout
        b.cruise(15.0)
        corner(math.pi / 2)
        b.cruise(10.0)
        b.change_speed(0.0, 2.0)
        b.stand(5.0)
    else:
        raise ValueError(f"motion.route: expected tunnel or town, got {m.route!r}")
    return b.build(duration_s)


def _motion(cfg: ScenarioConfig, rate: float, rng: np.random.Generator) -> tuple[Profile, Rotation | None]:
    m = cfg.motion
    if isinstance(m, StaticMotion):
        return _static(m, rate, cfg.duration_s), None
    if isinstance(m, TrackMotion):
        return _track(m, rate, cfg.duration_s), None
    if isinstance(m, WalkMotion):
        return _walk(m, rate, cfg.duration_s, rng)
    if isinstance(m, CarMotion):
        return _car(m, rate, cfg.duration_s), None
    raise TypeError(f"unknown motion {type(m).__name__}")


# ----------------------------------------------------------------------------- pipeline


@dataclass
class SimResult:
    """A simulated scenario in memory.

    Attributes
    ----------
    config : ScenarioConfig
        The configuration used (defaults plus overrides).
    seed : int
        Random seed.
    utc_offset_s : float
        ``utc = t + utc_offset_s``.
    truth : pandas.DataFrame
        Columns :data:`TRUTH_COLUMNS`: device time (s), lat/lon (deg), ellipsoidal height (m),
        NED position (m) and velocity (m/s) of the IMU, vehicle attitude ``C_nv`` as roll,
        pitch, yaw (rad), at ``max(imu.rate_hz, 10)`` Hz.
    imu, mag, gnss : pandas.DataFrame
        Sensor outputs in the :mod:`iotnav.io.schema` forms.
    fixes : pandas.DataFrame or None
        Absolute fixes (:data:`FIXES_COLUMNS`), device attitude ``C_nb`` angles.
    last_position : dict or None
        ``{"lat", "lon", "height", "t_saved_utc"}``.
    meta : dict
        Resolved sensor parameters and the constants drawn (echoed into ``scenario.json``).
    gnss_extras : dict
        Per-epoch position / velocity errors, outlier flags and satellite ids.
    internal : Truth or None
        Truth at the internal rate (``build(..., keep_truth=True)``).
    """

    config: ScenarioConfig
    seed: int
    utc_offset_s: float
    truth: pd.DataFrame
    imu: pd.DataFrame
    mag: pd.DataFrame
    gnss: pd.DataFrame
    fixes: pd.DataFrame | None = None
    last_position: dict[str, float] | None = None
    meta: dict[str, Any] = field(default_factory=dict)
    gnss_extras: dict[str, np.ndarray] = field(default_factory=dict)
    internal: Truth | None = None

    def mag_calibration(self) -> tuple[tuple[float, ...], tuple[float, ...]]:
        """The user's magnetometer calibration: the hard and soft iron drawn for this run.

        What a calibration routine would find (the paper's sensors are "previously
        calibrated"), in the form the engines take (``mag_hard_iron_ut``, ``mag_soft_iron``).

        Returns
        -------
        hard_iron_ut : tuple of float
            Offset in the sensor frame, uT (3).
        soft_iron : tuple of float
            Row-major 3x3 matrix (9).

        Raises
        ------
        ValueError
            When the scenario has no magnetometer.
        """
        md = self.meta.get("mag_draw")
        if md is None:
            raise ValueError("this scenario has no magnetometer")
        hard = tuple(float(v) for v in md["hard_iron_ut"])
        soft = tuple(float(v) for v in np.ravel(md["soft_iron"]))
        return hard, soft


def _factor(rate: float, sub: float, what: str) -> int:
    k = rate / sub
    if sub <= 0 or abs(k - round(k)) > 1e-9 or round(k) < 1:
        raise ValueError(f"{what} = {sub:g} Hz must divide truth_rate_hz = {rate:g} Hz")
    return round(k)


def build(
    name: str,
    seed: int = 0,
    overrides: Mapping[str, object] | None = None,
    *,
    keep_truth: bool = False,
    progress: Progress | None = None,
) -> SimResult:
    """Simulate a named scenario.

    Parameters
    ----------
    name : str
        One of :func:`list_scenarios`.
    seed : int
        Random seed; the same seed and overrides give identical results.
    overrides : Mapping[str, object], optional
        Dotted-key parameter changes (``{"imu.preset": "mpu6050", "duration_s": 600}``).
    keep_truth : bool
        Keep the internal-rate truth in :attr:`SimResult.internal`.
    progress : callable, optional
        Called with the fraction of work done (0..1).

    Returns
    -------
    SimResult
    """
    cfg = apply_overrides(default_config(name), overrides)
    return simulate(cfg, seed, keep_truth=keep_truth, progress=progress)


def simulate(
    cfg: ScenarioConfig, seed: int = 0, *, keep_truth: bool = False, progress: Progress | None = None
) -> SimResult:
    """Simulate a scenario configuration (see :func:`build`)."""
    report = progress or (lambda _x: None)
    R = cfg.truth_rate_hz
    imu_m = _factor(R, cfg.imu.rate_hz, "imu.rate_hz") if cfg.imu.enabled else 1
    out_rate = max(cfg.imu.rate_hz, 10.0) if cfg.imu.enabled else 10.0
    out_m = _factor(R, out_rate, "truth output rate max(imu.rate_hz, 10)")
    gnss_m = _factor(R, cfg.gnss.rate_hz, "gnss.rate_hz") if cfg.gnss.enabled else 1
    if cfg.gnss.enabled and not 1.0 <= cfg.gnss.rate_hz <= 20.0:
        raise ValueError(f"gnss.rate_hz = {cfg.gnss.rate_hz:g}: expected 1 to 20 Hz")
    if cfg.mag.enabled and not cfg.imu.enabled:
        raise ValueError("mag.enabled needs imu.enabled (magnetometer columns live in imu.csv)")
    streams = [np.random.default_rng(s) for s in np.random.SeedSequence(seed).spawn(6)]
    rng_motion, rng_imu, rng_gnss, rng_mag, rng_fix, rng_misc = streams
    frame = LocalFrame(cfg.origin_lat_deg, cfg.origin_lon_deg, cfg.origin_height_m)
    g_n = gravity_n(cfg.origin_lat_deg, cfg.origin_height_m)
    utc_offset = datetime.fromisoformat(cfg.start_utc.replace("Z", "+00:00")).timestamp()
    report(0.02)

    profile, carry = _motion(cfg, R, rng_motion)
    C_vb = euler_to_dcm(cfg.mount_roll_rad, cfg.mount_pitch_rad, cfg.mount_yaw_rad)
    truth = make_truth(profile, C_vb, g_n, carry)
    report(0.35)
    meta: dict[str, Any] = {"g_n_mps2": g_n.tolist(), "truth_output_rate_hz": out_rate}

    # IMU
    imu_df = empty_table(IMU_COLUMNS)
    mag_df = empty_table(MAG_COLUMNS)
    if cfg.imu.enabled:
        spec: ImuSpec = imu_preset(cfg.imu.preset, **dict(cfg.imu.spec))
        used = spec if cfg.imu.errors else replace(IDEAL, name=f"{spec.name} (errors off)")
        f = resample(truth.f_b, imu_m, cfg.imu.anti_alias)
        w = resample(truth.omega_b, imu_m, cfg.imu.anti_alias)
        n_imu = len(f)
        t_imu = truth.t[: n_imu * imu_m : imu_m]
        speed = truth.speed[: n_imu * imu_m : imu_m]
        vib = cfg.imu.errors
        t_rec, acc, gyro, draw = corrupt(
            t_imu,
            f,
            w,
            speed,
            used,
            vib_acc_rms=cfg.imu.vibration_acc_rms_mps2 if vib else 0.0,
            vib_gyro_rms=cfg.imu.vibration_gyro_rms_rads if vib else 0.0,
            vib_freq_hz=cfg.imu.vibration_freq_hz,
            vib_speed_ref=cfg.imu.vibration_speed_ref_mps,
            rng=rng_imu,
        )
        imu_df = coerce(
            pd.DataFrame(
                {
                    "t": t_rec,
                    "acc_x": acc[:, 0],
                    "acc_y": acc[:, 1],
                    "acc_z": acc[:, 2],
                    "gyro_x": gyro[:, 0],
                    "gyro_y": gyro[:, 1],
                    "gyro_z": gyro[:, 2],
                }
            ),
            IMU_COLUMNS,
        )
        meta["imu_spec"] = spec.__dict__ | {"errors_applied": cfg.imu.errors}
        meta["imu_draw"] = _draw_dict(draw)
        if cfg.mag.enabled:
            mspec = mag_preset(cfg.mag.preset)
            t_nom = np.arange(0.0, t_imu[-1] + 1e-9, 1.0 / cfg.mag.rate_hz)
            idx = np.unique(np.clip(np.round(t_nom * cfg.imu.rate_hz).astype(int), 0, n_imu - 1))
            mag, mdraw = simulate_mag(cfg.mag, mspec, t_imu[idx], truth.q_nb[idx * imu_m], rng_mag)
            mag_df = coerce(
                pd.DataFrame(
                    {"t": t_rec[idx], "mag_x_ut": mag[:, 0], "mag_y_ut": mag[:, 1], "mag_z_ut": mag[:, 2]}
                ),
                MAG_COLUMNS,
            )
            meta["mag_spec"] = mspec.__dict__
            meta["mag_draw"] = {k: np.asarray(v).tolist() for k, v in mdraw.items()}
    report(0.55)

    # GNSS
    gnss_df = empty_table(GNSS_COLUMNS)
    extras: dict[str, np.ndarray] = {}
    if cfg.gnss.enabled:
        idx = np.arange(0, len(truth.t), gnss_m)
        gnss_df, extras = simulate_gnss(
            cfg.gnss, truth.t[idx], truth.p_n[idx], truth.v_n[idx], frame, utc_offset, rng_gnss
        )
        env, sh, sv, th, tv, orate = resolve_environment(cfg.gnss)
        meta["gnss_environment"] = env.__dict__ | {
            "sigma_h_m_used": sh,
            "sigma_v_m_used": sv,
            "tau_h_s_used": th,
            "tau_v_s_used": tv,
            "outliers_per_hour_used": orate,
        }
    report(0.75)

    # truth table
    idx = np.arange(0, len(truth.t), out_m)
    lat, lon, h = frame.from_ned(truth.p_n[idx])
    tr = {
        "t": truth.t[idx],
        "lat": lat,
        "lon": lon,
        "height": h,
        "north": truth.p_n[idx, 0],
        "east": truth.p_n[idx, 1],
        "down": truth.p_n[idx, 2],
        "vn": truth.v_n[idx, 0],
        "ve": truth.v_n[idx, 1],
        "vd": truth.v_n[idx, 2],
        "roll": truth.euler_nv[idx, 0],
        "pitch": truth.euler_nv[idx, 1],
        "yaw": truth.euler_nv[idx, 2],
    }
    truth_df = pd.DataFrame(tr)

    fixes_df = _fixes(cfg.fixes, truth, frame, rng_fix) if cfg.fixes.enabled else None
    last = None
    if cfg.last_position_error_m is not None:
        ang = rng_misc.uniform(0.0, 2.0 * np.pi)
        p = truth.p_n[0] + cfg.last_position_error_m * np.array([np.cos(ang), np.sin(ang), 0.0])
        la, lo, hh = frame.from_ned(p)
        last = {
            "lat": float(la),
            "lon": float(lo),
            "height": float(hh),
            "t_saved_utc": float(utc_offset - cfg.last_position_age_s),
        }
    report(0.85)
    return SimResult(
        config=cfg,
        seed=seed,
        utc_offset_s=utc_offset,
        truth=truth_df,
        imu=imu_df,
        mag=mag_df,
        gnss=gnss_df,
        fixes=fixes_df,
        last_position=last,
        meta=meta,
        gnss_extras=extras,
        internal=truth if keep_truth else None,
    )


def _draw_dict(draw: ImuDraw) -> dict[str, list[Any]]:
    return {k: np.asarray(v).tolist() for k, v in draw.__dict__.items()}


def _fixes(cfg: FixesConfig, truth: Truth, frame: LocalFrame, rng: np.random.Generator) -> pd.DataFrame:
    R = 1.0 / (truth.t[1] - truth.t[0])
    t_valid = np.arange(cfg.interval_s, truth.t[-1] + 1e-9, cfg.interval_s)
    idx = np.clip(np.round(t_valid * R).astype(int), 0, len(truth.t) - 1)
    t_valid = truth.t[idx]
    pos = truth.p_n[idx] + rng.normal(0.0, cfg.sigma_pos_m, (len(idx), 3))
    lat, lon, h = frame.from_ned(pos)
    err = Rotation.from_rotvec(rng.normal(0.0, cfg.sigma_att_rad, (len(idx), 3)))
    C = (err * Rotation.from_quat(truth.q_nb[idx])).as_matrix()
    roll, pitch, yaw = dcm_to_euler(C)
    return pd.DataFrame(
        {
            "t_valid": t_valid,
            "t_arrival": t_valid + cfg.latency_s,
            "lat": lat,
            "lon": lon,
            "height": h,
            "roll": roll,
            "pitch": pitch,
            "yaw": yaw,
            "sigma_pos_m": cfg.sigma_pos_m,
            "sigma_att_rad": cfg.sigma_att_rad,
        }
    )
