"""Magnetometer hard- and soft-iron calibration from a log that turns the device about all axes.

The engines take a calibrated magnetometer, ``m_cal = W^-1 (m_raw - h)`` (``mag_hard_iron_ut``
``h``, ``mag_soft_iron`` ``W``): ``eskf`` leaves an uncalibrated one out, because its heading
can be tens of degrees off. This module finds ``h`` and ``W`` from the raw samples alone.

Model: in a constant field of magnitude ``B`` the raw samples lie on the ellipsoid
``(m - h)^T A (m - h) = 1`` with ``A = W^-T W^-1 / B^2``. The algebraic least-squares fit of the
quadric ``m^T Q m + 2 b^T m = 1`` (nine unknowns, linear; the general ellipsoid fit of
e.g. Li and Griffiths 2004, "Least squares ellipsoid specific fitting", without their
ellipsoid-specific constraint, which the coverage check below replaces) gives
``h = -Q^-1 b`` and ``A = Q / (1 + h^T Q h)``; then ``W^-1 = B sqrtm(A)`` (symmetric soft iron,
the usual convention: a rotation in ``W`` is not observable from the magnitudes) with ``B`` the
geometric-mean radius, ``det(A)^(-1/6)``, so that ``W`` keeps the volume and the calibrated
field keeps the raw data's scale.

Coverage. The fit needs the field seen from all directions (a "figure 8" with a handheld, or a
full turn on every axis). A vehicle turns about one axis only: the samples lie on a circle, the
quadric is not determined, and the fit is refused (:class:`CalibrationError`) with the
coverage figure, taken on the raw samples before any fit (a fit to degenerate data can spread
its own calibrated directions): the smallest eigenvalue of the samples' covariance over their
mean square norm (1/3 for directions spread over the sphere about a small offset, 0 on a
circle, about ``(noise / field)^2`` at a standstill); at least ``min_coverage`` (0.05) is
required.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import numpy.typing as npt
from scipy.linalg import sqrtm

__all__ = ["CalibrationError", "MagCalibration", "fit_mag_calibration"]

FloatArray = npt.NDArray[np.float64]


class CalibrationError(ValueError):
    """The samples do not determine a calibration (too few, or too little rotation)."""


@dataclass(frozen=True)
class MagCalibration:
    """A fitted magnetometer calibration, in the form the engines take.

    Attributes
    ----------
    hard_iron_ut : numpy.ndarray
        Offset ``h`` in the sensor frame, uT (3).
    soft_iron : numpy.ndarray
        Matrix ``W`` (3, 3), symmetric, unit determinant: ``m_cal = W^-1 (m_raw - h)``.
    field_ut : float
        Magnitude of the calibrated field, uT.
    residual_ut : float
        RMS of ``|m_cal| - field_ut`` over the samples, uT.
    raw_spread_ut : float
        RMS of ``|m_raw| - mean |m_raw|``, uT (what the calibration removed).
    coverage : float
        Smallest eigenvalue of the raw samples' covariance over their mean square norm (1/3 at
        best).
    n_samples : int
        Samples used.
    n_nonfinite : int
        Samples left out for a non-finite value.
    """

    hard_iron_ut: FloatArray
    soft_iron: FloatArray
    field_ut: float
    residual_ut: float
    raw_spread_ut: float
    coverage: float
    n_samples: int
    n_nonfinite: int = 0

    def apply(self, m_raw: npt.ArrayLike) -> FloatArray:
        """Calibrated field ``W^-1 (m_raw - h)`` of ``(N, 3)`` raw samples, uT."""
        m = np.asarray(m_raw, dtype=np.float64) - self.hard_iron_ut
        return np.asarray(np.linalg.solve(self.soft_iron, m.T).T, dtype=np.float64)

    def to_config(self) -> dict[str, list[float]]:
        """``mag_hard_iron_ut`` and ``mag_soft_iron`` (row-major) as the engines' TOML takes them."""
        return {
            "mag_hard_iron_ut": [float(v) for v in self.hard_iron_ut],
            "mag_soft_iron": [float(v) for v in self.soft_iron.ravel()],
        }


