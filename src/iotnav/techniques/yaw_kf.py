"""Yaw Kalman filter: the North axis in the sensor frame (Forno et al. 2020, block 2).

Zihajehzadeh et al. 2015 estimate the first row of ``C_nb`` (the navigation-frame North axis
resolved in ``b``) with a 3-state filter aided by the magnetometer. Forno et al. replace the
magnetometer by the GPS course over ground while the vehicle moves, corrected by the yaw
mounting angle of block 5. Both aids are supported here.

State and process model (same kinematics as the tilt filter)::

    x = C_nb[0, :]^T = [cos(pitch) cos(psi),
                        sin(roll) sin(pitch) cos(psi) - cos(roll) sin(psi),
                        cos(roll) sin(pitch) cos(psi) + sin(roll) sin(psi)]^T
    x_k = (I - dt [omega_b x]) x_{k-1},   Q = dt^2 sigma_g^2 (I - x x^T)

Course aiding (derived here; the paper does not state it). With the non-holonomic assumption
the vehicle yaw equals the course ``alpha``, so the sensor yaw is ``psi_b = alpha + mount_yaw``
(``mount_yaw``: sensor x relative to vehicle forward, clockwise positive). The measurement is
the row that roll and pitch of the tilt filter and ``psi_b`` imply::

    z = r1(roll, pitch, psi_b),   H = I,
    R = sigma_psi^2 J J^T + sigma_floor^2 I,   J = d r1 / d psi

so the information is along the heading direction only (``sigma_floor`` keeps R regular).

Magnetometer aiding (Zihajehzadeh's original form): the field projected on the horizontal
plane, ``m_h = m_b - (m_b . x3) x3``, normalised, points to magnetic North; rotating it by the
declination ``D`` (East positive) about the down axis gives true North::

    z = cos(D) u - sin(D) (x3 x u),   u = m_h / |m_h|,   H = I,   R = sigma_m^2 I

After each step ``x`` is made orthogonal to the tilt estimate ``x3`` and unit length;
``C_nb = [x1; x3 x x1; x3]`` (rows North, East, Down in ``b``).

Implementation: the state lives in one float64 array (``Y_*`` layout); the IMU-rate prediction
is the compiled :func:`yaw_predict` and the aids use the compiled 3-state update of
:mod:`iotnav.techniques.kf3`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numba
import numpy as np
import numpy.typing as npt

from iotnav import kalman
from iotnav.techniques.kf3 import ThreeStateArrays, diag3, predict_row3, update3
from iotnav.techniques.tilt_kf import roll_pitch_from_down

FloatArray = npt.NDArray[np.float64]

#: State layout: the single 3-vector ``x`` (North axis of ``n`` in ``b``).
NORTH_B = slice(0, 3)
N_STATES = 3
#: The filter's state array: ``x`` (3), ``P`` (3 x 3 row-major), initialised flag, last NIS.
Y_INIT, Y_NIS = 12, 13
STATE_SIZE = 14
#: Parameter vector of the compiled kernels (:func:`yaw_params`).
YP_GYRO, YP_QFLOOR = range(2)


@dataclass(frozen=True)
class YawConfig:
    """Yaw filter tunables (SI).

    Attributes
    ----------
    gyro_noise_rad_s : float
        Gyroscope white noise per sample, rad/s.
    course_noise_rad : float
        Standard deviation of the course-derived sensor heading, rad.
    min_course_speed_mps : float
        Course aiding only above this GPS speed, m/s.
    mag_noise : float
        Standard deviation of the magnetometer North direction (unit vector), dimensionless.
    declination_rad : float
        Magnetic declination, rad, East positive.
    use_mag : bool
        Use magnetometer samples when given.
    gate_probability : float
        Chi-square probability of the NIS gate on course updates (3 dof); 0 disables gating.
    q_floor : float
        Process-noise floor on each diagonal element.
    """

    gyro_noise_rad_s: float = 0.01
    course_noise_rad: float = 0.1
    min_course_speed_mps: float = 2.0
    mag_noise: float = 0.1
    declination_rad: float = 0.0
    use_mag: bool = True
    gate_probability: float = 0.0
    q_floor: float = 1e-10


def north_row(roll: float, pitch: float, yaw: float) -> FloatArray:
    """First row of ``C_nb`` (North axis in ``b``) from Euler angles (rad)."""
    sr, cr = np.sin(roll), np.cos(roll)
    sp, cp = np.sin(pitch), np.cos(pitch)
    sy, cy = np.sin(yaw), np.cos(yaw)
    return np.array([cp * cy, sr * sp * cy - cr * sy, cr * sp * cy + sr * sy])


def north_row_dyaw(roll: float, pitch: float, yaw: float) -> FloatArray:
    """Derivative of :func:`north_row` with respect to yaw."""
    sr, cr = np.sin(roll), np.cos(roll)
    sp, cp = np.sin(pitch), np.cos(pitch)
    sy, cy = np.sin(yaw), np.cos(yaw)
    return np.array([-cp * sy, -sr * sp * sy - cr * cy, -cr * sp * sy + sr * cy])


@numba.njit(cache=True)
def dcm_rows_into(x1: FloatArray, x3: FloatArray, C: FloatArray) -> None:
    """Write the orthonormal ``C_nb`` (row-major, 9) built from ``x1`` and ``x3`` into ``C``.

    Scalar form of :func:`dcm_from_rows` for compiled kernels (``C`` must not alias the inputs
    other than ``x1`` being read before it is written).
    """
    n3 = math.sqrt(x3[0] * x3[0] + x3[1] * x3[1] + x3[2] * x3[2])
    d0, d1, d2 = x3[0] / n3, x3[1] / n3, x3[2] / n3
    p = x1[0] * d0 + x1[1] * d1 + x1[2] * d2
    n0, n1, n2 = x1[0] - p * d0, x1[1] - p * d1, x1[2] - p * d2
    nn = math.sqrt(n0 * n0 + n1 * n1 + n2 * n2)
    if nn < 1e-9:  # degenerate: pick any horizontal direction
        if abs(d1) < 0.9:  # d x [0, 1, 0]
            n0, n1, n2 = -d2, 0.0, d0
        else:  # d x [1, 0, 0]
            n0, n1, n2 = 0.0, d2, -d1
        nn = math.sqrt(n0 * n0 + n1 * n1 + n2 * n2)
    n0, n1, n2 = n0 / nn, n1 / nn, n2 / nn
    C[0], C[1], C[2] = n0, n1, n2
    C[3], C[4], C[5] = d1 * n2 - d2 * n1, d2 * n0 - d0 * n2, d0 * n1 - d1 * n0
    C[6], C[7], C[8] = d0, d1, d2


def dcm_from_rows(x1: FloatArray, x3: FloatArray) -> FloatArray:
    """Orthonormal ``C_nb`` from the North row ``x1`` and the down row ``x3`` (both in ``b``).

    ``x3`` is kept, ``x1`` is Gram-Schmidt orthogonalised to it, the East row is ``x3 x x1``.
    """
    C = np.empty(9)
    dcm_rows_into(np.asarray(x1, float), np.asarray(x3, float), C)
    return C.reshape(3, 3)


def yaw_of_dcm(C_nb: FloatArray) -> float:
    """Yaw (rad, clockwise from North) of ``C_nb``."""
    return float(np.arctan2(C_nb[1, 0], C_nb[0, 0]))


def yaw_params(c: YawConfig) -> FloatArray:
    """Parameter vector (``YP_*`` layout) of :func:`yaw_predict`."""
    return np.array([c.gyro_noise_rad_s, c.q_floor])


@numba.njit(cache=True)
def yaw_predict(
    s: FloatArray, p: FloatArray, wx: float, wy: float, wz: float, dt: float, bias_var: float
) -> None:
    """Propagate the state array ``s`` with ``omega_b`` (rad/s) over ``dt`` (s).

    ``bias_var`` is the gyro-bias variance, (rad/s)^2 (added to the rate noise).
    """
    if dt <= 0.0:
        return
    predict_row3(s, wx, wy, wz, dt, math.sqrt(p[YP_GYRO] ** 2 + bias_var), p[YP_QFLOOR])


class YawKF(ThreeStateArrays):
    """Three-state yaw Kalman filter; hot state in :attr:`state` (``Y_*`` layout).

    ``x``: the North axis of ``n`` in ``b`` (unit vector).

    ``x`` (3,) and ``P`` (3, 3) are views of :attr:`state`; assigning to them copies in place.
    The heading is unknown until the first course (or magnetometer) measurement, which
    initialises the state directly; until then only the gyroscope propagates it.
    """

    def __init__(self, config: YawConfig | None = None) -> None:
        self.config = config or YawConfig()
        self.params = yaw_params(self.config)
        self.state = np.zeros(STATE_SIZE)
        self.x = np.array([1.0, 0.0, 0.0])
        self.P = np.eye(N_STATES)
        self.state[Y_NIS] = math.nan
        self._gate = (
            kalman.gate_threshold(3, self.config.gate_probability)
            if self.config.gate_probability > 0.0
            else math.inf
        )

    @property
    def initialised(self) -> bool:
        """True once a heading measurement set the state."""
        return bool(self.state[Y_INIT] != 0.0)

    @initialised.setter
    def initialised(self, value: bool) -> None:
        self.state[Y_INIT] = 1.0 if value else 0.0

    @property
    def last_nis(self) -> float:
        """NIS of the latest update (NaN before any)."""
        return float(self.state[Y_NIS])

    def predict(self, omega_b: FloatArray, dt: float, bias_var: float = 0.0) -> None:
        """Propagate with the bias-corrected gyroscope ``omega_b`` (rad/s) over ``dt`` (s).

        ``bias_var`` is the variance of the gyro-bias estimate, (rad/s)^2 (added to the noise).
        """
        w = np.asarray(omega_b, float)
        yaw_predict(
            self.state, self.params, float(w[0]), float(w[1]), float(w[2]), float(dt), float(bias_var)
        )

    def _heading_meas(self, psi_b: float, x3: FloatArray, sigma: float) -> tuple[FloatArray, FloatArray]:
        roll, pitch = roll_pitch_from_down(x3)
        z = north_row(roll, pitch, psi_b)
        J = north_row_dyaw(roll, pitch, psi_b)
        R = sigma**2 * np.outer(J, J) + (0.02 * sigma) ** 2 * np.eye(3)
        return z, R

    def reset_heading(self, psi_b: float, x3: FloatArray, sigma: float | None = None) -> None:
        """Set the state to the sensor yaw ``psi_b`` (rad) at the tilt ``x3``."""
        s = self.config.course_noise_rad if sigma is None else sigma
        z, R = self._heading_meas(psi_b, x3, s)
        self.x = z
        self.P = R
        self.initialised = True

    def update_heading(self, psi_b: float, x3: FloatArray, sigma: float | None = None) -> bool:
        """Correct with a sensor-yaw measurement ``psi_b`` (rad), e.g. course + mount angle.

        Returns
        -------
        bool
            True when applied (False when gated out).
        """
        s = self.config.course_noise_rad if sigma is None else sigma
        if not self.initialised:
            self.reset_heading(psi_b, x3, s)
            return True
        z, R = self._heading_meas(psi_b, x3, s)
        r = R.ravel().tolist()
        R9 = (r[0], r[1], r[2], r[3], r[4], r[5], r[6], r[7], r[8])
        nis, accepted = update3(self.state, float(z[0]), float(z[1]), float(z[2]), R9, self._gate)
        self.state[Y_NIS] = nis
        if accepted:
            self._constrain(x3)
        return bool(accepted)

    def update_mag(self, m_b: FloatArray, x3: FloatArray) -> bool:
        """Correct with a magnetometer sample ``m_b`` (any unit) given the tilt ``x3``."""
        c = self.config
        m_h = m_b - (m_b @ x3) * x3
        nm = float(np.linalg.norm(m_h))
        if nm <= 0.0 or not np.isfinite(nm):
            return False
        u = m_h / nm
        z = np.cos(c.declination_rad) * u - np.sin(c.declination_rad) * np.cross(x3, u)
        if not self.initialised:
            self.x = z
            self.P = np.eye(3) * c.mag_noise**2
            self.initialised = True
            return True
        nis, _ = update3(self.state, float(z[0]), float(z[1]), float(z[2]), diag3(c.mag_noise**2), math.inf)
        self.state[Y_NIS] = nis
        self._constrain(x3)
        return True

    def _constrain(self, x3: FloatArray) -> None:
        self.x = dcm_from_rows(self.x, x3)[0]
