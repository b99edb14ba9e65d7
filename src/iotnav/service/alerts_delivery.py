"""Alerts in ``iotnav serve``: the rules of :mod:`iotnav.alerts` on the stored stream, and delivery.

How it runs
-----------
:class:`AlertService` reads what the ingest has *committed*: the positions of the engine in
use (joined with the fix as sent, for the device's ``ignition`` flag; for a device sending raw
GNSS + IMU batches, the clean positions of its IMU engine instead, :func:`rules_stream`) and the engine events
``fix_rejected`` / ``moved_while_off``, by increasing row id, every ``poll_interval_s``, on the
service's database thread (so it sees commits in order and writes with the single writer).
It feeds them to one :class:`iotnav.alerts.AlertEngine`, ticks it with the server clock,
stores each alert in ``events`` (type ``alert_<kind>``, with the alert in ``attributes``) in
the same transaction (alerts whose storing failed, the database away, are stored at the next
poll), then delivers it: on the API's WebSocket (``{"events": [alert]}``), to a
webhook and to an MQTT topic. It reads the database only, so it does not depend on how the
positions got there. It starts at the rows present when the service starts (nothing earlier
is evaluated again) and its rule state is in memory: after a restart a device's first
position sets its zone states without alerts, a device silent since before the restart is
not reported until it has reported once, and a webhook delivery still being retried at
shutdown is not resumed (the alert stays in ``events``). The tail by id assumes rows
committed in id order: the service's one database thread, or on SQLite any number of
writing processes (``serve --processes N``: each holds the database's one write lock from
its first insert to its commit, so no row becomes visible after a row with a larger id);
not several writers on PostgreSQL, whose workers raise the alerts themselves
(:mod:`iotnav.service.workers`).

Devices and groups: a device's group is its attribute ``group`` (``PUT /api/devices/{id}``
with ``{"attributes": {"group": "trucks"}}``); devices of a group without rules take the
``default`` group's. Geofences: the service's ``geofences`` table (Traccar areas; circles and
polygons; a ``LINESTRING`` is not a zone and is skipped, counted), re-read every
``geofence_reload_s``. Counters (``alerts_*``) show in ``GET /api/server``.

Configuration (``[alerts]`` table; ``serve``'s ``alerts`` setting names the TOML file)::

    [alerts]
    webhook_url = "https://example.org/iotnav-hook"
    # webhook_secret: or the environment variable IOTNAV_ALERTS_WEBHOOK_SECRET
    webhook_attempts = 6          # first try + 5 retries
    webhook_backoff_s = 1.0       # 1, 2, 4, 8, 16 s between tries (capped at webhook_backoff_max_s)
    mqtt = "mqtt://127.0.0.1:1883"
    mqtt_topic = "iotnav/alerts"  # published to iotnav/alerts/<deviceId>/<kind>, QoS 1

    [alerts.groups.default]
    geofences = true              # every zone (or a list of zone names)
    overspeed_kmh = 120
    overspeed_min_duration_s = 10
    stop_minutes = 30
    silent_minutes = 60
    moved_while_off_m = 100
    gnss_jump = true

    [alerts.groups.trucks]
    overspeed_kmh = 80

The alert (webhook body, MQTT payload, WebSocket ``events`` item)::

    {"id": 42, "type": "alert_geofence_enter", "kind": "geofence_enter", "deviceId": 3,
     "uniqueId": "353201350896384", "group": "default", "eventTime": "2026-12-02T01:00:00.000Z",
     "latitude": 48.0001, "longitude": 16.0002, "attributes": {"zone": "depot", "border_m": -7.9}}

``id`` is the row of ``events`` (the same in every retry: receivers de-duplicate on it);
``eventTime`` the device time the rule fired (the server clock for ``silent``).

Webhook deliveries (as GitHub's and Stripe's webhooks are documented)
--------------------------------------------------------------------
``POST webhook_url`` with the alert as a JSON body and the headers

``Content-Type: application/json``; ``User-Agent: iotnav-alerts``;
``X-Iotnav-Event: <kind>``; ``X-Iotnav-Delivery: <id>``; ``Idempotency-Key: <id>`` (the same
value, under the name of the IETF draft ``draft-ietf-httpapi-idempotency-key-header``);
``X-Iotnav-Signature: t=<unix seconds>,v1=<hex>``, where ``<hex>`` is the lowercase hex
HMAC-SHA256, keyed with the shared secret (UTF-8), of the ASCII timestamp, a ``.``, and the
raw body bytes: ``HMAC_SHA256(secret, "<t>." + body)``.

To verify (:func:`verify_signature`): split the header on ``,`` into ``t`` and ``v1``; compute
the HMAC over ``t``, ``.`` and the body *as received* (before any JSON parsing); compare in
constant time; reject a ``t`` more than 300 s from your clock (a replayed delivery). Every
attempt is signed afresh with its own ``t``.

A 2xx answer is a delivery. A connection error, a timeout, 408, 429 or a 5xx is retried
after ``webhook_backoff_s * 2^(k-1)`` s (the ``Retry-After`` seconds of a 429 / 503 when
longer, both capped at ``webhook_backoff_max_s``), up to ``webhook_attempts`` tries in all;
any other answer (a 4xx: the receiver refuses it) ends the delivery. A delivery given up is
logged and counted (``alerts_webhook_failed``). Deliveries run concurrently: receivers
should not rely on their order (use ``eventTime``). The defaults (6 tries, 1 s doubling: the
last try 31 s after the first; 10 s per try) are a choice, not a published figure: they ride
out a receiver's restart or a proxy's brief 502 without holding alerts for long; Stripe
retries for days, GitHub not at all, and a receiver down for longer finds the alerts in
``events``.

Scale: each poll reads at most 5000 positions and 5000 events, and each tick visits every
device the rules know (Python, about a microsecond each): enough for thousands of devices on
one service, not for the 100,000 of issue 19's scaling part.
"""

