"""Storage of the service: SQLAlchemy 2 Core tables, the same schema on SQLite and PostgreSQL.

The schema is created and upgraded by the Alembic migrations in ``migrations/``
(:func:`upgrade`, run at every start); :data:`metadata` mirrors the head revision and
``tests/test_service_store.py`` checks that the two agree.

Tables
    ``devices``       one row per tracker (``unique_id`` IMEI / OsmAnd id / OwnTracks user/device);
    ``raw_messages``  every accepted message as received, append-only, unique per
                      (``protocol``, ``dedup_key``) so a message resent is stored once;
                      ``dedup_key`` is the 32-byte SHA-256 digest (binary: half the bytes
                      of its hex text in the unique index every message writes; migration
                      ``0004``);
    ``positions``     clean fixes (``engine = 'none'``: the fix as sent) and engine outputs
                      (``engine`` = the engine's name), unique per (``device_id``, ``engine``,
                      ``dedup_key``);
    ``events``        per-device events (late fixes, engine events);
    ``engine_states`` the checkpoint of each device's engine (:mod:`iotnav.service.checkpoint`),
                      written in the transaction that stores the fixes it has seen;
    ``geofences``     named areas (Traccar's area text, :mod:`iotnav.service.geofence`);
    ``api_tokens``    bearer tokens, stored as SHA-256 digests only, with a scope (``read`` or
                      ``admin``).

Times are float seconds since 1970 UTC; speeds m/s; courses radians (SI inside; the API
converts to Traccar's knots and degrees). On SQLite every connection runs in WAL mode with
``synchronous=FULL``: a committed transaction survives a power cut, not only a crash of the
process. ``synchronous=NORMAL`` would also keep every committed transaction across a crash or
kill -9 of the process ("Transactions are durable across application crashes regardless of
the synchronous setting or journal mode", https://www.sqlite.org/pragma.html#pragma_synchronous),
but in WAL mode it "might roll back following a power loss or system crash"; since the ingest
commits a batch of messages per transaction (group commit, :mod:`iotnav.service.ingest`), the
fsync of ``FULL`` is paid once per batch and is kept.
"""

from __future__ import annotations

import hashlib
from pathlib import Path
from typing import Any

import sqlalchemy as sa
from sqlalchemy import event
from sqlalchemy.engine import Engine

metadata = sa.MetaData()

devices = sa.Table(
    "devices",
    metadata,
    sa.Column("id", sa.Integer, primary_key=True, autoincrement=True),
    sa.Column("unique_id", sa.String(128), nullable=False, unique=True),
    sa.Column("name", sa.String(256), nullable=False),
    sa.Column("protocol", sa.String(32), nullable=True),
    sa.Column("created_at", sa.Float, nullable=False),
    sa.Column("last_update", sa.Float, nullable=True),
    sa.Column("disabled", sa.Boolean, nullable=False, server_default=sa.false()),
    sa.Column("attributes", sa.JSON, nullable=False),
)

raw_messages = sa.Table(
    "raw_messages",
    metadata,
    sa.Column("id", sa.Integer, primary_key=True, autoincrement=True),
    sa.Column("device_id", sa.Integer, sa.ForeignKey("devices.id", ondelete="CASCADE"), nullable=False),
    sa.Column("protocol", sa.String(32), nullable=False),
    sa.Column("received_at", sa.Float, nullable=False),
    sa.Column("remote", sa.String(128), nullable=True),
    sa.Column("payload", sa.LargeBinary, nullable=False),
    sa.Column("dedup_key", sa.LargeBinary(32), nullable=False),
    sa.Column("n_records", sa.Integer, nullable=False),
    sa.UniqueConstraint("protocol", "dedup_key", name="uq_raw_messages_protocol_dedup"),
)

