"""IMU noise characterisation from static logs: Allan deviation and residual RMS.

Dabove et al. (2016) characterise the inertial platforms of two smartphones with a 6-hour static
recording and report the RMS of the static residuals per axis (their Table 2: acceleration in g,
angular rate in rad/s). This module computes that table and, from the same static log, the
Allan deviation and the three IEEE Std 952-1997 noise terms that Kalman filters and simulators
need: the white-noise density, the bias instability and the rate random walk.

Overlapping Allan variance (IEEE Std 952-1997 Annex C; El-Sheimy, Hou and Niu, "Analysis and
modeling of inertial sensors using Allan variance", IEEE TIM 57(1), 2008). For a rate signal
``y_k`` (rad/s or m/s^2) sampled every ``tau_0`` seconds, ``M`` samples, cluster time
``tau = m tau_0``, with the integrated signal ``theta_k = tau_0 * sum_{i<k} y_i``::

    sigma^2(tau) = 1 / (2 tau^2 (M - 2m)) * sum_{k=0}^{M-2m-1} (theta_{k+2m} - 2 theta_{k+m} + theta_k)^2

computed here by ``allantools.oadev`` (frequency-type data). Its link to the two-sided power
spectral density ``S(f)`` of the rate signal is::

    sigma^2(tau) = 4 * integral_0^inf S(f) sin^4(pi f tau) / (pi f tau)^2 df

and the three terms identified here are (IEEE Std 952 Table C.1):

=====================  ========================  ===========================  ==============
term                   PSD ``S(f)``              Allan deviation              log-log slope
=====================  ========================  ===========================  ==============
white noise (ARW/VRW)  ``N^2``                   ``N / sqrt(tau)``            -1/2
bias instability       ``B^2 / (2 pi f)``        ``B sqrt(2 ln 2 / pi)``      0
                                                 ``= 0.664 B``
rate random walk       ``K^2 / (2 pi f)^2``      ``K sqrt(tau / 3)``          +1/2
=====================  ========================  ===========================  ==============

Fitting the terms to the whole curve (IEEE Std 952 Annex C model, fitted instead of read off
graphically). The Allan variance of independent noises adds, so per axis::

    sigma^2(tau) = N^2 / tau + (0.664 B)^2 + K^2 tau / 3

is linear in ``(N^2, (0.664 B)^2, K^2)``, and these are found by non-negative weighted least
squares (``scipy.optimize.nnls``) on the overlapping Allan variance at every averaging time:

* The weight of each point is ``1 / var(sigma^2)``, ``var(sigma^2) = 2 sigma^4 / edf``, with the
  equivalent degrees of freedom ``edf`` of NIST SP 1065 Table 5 (allantools ``edf_simple``) for
  the noise type the model's local slope says dominates there (interpolated between white,
  flicker and random-walk FM), and ``sigma^2`` the *model* value, refitted ``FIT_ITERATIONS``
  times (weights from the noisy data would favour the low points and bias ``B`` down).
  allantools' own ``adev_err = adev / sqrt(n)`` counts overlapping clusters as independent and
  is ~20 times too small at ``tau = T / 10``, so it is not used.
* The uncertainty of each term is the fit covariance ``(A^T W A)^-1`` (delta method for the
  square roots), widened by ``sqrt(chi^2 / dof)`` when the model fits badly and by the
  correlation of neighbouring overlapping ADEVs (``INDEPENDENT_PER_DECADE``).
* A term is *identified* when its relative 1-sigma uncertainty is below
  ``IDENTIFIED_REL_SIGMA`` (10 %); otherwise it is reported as NaN with a note, and ``B`` keeps
  the bound ``B <= min(ADEV) / 0.664``. ``N`` also needs a slope -1/2 region (within 0.15). If
  the curve falls faster than slope -3/4 or rises (without a random walk) in its well-estimated
  part (tau up to ``T / 10 / sqrt(10)``), it holds periodic components (vibration, IEEE Std 952
  "sinusoidal noise") that the model lacks: ``B`` and ``K`` are then not identified.
* ``B`` is the flicker level itself, not the ADEV minimum / 0.664: white noise and rate random
  walk lift the minimum above ``0.664 B`` (by ~5 % in the six-hour test of tests/test_allan.py)
  and the fit separates them. The fit also uses the part of the curve where white noise still
  dominates, so ``B`` is identified even when the ADEV has not yet turned flat at the longest
  ``tau`` (the simulator's 3DM-GX3-35 gyro: ``N`` falls to the floor only near 80 s). On a
  6-hour log the fitted ``B`` scatters by ~6 % (gyro) and ~2 % (accelerometer) per axis, which
  the reported uncertainty matches (``benchmarks/bench_characterize_sim.py``).
* ``bias_instability_tau_s`` is the averaging time of the fitted curve's minimum,
  ``sqrt(3) N / K`` (clipped to the curve), or the longest ``tau`` when ``K = 0``.
* Quantisation noise (slope -1) and the exact finite-band flicker shape are not modelled: for
  records sampled at >= 10 Hz and the averaging times used here their effect on ``N`` and ``B``
  is within the statistical scatter.

Averaging times run from ``tau_0`` to a tenth of the record (``max_tau_fraction``): beyond that
fewer than ten independent clusters remain. The record length therefore bounds which terms can
be identified: a 30 s static segment gives ``N`` (and only an upper bound on ``B``); the 6-hour
log of Dabove et al. gives ``N`` and ``B``; ``K`` usually needs many hours more.

Units: everything in this module is SI (rad/s, m/s^2, s). :class:`NoiseModel` converts to the
datasheet units its field names carry (deg/s/sqrt(Hz), deg/h, ug/sqrt(Hz), ug, ...) and back.

References
----------
P. Dabove, G. Ghinamo, A. M. Lingua, "Inertial sensors for smartphones navigation",
SpringerPlus 4:834, 2015 (the paper shipped as ``ins-with-image-based-positioning.txt``; cited
in this project as Dabove et al. 2016), section "Data acquired through smartphones and wavelet
filtering", Table 2.
IEEE Std 952-1997, "IEEE Standard Specification Format Guide and Test Procedure for Single-Axis
Interferometric Fiber Optic Gyros", Annex C (Allan variance method).
D. W. Allan, "Statistics of atomic frequency standards", Proc. IEEE 54(2), 1966.
"""

