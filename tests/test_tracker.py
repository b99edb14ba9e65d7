"""The tracker's vocabulary on constructed tracks with known truth: trips, stops, odometer, zones."""

from __future__ import annotations

import json

import numpy as np
import pandas as pd
import pytest

from iotnav.geo import LocalFrame
from iotnav.tracker import TrackerConfig, TripRules, describe, segments, track_from_fixes, zones_from_geojson
from iotnav.tracker.geofence import geofence_events

FRAME = LocalFrame(45.0, 7.0, 0.0)


def _track(t: np.ndarray, n: np.ndarray, e: np.ndarray, sigma: float, **cols: object) -> pd.DataFrame:
    lat, lon, _ = FRAME.from_ned(np.column_stack([n, e, np.zeros_like(t)]))
    df = pd.DataFrame(
        {"t": t, "lat": lat, "lon": lon, "static": False, "std_north": sigma, "std_east": sigma}
    )
    for k, v in cols.items():
        df[k] = v
    return df


def _parked_noise(rng: np.random.Generator, t: np.ndarray, sigma: float) -> tuple[np.ndarray, np.ndarray]:
    """White noise plus a slow random walk-like drift (correlated multipath) and 200 m jumps."""
    n = rng.normal(0, sigma, t.size) + np.convolve(rng.normal(0, 1.0, t.size), np.ones(60) / 8, "same")
    e = rng.normal(0, sigma, t.size) + np.convolve(rng.normal(0, 1.0, t.size), np.ones(60) / 8, "same")
    for i0 in rng.integers(0, t.size - 5, 6):
        n[i0 : i0 + 3] += 200.0
    return n, e


def test_park_drive_park_trips_and_distance() -> None:
    """20 min parked, 10 min at 10 m/s east (6000 m), 30 min parked: one trip, two stops."""
    rng = np.random.default_rng(1)
    t = np.arange(0.0, 3600.0)
    v = np.where((t >= 1200) & (t < 1800), 10.0, 0.0)
    e_true = np.cumsum(v) - v  # position at t: 10 m/s from t = 1200 to 1800
    n_noise, e_noise = _parked_noise(rng, t, 3.0)
    tr = _track(t, n_noise, e_true + e_noise, 3.0, vn=0.0, ve=v + rng.normal(0, 0.1, t.size))
    res = describe(tr)
    kinds = res.trips["kind"].tolist()
    assert kinds == ["stop", "trip", "stop"]
    trip = res.trips.iloc[1]
    assert abs(trip["t_start"] - 1200.0) <= 5.0
    assert abs(trip["t_end"] - 1800.0) <= 5.0
    assert trip["distance_m"] == pytest.approx(6000.0, rel=0.03)
    assert res.odometer_m == pytest.approx(trip["distance_m"])
    assert res.trips.iloc[0]["distance_m"] == 0.0 and res.trips.iloc[2]["distance_m"] == 0.0
    assert res.trips.iloc[2]["open"] and not res.trips.iloc[1]["open"]
    assert trip["max_speed_mps"] == pytest.approx(10.0, abs=0.5)
    types = [e["type"] for e in res.events]
    assert types == ["trip_start", "trip_end"]
    assert res.summary()["trips"] == 1 and res.summary()["stops"] == 2


def test_odometer_flat_on_noisy_static_fixes() -> None:
    """Two hours parked: noisy, drifting fixes with jumps; no trip, odometer 0, raw path km."""
    rng = np.random.default_rng(7)
    t = np.arange(0.0, 7200.0)
    n, e = _parked_noise(rng, t, 4.0)
    res = describe(_track(t, n, e, 4.0))
    raw_path = float(np.hypot(np.diff(n), np.diff(e)).sum())
    assert raw_path > 30_000.0  # the noise the plain sum would count
    assert res.trips["kind"].tolist() == ["stop"]
    assert res.odometer_m == 0.0


def test_stop_and_go_is_one_trip() -> None:
    """Creeping at 1-5 m/s with halts of 60 s (shorter than the 300 s parking) is one trip."""
    t = np.arange(0.0, 2400.0)
    rng = np.random.default_rng(3)
    speed = np.zeros_like(t)
    moving = (t >= 300) & (t < 2100)
    cycle = (t - 300) % 180
    speed[moving] = np.where(cycle[moving] < 120, 1.0 + 4.0 * rng.random(int(moving.sum())) * 0 + 2.0, 0.0)
    e_true = np.cumsum(speed) - speed
    tr = _track(t, rng.normal(0, 2.0, t.size), e_true + rng.normal(0, 2.0, t.size), 2.0)
    res = describe(tr)
    trips = res.trips[res.trips["kind"] == "trip"]
    assert len(trips) == 1
    assert abs(trips["t_start"].iloc[0] - 300.0) <= 30.0
    assert trips["distance_m"].iloc[0] == pytest.approx(e_true[-1], rel=0.05)


