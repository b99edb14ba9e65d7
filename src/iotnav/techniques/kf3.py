"""Compiled three-state Kalman kernels on flat float64 arrays (block 2 filters, STYLE §7).

The tilt, yaw and gyro-bias filters of :mod:`iotnav.techniques.cascade` each keep their state
in one float64 array ``s`` laid out as ``x = s[0:3]``, ``P = s[3:12]`` (row-major 3 x 3); these
kernels update it in place with scalar arithmetic (no numpy temporaries, no BLAS), so the same
code serves the classes' Python methods and the engines' compiled IMU loops.

Equations (as :mod:`iotnav.kalman`, specialised to ``n = 3``)::

    predict:  x- = F x,   P- = sym(F P F^T + Q)
    update (H = I):  y = z - x-,  S = sym(P- + R) = L L^T (Cholesky),  K = P- S^-1
              x+ = x- + K y,  P+ = sym((I - K) P- (I - K)^T + K R K^T),  NIS = y^T S^-1 y
"""

from __future__ import annotations

import math

import numba
import numpy as np
import numpy.typing as npt

FloatArray = npt.NDArray[np.float64]

#: Offsets of ``x`` and ``P`` in a three-state filter's state array.
X3, P3 = 0, 3


class ThreeStateArrays:
    """``x`` and ``P`` of a three-state filter as views of its float64 array :attr:`state`.

    Base of the cascade's tilt, yaw and gyro-bias filters: ``x = state[0:3]``,
    ``P = state[3:12].reshape(3, 3)``; assigning copies into the array (units: the filter's).
    """

    state: FloatArray

    @property
    def x(self) -> FloatArray:
        """State vector (view)."""
        return self.state[X3 : X3 + 3]

    @x.setter
    def x(self, value: FloatArray) -> None:
        self.state[X3 : X3 + 3] = value

    @property
    def P(self) -> FloatArray:
        """Covariance of :attr:`x` (view)."""
        return self.state[P3 : P3 + 9].reshape(3, 3)

    @P.setter
    def P(self, value: FloatArray) -> None:
        self.state[P3 : P3 + 9] = np.asarray(value, float).reshape(9)


@numba.njit(cache=True)
def symmetrize3(s: FloatArray, off: int) -> None:
    """Replace the 3 x 3 block at ``s[off:off+9]`` by ``(P + P^T) / 2``."""
    for i in range(3):
        for j in range(i + 1, 3):
            v = 0.5 * (s[off + 3 * i + j] + s[off + 3 * j + i])
            s[off + 3 * i + j] = v
            s[off + 3 * j + i] = v


@numba.njit(cache=True)
def predict_row3(
    s: FloatArray, wx: float, wy: float, wz: float, dt: float, sigma: float, q_floor: float
) -> None:
    """Row-vector prediction of the tilt and yaw filters, in place.

    ``F = I - dt [omega_b x]``, ``Q = (dt sigma)^2 (I - x x^T) + q_floor I`` (prior ``x``).

    Parameters
    ----------
    s : numpy.ndarray
        State array (``x`` at 0, ``P`` at 3), updated in place.
    wx, wy, wz : float
        Bias-corrected angular rate in ``b``, rad/s.
    dt : float
        Step, s.
    sigma : float
        Angular-rate noise standard deviation, rad/s.
    q_floor : float
        Process-noise floor on each diagonal element.
    """
    a = dt
    F = (1.0, a * wz, -a * wy, -a * wz, 1.0, a * wx, a * wy, -a * wx, 1.0)
    x = (s[0], s[1], s[2])
    P = (s[3], s[4], s[5], s[6], s[7], s[8], s[9], s[10], s[11])
    q = (dt * sigma) ** 2
    for i in range(3):
        s[i] = F[3 * i] * x[0] + F[3 * i + 1] * x[1] + F[3 * i + 2] * x[2]
    # M = F P
    m0 = F[0] * P[0] + F[1] * P[3] + F[2] * P[6]
    m1 = F[0] * P[1] + F[1] * P[4] + F[2] * P[7]
    m2 = F[0] * P[2] + F[1] * P[5] + F[2] * P[8]
    m3 = F[3] * P[0] + F[4] * P[3] + F[5] * P[6]
    m4 = F[3] * P[1] + F[4] * P[4] + F[5] * P[7]
    m5 = F[3] * P[2] + F[4] * P[5] + F[5] * P[8]
    m6 = F[6] * P[0] + F[7] * P[3] + F[8] * P[6]
    m7 = F[6] * P[1] + F[7] * P[4] + F[8] * P[7]
    m8 = F[6] * P[2] + F[7] * P[5] + F[8] * P[8]
    M = (m0, m1, m2, m3, m4, m5, m6, m7, m8)
    for i in range(3):
        for j in range(3):
            v = M[3 * i] * F[3 * j] + M[3 * i + 1] * F[3 * j + 1] + M[3 * i + 2] * F[3 * j + 2]
            qij = -q * x[i] * x[j]
            if i == j:
                qij += q + q_floor
            s[3 + 3 * i + j] = v + qij
    symmetrize3(s, 3)


