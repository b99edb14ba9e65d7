"""Time scales: GPS time versus UTC (leap seconds), device-time units.

GPS time (GPST) runs ahead of UTC by the number of leap seconds inserted since 1980-01-06;
18 s since 2017-01-01. The table below lists when each offset took effect (UTC); iotnav
converts GPST to UTC once, at the reader, with :func:`gpst_to_utc`.
"""

from __future__ import annotations

import calendar

import numpy as np
import numpy.typing as npt

#: (UTC Unix time at which the offset starts, GPST - UTC in seconds), IERS Bulletin C.
_LEAPS: list[tuple[str, int]] = [
    ("1981-07-01", 1),
    ("1982-07-01", 2),
    ("1983-07-01", 3),
    ("1985-07-01", 4),
    ("1988-01-01", 5),
    ("1990-01-01", 6),
    ("1991-01-01", 7),
    ("1992-07-01", 8),
    ("1993-07-01", 9),
    ("1994-07-01", 10),
    ("1996-01-01", 11),
    ("1997-07-01", 12),
    ("1999-01-01", 13),
    ("2006-01-01", 14),
    ("2009-01-01", 15),
    ("2012-07-01", 16),
    ("2015-07-01", 17),
    ("2017-01-01", 18),
]
_LEAP_T = np.array(
    [calendar.timegm((*tuple(int(x) for x in d.split("-")), 0, 0, 0)) for d, _ in _LEAPS],  # type: ignore[arg-type]
    dtype=float,
)
_LEAP_S = np.array([s for _, s in _LEAPS], dtype=float)

GPS_EPOCH_UNIX = 315964800.0  # 1980-01-06T00:00:00 UTC as Unix seconds
SECONDS_PER_WEEK = 604800.0


def leap_seconds_at_utc(utc: npt.ArrayLike) -> npt.NDArray[np.float64]:
    """GPST - UTC in seconds at the given UTC Unix times.

    Parameters
    ----------
    utc : array_like
        UTC, seconds since 1970-01-01.

    Returns
    -------
    numpy.ndarray
        Leap seconds (0 before 1981-07-01).
    """
    u = np.asarray(utc, dtype=float)
    idx = np.searchsorted(_LEAP_T, u, side="right")
    return np.where(idx > 0, _LEAP_S[np.maximum(idx - 1, 0)], 0.0)


def gpst_to_utc(gpst_unix: npt.ArrayLike) -> npt.NDArray[np.float64]:
    """Convert GPS time written as Unix-style seconds to UTC Unix seconds.

    ``gpst_unix`` is GPST expressed as if it were a Unix timestamp (the RTKLIB convention:
    calendar date and time of the GPST scale through ``timegm``).

    Parameters
    ----------
    gpst_unix : array_like
        GPST, seconds since 1970-01-01 on the GPS scale.

    Returns
    -------
    numpy.ndarray
        UTC, seconds since 1970-01-01.
    """
    g = np.asarray(gpst_unix, dtype=float)
    # The offset at (g - 18) is correct except within 18 s of a leap; re-evaluate once.
    first = g - leap_seconds_at_utc(g)
    return g - leap_seconds_at_utc(first)


def utc_to_gpst(utc: npt.ArrayLike) -> npt.NDArray[np.float64]:
    """Convert UTC Unix seconds to GPST written as Unix-style seconds."""
    u = np.asarray(utc, dtype=float)
    return u + leap_seconds_at_utc(u)


def gps_week_tow_to_utc(week: npt.ArrayLike, tow_s: npt.ArrayLike) -> npt.NDArray[np.float64]:
    """Convert GPS week and time of week (s) to UTC Unix seconds."""
    g = GPS_EPOCH_UNIX + np.asarray(week, dtype=float) * SECONDS_PER_WEEK + np.asarray(tow_s, float)
    return gpst_to_utc(g)


_UNIT_SCALE = {"s": 1.0, "ms": 1e-3, "us": 1e-6, "ns": 1e-9}


def unit_scale(unit: str) -> float:
    """Seconds per tick of a device-time unit (``s``, ``ms``, ``us``, ``ns``).

    Raises
    ------
    ValueError
        For an unknown unit.
    """
    try:
        return _UNIT_SCALE[unit]
    except KeyError:
        raise ValueError(f"unknown time unit {unit!r}; expected one of s, ms, us, ns") from None


def guess_time_unit(t: npt.ArrayLike, rate_hint_hz: tuple[float, float] = (0.05, 2000.0)) -> str:
    """Guess the unit of a column of device timestamps from its median step.

    The unit chosen is the one for which the median positive step gives a sample rate inside
    ``rate_hint_hz`` and closest to its geometric centre; for absolute Unix times the magnitude
    decides (about 1.7e9 s, 1.7e12 ms, 1.7e15 us, 1.7e18 ns).

    Parameters
    ----------
    t : array_like
        Raw timestamps, increasing.
    rate_hint_hz : tuple of float
        Plausible sample-rate range.

    Returns
    -------
    str
        ``s``, ``ms``, ``us`` or ``ns``.
    """
    a = np.asarray(t, dtype=float)
    a = a[np.isfinite(a)]
    if a.size == 0:
        return "s"
    med = float(np.median(np.abs(a)))
    # Absolute Unix epoch times (2001..2100)
    for unit, scale in (("s", 1.0), ("ms", 1e-3), ("us", 1e-6), ("ns", 1e-9)):
        if 1.0e9 <= med * scale <= 4.2e9:
            return unit
    d = np.diff(a)
    d = d[d > 0]
    if d.size == 0:
        return "s"
    step = float(np.median(d))
    lo, hi = rate_hint_hz
    centre = np.sqrt(lo * hi)
    best, best_score = "s", np.inf
    for unit, scale in _UNIT_SCALE.items():
        rate = 1.0 / (step * scale)
        if lo <= rate <= hi:
            score = abs(np.log(rate / centre))
            if score < best_score:
                best, best_score = unit, score
    return best
