"""Initialisation of the quaternion EKF (paper Sec. 3.1), run by :class:`~iotnav.engines.qekf.QekfEngine`.

Initialisation (Sec. 3.1): the device is still for ``init_duration_s`` (paper: 40 s; it ends
earlier when the fixes have moved more than ``init_max_displacement_m`` from their mean with a
speed above ``init_max_speed_mps``, the averages then ending one GNSS interval before the speed
last was below it: on car-tunnel, 30 s of driving averaged into the gyro bias leave a yaw-rate
error of 0.01 rad/s; the displacement test ignores the GNSS speed noise of a still receiver); the
mean GPS fix (in ECEF) sets the origin ``r_e(0)`` and ``C_en``; the mean gyro output the gyro
bias; the improved TRIAD of the mean accelerometer and magnetometer outputs the attitude. Its
covariance carries the accelerometer bias the mean still contains: the static gravity is
``-f_mean = g_b - b_a``, so ``dtheta = J_g b_a + noise``, ``P_theta = J_g P_ba J_g^T + P_TRIAD``
and ``P_theta,ba = J_g P_ba`` (mapped to the quaternion with ``Xi / 2``): tilt and horizontal bias
start correlated, and the heading inherits the tilt error through the magnetic dip. ``P_TRIAD``
is the rest of the error propagated through the Jacobians of the weighted TRIAD: the white
noise of the 40 s mean of the accelerometer (0.1 deg) and the magnetometer's direction error
``mag_dir_std_rad`` (:meth:`QekfEngine._init_triad_noise`), so that the tilt error is nearly
all bias, as it is (a single sample's ``acc_dir_std_rad`` in its place halved that
correlation). The
magnetic reference ``m_n`` is a configured field or the World Magnetic Model at the origin
(``pygeomag``); magnetometer calibration (hard and soft iron) is configured, the paper's
sensors being "previously calibrated".
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING

import numpy as np

from iotnav.engines.base import C_T, SRC_NONE, GnssSample, OutputBlock
from iotnav.engines.qekf_models import (
    BA,
    BG,
    N_STATES,
    POS,
    Q_NB,
    SA,
    SG,
    VEL,
    FloatArray,
    _level,
    quat_right,
)
from iotnav.geo import LocalFrame, ecef_to_geodetic, normal_gravity
from iotnav.gnss_accuracy import position_sigmas
from iotnav.techniques.triad import dcm_to_quat, improved_triad, triad_jacobian
from iotnav.wmm import log_year, reference_field

if TYPE_CHECKING:
    from iotnav.engines.qekf import QekfEngine

_I3 = np.eye(3)


def init_imu(eng: QekfEngine, t: float, acc: FloatArray, gyro: FloatArray, out: OutputBlock, k: int) -> bool:
    """One IMU sample (time s, specific force m/s^2, rate rad/s) of the initialisation: its
    sums, then the end of the initialisation when due. Returns True when it ended here (the
    sample is then processed as the first of the filter, without a prediction); else row
    ``k`` of ``out`` is written (no solution)."""
    if math.isnan(eng.t0):
        eng.t0 = t
    eng._sum_acc += acc
    eng._sum_gyro += gyro
    eng._n_imu += 1
    eng._n_init_all += 1
    eng._t_init_last = t
    if t - eng.t0 >= eng.config.init_duration_s:
        eng._finish_init(t)
    if eng.initialised:
        return True
    eng.acc[:] = acc
    eng.gyro[:] = gyro
    eng.have_imu = True
    out.floats[:, k] = math.nan
    out.floats[C_T, k] = t
    out.source[k] = SRC_NONE
    return False


def init_motion(eng: QekfEngine, s: GnssSample, r_e: FloatArray) -> bool:
    """End the initialisation early when the device moves (``init_max_displacement_m``).

    The averages then stop one GNSS interval before the latest epoch whose speed was at most
    ``init_max_speed_mps``. Returns True when the initialisation was completed here.
    """
    c = eng.config
    k = len(eng._init_snaps)
    eng._init_snaps.append(
        (eng._sum_acc.copy(), eng._sum_gyro.copy(), eng._n_imu, eng._sum_mag.copy(), eng._n_mag)
    )
    if not (math.isfinite(s.speed_mps) and s.speed_mps > c.init_max_speed_mps):
        eng._init_k_slow = k
        return False
    dist = float(np.linalg.norm(r_e - eng._sum_r_e / eng._n_fix))
    if c.init_max_displacement_m <= 0.0 or dist <= c.init_max_displacement_m:
        return False
    acc, gyro, n_imu, mag, n_mag = eng._init_snaps[max(eng._init_k_slow - 1, 0)]
    if n_imu == 0:
        return False
    eng._sum_acc, eng._sum_gyro, eng._n_imu, eng._sum_mag, eng._n_mag = acc, gyro, n_imu, mag, n_mag
    eng._finish_init(s.t)
    eng.P[VEL, VEL] += np.eye(3) * s.speed_mps**2
    eng.events.append({"type": "init_ended_by_motion", "t": s.t, "speed_mps": s.speed_mps, "dist_m": dist})
    return True


def finish_init(eng: QekfEngine, t: float) -> None:
    c = eng.config
    if eng._n_fix == 0 or eng._n_imu == 0:
        return  # keep waiting
    r_e0 = eng._sum_r_e / eng._n_fix
    lat, lon, h = (float(v) for v in ecef_to_geodetic(r_e0))
    eng.frame = LocalFrame(lat, lon, h)
    eng.r_e0 = r_e0
    eng.C_en = eng.frame.C_en
    eng._geo[:3] = r_e0
    eng._geo[3:] = eng.C_en.ravel()
    g = c.gravity_mps2 if c.gravity_mps2 > 0 else normal_gravity(lat, h)
    eng.g_n = np.array([0.0, 0.0, g])
    if c.mag_field_n_ut is not None:
        eng.m_n = np.asarray(c.mag_field_n_ut, float)
    else:
        year, year_from = log_year(t, eng.utc_offset_s, c.wmm_year)
        ref = reference_field(lat, lon, h, year)
        eng.m_n = ref.field_n_ut
        eng.mag_reference = {**ref.to_dict(), "year_from": year_from}
    f_mean = eng._sum_acc / eng._n_imu
    gyro_mean = eng._sum_gyro / eng._n_imu
    x = np.zeros(N_STATES)
    x[SG] = 1.0
    x[SA] = 1.0
    x[BG] = gyro_mean
    J_g: FloatArray | None = None
    if eng._n_mag > 0 and c.use_mag:
        m_b = eng._sum_mag / eng._n_mag  # calibrated in _mag
        C = improved_triad(-f_mean, m_b, eng.g_n, eng.m_n, c.acc_dir_std_rad, c.mag_dir_std_rad)
        J_g, J_m = triad_jacobian(-f_mean, m_b, eng.g_n, eng.m_n, c.acc_dir_std_rad, c.mag_dir_std_rad)
        P_th = eng._init_triad_noise(J_g, J_m, m_b)
    else:  # levelling only, yaw 0
        roll = math.atan2(-f_mean[1], -f_mean[2])
        pitch = math.atan2(f_mean[0], math.hypot(f_mean[1], f_mean[2]))
        C = _level(roll, pitch)
    x[Q_NB] = dcm_to_quat(C)
    eng.x = np.concatenate([x, np.zeros(eng.n - N_STATES)])
    P = np.zeros(N_STATES)
    P[Q_NB] = (0.5 * c.init_att_std_rad) ** 2
    P[VEL] = c.init_vel_std_mps**2
    sig = position_sigmas(math.nan, math.nan, math.nan, math.nan, c.uere_m, c.default_dop)
    P[POS] = sig.ned_m**2
    P[BG] = c.gyro_bias_init_rad_s**2
    P[BA] = c.acc_bias_init_mps2**2
    P[SG] = P[SA] = c.scale_init**2
    eng.P = np.diag(P)
    if eng.n > N_STATES:
        eng.P = np.pad(eng.P, (0, eng.n - N_STATES))
        eng._init_gnss_error(t)
    if J_g is not None:
        # the static TRIAD used gravity -f_mean = g_b - b_a: its attitude error is
        # dtheta = J_g b_a + noise, hence P_tt = J_g P_ba J_g^T + P_triad, P_t,ba = J_g P_ba
        Xi = 0.5 * quat_right(x[Q_NB])[:, 1:]
        P_ba = eng.P[BA, BA]
        P_tt = J_g @ P_ba @ J_g.T + P_th
        eng.P[Q_NB, Q_NB] = Xi @ P_tt @ Xi.T + c.quat_norm_std**2 * np.outer(x[Q_NB], x[Q_NB])
        eng.P[Q_NB, BA] = Xi @ J_g @ P_ba
        eng.P[BA, Q_NB] = eng.P[Q_NB, BA].T
    eng.fallback = J_g is None
    eng.heading_ok = not eng.fallback
    if eng.fallback:
        # standing still, the initialisation's mean specific force is the first gravity
        # reference of the mount aligner, which is only fed from here on: without it the
        # aligner waits for the next stop (:mod:`iotnav.engines.qekf_fallback`, step 1)
        eng.aligner.set_gravity_reference(f_mean, t)
    eng.initialised = True
    eng.t_x = t
    eng._norm_update(t)
    eng._prior = None
    eng.events.append(
        {
            "type": "init_done",
            "t": t,
            "lat_deg": lat,
            "lon_deg": lon,
            "height_m": h,
            "fixes": eng._n_fix,
            "imu_samples": eng._n_imu,
            "mag_samples": eng._n_mag,
            "fallback": eng.fallback,
            "gyro_bias_rad_s": gyro_mean.tolist(),
        }
    )
    eng._flush_record()


def init_triad_noise(eng: QekfEngine, J_g: FloatArray, J_m: FloatArray, m_b: FloatArray) -> FloatArray:
    """Covariance (rad^2, in ``n``) of the initial TRIAD's errors other than the accelerometer
    bias (which :meth:`_finish_init` carries as ``J_g P_ba J_g^T``).

    The vector errors are propagated through the Jacobians of the weighted solution,
    ``P = J_g S_g J_g^T + J_m S_m J_m^T``. Gravity is the mean of ``N`` specific-force samples
    over ``T = N dt`` seconds: its white error has the per-axis variance ``A^2 / T``
    (``A`` = ``acc_noise_mps2_rthz``, m/s^2/sqrt(Hz)), ``S_g = A^2 / T I`` (about 0.1 deg over
    40 s), the rest of its error being the bias. ``acc_dir_std_rad``, the direction sigma of a
    single observation, is not the error of a 40 s mean: used here it said half of the
    initial tilt variance was white noise and so halved the tilt / bias correlation; a tilt
    later corrected from the GNSS velocity then corrected the bias only half, and the
    following TRIAD observations pulled the attitude back (car-magnetometer seeds 6 and 8:
    a 2.5 deg tilt and 5 deg yaw error for the first 30 s of driving). The magnetometer's
    ``mag_dir_std_rad`` stands for calibration residuals and the reference field's error,
    which do not average out: ``S_m = (mag_dir_std_rad |m_b|)^2 I``. (Components along the
    vectors drop out in the Jacobians.)
    """
    c = eng.config
    n_all = eng._n_init_all
    dt = (eng._t_init_last - eng.t0) / (n_all - 1) if n_all > 1 else 0.0
    T = eng._n_imu * dt
    if not T > 0.0:
        S_g = (c.acc_dir_std_rad * float(eng.g_n[2])) ** 2 * _I3  # a single sample
    else:
        S_g = c.acc_noise_mps2_rthz**2 / T * _I3
    S_m = (c.mag_dir_std_rad * float(np.linalg.norm(m_b))) ** 2 * _I3
    return J_g @ S_g @ J_g.T + J_m @ S_m @ J_m.T