from __future__ import annotations

import asyncio
import dataclasses
import hashlib
import hmac
import json
import logging
import math
import os
import time
import tomllib
from collections.abc import Callable
from concurrent.futures import Executor
from dataclasses import dataclass, field
from datetime import UTC, datetime
from pathlib import Path
from typing import Any
from urllib.parse import urlparse

import numpy as np
import sqlalchemy as sa
from sqlalchemy.engine import Connection, Engine

from iotnav.alerts import Alert, AlertEngine, AlertRules, Position, groups_from_dict
from iotnav.service.geofence import parse_area
from iotnav.service.ingest import NO_ENGINE, Ingestor, clean_json
from iotnav.service.protocols.iotnav_raw import PROTOCOL as RAW_PROTOCOL
from iotnav.service.store import devices, events, geofences, inserted_id, positions, raw_messages
from iotnav.tracker import Zone

log = logging.getLogger("iotnav.service.alerts")

SIGNATURE_HEADER = "X-Iotnav-Signature"
SECRET_ENV = "IOTNAV_ALERTS_WEBHOOK_SECRET"
ENGINE_EVENTS = ("fix_rejected", "moved_while_off")
"""Engine event types the rules read."""
SKIPS = ("out_of_order", "nonfinite", "no_rules")
"""Counters of :class:`iotnav.alerts.AlertEngine` shown as ``alerts_skipped_<reason>``."""


