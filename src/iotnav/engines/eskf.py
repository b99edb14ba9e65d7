"""Error-state extended Kalman filter (ESKF) for low-cost GNSS + MEMS IMU (+ magnetometer).

Loosely coupled INS/GNSS in the flat-earth local NED frame of :mod:`iotnav.strapdown`
(Groves 2013, "Principles of GNSS, Inertial, and Multisensor Integrated Navigation
Systems", 2nd ed., ch. 14; Sola 2017, "Quaternion kinematics for the error-state Kalman
filter", §5-§7). The nominal state is integrated at the IMU rate with the same strapdown step
as the simulator; an error state carries the uncertainty:
position, velocity, attitude, gyro and accelerometer biases (first-order Gauss-Markov, from
the datasheet's bias instability and correlation time), the mounting rotation ``C_vb``, the
time-correlated GNSS position error (two blocks: the receiver's smoothed output and the
Gauss-Markov error behind it) and optionally the gyro and accelerometer scale factors
(24 states, 30 with them).
The sensors' cross-axis coupling is not estimated but enters the noise model (gyro:
rate-dependent attitude noise; accelerometer: a wider turn-on bias at levelling and
acceleration-dependent bias noise), so that the covariance stays honest with it.
The error-state equations, the discretisation and every measurement model (with its ``H``)
are written out in :mod:`iotnav.engines.eskf_models`.

Wiring per sample
-----------------
IMU
    The previous sample (mean rate and specific force over its interval) is integrated up to
    the new sample's time; the covariance is propagated every ``cov_interval_s`` with the
    interval means (and always before a measurement). Block 3's static detector
    (:class:`iotnav.techniques.static.StaticDetector`) decides static / moving; static:
    zero-velocity and zero-angular-rate updates every ``zupt_interval_s``; moving wheeled
    vehicle with a known mount: the non-holonomic constraint every ``nhc_interval_s``
    (Shin 2005, "Estimation techniques for low-cost inertial navigation", §4.3). One
    :class:`~iotnav.engines.base.Output` is returned per IMU sample.

    All of that is one numba-compiled kernel (``_imu_kernel``) on the engine's arrays
    (:attr:`EskfEngine.st` for flags, times and small vectors, the nominal-state arrays,
    ``P``, the covariance accumulator, block 3's and block 5's state): ``step(ImuSample)``
    runs it on a one-sample block and :func:`~iotnav.engines.base.run_batch` on the runs of
    IMU samples between GNSS / magnetometer samples (:meth:`EskfEngine.imu_block`), so both
    execute the same code. The covariance propagation skips the zeros of ``Phi`` and the
    measurement update is the Joseph form written out in ``O(n^2 m)``
    (:func:`eskf_models.kalman_update`); GNSS and magnetometer samples stay in Python and use
    the same compiled propagation and update. Events and NIS records of the kernel go through
    a record buffer (``EskfEngine.rec``) and are appended in order; the kernel returns to
    Python only when the levelling window completes (once) or that buffer is full.
GNSS
    The nominal state is integrated to the fix time and the covariance and the GNSS error
    estimates ``e``, ``e_gm`` propagated to it (before, ``e`` and ``e_gm`` in the position
    innovation could lag the fix by up to ``cov_interval_s``), then position (with lever
    arm) and velocity updates. Velocity is the receiver's NED velocity when present
    (``sample.vn/ve/vd``), else speed and course (horizontal). Noise: ``h_acc_m`` /
    ``v_acc_m`` / ``s_acc_mps`` when the receiver reports them, else DOP x ``uere_m``
    (:mod:`iotnav.gnss_accuracy`: ``h_acc_m`` is the 2D figure, per axis ``/ sqrt(2)``). The
    position error is split into a white part and a time-correlated part carried as states.
    The white part is the rounding of the fixes' output format, found from the fixes
    themselves (:mod:`iotnav.engines.gnss_resolution`: NMEA minutes with 3, 4 or 5 decimals
    are steps of 1.85 m, 0.185 m or 1.85 cm of latitude, white noise of ``step / sqrt(12)``;
    ``gnss_white_from_resolution``), or ``gnss_white_floor_m`` (5 mm), or
    ``gnss_white_fraction`` of the accuracy for receivers whose fixes jitter (0 by default),
    whichever is largest.
    The correlated part is carried as states so that minutes-long correlated receiver errors do
    not make the filter over-confident: a Gauss-Markov error (``GNM``, correlation time
    ``gnss_corr_time_s``, vertically ``gnss_corr_time_v_s``) seen through the receiver's
    position smoothing (first-order
    low-pass, ``gnss_receiver_filter_s``), whose output ``GNE`` is what the fix carries. The
    smoothed error is second order, smooth from fix to fix, as a consumer receiver's is; a
    first-order model predicts larger fix-to-fix changes than occur (GNSS position NIS/dof
    0.11 instead of 0.39 over 20 simulated car runs). See :mod:`iotnav.engines.eskf_models`.
Magnetometer
    Calibrated (``mag_hard_iron_ut``, ``mag_soft_iron``), heading update every
    ``mag_interval_s``; also gives the initial heading. Without a calibration (or
    ``mag_calibrated``) it is left out, counted in ``summary()["mag_unused"]``.

GNSS velocity noise
    A receiver that smooths its position reports a velocity (from Doppler) whose error is the
    derivative of the smoothed position error, ``(e_gm - e) / t_f``, plus the white Doppler
    noise of ``s_acc_mps``: the first part is in the measurement model through the GNSS
    error states, ``R`` holds the second only.

Every update is gated by its NIS (``gate_probability``); a rejected update becomes an
``update_rejected`` event (``fix_rejected`` for GNSS positions) with NIS and test ratio. After
``max_gnss_rejections`` consecutive rejected fixes the position covariance is inflated and the
next fix is accepted (event ``gate_reset``), so the filter cannot lock itself out. Covariance
updates use the Joseph form and symmetrisation of :mod:`iotnav.kalman`.

Consistency
-----------
Over 20 Monte Carlo runs of 90 s ``car-tunnel`` (seeds 0-19, 1 Hz GNSS, open sky; the runs
of ``tests/test_eskf.py``; figures on held-out seeds 100-119 in brackets):

* NEES of position, velocity, attitude (9 dof, 95 % band 7.2-11.0): 10.3 with the
  simulator's full MPU-6050 errors (10.1 [9.8] before ``gnss_corr_time_v_s``; position 3.1
  for 3 dof, velocity 2.3, tilt 2.3 for 2, yaw 1.4 for 1); 8.9 [7.2] with the IMU errors the
  filter models exactly. The position
  starts correlated with the GNSS error states (``cov(dp, de) = -var(e)``: the position is
  the fix minus ``e``); started independent, the first fix halved the position variance and
  the NEES was 12.2 [12.5], over-confident.
* GNSS position NIS per dof 0.94 (0.88 [0.86] before ``gnss_corr_time_v_s``).
* Whiteness (Bar-Shalom, Li, Kirubarajan 2001, "Estimation with Applications to Tracking and
  Navigation", §5.4): time-average normalised autocorrelation of the whitened innovations
  ``L^-1 nu`` (``S = L L^T``), pooled over the runs
  (:func:`iotnav.eval.consistency.innovation_autocorrelation`), lags 1-10 s, 95 % band
  +-0.058 (lag 1) to +-0.063 (lag 10). GNSS position: white, Box-Pierce sums over the 10
  lags 12.2 / 13.6 / 14.0 (N / E / D) [12.0 / 13.9 / 16.0, modelled] against chi-square(10)
  18.3 (21.7 for the three together at 95 %, the tests' criterion).
  This needs the white part of the position noise to be what the fixes carry: with a fixed
  2 % of the accuracy and a 5 cm floor (the earlier default, absent from the simulated
  fixes, which are continuous), the white part was larger than the error of the filter's 1 s
  position prediction (the Doppler velocity and the smoothed, second-order GNSS error states
  make that prediction good to a few cm), the gain fell below the optimum and each
  innovation left part of itself for the next: lag 1 +0.51 / +0.49 / +0.26, Box-Pierce
  355 / 314 / 84. Hence the white part from the fixes' own rounding
  (:mod:`iotnav.engines.gnss_resolution`). GNSS velocity: lag 1 -0.04 / -0.07 / +0.04,
  Box-Pierce 15.6 / 19.4 / 9.0 [15.5 / 2.7 / 6.6]; over 398 runs (seeds 0-399 less one
  diverging and one with a multipath jump; lag-1 band +-0.013) 8.1 / 10.3 / 13.0, lag 1
  +0.01 / -0.00 / +0.02: white (the east 19.4 of seeds 0-19 is a chance exceedance, the only
  horizontal one in 19 disjoint sets of 20 runs). With a single correlation time (the
  simulator's vertical 200 s taken as the horizontal 150 s) the filter expected a third more
  vertical velocity error from the receiver's smoothing than there is and under-weighted the
  vertical fixes: whitened variance 0.82 (velocity and position), lag 1 +0.043, Box-Pierce 46.6
  over the 398 runs; hence ``gnss_corr_time_v_s``. The velocity NEES below 3 (2.4 full
  preset, 2.7 modelled, 200 runs) is mostly vertical, per axis 0.91 / 0.97 / 0.64: the NHC's
  0.1 m/s vertical noise, where the simulated car has none (with 0.03 m/s the vertical is
  0.95, modelled); it does not change the innovations' whiteness.

Reported accuracy
-----------------
``gnss_error_scales_with_accuracy`` (default): the correlated receiver error is taken as
``e = sigma(t) y`` with ``y`` a unit Gauss-Markov process, so when the reported accuracy
changes by ``k`` the estimates ``e``, ``e_gm`` and their covariance rows are scaled by ``k``
(:meth:`EskfEngine._scale_gnss_error`), at once for continuous figures and for jumps, but
low-passed over the rounding steps of rounded figures
(:class:`~iotnav.engines.gnss_resolution.AccuracyScaling`). Scaled at once by every step
(before), the rounding of the DOPs was taken for information about ``e``: 8 car-tunnel runs
of 90 s, ANEES 10.9 with continuous figures, 14.5 with DOPs of 2 decimals and 34 with 1
decimal, as many NMEA receivers write HDOP; low-passed (5 s) 11.0 and 12.1. It costs some
accuracy where the model is exact, as in the simulator: on the 600 s car-tunnel run through
NMEA the open-sky RMS is 1.23 m forward and 0.92 m smoothed, 1.02 and 0.72 m before. A receiver re-acquiring after a tunnel reports a
larger accuracy and its fixes are that much further off; without the scaling the states kept
the open-sky 1.3 m, the filter accepted a first fix 9-11 m off and rejected the next five
good ones (car-tunnel seed 0, 600 s: RMS 3.62 m, four gate resets; with it 2.79 m and none;
seeds 1-3: 1.62 / 1.44 / 2.11 -> 0.94 / 0.86 / 1.05 m outside the outages). The ratio is
taken only between sigmas of the same kind (hAcc/vAcc, or DOPs x UERE), not
when a receiver's fixes switch between them. For the smoother the scaling is a linear step of
the transition into the fix's record (RTS uses the records' priors too: recorded as part of
the fix's update it carried the smoothed estimate back in the wrong units, 600 s smoothed
RMS 0.97 instead of 0.86 m). A receiver whose reported accuracy does not follow its error
can turn it off.

Innovations are kept on request: ``EskfEngine(config, record_innovations=True)`` stores the
innovation and ``S`` of every GNSS position and velocity update (:class:`InnovationLog`).

RTS smoothing
-------------
``EskfConfig(smoothing=True)`` (``iotnav run --smooth``) keeps the records of the
fixed-interval Rauch-Tung-Striebel smoother (Rauch, Tung and Striebel 1965, "Maximum
likelihood estimates of linear dynamic systems", AIAA J. 3(8)) of
:mod:`iotnav.engines.smoother` in its error-state form: RTS runs on the linear error-state
model about the nominal trajectory. Let ``e_k`` be the error about the *prior* nominal state at
record ``k`` (before its updates). The filter's prior is ``x-_k = 0`` (the error state is zero
after every reset) with ``P-_k``; its updates give ``x+_k = dx_k`` and ``P+_k``; the nominal
becomes ``x^_k (+) dx_k``, about which the error is ``e_k - dx_k``, so
``e_{k+1} = Phi_{k+1} (e_k - dx_k) + w`` and ``x-_{k+1} = Phi_{k+1} (x+_k - dx_k) = 0`` as
recorded (the control input ``-Phi dx`` is implicit). The backward pass gives ``xs_k`` about
the prior nominal at ``k``: the rows output after the updates at ``k`` are corrected by
``xs_k - dx_k`` and those reaching ``k + 1`` by ``xs_{k+1} - 0``, what
:func:`~iotnav.engines.smoother.smooth_output` interpolates
(:meth:`EskfEngine.smoothing_corrections`; attitude: ``C_true = exp([dth x]) C_nb`` with
``dth`` in ``n``, the smoother's convention, and the mount error for the vehicle attitude).

* Record points: every update epoch -- GNSS, magnetometer and the kernel's ZUPT, ZARU and NHC
  (all updates at one ``t_state`` form one record) -- and every ``record_every`` covariance
  propagations without one. A record is opened before the first update of its time (prior:
  ``P`` then), the updates' ``dx`` are summed (each is about the nominal the previous one left:
  to first order the sum is the correction about the prior nominal), and it is written at the
  next covariance propagation (posterior: ``P`` before that interval). ``Phi`` is the product
  of the transitions that propagated ``P`` since the previous record
  (:func:`eskf_models.propagate_covariance_phi`), so ``P-_{k+1} = Phi P+_k Phi^T + Q`` holds
  exactly and, with only predictions between record points, RTS on them is exact (tested
  against a record at every propagation).
* Start: the first record is at the epoch where position and heading are both initialised;
  before, the output is the last fix, not the nominal state, and the levelling, the heading
  reset and the position initialisation all come before it.
* Covariance resets while recording (the mount from magnetometer and course):
  ``P <- T P T^T + Q_r``. The open record is written and ``T`` joins the transition to the next
  one (:meth:`EskfEngine._smoothing_reset`), a linear step like any other; a re-initialised
  state has a zero row in ``T``, so nothing is carried back to it across the reset.
* Gate reset (``gate_reset``: position covariance widened to ``(3 sigma_p)^2``, decorrelated,
  then a forced fix) is *not* such a step: the widening is part of the forced update. The
  record of the forced fix gets the prior the filter had without the widening (the
  un-widened ``P`` propagated to the fix, :meth:`EskfEngine._smoothing_unwidened_prior`), its
  posterior is the filter's (``dx`` and ``P+`` after the forced fix), and the transition to
  it carries no reset. The widening is the filter's remedy for a position error larger than
  its ``P`` (a drift in an outage beyond the model, or an accepted bad fix, typically the
  first fix after a tunnel, whose reacquisition error is a few times the reported one); it
  is not a jump of the true position, which is continuous. Recorded as a reset (a zero
  ``POS`` row in ``T``, or ``T = I`` with ``Q_r = (3 sigma_p)^2``), it told the smoother that
  the position could jump there by metres, so the forced fix -- the first fix the filter
  trusts after the outage -- barely corrected the outage and the fixes before it, and an
  accepted bad exit fix stayed uncorrected: on the 600 s ``car-tunnel`` (seed 0, resets at
  401, 481 and 567 s) the smoothed horizontal RMS was 3.57 m against 3.48 m forward (largest
  error in the 440-475 s tunnel 11.5 m both; errors up to 9 m in it where the forward filter
  had 1-3 m, the smoother following the accepted exit fix at 476 s, 8.9 m off); seeds 0-10:
  mean RMS 3.64 m forward, 3.00 m smoothed with the reset recorded (3.00 m with ``T = I``
  and ``Q_r``), 2.22 m with the un-widened prior (outside outages, ``t >= 60 s``: 2.60 ->
  2.61 and 2.15 m); the smoothed normalised position error (error / smoothed std, ideally
  1) 1.77-2.63 -> 1.08-1.44 on seeds 0, 5, 6. The filter's posterior at the forced fix may
  exceed the un-widened prior in some directions (the decorrelated ones), so before a gate
  reset the smoothed covariance is not everywhere below the filter's. This holds after an
  outage (a gap of valid fixes longer than ``smoothing_drift_gap_s``, 10 s, ended at most
  twice that before the forced fix). After a short gap the forced fix is more likely the
  re-acquiring receiver's error than a drift, and the reset is recorded as a
  re-initialisation of the position: on ``car-magnetometer`` (4 s gap, resets on seeds 0, 3,
  4, 5) the un-widened prior made the smoothed RMS 0.1-0.9 m worse than the forward filter's
  (seed 0: 2.11 forward, 3.07 smoothed), the re-initialisation keeps it at or below (2.12).
* Memory: ``8 (1 + 2 n + 3 n^2)`` bytes a record, 21.8 KB with 30 states (13.8 KB with 24).
  With the NHC or ZUPT running (10 Hz) every 0.1 s is a record: about 220 KB per second of
  data; ``record_every`` (default 10, i.e. 0.5 s) sets the spacing without them.
* Off (default): the forward output is bit-identical and the kernel's extra cost is a flag
  test per sample, propagation and update. On, the forward output is the same.

Initialisation
--------------
1. Levelling: roll and pitch from the mean accelerometer over ``level_time_s`` (gyro mean as
   the initial gyro bias when the accelerometer is quiet). Levelling absorbs the
   accelerometer bias and scale error, so the tilt covariance is that error over ``g`` and
   fully correlated with it (:func:`eskf_models.level_covariance`; an MPU-6050's 17 mg
   turn-on bias alone is a 1-degree tilt). Anything integrated before is discarded.
   When the yaw is later set, every navigation-frame error is rotated with it
   (:func:`eskf_models.heading_reset_transform`), or the tilt/bias correlation learnt at rest
   would point the wrong way and make the tilt look observable.
2. Heading: magnetometer (if any) or, without one, ``course + mount yaw`` at the first GNSS
   epoch faster than ``align_min_speed_mps`` once the mount yaw is known (``mount_rpy_rad``
   from the configuration, else the first accepted estimate of block 5,
   :class:`iotnav.techniques.mount.MountAligner`). With a magnetometer and no configured
   mount, the mount yaw is ``sensor yaw - course`` at that epoch. Mount roll and pitch are
   the sensor's at that epoch (the vehicle taken as level within ``vehicle_level_std_rad``;
   any mounting, upside down included), their error tied to the sensor tilt error
   (:meth:`EskfEngine._init_mount`); the whole mount is refined as states by the NHC
   (``estimate_mount``). The mount roll is not observable from the NHC (a rotation about
   the direction of travel); it follows the sensor roll through that correlation.
3. Before the heading is known, the output is the last fix extrapolated with the GNSS
   velocity (source ``fix``).

Start anywhere (issue 16): a log may begin in motion, with no static period and a raw gyro.

* Levelling in motion (the window not quiet, or the latest GNSS speed above
  ``zupt_max_gnss_speed_mps``: a car cruising straight is as quiet as one at rest) takes the
  gyro bias as unknown (its turn-on sigma) and the tilt 1-sigma as ``moving_tilt_std_rad``
  (the window's mean acceleration is unknown: 0.1 rad is 1 m/s^2). On car-tunnel cut at
  40 s (5.6 m/s), seeds 0-3, the window's mean rate was taken for the bias before: mount
  34-38 deg off, 18 gate resets, RMS 81-101 m; now 0.2-1.0 deg, none, 1.1-2.0 m.
* Gravity aiding (``gravity_aiding``) until the heading is known, as long as no static period
  has been seen (after one, the ZUPT and ZARU have levelled the sensor and measured the gyro
  bias, and the from-rest behaviour is unchanged, bit for bit): every ``gravity_interval_s``
  the mean specific force is a measurement of the horizontal specific force in ``n``,
  ``(C_nb f)_NE = 0`` (:func:`eskf_models.gravity_rows`), whose noise holds the GNSS-derived
  horizontal acceleration ``a_h`` (from the fixes' velocities at least
  ``gnss_accel_span_s`` apart) and its error, per axis ``a_h^2 + 2 sigma_v^2 / dt^2``, plus the
  accelerometer's white noise; only while ``a_h <= gravity_max_acc_mps2``. The acceleration is
  not removed (its direction in the sensor frame needs the heading), it is in ``R``. Through
  the tilt's correlation with the gyro bias this estimates the roll / pitch part of the bias
  while moving, as an AHRS does; after ``max_gravity_rejections`` rejected updates in a row
  the tilt covariance is re-opened (``gravity_resets`` in the summary). On drive_0708 cut at
  100 s with 3 deg/s of gyro bias per axis, without it the tilt was lost before the mount was
  known (block 5's buffers levelled with a tilt tens of degrees off) and the filter diverged
  to kilometres; with it the mount is found at 28 s within 1 deg and the gyro bias to
  0.05 deg/s.
* The mount yaw is committed only once block 5's own 1-sigma is at most
  ``mount_commit_std_rad`` (:class:`iotnav.techniques.mount3d.Mount3d`); before, the summary's
  ``mount`` says ``unobservable`` (event ``mount_unobservable`` once) and gives no angle.
* The gravity aiding also ends the divergence of car-tunnel seed 137 (90 s, modelled IMU;
  gyro turn-on bias -17.9 / -14.5 deg/s, a start not quiet enough for the static detector):
  9-state ANEES over 45-90 s about 7e4 before, 13.9 now (the same with or without the
  commitment bound; without the aiding the mount is not committed by 45 s at all).

Limitations: flat earth (see :mod:`iotnav.strapdown`); the NHC is applied at the IMU (no
IMU-to-axle lever arm); without a magnetometer the device must move with some acceleration
or turns before the mount yaw, hence the heading, is known.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Iterable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, cast

import numba
import numpy as np
import numpy.typing as npt
from scipy.spatial.transform import Rotation

from iotnav import kalman
from iotnav.engines import eskf_models as M
from iotnav.engines.base import (
    C_DOWN,
    C_EAST,
    C_HEIGHT,
    C_LAT,
    C_LON,
    C_NORTH,
    C_PITCH,
    C_ROLL,
    C_STD_EAST,
    C_STD_NORTH,
    C_T,
    C_VD,
    C_VE,
    C_VN,
    C_YAW,
    SRC_DR,
    SRC_FIX,
    SRC_NONE,
    CountSlot,
    FlagSlot,
    GnssSample,
    ImuSample,
    InputGuard,
    MagSample,
    OneSampleBlock,
    Output,
    OutputBlock,
    Sample,
    StateSlot,
    TangentPlane,
)
from iotnav.engines.config import config_from_toml, dataclass_from_dict
from iotnav.engines.gnss_resolution import AccuracyScaling, PositionResolution
from iotnav.engines.smoother import (
    CORR_ATT,
    CORR_POS,
    CORR_STD,
    CORR_VEL,
    SmoothingLog,
    drain_records,
    plane_to_geodetic,
    record_size,
    write_record,
)
from iotnav.eval.consistency import InnovationLog
from iotnav.geo import dcm_to_rpy, euler_to_dcm, normal_gravity, rot_z
from iotnav.gnss_accuracy import position_sigmas
from iotnav.techniques.mount import MountConfig, accumulate_levelled
from iotnav.techniques.mount3d import Mount3d, mount_from_tilt
from iotnav.techniques.static import StaticConfig, StaticDetector, static_step
from iotnav.wmm import log_year, reference_field

FloatArray = npt.NDArray[np.float64]

G0 = 9.80665
DEG = math.pi / 180.0
_GM_PEAK = 0.6186  # peak Allan deviation of a unit first-order Gauss-Markov process


@dataclass(frozen=True)
class EskfConfig:
    """Every tunable of the ``eskf`` engine (units in the names; datasheet defaults: MPU-6050).

    Attributes
    ----------
    acc_noise_density_ug_rthz, gyro_noise_density_mdps_rthz : float
        White-noise densities (velocity / angle random walk).
    acc_turn_on_bias_mg, gyro_turn_on_bias_dps : float
        1-sigma turn-on biases (initial bias covariance).
    acc_bias_instability_mg, gyro_bias_instability_dph : float
        Allan-deviation floors; Gauss-Markov sigma = value / 0.6186.
    bias_correlation_time_s : float
        Gauss-Markov correlation time of both biases.
    estimate_scale_factors : bool
        Add gyro and accelerometer scale-factor states (30 states instead of 24).
    acc_scale_factor_pct, gyro_scale_factor_pct : float
        1-sigma scale-factor errors (initial covariance).
    scale_factor_rw_ppm_rts : float
        Random walk of the scale factors, ppm/sqrt(s).
    gyro_misalignment_pct : float
        1-sigma gyro cross-axis coupling, each off-diagonal element (not estimated; enters as
        rate-dependent attitude noise ``k_w (|omega_b|^2 - omega_b,i^2)`` per sensor axis,
        ``k_w = 2 m_g^2 tau_x``, see :mod:`iotnav.engines.eskf_models`). Default: the
        MPU-6050's +/-2 % cross-axis sensitivity read as 3-sigma, like the turn-on biases;
        0 leaves the coupling out of ``Q``.
    acc_misalignment_pct : float
        1-sigma accelerometer cross-axis coupling, each off-diagonal element (not estimated):
        its gravity part widens the turn-on bias at levelling, its kinematic part drives the
        accelerometer bias noise ``k_a (|a_b|^2 - a_b,i^2)``, ``k_a = 2 m_a^2 / tau_x`` (see
        :mod:`iotnav.engines.eskf_models`). Default: MPU-6050, +/-2 % as 3-sigma; 0 leaves
        the coupling out (the 9-state ANEES on the full MPU-6050 preset is then ~18 instead of
        ~9, band 7.2-11.0).
    cross_axis_corr_time_s : float
        Correlation time ``tau_x`` of the motion that the cross-axis errors scale (angular
        rate and kinematic acceleration: the duration of a manoeuvre, a start, a brake, a
        turn), s. Also used for the gyro scale factor when it is not estimated. The
        MPU-6050 car runs are insensitive to it (ANEES within the band from 2 to 10 s).
    gnss_lever_arm_b_m : tuple of float
        Antenna position relative to the IMU in ``b``, m.
    uere_m : float
        User equivalent range error used with the DOPs when the receiver gives no accuracy, m.
    default_hdop : float
        HDOP assumed when none is reported.
    gnss_white_fraction : float
        Fraction of the position sigma treated as white; the rest is the time-correlated
        error states. A smoothing receiver's output has little white content, the simulator's
        none: 0 (see the consistency paragraph of the module docstring); raise it for a
        receiver whose fixes jitter from epoch to epoch.
    gnss_white_floor_m : float
        Floor of the white part's 1-sigma, m.
    gnss_white_from_resolution : bool
        Add the rounding of the fixes' output format to the white part, found from the fixes
        (:class:`~iotnav.engines.gnss_resolution.PositionResolution`: 4-decimal NMEA minutes
        are 0.185 m steps, 5.3 cm of white noise; 3 decimals 0.53 m), reported in
        ``summary()["gnss_resolution"]``.
    gnss_error_scales_with_accuracy : bool
        Scale the GNSS error states with the reported accuracy (module docstring, "Reported
        accuracy").
    gnss_corr_time_s : float
        Correlation time of the horizontal Gauss-Markov GNSS position error before the
        receiver's smoothing, s. Default: the horizontal value of the simulator's ``open-sky``
        receiver model (:data:`iotnav.sim.gnss_model.ENVIRONMENTS`, 120-300 s across
        environments).
    gnss_corr_time_v_s : float
        The same for the vertical error, s (the vertical error of a receiver wanders more
        slowly; the simulator's ``open-sky`` value, 180-300 s across environments). It sets
        the vertical velocity error the receiver's smoothing adds, ``sigma_v^2 / (t_f T_e)``:
        with the horizontal 150 s instead of the simulator's 200 s it was a third too large,
        the vertical GNSS velocity and position were under-weighted (whitened innovation
        variance 0.82, lag-1 autocorrelation of the velocity innovation +0.04, 398 runs).
    gnss_speed_noise_mps : float
        1-sigma of each GNSS velocity component when ``s_acc_mps`` is absent, m/s.
    gnss_receiver_filter_s : float
        Time constant ``t_f`` of the receiver's own position smoothing (u-blox-class receivers
        low-pass their navigation solution; the simulator's ``receiver_filter_s``, 2 s), s:
        the reported position error is the Gauss-Markov error through that first-order
        low-pass, and the velocity error its derivative ``(e_gm - e) / t_f`` on top of the
        Doppler noise that ``s_acc_mps`` reports (see :mod:`iotnav.engines.eskf_models`);
        0: no smoothing, first-order Gauss-Markov position error, Doppler noise only.
    use_gnss_velocity : bool
        Apply GNSS velocity updates.
    gnss_min_course_speed_mps : float
        Speed+course velocity is used only above this speed (course too noisy below), m/s.
    nhc : bool
        Apply the non-holonomic constraint (wheeled vehicles).
    nhc_interval_s, nhc_lateral_noise_mps, nhc_vertical_noise_mps : float
        NHC update period (s) and 1-sigma of the vehicle's lateral / vertical velocity (m/s).
    nhc_min_speed_mps : float
        NHC only above this dead-reckoned speed, m/s.
    zupt_interval_s, zupt_noise_mps : float
        Zero-velocity update period while static (s) and its 1-sigma (m/s).
    zaru_floor_dps : float
        Floor of the zero-angular-rate update sigma (quantisation, vibration, cross-axis
        errors that a white model does not cover), deg/s.
    zaru_interval_s : float
        Averaging period of the zero-angular-rate update, s.
    zupt_max_acc_mps2 : float
        Extra condition for the static updates: the low-passed, bias-compensated horizontal
        specific force stays below this (block 3 reacts late to a gentle start), m/s^2.
    zupt_max_gnss_speed_mps : float
        No static update while the latest GNSS speed (under 1.5 s old) exceeds this, m/s.
    mount_rpy_rad : tuple of float or None
        Known mounting rotation ``C_vb`` (roll, pitch, yaw of ``b`` in ``v``), rad; None: find it.
    estimate_mount : bool
        Carry the mount as states (refined by the NHC).
    mount_std_rad : float
        Initial 1-sigma of a configured mount, rad.
    mount_aligner_std_rad : float
        1-sigma of block 5's coarse mount yaw, rad.
    mount_rw_rad_rts : float
        Random walk of the mount, rad/sqrt(s).
    vehicle_level_std_rad : float
        1-sigma of the vehicle's roll and pitch when the mount is initialised from the sensor
        tilt (road crossfall and grade up to about 5 %), rad.
    align_min_speed_mps : float
        Heading (and mount yaw with a magnetometer) from the GNSS course above this speed, m/s.
    level_time_s : float
        Levelling window at start, s.
    initial_tilt_std_rad : float
        1-sigma of the levelled roll and pitch, rad.
    cov_interval_s : float
        Covariance propagation period, s.
    gate_probability : float
        Chi-square probability of the NIS gate (every measurement).
    max_gnss_rejections : int
        Consecutive rejected fixes after which the position covariance is re-opened.
    fix_hold_s : float
        Output ``source`` is ``fix`` up to this long after an accepted fix, s.
    gravity_mps2 : float
        Gravity magnitude; 0 uses WGS84 normal gravity at the NED origin.
    mag_hard_iron_ut : tuple of float
        Hard-iron offset, uT (``m_cal = inv(W) (m_raw - h)``).
    mag_soft_iron : tuple of float
        Soft-iron matrix ``W`` row by row (9 values).
    mag_declination_rad : float or None
        Magnetic declination (East positive), rad. None (default): the World Magnetic Model's
        at the first good fix and the log's date (:mod:`iotnav.wmm`; the value used is in
        ``summary()["mag_reference"]``); magnetometer samples before that fix are skipped
        (counted as ``mag_before_declination``).
    mag_interval_s, mag_heading_noise_rad : float
        Magnetometer heading update period (s) and 1-sigma (rad).
    use_mag : bool
        Use the magnetometer when samples arrive (and it is calibrated).
    mag_calibrated : bool
        The magnetometer's output is calibrated already (e.g. Android's calibrated field).
        Otherwise it is used only with a configured calibration (``mag_hard_iron_ut`` or
        ``mag_soft_iron`` not the defaults): an uncalibrated magnetometer's heading is off by
        up to tens of degrees (car-magnetometer, raw HMC5883L: the first GNSS epochs after the
        start were then rejected one after the other, the gate re-opened every 6 s); its
        samples are counted in ``summary()["mag_unused"]`` and the heading comes from the
        GNSS course.
    static_prefilter_tau_s : float
        Time constant of a first-order low-pass on ``C_nb f_b`` before block 3 (averages
        engine vibration out before the detector takes the norm), s; 0 disables.
    smoothing : bool
        Keep a :class:`~iotnav.engines.smoother.SmoothingLog` for the RTS smoother (``iotnav run
        --smooth`` turns it on; module docstring, "RTS smoothing"). Off by default; the
        forward output is the same either way.
    record_every : int
        Covariance propagations (``cov_interval_s`` each) between smoothing records when there
        is no measurement; every update epoch is a record too. A record holds ``P`` twice and
        ``Phi``: ``8 (1 + 2 n + 3 n^2)`` bytes, 21.8 KB with the 30 states (13.8 KB with 24).
    smoothing_drift_gap_s : float
        How the smoother reads a gate reset's forced fix, s. Within twice this time after a
        GNSS gap (no valid fix) longer than this, the filter has likely drifted and the fix is
        right: it is recorded against the un-widened prior, so it corrects the gap
        (car-tunnel, 12-60 s tunnels: mean RMS over seeds 0-10 3.00 -> 2.22 m). After a
        shorter gap the disagreement more likely comes from the re-acquiring receiver's
        first fixes: the reset is recorded as a re-initialisation of the position, carrying
        nothing back (car-magnetometer, 4 s gap: recorded un-widened, the smoothed RMS of
        the four seeds with a reset was 0.1-0.9 m worse than this way).
    gravity_aiding : bool
        Before the heading is known, aid the tilt (and through it the roll / pitch gyro bias)
        with gravity while the GNSS-derived horizontal acceleration is small, as an AHRS
        does (module docstring, "Initialisation"). Without it a start in motion with a few
        deg/s of gyro bias loses the tilt before the mount, hence the heading, is known.
    gravity_interval_s : float
        Averaging period of the gravity update, s: one update per second, about the
        correlation time of the vehicle acceleration lumped into its noise (a car's speed
        changes over seconds), so successive updates are not counted as independent
        information about the same acceleration.
    gravity_max_acc_mps2 : float
        Gravity aiding only while the GNSS-derived horizontal acceleration is at most this,
        m/s^2 (12 deg of tilt; that acceleration is in the update's noise, so a larger one
        only weakens it). VQF and Madgwick-type AHRS likewise rest the accelerometer
        correction on a small deviation of ``|f|`` from ``g``. With 0.5 m/s^2 the start of
        drive_0708 cut at 100 s (a car pulling away) had no update for 16 s and a 3 deg/s
        gyro bias took the tilt 48 deg off before the first.
    max_gravity_rejections : int
        Consecutive rejected gravity updates after which the tilt covariance is re-opened to
        ``gravity_reopen_std_rad`` (decorrelated) and the next update is taken (event
        ``gravity_reset`` counted in the summary): the tilt is then further off than the
        configured gyro turn-on bias allows, and gating every update out would lose it for
        good, as the GNSS gate reset does for fixes.
    gravity_reopen_std_rad : float
        1-sigma of the re-opened roll and pitch, rad (30 deg: a linear update then takes most
        of a tilt error of that size, the following ones the rest).
    gnss_accel_span_s : float
        Shortest time between the two fixes whose velocity difference gives the GNSS-derived
        acceleration, s (a 10 Hz receiver's 0.1 s difference is ten times noisier than a 1 s
        one: 1.4 m/s^2 1-sigma for 0.1 m/s velocity noise).
    moving_tilt_std_rad : float
        1-sigma of the levelled roll and pitch when the levelling window was not quiet
        (levelled in motion, where the window's mean acceleration is unknown): 0.1 rad is the
        tilt of 1 m/s^2, a brisk car acceleration (Bokare and Maurya 2017, "Acceleration-
        deceleration behaviour of various vehicle types", Transp. Res. Procedia 25: cars
        0.6-1.5 m/s^2 typical).
    mount_commit_std_rad : float
        Block 5's mount yaw is committed (and the heading set from the course) only once its
        own 1-sigma is at most this, rad (0.1 rad, the ``mount_aligner_std_rad`` the filter
        assumes for it). Until then the mount is reported ``unobservable`` and the output is
        the last fix moved on at its velocity. With no bound (before), a first buffer with a
        high coherence but a 180-degree sigma was accepted on a start in motion with a lost
        tilt (drive_0708 from 100 s, 3 deg/s gyro bias: mount 126 deg off, km of error).
    static : StaticConfig
        Block 3 static detector.
    mount : MountConfig
        Block 5 coarse mount aligner.
    """

    acc_noise_density_ug_rthz: float = 400.0
    gyro_noise_density_mdps_rthz: float = 5.0
    acc_turn_on_bias_mg: float = 50.0 / 3.0
    gyro_turn_on_bias_dps: float = 20.0 / 3.0
    acc_bias_instability_mg: float = 0.2
    gyro_bias_instability_dph: float = 30.0
    bias_correlation_time_s: float = 100.0
    estimate_scale_factors: bool = True
    acc_scale_factor_pct: float = 1.0
    gyro_scale_factor_pct: float = 1.0
    scale_factor_rw_ppm_rts: float = 1.0
    gyro_misalignment_pct: float = 2.0 / 3.0
    acc_misalignment_pct: float = 2.0 / 3.0
    cross_axis_corr_time_s: float = 5.0
    gnss_lever_arm_b_m: tuple[float, float, float] = (0.0, 0.0, 0.0)
    uere_m: float = 2.0
    default_hdop: float = 1.5
    gnss_white_fraction: float = 0.0
    gnss_white_floor_m: float = 0.005
    gnss_white_from_resolution: bool = True
    gnss_error_scales_with_accuracy: bool = True
    gnss_corr_time_s: float = 150.0
    gnss_corr_time_v_s: float = 200.0
    gnss_speed_noise_mps: float = 0.12
    gnss_receiver_filter_s: float = 2.0
    use_gnss_velocity: bool = True
    gnss_min_course_speed_mps: float = 1.0
    nhc: bool = True
    nhc_interval_s: float = 0.1
    nhc_lateral_noise_mps: float = 0.1
    nhc_vertical_noise_mps: float = 0.1
    nhc_min_speed_mps: float = 1.0
    zupt_interval_s: float = 0.1
    zupt_noise_mps: float = 0.02
    zaru_floor_dps: float = 0.1
    zaru_interval_s: float = 1.0
    zupt_max_acc_mps2: float = 0.08
    zupt_max_gnss_speed_mps: float = 0.3
    mount_rpy_rad: tuple[float, float, float] | None = None
    estimate_mount: bool = True
    mount_std_rad: float = 0.02
    mount_aligner_std_rad: float = 0.1
    mount_rw_rad_rts: float = 1e-5
    vehicle_level_std_rad: float = 0.05
    align_min_speed_mps: float = 3.0
    level_time_s: float = 1.0
    initial_tilt_std_rad: float = 0.02
    cov_interval_s: float = 0.05
    gate_probability: float = 0.9999
    max_gnss_rejections: int = 5
    fix_hold_s: float = 1.5
    gravity_mps2: float = 0.0
    mag_hard_iron_ut: tuple[float, float, float] = (0.0, 0.0, 0.0)
    mag_soft_iron: tuple[float, ...] = (1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0)
    mag_declination_rad: float | None = None
    mag_interval_s: float = 1.0
    mag_heading_noise_rad: float = 0.035
    use_mag: bool = True
    mag_calibrated: bool = False
    static_prefilter_tau_s: float = 0.25
    smoothing: bool = False
    record_every: int = 10
    smoothing_drift_gap_s: float = 10.0
    gravity_aiding: bool = True
    gravity_interval_s: float = 1.0
    gravity_max_acc_mps2: float = 2.0
    max_gravity_rejections: int = 3
    gravity_reopen_std_rad: float = 0.5
    gnss_accel_span_s: float = 1.0
    moving_tilt_std_rad: float = 0.1
    mount_commit_std_rad: float = 0.1
    static: StaticConfig = field(default_factory=StaticConfig)
    mount: MountConfig = field(default_factory=MountConfig)

    # ------------------------------------------------------------------ I/O
    def to_dict(self) -> dict[str, Any]:
        """Plain dict (for ``summary.json``)."""
        return dataclasses.asdict(self)

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> EskfConfig:
        """Build from a dict (keys: field names; ``static`` and ``mount`` as sub-tables).

        Raises
        ------
        ValueError
            For unknown keys.
        """
        return cast(EskfConfig, dataclass_from_dict(cls(), data, "eskf"))

    @classmethod
    def from_toml(cls, path: str | Path) -> EskfConfig:
        """Load ``[eskf]`` (optionally ``[eskf.static]``, ``[eskf.mount]``) from a TOML file."""
        return cast(EskfConfig, config_from_toml(path, cls(), "eskf"))

    @classmethod
    def from_imu_spec(cls, spec: Any, **changes: Any) -> EskfConfig:
        """Noise model from a datasheet record with the :class:`iotnav.sim.presets.ImuSpec` fields."""
        names = (
            "acc_noise_density_ug_rthz",
            "gyro_noise_density_mdps_rthz",
            "acc_turn_on_bias_mg",
            "gyro_turn_on_bias_dps",
            "acc_bias_instability_mg",
            "gyro_bias_instability_dph",
            "bias_correlation_time_s",
            "acc_scale_factor_pct",
            "gyro_scale_factor_pct",
            "gyro_misalignment_pct",
            "acc_misalignment_pct",
        )
        kw: dict[str, Any] = {k: float(getattr(spec, k)) for k in names}
        kw.update(changes)
        return cls(**kw)

    def replace(self, **changes: Any) -> EskfConfig:
        """Copy with some fields replaced."""
        return dataclasses.replace(self, **changes)


def noise_vector(c: EskfConfig) -> FloatArray:
    """SI process-noise parameters in the order of :func:`eskf_models.error_transition`.

    Raises
    ------
    ValueError
        For a non-positive ``cross_axis_corr_time_s``.
    """
    nd_a = c.acc_noise_density_ug_rthz * 1e-6 * G0
    nd_g = c.gyro_noise_density_mdps_rthz * 1e-3 * DEG
    s_ba = c.acc_bias_instability_mg * 1e-3 * G0 / _GM_PEAK
    s_bg = c.gyro_bias_instability_dph * DEG / 3600.0 / _GM_PEAK
    tc = c.bias_correlation_time_s
    # cross-axis (and unestimated scale-factor) errors: white noise of the intensity of a
    # process correlated over a manoeuvre, 2 sigma^2 tau, or bias noise 2 sigma^2 / tau
    tau = c.cross_axis_corr_time_s
    if not tau > 0.0:
        raise ValueError(f"eskf.cross_axis_corr_time_s must be > 0 s, got {tau}")
    k_w = 2.0 * (c.gyro_misalignment_pct * 1e-2) ** 2 * tau
    k_a = 2.0 * (c.acc_misalignment_pct * 1e-2) ** 2 / tau
    k_s = 0.0 if c.estimate_scale_factors else 2.0 * (c.gyro_scale_factor_pct * 1e-2) ** 2 * tau
    return np.array(
        [
            nd_a**2,
            nd_g**2,
            2.0 * s_ba**2 / tc,
            2.0 * s_bg**2 / tc,
            # no decay of the bias *errors*: the true bias is the turn-on constant plus the
            # Gauss-Markov in-run part, and the nominal bias is held between updates, so the
            # error ``b - b_hat`` does not decay; it wanders with the in-run driving noise.
            0.0,
            0.0,
            c.mount_rw_rad_rts**2,
            (c.scale_factor_rw_ppm_rts * 1e-6) ** 2,
            0.0,  # GNSS error driving intensities: set from the fix accuracy
            0.0,
            1.0 / c.gnss_corr_time_s,
            k_w,
            k_a,
            k_s,
            1.0 / c.gnss_receiver_filter_s if c.gnss_receiver_filter_s > 0.0 else 0.0,
            1.0 / c.gnss_corr_time_v_s,
        ]
    )


# ----------------------------------------------------------------------------- compiled IMU path
# Hot engine state, one float64 array ``EskfEngine.st`` (flags as 0/1, times in s); the
# engine's attributes of the same names read and write it (descriptors :class:`~iotnav.engines.base.StateSlot` and kin).
(
    E_HAVE_IMU,
    E_T_STATE,
    E_LEVELLED,
    E_LEVEL_N,
    E_LEVEL_T0,
    E_HEADING_OK,
    E_POS_OK,
    E_MOUNT_OK,
    E_STATIC,
    E_STATIC_SEEN,
    E_T_SPEED,
    E_LAST_SPEED,
    E_T_PREFILT,
    E_T_NHC,
    E_T_ZUPT,
    E_ZARU_N,
    E_T_ZARU,
    E_T_FIX,
    E_N_IMU,
    E_HAS_FRAME,
    E_LAT0,
    E_LON0,
    E_H0,
    E_KN,
    E_KE,
    E_HAS_FIX,
    E_FIX_T,
    E_NREC,
) = range(28)
#: Vectors in ``st``: last fix position (m, NED) and velocity (m/s), pending raw IMU sample,
#: low-passed ``C_nb f_b``, ZARU gyro sum, levelling sums (sum f, sum w, sum |f|^2).
E_FIX_Z, E_FIX_V, E_F_PEND, E_W_PEND, E_F_N_LP, E_ZARU_SUM, E_LEVEL_SUM = 28, 31, 34, 37, 40, 43, 46
#: RTS smoothing (module docstring): recording on, a record open (its prior saved, its updates
#: being summed), its time (s), covariance propagations since the last record, records in the buffer.
E_SM_ON, E_SM_PEND, E_SM_T, E_SM_COUNT, E_SM_N = 53, 54, 55, 56, 57
#: Gravity aiding before the heading (module docstring, "Initialisation"): raw accelerometer
#: sum over the aiding interval (3), its count, the interval's start (s); the GNSS-derived
#: horizontal acceleration (m/s^2), its 1-sigma (m/s^2) and time (s).
E_GRAV_SUM, E_GRAV_N, E_T_GRAV, E_A_GNSS, E_SA_GNSS, E_T_A_GNSS = 58, 61, 62, 63, 64, 65
#: consecutive rejected gravity updates; gravity re-openings (tilt covariance widened)
E_GRAV_REJ, E_GRAV_RESETS = 66, 67
E_SIZE = 68

# Parameters, one float64 array ``EskfEngine.prm`` (see ``_params``).
(
    Q_COV_INTERVAL,
    Q_PREFILT_TAU,
    Q_ZUPT_MAX_ACC,
    Q_ZUPT_MAX_GNSS_SPEED,
    Q_ZUPT_INTERVAL,
    Q_ZUPT_NOISE,
    Q_ZARU_INTERVAL,
    Q_ND_G,
    Q_ZARU_FLOOR,
    Q_NHC,
    Q_NHC_INTERVAL,
    Q_NHC_MIN_SPEED,
    Q_NHC_LAT,
    Q_NHC_VERT,
    Q_LEVEL_TIME,
    Q_FIX_HOLD,
    Q_FIX_STD,
    Q_EST_MOUNT,
    Q_GATE1,
    Q_GATE2,
    Q_GATE3,
    Q_RECORD_EVERY,
    Q_GRAV,
    Q_GRAV_INTERVAL,
    Q_GRAV_MAX_ACC,
    Q_ND_A,
    Q_GRAV_MAX_REJ,
    Q_GRAV_REOPEN_STD,
) = range(28)

#: Records written by the compiled code into ``EskfEngine.rec`` (one row each), turned into
#: ``events`` / ``nis_log`` entries in order by ``EskfEngine._flush``: ``kind`` (``REC_*``),
#: ``t`` (s), measurement code (index into :data:`MEAS_NAMES`), NIS, dof, accepted, test ratio.
REC_STATIC_END, REC_STATIC_START, REC_UPDATE = 0, 1, 2
R_KIND, R_T, R_MEAS, R_NIS, R_DOF, R_ACC, R_RATIO = range(7)
REC_ROWS = 256
MEAS_NAMES = ("zupt", "zaru", "nhc", "gnss_position", "gnss_velocity", "mag_heading", "gravity")
MEAS_CODES = {name: k for k, name in enumerate(MEAS_NAMES)}
#: Kernel return codes: block done; levelling window complete at the returned sample (Python
#: finishes the levelling, then the kernel resumes that sample); record buffer full.
K_DONE, K_LEVEL, K_FLUSH = 0, 1, 2
#: Rows of the smoothing record buffer (:func:`iotnav.engines.smoother.write_record` layout,
#: 22 KB each with 30 states); the kernel returns ``K_FLUSH`` before it could overflow.
SM_ROWS = 64


@numba.njit(cache=True)
def _freeze_yaw_nb(P: FloatArray) -> None:
    """Before the heading is known its error is left out of the filter (zero row/column).

    A 180-degree yaw sigma would be linearised through the small horizontal specific
    force and make yaw, then tilt and accelerometer bias, spuriously observable from
    zero-velocity updates at rest.
    """
    k = M.ATT_0 + 2
    P[k, :] = 0.0
    P[:, k] = 0.0


@numba.njit(cache=True)
def _sm_open(st: FloatArray, nom: Any, P: FloatArray, sm: Any) -> None:
    """Open a smoothing record at ``t_state``: save the prior ``x- = 0``, ``P-``; zero the update sum.

    Also writes the record's output-attitude map (row ``E_SM_N`` of the attitude buffer):
    ``C_nb C_vb^T`` once the mount is known (the output is then the vehicle attitude), else zero.
    """
    buf, _Phi, _work, _rec, att = sm
    C_nb, C_vb = nom[0], nom[7]
    n = P.shape[0]
    prior = buf[0]
    post = buf[1]
    for i in range(n):
        prior[i] = 0.0
        post[i] = 0.0
        for j in range(n):
            prior[n + n * i + j] = P[i, j]
    r = int(st[E_SM_N])
    mount = st[E_MOUNT_OK] != 0.0
    for i in range(3):
        for j in range(3):
            v = 0.0
            if mount:
                for k in range(3):
                    v += C_nb[i, k] * C_vb[j, k]
            att[r, 3 * i + j] = v
    st[E_SM_PEND] = 1.0
    st[E_SM_T] = st[E_T_STATE]


@numba.njit(cache=True)
def _sm_close(st: FloatArray, P: FloatArray, sm: Any) -> None:
    """Write the open record (posterior: summed ``dx`` and ``P`` now) and restart ``Phi`` at ``I``."""
    buf, Phi, _work, rec, _att = sm
    n = P.shape[0]
    post = buf[1]
    for i in range(n):
        for j in range(n):
            post[n + n * i + j] = P[i, j]
    r = int(st[E_SM_N])
    write_record(rec, r, st[E_SM_T], buf[0], post, Phi, n)
    st[E_SM_N] = r + 1
    st[E_SM_PEND] = 0.0
    st[E_SM_COUNT] = 0.0


@numba.njit(cache=True)
def _propagate_cov_nb(
    P: FloatArray,
    acc: FloatArray,
    noise: FloatArray,
    nom: Any,
    st: FloatArray,
    prm: FloatArray,
    sm: Any,
) -> None:
    """Covariance over the accumulated interval; GNSS-error decay; yaw freeze; fixed mount.

    When recording for the smoother: the open record is written first (its posterior is ``P``
    before this interval), the interval's transition is multiplied into ``Phi``, and a record
    is opened after ``record_every`` propagations.
    """
    T = acc[M.ACC_T]
    _C_nb, _v_n, _p_n, _b_g, _b_a, _s_g, _s_a, _C_vb, e_n, e_gm = nom
    smoothing = st[E_SM_ON] != 0.0
    if smoothing:
        if T <= 0.0:
            return
        if st[E_SM_PEND] != 0.0:
            _sm_close(st, P, sm)
        n = P.shape[0]
        work = sm[2]
        M.propagate_covariance_phi(P, acc, noise, work[0])
        M.accumulate_transition(work[0], sm[1].reshape((n, n)), work[1])
    elif not M.propagate_covariance(P, acc, noise):
        return
    # the GNSS error is zero-mean: its estimate follows the error model without noise, exactly
    # (e_gm decays with T_e; the smoothed e follows it through the receiver's low-pass t_f)
    inv_tf = noise[14]
    inv_te_v = noise[15] if noise.shape[0] > 15 else noise[10]
    for i in range(3):
        inv_te = noise[10] if i < 2 else inv_te_v  # horizontal, vertical correlation time
        d = math.exp(-T * inv_te)
        if inv_tf > 0.0:
            a = math.exp(-T * inv_tf)
            den = inv_tf - inv_te
            c = inv_tf * (d - a) / den if abs(den) > 1e-12 else T * inv_tf * d
            e_n[i] = a * e_n[i] + c * e_gm[i]
            e_gm[i] *= d
        else:
            e_n[i] *= d
    acc[:] = 0.0
    if st[E_HEADING_OK] == 0.0:
        _freeze_yaw_nb(P)
    if prm[Q_EST_MOUNT] == 0.0:
        P[M.MNT_0 : M.MNT_0 + 3, :] = 0.0
        P[:, M.MNT_0 : M.MNT_0 + 3] = 0.0
        if smoothing:  # the zeroed mount is part of the transition
            n = P.shape[0]
            sm[1][M.MNT_0 * n : (M.MNT_0 + 3) * n] = 0.0
    if smoothing:
        st[E_SM_COUNT] += 1.0
        if st[E_SM_COUNT] >= prm[Q_RECORD_EVERY]:
            _sm_open(st, nom, P, sm)


@numba.njit(cache=True)
def _apply_nb(
    t: float,
    code: int,
    y: FloatArray,
    H: FloatArray,
    R: FloatArray,
    m: int,
    gate: float,
    P: FloatArray,
    nom: Any,
    acc: FloatArray,
    noise: FloatArray,
    st: FloatArray,
    prm: FloatArray,
    rec: FloatArray,
    sm: Any,
) -> bool:
    """Propagate the covariance to now, gate and apply one measurement, record it; True if accepted.

    When recording for the smoother the update belongs to the record open at ``t_state`` (opened
    here if none is), and its ``dx`` is added to that record's posterior.
    """
    C_nb, v_n, p_n, b_g, b_a, s_g, s_a, C_vb, e_n, e_gm = nom
    _propagate_cov_nb(P, acc, noise, nom, st, prm, sm)
    smoothing = st[E_SM_ON] != 0.0
    if smoothing:
        if st[E_SM_PEND] != 0.0 and st[E_SM_T] != st[E_T_STATE]:
            _sm_close(st, P, sm)  # time moved on without a propagation (data gap): identity transition
        if st[E_SM_PEND] == 0.0:
            _sm_open(st, nom, P, sm)
    dx = np.empty(P.shape[0])
    nis, ok, ratio = M.kalman_update(P, dx, y, H, R, m, gate)
    j = int(st[E_NREC])
    rec[j, R_KIND] = REC_UPDATE
    rec[j, R_T] = t
    rec[j, R_MEAS] = code
    rec[j, R_NIS] = nis
    rec[j, R_DOF] = m
    rec[j, R_ACC] = 1.0 if ok else 0.0
    rec[j, R_RATIO] = ratio
    st[E_NREC] = j + 1
    if not ok:
        return False
    M.inject_arrays(dx, C_nb, v_n, p_n, b_g, b_a, s_g, s_a, C_vb, e_n, e_gm)
    if smoothing:
        # several updates at one time: their corrections, each about the nominal the previous
        # one left, summed (to first order the correction about the record's prior nominal)
        post = sm[0][1]
        for i in range(P.shape[0]):
            post[i] += dx[i]
    if st[E_HEADING_OK] == 0.0:
        _freeze_yaw_nb(P)
    return True


@numba.njit(cache=True)
def _integrate_to_nb(
    t: float,
    st: FloatArray,
    prm: FloatArray,
    nom: Any,
    g_n: FloatArray,
    acc: FloatArray,
    P: FloatArray,
    noise: FloatArray,
    fw: FloatArray,
    sm: Any,
) -> None:
    """Integrate the pending IMU sample from ``t_state`` to ``t`` (``fw``: 6-element work array)."""
    if st[E_HAVE_IMU] == 0.0 or not math.isfinite(st[E_T_STATE]):
        return
    dt = t - st[E_T_STATE]
    if dt <= 0.0 or dt > 1.0:
        st[E_T_STATE] = max(st[E_T_STATE], t)
        return
    C_nb, v_n, p_n, b_g, b_a, s_g, s_a, _C_vb, _e_n, _e_gm = nom
    f = fw[0:3]
    w = fw[3:6]
    M.compensate_into(st[E_F_PEND : E_F_PEND + 3], b_a, s_a, f)
    M.compensate_into(st[E_W_PEND : E_W_PEND + 3], b_g, s_g, w)
    M.propagate_nominal(C_nb, v_n, p_n, f, w, dt, g_n, acc)
    st[E_T_STATE] = t
    if acc[M.ACC_T] >= prm[Q_COV_INTERVAL]:
        _propagate_cov_nb(P, acc, noise, nom, st, prm, sm)


@numba.njit(cache=True)
def _static_updates_nb(
    t: float,
    st: FloatArray,
    prm: FloatArray,
    nom: Any,
    P: FloatArray,
    acc: FloatArray,
    noise: FloatArray,
    rec: FloatArray,
    y: FloatArray,
    H: FloatArray,
    R: FloatArray,
    sm: Any,
) -> None:
    """ZUPT, and ZARU with the mean gyro output once ``zaru_interval_s`` of static data is summed."""
    _C_nb, v_n, _p_n, b_g, _b_a, s_g, _s_a, _C_vb, _e_n, _e_gm = nom
    st[E_T_ZUPT] = t
    M.zupt_rows(v_n, y, H)
    R[:, :] = 0.0
    for i in range(3):
        R[i, i] = prm[Q_ZUPT_NOISE] ** 2
    _apply_nb(t, 0, y, H, R, 3, prm[Q_GATE3], P, nom, acc, noise, st, prm, rec, sm)
    T = t - st[E_T_ZARU]
    n = st[E_ZARU_N]
    if n >= 5 and T >= prm[Q_ZARU_INTERVAL]:
        st[E_T_ZARU] = t
        sigma = math.hypot(prm[Q_ND_G] / math.sqrt(T), prm[Q_ZARU_FLOOR])
        w_mean = np.empty(3)
        for i in range(3):
            w_mean[i] = st[E_ZARU_SUM + i] / n
        M.zaru_rows(w_mean, b_g, s_g, y, H)
        R[:, :] = 0.0
        for i in range(3):
            y[i] = -y[i]
            R[i, i] = sigma * sigma
        _apply_nb(t, 1, y, H, R, 3, prm[Q_GATE3], P, nom, acc, noise, st, prm, rec, sm)
        st[E_ZARU_SUM : E_ZARU_SUM + 3] = 0.0
        st[E_ZARU_N] = 0.0


@numba.njit(cache=True)
def _gravity_nb(
    t: float,
    fx: float,
    fy: float,
    fz: float,
    st: FloatArray,
    prm: FloatArray,
    nom: Any,
    P: FloatArray,
    acc: FloatArray,
    noise: FloatArray,
    rec: FloatArray,
    y: FloatArray,
    H: FloatArray,
    R: FloatArray,
    sm: Any,
) -> None:
    """Gravity aiding of the tilt before the heading (module docstring, "Initialisation").

    Sums the raw specific force; every ``gravity_interval_s`` its mean is a horizontal
    specific-force measurement ``(C_nb f)_NE = 0`` (:func:`eskf_models.gravity_rows`) when the
    GNSS-derived horizontal acceleration (at most two intervals old) is at most
    ``gravity_max_acc_mps2``; that acceleration and its own error enter ``R`` per axis, with
    the accelerometer's white noise over the interval.
    """
    st[E_GRAV_SUM] += fx
    st[E_GRAV_SUM + 1] += fy
    st[E_GRAV_SUM + 2] += fz
    st[E_GRAV_N] += 1.0
    T = t - st[E_T_GRAV]
    if T < prm[Q_GRAV_INTERVAL]:
        return
    n = st[E_GRAV_N]
    a_h = st[E_A_GNSS]
    fresh = t - st[E_T_A_GNSS] <= 2.0 * prm[Q_GRAV_INTERVAL]
    if n >= 5.0 and fresh and a_h <= prm[Q_GRAV_MAX_ACC]:
        C_nb, _v_n, _p_n, _b_g, b_a, _s_g, s_a, _C_vb, _e_n, _e_gm = nom
        f_mean = np.empty(3)
        for i in range(3):
            f_mean[i] = st[E_GRAV_SUM + i] / n
        M.gravity_rows(C_nb, f_mean, b_a, s_a, y, H)
        y[0] = -y[0]
        y[1] = -y[1]
        var = prm[Q_ND_A] ** 2 / T + a_h * a_h + st[E_SA_GNSS] ** 2
        R[:, :] = 0.0
        R[0, 0] = var
        R[1, 1] = var
        gate = prm[Q_GATE2]
        if st[E_GRAV_REJ] >= prm[Q_GRAV_MAX_REJ]:
            # the tilt is further off than its covariance says (a gyro bias beyond the
            # configured turn-on bias): re-open the tilt, decorrelated, and take this update
            for i in range(2):
                P[M.ATT_0 + i, :] = 0.0
                P[:, M.ATT_0 + i] = 0.0
                P[M.ATT_0 + i, M.ATT_0 + i] = prm[Q_GRAV_REOPEN_STD] ** 2
            gate = -1.0
            st[E_GRAV_RESETS] += 1.0
        if _apply_nb(t, 6, y, H, R, 2, gate, P, nom, acc, noise, st, prm, rec, sm):
            st[E_GRAV_REJ] = 0.0
        else:
            st[E_GRAV_REJ] += 1.0
    st[E_GRAV_SUM : E_GRAV_SUM + 3] = 0.0
    st[E_GRAV_N] = 0.0
    st[E_T_GRAV] = t


@numba.njit(cache=True)
def _output_row_nb(
    k: int,
    t: float,
    of: FloatArray,
    ostat: npt.NDArray[np.bool_],
    osrc: npt.NDArray[np.int8],
    st: FloatArray,
    prm: FloatArray,
    nom: Any,
    P: FloatArray,
) -> None:
    """Row ``k``: attitude of ``C_nb C_vb^T`` (of ``C_nb`` before the mount is known), NED and geodetic position."""
    C_nb, v_n, p_n, _b_g, _b_a, _s_g, _s_a, C_vb, _e_n, _e_gm = nom
    nan = math.nan
    roll = pitch = yaw = nan
    if st[E_LEVELLED] != 0.0:
        if st[E_MOUNT_OK] != 0.0:
            c20 = C_nb[2, 0] * C_vb[0, 0] + C_nb[2, 1] * C_vb[0, 1] + C_nb[2, 2] * C_vb[0, 2]
            c21 = C_nb[2, 0] * C_vb[1, 0] + C_nb[2, 1] * C_vb[1, 1] + C_nb[2, 2] * C_vb[1, 2]
            c22 = C_nb[2, 0] * C_vb[2, 0] + C_nb[2, 1] * C_vb[2, 1] + C_nb[2, 2] * C_vb[2, 2]
            c10 = C_nb[1, 0] * C_vb[0, 0] + C_nb[1, 1] * C_vb[0, 1] + C_nb[1, 2] * C_vb[0, 2]
            c00 = C_nb[0, 0] * C_vb[0, 0] + C_nb[0, 1] * C_vb[0, 1] + C_nb[0, 2] * C_vb[0, 2]
        else:
            c20, c21, c22, c10, c00 = C_nb[2, 0], C_nb[2, 1], C_nb[2, 2], C_nb[1, 0], C_nb[0, 0]
        # as iotnav.geo.dcm_to_rpy
        roll = math.atan2(c21, c22)
        pitch = math.asin(max(-1.0, min(1.0, -c20)))
        yaw = math.atan2(c10, c00) if st[E_HEADING_OK] != 0.0 else nan
    of[C_T, k] = t
    of[C_ROLL, k] = roll
    of[C_PITCH, k] = pitch
    of[C_YAW, k] = yaw
    ostat[k] = st[E_STATIC] != 0.0
    if st[E_HAS_FRAME] == 0.0:
        for c in (C_LAT, C_LON, C_HEIGHT, C_NORTH, C_EAST, C_DOWN, C_VN, C_VE, C_VD, C_STD_NORTH, C_STD_EAST):
            of[c, k] = nan
        osrc[k] = SRC_NONE
        return
    if st[E_HEADING_OK] != 0.0 and st[E_POS_OK] != 0.0:
        r0, r1, r2 = p_n[0], p_n[1], p_n[2]
        of[C_VN, k] = v_n[0]
        of[C_VE, k] = v_n[1]
        of[C_VD, k] = v_n[2]
        of[C_STD_NORTH, k] = math.sqrt(P[0, 0])
        of[C_STD_EAST, k] = math.sqrt(P[1, 1])
        osrc[k] = SRC_FIX if t - st[E_T_FIX] <= prm[Q_FIX_HOLD] else SRC_DR
    else:
        # before the heading: the last fix extrapolated with the GNSS velocity
        dt = t - st[E_FIX_T]
        r0 = st[E_FIX_Z] + st[E_FIX_V] * dt
        r1 = st[E_FIX_Z + 1] + st[E_FIX_V + 1] * dt
        r2 = st[E_FIX_Z + 2] + st[E_FIX_V + 2] * dt
        of[C_VN, k] = st[E_FIX_V]
        of[C_VE, k] = st[E_FIX_V + 1]
        of[C_VD, k] = st[E_FIX_V + 2]
        of[C_STD_NORTH, k] = prm[Q_FIX_STD]
        of[C_STD_EAST, k] = prm[Q_FIX_STD]
        osrc[k] = SRC_FIX
    of[C_NORTH, k] = r0
    of[C_EAST, k] = r1
    of[C_DOWN, k] = r2
    # TangentPlane.from_ned
    of[C_LAT, k] = st[E_LAT0] + r0 / st[E_KN]
    of[C_LON, k] = st[E_LON0] + r1 / st[E_KE]
    of[C_HEIGHT, k] = st[E_H0] - r2


@numba.njit(cache=True)
def _imu_kernel(
    t: FloatArray,
    acc_b: Any,
    gyro_b: Any,
    of: FloatArray,
    ostat: npt.NDArray[np.bool_],
    osrc: npt.NDArray[np.int8],
    i0: int,
    i1: int,
    resume: bool,
    st: FloatArray,
    prm: FloatArray,
    nom: Any,
    P: FloatArray,
    acc: FloatArray,
    noise: FloatArray,
    g_n: FloatArray,
    sd_state: FloatArray,
    sd_speeds: FloatArray,
    sd_params: FloatArray,
    imu_sums: FloatArray,
    rec: FloatArray,
    sm: Any,
) -> tuple[int, int]:
    """The ``eskf`` IMU step over samples ``i0 .. i1-1`` (see :meth:`EskfEngine.imu_block`).

    Returns the sample index and a ``K_*`` code: ``K_DONE`` (``i1``), ``K_LEVEL`` (levelling
    window complete at that sample: Python finishes it, then calls again with ``resume`` to
    run the rest of that sample), ``K_FLUSH`` (record buffer, or smoothing record buffer, full
    before that sample). ``sm``: the smoothing arrays (:attr:`EskfEngine.sm`), untouched
    unless recording.
    """
    C_nb, v_n, _p_n, b_g, b_a, s_g, s_a, C_vb, _e_n, _e_gm = nom
    ax, ay, az = acc_b
    gx, gy, gz = gyro_b
    n = P.shape[0]
    fw = np.empty(6)
    fc = np.empty(3)
    y = np.zeros(3)
    H = np.zeros((3, n))
    R = np.zeros((3, 3))
    for k in range(i0, i1):
        tk = t[k]
        if not (resume and k == i0):
            if st[E_NREC] > rec.shape[0] - 4 or (st[E_SM_ON] != 0.0 and st[E_SM_N] > sm[3].shape[0] - 4):
                return k, K_FLUSH
            st[E_N_IMU] += 1.0
            if st[E_HAVE_IMU] == 0.0:
                st[E_T_STATE] = tk
                st[E_HAVE_IMU] = 1.0
                st[E_LEVEL_T0] = tk
            else:
                _integrate_to_nb(tk, st, prm, nom, g_n, acc, P, noise, fw, sm)
            st[E_F_PEND] = ax[k]
            st[E_F_PEND + 1] = ay[k]
            st[E_F_PEND + 2] = az[k]
            st[E_W_PEND] = gx[k]
            st[E_W_PEND + 1] = gy[k]
            st[E_W_PEND + 2] = gz[k]
            if st[E_LEVELLED] == 0.0:
                ls = E_LEVEL_SUM
                st[ls] += ax[k]
                st[ls + 1] += ay[k]
                st[ls + 2] += az[k]
                st[ls + 3] += gx[k]
                st[ls + 4] += gy[k]
                st[ls + 5] += gz[k]
                st[ls + 6] += ax[k] * ax[k] + ay[k] * ay[k] + az[k] * az[k]
                st[E_LEVEL_N] += 1.0
                if not (tk - st[E_LEVEL_T0] < prm[Q_LEVEL_TIME] or st[E_LEVEL_N] < 2.0):
                    return k, K_LEVEL
        levelled = st[E_LEVELLED] != 0.0
        # block 3 on the low-passed C_nb f_b
        M.compensate_into(st[E_F_PEND : E_F_PEND + 3], b_a, s_a, fc)
        was = st[E_STATIC] != 0.0
        v_dr = math.hypot(v_n[0], v_n[1]) if st[E_POS_OK] != 0.0 and st[E_HEADING_OK] != 0.0 else math.nan
        tau = prm[Q_PREFILT_TAU]
        a = 1.0 if tau <= 0.0 else 1.0 - math.exp(-max(tk - st[E_T_PREFILT], 0.0) / tau)
        st[E_T_PREFILT] = tk
        fn0 = 0.0
        fn1 = 0.0
        for i in range(3):
            fni = C_nb[i, 0] * fc[0] + C_nb[i, 1] * fc[1] + C_nb[i, 2] * fc[2]
            st[E_F_N_LP + i] += a * (fni - st[E_F_N_LP + i])
            if i == 0:
                fn0 = fni
            elif i == 1:
                fn1 = fni
        static = False
        if levelled:
            static = static_step(sd_state, sd_speeds, sd_params, tk, st[E_F_N_LP], st[E_F_N_LP + 1], v_dr)
        st[E_STATIC] = 1.0 if static else 0.0
        if static != was:
            j = int(st[E_NREC])
            rec[j, R_KIND] = REC_STATIC_START if static else REC_STATIC_END
            rec[j, R_T] = tk
            st[E_NREC] = j + 1
            st[E_ZARU_SUM : E_ZARU_SUM + 3] = 0.0
            st[E_ZARU_N] = 0.0
            st[E_T_ZARU] = tk
        if static:
            st[E_STATIC_SEEN] = 1.0
            st[E_ZARU_SUM] += gx[k]
            st[E_ZARU_SUM + 1] += gy[k]
            st[E_ZARU_SUM + 2] += gz[k]
            st[E_ZARU_N] += 1.0
            quiet = math.hypot(st[E_F_N_LP], st[E_F_N_LP + 1]) < prm[Q_ZUPT_MAX_ACC] and not (
                tk - st[E_T_SPEED] < 1.5 and st[E_LAST_SPEED] > prm[Q_ZUPT_MAX_GNSS_SPEED]
            )
            if tk - st[E_T_ZUPT] >= prm[Q_ZUPT_INTERVAL] and levelled and quiet:
                _static_updates_nb(tk, st, prm, nom, P, acc, noise, rec, y, H, R, sm)
        # mount aligner (block 5) while the mount yaw is unknown
        if st[E_MOUNT_OK] == 0.0 and levelled:
            psi = math.atan2(C_nb[1, 0], C_nb[0, 0])
            cp, sp = math.cos(psi), math.sin(psi)
            M.compensate_into(st[E_W_PEND : E_W_PEND + 3], b_g, s_g, fc)
            r = C_nb[2, 0] * fc[0] + C_nb[2, 1] * fc[1] + C_nb[2, 2] * fc[2]
            accumulate_levelled(imu_sums, cp * fn0 + sp * fn1, -sp * fn0 + cp * fn1, r)
        if prm[Q_GRAV] != 0.0 and levelled and st[E_HEADING_OK] == 0.0 and st[E_STATIC_SEEN] == 0.0:
            _gravity_nb(tk, ax[k], ay[k], az[k], st, prm, nom, P, acc, noise, rec, y, H, R, sm)
        if (
            prm[Q_NHC] != 0.0
            and st[E_HEADING_OK] != 0.0
            and st[E_POS_OK] != 0.0
            and st[E_MOUNT_OK] != 0.0
            and not static
            and tk - st[E_T_NHC] >= prm[Q_NHC_INTERVAL]
        ):
            st[E_T_NHC] = tk
            if math.hypot(v_n[0], v_n[1]) >= prm[Q_NHC_MIN_SPEED]:
                M.nhc_rows(C_nb, v_n, C_vb, y, H)
                y[0] = -y[0]
                y[1] = -y[1]
                R[:, :] = 0.0
                R[0, 0] = prm[Q_NHC_LAT] ** 2
                R[1, 1] = prm[Q_NHC_VERT] ** 2
                _apply_nb(tk, 2, y, H, R, 2, prm[Q_GATE2], P, nom, acc, noise, st, prm, rec, sm)
        _output_row_nb(k, tk, of, ostat, osrc, st, prm, nom, P)
    return i1, K_DONE


def _params(c: EskfConfig, gates: dict[int, float]) -> FloatArray:
    """The parameter vector ``prm`` (``Q_*`` layout) of the compiled IMU path."""
    return np.array(
        [
            c.cov_interval_s,
            c.static_prefilter_tau_s,
            c.zupt_max_acc_mps2,
            c.zupt_max_gnss_speed_mps,
            c.zupt_interval_s,
            c.zupt_noise_mps,
            c.zaru_interval_s,
            c.gyro_noise_density_mdps_rthz * 1e-3 * DEG,
            c.zaru_floor_dps * DEG,
            1.0 if c.nhc else 0.0,
            c.nhc_interval_s,
            c.nhc_min_speed_mps,
            c.nhc_lateral_noise_mps,
            c.nhc_vertical_noise_mps,
            c.level_time_s,
            c.fix_hold_s,
            c.uere_m * c.default_hdop / math.sqrt(2.0),  # per axis (iotnav.gnss_accuracy)
            1.0 if c.estimate_mount else 0.0,
            gates[1],
            gates[2],
            gates[3],
            float(c.record_every),
            1.0 if c.gravity_aiding else 0.0,
            c.gravity_interval_s,
            c.gravity_max_acc_mps2,
            c.acc_noise_density_ug_rthz * 1e-6 * G0,
            float(c.max_gravity_rejections),
            c.gravity_reopen_std_rad,
        ]
    )


#: Measurements recorded by ``EskfEngine(record_innovations=True)``.
DEFAULT_RECORDED = ("gnss_position", "gnss_velocity")


class EskfEngine:
    """Streaming ESKF engine (see the module docstring).

    The IMU step is the compiled kernel ``_imu_kernel``: :meth:`imu_block` runs it over a
    block of samples and :meth:`step` over a one-sample block, so batch and streaming execute
    the same code. GNSS and magnetometer samples are handled in Python, with the same compiled
    propagation and measurement update.

    Parameters
    ----------
    config : EskfConfig, optional
        Tunables (MPU-6050 datasheet defaults).
    record_innovations : bool or iterable of str, optional
        Keep the innovation vector and its covariance ``S`` of every attempted update of these
        measurements (names of :data:`MEAS_NAMES` handled in Python: ``gnss_position``,
        ``gnss_velocity``, ``mag_heading``) in :attr:`innovations`; True: the GNSS position and
        velocity (:data:`DEFAULT_RECORDED`). Off by default; when on, it costs one ``H P H^T``
        per recorded update and does not change the estimates.

    Attributes
    ----------
    nom : eskf_models.Nominal
        Nominal state.
    P : numpy.ndarray
        Error-state covariance (layout of :mod:`iotnav.engines.eskf_models`).
    st : numpy.ndarray
        Hot scalar state of the IMU path (``E_*`` layout); flags and times such as
        :attr:`levelled`, :attr:`static`, :attr:`t_state` are views of it.
    events : list of dict
        Static transitions, alignment, mount estimates, rejected updates.
    nis_log : dict of list
        Per measurement name: ``(t, nis, dof, accepted)`` of every attempted update.
    innovations : dict of InnovationLog
        Per recorded measurement name (see ``record_innovations``): time, innovation ``y``,
        ``S`` and acceptance of every attempted update; empty when not recording.
    smoothing_log : SmoothingLog or None
        Records of the RTS smoother when ``config.smoothing`` (module docstring, "RTS
        smoothing"); :meth:`smoothing_corrections` and :meth:`ned_to_geodetic` complete the
        :class:`~iotnav.engines.smoother.Smoothable` interface.
    """

    have_imu = FlagSlot(E_HAVE_IMU, "st")
    t_state = StateSlot(E_T_STATE, "st")
    levelled = FlagSlot(E_LEVELLED, "st")
    level_n = CountSlot(E_LEVEL_N, "st")
    level_t0 = StateSlot(E_LEVEL_T0, "st")
    heading_ok = FlagSlot(E_HEADING_OK, "st")
    pos_ok = FlagSlot(E_POS_OK, "st")
    mount_ok = FlagSlot(E_MOUNT_OK, "st")
    static = FlagSlot(E_STATIC, "st")
    static_seen = FlagSlot(E_STATIC_SEEN, "st")
    t_speed = StateSlot(E_T_SPEED, "st")
    last_speed = StateSlot(E_LAST_SPEED, "st")
    t_prefilt = StateSlot(E_T_PREFILT, "st")
    t_nhc = StateSlot(E_T_NHC, "st")
    t_zupt = StateSlot(E_T_ZUPT, "st")
    zaru_n = CountSlot(E_ZARU_N, "st")
    t_zaru = StateSlot(E_T_ZARU, "st")
    t_fix = StateSlot(E_T_FIX, "st")
    n_imu = CountSlot(E_N_IMU, "st")

    def __init__(
        self, config: EskfConfig | None = None, *, record_innovations: bool | Iterable[str] = False
    ) -> None:
        self.config = c = config or EskfConfig()
        names: tuple[str, ...] = (
            DEFAULT_RECORDED
            if record_innovations is True
            else (() if record_innovations is False else tuple(record_innovations))
        )
        for name in names:
            if name not in ("gnss_position", "gnss_velocity", "mag_heading"):
                raise ValueError(f"record_innovations: {name!r} is not recorded (GNSS, magnetometer only)")
        self.innovations: dict[str, InnovationLog] = {name: InnovationLog() for name in names}
        self.n = M.n_states(c.estimate_scale_factors)
        self.nom = M.Nominal()
        self.P = np.eye(self.n) * 1e-6
        self.noise = noise_vector(c)
        self.lever_b = np.asarray(c.gnss_lever_arm_b_m, float)
        W = np.asarray(c.mag_soft_iron, float).reshape(3, 3)
        self.mag_Winv = np.linalg.inv(W)
        self.mag_h = np.asarray(c.mag_hard_iron_ut, float)
        #: the magnetometer is calibrated (configured, or declared calibrated): usable
        self.mag_usable = c.mag_calibrated or bool(np.any(self.mag_h != 0.0) or np.any(W != np.eye(3)))
        self.mag_unused = 0  # magnetometer samples left out, uncalibrated
        #: ``utc = t + utc_offset_s`` (set by :func:`run_batch` from the log): the WMM's date
        self.utc_offset_s = math.nan
        self.mag_declination_rad = c.mag_declination_rad
        self.mag_reference: dict[str, Any] | None = None
        self.static_det = StaticDetector(c.static)
        #: block 5 with the commitment rule (:mod:`iotnav.techniques.mount3d`)
        self.mount3d = Mount3d(c.mount, c.mount_commit_std_rad)
        self.aligner = self.mount3d.aligner
        self._mount_unobservable_reported = False
        self.events: list[dict[str, Any]] = []
        self.guard = InputGuard(self.events)
        self.nis_log: dict[str, list[tuple[float, float, int, bool]]] = {}
        self._gates = {d: kalman.gate_threshold(d, c.gate_probability) for d in (1, 2, 3)}
        self.prm = _params(c, self._gates)
        self.st = np.zeros(E_SIZE)
        self.rec = np.zeros((REC_ROWS, 7))
        self._frame: TangentPlane | None = None
        self._last_fix: tuple[float, FloatArray, FloatArray] | None = None
        self.g_n = np.array([0.0, 0.0, c.gravity_mps2 if c.gravity_mps2 > 0 else G0])
        self.acc = np.zeros(M.ACC_SIZE)
        self.t_state = math.nan
        self.f_pend = self.st[E_F_PEND : E_F_PEND + 3]  # raw IMU sample being integrated
        self.w_pend = self.st[E_W_PEND : E_W_PEND + 3]
        self.have_imu = False
        # initialisation flags
        self.levelled = False
        self.level_sum = self.st[E_LEVEL_SUM : E_LEVEL_SUM + 7]  # sum f (3), sum w (3), sum |f|^2
        self.level_n = 0
        self.level_t0 = math.nan
        self.heading_ok = False
        self.pos_ok = False
        self.mount_ok = c.mount_rpy_rad is not None
        if c.mount_rpy_rad is not None:
            self.nom.C_vb[:] = euler_to_dcm(*c.mount_rpy_rad)
        self.static = False
        self.static_seen = False
        self.f_n_lp = self.st[E_F_N_LP : E_F_N_LP + 3]
        self.t_speed = -math.inf
        self.last_speed = math.nan
        self.t_prefilt = -math.inf
        # scheduling
        self.t_nhc = -math.inf
        self.t_zupt = -math.inf
        self.t_mag = -math.inf
        self.zaru_sum = self.st[E_ZARU_SUM : E_ZARU_SUM + 3]
        self.zaru_n = 0
        self.t_zaru = -math.inf
        self.t_fix = -math.inf
        self.n_rejected_fix = 0
        #: recent fixes' (t, v_N, v_E) for the GNSS-derived acceleration (:meth:`_gnss_accel`)
        self._v_hist: list[tuple[float, float, float]] = []
        self.st[E_T_A_GNSS] = -math.inf
        self._t_valid = math.nan  # time of the latest valid fix, s
        self._t_long_gap_end = -math.inf  # first valid fix after a long gap, s
        #: the origin came from a fix without a height: the vertical is unknown until a 3D fix
        self._vertical_unknown = False
        self.sigma_e = np.array([1.0, 1.0, 1.5])  # current sigma of the smoothed GNSS error, m
        #: which receiver figures gave the latest fix's position sigma (:meth:`_gnss_noise`)
        self._scaling = AccuracyScaling()
        self._fix_source: tuple[str, str] = ("", "")  # figures behind the latest fix's sigma
        #: output rounding of the fixes (NMEA decimals), the white part of the position noise
        self.resolution = PositionResolution()
        self.n_imu = 0
        # one-sample block for step(ImuSample)
        self._one = OneSampleBlock()  # step(ImuSample): the batch kernel on one sample
        # RTS smoothing (module docstring): the records drained from the kernels' buffer, with
        # the output-attitude map of each record
        if c.smoothing and c.record_every < 1:
            raise ValueError(f"eskf.record_every must be >= 1, got {c.record_every}")
        self._sm_log: SmoothingLog | None = SmoothingLog(c.record_every) if c.smoothing else None
        self._sm_att: list[FloatArray] = []
        #: Smoothing arrays of the compiled code: ``(buf, Phi, work, rec, att)``: the open
        #: record's prior and posterior (``x`` then ``P`` row-major, 2 rows), the transition
        #: since the previous record (``n^2``, row-major), two ``(n, n)`` work matrices, the
        #: record buffer (:func:`~iotnav.engines.smoother.record_size` columns) and each
        #: buffered record's output-attitude map (9). Placeholders when not smoothing.
        n, rows = (self.n, SM_ROWS) if c.smoothing else (1, 1)
        self.sm: tuple[FloatArray, FloatArray, FloatArray, FloatArray, FloatArray] = (
            np.zeros((2, n + n * n)),
            np.eye(n).reshape(-1),
            np.zeros((2, n, n)),
            np.zeros((rows, record_size(n))),
            np.zeros((rows, 9)),
        )

    # ------------------------------------------------------------------ state kept in st
    @property
    def frame(self) -> TangentPlane | None:
        """NED origin (set at the first fix)."""
        return self._frame

    @frame.setter
    def frame(self, fr: TangentPlane | None) -> None:
        self._frame = fr
        st = self.st
        st[E_HAS_FRAME] = 0.0 if fr is None else 1.0
        if fr is not None:
            st[E_LAT0], st[E_LON0], st[E_H0], st[E_KN], st[E_KE] = (
                fr.lat0_deg,
                fr.lon0_deg,
                fr.h0_m,
                fr.k_n,
                fr.k_e,
            )

    @property
    def last_fix(self) -> tuple[float, FloatArray, FloatArray] | None:
        """Time (s), NED position (m) and velocity (m/s) of the latest valid fix."""
        return self._last_fix

    @last_fix.setter
    def last_fix(self, fix: tuple[float, FloatArray, FloatArray] | None) -> None:
        self._last_fix = fix
        st = self.st
        st[E_HAS_FIX] = 0.0 if fix is None else 1.0
        if fix is not None:
            st[E_FIX_T] = fix[0]
            st[E_FIX_Z : E_FIX_Z + 3] = fix[1]
            st[E_FIX_V : E_FIX_V + 3] = fix[2]

    # ------------------------------------------------------------------ protocol
    @property
    def mount_yaw_rad(self) -> float:
        """Mount yaw (sensor x from vehicle forward, clockwise), rad; NaN while not committed."""
        if not self.mount_ok:
            return math.nan
        C = self.nom.C_vb
        return math.atan2(C[1, 0], C[0, 0])

    @property
    def mount_rpy_rad(self) -> tuple[float, float, float]:
        """Current mounting rotation ``C_vb`` as roll, pitch, yaw, rad; NaN while not committed
        (``unobservable``, :mod:`iotnav.techniques.mount3d`), not the identity it starts from."""
        if not self.mount_ok:
            return (math.nan, math.nan, math.nan)
        return dcm_to_rpy(self.nom.C_vb)

    def summary(self) -> dict[str, Any]:
        """Configuration, final state and statistics (for ``summary.json``)."""
        counts: dict[str, int] = {}
        for e in self.events:
            counts[e["type"]] = counts.get(e["type"], 0) + 1
        nis = {
            k: {
                "count": len(v),
                "accepted": int(sum(1 for r in v if r[3])),
                "mean_nis_per_dof": float(np.mean([r[1] / r[2] for r in v])) if v else math.nan,
            }
            for k, v in self.nis_log.items()
        }
        return {
            "skipped": dict(self.guard.skipped),
            "engine": "eskf",
            "mag_unused": self.mag_unused,
            "mag_reference": self._mag_reference_summary(),
            "config": self.config.to_dict(),
            "n_states": self.n,
            "gnss_resolution": self.resolution.to_dict(),
            "mount_rpy_rad": list(self.mount_rpy_rad),
            "mount_known": self.mount_ok,
            "mount": self.mount3d.report(
                self.nom.C_vb if self.mount_ok else None,
                self.P[M.MNT, M.MNT] if self.mount_ok else None,
                self.config.mount_commit_std_rad,
            ),
            "gyro_bias_rad_s": self.nom.b_g.tolist(),
            "acc_bias_mps2": self.nom.b_a.tolist(),
            "gyro_scale": self.nom.s_g.tolist(),
            "acc_scale": self.nom.s_a.tolist(),
            "origin": None
            if self.frame is None
            else {
                "lat_deg": self.frame.lat0_deg,
                "lon_deg": self.frame.lon0_deg,
                "height_m": self.frame.h0_m,
            },
            "event_counts": counts,
            "nis": nis,
            "imu_samples": self.n_imu,
            "gravity_resets": int(self.st[E_GRAV_RESETS]),
        }

    def step(self, sample: Sample) -> Output | None:
        """Process one sample (streaming; batch runs the same code, see :meth:`imu_block`).

        An IMU sample runs the compiled kernel on a one-sample block and returns its row.
        """
        sample = self.guard.admit(sample)
        if sample is None:
            return None
        if isinstance(sample, ImuSample):
            return self._one.run(self.imu_block, sample)
        if isinstance(sample, GnssSample):
            self._gnss(sample)
        elif isinstance(sample, MagSample):
            self._mag(sample)
        if self._sm_log is not None:
            self._drain_smoothing()
        return None

    # ------------------------------------------------------------------ smoothing
    @property
    def smoothing_log(self) -> SmoothingLog | None:
        """Records for the RTS smoother (:mod:`iotnav.engines.smoother`); None unless ``smoothing``.

        The records written so far plus, as the last one, the record still open (or, when
        none is, one at the latest covariance propagation, with the transition since the
        previous record), so that the log read after a run covers it to its end. Reading it
        does not change the engine.
        """
        log = self._sm_log
        if log is None:
            return None
        self._drain_smoothing()
        tail = self._smoothing_tail()
        if tail is None:
            return log
        out = SmoothingLog(
            log.record_every,
            list(log.t),
            list(log.x_prior),
            list(log.P_prior),
            list(log.x_post),
            list(log.P_post),
            list(log.Phi),
        )
        out.record(*tail[:6])
        return out

    def _smoothing_tail(
        self,
    ) -> tuple[float, FloatArray, FloatArray, FloatArray, FloatArray, FloatArray, FloatArray] | None:
        """The open (or implicit last) record: ``t, x-, P-, Phi, x+, P+`` and its attitude map."""
        st, n = self.st, self.n
        if st[E_SM_ON] == 0.0:
            return None
        buf, Phi, _work, _rec, att = self.sm
        if st[E_SM_PEND] != 0.0:
            return (
                float(st[E_SM_T]),
                buf[0, :n].copy(),
                buf[0, n:].reshape(n, n).copy(),
                Phi.reshape(n, n).copy(),
                buf[1, :n].copy(),
                self.P.copy(),
                att[int(st[E_SM_N])].copy(),
            )
        if st[E_SM_COUNT] == 0.0:
            return None
        # propagations since the last record and no record open: P is the prior (and, with no
        # update, the posterior) at the latest propagation
        t_last = self._sm_log.t[-1] if self._sm_log is not None and len(self._sm_log) else -math.inf
        t = max(float(self.t_state - self.acc[M.ACC_T]), t_last)
        mount = self.nom.C_nb @ self.nom.C_vb.T if self.mount_ok else np.zeros((3, 3))
        z = np.zeros(n)
        return t, z, self.P.copy(), Phi.reshape(n, n).copy(), z, self.P.copy(), mount.reshape(-1)

    def _drain_smoothing(self) -> None:
        """Move the records the compiled code wrote into the log (and their attitude maps)."""
        st = self.st
        count = int(st[E_SM_N])
        if count == 0 or self._sm_log is None:
            return
        _buf, _Phi, _work, rec, att = self.sm
        drain_records(self._sm_log, rec, count, self.n)
        self._sm_att.append(att[:count].copy())
        if st[E_SM_PEND] != 0.0:
            att[0] = att[count]  # the open record's map moves with it to row 0
        st[E_SM_N] = 0.0

    def _start_smoothing(self) -> None:
        """Position and heading known: the output is the nominal state from now on; first record."""
        if self._sm_log is None or self.st[E_SM_ON] != 0.0:
            return
        self.st[E_SM_ON] = 1.0
        self.st[E_SM_COUNT] = 0.0
        self.sm[1][:] = np.eye(self.n).reshape(-1)
        _sm_open(self.st, self.nom.arrays(), self.P, self.sm)

    def _smoothing_reset(self, T: FloatArray) -> None:
        """Record a covariance reset ``P <- T P T^T + Q_r`` (call before ``P`` is changed).

        The open record is written (its posterior is ``P`` before the reset) and ``T`` joins the
        transition to the next record, whose prior is then ``... T P+ T^T + Q_r ...``: the
        reset is one more linear step of the smoothing model (a re-initialised state has a
        zero row in ``T``, so nothing is carried back to it across the reset).
        """
        if self.st[E_SM_ON] == 0.0:
            return
        if self.st[E_SM_PEND] != 0.0:
            _sm_close(self.st, self.P, self.sm)
        Phi = self.sm[1].reshape(self.n, self.n)
        Phi[:] = T @ Phi
        self._drain_smoothing()

    def _smoothing_unwidened_prior(self, P_u: FloatArray, acc_u: FloatArray) -> None:
        """Open the forced fix's record with the prior the filter had *without* the gate reset.

        ``P_u`` and ``acc_u`` are the covariance and the covariance accumulator just before the
        position covariance was widened; ``P_u`` is propagated over the same interval (the same
        compiled arithmetic, and the fixed mount zeroed likewise) to the fix time, where the
        record is opened (if no record is open there yet) with that prior. The widening and
        the forced update then together form the record's update: its ``dx`` and ``P+`` are the
        filter's, and the transition to the record carries no reset.
        """
        n = self.n
        P = P_u.copy()
        M.propagate_covariance_phi(P, acc_u, self.noise, np.empty((n, n)))
        if self.prm[Q_EST_MOUNT] == 0.0:
            P[M.MNT, :] = 0.0
            P[:, M.MNT] = 0.0
        if self.st[E_SM_PEND] == 0.0:
            _sm_open(self.st, self.nom.arrays(), self.P, self.sm)
        self.sm[0][0, n:] = P.reshape(-1)

    def _reinit_rows(self, rows: slice | int) -> FloatArray:
        """``T`` of a reset that re-initialises the error states ``rows`` (their rows zeroed)."""
        T = np.eye(self.n)
        T[rows, :] = 0.0
        return T

    def _attitude_maps(self, K: int) -> FloatArray:
        """``(K, 3, 3)`` output-attitude maps of the first ``K`` records of :attr:`smoothing_log`."""
        parts = list(self._sm_att)
        have = sum(p.shape[0] for p in parts)
        if K > have:
            tail = self._smoothing_tail()
            if tail is not None:
                parts.append(tail[6].reshape(1, 9))
        A = np.concatenate(parts, axis=0) if parts else np.zeros((0, 9))
        if A.shape[0] < K:
            raise ValueError(f"{K} records asked, {A.shape[0]} recorded")
        return A[:K].reshape(K, 3, 3)

    def smoothing_corrections(
        self, x_filt: FloatArray, x_smooth: FloatArray, P_smooth: FloatArray
    ) -> FloatArray:
        """Corrections at the record points (:mod:`iotnav.engines.smoother`): error-state RTS.

        The smoothed error ``xs`` and the filter's ``x`` (``dx`` after the updates, 0 before)
        are both about the record's prior nominal state, so the correction of what was output
        is their difference.

        Parameters
        ----------
        x_filt, x_smooth : numpy.ndarray
            ``(K, n)`` filtered and smoothed error states of the records of :attr:`smoothing_log`.
        P_smooth : numpy.ndarray
            ``(K, n, n)`` smoothed covariances.

        Returns
        -------
        numpy.ndarray
            ``(K, 11)``: position ``xs - x`` (NED, m), velocity (NED, m/s), the rotation
            ``dtheta`` in ``n`` (rad) with ``C_s = exp([dtheta x]) C_out``, smoothed ``std_north``,
            ``std_east`` (m). The output attitude is ``C_out = C_nb C_vb^T`` once the mount is
            known, whose error is ``dth - C_out dmu`` (``C_nb`` error ``dth`` in ``n``, mount error
            ``dmu`` in ``v``; :mod:`iotnav.engines.eskf_models`), else ``C_nb`` (error ``dth``).
        """
        K = x_filt.shape[0]
        out = np.zeros((K, 11))
        out[:, CORR_POS] = x_smooth[:, M.POS] - x_filt[:, M.POS]
        out[:, CORR_VEL] = x_smooth[:, M.VEL] - x_filt[:, M.VEL]
        A = self._attitude_maps(K)
        th_s = x_smooth[:, M.ATT] - np.einsum("kij,kj->ki", A, x_smooth[:, M.MNT])
        th_f = x_filt[:, M.ATT] - np.einsum("kij,kj->ki", A, x_filt[:, M.MNT])
        if K:
            out[:, CORR_ATT] = (Rotation.from_rotvec(th_s) * Rotation.from_rotvec(th_f).inv()).as_rotvec()
        i_n, i_e = M.POS.start, M.POS.start + 1
        out[:, CORR_STD] = np.sqrt(
            np.maximum(np.stack([P_smooth[:, i_n, i_n], P_smooth[:, i_e, i_e]], axis=1), 0.0)
        )
        return out

    def ned_to_geodetic(self, r_n: FloatArray) -> tuple[FloatArray, FloatArray, FloatArray]:
        """NED ``(N, 3)`` (m) about the origin to lat, lon (deg), height (m)."""
        return plane_to_geodetic(self.frame, r_n)

    def imu_block(
        self,
        t: FloatArray,
        acc: tuple[FloatArray, FloatArray, FloatArray],
        gyro: tuple[FloatArray, FloatArray, FloatArray],
        out: OutputBlock,
        i0: int,
        i1: int,
    ) -> None:
        """Process IMU samples ``i0 .. i1-1`` in time order, writing row ``k`` of ``out`` for sample ``k``.

        Parameters
        ----------
        t : numpy.ndarray
            Device times, s.
        acc, gyro : tuple of numpy.ndarray
            Specific force along sensor x, y, z (m/s^2) and angular rate about them (rad/s),
            one 1-D float64 array per axis.
        out : OutputBlock
            Output rows (columns of :data:`iotnav.engines.base.FLOAT_COLUMNS`).
        i0, i1 : int
            Sample range.

        Notes
        -----
        Everything per IMU sample runs in the compiled kernel: strapdown, covariance
        propagation, static detection (block 3), ZUPT/ZARU and NHC updates, block 5's
        accumulation and the output row. The kernel stops for Python only when the levelling
        window completes (once) and when its record buffer (events, NIS log) is full.
        """
        k = i0
        resume = False
        while True:
            k, code = _imu_kernel(
                t,
                acc,
                gyro,
                out.floats,
                out.static,
                out.source,
                k,
                i1,
                resume,
                self.st,
                self.prm,
                self.nom.arrays(),
                self.P,
                self.acc,
                self.noise,
                self.g_n,
                self.static_det.state,
                self.static_det.speeds,
                self.static_det.params,
                self.aligner.imu_sums,
                self.rec,
                self.sm,
            )
            self._flush()
            if code == K_DONE:
                return
            resume = code == K_LEVEL
            if resume:
                self._level_finish(float(t[k]))

    def _flush(self) -> None:
        """Turn the compiled code's records into ``events`` and ``nis_log`` entries, in order.

        Smoothing records are moved to the log too (:meth:`_drain_smoothing`).
        """
        if self._sm_log is not None:
            self._drain_smoothing()
        n = int(self.st[E_NREC])
        if n == 0:
            return
        for row in self.rec[:n].tolist():
            kind, t = int(row[R_KIND]), row[R_T]
            if kind == REC_UPDATE:
                name = MEAS_NAMES[int(row[R_MEAS])]
                ok = bool(row[R_ACC])
                self.nis_log.setdefault(name, []).append((t, row[R_NIS], int(row[R_DOF]), ok))
                if not ok and name != "gnss_position":
                    self.events.append(
                        {
                            "type": "update_rejected",
                            "t": t,
                            "measurement": name,
                            "nis": row[R_NIS],
                            "test_ratio": row[R_RATIO],
                        }
                    )
            else:
                self.events.append(
                    {"type": "static_start" if kind == REC_STATIC_START else "static_end", "t": t}
                )
        self.st[E_NREC] = 0.0

    # ------------------------------------------------------------------ propagation
    def _integrate_to(self, t: float) -> None:
        """Integrate the pending IMU sample from ``t_state`` to ``t`` (compiled)."""
        _integrate_to_nb(
            float(t),
            self.st,
            self.prm,
            self.nom.arrays(),
            self.g_n,
            self.acc,
            self.P,
            self.noise,
            np.empty(6),
            self.sm,
        )

    def _propagate_cov(self) -> None:
        """Propagate the covariance over the accumulated interval (compiled)."""
        _propagate_cov_nb(self.P, self.acc, self.noise, self.nom.arrays(), self.st, self.prm, self.sm)

    # ------------------------------------------------------------------ updates
    def _apply(self, t: float, meas: M.Meas | None, force: bool = False) -> bool:
        """Gate and apply one measurement (compiled update); returns True when accepted."""
        if meas is None:
            return False
        m = meas.y.size
        y = np.zeros(3)
        y[:m] = meas.y
        H = np.zeros((3, self.n))
        H[:m] = meas.H
        R = np.zeros((3, 3))
        R[:m, :m] = meas.R
        gate = -1.0 if force else self._gates[m]  # m is 1, 2 or 3
        log = self.innovations.get(meas.name) if self.innovations else None
        S = None
        if log is not None:
            # P to now (the compiled update then finds the interval empty, as without recording)
            self._propagate_cov()
            HP = meas.H @ self.P
            S = HP @ meas.H.T + meas.R
        ok = _apply_nb(
            float(t),
            MEAS_CODES[meas.name],
            y,
            H,
            R,
            m,
            gate,
            self.P,
            self.nom.arrays(),
            self.acc,
            self.noise,
            self.st,
            self.prm,
            self.rec,
            self.sm,
        )
        self._flush()
        if log is not None and S is not None:
            log.append(float(t), meas.y, S, bool(ok))
        return bool(ok)

    # ------------------------------------------------------------------ IMU
    def _level_finish(self, t: float) -> None:
        """Levelling window complete (the kernel has summed it): attitude, biases, covariance."""
        c = self.config
        n = self.level_n
        fm = self.level_sum[:3] / n
        wm = self.level_sum[3:6] / n
        var_f = max(self.level_sum[6] / n - float(fm @ fm), 0.0)
        roll = math.atan2(-fm[1], -fm[2])
        pitch = math.atan2(fm[0], math.hypot(fm[1], fm[2]))
        self.nom.C_nb[:] = euler_to_dcm(roll, pitch, 0.0)
        # what was integrated before with the unknown attitude is discarded (a sensor mounted
        # z up would otherwise have gained 2 g of vertical velocity per second)
        self.nom.v_n[:] = 0.0
        self.nom.p_n[:] = 0.0
        quiet = math.sqrt(var_f) < 0.5 and abs(float(np.linalg.norm(fm)) - G0) < 0.5
        # a car cruising straight is as quiet as one at rest: the GNSS speed tells them apart (a
        # start in motion must not take the window's mean rate, yaw rate included, as the bias)
        moving = t - self.t_speed < 1.5 and self.last_speed > c.zupt_max_gnss_speed_mps
        quiet = quiet and not moving
        if quiet:
            self.nom.b_g[:] = wm
        self.levelled = True
        sg = c.gyro_turn_on_bias_dps * DEG
        nd_g = c.gyro_noise_density_mdps_rthz * 1e-3 * DEG
        bg_std = math.hypot(nd_g / math.sqrt(max(t - self.level_t0, 1e-3)), 0.05 * sg) if quiet else sg
        ba_std = c.acc_turn_on_bias_mg * 1e-3 * G0
        # the cross-axis coupling of gravity, M_a f_b at rest, is a constant offset like the
        # turn-on bias while the tilt holds: per axis m_a^2 (|f|^2 - f_i^2)
        m_a = c.acc_misalignment_pct * 1e-2
        var_ba = ba_std**2 + m_a**2 * (float(fm @ fm) - fm**2)
        sa_std = c.acc_scale_factor_pct * 1e-2
        d = np.zeros(self.n)
        d[M.POS] = 100.0
        d[M.VEL] = 1.0 if quiet else 10.0
        d[M.BG] = bg_std
        d[M.MNT] = c.mount_std_rad if c.mount_rpy_rad is not None else c.mount_aligner_std_rad
        d[M.GNE] = 3.0
        d[M.GNM] = 3.0
        if self.n >= M.N_FULL:
            d[M.SG] = c.gyro_scale_factor_pct * 1e-2
        self.P = np.diag(d**2)
        # tilt = accelerometer error / g, fully correlated with it (eskf_models.level_covariance);
        # the independent part: standard error of the mean when quiet, else the configured value
        g = float(self.g_n[2])
        white = math.sqrt(var_f / n) / g if quiet else max(c.initial_tilt_std_rad, c.moving_tilt_std_rad)
        full = self.n >= M.N_FULL
        Pl = M.level_covariance(
            self.nom.C_nb,
            fm,
            g,
            var_ba,
            np.full(3, sa_std**2) if full else None,
            white,
        )
        idx = np.r_[np.arange(M.ATT.start, M.ATT.stop), np.arange(M.BA.start, M.BA.stop)]
        if full:
            idx = np.r_[idx, np.arange(M.SA.start, M.SA.stop)]
        self.P[np.ix_(idx, idx)] = Pl  # yaw row stays zero until initialised (see _freeze_yaw_nb)
        self.acc[:] = 0.0
        st = self.st
        st[E_GRAV_SUM : E_GRAV_SUM + 3] = 0.0
        st[E_GRAV_N] = 0.0
        st[E_T_GRAV] = t
        self.events.append({"type": "levelled", "t": t, "roll": roll, "pitch": pitch, "quiet": quiet})

    # ------------------------------------------------------------------ magnetometer
    def _mag_reference_summary(self) -> dict[str, Any]:
        """The declination used (degrees) and where it came from, for ``summary()``."""
        if self.mag_reference is not None:
            return self.mag_reference
        d = self.mag_declination_rad
        return {
            "declination_deg": None if d is None else math.degrees(d),
            "from": "no fix yet" if d is None else "config",
        }

    def _mag(self, s: MagSample) -> None:
        c = self.config
        if not c.use_mag or not self.levelled:
            return
        if not self.mag_usable:
            if self.mag_unused == 0:
                self.events.append({"type": "mag_unused", "t": s.t, "reason": "uncalibrated"})
            self.mag_unused += 1
            return
        decl = self.mag_declination_rad
        if decl is None:
            self.guard.skip("mag_before_declination", s.t)
            return
        m_b = self.mag_Winv @ (np.asarray(s.mag_b_ut, float) - self.mag_h)
        self._integrate_to(s.t)
        if not self.heading_ok:
            r, p, _ = dcm_to_rpy(self.nom.C_nb)
            C_tilt = euler_to_dcm(r, p, 0.0)
            m = C_tilt @ m_b
            yaw = decl - math.atan2(m[1], m[0])
            self._set_heading(s.t, yaw, c.mag_heading_noise_rad, "magnetometer")
            self.t_mag = s.t
            return
        if s.t - self.t_mag >= c.mag_interval_s:
            self.t_mag = s.t
            self._apply(s.t, M.mag_heading(self.nom, m_b, decl, c.mag_heading_noise_rad, self.n))

    def _set_heading(self, t: float, yaw: float, sigma: float, how: str, mount_cov: float = 0.0) -> None:
        """Set the sensor yaw, keeping roll and pitch; reset the yaw covariance."""
        r, p, yaw_old = dcm_to_rpy(self.nom.C_nb)
        self.nom.C_nb[:] = euler_to_dcm(r, p, yaw)
        # the navigation frame turns with the yaw: rotate every n-frame error (P' = T P T^T)
        T = M.heading_reset_transform(yaw - yaw_old, self.n)
        # the yaw row/column: decorrelate, set variance (and its mount correlation)
        k = M.ATT.start + 2
        self._smoothing_reset(self._reinit_rows(k) @ T)
        self.P = kalman.symmetrize(T @ self.P @ T.T)
        self.P[k, :] = 0.0
        self.P[:, k] = 0.0
        self.P[k, k] = sigma**2
        if mount_cov:
            km = M.MNT.start + 2
            self.P[k, km] = self.P[km, k] = mount_cov
        self.heading_ok = True
        self.events.append(
            {"type": "heading_initialised", "t": t, "yaw_rad": yaw, "source": how, "std_rad": sigma}
        )

    # ------------------------------------------------------------------ GNSS
    def _gnss_noise(self, s: GnssSample) -> tuple[FloatArray, float, tuple[str, str]]:
        """Per-axis NED position sigma (m), velocity sigma (m/s) and which figures gave the
        position sigma, horizontal and vertical (the accuracy scaling compares like with like:
        :class:`~iotnav.engines.gnss_resolution.AccuracyScaling`)."""
        c = self.config
        sig = position_sigmas(s.h_acc_m, s.v_acc_m, s.hdop, s.pdop, c.uere_m, c.default_hdop)
        s_acc = float(getattr(s, "s_acc_mps", math.nan))
        sv_ = s_acc if math.isfinite(s_acc) and s_acc > 0 else c.gnss_speed_noise_mps
        return sig.ned_m, sv_, sig.source

    def _gnss_velocity(self, s: GnssSample) -> FloatArray | None:
        c = self.config
        vn = float(getattr(s, "vn", math.nan))
        ve = float(getattr(s, "ve", math.nan))
        vd = float(getattr(s, "vd", math.nan))
        if math.isfinite(vn) and math.isfinite(ve):
            return np.array([vn, ve, vd]) if math.isfinite(vd) else np.array([vn, ve])
        if math.isfinite(s.speed_mps):
            if s.speed_mps < c.gnss_min_course_speed_mps:
                return np.zeros(2) if s.speed_mps < 0.2 else None
            if s.course_valid and math.isfinite(s.course_rad):
                return s.speed_mps * np.array([math.cos(s.course_rad), math.sin(s.course_rad)])
        return None

    def _gnss(self, s: GnssSample) -> None:
        c = self.config
        if not s.valid or not (math.isfinite(s.lat_deg) and math.isfinite(s.lon_deg)):
            self.events.append({"type": "fix_rejected", "t": s.t, "reason": "invalid"})
            self.aligner.add_gnss(s.t, math.nan, math.nan, False, self.static)
            return
        # end of the latest gap between valid fixes longer than smoothing_drift_gap_s
        if math.isfinite(self._t_valid) and s.t - self._t_valid > c.smoothing_drift_gap_s:
            self._t_long_gap_end = s.t
        self._t_valid = s.t
        self._integrate_to(s.t)
        if self.frame is None:
            h0 = s.height_m if math.isfinite(s.height_m) else 0.0
            self.frame = TangentPlane(s.lat_deg, s.lon_deg, h0)
            if c.gravity_mps2 <= 0:
                self.g_n[2] = normal_gravity(s.lat_deg, h0)
            self._vertical_unknown = not math.isfinite(s.height_m)
            self.events.append({"type": "first_fix", "t": s.t, "pdop": s.pdop, "num_sv": s.num_sv})
            if self.mag_declination_rad is None:
                year, year_from = log_year(s.t, self.utc_offset_s, None)
                ref = reference_field(s.lat_deg, s.lon_deg, h0, year)
                self.mag_declination_rad = ref.declination_rad
                self.mag_reference = {**ref.to_dict(), "year_from": year_from}
        has_height = math.isfinite(s.height_m)
        # a 2D fix (no height) updates the horizontal only; its down is the filter's own
        z = self.frame.to_ned(s.lat_deg, s.lon_deg, s.height_m if has_height else self.frame.h0_m)
        if self.frame.follow(z):  # long routes: the plane re-linearised at the fix (same coordinates)
            self.frame = self.frame
        if not has_height:
            z[2] = float(self.nom.p_n[2] + (self.nom.C_nb @ self.lever_b)[2])
        sig_p, sig_v, source = self._gnss_noise(s)
        # the figures' decimals are learnt at every fix (gnss_resolution.FigureDecimals)
        steps = self._scaling.figures.relative_steps(
            float(getattr(s, "h_acc_m", math.nan)),
            float(getattr(s, "v_acc_m", math.nan)),
            s.hdop,
            s.pdop,
            source,
        )
        self._fix_source = source
        v_meas = self._gnss_velocity(s)
        speed = (
            s.speed_mps
            if math.isfinite(s.speed_mps)
            else (math.hypot(v_meas[0], v_meas[1]) if v_meas is not None else math.nan)
        )
        self.static_det.update_speed(s.t, speed)
        if math.isfinite(speed):
            self.t_speed, self.last_speed = s.t, speed
        course = s.course_rad
        course_ok = s.course_valid and math.isfinite(course)
        if (
            v_meas is not None
            and not course_ok
            and v_meas.size >= 2
            and math.hypot(v_meas[0], v_meas[1]) > 1.0
        ):
            course, course_ok = math.atan2(v_meas[1], v_meas[0]), True
        # block 5 while the mount yaw is unknown
        if not self.mount_ok and self.levelled:
            ev = self.aligner.add_gnss(s.t, speed, course, course_ok, self.static)
            if ev is not None:
                self.events.append(ev)
        # time-correlated part of the GNSS error follows the reported accuracy
        f = c.gnss_white_fraction
        self.sigma_e = math.sqrt(max(1.0 - f * f, 0.0)) * sig_p
        tf = c.gnss_receiver_filter_s
        te_h, te_v = c.gnss_corr_time_s, c.gnss_corr_time_v_s
        self.noise[8] = 2.0 * M.gm_variance_factor(te_h, tf) / te_h * self.sigma_e[0] ** 2
        self.noise[9] = 2.0 * M.gm_variance_factor(te_v, tf) / te_v * self.sigma_e[2] ** 2
        self.resolution.update(s.lat_deg, s.lon_deg, s.height_m)
        sig_white = np.maximum(f * sig_p, c.gnss_white_floor_m)
        if c.gnss_white_from_resolution:
            sig_white = np.maximum(sig_white, self.resolution.sigma_ned_m(s.lat_deg))
        v_fix = np.zeros(3)
        if v_meas is not None:
            v_fix[: v_meas.size] = v_meas
            self._gnss_accel(s.t, v_meas, sig_v)
        self.last_fix = (s.t, z, v_fix)
        if not self.levelled:
            return
        moving_fast = course_ok and math.isfinite(speed) and speed >= c.align_min_speed_mps
        if not self.heading_ok:
            if not self.mount_ok and self.mount3d.committable:
                self._init_mount(s.t, self.aligner.mount_yaw_rad, "block5")
            elif not self.mount_ok and self.aligner.known and not self._mount_unobservable_reported:
                # block 5 has an angle, but not yet one the data determine: not committed
                self._mount_unobservable_reported = True
                self.events.append(
                    {
                        "type": "mount_unobservable",
                        "t": s.t,
                        "block5_yaw_rad": self.mount3d.mount_yaw_rad,
                        "block5_std_rad": self.mount3d.yaw_std_rad,
                        "commit_std_rad": c.mount_commit_std_rad,
                    }
                )
            if self.mount_ok and moving_fast:
                # vehicle yaw = course; sensor yaw = vehicle yaw + mount yaw
                r, p, _ = dcm_to_rpy(self.nom.C_nb @ self.nom.C_vb.T)
                C_nv = euler_to_dcm(r, p, course)
                _, _, yaw_b = dcm_to_rpy(C_nv @ self.nom.C_vb)
                sig_c = sig_v / max(speed, 0.1)
                sm = float(np.sqrt(self.P[M.MNT.start + 2, M.MNT.start + 2]))
                self._set_heading(s.t, yaw_b, math.hypot(sig_c, sm), "gnss_course", mount_cov=sm * sm)
                self._reset_position(s.t, z, v_meas, sig_v, has_height, sig_white)
            return
        if not self.pos_ok:
            self._reset_position(s.t, z, v_meas, sig_v, has_height, sig_white)
            return
        if not self.mount_ok and moving_fast:
            # magnetometer heading known: mount yaw = sensor yaw - course
            _, _, yaw_b = dcm_to_rpy(self.nom.C_nb)
            mu = math.remainder(yaw_b - course, 2.0 * math.pi)
            self._init_mount(s.t, mu, "mag_course")
            km = M.MNT.start + 2
            self._smoothing_reset(self._reinit_rows(km))
            self.P[km, :] = 0.0
            self.P[:, km] = 0.0
            self.P[km, km] = self.P[M.ATT.start + 2, M.ATT.start + 2] + (sig_v / speed) ** 2
        if c.gnss_error_scales_with_accuracy and self.pos_ok:
            # between figures of one kind (not h_acc on one fix and DOP x UERE on the next), the
            # figures' rounding steps low-passed: gnss_resolution.AccuracyScaling
            kr = self._scaling.ratio(s.t, self.sigma_e, source, steps)
            if kr is not None:
                self._scale_gnss_error(s.t, np.array(kr))
        # position update (gated; re-open after repeated rejections)
        force = self.n_rejected_fix >= c.max_gnss_rejections
        rows_p = M.POS if has_height else slice(M.POS.start, M.POS.start + 2)  # rows a fix updates
        unwidened: tuple[FloatArray, FloatArray] | None = None
        if force:
            drifted = s.t - self._t_long_gap_end <= 2.0 * c.smoothing_drift_gap_s
            if self.st[E_SM_ON] != 0.0 and drifted:
                # the widening is part of the forced update, not of the smoothing model
                # (module docstring, "RTS smoothing"): the open record ends here, before it
                self._smoothing_reset(np.eye(self.n))
                unwidened = (self.P.copy(), self.acc.copy())
            else:
                self._smoothing_reset(self._reinit_rows(rows_p))
            self.P[rows_p, :] = 0.0
            self.P[:, rows_p] = 0.0
            self.P[rows_p, rows_p] = np.diag((3.0 * sig_p[: rows_p.stop - rows_p.start]) ** 2)
            self.events.append({"type": "gate_reset", "t": s.t, "rejected": self.n_rejected_fix})
        self._propagate_cov()  # P and the GNSS error estimates e, e_gm to the fix time, before y
        if unwidened is not None:
            self._smoothing_unwidened_prior(*unwidened)
        horizontal_only = not has_height
        if has_height and self._vertical_unknown and self.pos_ok:
            self._reset_vertical(s.t, z, sig_white)
            horizontal_only = True  # its height is in the reset already: not twice
        meas = M.gnss_position(self.nom, z, self.lever_b, sig_white, self.n)
        if horizontal_only:
            meas = M.Meas(meas.name, meas.y[:2], meas.H[:2], meas.R[:2, :2])
        ok = self._apply(s.t, meas, force=force)
        if ok:
            self.n_rejected_fix = 0
            self.t_fix = s.t
        else:
            self.n_rejected_fix += 1
            rec = self.nis_log["gnss_position"][-1]
            self.events.append(
                {
                    "type": "fix_rejected",
                    "t": s.t,
                    "reason": "nis",
                    "nis": rec[1],
                    "test_ratio": rec[1] / self._gates[rec[2]],
                }
            )
        if c.use_gnss_velocity and v_meas is not None:
            inv_tf = float(self.noise[14])
            sv = np.full(3, sig_v)
            self._apply(s.t, M.gnss_velocity(self.nom, self.w_pend, v_meas, self.lever_b, sv, self.n, inv_tf))

    def _gnss_accel(self, t: float, v_meas: FloatArray, sig_v: float) -> None:
        """Horizontal acceleration from the fixes' velocities (m/s^2) and its 1-sigma, into ``st``.

        The difference is taken to the latest fix at least ``gnss_accel_span_s`` older (up to
        2.5 s; older fixes are forgotten); its 1-sigma is ``sqrt(2) sigma_v / dt``.
        """
        c = self.config
        hist = self._v_hist
        hist.append((t, float(v_meas[0]), float(v_meas[1])))
        while len(hist) > 1 and t - hist[0][0] > 2.5:
            hist.pop(0)
        old = None
        for rec in hist:
            if t - rec[0] >= c.gnss_accel_span_s:
                old = rec
        if old is None:
            return
        dt = t - old[0]
        st = self.st
        st[E_A_GNSS] = math.hypot(v_meas[0] - old[1], v_meas[1] - old[2]) / dt
        st[E_SA_GNSS] = math.sqrt(2.0) * sig_v / dt
        st[E_T_A_GNSS] = t

    def _init_mount(self, t: float, mount_yaw: float, how: str) -> None:
        """Mount from its yaw and the level-vehicle assumption; covariance of its roll and pitch.

        The vehicle is taken as level (roll and pitch zero within ``vehicle_level_std_rad``,
        road crossfall and grade) at this epoch, so the mount's roll and pitch are the sensor's:
        ``C_vb = R_z(mu) R_y(pitch_b) R_x(roll_b)`` (works for any mounting, sensor upside down
        included). Their error is then the sensor tilt error seen in the vehicle frame plus
        the road's tilt, ``dmu_xy = [R_z(-psi_v) dth]_xy - road_xy``: the rows are rebuilt with
        that transform, ``P' = T P T^T + diag(road^2)``, keeping the correlation with the
        tilt (and through it with the accelerometer bias). With ``mount_rpy_rad`` configured
        nothing here runs.
        """
        c = self.config
        r_b, p_b, psi_b = dcm_to_rpy(self.nom.C_nb)
        self.nom.C_vb[:] = mount_from_tilt(self.nom.C_nb, mount_yaw)
        psi_v = psi_b - mount_yaw
        rows = np.arange(M.MNT.start, M.MNT.start + 2)
        T = np.eye(self.n)
        T[rows, :] = 0.0
        T[np.ix_(rows, np.arange(M.ATT.start, M.ATT.stop))] = rot_z(-psi_v)[:2, :]
        self._smoothing_reset(T)
        self.P = T @ self.P @ T.T
        self.P[rows, rows] += c.vehicle_level_std_rad**2
        self.P = kalman.symmetrize(self.P)
        self.mount_ok = True
        self.events.append(
            {
                "type": "mount_initialised",
                "t": t,
                "mount_yaw_rad": mount_yaw,
                "mount_roll_rad": r_b,
                "mount_pitch_rad": p_b,
                "source": how,
            }
        )

    def _scale_gnss_error(self, t: float, k: FloatArray) -> None:
        """The receiver's correlated error scales with its reported accuracy, per NED axis.

        ``e = sigma(t) y`` with ``y`` a unit Gauss-Markov process (as a DOP or a re-acquisition
        multiplies the error it scales): a change of the reported sigma by ``k`` scales the
        estimates ``e``, ``e_gm`` and their error, ``P' = T P T^T`` with ``k`` on the ``GNE``
        and ``GNM`` rows of ``T``.
        """
        kn, ke, kd = float(k[0]), float(k[1]), float(k[2])
        if not (kn > 0.0 and ke > 0.0 and kd > 0.0 and math.isfinite(kn + ke + kd)):
            return
        if abs(kn - 1.0) <= 1e-6 and abs(ke - 1.0) <= 1e-6 and abs(kd - 1.0) <= 1e-6:
            return  # (plain floats: this runs at every fix; numpy's allclose was 6 % of a run)
        self._propagate_cov()  # P and e, e_gm at the fix time
        n = self.n
        d = np.ones(n)
        d[M.GNE] = k
        d[M.GNM] = k
        st = self.st
        if st[E_SM_ON] != 0.0:
            # a linear step of the smoothing model, in the transition into the fix's record
            # (RTS uses each record's prior as well as its posterior: inside the record, as an
            # "update", it set the smoothed estimate of the records before in the wrong units)
            buf = self.sm[0]
            fresh = (
                st[E_SM_PEND] != 0.0
                and st[E_SM_T] == st[E_T_STATE]
                and not np.any(buf[1][:n])
                and np.array_equal(buf[0][n:], self.P.reshape(-1))
            )
            if st[E_SM_PEND] != 0.0 and not fresh:
                _sm_close(st, self.P, self.sm)  # a record with updates already: ends here
        else:
            fresh = False
        self.P *= np.outer(d, d)  # T P T^T with a diagonal T: stays symmetric
        self.nom.e_n[:] *= k
        self.nom.e_gm[:] *= k
        if st[E_SM_ON] != 0.0:
            Phi = self.sm[1].reshape(n, n)
            Phi[:] = d[:, None] * Phi
            if fresh:  # opened at the fix time, no update yet: its prior takes the scaling
                self.sm[0][0][n:] = self.P.reshape(-1)
            self._drain_smoothing()

    def _reset_vertical(self, t: float, z: FloatArray, sig_white: FloatArray) -> None:
        """First fix with a height after an origin without one: down position (and the down
        GNSS error states) re-initialised from it, event ``vertical_reset``."""
        nom = self.nom
        k, ke, km = M.POS.start + 2, M.GNE.start + 2, M.GNM.start + 2
        rows = [k, ke, km]
        T = np.eye(self.n)
        T[rows, :] = 0.0
        self._smoothing_reset(T)
        old = float(nom.p_n[2])
        nom.p_n[2] = z[2] - float((nom.C_nb @ self.lever_b)[2])
        nom.e_n[2] = 0.0
        nom.e_gm[2] = 0.0
        self.P[rows, :] = 0.0
        self.P[:, rows] = 0.0
        c = self.config
        C = M.stationary_gnss_error_cov(self.sigma_e[2:] ** 2, c.gnss_corr_time_v_s, c.gnss_receiver_filter_s)
        ge = [ke, km]
        self.P[k, k] = C[0, 0] + float(sig_white[2] ** 2)
        self.P[np.ix_(ge, ge)] = C
        self.P[k, ge] = self.P[ge, k] = -C[0]  # as in _reset_position
        self._scaling.reset(self.sigma_e, axes=(2,), t=t)
        self._vertical_unknown = False
        self.events.append({"type": "vertical_reset", "t": t, "jump_m": float(nom.p_n[2] - old)})

    def _reset_position(
        self,
        t: float,
        z: FloatArray,
        v_meas: FloatArray | None,
        sig_v: float,
        has_height: bool,
        sig_white: FloatArray,
    ) -> None:
        """Position (and velocity) from a fix; decorrelate those states. A fix without a height
        leaves the vertical unknown until the next that has one (:meth:`_reset_vertical`)."""
        nom = self.nom
        self._vertical_unknown = not has_height
        T = np.eye(self.n)
        for sl in (M.POS, M.VEL, M.GNE, M.GNM):
            T[sl, :] = 0.0
        self._smoothing_reset(T)  # (the first call starts the recording, below)
        nom.p_n[:] = z - nom.C_nb @ self.lever_b
        nom.e_n[:] = 0.0
        if v_meas is not None:
            nom.v_n[: v_meas.size] = v_meas
            if v_meas.size == 2:
                nom.v_n[2] = 0.0
        nom.e_gm[:] = 0.0
        for sl in (M.POS, M.VEL, M.GNE, M.GNM):
            self.P[sl, :] = 0.0
            self.P[:, sl] = 0.0
        self.P[M.POS, M.POS] = np.diag(self.sigma_e**2 + sig_white**2)
        # [e, e_gm] at their stationary covariance (eskf_models.stationary_gnss_error_cov); the
        # position is the fix minus e, whose estimate is 0: its error is the fix's error -e (plus
        # the white part), hence cov(dp, de) = -var(e) and cov(dp, de_gm) = -cov(e, e_gm) (taken
        # as independent, the fix's exact sum p + e made the filter halve the position variance
        # at the first update: horizontal NEES per axis 1.4-1.7 over 20 runs)
        c = self.config
        te = np.array([c.gnss_corr_time_s, c.gnss_corr_time_s, c.gnss_corr_time_v_s])
        C = M.stationary_gnss_error_cov(self.sigma_e**2, te, c.gnss_receiver_filter_s)
        ge = slice(M.GNE.start, M.GNM.stop)
        self.P[ge, ge] = C
        self.P[M.POS, ge] = -C[:3]
        self.P[ge, M.POS] = -C[:, :3]
        self._scaling.reset(self.sigma_e, self._fix_source, t=t)
        sv = sig_v if v_meas is not None else 5.0
        self.P[M.VEL, M.VEL] = np.diag([sv**2, sv**2, max(sv, 0.3) ** 2])
        self.pos_ok = True
        self.t_fix = t
        self.events.append({"type": "position_initialised", "t": t})
        if self.heading_ok:
            self._start_smoothing()
