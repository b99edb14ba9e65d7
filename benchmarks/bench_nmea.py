"""Throughput of :func:`iotnav.io.nmea.read_nmea` on a day of 1 Hz NMEA.

A real capture (gpsd corpus, ``bu353s4.log``, SiRF IV: GGA + GSA + RMC each second, GSV every
5 s) is repeated with its times shifted second by second to one day (about 500 000 sentences, 1.6 days
at 3.6 sentences per fix, checksums recomputed), then read. Also times pynmeagps alone on a sample, the
rate a pure-pynmeagps reader could not beat.

Run: ``python benchmarks/bench_nmea.py``
"""

from __future__ import annotations

import os
import statistics
import time
from pathlib import Path
from typing import Any

from pynmeagps import NMEAReader

from iotnav.io.nmea import read_nmea

DATASETS = Path(
    os.environ.get("IOTNAV_DATASETS", Path(__file__).resolve().parents[2] / "shared" / "datasets")
)
LOG = DATASETS / "gpsd_nmea_corpus" / "logs" / "bu353s4.log"
SENTENCES_PER_DAY = 500_000


def _with_checksum(body: str) -> str:
    ck = 0
    for ch in body.encode("ascii"):
        ck ^= ch
    return f"${body}*{ck:02X}"


def synthesise() -> bytes:
    """One cycle template per second of a day, sentences with the second's time and date."""
    lines = [ln.strip() for ln in LOG.read_text("ascii").splitlines() if ln.startswith("$GP")]
    cycle = [ln[1 : ln.index("*")] for ln in lines[:3]]  # GGA, GSA, RMC
    gsv = [ln[1 : ln.index("*")] for ln in lines if ln.startswith("$GPGSV")][:3]
    out = []
    n = 0
    sec = 0
    while n < SENTENCES_PER_DAY:
        hh, mm, ss = sec // 3600 % 24, sec // 60 % 60, sec % 60
        tod = f"{hh:02d}{mm:02d}{ss:02d}.000"
        for body in cycle:
            f = body.split(",")
            if f[0] in ("GPGGA", "GPRMC"):
                f[1] = tod
            if f[0] == "GPRMC":
                f[9] = f"{1 + sec // 86400:02d}0115"  # 1 Jan 2015, 2 Jan ...
            out.append(_with_checksum(",".join(f)))
            n += 1
        if sec % 5 == 0:
            out += [_with_checksum(b) for b in gsv]
            n += len(gsv)
        sec += 1
    return ("\r\n".join(out) + "\r\n").encode("ascii")


def measure(repeats: int = 3) -> dict[str, Any]:
    """Read the synthesised day ``repeats`` times; median wall time and pynmeagps's rate."""
    data = synthesise()
    n = data.count(b"$")
    walls = []
    epochs = 0
    for _ in range(repeats):
        t0 = time.perf_counter()
        part = read_nmea(data)
        walls.append(time.perf_counter() - t0)
        epochs = len(part.gnss)
    wall = statistics.median(walls)
    sample = data[:2_000_000].split(b"\r\n")[:20000]
    t0 = time.perf_counter()
    for s in sample:
        if s:
            NMEAReader.parse(s, validate=1)
    rate_ref = len(sample) / (time.perf_counter() - t0)
    return {"sentences": n, "epochs": epochs, "wall_s": wall, "runs": walls, "pynmeagps_rate": rate_ref}


def main() -> None:
    r = measure()
    n, dt = r["sentences"], r["wall_s"]
    print(
        f"read_nmea: {n} sentences, {r['epochs']} epochs in {dt:.2f} s (median) = {n / dt:,.0f} sentences/s"
    )
    rate = r["pynmeagps_rate"]
    print(f"pynmeagps alone: {rate:,.0f} sentences/s -> {n / rate:.1f} s for the day")


if __name__ == "__main__":
    main()
