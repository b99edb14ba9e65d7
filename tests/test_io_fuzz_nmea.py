"""Property-based robustness of the NMEA and UBX readers (hypothesis, derandomised).

Properties: no input makes a reader raise anything but :class:`IngestError`; the accounting
identity ``records + ignored + skipped == units`` holds and ``units`` equals the independent
regex count of ``tests/_nmea_helpers.py``; a valid sentence after garbage on its line is read;
epochs stay strictly increasing in time and inside the coordinate ranges.
"""

from __future__ import annotations

import numpy as np
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from _nmea_helpers import GPSD_LOGS, PYNMEAGPS_LOGS, count_units
from iotnav.io.errors import IngestError
from iotnav.io.log import Part
from iotnav.io.nmea import read_nmea
from iotnav.io.ubx import read_ubx

FUZZ = settings(
    derandomize=True, max_examples=250, deadline=None, suppress_health_check=[HealthCheck.too_slow]
)
SEEDS = [
    (GPSD_LOGS / "bu353s4.log").read_bytes(),
    (GPSD_LOGS / "ch-4711.log").read_bytes(),
    (GPSD_LOGS / "gp-320fw-2019-04-07-coldboot.log").read_bytes(),
    (PYNMEAGPS_LOGS / "pygpsdata-mixed.log").read_bytes(),
]
GGA = b"$GPGGA,123519,4807.038,N,01131.000,E,1,08,0.9,545.4,M,46.9,M,,*47"


def check_part(part: Part, data: bytes | None = None) -> None:
    rep = part.report
    assert rep.n_records + sum(rep.ignored.values()) + rep.n_skipped == rep.units
    if data is not None:
        assert rep.units == count_units(data)
    t = part.gnss.t.to_numpy()
    assert np.all(np.diff(t) > 0)
    lat = part.gnss.lat_deg.to_numpy()
    lat = lat[np.isfinite(lat)]
    assert np.all(np.abs(lat) <= 90)


def read_any(reader, data: bytes, with_count: bool) -> None:
    try:
        part = reader(data)
    except IngestError:
        return
    check_part(part, data if with_count else None)


@FUZZ
@given(st.binary(max_size=2000))
def test_arbitrary_bytes(data):
    read_any(read_nmea, data, True)
    read_any(read_ubx, data, False)


@FUZZ
@given(st.binary(max_size=300).filter(lambda b: b"\n" not in b and b"$" not in b and b"!" not in b))
def test_sentence_after_garbage_is_read(junk):
    data = junk.lstrip(b"#") + GGA + b"\r\n"
    part = read_nmea(data)
    assert len(part.gnss) == 1
    assert abs(part.gnss.lat_deg.iloc[0] - 48.1173) < 1e-9
    check_part(part, data)


@st.composite
def mutated_log(draw):
    data = bytearray(draw(st.sampled_from(SEEDS)))
    for _ in range(draw(st.integers(0, 20))):  # byte flips
        i = draw(st.integers(0, len(data) - 1))
        data[i] = draw(st.integers(0, 255))
    lines = bytes(data).split(b"\n")
    for _ in range(draw(st.integers(0, 5))):  # line duplication
        i = draw(st.integers(0, len(lines) - 1))
        lines.insert(i, lines[i])
    if draw(st.booleans()):  # interleave another log line by line
        other = draw(st.sampled_from(SEEDS)).split(b"\n")
        merged = []
        for a, b in zip(lines, other, strict=False):
            merged += [a, b]
        lines = merged
    out = b"\n".join(lines)
    cut = draw(st.integers(0, len(out)))  # truncation
    return out[:cut]


@FUZZ
@given(mutated_log())
def test_mutated_real_logs(data):
    read_any(read_nmea, data, True)
    read_any(read_ubx, data, False)
