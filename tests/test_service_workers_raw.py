"""Raw GNSS + IMU batches on the workers (real mosquitto, nats-server and PostgreSQL).

Four devices stream raw batches (a short simulated drive, 100 Hz IMU, 1 Hz GNSS, one batch a
second of device time) over MQTT to an ``iotnav serve --nats`` edge; the edge publishes each
batch to JetStream on its device's partition and two ``iotnav worker`` processes, sharing 4
partitions by lease, run the raw engine (``pipeline``) on them. One worker is SIGKILLed
mid-stream; its partitions move to the other, which resumes from the engines' checkpoints and
the batches not acknowledged. Every batch the broker accepted must be stored exactly once, in
order, and the clean positions must equal those of one uninterrupted in-process run.

The edge connects to PostgreSQL as a role that may not write ``raw_messages``, ``positions``
nor ``engine_states``: whatever the test finds there was written by a worker, not the edge.
"""

from __future__ import annotations

import asyncio
import os
import threading
import time
from collections import Counter

import pytest
import sqlalchemy as sa

from _cluster_helpers import (
    InProcessWorker,
    NatsServer,
    lease_owners,
    new_database,
    shared_cluster,
    start_worker,
)
from _service_helpers import FetchedMessage, Mosquitto, Service
from iotnav.service.workers import ClusterSettings, WorkerConfig, open_database, partition_of

PARTITIONS = 4
DEVICES = ["car-0", "car-1", "car-4", "car-5"]  # one per partition (asserted below)
FIRST = 5  # batches each device sends before the kill phase
EDGE_ROLE = "iotnav_edge_no_positions"


@pytest.fixture(scope="module")
def batches(tmp_path_factory: pytest.TempPathFactory) -> list[bytes]:
    """JSON raw batches of a 16 s drive (moving from 3 s), one per second of device time."""
    from iotnav import sim
    from iotnav.io import ingest
    from iotnav.service.raw_ingest import log_batches

    out = tmp_path_factory.mktemp("drive")
    res = sim.build("car-tunnel", seed=7, overrides={"duration_s": 16.0, "motion.wait_start_s": 3.0})
    sim.write(res, out)
    return list(log_batches(ingest([out])))


def _expected(tmp_path, batches: list[bytes]) -> dict[str, list[tuple[float, float, float]]]:
    """Clean positions of one uninterrupted in-process run of every device's batches (SQLite)."""
    from iotnav.service import store
    from iotnav.service.ingest import Ingestor
    from iotnav.service.protocols.iotnav_raw import RawBatch, decode
    from iotnav.service.raw_ingest import RawProcessor

    db = store.make_engine(store.sqlite_url(tmp_path))
    store.upgrade(db)
    rp = RawProcessor(Ingestor(db, "none"))
    for dev in DEVICES:
        for p in batches:
            b = decode(p, topic=f"iotnav/{dev}/raw")
            assert isinstance(b, RawBatch)
            assert rp.ingest(p, b).accepted
    out = {dev: _clean(db, dev) for dev in DEVICES}
    db.dispose()
    return out


def _clean(db: sa.engine.Engine, dev: str) -> list[tuple[float, float, float]]:
    q = sa.text(
        "SELECT p.fix_time, p.latitude, p.longitude FROM positions p JOIN devices d ON d.id = p.device_id "
        "WHERE d.unique_id = :u AND p.engine = 'pipeline' ORDER BY p.id"
    )
    with db.connect() as con:
        return [tuple(r) for r in con.execute(q, {"u": dev})]  # type: ignore[misc]


def _edge_role(url: str) -> str:
    """A role that reads and writes the schema but may not write what the workers store; its URL."""
    db = sa.create_engine(url)
    with db.begin() as con:
        if not con.exec_driver_sql(f"SELECT 1 FROM pg_roles WHERE rolname = '{EDGE_ROLE}'").first():
            con.exec_driver_sql(f"CREATE ROLE {EDGE_ROLE} LOGIN")
        con.exec_driver_sql(f"GRANT ALL ON ALL TABLES IN SCHEMA public TO {EDGE_ROLE}")
        con.exec_driver_sql(f"GRANT ALL ON ALL SEQUENCES IN SCHEMA public TO {EDGE_ROLE}")
        con.exec_driver_sql(
            f"REVOKE INSERT, UPDATE, DELETE ON raw_messages, positions, engine_states FROM {EDGE_ROLE}"
        )
    db.dispose()
    return url.replace("//iotnav@", f"//{EDGE_ROLE}@")


