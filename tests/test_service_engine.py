"""The service's clean positions are the ``fixes`` engine's, live, across restarts and re-ordering.

Every expected track is the same fixes run offline through the engine
(:func:`iotnav.engines.base.run_batch` over a :class:`~iotnav.io.log.Log`, the path of
``iotnav run``). The live test runs a real ``iotnav serve`` (OsmAnd over HTTP); restarts,
re-ordering and the memory bound run the service's ingestor on a real SQLite file, a restart
being a new ingestor on the same database and key file (all that a restarted process keeps;
that a committed transaction survives kill -9 is ``tests/test_service_live.py``'s test).
"""

from __future__ import annotations

import math
import sqlite3

import httpx
import numpy as np
import pandas as pd
import pytest
import sqlalchemy as sa

from _service_helpers import Service, codec8_packet
from iotnav.engines.base import run_batch
from iotnav.engines.registry import make_engine
from iotnav.io.log import Log
from iotnav.io.schema import GNSS_COLUMNS, coerce
from iotnav.service import checkpoint, store
from iotnav.service.ingest import ConcurrentWriteError, Ingestor, Message
from iotnav.service.protocols import osmand
from iotnav.service.protocols.common import KNOT_MPS
from iotnav.service.protocols.teltonika import decode_avl

T0 = 1_700_000_000
N = 24
JUMP = 16  # the fix at T0 + JUMP is 500 m off the road (a GNSS glitch)
DAY = {"from": "2023-11-14T00:00:00Z", "to": "2023-11-16T00:00:00Z"}


def _drive(n: int = N, seed: int = 7) -> list[dict[str, str]]:
    """OsmAnd queries of a car driving north at 10 m/s, 1 Hz, 3 m noise, one 500 m glitch."""
    rng = np.random.default_rng(seed)
    out = []
    for i in range(n):
        north = 10.0 * i + 3.0 * rng.standard_normal() + (500.0 if i == JUMP else 0.0)
        east = 3.0 * rng.standard_normal()
        lat = 48.2 + north / 111_200.0
        lon = 16.37 + east / (111_200.0 * math.cos(math.radians(48.2)))
        out.append(
            {
                "id": "car",
                "timestamp": str(T0 + i),
                "lat": f"{lat:.7f}",
                "lon": f"{lon:.7f}",
                "speed": f"{10.0 + 0.3 * rng.standard_normal():.2f}",
                "bearing": "0",
                "accuracy": "4",
                "altitude": "200",
            }
        )
    return out


def _offline(queries: list[dict[str, str]]) -> pd.DataFrame:
    """The fixes of ``queries`` (protocol units: m/s, degrees) through a fresh ``fixes`` engine, offline."""
    df = pd.DataFrame(
        {
            "t": [float(q["timestamp"]) for q in queries],
            "lat_deg": [float(q["lat"]) for q in queries],
            "lon_deg": [float(q["lon"]) for q in queries],
            "height_m": [float(q["altitude"]) for q in queries],
            "speed_mps": [float(q["speed"]) for q in queries],
            "course_rad": [math.radians(float(q["bearing"])) for q in queries],
            "course_valid": True,
            "h_acc_m": [float(q["accuracy"]) for q in queries],
            "valid": True,
        }
    ).sort_values("t", kind="stable")
    return run_batch(make_engine("fixes"), Log(gnss=coerce(df.reset_index(drop=True), GNSS_COLUMNS)))


def _assert_same_track(api: list[dict], offline: pd.DataFrame) -> None:
    """API positions (Traccar fields) equal the offline engine rows: times, coordinates exactly."""
    assert [p["fixTime"] for p in api] == [
        pd.Timestamp(t, unit="s", tz="UTC").strftime("%Y-%m-%dT%H:%M:%S.000Z") for t in offline["t"]
    ]
    assert [(p["latitude"], p["longitude"]) for p in api] == list(
        zip(offline["lat"], offline["lon"], strict=True)
    )
    speed_kn = np.hypot(offline["vn"], offline["ve"]) / KNOT_MPS
    assert [p["speed"] for p in api] == pytest.approx(list(speed_kn), rel=1e-12)
    assert [p["attributes"]["source"] for p in api] == list(offline["source"])


def _positions(svc: Service, unique_id: str, engine: str | None = None) -> list[dict]:
    h = {"Authorization": f"Bearer {svc.admin_token}"}
    (dev,) = httpx.get(svc.url("/api/devices"), params={"uniqueId": unique_id}, headers=h).json()
    params = {"deviceId": dev["id"], **DAY, **({"engine": engine} if engine else {})}
    return httpx.get(svc.url("/api/positions"), params=params, headers=h).json()


