"""NMEA 0183 reader: hand-computed values, time handling, accounting, edge-case logs.

Expected values come from the NMEA 0183 definitions worked by hand in the comments (ddmm.mmm ->
degrees, knots -> m/s, ddmmyy dates through :func:`calendar.timegm`) and from independent
regular-expression counts over the raw bytes (``tests/_nmea_helpers.py``).
"""

from __future__ import annotations

import calendar
import math
import re

import numpy as np
import pytest
from pynmeagps import NMEAReader

from _nmea_helpers import GPSD_LOGS, PYNMEAGPS_LOGS, SENTENCE, count_bad_checksums, count_units
from iotnav.io.errors import IngestError
from iotnav.io.nmea import NmeaEpochAssembler, decode_fast, read_nmea, sentence_from_message
from iotnav.io.report import FileReport, SkipReason


def nmea(body: str, lower: bool = False) -> str:
    """'GPGGA,...' -> '$GPGGA,...*hh' with the XOR checksum computed here."""
    ck = 0
    for ch in body.encode("ascii"):
        ck ^= ch
    hh = f"{ck:02X}"
    return f"${body}*{hh.lower() if lower else hh}"


def log(*sentences: str) -> bytes:
    return ("\r\n".join(sentences) + "\r\n").encode("ascii")


def accounted(rep: FileReport) -> int:
    return rep.n_records + sum(rep.ignored.values()) + rep.n_skipped


KN = 1852.0 / 3600.0

# ------------------------------------------------------------------ hand-computed single fixes


def test_gga_rmc_classic_example():
    # The textbook sentences: 4807.038 N = 48 + 7.038/60 = 48.1173 deg; 01131.000 E = 11 + 31/60.
    data = log(
        nmea("GPGGA,123519,4807.038,N,01131.000,E,1,08,0.9,545.4,M,46.9,M,,"),
        nmea("GPRMC,123519,A,4807.038,N,01131.000,E,022.4,084.4,230394,003.1,W"),
    )
    part = read_nmea(data)
    g = part.gnss
    assert part.clock == "utc"
    assert len(g) == 1
    r = g.iloc[0]
    assert r.lat_deg == pytest.approx(48.1173, abs=1e-9)
    assert r.lon_deg == pytest.approx(11.0 + 31.0 / 60.0, abs=1e-9)
    assert r.alt_msl_m == pytest.approx(545.4)
    assert r.geoid_sep_m == pytest.approx(46.9)
    assert r.height_m == pytest.approx(592.3)
    assert r.quality == 1 and r.num_sv == 8 and r.hdop == pytest.approx(0.9)
    assert r["mode"] == 3  # GGA quality 1 with an altitude, no GSA
    assert r.speed_mps == pytest.approx(22.4 * 1852 / 3600)
    assert r.course_rad == pytest.approx(math.radians(84.4))
    assert r.course_valid and r.valid
    utc = calendar.timegm((1994, 3, 23, 12, 35, 19, 0, 0, 0))
    assert r.utc == utc and r.t == utc
    assert r.source == "nmea"
    assert dict(part.report.records) == {"GGA": 1, "RMC": 1}


def test_southern_western_hemispheres_and_fraction_of_second():
    # 3747.0873 S = -(37 + 47.0873/60); 17518.8938 W = -(175 + 18.8938/60); time 03:07:19.250.
    data = log(
        nmea("GNGGA,030719.250,3747.0873,S,17518.8938,W,2,12,0.7,59.9,M,23.7,M,1.0,0000"),
        nmea("GNRMC,030719.250,A,3747.0873,S,17518.8938,W,0.00,,311214,,,D"),
    )
    r = read_nmea(data).gnss.iloc[0]
    assert r.lat_deg == pytest.approx(-(37 + 47.0873 / 60), abs=1e-10)
    assert r.lon_deg == pytest.approx(-(175 + 18.8938 / 60), abs=1e-10)
    assert r.utc == pytest.approx(calendar.timegm((2014, 12, 31, 3, 7, 19, 0, 0, 0)) + 0.25)
    assert r.quality == 2
    assert not r.course_valid  # empty course field
    assert np.isnan(r.course_rad)


