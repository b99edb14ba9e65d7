"""Tilt Kalman filter: the gravity direction in the sensor frame (Forno et al. 2020, block 2).

The paper's input pre-processing (Sec. III-A2, Fig. 2) follows the cascaded filter of
Zihajehzadeh et al. 2015 (Measurement 73, 200-210). The tilt filter there estimates the third
row of ``C_nb``, i.e. the navigation-frame *down* axis resolved in the sensor frame,

    x = C_nb[2, :]^T = [-sin(pitch), sin(roll) cos(pitch), cos(roll) cos(pitch)]^T .

Process model (a fixed ``n`` vector seen from a frame rotating at ``omega_b``,
``dx/dt = -omega_b x x``), discretised to first order::

    x_k = (I - dt [omega_b x]) x_{k-1},      F = I - dt [omega_b x]
    Q   = dt^2 (sigma_g^2 + sigma_b^2) (I - x x^T)  (+ q_floor I)

where ``omega_b`` is the bias-corrected gyroscope rate (rad/s) and ``sigma_g`` the gyroscope
white noise per sample (rad/s); ``-[x x][x x] = I - x x^T`` for a unit ``x`` (the form of
Zihajehzadeh's ``Q = -dt^2 [x x] Sigma_g [x x]``). ``sigma_b^2`` is the current variance of the
gyro-bias estimate (mean of the bias filter's diagonal, passed in by the cascade): an
unknown turn-on bias (several deg/s on consumer MEMS) must not be treated as a perfectly
known rate, else the tilt drifts away from the accelerometer before the bias is learnt.

Measurement: at rest the accelerometer reads the specific force ``f_b = -g x``. The paper
(and the issue) use the normalised accelerometer::

    z = -f_b / |f_b|,   H = I,
    R = (sigma_a^2 + k_ext |a_ext|^2 + k_gnss max(|a_v| - a_0, 0)^2) / g^2 I,
    a_ext = f_b + g x_prior

``a_ext`` is the external (non-gravitational) acceleration implied by the gyro-propagated
prior, so the accelerometer is trusted less while the device accelerates (Zihajehzadeh's
adaptive measurement noise; here without their low-pass of ``a_ext``). ``a_ext`` alone misses
a slow, sustained acceleration once the estimate has started to lean towards it, so the
engine may also pass ``|a_v|``, the vehicle acceleration magnitude known from GNSS and the
gyroscope (``sqrt((dv/dt)^2 + (v r)^2)``, independent of attitude and mount angle); above the
dead band ``a_0`` it makes the accelerometer nearly ignored (``k_gnss`` large) and the tilt
is held by the gyroscope. Samples with
``| |f_b| - g | > reject_mps2`` are not used at all. After each step ``x`` is renormalised
to unit length (a constraint the linear filter does not keep by itself).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from iotnav import kalman
from iotnav.geo import skew

FloatArray = npt.NDArray[np.float64]

#: State layout: the single 3-vector ``x`` (down axis of ``n`` in ``b``).
DOWN_B = slice(0, 3)
N_STATES = 3


@dataclass(frozen=True)
class TiltConfig:
    """Tilt filter tunables (SI).

    Attributes
    ----------
    gyro_noise_rad_s : float
        Gyroscope white noise standard deviation per sample, rad/s.
    acc_noise_mps2 : float
        Accelerometer white noise standard deviation per sample, m/s^2.
    ext_acc_gain : float
        ``k_ext``: weight of the squared external acceleration in the measurement variance.
    reject_mps2 : float
        Skip the accelerometer update when ``| |f_b| - g |`` exceeds this, m/s^2.
    init_std : float
        Initial standard deviation of each state component (unit vector, dimensionless).
    q_floor : float
        Small process-noise floor added to each diagonal element (keeps P positive definite).
    gnss_acc_gain : float
        ``k_gnss``: weight of the GNSS-derived vehicle acceleration beyond the dead band.
    gnss_acc_deadband_mps2 : float
        ``a_0``: dead band of the GNSS-derived acceleration (its noise), m/s^2.
    """

    gyro_noise_rad_s: float = 0.01
    acc_noise_mps2: float = 0.05
    ext_acc_gain: float = 1.0
    reject_mps2: float = 3.0
    init_std: float = 0.5
    q_floor: float = 1e-10
    gnss_acc_gain: float = 100.0
    gnss_acc_deadband_mps2: float = 0.2


def tilt_transition(omega_b: FloatArray, dt: float) -> FloatArray:
    """``F = I - dt [omega_b x]`` for the tilt and yaw row filters (omega in rad/s, dt in s)."""
    return np.eye(3) - dt * skew(omega_b)


def row_process_noise(x: FloatArray, dt: float, gyro_noise_rad_s: float, q_floor: float) -> FloatArray:
    """``Q = dt^2 sigma_g^2 (I - x x^T) + q_floor I`` for a unit row vector ``x``."""
    return (dt * gyro_noise_rad_s) ** 2 * (np.eye(3) - np.outer(x, x)) + q_floor * np.eye(3)


def roll_pitch_from_down(x: FloatArray) -> tuple[float, float]:
    """Roll and pitch (rad) from the down axis in ``b`` (third row of ``C_nb``)."""
    pitch = float(np.arcsin(np.clip(-x[0], -1.0, 1.0)))
    roll = float(np.arctan2(x[1], x[2]))
    return roll, pitch


class TiltKF:
    """Three-state tilt Kalman filter; hot state in ``x`` (3,) and ``P`` (3, 3).

    Parameters
    ----------
    config : TiltConfig
        Tunables.
    x0 : numpy.ndarray, optional
        Initial down axis in ``b``; when omitted, the first accelerometer sample initialises it.
    """

    def __init__(self, config: TiltConfig | None = None, x0: FloatArray | None = None) -> None:
        self.config = config or TiltConfig()
        self.x = np.array([0.0, 0.0, 1.0]) if x0 is None else np.asarray(x0, float) / np.linalg.norm(x0)
        self.P = np.eye(N_STATES) * self.config.init_std**2
        self.initialised = x0 is not None
        self.last_nis = float("nan")

    def predict(self, omega_b: FloatArray, dt: float, bias_var: float = 0.0) -> None:
        """Propagate with the bias-corrected gyroscope ``omega_b`` (rad/s) over ``dt`` (s).

        ``bias_var`` is the variance of the gyro-bias estimate, (rad/s)^2.
        """
        if dt <= 0.0:
            return
        c = self.config
        F = tilt_transition(omega_b, dt)
        Q = row_process_noise(self.x, dt, math.sqrt(c.gyro_noise_rad_s**2 + bias_var), c.q_floor)
        self.x, self.P = kalman.predict(self.x, self.P, F, Q)
        self.x /= np.linalg.norm(self.x)

    def update(self, f_b: FloatArray, g: float, vehicle_acc_mps2: float = 0.0) -> bool:
        """Correct with the accelerometer specific force ``f_b`` (m/s^2); ``g`` gravity, m/s^2.

        ``vehicle_acc_mps2`` is the optional GNSS/gyro acceleration magnitude ``|a_v|``.

        Returns
        -------
        bool
            True when the sample was used.
        """
        c = self.config
        norm = float(np.linalg.norm(f_b))
        if norm <= 0.0 or not np.isfinite(norm):
            return False
        z = -f_b / norm
        if not self.initialised:
            self.x = z.copy()
            self.initialised = True
            return True
        if abs(norm - g) > c.reject_mps2:
            return False
        a_ext = f_b + g * self.x
        extra = max(vehicle_acc_mps2 - c.gnss_acc_deadband_mps2, 0.0)
        r = (c.acc_noise_mps2**2 + c.ext_acc_gain * float(a_ext @ a_ext) + c.gnss_acc_gain * extra**2) / g**2
        res = kalman.update(self.x, self.P, z, np.eye(3), np.eye(3) * r)
        self.x = res.x / np.linalg.norm(res.x)
        self.P = res.P
        self.last_nis = res.nis
        return True
