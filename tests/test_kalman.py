"""Kalman kernels against independent textbook forms (layer a)."""

from __future__ import annotations

import numpy as np
import pytest

from iotnav import kalman


def _random_spd(rng: np.random.Generator, n: int) -> np.ndarray:
    a = rng.normal(size=(n, n))
    return a @ a.T + n * np.eye(n)


def test_scalar_update_by_hand() -> None:
    # Prior N(1, 4), measurement 3 with variance 1: gain 0.8, posterior 2.6 with variance 0.8.
    res = kalman.update(np.array([1.0]), np.array([[4.0]]), np.array([3.0]), np.eye(1), np.array([[1.0]]))
    assert res.x[0] == pytest.approx(2.6)
    assert res.P[0, 0] == pytest.approx(0.8)
    assert res.nis == pytest.approx(4.0 / 5.0)
    assert res.accepted


def test_update_matches_information_form() -> None:
    rng = np.random.default_rng(3)
    n, m = 6, 3
    x = rng.normal(size=n)
    P = _random_spd(rng, n)
    H = rng.normal(size=(m, n))
    R = _random_spd(rng, m)
    z = rng.normal(size=m)
    res = kalman.update(x, P, z, H, R)
    # Information form, computed with explicit inverses (independent route).
    Pi = np.linalg.inv(np.linalg.inv(P) + H.T @ np.linalg.inv(R) @ H)
    xi = Pi @ (np.linalg.inv(P) @ x + H.T @ np.linalg.inv(R) @ z)
    np.testing.assert_allclose(res.P, Pi, rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(res.x, xi, rtol=1e-9, atol=1e-12)
    S = H @ P @ H.T + R
    y = z - H @ x
    assert res.nis == pytest.approx(float(y @ np.linalg.solve(S, y)))
    np.testing.assert_array_equal(res.P, res.P.T)


def test_gate_rejects_and_leaves_state() -> None:
    x, P = np.zeros(2), np.eye(2)
    gate = kalman.gate_threshold(1, 0.99)
    assert gate == pytest.approx(6.634896601, rel=1e-6)  # chi2(1) 99 % quantile, tables
    res = kalman.update(x, P, np.array([10.0]), np.array([[1.0, 0.0]]), np.eye(1), gate=gate)
    assert not res.accepted
    assert res.test_ratio == pytest.approx(50.0 / gate)
    np.testing.assert_array_equal(res.x, x)
    np.testing.assert_array_equal(res.P, P)


def test_predict_with_control() -> None:
    F = np.array([[1.0, 0.1], [0.0, 1.0]])
    B = np.array([[0.005], [0.1]])
    x, P = kalman.predict(np.array([0.0, 1.0]), np.eye(2), F, 0.01 * np.eye(2), B, np.array([2.0]))
    np.testing.assert_allclose(x, [0.1 + 0.01, 1.2])
    np.testing.assert_allclose(P, F @ F.T + 0.01 * np.eye(2))


def test_rts_equals_batch_least_squares_on_random_walk() -> None:
    # For a scalar random walk observed with noise, the RTS smoother equals the batch
    # (all-data) Gaussian posterior mean, computed here by one dense linear solve.
    rng = np.random.default_rng(7)
    N, q, r, p0 = 40, 0.3, 1.0, 10.0
    z = np.cumsum(rng.normal(0, np.sqrt(q), N)) + rng.normal(0, np.sqrt(r), N)
    F = np.ones((N, 1, 1))
    xs, Ps, xps, Pps = np.zeros((N, 1)), np.zeros((N, 1, 1)), np.zeros((N, 1)), np.zeros((N, 1, 1))
    x, P = np.zeros(1), np.array([[p0]])
    for k in range(N):
        if k:
            x, P = kalman.predict(x, P, F[k], np.array([[q]]))
        xps[k], Pps[k] = x, P
        res = kalman.update(x, P, z[k : k + 1], np.eye(1), np.array([[r]]))
        x, P = res.x, res.P
        xs[k], Ps[k] = x, P
    x_s, P_s = kalman.rts_smooth(xs, Ps, xps, Pps, F)
    # Batch: minimise x0^2/p0 + sum (x_k - x_{k-1})^2/q + sum (z_k - x_k)^2/r
    D = np.eye(N) - np.eye(N, k=-1)
    D = D[1:]
    info = np.zeros((N, N))
    info[0, 0] += 1 / p0
    info += D.T @ D / q + np.eye(N) / r
    mean = np.linalg.solve(info, z / r)
    cov = np.linalg.inv(info)
    np.testing.assert_allclose(x_s[:, 0], mean, rtol=1e-8, atol=1e-10)
    np.testing.assert_allclose(P_s[:, 0, 0], np.diag(cov), rtol=1e-8)
