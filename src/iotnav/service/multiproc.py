"""Several processes for the Teltonika devices of one ``iotnav serve`` (``processes`` > 1).

One Python process uses at most one core (the interpreter lock); ``iotnav serve --processes
N`` runs the Teltonika devices in N worker processes:

- The **main process** (:class:`WorkerPool`) listens on the Teltonika port, reads each new
  connection's IMEI handshake (:func:`iotnav.service.protocols.teltonika.decode_imei`; a
  malformed one is rejected, counted and answered ``00`` here), and hands the connected socket
  with the bytes it has read to a worker over a Unix ``SOCK_SEQPACKET`` socket
  (``socket.send_fds``, ``SCM_RIGHTS``), then closes its own copy. The worker is
  :func:`worker_of` the IMEI among the live workers (a rendezvous hash of ``crc32``: stable
  for a device while the set of live workers does not change, and when a worker dies only its
  devices move). The OsmAnd / OwnTracks HTTP, MQTT, NMEA listeners and the API stay in the
  main process, with its own :class:`~iotnav.service.ingest.Ingestor`.
- Each **worker process** (:func:`worker_main`) runs the unchanged Teltonika protocol
  (:mod:`iotnav.service.teltonika_tcp`: the handshake's answer, framing, limits, the ACK sent
  only after the commit) and an :class:`~iotnav.service.ingest.Ingestor` of its own (group
  commit on its database thread, de-duplication, checkpoints, replay) on the same database.
  The positions it commits are sent to the main process (pickled, over a second Unix socket)
  and handed to the main ingestor's listeners, so ``/api/socket`` shows them.
- **Database**: every process writes its own transactions (SQLite in WAL mode: one writer at a
  time, each transaction ``BEGIN IMMEDIATE`` waiting up to the 10 s ``busy_timeout``,
  :func:`iotnav.service.store.make_engine`; PostgreSQL: concurrent transactions). An ACK still
  follows the commit of its message in the worker that stored it.
- **A worker that dies** (crash, kill -9): its sockets close with it, so its devices'
  connections drop; they reconnect and are handed to a live worker. The main process starts
  a new worker in its place after :data:`RESTART_DELAY_S` (its devices move back to it once it
  is ready). A device handed to another worker than the one it had last (:attr:`WorkerPool.last`)
  is marked ``moved``: the receiving worker drops what it holds of that device in memory
  before the connection is served, so the state is rebuilt from the checkpoint and the fixes
  stored after it (the service's replay), never from a stale copy of its own.
- **Shutdown** (SIGTERM / SIGINT of the main process): the main process stops accepting and
  sends SIGTERM to every worker; each closes its connections and writes its devices'
  checkpoints (:meth:`~iotnav.service.ingest.Ingestor.close`). A worker whose main process
  has gone (its control socket at end of file) stops the same way.

Limits: the per-address connection limit is counted per worker; a device id used by a
Teltonika device and by an HTTP device at the same time has two engine states (one per
process); alerts are not supported with ``processes`` > 1.
"""

from __future__ import annotations

import asyncio
import contextlib
import gc
import json
import logging
import multiprocessing as mp
import os
import pickle
import shutil
import signal
import socket
import tempfile
import threading
import zlib
from collections import deque
from collections.abc import Sequence
from typing import TYPE_CHECKING, Any

from iotnav.service.protocols.common import Decoded, Incomplete, Rejected
from iotnav.service.protocols.teltonika import decode_imei
from iotnav.service.teltonika_tcp import TeltonikaServer, _Connection

if TYPE_CHECKING:
    from iotnav.service.app import ServiceConfig
    from iotnav.service.ingest import Ingestor

log = logging.getLogger("iotnav.service.multiproc")

#: A worker that died is started again after this long, s.
RESTART_DELAY_S = 1.0
#: Time allowed for the workers to start (imports, the engine's compiled kernels), s.
START_TIMEOUT_S = 120.0
#: Time allowed for a worker to stop after SIGTERM (it checkpoints its devices: about 1 ms
#: each for ``fixes``), s; then it is killed.
STOP_TIMEOUT_S = 120.0
#: Positions per message of a worker to the main process (a ``SOCK_SEQPACKET`` message must fit
#: in the socket's send buffer, about 200 kB on Linux).
ROWS_PER_MESSAGE = 100
#: Largest message received on the Unix sockets, bytes.
MAX_MESSAGE_BYTES = 1 << 22