def _send(svc: Service, queries: list[dict[str, str]]) -> None:
    with httpx.Client() as client:
        for q in queries:
            assert client.get(svc.url("/", svc.osmand), params=q).status_code == 200


@pytest.fixture(scope="module")
def svc(tmp_path_factory):
    s = Service(tmp_path_factory.mktemp("engine") / "data", engine="fixes", osmand_speed_unit="mps").start()
    yield s
    assert s.stop() == 0


def test_osmand_device_gets_the_fixes_engine_track_and_the_jump_is_rejected(svc: Service) -> None:
    drive = _drive()
    _send(svc, drive)
    offline = _offline(drive)
    clean = _positions(svc, "car")
    _assert_same_track(clean, offline)
    raw = _positions(svc, "car", engine="none")  # kept beside: the fixes as sent
    assert [(p["latitude"], p["longitude"]) for p in raw] == [
        (float(q["lat"]), float(q["lon"])) for q in drive
    ]
    jump = clean[JUMP]
    assert jump["attributes"] == {"engine": "fixes", "source": "dr", "static": False}  # the prediction
    off_m = (raw[JUMP]["latitude"] - jump["latitude"]) * 111_200.0
    assert off_m > 400.0  # the clean track did not follow the 500 m glitch
    assert abs(clean[JUMP + 1]["latitude"] - raw[JUMP + 1]["latitude"]) * 111_200.0 < 15.0  # back on the road
    con = sqlite3.connect(svc.data / "iotnav.sqlite")
    rejected = con.execute("SELECT event_time FROM events WHERE type = 'fix_rejected'").fetchall()
    con.close()
    assert rejected == [(float(T0 + JUMP),)]


def test_a_restart_resumes_each_engine_from_its_checkpoint(tmp_path) -> None:
    """Teltonika records of device A split by a restart (a new ingestor on the same database and
    key file: all that a restarted process keeps), device B's the same records uninterrupted:
    equal clean tracks, bit for bit. With another key the checkpoint is refused and the track
    differs (so the checkpoint is what carries the state). Checkpoints with every message here
    (interval 0); the replay on top of an older checkpoint is
    ``test_service_store.py::test_a_crash_replays_the_fixes_stored_after_the_checkpoint``."""
    recs = [
        (1000 * (T0 + i), 48.2 + (10.0 * i + (500.0 if i == JUMP else 0.0)) / 111_200.0, 16.37, 36, 9)
        for i in range(N)
    ]
    packets = [codec8_packet(recs[k : k + 6]) for k in range(0, N, 6)]
    db = store.make_engine(store.sqlite_url(tmp_path))
    store.upgrade(db)
    key = checkpoint.load_key(tmp_path)

    def send(ing: Ingestor, imei: str, pkts: list[bytes]) -> None:
        for p in pkts:
            assert ing.ingest("teltonika", imei, p, decode_avl(p, imei).records).n_engine == 6

    def track(imei: str) -> list[tuple]:
        with db.connect() as conn:
            return conn.exec_driver_sql(
                "SELECT fix_time, latitude, longitude, altitude, speed_mps, course_rad, accuracy_m, p.attributes "
                "FROM positions p JOIN devices d ON d.id = p.device_id "
                f"WHERE engine = 'fixes' AND d.unique_id = '{imei}' ORDER BY fix_time"
            ).all()

    a, b, c = "356307042441013", "356307042441014", "356307042441015"
    every = {"checkpoint_interval_s": 0.0}
    send(Ingestor(db, "fixes", checkpoint_key=key, **every), a, packets[:2])
    send(Ingestor(db, "fixes", checkpoint_key=key, **every), c, packets[:2])
    restarted = Ingestor(db, "fixes", checkpoint_key=checkpoint.load_key(tmp_path), **every)
    send(restarted, a, packets[2:])
    send(restarted, b, packets)
    other_key = Ingestor(db, "fixes", checkpoint_key=b"another key of 32 bytes........", **every)
    send(other_key, c, packets[2:])
    db.dispose()
    assert track(a) == track(b) and len(track(a)) == N
    assert '"source": "dr"' in track(a)[JUMP][-1]  # the glitch rejected
    assert restarted.counts["checkpoint_restored"] == 1
    assert other_key.counts["checkpoint_discarded"] == 1 and track(c) != track(b)


