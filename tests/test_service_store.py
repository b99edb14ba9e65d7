"""Storage and ingest of ``iotnav serve`` (in-process, no sockets).

Each test runs on a real SQLite file and on a real PostgreSQL database (a throw-away cluster
of the Debian ``postgresql`` package, started by the test).
"""

from __future__ import annotations

import hashlib
import json
import math
import subprocess
import sys
import time
import uuid
from typing import Any

import pytest
import sqlalchemy as sa
from alembic.autogenerate import compare_metadata
from alembic.migration import MigrationContext

from _service_helpers import Postgres, codec8_packet
from iotnav.engines.base import GnssSample, Output
from iotnav.service import store
from iotnav.service.ingest import Ingestor
from iotnav.service.protocols.teltonika import decode_avl


@pytest.fixture(scope="module")
def postgres():
    pg = Postgres().start()
    yield pg
    pg.stop()


@pytest.fixture(params=["sqlite", "postgresql"])
def empty_db(request, tmp_path):
    """An empty service database: a SQLite file, or a fresh database on a PostgreSQL cluster."""
    if request.param == "sqlite":
        url = store.sqlite_url(tmp_path)
    else:
        pg = request.getfixturevalue("postgres")
        name = f"t{uuid.uuid4().hex[:12]}"
        admin = sa.create_engine(pg.url, isolation_level="AUTOCOMMIT")
        with admin.connect() as conn:
            conn.exec_driver_sql(f"CREATE DATABASE {name}")
        admin.dispose()
        url = pg.url.replace("/postgres?", f"/{name}?")
    eng = store.make_engine(url)
    yield eng
    eng.dispose()


@pytest.fixture
def db(empty_db):
    """The service database at head (:func:`empty_db` upgraded)."""
    store.upgrade(empty_db)
    return empty_db


def test_migrations_build_the_declared_schema(db) -> None:
    store.upgrade(db)  # a second upgrade is a no-op
    with db.connect() as conn:
        assert compare_metadata(MigrationContext.configure(conn), store.metadata) == []
        assert conn.exec_driver_sql("SELECT version_num FROM alembic_version").scalar() == "0004"
        if db.dialect.name == "sqlite":
            assert conn.exec_driver_sql("PRAGMA journal_mode").scalar() == "wal"
            assert conn.exec_driver_sql("PRAGMA synchronous").scalar() == 2  # FULL


def test_processes_starting_at_once_on_a_fresh_postgresql_all_upgrade(postgres) -> None:
    """A service and its workers started together on an empty database: each process's upgrade
    succeeds (before the advisory lock, the second died creating ``alembic_version`` twice;
    with the workers on a lock key of their own, a worker and the service still raced)."""
    name = f"t{uuid.uuid4().hex[:12]}"
    admin = sa.create_engine(postgres.url, isolation_level="AUTOCOMMIT")
    with admin.connect() as conn:
        conn.exec_driver_sql(f"CREATE DATABASE {name}")
    admin.dispose()
    url = postgres.url.replace("/postgres?", f"/{name}?")
    service = "import sys; from iotnav.service import store; store.upgrade(store.make_engine(sys.argv[1]))"
    worker = "import sys; from iotnav.service.workers import open_database; open_database(sys.argv[1], 2)"
    procs = [  # two as `iotnav serve` opens it, two as `iotnav worker` does
        subprocess.Popen([sys.executable, "-c", code, url], stderr=subprocess.PIPE, text=True)
        for code in (service, worker, service, worker)
    ]
    errors = [p.communicate(timeout=120)[1] for p in procs]
    assert [p.returncode for p in procs] == [0, 0, 0, 0], errors
    eng = store.make_engine(url)
    with eng.connect() as conn:
        assert conn.exec_driver_sql("SELECT version_num FROM alembic_version").scalars().all() == ["0004"]
        assert compare_metadata(MigrationContext.configure(conn), store.metadata) == []
    eng.dispose()


