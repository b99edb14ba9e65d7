"""Block 5 (mount alignment): closed-form sign cases and synthetic drives through the pipeline."""

from __future__ import annotations

import math

import numpy as np
import pytest

from _pipeline_synth import G, laps, make_log
from iotnav.engines import Pipeline, PipelineConfig, run_batch
from iotnav.engines.config import EngineConfig
from iotnav.techniques.mount import MountConfig, lsq_estimate, lsq_sums, paper_estimate

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
