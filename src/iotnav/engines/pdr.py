"""``pdr``: pedestrian dead reckoning -- steps along a gyro heading, reset by GNSS in a small KF.

For a walker carrying the device (hand-held), a strapdown INS on a consumer IMU drifts by
about the distance walked within 15-30 s of GNSS outage; counting steps does not (the error
grows with the step-length and heading errors, not with the double integral of the
accelerometer). Blocks:

1. **Steps** (:mod:`iotnav.techniques.steps`): peaks of the low-passed specific-force norm,
   Weinberg length ``L = s K (a_max - a_min)^(1/4)`` with the KF's step scale ``s``.
2. **Device yaw** ``psi_d`` by integrating the gyro about the vertical: the down direction in
   ``b`` is ``d_b = -f_lp / |f_lp|`` (``f_lp`` the accelerometer low-passed with
   ``gravity_tau_s``), ``d psi_d / dt = (omega_b - b_g) . d_b``. The gyro bias ``b_g`` is the
   mean rate while static (the initial static period, then any later one, time constant
   ``bias_tau_s``); static is: no step for ``static_after_s`` and a smoothed gyro norm below
   ``static_gyro_rads``. While static the output velocity is zero.
3. **KF** with the named state ``x = [north, east, dpsi, s]`` (m, m, rad, 1): ``dpsi`` is the
   offset between the device yaw and the walking direction (``psi_w = psi_d + dpsi``; it also
   absorbs the unknown initial yaw and the residual gyro drift, as a random walk of
   ``heading_rw_rad_rsqrt_s``), ``s`` scales the configured Weinberg ``K`` (random walk
   ``scale_rw_rsqrt_s``). Per step::

       north += L cos(psi_w),  east += L sin(psi_w)
       F = I + d(north, east)/d(dpsi, s),  Q = R(psi_w) diag(sa^2 L^2, sc^2 L^2) R(psi_w)^T
           (+ the random walks of dpsi and s over the time since the last prediction)

   Measurements (:func:`iotnav.kalman.update`: Cholesky, Joseph form, NIS gate):

   * GNSS position, ``z = [north, east]`` of the fix, ``H = [I 0 0]``,
     ``R = (h_acc / sqrt 2)^2 I`` from the receiver's horizontal (2D) accuracy (else
     ``uere_m HDOP / sqrt 2``, HDOP from PDOP when only that is reported, else
     ``default_fix_std_m``; :mod:`iotnav.gnss_accuracy`);
   * GNSS course while walking faster than ``min_course_speed_mps``: ``z = course - psi_d``,
     ``H = [0 0 1 0]``, ``R = (s_acc / speed)^2 + course_std_floor_rad^2``; the first such
     course initialises ``dpsi`` (no step moves the position before: its variance grows by
     ``L^2`` per step instead);
   * step scale from the online Weinberg calibration
     (:class:`~iotnav.techniques.steps.StepLengthCalibrator`: GNSS distance ``sum v dt`` over
     ``calib_interval_s`` against the steps' fourth roots), ``z = K_interval / K``,
     ``H = [0 0 0 1]``, ``R = scale_meas_std^2``.

   Without GNSS it is pure PDR. A fix rejected by the gate ``max_rejects`` times in a row is
   applied anyway with the position variance reset (re-acquisition), as an event.

Outputs: one :class:`~iotnav.engines.base.Output` per IMU sample, ``source`` ``fix`` up to
``fix_hold_s`` after an applied fix, ``dr`` otherwise, ``none`` before the first fix; the
1-sigma from the KF; ``roll`` and ``pitch`` of the sensor from gravity, ``yaw`` the walking
heading (NaN before it is known); ``down`` follows the fixes' heights (low-pass, held in
outages). ``mount_yaw_rad`` is NaN: without a magnetometer the sensor's absolute yaw, hence
its angle to the walking direction, is not observable here (``dpsi`` is reported instead).

Bad input is never fixed silently: samples with non-finite values or a time before the
previous one (:class:`~iotnav.engines.base.InputGuard`, no output), invalid GNSS epochs and
IMU gaps longer than ``max_imu_gap_s`` (``imu_gap_not_integrated``: propagated over no time; the sample still gives an
output) are counted by reason (``summary()["skipped"]``; the first of each reason is an
event).

Compiled: the IMU step (blocks 1-2, the step's KF prediction and the output row) is
:func:`iotnav.engines.pdr_kernel.imu_run`, run by :meth:`PdrEngine.imu_block` over the IMU
samples between GNSS epochs (batch) and by ``step()`` on one sample (streaming); the GNSS
updates stay in Python. It reproduces the per-sample Python engine it replaced to 1e-9
(``tests/test_pdr_kernel.py``).

References: H. Weinberg, Analog Devices AN-602 (2002), step length; R. Harle, IEEE Commun.
Surveys Tuts. 15(3) (2013), step-and-heading systems.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import numpy.typing as npt

from iotnav.engines import pdr_kernel as K
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
from iotnav.gnss_accuracy import position_sigmas
from iotnav.kalman import gate_threshold, update
from iotnav.techniques.steps import StepConfig, StepDetector, StepLengthCalibrator

FloatArray = npt.NDArray[np.float64]

__all__ = ["DPSI", "N_STATE", "POS", "SCALE", "PdrConfig", "PdrEngine"]

#: Named state layout of the KF (STYLE §5).
POS = slice(0, 2)  # north, east, m
DPSI = 2  # walking direction minus device yaw, rad
SCALE = 3  # step-length scale on the configured Weinberg K, 1
N_STATE = 4

#: Default step detector for a hand-held device (tuned on the rtklibexplorer walk: weak
#: vertical bounce, dynamic norm std about 0.35 m/s^2 while walking).
PDR_STEPS = StepConfig(threshold_mps2=0.25, release_mps2=-0.15, min_interval_s=0.35)


@dataclass(frozen=True)
class PdrConfig:
    """Configuration of :class:`PdrEngine` (``[pdr]`` table, steps in ``[pdr.steps]``).

    Attributes
    ----------
    steps : StepConfig
        Step detector and Weinberg K.
    gravity_tau_s : float
        Low-pass of the accelerometer giving the vertical for the gyro, s.
    bias_tau_s : float
        Time constant of the gyro-bias average while static, s (the first static seconds use
        the plain mean).
    static_gyro_rads : float
        Static when the smoothed ``|omega - b_g|`` is below this, rad/s ...
    static_after_s : float
        ... and no step for this long, s.
    max_imu_gap_s : float
        Longer IMU gaps are not integrated (counted), s.
    heading_init_std_rad : float
        1-sigma of ``dpsi`` set from the first course, floor, rad.
    heading_rw_rad_rsqrt_s : float
        Random walk of ``dpsi`` (device turning in the hand, residual gyro drift), rad/sqrt(s).
    scale_init_std : float
        Initial 1-sigma of the step scale ``s``.
    scale_rw_rsqrt_s : float
        Random walk of ``s``, 1/sqrt(s).
    step_along_std : float
        Along-track step-length noise as a fraction of ``L``.
    step_cross_std : float
        Cross-track noise per step as a fraction of ``L`` (heading jitter of a step).
    uere_m : float
        Range error used with HDOP when the receiver reports no accuracy, m.
    default_fix_std_m : float
        Per-axis 1-sigma of a fix with neither accuracy nor DOP, m.
    min_course_speed_mps : float
        GNSS course is used above this speed (and while stepping), m/s.
    course_std_floor_rad : float
        Floor of the course 1-sigma (gait sway of the device), rad.
    calib_interval_s : float
        Interval of the online Weinberg calibration, s.
    calib_forget : float
        Forgetting factor per interval of the calibration.
    scale_meas_std : float
        1-sigma of one interval's scale measurement (step-count and speed noise).
    gate_probability : float
        Chi-square probability of the NIS gate of every measurement.
    max_rejects : int
        Consecutive gated-out fixes after which a fix is applied with a position reset.
    fix_hold_s : float
        Output ``source`` is ``fix`` up to this long after an applied fix, s.
    height_tau_s : float
        Low-pass of the fixes' heights for ``down``, s.
    max_extrapolation_steps : float
        Between steps the position moves on at the last step's pace (output and GNSS epochs),
        up to this many step lengths past the last step (a step is confirmed after its peak).
    """

    steps: StepConfig = field(default_factory=lambda: PDR_STEPS)
    gravity_tau_s: float = 1.0
    bias_tau_s: float = 10.0
    static_gyro_rads: float = 0.1
    static_after_s: float = 1.5
    max_imu_gap_s: float = 0.5
    heading_init_std_rad: float = 0.1
    heading_rw_rad_rsqrt_s: float = 0.01
    scale_init_std: float = 0.5
    scale_rw_rsqrt_s: float = 0.005
    step_along_std: float = 0.2
    step_cross_std: float = 0.05
    uere_m: float = 3.0
    default_fix_std_m: float = 5.0
    min_course_speed_mps: float = 0.6
    course_std_floor_rad: float = 0.2
    calib_interval_s: float = 5.0
    calib_forget: float = 0.9
    scale_meas_std: float = 0.2
    gate_probability: float = 0.9999
    max_rejects: int = 5
    fix_hold_s: float = 1.5
    height_tau_s: float = 10.0
    max_extrapolation_steps: float = 1.5

    def to_dict(self) -> dict[str, Any]:
        """Plain nested dict (for ``summary.json``)."""
        return dataclasses.asdict(self)


class PdrEngine:
    """Pedestrian dead reckoning engine (module docstring); satisfies :class:`~iotnav.engines.base.BlockEngine`.

    The IMU step is the compiled :func:`iotnav.engines.pdr_kernel.imu_run`: :meth:`imu_block`
    runs it over a block of samples (batch) and ``step(ImuSample)`` over a one-sample block
    (streaming); the GNSS updates stay in Python. The scalars the kernel and the GNSS code
    share live in the float array ``_st`` (indices ``pdr_kernel.T_*``), read and written
    through the attributes below.
    """

    psi_d = StateSlot(K.T_PSI_D)  # device yaw, rad (arbitrary origin)
    gyro_var = StateSlot(K.T_GYRO_VAR)  # smoothed |omega - b_g|^2, (rad/s)^2
    t_imu = StateSlot(K.T_IMU)
    t_fix = StateSlot(K.T_FIX)
    t_pred = StateSlot(K.T_PRED)  # time of the last KF prediction
    t_pos = StateSlot(K.T_POS)  # time the KF position refers to, s
    adv = StateSlot(K.T_ADV)  # distance advanced into the current step at GNSS epochs, m
    speed = StateSlot(K.T_SPEED)  # walking speed from the last step, m/s
    L_last = StateSlot(K.T_L_LAST)  # last step length, m
    static = FlagSlot(K.T_STATIC)
    heading_known = FlagSlot(K.T_HEADING_KNOWN)
    down = StateSlot(K.T_DOWN)

    def __init__(self, config: PdrConfig | None = None) -> None:
        self.config = cfg = config or PdrConfig()
        self.events: list[dict[str, Any]] = []
        self.guard = InputGuard(self.events)
        self.detector = StepDetector(cfg.steps)
        self.calibrator = StepLengthCalibrator(cfg.steps.weinberg_k, cfg.calib_interval_s, cfg.calib_forget)
        self._st = np.zeros(K.N_ST)
        self.x = np.array([0.0, 0.0, 0.0, 1.0])
        self.P = np.diag([1e6, 1e6, math.pi**2, cfg.scale_init_std**2])
        self.frame: TangentPlane | None = None
        self._geo = np.full(5, math.nan)  # the frame's constants() for the kernel
        self.f_lp = np.zeros(3)  # low-passed specific force, m/s^2, b
        self.bias_g = np.zeros(3)  # gyro bias, rad/s, b
        self.gyro_var = math.nan
        self.t_imu = math.nan
        self.t_fix = -math.inf
        self.t_pred = math.nan
        self.t_pos = -math.inf
        self.static = True
        self.n_fixes = 0
        self.n_rejected = 0
        self.n_consecutive_rejects = 0
        self.n_course = 0
        self.n_scale = 0
        self._gate2 = gate_threshold(2, cfg.gate_probability)
        self._gate1 = gate_threshold(1, cfg.gate_probability)
        self._det_prm = K.step_params(cfg.steps)
        prm = np.empty(K.N_PRM)
        prm[K.K_GRAVITY_TAU] = cfg.gravity_tau_s
        prm[K.K_BIAS_TAU] = cfg.bias_tau_s
        prm[K.K_STATIC_GYRO] = cfg.static_gyro_rads
        prm[K.K_STATIC_AFTER] = cfg.static_after_s
        prm[K.K_MAX_IMU_GAP] = cfg.max_imu_gap_s
        prm[K.K_GROUP_DELAY] = cfg.steps.group_delay_s
        prm[K.K_WEINBERG_K] = cfg.steps.weinberg_k
        prm[K.K_MIN_LENGTH] = cfg.steps.min_length_m
        prm[K.K_MAX_LENGTH] = cfg.steps.max_length_m
        prm[K.K_MIN_INTERVAL] = cfg.steps.min_interval_s
        prm[K.K_FIX_HOLD] = cfg.fix_hold_s
        prm[K.K_MAX_EXTRAP] = cfg.max_extrapolation_steps
        prm[K.K_ALONG] = cfg.step_along_std
        prm[K.K_CROSS] = cfg.step_cross_std
        prm[K.K_HEADING_RW] = cfg.heading_rw_rad_rsqrt_s
        prm[K.K_SCALE_RW] = cfg.scale_rw_rsqrt_s
        self._prm = prm
        self._one = OneSampleBlock()

    # ------------------------------------------------------------------ protocol

    @property
    def mount_yaw_rad(self) -> float:
        """NaN: the sensor's yaw to the walking direction is not observable without a magnetometer."""
        return math.nan

    def step(self, sample: Sample) -> Output | None:
        """Process one sample; an :class:`Output` for every IMU sample, None otherwise."""
        sample = self.guard.admit(sample)
        if sample is None:
            return None
        if isinstance(sample, ImuSample):
            return self._one.run(self.imu_block, sample)
        if isinstance(sample, GnssSample):
            self._gnss(sample)
        elif not isinstance(sample, MagSample):
            self.guard.skip("unknown_sample", math.nan)
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
        """Process IMU samples ``i0 .. i1-1`` with :func:`~iotnav.engines.pdr_kernel.imu_run`, row ``k`` of ``out`` for sample ``k``.

        ``t`` device time (s); ``acc`` specific force along sensor x, y, z (m/s^2); ``gyro``
        angular rate about sensor x, y, z (rad/s). Gaps longer than ``max_imu_gap_s`` are
        counted here, between kernel calls.
        """
        st, cal = self._st, self.calibrator
        # the calibrator's open interval collects the steps' roots (StepLengthCalibrator.add_step)
        st[K.T_CAL_ON] = 1.0 if math.isfinite(cal._t0) else 0.0
        st[K.T_CAL_R], st[K.T_CAL_N] = cal._r, cal._n
        k = i0
        while k < i1:
            k, flags = K.imu_run(
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
                st,
                self.x,
                self.P,
                self.f_lp,
                self.bias_g,
                self.detector.state,
                self._det_prm,
                self._prm,
                self._geo,
            )
            if flags & K.EV_GAP:
                self.guard.skip("imu_gap_not_integrated", float(t[k - 1]))
        cal._r, cal._n = float(st[K.T_CAL_R]), int(st[K.T_CAL_N])

    def summary(self) -> dict[str, Any]:
        """Configuration and final state (for ``summary.json``)."""
        k = self.config.steps.weinberg_k
        return {
            "skipped": dict(self.guard.skipped),
            "engine": "pdr",
            "config": self.config.to_dict(),
            "steps": self.detector.n_steps,
            "steps_merged": self.detector.n_merged,
            "step_scale": float(self.x[SCALE]),
            "weinberg_k_effective": float(self.x[SCALE]) * k,
            "weinberg_k_calibrated": self.calibrator.k,
            "calibration_intervals": self.calibrator.n_intervals,
            "heading_offset_rad": float(self.x[DPSI]) if self.heading_known else math.nan,
            "heading_offset_std_rad": math.sqrt(self.P[DPSI, DPSI]) if self.heading_known else math.nan,
            "gyro_bias_rads": self.bias_g.tolist(),
            "fixes_applied": self.n_fixes,
            "fixes_rejected": self.n_rejected,
            "course_updates": self.n_course,
            "scale_updates": self.n_scale,
            "mount_yaw_rad": math.nan,
        }

    # ------------------------------------------------------------------ helpers

    def _predict_time(self, t: float) -> None:
        """Random walks of ``dpsi`` and ``s`` from the last prediction to ``t``."""
        K.predict_time(self._st, self.P, self._prm, t)

    def _advance(self, d: float, s: float) -> None:
        """Move ``d`` metres along the walking heading (``d`` proportional to the scale ``s``)."""
        K.advance(self._st, self.x, self.P, self._prm, d, s)

    def _extrapolation(self, t: float) -> float:
        """Distance walked since the position's time ``t_pos`` at the current pace, m (within one step)."""
        return float(K.extrapolation(self._st, self._prm, t))

    # ------------------------------------------------------------------ GNSS

    def _gnss(self, g: GnssSample) -> None:
        c = self.config
        t = float(g.t)
        if not (g.valid and math.isfinite(g.lat_deg) and math.isfinite(g.lon_deg)):
            self.guard.skip("gnss_invalid", t)
            return
        h = g.height_m if math.isfinite(g.height_m) else 0.0
        if self.frame is None:
            self.frame = TangentPlane(g.lat_deg, g.lon_deg, h)
            self._st[K.T_HAS_FRAME] = 1.0
        z_ne = self.frame.to_ned(g.lat_deg, g.lon_deg, h)
        self.frame.follow(z_ne)  # long routes: the plane re-linearised at the fix (same coordinates)
        self._geo[:] = self.frame.constants()  # the kernel's copy (the plane may have moved)
        fig = position_sigmas(g.h_acc_m, g.v_acc_m, g.hdop, g.pdop, c.uere_m, math.nan)
        sig = c.default_fix_std_m if fig.source[0] == "default" else fig.north_east_m
        self._predict_time(t)
        e = self._extrapolation(t)
        if e > 0:
            self._advance(e, self.x[SCALE])
            self.adv += e
        self.t_pos = max(self.t_pos, t)
        self._fix(t, z_ne, sig)
        if math.isfinite(g.height_m):
            if self.n_fixes <= 1:
                self.down = float(z_ne[2])
            else:
                self.down += (1.0 - math.exp(-1.0 / max(c.height_tau_s, 1e-9))) * (float(z_ne[2]) - self.down)
        # velocity: course and calibration
        if math.isfinite(g.vn) and math.isfinite(g.ve):
            speed, course = math.hypot(g.vn, g.ve), math.atan2(g.ve, g.vn)
        elif math.isfinite(g.speed_mps):
            speed, course = g.speed_mps, g.course_rad if g.course_valid else math.nan
        else:
            self.calibrator.reset_interval(t)
            return
        walking = t - self.detector.last_step_t < 1.0
        k_int = self.calibrator.add_speed(t, speed if walking else 0.0)
        if k_int is not None:
            self._scale_update(t, k_int / c.steps.weinberg_k)
        if walking and speed > c.min_course_speed_mps and math.isfinite(course):
            s_acc = g.s_acc_mps if math.isfinite(g.s_acc_mps) else 0.3
            self._course_update(t, course, math.hypot(s_acc / speed, c.course_std_floor_rad))

    def _fix(self, t: float, z_ne: FloatArray, sig: float) -> None:
        c = self.config
        R = np.eye(2) * sig * sig
        H = np.zeros((2, N_STATE))
        H[0, 0] = H[1, 1] = 1.0
        if self.n_fixes == 0:
            self.x[POS] = z_ne[:2]
            self.P[POS, :] = 0.0
            self.P[:, POS] = 0.0
            self.P[POS, POS] = R
            self._accept_fix(t)
            return
        res = update(self.x, self.P, z_ne[:2], H, R, gate=self._gate2)
        if res.accepted:
            self.x[:], self.P[:] = res.x, res.P
            self._accept_fix(t)
            return
        self.n_rejected += 1
        self.n_consecutive_rejects += 1
        self.events.append({"t": t, "type": "fix_rejected", "nis": res.nis, "test_ratio": res.test_ratio})
        if self.n_consecutive_rejects >= c.max_rejects:
            self.x[POS] = z_ne[:2]
            self.P[POS, :] = 0.0
            self.P[:, POS] = 0.0
            self.P[POS, POS] = R
            self.events.append({"t": t, "type": "position_reset"})
            self._accept_fix(t)

    def _accept_fix(self, t: float) -> None:
        self.n_fixes += 1
        self.n_consecutive_rejects = 0
        self.t_fix = t

    def _course_update(self, t: float, course: float, sig: float) -> None:
        if not self.heading_known:
            self.x[DPSI] = K.wrap(course - self.psi_d)
            self.P[DPSI, :] = 0.0
            self.P[:, DPSI] = 0.0
            self.P[DPSI, DPSI] = max(sig, self.config.heading_init_std_rad) ** 2
            self.heading_known = True
            self.events.append({"t": t, "type": "heading_init", "dpsi_rad": float(self.x[DPSI])})
            return
        H = np.zeros((1, N_STATE))
        H[0, DPSI] = 1.0
        # innovation wrapped: measurement expressed next to the prediction
        z = np.array([self.x[DPSI] + K.wrap(course - self.psi_d - self.x[DPSI])])
        res = update(self.x, self.P, z, H, np.array([[sig * sig]]), gate=self._gate1)
        if res.accepted:
            self.x[:], self.P[:] = res.x, res.P
            self.x[DPSI] = K.wrap(self.x[DPSI])
            self.n_course += 1

    def _scale_update(self, t: float, z_scale: float) -> None:
        H = np.zeros((1, N_STATE))
        H[0, SCALE] = 1.0
        R = np.array([[self.config.scale_meas_std**2]])
        res = update(self.x, self.P, np.array([z_scale]), H, R, gate=self._gate1)
        if res.accepted:
            self.x[:], self.P[:] = res.x, res.P
            self.n_scale += 1
