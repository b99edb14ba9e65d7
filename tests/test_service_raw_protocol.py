"""iotnav's raw GNSS + IMU batches (:mod:`iotnav.service.protocols.iotnav_raw`): schema, then fuzzing.

Expected values are written out by hand from the schema in the module docstring (byte
offsets, struct formats, CRC-32 of IEEE 802.3 whose check value ``crc32(b"123456789") =
0xCBF43926`` is the catalogue's), never computed by the decoder itself.
"""

from __future__ import annotations

import json
import math
import struct
import zlib

import numpy as np
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from iotnav.service.protocols.common import Rejected
from iotnav.service.protocols.iotnav_raw import (
    MAX_SAMPLES,
    GnssRecord,
    RawBatch,
    decode,
    device_from_topic,
    encode_binary,
    encode_json,
)

FUZZ = settings(
    max_examples=200, deadline=None, suppress_health_check=[HealthCheck.too_slow], derandomize=True
)
T0 = 1_700_000_000.0
FIX = {"t": T0, "lat": 45.5, "lon": 7.25, "alt": 250.0, "acc": 3.0, "speed": 10.0, "course": 1.5, "nsat": 9}


def _ok(payload: bytes, device: str = "dev") -> RawBatch:
    r = decode(payload, device)
    assert isinstance(r, RawBatch), r
    return r


def test_crc32_is_the_ieee_catalogue_crc() -> None:
    assert zlib.crc32(b"123456789") == 0xCBF43926


def test_json_batch_units_and_fields() -> None:
    body = json.dumps(
        {
            "v": 1,
            "utc_offset_s": 100.0,
            "imu": [
                [T0, 0.1, 0.2, 9.8, 0.01, 0.02, 0.03],
                [T0 + 0.01, 0.1, 0.2, 9.8, 0.0, 0.0, 0.0, 20.0, 1.0, -40.0],
            ],
            "gnss": [FIX | {"hdop": None}],
        }
    ).encode()
    r = decode(body, topic="iotnav/car-7/raw")
    assert isinstance(r, Rejected) and r.reason == "bad_schema"  # rows of 7 and 10 numbers mixed
    body = body.replace(b", 0.0, 0.0, 0.0, 20.0, 1.0, -40.0]", b", 0.0, 0.0, 0.0]")
    b = decode(body, topic="iotnav/car-7/raw")
    assert isinstance(b, RawBatch) and b.device == "car-7"
    assert b.imu.shape == (2, 7) and b.imu[0].tolist() == [T0, 0.1, 0.2, 9.8, 0.01, 0.02, 0.03]
    (g,) = b.gnss
    assert (g.t, g.lat_deg, g.lon_deg, g.height_m, g.h_acc_m, g.speed_mps, g.course_rad, g.num_sv) == (
        T0,
        45.5,
        7.25,
        250.0,
        3.0,
        10.0,
        1.5,
        9,
    )
    assert math.isnan(g.hdop) and g.valid
    (fix,) = b.fixes()
    assert fix.t == T0 + 100.0 and fix.device == "car-7" and fix.attributes["t_device"] == T0


def test_json_magnetometer_in_imu_rows() -> None:
    b = _ok(encode_json([[T0, 0, 0, 9.8, 0, 0, 0, 20.0, 1.0, -40.0]]))
    assert b.imu.shape == (1, 7) and b.mag.tolist() == [[T0, 20.0, 1.0, -40.0]]


def test_binary_layout_by_hand() -> None:
    """A binary batch assembled field by field from the documented table."""
    imu = struct.pack("<I6f", 10_000, 0.5, -0.25, 9.75, 0.125, 0.0, -0.5)
    gnss = struct.pack("<IddfffffBB", 0, 45.5, 7.25, 250.0, 3.0, 10.0, 1.5, 0.75, 9, 1)
    body = b"IR" + bytes([1, 0]) + struct.pack("<ddHH", T0, 0.0, 1, 1) + imu + gnss
    assert len(body) == 24 + 28 + 42
    b = _ok(body + struct.pack("<I", zlib.crc32(body)))
    assert b.imu.tolist() == [[T0 + 0.01, 0.5, -0.25, 9.75, 0.125, 0.0, -0.5]]
    (g,) = b.gnss
    assert (g.t, g.lat_deg, g.lon_deg, g.height_m, g.hdop, g.num_sv, g.valid) == (
        T0,
        45.5,
        7.25,
        250.0,
        0.75,
        9,
        True,
    )
    bad = body + struct.pack("<I", zlib.crc32(body) ^ 1)
    assert decode(bad, "d") == Rejected("bad_crc", "CRC-32 does not match")


def test_binary_round_trip_and_float32_rounding() -> None:
    rows = np.array([[T0 + k * 0.01, 0.1 * k, 0.2, 9.81, 0.001, -0.002, 0.3] for k in range(100)])
    g = GnssRecord(T0 + 0.5, 45.123456789, 7.987654321, 300.0, 2.5, speed_mps=12.0, course_rad=2.0, num_sv=12)
    b = _ok(encode_binary(T0, rows, [g], utc_offset_s=0.0))
    assert b.imu.shape == (100, 7)
    assert np.max(np.abs(b.imu[:, 0] - rows[:, 0])) < 1e-6  # microsecond time steps
    assert np.max(np.abs(b.imu[:, 1:] - rows[:, 1:])) < 1e-6 * 10  # float32
    assert b.gnss[0].lat_deg == g.lat_deg and b.gnss[0].lon_deg == g.lon_deg  # float64 positions
    assert len(encode_binary(T0, rows)) == 24 + 100 * 28 + 4  # 2.8 kB a second at 100 Hz


