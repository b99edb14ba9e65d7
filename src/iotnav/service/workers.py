"""A fleet shared by workers with per-device affinity and ordering, on NATS JetStream.

``iotnav serve --nats URL`` becomes an ingest edge and ``iotnav worker --nats URL --db
postgresql://...`` processes; the engine that partitions, orders, leases and redelivers is
NATS JetStream (the Debian package ``nats-server``, 2.9), not a scheme of our own.

Edge (:class:`~iotnav.service.worker_edge.EdgeIngestor`): the listeners of ``iotnav serve`` hand a decoded message to
``submit`` / ``enqueue`` as always; the edge publishes it to the stream ``IOTNAV_IN`` on the
subject ``iotnav.in.<partition>``, ``partition = crc32(device id) mod P``
(:func:`partition_of`), with the message's store de-duplication key
(:meth:`iotnav.service.ingest.Message.digest`) as ``Nats-Msg-Id``, and answers the device only
after JetStream's publish acknowledgement (the message is in the stream's file storage). A
message the device resends within the stream's duplicate window is dropped by JetStream; a
later one by the database's unique key, as on one machine.

Workers (:class:`Worker`): a partition is owned through a lease, a key ``p.<n>`` of the
JetStream key-value bucket ``iotnav_leases`` whose values expire after ``lease_s``
(the bucket's ``max_age``): a worker creates the key (JetStream's compare-and-set: only one
creation succeeds) and renews it with an update conditioned on its revision. A worker that
stops renewing (killed, partitioned, paused) loses its keys after ``lease_s``; another creates
them. Every live worker also refreshes a key ``worker.<id>``, and aims at ``ceil(P / live
workers)`` partitions: it takes free ones and, when over, releases the excess after
committing what it has (so a new worker gets its share).

A partition's messages are read from a durable pull consumer of that subject only (JetStream
delivers a subject's messages in stream order), named after the owner and its lease revision,
acknowledged with ``AckAll`` after the database commit of the batch. The new owner of a
partition reads the acknowledgement floor of the previous owner's consumer, deletes it (the
old owner, if still alive, then receives nothing), and creates its own from the next message:
so the messages a dead worker had fetched but not committed are delivered again, in order, at
once (no wait for a redelivery timeout).

Processing reuses the service's :class:`iotnav.service.ingest.Ingestor` unchanged, one per
owned partition (its device states belong to that partition only: a partition taken over
starts from the database, never from a stale copy in memory), through its public
:meth:`~iotnav.service.ingest.Ingestor.ingest_batch`: the same de-duplication by message key,
the same engine ``step()``, the same checkpoints in ``engine_states`` and the same replay of
the fixes stored after a checkpoint. So a partition resumed on another worker stores nothing
twice (a message committed before the crash but not acknowledged is answered as a duplicate
by the ``raw_messages`` key) and loses nothing (a message not acknowledged is delivered again).

Raw GNSS + IMU batches (MQTT ``iotnav/+/raw``, :mod:`iotnav.service.protocols.iotnav_raw`)
take the same path: the edge checks a batch, publishes its bytes as received (protocol
``iotnav_raw``, its topic as ``remote``, ``Nats-Msg-Id`` the ``raw_messages`` key) on its
device's subject, so a device's raw batches and its other messages stay in one order, and
acknowledges the MQTT message after JetStream's. The partition's owner stores them with a
:class:`iotnav.service.raw_ingest.RawProcessor` of its own (``make_raw``: the same engine
step, output schedule and per-batch checkpoint as ``iotnav serve`` without ``--nats``), the
consecutive raw batches of a fetch in one transaction, before the acknowledgement.

Live view: a worker publishes the positions it has committed (the rows the ingest hands its
listeners) on the core NATS subject ``iotnav.live``; every edge hands them to its own
listeners, so the API's ``/api/socket`` of any edge shows the whole fleet. At most once (a
worker killed between its commit and that publish leaves a gap in the live view only).

Alerts (``iotnav worker --alerts FILE``, the ``[alerts]`` table of
:mod:`iotnav.service.alerts_delivery`): each partition's :class:`AlertingIngestor` evaluates
the rules on the rows a batch stores, in the batch's own transaction, and stores the alerts
with it (:class:`PartitionAlerts`: a device's rule state rebuilt from its stored rows when an
owner first sees it; a de-duplication key per alert); :class:`WorkerAlerts` delivers them
(webhook, MQTT, the edges' WebSocket) and records the end of each delivery, and a new owner
delivers again what its predecessor left ``pending``: at least once, with the stored ``id``
as the receivers' de-duplication key (``docs/scaling.md``).

Fencing: a worker commits a batch only while its lease is valid by its own clock (the last
successful renewal, taken before the request, plus ``lease_s``, less a margin of a third);
past that it abandons the partition. A worker paused longer than the margin in the middle of
a commit could still overlap its successor; the database's unique keys then keep every
message stored once (its successor may skip that message's engine output).
"""

