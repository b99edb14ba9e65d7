"""State layout, nominal state, error dynamics and measurement models of the ``eskf`` engine.

Everything here is a plain function on numpy arrays (STYLE §4-§7, §10): the engine
:mod:`iotnav.engines.eskf` wires them; the tests check every Jacobian against finite
differences through :func:`inject` / :func:`difference`. What runs per IMU sample is
numba-compiled and called both from Python and from the engine's compiled IMU kernel:
:func:`propagate_nominal`, :func:`transition_into` (behind :func:`error_transition`),
:func:`propagate_covariance` (and :func:`propagate_covariance_phi`, :func:`accumulate_transition`
for the RTS smoother), :func:`kalman_update`, :func:`inject_arrays` (behind
:func:`inject`), and the row builders :func:`nhc_rows`, :func:`zupt_rows`, :func:`zaru_rows`
(behind :func:`h_nhc`, :func:`zupt`, :func:`h_zaru`).

Error-state definitions (true = estimate (+) error)
---------------------------------------------------
::

    p_true = p + dp                  (POS, m, n)
    v_true = v + dv                  (VEL, m/s, n)
    C_nb_true = exp([dth x]) C_nb    (ATT, rad, rotation error resolved in n)
    b_g_true = b_g + db_g            (BG, rad/s, b)      b_a_true = b_a + db_a  (BA, m/s^2, b)
    C_vb_true = exp([dmu x]) C_vb    (MNT, rad, mount rotation error resolved in v)
    e_true = e + de                  (GNE, m, n: time-correlated GNSS position error, as output)
    e_gm_true = e_gm + de_gm         (GNM, m, n: the Gauss-Markov error before the receiver filter)
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
    d(de_gm)/dt = -de_gm / T_e + w_e       (GNSS error, Gauss-Markov)
    d(de)/dt  = (de_gm - de) / t_f         (seen through the receiver's low-pass)

The true biases are a turn-on constant plus a first-order Gauss-Markov in-run part; the
nominal bias is held between updates, so the *error* does not decay: it is driven by the
Gauss-Markov noise ``2 s^2 / T_c`` (the engine passes zero decay rates; ``A[BA, BA]`` and
``A[BG, BG]`` stay available for a decaying nominal). The GNSS error estimates ``e_gm``, ``e``
are propagated by the engine with the noise-free error model (exactly: ``e_gm`` decays by
``exp(-T/T_e)``), so the error equations above hold.

GNSS error model (receiver smoothing)
-------------------------------------
Consumer receivers (u-blox class) low-pass their navigation solution, so the position error
they report is not a first-order Gauss-Markov process but one seen through a first-order
filter of time constant ``t_f`` (``gnss_receiver_filter_s``, 2 s; the simulator's
``receiver_filter_s``, :mod:`iotnav.sim.gnss_model`): a second-order process, smooth at the
1 s fix interval. Its fix-to-fix change has variance
``2 sigma_e^2 (1 - rho(1 s))``, ``rho(L) = (T_e e^{-L/T_e} - t_f e^{-L/t_f}) / (T_e - t_f)``,
about ``sigma_e^2 L^2 / (T_e t_f)`` for ``L << t_f``, instead of ``2 sigma_e^2 L / T_e`` for
the first-order model (four times less at ``L = 1 s``, ``t_f = 2 s``; the first-order model made
the GNSS position NIS/dof ~0.11). ``e_gm`` is scaled so that ``e`` has the fix accuracy's
standard deviation ``sigma_e``: ``var(e_gm) = sigma_e^2 (T_e + t_f) / T_e``, driving intensity
``2 var(e_gm) / T_e``; stationary ``cov(e, e_gm) = sigma_e^2`` (Gelb 1974, §3.8). The receiver's
velocity comes from Doppler, so its error is the derivative of the smoothed position error plus
white Doppler noise: ``(e_gm - e) / t_f + w_D`` (the GNSS velocity model below), consistent with
the position model by construction. With ``t_f = 0`` the ``GNM`` states are inert and ``e`` is the
first-order Gauss-Markov process itself (``d(de)/dt = -de / T_e + w_e``).

``F = A`` above; over a covariance interval ``T`` (a few IMU samples, with the mean ``C_nb``,
``f_b``, ``omega_b``) ``Phi = I + A T + (A T)^2 / 2`` and ``Q_d = G Q_c G^T T`` with
``Q_c = diag(N_a^2, N_g^2 + q_w,j, q_ba,i, 2 s_bg^2/T_c, q_mu, q_s, 2 var(e_gm)/T_e)``,
``q_w,j = sum_i C_nb[j, i]^2 (k_w (|omega_b|^2 - omega_b,i^2) + k_s omega_b,i^2)`` on
navigation axis ``j`` and ``q_ba,i = 2 s_ba^2/T_c + k_a (|a_b|^2 - a_b,i^2)`` on sensor axis
``i`` (noise densities ``N`` and bias-instability sigmas ``s`` from the sensor datasheet; the
``k`` terms below).

Cross-axis coupling (not estimated; the off-diagonal elements of ``M`` in the sensor model
``(I + S + M) x``, each of 1-sigma ``m`` from the datasheet's cross-axis sensitivity). Both
errors scale with the motion, which stays correlated over a manoeuvre (a start, a brake, a
turn: ``tau_x`` of a few seconds, ``cross_axis_corr_time_s``); on sensor axis ``i``:

* Gyro, ``M_g omega_b``: a rate error of variance ``m_g^2 (|omega_b|^2 - omega_b,i^2)``
  correlated over ``tau_x``, taken as white attitude noise of the same intensity (PSD
  ``2 sigma^2 tau_x``): ``k_w = 2 m_g^2 tau_x``; resolved in ``n`` as the diagonal of
  ``C_nb diag(.) C_nb^T`` (``Q_d`` is kept diagonal; the dropped off-diagonal terms vanish
  when the sensor axes are aligned with ``n`` up to a yaw, as for a level car). Without scale-factor states the scale error ``s_g omega_b,i``
  is added likewise: ``k_s omega_b,i^2``, ``k_s = 2 s_g^2 tau_x``.
* Accelerometer, ``M_a f_b`` with ``f_b = a_b - C_nb^T g_n`` (``a_b`` the kinematic
  acceleration in ``b``, formed with standard gravity :data:`G_STD`): the gravity part is
  constant while the tilt holds, i.e. a further turn-on bias of variance
  ``m_a^2 (|f_b|^2 - f_b,i^2)``, added to the bias variance at levelling; the kinematic part
  ``M_a a_b`` is an offset of variance ``m_a^2 (|a_b|^2 - a_b,i^2)`` that changes from one
  manoeuvre to the next, i.e. a bias wandering with correlation time ``tau_x``: the driving
  intensity of a first-order Gauss-Markov process of that variance, ``k_a = 2 m_a^2 / tau_x``,
  is added to the accelerometer bias noise (the bias error, held between updates, does not
  decay). As white velocity noise instead it would not reach the bias and tilt estimates
  that it corrupts.

Over 20 Monte Carlo runs of 90 s ``car-tunnel`` (MPU-6050 preset, 2/3 % cross-axis per
element; NEES of pos, vel, att, 9 dof, band 7.2-11.0) the accelerometer term is the one that
matters: without it the ANEES is 17.7 (tilt and vertical velocity over-confident; larger
white accelerometer noise only brings it to 12.8); with both terms, 8.7 (held-out seeds: 9.0).

Measurements (each returns ``Meas(name, y, H, R)``, ``y = z - h(x)``, or ``None``)
---------------------------------------------------------------------------------
GNSS position with lever arm ``l_b`` (antenna in ``b``)::

    h = p + C_nb l_b + e,       H_p = I, H_th = -[(C_nb l_b) x], H_e = I

GNSS velocity (2 rows from NMEA speed and course, 3 when the receiver gives ``vd``)::

    h = v + C_nb (omega_b x l_b) + (e_gm - e) / t_f,
    H_v = I, H_th = -[(C_nb (omega x l)) x], H_e = -I / t_f, H_e_gm = I / t_f,
    H_bg = C_nb [l_b x] K, H_sg = C_nb [l_b x] K diag(omega_b),  K = diag(1 / (1 + s_g))

``R`` is the white Doppler part only (the smoothed-error derivative is in the states).

Non-holonomic constraint (Shin 2005, §4.3; Sukkarieh 2000): lateral and vertical velocity
of the vehicle are zero, ``v_v = C_vb C_nb^T v_n``, rows y and z::

    H_v = C_vn, H_th = C_vn [v_n x], H_mu = -[v_v x]

Zero velocity (``h = v``, ``H_v = I``) and zero angular rate (``h = omega``, ``H_bg = -K``,
``H_sg = -K diag(omega)``) while static. (In ``F`` the factor ``K`` is taken as ``I``.)

Gravity (before the heading, small acceleration; :func:`gravity_rows`): ``h = (C_nb f)_NE``,
``z = 0``, ``H_th = -[f_n x]_NE``, ``H_ba = -(C_nb K)_NE``, ``H_sa = -(C_nb K diag(f))_NE``.

Magnetometer heading (calibrated ``m_b``, declination ``D``): ``m = C_nb m_b``,
``h = atan2(m_E, m_N)``, ``z = D``::

    H_th = [-m_N m_D / |m_h|^2, -m_E m_D / |m_h|^2, 1]

No Euler angle enters any model, so none is singular at pitch +-90 deg.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import NamedTuple, TypeVar

import numba
import numpy as np
import numpy.typing as npt

from iotnav.strapdown import rodrigues as _rodrigues

FloatArray = npt.NDArray[np.float64]
#: A float or an array of floats, the same kind in and out.
FloatLike = TypeVar("FloatLike", float, FloatArray)

# ----------------------------------------------------------------------------- layout
POS = slice(0, 3)
VEL = slice(3, 6)
ATT = slice(6, 9)
BG = slice(9, 12)
BA = slice(12, 15)
MNT = slice(15, 18)
GNE = slice(18, 21)
GNM = slice(21, 24)
SG = slice(24, 27)
SA = slice(27, 30)
#: Error-state size without / with scale-factor states.
N_BASE = 24
N_FULL = 30
#: Standard gravity, m/s^2 (the kinematic acceleration of the cross-axis noise; the local
#: value differs by < 0.03 m/s^2, negligible there).
G_STD = 9.80665
#: First index of each block (for the compiled kernels, which take no slices).
POS_0, VEL_0, ATT_0, BG_0, BA_0, MNT_0, GNE_0, GNM_0, SG_0, SA_0 = 0, 3, 6, 9, 12, 15, 18, 21, 24, 27


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


# ----------------------------------------------------------------------------- propagation
#: Layout of the accumulator used between covariance propagations.
ACC_T, ACC_FN, ACC_FB, ACC_WB, ACC_C = 0, slice(1, 4), slice(4, 7), slice(7, 10), slice(10, 19)
ACC_SIZE = 19


@numba.njit(cache=True)
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
    """One strapdown step (as :func:`iotnav.strapdown.step`) in place, plus accumulation (compiled).

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
    h = 0.5 * dt
    r = _rodrigues(h * omega_b[0], h * omega_b[1], h * omega_b[2])  # R_half
    f0, f1, f2 = f_b[0], f_b[1], f_b[2]
    for i in range(3):
        c0, c1, c2 = C_nb[i, 0], C_nb[i, 1], C_nb[i, 2]
        # row i of C_half = C_nb R_half
        h0 = c0 * r[0] + c1 * r[3] + c2 * r[6]
        h1 = c0 * r[1] + c1 * r[4] + c2 * r[7]
        h2 = c0 * r[2] + c1 * r[5] + c2 * r[8]
        fn = h0 * f0 + h1 * f1 + h2 * f2
        v_old = v_n[i]
        v_new = v_old + (fn + g_n[i]) * dt
        v_n[i] = v_new
        p_n[i] += 0.5 * (v_old + v_new) * dt
        # C_nb <- C_half R_half
        C_nb[i, 0] = h0 * r[0] + h1 * r[3] + h2 * r[6]
        C_nb[i, 1] = h0 * r[1] + h1 * r[4] + h2 * r[7]
        C_nb[i, 2] = h0 * r[2] + h1 * r[5] + h2 * r[8]
        acc[1 + i] += fn * dt
        acc[4 + i] += f_b[i] * dt
        acc[7 + i] += omega_b[i] * dt
        acc[10 + 3 * i] += h0 * dt
        acc[11 + 3 * i] += h1 * dt
        acc[12 + 3 * i] += h2 * dt
    acc[0] += dt


