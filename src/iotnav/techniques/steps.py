"""Step detection on the accelerometer norm and Weinberg step length (pedestrian dead reckoning).

Step detection (streaming, one sample in, at most one step event out)
    The specific-force norm ``a_k = |f_b,k|`` (m/s^2; no attitude needed, so it works for any
    way the device is carried) is smoothed by two cascaded first-order low-passes with time
    constant ``tau_lp = 1 / (2 pi f_c)`` (``f_c`` = ``lowpass_hz``, 3 Hz: walking cadence is
    1.5-2.5 Hz), ``y_k = y_{k-1} + alpha (x_k - y_{k-1})``, ``alpha = 1 - exp(-dt / tau_lp)``.
    The gravity level ``g_k`` is a slower low-pass (``gravity_tau_s``) of the same norm, and the
    dynamic part is ``d_k = y_k - g_k``. A step is a peak of ``d`` with hysteresis: the detector
    arms when ``d`` rises above ``threshold_mps2``, tracks the maximum and its time while armed,
    and confirms the step when ``d`` falls back below ``release_mps2``. The step is reported
    with the time of its peak (which lags the impact by about the low-pass group delay
    ``2 / (2 pi f_c)``, :attr:`StepConfig.group_delay_s`); a peak closer than ``min_interval_s`` to the previous step is
    counted (``merged``) and not reported. (Threshold-and-peak detection as surveyed by
    Harle, "A survey of indoor inertial positioning systems for pedestrians", IEEE Commun.
    Surveys Tuts. 15(3), 2013, sec. IV-A.)

Step length (Weinberg 2002)
    ``L = K (a_max - a_min)^(1/4)`` with ``a_max`` the peak of the low-passed norm at the step
    and ``a_min`` the lowest low-passed norm since the previous step (m/s^2); ``K`` (m per
    (m/s^2)^(1/4)) depends on the walker and the carrying mode. H. Weinberg, "Using the ADXL202
    in pedometer and personal navigation applications", Analog Devices AN-602, 2002.

Online calibration of K (:class:`StepLengthCalibrator`)
    While GNSS is good and the walker moves, the distance the receiver reports over an interval
    (its Doppler speed integrated in time, ``D = sum v_k dt_k``, much less noisy than
    differenced positions over a few metres) and the sum of the steps' fourth roots
    ``R = sum (a_max - a_min)^(1/4)`` over the same interval give ``K = D / R``; with
    exponential forgetting (``forget`` per interval)::

        S_D <- lambda S_D + D,   S_R <- lambda S_R + R,   K = S_D / S_R

State layout of the detector (STYLE §5, §7): a float64 array with the named indices below,
advanced by the pure function :func:`step_update`, so that it can later be compiled.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np
import numpy.typing as npt

FloatArray = npt.NDArray[np.float64]

__all__ = [
    "N_STEP_STATE",
    "StepConfig",
    "StepDetector",
    "StepEvent",
    "StepLengthCalibrator",
    "step_update",
    "weinberg_length",
]

# Named indices of the detector state array.
S_T = 0  # time of the previous sample, s (NaN before the first)
S_LP1 = 1  # first low-pass stage of |f|, m/s^2
S_LP2 = 2  # second low-pass stage (the smoothed norm y), m/s^2
S_GRAV = 3  # gravity level g, m/s^2
S_ARMED = 4  # 1.0 while above the threshold
S_PEAK = 5  # maximum of y while armed, m/s^2
S_PEAK_D = 6  # maximum of d = y - g while armed, m/s^2
S_PEAK_T = 7  # its time, s
S_MIN = 8  # lowest y since the previous step, m/s^2
S_LAST_T = 9  # time of the previous step, s (-inf before the first)
S_N_STEPS = 10  # steps reported
S_N_MERGED = 11  # peaks closer than min_interval_s to the previous step
S_N_WARM = 12  # samples seen (the detector is armed only after warm-up)
N_STEP_STATE = 13


@dataclass(frozen=True)
class StepConfig:
    """Step detector and step-length settings (``[steps]`` table).

    Attributes
    ----------
    lowpass_hz : float
        Cut-off of each of the two first-order low-pass stages on ``|f_b|``, Hz.
    gravity_tau_s : float
        Time constant of the gravity level subtracted from the smoothed norm, s.
    threshold_mps2 : float
        The detector arms when the dynamic norm rises above this, m/s^2.
    release_mps2 : float
        ... and confirms the step when it falls below this, m/s^2 (< ``threshold_mps2``).
    min_interval_s : float
        Shortest time between two steps, s (a running cadence of 3.3 steps/s).
    max_gap_s : float
        A longer time between samples restarts the filters (no step across a gap), s.
    warmup_s : float
        The detector does not arm during the first ``warmup_s`` (filters settling), s.
    weinberg_k : float
        Weinberg constant K, m / (m/s^2)^(1/4) (about 0.5 for a hand-held device at
        ``lowpass_hz`` = 3 Hz; calibrated online by :class:`StepLengthCalibrator`).
    min_length_m, max_length_m : float
        Step lengths are clipped to this range, m (a step out of it is counted).
    """

    lowpass_hz: float = 3.0
    gravity_tau_s: float = 2.0
    threshold_mps2: float = 0.6
    release_mps2: float = 0.0
    min_interval_s: float = 0.3
    max_gap_s: float = 0.5
    warmup_s: float = 0.5
    weinberg_k: float = 0.5
    min_length_m: float = 0.1
    max_length_m: float = 1.6

    @property
    def group_delay_s(self) -> float:
        """Low-frequency group delay of the two low-pass stages, ``2 / (2 pi f_c)``, s."""
        return 2.0 / (2.0 * math.pi * self.lowpass_hz)

    def __post_init__(self) -> None:
        if not (self.lowpass_hz > 0 and self.gravity_tau_s > 0 and self.min_interval_s >= 0):
            raise ValueError("steps: lowpass_hz and gravity_tau_s must be > 0, min_interval_s >= 0")
        if self.release_mps2 >= self.threshold_mps2:
            raise ValueError("steps: release_mps2 must be below threshold_mps2")
        if not 0 < self.min_length_m < self.max_length_m:
            raise ValueError("steps: expected 0 < min_length_m < max_length_m")


class StepEvent(NamedTuple):
    """One detected step.

    Attributes
    ----------
    t : float
        Time of the peak, s (device time).
    a_max, a_min : float
        Peak and preceding minimum of the low-passed norm, m/s^2.
    root : float
        ``(a_max - a_min)^(1/4)``, (m/s^2)^(1/4); the step length is ``K root``.
    interval_s : float
        Time since the previous step, s (inf for the first).
    """

    t: float
    a_max: float
    a_min: float
    root: float
    interval_s: float


def weinberg_length(a_max: float, a_min: float, k: float) -> float:
    """Weinberg step length ``L = K (a_max - a_min)^(1/4)``, m (accelerations in m/s^2)."""
    return k * max(a_max - a_min, 0.0) ** 0.25


def new_step_state() -> FloatArray:
    """A fresh detector state array."""
    st = np.zeros(N_STEP_STATE)
    st[S_T] = math.nan
    st[S_LAST_T] = -math.inf
    return st


def step_update(st: FloatArray, t: float, a_norm: float, cfg: StepConfig) -> StepEvent | None:
    """Advance the detector by one sample; a :class:`StepEvent` when a step is confirmed.

    Parameters
    ----------
    st : numpy.ndarray
        Detector state (:func:`new_step_state`), updated in place.
    t : float
        Sample time, s (increasing; the caller rejects non-finite values and time reversals).
    a_norm : float
        ``|f_b|``, m/s^2.
    cfg : StepConfig
        Settings.
    """
    t_prev = st[S_T]
    st[S_T] = t
    if not math.isfinite(t_prev) or t - t_prev > cfg.max_gap_s:
        st[S_LP1] = st[S_LP2] = st[S_GRAV] = st[S_MIN] = a_norm
        st[S_ARMED] = 0.0
        st[S_N_WARM] = 0.0
        return None
    dt = t - t_prev
    alpha = 1.0 - math.exp(-dt * 2.0 * math.pi * cfg.lowpass_hz)
    st[S_LP1] += alpha * (a_norm - st[S_LP1])
    st[S_LP2] += alpha * (st[S_LP1] - st[S_LP2])
    st[S_GRAV] += (1.0 - math.exp(-dt / cfg.gravity_tau_s)) * (a_norm - st[S_GRAV])
    st[S_N_WARM] += dt
    y = st[S_LP2]
    d = y - st[S_GRAV]
    if st[S_ARMED] == 0.0:
        st[S_MIN] = min(st[S_MIN], y)
        if d > cfg.threshold_mps2 and st[S_N_WARM] >= cfg.warmup_s:
            st[S_ARMED] = 1.0
            st[S_PEAK], st[S_PEAK_D], st[S_PEAK_T] = y, d, t
        return None
    if d > st[S_PEAK_D]:
        st[S_PEAK], st[S_PEAK_D], st[S_PEAK_T] = y, d, t
    if d >= cfg.release_mps2:
        return None
    st[S_ARMED] = 0.0
    t_peak = st[S_PEAK_T]
    interval = t_peak - st[S_LAST_T]
    if interval < cfg.min_interval_s:
        st[S_N_MERGED] += 1.0
        st[S_MIN] = y
        return None
    a_max, a_min = st[S_PEAK], st[S_MIN]
    st[S_LAST_T] = t_peak
    st[S_N_STEPS] += 1.0
    st[S_MIN] = y
    return StepEvent(
        float(t_peak), float(a_max), float(a_min), max(a_max - a_min, 0.0) ** 0.25, float(interval)
    )


class StepDetector:
    """Streaming step detector: ``update(t, acc_b)`` per sample (see the module docstring)."""

    def __init__(self, config: StepConfig | None = None) -> None:
        self.config = config or StepConfig()
        self.state = new_step_state()

    def update(self, t: float, acc_b: FloatArray) -> StepEvent | None:
        """One sample: time (s), specific force in ``b`` (m/s^2); the step confirmed by it, if any."""
        return step_update(self.state, t, float(math.sqrt(float(acc_b @ acc_b))), self.config)

    def length(self, ev: StepEvent, k: float | None = None) -> float:
        """Weinberg length of a step, clipped to ``[min_length_m, max_length_m]``, m."""
        c = self.config
        kk = c.weinberg_k if k is None else k
        return min(max(kk * ev.root, c.min_length_m), c.max_length_m)

    @property
    def n_steps(self) -> int:
        """Steps reported."""
        return int(self.state[S_N_STEPS])

    @property
    def n_merged(self) -> int:
        """Peaks dropped as closer than ``min_interval_s`` to the previous step."""
        return int(self.state[S_N_MERGED])

    @property
    def last_step_t(self) -> float:
        """Time of the last step, s (-inf before the first)."""
        return float(self.state[S_LAST_T])


class StepLengthCalibrator:
    """Online Weinberg K from GNSS distance: ``K = S_D / S_R`` with forgetting (module docstring).

    Parameters
    ----------
    k0 : float
        Initial K, m / (m/s^2)^(1/4).
    interval_s : float
        Length of one accumulation interval, s.
    forget : float
        Weight of the past per interval (0..1).
    min_steps : int
        Intervals with fewer steps are discarded (the walker stood or GNSS was lost).
    """

    def __init__(self, k0: float, interval_s: float = 5.0, forget: float = 0.9, min_steps: int = 4) -> None:
        self.k = k0
        self.interval_s = interval_s
        self.forget = forget
        self.min_steps = min_steps
        self.s_d = 0.0
        self.s_r = 0.0
        self.n_intervals = 0
        self._d = 0.0
        self._r = 0.0
        self._n = 0
        self._t0 = math.nan
        self._t_last = math.nan
        self._v_last = 0.0
        self.last_distance_m = math.nan
        self.last_duration_s = math.nan

    def add_step(self, root: float) -> None:
        """Add one step's ``(a_max - a_min)^(1/4)`` to the current interval."""
        if math.isfinite(self._t0):
            self._r += root
            self._n += 1

    def add_speed(self, t: float, speed_mps: float) -> float | None:
        """Add a GNSS speed (m/s) at time ``t`` (s); the interval's K when one completes, else None."""
        if not math.isfinite(self._t_last) or t - self._t_last > 2.0 * self.interval_s:
            self.reset_interval(t, speed_mps)
            return None
        self._d += 0.5 * speed_mps * (t - self._t_last)  # trapezoid with the previous speed
        self._d += 0.5 * self._v_last * (t - self._t_last)
        self._t_last, self._v_last = t, speed_mps
        if t - self._t0 < self.interval_s:
            return None
        out = None
        if self._n >= self.min_steps and self._r > 0:
            self.s_d = self.forget * self.s_d + self._d
            self.s_r = self.forget * self.s_r + self._r
            self.k = self.s_d / self.s_r
            self.n_intervals += 1
            out = self._d / self._r
            self.last_distance_m = self._d
            self.last_duration_s = t - self._t0
        self._d = self._r = 0.0
        self._n = 0
        self._t0 = t
        return out

    def reset_interval(self, t: float, speed_mps: float = math.nan) -> None:
        """Start a new interval at ``t`` (after a GNSS gap); the accumulated K is kept."""
        self._d = self._r = 0.0
        self._n = 0
        self._t0 = self._t_last = t
        self._v_last = speed_mps if math.isfinite(speed_mps) else 0.0
