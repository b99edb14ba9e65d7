"""IoT mobile anchor node: GNSS + IMU Kalman filter with the acceleration as control input.

Reference: "Real time IoT mobile anchor nodes outdoor localization mechanism", Int. J. Smart
Sensing and Intelligent Systems 15(1), 2022 (section "Proposed outdoor localization analysis"
and the pseudo-code of Fig. 5).

Model (per axis of the local NED frame ``n``; the paper writes one axis, we stack three)::

    x = [p_n, v_n]                                  (6 states: POS, VEL)
    x_k = F_k x_{k-1} + B_k u_k,   P_k = F_k P_{k-1} F_k^T + Q_k
    F_k = [[I, dt I], [0, I]],     B_k = [[dt^2/2 I], [dt I]]
    u_k = a_n = C_nb f_b + g_n                      (IMU acceleration rotated to n)
    z = H x + w,   H = [I 0] (position) or [0 I] (velocity),   R = diag(sigma_pos^2, sigma_vel^2)
    K = P H^T (H P H^T + R)^-1,   x' = x + K (z - H x),   P' = (I - K H) P

The paper leaves ``Q`` as "depends on the IMU acceleration errors"; we use the white
acceleration error of spectral density ``q_a`` (m^2/s^3) integrated over the step,
``Q = q_a [[dt^3/3 I, dt^2/2 I], [dt^2/2 I, dt I]]``. ``R`` comes from the receiver's own
quality figures, read as every iotnav engine reads them (:mod:`iotnav.gnss_accuracy`):
``h_acc_m / sqrt(2)`` per horizontal axis (u-blox hAcc is the 2D figure) and ``v_acc_m``
(``1.5 h_acc_m`` without it) when reported, else ``UERE x HDOP / sqrt(2)`` per horizontal axis
and ``UERE x VDOP`` vertically (:func:`gnss_position_noise`). GNSS velocity (``vn, ve, vd`` when the
receiver gives them, else speed and course) is a second measurement when the paper's
"Correct IoT device's velocity" applies.

Attitude error in ``Q`` (not in the paper; ``attitude_in_q``, on by default). The control
input ``u = C_nb f_b + g_n`` inherits the attitude error of the cascade: a tilt error
``dtheta`` (rad, per horizontal axis) gives ``g dtheta``, a heading error ``dpsi`` gives
``|f_h| dpsi`` across the horizontal specific force. Both vary slowly (the tilt and yaw filters
correct them over tens of seconds), so over a GNSS outage they act as an unknown *constant*
acceleration error ``b ~ N(0, sigma_a^2)`` per axis, with

    sigma_a^2 = g^2 tr(P_tilt) / 2 + |f_h|^2 P_yaw

from the cascade's own covariances (``P_tilt`` of the down row ``x3`` in ``b``, whose two
components perpendicular to ``x3`` are the tilt errors; ``P_yaw`` the heading variance). A
constant ``b`` since the last fix at ``t_f`` gives ``var p = sigma_a^2 s^4 / 4``,
``cov(p, v) = sigma_a^2 s^3 / 2``, ``var v = sigma_a^2 s^2`` after ``s = t - t_f``. The state
``[p v]`` has no room for ``b`` (the paper's model), so it is carried as white acceleration
noise of growing density ``q(s) = 3 sigma_a^2 s``: integrating ``q`` through ``F`` gives
``var p = int_0^s q(u) (s - u)^2 du = sigma_a^2 s^4 / 4`` and ``cov(p, v) = sigma_a^2 s^3 / 2``
exactly, ``var v = 3/2 sigma_a^2 s^2`` (conservative by 1.5). With GNSS every second ``s``
stays below 1 s and the term is negligible; in a tunnel ``std_north``/``std_east`` grow like
the drift the attitude error causes. ``q_a = acc_psd_m2_s3`` remains for the white part
(noise, vibration).

The white-noise form matches the forward covariance, not the correlation over time that the
RTS smoother uses: smoothing an outage with it spreads the correction as if the acceleration
error were white, which pushes the start of an outage the wrong way when the error built up
late in it (a turn at the end of a tunnel, where the tilt filter leans towards the
centripetal acceleration). The smoother therefore adds a random-walk acceleration error to
the state (:class:`~iotnav.engines.smoother.AccelErrorModel`, attribute
``smoothing_accel_error``; ``smoothing_accel_rw_mps2_sqrt_s``), re-running the filter on the
smoothing records; the forward filter keeps the paper's ``[p v]``.

Pseudo-code of the paper, as implemented here:

* a fix is used only with *more than 4 satellites* (``min_satellites = 5``, configurable);
  others are rejected and reported in ``events`` (``fix_rejected``, reason ``num_sv``), as are
  invalid epochs and fixes failing the NIS gate;
* every IMU sample predicts (output at the IMU rate, 100 Hz on an MPU-6050 at 100 Hz);
* without fixes (tunnels) the filter only predicts: the position keeps moving with the
  IMU acceleration and its covariance grows (``std_north``, ``std_east`` of the output).

Attitude ``C_nb`` (not part of the paper's state: "the IMU provides orientation") comes from
the cascaded tilt / yaw / gyro-bias filters of :mod:`iotnav.techniques.cascade`, with the
static detector (:mod:`iotnav.techniques.static`) enabling the gyro-bias updates and the GPS
course plus the mount angle (:mod:`iotnav.techniques.mount`, or a configured angle) aiding
the yaw filter, wired as in :mod:`iotnav.engines.pipeline`.

Timing: an IMU sample stamped ``t_k`` is the mean over ``[t_k, t_k+1)``
(:mod:`iotnav.strapdown`), so the prediction to ``t_k`` uses the previous sample; a GNSS epoch
between two IMU samples is applied after a partial prediction to its time.

Implementation: the IMU step is one compiled kernel, :func:`anchor_imu_kernel`, over a block
of samples (:meth:`AnchorEngine.imu_block`); ``step(ImuSample)`` runs it on a one-sample block.
The prediction is the compiled :func:`anchor_predict_to` (``F``, ``B``, ``Q`` above written out
per 3 x 3 block; :func:`transition` is the dense reference form), shared with the GNSS path.
Smoothing record points are written by the kernels into a buffer and moved to the
:class:`~iotnav.engines.smoother.SmoothingLog` between kernel calls.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import numpy.typing as npt

from iotnav import kalman
from iotnav.engines.anchor_kernel import (
    AT_A_LONG,
    AT_AN,
    AT_G,
    AT_HAS_PRIOR,
    AT_HAVE_FRAME,
    AT_INIT,
    AT_N_REC,
    AT_SIGMA_A2,
    AT_SIZE,
    AT_STATIC,
    AT_T_FIX,
    AT_T_IMU,
    AT_T_SPEED,
    AT_T_X,
    AT_V_GNSS,
    EV_FULL,
    EV_STATIC,
    REC_SIZE,
    anchor_flush,
    anchor_imu_kernel,
    anchor_predict_to,
)
from iotnav.engines.anchor_kernel import N_STATES as N_STATES  # re-exported: the state layout
from iotnav.engines.anchor_kernel import POS as POS
from iotnav.engines.anchor_kernel import VEL as VEL
from iotnav.engines.base import (
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
from iotnav.engines.smoother import (
    AccelErrorModel,
    KinematicRecords,
    SmoothingLog,
)
from iotnav.geo import normal_gravity
from iotnav.gnss_accuracy import position_sigmas
from iotnav.techniques.cascade import CascadeConfig, CascadeKF, front_end
from iotnav.techniques.gyro_bias_kf import GyroBiasConfig
from iotnav.techniques.mount import MountAligner, MountConfig, wrap
from iotnav.techniques.static import StaticConfig, StaticDetector
from iotnav.techniques.tilt_kf import TiltConfig
from iotnav.techniques.yaw_kf import YawConfig

FloatArray = npt.NDArray[np.float64]

__all__ = ["N_STATES", "POS", "VEL", "AnchorConfig", "AnchorEngine", "AnchorKFConfig", "transition"]


_I3 = np.eye(3)


@dataclass(frozen=True)
class AnchorKFConfig:
    """Tunables of the anchor Kalman filter (SI).

    Attributes
    ----------
    min_satellites : int
        Fixes need at least this many satellites (paper: "more than 4" -> 5).
    accept_unknown_num_sv : bool
        Use fixes whose satellite count is not reported (-1).
    acc_psd_m2_s3 : float
        ``q_a``: spectral density of the control-acceleration error, m^2/s^3.
    uere_m : float
        User equivalent range error multiplying the DOPs when no hAcc is reported, m.
    default_dop : float
        HDOP assumed when the receiver reports neither an accuracy nor a DOP.
    vel_noise_mps : float
        Standard deviation of each GNSS velocity component when no sAcc is reported, m/s.
    use_velocity : bool
        Apply GNSS velocity updates.
    min_course_speed_mps : float
        Speed and course give a velocity (and aid the yaw filter) only above this speed, m/s.
    init_vel_std_mps : float
        Initial velocity standard deviation, m/s.
    gate_probability : float
        Chi-square probability of the position NIS gate; 0 (default) disables it, as in the
        paper, whose filter accepts every fix with more than 4 satellites.
    max_rejections : int
        After this many consecutive gated fixes the next is accepted (re-convergence).
    fix_hold_s : float
        Output ``source`` is ``fix`` up to this long after an accepted fix, then ``dr``, s.
    gravity_mps2 : float
        Gravity magnitude, m/s^2; 0 uses WGS84 normal gravity at the origin.
    mount_yaw_rad : float or None
        Known mounting yaw (sensor x from vehicle forward, clockwise), rad; None estimates it.
    smoothing : bool
        Keep a :class:`~iotnav.engines.smoother.SmoothingLog` for the RTS smoother (``iotnav run
        --smooth`` turns it on): about 1 KB a record, one every ``record_every`` rows and one
        per measurement, so about 1.5 GB for a day of 100 Hz data; off by default.
    record_every : int
        Output rows between smoothing records without a measurement.
    smoothing_accel_rw_mps2_sqrt_s : float
        Random-walk density of the acceleration error the RTS smoother adds to the state
        (module docstring), m/s^2/sqrt(s): the rms change of the attitude-induced acceleration
        error of the car-tunnel scenario (MPU-6050, cascade attitude) over 5-15 s in a tunnel is
        0.10-0.17 m/s^2/sqrt(s). 0 smooths with the filter's own (white-noise) model.
    smoothing_accel_init_std_mps2 : float
        Standard deviation of that acceleration error at the first fix, m/s^2.
    attitude_in_q : bool
        Add the cascade's attitude uncertainty to ``Q`` (module docstring).
    """

    min_satellites: int = 5
    accept_unknown_num_sv: bool = True
    acc_psd_m2_s3: float = 0.5
    uere_m: float = 3.0
    default_dop: float = 2.0
    vel_noise_mps: float = 0.3
    use_velocity: bool = True
    min_course_speed_mps: float = 2.0
    init_vel_std_mps: float = 1.0
    gate_probability: float = 0.0
    max_rejections: int = 5
    fix_hold_s: float = 1.5
    gravity_mps2: float = 0.0
    mount_yaw_rad: float | None = None
    smoothing: bool = False
    record_every: int = 10
    smoothing_accel_rw_mps2_sqrt_s: float = 0.15
    smoothing_accel_init_std_mps2: float = 1.0
    attitude_in_q: bool = True


@dataclass(frozen=True)
class AnchorConfig:
    """Every tunable of the anchor engine: the KF and the attitude techniques it uses.

    ``mount`` gates buffers whose angle is more than 3 combined sigma from the fused one
    (``gate_sigma``, as the pipeline does): right after a GNSS outage the tilt filter that
    levels the anchor's buffers may still carry the outage's error (car-tunnel seed 4: one
    buffer 21 deg off pulled the fused angle 3 deg).
    """

    kf: AnchorKFConfig = field(default_factory=AnchorKFConfig)
    tilt: TiltConfig = field(default_factory=TiltConfig)
    yaw: YawConfig = field(default_factory=lambda: YawConfig(use_mag=False))
    gyro_bias: GyroBiasConfig = field(default_factory=GyroBiasConfig)
    static: StaticConfig = field(default_factory=StaticConfig)
    mount: MountConfig = field(default_factory=lambda: MountConfig(gate_sigma=3.0))

    def to_dict(self) -> dict[str, dict[str, Any]]:
        """Nested plain dict (for ``summary.json``)."""
        return {f.name: dataclasses.asdict(getattr(self, f.name)) for f in dataclasses.fields(self)}


def transition(dt: float, q_a: float) -> tuple[FloatArray, FloatArray, FloatArray]:
    """``F`` (6, 6), ``B`` (6, 3) and ``Q`` (6, 6) of one step of ``dt`` seconds.

    Parameters
    ----------
    dt : float
        Step, s.
    q_a : float
        Acceleration error spectral density, m^2/s^3.
    """
    F = np.eye(N_STATES)
    F[POS, VEL] = dt * _I3
    B = np.zeros((N_STATES, 3))
    B[POS] = 0.5 * dt * dt * _I3
    B[VEL] = dt * _I3
    Q = np.zeros((N_STATES, N_STATES))
    Q[POS, POS] = q_a * dt**3 / 3.0 * _I3
    Q[POS, VEL] = Q[VEL, POS] = q_a * dt**2 / 2.0 * _I3
    Q[VEL, VEL] = q_a * dt * _I3
    return F, B, Q


def gnss_position_noise_source(
    s: GnssSample, uere_m: float, default_dop: float
) -> tuple[FloatArray, tuple[str, str]]:
    """``R`` (3, 3), NED, m^2, of a fix and the figures that gave it, horizontal and vertical
    (``h_acc``, ``v_acc``, ``hdop``, ``pdop`` or ``default``: what
    :class:`~iotnav.engines.gnss_resolution.AccuracyScaling` compares like with like).

    :func:`iotnav.gnss_accuracy.position_sigmas` reads the figures (``h_acc_m`` is the
    horizontal 2D accuracy, per axis ``h_acc / sqrt(2)``; else the DOPs x ``uere_m``; else
    ``default_dop`` as HDOP).
    """
    sig = position_sigmas(s.h_acc_m, s.v_acc_m, s.hdop, s.pdop, uere_m, default_dop)
    return np.diag(sig.ned_m**2), sig.source


def gnss_position_noise(s: GnssSample, uere_m: float, default_dop: float) -> FloatArray:
    """``R`` (3, 3), NED, m^2, of a fix (:func:`gnss_position_noise_source`)."""
    return gnss_position_noise_source(s, uere_m, default_dop)[0]


def gnss_position_measurement(
    s: GnssSample, r_n: FloatArray, uere_m: float, default_dop: float
) -> tuple[FloatArray, FloatArray, FloatArray]:
    """GNSS position in ``n`` as ``(z, H, R)``; ``R`` from :func:`gnss_position_noise` (m^2)."""
    R = gnss_position_noise(s, uere_m, default_dop)
    H = np.zeros((3, N_STATES))
    H[:, POS] = _I3
    return np.asarray(r_n, float), H, R


def gnss_velocity_measurement(
    s: GnssSample, sigma_default_mps: float, min_speed_mps: float
) -> tuple[FloatArray, FloatArray, FloatArray] | None:
    """GNSS velocity as ``(z, H, R)``: ``vn, ve, vd`` when reported, else speed and course.

    Returns None when the epoch carries no usable velocity.
    """
    s_acc = float(getattr(s, "s_acc_mps", math.nan))
    sigma = s_acc if math.isfinite(s_acc) and s_acc > 0 else sigma_default_mps
    vn = float(getattr(s, "vn", math.nan))
    ve = float(getattr(s, "ve", math.nan))
    vd = float(getattr(s, "vd", math.nan))
    if math.isfinite(vn) and math.isfinite(ve):
        if math.isfinite(vd):
            H = np.zeros((3, N_STATES))
            H[:, VEL] = _I3
            return np.array([vn, ve, vd]), H, np.eye(3) * sigma**2
        H = np.zeros((2, N_STATES))
        H[:, 3:5] = np.eye(2)
        return np.array([vn, ve]), H, np.eye(2) * sigma**2
    if s.course_valid and math.isfinite(s.speed_mps) and s.speed_mps >= min_speed_mps:
        H = np.zeros((2, N_STATES))
        H[:, 3:5] = np.eye(2)
        z = s.speed_mps * np.array([math.cos(s.course_rad), math.sin(s.course_rad)])
        return z, H, np.eye(2) * sigma**2
    return None


class AnchorEngine(KinematicRecords):
    """Streaming anchor-node engine (see the module docstring).

    Parameters
    ----------
    config : AnchorConfig, optional
        Tunables (paper values where the paper gives one).
    """

    _kin_pos, _kin_vel, _kin_states, _kin_n_rec = POS, VEL, N_STATES, AT_N_REC

    def __init__(self, config: AnchorConfig | None = None) -> None:
        self.config = c = config or AnchorConfig()
        k = c.kf
        #: Distance from the plane's anchor beyond which it is re-linearised at a fix, m
        #: (:meth:`TangentPlane.follow`); ``inf`` keeps one plane (the C library: always the default).
        self.reanchor_distance_m: float | None = None
        self.cascade = CascadeKF(CascadeConfig(c.tilt, c.yaw, c.gyro_bias))
        self.static_det = StaticDetector(c.static)
        self.mount = MountAligner(c.mount)
        if k.mount_yaw_rad is not None:
            self.mount.mount_yaw_rad = float(k.mount_yaw_rad)
            self.mount.known = True
            self.mount.done = True
        self.events: list[dict[str, Any]] = []
        self.guard = InputGuard(self.events)
        self.frame: TangentPlane | None = None
        self._st = np.zeros(AT_SIZE)
        self._prm = np.array(
            [k.acc_psd_m2_s3, float(k.attitude_in_q), float(k.smoothing), float(k.record_every), k.fix_hold_s]
        )
        self._frame = np.zeros(5)  # TangentPlane constants for the kernel
        self._kf = np.zeros(N_STATES + N_STATES * N_STATES)  # x, then P row-major
        self.g = k.gravity_mps2 if k.gravity_mps2 > 0 else 9.80665
        self.x = np.zeros(N_STATES)
        self.P = np.eye(N_STATES)
        self.initialised = False
        self._origin_2d = False  # origin set from a fix without height: vertical unknown
        self.t_x = math.nan  # time of the state, s
        self.t_imu = math.nan
        self.a_n = np.zeros(3)  # control input of the latest IMU sample, m/s^2
        self.sigma_a2 = 0.0  # variance of its attitude-induced error per axis, m^2/s^4
        self.static = False
        self.t_fix = -math.inf
        self.n_rejected = 0
        self.a_long = 0.0
        self.v_gnss = 0.0
        self.t_speed = math.nan
        self.n_fixes = 0
        self._gate = kalman.gate_threshold(3, k.gate_probability) if k.gate_probability > 0 else None
        self._gate2 = kalman.gate_threshold(2, k.gate_probability) if k.gate_probability > 0 else None
        self.smoothing_log: SmoothingLog | None = SmoothingLog(k.record_every) if k.smoothing else None
        #: acceleration error of the smoothing model (read by :func:`~iotnav.engines.smoother.smooth_output`)
        self.smoothing_accel_error: AccelErrorModel | None = (
            AccelErrorModel(POS, VEL, k.smoothing_accel_rw_mps2_sqrt_s, k.smoothing_accel_init_std_mps2)
            if k.smoothing and k.smoothing_accel_rw_mps2_sqrt_s > 0
            else None
        )
        # smoothing: transition since the last record point, the prior before pending updates
        # (flag AT_HAS_PRIOR) and record points written by the kernels until drained to the log
        self._Phi = np.eye(N_STATES).reshape(-1)
        self._prior = np.zeros_like(self._kf)
        self._rec = np.zeros((64, REC_SIZE))
        self._one = OneSampleBlock()  # reused by step(ImuSample)

    # Scalars shared with the compiled IMU kernel (elements of ``_st``).
    t_imu = StateSlot(AT_T_IMU)
    t_x = StateSlot(AT_T_X)
    initialised = FlagSlot(AT_INIT)
    sigma_a2 = StateSlot(AT_SIGMA_A2)
    static = FlagSlot(AT_STATIC)
    t_fix = StateSlot(AT_T_FIX)
    a_long = StateSlot(AT_A_LONG)
    v_gnss = StateSlot(AT_V_GNSS)
    t_speed = StateSlot(AT_T_SPEED)
    g = StateSlot(AT_G)

    @property
    def x(self) -> FloatArray:
        """State ``[p_n, v_n]`` (m, m/s; view)."""
        return self._kf[:N_STATES]

    @x.setter
    def x(self, value: FloatArray) -> None:
        self._kf[:N_STATES] = value

    @property
    def P(self) -> FloatArray:
        """Covariance (view)."""
        return self._kf[N_STATES:].reshape(N_STATES, N_STATES)

    @P.setter
    def P(self, value: FloatArray) -> None:
        self._kf[N_STATES:] = np.asarray(value, float).reshape(-1)

    @property
    def a_n(self) -> FloatArray:
        """Control input ``C_nb f_b + g_n`` of the latest IMU sample, m/s^2 (view)."""
        return self._st[AT_AN : AT_AN + 3]

    @a_n.setter
    def a_n(self, value: FloatArray) -> None:
        self._st[AT_AN : AT_AN + 3] = value

    # ------------------------------------------------------------------ protocol
    @property
    def mount_yaw_rad(self) -> float:
        """Mounting yaw in use, rad."""
        return float(self.mount.mount_yaw_rad)

    def summary(self) -> dict[str, Any]:
        """Configuration and final state."""
        counts: dict[str, int] = {}
        for e in self.events:
            counts[e["type"]] = counts.get(e["type"], 0) + 1
        return {
            "skipped": dict(self.guard.skipped),
            "engine": "anchor",
            "config": self.config.to_dict(),
            "mount_yaw_rad": self.mount_yaw_rad,
            "origin": None
            if self.frame is None
            else {
                "lat_deg": self.frame.lat0_deg,
                "lon_deg": self.frame.lon0_deg,
                "height_m": self.frame.h0_m,
            },
            "gyro_bias_rad_s": self.cascade.bias.x.tolist(),
            "fixes_used": self.n_fixes,
            "event_counts": counts,
        }

    def step(self, sample: Sample) -> Output | None:
        """Process one sample; an :class:`Output` for each IMU sample."""
        sample = self.guard.admit(sample)
        if sample is None:
            return None
        if isinstance(sample, ImuSample):
            return self._imu(sample)
        if isinstance(sample, GnssSample):
            self._gnss(sample)
        elif isinstance(sample, MagSample):
            pass  # the paper's anchor node has no magnetometer
        return None

    # ------------------------------------------------------------------ smoothing
    def _flush_record(self) -> None:
        if self.smoothing_log is None or not self.initialised:
            return
        anchor_flush(self._st, self._kf, self._prior, self._Phi, self._rec)
        self._drain_records()

    def _mark_update(self) -> None:
        if self.smoothing_log is not None and self._st[AT_HAS_PRIOR] == 0.0:
            self._prior[:] = self._kf
            self._st[AT_HAS_PRIOR] = 1.0

    # ------------------------------------------------------------------ filter
    def _predict_to(self, t: float) -> None:
        anchor_predict_to(self._st, self._prm, self._kf, self._prior, self._Phi, self._rec, float(t))
        self._drain_records()

    def _reject(self, s: GnssSample, reason: str, **extra: Any) -> None:
        self.events.append({"type": "fix_rejected", "t": s.t, "reason": reason, "num_sv": s.num_sv, **extra})

    def _gnss(self, s: GnssSample) -> None:
        k = self.config.kf
        if not s.valid or not (math.isfinite(s.lat_deg) and math.isfinite(s.lon_deg)):
            self._reject(s, "invalid")
            return
        if s.num_sv < 0 and not k.accept_unknown_num_sv:
            self._reject(s, "num_sv_unknown")
            return
        if 0 <= s.num_sv < k.min_satellites:
            self._reject(s, "num_sv")
            return
        # a fix without height (2D) updates the horizontal only; an origin set from one has
        # height 0 until the first fix with a height re-initialises the vertical
        has_height = math.isfinite(s.height_m)
        height = s.height_m if has_height else (self.frame.h0_m if self.frame else 0.0)
        if self.frame is None:
            self._origin_2d = not has_height
            self.frame = TangentPlane(s.lat_deg, s.lon_deg, height)
            self._frame[:] = self.frame.constants()
            self._st[AT_HAVE_FRAME] = 1.0
            if k.gravity_mps2 <= 0:
                self.g = normal_gravity(s.lat_deg, height)
            self.events.append({"type": "first_fix", "t": s.t, "num_sv": s.num_sv, "pdop": s.pdop})
        r_n = self.frame.to_ned(s.lat_deg, s.lon_deg, height)
        if self.frame.follow(
            r_n, self.reanchor_distance_m
        ):  # long routes: the plane re-linearised at the fix (same coordinates)
            self._frame[:] = self.frame.constants()
        z, H, R = gnss_position_measurement(s, r_n, k.uere_m, k.default_dop)
        vel = (
            gnss_velocity_measurement(s, k.vel_noise_mps, k.min_course_speed_mps) if k.use_velocity else None
        )
        self._attitude_aiding(s)
        if not self.initialised:
            self.x = np.zeros(N_STATES)
            self.x[POS] = z
            self.P = np.zeros((N_STATES, N_STATES))
            self.P[POS, POS] = R
            self.P[VEL, VEL] = _I3 * k.init_vel_std_mps**2
            if vel is not None and vel[0].size >= 2:
                self.x[3 : 3 + vel[0].size] = vel[0]
            self.initialised = True
            self.t_x = s.t
            self.t_fix = s.t
            self.n_fixes += 1
            self._flush_record()
            return
        self._predict_to(s.t)
        self._mark_update()
        horizontal_only = not has_height
        if has_height and self._origin_2d:
            # part of this record's update for the smoother; the fix's height is in the
            # reset, so its update below takes the horizontal only (not the height twice)
            horizontal_only = True
            old = float(self.x[2])
            self.x[2] = z[2]
            self.P[2, :] = 0.0
            self.P[:, 2] = 0.0
            self.P[2, 2] = R[2, 2]
            self._origin_2d = False
            self.events.append({"type": "vertical_reset", "t": s.t, "jump_m": float(z[2] - old)})
        if horizontal_only:
            z, H, R = z[:2].copy(), H[:2].copy(), R[:2, :2].copy()
        gate = (
            (self._gate2 if horizontal_only else self._gate) if self.n_rejected < k.max_rejections else None
        )
        if gate is None and self._gate is not None:
            ip = slice(POS.start, POS.start + z.size)
            self.P[ip, ip] += R  # forced re-convergence after repeated rejections
        nis, accepted = self._update(z, H, R, gate)
        if accepted:
            self.n_rejected = 0
            self.t_fix = s.t
            self.n_fixes += 1
        else:
            self.n_rejected += 1
            self._reject(s, "nis", nis=nis)
        if vel is not None and accepted:
            self._update(vel[0], vel[1], vel[2], None)

    def _update(self, z: FloatArray, H: FloatArray, R: FloatArray, gate: float | None) -> tuple[float, bool]:
        """Kalman update in place (:func:`iotnav.kalman.update_selected`; ``H`` has unit rows)."""
        idx = np.argmax(H, axis=1)
        m = idx.size
        nis, ok = kalman.update_selected(
            self.x, self.P, idx, z, R, math.inf if gate is None else gate, np.empty(m), np.empty((m, m))
        )
        return float(nis), bool(ok)

    def _attitude_aiding(self, s: GnssSample) -> None:
        c = self.config
        self.static_det.update_speed(s.t, s.speed_mps)
        if math.isfinite(s.speed_mps):
            dt_v = s.t - self.t_speed
            self.a_long = (s.speed_mps - self.v_gnss) / dt_v if 0.0 < dt_v <= 2.5 else 0.0
            self.v_gnss, self.t_speed = s.speed_mps, s.t
        moving = s.course_valid and math.isfinite(s.speed_mps) and s.speed_mps >= c.kf.min_course_speed_mps
        if moving and not self.static:
            self.cascade.aid_heading(wrap(s.course_rad + self.mount.mount_yaw_rad))
        old = self.mount.mount_yaw_rad
        ev = self.mount.add_gnss(s.t, s.speed_mps, s.course_rad, s.course_valid, self.static)
        if ev is not None:
            self.events.append(ev)
            if ev["applied"]:
                self.cascade.rotate_heading(wrap(self.mount.mount_yaw_rad - old))

    def _imu(self, s: ImuSample) -> Output:
        """One IMU sample: :meth:`imu_block` on a one-sample block."""
        return self._one.run(self.imu_block, s)

    def imu_block(
        self,
        t: FloatArray,
        acc: tuple[FloatArray, FloatArray, FloatArray],
        gyro: tuple[FloatArray, FloatArray, FloatArray],
        out: OutputBlock,
        i0: int,
        i1: int,
    ) -> None:
        """Process IMU samples ``i0 .. i1-1`` with :func:`anchor_imu_kernel`, row ``k`` of ``out`` for sample ``k``.

        ``t`` device time (s); ``acc`` specific force along sensor x, y, z (m/s^2); ``gyro``
        angular rate about sensor x, y, z (rad/s). Events and the smoothing records are moved
        to Python here, between kernel calls.
        """
        fe, mount = front_end(self.cascade, self.static_det), self.mount
        k = i0
        while k < i1:
            k, flags = anchor_imu_kernel(
                t,
                acc[0],
                acc[1],
                acc[2],
                gyro[0],
                gyro[1],
                gyro[2],
                out.floats,
                out.static,
                out.source,
                k,
                i1,
                self._st,
                self._prm,
                self._frame,
                self._kf,
                self._prior,
                self._Phi,
                self._rec,
                fe,
                mount.imu_sums,
                float(mount.mount_yaw_rad),
                bool(mount.known),
                bool(mount.done),
            )
            if flags & EV_STATIC:
                self.events.append(
                    {"type": "static_start" if self.static else "static_end", "t": float(t[k - 1])}
                )
            if flags & EV_FULL:
                self._drain_records()
        self._drain_records()
