"""Gyroscope-bias Kalman filter (Forno et al. 2020, block 2, "Gyro Bias KF").

The paper only says that this filter "iteratively computes the bias correction to be applied
to the gyroscope output". The model used here (stated because the paper omits it): the bias
``b_g`` (rad/s, sensor frame) is a random walk, observed directly by the gyroscope whenever the
device is static (true angular rate ~ 0, the Earth rate ~7e-5 rad/s being below MEMS noise)::

    b_k = b_{k-1},             F = I,   Q = q_b dt I        (q_b: bias random walk, rad^2/s^3)
    z   = omega_meas_b,        H = I,   R = sigma_g^2 I     (only while static)

While moving the bias is propagated only (its covariance grows), so it is most observable
while static, as the issue states. The corrected rate is ``omega_b = omega_meas_b - b_g``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from iotnav import kalman

FloatArray = npt.NDArray[np.float64]

#: State layout: the gyroscope bias in ``b``, rad/s.
BIAS_B = slice(0, 3)
N_STATES = 3


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


class GyroBiasKF:
    """Three-state random-walk gyroscope-bias filter; hot state ``x`` (3,) and ``P`` (3, 3)."""

    def __init__(self, config: GyroBiasConfig | None = None, b0: FloatArray | None = None) -> None:
        self.config = config or GyroBiasConfig()
        self.x = np.zeros(N_STATES) if b0 is None else np.asarray(b0, float).copy()
        self.P = np.eye(N_STATES) * self.config.init_std_rad_s**2

    def predict(self, dt: float) -> None:
        """Random-walk propagation over ``dt`` seconds."""
        if dt <= 0.0:
            return
        q = self.config.bias_rw_rad_s2_rthz**2 * dt
        self.x, self.P = kalman.predict(self.x, self.P, np.eye(3), np.eye(3) * q)

    def update_static(self, gyro_b: FloatArray) -> bool:
        """Use a raw gyroscope sample (rad/s) taken while static as a bias measurement."""
        if float(np.max(np.abs(gyro_b))) > self.config.max_rate_rad_s:
            return False
        R = np.eye(3) * self.config.gyro_noise_rad_s**2
        res = kalman.update(self.x, self.P, np.asarray(gyro_b, float), np.eye(3), R)
        self.x, self.P = res.x, res.P
        return True
