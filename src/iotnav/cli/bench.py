"""``iotnav bench``: run the benchmark scripts and regenerate BENCHMARKS.md.

The scripts live in the repository's ``benchmarks/`` folder (a development checkout): each
``bench_*.py`` writes its own section to ``benchmarks/results/`` when run with
``IOTNAV_WRITE_RESULTS=1``; ``benchmarks/assemble.py`` then writes ``BENCHMARKS.md``. With
``--quick`` the environment variable ``IOTNAV_BENCH_QUICK=1`` asks each script for its short
variant (scripts that have none run in full) and a curated subset of the slowest studies is
skipped. The figures quoted in the README come from this one command.
"""

from __future__ import annotations

import os
import subprocess
import sys
import time
from pathlib import Path
from typing import Annotated

import typer
from rich.table import Table

import iotnav
from iotnav.cli._common import console, user_errors

#: Scripts run by default, in order; bench_imu_csv and bench_nmea are run through bench_ingest.
ORDER = [
    "bench_ingest",
    "bench_sim",
    "bench_pipeline",
    "bench_eskf",
    "bench_engines",
    "bench_outages",
    "bench_attitude",
    "bench_absfix",
    "bench_characterize",
    "bench_nodes",
    "bench_speed",
    "bench_e2e",
    "bench_fleet",
]
#: Slow studies left out by --quick.
SLOW = {"bench_nodes", "bench_attitude", "bench_attitude_loo", "bench_outages", "bench_engines"}


def benchmarks_dir() -> Path:
    """The ``benchmarks/`` folder of the development checkout iotnav runs from."""
    d = Path(iotnav.__file__).resolve().parents[2] / "benchmarks"
    if not (d / "assemble.py").is_file():
        raise FileNotFoundError(
            f"{d}: no benchmarks folder; iotnav bench runs from a development checkout (pip install -e .)"
        )
    return d


def register(app: typer.Typer) -> None:
    """Register ``bench`` on ``app``."""

    @app.command("bench")
    @user_errors
    def bench_cmd(
        quick: Annotated[bool, typer.Option(help="Short variants; skip the slowest studies.")] = False,
        only: Annotated[
            list[str] | None, typer.Option(help="Run only these scripts (e.g. bench_sim).")
        ] = None,
    ) -> None:
        """Run every benchmark script and regenerate BENCHMARKS.md."""
        d = benchmarks_dir()
        names = [n for n in ORDER if (d / f"{n}.py").is_file()]
        names += sorted(
            p.stem
            for p in d.glob("bench_*.py")
            if p.stem not in names and p.stem not in ("bench_imu_csv", "bench_nmea")
        )
        if only:
            unknown = set(only) - set(names)
            if unknown:
                raise ValueError(f"unknown benchmark(s) {sorted(unknown)}; available: {', '.join(names)}")
            names = [n for n in names if n in only]
        elif quick:
            names = [n for n in names if n not in SLOW]
        env = {**os.environ, "IOTNAV_WRITE_RESULTS": "1"}
        if quick:
            env["IOTNAV_BENCH_QUICK"] = "1"
        table = Table(title="iotnav bench")
        table.add_column("script")
        table.add_column("status")
        table.add_column("seconds", justify="right")
        failed = 0
        for n in names:
            console.print(f"[bold]running {n}[/]")
            t0 = time.perf_counter()
            res = subprocess.run([sys.executable, str(d / f"{n}.py")], env=env, cwd=d.parent)
            dt = time.perf_counter() - t0
            ok = res.returncode == 0
            failed += not ok
            table.add_row(n, "ok" if ok else f"[red]failed ({res.returncode})[/]", f"{dt:.0f}")
        subprocess.run([sys.executable, str(d / "assemble.py")], cwd=d.parent, check=True)
        console.print(table)
        if failed:
            raise typer.Exit(code=1)
