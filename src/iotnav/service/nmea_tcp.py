"""Raw NMEA 0183 over TCP: a receiver or tracker writes sentences, one a line, to a port.

What is on the wire is what a GNSS receiver prints on its serial port (``$GPGGA,...*hh``
lines), forwarded by a serial-to-TCP bridge, a phone app (``NMEA over TCP``) or a tracker. Port
:attr:`NmeaSettings.port` (off by default; 10110 is the IANA port of ``nmea-0183``, the one
OpenCPN and Signal K use).

Device id, in this order (what gpsd and Traccar users meet):

1. a first line that is not a sentence (does not start with ``$`` or ``!``): its text (1 to
   64 printable ASCII characters, no blank) is the id, as trackers send an IMEI login line;
2. a first sentence ``$PGID,<id>*hh`` (Traccar's T55 identification sentence);
3. otherwise the port's configured :attr:`NmeaSettings.device_id` (a receiver that only
   prints NMEA, which is all gpsd expects of a source); without one the connection is closed
   (counted ``nmea_rejected_no_device``).

Sentences are framed, checksum-checked and decoded by the project's NMEA reader
(:mod:`iotnav.io.nmea`: pynmeagps and its fast decoder, the same rules as ``iotnav run``) and
grouped into fix cycles by its :class:`~iotnav.io.nmea.NmeaEpochAssembler`. A cycle becomes one
fix once the next cycle starts (or the connection closes), and is stored by
:meth:`iotnav.service.ingest.Ingestor.ingest` (protocol ``nmea``, the cycle's lines as the raw
message) and run through the service's fixes engine. Bad sentences are counted by the reader's
reason (``nmea_rejected_bad_checksum``, ``..._malformed``, ``..._garbage``, ...); cycles without
a position (``nmea_no_fix``) or before the first date (RMC / ZDA; ``nmea_no_date``) give no fix.
NMEA has no acknowledgement: a fix is stored when its cycle is complete; the device learns
nothing of it. Limits: line length (:data:`MAX_LINE_BYTES`, a sentence is at most 82),
connections per address and idle time (:class:`~iotnav.service.teltonika_tcp.TcpLimits`).
"""

from __future__ import annotations

import asyncio
import logging
import math
from collections import Counter
from concurrent.futures import Executor
from dataclasses import dataclass
from typing import Any

from iotnav.io.nmea import NmeaEpochAssembler, _Framer
from iotnav.io.report import FileReport, SkipReason
from iotnav.service.ingest import Ingestor
from iotnav.service.protocols.common import Fix, plausible_time, record_key
from iotnav.service.teltonika_tcp import TcpLimits

log = logging.getLogger("iotnav.service.nmea")

PROTOCOL = "nmea"
MAX_LINE_BYTES = 1024
"""Longest line accepted, bytes (a standard sentence is at most 82 characters)."""


@dataclass(frozen=True)
class NmeaSettings:
    """Port of the listener (0: off) and the device id of connections that do not name one."""

    port: int = 0
    device_id: str = ""


def _login_id(line: bytes) -> str | None:
    """The device id of a first line (a bare id or ``$PGID,<id>*hh``), None if it is not one."""
    text = line.decode("ascii", "replace").strip()
    if text.startswith("$PGID,") and "*" in text:
        text = text[6 : text.index("*")]
    elif text[:1] in ("$", "!"):
        return None
    if 1 <= len(text) <= 64 and text.isascii() and text.isprintable() and " " not in text:
        return text
    return ""


class _Stream:
    """One connection's sentences into fixes: the reader's framer and epoch assembler."""

    def __init__(self, device: str) -> None:
        self.device = device
        self.report = FileReport(path=device, format="nmea")
        self.asm = NmeaEpochAssembler(self.report, source="nmea")
        self.framer = _Framer(self.report, self.asm)
        self.lines: list[bytes] = []  # of the cycles not stored yet
        self.units = 0

    def add(self, line: bytes) -> None:
        self.units += 1
        self.lines.append(line)
        head, *frags = line.split(b"$")
        if head.strip():  # text before the first sentence
            self.report.skip(SkipReason.GARBAGE, self.units, head.decode("latin-1"))
        for frag in frags:
            self.framer.sentence(b"$" + frag.strip(), math.nan, self.units)

    def take(self, rows: list[dict[str, Any]], counts: Counter[str]) -> tuple[bytes, list[Fix]]:
        """The raw bytes and fixes of the closed cycles ``rows`` (counted when unusable)."""
        payload = b"\n".join(self.lines)
        self.lines = []
        fixes = []
        for r in rows:
            t = r.get("utc", r.get("t", math.nan))
            if not r["valid"] or not math.isfinite(r["lat_deg"]):
                counts["nmea_no_fix"] += 1
            elif not (isinstance(t, float) and math.isfinite(t) and plausible_time(t)):
                counts["nmea_no_date"] += 1
            else:
                course = r["course_rad"] if r["course_valid"] else math.nan
                fixes.append(
                    Fix(
                        self.device,
                        t,
                        r["lat_deg"],
                        r["lon_deg"],
                        r["height_m"],
                        r["speed_mps"],
                        course,
                        num_sv=int(r["num_sv"]),
                        hdop=r["hdop"],
                        attributes={"quality": int(r["quality"]), "pdop": r["pdop"]},
                        key=record_key(self.device, repr((t, r["lat_deg"], r["lon_deg"])).encode()),
                    )
                )
        return payload, fixes

    def closed_rows(self) -> list[dict[str, Any]]:
        """Rows of the cycles the assembler has closed so far (taken out of it)."""
        rows, self.asm._rows, self.asm._row_units = self.asm._rows, [], []
        return rows

    def final_rows(self) -> list[dict[str, Any]]:
        """Close the last cycle (connection closed): its rows."""
        df = self.asm.finish(clock="utc")
        rows: list[dict[str, Any]] = df.to_dict("records")  # type: ignore[assignment]
        return rows