def test_vtg_speed_and_course_when_no_rmc():
    # VTG: 054.7 deg true, 005.5 knots; km/h used only when knots are empty (10.2 km/h).
    data = log(
        nmea("GPGGA,120000,4807.038,N,01131.000,E,1,08,0.9,545.4,M,46.9,M,,"),
        nmea("GPVTG,054.7,T,034.4,M,005.5,N,010.2,K,A"),
        nmea("GPGGA,120001,4807.038,N,01131.000,E,1,08,0.9,545.4,M,46.9,M,,"),
        nmea("GPVTG,054.7,T,034.4,M,,N,010.2,K,N"),
    )
    g = read_nmea(data).gnss
    assert g.speed_mps.iloc[0] == pytest.approx(5.5 * KN)
    assert g.course_rad.iloc[0] == pytest.approx(math.radians(54.7))
    assert g.course_valid.iloc[0]
    assert g.speed_mps.iloc[1] == pytest.approx(10.2 / 3.6)
    assert not g.course_valid.iloc[1]  # VTG mode N: receiver says the data are not valid


def test_course_invalid_when_rmc_status_void():
    data = log(
        nmea("GPRMC,120000,V,4807.038,N,01131.000,E,0.5,123.0,230394,,,N"),
        nmea("GPRMC,120001,A,4807.038,N,01131.000,E,0.5,359.99,230394,,,A"),
    )
    g = read_nmea(data).gnss
    assert not g.course_valid.iloc[0] and not g.valid.iloc[0]
    assert g["mode"].iloc[0] == 1  # RMC V -> no fix
    assert np.isnan(g.lat_deg.iloc[0])  # no position reported for a no-fix cycle
    assert g.course_valid.iloc[1] and g["mode"].iloc[1] == 2  # RMC alone: 2D
    assert 0 <= g.course_rad.iloc[1] < 2 * math.pi
    assert g.course_rad.iloc[1] == pytest.approx(math.radians(359.99))


@pytest.mark.parametrize(
    ("sentences", "mode", "valid"),
    [
        (["GPGGA,120000,4807.038,N,01131.000,E,0,00,,,M,,M,,"], 1, False),
        (["GPGGA,120000,4807.038,N,01131.000,E,1,05,1.2,,M,,M,,"], 2, True),  # no altitude -> 2D
        (["GPGGA,120000,4807.038,N,01131.000,E,1,05,1.2,10.0,M,,M,,"], 3, True),
        (
            [
                "GPGGA,120000,4807.038,N,01131.000,E,1,05,1.2,10.0,M,,M,,",
                "GPGSA,A,2,01,02,03,,,,,,,,,,2.0,1.2,1.6",
            ],
            2,  # the receiver's explicit 2D in GSA wins over the altitude field
            True,
        ),
        (["GNGNS,120000,4807.038,N,01131.000,E,NN,00,,,,,,V"], 1, False),
        (["GNGNS,120000,4807.038,N,01131.000,E,AN,05,1.1,10.0,2.0,,,V"], 3, True),
        (["GPGLL,4807.038,N,01131.000,E,120000,A,A"], 2, True),
    ],
)
def test_mode_and_validity(sentences, mode, valid):
    g = read_nmea(log(*(nmea(s) for s in sentences))).gnss
    assert len(g) == 1
    assert g["mode"].iloc[0] == mode
    assert bool(g.valid.iloc[0]) is valid


def test_gns_gll_zda_through_pynmeagps():
    data = log(
        nmea("GPZDA,120000.00,23,03,1994,00,00"),
        nmea("GNGNS,120000.00,4807.038,N,01131.000,E,AA,10,0.9,545.4,46.9,,,V"),
    )
    r = read_nmea(data).gnss.iloc[0]
    assert r.lat_deg == pytest.approx(48.1173)
    assert r.height_m == pytest.approx(592.3)
    assert r.num_sv == 10
    assert r.utc == calendar.timegm((1994, 3, 23, 12, 0, 0, 0, 0, 0))