def test_upgrade_from_0001_keeps_the_data(tmp_path) -> None:
    eng = store.make_engine(store.sqlite_url(tmp_path))
    store.upgrade(eng, "0001")
    with eng.begin() as conn:
        conn.exec_driver_sql(
            "INSERT INTO geofences (name, area, attributes) VALUES ('depot', 'CIRCLE (48 16, 100)', '{}')"
        )
    store.upgrade(eng)
    with eng.connect() as conn:
        row = conn.execute(sa.select(store.geofences)).one()
        assert (row.name, row.description, row.area) == ("depot", None, "CIRCLE (48 16, 100)")
        assert compare_metadata(MigrationContext.configure(conn), store.metadata) == []
    eng.dispose()


def test_upgrade_to_binary_raw_keys_keeps_every_message_and_still_refuses_resends(empty_db) -> None:
    """A database at 0003 with messages stored by the hex-key version: the upgrade to 0004 keeps
    every raw message and the positions' links to them (SQLite rebuilds the table: with foreign
    keys on, its DROP would set every ``raw_id`` to NULL), turns each key into the digest's bytes,
    and a message resent after the upgrade is refused as a duplicate while a new one is stored."""
    eng = empty_db
    store.upgrade(eng, "0003")
    imei = "350000000000001"
    packets = [_packet(2, t0_ms=1_700_000_000_000 + 10_000 * k)[0] for k in range(3)]
    hexkeys = [hashlib.sha256(imei.encode() + b"\x00" + p).hexdigest() for p in packets]  # 0003's key
    with eng.begin() as conn:
        dev = store.inserted_id(
            conn.execute(
                store.devices.insert().values(unique_id=imei, name=imei, created_at=1.0, attributes={})
            )
        )
        for k, (p, key) in enumerate(zip(packets, hexkeys, strict=True)):
            raw = conn.execute(
                sa.text(
                    "INSERT INTO raw_messages (device_id, protocol, received_at, payload, dedup_key, n_records) "
                    "VALUES (:d, 'teltonika', :t, :p, :k, 2) RETURNING id"
                ),
                {"d": dev, "t": 2.0 + k, "p": p, "k": key},
            ).scalar_one()
            conn.execute(
                store.positions.insert().values(
                    device_id=dev,
                    raw_id=raw,
                    engine="none",
                    fix_time=1.7e9 + 10 * k,
                    server_time=2.0 + k,
                    valid=True,
                    latitude=48.0,
                    longitude=16.0,
                    attributes={},
                    dedup_key=f"r{k}",
                )
            )
    store.upgrade(eng)
    with eng.connect() as conn:
        assert compare_metadata(MigrationContext.configure(conn), store.metadata) == []
        raws = conn.execute(sa.select(store.raw_messages).order_by(store.raw_messages.c.id)).all()
        links = (
            conn.execute(sa.select(store.positions.c.raw_id).order_by(store.positions.c.id)).scalars().all()
        )
    assert [bytes(r.dedup_key) for r in raws] == [bytes.fromhex(k) for k in hexkeys]
    assert [bytes(r.payload) for r in raws] == packets
    assert links == [r.id for r in raws]
    ing = Ingestor(eng, engine_name="none")
    for p in packets:  # resent after the upgrade: the converted key refuses them
        res = ing.ingest("teltonika", imei, p, decode_avl(p, imei).records)
        assert res.accepted and res.duplicate
    new = _packet(1, t0_ms=1_700_000_100_000)[0]
    assert not ing.ingest("teltonika", imei, new, decode_avl(new, imei).records).duplicate
    with eng.connect() as conn:
        assert conn.execute(sa.select(sa.func.count()).select_from(store.raw_messages)).scalar() == 4
    with pytest.raises(sa.exc.IntegrityError):  # the unique key itself, not only the ingest's read
        with eng.begin() as conn:
            conn.execute(
                store.raw_messages.insert().values(
                    device_id=dev,
                    protocol="teltonika",
                    received_at=9.0,
                    payload=b"x",
                    dedup_key=bytes.fromhex(hexkeys[0]),
                    n_records=0,
                )
            )


