"""Configuration of ``iotnav serve`` and the event loop that runs its listeners.

:func:`run` upgrades the database to the head migration, makes sure an admin token exists
(:func:`ensure_admin_token`), then serves Teltonika on TCP, OsmAnd / OwnTracks on HTTP and
the API on HTTP in one asyncio loop until SIGINT or SIGTERM. Every database write goes
through one worker thread (:attr:`iotnav.service.ingest.Ingestor.executor`).
"""

from __future__ import annotations

import asyncio
import contextlib
import dataclasses
import functools
import gc
import logging
import os
import secrets
import signal
import time
import tomllib
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import sqlalchemy as sa

from iotnav.service import store
from iotnav.service.checkpoint import load_key
from iotnav.service.ingest import Ingestor
from iotnav.service.teltonika_tcp import TcpLimits, TeltonikaServer

log = logging.getLogger("iotnav.service")

ADMIN_TOKEN_FILE = "admin_token"


@dataclass(frozen=True)
class ServiceConfig:
    """Settings of ``iotnav serve`` (TOML table ``[serve]`` or top level; CLI options override).

    Attributes
    ----------
    data : str
        Data directory (SQLite file ``iotnav.sqlite``, ``admin_token``).
    db : str
        SQLAlchemy URL; empty for SQLite in ``data``.
    host : str
        Address the listeners bind.
    teltonika_port, osmand_port, api_port : int
        Traccar's defaults: 5027 (Teltonika), 5055 (OsmAnd), 8082 (web / API).
    engine : str
        Engine run on each device's fixes (``fixes``, the GNSS-only engine; ``none`` stores
        fixes only; an unavailable engine falls back to ``none`` with a warning, an engine
        that needs IMU samples to ``fixes``, :mod:`iotnav.service.ingest`).
    engine_config : str
        TOML configuration of the engine (empty: its defaults).
    registration_open : bool
        Unknown devices are registered on first contact; False: only devices created
        through the API are accepted (Teltonika answers ``00``, HTTP 400).
    osmand_speed_unit : str
        Unit of OsmAnd's ``speed`` query parameter: ``kn`` (Traccar's default), ``kmh``, ``mps``.
    tile_url, tile_attribution : str
        Map tiles of the web page at the API's root (:mod:`iotnav.service.web`), a
        ``https://.../{z}/{x}/{y}.png`` template, and the credit the tile provider asks for;
        empty: no tiles, the page draws on a plain metric grid (offline).
    reorder_window_s : float
        Device-time window within which out-of-order fixes are re-ordered before the engine, s.
    checkpoint_interval_s : float
        A device's engine state is checkpointed after this long with unsaved changes, s (and
        at shutdown); a restart after a crash replays the fixes stored since (0: a checkpoint
        with every message; :mod:`iotnav.service.ingest`).
    retention_days : float
        Raw messages, positions and events older than this (server time) are deleted at start
        and every hour; 0 keeps everything.
    max_packet_bytes, idle_timeout_s, packet_timeout_s, max_connections_per_address
        TCP limits (:class:`~iotnav.service.teltonika_tcp.TcpLimits`).
    mqtt : str
        MQTT broker URL (``mqtt://host:1883``) for OwnTracks over MQTT; empty: no MQTT.
    mqtt_client_id, mqtt_topic : str
        Client id of the persistent session and the topic filter subscribed with QoS 1.
    mqtt_raw_topic : str
        Topic filter of raw GNSS + IMU batches (:mod:`iotnav.service.protocols.iotnav_raw`),
        subscribed with ``mqtt`` unless ``raw_engine`` is ``none``.
    raw_engine, raw_engine_config : str
        Engine of raw IMU devices (``pipeline``) and its TOML configuration
        (:class:`iotnav.service.raw_ingest.RawSettings`); ``none``: no raw topic.
    raw_engines : dict
        Unique-id pattern (``fnmatch``) -> engine (``name`` or ``name:config.toml``) for groups
        of raw devices; a device's ``attributes.engine`` comes first.
    raw_output_interval_s : float
        Clean positions of raw devices stored at each fix and every this many seconds, s (0: all).
    nmea_port : int
        Raw NMEA 0183 over TCP (:mod:`iotnav.service.nmea_tcp`); 0: off (10110 is IANA's port).
    nmea_device_id : str
        Device id of NMEA connections that send no id line.
    nats, nats_partitions
        NATS JetStream URL and partition count: this service is then an ingest edge that
        publishes every message to JetStream, and ``iotnav worker`` processes store them
        (:mod:`iotnav.service.workers`); empty: messages are stored here. Raw GNSS + IMU
        batches too: the edge only checks and publishes them (``raw_engine`` other than
        ``none`` subscribes the raw topic); the workers run the raw engines.
    alerts : str or dict
        Alerts (:mod:`iotnav.service.alerts_delivery`): a TOML file with an ``[alerts]`` table,
        or the table itself; empty: no alerts.
    processes : int
        Processes that run the Teltonika devices (:mod:`iotnav.service.multiproc`): 1 (the
        default) runs everything in this process; N > 1 starts N worker processes, each
        device's connection handed to one of them by a stable hash of its IMEI (the other
        listeners and the API stay in this process). SQLite or PostgreSQL; not with ``nats``;
        with ``alerts`` on SQLite only (its one write lock commits rows in id order).
    """

    data: str = "iotnav-data"
    db: str = ""
    host: str = "0.0.0.0"
    teltonika_port: int = 5027
    osmand_port: int = 5055
    api_port: int = 8082
    engine: str = "fixes"
    engine_config: str = ""
    registration_open: bool = True
    osmand_speed_unit: str = "kn"
    tile_url: str = ""
    tile_attribution: str = ""
    reorder_window_s: float = 0.0
    checkpoint_interval_s: float = 60.0
    retention_days: float = 0.0
    max_packet_bytes: int = TcpLimits.max_packet_bytes
    idle_timeout_s: float = TcpLimits.idle_timeout_s
    packet_timeout_s: float = TcpLimits.packet_timeout_s
    max_connections_per_address: int = TcpLimits.max_connections_per_address
    mqtt: str = ""
    mqtt_client_id: str = "iotnav-serve"
    mqtt_topic: str = "owntracks/+/+"
    alerts: str | dict[str, Any] = ""
    mqtt_raw_topic: str = "iotnav/+/raw"
    raw_engine: str = "pipeline"
    raw_engine_config: str = ""
    raw_engines: dict[str, str] = dataclasses.field(default_factory=dict)
    raw_output_interval_s: float = 1.0
    nmea_port: int = 0
    nmea_device_id: str = ""
    nats: str = ""
    nats_partitions: int = 16
    processes: int = 1

    @classmethod
    def from_toml(cls, path: str | Path, **overrides: Any) -> ServiceConfig:
        """Settings from a TOML file (``[serve]`` table or top level), then ``overrides`` (not None)."""
        with open(path, "rb") as fh:
            doc = tomllib.load(fh)
        table = doc.get("serve", doc)
        return cls.from_dict({**table, **{k: v for k, v in overrides.items() if v is not None}})

    @classmethod
    def from_dict(cls, values: dict[str, Any]) -> ServiceConfig:
        """Settings from a dict; unknown keys raise ValueError naming them."""
        names = {f.name: f for f in dataclasses.fields(cls)}
        unknown = sorted(set(values) - set(names))
        if unknown:
            raise ValueError(f"unknown serve setting(s): {', '.join(unknown)}; expected {', '.join(names)}")
        return cls(**values)

    def __post_init__(self) -> None:
        from iotnav.service.web import check_tile_url

        check_tile_url(self.tile_url)
        if not (isinstance(self.processes, int) and 1 <= self.processes <= 64):
            raise ValueError(f"processes {self.processes!r}: expected an integer from 1 to 64")
        if self.processes > 1 and self.nats:
            raise ValueError("processes > 1 with nats: run several iotnav worker processes instead")
        if self.processes > 1 and self.alerts and not self.db_url.startswith("sqlite"):
            # the alerts' tail reads new rows by id (iotnav.service.alerts_delivery): on SQLite
            # every writer, each process's, holds the one database write lock (BEGIN IMMEDIATE)
            # from its first insert to its commit, so ids are committed in order; PostgreSQL's
            # sequences hand out ids that concurrent transactions commit out of order
            raise ValueError(
                "processes > 1 with alerts needs SQLite: on PostgreSQL run iotnav worker --alerts"
            )

    @property
    def db_url(self) -> str:
        """The database URL in use."""
        return self.db or store.sqlite_url(self.data)

    @property
    def limits(self) -> TcpLimits:
        """The TCP limits."""
        return TcpLimits(
            self.max_packet_bytes,
            self.idle_timeout_s,
            self.packet_timeout_s,
            self.max_connections_per_address,
        )