def _wait(cond, timeout: float, what: str) -> None:
    t_end = time.monotonic() + timeout
    while not cond():
        if time.monotonic() > t_end:
            raise TimeoutError(what)
        time.sleep(0.05)


def _stream(port: int, batches: list[bytes], sent: dict[str, int], gate: threading.Event, stored) -> None:
    """Each device publishes its batches with QoS 1 (the next after the broker's PUBACK); the
    first one again until it is stored (the edge subscribed), then :data:`FIRST` of them, then
    waits for ``gate``."""
    import aiomqtt

    async def device(dev: str) -> None:
        async with aiomqtt.Client("127.0.0.1", port, identifier=f"sim-{dev}") as c:
            t_end = time.monotonic() + 60
            while not stored(dev) and time.monotonic() < t_end:  # the same bytes: stored once
                await c.publish(f"iotnav/{dev}/raw", batches[0], qos=1)
                await asyncio.sleep(0.3)
            sent[dev] = 1
            for k, p in enumerate(batches[1:], 1):
                if k == FIRST:
                    await asyncio.to_thread(gate.wait, 60)
                await c.publish(f"iotnav/{dev}/raw", p, qos=1)
                sent[dev] = k + 1
                await asyncio.sleep(0.1)

    async def main() -> None:
        await asyncio.gather(*(device(d) for d in DEVICES))

    asyncio.run(main())


