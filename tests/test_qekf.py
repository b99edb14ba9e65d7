"""Quaternion EKF: analytic Jacobians, car-magnetometer accuracy, Monte Carlo consistency,
no-magnetometer fallback on car-tunnel (seeded)."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
from scipy.spatial.transform import Rotation

from iotnav import sim
from iotnav.engines.base import iter_samples, run_batch
from iotnav.engines.qekf import (
    GNE,
    GNM,
    N_STATES,
    N_STATES_GNSS,
    POS,
    Q_NB,
    VEL,
    QekfConfig,
    QekfEngine,
    delta_quat,
    gnss_error_transition,
    mag_direction_measurement,
    nhc_measurement,
    norm_measurement,
    propagate,
    rotate_jacobian,
)
from iotnav.engines.smoother import smooth_output
from iotnav.eval.metrics import outage_drift, track_errors
from iotnav.eval.qekf_mc import MC_OVERRIDES_RECEIVER, attitude_rms_deg, car_config, simulate
from iotnav.io import ingest
from iotnav.io.log import Log

G_N = np.array([0.0, 0.0, 9.806])


def _state(yaw: float, pitch: float, roll: float) -> np.ndarray:
    x = np.zeros(N_STATES)
    qx, qy, qz, qw = Rotation.from_euler("ZYX", [yaw, pitch, roll]).as_quat()
    x[Q_NB] = [qw, qx, qy, qz]
    x[VEL] = [12.0, -3.0, 0.4]
    x[POS] = [150.0, -40.0, 2.0]
    x[10:13] = [0.01, -0.02, 0.004]
    x[13:16] = [0.15, -0.1, 0.05]
    x[16:19] = [1.01, 0.995, 1.002]
    x[19:22] = [0.99, 1.01, 1.004]
    return x


def _num_jac(fun, x: np.ndarray, eps: float = 1e-6) -> np.ndarray:  # type: ignore[no-untyped-def]
    cols = []
    for i in range(x.size):
        d = np.zeros(x.size)
        d[i] = eps
        cols.append((fun(x + d) - fun(x - d)) / (2 * eps))
    return np.array(cols).T


@pytest.mark.parametrize(
    "attitude",
    [(0.7, 0.2, -0.1), (2.5, np.pi / 2 - 1e-5, 0.3), (-1.0, -np.pi / 2 + 1e-5, -2.0), (0.0, 0.0, np.pi)],
    ids=["generic", "pitch+90", "pitch-90", "upside-down"],
)
@pytest.mark.parametrize(
    "gyro", [np.array([0.1, -0.2, 0.35]), np.array([1e-7, 0.0, -2e-7])], ids=["turn", "still"]
)
def test_propagation_jacobians_match_finite_differences(
    attitude: tuple[float, float, float], gyro: np.ndarray
) -> None:
    x = _state(*attitude)
    acc = np.array([0.6, -0.4, -9.7])
    dt = 0.02
    _, F, G_g, G_a = propagate(x, acc, gyro, dt, G_N)
    Fn = _num_jac(lambda z: propagate(z, acc, gyro, dt, G_N)[0], x)
    Ggn = _num_jac(lambda w: propagate(x, acc, w, dt, G_N)[0], gyro)
    Gan = _num_jac(lambda a: propagate(x, a, gyro, dt, G_N)[0], acc)
    assert np.abs(F - Fn).max() < 1e-7
    assert np.abs(G_g - Ggn).max() < 1e-7
    assert np.abs(G_a - Gan).max() < 1e-7


@pytest.mark.parametrize("scale", [0.0, 1e-6, 1e-3, 0.5])
def test_delta_quat_and_rotation_jacobians(scale: float) -> None:
    th = np.array([0.3, -0.7, 0.5]) * scale
    dq, J = delta_quat(th)
    x, y, z, w = Rotation.from_rotvec(th).as_quat()
    assert np.allclose(dq, [w, x, y, z], atol=1e-15)
    assert np.allclose(J, _num_jac(lambda t: delta_quat(t)[0], th, 1e-7), atol=1e-8)
    q = np.array([0.9, 0.1, -0.3, 0.2])  # deliberately not unit: the quadratic form's Jacobian
    f = np.array([1.0, -2.0, 9.0])
    _, Jc = rotate_jacobian(q, f)
    assert np.allclose(Jc, _num_jac(lambda qq: rotate_jacobian(qq, f)[0], q), atol=1e-8)


def test_norm_pseudo_observation_jacobian() -> None:
    x = _state(0.3, 0.1, 0.2)
    x[Q_NB] *= 1.01
    _z, H, _R, hx = norm_measurement(x, 1e-3)
    assert hx[0] == pytest.approx(1.0 - 1.01)
    Hn = _num_jac(lambda z: norm_measurement(z, 1e-3)[3], x)
    assert np.allclose(H, Hn, atol=1e-9)


@pytest.mark.parametrize(
    "attitude",
    [(0.7, 0.2, -0.1), (2.5, np.pi / 2 - 1e-5, 0.3), (-1.0, -np.pi / 2 + 1e-5, -2.0), (0.0, 0.0, np.pi)],
    ids=["generic", "pitch+90", "pitch-90", "upside-down"],
)
@pytest.mark.parametrize("qscale", [1.0, 1.02], ids=["unit", "non-unit"])
@pytest.mark.parametrize(
    "field", [[22.4, 1.1, 41.3], [0.0, 0.0, 50.0], [30.0, 0.0, 0.0]], ids=["dip", "pole", "equator"]
)
def test_mag_direction_measurement_jacobian(
    attitude: tuple[float, float, float], qscale: float, field: list[float]
) -> None:
    """``z = E^T u~_b`` with ``E`` fixed by the prediction: ``H`` is the derivative of the
    projected unit field direction that a quaternion ``q'`` would produce, at ``q'`` = state
    (the scale of ``q`` left out); the prediction itself projects to 0."""
    x = _state(*attitude)
    x[Q_NB] *= qscale
    m_n = np.array(field)
    q = x[Q_NB]
    R_nb = Rotation.from_quat(np.r_[q[1:], q[0]]).as_matrix()
    m_b = 3.0 * R_nb.T @ m_n  # a sample of another magnitude, the direction of the prediction
    z, H, R, hx = mag_direction_measurement(q, m_b, m_n, 0.01)
    assert np.allclose(z, 0.0, atol=1e-12) and np.allclose(hx, 0.0)
    assert np.allclose(R, 1e-4 * np.eye(2))
    # the projection: z of the three body axes (m_b = e_k) are the columns of E
    E = np.stack([mag_direction_measurement(q, e, m_n, 0.01)[0] for e in np.eye(3)], axis=1)
    assert np.allclose(E @ E.T, np.eye(2), atol=1e-12)
    assert np.allclose(E @ (R_nb.T @ m_n), 0.0, atol=1e-9)

    def z_of(xx: np.ndarray) -> np.ndarray:
        qq = xx[Q_NB] / np.linalg.norm(xx[Q_NB])
        u = Rotation.from_quat(np.r_[qq[1:], qq[0]]).as_matrix().T @ m_n
        return E @ (u / np.linalg.norm(u))

    Hn = _num_jac(z_of, x)
    assert np.allclose(H, Hn, atol=1e-8), np.abs(H - Hn).max()


def test_cross_axis_noise_follows_the_motion() -> None:
    """``gyro_misalignment`` / ``acc_misalignment`` add ``k_w (|w|^2 - w_i^2)`` to the gyro's
    white-noise intensity per axis and ``k_a (|a|^2 - a_i^2) dt`` to the accelerometer-bias
    variance, with ``k_w = 2 m^2 tau``, ``k_a = 2 m^2 / tau`` (as ``eskf``); nothing at rest
    without rotation, and nothing with 0 (the paper's form)."""

    def step_Q(cfg: QekfConfig, acc: np.ndarray, gyro: np.ndarray) -> np.ndarray:
        eng = QekfEngine(cfg)
        eng.initialised = eng.have_imu = True
        eng.x = _state(0.0, 0.0, 0.0)
        eng.x[10:22] = [0.0] * 6 + [1.0] * 6
        eng.P = np.zeros((N_STATES, N_STATES))
        eng.acc, eng.gyro, eng.g_n, eng.t_x = acc, gyro, G_N, 0.0
        eng._predict_to(0.02)
        return eng.P

    m, tau = 0.01, 4.0
    on = QekfConfig(gyro_misalignment=m, acc_misalignment=m, cross_axis_corr_time_s=tau)
    off = QekfConfig()
    rest = np.array([0.0, 0.0, -9.806])  # level, still: a = f + C^T g = 0
    assert np.allclose(step_Q(on, rest, np.zeros(3)), step_Q(off, rest, np.zeros(3)), rtol=0, atol=1e-18)
    acc = np.array([2.0, -1.0, -9.806])  # kinematic acceleration (2, -1, 0) m/s^2
    gyro = np.array([0.0, 0.0, 0.5])
    dP = step_Q(on, acc, gyro) - step_Q(off, acc, gyro)
    ba = np.diag(dP)[13:16]
    assert np.allclose(ba, 2 * m**2 / tau * np.array([1.0, 4.0, 5.0]) * 0.02, rtol=1e-9)
    # roll/pitch (quaternion x, y) get the yaw rate's coupling, the yaw (z) none
    dq = np.diag(dP)[Q_NB]
    var = 2 * m**2 * tau * 0.25 * 0.02  # (|w|^2 - w_i^2) per second, over dt
    assert np.allclose(dq[1:3], var * 0.25, rtol=1e-3) and abs(dq[3]) < 1e-15
    with pytest.raises(ValueError, match="cross_axis_corr_time_s"):
        QekfEngine(QekfConfig(cross_axis_corr_time_s=0.0))
    with pytest.raises(ValueError, match="mag_observation"):
        QekfEngine(QekfConfig(mag_observation="vector"))


# ----------------------------------------------------------------------------- scenario
# (simulate, car_config, attitude_rms_deg: iotnav.eval.qekf_mc, shared with the Monte Carlo)


def test_car_magnetometer_attitude_and_gap(tmp_path: Path) -> None:
    """Paper Sec. 5: 40 s static initialisation, ~220 s of town driving, a 4 s GNSS gap.

    Observed (seed 0): forward roll 0.32, pitch 0.32, yaw 0.59 deg RMS, largest horizontal
    error in the 4 s gap 3.3 m (before the changes to the initial alignment covariance, the
    TRIAD coupling and the along-track acceleration: 0.33, 0.49, 1.07 deg, 3.6 m); the RTS
    smoother lowers roll and pitch (0.20, 0.24 deg) and the horizontal RMS (2.23 -> 2.02 m).
    """
    r, log = simulate(tmp_path, seed=0)
    eng = QekfEngine(car_config(r, smoothing=True))
    rows = [o for s in iter_samples(log) if (o := eng.step(s)) is not None]
    fwd = pd.DataFrame(rows)
    assert len(fwd) == len(log.imu)  # one output per IMU sample (50 Hz)
    init = next(e for e in eng.events if e["type"] == "init_done")
    assert 39.9 < init["t"] < 40.2
    rms = attitude_rms_deg(fwd, r.truth, init["t"] + 1.0)
    assert rms["roll"] < 1.0 and rms["pitch"] < 1.0, rms
    assert rms["yaw"] < 2.0, rms
    gap = r.config.gnss.outages_s[0]
    err = track_errors(fwd.dropna(subset=["lat"]), r.truth)
    in_gap = (err.t >= gap[0]) & (err.t <= gap[1] + 0.5)
    assert in_gap.sum() > 150
    assert err.h_err[in_gap].max() < 5.0
    # the magnetic disturbance (120-132 s) is detected
    rej = [e["t"] for e in eng.events if e["type"] == "mag_rejected"]
    assert any(120.0 < t < 132.0 for t in rej)
    # RTS smoother over the same run (result stated in the smoother tests' docstring)
    sm = smooth_output(eng, fwd)
    rms_s = attitude_rms_deg(sm, r.truth, init["t"] + 1.0)
    err_s = track_errors(sm.dropna(subset=["lat"]), r.truth)
    assert np.sqrt(np.mean(err_s.h_err**2)) < np.sqrt(np.mean(err.h_err**2))
    assert rms_s["roll"] < rms["roll"] and rms_s["pitch"] < rms["pitch"]


@pytest.mark.slow
def test_smoother_across_tunnels_uses_the_unwidened_prior(tmp_path: Path) -> None:
    """The first fix after an outage is forced (covariance widened by the disagreement); its
    smoothing record gets the prior the filter had before the widening, so the exit fix
    corrects the tunnel behind it. car-tunnel seed 0, 330 s, consistent form. Observed: largest
    error in the tunnels 19.4 -> 2.2 m and 23.8 -> 2.4 m, RMS 6.45 -> 1.34 m; with the
    widened prior recorded 3.3 and 5.5 m (ratios 0.17, 0.23), RMS 2.27 m, and a position
    process noise of 354 and 163 m^2 in the records of the two exit fixes (now 1e-10)."""
    r = sim.build("car-tunnel", seed=0, overrides={"duration_s": 330.0})
    sim.write(r, tmp_path)
    eng = QekfEngine(QekfConfig.consistent(smoothing=True))
    fwd = run_batch(eng, ingest([tmp_path]))
    sm = smooth_output(eng, fwd)
    ef = track_errors(fwd.dropna(subset=["lat"]), r.truth)
    es = track_errors(sm.dropna(subset=["lat"]), r.truth)
    rms_f, rms_s = (float(np.sqrt(np.mean(e.h_err**2))) for e in (ef, es))
    assert rms_s < 0.3 * rms_f, (rms_f, rms_s)
    for a, b in [(a, b) for a, b in r.config.gnss.outages_s if b < 330.0]:
        m = (ef.t >= a) & (ef.t <= b)
        assert es.h_err[m].max() < 0.15 * ef.h_err[m].max(), (a, b)
    slog = eng.smoothing_log
    assert slog is not None
    t_rec = np.asarray(slog.t)
    forced = [e["t"] for e in eng.events if e["type"] == "gnss_pos_forced"]
    assert len(forced) == 2
    for t in forced:
        k = int(np.searchsorted(t_rec, t))
        assert t_rec[k] == t
        Q = slog.P_prior[k] - slog.Phi[k] @ slog.P_post[k - 1] @ slog.Phi[k].T
        assert np.linalg.eigvalsh(0.5 * (Q + Q.T)).min() > -1e-9
        assert np.linalg.eigvalsh(Q[POS, POS]).max() < 1e-3, t


@pytest.mark.parametrize("seed", [6, 8])
@pytest.mark.slow
def test_car_magnetometer_yaw_other_seeds(tmp_path: Path, seed: int) -> None:
    """Roll/pitch RMS below 1 deg and yaw below 2 deg on more seeds: met on 8 of 8 (seeds
    1-8, ``benchmarks/bench_qekf_consistency.py --part seeds``); the suite runs the two with
    the least margin, 6 and 8.

    Observed roll / pitch / yaw RMS (deg) on seeds 1-8: 0.43/0.37/0.78, 0.63/0.47/1.41,
    0.46/0.35/1.00, 0.82/0.52/1.39, 0.49/0.47/0.76, 0.72/0.58/1.57, 0.42/0.33/0.52,
    0.75/0.58/1.69. Before the initial tilt / accelerometer-bias correlation was kept whole,
    the TRIAD observation coupled to the accelerometer states through ``H`` and the
    along-track acceleration freed of its lag, seeds 4, 6 and 8 missed (yaw 2.22, 2.69,
    2.85 deg; roll/pitch 1.00/1.07 on seed 6, 1.03/1.00 on seed 8).
    """
    r, log = simulate(tmp_path, seed=seed)
    eng = QekfEngine(car_config(r, smoothing=False))
    fwd = pd.DataFrame([o for s in iter_samples(log) if (o := eng.step(s)) is not None])
    rms = attitude_rms_deg(fwd, r.truth, 41.0)
    assert rms["roll"] < 1.0 and rms["pitch"] < 1.0, rms
    assert rms["yaw"] < 2.0, rms


@pytest.mark.parametrize("zero_lag", [False, True], ids=["lagged", "zero-lag"])
def test_triad_measurement_jacobian_matches_finite_differences(zero_lag: bool) -> None:
    """``H`` of the TRIAD observation: ``-d z / d x_hat`` for the states that build ``g_b``;
    along-track acceleration from the last interval's speed change alone (``lagged``) or
    corrected by the accelerometer's change since (``zero-lag``, means of the interval set)."""
    from iotnav.engines.qekf import BA, BG, SA, SG, triad_measurement
    from iotnav.techniques.triad import dcm_to_quat, improved_triad

    x = _state(0.7, 0.1, -0.05)
    m_n = np.array([22.4, 1.1, 41.3])
    acc = np.array([0.5, -0.3, -9.6])
    gyro = np.array([0.01, -0.02, 0.15])
    eng = QekfEngine(QekfConfig(smoothing=False))
    eng.g_n, eng.m_n = G_N, m_n
    eng.t_x = eng.t_speed = 0.0
    eng.a_long = 0.4
    # the previous interval (zero-lag): its mean specific force, from another raw output and the
    # same bias and scale estimates; ``acc - acc_ref`` (1 m/s^2) is nearly perpendicular to
    # ``v_b`` ([0.58, -0.81, 0.05]), so ``g_b`` stays near the attitude's gravity (the TRIAD
    # Jacobian is exact for consistent vectors) while ``d a_l / d v`` is large
    acc_ref = np.array([-0.31, -0.88, -9.6])

    def set_reference(xx: np.ndarray) -> None:
        if zero_lag:
            eng._f_ref = (acc_ref - xx[BA]) / xx[SA]

    def gravity(xx: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        eng.x = xx.copy()
        set_reference(xx)
        eng._acc_mag_sum[:] = 0.0
        eng._dg_dx_sum[:] = 0.0
        eng._acc_mag_n = 0
        eng._accumulate_gravity(acc, gyro)
        return eng._acc_mag_sum.copy(), eng._dg_dx_sum.copy()

    from iotnav.techniques.triad import quat_to_dcm

    m_b = quat_to_dcm(x[Q_NB]).T @ m_n
    g_b, D = gravity(x)
    z, H, _R = triad_measurement(x[Q_NB], g_b, m_b, G_N, m_n, 0.02, 0.015, 1e-3, D)
    cols = np.r_[VEL, BG, BA, SG, SA]

    def zq(xx: np.ndarray) -> np.ndarray:
        q = dcm_to_quat(improved_triad(gravity(xx)[0], m_b, G_N, m_n, 0.02, 0.015))
        return q if q @ z >= 0 else -q

    Hn = _num_jac(zq, x)
    assert np.allclose(H[:, cols], -Hn[:, cols], atol=2e-4)
    assert np.allclose(H[:, Q_NB], np.eye(4))
    # the noise form keeps H = [I 0] and adds Jx P Jx^T to R
    P = np.eye(N_STATES) * 1e-4
    _z, H2, R2 = triad_measurement(x[Q_NB], g_b, m_b, G_N, m_n, 0.02, 0.015, 1e-3, D, P)
    Jx = -H[:, cols]
    assert np.allclose(H2[:, cols], 0.0)
    assert np.allclose(R2 - _R, 1e-4 * Jx @ Jx.T)
    # the default coupling: the accelerometer's bias and scale in H, the rest as noise
    acc_cols = np.r_[BA, SA]
    comp_cols = np.r_[VEL, BG, SG]
    _z, H3, R3 = triad_measurement(x[Q_NB], g_b, m_b, G_N, m_n, 0.02, 0.015, 1e-3, D, P, acc_cols)
    assert np.allclose(H3[:, acc_cols], H[:, acc_cols]) and np.abs(H[:, acc_cols]).max() > 1e-3
    assert np.allclose(H3[:, comp_cols], 0.0)
    Jc = -H[:, comp_cols]
    assert np.allclose(R3 - _R, 1e-4 * Jc @ Jc.T)


# ----------------------------------------------------------------------------- consistency


@pytest.mark.parametrize("seed", [0, 7])
@pytest.mark.slow
def test_car_magnetometer_consistent_form(tmp_path: Path, seed: int) -> None:
    """:meth:`QekfConfig.consistent` on the full car-magnetometer runs (GNSS velocity, the
    magnetic disturbance, the 4 s gap): roll/pitch RMS below 1 deg, yaw below 2 deg, the 4 s
    gap below 5 m, on all 9 seeds (``benchmarks/bench_qekf_consistency.py --part seeds``); the
    suite runs the two with the largest gap errors, 0 and 7.

    Observed roll / pitch / yaw RMS (deg) and the gap's largest error (m), seeds 0-8:
    0.36/0.33/0.65 3.5, 0.47/0.30/0.88 2.9, 0.31/0.30/0.57 2.3, 0.39/0.34/0.80 2.0,
    0.37/0.31/0.69 2.6, 0.33/0.31/0.57 1.8, 0.40/0.38/0.88 2.0, 0.48/0.34/0.82 3.4,
    0.39/0.34/0.80 2.7; mean yaw 0.74 deg against the paper form's 1.08 (its TRIAD
    observations while driving tie the tilt to the accelerometer's bias), roll and pitch
    0.39 / 0.33 against 0.56 / 0.45; horizontal RMS 1.44 m against 1.77 m.
    """
    r, log = simulate(tmp_path, seed=seed)
    eng = QekfEngine(car_config(r, True, smoothing=False))
    fwd = pd.DataFrame([o for s in iter_samples(log) if (o := eng.step(s)) is not None])
    rms = attitude_rms_deg(fwd, r.truth, 41.0)
    assert rms["roll"] < 1.0 and rms["pitch"] < 1.0, rms
    assert rms["yaw"] < 2.0, rms
    gap = r.config.gnss.outages_s[0]
    err = track_errors(fwd.dropna(subset=["lat"]), r.truth)
    in_gap = (err.t >= gap[0]) & (err.t <= gap[1] + 0.5)
    assert in_gap.sum() > 150 and err.h_err[in_gap].max() < 5.0
    n_mag = sum(1 for n in eng.nis if n[1] == "mag_dir")
    assert n_mag > 500 and not any(n[1] == "triad" for n in eng.nis)
    assert any(e["type"] == "mag_rejected" and 120.0 < e["t"] < 132.0 for e in eng.events)


@pytest.mark.parametrize(
    ("corr_time", "filt"), [(150.0, 2.0), (2.0, 2.0), (150.0, 0.0), (5.0, 5.0 * (1 - 1e-7)), (5.0, 4.99)]
)
@pytest.mark.parametrize("dt", [0.02, 1.0])
def test_gnss_error_transition_is_exact(corr_time: float, filt: float, dt: float) -> None:
    """Transition and process noise of ``[e, e_gm]`` against the matrix exponential (Van Loan
    1978), and the stationary covariance ``var(e) = cov(e, e_gm) = 1``,
    ``var(e_gm) = (T_e + t_f) / T_e`` kept by them."""
    from scipy.linalg import expm

    Phi, Q = gnss_error_transition(dt, corr_time, filt)
    if filt > 0:
        A = np.array([[-1.0 / filt, 1.0 / filt], [0.0, -1.0 / corr_time]])
        g = (corr_time + filt) / corr_time
        Qc = np.diag([0.0, 2.0 / corr_time])  # per unit var(e_gm)
        C = np.array([[1.0, 1.0], [1.0, g]])
    else:  # e itself first-order Gauss-Markov, e_gm inert
        A = np.array([[-1.0 / corr_time, 0.0], [0.0, 0.0]])
        g = 1.0
        Qc = np.diag([2.0 / corr_time, 0.0])
        C = np.diag([1.0, 0.0])
    M = expm(np.block([[-A, Qc], [np.zeros((2, 2)), A.T]]) * dt)
    Phi_ref = M[2:, 2:].T
    Q_ref = Phi_ref @ M[:2, 2:]
    assert np.allclose(Phi, Phi_ref, rtol=1e-9, atol=1e-15)
    # the O(dt^3) e-part of Q: closed form, to O(|T_e - t_f| / T_e) within 0.1 % of t_f = T_e
    assert np.allclose(Q, Q_ref, rtol=1e-5, atol=1e-15)
    assert np.allclose(Phi @ C @ Phi.T + g * Q, C, rtol=1e-7, atol=1e-12)  # var(e) = 1


def test_gnss_error_states_measurements() -> None:
    """``gnss_error_states``: position ``z = r + e + w`` (``H`` = I on POS and GNE, ``R`` the white
    part), velocity ``z = v + (e_gm - e) / t_f + w_D`` (-1/t_f on GNE, +1/t_f on GNM), the
    22-column models padded with zeros; the correlated part of the fix's sigma goes to the
    states."""
    eng = QekfEngine(QekfConfig(gnss_error_states=True, gnss_white_fraction=0.2, smoothing=False))
    assert eng.n == N_STATES_GNSS == 28 and eng.x.size == 28 and eng.P.shape == (28, 28)
    R = np.diag([1.5**2, 1.5**2, 3.0**2])
    eng._set_gnss_noise(R, 45.0)
    sig = np.array([1.5, 1.5, 3.0])
    assert np.allclose(eng._var_e, 0.96 * sig**2)
    te = np.array([150.0, 150.0, 200.0])  # horizontal and vertical correlation times
    assert np.allclose(eng._var_gm, 0.96 * sig**2 * (te + 2.0) / te)
    z, H, Rm = eng._position_measurement(np.array([1.0, 2.0, 3.0]), R)
    assert H.shape == (3, 28) and np.allclose(z, [1.0, 2.0, 3.0])
    assert np.allclose(H[:, POS], np.eye(3)) and np.allclose(H[:, GNE], np.eye(3))
    assert np.count_nonzero(H) == 6
    assert np.allclose(Rm, np.diag((0.2 * sig) ** 2))
    x = np.arange(28.0)
    assert np.allclose(H @ x, x[POS] + x[GNE])
    for m in (3, 2):  # receiver NED velocity, or speed and course
        _z, H, Rm = eng._velocity_measurement(np.ones(m), 0.1)
        assert H.shape == (m, 28) and np.allclose(Rm, 0.01 * np.eye(m))
        assert np.allclose(H[:, VEL.start : VEL.start + m], np.eye(m))
        assert np.allclose(H[:, GNE.start : GNE.start + m], -np.eye(m) / 2.0)
        assert np.allclose(H[:, GNM.start : GNM.start + m], np.eye(m) / 2.0)
        assert np.count_nonzero(H) == 3 * m
        assert np.allclose(H @ x, x[VEL][:m] + (x[GNM][:m] - x[GNE][:m]) / 2.0)
    # no receiver filter: the velocity error is the white Doppler noise alone
    eng0 = QekfEngine(QekfConfig(gnss_error_states=True, gnss_receiver_filter_s=0.0, smoothing=False))
    _z, H0, _R = eng0._velocity_measurement(np.ones(3), 0.1)
    assert np.count_nonzero(H0) == 3
    # the white floor: gnss_white_floor_m, or the output rounding of the fixes
    eng0.resolution.update(45.0 + 12.3456 / 60.0, 7.0 + 1.2345 / 60.0, 290.1)  # NMEA, 4 decimals
    eng0._set_gnss_noise(R, 45.0)
    q = 1852.0e-4 / np.sqrt(12.0)
    assert np.allclose(
        eng0._var_white, [q**2, (q * np.cos(np.radians(45.0))) ** 2, (0.1 / np.sqrt(12.0)) ** 2]
    )


@pytest.mark.parametrize("gnss_error_states", [False, True], ids=["paper-22", "gnss-28"])
def test_gnss_error_states_run(tmp_path: Path, gnss_error_states: bool) -> None:
    """A short run: 22 states (the paper's filter, unchanged) without the option, 28 with it,
    through the prediction, the updates and the smoothing records; the RTS smoother runs on
    either. With the option the covariance at the end of the initialisation is positive
    semi-definite and ties the position to the GNSS error (the origin is the mean fix)."""
    r, log = simulate(tmp_path, 3, MC_OVERRIDES_RECEIVER)
    eng = QekfEngine(car_config(r, init_duration_s=10.0, smoothing=True, gnss_error_states=gnss_error_states))
    n = N_STATES_GNSS if gnss_error_states else N_STATES
    rows = []
    checked = False
    for s in iter_samples(log):
        if (o := eng.step(s)) is not None:
            rows.append(o)
        if eng.initialised and not checked:
            checked = True
            assert eng.x.shape == (n,) and eng.P.shape == (n, n)
            assert np.linalg.eigvalsh(eng.P).min() > -1e-12
            if gnss_error_states:
                assert np.all(np.diag(eng.P[POS, GNE]) < 0.0)
                assert np.all(np.diag(eng.P[POS, GNM]) < 0.0)
                # r + e known better than either: the first fixes carry little news on it
                Hs = np.zeros((3, n))
                Hs[:, POS] = Hs[:, GNE] = np.eye(3)
                assert np.all(np.diag(Hs @ eng.P @ Hs.T) < np.diag(eng.P[POS, POS]))
    fwd = pd.DataFrame(rows)
    assert eng.x.shape == (n,) and eng.P.shape == (n, n)
    log_s = eng.smoothing_log
    assert log_s is not None and len(log_s) > 100
    assert log_s.Phi[-1].shape == (n, n) and log_s.P_post[-1].shape == (n, n)
    assert eng.summary()["gnss_resolution"]["fixes"] == len(log.gnss)
    sm = smooth_output(eng, fwd)
    err = track_errors(fwd.dropna(subset=["lat"]), r.truth)
    err_s = track_errors(sm.dropna(subset=["lat"]), r.truth)
    assert np.sqrt(np.mean(err.h_err**2)) < 5.0 and np.sqrt(np.mean(err_s.h_err**2)) < 5.0


# ----------------------------------------------------------------------------- no magnetometer


@pytest.mark.parametrize(
    "attitude",
    [(0.7, 0.2, -0.1), (2.5, np.radians(85.0), 0.3), (-1.0, np.radians(-89.0), -2.0), (3.1, 0.0, np.pi)],
    ids=["generic", "pitch+85", "pitch-89", "upside-down"],
)
@pytest.mark.parametrize("qscale", [1.0, 1.02], ids=["unit", "non-unit"])
def test_nhc_jacobian_matches_finite_differences(attitude: tuple[float, float, float], qscale: float) -> None:
    """``H`` of the non-holonomic observation against central differences of ``h(x)``."""
    x = _state(*attitude)
    x[Q_NB] *= qscale
    mount = -1.3
    _z, H, R, hx = nhc_measurement(x, mount, 0.5)
    assert R[0, 0] == pytest.approx(0.25)
    Hn = _num_jac(lambda z: nhc_measurement(z, mount, 0.5)[3], x, 1e-7)
    scale = max(1.0, float(np.abs(Hn).max()))
    assert np.abs(H - Hn).max() < 1e-6 * scale
    # closed form: the lateral velocity of a vehicle whose heading is sensor yaw - mount
    qw, qx, qy, qz = x[Q_NB]
    psi_v = np.arctan2(2 * (qx * qy + qw * qz), qw * qw + qx * qx - qy * qy - qz * qz) - mount
    assert hx[0] == pytest.approx(-np.sin(psi_v) * x[4] + np.cos(psi_v) * x[5])


def test_heading_reset_rotates_attitude_covariance() -> None:
    """Fallback heading reset: yaw set, roll and pitch kept, the tilt covariance and the
    tilt / accelerometer-bias correlation rotated with the yaw (``P' = T P T^T``), the yaw
    decorrelated with the requested variance."""
    from iotnav.engines.qekf import BA, quat_right
    from iotnav.techniques.triad import quat_to_dcm

    eng = QekfEngine(QekfConfig(smoothing=False))
    x = _state(0.4, 0.05, -0.08)
    rng = np.random.default_rng(0)
    A = rng.normal(size=(N_STATES, N_STATES)) * 1e-2
    eng.x, eng.P = x.copy(), A @ A.T + np.eye(N_STATES) * 1e-4

    def theta_cov(xx: np.ndarray, P: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        Xi = quat_right(xx[Q_NB])[:, 1:]  # dq = Xi dtheta / 2, Xi^T Xi = I
        return 4.0 * Xi.T @ P[Q_NB, Q_NB] @ Xi, 2.0 * Xi.T @ P[Q_NB, BA]

    Ptt0, Ptb0 = theta_cov(eng.x, eng.P)
    eng._set_heading(0.0, -2.0, 0.05)
    C0, C1 = quat_to_dcm(x[Q_NB]), quat_to_dcm(eng.x[Q_NB])
    assert np.arctan2(C1[1, 0], C1[0, 0]) == pytest.approx(-2.0)
    assert C1[2] == pytest.approx(C0[2], abs=1e-12)  # the down axis in b: same tilt
    d = -2.0 - 0.4
    Rz = np.array([[np.cos(d), -np.sin(d)], [np.sin(d), np.cos(d)]])
    Ptt1, Ptb1 = theta_cov(eng.x, eng.P)
    assert np.allclose(Ptt1[:2, :2], Rz @ Ptt0[:2, :2] @ Rz.T, atol=1e-12)
    assert np.allclose(Ptb1[:2], Rz @ Ptb0[:2], atol=1e-12)
    assert Ptt1[2, 2] == pytest.approx(0.05**2)
    assert np.allclose(Ptt1[2, :2], 0.0, atol=1e-12) and np.allclose(Ptb1[2], 0.0, atol=1e-12)
    assert np.allclose(eng.P[POS, POS], (A @ A.T + np.eye(N_STATES) * 1e-4)[POS, POS])  # not rotated
    assert eng.heading_ok


def test_car_tunnel_without_magnetometer_stays_bounded(tmp_path: Path) -> None:
    """No magnetometer: mount from block 5, heading reset from the course, NHC yaw observation.

    car-tunnel shortened to 330 s (outages 150-190 s and 255-315 s at 100 km/h, after a 10 s
    stop and 35 s of driving), default configuration, NMEA read back through ingest.
    Bound from the physics, not the result: the drift at the end of an outage is about
    ``sqrt(dpsi^2 + (b T / 2 v)^2)`` of the distance; the heading is tied to course + mount,
    whose accepted sigma is at most 2 deg (``max_std_rad``), so 3 sigma is 6 deg = 10 % of the
    distance, and a residual accelerometer bias of 0.05 m/s^2 adds 0.05 x 60 / (2 x 28) = 5 %:
    median below 10 %, worst below 15 %. A yaw left free drifts like holding the last fix
    (96 % on the full scenario); the engine did 112 / 69 % here before the fallback.
    Observed (seed 0): 0.7 / 0.6 %, mount -89.8 deg (truth -90), vehicle yaw RMS 0.23 deg
    after the heading reset at 46 s.
    """
    r = sim.build("car-tunnel", seed=0, overrides={"duration_s": 330.0})
    sim.write(r, tmp_path)
    log = ingest([tmp_path])
    eng = QekfEngine(QekfConfig(smoothing=False))
    df = pd.DataFrame([o for s in iter_samples(log) if (o := eng.step(s)) is not None])
    assert eng.fallback
    init = next(e for e in eng.events if e["type"] == "init_done")
    # ended by the motion (start at 10 s), not after 30 s of driving; averages over the stop only
    assert init["t"] < 20.0 and init["imu_samples"] <= 1010
    head = next(e for e in eng.events if e["type"] == "heading_initialised")
    assert head["t"] < 100.0
    assert abs(eng.mount_yaw_rad - r.config.mount_yaw_rad) < np.radians(2.0)
    err = track_errors(df.dropna(subset=["lat"]), r.truth)
    outs = [o for o in r.config.gnss.outages_s if o[1] <= 330.0]
    drift = [d["drift_pct"] for d in outage_drift(err, r.truth, outs)]
    assert len(drift) == 2
    assert float(np.median(drift)) < 10.0 and max(drift) < 15.0, drift
    d = df[df.t > head["t"]]
    ref = np.interp(d.t, r.truth.t, np.unwrap(r.truth.yaw))
    e = np.angle(np.exp(1j * (d.yaw.to_numpy() - ref)))
    assert np.degrees(np.sqrt(np.mean(e**2))) < 6.0  # vehicle yaw, 3 x the mount sigma bound


def test_real_drive_no_magnetometer_finds_the_mount(datasets: Path) -> None:
    """rtklibexplorer drive_0708 (ICM-45686, no magnetometer, roof-mounted with its x axis about
    backwards) fed as the outage study feeds it (1 Hz GNSS, metres off): the fallback's aligner
    starts from the initialisation's gravity reference, finds the author's mount yaw
    (-174.61 deg, the yaw of the dataset README's C_vb) itself and resets the heading."""
    from iotnav.cli.outages import load_dataset
    from iotnav.engines import run_batch
    from iotnav.eval import outages as O

    log, prof = load_dataset(datasets / "rtklibexplorer_gnss_imu" / "drive_0708")
    truth = O.rtk_truth(log.gnss)
    t0 = float(truth.t.iloc[0])
    eng = QekfEngine(QekfConfig())
    run_batch(eng, O.degraded_feed(log, truth, prof)[0])
    assert eng.fallback and eng.heading_ok
    est = [e for e in eng.events if e["type"] == "mount_estimate"]
    # the aligner works from the first minute of driving, not from the first stop (205 s)
    assert est[0]["t"] - t0 < 100.0
    accepted = [e for e in est if e["accepted"]]
    assert accepted
    author = -174.61
    for e in accepted:
        assert abs((np.degrees(e["mount_yaw_rad"]) - author + 180.0) % 360.0 - 180.0) < 2.0
    assert abs((np.degrees(eng.mount_yaw_rad) - author + 180.0) % 360.0 - 180.0) < 1.0
    # provisional estimates before the acceptance (about 400 s): the heading is reset from the
    # first minute of driving on, within 8 deg of the mount
    heading = next(e for e in eng.events if e["type"] == "heading_initialised")
    assert heading["t"] - t0 < 100.0 and heading["t"] < accepted[0]["t"] - 200.0
    assert abs((np.degrees(heading["mount_yaw_rad"]) - author + 180.0) % 360.0 - 180.0) < 8.0
    # no velocity lock-out: at most max_rejections gated GNSS velocities in a row (before the
    # velocity was forced like the position, 11 in a row at 295-305 s, east 1.9 m/s off)
    run, longest = 0, 0
    for e in eng.events:
        if e["type"] == "gnss_vel_rejected":
            run += 1
            longest = max(longest, run)
        elif e["type"] == "gnss_vel_forced":
            run = 0
    assert longest <= eng.config.max_rejections, longest


def test_real_drive_reacquires_position_and_velocity_after_an_outage(datasets: Path) -> None:
    """A 30 s outage 279 s into drive_0708 (459 m driven): the dead-reckoned velocity is then
    15.6 m/s off. The first fix after it widens the position *and* the velocity covariance by
    their innovations; with the position alone the velocity updates were rejected (NIS 135),
    the track drifted off again, 17-51 m off 1-3 s after the outage, until a second forced fix
    6 s later (now at most 8.8 m over the 10 s after the outage, 1.0-2.0 m at 1-3 s)."""
    from iotnav.cli.outages import load_dataset
    from iotnav.engines import run_batch
    from iotnav.eval import outages as O

    log, prof = load_dataset(datasets / "rtklibexplorer_gnss_imu" / "drive_0708")
    truth = O.rtk_truth(log.gnss).sort_values("t").reset_index(drop=True)
    fed = O.degraded_feed(log, truth, prof)[0]
    start = float(truth.t.iloc[0]) + 279.0
    eng = QekfEngine(QekfConfig())
    df = run_batch(eng, Log(gnss=O.mask_windows(fed.gnss, [(start, 30.0)]), imu=fed.imu))
    err = track_errors(df.dropna(subset=["lat"]), truth[["t", "lat", "lon", "height"]])
    after = (err.t > start + 30.5) & (err.t < start + 40.0)
    assert after.sum() > 500 and err.h_err[after].max() < 12.0, err.h_err[after].max()
    forced = [e["type"] for e in eng.events if abs(e["t"] - start - 30.0) < 1.5 and "forced" in e["type"]]
    assert forced == ["gnss_pos_forced", "gnss_vel_forced"]


def test_fixes_without_height(tmp_path: Path) -> None:
    """2D fixes (no height): during the initialisation they cannot join the mean fix that is the
    origin and are rejected with their reason; afterwards they update the horizontal only, at
    the filter's own height (before, every such fix was rejected as invalid). car-magnetometer
    90 s, the first 10 fixes and 60-75 s 2D: horizontal within 0.3 m of the run with heights
    (observed 0.29 m), height within 10.5 m while only the IMU and the GNSS vertical velocity
    carry it."""
    r, log = simulate(tmp_path, 0, {"duration_s": 90.0})
    g = log.gnss.copy()
    valid = g.index[g["valid"].to_numpy(bool)]
    g.loc[valid[:10], "height_m"] = math.nan
    two_d = (g["t"] > 60.0) & (g["t"] < 75.0)
    g.loc[two_d, "height_m"] = math.nan
    out = {}
    for name, gnss in (("3d", log.gnss), ("2d", g)):
        eng = QekfEngine(car_config(r))
        out[name] = (run_batch(eng, Log(gnss=gnss, imu=log.imu, mag=log.mag)), eng.events)
    (a, _), (b, ev) = out["3d"], out["2d"]
    reasons = [e.get("reason") for e in ev if e["type"] == "fix_rejected"]
    assert reasons.count("no_height_initialisation") == 10 and "invalid" not in reasons
    pos2d = [e for e in ev if e["type"] == "gnss_pos_rejected" and 60.0 < e["t"] < 75.0]
    assert not pos2d
    late = a["t"].to_numpy() > 45.0
    dh = np.hypot(a["north"] - b["north"], a["east"] - b["east"]).to_numpy()[late]
    assert float(np.nanmax(dh)) < 0.5
    assert float(np.nanmax(np.abs(a["height"] - b["height"]).to_numpy()[late])) < 15.0


def test_consistent_form_from_toml(tmp_path: Path) -> None:
    """``form = "consistent"`` in ``[qekf]`` starts from :meth:`QekfConfig.consistent`, other
    keys replace its fields; the paper's form stays the default; bad forms and keys are named."""
    from iotnav.engines.registry import make_engine

    path = tmp_path / "q.toml"
    path.write_text('[qekf]\nform = "consistent"\nacc_misalignment = 0.01\n')
    cfg = QekfConfig.from_toml(path)
    assert cfg == QekfConfig.consistent(acc_misalignment=0.01)
    assert cfg.mag_observation == "direction" and cfg.gnss_error_states
    assert cfg.acc_noise_mps2_rthz == pytest.approx(400e-6 * 9.80665)
    eng = make_engine("qekf", path, integrity=False)  # the engine itself, not the guard
    assert isinstance(eng, QekfEngine) and eng.config == cfg and eng.n == N_STATES_GNSS
    path.write_text("[qekf]\nuse_mag = false\n")
    assert QekfConfig.from_toml(path) == QekfConfig(use_mag=False)
    assert QekfConfig().mag_observation == "triad" and QekfConfig().gyro_misalignment == 0.0
    path.write_text('[qekf]\nform = "best"\n')
    with pytest.raises(ValueError, match="form must be"):
        QekfConfig.from_toml(path)
    path.write_text('[qekf]\nform = "consistent"\nmag_observaton = "direction"\n')
    with pytest.raises(ValueError, match="mag_observaton"):
        QekfConfig.from_toml(path)


def test_gnss_error_follows_the_reported_accuracy() -> None:
    """``_scale_gnss_error``: a reported sigma 3 times the level scales ``e``, ``e_gm``, their
    covariance rows and the smoothing transition by 3 (``x' = T x``, ``P' = T P T^T``,
    ``Phi' = T Phi``); a change within 4 rounding steps of the figures is low-passed (1 s of
    5 s); a change of the kind of figures (hAcc against DOPs) scales nothing."""
    eng = QekfEngine(QekfConfig(gnss_error_states=True, smoothing=True))
    rng = np.random.default_rng(3)
    A = rng.normal(size=(eng.n, eng.n))
    eng.x = rng.normal(size=eng.n)
    eng.P = A @ A.T + eng.n * np.eye(eng.n)
    eng._Phi = np.eye(eng.n) + 0.01 * rng.normal(size=(eng.n, eng.n))
    x0, P0, Phi0 = eng.x.copy(), eng.P.copy(), eng._Phi.copy()

    def fix(
        t: float, sigma: list[float], kind: tuple[bool, bool] = (False, False), steps: float = 0.0
    ) -> None:
        eng.t_x = t
        eng._var_e, eng._noise_kind = np.array(sigma) ** 2, kind
        eng._scale_gnss_error((steps, steps, steps))

    fix(0.0, [1.0, 1.0, 2.0])  # the first fix: the level
    fix(1.0, [1.0, 1.0, 2.0])
    assert np.array_equal(eng.x, x0) and np.array_equal(eng.P, P0) and np.array_equal(eng._Phi, Phi0)
    fix(2.0, [3.0, 3.0, 2.0])
    d = np.ones(eng.n)
    d[GNE] = d[GNM] = [3.0, 3.0, 1.0]
    assert np.allclose(eng.x, d * x0)
    assert np.allclose(eng.P, P0 * np.outer(d, d))
    assert np.allclose(eng._Phi, d[:, None] * Phi0)
    x1, P1 = eng.x.copy(), eng.P.copy()
    fix(3.0, [3.03, 3.0, 2.0], steps=0.01)  # north one DOP step up: 1 s of the 5 s low-pass
    d = np.ones(eng.n)
    d[GNE.start] = d[GNM.start] = 1.01 ** (1.0 - math.exp(-1.0 / 5.0))
    assert np.allclose(eng.x, d * x1) and np.allclose(eng.P, P1 * np.outer(d, d))
    x2, P2 = eng.x.copy(), eng.P.copy()
    fix(4.0, [1.0, 1.0, 4.0], (True, True))  # hAcc / vAcc now: a new level, nothing scaled
    assert np.array_equal(eng.x, x2) and np.array_equal(eng.P, P2)


@pytest.mark.slow
def test_consistent_form_without_gnss_velocity_recovers_after_the_gap(tmp_path: Path) -> None:
    """A receiver that gives positions only (NMEA GGA), the consistent form, car-magnetometer
    seed 7: after the 4 s gap the simulated receiver's error is three times larger (hAcc 1.6 ->
    4.8 m) and the filter, whose white ``R`` is the fixes' rounding, rejected every fix for a
    minute (its forced updates widened the position only, the velocity error stayed): RMS
    8.8 m, 13.7 m without the error states' scaling too. Now the correlated error follows
    the jump of the reported accuracy and a forced update widens the velocity by the
    disagreement over the time since the last accepted fix: RMS 2.02 m (scaling off: 2.32 m),
    largest error 7.8 m just after the gap, 5 fixes rejected. Seeds 0-8: RMS 0.9-2.0 m."""
    r, log = simulate(tmp_path, seed=7)
    eng = QekfEngine(car_config(r, True, smoothing=False, use_gnss_velocity=False))
    fwd = pd.DataFrame([o for s in iter_samples(log) if (o := eng.step(s)) is not None])
    err = track_errors(fwd.dropna(subset=["lat"]), r.truth)
    assert float(np.sqrt(np.mean(err.h_err**2))) < 3.0
    after = err.t > r.config.gnss.outages_s[0][1] + 30.0
    assert float(err.h_err[after].max()) < 5.0
    rejected = [e["t"] for e in eng.events if e["type"] == "gnss_pos_rejected"]
    assert len(rejected) < 15, rejected


def test_vertical_gnss_correlation_time() -> None:
    """``gnss_corr_time_v_s`` sets the down axis of the GNSS error states, ``gnss_corr_time_s``
    north and east: the transition ``exp(-dt / T_e)`` of ``GNM``, its noise
    ``(1 - exp(-2 dt / T_e)) var(e_gm)`` and ``var(e_gm) = var(e) (T_e + t_f) / T_e``."""
    eng = QekfEngine(QekfConfig(gnss_error_states=True, gnss_corr_time_s=150.0, gnss_corr_time_v_s=200.0))
    eng._set_gnss_noise(np.diag([1.0, 1.0, 4.0]), 45.0)
    te = np.array([150.0, 150.0, 200.0])
    var_gm = np.array([1.0, 1.0, 4.0]) * (te + 2.0) / te
    cov = eng._gnss_error_cov(slice(0, 3))
    np.testing.assert_allclose(np.diag(cov), np.r_[1.0, 1.0, 4.0, var_gm])
    # one prediction step of an initialised filter (level, at rest)
    eng.initialised = eng.have_imu = True
    eng.x[Q_NB] = [1.0, 0.0, 0.0, 0.0]
    eng.x[16:22] = 1.0  # gyro and accelerometer scale factors (SG, SA)
    eng.acc = -eng.g_n.copy()
    eng.gyro = np.zeros(3)
    eng.t_x = 0.0
    eng._predict_to(0.5)
    gnm = np.arange(GNM.start, GNM.stop)
    np.testing.assert_allclose(eng._F_full[gnm, gnm], np.exp(-0.5 / te), rtol=1e-12)
    np.testing.assert_allclose(eng._Q_full[gnm, gnm], -np.expm1(-1.0 / te) * var_gm, rtol=1e-9)