# ------------------------------------------------------------------ multi-constellation GSA


def test_multi_gsa_union_by_constellation():
    # GGA without a satellite count; three GSA: GPS 5 PRNs, GLONASS 3, Galileo with PRN 5 again
    # (NMEA 4.10 system id 3) -> the union is 5 + 3 + 1 = 9 distinct satellites.
    data = log(
        nmea("GNGGA,120000,4807.038,N,01131.000,E,1,,0.8,545.4,M,46.9,M,,"),
        nmea("GNGSA,A,3,01,05,12,15,24,,,,,,,,1.5,0.8,1.2,1"),
        nmea("GNGSA,A,3,65,71,72,,,,,,,,,,1.5,0.8,1.2,2"),
        nmea("GNGSA,A,3,05,,,,,,,,,,,,1.5,0.8,1.2,3"),
        nmea("GNRMC,120000,A,4807.038,N,01131.000,E,0.0,,230394,,,A"),
    )
    r = read_nmea(data).gnss.iloc[0]
    assert r.num_sv == 9
    assert (r.pdop, r.hdop, r.vdop) == (1.5, 0.8, 1.2)
    assert r["mode"] == 3


def test_gsa_before_first_timed_sentence_joins_that_cycle():
    data = log(
        nmea("GPGSA,A,3,01,05,12,,,,,,,,,,2.5,1.5,2.0"),
        nmea("GPGGA,120000,4807.038,N,01131.000,E,1,03,1.5,545.4,M,46.9,M,,"),
    )
    g = read_nmea(data).gnss
    assert len(g) == 1 and g.pdop.iloc[0] == 2.5


# ------------------------------------------------------------------ time: dates and rollover


def test_midnight_and_year_rollover_from_gga():
    # RMC gives 31 Dec 1999 at 23:59:59; the GGA at 00:00:00 and 00:00:01 carry no date: the
    # date must move to 1 Jan 2000.
    data = log(
        nmea("GPGGA,235959,4807.038,N,01131.000,E,1,08,0.9,545.4,M,46.9,M,,"),
        nmea("GPRMC,235959,A,4807.038,N,01131.000,E,0.0,0.0,311299,,,A"),
        nmea("GPGGA,000000,4807.038,N,01131.000,E,1,08,0.9,545.4,M,46.9,M,,"),
        nmea("GPGGA,000001,4807.038,N,01131.000,E,1,08,0.9,545.4,M,46.9,M,,"),
    )
    g = read_nmea(data).gnss
    midnight = calendar.timegm((2000, 1, 1, 0, 0, 0, 0, 0, 0))
    np.testing.assert_array_equal(g.utc.to_numpy(), [midnight - 1, midnight, midnight + 1])
    np.testing.assert_array_equal(g.t.to_numpy(), g.utc.to_numpy())


def test_no_date_gives_unwrapped_seconds_of_day_and_a_note():
    data = log(
        nmea("GPGGA,235958.5,4807.038,N,01131.000,E,1,08,0.9,545.4,M,46.9,M,,"),
        nmea("GPGGA,235959.5,4807.038,N,01131.000,E,1,08,0.9,545.4,M,46.9,M,,"),
        nmea("GPGGA,000000.5,4807.038,N,01131.000,E,1,08,0.9,545.4,M,46.9,M,,"),
    )
    part = read_nmea(data)
    np.testing.assert_allclose(part.gnss.t.to_numpy(), [86398.5, 86399.5, 86400.5])
    assert part.gnss.utc.isna().all()
    assert any("no date" in n for n in part.report.notes)


def test_cycles_before_the_first_date_are_placed_back_from_it():
    data = log(
        nmea("GPGGA,100000,4807.038,N,01131.000,E,1,08,0.9,545.4,M,46.9,M,,"),
        nmea("GPGGA,100001,4807.038,N,01131.000,E,1,08,0.9,545.4,M,46.9,M,,"),
        nmea("GPRMC,100001,A,4807.038,N,01131.000,E,0.0,0.0,010120,,,A"),
    )
    g = read_nmea(data).gnss
    t1 = calendar.timegm((2020, 1, 1, 10, 0, 1, 0, 0, 0))
    np.testing.assert_array_equal(g.t.to_numpy(), [t1 - 1, t1])
    assert np.isnan(g.utc.iloc[0]) and g.utc.iloc[1] == t1


