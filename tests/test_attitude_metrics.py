"""BROAD attitude metric and ENU/NED conversion against hand-computed cases."""

from __future__ import annotations

import math

import numpy as np
import pytest

from iotnav.eval.attitude import (
    Q_ENU_NED,
    attitude_rmse,
    enu_to_ned_quat,
    error_quat,
    heading_error,
    inclination_error,
    ned_to_enu_quat,
    quat_to_euler_ned,
    total_error,
)
from iotnav.techniques.ahrs_eskf import quat_multiply, quat_to_dcm


def _axis_angle(axis: list[float], deg: float) -> np.ndarray:
    a = np.asarray(axis, float) / np.linalg.norm(axis)
    h = math.radians(deg) / 2
    return np.array([math.cos(h), *(math.sin(h) * a)])


def _random_quats(n: int, seed: int = 1) -> np.ndarray:
    q = np.random.default_rng(seed).normal(size=(n, 4))
    return q / np.linalg.norm(q, axis=1, keepdims=True)


def test_identity_error_is_zero() -> None:
    q = _random_quats(5)
    e = error_quat(q, q)
    np.testing.assert_allclose(total_error(e), 0.0, atol=1e-6)
    np.testing.assert_allclose(heading_error(e), 0.0, atol=1e-6)
    np.testing.assert_allclose(inclination_error(e), 0.0, atol=1e-6)


def test_pure_heading_rotation_of_10_deg() -> None:
    q_ref = _random_quats(7)
    q_est = quat_multiply(_axis_angle([0, 0, 1], 10.0), q_ref)  # earth-frame rotation about Up
    r = attitude_rmse(q_est, q_ref, np.ones(7, bool))
    assert r.heading_deg == pytest.approx(10.0, abs=1e-9)
    assert r.inclination_deg == pytest.approx(0.0, abs=1e-6)
    assert r.total_deg == pytest.approx(10.0, abs=1e-9)


def test_pure_tilt_rotation() -> None:
    q_ref = _random_quats(7, seed=2)
    q_est = quat_multiply(_axis_angle([1, 1, 0], 7.0), q_ref)  # about a horizontal earth axis
    r = attitude_rmse(q_est, q_ref, np.ones(7, bool))
    assert r.heading_deg == pytest.approx(0.0, abs=1e-6)
    assert r.inclination_deg == pytest.approx(7.0, abs=1e-9)
    assert r.total_deg == pytest.approx(7.0, abs=1e-9)


def test_rmse_uses_movement_and_ignores_nan() -> None:
    q_ref = _random_quats(4, seed=3)
    q_est = q_ref.copy()
    q_est[1] = quat_multiply(_axis_angle([0, 0, 1], 20.0), q_ref[1])  # scored
    q_est[2] = quat_multiply(_axis_angle([0, 0, 1], 40.0), q_ref[2])  # not in movement
    q_ref = q_ref.copy()
    q_ref[3] = np.nan  # lost tracking
    movement = np.array([True, True, False, True])
    r = attitude_rmse(q_est, q_ref, movement)
    assert r.total_deg == pytest.approx(math.sqrt((0**2 + 20**2) / 2), abs=1e-6)


def test_constant_heading_offset_is_removed_for_6d() -> None:
    q_ref = _random_quats(9, seed=4)
    q_est = quat_multiply(_axis_angle([0, 0, 1], -30.0), q_ref)
    r = attitude_rmse(q_est, q_ref, np.ones(9, bool), remove_heading=True)
    assert r.heading_offset_deg == pytest.approx(-30.0, abs=1e-6)
    assert r.total_deg == pytest.approx(0.0, abs=1e-5)


def test_enu_ned_conversion_of_known_vectors() -> None:
    # sensor axes aligned with ENU: q_enu_b = identity
    q_nb = enu_to_ned_quat(np.array([1.0, 0.0, 0.0, 0.0]))
    C_nb = quat_to_dcm(q_nb)
    np.testing.assert_allclose(C_nb @ [1.0, 0.0, 0.0], [0.0, 1.0, 0.0], atol=1e-12)  # East
    np.testing.assert_allclose(C_nb @ [0.0, 1.0, 0.0], [1.0, 0.0, 0.0], atol=1e-12)  # North
    np.testing.assert_allclose(C_nb @ [0.0, 0.0, 1.0], [0.0, 0.0, -1.0], atol=1e-12)  # Up
    # sensor x North, y West, z Up (90 deg about ENU Up): in NED that is yaw 0, upside down
    q_enu_b = _axis_angle([0, 0, 1], 90.0)
    roll, pitch, yaw = quat_to_euler_ned(enu_to_ned_quat(q_enu_b))
    assert (abs(float(roll)), float(pitch), float(yaw)) == pytest.approx((math.pi, 0.0, 0.0), abs=1e-12)
    # sensor x pointing East is yaw +90 deg in NED
    _, _, yaw = quat_to_euler_ned(enu_to_ned_quat(np.array([1.0, 0, 0, 0])))
    assert float(yaw) == pytest.approx(math.pi / 2)


def test_enu_ned_round_trip() -> None:
    q = _random_quats(6, seed=5)
    back = ned_to_enu_quat(enu_to_ned_quat(q))
    np.testing.assert_allclose(np.abs(np.sum(back * q, axis=1)), 1.0, atol=1e-12)
    np.testing.assert_allclose(np.linalg.norm(Q_ENU_NED), 1.0)