from __future__ import annotations

import asyncio
import base64
import contextlib
import dataclasses
import itertools
import json
import logging
import math
import os
import secrets
import socket
import time
import zlib
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

import sqlalchemy as sa

from iotnav.service.ingest import Ingestor, IngestResult, Message
from iotnav.service.protocols.common import Fix
from iotnav.service.protocols.iotnav_raw import PROTOCOL as RAW_PROTOCOL
from iotnav.service.worker_alerts import (  # the names moved there are re-exported
    AlertingIngestor,
    PartitionAlerts,
    WorkerAlerts,
    alert_key,
    mark_delivered,
    partition_of,
)

__all__ = [
    "AlertingIngestor",
    "ClusterSettings",
    "PartitionAlerts",
    "Worker",
    "WorkerAlerts",
    "WorkerConfig",
    "WorkerStats",
    "alert_key",
    "decode_message",
    "encode_message",
    "ensure_stream",
    "mark_delivered",
    "open_database",
    "partition_of",
    "run_worker",
]

log = logging.getLogger("iotnav.service.workers")

#: Wire format version of :func:`encode_message`.
WIRE_VERSION = 1
_FIX_FIELDS = tuple(f.name for f in dataclasses.fields(Fix))


@dataclass(frozen=True)
class ClusterSettings:
    """Settings shared by the edge and the workers (they must agree on ``partitions``).

    Attributes
    ----------
    url : str
        NATS server URL(s), comma-separated (``nats://host:4222``).
    partitions : int
        Number of partitions P (subjects ``<subject>.0`` .. ``<subject>.P-1``): the unit of
        ownership, so at most P workers share the fleet. Checked against the stream's.
    stream, subject : str
        JetStream stream name and subject prefix.
    bucket : str
        Key-value bucket of the leases.
    lease_s : float
        Lease time to live, s: a dead worker's partitions move after at most this long.
    duplicate_window_s : float
        JetStream de-duplication window of the stream, s (its default, 2 min).
    max_age_s : float
        Messages are kept in the stream this long, s (acknowledged or not); 0: forever.
    fetch_batch : int
        Messages fetched (and committed in one transaction) per partition at most.
    replicas : int
        Stream and bucket replicas (1 on one server; 3 on a cluster of 3).
    live_subject : str
        Core NATS subject on which workers publish the positions they have committed and edges
        hand them to their listeners (the API's ``/api/socket``); at most once: a live view.
    """

    url: str = "nats://127.0.0.1:4222"
    partitions: int = 16
    stream: str = "IOTNAV_IN"
    subject: str = "iotnav.in"
    bucket: str = "iotnav_leases"
    lease_s: float = 10.0
    duplicate_window_s: float = 120.0
    max_age_s: float = 7 * 86400.0
    fetch_batch: int = 500
    replicas: int = 1
    live_subject: str = "iotnav.live"

    def __post_init__(self) -> None:
        if not 1 <= self.partitions <= 4096:
            raise ValueError(f"partitions {self.partitions}: expected 1 to 4096")
        if not self.lease_s > 0:
            raise ValueError(f"lease_s {self.lease_s}: expected > 0 s")
        if self.fetch_batch < 1:
            raise ValueError(f"fetch_batch {self.fetch_batch}: expected >= 1")

    def subject_of(self, partition: int) -> str:
        """The subject of ``partition``."""
        return f"{self.subject}.{partition}"

    @property
    def description(self) -> str:
        """The stream's description, which records P (edges and workers check it)."""
        return f"iotnav ingest, partitions={self.partitions}"