def test_engine_static_flag_and_zero_speed_are_believed() -> None:
    """A slow 100 m wander flagged static by the engine is no motion; the same unflagged is a trip."""
    t = np.arange(0.0, 1800.0)
    e = np.clip((t - 300) * 0.8, 0, 800.0)
    tr = _track(t, np.zeros_like(t), e, 1.0)
    assert (describe(tr).trips["kind"] == "trip").sum() == 1
    tr["static"] = True
    assert (describe(tr).trips["kind"] == "trip").sum() == 0
    tr["static"] = False
    tr["vn"], tr["ve"] = 0.0, 0.0  # a receiver reporting zero speed
    assert (describe(tr).trips["kind"] == "trip").sum() == 0


def test_segments_follow_traccar_hysteresis() -> None:
    """Hand-worked: 1 Hz rows, trips need 300 s or 500 m of motion, stops 300 s without.

    Rows 0-99 still; 100-119 moving (20 s, 0 m: too short, reset by 120-199 still); 200-599
    moving (confirmed at row 500: 300 s after 200, so the trip starts at row 200); 600-649 still
    (50 s: not a stop), 650-799 moving, 800-1199 still (confirmed at 1100, the stop starts at 800).
    """
    t = np.arange(1200.0)
    m = np.zeros(1200, bool)
    m[100:120] = True
    m[200:600] = True
    m[650:800] = True
    segs = segments(t, m, np.zeros(1200), TripRules())
    assert [(s.kind, s.i0, s.i1, s.open) for s in segs] == [
        ("stop", 0, 200, False),
        ("trip", 200, 800, False),
        ("stop", 800, 1199, True),
    ]
    # 500 m covered confirms before 300 s: distance grows 10 m per row from row 200
    dist = np.concatenate([np.zeros(200), np.arange(1000) * 10.0])
    segs = segments(t, m, dist, TripRules())
    assert segs[1].i0 == 200
    # a gap of an hour makes both of its rows stopped (row 400 too: the trip resumes at 401)
    t2 = np.concatenate([np.arange(400.0), 4000.0 + np.arange(400.0)])
    m2 = np.ones(800, bool)
    segs = segments(t2, m2, np.zeros(800), TripRules())
    assert [(s.kind, s.i0, s.i1) for s in segs] == [("trip", 0, 399), ("stop", 399, 401), ("trip", 401, 799)]


def test_geofence_hysteresis_against_border_noise() -> None:
    """A device parked 3 m inside a 50 m circle with 4 m noise, then driving out: one exit."""
    rng = np.random.default_rng(5)
    t = np.arange(0.0, 1200.0)
    e = np.where(t < 900, 47.0, 47.0 + (t - 900) * 5.0)
    n = rng.normal(0, 4.0, t.size)
    ee = e + rng.normal(0, 4.0, t.size)
    lat, lon, _ = FRAME.from_ned(np.column_stack([n, ee, np.zeros_like(t)]))
    zones = zones_from_geojson(
        {
            "type": "Feature",
            "properties": {"name": "depot", "radius": 50.0},
            "geometry": {"type": "Point", "coordinates": [7.0, 45.0]},
        }
    )
    plain, _ = geofence_events(t, lat, lon, np.zeros(t.size), zones, 1.96)
    assert len(plain) > 20  # point by point the noise toggles the state
    ev, initial = geofence_events(t, lat, lon, np.full(t.size, 4.0), zones, TrackerConfig().fence_k_sigma)
    assert initial == {"depot": True}
    assert [x["type"] for x in ev] == ["geofence_exit"]
    assert 900.0 < ev[0]["t"] < 905.0 and ev[0]["zone"] == "depot"


def test_geofence_polygon_with_hole_and_multipolygon() -> None:
    """Square 200 m with a 50 m hole; a drive east along the centre line crosses 4 borders."""
    d = 100.0 / FRAME.to_ned(45.001, 7.0, 0.0)[0] * 0.001  # degrees of latitude per 100 m

    def square(half_m: float) -> list[list[float]]:
        dlat = half_m / 100.0 * d
        dlon = dlat / np.cos(np.radians(45.0))
        return [
            [7 - dlon, 45 - dlat],
            [7 + dlon, 45 - dlat],
            [7 + dlon, 45 + dlat],
            [7 - dlon, 45 + dlat],
            [7 - dlon, 45 - dlat],
        ]

    gj = {
        "type": "FeatureCollection",
        "features": [
            {
                "type": "Feature",
                "properties": {"name": "yard"},
                "geometry": {"type": "Polygon", "coordinates": [square(100), square(25)]},
            },
            {
                "type": "Feature",
                "id": "multi",
                "properties": {},
                "geometry": {"type": "MultiPolygon", "coordinates": [[square(100)]]},
            },
        ],
    }
    zones = zones_from_geojson(gj)
    assert [z.name for z in zones] == ["yard", "multi"]
    t = np.arange(0.0, 301.0)
    east = -150.0 + t
    lat, lon, _ = FRAME.from_ned(np.column_stack([np.zeros_like(t), east, np.zeros_like(t)]))
    ev, initial = geofence_events(t, lat, lon, np.full(t.size, 1.0), zones, 3.0)
    yard = [(x["type"], x["t"]) for x in ev if x["zone"] == "yard"]
    # borders at east = -100, -25, 25, 100 (t = 50, 125, 175, 250), switched once more than 3 m
    # (3 sigma) beyond: t + 3 to t + 4 (the square is drawn in degrees, its sides within 1 m)
    assert [k for k, _ in yard] == ["geofence_enter", "geofence_exit", "geofence_enter", "geofence_exit"]
    assert np.allclose([x for _, x in yard], [53.5, 128.5, 178.5, 253.5], atol=1.0)
    assert [x["type"] for x in ev if x["zone"] == "multi"] == ["geofence_enter", "geofence_exit"]
    assert initial == {"yard": False, "multi": False}


