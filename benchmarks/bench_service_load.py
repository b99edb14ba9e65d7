"""Load on ``iotnav serve``: N simulated Teltonika devices, one fix per second each.

Issue #18 target: 10,000 devices at 1 Hz with p99 ingest-to-API latency under 1 s on SQLite,
on this 2-core machine. The benchmark starts a real ``iotnav serve`` subprocess (``engine =
"fixes"``, SQLite in a temporary data directory, free 127.0.0.1 ports), opens ``--devices``
Teltonika TCP connections (IMEI handshake, then one Codec 8 packet of one record per device
per second, each device waiting for its ACK as real devices do, phases spread over the
second) for ``--duration`` seconds, and listens on the ``/api/socket`` WebSocket in a second
process. Measured per message:

- ingest-to-ACK: from ``sendall`` of the packet to the 4-byte ACK (the ACK is sent only
  after the commit, so this is ingest-to-durable);
- ingest-to-visible: from ``sendall`` to the position arriving on ``/api/socket`` (same
  clock, ``time.time``, both processes on this machine).

At the end the SQLite file is counted: every acknowledged fix must be a stored position
(``lost`` must be 0). CPU of the service process is read from ``/proc/PID/stat`` over the load
phase. Everything is localhost and bounded in count and in time (the run stops by itself).

The service stores by group commit (:mod:`iotnav.service.ingest`): what arrives while a
transaction is written goes into the next one, and every ACK waits for the commit of its
message. The generator is one asyncio process (10,000 connections need ``ulimit -n`` above
10,000 for it and for the service).

Run: ``.venv/bin/python benchmarks/bench_service_load.py --devices 100 1000 10000 --duration 60``
(one fresh service per device count); with ``IOTNAV_WRITE_RESULTS=1`` the table is written to
``benchmarks/results/service_load.md``. ``--protocol`` offers ``teltonika`` only (OsmAnd HTTP is
not simulated yet). Before the load runs, :func:`db_thread_ms` times the database thread alone,
which bounds what the service can sustain.
"""

from __future__ import annotations

import argparse
import asyncio
import json
import multiprocessing as mp
import os
import sqlite3
import struct
import subprocess
import sys
import tempfile
import time
from datetime import datetime
from pathlib import Path
from typing import Any

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent.parent / "tests"))

from _service_helpers import Service, codec8_packet, imei_frame

BASE_MS = 1_700_000_000_000  # device time of tick 0 (the key of a fix: device, tick)
ACK_TIMEOUT_S = 30.0  # s a device waits for its ACK before it counts an error and stops
STOP_TIMEOUT_S = 180.0  # s allowed for the service's shutdown (10,000 checkpoints)
CLK_TCK = os.sysconf("SC_CLK_TCK")


def _imei(i: int) -> str:
    return f"35{i:013d}"


def _cpu_s(pid: int) -> float:
    """User + system CPU seconds of process ``pid`` (``/proc/PID/stat`` fields 14, 15)."""
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / CLK_TCK


def _listen(url: str, token: str, until: float, out: str, ready: Any, stop: Any) -> None:
    """WebSocket client (own process): (deviceId, fixTime ms, receive time) of each position.

    Listens until ``stop`` is set or ``until`` (``time.time``) passes, then writes ``out``.
    """
    import websockets

    async def run() -> None:
        got: list[tuple[int, int, float]] = []
        async with websockets.connect(url, additional_headers={"Authorization": f"Bearer {token}"}) as ws:
            ready.set()
            while time.time() < until and not stop.is_set():
                try:
                    msg = await asyncio.wait_for(ws.recv(), timeout=0.5)
                except TimeoutError:
                    continue
                t = time.time()
                for p in json.loads(msg).get("positions", []):
                    ms = round(datetime.fromisoformat(p["fixTime"].replace("Z", "+00:00")).timestamp() * 1000)
                    got.append((int(p["deviceId"]), ms, t))
        Path(out).write_text(json.dumps(got))

    asyncio.run(run())


