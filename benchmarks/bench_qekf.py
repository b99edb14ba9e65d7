"""End-to-end speed of ``iotnav run --engine qekf`` before and after its compiled step (issue 21).

Prints a markdown section; with ``IOTNAV_WRITE_RESULTS=1`` also writes
``benchmarks/results/qekf.md``.

What is measured
----------------
Whole ``iotnav run FILES --engine qekf --out O`` processes (start-up, ingest, the engine, the
outputs), wall and CPU time (user + sys of the child), each code version run alternately in the
same benchmark run (median of ``--repeats`` after one warm-up run per version, which fills its
numba cache): *before* is the source tree given by ``--before`` (a checkout of main before the
compiled step, e.g. ``git worktree add /tmp/qekf-before 7f3bbd5``), *after* this tree. The
engine's own time is the ``runtime_s`` that ``iotnav run`` writes into summary.json (wall).

Logs:

* the bundled real walk ``rtklibexplorer_gnss_imu/walk_0827`` (NMEA + ICM-45686 at 100 Hz, no
  magnetometer: the no-magnetometer fallback, whose GNSS epochs, mount aligner and
  non-holonomic observations leave the compiled block path);
* ``iotnav simulate car-magnetometer --seed 2101 --set duration_s=D`` (MPU-6050 at 50 Hz, HMC5883L
  at 6 Hz, GNSS 1 Hz; the paper's case, a seed no test uses).

Usage::

    python benchmarks/bench_qekf.py --before /tmp/qekf-before [--duration 300] [--repeats 3]
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import statistics
import subprocess
import sys
import tempfile
from pathlib import Path

from assemble import machine
from bench_e2e import timed

RESULTS = Path(__file__).resolve().parent / "results" / "qekf.md"
HERE = Path(__file__).resolve().parents[1]
SEED = 2101
CLI = "import sys; from iotnav.cli import main; sys.argv[0] = 'iotnav'; main()"


def run_once(src: Path, args: list[str], out: Path) -> tuple[float, float, float]:
    """Wall and CPU seconds of one ``iotnav`` process on the package in ``src``, and its engine
    ``runtime_s`` (summary.json)."""
    wall, cpu = timed(["env", f"PYTHONPATH={src}", sys.executable, "-c", CLI, *args, "--out", str(out)])
    runtime = float(json.loads((out / "summary.json").read_text())["runtime_s"])
    return wall, cpu, runtime


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--before", type=Path, required=True, help="Source tree of the code before (its src/).")
    ap.add_argument("--duration", type=float, default=300.0, help="Simulated drive length, s.")
    ap.add_argument("--repeats", type=int, default=3)
    args = ap.parse_args()
    datasets = Path(os.environ.get("IOTNAV_DATASETS", "/work/shared/datasets"))
    walk = datasets / "rtklibexplorer_gnss_imu" / "walk_0827"
    versions = {"before": args.before.resolve() / "src", "after": HERE / "src"}
    work = Path(tempfile.mkdtemp(prefix="iotnav-qekf-"))
    rows = []
    try:
        drive = work / "drive"
        subprocess.run(
            [sys.executable, "-c", CLI, "simulate", "car-magnetometer", "--out", str(drive), "--seed", str(SEED),
             "--set", f"duration_s={args.duration:g}"],
            env={**os.environ, "PYTHONPATH": str(versions["after"])}, check=True, capture_output=True,
        )  # fmt: skip
        logs = {
            "walk_0827 (real, no magnetometer)": [
                str(walk / "gnss_1730_nmea.txt"),
                str(walk / "imu_1730.csv"),
            ],
            f"car-magnetometer {args.duration:g} s (simulated)": [str(drive)],
        }
        for name, files in logs.items():
            cmd = ["run", *files, "--engine", "qekf"]
            res: dict[str, list[tuple[float, float, float]]] = {v: [] for v in versions}
            for v, src in versions.items():  # warm-up: numba caches
                run_once(src, cmd, work / f"warm-{v}")
            for k in range(args.repeats):  # alternate, so both see the same load
                for v, src in versions.items():
                    res[v].append(run_once(src, cmd, work / f"{v}-{k}"))
            med = {v: tuple(statistics.median(r[i] for r in res[v]) for i in range(3)) for v in versions}
            rows.append((name, med))
            print(name, {v: [round(x, 2) for x in m] for v, m in med.items()}, flush=True)
    finally:
        shutil.rmtree(work, ignore_errors=True)
    lines = [
        "## qekf end to end, before and after the compiled step",
        "",
        f"`benchmarks/bench_qekf.py --duration {args.duration:g} --repeats {args.repeats}`: whole "
        "`iotnav run FILES --engine qekf` processes (start-up, ingest, engine, outputs), before "
        "(main at 7f3bbd5, per-sample Python) and after (the compiled step of "
        "`iotnav.engines.qekf_kernel`), alternated in one run; medians of "
        f"{args.repeats} after a warm-up run each (warm numba cache). Engine = `runtime_s` of "
        f"summary.json (wall). Machine: {machine()}; shared, so wall times are inflated: CPU "
        "times beside them.",
        "",
        "| log | before: process wall / CPU, s | after: process wall / CPU, s | CPU ratio | "
        "engine wall before / after, s | engine ratio |",
        "| --- | ---: | ---: | ---: | ---: | ---: |",
    ]
    for name, med in rows:
        b, a = med["before"], med["after"]
        lines.append(
            f"| {name} | {b[0]:.2f} / {b[1]:.2f} | {a[0]:.2f} / {a[1]:.2f} | {b[1] / a[1]:.1f} | "
            f"{b[2]:.2f} / {a[2]:.2f} | {b[2] / a[2]:.1f} |"
        )
    text = "\n".join([*lines, ""])
    print(text)
    if os.environ.get("IOTNAV_WRITE_RESULTS") == "1":
        RESULTS.parent.mkdir(parents=True, exist_ok=True)
        RESULTS.write_text(text)
        print(f"wrote {RESULTS}")


if __name__ == "__main__":
    main()
