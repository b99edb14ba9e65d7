"""The Forno et al. 2020 low-effort pipeline (Fig. 1): blocks 1-6 behind one ``step()``.

Wiring, per sample:

GNSS epoch
    1. block 1 accepts or refuses the fix (validity, PDOP <= 10, optional satellite count;
       without a stored position the first fix must also have a settled PDOP, see
       :mod:`iotnav.techniques.last_position`); refused fixes become ``fix_rejected`` events
       and are not used at all;
    the first accepted fix sets the NED origin when no stored position exists (otherwise the
    stored last position is the origin), raises ``moved_while_off`` when it lies far from the
    stored position, and initialises the fusion filter;
    3. the GPS speed feeds the static detector;
    2. while moving above the course-speed threshold, the course plus block 5's mount angle aids
       the yaw filter;
    5. the interval since the previous epoch is offered to the mount aligner; an accepted new
       angle rotates the yaw filter's heading by the change;
    4./6. moving: the fix (position, and the receiver's NED velocity when it reports one, else
       horizontal velocity from speed and course) updates the fusion filter, with the noise of
       :func:`iotnav.techniques.fusion_kf.gnss_noise` (the receiver's ``h_acc/v_acc/s_acc``
       when finite, else DOP x UERE); static: the fix goes to the 3-level low-pass filter and never to the
       fusion filter; the low-pass output (when it changes) replaces it as the position
       measurement, with ``R_lp = R_fix / (1 + N dt / (2 tau))`` for an average of ``N`` fixes
       ``dt`` apart whose errors are correlated over ``tau`` (``lowpass_corr_time_s``), and a
       zero-velocity update is applied.
IMU sample
    2. the cascaded filter produces ``C_nb``;
    3. ``y_n = C_nb y_b`` decides static / moving (events on every change; the low-pass
       buffers are reset on both transitions);
    5. the sensor-frame specific force and the vertical rate are accumulated (block 5 levels
       them against its own gravity reference, not against the tilt filter);
    6. the fusion filter predicts with ``a_n = C_nb f_b + g_n`` -- except while static with
       block 4 active (``static_hold``): the device does not move, so the position and its
       covariance hold between low-pass measurements (the paper's "sleep mode"); one
       :class:`Output` row is returned.
Magnetometer sample
    aids the yaw filter when ``yaw.use_mag``.

Heading unresolved (designed here, issue 16 "do no harm")
    ``C_nb`` places the horizontal specific force in ``n`` only once the sensor's heading is
    known: the yaw filter has had a heading (a GPS course above ``yaw.min_course_speed_mps`` or
    the magnetometer) and, with block 5 on, a mount angle has been applied (the yaw filter is
    aided with course + mount angle, so before it the sensor heading is off by the whole
    mount). Until then block 6 predicts with no horizontal input (constant velocity; the
    vertical ``f_D + g`` still applies) and counts the force it cannot place as white
    acceleration noise, PSD ``q_a + |f_h|^2 T`` with ``T`` = ``UNRESOLVED_CORR_S`` (1 s: one
    GPS interval of a 1 Hz receiver; the force is taken as unknown in direction over it;
    :func:`~iotnav.techniques.fusion_kf.fusion_predict` has one PSD for the three axes, so the
    vertical gets it too; the RTS smoother reads it from the recorded covariances). Integrating
    the force along an assumed heading instead pushed the track sideways off the fixes before
    the first mount estimate (the measurements: ``benchmarks/results/pipeline_history.md``).

The IMU step is one compiled kernel, :func:`pipeline_imu_kernel`, over a block of samples
(:meth:`Pipeline.imu_block`, used by :func:`~iotnav.engines.base.run_batch`);
``step(ImuSample)`` runs it on a one-sample block, so streaming and batch execute the same
code. It returns to Python only at a sample that raises an event (static change, boot
movement). Scalars shared with the Python GNSS code live in the array ``Pipeline._st``.

Before any accepted fix: with a stored position the output is that position (source
``last_position``) while the INS sees no movement; once it does (block 3's accelerometer test,
no GPS speed being available) the source becomes ``dr`` and the horizontal sigma grows at
``boot_walk_speed_mps``. Without a stored position the output is NaN (source ``none``).

NED origin: the stored last position when one was loaded, else the first accepted fix.

Smoothing (``fusion.smoothing``, ``iotnav run --smooth``; off by default)
    The fusion filter (block 6) keeps a :class:`~iotnav.engines.smoother.SmoothingLog` for the
    fixed-interval RTS smoother (:mod:`iotnav.engines.smoother`). Record points: the filter's
    initialisation, every GNSS epoch that reaches the filter (position and velocity updates,
    or the low-pass position and zero-velocity update while static; a fix refused by the NIS
    gate still makes a record, with prior = posterior) and every ``fusion.record_every``-th
    output row once the filter runs. The kernel accumulates ``Phi``, the exact product of the
    per-step transitions the filter applied
    (:func:`~iotnav.techniques.fusion_kf.fusion_transition_step`: ``F`` with the bias coupling
    through each step's ``C_nb``); a held step (static with ``static_hold``) applies none, so
    it contributes the identity and no process noise, as in the forward filter. The recorded
    prior is the filter before the epoch's updates, the posterior the filter after them; a
    forced fix (:meth:`~iotnav.techniques.fusion_kf.FusionKF.update_position` after an outage
    or repeated rejections) widens the position covariance before its update, and that
    widening is part of the update, not of the recorded prior: recording the widened prior
    would tell the smoother that the position may jump at the tunnel exit, and the exit fix
    would barely correct the outage (pipeline_history.md). The pipeline does not predict to the fix time, so a GNSS record is
    stamped one ulp after the latest IMU sample: the row of that sample (written before the
    fix) is corrected as the prior, the later rows from the posterior.

    Rows that are not estimates of the fusion filter are left unchanged: before the filter is
    initialised (``none``, the stored ``last_position`` and the boot dead reckoning ``dr``)
    the rows precede the first record point, which :func:`~iotnav.engines.smoother.smooth_output`
    does not touch. The ``lowpass`` rows while static are the fusion filter's held state (the
    low-pass output is its measurement), so they are smoothed like the others. Attitude is not
    in the filter's state and is not corrected.

    Acceleration error (:class:`~iotnav.engines.smoother.AccelErrorModel`): off by default
    (``fusion.smoothing_accel_rw_mps2_sqrt_s = 0``), so the smoother runs on the filter's own
    model, white acceleration noise plus the sensor-frame accelerometer bias. A held step is
    not kinematic (the position does not integrate the velocity), so the augmentation cannot
    run over the default ``static_hold``; with ``static_hold = false`` it helps on car-tunnel
    (pipeline_history.md), so it is available (``smoothing_accel_error``) but not the default.
"""

