"""Workers sharing the fleet through NATS JetStream (real nats-server, real PostgreSQL).

``iotnav serve`` runs as an ingest edge (``nats = URL``): its Teltonika listener publishes
each packet to JetStream and answers the device after JetStream's acknowledgement. Two
``iotnav worker`` processes share 8 partitions by lease; one is killed with SIGKILL while
8 devices stream; its partitions move to the other, which resumes from the checkpoints and
the unacknowledged messages. Every record must be stored exactly once, in order, and the
engine's clean positions must equal those of one uninterrupted ingest of the same packets
(so the state was resumed, not restarted).
"""

from __future__ import annotations

import os
import socket
import struct
import threading
import time

import pytest

from _cluster_helpers import InProcessWorker, lease_owners, shared_cluster, start_worker
from _service_helpers import Service, codec8_packet, imei_frame, recv_exact
from iotnav.service import store
from iotnav.service.http import iso
from iotnav.service.ingest import Ingestor
from iotnav.service.protocols.teltonika import decode_avl
from iotnav.service.workers import ClusterSettings, WorkerConfig, partition_of

T0_MS = 1_700_000_000_000
PARTITIONS = 8
N_PACKETS = 24  # per device, 2 records each
FIRST = 6  # packets each device sends before the kill phase
IMEIS = [f"35210000000{k:04d}" for k in range(8)]


def _packets(k: int) -> list[bytes]:
    """A device driving north-east at about 10 m/s, one fix a second, 2 fixes a packet."""
    out = []
    for j in range(N_PACKETS):
        recs = []
        for r in range(2):
            i = 2 * j + r
            recs.append((T0_MS + 1000 * i, 48.0 + 0.01 * k + 9e-5 * i, 16.0 + 1.3e-4 * i, 36, 9))
        out.append(codec8_packet(recs))
    return out


def _device(port: int, imei: str, packets: list[bytes], acked: list[int], gate: threading.Event) -> None:
    """Send each packet, wait for its ACK (the edge has it in JetStream), then the next one;
    after the first :data:`FIRST` packets, wait for ``gate``."""
    sock = socket.create_connection(("127.0.0.1", port), timeout=10)
    sock.sendall(imei_frame(imei))
    assert recv_exact(sock, 1) == b"\x01"
    for j, p in enumerate(packets):
        if j == FIRST:
            gate.wait(60)
        sock.sendall(p)
        assert recv_exact(sock, 4) == struct.pack(">I", 2)
        acked.append(j)
        time.sleep(0.03)
    sock.close()


def _listen(url: str, token: str, got: list[dict], stop: threading.Event, ready: threading.Event) -> None:
    """Collect the positions pushed on the edge's ``/api/socket`` until ``stop``."""
    import json

    from websockets.sync.client import connect

    with connect(url, additional_headers={"Authorization": f"Bearer {token}"}, open_timeout=30) as ws:
        ready.set()
        while not stop.is_set():
            try:
                got.extend(json.loads(ws.recv(timeout=0.2)).get("positions", []))
            except TimeoutError:
                pass


def _expected(tmp_path) -> dict[str, list[tuple[float, float, float]]]:
    """Clean positions of one uninterrupted ingest of the same packets (SQLite, in-process)."""
    db = store.make_engine(store.sqlite_url(tmp_path))
    store.upgrade(db)
    ing = Ingestor(db, "fixes")
    out = {}
    for k, imei in enumerate(IMEIS):
        for p in _packets(k):
            ing.ingest("teltonika", imei, p, decode_avl(p, imei, 65536).records)
        with db.connect() as con:
            out[imei] = [
                tuple(r)
                for r in con.exec_driver_sql(
                    "SELECT p.fix_time, p.latitude, p.longitude FROM positions p JOIN devices d "
                    f"ON d.id = p.device_id WHERE d.unique_id = '{imei}' AND p.engine = 'fixes' ORDER BY p.id"
                )
            ]
    db.dispose()
    return out


def _wait(cond, timeout: float, what: str) -> None:
    t_end = time.monotonic() + timeout
    while not cond():
        if time.monotonic() > t_end:
            raise TimeoutError(what)
        time.sleep(0.05)


@pytest.fixture(scope="module")
def cluster(tmp_path_factory):
    return shared_cluster()  # (test_service_workers_alerts uses the same servers)