@numba.njit(cache=True)
def _sparse_rows_product(L: FloatArray, R: FloatArray, out: FloatArray) -> None:
    """``out = L @ R``, skipping the zero elements of ``L`` (square ``n x n``)."""
    n = L.shape[0]
    for i in range(n):
        for j in range(n):
            out[i, j] = 0.0
        for k in range(n):
            a = L[i, k]
            if a != 0.0:
                for j in range(n):
                    out[i, j] += a * R[k, j]


@numba.njit(cache=True)
def transition_into(
    C_nb: FloatArray,
    f_b: FloatArray,
    omega_b: FloatArray,
    T: float,
    noise: FloatArray,
    Phi: FloatArray,
    q: FloatArray,
    A: FloatArray,
) -> None:
    """Fill ``Phi`` and the diagonal ``q`` of ``Q_d`` of :func:`error_transition` (compiled).

    ``A T`` has its non-zeros in the POS, VEL, ATT rows and on the bias and GNSS-error
    diagonals, so ``(A T)^2`` is formed skipping zeros.

    Parameters
    ----------
    C_nb : numpy.ndarray
        Mean attitude over the interval (``b`` to ``n``).
    f_b, omega_b : numpy.ndarray
        Mean compensated specific force (m/s^2) and angular rate (rad/s) in ``b``.
    T : float
        Interval, s.
    noise : numpy.ndarray
        As in :func:`error_transition`.
    Phi : numpy.ndarray
        ``(n, n)``, receives the transition; ``n`` is :data:`N_BASE` or :data:`N_FULL`.
    q : numpy.ndarray
        ``(n,)``, receives the diagonal of ``Q_d``.
    A : numpy.ndarray
        ``(n, n)`` work array.
    """
    n = Phi.shape[0]
    A[:, :] = 0.0
    inv_tf = noise[14] if noise.shape[0] > 14 else 0.0
    fn0 = C_nb[0, 0] * f_b[0] + C_nb[0, 1] * f_b[1] + C_nb[0, 2] * f_b[2]
    fn1 = C_nb[1, 0] * f_b[0] + C_nb[1, 1] * f_b[1] + C_nb[1, 2] * f_b[2]
    fn2 = C_nb[2, 0] * f_b[0] + C_nb[2, 1] * f_b[1] + C_nb[2, 2] * f_b[2]
    # A[VEL, ATT] = -[f_n x]
    A[VEL_0, ATT_0 + 1] = fn2 * T
    A[VEL_0, ATT_0 + 2] = -fn1 * T
    A[VEL_0 + 1, ATT_0] = -fn2 * T
    A[VEL_0 + 1, ATT_0 + 2] = fn0 * T
    A[VEL_0 + 2, ATT_0] = fn1 * T
    A[VEL_0 + 2, ATT_0 + 1] = -fn0 * T
    for i in range(3):
        A[POS_0 + i, VEL_0 + i] = T
        A[BA_0 + i, BA_0 + i] = -noise[4] * T
        A[BG_0 + i, BG_0 + i] = -noise[5] * T
        # 1/T_e: horizontal, vertical (optional, else the horizontal)
        inv_te = noise[15] if (i == 2 and noise.shape[0] > 15) else noise[10]
        if inv_tf > 0.0:  # smoothed receiver: e' = (e_gm - e) / t_f, e_gm' = -e_gm / T_e + w
            A[GNM_0 + i, GNM_0 + i] = -inv_te * T
            A[GNE_0 + i, GNE_0 + i] = -inv_tf * T
            A[GNE_0 + i, GNM_0 + i] = inv_tf * T
        else:  # no smoothing: e itself is the Gauss-Markov process (GNM unused)
            A[GNE_0 + i, GNE_0 + i] = -inv_te * T
        for j in range(3):
            A[VEL_0 + i, BA_0 + j] = -C_nb[i, j] * T
            A[ATT_0 + i, BG_0 + j] = -C_nb[i, j] * T
            if n >= N_FULL:
                A[VEL_0 + i, SA_0 + j] = -C_nb[i, j] * f_b[j] * T
                A[ATT_0 + i, SG_0 + j] = -C_nb[i, j] * omega_b[j] * T
    _sparse_rows_product(A, A, Phi)
    for i in range(n):
        for j in range(n):
            Phi[i, j] = A[i, j] + 0.5 * Phi[i, j]
        Phi[i, i] += 1.0
    w2 = omega_b[0] * omega_b[0] + omega_b[1] * omega_b[1] + omega_b[2] * omega_b[2]
    # optional entries of ``noise``: accelerometer cross-axis, unestimated gyro scale factor
    k_a = noise[12] if noise.shape[0] > 12 else 0.0
    k_s = noise[13] if noise.shape[0] > 13 else 0.0
    # kinematic acceleration in b, a_b = f_b + C_nb^T g_n (g_n = (0, 0, G_STD))
    a0 = fn0
    a1 = fn1
    a2 = fn2 + G_STD
    ab0 = C_nb[0, 0] * a0 + C_nb[1, 0] * a1 + C_nb[2, 0] * a2
    ab1 = C_nb[0, 1] * a0 + C_nb[1, 1] * a1 + C_nb[2, 1] * a2
    ab2 = C_nb[0, 2] * a0 + C_nb[1, 2] * a1 + C_nb[2, 2] * a2
    a2_sum = ab0 * ab0 + ab1 * ab1 + ab2 * ab2
    q[:] = 0.0
    for i in range(3):
        ab_i = ab0 if i == 0 else (ab1 if i == 1 else ab2)
        q[VEL_0 + i] = noise[0] * T
        # gyro cross-axis (and unestimated scale factor): rate-error variance per body axis
        # k, resolved in n (diagonal of C_nb diag(.) C_nb^T)
        d_att = 0.0
        for k in range(3):
            wk2 = omega_b[k] * omega_b[k]
            d_att += C_nb[i, k] * C_nb[i, k] * (noise[11] * (w2 - wk2) + k_s * wk2)
        q[ATT_0 + i] = (noise[1] + d_att) * T
        q[BA_0 + i] = (noise[2] + k_a * (a2_sum - ab_i * ab_i)) * T
        q[BG_0 + i] = noise[3] * T
        q[MNT_0 + i] = noise[6] * T
        q[GNM_0 + i if inv_tf > 0.0 else GNE_0 + i] = (noise[8] if i < 2 else noise[9]) * T
        if n >= N_FULL:
            q[SG_0 + i] = noise[7] * T
            q[SA_0 + i] = noise[7] * T


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
        ``[N_a^2, N_g^2, q_ba, q_bg, 1/T_a, 1/T_g, q_mu, q_s, q_e_h, q_e_v, 1/T_e, k_w(, k_a,
        k_s, 1/t_f)]``: noise densities squared ((m/s^2)^2/Hz, (rad/s)^2/Hz), bias driving
        intensities, inverse correlation times (1/s), mount and scale random-walk intensities,
        GNSS-error driving intensities (m^2/s, horizontal and vertical; they drive ``GNM``, or
        ``GNE`` when ``1/t_f`` is 0 or absent), ``k_w`` (s) of the
        attitude noise ``k_w (|omega_b|^2 - omega_b,i^2)`` of the gyro cross-axis coupling,
        and optionally ``k_a`` (1/s) of the accelerometer-bias noise
        ``k_a (|a_b|^2 - a_b,i^2)`` of the accelerometer cross-axis coupling (``a_b`` the
        kinematic acceleration in ``b``) and ``k_s`` (s) of the attitude noise
        ``k_s omega_b,i^2`` of an unestimated gyro scale factor (see the module docstring),
        and the inverse time constant of the receiver's position smoothing ``1/t_f`` (1/s);
        absent: 0 (then ``GNE`` is a first-order Gauss-Markov process and ``GNM`` is inert);
        and ``1/T_e`` of the vertical GNSS error (absent: the horizontal ``1/T_e``).

    Returns
    -------
    Phi, Qd : numpy.ndarray
        ``(n, n)`` each (computed by :func:`transition_into`).
    """
    Phi = np.zeros((n, n))
    q = np.zeros(n)
    f64 = np.float64
    transition_into(
        np.ascontiguousarray(C_nb, dtype=f64),
        np.ascontiguousarray(f_b, dtype=f64),
        np.ascontiguousarray(omega_b, dtype=f64),
        float(T),
        np.ascontiguousarray(noise, dtype=f64),
        Phi,
        q,
        np.zeros((n, n)),
    )
    return Phi, np.diag(q)


@numba.njit(cache=True)
def propagate_covariance(P: FloatArray, acc: FloatArray, noise: FloatArray) -> bool:
    """``P <- Phi P Phi^T + Q_d`` in place over the accumulated interval (compiled).

    :func:`propagate_covariance_phi` with a scratch ``Phi`` (the same arithmetic).

    Parameters
    ----------
    P : numpy.ndarray
        ``(n, n)`` error-state covariance, updated in place.
    acc : numpy.ndarray
        Accumulator (``ACC_*`` layout).
    noise : numpy.ndarray
        As in :func:`error_transition`.

    Returns
    -------
    bool
        False (nothing done) when the interval is empty.
    """
    if acc[0] <= 0.0:
        return False
    n = P.shape[0]
    return propagate_covariance_phi(P, acc, noise, np.empty((n, n)))


@numba.njit(cache=True)
def propagate_covariance_phi(P: FloatArray, acc: FloatArray, noise: FloatArray, Phi: FloatArray) -> bool:
    """:func:`propagate_covariance`, also returning the interval's transition in ``Phi`` (compiled).

    ``Phi`` and ``Q_d`` come from :func:`transition_into` with the interval means of the
    accumulator ``acc`` (``ACC_*`` layout, from :func:`propagate_nominal`); the products skip
    the zeros of ``Phi`` (beyond the POS, VEL and ATT rows it is diagonal), and only the upper
    triangle is formed and mirrored, so ``P`` stays exactly symmetric. ``acc`` is not reset.

    Parameters
    ----------
    P : numpy.ndarray
        ``(n, n)`` error-state covariance, updated in place.
    acc : numpy.ndarray
        Accumulator (``ACC_*`` layout).
    noise : numpy.ndarray
        As in :func:`error_transition`.
    Phi : numpy.ndarray
        ``(n, n)``, receives the error-state transition over the interval (what the RTS
        smoother of :mod:`iotnav.engines.eskf` accumulates between its record points);
        untouched when the interval is empty.

    Returns
    -------
    bool
        False (nothing done) when the interval is empty.
    """
    T = acc[0]
    if T <= 0.0:
        return False
    n = P.shape[0]
    C = np.empty((3, 3))
    fb = np.empty(3)
    wb = np.empty(3)
    for i in range(3):
        fb[i] = acc[4 + i] / T
        wb[i] = acc[7 + i] / T
        for j in range(3):
            C[i, j] = acc[10 + 3 * i + j] / T
    W = np.empty((n, n))
    q = np.empty(n)
    transition_into(C, fb, wb, T, noise, Phi, q, W)
    # non-zero columns of each row of Phi
    nz = np.empty((n, n), dtype=np.int64)
    cnt = np.zeros(n, dtype=np.int64)
    for i in range(n):
        for k in range(n):
            if Phi[i, k] != 0.0:
                nz[i, cnt[i]] = k
                cnt[i] += 1
    # W = Phi P
    for i in range(n):
        for j in range(n):
            W[i, j] = 0.0
        for m in range(cnt[i]):
            k = nz[i, m]
            a = Phi[i, k]
            for j in range(n):
                W[i, j] += a * P[k, j]
    # P = W Phi^T + Q_d, upper triangle, mirrored
    for i in range(n):
        for j in range(i, n):
            s = 0.0
            for m in range(cnt[j]):
                k = nz[j, m]
                s += W[i, k] * Phi[j, k]
            P[i, j] = s
        P[i, i] += q[i]
    for i in range(n):
        for j in range(i + 1, n):
            P[j, i] = P[i, j]
    return True


@numba.njit(cache=True)
def accumulate_transition(Phi: FloatArray, Phi_acc: FloatArray, work: FloatArray) -> None:
    """``Phi_acc <- Phi @ Phi_acc`` in place, skipping the zeros of ``Phi`` (compiled).

    Parameters
    ----------
    Phi : numpy.ndarray
        ``(n, n)`` transition of the latest interval (:func:`propagate_covariance_phi`).
    Phi_acc : numpy.ndarray
        ``(n, n)`` product of the earlier transitions, updated in place.
    work : numpy.ndarray
        ``(n, n)`` scratch.
    """
    _sparse_rows_product(Phi, Phi_acc, work)
    n = Phi.shape[0]
    for i in range(n):
        for j in range(n):
            Phi_acc[i, j] = work[i, j]


@numba.njit(cache=True)
def kalman_update(
    P: FloatArray, dx: FloatArray, y: FloatArray, H: FloatArray, R: FloatArray, m: int, gate: float
) -> tuple[float, bool, float]:
    """Error-state measurement update of ``P`` in place, Joseph form, NIS gate (compiled).

    The prior error state is zero (ESKF), so ``dx = K y``. The equations are those of
    :func:`iotnav.kalman.update` (Cholesky solve of ``S``, never an inverse), with the
    Joseph form written out, ``(I - K H) P (I - K H)^T + K R K^T = P - K A^T - A K^T + K S K^T``
    with ``A = P H^T``, ``S = H A + R`` (algebraically identical, first-order insensitive to
    errors in ``K``, ``O(n^2 m)`` instead of ``O(n^3)``); the upper triangle is formed and
    mirrored. The zeros of ``H`` are skipped.

    Parameters
    ----------
    P : numpy.ndarray
        ``(n, n)`` covariance, updated in place when accepted.
    dx : numpy.ndarray
        ``(n,)`` output: the error-state estimate (zero when rejected).
    y : numpy.ndarray
        Innovation ``z - h(x)`` in its first ``m`` elements.
    H : numpy.ndarray
        Jacobian, first ``m`` rows of an ``(>= m, n)`` array.
    R : numpy.ndarray
        Measurement noise covariance, top-left ``m x m`` block.
    m : int
        Measurement size (1 to 3).
    gate : float
        NIS threshold; ``<= 0`` or NaN: no gate.

    Returns
    -------
    nis : float
        ``y^T S^-1 y`` (inf when ``S`` is not positive definite; then rejected).
    accepted : bool
        False when gated out.
    test_ratio : float
        ``nis / gate`` (NaN without a gate).
    """
    n = P.shape[0]
    gated = gate > 0.0
    for i in range(n):
        dx[i] = 0.0
    At = np.zeros((m, n))  # A^T = H P
    for r in range(m):
        for k in range(n):
            h = H[r, k]
            if h != 0.0:
                for j in range(n):
                    At[r, j] += h * P[k, j]
    S = np.empty((m, m))
    for r in range(m):
        for c in range(m):
            s = R[r, c]
            for k in range(n):
                s += H[r, k] * At[c, k]
            S[r, c] = s
    for r in range(m):
        for c in range(r + 1, m):
            v = 0.5 * (S[r, c] + S[c, r])
            S[r, c] = v
            S[c, r] = v
    # Cholesky S = L L^T
    L = np.zeros((m, m))
    for j in range(m):
        d = S[j, j]
        for k in range(j):
            d -= L[j, k] * L[j, k]
        if not d > 0.0:
            return math.inf, False, math.inf if gated else math.nan
        L[j, j] = math.sqrt(d)
        for i in range(j + 1, m):
            v = S[i, j]
            for k in range(j):
                v -= L[i, k] * L[j, k]
            L[i, j] = v / L[j, j]
    # u = S^-1 y
    u = np.empty(m)
    for i in range(m):
        v = y[i]
        for k in range(i):
            v -= L[i, k] * u[k]
        u[i] = v / L[i, i]
    for i in range(m - 1, -1, -1):
        v = u[i]
        for k in range(i + 1, m):
            v -= L[k, i] * u[k]
        u[i] = v / L[i, i]
    nis = 0.0
    for i in range(m):
        nis += y[i] * u[i]
    ratio = nis / gate if gated else math.nan
    if gated and nis > gate:
        return nis, False, ratio
    # K^T = S^-1 A^T (column by column)
    Kt = np.empty((m, n))
    for j in range(n):
        for i in range(m):
            v = At[i, j]
            for k in range(i):
                v -= L[i, k] * Kt[k, j]
            Kt[i, j] = v / L[i, i]
        for i in range(m - 1, -1, -1):
            v = Kt[i, j]
            for k in range(i + 1, m):
                v -= L[k, i] * Kt[k, j]
            Kt[i, j] = v / L[i, i]
    for i in range(n):
        v = 0.0
        for r in range(m):
            v += Kt[r, i] * y[r]
        dx[i] = v
    KSt = np.zeros((m, n))  # (K S)^T = S K^T
    for r in range(m):
        for c in range(m):
            s = S[r, c]
            for j in range(n):
                KSt[r, j] += s * Kt[c, j]
    for i in range(n):
        for j in range(i, n):
            v = P[i, j]
            for r in range(m):
                v += KSt[r, i] * Kt[r, j] - Kt[r, i] * At[r, j] - At[r, i] * Kt[r, j]
            P[i, j] = v
    for i in range(n):
        for j in range(i + 1, n):
            P[j, i] = P[i, j]
    return nis, True, ratio


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
    (position, velocity, attitude, both GNSS error blocks) rotates with it: ``dx_n' = R_z dx_n``, and
    ``P' = T P T^T`` (the biases, mount and scale factors are in ``b``/``v`` and unchanged).
    Without it the tilt / accelerometer-bias correlation learnt at rest points the wrong way
    and makes the tilt spuriously observable.
    """
    c, s = math.cos(dpsi), math.sin(dpsi)
    R = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    T = np.eye(n)
    for sl in (POS, VEL, ATT, GNE, GNM):
        T[sl, sl] = R
    return T


