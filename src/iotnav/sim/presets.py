"""Sensor presets: IMU and magnetometer error parameters from datasheets.

Datasheet tolerances written as "±X" (turn-on bias, sensitivity tolerance, cross-axis
sensitivity) are read as 3-sigma bounds of a part-to-part (turn-on) distribution: the
simulator draws ``N(0, (X/3)^2)``. Values the datasheet does not give are marked
*assumed* and chosen as typical for the sensor class; override them per scenario
(``imu.gyro_bias_instability_dph=5``).

Units are in the field names (``ug_rthz`` = micro-g per square-root hertz, ``mdps_rthz`` =
milli-degree per second per square-root hertz, ``dph`` = degree per hour, ``mg``, ``dps``,
``ppm`` and ``%``); :mod:`iotnav.sim.imu_model` converts them to SI once.
"""

from __future__ import annotations

from dataclasses import dataclass, fields, replace

__all__ = ["IMU_PRESETS", "MAG_PRESETS", "ImuSpec", "MagSpec", "imu_preset", "mag_preset"]


@dataclass(frozen=True)
class ImuSpec:
    """Error parameters of a 3-axis accelerometer + 3-axis gyroscope (per axis, 1-sigma).

    Attributes
    ----------
    name : str
        Preset name.
    source : str
        Datasheet (and revision) the values come from.
    acc_noise_density_ug_rthz, gyro_noise_density_mdps_rthz : float
        White-noise density (the Allan deviation at tau = 1 s).
    acc_turn_on_bias_mg, gyro_turn_on_bias_dps : float
        1-sigma of the constant bias drawn at power-on.
    acc_bias_instability_mg, gyro_bias_instability_dph : float
        Bias instability ``B`` of the in-run bias process (see :mod:`iotnav.sim.imu_model`):
        for ``bias_model="flicker"`` the IEEE Std 952 meaning (flat Allan deviation floor
        ``0.664 B``, PSD ``B^2 / (2 pi f)``), for ``"gauss-markov"`` the peak of the Allan
        deviation.
    bias_correlation_time_s : float
        Correlation time of the Gauss-Markov in-run bias (``bias_model="gauss-markov"`` only).
    bias_model : str
        ``flicker`` (1/f noise, what an Allan analysis calls bias instability; a sum of
        Gauss-Markov processes with log-spaced correlation times, see
        :func:`iotnav.sim.imu_model.flicker_noise`), ``gauss-markov`` (one first-order process,
        default) or ``random-walk``.
    acc_random_walk_mg_rts, gyro_random_walk_dph_rts : float
        Bias random-walk intensity (for ``bias_model="random-walk"``), per sqrt(s).
    acc_scale_factor_pct, gyro_scale_factor_pct : float
        1-sigma scale-factor error.
    acc_misalignment_pct, gyro_misalignment_pct : float
        1-sigma cross-axis coupling (each off-diagonal element).
    acc_range_g, gyro_range_dps : float
        Full scale; outputs saturate there.
    acc_lsb_mg, gyro_lsb_mdps : float
        Output resolution (0: no quantisation).
    timestamp_jitter_ms : float
        1-sigma jitter of the recorded sample times.
    """

    name: str
    source: str
    acc_noise_density_ug_rthz: float
    gyro_noise_density_mdps_rthz: float
    acc_turn_on_bias_mg: float
    gyro_turn_on_bias_dps: float
    acc_bias_instability_mg: float
    gyro_bias_instability_dph: float
    bias_correlation_time_s: float
    acc_scale_factor_pct: float
    gyro_scale_factor_pct: float
    acc_misalignment_pct: float
    gyro_misalignment_pct: float
    acc_range_g: float
    gyro_range_dps: float
    acc_lsb_mg: float
    gyro_lsb_mdps: float
    timestamp_jitter_ms: float = 0.0
    bias_model: str = "gauss-markov"
    acc_random_walk_mg_rts: float = 0.0
    gyro_random_walk_dph_rts: float = 0.0


#: ST LSM6DS3 (seed tracker's IMU). Datasheet DocID026899 Rev 10: acceleration noise
#: density 90 ug/sqrt(Hz) (high-performance mode), rate noise density 7 mdps/sqrt(Hz),
#: zero-g level offset accuracy +/-40 mg, zero-rate level +/-10 dps, sensitivity 0.061 mg/LSB
#: at +/-2 g and 8.75 mdps/LSB at +/-245 dps (16-bit). Sensitivity tolerance, cross-axis and
#: in-run stability are not in the datasheet: assumed 1 %, 1 %, 0.1 mg and 20 deg/h.
LSM6DS3 = ImuSpec(
    name="lsm6ds3",
    source="ST LSM6DS3 datasheet DocID026899 Rev 10",
    acc_noise_density_ug_rthz=90.0,
    gyro_noise_density_mdps_rthz=7.0,
    acc_turn_on_bias_mg=40.0 / 3.0,
    gyro_turn_on_bias_dps=10.0 / 3.0,
    acc_bias_instability_mg=0.1,
    gyro_bias_instability_dph=20.0,
    bias_correlation_time_s=100.0,
    acc_scale_factor_pct=1.0 / 3.0,
    gyro_scale_factor_pct=1.0 / 3.0,
    acc_misalignment_pct=1.0 / 3.0,
    gyro_misalignment_pct=1.0 / 3.0,
    acc_range_g=2.0,
    gyro_range_dps=245.0,
    acc_lsb_mg=0.061,
    gyro_lsb_mdps=8.75,
    timestamp_jitter_ms=1.0,
)