def test_time_going_backwards_is_dropped_and_counted():
    data = log(
        nmea("GPRMC,120002,A,4807.038,N,01131.000,E,0.0,0.0,010120,,,A"),
        nmea("GPRMC,120001,A,4807.038,N,01131.000,E,0.0,0.0,010120,,,A"),
        nmea("GPRMC,120003,A,4807.038,N,01131.000,E,0.0,0.0,010120,,,A"),
    )
    part = read_nmea(data)
    base = calendar.timegm((2020, 1, 1, 12, 0, 0, 0, 0, 0))
    np.testing.assert_array_equal(part.gnss.t.to_numpy(), [base + 2, base + 3])
    assert part.report.skipped[SkipReason.NON_MONOTONIC] == 1


# ------------------------------------------------------------------ timestamped logs

_TWO_FIXES = [
    nmea("GPGGA,120000,4807.038,N,01131.000,E,1,08,0.9,545.4,M,46.9,M,,"),
    nmea("GPRMC,120000,A,4807.038,N,01131.000,E,0.0,0.0,010120,,,A"),
    nmea("GPGGA,120001,4807.038,N,01131.000,E,1,08,0.9,545.4,M,46.9,M,,"),
    nmea("GPRMC,120001,A,4807.038,N,01131.000,E,0.0,0.0,010120,,,A"),
]


@pytest.mark.parametrize("sep", [",", " ", "\t"])
def test_device_timestamp_prefix_ms(sep):
    stamps = [123456, 123470, 124456, 124470]  # ms; the cycle takes its first sentence's stamp
    text = "".join(f"{s}{sep}{line}\r\n" for s, line in zip(stamps, _TWO_FIXES, strict=True))
    part = read_nmea(text.encode())
    assert part.clock == "device"
    np.testing.assert_allclose(part.gnss.t.to_numpy(), [123.456, 124.456])
    base = calendar.timegm((2020, 1, 1, 12, 0, 0, 0, 0, 0))
    np.testing.assert_array_equal(part.gnss.utc.to_numpy(), [base, base + 1])
    assert part.report.units == 4 and accounted(part.report) == 4


def test_device_timestamp_seconds_and_explicit_unit():
    text = "".join(
        f"{s},{line}\n" for s, line in zip([12.345, 12.36, 13.345, 13.36], _TWO_FIXES, strict=True)
    )
    part = read_nmea(text.encode())
    np.testing.assert_allclose(part.gnss.t.to_numpy(), [12.345, 13.345])
    part_us = read_nmea(text.encode(), time_unit="us")
    np.testing.assert_allclose(part_us.gnss.t.to_numpy(), [12.345e-6, 13.345e-6])


def test_interspersed_timestamp_lines_apply_to_following_sentences():
    text = "5000000\n" + "\n".join(_TWO_FIXES[:2]) + "\n6000000\n" + "\n".join(_TWO_FIXES[2:]) + "\n"
    part = read_nmea(text.encode())  # us: a 1 s step of 1e6 ticks
    assert part.clock == "device"
    np.testing.assert_allclose(part.gnss.t.to_numpy(), [5.0, 6.0])
    assert part.report.records["timestamp"] == 2
    assert part.report.units == 6 == accounted(part.report)


# ------------------------------------------------------------------ robustness and accounting


def test_checksums_lower_case_bad_and_missing():
    good = nmea("GPGGA,120000,4807.038,N,01131.000,E,1,08,0.9,545.4,M,46.9,M,,", lower=True)
    bad = good[:-2] + ("00" if good[-2:] != "00" else "01")
    missing = "$GPGGA,120001,4807.038,N,01131.000,E,1,08,0.9,545.4,M,46.9,M,,"
    part = read_nmea(log(good, bad, missing))
    rep = part.report
    assert len(part.gnss) == 1
    assert rep.skipped[SkipReason.BAD_CHECKSUM] == 1
    assert rep.skipped[SkipReason.TRUNCATED] == 1
    assert accounted(rep) == rep.units == 3


