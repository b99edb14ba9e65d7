"""Load on ``iotnav serve``: N simulated Teltonika devices, one fix per second each.

Issue #18 target: 10,000 devices at 1 Hz with p99 ingest-to-API latency under 1 s on SQLite,
on this 2-core machine. The benchmark starts a real ``iotnav serve`` subprocess (``engine =
"fixes"``, SQLite in a temporary data directory, free 127.0.0.1 ports), opens ``--devices``
Teltonika TCP connections (IMEI handshake, then one Codec 8 packet of one record per device
per second, each device waiting for its ACK as real devices do, phases spread over the
second) for ``--duration`` seconds, and listens on the ``/api/socket`` WebSocket in a second
process. Each device first sends one registration message (it creates the device and its engine
on the service) and waits for its ACK; the measured window starts once every device is
registered (a fleet registers once; the registration burst is timed apart). Measured per
message:

- ingest-to-ACK: from ``sendall`` of the packet to the 4-byte ACK (the ACK is sent only
  after the commit, so this is ingest-to-durable);
- ingest-to-visible: from ``sendall`` to the position arriving on ``/api/socket`` (same
  clock, ``time.time``, both processes on this machine).

At the end the SQLite file is counted: every acknowledged fix must be a stored position
(``lost`` must be 0). CPU of the service, of this generator and of the WebSocket listener is
read from ``/proc/PID/stat`` over the load phase. Everything is localhost and bounded in count and in time (the run stops by itself).

The service stores by group commit (:mod:`iotnav.service.ingest`): what arrives while a
transaction is written goes into the next one, and every ACK waits for the commit of its
message. The generator is one asyncio process of low-level protocols, a timer per packet, no
task per device (10,000 connections need ``ulimit -n`` above
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
import gc
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
REGISTER_TIMEOUT_S = 300.0  # s allowed for the registration messages of every device
STOP_TIMEOUT_S = 180.0  # s allowed for the service's shutdown (10,000 checkpoints)
CLK_TCK = os.sysconf("SC_CLK_TCK")


def _imei(i: int) -> str:
    return f"35{i:013d}"


def _cpu_s(pid: int) -> float:
    """User + system CPU seconds of process ``pid`` (``/proc/PID/stat`` fields 14, 15)."""
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / CLK_TCK


def _tree(pid: int) -> list[int]:
    """``pid`` and its descendants (``/proc/PID/task/*/children``): the service's worker processes."""
    out = [pid]
    for task in Path(f"/proc/{pid}/task").iterdir():
        for c in (task / "children").read_text().split():
            out += _tree(int(c))
    return out


def _tree_cpu_s(pids: list[int]) -> float:
    """CPU seconds of ``pids`` (those still running)."""
    total = 0.0
    for p in pids:
        try:
            total += _cpu_s(p)
        except FileNotFoundError:
            continue
    return total


def _listen(url: str, token: str, until: float, out: str, ready: Any, stop: Any) -> None:
    """WebSocket client (own process): (deviceId, fixTime ms, receive time) of each position.

    Listens until ``stop`` is set or ``until`` (``time.time``) passes, then writes ``out``.
    """
    import websockets

    async def run() -> None:
        got: list[tuple[int, int, float]] = []
        _collector_off()  # its pauses would delay the receive times (``got`` grows to 300,000 tuples)
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


class Device(asyncio.Protocol):
    """One simulated tracker: a TCP connection (a low-level protocol: 10,000 of them in one
    loop cost less than streams), its send times and ACK latencies.

    After the handshake it sends one packet per second at ``t0 + k + phase`` (``phase`` spreads
    the devices over the second) and waits for its ACK; a packet whose ACK comes after its
    next send time delays the next one (a device never has two packets in flight).
    """

    def __init__(self, i: int, n_devices: int) -> None:
        self.i = i
        self.imei = _imei(i)
        self.phase = i / n_devices
        self.sent: dict[int, float] = {}  # tick -> send time (time.time)
        self.ack_s: list[float] = []
        self.acked: list[int] = []
        self.errors = 0
        self.transport: asyncio.Transport | None = None
        self.buf = b""
        self.ready: asyncio.Future[None] | None = None
        self.done: asyncio.Future[None] | None = None
        self.k: int | None = None  # tick in flight
        self.warm: asyncio.Future[float] | None = None  # the ACK of the registration message
        self.t0 = 0.0
        self.n_ticks = 0
        self.loop: asyncio.AbstractEventLoop | None = None

    async def connect(self, port: int) -> None:
        self.loop = loop = asyncio.get_running_loop()
        self.ready, self.done = loop.create_future(), loop.create_future()
        await loop.create_connection(lambda: self, "127.0.0.1", port)
        assert self.transport is not None
        self.transport.write(imei_frame(self.imei))
        await asyncio.wait_for(self.ready, ACK_TIMEOUT_S * 3)

    def connection_made(self, transport: asyncio.BaseTransport) -> None:
        assert isinstance(transport, asyncio.Transport)
        self.transport = transport

    def data_received(self, data: bytes) -> None:
        self.buf += data
        assert self.ready is not None
        if not self.ready.done():
            answer, self.buf = self.buf[:1], self.buf[1:]
            if answer == b"\x01":
                self.ready.set_result(None)
            else:
                self.ready.set_exception(ConnectionError(f"device {self.imei} refused"))
            return
        while len(self.buf) >= 4 and self.k is not None:
            ack, self.buf = self.buf[:4], self.buf[4:]
            k, self.k = self.k, None
            if k < 0:  # the registration message (not measured)
                assert self.warm is not None
                if ack == _ACK1:
                    self.warm.set_result(time.time() - self.sent.pop(k))
                else:
                    self.warm.set_exception(
                        ConnectionError(f"device {self.imei}: registration not acknowledged")
                    )
                continue
            if ack == _ACK1:
                self.ack_s.append(time.time() - self.sent[k])
                self.acked.append(k)
            else:
                self.errors += 1
            self._next(k + 1)

    def connection_lost(self, exc: Exception | None) -> None:
        if self.ready is not None and not self.ready.done():
            self.ready.set_exception(ConnectionError(f"device {self.imei}: closed"))
        if self.warm is not None and not self.warm.done():
            self.warm.set_exception(ConnectionError(f"device {self.imei}: closed"))
        if self.k is not None:  # a packet in flight and the connection broke: counted, the device stops
            self.errors += 1
            self.k = None
        self._finish()

    def _finish(self) -> None:
        if self.done is not None and not self.done.done():
            self.done.set_result(None)

    def register(self) -> asyncio.Future[float]:
        """Send the registration message (tick -1: device created, engine started); its ACK time."""
        assert self.loop is not None
        self.warm = self.loop.create_future()
        self._send(-1)
        return self.warm

    def start(self, t0: float, n_ticks: int) -> None:
        """Send ticks ``0 .. n_ticks - 1``, the first at ``t0 + phase`` (``time.time``)."""
        self.t0, self.n_ticks = t0, n_ticks
        self._next(0)

    def _next(self, k: int) -> None:
        """Schedule tick ``k`` at its time (at once when it is late); finish after the last."""
        assert self.loop is not None
        now = time.time()
        if k >= self.n_ticks or now > self.t0 + self.n_ticks:
            self._finish()  # the load window is over (a saturated device sends no late backlog)
            return
        delay = self.t0 + k + self.phase - now
        if delay > 0:
            self.loop.call_later(delay, self._send, k)
        else:
            self._send(k)

    def _send(self, k: int) -> None:
        if self.transport is None or self.transport.is_closing():
            self._finish()
            return
        lat, lon = 48.0 + 1e-3 * (self.i % 1000), 11.0 + 1e-3 * (self.i // 1000) + 1e-5 * k
        packet = codec8_packet([(BASE_MS + 1000 * k, lat, lon, 3, 9)])
        self.k = k
        self.sent[k] = time.time()
        self.transport.write(packet)

    def overdue(self, now: float) -> bool:
        """The packet in flight has waited over ``ACK_TIMEOUT_S``: counted, the device stops."""
        if self.k is not None and self.k >= 0 and now - self.sent[self.k] > ACK_TIMEOUT_S:
            self.errors += 1
            self.k = None
            self.close()
            self._finish()
            return True
        return False

    def close(self) -> None:
        if self.transport is not None:
            self.transport.close()


_ACK1 = struct.pack(">I", 1)


async def _load(svc: Service, n: int, duration: float, ws_pid: int) -> tuple[list[Device], dict[str, float]]:
    """Connect ``n`` devices, then run them for ``duration`` s; the devices and the run's numbers
    (CPU in cores over the load phase of the service, this generator and the WebSocket listener ``ws_pid``)."""
    devices = [Device(i, n) for i in range(n)]
    sem = asyncio.Semaphore(200)

    async def connect(d: Device) -> None:
        async with sem:
            await d.connect(svc.tcp)

    t_c = time.monotonic()
    await asyncio.gather(*(connect(d) for d in devices))
    connect_s = time.monotonic() - t_c
    # the first message of each device creates it and its engine: sent and acknowledged before
    # the measured window (a fleet registers once), its time reported apart
    t_r = time.monotonic()
    await asyncio.wait_for(asyncio.gather(*(d.register() for d in devices)), REGISTER_TIMEOUT_S)
    register_s = time.monotonic() - t_r
    _collector_off()
    try:
        return devices, await _run_load(svc, devices, duration, ws_pid, connect_s, register_s)
    finally:
        gc.unfreeze()
        gc.enable()


def _collector_off() -> None:
    """Freeze what is allocated so far and stop the cyclic garbage collector, in a measuring
    process (the generator, the WebSocket listener) for its bounded run.

    With it on, the generator paused up to 529-689 ms at once at 10,000 devices (timed with
    ``gc.callbacks``, 2026-12-03, 6-8 pauses over 50 ms in 30 s): every ACK that arrived during
    a pause was timed late by it, inflating the measured p99. Reference counting still frees
    what the run drops; the run is bounded in count and time.
    """
    gc.collect()
    gc.freeze()
    gc.disable()


async def _run_load(
    svc: Service, devices: list[Device], duration: float, ws_pid: int, connect_s: float, register_s: float
) -> dict[str, float]:
    """The measured window of :func:`_load` (the devices connected and registered)."""
    assert svc.proc is not None
    tree = _tree(svc.proc.pid)  # the service and its worker processes (--processes)
    cpu0, gen0, ws0, w0 = _tree_cpu_s(tree), _cpu_s(os.getpid()), _cpu_s(ws_pid), time.time()
    t0 = time.time() + 1.0
    n_ticks = int(duration)
    for d in devices:
        d.start(t0, n_ticks)
    pending = [d.done for d in devices if d.done is not None]
    t_end = t0 + duration + ACK_TIMEOUT_S + 10
    while time.time() < t_end:  # bounded; the ACK timeout ends every device before this
        _, left = await asyncio.wait(pending, timeout=1.0)
        pending = list(left)
        if not pending:
            break
        now = time.time()
        for d in devices:
            d.overdue(now)
    wall = time.time() - t0
    dt = time.time() - w0
    cpu = (_tree_cpu_s(tree) - cpu0) / dt
    gen = (_cpu_s(os.getpid()) - gen0) / dt
    ws = (_cpu_s(ws_pid) - ws0) / dt
    for d in devices:
        d.close()
    return {
        "connect_s": connect_s,
        "register_s": register_s,
        "wall_s": wall,
        "cpu_cores": cpu,
        "gen_cores": gen,
        "ws_cores": ws,
        "ticks": n_ticks,
    }


def measure(
    n: int,
    duration: float,
    engine: str = "fixes",
    src: str | None = None,
    version: str = "this",
    processes: int = 1,
) -> dict[str, Any]:
    """Run ``n`` devices for ``duration`` s against a fresh service running ``engine``; the numbers.

    ``src``: run the service of another iotnav source tree (the reference of a comparison,
    named ``version`` in the table); None: this one. ``processes``: the service's
    ``processes`` setting (1: not written, so a reference without the setting runs).
    """
    extra: dict[str, Any] = {"processes": processes} if processes > 1 else {}
    load = os.getloadavg()[0]
    with tempfile.TemporaryDirectory(prefix="iotnav-load-") as tmp:
        svc = Service(
            Path(tmp) / "data",
            src=src,
            engine=engine,
            max_connections_per_address=n + 16,
            idle_timeout_s=600.0,
            **extra,
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
            assert ws_proc.pid is not None
            devices, res = asyncio.run(_load(svc, n, duration, ws_proc.pid))
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
        "version": version,
        "processes": processes,
        "devices": n,
        "load": load,
        "duration_s": res["wall_s"],
        "connect_s": res["connect_s"],
        "register_s": res["register_s"],
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
        "gen_cores": res["gen_cores"],
        "ws_cores": res["ws_cores"],
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
    "2-core machine shared with other jobs (*load*: its 1-minute load average at the start of the",
    "run; above 2 the service gets less than the machine); load generator (one asyncio process)",
    "and WebSocket listener run on the same machine. Each device's first message (it creates the",
    "device and its engine) is sent and acknowledged before the measured window (*registration*:",
    "how long all of them took). *ACK*: send to 4-byte ACK (sent after the commit). *visible*:",
    "send to the position on `/api/socket`. *lost*: acknowledged but not stored (must be 0).",
    "*unseen*: acknowledged but not received on the socket. *CPU*: cores used over the measured",
    "window by the service / the load generator / the WebSocket listener; *service CPU per fix*:",
    "the service's CPU time (all its processes) divided by the fixes acknowledged (what bounds the",
    "rate: a Python process's event loop and database thread share one interpreter lock, and only",
    "SQLite's own work runs beside it). *processes*: the service's `processes` setting (1: one",
    "process; N: the main process, which reads the IMEI handshakes and serves the API, and N",
    "worker processes, each with its Teltonika devices and its own SQLite transactions). *version*:",
    "this one, or the reference source tree (`--reference-src`) run right after it, under the same load.",
    "",
    "| devices | version | processes | load | registration | duration | offered fixes | acked | acked/s | ACK p50 / p99 / max | "
    "visible p50 / p99 | errors | lost | unseen | CPU service / generator / socket | service CPU per fix | "
    "p99 < 1 s |",
    "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|",
]


def row(r: dict[str, Any]) -> str:
    """One markdown table row of a :func:`measure` result."""
    ok = r["vis_p99"] < 1.0 and r["ack_p99"] < 1.0 and r["acked"] >= 0.99 * r["offered"] and r["lost"] == 0
    per_fix = r["cpu_cores"] * r["duration_s"] / r["acked"] * 1e6 if r["acked"] else float("nan")
    return (
        f"| {r['devices']:,} | {r['version']} | {r.get('processes', 1)} | {r['load']:.1f} | {r['register_s']:.1f} s | {r['duration_s']:.0f} s | "
        f"{r['offered']:,} | {r['acked']:,} | {r['rate']:,.0f} | "
        f"{r['ack_p50'] * 1e3:.0f} / {r['ack_p99'] * 1e3:.0f} / {r['ack_max'] * 1e3:.0f} ms | "
        f"{r['vis_p50'] * 1e3:.0f} / {r['vis_p99'] * 1e3:.0f} ms | {r['errors']} | {r['lost']} | {r['unseen']} | "
        f"{r['cpu_cores']:.2f} / {r['gen_cores']:.2f} / {r['ws_cores']:.2f} cores | {per_fix:.0f} us | "
        f"{'yes' if ok else 'no'} |"
    )


def main() -> None:
    """Parse the options, run each device count, print (and optionally write) the table."""
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--devices", type=int, nargs="+", default=[100, 1000], help="device counts to run")
    ap.add_argument("--duration", type=float, default=30.0, help="seconds of load per run")
    ap.add_argument("--engine", default="fixes", help="engine of the service (fixes; none: store only)")
    ap.add_argument("--protocol", choices=["teltonika"], default="teltonika", help="device protocol")
    ap.add_argument("--no-db-thread", action="store_true", help="skip the database-thread timing")
    ap.add_argument(
        "--reference-src",
        help="also run each device count, right after this version, on the service of this iotnav "
        "source tree (e.g. an earlier commit: git archive COMMIT src | tar -x -C DIR, then DIR/src)",
    )
    ap.add_argument("--reference-label", default="reference", help="name of the reference in the table")
    ap.add_argument(
        "--processes",
        type=int,
        nargs="+",
        default=[1],
        help="the service's processes setting; several: each device count runs once with each, back to back",
    )
    args = ap.parse_args()
    if max(args.devices) > 20000 or args.duration > 300:
        ap.error("bounded: at most 20,000 devices and 300 s")
    load0 = os.getloadavg()[0]
    ms = {
        (e, b): db_thread_ms(e, b, n_msg=500 if b == 1 else 3000)
        for e in dict.fromkeys([args.engine, "none"])
        for b in (1, 500)
        if not args.no_db_thread
    }
    rows = []
    for n in args.devices:
        for p in args.processes:  # each setting: this version, then the reference right after it
            r = measure(n, args.duration, args.engine, processes=p)
            print(json.dumps(r), flush=True)
            rows.append(row(r))
            if args.reference_src:
                r = measure(n, args.duration, args.engine, args.reference_src, args.reference_label, p)
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