#: InvenSense MPU-6050. Product specification PS-MPU-6000A-00 Rev 3.4: accelerometer noise
#: power spectral density 400 ug/sqrt(Hz), zero-g initial calibration tolerance +/-50 mg
#: (X, Y; +/-80 mg Z, the X/Y value is used), initial sensitivity tolerance +/-3 %,
#: cross-axis sensitivity +/-2 %; gyroscope rate noise spectral density 0.005 dps/sqrt(Hz),
#: initial ZRO tolerance +/-20 dps, sensitivity scale-factor tolerance +/-3 %, cross-axis
#: sensitivity +/-2 %; 16-bit, 16384 LSB/g at +/-2 g, 131 LSB/(dps) at +/-250 dps. In-run
#: stability not specified: assumed 0.2 mg and 30 deg/h.
MPU6050 = ImuSpec(
    name="mpu6050",
    source="InvenSense MPU-6000/MPU-6050 Product Specification PS-MPU-6000A-00 Rev 3.4",
    acc_noise_density_ug_rthz=400.0,
    gyro_noise_density_mdps_rthz=5.0,
    acc_turn_on_bias_mg=50.0 / 3.0,
    gyro_turn_on_bias_dps=20.0 / 3.0,
    acc_bias_instability_mg=0.2,
    gyro_bias_instability_dph=30.0,
    bias_correlation_time_s=100.0,
    acc_scale_factor_pct=1.0,
    gyro_scale_factor_pct=1.0,
    acc_misalignment_pct=2.0 / 3.0,
    gyro_misalignment_pct=2.0 / 3.0,
    acc_range_g=2.0,
    gyro_range_dps=250.0,
    acc_lsb_mg=1000.0 / 16384.0,
    gyro_lsb_mdps=1000.0 / 131.0,
    timestamp_jitter_ms=0.5,
)

#: Smartphone-grade IMU, modelled on the Bosch BMI160 found in many phones. Datasheet
#: BST-BMI160-DS000: accelerometer output noise density 180 ug/sqrt(Hz), zero-g offset
#: +/-40 mg; gyroscope output noise density 0.007 dps/sqrt(Hz), zero-rate offset +/-3 dps;
#: 16-bit, 0.061 mg/LSB at +/-2 g, 7.6 mdps/LSB at +/-250 dps. Sensitivity tolerance,
#: cross-axis, in-run stability and the timestamp jitter of a phone OS are assumed
#: (1 %, 1 %, 0.1 mg, 10 deg/h, 2 ms).
SMARTPHONE = ImuSpec(
    name="smartphone",
    source="Bosch BMI160 datasheet BST-BMI160-DS000 (smartphone-class IMU)",
    acc_noise_density_ug_rthz=180.0,
    gyro_noise_density_mdps_rthz=7.0,
    acc_turn_on_bias_mg=40.0 / 3.0,
    gyro_turn_on_bias_dps=3.0 / 3.0,
    acc_bias_instability_mg=0.1,
    gyro_bias_instability_dph=10.0,
    bias_correlation_time_s=100.0,
    acc_scale_factor_pct=1.0 / 3.0,
    gyro_scale_factor_pct=1.0 / 3.0,
    acc_misalignment_pct=1.0 / 3.0,
    gyro_misalignment_pct=1.0 / 3.0,
    acc_range_g=8.0,
    gyro_range_dps=1000.0,
    acc_lsb_mg=0.244,
    gyro_lsb_mdps=30.5,
    timestamp_jitter_ms=2.0,
)

#: Microstrain 3DM-GX3-35 class (industrial MEMS AHRS with GNSS). Datasheet 8400-0034:
#: accelerometer range +/-5 g, in-run bias stability +/-0.04 mg, initial bias error
#: +/-0.002 g, scale-factor stability +/-0.05 %, noise density 80 ug/sqrt(Hz); gyroscope range
#: +/-300 dps, in-run bias stability +/-18 deg/h, initial bias error +/-0.25 dps, scale-factor
#: stability +/-0.05 %, noise density 0.03 dps/sqrt(Hz); alignment error +/-0.05 deg
#: (0.087 %). Outputs are calibrated floats (no quantisation).
MICROSTRAIN_3DM_GX3_35 = ImuSpec(
    name="3dm-gx3-35",
    source="LORD Microstrain 3DM-GX3-35 datasheet 8400-0034",
    acc_noise_density_ug_rthz=80.0,
    gyro_noise_density_mdps_rthz=30.0,
    acc_turn_on_bias_mg=2.0 / 3.0,
    gyro_turn_on_bias_dps=0.25 / 3.0,
    acc_bias_instability_mg=0.04,
    gyro_bias_instability_dph=18.0,
    bias_correlation_time_s=300.0,
    acc_scale_factor_pct=0.05 / 3.0,
    gyro_scale_factor_pct=0.05 / 3.0,
    acc_misalignment_pct=0.087 / 3.0,
    gyro_misalignment_pct=0.087 / 3.0,
    acc_range_g=5.0,
    gyro_range_dps=300.0,
    acc_lsb_mg=0.0,
    gyro_lsb_mdps=0.0,
    timestamp_jitter_ms=0.0,
)

