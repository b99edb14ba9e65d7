"""``iotnav report``: a self-contained HTML report (and PNG figures) of one or more runs."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer
from rich.table import Table

from iotnav.cli._common import console, user_errors
from iotnav.report import Report, build_report
from iotnav.report.page import OSM_ATTRIBUTION, OSM_TILES


def print_report(rep: Report) -> None:
    """Print where a report was written, its accuracy table and the figures left out."""
    if rep.accuracy:
        table = Table(title="horizontal error against truth, m")
        table.add_column("solution")
        for c in ("mean", "rms", "p67", "p95", "max"):
            table.add_column(c, justify="right")
        for name, st in rep.accuracy.items():
            table.add_row(name, *(f"{st[f'h_err_{c}']:.2f}" for c in ("mean", "rms", "p67", "p95", "max")))
        console.print(table)
    for key, note in rep.omitted.items():
        console.print(f"[dim]{key}: {note}[/]")
    console.print(f"report: [bold]{rep.html}[/] ({len(rep.figures)} figures beside it)")


def register(app: typer.Typer) -> None:
    """Register ``report`` on ``app``."""

    @app.command("report")
    @user_errors
    def report_cmd(
        out: Annotated[Path, typer.Argument(help="Run directory written by `iotnav run --out OUT`.")],
        truth: Annotated[
            Path | None, typer.Option("--truth", help="Truth table (the simulator's truth.csv).")
        ] = None,
        compare: Annotated[
            list[Path] | None,
            typer.Option("--compare", help="Another run directory to overlay (repeat the option for more)."),
        ] = None,
        html: Annotated[
            Path | None, typer.Option("--html", help="Where to write the page (default OUT/report.html).")
        ] = None,
        gap_factor: Annotated[
            float,
            typer.Option(
                help="A gap between valid fixes longer than this x the median interval is an outage."
            ),
        ] = 3.0,
        fence_m: Annotated[float, typer.Option(help="Geofence radius around the static point, m.")] = 15.0,
        tiles: Annotated[
            str,
            typer.Option(
                help="Tile URL template ({z}/{x}/{y}) for the opt-in map-tile view, or 'none'. "
                "Nothing is fetched until the reader clicks the button."
            ),
        ] = OSM_TILES,
        tiles_attribution: Annotated[
            str, typer.Option(help="Attribution the tile server's terms require.")
        ] = OSM_ATTRIBUTION,
    ) -> None:
        """Write OUT/report.html (self-contained, offline) and its PNG figures beside it."""
        if gap_factor <= 1.0:
            raise ValueError(f"--gap-factor must be > 1, got {gap_factor}")
        if fence_m <= 0.0:
            raise ValueError(f"--fence-m must be > 0, got {fence_m}")
        tile_url = None if tiles.strip().lower() == "none" else tiles
        if tile_url is not None and not all(k in tile_url for k in ("{z}", "{x}", "{y}")):
            raise ValueError(f"--tiles must contain {{z}}, {{x}} and {{y}}, got {tiles!r}")
        rep = build_report(
            [out, *(compare or [])],
            html,
            truth,
            gap_factor=gap_factor,
            fence_m=fence_m,
            tile_url=tile_url,
            tile_attribution=tiles_attribution,
        )
        print_report(rep)