def worker_of(imei: str, live: Sequence[int]) -> int | None:
    """The worker of the device ``imei`` among the ``live`` worker indices; None if none is live.

    Rendezvous (highest random weight) hashing on ``crc32(imei/worker)``: the same worker for
    the same IMEI and live set, in any process and across restarts; removing a worker moves
    only the devices it had.
    """
    if not live:
        return None
    key = imei.encode()
    return max(live, key=lambda w: (zlib.crc32(key + b"/%d" % w), w))


def forget(ingestor: Ingestor, unique_id: str) -> None:
    """Drop what ``ingestor`` holds in memory of the device ``unique_id`` (on its database thread).

    Its next message rebuilds the state from the checkpoint and the stored fixes after it
    (:mod:`iotnav.service.ingest`), as after a restart.
    """
    entry = ingestor._device_rows.pop(unique_id, None)
    if entry is not None and entry[0] is not None:
        dev = entry[0]
        ingestor._devices.pop(dev, None)
        ingestor._recent.pop(dev, None)
        ingestor._dirty.pop(dev, None)


# --- worker process --------------------------------------------------------------------------


class _Handed(_Connection):
    """A connection accepted by the main process: starts with the bytes the main process read."""

    def __init__(self, server: TeltonikaServer, prefix: bytes) -> None:
        super().__init__(server)
        self.prefix = prefix

    def connection_made(self, transport: asyncio.BaseTransport) -> None:
        super().connection_made(transport)
        if not self.closed and self.prefix:  # before the transport reads anything of its own
            self.data_received(self.prefix)


def _unix(path: str, hello: dict[str, Any]) -> socket.socket:
    sock = socket.socket(socket.AF_UNIX, socket.SOCK_SEQPACKET)
    sock.connect(path)
    sock.send(json.dumps(hello).encode())
    return sock


