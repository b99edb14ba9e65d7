"""Phone log readers on hand-written fixtures (see tests/data/README.md)."""

from __future__ import annotations

import math
import shutil
import zipfile
from pathlib import Path

import numpy as np
import pytest

from iotnav.io.errors import IngestError
from iotnav.io.log import merge
from iotnav.io.phone import read_gnsslogger, read_sensor_logger
from iotnav.io.report import SkipReason

DATA = Path(__file__).parent / "data"
GL = DATA / "gnsslogger_small.txt"
SL = DATA / "sensor_logger_android"


def _total(part) -> int:
    r = part.report
    return r.n_records + sum(r.ignored.values()) + r.n_skipped


def test_gnsslogger_records_and_accounting() -> None:
    part = read_gnsslogger(GL)
    r = part.report
    n_lines = len(GL.read_text().splitlines())
    assert r.units == n_lines and _total(part) == n_lines
    assert r.records["Fix GPS"] == 2
    assert r.ignored["Fix FLP"] == 1  # fused fix not used when GPS fixes exist
    assert r.ignored["Accel (other calibration preferred)"] == 1
    assert r.ignored["Raw"] == 1 and r.ignored["Status"] == 1 and r.ignored["OrientationDeg"] == 1
    assert r.skipped[SkipReason.UNKNOWN_SENTENCE] == 1
    assert r.skipped[SkipReason.TRUNCATED] == 1
    assert r.skipped[SkipReason.MALFORMED] == 1
    assert part.clock == "utc"


def test_gnsslogger_values_and_clock() -> None:
    part = read_gnsslogger(GL)
    g = part.gnss
    assert g["t"].iloc[0] == pytest.approx(1_700_000_000.0)
    assert g["height_m"].iloc[1] == 550.5 and g["v_acc_m"].iloc[1] == 5.5
    # AccuracyMeters 3.5 is Android's 68 % radius: 2D sigma 3.5 sqrt(2) / sqrt(-2 ln 0.32)
    assert g["h_acc_m"].iloc[1] == pytest.approx(3.5 * math.sqrt(2.0) / math.sqrt(-2.0 * math.log(0.32)))
    # second fix: 2 m/s at bearing 0 deg -> north
    assert (g["vn"].iloc[1], g["ve"].iloc[1]) == pytest.approx((2.0, 0.0))
    assert bool(g["course_valid"].iloc[1]) and not bool(g["course_valid"].iloc[0])
    # clock: elapsedRealtimeNanos + (UnixTimeMillis/1e3 - elapsedRealtimeNanos/1e9) of the fixes;
    # both fixes give offset 1.7e9 - 1000 s, so the gyro at 1000.012 s boot time is 1.7e9 + 0.012
    imu = part.imu
    assert imu["t"].iloc[0] == pytest.approx(1_700_000_000.012, abs=1e-6)
    # uncalibrated values preferred; accel interpolated to the gyro time: 0.1 + (0.3-0.1)*0.2
    assert imu["gyro_x"].iloc[0] == pytest.approx(0.010)
    assert imu["acc_x"].iloc[0] == pytest.approx(0.14, abs=1e-5)
    assert imu["acc_z"].iloc[0] == pytest.approx(9.80)
    # gyro at 1000.042 s lies after the last usable accel sample (1000.030 s): not interpolated
    assert len(imu) == 2
    assert part.report.skipped[SkipReason.NO_TIME] == 2
    assert part.mag["mag_z_ut"].iloc[0] == -40.0
    cal = read_gnsslogger(GL, calibrated=True)
    assert cal.report.ignored["UncalAccel (other calibration preferred)"] == 5
    assert cal.report.records["Accel"] == 1


def test_gnsslogger_rejects_other_text(tmp_path: Path) -> None:
    p = tmp_path / "x.txt"
    p.write_text("just,some\ncsv,lines\n")
    with pytest.raises(IngestError, match="GnssLogger"):
        read_gnsslogger(p)