from __future__ import annotations

import math
import tomllib
from dataclasses import dataclass, fields
from typing import Any

import allantools
import numpy as np
import numpy.typing as npt
from scipy.optimize import nnls

FloatArray = npt.NDArray[np.float64]

#: Standard gravity, m/s^2 (the "g" of accelerometer datasheets).
G0_MPS2 = 9.80665
#: ``sigma_floor = BI_FACTOR * B`` for bias instability (sqrt(2 ln 2 / pi)).
BI_FACTOR = math.sqrt(2.0 * math.log(2.0) / math.pi)
#: Averaging time at which the white-noise line is read, s.
N_TAU_S = 1.0
#: Averaging time at which the rate-random-walk line is read, s.
K_TAU_S = 3.0

_DEG = math.pi / 180.0
_UG = 1e-6 * G0_MPS2


@dataclass(frozen=True)
class AllanCurve:
    """An overlapping Allan deviation curve of one axis.

    Attributes
    ----------
    tau_s : ndarray
        Averaging times, s (integer multiples of the sample interval).
    adev : ndarray
        Allan deviation, in the unit of the signal (rad/s or m/s^2).
    adev_err : ndarray
        1-sigma uncertainty of ``adev`` as allantools gives it (``adev / sqrt(n)``).
    n_terms : ndarray
        Number of overlapping second differences averaged at each ``tau_s``.
    """

    tau_s: FloatArray
    adev: FloatArray
    adev_err: FloatArray
    n_terms: FloatArray

    @property
    def slope(self) -> FloatArray:
        """Local log-log slope ``d ln sigma / d ln tau`` (NaN for fewer than 2 points)."""
        if len(self.tau_s) < 2:
            return np.full(len(self.tau_s), np.nan)
        return np.gradient(np.log(self.adev), np.log(self.tau_s))


@dataclass(frozen=True)
class AllanParams:
    """The IEEE Std 952 noise terms of one axis, SI.

    Attributes
    ----------
    noise_density : float
        ``N``: white-noise coefficient, unit/sqrt(Hz) (rad/s/sqrt(Hz) = rad/sqrt(s) for a gyro,
        m/s^2/sqrt(Hz) = m/s/sqrt(s) for an accelerometer). ``sigma(tau) = N / sqrt(tau)``.
    noise_density_identified : bool
        A slope -1/2 region was found (otherwise ``N`` is read at the point whose slope is
        closest to -1/2 and is only indicative).
    bias_instability : float
        ``B`` (flicker PSD ``B^2 / (2 pi f)``, ADEV floor ``0.664 B``), unit (rad/s or m/s^2),
        from the whole-curve fit; NaN when not identified (relative uncertainty above
        ``IDENTIFIED_REL_SIGMA``, or periodic components).
    bias_instability_tau_s : float
        Averaging time of the fitted curve's minimum, s (NaN when not identified).
    bias_instability_upper_bound : float
        Lowest ADEV / 0.664: an upper bound on ``B`` whether or not it was identified.
    rate_random_walk : float
        ``K``: ``sigma(tau) = K sqrt(tau / 3)``, unit/sqrt(s) (rad/s/sqrt(s), m/s^2/sqrt(s));
        NaN when not identified.
    notes : tuple of str
        Why a term is missing or only indicative.
    noise_density_sigma : float
        1-sigma uncertainty of ``N`` from the fit, unit of ``N``.
    bias_instability_fit : float
        Fitted ``B`` whether or not identified (0 when the fit puts no flicker term), unit of ``B``.
    bias_instability_sigma : float
        1-sigma uncertainty of the fitted ``B``, unit of ``B``.
    rate_random_walk_fit : float
        Fitted ``K`` whether or not identified, unit of ``K``.
    rate_random_walk_sigma : float
        1-sigma uncertainty of the fitted ``K``, unit of ``K``.
    fit_chi2_reduced : float
        ``chi^2 / dof`` of the fit with the EDF-based error bars (about 0.5-1 for the model's
        noises, since neighbouring points are correlated; much larger for unmodelled noise).
    """

    noise_density: float
    noise_density_identified: bool
    bias_instability: float
    bias_instability_tau_s: float
    bias_instability_upper_bound: float
    rate_random_walk: float
    notes: tuple[str, ...] = ()
    noise_density_sigma: float = math.nan
    bias_instability_fit: float = math.nan
    bias_instability_sigma: float = math.nan
    rate_random_walk_fit: float = math.nan
    rate_random_walk_sigma: float = math.nan
    fit_chi2_reduced: float = math.nan


