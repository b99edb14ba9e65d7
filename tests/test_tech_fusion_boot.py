"""Block 6 (fusion KF) dead reckoning and block 1 (last known position) logic and store."""

from __future__ import annotations

import json
import math
import os
from pathlib import Path

import numpy as np
import pytest

from iotnav.techniques.fusion_kf import POS, VEL, FusionConfig, FusionKF, gnss_noise
from iotnav.techniques.last_position import (
    LastPositionConfig,
    LastPositionLogic,
    LastPositionStore,
    StoredPosition,
    fix_rejection_reason,
)


def test_fusion_dead_reckons_through_30s_gap_with_growing_covariance() -> None:
    rng = np.random.default_rng(5)
    kf = FusionKF()
    kf.initialise(np.zeros(3), np.eye(3), np.array([5.0, 0.0, 0.0]))
    C = np.eye(3)
    dt = 0.05
    t = 0.0
    stds = []
    for k in range(int(60 / dt)):  # 1 Hz fixes for 20 s, 30 s gap, 10 s fixes
        t = (k + 1) * dt
        kf.predict(rng.normal(0.0, 0.02, 3), C, dt)
        truth = np.array([5.0 * t, 0.0, 0.0])
        in_gap = 20.0 <= t < 50.0
        if (k + 1) % 20 == 0 and not in_gap:
            kf.update_position(truth + rng.normal(0.0, 1.0, 3), np.eye(3))
            kf.update_velocity(np.array([5.0, 0.0]), 0.1)
        if in_gap:
            stds.append(math.sqrt(kf.P[0, 0]))
            if abs(t - 49.95) < 1e-6:
                assert abs(kf.x[POS][0] - 5.0 * t) < 15.0  # dead-reckoned, not lost
    assert np.all(np.diff(stds) > 0)  # covariance grows monotonically through the gap
    assert stds[-1] > 5 * stds[0]
    assert abs(kf.x[VEL][0] - 5.0) < 0.3


def test_fix_acceptance_reasons() -> None:
    c = LastPositionConfig(min_num_sv=5)
    assert fix_rejection_reason(False, 45.0, 7.0, 2.0, 8, c) == "invalid"
    assert fix_rejection_reason(True, math.nan, 7.0, 2.0, 8, c) == "no_position"
    assert fix_rejection_reason(True, 45.0, 7.0, 10.5, 8, c) == "pdop"
    assert fix_rejection_reason(True, 45.0, 7.0, 10.0, 8, c) is None  # PDOP <= 10 accepted
    assert fix_rejection_reason(True, 45.0, 7.0, 2.0, 4, c) == "num_sv"


def test_moved_while_off_event() -> None:
    stored = StoredPosition(45.0, 7.0, 200.0)
    far = LastPositionLogic(LastPositionConfig(moved_threshold_m=50.0), stored)
    ev = far.first_fix(10.0, 45.001, 7.0)  # ~111 m North
    assert ev is not None and ev["type"] == "moved_while_off"
    assert ev["distance_m"] == pytest.approx(111.2, abs=0.5)
    near = LastPositionLogic(LastPositionConfig(moved_threshold_m=50.0), stored)
    assert near.first_fix(10.0, 45.0002, 7.0) is None  # ~22 m


def test_save_interval() -> None:
    logic = LastPositionLogic(LastPositionConfig(save_interval_s=60.0))
    assert [logic.due(t) for t in (0.0, 30.0, 60.0, 61.0, 125.0)] == [True, False, True, False, True]


