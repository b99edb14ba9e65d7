"""Throughput of ``iotnav worker`` with 1 and 2 workers (NATS JetStream, PostgreSQL).

Per worker count: a fresh ``nats-server -js`` (file storage), a fresh PostgreSQL database
(``fsync=on``), ``--partitions`` partitions and ``iotnav worker --engine fixes`` processes
(the GNSS-only engine run on every fix, checkpoints every 60 s). Once the workers share the
partitions evenly they are paused (SIGSTOP), ``--devices`` x ``--messages`` Teltonika Codec 8
messages of one fix each are published to the stream (as ``iotnav serve --nats`` does: the
store's key as ``Nats-Msg-Id``, subject by device), the workers are resumed (SIGCONT) and the
time until every message is stored (``raw_messages`` rows) gives the fixes/s the workers
sustain from a backlog. CPU of each component (workers, PostgreSQL backends, nats-server) is
read from ``/proc`` over that phase and divided by the messages: the per-message costs that
``docs/scaling.md`` scales up.

Then the edge alone: ``iotnav serve --nats`` with ``--edge-devices`` Teltonika connections,
each sending ``--edge-messages`` packets and waiting for each ACK (sent after JetStream's
publish acknowledgement); the edge's CPU per message and the ACK latency.

Everything runs on this machine (2 cores shared with the generator, the server, PostgreSQL
and other jobs): the ratio of 2 to 1 workers is what this machine gives, not a proof of
scaling across machines. Bounded: each phase stops after ``--timeout`` s.

Run: ``.venv/bin/python benchmarks/bench_workers.py --repeat 2`` (defaults: 2,000 devices x 10 messages,
16 partitions); ``IOTNAV_WRITE_RESULTS=1`` writes ``benchmarks/results/workers.md``.
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import os
import signal
import struct
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import sqlalchemy as sa

sys.path.insert(0, str(Path(__file__).resolve().parent.parent / "tests"))

from _cluster_helpers import NatsServer, lease_owners, start_worker
from _service_helpers import Postgres, Service, codec8_packet, imei_frame
from iotnav.service.ingest import Message
from iotnav.service.protocols.teltonika import decode_avl
from iotnav.service.workers import ClusterSettings, encode_message, partition_of

BASE_MS = 1_700_000_000_000
CLK_TCK = os.sysconf("SC_CLK_TCK")


def cpu_s(pid: int) -> float:
    """User + system CPU of ``pid`` so far, s (0 when it has gone)."""
    try:
        fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    except (FileNotFoundError, ProcessLookupError):
        return 0.0
    return (int(fields[11]) + int(fields[12])) / CLK_TCK


def children(pid: int) -> list[int]:
    """Direct children of ``pid``."""
    out = []
    for d in Path("/proc").iterdir():
        if d.name.isdigit():
            try:
                if int((d / "stat").read_text().rsplit(")", 1)[1].split()[1]) == pid:
                    out.append(int(d.name))
            except (FileNotFoundError, ProcessLookupError, IndexError):
                pass
    return out


def pg_cpu(pg: Postgres) -> float:
    """CPU of the PostgreSQL cluster's processes (postmaster and its children), s."""
    master = int((pg.dir / "data" / "postmaster.pid").read_text().split()[0])
    return cpu_s(master) + sum(cpu_s(c) for c in children(master))


