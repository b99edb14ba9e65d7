"""Storing decoded messages and running one engine per device on them.

:meth:`Ingestor.ingest` stores one message in one transaction: the raw message (as
received, de-duplicated by a digest of device id and bytes), its fixes as positions flagged
``engine = 'none'`` (de-duplicated per record), and what the device's engine makes of them
(positions flagged with the engine's name, and its events). Only when the transaction has
committed does the caller answer the device (the Teltonika ACK, the HTTP 200), so an
acknowledged record is on disk (SQLite ``synchronous=FULL``) and a resent one is stored once.

Processing: one engine per device (:func:`iotnav.engines.registry.make_engine` by name),
fed its fixes in device-time order through the engines' streaming ``step()``: fixes wait
``reorder_window_s`` (device time, behind the device's newest fix) so that messages arriving
out of order within the window are re-ordered. A fix older than the last one fed to that
device's engine is stored (``engine = 'none'``) but not fed, and a ``late_fix`` event is
written. An engine name that is not available in this installation (``fixes``
before issue 10's engine lands) falls back to ``none``: fixes are stored as sent and the
service says so at start (:attr:`Ingestor.engine_name`).

Engine state lives in memory: after a restart each device's engine starts afresh (state
checkpointing is not implemented yet). An engine whose ``step()`` raises is logged, counted
(``engine_error``, and an event) and replaced by a fresh one; the message is still stored
and acknowledged, so an engine bug cannot block a device's stream.

All methods are synchronous and meant to run on one worker thread (the transports hand
them to a single-thread executor), which serialises the writers.
"""

from __future__ import annotations

import hashlib
import heapq
import logging
import math
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import sqlalchemy as sa
from sqlalchemy.engine import Connection, Engine

from iotnav.service.protocols.common import Fix
from iotnav.service.store import devices, events, inserted_id, positions, raw_messages

if TYPE_CHECKING:  # the engines (numba, scipy) load only when an engine runs
    from iotnav.engines.base import Engine as NavEngine
    from iotnav.engines.base import GnssSample, Output

log = logging.getLogger("iotnav.service")

NO_ENGINE = "none"


@dataclass(frozen=True)
class IngestResult:
    """What :meth:`Ingestor.ingest` did.

    ``accepted`` False: unknown device while registration is closed (nothing stored);
    ``duplicate``: the same message was stored before; ``n_new``: positions newly stored
    (``engine = 'none'``); ``n_engine``: engine positions stored.
    """

    accepted: bool
    duplicate: bool = False
    n_new: int = 0
    n_engine: int = 0
    device_id: int | None = None


def clean_json(v: Any) -> Any:
    """``v`` with every non-finite float replaced by None (strict JSON)."""
    if isinstance(v, float):
        return v if math.isfinite(v) else None
    if isinstance(v, dict):
        return {str(k): clean_json(x) for k, x in v.items()}
    if isinstance(v, list | tuple):
        return [clean_json(x) for x in v]
    return v


def _none_if_nan(x: float) -> float | None:
    return x if math.isfinite(x) else None


def fix_to_sample(fix: Fix) -> GnssSample:
    """The engines' :class:`GnssSample` of a fix (device time = Unix time of the fix, s)."""
    from iotnav.engines.base import GnssSample

    course_ok = math.isfinite(fix.course_rad) and math.isfinite(fix.speed_mps)
    return GnssSample(
        t=fix.t,
        lat_deg=fix.lat_deg,
        lon_deg=fix.lon_deg,
        height_m=fix.height_m,
        hdop=fix.hdop,
        num_sv=fix.num_sv,
        speed_mps=fix.speed_mps,
        course_rad=fix.course_rad if course_ok else math.nan,
        course_valid=course_ok,
        valid=fix.valid,
        h_acc_m=fix.h_acc_m,
    )


def _engine_available(name: str) -> bool:
    if name == NO_ENGINE:
        return True
    from iotnav.engines.registry import available_engines

    return name in available_engines()