class Device:
    """One simulated tracker: a TCP connection, its send times and ACK latencies."""

    def __init__(self, i: int) -> None:
        self.i = i
        self.imei = _imei(i)
        self.sent: dict[int, float] = {}  # tick -> send time (time.time)
        self.ack_s: list[float] = []
        self.acked: list[int] = []
        self.errors = 0
        self.reader: asyncio.StreamReader | None = None
        self.writer: asyncio.StreamWriter | None = None

    async def connect(self, port: int) -> None:
        self.reader, self.writer = await asyncio.open_connection("127.0.0.1", port)
        self.writer.write(imei_frame(self.imei))
        await self.writer.drain()
        if await asyncio.wait_for(self.reader.readexactly(1), ACK_TIMEOUT_S * 3) != b"\x01":
            raise ConnectionError(f"device {self.imei} refused")

    async def run(self, t0: float, n_ticks: int, n_devices: int) -> None:
        assert self.reader is not None and self.writer is not None
        phase = self.i / n_devices
        for k in range(n_ticks):
            if time.time() > t0 + n_ticks:
                return  # the load window is over (a saturated device sends no late backlog)
            delay = t0 + k + phase - time.time()
            if delay > 0:
                await asyncio.sleep(delay)
            lat, lon = 48.0 + 1e-3 * (self.i % 1000), 11.0 + 1e-3 * (self.i // 1000) + 1e-5 * k
            packet = codec8_packet([(BASE_MS + 1000 * k, lat, lon, 3, 9)])
            t = time.time()
            self.sent[k] = t
            try:
                self.writer.write(packet)
                async with asyncio.timeout(ACK_TIMEOUT_S):  # (no task per read: 10,000 devices in one loop)
                    ack = await self.reader.readexactly(4)
            except (OSError, asyncio.IncompleteReadError, TimeoutError):
                self.errors += 1
                return  # a device whose connection broke stops (counted)
            if ack == struct.pack(">I", 1):
                self.ack_s.append(time.time() - t)
                self.acked.append(k)
            else:
                self.errors += 1

    def close(self) -> None:
        if self.writer is not None:
            self.writer.close()


async def _load(svc: Service, n: int, duration: float) -> tuple[list[Device], dict[str, float]]:
    """Connect ``n`` devices, then run them for ``duration`` s; the devices and the run's numbers."""
    devices = [Device(i) for i in range(n)]
    sem = asyncio.Semaphore(200)

    async def connect(d: Device) -> None:
        async with sem:
            await d.connect(svc.tcp)

    t_c = time.monotonic()
    await asyncio.gather(*(connect(d) for d in devices))
    connect_s = time.monotonic() - t_c
    assert svc.proc is not None
    cpu0, w0 = _cpu_s(svc.proc.pid), time.time()
    t0 = time.time() + 1.0
    n_ticks = int(duration)
    tasks = [asyncio.create_task(d.run(t0, n_ticks, n)) for d in devices]
    _, late = await asyncio.wait(tasks, timeout=duration + ACK_TIMEOUT_S + 10)
    for task in late:  # cannot happen with the ACK timeout; bounded all the same
        task.cancel()
    wall = time.time() - t0
    cpu = (_cpu_s(svc.proc.pid) - cpu0) / (time.time() - w0)
    for d in devices:
        d.close()
    return devices, {"connect_s": connect_s, "wall_s": wall, "cpu_cores": cpu, "ticks": n_ticks}


def measure(n: int, duration: float, engine: str = "fixes") -> dict[str, Any]:
    """Run ``n`` devices for ``duration`` s against a fresh service running ``engine``; the numbers."""
    with tempfile.TemporaryDirectory(prefix="iotnav-load-") as tmp:
        svc = Service(
            Path(tmp) / "data", engine=engine, max_connections_per_address=n + 16, idle_timeout_s=600.0
        ).start(timeout=180)
        try:
            token = svc.admin_token
            t_ws_end = time.time() + duration + 60 + n / 50
            out = str(Path(tmp) / "ws.json")
            ctx = mp.get_context("spawn")
            ready, stop = ctx.Event(), ctx.Event()
            url = f"ws://127.0.0.1:{svc.api}/api/socket"
            ws_proc = ctx.Process(target=_listen, args=(url, token, t_ws_end, out, ready, stop))
            ws_proc.start()
            if not ready.wait(60):
                raise RuntimeError("WebSocket listener did not connect")
            devices, res = asyncio.run(_load(svc, n, duration))
            time.sleep(3.0)  # the last broadcasts
            stop.set()
            ws_proc.join(60)
            con = sqlite3.connect(Path(tmp) / "data" / "iotnav.sqlite", timeout=30)
            ids = dict(con.execute("SELECT unique_id, id FROM devices").fetchall())
            stored = set(
                con.execute(
                    "SELECT device_id, CAST(round(fix_time * 1000) AS INTEGER) FROM positions"
                ).fetchall()
            )
            con.close()
        finally:  # SIGTERM: the service drains its queue and writes every device's checkpoint
            assert svc.proc is not None
            svc.proc.terminate()
            try:
                svc.proc.wait(STOP_TIMEOUT_S)
            except subprocess.TimeoutExpired:
                svc.proc.kill()
                svc.proc.wait(10)
            svc.log.close()
        got = json.loads(Path(out).read_text()) if Path(out).exists() else []
    first: dict[tuple[int, int], float] = {}
    for dev, ms, t in got:
        first.setdefault((dev, ms), t)
    ack = np.concatenate([np.asarray(d.ack_s) for d in devices]) if devices else np.zeros(0)
    vis: list[float] = []
    lost = unseen = 0
    for d in devices:
        dev = ids.get(d.imei)
        for k in d.acked:
            key = (dev, BASE_MS + 1000 * k)
            if dev is None or key not in stored:
                lost += 1
            if key in first:
                vis.append(first[key] - d.sent[k])
            else:
                unseen += 1
    sent = sum(len(d.sent) for d in devices)
    visa = np.asarray(vis)

    def pct(a: np.ndarray, q: float) -> float:
        return float(np.percentile(a, q)) if a.size else float("nan")

    return {
        "engine": engine,
        "devices": n,
        "duration_s": res["wall_s"],
        "connect_s": res["connect_s"],
        "offered": n * res["ticks"],
        "sent": sent,
        "acked": int(ack.size),
        "rate": ack.size / res["wall_s"],
        "ack_p50": pct(ack, 50),
        "ack_p99": pct(ack, 99),
        "ack_max": float(ack.max()) if ack.size else float("nan"),
        "vis_p50": pct(visa, 50),
        "vis_p99": pct(visa, 99),
        "unseen": unseen,
        "errors": sum(d.errors for d in devices),
        "lost": lost,
        "cpu_cores": res["cpu_cores"],
    }


def db_thread_ms(engine: str, batch: int, n_dev: int = 500, n_msg: int = 3000) -> float:
    """Steady time per message of ``Ingestor.ingest_batch`` (the service's database thread), ms.

    In-process, SQLite in a temporary directory, one Codec 8 record per message as in the load
    run, ``batch`` messages per transaction (1: a transaction per message, as without group
    commit), after each of ``n_dev`` devices has sent one message (registration, engine start);
    ``1000 / db_thread_ms`` is the ceiling of the database thread in messages per second.
    """
    from iotnav.service.app import ServiceConfig, prepare
    from iotnav.service.ingest import Message
    from iotnav.service.protocols.teltonika import decode_avl

    with tempfile.TemporaryDirectory(prefix="iotnav-db-") as tmp:
        _, ing = prepare(ServiceConfig(data=tmp, engine=engine))

        def send(j0: int, n: int, size: int) -> None:
            msgs = []
            for j in range(j0, j0 + n):
                i, k = j % n_dev, j // n_dev
                pkt = codec8_packet([(BASE_MS + 1000 * k, 48.0 + 1e-3 * i, 11.0 + 1e-5 * k, 3, 9)])
                msgs.append(
                    Message("teltonika", _imei(i), pkt, decode_avl(pkt, _imei(i)).records, "127.0.0.1")
                )
            for b in range(0, n, size):
                assert not any(isinstance(r, Exception) for r in ing.ingest_batch(msgs[b : b + size]))

        send(0, n_dev, 100)
        t = time.perf_counter()
        send(n_dev, n_msg, batch)
        return (time.perf_counter() - t) / n_msg * 1e3


HEADER = [
    "## Service load (`benchmarks/bench_service_load.py`)",
    "",
    "Teltonika TCP devices at 1 fix/s each (one Codec 8 record per packet, each device waits for",
    'its ACK), `iotnav serve` with `engine = "fixes"` on SQLite (WAL, `synchronous=FULL`), group',
    "commit (one transaction for the messages that arrived while the previous one was written),",
    "2-core machine shared with other jobs; load generator (one asyncio process) and WebSocket",
    "listener run on the same machine. *ACK*: send to 4-byte ACK (sent after the commit).",
    "*visible*: send to the position on `/api/socket`. *lost*: acknowledged but not stored (must",
    "be 0). *unseen*: acknowledged but not received on the socket. *service CPU*: the service is",
    "one Python process, so about 1 core means it is saturated (the event loop and the database",
    "thread share one interpreter lock).",
    "",
    "| devices | engine | duration | offered fixes | acked | acked/s | ACK p50 / p99 / max | visible p50 / p99 | "
    "errors | lost | unseen | service CPU | p99 < 1 s |",
    "|---|---|---|---|---|---|---|---|---|---|---|---|---|",
]


def row(r: dict[str, Any]) -> str:
    """One markdown table row of a :func:`measure` result."""
    ok = r["vis_p99"] < 1.0 and r["ack_p99"] < 1.0 and r["acked"] >= 0.99 * r["offered"] and r["lost"] == 0
    return (
        f"| {r['devices']:,} | {r['engine']} | {r['duration_s']:.0f} s | {r['offered']:,} | {r['acked']:,} | {r['rate']:,.0f} | "
        f"{r['ack_p50'] * 1e3:.0f} / {r['ack_p99'] * 1e3:.0f} / {r['ack_max'] * 1e3:.0f} ms | "
        f"{r['vis_p50'] * 1e3:.0f} / {r['vis_p99'] * 1e3:.0f} ms | {r['errors']} | {r['lost']} | {r['unseen']} | "
        f"{r['cpu_cores']:.2f} cores | {'yes' if ok else 'no'} |"
    )


def main() -> None:
    """Parse the options, run each device count, print (and optionally write) the table."""
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--devices", type=int, nargs="+", default=[100, 1000], help="device counts to run")
    ap.add_argument("--duration", type=float, default=30.0, help="seconds of load per run")
    ap.add_argument("--engine", default="fixes", help="engine of the service (fixes; none: store only)")
    ap.add_argument("--protocol", choices=["teltonika"], default="teltonika", help="device protocol")
    args = ap.parse_args()
    if max(args.devices) > 20000 or args.duration > 300:
        ap.error("bounded: at most 20,000 devices and 300 s")
    load0 = os.getloadavg()[0]
    ms = {
        (e, b): db_thread_ms(e, b, n_msg=500 if b == 1 else 3000)
        for e in dict.fromkeys([args.engine, "none"])
        for b in (1, 500)
    }
    rows = []
    for n in args.devices:
        r = measure(n, args.duration, args.engine)
        print(json.dumps(r), flush=True)
        rows.append(row(r))
    notes = [
        "",
        "Database thread alone (`Ingestor.ingest_batch` in-process, one record per message, 500 devices, "
        "`synchronous=FULL`): "
        + "; ".join(
            f"engine `{e}`, {b} message{'s' if b > 1 else ''} per transaction: {v:.2f} ms/message, "
            f"ceiling {1000 / v:,.0f} messages/s"
            for (e, b), v in ms.items()
        )
        + f". Load average of the machine at the start: {load0:.1f} (2 cores).",
    ]
    text = "\n".join([*HEADER, *rows, *notes, ""])
    print(text)
    if os.environ.get("IOTNAV_WRITE_RESULTS") == "1":
        out = Path(__file__).parent / "results" / "service_load.md"
        out.write_text(text)


if __name__ == "__main__":
    main()
