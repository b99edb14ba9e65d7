"""State layout, nominal state, error dynamics and measurement models of the ``eskf`` engine.

Everything here is a plain function on numpy arrays (STYLE §4-§7, §10): the engine
:mod:`iotnav.engines.eskf` wires them; the tests check every Jacobian against finite
differences through :func:`inject` / :func:`difference`.

Error-state definitions (true = estimate (+) error)
---------------------------------------------------
::

    p_true = p + dp                  (POS, m, n)
    v_true = v + dv                  (VEL, m/s, n)
    C_nb_true = exp([dth x]) C_nb    (ATT, rad, rotation error resolved in n)
    b_g_true = b_g + db_g            (BG, rad/s, b)      b_a_true = b_a + db_a  (BA, m/s^2, b)
    C_vb_true = exp([dmu x]) C_vb    (MNT, rad, mount rotation error resolved in v)
    e_true = e + de                  (GNE, m, n: time-correlated GNSS position error)
    s_g_true = s_g + ds_g            (SG, scale factors, optional)   s_a likewise (SA)

Sensor model: ``omega_m = (1 + s_g) omega + b_g + w_g``, ``f_m = (1 + s_a) f + b_a + w_a``
(element-wise), compensated as ``omega = (omega_m - b_g) / (1 + s_g)``; to first order
``d omega = -db_g - diag(omega) ds_g`` and ``d f = -db_a - diag(f) ds_a``.

Continuous error dynamics (Groves 2013, §14.2.4, in the flat-earth local frame of
:mod:`iotnav.strapdown`; Sola 2017, §5.3 for the left attitude error)::

    d(dp)/dt  = dv
    d(dv)/dt  = -[f_n x] dth - C_nb db_a - C_nb diag(f_b) ds_a + C_nb w_a
    d(dth)/dt = -C_nb db_g - C_nb diag(omega_b) ds_g + C_nb w_g
    d(db)/dt  = w_b                        (both sensors; see below)
    d(dmu)/dt = w_mu,  d(ds)/dt = w_s      (slow random walks)
    d(de)/dt  = -de / T_e + w_e            (GNSS error, Gauss-Markov)

The true biases are a turn-on constant plus a first-order Gauss-Markov in-run part; the
nominal bias is held between updates, so the *error* does not decay: it is driven by the
Gauss-Markov noise ``2 s^2 / T_c`` (the engine passes zero decay rates; ``A[BA, BA]`` and
``A[BG, BG]`` stay available for a decaying nominal). The GNSS error estimate ``e`` is decayed
by the engine as its error model decays, so ``-de / T_e`` holds.

``F = A`` above; over a covariance interval ``T`` (a few IMU samples, with the mean ``C_nb``,
``f_b``, ``omega_b``) ``Phi = I + A T + (A T)^2 / 2`` and ``Q_d = G Q_c G^T T`` with
``Q_c = diag(N_a^2, N_g^2 + k_w |omega|^2, 2 s_ba^2/T_c, 2 s_bg^2/T_c, q_mu, q_s, 2 s_e^2/T_e)``
(noise densities ``N`` and bias-instability sigmas ``s`` from the sensor datasheet;
``k_w = 2 m_g^2 tau_m`` turns the datasheet gyro cross-axis sensitivity ``m_g`` into a
rate-dependent attitude noise with ``tau_m = 1 s``).

Measurements (each returns ``Meas(name, y, H, R)``, ``y = z - h(x)``, or ``None``)
---------------------------------------------------------------------------------
GNSS position with lever arm ``l_b`` (antenna in ``b``)::

    h = p + C_nb l_b + e,       H_p = I, H_th = -[(C_nb l_b) x], H_e = I

GNSS velocity (2 rows from NMEA speed and course, 3 when the receiver gives ``vd``)::

    h = v + C_nb (omega_b x l_b),  H_v = I, H_th = -[(C_nb (omega x l)) x],
    H_bg = C_nb [l_b x] K, H_sg = C_nb [l_b x] K diag(omega_b),  K = diag(1 / (1 + s_g))

Non-holonomic constraint (Shin 2005, §4.3; Sukkarieh 2000): lateral and vertical velocity
of the vehicle are zero, ``v_v = C_vb C_nb^T v_n``, rows y and z::

    H_v = C_vn, H_th = C_vn [v_n x], H_mu = -[v_v x]

Zero velocity (``h = v``, ``H_v = I``) and zero angular rate (``h = omega``, ``H_bg = -K``,
``H_sg = -K diag(omega)``) while static. (In ``F`` the factor ``K`` is taken as ``I``.)

Magnetometer heading (calibrated ``m_b``, declination ``D``): ``m = C_nb m_b``,
``h = atan2(m_E, m_N)``, ``z = D``::

    H_th = [-m_N m_D / |m_h|^2, -m_E m_D / |m_h|^2, 1]

No Euler angle enters any model, so none is singular at pitch +-90 deg.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import NamedTuple

import numpy as np
import numpy.typing as npt

from iotnav.strapdown import rotvec_to_dcm

FloatArray = npt.NDArray[np.float64]

# ----------------------------------------------------------------------------- layout
POS = slice(0, 3)
VEL = slice(3, 6)
ATT = slice(6, 9)
BG = slice(9, 12)
BA = slice(12, 15)
MNT = slice(15, 18)
GNE = slice(18, 21)
SG = slice(21, 24)
SA = slice(24, 27)
#: Error-state size without / with scale-factor states.
N_BASE = 21
N_FULL = 27


def n_states(scale_factors: bool) -> int:
    """Error-state dimension for the chosen layout."""
    return N_FULL if scale_factors else N_BASE


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
        Time-correlated GNSS position error, m, ``n``.
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

    def copy(self) -> Nominal:
        """Deep copy."""
        return Nominal(*(np.array(getattr(self, k), dtype=float) for k in self.__dataclass_fields__))


def inject(nom: Nominal, dx: FloatArray) -> None:
    """Add an error-state estimate to the nominal state, in place (the ESKF reset)."""
    nom.p_n += dx[POS]
    nom.v_n += dx[VEL]
    nom.C_nb[:] = rotvec_to_dcm(dx[ATT]) @ nom.C_nb
    nom.b_g += dx[BG]
    nom.b_a += dx[BA]
    nom.C_vb[:] = rotvec_to_dcm(dx[MNT]) @ nom.C_vb
    nom.e_n += dx[GNE]
    if dx.size >= N_FULL:
        nom.s_g += dx[SG]
        nom.s_a += dx[SA]


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
    if n >= N_FULL:
        dx[SG] = true.s_g - est.s_g
        dx[SA] = true.s_a - est.s_a
    return dx


def compensate(raw: FloatArray, bias: FloatArray, scale: FloatArray) -> FloatArray:
    """Sensor output corrected for bias and scale factor: ``(raw - b) / (1 + s)``."""
    return (raw - bias) / (1.0 + scale)


# ----------------------------------------------------------------------------- propagation
#: Layout of the accumulator used between covariance propagations.
ACC_T, ACC_FN, ACC_FB, ACC_WB, ACC_C = 0, slice(1, 4), slice(4, 7), slice(7, 10), slice(10, 19)
ACC_SIZE = 19


def propagate_nominal(
    C_nb: FloatArray,
    v_n: FloatArray,
    p_n: FloatArray,
    f_b: FloatArray,
    omega_b: FloatArray,
    dt: float,
    g_n: FloatArray,
    acc: FloatArray,
) -> None:
    """One strapdown step (as :func:`iotnav.strapdown.step`) in place, plus accumulation.

    Parameters
    ----------
    C_nb, v_n, p_n : numpy.ndarray
        Attitude, velocity (m/s) and position (m), updated in place.
    f_b, omega_b : numpy.ndarray
        Compensated specific force (m/s^2) and angular rate (rad/s) in ``b``.
    dt : float
        Step, s.
    g_n : numpy.ndarray
        Gravity in ``n`` (m/s^2).
    acc : numpy.ndarray
        Accumulator (``ACC_*`` layout): interval length and time integrals of ``f_n``,
        ``f_b``, ``omega_b`` and ``C_nb``, for :func:`error_transition`.
    """
    R_half = rotvec_to_dcm((0.5 * dt) * omega_b)
    C_half = C_nb @ R_half
    f_n = C_half @ f_b
    v_old = v_n.copy()
    v_n += (f_n + g_n) * dt
    p_n += 0.5 * (v_old + v_n) * dt
    C_nb[:] = C_half @ R_half
    acc[ACC_T] += dt
    acc[ACC_FN] += f_n * dt
    acc[ACC_FB] += f_b * dt
    acc[ACC_WB] += omega_b * dt
    acc[ACC_C] += C_half.ravel() * dt


def error_transition(
    C_nb: FloatArray,
    f_b: FloatArray,
    omega_b: FloatArray,
    T: float,
    n: int,
    noise: FloatArray,
) -> tuple[FloatArray, FloatArray]:
    """Discrete error-state transition ``Phi`` and process noise ``Q_d`` over ``T`` seconds.

    Parameters
    ----------
    C_nb : numpy.ndarray
        Mean attitude over the interval.
    f_b, omega_b : numpy.ndarray
        Mean compensated specific force (m/s^2) and angular rate (rad/s).
    T : float
        Interval, s.
    n : int
        Error-state dimension (:data:`N_BASE` or :data:`N_FULL`).
    noise : numpy.ndarray
        ``[N_a^2, N_g^2, q_ba, q_bg, 1/T_a, 1/T_g, q_mu, q_s, q_e_h, q_e_v, 1/T_e, k_w]``: noise
        densities squared ((m/s^2)^2/Hz, (rad/s)^2/Hz), bias driving intensities, inverse
        correlation times (1/s), mount and scale random-walk intensities, GNSS-error driving
        intensities (m^2/s, horizontal and vertical), and ``k_w`` (s) scaling the rate-dependent
        attitude noise ``k_w |omega|^2`` that stands for the unmodelled gyro cross-axis
        coupling (and scale factor when it is not estimated).

    Returns
    -------
    Phi, Qd : numpy.ndarray
        ``(n, n)`` each.
    """
    A = np.zeros((n, n))
    f_n = C_nb @ f_b
    A[POS, VEL] = np.eye(3)
    A[VEL, ATT] = -skew(f_n)
    A[VEL, BA] = -C_nb
    A[ATT, BG] = -C_nb
    A[BA, BA] = -noise[4] * np.eye(3)
    A[BG, BG] = -noise[5] * np.eye(3)
    A[GNE, GNE] = -noise[10] * np.eye(3)
    if n >= N_FULL:
        A[VEL, SA] = -C_nb * f_b[None, :]
        A[ATT, SG] = -C_nb * omega_b[None, :]
    AT = A * T
    Phi = np.eye(n) + AT + 0.5 * (AT @ AT)
    q = np.zeros(n)
    q[VEL] = noise[0]
    q[ATT] = noise[1] + noise[11] * float(omega_b @ omega_b)
    q[BA] = noise[2]
    q[BG] = noise[3]
    q[MNT] = noise[6]
    q[GNE] = (noise[8], noise[8], noise[9])
    if n >= N_FULL:
        q[SG] = noise[7]
        q[SA] = noise[7]
    Qd = np.diag(q * T)
    return Phi, Qd


# ----------------------------------------------------------------------------- initialisation
def level_covariance(
    C_nb: FloatArray,
    f_b: FloatArray,
    g: float,
    var_ba_b: FloatArray,
    var_sa: FloatArray | None,
    tilt_white_std_rad: float,
) -> FloatArray:
    """Joint covariance of ``[ATT, BA(, SA)]`` right after accelerometer levelling.

    Levelling finds the ``C_nb`` that makes the mean measured specific force point up, so it
    absorbs the accelerometer error ``u_b = db_a + diag(f_b) ds_a``: at rest the horizontal
    velocity error rate ``-[f_n x] dth - C_nb u_b`` is zero, which with ``f_n = (0, 0, -g)``
    gives (Groves 2013, §14.3.1; Titterton & Weston 2004, §10.2)::

        dth = J u_b + w,   J = (1/g) [[0, 1, 0], [-1, 0, 0], [0, 0, 0]] C_nb

    i.e. the tilt error is the accelerometer error divided by gravity and fully correlated
    with it; ``w`` (``tilt_white_std_rad``) is the part not due to the sensor errors (noise
    of the mean, motion during the window). Yaw is not levelled (zero row).

    Parameters
    ----------
    C_nb : numpy.ndarray
        Levelled attitude.
    f_b : numpy.ndarray
        Mean measured specific force over the window, m/s^2.
    g : float
        Gravity, m/s^2.
    var_ba_b : numpy.ndarray
        Per-axis accelerometer bias variance, (m/s^2)^2.
    var_sa : numpy.ndarray or None
        Per-axis accelerometer scale-factor variance (None without scale-factor states).
    tilt_white_std_rad : float
        Independent tilt error, rad.

    Returns
    -------
    numpy.ndarray
        ``(6, 6)`` (``ATT``, ``BA``) or ``(9, 9)`` (``ATT``, ``BA``, ``SA``) covariance.
    """
    J = np.array([[0.0, 1.0, 0.0], [-1.0, 0.0, 0.0], [0.0, 0.0, 0.0]]) @ C_nb / g
    m = 6 if var_sa is None else 9
    # error sources s = [db_a, ds_a]; dth = [J, J diag(f_b)] s + w
    S = np.diag(np.concatenate([var_ba_b, [] if var_sa is None else var_sa]))
    B = np.zeros((m, m - 3))
    B[0:3, 0:3] = J
    if var_sa is not None:
        B[0:3, 3:6] = J * f_b[None, :]
    B[3:, :] = np.eye(m - 3)
    P = B @ S @ B.T
    P[0:2, 0:2] += tilt_white_std_rad**2 * np.eye(2)
    return 0.5 * (P + P.T)


def heading_reset_transform(dpsi: float, n: int) -> FloatArray:
    """Error-state transform when the nominal yaw is reset by ``dpsi`` (``C_nb <- R_z C_nb``).

    The filter runs before the heading is known in a navigation frame with an arbitrary yaw;
    resetting the yaw rotates that frame by ``R_z(dpsi)``, so every error resolved in ``n``
    (position, velocity, attitude, GNSS error) rotates with it: ``dx_n' = R_z dx_n``, and
    ``P' = T P T^T`` (the biases, mount and scale factors are in ``b``/``v`` and unchanged).
    Without it the tilt / accelerometer-bias correlation learnt at rest points the wrong way
    and makes the tilt spuriously observable.
    """
    c, s = math.cos(dpsi), math.sin(dpsi)
    R = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    T = np.eye(n)
    for sl in (POS, VEL, ATT, GNE):
        T[sl, sl] = R
    return T


# ----------------------------------------------------------------------------- measurements
class Meas(NamedTuple):
    """A linearised measurement: innovation ``y = z - h(x)``, Jacobian ``H`` and noise ``R``."""

    name: str
    y: FloatArray
    H: FloatArray
    R: FloatArray


def h_gnss_position(nom: Nominal, lever_b: FloatArray, n: int) -> tuple[FloatArray, FloatArray]:
    """Predicted antenna position (m, n) and its Jacobian."""
    l_n = nom.C_nb @ lever_b
    H = np.zeros((3, n))
    H[:, POS] = np.eye(3)
    H[:, ATT] = -skew(l_n)
    H[:, GNE] = np.eye(3)
    return nom.p_n + l_n + nom.e_n, H


def gnss_position(nom: Nominal, z_n: FloatArray, lever_b: FloatArray, sigma_m: FloatArray, n: int) -> Meas:
    """GNSS position update; ``sigma_m`` the white part of the error per NED axis, m."""
    h, H = h_gnss_position(nom, lever_b, n)
    return Meas("gnss_position", z_n - h, H, np.diag(sigma_m**2))


def h_gnss_velocity(
    nom: Nominal, omega_raw_b: FloatArray, lever_b: FloatArray, n: int
) -> tuple[FloatArray, FloatArray]:
    """Predicted antenna velocity (m/s, n) and Jacobian, from the raw gyro output (rad/s)."""
    w = compensate(omega_raw_b, nom.b_g, nom.s_g)
    u_n = nom.C_nb @ np.cross(w, lever_b)
    H = np.zeros((3, n))
    H[:, VEL] = np.eye(3)
    H[:, ATT] = -skew(u_n)
    k = 1.0 / (1.0 + nom.s_g)
    Cl = nom.C_nb @ skew(lever_b)
    H[:, BG] = Cl * k[None, :]
    if n >= N_FULL:
        H[:, SG] = Cl * (w * k)[None, :]
    return nom.v_n + u_n, H


def gnss_velocity(
    nom: Nominal, omega_raw_b: FloatArray, z_n: FloatArray, lever_b: FloatArray, sigma_mps: FloatArray, n: int
) -> Meas:
    """GNSS velocity update; ``z_n`` of length 2 (North, East) or 3 (with Down)."""
    h, H = h_gnss_velocity(nom, omega_raw_b, lever_b, n)
    m = z_n.size
    return Meas("gnss_velocity", z_n - h[:m], H[:m], np.diag(sigma_mps[:m] ** 2))


def h_nhc(nom: Nominal, n: int) -> tuple[FloatArray, FloatArray]:
    """Vehicle-frame lateral and vertical velocity (m/s) and Jacobian."""
    C_vn = nom.C_vb @ nom.C_nb.T
    v_v = C_vn @ nom.v_n
    H = np.zeros((3, n))
    H[:, VEL] = C_vn
    H[:, ATT] = C_vn @ skew(nom.v_n)
    H[:, MNT] = -skew(v_v)
    return v_v[1:], H[1:]


def nhc(nom: Nominal, sigma_lat_mps: float, sigma_vert_mps: float, n: int) -> Meas:
    """Non-holonomic constraint ``v_v[1:] = 0``."""
    h, H = h_nhc(nom, n)
    return Meas("nhc", -h, H, np.diag([sigma_lat_mps**2, sigma_vert_mps**2]))


def zupt(nom: Nominal, sigma_mps: float, n: int) -> Meas:
    """Zero-velocity update."""
    H = np.zeros((3, n))
    H[:, VEL] = np.eye(3)
    return Meas("zupt", -nom.v_n, H, sigma_mps**2 * np.eye(3))


def h_zaru(nom: Nominal, omega_raw_b: FloatArray, n: int) -> tuple[FloatArray, FloatArray]:
    """Compensated angular rate (rad/s, b) and Jacobian."""
    w = compensate(omega_raw_b, nom.b_g, nom.s_g)
    k = 1.0 / (1.0 + nom.s_g)
    H = np.zeros((3, n))
    H[:, BG] = -np.diag(k)
    if n >= N_FULL:
        H[:, SG] = -np.diag(w * k)
    return w, H


def zaru(nom: Nominal, omega_raw_mean_b: FloatArray, sigma_rads: float, n: int) -> Meas:
    """Zero-angular-rate update from the mean raw gyro output over a static interval."""
    h, H = h_zaru(nom, omega_raw_mean_b, n)
    return Meas("zaru", -h, H, sigma_rads**2 * np.eye(3))


def h_mag_heading(nom: Nominal, m_b: FloatArray, n: int) -> tuple[float, FloatArray] | None:
    """Azimuth of the horizontal field (rad) and Jacobian; None when the field is vertical."""
    m = nom.C_nb @ m_b
    hh = m[0] * m[0] + m[1] * m[1]
    if hh < 1e-6 * float(m @ m):
        return None
    H = np.zeros((1, n))
    H[0, ATT] = (-m[0] * m[2] / hh, -m[1] * m[2] / hh, 1.0)
    return math.atan2(m[1], m[0]), H


def mag_heading(
    nom: Nominal, m_b: FloatArray, declination_rad: float, sigma_rad: float, n: int
) -> Meas | None:
    """Magnetometer heading update (calibrated field ``m_b``, any unit)."""
    out = h_mag_heading(nom, m_b, n)
    if out is None:
        return None
    h, H = out
    y = math.remainder(declination_rad - h, 2.0 * math.pi)
    return Meas("mag_heading", np.array([y]), H, np.array([[sigma_rad**2]]))
