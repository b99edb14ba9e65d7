"""Teltonika TCP listener (asyncio): handshake, framing, ACK after commit, limits.

Per connection: the IMEI handshake (answer ``01`` for a known device, or any device while
registration is open, ``00`` otherwise, then close); then AVL packets, each decoded by
:func:`iotnav.service.protocols.teltonika.decode_avl`, stored by
:meth:`iotnav.service.ingest.Ingestor.enqueue` (group commit on the single database thread),
and only then acknowledged with the 4-byte record count. A packet stored before (the device resent it
because our ACK was lost) is acknowledged again without being stored twice. A rejected
packet (bad CRC, bad framing) or a storage error closes the connection without an ACK, so
the device resends it later; every rejection is logged and counted by reason.

Each connection is a low-level :class:`asyncio.Protocol` (no stream reader, no task and no
timer per packet): at 10,000 devices the per-packet cost of the stream API (a task per
``wait_for``, the reader's buffer copies) was a large part of the service's CPU. One packet
of a connection is in storage at a time (a device waits for the ACK of a packet before the
next); bytes that arrive meanwhile wait in the connection's buffer, and reading pauses when
that buffer exceeds the packet limit.

Limits (:class:`TcpLimits`): packet size, idle time between packets, time to complete a
packet once started (a slow-drip "slowloris" sender is cut off), connections per remote
address. The two timeouts are enforced by one sweep over the connections (a few times per
timeout), not by a timer per packet; no timeout runs while a packet is being stored.
"""

from __future__ import annotations

import asyncio
import logging
import math
from collections import Counter
from concurrent.futures import Executor
from dataclasses import dataclass

from iotnav.service.ingest import Ingestor, IngestResult
from iotnav.service.protocols.common import Decoded, Incomplete, Rejected
from iotnav.service.protocols.teltonika import decode_avl, decode_imei, imei_answer

log = logging.getLogger("iotnav.service.teltonika")


@dataclass(frozen=True)
class TcpLimits:
    """Limits of the TCP listener.

    Attributes
    ----------
    max_packet_bytes : int
        Largest AVL packet accepted, bytes.
    idle_timeout_s : float
        Connection closed after this long without a byte, s (devices reconnect on their own).
    packet_timeout_s : float
        Time allowed to receive a whole packet (or the handshake) once it has started, s.
    max_connections_per_address : int
        Simultaneous connections accepted from one remote IP address.
    """

    max_packet_bytes: int = 65536
    idle_timeout_s: float = 600.0
    packet_timeout_s: float = 60.0
    max_connections_per_address: int = 32