def averaging_times(
    n_samples: int, rate_hz: float, per_decade: int = 10, max_tau_fraction: float = 0.1
) -> FloatArray:
    """Log-spaced averaging times, integer multiples of the sample interval.

    Parameters
    ----------
    n_samples : int
        Record length in samples.
    rate_hz : float
        Sample rate, Hz.
    per_decade : int
        Points per decade of ``tau``.
    max_tau_fraction : float
        Longest ``tau`` as a fraction of the record duration.

    Returns
    -------
    ndarray
        Unique averaging times, s, from ``1 / rate_hz`` upwards.
    """
    m_max = max(1, math.floor(max_tau_fraction * n_samples))
    n_pts = max(2, math.ceil(per_decade * math.log10(max(m_max, 1))) + 1)
    m = np.unique(np.round(np.logspace(0.0, math.log10(m_max), n_pts)).astype(np.int64))
    return m.astype(np.float64) / rate_hz


def allan_deviation(
    y: npt.ArrayLike, rate_hz: float, per_decade: int = 10, max_tau_fraction: float = 0.1
) -> AllanCurve:
    """Overlapping Allan deviation of a rate signal (allantools ``oadev``, frequency data).

    Parameters
    ----------
    y : array_like, shape (n,)
        Evenly sampled rate signal (rad/s or m/s^2) of a static sensor.
    rate_hz : float
        Sample rate, Hz.
    per_decade : int
        Averaging times per decade.
    max_tau_fraction : float
        Longest averaging time as a fraction of the record (default a tenth).

    Returns
    -------
    AllanCurve
        Averaging times (s) and Allan deviation (unit of ``y``).
    """
    x = np.asarray(y, dtype=np.float64)
    if x.ndim != 1:
        raise ValueError(f"expected a 1-D signal, got shape {x.shape}")
    if len(x) < 20:
        raise ValueError(f"{len(x)} samples are too few for an Allan deviation (need at least 20)")
    if not np.all(np.isfinite(x)):
        raise ValueError("the signal holds NaN or infinite samples")
    taus = averaging_times(len(x), rate_hz, per_decade, max_tau_fraction)
    tau_out, ad, ade, ns = allantools.oadev(x, rate=rate_hz, data_type="freq", taus=taus)
    return AllanCurve(
        tau_s=np.asarray(tau_out, dtype=np.float64),
        adev=np.asarray(ad, dtype=np.float64),
        adev_err=np.asarray(ade, dtype=np.float64),
        n_terms=np.asarray(ns, dtype=np.float64),
    )


#: Relative 1-sigma uncertainty below which a fitted term counts as identified.
IDENTIFIED_REL_SIGMA = 0.10
#: Statistically independent Allan variances per decade of ``tau`` assumed for the error bars.
#: Overlapping ADEVs at neighbouring averaging times share most of their data, so the fit's
#: covariance (which treats the points as independent) is widened by ``points per decade / this``.
#: 1.5 makes the reported uncertainty of ``B`` match its scatter over 16 seeded 6-hour logs of
#: the simulator (seeds 1000-1015, 10 points per decade) to within ~10 %.
INDEPENDENT_PER_DECADE = 1.5
#: Reweighting passes of the least-squares fit (weights from the model, not from the noisy data).
FIT_ITERATIONS = 4


def _first_run(mask: npt.NDArray[np.bool_]) -> npt.NDArray[np.intp]:
    """Indices of the first contiguous run of True in ``mask`` (empty if none)."""
    idx = np.flatnonzero(mask)
    if len(idx) == 0:
        return idx
    breaks = np.flatnonzero(np.diff(idx) > 1)
    end = breaks[0] + 1 if len(breaks) else len(idx)
    return idx[:end]


