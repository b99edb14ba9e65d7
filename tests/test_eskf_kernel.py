"""The ``eskf`` compiled IMU kernel: batch equals streaming, and its compiled maths equals the reference.

``run_batch`` hands runs of IMU samples to :meth:`EskfEngine.imu_block`; ``step()`` runs the
same kernel on one-sample blocks. Both must give the same rows (1e-9), events and NIS log.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
import pandas as pd
import pytest

from iotnav import (
    kalman,
    sim,
)
from iotnav.engines import eskf_models as M
from iotnav.engines.base import OUTPUT_COLUMNS, iter_samples, run_batch
from iotnav.engines.eskf import EskfConfig, EskfEngine
from iotnav.io.log import Log
from iotnav.strapdown import rotvec_to_dcm

FLOATS = [c for c in OUTPUT_COLUMNS if c not in ("static", "source")]


def _stepped(engine: EskfEngine, log: Log) -> pd.DataFrame:
    rows = [o for s in iter_samples(log) if (o := engine.step(s)) is not None]
    return pd.DataFrame(rows, columns=list(OUTPUT_COLUMNS))


def _assert_same(log: Log, make: Any) -> tuple[pd.DataFrame, EskfEngine]:
    eb, es = make(), make()
    batch = run_batch(eb, log)
    stream = _stepped(es, log)
    assert len(batch) == len(stream) == len(log.imu)
    np.testing.assert_allclose(batch[FLOATS].to_numpy(), stream[FLOATS].to_numpy(), rtol=0.0, atol=1e-9)
    assert (batch.static.to_numpy() == stream.static.to_numpy()).all()
    assert (batch.source.to_numpy() == stream.source.to_numpy()).all()
    assert eb.events == es.events
    assert eb.nis_log == es.nis_log
    np.testing.assert_allclose(eb.P, es.P, rtol=0.0, atol=1e-12)
    return batch, eb


def test_batch_equals_step_car_with_static_start() -> None:
    """Car with a static start (ZUPT/ZARU), block-5 mount, NHC, one GNSS outage (dead reckoning)."""
    res = sim.build("car-tunnel", seed=4, overrides={"duration_s": 80.0, "gnss.outages_s": ((60.0, 70.0),)})
    log = Log(gnss=res.gnss, imu=res.imu, mag=res.mag)
    df, eng = _assert_same(log, EskfEngine)
    types = {e["type"] for e in eng.events}
    assert {"levelled", "static_start", "static_end", "mount_initialised", "heading_initialised"} <= types
    assert {"zupt", "zaru", "nhc", "gnss_position"} <= set(eng.nis_log)
    assert {"fix", "dr"} <= set(df.source)


def test_batch_equals_step_magnetometer() -> None:
    """Magnetometer heading (initial heading and updates, some gated out) between IMU blocks."""
    res = sim.build("car-magnetometer", seed=2, overrides={"duration_s": 140.0})
    hard, soft = res.mag_calibration()
    cfg = EskfConfig(
        mag_hard_iron_ut=hard,
        mag_soft_iron=soft,
        mag_declination_rad=math.radians(res.config.mag.declination_deg),
    )
    log = Log(gnss=res.gnss, imu=res.imu, mag=res.mag)
    _, eng = _assert_same(log, lambda: EskfEngine(cfg))
    heading = [e for e in eng.events if e["type"] == "heading_initialised"]
    assert heading and heading[0]["source"] == "magnetometer"
    assert "mag_heading" in eng.nis_log


def test_batch_equals_step_fixed_mount_base_states_small_record_buffer() -> None:
    """Configured mount, no scale factors; a tiny record buffer makes the kernel stop to flush often."""
    res = sim.build("car-tunnel", seed=5, overrides={"duration_s": 50.0})
    c = res.config
    cfg = EskfConfig(
        mount_rpy_rad=(c.mount_roll_rad, c.mount_pitch_rad, c.mount_yaw_rad),
        estimate_scale_factors=False,
        estimate_mount=False,
    )
    log = Log(gnss=res.gnss, imu=res.imu, mag=res.mag)

    def small() -> EskfEngine:
        eng = EskfEngine(cfg)
        eng.rec = np.zeros((5, eng.rec.shape[1]))
        return eng

    batch, eng = _assert_same(log, small)
    ref = run_batch(EskfEngine(cfg), log)
    np.testing.assert_array_equal(batch[FLOATS].to_numpy(), ref[FLOATS].to_numpy())
    assert eng.events == ref.attrs["events"]
    assert eng.P.shape == (M.N_BASE, M.N_BASE)


@pytest.mark.parametrize("m", [1, 2, 3])
def test_compiled_update_matches_kalman_update(m: int) -> None:
    rng = np.random.default_rng(m)
    n = M.N_FULL
    A = rng.normal(size=(n, n))
    P = A @ A.T / n + np.eye(n) * 1e-3
    H = np.zeros((3, n))
    H[:m] = rng.normal(size=(m, n)) * (rng.uniform(size=(m, n)) < 0.3)
    y = np.zeros(3)
    y[:m] = rng.normal(size=m)
    R = np.zeros((3, 3))
    R[:m, :m] = np.diag(rng.uniform(0.1, 1.0, m))
    ref = kalman.update(np.zeros(n), P, y[:m], H[:m], R[:m, :m], gate=100.0)
    Pc = P.copy()
    dx = np.empty(n)
    nis, ok, ratio = M.kalman_update(Pc, dx, y, H, R, m, 100.0)
    assert ok and ref.accepted
    assert nis == pytest.approx(ref.nis, rel=1e-10)
    assert ratio == pytest.approx(ref.test_ratio, rel=1e-10)
    np.testing.assert_allclose(dx, ref.x, rtol=0.0, atol=1e-12)
    np.testing.assert_allclose(Pc, ref.P, rtol=0.0, atol=1e-12)
    assert (Pc == Pc.T).all()
    # gated out: nothing changes
    Pg = P.copy()
    nis_g, ok_g, _ = M.kalman_update(Pg, dx, y, H, R, m, 0.5 * nis)
    assert not ok_g and nis_g == pytest.approx(nis)
    assert (Pg == P).all() and (dx == 0.0).all()


@pytest.mark.parametrize("n", [M.N_BASE, M.N_FULL])
def test_compiled_covariance_propagation_matches_dense(n: int) -> None:
    rng = np.random.default_rng(n)
    A = rng.normal(size=(n, n))
    P = A @ A.T
    noise = np.abs(rng.normal(size=12)) * 1e-3
    acc = np.zeros(M.ACC_SIZE)
    C = rotvec_to_dcm(np.array([0.1, -0.2, 0.7]))
    f_b, w_b, T = np.array([0.3, -0.5, -9.7]), np.array([0.02, -0.01, 0.3]), 0.05
    acc[M.ACC_T] = T
    acc[M.ACC_FB] = f_b * T
    acc[M.ACC_WB] = w_b * T
    acc[M.ACC_C] = C.ravel() * T
    Phi, Qd = M.error_transition(C, f_b, w_b, T, n, noise)
    ref = kalman.symmetrize(Phi @ P @ Phi.T + Qd)
    Pc = P.copy()
    assert M.propagate_covariance(Pc, acc, noise)
    np.testing.assert_allclose(Pc, ref, rtol=1e-12, atol=1e-12)
    assert (Pc == Pc.T).all()


def test_rodrigues_and_propagate_nominal_match_strapdown() -> None:
    from iotnav import strapdown

    C = rotvec_to_dcm(np.array([0.3, -1.2, 2.0]))
    v, p = np.array([10.0, -3.0, 0.5]), np.array([100.0, 20.0, -5.0])
    f, w, g, dt = np.array([0.4, -0.2, -9.6]), np.array([0.05, -0.3, 0.8]), np.array([0.0, 0.0, 9.8]), 0.01
    C_ref, v_ref, p_ref = strapdown.step(C, v, p, f, w, dt, g)
    C1, v1, p1 = C.copy(), v.copy(), p.copy()
    M.propagate_nominal(C1, v1, p1, f, w, dt, g, np.zeros(M.ACC_SIZE))
    np.testing.assert_allclose(C1, C_ref, rtol=0.0, atol=1e-15)
    np.testing.assert_allclose(v1, v_ref, rtol=0.0, atol=1e-13)
    np.testing.assert_allclose(p1, p_ref, rtol=0.0, atol=1e-12)
