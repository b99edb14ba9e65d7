"""Closed-form tests of the decoupled velocity / bias / drift equations (Dabove et al. 2016)."""

from __future__ import annotations

import numpy as np
import pytest

from iotnav.geo import euler_to_dcm
from iotnav.strapdown import integrate, rotvec_to_dcm
from iotnav.techniques import decoupled_bias as db

G_N = np.array([0.0, 0.0, 9.80])


def _const_interval(C: np.ndarray, f_b: np.ndarray, T: float) -> db.IntervalIntegrals:
    """Integrals of a constant attitude and specific force, written out by hand."""
    a = C @ f_b + G_N
    return db.IntervalIntegrals(
        T, a * T, a * T**2 / 2, C * T, C * T**2 / 2, np.eye(3), np.eye(3) * T, np.zeros(3)
    )


def test_three_fixes_constant_attitude_give_velocity_and_bias() -> None:
    C = np.asarray(euler_to_dcm(0.1, -0.2, 1.0))
    a_n = np.array([0.3, -0.1, 0.05])  # true acceleration in n
    b = np.array([0.02, -0.03, 0.01])  # accelerometer bias in b
    v0 = np.array([1.2, 0.4, -0.1])
    f_meas = C.T @ (a_n - G_N) + b
    T1, T2 = 0.8, 1.3  # unequal intervals
    t = np.array([0.0, T1, T1 + T2])
    X = np.array([5.0, 2.0, -1.0]) + np.outer(t, v0) + 0.5 * np.outer(t**2, a_n)
    ivs = [_const_interval(C, f_meas, T1), _const_interval(C, f_meas, T2)]
    v_est, b_est, v_last = db.solve_velocity_bias(X, ivs)
    np.testing.assert_allclose(v_est, v0, atol=1e-12)
    np.testing.assert_allclose(b_est, b, atol=1e-12)
    np.testing.assert_allclose(v_last, v0 + a_n * (T1 + T2), atol=1e-12)


def test_more_fixes_least_squares_recovers_the_same() -> None:
    C = np.eye(3)
    a_n = np.array([0.1, 0.2, 0.0])
    b = np.array([-0.05, 0.02, 0.03])
    v0 = np.array([0.5, -0.5, 0.0])
    f_meas = a_n - G_N + b
    t = np.arange(6) * 0.7
    X = np.outer(t, v0) + 0.5 * np.outer(t**2, a_n)
    ivs = [_const_interval(C, f_meas, 0.7)] * 5
    v_est, b_est, _ = db.solve_velocity_bias(X, ivs)
    np.testing.assert_allclose(v_est, v0, atol=1e-12)
    np.testing.assert_allclose(b_est, b, atol=1e-12)


def test_compose_matches_closed_form_over_the_union() -> None:
    C = np.asarray(euler_to_dcm(0.0, 0.1, 0.4))
    f = np.array([0.2, 0.1, -9.7])
    whole = _const_interval(C, f, 3.0)
    comp = db.compose(_const_interval(C, f, 1.0), _const_interval(C, f, 2.0))
    for a, b in zip(whole, comp, strict=True):
        np.testing.assert_allclose(a, b, atol=1e-12)


def test_velocity_known_bias_closed_form() -> None:
    C = np.eye(3)
    a_n = np.array([0.0, 0.4, 0.0])
    b = np.array([0.01, 0.0, -0.02])
    v0 = np.array([1.0, 0.0, 0.0])
    T = 2.0
    iv = _const_interval(C, a_n - G_N + b, T)
    X1 = v0 * T + 0.5 * a_n * T**2
    v_a, v_b = db.velocity_known_bias(np.zeros(3), X1, iv, b)
    np.testing.assert_allclose(v_a, v0, atol=1e-12)
    np.testing.assert_allclose(v_b, v0 + a_n * T, atol=1e-12)