@pytest.mark.parametrize("interval_s", [0.0, 60.0])
def test_reorder_window_late_fixes_and_the_queue_survive_a_restart(tmp_path, interval_s: float) -> None:
    """Messages swapped in pairs are re-ordered within the 5 s window; a fix 6 s late is stored,
    flagged and counted but not fed; the queue held at a restart is fed after it, whether it
    comes from a checkpoint of every message (interval 0) or, never checkpointed (60 s), from
    replaying every stored fix through a fresh engine."""
    db = store.make_engine(store.sqlite_url(tmp_path))
    store.upgrade(db)
    key = b"k" * 32
    drive = _drive()
    order = [j for i in range(0, N, 2) for j in (i + 1, i)]  # every pair swapped
    late = 10
    order.remove(late)
    order.insert(order.index(16) + 1, late)  # arrives after fix 16: 6 s behind the newest
    opts = {"reorder_window_s": 5.0, "checkpoint_key": key, "checkpoint_interval_s": interval_s}
    ing = Ingestor(db, "fixes", **opts)
    for k, i in enumerate(order):
        if k == N // 2:  # a restart: a new process, same database and key
            ing = Ingestor(db, "fixes", **opts)
        q = "&".join(f"{a}={b}" for a, b in drive[i].items())
        fixes = osmand.decode_query(q, 0.0, "mps").records
        ing.ingest("osmand", "car", q.encode(), fixes, received_at=float(T0 + k))
    with db.connect() as conn:
        rows = conn.exec_driver_sql(
            "SELECT fix_time, latitude, longitude FROM positions WHERE engine = 'fixes' ORDER BY fix_time"
        ).all()
        flagged = conn.exec_driver_sql(
            "SELECT fix_time, attributes FROM positions WHERE engine = 'none' AND attributes LIKE '%late%'"
        ).all()
        late_events = conn.exec_driver_sql("SELECT event_time FROM events WHERE type = 'late_fix'").all()
    db.dispose()
    offline = _offline([q for i, q in enumerate(drive) if i != late])
    newest = T0 + N - 1
    fed = offline[offline["t"] <= newest - 5.0]  # the last 5 s are still held by the window
    assert [tuple(r) for r in rows] == list(zip(fed["t"], fed["lat"], fed["lon"], strict=True))
    assert [r[0] for r in flagged] == [T0 + late] and late_events == [(T0 + late,)]
    assert ing.counts["late_fix"] == 1
    if interval_s == 0.0:
        assert ing.counts["checkpoint_restored"] == 1 and "replayed_fixes" not in ing.counts
    else:  # no checkpoint yet: the N // 2 fixes stored before the restart fed again
        assert "checkpoint_restored" not in ing.counts and ing.counts["replayed_fixes"] == N // 2


def test_device_states_beyond_the_memory_bound_come_back_from_their_checkpoints(tmp_path) -> None:
    """Two devices interleaved, one state in memory: each track still equals its offline run."""
    db = store.make_engine(store.sqlite_url(tmp_path))
    store.upgrade(db)
    ing = Ingestor(db, "fixes", checkpoint_key=b"k" * 32, max_devices_in_memory=1)
    drives = {"car": _drive(), "van": [{**q, "id": "van"} for q in _drive(seed=8)]}
    for i in range(N):
        for name, drive in drives.items():
            q = "&".join(f"{a}={b}" for a, b in drive[i].items())
            ing.ingest("osmand", name, q.encode(), osmand.decode_query(q, 0.0, "mps").records)
    with db.connect() as conn:
        for name, drive in drives.items():
            rows = conn.exec_driver_sql(
                "SELECT fix_time, latitude, longitude FROM positions p JOIN devices d ON d.id = p.device_id "
                f"WHERE engine = 'fixes' AND d.unique_id = '{name}' ORDER BY fix_time"
            ).all()
            offline = _offline(drive)
            assert [tuple(r) for r in rows] == list(
                zip(offline["t"], offline["lat"], offline["lon"], strict=True)
            )
    db.dispose()
    assert ing.counts["checkpoint_restored"] == 2 * N - 2  # every message but each device's first


