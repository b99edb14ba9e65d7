"""Nominal state of the ``eskf`` engine, the error-state reset (inject) and sensor compensation."""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numba
import numpy as np
import numpy.typing as npt

from iotnav.engines.eskf.layout import (
    ATT,
    ATT_0,
    BA,
    BA_0,
    BG,
    BG_0,
    GNE,
    GNE_0,
    GNM,
    GNM_0,
    MNT,
    MNT_0,
    N_FULL,
    POS,
    POS_0,
    SA,
    SA_0,
    SG,
    SG_0,
    VEL,
    VEL_0,
)
from iotnav.strapdown import rodrigues as _rodrigues

FloatArray = npt.NDArray[np.float64]


def skew(a: FloatArray) -> FloatArray:
    """``[a x]`` of a 3-vector."""
    return np.array([[0.0, -a[2], a[1]], [a[2], 0.0, -a[0]], [-a[1], a[0], 0.0]])


def dcm_to_rotvec(C: FloatArray) -> FloatArray:
    """Rotation vector (rad) of a rotation matrix (inverse of ``rotvec_to_dcm``)."""
    c = max(-1.0, min(1.0, 0.5 * (C[0, 0] + C[1, 1] + C[2, 2] - 1.0)))
    a = math.acos(c)
    w = np.array([C[2, 1] - C[1, 2], C[0, 2] - C[2, 0], C[1, 0] - C[0, 1]])
    if a < 1e-6:
        return 0.5 * w
    if a > math.pi - 1e-6:  # near pi: axis from the symmetric part
        M = 0.5 * (C + np.eye(3))
        k = int(np.argmax(np.diag(M)))
        axis = M[:, k] / math.sqrt(max(M[k, k], 1e-300))
        return a * axis / np.linalg.norm(axis)
    return a / (2.0 * math.sin(a)) * w


# ----------------------------------------------------------------------------- nominal state
@dataclass
class Nominal:
    """Nominal (total) navigation state; arrays are updated in place by the engine.

    Attributes
    ----------
    C_nb : numpy.ndarray
        Sensor attitude, maps ``b`` to ``n``.
    v_n, p_n : numpy.ndarray
        IMU velocity (m/s) and position (m, NED about the origin).
    b_g, b_a : numpy.ndarray
        Gyro (rad/s) and accelerometer (m/s^2) biases in ``b``.
    s_g, s_a : numpy.ndarray
        Scale-factor errors (dimensionless).
    C_vb : numpy.ndarray
        Mounting rotation, maps ``b`` to ``v``.
    e_n : numpy.ndarray
        Time-correlated GNSS position error as the receiver reports it (smoothed), m, ``n``.
    e_gm : numpy.ndarray
        The Gauss-Markov error before the receiver's smoothing (what drives ``e_n``), m, ``n``.
    """

    C_nb: FloatArray = field(default_factory=lambda: np.eye(3))
    v_n: FloatArray = field(default_factory=lambda: np.zeros(3))
    p_n: FloatArray = field(default_factory=lambda: np.zeros(3))
    b_g: FloatArray = field(default_factory=lambda: np.zeros(3))
    b_a: FloatArray = field(default_factory=lambda: np.zeros(3))
    s_g: FloatArray = field(default_factory=lambda: np.zeros(3))
    s_a: FloatArray = field(default_factory=lambda: np.zeros(3))
    C_vb: FloatArray = field(default_factory=lambda: np.eye(3))
    e_n: FloatArray = field(default_factory=lambda: np.zeros(3))
    e_gm: FloatArray = field(default_factory=lambda: np.zeros(3))

    def copy(self) -> Nominal:
        """Deep copy."""
        return Nominal(*(np.array(getattr(self, k), dtype=float) for k in self.__dataclass_fields__))

    def arrays(
        self,
    ) -> tuple[
        FloatArray,
        FloatArray,
        FloatArray,
        FloatArray,
        FloatArray,
        FloatArray,
        FloatArray,
        FloatArray,
        FloatArray,
        FloatArray,
    ]:
        """``(C_nb, v_n, p_n, b_g, b_a, s_g, s_a, C_vb, e_n, e_gm)``, the arguments of the compiled kernels."""
        return (
            self.C_nb,
            self.v_n,
            self.p_n,
            self.b_g,
            self.b_a,
            self.s_g,
            self.s_a,
            self.C_vb,
            self.e_n,
            self.e_gm,
        )


