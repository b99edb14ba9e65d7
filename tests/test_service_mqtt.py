"""OwnTracks over MQTT through a real mosquitto broker the test starts (Debian ``mosquitto``).

QoS 1 on a persistent session with manual acknowledgement after commit: messages published
while the service is killed (-9) are kept by the broker and stored once it is back; a message
in flight at the kill is redelivered and stored once.
"""

from __future__ import annotations

import asyncio
import json
import sqlite3
import time

import aiomqtt

from _service_helpers import FlakyIngestor, Mosquitto, Service


async def _apublish(port: int, messages: list[tuple[str, bytes]]) -> None:
    """Publish ``(topic, payload)`` with QoS 1, each acknowledged by the broker (a phone's app)."""
    async with aiomqtt.Client("127.0.0.1", port, identifier="phone-sim") as c:
        for topic, payload in messages:
            await c.publish(topic, payload, qos=1)


def _publish(port: int, messages: list[tuple[str, bytes]]) -> None:
    asyncio.run(_apublish(port, messages))


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
    try:
        # the subscription exists once the service has connected; wait for its first message
        def send(*ks: int) -> None:
            msgs = [
                {
                    "_type": "location",
                    "lat": 48.0 + k * 1e-4,
                    "lon": 16.0,
                    "tst": 1_700_000_000 + k,
                    "tid": "ph",
                }
                for k in ks
            ]
            topics = [f"owntracks/jane/{dev}" for dev in ("phone", "tablet")]
            _publish(broker.port, [(t, json.dumps(m).encode()) for m in msgs for t in topics])

        send(0)
        assert _wait(db, n_sql, 2) == 2
        send(*range(1, 20))
        assert _wait(db, n_sql, 20, timeout=30) >= 20  # mid-stream
        svc.kill9()
        send(*range(20, 40))  # published while the service is down: kept by the broker
        svc.start()
        assert _wait(db, n_sql, 80) == 80
        time.sleep(1.0)  # nothing more arrives (no duplicates from redelivery)
        assert _count(db, n_sql) == 80
        assert _count(db, "SELECT count(DISTINCT fix_time) FROM positions") == 40
        assert (
            _count(db, "SELECT count(*) FROM devices WHERE unique_id IN ('jane/phone', 'jane/tablet')") == 2
        )
        _publish(broker.port, [("owntracks/jane/phone", b"{not json")])  # acked, counted, dropped
        send(40)
        assert _wait(db, n_sql, 82) == 82  # the bad message did not block the session
    finally:
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
    db = tmp_path / "iotnav.sqlite"
    n_sql = "SELECT count(*) FROM positions"

    async def until(cond, timeout: float) -> None:
        t_end = time.monotonic() + timeout
        while not cond() and time.monotonic() < t_end:
            await asyncio.sleep(0.05)

    async def main() -> tuple[int, int, int]:
        sub = MqttSubscriber(MqttSettings(broker.url, "iotnav-flaky"), ing, executor)
        task = asyncio.create_task(sub.run())
        try:
            await asyncio.wait_for(sub.subscribed.wait(), 20)
            ing.down.set()
            msg = {"_type": "location", "lat": 48.0, "lon": 16.0, "tst": 1_700_000_000, "tid": "ph"}
            await _apublish(broker.port, [("owntracks/jane/phone", json.dumps(msg).encode())])
            await until(lambda: ing.counts.get("mqtt_errors", 0) > 0, 20)
            errors, stored_while_down = ing.counts.get("mqtt_errors", 0), _count(db, n_sql)
            ing.down.clear()  # the database is back: the broker redelivers on the reconnect
            await until(lambda: _count(db, n_sql) > 0, 30)
            return errors, stored_while_down, _count(db, n_sql)
        finally:
            task.cancel()
            await asyncio.gather(task, return_exceptions=True)

    try:
        errors, stored_while_down, stored = asyncio.run(main())
        assert errors >= 1 and stored_while_down == 0
        assert stored == 1
    finally:
        executor.shutdown()
        eng.dispose()
        broker.stop()


def test_a_broker_restart_is_survived(tmp_path) -> None:
    """The subscriber reconnects and subscribes again after the broker went away and came back."""
    from concurrent.futures import ThreadPoolExecutor

    from iotnav.service import store
    from iotnav.service.ingest import Ingestor
    from iotnav.service.mqtt import MqttSettings, MqttSubscriber

    broker = Mosquitto(tmp_path / "broker").start()
    eng = store.make_engine(store.sqlite_url(tmp_path))
    store.upgrade(eng)
    ing = Ingestor(eng, engine_name="none")
    executor = ThreadPoolExecutor(1)
    db = tmp_path / "iotnav.sqlite"

    def msg(k: int) -> bytes:
        return json.dumps({"_type": "location", "lat": 48.0, "lon": 16.0, "tst": 1_700_000_000 + k}).encode()

    async def main() -> tuple[int, int]:
        sub = MqttSubscriber(MqttSettings(broker.url, "iotnav-restart", retry_max_s=1.0), ing, executor)
        task = asyncio.create_task(sub.run())
        try:
            await asyncio.wait_for(sub.subscribed.wait(), 20)
            await _apublish(broker.port, [("owntracks/jane/phone", msg(0))])
            t_end = time.monotonic() + 20
            while _count(db, "SELECT count(*) FROM positions") < 1 and time.monotonic() < t_end:
                await asyncio.sleep(0.05)
            before = _count(db, "SELECT count(*) FROM positions")
            broker.stop()
            while sub.subscribed.is_set() and time.monotonic() < t_end:
                await asyncio.sleep(0.05)
            broker.start()  # same port; a broker without persistence: the session is new
            await asyncio.wait_for(sub.subscribed.wait(), 20)
            await _apublish(broker.port, [("owntracks/jane/phone", msg(1))])
            while _count(db, "SELECT count(*) FROM positions") < 2 and time.monotonic() < t_end + 20:
                await asyncio.sleep(0.05)
            return before, _count(db, "SELECT count(*) FROM positions")
        finally:
            task.cancel()
            await asyncio.gather(task, return_exceptions=True)

    try:
        assert asyncio.run(main()) == (1, 2)
    finally:
        executor.shutdown()
        eng.dispose()
        broker.stop()
