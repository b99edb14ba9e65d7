"""State layout and models of the quaternion EKF (:mod:`iotnav.engines.qekf`, whose docstring
states the equations): quaternion algebra, the prediction :func:`propagate` (Eq. 8 with its
Jacobian), and the measurement models as ``(z, H, R)`` (GNSS position and velocity, Eq. 10;
TRIAD attitude, Eq. 7; magnetometer direction; quaternion norm, Eq. 9; non-holonomic).

These are the readable reference forms: the engine's per-sample prediction is compiled in
:mod:`iotnav.engines.qekf_kernel` and its updates in :mod:`iotnav.engines.qekf_updates_kernel`,
both tested against these.
"""

from __future__ import annotations

import math

import numpy as np
import numpy.typing as npt

from iotnav.geo import skew
from iotnav.techniques.triad import dcm_to_quat, improved_triad, quat_to_dcm, triad_covariance, triad_jacobian
from iotnav.wmm import reference_field

FloatArray = npt.NDArray[np.float64]

#: State layout.
Q_NB = slice(0, 4)
VEL = slice(4, 7)
POS = slice(7, 10)
BG = slice(10, 13)
BA = slice(13, 16)
SG = slice(16, 19)
SA = slice(19, 22)
N_STATES = 22
#: GNSS position error states of ``gnss_error_states`` (:mod:`iotnav.engines.qekf_gnss_error`), NED, m: the error
#: the fix carries (after the receiver's low-pass) and the Gauss-Markov error before it.
GNE = slice(22, 25)
GNM = slice(25, 28)
N_STATES_GNSS = 28
_GNE_I = np.arange(GNE.start, GNE.stop)
_GNM_I = np.arange(GNM.start, GNM.stop)

_I3 = np.eye(3)

#: The accelerometer's error states (bias and scale factor, Eq. 11): their estimation error
#: enters every TRIAD observation and the initial alignment alike (:mod:`iotnav.engines.qekf`).
_ACC_COLS = np.r_[BA, SA]
_CONJ = np.array([1.0, -1.0, -1.0, -1.0])


def quat_left(q: FloatArray) -> FloatArray:
    """``M_L(q)`` with ``q (x) p = M_L(q) p`` (scalar first)."""
    w, x, y, z = q
    return np.array([[w, -x, -y, -z], [x, w, -z, y], [y, z, w, -x], [z, -y, x, w]])


def quat_right(p: FloatArray) -> FloatArray:
    """``M_R(p)`` with ``q (x) p = M_R(p) q`` (scalar first)."""
    w, x, y, z = p
    return np.array([[w, -x, -y, -z], [x, w, z, -y], [y, -z, w, x], [z, y, -x, w]])


def delta_quat(theta: FloatArray) -> tuple[FloatArray, FloatArray]:
    """``dq(theta)`` (4,) and its Jacobian ``d dq / d theta`` (4, 3) for a rotation vector (rad)."""
    a2 = float(theta @ theta)
    if a2 < 1e-8:
        # series: sin(a/2)/a = 1/2 - a^2/48 + a^4/3840; cos(a/2) = 1 - a^2/8 + a^4/384
        s = 0.5 - a2 / 48.0 + a2 * a2 / 3840.0
        c = 1.0 - a2 / 8.0 + a2 * a2 / 384.0
        ds = -1.0 / 24.0 + a2 / 960.0  # (d/da (sin(a/2)/a)) / a
    else:
        a = math.sqrt(a2)
        s = math.sin(0.5 * a) / a
        c = math.cos(0.5 * a)
        ds = (0.5 * c / a - s / a) / a
    dq = np.array([c, s * theta[0], s * theta[1], s * theta[2]])
    J = np.empty((4, 3))
    J[0] = -0.5 * s * theta  # d cos(a/2) = -sin(a/2)/2 * theta/a
    J[1:] = s * _I3 + ds * np.outer(theta, theta)
    return dq, J


def rotate_jacobian(q: FloatArray, f: FloatArray) -> tuple[FloatArray, FloatArray]:
    """``C(q) f`` (quadratic form) and ``d(C(q) f)/dq`` (3, 4)."""
    w = q[0]
    v = q[1:]
    vxf = np.cross(v, f)
    Cf = (w * w - v @ v) * f + 2.0 * v * (v @ f) + 2.0 * w * vxf
    J = np.empty((3, 4))
    J[:, 0] = 2.0 * (w * f + vxf)
    J[:, 1:] = 2.0 * ((v @ f) * _I3 + np.outer(v, f) - np.outer(f, v) - w * skew(f))
    return Cf, J


