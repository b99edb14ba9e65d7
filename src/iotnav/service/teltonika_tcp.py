"""Teltonika TCP listener (asyncio): handshake, framing, ACK after commit, limits.

Per connection: the IMEI handshake (answer ``01`` for a known device, or any device while
registration is open, ``00`` otherwise, then close); then AVL packets, each decoded by
:func:`iotnav.service.protocols.teltonika.decode_avl`, stored by
:meth:`iotnav.service.ingest.Ingestor.submit` (group commit on the single database thread),
and only then acknowledged with the 4-byte record count. A packet stored before (the device resent it
because our ACK was lost) is acknowledged again without being stored twice. A rejected
packet (bad CRC, bad framing) or a storage error closes the connection without an ACK, so
the device resends it later; every rejection is logged and counted by reason.

Limits (:class:`TcpLimits`): packet size, idle time between packets, time to complete a
packet once started (a slow-drip "slowloris" sender is cut off), connections per remote
address.
"""

from __future__ import annotations

import asyncio
import logging
from collections import Counter
from concurrent.futures import Executor
from dataclasses import dataclass

from iotnav.service.ingest import Ingestor
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


class TeltonikaServer:
    """Serves Teltonika devices; ``executor`` must be the single database thread."""

    def __init__(self, ingestor: Ingestor, executor: Executor, limits: TcpLimits | None = None) -> None:
        self.ingestor = ingestor
        self.executor = executor
        self.limits = limits or TcpLimits()
        self.per_address: Counter[str] = Counter()
        self.server: asyncio.Server | None = None

    async def start(self, host: str, port: int) -> asyncio.Server:
        """Listen on ``host:port``."""
        self.server = await asyncio.start_server(self.handle, host, port, limit=self.limits.max_packet_bytes)
        return self.server

    def _reject(self, peer: str, reason: str, detail: str) -> None:
        self.ingestor.count(f"teltonika_rejected_{reason}")
        log.warning("teltonika %s: rejected (%s): %s", peer, reason, detail)

    async def _read(self, reader: asyncio.StreamReader, n: int, started: bool, deadline: float) -> bytes:
        """Up to ``n`` bytes (at least one); idle timeout before a packet, packet deadline inside one."""
        loop = asyncio.get_running_loop()
        timeout = max(0.0, deadline - loop.time()) if started else self.limits.idle_timeout_s
        data = await asyncio.wait_for(reader.read(max(n, 1)), timeout)
        if not data:
            raise ConnectionResetError("peer closed")
        return data

    async def handle(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        """One device connection."""
        peername = writer.get_extra_info("peername")
        addr = str(peername[0]) if peername else "?"
        peer = f"{addr}:{peername[1]}" if peername else "?"
        if self.per_address[addr] >= self.limits.max_connections_per_address:
            self._reject(peer, "too_many_connections", f"{self.per_address[addr]} open from {addr}")
            writer.close()
            return
        self.per_address[addr] += 1
        try:
            await self._session(reader, writer, peer)
        except (TimeoutError, ConnectionError, asyncio.IncompleteReadError) as exc:
            log.info("teltonika %s: closed (%s)", peer, type(exc).__name__)
        except Exception:  # a bug or a storage failure: no ACK, the device will resend
            self.ingestor.count("teltonika_errors")
            log.exception("teltonika %s: error; closing without ACK", peer)
        finally:
            self.per_address[addr] -= 1
            if self.per_address[addr] <= 0:
                del self.per_address[addr]
            writer.close()
            try:
                await writer.wait_closed()
            except (ConnectionError, OSError):
                pass

    async def _session(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter, peer: str) -> None:
        loop = asyncio.get_running_loop()
        buf = bytearray()
        imei: str | None = None
        deadline = 0.0
        while True:
            result = (
                decode_imei(bytes(buf))
                if imei is None
                else decode_avl(bytes(buf), imei, self.limits.max_packet_bytes)
            )
            if isinstance(result, Incomplete):
                if buf:
                    buf += await self._read(reader, result.need, True, deadline)
                else:  # between packets: idle timeout; the packet's deadline runs from its first byte
                    buf += await self._read(reader, result.need, False, 0.0)
                    deadline = loop.time() + self.limits.packet_timeout_s
                continue
            if isinstance(result, Rejected):
                self._reject(peer, result.reason, result.detail)
                if result.answer:
                    writer.write(result.answer)
                    await writer.drain()
                return
            assert isinstance(result, Decoded)
            packet = bytes(buf[: result.consumed])
            del buf[: result.consumed]
            deadline = loop.time() + self.limits.packet_timeout_s  # for bytes of the next packet
            if imei is None:
                assert result.device is not None
                allowed = await loop.run_in_executor(
                    self.executor, self.ingestor.device_allowed, result.device
                )
                writer.write(imei_answer(allowed))
                await writer.drain()
                if not allowed:
                    self._reject(peer, "unknown_device", f"IMEI {result.device} (registration closed)")
                    return
                imei = result.device
                log.info("teltonika %s: IMEI %s", peer, imei)
                continue
            res = await self.ingestor.submit("teltonika", imei, packet, result.records, peer)
            if not res.accepted:
                self._reject(peer, "unknown_device", f"IMEI {imei} no longer accepted")
                return
            writer.write(result.answer)  # only now: the records are committed
            await writer.drain()
