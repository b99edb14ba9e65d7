"""Alerts raised on the workers (real nats-server, real PostgreSQL, a real HTTP webhook receiver).

Two workers share 4 partitions, one a subprocess, one in this process, both with the same
``[alerts]`` settings; each device's group is read from its row in PostgreSQL. Four devices
drive out of a geofence at 80 km/h (``geofence_exit`` and, in the default group,
``overspeed``) while the receiver answers 503, so every alert is stored and its delivery still
retried when the subprocess worker is killed with SIGKILL; the devices then stream on and
drive back in (``geofence_enter``). The survivor takes over the dead worker's partitions: it
delivers the alerts the dead worker had stored but not delivered (their stored ``id``), and
raises no alert twice (its rule state of the moved devices is rebuilt from the database, so
the overspeed period that began before the kill is not reported again). Every alert reaches
the webhook (signed, accepted once), MQTT and the live subject of the edges' WebSocket with
the ``id`` it was stored with, and no other.
"""

from __future__ import annotations

import asyncio
import json
import threading
import time
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from types import SimpleNamespace
from typing import ClassVar

from _cluster_helpers import InProcessWorker, lease_owners, new_database, shared_cluster, start_worker_with
from _service_helpers import Mosquitto, free_ports
from iotnav.service import store
from iotnav.service.alerts_delivery import verify_signature
from iotnav.service.ingest import Message
from iotnav.service.protocols.common import Fix
from iotnav.service.worker_edge import EdgeIngestor
from iotnav.service.workers import (
    ClusterSettings,
    WorkerConfig,
    encode_message,
    open_database,
    partition_of,
)

SECRET = "test-secret"
P = 4
LAT0, LON0 = 48.2, 16.37
M_PER_DEG = 111_200.0  # latitude, m per degree (near enough for the test's geometry)
T0 = 1_765_000_000.0


class Receiver(BaseHTTPRequestHandler):
    """Records every delivery; answers 503 until ``accept`` is set, then 200."""

    got: ClassVar[list[dict]] = []
    accept: ClassVar[threading.Event] = threading.Event()

    def do_POST(self) -> None:
        body = self.rfile.read(int(self.headers["Content-Length"]))
        ok = self.accept.is_set()
        self.got.append({"headers": dict(self.headers), "body": body, "ok": ok, "t": time.time()})
        self.send_response(200 if ok else 503)
        self.send_header("Content-Length", "0")
        self.end_headers()

    def log_message(self, *args: object) -> None:
        pass


def _devices() -> list[str]:
    """Four device ids in four different partitions."""
    out: dict[int, str] = {}
    for k in range(100):
        imei = f"35300000000{k:04d}"
        out.setdefault(partition_of(imei, P), imei)
    return [out[p] for p in range(P)]


def _track() -> list[tuple[float, float]]:
    """(north offset m, speed km/h), one a second: 5 s at 20 km/h from the zone's centre, out at
    80 km/h to 370 m (the zone's radius is 150 m), back in at 80 km/h, and 3 s at 20 km/h."""
    out, y = [], 0.0
    for _ in range(5):
        out.append((y, 20.0))
        y += 5.6
    for _ in range(15):
        out.append((y, 80.0))
        y += 22.2
    for _ in range(12):
        out.append((y, 80.0))
        y -= 22.2
    for _ in range(3):
        out.append((y, 20.0))
    return out


PHASE1 = 14  # fixes before the kill: out of the zone, overspeeding


def _message(imei: str, i: int) -> Message:
    y, kmh = _track()[i]
    t = T0 + i
    f = Fix(imei, t, LAT0 + y / M_PER_DEG, LON0, speed_mps=kmh / 3.6, h_acc_m=5.0, key=f"{imei}-{i:04d}")
    return Message("osmand", imei, f"{imei}/{i}".encode(), [f], None, t, False)


def _publish(url: str, cluster: ClusterSettings, msgs: list[Message], pause_s: float = 0.0) -> None:
    """Publish ``msgs`` as an edge does (``pause_s`` after each round of the devices)."""

    async def go() -> None:
        import nats

        nc = await nats.connect(url)
        js = nc.jetstream()
        for k, m in enumerate(msgs):
            subject = cluster.subject_of(partition_of(m.device, cluster.partitions))
            await js.publish(subject, encode_message(m), headers={"Nats-Msg-Id": m.digest()})
            if pause_s and k % P == P - 1:
                await asyncio.sleep(pause_s)
        await nc.close()

    asyncio.run(go())


