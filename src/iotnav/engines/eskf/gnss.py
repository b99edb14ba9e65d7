"""GNSS epochs of the ``eskf`` engine."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from iotnav.engines.base import (
    GnssSample,
    TangentPlane,
)
from iotnav.engines.eskf import models as M
from iotnav.engines.eskf.consistency import NisAlarm
from iotnav.engines.eskf.layout import (
    E_A_GNSS,
    E_A_MS,
    E_FIX_ACC,
    E_FIX_REACH,
    E_FIX_SIG,
    E_FIX_SV,
    E_SA_GNSS,
    E_SM_ON,
    E_T_A_GNSS,
    E_T_A_MS,
    NZ_GNSS_H,
    NZ_GNSS_V,
    NZ_INV_TF,
)
from iotnav.engines.eskf.resets import EskfResets
from iotnav.geo import dcm_to_rpy, euler_to_dcm, normal_gravity
from iotnav.gnss_accuracy import position_sigmas
from iotnav.wmm import log_year, reference_field

FloatArray = npt.NDArray[np.float64]


@dataclass(frozen=True)
class GnssEpoch:
    """A valid fix read into the filter's terms (:meth:`EskfGnss._gnss_epoch`).

    Attributes
    ----------
    t : float
        Time, s.
    z : numpy.ndarray
        Antenna position, m, NED about the origin (a 2D fix: the filter's own down).
    has_height : bool
        The fix has a height (3D).
    sig_p : numpy.ndarray
        Per-axis 1-sigma of the reported position, m, NED (:func:`iotnav.gnss_accuracy.position_sigmas`).
    sig_v : float
        1-sigma of each velocity component (white Doppler part), m/s.
    sig_white : numpy.ndarray
        Per-axis 1-sigma of the white part of the position error, m (``R`` of the update).
    source : tuple of str
        Which receiver figures gave ``sig_p``, horizontal and vertical.
    steps : tuple of float
        Relative rounding of ``sig_p`` per axis (:class:`~iotnav.engines.gnss_resolution.AccuracyScaling`).
    v_meas : numpy.ndarray or None
        Velocity, m/s, NED (2 elements from speed and course, 3 with the receiver's down).
    speed : float
        Ground speed, m/s (NaN: none).
    course, course_ok : float, bool
        Course over ground, rad, and whether it is usable.
    """

    t: float
    z: FloatArray
    has_height: bool
    sig_p: FloatArray
    sig_v: float
    sig_white: FloatArray
    source: tuple[str, str]
    steps: tuple[float, float, float]
    v_meas: FloatArray | None
    speed: float
    course: float
    course_ok: bool


class EskfGnss(EskfResets):
    """GNSS fixes: origin, noise, alignment, position and velocity updates."""

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
        """One GNSS sample: read it (:meth:`_gnss_epoch`), initialise what it can, update.

        The order is that of the package docstring ("GNSS"): the nominal state is integrated
        to the fix time; the origin is set at the first fix; the GNSS error model follows the
        reported accuracy; before the heading (and the position) are known the fix
        initialises them; then the mount from the magnetometer heading, the accuracy scaling
        of the GNSS error states, the gate reset, and the position and velocity updates.
        """
        if not s.valid or not (math.isfinite(s.lat_deg) and math.isfinite(s.lon_deg)):
            self.events.append({"type": "fix_rejected", "t": s.t, "reason": "invalid"})
            self.aligner.add_gnss(s.t, math.nan, math.nan, False, self.static)
            return
        ep = self._gnss_epoch(s)
        request, self._reinit_request = self._reinit_request, None
        if not self.levelled or not self._gnss_initialise(ep):
            return
        if request is not None and self.pos_ok:
            self._reinitialise(ep, None, request)
            return  # re-initialised from this fix, as asked (request_reinitialise)
        self._gnss_mount_from_heading(ep)
        if self.config.gnss_error_scales_with_accuracy and self.pos_ok:
            # between figures of one kind (not h_acc on one fix and DOP x UERE on the next), the
            # figures' rounding steps low-passed: gnss_resolution.AccuracyScaling
            kr = self._scaling.ratio(ep.t, self.sigma_e, ep.source, ep.steps)
            if kr is not None:
                self._scale_gnss_error(ep.t, np.array(kr))
        # position update (gated; re-open after repeated rejections)
        force = self.n_rejected_fix >= self.config.max_gnss_rejections
        unwidened = self._gnss_gate_reset(ep) if force else None
        self._propagate_cov()  # P and the GNSS error estimates e, e_gm to the fix time, before y
        if unwidened is not None:
            self._smoothing_unwidened_prior(*unwidened)
        meas = self._gnss_position_meas(ep)
        ok = self._apply(ep.t, meas, force=force)
        self._gnss_position_result(ep.t, ok)
        if self._gnss_consistency(ep, float(np.hypot(meas.y[0], meas.y[1]))):
            return  # re-initialised from this fix (its velocity included)
        self._apply(ep.t, self._gnss_velocity_meas(ep))

    def _gnss_epoch(self, s: GnssSample) -> GnssEpoch:
        """Read a valid fix into the filter's terms; feed the fix's speed and course to blocks 3 and 5.

        Sets the origin at the first fix (and the WMM declination, the local gravity), the
        time-correlated GNSS error's driving intensities from the reported accuracy
        (``e = sigma(t) y``: ``2 var(e_gm) / T_e``, :func:`~iotnav.engines.eskf.models.gm_variance_factor`),
        the white part of the position noise (the fixes' rounding, a floor, a fraction of the
        accuracy: package docstring, "GNSS"), the GNSS-derived acceleration and the last fix.
        """
        c = self.config
        # end of the latest gap between valid fixes longer than smoothing_drift_gap_s
        if math.isfinite(self._t_valid) and s.t - self._t_valid > c.smoothing_drift_gap_s:
            self._t_long_gap_end = s.t
        self._t_valid = s.t
        self._integrate_to(s.t)
        if self.frame is None:
            self._gnss_origin(s)
        frame = self.frame
        assert frame is not None
        has_height = math.isfinite(s.height_m)
        # a 2D fix (no height) updates the horizontal only; its down is the filter's own
        z = frame.to_ned(s.lat_deg, s.lon_deg, s.height_m if has_height else frame.h0_m)
        if frame.follow(z):  # long routes: the plane re-linearised at the fix (same coordinates)
            self.frame = frame
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
        self.noise[NZ_GNSS_H] = 2.0 * M.gm_variance_factor(te_h, tf) / te_h * self.sigma_e[0] ** 2
        self.noise[NZ_GNSS_V] = 2.0 * M.gm_variance_factor(te_v, tf) / te_v * self.sigma_e[2] ** 2
        self.resolution.update(s.lat_deg, s.lon_deg, s.height_m)
        sig_white = np.maximum(f * sig_p, c.gnss_white_floor_m)
        if c.gnss_white_from_resolution:
            sig_white = np.maximum(sig_white, self.resolution.sigma_ned_m(s.lat_deg))
        v_fix = np.zeros(3)
        if v_meas is not None:
            v_fix[: v_meas.size] = v_meas
            self._gnss_accel(s.t, v_meas, sig_v)
        self._hold_sigmas(s.t, z, sig_p, sig_v, v_meas, speed)
        self.last_fix = (s.t, z, v_fix)
        return GnssEpoch(
            s.t, z, has_height, sig_p, sig_v, sig_white, source, steps, v_meas, speed, course, course_ok
        )

    def _hold_sigmas(
        self,
        t: float,
        z: FloatArray,
        sig_p: FloatArray,
        sig_v: float,
        v_meas: FloatArray | None,
        speed: float,
    ) -> None:
        """The per-fix figures of the claimed sigma of this fix moved on at its velocity, into ``st``.

        Called before :attr:`last_fix` is replaced. ``E_FIX_SIG``: the fix's reported position
        1-sigma (north, east), m. ``E_FIX_SV``: the 1-sigma of each velocity component it is
        moved on at, m/s: its white velocity noise; when it gives no horizontal velocity (held),
        its speed, or without one the speed from the previous fix (at most 10 s older), or
        ``gnss_min_course_speed_mps`` (a receiver reports no course below about that speed).
        ``E_FIX_ACC``: the RMS of the GNSS-derived horizontal acceleration (:meth:`_gnss_accel`),
        at least ``hold_accel_floor_mps2``, m/s^2. ``E_FIX_REACH``: the 1-sigma bound of each
        velocity component's change, ``sqrt((v_f^2 + s_top^2) / 2)``, ``s_top`` the top fix
        speed of the last ``hold_window_s`` (and ``v_f``) times ``hold_speed_margin``, m/s.
        """
        c = self.config
        st = self.st
        st[E_FIX_SIG] = sig_p[0]
        st[E_FIX_SIG + 1] = sig_p[1]
        if v_meas is not None:
            sv = sig_v
        elif math.isfinite(speed):
            sv = max(speed, sig_v)
        else:
            sv = c.gnss_min_course_speed_mps
            prev = self.last_fix
            if prev is not None and 0.0 < t - prev[0] <= 10.0:
                d = float(np.hypot(z[0] - prev[1][0], z[1] - prev[1][1]))
                sv = max(sv, (d + 2.0 * float(np.hypot(sig_p[0], sig_p[1]))) / (t - prev[0]))
        st[E_FIX_SV] = sv
        st[E_FIX_ACC] = max(c.hold_accel_floor_mps2, math.sqrt(max(float(st[E_A_MS]), 0.0)))
        # reach: the top fix speed of the last hold_window_s (a monotonic deque of (t, speed))
        top = self._speed_top
        if math.isfinite(speed):
            while top and top[-1][1] <= speed:
                top.pop()
            top.append((t, speed))
        while top and t - top[0][0] > c.hold_window_s:
            top.popleft()
        v_f = (
            math.hypot(v_meas[0], v_meas[1])
            if v_meas is not None
            else (speed if math.isfinite(speed) else sv)
        )
        s_top = c.hold_speed_margin * max(top[0][1] if top else 0.0, v_f)
        st[E_FIX_REACH] = math.sqrt((v_f * v_f + s_top * s_top) / 2.0)

    def _gnss_origin(self, s: GnssSample) -> None:
        """First valid fix: the NED origin, the local normal gravity, the WMM declination."""
        c = self.config
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

    def _gnss_initialise(self, ep: GnssEpoch) -> bool:
        """Heading, mount and position from the fix while they are unknown; True when the filter runs.

        Without a heading: block 5's mount yaw once committable (:class:`~iotnav.techniques.mount3d.Mount3d`),
        then, moving faster than ``align_min_speed_mps``, the sensor yaw from the course and
        the mount (vehicle yaw = course) and the position from the fix. With a heading and no
        position: the position from the fix.
        """
        c = self.config
        moving_fast = ep.course_ok and math.isfinite(ep.speed) and ep.speed >= c.align_min_speed_mps
        if not self.heading_ok:
            if not self.mount_ok and self.mount3d.committable:
                self._init_mount(ep.t, self.aligner.mount_yaw_rad, "block5")
            elif not self.mount_ok and self.aligner.known and not self._mount_unobservable_reported:
                # block 5 has an angle, but not yet one the data determine: not committed
                self._mount_unobservable_reported = True
                self.events.append(
                    {
                        "type": "mount_unobservable",
                        "t": ep.t,
                        "block5_yaw_rad": self.mount3d.mount_yaw_rad,
                        "block5_std_rad": self.mount3d.yaw_std_rad,
                        "commit_std_rad": c.mount_commit_std_rad,
                    }
                )
            if self.mount_ok and moving_fast:
                # vehicle yaw = course; sensor yaw = vehicle yaw + mount yaw
                r, p, _ = dcm_to_rpy(self.nom.C_nb @ self.nom.C_vb.T)
                C_nv = euler_to_dcm(r, p, ep.course)
                _, _, yaw_b = dcm_to_rpy(C_nv @ self.nom.C_vb)
                sig_c = ep.sig_v / max(ep.speed, 0.1)
                sm = float(np.sqrt(self.P[M.MNT.start + 2, M.MNT.start + 2]))
                self._set_heading(ep.t, yaw_b, math.hypot(sig_c, sm), "gnss_course", mount_cov=sm * sm)
                self._reset_position(ep.t, ep.z, ep.v_meas, ep.sig_v, ep.has_height, ep.sig_white)
            return False
        if not self.pos_ok:
            self._reset_position(ep.t, ep.z, ep.v_meas, ep.sig_v, ep.has_height, ep.sig_white)
            return False
        return True

    def _gnss_mount_from_heading(self, ep: GnssEpoch) -> None:
        """Heading known (magnetometer), mount not: mount yaw = sensor yaw - course, moving fast."""
        moving_fast = ep.course_ok and math.isfinite(ep.speed) and ep.speed >= self.config.align_min_speed_mps
        if self.mount_ok or not moving_fast:
            return
        _, _, yaw_b = dcm_to_rpy(self.nom.C_nb)
        mu = math.remainder(yaw_b - ep.course, 2.0 * math.pi)
        self._init_mount(ep.t, mu, "mag_course")
        km = M.MNT.start + 2
        self._smoothing_reset(self._reinit_rows(km))
        self.P[km, :] = 0.0
        self.P[:, km] = 0.0
        self.P[km, km] = self.P[M.ATT.start + 2, M.ATT.start + 2] + (ep.sig_v / ep.speed) ** 2

    def _gnss_gate_reset(self, ep: GnssEpoch) -> tuple[FloatArray, FloatArray] | None:
        """``max_gnss_rejections`` fixes rejected in a row: widen the position covariance (event ``gate_reset``).

        The position rows a fix updates are decorrelated and set to ``(3 sigma_p)^2``; the next
        update is then forced. Returns the un-widened ``P`` and accumulator when the smoother
        is to see the forced fix against them (after an outage: package docstring, "RTS
        smoothing"), else None.
        """
        c = self.config
        rows_p = M.POS if ep.has_height else slice(M.POS.start, M.POS.start + 2)  # rows a fix updates
        unwidened: tuple[FloatArray, FloatArray] | None = None
        drifted = ep.t - self._t_long_gap_end <= 2.0 * c.smoothing_drift_gap_s
        if self.st[E_SM_ON] != 0.0 and drifted:
            # the widening is part of the forced update, not of the smoothing model
            # (package docstring, "RTS smoothing"): the open record ends here, before it
            self._smoothing_reset(np.eye(self.n))
            unwidened = (self.P.copy(), self.acc.copy())
        else:
            self._smoothing_reset(self._reinit_rows(rows_p))
        self.P[rows_p, :] = 0.0
        self.P[:, rows_p] = 0.0
        self.P[rows_p, rows_p] = np.diag((3.0 * ep.sig_p[: rows_p.stop - rows_p.start]) ** 2)
        self.events.append({"type": "gate_reset", "t": ep.t, "rejected": self.n_rejected_fix})
        return unwidened

    def _gnss_position_meas(self, ep: GnssEpoch) -> M.Meas:
        """The fix's position measurement (:func:`~iotnav.engines.eskf.models.gnss_position`).

        ``R`` is the white part only (``sig_white``); the time-correlated part is in the
        ``GNE`` states. A 2D fix, or the first 3D fix after an origin without a height
        (whose height re-initialises the vertical, :meth:`_reset_vertical`), updates the
        horizontal only.
        """
        horizontal_only = not ep.has_height
        if ep.has_height and self._vertical_unknown and self.pos_ok:
            self._reset_vertical(ep.t, ep.z, ep.sig_white)
            horizontal_only = True  # its height is in the reset already: not twice
        meas = M.gnss_position(self.nom, ep.z, self.lever_b, ep.sig_white, self.n)
        if horizontal_only:
            meas = M.Meas(meas.name, meas.y[:2], meas.H[:2], meas.R[:2, :2])
        return meas

    def _gnss_position_result(self, t: float, ok: bool) -> None:
        """Count consecutive rejected fixes (event ``fix_rejected`` with NIS and test ratio)."""
        if ok:
            self.n_rejected_fix = 0
            self.t_fix = t
            return
        self.n_rejected_fix += 1
        rec = self.nis_log["gnss_position"][-1]
        self.events.append(
            {
                "type": "fix_rejected",
                "t": t,
                "reason": "nis",
                "nis": rec[1],
                "test_ratio": rec[1] / self._gates[rec[2]],
            }
        )

    def _gnss_consistency(self, ep: GnssEpoch, distance_m: float) -> bool:
        """The fix's position NIS into the windowed monitor; re-initialise on its alarm (True then).

        The NIS is divided by ``nis_tolerance`` (:class:`~iotnav.engines.eskf.config.EskfConfig`)
        before it enters the window (:class:`~iotnav.engines.eskf.consistency.NisWindow`), with
        ``distance_m``, the horizontal innovation (m), and the fix's reported horizontal sigma;
        rejected and forced fixes count as well as accepted ones.
        """
        c = self.config
        if not c.nis_monitor:
            return False
        _t, nis, dof, _ok = self.nis_log["gnss_position"][-1]
        sig_h = float(np.hypot(ep.sig_p[0], ep.sig_p[1]))
        alarm = self._nis_window.add(ep.t, nis / c.nis_tolerance, dof, distance_m, sig_h)
        if alarm is None:
            return False
        self._reinitialise(ep, alarm)
        return True

    def request_reinitialise(self, reason: str) -> None:
        """Re-initialise at the next valid fix as on an alarm of the own monitor (:meth:`_reinitialise`).

        For a supervisor that found the filter and the fixes inconsistent by its own test (the
        integrity guard, :class:`~iotnav.engines.integrity.IntegrityEngine`); ``reason`` goes
        into the event. A filter that has no position yet (or is re-initialising) ignores it.
        """
        self._reinit_request = reason

    def _reinitialise(self, ep: GnssEpoch, alarm: NisAlarm | None, reason: str = "nis_window") -> None:
        """The filter and GNSS disagree beyond chance: start again from this fix (event ``reinitialised``).

        Position, velocity and the GNSS error states from the fix (:meth:`_reset_position`);
        the sensor biases (and scale factors), the tilt and the mount re-opened
        (:meth:`_reopen_after_alarm`); the heading unknown again, so it is set from the course
        (and the mount yaw) at this fix when moving faster than ``align_min_speed_mps``, else at
        the first such fix, and the output is the last fix moved on until then (package
        docstring, "Consistency monitor"). A second alarm within ``reinit_escalate_s`` of the
        previous re-initialisation also releases the mount: block 5 estimates it again.
        """
        c = self.config
        release = ep.t - self._t_reinit <= c.reinit_escalate_s
        self._t_reinit = ep.t
        self._reopen_after_alarm(release)
        self._nis_window.clear()
        self.n_rejected_fix = 0
        self._gnss_initialise(ep)
        self.events.append(
            {
                "type": "reinitialised",
                "t": ep.t,
                "reason": reason,
                "by": "eskf",
                **(alarm.to_dict() if alarm is not None else {}),
                "tolerance": c.nis_tolerance,
                "false_alarm": c.nis_false_alarm,
                "mount_released": release,
                "heading_from_course": self.heading_ok,
            }
        )

    def _gnss_velocity_meas(self, ep: GnssEpoch) -> M.Meas | None:
        """The fix's velocity measurement (:func:`~iotnav.engines.eskf.models.gnss_velocity`), or None.

        None without a velocity or with ``use_gnss_velocity`` off. ``R`` is the white Doppler
        noise (``s_acc_mps`` or ``gnss_speed_noise_mps``); the derivative of the receiver's
        smoothed position error is in the model through ``1/t_f``.
        """
        if not self.config.use_gnss_velocity or ep.v_meas is None:
            return None
        inv_tf = float(self.noise[NZ_INV_TF])
        sv = np.full(3, ep.sig_v)
        return M.gnss_velocity(self.nom, self.w_pend, ep.v_meas, self.lever_b, sv, self.n, inv_tf)

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
        st[E_A_GNSS] = a = math.hypot(v_meas[0] - old[1], v_meas[1] - old[2]) / dt
        st[E_SA_GNSS] = math.sqrt(2.0) * sig_v / dt
        st[E_T_A_GNSS] = t
        # its running mean square over about hold_window_s (the first value as it is)
        w = 1.0
        if math.isfinite(st[E_T_A_MS]):
            w = 1.0 - math.exp(-max(t - st[E_T_A_MS], 0.0) / max(c.hold_window_s, 1e-9))
        st[E_A_MS] += w * (a * a - st[E_A_MS])
        st[E_T_A_MS] = t
