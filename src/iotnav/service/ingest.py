"""Storing decoded messages and running one engine per device on them, with group commit.

The listeners hand every decoded message to :meth:`Ingestor.submit` (or
:meth:`Ingestor.enqueue`, which returns the future at once) and answer the device (the
Teltonika ACK, the HTTP 200, the MQTT PUBACK) only when it returns: that is the interface
of every input, ``await ingestor.submit(protocol, device, payload, fixes, remote, unique)``
giving an :class:`IngestResult` once the message is durably stored (or raising when storing
failed: then no answer, the device resends).

Group commit: the messages that arrive while one transaction is being written wait in a
queue; the next transaction takes them all (:meth:`Ingestor.ingest_batch`, at most
``max_batch``), stores them with one executemany per table (the hot statements as SQL text
on the driver's own cursor: the per-row parameter and result processing of Core cost more
than the writes) and one commit, and only then resolves their futures. So under load one commit (and, on SQLite
with ``synchronous=FULL``, one fsync) serves hundreds of messages, and an acknowledged
record is on disk. When a batch fails (a database error, a constraint) it is rolled back
and its messages are stored one transaction each, so one bad message fails alone.

Write lock: a batch is prepared first (:meth:`Ingestor._prepare`: device ids, the
de-duplication reads, the engine steps, the rows), in a read snapshot that does not take
the database's write lock, and only its inserts, checkpoints and commit run in the write
transaction (``BEGIN IMMEDIATE`` with several processes on SQLite), so the processes' engine
steps run beside each other's writes. The reads outside the lock are sound because each
device is written by one ingestor (one process, its one database thread); the raw messages'
unique key still guards the insert.

Per message (in arrival order within the batch): the raw message as received, de-duplicated
by a digest of device id and bytes (``INSERT ... ON CONFLICT DO NOTHING RETURNING``: a
message stored before is answered as a duplicate and not processed again); its fixes as
positions flagged ``engine = 'none'``, de-duplicated per record by a per-device cache of the
recent record keys (exact: every stored key of the device newer than the cache's horizon is
in it; a fix older than the horizon is looked up in the database), behind the unique
constraint of ``positions``; what the device's engine makes of them (positions flagged with
the engine's name, and its events).

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

Checkpoints (:mod:`iotnav.service.checkpoint`): a device's state (engine, last fed time,
re-ordering queue, and the id of the last raw message it has processed) is written to
``engine_states`` when it has had unsaved changes for ``checkpoint_interval_s`` (in the
transaction of a batch, at most :attr:`Ingestor.MAX_CHECKPOINTS_PER_BATCH` per transaction,
oldest first), when it leaves the memory bound, and at shutdown
(:meth:`Ingestor.flush_checkpoints`); 0 writes it with every message. Exactly-once across a
crash comes from the append-only storage, not from the checkpoint: a state is rebuilt from
its checkpoint and then the fixes stored after it (``engine = 'none'`` positions of the raw
messages after the checkpoint's, in storage order) are fed again through the same code, their
outputs dropped (they were committed with their messages). The engines are deterministic, so
the state after that replay, and every clean row after it, equals an uninterrupted run's. A
device without a checkpoint row replays all its stored fixes (up to ``REPLAY_LIMIT``); one
whose checkpoint cannot be used (other key, other version) starts afresh after its last
stored output. A batch that fails anywhere (also when the write lock is not obtained
within ``busy_timeout``, after its engine steps) drops the states and recent keys it touched,
which are rebuilt the same way from what did commit: the device resends what was not
acknowledged, and it is new again. An engine whose ``step()`` raises is logged, counted
(``engine_error``, and an event) and replaced by a fresh one; the message is still stored
and acknowledged, so an engine bug cannot block a device's stream.

Caches (per device, in memory, bounded by ``max_devices_in_memory``): the device row (id,
disabled) for ``device_cache_s`` (so a device disabled or deleted through the API is refused
within that time), the recent record keys, the processing state.

The synchronous methods run on one database thread (:attr:`Ingestor.executor`, one worker),
which serialises the writers; :meth:`submit` and :meth:`enqueue` run on the event loop.

Modules (the code moved there unchanged; every public name is re-exported here):
:mod:`iotnav.service.ingest_messages` (:class:`Message`, :class:`IngestResult`,
:func:`group_commit`), :mod:`iotnav.service.ingest_devices` (device ids and registration),
:mod:`iotnav.service.ingest_rows` (de-duplication of records, the positions rows) and
:mod:`iotnav.service.ingest_engine` (each device's engine: rebuild, feeding, checkpoints).
"""

