"""Block 5 (mount alignment): closed-form sign cases and synthetic drives through the pipeline."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from _pipeline_synth import G, laps, make_log
from iotnav.engines import Pipeline, PipelineConfig, run_batch
from iotnav.engines.config import EngineConfig
from iotnav.techniques.mount import (
    AS_X,
    AS_Y,
    AV_Y,
    DT,
    DV,
    MountAligner,
    MountConfig,
    lsq_estimate,
    lsq_sums,
    paper_estimate,
)

MOUNTS_DEG = [0.0, 45.0, 90.0, 135.0, -90.0]


def _sensor(a_v: np.ndarray, mount_deg: float) -> np.ndarray:
    # a_s = R(-mount) a_v, written out
    m = math.radians(mount_deg)
    return np.array(
        [math.cos(m) * a_v[0] + math.sin(m) * a_v[1], -math.sin(m) * a_v[0] + math.cos(m) * a_v[1]]
    )


def _dwrap(a: float, b: float) -> float:
    return abs((a - b + 180.0) % 360.0 - 180.0)


@pytest.mark.parametrize("mount_deg", MOUNTS_DEG)
def test_paper_equations_with_sign_resolution(mount_deg: float) -> None:
    acc = _sensor(np.array([1.0, 0.0]), mount_deg)  # accelerating forward
    brake = _sensor(np.array([-1.0, 0.0]), mount_deg)  # braking
    mu_acc, _ = paper_estimate(acc, +3.0)
    mu_brk, literal = paper_estimate(brake, -3.0)
    assert _dwrap(math.degrees(mu_acc), mount_deg) < 1e-9
    assert _dwrap(math.degrees(mu_brk), mount_deg) < 1e-9
    # the literal arctan of Eq. 3 is only defined modulo 180 degrees
    assert _dwrap(math.degrees(-literal) % 180.0, mount_deg % 180.0) < 1e-9 or mount_deg % 180 == 90


@pytest.mark.parametrize("mount_deg", MOUNTS_DEG)
def test_lsq_uses_centripetal_acceleration(mount_deg: float) -> None:
    # constant speed: only lateral (centripetal) accelerations of both signs
    a_v = np.array([[0.0, 2.0], [0.0, -1.5], [0.0, 0.0], [0.0, 1.0]])
    a_s = np.array([_sensor(a, mount_deg) for a in a_v])
    mu, q = lsq_estimate(lsq_sums(a_s, a_v), len(a_v))
    assert _dwrap(math.degrees(mu), mount_deg) < 1e-9
    assert q["coherence"] == pytest.approx(1.0)


def _run(segments, mount_deg: float, method: str, seed: int = 0):
    log, _truth = make_log(segments, mount_yaw=math.radians(mount_deg), seed=seed)
    cfg = PipelineConfig(mount=MountConfig(method=method), pipeline=EngineConfig(gravity_mps2=G))
    df = run_batch(Pipeline(cfg), log)
    est = [e for e in df.attrs["events"] if e["type"] == "mount_estimate" and e["accepted"]]
    return df, est


@pytest.mark.parametrize("mount_deg", MOUNTS_DEG)
def test_lsq_recovers_mount_on_constant_speed_laps(mount_deg: float) -> None:
    df, est = _run(laps(1), mount_deg, "lsq", seed=int(mount_deg) % 7)
    assert est, "no accepted estimate"
    assert est[0]["t"] < 40.0  # within the first lap
    assert all(_dwrap(math.degrees(e["mount_yaw_rad"]), mount_deg) < 2.0 for e in est)
    assert _dwrap(math.degrees(df.attrs["mount_yaw_rad"]), mount_deg) < 2.0


ACC_BRAKE = [(5.0, 0.0, 0.0), (12.0, 1.0, 0.0), (10.0, 0.0, 0.0), (12.0, -1.0, 0.0), (5.0, 0.0, 0.0)]


@pytest.mark.parametrize("mount_deg", MOUNTS_DEG)
def test_paper_method_recovers_mount_on_accelerating_and_braking_straight(mount_deg: float) -> None:
    _df, est = _run(ACC_BRAKE, mount_deg, "paper", seed=3)
    assert len(est) >= 2  # one while accelerating, one while braking
    assert {e["speed_change_mps"] > 0 for e in est} == {True, False}
    assert all(_dwrap(math.degrees(e["mount_yaw_rad"]), mount_deg) < 2.0 for e in est)


def test_constant_speed_straight_is_not_accepted() -> None:
    straight = [(5.0, 0.0, 0.0), (4.0, 2.0, 0.0), (40.0, 0.0, 0.0)]
    for method in ("paper", "lsq"):
        df, est = _run(straight, 90.0, method)
        assert all(e["t"] < 14.5 for e in est)  # only the buffer touching the acceleration phase
        late = [e for e in df.attrs["events"] if e["type"] == "mount_estimate" and e["t"] > 15.0]
        assert len(late) >= 3 and not any(e["accepted"] for e in late)


def test_levelled_projection_closed_form() -> None:
    from iotnav.geo import euler_to_dcm
    from iotnav.techniques.mount import levelled

    roll, pitch, yaw = 0.2, -0.1, 0.7
    C_nb = euler_to_dcm(roll, pitch, yaw)
    a_n = np.array([0.3, -0.8, 0.0])  # horizontal acceleration in n
    down_b = C_nb.T @ np.array([0.0, 0.0, 1.0])
    a_s = levelled(C_nb.T @ a_n, down_b)
    # the levelled frame is n rotated by the sensor yaw about the vertical
    psi = math.atan2(C_nb[1, 0], C_nb[0, 0])
    expect = np.array(
        [math.cos(psi) * a_n[0] + math.sin(psi) * a_n[1], -math.sin(psi) * a_n[0] + math.cos(psi) * a_n[1]]
    )
    np.testing.assert_allclose(a_s, expect, atol=1e-12)


def _feed_turns(al, mount_deg: float, tilt_err_rad: float, body: bool) -> list:
    """Drive an aligner directly: 10 s standing, then 6 x (10 s straight at 5 m/s, 10 s left turn).

    The sensor is tilted (roll 3 deg, pitch -2 deg) and its accelerometer biased by
    0.15 m/s^2; ``tilt_err_rad`` is the error of a tilt estimate used for levelled input.
    """
    from iotnav.geo import euler_to_dcm

    g = 9.81
    mu = math.radians(mount_deg)
    C_vb = euler_to_dcm(math.radians(3.0), math.radians(-2.0), mu)
    bias = np.array([0.15, -0.1, 0.05])
    # levelling of levelled input: the true one tilted by tilt_err in pitch (about the vehicle's
    # lateral axis), which leaks gravity across the centripetal acceleration of the turns
    C_err = euler_to_dcm(0.0, tilt_err_rad, 0.0)
    events = []
    t, v = 0.0, 0.0
    al.add_gnss(t, 0.0, 0.0, False, True)
    phases = [(10.0, 0.0, 0.0)] + [(2.0, 2.5, 0.0)] + [(10.0, 0.0, 0.0), (10.0, 0.0, -0.5)] * 6
    for dur, acc, r in phases:
        for _ in range(round(dur)):
            for _k in range(20):  # 20 Hz IMU, flat ground: vehicle frame level
                a_v3 = np.array([acc, v * r, 0.0])
                f_v = a_v3 - np.array([0.0, 0.0, g])
                f_b = C_vb.T @ f_v + bias
                if body:
                    al.add_imu_body(f_b, r)
                else:
                    C_lev = C_err @ C_vb  # levelling = (tilt only) estimate of C_vb's tilt
                    f_l = C_lev @ (f_b - bias)
                    cm, sm = math.cos(mu), math.sin(mu)
                    al.add_imu(np.array([cm * f_l[0] + sm * f_l[1], -sm * f_l[0] + cm * f_l[1]]), r)
                v += acc / 20.0
            t += 1.0
            ev = al.add_gnss(t, v, 0.0, v > 1.0, v < 0.5)
            if ev is not None:
                events.append(ev)
    return events


@pytest.mark.parametrize("mount_deg", MOUNTS_DEG)
def test_gravity_reference_levelling_removes_the_tilt_leak(mount_deg: float) -> None:
    from iotnav.techniques.mount import MountAligner

    body = [e for e in _feed_turns(MountAligner(MountConfig()), mount_deg, 0.0, True) if e["accepted"]]
    assert body and all(_dwrap(math.degrees(e["mount_yaw_rad"]), mount_deg) < 0.05 for e in body)
    # the same drive levelled by a tilt estimate 1 degree off: the leak (0.17 m/s^2 against a
    # 2.5 m/s^2 centripetal signal) turns the estimate by several degrees
    tilted = [e for e in _feed_turns(MountAligner(MountConfig()), mount_deg, math.radians(1.0), False)]
    tilted = [e for e in tilted if e["accepted"]]
    assert tilted and _dwrap(math.degrees(tilted[-1]["mount_yaw_rad"]), mount_deg) > 2.0


def test_matched_smoothing_is_a_difference_of_speed_means() -> None:
    from iotnav.techniques.mount import AV_Y, DT, DV, IMU_N, IMU_R, MountAligner

    al = MountAligner(MountConfig(smooth_epochs=3, buffer_epochs=64))
    rng = np.random.default_rng(2)
    v = 5.0 + rng.normal(0.0, 0.1, 12)
    al.add_gnss(0.0, float(v[0]), 0.0, True, False)  # opens the first interval
    rows = []
    for k in range(1, 12):
        # one IMU sample per 1 s interval, its yaw rate making v_mean r = k
        al.imu_sums[IMU_N] = 1.0
        al.imu_sums[IMU_R] = k / (0.5 * (v[k] + v[k - 1]))
        n_before = al.k
        al.add_gnss(float(k), float(v[k]), 0.0, True, False)
        if k < 5:
            assert al.k == 0  # needs 2M - 1 = 5 contiguous intervals
        elif al.k > n_before:
            rows.append(al.buf[al.k - 1].copy())
    assert len(rows) == 7
    out = rows[-1]
    # rows over intervals 7..11 (speeds v[6..11]): (mean v[9..11] - mean v[6..8]) / 3 s
    assert out[DV] / out[DT] == pytest.approx((v[9:12].mean() - v[6:9].mean()) / 3.0, abs=1e-12)
    assert out[AV_Y] == pytest.approx((7 + 2 * 8 + 3 * 9 + 2 * 10 + 11) / 9.0)


def test_lsq_standard_deviation_is_consistent() -> None:
    rng = np.random.default_rng(9)
    mu, sigma, n = math.radians(30.0), 0.05, 40
    errs, stds = [], []
    for _ in range(1500):
        a_v = rng.normal(0.0, 0.6, (n, 2))
        a_s = np.array([_sensor(a, 30.0) for a in a_v]) + rng.normal(0.0, sigma, (n, 2))
        est, q = lsq_estimate(lsq_sums(a_s, a_v), n)
        errs.append(math.atan2(math.sin(est - mu), math.cos(est - mu)))
        stds.append(q["std_rad"])
    ratio = float(np.std(errs) / np.sqrt(np.mean(np.square(stds))))
    assert 0.9 < ratio < 1.1


def _fill(m: MountAligner, mount_deg: float, rng: np.random.Generator, noise: float) -> None:
    n = m.buf.shape[0]
    a_v = rng.normal(0.0, 0.8, (n, 2))
    a_s = np.array([_sensor(a, mount_deg) for a in a_v]) + rng.normal(0.0, noise, (n, 2))
    m.buf[:] = 0.0
    m.buf[:, AS_X], m.buf[:, AS_Y] = a_s[:, 0], a_s[:, 1]
    m.buf[:, DT] = 1.0
    m.buf[:, DV], m.buf[:, AV_Y] = a_v[:, 0], a_v[:, 1]


def test_forgetting_per_second_and_weight_bookkeeping() -> None:
    cfg = MountConfig(buffer_epochs=4, forget=0.5, forget_ref_s=2.0, min_accel_mps2=0.0, min_coherence=0.0)
    m = MountAligner(cfg)
    rng = np.random.default_rng(5)
    _fill(m, 30.0, rng, 0.01)
    m._evaluate(0.0, 5.0)
    assert m.n_acc == 4.0 and m.w2_acc == 4.0
    _fill(m, 30.0, rng, 0.01)
    m._evaluate(4.0, 5.0)
    # 4 s of buffer at 0.5 per 2 s: factor 0.25 on the sums, 0.0625 on the squared weights
    assert m.n_acc == pytest.approx(0.25 * 4 + 4)
    assert m.w2_acc == pytest.approx(0.0625 * 4 + 4)


def test_outlier_buffer_is_not_fused() -> None:
    cfg = MountConfig(buffer_epochs=8, min_accel_mps2=0.0, min_coherence=0.0, gate_sigma=3.0)
    m = MountAligner(cfg)
    rng = np.random.default_rng(6)
    _fill(m, 30.0, rng, 0.05)
    m._evaluate(0.0, 5.0)
    n0 = m.n_acc
    _fill(m, 90.0, rng, 0.05)  # a buffer 60 degrees off, each estimate good to a few degrees
    ev = m._evaluate(8.0, 5.0)
    assert ev["buffer_outlier"] == 1.0 and m.n_acc == n0
    _fill(m, 31.0, rng, 0.05)
    ev = m._evaluate(16.0, 5.0)
    assert ev["buffer_outlier"] == 0.0 and m.n_acc > n0
    assert _dwrap(math.degrees(ev["candidate_rad"]), 30.0) < 3.0


def test_provisional_estimate_replaces_a_rejected_initial_angle() -> None:
    """Before the first acceptance a useful estimate 3 sigma away from the angle in use is
    applied provisionally and followed by every later one; the estimates themselves and the
    acceptances are those of the aligner without it; after acceptance nothing is provisional."""
    cfg = MountConfig(buffer_epochs=8, min_accel_mps2=0.0, min_coherence=0.0, max_std_rad=math.radians(2.0))
    on = MountAligner(dataclasses.replace(cfg, provisional_sigmas=3.0))
    off = MountAligner(cfg)
    events = []
    for k in range(12):
        for m in (on, off):
            _fill(m, 150.0, np.random.default_rng(100 + k), 0.3)  # same buffers for both
        events.append((on._evaluate(8.0 * k, 5.0), off._evaluate(8.0 * k, 5.0)))
    for a, b in events:
        assert (a["candidate_rad"], a["std_rad"], a["accepted"]) == (
            b["candidate_rad"],
            b["std_rad"],
            b["accepted"],
        )
    first_acc = next(i for i, (a, _) in enumerate(events) if a["accepted"])
    assert first_acc >= 3  # the first buffers are above 2 deg (4.9, 3.5, 3.0, ...)
    for i, (a, b) in enumerate(events):
        if i < first_acc:
            assert a["provisional"] == 1.0 and a["applied"] and not b["applied"]
            assert a["mount_yaw_rad"] == a["candidate_rad"] and b["mount_yaw_rad"] == 0.0
            assert _dwrap(math.degrees(a["mount_yaw_rad"]), 150.0) < 3.0 * math.degrees(a["std_rad"])
        else:
            assert a["provisional"] == 0.0
    # an initial angle the data do not reject stays in use
    near = MountAligner(
        dataclasses.replace(cfg, provisional_sigmas=3.0, initial_mount_yaw_rad=math.radians(148.0))
    )
    _fill(near, 150.0, np.random.default_rng(100), 0.3)
    ev = near._evaluate(0.0, 5.0)
    assert not ev["applied"] and near.mount_yaw_rad == math.radians(148.0)


def test_provisional_estimate_does_not_end_a_one_off_calibration() -> None:
    """``one_off`` stops after the first *accepted* estimate; a provisional one keeps it going."""
    cfg = MountConfig(
        buffer_epochs=8,
        min_accel_mps2=0.0,
        min_coherence=0.0,
        max_std_rad=math.radians(2.0),
        provisional_sigmas=3.0,
        one_off=True,
    )
    m = MountAligner(cfg)
    seen = []
    for k in range(12):
        _fill(m, 150.0, np.random.default_rng(100 + k), 0.3)
        if m.done:
            break
        ev = m._evaluate(8.0 * k, 5.0)
        seen.append((ev["provisional"], ev["accepted"], m.done))
    assert seen[0] == (1.0, False, False)  # provisional, calibration still running
    assert seen[-1][1] and seen[-1][2] and m.accepted_once  # ended by the first acceptance
