"""22-state quaternion EKF with GPS and 3-axis magnetometer (improved TRIAD attitude observation).

(28 states with the option ``gnss_error_states``, the GNSS position error carried as states,
section "GNSS error states" at the end.)

Reference: "Design of a low cost 3D localization system based on strapdown IMU, GPS and 3-axis
magnetometer" (IMU-GPS-magnetometer quaternion EKF; 32-bit ARM prototype, 40 s
initialisation, 220 s car test with a 4 s GPS gap), Eqs. 1-13.

State (paper Sec. 3.2: "the filter state vector presents 22 states")::

    x = [q_nb (4), v_n (3), r_n (3), b_g (3), b_a (3), s_g (3), s_a (3)]
         Q_NB      VEL      POS      BG      BA      SG      SA

``q_nb`` scalar first, maps ``b`` to ``n`` (the paper's ``q^b_n`` in its notation); ``n`` is
the NED frame at an origin held still during the run (paper Sec. 2).

Sensor model (Eq. 11, per axis) and its inversion used in the prediction::

    f~ = s_a f + b_a + w_a,   w~ = s_g w + b_g + w_g
    f = (f~ - b_a) / s_a,     w = (w~ - b_g) / s_g            (element-wise)
    b(k+1) = b(k) + w_b,  s(k+1) = s(k) + w_s                 (Eqs. 12-13)

Prediction (Eq. 8; its quaternion line is lost in the extraction and restored here from Eq. 2,
``q' = 1/2 q (x) [0, w]``, integrated exactly for a rate constant over the step)::

    theta = w dt,  dq(theta) = [cos(|theta|/2), sin(|theta|/2) theta/|theta|]
    q(k+1) = q(k) (x) dq(theta)                                  = M_R(dq) q(k)
    a      = C(q_mid) f + g_n,   q_mid = q(k) (x) dq(theta/2)
    v(k+1) = v(k) + a dt
    r(k+1) = r(k) + v(k) dt + a dt^2 / 2

Eq. 8 rotates ``f`` with ``C(k)``; we use the mid-interval attitude ``q_mid`` (second order,
as :mod:`iotnav.strapdown`, whose convention the simulator follows). ``C(q)`` is the
quadratic form ``(w^2 - v.v) I + 2 v v^T + 2 w [v x]`` (exact rotation for ``|q| = 1``).

Jacobian ``F = d x(k+1) / d x(k)`` (derived here; the paper gives none), with
``M_L(q) p = q (x) p = M_R(p) q`` and ``J_dq(theta) = d dq / d theta``::

    d q'/d q   = M_R(dq)
    d q'/d b_g = M_L(q) J_dq(theta) (-dt diag(1/s_g))
    d q'/d s_g = M_L(q) J_dq(theta) (-dt diag(w/s_g))
    d a/d q    = J_Cf(q_mid, f) M_R(dq(theta/2)),   J_Cf = d(C(q) f)/dq
               = [2 (w f + v x f),  2 ((v.f) I + v f^T - f v^T - w [f x])]
    d a/d theta = J_Cf(q_mid, f) M_L(q) J_dq(theta/2) / 2     (then through b_g, s_g as above)
    d a/d b_a  = -C(q_mid) diag(1/s_a),   d a/d s_a = -C(q_mid) diag(f/s_a)
    d v'/d . = dt d a/d .,   d r'/d . = dt^2/2 d a/d .,   d r'/d v = dt I

``J_dq`` = [-sin(a/2) theta^T / (2a);  sin(a/2)/a I + theta theta^T (cos(a/2)/(2a^2) - sin(a/2)/a^3)],
``a = |theta|`` (Taylor series below 1e-4 rad). Process noise: the gyro and accelerometer
white noises enter like the measurements (``d x'/d w~ = -d x'/d b_g``), with per-step variances
``N^2 / dt`` (``N`` noise densities), plus random walks of the biases and scale factors.

Observations (Eq. 10, applied whenever available):

* GPS position, converted ECEF -> NED about the origin estimated in the initialisation
  (Eqs. 5-6, through :mod:`iotnav.geo`): ``r_n = C_en^T (r_e(gps) - r_e(0))``, ``H = [0 0 I 0]``;
  ``R`` from hAcc (the 2D figure: ``hAcc / sqrt(2)`` per axis) and vAcc, else DOP x UERE
  (:mod:`iotnav.gnss_accuracy`, the same reading in every engine);
* GPS velocity: ``vn, ve, vd`` rotated through ECEF from the fix's local NED to the origin's
  (``C_en(0)^T C_en(fix) v``), or horizontal speed and course when that is all the receiver
  gives;
* attitude: the improved TRIAD (:mod:`iotnav.techniques.triad`) of gravity and the magnetic
  field (Eq. 7) gives ``q_obs``, observed directly (``H = [I4 0]``; sign chosen to match the
  state). Gravity in ``b`` is ``-f`` corrected by the estimated bias and scale and by the
  vehicle's centripetal (``w x v_b``) and along-track (GPS speed rate) accelerations; its
  direction sigma grows with the remaining dynamic acceleration. The rotation-vector
  covariance ``P_theta`` of TRIAD (:func:`~iotnav.techniques.triad.triad_covariance`) maps to the
  quaternion as ``R_q = 1/4 Xi P_theta Xi^T + sigma_n^2 q q^T`` with ``Xi = M_R(q)[:, 1:]``
  (``q_true = [1, dtheta/2] (x) q``).
  *Dependence on the state estimate.* ``g_b`` is built from the estimated ``b_a, s_a, b_g, s_g``
  and ``v_n``, so ``z = T(g_b(x_hat)) = q_true - J_x (x_true - x_hat) + noise`` with
  ``J_x = 1/2 Xi J_g dg_b/dx`` (``J_g`` from :func:`~iotnav.techniques.triad.triad_jacobian`,
  ``dg_b/dx`` in :func:`iotnav.engines.qekf_kernel.accumulate_gravity`). ``triad_state_coupling="jacobian"``
  puts ``-J_x`` into ``H`` (exact linear model); ``"noise"`` keeps ``H = [I4 0]`` and adds
  ``J_x P J_x^T`` to ``R`` (the estimate's uncertainty treated as observation noise). Over 20
  Monte Carlo runs the Jacobian form was *less* consistent (mean NEES 12-16 against 10.5; yaw
  RMS 3-4 deg on seeds 0, 2, 3): the compensation's errors are time-correlated (lag,
  sideslip), and the Jacobian lets the filter explain them with the velocity and gyro states.
  The noise form is conservative for one update but not for a sequence: the error it adds is
  the *same* at every update when it comes from the accelerometer's bias and scale factor,
  which also made the initial alignment's error (``-f_mean = g_b - b_a``). Counted as fresh
  noise at 6 Hz it is averaged away: on car-magnetometer seed 8 (horizontal bias 0.46 m/s^2,
  2.7 deg of tilt at the alignment, 5 deg of yaw through the magnetic dip) four TRIAD updates
  in the first 0.7 s shrank the yaw sigma from 2.7 to 1.7 deg while its error grew from 4.8 to
  5.7 deg, and the accelerometer-bias sigma fell to 0.04 m/s^2 with an error of 0.3 m/s^2 (the
  TRIAD observations confirm the tilt the bias made). The default
  ``"accelerometer"`` therefore puts the ``b_a, s_a`` columns of ``-J_x`` into ``H`` (that
  error is then the state's own, observed nowhere twice) and keeps the velocity and gyro
  columns (the compensation ``w x v_b``) as noise. Yaw RMS on seeds 0-8, all three with the
  lagging along-track acceleration and the initial covariance of before (below): 1.07, 1.12,
  1.86, 1.35, 2.22, 1.25, 2.69, 0.94, 2.85 deg with ``"noise"``, 1.79, 1.30, 2.40, 2.23,
  2.17, 0.99, 2.30, 0.89, 1.75 with ``"jacobian"``, 1.44, 1.41, 1.82, 1.58, 1.92, 1.59, 2.32,
  1.12, 2.37 with ``"accelerometer"``; with the three changes 0.59, 0.78, 1.41, 1.00, 1.39,
  0.76, 1.57, 0.52, 1.69 (``"jacobian"``: 1.55, 0.72, 2.07, 2.18, 5.07, 0.90, 1.71, 0.69,
  1.42).
  *Vehicle acceleration.* The direction sigma of ``g_b`` is
  ``sqrt(acc_dir_std^2 + (dyn_acc_factor a_dyn / g)^2 + var_comp / g^2)``: ``a_dyn = ||g_b| - g|``
  inflates it while ``|f| != g`` (a residual acceleration along gravity), and
  ``var_comp = a_long_std^2 + (comp_rel_error |a_b|)^2`` covers the compensation itself, which
  ``| |g_b| - g |`` cannot see when the residual is perpendicular to gravity. The along-track
  acceleration is the GNSS (or, without GNSS velocity, the filter's) speed change over the
  last epoch interval, ``a_long``, a mean that lags the present by 0.5-1.5 s, plus the change
  of the accelerometer's along-track specific force since that interval (zero lag,
  :meth:`QekfEngine._speed_rate`); ``a_long_std`` is then the error of the speed difference,
  ``sqrt(2) sigma_v / dt``. Without that correction (the lagging mean alone, its lag error
  taken as its change between intervals) the compensation missed the onset of every
  speed-up and braking: on car-magnetometer seed 4, five TRIAD observations 75.5-76.2 s, as
  the car sped up after a turn (0.4-1.4 m/s^2 left uncompensated, the estimate still 0,
  within ``triad_max_comp_mps2``; NIS 1.7-23, all accepted) turned the yaw error from 0.9 to
  5.4 deg; with the true acceleration as compensation the seed's yaw RMS was 1.23 deg instead
  of 2.22. The remaining compensation errors (sideslip, lever arm) are systematic over a
  manoeuvre, not white: with TRIAD applied through accelerations, 20 Monte Carlo runs had a mean
  position/velocity NEES of 11.0 (seeds 100-119; 7.7 on 200-219) against the interval
  4.6-7.6, three runs with 3-4 deg tilt errors. So no TRIAD observation is made over an
  interval whose mean ``|a_b|`` exceeds ``triad_max_comp_mps2`` (1 m/s^2): NEES 6.3 and 6.6
  on the same seeds (5.6 and 5.3 with the zero-lag acceleration and the coupling above; with
  TRIAD throughout, the yaw RMS of seeds 0-8 rises to 0.9-2.4 deg, 1.7 on average against 1.1).
  The magnetometer sample is refused (``mag_rejected``
  event) when its norm or its dip angle departs from the reference field (disturbances);
* the quaternion-norm pseudo-observation ``e = 1 - |q| = 0`` (Eq. 9), ``H = -q^T / |q|``,
  applied with every other update (the propagation ``q (x) dq`` keeps the norm exactly, only
  updates change it).

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

Without a magnetometer (designed here; none arrived during the initialisation, or
``use_mag=False``) nothing observes the yaw at a constant velocity, and the paper's filter
drifts freely in heading. The fallback, active from the end of the initialisation:

1. *Mount yaw.* Block 5 of the pipeline, :class:`iotnav.techniques.mount.MountAligner`
   (``mount``, default the pipeline's ``PIPELINE_MOUNT_NAV``, provisional estimates included), fed like the pipeline feeds it:
   every IMU sample in ``b`` with the yaw rate ``r = C[2] . w`` (estimated tilt, corrected
   gyro), every GNSS epoch with speed and course. It compares the vehicle-frame
   acceleration from GNSS and the gyroscope with the levelled specific force and needs no
   absolute heading. Convention: sensor yaw = vehicle yaw + ``mu``. Its first gravity reference
   is the initialisation's mean specific force (standing still): the aligner is only fed from
   the end of the initialisation, usually when the vehicle already moves, and would otherwise
   wait for the next stop (on the rtklibexplorer drive 170 s of driving were lost that way).
2. *Before the heading is known* the yaw state is arbitrary (levelling only), so the GNSS
   horizontal position and velocity are not used as observations (their innovations would be
   explained by tilt and accelerometer bias through the wrong yaw): the horizontal position
   and velocity are re-initialised from each fix (rows and columns zeroed, variances from
   ``R``); the vertical position (and velocity, when given) are ordinary updates, which need
   no yaw. No other update acts on the yaw (the norm pseudo-observation ``H = -q^T`` is
   orthogonal to the yaw direction), so no spurious yaw information is created.
3. *Heading reset* at the first GNSS epoch with a valid course ``chi``, the speed at least
   ``heading_min_speed_mps``, the mean yaw rate over the epoch interval at most
   ``heading_max_yaw_rate_rad_s`` (driving straight) and a mount angle (accepted, or provisional
   with its sigma of up to 15 deg, which enters ``sigma_psi`` below): the sensor yaw
   becomes ``psi_b = chi + mu``, i.e. ``q' = q_z(dpsi) (x) q`` with ``q_z`` the rotation by
   ``dpsi`` about the ``n`` down axis. The attitude error rotates with it, ``P' = T P T^T``
   with ``T = M_L(q_z)`` on ``Q_NB`` (the tilt / bias correlations learnt so far keep their
   meaning in ``n``; cf. :func:`iotnav.engines.eskf_models.heading_reset_transform`).
   Position and velocity are *not* rotated here: unlike the ESKF, which runs in an arbitrary
   frame before the heading, they were just set from the fix in the true ``n`` (step 2), so
   their values and errors are already in the right frame (and uncorrelated with the
   attitude). The yaw direction ``e = 1/2 M_R(q)[:, 3]`` (``q_true = [1, dtheta/2] (x) q``,
   ``dtheta = [0, 0, dpsi]``) is then projected out of ``P`` (``P <- Pi P Pi^T``,
   ``Pi = I - u u^T``, ``u = e / |e|``) and given the variance
   ``sigma_psi^2 = (sigma_v / |v|)^2 + sigma_mu^2 + sigma_slip^2`` (course noise, the aligner's
   fused mount sigma, sideslip).
4. *Non-holonomic yaw observation* afterwards, every ``nhc_interval_s`` of IMU time (in GNSS
   outages too) while the filter's horizontal speed is at least ``nhc_min_speed_mps`` and
   the mean yaw rate since the last one at most ``nhc_max_yaw_rate_rad_s``: the vehicle's
   lateral horizontal velocity is zero when it does not skid::

       z = 0 = h(x) = -sin(psi_v) v_N + cos(psi_v) v_E = |v_h| sin(chi - psi_v),
       psi_v = psi_b(q) - mu,   psi_b = atan2(C_10, C_00)   (C = C(q), scale-invariant)
       dh/dv_n = [-sin psi_v, cos psi_v, 0]
       dh/dq   = -(cos psi_v v_N + sin psi_v v_E) (C_00 dC_10/dq - C_10 dC_00/dq) / (C_00^2 + C_10^2)
       dC_10/dq = 2 [z, y, x, w],   dC_00/dq = 2 [w, x, -y, -z]

   It is the course-minus-heading observation ``chi - (psi_b - mu)`` scaled by ``|v_h|``: with
   GNSS velocity it ties the yaw to the course, in an outage it keeps the velocity along the
   vehicle's axis. ``R = sigma_0^2 + |v_h|^2 (sigma_slip^2 + sigma_mu^2) + (r L)^2``: a
   velocity floor, the sideslip angle and the mount error as angles, and the lateral velocity
   ``r L`` of an IMU at a distance ``L`` ahead of the rear axle while turning at ``r``. The
   mount error is common to all these observations (a bias, not white noise): the yaw
   converges to ``chi + mu`` with the error of ``mu`` while its variance falls below
   ``sigma_mu^2``, the aligner's fused sigma of the angle in use (at most ``max_std_rad``
   once accepted, up to 15 deg while provisional). The RTS smoother is not carried back across the re-initialisations of step 2 and
   the heading reset (zero transition recorded there). Singular where the sensor x axis is vertical (``psi_b`` undefined), as the
   aligner's levelled frame. The output attitude is then the vehicle's, ``C_nb R_z(mu)^T``.

GNSS error states (option ``gnss_error_states``, designed here; default off, the paper's form)
----------------------------------------------------------------------------------------------
The paper takes the GNSS position error as white in ``R``. A consumer receiver's is not: a
Gauss-Markov error of minutes seen through the receiver's own low-pass (the simulator's
``open-sky``: 150 s horizontal, 200 s vertical, through 2 s). The option appends the second-order
model of ``eskf`` (:mod:`iotnav.engines.eskf_models`, "GNSS error model (receiver smoothing)")
as six total states after ``SA``, ``GNE`` (22-24, the error ``e`` the fix carries) and ``GNM``
(25-27, the Gauss-Markov error ``e_gm`` before the receiver's filter), NED, m::

    d(e_gm)/dt = -e_gm / T_e + w,   de/dt = (e_gm - e) / t_f      (per axis)
    a = exp(-dt/T_e), b = exp(-dt/t_f):  e_gm' = a e_gm,  e' = b e + T_e (a - b) / (T_e - t_f) e_gm

discretised exactly over each prediction step (:func:`gnss_error_transition`; the estimates
propagate with it too), ``c = T_e (a - b) / (T_e - t_f)`` written without cancellation
(``(dt/t_f) a`` at ``t_f = T_e``). The process noise is integrated exactly: ``var(e_gm)(1 - a^2)``
on ``GNM`` and the ``O(dt^3)`` ``e`` part (closed form; within 0.1 % of ``t_f = T_e`` that of
``t_f = T_e``). ``t_f = 0``: ``GNE`` is the first-order Gauss-Markov error itself, ``GNM`` inert.
``T_e`` is ``gnss_corr_time_s`` (north, east) and ``gnss_corr_time_v_s`` (down), ``t_f``
``gnss_receiver_filter_s``; ``var(e_gm) =
sigma_e^2 (T_e + t_f) / T_e`` (Gelb 1974, sec. 3.8) so that ``e`` has the variance
``sigma_e^2`` of the fix. Per axis ``sigma_p`` is the fix's sigma as ``R`` above (hAcc / vAcc,
else DOP x UERE), ``sigma_e = sqrt(1 - f^2) sigma_p`` with ``f = gnss_white_fraction`` (0), and
``R`` keeps the white remainder ``max(f sigma_p, floor)^2``, the floor the larger of
``gnss_white_floor_m`` (5 mm) and the fix's output rounding
(:class:`~iotnav.engines.gnss_resolution.PositionResolution`, ``summary()["gnss_resolution"]``).
The measurements::

    position  z = r + e + w,                 H: I on POS, I on GNE
    velocity  z = v + (e_gm - e) / t_f + w_D,  H: I on VEL, -I/t_f on GNE, +I/t_f on GNM

(rows 0-1 for speed and course; ``R`` the white Doppler part, sAcc). The paper's 22-column
models are padded with zero columns (the TRIAD, norm and non-holonomic observations do not
depend on the GNSS error). At the end of the initialisation ``[GNE, GNM]`` start with the
stationary covariance (``var(e) = cov(e, e_gm) = sigma_e^2``, ``var(e_gm) = sigma_e^2 (T_e +
t_f) / T_e``), and the position, 0 at the mean of the initialisation's fixes, with the error of
that mean under the model, correlated with ``e`` (:meth:`QekfEngine._init_gnss_error`; taking
the paper's uncorrelated ``P_POS = R`` instead changed the Monte Carlo NEES below from 4.8 to
5.1, nothing else). The fallback's horizontal re-initialisations from a fix set ``r = z``,
``e = e_gm = 0`` with ``var(r) = var_e + var_w``, ``cov(r, e) = cov(r, e_gm) = -var_e``. The
prediction multiplies the 28 x 28 covariance by a block-diagonal ``F`` (about 5 % slower than
22 states: 3450 against 3650 samples/s on car-magnetometer).

Results (20 Monte Carlo runs of the tests, car-magnetometer 75 s, positions only; with the
simulator's receiver error): NEES (6 dof, interval 4.6-7.6) 4.8 / 5.5 on seeds 100 / 200 with
the option, 18.7 / 24.3 without; GNSS-position NIS (3 dof) 1.65 / 1.61 with (below its interval
2.0-4.0: the 1 s position prediction is good to about 8 cm and the accelerometer's white noise,
sized to cover unmodelled errors, then dominates ``S``), 0.33 / 0.36 without. The vertical
innovations become nearly white (Box-Pierce over lags 1-10 22.9 against chi-square(10) 18.3;
3173 without; 46 on seeds 200-219), the horizontal ones do not (443 / 957 against 6302 / 4091;
291 / 908 on seeds 200-219): each run keeps a mean horizontal innovation of 0.2-0.5 sigma.
These figures are with the vertical error's own correlation time (``gnss_corr_time_v_s``,
200 s as the simulator's; NEES 4.65 / 5.33, NIS 1.55 / 1.51, vertical Box-Pierce 18.4 / 41
with the horizontal 150 s for all axes).
*Causes*, one switch at a time on seeds 100-119 (Box-Pierce N / E / D; mean NEES, NIS):

* the magnetic reference: the tests give the filter the World Magnetic Model (2020.45:
  declination 2.59 deg, dip 61.11 deg), the simulator's field is 2.9 / 61.5 deg, a 0.3 deg
  heading bias nothing in the filter models. With the simulator's field in
  ``mag_field_n_ut``: 140 / 683 / 21.8 (4.73, 1.45; seeds 200-219: 259 / 690 / 44); in the
  paper form's white-error runs it is most of the north correlation (94.5 / 52.4 / 21.8 ->
  16.0 / 24.4 / 22.9);
* the accelerometer's turn-on bias (16.7 mg per axis, the modelled ``b_a``) through the TRIAD
  observations made while driving. With the simulator's field and that bias set to 0: 48 /
  144 / 23 (4.61, 1.30; seeds 200-219: 55 / 204 / 45). An IMU with no error but that bias:
  383 / 1573 / 20.5; twice the bias: 2266 / 2802 / 6.7; no error at all: 9.4 / 44 / 28; the
  bias with TRIAD only at a standstill (``triad_max_comp_mps2 = 0``): 47 / 48 / 28; with TRIAD
  only below 0.1 (0.3) m/s^2 of compensated acceleration: 286 / 1269 (320 / 1501). So it is
  not the vehicle-acceleration compensation (whose errors are the same with and without the
  bias: TRIAD error against its linear model 4 / 3 / 12 mrad RMS below 0.3 m/s^2, seeds
  100-104) but the observation of the tilt / bias combination while moving, worse the larger
  the bias; with the ``"noise"`` coupling it moves to north (668 / 110 / 26), with
  ``"jacobian"`` and all the IMU's errors the filter diverges (NEES 131). The filter is
  over-confident in the attitude and the horizontal accelerometer bias (error / sigma RMS per
  axis, seeds 100-109, simulator's field: attitude 1.9 / 2.4 / 1.5, ``b_a`` 2.9 / 2.7 / 0.9);
  the position NEES stays in its interval only through the inflated white noise. Within the
  paper's form no fix was found; the consistent form (below) drops the accelerometer from
  the attitude observation after the alignment, and is white;
* the simulator's cross-axis coupling (0.67 %, not modelled): with the simulator's field and
  without it 37 / 429 / 27 (accelerometer's alone removed 75 / 649, gyro's 82 / 509);
* the accelerometer's white noise (0.1 m/s^2/sqrt(Hz), 25 times the MPU-6050's): the gain is
  too high, the lag-1 correlation negative (vertical -0.07 to -0.14; all axes once the TRIAD
  correlation is gone: ``triad_max_comp_mps2 = 0`` 27 / 23 / 22, lag 1 -0.11 / -0.08 /
  -0.08); with 0.05 in addition 23 / 18 / 6.3 (4.93, 1.88; paper form, white-error runs 18 /
  19 / 12, NEES 4.70, NIS 2.82).

Not causes (same switches, WMM reference unless said): the non-holonomic observation (only in
the fallback: unchanged), the along-track acceleration (the truth's speed in place of the
filter's: 189 / 667 / 21, simulator's field), the GNSS velocity (used: 131 / 467 / 22,
simulator's field), and, each switched off in the simulator (simulator's field), the gyro's
turn-on bias (141 / 683), the bias instabilities (175 / 657), the scale factors (131 / 752),
the white noises (150 / 711); the vibration helps (off: 561 / 1733 / 16; it raises
``a_dyn`` and so the TRIAD sigma: the IMU with only the bias and the vibration 45 / 423 / 28);
neither does the norm pseudo-observation (``quat_norm_std`` 0.01: 232 / 1674 / 20) nor the
bias correction of the TRIAD gravity (``triad_bias_corrected=False``: 769 / 1055 / 15). The
simulator has no GNSS latency and no lever arm in these runs.

In the tests' white-error runs the option with the defaults is wrong by construction (NIS
190): the correlation time must be the receiver's (with 0.25 s and 0.1 s, the runs' values, it
is the paper's filter: NEES 5.4, NIS 3.1). Full car-magnetometer runs, seeds 0-8,
without / with the option: yaw RMS 0.59, 0.78, 1.41, 1.00, 1.39, 0.76, 1.57, 0.52, 1.69 /
0.62, 0.96, 1.26, 1.05, 1.34, 0.76, 1.61, 0.54, 1.59 deg (mean 1.08 both), roll and pitch
within 0.1 deg of each other, largest error in the 4 s gap 3.3, 1.9, 1.5, 1.1, 2.0, 2.9,
2.2, 2.5, 3.8 / 3.2, 4.6, 4.8, 1.0, 2.6, 2.4, 1.4, 2.4, 3.5 m. car-tunnel seed 0 (330 s, no
magnetometer): drift 1.10 / 0.66 % against 0.71 / 0.68 %, horizontal RMS 7.9 / 8.1 m (1.8 m
both outside the outages). The absolute GNSS error stays unobservable: the option makes the
filter consistent, not the track more accurate.

Consistent form (:meth:`QekfConfig.consistent`; designed here, the paper's form stays the default)
--------------------------------------------------------------------------------------------------
Three changes, each a model of something the paper's filter leaves out, no tuning:

* ``mag_observation = "direction"``: after the initial alignment the attitude observation is
  the magnetometer's field direction alone (:func:`mag_direction_measurement`, 2 dof), not the
  TRIAD of gravity and field. The accelerometer's samples are then used once, in the
  prediction; the TRIAD observation used them twice (its gravity is ``-f`` minus a
  compensation built from the filter's own velocity and the GNSS speed rate), with errors
  correlated over a manoeuvre and with the prediction's. The tilt is observed through the
  GNSS positions, as in any loosely coupled INS; the heading through the field and the GNSS.
* ``gyro_misalignment``, ``acc_misalignment``: the cross-axis coupling enters ``Q`` as in
  ``eskf``: per sensor axis the gyro's white-noise intensity grows by ``k_w (|w|^2 - w_i^2)``
  and the accelerometer-bias random walk by ``k_a (|a|^2 - a_i^2)``, ``k_w = 2 m_g^2 tau``,
  ``k_a = 2 m_a^2 / tau`` (a process correlated over a manoeuvre of ``tau`` =
  ``cross_axis_corr_time_s``), ``w`` the corrected rate and ``a = f + C^T g_n`` the kinematic
  acceleration in ``b``.
* the IMU's datasheet white noises (MPU-6050: 400 ug/sqrt(Hz), 5 mdps/sqrt(Hz)) instead of
  the paper form's 0.1 m/s^2/sqrt(Hz) and 3e-4 rad/s/sqrt(Hz), which were sized to cover the
  errors above; and ``gnss_error_states`` for a real receiver.

Results, 20 Monte Carlo runs of the tests (car-magnetometer 75 s, positions only, the World
Magnetic Model's reference 0.3 deg off the simulator's field), seeds 100-119 (held-out
200-219), mean NEES (6 dof, interval 4.6-7.6), mean GNSS-position NIS (3 dof, 2.0-4.0),
Box-Pierce N / E / D over lags 1-10 (chi-square(10) 18.3 each, 21.7 for the three together
at 95 %, the tests' criterion):

* white GNSS errors, GNSS error states off: 5.83, 2.95, 8.4 / 8.7 / 13.7 (5.55, 2.91, 10.8 /
  17.9 / 10.9); the paper's form 5.58, 3.08, 94.5 / 52.4 / 21.8;
* the simulator's receiver error, GNSS error states on: 5.41, 2.89, 5.9 / 14.2 / 5.2 (5.98,
  2.88, 13.0 / 14.9 / 17.6); the paper's form with its GNSS error states 4.79, 1.65, 443 /
  957 / 22.9. With one correlation time for all axes (150 s, before ``gnss_corr_time_v_s``):
  5.23, 2.67, 6.1 / 14.2 / 4.5 (5.84, 2.65, 13.0 / 14.8 / 16.3).

One change at a time (seeds 100-119, white errors, N / E / D): the direction observation
alone 23.9 / 28.6 / 22.2 (NEES 4.63; with the simulator's field 19.2 / 15.9 / 22.7, lag 1
-0.07 north: the paper's white noise is too large once nothing is left for it to cover); the
cross-axis noise alone 34.4 / 77.3 / 23.3; the TRIAD kept, a perfect IMU and magnetometer in
the simulator, its field in the filter and 0.03 m/s^2/sqrt(Hz): 15.7 / 78.9 / 12.4, with no
TRIAD observation while moving 28.3 / 27.1 / 11.9 (lag 1 -0.09 / -0.06: the remaining white
noise too large for a perfect IMU). So the TRIAD observations made while driving correlate
the innovations even without sensor errors, through their acceleration compensation; with
the IMU's turn-on bias the more (causes of the paper's form above). The smaller white noise
needs the other two changes: with the TRIAD and the simulator's field, 0.05 and 0.03
m/s^2/sqrt(Hz) gave 20.2 / 107 / 14.4 and 28.5 / 177 / 11.8.

Full car-magnetometer runs, seeds 0-8 (GNSS velocity, magnetic disturbance, 4 s gap): roll /
pitch / yaw RMS mean 0.39 / 0.33 / 0.74 deg (largest yaw 0.88) against the paper form's 0.56 /
0.45 / 1.08 (1.69); largest error in the gap 1.6-3.7 m (paper form 1.1-3.8 m); horizontal
RMS 1.44 m against 1.77 m. Without GNSS velocity (positions only, NMEA GGA) 0.39 / 0.34 /
0.75 deg, RMS 0.9-2.0 m. The magnetometer's disturbance tests (norm, dip) are the same in
both forms.

Two changes of the GNSS error states came with it (both forms): the states follow a jump of
the reported accuracy (:meth:`QekfEngine._scale_gnss_error`, as ``eskf``, with the
figures' rounding low-passed), and a forced
position update without a GNSS velocity widens the velocity by the disagreement over the
time since the last accepted fix. The consistent form's white ``R`` is the fixes' rounding,
so after the 4 s gap, where the simulated receiver's error triples, it rejected every fix
for a minute (forced updates widened the position only): car-magnetometer without GNSS
velocity, RMS 5.5-14.3 m on five of nine seeds; now 0.9-2.0 m on all. With GNSS velocity the
RTS smoother had made the consistent form worse (8 seeds after 45 s: 2.02 -> 2.54 m; the
jump spread back over the error's 150 s correlation); now 1.47 -> 1.27 m.

Smoothing across an outage (both forms): the first fix after an outage (``reacquire_after_s``)
is forced, the position covariance widened by the disagreement. The widening is the filter's
remedy for a drift beyond its model, not a jump of the true position, so the smoother's
record of that fix gets the un-widened prior, as ``eskf``'s gate reset (recorded with the
widened prior, the exit fix barely corrected the outage behind it). car-tunnel seeds 0-3, 20
tunnels: the smoothed largest error inside a tunnel was at most a quarter of the forward one
in 9 of 20 for either form, now in 13; smoothed RMS after 45 s, paper form 1.83 -> 1.55 m,
consistent form 1.41 -> 1.47 m (seed 3's 60 s tunnel, 63 m forward, 3.7 -> 5.4 m smoothed).
The rest miss where the forward error is near the GNSS floor (12 s tunnel: 1-5 m). Forced
fixes after a run of rejected ones (no outage) keep the widened prior.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any, cast

import numpy as np
import numpy.typing as npt

from iotnav import kalman
from iotnav.engines import qekf_kernel as K
from iotnav.engines import qekf_updates_kernel as KU
from iotnav.engines.anchor import gnss_position_noise_source
from iotnav.engines.base import (
    C_T,
    SRC_NONE,
    GnssSample,
    ImuSample,
    InputGuard,
    MagSample,
    OneSampleBlock,
    Output,
    OutputBlock,
    Sample,
)
from iotnav.engines.config import PIPELINE_MOUNT_NAV, dataclass_from_dict, read_toml
from iotnav.engines.eskf_models import gm_variance_factor, stationary_gnss_error_cov
from iotnav.engines.gnss_resolution import AccuracyScaling, PositionResolution
from iotnav.engines.smoother import CORR_ATT, CORR_POS, CORR_STD, CORR_VEL, SmoothingLog
from iotnav.eval.consistency import InnovationLog
from iotnav.geo import LocalFrame, ecef_to_geodetic, geodetic_to_ecef, normal_gravity, skew
from iotnav.gnss_accuracy import position_sigmas
from iotnav.techniques.mount import MountAligner, MountConfig, wrap
from iotnav.techniques.triad import dcm_to_quat, improved_triad, quat_to_dcm, triad_covariance, triad_jacobian
from iotnav.wmm import log_year, reference_field

FloatArray = npt.NDArray[np.float64]

__all__ = [
    "BA",
    "BG",
    "GNE",
    "GNM",
    "N_STATES",
    "N_STATES_GNSS",
    "POS",
    "Q_NB",
    "SA",
    "SG",
    "VEL",
    "QekfConfig",
    "QekfEngine",
    "datasheet_noises",
    "gnss_error_transition",
    "nhc_measurement",
    "propagate",
    "wmm_field_n",
]

#: State layout.
Q_NB = slice(0, 4)
VEL = slice(4, 7)
POS = slice(7, 10)
BG = slice(10, 13)
BA = slice(13, 16)
SG = slice(16, 19)
SA = slice(19, 22)
N_STATES = 22
#: GNSS position error states of ``gnss_error_states`` (module docstring), NED, m: the error
#: the fix carries (after the receiver's low-pass) and the Gauss-Markov error before it.
GNE = slice(22, 25)
GNM = slice(25, 28)
N_STATES_GNSS = 28
_GNE_I = np.arange(GNE.start, GNE.stop)
_GNM_I = np.arange(GNM.start, GNM.stop)

_I3 = np.eye(3)
_G0 = 9.80665  # standard gravity, the datasheets' g, m/s^2


def datasheet_noises(
    acc_noise_density_ug_rthz: float = 400.0, gyro_noise_density_mdps_rthz: float = 5.0
) -> dict[str, float]:
    """:class:`QekfConfig` white noises from an IMU's datasheet densities (the units of
    ``eskf``'s configuration and the dataset profiles; defaults: the MPU-6050's).

    Parameters
    ----------
    acc_noise_density_ug_rthz : float
        Accelerometer noise density, ug/sqrt(Hz).
    gyro_noise_density_mdps_rthz : float
        Gyro noise density, mdps/sqrt(Hz).

    Returns
    -------
    dict
        ``acc_noise_mps2_rthz`` (m/s^2/sqrt(Hz)) and ``gyro_noise_rad_s_rthz`` (rad/s/sqrt(Hz)).
    """
    return {
        "acc_noise_mps2_rthz": acc_noise_density_ug_rthz / 1e6 * _G0,
        "gyro_noise_rad_s_rthz": math.radians(gyro_noise_density_mdps_rthz / 1e3),
    }


#: The accelerometer's error states (bias and scale factor, Eq. 11): their estimation error
#: enters every TRIAD observation and the initial alignment alike (module docstring).
_ACC_COLS = np.r_[BA, SA]
_CONJ = np.array([1.0, -1.0, -1.0, -1.0])


@dataclass(frozen=True)
class QekfConfig:
    """Tunables of the quaternion EKF (SI; the paper selected Q and R experimentally).

    Attributes
    ----------
    init_duration_s : float
        Static initialisation period from the first IMU sample, s (paper: 40 s).
    init_max_speed_mps, init_max_displacement_m : float
        The initialisation ends early (the device is no longer still) at the first fix more
        than ``init_max_displacement_m`` from the mean fix with a GNSS speed above
        ``init_max_speed_mps``; the averages then stop one GNSS interval before the last speed
        below it (m/s, m; 0 disables).
    gyro_noise_rad_s_rthz, acc_noise_mps2_rthz : float
        White-noise densities of gyro (rad/s/sqrt(Hz)) and accelerometer (m/s^2/sqrt(Hz)),
        including vibration and unmodelled errors.
    gyro_bias_rw_rad_s2_rthz, acc_bias_rw_mps3_rthz : float
        Bias random-walk densities.
    scale_rw_1_s_rthz : float
        Scale-factor random-walk density, 1/sqrt(s).
    gyro_bias_init_rad_s, acc_bias_init_mps2 : float
        Initial bias standard deviations (gyro bias after the static average).
    scale_init : float
        Initial scale-factor standard deviation (dimensionless).
    init_att_std_rad, init_vel_std_mps : float
        Initial attitude and velocity standard deviations.
    uere_m, default_dop : float
        UERE (m) multiplying the DOPs when the receiver gives no hAcc, and the HDOP assumed when
        it gives neither (:mod:`iotnav.gnss_accuracy`).
    vel_noise_mps : float
        GNSS velocity sigma per component when no sAcc is reported, m/s.
    min_course_speed_mps : float
        Speed and course give a velocity only above this speed, m/s.
    min_satellites : int
        Fixes need at least this many satellites.
    gate_probability : float
        Chi-square probability of the NIS gates (0 disables them).
    max_rejections : int
        After this many consecutive gated GNSS positions (or velocities) the next is accepted,
        the position (velocity) covariance first widened by its variance and by the outer
        product of its innovation
        (re-convergence in one step; adding the variance alone halved a 100 m error per
        forced fix, which took half a minute after a 60 s outage on the real drive).
    reacquire_after_s : float
        A fix that comes more than this long after the last accepted one (a GNSS outage) is
        taken the same way at once, s: the dead-reckoned position may be far off, and five
        gated epochs of it were the largest errors outside the outages on the real drive.
    acc_dir_std_rad : float
        Direction sigma of gravity from the accelerometer when quiet, rad.
    mag_dir_std_rad : float
        Direction sigma of the calibrated magnetic field, rad.
    dyn_acc_factor : float
        Gravity-direction sigma grows by ``dyn_acc_factor * a_dyn / g`` (``a_dyn`` the
        remaining dynamic acceleration ``| |g_b| - g |``, m/s^2).
    comp_rel_error : float
        Relative error of the vehicle-acceleration compensation ``|a_b|`` (speed, sideslip and
        lever arm, a priori 10 %); adds ``comp_rel_error |a_b| / g`` to the gravity-direction sigma.
    triad_max_comp_mps2 : float
        No TRIAD observation over an interval whose mean estimated vehicle acceleration
        ``|a_b|`` (the compensation removed from the accelerometer) exceeds this, m/s^2: there
        the gravity direction carries the compensation's errors (sideslip, lever arm, the
        speed-difference noise), which are systematic over a manoeuvre and so not the white
        noise the observation model assumes; the gyros carry the attitude through. Counted in
        ``summary()["triad_skipped"]``.
    mag_norm_tol, mag_dip_tol_rad : float
        Magnetometer refused when ``| |m| / |m_ref| - 1 |`` or the dip-angle error exceed these.
    quat_norm_std : float
        Sigma of the norm pseudo-observation and of the norm direction in ``R_q``.
    mag_field_n_ut : tuple of float or None
        Reference field in NED, microtesla; None: World Magnetic Model at the origin.
    wmm_year : float or None
        Decimal year for the World Magnetic Model; None (default): the log's date at the
        first fix (:func:`iotnav.wmm.log_year`; the WMM2025 epoch when the log has no date).
        The field used and where its year came from are in ``summary()["mag_reference"]``.
    mag_hard_iron_ut : tuple of float
        Hard-iron offset ``h`` (uT) of the calibration ``m = S^-1 (m~ - h)``.
    mag_soft_iron : tuple of float or None
        Soft-iron matrix ``S`` (row-major, 9 values); None: identity.
    gravity_mps2 : float
        Gravity magnitude; 0 uses WGS84 normal gravity at the origin.
    use_mag : bool
        Use the magnetometer (the TRIAD observation) after the initialisation.
    use_gnss_velocity : bool
        Use the GNSS velocity (update, and speed rate in the gravity compensation).
    triad_bias_corrected : bool
        Correct the accelerometer by the estimated bias before TRIAD (False: raw, the bias
        then counts in ``acc_dir_std_rad``; avoids feeding the bias estimate back as if the
        observation were independent of it).
    triad_state_coupling : str
        How the TRIAD observation's dependence on the estimated biases, scale factors and
        velocity enters (module docstring): ``"accelerometer"`` (default; accelerometer bias and
        scale factor in ``H``, the compensation's states as noise), ``"noise"`` (all as noise)
        or ``"jacobian"`` (all in ``H``).
    smoothing : bool
        Keep a :class:`~iotnav.engines.smoother.SmoothingLog` for the RTS smoother (``iotnav run
        --smooth`` turns it on; 22 states: about 12 KB a record); off by default.
    record_every : int
        IMU rows between smoothing records without a measurement.
    mount : MountConfig
        Mount-yaw aligner of the no-magnetometer fallback (module docstring).
    heading_min_speed_mps : float
        Fallback heading reset: minimum GNSS speed, m/s.
    heading_max_yaw_rate_rad_s : float
        Fallback heading reset: maximum mean yaw rate over the GNSS interval, rad/s.
    nhc_interval_s : float
        Period of the non-holonomic observation (0 disables it), s.
    nhc_min_speed_mps : float
        Minimum horizontal speed of the filter for the non-holonomic observation, m/s.
    nhc_max_yaw_rate_rad_s : float
        Maximum mean yaw rate since the previous non-holonomic observation, rad/s.
    nhc_vel_std_mps : float
        Lateral-velocity floor sigma ``sigma_0``, m/s.
    nhc_sideslip_std_rad : float
        Sideslip angle sigma (a car below 2-3 m/s^2 of lateral acceleration: about 1 deg), rad.
    nhc_lever_m : float
        Assumed distance ``L`` of the IMU from the rear axle (lateral velocity ``r L`` in turns), m.
    gnss_error_states : bool
        Carry the time-correlated GNSS position error as 6 more states (``GNE``, ``GNM``; 28 in
        all), the second-order model of :mod:`iotnav.engines.eskf_models` (module docstring,
        "GNSS error states"); False: the paper's 22 states, the GNSS error white in ``R``.
    gnss_corr_time_s : float
        With ``gnss_error_states``: correlation time ``T_e`` of the horizontal Gauss-Markov GNSS
        position error before the receiver's smoothing, s (the simulator's ``open-sky``
        horizontal value).
    gnss_corr_time_v_s : float
        The same for the vertical error, s (the simulator's ``open-sky`` vertical value; as
        ``eskf``'s ``gnss_corr_time_v_s``).
    gnss_receiver_filter_s : float
        With ``gnss_error_states``: time constant ``t_f`` of the receiver's first-order position
        smoothing, s (0: none, ``GNE`` is then the Gauss-Markov error itself, ``GNM`` inert).
    gnss_white_fraction : float
        With ``gnss_error_states``: fraction ``f`` of the fix's position sigma taken as white
        (in ``R``); the rest, ``sqrt(1 - f^2) sigma_p``, is the correlated error of the states.
    gnss_white_floor_m : float
        With ``gnss_error_states``: floor of the white part's sigma per axis, m (raised to the
        output rounding's sigma, :class:`~iotnav.engines.gnss_resolution.PositionResolution`).
    gnss_error_scales_with_accuracy : bool
        With ``gnss_error_states``: the correlated error's estimates and covariance follow the
        fix's reported sigma (a receiver re-acquiring after a tunnel reports a larger accuracy
        and is that much further off; :meth:`QekfEngine._scale_gnss_error`).
    mag_observation : str
        Attitude observation after the initial alignment: ``"triad"`` (the paper's improved
        TRIAD of gravity and field, Eq. 7; skipped above ``triad_max_comp_mps2``) or
        ``"direction"`` (the magnetometer's field direction alone, 2 dof, the accelerometer then
        used once, in the prediction; module docstring, "Consistent form"). The initial
        alignment is TRIAD in both.
    gyro_misalignment, acc_misalignment : float
        1-sigma cross-axis coupling of gyro and accelerometer, each off-diagonal element,
        dimensionless (0.01 = 1 %); not estimated, it enters ``Q`` as rate-dependent gyro noise
        and acceleration-dependent accelerometer-bias noise (as in ``eskf``,
        :mod:`iotnav.engines.eskf_models`). 0: left out (the paper's form).
    cross_axis_corr_time_s : float
        Correlation time of the motion that the cross-axis errors scale (a manoeuvre), s.
    """

    init_duration_s: float = 40.0
    init_max_speed_mps: float = 0.5
    init_max_displacement_m: float = 10.0
    gyro_noise_rad_s_rthz: float = 3e-4
    acc_noise_mps2_rthz: float = 0.1
    gyro_bias_rw_rad_s2_rthz: float = 2e-5
    acc_bias_rw_mps3_rthz: float = 1e-3
    scale_rw_1_s_rthz: float = 1e-5
    gyro_bias_init_rad_s: float = 2e-3
    acc_bias_init_mps2: float = 0.2
    scale_init: float = 0.01
    init_att_std_rad: float = 0.03
    init_vel_std_mps: float = 0.1
    uere_m: float = 2.0
    default_dop: float = 2.0
    vel_noise_mps: float = 0.15
    min_course_speed_mps: float = 2.0
    min_satellites: int = 5
    gate_probability: float = 0.9999
    max_rejections: int = 5
    reacquire_after_s: float = 10.0
    acc_dir_std_rad: float = 0.02
    mag_dir_std_rad: float = 0.015
    dyn_acc_factor: float = 1.5
    comp_rel_error: float = 0.1
    triad_max_comp_mps2: float = 1.0
    mag_norm_tol: float = 0.1
    mag_dip_tol_rad: float = 0.07
    quat_norm_std: float = 1e-3
    mag_field_n_ut: tuple[float, float, float] | None = None
    wmm_year: float | None = None
    mag_hard_iron_ut: tuple[float, float, float] = (0.0, 0.0, 0.0)
    mag_soft_iron: tuple[float, ...] | None = None
    gravity_mps2: float = 0.0
    use_mag: bool = True
    use_gnss_velocity: bool = True
    triad_bias_corrected: bool = True
    triad_state_coupling: str = "accelerometer"
    smoothing: bool = False
    record_every: int = 5
    mount: MountConfig = PIPELINE_MOUNT_NAV
    heading_min_speed_mps: float = 5.0
    heading_max_yaw_rate_rad_s: float = 0.03
    nhc_interval_s: float = 1.0
    nhc_min_speed_mps: float = 5.0
    nhc_max_yaw_rate_rad_s: float = 0.1
    nhc_vel_std_mps: float = 0.05
    nhc_sideslip_std_rad: float = 0.02
    nhc_lever_m: float = 1.5
    gnss_error_states: bool = False
    gnss_corr_time_s: float = 150.0
    gnss_corr_time_v_s: float = 200.0
    gnss_receiver_filter_s: float = 2.0
    gnss_white_fraction: float = 0.0
    gnss_white_floor_m: float = 0.005
    gnss_error_scales_with_accuracy: bool = True
    mag_observation: str = "triad"
    gyro_misalignment: float = 0.0
    acc_misalignment: float = 0.0
    cross_axis_corr_time_s: float = 5.0

    def to_dict(self) -> dict[str, Any]:
        """Plain dict (for ``summary.json``)."""
        return dataclasses.asdict(self)

    @classmethod
    def consistent(cls, **overrides: Any) -> QekfConfig:
        """The consistent form (module docstring): magnetometer direction observations, the
        IMU's datasheet noises and cross-axis coupling in ``Q``, GNSS error states.

        Defaults are the MPU-6050's datasheet values (PS-MPU-6000A-00 Rev 3.4: accelerometer
        400 ug/sqrt(Hz), gyro 5 mdps/sqrt(Hz), cross-axis +/-2 % read as 3 sigma, as ``eskf``
        reads them); put your IMU's in ``overrides``, with any other field.

        Parameters
        ----------
        **overrides
            :class:`QekfConfig` fields that replace these settings or the defaults.

        Returns
        -------
        QekfConfig
            The configuration.
        """
        settings: dict[str, Any] = {
            "mag_observation": "direction",
            **datasheet_noises(),
            "gyro_misalignment": 0.02 / 3.0,
            "acc_misalignment": 0.02 / 3.0,
            "gnss_error_states": True,
        }
        settings.update(overrides)
        return cls(**settings)

    @classmethod
    def from_toml(cls, path: str | Path) -> QekfConfig:
        """Load ``[qekf]`` (or the top-level keys) from a TOML file.

        ``form = "consistent"`` starts from :meth:`consistent` instead of the paper's form
        (``form = "paper"``, the default); the other keys replace fields of either.

        Raises
        ------
        ValueError
            For an unknown form or key, or a TOML syntax error (naming the file).
        """
        data = read_toml(path)
        raw = data.get("qekf", data)
        if not isinstance(raw, dict):
            raise ValueError(f"{path}: qekf must be a table, got {raw!r}")
        table = dict(raw)
        form = table.pop("form", "paper")
        if form not in ("paper", "consistent"):
            raise ValueError(f"{path}: qekf.form must be 'paper' or 'consistent', got {form!r}")
        base = cls.consistent() if form == "consistent" else cls()
        try:
            return cast(QekfConfig, dataclass_from_dict(base, table, "qekf"))
        except (TypeError, ValueError) as exc:
            raise ValueError(f"{path}: {exc}") from exc


# ----------------------------------------------------------------------------- quaternion algebra


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
    """One prediction step (module docstring) with its Jacobians.

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


