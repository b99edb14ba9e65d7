"""The engines of the ingest: each device's state, its rebuild, feeding, checkpoints.

Moved out of :mod:`iotnav.service.ingest` unchanged (which re-exports the public names):
:data:`REPLAY_LIMIT`, :func:`fix_to_sample`, :func:`checkpoint_discarded_event`, and
:class:`IngestEngine`, the methods of :class:`~iotnav.service.ingest.Ingestor` that build a
device's engine, rebuild its state (checkpoint, then replay of its stored fixes), feed it
through the re-ordering window, and write the checkpoints due. The design is in
:mod:`iotnav.service.ingest`'s docstring.
"""

from __future__ import annotations

import heapq
import logging
import math
import pickle
import time
from collections import OrderedDict
from collections.abc import Callable, Sequence
from typing import TYPE_CHECKING, Any

import sqlalchemy as sa
from sqlalchemy.engine import Connection, Engine

from iotnav.service import checkpoint
from iotnav.service.checkpoint import CheckpointError, DeviceState
from iotnav.service.ingest_messages import NO_ENGINE
from iotnav.service.ingest_rows import IngestRows, clean_json, fix_of_row
from iotnav.service.protocols.common import Fix, finite_or_nan
from iotnav.service.store import engine_states, events, positions

if TYPE_CHECKING:  # the engines (numba, scipy) load only when an engine runs
    from iotnav.engines.base import Engine as NavEngine
    from iotnav.engines.base import GnssSample, Output

__all__ = ["REPLAY_LIMIT", "IngestEngine", "checkpoint_discarded_event", "fix_to_sample"]

log = logging.getLogger("iotnav.service")

#: Stored fixes replayed at most to rebuild a device without a checkpoint row (beyond: it
#: starts afresh after its last stored output, as after a discarded checkpoint).
REPLAY_LIMIT = 100_000


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


def checkpoint_discarded_event(conn: Connection, device_id: int, now: float, exc: CheckpointError) -> None:
    """Store the event of a device's checkpoint discarded (``exc`` says why), in ``conn``'s transaction.

    Parameters
    ----------
    conn : sqlalchemy.engine.Connection
        Connection in the transaction that restores the device.
    device_id : int
        The device.
    now : float
        Server time, Unix s (the event's time and server time).
    exc : CheckpointError
        Why the checkpoint could not be used (its text, up to 200 characters, is the reason).
    """
    conn.execute(
        events.insert().values(
            device_id=device_id,
            type="checkpoint_discarded",
            event_time=now,
            server_time=now,
            attributes={"reason": str(exc)[:200]},
        )
    )


