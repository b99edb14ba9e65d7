"""Fleet metrics on hand-made inputs, and the seeded fleet days."""

from __future__ import annotations

import math

import numpy as np
import pandas as pd
import pytest

from iotnav.eval import tracker_metrics as M
from iotnav.geo import LocalFrame
from iotnav.sim.fleet_days import fleet_day
from iotnav.tracker import TRIP_COLUMNS


def _table(rows: list[tuple[str, float, float]]) -> pd.DataFrame:
    df = pd.DataFrame(
        [{c: 0.0 for c in TRIP_COLUMNS} | {"kind": k, "t_start": a, "t_end": b} for k, a, b in rows]
    )
    return df[list(TRIP_COLUMNS)]


def test_trip_matching_and_false_trips() -> None:
    rep = _table(
        [("stop", 0, 100), ("trip", 100, 400), ("stop", 400, 500), ("trip", 500, 520), ("trip", 900, 950)]
    )
    truth = [(110.0, 390.0), (600.0, 700.0)]
    assert M.false_trips(rep, truth) == 2  # 500-520 and 900-950 overlap no truth trip
    timing = M.trip_timing(rep, truth)
    assert timing[0] == (10.0, 10.0)
    assert all(math.isnan(x) for x in timing[1])


def test_fence_exits_and_growth() -> None:
    fr = LocalFrame(45.0, 7.0, 0.0)
    north = np.array([0.0, 20.0, 0.0, 16.0, 14.0, 30.0])  # out, in, out, in, out: 3 exits of 15 m
    lat, lon, _ = fr.from_ned(np.column_stack([north, np.zeros(6), np.zeros(6)]))
    assert M.fence_exits(lat, lon, (45.0, 7.0), 15.0) == 3
    assert M.apparent_path_m(lat, lon) == pytest.approx(20 + 20 + 16 + 2 + 16, abs=1e-3)
    assert M.growth_pct(1.0, 200.0) == 0.5 and math.isnan(M.growth_pct(1.0, 0.0))
    assert M.distance_error_pct(98.0, 100.0) == pytest.approx(-2.0)


def test_fleet_days_are_seeded_and_shaped() -> None:
    a, b = fleet_day("stop-and-go", seed=4), fleet_day("stop-and-go", seed=4)
    pd.testing.assert_frame_equal(a.gnss, b.gnss)
    assert a.trips == [(600.0, a.trips[0][1])] and a.trips[0][1] <= 2400.0
    sp = a.truth["speed"].to_numpy(float)
    moving = sp[(a.truth["t"] >= 600) & (a.truth["t"] < 2400)]
    assert moving.max() <= 5.0 and moving[moving > 0].min() >= 1.0 and (moving == 0).any()  # halts
    s = fleet_day("sparse-drive", seed=4)
    assert np.allclose(np.diff(s.gnss["t"].to_numpy(float)), 30.0)
    with pytest.raises(ValueError, match="unknown fleet day"):
        fleet_day("nope")
