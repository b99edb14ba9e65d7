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

Implementation: the state lives in one float64 array (``T_*`` layout) and the step is the
compiled :func:`tilt_predict` / :func:`tilt_update` (scalar 3 x 3 algebra of
:mod:`iotnav.techniques.kf3`), called by :class:`TiltKF` and by the engines' IMU kernels alike.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numba
import numpy as np
import numpy.typing as npt

from iotnav.techniques.kf3 import ThreeStateArrays, diag3, predict_row3, update3

FloatArray = npt.NDArray[np.float64]

#: State layout: the single 3-vector ``x`` (down axis of ``n`` in ``b``).
DOWN_B = slice(0, 3)
N_STATES = 3
#: The filter's state array: ``x`` (3), ``P`` (3 x 3 row-major), initialised flag, last NIS.
T_INIT, T_NIS = 12, 13
STATE_SIZE = 14
#: Parameter vector of the compiled kernels (:func:`tilt_params`).
TP_GYRO, TP_ACC, TP_EXT, TP_REJECT, TP_QFLOOR, TP_GNSS_GAIN, TP_DEADBAND = range(7)


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


def roll_pitch_from_down(x: FloatArray) -> tuple[float, float]:
    """Roll and pitch (rad) from the down axis in ``b`` (third row of ``C_nb``)."""
    pitch = float(np.arcsin(np.clip(-x[0], -1.0, 1.0)))
    roll = float(np.arctan2(x[1], x[2]))
    return roll, pitch


def tilt_params(c: TiltConfig) -> FloatArray:
    """Parameter vector (``TP_*`` layout, SI) of :func:`tilt_predict` and :func:`tilt_update`."""
    return np.array(
        [
            c.gyro_noise_rad_s,
            c.acc_noise_mps2,
            c.ext_acc_gain,
            c.reject_mps2,
            c.q_floor,
            c.gnss_acc_gain,
            c.gnss_acc_deadband_mps2,
        ]
    )


@numba.njit(cache=True)
def tilt_predict(
    s: FloatArray, p: FloatArray, wx: float, wy: float, wz: float, dt: float, bias_var: float
) -> None:
    """Propagate the state array ``s`` with ``omega_b`` (rad/s) over ``dt`` (s), then renormalise ``x``.

    ``bias_var`` is the gyro-bias variance, (rad/s)^2 (added to the rate noise).
    """
    if dt <= 0.0:
        return
    predict_row3(s, wx, wy, wz, dt, math.sqrt(p[TP_GYRO] ** 2 + bias_var), p[TP_QFLOOR])
    n = math.sqrt(s[0] * s[0] + s[1] * s[1] + s[2] * s[2])
    s[0] /= n
    s[1] /= n
    s[2] /= n


@numba.njit(cache=True)
def tilt_update(
    s: FloatArray, p: FloatArray, fx: float, fy: float, fz: float, g: float, a_veh: float
) -> bool:
    """Accelerometer update of the state array ``s`` (module docstring); True when used.

    ``f_b = [fx, fy, fz]`` specific force in ``b`` (m/s^2), ``g`` gravity (m/s^2), ``a_veh`` the
    GNSS/gyro vehicle acceleration magnitude ``|a_v|`` (m/s^2).
    """
    norm = math.sqrt(fx * fx + fy * fy + fz * fz)
    if norm <= 0.0 or not math.isfinite(norm):
        return False
    z0, z1, z2 = -fx / norm, -fy / norm, -fz / norm
    if s[T_INIT] == 0.0:
        s[0], s[1], s[2] = z0, z1, z2
        s[T_INIT] = 1.0
        return True
    if abs(norm - g) > p[TP_REJECT]:
        return False
    e0, e1, e2 = fx + g * s[0], fy + g * s[1], fz + g * s[2]
    extra = max(a_veh - p[TP_DEADBAND], 0.0)
    r = (p[TP_ACC] ** 2 + p[TP_EXT] * (e0 * e0 + e1 * e1 + e2 * e2) + p[TP_GNSS_GAIN] * extra**2) / g**2
    nis, _ = update3(s, z0, z1, z2, diag3(r), math.inf)
    n = math.sqrt(s[0] * s[0] + s[1] * s[1] + s[2] * s[2])
    s[0] /= n
    s[1] /= n
    s[2] /= n
    s[T_NIS] = nis
    return True


class TiltKF(ThreeStateArrays):
    """Three-state tilt Kalman filter; hot state in :attr:`state` (``T_*`` layout).

    ``x``: the down axis of ``n`` in ``b`` (unit vector).

    ``x`` (3,) and ``P`` (3, 3) are views of :attr:`state`; assigning to them copies in place.

    Parameters
    ----------
    config : TiltConfig
        Tunables.
    x0 : numpy.ndarray, optional
        Initial down axis in ``b``; when omitted, the first accelerometer sample initialises it.
    """

    def __init__(self, config: TiltConfig | None = None, x0: FloatArray | None = None) -> None:
        self.config = config or TiltConfig()
        self.params = tilt_params(self.config)
        self.state = np.zeros(STATE_SIZE)
        self.x = np.array([0.0, 0.0, 1.0]) if x0 is None else np.asarray(x0, float) / np.linalg.norm(x0)
        self.P = np.eye(N_STATES) * self.config.init_std**2
        self.initialised = x0 is not None
        self.state[T_NIS] = math.nan

    @property
    def initialised(self) -> bool:
        """True once the first accelerometer sample (or ``x0``) set the state."""
        return bool(self.state[T_INIT] != 0.0)

    @initialised.setter
    def initialised(self, value: bool) -> None:
        self.state[T_INIT] = 1.0 if value else 0.0

    @property
    def last_nis(self) -> float:
        """NIS of the latest accelerometer update (NaN before any)."""
        return float(self.state[T_NIS])

    def predict(self, omega_b: FloatArray, dt: float, bias_var: float = 0.0) -> None:
        """Propagate with the bias-corrected gyroscope ``omega_b`` (rad/s) over ``dt`` (s).

        ``bias_var`` is the variance of the gyro-bias estimate, (rad/s)^2.
        """
        w = np.asarray(omega_b, float)
        tilt_predict(
            self.state, self.params, float(w[0]), float(w[1]), float(w[2]), float(dt), float(bias_var)
        )

    def update(self, f_b: FloatArray, g: float, vehicle_acc_mps2: float = 0.0) -> bool:
        """Correct with the accelerometer specific force ``f_b`` (m/s^2); ``g`` gravity, m/s^2.

        ``vehicle_acc_mps2`` is the optional GNSS/gyro acceleration magnitude ``|a_v|``.

        Returns
        -------
        bool
            True when the sample was used.
        """
        f = np.asarray(f_b, float)
        return bool(
            tilt_update(
                self.state,
                self.params,
                float(f[0]),
                float(f[1]),
                float(f[2]),
                float(g),
                float(vehicle_acc_mps2),
            )
        )