def propagate(
    x: FloatArray, acc_b: FloatArray, gyro_b: FloatArray, dt: float, g_n: FloatArray
) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray]:
    """One prediction step (Eq. 8, :mod:`iotnav.engines.qekf`) with its Jacobians.

    Parameters
    ----------
    x : numpy.ndarray
        State (22,).
    acc_b, gyro_b : numpy.ndarray
        Raw specific force (m/s^2) and angular rate (rad/s) in ``b``, mean over the step.
    dt : float
        Step, s.
    g_n : numpy.ndarray
        Gravity in ``n``, m/s^2.

    Returns
    -------
    x_new : numpy.ndarray
        Predicted state (22,).
    F : numpy.ndarray
        ``d x_new / d x`` (22, 22).
    G_g, G_a : numpy.ndarray
        ``d x_new / d gyro_b`` and ``d x_new / d acc_b`` (22, 3).
    """
    q = x[Q_NB]
    v = x[VEL]
    r = x[POS]
    bg, ba, sg, sa = x[BG], x[BA], x[SG], x[SA]
    w = (gyro_b - bg) / sg
    f = (acc_b - ba) / sa
    theta = w * dt
    dq, Jdq = delta_quat(theta)
    dqh, Jdqh = delta_quat(0.5 * theta)
    ML = quat_left(q)
    q_new = ML @ dq
    q_mid = ML @ dqh
    Cf, Jcf = rotate_jacobian(q_mid, f)
    C_mid = quat_to_dcm(q_mid)
    a = Cf + g_n
    x_new = x.copy()
    x_new[Q_NB] = q_new
    x_new[VEL] = v + a * dt
    x_new[POS] = r + v * dt + 0.5 * dt * dt * a
    dth_dbg = -dt * np.diag(1.0 / sg)
    dth_dsg = -dt * np.diag(w / sg)
    dq_dth = ML @ Jdq
    da_dq = Jcf @ quat_right(dqh)
    da_dth = 0.5 * (Jcf @ (ML @ Jdqh))
    da_dba = -C_mid / sa  # column j scaled by 1/sa_j
    da_dsa = -C_mid * (f / sa)
    F = np.eye(N_STATES)
    F[Q_NB, Q_NB] = quat_right(dq)
    F[Q_NB, BG] = dq_dth @ dth_dbg
    F[Q_NB, SG] = dq_dth @ dth_dsg
    h2 = 0.5 * dt * dt
    for rows, k in ((VEL, dt), (POS, h2)):
        F[rows, Q_NB] = k * da_dq
        F[rows, BG] = k * (da_dth @ dth_dbg)
        F[rows, SG] = k * (da_dth @ dth_dsg)
        F[rows, BA] = k * da_dba
        F[rows, SA] = k * da_dsa
    F[POS, VEL] = dt * _I3
    G_g = np.zeros((N_STATES, 3))
    G_g[:10] = -F[:10, BG]
    G_a = np.zeros((N_STATES, 3))
    G_a[:10] = -F[:10, BA]
    return x_new, F, G_g, G_a


# ----------------------------------------------------------------------------- measurement models


def position_measurement(r_n: FloatArray, R: FloatArray) -> tuple[FloatArray, FloatArray, FloatArray]:
    """GNSS position in ``n`` (m) as ``(z, H, R)``."""
    H = np.zeros((3, N_STATES))
    H[:, POS] = _I3
    return r_n, H, R


def velocity_measurement(v: FloatArray, sigma_mps: float) -> tuple[FloatArray, FloatArray, FloatArray]:
    """GNSS velocity in ``n`` (2 horizontal or 3 components, m/s) as ``(z, H, R)``."""
    m = v.size
    H = np.zeros((m, N_STATES))
    H[:, VEL.start : VEL.start + m] = np.eye(m)
    return v, H, np.eye(m) * sigma_mps**2