class IngestEngine(IngestRows):
    """Each device's engine state: rebuild, feeding, checkpoints (mixed into ``Ingestor``).

    Attributes read (set by :class:`~iotnav.service.ingest.Ingestor`): ``db``,
    ``engine_name``, ``engine_config``, ``reorder_window_s`` (s, device time),
    ``checkpoint_interval_s`` (s), ``_factory`` (the engine factory or None), ``_template``
    (a fresh engine, pickled), ``_devices`` (device id -> state, least recently used first),
    ``_dirty`` (device id -> monotonic time of its first unsaved change), ``_events`` (events
    of the open batch), the checkpoints' HMAC key ``_key``, format tag ``_format`` and upsert
    statement ``_upsert_state``; and those of :class:`~iotnav.service.ingest_rows.IngestRows`.
    """

    db: Engine
    engine_config: str | None
    reorder_window_s: float
    checkpoint_interval_s: float
    _factory: Callable[[], NavEngine] | None
    _template: bytes | None
    _devices: OrderedDict[int, DeviceState]
    _dirty: OrderedDict[int, float]
    _events: list[dict[str, Any]]
    _key: bytes
    _format: str
    _upsert_state: Any

    #: Checkpoints written at most per transaction besides those of evicted states (when
    #: ``checkpoint_interval_s`` > 0): a checkpoint of ``fixes`` costs about 0.2 ms, and the
    #: devices of a fleet that started together all come due together (10,000 at once would
    #: hold one transaction, and every ACK waiting on it, for seconds); the rest wait for the
    #: next transactions, oldest first.
    MAX_CHECKPOINTS_PER_BATCH = 64

    def _checkpoints_due(self) -> tuple[list[int], list[int]]:
        """Devices to checkpoint now (unsaved for the interval, or leaving memory) and to drop."""
        over = len(self._devices) - max(1, self.max_devices_in_memory)
        evicted = list(self._devices)[:over] if over > 0 else []
        limit = time.monotonic() - self.checkpoint_interval_s
        due = [dev for dev in evicted if dev in self._dirty]
        cap = len(due) + self.MAX_CHECKPOINTS_PER_BATCH if self.checkpoint_interval_s > 0 else math.inf
        for dev, since in self._dirty.items():
            if since > limit or len(due) >= cap:
                break
            due.append(dev)
        return list(dict.fromkeys(due)), evicted

    def flush_checkpoints(self) -> int:
        """Checkpoint every device state with unsaved changes (at shutdown); how many.

        Call on the database thread, or once it has stopped.
        """
        dirty = [dev for dev in self._dirty if dev in self._devices]
        with self.db.begin() as conn:
            self._save(conn, dirty, time.time())
        self._dirty.clear()
        return len(dirty)

    # --- processing ----------------------------------------------------------------------

    def _new_engine(self) -> NavEngine:
        """A fresh engine: a copy of a pickled fresh one (half the time of a build), or the factory's."""
        if self._factory is not None:
            return self._factory()
        if self._template is None:
            from iotnav.engines.registry import make_engine

            self._template = pickle.dumps(make_engine(self.engine_name, self.engine_config))
        engine: NavEngine = pickle.loads(self._template)
        return engine

    def _state(self, conn: Connection, dev: int, unique_id: str, now: float) -> DeviceState:
        """The processing state of ``dev``: in memory, else rebuilt (checkpoint, then replay).

        Reads only (``conn`` may be a read snapshot); a discarded checkpoint's event goes to the
        batch's events (:attr:`_events`), stored by its write transaction.
        """
        st = self._devices.get(dev)
        if st is not None and st.unique_id == unique_id:  # (a deleted device's id may be reused)
            self._devices.move_to_end(dev)
            return st
        if dev in self._created:  # a fresh engine; nothing stored to replay
            st = self._devices[dev] = DeviceState(raw_id=0, unique_id=unique_id)
            return st
        st = None
        replay_after: int | None = None
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
                replay_after = st.raw_id  # None: a checkpoint of every message (earlier versions)
                self._count_on_commit("checkpoint_restored")
            except CheckpointError as exc:
                self._count_on_commit("checkpoint_discarded")
                log.warning("device %d: %s; its engine starts afresh", dev, exc)
                self._events.append(
                    {
                        "device_id": dev,
                        "type": "checkpoint_discarded",
                        "event_time": now,
                        "server_time": now,
                        "attributes": {"reason": str(exc)[:200]},
                    }
                )
        else:  # never checkpointed: a fresh engine fed all the device's stored fixes
            st, replay_after = DeviceState(raw_id=0), 0
        if st is None:
            st = self._after_outputs(conn, dev)
        st.unique_id = unique_id
        if replay_after is not None and not self._replay(conn, dev, st, replay_after, now, row is None):
            st = self._after_outputs(conn, dev)
            st.unique_id = unique_id
        self._devices[dev] = st
        return st

    def _after_outputs(self, conn: Connection, dev: int) -> DeviceState:
        """A fresh state that continues after the engine's last stored output."""
        last = conn.execute(
            sa.select(sa.func.max(positions.c.fix_time)).where(
                positions.c.device_id == dev, positions.c.engine == self.engine_name
            )
        ).scalar()
        st = DeviceState(last_t=-math.inf if last is None else float(last))
        st.newest = st.last_t
        return st

    def _replay(
        self, conn: Connection, dev: int, st: DeviceState, after: int, now: float, limited: bool
    ) -> bool:
        """Feed ``st`` again the fixes stored for ``dev`` after raw message ``after`` (outputs dropped).

        Only fixes not older than ``st.last_t`` can change the state (older ones are late);
        False when ``limited`` and there are more than :data:`REPLAY_LIMIT`.
        """
        cols = [positions.c[c] for c in ("raw_id", "fix_time", "latitude", "longitude", "altitude")]
        cols += [positions.c[c] for c in ("speed_mps", "course_rad", "accuracy_m", "valid", "attributes")]
        q = sa.select(*cols, positions.c.dedup_key).where(
            positions.c.device_id == dev, positions.c.engine == NO_ENGINE, positions.c.raw_id > after
        )
        if math.isfinite(st.last_t):
            q = q.where(positions.c.fix_time >= st.last_t)
        rows = conn.execute(q.order_by(positions.c.raw_id, positions.c.id).limit(REPLAY_LIMIT + 1)).all()
        if limited and len(rows) > REPLAY_LIMIT:
            log.warning(
                "device %d: no checkpoint and over %d stored fixes; its engine starts afresh",
                dev,
                REPLAY_LIMIT,
            )
            return False
        i = 0
        while i < len(rows):
            j = i
            while j < len(rows) and rows[j].raw_id == rows[i].raw_id:
                j += 1
            fixes = [fix_of_row(st.unique_id, r) for r in rows[i:j]]
            self._feed(st, dev, int(rows[i].raw_id), fixes, now, [], replay=True)
            i = j
        if rows:
            self._count_on_commit("replayed_fixes", len(rows))
        return True

    def _save(self, conn: Connection, devs: Sequence[int], now: float) -> None:
        """Write the checkpoints of ``devs`` (in the transaction storing what they have seen)."""
        params = []
        for dev in devs:
            st = self._devices.get(dev)
            if st is None:
                continue
            params.append(
                {
                    "device_id": dev,
                    "engine": self.engine_name,
                    "saved_at": now,
                    "last_t": st.last_t if math.isfinite(st.last_t) else None,
                    "format": self._format,
                    "state": checkpoint.dumps(st, self._key),
                }
            )
        if params:
            conn.execute(self._upsert_state, params)
            self._count_on_commit("checkpoints_saved", len(params))

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

    def _feed(
        self,
        st: DeviceState,
        dev: int,
        raw_id: int,
        fixes: list[Fix],
        now: float,
        evs: list[dict[str, Any]],
        replay: bool = False,
    ) -> list[dict[str, Any]]:
        """Queue the new ``fixes`` of raw message ``raw_id``, feed the device's engine those out
        of the re-ordering window in time order; its engine rows (events appended to ``evs``).

        ``replay``: rebuilding a state from stored fixes (nothing counted or logged).
        """
        rows: list[dict[str, Any]] = []
        mine: list[dict[str, Any]] = []
        for f in fixes:
            if f.t < st.last_t:  # older than what the engine has already seen
                if not replay:
                    self._count_on_commit("late_fix")
                mine.append({"type": "late_fix", "event_time": f.t, "attributes": {"last_t": st.last_t}})
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
                if not replay:
                    self._count_on_commit("engine_error")
                    log.exception(
                        "engine %s, device %d: step failed; the engine restarts", self.engine_name, dev
                    )
                self._drain_events(st, eng, now, mine)
                mine.append(
                    {"type": "engine_error", "event_time": f.t, "attributes": {"error": repr(exc)[:200]}}
                )
                st.engine = None
                break
            if out is not None and out.source != "none" and math.isfinite(out.lat + out.lon):
                rows.append(self._output_row(dev, f_raw, f, out, now))
        if st.engine is not None:
            self._drain_events(st, st.engine, now, mine)
        st.raw_id = raw_id
        evs += [{**e, "device_id": dev, "server_time": now} for e in mine]
        return rows
