"""Measurement models of the ``eskf`` engine: each returns ``Meas(name, y, H, R)`` or None."""

from __future__ import annotations

import math
from typing import NamedTuple, TypeVar

import numba
import numpy as np
import numpy.typing as npt

from iotnav.engines.eskf.layout import (
    ATT,
    ATT_0,
    BA_0,
    BG,
    BG_0,
    GNE,
    GNM,
    MNT_0,
    N_FULL,
    POS,
    SA_0,
    SG,
    SG_0,
    VEL,
    VEL_0,
)
from iotnav.engines.eskf.state import Nominal, compensate, skew

FloatArray = npt.NDArray[np.float64]
#: A float or an array of floats, the same kind in and out.
FloatLike = TypeVar("FloatLike", float, FloatArray)


# ----------------------------------------------------------------------------- measurements
class Meas(NamedTuple):
    """A linearised measurement: innovation ``y = z - h(x)``, Jacobian ``H`` and noise ``R``."""

    name: str
    y: FloatArray
    H: FloatArray
    R: FloatArray


def gm_variance_factor(corr_time_s: FloatLike, filter_s: float) -> FloatLike:
    """``var(e_gm) / var(e) = (T_e + t_f) / T_e`` of the GNSS error model (:mod:`iotnav.engines.eskf.models`).

    The receiver's output ``e`` is the Gauss-Markov error ``e_gm`` (correlation time ``T_e``,
    s) through a first-order low-pass of time constant ``t_f`` (s; 0 or less: none, factor 1);
    its stationary variance is ``var(e_gm) T_e / (T_e + t_f)`` (Gelb 1974, sec. 3.8), so
    ``e_gm`` is scaled by this factor to give ``e`` the variance of the fix accuracy.
    ``corr_time_s`` may be an array (one ``T_e`` per axis).
    """
    return (corr_time_s + max(filter_s, 0.0)) / corr_time_s


def stationary_gnss_error_cov(
    var_e: FloatArray, corr_time_s: float | FloatArray, filter_s: float
) -> FloatArray:
    """Stationary covariance ``(2k, 2k)`` of ``[e, e_gm]`` on ``k`` axes, m^2.

    ``var(e) = cov(e, e_gm) = var_e``, ``var(e_gm) = gm_variance_factor var_e`` per axis
    (``var_e`` ``(k,)``, m^2; ``corr_time_s`` one value or ``(k,)``, s); without receiver
    smoothing (``filter_s <= 0``) ``e`` is the Gauss-Markov error itself and ``e_gm`` is inert
    (zero rows). A position set from a fix,
    ``r = z - e`` with ``e`` estimated 0, has ``cov(dr, [de, de_gm]) = -`` the first ``k`` rows.
    """
    v = np.diag(np.asarray(var_e, dtype=np.float64))
    z = np.zeros_like(v)
    if filter_s <= 0.0:
        return np.block([[v, z], [z, z]])
    te = np.broadcast_to(np.asarray(corr_time_s, dtype=np.float64), v.shape[:1])
    f = gm_variance_factor(te, filter_s)
    return np.block([[v, v], [v, np.diag(f * np.diag(v))]])


def h_gnss_position(nom: Nominal, lever_b: FloatArray, n: int) -> tuple[FloatArray, FloatArray]:
    """Predicted antenna position (m, n) and its Jacobian."""
    l_n = nom.C_nb @ lever_b
    H = np.zeros((3, n))
    H[:, POS] = np.eye(3)
    H[:, ATT] = -skew(l_n)
    H[:, GNE] = np.eye(3)
    return nom.p_n + l_n + nom.e_n, H


