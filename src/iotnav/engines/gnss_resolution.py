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
from collections.abc import Sequence

import numpy as np
import numpy.typing as npt

#: Per-axis values (north, east, down): a sequence or an array.
Axes = Sequence[float] | npt.NDArray[np.float64]

__all__ = [
    "ALTITUDE_TOL",
    "FIGURE_TOL",
    "FINE_MINUTE_DECIMALS",
    "MAX_ALTITUDE_DECIMALS",
    "MAX_FIGURE_DECIMALS",
    "MAX_MINUTE_DECIMALS",
    "MINUTE_TOL",
    "MIN_DISTINCT",
    "AccuracyScaling",
    "FigureDecimals",
    "PositionResolution",
    "accuracy_relative_steps",
    "decimal_places",
    "relative_step",
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


# ----------------------------------------------------------------------------- reported accuracy

#: Decimals tested for a reported accuracy figure (DOP, hAcc, vAcc); a figure with more reads
#: as continuous (UBX's hAcc in mm reads as 3 decimals: 0.1 % of a metre).
MAX_FIGURE_DECIMALS = 3
#: A figure is on a decimal grid when within this of a grid point (figures are read from text).
FIGURE_TOL = 1e-7


def relative_step(value: float, decimals: int | None = None) -> float:
    """Rounding step of a reported figure divided by the figure (0: continuous, or not a positive
    finite number). ``1.1`` -> 0.09, ``1.07`` -> 0.0093, ``1.0734`` -> 0. ``decimals``: the
    stream's (:class:`FigureDecimals`) instead of this value's own."""
    if not (math.isfinite(value) and value > 0.0):
        return 0.0
    d = decimals if decimals is not None else decimal_places(value, MAX_FIGURE_DECIMALS, FIGURE_TOL)
    return 0.0 if d is None or d > MAX_FIGURE_DECIMALS else 10.0 ** (-d) / value


class FigureDecimals:
    """Decimals of a stream of reported accuracy figures (hAcc, vAcc, HDOP, PDOP), per figure.

    As :class:`PositionResolution`: the most decimals any value needed (a DOP of ``1.0`` read
    alone has none, its neighbours ``1.07`` have 2); a value on no grid up to
    :data:`MAX_FIGURE_DECIMALS` makes the figure continuous for good.
    """

    def __init__(self) -> None:
        self.decimals: dict[str, int] = {}

    def update(self, name: str, value: float) -> int | None:
        """Record ``value`` of figure ``name``; the stream's decimals so far (None: continuous)."""
        if not (math.isfinite(value) and value > 0.0):
            return self.decimals.get(name)
        d = decimal_places(value, MAX_FIGURE_DECIMALS, FIGURE_TOL)
        d = MAX_FIGURE_DECIMALS + 1 if d is None else d
        self.decimals[name] = max(self.decimals.get(name, 0), d)
        return self.decimals[name]

    def relative_steps(
        self, h_acc: float, v_acc: float, hdop: float, pdop: float, source: tuple[str, str]
    ) -> tuple[float, float, float]:
        """Relative rounding of a fix's position sigma per NED axis, from the figures it comes
        from, with the stream's decimals (:func:`accuracy_relative_steps`; call it at every fix,
        so that the decimals are learnt)."""
        d = {
            n: self.update(n, v)
            for n, v in (("h_acc", h_acc), ("v_acc", v_acc), ("hdop", hdop), ("pdop", pdop))
        }
        return accuracy_relative_steps(h_acc, v_acc, hdop, pdop, source, d)


def accuracy_relative_steps(
    h_acc: float,
    v_acc: float,
    hdop: float,
    pdop: float,
    source: tuple[str, str],
    decimals: dict[str, int | None] | None = None,
) -> tuple[float, float, float]:
    """Relative rounding of a fix's position sigma per NED axis, from the figures it comes from.

    ``source`` names them (horizontal, vertical: ``h_acc``, ``v_acc``, ``hdop``, ``pdop``,
    anything else for none), as :func:`iotnav.gnss_accuracy.position_sigmas` reports them for
    every engine. A vertical
    ``pdop`` is
    ``VDOP = sqrt(PDOP^2 - HDOP^2)``, whose relative error from steps ``a`` (PDOP ``p``) and
    ``b`` (HDOP ``h``) is ``(p a + h b) / (p^2 - h^2)`` (PDOP's own with no HDOP).
    ``decimals``: per figure name the stream's, else each value's own.
    """
    dec = decimals or {}
    values = {"h_acc": h_acc, "v_acc": v_acc, "hdop": hdop, "pdop": pdop}
    sh, sv = source

    def rel(name: str) -> float:
        return relative_step(values[name], dec.get(name)) if name in values else 0.0

    rh = rel(sh)
    if sv == "pdop" and math.isfinite(hdop) and 0.0 < hdop < pdop:
        a, b = rel("pdop") * pdop, rel("hdop") * hdop
        rv = (pdop * a + hdop * b) / (pdop * pdop - hdop * hdop)
    else:
        rv = rel(sv)
    return rh, rh, rv


class AccuracyScaling:
    """How the correlated-error states of a filter follow the receiver's reported accuracy.

    ``eskf`` and ``qekf`` (option ``gnss_error_states``) model the receiver's error as
    ``e = sigma(t) y`` (a re-acquiring receiver reports a larger accuracy and is that much
    further off), so a change of the reported sigma by ``k`` scales their error states by
    ``k``, exactly: with the fixes' precise ``r + e`` any mismatch between the scaling and the
    error's real change shows in the next innovation at once. Continuous figures (simulated
    values, more than 3 decimals) are followed fix by fix; hAcc in mm has a 0.1 % step. Rounded figures are not: a DOP written with 2
    decimals moves in steps of about 1 % that the true sigma crossed gradually, and a step
    applied at one fix as an exact scaling made it information about ``e``: the filters' NEES
    rose from 10.9 to 14.5 (``eskf``, 8 car-tunnel runs, DOPs with 2 decimals) and to 34 (1
    decimal, as many NMEA receivers write HDOP); ``qekf``'s from 5.5 to 8.0 (20 runs).

    So the sigma the states are scaled to (the *level*, per axis, in log) follows the reported
    one at once only on a jump beyond the figures' rounding, ``|ln(sigma / level)| >
    ln(1 + 4 s)`` with ``s`` the relative rounding step (:func:`accuracy_relative_steps`; 0 for
    continuous figures, so every change is followed); smaller differences are followed by a
    first-order low-pass of time constant ``tau_s``, scaling by a small ratio at each fix.
    With 2-decimal DOPs the 8 runs' NEES is then 11.0 and with 1 decimal 12.1 (continuous
    10.9). The time constant trades that against following a re-acquiring receiver whose
    sigma decays through the rounding band: on the 600 s car-tunnel run (NMEA, ``eskf``)
    smoothed RMS 0.86 m when every step was followed at once, 1.00 m with 5 s, 1.13 m with
    30 s (where 1-decimal DOPs gave 11.5).

    A different kind of figures (hAcc against DOPs) makes no ratio: the fix's sigma becomes
    the level.

    Parameters
    ----------
    tau_s : float
        Time constant of the low-pass over the rounding steps, s (default 5).
    """

    def __init__(self, tau_s: float = 5.0) -> None:
        if not tau_s > 0.0:
            raise ValueError(f"the accuracy low-pass time constant must be > 0 s, got {tau_s}")
        self.tau_s = tau_s
        #: per-axis sigma the states are scaled to, m (NaN: none yet)
        self.level = [math.nan, math.nan, math.nan]
        self.kind: object = None
        self.t = math.nan
        #: decimals of the figures seen (``relative_steps`` for :meth:`ratio`)
        self.figures = FigureDecimals()

    def reset(
        self, sigma: Axes, kind: object = None, axes: Sequence[int] = (0, 1, 2), t: float = math.nan
    ) -> None:
        """The states were (re)initialised with ``sigma`` (m) on ``axes`` (at ``t``, s): it is
        the level."""
        for i in axes:
            self.level[i] = float(sigma[i])
        if kind is not None:
            self.kind = kind
        if math.isfinite(t):
            self.t = t

    def ratio(
        self, t: float, sigma: Axes, kind: object, rel_steps: Axes
    ) -> tuple[float, float, float] | None:
        """Scale factors ``k`` per axis at a fix at ``t`` (s) reporting ``sigma`` (m), or None
        when nothing changes; the level moves by ``k``."""
        if not math.isfinite(t):
            return None
        dt = t - self.t if math.isfinite(self.t) else 0.0
        if dt < 0.0:  # time went backwards: no low-pass step, the clock is not moved back
            dt = 0.0
        else:
            self.t = t
        if kind != self.kind:
            self.reset(sigma, kind)
            return None
        a = -math.expm1(-dt / self.tau_s)  # exact first-order low-pass over dt
        k = [1.0, 1.0, 1.0]
        change = False
        for i in range(3):
            lev, s = self.level[i], float(sigma[i])
            if not (s > 0.0 and math.isfinite(s)):
                continue
            if not (lev > 0.0 and math.isfinite(lev)):
                self.level[i] = s
                continue
            d = math.log(s / lev)
            if abs(d) <= math.log1p(4.0 * float(rel_steps[i])):
                d *= a  # within the rounding: low-passed
            if d != 0.0:
                k[i] = math.exp(d)
                self.level[i] = lev * k[i]
                change = True
        return (k[0], k[1], k[2]) if change else None
