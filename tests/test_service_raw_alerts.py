"""Alerts of devices streaming raw GNSS + IMU batches (:mod:`iotnav.service.raw_ingest`).

A simulated car (``car-tunnel``, 24 s, moving from 4 s) sends its raw batches over MQTT
through a real mosquitto to a real ``iotnav serve`` (the service's engine for fix-only devices
``none``, the raw devices' ``pipeline``) and drives into a circle around its true position at
20 s; an OsmAnd device drives into the same zone over HTTP. Each raises exactly one
``geofence_enter``, stored once and delivered once to a webhook receiver; the car's is raised
on its fused (``pipeline``) positions, not on its fixes as sent (stored with ``engine = none``,
the fix-only devices' engine here): one stream per device. The same batches on the workers
(``iotnav worker --alerts``): in process through the partition's fetch handling, and through a
real nats-server and PostgreSQL to a webhook receiver.
"""

from __future__ import annotations

import asyncio
import hashlib
import json
import math
import sqlite3
import time

import httpx
import pytest

from _service_helpers import FetchedMessage, Mosquitto, Service, WebhookReceiver

CAR = "car-9"


def _count(db, sql: str) -> int:
    con = sqlite3.connect(db, timeout=10)
    try:
        return int(con.execute(sql).fetchone()[0])
    finally:
        con.close()


@pytest.fixture(scope="module")
def drive(tmp_path_factory: pytest.TempPathFactory) -> tuple[object, list[bytes], float, float]:
    """The log of a 24 s drive (moving from 4 s), its raw batches (1 s each) and the centre of the
    zone: the car's true position at 20 s."""
    from iotnav import sim
    from iotnav.io import ingest
    from iotnav.service.raw_ingest import log_batches

    out = tmp_path_factory.mktemp("drive")
    res = sim.build("car-tunnel", seed=5, overrides={"duration_s": 24.0, "motion.wait_start_s": 4.0})
    sim.write(res, out)
    log = ingest([out])
    truth = res.truth
    k20 = int((truth["t"] - 20.0).abs().idxmin())
    lat0, lon0 = float(truth["lat"].iloc[k20]), float(truth["lon"].iloc[k20])
    north = (truth["lat"].to_numpy() - lat0) * 111_200.0
    east = (truth["lon"].to_numpy() - lon0) * 111_200.0 * math.cos(math.radians(lat0))
    # a zone of 80 m around it: the car starts 150 m away, ends 60 m past its centre (inside)
    assert math.hypot(north[0], east[0]) > 140.0 and math.hypot(north[-1], east[-1]) < 65.0
    return log, list(log_batches(log)), lat0, lon0


