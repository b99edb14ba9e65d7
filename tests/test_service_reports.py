"""Traccar reports of ``iotnav serve``: ``/api/reports/route|trips|stops|events`` (issue 18).

In-process (FastAPI's TestClient) on a real SQLite file. The scenario is written into the
positions table as the service stores it, at 1 Hz with 2 m of noise per axis: a drive east at
10 m/s for 600 s, 900 s parked, a drive north at 10 m/s for 600 s. Expected times and places
come from that script, not from the code.
"""

from __future__ import annotations

import math
import time
from datetime import UTC, datetime

import numpy as np
import pytest
from fastapi.testclient import TestClient

from iotnav.geo import LocalFrame
from iotnav.service import store
from iotnav.service.http import api_app
from iotnav.service.ingest import Ingestor

T0 = datetime(2026, 5, 4, 8, 0, tzinfo=UTC).timestamp()
LAT0, LON0 = 48.2, 16.37
KNOT = 1852.0 / 3600.0
TOKEN = "reports-read-token"


def _iso(t: float) -> str:
    return datetime.fromtimestamp(t, UTC).isoformat().replace("+00:00", "Z")


def _scenario() -> list[dict]:
    """Rows of the drive-stop-drive script (device 1) in the service's positions form."""
    rng = np.random.default_rng(18)
    frame = LocalFrame(LAT0, LON0, 0.0)
    rows = []
    for k in range(2101):
        if k <= 600:  # east at 10 m/s
            n, e, v, crs = 0.0, 10.0 * k, 10.0, math.pi / 2
        elif k <= 1500:  # parked
            n, e, v, crs = 0.0, 6000.0, 0.0, None
        else:  # north at 10 m/s
            n, e, v, crs = 10.0 * (k - 1500), 6000.0, 10.0, 0.0
        if k in (600, 1500):
            v = 0.0
        n, e = n + rng.normal(0.0, 2.0), e + rng.normal(0.0, 2.0)
        lat, lon, _ = frame.from_ned(np.array([n, e, 0.0]))
        rows.append(
            {
                "device_id": 1,
                "engine": "none",
                "fix_time": T0 + k,
                "server_time": T0 + k + 1,
                "valid": True,
                "latitude": float(lat),
                "longitude": float(lon),
                "altitude": 200.0,
                "speed_mps": v,
                "course_rad": crs,
                "accuracy_m": 2.0 * math.sqrt(2.0),
                "attributes": {},
                "dedup_key": f"k{k}",
            }
        )
    return rows


@pytest.fixture(scope="module")
def client(tmp_path_factory):
    db = store.make_engine(store.sqlite_url(tmp_path_factory.mktemp("reports")))
    store.upgrade(db)
    now = time.time()
    with db.begin() as conn:
        for i in (1, 2):
            conn.execute(
                store.devices.insert().values(
                    id=i,
                    unique_id=f"dev{i}",
                    name=f"dev {i}",
                    protocol="osmand",
                    created_at=now,
                    attributes={},
                )
            )
        conn.execute(store.positions.insert(), _scenario())
        conn.execute(
            store.events.insert(),
            [
                {
                    "device_id": 1,
                    "type": "late_fix",
                    "event_time": T0 + 100,
                    "server_time": now,
                    "attributes": {},
                },
                {
                    "device_id": 1,
                    "type": "fix_rejected",
                    "event_time": T0 + 700,
                    "server_time": now,
                    "attributes": {"reason": "jump"},
                },
                {
                    "device_id": 1,
                    "type": "late_fix",
                    "event_time": T0 + 5000,
                    "server_time": now,
                    "attributes": {},
                },
                {
                    "device_id": 2,
                    "type": "late_fix",
                    "event_time": T0 + 200,
                    "server_time": now,
                    "attributes": {},
                },
            ],
        )
        conn.execute(
            store.api_tokens.insert().values(
                name="r", token_sha256=store.token_digest(TOKEN), scope="read", created_at=now
            )
        )
    app = api_app(db, Ingestor(db, engine_name="none"))
    with TestClient(app, headers={"Authorization": f"Bearer {TOKEN}"}) as c:
        yield c
    db.dispose()


def _period(t0: float = T0 - 60, t1: float = T0 + 2200) -> dict[str, str]:
    return {"from": _iso(t0), "to": _iso(t1)}


def _t(s: str) -> float:
    return datetime.fromisoformat(s.replace("Z", "+00:00")).timestamp()


