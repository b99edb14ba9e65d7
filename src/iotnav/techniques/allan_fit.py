"""Allan deviation of a static IMU record and its three-term fit (:mod:`iotnav.techniques.allan`).

The overlapping Allan deviation (IEEE Std 952-1997 Annex C, computed by ``allantools.oadev``),
the non-negative weighted least-squares fit of ``sigma^2(tau) = N^2 / tau + (0.664 B)^2 +
K^2 tau / 3`` with NIST SP 1065 degrees of freedom, and the static residual RMS of Dabove et al.
(2016), Table 2. The model, its identification rules and references are stated in
:mod:`iotnav.techniques.allan`. Units SI: rad/s or m/s^2 for rates, s for averaging times.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

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