def test_raw_batches_processed_by_workers_one_killed_mid_stream(tmp_path, batches) -> None:
    assert sorted(partition_of(d, PARTITIONS) for d in DEVICES) == list(range(PARTITIONS))
    _, pg = shared_cluster()
    url = new_database(pg, "raw_workers")
    open_database(url, 2).dispose()  # the schema, so that the edge's role gets its grants
    edge_url = _edge_role(url)
    nats = NatsServer().start()  # a stream and leases of this test only
    broker = Mosquitto(tmp_path / "broker").start()
    data = tmp_path / "data"
    args = ["--nats", nats.url, "--db", url, "--data", str(data), "--partitions", str(PARTITIONS)]
    args += ["--lease", "1.5", "--engine", "none", "--raw-engine", "pipeline"]
    victim = start_worker(tmp_path / "worker.log", *args)
    edge = Service(
        data,
        db=edge_url,
        engine="none",
        nats=nats.url,
        nats_partitions=PARTITIONS,
        mqtt=broker.url,
        mqtt_client_id="iotnav-edge-raw",
        raw_engine="pipeline",
    )
    survivor = InProcessWorker(
        WorkerConfig(db=url, data=str(data), engine="none", raw_engine="pipeline"),
        ClusterSettings(url=nats.url, partitions=PARTITIONS, lease_s=1.5),
    )
    db = sa.create_engine(url)
    try:
        edge.start()
        expected = _expected(tmp_path, batches)  # meanwhile, the worker subprocess warms up
        survivor.start()
        _wait(
            lambda: sorted(Counter(lease_owners(nats.url).values()).values()) == [2, 2],
            60,
            "two workers holding two partitions each",
        )

        def stored(dev: str) -> int:
            q = "SELECT count(*) FROM raw_messages r JOIN devices d ON d.id = r.device_id WHERE d.unique_id = :u"
            with db.connect() as con:
                return int(con.execute(sa.text(q), {"u": dev}).scalar_one())

        sent = dict.fromkeys(DEVICES, 0)
        gate = threading.Event()
        streamer = threading.Thread(target=_stream, args=(broker.port, batches, sent, gate, stored))
        streamer.start()
        _wait(lambda: all(stored(d) == FIRST for d in DEVICES), 60, "the first batches stored")
        owners = lease_owners(nats.url)
        victim_id = next(o for o in owners.values() if f"-{victim.pid}-" in o)
        mine = [d for d in DEVICES if owners[partition_of(d, PARTITIONS)] == victim_id]
        assert len(mine) == 2  # the victim has run two devices' engines up to here
        gate.set()
        n0 = sum(sent.values())
        _wait(lambda: sum(sent.values()) >= n0 + 2 * len(DEVICES), 20, "the stream going on")
        victim.kill()  # ... and the victim dies in the middle of it (SIGKILL)
        victim.wait(10)
        assert all(sent[d] < len(batches) - 4 for d in DEVICES)  # much of the stream comes after
        streamer.join(60)
        assert all(n == len(batches) for n in sent.values()), sent  # each accepted by the broker
        _wait(lambda: all(stored(d) == len(batches) for d in DEVICES), 30, "every batch stored")
        _wait(lambda: all(len(_clean(db, d)) == len(expected[d]) for d in DEVICES), 10, "the clean positions")
        owners = lease_owners(nats.url)
        assert len(owners) == PARTITIONS and all(f"-{os.getpid()}-" in o for o in owners.values())  # moved
        with db.connect() as con:
            for dev in DEVICES:
                rows = con.execute(
                    sa.text(
                        "SELECT r.payload FROM raw_messages r JOIN devices d ON d.id = r.device_id "
                        "WHERE d.unique_id = :u ORDER BY r.id"
                    ),
                    {"u": dev},
                ).all()
                assert [bytes(r[0]) for r in rows] == batches, dev  # each batch once, in order
                got, want = _clean(db, dev), expected[dev]
                assert [r[0] for r in got] == [r[0] for r in want], dev
                err = max(
                    abs(a - b)
                    for g, w in zip(got, want, strict=True)
                    for a, b in zip(g[1:], w[1:], strict=True)
                )
                # the engine resumed from the victim's checkpoint as if never stopped: on this
                # drive a filter restarted afresh at batch 8 differs by 1.7e-6 deg (0.2 m); 1e-9
                # deg (0.1 mm) leaves room for float rounding only (the same step() on the same
                # samples in the same order gives the same values, tests/test_service_raw_imu.py)
                assert err < 1e-9, (dev, err)
            n_states = con.exec_driver_sql("SELECT count(*) FROM engine_states WHERE engine = 'pipeline'")
            assert n_states.scalar_one() == len(DEVICES)
            evs = dict(con.exec_driver_sql("SELECT type, count(*) FROM events GROUP BY type").all())
            assert "engine_error" not in evs and "checkpoint_discarded" not in evs, evs
    finally:
        if victim.poll() is None:
            victim.kill()
            victim.wait(10)
        if survivor.is_alive():
            survivor.stop()
        db.dispose()
        assert edge.stop() == 0 if edge.proc is not None else True
        broker.stop()
        nats.stop()


def test_a_fetch_mixing_raw_batches_and_other_messages_is_stored_in_stream_order(tmp_path, batches) -> None:
    """One fetch of a partition: raw batches and Teltonika packets of one device, interleaved,
    stored in the stream's order (runs of one kind, one transaction each), then acknowledged
    once; a worker without a raw engine counts its raw batches as failed, stores the rest."""
    from _service_helpers import codec8_packet
    from iotnav.service import store
    from iotnav.service.ingest import Ingestor, Message
    from iotnav.service.protocols.teltonika import decode_avl
    from iotnav.service.raw_ingest import RawProcessor
    from iotnav.service.workers import Worker, _Lease, encode_message

    dev = DEVICES[0]
    pkts = [codec8_packet([(1_700_000_000_000 + 1000 * j, 48.0 + 1e-4 * j, 16.0, 36, 9)]) for j in range(3)]
    wire = [
        Message("iotnav_raw", dev, batches[0], [], f"iotnav/{dev}/raw"),
        Message("teltonika", dev, pkts[0], decode_avl(pkts[0], dev, 65536).records),
        Message("iotnav_raw", dev, batches[1], [], f"iotnav/{dev}/raw"),
        Message("iotnav_raw", dev, batches[2], [], f"iotnav/{dev}/raw"),
        Message("teltonika", dev, pkts[1], decode_avl(pkts[1], dev, 65536).records),
        Message("teltonika", dev, pkts[2], decode_avl(pkts[2], dev, 65536).records),
    ]
    for with_raw in (True, False):
        (tmp_path / str(with_raw)).mkdir()
        db = store.make_engine(store.sqlite_url(tmp_path / str(with_raw)))
        store.upgrade(db)
        ing = Ingestor(db, "none")
        raw = RawProcessor(ing) if with_raw else None
        worker = Worker(ClusterSettings(partitions=PARTITIONS), lambda ing=ing: ing)
        lease = _Lease(0, 1, time.monotonic() + 3600.0)
        acks: list[bytes] = []
        msgs = [FetchedMessage(encode_message(m), acks) for m in wire]

        async def run(worker=worker, lease=lease, ing=ing, raw=raw, msgs=msgs) -> None:
            await worker._process(lease, ing, raw, msgs, asyncio.get_running_loop())

        asyncio.run(run())
        assert acks == [msgs[-1].data]  # AckAll of the whole fetch, after its commits
        with db.connect() as con:
            got = [bytes(r[0]) for r in con.exec_driver_sql("SELECT payload FROM raw_messages ORDER BY id")]
        if with_raw:
            assert got == [m.payload for m in wire]  # the stream's order
            assert len(_clean(db, dev)) > 0 and worker.stats.failed == 0
        else:
            assert got == pkts and worker.stats.failed == 3  # counted, the others stored
        ing.close()
        db.dispose()