positions = sa.Table(
    "positions",
    metadata,
    sa.Column("id", sa.Integer, primary_key=True, autoincrement=True),
    sa.Column("device_id", sa.Integer, sa.ForeignKey("devices.id", ondelete="CASCADE"), nullable=False),
    sa.Column("raw_id", sa.Integer, sa.ForeignKey("raw_messages.id", ondelete="SET NULL"), nullable=True),
    sa.Column("engine", sa.String(32), nullable=False),
    sa.Column("fix_time", sa.Float, nullable=False),
    sa.Column("server_time", sa.Float, nullable=False),
    sa.Column("valid", sa.Boolean, nullable=False),
    sa.Column("latitude", sa.Float, nullable=False),
    sa.Column("longitude", sa.Float, nullable=False),
    sa.Column("altitude", sa.Float, nullable=True),
    sa.Column("speed_mps", sa.Float, nullable=True),
    sa.Column("course_rad", sa.Float, nullable=True),
    sa.Column("accuracy_m", sa.Float, nullable=True),
    sa.Column("attributes", sa.JSON, nullable=False),
    sa.Column("dedup_key", sa.String(64), nullable=False),
    sa.UniqueConstraint("device_id", "engine", "dedup_key", name="uq_positions_device_engine_dedup"),
    sa.Index("ix_positions_device_engine_time", "device_id", "engine", "fix_time"),
)

events = sa.Table(
    "events",
    metadata,
    sa.Column("id", sa.Integer, primary_key=True, autoincrement=True),
    sa.Column("device_id", sa.Integer, sa.ForeignKey("devices.id", ondelete="CASCADE"), nullable=False),
    sa.Column("type", sa.String(64), nullable=False),
    sa.Column("event_time", sa.Float, nullable=False),
    sa.Column("server_time", sa.Float, nullable=False),
    sa.Column("attributes", sa.JSON, nullable=False),
    sa.Index("ix_events_device_time", "device_id", "event_time"),
)

engine_states = sa.Table(
    "engine_states",
    metadata,
    sa.Column("device_id", sa.Integer, sa.ForeignKey("devices.id", ondelete="CASCADE"), nullable=False),
    sa.Column("engine", sa.String(32), nullable=False),
    sa.Column("saved_at", sa.Float, nullable=False),
    sa.Column("last_t", sa.Float, nullable=True),
    sa.Column("format", sa.String(64), nullable=False),
    sa.Column("state", sa.LargeBinary, nullable=False),
    sa.PrimaryKeyConstraint("device_id", "engine", name="pk_engine_states"),
)

geofences = sa.Table(
    "geofences",
    metadata,
    sa.Column("id", sa.Integer, primary_key=True, autoincrement=True),
    sa.Column("name", sa.String(256), nullable=False),
    sa.Column("description", sa.Text, nullable=True),
    sa.Column("area", sa.Text, nullable=False),
    sa.Column("attributes", sa.JSON, nullable=False),
)

api_tokens = sa.Table(
    "api_tokens",
    metadata,
    sa.Column("id", sa.Integer, primary_key=True, autoincrement=True),
    sa.Column("name", sa.String(128), nullable=False),
    sa.Column("token_sha256", sa.String(64), nullable=False, unique=True),
    sa.Column("scope", sa.String(16), nullable=False),
    sa.Column("created_at", sa.Float, nullable=False),
)

SCOPES = ("read", "admin")


def sqlite_url(data_dir: str | Path) -> str:
    """The SQLAlchemy URL of the service's SQLite file in ``data_dir``."""
    return f"sqlite:///{Path(data_dir).resolve() / 'iotnav.sqlite'}"


def _sqlite_pragmas(dbapi_conn: Any, _record: Any) -> None:
    cur = dbapi_conn.cursor()
    cur.execute("PRAGMA journal_mode=WAL")
    cur.execute("PRAGMA synchronous=FULL")
    cur.execute("PRAGMA foreign_keys=ON")
    cur.execute("PRAGMA busy_timeout=10000")
    cur.close()


def _driver_transactions_off(dbapi_conn: Any, _record: Any) -> None:
    dbapi_conn.isolation_level = None  # the driver's own implicit BEGIN (deferred) is off