def ensure_admin_token(db: sa.engine.Engine, data_dir: Path) -> str | None:
    """Make sure an admin token exists; return where it came from.

    ``IOTNAV_ADMIN_TOKEN`` (if set) is registered as an admin token. Otherwise, when the
    database has no admin token, one is created and written to ``DATA/admin_token`` (mode
    0600); only its SHA-256 is stored in the database.
    """
    env = os.environ.get("IOTNAV_ADMIN_TOKEN")
    with db.begin() as conn:
        if env:
            digest = store.token_digest(env)
            if (
                conn.execute(
                    sa.select(store.api_tokens.c.id).where(store.api_tokens.c.token_sha256 == digest)
                ).first()
                is None
            ):
                conn.execute(
                    store.api_tokens.insert().values(
                        name="IOTNAV_ADMIN_TOKEN", token_sha256=digest, scope="admin", created_at=time.time()
                    )
                )
            return "IOTNAV_ADMIN_TOKEN"
        if conn.execute(sa.select(store.api_tokens.c.id).where(store.api_tokens.c.scope == "admin")).first():
            return None
        token = secrets.token_urlsafe(32)
        path = data_dir / ADMIN_TOKEN_FILE
        fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)
        with os.fdopen(fd, "w") as fh:
            fh.write(token + "\n")
        conn.execute(
            store.api_tokens.insert().values(
                name="first start",
                token_sha256=store.token_digest(token),
                scope="admin",
                created_at=time.time(),
            )
        )
        return str(path)