def _edf(n_samples: float, m: FloatArray, alpha: FloatArray) -> FloatArray:
    """Equivalent degrees of freedom of the overlapping AVAR (NIST SP 1065 Table 5).

    ``alpha`` is the exponent of the frequency PSD (0 white, -1 flicker, -2 random walk), real
    valued: the EDF is interpolated linearly between the integer cases (allantools ``edf_simple``).
    """
    out = np.empty(len(m))
    for i, (mi, ai) in enumerate(zip(m, np.clip(alpha, -2.0, 0.0), strict=True)):
        lo = math.floor(ai)
        hi = min(lo + 1, 0)
        w = ai - lo
        e_lo = float(allantools.edf_simple(n_samples, mi, lo))
        e_hi = float(allantools.edf_simple(n_samples, mi, hi))
        out[i] = (1.0 - w) * e_lo + w * e_hi
    return np.maximum(out, 1.0)


def _wls_nonneg(a: FloatArray, y: FloatArray, sigma: FloatArray) -> tuple[FloatArray, FloatArray]:
    """Weighted least squares ``a x ~ y`` with ``x >= 0``; returns ``x`` and its covariance."""
    aw = a / sigma[:, None]
    yw = y / sigma
    scale = np.linalg.norm(aw, axis=0)
    x_s, _ = nnls(aw / scale, yw)
    x = x_s / scale
    normal = (aw / scale).T @ (aw / scale)
    cov = np.linalg.pinv(normal) / np.outer(scale, scale)
    return x, cov


