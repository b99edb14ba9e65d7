"""Multilateration: Jacobian, CRB closed form, geometry flags, robustness, efficiency."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.stats import chi2

from iotnav.nodes.multilateration import Status, crb, predict_rssi, solve_position
from iotnav.nodes.ranging import radio, rssi_from_distance

MODEL = radio("lora-sf7")  # P0 -17.2 dBm, n 2.7, sigma 6 dB
KAPPA = 10.0 * MODEL.n / math.log(10.0)


def _ring(n: int, radius: float, centre: np.ndarray, down: float = 0.0) -> np.ndarray:
    ang = 2.0 * math.pi * np.arange(n) / n
    return np.column_stack(
        [centre[0] + radius * np.cos(ang), centre[1] + radius * np.sin(ang), np.full(n, down)]
    )


def _fisher_fd(p: np.ndarray, A: np.ndarray, sigma: float, sigma_a: float, down: float) -> np.ndarray:
    """Independent Fisher information: finite-difference gradients of the distance model."""

    def h(q: np.ndarray) -> np.ndarray:
        d = np.sqrt((q[0] - A[:, 0]) ** 2 + (q[1] - A[:, 1]) ** 2 + (down - A[:, 2]) ** 2)
        return MODEL.p0_dbm - 10.0 * MODEL.n * np.log10(d)

    eps = 1e-4
    G = np.column_stack([(h(p + eps * e) - h(p - eps * e)) / (2 * eps) for e in np.eye(2)])
    s2 = sigma**2 + sigma_a**2 * np.sum(G**2, axis=1)  # isotropic anchor error: g^T (sa^2 I) g
    return G.T @ (G / s2[:, None])


def test_jacobian_matches_finite_differences() -> None:
    rng = np.random.default_rng(2)
    A = np.column_stack([rng.uniform(-300, 300, (20, 2)), np.full(20, -1.5)])
    for p in (np.array([10.0, -20.0]), np.array([0.5, 0.3]), A[0, :2] + 0.2):
        _, G, _ = predict_rssi(p, A, MODEL)
        eps = 1e-6
        for i in range(2):
            dp = np.zeros(2)
            dp[i] = eps
            hp, _, _ = predict_rssi(p + dp, A, MODEL)
            hm, _, _ = predict_rssi(p - dp, A, MODEL)
            np.testing.assert_allclose(G[:, i], (hp - hm) / (2 * eps), rtol=1e-5, atol=1e-7)


@pytest.mark.parametrize("sigma_a", [0.0, 3.0, 20.0])
def test_crb_closed_form_on_a_ring(sigma_a: float) -> None:
    # N anchors evenly on a circle of radius R around the node, same height:
    # |g| = kappa / R, sum u u^T = N/2 I, so tr CRB = 4 R^2 s^2 / (N kappa^2),
    # s^2 = sigma^2 + kappa^2 sigma_a^2 / R^2.
    N, R = 12, 150.0
    A = _ring(N, R, np.zeros(2))
    s2 = MODEL.shadowing_db**2 + KAPPA**2 * sigma_a**2 / R**2
    expected = 4.0 * R**2 * s2 / (N * KAPPA**2)
    C = crb(np.zeros(2), A, MODEL, np.full(N, sigma_a))
    assert np.trace(C) == pytest.approx(expected, rel=1e-9)
    np.testing.assert_allclose(C, expected / 2 * np.eye(2), atol=1e-9 * expected)


def test_noise_free_reports_give_the_truth() -> None:
    rng = np.random.default_rng(4)
    A = np.column_stack([rng.uniform(-400, 400, (8, 2)), np.full(8, -1.5)])
    p = np.array([37.0, -120.0])
    d = np.sqrt(np.sum((A[:, :2] - p) ** 2, axis=1) + 1.5**2)
    for method in ("wls", "huber", "ransac"):
        est = solve_position(A, rssi_from_distance(d, MODEL), MODEL, method=method)
        assert est.status is Status.OK
        np.testing.assert_allclose(est.p_ne, p, atol=1e-2)


def test_geometry_flags() -> None:
    assert solve_position(np.zeros((0, 3)), np.zeros(0), MODEL).status is Status.NO_DATA
    two = solve_position([[0, 0, 0], [100, 0, 0]], [-70.0, -75.0], MODEL)
    assert two.status is Status.UNDETERMINED
    assert np.all(np.isnan(two.P))
    same_place = solve_position(np.zeros((5, 3)), np.full(5, -70.0), MODEL)
    assert same_place.status is Status.UNDETERMINED
    # a vehicle driving a straight road: the node and its reflection across the road fit alike
    A = np.column_stack([np.linspace(-500, 500, 40), np.zeros(40), np.zeros(40)])
    p = np.array([50.0, 120.0])
    d = np.linalg.norm(A[:, :2] - p, axis=1)
    est = solve_position(A, rssi_from_distance(d, MODEL), MODEL)
    assert est.status is Status.AMBIGUOUS
    found = {tuple(np.round(est.p_ne)), tuple(np.round(est.mirror_ne))}
    assert found == {(50.0, 120.0), (50.0, -120.0)}
    with pytest.raises(ValueError, match="finite"):
        solve_position(A, np.where(np.arange(40) == 3, np.nan, -80.0), MODEL)


def test_robust_solvers_resist_nlos() -> None:
    rng = np.random.default_rng(8)
    p = np.array([80.0, 40.0])
    err = {"wls": [], "huber": [], "ransac": []}
    for _ in range(12):
        A = np.column_stack([rng.uniform(-300, 300, (40, 2)), np.zeros(40)])
        d = np.linalg.norm(A[:, :2] - p, axis=1)
        r = rssi_from_distance(d, MODEL) + rng.normal(0, 4.0, 40)
        r -= np.where(rng.random(40) < 0.25, 25.0, 0.0)  # NLOS: 25 % of reports 25 dB weaker
        m = MODEL.with_shadowing(4.0)
        for k in err:
            err[k].append(np.linalg.norm(solve_position(A, r, m, method=k).p_ne - p))
    med = {k: float(np.median(v)) for k, v in err.items()}
    assert med["huber"] < 0.6 * med["wls"]
    assert med["ransac"] < 0.6 * med["wls"]


def test_one_moving_anchor_is_efficient_and_consistent() -> None:
    # one vehicle circling the node (radius 300 m, 10 m/s, beacon every 10 s, 60 beacons),
    # 6 dB shadowing, 3 m anchor error: RMSE within 20 % of sqrt(tr CRB), NEES consistent.
    rng = np.random.default_rng(21)
    p = np.array([60.0, -40.0])
    ang = np.arange(60) * 10.0 * 10.0 / 300.0
    A = np.column_stack([300 * np.cos(ang), 300 * np.sin(ang), np.full(60, -1.5)])
    bound = math.sqrt(np.trace(np.linalg.inv(_fisher_fd(p, A, 6.0, 3.0, 0.0))))
    runs = 150
    e2, nees = [], []
    d = np.sqrt(np.sum((A[:, :2] - p) ** 2, axis=1) + 1.5**2)
    for _ in range(runs):
        Ar = A.copy()
        Ar[:, :2] += rng.normal(0.0, 3.0, (60, 2))
        r = rssi_from_distance(d, MODEL) + rng.normal(0.0, 6.0, 60)
        est = solve_position(Ar, r, MODEL, np.full(60, 3.0), node_down_m=0.0)
        e = est.p_ne - p
        e2.append(e @ e)
        nees.append(e @ np.linalg.solve(est.P, e))
    rmse = math.sqrt(np.mean(e2))
    assert rmse == pytest.approx(bound, rel=0.2)
    lo, hi = chi2.ppf([0.025, 0.975], 2 * runs) / runs
    assert lo < np.mean(nees) < hi