from __future__ import annotations

import asyncio
import itertools
import logging
import math
import secrets
import time
from collections import OrderedDict
from collections.abc import Callable, Iterator, Sequence
from concurrent.futures import Executor, ThreadPoolExecutor
from contextlib import contextmanager
from typing import TYPE_CHECKING, Any

from sqlalchemy.dialects import postgresql, sqlite
from sqlalchemy.engine import Connection, Engine

from iotnav.service import checkpoint
from iotnav.service.checkpoint import DeviceState
from iotnav.service.ingest_devices import IngestDevices
from iotnav.service.ingest_engine import (  # the public names moved there are re-exported
    REPLAY_LIMIT,
    IngestEngine,
    _engine_available,
    checkpoint_discarded_event,
    fix_to_sample,
)
from iotnav.service.ingest_messages import (  # the names moved there are re-exported
    FIXES_ENGINE,
    NO_ENGINE,
    ConcurrentWriteError,
    IngestResult,
    Message,
    _Plan,
    group_commit,
)
from iotnav.service.ingest_rows import (  # the public names moved there are re-exported
    _POSITION_COLUMNS,
    _RAW_ID,
    _RecentKeys,
    clean_json,
    fix_of_row,
)
from iotnav.service.protocols.common import Fix
from iotnav.service.store import READ_ONLY, engine_states, events, positions, raw_messages

if TYPE_CHECKING:  # the engines (numba, scipy) load only when an engine runs
    from iotnav.engines.base import Engine as NavEngine

__all__ = [
    "FIXES_ENGINE",
    "NO_ENGINE",
    "REPLAY_LIMIT",
    "ConcurrentWriteError",
    "IngestResult",
    "Ingestor",
    "Message",
    "checkpoint_discarded_event",
    "clean_json",
    "fix_of_row",
    "fix_to_sample",
    "group_commit",
]

log = logging.getLogger("iotnav.service")


_RAW_COLUMNS = ("device_id", "protocol", "received_at", "remote", "payload", "dedup_key", "n_records")
_RAW_CHUNK = 200  # rows of one multi-row INSERT of raw messages (7 parameters each)


def _insert_of(db: Engine) -> Callable[..., Any]:
    """The dialect's ``insert`` (with ``ON CONFLICT``): SQLite and PostgreSQL."""
    if db.dialect.name == "postgresql":
        return postgresql.insert
    if db.dialect.name == "sqlite":
        return sqlite.insert
    raise ValueError(f"database {db.dialect.name!r}: the service supports SQLite and PostgreSQL")