def test_geofence_areas() -> None:
    from iotnav.service.geofence import parse_area

    a = parse_area("CIRCLE (48.2 16.37, 250.5)")
    assert (a.kind, a.points, a.radius_m) == ("circle", ((48.2, 16.37),), 250.5)
    p = parse_area("POLYGON ((48 16, 48.1 16, 48.1 16.1, 48 16))")
    assert p.kind == "polygon" and p.points[2] == (48.1, 16.1)
    assert parse_area("linestring (1 2, 3 4)").points == ((1.0, 2.0), (3.0, 4.0))
    for bad in (
        "CIRCLE (48 16, -5)",
        "CIRCLE (95 16, 5)",
        "POLYGON ((1 2, 3 4))",
        "SQUARE (1 2)",
        "CIRCLE (1, 2)",
    ):
        with pytest.raises(ValueError):
            parse_area(bad)


def _packet(n: int, t0_ms: int = 1_700_000_000_000):
    pkt = codec8_packet([(t0_ms + 1000 * i, 48.0 + 1e-4 * i, 16.0, 36, 9) for i in range(n)])
    res = decode_avl(pkt, "350000000000001")
    return pkt, res.records


def test_ingest_stores_raw_and_fixes_once(db) -> None:
    ing = Ingestor(db, engine_name="none")
    pkt, recs = _packet(3)
    r = ing.ingest("teltonika", "350000000000001", pkt, recs, "127.0.0.1:1")
    assert r.accepted and not r.duplicate and r.n_new == 3
    again = ing.ingest("teltonika", "350000000000001", pkt, recs)
    assert again.accepted and again.duplicate and again.n_new == 0
    # a different packet repeating two of the records: only the new one is stored
    pkt2 = codec8_packet(
        [
            (1_700_000_001_000, 48.0001, 16.0, 36, 9),
            (1_700_000_002_000, 48.0002, 16.0, 36, 9),
            (1_700_000_003_000, 48.0003, 16.0, 36, 9),
        ]
    )
    r2 = ing.ingest("teltonika", "350000000000001", pkt2, decode_avl(pkt2, "350000000000001").records)
    assert r2.n_new == 1 and ing.counts["duplicate_record"] == 2
    other = store.make_engine(db.url)  # another connection sees the commit
    with other.connect() as con:
        assert con.exec_driver_sql("SELECT count(*) FROM raw_messages").scalar() == 2
        q = "SELECT fix_time, latitude, speed_mps, engine FROM positions ORDER BY fix_time"
        rows = con.exec_driver_sql(q).all()
        payload = con.exec_driver_sql("SELECT payload FROM raw_messages ORDER BY id").scalar()
    other.dispose()
    assert [r[0] for r in rows] == [1.7e9, 1.7e9 + 1, 1.7e9 + 2, 1.7e9 + 3]
    assert rows[1][1] == pytest.approx(48.0001) and rows[0][2] == pytest.approx(10.0)  # 36 km/h
    assert {r[3] for r in rows} == {"none"}
    assert bytes(payload) == pkt  # as received


def test_registration_closed_refuses_unknown_devices(db) -> None:
    ing = Ingestor(db, engine_name="none", registration_open=False)
    pkt, recs = _packet(1)
    assert not ing.device_allowed("350000000000001")
    assert not ing.ingest("teltonika", "350000000000001", pkt, recs).accepted
    with db.begin() as conn:
        conn.execute(
            store.devices.insert().values(
                unique_id="350000000000001", name="truck", created_at=0.0, attributes={}
            )
        )
    assert ing.device_allowed("350000000000001")
    assert ing.ingest("teltonika", "350000000000001", pkt, recs).n_new == 1


def test_unavailable_engine_falls_back_to_none(db) -> None:
    ing = Ingestor(db, engine_name="no-such-engine")
    assert ing.engine_name == "none" and ing.engine_requested == "no-such-engine"


