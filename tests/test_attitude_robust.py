"""ahrs_eskf under sustained linear acceleration and slow motion that looks like rest (issue 16).

Synthetic, seeded cases with known truth; the sustained-acceleration case is built on a real
BROAD segment (Laidig et al. 2021, CC BY 4.0) with translation added
(:func:`iotnav.eval.attitude.fast_translation_with_rest`).
"""

from __future__ import annotations

import math
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from iotnav.eval.attitude import (
    add_linear_acceleration,
    add_vertical_rotation,
    error_quat,
    inclination_error,
    load_broad,
    rest_breaks,
    slow_translation,
    translation_strokes,
)
from iotnav.techniques.ahrs_eskf import (
    AhrsEskfConfig,
    AhrsEskfResult,
    quat_exp,
    quat_multiply,
    quat_to_dcm,
    run_ahrs_eskf,
)

FS = 100.0
G = 9.81
BIAS = np.array([0.004, -0.006, 0.005])  # rad/s

#: The rest detector as it was before issue 16: rates up to 0.1 rad/s taken for a bias, no
#: window test on the accelerometer.
OLD_REST = replace(AhrsEskfConfig(), rest_max_rate_rad_s=0.1, rest_acc_drift_m_s2=math.inf)
#: All the parameters as they were before issue 16 (bias also learned in motion).
OLD = replace(OLD_REST, motion_bias_est=True, mag_noise_rad=2.0)


def _still_then(moving_s: float, turn_rad_s: float = 0.0, slow_amp_m_s2: float = 0.0, seed: int = 0):
    """6 s still, then ``moving_s`` of a turn about NED Down and/or a slow translation along
    North (0.25 Hz); returns truth q_nb, gyr, acc and the index where the motion starts."""
    rng = np.random.default_rng(seed)
    n0 = int(6.0 * FS)
    n = n0 + int(moving_s * FS)
    t = np.arange(n) / FS
    q = np.empty((n, 4))
    q[0] = quat_exp(np.array([0.2, -0.1, 0.5]))
    w_n = np.zeros((n, 3))
    w_n[n0:, 2] = turn_rad_s
    for k in range(1, n):  # a turn about the n-frame vertical: q <- Exp(w_n dt) (x) q
        qk = quat_multiply(quat_exp(w_n[k] / FS), q[k - 1])
        q[k] = qk / np.linalg.norm(qk)
    C = quat_to_dcm(q)  # C_nb
    a_n = np.zeros((n, 3))
    a_n[n0:, 0] = slow_amp_m_s2 * np.sin(2 * np.pi * 0.25 * (t[n0:] - t[n0]))
    f_n = a_n - np.array([0.0, 0.0, G])
    acc = np.einsum("kji,kj->ki", C, f_n) + rng.normal(0, 0.02, (n, 3))
    gyr = np.einsum("kji,kj->ki", C, w_n) + BIAS + rng.normal(0, 0.003, (n, 3))
    return q, gyr, acc, n0


def test_rest_detection_not_fooled_by_slow_translation() -> None:
    """A slow translation (0.3 m/s^2 at 0.25 Hz, no rotation) is steady enough for the per-sample
    tests; the window test on the low-passed accelerometer rejects it within 1 s."""
    _, gyr, acc, n0 = _still_then(20.0, slow_amp_m_s2=0.3)
    new = run_ahrs_eskf(gyr, acc, None, FS)
    old = run_ahrs_eskf(gyr, acc, None, FS, OLD_REST)
    assert new.rest[int(2.0 * FS) : n0].all()  # the still part is rest
    moving = slice(n0 + int(1.0 * FS), None)
    assert not new.rest[moving].any(), new.rest[moving].mean()
    # the old detector called all of the slow translation rest (100 %)
    assert old.rest[moving].mean() > 0.5


def test_rest_detection_not_fooled_by_slow_turn() -> None:
    """A steady turn of 3 deg/s about the vertical is above VQF's 2 deg/s bias clip: no rest, and
    the bias estimate does not swallow the turn (the old detector learned it as bias)."""
    _, gyr, acc, n0 = _still_then(15.0, turn_rad_s=math.radians(3.0))
    new = run_ahrs_eskf(gyr, acc, None, FS)
    old = run_ahrs_eskf(gyr, acc, None, FS, OLD_REST)
    moving = slice(n0 + int(1.0 * FS), None)
    assert not new.rest[moving].any()
    assert old.rest[moving].mean() > 0.5  # old: 95 %
    err_new = np.degrees(np.linalg.norm(new.gyro_bias_rad_s[-1] - BIAS))
    err_old = np.degrees(np.linalg.norm(old.gyro_bias_rad_s[-1] - BIAS))
    assert err_new < 0.1, err_new  # deg/s; measured 0.02
    assert err_old > 1.5, err_old  # old: 2.30 deg/s, most of the 3 deg/s turn became bias