def create_token(db: sa.engine.Engine, name: str, scope: str) -> str:
    """A new bearer token of ``scope`` (``read`` or ``admin``); only its digest is stored."""
    if scope not in store.SCOPES:
        raise ValueError(f"scope {scope!r}: expected one of {', '.join(store.SCOPES)}")
    token = secrets.token_urlsafe(32)
    with db.begin() as conn:
        conn.execute(
            store.api_tokens.insert().values(
                name=name, token_sha256=store.token_digest(token), scope=scope, created_at=time.time()
            )
        )
    return token


def _uvicorn_server(app: Any, host: str, port: int) -> Any:
    import uvicorn

    class Server(uvicorn.Server):
        """uvicorn without its own signal handling (:func:`run` stops all listeners together)."""

        @contextlib.contextmanager
        def capture_signals(self) -> Iterator[None]:
            yield

    return Server(
        uvicorn.Config(app, host=host, port=port, log_level="warning", lifespan="off", access_log=False)
    )


def prepare(config: ServiceConfig) -> tuple[sa.engine.Engine, Ingestor]:
    """Open and upgrade the database, ensure the admin token; the database engine and the ingestor."""
    data = Path(config.data)
    data.mkdir(parents=True, exist_ok=True)
    db = store.make_engine(config.db_url, immediate=config.processes > 1)
    store.upgrade(db)
    where = ensure_admin_token(db, data)
    if where:
        log.warning("admin token: %s", where)
    return db, make_ingestor(config, db)