@pytest.mark.parametrize(
    ("obj", "message"),
    [
        ([1, 2], "not a GeoJSON object"),
        ({"type": "FeatureCollection"}, "'features' list"),
        ({"type": "FeatureCollection", "features": []}, "no zones"),
        ({"type": "LineString", "coordinates": [[0, 0], [1, 1]]}, "'LineString' is not a zone"),
        ({"type": "Polygon", "coordinates": [[[0, 0], [1, 0], [1, 1], [0, 1]]]}, "must be closed"),
        ({"type": "Polygon", "coordinates": [[[0, 0], [1, 0], [0, 0]]]}, "at least 4"),
        ({"type": "Polygon", "coordinates": [[[0, 0], [1, 0], [1, 95], [0, 0]]]}, "lat"),
        ({"type": "Point", "coordinates": [7, 45]}, "needs a 'radius'"),
        (
            {
                "type": "Feature",
                "properties": {"radius": -3},
                "geometry": {"type": "Point", "coordinates": [7, 45]},
            },
            "positive",
        ),
        ({"type": "Feature", "properties": {}, "geometry": None}, "no geometry"),
    ],
)
def test_geojson_errors_name_the_problem(obj: object, message: str) -> None:
    with pytest.raises(ValueError, match=message) as exc:
        zones_from_geojson(json.loads(json.dumps(obj)), source="zones.geojson")
    assert "zones.geojson" in str(exc.value)


def test_engine_events_passed_through_with_reason() -> None:
    t = np.arange(0.0, 100.0)
    tr = _track(t, np.zeros_like(t), np.zeros_like(t), 1.0)
    tr.attrs["events"] = [
        {"type": "moved_while_off", "t": 0.0, "distance_m": 350.0},
        {"type": "fix_rejected", "t": 3.0, "reason": "pdop", "pdop": 9.0},
        {"type": "fix_rejected", "t": 4.0, "nis": 80.0},
        {"type": "first_fix", "t": 1.0},
    ]
    res = describe(tr)
    assert [(e["type"], e.get("reason")) for e in res.engine_events] == [
        ("moved_while_off", None),
        ("fix_rejected", "pdop"),
        ("fix_rejected", "nis"),
    ]
    s = res.summary()
    assert s["moved_while_off"] == 1 and s["fixes_rejected"] == {"pdop": 1, "nis": 1}


def test_track_from_fixes_sigma_and_velocity() -> None:
    g = pd.DataFrame(
        {
            "t": [0.0, 1.0, 2.0],
            "lat_deg": [45.0, 45.0, np.nan],
            "lon_deg": [7.0, 7.0001, np.nan],
            "valid": [True, True, False],
            "h_acc_m": [2.0 * np.sqrt(2.0), np.nan, np.nan],
            "hdop": [np.nan, 1.5, np.nan],
            "speed_mps": [2.0, 0.0, np.nan],
            "course_rad": [np.pi / 2, 0.0, np.nan],
        }
    )
    tr = track_from_fixes(g)
    assert len(tr) == 2
    # h_acc 2.83 m (2-D) -> 2 m per axis; HDOP 1.5 x UERE 3 m = 4.5 m (2-D) -> 3.18 m per axis
    assert tr["std_north"].tolist() == pytest.approx([2.0, 4.5 / np.sqrt(2.0)])
    assert tr["ve"].iloc[0] == pytest.approx(2.0) and abs(tr["vn"].iloc[0]) < 1e-12


def test_empty_and_unordered_tracks() -> None:
    empty = pd.DataFrame({"t": [], "lat": [], "lon": [], "static": []})
    res = describe(empty)
    assert len(res.trips) == 0 and res.odometer_m == 0.0
    bad = _track(np.array([0.0, 2.0, 1.0]), np.zeros(3), np.zeros(3), 1.0)
    with pytest.raises(ValueError, match="backwards"):
        describe(bad)