class NmeaServer:
    """Serves NMEA-over-TCP connections; ``executor`` must be the single database thread."""

    def __init__(
        self,
        ingestor: Ingestor,
        executor: Executor,
        settings: NmeaSettings | None = None,
        limits: TcpLimits | None = None,
    ) -> None:
        self.ingestor = ingestor
        self.executor = executor
        self.settings = settings or NmeaSettings()
        self.limits = limits or TcpLimits()
        self.per_address: Counter[str] = Counter()

    async def start(self, host: str, port: int) -> asyncio.Server:
        """Listen on ``host:port``."""
        return await asyncio.start_server(self.handle, host, port, limit=MAX_LINE_BYTES)

    def _reject(self, peer: str, reason: str, detail: str) -> None:
        self.ingestor.count(f"nmea_rejected_{reason}")
        log.warning("nmea %s: rejected (%s): %s", peer, reason, detail)

    async def handle(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        """One connection: lines until the peer closes, the idle timeout or a rejection."""
        peername = writer.get_extra_info("peername")
        addr = str(peername[0]) if peername else "?"
        peer = f"{addr}:{peername[1]}" if peername else "?"
        if self.per_address[addr] >= self.limits.max_connections_per_address:
            self._reject(peer, "too_many_connections", f"{self.per_address[addr]} open from {addr}")
            writer.close()
            return
        self.per_address[addr] += 1
        try:
            await self._session(reader, peer)
        except (TimeoutError, ConnectionError) as exc:
            log.info("nmea %s: closed (%s)", peer, type(exc).__name__)
        except Exception:  # a bug or a storage failure: logged, counted, the connection closed
            self.ingestor.count("nmea_errors")
            log.exception("nmea %s: error; closing", peer)
        finally:
            self.per_address[addr] -= 1
            if self.per_address[addr] <= 0:
                del self.per_address[addr]
            writer.close()
            try:
                await writer.wait_closed()
            except (ConnectionError, OSError):
                pass

    async def _session(self, reader: asyncio.StreamReader, peer: str) -> None:
        stream: _Stream | None = None
        try:
            while True:
                try:
                    line = await asyncio.wait_for(reader.readuntil(b"\n"), self.limits.idle_timeout_s)
                except asyncio.IncompleteReadError as exc:  # the peer closed; a last line without \n
                    if exc.partial.strip() and stream is not None:
                        stream.add(exc.partial.strip())
                    return
                except asyncio.LimitOverrunError:
                    self._reject(peer, "line_too_long", f"a line over {MAX_LINE_BYTES} bytes")
                    return
                line = line.strip()
                if not line:
                    continue
                if stream is None:
                    dev = _login_id(line)
                    if dev == "":
                        self._reject(peer, "bad_device_id", repr(line[:80]))
                        return
                    dev = dev or self.settings.device_id
                    if not dev:
                        self._reject(peer, "no_device", "no id line and no nmea_device_id configured")
                        return
                    stream = _Stream(dev)
                    log.info("nmea %s: device %s", peer, dev)
                    if _login_id(line) is not None:
                        continue
                stream.add(line)
                if stream.report.skipped:
                    self._count_skips(stream, peer)
                rows = stream.closed_rows()
                if rows and not await self._store(stream, rows, peer):
                    return
        finally:
            if stream is not None:
                rows = stream.final_rows()
                self._count_skips(stream, peer)
                if rows:
                    await self._store(stream, rows, peer)

    def _count_skips(self, stream: _Stream, peer: str) -> None:
        """Move the reader's new skip counts (by reason) to the service's counters."""
        for reason, n in stream.report.skipped.items():
            tag = reason.split(" (")[0].replace(" ", "_").replace("-", "_").lower()
            self.ingestor.count(f"nmea_rejected_{tag}", n)
            log.warning("nmea %s: %d sentence(s) rejected (%s)", peer, n, reason)
        stream.report.skipped.clear()

    async def _store(self, stream: _Stream, rows: list[dict[str, Any]], peer: str) -> bool:
        """Store the fixes of ``rows``; False when the device is refused."""
        counts: Counter[str] = Counter()
        payload, fixes = stream.take(rows, counts)
        for what, n in counts.items():
            self.ingestor.count(what, n)
        if not fixes:
            return True
        loop = asyncio.get_running_loop()
        res = await loop.run_in_executor(
            self.executor, self.ingestor.ingest, PROTOCOL, stream.device, payload, fixes, peer
        )
        if not res.accepted:
            self._reject(peer, "unknown_device", f"device {stream.device} not accepted")
            return False
        return True