def make_ingestor(config: ServiceConfig, db: sa.engine.Engine) -> Ingestor:
    """The ingestor of ``config`` on ``db`` (schema at head), its engine warmed up."""
    data = Path(config.data)
    make: Any = Ingestor
    if config.nats:  # an ingest edge: messages go to JetStream, workers store them
        from iotnav.service.worker_edge import EdgeIngestor
        from iotnav.service.workers import ClusterSettings

        if config.alerts:  # the edge would tail the database too: every alert twice
            raise ValueError("alerts with nats: give the alerts to the workers (iotnav worker --alerts)")

        make = functools.partial(EdgeIngestor, cluster=ClusterSettings(config.nats, config.nats_partitions))
    ingestor: Ingestor = make(
        db,
        config.engine,
        config.registration_open,
        config.engine_config or None,
        reorder_window_s=config.reorder_window_s,
        checkpoint_key=load_key(data),
        checkpoint_interval_s=config.checkpoint_interval_s,
    )
    log.info("engine %s ready in %.1f s", ingestor.engine_name, ingestor.warm_up())
    return ingestor


def _raw_processor(config: ServiceConfig, ingestor: Ingestor, background: bool = False) -> Any:
    """The processor of raw GNSS + IMU batches (:mod:`iotnav.service.raw_ingest`); None if off.

    Its engine is warmed up (kernels loaded or compiled) here, or with ``background`` in a thread
    of its own, so that the service answers its other devices meanwhile.
    """
    if config.raw_engine == "none":
        return None
    from iotnav.service.raw_ingest import RawProcessor, RawSettings

    raw = RawProcessor(
        ingestor,
        RawSettings(
            config.raw_engine,
            config.raw_engine_config,
            dict(config.raw_engines),
            config.raw_output_interval_s,
        ),
    )

    def warm() -> None:
        log.info("raw engine %s ready in %.1f s", config.raw_engine, raw.warm_up())

    if background:
        import threading

        threading.Thread(target=warm, name="iotnav-raw-warm-up", daemon=True).start()
    else:
        warm()
    return raw


def _with_map(api: Any, config: ServiceConfig) -> Any:
    """The API app with the web map at its root (:func:`iotnav.service.web.mount_web`)."""
    from iotnav.service.web import mount_web

    mount_web(api, config.tile_url, config.tile_attribution)
    return api


