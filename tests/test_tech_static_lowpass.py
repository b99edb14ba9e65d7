"""Blocks 3 (static detection) and 4 (3-level low-pass) on hand-built inputs."""

from __future__ import annotations

import numpy as np

from iotnav.techniques.lowpass3 import Lowpass3, Lowpass3Config
from iotnav.techniques.static import StaticConfig, StaticDetector


def _det(**kw: float) -> StaticDetector:
    return StaticDetector(StaticConfig(acc_tau_s=0.0, speed_window=1, **kw))


def test_static_requires_low_speed_and_low_horizontal_acceleration() -> None:
    d = _det()
    d.update_speed(0.0, 0.2)
    assert d.step(0.1, np.array([0.05, 0.05, -9.8]))  # |a_h| = 0.071 < 0.125
    assert not d.step(0.2, np.array([0.10, 0.10, -9.8]))  # 0.141 > 0.125
    d.update_speed(0.3, 0.8)  # above 0.5 m/s
    assert not d.step(0.4, np.array([0.0, 0.0, -9.8]))


def test_static_speed_moving_average_and_timeout() -> None:
    d = StaticDetector(StaticConfig(acc_tau_s=0.0, speed_window=3))
    for k, v in enumerate([1.2, 0.1, 0.1]):  # mean 0.47 < 0.5
        d.update_speed(float(k), v)
    assert abs(d.speed - 0.4666666) < 1e-6
    assert d.step(2.5, np.zeros(3))
    assert d.step(10.0, np.zeros(3))  # speed older than 3 s: accelerometer alone


def test_static_exit_is_immediate_on_one_large_sample() -> None:
    d = StaticDetector(StaticConfig(acc_tau_s=1.0))
    d.update_speed(0.0, 0.0)
    for k in range(50):
        assert d.step(0.01 * k, np.zeros(3)) or (k == 0 and False)
    assert not d.step(0.51, np.array([0.4, 0.0, 0.0]))  # 0.4 > 3 * 0.125


def test_lowpass3_levels_and_slowing_updates() -> None:
    lp = Lowpass3(Lowpass3Config(n1=3, n2=2, n3=2))
    outs = []
    for k in range(24):
        o = lp.push(np.array([float(k), 0.0, 0.0]))
        outs.append(None if o is None else float(o[0]))
    changed = [k for k, o in enumerate(outs) if o is not None]
    # level 2 after fixes 3 and 6 (every n1); level 3 from fix 6 on: every n1*n2 = 6 fixes
    assert changed == [2, 5, 11, 17, 23]
    assert outs[2] == 1.0  # mean of 0, 1, 2
    assert outs[5] == 2.5  # level 3: mean of level 2 {1, 4}
    assert outs[11] == (2.5 + 8.5) / 2  # level 3 holds {2.5, 8.5}
    assert outs[23] == (14.5 + 20.5) / 2  # circular level 3 of size 2
    assert lp.level == 3
    lp.reset()
    assert lp.output() is None and lp.level == 0


def test_static_hysteresis_ends_on_acceleration_or_a_clear_speed() -> None:
    for exit_speed, stays in ((0.0, False), (1.5, True)):
        d = StaticDetector(StaticConfig(acc_tau_s=0.0, speed_window=1, exit_speed_mps=exit_speed))
        d.update_speed(0.0, 0.1)
        assert d.step(0.1, np.zeros(3))
        d.update_speed(1.0, 0.9)  # GPS speed noise of a standing receiver in multipath
        assert d.step(1.1, np.zeros(3)) is stays
    d = StaticDetector(StaticConfig(acc_tau_s=0.0, speed_window=1, exit_speed_mps=1.5))
    d.update_speed(0.0, 0.1)
    assert d.step(0.1, np.zeros(3))
    d.update_speed(1.0, 2.0)  # clearly moving
    assert not d.step(1.1, np.zeros(3))
    d.update_speed(2.0, 0.1)
    assert d.step(2.1, np.zeros(3))
    assert not d.step(2.2, np.array([0.5, 0.0, -9.8]))  # the accelerometer ends it at once
    d.update_speed(3.0, 0.9)
    assert not d.step(3.1, np.zeros(3))  # entering still needs the speed below 0.5 m/s


def test_lowpass3_counts_the_fixes_behind_its_output() -> None:
    lp = Lowpass3(Lowpass3Config(n1=3, n2=2, n3=2))
    counts = []
    for k in range(18):
        lp.push(np.array([float(k), 0.0, 0.0]))
        counts.append(lp.n_fixes)
    # level 2 after 3 fixes (3 averaged); level 3 from fix 6 (2 x 3); two level-3 slots from fix 12
    assert counts[:3] == [0, 0, 3] and counts[5] == 6 and counts[11] == 12 and counts[17] == 12


def test_static_does_not_fire_at_highway_speed_when_the_gnss_speed_goes_stale() -> None:
    # issue 16: a car at 17 m/s enters an outage; the accelerometer is quiet (constant speed)
    # and the fusion filter's dead-reckoned speed has decayed to 0.2 m/s. Before the fix the
    # stale GPS speed was ignored and the fallback alone declared the car static.
    d = StaticDetector(StaticConfig(acc_tau_s=0.0, speed_window=1, exit_speed_mps=1.5))
    d.update_speed(0.0, 17.0)
    quiet = np.array([0.01, 0.0, -9.8])
    assert not d.step(0.5, quiet, fallback_speed_mps=17.0)
    for k in range(1, 200):  # 20 s of outage, speed older than the 3 s timeout
        assert not d.step(3.0 + 0.1 * k, quiet, fallback_speed_mps=0.2)
    # a car that was slow at the last fix may still be declared static in the outage
    d2 = StaticDetector(StaticConfig(acc_tau_s=0.0, speed_window=1))
    d2.update_speed(0.0, 0.1)
    assert d2.step(10.0, quiet, fallback_speed_mps=0.1)
    assert not d2.step(10.1, quiet, fallback_speed_mps=3.0)  # but not if it dead-reckons moving
