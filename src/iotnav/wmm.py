"""The Earth's magnetic reference from the World Magnetic Model at a date and a place.

The engines that use a magnetometer need the reference field in the navigation frame ``n``
(NED): its declination ``D`` (East positive, the angle from true to magnetic North), its
inclination ``I`` (positive down) and its intensity. Both vary with place (tens of degrees
across a continent) and with time (0.1-0.2 deg a year in Europe), so a fixed default is
wrong almost everywhere. :func:`reference_field` evaluates the World Magnetic Model
(WMM2025 from 2025.0, WMM2020 before; NOAA NCEI and BGS, through :mod:`pygeomag`) at the
log's date and first good fix. :func:`decimal_year` converts a UTC time to the model's
decimal year.

Published check: the WMM2025 technical report's test values (NOAA NCEI / BGS, "The US/UK
World Magnetic Model for 2025-2030: Technical Report", test-values table, also distributed as
``WMM2025_TEST_VALUES.txt``) are reproduced within their rounding by ``tests/test_wmm.py``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from datetime import UTC, datetime
from functools import lru_cache
from typing import Any

import numpy as np
import numpy.typing as npt

FloatArray = npt.NDArray[np.float64]

#: Decimal year used when a log carries no date (the WMM2025 epoch); reported as such.
EPOCH_WITHOUT_DATE = 2025.0


def decimal_year(utc_s: float) -> float:
    """Decimal year (e.g. 2025.5) of a UTC time in seconds since 1970-01-01.

    The fraction is the elapsed part of that calendar year (365 or 366 days), the WMM's
    convention.
    """
    t = datetime.fromtimestamp(utc_s, tz=UTC)
    start = datetime(t.year, 1, 1, tzinfo=UTC).timestamp()
    end = datetime(t.year + 1, 1, 1, tzinfo=UTC).timestamp()
    return t.year + (utc_s - start) / (end - start)


@dataclass(frozen=True)
class MagneticReference:
    """The geomagnetic field at one place and date.

    Attributes
    ----------
    field_n_ut : numpy.ndarray
        Field in NED, microtesla.
    declination_rad, inclination_rad : float
        Declination (East positive) and inclination (down positive), rad.
    intensity_ut : float
        Total intensity, microtesla.
    year : float
        Decimal year the model was evaluated at.
    model : str
        Coefficient set (``WMM2025`` / ``WMM2020``).
    lat_deg, lon_deg, height_m : float
        Where (degrees, ellipsoidal m).
    """

    field_n_ut: FloatArray
    declination_rad: float
    inclination_rad: float
    intensity_ut: float
    year: float
    model: str
    lat_deg: float
    lon_deg: float
    height_m: float

    def to_dict(self) -> dict[str, Any]:
        """For ``summary.json`` (degrees for the angles, as a reader checks them)."""
        return {
            "model": self.model,
            "year": self.year,
            "lat_deg": self.lat_deg,
            "lon_deg": self.lon_deg,
            "height_m": self.height_m,
            "declination_deg": math.degrees(self.declination_rad),
            "inclination_deg": math.degrees(self.inclination_rad),
            "intensity_ut": self.intensity_ut,
            "field_n_ut": [float(v) for v in self.field_n_ut],
        }


@lru_cache(maxsize=2)
def _model(cof: str) -> Any:
    from pygeomag import GeoMag

    return GeoMag(coefficients_file=cof)


def reference_field(lat_deg: float, lon_deg: float, height_m: float, year: float) -> MagneticReference:
    """World Magnetic Model field at a point and decimal year.

    Parameters
    ----------
    lat_deg, lon_deg : float
        Geodetic latitude and longitude, degrees.
    height_m : float
        Ellipsoidal height, m (a NaN height is taken as 0; 100 m changes the field by ~0.02 %).
    year : float
        Decimal year (:func:`decimal_year`); WMM2020 before 2025.0, WMM2025 from it (each
        extrapolated outside its five-year span rather than refused).

    Returns
    -------
    MagneticReference
    """
    h = height_m if math.isfinite(height_m) else 0.0
    name, cof = ("WMM2020", "wmm/WMM_2020.COF") if year < 2025.0 else ("WMM2025", "wmm/WMM_2025.COF")
    res = _model(cof).calculate(
        glat=lat_deg, glon=lon_deg, alt=h / 1000.0, time=year, allow_date_outside_lifespan=True
    )
    return MagneticReference(
        field_n_ut=np.array([res.x, res.y, res.z]) / 1000.0,
        declination_rad=math.radians(res.d),
        inclination_rad=math.radians(res.i),
        intensity_ut=float(res.f) / 1000.0,
        year=float(year),
        model=name,
        lat_deg=float(lat_deg),
        lon_deg=float(lon_deg),
        height_m=float(h),
    )


def log_year(t_s: float, utc_offset_s: float, configured: float | None) -> tuple[float, str]:
    """The decimal year to evaluate the model at, and where it came from.

    Parameters
    ----------
    t_s : float
        Device time of the first good fix, s.
    utc_offset_s : float
        ``utc = t + utc_offset_s`` of the log (NaN when no fix carries a date).
    configured : float or None
        An explicit year from the configuration (wins when given).

    Returns
    -------
    tuple of (float, str)
        The year and ``"config"``, ``"log"`` or ``"no date: model epoch"``.
    """
    if configured is not None:
        return float(configured), "config"
    utc = t_s + utc_offset_s
    if math.isfinite(utc):
        return decimal_year(utc), "log"
    return EPOCH_WITHOUT_DATE, "no date: model epoch"
