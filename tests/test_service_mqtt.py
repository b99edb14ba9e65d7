"""OwnTracks over MQTT through a real mosquitto broker the test starts (Debian ``mosquitto``).

QoS 1 on a persistent session with manual acknowledgement after commit: messages published
while the service is killed (-9) are kept by the broker and stored once it is back; a message
in flight at the kill is redelivered and stored once.
"""

from __future__ import annotations

import json
import sqlite3
import time

import paho.mqtt.client as mqtt

from _service_helpers import FlakyIngestor, Mosquitto, Service


def _publisher(url_port: int) -> mqtt.Client:
    c = mqtt.Client(callback_api_version=mqtt.CallbackAPIVersion.VERSION2, client_id="phone-sim")
    c.connect("127.0.0.1", url_port)
    c.loop_start()
    return c


def _count(db, sql: str) -> int:
    con = sqlite3.connect(db, timeout=10)
    try:
        return int(con.execute(sql).fetchone()[0])
    finally:
        con.close()


def _wait(db, sql: str, n: int, timeout: float = 60.0) -> int:
    t_end = time.monotonic() + timeout
    got = -1
    while time.monotonic() < t_end:
        got = _count(db, sql)
        if got >= n:
            return got
        time.sleep(0.1)
    return got


def test_owntracks_mqtt_qos1_survives_kill9(tmp_path) -> None:
    broker = Mosquitto(tmp_path / "broker").start()
    svc = Service(tmp_path / "data", mqtt=broker.url, mqtt_client_id="iotnav-test").start()
    db = tmp_path / "data" / "iotnav.sqlite"
    n_sql = "SELECT count(*) FROM positions WHERE engine = 'none'"
    pub = _publisher(broker.port)
    try:
        # the subscription exists once the service has connected; wait for its first message
        def send(k: int) -> None:
            msg = {
                "_type": "location",
                "lat": 48.0 + k * 1e-4,
                "lon": 16.0,
                "tst": 1_700_000_000 + k,
                "tid": "ph",
            }
            for dev in ("phone", "tablet"):
                pub.publish(f"owntracks/jane/{dev}", json.dumps(msg), qos=1).wait_for_publish(10)

        send(0)
        assert _wait(db, n_sql, 2) == 2
        for k in range(1, 20):
            send(k)
        assert _wait(db, n_sql, 20, timeout=30) >= 20  # mid-stream
        svc.kill9()
        for k in range(20, 40):  # published while the service is down: kept by the broker
            send(k)
        svc.start()
        assert _wait(db, n_sql, 80) == 80
        time.sleep(1.0)  # nothing more arrives (no duplicates from redelivery)
        assert _count(db, n_sql) == 80
        assert _count(db, "SELECT count(DISTINCT fix_time) FROM positions") == 40
        assert (
            _count(db, "SELECT count(*) FROM devices WHERE unique_id IN ('jane/phone', 'jane/tablet')") == 2
        )
        pub.publish("owntracks/jane/phone", b"{not json", qos=1).wait_for_publish(
            10
        )  # acked, counted, dropped
        send(40)
        assert _wait(db, n_sql, 82) == 82  # the bad message did not block the session
    finally:
        pub.loop_stop()
        pub.disconnect()
        svc.stop()
        broker.stop()


def test_storage_failure_is_not_acknowledged_and_redelivered(tmp_path) -> None:
    from concurrent.futures import ThreadPoolExecutor

    from iotnav.service import store
    from iotnav.service.mqtt import MqttSettings, MqttSubscriber

    broker = Mosquitto(tmp_path / "broker").start()
    eng = store.make_engine(store.sqlite_url(tmp_path))
    store.upgrade(eng)
    ing = FlakyIngestor(eng, engine_name="none")
    executor = ThreadPoolExecutor(1)
    sub = MqttSubscriber(MqttSettings(broker.url, "iotnav-flaky"), ing, executor)
    sub.start()
    pub = _publisher(broker.port)
    db = tmp_path / "iotnav.sqlite"
    try:
        t_end = time.monotonic() + 20
        while not sub.client.is_connected() and time.monotonic() < t_end:
            time.sleep(0.05)
        time.sleep(0.3)  # subscribed
        ing.down.set()
        msg = {"_type": "location", "lat": 48.0, "lon": 16.0, "tst": 1_700_000_000, "tid": "ph"}
        pub.publish("owntracks/jane/phone", json.dumps(msg), qos=1).wait_for_publish(10)
        t_end = time.monotonic() + 20
        while ing.counts.get("mqtt_errors", 0) == 0 and time.monotonic() < t_end:
            time.sleep(0.05)
        assert ing.counts["mqtt_errors"] >= 1 and _count(db, "SELECT count(*) FROM positions") == 0
        ing.down.clear()  # the database is back: the broker redelivers on the reconnect
        assert _wait(db, "SELECT count(*) FROM positions", 1, timeout=30) == 1
    finally:
        pub.loop_stop()
        pub.disconnect()
        sub.stop()
        executor.shutdown()
        eng.dispose()
        broker.stop()