def test_two_trips_of_a_drive_a_stop_and_a_drive(client) -> None:
    trips = client.get("/api/reports/trips", params={"deviceId": 1, **_period()})
    assert trips.status_code == 200, trips.text
    trips = trips.json()
    assert len(trips) == 2
    for trip, (a, b) in zip(trips, [(0, 600), (1500, 2100)], strict=True):
        assert trip["deviceId"] == 1 and trip["deviceName"] == "dev 1"
        assert abs(_t(trip["startTime"]) - (T0 + a)) <= 3.0
        assert abs(_t(trip["endTime"]) - (T0 + b)) <= 3.0
        assert abs(trip["duration"] - 600_000) <= 5_000  # ms
        assert abs(trip["distance"] - 6000.0) <= 0.03 * 6000.0  # m
        assert abs(trip["averageSpeed"] - 10.0 / KNOT) <= 0.05 * 10.0 / KNOT  # knots
        assert abs(trip["maxSpeed"] - 10.0 / KNOT) < 0.01
    frame = LocalFrame(LAT0, LON0, 0.0)
    ends = [(0.0, 0.0), (0.0, 6000.0), (0.0, 6000.0), (6000.0, 6000.0)]
    got = [
        (trips[0]["startLat"], trips[0]["startLon"]),
        (trips[0]["endLat"], trips[0]["endLon"]),
        (trips[1]["startLat"], trips[1]["startLon"]),
        (trips[1]["endLat"], trips[1]["endLon"]),
    ]
    for (n, e), (lat, lon) in zip(ends, got, strict=True):
        ned = frame.to_ned(np.array([lat]), np.array([lon]), np.zeros(1))[0]
        assert math.hypot(ned[0] - n, ned[1] - e) < 30.0  # 3 s at 10 m/s plus noise


def test_the_stop_between_the_drives(client) -> None:
    frame = LocalFrame(LAT0, LON0, 0.0)
    stops = client.get("/api/reports/stops", params={"deviceId": 1, **_period()}).json()
    assert len(stops) == 1
    (stop,) = stops
    assert abs(_t(stop["startTime"]) - (T0 + 600)) <= 3.0
    assert abs(_t(stop["endTime"]) - (T0 + 1500)) <= 3.0
    assert abs(stop["duration"] - 900_000) <= 5_000
    ned = frame.to_ned(np.array([stop["latitude"]]), np.array([stop["longitude"]]), np.zeros(1))[0]
    assert math.hypot(ned[0], ned[1] - 6000.0) < 2.0  # median of 900 fixes of 2 m noise


def test_device_id_repeats_and_a_device_without_positions_adds_nothing(client) -> None:
    both = client.get("/api/reports/trips", params={"deviceId": [1, 2], **_period()}).json()
    assert [t["deviceId"] for t in both] == [1, 1]


def test_route_is_the_stored_positions_in_traccar_form(client) -> None:
    r = client.get("/api/reports/route", params={"deviceId": 1, **_period(T0 + 10, T0 + 19)})
    assert r.status_code == 200, r.text
    route = r.json()
    assert [_t(p["fixTime"]) for p in route] == [T0 + k for k in range(10, 20)]
    p = route[0]
    assert p["deviceId"] == 1 and p["protocol"] == "osmand"
    assert abs(p["speed"] - 10.0 / KNOT) < 1e-9 and abs(p["course"] - 90.0) < 1e-9
    assert p == client.get("/api/positions", params={"deviceId": 1, **_period(T0 + 10, T0 + 19)}).json()[0]


def test_events_filtered_by_device_type_and_period(client) -> None:
    def types(**params) -> list[tuple[int, str, float]]:
        r = client.get("/api/reports/events", params=params)
        assert r.status_code == 200, r.text
        return [(e["deviceId"], e["type"], _t(e["eventTime"])) for e in r.json()]

    assert types(deviceId=1, **_period()) == [(1, "late_fix", T0 + 100), (1, "fix_rejected", T0 + 700)]
    assert types(deviceId=1, type="fix_rejected", **_period()) == [(1, "fix_rejected", T0 + 700)]
    assert types(deviceId=1, type="allEvents", **_period(T0 + 4000, T0 + 6000)) == [
        (1, "late_fix", T0 + 5000)
    ]
    assert types(deviceId=[1, 2], type="late_fix", **_period(T0, T0 + 300)) == [
        (1, "late_fix", T0 + 100),
        (2, "late_fix", T0 + 200),
    ]


@pytest.mark.parametrize(
    ("params", "message"),
    [
        ({"from": "2026-05-04T08:00:00Z", "to": "2026-05-04T09:00:00Z"}, "deviceId is required"),
        ({"deviceId": "x", "from": "2026-05-04T08:00:00Z", "to": "2026-05-04T09:00:00Z"}, "not a device id"),
        ({"deviceId": 1, "to": "2026-05-04T09:00:00Z"}, "from and to are required"),
        ({"deviceId": 1, "from": "yesterday", "to": "2026-05-04T09:00:00Z"}, "not an ISO 8601 time"),
        ({"deviceId": 1, "from": "2026-05-04T09:00:00Z", "to": "2026-05-04T08:00:00Z"}, "is before from"),
    ],
)
@pytest.mark.parametrize("report", ["route", "trips", "stops", "events"])
def test_bad_parameters_are_400_with_a_message(client, report, params, message) -> None:
    r = client.get(f"/api/reports/{report}", params=params)
    assert r.status_code == 400
    assert message in r.json()["detail"]


def test_reports_need_a_token(client) -> None:
    r = client.get("/api/reports/trips", params={"deviceId": 1, **_period()}, headers={"Authorization": ""})
    assert r.status_code == 401