from __future__ import annotations

import math
from typing import Any

import numba
import numpy as np
import numpy.typing as npt

from iotnav.engines.base import (
    C_T,
    SRC_DR,
    SRC_FIX,
    SRC_LAST_POSITION,
    SRC_LOWPASS,
    SRC_NONE,
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
    write_attitude,
    write_no_position,
    write_position,
)
from iotnav.engines.config import PipelineConfig
from iotnav.engines.smoother import (
    AccelErrorModel,
    KinematicRecords,
    SmoothingLog,
    record_size,
    write_record,
)
from iotnav.geo import normal_gravity
from iotnav.techniques.cascade import (
    CS_C,
    CS_OMEGA,
    CascadeConfig,
    CascadeKF,
    FrontEnd,
    front_end,
    front_end_step,
)
from iotnav.techniques.fusion_kf import (
    F_INIT,
    F_P,
    FP_QA,
    N_STATES,
    POS,
    VEL,
    FusionKF,
    fusion_predict,
    fusion_transition_step,
    gnss_noise,
)
from iotnav.techniques.last_position import LastPositionLogic, LastPositionStore, StoredPosition
from iotnav.techniques.lowpass3 import Lowpass3
from iotnav.techniques.mount import MountAligner, accumulate_body, wrap
from iotnav.techniques.static import StaticDetector
from iotnav.techniques.yaw_kf import Y_INIT