def gnss_position(nom: Nominal, z_n: FloatArray, lever_b: FloatArray, sigma_m: FloatArray, n: int) -> Meas:
    """GNSS position with lever arm, loosely coupled (Groves 2013, ch. 14).

    The antenna at ``l_b`` (``b``) reports ``z = p + C_nb l_b + e + w``: ``e`` the
    time-correlated receiver error carried as the ``GNE`` states (package docstring, "GNSS"),
    ``w`` white. ``y = z - h``, ``H_p = I``, ``H_th = -[(C_nb l_b) x]``, ``H_e = I``
    (:func:`h_gnss_position`), ``R = diag(sigma_m^2)``.

    Parameters
    ----------
    nom : Nominal
        Nominal state.
    z_n : numpy.ndarray
        Antenna position, m, NED about the origin.
    lever_b : numpy.ndarray
        Antenna position relative to the IMU, m, ``b``.
    sigma_m : numpy.ndarray
        1-sigma of the white part of the error per NED axis, m.
    n : int
        Error-state size.

    Returns
    -------
    Meas
        ``gnss_position``, 3 rows.
    """
    h, H = h_gnss_position(nom, lever_b, n)
    return Meas("gnss_position", z_n - h, H, np.diag(sigma_m**2))


def h_gnss_velocity(
    nom: Nominal, omega_raw_b: FloatArray, lever_b: FloatArray, n: int, inv_tf: float = 0.0
) -> tuple[FloatArray, FloatArray]:
    """Predicted antenna velocity (m/s, n) and Jacobian, from the raw gyro output (rad/s).

    ``inv_tf``: inverse time constant of the receiver's position smoothing (1/s); its
    velocity then carries the derivative of the smoothed position error,
    ``(e_gm - e_n) / t_f``; 0: none.
    """
    w = compensate(omega_raw_b, nom.b_g, nom.s_g)
    lb = lever_b
    w_x_l = np.array([w[1] * lb[2] - w[2] * lb[1], w[2] * lb[0] - w[0] * lb[2], w[0] * lb[1] - w[1] * lb[0]])
    u_n = nom.C_nb @ w_x_l  # C_nb (omega x l_b)
    H = np.zeros((3, n))
    H[:, VEL] = np.eye(3)
    H[:, ATT] = -skew(u_n)
    k = 1.0 / (1.0 + nom.s_g)
    Cl = nom.C_nb @ skew(lever_b)
    H[:, BG] = Cl * k[None, :]
    if n >= N_FULL:
        H[:, SG] = Cl * (w * k)[None, :]
    H[:, GNE] = -inv_tf * np.eye(3)
    H[:, GNM] = inv_tf * np.eye(3)
    return nom.v_n + u_n + inv_tf * (nom.e_gm - nom.e_n), H


def gnss_velocity(
    nom: Nominal,
    omega_raw_b: FloatArray,
    z_n: FloatArray,
    lever_b: FloatArray,
    sigma_mps: FloatArray,
    n: int,
    inv_tf: float = 0.0,
) -> Meas:
    """GNSS velocity with lever arm, loosely coupled (Groves 2013, ch. 14).

    ``z = v + C_nb (omega_b x l_b) + (e_gm - e) / t_f + w_D``: the lever arm's rotation, the
    derivative of the receiver's smoothed position error (the GNSS error model of
    :mod:`iotnav.engines.eskf.models`; Gelb 1974, §3.8) and white Doppler noise ``w_D``,
    whose 1-sigma ``sigma_mps`` is all of ``R``. Jacobian in :func:`h_gnss_velocity`.

    Parameters
    ----------
    nom : Nominal
        Nominal state.
    omega_raw_b : numpy.ndarray
        Raw gyro output, rad/s, ``b``.
    z_n : numpy.ndarray
        Velocity, m/s, NED: 2 elements (North, East: NMEA speed and course) or 3 (with Down).
    lever_b : numpy.ndarray
        Antenna position relative to the IMU, m, ``b``.
    sigma_mps : numpy.ndarray
        1-sigma of the white (Doppler) part per axis, m/s.
    n : int
        Error-state size.
    inv_tf : float, optional
        Inverse time constant of the receiver's position smoothing, 1/s (0: none).

    Returns
    -------
    Meas
        ``gnss_velocity``, as many rows as ``z_n``.
    """
    h, H = h_gnss_velocity(nom, omega_raw_b, lever_b, n, inv_tf)
    m = z_n.size
    return Meas("gnss_velocity", z_n - h[:m], H[:m], np.diag(sigma_mps[:m] ** 2))


