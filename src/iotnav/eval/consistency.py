"""Filter consistency: whitened innovations and the whiteness (autocorrelation) test.

A consistent Kalman filter's innovations ``nu_k = z_k - h(x_k|k-1)`` are zero-mean, have the
covariance ``S_k`` the filter computes, and are white: uncorrelated from one update to the
next (Bar-Shalom, Li, Kirubarajan 2001, "Estimation with Applications to Tracking and
Navigation", §5.4). The NIS ``nu^T S^-1 nu`` tests the first two; :func:`innovation_autocorrelation`
tests the third with the time-average autocorrelation of the normalised innovations, pooled
over Monte Carlo runs (§5.4.2 and §5.4.3).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt
from scipy.stats import chi2, norm

from iotnav.innovations import InnovationLog, whiten_innovations

FloatArray = npt.NDArray[np.float64]

__all__ = [
    "Autocorrelation",
    "InnovationLog",
    "epoch_grid",
    "innovation_autocorrelation",
    "whiten_innovations",
]


def epoch_grid(t: npt.ArrayLike, values: npt.ArrayLike, rate_hz: float, skip: int = 0) -> FloatArray:
    """Rows of ``values`` on the regular epoch grid that starts at ``t[0]`` (NaN: no sample).

    The series that :func:`innovation_autocorrelation` expects: a lag then always spans the
    same time, whatever updates were missing.

    Parameters
    ----------
    t : array_like
        ``(K,)`` times of the rows, s, increasing.
    values : array_like
        ``(K, m)`` rows (e.g. whitened innovations).
    rate_hz : float
        Epoch rate, Hz; each time goes to the nearest epoch.
    skip : int, optional
        Leading rows to blank (NaN), e.g. an initial transient.

    Returns
    -------
    numpy.ndarray
        ``(N, m)``, ``N`` = epochs from ``t[0]`` to ``t[-1]``.
    """
    tt = np.asarray(t, dtype=float)
    w = np.asarray(values, dtype=float)
    if tt.size == 0:
        return np.empty((0, w.shape[1] if w.ndim == 2 else 1))
    k = np.round((tt - tt[0]) * rate_hz).astype(int)
    g = np.full((int(k[-1]) + 1, w.shape[1]), np.nan)
    g[k] = w
    g[: int(k[min(skip, len(k) - 1)])] = np.nan
    return g


@dataclass(frozen=True)
class Autocorrelation:
    """Result of :func:`innovation_autocorrelation`.

    Attributes
    ----------
    lags : numpy.ndarray
        Lags, in samples of the series, ``(L,)``.
    rho : numpy.ndarray
        Normalised autocorrelation per lag and component, ``(L, m)``, dimensionless.
    n_pairs : numpy.ndarray
        Number of sample pairs behind each entry of ``rho``, ``(L, m)``.
    band : numpy.ndarray
        Half-width of the acceptance interval of each entry, ``z / sqrt(n_pairs)``, ``(L, m)``.
    """

    lags: npt.NDArray[np.int64]
    rho: FloatArray
    n_pairs: npt.NDArray[np.int64]
    band: FloatArray

    @property
    def inside(self) -> npt.NDArray[np.bool_]:
        """``|rho| <= band`` per lag and component."""
        return np.asarray(np.abs(self.rho) <= self.band)

    @property
    def portmanteau(self) -> FloatArray:
        """Box-Pierce statistic over all lags, ``Q = sum_l n_l rho_l^2``, per component, ``(m,)``.

        One test of all lags at once (Box and Pierce 1970, "Distribution of residual
        autocorrelations in autoregressive-integrated moving average time series models",
        JASA 65): under whiteness ``n_l rho_l^2`` is about chi-square with 1 degree of freedom
        and independent across lags, so ``Q`` is about chi-square with ``len(lags)`` degrees of
        freedom (:meth:`portmanteau_threshold`). Testing ``L`` lags one by one against their
        95 % band leaves, on average, ``0.05 L`` of them outside by chance.
        """
        return np.asarray(np.sum(self.n_pairs * self.rho**2, axis=0), dtype=float)

    def portmanteau_threshold(self, probability: float = 0.95, familywise: bool = False) -> float:
        """Upper chi-square quantile of :attr:`portmanteau` (``len(lags)`` degrees of freedom).

        ``familywise``: ``probability`` is that of all ``m`` components passing together when
        white (Sidak: each at ``probability ** (1 / m)``). Per component at 95 %, a white
        3-component innovation fails somewhere in 14 % of the tests (0.95^3 = 0.86); together
        at 95 % each is tested at 98.3 % (chi-square(10): 21.7 in place of 18.3).
        """
        p = probability ** (1.0 / self.rho.shape[1]) if familywise else probability
        return float(chi2.ppf(p, self.lags.size))


def innovation_autocorrelation(
    runs: Sequence[npt.ArrayLike], lags: Sequence[int] | npt.ArrayLike, probability: float = 0.95
) -> Autocorrelation:
    """Time-average normalised autocorrelation of innovations, pooled over Monte Carlo runs.

    Per lag ``l`` and component ``c`` (Bar-Shalom et al. 2001, §5.4.3, time average of one
    run, with the sums taken over all runs as in the Monte Carlo tests of §5.4.2)::

        rho(l) = sum_r sum_k nu_r(k) nu_r(k+l) / sqrt(sum_r sum_k nu_r(k)^2 * sum_r sum_k nu_r(k+l)^2)

    over the pairs where both samples are finite. Under the hypothesis that the innovations
    are zero-mean and white, ``rho(l)`` is, for many pairs ``n``, normal with mean 0 and
    variance ``1 / n``: the acceptance interval at ``probability`` is
    ``+-z / sqrt(n)`` (``z = 1.96`` at 95 %). The statistic is scale-invariant, so the
    innovations need only be normalised per component (e.g. :func:`whiten_innovations`); an
    over- or under-estimated ``S`` does not change it.

    Parameters
    ----------
    runs : sequence of array_like
        One series per run, ``(K_r, m)`` or ``(K_r,)``, sampled on a regular grid (e.g. one
        row per GNSS epoch); NaN marks a missing sample (no update, or rejected), so that a
        lag always spans the same time.
    lags : sequence of int
        Lags to evaluate, in samples (>= 1).
    probability : float, optional
        Two-sided probability of the acceptance interval.

    Returns
    -------
    Autocorrelation
        ``rho``, the pair counts and the band half-width per lag and component.

    Raises
    ------
    ValueError
        For no runs, runs of different widths, or a lag below 1.
    """
    series = [np.asarray(r, dtype=float) for r in runs]
    if not series:
        raise ValueError("innovation_autocorrelation: no runs")
    series = [s[:, None] if s.ndim == 1 else s for s in series]
    m = series[0].shape[1]
    if any(s.ndim != 2 or s.shape[1] != m for s in series):
        raise ValueError("innovation_autocorrelation: every run must have the same components")
    lag_a = np.asarray(lags, dtype=np.int64).ravel()
    if lag_a.size == 0 or np.any(lag_a < 1):
        raise ValueError("innovation_autocorrelation: lags must be >= 1")
    z = float(norm.ppf(0.5 + 0.5 * probability))
    rho = np.full((lag_a.size, m), np.nan)
    n_pairs = np.zeros((lag_a.size, m), dtype=np.int64)
    for i, lag in enumerate(lag_a):
        num = np.zeros(m)
        d0 = np.zeros(m)
        d1 = np.zeros(m)
        for s in series:
            if s.shape[0] <= lag:
                continue
            a, b = s[:-lag], s[lag:]
            ok = np.isfinite(a) & np.isfinite(b)
            a0, b0 = np.where(ok, a, 0.0), np.where(ok, b, 0.0)
            num += np.sum(a0 * b0, axis=0)
            d0 += np.sum(a0 * a0, axis=0)
            d1 += np.sum(b0 * b0, axis=0)
            n_pairs[i] += np.sum(ok, axis=0)
        den = np.sqrt(d0 * d1)
        good = den > 0.0
        rho[i, good] = num[good] / den[good]
    with np.errstate(divide="ignore"):
        band = np.where(n_pairs > 0, z / np.sqrt(np.maximum(n_pairs, 1)), np.nan)
    return Autocorrelation(lags=lag_a, rho=rho, n_pairs=n_pairs, band=band)
