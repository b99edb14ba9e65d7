"""Gyroscope-bias Kalman filter (Forno et al. 2020, block 2, "Gyro Bias KF").

The paper only says that this filter "iteratively computes the bias correction to be applied
to the gyroscope output". The model used here (stated because the paper omits it): the bias
``b_g`` (rad/s, sensor frame) is a random walk, observed directly by the gyroscope whenever the
device is static (true angular rate ~ 0, the Earth rate ~7e-5 rad/s being below MEMS noise)::

    b_k = b_{k-1},             F = I,   Q = q_b dt I        (q_b: bias random walk, rad^2/s^3)
    z   = omega_meas_b,        H = I,   R = sigma_g^2 I     (only while static)

While moving the bias is propagated only (its covariance grows), so it is most observable
while static, as the issue states. The corrected rate is ``omega_b = omega_meas_b - b_g``.

Implementation: state in one float64 array (``x``, ``P``); the compiled
:func:`gyro_bias_predict` and :func:`gyro_bias_update` serve :class:`GyroBiasKF` and the
engines' IMU kernels.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numba
import numpy as np
import numpy.typing as npt

from iotnav.techniques.kf3 import ThreeStateArrays, diag3, update3

FloatArray = npt.NDArray[np.float64]

#: State layout: the gyroscope bias in ``b``, rad/s.
BIAS_B = slice(0, 3)
N_STATES = 3
#: Length of the filter's state array: ``x`` (3) then ``P`` (3 x 3, row-major).
STATE_SIZE = 12
#: Parameter vector of the compiled kernels (:func:`gyro_bias_params`).
GB_Q, GB_R, GB_MAX_RATE = range(3)


@dataclass(frozen=True)
class GyroBiasConfig:
    """Gyro-bias filter tunables (SI).

    Attributes
    ----------
    gyro_noise_rad_s : float
        Gyroscope white noise per sample, rad/s.
    bias_rw_rad_s2_rthz : float
        Bias random walk, rad/s^2/sqrt(Hz) (``q_b`` is its square).
    init_std_rad_s : float
        Initial bias standard deviation, rad/s.
    max_rate_rad_s : float
        A "static" sample with a larger rate than this is not used (guard against
        detector errors), rad/s.
    """

    gyro_noise_rad_s: float = 0.01
    bias_rw_rad_s2_rthz: float = 1e-4
    init_std_rad_s: float = 0.1
    max_rate_rad_s: float = 0.3


def gyro_bias_params(c: GyroBiasConfig) -> FloatArray:
    """``[q_b (rad^2/s^3), sigma_g^2 (rad^2/s^2), max_rate (rad/s)]`` for the kernels."""
    return np.array([c.bias_rw_rad_s2_rthz**2, c.gyro_noise_rad_s**2, c.max_rate_rad_s])


@numba.njit(cache=True)
def gyro_bias_predict(s: FloatArray, p: FloatArray, dt: float) -> None:
    """Random-walk propagation over ``dt`` s: ``P += q_b dt I`` (state array ``s``, in place)."""
    if dt <= 0.0:
        return
    q = p[GB_Q] * dt
    for i in range(3):
        s[3 + 4 * i] += q


@numba.njit(cache=True)
def gyro_bias_update(s: FloatArray, p: FloatArray, gx: float, gy: float, gz: float) -> bool:
    """Static update with the raw rate ``[gx, gy, gz]`` (rad/s, ``b``).

    False (state unchanged) above ``max_rate`` and for a rate that is not a number (written so
    that every comparison with NaN refuses, as the C port does: a NaN taken once would be the
    bias for good).
    """
    lim = p[GB_MAX_RATE]
    if not (abs(gx) <= lim and abs(gy) <= lim and abs(gz) <= lim):
        return False
    update3(s, gx, gy, gz, diag3(p[GB_R]), math.inf)
    return True


class GyroBiasKF(ThreeStateArrays):
    """Three-state random-walk gyroscope-bias filter; hot state in :attr:`state` (``x``, ``P``).

    ``x``: the gyro bias in ``b``, rad/s; ``x`` and ``P`` are views of :attr:`state`.

    ``x`` (3,) and ``P`` (3, 3) are views of :attr:`state`; assigning to them copies in place.
    """

    def __init__(self, config: GyroBiasConfig | None = None, b0: FloatArray | None = None) -> None:
        self.config = config or GyroBiasConfig()
        self.params = gyro_bias_params(self.config)
        self.state = np.zeros(STATE_SIZE)
        if b0 is not None:
            self.x = np.asarray(b0, float)
        self.P = np.eye(N_STATES) * self.config.init_std_rad_s**2

    def predict(self, dt: float) -> None:
        """Random-walk propagation over ``dt`` seconds."""
        gyro_bias_predict(self.state, self.params, float(dt))

    def update_static(self, gyro_b: FloatArray) -> bool:
        """Use a raw gyroscope sample (rad/s) taken while static as a bias measurement."""
        g = np.asarray(gyro_b, float)
        return bool(gyro_bias_update(self.state, self.params, float(g[0]), float(g[1]), float(g[2])))
