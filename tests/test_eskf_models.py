"""Unit tests of the ``eskf`` models: Jacobians against finite differences (STYLE §10), config I/O."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from iotnav.engines import eskf_models as M
from iotnav.engines.eskf import EskfConfig, noise_vector
from iotnav.geo import euler_to_dcm

N = M.N_FULL
EPS = 1e-6


def _nominal(roll: float, pitch: float, yaw: float) -> M.Nominal:
    rng = np.random.default_rng(7)
    return M.Nominal(
        C_nb=euler_to_dcm(roll, pitch, yaw),
        v_n=np.array([12.0, -5.0, 0.4]),
        p_n=np.array([100.0, -40.0, 3.0]),
        b_g=rng.normal(0, 0.01, 3),
        b_a=rng.normal(0, 0.1, 3),
        s_g=rng.normal(0, 0.01, 3),
        s_a=rng.normal(0, 0.01, 3),
        C_vb=euler_to_dcm(0.03, -0.02, -1.5),
        e_n=np.array([0.5, -0.3, 1.0]),
        e_gm=np.array([0.7, -0.1, 1.2]),
    )


def _fd(h, nom: M.Nominal) -> np.ndarray:  # type: ignore[no-untyped-def]
    h0 = np.atleast_1d(h(nom))
    J = np.zeros((h0.size, N))
    for j in range(N):
        dx = np.zeros(N)
        dx[j] = EPS
        pert = nom.copy()
        M.inject(pert, dx)
        d = np.atleast_1d(h(pert)) - h0
        J[:, j] = np.remainder(d + np.pi, 2 * np.pi) - np.pi if h0.size == 1 else d
        J[:, j] /= EPS
    return J


ATTITUDES = [(0.1, -0.2, 0.7), (0.3, np.radians(89.9), 2.0), (-0.2, -np.radians(89.95), -2.5)]
LEVER = np.array([0.3, -0.2, -0.8])
W_RAW = np.array([0.05, -0.1, 0.3])
F_RAW = np.array([0.4, -0.3, -9.7])


@pytest.mark.parametrize("att", ATTITUDES)
def test_measurement_jacobians_match_finite_differences(att: tuple[float, float, float]) -> None:
    nom = _nominal(*att)
    m_b = np.array([20.0, -5.0, 40.0])
    cases = [
        (lambda s: M.h_gnss_position(s, LEVER, N)[0], M.h_gnss_position(nom, LEVER, N)[1]),
        (lambda s: M.h_gnss_velocity(s, W_RAW, LEVER, N)[0], M.h_gnss_velocity(nom, W_RAW, LEVER, N)[1]),
        (  # smoothing receiver: velocity carries (e_gm - e_n) / t_f
            lambda s: M.h_gnss_velocity(s, W_RAW, LEVER, N, 0.5)[0],
            M.h_gnss_velocity(nom, W_RAW, LEVER, N, 0.5)[1],
        ),
        (lambda s: M.h_nhc(s, N)[0], M.h_nhc(nom, N)[1]),
        (lambda s: M.h_zaru(s, W_RAW, N)[0], M.h_zaru(nom, W_RAW, N)[1]),
        (lambda s: M.h_gravity(s, F_RAW, N)[0], M.h_gravity(nom, F_RAW, N)[1]),
    ]
    mag = M.h_mag_heading(nom, m_b, N)
    assert mag is not None
    cases.append((lambda s: M.h_mag_heading(s, m_b, N)[0], mag[1]))  # type: ignore[index]
    for h, H in cases:
        np.testing.assert_allclose(_fd(h, nom), H, atol=2e-5 * max(1.0, np.abs(H).max()))


@pytest.mark.parametrize("att", ATTITUDES)
def test_transition_matches_propagated_perturbation(att: tuple[float, float, float]) -> None:
    """``Phi`` against the difference of two strapdown propagations (true vs estimate)."""
    est = _nominal(*att)
    f_raw = np.array([0.8, -0.4, -9.6])
    noise = np.zeros(12)
    noise[4] = noise[5] = 1 / 100.0
    noise[10] = 1 / 300.0
    g = np.array([0.0, 0.0, 9.81])
    T = 0.01
    f = M.compensate(f_raw, est.b_a, est.s_a)
    w = M.compensate(W_RAW, est.b_g, est.s_g)
    Phi, _ = M.error_transition(est.C_nb, f, w, T, N, noise)
    base = est.copy()
    M.propagate_nominal(base.C_nb, base.v_n, base.p_n, f, w, T, g, np.zeros(M.ACC_SIZE))
    rng = np.random.default_rng(3)
    dx0 = rng.normal(0.0, 1.0, N) * 1e-5
    true = est.copy()
    M.inject(true, dx0)
    ft = M.compensate(f_raw, true.b_a, true.s_a)
    wt = M.compensate(W_RAW, true.b_g, true.s_g)
    M.propagate_nominal(true.C_nb, true.v_n, true.p_n, ft, wt, T, g, np.zeros(M.ACC_SIZE))
    dx1 = M.difference(true, base, N)
    pred = Phi @ dx0
    # the Gauss-Markov decay of biases/GNSS error is not in the deterministic propagation
    for sl in (M.BG, M.BA, M.GNE):
        pred[sl] = dx0[sl]
    np.testing.assert_allclose(dx1, pred, atol=2e-8, rtol=2e-3)


def test_inject_difference_roundtrip() -> None:
    nom = _nominal(0.2, 1.2, -3.0)
    dx = np.random.default_rng(1).normal(0, 0.01, N)
    true = nom.copy()
    M.inject(true, dx)
    np.testing.assert_allclose(M.difference(true, nom, N), dx, atol=1e-12)


def test_config_toml_roundtrip_and_unknown_key(tmp_path: Path) -> None:
    p = tmp_path / "eskf.toml"
    p.write_text(
        "[eskf]\nuere_m = 3.5\nnhc = false\ngnss_lever_arm_b_m = [0.1, 0.0, -0.5]\n"
        "[eskf.static]\ntheta_a_mps2 = 0.2\n"
    )
    c = EskfConfig.from_toml(p)
    assert c.uere_m == 3.5 and c.nhc is False
    assert c.gnss_lever_arm_b_m == (0.1, 0.0, -0.5)
    assert c.static.theta_a_mps2 == 0.2
    assert EskfConfig.from_dict(c.to_dict()) == c
    p.write_text("[eskf]\nuere = 3\n")
    with pytest.raises(ValueError, match="uere"):
        EskfConfig.from_toml(p)


def test_level_covariance_matches_monte_carlo_levelling() -> None:
    """Levelling absorbs the accelerometer error: tilt/bias/scale joint covariance by sampling."""
    rng = np.random.default_rng(11)
    g = 9.8
    C_true = euler_to_dcm(0.2, -0.1, 0.0)
    f_true = C_true.T @ np.array([0.0, 0.0, -g])
    s_b, s_s = 0.15, 0.01
    samples = []
    for _ in range(4000):
        b = rng.normal(0.0, s_b, 3)
        sc = rng.normal(0.0, s_s, 3)
        f = (1.0 + sc) * f_true + b
        C_lev = euler_to_dcm(math.atan2(-f[1], -f[2]), math.atan2(f[0], math.hypot(f[1], f[2])), 0.0)
        dth = M.dcm_to_rotvec(C_true @ C_lev.T)
        # yaw of the levelled frame is arbitrary: compare tilt only
        samples.append(np.concatenate([dth[:2], b, sc]))
    S = np.cov(np.array(samples).T)
    P = M.level_covariance(C_true, f_true, g, np.full(3, s_b**2), np.full(3, s_s**2), 0.0)
    keep = [0, 1, 3, 4, 5, 6, 7, 8]
    Pk = P[np.ix_(keep, keep)]
    scale = np.sqrt(np.outer(np.diag(Pk), np.diag(Pk)))
    np.testing.assert_allclose(S / scale, Pk / scale, atol=0.08)


def test_heading_reset_transform_rotates_navigation_errors() -> None:
    est = _nominal(0.1, -0.2, 0.7)
    dx = np.random.default_rng(2).normal(0.0, 1e-3, N)
    true = est.copy()
    M.inject(true, dx)
    dpsi = 1.1
    R = euler_to_dcm(0.0, 0.0, dpsi)
    for nom in (est, true):
        nom.C_nb[:] = R @ nom.C_nb
        nom.p_n[:] = R @ nom.p_n
        nom.v_n[:] = R @ nom.v_n
        nom.e_n[:] = R @ nom.e_n
        nom.e_gm[:] = R @ nom.e_gm
    np.testing.assert_allclose(M.difference(true, est, N), M.heading_reset_transform(dpsi, N) @ dx, atol=1e-9)


def test_vertical_gnss_correlation_time() -> None:
    """``gnss_corr_time_v_s`` sets the down axis of the GNSS error model, the horizontal time the
    north and east axes (``noise[15]``; a 15-entry vector takes the horizontal one for all)."""
    noise = noise_vector(EskfConfig(gnss_corr_time_s=150.0, gnss_corr_time_v_s=200.0))
    assert noise.shape == (16,)
    T = 0.5
    C, f, w = np.eye(3), np.array([0.0, 0.0, -9.81]), np.zeros(3)
    Phi, _ = M.error_transition(C, f, w, T, N, noise)
    gm = np.diag(Phi)[M.GNM]
    np.testing.assert_allclose(gm, np.exp(-T / np.array([150.0, 150.0, 200.0])), rtol=1e-6)
    Phi15, _ = M.error_transition(C, f, w, T, N, noise[:15])
    np.testing.assert_allclose(np.diag(Phi15)[M.GNM], np.exp(-T / 150.0), rtol=1e-6)
    # stationary covariance of [e, e_gm]: var(e_gm) = var_e (T_e + t_f) / T_e per axis
    cov = M.stationary_gnss_error_cov(np.array([1.0, 1.0, 4.0]), np.array([150.0, 150.0, 200.0]), 2.0)
    np.testing.assert_allclose(np.diag(cov)[3:], [152.0 / 150.0, 152.0 / 150.0, 4.0 * 202.0 / 200.0])
    np.testing.assert_allclose(np.diag(cov[:3, 3:]), [1.0, 1.0, 4.0])