class _EchoEngine:
    """Test double with the Engine protocol: one Output per GNSS sample, at the fix.

    It checks the dispatch plumbing only (time order, late fixes, rows, events); the real
    ``fixes`` engine's track is checked in ``tests/test_service_engine.py``.
    """

    def __init__(self) -> None:
        self.events: list[dict[str, Any]] = []
        self.seen: list[float] = []

    def step(self, s: GnssSample) -> Output | None:
        self.seen.append(s.t)
        if len(self.seen) == 1:
            self.events.append({"type": "first_fix", "t": s.t})
        nan = math.nan
        return Output(
            s.t,
            s.lat_deg,
            s.lon_deg,
            s.height_m,
            nan,
            nan,
            nan,
            1.0,
            0.0,
            0.0,
            nan,
            nan,
            nan,
            False,
            2.0,
            2.0,
            "fix",
        )

    @property
    def mount_yaw_rad(self) -> float:
        return math.nan

    def summary(self) -> dict[str, Any]:
        return {}


def test_dispatch_feeds_each_device_engine_in_time_order(db) -> None:
    engines: list[_EchoEngine] = []

    def factory() -> _EchoEngine:
        engines.append(_EchoEngine())
        return engines[-1]

    ing = Ingestor(db, engine_name="echo", engine_factory=factory)
    t0 = 1_700_000_000_000
    # records sent out of order within a packet are fed sorted; an older one later is "late"
    pkt = codec8_packet(
        [(t0 + 2000, 48.0, 16.0, 0, 9), (t0, 48.0, 16.0, 0, 9), (t0 + 1000, 48.0, 16.0, 0, 9)]
    )
    ing.ingest("teltonika", "A", pkt, decode_avl(pkt, "A").records)
    late = codec8_packet([(t0 + 500, 48.0, 16.0, 0, 9)])
    ing.ingest("teltonika", "A", late, decode_avl(late, "A").records)
    other = codec8_packet([(t0, 10.0, 20.0, 0, 9)])
    ing.ingest("teltonika", "B", other, decode_avl(other, "B").records)
    assert len(engines) == 2  # one per device
    assert engines[0].seen == [1.7e9, 1.7e9 + 1, 1.7e9 + 2] and engines[1].seen == [1.7e9]
    with db.connect() as conn:
        q = sa.select(store.positions.c.engine, sa.func.count()).group_by(store.positions.c.engine)
        assert dict(conn.execute(q).all()) == {"none": 5, "echo": 4}
        ev = conn.execute(sa.select(store.events.c.type, store.events.c.event_time)).all()
        speed = conn.execute(
            sa.select(store.positions.c.speed_mps).where(store.positions.c.engine == "echo")
        ).scalar()
    assert ("late_fix", 1.7e9 + 0.5) in ev and ev.count(("first_fix", 1.7e9)) == 2
    assert speed == 1.0 and ing.counts["late_fix"] == 1


def test_osmand_repeats_without_timestamp_are_new_reports(db) -> None:
    from iotnav.service.protocols import osmand

    ing = Ingestor(db, engine_name="none")
    q = "id=phone&lat=48.0&lon=16.0"
    for now in (1.7e9, 1.7e9 + 5):  # the same bytes twice, 5 s apart, no timestamp: two reports
        r = osmand.decode_query(q, now)
        assert ing.ingest("osmand", "phone", q.encode(), r.records, received_at=now, unique=True).n_new == 1
    q = "id=phone&lat=48.0&lon=16.0&timestamp=1700000100"
    for now in (1.7e9 + 10, 1.7e9 + 15):  # with a timestamp: the second is a resend
        r = osmand.decode_query(q, now)
        ing.ingest("osmand", "phone", q.encode(), r.records, received_at=now)
    with db.connect() as conn:
        times = conn.execute(
            sa.select(store.positions.c.fix_time).order_by(store.positions.c.fix_time)
        ).scalars()
        assert list(times) == [1.7e9, 1.7e9 + 5, 1.7e9 + 100]


