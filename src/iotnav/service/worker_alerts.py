"""Alerts on the NATS workers: each worker's partitions' alert rules, in the batch transaction.

Moved out of :mod:`iotnav.service.workers` unchanged (which re-exports every name here):
:func:`partition_of` (the partition of a device), :func:`alert_key`, :class:`PartitionAlerts`,
:func:`mark_delivered`, :class:`AlertingIngestor` and :class:`WorkerAlerts`. The design is in
:mod:`iotnav.service.workers`' docstring.
"""

from __future__ import annotations

import asyncio
import dataclasses
import hashlib
import logging
import math
import time
import zlib
from collections.abc import Callable, Sequence
from typing import Any

import sqlalchemy as sa
from sqlalchemy.engine import Connection

from iotnav.service.ingest import Ingestor, IngestResult, Message

log = logging.getLogger("iotnav.service.workers")

__all__ = [
    "AlertingIngestor",
    "PartitionAlerts",
    "WorkerAlerts",
    "alert_key",
    "mark_delivered",
    "partition_of",
]


def partition_of(device: str, partitions: int) -> int:
    """The partition of ``device``: CRC-32 of its UTF-8 id modulo ``partitions`` (stable everywhere)."""
    return zlib.crc32(device.encode("utf-8", "replace")) % partitions


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
