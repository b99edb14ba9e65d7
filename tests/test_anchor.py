"""Anchor-node engine: IMU-rate output, prediction through tunnels, satellite-count rule (seeded)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pandas as pd

from iotnav import sim
from iotnav.engines.anchor import AnchorConfig, AnchorEngine, AnchorKFConfig, transition
from iotnav.engines.base import run_batch
from iotnav.io import ingest


def test_transition_matches_paper_matrices() -> None:
    F, B, Q = transition(0.01, 0.5)
    assert np.allclose(F[:3, 3:], 0.01 * np.eye(3)) and np.allclose(F[:3, :3], np.eye(3))
    assert np.allclose(B[:3], 0.5e-4 * np.eye(3)) and np.allclose(B[3:], 0.01 * np.eye(3))
    assert np.allclose(Q[3:, 3:], 0.005 * np.eye(3))
    # constant acceleration: x_k = F x + B u integrates p = a t^2 / 2 exactly
    x = np.zeros(6)
    for _ in range(100):
        x = F @ x + B @ np.array([1.5, 0.0, 0.0])
    assert np.isclose(x[0], 0.5 * 1.5 * 1.0**2) and np.isclose(x[3], 1.5)


def test_car_tunnel_rate_and_outage(tmp_path: Path) -> None:
    """100 Hz output from 1 Hz GNSS; through a 40 s tunnel the filter predicts, std grows."""
    r = sim.build("car-tunnel", seed=0, overrides={"duration_s": 200.0})
    sim.write(r, tmp_path)
    log = ingest([tmp_path])
    eng = AnchorEngine()
    df = run_batch(eng, log)
    assert len(df) == len(log.imu)
    t = df["t"].to_numpy()
    assert abs(np.median(np.diff(t)) - 0.01) < 1e-3
    ok = df.dropna(subset=["lat"])
    assert len(ok) > 0.98 * len(df)
    valid_fix_rate = log.gnss["valid"].sum() / (log.gnss["t"].iloc[-1] - log.gnss["t"].iloc[0])
    assert len(ok) / (ok["t"].iloc[-1] - ok["t"].iloc[0]) > 80 * valid_fix_rate
    a, b = r.config.gnss.outages_s[0]
    tun = ok[(ok["t"] > a + 1.0) & (ok["t"] < b)]
    assert (tun["source"] == "dr").all()
    std = np.hypot(tun["std_north"].to_numpy(), tun["std_east"].to_numpy())
    assert np.all(np.diff(std) >= 0) and std[-1] > 10 * std[0]
    # the position keeps moving at driving speed through the tunnel
    dist = np.hypot(np.diff(tun["north"]), np.diff(tun["east"])).sum()
    true_dist = np.hypot(np.diff(r.truth.north), np.diff(r.truth.east))[
        (r.truth.t[1:] > a + 1.0) & (r.truth.t[1:] < b)
    ].sum()
    assert 0.8 * true_dist < dist < 1.2 * true_dist
    # after the tunnel the filter re-converges
    after = ok[(ok["t"] > b + 1.0) & (ok["t"] < b + 9.0)]
    assert len(after) > 700 and (after["source"] == "fix").mean() > 0.9


def test_fixes_with_four_satellites_or_fewer_are_rejected(tmp_path: Path) -> None:
    r = sim.build("car-tunnel", seed=1, overrides={"duration_s": 60.0})
    sim.write(r, tmp_path)
    log = ingest([tmp_path])
    g = log.gnss.copy()
    few = (g["t"] >= 30.0) & (g["t"] <= 40.0)
    g.loc[few, "num_sv"] = np.where(g.loc[few, "t"].to_numpy() % 2 == 0, 4, 3).astype(np.int16)
    log.gnss = g
    eng = AnchorEngine()
    df = run_batch(eng, log)
    rej = [e for e in eng.events if e["type"] == "fix_rejected" and e["reason"] == "num_sv"]
    assert sorted(e["t"] for e in rej) == list(g.loc[few, "t"])
    assert all(e["num_sv"] <= 4 for e in rej)
    span = df[(df["t"] > 31.6) & (df["t"] < 40.0)]
    assert (span["source"] == "dr").all()
    # configurable: requiring 3 satellites accepts them
    eng3 = AnchorEngine(AnchorConfig(kf=AnchorKFConfig(min_satellites=3)))
    run_batch(eng3, log)
    assert not [e for e in eng3.events if e["type"] == "fix_rejected" and e["reason"] == "num_sv"]
    assert isinstance(df, pd.DataFrame)


def test_growing_q_reproduces_a_constant_acceleration_error() -> None:
    """``q(s) = 3 sigma_a^2 s`` through ``F`` gives ``var p = sigma_a^2 s^4 / 4`` (module docstring)."""
    sigma_a2, dt = 0.04, 0.01
    P = np.zeros((6, 6))
    for k in range(3000):
        F, _B, Q = transition(dt, 3.0 * sigma_a2 * (k + 0.5) * dt)
        P = F @ P @ F.T + Q
    s = 30.0
    assert np.isclose(P[0, 0], sigma_a2 * s**4 / 4, rtol=1e-3)
    assert np.isclose(P[0, 3], sigma_a2 * s**3 / 2, rtol=1e-3)
    assert np.isclose(P[3, 3], 1.5 * sigma_a2 * s**2, rtol=1e-3)