def test_sensor_logger_directory_and_zip(tmp_path: Path) -> None:
    part = read_sensor_logger(SL)
    r = part.report
    n_lines = sum(
        len((SL / f).read_text().splitlines())
        for f in (
            "Gyroscope.csv",
            "TotalAcceleration.csv",
            "Accelerometer.csv",
            "Gravity.csv",
            "Magnetometer.csv",
            "Location.csv",
        )
    )
    assert r.units == n_lines and _total(part) == n_lines
    imu = part.imu
    # gyro samples at 0 ms and 50 ms fall outside TotalAcceleration (5..45 ms)
    assert len(imu) == 4 and r.skipped[SkipReason.NO_TIME] == 2
    assert imu["t"].iloc[0] == pytest.approx(1_700_000_000.01, abs=1e-6)
    # columns are read by name: file order is z, y, x
    assert (imu["gyro_x"].iloc[0], imu["gyro_z"].iloc[0]) == pytest.approx((0.01, 0.03))
    assert imu["acc_z"].iloc[0] == pytest.approx(9.81)
    assert imu["acc_x"].iloc[0] == pytest.approx(0.1, abs=1e-5)  # interpolated between 0.0 and 0.2
    assert r.skipped[SkipReason.DUPLICATE] == 1 and len(part.mag) == 2
    g = part.gnss
    assert len(g) == 2
    assert math.isnan(g["course_rad"].iloc[0]) and math.isnan(g["s_acc_mps"].iloc[0])  # -1 = invalid
    assert g["course_rad"].iloc[1] == pytest.approx(math.pi / 2) and g["ve"].iloc[1] == pytest.approx(1.5)
    assert g["height_m"].iloc[1] == 550.2
    z = tmp_path / "rec.zip"
    with zipfile.ZipFile(z, "w") as zf:
        for f in SL.iterdir():
            zf.write(f, f"rec/{f.name}")
    pz = read_sensor_logger(z)
    assert pz.imu.equals(part.imu) and pz.gnss.equals(part.gnss)
    log = merge([part])
    assert len(log.imu) == 4


def test_sensor_logger_ios_accelerometer_plus_gravity(tmp_path: Path) -> None:
    d = tmp_path / "ios"
    d.mkdir()
    for f in ("Gyroscope.csv", "Accelerometer.csv", "Gravity.csv"):
        shutil.copy(SL / f, d / f)
    # iOS conventions: gravity reads -z when flat; user acceleration has the same sign flip
    (d / "Gravity.csv").write_text(
        "time,seconds_elapsed,z,y,x\n1700000000005000000,0.005,-9.81,0,0\n1700000000015000000,0.015,-9.81,0,0\n"
    )
    (d / "Accelerometer.csv").write_text(
        "time,seconds_elapsed,z,y,x\n1700000000005000000,0.005,0,0,0\n1700000000015000000,0.015,0,0,-0.2\n"
    )
    (d / "Metadata.csv").write_text("version,platform\n3,ios\n")
    part = read_sensor_logger(d)
    imu = part.imu
    assert len(imu) == 1  # only the gyro sample at 10 ms is inside 5..15 ms
    assert imu["acc_z"].iloc[0] == pytest.approx(9.81)  # negated to specific force
    assert imu["acc_x"].iloc[0] == pytest.approx(0.1, abs=1e-5)  # ns times held as float64 s
    assert any("iOS" in n for n in part.report.notes)
    android = read_sensor_logger(d, platform="android")
    assert android.imu["acc_z"].iloc[0] == pytest.approx(-9.81)


def test_sensor_logger_not_an_export(tmp_path: Path) -> None:
    (tmp_path / "foo.csv").write_text("a,b\n1,2\n")
    with pytest.raises(IngestError, match="Sensor Logger"):
        read_sensor_logger(tmp_path)
    bad = tmp_path / "x.zip"
    bad.write_bytes(b"not a zip")
    with pytest.raises(IngestError):
        read_sensor_logger(bad)
    assert np.isfinite(read_sensor_logger(SL).imu["t"]).all()
