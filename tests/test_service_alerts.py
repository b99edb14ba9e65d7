"""Alerts through the running service, real sockets end to end (:mod:`iotnav.service.alerts_delivery`).

``serve()`` runs in this process on free localhost ports with alerts configured: a geofence is
created through the API, an OsmAnd device drives into it over HTTP, and the alert arrives on
the API's WebSocket, at a webhook receiver served here on 127.0.0.1 (which answers 500 to the
first try: the retry must come, signed afresh, verifiable with the shared secret by the
documented scheme) and on the MQTT topic through a real mosquitto (Debian ``mosquitto``).
"""

from __future__ import annotations

import asyncio
import contextlib
import hashlib
import hmac
import json
import sqlite3
import threading
import time
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from typing import Any

import alembic.command  # noqa: F401  (these load at collection, as for the other service tests)
import httpx
import paho.mqtt.client as mqtt
import pytest
from websockets.asyncio.client import connect

import iotnav.service.http  # noqa: F401
from _service_helpers import Mosquitto, WebhookReceiver, free_ports
from iotnav.service.alerts_delivery import SIGNATURE_HEADER, verify_signature
from iotnav.service.app import ServiceConfig, serve

SECRET = "s3cret-for-the-test"


def test_geofence_alert_reaches_socket_signed_webhook_after_a_500_and_mqtt(tmp_path) -> None:
    broker = Mosquitto(tmp_path / "broker").start()
    receiver = WebhookReceiver(fail_first=1)
    mqtt_got: list[tuple[str, bytes]] = []
    sub = mqtt.Client(callback_api_version=mqtt.CallbackAPIVersion.VERSION2, client_id="alert-listener")
    subscribed = threading.Event()
    sub.on_connect = lambda c, *_: c.subscribe("iotnav/alerts/#", qos=1)
    sub.on_subscribe = lambda *_: subscribed.set()
    sub.on_message = lambda _c, _u, m: mqtt_got.append((m.topic, bytes(m.payload)))
    sub.connect("127.0.0.1", broker.port)
    sub.loop_start()
    tcp, osmand, api = free_ports(3)
    alerts = {
        "webhook_url": receiver.url,
        "webhook_secret": SECRET,
        "webhook_backoff_s": 0.1,
        "mqtt": broker.url,
        "poll_interval_s": 0.05,
        "geofence_reload_s": 0.05,
        "groups": {"default": {"geofences": True}},
    }
    cfg = ServiceConfig(
        data=str(tmp_path / "data"),
        host="127.0.0.1",
        teltonika_port=tcp,
        osmand_port=osmand,
        api_port=api,
        engine="none",
        alerts=alerts,
    )

    async def scenario() -> dict[str, Any]:
        task = asyncio.create_task(serve(cfg))
        try:
            async with httpx.AsyncClient(timeout=10) as http:
                for _ in range(200):  # the listeners are up
                    with contextlib.suppress(httpx.HTTPError):
                        if (await http.get(f"http://127.0.0.1:{api}/api/server")).status_code == 401:
                            break
                    await asyncio.sleep(0.02)
                token = (tmp_path / "data" / "admin_token").read_text().strip()
                auth = {"Authorization": f"Bearer {token}"}
                depot = {"name": "depot", "area": "CIRCLE (48.0 16.0, 100)"}
                assert (
                    await http.post(f"http://127.0.0.1:{api}/api/geofences", json=depot, headers=auth)
                ).is_success
                async with connect(f"ws://127.0.0.1:{api}/api/socket?token={token}") as ws:
                    await asyncio.sleep(0.1)  # the geofence is read, the socket registered
                    # 1 km north of the depot, then 20 m from its centre (accuracy 5 m: margin 10.6 m)
                    for k, lat in enumerate((48.009, 48.00018)):
                        q = {
                            "id": "van7",
                            "lat": lat,
                            "lon": 16.0,
                            "timestamp": 1_700_000_000 + 60 * k,
                            "accuracy": 5,
                        }
                        assert (await http.get(f"http://127.0.0.1:{osmand}/", params=q)).status_code == 200
                    seen: list[dict[str, Any]] = []  # each message's positions, then the alert
                    while not seen or "events" not in seen[-1]:
                        seen.append(json.loads(await asyncio.wait_for(ws.recv(), timeout=4.0)))
                    assert [list(m) for m in seen] == [["positions"], ["positions"], ["events"]]
                    (event,) = seen[-1]["events"]
                for _ in range(200):  # the retry after the 500 (0.1 s backoff), and MQTT
                    if len(receiver.got) >= 2 and mqtt_got:
                        break
                    await asyncio.sleep(0.02)
                return event
        finally:
            task.cancel()
            await asyncio.gather(task, return_exceptions=True)

    try:
        assert subscribed.wait(5)
        event = asyncio.run(scenario())
    finally:
        sub.loop_stop()
        receiver.server.shutdown()
        broker.stop()

    assert event["type"] == "alert_geofence_enter" and event["kind"] == "geofence_enter"
    assert event["uniqueId"] == "van7" and event["attributes"]["zone"] == "depot"
    assert event["eventTime"] == "2023-11-14T22:14:20.000Z"  # the second fix's time

    # the webhook: a 500, then the same delivery again, each try signed with its own timestamp
    assert [g[3] for g in receiver.got] == [500, 200]
    (t1, h1, b1, _), (t2, h2, b2, _) = receiver.got
    assert b1 == b2 and json.loads(b2) == event
    assert h1["X-Iotnav-Delivery"] == h2["X-Iotnav-Delivery"] == str(event["id"])
    assert h2["X-Iotnav-Event"] == "geofence_enter" and t2 - t1 >= 0.1
    for h, b in ((h1, b1), (h2, b2)):
        fields = dict(kv.split("=", 1) for kv in h[SIGNATURE_HEADER].split(","))
        mac = hmac.new(SECRET.encode(), fields["t"].encode() + b"." + b, hashlib.sha256).hexdigest()
        assert hmac.compare_digest(mac, fields["v1"]) and abs(time.time() - int(fields["t"])) < 60
    assert verify_signature(SECRET, h2[SIGNATURE_HEADER], b2, time.time())
    assert not verify_signature(SECRET, h2[SIGNATURE_HEADER], b2.replace(b"depot", b"depoT"), time.time())
    assert not verify_signature("other", h2[SIGNATURE_HEADER], b2, time.time())
    assert not verify_signature(SECRET, h2[SIGNATURE_HEADER], b2, time.time() + 3600)  # replayed later

    # MQTT: the same alert under iotnav/alerts/<deviceId>/<kind>
    assert [(t, json.loads(p)) for t, p in mqtt_got] == [
        (f"iotnav/alerts/{event['deviceId']}/geofence_enter", event)
    ]

    # stored with the events
    con = sqlite3.connect(tmp_path / "data" / "iotnav.sqlite")
    rows = con.execute("SELECT id, type, attributes FROM events WHERE type LIKE 'alert_%'").fetchall()
    con.close()
    assert [(r[0], r[1]) for r in rows] == [(event["id"], "alert_geofence_enter")]
    assert json.loads(rows[0][2])["zone"] == "depot"