async def serve(config: ServiceConfig) -> None:
    """Run every listener until SIGINT / SIGTERM."""
    from iotnav.service.http import api_app, device_app

    db, ingestor = prepare(config)
    if config.nats:
        await ingestor.connect()  # type: ignore[attr-defined]
    # a young-generation collection per 50,000 allocations instead of 700: the ingest of one
    # message allocates hundreds of objects and the heap holds every device's state, which the
    # older generations' collections walk (in-process, 2,000 devices: 108 -> 92 us of CPU per
    # message in one run, within the noise of a loaded machine in another); what the service
    # keeps is freed by reference counting, the collector only breaks cycles
    gc.set_threshold(50_000, 20, 20)
    executor = ingestor.executor  # the database thread
    http_servers = [
        _uvicorn_server(
            device_app(ingestor, executor, config.osmand_speed_unit), config.host, config.osmand_port
        ),
        _uvicorn_server(api := _with_map(api_app(db, ingestor), config), config.host, config.api_port),
    ]
    # everything imported and built so far lives as long as the service: out of the collector's
    # generations, its full collections walk only what the devices add
    gc.freeze()
    stop = asyncio.Event()
    loop = asyncio.get_running_loop()
    for sig in (signal.SIGINT, signal.SIGTERM):
        with contextlib.suppress(NotImplementedError, RuntimeError):
            loop.add_signal_handler(sig, stop.set)
    subscriber = None
    if config.mqtt:
        from iotnav.service.mqtt import MqttSettings, MqttSubscriber

        # an edge publishes raw batches to JetStream: the workers run the raw engine
        raw = None if config.nats else _raw_processor(config, ingestor, background=True)
        publish_raw = bool(config.nats) and config.raw_engine != "none"
        settings = MqttSettings(config.mqtt, config.mqtt_client_id, config.mqtt_topic, config.mqtt_raw_topic)
        mqtt_sub = MqttSubscriber(settings, ingestor, executor, raw, publish_raw)
        subscriber = asyncio.create_task(mqtt_sub.run())
    nmea_server = None
    if config.nmea_port:
        from iotnav.service.nmea_tcp import NmeaServer, NmeaSettings

        nmea = NmeaServer(
            ingestor, executor, NmeaSettings(config.nmea_port, config.nmea_device_id), config.limits
        )
        nmea_server = await nmea.start(config.host, config.nmea_port)
    tasks = [asyncio.create_task(s.serve()) for s in http_servers]
    if hasattr(ingestor, "socket_send"):  # an edge: the workers' alerts to its /api/socket
        ingestor.socket_send = api.state.socket_send
    alerts = None
    if config.alerts:  # alerts_delivery loads the tracker (pandas, numba) only when alerts are on
        from iotnav.service.alerts_delivery import start_alerts

        alerts = start_alerts(config.alerts, db, ingestor, executor, api.state.socket_send)

    async def retention() -> None:
        while True:
            try:
                await loop.run_in_executor(executor, ingestor.purge, config.retention_days)
            except Exception:  # the database may be away; try again in an hour
                log.exception("retention: purge failed")
            await asyncio.sleep(3600.0)

    # not among the tasks whose end stops the service
    purger = asyncio.create_task(retention()) if config.retention_days > 0 else None
    # the worker processes last: a setting refused above (an alerts file, say) must end the
    # service before there are processes to stop (they are not daemons: the exit would wait)
    pool = None
    if config.processes > 1:  # the Teltonika devices in worker processes (iotnav.service.multiproc)
        from iotnav.service.multiproc import WorkerPool

        pool = WorkerPool(config, ingestor)
        await pool.start()
        try:
            tcp_server = await pool.listen(config.host, config.teltonika_port)
        except BaseException:  # the port taken, say: the workers go too
            await pool.stop()
            raise
    else:
        tcp_server = await TeltonikaServer(ingestor, executor, config.limits).start(
            config.host, config.teltonika_port
        )
    log.warning(
        "iotnav serve: engine %s, %d process(es), Teltonika tcp/%d, OsmAnd http/%d, API http/%d, database %s",
        ingestor.engine_name,
        config.processes,
        config.teltonika_port,
        config.osmand_port,
        config.api_port,
        db.url.render_as_string(hide_password=True),
    )
    try:
        done, _ = await asyncio.wait(
            [asyncio.create_task(stop.wait()), *tasks], return_when=asyncio.FIRST_COMPLETED
        )
        for t in done:
            if t in tasks and t.exception() is not None:
                raise t.exception()  # type: ignore[misc]
    finally:
        if alerts is not None:
            await alerts.stop()
        if purger is not None:
            purger.cancel()
        if subscriber is not None:
            subscriber.cancel()
            await asyncio.gather(subscriber, return_exceptions=True)
        for s in http_servers:
            s.should_exit = True
        tcp_server.close()
        if pool is not None:
            await pool.stop()
        if nmea_server is not None:
            nmea_server.close()
        await asyncio.gather(*tasks, return_exceptions=True)
        if config.nats:
            await ingestor.disconnect()  # type: ignore[attr-defined]
        ingestor.close()  # the database thread's queue, then every device's checkpoint
        db.dispose()


def main(argv: list[str] | None = None) -> None:
    """``python -m iotnav.service CONFIG.toml``: :func:`serve` with a TOML file only.

    The same service as ``iotnav serve --config CONFIG.toml``, without loading the rest of
    the command line (for process supervisors and the tests).
    """
    import sys

    args = sys.argv[1:] if argv is None else argv
    if len(args) != 1:
        raise SystemExit("usage: python -m iotnav.service CONFIG.toml")
    logging.basicConfig(level=logging.WARNING, format="%(asctime)s %(name)s %(levelname)s %(message)s")
    asyncio.run(serve(ServiceConfig.from_toml(args[0])))