#: Error-free IMU (for consistency checks).
IDEAL = ImuSpec(
    name="ideal",
    source="no errors",
    acc_noise_density_ug_rthz=0.0,
    gyro_noise_density_mdps_rthz=0.0,
    acc_turn_on_bias_mg=0.0,
    gyro_turn_on_bias_dps=0.0,
    acc_bias_instability_mg=0.0,
    gyro_bias_instability_dph=0.0,
    bias_correlation_time_s=100.0,
    acc_scale_factor_pct=0.0,
    gyro_scale_factor_pct=0.0,
    acc_misalignment_pct=0.0,
    gyro_misalignment_pct=0.0,
    acc_range_g=1e6,
    gyro_range_dps=1e9,
    acc_lsb_mg=0.0,
    gyro_lsb_mdps=0.0,
)

IMU_PRESETS: dict[str, ImuSpec] = {
    s.name: s for s in (LSM6DS3, MPU6050, SMARTPHONE, MICROSTRAIN_3DM_GX3_35, IDEAL)
}


@dataclass(frozen=True)
class MagSpec:
    """Error parameters of a 3-axis magnetometer (per axis, 1-sigma unless stated).

    Attributes
    ----------
    name, source : str
        Preset name and datasheet.
    noise_ut : float
        White noise per sample, microtesla RMS.
    lsb_ut : float
        Resolution, microtesla (0: none).
    range_ut : float
        Full scale, microtesla.
    hard_iron_ut : float
        1-sigma of the constant offset (sensor offset plus magnetised parts of the host).
    soft_iron_pct : float
        1-sigma of the elements of the soft-iron matrix ``I + S`` (symmetric ``S``).
    """

    name: str
    source: str
    noise_ut: float
    lsb_ut: float
    range_ut: float
    hard_iron_ut: float
    soft_iron_pct: float


#: ST LIS3MDL (companion of the LSM6DS3 on many boards). Datasheet DocID024204 Rev 5: RMS noise
#: 3.2 mgauss (0.32 uT, X/Y, ultra-high-performance, +/-4 gauss), sensitivity 6842 LSB/gauss
#: (0.0146 uT/LSB), full scale +/-4 gauss (400 uT), zero-gauss level +/-1 gauss is the worst case;
#: hard iron of the host (10 uT) and soft iron (3 %) are assumed typical of a small board.
LIS3MDL = MagSpec(
    name="lis3mdl",
    source="ST LIS3MDL datasheet DocID024204 Rev 5",
    noise_ut=0.32,
    lsb_ut=100.0 / 6842.0,
    range_ut=400.0,
    hard_iron_ut=10.0,
    soft_iron_pct=3.0,
)

#: Honeywell HMC5883L. Datasheet Rev E: noise floor 2 milli-gauss (0.2 uT); default gain
#: 1090 LSB/gauss at +/-1.3 gauss (0.092 uT/LSB, 130 uT full scale); host hard/soft iron
#: assumed (10 uT, 3 %).
HMC5883L = MagSpec(
    name="hmc5883l",
    source="Honeywell HMC5883L datasheet Rev E",
    noise_ut=0.2,
    lsb_ut=100.0 / 1090.0,
    range_ut=130.0,
    hard_iron_ut=10.0,
    soft_iron_pct=3.0,
)

IDEAL_MAG = MagSpec(
    name="ideal",
    source="no errors",
    noise_ut=0.0,
    lsb_ut=0.0,
    range_ut=1e9,
    hard_iron_ut=0.0,
    soft_iron_pct=0.0,
)

MAG_PRESETS: dict[str, MagSpec] = {s.name: s for s in (LIS3MDL, HMC5883L, IDEAL_MAG)}


def _lookup(table: dict, name: str, kind: str):  # type: ignore[no-untyped-def]
    try:
        return table[name]
    except KeyError:
        raise ValueError(f"unknown {kind} preset {name!r}; expected one of {', '.join(table)}") from None


def imu_preset(name: str, **overrides: float | str) -> ImuSpec:
    """The IMU preset ``name`` with some fields replaced.

    Raises
    ------
    ValueError
        For an unknown preset or field.
    """
    spec: ImuSpec = _lookup(IMU_PRESETS, name, "IMU")
    known = {f.name for f in fields(ImuSpec)}
    bad = set(overrides) - known
    if bad:
        raise ValueError(f"unknown IMU parameter(s) {sorted(bad)}; expected some of {sorted(known)}")
    return replace(spec, **overrides)  # type: ignore[arg-type]


def mag_preset(name: str) -> MagSpec:
    """The magnetometer preset ``name``."""
    spec: MagSpec = _lookup(MAG_PRESETS, name, "magnetometer")
    return spec
