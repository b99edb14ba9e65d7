"""``iotnav eval``: horizontal error statistics of a run against a truth track."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Annotated

import pandas as pd
import typer
from rich.table import Table

from iotnav.cli._common import console, user_errors
from iotnav.eval.metrics import error_stats, track_errors
from iotnav.io.export import read_table


def _read_track(path: Path) -> pd.DataFrame:
    if path.is_dir():
        parquet = path / "track.parquet"
        path = parquet if parquet.is_file() and not (path / "track.csv").is_file() else path / "track.csv"
    if not path.is_file():
        raise FileNotFoundError(f"{path}: no track file (expected OUT/track.csv as iotnav run writes)")
    return read_table(path)


def register(app: typer.Typer) -> None:
    """Register ``eval`` on ``app``."""

    @app.command("eval")
    @user_errors
    def eval_cmd(
        out: Annotated[Path, typer.Argument(help="A run's output directory (OUT/track.csv) or a track CSV.")],
        truth: Annotated[Path, typer.Option(help="truth.csv with t, lat, lon[, height] on the same clock.")],
    ) -> None:
        """Print and write OUT/eval.json: horizontal error statistics (metres) against truth."""
        track = _read_track(out)
        ref = pd.read_csv(truth)
        stats = error_stats(track_errors(track, ref))
        table = Table(title=f"{out} vs {truth.name} ({int(stats['n'])} epochs)")
        table.add_column("error, m")
        for col in ("mean", "rms", "p50", "p67", "p95", "max"):
            table.add_column(col, justify="right")
        for prefix, label in (("h_err", "horizontal"), ("n_err", "|north|"), ("e_err", "|east|")):
            table.add_row(
                label, *(f"{stats[f'{prefix}_{c}']:.3f}" for c in ("mean", "rms", "p50", "p67", "p95", "max"))
            )
        console.print(table)
        if stats["outside_truth"]:
            console.print(
                f"note: {int(stats['outside_truth'])} track rows outside the truth's time span left out"
            )
        dest = (out if out.is_dir() else out.parent) / "eval.json"
        dest.write_text(json.dumps(stats, indent=1))
        console.print(f"wrote {dest}")
