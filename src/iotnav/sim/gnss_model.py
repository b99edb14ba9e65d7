"""GNSS receiver model: true position and velocity to fix epochs (GNSS_COLUMNS form).

Position error
--------------
Per axis (north, east: horizontal; down: vertical) the error is a first-order Gauss-Markov
process ``x`` (standard deviation ``sigma``, correlation time ``tau`` of minutes, set by the
environment) seen through the receiver's own position filter, a first-order low-pass ``y``
with time constant ``tf`` (``receiver_filter_s``, 2 s)::

    dx/dt = -x / tau + w,        dy/dt = (x - y) / tf

sampled exactly at the fix epochs (:func:`filtered_gm`). ``x`` is scaled so that ``y`` has
exactly the standard deviation ``sigma`` (``var(y) = var(x) tau / (tau + tf)``); the
autocorrelation of ``y``,
``(tau e^{-L/tau} - tf e^{-L/tf}) / (tau - tf)``, is ``e^{-L/tau}`` within 1 % for lags
``L > 5 tf``. A static receiver therefore wanders over metres with minute-long correlation.

The per-axis sigma is ``UERE * HDOP / sqrt(2)`` horizontally and ``UERE * VDOP`` vertically
(user equivalent range error times the dilution of precision), with DOPs that drift slowly
(relative sigma ``dop_variation``, 600 s) and a satellite count that falls when the DOP
rises; the environment table below gives UERE, nominal DOPs, satellites, correlation times
and the multipath-outlier statistics. These are model values chosen to reproduce the typical
behaviour of a consumer receiver (CEP 1.5-2.5 m in open sky, metres to tens of metres in
multipath), not datasheet facts.

Velocity
--------
Receivers measure velocity from Doppler, not by differencing positions: the velocity error
is the derivative of the position error, ``dy/dt = (x - y) / tf`` (a few cm/s), plus white
Doppler noise (``doppler_noise_mps``, 1-sigma per axis, reported as ``s_acc_mps``: the
1-sigma of the speed, its along-track component). Speed is the horizontal norm,
course ``atan2(ve, vn)``; below ``course_min_speed_mps`` the course is flagged invalid.

Events
------
* cold start: no fix until ``ttff_s``; then the errors and DOPs are inflated by
  ``m(t) = 1 + (initial_pdop / pdop - 1) e^{-(t - ttff) / converge_tau_s}`` and an offset of
  ``initial_offset_m`` in a random direction decays with the same time constant;
* outages (tunnels): no fix (quality 0 with empty fields, or no sentences at all); after each,
  the error is inflated by ``1 + 2 e^{-(t - t_end) / reacquire_tau_s}``;
* outliers (multipath jumps): Poisson events at ``outliers_per_hour``, each a constant
  horizontal jump of uniform size in ``[outlier_min_m, outlier_max_m]`` lasting about
  ``outlier_duration_s``; the reported DOP does not show them (as in real receivers).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import numpy.typing as npt
import pandas as pd
from scipy.linalg import expm, solve_discrete_lyapunov
from scipy.signal import lfilter

from iotnav.geo import LocalFrame
from iotnav.io.schema import GNSS_COLUMNS, coerce
from iotnav.sim.config import GnssConfig
from iotnav.sim.imu_model import gauss_markov

FloatArray = npt.NDArray[np.float64]

__all__ = ["ENVIRONMENTS", "GnssEnvironment", "filtered_gm", "resolve_environment", "simulate_gnss"]


@dataclass(frozen=True)
class GnssEnvironment:
    """Error level of a reception environment (model values, see the module docstring).

    Attributes
    ----------
    name : str
        Environment name.
    uere_m : float
        User equivalent range error, m (1-sigma).
    hdop, vdop : float
        Nominal dilutions of precision.
    num_sv : int
        Nominal satellites used.
    tau_h_s, tau_v_s : float
        Correlation times of the horizontal and vertical errors, s.
    outliers_per_hour : float
        Rate of multipath jumps.
    outlier_min_m, outlier_max_m : float
        Size range of a jump, m.
    outlier_duration_s : float
        Mean duration of a jump, s.
    """

    name: str
    uere_m: float
    hdop: float
    vdop: float
    num_sv: int
    tau_h_s: float
    tau_v_s: float
    outliers_per_hour: float
    outlier_min_m: float
    outlier_max_m: float
    outlier_duration_s: float

    @property
    def sigma_h_m(self) -> float:
        """Per-axis horizontal 1-sigma, m."""
        return self.uere_m * self.hdop / np.sqrt(2.0)

    @property
    def sigma_v_m(self) -> float:
        """Vertical 1-sigma, m."""
        return self.uere_m * self.vdop


ENVIRONMENTS: dict[str, GnssEnvironment] = {
    e.name: e
    for e in (
        GnssEnvironment("open-sky", 2.0, 0.9, 1.4, 11, 150.0, 200.0, 0.5, 5.0, 12.0, 3.0),
        GnssEnvironment("courtyard", 4.0, 1.7, 2.6, 8, 300.0, 300.0, 6.0, 10.0, 35.0, 5.0),
        GnssEnvironment("urban-canyon", 5.5, 2.3, 3.5, 6, 120.0, 180.0, 20.0, 15.0, 60.0, 4.0),
        GnssEnvironment("under-trees", 4.0, 1.4, 2.2, 9, 180.0, 240.0, 3.0, 8.0, 25.0, 4.0),
    )
}


def resolve_environment(cfg: GnssConfig) -> tuple[GnssEnvironment, float, float, float, float, float]:
    """The environment and the effective ``(sigma_h, sigma_v, tau_h, tau_v, outliers/h)``."""
    try:
        env = ENVIRONMENTS[cfg.environment]
    except KeyError:
        raise ValueError(
            f"gnss.environment: unknown {cfg.environment!r}; expected one of {', '.join(ENVIRONMENTS)}"
        ) from None
    return (
        env,
        env.sigma_h_m if cfg.sigma_h_m is None else cfg.sigma_h_m,
        env.sigma_v_m if cfg.sigma_v_m is None else cfg.sigma_v_m,
        env.tau_h_s if cfg.tau_h_s is None else cfg.tau_h_s,
        env.tau_v_s if cfg.tau_v_s is None else cfg.tau_v_s,
        env.outliers_per_hour if cfg.outliers_per_hour is None else cfg.outliers_per_hour,
    )


def filtered_gm(
    n: int, dt: float, sigma: float, tau: float, tf: float, rng: np.random.Generator, dim: int = 1
) -> tuple[FloatArray, FloatArray]:
    """Gauss-Markov error seen through a first-order receiver filter, sampled exactly.

    The continuous system ``dx = -x/tau dt + q dW``, ``dy = (x - y)/tf dt`` is discretised
    exactly (transition ``expm(A dt)``, noise covariance by Van Loan's method), so the samples
    are those of the continuous process: ``var(y) = var(x) tau / (tau + tf)`` (set to
    ``sigma^2``) and ``var(dy/dt) = sigma^2 / (tf tau)``.

    Returns
    -------
    y, dydt : numpy.ndarray
        Error and its time derivative, each ``(n, dim)``, in steady state from the first sample.
    """
    if sigma == 0.0 or n == 0:
        return np.zeros((n, dim)), np.zeros((n, dim))
    if tf <= 0.0:
        return gauss_markov(n, dt, sigma, tau, rng, dim), np.zeros((n, dim))
    var_x = sigma**2 * (tau + tf) / tau
    qc = 2.0 * var_x / tau  # white-noise intensity driving x
    A = np.array([[-1.0 / tau, 0.0], [1.0 / tf, -1.0 / tf]])
    B = np.array([[qc, 0.0], [0.0, 0.0]])
    vl = expm(np.block([[-A, B], [np.zeros((2, 2)), A.T]]) * dt)
    Phi = vl[2:, 2:].T
    Q = Phi @ vl[:2, 2:]
    Q = 0.5 * (Q + Q.T)
    # stationary covariance P solves P = Phi P Phi^T + Q
    P = solve_discrete_lyapunov(Phi, Q)
    Lq = np.linalg.cholesky(Q + 1e-300 * np.eye(2))
    w = rng.standard_normal((n, 2, dim))
    noise = np.einsum("ij,njd->nid", Lq, w)
    s0 = np.linalg.cholesky(P) @ rng.standard_normal((2, dim))
    # x_k = phi x_{k-1} + w1_k
    phi = Phi[0, 0]
    x = lfilter([1.0], [1.0, -phi], noise[:, 0, :], axis=0, zi=(phi * s0[0])[None, :])[0]
    # y_k = a y_{k-1} + Phi21 x_{k-1} + w2_k
    a = Phi[1, 1]
    x_prev = np.vstack([s0[0][None, :], x[:-1]])
    u = Phi[1, 0] * x_prev + noise[:, 1, :]
    y = lfilter([1.0], [1.0, -a], u, axis=0, zi=(a * s0[1])[None, :])[0]
    return y, (x - y) / tf


def _intervals_mask(t: FloatArray, intervals: tuple[tuple[float, float], ...]) -> npt.NDArray[np.bool_]:
    m = np.zeros(len(t), dtype=bool)
    for a, b in intervals:
        m |= (t >= a) & (t < b)
    return m


def simulate_gnss(
    cfg: GnssConfig,
    t_fix: FloatArray,
    p_n: FloatArray,
    v_n: FloatArray,
    frame: LocalFrame,
    utc_offset_s: float,
    rng: np.random.Generator,
) -> tuple[pd.DataFrame, dict[str, FloatArray]]:
    """Simulate receiver epochs.

    Parameters
    ----------
    cfg : GnssConfig
        Receiver model.
    t_fix : numpy.ndarray
        Fix (validity) times, device clock, s, ``(n,)`` uniform at ``cfg.rate_hz``.
    p_n, v_n : numpy.ndarray
        True antenna position (NED, m) and velocity (m/s) at ``t_fix``, ``(n, 3)``.
    frame : LocalFrame
        Origin of ``n``.
    utc_offset_s : float
        ``utc = t + utc_offset_s``.
    rng : numpy.random.Generator
        Random source.

    Returns
    -------
    pandas.DataFrame
        Epochs in :data:`iotnav.io.schema.GNSS_COLUMNS` form (``source = "sim"``); ``t`` is
        the device time of the NMEA lines (fix time + latency), ``utc`` the fix time.
    dict
        Extras for the writers and the tests: ``err_n`` (position error, m), ``verr_n``
        (velocity error, m/s), ``outlier`` flags, ``prn`` (satellite ids per epoch, -1 unused).
    """
    env, sig_h, sig_v, tau_h, tau_v, out_rate = resolve_environment(cfg)
    if cfg.outage_output not in ("quality0", "silent"):
        raise ValueError(f"gnss.outage_output: expected quality0 or silent, got {cfg.outage_output!r}")
    n = len(t_fix)
    dt = 1.0 / cfg.rate_hz
    # slowly drifting DOPs, common factor for H and V
    dop_f = np.exp(gauss_markov(n, dt, cfg.dop_variation, 600.0, rng, 1)[:, 0])
    hdop = env.hdop * dop_f
    vdop = env.vdop * dop_f
    fix = np.ones(n, dtype=bool)
    m = np.ones(n)
    offset = np.zeros((n, 3))
    if cfg.cold_start:
        fix &= t_fix >= cfg.ttff_s
        pdop0 = float(np.hypot(env.hdop, env.vdop))
        k = np.exp(-np.clip(t_fix - cfg.ttff_s, 0.0, None) / cfg.converge_tau_s)
        m *= 1.0 + (cfg.initial_pdop / pdop0 - 1.0) * k
        ang = rng.uniform(0.0, 2.0 * np.pi)
        offset += cfg.initial_offset_m * k[:, None] * np.array([np.cos(ang), np.sin(ang), 0.5])
    outage = _intervals_mask(t_fix, cfg.outages_s)
    fix &= ~outage
    for _, end in cfg.outages_s:
        after = t_fix >= end
        m[after] *= 1.0 + 2.0 * np.exp(-(t_fix[after] - end) / cfg.reacquire_tau_s)
    hdop = hdop * m
    vdop = vdop * m
    pdop = np.hypot(hdop, vdop)
    num_sv = np.clip(np.round(env.num_sv * (env.hdop / hdop) ** 0.7), 4, 24).astype(int)
    num_sv[~fix] = np.clip(np.round(env.num_sv * 0.3), 0, 3)

    err = np.zeros((n, 3))
    verr = np.zeros((n, 3))
    outlier = np.zeros(n, dtype=bool)
    if cfg.errors:
        yh, dyh = filtered_gm(n, dt, 1.0, tau_h, cfg.receiver_filter_s, rng, 2)
        yv, dyv = filtered_gm(n, dt, 1.0, tau_v, cfg.receiver_filter_s, rng, 1)
        gain_h = sig_h * m * dop_f
        gain_v = sig_v * m * dop_f
        err[:, :2] = yh * gain_h[:, None]
        err[:, 2] = yv[:, 0] * gain_v
        err += offset
        verr[:, :2] = dyh * gain_h[:, None]
        verr[:, 2] = dyv[:, 0] * gain_v
        verr += rng.normal(0.0, cfg.doppler_noise_mps, (n, 3)) * np.sqrt(m)[:, None]
        # multipath jumps
        span_h = n * dt / 3600.0
        n_out = rng.poisson(out_rate * span_h)
        for _ in range(n_out):
            i0 = int(rng.integers(0, n))
            length = max(round(rng.exponential(env.outlier_duration_s) / dt), 1)
            size = rng.uniform(env.outlier_min_m, env.outlier_max_m)
            ang = rng.uniform(0.0, 2.0 * np.pi)
            sl = slice(i0, min(i0 + length, n))
            err[sl] += size * np.array([np.cos(ang), np.sin(ang), rng.normal(0.0, 0.5)])
            outlier[sl] = True

    pos = p_n + err
    vel = v_n + verr
    lat, lon, h = frame.from_ned(pos)
    speed = np.hypot(vel[:, 0], vel[:, 1])
    course = np.mod(np.arctan2(vel[:, 1], vel[:, 0]), 2.0 * np.pi)
    uere = env.uere_m if cfg.sigma_h_m is None else cfg.sigma_h_m * np.sqrt(2.0) / env.hdop
    nan = np.full(n, np.nan)
    df = pd.DataFrame(
        {
            "t": t_fix + cfg.latency_s,
            "utc": t_fix + utc_offset_s,
            "lat_deg": np.where(fix, lat, nan),
            "lon_deg": np.where(fix, lon, nan),
            "height_m": np.where(fix, h, nan),
            "alt_msl_m": np.where(fix, h - cfg.geoid_sep_m, nan),
            "geoid_sep_m": np.where(fix, cfg.geoid_sep_m, nan),
            "quality": np.where(fix, 1, 0),
            "mode": np.where(fix, 3, 1),
            "num_sv": num_sv,
            "pdop": np.where(fix, pdop, nan),
            "hdop": np.where(fix, hdop, nan),
            "vdop": np.where(fix, vdop, nan),
            "speed_mps": np.where(fix, speed, nan),
            "course_rad": np.where(fix, course, nan),
            "course_valid": fix & (speed >= cfg.course_min_speed_mps),
            "vn": np.where(fix, vel[:, 0], nan),
            "ve": np.where(fix, vel[:, 1], nan),
            "vd": np.where(fix, vel[:, 2], nan),
            "h_acc_m": np.where(fix, uere * hdop, nan),
            "v_acc_m": np.where(fix, uere * vdop, nan),
            # the 1-sigma of the speed: the per-axis Doppler sigma (the velocity error along track)
            "s_acc_mps": np.where(fix, cfg.doppler_noise_mps * np.sqrt(m), nan),
            "valid": fix,
            "source": "sim",
        }
    )
    # satellite ids: a fixed random ordering of PRNs, the first num_sv used
    prn_order = rng.permutation(np.arange(1, 33))
    prn = np.where(np.arange(12)[None, :] < np.minimum(num_sv, 12)[:, None], prn_order[None, :12], -1)
    prn[~fix] = -1
    extras = {"err_n": err, "verr_n": verr, "outlier": outlier, "prn": prn}
    if cfg.outage_output == "silent":
        keep = ~outage
        df = df.loc[keep].reset_index(drop=True)
        extras = {k: v[keep] for k, v in extras.items()}
    return coerce(df, GNSS_COLUMNS), extras