def fit_allan(curve: AllanCurve) -> AllanParams:
    """Fit ``N``, ``B`` and ``K`` to a whole Allan deviation curve (see the module docstring).

    Parameters
    ----------
    curve : AllanCurve
        The Allan deviation of one axis, SI, as :func:`allan_deviation` returns it (averaging
        times integer multiples of the sample interval, overlapping estimator).

    Returns
    -------
    AllanParams
        The terms, SI, with their 1-sigma uncertainties, and NaN and a note for the ones the
        record cannot identify.
    """
    tau, sig = curve.tau_s, curve.adev
    ltau, lsig = np.log(tau), np.log(sig)
    slope = curve.slope
    notes: list[str] = []

    # --- record facts for the error bars: tau = m tau0, n_terms = M - 2m ------------------
    if len(tau) >= 2 and curve.n_terms[0] != curve.n_terms[-1]:
        tau0 = 2.0 * (tau[-1] - tau[0]) / (curve.n_terms[0] - curve.n_terms[-1])
    else:
        tau0 = float(tau[0])
    m = np.maximum(np.round(tau / tau0), 1.0)
    n_samples = float(curve.n_terms[0] + 2.0 * m[0])

    # --- weighted least squares on the Allan variance -------------------------------------
    design = np.column_stack([1.0 / tau, np.ones_like(tau), tau / 3.0])
    avar = sig**2
    model = avar.copy()
    x = np.zeros(3)
    cov = np.zeros((3, 3))
    for _ in range(FIT_ITERATIONS):
        mslope = np.gradient(np.log(model), ltau) if len(tau) >= 2 else np.full(len(tau), -0.5)
        edf = _edf(n_samples, m, -2.0 * mslope - 1.0)
        x, cov = _wls_nonneg(design, avar, model * np.sqrt(2.0 / edf))
        model = np.maximum(design @ x, 1e-300)
    edf = _edf(n_samples, m, -2.0 * np.gradient(np.log(model), ltau) - 1.0)
    resid = (avar - model) / (model * np.sqrt(2.0 / edf))
    n_free = int(np.count_nonzero(x > 0.0))
    chi2_red = float(np.sum(resid**2) / max(len(tau) - n_free, 1))
    decades = math.log10(tau[-1] / tau[0]) if len(tau) >= 2 else 1.0
    per_decade = max((len(tau) - 1) / max(decades, 1e-9), INDEPENDENT_PER_DECADE)
    # correlated points, and a poor fit (unmodelled noise), widen the error bars
    cov = cov * (per_decade / INDEPENDENT_PER_DECADE) * max(1.0, chi2_red)
    var_sd = np.sqrt(np.maximum(np.diag(cov), 0.0))

    def term(k: int, factor: float) -> tuple[float, float, float]:
        """Value, 1-sigma and relative 1-sigma of ``sqrt(x_k) / factor`` (delta method)."""
        value = math.sqrt(float(x[k])) / factor
        if x[k] <= 0.0:
            return 0.0, math.sqrt(float(var_sd[k])) / factor, math.inf
        sd = float(var_sd[k]) / (2.0 * math.sqrt(float(x[k]))) / factor
        return value, sd, sd / value

    n_fit, n_sd, n_rel = term(0, 1.0)
    b_fit, b_sd, b_rel = term(1, BI_FACTOR)
    k_fit, k_sd, k_rel = term(2, 1.0)

    # --- white noise -------------------------------------------------------------------------
    run = _first_run(np.abs(slope + 0.5) <= 0.15)
    # the fit puts no white term (e.g. vibration-dominated curve): read the point closest to -1/2
    i_read = run if len(run) else np.array([int(np.nanargmin(np.abs(slope + 0.5)))])
    n_read = float(np.exp(np.median(lsig[i_read] + 0.5 * (ltau[i_read] - math.log(N_TAU_S)))))
    n_ident = bool(len(run) > 0 and n_rel < IDENTIFIED_REL_SIGMA)
    if not n_ident:
        i_close = int(np.nanargmin(np.abs(slope + 0.5)))
        notes.append(
            f"no clear slope -1/2 region (closest slope {slope[i_close]:.2f} at tau={tau[i_close]:.3g} s, "
            f"fitted N +/- {100.0 * min(n_rel, 9.99):.0f} %): N is indicative only"
        )

    # --- bias instability --------------------------------------------------------------------
    upper = float(np.min(sig) / BI_FACTOR)
    periodic = bool(np.min(slope[tau <= tau[-1] / math.sqrt(10.0)], initial=0.0) < -0.75)
    rising = bool(np.max(slope[tau <= tau[-1] / math.sqrt(10.0)], initial=0.0) > 0.25) and k_fit == 0.0
    bias, bias_tau = math.nan, math.nan
    if periodic or rising:
        notes.append(
            "ADEV has slopes below -3/4 or rising parts the white/flicker/random-walk model does not "
            "have: periodic components (e.g. vibration) are present, N may include them and B is "
            f"not identifiable, only B <= {upper:.3g} (SI unit of the signal)"
        )
    elif b_rel < IDENTIFIED_REL_SIGMA:
        bias = b_fit
        tau_min = math.sqrt(3.0) * n_fit / k_fit if k_fit > 0.0 else math.inf
        bias_tau = float(np.clip(tau_min, tau[0], tau[-1]))
    else:
        notes.append(
            f"fitted B = {b_fit:.3g} +/- {b_sd:.2g} (SI unit of the signal) is not separated from "
            f"white noise and rate random walk by this record (relative uncertainty above "
            f"{IDENTIFIED_REL_SIGMA:.0%}; longest tau {tau[-1]:.3g} s): bias instability not "
            f"identifiable, only B <= {upper:.3g}"
        )

    # --- rate random walk --------------------------------------------------------------------
    rrw = k_fit if (k_rel < IDENTIFIED_REL_SIGMA and not periodic) else math.nan
    if not math.isfinite(rrw):
        notes.append("rate random walk not identifiable from this record (fit uncertainty too large)")

    return AllanParams(
        noise_density=n_fit if n_fit > 0.0 else n_read,
        noise_density_identified=n_ident,
        bias_instability=bias,
        bias_instability_tau_s=bias_tau,
        bias_instability_upper_bound=upper,
        rate_random_walk=rrw,
        notes=tuple(notes),
        noise_density_sigma=n_sd,
        bias_instability_fit=b_fit,
        bias_instability_sigma=b_sd,
        rate_random_walk_fit=k_fit,
        rate_random_walk_sigma=k_sd,
        fit_chi2_reduced=chi2_red,
    )


def residual_rms(samples: npt.ArrayLike) -> FloatArray:
    """RMS of the static residuals about the mean, per column (Dabove et al. Table 2).

    Parameters
    ----------
    samples : array_like, shape (n,) or (n, k)
        Static samples of one or more axes, any unit.

    Returns
    -------
    ndarray, shape (k,)
        ``sqrt(mean((y - mean(y))^2))`` per column, same unit as the input.
    """
    y = np.asarray(samples, dtype=np.float64)
    if y.ndim == 1:
        y = y[:, None]
    return np.sqrt(np.mean((y - y.mean(axis=0)) ** 2, axis=0))


# ------------------------------------------------------------------------------------------
# Noise model file
# ------------------------------------------------------------------------------------------