#: Execution option of a connection that only reads (:meth:`iotnav.service.ingest.Ingestor`
#: prepares a batch with one): on an ``immediate`` engine its transactions start with a
#: deferred ``BEGIN``, a read snapshot that does not take the write lock.
READ_ONLY = "iotnav_read_only"


def _begin_immediate(conn: sa.Connection) -> None:
    conn.exec_driver_sql("BEGIN" if conn.get_execution_options().get(READ_ONLY) else "BEGIN IMMEDIATE")


def make_engine(url: str, immediate: bool = False) -> Engine:
    """A SQLAlchemy engine for ``url``; SQLite connections get WAL, ``synchronous=FULL``, foreign keys.

    ``immediate`` (SQLite; for several writing processes, :mod:`iotnav.service.multiproc`):
    every transaction starts with ``BEGIN IMMEDIATE``, taking the write lock (waiting up to the
    ``busy_timeout`` of 10 s) before its first read. With the driver's deferred ``BEGIN``, a
    transaction that reads and then writes while another process has committed since its read
    fails at once with ``SQLITE_BUSY`` instead of waiting (https://www.sqlite.org/lang_transaction.html).
    A connection with the execution option :data:`READ_ONLY` begins deferred (reads only).
    """
    engine = sa.create_engine(url, future=True)
    if engine.dialect.name == "sqlite":
        event.listen(engine, "connect", _sqlite_pragmas)
        if immediate:
            event.listen(engine, "connect", _driver_transactions_off)
            event.listen(engine, "begin", _begin_immediate)
    return engine


#: Key of the PostgreSQL advisory lock that serialises :func:`upgrade` across processes (any
#: constant unique to iotnav: the ASCII of "iotnav" as an integer).
MIGRATION_LOCK_KEY = 0x696F746E6176


def upgrade(engine: Engine, revision: str = "head") -> None:
    """Bring the database to ``revision`` with the package's Alembic migrations.

    Processes that start at once on one PostgreSQL database (a service and its workers) take
    turns: the migration runs under a transaction-scoped advisory lock, so the second finds the
    schema at ``revision`` instead of racing to create the same tables.
    """
    from alembic import command
    from alembic.config import Config

    cfg = Config()
    cfg.set_main_option("script_location", str(Path(__file__).parent / "migrations"))
    with engine.connect() as conn:
        # SQLite: a migration that rebuilds a table (Alembic's batch mode: copy, DROP, rename)
        # runs with foreign keys off, else the DROP of ``raw_messages`` would fire positions'
        # ``ON DELETE SET NULL`` on every ``raw_id`` (https://www.sqlite.org/lang_altertable.html,
        # "Making Other Kinds Of Table Schema Changes"); the pragma is a no-op inside a
        # transaction, so it is set on the driver's connection before the transaction begins
        raw = conn.connection.dbapi_connection if conn.dialect.name == "sqlite" else None
        if raw is not None:
            raw.execute("PRAGMA foreign_keys=OFF")
        try:
            with conn.begin():
                if conn.dialect.name == "postgresql":
                    conn.execute(sa.text("SELECT pg_advisory_xact_lock(:k)"), {"k": MIGRATION_LOCK_KEY})
                cfg.attributes["connection"] = conn
                command.upgrade(cfg, revision)
                if raw is not None and conn.exec_driver_sql("PRAGMA foreign_key_check").first():
                    raise RuntimeError("migration left rows whose foreign keys do not match")
        finally:
            if raw is not None:
                raw.execute("PRAGMA foreign_keys=ON")


def token_digest(token: str) -> str:
    """SHA-256 of a bearer token, hex (tokens are 256-bit random strings: no salt needed)."""
    return hashlib.sha256(token.encode()).hexdigest()


def inserted_id(result: sa.CursorResult[Any]) -> int:
    """Primary key of the row an ``INSERT`` made."""
    key = result.inserted_primary_key
    if key is None:
        raise RuntimeError("INSERT returned no primary key")
    return int(key[0])