@pytest.mark.parametrize("interval_s", [0.0, 60.0])
def test_a_transaction_refused_by_a_held_write_lock_leaves_no_engine_state_ahead(
    tmp_path, interval_s
) -> None:
    """The engine steps of a batch run before its write transaction. When another connection
    holds SQLite's write lock beyond ``busy_timeout`` (a real lock, 0.2 s here), the batch fails
    after its steps, is not acknowledged, and the device resends it: it is stored once and the
    clean track equals device B's, sent the same records uninterrupted; so does every record
    after it (rebuilt from the checkpoint of every message at interval 0, by replaying all
    stored fixes at 60 s)."""
    recs = [
        (1000 * (T0 + i), 48.2 + 10.0 * i / 111_200.0, 16.37 + 3.0 * i / 74_000.0, 36, 9) for i in range(N)
    ]
    packets = [codec8_packet(recs[k : k + 4]) for k in range(0, N, 4)]
    db = store.make_engine(store.sqlite_url(tmp_path), immediate=True)
    store.upgrade(db)
    sa.event.listen(db, "connect", lambda c, _: c.execute("PRAGMA busy_timeout=200"))
    db.dispose()  # (connections made from now on wait 0.2 s for the lock)
    ing = Ingestor(db, "fixes", checkpoint_key=b"k" * 32, checkpoint_interval_s=interval_s)
    a, b = "356307042441013", "356307042441014"

    def send(imei: str, p: bytes) -> int:
        return ing.ingest("teltonika", imei, p, decode_avl(p, imei).records).n_new

    for p in packets:
        assert send(b, p) == 4
    for p in packets[:3]:
        assert send(a, p) == 4
    other = sqlite3.connect(tmp_path / "iotnav.sqlite", isolation_level=None)
    other.execute("BEGIN IMMEDIATE")  # another writer holds the lock
    with pytest.raises(sa.exc.OperationalError, match="locked"):
        send(a, packets[3])
    other.execute("ROLLBACK")
    other.close()
    for p in packets[3:]:  # the unacknowledged packet resent, then the rest
        assert send(a, p) == 4
    with db.connect() as conn:

        def rows(imei: str, engine: str) -> list[tuple]:
            return conn.exec_driver_sql(
                "SELECT fix_time, latitude, longitude, altitude, speed_mps, course_rad, accuracy_m, "
                "p.attributes FROM positions p JOIN devices d ON d.id = p.device_id "
                f"WHERE engine = '{engine}' AND d.unique_id = '{imei}' ORDER BY fix_time, p.id"
            ).all()

        n_raw = conn.exec_driver_sql("SELECT count(*) FROM raw_messages").scalar()
        assert rows(a, "none") == rows(b, "none") and len(rows(a, "none")) == N
        assert rows(a, "fixes") == rows(b, "fixes") and len(rows(a, "fixes")) == N
    db.dispose()
    assert n_raw == 2 * len(packets)
    assert ing.counts.get("checkpoint_restored", 0) == (1 if interval_s == 0.0 else 0)
    assert ing.counts.get("replayed_fixes", 0) == (0 if interval_s == 0.0 else 12)


def test_a_raw_message_stored_by_another_writer_after_the_prepare_fails_the_batch_and_is_stored_once(
    tmp_path,
) -> None:
    """The de-duplication read runs outside the write lock (sound while a device has one writer).
    When another writer stores one of the batch's messages between that read and the write
    transaction, the batch is refused (ConcurrentWriteError) and rolled back; stored one by one,
    that message is a duplicate and the other one is stored: each record once."""
    recs = [(1000 * (T0 + i), 48.2 + 10.0 * i / 111_200.0, 16.37, 36, 9) for i in range(13)]
    p0, p1, p2, p3 = (codec8_packet(recs[k : k + 4]) for k in (0, 4, 8, 12))
    db = store.make_engine(store.sqlite_url(tmp_path), immediate=True)
    store.upgrade(db)
    imei = "356307042441013"
    other = Ingestor(db, "fixes", checkpoint_key=b"k" * 32)

    def msg(p: bytes) -> Message:
        return Message("teltonika", imei, p, decode_avl(p, imei).records)

    class Raced(Ingestor):
        race = False

        def _prepare(self, msgs, touched):  # another writer of the same device, between read and write
            plan = super()._prepare(msgs, touched)
            if self.race:
                self.race = False
                assert other.ingest_batch([msgs[0]])[0].n_new == len(msgs[0].fixes)
            return plan

    ing = Raced(db, "fixes", checkpoint_key=b"k" * 32)
    assert ing.ingest_batch([msg(p0)])[0].n_new == 4
    ing.race = True
    first, second = ing.ingest_batch([msg(p1), msg(p2)])
    assert first.duplicate and second.n_new == 4 and ing.counts["batch_split"] == 1
    ing.race = True
    with pytest.raises(ConcurrentWriteError):  # a batch of one fails: the device resends it
        ing.ingest("teltonika", imei, p3, msg(p3).fixes)
    assert ing.ingest_batch([msg(p3)])[0].duplicate
    with db.connect() as conn:
        n_raw = conn.exec_driver_sql("SELECT count(*) FROM raw_messages").scalar()
        fixes = conn.exec_driver_sql("SELECT fix_time FROM positions WHERE engine = 'none' ORDER BY 1").all()
    db.dispose()
    assert n_raw == 4 and [f[0] for f in fixes] == [r[0] / 1000 for r in recs]