class Ingestor(IngestDevices, IngestEngine):
    """Stores messages and feeds each device's engine (module docstring).

    Parameters
    ----------
    db : sqlalchemy.engine.Engine
        The service database (schema at head), SQLite or PostgreSQL.
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
        recently used are checkpointed and dropped, and come back from their checkpoints.
    checkpoint_interval_s : float
        A device's state is checkpointed once it has had unsaved changes this long (server
        time, s); 0: with every message. Bounds what a restart after a crash replays (about
        this many seconds of each device's fixes). Default 60 s: a checkpoint of ``fixes``
        costs about 1 ms (pickle, zlib, HMAC), so 10,000 devices spend about 0.17 s of CPU
        per second on them; a replay costs about 50 us per fix.
    max_batch : int
        Messages stored in one transaction at most (group commit).
    device_cache_s : float
        A device's row (id, disabled) is re-read after this long, s: a device disabled or
        deleted through the API is refused within this time.
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
        checkpoint_interval_s: float = 60.0,
        max_batch: int = 2000,
        device_cache_s: float = 10.0,
    ) -> None:
        if not reorder_window_s >= 0.0:
            raise ValueError(f"reorder_window_s {reorder_window_s}: expected >= 0 s")
        if not checkpoint_interval_s >= 0.0:
            raise ValueError(f"checkpoint_interval_s {checkpoint_interval_s}: expected >= 0 s")
        self.reorder_window_s = reorder_window_s
        self.checkpoint_interval_s = checkpoint_interval_s
        self.max_batch = max(1, int(max_batch))
        self.device_cache_s = device_cache_s
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
        #: Devices whose state has changes not checkpointed yet -> when the first came (monotonic s).
        self._dirty: OrderedDict[int, float] = OrderedDict()
        self._recent: OrderedDict[int, _RecentKeys] = OrderedDict()
        #: unique id -> (device id, None when disabled; monotonic time it was read).
        self._device_rows: dict[str, tuple[int | None, float]] = {}
        self.max_devices_in_memory = max_devices_in_memory
        self._key = checkpoint_key if checkpoint_key is not None else secrets.token_bytes(32)
        self._format = checkpoint.format_tag(self.engine_name, engine_config)
        self.counts: dict[str, int] = {}
        self._tally: dict[str, int] = {}  # counts of the open transaction, added at its commit
        #: Called after each commit with (protocol, rows of the positions stored for the engine
        #: in use: those of every message of that protocol in the batch), on the database
        #: thread; the API's WebSocket registers here.
        self.listeners: list[Callable[[str, list[dict[str, Any]]], None]] = []
        insert = _insert_of(db)
        # the hot statements as SQL text run through the driver (executemany of tuples): the
        # per-row parameter processing of Core would cost more than the writes themselves
        mark, json_mark = ("?", "?") if db.dialect.name == "sqlite" else ("%s", "CAST(%s AS JSON)")
        cols = ", ".join(_RAW_COLUMNS)
        self._sql_raw = (
            f"INSERT INTO raw_messages ({cols}) VALUES {{values}} "
            "ON CONFLICT (protocol, dedup_key) DO NOTHING RETURNING id, protocol, dedup_key"
        )
        self._raw_values = "(" + ", ".join([mark] * len(_RAW_COLUMNS)) + ")"
        marks = [json_mark if c == "attributes" else mark for c in _POSITION_COLUMNS]
        self._sql_positions = (
            f"INSERT INTO positions ({', '.join(_POSITION_COLUMNS)}) VALUES ({', '.join(marks)})"
        )
        self._sql_last_update = f"UPDATE devices SET last_update = {mark} WHERE id = {mark}"
        self._sql_devices = (
            "INSERT INTO devices (unique_id, name, protocol, created_at, attributes) VALUES {values} "
            "RETURNING id, unique_id"
        )
        self._device_values = f"({mark}, {mark}, {mark}, {mark}, {json_mark})"
        self._insert_events = events.insert()
        upsert = insert(engine_states)
        self._upsert_state = upsert.on_conflict_do_update(
            index_elements=["device_id", "engine"],
            set_={c: upsert.excluded[c] for c in ("saved_at", "last_t", "format", "state")},
        )
        #: Devices created for the open batch (nothing is stored for them: no queries).
        self._created: set[int] = set()
        #: Events of the open batch found while preparing it (discarded checkpoints).
        self._events: list[dict[str, Any]] = []
        self._plan: _Plan | None = None  # the open batch, prepared (:meth:`_prepare`)
        self._mark = mark
        self._template: bytes | None = None  # a fresh engine, pickled (copies are cheaper than builds)
        self._output_json: dict[tuple[str, bool], str] = {}  # attributes text of engine rows
        self._executor: Executor | None = None
        self._queue: list[tuple[Message, asyncio.Future[IngestResult]]] = []
        self._flusher: asyncio.Task[None] | None = None

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

    def _count_on_commit(self, what: str, n: int = 1) -> None:
        self._tally[what] = self._tally.get(what, 0) + n

    # --- the listeners' interface --------------------------------------------------------

    @property
    def executor(self) -> Executor:
        """The database thread (one worker): every write of the service goes through it."""
        if self._executor is None:
            self._executor = ThreadPoolExecutor(max_workers=1, thread_name_prefix="iotnav-db")
        return self._executor

    def enqueue(
        self,
        protocol: str,
        device: str,
        payload: bytes,
        fixes: Sequence[Fix],
        remote: str | None = None,
        unique: bool = False,
    ) -> asyncio.Future[IngestResult]:
        """Queue a decoded message for the next group commit; the future of its result.

        Call on the event loop. The future is resolved once the transaction storing the
        message has committed (then answer the device), or fails with the storing error (then
        do not answer: the device resends). Futures resolve in the order of their calls to
        :meth:`enqueue` (MQTT acknowledges in that order). ``unique``: as :class:`Message`.
        """
        loop = asyncio.get_running_loop()
        fut: asyncio.Future[IngestResult] = loop.create_future()
        self._queue.append(
            (Message(protocol, device, payload, list(fixes), remote, time.time(), unique), fut)
        )
        if self._flusher is None or self._flusher.done():
            self._flusher = loop.create_task(self._flush())
        return fut

    async def submit(
        self,
        protocol: str,
        device: str,
        payload: bytes,
        fixes: Sequence[Fix],
        remote: str | None = None,
        unique: bool = False,
    ) -> IngestResult:
        """Store a decoded message durably and return its result (:meth:`enqueue`, awaited).

        This is what every listener calls: answer the device only after it returns.
        """
        return await self.enqueue(protocol, device, payload, fixes, remote, unique)

    async def _flush(self) -> None:
        """Write the queued messages, a batch per transaction, until the queue is empty."""
        loop = asyncio.get_running_loop()
        while self._queue:
            batch = self._queue[: self.max_batch]
            del self._queue[: self.max_batch]
            results: list[IngestResult | Exception]
            t0 = time.perf_counter()
            try:
                results = await loop.run_in_executor(self.executor, self.ingest_batch, [m for m, _ in batch])
                log.debug("batch of %d messages in %.1f ms", len(batch), 1e3 * (time.perf_counter() - t0))
            except asyncio.CancelledError:
                for _, fut in batch + self._queue:
                    fut.cancel()
                self._queue.clear()
                raise
            except Exception as exc:  # the executor is shut down (the service is stopping)
                results = [exc] * len(batch)
            for (_, fut), res in zip(batch, results, strict=True):
                if fut.done():  # its caller has gone (connection closed)
                    continue
                if isinstance(res, Exception):
                    fut.set_exception(res)
                else:
                    fut.set_result(res)

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
        """Store one message in one transaction (synchronous; :meth:`ingest_batch` of one).

        ``unique``: as :class:`Message`. Raises what storing raised (nothing committed).
        """
        now = time.time() if received_at is None else received_at
        res = self.ingest_batch([Message(protocol, device, payload, fixes, remote, now, unique)])[0]
        if isinstance(res, Exception):
            raise res
        return res

    def ingest_batch(self, msgs: Sequence[Message]) -> list[IngestResult | Exception]:
        """Store ``msgs`` in one transaction (group commit); the result of each, or its error.

        When the batch fails it is rolled back and, unless the database is unreachable
        (``OperationalError``: every message fails with it), each message is stored in a
        transaction of its own, so one bad message fails alone. Runs on the database thread.
        """
        return group_commit(
            msgs,
            self._transaction,
            on_split=lambda: self.count("batch_split"),
            name=lambda m: f"{m.protocol} {m.device}",
        )

    @contextmanager
    def _reading(self) -> Iterator[Connection]:
        """A connection in a read transaction (on SQLite a deferred ``BEGIN``: no write lock)."""
        with self.db.connect() as conn:
            conn.execution_options(**{READ_ONLY: True})
            with conn.begin():
                yield conn

    def _transaction(self, msgs: Sequence[Message]) -> list[IngestResult]:
        """Prepare ``msgs`` (reads, engine steps, rows: :meth:`_prepare`), then write them in one
        transaction (:meth:`_store`, the only part holding the database's write lock).

        Rule of a failure anywhere (a read, the lock not obtained within ``busy_timeout``, an
        insert, the commit): every device whose state or recent keys the batch changed in memory
        is dropped from memory and rebuilt from what did commit (checkpoint, then replay of its
        stored fixes) at its next message. So no state is ahead of the database, the resent
        records are new again to it, and its track equals an uninterrupted run's.
        """
        touched: set[int] = set()  # devices whose in-memory state this batch changes
        self._tally = {}
        self._created = set()
        self._events = []
        try:
            self._plan = self._prepare(msgs, touched)
            with self.db.begin() as conn:
                results, notify, saved, evicted = self._store(conn, msgs, touched)
        except BaseException:  # not committed: drop what it changed in memory (rebuilt from the database)
            for dev in touched:
                self._devices.pop(dev, None)
                self._recent.pop(dev, None)
                self._dirty.pop(dev, None)
            for m in msgs:
                self._device_rows.pop(m.device, None)
            self._tally = {}
            raise
        finally:
            self._plan = None
        for dev in saved:  # committed: their checkpoints are on disk
            self._dirty.pop(dev, None)
        for dev in evicted:
            self._devices.pop(dev, None)
        for what, n in self._tally.items():
            self.count(what, n)
        self._tally = {}
        by_protocol: dict[str, list[dict[str, Any]]] = {}
        for protocol, rows in notify:  # one call per protocol and batch (one socket message)
            by_protocol.setdefault(protocol, []).extend(rows)
        for protocol, rows in by_protocol.items():
            self._notify(protocol, rows)
        return results

    def _stored_digests(self, conn: Connection, keys: Sequence[tuple[str, bytes]]) -> set[tuple[str, bytes]]:
        """The (protocol, digest) of ``keys`` already in ``raw_messages`` (index lookups)."""
        by_protocol: dict[str, list[bytes]] = {}
        for protocol, digest in keys:
            by_protocol.setdefault(protocol, []).append(digest)
        out: set[tuple[str, bytes]] = set()
        cur = conn.connection.cursor()
        for protocol, digests in by_protocol.items():
            for b in range(0, len(digests), 500):
                chunk = digests[b : b + 500]
                cur.execute(
                    f"SELECT dedup_key FROM raw_messages WHERE protocol = {self._mark} "
                    f"AND dedup_key IN ({', '.join([self._mark] * len(chunk))})",
                    (protocol, *chunk),
                )
                out.update((protocol, bytes(k)) for (k,) in cur.fetchall())
        cur.close()
        return out

    def _prepare(self, msgs: Sequence[Message], touched: set[int]) -> _Plan:
        """Everything of a batch that needs no write: device ids, de-duplication, engine steps, rows.

        Runs before the write transaction, in a read snapshot. Reading there what the batch
        then writes (are these raw messages and records stored? the device's checkpoint and
        fixes) is safe because a device is written by one ingestor only: one process (the
        socket of a device goes to one worker by rendezvous hash of its IMEI,
        :func:`iotnav.service.multiproc.owner`), and in it the one database thread, which
        prepares and writes one batch at a time. A raw message stored meanwhile all the same
        fails the write transaction (:class:`ConcurrentWriteError`), which then rolls back.
        """
        clock = time.monotonic()
        with self._reading() as conn:
            missing = self._read_devices(conn, msgs, clock)
            if not missing or not self.registration_open:  # the usual case: one read snapshot
                return self._prepared(conn, msgs, touched, self._device_ids(msgs, clock))
        self._create_missing(missing, clock)
        with self._reading() as conn:
            return self._prepared(conn, msgs, touched, self._device_ids(msgs, clock))

    def _prepared(
        self, conn: Connection, msgs: Sequence[Message], touched: set[int], devs: list[int | None]
    ) -> _Plan:
        """:meth:`_prepare` once the devices are known (ids ``devs``), in the read snapshot ``conn``."""
        results: list[IngestResult | None] = [None] * len(msgs)
        digests = [m.dedup_key() for m in msgs]
        first: dict[tuple[str, bytes], int] = {}
        for i, (m, dev) in enumerate(zip(msgs, devs, strict=True)):
            if dev is None:
                self._count_on_commit("device_refused")
                results[i] = IngestResult(accepted=False)
            elif (m.protocol, digests[i]) in first:  # the same message twice in the batch
                self._count_on_commit("duplicate_message")
                results[i] = IngestResult(accepted=True, duplicate=True, device_id=dev)
            else:
                first[(m.protocol, digests[i])] = i
        values: list[tuple[Any, ...]] = []
        evs: list[dict[str, Any]] = []
        notify: list[tuple[str, list[dict[str, Any]]]] = []
        last_update: dict[int, float] = {}
        new: list[int] = []
        stored = self._stored_digests(conn, list(first)) if first else set()
        for key, i in first.items():
            if key in stored:  # stored before (a resend): answered, not processed again
                self._count_on_commit("duplicate_message")
                results[i] = IngestResult(accepted=True, duplicate=True, device_id=devs[i])
            else:
                new.append(i)
        for i in new:  # arrival order: the order of their raw ids (storage order, a replay's)
            m, dev, raw_id = msgs[i], devs[i], -1 - i  # provisional raw id (_Plan)
            assert dev is not None
            touched.add(dev)
            fresh = self._new_fixes(conn, dev, m.fixes)
            st = (
                self._state(conn, dev, m.device, m.received_at)
                if fresh and self.engine_name != NO_ENGINE
                else None
            )
            late = -math.inf if st is None else st.last_t
            fix_rows = []
            for f in fresh:
                row, vals = self._row_values(dev, raw_id, NO_ENGINE, f, m.received_at, f.t < late)
                fix_rows.append(row)
                values.append(vals)
            engine_rows: list[dict[str, Any]] = []
            if st is not None:
                engine_rows = self._feed(st, dev, raw_id, fresh, m.received_at, evs)
                self._dirty.setdefault(dev, time.monotonic())
                values += [self._output_values(r) for r in engine_rows]
            last_update[dev] = max(last_update.get(dev, -math.inf), m.received_at)
            self._count_on_commit("records", len(fresh))
            notify.append((m.protocol, engine_rows if self.engine_name != NO_ENGINE else fix_rows))
            results[i] = IngestResult(
                accepted=True, n_new=len(fresh), n_engine=len(engine_rows), device_id=dev
            )
        assert all(r is not None for r in results)
        done = [r for r in results if r is not None]
        return _Plan(done, devs, digests, new, values, self._events + evs, notify, last_update)

    def _store(
        self, conn: Connection, msgs: Sequence[Message], touched: set[int]
    ) -> tuple[list[IngestResult], list[tuple[str, list[dict[str, Any]]]], list[int], list[int]]:
        """The writes of the prepared batch (:attr:`_plan`), in its write transaction: the raw
        messages (their ids replace the provisional ones), positions, events, devices' last
        update, checkpoints due. Results, rows to notify, devices checkpointed, evicted."""
        plan = self._plan
        assert plan is not None
        raw_ids: dict[int, int] = {}  # provisional raw id -> stored id
        # the hot statements go through the driver's own cursor (no result processing of Core)
        cur = conn.connection.cursor()
        if plan.new:
            index = {(msgs[i].protocol, plan.digests[i]): i for i in plan.new}
            params = [
                (plan.devs[i], m.protocol, m.received_at, m.remote, m.payload, plan.digests[i], len(m.fixes))
                for i in plan.new
                for m in (msgs[i],)
            ]
            for b in range(0, len(params), _RAW_CHUNK):
                chunk = params[b : b + _RAW_CHUNK]
                sql = self._sql_raw.format(values=", ".join([self._raw_values] * len(chunk)))
                cur.execute(sql, tuple(v for p in chunk for v in p))
                for raw_id, protocol, dedup_key in cur.fetchall():
                    raw_ids[-1 - index[(protocol, bytes(dedup_key))]] = int(raw_id)
            ids = [raw_ids.get(-1 - i, 0) for i in plan.new]
            if len(raw_ids) != len(plan.new) or any(a >= b for a, b in itertools.pairwise(ids)):
                raise ConcurrentWriteError(
                    f"{len(plan.new) - len(raw_ids)} of {len(plan.new)} raw messages read as new were "
                    "stored meanwhile (or stored out of order)"
                )
        values = [
            v if v[_RAW_ID] >= 0 else (*v[:_RAW_ID], raw_ids[v[_RAW_ID]], *v[_RAW_ID + 1 :])
            for v in plan.values
        ]
        for _, rows in plan.notify:
            for r in rows:
                if r["raw_id"] < 0:
                    r["raw_id"] = raw_ids[r["raw_id"]]
        for dev in touched:
            st = self._devices.get(dev)
            if st is not None:
                st.raw_id = raw_ids.get(st.raw_id, st.raw_id) if st.raw_id is not None else None
                if any(e[3] < 0 for e in st.pending):  # (same times and order: still a heap)
                    st.pending = [(t, q, f, raw_ids.get(r, r)) for t, q, f, r in st.pending]
        if values:
            cur.executemany(self._sql_positions, values)
        if plan.evs:
            conn.execute(self._insert_events, plan.evs)
        if plan.last_update:
            cur.executemany(self._sql_last_update, [(t, d) for d, t in plan.last_update.items()])
        cur.close()
        saved, evicted = self._checkpoints_due()
        self._save(conn, saved, time.time())
        return plan.results, plan.notify, saved, evicted

    def close(self) -> None:
        """Stop the database thread (after the work queued on it) and checkpoint every state."""
        if self._executor is not None:
            self._executor.shutdown(wait=True)
        try:
            n = self.flush_checkpoints()
        except Exception:  # the database is away: the states are rebuilt by replay at the next start
            log.exception("checkpoints at shutdown failed")
        else:
            log.info("%d device checkpoints written at shutdown", n)

    def _notify(self, protocol: str, rows: list[dict[str, Any]]) -> None:
        """Hand the committed positions (rows of the engine in use) to every listener."""
        if not rows:
            return
        for listener in list(self.listeners):
            try:
                listener(protocol, rows)
            except Exception:  # a listener (a WebSocket client) must not fail the ingest
                log.exception("position listener failed")
