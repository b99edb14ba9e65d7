"""22-state quaternion EKF with GPS and 3-axis magnetometer (improved TRIAD attitude observation).

(28 states with the option ``gnss_error_states``, the GNSS position error carried as states:
:mod:`iotnav.engines.qekf_gnss_error`.)

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
  puts ``-J_x`` into ``H`` (exact linear model); ``"noise"`` keeps ``H = [I4 0]`` and adds
  ``J_x P J_x^T`` to ``R`` (the estimate's uncertainty treated as observation noise); the
  default ``"accelerometer"`` puts the ``b_a, s_a`` columns of ``-J_x`` into ``H`` (the error
  the accelerometer's bias and scale factor put into every TRIAD observation and into the
  initial alignment alike is then the state's own, observed nowhere twice) and keeps the
  velocity and gyro columns (the compensation ``w x v_b``) as noise.
  *Vehicle acceleration.* The direction sigma of ``g_b`` is
  ``sqrt(acc_dir_std^2 + (dyn_acc_factor a_dyn / g)^2 + var_comp / g^2)``: ``a_dyn = ||g_b| - g|``
  inflates it while ``|f| != g`` (a residual acceleration along gravity), and
  ``var_comp = a_long_std^2 + (comp_rel_error |a_b|)^2`` covers the compensation itself. The
  along-track acceleration is the GNSS (or, without GNSS velocity, the filter's) speed change
  over the last epoch interval, ``a_long``, plus the change of the accelerometer's along-track
  specific force since that interval (zero lag, :meth:`QekfEngine._speed_rate`); ``a_long_std``
  is then the error of the speed difference, ``sqrt(2) sigma_v / dt``. No TRIAD observation is
  made over an interval whose mean ``|a_b|`` exceeds ``triad_max_comp_mps2``: the
  compensation's remaining errors (sideslip, lever arm) are systematic over a manoeuvre, not
  the white noise the model assumes. The magnetometer sample is refused (``mag_rejected``
  event) when its norm or its dip angle departs from the reference field (disturbances);
* the quaternion-norm pseudo-observation ``e = 1 - |q| = 0`` (Eq. 9), ``H = -q^T / |q|``,
  applied with every other update (the propagation ``q (x) dq`` keeps the norm exactly, only
  updates change it).

Consistent form (:meth:`QekfConfig.consistent`; designed here, the paper's form stays the default):
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

The engine's other parts, each its own module with its model:

* :mod:`iotnav.engines.qekf_config`: :class:`QekfConfig` (tunables, SI, the paper's defaults);
* :mod:`iotnav.engines.qekf_models`: state layout, quaternion algebra, :func:`propagate` and the
  measurement models ``(z, H, R)`` (the readable reference forms);
* :mod:`iotnav.engines.qekf_init`: the static initialisation (paper Sec. 3.1);
* :mod:`iotnav.engines.qekf_fallback`: the no-magnetometer fallback (mount yaw, heading reset,
  non-holonomic observation; designed here);
* :mod:`iotnav.engines.qekf_gnss_error`: the GNSS error states (designed here);
* :mod:`iotnav.engines.qekf_kernel` (IMU loop, output rows), ``qekf_predict_kernel``,
  ``qekf_updates_kernel`` and ``qekf_layout`` (their shared arrays): the compiled step.

The figures (Monte Carlo NEES / NIS, per-seed attitude errors) behind the design choices:
``benchmarks/results/qekf_history.md``.
"""

from __future__ import annotations

import math
from typing import Any, cast

import numpy as np

