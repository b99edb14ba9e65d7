"""UBX reader: hand-built frames (struct, per the u-blox interface description) and the real
walk recording (mixed UBX + NMEA, NAV-PVT at 4 Hz)."""

from __future__ import annotations

import calendar
import math
import struct

import numpy as np
import pytest

from _nmea_helpers import WALK, ubx_frames
from iotnav.io.errors import IngestError
from iotnav.io.nmea import read_nmea
from iotnav.io.report import SkipReason
from iotnav.io.ubx import read_ubx

PVT_FMT = "<IHBBBBBBIiBBBBiiiiIIiiiiiIIHH4siHH"


def frame(cls: int, mid: int, payload: bytes) -> bytes:
    body = bytes((cls, mid)) + struct.pack("<H", len(payload)) + payload
    a = b = 0
    for x in body:
        a = (a + x) % 256
        b = (b + a) % 256
    return b"\xb5\x62" + body + bytes((a, b))


def nav_pvt(
    sec: int = 30,
    nano: int = 0,
    fix: int = 3,
    flags: int = 0b1000_0001,  # gnssFixOK, carrSoln = 2 (fixed)
    valid: int = 0b11,
    g_speed_mm: int = 1500,
    s_acc_mm: int = 100,
) -> bytes:
    assert struct.calcsize(PVT_FMT) == 92
    payload = struct.pack(
        PVT_FMT,
        0, 2025, 8, 28, 17, 30, sec, valid, 20, nano, fix, flags, 0, 17,
        -1051471665, 400966916,  # lon, lat in 1e-7 deg
        1580048, 1601435,  # height, hMSL in mm
        14, 10,  # hAcc, vAcc mm
        1000, -1120, 30,  # velN, velE, velD mm/s
        g_speed_mm, 31_824_000,  # gSpeed mm/s, headMot 1e-5 deg (318.24 deg)
        s_acc_mm, 100000, 114,  # sAcc mm/s, headAcc, pDOP 0.01
        0, b"\x00" * 4, 0, 0, 0,
    )  # fmt: skip
    return frame(0x01, 0x07, payload)


def nmea(body: str) -> bytes:
    ck = 0
    for ch in body.encode():
        ck ^= ch
    return f"${body}*{ck:02X}\r\n".encode()


def test_nav_pvt_fields_by_hand():
    part = read_ubx(nav_pvt(nano=-250_000_000))
    assert part.clock == "utc"
    r = part.gnss.iloc[0]
    t = calendar.timegm((2025, 8, 28, 17, 30, 30, 0, 0, 0)) - 0.25
    assert r.t == pytest.approx(t) and r.utc == pytest.approx(t)
    assert r.lat_deg == pytest.approx(40.0966916) and r.lon_deg == pytest.approx(-105.1471665)
    assert r.height_m == pytest.approx(1580.048) and r.alt_msl_m == pytest.approx(1601.435)
    assert r.geoid_sep_m == pytest.approx(1580.048 - 1601.435)
    assert (r.vn, r.ve, r.vd) == pytest.approx((1.0, -1.12, 0.03))
    assert r.speed_mps == pytest.approx(1.5) and r.s_acc_mps == pytest.approx(0.1)
    assert r.course_rad == pytest.approx(math.radians(318.24)) and r.course_valid
    assert (r.h_acc_m, r.v_acc_m, r.pdop, r.num_sv) == pytest.approx((0.014, 0.010, 1.14, 17))
    assert r["mode"] == 3 and r.quality == 4 and r.valid and r.source == "ubx"
    assert part.report.records == {"UBX NAV-PVT": 1}


@pytest.mark.parametrize(
    ("kw", "mode", "quality", "valid", "course_valid"),
    [
        ({"fix": 0, "flags": 0}, 1, 0, False, False),
        ({"fix": 2, "flags": 0b01}, 2, 1, True, True),
        ({"fix": 3, "flags": 0b0100_0011}, 3, 5, True, True),  # float RTK
        ({"fix": 3, "flags": 0b11}, 3, 2, True, True),  # differential
        ({"fix": 3, "flags": 0b1, "g_speed_mm": 150}, 3, 1, True, False),  # speed < 2 sAcc
    ],
)
def test_nav_pvt_fix_codes(kw, mode, quality, valid, course_valid):
    r = read_ubx(nav_pvt(**kw)).gnss.iloc[0]
    assert (r["mode"], r.quality, bool(r.valid), bool(r.course_valid)) == (mode, quality, valid, course_valid)


def test_nav_pvt_without_valid_time_is_skipped():
    part = read_ubx(nav_pvt(valid=0b01))
    assert len(part.gnss) == 0 and part.report.skipped[SkipReason.NO_TIME] == 1


