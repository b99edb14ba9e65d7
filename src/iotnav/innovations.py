"""Innovation records of the Kalman engines: :class:`InnovationLog` and whitening.

An engine built with ``record_innovations`` keeps, per measurement type, the innovation
``nu = z - h(x)`` and its covariance ``S = H P H^T + R`` of every attempted update in an
:class:`InnovationLog`. The whiteness and NIS studies of :mod:`iotnav.eval.consistency`
read them (that module re-exports both names); the engines import this module, not the
evaluation layer.
"""

from __future__ import annotations

import math

import numpy as np
import numpy.typing as npt

FloatArray = npt.NDArray[np.float64]

__all__ = ["InnovationLog", "whiten_innovations"]


def whiten_innovations(y: npt.ArrayLike, S: npt.ArrayLike) -> FloatArray:
    """Whitened innovations ``L^-1 nu`` with ``S = L L^T`` (lower Cholesky factor).

    For a consistent filter the result has unit covariance. Component ``i`` is the
    innovation of measurement ``i`` given the earlier ones, in units of its own standard
    deviation (for a diagonal ``S``, ``nu_i / sqrt(S_ii)``); ``|L^-1 nu|^2`` is the NIS.

    Parameters
    ----------
    y : array_like
        Innovations, ``(K, m)`` (or ``(m,)``), in the measurement's units (e.g. m in NED for a
        GNSS position). Rows of a smaller measurement may be NaN-padded at the end.
    S : array_like
        Innovation covariances ``H P H^T + R``, ``(K, m, m)`` (or ``(m, m)``), same units
        squared; the NaN-padded rows and columns of a smaller measurement are ignored.

    Returns
    -------
    numpy.ndarray
        Whitened innovations, dimensionless, shape of ``y``; NaN where ``y`` is NaN or ``S`` is
        not positive definite.

    Raises
    ------
    ValueError
        When the shapes of ``y`` and ``S`` do not match.
    """
    y_a = np.asarray(y, dtype=float)
    S_a = np.asarray(S, dtype=float)
    single = y_a.ndim == 1
    y2 = np.atleast_2d(y_a)
    S3 = S_a[None] if S_a.ndim == 2 else S_a
    if S3.shape != (y2.shape[0], y2.shape[1], y2.shape[1]):
        raise ValueError(f"whiten_innovations: y {y_a.shape} and S {S_a.shape} do not match")
    w = np.full(y2.shape, np.nan)
    for k in range(y2.shape[0]):
        m = int(np.sum(np.isfinite(y2[k])))
        if m == 0 or not np.all(np.isfinite(y2[k, :m])):
            continue
        try:
            L = np.linalg.cholesky(S3[k, :m, :m])
        except np.linalg.LinAlgError:
            continue
        w[k, :m] = np.linalg.solve(L, y2[k, :m])
    return w[0] if single else w


class InnovationLog:
    """Innovations and innovation covariances of one measurement type, in growing numpy storage.

    Filled by :class:`~iotnav.engines.eskf.EskfEngine` and :class:`~iotnav.engines.qekf.QekfEngine`
    when built with ``record_innovations`` (one row per
    attempted update, accepted or gated out, O(1) amortised). A measurement with fewer than
    ``m_max`` rows (GNSS speed and course: 2) is NaN-padded.

    Parameters
    ----------
    m_max : int, optional
        Largest measurement size.
    capacity : int, optional
        Initial number of rows (doubled when full).
    """

    def __init__(self, m_max: int = 3, capacity: int = 256) -> None:
        self.m_max = m_max
        self._n = 0
        self._t = np.empty(capacity)
        self._y = np.empty((capacity, m_max))
        self._S = np.empty((capacity, m_max, m_max))
        self._acc = np.empty(capacity, dtype=bool)

    def __len__(self) -> int:
        return self._n

    def append(self, t: float, y: FloatArray, S: FloatArray, accepted: bool) -> None:
        """Add one update: time (s), innovation ``(m,)`` and its covariance ``(m, m)``."""
        k = self._n
        if k == self._t.shape[0]:
            grow = max(k, 16)
            self._t = np.concatenate([self._t, np.empty(grow)])
            self._y = np.concatenate([self._y, np.empty((grow, self.m_max))])
            self._S = np.concatenate([self._S, np.empty((grow, self.m_max, self.m_max))])
            self._acc = np.concatenate([self._acc, np.empty(grow, dtype=bool)])
        m = y.shape[0]
        self._t[k] = t
        self._y[k] = math.nan
        self._y[k, :m] = y
        self._S[k] = math.nan
        self._S[k, :m, :m] = S
        self._acc[k] = accepted
        self._n = k + 1

    @property
    def t(self) -> FloatArray:
        """Update times, s, ``(K,)``."""
        return self._t[: self._n]

    @property
    def y(self) -> FloatArray:
        """Innovations ``z - h(x)`` before the update, measurement units (NED m, m/s), ``(K, m_max)``."""
        return self._y[: self._n]

    @property
    def S(self) -> FloatArray:
        """Innovation covariances ``H P H^T + R``, measurement units squared, ``(K, m_max, m_max)``."""
        return self._S[: self._n]

    @property
    def accepted(self) -> npt.NDArray[np.bool_]:
        """False for updates rejected by the NIS gate, ``(K,)``."""
        return self._acc[: self._n]

    def whitened(self) -> FloatArray:
        """``L^-1 y`` with ``S = L L^T``, dimensionless, ``(K, m_max)`` (unit covariance if consistent).

        See :func:`whiten_innovations`.
        """
        return whiten_innovations(self.y, self.S)
