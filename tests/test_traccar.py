"""Each Traccar rule on a constructed sequence, against its documented behaviour.

Expected values are worked out by hand from the documentation of the keys (see
:mod:`iotnav.eval.traccar`). Positions differ in latitude only, by multiples of 1e-4 degree:
on Traccar's sphere (radius 6378.137 km) that is ``R * pi / 180 * 1e-4 = 11.1319 m``.
"""

from __future__ import annotations

import math

import numpy as np
import pandas as pd
import pytest

from iotnav.eval.traccar import TraccarConfig, TraccarCoordinates, TraccarFilter, traccar_rules

STEP_M = 6378137.0 * math.pi / 180.0 * 1e-4  # 11.1319 m


def _fixes(t: list[float], k_lat: list[float], **cols: list[object]) -> pd.DataFrame:
    n = len(t)
    df = pd.DataFrame(
        {
            "t": t,
            "lat_deg": 45.0 + 1e-4 * np.asarray(k_lat),
            "lon_deg": [7.0] * n,
            "valid": True,
            "speed_mps": 5.0,
        }
    )
    for k, v in cols.items():
        df[k] = v
    return df


def _cfg(**filters: object) -> TraccarConfig:
    return TraccarConfig(filter=TraccarFilter(enable=True, **filters))  # type: ignore[arg-type]


def test_defaults_keep_everything_and_sum_every_step() -> None:
    """All filters are off by default; the odometer adds every step, parked jitter included."""
    g = _fixes([0, 1, 2, 3, 4], [0, 1, 0, 1, 0], speed_mps=[0.0] * 5)
    r = traccar_rules(g)
    assert len(r.positions) == 5 and r.n_dropped == 0
    assert r.positions["distance_m"].tolist() == pytest.approx([0, STEP_M, STEP_M, STEP_M, STEP_M], rel=1e-9)
    assert r.odometer_m == pytest.approx(4 * STEP_M, rel=1e-9)  # 44.5 m gained while parked


def test_enable_gates_the_filters() -> None:
    g = _fixes([0, 0], [0, 0], valid=[False, False])
    r = traccar_rules(g, TraccarConfig(filter=TraccarFilter(invalid=True, duplicate=True)))
    assert r.n_dropped == 0


def test_invalid_zero_accuracy_future_past() -> None:
    g = pd.DataFrame(
        {
            "t": [0.0, 1.0, 2.0, 3.0, 1000.0, 5.0],
            "lat_deg": [45.0, 45.0, 0.0, 45.0, 45.0, 45.0],
            "lon_deg": [7.0, 7.0, 0.0, 7.0, 7.0, 7.0],
            "valid": [True, False, True, True, True, True],
            "speed_mps": 1.0,
            "h_acc_m": [5.0, 5.0, 5.0, 80.0, 5.0, 5.0],
        }
    )
    server = np.array([0.0, 1.0, 2.0, 3.0, 4.0, 1000.0])
    cfg = _cfg(invalid=True, zero=True, accuracy_m=50, future_s=60, past_s=60)
    r = traccar_rules(g, cfg, t_server=server)
    # row 1 invalid, row 2 at (0, 0), row 3 accuracy 80 > 50, row 4 996 s ahead of the
    # server (> 60), row 5 995 s behind it (> 60): only row 0 is stored
    assert r.positions["t"].tolist() == [0.0]
    assert r.dropped == {"invalid": 1, "zero": 1, "accuracy": 1, "future": 1, "past": 1}


def test_duplicate_min_period_static() -> None:
    g = _fixes([0, 0, 1, 2, 5, 6, 10], [0, 1, 2, 3, 4, 5, 6])
    r = traccar_rules(g, _cfg(duplicate=True))
    assert r.positions["t"].tolist() == [0, 1, 2, 5, 6, 10]  # the second t = 0 is a duplicate
    r = traccar_rules(g, _cfg(min_period_s=5))
    # compared with the last stored: 0 (0 s: not "more than 0") is kept, 1, 2 dropped, 5 kept,
    # 6 dropped (1 s after 5), 10 kept (5 s after 5: not less than 5)
    assert r.positions["t"].tolist() == [0, 0, 5, 10]
    g2 = _fixes([0, 1, 2], [0, 1, 2], speed_mps=[0.0, 0.5, 0.0])
    r = traccar_rules(g2, _cfg(static=True))
    assert r.positions["t"].tolist() == [1] and r.dropped == {"static": 2}


