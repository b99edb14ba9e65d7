"""``iotnav demo``: the main job on the bundled default log (what ``make run`` runs)."""

from __future__ import annotations

from importlib import resources
from pathlib import Path
from typing import Annotated

import typer

from iotnav.cli._common import console, user_errors
from iotnav.cli.ingest import print_report, write_merged
from iotnav.io import ingest
from iotnav.io.export import export_track


def bundled_log() -> Path:
    """Path of the bundled real NMEA log (rtklibexplorer walk, BSD-3-Clause)."""
    return Path(str(resources.files("iotnav") / "data" / "walk_0827_nmea.txt"))


def register(app: typer.Typer) -> None:
    """Register ``demo`` on ``app``."""

    @app.command("demo")
    @user_errors
    def demo_cmd(
        out: Annotated[Path, typer.Option("--out", "-o", help="Output directory.")] = Path("out/run"),
    ) -> None:
        """Ingest the bundled real log and export its track (CSV, GeoJSON, GPX, KML)."""
        src = bundled_log()
        console.print(f"[bold]iotnav demo[/]: ingesting bundled log {src.name}")
        log = ingest([src])
        print_report(log.report)
        out.mkdir(parents=True, exist_ok=True)
        write_merged(log, out / "merged.csv")
        track = log.gnss.loc[log.gnss["valid"]].reset_index(drop=True)
        for ext in ("csv", "geojson", "gpx", "kml"):
            res = export_track(track, out / f"track.{ext}", name="walk_0827", utc_offset_s=log.utc_offset_s)
            console.print(f"wrote {res.path} ({res.points} points)")
