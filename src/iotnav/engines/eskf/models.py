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
the first-order model (four times less at ``L = 1 s``, ``t_f = 2 s``). ``e_gm`` is scaled so that ``e`` has the fix accuracy's
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

The Monte Carlo runs that showed these terms are needed are in
``benchmarks/results/eskf_history.md`` ("Cross-axis coupling in the noise model").

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

# The model's pieces, re-exported: the one namespace (``M``) the engine and the tests use.
from __future__ import annotations

from iotnav.engines.eskf.alignment import *  # noqa: F403
from iotnav.engines.eskf.layout import *  # noqa: F403
from iotnav.engines.eskf.measurements import *  # noqa: F403
from iotnav.engines.eskf.propagation import *  # noqa: F403
from iotnav.engines.eskf.state import *  # noqa: F403
from iotnav.engines.eskf.update import *  # noqa: F403