def test_sentence_after_garbage_on_the_same_line_is_read():
    gga = nmea("GPGGA,120000,4807.038,N,01131.000,E,1,08,0.9,545.4,M,46.9,M,,")
    data = b"\x00\xff\xfeJUNK" + gga.encode() + b"\r\n"
    part = read_nmea(data)
    assert len(part.gnss) == 1 and part.gnss.lat_deg.iloc[0] == pytest.approx(48.1173)
    assert part.report.skipped[SkipReason.GARBAGE] == 1
    assert accounted(part.report) == part.report.units == count_units(data) == 2


def test_unknown_proprietary_ais_comments_and_out_of_range():
    data = log(
        "# a header line",
        nmea("PUBX,00,120000.00,4807.038,N,01131.000,E,545.4,G3,2.1,2.0,0.0,0.0,0.0,,0.9,1.0,0.8,8,0,0"),
        nmea("GPXYZ,1,2,3"),  # a type pynmeagps does not know
        "!AIVDM,1,1,,A,13aEOK?P00PD2wVMdLDRhgvL289?,0*26",
        nmea("GPGGA,120000,9107.038,N,01131.000,E,1,08,0.9,545.4,M,46.9,M,,"),  # 91 deg N
        nmea("GPGGA,120001,4807.038,N,01131.000,E,1,08,0.9,XXXXX,M,46.9,M,,"),  # not a number
        nmea("GPGSV,1,1,01,05,40,083,46"),
    )
    rep = read_nmea(data).report
    assert rep.ignored["comment"] == 1
    assert rep.ignored["PUBX"] == 1
    assert rep.ignored["GSV"] == 1
    assert rep.skipped[SkipReason.UNKNOWN_SENTENCE] == 1
    assert rep.skipped[SkipReason.OUT_OF_RANGE] == 1
    assert rep.skipped[SkipReason.MALFORMED] == 1
    # the AIS line's checksum is whatever the capture had: counted one way or the other
    assert accounted(rep) == rep.units == count_units(data) == 7


@pytest.mark.parametrize(
    "blob",
    [
        b"\x89PNG\r\n\x1a\n\x00\x00\x00\rIHDR\x00\x00\x00\x10",
        b"time,lat,lon\n1,48.1,11.5\n2,48.2,11.6\n",
        b"",
        b"$",
    ],
)
def test_no_nmea_raises_ingest_error(blob):
    with pytest.raises(IngestError, match="no NMEA 0183 sentences"):
        read_nmea(blob, name="x.bin")


def test_lone_dollar_at_eof_and_truncated_last_line():
    gga = nmea("GPGGA,120000,4807.038,N,01131.000,E,1,08,0.9,545.4,M,46.9,M,,")
    data = (gga + "\r\n$GPGGA,120001,4807.0\r\n$").encode()
    part = read_nmea(data)
    assert len(part.gnss) == 1
    assert part.report.skipped[SkipReason.TRUNCATED] == 1
    assert part.report.skipped[SkipReason.GARBAGE] == 1  # the lone '$'
    assert accounted(part.report) == part.report.units == count_units(data) == 3


# ------------------------------------------------------------------ real logs


@pytest.mark.parametrize("path", sorted(PYNMEAGPS_LOGS.glob("*.log")), ids=lambda p: p.name)
def test_pynmeagps_edge_case_logs(path):
    data = path.read_bytes()
    part = read_nmea(path)
    rep = part.report
    assert rep.units == count_units(data) == accounted(rep)
    assert rep.skipped.get(SkipReason.BAD_CHECKSUM, 0) == count_bad_checksums(data)
    assert part.gnss.t.is_monotonic_increasing
    ok = part.gnss.valid.to_numpy()
    lat = part.gnss.lat_deg.to_numpy()[ok]
    assert np.all(np.abs(lat) <= 90)


