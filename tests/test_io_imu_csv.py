"""IMU CSV reader: real rtklibexplorer logs with time tags, unit/column detection, bad rows."""

from __future__ import annotations

import calendar
import math
import struct
from pathlib import Path

import numpy as np
import pytest

from iotnav.io.errors import IngestError
from iotnav.io.imu_csv import IMU_PRESETS, read_imu_csv
from iotnav.io.log import merge
from iotnav.io.report import SkipReason
from iotnav.io.rtklib import read_rtklib_pos
from iotnav.io.schema import IMU_COLUMNS
from iotnav.io.timetag import read_timetag

RTK = "rtklibexplorer_gnss_imu"
G0 = 9.80665
D2R = math.pi / 180


def _accounting(part) -> tuple[int, int]:
    r = part.report
    return r.n_records + sum(r.ignored.values()) + r.n_skipped, r.units


@pytest.mark.parametrize("rel", ["drive_0708/imu_1934", "walk_0827/imu_1730"])
def test_real_imu_with_timetag(datasets: Path, rel: str) -> None:
    csv = datasets / RTK / f"{rel}.csv"
    part = read_imu_csv(csv, timetag=f"{csv}.tag")
    lines = csv.read_bytes().decode().split("\n")
    if lines[-1] == "":
        lines.pop()
    n_bad = sum(1 for ln in lines if ln.count(",") != 6)  # independent count of truncated lines
    assert part.report.skipped.get(SkipReason.TRUNCATED, 0) == n_bad
    assert len(part.imu) == len(lines) - n_bad  # no other damage in these files
    assert _accounting(part) == (len(lines), len(lines))
    assert part.clock == "utc"
    assert list(part.imu.columns) == list(IMU_COLUMNS)

    # Independent route 1: the derived *_gpst.csv (gpst_s printed with 4 decimals: half a unit of
    # the last digit, 5e-5 s, plus the float64 spacing of Unix times)
    derived = np.loadtxt(datasets / RTK / f"{rel}_gpst.csv", delimiter=",", comments="#")
    assert len(derived) == len(part.imu)
    np.testing.assert_array_equal(part.imu["acc_x"].to_numpy(), derived[:, 1] * G0)
    np.testing.assert_allclose(part.imu["t"].to_numpy() + 18.0, derived[:, 0], rtol=0, atol=5e-5 + 1e-6)

    # Independent route 2: the README formula computed here from the raw bytes, to 1e-6 s
    raw = (datasets / RTK / f"{rel}.csv.tag").read_bytes()
    time_t, frac = struct.unpack_from("<I", raw, 64)[0], struct.unpack_from("<d", raw, 68)[0]
    start = time_t + frac
    last_tick = struct.unpack_from("<I", raw, len(raw) - 8)[0]
    end = start + last_tick / 1000
    tick = derived[:, 7]
    t_expect = start + (tick - tick[0]) / 1000 * (end - start) / ((tick[-1] - tick[0]) / 1000) - 18.0
    np.testing.assert_allclose(part.imu["t"].to_numpy(), t_expect, rtol=0, atol=1e-6)


def test_drive_static_norm_and_units(datasets: Path) -> None:
    csv = datasets / RTK / "drive_0708/imu_1934.csv"
    part = read_imu_csv(csv, preset="rtklib-demo5", timetag=f"{csv}.tag")
    imu = part.imu
    t = imu["t"].to_numpy()
    first = t < t[0] + 30.0  # static for about 38 s at the start
    f = imu[["acc_x", "acc_y", "acc_z"]].to_numpy()[first]
    norm = float(np.linalg.norm(f, axis=1).mean())
    assert 9.8 < norm < 10.0  # README: about 1.01 g at rest
    # gyro converted from deg/s: first raw sample 0.198 deg/s on z
    assert imu["gyro_z"].iloc[0] == pytest.approx(0.198 * D2R)