def test_pump_groups_from_device_attributes_ignition_of_the_fix_and_the_clock(tmp_path) -> None:
    """The rules read what ingest committed: a device's group, the ignition flag of the fix as sent."""
    import sqlalchemy as sa

    from iotnav.service import store
    from iotnav.service.alerts_delivery import AlertService, AlertSettings
    from iotnav.service.ingest import Ingestor
    from iotnav.service.protocols.common import Fix

    db = store.make_engine(store.sqlite_url(tmp_path))
    store.upgrade(db)
    ingestor = Ingestor(db, "none")
    settings = AlertSettings.load(
        {"groups": {"default": {"silent_minutes": 10}, "trucks": {"moved_while_off_m": 50}}}
    )
    rules = AlertService(settings, db, ingestor, executor=None)  # type: ignore[arg-type]
    assert rules.pump(0.0) == []
    t0 = 1_700_000_000.0

    def send(dev: str, k: int, lat: float, ignition: float) -> None:
        fix = Fix(dev, t0 + k, lat, 16.0, h_acc_m=5.0, attributes={"ignition": ignition}, key=f"{dev}{k}")
        ingestor.ingest("teltonika", dev, f"{dev}{k}".encode(), [fix], received_at=t0 + k)

    send("truck1", 0, 48.0, 1.0)
    send("car1", 0, 48.0, 0.0)
    with db.begin() as conn:
        conn.execute(
            store.devices.update()
            .where(store.devices.c.unique_id == "truck1")
            .values(attributes={"group": "trucks"})
        )
    for k in range(1, 40):  # truck parked, ignition off; then towed 3 m/s north with it still off
        send("truck1", k, 48.0 if k < 10 else 48.0 + 3.0 * (k - 10) / 111_200.0, 0.0)
    got = rules.pump(t0 + 40)
    assert [(a["kind"], a["uniqueId"], a["group"]) for a in got] == [("moved_while_off", "truck1", "trucks")]
    # 50 m from the anchor (the first ignition-off fix, k = 1) is passed at k = 27 (51 m; 48 m at 26)
    assert got[0]["eventTime"] == "2023-11-14T22:13:47.000Z"
    # silent: car1 (default group) last received at t0; trucks have no silent rule
    assert rules.pump(t0 + 599) == []
    with db.begin() as conn:  # the database refuses the alert's row: it is stored at the next poll
        conn.exec_driver_sql(
            "CREATE TRIGGER refuse BEFORE INSERT ON events WHEN NEW.type LIKE 'alert_%' "
            "BEGIN SELECT RAISE(ABORT, 'disk full'); END"
        )
    with pytest.raises(sa.exc.IntegrityError, match="disk full"):
        rules.pump(t0 + 600)
    with db.begin() as conn:
        conn.exec_driver_sql("DROP TRIGGER refuse")
    silent = rules.pump(t0 + 601)
    assert [(a["kind"], a["uniqueId"]) for a in silent] == [("silent", "car1")]
    with db.connect() as conn:
        types = conn.execute(sa.select(store.events.c.type).order_by(store.events.c.id)).scalars().all()
    assert types == ["alert_moved_while_off", "alert_silent"]
    assert ingestor.counts["alerts_silent"] == 1


