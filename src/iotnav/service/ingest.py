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
"""

from __future__ import annotations

import asyncio
import hashlib
import heapq
import itertools
import json
import logging
import math
import operator
import pickle
import secrets
import time
from collections import OrderedDict
from collections.abc import Callable, Iterator, Sequence
from concurrent.futures import Executor, ThreadPoolExecutor
from contextlib import contextmanager
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any, TypeVar

import sqlalchemy as sa
from sqlalchemy.dialects import postgresql, sqlite
from sqlalchemy.engine import Connection, Engine

from iotnav.service import checkpoint
from iotnav.service.checkpoint import CheckpointError, DeviceState
from iotnav.service.protocols.common import Fix, finite_or_nan
from iotnav.service.store import (
    READ_ONLY,
    devices,
    engine_states,
    events,
    inserted_id,
    positions,
    raw_messages,
)

if TYPE_CHECKING:  # the engines (numba, scipy) load only when an engine runs
    from iotnav.engines.base import Engine as NavEngine
    from iotnav.engines.base import GnssSample, Output

log = logging.getLogger("iotnav.service")

NO_ENGINE = "none"
#: The engine of devices that send fixes only (every input of this version).
FIXES_ENGINE = "fixes"
#: Stored fixes replayed at most to rebuild a device without a checkpoint row (beyond: it
#: starts afresh after its last stored output, as after a discarded checkpoint).
REPLAY_LIMIT = 100_000


@dataclass
class Message:
    """A decoded message handed to the ingest.

    Attributes
    ----------
    protocol : str
        Input protocol (``teltonika``, ``osmand``, ``owntracks``, ...).
    device : str
        The device's unique id.
    payload : bytes
        The message as received (stored append-only in ``raw_messages``).
    fixes : list of Fix
        Its decoded records.
    remote : str or None
        Peer address or MQTT topic.
    received_at : float
        Server time of arrival, s since 1970 UTC.
    unique : bool
        The message is new whatever its bytes (an OsmAnd request without a timestamp repeats
        its bytes for every report); otherwise the same device and bytes are a duplicate.
    """

    protocol: str
    device: str
    payload: bytes
    fixes: list[Fix]
    remote: str | None = None
    received_at: float = field(default_factory=time.time)
    unique: bool = False

    def dedup_key(self) -> bytes:
        """De-duplication key of the raw message: SHA-256 of device id and bytes, the 32-byte
        digest (``raw_messages.dedup_key``)."""
        salt = repr(self.received_at).encode() if self.unique else b""
        return hashlib.sha256(self.device.encode("utf-8", "replace") + b"\x00" + self.payload + salt).digest()

    def digest(self) -> str:
        """:meth:`dedup_key` as hex text (the ``Nats-Msg-Id`` of :mod:`iotnav.service.workers`)."""
        return self.dedup_key().hex()


@dataclass(frozen=True)
class IngestResult:
    """What :meth:`Ingestor.ingest` did.

    ``accepted`` False: unknown device while registration is closed, or the message refused
    for ``reason`` (nothing stored; empty: the unknown device); ``duplicate``: the same message was stored before; ``n_new``: positions newly stored
    (``engine = 'none'``); ``n_engine``: engine positions stored.
    """

    accepted: bool
    duplicate: bool = False
    n_new: int = 0
    n_engine: int = 0
    device_id: int | None = None
    reason: str = ""


class ConcurrentWriteError(RuntimeError):
    """A raw message read as new before the write transaction was stored meanwhile (by another
    writer of the same device: the one-process-per-device rule was broken)."""


@dataclass
class _Plan:
    """A batch prepared before its write transaction (:meth:`Ingestor._prepare`).

    The messages to store (``new``, indices in arrival order: the order of their raw ids,
    which is the order of a replay) have provisional raw ids ``-1 - index`` in ``values`` (the
    positions rows' INSERT parameters), in ``notify`` and in the device states; the write
    transaction replaces them by the stored ids (:meth:`Ingestor._store`).
    """

    results: list[IngestResult]
    devs: list[int | None]
    digests: list[bytes]
    new: list[int]
    values: list[tuple[Any, ...]]
    evs: list[dict[str, Any]]
    notify: list[tuple[str, list[dict[str, Any]]]]
    last_update: dict[int, float]


T = TypeVar("T")


def group_commit(
    items: Sequence[T],
    store: Callable[[Sequence[T]], list[IngestResult]],
    on_split: Callable[[], None] | None = None,
    name: Callable[[T], str] = str,
) -> list[IngestResult | Exception]:
    """``store(items)`` (one transaction: the group commit); the result of each item, or its error.

    When that fails it is rolled back and, unless the database is unreachable
    (``OperationalError``: every item fails with it), each item is stored by ``store([item])``
    in a transaction of its own, so one bad item fails alone (``on_split`` is called once
    then; ``name`` labels an item in the log). Shared by the messages' ingest
    (:meth:`Ingestor.ingest_batch`) and the workers' raw batches
    (:meth:`iotnav.service.raw_ingest.RawProcessor.ingest_messages`).
    """
    if not items:
        return []
    try:
        return list(store(items))
    except Exception as exc:
        if len(items) == 1 or isinstance(exc, sa.exc.OperationalError):
            return [exc] * len(items)
        log.warning("a batch of %d failed (%r); storing them one by one", len(items), exc)
        if on_split is not None:
            on_split()
    out: list[IngestResult | Exception] = []
    for item in items:
        try:
            out += store([item])
        except Exception as exc:
            log.warning("%s: storing failed: %r", name(item), exc)
            out.append(exc)
    return out


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


@dataclass
class _RecentKeys:
    """The recent record keys of one device: every stored key of the device whose fix time is
    after ``horizon`` (s) is in ``keys`` (key -> fix time), so a fix newer than the horizon and
    not in ``keys`` is new without a query."""

    horizon: float
    keys: dict[str, float] = field(default_factory=dict)

    def add(self, key: str, t: float, bound: int) -> None:
        self.keys[key] = t
        while len(self.keys) > bound:  # forget the oldest key; the horizon moves past its time
            old = next(iter(self.keys))
            self.horizon = max(self.horizon, self.keys.pop(old))


_RAW_COLUMNS = ("device_id", "protocol", "received_at", "remote", "payload", "dedup_key", "n_records")
_RAW_CHUNK = 200  # rows of one multi-row INSERT of raw messages (7 parameters each)
_POSITION_COLUMNS = tuple(c.name for c in positions.columns if c.name != "id")


_position_tuple = operator.itemgetter(*_POSITION_COLUMNS)
_RAW_ID = _POSITION_COLUMNS.index("raw_id")
_ATTRIBUTES = _POSITION_COLUMNS.index("attributes")


def _position_values(row: dict[str, Any], attributes_json: str) -> tuple[Any, ...]:
    """The parameters of :data:`_POSITION_COLUMNS` of a positions row, its attributes as the JSON
    text ``attributes_json``."""
    values = _position_tuple(row)
    return (*values[:_ATTRIBUTES], attributes_json, *values[_ATTRIBUTES + 1 :])


def _strict_json(attrs: dict[str, Any]) -> tuple[dict[str, Any], str]:
    """``attrs`` as strict JSON (non-finite floats replaced by None) and its JSON text.

    Serialised once: the text of the usual case (every float finite) has no ``NaN`` or
    ``Infinity`` token; when it has one (also when a string merely contains it) the attributes
    are cleaned (:func:`clean_json`) and serialised again.
    """
    text = json.dumps(attrs)
    if "NaN" in text or "Infinity" in text:
        attrs = clean_json(attrs)
        text = json.dumps(attrs)
    return attrs, text


def _insert_of(db: Engine) -> Callable[..., Any]:
    """The dialect's ``insert`` (with ``ON CONFLICT``): SQLite and PostgreSQL."""
    if db.dialect.name == "postgresql":
        return postgresql.insert
    if db.dialect.name == "sqlite":
        return sqlite.insert
    raise ValueError(f"database {db.dialect.name!r}: the service supports SQLite and PostgreSQL")


def fix_of_row(unique_id: str, r: Any) -> Fix:
    """The :class:`Fix` a stored ``engine = 'none'`` position was made from (for a replay)."""
    attrs = r.attributes or {}
    num_sv = attrs.get("num_sv")
    hdop = attrs.get("hdop")
    return Fix(
        device=unique_id,
        t=float(r.fix_time),
        lat_deg=float(r.latitude),
        lon_deg=float(r.longitude),
        height_m=math.nan if r.altitude is None else float(r.altitude),
        speed_mps=math.nan if r.speed_mps is None else float(r.speed_mps),
        course_rad=math.nan if r.course_rad is None else float(r.course_rad),
        h_acc_m=math.nan if r.accuracy_m is None else float(r.accuracy_m),
        num_sv=int(num_sv) if isinstance(num_sv, int) and not isinstance(num_sv, bool) else -1,
        hdop=float(hdop) if isinstance(hdop, int | float) and not isinstance(hdop, bool) else math.nan,
        valid=bool(r.valid),
        attributes=attrs,
        key=r.dedup_key,
    )


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


class Ingestor:
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

    #: Recent record keys kept per device (the de-duplication cache).
    RECENT_KEYS = 128
    #: Checkpoints written at most per transaction besides those of evicted states (when
    #: ``checkpoint_interval_s`` > 0): a checkpoint of ``fixes`` costs about 0.2 ms, and the
    #: devices of a fleet that started together all come due together (10,000 at once would
    #: hold one transaction, and every ACK waiting on it, for seconds); the rest wait for the
    #: next transactions, oldest first.
    MAX_CHECKPOINTS_PER_BATCH = 64

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

    # --- devices -------------------------------------------------------------------------

    def device_id(self, conn: Connection, unique_id: str, protocol: str | None, now: float) -> int | None:
        """Id of the device ``unique_id``, created when registration is open; None if refused."""
        row = conn.execute(
            sa.select(devices.c.id, devices.c.disabled).where(devices.c.unique_id == unique_id)
        ).first()
        if row is not None:
            return None if row.disabled else int(row.id)
        return self._create_device(conn, unique_id, protocol, now) if self.registration_open else None

    @staticmethod
    def _create_device(conn: Connection, unique_id: str, protocol: str | None, now: float) -> int:
        """Insert the device ``unique_id`` (named after it); its id."""
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

    def _create_missing(self, missing: Sequence[Message], clock: float) -> None:
        """Create the devices of ``missing`` (registration open), in a write transaction of their
        own committed before the batch's: a batch that fails after it leaves them registered,
        with nothing stored for them yet (as a first contact whose message failed)."""
        with self.db.begin() as conn:
            created = self._create_devices(conn, missing)
        for unique_id, dev in created.items():  # created now: nothing is stored for them yet
            self._device_rows[unique_id] = (dev, clock)
            self._created.add(dev)

    def _device_ids(self, msgs: Sequence[Message], clock: float) -> list[int | None]:
        """The device id of each message (None: refused) from the rows read since ``clock - device_cache_s``."""
        rows = self._device_rows
        out: list[int | None] = []
        for m in msgs:
            entry = rows.get(m.device)
            out.append(entry[0] if entry is not None and clock - entry[1] <= self.device_cache_s else None)
        return out

    def _read_devices(self, conn: Connection, msgs: Sequence[Message], clock: float) -> list[Message]:
        """Read the device rows of ``msgs`` not cached since ``clock - device_cache_s`` (monotonic
        s); the first message of each device not in the table."""
        rows = self._device_rows
        if len(rows) > 4 * max(self.max_devices_in_memory, 1000):
            rows.clear()
        stale = sorted(
            {m.device for m in msgs if clock - rows.get(m.device, (None, -math.inf))[1] > self.device_cache_s}
        )
        for i in range(0, len(stale), 500):
            for r in conn.execute(
                sa.select(devices.c.id, devices.c.unique_id, devices.c.disabled).where(
                    devices.c.unique_id.in_(stale[i : i + 500])
                )
            ):
                rows[r.unique_id] = (None if r.disabled else int(r.id), clock)
        missing: dict[str, Message] = {}  # not in the table: the first message of each
        for m in msgs:
            entry = rows.get(m.device)
            if entry is None or clock - entry[1] > self.device_cache_s:
                missing.setdefault(m.device, m)
        return list(missing.values())

    def _create_devices(self, conn: Connection, msgs: Sequence[Message]) -> dict[str, int]:
        """Insert the devices of ``msgs`` (one each, named after its unique id); unique id -> id.

        Multi-row ``INSERT ... RETURNING`` on the driver's cursor: a fleet's first contact
        (10,000 devices within seconds) costs one statement per 200 devices, not one each.
        """
        ids: dict[str, int] = {}
        cur = conn.connection.cursor()
        for b in range(0, len(msgs), 200):
            chunk = msgs[b : b + 200]
            sql = self._sql_devices.format(values=", ".join([self._device_values] * len(chunk)))
            cur.execute(
                sql, tuple(v for m in chunk for v in (m.device, m.device, m.protocol, m.received_at, "{}"))
            )
            for dev, unique_id in cur.fetchall():
                ids[unique_id] = int(dev)
        cur.close()
        if len(ids) != len(msgs):
            raise RuntimeError(f"{len(msgs)} devices inserted, {len(ids)} returned")
        return ids

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

    def _recent_of(self, conn: Connection, dev: int) -> _RecentKeys:
        """The recent-keys cache of ``dev`` (a new one's horizon: its newest stored fix time)."""
        rec = self._recent.get(dev)
        if rec is not None:
            self._recent.move_to_end(dev)
            return rec
        newest = None
        if dev not in self._created:
            newest = conn.execute(
                sa.select(sa.func.max(positions.c.fix_time)).where(
                    positions.c.device_id == dev, positions.c.engine == NO_ENGINE
                )
            ).scalar()
        rec = self._recent[dev] = _RecentKeys(-math.inf if newest is None else float(newest))
        while len(self._recent) > max(1, self.max_devices_in_memory):
            self._recent.popitem(last=False)
        return rec

    def _new_fixes(self, conn: Connection, dev: int, fixes: list[Fix]) -> list[Fix]:
        """The fixes of ``fixes`` not stored yet for ``dev`` (and not repeated within the message).

        A fix newer than the cache's horizon is new unless its key is in the cache; only older
        fixes not in the cache are looked up in the database.
        """
        rec = self._recent_of(conn, dev)
        doubt = [f.key for f in fixes if f.key not in rec.keys and f.t <= rec.horizon]
        seen: set[str] = set()
        for i in range(0, len(doubt), 500):
            seen.update(
                conn.execute(
                    sa.select(positions.c.dedup_key).where(
                        positions.c.device_id == dev,
                        positions.c.engine == NO_ENGINE,
                        positions.c.dedup_key.in_(doubt[i : i + 500]),
                    )
                ).scalars()
            )
        out = []
        for f in fixes:
            if f.key not in seen and f.key not in rec.keys:
                rec.add(f.key, f.t, self.RECENT_KEYS)
                out.append(f)
        if len(out) < len(fixes):
            self._count_on_commit("duplicate_record", len(fixes) - len(out))
        return out

    @classmethod
    def _row(
        cls, dev: int, raw_id: int | None, engine: str, f: Fix, now: float, late: bool
    ) -> dict[str, Any]:
        """A positions row of a fix as sent; ``late``: older than what the engine had seen (flagged).

        ``num_sv`` and ``hdop`` go to the attributes (with ``hdop`` also when the satellites
        are unknown): a replay rebuilds the fix from the row (:func:`fix_of_row`).
        """
        return cls._row_values(dev, raw_id, engine, f, now, late)[0]

    @staticmethod
    def _row_values(
        dev: int, raw_id: int | None, engine: str, f: Fix, now: float, late: bool
    ) -> tuple[dict[str, Any], tuple[Any, ...]]:
        """:meth:`_row` and its INSERT parameters (:data:`_POSITION_COLUMNS`; attributes serialised once)."""
        if f.num_sv >= 0:
            attrs = {**f.attributes, "num_sv": f.num_sv, "hdop": _none_if_nan(f.hdop)}
        else:
            attrs = dict(f.attributes)
            if math.isfinite(f.hdop):
                attrs["hdop"] = f.hdop
        if late:
            attrs["late"] = True
        attrs, text = _strict_json(attrs)
        row = {
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
            "attributes": attrs,
            "dedup_key": f.key,
        }
        return row, _position_values(row, text)

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

    def _output_values(self, row: dict[str, Any]) -> tuple[Any, ...]:
        """The INSERT parameters of an engine row of :meth:`_output_row` (its few attribute texts cached)."""
        attrs = row["attributes"]
        key = (attrs["source"], attrs["static"])
        text = self._output_json.get(key)
        if text is None:
            text = self._output_json[key] = json.dumps(attrs)
        return _position_values(row, text)

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
            "attributes": {"source": str(out.source), "static": bool(out.static)},
            "dedup_key": f.key,
        }