@numba.njit(cache=True)
def nhc_rows(C_nb: FloatArray, v_n: FloatArray, C_vb: FloatArray, h: FloatArray, H: FloatArray) -> None:
    """Vehicle lateral and vertical velocity ``h[:2]`` (m/s) and Jacobian rows ``H[:2]`` (compiled).

    ``v_v = C_vn v_n`` with ``C_vn = C_vb C_nb^T``; rows y and z of ``H_v = C_vn``,
    ``H_th = C_vn [v_n x]``, ``H_mu = -[v_v x]``. The rest of ``H[:2]`` is zeroed.

    Parameters
    ----------
    C_nb, v_n, C_vb : numpy.ndarray
        Attitude (``b`` to ``n``), velocity (m/s, ``n``), mount (``b`` to ``v``).
    h : numpy.ndarray
        Receives the predicted lateral and vertical vehicle velocity (m/s) in ``h[:2]``.
    H : numpy.ndarray
        ``(>= 2, n)``, receives the Jacobian in its first two rows.
    """
    H[0:2, :] = 0.0
    C = np.empty((3, 3))
    for r in range(3):
        for c in range(3):
            C[r, c] = C_vb[r, 0] * C_nb[c, 0] + C_vb[r, 1] * C_nb[c, 1] + C_vb[r, 2] * C_nb[c, 2]
    vv0 = C[0, 0] * v_n[0] + C[0, 1] * v_n[1] + C[0, 2] * v_n[2]
    vv1 = C[1, 0] * v_n[0] + C[1, 1] * v_n[1] + C[1, 2] * v_n[2]
    vv2 = C[2, 0] * v_n[0] + C[2, 1] * v_n[1] + C[2, 2] * v_n[2]
    h[0] = vv1
    h[1] = vv2
    for k in range(2):
        r = k + 1
        for c in range(3):
            H[k, VEL_0 + c] = C[r, c]
        # row r of C_vn [v x] = (row r) x v
        H[k, ATT_0] = C[r, 1] * v_n[2] - C[r, 2] * v_n[1]
        H[k, ATT_0 + 1] = C[r, 2] * v_n[0] - C[r, 0] * v_n[2]
        H[k, ATT_0 + 2] = C[r, 0] * v_n[1] - C[r, 1] * v_n[0]
    # -[v_v x], rows y and z
    H[0, MNT_0] = -vv2
    H[0, MNT_0 + 2] = vv0
    H[1, MNT_0] = vv1
    H[1, MNT_0 + 1] = -vv0


def h_nhc(nom: Nominal, n: int) -> tuple[FloatArray, FloatArray]:
    """Vehicle-frame lateral and vertical velocity (m/s) and Jacobian (:func:`nhc_rows`)."""
    h = np.zeros(3)
    H = np.zeros((3, n))
    nhc_rows(nom.C_nb, nom.v_n, nom.C_vb, h, H)
    return h[:2], H[:2]


def nhc(nom: Nominal, sigma_lat_mps: float, sigma_vert_mps: float, n: int) -> Meas:
    """Non-holonomic constraint: a wheeled vehicle does not slip sideways nor leave the road.

    ``z = 0`` for the lateral and vertical vehicle velocity ``v_v = C_vb C_nb^T v_n`` (rows
    y and z; Shin 2005, "Estimation techniques for low-cost inertial navigation", §4.3;
    Sukkarieh 2000; Groves 2013, ch. 15, motion constraints), Jacobian in :func:`nhc_rows`,
    ``R = diag(sigma_lat^2, sigma_vert^2)`` (m/s).
    """
    h, H = h_nhc(nom, n)
    return Meas("nhc", -h, H, np.diag([sigma_lat_mps**2, sigma_vert_mps**2]))


