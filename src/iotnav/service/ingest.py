"""Storing decoded messages and running one engine per device on them.

:meth:`Ingestor.ingest` stores one message in one transaction: the raw message (as
received, de-duplicated by a digest of device id and bytes), its fixes as positions flagged
``engine = 'none'`` (de-duplicated per record), and what the device's engine makes of them
(positions flagged with the engine's name, and its events). Only when the transaction has
committed does the caller answer the device (the Teltonika ACK, the HTTP 200), so an
acknowledged record is on disk (SQLite ``synchronous=FULL``) and a resent one is stored once.

Processing: one engine per device (:func:`iotnav.engines.registry.make_engine` by name),
fed its fixes in device-time order through the engines' streaming ``step()`` (the one batch
``iotnav run`` loops over), its outputs stored as the clean positions (``engine`` = its
name) beside the fixes as sent (``engine = 'none'``). Every input of this version carries
fixes only, so a device runs the GNSS-only engine ``fixes``; an engine that works on IMU
samples (``eskf``, ``pipeline``, ...; they give no output for a fix) is not used for such
a device, and the service says so at start. An engine name that is not available in this
installation falls back to ``none``: fixes are stored as sent (:attr:`Ingestor.engine_name`).

Re-ordering: fixes wait ``reorder_window_s`` (device time, behind the device's newest fix)
so that messages arriving out of order within the window are fed in time order. A fix older
than the last one fed to that device's engine is stored (``engine = 'none'``, attribute
``late``), not fed, counted (``late_fix``) and written as a ``late_fix`` event.

Checkpoints (:mod:`iotnav.service.checkpoint`): the device's engine, its last fed time and
its re-ordering queue are written to ``engine_states`` in the transaction that stores the
message, so a restart (even kill -9) resumes each device where its last committed message
left it; a transaction that fails drops the state in memory, which is then reloaded from
the committed checkpoint. An engine whose ``step()`` raises is logged, counted
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
import secrets
import time
from collections import OrderedDict
from collections.abc import Callable
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import sqlalchemy as sa
from sqlalchemy.engine import Connection, Engine

from iotnav.service import checkpoint
from iotnav.service.checkpoint import CheckpointError, DeviceState
from iotnav.service.protocols.common import Fix, finite_or_nan
from iotnav.service.store import devices, engine_states, events, inserted_id, positions, raw_messages

if TYPE_CHECKING:  # the engines (numba, scipy) load only when an engine runs
    from iotnav.engines.base import Engine as NavEngine
    from iotnav.engines.base import GnssSample, Output

log = logging.getLogger("iotnav.service")

NO_ENGINE = "none"
#: The engine of devices that send fixes only (every input of this version).
FIXES_ENGINE = "fixes"


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


def _finite_or(x: Any, default: float) -> float:
    """``float(x)`` when it is a finite number, else ``default``."""
    v = finite_or_nan(x)
    return v if math.isfinite(v) else default


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
    """Whether the engine ``name`` can be built here (imports that engine's module only)."""
    if name == NO_ENGINE:
        return True
    from iotnav.engines.registry import ENGINE_NAMES, make_engine

    if name not in ENGINE_NAMES:
        return False
    try:
        make_engine(name)
    except ValueError:  # its module does not import in this installation
        return False
    return True


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
        (``engine = 'none'``) at once; only their feeding waits (the queue is checkpointed).
    checkpoint_key : bytes, optional
        Key of the checkpoints' HMAC (:func:`iotnav.service.checkpoint.load_key`); without
        one a random key of this process: checkpoints then do not survive a restart.
    max_devices_in_memory : int
        Device states kept in memory (about 15 kB each for ``fixes``); beyond it the least
        recently used are dropped after a commit and reloaded from their checkpoints.
    """

    def __init__(
        self,
        db: Engine,
        engine_name: str = "fixes",
        registration_open: bool = True,
        engine_config: str | None = None,
        engine_factory: Callable[[], NavEngine] | None = None,
        reorder_window_s: float = 0.0,
        checkpoint_key: bytes | None = None,
        max_devices_in_memory: int = 10_000,
    ) -> None:
        if not reorder_window_s >= 0.0:
            raise ValueError(f"reorder_window_s {reorder_window_s}: expected >= 0 s")
        self.reorder_window_s = reorder_window_s
        self.db = db
        self.engine_requested = engine_name
        self._factory = engine_factory
        available = engine_factory is not None or _engine_available(engine_name)
        self.engine_name = engine_name if available else NO_ENGINE
        if self.engine_name != engine_name:
            log.warning("engine %r is not available; fixes are stored as sent (engine 'none')", engine_name)
        elif engine_factory is None and engine_name not in (NO_ENGINE, FIXES_ENGINE):
            # the other engines give an output per IMU sample: nothing from fixes alone
            self.engine_name = FIXES_ENGINE
            log.warning(
                "engine %r runs on IMU samples; devices that send fixes only run %r",
                engine_name,
                FIXES_ENGINE,
            )
        self.engine_config = engine_config
        self.registration_open = registration_open
        #: States of the devices seen lately, least recently used first (the rest are in the database).
        self._devices: OrderedDict[int, DeviceState] = OrderedDict()
        self.max_devices_in_memory = max_devices_in_memory
        self._key = checkpoint_key if checkpoint_key is not None else secrets.token_bytes(32)
        self._format = checkpoint.format_tag(self.engine_name, engine_config)
        self.counts: dict[str, int] = {}
        #: Called after each commit with (protocol, rows of the positions stored for the engine
        #: in use), on the database thread; the API's WebSocket registers here.
        self.listeners: list[Callable[[str, list[dict[str, Any]]], None]] = []

    def warm_up(self) -> float:
        """Build a throw-away engine and step it once (loads the compiled kernels); seconds taken.

        Called at start, so that the first device's message does not wait for the engines'
        imports and compiled code (several seconds) before its answer.
        """
        if self.engine_name == NO_ENGINE:
            return 0.0
        from iotnav.service.protocols.common import T_MIN

        t0 = time.perf_counter()
        self._new_engine().step(fix_to_sample(Fix("warm-up", T_MIN, 0.5, 0.5, h_acc_m=5.0)))
        return time.perf_counter() - t0

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
        touched: int | None = None  # the device whose state this transaction changes
        try:
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
                st = None
                if new and self.engine_name != NO_ENGINE:
                    touched, st = dev, self._state(conn, dev, device, now)
                late = -math.inf if st is None else st.last_t
                fix_rows = [self._row(dev, raw_id, NO_ENGINE, f, now, f.t < late) for f in new]
                if fix_rows:
                    conn.execute(positions.insert(), fix_rows)
                engine_rows = self._process(conn, dev, raw_id, st, new, now) if st is not None else []
                conn.execute(devices.update().where(devices.c.id == dev).values(last_update=now))
        except BaseException:  # not committed: the state is reloaded from its committed checkpoint
            if touched is not None:
                self._devices.pop(touched, None)
            raise
        if touched is not None:  # committed: its checkpoint is on disk, the oldest may go
            self._devices.move_to_end(touched)
            while len(self._devices) > max(1, self.max_devices_in_memory):
                self._devices.popitem(last=False)
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
    def _row(dev: int, raw_id: int | None, engine: str, f: Fix, now: float, late: bool) -> dict[str, Any]:
        """A positions row of a fix as sent; ``late``: older than what the engine had seen (flagged)."""
        attrs = {**f.attributes, "num_sv": f.num_sv, "hdop": f.hdop} if f.num_sv >= 0 else dict(f.attributes)
        if late:
            attrs["late"] = True
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
            "attributes": clean_json(attrs),
            "dedup_key": f.key,
        }

    # --- processing ----------------------------------------------------------------------

    def _new_engine(self) -> NavEngine:
        if self._factory is not None:
            return self._factory()
        from iotnav.engines.registry import make_engine

        return make_engine(self.engine_name, self.engine_config)

    def _state(self, conn: Connection, dev: int, unique_id: str, now: float) -> DeviceState:
        """The processing state of ``dev``: in memory, else its checkpoint, else a fresh one."""
        st = self._devices.get(dev)
        if st is not None and st.unique_id == unique_id:  # (a deleted device's id may be reused)
            return st
        st = None
        row = conn.execute(
            sa.select(engine_states.c.format, engine_states.c.state).where(
                engine_states.c.device_id == dev, engine_states.c.engine == self.engine_name
            )
        ).first()
        if row is not None:
            try:
                if row.format != self._format:
                    raise CheckpointError(f"checkpoint format {row.format!r}, this service {self._format!r}")
                st = checkpoint.loads(bytes(row.state), self._key)
                self.count("checkpoint_restored")
            except CheckpointError as exc:
                self.count("checkpoint_discarded")
                log.warning("device %d: %s; its engine starts afresh", dev, exc)
                conn.execute(
                    events.insert().values(
                        device_id=dev,
                        type="checkpoint_discarded",
                        event_time=now,
                        server_time=now,
                        attributes={"reason": str(exc)[:200]},
                    )
                )
        if st is None:  # no usable checkpoint: continue after the engine's last stored output
            last = conn.execute(
                sa.select(sa.func.max(positions.c.fix_time)).where(
                    positions.c.device_id == dev, positions.c.engine == self.engine_name
                )
            ).scalar()
            st = DeviceState(last_t=-math.inf if last is None else float(last))
            st.newest = st.last_t
        st.unique_id = unique_id
        self._devices[dev] = st
        return st

    def _save(self, conn: Connection, dev: int, st: DeviceState, now: float) -> None:
        """Write the checkpoint of ``dev`` (in the transaction storing what it has seen)."""
        values = {
            "saved_at": now,
            "last_t": st.last_t if math.isfinite(st.last_t) else None,
            "format": self._format,
            "state": checkpoint.dumps(st, self._key),
        }
        where = (engine_states.c.device_id == dev) & (engine_states.c.engine == self.engine_name)
        if not conn.execute(engine_states.update().where(where).values(**values)).rowcount:
            conn.execute(engine_states.insert().values(device_id=dev, engine=self.engine_name, **values))

    def _drain_events(self, st: DeviceState, eng: NavEngine, now: float, evs: list[dict[str, Any]]) -> None:
        """Move the engine's new events to ``evs``; a plain list attribute is emptied (bounded memory)."""
        for e in eng.events[st.n_events :]:
            evs.append(
                {
                    "type": str(e.get("type", "engine")),
                    "event_time": _finite_or(e.get("t"), now),
                    "attributes": clean_json(dict(e)),
                }
            )
        if isinstance(vars(eng).get("events"), list):
            del eng.events[:]
        st.n_events = len(eng.events)

    def _process(
        self, conn: Connection, dev: int, raw_id: int, st: DeviceState, fixes: list[Fix], now: float
    ) -> list[dict[str, Any]]:
        """Queue ``fixes``, feed the device's engine those out of the re-ordering window in time
        order; store its outputs, its events and its checkpoint; the engine rows stored."""
        rows, evs = [], []
        for f in fixes:
            if f.t < st.last_t:  # older than what the engine has already seen
                self.count("late_fix")
                evs.append({"type": "late_fix", "event_time": f.t, "attributes": {"last_t": st.last_t}})
                continue
            st.seq += 1
            heapq.heappush(st.pending, (f.t, st.seq, f, raw_id))
            st.newest = max(st.newest, f.t)
        release = st.newest - self.reorder_window_s
        while st.pending and st.pending[0][0] <= release:
            if st.engine is None:
                st.engine, st.n_events = self._new_engine(), 0
            eng = st.engine
            _, _, f, f_raw = heapq.heappop(st.pending)
            st.last_t = f.t
            try:
                out: Output | None = eng.step(fix_to_sample(f))
            except Exception as exc:  # an engine bug must not block the device's stream (no ACK)
                self.count("engine_error")
                log.exception("engine %s, device %d: step failed; the engine restarts", self.engine_name, dev)
                self._drain_events(st, eng, now, evs)
                evs.append(
                    {"type": "engine_error", "event_time": f.t, "attributes": {"error": repr(exc)[:200]}}
                )
                st.engine = None
                break
            if out is not None and out.source != "none" and math.isfinite(out.lat + out.lon):
                rows.append(self._output_row(dev, f_raw, f, out, now))
        if st.engine is not None:
            self._drain_events(st, st.engine, now, evs)
        if rows:
            conn.execute(positions.insert(), rows)
        if evs:
            conn.execute(events.insert(), [{**e, "device_id": dev, "server_time": now} for e in evs])
        self._save(conn, dev, st, now)
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