_FIELD_DOCS: dict[str, str] = {
    "gyro_noise_density_dps_rthz": "gyro white noise N (angle random walk), deg/s/sqrt(Hz) = deg/sqrt(s); "
    "ADEV(1 s) of the white part; per-sample std at f_s Hz = N*sqrt(f_s)",
    "gyro_bias_instability_dph": "gyro bias instability B (ADEV floor 0.664 B, whole-curve fit), deg/h",
    "gyro_bias_instability_tau_s": "averaging time of the fitted gyro ADEV minimum, s",
    "gyro_rate_random_walk_dps_per_rts": "gyro rate random walk K, ADEV = K*sqrt(tau/3), "
    "deg/s/sqrt(s) = deg/s^2/sqrt(Hz)",
    "accel_noise_density_ug_rthz": "accel white noise N (velocity random walk), ug/sqrt(Hz); "
    "ADEV(1 s) of the white part; per-sample std at f_s Hz = N*sqrt(f_s)",
    "accel_bias_instability_ug": "accel bias instability B (ADEV floor 0.664 B, whole-curve fit), ug",
    "accel_bias_instability_tau_s": "averaging time of the fitted accel ADEV minimum, s",
    "accel_rate_random_walk_ug_per_rts": "accel rate random walk K, ADEV = K*sqrt(tau/3), "
    "ug/sqrt(s) = ug/s/sqrt(Hz)",
    "sample_rate_hz": "sample rate of the characterised log, Hz",
    "duration_s": "length of the static record used, s",
    "source": "where the figures come from",
}