def test_worker_reads_the_raw_engines_of_serves_settings(tmp_path) -> None:
    """``iotnav worker --config serve.toml`` takes the edge's ``raw_*`` settings; an option given
    on the command line wins; without either, the defaults of ``iotnav serve``."""
    from iotnav.cli.worker import raw_settings

    toml = tmp_path / "serve.toml"
    toml.write_text(
        '[serve]\nraw_engine = "eskf"\nraw_output_interval_s = 0.5\n[serve.raw_engines]\n"truck-*" = "anchor"\n'
    )
    got = raw_settings(toml, raw_engine_config="eskf.toml")
    assert got == {
        "raw_engine": "eskf",
        "raw_engine_config": "eskf.toml",
        "raw_engines": {"truck-*": "anchor"},
        "raw_output_interval_s": 0.5,
    }
    cfg = WorkerConfig(db="sqlite://", **raw_settings(None, raw_output_interval_s=2.0))
    assert (cfg.raw_engine, cfg.raw_engine_config, cfg.raw_engines, cfg.raw_output_interval_s) == (
        "pipeline",
        "",
        {},
        2.0,
    )


def test_an_edge_refuses_a_batch_larger_than_nats_takes(tmp_path) -> None:
    """A raw batch the decoder accepts (up to 2 MB) may exceed the NATS server's ``max_payload``
    (1 MB by default) once encoded: the edge refuses it, counted, instead of failing the
    publish on every redelivery; a batch within the limit is published."""
    import numpy as np

    from iotnav.service import store
    from iotnav.service.protocols.iotnav_raw import MAX_MESSAGE_BYTES, RawBatch, decode, encode_json
    from iotnav.service.worker_edge import EdgeIngestor

    rng = np.random.default_rng(3)
    imu = np.column_stack([1e9 + 0.01 * np.arange(9000), rng.normal(size=(9000, 6))])
    big = encode_json(imu, [])
    assert 1_100_000 < len(big) < MAX_MESSAGE_BYTES and isinstance(decode(big, "car-0"), RawBatch)
    nats = NatsServer().start()
    db = store.make_engine(store.sqlite_url(tmp_path))
    store.upgrade(db)
    edge = EdgeIngestor(db, "none", cluster=ClusterSettings(url=nats.url, partitions=PARTITIONS))

    async def send() -> list:
        await edge.connect()
        try:
            return [
                await edge.enqueue("iotnav_raw", "car-0", p, [], "iotnav/car-0/raw") for p in (big, b"{}")
            ]
        finally:
            await edge.disconnect()

    try:
        too_large, small = asyncio.run(send())
    finally:
        nats.stop()
        edge.close()
        db.dispose()
    assert (
        not too_large.accepted and too_large.reason == "too_large" and edge.counts["published_too_large"] == 1
    )
    assert small.accepted and edge.counts["published"] == 1
