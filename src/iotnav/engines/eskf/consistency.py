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
jump) cannot trigger the test alone: it fires on a *fraction* of the window far off. With
``N = 60``, ``m = 3``, ``p = 1e-6`` and the cap at 0.99 (11.3 per 3-dof fix) the threshold is
about 4.7 per fix: five rejections in a row among otherwise consistent fixes sum to about
``5 x 11.3 + 55 x 3 = 222``, under the threshold (281); a window where a fifth or more of the
fixes are at the cap is over it. The test runs at every fix once the window holds
``min_fixes``; after a re-initialisation the window starts empty.
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass

from scipy.stats import chi2


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
    """

    statistic: float
    threshold: float
    dof: int
    fixes: int
    span_s: float

    def to_dict(self) -> dict[str, float | int]:
        """The figures for an event (``reinitialised``)."""
        return {
            "statistic": self.statistic,
            "threshold": self.threshold,
            "dof": self.dof,
            "fixes": self.fixes,
            "span_s": self.span_s,
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
    """

    def __init__(self, fixes: int, false_alarm: float, cap_probability: float, min_fixes: int) -> None:
        if fixes < 1 or not 0 < min_fixes <= fixes:
            raise ValueError(f"NIS window: need 1 <= min_fixes <= fixes, got {min_fixes}, {fixes}")
        if not (0.0 < false_alarm < 1.0 and 0.0 < cap_probability < 1.0):
            raise ValueError("NIS window: probabilities must be in (0, 1)")
        self.fixes = int(fixes)
        self.false_alarm = float(false_alarm)
        self.cap_probability = float(cap_probability)
        self.min_fixes = int(min_fixes)
        self._win: deque[tuple[float, float, int]] = deque()
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
            c = self._caps[dof] = float(chi2.isf(1.0 - self.cap_probability, dof))
        return c

    def threshold(self, dof: int) -> float:
        """Threshold of the window's sum with ``dof`` degrees of freedom."""
        c = self._thresholds.get(dof)
        if c is None:
            c = self._thresholds[dof] = float(chi2.isf(self.false_alarm, dof))
        return c

    def clear(self) -> None:
        """Empty the window (after a re-initialisation)."""
        self._win.clear()
        self._sum = 0.0
        self._dof = 0

    def add(self, t: float, nis: float, dof: int) -> NisAlarm | None:
        """Add one fix's NIS (``dof`` position components) at time ``t`` (s); the alarm or None.

        A non-finite NIS counts at its cap (the filter could not even evaluate the fix).
        """
        v = nis if math.isfinite(nis) else math.inf
        v = min(max(v, 0.0), self.cap(dof))
        self._win.append((t, v, dof))
        self._sum += v
        self._dof += dof
        while len(self._win) > self.fixes:
            _, v0, d0 = self._win.popleft()
            self._sum -= v0
            self._dof -= d0
        if len(self._win) < self.min_fixes:
            return None
        # the running sum re-added from the window now and then would cost more than it saves:
        # the values are capped and few, the rounding error stays far below the threshold's scale
        thr = self.threshold(self._dof)
        if self._sum <= thr:
            return None
        return NisAlarm(self._sum, thr, self._dof, len(self._win), t - self._win[0][0])
