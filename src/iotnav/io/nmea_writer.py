"""NMEA 0183 writer: GNSS epochs to GGA, RMC, GSA, VTG sentences with valid checksums.

Each epoch of a :data:`iotnav.io.schema.GNSS_COLUMNS` table becomes four sentences (NMEA 2.3
layout, with the RMC/VTG mode indicator). Resolution: latitude and longitude as
``ddmm.mmmmmmm`` / ``dddmm.mmmmmmm`` (1e-7 minute, 0.2 mm), altitude and geoid separation
1 mm, time of day 0.01 s, speed 0.001 knot and 0.001 km/h, course 0.01 deg, DOPs 0.01.
An epoch without a valid fix gives quality 0, RMC status ``V`` and empty position fields; an
invalid course gives empty course fields. :func:`write_nmea_log` prefixes each line with the
device time (``12.345,$GPGGA,...``), the timestamped-log layout :mod:`iotnav.io.nmea` reads.
"""

from __future__ import annotations

import math
import os
from collections.abc import Sequence
from datetime import UTC, datetime

import numpy as np
import pandas as pd

__all__ = ["checksum", "epoch_sentences", "sentence", "write_nmea_log"]

KNOT_MPS = 1852.0 / 3600.0


def checksum(body: str) -> str:
    """XOR checksum of the characters between ``$`` and ``*``, two upper-case hex digits."""
    c = 0
    for ch in body.encode("ascii"):
        c ^= ch
    return f"{c:02X}"


def sentence(body: str) -> str:
    """``$body*hh`` with its checksum."""
    return f"${body}*{checksum(body)}"


def _lat(lat: float) -> tuple[str, str]:
    hemi = "N" if lat >= 0 else "S"
    a = abs(lat)
    d = int(a)
    m = (a - d) * 60.0
    if round(m, 7) >= 60.0:
        d, m = d + 1, 0.0
    return f"{d:02d}{m:010.7f}", hemi


def _lon(lon: float) -> tuple[str, str]:
    hemi = "E" if lon >= 0 else "W"
    a = abs(lon)
    d = int(a)
    m = (a - d) * 60.0
    if round(m, 7) >= 60.0:
        d, m = d + 1, 0.0
    return f"{d:03d}{m:010.7f}", hemi


def _f(x: float, fmt: str) -> str:
    return "" if x is None or not math.isfinite(x) else format(x, fmt)


def epoch_sentences(row: pd.Series | dict, prn: Sequence[int] = (), talker: str = "GP") -> list[str]:
    """GGA, RMC, GSA, VTG sentences of one epoch.

    Parameters
    ----------
    row : mapping
        One epoch with the :data:`GNSS_COLUMNS` fields (``utc`` must be finite).
    prn : sequence of int
        Satellite ids used (up to 12; negative ids are skipped).
    talker : str
        Talker id.

    Returns
    -------
    list of str
        Sentences without line terminators.
    """
    utc = float(row["utc"])
    dt = datetime.fromtimestamp(round(utc, 2), tz=UTC)
    hms = f"{dt.hour:02d}{dt.minute:02d}{dt.second:02d}.{dt.microsecond // 10000:02d}"
    date = f"{dt.day:02d}{dt.month:02d}{dt.year % 100:02d}"
    fix = bool(row["valid"]) and math.isfinite(float(row["lat_deg"]))
    sats = [p for p in prn if p > 0][:12]
    sat_fields = ",".join([f"{p:02d}" for p in sats] + [""] * (12 - len(sats)))
    if not fix:
        return [
            sentence(f"{talker}GGA,{hms},,,,,0,{max(int(row['num_sv']), 0):02d},,,M,,M,,"),
            sentence(f"{talker}RMC,{hms},V,,,,,,,{date},,,N"),
            sentence(f"{talker}GSA,A,1," + ",".join([""] * 12) + ",,,"),
            sentence(f"{talker}VTG,,T,,M,,N,,K,N"),
        ]
    la, ns = _lat(float(row["lat_deg"]))
    lo, ew = _lon(float(row["lon_deg"]))
    q = int(row["quality"])
    hdop = _f(float(row["hdop"]), ".2f")
    alt = _f(float(row["alt_msl_m"]), ".3f")
    sep = _f(float(row["geoid_sep_m"]), ".3f")
    spd = float(row["speed_mps"])
    kn = _f(spd / KNOT_MPS, ".3f")
    kmh = _f(spd * 3.6, ".3f")
    cog = _f(math.degrees(float(row["course_rad"])), ".2f") if bool(row["course_valid"]) else ""
    mode3 = "3" if int(row["mode"]) == 3 else "2"
    return [
        sentence(
            f"{talker}GGA,{hms},{la},{ns},{lo},{ew},{q},{int(row['num_sv']):02d},{hdop},{alt},M,{sep},M,,"
        ),
        sentence(f"{talker}RMC,{hms},A,{la},{ns},{lo},{ew},{kn},{cog},{date},,,A"),
        sentence(
            f"{talker}GSA,A,{mode3},{sat_fields},{_f(float(row['pdop']), '.2f')},{hdop},{_f(float(row['vdop']), '.2f')}"
        ),
        sentence(f"{talker}VTG,{cog},T,,M,{kn},N,{kmh},K,A"),
    ]


def write_nmea_log(
    path: str | os.PathLike[str],
    gnss: pd.DataFrame,
    prn: np.ndarray | None = None,
    talker: str = "GP",
    timestamped: bool = True,
) -> int:
    """Write epochs as an NMEA log, one sentence per line.

    Parameters
    ----------
    path : path-like
        Output file.
    gnss : pandas.DataFrame
        Epochs (:data:`GNSS_COLUMNS`); ``t`` is the device time written before each line.
    prn : numpy.ndarray, optional
        ``(n, 12)`` satellite ids per epoch (-1 unused).
    talker : str
        Talker id.
    timestamped : bool
        Prefix lines with ``<device time, 3 decimals>,``.

    Returns
    -------
    int
        Number of lines written.
    """
    lines: list[str] = []
    recs = gnss.to_dict("records")
    for i, row in enumerate(recs):
        sats: Sequence[int] = () if prn is None else [int(p) for p in prn[i]]
        pre = f"{float(row['t']):.3f}," if timestamped else ""
        lines.extend(pre + s for s in epoch_sentences(row, sats, talker))
    with open(path, "w", newline="") as fh:
        fh.write("\r\n".join(lines) + ("\r\n" if lines else ""))
    return len(lines)