def test_worker_killed_mid_stream_its_devices_resume_on_the_other(cluster, tmp_path) -> None:
    nats, pg = cluster
    assert len({partition_of(m, PARTITIONS) for m in IMEIS}) >= 5  # the devices spread
    data = tmp_path / "data"
    args = ["--nats", nats.url, "--db", pg.url, "--data", str(data), "--partitions", str(PARTITIONS)]
    args += ["--lease", "1.5", "--engine", "fixes", "--checkpoint-interval", "0.3"]
    edge = Service(data, db=pg.url, engine="none", nats=nats.url, nats_partitions=PARTITIONS)
    victim = start_worker(tmp_path / "worker.log", *args)
    edge.start()
    expected = _expected(tmp_path)  # meanwhile, the worker subprocess warms up
    survivor = InProcessWorker(
        WorkerConfig(db=pg.url, data=str(data), engine="fixes", checkpoint_interval_s=0.3),
        ClusterSettings(url=nats.url, partitions=PARTITIONS, lease_s=1.5),
    )
    survivor.start()
    try:
        # both workers hold a share (4 partitions each) before the devices start
        _wait(
            lambda: len(o := lease_owners(nats.url)) == PARTITIONS and len(set(o.values())) == 2,
            120,  # (a loaded machine; a few seconds on an idle one)
            "two workers sharing the partitions",
        )
        acked: dict[str, list[int]] = {m: [] for m in IMEIS}
        gate = threading.Event()
        live: list[dict] = []
        stop_live, live_ready = threading.Event(), threading.Event()
        ws_url = f"ws://127.0.0.1:{edge.api}/api/socket"
        listener = threading.Thread(
            target=_listen, args=(ws_url, edge.admin_token, live, stop_live, live_ready)
        )
        listener.start()
        assert live_ready.wait(30)
        threads = [
            threading.Thread(target=_device, args=(edge.tcp, m, _packets(k), acked[m], gate))
            for k, m in enumerate(IMEIS)
        ]
        for t in threads:
            t.start()
        db = store.make_engine(pg.url)
        q = "SELECT count(*) FROM positions p JOIN devices d ON d.id = p.device_id WHERE d.unique_id = '{}'"
        q += " AND p.engine = 'none'"

        def stored(imei: str) -> int:
            with db.connect() as con:
                return int(con.exec_driver_sql(q.format(imei)).scalar() or 0)

        # every worker is processing: the devices' first packets are stored
        _wait(lambda: all(stored(m) == 2 * FIRST for m in IMEIS), 60, "the first packets stored")
        owners = lease_owners(nats.url)
        victim_id = next(o for o in owners.values() if f"-{victim.pid}-" in o)
        survivor_id = next(o for o in owners.values() if f"-{os.getpid()}-" in o)
        victim_parts = {p for p, o in owners.items() if o == victim_id}
        assert {partition_of(m, PARTITIONS) for m in IMEIS} & victim_parts  # it has devices
        gate.set()  # the devices stream on; the victim is killed in the middle of it
        n0 = sum(map(len, acked.values()))
        _wait(lambda: sum(map(len, acked.values())) >= n0 + len(IMEIS), 20, "the stream going on")
        victim.kill()  # SIGKILL, mid-stream: its consumers hold fetched, uncommitted messages
        victim.wait(10)
        at_kill = sum(map(len, acked.values()))
        assert at_kill <= len(IMEIS) * (N_PACKETS - 8)  # much of the stream comes after the kill
        for t in threads:
            t.join(30)
        assert all(len(a) == N_PACKETS for a in acked.values()), {m: len(a) for m, a in acked.items()}

        def done() -> bool:
            with db.connect() as con:
                n = con.exec_driver_sql("SELECT count(*) FROM positions WHERE engine = 'fixes'").scalar()
            return n == sum(map(len, expected.values()))

        _wait(done, 20, "every clean position stored")
        # the edge's live socket gets the workers' committed positions (at most once: a live
        # view), the survivor's after the kill: every device's last one
        with db.connect() as con:
            ids = dict(con.exec_driver_sql("SELECT unique_id, id FROM devices").all())
        last = {(ids[m], iso(expected[m][-1][0])) for m in IMEIS}
        _wait(lambda: last <= {(p["deviceId"], p["fixTime"]) for p in list(live)}, 10, "the live positions")
        stop_live.set()
        listener.join(10)
        keys = [(p["deviceId"], p["fixTime"]) for p in live]
        assert len(keys) == len(set(keys)) and len(keys) > len(IMEIS) * N_PACKETS  # none twice
        owners = lease_owners(nats.url)
        assert (
            set(owners.values()) == {survivor_id} and len(owners) == PARTITIONS
        )  # it took the victim's share
        with db.connect() as con:
            raw = con.exec_driver_sql("SELECT count(*), count(DISTINCT dedup_key) FROM raw_messages").one()
            assert tuple(raw) == (N_PACKETS * len(IMEIS),) * 2  # every packet once
            for imei in IMEIS:
                sent = con.exec_driver_sql(
                    "SELECT p.fix_time FROM positions p JOIN devices d ON d.id = p.device_id "
                    f"WHERE d.unique_id = '{imei}' AND p.engine = 'none' ORDER BY p.id"
                ).all()
                # every record exactly once, stored in the device's order
                assert [r[0] for r in sent] == [T0_MS / 1000 + i for i in range(2 * N_PACKETS)], imei
                clean = con.exec_driver_sql(
                    "SELECT p.fix_time, p.latitude, p.longitude FROM positions p JOIN devices d "
                    f"ON d.id = p.device_id WHERE d.unique_id = '{imei}' AND p.engine = 'fixes' ORDER BY p.id"
                ).all()
                got, want = [tuple(r) for r in clean], expected[imei]
                assert [r[0] for r in got] == [r[0] for r in want], imei
                err = max(
                    abs(a - b)
                    for g, w in zip(got, want, strict=True)
                    for a, b in zip(g[1:], w[1:], strict=True)
                )
                assert err < 1e-9, (imei, err)  # the engine resumed its state, as if never stopped
            events = con.exec_driver_sql("SELECT type, count(*) FROM events GROUP BY type").all()
            assert "engine_error" not in dict(events) and "late_fix" not in dict(events), events
        db.dispose()
    finally:
        if victim.poll() is None:
            victim.kill()
            victim.wait(10)
        survivor.stop()
        assert edge.stop() == 0