def quaternion_measurement(
    q_obs: FloatArray, q_state: FloatArray, P_theta_n: FloatArray, norm_std: float
) -> tuple[FloatArray, FloatArray, FloatArray]:
    """Attitude quaternion observation as ``(z, H, R)``.

    Parameters
    ----------
    q_obs : numpy.ndarray
        Observed unit quaternion ``q_nb``; its sign is matched to ``q_state``.
    q_state : numpy.ndarray
        Current state quaternion.
    P_theta_n : numpy.ndarray
        Rotation-vector covariance of the observation in ``n``, rad^2.
    norm_std : float
        Sigma along the quaternion itself (keeps ``R`` positive definite).
    """
    z = q_obs if float(q_obs @ q_state) >= 0.0 else -q_obs
    Xi = quat_right(z)[:, 1:]
    R = 0.25 * Xi @ P_theta_n @ Xi.T + norm_std**2 * np.outer(z, z)
    H = np.zeros((4, N_STATES))
    H[:, Q_NB] = np.eye(4)
    return z, H, R


def mag_direction_measurement(
    q: FloatArray, m_b: FloatArray, m_n: FloatArray, sigma: float
) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray]:
    """The magnetic field's direction in ``b`` as a 2-dof observation of the attitude alone.

    Used by ``mag_observation = "direction"`` (:mod:`iotnav.engines.qekf`, "Consistent form"): unlike
    the TRIAD observation it takes nothing from the accelerometer, whose samples the
    prediction already integrates. With ``u = m / |m|`` and the scale-invariant prediction
    ``u_b(q) = C(q)^T u_n / |q|^2`` (``C`` the quadratic form, so ``|q| != 1`` does not
    change it), the measured and predicted unit vectors are projected on two unit axes ``E``
    perpendicular to the prediction (the component along it is of second order)::

        z = E^T u~_b,   h(x) = E^T u_b(q) = 0,   H_q = E^T d(C(q)^T u_n)/dq / |q|^2
        R = sigma^2 I_2

    Parameters
    ----------
    q : numpy.ndarray
        State quaternion ``q_nb`` (4,), scalar first.
    m_b : numpy.ndarray
        Calibrated magnetometer sample in ``b`` (3,), any unit.
    m_n : numpy.ndarray
        Reference field in ``n`` (NED, 3), any unit.
    sigma : float
        Direction noise of one sample, rad.

    Returns
    -------
    z, H, R, h_x : numpy.ndarray
        Measurement (2,), Jacobian (2, 22), noise (2, 2) and prediction (2,).
    """
    qc = q * _CONJ  # C(q)^T = C(q*)
    u_n = m_n / float(np.linalg.norm(m_n))
    h, J = rotate_jacobian(qc, u_n)
    u = h / float(np.linalg.norm(h))
    e1 = np.cross(u, _I3[0] if abs(u[0]) < 0.9 else _I3[1])
    e1 /= float(np.linalg.norm(e1))
    E = np.stack([e1, np.cross(u, e1)])
    H = np.zeros((2, N_STATES))
    H[:, Q_NB] = (E @ (J * _CONJ)) / float(q @ q)
    z = E @ (m_b / float(np.linalg.norm(m_b)))
    return z, H, sigma**2 * np.eye(2), np.zeros(2)


