"""The integrity guard's compiled fix-rate step: its dynamics window over many fixes."""

from __future__ import annotations

import math

import numpy as np
import pytest

from iotnav.engines import integrity as ig
from iotnav.engines.base import GnssSample
from iotnav.engines.integrity_fix import INITIAL_CAPACITY

RATE_HZ = 10.0  # fixes per second: the window holds 600, more than the queues' first capacity
DECEL = 1.0  # m/s^2, constant: every rate between fixes is this
V0 = 90.0  # m/s at t = 0
K_N = 111_000.0  # m per degree of latitude, roughly: positions only need to move north


def _fix(t: float) -> GnssSample:
    v = V0 - DECEL * t
    north = V0 * t - 0.5 * DECEL * t * t
    return GnssSample(t, 45.0 + north / K_N, 7.0, 300.0, vn=v, ve=0.0, vd=0.0, h_acc_m=2.0, s_acc_mps=0.2)


def test_dynamics_window_top_speed_and_rates_over_a_long_decreasing_run() -> None:
    g = ig.IntegrityGuard()
    c = g.config
    times = np.arange(int(80.0 * RATE_HZ)) / RATE_HZ
    for t in times:
        assert g.on_fix(_fix(float(t))) is None  # no engine row: nothing to compare, no request
        # top speed of the fixes of the last dynamics_window_s: the oldest of them (speeds decrease)
        in_window = times[(times >= t - c.dynamics_window_s) & (times <= t)]
        assert g.st[ig.S_SPEED_MAX] == pytest.approx(V0 - DECEL * in_window[0], rel=1e-12)
    assert g.buf.shape[1] > INITIAL_CAPACITY  # the queues grew past their first size
    # rates of a constant deceleration along north: speed and velocity rates DECEL, no turning
    assert g.st[ig.S_A_S] == pytest.approx(c.dynamics_margin * DECEL, rel=1e-9)
    assert g.st[ig.S_A_H] == pytest.approx(c.dynamics_margin * DECEL, rel=1e-9)
    assert g.st[ig.S_W] == c.yaw_rate_floor_rad_s
    assert g.st[ig.S_A_RMS] == pytest.approx(max(DECEL, c.accel_floor_mps2), rel=1e-9)
    assert g.counts == {"fixes_checked": 0, "reinitialised": 0}
    assert g.st[ig.S_FIX_T] == times[-1]
    assert math.isclose(g.st[ig.S_FIX_VN], V0 - DECEL * times[-1])
