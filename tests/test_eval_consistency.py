"""Whitened innovations and the innovation autocorrelation test (seeded, hand-computed values)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from iotnav.eval.consistency import epoch_grid, innovation_autocorrelation, whiten_innovations


def test_whiten_diagonal_and_padded() -> None:
    y = np.array([[2.0, -3.0, 1.0], [1.0, 2.0, np.nan]])
    S = np.array([np.diag([4.0, 9.0, 0.25]), np.full((3, 3), np.nan)])
    S[1, :2, :2] = np.diag([1.0, 16.0])
    w = whiten_innovations(y, S)
    np.testing.assert_allclose(w[0], [1.0, -1.0, 2.0])
    np.testing.assert_allclose(w[1, :2], [1.0, 0.5])
    assert math.isnan(w[1, 2])


def test_whiten_full_covariance() -> None:
    # S = L L^T with L = [[2, 0], [1, 3]]: w = L^-1 y by forward substitution
    S = np.array([[4.0, 2.0], [2.0, 10.0]])
    y = np.array([4.0, 5.0])
    w = whiten_innovations(y, S)
    np.testing.assert_allclose(w, [2.0, (5.0 - 1.0 * 2.0) / 3.0])
    # |w|^2 is the NIS
    assert float(w @ w) == pytest.approx(float(y @ np.linalg.solve(S, y)))
    # samples of N(0, S) come out with unit covariance
    rng = np.random.default_rng(4)
    Y = rng.multivariate_normal([0.0, 0.0], S, 20000)
    W = whiten_innovations(Y, np.broadcast_to(S, (20000, 2, 2)))
    np.testing.assert_allclose(np.cov(W.T), np.eye(2), atol=0.03)
    with pytest.raises(ValueError):
        whiten_innovations(np.zeros((3, 2)), np.zeros((2, 2, 2)))


def test_autocorrelation_hand_computed() -> None:
    # lag 1 of [1, 2, 3]: (1*2 + 2*3) / sqrt((1 + 4)(4 + 9)); the second run has no lag-1 pair
    runs = [np.array([1.0, 2.0, 3.0]), np.array([1.0, np.nan, 1.0])]
    ac = innovation_autocorrelation(runs, [1, 2])
    assert ac.rho[0, 0] == pytest.approx(8.0 / math.sqrt(65.0))
    assert ac.n_pairs[0, 0] == 2
    # lag 2: pairs (1, 3) and (1, 1)
    assert ac.rho[1, 0] == pytest.approx(4.0 / math.sqrt(2.0 * 10.0))
    assert ac.band[1, 0] == pytest.approx(1.959964 / math.sqrt(2.0), rel=1e-6)
    with pytest.raises(ValueError):
        innovation_autocorrelation(runs, [0])
    with pytest.raises(ValueError):
        innovation_autocorrelation([], [1])


def test_autocorrelation_white_and_ar1() -> None:
    rng = np.random.default_rng(11)
    white = [rng.standard_normal((400, 2)) for _ in range(10)]
    ac = innovation_autocorrelation(white, range(1, 11))
    assert ac.n_pairs[0, 0] == 10 * 399
    assert np.all(ac.portmanteau < ac.portmanteau_threshold())
    # AR(1), phi = 0.5: rho(l) = 0.5^l, standard error about 1 / sqrt(n)
    ar = []
    for _ in range(10):
        e = rng.standard_normal(400)
        x = np.empty(400)
        x[0] = e[0] / math.sqrt(0.75)
        for k in range(1, 400):
            x[k] = 0.5 * x[k - 1] + e[k]
        ar.append(x)
    ac = innovation_autocorrelation(ar, [1, 2, 3])
    np.testing.assert_allclose(ac.rho[:, 0], [0.5, 0.25, 0.125], atol=3.0 / math.sqrt(4000))
    assert not ac.inside[0, 0]
    assert ac.portmanteau[0] > 10.0 * ac.portmanteau_threshold()


def test_epoch_grid_places_rows_and_blanks_the_transient() -> None:
    t = np.array([10.0, 11.0, 13.02, 14.0])  # the epoch at 12 s is missing, 13.02 rounds to 13
    w = np.arange(8.0).reshape(4, 2)
    g = epoch_grid(t, w, 1.0, skip=1)
    assert g.shape == (5, 2)
    assert np.all(np.isnan(g[0])) and np.all(np.isnan(g[2]))  # skipped, and the missing epoch
    np.testing.assert_array_equal(g[[1, 3, 4]], w[1:])
    g2 = epoch_grid(t[:2], w[:2], 2.0)  # 2 Hz: one empty epoch between them
    assert g2.shape == (3, 2) and np.all(np.isnan(g2[1]))
    np.testing.assert_array_equal(g2[[0, 2]], w[:2])


def test_familywise_portmanteau_false_alarm_rate() -> None:
    """White 3-component innovations, 600 seeded trials of 10 runs x 200 samples: one
    component or more over its 95 % Box-Pierce threshold in about 14 % of the trials
    (1 - 0.95^3), over the familywise threshold in about 5 % (binomial sd 0.9 %)."""
    rng = np.random.default_rng(7)
    per_component = together = 0
    n_trials = 600
    for _ in range(n_trials):
        ac = innovation_autocorrelation([rng.standard_normal((200, 3)) for _ in range(10)], range(1, 11))
        per_component += bool(np.any(ac.portmanteau > ac.portmanteau_threshold()))
        together += bool(np.any(ac.portmanteau > ac.portmanteau_threshold(familywise=True)))
    assert 0.10 < per_component / n_trials < 0.18, per_component
    assert 0.025 < together / n_trials < 0.075, together
