"""Block 2 filters on closed-form synthetic inputs: tilt, yaw, gyro bias, cascade."""

from __future__ import annotations

import math

import numpy as np

from iotnav.techniques.cascade import CascadeKF
from iotnav.techniques.gyro_bias_kf import GyroBiasConfig, GyroBiasKF
from iotnav.techniques.tilt_kf import TiltKF, roll_pitch_from_down
from iotnav.techniques.yaw_kf import YawKF, dcm_from_rows, yaw_of_dcm

G = 9.81


def _angle(a: np.ndarray, b: np.ndarray) -> float:
    return math.degrees(math.acos(np.clip(a @ b / np.linalg.norm(a) / np.linalg.norm(b), -1, 1)))


def _down_b(roll: float, pitch: float) -> np.ndarray:
    # third row of C_nb, written out independently of the code under test
    return np.array([-math.sin(pitch), math.sin(roll) * math.cos(pitch), math.cos(roll) * math.cos(pitch)])


def test_tilt_converges_from_wrong_start_when_static() -> None:
    rng = np.random.default_rng(1)
    truth = _down_b(math.radians(20), math.radians(-10))
    kf = TiltKF(x0=np.array([0.0, 0.0, 1.0]))  # ~22 degrees off
    for _ in range(500):
        kf.predict(rng.normal(0, 0.01, 3), 0.01)
        kf.update(-G * truth + rng.normal(0, 0.05, 3), G)
    assert _angle(kf.x, truth) < 0.5


def test_tilt_tracks_known_rotation() -> None:
    # rotation about the sensor x axis at 10 deg/s for 6 s: roll goes 0 -> 60 degrees
    rng = np.random.default_rng(2)
    rate = math.radians(10.0)
    kf = TiltKF(x0=np.array([0.0, 0.0, 1.0]))
    dt = 0.01
    worst = 0.0
    for k in range(1, 601):
        truth = _down_b(rate * k * dt, 0.0)
        kf.predict(np.array([rate, 0.0, 0.0]) + rng.normal(0, 0.005, 3), dt)
        kf.update(-G * truth + rng.normal(0, 0.05, 3), G)
        worst = max(worst, _angle(kf.x, truth))
    assert worst < 1.0
    assert _angle(kf.x, _down_b(math.radians(60), 0.0)) < 0.5


def test_tilt_trusts_gyro_during_external_acceleration() -> None:
    kf = TiltKF(x0=np.array([0.0, 0.0, 1.0]))
    for _ in range(500):  # 5 s at rest first
        kf.predict(np.zeros(3), 0.01)
        kf.update(np.array([0.0, 0.0, -G]), G)
    for _ in range(300):  # 3 s of 3 m/s^2 forward acceleration, level
        kf.predict(np.zeros(3), 0.01)
        kf.update(np.array([3.0, 0.0, -G]), G)
    assert _angle(kf.x, np.array([0.0, 0.0, 1.0])) < 3.0  # naive accel tilt would be 17 degrees


def test_yaw_course_aiding_converges_and_gyro_propagates() -> None:
    rng = np.random.default_rng(3)
    x3 = np.array([0.0, 0.0, 1.0])
    kf = YawKF()
    kf.reset_heading(math.radians(-40.0), x3, sigma=1.0)  # wrong, uncertain start
    psi = math.radians(30.0)
    for k in range(2000):
        kf.predict(rng.normal(0, 0.005, 3), 0.01)
        if k % 100 == 0:
            kf.update_heading(psi + rng.normal(0, 0.05), x3, 0.05)
    C = dcm_from_rows(kf.x, x3)
    assert abs(math.degrees(yaw_of_dcm(C) - psi)) < 2.0
    # gyro-only: turn at 20 deg/s for 2 s about the down axis -> +40 degrees
    for _ in range(200):
        kf.predict(np.array([0.0, 0.0, math.radians(20.0)]), 0.01)
    C = dcm_from_rows(kf.x, x3)
    assert abs(math.degrees(yaw_of_dcm(C)) - 70.0) < 2.5


def test_yaw_magnetometer_aiding() -> None:
    x3 = np.array([0.0, 0.0, 1.0])
    psi = math.radians(-120.0)
    # field: horizontal to magnetic North (declination 0) with a downward dip, resolved in b
    m_n = np.array([20.0, 0.0, 40.0])
    C_bn = np.array([[math.cos(psi), math.sin(psi), 0], [-math.sin(psi), math.cos(psi), 0], [0, 0, 1]])
    kf = YawKF()
    for _ in range(20):
        kf.update_mag(C_bn @ m_n, x3)
    assert abs(math.degrees(yaw_of_dcm(dcm_from_rows(kf.x, x3)) - psi)) < 0.5


def test_gyro_bias_static_estimate() -> None:
    rng = np.random.default_rng(4)
    bias = np.array([0.01, -0.02, 0.005])
    kf = GyroBiasKF(GyroBiasConfig(gyro_noise_rad_s=0.01))
    for _ in range(4000):
        kf.predict(0.01)
        kf.update_static(bias + rng.normal(0, 0.01, 3))
    assert np.all(np.abs(kf.x - bias) < 1e-3)
    assert np.all(np.sqrt(np.diag(kf.P)) < 1e-3)


def test_gyro_bias_refuses_a_rate_that_is_not_a_number() -> None:
    kf = GyroBiasKF()
    kf.update_static(np.array([0.01, -0.02, 0.005]))
    before = kf.state.copy()
    for bad in ([math.nan, 0.0, 0.0], [0.0, math.nan, 0.0], [0.0, 0.0, math.nan]):
        assert kf.update_static(np.array(bad)) is False
    np.testing.assert_array_equal(kf.state, before)
    assert kf.update_static(np.array([0.4, 0.0, 0.0])) is False  # above max_rate_rad_s = 0.3


def test_tilt_initialises_in_any_orientation() -> None:
    # sensor z up (the rtklibexplorer car): at rest f_b = +g e_z, so the down axis is -e_z
    tilt = TiltKF()
    tilt.update(np.array([0.0, 0.0, G]), G)
    np.testing.assert_allclose(tilt.x, [0.0, 0.0, -1.0], atol=1e-12)
    for roll_deg, pitch_deg in ((180.0, 0.0), (150.0, -40.0), (-100.0, 70.0)):
        d = _down_b(math.radians(roll_deg), math.radians(pitch_deg))
        casc = CascadeKF()
        rng = np.random.default_rng(4)
        for _ in range(200):
            casc.step(-G * d + rng.normal(0, 0.02, 3), rng.normal(0, 0.002, 3), 0.01, True, G)
        assert _angle(casc.C_nb[2], d) < 0.5
        r, p = roll_pitch_from_down(casc.tilt.x)
        assert abs((math.degrees(r) - roll_deg + 180.0) % 360.0 - 180.0) < 0.5
        assert abs(math.degrees(p) - pitch_deg) < 0.5
