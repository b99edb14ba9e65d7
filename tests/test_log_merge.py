"""Merging reader parts onto one device-time axis (layer a)."""

from __future__ import annotations

import numpy as np
import pandas as pd
import pytest

from iotnav.io import IngestError
from iotnav.io.log import Part, merge
from iotnav.io.report import FileReport
from iotnav.io.schema import GNSS_COLUMNS, IMU_COLUMNS


def _gnss(t: np.ndarray, utc: np.ndarray) -> pd.DataFrame:
    return pd.DataFrame(
        {"t": t, "utc": utc, "lat_deg": 45.0, "lon_deg": 7.0, "valid": True, "source": "nmea"}
    )


def _imu(t: np.ndarray) -> pd.DataFrame:
    return pd.DataFrame(
        {"t": t, "acc_x": 0.0, "acc_y": 0.0, "acc_z": -9.8, "gyro_x": 0.0, "gyro_y": 0.0, "gyro_z": 0.0}
    )


def test_device_clock_gnss_moves_utc_parts_onto_device_time() -> None:
    t = np.arange(10.0, 20.0)
    g = Part.make(FileReport("g.nmea", "nmea"), "device", gnss=_gnss(t, t + 1000.0))
    # IMU on UTC (e.g. time-tagged): 1010.5 UTC is device time 10.5.
    i = Part.make(FileReport("i.csv", "imu-csv"), "utc", imu=_imu(np.array([1012.5, 1010.5, 1011.5])))
    log = merge([g, i])
    assert log.utc_offset_s == pytest.approx(1000.0)
    np.testing.assert_allclose(log.imu["t"], [10.5, 11.5, 12.5])
    assert list(log.gnss.columns) == list(GNSS_COLUMNS)
    assert list(log.imu.columns) == list(IMU_COLUMNS)
    tl = log.report.timeline
    assert tl["clock"] == "device"
    assert tl["gnss"]["count"] == 10
    assert tl["gnss"]["rate_hz"] == pytest.approx(1.0)
    frame = log.to_frame()
    assert frame["t"].is_monotonic_increasing
    assert (frame["kind"] == "imu").sum() == 3


def test_duplicates_and_nan_times_counted_not_silently_dropped() -> None:
    t = np.array([1.0, 2.0, 2.0, np.nan, 3.0])
    g = Part.make(FileReport("g", "nmea"), "utc", gnss=_gnss(t, t))
    log = merge([g])
    assert len(log.gnss) == 3
    skipped = {k: v for f in log.report.files for k, v in f.skipped.items()}
    assert skipped == {"no usable time": 1, "duplicate": 1}


def test_gaps_reported() -> None:
    t = np.concatenate([np.arange(0.0, 10.0), np.arange(40.0, 50.0)])
    log = merge([Part.make(FileReport("g", "nmea"), "utc", gnss=_gnss(t, t))])
    gaps = log.report.timeline["gnss"]["gaps"]
    assert gaps == [{"start": 9.0, "end": 40.0, "length_s": 31.0}]


def test_unlinkable_clocks_raise_a_clear_error() -> None:
    t = np.arange(5.0)
    g = Part.make(FileReport("g.pos", "rtklib-pos"), "utc", gnss=_gnss(t + 1e9, t + 1e9))
    i = Part.make(FileReport("i.csv", "imu-csv"), "device", imu=_imu(t))
    with pytest.raises(IngestError, match="give the offset explicitly"):
        merge([g, i])
    log = merge([g, i], imu_utc_offset_s=1e9)
    np.testing.assert_allclose(log.gnss["t"], t)