@dataclass(frozen=True)
class AlertSettings:
    """The ``[alerts]`` table (module docstring).

    Attributes
    ----------
    groups : dict
        Rules per device group (:func:`iotnav.alerts.groups_from_dict`).
    webhook_url, webhook_secret : str
        Receiver and shared HMAC secret (a webhook needs one; ``IOTNAV_ALERTS_WEBHOOK_SECRET``).
    webhook_attempts : int
        Tries per alert, the first included.
    webhook_backoff_s, webhook_backoff_max_s : float
        First delay between tries and the cap of the doubling delays, s.
    webhook_timeout_s : float
        Time allowed per try, s.
    mqtt, mqtt_topic, mqtt_client_id : str
        Broker URL (``mqtt://host:port``; empty: no MQTT), topic prefix, client id.
    poll_interval_s : float
        How often committed rows are read, s.
    geofence_reload_s : float
        How often the geofences table is re-read, s.
    default_group : str
        Group of devices whose own has no rules.
    """

    groups: dict[str, AlertRules] = field(default_factory=dict)
    webhook_url: str = ""
    webhook_secret: str = ""
    webhook_attempts: int = 6
    webhook_backoff_s: float = 1.0
    webhook_backoff_max_s: float = 60.0
    webhook_timeout_s: float = 10.0
    mqtt: str = ""
    mqtt_topic: str = "iotnav/alerts"
    mqtt_client_id: str = "iotnav-alerts"
    poll_interval_s: float = 0.5
    geofence_reload_s: float = 10.0
    default_group: str = "default"

    @classmethod
    def load(cls, source: str | Path | dict[str, Any]) -> AlertSettings:
        """Settings from a TOML file's ``[alerts]`` table (or the table itself); ValueError names bad keys."""
        if isinstance(source, dict):
            table, where = source, "alerts"
        else:
            with open(source, "rb") as fh:
                doc = tomllib.load(fh)
            if "alerts" not in doc:
                raise ValueError(f"{source}: no [alerts] table")
            table, where = doc["alerts"], f"{source}: alerts"
        names = {f.name for f in dataclasses.fields(cls)}
        unknown = sorted(set(table) - names)
        if unknown:
            raise ValueError(
                f"{where}: unknown setting(s) {', '.join(unknown)}; expected {', '.join(sorted(names))}"
            )
        values = dict(table)
        values["groups"] = groups_from_dict(dict(table.get("groups", {})), f"{where}.groups")
        if not values.get("webhook_secret"):
            values["webhook_secret"] = os.environ.get(SECRET_ENV, "")
        out = cls(**values)
        if out.webhook_url and not out.webhook_secret:
            raise ValueError(
                f"{where}: webhook_url needs webhook_secret (or {SECRET_ENV}) to sign deliveries"
            )
        if out.webhook_url and urlparse(out.webhook_url).scheme not in ("http", "https"):
            raise ValueError(f"{where}: webhook_url {out.webhook_url!r}: expected http(s)://...")
        if out.webhook_attempts < 1:
            raise ValueError(f"{where}: webhook_attempts must be at least 1")
        u = urlparse(out.mqtt)
        if out.mqtt and (u.scheme not in ("mqtt", "tcp") or not u.hostname):
            raise ValueError(f"{where}: mqtt {out.mqtt!r}: expected mqtt://host[:port]")
        return out


def sign(secret: str, body: bytes, t: int) -> str:
    """The ``X-Iotnav-Signature`` value of ``body`` at Unix time ``t`` (module docstring)."""
    mac = hmac.new(secret.encode(), str(t).encode() + b"." + body, hashlib.sha256).hexdigest()
    return f"t={t},v1={mac}"


def verify_signature(secret: str, header: str, body: bytes, now: float, tolerance_s: float = 300.0) -> bool:
    """True when ``header`` signs ``body`` with ``secret`` at a time within ``tolerance_s`` of ``now``."""
    parts = dict(p.split("=", 1) for p in header.split(",") if "=" in p)
    try:
        t = int(parts["t"])
    except (KeyError, ValueError):
        return False
    if abs(now - t) > tolerance_s:
        return False
    return hmac.compare_digest(sign(secret, body, t), f"t={t},v1={parts.get('v1', '')}")


def _iso(t: float) -> str | None:
    if not math.isfinite(t):
        return None
    return datetime.fromtimestamp(t, UTC).isoformat(timespec="milliseconds").replace("+00:00", "Z")


def _flag(v: Any) -> bool | None:
    """A device's on/off attribute (Teltonika 0/1, OsmAnd ``true``/``false``); None when absent."""
    if isinstance(v, bool):
        return v
    if isinstance(v, int | float) and math.isfinite(v):
        return v != 0
    if isinstance(v, str) and v.strip().lower() in ("1", "true", "on", "0", "false", "off"):
        return v.strip().lower() in ("1", "true", "on")
    return None