class Ingestor:
    """Stores messages and feeds each device's engine.

    Parameters
    ----------
    db : sqlalchemy.engine.Engine
        The service database (schema at head).
    engine_name : str
        Engine run on every device's fixes (``none`` to store fixes only). Falls back to
        ``none`` when not available; :attr:`engine_name` is the one in use and
        :attr:`engine_requested` the one asked for.
    registration_open : bool
        Unknown devices are created on first contact; when False they are refused.
    engine_config : str, optional
        TOML configuration of the engine.
    engine_factory : callable, optional
        Builds a device's engine instead of ``make_engine(engine_name, engine_config)``
        (any object with the :class:`iotnav.engines.base.Engine` protocol).
    reorder_window_s : float
        Fixes are held this long (in device time, behind the newest fix of the device) and fed
        to the engine in time order, so messages arriving out of order within the window are
        re-ordered; 0 feeds each message's fixes at once (sorted). Held fixes are stored
        (``engine = 'none'``) at once; only their feeding waits (and is lost at a restart).
    """

    def __init__(
        self,
        db: Engine,
        engine_name: str = "fixes",
        registration_open: bool = True,
        engine_config: str | None = None,
        engine_factory: Callable[[], NavEngine] | None = None,
        reorder_window_s: float = 0.0,
    ) -> None:
        if not reorder_window_s >= 0.0:
            raise ValueError(f"reorder_window_s {reorder_window_s}: expected >= 0 s")
        self.reorder_window_s = reorder_window_s
        self._pending: dict[int, list[tuple[float, int, Fix, int]]] = {}
        self._newest: dict[int, float] = {}
        self._seq = 0
        self.db = db
        self.engine_requested = engine_name
        self._factory = engine_factory
        available = engine_factory is not None or _engine_available(engine_name)
        self.engine_name = engine_name if available else NO_ENGINE
        if self.engine_name != engine_name:
            log.warning("engine %r is not available; fixes are stored as sent (engine 'none')", engine_name)
        self.engine_config = engine_config
        self.registration_open = registration_open
        self._engines: dict[int, NavEngine] = {}
        self._n_events: dict[int, int] = {}
        self._last_t: dict[int, float] = {}
        self.counts: dict[str, int] = {}
        #: Called after each commit with (protocol, rows of the positions stored for the engine
        #: in use), on the database thread; the API's WebSocket registers here.
        self.listeners: list[Callable[[str, list[dict[str, Any]]], None]] = []

    def count(self, what: str, n: int = 1) -> None:
        """Add ``n`` to the counter ``what`` (rejections by reason, duplicates, ...)."""
        self.counts[what] = self.counts.get(what, 0) + n

    # --- devices -------------------------------------------------------------------------

    def device_id(self, conn: Connection, unique_id: str, protocol: str | None, now: float) -> int | None:
        """Id of the device ``unique_id``, created when registration is open; None if refused."""
        row = conn.execute(
            sa.select(devices.c.id, devices.c.disabled).where(devices.c.unique_id == unique_id)
        ).first()
        if row is not None:
            return None if row.disabled else int(row.id)
        if not self.registration_open:
            return None
        res = conn.execute(
            devices.insert().values(
                unique_id=unique_id, name=unique_id, protocol=protocol, created_at=now, attributes={}
            )
        )
        return inserted_id(res)

    def device_allowed(self, unique_id: str) -> bool:
        """True when ``unique_id`` is a known, enabled device or registration is open."""
        with self.db.connect() as conn:
            row = conn.execute(sa.select(devices.c.disabled).where(devices.c.unique_id == unique_id)).first()
        return (row is None and self.registration_open) or (row is not None and not row.disabled)

    # --- retention -----------------------------------------------------------------------

    def purge(self, retention_days: float, now: float | None = None) -> dict[str, int]:
        """Delete raw messages, positions and events received more than ``retention_days`` ago.

        Returns the rows deleted per table; ``retention_days <= 0`` keeps everything.
        """
        if retention_days <= 0:
            return {}
        cutoff = (time.time() if now is None else now) - retention_days * 86400.0
        with self.db.begin() as conn:
            out = {
                "positions": conn.execute(
                    positions.delete().where(positions.c.server_time < cutoff)
                ).rowcount,
                "events": conn.execute(events.delete().where(events.c.server_time < cutoff)).rowcount,
                "raw_messages": conn.execute(
                    raw_messages.delete().where(raw_messages.c.received_at < cutoff)
                ).rowcount,
            }
        if any(out.values()):
            log.warning("retention %.1f days: deleted %s", retention_days, out)
        return out

    # --- ingest --------------------------------------------------------------------------

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
        """Store one message and its fixes in one transaction (see the module docstring).

        ``unique``: the message is new whatever its bytes (an OsmAnd request without a
        timestamp repeats its bytes for every report); otherwise a message whose device and
        bytes were stored before is a duplicate.
        """
        now = time.time() if received_at is None else received_at
        salt = repr(now).encode() if unique else b""
        digest = hashlib.sha256(device.encode("utf-8", "replace") + b"\x00" + payload + salt).hexdigest()
        with self.db.begin() as conn:
            dev = self.device_id(conn, device, protocol, now)
            if dev is None:
                self.count("device_refused")
                return IngestResult(accepted=False)
            dup = conn.execute(
                sa.select(raw_messages.c.id).where(
                    raw_messages.c.protocol == protocol, raw_messages.c.dedup_key == digest
                )
            ).first()
            if dup is not None:
                self.count("duplicate_message")
                return IngestResult(accepted=True, duplicate=True, device_id=dev)
            raw_id = inserted_id(
                conn.execute(
                    raw_messages.insert().values(
                        device_id=dev,
                        protocol=protocol,
                        received_at=now,
                        remote=remote,
                        payload=payload,
                        dedup_key=digest,
                        n_records=len(fixes),
                    )
                )
            )
            new = self._new_fixes(conn, dev, fixes)
            fix_rows = [self._row(dev, raw_id, NO_ENGINE, f, now) for f in new]
            if fix_rows:
                conn.execute(positions.insert(), fix_rows)
            engine_rows = self._process(conn, dev, raw_id, new, now) if self.engine_name != NO_ENGINE else []
            conn.execute(devices.update().where(devices.c.id == dev).values(last_update=now))
        self.count("records", len(new))
        self._notify(protocol, engine_rows if self.engine_name != NO_ENGINE else fix_rows)
        return IngestResult(accepted=True, n_new=len(new), n_engine=len(engine_rows), device_id=dev)

    def _notify(self, protocol: str, rows: list[dict[str, Any]]) -> None:
        """Hand the committed positions (rows of the engine in use) to every listener."""
        if not rows:
            return
        for listener in list(self.listeners):
            try:
                listener(protocol, rows)
            except Exception:  # a listener (a WebSocket client) must not fail the ingest
                log.exception("position listener failed")

    def _new_fixes(self, conn: Connection, dev: int, fixes: list[Fix]) -> list[Fix]:
        """The fixes of ``fixes`` not stored yet for ``dev`` (and not repeated within the message)."""
        keys = [f.key for f in fixes]
        seen: set[str] = set()
        for i in range(0, len(keys), 500):
            seen.update(
                conn.execute(
                    sa.select(positions.c.dedup_key).where(
                        positions.c.device_id == dev,
                        positions.c.engine == NO_ENGINE,
                        positions.c.dedup_key.in_(keys[i : i + 500]),
                    )
                ).scalars()
            )
        out = []
        for f in fixes:
            if f.key not in seen:
                seen.add(f.key)
                out.append(f)
        if len(out) < len(fixes):
            self.count("duplicate_record", len(fixes) - len(out))
        return out

    @staticmethod
    def _row(dev: int, raw_id: int | None, engine: str, f: Fix, now: float) -> dict[str, Any]:
        return {
            "device_id": dev,
            "raw_id": raw_id,
            "engine": engine,
            "fix_time": f.t,
            "server_time": now,
            "valid": bool(f.valid),
            "latitude": f.lat_deg,
            "longitude": f.lon_deg,
            "altitude": _none_if_nan(f.height_m),
            "speed_mps": _none_if_nan(f.speed_mps),
            "course_rad": _none_if_nan(f.course_rad),
            "accuracy_m": _none_if_nan(f.h_acc_m),
            "attributes": clean_json(
                {**f.attributes, "num_sv": f.num_sv, "hdop": f.hdop} if f.num_sv >= 0 else dict(f.attributes)
            ),
            "dedup_key": f.key,
        }

    # --- processing ----------------------------------------------------------------------

    def _engine(self, conn: Connection, dev: int) -> NavEngine:
        eng = self._engines.get(dev)
        if eng is None:
            if self._factory is not None:
                eng = self._factory()
            else:
                from iotnav.engines.registry import make_engine

                eng = make_engine(self.engine_name, self.engine_config)
            self._engines[dev] = eng
            self._n_events[dev] = len(eng.events)
            last = conn.execute(
                sa.select(sa.func.max(positions.c.fix_time)).where(
                    positions.c.device_id == dev, positions.c.engine == self.engine_name
                )
            ).scalar()
            self._last_t[dev] = -math.inf if last is None else float(last)
        return eng

    def _process(
        self, conn: Connection, dev: int, raw_id: int, fixes: list[Fix], now: float
    ) -> list[dict[str, Any]]:
        """Queue ``fixes``, feed the device's engine those out of the re-ordering window in time
        order; store its outputs and events; the engine rows stored."""
        if not fixes:
            return []
        eng = self._engine(conn, dev)
        rows, evs = [], []
        heap = self._pending.setdefault(dev, [])
        for f in fixes:
            if f.t < self._last_t[dev]:  # older than what the engine has already seen
                self.count("late_fix")
                evs.append(
                    {"type": "late_fix", "event_time": f.t, "attributes": {"last_t": self._last_t[dev]}}
                )
                continue
            self._seq += 1
            heapq.heappush(heap, (f.t, self._seq, f, raw_id))
            self._newest[dev] = max(self._newest.get(dev, -math.inf), f.t)
        release = self._newest.get(dev, -math.inf) - self.reorder_window_s
        while heap and heap[0][0] <= release:
            _, _, f, f_raw = heapq.heappop(heap)
            self._last_t[dev] = f.t
            try:
                out: Output | None = eng.step(fix_to_sample(f))
            except Exception as exc:  # an engine bug must not block the device's stream (no ACK)
                self.count("engine_error")
                log.exception("engine %s, device %d: step failed; the engine restarts", self.engine_name, dev)
                evs.append(
                    {"type": "engine_error", "event_time": f.t, "attributes": {"error": repr(exc)[:200]}}
                )
                del self._engines[dev]
                break
            if out is not None and out.source != "none" and math.isfinite(out.lat + out.lon):
                rows.append(self._output_row(dev, f_raw, f, out, now))
        new_events = eng.events[self._n_events.get(dev, 0) :] if dev in self._engines else []
        self._n_events[dev] = len(eng.events)
        for e in new_events:
            evs.append(
                {
                    "type": str(e.get("type", "engine")),
                    "event_time": float(e.get("t", now)),
                    "attributes": clean_json(dict(e)),
                }
            )
        if rows:
            conn.execute(positions.insert(), rows)
        if evs:
            conn.execute(events.insert(), [{**e, "device_id": dev, "server_time": now} for e in evs])
        return rows

    def _output_row(self, dev: int, raw_id: int, f: Fix, out: Output, now: float) -> dict[str, Any]:
        """A positions row of an engine output: speed and course from ``vn``, ``ve``; accuracy the
        2D RMS radius ``sqrt(std_north**2 + std_east**2)``, m."""
        speed = math.hypot(out.vn, out.ve)
        course = math.atan2(out.ve, out.vn) % (2 * math.pi)
        std = math.hypot(out.std_north, out.std_east)
        return {
            "device_id": dev,
            "raw_id": raw_id,
            "engine": self.engine_name,
            "fix_time": out.t,
            "server_time": now,
            "valid": True,
            "latitude": out.lat,
            "longitude": out.lon,
            "altitude": _none_if_nan(out.height),
            "speed_mps": _none_if_nan(speed),
            "course_rad": _none_if_nan(course) if math.isfinite(speed) else None,
            "accuracy_m": _none_if_nan(std),
            "attributes": clean_json({"source": out.source, "static": bool(out.static)}),
            "dedup_key": f.key,
        }