def test_store_round_trip_and_atomic_write(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    path = tmp_path / "dev42.json"
    store = LastPositionStore(path)
    assert store.load() is None
    first = StoredPosition(45.0, 7.5, 230.0, 12.0, 1.5)
    store.save(first)
    assert store.load() == first
    assert json.loads(path.read_text())["lat_deg"] == 45.0

    def boom(src: str, dst: str) -> None:  # power cut between temp write and rename
        raise OSError("power cut")

    monkeypatch.setattr(os, "replace", boom)
    with pytest.raises(OSError):
        store.save(StoredPosition(0.0, 0.0, 0.0))
    assert store.load() == first  # the old file is intact
    assert sorted(p.name for p in tmp_path.iterdir()) == ["dev42.json"]  # no temp left behind
    path.write_text("{not json")
    assert store.load() is None


def test_settling_gate_refuses_converging_first_fixes_without_stored_position() -> None:
    # cold start: PDOP 7 falling with a 20 s time constant towards 3 (as a converging receiver)
    logic = LastPositionLogic(LastPositionConfig())
    t = np.arange(25.0, 120.0)
    pdop = 3.0 * (1.0 + 1.33 * np.exp(-(t - 25.0) / 20.0))
    reasons = [
        logic.check_fix(True, 45.0, 7.0, float(p), 8, float(tk)) for tk, p in zip(t, pdop, strict=True)
    ]
    first = int(np.argmax([r is None for r in reasons]))
    assert all(r == "settling" for r in reasons[:first])
    # accepted at the first epoch whose PDOP fell by less than 5 % over the previous 10 s
    ratio = pdop[first] / pdop[first - 10]
    assert ratio >= 0.95 and pdop[first - 1] / pdop[first - 11] < 0.95
    assert 60.0 < t[first] < 100.0


def test_settling_gate_accepts_a_low_steady_pdop_at_once_and_ignores_stored_boots() -> None:
    logic = LastPositionLogic(LastPositionConfig())
    assert logic.check_fix(True, 45.0, 7.0, 1.8, 9, 0.0) is None  # PDOP <= 4 from the first fix
    logic = LastPositionLogic(LastPositionConfig())
    assert logic.check_fix(True, 45.0, 7.0, 6.0, 9, 0.0) == "settling"  # no history, PDOP > 4
    for k in range(1, 11):  # steady 6.0 for 10 s: settled
        r = logic.check_fix(True, 45.0, 7.0, 6.0, 9, float(k))
    assert r is None
    stored = LastPositionLogic(LastPositionConfig(), StoredPosition(45.0, 7.0, 200.0))
    assert stored.check_fix(True, 45.0, 7.0, 9.0, 9, 0.0) is None  # the paper's rule: PDOP <= 10
    off = LastPositionLogic(LastPositionConfig(settle_ratio=0.0))
    assert off.check_fix(True, 45.0, 7.0, 9.0, 9, 0.0) is None


def test_gnss_noise_prefers_receiver_accuracy_then_dop_then_default() -> None:
    cfg = FusionConfig(uere_m=3.0, default_dop=2.0, speed_noise_mps=0.3, min_pos_std_m=0.0)
    # receiver accuracy: h_acc is the horizontal DRMS, each axis gets h_acc^2 / 2
    R, sv = gnss_noise(0.014, 0.01, 0.06, math.nan, math.nan, cfg)
    np.testing.assert_allclose(np.diag(R), [0.000098, 0.000098, 0.0001])
    assert sv == 0.06
    # h_acc only: vertical = 1.5 x h_acc (VDOP = 1.5 HDOP), whatever the DOPs
    R, _ = gnss_noise(2.0, math.nan, math.nan, 1.0, 1.0, cfg)
    np.testing.assert_allclose(np.diag(R), [2.0, 2.0, 9.0])
    # DOPs: UERE x HDOP = 6 m is the 2D figure, s_h^2 = 36 / 2; s_v = 3 * sqrt(9 - 4)
    R, sv = gnss_noise(math.nan, math.nan, math.nan, 3.0, 2.0, cfg)
    np.testing.assert_allclose(np.diag(R), [18.0, 18.0, 45.0])
    assert sv == 0.3
    # nothing: default DOP 2 as HDOP, VDOP = 1.5 x 2: s_v = 3 * 3
    R, _ = gnss_noise(math.nan, math.nan, math.nan, math.nan, math.nan, cfg)
    np.testing.assert_allclose(np.diag(R), [18.0, 18.0, 81.0])
    # floor
    R, _ = gnss_noise(0.014, 0.01, 0.06, math.nan, math.nan, FusionConfig(min_pos_std_m=0.02))
    np.testing.assert_allclose(np.diag(R), [0.0004, 0.0004, 0.0004])


def test_ned_velocity_update_sets_all_three_components() -> None:
    kf = FusionKF()
    kf.initialise(np.zeros(3), np.eye(3))
    kf.update_velocity_ned(np.array([3.0, -4.0, 0.5]), 0.001)
    np.testing.assert_allclose(kf.x[VEL], [3.0, -4.0, 0.5], atol=1e-4)