@numba.njit(cache=True)
def zupt_rows(v_n: FloatArray, y: FloatArray, H: FloatArray) -> None:
    """Zero-velocity innovation ``y = -v_n`` (m/s, ``n``) and ``H[:3]`` (``H_v = I``; compiled).

    Parameters
    ----------
    v_n : numpy.ndarray
        Velocity, m/s, ``n``.
    y : numpy.ndarray
        Receives the innovation (3).
    H : numpy.ndarray
        ``(>= 3, n)``, receives the Jacobian in its first three rows.
    """
    H[0:3, :] = 0.0
    for i in range(3):
        y[i] = -v_n[i]
        H[i, VEL_0 + i] = 1.0


def zupt(nom: Nominal, sigma_mps: float, n: int) -> Meas:
    """Zero-velocity update while static: ``z = 0 = v_n`` with ``R = sigma^2 I`` (m/s).

    ``H_v = I`` (:func:`zupt_rows`; Groves 2013, ch. 15, zero updates).
    """
    y = np.zeros(3)
    H = np.zeros((3, n))
    zupt_rows(nom.v_n, y, H)
    return Meas("zupt", y, H, sigma_mps**2 * np.eye(3))


@numba.njit(cache=True)
def zaru_rows(
    omega_raw_b: FloatArray, b_g: FloatArray, s_g: FloatArray, h: FloatArray, H: FloatArray
) -> None:
    """Compensated angular rate ``h`` (rad/s, b) and ``H[:3]`` (compiled; SG columns when ``H`` has them).

    ``H_bg = -K``, ``H_sg = -K diag(omega)``, ``K = diag(1 / (1 + s_g))``.

    Parameters
    ----------
    omega_raw_b : numpy.ndarray
        Raw gyro output, rad/s, ``b``.
    b_g, s_g : numpy.ndarray
        Gyro bias (rad/s, ``b``) and scale-factor error.
    h : numpy.ndarray
        Receives the compensated rate (3).
    H : numpy.ndarray
        ``(>= 3, n)``, receives the Jacobian in its first three rows.
    """
    H[0:3, :] = 0.0
    for i in range(3):
        k = 1.0 / (1.0 + s_g[i])
        w = (omega_raw_b[i] - b_g[i]) / (1.0 + s_g[i])
        h[i] = w
        H[i, BG_0 + i] = -k
        if H.shape[1] >= N_FULL:
            H[i, SG_0 + i] = -(w * k)


def h_zaru(nom: Nominal, omega_raw_b: FloatArray, n: int) -> tuple[FloatArray, FloatArray]:
    """Compensated angular rate (rad/s, b) and Jacobian (:func:`zaru_rows`)."""
    h = np.zeros(3)
    H = np.zeros((3, n))
    zaru_rows(np.ascontiguousarray(omega_raw_b, dtype=np.float64), nom.b_g, nom.s_g, h, H)
    return h, H


def zaru(nom: Nominal, omega_raw_mean_b: FloatArray, sigma_rads: float, n: int) -> Meas:
    """Zero-angular-rate update from the mean raw gyro output over a static interval.

    At rest the compensated rate ``(omega_raw - b_g) / (1 + s_g)`` is zero (the earth rate is
    below the MEMS noise): ``z = 0``, ``H_bg = -K``, ``H_sg = -K diag(omega)`` (:func:`zaru_rows`;
    Groves 2013, ch. 15, zero updates), ``R = sigma^2 I`` (rad/s).
    """
    h, H = h_zaru(nom, omega_raw_mean_b, n)
    return Meas("zaru", -h, H, sigma_rads**2 * np.eye(3))