FloatArray = npt.NDArray[np.float64]

_G_STD = 9.80665
#: Correlation time given to the horizontal specific force while the heading is unresolved, s
#: (its PSD is ``|f_h|^2`` times this; module docstring, "Heading unresolved"): one interval
#: of a 1 Hz GPS receiver.
UNRESOLVED_CORR_S = 1.0

# Scalars shared by the compiled IMU kernel and the Python GNSS code (``Pipeline._st``).
(
    ST_T_PREV,
    ST_STATIC,
    ST_A_LONG,
    ST_V_GNSS,
    ST_T_SPEED,
    ST_T_FIX,
    ST_T_BOOT_MOVE,
    ST_G,
    ST_HAVE_FRAME,
    ST_ROWS,
    ST_N_REC,
) = range(11)
ST_SIZE = 11
# Engine parameters of the kernel (``Pipeline._prm``).
(
    PR_USE_MOUNT,
    PR_USE_LOWPASS,
    PR_STATIC_HOLD,
    PR_FIX_HOLD,
    PR_STORED_STD,
    PR_WALK,
    PR_SMOOTH,
    PR_RECORD_EVERY,
) = range(8)
# Flags returned by the kernel when a sample needs Python (events, low-pass reset, records).
EV_STATIC = 1
EV_BOOT_MOVE = 2
EV_FULL = 4
#: Columns of a smoothing record of the fusion filter (:func:`~iotnav.engines.smoother.write_record`).
REC_SIZE = record_size(N_STATES)


