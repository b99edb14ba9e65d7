"""Error-state extended Kalman filter (ESKF) for low-cost GNSS + MEMS IMU (+ magnetometer).

Loosely coupled INS/GNSS in the flat-earth local NED frame of :mod:`iotnav.strapdown`
(Groves 2013, "Principles of GNSS, Inertial, and Multisensor Integrated Navigation
Systems", 2nd ed., ch. 14; Sola 2017, "Quaternion kinematics for the error-state Kalman
filter", §5-§7). The nominal state is integrated at the IMU rate with the simulator's
strapdown step; the error state carries the uncertainty: position, velocity, attitude, gyro
and accelerometer biases (first-order Gauss-Markov, from the datasheet's bias instability and
correlation time), the mounting rotation ``C_vb``, the time-correlated GNSS position error
(two blocks: the receiver's smoothed output and the Gauss-Markov error behind it) and
optionally the gyro and accelerometer scale factors (24 states, 30 with them). The sensors'
cross-axis coupling is not estimated but enters the noise model (gyro: rate-dependent
attitude noise; accelerometer: a wider turn-on bias at levelling and acceleration-dependent
bias noise). The measured evidence behind the model and its defaults (Monte Carlo NEES,
NIS, whiteness, real drives) is in ``benchmarks/results/eskf_history.md``.

The house
---------
:mod:`~iotnav.engines.eskf.layout`
    Every array layout, declared once: the error state (``POS`` ... ``SA``), the process-noise
    record (``NZ_*``), the strapdown accumulator, the hot state ``st``, the parameters ``prm``,
    the record rows.
:mod:`~iotnav.engines.eskf.models`
    The model on one page (error states, dynamics, noise, GNSS error model, every
    measurement), re-exporting its pieces: :mod:`~iotnav.engines.eskf.state` (nominal state,
    reset), :mod:`~iotnav.engines.eskf.propagation` (strapdown, ``Phi``, ``Q_d``, covariance),
    :mod:`~iotnav.engines.eskf.update` (Joseph-form update with NIS gate),
    :mod:`~iotnav.engines.eskf.alignment` (levelling and heading-reset covariances),
    :mod:`~iotnav.engines.eskf.measurements` (each model returns ``Meas(name, y, H, R)`` or None).
:mod:`~iotnav.engines.eskf.config`
    :class:`EskfConfig` and the noise record of a configuration (:func:`noise_vector`).
:mod:`~iotnav.engines.eskf.kernel`
    The compiled IMU path: strapdown, covariance propagation, static detection, ZUPT / ZARU,
    NHC, gravity aiding, the output row, the smoother's records.
:mod:`~iotnav.engines.eskf.core`, :mod:`~iotnav.engines.eskf.smoothing`, :mod:`~iotnav.engines.eskf.resets`, :mod:`~iotnav.engines.eskf.gnss`, :mod:`~iotnav.engines.eskf.engine`
    :class:`EskfEngine` in layers, each a base of the next: the arrays and the calls into the
    compiled code; the RTS records; the initialisation steps and covariance resets; the GNSS
    epochs; the streaming ``step()``, the batch block, the magnetometer and the summary.

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
    :class:`~iotnav.engines.base.Output` is returned per IMU sample. All of it is one
    compiled kernel on the engine's arrays; ``step(ImuSample)`` runs it on a one-sample block
    and :func:`~iotnav.engines.base.run_batch` on the runs of IMU samples between GNSS /
    magnetometer samples (:meth:`EskfEngine.imu_block`), so both execute the same code. The
    kernel returns to Python only when the levelling window completes (once) or its record
    buffer (events, NIS log) is full.
GNSS
    The nominal state, the covariance and the GNSS error estimates ``e``, ``e_gm`` are
    brought to the fix time, then position (with lever arm) and velocity updates. Velocity
    is the receiver's NED velocity when present, else speed and course (horizontal). Noise:
    ``h_acc_m`` / ``v_acc_m`` / ``s_acc_mps`` when the receiver reports them, else DOP x
    ``uere_m`` (:mod:`iotnav.gnss_accuracy`). The position error is a white part, the
    rounding of the fixes' output format (:mod:`iotnav.engines.gnss_resolution`: NMEA minutes
    with 3, 4 or 5 decimals are steps of 1.85 m, 0.185 m or 1.85 cm of latitude, white noise
    of ``step / sqrt(12)``), or ``gnss_white_floor_m``, or ``gnss_white_fraction`` of the
    accuracy, whichever is largest; and a time-correlated part carried as states: a
    Gauss-Markov error (``GNM``, correlation times ``gnss_corr_time_s`` and, vertically,
    ``gnss_corr_time_v_s``) seen through the receiver's first-order position smoothing
    (``gnss_receiver_filter_s``), whose output ``GNE`` is what the fix carries (second order,
    smooth from fix to fix as a consumer receiver's is). The receiver's Doppler velocity
    error is the derivative of the smoothed position error, ``(e_gm - e) / t_f``, in the
    model through the states, plus white noise (``s_acc_mps``), all of ``R``.
Magnetometer
    Calibrated (``mag_hard_iron_ut``, ``mag_soft_iron``), heading update every
    ``mag_interval_s``; also gives the initial heading. Without a calibration (or
    ``mag_calibrated``) it is left out, counted in ``summary()["mag_unused"]``.

Every update is gated by its NIS (``gate_probability``); a rejected update becomes an
``update_rejected`` event (``fix_rejected`` for GNSS positions) with NIS and test ratio. After
``max_gnss_rejections`` consecutive rejected fixes the position covariance is inflated and the
next fix is accepted (event ``gate_reset``); a persistent disagreement re-initialises the filter
("Consistency monitor"), so it cannot lock itself out. Covariance
updates use the Joseph form and symmetrisation of :mod:`iotnav.kalman`. Innovations are kept
on request: ``EskfEngine(config, record_innovations=True)`` stores the innovation and ``S`` of
every GNSS position and velocity update (:class:`~iotnav.innovations.InnovationLog`).

Consistency monitor
-------------------
The gate handles a transient disagreement; a persistent one (a wrong heading or mount: the
filter drifts off again after every gate reset) is caught by the windowed NIS test of
:mod:`~iotnav.engines.eskf.consistency` (``nis_monitor``, on by default): the GNSS position
NIS of the last ``nis_window_fixes`` fixes, each divided by ``nis_tolerance`` and capped at its
``nis_cap_probability`` quantile, summed and tested against the chi-square quantile of the
summed dof at ``nis_false_alarm``. On an alarm the filter re-initialises from that fix
(:meth:`EskfEngine._reinitialise`, one step for batch and streaming: both run
:meth:`EskfEngine._gnss`): tilt, biases, scale factors and mount re-opened to their priors of
a start in motion, the heading and position unknown again, so the heading comes from the
course (with the mount yaw) at once when moving faster than ``align_min_speed_mps``, else at
the first such fix, the output being the last fix moved on until then; a second alarm within
``reinit_escalate_s`` also releases the mount (block 5 again). Event ``reinitialised`` (reason,
the window's statistic, threshold, dof, fixes and span, whether the mount was released),
counted in ``summary()["reinitialisations"]``. Fixes are then never rejected for longer than
about one window. Evidence: ``benchmarks/results/eskf_nis.md``.

Reported accuracy
-----------------
``gnss_error_scales_with_accuracy`` (default): the correlated receiver error is ``e = sigma(t) y``
with ``y`` a unit Gauss-Markov process, so when the reported accuracy changes by ``k`` the
estimates ``e``, ``e_gm`` and their covariance rows are scaled by ``k``
(:meth:`EskfEngine._scale_gnss_error`), at once for continuous figures and for jumps, low-passed
over the rounding steps of rounded figures
(:class:`~iotnav.engines.gnss_resolution.AccuracyScaling`), and only between sigmas of the same
kind (hAcc/vAcc, or DOPs x UERE). For the smoother the scaling is a linear step of the
transition into the fix's record. A receiver whose reported accuracy does not follow its error
can turn it off.

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

* Record points: every update epoch (GNSS, magnetometer and the kernel's ZUPT, ZARU and NHC;
  all updates at one ``t_state`` form one record) and every ``record_every`` covariance
  propagations without one. A record is opened before the first update of its time (prior:
  ``P`` then), the updates' ``dx`` are summed (to first order the correction about the prior
  nominal), and it is written at the next covariance propagation (posterior: ``P`` before that
  interval). ``Phi`` is the product of the transitions that propagated ``P`` since the
  previous record (:func:`~iotnav.engines.eskf.propagation.propagate_covariance_phi`), so
  ``P-_{k+1} = Phi P+_k Phi^T + Q`` holds exactly and RTS on the records is exact.
* Start: the first record is at the epoch where position and heading are both initialised.
* Covariance resets while recording (heading, mount, position): ``P <- T P T^T + Q_r``; the
  open record is written and ``T`` joins the transition to the next one
  (:meth:`EskfEngine._smoothing_reset`); a re-initialised state has a zero row in ``T``, so
  nothing is carried back to it across the reset.
* Gate reset after an outage (a gap of valid fixes longer than ``smoothing_drift_gap_s``,
  ended at most twice that before the forced fix): the widening is part of the forced
  update, not a step of the model (the true position is continuous). The forced fix's record
  gets the prior the filter had without the widening
  (:meth:`EskfEngine._smoothing_unwidened_prior`) and the filter's posterior. After a
  shorter gap the reset is recorded as a re-initialisation of the position.
* Memory: ``8 (1 + 2 n + 3 n^2)`` bytes a record, 21.8 KB with 30 states (13.8 KB with 24);
  :mod:`iotnav.engines.smoother_records` stores it exactly in about 8.8 KB (upper triangles,
  nonzero patterns) and keeps at most 32 MB in RAM, the rest in a temporary file
  (``benchmarks/results/smoother_memory.md``: 1,217 -> 181 MB of RAM per hour of 100 Hz).
  With the NHC or ZUPT running (10 Hz) every 0.1 s is a record.
* Off (default): the forward output is bit-identical; on, the forward output is the same.

Initialisation
--------------
1. Levelling: roll and pitch from the mean accelerometer over ``level_time_s`` (gyro mean as
   the initial gyro bias when the window is quiet and the GNSS speed low). Levelling absorbs
   the accelerometer bias and scale error, so the tilt covariance is that error over ``g``
   and fully correlated with it (:func:`~iotnav.engines.eskf.alignment.level_covariance`).
   Levelled in motion, the gyro bias is unknown (its turn-on sigma) and the tilt 1-sigma is
   ``moving_tilt_std_rad``. When the yaw is later set, every navigation-frame error is
   rotated with it (:func:`~iotnav.engines.eskf.alignment.heading_reset_transform`).
2. Heading: magnetometer (if any) or ``course + mount yaw`` at the first GNSS epoch faster
   than ``align_min_speed_mps`` once the mount yaw is known (``mount_rpy_rad``, else block
   5's estimate, :class:`iotnav.techniques.mount.MountAligner`, committed once its own
   1-sigma is at most ``mount_commit_std_rad``, :class:`iotnav.techniques.mount3d.Mount3d`).
   With a magnetometer and no configured mount, the mount yaw is ``sensor yaw - course``.
   Mount roll and pitch are the sensor's at that epoch (vehicle level within
   ``vehicle_level_std_rad``), their error tied to the sensor tilt error
   (:meth:`EskfEngine._init_mount`); the NHC refines the mount as states.
3. Before the heading is known the output is the last fix extrapolated with the GNSS
   velocity: source ``fix`` up to ``fix_hold_s`` after the fix, then ``dr_velocity`` (or
   ``last_position`` when the fix had no velocity: it is held), with the honest per-axis
   1-sigma ``sqrt(sigma_f^2 + (sigma_v tau)^2 + (a tau^2 / 2)^2)``, ``tau`` the time since
   the fix: the fix's reported position sigma, its velocity sigma carried forward (the speed
   itself when it gave no velocity) and the unknown acceleration ``a``, the RMS of the
   GNSS-derived horizontal acceleration over the last ``hold_window_s`` and at least
   ``hold_accel_floor_mps2``; the velocity change ``a t`` is capped at the reach bound of
   ``hold_speed_margin`` times the recent top speed (the third term is then ``a T^2 / 2 +
   v_r (tau - T)``, ``T = v_r / a``): what the vehicle did before the outage, bounded.
   While no static period has been seen, gravity aids the
   tilt (``gravity_aiding``): the mean specific force over ``gravity_interval_s`` is a
   measurement ``(C_nb f)_NE = 0`` (:func:`~iotnav.engines.eskf.measurements.gravity_rows`)
   with the GNSS-derived horizontal acceleration in ``R``, while that acceleration is at most
   ``gravity_max_acc_mps2``; after ``max_gravity_rejections`` rejections in a row the tilt
   covariance is re-opened.

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