def test_raw_device_driving_into_a_geofence_raises_one_alert_on_its_fused_track(tmp_path, drive) -> None:
    import aiomqtt

    log, batches, lat0, lon0 = drive
    broker = Mosquitto(tmp_path / "broker").start()
    receiver = WebhookReceiver()
    (tmp_path / "alerts.toml").write_text(
        "[alerts]\n"
        f'webhook_url = "{receiver.url}"\nwebhook_secret = "s"\n'
        "poll_interval_s = 0.05\ngeofence_reload_s = 0.05\n"
        "[alerts.groups.default]\ngeofences = true\n"
    )
    svc = Service(
        tmp_path / "data",
        mqtt=broker.url,
        mqtt_client_id="iotnav-raw-alerts",
        raw_engine="pipeline",
        alerts=str(tmp_path / "alerts.toml"),
    )
    db = tmp_path / "data" / "iotnav.sqlite"
    try:
        svc.start()
        auth = {"Authorization": f"Bearer {svc.admin_token}"}
        zone = {"name": "yard", "area": f"CIRCLE ({lat0} {lon0}, 80)"}
        assert httpx.post(svc.url("/api/geofences"), json=zone, headers=auth).is_success
        time.sleep(0.3)  # the zone is read by the alerts

        async def publish() -> None:
            async with aiomqtt.Client("127.0.0.1", broker.port, identifier="car-sim") as c:
                t_end = time.monotonic() + 60
                while _count(db, "SELECT count(*) FROM raw_messages") == 0 and time.monotonic() < t_end:
                    await c.publish(f"iotnav/{CAR}/raw", batches[0], qos=1)  # until subscribed
                    await asyncio.sleep(0.3)
                for p in batches[1:]:
                    await c.publish(f"iotnav/{CAR}/raw", p, qos=1)

        asyncio.run(publish())
        for k, lat in enumerate((lat0 + 0.01, lat0)):  # a fix-only device: 1.1 km north, then inside
            q = {"id": "van3", "lat": lat, "lon": lon0, "timestamp": 1_700_000_000 + 60 * k, "accuracy": 5}
            assert httpx.get(svc.url("/", svc.osmand), params=q).status_code == 200
        t_end = time.monotonic() + 30
        while time.monotonic() < t_end and (
            _count(db, "SELECT count(*) FROM raw_messages WHERE protocol = 'iotnav_raw'") < len(batches)
            or len(receiver.got) < 2
        ):
            time.sleep(0.1)
        time.sleep(0.5)  # an alert raised twice would be delivered by now
    finally:
        svc.stop()
        receiver.server.shutdown()
        broker.stop()

    con = sqlite3.connect(db)
    stored = con.execute(
        "SELECT e.id, d.unique_id, e.type, e.event_time FROM events e JOIN devices d ON d.id = e.device_id"
        " WHERE e.type LIKE 'alert_%' ORDER BY d.unique_id"
    ).fetchall()
    fused = con.execute(
        "SELECT fix_time, latitude, longitude FROM positions p JOIN devices d ON d.id = p.device_id"
        f" WHERE d.unique_id = '{CAR}' AND engine = 'pipeline'"
    ).fetchall()
    fixes = con.execute(
        "SELECT latitude, longitude FROM positions p JOIN devices d ON d.id = p.device_id"
        f" WHERE d.unique_id = '{CAR}' AND engine = 'none'"
    ).fetchall()
    con.close()
    assert len(fused) > 20 and len(fixes) == len(log.gnss)
    assert [(u, t) for _, u, t, _ in stored] == [
        (CAR, "alert_geofence_enter"),
        ("van3", "alert_geofence_enter"),
    ]
    delivered = sorted(
        (json.loads(b) for _, _, b, code in receiver.got if code == 200), key=lambda a: a["uniqueId"]
    )
    assert [(a["id"], a["uniqueId"], a["kind"]) for a in delivered] == [
        (stored[0][0], CAR, "geofence_enter"),
        (stored[1][0], "van3", "geofence_enter"),
    ]
    car = delivered[0]
    assert car["attributes"]["zone"] == "yard"
    # raised on a fused position (its time and place), not on a fix as the car sent it
    at = [(lat, lon) for t, lat, lon in fused if t == stored[0][3]]
    assert at == [(car["latitude"], car["longitude"])]
    assert (car["latitude"], car["longitude"]) not in fixes


def test_worker_raises_a_raw_devices_alert_once_in_its_batch_transaction(tmp_path, drive) -> None:
    """``iotnav worker --alerts``: a raw device's batches (stored by the partition's
    RawProcessor, not by the fixes' ingest) go through the partition's rules in their own
    transaction: one ``geofence_enter`` on a fused position, stored with its key and
    ``delivery: pending`` (the outbox) and handed out once. A new owner of the partition gets
    the last two batches again (not acknowledged) and the rest: it raises nothing again."""
    import sqlalchemy as sa

    from iotnav.service import store
    from iotnav.service.alerts_delivery import AlertSettings
    from iotnav.service.checkpoint import load_key
    from iotnav.service.ingest import Message
    from iotnav.service.raw_ingest import RawProcessor
    from iotnav.service.workers import (
        AlertingIngestor,
        ClusterSettings,
        Worker,
        _Lease,
        encode_message,
    )

    _, batches, lat0, lon0 = drive
    db = store.make_engine(store.sqlite_url(tmp_path))
    store.upgrade(db)
    with db.begin() as con:
        con.execute(
            store.geofences.insert().values(name="yard", area=f"CIRCLE ({lat0} {lon0}, 80)", attributes={})
        )
    settings = AlertSettings.load({"groups": {"default": {"geofences": True}}})
    key = load_key(tmp_path)
    wire = [Message("iotnav_raw", CAR, p, [], f"iotnav/{CAR}/raw") for p in batches]

    def owner(msgs: list[Message]) -> tuple[AlertingIngestor, list[dict]]:
        """A partition owner (fresh rule and engine state) storing ``msgs`` in fetches of 4."""
        ing = AlertingIngestor(db, "none", checkpoint_key=key, alert_settings=settings)
        raw = RawProcessor(ing)
        worker = Worker(ClusterSettings(partitions=4), lambda: ing)
        lease = _Lease(0, 1, time.monotonic() + 3600.0)
        acks: list[bytes] = []

        async def run() -> None:
            for k in range(0, len(msgs), 4):
                fetch = [FetchedMessage(encode_message(m), acks) for m in msgs[k : k + 4]]
                await worker._process(lease, ing, raw, fetch, asyncio.get_running_loop())

        asyncio.run(run())
        assert worker.stats.failed == 0 and len(acks) == (len(msgs) + 3) // 4
        return ing, ing.alerts.take()

    first, handed = owner(wire[:18])
    second, again = owner(wire[16:])
    assert again == [] and second.alerts.counts.get("alerts_geofence_enter", 0) == 0
    assert second.counts["duplicate_message"] == 2
    with db.connect() as con:
        rows = con.execute(sa.select(store.events).where(store.events.c.type.like("alert_%"))).all()
        fused = con.execute(
            sa.select(
                store.positions.c.fix_time, store.positions.c.latitude, store.positions.c.longitude
            ).where(store.positions.c.engine == "pipeline")
        ).all()
    (row,) = rows
    assert row.type == "alert_geofence_enter" and row.attributes["zone"] == "yard"
    assert row.attributes["delivery"] == "pending"
    text = f"{CAR}|geofence_enter|{row.event_time!r}|yard"  # the documented key (alert_key)
    assert row.attributes["key"] == hashlib.sha256(text.encode()).hexdigest()[:32]
    assert [(a["id"], a["uniqueId"], a["kind"]) for a in handed] == [(row.id, CAR, "geofence_enter")]
    # on a fused position of the car (its time and place)
    at = [(lat, lon) for t, lat, lon in fused if t == row.event_time]
    assert at == [(handed[0]["latitude"], handed[0]["longitude"])]
    first.close()
    second.close()
    db.dispose()