def test_device_days_reprocessed_on_dask_equal_the_live_engine(tmp_path) -> None:
    """Re-processing device-days from the database (on a Dask cluster) gives the live track."""
    from distributed import LocalCluster  # the dev extra installs Dask: fail, not skip, without it

    from iotnav.service.workers_batch import list_device_days, reprocess

    db = store.make_engine(store.sqlite_url(tmp_path))
    store.upgrade(db)
    ing = Ingestor(db, "fixes")
    day0 = 1_700_006_400.0  # 2023-11-15 00:00 UTC
    for k, imei in enumerate(IMEIS[:2]):
        for j in range(12):  # 6 packets before midnight, 6 after
            t_ms = int(1000 * (day0 - 60 + 10 * j))
            pkt = codec8_packet([(t_ms, 48.0 + 0.01 * k + 1e-4 * j, 16.0, 36, 9)])
            ing.ingest("teltonika", imei, pkt, decode_avl(pkt, imei, 65536).records)
    jobs = list_device_days(db)
    assert [(j.unique_id, j.day) for j in jobs] == [
        (m, d) for m in IMEIS[:2] for d in ("2023-11-14", "2023-11-15")
    ]
    with LocalCluster(n_workers=1, threads_per_worker=2, processes=False, dashboard_address=None) as cluster:
        res = reprocess(
            store.sqlite_url(tmp_path), jobs, "fixes", str(tmp_path / "out"), cluster.scheduler_address
        )
    assert all(isinstance(r, dict) for r in res), res
    with db.connect() as con:
        for job, r in zip(jobs, res, strict=True):
            assert isinstance(r, dict) and r["fixes"] == 6 and r["raw_messages"] == 6
            live = con.exec_driver_sql(
                "SELECT fix_time, latitude, longitude FROM positions WHERE engine = 'fixes' AND device_id = ? "
                "AND fix_time >= ? AND fix_time < ? ORDER BY fix_time",
                (job.device_id, job.day_start, job.day_start + 86400.0),
            ).all()
            if job.day == "2023-11-14":  # the live engine had seen nothing before either: same track
                assert [tuple(x) for x in live] == [tuple(x) for x in r["lat_lon"]]
            else:  # the re-run starts afresh at midnight; it still gives one position a fix
                assert r["outputs"] == 6 and [x[0] for x in live] == [x[0] for x in r["lat_lon"]]
            assert (tmp_path / "out" / job.unique_id / f"{job.day}.csv").read_text().count("\n") == 7
    db.dispose()


def test_stream_message_round_trip_and_bad_bodies() -> None:
    """What the edge publishes is what the worker ingests (NaN fields, bytes, the key); a body
    that is not one is refused with ValueError (the worker counts and skips it)."""
    import math

    from iotnav.service.ingest import Message
    from iotnav.service.workers import decode_message, encode_message

    pkt = codec8_packet([(T0_MS, 48.5, 16.25, 36, 9), (T0_MS + 1000, 48.5001, 16.2501, 0, 0)])
    fixes = decode_avl(pkt, IMEIS[0], 65536).records
    m = Message("teltonika", IMEIS[0], pkt, fixes, "10.0.0.1:5000", 1_700_000_123.25, unique=True)
    back = decode_message(encode_message(m))
    assert back.digest() == m.digest() and back.payload == pkt and back.unique
    for a, b in zip(back.fixes, fixes, strict=True):
        assert a.key == b.key and a.attributes == b.attributes and a.t == b.t and a.num_sv == b.num_sv
        assert all(
            getattr(a, f) == getattr(b, f) or (math.isnan(getattr(a, f)) and math.isnan(getattr(b, f)))
            for f in ("lat_deg", "lon_deg", "height_m", "speed_mps", "course_rad", "h_acc_m", "hdop")
        )
    for bad in (b"", b"[]", b'{"v": 2}', encode_message(m).replace(b'"payload":"', b'"payload":"!')):
        with pytest.raises(ValueError):
            decode_message(bad)