# ----------------------------------------------------------------------------- GNSS error model


def gnss_error_transition(dt: float, corr_time_s: float, filter_s: float) -> tuple[FloatArray, FloatArray]:
    """Exact discretisation of one axis of the GNSS error model over ``dt`` (module docstring).

    State ``[e, e_gm]`` (the error the fix carries, the Gauss-Markov error before the receiver's
    low-pass): ``d(e_gm)/dt = -e_gm / T_e + w``, ``de/dt = (e_gm - e) / t_f``.

    Parameters
    ----------
    dt : float
        Step, s.
    corr_time_s : float
        Correlation time ``T_e`` of ``e_gm``, s.
    filter_s : float
        Receiver filter time constant ``t_f``, s; 0: none (``e`` is then the Gauss-Markov
        process itself and ``e_gm`` is inert).

    Returns
    -------
    Phi : numpy.ndarray
        Transition (2, 2): ``[[b, c], [0, a]]``, ``a = exp(-dt/T_e)``, ``b = exp(-dt/t_f)``,
        ``c = T_e (a - b) / (T_e - t_f)`` (``(dt / t_f) a`` when ``t_f = T_e``).
    Q : numpy.ndarray
        Process noise (2, 2) per unit ``var(e_gm)`` (driving intensity ``2 var(e_gm) / T_e``),
        integrated exactly; its ``e_gm`` element is ``1 - a^2``. Without a receiver filter
        ``[[1 - a^2, 0], [0, 0]]`` per unit ``var(e)``.
    """
    g = np.empty(6)
    K.gnss_error_step(dt, corr_time_s, filter_s, g)  # the engine's compiled prediction uses it too
    b, c, a, q_ee, q_eg, q_gg = g.tolist()
    return np.array([[b, c], [0.0, a]]), np.array([[q_ee, q_eg], [q_eg, q_gg]])