def _fix_dict(f: Fix) -> dict[str, Any]:
    return {name: getattr(f, name) for name in _FIX_FIELDS}


def encode_message(m: Message) -> bytes:
    """``m`` as the stream's message body (JSON; the payload base64; NaN written as ``NaN``)."""
    doc = {
        "v": WIRE_VERSION,
        "protocol": m.protocol,
        "device": m.device,
        "payload": base64.b64encode(m.payload).decode("ascii"),
        "fixes": [_fix_dict(f) for f in m.fixes],
        "remote": m.remote,
        "received_at": m.received_at,
        "unique": m.unique,
    }
    return json.dumps(doc, separators=(",", ":")).encode()


def decode_message(data: bytes) -> Message:
    """The :class:`Message` of a stream message body; ValueError when it is not one."""
    try:
        doc = json.loads(data)
        if not isinstance(doc, dict) or doc.get("v") != WIRE_VERSION:
            raise ValueError(f"wire version {doc.get('v') if isinstance(doc, dict) else None!r}")
        fixes = [Fix(**{k: f[k] for k in _FIX_FIELDS if k in f}) for f in doc["fixes"]]
        return Message(
            protocol=str(doc["protocol"]),
            device=str(doc["device"]),
            payload=base64.b64decode(doc["payload"], validate=True),
            fixes=fixes,
            remote=doc.get("remote"),
            received_at=float(doc["received_at"]),
            unique=bool(doc.get("unique", False)),
        )
    except (KeyError, TypeError, ValueError, UnicodeDecodeError) as exc:
        raise ValueError(f"not an iotnav stream message: {exc!r}") from exc


async def ensure_stream(js: Any, settings: ClusterSettings) -> None:
    """Create the stream (file storage, limits retention) unless it exists; check its P."""
    from nats.js import api
    from nats.js.errors import NotFoundError

    try:
        info = await js.stream_info(settings.stream)
    except NotFoundError:
        config = api.StreamConfig(
            name=settings.stream,
            description=settings.description,
            subjects=[f"{settings.subject}.*"],
            retention=api.RetentionPolicy.LIMITS,
            storage=api.StorageType.FILE,
            max_age=settings.max_age_s or None,
            duplicate_window=settings.duplicate_window_s,
            num_replicas=settings.replicas,
        )
        try:
            await js.add_stream(config)
            return
        except Exception:  # another process created it meanwhile
            info = await js.stream_info(settings.stream)
    if info.config.description != settings.description:
        raise ValueError(
            f"stream {settings.stream}: {info.config.description!r}; this process has "
            f"partitions={settings.partitions} (every edge and worker must use the same)"
        )


@dataclass
class _Lease:
    partition: int
    revision: int
    #: Monotonic time until which the lease is valid by this worker's clock.
    valid_until: float
    task: asyncio.Task[None] | None = None
    ingestor: Ingestor | None = None
    release: bool = False  # finish the current batch, then hand the partition back


@dataclass
class WorkerStats:
    """What a worker has done (for logs and the benchmark)."""

    messages: int = 0
    duplicates: int = 0
    batches: int = 0
    failed: int = 0
    bad: int = 0
    acquired: int = 0
    lost: int = 0
    released: int = 0


def _worker_id() -> str:
    host = "".join(c if c.isalnum() else "-" for c in socket.gethostname())[:24]
    return f"{host}-{os.getpid()}-{secrets.token_hex(2)}"


