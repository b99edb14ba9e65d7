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
* when no GPS speed has arrived for ``speed_timeout_s`` (outage) the latest GPS speed must
  itself have been below the threshold *and* the caller's fallback speed (the engine passes
  the fusion filter's dead-reckoned horizontal speed) must be: the accelerometer cannot see a
  constant velocity, and a dead-reckoned speed that has decayed (or been held at zero by the
  static state itself) would otherwise declare a car cruising at 17 m/s through a tunnel
  static, the pipeline then holding it in place for the rest of the outage (issue 16). A
  vehicle that stops inside an outage after the last fix saw it moving stays "moving" until
  the next GPS speed: the safe side, since a wrong static holds the position while a missed
  one only forgoes a zero-velocity update. Before any GPS speed (cold boot, e.g. a stored
  position at boot) the fallback speed decides when there is one, else the accelerometer
  alone; the first GPS speed above ``exit_speed_mps`` ends such a static period at once.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numba
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


# Hot state of the detector, one float64 array (so the per-sample step compiles with numba
# and engines' compiled IMU kernels call the very same function).
S_N_SPEEDS, S_T_SPEED, S_ACC_H, S_T_PREV, S_STATIC = range(5)
# Parameters, one float64 array in this order (see :func:`static_params`).
P_THETA_A, P_SPEED_THR, P_ACC_TAU, P_EXIT_FACTOR, P_SPEED_TIMEOUT, P_EXIT_SPEED = range(6)


def static_params(c: StaticConfig) -> FloatArray:
    """The parameter vector of :func:`static_step` from a :class:`StaticConfig`."""
    return np.array(
        [
            c.theta_a_mps2,
            c.speed_threshold_mps,
            c.acc_tau_s,
            c.exit_factor,
            c.speed_timeout_s,
            c.exit_speed_mps,
        ]
    )


@numba.njit(cache=True)
def smoothed_speed(state: FloatArray, speeds: FloatArray) -> float:
    """Moving average of the latest GPS speeds, m/s (NaN before any)."""
    n = int(state[S_N_SPEEDS])
    if n == 0:
        return math.nan
    k = min(n, speeds.size)
    total = 0.0
    for i in range(k):
        total += speeds[i]
    return total / k


@numba.njit(cache=True)
def static_step(
    state: FloatArray,
    speeds: FloatArray,
    p: FloatArray,
    t: float,
    acc_north: float,
    acc_east: float,
    fallback_speed_mps: float,
) -> bool:
    """Block 3 for one IMU sample (compiled; :meth:`StaticDetector.step` and engines call it).

    Parameters
    ----------
    state : numpy.ndarray
        Detector state (``S_*`` layout), updated in place.
    speeds : numpy.ndarray
        Ring of the latest GPS speeds, m/s.
    p : numpy.ndarray
        Parameters from :func:`static_params`.
    t : float
        Device time, s.
    acc_north, acc_east : float
        Horizontal components of ``y_n = C_nb y_b`` (or of the acceleration), m/s^2.
    fallback_speed_mps : float
        Speed used when the GPS speed is stale, m/s (NaN: none).

    Returns
    -------
    bool
        True when static.
    """
    a_h = math.hypot(acc_north, acc_east)
    tau = p[P_ACC_TAU]
    if not math.isfinite(state[S_ACC_H]) or tau <= 0.0:
        state[S_ACC_H] = a_h
    else:
        dt = max(t - state[S_T_PREV], 0.0)
        state[S_ACC_H] += (1.0 - math.exp(-dt / tau)) * (a_h - state[S_ACC_H])
    state[S_T_PREV] = t
    was = state[S_STATIC] != 0.0
    thr = max(p[P_SPEED_THR], p[P_EXIT_SPEED]) if was else p[P_SPEED_THR]
    speed_ok = True
    if t - state[S_T_SPEED] <= p[P_SPEED_TIMEOUT]:
        speed_ok = smoothed_speed(state, speeds) < thr
    else:
        if state[S_N_SPEEDS] > 0.0:  # stale: the vehicle must have been slow at the last fix
            speed_ok = smoothed_speed(state, speeds) < thr
        if math.isfinite(fallback_speed_mps):
            speed_ok = speed_ok and fallback_speed_mps < thr
    quiet = state[S_ACC_H] < p[P_THETA_A] and a_h < p[P_EXIT_FACTOR] * p[P_THETA_A]
    now = speed_ok and quiet
    state[S_STATIC] = 1.0 if now else 0.0
    return now


class StaticDetector:
    """Block 3; hot state in :attr:`state` (``S_*`` layout) and the :attr:`speeds` ring."""

    def __init__(self, config: StaticConfig | None = None) -> None:
        self.config = config or StaticConfig()
        self.params = static_params(self.config)
        self.speeds = np.full(max(1, self.config.speed_window), np.nan)
        self.state = np.array([0.0, -math.inf, math.nan, math.nan, 0.0])

    @property
    def static(self) -> bool:
        """The latest decision."""
        return bool(self.state[S_STATIC] != 0.0)

    def update_speed(self, t: float, speed_mps: float) -> None:
        """Feed a GPS speed over ground (m/s) at device time ``t`` (s)."""
        if not math.isfinite(speed_mps):
            return
        n = int(self.state[S_N_SPEEDS])
        self.speeds[n % self.speeds.size] = speed_mps
        self.state[S_N_SPEEDS] = n + 1
        self.state[S_T_SPEED] = t

    @property
    def speed(self) -> float:
        """Smoothed GPS speed, m/s (NaN before any)."""
        return float(smoothed_speed(self.state, self.speeds))

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
        return bool(
            static_step(
                self.state,
                self.speeds,
                self.params,
                float(t),
                float(acc_n[0]),
                float(acc_n[1]),
                float(fallback_speed_mps),
            )
        )