def test_samples_that_cannot_be_used_are_counted_not_fatal() -> None:
    imu = [
        [T0, 0, 0, 9.8, 0, 0, 0],
        [T0 + 0.01, math.nan, 0, 9.8, 0, 0, 0],
        [T0 + 0.02, 0, 0, 9.8, 0, 0, 0],
        [T0 + 0.005, 0, 0, 9.8, 0, 0, 0],  # time backwards
        [T0 + 0.03, 0, 0, math.inf, 0, 0, 0],
    ]
    gnss = [FIX, FIX | {"t": T0 - 1}, FIX | {"lat": 91.0}, FIX | {"t": 5.0}, FIX | {"lon": math.nan}]
    b = _ok(json.dumps({"v": 1, "imu": imu, "gnss": gnss}).encode())  # Python writes NaN / Infinity
    assert b.imu[:, 0].tolist() == [T0, T0 + 0.02]
    assert len(b.gnss) == 1
    assert b.skipped == {
        "imu_nonfinite": 2,
        "imu_time_backwards": 1,
        "gnss_time_backwards": 1,
        "gnss_bad_position": 1,
        "gnss_bad_time": 1,
        "gnss_nonfinite": 1,
    }


def test_rejections() -> None:
    cases = {
        b"{": "bad_json",
        b"[]": "bad_json",
        b'{"v": 2}': "bad_version",
        b'{"v": 1, "imu": [[1, 2, 3]]}': "bad_schema",
        b'{"v": 1, "imu": [[1, 2, 3, 4, 5, 6, "x"]]}': "bad_schema",
        b'{"v": 1, "gnss": [{"t": 1}]}': "bad_schema",
        b'{"v": 1, "utc_offset_s": 1e300}': "bad_offset",
        b"IR\x01\x00": "bad_length",
        b"IR\x02" + bytes(30): "bad_version",
        b"XY" + bytes(30): "bad_json",
    }
    for payload, reason in cases.items():
        r = decode(payload, "d")
        assert isinstance(r, Rejected) and r.reason == reason, (payload, r)
    huge = {"v": 1, "imu": [[T0, 0, 0, 0, 0, 0, 0]] * (MAX_SAMPLES + 1)}
    assert decode(json.dumps(huge).encode(), "d").reason == "too_many_samples"  # type: ignore[union-attr]
    assert decode(b"{}", topic="owntracks/a/b").reason == "no_device"  # type: ignore[union-attr]
    assert device_from_topic("iotnav/x/raw") == "x" and device_from_topic("iotnav/x/y/raw") is None


@FUZZ
@given(st.binary(max_size=600))
def test_fuzz_arbitrary_bytes(b: bytes) -> None:
    for p in (b, b"IR\x01" + b, b"{" + b):
        assert isinstance(decode(p, "d"), RawBatch | Rejected)


@FUZZ
@given(st.data())
def test_fuzz_binary_mutated_truncated_huge_counts(data: st.DataObject) -> None:
    rows = np.array([[T0 + k * 0.01, 0.1, 0.2, 9.81, 0.0, 0.0, 0.3] for k in range(5)])
    pkt = bytearray(encode_binary(T0, rows, [GnssRecord(T0, 45.0, 7.0)]))
    i = data.draw(st.integers(0, len(pkt) - 1))
    pkt[i] = data.draw(st.integers(0, 255))
    if data.draw(st.booleans()):  # counts set to anything, CRC repaired: lengths must not be trusted
        struct.pack_into("<HH", pkt, 20, data.draw(st.integers(0, 65535)), data.draw(st.integers(0, 65535)))
    if data.draw(st.booleans()):
        pkt[-4:] = struct.pack("<I", zlib.crc32(bytes(pkt[:-4])))
    cut = data.draw(st.integers(0, len(pkt)))
    r = decode(bytes(pkt[:cut]), "d")
    assert isinstance(r, RawBatch | Rejected)
    if isinstance(r, RawBatch):
        assert np.isfinite(r.imu).all() and all(math.isfinite(g.lat_deg) for g in r.gnss)


_num = st.floats() | st.integers(-(2**70), 2**70) | st.none() | st.text(max_size=3) | st.booleans()


@settings(FUZZ, max_examples=60)
@given(
    imu=st.lists(st.lists(_num, min_size=0, max_size=11), max_size=6),
    gnss=st.lists(
        st.dictionaries(st.sampled_from(["t", "lat", "lon", "alt", "nsat", "valid", "course"]), _num),
        max_size=4,
    ),
    off=_num,
)
def test_fuzz_json_fields(imu: list, gnss: list, off: object) -> None:
    body = json.dumps({"v": 1, "imu": imu, "gnss": gnss, "utc_offset_s": off}).encode()
    r = decode(body, "d")
    assert isinstance(r, RawBatch | Rejected)
    if isinstance(r, RawBatch):
        assert np.isfinite(r.imu).all()
        assert all(np.diff(r.imu[:, 0]) >= 0)
        assert all(math.isfinite(f.t) and abs(f.lat_deg) <= 90 for f in r.fixes())
