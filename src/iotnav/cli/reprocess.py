"""``iotnav reprocess``: re-run device-days stored by the service with an engine, inline or on Dask.

The maths is the engines' own streaming ``step()``; reading the stored fixes and the Dask
fan-out are :mod:`iotnav.service.workers_batch`. This module parses the options, shows the
progress and writes ``OUT/reprocess_summary.json``.
"""

from __future__ import annotations

import json
from datetime import UTC, datetime
from pathlib import Path
from typing import Annotated, Any

import typer

from iotnav.cli._common import console, err_console, progress, user_errors


def parse_utc(text: str, option: str) -> float:
    """``text`` (ISO 8601 date or date-time; UTC when it names no zone) as Unix seconds.

    Raises
    ------
    ValueError
        When ``text`` is not ISO 8601; the message names ``option``.
    """
    try:
        when = datetime.fromisoformat(text)
    except ValueError:
        raise ValueError(
            f"{option} {text!r}: expected an ISO 8601 date or date-time (2026-11-30T06:00)"
        ) from None
    if when.tzinfo is None:
        when = when.replace(tzinfo=UTC)
    return when.timestamp()


def register(app: typer.Typer) -> None:
    """Register ``reprocess`` on ``app``."""

    @app.command("reprocess")
    @user_errors
    def reprocess_cmd(
        out: Annotated[Path, typer.Option(help="Folder for OUT/<device>/<YYYY-MM-DD>.csv and the summary.")],
        data: Annotated[
            Path, typer.Option("--data", help="The service's data directory (its iotnav.sqlite).")
        ] = Path("iotnav-data"),
        db: Annotated[
            str, typer.Option("--db", help="Database URL instead of --data (postgresql+psycopg://...).")
        ] = "",
        engine: Annotated[str, typer.Option(help="Engine for the stored fixes.")] = "fixes",
        config: Annotated[
            Path | None, typer.Option(help="The engine's TOML configuration (as iotnav run reads it).")
        ] = None,
        device: Annotated[
            list[str] | None, typer.Option("--device", help="Unique id (IMEI, ...) to re-run; repeatable.")
        ] = None,
        since: Annotated[str, typer.Option(help="First fix time, ISO 8601 (UTC without a zone).")] = "",
        until: Annotated[str, typer.Option(help="Fix times before this, ISO 8601.")] = "",
        workers: Annotated[int, typer.Option(help="Local Dask worker processes (0: in this process).")] = 0,
        scheduler: Annotated[
            str, typer.Option(help="Dask scheduler address (tcp://host:8786) instead of --workers.")
        ] = "",
    ) -> None:
        """Re-run the stored fixes of every (device, UTC day) with ENGINE; write one CSV per device-day."""
        from iotnav.engines.registry import ENGINE_NAMES
        from iotnav.service import store
        from iotnav.service.workers_batch import list_device_days, reprocess

        if engine not in ENGINE_NAMES:
            raise ValueError(f"unknown engine {engine!r}; expected one of {', '.join(ENGINE_NAMES)}")
        if config is not None and not config.is_file():
            raise FileNotFoundError(f"--config {config}: no such file")
        if workers < 0:
            raise ValueError(f"--workers {workers}: expected 0 or more")
        t_from = parse_utc(since, "--since") if since else None
        t_to = parse_utc(until, "--until") if until else None
        if not db:
            if not (data / "iotnav.sqlite").is_file():
                raise FileNotFoundError(
                    f"--data {data}: no iotnav.sqlite there (the folder iotnav serve --data wrote)"
                )
            db = store.sqlite_url(data)
        import sqlalchemy.exc

        try:
            dbe = store.make_engine(db)
            try:
                jobs = list_device_days(dbe, t_from, t_to, device)
            finally:
                dbe.dispose()
        except sqlalchemy.exc.SQLAlchemyError as exc:  # unreachable server, not a service database
            reason = str(getattr(exc, "orig", None) or exc).splitlines()[0]
            raise ValueError(f"cannot read the stored fixes from {db}: {reason}") from None
        if device:
            missing = sorted(set(device) - {j.unique_id for j in jobs})
            if missing:
                err_console.print(f"[yellow]no stored fixes in the period for:[/] {', '.join(missing)}")
        if not jobs:
            raise ValueError("no device-day with stored fixes matches the options")
        out.mkdir(parents=True, exist_ok=True)
        with progress(f"re-processing {len(jobs)} device-days", len(jobs)) as advance:
            results = reprocess(
                db,
                jobs,
                engine,
                str(out),
                scheduler or None,
                workers,
                None if config is None else str(config.resolve()),
                on_done=lambda: advance(1.0),
            )
        rows: list[dict[str, Any]] = []
        failed = 0
        for job, r in zip(jobs, results, strict=True):
            if isinstance(r, BaseException):
                failed += 1
                rows.append({"device": job.unique_id, "day": job.day, "error": f"{type(r).__name__}: {r}"})
            else:
                rows.append({k: v for k, v in r.items() if k != "lat_lon"})
        summary = {"engine": engine, "config": None if config is None else str(config), "device_days": rows}
        (out / "reprocess_summary.json").write_text(json.dumps(summary, indent=1) + "\n")
        fixes = sum(int(r.get("fixes", 0)) for r in rows)
        outputs = sum(int(r.get("outputs", 0)) for r in rows)
        console.print(
            f"{len(jobs) - failed} of {len(jobs)} device-days re-run with {engine}: {fixes} fixes read, "
            f"{outputs} positions written to {out}"
        )
        if failed:
            for r in rows:
                if "error" in r:
                    err_console.print(
                        f"[bold red]failed:[/] {r['device']} {r['day']}: {r['error']}", soft_wrap=True
                    )
            raise typer.Exit(code=1)
