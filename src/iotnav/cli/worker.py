"""``iotnav worker``: process a share of the fleet from NATS JetStream (:mod:`iotnav.service.workers`)."""

from __future__ import annotations

import logging
from pathlib import Path
from typing import Annotated, Any

import typer

from iotnav.cli._common import user_errors

#: The raw-engine settings a worker shares with ``iotnav serve`` (``ServiceConfig`` names).
RAW_KEYS = ("raw_engine", "raw_engine_config", "raw_engines", "raw_output_interval_s")


def raw_settings(
    config: Path | None,
    raw_engine: str | None = None,
    raw_engine_config: str | None = None,
    raw_output_interval_s: float | None = None,
) -> dict[str, Any]:
    """The raw-engine settings of a worker (:class:`iotnav.service.workers.WorkerConfig` fields):
    those of serve's TOML file ``config`` (its defaults when None), then the options not None."""
    raw: dict[str, Any] = {}
    if config is not None:  # the raw engines of the edge's own settings
        from iotnav.service.app import ServiceConfig

        serve = ServiceConfig.from_toml(config)
        raw = {k: getattr(serve, k) for k in RAW_KEYS}
    given = (raw_engine, raw_engine_config, raw_output_interval_s)
    return raw | {k: v for k, v in zip(RAW_KEYS[:2] + RAW_KEYS[3:], given, strict=True) if v is not None}


def register(app: typer.Typer) -> None:
    """Register ``worker`` on ``app``."""

    @app.command("worker")
    @user_errors
    def worker_cmd(
        nats: Annotated[str, typer.Option("--nats", help="NATS server URL(s), comma-separated.")],
        db: Annotated[str, typer.Option("--db", help="Shared database URL (postgresql+psycopg://...).")],
        data: Annotated[
            Path, typer.Option("--data", help="Directory of the checkpoint key shared by all workers.")
        ] = Path("iotnav-data"),
        partitions: Annotated[int, typer.Option(help="Partitions P (the same on edges and workers).")] = 16,
        lease: Annotated[
            float, typer.Option(help="Lease time to live, s (a dead worker's share moves).")
        ] = 10.0,
        engine: Annotated[str, typer.Option(help="Engine for each device's fixes (fixes; none).")] = "fixes",
        checkpoint_interval: Annotated[
            float, typer.Option(help="Checkpoint a device's state after this long with changes, s.")
        ] = 60.0,
        reorder_window: Annotated[float, typer.Option(help="Device-time re-ordering window, s.")] = 0.0,
        registration: Annotated[
            str, typer.Option(help="open: unknown devices are registered; closed: API-created only.")
        ] = "open",
        alerts: Annotated[
            str, typer.Option(help="TOML file of the alert rules and delivery (as for serve).")
        ] = "",
        config: Annotated[
            Path | None,
            typer.Option(
                "--config",
                help="serve's TOML settings: its raw_engine, raw_engine_config, raw_engines, "
                "raw_output_interval_s (its serve table).",
            ),
        ] = None,
        raw_engine: Annotated[
            str | None, typer.Option(help="Engine of raw GNSS + IMU devices (pipeline; none).")
        ] = None,
        raw_engine_config: Annotated[
            str | None, typer.Option(help="TOML configuration of --raw-engine.")
        ] = None,
        raw_output_interval: Annotated[
            float | None,
            typer.Option(help="Raw devices' clean positions: at each fix and every this many s."),
        ] = None,
    ) -> None:
        """Process a share of the fleet from NATS JetStream: partitions by lease, state in the database."""
        import asyncio

        from iotnav.service.workers import ClusterSettings, WorkerConfig, run_worker

        if registration not in ("open", "closed"):
            raise ValueError(f"--registration {registration!r}: expected open or closed")
        raw = raw_settings(config, raw_engine, raw_engine_config, raw_output_interval)
        cfg = WorkerConfig(
            db=db,
            data=str(data),
            engine=engine,
            registration_open=registration == "open",
            reorder_window_s=reorder_window,
            checkpoint_interval_s=checkpoint_interval,
            alerts=alerts,
            **raw,
        )
        cluster = ClusterSettings(url=nats, partitions=partitions, lease_s=lease)
        logging.basicConfig(level=logging.WARNING, format="%(asctime)s %(name)s %(levelname)s %(message)s")
        asyncio.run(run_worker(cfg, cluster))