def triad_measurement(
    q_state: FloatArray,
    g_b: FloatArray,
    m_b: FloatArray,
    g_n: FloatArray,
    m_n: FloatArray,
    sigma_g: float,
    sigma_m: float,
    norm_std: float,
    dg_dx: FloatArray,
    P: FloatArray | None = None,
    exact_cols: npt.NDArray[np.intp] | None = None,
) -> tuple[FloatArray, FloatArray, FloatArray]:
    """Improved-TRIAD attitude observation with its dependence on the state, ``(z, H, R)``.

    The gravity vector ``g_b`` is built from the accelerometer corrected with the *estimated*
    bias and scale factor and the estimated vehicle acceleration, so the observation is
    ``z = T(g_b(x_hat)) = q_true - (dT/dx) (x_true - x_hat) + noise`` to first order: its
    measurement function is ``h(x) = q + (dT/dx)(x_hat - x)`` and
    ``H = [I4 at Q_NB] - 1/2 Xi J_g dg_dx`` with ``J_g = d theta_n / d g_b``
    (:func:`~iotnav.techniques.triad.triad_jacobian`) and ``Xi = M_R(z)[:, 1:]``
    (``q' = [1, dtheta/2] (x) q``). ``h(x_hat) = q_hat``, so the innovation is unchanged; the
    extra columns give the bias states the variance and the correlation with the tilt that the
    observation carries.

    Parameters
    ----------
    q_state : numpy.ndarray
        State quaternion (the observation's sign is matched to it).
    g_b, m_b : numpy.ndarray
        Gravity (down, m/s^2) and calibrated magnetic field (uT) in ``b``.
    g_n, m_n : numpy.ndarray
        Their references in ``n``.
    sigma_g, sigma_m : float
        Direction standard deviations, rad.
    norm_std : float
        Sigma along the quaternion itself.
    dg_dx : numpy.ndarray
        ``d g_b / d x`` (3, N_STATES), the gravity vector's dependence on the state estimate.
    P : numpy.ndarray or None
        State covariance (N_STATES, N_STATES). None: every column of ``J_x`` goes into ``H``
        (exact linear model). Given: the columns not in ``exact_cols`` are treated as noise,
        ``R += J_n P J_n^T`` with ``J_n`` those columns of ``J_x`` (:mod:`iotnav.engines.qekf`).
    exact_cols : numpy.ndarray of int or None
        With ``P``: state indices whose dependence goes into ``H`` all the same (the
        accelerometer's bias and scale factor in the engine's default coupling).
    """
    # the readable reference form: the engine runs its compiled twin,
    # iotnav.engines.qekf_updates_kernel.triad_model (tests/test_qekf_kernel.py compares them)
    C = improved_triad(g_b, m_b, g_n, m_n, sigma_g, sigma_m)
    P_th = triad_covariance(g_n, m_n, sigma_g, sigma_m)
    z, H, R = quaternion_measurement(dcm_to_quat(C), q_state, P_th, norm_std)
    J_g, _ = triad_jacobian(g_b, m_b, g_n, m_n, sigma_g, sigma_m)
    Jx = 0.5 * (quat_right(z)[:, 1:] @ J_g) @ dg_dx
    if P is None:
        return z, H - Jx, R
    if exact_cols is not None:
        Je = np.zeros_like(Jx)
        Je[:, exact_cols] = Jx[:, exact_cols]
        H = H - Je
        Jx = Jx - Je
    return z, H, R + Jx @ P @ Jx.T


def norm_measurement(x: FloatArray, sigma: float) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray]:
    """Pseudo-observation ``e = 1 - |q| = 0`` (Eq. 9) as ``(z, H, R, h_x)``."""
    q = x[Q_NB]
    nq = float(np.linalg.norm(q))
    H = np.zeros((1, N_STATES))
    H[0, Q_NB] = -q / nq
    return np.zeros(1), H, np.array([[sigma**2]]), np.array([1.0 - nq])


def nhc_measurement(
    x: FloatArray, mount_yaw_rad: float, sigma_mps: float
) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray]:
    """Non-holonomic observation: vehicle lateral horizontal velocity 0, ``(z, H, R, h_x)``.

    ``h(x) = -sin(psi_v) v_N + cos(psi_v) v_E`` with ``psi_v = atan2(C_10, C_00) - mount_yaw_rad``
    (:mod:`iotnav.engines.qekf_fallback`, step 4; m/s). ``sigma_mps`` is the lateral-velocity sigma.
    """
    w, qx, qy, qz = x[Q_NB]
    c00 = w * w + qx * qx - qy * qy - qz * qz
    c10 = 2.0 * (qx * qy + w * qz)
    psi_v = math.atan2(c10, c00) - mount_yaw_rad
    sp, cp = math.sin(psi_v), math.cos(psi_v)
    vn, ve = float(x[VEL.start]), float(x[VEL.start + 1])
    h = -sp * vn + cp * ve
    d00 = 2.0 * np.array([w, qx, -qy, -qz])
    d10 = 2.0 * np.array([qz, qy, qx, w])
    dpsi_dq = (c00 * d10 - c10 * d00) / (c00 * c00 + c10 * c10)
    H = np.zeros((1, N_STATES))
    H[0, VEL] = [-sp, cp, 0.0]
    H[0, Q_NB] = -(cp * vn + sp * ve) * dpsi_dq
    return np.zeros(1), H, np.array([[sigma_mps**2]]), np.array([h])


def wmm_field_n(lat_deg: float, lon_deg: float, height_m: float, year: float) -> FloatArray:
    """World Magnetic Model field in NED at a point, microtesla (:func:`iotnav.wmm.reference_field`)."""
    return reference_field(lat_deg, lon_deg, height_m, year).field_n_ut


def _level(roll: float, pitch: float) -> FloatArray:
    cr, sr, cp, spp = math.cos(roll), math.sin(roll), math.cos(pitch), math.sin(pitch)
    return np.array([[cp, sr * spp, cr * spp], [0.0, cr, -sr], [-spp, sr * cp, cr * cp]])