def test_too_few_fixes_raise() -> None:
    iv = _const_interval(np.eye(3), np.zeros(3), 1.0)
    with pytest.raises(ValueError, match="K >= 3"):
        db.solve_velocity_bias(np.zeros((2, 3)), [iv])


def test_accumulated_integrals_recover_bias_on_a_rotating_body() -> None:
    """Strapdown truth with rotation; integrals accumulated from biased samples; exact recovery."""
    rng = np.random.default_rng(3)
    n, dt = 301, 0.01
    t = np.arange(n) * dt
    w_true = np.column_stack([0.3 * np.sin(2 * t), 0.2 * np.cos(3 * t), 0.5 + 0.0 * t])
    f_true = np.column_stack([0.5 * np.sin(t), 0.2 + 0.0 * t, -9.8 + 0.1 * np.cos(4 * t)])
    C0 = np.asarray(euler_to_dcm(0.05, -0.1, 2.0))
    v0 = np.array([1.0, -0.3, 0.05])
    C, _, p = integrate(C0, v0, np.zeros(3), t, f_true, w_true, G_N)
    b = rng.normal(0.0, 0.05, 3)
    acc = np.zeros(db.N_ACC)
    db.reset_flat(acc)
    marks = {0: 0, 120: 1, 300: 2}
    ivs = []
    Ck = C0.copy()
    for k in range(n - 1):
        R_half = rotvec_to_dcm(0.5 * dt * w_true[k])
        C_half = Ck @ R_half
        db.accumulate(acc, C_half, R_half @ R_half, f_true[k] + b, np.zeros(3), dt, G_N)
        Ck = C_half @ R_half
        if k + 1 in marks and k + 1 > 0:
            ivs.append(db.interval_from_flat(acc))
            db.reset_flat(acc)
    v_est, b_est, _v_last = db.solve_velocity_bias(p[[0, 120, 300]], ivs)
    np.testing.assert_allclose(b_est, b, atol=1e-9)
    np.testing.assert_allclose(v_est, v0, atol=1e-9)
    np.testing.assert_allclose(Ck, C[-1], atol=1e-12)


def test_drift_from_two_attitudes_without_rotation_is_exact() -> None:
    d = np.array([0.004, -0.002, 0.003])
    T, dt = 2.0, 0.01
    acc = np.zeros(db.N_ACC)
    db.reset_flat(acc)
    C0 = np.asarray(euler_to_dcm(0.2, 0.1, -1.0))
    R = rotvec_to_dcm(d * dt)  # the gyro sees only its drift: the device is still
    for _ in range(round(T / dt)):
        db.accumulate(acc, C0, R, np.zeros(3), np.zeros(3), dt, G_N)
    d_est = db.solve_gyro_drift(C0, C0, db.interval_from_flat(acc))
    np.testing.assert_allclose(d_est, d, atol=1e-12)


def test_drift_while_rotating_is_recovered_to_second_order() -> None:
    """Rotating at 0.5 rad/s for 1 s; the linearisation error is of order |d| * |omega T| * dt."""
    d = np.array([0.01, -0.005, 0.008])
    w = np.array([0.1, -0.2, 0.5])
    T, dt = 1.0, 0.01
    C0 = np.asarray(euler_to_dcm(0.1, 0.0, 0.3))
    C1 = C0 @ rotvec_to_dcm(w * T)
    acc = np.zeros(db.N_ACC)
    db.reset_flat(acc)
    R = rotvec_to_dcm((w + d) * dt)
    for _ in range(round(T / dt)):
        db.accumulate(acc, C0, R, np.zeros(3), np.zeros(3), dt, G_N)
    d_est = db.solve_gyro_drift(C0, C1, db.interval_from_flat(acc))
    # second-order terms: |d T|^2 / T ~ 2e-4 and |omega dt| |d| / 2 ~ 3e-5 rad/s
    np.testing.assert_allclose(d_est, d, atol=3e-4)