def test_added_translation_is_a_pure_translation(datasets: Path) -> None:
    """The synthetic builders keep gyro, truth and the earth-frame specific force consistent."""
    rec = load_broad(datasets / "broad_attitude" / "05_undisturbed_slow_rotation_with_breaks_B.npz")
    seg = rec.segment(int(60 * rec.fs_hz), int(80 * rec.fs_hz))
    assert seg.q_ref_enu is not None and seg.movement is not None
    a = translation_strokes(seg.movement, seg.fs_hz, seed=3) + slow_translation(~seg.movement, seg.fs_hz)
    moved = add_linear_acceleration(seg, a)
    ok = np.isfinite(seg.q_ref_enu).all(axis=1)
    C = quat_to_dcm(seg.q_ref_enu[ok])
    d_enu = np.einsum("kij,kj->ki", C, moved.acc_b[ok] - seg.acc_b[ok])
    np.testing.assert_allclose(d_enu, a[ok], atol=1e-9)
    np.testing.assert_array_equal(moved.gyr_b, seg.gyr_b)
    # a turn about the vertical: the earth-frame specific force is unchanged
    turned = add_vertical_rotation(seg, np.full(len(seg.gyr_b), 0.05))
    assert turned.q_ref_enu is not None
    f0 = np.einsum("kij,kj->ki", C, seg.acc_b[ok])
    f1 = np.einsum("kij,kj->ki", quat_to_dcm(turned.q_ref_enu[ok]), turned.acc_b[ok])
    np.testing.assert_allclose(f1, f0, atol=1e-9)
    assert rest_breaks(rec).sum() > 30 * rec.fs_hz  # three breaks of about 10 s


def _fooled_rest_then_strokes(seed: int):
    """6 s still; 10 s of a slow tilt turn (3 deg/s about North) with a slow translation, which
    the old rest test took for rest; then 44 s of rotation with fast translation strokes
    (:func:`translation_strokes`, 2-5 m/s^2 held 0.4-1.5 s each way). Returns truth, gyr, acc and
    the index where the strokes start."""
    rng = np.random.default_rng(seed)
    n0, n1 = int(6 * FS), int(16 * FS)
    n = n1 + int(44 * FS)
    t = np.arange(n) / FS
    w_n = np.zeros((n, 3))
    w_n[n0:n1, 0] = math.radians(3.0)
    w_b = np.zeros((n, 3))
    tc = t[n1:] - t[n1]
    w_b[n1:] = np.stack(
        [0.6 * np.sin(0.5 * tc), 0.5 * np.sin(0.31 * tc + 1.0), 0.8 * np.sin(0.23 * tc + 2.0)], 1
    )
    q = np.empty((n, 4))
    q[0] = quat_exp(np.array([0.2, -0.1, 0.5]))
    for k in range(1, n):
        qk = quat_multiply(quat_exp(w_n[k] / FS), quat_multiply(q[k - 1], quat_exp(w_b[k] / FS)))
        q[k] = qk / np.linalg.norm(qk)
    C = quat_to_dcm(q)
    a_n = np.zeros((n, 3))
    a_n[n0:n1, 0] = 0.3 * np.sin(2 * np.pi * 0.25 * (t[n0:n1] - t[n0]))
    a_n += translation_strokes(t >= t[n1], FS, seed=seed)  # random directions: the frame is moot
    f_n = a_n - np.array([0.0, 0.0, G])
    acc = np.einsum("kji,kj->ki", C, f_n) + rng.normal(0, 0.02, (n, 3))
    gyr = np.einsum("kji,kj->ki", C, w_n) + w_b + BIAS + rng.normal(0, 0.003, (n, 3))
    return q, gyr, acc, n1


@pytest.mark.parametrize("seed", [0, 1])
def test_inclination_under_sustained_acceleration_after_fooled_rest(seed: int) -> None:
    """Inclination RMSE over 44 s of rotation with fast translation strokes, after a slow tilt
    turn that the old rest test took for rest: under 3.5 deg with the defaults (measured 2.78 /
    2.92 deg for seeds 0 / 1); the old parameters exceed it (4.07 / 4.09 deg, having learned
    1.6 deg/s of the turn as gyro bias)."""
    q, gyr, acc, n1 = _fooled_rest_then_strokes(seed)
    new = run_ahrs_eskf(gyr, acc, None, FS)
    old = run_ahrs_eskf(gyr, acc, None, FS, OLD)

    def incl_rms(res: AhrsEskfResult) -> float:
        e = np.degrees(inclination_error(error_quat(res.q_nb, q)))[n1:]
        return float(np.sqrt(np.mean(e**2)))

    assert incl_rms(new) < 3.5, incl_rms(new)
    assert incl_rms(old) > 3.5, incl_rms(old)
    assert np.degrees(np.linalg.norm(new.gyro_bias_rad_s[n1] - BIAS)) < 0.1  # deg/s; measured 0.03


def test_cascade_batch_equals_its_step() -> None:
    """The attitude benchmark's compiled cascade loop gives what CascadeKF.step gives per sample."""
    from iotnav.techniques.cascade import CascadeKF, run_cascade_imu

    _, gyr, acc, n0 = _still_then(4.0, turn_rad_s=0.2, slow_amp_m_s2=0.5)
    static = np.zeros(len(gyr), dtype=bool)
    static[: n0 - 50] = True
    batch = run_cascade_imu(acc, gyr, FS, static, G)
    kf = CascadeKF()
    for k in range(len(gyr)):
        C = kf.step(acc[k], gyr[k], 1.0 / FS if k else 0.0, bool(static[k]), G)
        np.testing.assert_allclose(batch[k], C, atol=1e-12)
