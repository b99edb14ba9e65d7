"""MQTT subscriber (aiomqtt): OwnTracks and iotnav's raw GNSS + IMU batches, acknowledged after commit.

The service subscribes to ``owntracks/+/+`` and, when raw IMU devices are enabled, to
``iotnav/+/raw`` (:mod:`iotnav.service.protocols.iotnav_raw`, processed by
:mod:`iotnav.service.raw_ingest`; both filters configurable) with QoS 1 on a persistent session
(``clean_session = False`` and a fixed client id), so the broker keeps the messages that
arrive while the service is down and delivers them when it is back.

Acknowledgements are manual: the PUBACK of a message is sent only once its records are
committed. Raw batches already waiting in the client's queue are stored together in one
transaction (at most ``max_raw_group``: one commit, one ``fsync``, for many devices), each
acknowledged once it has committed. Other messages are handed to the ingest
(:meth:`iotnav.service.ingest.Ingestor.enqueue`, group commit) in the order they arrive and a
second task acknowledges them in that same order as their transactions finish (MQTT 3.1.1
requires PUBACKs in the order of the PUBLISHes, [MQTT-4.6.0-2]); at most
``max_in_flight`` messages wait for their commit (back-pressure: the subscriber stops
reading the socket, so the broker holds the rest). A message the service stored before
(redelivered because the PUBACK was lost) is acknowledged without being stored again. A
message the decoder rejects is acknowledged (it would otherwise come back forever), logged
and counted. When storing fails the message and every later one stay unacknowledged: the
subscriber drops the connection and reconnects, and the broker redelivers them. A lost broker
is reconnected with a back-off from ``retry_min_s`` doubling to ``retry_max_s``.

aiomqtt 2.5 has no manual-acknowledgement option of its own (its issue 345): the subscriber
switches the underlying paho-mqtt client to manual acknowledgement (``manual_ack_set``)
and acknowledges through it (``ack(mid, qos)``), on the event loop that drives that client.
Both go through :func:`_paho`, the one place that reaches inside aiomqtt; the version is
pinned and ``tests/test_service_mqtt.py`` checks the behaviour against a real mosquitto.
"""

from __future__ import annotations

import asyncio
import logging
from concurrent.futures import Executor
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any
from urllib.parse import urlparse

import aiomqtt

from iotnav.service.ingest import Ingestor, IngestResult
from iotnav.service.protocols import iotnav_raw, owntracks
from iotnav.service.protocols.common import Rejected

if TYPE_CHECKING:
    from iotnav.service.raw_ingest import RawProcessor

log = logging.getLogger("iotnav.service.mqtt")


@dataclass(frozen=True)
class MqttSettings:
    """Broker URL (``mqtt://[user:password@]host[:port]``), client id of the persistent session,
    topic filter (OwnTracks), topic filter of raw batches (used with a raw processor),
    messages awaiting their commit at most, raw batches stored in one transaction at most,
    reconnection back-off (s)."""

    url: str
    client_id: str = "iotnav-serve"
    topic: str = "owntracks/+/+"
    raw_topic: str = "iotnav/+/raw"
    max_in_flight: int = 1000
    max_raw_group: int = 200
    retry_min_s: float = 0.5
    retry_max_s: float = 30.0


#: A message and the future of its transaction (None: rejected by the decoder, acknowledged as is).
_Pending = tuple[aiomqtt.Message, "asyncio.Future[IngestResult] | None"]


class _StoreFailed(Exception):
    """Storing a message failed: reconnect without acknowledging it."""


def _pick(fut: asyncio.Future[list[IngestResult]], k: int) -> asyncio.Future[IngestResult]:
    """A future of item ``k`` of the results of a grouped transaction."""

    async def pick() -> IngestResult:
        return (await fut)[k]

    return asyncio.ensure_future(pick())


def _paho(client: aiomqtt.Client) -> Any:
    """The paho-mqtt client inside an aiomqtt client (manual acknowledgement, module docstring)."""
    return client._client