def worker_main(config: ServiceConfig, index: int, path: str) -> None:
    """Body of worker process ``index``: serve the connections the main process at ``path`` hands over."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # a terminal's Ctrl-C: the main process stops us
    logging.basicConfig(
        level=logging.WARNING, format=f"%(asctime)s worker{index} %(name)s %(levelname)s %(message)s"
    )
    asyncio.run(_worker(config, index, path))


async def _worker(config: ServiceConfig, index: int, path: str) -> None:
    from iotnav.service import store
    from iotnav.service.app import make_ingestor

    gc.set_threshold(50_000, 20, 20)  # as the single process (iotnav.service.app.serve)
    db = store.make_engine(config.db_url, immediate=True)
    ingestor = make_ingestor(config, db)
    gc.freeze()  # as the single process (iotnav.service.app.serve)
    rows = _unix(path, {"kind": "rows", "index": index})
    rows_lock = threading.Lock()

    def forward(protocol: str, committed: list[dict[str, Any]]) -> None:
        """Ingestor listener (database thread): the committed positions to the main process."""
        for i in range(0, len(committed), ROWS_PER_MESSAGE):
            data = pickle.dumps((protocol, committed[i : i + ROWS_PER_MESSAGE]), pickle.HIGHEST_PROTOCOL)
            try:
                with rows_lock:
                    rows.send(data)
            except OSError:  # the main process has gone: the live view only (the rows are stored)
                return

    ingestor.listeners.append(forward)
    tcp = TeltonikaServer(ingestor, ingestor.executor, config.limits)
    loop = asyncio.get_running_loop()
    stop = asyncio.Event()
    loop.add_signal_handler(signal.SIGTERM, stop.set)
    ctl = _unix(path, {"kind": "ctl", "index": index, "pid": os.getpid()})
    ctl.setblocking(False)
    adopting: set[asyncio.Task[None]] = set()

    async def adopt(sock: socket.socket, head: dict[str, Any]) -> None:
        try:
            if head.get("moved"):
                await loop.run_in_executor(ingestor.executor, forget, ingestor, head["imei"])
            await loop.connect_accepted_socket(lambda: _Handed(tcp, bytes.fromhex(head["data"])), sock)
        except Exception:
            log.exception("worker %d: a handed connection could not be served", index)
            sock.close()

    def on_ctl() -> None:
        while True:
            try:
                msg, fds, _, _ = socket.recv_fds(ctl, MAX_MESSAGE_BYTES, 1)
            except BlockingIOError:
                return
            except OSError:
                stop.set()
                return
            if not msg:  # the main process has gone
                for fd in fds:
                    os.close(fd)
                stop.set()
                return
            if not fds:
                continue
            sock = socket.socket(fileno=fds[0])
            sock.setblocking(False)
            task = loop.create_task(adopt(sock, json.loads(msg)))
            adopting.add(task)
            task.add_done_callback(adopting.discard)

    loop.add_reader(ctl.fileno(), on_ctl)
    ctl.send(b'{"ready": true}')
    try:
        await stop.wait()
    finally:
        loop.remove_reader(ctl.fileno())
        ctl.close()
        for conn in list(tcp.connections):
            conn._close()
        ingestor.close()  # the database thread's queue, then every device's checkpoint
        with rows_lock:
            rows.close()
        db.dispose()


# --- main process ----------------------------------------------------------------------------


class _Handshake(asyncio.Protocol):
    """A new Teltonika connection in the main process, until its IMEI handshake is complete."""

    def __init__(self, pool: WorkerPool) -> None:
        self.pool = pool
        self.buf = bytearray()
        self.transport: asyncio.Transport | None = None
        self.timer: asyncio.TimerHandle | None = None

    def connection_made(self, transport: asyncio.BaseTransport) -> None:
        assert isinstance(transport, asyncio.Transport)
        self.transport = transport
        self.timer = asyncio.get_running_loop().call_later(
            self.pool.config.packet_timeout_s, self._give_up, "handshake timeout"
        )

    def _give_up(self, why: str) -> None:
        log.info("teltonika %s: closed (%s)", self._peer(), why)
        if self.transport is not None:
            self.transport.close()

    def _peer(self) -> str:
        peer = self.transport.get_extra_info("peername") if self.transport is not None else None
        return f"{peer[0]}:{peer[1]}" if peer else "?"

    def data_received(self, data: bytes) -> None:
        assert self.transport is not None
        self.buf += data
        result = decode_imei(bytes(self.buf))
        if isinstance(result, Incomplete):
            return
        if self.timer is not None:
            self.timer.cancel()
        if isinstance(result, Rejected):
            self.pool.ingestor.count(f"teltonika_rejected_{result.reason}")
            log.warning("teltonika %s: rejected (%s): %s", self._peer(), result.reason, result.detail)
            if result.answer:
                self.transport.write(result.answer)
            self.transport.close()
            return
        assert isinstance(result, Decoded) and result.device is not None
        self.transport.pause_reading()
        self.pool.hand(result.device, bytes(self.buf), self.transport)

    def connection_lost(self, exc: Exception | None) -> None:
        if self.timer is not None:
            self.timer.cancel()


class WorkerPool:
    """The worker processes of ``iotnav serve --processes N`` and the hand-off (module docstring).

    Parameters
    ----------
    config : ServiceConfig
        The service's settings (``processes`` workers).
    ingestor : Ingestor
        The main process's ingestor: its counters (rejections, hand-off failures) and its
        listeners (the API's WebSocket), which receive the workers' committed positions.
    """

    def __init__(self, config: ServiceConfig, ingestor: Ingestor) -> None:
        self.config = config
        self.ingestor = ingestor
        self.dir = tempfile.mkdtemp(prefix="iotnav-")
        self.path = os.path.join(self.dir, "workers.sock")
        self.procs: dict[int, Any] = {}
        #: Control sockets of the live (ready) workers.
        self.ctl: dict[int, socket.socket] = {}
        self._pending: dict[int, deque[tuple[bytes, int]]] = {}
        self._writing: set[int] = set()
        #: IMEI -> the worker it was last handed to.
        self.last: dict[str, int] = {}
        self._ctx = mp.get_context("spawn")
        self._listener: socket.socket | None = None
        self._supervisor: asyncio.Task[None] | None = None
        self._stopping = False
        self._threads: list[threading.Thread] = []

    @property
    def live(self) -> list[int]:
        """Indices of the workers ready to take connections."""
        return sorted(self.ctl)

    async def start(self) -> None:
        """Start the workers and wait until every one is ready (RuntimeError if one exits)."""
        loop = asyncio.get_running_loop()
        lst = socket.socket(socket.AF_UNIX, socket.SOCK_SEQPACKET)
        lst.bind(self.path)
        lst.listen(64)
        lst.setblocking(False)
        self._listener = lst
        loop.add_reader(lst.fileno(), self._accept)
        for i in range(self.config.processes):
            self._spawn(i)
        t_end = loop.time() + START_TIMEOUT_S
        while len(self.ctl) < self.config.processes:
            dead = [i for i, p in self.procs.items() if not p.is_alive()]
            if dead:
                raise RuntimeError(f"worker {dead[0]} exited with {self.procs[dead[0]].exitcode} at start")
            if loop.time() > t_end:
                raise RuntimeError(f"workers not ready after {START_TIMEOUT_S} s")
            await asyncio.sleep(0.05)
        self._supervisor = loop.create_task(self._supervise())

    async def listen(self, host: str, port: int) -> asyncio.Server:
        """Accept Teltonika connections on ``host:port`` (the handshake here, the rest in a worker)."""
        loop = asyncio.get_running_loop()
        return await loop.create_server(lambda: _Handshake(self), host, port, backlog=4096)

    def _spawn(self, i: int) -> None:
        p = self._ctx.Process(
            target=worker_main, args=(self.config, i, self.path), name=f"iotnav-worker-{i}", daemon=False
        )
        p.start()
        self.procs[i] = p

    # --- the workers' sockets ----------------------------------------------------------------

    def _accept(self) -> None:
        assert self._listener is not None
        loop = asyncio.get_running_loop()
        while True:
            try:
                conn, _ = self._listener.accept()
            except (BlockingIOError, InterruptedError):
                return
            conn.setblocking(False)
            loop.add_reader(conn.fileno(), self._hello, conn)

    def _hello(self, conn: socket.socket) -> None:
        loop = asyncio.get_running_loop()
        msg = _recv_ready(conn)
        if msg is None:
            return
        loop.remove_reader(conn.fileno())
        if not msg:
            conn.close()
            return
        hello = json.loads(msg)
        i = int(hello["index"])
        if hello["kind"] == "rows":
            conn.setblocking(True)
            t = threading.Thread(target=self._rows, args=(conn,), name=f"iotnav-rows-{i}", daemon=True)
            t.start()
            self._threads.append(t)
        else:
            loop.add_reader(conn.fileno(), self._control, i, conn)

    def _control(self, i: int, conn: socket.socket) -> None:
        msg = _recv_ready(conn)
        if msg is None:
            return
        if not msg:
            self._lost(i, conn)
        elif json.loads(msg).get("ready"):
            self.ctl[i] = conn
            self._pending[i] = deque()
            log.warning("worker %d ready (pid %s)", i, self.procs[i].pid if i in self.procs else "?")

    def _rows(self, conn: socket.socket) -> None:
        """Thread: a worker's committed positions to the main ingestor's listeners."""
        while True:
            try:
                msg = conn.recv(MAX_MESSAGE_BYTES)
            except OSError:
                break
            if not msg:
                break
            protocol, rows = pickle.loads(msg)
            self.ingestor._notify(protocol, rows)
        conn.close()

    def _lost(self, i: int, conn: socket.socket) -> None:
        """Worker ``i``'s control socket closed: no more hand-offs to it."""
        loop = asyncio.get_running_loop()
        loop.remove_reader(conn.fileno())
        if i in self._writing:
            self._writing.discard(i)
            loop.remove_writer(conn.fileno())
        if self.ctl.get(i) is conn:
            del self.ctl[i]
            for _, fd in self._pending.pop(i, deque()):
                os.close(fd)  # not handed: that device's connection drops, it reconnects
        conn.close()
        if not self._stopping:
            log.error("worker %d: control socket closed", i)

    # --- hand-off ------------------------------------------------------------------------------

    def hand(self, imei: str, data: bytes, transport: asyncio.Transport) -> None:
        """Hand the connection of ``transport`` (its IMEI read, ``data`` the bytes read) to its worker."""
        w = worker_of(imei, self.live)
        if w is None:
            self.ingestor.count("teltonika_no_worker")
            log.warning("teltonika IMEI %s: no live worker; closed", imei)
            transport.abort()
            return
        moved = self.last.get(imei, w) != w
        self.last[imei] = w
        head = json.dumps({"imei": imei, "data": data.hex(), "moved": moved}).encode()
        fd = os.dup(transport.get_extra_info("socket").fileno())
        transport.abort()  # the main process's copy; the duplicate keeps the connection open
        self._pending[w].append((head, fd))
        self._drain(w)

    def _drain(self, w: int) -> None:
        conn = self.ctl.get(w)
        if conn is None:
            return
        queue = self._pending[w]
        while queue:
            head, fd = queue[0]
            try:
                socket.send_fds(conn, [head], [fd])
            except BlockingIOError:  # the worker is behind: send the rest when it has read
                if w not in self._writing:
                    self._writing.add(w)
                    asyncio.get_running_loop().add_writer(conn.fileno(), self._drain, w)
                return
            except OSError:
                self._lost(w, conn)
                return
            queue.popleft()
            os.close(fd)
        if w in self._writing:
            self._writing.discard(w)
            asyncio.get_running_loop().remove_writer(conn.fileno())

    # --- supervision and shutdown ----------------------------------------------------------------

    async def _supervise(self) -> None:
        """Restart a worker that died (after :data:`RESTART_DELAY_S`)."""
        died: dict[int, float] = {}
        loop = asyncio.get_running_loop()
        while not self._stopping:
            await asyncio.sleep(0.2)
            for i, p in list(self.procs.items()):
                if p.is_alive() or self._stopping:
                    continue
                if i not in died:
                    log.error("worker %d (pid %s) exited with %s; restarting it", i, p.pid, p.exitcode)
                    self.ingestor.count("worker_exited")
                    died[i] = loop.time()
                    conn = self.ctl.get(i)
                    if conn is not None:
                        self._lost(i, conn)
                elif loop.time() - died[i] >= RESTART_DELAY_S:
                    del died[i]
                    p.close()
                    self._spawn(i)

    async def stop(self) -> None:
        """SIGTERM to every worker, wait for them (kill after :data:`STOP_TIMEOUT_S`), clean up."""
        self._stopping = True
        if self._supervisor is not None:
            self._supervisor.cancel()
            await asyncio.gather(self._supervisor, return_exceptions=True)
        loop = asyncio.get_running_loop()
        if self._listener is not None:
            loop.remove_reader(self._listener.fileno())
            self._listener.close()
        procs = list(self.procs.values())
        for p in procs:
            if p.is_alive():
                p.terminate()

        def join() -> None:
            for p in procs:
                p.join(STOP_TIMEOUT_S)
                if p.is_alive():
                    log.error("worker %s did not stop; killed", p.name)
                    p.kill()
                    p.join(10)

        await asyncio.to_thread(join)
        for i, conn in list(self.ctl.items()):
            self._lost(i, conn)
        for t in self._threads:
            t.join(5)
        with contextlib.suppress(OSError):
            shutil.rmtree(self.dir)


def _recv_ready(conn: socket.socket) -> bytes | None:
    """One control message from a non-blocking worker socket: None when nothing is there yet,
    ``b""`` when the peer closed or the socket failed (the caller treats both as gone)."""
    try:
        return conn.recv(4096)
    except BlockingIOError:
        return None
    except OSError:
        return b""
