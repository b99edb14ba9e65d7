"""The World Magnetic Model reference (:mod:`iotnav.wmm`) and its use by eskf and qekf.

Test vectors: NOAA NCEI / BGS, "The US/UK World Magnetic Model for 2025-2030: Technical
Report" (December 2024), table of test values (also ``WMM2025_TEST_VALUES.txt`` on
ncei.noaa.gov): decimal year, height above the WGS84 ellipsoid (km), geodetic latitude and
longitude (deg), X, Y, Z (nT), inclination and declination (deg). The table rounds to 0.1 nT
and 0.01 deg.
"""

from __future__ import annotations

import dataclasses
import math
from datetime import UTC, datetime

import numpy as np
import pytest

from iotnav.engines.base import GnssSample, MagSample, run_batch
from iotnav.engines.eskf import EskfConfig, EskfEngine
from iotnav.engines.qekf import QekfConfig, QekfEngine
from iotnav.io.log import Log
from iotnav.wmm import decimal_year, log_year, reference_field

# year, h_km, lat, lon, X, Y, Z (nT), I, D (deg)
WMM2025_TEST_VALUES = [
    (2025.0, 0.0, 80.0, 0.0, 6521.6, 145.9, 54791.5, 83.21, 1.28),
    (2025.0, 0.0, 0.0, 120.0, 39677.8, -109.6, -10580.2, -14.93, -0.16),
    (2025.0, 0.0, -80.0, 240.0, 6117.5, 15751.9, -52022.5, -72.00, 68.78),
    (2025.0, 100.0, 80.0, 0.0, 6216.0, 92.4, 52598.8, 83.26, 0.85),
    (2025.0, 100.0, 0.0, 120.0, 37688.6, -96.2, -10152.1, -15.08, -0.15),
    (2025.0, 100.0, -80.0, 240.0, 5907.6, 14780.3, -49540.7, -72.19, 68.21),
    (2027.5, 0.0, 80.0, 0.0, 6500.8, 294.5, 54869.4, 83.24, 2.59),
    (2027.5, 0.0, 0.0, 120.0, 39701.6, -167.4, -10381.8, -14.65, -0.24),
    (2027.5, 0.0, -80.0, 240.0, 6200.7, 15730.3, -51783.7, -71.92, 68.49),
    (2027.5, 100.0, 80.0, 0.0, 6196.7, 233.8, 52670.5, 83.29, 2.16),
    (2027.5, 100.0, 0.0, 120.0, 37711.5, -148.7, -9969.8, -14.81, -0.23),
    (2027.5, 100.0, -80.0, 240.0, 5984.0, 14760.1, -49317.7, -72.10, 67.93),
]


@pytest.mark.parametrize("row", WMM2025_TEST_VALUES)
def test_reference_field_matches_the_wmm2025_report(row: tuple[float, ...]) -> None:
    year, h_km, lat, lon, x, y, z, inc, dec = row
    ref = reference_field(lat, lon, h_km * 1000.0, year)
    assert ref.model == "WMM2025"
    np.testing.assert_allclose(ref.field_n_ut * 1000.0, [x, y, z], atol=0.06)  # table: 0.1 nT
    assert math.degrees(ref.inclination_rad) == pytest.approx(inc, abs=0.006)
    assert math.degrees(ref.declination_rad) == pytest.approx(dec, abs=0.006)
    assert ref.intensity_ut == pytest.approx(math.sqrt(x * x + y * y + z * z) / 1000.0, abs=1e-4)


def test_decimal_year() -> None:
    assert decimal_year(datetime(2025, 1, 1, tzinfo=UTC).timestamp()) == 2025.0
    # 2024 is a leap year: 1 July 00:00 is day 182 of 366
    assert decimal_year(datetime(2024, 7, 1, tzinfo=UTC).timestamp()) == pytest.approx(2024 + 182 / 366)


