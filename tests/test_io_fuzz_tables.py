"""Fuzzing the table readers: arbitrary and mutated input never escapes as anything but IngestError,
and every line of a file is accounted for (records + ignored + skipped == lines)."""

from __future__ import annotations

import tempfile
from pathlib import Path

from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from conftest import datasets_dir
from iotnav.io.errors import IngestError
from iotnav.io.imu_csv import read_imu_csv
from iotnav.io.phone import read_gnsslogger
from iotnav.io.rtklib import read_rtklib_pos

RTK = datasets_dir() / "rtklibexplorer_gnss_imu"


def _head(path: Path, n: int) -> bytes:
    return b"".join(path.read_bytes().splitlines(keepends=True)[:n])


# Excerpts of real files (read at import, a few KB; nothing is copied into the repository)
SEEDS = {
    "imu": _head(RTK / "walk_0827" / "imu_1730.csv", 25),
    "imu_hdr": _head(RTK / "drive_0708" / "imu_1934_gpst.csv", 25),
    "pos": _head(RTK / "drive_0708" / "gnss_1934_sf.pos", 20),
    "gl": (Path(__file__).parent / "data" / "gnsslogger_small.txt").read_bytes(),
}


def _lines(data: bytes) -> int:
    """Lines ended by \\n, \\r\\n or a lone \\r; a last unterminated line counts."""
    n = data.count(b"\n") + data.count(b"\r") - data.count(b"\r\n")
    return n + (1 if data and not data.endswith((b"\n", b"\r")) else 0)


@st.composite
def mutated(draw: st.DrawFn, seed: bytes) -> bytes:
    data = bytearray(seed)
    for _ in range(draw(st.integers(0, 6))):
        if not data:
            break
        op = draw(st.sampled_from(["flip", "insert", "delete", "dup_line"]))
        i = draw(st.integers(0, len(data) - 1))
        if op == "flip":
            data[i] = draw(st.sampled_from(list(b",.-\n\r e0123456789xn#%\x00\xff")))
        elif op == "insert":
            data[i:i] = draw(st.binary(min_size=1, max_size=8))
        elif op == "delete":
            del data[i : i + draw(st.integers(1, 20))]
        else:
            j = data.find(b"\n", i)
            k = data.rfind(b"\n", 0, i) + 1
            if j > k:
                data[j + 1 : j + 1] = data[k : j + 1]
    return bytes(data)


def _check(reader, data: bytes, suffix: str, **kw) -> None:
    with tempfile.TemporaryDirectory() as d:
        p = Path(d) / f"f{suffix}"
        p.write_bytes(data)
        try:
            part = reader(p, **kw)
        except IngestError:
            return
        r = part.report
        assert r.n_records + sum(r.ignored.values()) + r.n_skipped == r.units
        assert r.units == _lines(data)


FUZZ = settings(
    max_examples=60, derandomize=True, deadline=None, suppress_health_check=[HealthCheck.too_slow]
)


@FUZZ
@given(st.binary(max_size=600))
def test_random_bytes(data: bytes) -> None:
    _check(read_imu_csv, data, ".csv")
    _check(read_rtklib_pos, data, ".pos")
    _check(read_gnsslogger, data, ".txt")


@FUZZ
@given(mutated(SEEDS["imu"]))
def test_mutated_imu(data: bytes) -> None:
    _check(read_imu_csv, data, ".csv", preset="rtklib-demo5", time_unit="ms")


@FUZZ
@given(mutated(SEEDS["imu_hdr"]))
def test_mutated_imu_with_header(data: bytes) -> None:
    _check(read_imu_csv, data, ".csv")


@FUZZ
@given(mutated(SEEDS["pos"]))
def test_mutated_pos(data: bytes) -> None:
    _check(read_rtklib_pos, data, ".pos")


@FUZZ
@given(mutated(SEEDS["gl"]))
def test_mutated_gnsslogger(data: bytes) -> None:
    _check(read_gnsslogger, data, ".txt")