@dataclass(frozen=True)
class NoiseModel:
    """IMU noise parameters in datasheet units, as the Kalman engines and the simulator take them.

    One scalar per sensor (the largest over the three axes that identified the term, i.e. the
    conservative choice for filter tuning). NaN means *not identified from the data* (record too
    short): a consumer must then fall back to a datasheet value, never to zero. ``ug`` is
    micro-g with g = 9.80665 m/s^2. The SI properties (``gyro_noise_density`` ...) give the same
    numbers in rad and m/s^2.

    Attributes
    ----------
    gyro_noise_density_dps_rthz : float
        Gyro white-noise coefficient ``N`` (angle random walk), deg/s/sqrt(Hz), which equals
        deg/sqrt(s) (multiply by 60 for deg/sqrt(h)). It is the Allan deviation at
        ``tau = 1 s`` of the white part; a white sequence sampled at ``f_s`` has per-sample
        standard deviation ``N sqrt(f_s)``.
    gyro_bias_instability_dph : float
        Gyro bias instability ``B``, deg/h: the flat floor of the Allan deviation divided by
        ``sqrt(2 ln 2 / pi) = 0.664`` (IEEE Std 952); the PSD is ``B^2 / (2 pi f)``.
    gyro_bias_instability_tau_s : float
        Averaging time at which the gyro floor occurs, s. A first-order Gauss-Markov bias with
        correlation time ``T_c ~ tau / 1.89`` peaks there.
    gyro_rate_random_walk_dps_per_rts : float
        Gyro rate random walk ``K``, deg/s/sqrt(s) (= deg/s^2/sqrt(Hz)): the bias is a random
        walk whose increment over ``dt`` has standard deviation ``K sqrt(dt)``;
        ``ADEV(tau) = K sqrt(tau / 3)``.
    accel_noise_density_ug_rthz : float
        Accelerometer white-noise coefficient ``N`` (velocity random walk), ug/sqrt(Hz); per-sample
        standard deviation at ``f_s`` is ``N sqrt(f_s)``.
    accel_bias_instability_ug : float
        Accelerometer bias instability ``B`` = ADEV floor / 0.664, ug.
    accel_bias_instability_tau_s : float
        Averaging time at which the accelerometer floor occurs, s.
    accel_rate_random_walk_ug_per_rts : float
        Accelerometer rate random walk ``K``, ug/sqrt(s) (= ug/s/sqrt(Hz)).
    sample_rate_hz : float
        Sample rate of the log the model was estimated from, Hz (NaN if given by hand).
    duration_s : float
        Length of the static record used, s (NaN if given by hand).
    source : str
        Free text: file, time window, or "datasheet".
    """

    gyro_noise_density_dps_rthz: float
    gyro_bias_instability_dph: float
    gyro_rate_random_walk_dps_per_rts: float
    accel_noise_density_ug_rthz: float
    accel_bias_instability_ug: float
    accel_rate_random_walk_ug_per_rts: float
    gyro_bias_instability_tau_s: float = math.nan
    accel_bias_instability_tau_s: float = math.nan
    sample_rate_hz: float = math.nan
    duration_s: float = math.nan
    source: str = ""

    # --- SI views --------------------------------------------------------------------------
    @property
    def gyro_noise_density(self) -> float:
        """Gyro ``N``, rad/s/sqrt(Hz)."""
        return self.gyro_noise_density_dps_rthz * _DEG

    @property
    def gyro_bias_instability(self) -> float:
        """Gyro ``B``, rad/s."""
        return self.gyro_bias_instability_dph * _DEG / 3600.0

    @property
    def gyro_rate_random_walk(self) -> float:
        """Gyro ``K``, rad/s/sqrt(s)."""
        return self.gyro_rate_random_walk_dps_per_rts * _DEG

    @property
    def accel_noise_density(self) -> float:
        """Accelerometer ``N``, m/s^2/sqrt(Hz)."""
        return self.accel_noise_density_ug_rthz * _UG

    @property
    def accel_bias_instability(self) -> float:
        """Accelerometer ``B``, m/s^2."""
        return self.accel_bias_instability_ug * _UG

    @property
    def accel_rate_random_walk(self) -> float:
        """Accelerometer ``K``, m/s^2/sqrt(s)."""
        return self.accel_rate_random_walk_ug_per_rts * _UG

    @classmethod
    def from_si(
        cls,
        gyro: AllanParams | None,
        accel: AllanParams | None,
        sample_rate_hz: float = math.nan,
        duration_s: float = math.nan,
        source: str = "",
    ) -> NoiseModel:
        """Build a model from one gyro and one accelerometer :class:`AllanParams` (SI).

        Parameters
        ----------
        gyro, accel : AllanParams or None
            Terms of one axis each (e.g. the worst axis); None gives NaN fields.
        sample_rate_hz, duration_s : float
            Record facts, Hz and s.
        source : str
            Free text.

        Returns
        -------
        NoiseModel
        """
        nan = math.nan
        g = gyro
        a = accel
        return cls(
            gyro_noise_density_dps_rthz=g.noise_density / _DEG if g else nan,
            gyro_bias_instability_dph=g.bias_instability * 3600.0 / _DEG if g else nan,
            gyro_rate_random_walk_dps_per_rts=g.rate_random_walk / _DEG if g else nan,
            accel_noise_density_ug_rthz=a.noise_density / _UG if a else nan,
            accel_bias_instability_ug=a.bias_instability / _UG if a else nan,
            accel_rate_random_walk_ug_per_rts=a.rate_random_walk / _UG if a else nan,
            gyro_bias_instability_tau_s=g.bias_instability_tau_s if g else nan,
            accel_bias_instability_tau_s=a.bias_instability_tau_s if a else nan,
            sample_rate_hz=float(sample_rate_hz),
            duration_s=float(duration_s),
            source=source,
        )

    def to_toml(self) -> str:
        """The model as a TOML document (table ``[imu_noise]``, units in comments).

        NaN values are written as TOML ``nan``.
        """
        lines = [
            "# iotnav IMU noise model (Allan variance, IEEE Std 952). nan = not identified from the data.",
            "# ug = micro-g, g = 9.80665 m/s^2. Per-sample white-noise std at f_s Hz = N * sqrt(f_s).",
            "[imu_noise]",
        ]
        for f in fields(self):
            value = getattr(self, f.name)
            if isinstance(value, str):
                text = '"' + value.replace("\\", "\\\\").replace('"', '\\"').replace("\n", " ") + '"'
            elif math.isnan(value):
                text = "nan"
            elif math.isinf(value):
                text = "inf" if value > 0 else "-inf"
            else:
                text = repr(float(value))
            lines.append(f"{f.name} = {text}  # {_FIELD_DOCS[f.name]}")
        return "\n".join(lines) + "\n"

    @classmethod
    def from_toml(cls, text: str) -> NoiseModel:
        """Parse a TOML document written by :meth:`to_toml` (or by hand).

        The keys may sit in an ``[imu_noise]`` table or at the top level. Missing optional keys
        take their defaults; unknown keys are an error (a misspelt key must not pass silently).

        Parameters
        ----------
        text : str
            TOML text.

        Returns
        -------
        NoiseModel

        Raises
        ------
        ValueError
            On unknown or missing required keys, or non-numeric values.
        """
        doc: dict[str, Any] = tomllib.loads(text)
        table = doc.get("imu_noise", doc)
        if not isinstance(table, dict):
            raise ValueError("[imu_noise] must be a table")
        known = {f.name: f for f in fields(cls)}
        unknown = sorted(set(table) - set(known))
        if unknown:
            raise ValueError(f"unknown noise-model key(s): {', '.join(unknown)}; expected {', '.join(known)}")
        kwargs: dict[str, Any] = {}
        for name, value in table.items():
            if name == "source":
                kwargs[name] = str(value)
            elif isinstance(value, (int, float)) and not isinstance(value, bool):
                kwargs[name] = float(value)
            else:
                raise ValueError(f"noise-model key {name} must be a number, got {value!r}")
        try:
            return cls(**kwargs)
        except TypeError as exc:
            raise ValueError(f"incomplete noise model: {exc}") from None


# ------------------------------------------------------------------------------------------
# Whole-IMU characterisation
# ------------------------------------------------------------------------------------------

AXES = ("x", "y", "z")