class Worker:
    """Owns partitions through leases and runs an :class:`Ingestor` per owned partition.

    Parameters
    ----------
    cluster : ClusterSettings
        Where the stream and the leases are.
    make_ingestor : callable
        Builds the ingestor of one partition (same database, engine and checkpoint key for
        every worker).
    worker_id : str, optional
        Unique name of this worker (default: host, pid and a random suffix).
    max_partitions : int, optional
        Owns at most this many partitions (default: no limit beyond the fair share).
    alerts : WorkerAlerts, optional
        Delivery of the alerts that ``make_ingestor``'s :class:`AlertingIngestor` raise.
    make_raw : callable, optional
        Builds the processor of raw GNSS + IMU batches of one partition on its ingestor
        (:class:`iotnav.service.raw_ingest.RawProcessor`); None: raw batches are not stored
        (counted ``cluster_raw_no_engine`` and logged).
    """

    def __init__(
        self,
        cluster: ClusterSettings,
        make_ingestor: Callable[[], Ingestor],
        worker_id: str | None = None,
        max_partitions: int | None = None,
        alerts: WorkerAlerts | None = None,
        make_raw: Callable[[Ingestor], Any] | None = None,
    ) -> None:
        self.alerts = alerts
        self.make_raw = make_raw
        self.cluster = cluster
        self.make_ingestor = make_ingestor
        self.worker_id = worker_id or _worker_id()
        self.max_partitions = max_partitions
        self.leases: dict[int, _Lease] = {}
        self.stats = WorkerStats()
        self._nc: Any = None
        self._js: Any = None
        self._kv: Any = None
        self._live: set[asyncio.Future[None]] = set()

    # --- leases -----------------------------------------------------------------------

    @property
    def _margin(self) -> float:
        return self.cluster.lease_s / 3.0

    def _valid(self, lease: _Lease) -> bool:
        return time.monotonic() < lease.valid_until - self._margin

    async def _connect(self) -> None:
        import nats
        from nats.js import api
        from nats.js.errors import BucketNotFoundError

        self._nc = await nats.connect(self.cluster.url.split(","), name=f"iotnav-worker-{self.worker_id}")
        self._js = self._nc.jetstream()
        await ensure_stream(self._js, self.cluster)
        try:
            self._kv = await self._js.key_value(self.cluster.bucket)
        except BucketNotFoundError:
            self._kv = await self._js.create_key_value(
                api.KeyValueConfig(
                    bucket=self.cluster.bucket,
                    history=1,
                    ttl=self.cluster.lease_s,
                    storage=api.StorageType.FILE,
                    replicas=self.cluster.replicas,
                )
            )

    async def _live_workers(self) -> int:
        from nats.js.errors import NoKeysError

        try:
            keys = await self._kv.keys()
        except NoKeysError:
            return 1
        return max(1, sum(1 for k in keys if k.startswith("worker.")))

    async def _renew(self) -> None:
        """Renew every owned lease; a lease whose key changed or expired is lost."""
        from nats.js.errors import KeyWrongLastSequenceError

        value = self.worker_id.encode()
        for p, lease in list(self.leases.items()):
            t0 = time.monotonic()
            try:
                lease.revision = await self._kv.update(f"p.{p}", value, last=lease.revision)
                lease.valid_until = t0 + self.cluster.lease_s
            except KeyWrongLastSequenceError:
                log.warning("worker %s: lease of partition %d lost", self.worker_id, p)
                self._drop(p, lost=True)
            except Exception as exc:  # NATS away for a moment: the lease may still be valid
                log.warning("worker %s: renewing partition %d failed (%r)", self.worker_id, p, exc)
                if not self._valid(lease):
                    self._drop(p, lost=True)

    def _drop(self, p: int, lost: bool) -> None:
        """Stop partition ``p`` at once (its lease is gone): nothing more is committed for it."""
        lease = self.leases.pop(p, None)
        if lease is None:
            return
        if lost:
            self.stats.lost += 1
        if lease.task is not None:
            lease.task.cancel()
        if lease.ingestor is not None:  # no checkpoints: the new owner's are newer
            lease.ingestor.executor.shutdown(wait=False, cancel_futures=True)

    async def _balance(self) -> None:
        """Take free partitions up to the fair share; release those above it."""
        target = math.ceil(self.cluster.partitions / await self._live_workers())
        if self.max_partitions is not None:
            target = min(target, self.max_partitions)
        active = [p for p, lease in self.leases.items() if not lease.release]
        if len(active) > target:
            for p in sorted(active)[target:]:
                self.leases[p].release = True
            return
        need = target - len(active)
        if need <= 0:
            return
        from nats.js.errors import KeyWrongLastSequenceError

        start = zlib.crc32(self.worker_id.encode()) % self.cluster.partitions
        for k in range(self.cluster.partitions):
            if need <= 0:
                break
            p = (start + k) % self.cluster.partitions
            if p in self.leases:
                continue
            t0 = time.monotonic()
            try:
                rev = await self._kv.create(f"p.{p}", self.worker_id.encode())
            except KeyWrongLastSequenceError:
                continue  # owned by another worker
            lease = self.leases[p] = _Lease(p, rev, t0 + self.cluster.lease_s)
            self.stats.acquired += 1
            lease.task = asyncio.create_task(self._run_partition(lease))
            need -= 1

    async def _lease_loop(self) -> None:
        heartbeat = f"worker.{self.worker_id}"
        period = self.cluster.lease_s / 4.0
        while True:
            t0 = time.monotonic()
            try:
                await self._kv.put(heartbeat, b"alive")
                await self._renew()
                await self._balance()
            except asyncio.CancelledError:
                raise
            except Exception:
                log.exception("worker %s: lease round failed", self.worker_id)
            for p, lease in list(self.leases.items()):
                if not self._valid(lease):
                    log.warning("worker %s: lease of partition %d timed out", self.worker_id, p)
                    self._drop(p, lost=True)
            await asyncio.sleep(max(0.0, period - (time.monotonic() - t0)))

    # --- consuming a partition --------------------------------------------------------

    async def _take_over(self, lease: _Lease) -> Any:
        """Delete the previous owners' consumers of the partition; ours, from their ack floor."""
        from nats.js import api

        subject = self.cluster.subject_of(lease.partition)
        start = 0
        for info in await self._js.consumers_info(self.cluster.stream):
            if info.config.filter_subject != subject:
                continue
            floor = info.ack_floor.stream_seq if info.ack_floor is not None else 0
            created_from = _start_of(info.config.description)
            start = max(start, (floor or 0) + 1, created_from)
            await self._js.delete_consumer(self.cluster.stream, info.name)
        name = f"p{lease.partition}-{self.worker_id}-{lease.revision}"
        config = api.ConsumerConfig(
            name=name,
            durable_name=name,
            description=f"start={start}",
            filter_subject=subject,
            ack_policy=api.AckPolicy.ALL,
            deliver_policy=api.DeliverPolicy.BY_START_SEQUENCE if start > 0 else api.DeliverPolicy.ALL,
            opt_start_seq=start if start > 0 else None,
            ack_wait=max(30.0, 3 * self.cluster.lease_s),
            max_ack_pending=max(10_000, 4 * self.cluster.fetch_batch),
            max_waiting=16,
        )
        await self._js.add_consumer(self.cluster.stream, config=config)
        log.info("worker %s: partition %d from stream sequence %d", self.worker_id, lease.partition, start)
        return await self._js.pull_subscribe_bind(name, stream=self.cluster.stream)

    async def _run_partition(self, lease: _Lease) -> None:
        import nats.errors

        loop = asyncio.get_running_loop()
        try:
            sub = await self._take_over(lease)
            lease.ingestor = ing = self.make_ingestor()
            ing.listeners.append(self._forwarder(loop))
            raw = self.make_raw(ing) if self.make_raw is not None else None
            hub = self.alerts
            alerts = ing.alerts if isinstance(ing, AlertingIngestor) and hub is not None else None
            if alerts is not None and hub is not None:  # a previous owner's unfinished deliveries
                args = (ing.db, lease.partition, self.cluster.partitions, time.time(), hub.redeliver_window_s)
                again = await loop.run_in_executor(ing.executor, alerts.pending, *args)
                if again:
                    log.warning("partition %d: %d alerts delivered again", lease.partition, len(again))
                for a in again:
                    hub.deliver(a)
            ticked = time.monotonic()
            while not lease.release:
                try:
                    msgs = await sub.fetch(self.cluster.fetch_batch, timeout=0.5)
                except (TimeoutError, nats.errors.TimeoutError):  # nothing new within the fetch's wait
                    msgs = []
                if msgs:
                    await self._process(lease, ing, raw, msgs, loop)
                if alerts is not None and hub is not None:
                    due = time.monotonic() - ticked >= hub.settings.poll_interval_s
                    if due and self._valid(lease):
                        ticked = time.monotonic()
                        await loop.run_in_executor(ing.executor, self._tick, alerts, ing)
                    for a in alerts.take():
                        hub.deliver(a)
            # released: the batch is committed and acknowledged; checkpoints then hand over
            await loop.run_in_executor(ing.executor, ing.flush_checkpoints)
            ing.executor.shutdown(wait=True)
            with contextlib.suppress(Exception):
                await sub.unsubscribe()
            self.leases.pop(lease.partition, None)  # no more renewals: the revision below stays ours
            with contextlib.suppress(Exception):
                await self._kv.delete(f"p.{lease.partition}", last=lease.revision)
            self.stats.released += 1
            log.info("worker %s: partition %d released", self.worker_id, lease.partition)
        except asyncio.CancelledError:
            raise
        except Exception:
            log.exception("worker %s: partition %d failed; giving it up", self.worker_id, lease.partition)
            self._drop(lease.partition, lost=False)

    @staticmethod
    def _tick(alerts: PartitionAlerts, ing: Ingestor) -> None:
        """The clock rules of a partition (its database thread); a failure waits for the next tick."""
        try:
            alerts.tick(ing.db, time.time())
        except Exception:
            alerts.rolled_back()
            ing.count("alerts_errors")
            log.exception("alerts: the clock rules failed")
        else:
            alerts.committed()

    def _socket_send(self, msg: dict[str, Any]) -> None:
        """The edges' WebSocket (``{"events": [alert]}`` on the live subject; event loop)."""
        if self._nc is not None and not self._nc.is_closed:
            body = json.dumps(msg, separators=(",", ":")).encode()
            task = asyncio.ensure_future(self._nc.publish(self.cluster.live_subject, body))
            self._live.add(task)
            task.add_done_callback(self._live.discard)

    def _forwarder(self, loop: asyncio.AbstractEventLoop) -> Callable[[str, list[dict[str, Any]]], None]:
        """An Ingestor listener (database thread) publishing committed positions to the edges."""

        def publish(body: bytes) -> None:
            if self._nc is not None and not self._nc.is_closed:
                task = asyncio.ensure_future(self._nc.publish(self.cluster.live_subject, body))
                self._live.add(task)  # (a reference until it is done)
                task.add_done_callback(self._live.discard)

        def listener(protocol: str, rows: list[dict[str, Any]]) -> None:
            body = json.dumps({"protocol": protocol, "rows": rows}, separators=(",", ":")).encode()
            loop.call_soon_threadsafe(publish, body)

        return listener

    async def _process(
        self, lease: _Lease, ing: Ingestor, raw: Any, msgs: list[Any], loop: asyncio.AbstractEventLoop
    ) -> None:
        """Store ``msgs`` (retrying while the database is away), then ack: the consecutive
        messages of one kind (raw batches, others) in one transaction each, in stream order."""
        batch: list[Message] = []
        for m in msgs:
            try:
                batch.append(decode_message(m.data))
            except ValueError as exc:
                self.stats.bad += 1
                ing.count("cluster_bad_message")
                log.error("partition %d: %s (skipped)", lease.partition, exc)
        for _, run in itertools.groupby(batch, key=lambda m: m.protocol == RAW_PROTOCOL):
            await self._store_run(lease, ing, raw, list(run), msgs[-1], loop)
        self.stats.batches += 1
        await msgs[-1].ack()  # AckAll: acknowledges the batch (committed above)

    async def _store_run(
        self, lease: _Lease, ing: Ingestor, raw: Any, batch: list[Message], last: Any, loop: Any
    ) -> None:
        """Store ``batch`` (all raw batches or none) in one transaction, retrying what the
        database could not take (``OperationalError``) until it can."""
        store: Callable[[Sequence[Message]], list[IngestResult | Exception]] = ing.ingest_batch
        if batch[0].protocol == RAW_PROTOCOL:
            store = raw.ingest_messages if raw is not None else _no_raw_engine
        delay = 0.2
        while batch:
            if not self._valid(lease):
                raise asyncio.CancelledError  # the lease may be someone else's by now: commit nothing
            results = await loop.run_in_executor(ing.executor, store, batch)
            retry = []
            for m, res in zip(batch, results, strict=True):
                if isinstance(res, sa.exc.OperationalError):
                    retry.append(m)
                elif isinstance(res, Exception):  # this message can never be stored: counted
                    self.stats.failed += 1
                    ing.count("cluster_store_failed")
                    log.error(
                        "partition %d: %s %s not stored: %r", lease.partition, m.protocol, m.device, res
                    )
                else:
                    self.stats.messages += 1
                    self.stats.duplicates += res.duplicate
            if retry:
                log.warning(
                    "partition %d: database unavailable; retrying %d messages", lease.partition, len(retry)
                )
                await last.in_progress()  # keep them ours meanwhile
                await asyncio.sleep(delay)
                delay = min(5.0, 2 * delay)
            batch = retry

    # --- running ----------------------------------------------------------------------

    async def run(self, stop: asyncio.Event | None = None) -> None:
        """Serve until ``stop`` is set; then release every partition (checkpoints written)."""
        stop = stop or asyncio.Event()
        await self._connect()
        if self.alerts is not None:
            self.alerts.start(self._socket_send, self.worker_id)
        log.warning(
            "iotnav worker %s: %d partitions on %s", self.worker_id, self.cluster.partitions, self.cluster.url
        )
        leases = asyncio.create_task(self._lease_loop())
        try:
            await stop.wait()
        finally:
            leases.cancel()
            await asyncio.gather(leases, return_exceptions=True)
            for lease in list(self.leases.values()):
                lease.release = True
            tasks = [lease.task for lease in self.leases.values() if lease.task is not None]
            await asyncio.gather(*tasks, return_exceptions=True)
            with contextlib.suppress(Exception):
                await self._kv.delete(f"worker.{self.worker_id}")
            if self.alerts is not None:
                await self.alerts.stop()
            with contextlib.suppress(Exception):
                await (
                    self._nc.flush()
                )  # the last acknowledgements (drain waits forever on pull subscriptions)
            with contextlib.suppress(Exception):
                await self._nc.close()