def test_clock_agreement_drive(datasets: Path) -> None:
    """IMU (tag-timed) and .pos (GPST->UTC) on one timeline: gyro_z vs GNSS course rate."""
    base = datasets / RTK / "drive_0708"
    pos = read_rtklib_pos(base / "gnss_1934_sf.pos")
    imu = read_imu_csv(base / "imu_1934.csv", timetag=base / "imu_1934.csv.tag")
    g = pos.gnss
    tg = g["t"].to_numpy()
    vn, ve = g["vn"].to_numpy(), g["ve"].to_numpy()
    course = np.unwrap(np.arctan2(ve, vn))
    speed = np.hypot(vn, ve)
    rate = np.full(tg.size, np.nan)
    rate[1:-1] = (course[2:] - course[:-2]) / (tg[2:] - tg[:-2])
    use = np.zeros(tg.size, bool)
    use[1:-1] = (speed[1:-1] > 3.0) & (speed[:-2] > 3.0) & (speed[2:] > 3.0)
    ti = imu.imu["t"].to_numpy()
    wz = imu.imu["gyro_z"].to_numpy()
    csum = np.concatenate(([0.0], np.cumsum(wz)))
    lo_t, hi_t = np.r_[np.nan, tg[:-2], np.nan], np.r_[np.nan, tg[2:], np.nan]
    lags = np.round(np.arange(-0.5, 0.5001, 0.025), 3)
    corr = []
    for lag in lags:
        shifted = ti + lag
        lo = np.searchsorted(shifted, lo_t[use])
        hi = np.searchsorted(shifted, hi_t[use])
        mean_w = (csum[hi] - csum[lo]) / np.maximum(hi - lo, 1)
        corr.append(np.corrcoef(mean_w, rate[use])[0, 1])
    corr_arr = np.array(corr)
    best = int(np.argmax(np.abs(corr_arr)))
    assert -0.25 <= lags[best] <= 0.1
    assert abs(corr_arr[best]) > 0.95
    assert corr_arr[best] < 0  # sensor z up: gyro_z is minus the NED yaw rate

    log = merge([pos, imu])
    assert len(log.gnss) == len(g) and len(log.imu) == len(imu.imu)
    assert log.utc_offset_s == 0.0 and log.report.timeline["clock"] == "utc"
    assert (np.diff(log.imu["t"].to_numpy()) > 0).all()
    frame = log.to_frame()
    assert frame["t"].is_monotonic_increasing
    # the IMU log spans the GNSS epochs (minus the static ends)
    assert log.imu["t"].iloc[0] < log.gnss["t"].iloc[100] and log.imu["t"].iloc[-1] > log.gnss["t"].iloc[-100]


def _w(tmp_path: Path, name: str, text: str) -> Path:
    p = tmp_path / name
    p.write_text(text)
    return p


ROWS = [
    (0.0, 0.1, 0.0, 1.0, 10.0, 0.0, -20.0),
    (0.01, 0.0, 0.1, 1.0, 0.0, 10.0, 0.0),
    (0.02, 0.0, 0.0, 1.0, 0, 0, 5),
]


def _csv(header: str, rows=ROWS, scale_acc=1.0, scale_gyro=1.0) -> str:
    out = [header]
    for t, ax, ay, az, gx, gy, gz in rows:
        a = [v * scale_acc for v in (ax, ay, az)]
        w = [v * scale_gyro for v in (gx, gy, gz)]
        out.append(",".join(f"{v:.6g}" for v in (t, *a, *w)))
    return "\n".join(out) + "\n"


@pytest.mark.parametrize(
    ("header", "sa", "sg", "acc_si", "gyro_si"),
    [
        ("t,ax,ay,az,gx,gy,gz", 1.0, 1.0, G0, D2R),  # guessed: g, companion deg/s
        ("time,acc_x_g,acc_y_g,acc_z_g,gyro_x_dps,gyro_y_dps,gyro_z_dps", 1.0, 1.0, G0, D2R),
        ("ts,ax[m/s^2],ay[m/s^2],az[m/s^2],gx (rad/s),gy (rad/s),gz (rad/s)", G0, 1.0, 1.0, 1.0),
        ("timestamp,AccX,AccY,AccZ,GyroX(deg/s),GyroY(deg/s),GyroZ(deg/s)", 1000.0, 1.0, G0 * 1e-3, D2R),
        ("t,accel_x,accel_y,accel_z,wx_mdps,wy_mdps,wz_mdps", 1.0, 1000.0, G0, D2R * 1e-3),
        (
            "seconds_elapsed,accelerometer_x,accelerometer_y,accelerometer_z,gyro_x,gyro_y,gyro_z",
            G0,
            1.0,
            1.0,
            1.0,
        ),
    ],
)
def test_header_names_and_units(tmp_path: Path, header: str, sa: float, sg: float, acc_si, gyro_si) -> None:
    p = _w(tmp_path, "imu.csv", _csv(header, scale_acc=sa, scale_gyro=sg))
    part = read_imu_csv(p)
    imu = part.imu
    assert len(imu) == 3 and part.clock == "device"
    # raw file value times the unit factor, hand-computed
    assert imu["acc_z"].iloc[0] == pytest.approx(1.0 * sa * acc_si, rel=1e-6)
    assert imu["gyro_x"].iloc[0] == pytest.approx(10.0 * sg * gyro_si, rel=1e-6)
    assert imu["gyro_z"].iloc[0] == pytest.approx(-20.0 * sg * gyro_si, rel=1e-6)
    assert imu["t"].tolist() == pytest.approx([0.0, 0.01, 0.02])
    assert any("acc unit" in n for n in part.report.notes)