def test_pynmeagps_logs_with_known_bad_checksums_are_counted():
    # The fixtures named for bad checksums must really exercise that path.
    total = sum(
        read_nmea(PYNMEAGPS_LOGS / n).report.skipped.get(SkipReason.BAD_CHECKSUM, 0)
        for n in ("pygpsdata-nmeabadck.log", "pygpsdata-nmeabadck2.log")
    )
    assert total >= 1


def test_lower_case_checksum_log_is_fully_read():
    path = PYNMEAGPS_LOGS / "pygpsdata-nmea4lc.log"
    data = path.read_bytes()
    assert re.search(rb"\*[0-9a-f]*[a-f][0-9a-f]*\r?\n", data)  # the fixture has lower-case hex
    rep = read_nmea(path).report
    assert rep.skipped.get(SkipReason.BAD_CHECKSUM, 0) == 0
    assert rep.n_records > 0


# ------------------------------------------------------------------ fast path == pynmeagps


def _corpus_sentences(kinds: tuple[str, ...]):
    for path in sorted(GPSD_LOGS.glob("*.log")):
        for line in path.read_bytes().split(b"\n"):
            for m in SENTENCE.finditer(line):
                addr = m.group(1)
                if addr[:1] == b"P" or addr[2:].decode() not in kinds:
                    continue
                body = line[m.start() + 1 : m.end() - 3]
                ck = 0
                for b in body:
                    ck ^= b
                if ck == int(m.group(3), 16):
                    yield line[m.start() : m.end()]


def test_fast_decoder_equals_pynmeagps_on_the_gpsd_corpus():
    n = 0
    for raw in _corpus_sentences(("GGA", "RMC", "GSA", "VTG")):
        text = raw.decode("ascii", "replace")
        addr, *fields = text[1:-3].split(",")
        try:
            ref = sentence_from_message(NMEAReader.parse(text, validate=0))
        except Exception:
            ref = None
        try:
            fast = decode_fast(addr[:2], addr[2:], fields)
        except ValueError:
            fast = None
        assert (ref is None) == (fast is None), text
        if ref is not None:
            for name in ref.__slots__:
                a, b = getattr(ref, name), getattr(fast, name)
                same = a == b or (
                    isinstance(a, float) and isinstance(b, float) and math.isnan(a) and math.isnan(b)
                )
                if name in ("speed_mps",) and isinstance(a, float) and not same:
                    same = abs(a - b) <= 1e-12 * max(1.0, abs(a))
                assert same, (text, name, a, b)
        n += 1
    assert n > 10000  # the corpus holds tens of thousands of these


def test_assembler_accepts_pynmeagps_messages():
    rep = FileReport(path="mem", format="nmea")
    asm = NmeaEpochAssembler(rep)
    for i, s in enumerate(
        [
            nmea("GPGGA,120000,4807.038,N,01131.000,E,1,08,0.9,545.4,M,46.9,M,,"),
            nmea("GPGSV,1,1,01,05,40,083,46"),
            nmea("GPRMC,120000,A,4807.038,N,01131.000,E,0.0,0.0,010120,,,A"),
        ]
    ):
        asm.add(NMEAReader.parse(s), float(i), i)
    df = asm.finish()
    assert len(df) == 1 and df.lat_deg.iloc[0] == pytest.approx(48.1173)
    assert rep.records == {"GGA": 1, "RMC": 1} and rep.ignored == {"GSV": 1}


def test_nan_and_inf_written_in_number_fields_are_skipped():
    data = log(
        nmea("GPGGA,120000,4807.038,N,01131.000,E,1,08,0.9,nan,M,46.9,M,,"),
        nmea("GPRMC,120001,A,4807.038,N,01131.000,E,inf,0.0,010120,,,A"),
        nmea("GPGGA,120002,4807.038,N,01131.000,E,1,08,0.9,545.4,M,46.9,M,,"),
    )
    part = read_nmea(data)
    assert part.report.skipped[SkipReason.NAN_FIELD] == 2
    assert len(part.gnss) == 1
