"""IMU error model: true ``f_b``, ``omega_b`` to what a MEMS IMU writes.

For each sensor (accelerometer, gyroscope) and axis the measurement is::

    y = sat(quant((I + S + M) x + b0 + b(t) + n + vib))

* ``x``: the true signal resampled to the output rate (mean over each output interval, or
  point samples, see :class:`iotnav.sim.config.ImuConfig`);
* ``S``: diagonal scale-factor error, ``M``: off-diagonal cross-axis coupling (drawn once);
* ``b0``: turn-on bias (drawn once);
* ``b(t)``: in-run bias, one of (``bias_model``)

  - ``"flicker"``: flicker (1/f) noise of bias instability ``B`` in the sense of IEEE Std 952
    (two-sided PSD ``B^2 / (2 pi f)``, flat Allan deviation ``sqrt(2 ln 2 / pi) B = 0.664 B``),
    the definition :mod:`iotnav.techniques.allan` recovers; see :func:`flicker_noise`;
  - ``"gauss-markov"``: a first-order Gauss-Markov process (correlation time ``T``) whose
    Allan deviation *peaks* at ``B`` (the peak of a GM's Allan deviation is ``0.6186 sigma`` at
    ``tau = 1.89 T``, so ``sigma = B / 0.6186``); its ADEV has a hump, not a floor, so an
    Allan analysis of it reads a different ``B``;
  - ``"random-walk"``: a random walk of intensity ``acc/gyro_random_walk``;
* ``n``: white noise of standard deviation ``ND sqrt(fs)`` for noise density ``ND`` and
  sample rate ``fs`` (so the Allan deviation is ``ND / sqrt(tau)``);
* ``vib``: vibration, a sinusoid at ``f0`` plus one at ``2 f0`` of half amplitude with slowly
  wandering phases, point-sampled (it aliases as real vibration does);
* ``quant``: rounding to the output resolution; ``sat``: clipping to the full scale.

Recorded times are the nominal sample times plus white jitter (kept increasing). Datasheet
units are converted to SI once here (``g0 = 9.80665 m/s^2``).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt
from scipy.signal import lfilter

from iotnav.sim.presets import ImuSpec

FloatArray = npt.NDArray[np.float64]

G0 = 9.80665
_DEG = np.pi / 180.0


def gm_allan_variance(tau: npt.ArrayLike, sigma: float, corr_time_s: float) -> FloatArray:
    """Allan variance of a first-order Gauss-Markov process (autocorrelation sigma^2 e^{-|t|/T}).

    ``AVAR(tau) = (2 sigma^2 T / tau) (1 - T / (2 tau) (3 - 4 e^{-tau/T} + e^{-2 tau/T}))``.
    """
    tau = np.asarray(tau, dtype=float)
    x = tau / corr_time_s
    return 2.0 * sigma**2 / x * (1.0 - (3.0 - 4.0 * np.exp(-x) + np.exp(-2.0 * x)) / (2.0 * x))


def _gm_peak_ratio() -> float:
    x = np.linspace(0.5, 5.0, 20001)
    return float(np.sqrt(np.max(gm_allan_variance(x, 1.0, 1.0))))


#: Peak Allan deviation of a unit-variance first-order Gauss-Markov process (about 0.6186).
GM_ADEV_PEAK = _gm_peak_ratio()


def gauss_markov(
    n: int, dt: float, sigma: float, corr_time_s: float, rng: np.random.Generator, dim: int = 3
) -> FloatArray:
    """Stationary first-order Gauss-Markov samples (exact discretisation), ``(n, dim)``."""
    if n == 0 or sigma == 0.0:
        return np.zeros((n, dim))
    phi = np.exp(-dt / corr_time_s)
    w = rng.normal(0.0, sigma * np.sqrt(1.0 - phi**2), size=(n, dim))
    w[0] = rng.normal(0.0, sigma, size=dim)
    return lfilter([1.0], [1.0, -phi], w, axis=0)


#: Correlation times per decade of the Gauss-Markov sum in :func:`flicker_noise`.
FLICKER_PER_DECADE = 2


def flicker_correlation_times(
    dt: float, duration_s: float, per_decade: int = FLICKER_PER_DECADE
) -> tuple[FloatArray, float]:
    """Log-spaced correlation times of :func:`flicker_noise` and their log step.

    The interval ``[ln(dt / pi), ln(duration_s)]`` is cut into ``k = ceil(decades * per_decade)``
    equal steps ``Delta``; the times are the step midpoints.

    Returns
    -------
    corr_times_s : ndarray, shape (k,)
        Correlation times, s.
    log_step : float
        ``Delta`` (natural log).
    """
    lo, hi = math.log(dt / math.pi), math.log(max(duration_s, 2.0 * dt))
    k = max(1, math.ceil((hi - lo) / math.log(10.0) * per_decade))
    step = (hi - lo) / k
    return np.exp(lo + step * (np.arange(k) + 0.5)), step


def flicker_noise(
    n: int, dt: float, b: float, rng: np.random.Generator, dim: int = 3, per_decade: int = FLICKER_PER_DECADE
) -> FloatArray:
    """Flicker (1/f) noise of bias instability ``b`` as a sum of Gauss-Markov processes, ``(n, dim)``.

    A first-order Gauss-Markov process of variance ``s^2`` and correlation time ``T`` has the
    two-sided PSD ``2 s^2 T / (1 + (2 pi f T)^2)``. Spreading variance evenly over ``ln T``,
    ``s^2 = c dlnT``, and integrating over all ``T`` gives
    ``int 2 c T / (1 + (w T)^2) dT / T = 2 c (pi / 2) / w = c / (2 f)`` (``w = 2 pi f``), which
    equals the flicker PSD ``B^2 / (2 pi f)`` for ``c = B^2 / pi``. Discretised with ``k`` log
    steps ``Delta`` (``per_decade`` per decade, :func:`flicker_correlation_times`) the process is

        ``b(t) = sum_j GM_j(t)``, ``GM_j`` independent with ``T_j`` the step midpoints and
        ``s_j^2 = B^2 Delta / pi``.

    With ``T`` from ``T_lo = dt / pi`` (corner ``f_s / 2``) to ``T_hi = duration`` (corner
    ``1 / (2 pi duration)``) the continuous-``T`` integral gives the PSD
    ``B^2 / (2 pi f) * (2 / pi) (atan(2 pi f T_hi) - atan(2 pi f T_lo))``: 1/f between the
    corners, 0.90 of it at ``f = 1 / duration``, half of it at ``f = f_s / 2``. Its Allan variance
    is the sum of the Gauss-Markov Allan variances (:func:`gm_allan_variance`); for
    ``per_decade = 2`` and a 6-hour record at 100 Hz it is ``0.664 B`` within 2.5 % for every
    ``1 s <= tau <= duration / 10`` (within 0.5 % up to tau = 300 s, 0.8 % low at 700 s, 2.2 %
    low at 2160 s: the low-frequency corner; the log-step ripple is below 0.1 %). ``T_hi`` is the record length, not
    ``duration / (2 pi)``: with the soft Lorentzian corners that shorter choice would already cut
    the ADEV by 13 % at ``tau = duration / 10``.

    Parameters
    ----------
    n : int
        Number of samples.
    dt : float
        Sample interval, s (``duration = n dt``).
    b : float
        Bias instability ``B`` (unit of the signal; the flat ADEV is ``0.664 b``).
    rng : numpy.random.Generator
        Random source.
    dim : int
        Number of independent axes.
    per_decade : int
        Gauss-Markov components per decade of correlation time.

    Returns
    -------
    numpy.ndarray
        Samples, ``(n, dim)``, stationary from the first sample.
    """
    if n == 0 or b == 0.0:
        return np.zeros((n, dim))
    taus, step = flicker_correlation_times(dt, n * dt, per_decade)
    sigma = b * math.sqrt(step / math.pi)
    out = np.zeros((dim, n))  # time along the contiguous axis: lfilter is ~5x faster so
    for corr_time in taus:
        # exact discretisation of each Gauss-Markov component, started in its stationary state
        phi = math.exp(-dt / float(corr_time))
        w = rng.standard_normal((dim, n))
        w[:, 1:] *= sigma * math.sqrt(1.0 - phi**2)
        w[:, 0] *= sigma
        out += lfilter([1.0], [1.0, -phi], w, axis=-1)
    return out.T


#: Accepted values of ``ImuSpec.bias_model``.
BIAS_MODELS = ("flicker", "gauss-markov", "random-walk")


@dataclass(frozen=True)
class SiSpec:
    """An :class:`ImuSpec` in SI units (per axis, 1-sigma)."""

    acc_nd: float  # m/s^2/sqrt(Hz)
    gyro_nd: float  # rad/s/sqrt(Hz)
    acc_b0: float  # m/s^2
    gyro_b0: float  # rad/s
    acc_bi: float  # m/s^2 (Allan floor / 0.664 for flicker, Allan peak for gauss-markov)
    gyro_bi: float  # rad/s
    tau_c: float  # s
    acc_rw: float  # m/s^2/sqrt(s)
    gyro_rw: float  # rad/s/sqrt(s)
    acc_sf: float
    gyro_sf: float
    acc_mis: float
    gyro_mis: float
    acc_range: float  # m/s^2
    gyro_range: float  # rad/s
    acc_lsb: float  # m/s^2
    gyro_lsb: float  # rad/s
    jitter: float  # s
    bias_model: str

    @classmethod
    def from_spec(cls, s: ImuSpec) -> SiSpec:
        """Convert datasheet units to SI."""
        if s.bias_model not in BIAS_MODELS:
            raise ValueError(
                f"imu.bias_model: expected one of {', '.join(BIAS_MODELS)}, got {s.bias_model!r}"
            )
        return cls(
            acc_nd=s.acc_noise_density_ug_rthz * 1e-6 * G0,
            gyro_nd=s.gyro_noise_density_mdps_rthz * 1e-3 * _DEG,
            acc_b0=s.acc_turn_on_bias_mg * 1e-3 * G0,
            gyro_b0=s.gyro_turn_on_bias_dps * _DEG,
            acc_bi=s.acc_bias_instability_mg * 1e-3 * G0,
            gyro_bi=s.gyro_bias_instability_dph * _DEG / 3600.0,
            tau_c=s.bias_correlation_time_s,
            acc_rw=s.acc_random_walk_mg_rts * 1e-3 * G0,
            gyro_rw=s.gyro_random_walk_dph_rts * _DEG / 3600.0,
            acc_sf=s.acc_scale_factor_pct * 1e-2,
            gyro_sf=s.gyro_scale_factor_pct * 1e-2,
            acc_mis=s.acc_misalignment_pct * 1e-2,
            gyro_mis=s.gyro_misalignment_pct * 1e-2,
            acc_range=s.acc_range_g * G0,
            gyro_range=s.gyro_range_dps * _DEG,
            acc_lsb=s.acc_lsb_mg * 1e-3 * G0,
            gyro_lsb=s.gyro_lsb_mdps * 1e-3 * _DEG,
            jitter=s.timestamp_jitter_ms * 1e-3,
            bias_model=s.bias_model,
        )


@dataclass
class ImuDraw:
    """The constants drawn for one simulated unit (echoed into ``scenario.json``)."""

    acc_turn_on_bias_mps2: FloatArray
    gyro_turn_on_bias_rads: FloatArray
    acc_matrix: FloatArray  # I + S + M
    gyro_matrix: FloatArray


def resample(x: FloatArray, factor: int, average: bool) -> FloatArray:
    """Take every ``factor``-th sample, or the mean of each block of ``factor`` samples."""
    if factor == 1:
        return x.copy()
    m = len(x) // factor
    if not average:
        return x[: m * factor : factor].copy()
    return x[: m * factor].reshape(m, factor, *x.shape[1:]).mean(axis=1)


def _vibration(
    t: FloatArray, rms: float, f0: float, scale: FloatArray, rng: np.random.Generator
) -> FloatArray:
    """Vibration on 3 axes (z full, x/y half), RMS ``rms`` on z at ``scale = 1``."""
    if rms == 0.0:
        return np.zeros((len(t), 3))
    n = len(t)
    dt = np.diff(t, prepend=t[0] - (t[1] - t[0] if n > 1 else 1.0))
    out = np.empty((n, 3))
    # amplitudes of the two tones so that the RMS of their sum is rms: a^2/2 (1 + 1/4) = rms^2
    a = rms / np.sqrt(0.5 * 1.25)
    for i, axis_gain in enumerate((0.5, 0.5, 1.0)):
        phase_noise = np.cumsum(rng.normal(0.0, 0.3 * np.sqrt(dt)))  # rad, wanders over seconds
        ph = 2.0 * np.pi * f0 * t + rng.uniform(0, 2 * np.pi) + phase_noise
        out[:, i] = axis_gain * a * (np.sin(ph) + 0.5 * np.sin(2.0 * ph + 1.0))
    return out * scale[:, None]


def corrupt(
    t: FloatArray,
    f_b: FloatArray,
    omega_b: FloatArray,
    speed: FloatArray,
    spec: ImuSpec,
    *,
    vib_acc_rms: float,
    vib_gyro_rms: float,
    vib_freq_hz: float,
    vib_speed_ref: float,
    rng: np.random.Generator,
) -> tuple[FloatArray, FloatArray, FloatArray, ImuDraw]:
    """Apply the error model to true samples at the output rate.

    Parameters
    ----------
    t : numpy.ndarray
        True sample times, s, ``(n,)`` (uniform).
    f_b, omega_b : numpy.ndarray
        True specific force (m/s^2) and angular rate (rad/s), ``(n, 3)``.
    speed : numpy.ndarray
        Vehicle speed at the samples, m/s (vibration scaling).
    spec : ImuSpec
        Error parameters.
    vib_acc_rms, vib_gyro_rms, vib_freq_hz, vib_speed_ref : float
        Vibration (see :class:`iotnav.sim.config.ImuConfig`).
    rng : numpy.random.Generator
        Random source.

    Returns
    -------
    t_rec, acc, gyro : numpy.ndarray
        Recorded times (s), accelerometer (m/s^2) and gyroscope (rad/s) outputs.
    draw : ImuDraw
        Constants drawn for this unit.
    """
    si = SiSpec.from_spec(spec)
    n = len(t)
    dt = float(t[1] - t[0]) if n > 1 else 1.0
    fs = 1.0 / dt

    def matrix(sf: float, mis: float) -> FloatArray:
        m = np.eye(3) + np.diag(rng.normal(0.0, sf, 3))
        off = rng.normal(0.0, mis, (3, 3))
        np.fill_diagonal(off, 0.0)
        return m + off

    A = matrix(si.acc_sf, si.acc_mis)
    Gm = matrix(si.gyro_sf, si.gyro_mis)
    b0a = rng.normal(0.0, si.acc_b0, 3)
    b0g = rng.normal(0.0, si.gyro_b0, 3)
    if si.bias_model == "gauss-markov":
        ba = gauss_markov(n, dt, si.acc_bi / GM_ADEV_PEAK, si.tau_c, rng)
        bg = gauss_markov(n, dt, si.gyro_bi / GM_ADEV_PEAK, si.tau_c, rng)
    elif si.bias_model == "flicker":
        ba = flicker_noise(n, dt, si.acc_bi, rng)
        bg = flicker_noise(n, dt, si.gyro_bi, rng)
    else:
        ba = np.cumsum(rng.normal(0.0, si.acc_rw * np.sqrt(dt), (n, 3)), axis=0)
        bg = np.cumsum(rng.normal(0.0, si.gyro_rw * np.sqrt(dt), (n, 3)), axis=0)
    na = rng.normal(0.0, si.acc_nd * np.sqrt(fs), (n, 3))
    ng = rng.normal(0.0, si.gyro_nd * np.sqrt(fs), (n, 3))
    scale = np.ones(n) if vib_speed_ref <= 0.0 else np.minimum(speed / vib_speed_ref, 2.0)
    va = _vibration(t, vib_acc_rms, vib_freq_hz, scale, rng)
    vg = _vibration(t, vib_gyro_rms, vib_freq_hz, scale, rng)

    acc = f_b @ A.T + b0a + ba + na + va
    gyro = omega_b @ Gm.T + b0g + bg + ng + vg
    if si.acc_lsb > 0:
        acc = np.round(acc / si.acc_lsb) * si.acc_lsb
    if si.gyro_lsb > 0:
        gyro = np.round(gyro / si.gyro_lsb) * si.gyro_lsb
    acc = np.clip(acc, -si.acc_range, si.acc_range)
    gyro = np.clip(gyro, -si.gyro_range, si.gyro_range)

    t_rec = t.copy()
    if si.jitter > 0 and n > 1:
        t_rec = t + np.clip(rng.normal(0.0, si.jitter, n), -0.45 * dt, 0.45 * dt)
        t_rec[0] = max(t_rec[0], t[0])  # no recorded time before the start of the log
    return t_rec, acc, gyro, ImuDraw(b0a, b0g, A, Gm)