def _no_raw_engine(msgs: Sequence[Message]) -> list[IngestResult | Exception]:
    """The results of raw batches on a worker without a raw engine (``raw_engine = none``)."""
    return [RuntimeError("this worker has no raw engine (raw_engine = none)")] * len(msgs)


def _start_of(description: str | None) -> int:
    """The start sequence a consumer of ours was created with (its description ``start=N``)."""
    if description and description.startswith("start="):
        with contextlib.suppress(ValueError):
            return int(description[6:])
    return 0


@dataclass(frozen=True)
class WorkerConfig:
    """Settings of ``iotnav worker`` (the processing settings as ``iotnav serve``'s).

    Attributes
    ----------
    db : str
        SQLAlchemy URL of the shared database (PostgreSQL: ``postgresql+psycopg://...``).
    data : str
        Directory of the checkpoint key (``checkpoint_key``): every worker must read the same
        key (copy the file), or the checkpoints of another worker are discarded (replayed).
    engine, engine_config, registration_open, reorder_window_s, checkpoint_interval_s
        As :class:`iotnav.service.app.ServiceConfig`.
    alerts : str or dict
        The ``[alerts]`` settings (:mod:`iotnav.service.alerts_delivery`: a TOML file or the
        table), as ``iotnav serve``'s; empty: no alerts.
    raw_engine, raw_engine_config, raw_engines, raw_output_interval_s
        The engines of raw GNSS + IMU devices, as :class:`iotnav.service.app.ServiceConfig`'s
        (:class:`iotnav.service.raw_ingest.RawSettings`); ``raw_engine = none``: raw batches
        are not stored.
    """

    db: str
    data: str = "iotnav-data"
    engine: str = "fixes"
    engine_config: str = ""
    registration_open: bool = True
    reorder_window_s: float = 0.0
    checkpoint_interval_s: float = 60.0
    alerts: str | dict[str, Any] = ""
    raw_engine: str = "pipeline"
    raw_engine_config: str = ""
    raw_engines: dict[str, str] = dataclasses.field(default_factory=dict)
    raw_output_interval_s: float = 1.0


