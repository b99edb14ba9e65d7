"""Initialisation steps and covariance resets of the ``eskf`` engine."""

from __future__ import annotations

import math

import numpy as np
import numpy.typing as npt

from iotnav import kalman
from iotnav.engines.eskf import models as M
from iotnav.engines.eskf.config import DEG, G0
from iotnav.engines.eskf.kernel import _sm_close
from iotnav.engines.eskf.layout import (
    E_GRAV_N,
    E_GRAV_SUM,
    E_SM_ON,
    E_SM_PEND,
    E_SM_T,
    E_T_GRAV,
    E_T_STATE,
)
from iotnav.engines.eskf.smoothing import EskfSmoothing
from iotnav.geo import dcm_to_rpy, euler_to_dcm, rot_z
from iotnav.techniques.mount3d import Mount3d, mount_from_tilt

FloatArray = npt.NDArray[np.float64]


class EskfResets(EskfSmoothing):
    """Levelling, heading, mount, position and GNSS-error resets."""

    # ------------------------------------------------------------------ IMU
    def _level_finish(self, t: float) -> None:
        """Levelling window complete (the kernel has summed it): attitude, biases, covariance."""
        c = self.config
        n = self.level_n
        fm = self.level_sum[:3] / n
        wm = self.level_sum[3:6] / n
        var_f = max(self.level_sum[6] / n - float(fm @ fm), 0.0)
        roll = math.atan2(-fm[1], -fm[2])
        pitch = math.atan2(fm[0], math.hypot(fm[1], fm[2]))
        self.nom.C_nb[:] = euler_to_dcm(roll, pitch, 0.0)
        # what was integrated before with the unknown attitude is discarded (a sensor mounted
        # z up would otherwise have gained 2 g of vertical velocity per second)
        self.nom.v_n[:] = 0.0
        self.nom.p_n[:] = 0.0
        quiet = math.sqrt(var_f) < 0.5 and abs(float(np.linalg.norm(fm)) - G0) < 0.5
        # a car cruising straight is as quiet as one at rest: the GNSS speed tells them apart (a
        # start in motion must not take the window's mean rate, yaw rate included, as the bias)
        moving = t - self.t_speed < 1.5 and self.last_speed > c.zupt_max_gnss_speed_mps
        quiet = quiet and not moving
        if quiet:
            self.nom.b_g[:] = wm
        self.levelled = True
        sg = c.gyro_turn_on_bias_dps * DEG
        nd_g = c.gyro_noise_density_mdps_rthz * 1e-3 * DEG
        bg_std = math.hypot(nd_g / math.sqrt(max(t - self.level_t0, 1e-3)), 0.05 * sg) if quiet else sg
        ba_std = c.acc_turn_on_bias_mg * 1e-3 * G0
        # the cross-axis coupling of gravity, M_a f_b at rest, is a constant offset like the
        # turn-on bias while the tilt holds: per axis m_a^2 (|f|^2 - f_i^2)
        m_a = c.acc_misalignment_pct * 1e-2
        var_ba = ba_std**2 + m_a**2 * (float(fm @ fm) - fm**2)
        sa_std = c.acc_scale_factor_pct * 1e-2
        d = np.zeros(self.n)
        d[M.POS] = 100.0
        d[M.VEL] = 1.0 if quiet else 10.0
        d[M.BG] = bg_std
        d[M.MNT] = c.mount_std_rad if c.mount_rpy_rad is not None else c.mount_aligner_std_rad
        d[M.GNE] = 3.0
        d[M.GNM] = 3.0
        if self.n >= M.N_FULL:
            d[M.SG] = c.gyro_scale_factor_pct * 1e-2
        self.P = np.diag(d**2)
        # tilt = accelerometer error / g, fully correlated with it (models.level_covariance);
        # the independent part: standard error of the mean when quiet, else the configured value
        g = float(self.g_n[2])
        white = math.sqrt(var_f / n) / g if quiet else max(c.initial_tilt_std_rad, c.moving_tilt_std_rad)
        full = self.n >= M.N_FULL
        Pl = M.level_covariance(
            self.nom.C_nb,
            fm,
            g,
            var_ba,
            np.full(3, sa_std**2) if full else None,
            white,
        )
        idx = np.r_[np.arange(M.ATT.start, M.ATT.stop), np.arange(M.BA.start, M.BA.stop)]
        if full:
            idx = np.r_[idx, np.arange(M.SA.start, M.SA.stop)]
        self.P[np.ix_(idx, idx)] = Pl  # yaw row stays zero until initialised (see _freeze_yaw_nb)
        self.acc[:] = 0.0
        st = self.st
        st[E_GRAV_SUM : E_GRAV_SUM + 3] = 0.0
        st[E_GRAV_N] = 0.0
        st[E_T_GRAV] = t
        self.events.append({"type": "levelled", "t": t, "roll": roll, "pitch": pitch, "quiet": quiet})

    def _set_heading(self, t: float, yaw: float, sigma: float, how: str, mount_cov: float = 0.0) -> None:
        """Set the sensor yaw, keeping roll and pitch; reset the yaw covariance."""
        r, p, yaw_old = dcm_to_rpy(self.nom.C_nb)
        self.nom.C_nb[:] = euler_to_dcm(r, p, yaw)
        # the navigation frame turns with the yaw: rotate every n-frame error (P' = T P T^T)
        T = M.heading_reset_transform(yaw - yaw_old, self.n)
        # the yaw row/column: decorrelate, set variance (and its mount correlation)
        k = M.ATT.start + 2
        self._smoothing_reset(self._reinit_rows(k) @ T)
        self.P = kalman.symmetrize(T @ self.P @ T.T)
        self.P[k, :] = 0.0
        self.P[:, k] = 0.0
        self.P[k, k] = sigma**2
        if mount_cov:
            km = M.MNT.start + 2
            self.P[k, km] = self.P[km, k] = mount_cov
        self.heading_ok = True
        self.events.append(
            {"type": "heading_initialised", "t": t, "yaw_rad": yaw, "source": how, "std_rad": sigma}
        )

    def _init_mount(self, t: float, mount_yaw: float, how: str) -> None:
        """Mount from its yaw and the level-vehicle assumption; covariance of its roll and pitch.

        The vehicle is taken as level (roll and pitch zero within ``vehicle_level_std_rad``,
        road crossfall and grade) at this epoch, so the mount's roll and pitch are the sensor's:
        ``C_vb = R_z(mu) R_y(pitch_b) R_x(roll_b)`` (works for any mounting, sensor upside down
        included). Their error is then the sensor tilt error seen in the vehicle frame plus
        the road's tilt, ``dmu_xy = [R_z(-psi_v) dth]_xy - road_xy``: the rows are rebuilt with
        that transform, ``P' = T P T^T + diag(road^2)``, keeping the correlation with the
        tilt (and through it with the accelerometer bias). With ``mount_rpy_rad`` configured
        nothing here runs.
        """
        c = self.config
        r_b, p_b, psi_b = dcm_to_rpy(self.nom.C_nb)
        self.nom.C_vb[:] = mount_from_tilt(self.nom.C_nb, mount_yaw)
        psi_v = psi_b - mount_yaw
        rows = np.arange(M.MNT.start, M.MNT.start + 2)
        T = np.eye(self.n)
        T[rows, :] = 0.0
        T[np.ix_(rows, np.arange(M.ATT.start, M.ATT.stop))] = rot_z(-psi_v)[:2, :]
        self._smoothing_reset(T)
        self.P = T @ self.P @ T.T
        self.P[rows, rows] += c.vehicle_level_std_rad**2
        self.P = kalman.symmetrize(self.P)
        self.mount_ok = True
        self.events.append(
            {
                "type": "mount_initialised",
                "t": t,
                "mount_yaw_rad": mount_yaw,
                "mount_roll_rad": r_b,
                "mount_pitch_rad": p_b,
                "source": how,
            }
        )

    def _reopen_after_alarm(self, release_mount: bool) -> None:
        """The error states re-opened for a re-initialisation (:meth:`EskfGnss._reinitialise`).

        Every state the alarm puts in doubt is decorrelated from the rest and given its prior
        of a start in motion (:meth:`_level_finish`): tilt ``moving_tilt_std_rad``, gyro and
        accelerometer biases their turn-on 1-sigma (a nominal bias beyond 3 of those is taken
        as diverged and zeroed), scale factors their datasheet 1-sigma, the mount
        ``mount_aligner_std_rad``; position and velocity wide until the fix sets them. The
        heading and the position are marked unknown. ``release_mount``: the mount is unknown
        too and block 5 starts again (a configured ``mount_rpy_rad`` included: the data
        contradict it).
        """
        c = self.config
        nom = self.nom
        n = self.n
        blocks = [M.ATT, M.BG, M.BA, M.MNT, M.POS, M.VEL, M.GNE, M.GNM]
        if n >= M.N_FULL:
            blocks += [M.SG, M.SA]
        rows = np.concatenate([np.arange(b.start, b.stop) for b in blocks])
        T = np.eye(n)
        T[rows, :] = 0.0  # the re-opened states carry nothing back across the reset
        self._smoothing_reset(T)
        self.P[rows, :] = 0.0
        self.P[:, rows] = 0.0
        sg = c.gyro_turn_on_bias_dps * DEG
        sa = c.acc_turn_on_bias_mg * 1e-3 * G0
        nom.b_g[np.abs(nom.b_g) > 3.0 * sg] = 0.0
        nom.b_a[np.abs(nom.b_a) > 3.0 * sa] = 0.0
        d = np.zeros(n)
        tilt = max(c.initial_tilt_std_rad, c.moving_tilt_std_rad)
        d[M.ATT.start : M.ATT.start + 2] = tilt  # the yaw row stays zero until the heading is set
        d[M.BG] = sg
        d[M.BA] = sa
        d[M.MNT] = c.mount_aligner_std_rad
        d[M.POS] = 100.0
        d[M.VEL] = 10.0
        d[M.GNE] = 3.0
        d[M.GNM] = 3.0
        if n >= M.N_FULL:
            d[M.SG] = c.gyro_scale_factor_pct * 1e-2
            d[M.SA] = c.acc_scale_factor_pct * 1e-2
        self.P[rows, rows] = d[rows] ** 2
        self.heading_ok = False
        self.pos_ok = False
        if release_mount:
            self.mount_ok = False
            nom.C_vb[:] = np.eye(3)
            self.mount3d = Mount3d(c.mount, c.mount_commit_std_rad)
            self.aligner = self.mount3d.aligner
            self._mount_unobservable_reported = False

    def _scale_gnss_error(self, t: float, k: FloatArray) -> None:
        """The receiver's correlated error scales with its reported accuracy, per NED axis.

        ``e = sigma(t) y`` with ``y`` a unit Gauss-Markov process (as a DOP or a re-acquisition
        multiplies the error it scales): a change of the reported sigma by ``k`` scales the
        estimates ``e``, ``e_gm`` and their error, ``P' = T P T^T`` with ``k`` on the ``GNE``
        and ``GNM`` rows of ``T``.
        """
        kn, ke, kd = float(k[0]), float(k[1]), float(k[2])
        if not (kn > 0.0 and ke > 0.0 and kd > 0.0 and math.isfinite(kn + ke + kd)):
            return
        if abs(kn - 1.0) <= 1e-6 and abs(ke - 1.0) <= 1e-6 and abs(kd - 1.0) <= 1e-6:
            return  # (plain floats: this runs at every fix; numpy's allclose was 6 % of a run)
        self._propagate_cov()  # P and e, e_gm at the fix time
        n = self.n
        d = np.ones(n)
        d[M.GNE] = k
        d[M.GNM] = k
        st = self.st
        if st[E_SM_ON] != 0.0:
            # a linear step of the smoothing model, in the transition into the fix's record
            # (RTS uses each record's prior as well as its posterior: inside the record, as an
            # "update", it set the smoothed estimate of the records before in the wrong units)
            buf = self.sm[0]
            fresh = (
                st[E_SM_PEND] != 0.0
                and st[E_SM_T] == st[E_T_STATE]
                and not np.any(buf[1][:n])
                and np.array_equal(buf[0][n:], self.P.reshape(-1))
            )
            if st[E_SM_PEND] != 0.0 and not fresh:
                _sm_close(st, self.P, self.sm)  # a record with updates already: ends here
        else:
            fresh = False
        self.P *= np.outer(d, d)  # T P T^T with a diagonal T: stays symmetric
        self.nom.e_n[:] *= k
        self.nom.e_gm[:] *= k
        if st[E_SM_ON] != 0.0:
            Phi = self.sm[1].reshape(n, n)
            Phi[:] = d[:, None] * Phi
            if fresh:  # opened at the fix time, no update yet: its prior takes the scaling
                self.sm[0][0][n:] = self.P.reshape(-1)
            self._drain_smoothing()

    def _reset_vertical(self, t: float, z: FloatArray, sig_white: FloatArray) -> None:
        """First fix with a height after an origin without one: down position (and the down
        GNSS error states) re-initialised from it, event ``vertical_reset``."""
        nom = self.nom
        k, ke, km = M.POS.start + 2, M.GNE.start + 2, M.GNM.start + 2
        rows = [k, ke, km]
        T = np.eye(self.n)
        T[rows, :] = 0.0
        self._smoothing_reset(T)
        old = float(nom.p_n[2])
        nom.p_n[2] = z[2] - float((nom.C_nb @ self.lever_b)[2])
        nom.e_n[2] = 0.0
        nom.e_gm[2] = 0.0
        self.P[rows, :] = 0.0
        self.P[:, rows] = 0.0
        c = self.config
        C = M.stationary_gnss_error_cov(self.sigma_e[2:] ** 2, c.gnss_corr_time_v_s, c.gnss_receiver_filter_s)
        ge = [ke, km]
        self.P[k, k] = C[0, 0] + float(sig_white[2] ** 2)
        self.P[np.ix_(ge, ge)] = C
        self.P[k, ge] = self.P[ge, k] = -C[0]  # as in _reset_position
        self._scaling.reset(self.sigma_e, axes=(2,), t=t)
        self._vertical_unknown = False
        self.events.append({"type": "vertical_reset", "t": t, "jump_m": float(nom.p_n[2] - old)})

    def _reset_position(
        self,
        t: float,
        z: FloatArray,
        v_meas: FloatArray | None,
        sig_v: float,
        has_height: bool,
        sig_white: FloatArray,
    ) -> None:
        """Position (and velocity) from a fix; decorrelate those states. A fix without a height
        leaves the vertical unknown until the next that has one (:meth:`_reset_vertical`)."""
        nom = self.nom
        self._vertical_unknown = not has_height
        T = np.eye(self.n)
        for sl in (M.POS, M.VEL, M.GNE, M.GNM):
            T[sl, :] = 0.0
        self._smoothing_reset(T)  # (the first call starts the recording, below)
        nom.p_n[:] = z - nom.C_nb @ self.lever_b
        nom.e_n[:] = 0.0
        if v_meas is not None:
            nom.v_n[: v_meas.size] = v_meas
            if v_meas.size == 2:
                nom.v_n[2] = 0.0
        nom.e_gm[:] = 0.0
        for sl in (M.POS, M.VEL, M.GNE, M.GNM):
            self.P[sl, :] = 0.0
            self.P[:, sl] = 0.0
        self.P[M.POS, M.POS] = np.diag(self.sigma_e**2 + sig_white**2)
        # [e, e_gm] at their stationary covariance (models.stationary_gnss_error_cov); the
        # position is the fix minus e, whose estimate is 0: its error is the fix's error -e (plus
        # the white part), hence cov(dp, de) = -var(e) and cov(dp, de_gm) = -cov(e, e_gm) (taken
        # as independent, the fix's exact sum p + e made the filter halve the position variance
        # at the first update: horizontal NEES per axis 1.4-1.7 over 20 runs)
        c = self.config
        te = np.array([c.gnss_corr_time_s, c.gnss_corr_time_s, c.gnss_corr_time_v_s])
        C = M.stationary_gnss_error_cov(self.sigma_e**2, te, c.gnss_receiver_filter_s)
        ge = slice(M.GNE.start, M.GNM.stop)
        self.P[ge, ge] = C
        self.P[M.POS, ge] = -C[:3]
        self.P[ge, M.POS] = -C[:, :3]
        self._scaling.reset(self.sigma_e, self._fix_source, t=t)
        sv = sig_v if v_meas is not None else 5.0
        self.P[M.VEL, M.VEL] = np.diag([sv**2, sv**2, max(sv, 0.3) ** 2])
        self.pos_ok = True
        self.t_fix = t
        self.events.append({"type": "position_initialised", "t": t})
        if self.heading_ok:
            self._start_smoothing()
