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

from iotnav.engines.eskf.config import DEG, G0, EskfConfig, noise_vector
from iotnav.engines.eskf.engine import EskfEngine
from iotnav.engines.eskf.layout import DEFAULT_RECORDED, MEAS_CODES, MEAS_NAMES

__all__ = [
    "DEFAULT_RECORDED",
    "DEG",
    "G0",
    "MEAS_CODES",
    "MEAS_NAMES",
    "EskfConfig",
    "EskfEngine",
    "noise_vector",
]
