"""GPS time versus UTC and device-time units (layer a)."""

from __future__ import annotations

import calendar

import numpy as np
import pytest

from iotnav.io import timeutil


def test_gpst_utc_offsets_by_date() -> None:
    t2025 = calendar.timegm((2025, 7, 8, 19, 34, 18))
    assert timeutil.gpst_to_utc(t2025) == pytest.approx(t2025 - 18)
    t2010 = calendar.timegm((2010, 1, 1, 0, 0, 0))
    assert timeutil.utc_to_gpst(t2010) == pytest.approx(t2010 + 15)
    assert timeutil.leap_seconds_at_utc(calendar.timegm((1980, 1, 6, 0, 0, 0))) == 0


def test_leap_second_boundary_2017() -> None:
    before = calendar.timegm((2016, 12, 31, 23, 59, 59))
    after = calendar.timegm((2017, 1, 1, 0, 0, 0))
    assert timeutil.leap_seconds_at_utc(before) == 17
    assert timeutil.leap_seconds_at_utc(after) == 18
    for u in (before - 30, before, after, after + 30):
        assert timeutil.gpst_to_utc(timeutil.utc_to_gpst(u)) == pytest.approx(u)


def test_week_tow() -> None:
    # Hand computed: GPS week 2374 starts on Sunday 2025-07-06 (16618 days after 1980-01-06);
    # TOW 243276 s = 2 d 19 h 34 min 36 s, i.e. 2025-07-08 19:34:36 GPST = 19:34:18 UTC.
    utc = timeutil.gps_week_tow_to_utc(2374, 243276.0)
    assert utc == pytest.approx(calendar.timegm((2025, 7, 8, 19, 34, 36)) - 18)


@pytest.mark.parametrize(
    ("step", "n0", "expected"),
    [(1.0, 0.0, "s"), (0.01, 5.0, "s"), (10.0, 261906.0, "ms"), (250.0, 0.0, "ms"), (1000.0, 12345.0, "ms")],
)
def test_guess_unit_from_rate(step: float, n0: float, expected: str) -> None:
    t = n0 + step * np.arange(100)
    assert timeutil.guess_time_unit(t) == expected


@pytest.mark.parametrize(("scale", "expected"), [(1.0, "s"), (1e3, "ms"), (1e6, "us"), (1e9, "ns")])
def test_guess_unit_of_unix_epoch(scale: float, expected: str) -> None:
    t = (1.75e9 + 0.01 * np.arange(50)) * scale
    assert timeutil.guess_time_unit(t) == expected


def test_unit_scale_rejects_unknown() -> None:
    with pytest.raises(ValueError, match="unknown time unit"):
        timeutil.unit_scale("fortnights")