@numba.njit(cache=True)
def update3(
    s: FloatArray,
    z0: float,
    z1: float,
    z2: float,
    R: tuple[float, float, float, float, float, float, float, float, float],
    gate: float,
) -> tuple[float, bool]:
    """Measurement ``z = x + w`` (``H = I``), ``w ~ N(0, R)``, in place; NIS gate ``gate``.

    Parameters
    ----------
    s : numpy.ndarray
        State array (``x`` at 0, ``P`` at 3), updated in place when accepted.
    z0, z1, z2 : float
        Measurement, in the state's units.
    R : tuple of 9 float
        Measurement covariance, row-major.
    gate : float
        NIS threshold (``inf``: no gate).

    Returns
    -------
    nis : float
        Normalised innovation squared.
    accepted : bool
        False when ``nis > gate`` (state unchanged).
    """
    x = (s[0], s[1], s[2])
    P = (s[3], s[4], s[5], s[6], s[7], s[8], s[9], s[10], s[11])
    y0, y1, y2 = z0 - x[0], z1 - x[1], z2 - x[2]
    S00 = P[0] + R[0]
    S11 = P[4] + R[4]
    S22 = P[8] + R[8]
    S10 = 0.5 * ((P[3] + R[3]) + (P[1] + R[1]))
    S20 = 0.5 * ((P[6] + R[6]) + (P[2] + R[2]))
    S21 = 0.5 * ((P[7] + R[7]) + (P[5] + R[5]))
    l00 = math.sqrt(S00)
    l10 = S10 / l00
    l20 = S20 / l00
    l11 = math.sqrt(S11 - l10 * l10)
    l21 = (S21 - l20 * l10) / l11
    l22 = math.sqrt(S22 - l20 * l20 - l21 * l21)
    # u = L^-1 y
    u0 = y0 / l00
    u1 = (y1 - l10 * u0) / l11
    u2 = (y2 - l20 * u0 - l21 * u1) / l22
    nis = u0 * u0 + u1 * u1 + u2 * u2
    if nis > gate:
        return nis, False
    # L^-1 (lower triangular)
    i00 = 1.0 / l00
    i11 = 1.0 / l11
    i22 = 1.0 / l22
    i10 = -l10 * i00 * i11
    i21 = -l21 * i11 * i22
    i20 = -(l20 * i00 + l21 * i10) * i22
    # S^-1 = L^-T L^-1 (symmetric)
    a00 = i00 * i00 + i10 * i10 + i20 * i20
    a01 = i10 * i11 + i20 * i21
    a02 = i20 * i22
    a11 = i11 * i11 + i21 * i21
    a12 = i21 * i22
    a22 = i22 * i22
    Si = (a00, a01, a02, a01, a11, a12, a02, a12, a22)
    # K = P S^-1
    k = (
        P[0] * Si[0] + P[1] * Si[3] + P[2] * Si[6],
        P[0] * Si[1] + P[1] * Si[4] + P[2] * Si[7],
        P[0] * Si[2] + P[1] * Si[5] + P[2] * Si[8],
        P[3] * Si[0] + P[4] * Si[3] + P[5] * Si[6],
        P[3] * Si[1] + P[4] * Si[4] + P[5] * Si[7],
        P[3] * Si[2] + P[4] * Si[5] + P[5] * Si[8],
        P[6] * Si[0] + P[7] * Si[3] + P[8] * Si[6],
        P[6] * Si[1] + P[7] * Si[4] + P[8] * Si[7],
        P[6] * Si[2] + P[7] * Si[5] + P[8] * Si[8],
    )
    for i in range(3):
        s[i] = x[i] + k[3 * i] * y0 + k[3 * i + 1] * y1 + k[3 * i + 2] * y2
    # A = I - K
    A = (1.0 - k[0], -k[1], -k[2], -k[3], 1.0 - k[4], -k[5], -k[6], -k[7], 1.0 - k[8])
    AP = (
        A[0] * P[0] + A[1] * P[3] + A[2] * P[6],
        A[0] * P[1] + A[1] * P[4] + A[2] * P[7],
        A[0] * P[2] + A[1] * P[5] + A[2] * P[8],
        A[3] * P[0] + A[4] * P[3] + A[5] * P[6],
        A[3] * P[1] + A[4] * P[4] + A[5] * P[7],
        A[3] * P[2] + A[4] * P[5] + A[5] * P[8],
        A[6] * P[0] + A[7] * P[3] + A[8] * P[6],
        A[6] * P[1] + A[7] * P[4] + A[8] * P[7],
        A[6] * P[2] + A[7] * P[5] + A[8] * P[8],
    )
    KR = (
        k[0] * R[0] + k[1] * R[3] + k[2] * R[6],
        k[0] * R[1] + k[1] * R[4] + k[2] * R[7],
        k[0] * R[2] + k[1] * R[5] + k[2] * R[8],
        k[3] * R[0] + k[4] * R[3] + k[5] * R[6],
        k[3] * R[1] + k[4] * R[4] + k[5] * R[7],
        k[3] * R[2] + k[4] * R[5] + k[5] * R[8],
        k[6] * R[0] + k[7] * R[3] + k[8] * R[6],
        k[6] * R[1] + k[7] * R[4] + k[8] * R[7],
        k[6] * R[2] + k[7] * R[5] + k[8] * R[8],
    )
    for i in range(3):
        for j in range(3):
            v = AP[3 * i] * A[3 * j] + AP[3 * i + 1] * A[3 * j + 1] + AP[3 * i + 2] * A[3 * j + 2]
            v += KR[3 * i] * k[3 * j] + KR[3 * i + 1] * k[3 * j + 1] + KR[3 * i + 2] * k[3 * j + 2]
            s[3 + 3 * i + j] = v
    symmetrize3(s, 3)
    return nis, True


@numba.njit(cache=True)
def diag3(r: float) -> tuple[float, float, float, float, float, float, float, float, float]:
    """``r I`` as the row-major 9-tuple :func:`update3` takes."""
    return (r, 0.0, 0.0, 0.0, r, 0.0, 0.0, 0.0, r)
