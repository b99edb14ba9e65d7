"""Error-state (multiplicative) quaternion Kalman filter for attitude and gyro bias (AHRS).

iotnav's own attitude filter: gyroscope strapdown of ``q_nb`` (``n`` = NED, ``b`` = sensor,
scalar-first) with a six-state error-state Kalman filter on top, after the error-state
formulation of Solà (2017) with the *global* (``n``-frame) attitude error, plus the robustness
devices that make real low-cost IMU data usable (gated / adaptive accelerometer, heading-only
magnetometer with disturbance tests, rest detection), in the spirit of VQF (Laidig and Seel 2023).
No code is taken from either; the equations below are written from the papers.

Nominal state and error state
-----------------------------
Nominal: ``q_nb`` (unit quaternion, b -> n) and gyro bias ``b_g`` (rad/s, in ``b``).
Error state ``dx = [dtheta_n (3), db_g (3)]`` (named slices :data:`ATT`, :data:`BG`) with

    q_nb_true = Exp(dtheta_n) (x) q_nb,       b_true = b_g + db_g,

``Exp(v) = [cos(|v|/2), sin(|v|/2) v/|v|]`` (Solà 2017, eqs. 101 and 180 for the global error).
With the global error the heading error is exactly ``dtheta_n[2]``, rotation about ``n``-Down,
which is what lets the magnetometer act on heading only.

Prediction (per sample, ``omega = omega_meas_b - b_g``, ``dt`` the sample period):

    q_nb <- q_nb (x) Exp(omega dt)
    F = [[I, -C_nb dt], [0, I]],     Q = diag(sigma_g^2 dt I, sigma_bw^2 dt I)
    P <- F P F^T + Q                  (Solà 2017, sec. 7.2, global-error form, eq. 286 ff.)

with ``sigma_g`` the gyro white noise (rad/s/sqrt(Hz)) and ``sigma_bw`` the bias random walk
(rad/s/sqrt(s)).

Accelerometer (tilt) update
    Linear acceleration is removed before the update by low-pass filtering the specific force in
    a quasi-inertial frame ``I``, the idea at the heart of VQF (Laidig and Seel 2023, sec. IV-A):
    ``q_Ib`` is the gyro-only strapdown (bias-corrected, never corrected by the measurements),
    ``f_I = C_Ib f_b`` is low-passed by two cascaded first-order filters of time constant
    ``acc_lp_tau_s`` (gravity is constant in ``I`` up to gyro drift, the linear acceleration
    averages out since velocity stays bounded), and the result is brought into ``n`` with the
    current correction ``C_nI = C_nb C_Ib^T``: ``a_n = C_nI lp(f_I) / |lp(f_I)|``. Without
    error ``a_n = u = [0, 0, -1]``; to first order ``a_n = u + u x dtheta_n``, so the measurement
    is the horizontal part ``z = [a_n,x, a_n,y]`` with ``H = [[0, 1, 0 | 0], [-1, 0, 0 | 0]]``
    (it cannot see heading). The noise is adaptive,
    ``R = sigma_a^2 (1 + ((|lp(f_I)| - g) / s_a)^2) I``, and a raw sample with
    ``||f| - g| > acc_reject_m_s2`` (an impact) is neither fed to the low-pass nor used
    (cf. the acceleration rejection of Madgwick's Fusion).

Magnetometer (heading only)
    ``m_n = C_nb m_b``; its horizontal angle measures the heading error,
    ``z = wrap(declination - atan2(m_n,y, m_n,x)) = dtheta_n[2] + noise``. The update is
    *projected*: the Kalman gain is restricted to the heading error (a Schmidt / "consider"
    update: ``K = [0, 0, k, 0, 0, 0]^T``, ``k = P_psi,psi / S``, Joseph form with that gain), so
    the magnetometer can correct neither tilt nor gyro bias. The heading update is skipped while
    the field is disturbed: its norm departs from the reference by more than ``mag_norm_rel_th``
    (relative) or its dip angle by more than ``mag_dip_th_rad`` (VQF's norm and dip tests). The
    reference norm and dip are learned at start and tracked slowly (``mag_ref_tau_s``) while
    undisturbed; a new field that stays consistent for ``mag_new_field_s`` is adopted.

Rest detection and bias learning
    The gyro and accelerometer are low-passed (first order, ``rest_tau_s``); the sensor is at
    rest when ``|omega_meas - lp(omega)| < rest_gyro_th_rad_s``, ``|f - lp(f)| <
    rest_acc_th_m_s2`` and ``|lp(omega)| < rest_max_rate_rad_s`` for ``rest_min_s``. At rest,
    ``lp(omega)`` measures the bias directly: ``z = lp(omega)``, ``H = [0 | I]``,
    ``R = sigma_rest^2 I`` (rest-phase bias estimation as in VQF, Laidig and Seel 2023, sec. IV-C).
    During motion the bias is still observed through the accelerometer updates (the cross
    covariance built by ``F``).

The error state is injected after each update, ``q_nb <- Exp(dtheta) (x) q_nb``,
``b_g <- b_g + db_g``, and reset with ``G = I + [dtheta/2 x]`` on the attitude block (Solà 2017,
eq. 287, global error).

Two code paths compute the same thing: :class:`AhrsEskf` (streaming, pure numpy, every update
through :func:`iotnav.kalman.update`) and :func:`run_ahrs_eskf` (a numba-compiled batch loop
with the same equations written out; tested equal to the streaming path).

References
----------
J. Solà, "Quaternion kinematics for the error-state Kalman filter", arXiv:1711.02508, 2017.
D. Laidig, T. Seel, "VQF: Highly accurate IMU orientation estimation with bias estimation and
magnetic disturbance rejection", Information Fusion 91:187-204, 2023.
F. L. Markley, "Attitude error representations for Kalman filtering", JGCD 26(2), 2003.
S. O. H. Madgwick, "AHRS algorithms and calibration solutions to facilitate new applications
using low-cost MEMS", PhD thesis, Univ. of Bristol, 2014 (acceleration/magnetic rejection).
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass

import numba
import numpy as np
import numpy.typing as npt

from iotnav import kalman

FloatArray = npt.NDArray[np.float64]

#: Error-state layout: global attitude error (rad, n-frame) and gyro-bias error (rad/s, b-frame).
ATT = slice(0, 3)
BG = slice(3, 6)
STATE_DIM = 6
#: Index of the heading (rotation about n-Down) component of the attitude error.
HEADING = 2


@dataclass(frozen=True)
class AhrsEskfConfig:
    """Tunables of :class:`AhrsEskf` (SI units; names carry any other unit).

    The defaults were tuned once for all five BROAD trials together (as BROAD tunes its
    baselines), minimising the average total RMSE on a small grid: ``acc_lp_tau_s`` in
    {0.5, 0.7, 1, 2, 3}, ``acc_noise_rad`` in {0.01, 0.02, 0.05, 0.15}, ``acc_adapt_m_s2`` in
    {0.5, 1, 2} (6-axis), then ``mag_noise_rad`` in {0.05, 0.15, 0.4, 1, 2, 4} (9-axis; 4 was
    marginally better on BROAD, 2 was kept for a heading time constant of about two minutes).
    The other values are physical or VQF-like defaults, not tuned.

    Attributes
    ----------
    gyro_noise_rad_s_rthz : float
        Gyro white noise density, rad/s/sqrt(Hz); with ``acc_noise_rad`` it sets the
        accelerometer time constant ``tau ~ acc_noise_rad / (gyro_noise * sqrt(fs))``.
    gyro_bias_rw_rad_s_rts : float
        Gyro-bias random walk, rad/s/sqrt(s).
    gyro_bias_init_rad_s : float
        Initial 1-sigma of the gyro bias, rad/s.
    init_tilt_sigma_rad, init_heading_sigma_rad : float
        Initial 1-sigma of the tilt and heading errors, rad.
    acc_noise_rad : float
        1-sigma of the filtered accelerometer direction per sample, rad (includes unmodelled
        motion and the time correlation left by the low-pass).
    acc_lp_tau_s : float
        Time constant of each of the two cascaded first-order low-passes applied to the
        specific force in the quasi-inertial frame, s.
    acc_adapt_m_s2 : float
        Scale of the adaptive inflation of the accelerometer noise with the deviation of the
        filtered specific-force norm from ``g``, m/s^2.
    acc_reject_m_s2 : float
        Raw accelerometer samples with ``||f| - g|`` above this (impacts) are not fed to the
        low-pass and give no update, m/s^2.
    gravity_m_s2 : float
        Gravity magnitude, m/s^2.
    use_mag : bool
        Use the magnetometer for heading (9-axis); False gives a 6-axis filter.
    mag_noise_rad : float
        1-sigma of the magnetic heading per sample, rad.
    mag_declination_rad : float
        Angle from the filter's North to magnetic North, rad (0: magnetic North).
    mag_norm_rel_th : float
        Relative field-norm deviation treated as a disturbance.
    mag_dip_th_rad : float
        Dip-angle deviation treated as a disturbance, rad.
    mag_ref_tau_s : float
        Time constant of the reference norm/dip tracking while undisturbed, s.
    mag_new_field_s : float
        A disturbed but steady field is adopted as the new reference after this time, s.
    rest_tau_s : float
        Low-pass time constant of the rest detector, s.
    rest_gyro_th_rad_s, rest_acc_th_m_s2 : float
        Rest thresholds on the deviation of gyro (rad/s) and accelerometer (m/s^2) from their
        low-passed values.
    rest_max_rate_rad_s : float
        Largest low-passed rate accepted as rest, rad/s.
    rest_min_s : float
        Minimum duration of a rest phase, s.
    rest_noise_rad_s : float
        1-sigma of the rest bias measurement, rad/s.
    """

    gyro_noise_rad_s_rthz: float = 1.0e-3
    gyro_bias_rw_rad_s_rts: float = 2.0e-5
    gyro_bias_init_rad_s: float = 0.01
    init_tilt_sigma_rad: float = 0.05
    init_heading_sigma_rad: float = 0.2
    acc_noise_rad: float = 0.01
    acc_lp_tau_s: float = 1.0
    acc_adapt_m_s2: float = 2.0
    acc_reject_m_s2: float = 50.0
    gravity_m_s2: float = 9.81
    use_mag: bool = True
    mag_noise_rad: float = 2.0
    mag_declination_rad: float = 0.0
    mag_norm_rel_th: float = 0.1
    mag_dip_th_rad: float = 0.1745
    mag_ref_tau_s: float = 20.0
    mag_new_field_s: float = 20.0
    rest_tau_s: float = 0.5
    rest_gyro_th_rad_s: float = 0.035
    rest_acc_th_m_s2: float = 0.5
    rest_max_rate_rad_s: float = 0.1
    rest_min_s: float = 1.5
    rest_noise_rad_s: float = 0.005

    def as_dict(self) -> dict[str, float | bool]:
        """The configuration as a plain dict (for ``summary.json``)."""
        return asdict(self)


# --------------------------------------------------------------------------------------------
# Quaternion helpers (scalar first). Plain functions, compiled once more below for the kernel.
# --------------------------------------------------------------------------------------------


def quat_multiply(p: FloatArray, q: FloatArray) -> FloatArray:
    """Hamilton product ``p (x) q`` of scalar-first quaternions (broadcasts over ``(..., 4)``)."""
    p = np.asarray(p, dtype=float)
    q = np.asarray(q, dtype=float)
    pw, px, py, pz = p[..., 0], p[..., 1], p[..., 2], p[..., 3]
    qw, qx, qy, qz = q[..., 0], q[..., 1], q[..., 2], q[..., 3]
    return np.stack(
        [
            pw * qw - px * qx - py * qy - pz * qz,
            pw * qx + px * qw + py * qz - pz * qy,
            pw * qy - px * qz + py * qw + pz * qx,
            pw * qz + px * qy - py * qx + pz * qw,
        ],
        axis=-1,
    )


def quat_conjugate(q: FloatArray) -> FloatArray:
    """Conjugate (inverse of a unit quaternion), ``(..., 4)``."""
    out = np.array(q, dtype=float, copy=True)
    out[..., 1:] *= -1.0
    return out


def quat_to_dcm(q: FloatArray) -> FloatArray:
    """Rotation matrix ``(..., 3, 3)`` of a unit quaternion ``(..., 4)`` (``q_nb`` -> ``C_nb``)."""
    q = np.asarray(q, dtype=float)
    w, x, y, z = q[..., 0], q[..., 1], q[..., 2], q[..., 3]
    C = np.empty((*q.shape[:-1], 3, 3))
    C[..., 0, 0] = 1 - 2 * (y * y + z * z)
    C[..., 0, 1] = 2 * (x * y - w * z)
    C[..., 0, 2] = 2 * (x * z + w * y)
    C[..., 1, 0] = 2 * (x * y + w * z)
    C[..., 1, 1] = 1 - 2 * (x * x + z * z)
    C[..., 1, 2] = 2 * (y * z - w * x)
    C[..., 2, 0] = 2 * (x * z - w * y)
    C[..., 2, 1] = 2 * (y * z + w * x)
    C[..., 2, 2] = 1 - 2 * (x * x + y * y)
    return C


def dcm_to_quat(C: FloatArray) -> FloatArray:
    """Unit quaternion (``w >= 0``) of a rotation matrix ``(3, 3)`` (Shepperd's method)."""
    C = np.asarray(C, dtype=float)
    tr = C[0, 0] + C[1, 1] + C[2, 2]
    cand = np.array([tr, C[0, 0], C[1, 1], C[2, 2]])
    i = int(np.argmax(cand))
    if i == 0:
        s = 2.0 * math.sqrt(1.0 + tr)
        q = [0.25 * s, (C[2, 1] - C[1, 2]) / s, (C[0, 2] - C[2, 0]) / s, (C[1, 0] - C[0, 1]) / s]
    elif i == 1:
        s = 2.0 * math.sqrt(1.0 + 2.0 * C[0, 0] - tr)
        q = [(C[2, 1] - C[1, 2]) / s, 0.25 * s, (C[0, 1] + C[1, 0]) / s, (C[0, 2] + C[2, 0]) / s]
    elif i == 2:
        s = 2.0 * math.sqrt(1.0 + 2.0 * C[1, 1] - tr)
        q = [(C[0, 2] - C[2, 0]) / s, (C[0, 1] + C[1, 0]) / s, 0.25 * s, (C[1, 2] + C[2, 1]) / s]
    else:
        s = 2.0 * math.sqrt(1.0 + 2.0 * C[2, 2] - tr)
        q = [(C[1, 0] - C[0, 1]) / s, (C[0, 2] + C[2, 0]) / s, (C[1, 2] + C[2, 1]) / s, 0.25 * s]
    out = np.array(q)
    out /= np.linalg.norm(out)
    return out if out[0] >= 0 else -out


def quat_exp(v: FloatArray) -> FloatArray:
    """``Exp(v)``: unit quaternion of the rotation vector ``v`` (rad), ``(3,)`` -> ``(4,)``."""
    v = np.asarray(v, dtype=float)
    a = float(np.linalg.norm(v))
    if a < 1e-12:
        out = np.array([1.0, 0.5 * v[0], 0.5 * v[1], 0.5 * v[2]])
        return out / np.linalg.norm(out)
    s = math.sin(0.5 * a) / a
    return np.array([math.cos(0.5 * a), s * v[0], s * v[1], s * v[2]])


def initial_attitude(
    acc_b: FloatArray, mag_b: FloatArray | None = None, declination_rad: float = 0.0
) -> FloatArray:
    """``q_nb`` (NED) from one accelerometer and, optionally, one magnetometer sample (TRIAD).

    Parameters
    ----------
    acc_b : numpy.ndarray
        Specific force in ``b``, m/s^2 (at rest it points up).
    mag_b : numpy.ndarray, optional
        Magnetic field in ``b`` (any unit). Without it the heading is set to zero.
    declination_rad : float
        Angle from the filter's North to magnetic North, rad.

    Returns
    -------
    numpy.ndarray
        ``q_nb``, shape ``(4,)``.
    """
    down_b = -np.asarray(acc_b, dtype=float)
    down_b /= np.linalg.norm(down_b)
    ref = np.array([1.0, 0.0, 0.0]) if mag_b is None else np.asarray(mag_b, dtype=float)
    east_b = np.cross(down_b, ref)
    if np.linalg.norm(east_b) < 1e-9:  # reference parallel to gravity: use another axis
        east_b = np.cross(down_b, np.array([0.0, 1.0, 0.0]))
    east_b /= np.linalg.norm(east_b)
    north_b = np.cross(east_b, down_b)
    C_mb = np.vstack([north_b, east_b, down_b])  # rows: magnetic-NED axes in b
    q_mb = dcm_to_quat(C_mb)
    if mag_b is None or declination_rad == 0.0:
        return q_mb
    return quat_multiply(quat_exp(np.array([0.0, 0.0, declination_rad])), q_mb)


# --------------------------------------------------------------------------------------------
# Shared scalar logic (used as plain Python by the reference path and compiled for the kernel)
# --------------------------------------------------------------------------------------------


def _dip_angle(
    C00: float,
    C01: float,
    C02: float,
    C10: float,
    C11: float,
    C12: float,
    C20: float,
    C21: float,
    C22: float,
    mx: float,
    my: float,
    mz: float,
) -> tuple[float, float, float, float]:
    """``m_n = C m_b`` and its dip angle (rad, positive when pointing down)."""
    mnx = C00 * mx + C01 * my + C02 * mz
    mny = C10 * mx + C11 * my + C12 * mz
    mnz = C20 * mx + C21 * my + C22 * mz
    norm = math.sqrt(mnx * mnx + mny * mny + mnz * mnz)
    dip = math.asin(min(1.0, max(-1.0, mnz / norm))) if norm > 0.0 else 0.0
    return mnx, mny, norm, dip


def _rest_step(
    lp: FloatArray,
    gyr: FloatArray,
    acc: FloatArray,
    alpha: float,
    th_gyr: float,
    th_acc: float,
    max_rate: float,
    rest_time: float,
    dt: float,
) -> float:
    """Advance the rest detector; ``lp[0:3]`` gyro and ``lp[3:6]`` acc low-pass (in place).

    Returns the time (s) the sensor has been continuously at rest (0 when moving).
    """
    dg = 0.0
    da = 0.0
    r = 0.0
    for i in range(3):
        lp[i] += alpha * (gyr[i] - lp[i])
        lp[3 + i] += alpha * (acc[i] - lp[3 + i])
        dg += (gyr[i] - lp[i]) ** 2
        da += (acc[i] - lp[3 + i]) ** 2
        r += lp[i] ** 2
    if math.sqrt(dg) < th_gyr and math.sqrt(da) < th_acc and math.sqrt(r) < max_rate:
        return rest_time + dt
    return 0.0


def _mag_check(ref: FloatArray, norm: float, dip: float, cfg: FloatArray, dt: float) -> bool:
    """Magnetic disturbance test and reference tracking (``ref`` updated in place).

    ``ref = [norm_ref, dip_ref, candidate_norm, candidate_dip, candidate_time, initialised]``;
    ``cfg = [norm_rel_th, dip_th, ref_tau, new_field_s]``. Returns True when the field is usable.
    """
    if ref[5] == 0.0:
        ref[0] = norm
        ref[1] = dip
        ref[5] = 1.0
        return True
    ok = abs(norm - ref[0]) < cfg[0] * ref[0] and abs(dip - ref[1]) < cfg[1]
    if ok:
        a = dt / (cfg[2] + dt)
        ref[0] += a * (norm - ref[0])
        ref[1] += a * (dip - ref[1])
        ref[4] = 0.0
        return True
    # disturbed: is it a steady new field?
    steady = abs(norm - ref[2]) < cfg[0] * ref[2] and abs(dip - ref[3]) < cfg[1]
    if ref[4] > 0.0 and steady:
        ref[4] += dt
    else:
        ref[2] = norm
        ref[3] = dip
        ref[4] = dt
    if ref[4] >= cfg[3]:
        ref[0] = ref[2]
        ref[1] = ref[3]
        ref[4] = 0.0
        return True
    return False


def _acc_lp_step(C_I: FloatArray, f: FloatArray, lp: FloatArray, alpha: float, first: bool) -> None:
    """Two cascaded first-order low-passes of ``f_I = C_I f`` (``lp[0:3]``, ``lp[3:6]``, in place)."""
    for i in range(3):
        a = C_I[i, 0] * f[0] + C_I[i, 1] * f[1] + C_I[i, 2] * f[2]
        if first:
            lp[i] = a
            lp[3 + i] = a
        else:
            lp[i] += alpha * (a - lp[i])
            lp[3 + i] += alpha * (lp[i] - lp[3 + i])


def _acc_innovation(C_nb: FloatArray, C_I: FloatArray, lp: FloatArray) -> tuple[float, float, float]:
    """Horizontal components of ``a_n = C_nb C_I^T lp / |lp|`` and ``|lp|``."""
    v0, v1, v2 = lp[3], lp[4], lp[5]
    nrm = math.sqrt(v0 * v0 + v1 * v1 + v2 * v2)
    # back to b with C_I^T, then to n with C_nb
    b0 = C_I[0, 0] * v0 + C_I[1, 0] * v1 + C_I[2, 0] * v2
    b1 = C_I[0, 1] * v0 + C_I[1, 1] * v1 + C_I[2, 1] * v2
    b2 = C_I[0, 2] * v0 + C_I[1, 2] * v1 + C_I[2, 2] * v2
    ax = (C_nb[0, 0] * b0 + C_nb[0, 1] * b1 + C_nb[0, 2] * b2) / nrm
    ay = (C_nb[1, 0] * b0 + C_nb[1, 1] * b1 + C_nb[1, 2] * b2) / nrm
    return ax, ay, nrm


_acc_lp_step_nb = numba.njit(cache=True)(_acc_lp_step)
_acc_innovation_nb = numba.njit(cache=True)(_acc_innovation)
_rest_step_nb = numba.njit(cache=True)(_rest_step)
_mag_check_nb = numba.njit(cache=True)(_mag_check)
_dip_angle_nb = numba.njit(cache=True)(_dip_angle)


# --------------------------------------------------------------------------------------------
# Streaming reference path (pure numpy, kalman.update)
# --------------------------------------------------------------------------------------------


class AhrsEskf:
    """Streaming error-state quaternion AHRS (see the module docstring for the equations).

    Parameters
    ----------
    config : AhrsEskfConfig, optional
        Tunables; the BROAD-tuned defaults when omitted.
    q0_nb : numpy.ndarray, optional
        Initial ``q_nb`` (NED, scalar first); when omitted it is computed from the first
        accelerometer (and magnetometer) sample.
    b0_rad_s : numpy.ndarray, optional
        Initial gyro bias, rad/s.
    """

    def __init__(
        self,
        config: AhrsEskfConfig | None = None,
        q0_nb: FloatArray | None = None,
        b0_rad_s: FloatArray | None = None,
    ) -> None:
        self.config = config or AhrsEskfConfig()
        c = self.config
        self.q_nb = None if q0_nb is None else np.asarray(q0_nb, dtype=float) / np.linalg.norm(q0_nb)
        self.b_g = np.zeros(3) if b0_rad_s is None else np.asarray(b0_rad_s, dtype=float).copy()
        self.P = np.diag(
            [c.init_tilt_sigma_rad**2] * 2 + [c.init_heading_sigma_rad**2] + [c.gyro_bias_init_rad_s**2] * 3
        )
        self.q_Ib: FloatArray | None = None
        self._acc_lp = np.zeros(6)
        self._acc_first = True
        self._lp = np.zeros(6)
        self._rest_time = 0.0
        self._mag_ref = np.zeros(6)
        self._mag_cfg = np.array([c.mag_norm_rel_th, c.mag_dip_th_rad, c.mag_ref_tau_s, c.mag_new_field_s])
        self.rest = False
        self.mag_used = False
        self.acc_used = False

    @property
    def C_nb(self) -> FloatArray:
        """Current ``C_nb`` (3, 3)."""
        if self.q_nb is None:
            raise RuntimeError("filter not initialised: call step() first")
        return quat_to_dcm(self.q_nb)

    def _inject(self, dx: FloatArray) -> None:
        dtheta = dx[ATT]
        assert self.q_nb is not None
        q = quat_multiply(quat_exp(dtheta), self.q_nb)
        self.q_nb = q / np.linalg.norm(q)
        self.b_g = self.b_g + dx[BG]

    def predict(self, gyr_b: FloatArray, dt: float) -> None:
        """Strapdown and covariance propagation with one gyro sample (rad/s) over ``dt`` (s)."""
        c = self.config
        assert self.q_nb is not None
        omega = np.asarray(gyr_b, dtype=float) - self.b_g
        dq = quat_exp(omega * dt)
        q = quat_multiply(self.q_nb, dq)
        self.q_nb = q / np.linalg.norm(q)
        if self.q_Ib is not None:
            qi = quat_multiply(self.q_Ib, dq)
            self.q_Ib = qi / np.linalg.norm(qi)
        F = np.eye(STATE_DIM)
        F[ATT, BG] = -quat_to_dcm(self.q_nb) * dt
        Q = np.diag([c.gyro_noise_rad_s_rthz**2 * dt] * 3 + [c.gyro_bias_rw_rad_s_rts**2 * dt] * 3)
        _, self.P = kalman.predict(np.zeros(STATE_DIM), self.P, F, Q)

    def update_acc(self, acc_b: FloatArray, dt: float) -> bool:
        """Tilt update with one accelerometer sample (m/s^2); returns True when used."""
        c = self.config
        f = np.asarray(acc_b, dtype=float)
        fn = float(np.linalg.norm(f))
        if fn == 0.0 or abs(fn - c.gravity_m_s2) > c.acc_reject_m_s2:
            return False
        assert self.q_Ib is not None
        C_I = quat_to_dcm(self.q_Ib)
        _acc_lp_step(C_I, f, self._acc_lp, dt / (c.acc_lp_tau_s + dt), self._acc_first)
        self._acc_first = False
        ax, ay, nrm = _acc_innovation(self.C_nb, C_I, self._acc_lp)
        z = np.array([ax, ay])
        H = np.zeros((2, STATE_DIM))
        H[0, 1] = 1.0
        H[1, 0] = -1.0
        r = c.acc_noise_rad**2 * (1.0 + ((nrm - c.gravity_m_s2) / c.acc_adapt_m_s2) ** 2)
        res = kalman.update(np.zeros(STATE_DIM), self.P, z, H, r * np.eye(2))
        self.P = res.P
        self._inject(res.x)
        return True

    def update_mag(self, mag_b: FloatArray, dt: float) -> bool:
        """Heading-only update with one magnetometer sample (any unit); True when used."""
        c = self.config
        C = self.C_nb
        m = np.asarray(mag_b, dtype=float)
        mnx, mny, norm, dip = _dip_angle(
            C[0, 0], C[0, 1], C[0, 2], C[1, 0], C[1, 1], C[1, 2], C[2, 0], C[2, 1], C[2, 2], m[0], m[1], m[2]
        )
        if norm == 0.0 or not _mag_check(self._mag_ref, norm, dip, self._mag_cfg, dt):
            return False
        z = math.remainder(c.mag_declination_rad - math.atan2(mny, mnx), 2.0 * math.pi)
        # projected (consider) update: only the heading error receives a gain
        res = kalman.update(
            np.zeros(1),
            self.P[HEADING : HEADING + 1, HEADING : HEADING + 1],
            np.array([z]),
            np.eye(1),
            np.array([[c.mag_noise_rad**2]]),
        )
        k = float(self.P[HEADING, HEADING] / res.S[0, 0])
        P = self.P.copy()
        P[HEADING, :] *= 1.0 - k
        P[:, HEADING] *= 1.0 - k
        P[HEADING, HEADING] = res.P[0, 0]
        self.P = kalman.symmetrize(P)
        dx = np.zeros(STATE_DIM)
        dx[HEADING] = res.x[0]
        self._inject(dx)
        return True

    def update_rest(self, dt: float, gyr_b: FloatArray, acc_b: FloatArray) -> bool:
        """Advance the rest detector; at rest, measure the bias with the low-passed gyro."""
        c = self.config
        alpha = dt / (c.rest_tau_s + dt)
        self._rest_time = _rest_step(
            self._lp,
            np.asarray(gyr_b, float),
            np.asarray(acc_b, float),
            alpha,
            c.rest_gyro_th_rad_s,
            c.rest_acc_th_m_s2,
            c.rest_max_rate_rad_s,
            self._rest_time,
            dt,
        )
        if self._rest_time < c.rest_min_s:
            return False
        H = np.zeros((3, STATE_DIM))
        H[:, BG] = np.eye(3)
        z = self._lp[0:3] - self.b_g
        res = kalman.update(np.zeros(STATE_DIM), self.P, z, H, c.rest_noise_rad_s**2 * np.eye(3))
        self.P = res.P
        self._inject(res.x)
        return True

    def step(self, gyr_b: FloatArray, acc_b: FloatArray, mag_b: FloatArray | None, dt: float) -> FloatArray:
        """Process one sample and return ``q_nb`` (4,).

        Parameters
        ----------
        gyr_b : numpy.ndarray
            Angular rate in ``b``, rad/s.
        acc_b : numpy.ndarray
            Specific force in ``b``, m/s^2.
        mag_b : numpy.ndarray or None
            Magnetic field in ``b`` (any unit, e.g. µT); ignored for a 6-axis configuration.
        dt : float
            Sample period, s.
        """
        c = self.config
        use_mag = c.use_mag and mag_b is not None
        if self.q_nb is None:
            self.q_nb = initial_attitude(acc_b, mag_b if use_mag else None, c.mag_declination_rad)
        if self.q_Ib is None:
            self.q_Ib = self.q_nb.copy()
        self.predict(gyr_b, dt)
        self.rest = self.update_rest(dt, gyr_b, acc_b)
        self.acc_used = self.update_acc(acc_b, dt)
        self.mag_used = self.update_mag(mag_b, dt) if use_mag and mag_b is not None else False
        assert self.q_nb is not None
        return self.q_nb.copy()


# --------------------------------------------------------------------------------------------
# Compiled batch path (same equations, written out for numba)
# --------------------------------------------------------------------------------------------


@numba.njit(cache=True)
def _qmul(p: FloatArray, q: FloatArray) -> FloatArray:
    out = np.empty(4)
    out[0] = p[0] * q[0] - p[1] * q[1] - p[2] * q[2] - p[3] * q[3]
    out[1] = p[0] * q[1] + p[1] * q[0] + p[2] * q[3] - p[3] * q[2]
    out[2] = p[0] * q[2] - p[1] * q[3] + p[2] * q[0] + p[3] * q[1]
    out[3] = p[0] * q[3] + p[1] * q[2] - p[2] * q[1] + p[3] * q[0]
    return out


@numba.njit(cache=True)
def _qexp(vx: float, vy: float, vz: float) -> FloatArray:
    a = math.sqrt(vx * vx + vy * vy + vz * vz)
    out = np.empty(4)
    if a < 1e-12:
        out[0] = 1.0
        out[1] = 0.5 * vx
        out[2] = 0.5 * vy
        out[3] = 0.5 * vz
        return out / math.sqrt(out[0] ** 2 + out[1] ** 2 + out[2] ** 2 + out[3] ** 2)
    s = math.sin(0.5 * a) / a
    out[0] = math.cos(0.5 * a)
    out[1] = s * vx
    out[2] = s * vy
    out[3] = s * vz
    return out


@numba.njit(cache=True)
def _dcm(q: FloatArray) -> FloatArray:
    w, x, y, z = q[0], q[1], q[2], q[3]
    C = np.empty((3, 3))
    C[0, 0] = 1 - 2 * (y * y + z * z)
    C[0, 1] = 2 * (x * y - w * z)
    C[0, 2] = 2 * (x * z + w * y)
    C[1, 0] = 2 * (x * y + w * z)
    C[1, 1] = 1 - 2 * (x * x + z * z)
    C[1, 2] = 2 * (y * z - w * x)
    C[2, 0] = 2 * (x * z - w * y)
    C[2, 1] = 2 * (y * z + w * x)
    C[2, 2] = 1 - 2 * (x * x + y * y)
    return C


@numba.njit(cache=True)
def _joseph(P: FloatArray, H: FloatArray, R: FloatArray, y: FloatArray) -> tuple[FloatArray, FloatArray]:
    """Kalman update of a zero error state: returns (dx, P+) (Joseph form, Cholesky solve)."""
    PHt = P @ H.T
    S = H @ PHt + R
    S = 0.5 * (S + S.T)
    L = np.linalg.cholesky(S)
    # K = PHt S^-1  ->  solve S K^T = PHt^T
    Z = np.linalg.solve(L, PHt.T)
    Kt = np.linalg.solve(L.T, Z)
    K = Kt.T
    dx = K @ y
    IKH = np.eye(P.shape[0]) - K @ H
    Pn = IKH @ P @ IKH.T + K @ R @ K.T
    return dx, 0.5 * (Pn + Pn.T)


@numba.njit(cache=True)
def _inject_nb(q: FloatArray, b: FloatArray, dx: FloatArray) -> FloatArray:
    qn = _qmul(_qexp(dx[0], dx[1], dx[2]), q)
    qn /= math.sqrt(qn[0] ** 2 + qn[1] ** 2 + qn[2] ** 2 + qn[3] ** 2)
    for i in range(3):
        b[i] += dx[3 + i]
    return qn


@numba.njit(cache=True)
def _kernel(
    gyr: FloatArray,
    acc: FloatArray,
    mag: FloatArray,
    dt: float,
    q0: FloatArray,
    b0: FloatArray,
    P0: FloatArray,
    prm: FloatArray,
    use_mag: bool,
) -> tuple[FloatArray, FloatArray, npt.NDArray[np.int8]]:
    n = gyr.shape[0]
    q_out = np.empty((n, 4))
    b_out = np.empty((n, 3))
    flags = np.zeros((n, 3), dtype=np.int8)  # rest, acc used, mag used
    q = q0.copy()
    b = b0.copy()
    P = P0.copy()
    (sg, sbw, sa, sa_adapt, a_rej, grav, sm, decl, rest_tau, th_g, th_a, max_rate, rest_min, s_rest) = (
        prm[0],
        prm[1],
        prm[2],
        prm[3],
        prm[4],
        prm[5],
        prm[6],
        prm[7],
        prm[8],
        prm[9],
        prm[10],
        prm[11],
        prm[12],
        prm[13],
    )
    mag_cfg = prm[14:18].copy()
    acc_tau = prm[18]
    alpha_acc = dt / (acc_tau + dt)
    qI = q0.copy()
    acc_lp = np.zeros(6)
    acc_first = True
    lp = np.zeros(6)
    mag_ref = np.zeros(6)
    rest_time = 0.0
    alpha = dt / (rest_tau + dt)
    Q = np.zeros((6, 6))
    for i in range(3):
        Q[i, i] = sg * sg * dt
        Q[3 + i, 3 + i] = sbw * sbw * dt
    H_acc = np.zeros((2, 6))
    H_acc[0, 1] = 1.0
    H_acc[1, 0] = -1.0
    H_rest = np.zeros((3, 6))
    for i in range(3):
        H_rest[i, 3 + i] = 1.0
    R_rest = np.eye(3) * s_rest * s_rest
    for k in range(n):
        # predict
        dq = _qexp((gyr[k, 0] - b[0]) * dt, (gyr[k, 1] - b[1]) * dt, (gyr[k, 2] - b[2]) * dt)
        q = _qmul(q, dq)
        q /= math.sqrt(q[0] ** 2 + q[1] ** 2 + q[2] ** 2 + q[3] ** 2)
        qI = _qmul(qI, dq)
        qI /= math.sqrt(qI[0] ** 2 + qI[1] ** 2 + qI[2] ** 2 + qI[3] ** 2)
        F = np.eye(6)
        C = _dcm(q)
        F[0:3, 3:6] = -C * dt
        P = F @ P @ F.T + Q
        P = 0.5 * (P + P.T)
        # rest
        rest_time = _rest_step_nb(lp, gyr[k], acc[k], alpha, th_g, th_a, max_rate, rest_time, dt)
        if rest_time >= rest_min:
            y = lp[0:3] - b
            dx, P = _joseph(P, H_rest, R_rest, y)
            q = _inject_nb(q, b, dx)
            flags[k, 0] = 1
        # accelerometer
        fx, fy, fz = acc[k, 0], acc[k, 1], acc[k, 2]
        fn = math.sqrt(fx * fx + fy * fy + fz * fz)
        if fn > 0.0 and abs(fn - grav) <= a_rej:
            C_I = _dcm(qI)
            _acc_lp_step_nb(C_I, acc[k], acc_lp, alpha_acc, acc_first)
            acc_first = False
            ax, ay, nrm = _acc_innovation_nb(_dcm(q), C_I, acc_lp)
            y2 = np.empty(2)
            y2[0] = ax
            y2[1] = ay
            r = sa * sa * (1.0 + ((nrm - grav) / sa_adapt) ** 2)
            dx, P = _joseph(P, H_acc, np.eye(2) * r, y2)
            q = _inject_nb(q, b, dx)
            flags[k, 1] = 1
        # magnetometer (heading only)
        if use_mag:
            C = _dcm(q)
            mnx, mny, norm, dip = _dip_angle_nb(
                C[0, 0],
                C[0, 1],
                C[0, 2],
                C[1, 0],
                C[1, 1],
                C[1, 2],
                C[2, 0],
                C[2, 1],
                C[2, 2],
                mag[k, 0],
                mag[k, 1],
                mag[k, 2],
            )
            if norm > 0.0 and _mag_check_nb(mag_ref, norm, dip, mag_cfg, dt):
                z = decl - math.atan2(mny, mnx)
                z = z - 2.0 * math.pi * round(z / (2.0 * math.pi))
                S = P[2, 2] + sm * sm
                kg = P[2, 2] / S
                pnew = (1.0 - kg) ** 2 * P[2, 2] + kg * kg * sm * sm
                for j in range(6):
                    P[2, j] *= 1.0 - kg
                    P[j, 2] *= 1.0 - kg
                P[2, 2] = pnew
                dx = np.zeros(6)
                dx[2] = kg * z
                q = _inject_nb(q, b, dx)
                flags[k, 2] = 1
        q_out[k] = q
        b_out[k] = b
    return q_out, b_out, flags


@dataclass(frozen=True)
class AhrsEskfResult:
    """Batch output of :func:`run_ahrs_eskf`.

    Attributes
    ----------
    q_nb : numpy.ndarray
        ``(N, 4)`` attitude, ``b`` -> NED, scalar first.
    gyro_bias_rad_s : numpy.ndarray
        ``(N, 3)`` estimated gyro bias, rad/s.
    rest, acc_used, mag_used : numpy.ndarray
        ``(N,)`` bool flags per sample.
    """

    q_nb: FloatArray
    gyro_bias_rad_s: FloatArray
    rest: npt.NDArray[np.bool_]
    acc_used: npt.NDArray[np.bool_]
    mag_used: npt.NDArray[np.bool_]


def _params(c: AhrsEskfConfig) -> FloatArray:
    return np.array(
        [
            c.gyro_noise_rad_s_rthz,
            c.gyro_bias_rw_rad_s_rts,
            c.acc_noise_rad,
            c.acc_adapt_m_s2,
            c.acc_reject_m_s2,
            c.gravity_m_s2,
            c.mag_noise_rad,
            c.mag_declination_rad,
            c.rest_tau_s,
            c.rest_gyro_th_rad_s,
            c.rest_acc_th_m_s2,
            c.rest_max_rate_rad_s,
            c.rest_min_s,
            c.rest_noise_rad_s,
            c.mag_norm_rel_th,
            c.mag_dip_th_rad,
            c.mag_ref_tau_s,
            c.mag_new_field_s,
            c.acc_lp_tau_s,
        ]
    )


def run_ahrs_eskf(
    gyr_b: FloatArray,
    acc_b: FloatArray,
    mag_b: FloatArray | None,
    fs_hz: float,
    config: AhrsEskfConfig | None = None,
    q0_nb: FloatArray | None = None,
    b0_rad_s: FloatArray | None = None,
) -> AhrsEskfResult:
    """Run the filter over a whole recording (compiled loop; same results as :class:`AhrsEskf`).

    Parameters
    ----------
    gyr_b : numpy.ndarray
        ``(N, 3)`` angular rate in ``b``, rad/s.
    acc_b : numpy.ndarray
        ``(N, 3)`` specific force in ``b``, m/s^2.
    mag_b : numpy.ndarray or None
        ``(N, 3)`` magnetic field in ``b`` (any unit), or None for 6-axis use.
    fs_hz : float
        Sampling rate, Hz (constant).
    config : AhrsEskfConfig, optional
        Tunables (``use_mag=False`` forces 6-axis use).
    q0_nb, b0_rad_s : numpy.ndarray, optional
        Initial attitude (NED) and gyro bias; by default from the first sample and zero.

    Returns
    -------
    AhrsEskfResult
        Attitude, bias and per-sample flags.
    """
    c = config or AhrsEskfConfig()
    gyr = np.ascontiguousarray(gyr_b, dtype=float)
    acc = np.ascontiguousarray(acc_b, dtype=float)
    use_mag = bool(c.use_mag and mag_b is not None)
    mag = np.ascontiguousarray(mag_b, dtype=float) if use_mag and mag_b is not None else np.zeros_like(gyr)
    if gyr.shape != acc.shape or gyr.ndim != 2 or gyr.shape[1] != 3 or mag.shape != gyr.shape:
        raise ValueError(f"gyr/acc/mag must share shape (N, 3); got {gyr.shape}, {acc.shape}, {mag.shape}")
    if q0_nb is None:
        q0 = initial_attitude(acc[0], mag[0] if use_mag else None, c.mag_declination_rad)
    else:
        q0 = np.asarray(q0_nb, dtype=float) / np.linalg.norm(q0_nb)
    b0 = np.zeros(3) if b0_rad_s is None else np.asarray(b0_rad_s, dtype=float)
    P0 = np.diag(
        [c.init_tilt_sigma_rad**2] * 2 + [c.init_heading_sigma_rad**2] + [c.gyro_bias_init_rad_s**2] * 3
    )
    q, b, flags = _kernel(gyr, acc, mag, 1.0 / fs_hz, q0, b0, P0, _params(c), use_mag)
    return AhrsEskfResult(q, b, flags[:, 0] == 1, flags[:, 1] == 1, flags[:, 2] == 1)


def run_ahrs_eskf_reference(
    gyr_b: FloatArray,
    acc_b: FloatArray,
    mag_b: FloatArray | None,
    fs_hz: float,
    config: AhrsEskfConfig | None = None,
    q0_nb: FloatArray | None = None,
    b0_rad_s: FloatArray | None = None,
) -> AhrsEskfResult:
    """Same as :func:`run_ahrs_eskf` through the streaming :class:`AhrsEskf` (slow; for tests)."""
    f = AhrsEskf(config, q0_nb, b0_rad_s)
    n = len(gyr_b)
    q = np.empty((n, 4))
    b = np.empty((n, 3))
    fl = np.zeros((n, 3), dtype=bool)
    dt = 1.0 / fs_hz
    for k in range(n):
        q[k] = f.step(gyr_b[k], acc_b[k], None if mag_b is None else mag_b[k], dt)
        b[k] = f.b_g
        fl[k] = (f.rest, f.acc_used, f.mag_used)
    return AhrsEskfResult(q, b, fl[:, 0], fl[:, 1], fl[:, 2])