@numba.njit(cache=True)
def _rotate_left(x: float, y: float, z: float, C: FloatArray) -> None:
    """``C <- exp([theta x]) C`` in place for the rotation vector ``theta = (x, y, z)`` (rad)."""
    r = _rodrigues(x, y, z)
    for j in range(3):
        c0, c1, c2 = C[0, j], C[1, j], C[2, j]
        C[0, j] = r[0] * c0 + r[1] * c1 + r[2] * c2
        C[1, j] = r[3] * c0 + r[4] * c1 + r[5] * c2
        C[2, j] = r[6] * c0 + r[7] * c1 + r[8] * c2


@numba.njit(cache=True)
def inject_arrays(
    dx: FloatArray,
    C_nb: FloatArray,
    v_n: FloatArray,
    p_n: FloatArray,
    b_g: FloatArray,
    b_a: FloatArray,
    s_g: FloatArray,
    s_a: FloatArray,
    C_vb: FloatArray,
    e_n: FloatArray,
    e_gm: FloatArray,
) -> None:
    """:func:`inject` on the nominal state's arrays, in place (compiled; the engine's kernels call it).

    Parameters
    ----------
    dx : numpy.ndarray
        Error-state estimate (:data:`N_BASE` or :data:`N_FULL` elements; layout above).
    C_nb, v_n, p_n, b_g, b_a, s_g, s_a, C_vb, e_n, e_gm : numpy.ndarray
        The :class:`Nominal` fields (attitude ``b`` to ``n``; velocity m/s and position m in
        ``n``; gyro rad/s and accelerometer m/s^2 biases in ``b``; scale factors; mount ``b``
        to ``v``; smoothed and unsmoothed GNSS error m in ``n``), updated in place.
    """
    for i in range(3):
        p_n[i] += dx[POS_0 + i]
        v_n[i] += dx[VEL_0 + i]
        b_g[i] += dx[BG_0 + i]
        b_a[i] += dx[BA_0 + i]
        e_n[i] += dx[GNE_0 + i]
        e_gm[i] += dx[GNM_0 + i]
    _rotate_left(dx[ATT_0], dx[ATT_0 + 1], dx[ATT_0 + 2], C_nb)
    _rotate_left(dx[MNT_0], dx[MNT_0 + 1], dx[MNT_0 + 2], C_vb)
    if dx.size >= N_FULL:
        for i in range(3):
            s_g[i] += dx[SG_0 + i]
            s_a[i] += dx[SA_0 + i]


def inject(nom: Nominal, dx: FloatArray) -> None:
    """Add an error-state estimate to the nominal state, in place (the ESKF reset).

    ``p += dp``, ``v += dv``, ``C_nb <- exp([dth x]) C_nb``, biases, GNSS error and scale
    factors added, ``C_vb <- exp([dmu x]) C_vb`` (:func:`inject_arrays`).
    """
    inject_arrays(np.ascontiguousarray(dx, dtype=np.float64), *nom.arrays())


def difference(true: Nominal, est: Nominal, n: int) -> FloatArray:
    """Error state ``dx`` with ``true = est (+) dx`` (inverse of :func:`inject`)."""
    dx = np.zeros(n)
    dx[POS] = true.p_n - est.p_n
    dx[VEL] = true.v_n - est.v_n
    dx[ATT] = dcm_to_rotvec(true.C_nb @ est.C_nb.T)
    dx[BG] = true.b_g - est.b_g
    dx[BA] = true.b_a - est.b_a
    dx[MNT] = dcm_to_rotvec(true.C_vb @ est.C_vb.T)
    dx[GNE] = true.e_n - est.e_n
    dx[GNM] = true.e_gm - est.e_gm
    if n >= N_FULL:
        dx[SG] = true.s_g - est.s_g
        dx[SA] = true.s_a - est.s_a
    return dx


@numba.njit(cache=True)
def compensate_into(raw: FloatArray, bias: FloatArray, scale: FloatArray, out: FloatArray) -> None:
    """``out = (raw - b) / (1 + s)`` element-wise (compiled).

    Parameters
    ----------
    raw, bias, scale : numpy.ndarray
        Sensor output, bias (same unit, ``b``) and scale-factor error (dimensionless), 3 each.
    out : numpy.ndarray
        Receives the compensated output (3).
    """
    for i in range(3):
        out[i] = (raw[i] - bias[i]) / (1.0 + scale[i])


def compensate(raw: FloatArray, bias: FloatArray, scale: FloatArray) -> FloatArray:
    """Sensor output corrected for bias and scale factor: ``(raw - b) / (1 + s)``."""
    out = np.empty(3)
    compensate_into(
        np.ascontiguousarray(raw, dtype=np.float64),
        np.ascontiguousarray(bias, dtype=np.float64),
        np.ascontiguousarray(scale, dtype=np.float64),
        out,
    )
    return out