# ----------------------------------------------------------------------------- measurements
class Meas(NamedTuple):
    """A linearised measurement: innovation ``y = z - h(x)``, Jacobian ``H`` and noise ``R``."""

    name: str
    y: FloatArray
    H: FloatArray
    R: FloatArray


def gm_variance_factor(corr_time_s: FloatLike, filter_s: float) -> FloatLike:
    """``var(e_gm) / var(e) = (T_e + t_f) / T_e`` of the GNSS error model (module docstring).

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
    """GNSS position update; ``sigma_m`` the white part of the error per NED axis, m."""
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
    """GNSS velocity update; ``z_n`` of length 2 (North, East) or 3 (with Down).

    ``sigma_mps`` is the white (Doppler) part per axis; ``inv_tf`` as in :func:`h_gnss_velocity`.
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
    """Non-holonomic constraint ``v_v[1:] = 0``."""
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
    """Zero-velocity update (:func:`zupt_rows`)."""
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
    """Zero-angular-rate update from the mean raw gyro output over a static interval."""
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
    """Magnetometer heading update (calibrated field ``m_b``, any unit)."""
    out = h_mag_heading(nom, m_b, n)
    if out is None:
        return None
    h, H = out
    y = math.remainder(declination_rad - h, 2.0 * math.pi)
    return Meas("mag_heading", np.array([y]), H, np.array([[sigma_rad**2]]))