class _BrokenEngine(_EchoEngine):
    """Test double: the second step of the first instance raises (an engine bug)."""

    armed = True

    def step(self, s: GnssSample) -> Output | None:
        if len(self.seen) == 1 and _BrokenEngine.armed:
            _BrokenEngine.armed = False
            self.seen.append(s.t)
            raise ZeroDivisionError("engine bug")
        return super().step(s)


def test_an_engine_error_does_not_block_the_device(db) -> None:
    _BrokenEngine.armed = True
    made: list[_BrokenEngine] = []
    ing = Ingestor(db, engine_name="broken", engine_factory=lambda: made.append(_BrokenEngine()) or made[-1])
    t0 = 1_700_000_000_000
    pkt = codec8_packet([(t0 + 1000 * i, 48.0, 16.0, 0, 9) for i in range(3)])
    r = ing.ingest("teltonika", "A", pkt, decode_avl(pkt, "A").records)
    assert r.accepted and r.n_new == 3 and r.n_engine == 1  # stored (and so acknowledged)
    pkt2 = codec8_packet([(t0 + 5000, 48.0, 16.0, 0, 9)])
    # the fresh engine gets the fix the broken one did not reach, then the new one
    assert ing.ingest("teltonika", "A", pkt2, decode_avl(pkt2, "A").records).n_engine == 2
    assert made[1].seen == [1.7e9 + 2, 1.7e9 + 5]
    assert len(made) == 2 and ing.counts["engine_error"] == 1  # a fresh engine took over
    with db.connect() as conn:
        types = conn.execute(sa.select(store.events.c.type)).scalars().all()
    assert types.count("engine_error") == 1


def test_reorder_window_feeds_out_of_order_messages_in_time_order(db) -> None:
    made: list[_EchoEngine] = []
    ing = Ingestor(
        db,
        engine_name="echo",
        engine_factory=lambda: made.append(_EchoEngine()) or made[-1],
        reorder_window_s=10.0,
    )
    t0 = 1_700_000_000_000

    def send(*dt_s: int) -> int:
        pkt = codec8_packet([(t0 + 1000 * d, 48.0, 16.0, 0, 9) for d in dt_s])
        return ing.ingest("teltonika", "A", pkt, decode_avl(pkt, "A").records).n_engine

    assert send(0) == 0 and send(5) == 0 and send(3) == 0  # held: within 10 s of the newest
    assert send(20) == 3  # 0, 3 and 5 leave the window, in time order
    assert made[0].seen == [1.7e9, 1.7e9 + 3, 1.7e9 + 5]
    assert send(4) == 0 and ing.counts["late_fix"] == 1  # older than what the engine has seen
    assert send(15, 31) == 2 and made[0].seen[3:] == [1.7e9 + 15, 1.7e9 + 20]


def test_retention_deletes_what_is_older_than_the_setting(db) -> None:
    ing = Ingestor(db, engine_name="none")
    day = 86400.0
    for k, received in enumerate((1.7e9, 1.7e9 + 10 * day)):
        pkt = codec8_packet([(1_700_000_000_000 + 1000 * k, 48.0, 16.0, 0, 9)])
        ing.ingest("teltonika", "A", pkt, decode_avl(pkt, "A").records, received_at=received)
    assert ing.purge(0.0, now=1.7e9 + 20 * day) == {}  # 0: keep everything
    assert ing.purge(15.0, now=1.7e9 + 20 * day) == {"positions": 1, "events": 0, "raw_messages": 1}
    with db.connect() as conn:
        assert conn.execute(sa.select(store.positions.c.server_time)).scalars().all() == [1.7e9 + 10 * day]