def test_worker_delivers_a_raw_devices_alert_through_jetstream_and_postgres(tmp_path, drive) -> None:
    """The same on a real nats-server and PostgreSQL: a worker (``--alerts``, raw engine
    ``pipeline``) fed the car's raw batches from JetStream delivers its one ``geofence_enter``
    to a webhook receiver once and writes ``delivered`` in the outbox."""
    from _cluster_helpers import InProcessWorker, lease_owners, new_database, shared_cluster
    from iotnav.service import store
    from iotnav.service.ingest import Message
    from iotnav.service.workers import (
        ClusterSettings,
        WorkerConfig,
        encode_message,
        open_database,
        partition_of,
    )

    _, batches, lat0, lon0 = drive
    nats, pg = shared_cluster()
    url = new_database(pg, "raw_alerts")
    db = open_database(url, 2)
    with db.begin() as con:
        con.execute(
            store.geofences.insert().values(name="yard", area=f"CIRCLE ({lat0} {lon0}, 80)", attributes={})
        )
    receiver = WebhookReceiver()
    alerts = {
        "webhook_url": receiver.url,
        "webhook_secret": "s",
        "poll_interval_s": 0.1,
        "groups": {"default": {"geofences": True}},
    }
    cluster = ClusterSettings(
        url=nats.url,
        partitions=2,
        stream="IOTNAV_RA",
        subject="iotnav.ra",
        bucket="iotnav_ra_leases",
        lease_s=1.5,
        live_subject="iotnav.ralive",
    )
    worker = InProcessWorker(
        WorkerConfig(db=url, data=str(tmp_path / "data"), engine="none", alerts=alerts), cluster
    )
    worker.start()
    try:
        t_end = time.monotonic() + 30
        while len(lease_owners(nats.url, cluster.bucket)) < 2 and time.monotonic() < t_end:
            time.sleep(0.05)

        async def publish() -> None:
            import nats as nats_client

            nc = await nats_client.connect(nats.url)
            js = nc.jetstream()
            subject = cluster.subject_of(partition_of(CAR, cluster.partitions))
            for p in batches:
                m = Message("iotnav_raw", CAR, p, [], f"iotnav/{CAR}/raw")
                await js.publish(subject, encode_message(m), headers={"Nats-Msg-Id": m.digest()})
            await nc.close()

        asyncio.run(publish())
        q = "SELECT count(*) FROM raw_messages"
        t_end = time.monotonic() + 30
        while time.monotonic() < t_end:
            with db.connect() as con:
                if con.exec_driver_sql(q).scalar_one() == len(batches) and receiver.got:
                    break
            time.sleep(0.05)
        time.sleep(0.5)  # a second delivery would be made by now
    finally:
        worker.stop()
        receiver.server.shutdown()
    with db.connect() as con:
        rows = con.exec_driver_sql(
            "SELECT id, type, attributes FROM events WHERE left(type, 6) = 'alert_'"
        ).all()
    db.dispose()
    (row,) = rows
    assert row[1] == "alert_geofence_enter" and row[2]["delivery"] == "delivered"
    assert [json.loads(b)["id"] for _, _, b, code in receiver.got] == [row[0]]
