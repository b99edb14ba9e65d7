"""Static case determination (Forno et al. 2020, block 3, Eq. 1).

The accelerometer is resolved in the navigation frame with block 2's rotation (Eq. 1)::

    y_n = C_nb y_b

and the device is *static* when both

* the GPS speed over ground, optionally smoothed by a moving average over the last
  ``speed_window`` epochs, is below ``speed_threshold_mps``, and
* the norm of the North and East components of ``y_n`` (gravity has none) is below
  ``theta_a_mps2`` (paper: 0.125 m/s^2).

Additions, stated because the paper leaves them open:

* the horizontal-acceleration norm is smoothed by a first-order low-pass with time constant
  ``acc_tau_s`` (0 gives the paper's instantaneous test), and a single sample above
  ``exit_factor * theta_a_mps2`` leaves the static state at once (the paper's immediate return
  to the normal regime);
* hysteresis (``exit_speed_mps`` above ``speed_threshold_mps``): once static, the state ends on
  the accelerometer (as in the paper: "as soon as the horizontal acceleration grows greater
  than theta_A, the algorithm immediately returns to the normal update regime") or when the
  smoothed speed exceeds ``exit_speed_mps``; the GPS speed alone, whose noise can reach
  0.5 m/s in multipath while the receiver stands still, no longer ends a static period;
* when no GPS speed has arrived for ``speed_timeout_s`` (cold boot, outage) the speed test
  uses the caller's fallback speed (the engine passes the fusion filter's dead-reckoned
  horizontal speed, so a vehicle cruising through a tunnel is not declared static); without
  one (cold boot) the decision rests on the accelerometer alone.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

FloatArray = npt.NDArray[np.float64]


@dataclass(frozen=True)
class StaticConfig:
    """Static-detector tunables (SI).

    Attributes
    ----------
    theta_a_mps2 : float
        Horizontal-acceleration threshold ``theta_A``, m/s^2 (paper: 0.125).
    speed_threshold_mps : float
        GPS speed threshold, m/s (the paper gives no value).
    speed_window : int
        Moving-average length over GPS epochs (1: no smoothing).
    acc_tau_s : float
        Time constant of the low-pass on the horizontal-acceleration norm, s (0: instantaneous).
    exit_factor : float
        One sample above ``exit_factor * theta_a_mps2`` ends a static period immediately.
    speed_timeout_s : float
        GPS speed older than this is ignored, s.
    exit_speed_mps : float
        While static, the speed must exceed this to end the static state, m/s (values at or
        below ``speed_threshold_mps``: no hysteresis).
    """

    theta_a_mps2: float = 0.125
    speed_threshold_mps: float = 0.5
    speed_window: int = 3
    acc_tau_s: float = 0.5
    exit_factor: float = 3.0
    speed_timeout_s: float = 3.0
    exit_speed_mps: float = 0.0


class StaticDetector:
    """Block 3; hot state in the ``speeds`` ring (numpy) and a few floats."""

    def __init__(self, config: StaticConfig | None = None) -> None:
        self.config = config or StaticConfig()
        self.speeds = np.full(max(1, self.config.speed_window), np.nan)
        self.n_speeds = 0
        self.t_speed = -math.inf
        self.acc_h = math.nan
        self.t_prev = math.nan
        self.static = False

    def update_speed(self, t: float, speed_mps: float) -> None:
        """Feed a GPS speed over ground (m/s) at device time ``t`` (s)."""
        if not math.isfinite(speed_mps):
            return
        self.speeds[self.n_speeds % self.speeds.size] = speed_mps
        self.n_speeds += 1
        self.t_speed = t

    @property
    def speed(self) -> float:
        """Smoothed GPS speed, m/s (NaN before any)."""
        if self.n_speeds == 0:
            return math.nan
        k = min(self.n_speeds, self.speeds.size)
        return float(np.mean(self.speeds[:k]))

    def step(self, t: float, acc_n: FloatArray, fallback_speed_mps: float = math.nan) -> bool:
        """Decide for one IMU sample.

        Parameters
        ----------
        t : float
            Device time, s.
        acc_n : numpy.ndarray
            ``y_n = C_nb y_b`` or the acceleration with gravity removed (m/s^2); only its North
            and East components are used.
        fallback_speed_mps : float
            Speed used when the GPS speed is stale, m/s (NaN: none).

        Returns
        -------
        bool
            True when static.
        """
        c = self.config
        a_h = math.hypot(float(acc_n[0]), float(acc_n[1]))
        if not math.isfinite(self.acc_h) or c.acc_tau_s <= 0.0:
            self.acc_h = a_h
        else:
            dt = max(t - self.t_prev, 0.0)
            self.acc_h += (1.0 - math.exp(-dt / c.acc_tau_s)) * (a_h - self.acc_h)
        self.t_prev = t
        thr = max(c.speed_threshold_mps, c.exit_speed_mps) if self.static else c.speed_threshold_mps
        speed_ok = True
        if t - self.t_speed <= c.speed_timeout_s:
            speed_ok = self.speed < thr
        elif math.isfinite(fallback_speed_mps):
            speed_ok = fallback_speed_mps < thr
        quiet = self.acc_h < c.theta_a_mps2 and a_h < c.exit_factor * c.theta_a_mps2
        self.static = bool(speed_ok and quiet)
        return self.static