@numba.njit(cache=True)
def gravity_rows(
    C_nb: FloatArray, f_raw_b: FloatArray, b_a: FloatArray, s_a: FloatArray, h: FloatArray, H: FloatArray
) -> None:
    """Horizontal specific force in ``n``, ``h[:2]`` (m/s^2), and ``H[:2]`` (compiled).

    Gravity aiding of the tilt (as an AHRS levels itself, Groves 2013, §10.1.1, §16.2.1):
    with a small kinematic acceleration ``a_n`` the specific force ``C_nb f_b = a_n - g_n``
    has no horizontal part, so ``z = 0`` with ``a_n``'s size in ``R``. With
    ``f = (f_raw - b_a) / (1 + s_a)`` and ``f_n = C_nb f``::

        h = (f_n)_NE,  H_th = -[f_n x]_NE,  H_ba = -(C_nb K)_NE,  H_sa = -(C_nb K diag(f))_NE

    ``K = diag(1 / (1 + s_a))`` (SA columns when ``H`` has them). Rows of the yaw error are
    ``-[f_n x]`` too: with ``f_n`` nearly vertical they are nearly zero, and before the
    heading is known the engine keeps the yaw error out of the filter anyway.

    Parameters
    ----------
    C_nb : numpy.ndarray
        Attitude (``b`` to ``n``).
    f_raw_b : numpy.ndarray
        Mean raw accelerometer output over the aiding interval, m/s^2, ``b``.
    b_a, s_a : numpy.ndarray
        Accelerometer bias (m/s^2, ``b``) and scale-factor error.
    h : numpy.ndarray
        Receives the predicted horizontal specific force (N, E) in ``h[:2]``.
    H : numpy.ndarray
        ``(>= 2, n)``, receives the Jacobian in its first two rows.
    """
    H[0:2, :] = 0.0
    f = np.empty(3)
    k = np.empty(3)
    for i in range(3):
        k[i] = 1.0 / (1.0 + s_a[i])
        f[i] = (f_raw_b[i] - b_a[i]) * k[i]
    fn = np.empty(3)
    for r in range(3):
        fn[r] = C_nb[r, 0] * f[0] + C_nb[r, 1] * f[1] + C_nb[r, 2] * f[2]
    h[0] = fn[0]
    h[1] = fn[1]
    # -[f_n x] rows N, E
    H[0, ATT_0 + 1] = fn[2]
    H[0, ATT_0 + 2] = -fn[1]
    H[1, ATT_0] = -fn[2]
    H[1, ATT_0 + 2] = fn[0]
    full = H.shape[1] >= N_FULL
    for r in range(2):
        for c in range(3):
            H[r, BA_0 + c] = -C_nb[r, c] * k[c]
            if full:
                H[r, SA_0 + c] = -C_nb[r, c] * k[c] * f[c]


def h_gravity(nom: Nominal, f_raw_b: FloatArray, n: int) -> tuple[FloatArray, FloatArray]:
    """Horizontal specific force in ``n`` (m/s^2) and Jacobian (:func:`gravity_rows`)."""
    h = np.zeros(3)
    H = np.zeros((3, n))
    gravity_rows(nom.C_nb, np.ascontiguousarray(f_raw_b, dtype=np.float64), nom.b_a, nom.s_a, h, H)
    return h[:2], H[:2]


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
    """Magnetometer heading update (calibrated field ``m_b``, any unit).

    The azimuth of the horizontal field in ``n`` is the declination ``D``:
    ``h = atan2(m_E, m_N)`` with ``m = C_nb m_b``, ``z = D``, ``y`` wrapped to
    ``(-pi, pi]``, ``H_th = [-m_N m_D / |m_h|^2, -m_E m_D / |m_h|^2, 1]`` (:func:`h_mag_heading`;
    Groves 2013, ch. 6, magnetic heading), ``R = sigma^2`` (rad). None when the field is vertical.
    """
    out = h_mag_heading(nom, m_b, n)
    if out is None:
        return None
    h, H = out
    y = math.remainder(declination_rad - h, 2.0 * math.pi)
    return Meas("mag_heading", np.array([y]), H, np.array([[sigma_rad**2]]))
