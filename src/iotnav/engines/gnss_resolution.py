"""Output resolution of a GNSS position stream, found from the fixes themselves.

A receiver's position reaches the filter rounded to the resolution of its output format:
NMEA writes latitude and longitude as degrees and decimal minutes (``ddmm.mmmm``) with 3 to 7
decimals depending on the receiver and its settings (3: 1.85 m of latitude; 4: 0.185 m; 5,
u-blox's default: 1.85 cm), and the altitude in metres with usually one decimal; UBX NAV-PVT
and RTKLIB solutions carry 1e-7 degree or better. The rounding is a white error, uniform over
one step ``q`` (standard deviation ``q / sqrt(12)``), independent from fix to fix, unlike the
receiver's own error, which is correlated over minutes. A filter that carries the correlated
part as states (``eskf``) needs exactly this white part in ``R``: a larger one lowers the gain
below the optimum and correlates the innovations from fix to fix, a smaller one trusts the
fix-to-fix changes more than the data allows.

:class:`PositionResolution` finds the number of decimals from the values: the minutes of
every coordinate are tested against the decimal grids of 0 to :data:`MAX_MINUTE_DECIMALS`
decimals; a coordinate on none of them (simulated values, finer NMEA, RTKLIB's 1e-9 degree)
makes the stream continuous (resolution 0); UBX's 1e-7 degree reads as 6 decimals (0.5 mm). The
finest grid any fix needed is the stream's: a fix whose minutes happen to end in a zero reads
as one decimal fewer, the next ones correct it.
"""

from __future__ import annotations

import math

__all__ = [
    "ALTITUDE_TOL",
    "FINE_MINUTE_DECIMALS",
    "MAX_ALTITUDE_DECIMALS",
    "MAX_MINUTE_DECIMALS",
    "MINUTE_TOL",
    "MIN_DISTINCT",
    "PositionResolution",
    "decimal_places",
]

#: Finest NMEA minute resolution tested (6 decimals: 1.9 mm of latitude; finer ones, such as
#: u-blox's 7-decimal high-precision mode, read as continuous, which they are for the filter).
MAX_MINUTE_DECIMALS = 6
#: Finest altitude resolution tested (4 decimals: 0.1 mm).
MAX_ALTITUDE_DECIMALS = 4
#: Minute grids with fewer decimals than this (2: 18.5 m steps and coarser) need confirmation.
FINE_MINUTE_DECIMALS = 3
#: Different values that confirm a coarse grid.
MIN_DISTINCT = 3
#: Metres per minute of latitude (one nautical mile; the ellipsoid changes it by < 0.6 %).
_M_PER_MINUTE = 1852.0
#: A minute value is on a grid when it is within this of a grid point, minutes: the NMEA
#: reader (pynmeagps) keeps 10 decimals of a degree, 6e-9 minute at most (0.006 of a step at
#: 6 decimals).
MINUTE_TOL = 1e-8
#: The same for a height, m (read from its text, exact to the float's precision).
ALTITUDE_TOL = 1e-7


def decimal_places(value: float, max_decimals: int, tol: float) -> int | None:
    """Fewest decimals that write ``value``, or None above ``max_decimals``.

    Parameters
    ----------
    value : float
        Value as read (e.g. minutes of arc, or metres).
    max_decimals : int
        Largest number of decimals tested.
    tol : float
        Largest distance from a grid point still counted on the grid, in the value's unit.

    Returns
    -------
    int or None
        Number of decimals; None when the value is on none of the grids (or not finite).
    """
    if not math.isfinite(value):
        return None
    a = abs(value)
    for d in range(max_decimals + 1):
        scale = 10.0**d
        x = a * scale
        if abs(x - round(x)) <= tol * scale:
            return d
    return None


class PositionResolution:
    """Running estimate of the output resolution of a GNSS position stream.

    A coarse grid (fewer than :data:`FINE_MINUTE_DECIMALS` decimals of a minute, or whole metres
    of height) is trusted only once :data:`MIN_DISTINCT` different values have shown it: a fix
    repeated at one place, or a hand-made one on whole minutes, would otherwise read as a grid
    of hundreds of metres and make the filter ignore the GNSS.

    Attributes
    ----------
    continuous : bool
        A coordinate was on none of the grids: a binary or computed position.
    n_fixes : int
        Fixes seen.
    """

    def __init__(self) -> None:
        self._minute: int | None = None
        self._altitude: int | None = None
        self.continuous = False
        self._alt_continuous = False
        self.n_fixes = 0
        self._last_pos = (math.nan, math.nan)
        self._last_alt = math.nan
        self._n_pos = 0  # distinct horizontal positions seen
        self._n_alt = 0  # distinct heights seen

    @property
    def minute_decimals(self) -> int | None:
        """Decimals of the minutes of latitude and longitude; None while unknown or untrusted,
        or when the stream is continuous."""
        d = self._minute
        if d is None or self.continuous or (d < FINE_MINUTE_DECIMALS and self._n_pos < MIN_DISTINCT):
            return None
        return d

    @property
    def altitude_decimals(self) -> int | None:
        """Decimals of the height in metres, likewise (whole metres need confirmation)."""
        d = self._altitude
        if d is None or self._alt_continuous or (d < 1 and self._n_alt < MIN_DISTINCT):
            return None
        return d

    def update(self, lat_deg: float, lon_deg: float, height_m: float = math.nan) -> None:
        """Take one fix's coordinates (degrees, metres; a NaN height is ignored, and a fix
        without a finite latitude and longitude is not taken)."""
        if not (math.isfinite(lat_deg) and math.isfinite(lon_deg)):
            return
        self.n_fixes += 1
        if (lat_deg, lon_deg) != self._last_pos:
            self._n_pos += 1
            self._last_pos = (lat_deg, lon_deg)
        if not self.continuous:
            for deg in (lat_deg, lon_deg):
                d = decimal_places(deg * 60.0, MAX_MINUTE_DECIMALS, MINUTE_TOL)
                if d is None:
                    self.continuous = True
                    break
                self._minute = d if self._minute is None else max(d, self._minute)
        if not math.isfinite(height_m):
            return
        if height_m != self._last_alt:
            self._n_alt += 1
            self._last_alt = height_m
        if not self._alt_continuous:
            d = decimal_places(height_m, MAX_ALTITUDE_DECIMALS, ALTITUDE_TOL)
            if d is None:
                self._alt_continuous = True
            else:
                self._altitude = d if self._altitude is None else max(d, self._altitude)

    def sigma_ned_m(self, lat_deg: float) -> tuple[float, float, float]:
        """Standard deviation of the rounding per NED axis, m (0 where continuous or unknown).

        Parameters
        ----------
        lat_deg : float
            Latitude, degrees (a minute of longitude is ``cos(lat)`` of a minute of latitude).

        Returns
        -------
        tuple of float
            ``q / sqrt(12)`` north, east and down, m.
        """
        s12 = math.sqrt(12.0)
        n = e = d = 0.0
        if self.minute_decimals is not None:
            q = _M_PER_MINUTE * 10.0 ** (-self.minute_decimals)
            n = q / s12
            e = q * math.cos(math.radians(lat_deg)) / s12
        if self.altitude_decimals is not None:
            d = 10.0 ** (-self.altitude_decimals) / s12
        return n, e, d

    def to_dict(self) -> dict[str, object]:
        """What was found, for a run summary."""
        return {
            "fixes": self.n_fixes,
            "minute_decimals": self.minute_decimals,
            "altitude_decimals": self.altitude_decimals,
            "continuous": self.continuous,
        }