@pytest.mark.parametrize(
    ("unit_header", "scale", "to_ut"),
    [("_ut", 1.0, 1.0), ("_mG", 10.0, 0.1), ("_gauss", 0.01, 100.0), ("_nT", 1000.0, 1e-3), ("", 1.0, 1.0)],
)
def test_magnetometer_units(tmp_path: Path, unit_header: str, scale: float, to_ut: float) -> None:
    b = (20.0, -5.0, -40.0)  # uT
    head = "t,ax,ay,az,gx,gy,gz," + ",".join(f"mag_{a}{unit_header}" for a in "xyz")
    body = "".join(
        f"{i * 0.01},0,0,1,0,0,0,{b[0] * scale:g},{b[1] * scale:g},{b[2] * scale:g}\n" for i in range(4)
    )
    part = read_imu_csv(_w(tmp_path, "m.csv", head + "\n" + body))
    assert len(part.mag) == 4
    assert part.mag["mag_z_ut"].iloc[0] == pytest.approx(b[2] * scale * to_ut)
    assert part.mag["mag_z_ut"].iloc[0] == pytest.approx(-40.0)


def test_explicit_units_columns_and_order(tmp_path: Path) -> None:
    p = _w(
        tmp_path,
        "a.csv",
        "Zeit;A1;A2;A3;W1;W2;W3;junk\n" + "".join(f"{i * 5};0;0;9.81;1;2;3;x\n" for i in range(4)),
    )
    cols = {
        "t": "Zeit",
        "acc_x": "A1",
        "acc_y": "A2",
        "acc_z": "A3",
        "gyro_x": "W1",
        "gyro_y": "W2",
        "gyro_z": "W3",
    }
    part = read_imu_csv(p, columns=cols, gyro_unit="deg/s", time_unit="ms")
    assert part.imu["gyro_y"].iloc[0] == pytest.approx(2 * D2R)
    assert part.imu["t"].iloc[1] == pytest.approx(0.005)
    assert any("junk" in n for n in part.report.notes)  # unknown column listed
    # header-less with a given order (tick last, like the rtklibexplorer logger)
    q = _w(tmp_path, "b.csv", "".join(f"0,0,1,0,0,{i},{1000 + 10 * i}\n" for i in range(5)))
    order = ["acc_x", "acc_y", "acc_z", "gyro_x", "gyro_y", "gyro_z", "t"]
    part2 = read_imu_csv(q, column_order=order, acc_unit="g", gyro_unit="deg/s", time_unit="ms")
    assert part2.imu["t"].tolist() == pytest.approx([1.0, 1.01, 1.02, 1.03, 1.04])
    assert part2.imu["gyro_z"].iloc[4] == pytest.approx(4 * D2R)
    with pytest.raises(ValueError, match="preset"):
        read_imu_csv(q, preset="nope")
    with pytest.raises(ValueError, match="gyroscope unit"):
        read_imu_csv(q, column_order=order, gyro_unit="furlong/s")
    assert IMU_PRESETS["rtklib-demo5"].acc_unit == "g"


def test_absolute_times_and_sensor_logger_names(tmp_path: Path) -> None:
    # Sensor Logger style: time in ns since the epoch, x/y/z columns named by the file
    t0 = calendar.timegm((2023, 11, 14, 22, 13, 20))
    body = "".join(f"{(t0 * 10**9) + i * 10**7},{i * 0.01},0.3,0.2,0.1\n" for i in range(5))
    p = _w(tmp_path, "Gyroscope.csv", "time,seconds_elapsed,z,y,x\n" + body)
    part = read_imu_csv(p, gyro_unit="rad/s")
    assert part.clock == "utc"
    assert part.imu["t"].iloc[0] == pytest.approx(t0, abs=1e-6)
    assert part.imu["gyro_x"].iloc[0] == pytest.approx(0.1)
    assert part.imu["gyro_z"].iloc[0] == pytest.approx(0.3)
    assert np.isnan(part.imu["acc_x"]).all()


