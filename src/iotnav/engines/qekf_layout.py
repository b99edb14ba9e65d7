"""State layout of the compiled quaternion EKF step (:mod:`iotnav.engines.qekf_kernel`).

One declaration of the float arrays the kernels and the engine share: the engine's scalar state
``st`` (indices ``S_*``), its vectors ``vec`` (offsets ``V_*``), the constant tunables ``prm``
(``K_*``), the return codes of :func:`iotnav.engines.qekf_kernel.imu_run` (``R_*``) and the
kernels' scratch (``W_*``, :func:`scratch`). The engine's attributes of the same names are views
of these arrays (:class:`iotnav.engines.qekf.QekfEngine`).
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING

import numba
import numpy as np
import numpy.typing as npt

if TYPE_CHECKING:
    from iotnav.engines.qekf_config import QekfConfig

FloatArray = npt.NDArray[np.float64]

#: Navigation states (the paper's 22; the GNSS error states follow, 22-27).
N0 = 22
#: ``st``: time of the state (s), IMU seen (0/1), time and horizontal speed of the latest speed
#: epoch (s, m/s), along-track acceleration and its sigma (m/s^2), IMU samples since the latest
#: GNSS epoch, samples in the specific-force sum, gravity samples since the latest magnetometer
#: sample, sums of ``a_dyn``, ``|a_b|`` (m/s^2) and the compensation variance (m^2/s^4), time of
#: the latest accepted fix (s), ``dt`` of the cached GNSS error transition (s; NaN: none), a
#: smoothing record pending (0/1: an update since the last one), IMU rows since the last
#: record, time of the latest non-holonomic observation (s), the no-magnetometer fallback and
#: its heading known (0/1); set by the engine before each :func:`~iotnav.engines.qekf_kernel.imu_run`:
#: the non-holonomic observation compiled there (0/1; else Python applies it), the mount yaw it
#: uses (rad) and the mount aligner's sigma of it (rad); entries in the kernel's NIS log
#: (:data:`N_LOG`).
(
    S_T_X,
    S_HAVE_IMU,
    S_T_SPEED,
    S_V_SPEED,
    S_A_LONG,
    S_A_LONG_STD,
    S_N_INTERVAL,
    S_F_N,
    S_ACC_MAG_N,
    S_A_DYN_SUM,
    S_A_COMP_SUM,
    S_COMP_VAR_SUM,
    S_T_FIX,
    S_GE_DT,
    S_PRIOR,
    S_ROWS,
    S_T_NHC,
    S_FALLBACK,
    S_HEADING_OK,
    S_NHC_COMPILED,
    S_NHC_MOUNT,
    S_NHC_SIG_MU,
    S_N_LOG,
) = range(23)
N_ST = 23
#: ``vec`` offsets (3 floats each unless said): latest raw specific force (m/s^2) and rate
#: (rad/s), specific-force sum and the previous interval's mean (m/s^2), compensated gravity
#: sum (m/s^2), ``var(e_gm)`` per NED axis (m^2), the cached GNSS error transition (12: per
#: horizontal and vertical axis ``b, c, a, Q_ee, Q_eg, Q_gg`` per unit variance), the fallback's
#: yaw-rate sum (rad/s) and count since the latest GNSS epoch (2) and since the latest
#: non-holonomic observation (2).
V_ACC, V_GYRO, V_F_SUM, V_F_REF, V_G_SUM, V_VAR_GM, V_GE, V_R_GNSS, V_R_NHC = 0, 3, 6, 9, 12, 15, 18, 30, 32
N_VEC = 34
#: ``prm``: gyro and accelerometer white-noise densities squared, bias random walks squared
#: (gyro, accelerometer), scale-factor random walk squared, cross-axis intensities ``k_w``,
#: ``k_a``, relative compensation error, TRIAD bias correction (0/1), GNSS error correlation
#: times (horizontal, vertical, s) and receiver filter (s), smoothing (0/1), IMU rows between
#: smoothing records, period of the non-holonomic observation (s; 0: none), its minimum speed
#: (m/s), maximum mean yaw rate (rad/s), velocity floor (m/s), sideslip sigma (rad) and lever
#: (m), the sigma of the quaternion norm pseudo-observation, the NIS gate of a scalar
#: observation (inf: none).
(
    K_VAR_G,
    K_VAR_A,
    K_RW_BG,
    K_RW_BA,
    K_RW_S,
    K_K_W,
    K_K_A,
    K_COMP_REL,
    K_CORRECTED,
    K_TE_H,
    K_TE_V,
    K_TF,
    K_SMOOTH,
    K_RECORD_EVERY,
    K_NHC_INTERVAL,
    K_NHC_MIN_SPEED,
    K_NHC_MAX_YAW_RATE,
    K_NHC_VEL_STD,
    K_NHC_SIDESLIP,
    K_NHC_LEVER,
    K_NORM_STD,
    K_GATE_1,
) = range(22)
N_PRM = 22
#: Rows of the kernel's NIS log (``(t, kind, NIS, accepted)``, kind ``LOG_NHC`` or
#: ``LOG_NORM``), which the engine moves into its ``nis`` list after each
#: :func:`~iotnav.engines.qekf_kernel.imu_run`.
N_LOG = 64
LOG_NHC, LOG_NORM = 0.0, 1.0
#: :func:`~iotnav.engines.qekf_kernel.imu_run` return codes: block done; sample ``k`` not
#: started, a smoothing record is pending (Python records it, then runs ``k`` again); sample
#: ``k`` predicted and accumulated, a non-holonomic observation due (Python applies it, then the
#: rest of the sample); the same with a smoothing record due (Python records it and writes the
#: row).
R_DONE, R_FLUSH, R_NHC, R_RECORD = 0, 1, 2, 3

#: Scratch of the kernels (:func:`scratch`), so that no kernel allocates per sample: ``wm``, up
#: to four (n, n) matrices of the prediction; ``ws``, rows of ``W_MAX`` floats holding the small
#: vectors and matrices of :mod:`iotnav.engines.qekf_predict_kernel`'s ``_propagate`` (rows
#: ``W_PROP``) and ``predict`` (``W_PRED``), and of :mod:`iotnav.engines.qekf_kernel`'s
#: ``accumulate_gravity`` (``W_GRAV``), ``write_row`` (``W_ROW``) and ``fallback_accumulate``
#: (``W_FB``).
W_MAX = 28
W_PROP, W_PRED, W_GRAV, W_ROW, W_FB = 0, 50, 68, 86, 96
N_WM, N_WS = 4, 102


@numba.njit(cache=True)
def scratch() -> tuple[FloatArray, FloatArray]:
    """New scratch ``(wm, ws)`` of the kernels (``N_WM`` (``W_MAX``, ``W_MAX``) matrices and
    ``N_WS`` rows of ``W_MAX``; module constants above); contents need no initialisation."""
    return np.empty((N_WM, W_MAX, W_MAX)), np.empty((N_WS, W_MAX))


def parameters(c: QekfConfig, k_w: float, k_a: float, gate_1: float | None) -> FloatArray:
    """The constant tunables ``prm`` (``K_*``) of configuration ``c``, with the cross-axis
    intensities ``k_w``, ``k_a`` (:class:`iotnav.engines.qekf.QekfEngine`) and the NIS gate of a
    scalar observation ``gate_1`` (None: none)."""
    return np.array(
        [
            c.gyro_noise_rad_s_rthz**2,
            c.acc_noise_mps2_rthz**2,
            c.gyro_bias_rw_rad_s2_rthz**2,
            c.acc_bias_rw_mps3_rthz**2,
            c.scale_rw_1_s_rthz**2,
            k_w,
            k_a,
            c.comp_rel_error,
            float(c.triad_bias_corrected),
            c.gnss_corr_time_s,
            c.gnss_corr_time_v_s,
            c.gnss_receiver_filter_s,
            float(c.smoothing),
            float(c.record_every),
            c.nhc_interval_s,
            c.nhc_min_speed_mps,
            c.nhc_max_yaw_rate_rad_s,
            c.nhc_vel_std_mps,
            c.nhc_sideslip_std_rad,
            c.nhc_lever_m,
            c.quat_norm_std,
            math.inf if gate_1 is None else gate_1,
        ]
    )