def stored_position(
    fix_time: float,
    latitude: float,
    longitude: float,
    speed_mps: float | None,
    accuracy_m: float | None,
    server_time: float,
    attributes: dict[str, Any] | None,
    raw: dict[str, Any] | None,
) -> Position:
    """The rules' :class:`~iotnav.alerts.Position` of a stored position row.

    ``attributes`` are the row's own (its ``static`` flag), ``raw`` those of the fix as the device
    sent it (its ``ignition`` flag); ``accuracy_m`` is the 2-D RMS radius, so the per-axis sigma is
    ``accuracy / sqrt(2)``. Times in s (Unix), degrees, m/s.
    """
    return Position(
        t=float(fix_time),
        lat_deg=float(latitude),
        lon_deg=float(longitude),
        speed_mps=float(speed_mps) if speed_mps is not None else math.nan,
        sigma_m=float(accuracy_m) / math.sqrt(2.0) if accuracy_m is not None else math.nan,
        static=bool((attributes or {}).get("static", False)),
        ignition=_flag((raw or {}).get("ignition")),
        received_at=float(server_time),
    )


def positions_query(engine: str) -> tuple[Any, Any]:
    """The positions of ``engine`` with the attributes of the fix as sent (column ``raw``).

    Returns the alias ``p`` of the positions table (to add conditions on) and the select. For an
    engine other than the raw one (``NO_ENGINE``) the device's flags are in the stored raw fix of
    the same key, joined in.
    """
    p = positions.alias("p")
    cols = [p.c.id, p.c.device_id, p.c.fix_time, p.c.server_time, p.c.latitude, p.c.longitude]
    cols += [p.c.speed_mps, p.c.accuracy_m, p.c.attributes]
    if engine == NO_ENGINE:
        return p, sa.select(*cols, p.c.attributes.label("raw"))
    sent = positions.alias("sent")
    on = sa.and_(
        sent.c.device_id == p.c.device_id,
        sent.c.engine == NO_ENGINE,
        sent.c.dedup_key == p.c.dedup_key,
    )
    return p, sa.select(*cols, sent.c.attributes.label("raw")).select_from(p.outerjoin(sent, on))


def rules_stream(p: Any, engine: str) -> Any:
    """The condition on positions ``p`` (the table or an alias) of the one stream the rules read.

    A position of a raw GNSS + IMU batch (its message's protocol ``iotnav_raw``) is read when
    it is a clean position of the device's IMU engine (``engine`` other than ``none``; not the
    batch's fixes as sent); any other position when its ``engine`` is ``engine`` (the engine
    of the fix-only devices). So a raw device is read on its engine's positions only, even
    when ``engine`` is ``none``: its zone states do not flip between two streams.
    """
    m = raw_messages.alias("m")
    from_raw = sa.exists().where(m.c.id == p.c.raw_id, m.c.protocol == RAW_PROTOCOL)
    return sa.or_(sa.and_(p.c.engine == engine, ~from_raw), sa.and_(p.c.engine != NO_ENGINE, from_raw))


def position_of_row(row: Any) -> Position:
    """:func:`stored_position` of a row of :func:`positions_query`."""
    return stored_position(
        row.fix_time,
        row.latitude,
        row.longitude,
        row.speed_mps,
        row.accuracy_m,
        row.server_time,
        row.attributes,
        row.raw,
    )


def zones_of_areas(rows: list[tuple[str, str]]) -> tuple[list[Zone], int]:
    """Zones of ``(name, Traccar area)`` rows; and how many rows are not zones (lines, bad text)."""
    zones, skipped = [], 0
    for name, text in rows:
        try:
            area = parse_area(text)
        except ValueError:
            skipped += 1
            continue
        if area.kind == "circle":
            zones.append(Zone(name, center=area.points[0], radius_m=area.radius_m))
        elif area.kind == "polygon":
            pts = list(area.points)
            if pts[0] == pts[-1]:
                pts = pts[:-1]
            ring = [[lon, lat] for lat, lon in pts]
            zones.append(Zone(name, polygons=((np.asarray(ring, dtype=float),),)))
        else:
            skipped += 1
    return zones, skipped