@dataclass(frozen=True)
class Characterization:
    """Everything :func:`characterize` finds in a static IMU record (SI).

    Attributes
    ----------
    rate_hz : float
        Sample rate used, Hz.
    duration_s : float
        Record length, s.
    acc_rms : ndarray, shape (3,)
        RMS of the accelerometer static residuals per axis, m/s^2 (Table 2 form).
    gyro_rms : ndarray, shape (3,)
        RMS of the gyro static residuals per axis, rad/s.
    acc_curves, gyro_curves : tuple of AllanCurve
        Allan deviation per axis (m/s^2, rad/s).
    acc_params, gyro_params : tuple of AllanParams
        Noise terms per axis.
    model : NoiseModel
        Worst-axis summary in datasheet units.
    notes : tuple of str
        Remarks on the record (irregular sampling, short length).
    """

    rate_hz: float
    duration_s: float
    acc_rms: FloatArray
    gyro_rms: FloatArray
    acc_curves: tuple[AllanCurve, ...]
    gyro_curves: tuple[AllanCurve, ...]
    acc_params: tuple[AllanParams, ...]
    gyro_params: tuple[AllanParams, ...]
    model: NoiseModel
    notes: tuple[str, ...]


def _worst(params: tuple[AllanParams, ...]) -> AllanParams:
    """Per term, the largest identified value over the axes (NaN if none)."""

    def top(values: list[float]) -> float:
        finite = [v for v in values if math.isfinite(v)]
        return max(finite) if finite else math.nan

    nd = [p.noise_density for p in params if p.noise_density_identified]
    bi = [(p.bias_instability, p.bias_instability_tau_s) for p in params if math.isfinite(p.bias_instability)]
    b, b_tau = max(bi) if bi else (math.nan, math.nan)
    return AllanParams(
        noise_density=top(nd),
        noise_density_identified=bool(nd),
        bias_instability=b,
        bias_instability_tau_s=b_tau,
        bias_instability_upper_bound=top([p.bias_instability_upper_bound for p in params]),
        rate_random_walk=top([p.rate_random_walk for p in params]),
    )


def characterize(
    t: npt.ArrayLike,
    acc: npt.ArrayLike,
    gyro: npt.ArrayLike,
    source: str = "",
    per_decade: int = 10,
    max_tau_fraction: float = 0.1,
) -> Characterization:
    """Residual RMS, Allan deviation and noise terms of a static IMU record.

    Parameters
    ----------
    t : array_like, shape (n,)
        Sample times, s (the rate is ``(n - 1) / (t[-1] - t[0])``; samples are assumed evenly
        spaced, and a note says when they are not).
    acc : array_like, shape (n, 3)
        Specific force, m/s^2.
    gyro : array_like, shape (n, 3)
        Angular rate, rad/s.
    source : str
        Free text for :attr:`NoiseModel.source`.
    per_decade, max_tau_fraction :
        See :func:`allan_deviation`.

    Returns
    -------
    Characterization
    """
    tt = np.asarray(t, dtype=np.float64)
    a = np.asarray(acc, dtype=np.float64)
    w = np.asarray(gyro, dtype=np.float64)
    if a.shape != (len(tt), 3) or w.shape != (len(tt), 3):
        raise ValueError(f"expected t (n,), acc (n, 3), gyro (n, 3); got {tt.shape}, {a.shape}, {w.shape}")
    if len(tt) < 20:
        raise ValueError(f"only {len(tt)} IMU samples in the window; need at least 20")
    duration = float(tt[-1] - tt[0])
    if not duration > 0:
        raise ValueError("the IMU time stamps do not increase")
    rate = (len(tt) - 1) / duration
    notes: list[str] = []
    dt = np.diff(tt)
    irregular = np.abs(dt - 1.0 / rate) > 0.5 / rate
    if np.any(irregular):
        notes.append(
            f"{np.count_nonzero(irregular)} of {len(dt)} sample intervals differ from 1/rate by more "
            "than half an interval (duplicates or gaps); the Allan deviation assumes even sampling"
        )
    if duration < 3600.0:
        notes.append(
            f"record is {duration:.1f} s long: ADEV reaches tau = {max_tau_fraction * duration:.3g} s, so "
            "the noise density is identified but bias instability and rate random walk need hours"
        )
    acc_curves = tuple(allan_deviation(a[:, i], rate, per_decade, max_tau_fraction) for i in range(3))
    gyro_curves = tuple(allan_deviation(w[:, i], rate, per_decade, max_tau_fraction) for i in range(3))
    acc_params = tuple(fit_allan(c) for c in acc_curves)
    gyro_params = tuple(fit_allan(c) for c in gyro_curves)
    model = NoiseModel.from_si(
        _worst(gyro_params), _worst(acc_params), sample_rate_hz=rate, duration_s=duration, source=source
    )
    return Characterization(
        rate_hz=rate,
        duration_s=duration,
        acc_rms=residual_rms(a),
        gyro_rms=residual_rms(w),
        acc_curves=acc_curves,
        gyro_curves=gyro_curves,
        acc_params=acc_params,
        gyro_params=gyro_params,
        model=model,
        notes=tuple(notes),
    )