def test_webhook_retries_are_bounded_and_a_4xx_is_not_retried(tmp_path) -> None:
    from iotnav.service import store
    from iotnav.service.alerts_delivery import AlertService, AlertSettings
    from iotnav.service.ingest import Ingestor

    codes: list[int] = []

    class Always(BaseHTTPRequestHandler):
        def do_POST(self) -> None:
            self.rfile.read(int(self.headers["Content-Length"]))
            code = 500 if self.path == "/down" else 410
            codes.append(code)
            self.send_response(code)
            self.send_header("Content-Length", "0")
            self.end_headers()

        def log_message(self, *_: Any) -> None:
            pass

    server = ThreadingHTTPServer(("127.0.0.1", 0), Always)
    threading.Thread(target=server.serve_forever, daemon=True).start()
    base = f"http://127.0.0.1:{server.server_address[1]}"
    ingestor = Ingestor(store.make_engine("sqlite://"), "none")

    async def run(path: str) -> None:
        s = AlertSettings.load(
            {
                "webhook_url": base + path,
                "webhook_secret": "k",
                "webhook_attempts": 3,
                "webhook_backoff_s": 0.05,
            }
        )
        svc = AlertService(s, ingestor.db, ingestor, executor=None)  # type: ignore[arg-type]
        svc.start()
        assert svc._task is not None
        svc._task.cancel()  # no polling here: one alert handed to delivery
        svc.deliver({"id": 1, "kind": "overspeed", "deviceId": 1})
        await svc.stop()

    try:
        asyncio.run(run("/down"))
        assert codes == [500, 500, 500] and ingestor.counts["alerts_webhook_failed"] == 1
        assert ingestor.counts["alerts_webhook_retries"] == 2
        codes.clear()
        asyncio.run(run("/gone"))
        assert codes == [410] and ingestor.counts["alerts_webhook_failed"] == 2
    finally:
        server.shutdown()


def test_alert_settings_refuse_what_cannot_work(monkeypatch) -> None:
    from iotnav.service.alerts_delivery import SECRET_ENV, AlertSettings

    monkeypatch.delenv(SECRET_ENV, raising=False)
    with pytest.raises(ValueError, match="webhook_secret"):
        AlertSettings.load({"webhook_url": "https://example.org/h"})
    monkeypatch.setenv(SECRET_ENV, "from-env")
    assert AlertSettings.load({"webhook_url": "https://example.org/h"}).webhook_secret == "from-env"
    with pytest.raises(ValueError, match="webhok_url"):
        AlertSettings.load({"webhok_url": "https://example.org/h"})
    with pytest.raises(ValueError, match="mqtt://host"):
        AlertSettings.load({"mqtt": "localhost:1883"})
    with pytest.raises(ValueError, match=r"groups\.vans: unknown key"):
        AlertSettings.load({"groups": {"vans": {"overspeed": 80}}})


def test_alerts_file_named_by_the_serve_settings(tmp_path) -> None:
    from iotnav.service.alerts_delivery import AlertSettings

    alerts = tmp_path / "alerts.toml"
    (tmp_path / "serve.toml").write_text(f'[serve]\nalerts = "{alerts}"\n')
    cfg = ServiceConfig.from_toml(tmp_path / "serve.toml")
    head = '[alerts]\nmqtt = "mqtt://127.0.0.1:1884"\n[alerts.groups.trucks]\n'
    alerts.write_text(head + "overspeed = 80\n")
    with pytest.raises(ValueError, match=r"unknown key.*overspeed_kmh"):  # the unit is in the name
        AlertSettings.load(cfg.alerts)
    alerts.write_text(head + "overspeed_kmh = 80\nstop_minutes = 45\n")
    s = AlertSettings.load(cfg.alerts)
    assert s.mqtt == "mqtt://127.0.0.1:1884" and s.groups["trucks"].stop_max_s == 2700.0
    assert s.groups["trucks"].overspeed_mps == pytest.approx(80 / 3.6)
