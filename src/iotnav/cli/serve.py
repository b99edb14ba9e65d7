"""``iotnav serve``: the live service (Teltonika TCP, OsmAnd / OwnTracks HTTP, the API)."""

from __future__ import annotations

import logging
from pathlib import Path
from typing import Annotated

import typer

from iotnav.cli._common import user_errors


def register(app: typer.Typer) -> None:
    """Register ``serve`` on ``app``."""

    @app.command("serve")
    @user_errors
    def serve_cmd(
        data: Annotated[
            Path | None, typer.Option("--data", help="Data directory (SQLite, admin token).")
        ] = None,
        config: Annotated[
            Path | None, typer.Option("--config", help="TOML settings ([serve] table).")
        ] = None,
        db: Annotated[
            str | None, typer.Option("--db", help="SQLAlchemy URL (default: SQLite in --data).")
        ] = None,
        host: Annotated[str | None, typer.Option(help="Address to bind.")] = None,
        teltonika_port: Annotated[int | None, typer.Option(help="Teltonika TCP port (5027).")] = None,
        osmand_port: Annotated[int | None, typer.Option(help="OsmAnd / OwnTracks HTTP port (5055).")] = None,
        api_port: Annotated[int | None, typer.Option(help="API HTTP port (8082).")] = None,
        engine: Annotated[
            str | None, typer.Option(help="Engine for each device's fixes (fixes; none).")
        ] = None,
        mqtt: Annotated[
            str | None, typer.Option(help="MQTT broker URL (mqtt://host:1883) for OwnTracks over MQTT.")
        ] = None,
        registration: Annotated[
            str | None, typer.Option(help="open: unknown devices are registered; closed: API-created only.")
        ] = None,
        tile_url: Annotated[
            str | None,
            typer.Option(
                help="Map tiles of the web page, https://.../{z}/{x}/{y}.png (none: a metric grid)."
            ),
        ] = None,
        raw_engine: Annotated[
            str | None,
            typer.Option(help="Engine of raw GNSS + IMU devices on MQTT iotnav/<id>/raw (pipeline; none)."),
        ] = None,
        nmea_port: Annotated[
            int | None, typer.Option(help="Raw NMEA over TCP port (0: off; 10110 is IANA's nmea-0183).")
        ] = None,
        nats: Annotated[
            str | None, typer.Option(help="NATS JetStream URL: publish to workers (iotnav worker).")
        ] = None,
        processes: Annotated[
            int | None,
            typer.Option(
                help="Processes for the Teltonika devices (1: all in this one; N: N workers, "
                "each device's connection handed to one by a hash of its IMEI)."
            ),
        ] = None,
    ) -> None:
        """Serve trackers live: Teltonika on TCP, OsmAnd and OwnTracks on HTTP, a Traccar-compatible API."""
        import asyncio

        from iotnav.service.app import ServiceConfig, serve

        if registration not in (None, "open", "closed"):
            raise ValueError(f"--registration {registration!r}: expected open or closed")
        overrides = {
            "data": str(data) if data is not None else None,
            "db": db,
            "host": host,
            "teltonika_port": teltonika_port,
            "osmand_port": osmand_port,
            "api_port": api_port,
            "engine": engine,
            "mqtt": mqtt,
            "registration_open": None if registration is None else registration == "open",
            "tile_url": tile_url,
            "raw_engine": raw_engine,
            "nmea_port": nmea_port,
            "nats": nats,
            "processes": processes,
        }
        if config is not None:
            cfg = ServiceConfig.from_toml(config, **overrides)
        else:
            cfg = ServiceConfig.from_dict({k: v for k, v in overrides.items() if v is not None})
        logging.basicConfig(level=logging.WARNING, format="%(asctime)s %(name)s %(levelname)s %(message)s")
        asyncio.run(serve(cfg))
