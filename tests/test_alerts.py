"""The alert rules (:mod:`iotnav.alerts`): each kind fires once at the right time and not on noise.

Scenarios are short 1 Hz streams on a tangent plane at 48 N 16 E, seeded; the expected times
follow from the scenario's geometry and the documented rules, not from the code.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from iotnav.alerts import KMH_MPS, AlertEngine, AlertRules, Position, groups_from_dict, rules_from_dict
from iotnav.geo import LocalFrame
from iotnav.tracker import Zone

FRAME = LocalFrame(48.0, 16.0, 0.0)
T0 = 1_700_000_000.0


def pos(t: float, north: float, east: float, **kw: object) -> Position:
    """A position ``north``, ``east`` metres from the origin (small offsets: the plane's
    metres per degree of WGS84 at 48 N, Groves 2013 eq. 2.105-2.106, exact to 1e-6 here)."""
    lat = 48.0 + north / M_PER_DEG_LAT
    lon = 16.0 + east / M_PER_DEG_LON
    return Position(t=T0 + t, lat_deg=lat, lon_deg=lon, **kw)  # type: ignore[arg-type]


def _metres_per_degree() -> tuple[float, float]:
    lat, lon, _ = FRAME.from_ned(np.array([1000.0, 1000.0, 0.0]))
    return 1000.0 / (float(lat) - 48.0), 1000.0 / (float(lon) - 16.0)


M_PER_DEG_LAT, M_PER_DEG_LON = _metres_per_degree()


def feed(eng: AlertEngine, ps: list[Position], device: str = "d1", group: str = "default") -> list:
    out = []
    for p in ps:
        out += eng.position(device, group, p)
    return out


def test_geofence_enter_exit_once_at_the_margin_and_not_on_border_noise() -> None:
    zone = Zone("depot", center=(48.0, 16.0), radius_m=100.0)
    eng = AlertEngine({"default": AlertRules()}, [zone])
    rng = np.random.default_rng(3)
    sigma = 2.0
    # drive east through the centre at 10 m/s, per-axis noise 2 m: margin 3 sigma = 6 m
    ps = [
        pos(k, rng.normal(0, sigma), -500.0 + 10.0 * k + rng.normal(0, sigma), sigma_m=sigma)
        for k in range(101)
    ]
    alerts = feed(eng, ps)
    assert [a.kind for a in alerts] == ["geofence_enter", "geofence_exit"]
    # true crossings of the 6 m margins: east = -94 m at t = 40.6 s, east = +106 m at t = 60.6 s
    assert abs(alerts[0].t - T0 - 40.6) <= 1.5 and abs(alerts[1].t - T0 - 60.6) <= 1.5
    assert alerts[0].detail["zone"] == "depot" and alerts[0].detail["border_m"] < -6.0

    # parked 5 m inside the border for 10 min with the same noise: a point-by-point test toggles
    eng2 = AlertEngine({"default": AlertRules()}, [zone])
    parked = [pos(k, rng.normal(0, sigma), 95.0 + rng.normal(0, sigma), sigma_m=sigma) for k in range(600)]
    d = zone.signed_distance(np.array([p.lat_deg for p in parked]), np.array([p.lon_deg for p in parked]))
    assert np.count_nonzero(np.diff(d > 0)) > 0  # the noise does cross the border itself
    assert feed(eng2, parked) == []


def test_overspeed_once_per_period_after_the_minimal_duration_not_on_a_spike() -> None:
    rules = AlertRules(overspeed_mps=90 * KMH_MPS, overspeed_min_duration_s=5.0)
    eng = AlertEngine({"default": rules})
    speeds = [20.0] * 30 + [30.0] + [20.0] * 30 + [30.0] * 20 + [20.0] * 10 + [26.0] * 10
    ps = [pos(k, 0.0, 20.0 * k, speed_mps=v) for k, v in enumerate(speeds)]
    alerts = feed(eng, ps)
    assert [a.kind for a in alerts] == ["overspeed", "overspeed"]
    # the one-second spike at t = 30 raises nothing; the 20 s period from t = 61 fires at 66;
    # the period from t = 91 at 96
    assert [a.t - T0 for a in alerts] == [66.0, 96.0]
    assert alerts[0].detail["since"] == T0 + 61.0


def test_stop_after_a_trip_fires_once_when_it_has_lasted_n_minutes() -> None:
    rules = rules_from_dict({"stop_minutes": 30})
    eng = AlertEngine({"default": rules})
    drive = [pos(k, 0.0, 10.0 * k, speed_mps=10.0) for k in range(600)]
    park = [pos(600 + k, 0.0, 6000.0, speed_mps=0.0, static=True) for k in range(0, 2400, 5)]
    alerts = feed(eng, drive + park)
    assert [a.kind for a in alerts] == ["stop"]
    # the stop begins at the first parked row (t = 600 s) and is 30 min long at t = 2400 s
    assert alerts[0].detail["since"] == T0 + 600.0
    assert alerts[0].t == T0 + 2400.0

    # a 20 min stop, and a device parked since the service started: nothing
    eng2 = AlertEngine({"default": rules})
    short = [pos(600 + k, 0.0, 6000.0, speed_mps=0.0, static=True) for k in range(0, 1200, 5)]
    assert (
        feed(eng2, drive + short + [pos(1800 + k, 0.0, 6000.0 + 10 * k, speed_mps=10.0) for k in range(60)])
        == []
    )
    eng3 = AlertEngine({"default": rules})
    assert feed(eng3, [pos(k, 0.0, 0.0, speed_mps=0.0, static=True) for k in range(0, 4000, 10)]) == []
    assert eng3.tick(T0 + 9000.0) == []


def test_stop_found_on_the_clock_when_a_parked_tracker_stops_reporting() -> None:
    eng = AlertEngine({"default": rules_from_dict({"stop_minutes": 30})})
    drive = [pos(k, 0.0, 10.0 * k, speed_mps=10.0) for k in range(600)]
    park = [pos(600 + k, 0.0, 6000.0, speed_mps=0.0, static=True) for k in range(0, 400, 5)]
    assert feed(eng, drive + park) == []
    assert eng.tick(T0 + 2399.0) == []
    alerts = eng.tick(T0 + 2400.0)
    assert [a.kind for a in alerts] == ["stop"] and alerts[0].detail["since"] == T0 + 600.0
    assert eng.tick(T0 + 3000.0) == []


def test_silent_device_on_the_clock_passed_in_once_per_silence() -> None:
    eng = AlertEngine({"default": rules_from_dict({"silent_minutes": 10})})
    feed(eng, [pos(k, 0.0, 0.0, received_at=T0 + k + 0.4) for k in range(100)])
    last = T0 + 99.4
    assert eng.tick(last + 599.9) == []
    alerts = eng.tick(last + 600.0)
    assert [a.kind for a in alerts] == ["silent"] and alerts[0].detail["last_received"] == last
    assert eng.tick(last + 1200.0) == []  # once per silence
    feed(eng, [pos(2000.0, 0.0, 0.0, received_at=T0 + 2000.0)])
    assert eng.tick(T0 + 2599.0) == [] and len(eng.tick(T0 + 2600.0)) == 1


def test_moved_while_off_once_when_towed_not_on_parked_noise() -> None:
    eng = AlertEngine({"default": rules_from_dict({"moved_while_off_m": 100.0})})
    rng = np.random.default_rng(7)
    s = 5.0
    parked = [
        pos(k, rng.normal(0, s), rng.normal(0, s), sigma_m=s, ignition=False, speed_mps=0.0)
        for k in range(0, 3600, 10)
    ]
    assert feed(eng, parked) == []
    towed = [pos(3600 + k, 0.0, 2.0 * k, sigma_m=s, ignition=False, speed_mps=2.0) for k in range(150)]
    alerts = feed(eng, towed)
    assert [a.kind for a in alerts] == ["moved_while_off"]
    # the anchor is the first ignition-off position (within noise of the origin): 100 m at t ~ 3650 s
    assert abs(alerts[0].t - T0 - 3650.0) <= 8.0 and alerts[0].detail["distance_m"] > 100.0
    # ignition on re-arms; driving with it on raises nothing
    on = [pos(3800 + k, 0.0, 300.0 + 10.0 * k, ignition=True, speed_mps=10.0) for k in range(60)]
    assert feed(eng, on) == []
    # the engine's own boot event is passed on
    ev = eng.event(
        "d1", "default", "moved_while_off", T0 + 5000.0, {"type": "moved_while_off", "distance_m": 800.0}
    )
    assert [a.kind for a in ev] == ["moved_while_off"] and ev[0].detail["source"] == "engine"


def test_gnss_jump_rejected_one_alert_per_glitch() -> None:
    eng = AlertEngine({"default": rules_from_dict({"gnss_jump": True})})
    feed(eng, [pos(0.0, 0.0, 0.0)])
    out = []
    for t in (100.0, 101.0, 102.0, 300.0):  # a 3-fix glitch, then another one later
        out += eng.event(
            "d1", "default", "fix_rejected", T0 + t, {"type": "fix_rejected", "reason": "nis", "nis": 40.0}
        )
    assert [a.t - T0 for a in out] == [100.0, 300.0] and out[0].detail["nis"] == 40.0
    assert not math.isnan(out[0].lat_deg)
    off = AlertEngine({"default": AlertRules()})
    assert off.event("d1", "default", "fix_rejected", T0, {"nis": 40.0}) == []


def test_rules_per_group_and_the_toml_table() -> None:
    groups = groups_from_dict(
        {"default": {"overspeed_kmh": 120}, "trucks": {"overspeed_kmh": 80, "geofences": ["yard"]}}
    )
    assert groups["trucks"].overspeed_mps == pytest.approx(80 / 3.6) and groups["trucks"].geofences == (
        "yard",
    )
    eng = AlertEngine(groups)
    ps = [pos(k, 0.0, 25.0 * k, speed_mps=25.0) for k in range(5)]  # 90 km/h
    assert feed(eng, ps, "car", "default") == []
    assert feed(eng, ps, "truck", "trucks")[0].kind == "overspeed"
    assert feed(eng, ps, "van", "vans") == []  # not configured: the default group's rules
    assert AlertEngine({"trucks": groups["trucks"]}).position("van", "vans", ps[0]) == []
    with pytest.raises(ValueError, match="overspeed_mph"):
        rules_from_dict({"overspeed_mph": 50})
    with pytest.raises(ValueError, match="stop_minutes"):
        rules_from_dict({"stop_minutes": -1})
    assert (
        rules_from_dict({"trips": {"min_parking_duration_s": 60}}).tracker.trips.min_parking_duration_s
        == 60.0
    )


def test_distance_on_the_tangent_plane_agrees_with_vincenty() -> None:
    from pymap3d.vincenty import vdist

    from iotnav.alerts import _distance_m

    rng = np.random.default_rng(0)
    for _ in range(50):
        lat, lon = rng.uniform(-70, 70), rng.uniform(-180, 180)
        lat2, lon2 = lat + rng.uniform(-0.05, 0.05), lon + rng.uniform(-0.05, 0.05)
        ref = float(vdist(lat, lon, lat2, lon2)[0])
        assert _distance_m(Position(0, lat, lon), Position(0, lat2, lon2)) == pytest.approx(ref, rel=1e-5)


def test_geofence_alerts_equal_the_tracker_batch_events_on_a_wandering_track() -> None:
    from iotnav.tracker import geofence_events, zones_from_geojson

    square = [
        [16.0 + dx / M_PER_DEG_LON, 48.0 + dy / M_PER_DEG_LAT]
        for dx, dy in ((-80, -80), (80, -80), (80, 80), (-80, 80), (-80, -80))
    ]
    zones = zones_from_geojson(
        {
            "type": "FeatureCollection",
            "features": [
                {
                    "type": "Feature",
                    "properties": {"name": "yard"},
                    "geometry": {"type": "Polygon", "coordinates": [square]},
                },
                {
                    "type": "Feature",
                    "properties": {"name": "far", "radius": 50},
                    "geometry": {"type": "Point", "coordinates": [16.5, 48.0]},
                },
                {
                    "type": "Feature",
                    "properties": {"name": "gate", "radius": 30},
                    "geometry": {"type": "Point", "coordinates": [16.0, 48.0 + 90 / M_PER_DEG_LAT]},
                },
            ],
        }
    )
    rng = np.random.default_rng(11)
    heading = np.cumsum(rng.normal(0, 0.3, 900))
    north = np.cumsum(4.0 * np.cos(heading)) - 200.0
    east = np.cumsum(4.0 * np.sin(heading))
    north, east = np.clip(north, -250, 250), np.clip(east, -250, 250)  # wander in and out
    sigma = rng.uniform(1.0, 4.0, north.size)
    ps = [
        pos(k, float(n), float(e), sigma_m=float(s))
        for k, (n, e, s) in enumerate(zip(north, east, sigma, strict=True))
    ]
    alerts = feed(AlertEngine({"default": AlertRules()}, zones), ps)
    t = np.array([p.t for p in ps])
    lat, lon = np.array([p.lat_deg for p in ps]), np.array([p.lon_deg for p in ps])
    batch, _ = geofence_events(t, lat, lon, sigma, zones, k_sigma=3.0)
    assert len(batch) >= 6  # the track does cross the yard and the gate
    assert [(a.kind, a.detail["zone"], a.t) for a in alerts] == [
        (e["type"], e["zone"], e["t"]) for e in batch
    ]


def test_streaming_trip_hysteresis_switches_where_the_batch_segments_do() -> None:
    from iotnav.tracker import TripHysteresis, TripRules, segments

    rng = np.random.default_rng(5)
    n_trips = 0
    for k in range(300):
        n = int(rng.integers(2, 150))
        t = np.cumsum(rng.choice([1.0, 5.0, 30.0, 100.0, 4000.0], size=n, p=[0.5, 0.2, 0.15, 0.1, 0.05]))
        moving = np.repeat(rng.random(n // 10 + 1) < rng.uniform(0.1, 0.9), 10)[:n]
        dist = np.cumsum(rng.uniform(0, 50, n))
        rules = TripRules(*(float(rng.choice(c)) for c in ((10, 300), (50, 500), (10, 300), (0, 600, 3600))))
        bridge = bool(k % 2)
        hyst, bounds = TripHysteresis(rules, bridge), []
        for sw in [
            hyst.push(a, b, c) for a, b, c in zip(t.tolist(), moving.tolist(), dist.tolist(), strict=True)
        ]:
            bounds += [sw.i0] if sw is not None else []
        last = hyst.flush()
        bounds += [last.i0] if last is not None else []
        segs = segments(t, moving, dist, rules, bridge)
        n_trips += sum(s.kind == "trip" for s in segs)
        assert [s.i0 for s in segs[1:]] == [b for b in bounds if b > 0][: len(segs) - 1]
    assert n_trips > 100