class LiveListener(threading.Thread):
    """Collects the alerts the workers publish for the edges' WebSocket (``{"events": [...]}``)."""

    def __init__(self, url: str, subject: str) -> None:
        super().__init__(daemon=True)
        self.url, self.subject = url, subject
        self.got: list[bytes] = []
        self.ready, self.stop = threading.Event(), threading.Event()

    def run(self) -> None:
        async def go() -> None:
            import nats

            nc = await nats.connect(self.url)

            async def on(msg) -> None:
                if b'"events"' in msg.data:
                    self.got.append(msg.data)

            await nc.subscribe(self.subject, cb=on)
            await nc.flush()
            self.ready.set()
            while not self.stop.is_set():
                await asyncio.sleep(0.05)
            await nc.close()

        asyncio.run(go())


def _wait(cond, timeout: float, what: str) -> None:
    t_end = time.monotonic() + timeout
    while not cond():
        if time.monotonic() > t_end:
            raise TimeoutError(what)
        time.sleep(0.05)


def test_worker_alerts_reach_the_webhook_once_across_a_worker_kill(tmp_path) -> None:
    go = tmp_path / "go.json"
    victim = start_worker_with(tmp_path / "victim.log", go)  # (its imports meanwhile)
    nats, pg = shared_cluster()
    url = new_database(pg, "alerts_workers")
    db = open_database(url, 2)
    imeis = _devices()
    now = time.time()
    with db.begin() as con:  # the first device is a truck (its group's rules: no overspeed alert)
        con.execute(
            store.devices.insert().values(
                unique_id=imeis[0], name="truck", created_at=now, attributes={"group": "trucks"}
            )
        )
        con.execute(
            store.geofences.insert().values(name="depot", area=f"CIRCLE ({LAT0} {LON0}, 150)", attributes={})
        )
    broker = Mosquitto(tmp_path / "broker").start()
    import paho.mqtt.client as mqtt

    mqtt_got: list[tuple[str, bytes]] = []
    sub = mqtt.Client(callback_api_version=mqtt.CallbackAPIVersion.VERSION2, client_id="alert-listener")
    subscribed = threading.Event()
    sub.on_connect = lambda c, *_: c.subscribe("iotnav/alerts/#", qos=1)
    sub.on_subscribe = lambda *_: subscribed.set()
    sub.on_message = lambda _c, _u, m: mqtt_got.append((m.topic, bytes(m.payload)))
    sub.connect("127.0.0.1", broker.port)
    sub.loop_start()
    Receiver.got.clear()
    Receiver.accept.clear()
    port = free_ports(1)[0]
    server = ThreadingHTTPServer(("127.0.0.1", port), Receiver)
    threading.Thread(target=server.serve_forever, daemon=True).start()
    alerts = {
        "webhook_url": f"http://127.0.0.1:{port}/hook",
        "webhook_secret": SECRET,
        "webhook_attempts": 1000,
        "webhook_backoff_s": 0.2,
        "webhook_backoff_max_s": 0.3,
        "poll_interval_s": 0.2,
        "mqtt": broker.url,
        "groups": {
            "default": {"geofences": True, "overspeed_kmh": 60},
            "trucks": {"geofences": True, "overspeed_kmh": 100},
        },
    }
    cluster = ClusterSettings(
        url=nats.url,
        partitions=P,
        stream="IOTNAV_AT",
        subject="iotnav.at",
        bucket="iotnav_at_leases",
        lease_s=1.5,
        live_subject="iotnav.atlive",
    )
    config = WorkerConfig(db=url, data=str(tmp_path / "data"), engine="none", alerts=alerts)
    cluster_dict = {k: getattr(cluster, k) for k in cluster.__dataclass_fields__}
    go.with_suffix(".tmp").write_text(json.dumps([config.__dict__, cluster_dict]))
    go.with_suffix(".tmp").rename(go)  # the subprocess worker starts
    survivor = InProcessWorker(config, cluster)
    survivor.start()
    live = LiveListener(nats.url, cluster.live_subject)
    live.start()
    assert live.ready.wait(10)
    try:
        _wait(
            lambda: len(o := lease_owners(nats.url, cluster.bucket)) == P and len(set(o.values())) == 2,
            60,
            "two workers sharing the partitions",
        )
        owners = lease_owners(nats.url, cluster.bucket)
        victim_devs = {m for m in imeis if f"-{victim.pid}-" in owners[partition_of(m, P)]}
        assert victim_devs and len(victim_devs) < len(imeis)
        _publish(nats.url, cluster, [_message(m, i) for i in range(PHASE1) for m in imeis])

        def stored() -> dict[tuple[str, str], list[int]]:
            q = (
                "SELECT d.unique_id, e.type, e.id FROM events e JOIN devices d ON d.id = e.device_id "
                "WHERE left(e.type, 6) = 'alert_' ORDER BY e.id"
            )
            out: dict[tuple[str, str], list[int]] = {}
            with db.connect() as con:
                for uid, typ, eid in con.exec_driver_sql(q):
                    out.setdefault((uid, typ[6:]), []).append(eid)
            return out

        first = {(m, "geofence_exit") for m in imeis} | {(m, "overspeed") for m in imeis[1:]}
        _wait(lambda: set(stored()) == first, 30, "the exit and overspeed alerts stored")
        ids = {k: v[0] for k, v in stored().items()}
        tried = lambda: {json.loads(r["body"])["id"] for r in list(Receiver.got)}  # noqa: E731
        _wait(lambda: set(ids.values()) <= tried(), 10, "every alert tried (and refused) once")
        rest = [_message(m, i) for i in range(PHASE1, len(_track())) for m in imeis]
        streamer = threading.Thread(target=_publish, args=(nats.url, cluster, rest, 0.05))
        streamer.start()  # the devices stream on; the victim is killed in the middle of it
        q = "SELECT count(*) FROM positions p JOIN devices d ON d.id = p.device_id WHERE d.unique_id = '{}'"
        with db.connect() as con:
            victim_stored = lambda: min(  # noqa: E731
                int(con.exec_driver_sql(q.format(m)).scalar() or 0) for m in victim_devs
            )
            _wait(lambda: victim_stored() > PHASE1, 10, "the victim processing the stream")
            assert victim_stored() < len(_track())  # mid-stream: more to come for its devices
        victim.kill()  # SIGKILL: its alerts are stored, their webhook deliveries not finished
        victim.wait(10)
        killed_at = time.time()
        Receiver.accept.set()
        streamer.join(30)
        every = first | {(m, "geofence_enter") for m in imeis}
        _wait(lambda: set(stored()) == every, 30, "the enter alerts stored")
        ids = {k: v[0] for k, v in stored().items()}
        delivered = lambda: {json.loads(r["body"])["id"] for r in list(Receiver.got) if r["ok"]}  # noqa: E731
        _wait(lambda: set(ids.values()) <= delivered(), 20, "every alert delivered")
        assert set(lease_owners(nats.url, cluster.bucket).values()) == {survivor_id(survivor, owners)}
        time.sleep(0.3)  # (a duplicate would come now)
        # stored once each (the survivor rebuilt the moved devices' rule state: no second overspeed)
        assert all(len(v) == 1 for v in stored().values()), stored()
        by_id: dict[int, list[dict]] = {}
        for r in list(Receiver.got):
            body, h = r["body"], r["headers"]
            assert verify_signature(SECRET, h["X-Iotnav-Signature"], body, r["t"]), h
            a = json.loads(body)
            assert h["Idempotency-Key"] == h["X-Iotnav-Delivery"] == str(a["id"])
            assert ids[(a["uniqueId"], a["kind"])] == a["id"]  # any repeat carries the stored id
            by_id.setdefault(a["id"], []).append(r)
        for (m, kind), eid in ids.items():
            oks = [r for r in by_id[eid] if r["ok"]]
            assert len(oks) == 1, (m, kind, len(oks))  # delivered once (a retry only after a 503)
            if m in victim_devs and kind != "geofence_enter":  # raised on the victim, before the kill,
                assert min(r["t"] for r in by_id[eid]) < killed_at  # delivered by the survivor
        # MQTT (QoS 1, published again on a redelivery): every alert, only with its stored id
        assert subscribed.wait(5)
        _wait(lambda: {json.loads(b)["id"] for _, b in list(mqtt_got)} == set(ids.values()), 5, "mqtt")
        for topic, body in mqtt_got:
            a = json.loads(body)
            assert (
                ids[(a["uniqueId"], a["kind"])] == a["id"]
                and topic == f"iotnav/alerts/{a['deviceId']}/{a['kind']}"
            )
        # the edges' WebSocket: every alert (at most once: it is a live view), as an edge forwards it
        socket = [a for body in live.got for a in json.loads(body)["events"]]
        assert {a["id"] for a in socket} == set(ids.values())
        edge = EdgeIngestor(db, "none", cluster=cluster)
        sent: list[dict] = []
        edge.socket_send = sent.append
        asyncio.run(edge._on_live(SimpleNamespace(data=live.got[0])))
        assert sent == [json.loads(live.got[0])]
        with db.connect() as con:
            states = con.exec_driver_sql(
                "SELECT attributes FROM events WHERE left(type, 6) = 'alert_'"
            ).scalars()
            assert {json.loads(s)["delivery"] if isinstance(s, str) else s["delivery"] for s in states} == {
                "delivered"
            }
    finally:
        if victim.poll() is None:
            victim.kill()
            victim.wait(10)
        survivor.stop()
        live.stop.set()
        server.shutdown()
        sub.loop_stop()
        broker.stop()
        db.dispose()


def survivor_id(survivor: InProcessWorker, owners: dict[int, str]) -> str:
    import os

    return next(o for o in owners.values() if f"-{os.getpid()}-" in o)