def fit_mag_calibration(
    m_raw: npt.ArrayLike, min_coverage: float = 0.05, min_samples: int = 50
) -> MagCalibration:
    """Fit hard and soft iron to raw magnetometer samples (module docstring).

    Parameters
    ----------
    m_raw : array_like
        Raw samples ``(N, 3)`` in the sensor frame, uT (any consistent unit; the results are in
        it). Rows with a non-finite value are left out and counted (``n_nonfinite``).
    min_coverage : float
        Smallest accepted coverage (module docstring; at most 1/3).
    min_samples : int
        Fewest finite samples accepted.

    Returns
    -------
    MagCalibration

    Raises
    ------
    CalibrationError
        Too few samples, a quadric that is not an ellipsoid, too little rotation, or a fit
        that leaves the field's magnitude varying more than the raw samples' (not an
        ellipsoid: a changing field, or not magnetometer data).
    """
    m = np.asarray(m_raw, dtype=np.float64)
    if m.ndim != 2 or m.shape[1] != 3:
        raise CalibrationError(f"expected (N, 3) magnetometer samples, got shape {m.shape}")
    finite = np.all(np.isfinite(m), axis=1)
    n_nonfinite = int(np.count_nonzero(~finite))
    m = m[finite]
    if len(m) < min_samples:
        raise CalibrationError(f"{len(m)} finite magnetometer samples; at least {min_samples} needed")
    lam = np.linalg.eigvalsh(np.cov(m.T))
    scale = float(np.mean(np.sum(m * m, axis=1)))
    coverage = float(lam.min() / scale) if scale > 0.0 else 0.0
    if coverage < min_coverage:
        raise CalibrationError(
            f"the log turns the magnetometer about too few axes (coverage {coverage:.3f}, at least "
            f"{min_coverage} needed; a vehicle that only yaws gives ~0): record a calibration "
            "turning the device about all its axes (a figure 8)"
        )
    # centre and scale for conditioning; the fit is done on s = (m - c) / r
    c = m.mean(axis=0)
    r = float(np.sqrt(np.mean(np.sum((m - c) ** 2, axis=1))))
    if not r > 0.0:
        raise CalibrationError("the magnetometer samples do not vary: the device did not turn")
    s = (m - c) / r
    x, y, z = s[:, 0], s[:, 1], s[:, 2]
    D = np.column_stack([x * x, y * y, z * z, 2 * x * y, 2 * x * z, 2 * y * z, 2 * x, 2 * y, 2 * z])
    v, *_ = np.linalg.lstsq(D, np.ones(len(s)), rcond=None)
    Q = np.array([[v[0], v[3], v[4]], [v[3], v[1], v[5]], [v[4], v[5], v[2]]])
    b = v[6:9]
    try:
        h_s = -np.linalg.solve(Q, b)
    except np.linalg.LinAlgError as exc:
        raise CalibrationError("the samples do not determine an ellipsoid (too little rotation)") from exc
    k = 1.0 + float(h_s @ Q @ h_s)
    A_s = Q / k
    eig = np.linalg.eigvalsh(A_s)
    if not (k > 0.0 and eig.min() > 0.0):
        raise CalibrationError(
            "the samples do not lie on an ellipsoid (too little rotation, or a changing field); "
            "turn the device about all its axes"
        )
    # back to the raw units: (m - h)^T A (m - h) = 1 with h = c + r h_s, A = A_s / r^2
    h = c + r * h_s
    A = A_s / (r * r)
    B = float(np.prod(np.linalg.eigvalsh(A))) ** (-1.0 / 6.0)
    W_inv = np.real(sqrtm(A)) * B
    W_inv = 0.5 * (W_inv + W_inv.T)
    W = np.linalg.inv(W_inv)
    W_sym = 0.5 * (W + W.T)
    norm = np.linalg.norm(np.linalg.solve(W_sym, (m - h).T).T, axis=1)
    raw_norm = np.linalg.norm(m, axis=1)
    residual = float(np.sqrt(np.mean((norm - B) ** 2)))
    raw_spread = float(np.sqrt(np.mean((raw_norm - raw_norm.mean()) ** 2)))
    if residual > raw_spread:
        raise CalibrationError(
            f"the fit leaves the field's magnitude varying by {residual:.2f} uT RMS, more than the raw "
            f"samples' {raw_spread:.2f}: the samples do not lie on an ellipsoid (a changing field, "
            "or not magnetometer data)"
        )
    return MagCalibration(
        hard_iron_ut=h,
        soft_iron=W_sym,
        field_ut=B,
        residual_ut=residual,
        raw_spread_ut=raw_spread,
        coverage=coverage,
        n_samples=len(m),
        n_nonfinite=n_nonfinite,
    )