def test_distance_and_skip_limit() -> None:
    """filter.distance 20 m: a step of 11.1 m from the last stored is dropped, 22.3 m kept.

    With filter.skipLimit 30 s the rule does not apply after 30 s without a stored position.
    """
    g = _fixes([0, 1, 2, 3, 40], [0, 1, 2, 3, 4])
    r = traccar_rules(g, _cfg(distance_m=20))
    assert r.positions["t"].tolist() == [0, 2, 40]  # 3 is 11 m from 2; 40 is 22 m from 2
    assert r.positions["distance_m"].tolist() == pytest.approx([0, 2 * STEP_M, 2 * STEP_M], rel=1e-9)
    g = _fixes([0, 1, 45], [0, 1, 2])
    r = traccar_rules(g, _cfg(distance_m=20, skip_limit_s=30))
    assert r.positions["t"].tolist() == [0, 45]  # 45 s after the last stored: not filtered


def test_max_speed() -> None:
    """filter.maxSpeed 100 kn (51.4 m/s): a 100-step jump in 1 s (2147 kn) is dropped."""
    g = _fixes([0, 1, 2, 12], [0, 100, 1, 101])
    r = traccar_rules(g, _cfg(max_speed_kn=100))
    # t=2: 11.1 m in 2 s from t=0 (10.8 kn) kept; t=12: 1113 m in 10 s (216 kn) dropped
    assert r.positions["t"].tolist() == [0, 2]
    assert r.dropped == {"max_speed": 2}


def test_coordinates_min_error_holds_parked_position() -> None:
    """coordinates.minError 15 m: a change of 11.1 m keeps the last coordinates (distance 0)."""
    g = _fixes([0, 1, 2, 3], [0, 1, 2, 4])
    r = traccar_rules(g, TraccarConfig(coordinates=TraccarCoordinates(filter=True, min_error_m=15)))
    p = r.positions
    assert p["replaced"].tolist() == [False, True, False, False]
    assert p["lat"].tolist() == pytest.approx([45.0, 45.0, 45.0002, 45.0004], abs=1e-12)
    # t=2 is 22.3 m from the (held) 45.0; t=4 another 22.3 m
    assert p["distance_m"].tolist() == pytest.approx([0, 0, 2 * STEP_M, 2 * STEP_M], rel=1e-9)
    assert r.odometer_m == pytest.approx(4 * STEP_M, rel=1e-9)


def test_coordinates_max_error_only_for_invalid_positions() -> None:
    """coordinates.maxError 500 m: a 1113 m jump is held only when the position is invalid."""
    g = _fixes([0, 1, 2], [0, 100, 100], valid=[True, False, True])
    r = traccar_rules(g, TraccarConfig(coordinates=TraccarCoordinates(filter=True, max_error_m=500)))
    p = r.positions
    assert p["replaced"].tolist() == [False, True, False]
    assert p["valid"].tolist() == [True, True, True]  # the held position takes the last validity
    assert p["distance_m"].tolist() == pytest.approx([0, 0, 100 * STEP_M], rel=1e-9)


def test_no_position_rows_counted() -> None:
    g = _fixes([0, 1, 2], [0, 1, 2])
    g.loc[1, ["lat_deg", "lon_deg"]] = np.nan
    r = traccar_rules(g)
    assert len(r.positions) == 2 and r.dropped == {"no_position": 1}


def test_trip_report_from_speed_with_documented_defaults() -> None:
    """Speed 0 for 600 s, 10 m/s for 400 s, 0 for 600 s, 1 Hz, steps of 1e-4 degree while moving.

    Motion (speed > 0.01 kn) from row 600: 500 m is reached 45 steps later (45 x 11.13 m),
    before 300 s: the trip starts at row 600. The stop is confirmed 300 s after row 1000 and
    starts there. The trip's distance is the growth of totalDistance from its first row (600,
    which already made the first step) to its last (1000): 399 steps.
    """
    n = 1600
    t = np.arange(n, dtype=float)
    moving = (t >= 600) & (t < 1000)
    k = np.cumsum(moving)
    g = _fixes(t.tolist(), k.tolist(), speed_mps=np.where(moving, 10.0, 0.0).tolist())
    r = traccar_rules(g)
    trips = r.trips
    assert trips["kind"].tolist() == ["stop", "trip", "stop"]
    assert trips["t_start"].tolist() == [0.0, 600.0, 1000.0]
    assert trips["distance_m"].iloc[1] == pytest.approx(399 * STEP_M, rel=1e-9)
    assert trips["max_speed_mps"].iloc[1] == 10.0
    assert r.summary()["trips"] == 1
