"""No-magnetometer fallback of the quaternion EKF (designed here), run by
:class:`~iotnav.engines.qekf.QekfEngine`.

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
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING

import numpy as np

from iotnav import kalman
from iotnav.engines import qekf_kernel as K
from iotnav.engines import qekf_updates_kernel as KU
from iotnav.engines.base import GnssSample
from iotnav.engines.qekf_models import GNE, GNM, N_STATES, POS, Q_NB, VEL, FloatArray, quat_left, quat_right
from iotnav.techniques.mount import wrap
from iotnav.techniques.triad import quat_to_dcm

if TYPE_CHECKING:
    from iotnav.engines.qekf import QekfEngine


def gnss_before_heading(
    eng: QekfEngine, s: GnssSample, z: FloatArray, H: FloatArray, R: FloatArray, r_mean: float
) -> None:
    """Fallback steps 2-3 (module docstring): vertical updates, horizontal re-initialisation,
    and the heading reset once driving straight and fast with a mount angle."""
    c = eng.config
    if eng.smoothing_log is not None:
        if eng._prior is None:
            eng._prior = (eng.x.copy(), eng.P.copy())
        # the re-initialisation is no Kalman update: the RTS smoother must not carry
        # information back across it (zero transition, zero gain)
        eng._Phi = np.zeros((eng.n, eng.n))
    if z.size == 3:
        eng._update(z[2:], H[2:], R[2:, 2:], None, "gnss_pos_down", s.t)
    v = eng._gnss_velocity(s) if c.use_gnss_velocity else None
    s_acc = float(getattr(s, "s_acc_mps", math.nan))
    sig_v = s_acc if math.isfinite(s_acc) and s_acc > 0 else c.vel_noise_mps
    if v is not None and v.size == 3:
        zv, Hv, Rv = eng._velocity_measurement(v, sig_v)
        eng._update(zv[2:], Hv[2:], Rv[2:, 2:], None, "gnss_vel_down", s.t)
    elif v is None and math.isfinite(s.speed_mps):
        v, sig_v = np.zeros(2), math.hypot(s.speed_mps, c.vel_noise_mps)  # slow: no course
    idx = [POS.start, POS.start + 1]
    var = [R[0, 0], R[1, 1]]
    if v is not None:
        idx += [VEL.start, VEL.start + 1]
        var += [sig_v**2, sig_v**2]
    ge = [GNE.start, GNE.start + 1, GNM.start, GNM.start + 1] if eng.n > N_STATES else []
    eng.P[idx + ge, :] = 0.0
    eng.P[:, idx + ge] = 0.0
    eng.P[idx, idx] = var
    eng.x[POS.start : POS.start + 2] = z[:2]
    if ge:
        # r = z - e - w with e = 0: var(r) = var_e + var_w, cov(r, e) = cov(r, e_gm) = -var_e
        C = eng._gnss_error_cov(slice(0, 2))
        eng.x[ge] = 0.0
        eng.P[np.ix_(ge, ge)] = C
        eng.P[np.ix_(idx[:2], ge)] = -C[:2]
        eng.P[np.ix_(ge, idx[:2])] = -C[:, :2]
        eng.P[idx[:2], idx[:2]] += eng._var_e[:2]
        eng._scaling.reset(np.sqrt(eng._var_e), axes=(0, 1))
    if v is not None:
        eng.x[VEL.start : VEL.start + 2] = v[:2]
    eng.t_fix = s.t
    eng._norm_update(s.t)
    eng._speed_rate(s.t, *(eng._gnss_speed(s) if math.isfinite(s.speed_mps) else eng._filter_speed()))
    if v is None or not eng.aligner.known:
        return
    speed = float(np.hypot(v[0], v[1]))
    if speed < c.heading_min_speed_mps or not abs(r_mean) <= c.heading_max_yaw_rate_rad_s:
        return
    chi = math.atan2(v[1], v[0])
    sig_mu = float(eng.aligner.quality.get("std_rad", c.mount.max_std_rad))
    sigma = math.sqrt((sig_v / speed) ** 2 + sig_mu**2 + c.nhc_sideslip_std_rad**2)
    eng._set_heading(s.t, wrap(chi + eng.aligner.mount_yaw_rad), sigma)


def set_heading(eng: QekfEngine, t: float, yaw_b: float, sigma: float) -> None:
    """Fallback step 3: reset the sensor yaw to ``yaw_b`` (rad) with sigma ``sigma`` (rad)."""
    q = eng.x[Q_NB]
    C = quat_to_dcm(q / np.linalg.norm(q))
    d = wrap(yaw_b - math.atan2(C[1, 0], C[0, 0]))
    T = np.eye(eng.n)
    T[Q_NB, Q_NB] = quat_left(np.array([math.cos(0.5 * d), 0.0, 0.0, math.sin(0.5 * d)]))
    eng.x = T @ eng.x
    P = T @ eng.P @ T.T
    e = np.zeros(eng.n)
    e[Q_NB] = 0.5 * quat_right(eng.x[Q_NB])[:, 3]
    u = e / np.linalg.norm(e)
    Pi = np.eye(eng.n) - np.outer(u, u)
    eng.P = kalman.symmetrize(Pi @ P @ Pi.T + sigma**2 * np.outer(e, e))
    eng.heading_ok = True
    eng.t_nhc = t
    eng._r_nhc[:] = 0.0
    eng.events.append(
        {
            "type": "heading_initialised",
            "t": t,
            "yaw_rad": yaw_b,
            "change_rad": d,
            "std_rad": sigma,
            "mount_yaw_rad": eng.aligner.mount_yaw_rad,
            "source": "gnss_course",
        }
    )


def nhc(eng: QekfEngine, t: float) -> None:
    """Fallback step 4: the non-holonomic observation (module docstring), its Python form, run
    with smoothing records or innovation logs of it; otherwise the IMU loop runs the compiled
    :func:`iotnav.engines.qekf_updates_kernel.nhc_step`, bitwise the same
    (``tests/test_qekf_kernel.py``)."""
    c = eng.config
    r_mean = eng._r_nhc[0] / eng._r_nhc[1] if eng._r_nhc[1] > 0 else 0.0
    eng._r_nhc[:] = 0.0
    eng.t_nhc = t
    speed = math.hypot(eng.x[VEL.start], eng.x[VEL.start + 1])
    if speed < c.nhc_min_speed_mps or abs(r_mean) > c.nhc_max_yaw_rate_rad_s:
        return
    sig_mu = float(eng.aligner.quality.get("std_rad", c.mount.max_std_rad))
    var = (
        c.nhc_vel_std_mps**2
        + speed**2 * (c.nhc_sideslip_std_rad**2 + sig_mu**2)
        + (r_mean * c.nhc_lever_m) ** 2
    )
    H, R, hx = np.empty((1, eng.n)), np.empty((1, 1)), np.empty(1)
    eng._contiguous()  # nhc_measurement, compiled
    KU.nhc_model(eng.x, float(eng.aligner.mount_yaw_rad), math.sqrt(var), H, R, hx)
    eng._update(np.zeros(1), H, R, hx, "nhc", t)
    eng._norm_update(t)


def nhc_kernel_inputs(eng: QekfEngine) -> None:
    """Before :func:`iotnav.engines.qekf_kernel.imu_run`: whether it applies the non-holonomic
    observation itself (:func:`iotnav.engines.qekf_updates_kernel.nhc_step`, the same steps as
    :func:`nhc`: without smoothing records and without innovation logs of ``nhc`` or ``norm``),
    and the aligner's mount yaw and sigma it uses (constant between GNSS epochs)."""
    st = eng.st
    compiled = eng.smoothing_log is None and "nhc" not in eng.innovations and "norm" not in eng.innovations
    st[K.S_NHC_COMPILED] = 1.0 if compiled and eng.fallback and eng.heading_ok else 0.0
    if st[K.S_NHC_COMPILED] != 0.0:
        st[K.S_NHC_MOUNT] = float(eng.aligner.mount_yaw_rad)
        st[K.S_NHC_SIG_MU] = float(eng.aligner.quality.get("std_rad", eng.config.mount.max_std_rad))


def nhc_kernel_log(eng: QekfEngine) -> None:
    """After :func:`iotnav.engines.qekf_kernel.imu_run`: its non-holonomic and norm updates into
    ``eng.nis`` (and a rejection into ``eng.events``), as :meth:`QekfEngine._update` records them."""
    n = int(eng.st[K.S_N_LOG])
    if n == 0:
        return
    for t, kind, nis, accepted in eng._nlog[:n].tolist():
        name = "nhc" if kind == K.LOG_NHC else "norm"
        eng.nis.append((t, name, nis, 1))
        if not accepted:
            eng.events.append({"type": f"{name}_rejected", "t": t, "reason": "nis", "nis": nis})
    eng.st[K.S_N_LOG] = 0.0