def messages(devices: int, per_device: int) -> list[Message]:
    """``per_device`` one-fix Teltonika messages of each device, in device-time order."""
    out = []
    for j in range(per_device):
        for k in range(devices):
            imei = f"35300000{k:07d}"
            lat, lon = 45.0 + 0.001 * (k % 100) + 9e-5 * j, 7.0 + 0.001 * (k // 100) + 1e-4 * j
            pkt = codec8_packet([(BASE_MS + 1000 * j, lat, lon, 36, 9)])
            out.append(Message("teltonika", imei, pkt, decode_avl(pkt, imei, 65536).records, "bench"))
    return out


async def publish_all(url: str, cluster: ClusterSettings, msgs: list[Message]) -> None:
    import nats

    nc = await nats.connect(url)
    js = nc.jetstream()
    from iotnav.service.workers import ensure_stream

    await ensure_stream(js, cluster)
    for i in range(0, len(msgs), 1000):
        await asyncio.gather(
            *[
                js.publish(
                    cluster.subject_of(partition_of(m.device, cluster.partitions)),
                    encode_message(m),
                    headers={"Nats-Msg-Id": m.digest()},
                )
                for m in msgs[i : i + 1000]
            ]
        )
    await nc.close()


def count(db: sa.engine.Engine) -> int:
    with db.connect() as con:
        return int(con.exec_driver_sql("SELECT count(*) FROM raw_messages").scalar() or 0)


def db_size(db: sa.engine.Engine) -> int:
    """Size of the database on disk, bytes (tables, indexes, TOAST; after a checkpoint of its pages)."""
    with db.connect() as con:
        return int(con.exec_driver_sql("SELECT pg_database_size(current_database())").scalar() or 0)


def run_workers(n: int, pg: Postgres, args: argparse.Namespace, work: Path, run: int = 0) -> dict[str, float]:
    """One run with ``n`` workers (``run``: its number, for a fresh database); its figures."""
    dbname = f"bench_w{n}_{run}_{os.getpid()}"
    admin = sa.create_engine(pg.url, isolation_level="AUTOCOMMIT")
    with admin.connect() as con:
        con.exec_driver_sql(f"CREATE DATABASE {dbname}")
    admin.dispose()
    nats = NatsServer().start()  # (after the database: a failure above leaves no server behind)
    url = pg.url.replace("/postgres?", f"/{dbname}?")
    cluster = ClusterSettings(url=nats.url, partitions=args.partitions, lease_s=60.0)
    wargs = [
        "--nats",
        nats.url,
        "--db",
        url,
        "--data",
        str(work / "data"),
        "--partitions",
        str(args.partitions),
    ]
    wargs += ["--lease", "60", "--engine", "fixes"]
    procs = [start_worker(work / f"w{n}-{i}.log", *wargs) for i in range(n)]
    try:
        t_end = time.monotonic() + args.timeout
        while True:  # each worker holds its share (P / n)
            owners = lease_owners(nats.url)
            share = [sum(1 for o in owners.values() if f"-{p.pid}-" in o) for p in procs]
            if len(owners) == args.partitions and max(share) - min(share) <= 1:
                break
            if time.monotonic() > t_end:
                raise TimeoutError(f"workers not balanced: {share}")
            time.sleep(0.2)
        time.sleep(1.0)
        for p in procs:
            os.kill(p.pid, signal.SIGSTOP)
        msgs = messages(args.devices, args.messages)
        t0 = time.perf_counter()
        asyncio.run(publish_all(nats.url, cluster, msgs))
        t_pub = time.perf_counter() - t0
        db = sa.create_engine(url)
        size0 = db_size(db)
        cpu0 = [sum(cpu_s(p.pid) for p in procs), pg_cpu(pg), cpu_s(nats.proc.pid)]  # type: ignore[union-attr]
        t0 = time.perf_counter()
        for p in procs:
            os.kill(p.pid, signal.SIGCONT)
        n_total = len(msgs)
        while (got := count(db)) < n_total and time.perf_counter() - t0 < args.timeout:
            time.sleep(0.1)
        dt = time.perf_counter() - t0
        cpu1 = [sum(cpu_s(p.pid) for p in procs), pg_cpu(pg), cpu_s(nats.proc.pid)]  # type: ignore[union-attr]
        with db.connect() as con:
            n_clean = con.exec_driver_sql("SELECT count(*) FROM positions WHERE engine = 'fixes'").scalar()
        size1 = db_size(db)
        db.dispose()
        return {
            "workers": n,
            "messages": n_total,
            "stored": got,
            "clean": int(n_clean or 0),
            "seconds": dt,
            "rate": got / dt,
            "publish_rate": n_total / t_pub,
            "worker_us": 1e6 * (cpu1[0] - cpu0[0]) / max(got, 1),
            "pg_us": 1e6 * (cpu1[1] - cpu0[1]) / max(got, 1),
            "nats_us": 1e6 * (cpu1[2] - cpu0[2]) / max(got, 1),
            "bytes": (size1 - size0) / max(got, 1),
        }
    finally:
        for p in procs:
            with contextlib.suppress(ProcessLookupError):
                os.kill(p.pid, signal.SIGCONT)
            p.terminate()
            p.wait(60)
        nats.stop()


async def _edge_device(port: int, imei: str, n: int, lat: list[float]) -> None:
    reader, writer = await asyncio.open_connection("127.0.0.1", port)
    writer.write(imei_frame(imei))
    await writer.drain()
    assert await reader.readexactly(1) == b"\x01"
    for j in range(n):
        pkt = codec8_packet([(BASE_MS + 1000 * j, 45.0 + 1e-4 * j, 7.0, 36, 9)])
        t0 = time.perf_counter()
        writer.write(pkt)
        await writer.drain()
        assert await reader.readexactly(4) == struct.pack(">I", 1)
        lat.append(time.perf_counter() - t0)
    writer.close()


def run_edge(pg: Postgres, args: argparse.Namespace, work: Path) -> dict[str, float]:
    """The edge alone: Teltonika devices -> ``iotnav serve --nats`` -> JetStream (no worker)."""
    nats = NatsServer().start()
    svc = Service(
        work / "edge",
        db=pg.url,
        engine="none",
        nats=nats.url,
        nats_partitions=args.partitions,
        max_connections_per_address=args.edge_devices + 10,  # every simulated device is on 127.0.0.1
    )
    svc.start()
    try:
        lat: list[float] = []

        async def go() -> None:
            await asyncio.gather(
                *[
                    _edge_device(svc.tcp, f"35400000{k:07d}", args.edge_messages, lat)
                    for k in range(args.edge_devices)
                ]
            )

        assert svc.proc is not None
        c0, n0, t0 = cpu_s(svc.proc.pid), cpu_s(nats.proc.pid), time.perf_counter()  # type: ignore[union-attr]
        asyncio.run(go())
        dt = time.perf_counter() - t0
        c1, n1 = cpu_s(svc.proc.pid), cpu_s(nats.proc.pid)  # type: ignore[union-attr]
        n = len(lat)
        ms = 1e3 * np.array(lat)
        return {
            "messages": n,
            "rate": n / dt,
            "edge_us": 1e6 * (c1 - c0) / n,
            "nats_us": 1e6 * (n1 - n0) / n,
            "p50": float(np.percentile(ms, 50)),
            "p99": float(np.percentile(ms, 99)),
        }
    finally:
        svc.stop()
        nats.stop()


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--devices", type=int, default=2000)
    ap.add_argument("--messages", type=int, default=10, help="messages (one fix each) per device")
    ap.add_argument("--partitions", type=int, default=16)
    ap.add_argument("--workers", type=int, nargs="*", default=[1, 2])
    ap.add_argument(
        "--repeat", type=int, default=1, help="runs of the worker counts, interleaved (1, 2, 1, 2, ...)"
    )
    ap.add_argument("--edge-devices", type=int, default=200)
    ap.add_argument("--edge-messages", type=int, default=20)
    ap.add_argument("--timeout", type=float, default=240.0)
    args = ap.parse_args()
    load = os.getloadavg()[0]
    pg = Postgres().start()
    rows = []
    edge = None
    try:
        with tempfile.TemporaryDirectory(prefix="iotnav-bench-workers-") as tmp:
            for i, n in enumerate([n for _ in range(args.repeat) for n in args.workers]):
                r = run_workers(n, pg, args, Path(tmp), i)
                print(r, flush=True)
                rows.append(r)
            edge = run_edge(pg, args, Path(tmp)) if args.edge_devices > 0 else None
            print(edge, flush=True)
    finally:
        pg.stop()
    lines = [
        "## Workers on NATS JetStream (`benchmarks/bench_workers.py`)",
        "",
        f"A backlog of {args.devices:,} Teltonika devices x {args.messages} messages (one fix each) in the"
        f" JetStream stream, {args.partitions} partitions, `iotnav worker --engine fixes` processes"
        " storing to PostgreSQL (`fsync=on`, checkpoints every 60 s), acknowledging each batch after its"
        " commit. *fixes/s*: messages stored per second of wall time from the workers' resumption to the"
        " last row. CPU per message from `/proc` over that phase. Everything (nats-server, PostgreSQL,"
        " workers, generator) on this 2-core machine shared with other jobs: the 2-worker ratio is what"
        " one machine gives, **not a proof of scaling** across machines (the other jobs' load changes"
        " from run to run: the runs are interleaved, the ratio is to the median 1-worker run).",
        "",
        "| workers | messages stored | clean positions | time | fixes/s | ratio to 1 worker | worker CPU / msg | PostgreSQL CPU / msg | nats-server CPU / msg | database growth / msg |",
        "|---|---|---|---|---|---|---|---|---|---|",
    ]
    ones = [r["rate"] for r in rows if r["workers"] == 1]
    base = float(np.median(ones)) if ones else 1.0  # the ratio is to the median of the 1-worker runs
    for r in rows:
        lines.append(
            f"| {r['workers']} | {r['stored']:,} / {r['messages']:,} | {r['clean']:,} | {r['seconds']:.1f} s |"
            f" {r['rate']:,.0f} | {r['rate'] / base:.2f} | {r['worker_us']:.0f} us | {r['pg_us']:.0f} us |"
            f" {r['nats_us']:.0f} us | {r['bytes']:,.0f} B |"
        )
    if edge is not None:
        lines += [
            "",
            f"Edge alone (`iotnav serve --nats`, no worker): {args.edge_devices} Teltonika connections x"
            f" {args.edge_messages} packets, each waiting for its ACK (sent after JetStream's publish"
            f" acknowledgement): {edge['messages']:,} messages at {edge['rate']:,.0f} msg/s, ACK latency"
            f" p50 {edge['p50']:.1f} ms / p99 {edge['p99']:.1f} ms, edge CPU {edge['edge_us']:.0f} us/msg,"
            f" nats-server {edge['nats_us']:.0f} us/msg.",
        ]
    lines += ["", f"Load average of the machine at the start: {load:.1f} (2 cores)."]
    text = "\n".join(lines) + "\n"
    print(text)
    if os.environ.get("IOTNAV_WRITE_RESULTS") == "1":
        (Path(__file__).parent / "results" / "workers.md").write_text(text)


if __name__ == "__main__":
    main()