def open_database(url: str, pool_size: int) -> sa.engine.Engine:
    """The database of ``url`` at the head migration (upgraded under a PostgreSQL advisory lock,
    so that workers starting together do not race); ``pool_size`` connections for PostgreSQL."""
    from iotnav.service import store

    if sa.engine.make_url(url).get_backend_name() == "postgresql":
        db = sa.create_engine(url, pool_size=pool_size, max_overflow=4, pool_pre_ping=True)
    else:
        db = store.make_engine(url)
    store.upgrade(db)  # the service's own lock key: a worker and an edge starting together take turns
    return db


def _shared_key(data: str) -> bytes:
    from iotnav.service.checkpoint import load_key

    os.makedirs(data, exist_ok=True)
    try:
        return load_key(data)
    except FileExistsError:  # another worker created it at the same moment
        time.sleep(0.1)
        return load_key(data)


async def run_worker(
    config: WorkerConfig, cluster: ClusterSettings, stop: asyncio.Event | None = None
) -> Worker:
    """Run one worker until ``stop`` (or SIGINT / SIGTERM when None); the worker (with its stats)."""
    import signal

    db = open_database(config.db, pool_size=min(cluster.partitions, 32) + 1)
    key = _shared_key(config.data)

    settings: Any = None
    if config.alerts:
        from iotnav.service.alerts_delivery import AlertSettings

        settings = AlertSettings.load(config.alerts)

    def make_ingestor() -> Ingestor:
        args = (db, config.engine, config.registration_open, config.engine_config or None)
        kwargs: dict[str, Any] = {
            "reorder_window_s": config.reorder_window_s,
            "checkpoint_key": key,
            "checkpoint_interval_s": config.checkpoint_interval_s,
        }
        if settings is None:
            return Ingestor(*args, **kwargs)
        return AlertingIngestor(*args, alert_settings=settings, **kwargs)

    make_raw = None
    if config.raw_engine != "none":
        from iotnav.service.raw_ingest import RawProcessor, RawSettings

        raw_settings = RawSettings(
            config.raw_engine,
            config.raw_engine_config,
            dict(config.raw_engines),
            config.raw_output_interval_s,
        )

        def make_raw(ing: Ingestor) -> RawProcessor:
            return RawProcessor(ing, raw_settings)

    first = make_ingestor()
    log.info("engine %s ready in %.1f s", config.engine, first.warm_up())
    if make_raw is not None:
        log.info("raw engine %s ready in %.1f s", config.raw_engine, make_raw(first).warm_up())
    hub = WorkerAlerts(settings, db, first) if settings is not None else None
    if stop is None:
        stop = asyncio.Event()
        loop = asyncio.get_running_loop()
        for sig in (signal.SIGINT, signal.SIGTERM):
            with contextlib.suppress(NotImplementedError, RuntimeError):
                loop.add_signal_handler(sig, stop.set)
    worker = Worker(cluster, make_ingestor, alerts=hub, make_raw=make_raw)
    try:
        await worker.run(stop)
    finally:
        db.dispose()
    log.warning("iotnav worker %s stopped: %s", worker.worker_id, worker.stats)
    return worker
