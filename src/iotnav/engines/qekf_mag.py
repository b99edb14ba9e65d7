"""Magnetometer observations of the quaternion EKF and the vehicle acceleration that the TRIAD
gravity is corrected by, run by :class:`~iotnav.engines.qekf.QekfEngine`.

A calibrated magnetometer sample ``m = S^-1 (m~ - h)`` gives, after the initialisation and once
the heading is known, either the paper's improved-TRIAD attitude observation of gravity and field
(Eq. 7; :func:`~iotnav.engines.qekf_models.triad_measurement`, gravity the mean compensated
``g_b`` since the previous sample, :func:`iotnav.engines.qekf_kernel.accumulate_gravity`) or, in
the consistent form, the field direction alone
(:func:`~iotnav.engines.qekf_models.mag_direction_measurement`); the model, the sigmas and the
disturbance tests are in the module docstring of :mod:`iotnav.engines.qekf`.
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING

import numpy as np

from iotnav.engines import qekf_updates_kernel as KU
from iotnav.engines.base import GnssSample, MagSample
from iotnav.engines.qekf_models import N_STATES, Q_NB, mag_direction_measurement

#: ``triad_state_coupling`` -> :func:`iotnav.engines.qekf_updates_kernel.triad_model`'s ``coupling``
_COUPLING = {"jacobian": KU.TRIAD_JACOBIAN, "noise": KU.TRIAD_NOISE, "accelerometer": KU.TRIAD_ACCELEROMETER}

if TYPE_CHECKING:
    from iotnav.engines.qekf import QekfEngine


def mag(eng: QekfEngine, s: MagSample) -> None:
    c = eng.config
    m_b = eng._S_inv @ (np.asarray(s.mag_b_ut, float) - eng._hard)
    if not eng.initialised:
        eng._sum_mag += m_b
        eng._n_mag += 1
        return
    if not c.use_mag or eng._acc_mag_n == 0 or not eng.heading_ok:
        return
    eng._predict_to(s.t)
    gb = eng._acc_mag_sum / eng._acc_mag_n  # gravity in b (down), m/s^2
    a_dyn = eng._a_dyn_sum / eng._acc_mag_n
    a_comp = eng._a_comp_sum / eng._acc_mag_n
    eng._a_comp_sum = 0.0
    dg_dx = eng._dg_dx_sum / eng._acc_mag_n
    comp_var = eng._comp_var_sum / eng._acc_mag_n
    eng._dg_dx_sum[:] = 0.0
    eng._comp_var_sum = 0.0
    eng._acc_mag_sum[:] = 0.0
    eng._acc_mag_n = 0
    eng._a_dyn_sum = 0.0
    g = float(eng.g_n[2])
    m_ref = float(np.linalg.norm(eng.m_n))
    nm = float(np.linalg.norm(m_b))
    dip_ref = math.asin(eng.m_n[2] / m_ref)
    cos_gm = float(gb @ m_b) / (float(np.linalg.norm(gb)) * nm)
    dip = math.asin(max(-1.0, min(1.0, cos_gm)))
    if abs(nm / m_ref - 1.0) > c.mag_norm_tol or (a_dyn < 0.5 and abs(dip - dip_ref) > c.mag_dip_tol_rad):
        eng.events.append(
            {"type": "mag_rejected", "t": s.t, "reason": "disturbance", "norm_ratio": nm / m_ref}
        )
        return
    if c.mag_observation == "direction":
        z, H, R, hx = mag_direction_measurement(eng.x[Q_NB], m_b, eng.m_n, c.mag_dir_std_rad)
        eng._update(z, eng._pad(H), R, hx, "mag_dir", s.t)
        eng._norm_update(s.t)
        return
    if a_comp > c.triad_max_comp_mps2:
        eng.triad_skipped += 1
        eng.events.append({"type": "triad_skipped", "t": s.t, "reason": "acceleration", "a_mps2": a_comp})
        return
    sig_a = math.sqrt(c.acc_dir_std_rad**2 + (c.dyn_acc_factor * a_dyn / g) ** 2 + comp_var / g**2)
    # triad_measurement, compiled (with the padding of H to the engine's states)
    z, H, R = np.empty(4), np.empty((4, eng.n)), np.empty((4, 4))
    P = eng.P if c.triad_state_coupling == "jacobian" else np.ascontiguousarray(eng.P[:N_STATES, :N_STATES])
    if not KU.triad_model(
        np.ascontiguousarray(eng.x[Q_NB]), gb, m_b, eng.g_n, eng.m_n, sig_a, c.mag_dir_std_rad,
        c.quat_norm_std, dg_dx, P, _COUPLING.get(c.triad_state_coupling, KU.TRIAD_NOISE), z, H, R,
    ):  # fmt: skip
        raise ValueError("TRIAD: the two vectors are (nearly) collinear")
    eng._update(z, H, R, None, "triad", s.t)
    eng._norm_update(s.t)


def gnss_speed(eng: QekfEngine, s: GnssSample) -> tuple[float, float]:
    """GNSS horizontal speed and its sigma (sAcc, else ``vel_noise_mps``), m/s."""
    s_acc = float(getattr(s, "s_acc_mps", math.nan))
    sigma = s_acc if math.isfinite(s_acc) and s_acc > 0 else eng.config.vel_noise_mps
    return float(s.speed_mps), sigma


def filter_speed(eng: QekfEngine) -> tuple[float, float]:
    """The filter's horizontal speed and its sigma (mean horizontal velocity sigma), m/s."""
    return math.hypot(eng.x[4], eng.x[5]), math.sqrt(0.5 * (eng.P[4, 4] + eng.P[5, 5]))


def speed_rate(eng: QekfEngine, t: float, speed: float, sigma_v: float) -> None:
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
    dt_v = t - eng.t_speed
    ok = 0.0 < dt_v <= 1.5
    a = (speed - eng.v_speed) / dt_v if ok else 0.0
    n = eng._f_n
    if ok and n > 0 and n == eng._n_interval and math.isfinite(sigma_v):
        eng._f_ref[:] = eng._f_sum / n
        eng.a_long_std = math.sqrt(2.0) * sigma_v / dt_v
    else:
        eng._f_ref[:] = math.nan
        eng.a_long_std = abs(a - eng.a_long) if ok else abs(a)
    eng._f_sum[:] = 0.0
    eng._f_n = 0
    eng._n_interval = 0
    eng.a_long = a
    eng.t_speed, eng.v_speed = t, speed
