"""``iotnav demo``: the main job on bundled defaults (what ``make run`` runs).

1. Ingest the bundled real NMEA log (rtklibexplorer walk) and export its track.
2. Simulate a scenario (``scooter-laps`` by default, shortened), fuse it with the ``pipeline``
   engine and print the evaluation against the simulator's truth.
"""

from __future__ import annotations

import math
import time
from importlib import resources
from pathlib import Path
from typing import Annotated

import pandas as pd
import typer
from rich.table import Table

from iotnav import sim
from iotnav.cli._common import console, user_errors
from iotnav.cli.ingest import print_report, write_merged
from iotnav.engines.base import run_batch
from iotnav.engines.registry import make_engine
from iotnav.eval.metrics import error_stats, track_errors
from iotnav.io import ingest
from iotnav.io.export import export_track
from iotnav.report import build_report
from iotnav.runs import write_run


def bundled_log() -> Path:
    """Path of the bundled real NMEA log (rtklibexplorer walk, BSD-3-Clause)."""
    return Path(str(resources.files("iotnav") / "data" / "walk_0827_nmea.txt"))


def register(app: typer.Typer) -> None:
    """Register ``demo`` on ``app``."""

    @app.command("demo")
    @user_errors
    def demo_cmd(
        out: Annotated[Path, typer.Option("--out", "-o", help="Output directory.")] = Path("out/run"),
        scenario: Annotated[str, typer.Option(help="Scenario to simulate and fuse.")] = "scooter-laps",
        duration: Annotated[
            float, typer.Option(help="Scenario duration override, s (0: its default).")
        ] = 240.0,
        seed: Annotated[int, typer.Option(help="Simulation seed.")] = 1,
        engine: Annotated[str, typer.Option(help="Engine to fuse with.")] = "pipeline",
    ) -> None:
        """Ingest the bundled real log, then simulate, fuse and evaluate a scenario."""
        src = bundled_log()
        console.rule("[bold]1. a real tracker log")
        console.print(f"ingesting bundled log {src.name} (rtklibexplorer walk, BSD-3-Clause)")
        log = ingest([src])
        print_report(log.report)
        real = out / "real"
        real.mkdir(parents=True, exist_ok=True)
        write_merged(log, real / "merged.csv")
        track = log.gnss.loc[log.gnss["valid"]].reset_index(drop=True)
        for ext in ("csv", "geojson", "gpx", "kml"):
            res = export_track(track, real / f"track.{ext}", name="walk_0827", utc_offset_s=log.utc_offset_s)
            console.print(f"wrote {res.path} ({res.points} points)")

        console.rule(f"[bold]2. simulate {scenario}, fuse with {engine}, evaluate")
        overrides = {"duration_s": duration} if duration > 0 else {}
        result = sim.build(scenario, seed=seed, overrides=overrides)
        sim_dir = out / "sim"
        sim.write(result, sim_dir)
        console.print(f"simulated {scenario} (seed {seed}) into {sim_dir}")
        slog = ingest([sim_dir])
        eng = make_engine(engine)
        t0 = time.perf_counter()
        fused = run_batch(eng, slog)
        runtime = time.perf_counter() - t0
        run_dir = out / engine
        summary = write_run(run_dir, fused, slog, engine, runtime)
        truth = pd.read_csv(sim_dir / "truth.csv")
        raw = slog.gnss.loc[slog.gnss["valid"]].rename(
            columns={"lat_deg": "lat", "lon_deg": "lon", "height_m": "height"}
        )
        rows = {
            "GNSS only (raw fixes)": error_stats(track_errors(raw, truth)),
            engine: error_stats(track_errors(fused, truth)),
        }
        table = Table(
            title=f"horizontal error against truth, m ({scenario}, {summary['rates_hz']['output']:.0f} Hz output)"
        )
        table.add_column("solution")
        for c in ("mean", "rms", "p67", "p95", "max"):
            table.add_column(c, justify="right")
        for name, st in rows.items():
            table.add_row(name, *(f"{st[f'h_err_{c}']:.2f}" for c in ("mean", "rms", "p67", "p95", "max")))
        console.print(table)
        mount = summary["mount_yaw_rad"]
        true_mount = result.config.mount_yaw_rad
        if math.isfinite(mount):
            console.print(
                f"mount yaw found: {math.degrees(mount):.1f} deg (true {math.degrees(true_mount):.1f} deg)"
            )
        console.print(f"outputs in {run_dir}: track.csv, events.json, summary.json, track.geojson, track.gpx")
        rep = build_report([run_dir], run_dir / "report.html", sim_dir / "truth.csv")
        console.print(f"report: [bold]{rep.html}[/] ({len(rep.figures)} figures beside it)")