def test_bad_rows_counted_by_reason(tmp_path: Path) -> None:
    good = [f"{i * 0.01:.2f},0,0,1,0,0,1" for i in range(10)]
    lines = ["t,ax,ay,az,gx,gy,gz"]
    lines += good[:2]
    lines += ["0.02,0,0"]  # truncated
    lines += [good[2]]
    lines += ["0.025,nan,0,1,0,0,1"]  # NaN
    lines += ["0.026,0,abc,1,0,0,1"]  # text
    lines += ["0.027,0,0,99,0,0,1"]  # 99 g: out of range
    lines += ["0.028,0,0,1,0,0,4000"]  # 4000 deg/s = 70 rad/s: out of range
    lines += [good[3], good[3]]  # duplicate
    lines += ["0.01,0,0,1,0,0,1"]  # backwards
    lines += ["0.03,0,0,1,0,0,2"]  # same time, different values: not after the last
    lines += [""]  # empty line
    lines += good[4:]
    p = _w(tmp_path, "bad.csv", "\n".join(lines) + "\n")
    part = read_imu_csv(p, acc_unit="g", gyro_unit="deg/s")
    sk = part.report.skipped
    assert sk[SkipReason.TRUNCATED] == 1
    assert sk[SkipReason.NAN_FIELD] == 1
    assert sk[SkipReason.MALFORMED] == 1
    assert sk[SkipReason.OUT_OF_RANGE] == 2
    assert sk[SkipReason.DUPLICATE] == 1
    assert sk[SkipReason.NON_MONOTONIC] == 2
    assert part.report.ignored["empty line"] == 1
    assert len(part.imu) == 10
    assert part.imu["t"].tolist() == pytest.approx([i * 0.01 for i in range(10)])
    assert _accounting(part) == (len(lines), len(lines))
    # examples carry the physical line number
    assert part.report.examples[str(SkipReason.MALFORMED)][0][0] == 7
    assert part.report.examples[str(SkipReason.TRUNCATED)][0][0] == 4


def test_not_an_imu_csv(tmp_path: Path) -> None:
    p = _w(tmp_path, "people.csv", "name,age,city\nann,31,Oslo\nbob,42,Rome\n")
    with pytest.raises(IngestError, match=r"people\.csv.*acc_x"):
        read_imu_csv(p)
    q = _w(tmp_path, "ua.csv", "t,ax,ay,az\n0,0.01,0.02,0.0\n0.01,0.02,0.01,0.01\n")
    with pytest.raises(IngestError, match="acc_unit"):  # gravity-free values: unit ambiguous
        read_imu_csv(q)
    with pytest.raises(IngestError, match="empty"):
        read_imu_csv(_w(tmp_path, "e.csv", ""))


def test_timetag_reader(datasets: Path, tmp_path: Path) -> None:
    tag = read_timetag(datasets / RTK / "drive_0708/imu_1934.csv.tag")
    assert tag.header.startswith("TIMETAG RTKLIB")
    # README: drive GPST 2025-07-08 19:34:18 .. 19:43:30; the IMU log starts 19:34:21.854
    assert tag.start_gpst == pytest.approx(calendar.timegm((2025, 7, 8, 19, 34, 21)) + 0.854, abs=1e-3)
    assert tag.tag_tick_ms.size == (301132 - 76) // 8 and tag.trailing_bytes == 0
    assert (np.diff(tag.tag_tick_ms.astype(np.int64)) >= 0).all()
    assert tag.ticks_to_gpst([0, 500, 1000]) == pytest.approx(
        [tag.start_gpst, (tag.start_gpst + tag.end_gpst) / 2, tag.end_gpst]
    )
    bad = tmp_path / "x.tag"
    bad.write_bytes(b"NOTATAG" + bytes(100))
    with pytest.raises(IngestError, match="TIMETAG"):
        read_timetag(bad)


def test_invalid_utf8_in_a_truncated_line(tmp_path: Path) -> None:
    body = b"0.1,0.0,1.0,0,0,0,100\n\xff\xfe0,1.0\n0.1,0.0,1.0,0,0,0,110\n0.1,0.0,1.0,0,0,0,120\n"
    p = tmp_path / "raw.csv"
    p.write_bytes(body)
    part = read_imu_csv(p, preset="rtklib-demo5")
    assert part.report.skipped[SkipReason.TRUNCATED] == 1
    assert len(part.imu) == 3 and part.clock == "device"
    assert part.imu["t"].tolist() == pytest.approx([0.1, 0.11, 0.12])