def _gnss_error_correlation(lag_s: FloatArray, corr_time_s: float, filter_s: float) -> FloatArray:
    """Autocorrelation ``cov(e(t), e(t + L)) / var(e)`` of the model's ``e`` at lags ``L >= 0``."""
    L = np.abs(lag_s)
    Te, tf = corr_time_s, filter_s
    if tf <= 0.0:
        return np.exp(-L / Te)
    if abs(Te - tf) <= 1e-6 * Te:
        return (1.0 + L / Te) * np.exp(-L / Te)
    return (Te * np.exp(-L / Te) - tf * np.exp(-L / tf)) / (Te - tf)


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

    Used by ``mag_observation = "direction"`` (module docstring, "Consistent form"): unlike
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
        ``R += J_n P J_n^T`` with ``J_n`` those columns of ``J_x`` (module docstring).
    exact_cols : numpy.ndarray of int or None
        With ``P``: state indices whose dependence goes into ``H`` all the same (the
        accelerometer's bias and scale factor in the engine's default coupling).
    """
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
    (module docstring; m/s). ``sigma_mps`` is the lateral-velocity sigma.
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


def _rotvec(C: FloatArray) -> FloatArray:
    """Rotation vector of a rotation matrix (small and large angles)."""
    c = max(-1.0, min(1.0, 0.5 * (np.trace(C) - 1.0)))
    ang = math.acos(c)
    v = np.array([C[2, 1] - C[1, 2], C[0, 2] - C[2, 0], C[1, 0] - C[0, 1]])
    if ang < 1e-6:
        return 0.5 * v
    return v * (ang / (2.0 * math.sin(ang)))


class _Slot:
    """An engine attribute kept in the compiled kernels' scalar state ``st`` at index ``i``
    (:mod:`iotnav.engines.qekf_kernel`, ``S_*``), read as ``kind``."""

    def __init__(self, i: int, kind: type = float) -> None:
        self.i, self.kind = i, kind

    def __get__(self, obj: Any, owner: Any = None) -> Any:
        return self.kind(obj.st[self.i])

    def __set__(self, obj: Any, value: float) -> None:
        obj.st[self.i] = value


class _VecSlot:
    """An engine vector attribute kept in the compiled kernels' ``_vec`` at ``[i : i + m]``
    (:mod:`iotnav.engines.qekf_kernel`, ``V_*``): read as a view, assigned by copying in."""

    def __init__(self, i: int, m: int) -> None:
        self.i, self.m = i, m

    def __get__(self, obj: Any, owner: Any = None) -> FloatArray:
        return cast(FloatArray, obj._vec[self.i : self.i + self.m])

    def __set__(self, obj: Any, value: FloatArray) -> None:
        obj._vec[self.i : self.i + self.m] = value


class QekfEngine:
    """Streaming 22-state quaternion EKF (28 with ``gnss_error_states``; see the module docstring).

    The per-IMU-sample work (prediction, gravity accumulation, output row) runs in the compiled
    kernels of :mod:`iotnav.engines.qekf_kernel`: :meth:`imu_block` over a block of samples and
    ``step(ImuSample)`` over a one-sample block, so batch and streaming execute the same code.

    Parameters
    ----------
    config : QekfConfig, optional
        Tunables.
    record_innovations : bool, optional
        Keep the innovation and its covariance of every GNSS position and velocity update in
        :attr:`innovations` (``gnss_pos``, ``gnss_vel``; :class:`~iotnav.eval.consistency.InnovationLog`).
    """

    # scalar state shared with the compiled kernels (qekf_kernel.S_*)
    t_x = _Slot(K.S_T_X)
    have_imu = _Slot(K.S_HAVE_IMU, bool)
    t_speed = _Slot(K.S_T_SPEED)
    v_speed = _Slot(K.S_V_SPEED)
    a_long = _Slot(K.S_A_LONG)
    a_long_std = _Slot(K.S_A_LONG_STD)
    _n_interval = _Slot(K.S_N_INTERVAL, int)  # IMU samples since the last GNSS epoch
    _f_n = _Slot(K.S_F_N, int)  # samples in _f_sum
    _acc_mag_n = _Slot(K.S_ACC_MAG_N, int)
    _a_dyn_sum = _Slot(K.S_A_DYN_SUM)
    _a_comp_sum = _Slot(K.S_A_COMP_SUM)
    _comp_var_sum = _Slot(K.S_COMP_VAR_SUM)  # variance of the acceleration compensation, summed like g_b
    t_fix = _Slot(K.S_T_FIX)
    _rows = _Slot(K.S_ROWS, int)  # IMU rows since the last smoothing record
    t_nhc = _Slot(K.S_T_NHC)
    fallback = _Slot(K.S_FALLBACK, bool)
    heading_ok = _Slot(K.S_HEADING_OK, bool)

    @property
    def _prior(self) -> tuple[FloatArray, FloatArray] | None:
        """The state before the updates since the last smoothing record (None: no update)."""
        return self._prior_xP

    @_prior.setter
    def _prior(self, value: tuple[FloatArray, FloatArray] | None) -> None:
        self._prior_xP = value
        self.st[K.S_PRIOR] = value is not None

    # vector state shared with the compiled kernels (qekf_kernel.V_*): the latest IMU sample
    # held over the step (m/s^2, rad/s); the specific force summed while moving since the last
    # GNSS epoch and its mean over the interval before (the zero-lag along-track acceleration,
    # _speed_rate; m/s^2); the compensated gravity since the last magnetometer sample (m/s^2);
    # var(e_gm) per NED axis (m^2); the fallback's yaw-rate sum (rad/s) and count since the
    # last epoch and since the last non-holonomic observation
    acc = _VecSlot(K.V_ACC, 3)
    gyro = _VecSlot(K.V_GYRO, 3)
    _f_sum = _VecSlot(K.V_F_SUM, 3)
    _f_ref = _VecSlot(K.V_F_REF, 3)
    _acc_mag_sum = _VecSlot(K.V_G_SUM, 3)
    _var_gm = _VecSlot(K.V_VAR_GM, 3)
    _r_gnss = _VecSlot(K.V_R_GNSS, 2)
    _r_nhc = _VecSlot(K.V_R_NHC, 2)

    def __init__(self, config: QekfConfig | None = None, *, record_innovations: bool = False) -> None:
        self.config = c = config or QekfConfig()
        #: scalar and vector state of the compiled kernels (qekf_kernel.S_*, V_*); the attributes
        #: above and the vectors below are views of them
        self.st = np.zeros(K.N_ST)
        self.st[K.S_GE_DT] = math.nan
        self._vec = np.zeros(K.N_VEC)
        self._one = OneSampleBlock()
        self.events: list[dict[str, Any]] = []
        #: GNSS position and velocity innovations and ``S`` of every attempted update, kept
        #: with ``record_innovations`` (whiteness checks, :mod:`iotnav.eval.consistency`)
        self.innovations: dict[str, InnovationLog] = (
            {"gnss_pos": InnovationLog(3), "gnss_vel": InnovationLog(3)} if record_innovations else {}
        )
        self.guard = InputGuard(self.events)
        #: ``utc = t + utc_offset_s`` (set by :func:`run_batch` from the log): the WMM's date
        self.utc_offset_s = math.nan
        self.mag_reference: dict[str, Any] | None = None
        #: state count: 22, or 28 with ``gnss_error_states`` (GNE, GNM after SA)
        self.n = N_STATES_GNSS if c.gnss_error_states else N_STATES
        self.x = np.zeros(self.n)
        self.x[0] = 1.0
        self.x[SG] = 1.0
        self.x[SA] = 1.0
        self.P = np.eye(self.n) * 1e-6
        #: output resolution of the GNSS positions (the white floor of ``gnss_error_states``)
        self.resolution = PositionResolution()
        # gnss_error_states: per-axis var(e) and var(e_gm) of the latest fix (m^2), its white
        # variance (R), and the initialisation's fix times and summed white variances
        self._var_e = np.zeros(3)
        # the latest fix's figures behind its sigma (gnss_position_noise_source), and how the
        # error states follow the reported accuracy (_scale_gnss_error)
        self._noise_kind: tuple[str, str] | None = None
        self._scaling = AccuracyScaling()
        # correlation time of the GNSS error per NED axis, s
        self._te = np.array([c.gnss_corr_time_s, c.gnss_corr_time_s, c.gnss_corr_time_v_s])
        self._var_white = np.zeros(3)
        self._init_fix_t: list[float] = []
        self._init_var_white = np.zeros(3)
        # F and Q of the latest prediction step (n x n; written by the compiled prediction)
        self._F_full = np.eye(self.n)
        self._Q_full = np.zeros((self.n, self.n))
        if c.mag_observation not in ("triad", "direction"):
            raise ValueError(
                f"qekf.mag_observation must be 'triad' or 'direction', got {c.mag_observation!r}"
            )
        tau = c.cross_axis_corr_time_s
        if not tau > 0.0:
            raise ValueError(f"qekf.cross_axis_corr_time_s must be > 0 s, got {tau}")
        # cross-axis coupling intensities (eskf_models): 2 m_g^2 tau, 2 m_a^2 / tau
        self._k_w = 2.0 * c.gyro_misalignment**2 * tau
        self._k_a = 2.0 * c.acc_misalignment**2 / tau
        #: constant tunables of the compiled kernels (qekf_kernel.K_*)
        self._prm = np.array(
            [
                c.gyro_noise_rad_s_rthz**2,
                c.acc_noise_mps2_rthz**2,
                c.gyro_bias_rw_rad_s2_rthz**2,
                c.acc_bias_rw_mps3_rthz**2,
                c.scale_rw_1_s_rthz**2,
                self._k_w,
                self._k_a,
                c.comp_rel_error,
                float(c.triad_bias_corrected),
                c.gnss_corr_time_s,
                c.gnss_corr_time_v_s,
                c.gnss_receiver_filter_s,
                float(c.smoothing),
                float(c.record_every),
                c.nhc_interval_s,
            ]
        )
        self.initialised = False
        self.frame: LocalFrame | None = None
        self.r_e0 = np.zeros(3)
        self.C_en = np.eye(3)
        self._geo = np.zeros(12)  # r_e0 and C_en (row-major) for the kernels' output rows
        self.g_n = np.array([0.0, 0.0, 9.80665])
        self.m_n = np.zeros(3)
        S = np.asarray(c.mag_soft_iron, float).reshape(3, 3) if c.mag_soft_iron is not None else np.eye(3)
        self._S_inv = np.linalg.inv(S)
        self._hard = np.asarray(c.mag_hard_iron_ut, float)
        self.t0 = math.nan
        self.t_x = math.nan
        self._sum_acc = np.zeros(3)
        self._sum_gyro = np.zeros(3)
        self._n_imu = 0
        self._sum_mag = np.zeros(3)
        self._n_mag = 0
        self._sum_r_e = np.zeros(3)
        self._n_fix = 0
        self.triad_skipped = 0  # TRIAD observations left out under acceleration
        # d g_b / d x summed over the same samples (the navigation states: g_b does not depend
        # on the GNSS error states, whose columns the TRIAD observation's H gets as zeros)
        self._dg_dx_sum = np.zeros((3, N_STATES))
        self._f_ref[:] = math.nan
        self._t_init_last = math.nan  # last IMU time of the initialisation, s
        self._n_init_all = 0  # IMU samples of the initialisation (all, even those not averaged)
        self.t_speed = math.nan
        self.v_speed = math.nan
        self.t_fix = -math.inf
        self._t_valid = -math.inf  # time of the latest valid fix (accepted or not), s
        self.n_pos_rejected = 0
        self.n_vel_rejected = 0  # consecutive gated GNSS velocities
        self.nis: list[tuple[float, str, float, int]] = []
        self._gate = (
            {m: kalman.gate_threshold(m, c.gate_probability) for m in (2, 3, 4)}
            if c.gate_probability > 0
            else {}
        )
        self.smoothing_log: SmoothingLog | None = SmoothingLog(c.record_every) if c.smoothing else None
        self._Phi = np.eye(self.n)
        self._prior = None
        self._rows = 0
        # no-magnetometer fallback (module docstring)
        self.heading_ok = True  # decided in _finish_init
        self.fallback = False
        self.aligner = MountAligner(c.mount)
        self.t_nhc = -math.inf
        self._init_snaps: list[tuple[FloatArray, FloatArray, int, FloatArray, int]] = []
        self._init_k_slow = 0  # index in _init_snaps of the latest epoch with a low speed

    # ------------------------------------------------------------------ protocol
    @property
    def mount_yaw_rad(self) -> float:
        """Mount yaw of the no-magnetometer fallback once accepted, rad; else 0 (sensor attitude)."""
        return float(self.aligner.mount_yaw_rad) if self.fallback and self.aligner.known else 0.0

    def summary(self) -> dict[str, Any]:
        """Configuration and final state."""
        counts: dict[str, int] = {}
        for e in self.events:
            counts[e["type"]] = counts.get(e["type"], 0) + 1
        return {
            "skipped": dict(self.guard.skipped),
            "engine": "qekf",
            "config": self.config.to_dict(),
            "origin": None
            if self.frame is None
            else {
                "lat_deg": self.frame.lat0_deg,
                "lon_deg": self.frame.lon0_deg,
                "height_m": self.frame.h0_m,
            },
            "mag_field_n_ut": self.m_n.tolist(),
            "mag_reference": self.mag_reference
            if self.mag_reference is not None
            else {"from": "config" if self.config.mag_field_n_ut is not None else "not initialised"},
            "gyro_bias_rad_s": self.x[BG].tolist(),
            "acc_bias_mps2": self.x[BA].tolist(),
            "gyro_scale": self.x[SG].tolist(),
            "acc_scale": self.x[SA].tolist(),
            "event_counts": counts,
            "triad_skipped": self.triad_skipped,
            "fallback": self.fallback,
            "heading_known": self.heading_ok,
            "mount_yaw_rad": self.mount_yaw_rad,
            "mount_quality": dict(self.aligner.quality),
            "gnss_resolution": self.resolution.to_dict(),
            "gnss_error_m": self.x[GNE].tolist() if self.n > N_STATES else None,
        }

    def step(self, sample: Sample) -> Output | None:
        """Process one sample; an :class:`Output` for each IMU sample."""
        sample = self.guard.admit(sample)
        if sample is None:
            return None
        if isinstance(sample, ImuSample):
            return self._one.run(self.imu_block, sample)
        if isinstance(sample, GnssSample):
            self._gnss(sample)
        elif isinstance(sample, MagSample):
            self._mag(sample)
        return None

    # ------------------------------------------------------------------ smoothing
    def smoothing_corrections(
        self, x_filt: FloatArray, x_smooth: FloatArray, P_smooth: FloatArray
    ) -> FloatArray:
        """Corrections at the record points (:mod:`iotnav.engines.smoother`)."""
        K = x_filt.shape[0]
        out = np.zeros((K, 11))
        out[:, CORR_POS] = x_smooth[:, POS] - x_filt[:, POS]
        out[:, CORR_VEL] = x_smooth[:, VEL] - x_filt[:, VEL]
        for k in range(K):
            qf = x_filt[k, Q_NB] / np.linalg.norm(x_filt[k, Q_NB])
            qs = x_smooth[k, Q_NB] / np.linalg.norm(x_smooth[k, Q_NB])
            out[k, CORR_ATT] = _rotvec(quat_to_dcm(qs) @ quat_to_dcm(qf).T)
        out[:, CORR_STD] = np.sqrt(np.maximum(np.stack([P_smooth[:, 7, 7], P_smooth[:, 8, 8]], axis=1), 0.0))
        return out

    def ned_to_geodetic(self, r_n: FloatArray) -> tuple[FloatArray, FloatArray, FloatArray]:
        """NED ``(N, 3)`` about the origin to lat, lon (deg), height (m), through ECEF."""
        r_e = self.r_e0 + np.asarray(r_n, float) @ self.C_en.T
        return ecef_to_geodetic(r_e)

    def _flush_record(self) -> None:
        log = self.smoothing_log
        if log is None or not self.initialised:
            return
        xp, Pp = self._prior if self._prior is not None else (self.x, self.P)
        log.record(self.t_x, xp, Pp, self._Phi, self.x, self.P)
        self._Phi = np.eye(self.n)
        self._prior = None
        self._rows = 0

    def _update(
        self,
        z: FloatArray,
        H: FloatArray,
        R: FloatArray,
        h_x: FloatArray | None,
        kind: str,
        t: float,
        force: bool = False,
    ) -> bool:
        if self.smoothing_log is not None and self._prior is None:
            self._prior = (self.x.copy(), self.P.copy())
        gate = self._gate.get(z.size) if kind != "norm" and not force else None
        m = z.size
        y, S = np.empty(m), np.empty((m, m))
        self._contiguous()
        H = np.ascontiguousarray(H, dtype=float)
        accepted, nis, x, P = KU.update(
            self.x, self.P, np.ascontiguousarray(z, dtype=float), H, np.ascontiguousarray(R, dtype=float),
            H @ self.x if h_x is None else np.ascontiguousarray(h_x, dtype=float),
            math.inf if gate is None else gate, y, S,
        )  # fmt: skip
        self.nis.append((t, kind, nis, m))
        if kind in self.innovations:
            self.innovations[kind].append(t, y, S, accepted)
        if accepted:
            self.x, self.P = x, P
        else:
            self.events.append({"type": f"{kind}_rejected", "t": t, "reason": "nis", "nis": nis})
        return bool(accepted)

    def _norm_update(self, t: float) -> None:
        """The norm pseudo-observation (:func:`norm_measurement`, compiled:
        :func:`iotnav.engines.qekf_updates_kernel.norm_model`)."""
        H, R, hx = np.empty((1, self.n)), np.empty((1, 1)), np.empty(1)
        self._contiguous()
        KU.norm_model(self.x, self.config.quat_norm_std, H, R, hx)
        self._update(np.zeros(1), H, R, hx, "norm", t)

    def _pad(self, H: FloatArray) -> FloatArray:
        """A 22-column ``H`` widened with zero columns to the engine's state count."""
        if H.shape[1] == self.n:
            return H
        Hp = np.zeros((H.shape[0], self.n))
        Hp[:, : H.shape[1]] = H
        return Hp

    # ------------------------------------------------------------------ prediction
    def _predict_to(self, t: float) -> None:
        """Predict to ``t`` (s) with the held IMU sample (:func:`iotnav.engines.qekf_kernel.predict`,
        the compiled form of :func:`propagate` with its process noise)."""
        if not self.initialised or not self.have_imu:
            return
        dt = t - self.t_x
        if dt <= 0.0:
            return
        if self._prior is not None:
            self._flush_record()
        self._contiguous()
        K.predict(
            self.x, self.P, self._Phi, self.acc, self.gyro, dt, self.g_n, self._prm, self._vec, self.st,
            self._F_full, self._Q_full,
        )  # fmt: skip
        self.t_x = t

    def _contiguous(self) -> None:
        """``x``, ``P`` and ``Phi`` as the C-ordered float arrays the kernels update in place."""
        self.x = np.ascontiguousarray(self.x, dtype=float)
        self.P = np.ascontiguousarray(self.P, dtype=float)
        self._Phi = np.ascontiguousarray(self._Phi, dtype=float)

    def _set_gnss_noise(
        self,
        R: FloatArray,
        lat_deg: float,
        kind: tuple[str, str] | None = None,
    ) -> None:
        """Split a fix's position variance ``R`` (diagonal, m^2) into the correlated part carried
        by the states and the white part of the measurement (``gnss_error_states``); ``kind``:
        the figures that gave it (:func:`~iotnav.engines.anchor.gnss_position_noise_source`)."""
        c = self.config
        var_p = np.diag(R).copy()
        f = c.gnss_white_fraction
        self._noise_kind = kind
        self._var_e = max(1.0 - f * f, 0.0) * var_p
        self._var_gm[:] = gm_variance_factor(self._te, c.gnss_receiver_filter_s) * self._var_e
        floor = np.maximum(c.gnss_white_floor_m, np.asarray(self.resolution.sigma_ned_m(lat_deg)))
        self._var_white = np.maximum(f * np.sqrt(var_p), floor) ** 2

    def _scale_gnss_error(self, steps: tuple[float, float, float]) -> None:
        """The correlated-error states follow the reported accuracy (per NED axis); ``steps``:
        the relative rounding of the figures behind the fix's sigma.

        A receiver re-acquiring after a tunnel reports a larger sigma and its fixes are that
        much further off (in the simulator exactly ``e = sigma(t) y``). As ``eskf``
        (:meth:`iotnav.engines.eskf.EskfEngine._scale_gnss_error`) the estimates and the
        covariance rows of ``[e, e_gm]`` are scaled by the ratio ``k`` of the fix's sigma to
        the level they were scaled to (``x' = T x``, ``P' = T P T^T``), of the same kind of
        figures (hAcc / vAcc, or DOPs), at once for continuous figures and jumps, low-passed
        over the figures' rounding steps
        (:class:`~iotnav.engines.gnss_resolution.AccuracyScaling`). Scaled at once by every
        rounding step of the DOPs (0.01, +-1 %) the states took those steps for information
        about ``e``: on the tests' receiver-error runs the position sigma fell from 1.22 to
        0.75 m with the error unchanged (NEES 5.5 -> 8.0); adding only the variance increase
        instead left the innovations correlated (Box-Pierce 10.5 / 22.0 / 21.6). For the
        smoother the scaling is a step of the transition into the fix's record
        (``Phi' = T Phi``).
        """
        kr = self._scaling.ratio(self.t_x, np.sqrt(self._var_e), self._noise_kind, steps)
        if kr is None:
            return
        k = np.array(kr)
        if self._prior is not None:  # an update at this time already: its record ends here
            self._flush_record()
        d = np.ones(self.n)
        d[GNE] = k
        d[GNM] = k
        self.x *= d
        self.P *= np.outer(d, d)
        if self.smoothing_log is not None:
            self._Phi = d[:, None] * self._Phi

    def _gnss_error_cov(self, rows: slice | list[int]) -> FloatArray:
        """Stationary covariance of ``[e, e_gm]`` on the given axes (2k, 2k): ``var(e) =
        cov(e, e_gm) = sigma_e^2``, ``var(e_gm) = sigma_e^2 (T_e + t_f) / T_e``."""
        c = self.config
        return stationary_gnss_error_cov(self._var_e[rows], self._te[rows], c.gnss_receiver_filter_s)

    # ------------------------------------------------------------------ initialisation
    def _init_triad_noise(self, J_g: FloatArray, J_m: FloatArray, m_b: FloatArray) -> FloatArray:
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
        c = self.config
        n_all = self._n_init_all
        dt = (self._t_init_last - self.t0) / (n_all - 1) if n_all > 1 else 0.0
        T = self._n_imu * dt
        if not T > 0.0:
            S_g = (c.acc_dir_std_rad * float(self.g_n[2])) ** 2 * _I3  # a single sample
        else:
            S_g = c.acc_noise_mps2_rthz**2 / T * _I3
        S_m = (c.mag_dir_std_rad * float(np.linalg.norm(m_b))) ** 2 * _I3
        return J_g @ S_g @ J_g.T + J_m @ S_m @ J_m.T

    def _finish_init(self, t: float) -> None:
        c = self.config
        if self._n_fix == 0 or self._n_imu == 0:
            return  # keep waiting
        r_e0 = self._sum_r_e / self._n_fix
        lat, lon, h = (float(v) for v in ecef_to_geodetic(r_e0))
        self.frame = LocalFrame(lat, lon, h)
        self.r_e0 = r_e0
        self.C_en = self.frame.C_en
        self._geo[:3] = r_e0
        self._geo[3:] = self.C_en.ravel()
        g = c.gravity_mps2 if c.gravity_mps2 > 0 else normal_gravity(lat, h)
        self.g_n = np.array([0.0, 0.0, g])
        if c.mag_field_n_ut is not None:
            self.m_n = np.asarray(c.mag_field_n_ut, float)
        else:
            year, year_from = log_year(t, self.utc_offset_s, c.wmm_year)
            ref = reference_field(lat, lon, h, year)
            self.m_n = ref.field_n_ut
            self.mag_reference = {**ref.to_dict(), "year_from": year_from}
        f_mean = self._sum_acc / self._n_imu
        gyro_mean = self._sum_gyro / self._n_imu
        x = np.zeros(N_STATES)
        x[SG] = 1.0
        x[SA] = 1.0
        x[BG] = gyro_mean
        J_g: FloatArray | None = None
        if self._n_mag > 0 and c.use_mag:
            m_b = self._sum_mag / self._n_mag  # calibrated in _mag
            C = improved_triad(-f_mean, m_b, self.g_n, self.m_n, c.acc_dir_std_rad, c.mag_dir_std_rad)
            J_g, J_m = triad_jacobian(-f_mean, m_b, self.g_n, self.m_n, c.acc_dir_std_rad, c.mag_dir_std_rad)
            P_th = self._init_triad_noise(J_g, J_m, m_b)
        else:  # levelling only, yaw 0
            roll = math.atan2(-f_mean[1], -f_mean[2])
            pitch = math.atan2(f_mean[0], math.hypot(f_mean[1], f_mean[2]))
            C = _level(roll, pitch)
        x[Q_NB] = dcm_to_quat(C)
        self.x = np.concatenate([x, np.zeros(self.n - N_STATES)])
        P = np.zeros(N_STATES)
        P[Q_NB] = (0.5 * c.init_att_std_rad) ** 2
        P[VEL] = c.init_vel_std_mps**2
        sig = position_sigmas(math.nan, math.nan, math.nan, math.nan, c.uere_m, c.default_dop)
        P[POS] = sig.ned_m**2
        P[BG] = c.gyro_bias_init_rad_s**2
        P[BA] = c.acc_bias_init_mps2**2
        P[SG] = P[SA] = c.scale_init**2
        self.P = np.diag(P)
        if self.n > N_STATES:
            self.P = np.pad(self.P, (0, self.n - N_STATES))
            self._init_gnss_error(t)
        if J_g is not None:
            # the static TRIAD used gravity -f_mean = g_b - b_a: its attitude error is
            # dtheta = J_g b_a + noise, hence P_tt = J_g P_ba J_g^T + P_triad, P_t,ba = J_g P_ba
            Xi = 0.5 * quat_right(x[Q_NB])[:, 1:]
            P_ba = self.P[BA, BA]
            P_tt = J_g @ P_ba @ J_g.T + P_th
            self.P[Q_NB, Q_NB] = Xi @ P_tt @ Xi.T + c.quat_norm_std**2 * np.outer(x[Q_NB], x[Q_NB])
            self.P[Q_NB, BA] = Xi @ J_g @ P_ba
            self.P[BA, Q_NB] = self.P[Q_NB, BA].T
        self.fallback = J_g is None
        self.heading_ok = not self.fallback
        if self.fallback:
            # standing still, the initialisation's mean specific force is the first gravity
            # reference of the mount aligner, which is only fed from here on: without it the
            # aligner waits for the next stop (module docstring, fallback step 1)
            self.aligner.set_gravity_reference(f_mean, t)
        self.initialised = True
        self.t_x = t
        self._norm_update(t)
        self._prior = None
        self.events.append(
            {
                "type": "init_done",
                "t": t,
                "lat_deg": lat,
                "lon_deg": lon,
                "height_m": h,
                "fixes": self._n_fix,
                "imu_samples": self._n_imu,
                "mag_samples": self._n_mag,
                "fallback": self.fallback,
                "gyro_bias_rad_s": gyro_mean.tolist(),
            }
        )
        self._flush_record()

    def _init_gnss_error(self, t: float) -> None:
        """Covariance of the position and GNSS error states at the end of the initialisation.

        The position state is 0 at the origin, the mean of the ``N`` initialisation fixes, so
        its error is minus the mean of their errors, ``-(mean_k e(t_k) + mean_k w_k)``, which is
        correlated with the error ``e(t)`` the next fixes carry: ``r + e`` is known better than
        either. Under the model (stationary ``e``, the latest fix's variances, device still)::

            P_POS     = var_e mean_jk rho(t_j - t_k) + sum_k var_w,k / N^2
            P_POS,GNE = -var_e mean_k rho(t - t_k),   P_POS,GNM = -var_e mean_k exp(-(t - t_k)/T_e)

        (``rho`` the autocorrelation of ``e``, :func:`_gnss_error_correlation`; ``cov(e(t_k),
        e_gm(t)) = var_e exp(-(t - t_k)/T_e)`` for ``t >= t_k``), and ``[GNE, GNM]`` the
        stationary covariance. Taking ``P_POS = R`` uncorrelated instead would claim the first
        fixes after the initialisation carry metres of new information on ``r + e`` that they
        do not; and a fix taken as a single one (``P_POS = var_e + var_w``,
        ``P_POS,GNE = -var_e``) would claim ``r + e`` known to ``var_w``, while ``e`` moves over
        the initialisation's 40 s.
        """
        c = self.config
        n0 = N_STATES
        self.P[n0:, n0:] = self._gnss_error_cov(slice(0, 3))
        self._scaling.reset(np.sqrt(self._var_e), self._noise_kind)
        tk = np.asarray(self._init_fix_t, float)
        N = tk.size
        if N == 0:
            return
        tf = c.gnss_receiver_filter_s
        v = self._var_e
        lag = np.maximum(t - tk, 0.0)
        m_ee, m_e, m_g = np.empty(3), np.empty(3), np.zeros(3)
        for i, Te in enumerate(self._te):
            m_ee[i] = np.mean(_gnss_error_correlation(tk[:, None] - tk[None, :], Te, tf))
            m_e[i] = np.mean(_gnss_error_correlation(lag, Te, tf))
            m_g[i] = np.mean(np.exp(-lag / Te)) if tf > 0.0 else 0.0
        self.P[POS, POS] = np.diag(v * m_ee + self._init_var_white / N**2)
        for sl, m in ((GNE, m_e), (GNM, m_g)):
            self.P[POS, sl] = -np.diag(v * m)
            self.P[sl, POS] = self.P[POS, sl]

    # ------------------------------------------------------------------ samples
    def _fix_ok(self, s: GnssSample) -> bool:
        if not s.valid or not (math.isfinite(s.lat_deg) and math.isfinite(s.lon_deg)):
            self.events.append({"type": "fix_rejected", "t": s.t, "reason": "invalid"})
            return False
        if not self.initialised and not math.isfinite(s.height_m):
            # the origin is the mean fix in ECEF: a 2D fix cannot join it
            self.events.append({"type": "fix_rejected", "t": s.t, "reason": "no_height_initialisation"})
            return False
        if 0 <= s.num_sv < self.config.min_satellites:
            self.events.append({"type": "fix_rejected", "t": s.t, "reason": "num_sv", "num_sv": s.num_sv})
            return False
        return True

    def _gnss(self, s: GnssSample) -> None:
        c = self.config
        if not self._fix_ok(s):
            return
        # an outage: no valid fix for longer than reacquire_after_s (not a run of rejected ones)
        outage = s.t - self._t_valid > c.reacquire_after_s
        self._t_valid = s.t
        # a 2D fix (no height) updates the horizontal only, at the filter's own height
        has_height = math.isfinite(s.height_m)
        if has_height:
            h = s.height_m
        else:
            h = float(self.ned_to_geodetic(self.x[POS])[2])
        r_e = geodetic_to_ecef(s.lat_deg, s.lon_deg, h)
        R, kind = gnss_position_noise_source(s, c.uere_m, c.default_dop)
        self.resolution.update(s.lat_deg, s.lon_deg, s.height_m)
        ge = self.n > N_STATES
        if ge:
            h_acc = float(getattr(s, "h_acc_m", math.nan))
            v_acc = float(getattr(s, "v_acc_m", math.nan))
            steps = self._scaling.figures.relative_steps(h_acc, v_acc, s.hdop, s.pdop, kind)
            self._set_gnss_noise(R, s.lat_deg, kind)
        if not self.initialised:
            self._sum_r_e += r_e
            self._n_fix += 1
            if ge:
                self._init_fix_t.append(s.t)
                self._init_var_white += self._var_white
            if not self._init_motion(s, r_e):
                return
        self._predict_to(s.t)
        if ge and c.gnss_error_scales_with_accuracy:
            self._scale_gnss_error(steps)
        r_n = self.C_en.T @ (r_e - self.r_e0)  # Eq. 6
        r_mean = math.inf  # mean yaw rate over the epoch interval (fallback), rad/s
        if self.fallback:
            ev = self.aligner.add_gnss(s.t, s.speed_mps, s.course_rad, s.course_valid, False)
            if ev is not None:
                self.events.append(ev)
            r_mean = self._r_gnss[0] / self._r_gnss[1] if self._r_gnss[1] > 0 else math.inf
            self._r_gnss[:] = 0.0
        z, H, Rm = self._position_measurement(r_n, R)
        if not has_height:
            z, H, Rm = z[:2], H[:2], Rm[:2, :2]
        if not self.heading_ok:
            self._gnss_before_heading(s, z, H, Rm, r_mean)
            return
        stale = s.t - self.t_fix > c.reacquire_after_s  # first fix after an outage
        force = self._gate and (self.n_pos_rejected >= c.max_rejections or stale)
        v = self._gnss_velocity(s) if c.use_gnss_velocity else None
        if force:
            # the fixes keep disagreeing by more than the covariance allows (e.g. after a long
            # outage): widen it by the disagreement itself, so this fix is taken nearly whole
            if outage and self.smoothing_log is not None and self._prior is None:
                # after an outage the widening is part of the forced update, not of the
                # smoothing model: the record gets the un-widened prior (as eskf's gate reset)
                self._prior = (self.x.copy(), self.P.copy())
            y = z - H @ self.x
            ip = slice(POS.start, POS.start + z.size)
            self.P[ip, ip] += Rm + np.outer(y, y)
            if v is None:
                # no velocity to widen below: the disagreement grew since the last accepted fix,
                # a velocity error of about y / dt, or the next fixes are rejected in turn (the
                # consistent form, whose white R is the fixes' rounding, locked out for a minute)
                yv = y[:2] / max(s.t - self.t_fix, 1.0)
                self.P[VEL.start : VEL.start + 2, VEL.start : VEL.start + 2] += np.outer(yv, yv)
            self.events.append(
                {"type": "gnss_pos_forced", "t": s.t, "innovation_m": float(np.linalg.norm(y))}
            )
        if self._update(z, H, Rm, None, "gnss_pos", s.t, force=bool(force)):
            self.t_fix = s.t
            self.n_pos_rejected = 0
        else:
            self.n_pos_rejected += 1
        if v is not None:
            s_acc = float(getattr(s, "s_acc_mps", math.nan))
            sigma = s_acc if math.isfinite(s_acc) and s_acc > 0 else c.vel_noise_mps
            z, H, Rm = self._velocity_measurement(v, sigma)
            # the velocity dead-reckoned through the same outage is as far off as the position,
            # and velocities rejected again and again are the same lock-out: widen it likewise,
            # or the next fixes drift away and are rejected in turn
            force_v = force or (self._gate and self.n_vel_rejected >= c.max_rejections)
            if force_v:
                iv = slice(VEL.start, VEL.start + z.size)
                y = z - H @ self.x
                self.P[iv, iv] += Rm + np.outer(y, y)
                self.events.append(
                    {"type": "gnss_vel_forced", "t": s.t, "innovation_mps": float(np.linalg.norm(y))}
                )
            if self._update(z, H, Rm, None, "gnss_vel", s.t, force=bool(force_v)):
                self.n_vel_rejected = 0
            else:
                self.n_vel_rejected += 1
        self._norm_update(s.t)
        use_gnss_speed = c.use_gnss_velocity and math.isfinite(s.speed_mps)
        self._speed_rate(s.t, *(self._gnss_speed(s) if use_gnss_speed else self._filter_speed()))

    def _position_measurement(
        self, r_n: FloatArray, R: FloatArray
    ) -> tuple[FloatArray, FloatArray, FloatArray]:
        """GNSS position ``(z, H, R)``; with ``gnss_error_states`` ``z = r + e + w``: ``H`` is ``I``
        on ``POS`` and on ``GNE``, ``R`` the white part (:meth:`_set_gnss_noise`), else the
        fix's whole ``R``."""
        if self.n == N_STATES:
            return position_measurement(r_n, R)
        z, H, Rm = position_measurement(r_n, np.diag(self._var_white))
        H = self._pad(H)
        H[:, GNE] = _I3
        return z, H, Rm

    def _velocity_measurement(self, v: FloatArray, sigma: float) -> tuple[FloatArray, FloatArray, FloatArray]:
        """GNSS velocity ``(z, H, R)``; with ``gnss_error_states`` its error is the derivative of
        the smoothed position error plus white Doppler noise, ``z = v + (e_gm - e) / t_f + w``."""
        z, H, Rm = velocity_measurement(v, sigma)
        H = self._pad(H)
        tf = self.config.gnss_receiver_filter_s
        if self.n > N_STATES and tf > 0.0:
            m = z.size
            H[:, GNE.start : GNE.start + m] = -np.eye(m) / tf
            H[:, GNM.start : GNM.start + m] = np.eye(m) / tf
        return z, H, Rm

    def _init_motion(self, s: GnssSample, r_e: FloatArray) -> bool:
        """End the initialisation early when the device moves (``init_max_displacement_m``).

        The averages then stop one GNSS interval before the latest epoch whose speed was at most
        ``init_max_speed_mps``. Returns True when the initialisation was completed here.
        """
        c = self.config
        k = len(self._init_snaps)
        self._init_snaps.append(
            (self._sum_acc.copy(), self._sum_gyro.copy(), self._n_imu, self._sum_mag.copy(), self._n_mag)
        )
        if not (math.isfinite(s.speed_mps) and s.speed_mps > c.init_max_speed_mps):
            self._init_k_slow = k
            return False
        dist = float(np.linalg.norm(r_e - self._sum_r_e / self._n_fix))
        if c.init_max_displacement_m <= 0.0 or dist <= c.init_max_displacement_m:
            return False
        acc, gyro, n_imu, mag, n_mag = self._init_snaps[max(self._init_k_slow - 1, 0)]
        if n_imu == 0:
            return False
        self._sum_acc, self._sum_gyro, self._n_imu, self._sum_mag, self._n_mag = acc, gyro, n_imu, mag, n_mag
        self._finish_init(s.t)
        self.P[VEL, VEL] += np.eye(3) * s.speed_mps**2
        self.events.append(
            {"type": "init_ended_by_motion", "t": s.t, "speed_mps": s.speed_mps, "dist_m": dist}
        )
        return True

    def _gnss_before_heading(
        self, s: GnssSample, z: FloatArray, H: FloatArray, R: FloatArray, r_mean: float
    ) -> None:
        """Fallback steps 2-3 (module docstring): vertical updates, horizontal re-initialisation,
        and the heading reset once driving straight and fast with a mount angle."""
        c = self.config
        if self.smoothing_log is not None:
            if self._prior is None:
                self._prior = (self.x.copy(), self.P.copy())
            # the re-initialisation is no Kalman update: the RTS smoother must not carry
            # information back across it (zero transition, zero gain)
            self._Phi = np.zeros((self.n, self.n))
        if z.size == 3:
            self._update(z[2:], H[2:], R[2:, 2:], None, "gnss_pos_down", s.t)
        v = self._gnss_velocity(s) if c.use_gnss_velocity else None
        s_acc = float(getattr(s, "s_acc_mps", math.nan))
        sig_v = s_acc if math.isfinite(s_acc) and s_acc > 0 else c.vel_noise_mps
        if v is not None and v.size == 3:
            zv, Hv, Rv = self._velocity_measurement(v, sig_v)
            self._update(zv[2:], Hv[2:], Rv[2:, 2:], None, "gnss_vel_down", s.t)
        elif v is None and math.isfinite(s.speed_mps):
            v, sig_v = np.zeros(2), math.hypot(s.speed_mps, c.vel_noise_mps)  # slow: no course
        idx = [POS.start, POS.start + 1]
        var = [R[0, 0], R[1, 1]]
        if v is not None:
            idx += [VEL.start, VEL.start + 1]
            var += [sig_v**2, sig_v**2]
        ge = [GNE.start, GNE.start + 1, GNM.start, GNM.start + 1] if self.n > N_STATES else []
        self.P[idx + ge, :] = 0.0
        self.P[:, idx + ge] = 0.0
        self.P[idx, idx] = var
        self.x[POS.start : POS.start + 2] = z[:2]
        if ge:
            # r = z - e - w with e = 0: var(r) = var_e + var_w, cov(r, e) = cov(r, e_gm) = -var_e
            C = self._gnss_error_cov(slice(0, 2))
            self.x[ge] = 0.0
            self.P[np.ix_(ge, ge)] = C
            self.P[np.ix_(idx[:2], ge)] = -C[:2]
            self.P[np.ix_(ge, idx[:2])] = -C[:, :2]
            self.P[idx[:2], idx[:2]] += self._var_e[:2]
            self._scaling.reset(np.sqrt(self._var_e), axes=(0, 1))
        if v is not None:
            self.x[VEL.start : VEL.start + 2] = v[:2]
        self.t_fix = s.t
        self._norm_update(s.t)
        self._speed_rate(s.t, *(self._gnss_speed(s) if math.isfinite(s.speed_mps) else self._filter_speed()))
        if v is None or not self.aligner.known:
            return
        speed = float(np.hypot(v[0], v[1]))
        if speed < c.heading_min_speed_mps or not abs(r_mean) <= c.heading_max_yaw_rate_rad_s:
            return
        chi = math.atan2(v[1], v[0])
        sig_mu = float(self.aligner.quality.get("std_rad", c.mount.max_std_rad))
        sigma = math.sqrt((sig_v / speed) ** 2 + sig_mu**2 + c.nhc_sideslip_std_rad**2)
        self._set_heading(s.t, wrap(chi + self.aligner.mount_yaw_rad), sigma)

    def _set_heading(self, t: float, yaw_b: float, sigma: float) -> None:
        """Fallback step 3: reset the sensor yaw to ``yaw_b`` (rad) with sigma ``sigma`` (rad)."""
        q = self.x[Q_NB]
        C = quat_to_dcm(q / np.linalg.norm(q))
        d = wrap(yaw_b - math.atan2(C[1, 0], C[0, 0]))
        T = np.eye(self.n)
        T[Q_NB, Q_NB] = quat_left(np.array([math.cos(0.5 * d), 0.0, 0.0, math.sin(0.5 * d)]))
        self.x = T @ self.x
        P = T @ self.P @ T.T
        e = np.zeros(self.n)
        e[Q_NB] = 0.5 * quat_right(self.x[Q_NB])[:, 3]
        u = e / np.linalg.norm(e)
        Pi = np.eye(self.n) - np.outer(u, u)
        self.P = kalman.symmetrize(Pi @ P @ Pi.T + sigma**2 * np.outer(e, e))
        self.heading_ok = True
        self.t_nhc = t
        self._r_nhc[:] = 0.0
        self.events.append(
            {
                "type": "heading_initialised",
                "t": t,
                "yaw_rad": yaw_b,
                "change_rad": d,
                "std_rad": sigma,
                "mount_yaw_rad": self.aligner.mount_yaw_rad,
                "source": "gnss_course",
            }
        )

    def _nhc(self, t: float) -> None:
        """Fallback step 4: the non-holonomic observation (module docstring)."""
        c = self.config
        r_mean = self._r_nhc[0] / self._r_nhc[1] if self._r_nhc[1] > 0 else 0.0
        self._r_nhc[:] = 0.0
        self.t_nhc = t
        speed = math.hypot(self.x[VEL.start], self.x[VEL.start + 1])
        if speed < c.nhc_min_speed_mps or abs(r_mean) > c.nhc_max_yaw_rate_rad_s:
            return
        sig_mu = float(self.aligner.quality.get("std_rad", c.mount.max_std_rad))
        var = (
            c.nhc_vel_std_mps**2
            + speed**2 * (c.nhc_sideslip_std_rad**2 + sig_mu**2)
            + (r_mean * c.nhc_lever_m) ** 2
        )
        H, R, hx = np.empty((1, self.n)), np.empty((1, 1)), np.empty(1)
        self._contiguous()  # nhc_measurement, compiled
        KU.nhc_model(self.x, float(self.aligner.mount_yaw_rad), math.sqrt(var), H, R, hx)
        self._update(np.zeros(1), H, R, hx, "nhc", t)
        self._norm_update(t)

    def _gnss_speed(self, s: GnssSample) -> tuple[float, float]:
        """GNSS horizontal speed and its sigma (sAcc, else ``vel_noise_mps``), m/s."""
        s_acc = float(getattr(s, "s_acc_mps", math.nan))
        sigma = s_acc if math.isfinite(s_acc) and s_acc > 0 else self.config.vel_noise_mps
        return float(s.speed_mps), sigma

    def _filter_speed(self) -> tuple[float, float]:
        """The filter's horizontal speed and its sigma (mean horizontal velocity sigma), m/s."""
        return math.hypot(self.x[4], self.x[5]), math.sqrt(0.5 * (self.P[4, 4] + self.P[5, 5]))

    def _speed_rate(self, t: float, speed: float, sigma_v: float) -> None:
        """Along-track acceleration for the gravity compensation (:func:`~iotnav.engines.qekf_kernel.accumulate_gravity`).

        ``a_long`` is the speed change over the last GNSS interval (GNSS speed, or the filter's
        horizontal speed after the position update when GNSS velocity is not used): the mean
        acceleration over that interval, which lags the present by half an interval to one and a
        half. The accelerometer removes the lag: the specific force in ``b`` is ``f = a_b - g_b``
        and ``g_b`` changes only with roll and pitch (not with the yaw of a turn), so the change
        of the along-track acceleration since that interval is ``u . (f(t) - f_ref)``, ``f_ref``
        the mean of ``f`` over the interval (kept here) and ``u`` the present direction of
        ``v_b``: ``a_l(t) = a_long + u . (f(t) - f_ref)`` (:func:`~iotnav.engines.qekf_kernel.accumulate_gravity`). Its
        error is that of the speed difference, ``sqrt(2) sigma_v / dt`` (``a_long_std``). When
        the interval was not all driven (``|v_b| <= 0.5`` m/s somewhere, or no speed before it)
        the lagging mean is used alone, its lag error taken as its change between intervals
        (jerk x lag), as before.

        Parameters
        ----------
        t : float
            Epoch time, s.
        speed, sigma_v : float
            Horizontal speed and its standard deviation, m/s.
        """
        dt_v = t - self.t_speed
        ok = 0.0 < dt_v <= 1.5
        a = (speed - self.v_speed) / dt_v if ok else 0.0
        n = self._f_n
        if ok and n > 0 and n == self._n_interval and math.isfinite(sigma_v):
            self._f_ref[:] = self._f_sum / n
            self.a_long_std = math.sqrt(2.0) * sigma_v / dt_v
        else:
            self._f_ref[:] = math.nan
            self.a_long_std = abs(a - self.a_long) if ok else abs(a)
        self._f_sum[:] = 0.0
        self._f_n = 0
        self._n_interval = 0
        self.a_long = a
        self.t_speed, self.v_speed = t, speed

    def _gnss_velocity(self, s: GnssSample) -> FloatArray | None:
        vn = float(getattr(s, "vn", math.nan))
        ve = float(getattr(s, "ve", math.nan))
        vd = float(getattr(s, "vd", math.nan))
        if math.isfinite(vn) and math.isfinite(ve) and math.isfinite(vd):
            C_en_fix = LocalFrame(s.lat_deg, s.lon_deg, s.height_m).C_en
            return self.C_en.T @ (C_en_fix @ np.array([vn, ve, vd]))
        if s.course_valid and math.isfinite(s.speed_mps) and s.speed_mps >= self.config.min_course_speed_mps:
            return s.speed_mps * np.array([math.cos(s.course_rad), math.sin(s.course_rad)])
        return None

    def _mag(self, s: MagSample) -> None:
        c = self.config
        m_b = self._S_inv @ (np.asarray(s.mag_b_ut, float) - self._hard)
        if not self.initialised:
            self._sum_mag += m_b
            self._n_mag += 1
            return
        if not c.use_mag or self._acc_mag_n == 0 or not self.heading_ok:
            return
        self._predict_to(s.t)
        gb = self._acc_mag_sum / self._acc_mag_n  # gravity in b (down), m/s^2
        a_dyn = self._a_dyn_sum / self._acc_mag_n
        a_comp = self._a_comp_sum / self._acc_mag_n
        self._a_comp_sum = 0.0
        dg_dx = self._dg_dx_sum / self._acc_mag_n
        comp_var = self._comp_var_sum / self._acc_mag_n
        self._dg_dx_sum[:] = 0.0
        self._comp_var_sum = 0.0
        self._acc_mag_sum[:] = 0.0
        self._acc_mag_n = 0
        self._a_dyn_sum = 0.0
        g = float(self.g_n[2])
        m_ref = float(np.linalg.norm(self.m_n))
        nm = float(np.linalg.norm(m_b))
        dip_ref = math.asin(self.m_n[2] / m_ref)
        cos_gm = float(gb @ m_b) / (float(np.linalg.norm(gb)) * nm)
        dip = math.asin(max(-1.0, min(1.0, cos_gm)))
        if abs(nm / m_ref - 1.0) > c.mag_norm_tol or (a_dyn < 0.5 and abs(dip - dip_ref) > c.mag_dip_tol_rad):
            self.events.append(
                {"type": "mag_rejected", "t": s.t, "reason": "disturbance", "norm_ratio": nm / m_ref}
            )
            return
        if c.mag_observation == "direction":
            z, H, R, hx = mag_direction_measurement(self.x[Q_NB], m_b, self.m_n, c.mag_dir_std_rad)
            self._update(z, self._pad(H), R, hx, "mag_dir", s.t)
            self._norm_update(s.t)
            return
        if a_comp > c.triad_max_comp_mps2:
            self.triad_skipped += 1
            self.events.append(
                {"type": "triad_skipped", "t": s.t, "reason": "acceleration", "a_mps2": a_comp}
            )
            return
        sig_a = math.sqrt(c.acc_dir_std_rad**2 + (c.dyn_acc_factor * a_dyn / g) ** 2 + comp_var / g**2)
        z, H, R = triad_measurement(
            self.x[Q_NB],
            gb,
            m_b,
            self.g_n,
            self.m_n,
            sig_a,
            c.mag_dir_std_rad,
            c.quat_norm_std,
            dg_dx,
            None if c.triad_state_coupling == "jacobian" else self.P[:N_STATES, :N_STATES],
            _ACC_COLS if c.triad_state_coupling == "accelerometer" else None,
        )
        self._update(z, self._pad(H), R, None, "triad", s.t)
        self._norm_update(s.t)

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
        Once initialised, without the no-magnetometer fallback and without smoothing, the whole
        range runs in one compiled call (:func:`iotnav.engines.qekf_kernel.imu_run`). Otherwise
        each sample runs the same compiled pieces with Python between them: the
        initialisation's sums, the mount aligner and the non-holonomic observation of the
        fallback, the smoothing records.
        """
        k = i0
        while k < i1:
            if not self.initialised:
                tk = float(t[k])
                a = np.array([acc[0][k], acc[1][k], acc[2][k]])
                w = np.array([gyro[0][k], gyro[1][k], gyro[2][k]])
                if not self._init_imu(tk, a, w, out, k):
                    k += 1
                    continue  # else sample k, which completed the initialisation, runs below
            self._contiguous()
            mount = self.fallback and self.aligner.known
            k, code = K.imu_run(
                t, *acc, *gyro, k, i1, self.x, self.P, self._Phi, self.g_n, self._prm, self._vec,
                self.st, self._dg_dx_sum, self._geo, self.aligner.imu_sums,
                float(self.aligner.mount_yaw_rad) if mount else 0.0, mount, out.floats, out.source,
                self._F_full, self._Q_full,
            )  # fmt: skip
            if code == K.R_DONE:
                return
            if code == K.R_FLUSH:
                self._flush_record()
                continue
            tk = float(t[k])
            if code == K.R_NHC:
                self._nhc(tk)
                if self.smoothing_log is not None:
                    self._rows += 1
            if self._prior is not None or self._rows >= self.config.record_every:
                self._flush_record()
            self._contiguous()
            K.write_row(
                k, tk, self.x, self.P, self.st, self._geo,
                float(self.aligner.mount_yaw_rad) if mount else 0.0, mount, out.floats, out.source,
            )  # fmt: skip
            k += 1

    def _accumulate_gravity(self, acc: FloatArray, gyro: FloatArray) -> None:
        """Gravity in ``b`` from one sample (m/s^2, rad/s), summed with its Jacobian for the next
        TRIAD observation (:func:`iotnav.engines.qekf_kernel.accumulate_gravity`, which the IMU
        step runs)."""
        self._contiguous()
        a, w = np.array(acc, dtype=float), np.array(gyro, dtype=float)
        K.accumulate_gravity(self.x, a, w, self.g_n, self._prm, self._vec, self.st, self._dg_dx_sum)

    def _init_imu(self, t: float, acc: FloatArray, gyro: FloatArray, out: OutputBlock, k: int) -> bool:
        """One IMU sample (time s, specific force m/s^2, rate rad/s) of the initialisation: its
        sums, then the end of the initialisation when due. Returns True when it ended here (the
        sample is then processed as the first of the filter, without a prediction); else row
        ``k`` of ``out`` is written (no solution)."""
        if math.isnan(self.t0):
            self.t0 = t
        self._sum_acc += acc
        self._sum_gyro += gyro
        self._n_imu += 1
        self._n_init_all += 1
        self._t_init_last = t
        if t - self.t0 >= self.config.init_duration_s:
            self._finish_init(t)
        if self.initialised:
            return True
        self.acc[:] = acc
        self.gyro[:] = gyro
        self.have_imu = True
        out.floats[:, k] = math.nan
        out.floats[C_T, k] = t
        out.source[k] = SRC_NONE
        return False


def _level(roll: float, pitch: float) -> FloatArray:
    cr, sr, cp, spp = math.cos(roll), math.sin(roll), math.cos(pitch), math.sin(pitch)
    return np.array([[cp, sr * spp, cr * spp], [0.0, cr, -sr], [-spp, sr * cp, cr * cp]])