@numba.njit(cache=True)
def pipeline_imu_kernel(
    t: FloatArray,
    ax: FloatArray,
    ay: FloatArray,
    az: FloatArray,
    gx: FloatArray,
    gy: FloatArray,
    gz: FloatArray,
    floats: FloatArray,
    static_out: npt.NDArray[np.bool_],
    source_out: npt.NDArray[np.int8],
    i0: int,
    i1: int,
    st: FloatArray,
    prm: FloatArray,
    frame: FloatArray,
    fe: FrontEnd,
    mount_sums: FloatArray,
    fus_s: FloatArray,
    fus_p: FloatArray,
    Phi: FloatArray,
    rec: FloatArray,
    mount_yaw: float,
    mount_known: bool,
) -> tuple[int, int]:
    """The IMU step of :class:`Pipeline` over samples ``i0 .. i1-1`` (module docstring, "IMU sample").

    Reads device time ``t`` (s), specific force ``ax, ay, az`` (m/s^2) and rate ``gx, gy, gz``
    (rad/s) in the sensor frame; writes row ``k`` of the output columns for sample ``k``.
    Stops after a sample that needs Python (a static change or the boot movement), or before a
    sample when the smoothing record buffer ``rec`` is full, and returns ``(next index, EV_*
    flags)``; ``(i1, 0)`` when the block is done. When smoothing, ``Phi`` (81,) accumulates the
    fusion filter's transition (:func:`~iotnav.techniques.fusion_kf.fusion_transition_step`) and
    every ``record_every``-th row with the filter running is a record point.
    """
    use_mount = prm[PR_USE_MOUNT] != 0.0
    smoothing = prm[PR_SMOOTH] != 0.0
    use_lowpass = prm[PR_USE_LOWPASS] != 0.0
    hold = use_lowpass and prm[PR_STATIC_HOLD] != 0.0
    cos_mu = math.cos(mount_yaw)
    sin_mu = math.sin(mount_yaw)
    cs = fe.cs
    C = cs[CS_C : CS_C + 9]
    zero3 = np.zeros(3)
    for k in range(i0, i1):
        if smoothing and st[ST_N_REC] + 1.0 > rec.shape[0]:
            return k, EV_FULL
        tk = t[k]
        a0, a1, a2 = ax[k], ay[k], az[k]
        dt = tk - st[ST_T_PREV] if math.isfinite(st[ST_T_PREV]) else 0.0
        st[ST_T_PREV] = tk
        g = st[ST_G]
        was = st[ST_STATIC] != 0.0
        init = fus_s[F_INIT] != 0.0
        v_dr = math.hypot(fus_s[3], fus_s[4]) if init else math.nan
        f0, f1, f2, static = front_end_step(
            fe,
            tk,
            a0,
            a1,
            a2,
            gx[k],
            gy[k],
            gz[k],
            dt,
            was,
            g,
            st[ST_A_LONG],
            st[ST_V_GNSS],
            st[ST_T_SPEED],
            v_dr,
        )
        st[ST_STATIC] = 1.0 if static else 0.0
        flags = EV_STATIC if static != was else 0
        if use_mount:
            r_yaw = C[6] * cs[CS_OMEGA] + C[7] * cs[CS_OMEGA + 1] + C[8] * cs[CS_OMEGA + 2]
            accumulate_body(mount_sums, a0, a1, a2, r_yaw)
        if not (static and hold):
            if fe.yaw_s[Y_INIT] == 0.0 or (use_mount and not mount_known):
                # heading unresolved (module docstring): the horizontal specific force cannot
                # be placed in n; it is process noise, not an input
                qa = fus_p[FP_QA]
                fus_p[FP_QA] = qa + (f0 * f0 + f1 * f1) * UNRESOLVED_CORR_S
                fusion_predict(fus_s, fus_p, 0.0, 0.0, f2 + g, C, dt)
                fus_p[FP_QA] = qa
            else:
                fusion_predict(fus_s, fus_p, f0, f1, f2 + g, C, dt)
            if smoothing and init and dt > 0.0:
                fusion_transition_step(Phi, C, dt)
        floats[C_T, k] = tk
        write_attitude(floats, k, C, cos_mu, sin_mu, mount_known)
        static_out[k] = static
        if init:
            write_position(
                floats, k, fus_s[0:3], fus_s[3:6], math.sqrt(fus_s[F_P]), math.sqrt(fus_s[F_P + 10]), frame
            )
            if static and use_lowpass:
                source_out[k] = SRC_LOWPASS
            elif tk - st[ST_T_FIX] <= prm[PR_FIX_HOLD]:
                source_out[k] = SRC_FIX
            else:
                source_out[k] = SRC_DR
            if smoothing:
                st[ST_ROWS] += 1.0
                if st[ST_ROWS] >= prm[PR_RECORD_EVERY]:
                    n_rec = int(st[ST_N_REC])
                    write_record(rec, n_rec, tk, fus_s, fus_s, Phi, N_STATES)
                    st[ST_N_REC] = n_rec + 1
                    st[ST_ROWS] = 0.0
        elif st[ST_HAVE_FRAME] != 0.0:  # stored last position, no fix yet
            std = prm[PR_STORED_STD]
            source = SRC_LAST_POSITION
            if not static and not math.isnan(tk) and math.isnan(st[ST_T_BOOT_MOVE]) and dt > 0:
                st[ST_T_BOOT_MOVE] = tk
                flags |= EV_BOOT_MOVE
            if math.isfinite(st[ST_T_BOOT_MOVE]):
                std = std + prm[PR_WALK] * (tk - st[ST_T_BOOT_MOVE])
                source = SRC_DR
            write_position(floats, k, zero3, zero3, std, std, frame)
            source_out[k] = source
        else:
            write_no_position(floats, k)
            source_out[k] = SRC_NONE
        if flags:
            return k + 1, flags
    return i1, 0


