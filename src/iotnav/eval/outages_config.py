"""Configuration of the real-data GNSS-outage study (:mod:`iotnav.eval.outages`).

:class:`DatasetProfile` holds what the study needs to know about one recording (values from
the dataset README: lever arms in metres in ``b``, mount angles in degrees), :data:`DATASETS`
the profiles of the rtklibexplorer ``drive_0708`` and ``walk_0827`` recordings,
:class:`OutageConfig` the study's tunables (rates in Hz, lengths and spacings in seconds) and
:class:`OutageResult` its tables; the baseline labels name the GNSS-only rows.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import numpy.typing as npt
import pandas as pd

from iotnav.geo import euler_to_dcm
from iotnav.sim.config import GnssConfig

FloatArray = npt.NDArray[np.float64]


#: Label of the GNSS-only, last-position-hold baseline (the last fix held).
HOLD = "hold"
#: Former name of :data:`HOLD`.
GNSS_HOLD = HOLD
#: Label of the dead-reckoning baseline: the last fix moved on at its own reported velocity.
DR_VELOCITY = "dr-velocity"
#: The baseline rows of every outage table.
BASELINES = (HOLD, DR_VELOCITY)


@dataclass(frozen=True)
class DatasetProfile:
    """What the study needs to know about one recording (from the dataset README).

    Attributes
    ----------
    name : str
        Folder name (``drive_0708``, ``walk_0827``).
    pos_file, imu_file : str
        RTK solution and raw IMU file names inside the folder.
    vehicle : str
        ``car`` (non-holonomic constraint applies) or ``pedestrian`` (no NHC).
    imu_time_offset_s : float
        Added to the IMU time stamps (the author's logging delay), s.
    author_mount_rpy_deg : tuple of float
        The author's IMU mounting rotation, RPY in degrees, applied as ``C(rpy) @ acc``
        (a passive rotation: ``C_vb = C(rpy)^T`` in iotnav's convention).
    eskf : dict
        :class:`iotnav.engines.eskf.EskfConfig` fields for this IMU and platform.
    extra_engines : tuple of str
        Engines that apply to this platform only and always run on it besides
        ``OutageConfig.engines`` (``pdr``, pedestrian dead reckoning, on the walk).
    """

    name: str
    pos_file: str
    imu_file: str
    vehicle: str
    imu_time_offset_s: float
    author_mount_rpy_deg: tuple[float, float, float]
    eskf: Mapping[str, Any] = field(default_factory=dict)
    extra_engines: tuple[str, ...] = ()

    def author_C_vb(self) -> FloatArray:
        """The author's mount as ``C_vb`` (maps ``b`` to the vehicle frame ``v``)."""
        return euler_to_dcm(*np.radians(self.author_mount_rpy_deg)).T


# ICM-45686 on a car roof: the white noise includes engine vibration (gyro std at standstill up
# to 2.7 deg/s at 100 Hz), so the densities are well above the datasheet's; as in
# benchmarks/bench_eskf.py.
_ICM45686_ESKF: dict[str, Any] = {
    "acc_noise_density_ug_rthz": 1000.0,
    "gyro_noise_density_mdps_rthz": 150.0,
    "acc_turn_on_bias_mg": 20.0,
    "gyro_turn_on_bias_dps": 1.0,
    "acc_scale_factor_pct": 0.5,
    "gyro_scale_factor_pct": 0.5,
}

DATASETS: dict[str, DatasetProfile] = {
    "drive_0708": DatasetProfile(
        name="drive_0708",
        pos_file="gnss_1934_sf.pos",
        imu_file="imu_1934.csv",
        vehicle="car",
        imu_time_offset_s=-0.125,
        author_mount_rpy_deg=(180.0, -6.79, 185.35),  # [180, 0, 180] + [0, -6.79, 5.35]
        eskf=_ICM45686_ESKF,
    ),
    "walk_0827": DatasetProfile(
        name="walk_0827",
        pos_file="gnss_1730_sf.pos",
        imu_file="imu_1730.csv",
        vehicle="pedestrian",
        imu_time_offset_s=0.0,
        author_mount_rpy_deg=(180.0, 0.0, -90.0),
        eskf={**_ICM45686_ESKF, "nhc": False},
        extra_engines=("pdr",),
    ),
}


@dataclass(frozen=True)
class OutageConfig:
    """Settings of the outage study (echoed into the result).

    Attributes
    ----------
    lengths_s : tuple of float
        Outage lengths, s.
    spacing_s : float
        A window starts every ``spacing_s`` of the moving part, s (>= every length).
    moving_speed_mps : float
        The moving part is where the RTK speed exceeds this, m/s.
    first_offset_s : float
        The first window starts this long after the moving part begins, s: an engine without
        a magnetometer cannot know its heading before the vehicle has moved and turned, so an
        outage at the very first metres measures the alignment, not the dead reckoning.
    gnss_rate_hz : float
        Rate of the degraded GNSS fed to the engines, Hz.
    environment : str
        Receiver environment of :mod:`iotnav.sim.gnss_model` (``open-sky``).
    sigma_h_m : float or None
        Override of the per-axis horizontal 1-sigma, m (None: the environment's).
    seed : int
        Seed of the GNSS degradation.
    engines : tuple of str
        Engines to run (``pipeline``, ``anchor``, ``qekf``, ``qekf-consistent``, ``eskf``);
        the baselines ``hold`` and ``dr-velocity`` are always
        reported, and so are the profile's ``extra_engines`` (``pdr`` on the walk).
    max_duration_s : float or None
        Use only the first ``max_duration_s`` of the RTK span (shortened studies), s.
    """

    lengths_s: tuple[float, ...] = (15.0, 30.0, 60.0)
    spacing_s: float = 60.0
    moving_speed_mps: float = 0.5
    first_offset_s: float = 60.0
    gnss_rate_hz: float = 1.0
    environment: str = "open-sky"
    sigma_h_m: float | None = None
    seed: int = 0
    engines: tuple[str, ...] = ("pipeline", "anchor", "qekf", "qekf-consistent", "eskf")
    max_duration_s: float | None = None

    def gnss_config(self) -> GnssConfig:
        """The receiver model of the degradation."""
        return GnssConfig(
            rate_hz=self.gnss_rate_hz,
            environment=self.environment,
            sigma_h_m=self.sigma_h_m,
            cold_start=False,
            latency_s=0.0,
            outages_s=(),
        )


@dataclass
class OutageResult:
    """Tables of the outage study.

    Attributes
    ----------
    windows : pandas.DataFrame
        Per (engine, length, start): ``engine``, ``length_s``, ``start``, ``end``,
        ``distance_m``, ``end_error_m``, ``end_sigma_m`` (the horizontal 1-sigma
        ``hypot(std_north, std_east)`` the output claimed at the end row; NaN for the
        baselines), ``max_error_m``, ``drift_pct``, ``fixes_masked``.
    summary : pandas.DataFrame
        Per (engine, length): ``rms_outside_m``, ``median_drift_pct``, ``worst_drift_pct``,
        ``n_windows``, ``rms_no_outage_m``.
    mount : pandas.DataFrame
        Per engine: ``roll_deg``, ``pitch_deg``, ``yaw_deg`` found (NaN where the engine has
        no such estimate), the author's ``author_*_deg`` and ``apart_deg`` (rotation angle
        between the two for a full mount, yaw difference for a yaw-only one).
    gnss : dict
        The fed GNSS: epochs, achieved per-axis horizontal std / RMS and vertical RMS of its
        error against the RTK, the configured sigmas, velocity error RMS.
    meta : dict
        Dataset, configuration, moving part, windows, time origin.
    """

    windows: pd.DataFrame
    summary: pd.DataFrame
    mount: pd.DataFrame
    gnss: dict[str, Any]
    meta: dict[str, Any]
