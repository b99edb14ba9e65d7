"""UBX writer: GNSS epochs to u-blox NAV-PVT messages (built and checksummed by pyubx2).

Units follow the UBX protocol: position 1e-7 deg, heights/accuracies mm, velocities mm/s,
heading 1e-5 deg, PDOP 0.01. ``iTOW`` and the date/time fields come from ``utc`` (GPST =
UTC + leap seconds for ``iTOW``). An epoch without a fix is written with ``fixType = 0`` and
``gnssFixOk = 0``; an invalid course gives ``headMot = 0`` and a 180 deg ``headAcc``.
"""

from __future__ import annotations

import math
import os
from datetime import UTC, datetime

import pandas as pd
from pyubx2 import UBXMessage

from iotnav.io.timeutil import GPS_EPOCH_UNIX, SECONDS_PER_WEEK, utc_to_gpst

__all__ = ["nav_pvt", "write_nav_pvt"]


def _i(x: float, scale: float = 1.0) -> int:
    return round(x * scale) if math.isfinite(x) else 0


def _scaled(x: float, lsb: float) -> float:
    """A value pyubx2 (which truncates ``value / lsb``) will encode as ``round(x / lsb)``."""
    k = round(x / lsb)
    return (k + (0.5 if k >= 0 else -0.5)) * lsb


def nav_pvt(row: pd.Series | dict) -> bytes:
    """One NAV-PVT message (serialised bytes) of an epoch in GNSS_COLUMNS form."""
    utc = float(row["utc"])
    gpst = float(utc_to_gpst(utc))
    itow = round(((gpst - GPS_EPOCH_UNIX) % SECONDS_PER_WEEK) * 1000.0)
    whole = math.floor(round(utc, 3))
    nano = round((round(utc, 3) - whole) * 1e9)
    dt = datetime.fromtimestamp(whole, tz=UTC)
    fix = bool(row["valid"]) and math.isfinite(float(row["lat_deg"]))
    course_ok = fix and bool(row["course_valid"])
    kw = dict(
        iTOW=itow,
        year=dt.year,
        month=dt.month,
        day=dt.day,
        hour=dt.hour,
        min=dt.minute,
        second=dt.second,
        validDate=1,
        validTime=1,
        fullyResolved=1,
        tAcc=50,
        nano=nano,
        fixType=3 if fix else 0,
        gnssFixOk=1 if fix else 0,
        numSV=max(int(row["num_sv"]), 0),
        lat=_scaled(float(row["lat_deg"]), 1e-7) if fix else 0.0,
        lon=_scaled(float(row["lon_deg"]), 1e-7) if fix else 0.0,
        height=_i(float(row["height_m"]), 1000.0) if fix else 0,
        hMSL=_i(float(row["alt_msl_m"]), 1000.0) if fix else 0,
        hAcc=_i(float(row["h_acc_m"]), 1000.0) if fix else 4294967295 // 1000,
        vAcc=_i(float(row["v_acc_m"]), 1000.0) if fix else 4294967295 // 1000,
        velN=_i(float(row["vn"]), 1000.0) if fix else 0,
        velE=_i(float(row["ve"]), 1000.0) if fix else 0,
        velD=_i(float(row["vd"]), 1000.0) if fix else 0,
        gSpeed=_i(float(row["speed_mps"]), 1000.0) if fix else 0,
        headMot=_scaled(math.degrees(float(row["course_rad"])), 1e-5) if course_ok else 0.0,
        sAcc=_i(float(row["s_acc_mps"]), 1000.0) if fix else 0,
        headAcc=_scaled(1.0 if course_ok else 180.0, 1e-5),
        pDOP=_scaled(float(row["pdop"]), 0.01) if fix else _scaled(99.99, 0.01),
        invalidLlh=0 if fix else 1,
    )
    return bytes(UBXMessage("NAV", "NAV-PVT", 0, **kw).serialize())


def write_nav_pvt(path: str | os.PathLike[str], gnss: pd.DataFrame) -> int:
    """Write every epoch as a NAV-PVT message; returns the number of messages."""
    recs = gnss.to_dict("records")
    with open(path, "wb") as fh:
        for row in recs:
            fh.write(nav_pvt(row))
    return len(recs)