def test_a_crash_replays_the_fixes_stored_after_the_checkpoint(db) -> None:
    """Device A: two packets, a checkpoint (as written at a shutdown), two more packets, then a
    crash (the ingestor dropped without writing its states: the database is all a killed process
    leaves); a restarted ingestor rebuilds A's state from the checkpoint and the 12 fixes stored
    after it, and A's clean track equals device B's (the same records, uninterrupted), bit for
    bit. Device C, restarted the same way with the replay switched off (the checkpoint alone),
    gets another track: the replay is what carries the lost changes."""
    t0 = 1_700_000_000_000
    recs = [
        (t0 + 1000 * i, 48.2 + (10.0 * i + (500.0 if i == 16 else 0.0)) / 111_200.0, 16.37, 36, 9)
        for i in range(36)
    ]
    packets = [codec8_packet(recs[k : k + 6]) for k in range(0, 36, 6)]
    key = b"k" * 32

    def send(ing: Ingestor, imei: str, pkts: list[bytes]) -> None:
        for p in pkts:
            assert ing.ingest("teltonika", imei, p, decode_avl(p, imei).records).n_new == 6

    def track(imei: str) -> list[tuple[Any, ...]]:
        p, d = store.positions, store.devices
        q = sa.select(
            p.c.fix_time, p.c.latitude, p.c.longitude, p.c.speed_mps, p.c.accuracy_m, p.c.attributes
        )
        q = q.join(d, d.c.id == p.c.device_id).where(p.c.engine == "fixes", d.c.unique_id == imei)
        with db.connect() as conn:
            return [tuple(r) for r in conn.execute(q.order_by(p.c.fix_time))]

    first = Ingestor(db, "fixes", checkpoint_key=key)  # checkpoints after 60 s of changes
    for imei in ("A", "C"):
        send(first, imei, packets[:2])
    assert first.flush_checkpoints() == 2
    for imei in ("A", "C"):
        send(first, imei, packets[2:4])  # not checkpointed: lost in memory at the crash
    del first
    again = Ingestor(db, "fixes", checkpoint_key=key)
    send(again, "A", packets[4:])
    send(again, "B", packets)
    assert again.counts["checkpoint_restored"] == 1 and again.counts["replayed_fixes"] == 12
    no_replay = Ingestor(db, "fixes", checkpoint_key=key)
    no_replay._replay = lambda *a, **k: True  # type: ignore[method-assign]
    send(no_replay, "C", packets[4:])
    assert len(track("A")) == 36 and track("A") == track("B")
    assert '"source": "dr"' in json.dumps(
        track("A")[16][-1]
    )  # the glitch was rejected (in the replayed part)
    assert track("C")[:24] == track("B")[:24] and track("C")[24:] != track("B")[24:]


def test_checkpoints_due_together_are_spread_over_transactions_oldest_first(tmp_path) -> None:
    """Eight devices whose states come due at once are checkpointed at most
    ``MAX_CHECKPOINTS_PER_BATCH`` (here 3) per transaction, in the order their changes came."""
    db = store.make_engine(store.sqlite_url(tmp_path))
    store.upgrade(db)
    ing = Ingestor(db, "echo", engine_factory=_EchoEngine, checkpoint_interval_s=0.3)
    ing.MAX_CHECKPOINTS_PER_BATCH = 3
    t0 = 1_700_000_000_000

    def msg(imei: str, k: int) -> Any:
        from iotnav.service.ingest import Message

        p = codec8_packet([(t0 + 1000 * k, 48.2, 16.37, 36, 9)])
        return Message("teltonika", imei, p, decode_avl(p, imei).records)

    assert not any(isinstance(r, Exception) for r in ing.ingest_batch([msg(f"D{i}", 0) for i in range(8)]))
    time.sleep(0.35)
    saved = []
    for k in range(1, 4):
        before = ing.counts.get("checkpoints_saved", 0)
        ing.ingest_batch([msg("late", k)])
        saved.append(ing.counts.get("checkpoints_saved", 0) - before)
        if k == 1:
            with db.connect() as conn:
                ids = conn.execute(
                    sa.select(store.devices.c.unique_id)
                    .join(store.engine_states, store.engine_states.c.device_id == store.devices.c.id)
                    .order_by(store.devices.c.unique_id)
                ).scalars()
                assert list(ids) == ["D0", "D1", "D2"]
    assert saved == [3, 3, 2]
    db.dispose()
