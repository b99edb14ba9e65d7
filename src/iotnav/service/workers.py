"""A fleet shared by workers with per-device affinity and ordering, on NATS JetStream.

``iotnav serve --nats URL`` becomes an ingest edge and ``iotnav worker --nats URL --db
postgresql://...`` processes; the engine that partitions, orders, leases and redelivers is
NATS JetStream (the Debian package ``nats-server``, 2.9), not a scheme of our own.

Edge (:class:`EdgeIngestor`): the listeners of ``iotnav serve`` hand a decoded message to
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
import hashlib
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
from concurrent.futures import Future as ConcurrentFuture
from dataclasses import dataclass
from typing import Any

import sqlalchemy as sa
from sqlalchemy.engine import Connection

from iotnav.service.ingest import Ingestor, IngestResult, Message
from iotnav.service.protocols.common import Fix
from iotnav.service.protocols.iotnav_raw import PROTOCOL as RAW_PROTOCOL

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


def partition_of(device: str, partitions: int) -> int:
    """The partition of ``device``: CRC-32 of its UTF-8 id modulo ``partitions`` (stable everywhere)."""
    return zlib.crc32(device.encode("utf-8", "replace")) % partitions


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


# --- alerts on the workers ---------------------------------------------------------------


def alert_key(unique_id: str, kind: str, anchor_t: float, zone: str = "") -> str:
    """The de-duplication key of an alert: SHA-256 (hex, 32 characters) of the device, the kind,
    the device time that anchors it (the triggering position or event; the last position for
    ``silent``, the stop's start for ``stop``) and the zone of a geofence alert."""
    text = f"{unique_id}|{kind}|{anchor_t!r}|{zone}"
    return hashlib.sha256(text.encode()).hexdigest()[:32]


def _anchor(a: Any) -> float:
    """The device time an alert is anchored to (:func:`alert_key`), s; <= ``a.t``."""
    if a.kind == "silent":
        return float(a.detail.get("last_received", a.t))
    if a.kind == "stop":
        return float(a.detail.get("since", a.t))
    return float(a.t)


class PartitionAlerts:
    """The alert rules of one partition, evaluated inside its ingest transactions.

    The rows a batch stores (the positions of the engine in use with the ``ignition`` flag of the
    fix as sent, or a raw batch's clean ones, as handed to listeners; the engine events
    ``fix_rejected`` / ``moved_while_off``, read back by id) are, in the same transaction, fed to one :class:`iotnav.alerts.AlertEngine`, and
    its alerts stored in ``events`` (as :class:`iotnav.service.alerts_delivery.AlertService`
    stores them, with a de-duplication ``key`` (:func:`alert_key`) and ``delivery: pending``
    in the attributes) before the commit: a batch and its alerts are committed together or
    not at all. A device's rule state is rebuilt, the first time the partition's owner sees
    it, from its rows stored before (the last ``lookback_s`` of device time), with the alerts
    of that replay discarded (they were evaluated by the previous owner, in their own
    transactions). An alert whose key is already stored is not stored again.

    Parameters
    ----------
    settings : iotnav.service.alerts_delivery.AlertSettings
        Rules per group, geofence reload period, default group.
    engine_name : str
        The engine whose positions the rules read.
    lookback_s : float
        Device time replayed to rebuild a device's rule state, s.
    """

    def __init__(self, settings: Any, engine_name: str, lookback_s: float = 3600.0) -> None:
        from iotnav.alerts import AlertEngine

        self.settings = settings
        self.engine_name = engine_name
        self.lookback_s = lookback_s
        self.rules = AlertEngine(settings.groups, default_group=settings.default_group)
        self.counts: dict[str, int] = {}
        self._wm: dict[int, tuple[int, int]] = {}  # device id -> (positions id, events id) read
        self._uid: dict[int, str] = {}
        self._known: set[str] = set()
        self._zones_at = -math.inf
        self._touched: set[int] = set()
        self._staged: list[dict[str, Any]] = []
        self._ready: list[dict[str, Any]] = []

    def _count(self, what: str, n: int = 1) -> None:
        self.counts[what] = self.counts.get(what, 0) + n

    # --- in the ingest transaction (the partition's database thread) ---------------------

    def floors(self, conn: Connection, msgs: Sequence[Message]) -> tuple[int, int] | None:
        """The largest row ids before this transaction's, when a device is new here (else None)."""
        if all(m.device in self._known for m in msgs):
            return None
        from iotnav.service.store import events, positions

        return (
            int(conn.execute(sa.select(sa.func.coalesce(sa.func.max(positions.c.id), 0))).scalar_one()),
            int(conn.execute(sa.select(sa.func.coalesce(sa.func.max(events.c.id), 0))).scalar_one()),
        )

    def _reload_zones(self, conn: Connection, now: float) -> None:
        if now - self._zones_at < self.settings.geofence_reload_s:
            return
        from iotnav.service.alerts_delivery import zones_of_areas
        from iotnav.service.store import geofences

        self._zones_at = now
        zones, skipped = zones_of_areas(list(conn.execute(sa.select(geofences.c.name, geofences.c.area))))
        self.rules.set_zones(zones)
        self.counts["alerts_geofences_skipped"] = skipped

    def _items(
        self, conn: Connection, devs: Sequence[int], pos_where: Any, ev_where: Any
    ) -> list[tuple[float, int, int, Any]]:
        """Positions and engine events of ``devs`` (in device-time order), as the service reads
        them; no positions when ``pos_where`` is None."""
        from iotnav.service import alerts_delivery as ad
        from iotnav.service.store import events

        p, q = ad.positions_query(self.engine_name)
        rows: Sequence[Any] = []
        if pos_where is not None:
            where = sa.and_(p.c.device_id.in_(devs), ad.rules_stream(p, self.engine_name), pos_where(p))
            rows = conn.execute(q.where(where).order_by(p.c.id)).all()
        evq = sa.select(
            events.c.id, events.c.device_id, events.c.type, events.c.event_time, events.c.attributes
        ).where(events.c.device_id.in_(devs), events.c.type.in_(ad.ENGINE_EVENTS), ev_where(events))
        evs = conn.execute(evq.order_by(events.c.id)).all()
        items: list[tuple[float, int, int, Any]] = []
        for row in rows:
            items.append((row.fix_time, 1, row.device_id, (row.id, ad.position_of_row(row))))
        for e in evs:
            items.append((e.event_time, 0, e.device_id, (e.id, (e.type, e.event_time, e.attributes or {}))))
        items.sort(key=lambda x: (x[0], x[1]))
        return items

    def _feed(self, uid: str, group: str, item: Any) -> list[Any]:
        from iotnav.alerts import Position

        if isinstance(item, Position):
            return self.rules.position(uid, group, item)
        return self.rules.event(uid, group, item[0], item[1], item[2])

    def _rebuild(self, conn: Connection, new: dict[int, tuple[str, str]], floors: tuple[int, int]) -> None:
        """The rule state of the devices ``new`` (id -> unique id, group) from their rows up to
        ``floors``, the last ``lookback_s`` of each (alerts discarded); three queries in all."""
        from iotnav.service.alerts_delivery import rules_stream
        from iotnav.service.store import positions

        q = (
            sa.select(positions.c.device_id, sa.func.max(positions.c.fix_time))
            .where(
                positions.c.device_id.in_(list(new)),
                rules_stream(positions, self.engine_name),
                positions.c.id <= floors[0],
            )
            .group_by(positions.c.device_id)
        )
        t0 = {int(d): float(t) - self.lookback_s for d, t in conn.execute(q) if t is not None}
        if t0:
            counts = dict(self.rules.counts)
            lo = min(t0.values())
            items = self._items(
                conn,
                list(t0),
                lambda p: sa.and_(p.c.id <= floors[0], p.c.fix_time >= lo),
                lambda e: sa.and_(e.c.id <= floors[1], e.c.event_time >= lo),
            )
            n = 0
            for t, _, dev, (_, item) in items:
                if t >= t0[dev]:
                    uid, group = new[dev]
                    self._feed(uid, group, item)
                    n += 1
            self.rules.counts = counts
            self._count("alerts_rebuilt_positions", n)
        for dev in new:
            self._wm[dev] = floors

    def evaluate(
        self,
        conn: Connection,
        msgs: Sequence[Message],
        floors: tuple[int, int] | None,
        now: float,
        notify: Sequence[tuple[str, list[dict[str, Any]]]] = (),
    ) -> None:
        """Evaluate what this transaction stored for ``msgs``' devices (``notify``: the position
        rows the ingest hands its listeners); stage the alerts."""
        from iotnav.service.store import devices

        self._reload_zones(conn, now)
        uids = sorted({m.device for m in msgs})
        q = sa.select(devices.c.id, devices.c.unique_id, devices.c.attributes).where(
            devices.c.unique_id.in_(uids)
        )
        groups: dict[int, tuple[str, str]] = {}
        for d in conn.execute(q):
            group = (d.attributes or {}).get("group")
            groups[int(d.id)] = (str(d.unique_id), str(group) if group else self.settings.default_group)
        if not groups:
            return
        self._touched.update(groups)
        for dev, (uid, _) in groups.items():
            self._uid[dev] = uid
        new = {dev: g for dev, g in groups.items() if dev not in self._wm}
        if new:
            assert floors is not None  # a device new here has a unique id not known before
            self._rebuild(conn, new, floors)
        # the positions this transaction stored: the rows the ingest hands its listeners (no
        # read-back); the engine events (few) read back by id
        from iotnav.service.alerts_delivery import stored_position

        sent: dict[tuple[str, str], dict[str, Any]] = {
            (m.device, f.key): f.attributes for m in msgs for f in m.fixes
        }
        items: list[tuple[float, int, int, Any]] = []
        for _, rows in notify:
            for r in rows:
                dev = int(r["device_id"])
                if dev not in groups:
                    continue
                attrs: dict[str, Any] = r.get("attributes") or {}
                raw = sent.get((groups[dev][0], str(r.get("dedup_key"))), attrs)
                pos = stored_position(
                    r["fix_time"],
                    r["latitude"],
                    r["longitude"],
                    r.get("speed_mps"),
                    r.get("accuracy_m"),
                    r["server_time"],
                    attrs,
                    raw,
                )
                items.append((pos.t, 1, dev, (0, pos)))
        wm_ev = min(self._wm[d][1] for d in groups)
        for item in self._items(conn, list(groups), None, lambda e: e.c.id > wm_ev):
            items.append(item)
        items.sort(key=lambda x: (x[0], x[1]))
        for _, kind, dev, (rid, item) in items:
            wp, we = self._wm[dev]
            if kind == 0:
                if rid <= we:
                    continue  # read before (another device's watermark is lower)
                self._wm[dev] = (wp, max(we, rid))
            uid, group = groups[dev]
            for a in self._feed(uid, group, item):
                self._store(conn, a, dev, now)

    def tick(self, db: sa.engine.Engine, now: float) -> None:
        """The clock rules (``silent``, ``stop`` at a tick) of the devices seen here; staged."""
        with db.begin() as conn:
            found = self.rules.tick(now)
            ids = {u: d for d, u in self._uid.items()}
            for a in found:
                if a.device in ids:
                    self._touched.add(ids[a.device])
                    self._store(conn, a, ids[a.device], now)

    def _store(self, conn: Connection, a: Any, dev: int, now: float) -> None:
        """Store alert ``a`` of ``dev`` unless its key is stored; stage it for delivery."""
        from iotnav.service.alerts_delivery import _iso
        from iotnav.service.ingest import clean_json
        from iotnav.service.store import events, inserted_id

        anchor = _anchor(a)
        key = alert_key(a.device, a.kind, anchor, str(a.detail.get("zone", "")))
        etype = f"alert_{a.kind}"
        dup = conn.execute(
            sa.select(events.c.id).where(
                events.c.device_id == dev,
                events.c.type == etype,
                events.c.event_time >= anchor,
                events.c.attributes["key"].as_string() == key,
            )
        ).first()
        if dup is not None:
            self._count("alerts_duplicate_key")
            return
        lat = a.lat_deg if math.isfinite(a.lat_deg) else None
        lon = a.lon_deg if math.isfinite(a.lon_deg) else None
        detail = clean_json(dict(a.detail))
        attrs = {"kind": a.kind, "group": a.group, "latitude": lat, "longitude": lon, **detail}
        attrs |= {"key": key, "delivery": "pending"}
        eid = inserted_id(
            conn.execute(
                events.insert().values(
                    device_id=dev, type=etype, event_time=a.t, server_time=now, attributes=attrs
                )
            )
        )
        self._count(f"alerts_{a.kind}")
        self._staged.append(
            {
                "id": eid,
                "type": etype,
                "kind": a.kind,
                "deviceId": dev,
                "uniqueId": a.device,
                "group": a.group,
                "eventTime": _iso(a.t),
                "latitude": lat,
                "longitude": lon,
                "attributes": detail,
            }
        )

    # --- after the transaction ------------------------------------------------------------

    def committed(self) -> None:
        """The transaction committed: its alerts are ready to deliver."""
        self._ready += self._staged
        self._staged = []
        self._known.update(self._uid[d] for d in self._touched if d in self._wm)
        self._touched.clear()

    def rolled_back(self) -> None:
        """The transaction rolled back: forget what it changed (rebuilt from the database)."""
        for dev in self._touched:
            self._wm.pop(dev, None)
            uid = self._uid.pop(dev, None)
            if uid is not None:
                self.rules.devices.pop(uid, None)
                self._known.discard(uid)
        self._staged = []
        self._touched.clear()

    def take(self) -> list[dict[str, Any]]:
        """The committed alerts not yet handed out (to deliver)."""
        out, self._ready = self._ready, []
        return out

    def pending(
        self, db: sa.engine.Engine, partition: int, partitions: int, now: float, window_s: float
    ) -> list[dict[str, Any]]:
        """Alerts of the partition's devices stored within ``window_s`` whose delivery has not
        ended (a previous owner stopped before): to deliver again, with their stored ``id``."""
        from iotnav.service.alerts_delivery import _iso
        from iotnav.service.store import devices, events

        q = (
            sa.select(events, devices.c.unique_id)
            .select_from(events.join(devices, devices.c.id == events.c.device_id))
            .where(
                events.c.type.like("alert\\_%", escape="\\"),
                events.c.server_time >= now - window_s,
                events.c.attributes["delivery"].as_string() == "pending",
            )
            .order_by(events.c.id)
        )
        out = []
        with db.connect() as conn:
            for r in conn.execute(q):
                if partition_of(r.unique_id, partitions) != partition:
                    continue
                attrs = dict(r.attributes or {})
                detail = {
                    k: v
                    for k, v in attrs.items()
                    if k not in ("kind", "group", "latitude", "longitude", "key", "delivery")
                }
                out.append(
                    {
                        "id": r.id,
                        "type": r.type,
                        "kind": attrs.get("kind", r.type[6:]),
                        "deviceId": r.device_id,
                        "uniqueId": r.unique_id,
                        "group": attrs.get("group"),
                        "eventTime": _iso(r.event_time),
                        "latitude": attrs.get("latitude"),
                        "longitude": attrs.get("longitude"),
                        "attributes": detail,
                    }
                )
        return out


def mark_delivered(db: sa.engine.Engine, event_id: int, delivered: bool) -> None:
    """Record that the delivery of stored alert ``event_id`` has ended (``delivered`` or ``given_up``)."""
    from iotnav.service.store import events

    with db.begin() as conn:
        attrs = conn.execute(sa.select(events.c.attributes).where(events.c.id == event_id)).scalar()
        if attrs is None:
            return
        attrs = {**attrs, "delivery": "delivered" if delivered else "given_up"}
        conn.execute(events.update().where(events.c.id == event_id).values(attributes=attrs))


class AlertingIngestor(Ingestor):
    """The ingest of one partition with its alerts evaluated in each transaction
    (:class:`PartitionAlerts`). It overrides the two private transaction methods of
    :class:`~iotnav.service.ingest.Ingestor` (the hook is there, nothing else changes)."""

    def __init__(self, *args: Any, alert_settings: Any, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        self.alerts = PartitionAlerts(alert_settings, self.engine_name)

    def _store(self, conn: Connection, msgs: Sequence[Message], touched: set[int]) -> Any:
        floors = self.alerts.floors(conn, msgs)
        out = super()._store(conn, msgs, touched)
        self.alerts.evaluate(conn, msgs, floors, time.time(), out[1])
        return out

    def _transaction(self, msgs: Sequence[Message]) -> list[IngestResult]:
        try:
            out = super()._transaction(msgs)
        except BaseException:
            self.alerts.rolled_back()
            raise
        self.alerts.committed()
        return out


class WorkerAlerts:
    """Delivery of a worker's alerts (the service's :class:`~iotnav.service.alerts_delivery.AlertService`
    without its polling): the WebSocket of every edge (``{"events": [alert]}`` on the live
    subject, at most once), MQTT and the webhook; a delivery that has ended is recorded in the
    stored alert (``delivery``: ``delivered`` / ``given_up``), so that an alert still
    ``pending`` when its worker died is delivered again by the partition's next owner.

    Parameters
    ----------
    settings : iotnav.service.alerts_delivery.AlertSettings
    db : sqlalchemy.engine.Engine
    counter : Ingestor
        Holds the delivery counters (``alerts_webhook_*``, ``alerts_mqtt_*``).
    redeliver_window_s : float
        Pending alerts stored within this long are delivered again by a new owner, s.
    """

    def __init__(
        self, settings: Any, db: sa.engine.Engine, counter: Ingestor, redeliver_window_s: float = 86400.0
    ) -> None:
        self.settings = settings
        self.db = db
        self.counter = counter
        self.redeliver_window_s = redeliver_window_s
        self.service: Any = None
        self._marks: set[asyncio.Future[None]] = set()

    def start(self, socket_send: Callable[[dict[str, Any]], None] | None, worker_id: str = "") -> None:
        """Connect MQTT and the webhook client (in the running event loop). The MQTT client id
        is ``mqtt_client_id-<worker_id>``: a broker disconnects a client whose id another
        client takes, and every worker publishes."""
        from iotnav.service.alerts_delivery import AlertService

        settings = self.settings
        if worker_id:
            settings = dataclasses.replace(settings, mqtt_client_id=f"{settings.mqtt_client_id}-{worker_id}")
        self.service = AlertService(settings, self.db, self.counter, self.counter.executor, socket_send)
        self.service.start(poll=False)

    def deliver(self, alert: dict[str, Any]) -> None:
        """Deliver ``alert`` (a stored one: its ``id`` is the receivers' de-duplication key)."""
        eid = int(alert["id"])

        def done(delivered: bool) -> None:
            task = asyncio.ensure_future(asyncio.to_thread(self._mark, eid, delivered))
            self._marks.add(task)
            task.add_done_callback(self._marks.discard)

        self.service.deliver(alert, done)

    def _mark(self, eid: int, delivered: bool) -> None:
        try:
            mark_delivered(self.db, eid, delivered)
        except Exception:  # the database away: the next owner may deliver it again (same id)
            log.exception("alerts: recording the delivery of alert %d failed", eid)

    async def stop(self) -> None:
        """Give pending webhook deliveries their time (as the service does), then disconnect."""
        if self.service is not None:
            await self.service.stop()
        if self._marks:
            await asyncio.gather(*self._marks, return_exceptions=True)


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