def test_garbage_chunks_resync_and_nmea_duplicates():
    gga_same = nmea("GNGGA,173030.00,4005.8014957,N,10508.8299894,W,4,12,0.62,1601.435,M,-21.387,M,0.8,0000")
    gga_other = nmea("GNGGA,173031.50,4005.8014957,N,10508.8299894,W,4,12,0.62,1601.435,M,-21.387,M,0.8,0000")
    rmc = nmea("GNRMC,173031.50,A,4005.8014957,N,10508.8299894,W,0.005,,280825,,,R,V")
    broken = nav_pvt(sec=31)[:-1] + b"\x00"  # bad checksum: its bytes are garbage
    data = b"\x01\x02junk" + nav_pvt() + gga_same + broken + b"\xb5" + nav_pvt(sec=32) + gga_other + rmc
    part = read_ubx(data)
    rep = part.report
    assert rep.records["UBX NAV-PVT"] == 2
    assert rep.ignored["GGA (duplicate of UBX NAV-PVT)"] == 1
    assert rep.records["GGA"] == 1 and rep.records["RMC"] == 1  # the 17:30:31.5 cycle is kept
    assert rep.skipped[SkipReason.GARBAGE] == 2  # leading junk; broken frame + lone sync byte
    assert rep.units == 2 + 3 + 2 == rep.n_records + sum(rep.ignored.values()) + rep.n_skipped
    np.testing.assert_array_equal(part.gnss.source.to_numpy(), ["ubx", "nmea", "ubx"])
    assert part.gnss.t.is_monotonic_increasing


def test_esf_raw_imu_rows():
    # dataType 14 gyro x = 4096 LSB = 1 deg/s; 16 acc x = -1024 LSB = -1 m/s^2; 18 acc z = 10240.
    def word(dtype: int, value: int) -> int:
        return (dtype << 24) | (value & 0xFFFFFF)

    samples = [(word(14, 4096), 1000), (word(16, -1024), 1000), (word(18, 10240), 1000), (word(14, 0), 1010)]
    payload = b"\x00" * 4 + b"".join(struct.pack("<II", w, tag) for w, tag in samples)
    part = read_ubx(nav_pvt() + frame(0x10, 0x03, payload))
    imu = part.imu
    assert len(imu) == 2
    assert imu.gyro_x.iloc[0] == pytest.approx(math.radians(1.0))
    assert imu.acc_x.iloc[0] == pytest.approx(-1.0) and imu.acc_z.iloc[0] == pytest.approx(10.0)
    assert np.isnan(imu.acc_y.iloc[0])
    assert imu.t.iloc[1] - imu.t.iloc[0] == pytest.approx(0.010)
    assert imu.t.iloc[0] == pytest.approx(part.gnss.t.iloc[0])
    assert part.report.records["UBX ESF-RAW"] == 1


def test_no_ubx_raises():
    with pytest.raises(IngestError):
        read_ubx(b"\x00" * 100 + b"hello")


# ------------------------------------------------------------------ the real walk recording


@pytest.fixture(scope="module")
def walk():
    return read_ubx(WALK / "gnss_1730.ubx")


def test_walk_nav_pvt_count_matches_independent_scan(walk):
    data = (WALK / "gnss_1730.ubx").read_bytes()
    n_pvt = sum(1 for i in ubx_frames(data, b"\x01\x07") if data[i + 4 : i + 6] == b"\x5c\x00")
    assert n_pvt == 536  # the README's count, found here by brute scan
    assert walk.report.records["UBX NAV-PVT"] == n_pvt == (walk.gnss.source == "ubx").sum()
    # units: every frame + every NMEA sentence (the README's 2010 extracted sentences)
    n_frames = len(ubx_frames(data))
    n_sentences = sum(1 for line in (WALK / "gnss_1730_nmea.txt").read_bytes().splitlines() if line)
    rep = walk.report
    assert rep.units == n_frames + n_sentences == rep.n_records + sum(rep.ignored.values()) + rep.n_skipped


def test_walk_positions_agree_with_the_receivers_gga(walk):
    gga = read_nmea(WALK / "gnss_1730_nmea.txt").gnss
    pvt = walk.gnss
    key_n = np.round(gga.utc.to_numpy(), 2)
    key_p = np.round(pvt.utc.to_numpy(), 2)
    common, i_n, i_p = np.intersect1d(key_n, key_p, return_indices=True)
    assert len(common) >= 530
    d_north = (gga.lat_deg.to_numpy()[i_n] - pvt.lat_deg.to_numpy()[i_p]) * 111_000
    d_east = (
        (gga.lon_deg.to_numpy()[i_n] - pvt.lon_deg.to_numpy()[i_p]) * 111_000 * math.cos(math.radians(40.1))
    )
    d_up = gga.alt_msl_m.to_numpy()[i_n] - pvt.alt_msl_m.to_numpy()[i_p]
    assert np.max(np.abs(d_north)) < 0.03 and np.max(np.abs(d_east)) < 0.03
    assert np.max(np.abs(d_up)) < 0.003
    # the receiver's GGA quality (4 fixed / 5 float) is the NAV-PVT carrier solution
    np.testing.assert_array_equal(gga.quality.to_numpy()[i_n], pvt.quality.to_numpy()[i_p])