class MqttSubscriber:
    """Subscribes on the service's event loop (:meth:`run`); storing goes through ``executor``."""

    def __init__(
        self,
        settings: MqttSettings,
        ingestor: Ingestor,
        executor: Executor,
        raw: RawProcessor | None = None,
        publish_raw: bool = False,
    ) -> None:
        self.settings = settings
        self.ingestor = ingestor
        self.executor = executor
        #: Processor of raw GNSS + IMU batches; None: ``raw_topic`` is not subscribed.
        self.raw = raw
        #: An edge: raw batches go to ``ingestor.enqueue`` (JetStream), not to ``raw``.
        self.publish_raw = publish_raw
        if raw is not None and publish_raw:
            raise ValueError("a raw processor and publish_raw: raw batches are processed here or published")
        u = urlparse(settings.url)
        if u.scheme not in ("mqtt", "tcp") or not u.hostname:
            raise ValueError(f"MQTT URL {settings.url!r}: expected mqtt://host[:port]")
        self.host, self.port = u.hostname, u.port or 1883
        self.username, self.password = u.username, u.password
        #: Set while subscribed (tests and health checks wait on it).
        self.subscribed = asyncio.Event()

    async def run(self) -> None:
        """Connect, subscribe and store until cancelled; reconnect after any loss."""
        delay = self.settings.retry_min_s
        while True:
            try:
                await self._session()
            except* _StoreFailed:
                self.ingestor.count("mqtt_errors")
                log.error("mqtt: storing failed; not acknowledged, reconnecting for redelivery")
            except* aiomqtt.MqttError as group:
                exc = group.exceptions[0]
                log.warning("mqtt %s:%d: %s; reconnecting in %.1f s", self.host, self.port, exc, delay)
            if self.subscribed.is_set():  # the session had worked: start the back-off again
                delay = self.settings.retry_min_s
            self.subscribed.clear()
            await asyncio.sleep(delay)
            delay = min(2.0 * delay, self.settings.retry_max_s)

    async def _session(self) -> None:
        client = aiomqtt.Client(
            self.host,
            self.port,
            identifier=self.settings.client_id,
            clean_session=False,
            protocol=aiomqtt.ProtocolVersion.V311,
            username=self.username,
            password=self.password,
            keepalive=30,
        )
        _paho(client).manual_ack_set(True)
        async with client:
            with_raw = self.raw is not None or self.publish_raw
            topics = [self.settings.topic] + ([self.settings.raw_topic] if with_raw else [])
            await client.subscribe([(t, 1) for t in topics])
            log.warning("mqtt %s:%d: subscribed to %s", self.host, self.port, ", ".join(topics))
            self.subscribed.set()
            queue: asyncio.Queue[_Pending] = asyncio.Queue(self.settings.max_in_flight)
            async with asyncio.TaskGroup() as tg:  # either task failing ends the session
                tg.create_task(self._acknowledge(client, queue))
                async for msg in client.messages:
                    msgs = [msg]  # and those already waiting: their raw batches share a commit
                    while len(client.messages) and len(msgs) < self.settings.max_raw_group:
                        msgs.append(await anext(client.messages))
                    for pending in self._submit_all(msgs):
                        await queue.put(pending)

    def _submit_all(self, msgs: list[aiomqtt.Message]) -> list[_Pending]:
        """Hand ``msgs`` to the database thread in order; consecutive raw batches as one transaction."""
        out: list[_Pending] = []
        group: list[tuple[aiomqtt.Message, bytes, iotnav_raw.RawBatch]] = []

        def flush() -> None:
            if not group:
                return
            assert self.raw is not None
            items: list[tuple[bytes, iotnav_raw.RawBatch, str | None]] = [
                (p, b, str(m.topic)) for m, p, b in group
            ]
            fut = asyncio.get_running_loop().run_in_executor(self.executor, self.raw.ingest_many, items)
            out.extend((m, _pick(fut, k)) for k, (m, _, _) in enumerate(group))
            group.clear()

        for msg in msgs:
            if self.raw is not None and msg.topic.matches(self.settings.raw_topic):
                payload = bytes(msg.payload) if isinstance(msg.payload, bytes | bytearray) else b""
                batch = iotnav_raw.decode(payload, topic=str(msg.topic))
                if not isinstance(batch, Rejected):
                    group.append((msg, payload, batch))
                    continue
            flush()
            out.append((msg, self._submit(msg)))
        flush()
        return out

    def _submit(self, msg: aiomqtt.Message) -> asyncio.Future[IngestResult] | None:
        """Hand ``msg`` to the database thread; None for a message the decoder rejects."""
        topic = str(msg.topic)
        payload = bytes(msg.payload) if isinstance(msg.payload, bytes | bytearray) else b""
        loop = asyncio.get_running_loop()
        if (self.raw is not None or self.publish_raw) and msg.topic.matches(self.settings.raw_topic):
            batch = iotnav_raw.decode(payload, topic=topic)
            if isinstance(batch, Rejected):
                self.ingestor.count(f"mqtt_rejected_raw_{batch.reason}")
                log.warning("mqtt %s: rejected (%s: %s)", topic, batch.reason, batch.detail)
                return None
            if self.raw is None:  # an edge: to JetStream, the bytes as received (the worker decodes)
                return self.ingestor.enqueue(iotnav_raw.PROTOCOL, batch.device or "", payload, [], topic)
            return loop.run_in_executor(self.executor, self.raw.ingest, payload, batch, topic)
        result = owntracks.decode(payload, topic=topic)
        if isinstance(result, Rejected) or result.device is None:
            reason = result.reason if isinstance(result, Rejected) else "no_device"
            self.ingestor.count(f"mqtt_rejected_{reason}")
            log.warning("mqtt %s: rejected (%s)", topic, reason)
            return None
        return self.ingestor.enqueue("owntracks", result.device, payload, result.records, topic)

    async def _acknowledge(self, client: aiomqtt.Client, queue: asyncio.Queue[_Pending]) -> None:
        """Acknowledge the queued messages in arrival order, each once its commit is done."""
        while True:
            msg, fut = await queue.get()
            if fut is not None:
                try:
                    res = await fut
                except Exception as exc:
                    log.error("mqtt %s: storing failed (%s)", msg.topic, exc)
                    raise _StoreFailed from exc
                if not res.accepted:
                    self.ingestor.count(f"mqtt_rejected_{res.reason or 'unknown_device'}")
            if msg.qos > 0:
                _paho(client).ack(msg.mid, msg.qos)
