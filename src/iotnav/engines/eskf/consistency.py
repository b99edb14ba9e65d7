"""Windowed NIS consistency monitor of the ``eskf`` engine (issue 16, "do no harm").

The gate tests each fix on its own and, after ``max_gnss_rejections`` rejections in a row,
re-opens the position covariance (``gate_reset``). That handles a transient disagreement (the
first fixes after an outage, a multipath jump), not a persistent one: with a wrong mount or
heading the filter drifts off again after every gate reset and rejects most fixes for as long
as the log lasts. The monitor tests the filter's consistency over a window instead.

Test
----
Under the filter's model the normalised innovation squared of a fix, ``NIS = y^T S^-1 y``, is
chi-square distributed with ``m`` degrees of freedom (``m`` = 2 or 3 position components), and
the innovations of successive fixes are independent (Bar-Shalom, Li and Kirubarajan 2001,
"Estimation with Applications to Tracking and Navigation", §5.4.2, the time-average NIS test).
The sum over the last ``N`` fixes is then chi-square with ``sum m`` degrees of freedom, and the
filter and GNSS disagree beyond chance when it exceeds that distribution's upper quantile at the
stated false-alarm probability ``p``.

Each fix's NIS enters the sum capped at its own ``cap_probability`` quantile. A capped sum is
never larger than the uncapped one, so the false-alarm probability stays at most ``p``; what the
cap buys is that a few fixes far off (the first ones after an outage before the gate re-opens, a
jump) cannot trigger the test alone: it fires on a *fraction* of the window far off. The engine
feeds the NIS divided by its ``nis_tolerance`` (3): with the defaults (``N = 30`` 3-dof fixes,
``p = 1e-6``, the cap at 0.99, 11.3 per fix) the threshold is 168.7; consistent fixes add about
1 each, so five rejections in a row among them sum to about ``5 x 11.3 + 25 = 82``, and it takes
about 14 fixes at the cap (``(168.7 - 30) / (11.3 - 1)``) to fire. The test runs at every fix
once the window holds ``min_fixes``; after a re-initialisation the window starts empty.

A large NIS says the filter and GNSS disagree *relative to the filter's claim*: a filter whose
state is right but whose covariance is too small (a GNSS error model that does not fit the
receiver: a filter metres from the fixes that claims decimetres) fails the test as surely as one
whose state is wrong, and re-initialising it only throws away its calibration. So the alarm also
needs the state to be off: the mean horizontal distance between the predicted position and the
fixes over the window above ``max(min_distance_m, distance_sigmas x`` the RMS of the fixes'
reported horizontal 1-sigma ``)`` (the integrity guard's rule, :mod:`iotnav.engines.integrity`,
whose 10 m floor is the same figure).
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass

# chdtri(dof, q) is scipy.stats.chi2.isf(q, dof) (the same values), without scipy.stats' 0.6 s import
from scipy.special import chdtri


@dataclass(frozen=True)
class NisAlarm:
    """The window's statistic when it exceeded its threshold.

    Attributes
    ----------
    statistic : float
        Sum of the window's capped NIS values.
    threshold : float
        Upper quantile of chi-square with ``dof`` degrees of freedom at the false-alarm
        probability.
    dof : int
        Degrees of freedom summed over the window.
    fixes : int
        Fixes in the window.
    span_s : float
        Time from the window's first fix to its last, s.
    mean_distance_m : float
        Mean horizontal distance between the predicted position and the fixes, m.
    distance_bound_m : float
        The distance above which the state is taken as off, m.
    """

    statistic: float
    threshold: float
    dof: int
    fixes: int
    span_s: float
    mean_distance_m: float
    distance_bound_m: float

    def to_dict(self) -> dict[str, float | int]:
        """The figures for an event (``reinitialised``)."""
        return {
            "statistic": self.statistic,
            "threshold": self.threshold,
            "dof": self.dof,
            "fixes": self.fixes,
            "span_s": self.span_s,
            "mean_distance_m": self.mean_distance_m,
            "distance_bound_m": self.distance_bound_m,
        }


class NisWindow:
    """Running window of GNSS position NIS values and its chi-square test (module docstring).

    Parameters
    ----------
    fixes : int
        Window length, fixes (``N``).
    false_alarm : float
        False-alarm probability of one test (at most; the cap only lowers it).
    cap_probability : float
        Each fix's NIS is capped at the chi-square quantile of this probability for its dof.
    min_fixes : int
        Fixes the window must hold before it is tested.
    min_distance_m : float
        Least mean distance to the fixes of an alarm, m.
    distance_sigmas : float
        The alarm's mean distance is also at least this many times the RMS of the fixes'
        reported horizontal 1-sigma.
    """

    def __init__(
        self,
        fixes: int,
        false_alarm: float,
        cap_probability: float,
        min_fixes: int,
        min_distance_m: float = 0.0,
        distance_sigmas: float = 0.0,
    ) -> None:
        if fixes < 1 or not 0 < min_fixes <= fixes:
            raise ValueError(f"NIS window: need 1 <= min_fixes <= fixes, got {min_fixes}, {fixes}")
        if not (0.0 < false_alarm < 1.0 and 0.0 < cap_probability < 1.0):
            raise ValueError("NIS window: probabilities must be in (0, 1)")
        self.fixes = int(fixes)
        self.false_alarm = float(false_alarm)
        self.cap_probability = float(cap_probability)
        self.min_fixes = int(min_fixes)
        self.min_distance_m = float(min_distance_m)
        self.distance_sigmas = float(distance_sigmas)
        #: per fix: time (s), capped NIS, dof, distance (m), reported horizontal sigma squared (m^2)
        self._win: deque[tuple[float, float, int, float, float]] = deque()
        self._sum = 0.0
        self._dof = 0
        self._caps: dict[int, float] = {}
        self._thresholds: dict[int, float] = {}

    def __len__(self) -> int:
        return len(self._win)

    def cap(self, dof: int) -> float:
        """Cap of one fix's NIS with ``dof`` degrees of freedom."""
        c = self._caps.get(dof)
        if c is None:
            c = self._caps[dof] = float(chdtri(dof, 1.0 - self.cap_probability))
        return c

    def threshold(self, dof: int) -> float:
        """Threshold of the window's sum with ``dof`` degrees of freedom."""
        c = self._thresholds.get(dof)
        if c is None:
            c = self._thresholds[dof] = float(chdtri(dof, self.false_alarm))
        return c

    def clear(self) -> None:
        """Empty the window (after a re-initialisation)."""
        self._win.clear()
        self._sum = 0.0
        self._dof = 0

    def add(
        self, t: float, nis: float, dof: int, distance_m: float = math.inf, sigma_h_m: float = 0.0
    ) -> NisAlarm | None:
        """Add one fix; the alarm or None.

        Parameters
        ----------
        t : float
            Time, s.
        nis : float
            Its NIS (a non-finite one counts at the cap: the filter could not even evaluate it).
        dof : int
            Position components of the fix.
        distance_m : float
            Horizontal distance between the predicted position and the fix, m.
        sigma_h_m : float
            The fix's reported horizontal 1-sigma, ``hypot(sigma_N, sigma_E)``, m.
        """
        v = nis if math.isfinite(nis) else math.inf
        v = min(max(v, 0.0), self.cap(dof))
        d = distance_m if math.isfinite(distance_m) else 1e12
        self._win.append((t, v, dof, d, sigma_h_m * sigma_h_m))
        self._sum += v
        self._dof += dof
        while len(self._win) > self.fixes:
            _, v0, d0, _, _ = self._win.popleft()
            self._sum -= v0
            self._dof -= d0
        if len(self._win) < self.min_fixes:
            return None
        # (the running sum is not re-added from the window: the values are capped and few, the
        # rounding error stays far below the threshold's scale)
        thr = self.threshold(self._dof)
        if self._sum <= thr:
            return None
        n = len(self._win)
        mean_d = sum(r[3] for r in self._win) / n
        rms_sig = math.sqrt(sum(r[4] for r in self._win) / n)
        bound = max(self.min_distance_m, self.distance_sigmas * rms_sig)
        if not mean_d > bound:
            return None
        return NisAlarm(self._sum, thr, self._dof, n, t - self._win[0][0], mean_d, bound)
