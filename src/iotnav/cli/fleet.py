"""``iotnav run-many``: fuse the logs of many devices in parallel (local processes or Dask)."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated, Any

import typer
from rich.table import Table

from iotnav.cli._common import console, progress, user_errors
from iotnav.engines.registry import ENGINE_NAMES
from iotnav.fleet import FLEET_SUMMARY, discover_devices, run_fleet


def register(app: typer.Typer) -> None:
    """Register ``run-many`` on ``app``."""

    @app.command("run-many")
    @user_errors
    def run_many_cmd(
        log_dirs: Annotated[
            list[Path],
            typer.Argument(
                help="Device directories, or parents whose subdirectories are devices "
                "(a directory holding gnss.nmea / gnss.ubx / imu.csv or other log files is a device)."
            ),
        ],
        out: Annotated[Path, typer.Option("--out", "-o", help="Output root: OUT/<device>/ per device.")],
        engine: Annotated[str, typer.Option(help=f"One of {', '.join(ENGINE_NAMES)}.")] = "pipeline",
        config: Annotated[
            Path | None, typer.Option(help="Engine configuration (TOML), for every device.")
        ] = None,
        workers: Annotated[
            int, typer.Option(help="Local worker processes (0: in this process). Ignored with --scheduler.")
        ] = 1,
        scheduler: Annotated[
            str | None,
            typer.Option(
                help="Dask scheduler address (tcp://host:8786); paths must be shared with its workers."
            ),
        ] = None,
    ) -> None:
        """Fuse every device's log with an engine; write OUT/<device>/ (as iotnav run) and OUT/fleet_summary.json.

        Exit code 0 when every device succeeded, 1 when some failed (the reasons are listed and in
        fleet_summary.json), 2 for a usage error.
        """
        jobs = discover_devices(log_dirs, out=out)
        counts = {"ok": 0, "failed": 0}
        with progress(f"{len(jobs)} devices", total=len(jobs)) as advance:

            def done(res: dict[str, Any]) -> None:
                counts["ok" if res["ok"] else "failed"] += 1
                advance(1)

            result = run_fleet(jobs, out, engine, config, workers=workers, scheduler=scheduler, on_done=done)
        where = f"Dask {scheduler}" if scheduler else f"{result.workers} local worker(s)"
        table = Table(title=f"iotnav run-many --engine {engine}: {out} ({where})")
        table.add_column("what")
        table.add_column("value", justify="right")
        table.add_row("devices", str(len(result.devices)))
        table.add_row("ok", str(result.ok))
        table.add_row("failed", f"[red]{result.failed}[/]" if result.failed else "0")
        table.add_row("wall time", f"{result.wall_s:.1f} s")
        table.add_row("devices per minute", f"{result.devices_per_min:.1f}")
        table.add_row("IMU samples per second", f"{result.imu_samples_per_s:,.0f}")
        table.add_row("summary", str(out / FLEET_SUMMARY))
        console.print(table)
        failures = result.failures()
        if failures:
            ft = Table(title="failed devices")
            ft.add_column("device")
            ft.add_column("reason", overflow="fold")
            for name, reason in failures:
                ft.add_row(name, reason)
            console.print(ft)
            raise typer.Exit(code=1)