from iotnav import kalman
from iotnav.engines import qekf_fallback as FB
from iotnav.engines import qekf_gnss_error as GE
from iotnav.engines import qekf_init as INIT
from iotnav.engines import qekf_kernel as K
from iotnav.engines import qekf_mag as MAG
from iotnav.engines import qekf_updates_kernel as KU
from iotnav.engines.anchor import gnss_position_noise_source
from iotnav.engines.base import (
    GnssSample,
    ImuSample,
    InputGuard,
    MagSample,
    OneSampleBlock,
    Output,
    OutputBlock,
    Sample,
)
from iotnav.engines.gnss_resolution import AccuracyScaling, PositionResolution
from iotnav.engines.qekf_config import QekfConfig, datasheet_noises
from iotnav.engines.qekf_gnss_error import gnss_error_transition
from iotnav.engines.qekf_models import (
    BA,
    BG,
    GNE,
    GNM,
    N_STATES,
    N_STATES_GNSS,
    POS,
    Q_NB,
    SA,
    SG,
    VEL,
    FloatArray,
    delta_quat,
    mag_direction_measurement,
    nhc_measurement,
    norm_measurement,
    position_measurement,
    propagate,
    quat_left,
    quat_right,
    quaternion_measurement,
    rotate_jacobian,
    triad_measurement,
    velocity_measurement,
    wmm_field_n,
)
from iotnav.engines.smoother import CORR_ATT, CORR_POS, CORR_STD, CORR_VEL, SmoothingLog
from iotnav.geo import LocalFrame, ecef_to_geodetic, geodetic_to_ecef
from iotnav.innovations import InnovationLog
from iotnav.techniques.mount import MountAligner

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
    "delta_quat",
    "gnss_error_transition",
    "mag_direction_measurement",
    "nhc_measurement",
    "norm_measurement",
    "position_measurement",
    "propagate",
    "quat_left",
    "quat_right",
    "quaternion_measurement",
    "rotate_jacobian",
    "triad_measurement",
    "velocity_measurement",
    "wmm_field_n",
]


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
        :attr:`innovations` (``gnss_pos``, ``gnss_vel``; :class:`~iotnav.innovations.InnovationLog`).
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
        # scratch of the compiled kernels (qekf_kernel.scratch: nothing allocated per sample)
        self._wm = np.zeros((K.N_WM, K.W_MAX, K.W_MAX))
        self._ws = np.zeros((K.N_WS, K.W_MAX))
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
        #: constant tunables of the compiled kernels (qekf_kernel.K_*), and their NIS log
        self._prm = K.parameters(c, self._k_w, self._k_a, self._gate.get(1))
        self._nlog = np.zeros((K.N_LOG, 4))
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
        att = np.empty((K, 3))
        KU.attitude_corrections(
            np.ascontiguousarray(x_filt[:, Q_NB]), np.ascontiguousarray(x_smooth[:, Q_NB]), att
        )
        out[:, CORR_ATT] = att
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
            self._F_full, self._Q_full, self._wm, self._ws,
        )  # fmt: skip
        self.t_x = t

    def _contiguous(self) -> None:
        """``x``, ``P`` and ``Phi`` as the C-ordered float arrays the kernels update in place."""
        self.x = np.ascontiguousarray(self.x, dtype=float)
        self.P = np.ascontiguousarray(self.P, dtype=float)
        self._Phi = np.ascontiguousarray(self._Phi, dtype=float)

    # ------------------------------------------------------------------ initialisation

    # ------------------------------------------------------------------ parts in their own modules
    # initialisation (qekf_init), GNSS error states (qekf_gnss_error), magnetometer and vehicle
    # acceleration (qekf_mag), no-magnetometer fallback (qekf_fallback)
    _init_triad_noise = INIT.init_triad_noise
    _finish_init = INIT.finish_init
    _init_motion = INIT.init_motion
    _init_imu = INIT.init_imu
    _set_gnss_noise = GE.set_gnss_noise
    _scale_gnss_error = GE.scale_gnss_error
    _gnss_error_cov = GE.gnss_error_cov
    _init_gnss_error = GE.init_gnss_error
    _position_measurement = GE.position_model
    _velocity_measurement = GE.velocity_model
    _gnss_speed = MAG.gnss_speed
    _filter_speed = MAG.filter_speed
    _speed_rate = MAG.speed_rate
    _mag = MAG.mag
    _gnss_before_heading = FB.gnss_before_heading
    _set_heading = FB.set_heading
    _nhc = FB.nhc

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
        Once initialised, the range runs in compiled calls (:func:`iotnav.engines.qekf_kernel.imu_run`),
        the fallback's aligner sums and non-holonomic observation included; Python acts between
        them for the smoothing records, and for the non-holonomic observation when smoothing (or
        an innovation log of ``nhc`` or ``norm``) is kept
        (:func:`iotnav.engines.qekf_fallback.nhc`); the initialisation's sums run in Python.
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
            FB.nhc_kernel_inputs(self)
            k, code = K.imu_run(
                t, *acc, *gyro, k, i1, self.x, self.P, self._Phi, self.g_n, self._prm, self._vec,
                self.st, self._dg_dx_sum, self._geo, self.aligner.imu_sums,
                float(self.aligner.mount_yaw_rad) if mount else 0.0, mount, out.floats, out.source,
                self._F_full, self._Q_full, self._wm, self._ws, self._nlog,
            )  # fmt: skip
            FB.nhc_kernel_log(self)
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
                self._ws,
            )  # fmt: skip
            k += 1

    def _accumulate_gravity(self, acc: FloatArray, gyro: FloatArray) -> None:
        """Gravity in ``b`` from one sample (m/s^2, rad/s), summed with its Jacobian for the next
        TRIAD observation (:func:`iotnav.engines.qekf_kernel.accumulate_gravity`, which the IMU
        step runs)."""
        self._contiguous()
        a, w = np.array(acc, dtype=float), np.array(gyro, dtype=float)
        K.accumulate_gravity(self.x, a, w, self.g_n, self._prm, self._vec, self.st, self._dg_dx_sum, self._ws)