class Pipeline(KinematicRecords):
    """Streaming engine for Forno et al. 2020 Fig. 1.

    Parameters
    ----------
    config : PipelineConfig, optional
        Every tunable (paper defaults).
    stored : StoredPosition, optional
        Last known position at boot (overrides ``store.load()``).
    store : LastPositionStore, optional
        Where the latest good position is saved periodically (and loaded at boot).
    """

    _kin_pos, _kin_vel, _kin_states, _kin_n_rec = POS, VEL, N_STATES, ST_N_REC

    def __init__(
        self,
        config: PipelineConfig | None = None,
        stored: StoredPosition | None = None,
        store: LastPositionStore | None = None,
    ) -> None:
        self.config = c = config or PipelineConfig()
        if stored is None and store is not None:
            stored = store.load()
        self.store = store
        self.cascade = CascadeKF(CascadeConfig(c.tilt, c.yaw, c.gyro_bias))
        self.static_det = StaticDetector(c.static)
        self.lowpass = Lowpass3(c.lowpass3)
        self.mount = MountAligner(c.mount)
        self.fusion = FusionKF(c.fusion)
        self.boot = LastPositionLogic(c.last_position, stored)
        self.events: list[dict[str, Any]] = []
        self.guard = InputGuard(self.events)
        self.frame: TangentPlane | None = None
        self._frame = np.zeros(5)  # TangentPlane constants for the kernel
        self._st = np.zeros(ST_SIZE)
        self._prm = np.array(
            [
                float(c.pipeline.use_mount),
                float(c.pipeline.use_lowpass),
                float(c.pipeline.static_hold),
                c.pipeline.fix_hold_s,
                c.last_position.stored_std_m,
                c.last_position.boot_walk_speed_mps,
                float(c.fusion.smoothing),
                float(c.fusion.record_every),
            ]
        )
        self.g = c.pipeline.gravity_mps2 if c.pipeline.gravity_mps2 > 0 else _G_STD
        self.t_prev = math.nan
        self.static = False
        self.t_fix = -math.inf
        self.t_boot_move = math.nan
        self.a_long = 0.0  # GNSS longitudinal acceleration dv/dt, m/s^2
        self.v_gnss = 0.0  # latest GNSS speed, m/s
        self.t_speed = math.nan
        self.t_gnss = math.nan  # time of the latest accepted fix, s
        self._one = OneSampleBlock()  # reused by step(ImuSample)
        #: forward-run record of the fusion filter for the RTS smoother (``fusion.smoothing``)
        self.smoothing_log: SmoothingLog | None = (
            SmoothingLog(c.fusion.record_every) if c.fusion.smoothing else None
        )
        #: acceleration error of the smoothing model (read by :func:`~iotnav.engines.smoother.smooth_output`)
        self.smoothing_accel_error: AccelErrorModel | None = None
        if c.fusion.smoothing and c.fusion.smoothing_accel_rw_mps2_sqrt_s > 0:
            if c.pipeline.use_lowpass and c.pipeline.static_hold:
                raise ValueError(
                    "fusion.smoothing_accel_rw_mps2_sqrt_s > 0 needs pipeline.static_hold = false "
                    "(held steps are not kinematic)"
                )
            self.smoothing_accel_error = AccelErrorModel(
                POS, VEL, c.fusion.smoothing_accel_rw_mps2_sqrt_s, c.fusion.smoothing_accel_init_std_mps2
            )
        # smoothing: transition since the last record point, record points written by the kernel
        # until drained to the log (no buffer without smoothing)
        self._Phi = np.eye(N_STATES).reshape(-1)
        self._rec = np.zeros((64 if c.fusion.smoothing else 0, REC_SIZE))
        self._origin_2d = False  # origin set from a fix without height
        self._restamp_from = -1  # first record made before any IMU sample (-1: none)
        if stored is not None:
            self._set_origin(stored.lat_deg, stored.lon_deg, stored.height_m)
            if math.isfinite(stored.mount_yaw_rad):
                self.mount.mount_yaw_rad = stored.mount_yaw_rad
                self.mount.known = True
                self.mount.accepted_once = True  # only accepted angles are stored
                self.mount.done = c.mount.one_off
            self.events.append({"type": "boot", "t": math.nan, "decision": "stored_position", **vars(stored)})
        else:
            self.events.append({"type": "boot", "t": math.nan, "decision": "wait_for_fix"})

    # Scalars shared with the compiled IMU kernel (elements of ``_st``).
    t_prev = StateSlot(ST_T_PREV)
    static = FlagSlot(ST_STATIC)
    a_long = StateSlot(ST_A_LONG)
    v_gnss = StateSlot(ST_V_GNSS)
    t_speed = StateSlot(ST_T_SPEED)
    t_fix = StateSlot(ST_T_FIX)
    t_boot_move = StateSlot(ST_T_BOOT_MOVE)
    g = StateSlot(ST_G)

    # ------------------------------------------------------------------ helpers
    def _set_origin(self, lat: float, lon: float, h: float) -> None:
        self.frame = TangentPlane(lat, lon, h)
        self._frame[:] = self.frame.constants()
        self._st[ST_HAVE_FRAME] = 1.0
        if self.config.pipeline.gravity_mps2 <= 0:
            self.g = normal_gravity(lat, h)

    @property
    def mount_yaw_rad(self) -> float:
        """Current mount-angle estimate (rad, sensor x from vehicle forward, clockwise)."""
        return float(self.mount.mount_yaw_rad)

    def summary(self) -> dict[str, Any]:
        """Configuration and final state."""
        counts: dict[str, int] = {}
        for e in self.events:
            counts[e["type"]] = counts.get(e["type"], 0) + 1
        return {
            "skipped": dict(self.guard.skipped),
            "engine": "pipeline",
            "config": self.config.to_dict(),
            "mount_yaw_rad": self.mount_yaw_rad,
            "mount_known": self.mount.known,
            "mount_quality": dict(self.mount.quality),
            "origin": None
            if self.frame is None
            else {
                "lat_deg": self.frame.lat0_deg,
                "lon_deg": self.frame.lon0_deg,
                "height_m": self.frame.h0_m,
            },
            "gyro_bias_rad_s": self.cascade.bias.x.tolist(),
            "acc_bias_mps2": self.fusion.x[6:9].tolist(),
            "event_counts": counts,
        }

    # ------------------------------------------------------------------ smoothing
    def _record_epoch(self, t: float, prior: FloatArray) -> None:
        """Record point of a GNSS epoch at fix time ``t`` (s): ``prior`` (filter array before its updates), the filter now.

        Stamped one ulp after the filter's time, the latest IMU sample (the pipeline does not
        predict to the fix time): the row written at that sample shows the prior, the later rows
        start from the posterior, and :func:`~iotnav.engines.smoother.smooth_output` corrects a
        row at a record's time as its posterior. Before any IMU sample the record is stamped
        ``t`` and moved to the first IMU sample's time when it arrives (that sample does not
        predict: its row shows this posterior), so record times stay the filter's times.
        """
        log = self.smoothing_log
        if log is None:
            return
        t_x = self.t_prev
        if math.isfinite(t_x):
            t_rec = float(np.nextafter(t_x, math.inf))
        else:
            t_rec = t
            if self._restamp_from < 0:
                self._restamp_from = len(log)
        f = self.fusion
        log.record(
            t_rec,
            prior[:N_STATES],
            prior[F_P : F_P + N_STATES * N_STATES].reshape(N_STATES, -1),
            self._Phi.reshape(N_STATES, N_STATES),
            f.x,
            f.P,
        )
        self._Phi[:] = np.eye(N_STATES).reshape(-1)
        self._st[ST_ROWS] = 0.0

    # ------------------------------------------------------------------ step
    def step(self, sample: Sample) -> Output | None:
        """Process one sample (streaming and batch share this)."""
        sample = self.guard.admit(sample)
        if sample is None:
            return None
        if isinstance(sample, ImuSample):
            return self._imu(sample)
        if isinstance(sample, GnssSample):
            self._gnss(sample)
        elif isinstance(sample, MagSample):
            if self.config.yaw.use_mag:
                self.cascade.aid_mag(np.asarray(sample.mag_b_ut, float))
        return None

    def _gnss(self, s: GnssSample) -> None:
        c = self.config
        reason = self.boot.check_fix(s.valid, s.lat_deg, s.lon_deg, s.pdop, s.num_sv, s.t)
        if reason is not None:
            self.events.append({"type": "fix_rejected", "t": s.t, "reason": reason, "pdop": s.pdop})
            return
        # a fix without height (2D) brings no vertical information: it takes the filter's own
        # height (the origin's before the filter starts, 0 without an origin); the first fix
        # with a height after an origin set from a 2D fix then re-initialises the vertical
        if math.isfinite(s.height_m):
            h = s.height_m
        elif self.frame is None:
            h = 0.0
            self._origin_2d = True
        elif self.fusion.initialised:
            h = self.frame.h0_m - float(self.fusion.x[2])
        else:
            h = self.frame.h0_m
        vertical_reset = self._origin_2d and math.isfinite(s.height_m)
        if not self.boot.first_fix_seen:
            ev = self.boot.first_fix(s.t, s.lat_deg, s.lon_deg)
            if ev is not None:
                self.events.append(ev)
            if self.frame is None:
                self._set_origin(s.lat_deg, s.lon_deg, h)
            self.events.append({"type": "first_fix", "t": s.t, "pdop": s.pdop, "num_sv": s.num_sv})
        assert self.frame is not None
        dt_fix = s.t - self.t_gnss if 0.0 < s.t - self.t_gnss <= 2.5 else 1.0
        after_outage = s.t - self.t_gnss > c.fusion.reacquire_after_s  # first fix after a gap
        self.t_gnss = s.t
        r = self.frame.to_ned(s.lat_deg, s.lon_deg, h)
        if self.frame.follow(r):  # long routes: the plane re-linearised at the fix (same coordinates)
            self._frame[:] = self.frame.constants()
        R, sigma_v = gnss_noise(s.h_acc_m, s.v_acc_m, s.s_acc_mps, s.pdop, s.hdop, c.fusion)
        if vertical_reset and self.fusion.initialised:
            jump = float(r[2] - self.fusion.x[2])
            P = self.fusion.P
            P[2, :] = 0.0
            P[:, 2] = 0.0
            # unknown: the fix's own update below sets it (once; R[2, 2] here counted it twice)
            P[2, 2] = 1e6
            self.fusion.x[2] = r[2]
            self.fusion.P = P
            self._origin_2d = False
            self.events.append({"type": "vertical_reset", "t": s.t, "down_m": float(r[2]), "jump_m": jump})
        v_ned = np.array([s.vn, s.ve, s.vd], dtype=float)
        have_ned = c.fusion.use_ned_velocity and bool(np.all(np.isfinite(v_ned)))
        moving_course = (
            s.course_valid and math.isfinite(s.speed_mps) and s.speed_mps >= c.yaw.min_course_speed_mps
        )
        v_ne = (
            s.speed_mps * np.array([math.cos(s.course_rad), math.sin(s.course_rad)])
            if moving_course
            else None
        )
        if not self.fusion.initialised:
            v0 = v_ned if have_ned else None if v_ne is None else np.array([v_ne[0], v_ne[1], 0.0])
            self.fusion.initialise(r, R, v0)
            self.t_fix = s.t
            self._record_epoch(s.t, self.fusion.state)
            return_after_init = True
        else:
            return_after_init = False
        self.static_det.update_speed(s.t, s.speed_mps)
        if math.isfinite(s.speed_mps):
            dt_v = s.t - self.t_speed
            self.a_long = (s.speed_mps - self.v_gnss) / dt_v if 0.0 < dt_v <= 2.5 else 0.0
            self.v_gnss, self.t_speed = s.speed_mps, s.t
        if moving_course and not self.static:
            self.cascade.aid_heading(wrap(s.course_rad + self.mount.mount_yaw_rad))
        if c.pipeline.use_mount:
            old = self.mount.mount_yaw_rad
            ev = self.mount.add_gnss(s.t, s.speed_mps, s.course_rad, s.course_valid, self.static)
            if ev is not None:
                self.events.append(ev)
                if ev["applied"]:
                    self.cascade.rotate_heading(wrap(self.mount.mount_yaw_rad - old))
        if return_after_init:
            return
        prior = self.fusion.state.copy() if self.smoothing_log is not None else self.fusion.state
        if self.static and c.pipeline.use_lowpass:
            out = self.lowpass.push(r)
            if out is not None:
                n_eff = 1.0 + self.lowpass.n_fixes * dt_fix / (2.0 * c.pipeline.lowpass_corr_time_s)
                self.fusion.update_position(out, R / n_eff)
            self.fusion.update_velocity(np.zeros(2), c.pipeline.zupt_noise_mps)
        else:
            res = self.fusion.update_position(r, R, stale=after_outage)
            if res.accepted:
                self.t_fix = s.t
            else:
                self.events.append({"type": "fix_rejected", "t": s.t, "reason": "nis", "nis": res.nis})
            if have_ned:
                self.fusion.update_velocity_ned(v_ned, sigma_v)
            elif v_ne is not None:
                self.fusion.update_velocity(v_ne, sigma_v)
        self._record_epoch(s.t, prior)
        if self.store is not None and self.boot.due(s.t):
            lat, lon, h = self.frame.from_ned(self.fusion.x[POS])
            # a provisional angle is not stored: it would come back as a calibration
            mu = self.mount.mount_yaw_rad if self.mount.known and not self.mount.provisional else math.nan
            self.store.save(StoredPosition(lat, lon, h, s.t, mu))

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
        """Process IMU samples ``i0 .. i1-1`` with :func:`pipeline_imu_kernel`, row ``k`` of ``out`` for sample ``k``.

        ``t`` device time (s); ``acc`` specific force along sensor x, y, z (m/s^2); ``gyro``
        angular rate about sensor x, y, z (rad/s). Events and the low-pass reset are done
        here, between kernel calls.
        """
        fe, mount = front_end(self.cascade, self.static_det), self.mount
        if self._restamp_from >= 0 and self.smoothing_log is not None and i1 > i0:
            log_t = self.smoothing_log.t
            log_t[self._restamp_from :] = [float(t[i0])] * (len(log_t) - self._restamp_from)
            self._restamp_from = -1
        k = i0
        while k < i1:
            k, flags = pipeline_imu_kernel(
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
                fe,
                mount.imu_sums,
                self.fusion.state,
                self.fusion.params,
                self._Phi,
                self._rec,
                float(mount.mount_yaw_rad),
                bool(mount.known),
            )
            if flags:
                if flags & EV_STATIC:
                    self.events.append(
                        {"type": "static_start" if self.static else "static_end", "t": float(t[k - 1])}
                    )
                    self.lowpass.reset()
                if flags & EV_BOOT_MOVE:
                    self.events.append({"type": "boot_movement_before_fix", "t": float(t[k - 1])})
                if flags & EV_FULL:
                    self._drain_records()
        if self.smoothing_log is not None:
            self._drain_records()