def test_log_year_sources() -> None:
    utc = datetime(2027, 7, 2, 12, tzinfo=UTC).timestamp()
    assert log_year(10.0, utc - 10.0, None) == (pytest.approx(2027.5), "log")
    assert log_year(10.0, utc - 10.0, 2026.0) == (2026.0, "config")  # the configuration wins
    assert log_year(10.0, math.nan, None)[1] == "no date: model epoch"


def _log_at(lat: float, lon: float, utc_s: float) -> Log:
    """A log with one fix (device time 1 s) at ``lat``/``lon``, dated ``utc_s``."""
    import pandas as pd

    from iotnav.io.schema import GNSS_COLUMNS, coerce

    g = coerce(
        pd.DataFrame(
            {
                "t": [1.0],
                "utc": [utc_s],
                "lat_deg": [lat],
                "lon_deg": [lon],
                "height_m": [0.0],
                "valid": [True],
            }
        ),
        GNSS_COLUMNS,
    )
    return Log(gnss=g, utc_offset_s=utc_s - 1.0)


def test_eskf_declination_from_the_log_date_and_first_fix() -> None:
    """Default: the WMM declination at the first fix and date; a configured value wins."""
    utc = datetime(2027, 7, 2, 12, tzinfo=UTC).timestamp()  # 2027.5, a report epoch
    eng = EskfEngine(EskfConfig())
    run_batch(eng, _log_at(-80.0, 240.0, utc))
    ref = eng.summary()["mag_reference"]
    assert ref["year_from"] == "log" and ref["year"] == pytest.approx(2027.5, abs=1e-9)
    assert ref["declination_deg"] == pytest.approx(68.49, abs=0.006)  # report, 2027.5, 0 km
    assert eng.mag_declination_rad == pytest.approx(math.radians(68.49), abs=1e-4)
    fixed = EskfEngine(EskfConfig(mag_declination_rad=0.1))
    run_batch(fixed, _log_at(-80.0, 240.0, utc))
    assert fixed.mag_declination_rad == 0.1
    assert fixed.summary()["mag_reference"] == {
        "declination_deg": pytest.approx(math.degrees(0.1)),
        "from": "config",
    }


def test_eskf_skips_and_counts_magnetometer_before_the_declination_is_known() -> None:
    eng = EskfEngine(EskfConfig(mag_calibrated=True))
    eng.levelled = True  # as after levelling; no fix yet
    eng.step(MagSample(0.5, np.array([20.0, 0.0, 40.0])))
    assert eng.summary()["skipped"] == {"mag_before_declination": 1}
    eng.step(GnssSample(1.0, 80.0, 0.0, 0.0))
    assert eng.mag_declination_rad == pytest.approx(math.radians(1.28), abs=0.01)  # no date: 2025.0


def test_qekf_field_from_the_log_date() -> None:
    """qekf's reference field is the WMM's at its origin and the log's date (config year wins)."""
    from iotnav.engines.base import ImuSample

    utc = datetime(2027, 7, 2, 12, tzinfo=UTC).timestamp()
    for cfg, year in ((QekfConfig(), 2027.5), (QekfConfig(wmm_year=2025.0), 2025.0)):
        eng = QekfEngine(dataclasses.replace(cfg, init_duration_s=1.0))
        eng.utc_offset_s = utc - 1.0
        eng.step(GnssSample(1.0, 0.0, 120.0, 0.0))
        for k in range(150):
            eng.step(ImuSample(1.0 + 0.01 * k, np.array([0.0, 0.0, -9.81]), np.zeros(3)))
        ref = eng.summary()["mag_reference"]
        assert ref["year"] == pytest.approx(year, abs=1e-6), ref  # 1e-6 yr: 32 s
        want = {2027.5: (39701.6, -167.4, -10381.8), 2025.0: (39677.8, -109.6, -10580.2)}[year]
        np.testing.assert_allclose(np.array(ref["field_n_ut"]) * 1000.0, want, atol=0.06)
