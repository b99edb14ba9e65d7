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

Before any accepted fix: with a stored position the output is that position (source
``last_position``) while the INS sees no movement; once it does (block 3's accelerometer test,
no GPS speed being available) the source becomes ``dr`` and the horizontal sigma grows at
``boot_walk_speed_mps``. Without a stored position the output is NaN (source ``none``).

NED origin: the stored last position when one was loaded, else the first accepted fix.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
import numpy.typing as npt

from iotnav.engines.base import (
    GnssSample,
    ImuSample,
    MagSample,
    Output,
    Sample,
    TangentPlane,
    output_at,
    output_without_position,
)
from iotnav.engines.config import PipelineConfig
from iotnav.geo import dcm_to_rpy, normal_gravity, rot_z
from iotnav.techniques.cascade import CascadeConfig, CascadeKF
from iotnav.techniques.fusion_kf import POS, VEL, FusionKF, gnss_noise
from iotnav.techniques.last_position import LastPositionLogic, LastPositionStore, StoredPosition
from iotnav.techniques.lowpass3 import Lowpass3
from iotnav.techniques.mount import MountAligner, wrap
from iotnav.techniques.static import StaticDetector

FloatArray = npt.NDArray[np.float64]

_G_STD = 9.80665


class Pipeline:
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
        self.frame: TangentPlane | None = None
        self.g = c.pipeline.gravity_mps2 if c.pipeline.gravity_mps2 > 0 else _G_STD
        self.t_prev = math.nan
        self.static = False
        self.t_fix = -math.inf
        self.t_boot_move = math.nan
        self.a_long = 0.0  # GNSS longitudinal acceleration dv/dt, m/s^2
        self.v_gnss = 0.0  # latest GNSS speed, m/s
        self.t_speed = math.nan
        self.t_gnss = math.nan  # time of the latest accepted fix, s
        if stored is not None:
            self._set_origin(stored.lat_deg, stored.lon_deg, stored.height_m)
            if math.isfinite(stored.mount_yaw_rad):
                self.mount.mount_yaw_rad = stored.mount_yaw_rad
                self.mount.known = True
                self.mount.done = c.mount.one_off
            self.events.append({"type": "boot", "t": math.nan, "decision": "stored_position", **vars(stored)})
        else:
            self.events.append({"type": "boot", "t": math.nan, "decision": "wait_for_fix"})

    # ------------------------------------------------------------------ helpers
    def _set_origin(self, lat: float, lon: float, h: float) -> None:
        self.frame = TangentPlane(lat, lon, h)
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

    # ------------------------------------------------------------------ step
    def step(self, sample: Sample) -> Output | None:
        """Process one sample (streaming and batch share this)."""
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
        if not self.boot.first_fix_seen:
            ev = self.boot.first_fix(s.t, s.lat_deg, s.lon_deg)
            if ev is not None:
                self.events.append(ev)
            if self.frame is None:
                self._set_origin(s.lat_deg, s.lon_deg, s.height_m)
            self.events.append({"type": "first_fix", "t": s.t, "pdop": s.pdop, "num_sv": s.num_sv})
        assert self.frame is not None
        dt_fix = s.t - self.t_gnss if 0.0 < s.t - self.t_gnss <= 2.5 else 1.0
        self.t_gnss = s.t
        r = self.frame.to_ned(s.lat_deg, s.lon_deg, s.height_m)
        R, sigma_v = gnss_noise(s.h_acc_m, s.v_acc_m, s.s_acc_mps, s.pdop, s.hdop, c.fusion)
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
                if ev["accepted"]:
                    self.cascade.rotate_heading(wrap(self.mount.mount_yaw_rad - old))
        if return_after_init:
            return
        if self.static and c.pipeline.use_lowpass:
            out = self.lowpass.push(r)
            if out is not None:
                n_eff = 1.0 + self.lowpass.n_fixes * dt_fix / (2.0 * c.pipeline.lowpass_corr_time_s)
                self.fusion.update_position(out, R / n_eff)
            self.fusion.update_velocity(np.zeros(2), c.pipeline.zupt_noise_mps)
        else:
            res = self.fusion.update_position(r, R)
            if res.accepted:
                self.t_fix = s.t
            else:
                self.events.append({"type": "fix_rejected", "t": s.t, "reason": "nis", "nis": res.nis})
            if have_ned:
                self.fusion.update_velocity_ned(v_ned, sigma_v)
            elif v_ne is not None:
                self.fusion.update_velocity(v_ne, sigma_v)
        if self.store is not None and self.boot.due(s.t):
            lat, lon, h = self.frame.from_ned(self.fusion.x[POS])
            mu = self.mount.mount_yaw_rad if self.mount.known else math.nan
            self.store.save(StoredPosition(lat, lon, h, s.t, mu))

    def _imu(self, s: ImuSample) -> Output:
        c = self.config
        acc_b = np.asarray(s.acc_b, float)
        gyro_b = np.asarray(s.gyro_b, float)
        dt = s.t - self.t_prev if math.isfinite(self.t_prev) else 0.0
        self.t_prev = s.t
        r_prev = float(self.cascade.C_nb[2] @ self.cascade.omega_b)
        a_veh = math.hypot(self.a_long, self.v_gnss * r_prev) if s.t - self.t_speed <= 2.5 else 0.0
        C = self.cascade.step(acc_b, gyro_b, dt, self.static, self.g, a_veh)
        f_n = C @ acc_b
        was = self.static
        v_dr = math.hypot(self.fusion.x[3], self.fusion.x[4]) if self.fusion.initialised else math.nan
        self.static = self.static_det.step(s.t, f_n, v_dr)
        if self.static != was:
            self.events.append({"type": "static_start" if self.static else "static_end", "t": s.t})
            self.lowpass.reset()
        if c.pipeline.use_mount:
            self.mount.add_imu_body(acc_b, float(C[2] @ self.cascade.omega_b))
        a_n = f_n + np.array([0.0, 0.0, self.g])
        if not (self.static and c.pipeline.use_lowpass and c.pipeline.static_hold):
            self.fusion.predict(a_n, C, dt)
        C_out = C @ rot_z(self.mount.mount_yaw_rad).T if self.mount.known else C
        roll, pitch, yaw = dcm_to_rpy(C_out)
        if self.fusion.initialised:
            assert self.frame is not None
            x, P = self.fusion.x, self.fusion.P
            r, v = x[POS], x[VEL]
            std_n, std_e = math.sqrt(P[0, 0]), math.sqrt(P[1, 1])
            if self.static and c.pipeline.use_lowpass:
                source = "lowpass"
            elif s.t - self.t_fix <= c.pipeline.fix_hold_s:
                source = "fix"
            else:
                source = "dr"
        elif self.frame is not None:  # stored last position, no fix yet
            r, v = np.zeros(3), np.zeros(3)
            std_n = std_e = c.last_position.stored_std_m
            source = "last_position"
            if not self.static and not math.isnan(s.t) and math.isnan(self.t_boot_move) and dt > 0:
                self.t_boot_move = s.t
                self.events.append({"type": "boot_movement_before_fix", "t": s.t})
            if math.isfinite(self.t_boot_move):
                std_n = std_e = std_n + c.last_position.boot_walk_speed_mps * (s.t - self.t_boot_move)
                source = "dr"
        else:
            return output_without_position(s.t, (roll, pitch, yaw), self.static)
        return output_at(s.t, self.frame, r, v, (roll, pitch, yaw), self.static, (std_n, std_e), source)
