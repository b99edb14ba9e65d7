"""Tracking filter: transition closed form, a slowly moving node heard from one passing anchor."""

from __future__ import annotations

import numpy as np
import pandas as pd
import pytest

from iotnav.nodes.multilateration import solve_position
from iotnav.nodes.ranging import radio
from iotnav.nodes.simulate import RadioSimConfig, loop_track, simulate_rssi
from iotnav.nodes.tracking import NodeTracker, TrackerConfig, track_node, transition


def test_transition_is_the_integrated_white_acceleration_model() -> None:
    F, Q = transition(2.0, 0.5)
    assert F[0, 2] == 2.0 and F[1, 3] == 2.0 and F[0, 0] == 1.0
    # q dt^3/3, q dt^2/2, q dt for dt = 2, q = 0.5
    assert Q[0, 0] == pytest.approx(0.5 * 8 / 3)
    assert Q[0, 2] == pytest.approx(0.5 * 4 / 2)
    assert Q[2, 2] == pytest.approx(1.0)
    assert Q[0, 1] == 0.0


def test_time_going_backwards_is_an_error() -> None:
    m = radio("lora-sf7")
    trk = NodeTracker(m)
    rng = np.random.default_rng(0)
    for k in range(40):
        a = np.array([*rng.uniform(-300, 300, 2), 0.0])
        trk.step(float(k), a, np.zeros((2, 2)), -80.0 + rng.normal())
    assert trk.initialised
    with pytest.raises(ValueError, match="backwards"):
        trk.step(1.0, np.zeros(3), np.zeros((2, 2)), -80.0)


def test_moving_node_tracked_from_one_moving_anchor() -> None:
    # A node walks north at 0.25 m/s for 40 min; one vehicle circles (radius 300 m) around the
    # area, beaconing every 5 s (SF7 at 1 % duty cycle allows 4.1 s). The filter follows the node; a static fit of all reports
    # cannot (it lands near the mean position).
    m = radio("lora-sf7")
    t = np.arange(0.0, 2401.0, 1.0)
    anchor = loop_track([0.0, 0.0], 300.0, 10.0, t, std_m=3.0)
    node = pd.DataFrame({"node_id": "N1", "t": t, "north": -300.0 + 0.25 * t, "east": 50.0, "down": 1.5})
    cfg = RadioSimConfig(packet_loss=0.1, beacon_interval_s=5.0)
    final_err, static_err, nees = [], [], []
    for seed in range(6):
        rng = np.random.default_rng(seed)
        rep = simulate_rssi(anchor, node, m, cfg, rng)
        tt = rep["t"].to_numpy()
        A = np.column_stack([np.interp(tt, t, anchor[c].to_numpy()) for c in ("north", "east", "down")])
        A[:, :2] += rng.normal(0.0, 3.0, (tt.size, 2))
        C = np.broadcast_to(9.0 * np.eye(2), (tt.size, 2, 2))
        res = track_node(tt, A, C, rep["rssi_dbm"].to_numpy(), m, 1.5, TrackerConfig(accel_psd=1e-4))
        truth_end = np.array([-300.0 + 0.25 * tt[-1], 50.0])
        e = res.x[-1, :2] - truth_end
        final_err.append(np.linalg.norm(e))
        nees.append(e @ np.linalg.solve(res.P[-1, :2, :2], e))
        est = solve_position(A, rep["rssi_dbm"].to_numpy(), m, C, 1.5)
        static_err.append(np.linalg.norm(est.p_ne - truth_end))
        assert res.accepted.mean() > 0.9
    assert np.median(final_err) < 80.0
    assert np.median(final_err) < 0.3 * np.median(static_err)
    assert np.mean(nees) < 6.0
