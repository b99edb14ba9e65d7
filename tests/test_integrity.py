"""The integrity guard (:mod:`iotnav.engines.integrity`): re-initialisation, outage fallback, NEES."""

from __future__ import annotations

import math
from typing import Any

import numpy as np
import pytest

from iotnav.engines.base import (
    GnssSample,
    ImuSample,
    Output,
    TangentPlane,
    output_at,
    output_without_position,
)
from iotnav.engines.integrity import DR_VELOCITY_SOURCE, IntegrityEngine

FRAME = TangentPlane(45.0, 7.0, 100.0)
SPEED = 10.0  # m/s, due north


class _Toy:
    """An engine that reports the truth (north at SPEED) plus ``offset_m``, with ``std_m``.

    ``diverge`` multiplies its speed once no fix has come for 2 s (a bad dead reckoner).
    It has a position once it has seen ``fixes_to_start`` fixes.
    """

    made = 0

    def __init__(self, offset_m: float = 0.0, std_m: float = 1.0, diverge: float = 1.0) -> None:
        _Toy.made += 1
        self.events: list[dict[str, Any]] = []
        self.offset_m, self.std_m, self.diverge = offset_m, std_m, diverge
        self.fixes = 0
        self.t_fix = -math.inf
        self.north = 0.0
        self.t = 0.0

    @property
    def mount_yaw_rad(self) -> float:
        return 0.0

    def summary(self) -> dict[str, Any]:
        return {"toy": True}

    def step(self, s: Any) -> Output | None:
        if isinstance(s, GnssSample):
            self.fixes += 1
            self.t_fix = s.t
            self.north = SPEED * s.t
            self.t = s.t
            return None
        dt = s.t - self.t
        self.t = s.t
        v = SPEED * (self.diverge if s.t - self.t_fix > 2.0 else 1.0)
        self.north += v * dt
        if self.fixes < 2:
            return output_without_position(s.t, (0.0, 0.0, 0.0), False)
        r = np.array([self.north + self.offset_m, 0.0, 0.0])
        return output_at(
            s.t, FRAME, r, np.array([v, 0.0, 0.0]), (0.0, 0.0, 0.0), False, (self.std_m,) * 2, "dr"
        )


def _fix(t: float) -> GnssSample:
    lat, lon, h = FRAME.from_ned(np.array([SPEED * t, 0.0, 0.0]))
    return GnssSample(t, lat, lon, h, vn=SPEED, ve=0.0, vd=0.0, h_acc_m=1.0, s_acc_mps=0.1, speed_mps=SPEED)


def _run(eng: Any, t_end: float, outage: tuple[float, float] = (math.inf, math.inf)) -> list[Output]:
    out = []
    imu = ImuSample(0.0, np.zeros(3), np.zeros(3))
    for k in range(int(t_end * 10)):
        t = k * 0.1
        if k % 10 == 0 and not outage[0] <= t < outage[1]:
            eng.step(_fix(t))
        o = eng.step(imu._replace(t=t))
        if o is not None:
            out.append(o)
    return out


def test_a_wrong_engine_is_reinitialised_and_fixes_are_used_again() -> None:
    made = []

    def factory() -> _Toy:
        made.append(1)
        # the first engine is forced 200 m off (a wrong state it never leaves); the next is right
        return _Toy(offset_m=200.0 if len(made) == 1 else 0.0)

    eng = IntegrityEngine(factory)
    out = _run(eng, 60.0)
    ev = [e for e in eng.events if e["type"] == "reinitialised"]
    assert len(ev) == 1 and len(made) == 2
    assert ev[0]["reason"] in ("windowed_nis", "consecutive_rejections")
    assert ev[0]["nis_window_sum"] > ev[0]["nis_window_bound"] and ev[0]["distance_m"] > 150.0
    assert ev[0]["t"] <= 21.0  # once the holdoff and the window allow it
    # after it: the fresh engine's outputs, on the truth
    late = [o for o in out if o.t > 40.0]
    assert all(abs(o.north - SPEED * o.t) < 1.0 for o in late)
    assert eng.summary()["integrity"]["reinitialised"] == 1


def test_a_consistent_engine_is_never_reinitialised() -> None:
    eng = IntegrityEngine(lambda: _Toy(offset_m=0.5, std_m=1.0))
    _run(eng, 120.0)
    assert not [e for e in eng.events if e["type"] == "reinitialised"]


def test_a_diverging_dead_reckoner_falls_back_to_the_last_fix_at_its_velocity() -> None:
    eng = IntegrityEngine(lambda: _Toy(diverge=3.0))
    out = _run(eng, 60.0, outage=(30.5, 50.5))
    inside = [o for o in out if 35.0 <= o.t < 50.5]
    assert inside and all(o.source == DR_VELOCITY_SOURCE for o in inside)
    assert all(abs(o.north - SPEED * o.t) < 1.0 for o in inside)  # truth is constant velocity here
    ev = [e for e in eng.events if e["type"] == "integrity_fallback"]
    assert len(ev) == 1 and ev[0]["reason"] in ("speed", "position", "reach")
    # its sigma grows with the time since the fix
    assert inside[-1].std_north > inside[0].std_north > 0.0
    # after the outage the engine is back
    assert all(o.source == "dr" for o in out if o.t > 55.0)


def test_a_good_dead_reckoner_is_kept_through_an_outage() -> None:
    eng = IntegrityEngine(lambda: _Toy())
    out = _run(eng, 60.0, outage=(30.5, 50.5))
    assert all(o.source == "dr" for o in out if o.t > 1.0)
    assert not [e for e in eng.events if e["type"] == "integrity_fallback"]


def test_before_the_engine_has_a_position_the_fixes_are_reported() -> None:
    eng = IntegrityEngine(lambda: _Toy())
    out = _run(eng, 1.5)
    first = [o for o in out if o.t < 1.0]  # the toy needs two fixes
    assert first and all(o.source == DR_VELOCITY_SOURCE for o in first)
    assert all(o.north == pytest.approx(SPEED * o.t, abs=1e-6) for o in first)
