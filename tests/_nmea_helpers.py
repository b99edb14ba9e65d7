"""Helpers shared by the NMEA/UBX tests: corpus locations and independent counters.

The counters here re-implement the *definitions* stated in the docstrings of
:mod:`iotnav.io.nmea` and :mod:`iotnav.io.ubx` with plain regular expressions; they never call
the code under test.
"""

from __future__ import annotations

import calendar
import csv
import itertools
import json
import re
import tarfile
from functools import cache
from pathlib import Path

from conftest import datasets_dir

DATA = datasets_dir()
GPSD = DATA / "gpsd_nmea_corpus"
GPSD_LOGS = GPSD / "logs"
PYNMEAGPS_LOGS = DATA / "pynmeagps_nmea_tests" / "logs"
WALK = DATA / "rtklibexplorer_gnss_imu" / "walk_0827"

_FRAG = re.compile(rb"\$|![A-Z]{2}")
_NUM_LINE = re.compile(rb"\s*[+-]?\d+(?:\.\d*)?\s*")
_TS_PREFIX = re.compile(rb"\s*[+-]?\d+(?:\.\d*)?\s*[,;\t ]\s*")
SENTENCE = re.compile(rb"[$!]([A-Za-z0-9]{2,15})(,[^*]*)?\*([0-9A-Fa-f]{2})")


def count_units(data: bytes) -> int:
    """Units as defined in :mod:`iotnav.io.nmea`: one per '$'/'!XX' fragment, one per comment
    line, number-only line or garbage text before the first fragment (a timestamp prefix is
    not a unit)."""
    n = 0
    for line in data.split(b"\n"):
        line = line.strip()
        if not line:
            continue
        if line.startswith(b"#"):
            n += 1
            continue
        frags = list(_FRAG.finditer(line))
        n += len(frags)
        head = line[: frags[0].start()] if frags else line
        if head.strip() and not (frags and _TS_PREFIX.fullmatch(head)):
            n += 1
    return n


def xor_checksum(body: bytes) -> int:
    ck = 0
    for b in body:
        ck ^= b
    return ck


def count_bad_checksums(data: bytes) -> int:
    """Fragments '$ADDR,...*hh' (not in '#' lines) whose checksum is wrong."""
    n = 0
    for line in data.split(b"\n"):
        line = line.strip()
        if line.startswith(b"#"):
            continue
        starts = [m.start() for m in _FRAG.finditer(line)] + [len(line)]
        for a, b in itertools.pairwise(starts):
            m = SENTENCE.match(line[a:b].strip())
            if m and xor_checksum(line[a + 1 : a + m.end() - 3]) != int(m.group(3), 16):
                n += 1
    return n


def has_valid_nmea(data: bytes) -> bool:
    """True when any '$ADDR,...*hh' with a correct checksum occurs anywhere in the bytes."""
    for m in re.finditer(rb"[$!][A-Za-z0-9]{2,15}(?:,[^*$\r\n]*)?\*([0-9A-Fa-f]{2})", data):
        body = data[m.start() + 1 : m.end() - 3]
        if xor_checksum(body) == int(m.group(1), 16):
            return True
    return False


def ubx_frames(data: bytes, cls_id: bytes | None = None) -> list[int]:
    """Offsets of checksum-valid UBX frames (optionally of one class/id), found by brute scan."""
    out = []
    i = data.find(b"\xb5\x62")
    while i >= 0:
        if i + 8 <= len(data):
            length = data[i + 4] | (data[i + 5] << 8)
            end = i + 8 + length
            if end <= len(data):
                a = b = 0
                for x in data[i + 2 : i + 6 + length]:
                    a = (a + x) % 256
                    b = (b + a) % 256
                if bytes((a, b)) == data[end - 2 : end] and (cls_id is None or data[i + 2 : i + 4] == cls_id):
                    out.append(i)
        i = data.find(b"\xb5\x62", i + 1)
    return out


@cache
def gpsd_index() -> dict[str, dict[str, str]]:
    with open(GPSD / "index.csv", newline="", encoding="utf-8") as f:
        return {row["file"]: row for row in csv.DictReader(f)}


@cache
def gpsd_chk() -> dict[str, str]:
    """The expected gpsd output per log name (``<log>.log``), from the tarball, in memory."""
    out = {}
    with tarfile.open(GPSD / "gpsd_expected_chk.tar.xz") as tar:
        for member in tar.getmembers():
            if member.isfile() and member.name.endswith(".chk"):
                f = tar.extractfile(member)
                assert f is not None
                out[Path(member.name).name[: -len(".chk")]] = f.read().decode("utf-8", "replace")
    return out


def iso_to_unix(s: str) -> float:
    """'2014-12-31T03:07:19.000Z' -> Unix seconds (ms precision)."""
    date, time = s.rstrip("Z").split("T")
    y, mo, d = (int(x) for x in date.split("-"))
    hh, mm, ss = time.split(":")
    return calendar.timegm((y, mo, d, int(hh), int(mm), 0, 0, 0, 0)) + float(ss)


def gpsd_tpvs(chk: str) -> dict[float, dict]:
    """gpsd's TPV per time (ms-rounded Unix s): the last TPV reported for that time, which holds
    everything gpsd merged over the cycle."""
    out: dict[float, dict] = {}
    for line in chk.splitlines():
        if not line.startswith('{"class":"TPV"'):
            continue
        try:
            tpv = json.loads(line)
        except json.JSONDecodeError:
            continue
        if "time" in tpv:
            out[round(iso_to_unix(tpv["time"]), 3)] = tpv
    return out