class AlertService:
    """The alert rules on the service's committed rows, and their delivery (module docstring).

    Parameters
    ----------
    settings : AlertSettings
    db : sqlalchemy.engine.Engine
        The service database.
    ingestor : Ingestor
        For the engine in use and the counters.
    executor : Executor
        The service's database thread.
    socket_send : callable, optional
        Sends a message to every open ``/api/socket`` (from any thread).
    """

    def __init__(
        self,
        settings: AlertSettings,
        db: Engine,
        ingestor: Ingestor,
        executor: Executor,
        socket_send: Callable[[dict[str, Any]], None] | None = None,
    ) -> None:
        self.settings = settings
        self.db = db
        self.ingestor = ingestor
        self.executor = executor
        self.socket_send = socket_send
        self.rules = AlertEngine(settings.groups, default_group=settings.default_group)
        self._wm: tuple[int, int] | None = None
        self._ids: dict[str, int] = {}
        self._unsaved: list[tuple[Alert, int]] = []
        self._zones_at = -math.inf
        self._task: asyncio.Task[None] | None = None
        self._deliveries: set[asyncio.Task[None]] = set()
        self._mqtt: Any = None
        self._http: Any = None

    # --- reading, evaluating, storing (database thread) ----------------------------------

    def pump(self, now: float) -> list[dict[str, Any]]:
        """Evaluate the rows committed since the last call and the clock ``now``; store the
        alerts in ``events`` and return them as delivered (module docstring)."""
        with self.db.begin() as conn:
            if self._wm is None:
                self._wm = (
                    int(
                        conn.execute(sa.select(sa.func.coalesce(sa.func.max(positions.c.id), 0))).scalar_one()
                    ),
                    int(conn.execute(sa.select(sa.func.coalesce(sa.func.max(events.c.id), 0))).scalar_one()),
                )
            if now - self._zones_at >= self.settings.geofence_reload_s:
                self._zones_at = now
                zones, skipped = zones_of_areas(
                    list(conn.execute(sa.select(geofences.c.name, geofences.c.area)))
                )
                self.rules.set_zones(zones)
                self.ingestor.counts["alerts_geofences_skipped"] = skipped
            items = self._read(conn)
            devs = self._devices(conn, {d for _, _, d, _ in items}) if items else {}
            found: list[tuple[Alert, int]] = []
            for _, _, dev, item in items:
                unique, group = devs.get(dev, (str(dev), self.settings.default_group))
                if isinstance(item, Position):
                    got = self.rules.position(unique, group, item)
                else:
                    got = self.rules.event(unique, group, item[0], item[1], item[2])
                found += [(a, dev) for a in got]
            self._ids.update({u: d for d, (u, _) in devs.items()})
            for a in self.rules.tick(now):
                found.append((a, self._ids.get(a.device, -1)))
            for what in SKIPS:  # positions the rules could not use, counted for GET /api/server
                if what in self.rules.counts:
                    self.ingestor.counts[f"alerts_skipped_{what}"] = self.rules.counts[what]
            # alerts whose storing failed last time (the rows are not read again) go first
            self._unsaved += [(a, dev) for a, dev in found if dev >= 0]
            out = [self._store(conn, a, dev, now) for a, dev in self._unsaved]
        self._unsaved = []
        return out

    def _read(self, conn: Connection) -> list[tuple[float, int, int, Any]]:
        assert self._wm is not None
        wm_pos, wm_ev = self._wm
        engine = self.ingestor.engine_name
        p, q = positions_query(engine)
        where = sa.and_(p.c.id > wm_pos, rules_stream(p, engine))
        rows = conn.execute(q.where(where).order_by(p.c.id).limit(5000)).all()
        evs = conn.execute(
            sa.select(
                events.c.id, events.c.device_id, events.c.type, events.c.event_time, events.c.attributes
            )
            .where(events.c.id > wm_ev, events.c.type.in_(ENGINE_EVENTS))
            .order_by(events.c.id)
            .limit(5000)
        ).all()
        self._wm = (max([wm_pos, *(row.id for row in rows)]), max([wm_ev, *(e.id for e in evs)]))
        items: list[tuple[float, int, int, Any]] = []
        for row in rows:
            items.append((row.fix_time, 1, row.device_id, position_of_row(row)))
        for e in evs:
            items.append((e.event_time, 0, e.device_id, (e.type, e.event_time, e.attributes or {})))
        items.sort(key=lambda x: (x[0], x[1]))
        return items

    def _devices(self, conn: Connection, ids: set[int]) -> dict[int, tuple[str, str]]:
        """Device id -> (unique id, group) of ``ids`` (read at each batch: a group change applies)."""
        q = sa.select(devices.c.id, devices.c.unique_id, devices.c.attributes)
        out = {}
        for d in conn.execute(q.where(devices.c.id.in_(ids))):
            group = (d.attributes or {}).get("group")
            out[int(d.id)] = (str(d.unique_id), str(group) if group else self.settings.default_group)
        return out

    def _store(self, conn: Connection, a: Alert, dev: int, now: float) -> dict[str, Any]:
        lat = a.lat_deg if math.isfinite(a.lat_deg) else None
        lon = a.lon_deg if math.isfinite(a.lon_deg) else None
        detail = clean_json(dict(a.detail))
        attrs = {"kind": a.kind, "group": a.group, "latitude": lat, "longitude": lon, **detail}
        eid = inserted_id(
            conn.execute(
                events.insert().values(
                    device_id=dev, type=f"alert_{a.kind}", event_time=a.t, server_time=now, attributes=attrs
                )
            )
        )
        self.ingestor.count(f"alerts_{a.kind}")
        return {
            "id": eid,
            "type": f"alert_{a.kind}",
            "kind": a.kind,
            "deviceId": dev,
            "uniqueId": a.device,
            "group": a.group,
            "eventTime": _iso(a.t),
            "latitude": lat,
            "longitude": lon,
            "attributes": detail,
        }

    # --- the loop and delivery (event loop) ----------------------------------------------

    def start(self, poll: bool = True) -> None:
        """Connect the MQTT publisher and start polling (in the running event loop).

        ``poll=False``: delivery only (:meth:`deliver`); the workers of
        :mod:`iotnav.service.workers` evaluate the rules themselves.
        """
        s = self.settings
        if s.mqtt:
            import paho.mqtt.client as mqtt

            u = urlparse(s.mqtt)  # checked by AlertSettings.load
            c = mqtt.Client(
                callback_api_version=mqtt.CallbackAPIVersion.VERSION2,
                client_id=s.mqtt_client_id,
                clean_session=False,
                protocol=mqtt.MQTTv311,
            )
            if u.username:
                c.username_pw_set(u.username, u.password)
            c.reconnect_delay_set(1, 30)
            c.connect_async(str(u.hostname), u.port or 1883, keepalive=30)
            c.loop_start()
            self._mqtt = c
        if s.webhook_url:
            import httpx

            self._http = httpx.AsyncClient(timeout=s.webhook_timeout_s)
        if poll:
            self._task = asyncio.create_task(self._run())

    @property
    def mqtt_connected(self) -> bool:
        """True when the MQTT publisher is connected (False without MQTT)."""
        return self._mqtt is not None and bool(self._mqtt.is_connected())

    async def _run(self) -> None:
        loop = asyncio.get_running_loop()
        while True:
            try:
                alerts = await loop.run_in_executor(self.executor, self.pump, time.time())
            except RuntimeError:  # the executor has shut down: the service is stopping
                return
            except Exception:  # the database may be away; the rows wait for the next poll
                self.ingestor.count("alerts_errors")
                log.exception("alerts: evaluating failed")
                alerts = []
            for a in alerts:
                self.deliver(a)
            await asyncio.sleep(self.settings.poll_interval_s)

    def deliver(self, alert: dict[str, Any], done: Callable[[bool], None] | None = None) -> None:
        """Send ``alert`` on the WebSocket and to MQTT at once, and start its webhook delivery.

        ``done(delivered)`` is called when the webhook delivery has ended (a 2xx: True; given
        up: False), at once (True) without a webhook.
        """
        if self.socket_send is not None:
            self.socket_send({"events": [alert]})
        body = json.dumps(alert, separators=(",", ":")).encode()
        if self._mqtt is not None:
            topic = f"{self.settings.mqtt_topic}/{alert['deviceId']}/{alert['kind']}"
            info = self._mqtt.publish(topic, body, qos=1)
            self.ingestor.count("alerts_mqtt_published" if info.rc == 0 else "alerts_mqtt_queued")
        if self._http is not None:
            task = asyncio.create_task(self._webhook(alert, body, done))
            self._deliveries.add(task)
            task.add_done_callback(self._deliveries.discard)
        elif done is not None:
            done(True)

    async def _webhook(
        self, alert: dict[str, Any], body: bytes, done: Callable[[bool], None] | None = None
    ) -> None:
        import httpx

        s = self.settings
        reason = ""
        for attempt in range(1, s.webhook_attempts + 1):
            headers = {
                "Content-Type": "application/json",
                "User-Agent": "iotnav-alerts",
                "X-Iotnav-Event": str(alert["kind"]),
                "X-Iotnav-Delivery": str(alert["id"]),
                "Idempotency-Key": str(alert["id"]),
                SIGNATURE_HEADER: sign(s.webhook_secret, body, int(time.time())),
            }
            wait = min(s.webhook_backoff_s * 2.0 ** (attempt - 1), s.webhook_backoff_max_s)
            try:
                r = await self._http.post(s.webhook_url, content=body, headers=headers)
            except httpx.HTTPError as exc:
                reason = f"{type(exc).__name__}: {exc}"
            else:
                if 200 <= r.status_code < 300:
                    self.ingestor.count("alerts_webhook_delivered")
                    if done is not None:
                        done(True)
                    return
                reason = f"HTTP {r.status_code}"
                if r.status_code < 500 and r.status_code not in (408, 429):
                    break
                after = r.headers.get("retry-after", "")
                if after.isdigit():
                    wait = min(max(wait, float(after)), s.webhook_backoff_max_s)
            if attempt < s.webhook_attempts:
                self.ingestor.count("alerts_webhook_retries")
                await asyncio.sleep(wait)
        self.ingestor.count("alerts_webhook_failed")
        log.warning("alerts: webhook gave up on alert %s (%s)", alert["id"], reason)
        if done is not None:
            done(False)

    async def stop(self) -> None:
        """Evaluate the last rows, give pending webhook deliveries ``webhook_timeout_s``, disconnect."""
        if self._task is not None:
            self._task.cancel()
            await asyncio.gather(self._task, return_exceptions=True)
            try:
                for a in await asyncio.get_running_loop().run_in_executor(
                    self.executor, self.pump, time.time()
                ):
                    self.deliver(a)
            except Exception:
                log.exception("alerts: the last evaluation failed")
        if self._deliveries:
            await asyncio.wait(set(self._deliveries), timeout=self.settings.webhook_timeout_s)
            for t in self._deliveries:
                t.cancel()
        if self._http is not None:
            await self._http.aclose()
        if self._mqtt is not None:
            self._mqtt.disconnect()
            self._mqtt.loop_stop()


def start_alerts(
    source: str | dict[str, Any],
    db: Engine,
    ingestor: Ingestor,
    executor: Executor,
    socket_send: Callable[[dict[str, Any]], None] | None = None,
) -> AlertService:
    """The :class:`AlertService` of ``serve``'s ``alerts`` setting (a TOML path or the table), started."""
    service = AlertService(AlertSettings.load(source), db, ingestor, executor, socket_send)
    service.start()
    log.warning(
        "alerts: groups %s; webhook %s; mqtt %s",
        ", ".join(service.settings.groups) or "(none)",
        service.settings.webhook_url or "-",
        service.settings.mqtt or "-",
    )
    return service


__all__ = ["SIGNATURE_HEADER", "AlertService", "AlertSettings", "sign", "start_alerts", "verify_signature"]
