"""Latency compensation: a toy 1-D engine (position integrates a velocity sample) with fixes."""

from __future__ import annotations

from typing import Any, NamedTuple

import pytest

from iotnav.techniques.latency import LatencyBuffer


class Sample(NamedTuple):
    t: float
    v: float


class Fix(NamedTuple):
    t_valid: float
    p: float


class Toy:
    """p' = v (sample held over its interval); a fix sets p; output (t, p, fixed)."""

    def __init__(self) -> None:
        self.p = 0.0
        self.last: Sample | None = None
        self.applied: list[float] = []

    def snapshot(self) -> Any:
        return (self.p, self.last, tuple(self.applied))

    def restore(self, snap: Any) -> None:
        self.p, self.last, applied = snap
        self.applied = list(applied)

    def propagate(self, s: Sample) -> None:
        if self.last is not None:
            self.p += self.last.v * (s.t - self.last.t)
        self.last = s

    def apply_fix(self, f: Fix) -> None:
        self.p = f.p
        self.applied.append(f.t_valid)

    def output(self, t: float, fixed: bool) -> tuple[float, float, bool]:
        return (t, self.p, fixed)


DT = 0.01
SAMPLES = [Sample(round(k * DT, 10), 1.0 + 0.1 * k) for k in range(600)]


def _run(
    fixes_by_arrival: list[tuple[float, Fix]], max_latency_s: float = 2.0
) -> tuple[Toy, list[Any], list[Any]]:
    """Feed samples and fixes (arrival time, fix); returns engine, real-time and revised outputs."""
    eng, buf = Toy(), LatencyBuffer(max_latency_s=max_latency_s)
    rt: list[Any] = []
    rev: list[Any] = []
    outcomes = []
    pending = sorted(fixes_by_arrival, key=lambda a: a[0])
    for s in SAMPLES:
        while pending and pending[0][0] <= s.t + 1e-12:
            outcomes.append(buf.process_fix(eng, pending.pop(0)[1]))
            if outcomes[-1].replayed:
                n = len(outcomes[-1].replayed)
                rev[-n:] = list(outcomes[-1].replayed)
        out = buf.process_imu(eng, s)
        rt.append(out)
        rev.append(out)
    return eng, rt, rev


FIXES = [Fix(1.0, 10.0), Fix(2.0, 30.0), Fix(3.0, 20.0)]


@pytest.mark.parametrize("latency", [0.5, 1.0, 2.0])
def test_delayed_fixes_give_the_zero_latency_state_and_revised_track(latency: float) -> None:
    eng0, rt0, _ = _run([(f.t_valid, f) for f in FIXES])
    eng, rt, rev = _run([(f.t_valid + latency, f) for f in FIXES])
    assert eng.p == pytest.approx(eng0.p, abs=1e-9)
    assert eng.applied == [1.0, 2.0, 3.0]
    assert [r[0] for r in rev] == [r[0] for r in rt0]
    for a, b in zip(rev, rt0, strict=True):
        assert a[1] == pytest.approx(b[1], abs=1e-9)
    # the real-time track is not revised: right after t_valid it still shows the old position
    k = round((1.0 + latency / 2) / DT)
    assert rt[k][1] != pytest.approx(rt0[k][1], abs=1e-6)


def test_fix_at_zero_latency_is_applied_at_its_epoch_with_hand_computed_position() -> None:
    _eng, rt, _ = _run([(1.0, Fix(1.0, 10.0))])
    k = 100  # t = 1.0
    assert rt[k] == (1.0, 10.0, True)
    # one step later: p = 10 + v_100 * dt with v_100 = 1 + 0.1 * 100 = 11
    assert rt[k + 1][1] == pytest.approx(10.0 + 11.0 * DT, abs=1e-12)


def test_out_of_order_fixes_are_applied_in_t_valid_order() -> None:
    in_order = _run([(2.5, Fix(1.0, 10.0)), (2.6, Fix(2.0, 30.0))])[0]
    reversed_ = _run([(2.5, Fix(2.0, 30.0)), (2.6, Fix(1.0, 10.0))])[0]
    assert reversed_.p == pytest.approx(in_order.p, abs=1e-9)
    assert reversed_.applied[-2:] == [1.0, 2.0]


def test_fix_older_than_the_buffer_is_rejected() -> None:
    eng, buf = Toy(), LatencyBuffer(max_latency_s=2.0)
    for s in SAMPLES[:400]:  # up to t = 3.99
        buf.process_imu(eng, s)
    out = buf.process_fix(eng, Fix(1.5, 99.0))
    assert out.status == "rejected"
    assert "buffer" in out.reason
    assert eng.p != 99.0
    span = buf.entries[-1].t - buf.entries[0].t
    assert span <= 2.0 + DT


def test_fix_from_the_future_waits_for_the_imu() -> None:
    eng, buf = Toy(), LatencyBuffer()
    for s in SAMPLES[:100]:
        buf.process_imu(eng, s)
    assert buf.process_fix(eng, Fix(1.5, 7.0)).status == "pending"
    outs = [buf.process_imu(eng, s) for s in SAMPLES[100:200]]
    fixed = [o for o in outs if o[2]]
    assert fixed == [(1.5, 7.0, True)]


def test_capacity_bounds_the_buffer() -> None:
    eng, buf = Toy(), LatencyBuffer(max_latency_s=10.0, capacity=50)
    for s in SAMPLES:
        buf.process_imu(eng, s)
    assert len(buf.entries) == 50