class _Connection(asyncio.Protocol):
    """One device connection (module docstring)."""

    def __init__(self, server: TeltonikaServer) -> None:
        self.server = server
        self.loop = asyncio.get_running_loop()
        self.transport: asyncio.Transport | None = None
        self.buf = bytearray()
        self.imei: str | None = None
        self.busy = False  # a handshake or a packet is being decided / stored: no reading of more
        self.closed = False
        self.paused = False
        self.deadline = math.inf  # loop time after which the connection is closed (not while busy)
        self.addr = "?"
        self.peer = "?"
        self.counted = False

    # --- asyncio callbacks ---------------------------------------------------------------

    def connection_made(self, transport: asyncio.BaseTransport) -> None:
        assert isinstance(transport, asyncio.Transport)
        self.transport = transport
        srv = self.server
        peername = transport.get_extra_info("peername")
        if peername:
            self.addr, self.peer = str(peername[0]), f"{peername[0]}:{peername[1]}"
        if srv.per_address[self.addr] >= srv.limits.max_connections_per_address:
            srv._reject(
                self.peer, "too_many_connections", f"{srv.per_address[self.addr]} open from {self.addr}"
            )
            self._close()
            return
        srv.per_address[self.addr] += 1
        self.counted = True
        srv.connections.add(self)
        srv._ensure_sweeper()
        self.deadline = self.loop.time() + srv.limits.idle_timeout_s

    def data_received(self, data: bytes) -> None:
        if self.closed:
            return
        if not self.buf and not self.busy:  # the first byte of a packet: its deadline starts
            self.deadline = self.loop.time() + self.server.limits.packet_timeout_s
        self.buf += data
        if self.busy:
            if len(self.buf) > self.server.limits.max_packet_bytes and not self.paused:
                self.paused = True
                assert self.transport is not None
                self.transport.pause_reading()
            return
        self._process()

    def connection_lost(self, exc: Exception | None) -> None:
        if not self.closed:
            log.info("teltonika %s: closed (%s)", self.peer, type(exc).__name__ if exc else "peer closed")
        self.closed = True
        self.server.connections.discard(self)
        if self.counted:
            self.counted = False
            per = self.server.per_address
            per[self.addr] -= 1
            if per[self.addr] <= 0:
                del per[self.addr]

    # --- framing -------------------------------------------------------------------------

    def _close(self) -> None:
        self.closed = True
        if self.transport is not None:
            self.transport.close()

    def timed_out(self, now: float) -> bool:
        """Close the connection when its deadline has passed (called by the sweep)."""
        if self.busy or self.closed or now < self.deadline:
            return False
        log.info("teltonika %s: closed (%s)", self.peer, "packet timeout" if self.buf else "idle")
        self._close()
        return True

    def _process(self) -> None:
        """Decode and hand on what the buffer holds, until it needs more bytes or waits on storage."""
        try:
            self._decode()
        except Exception as exc:  # a bug: counted and logged, the connection closed without an ACK
            self._failed(exc)

    def _decode(self) -> None:
        srv = self.server
        while not self.closed and not self.busy:
            buf = self.buf
            if not buf:
                self.deadline = self.loop.time() + srv.limits.idle_timeout_s
                break
            data = bytes(buf)
            result = (
                decode_imei(data)
                if self.imei is None
                else decode_avl(data, self.imei, srv.limits.max_packet_bytes)
            )
            if isinstance(result, Incomplete):
                break
            if isinstance(result, Rejected):
                srv._reject(self.peer, result.reason, result.detail)
                if result.answer and self.transport is not None:
                    self.transport.write(result.answer)
                self._close()
                return
            assert isinstance(result, Decoded)
            packet = data if result.consumed == len(data) else data[: result.consumed]
            del buf[: result.consumed]
            self.deadline = self.loop.time() + srv.limits.packet_timeout_s  # for bytes of the next packet
            self.busy = True
            if self.imei is None:
                assert result.device is not None
                device = result.device
                fut = self.loop.run_in_executor(srv.executor, srv.ingestor.device_allowed, device)
                fut.add_done_callback(lambda f, d=device: self._handshake_done(f, d))  # type: ignore[misc]
            else:
                answer = result.answer
                stored = srv.ingestor.enqueue("teltonika", self.imei, packet, result.records, self.peer)
                stored.add_done_callback(lambda f, a=answer: self._stored(f, a))  # type: ignore[misc]
        if self.paused and not self.closed and len(self.buf) <= srv.limits.max_packet_bytes:
            self.paused = False
            assert self.transport is not None
            self.transport.resume_reading()

    def _handshake_done(self, fut: asyncio.Future[bool], device: str) -> None:
        self.busy = False
        if self.closed:
            return
        assert self.transport is not None
        if fut.cancelled() or fut.exception() is not None:
            self._failed(fut.exception() if not fut.cancelled() else None)
            return
        allowed = fut.result()
        self.transport.write(imei_answer(allowed))
        if not allowed:
            self.server._reject(self.peer, "unknown_device", f"IMEI {device} (registration closed)")
            self._close()
            return
        self.imei = device
        log.info("teltonika %s: IMEI %s", self.peer, device)
        self._process()

    def _stored(self, fut: asyncio.Future[IngestResult], answer: bytes) -> None:
        self.busy = False
        if self.closed:
            return
        assert self.transport is not None
        if fut.cancelled() or fut.exception() is not None:
            self._failed(fut.exception() if not fut.cancelled() else None)
            return
        if not fut.result().accepted:
            self.server._reject(self.peer, "unknown_device", f"IMEI {self.imei} no longer accepted")
            self._close()
            return
        self.transport.write(answer)  # only now: the records are committed
        self._process()

    def _failed(self, exc: BaseException | None) -> None:
        """A storage failure (or a bug): no ACK, the connection closed, the device will resend."""
        self.server.ingestor.count("teltonika_errors")
        log.error("teltonika %s: error; closing without ACK", self.peer, exc_info=exc)
        self._close()


class TeltonikaServer:
    """Serves Teltonika devices; ``executor`` must be the single database thread."""

    def __init__(self, ingestor: Ingestor, executor: Executor, limits: TcpLimits | None = None) -> None:
        self.ingestor = ingestor
        self.executor = executor
        self.limits = limits or TcpLimits()
        self.per_address: Counter[str] = Counter()
        self.server: asyncio.Server | None = None
        self.connections: set[_Connection] = set()
        self._sweeper: asyncio.Task[None] | None = None

    async def start(self, host: str, port: int) -> asyncio.Server:
        """Listen on ``host:port``."""
        loop = asyncio.get_running_loop()
        self.server = await loop.create_server(lambda: _Connection(self), host, port, backlog=4096)
        return self.server

    def _reject(self, peer: str, reason: str, detail: str) -> None:
        self.ingestor.count(f"teltonika_rejected_{reason}")
        log.warning("teltonika %s: rejected (%s): %s", peer, reason, detail)

    def _ensure_sweeper(self) -> None:
        if self._sweeper is None or self._sweeper.done():
            self._sweeper = asyncio.get_running_loop().create_task(self._sweep())

    async def _sweep(self) -> None:
        """Close the connections whose idle or packet deadline has passed, a few times per timeout."""
        loop = asyncio.get_running_loop()
        period = min(1.0, max(0.05, min(self.limits.idle_timeout_s, self.limits.packet_timeout_s) / 5))
        while self.connections:
            await asyncio.sleep(period)
            now = loop.time()
            for conn in [c for c in self.connections if not c.busy and now >= c.deadline]:
                conn.timed_out(now)
