"""The Forno pipeline on a real car drive (rtklibexplorer GNSS_IMU ``drive_0708``).

A consumer IMU (ICM-45686, ~100 Hz) mounted with its z axis up (roll ~180 deg) and its x axis
about backwards, and a 4 Hz RTK receiver reporting ~1 cm accuracies (``h_acc_m``, ``v_acc_m``)
and an NED velocity. The first 260 s (38 s parked, then residential streets on a hill) go
through :func:`iotnav.io.ingest` and :class:`iotnav.engines.Pipeline` with the default
configuration.

References, not computed by the code under test:

* positions: the RTK input itself, interpolated linearly to the output times, both converted
  to local north/east with a flat-earth approximation written out here;
* mount yaw: the dataset author's IMU rotation, RPY ``[180, 0, 180] + [0, -6.79, 5.35]`` deg
  (upstream ``src/drive_config.py``), i.e. a yaw of 185.35 deg = -174.65 deg; the ESKF engine
  finds -174.9 deg.
"""

from __future__ import annotations

import dataclasses
import math
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from iotnav.engines import Pipeline, PipelineConfig, run_batch
from iotnav.io import ingest

DRIVE = "rtklibexplorer_gnss_imu/drive_0708"
SPAN_S = 260.0
AUTHOR_MOUNT_YAW_DEG = 180.0 + 5.35 - 360.0
R_EARTH_M = 6371008.8


def _dwrap_deg(a_deg: float, b_deg: float) -> float:
    return abs((a_deg - b_deg + 180.0) % 360.0 - 180.0)


def _flat_ne(lat: np.ndarray, lon: np.ndarray, lat0: float, lon0: float) -> np.ndarray:
    """North/east (m) of lat/lon (deg) about (lat0, lon0), flat earth (mm-level over 2 km)."""
    n = np.radians(lat - lat0) * R_EARTH_M
    e = np.radians(lon - lon0) * R_EARTH_M * math.cos(math.radians(lat0))
    return np.column_stack([n, e])


@pytest.fixture(scope="module")
def drive(datasets: Path) -> tuple[pd.DataFrame, pd.DataFrame, Pipeline]:
    d = datasets / DRIVE
    log = ingest([d / "gnss_1934_sf.pos", d / "imu_1934.csv"])
    t0 = float(log.gnss.t.iloc[0])
    log.gnss = log.gnss[log.gnss.t < t0 + SPAN_S].reset_index(drop=True)
    log.imu = log.imu[log.imu.t < t0 + SPAN_S].reset_index(drop=True)
    # Roof-mounted on hilly roads the fused mount std levels off at 1.1-1.5 deg, above the
    # pipeline's 1 deg default acceptance: this installation is configured at 2 deg, as a user
    # would through `[mount] max_std_rad` (see PIPELINE_MOUNT in iotnav.engines.config).
    base = PipelineConfig()
    config = base.replace(mount=dataclasses.replace(base.mount, max_std_rad=math.radians(2.0)))
    engine = Pipeline(config)
    return run_batch(engine, log), log.gnss, engine


def test_fix_rows_follow_rtk(drive: tuple[pd.DataFrame, pd.DataFrame, Pipeline]) -> None:
    df, gnss, _ = drive
    fix = df[df.source == "fix"]
    assert len(fix) > 0.6 * len(df)
    lat0, lon0 = float(gnss.lat_deg.iloc[0]), float(gnss.lon_deg.iloc[0])
    ref = _flat_ne(gnss.lat_deg.to_numpy(), gnss.lon_deg.to_numpy(), lat0, lon0)
    t = fix.t.to_numpy()
    ref_t = np.column_stack([np.interp(t, gnss.t, ref[:, 0]), np.interp(t, gnss.t, ref[:, 1])])
    out = _flat_ne(fix.lat.to_numpy(), fix.lon.to_numpy(), lat0, lon0)
    err = np.hypot(*(out - ref_t).T)
    assert np.percentile(err, 95) < 0.5, np.percentile(err, [50, 95, 100])


def test_mount_found_near_author_yaw(drive: tuple[pd.DataFrame, pd.DataFrame, Pipeline]) -> None:
    _, _, engine = drive
    est = [e for e in engine.events if e["type"] == "mount_estimate"]
    accepted = [e for e in est if e["accepted"]]
    assert accepted, "mount never accepted"
    for e in accepted:
        assert _dwrap_deg(math.degrees(e["mount_yaw_rad"]), AUTHOR_MOUNT_YAW_DEG) < 5.0
        assert e["std_rad"] <= engine.config.mount.max_std_rad
    assert engine.mount.known
    assert _dwrap_deg(math.degrees(engine.mount_yaw_rad), AUTHOR_MOUNT_YAW_DEG) < 5.0
    # the fused standard deviation shrinks as buffers accumulate
    stds = [e["std_rad"] for e in est]
    assert stds[-1] < 0.5 * stds[0]


def test_upside_down_sensor_levels(drive: tuple[pd.DataFrame, pd.DataFrame, Pipeline]) -> None:
    df, _, engine = drive
    # parked at the start, sensor z up: |roll| near 180 deg from the first sample on
    first = df.iloc[:300]
    assert np.all(np.abs(np.degrees(first.roll.to_numpy())) > 170.0)
    assert engine.cascade.tilt.x[2] < -0.95  # down axis along -z of the sensor
