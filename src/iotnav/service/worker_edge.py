"""The edge of a NATS cluster: ``iotnav serve`` publishing to JetStream instead of storing.

:class:`EdgeIngestor`, moved out of :mod:`iotnav.service.workers` unchanged; the design (edges,
partitions, workers) is in that module's docstring.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import logging
import os
import socket
import time
from collections.abc import Callable, Sequence
from concurrent.futures import Future as ConcurrentFuture
from typing import Any

from iotnav.service.ingest import Ingestor, IngestResult, Message
from iotnav.service.protocols.common import Fix
from iotnav.service.worker_alerts import partition_of
from iotnav.service.workers import ClusterSettings, encode_message, ensure_stream

log = logging.getLogger("iotnav.service.workers")

__all__ = ["EdgeIngestor"]


class EdgeIngestor(Ingestor):
    """The ingest of an edge: messages are published to JetStream instead of stored here.

    Same interface as :class:`~iotnav.service.ingest.Ingestor` for the listeners
    (``submit``, ``enqueue``, ``ingest``, ``device_allowed``, ``count``); the database is used
    for device admission only (registration closed, disabled devices, cached
    ``device_cache_s``) and by the API. The result's ``n_new`` is the number of fixes sent
    (the worker de-duplicates them); ``duplicate`` is JetStream's de-duplication verdict.
    Call :meth:`connect` on the event loop before the listeners start.
    """

    def __init__(self, *args: Any, cluster: ClusterSettings, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        self.cluster = cluster
        self._nc: Any = None
        self._js: Any = None
        self._loop: asyncio.AbstractEventLoop | None = None
        self._allowed: dict[str, tuple[bool, float]] = {}
        #: Sends to the API's ``/api/socket`` (set by ``iotnav serve``): the workers' alerts.
        self.socket_send: Callable[[dict[str, Any]], None] | None = None

    def warm_up(self) -> float:
        """Nothing to warm: the edge runs no engine."""
        return 0.0

    async def connect(self) -> None:
        """Connect to NATS and make sure the stream exists."""
        import nats

        self._loop = asyncio.get_running_loop()
        self._nc = await nats.connect(
            self.cluster.url.split(","), name=f"iotnav-edge-{socket.gethostname()}-{os.getpid()}"
        )
        self._js = self._nc.jetstream()
        await ensure_stream(self._js, self.cluster)
        await self._nc.subscribe(self.cluster.live_subject, cb=self._on_live)

    async def _on_live(self, msg: Any) -> None:
        """Positions a worker has committed: to this edge's listeners (the API's socket)."""
        try:
            doc = json.loads(msg.data)
            if "events" in doc:  # a worker's alert
                if self.socket_send is not None:
                    self.socket_send({"events": list(doc["events"])})
                return
            protocol, rows = str(doc["protocol"]), list(doc["rows"])
        except (ValueError, KeyError, TypeError):
            self.count("live_bad_message")
            return
        for listener in list(self.listeners):
            try:
                listener(protocol, rows)
            except Exception:  # a listener (a WebSocket client) must not stop the others
                log.exception("position listener failed")

    async def disconnect(self) -> None:
        """Flush and close the NATS connection."""
        if self._nc is not None:
            with contextlib.suppress(Exception):
                await self._nc.flush()
            with contextlib.suppress(Exception):
                await self._nc.close()
            self._nc = None

    def _allowed_cached(self, device: str) -> bool | None:
        hit = self._allowed.get(device)
        if hit is not None and time.monotonic() - hit[1] < self.device_cache_s:
            return hit[0]
        return None

    def device_allowed(self, unique_id: str) -> bool:
        """True when ``unique_id`` is a known, enabled device or registration is open (cached)."""
        hit = self._allowed_cached(unique_id)
        if hit is None:
            hit = super().device_allowed(unique_id)
            if len(self._allowed) > 100_000:
                self._allowed.clear()
            self._allowed[unique_id] = (hit, time.monotonic())
        return hit

    async def _send(self, m: Message) -> IngestResult:
        """Publish ``m`` to its partition's subject; its result once JetStream has stored it."""
        if self._js is None:
            raise RuntimeError("EdgeIngestor.connect() has not been called")
        subject = self.cluster.subject_of(partition_of(m.device, self.cluster.partitions))
        body = encode_message(m)
        limit = self._nc.max_payload - 128  # (its Nats-Msg-Id header: about 90 bytes)
        if len(body) > limit:  # JetStream can never take it: refused and counted, not retried forever
            self.count("published_too_large")
            log.error("%s %s: %d bytes > max_payload: refused", m.protocol, m.device, len(body))
            return IngestResult(accepted=False, reason="too_large")
        ack = await self._js.publish(subject, body, headers={"Nats-Msg-Id": m.digest()})
        self.count("published_duplicate" if ack.duplicate else "published")
        return IngestResult(accepted=True, duplicate=bool(ack.duplicate), n_new=len(m.fixes))

    async def _publish(self, m: Message) -> IngestResult:
        allowed = self._allowed_cached(m.device)
        if allowed is None:
            allowed = await asyncio.get_running_loop().run_in_executor(
                self.executor, self.device_allowed, m.device
            )
        if not allowed:
            self.count("device_refused")
            return IngestResult(accepted=False)
        return await self._send(m)

    def enqueue(
        self,
        protocol: str,
        device: str,
        payload: bytes,
        fixes: Sequence[Fix],
        remote: str | None = None,
        unique: bool = False,
    ) -> asyncio.Future[IngestResult]:
        """Publish the message; the future resolves after JetStream's acknowledgement.

        Futures resolve in the order of the calls (publishes are sent in that order on one
        connection and JetStream answers them in order).
        """
        m = Message(protocol, device, payload, list(fixes), remote, time.time(), unique)
        return asyncio.ensure_future(self._publish(m))

    def ingest(
        self,
        protocol: str,
        device: str,
        payload: bytes,
        fixes: list[Fix],
        remote: str | None = None,
        received_at: float | None = None,
        unique: bool = False,
    ) -> IngestResult:
        """Publish from another thread (the NMEA listener calls this on the database thread)."""
        if self._loop is None:
            raise RuntimeError("EdgeIngestor.connect() has not been called")
        if not self.device_allowed(device):  # on this thread (the database thread)
            self.count("device_refused")
            return IngestResult(accepted=False)
        now = time.time() if received_at is None else received_at
        m = Message(protocol, device, payload, list(fixes), remote, now, unique)
        fut: ConcurrentFuture[IngestResult] = asyncio.run_coroutine_threadsafe(self._send(m), self._loop)
        return fut.result(timeout=60.0)

    def ingest_batch(self, msgs: Sequence[Message]) -> list[IngestResult | Exception]:
        """Not used on an edge (its messages go to JetStream): raises RuntimeError for each."""
        return [RuntimeError("an edge stores no messages; they go to JetStream")] * len(msgs)
