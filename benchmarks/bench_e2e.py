"""End-to-end speed of ``iotnav run`` as a user runs it (read, fuse, write), beside the kernel.

Prints a markdown section; with ``IOTNAV_WRITE_RESULTS=1`` also writes
``benchmarks/results/e2e.md``.

What is measured
----------------
* The drive: ``iotnav simulate car-tunnel --set duration_s=1800 --seed 2101`` (30 minutes,
  MPU-6050 at 100 Hz, GNSS at 1 Hz, tunnels), a seed no test or tuning uses (held out).
* **End to end**: wall and CPU time of the whole ``iotnav run DIR --engine E --out O``
  process (start-up, ingest of gnss.nmea and imu.csv, the engine, track.csv, gnss.csv,
  events/summary JSON, GeoJSON and GPX), median of ``--repeats`` runs after one warm-up run
  that fills the numba cache.
* **Start-up**: the same command on a 3 s drive of the same scenario and seed (same engine,
  same outputs); its median is subtracted from the end-to-end time, so ``samples/s`` is the rate
  at which a longer log is processed once the process is up.
* **Kernel**: in one Python process, :func:`iotnav.engines.base.run_batch` alone on the same
  ingested log (median of ``--repeats``, after a warm-up call), and the stages of a run
  apart: ingest, engine, writing (:func:`iotnav.runs.write_run`).
* ``iotnav --help``: wall and CPU time of the whole process, median.

* ``--reference-src DIR``: the same runs of another tree's ``src/`` (``git archive REV src``),
  alternated run by run with this tree's, so a before/after comparison sees the same load.

Targets (issue 21): pipeline >= 300,000, eskf >= 150,000 and qekf >= 100,000 IMU samples/s end
to end, start-up subtracted; ``iotnav --help`` under 1 s. Every engine that runs on the drive
is timed (``ENGINES``).

Usage::

    python benchmarks/bench_e2e.py [--duration 1800] [--repeats 5] [--engines pipeline eskf]
        [--reference-src /tmp/old/src --reference-label "main 1234abc"]
"""

from __future__ import annotations

import argparse
import math
import os
import resource
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

from assemble import machine
from iotnav.engines.base import run_batch
from iotnav.engines.registry import make_engine
from iotnav.io import ingest
from iotnav.runs import write_run

RESULTS = Path(__file__).resolve().parent / "results" / "e2e.md"
SEED = 2101
TARGETS = {"pipeline": 300_000.0, "eskf": 150_000.0, "qekf": 100_000.0}
#: The engines timed by default: every engine that runs on an IMU + GNSS drive.
ENGINES = ("pipeline", "anchor", "eskf", "qekf", "pdr")
SHORT_S = 3.0  # the start-up run's drive


def iotnav_cmd() -> list[str]:
    """The ``iotnav`` console script beside this Python, else the same entry point through ``-c``."""
    script = Path(sys.executable).parent / "iotnav"
    if script.is_file():
        return [str(script)]
    return [sys.executable, "-c", "import sys; from iotnav.cli import main; sys.argv[0] = 'iotnav'; main()"]


def timed(cmd: list[str], env: dict[str, str] | None = None) -> tuple[float, float]:
    """Wall and CPU (user + sys of the child) seconds of one process; raises if it fails."""
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    t0 = time.perf_counter()
    res = subprocess.run(cmd, capture_output=True, text=True, env=env)
    wall = time.perf_counter() - t0
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    if res.returncode != 0:
        raise RuntimeError(f"{' '.join(cmd)} failed ({res.returncode}): {res.stderr[-2000:]}")
    return wall, (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)


def medians(cmd: list[str], repeats: int, warmup: int = 1) -> tuple[float, float]:
    """Median wall and CPU seconds of ``repeats`` runs after ``warmup`` uncounted ones."""
    for _ in range(warmup):
        timed(cmd)
    runs = [timed(cmd) for _ in range(repeats)]
    return statistics.median(r[0] for r in runs), statistics.median(r[1] for r in runs)


def in_process(drive: Path, engine: str, repeats: int, out: Path) -> dict[str, float]:
    """Stage times of a run in one process: ingest, engine (kernel), write; medians."""
    files = [drive / "gnss.nmea", drive / "imu.csv"]
    ingest(files)  # warm the readers
    t, c = time.perf_counter(), time.process_time()
    log = ingest(files)
    read_s, read_cpu_s = time.perf_counter() - t, time.process_time() - c
    run_batch(make_engine(engine), log)  # warm-up: numba cache load / compile
    fuse, fuse_cpu, write, write_cpu = [], [], [], []
    for _ in range(repeats):
        eng = make_engine(engine)
        t, c = time.perf_counter(), time.process_time()
        track = run_batch(eng, log)
        fuse.append(time.perf_counter() - t)
        fuse_cpu.append(time.process_time() - c)
        t, c = time.perf_counter(), time.process_time()
        write_run(out, track, log, engine, fuse[-1])
        write.append(time.perf_counter() - t)
        write_cpu.append(time.process_time() - c)
    return {
        "n_imu": float(len(log.imu)),
        "read_s": read_s,
        "read_cpu_s": read_cpu_s,
        "fuse_s": statistics.median(fuse),
        "fuse_cpu_s": statistics.median(fuse_cpu),
        "write_s": statistics.median(write),
        "write_cpu_s": statistics.median(write_cpu),
    }


def _row(
    engine: str, full: list[tuple[float, float]], up: list[tuple[float, float]], stages: dict[str, float]
) -> dict[str, Any]:
    """One table row from the whole-process runs (wall, CPU) and the in-process stages."""
    full_wall, full_cpu = (statistics.median(r[i] for r in full) for i in (0, 1))
    up_wall, up_cpu = (statistics.median(r[i] for r in up) for i in (0, 1))
    n = stages["n_imu"]
    # a drive too short to stand out of the start-up's noise gives NaN, not a made-up rate
    e2e = n / (full_wall - up_wall) if full_wall > up_wall else math.nan
    e2e_cpu = n / (full_cpu - up_cpu) if full_cpu > up_cpu else math.nan
    kernel = n / stages["fuse_s"]
    kernel_cpu = n / stages["fuse_cpu_s"]
    return {
        "engine": engine,
        "full_wall": full_wall,
        "full_cpu": full_cpu,
        "up_wall": up_wall,
        "up_cpu": up_cpu,
        "e2e_sps": e2e,
        "e2e_cpu_sps": e2e_cpu,
        "kernel_sps": kernel,
        "kernel_cpu_sps": kernel_cpu,
        "ratio": e2e / kernel,
        "ratio_cpu": e2e_cpu / kernel_cpu,
        **stages,
    }


def _table(rows: list[dict[str, Any]]) -> list[str]:
    lines = [
        "| engine | end to end, s (wall / CPU) | start-up, s (wall / CPU) | samples/s end to end "
        "(wall / CPU) | kernel samples/s (wall / CPU) | end to end / kernel (wall / CPU) | target | in one process: "
        "read / fuse / write, s (wall, CPU) |",
        "| --- | ---: | ---: | ---: | ---: | ---: | ---: | ---: |",
    ]
    for r in rows:
        target = TARGETS.get(r["engine"])
        met = (
            ""
            if not target
            else (" (met)" if r["e2e_cpu_sps"] >= target and r["e2e_sps"] >= target else " (**not met**)")
        )
        lines.append(
            f"| {r['engine']} | {r['full_wall']:.2f} / {r['full_cpu']:.2f} | {r['up_wall']:.2f} / "
            f"{r['up_cpu']:.2f} | {r['e2e_sps']:,.0f} / {r['e2e_cpu_sps']:,.0f} | {r['kernel_sps']:,.0f} / "
            f"{r['kernel_cpu_sps']:,.0f} | {r['ratio']:.2f} / {r['ratio_cpu']:.2f} | "
            f"{f'>= {target:,.0f}{met}' if target else '-'} | "
            f"{r['read_s']:.2f} / {r['fuse_s']:.2f} / {r['write_s']:.2f} (CPU {r['read_cpu_s']:.2f} / "
            f"{r['fuse_cpu_s']:.2f} / {r['write_cpu_s']:.2f}) |"
        )
    return lines


def _with_src(src: Path | None) -> dict[str, str] | None:
    """The environment of a process importing iotnav from ``src`` (None: this tree's)."""
    if src is None:
        return None
    env = dict(os.environ)
    env["PYTHONPATH"] = os.pathsep.join([str(src), *filter(None, [env.get("PYTHONPATH")])])
    return env


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    quick = os.environ.get("IOTNAV_BENCH_QUICK") == "1"
    ap.add_argument("--duration", type=float, default=300.0 if quick else 1800.0, help="Drive length, s.")
    ap.add_argument("--repeats", type=int, default=2 if quick else 5)
    ap.add_argument("--engines", nargs="+", default=list(ENGINES))
    ap.add_argument(
        "--reference-src",
        type=Path,
        default=None,
        help="Also time the iotnav of this src/ folder (e.g. an older tree from `git archive`), "
        "its runs alternated with this tree's.",
    )
    ap.add_argument("--reference-label", default="reference")
    args = ap.parse_args()
    cmd = iotnav_cmd()
    trees: list[tuple[str, Path | None]] = [("this tree", None)]
    if args.reference_src is not None:
        trees.append((args.reference_label, args.reference_src.resolve()))
    work = Path(tempfile.mkdtemp(prefix="iotnav-e2e-"))
    try:
        drive = work / "drive"
        short = work / "short"
        for d, seconds in ((drive, args.duration), (short, SHORT_S)):
            sim = [*cmd, "simulate", "car-tunnel", "--out", str(d), "--seed", str(SEED)]
            timed([*sim, "--set", f"duration_s={seconds:g}"])
        help_wall, help_cpu = medians([*cmd, "--help"], max(5, args.repeats))
        rows: dict[str, list[dict[str, Any]]] = {label: [] for label, _ in trees}
        for engine in args.engines:
            run = [*cmd, "run", "--engine", engine, "--out"]
            full: dict[str, list[tuple[float, float]]] = {label: [] for label, _ in trees}
            up: dict[str, list[tuple[float, float]]] = {label: [] for label, _ in trees}
            for _label, src in trees:  # warm-up: fills each tree's numba cache
                timed([*run, str(work / "warm"), str(drive)], _with_src(src))
            for _ in range(args.repeats):  # the trees' runs alternated, so both see the same load
                for label, src in trees:
                    env = _with_src(src)
                    full[label].append(timed([*run, str(work / f"out-{engine}"), str(drive)], env))
                    up[label].append(timed([*run, str(work / f"up-{engine}"), str(short)], env))
            stages = in_process(drive, engine, min(args.repeats, 3), work / f"in-{engine}")
            for label, _ in trees:
                # the in-process stages are this tree's (the reference's are not timed in this process)
                r = _row(engine, full[label], up[label], stages)
                rows[label].append(r)
                print(
                    f"{label}, {engine}: {r['full_wall']:.2f} s end to end, start-up {r['up_wall']:.2f} s, "
                    f"{r['e2e_sps']:,.0f} samples/s vs kernel {r['kernel_sps']:,.0f} ({r['ratio']:.2f})"
                )
    finally:
        shutil.rmtree(work, ignore_errors=True)
    mine = rows["this tree"]
    n_imu = int(mine[0]["n_imu"]) if mine else 0
    ref = f" --reference-src {args.reference_src}" if args.reference_src is not None else ""
    lines = [
        "## End to end: `iotnav run` as a user runs it",
        "",
        f"`benchmarks/bench_e2e.py --duration {args.duration:g} --repeats {args.repeats}{ref}`: "
        f"`iotnav simulate car-tunnel --seed {SEED} --set duration_s={args.duration:g}` "
        f"({n_imu:,} IMU samples at 100 Hz, GNSS 1 Hz, held-out seed), then "
        "`iotnav run DIR --engine E` as a whole process (read gnss.nmea and imu.csv, fuse, write "
        "track.csv, gnss.csv, JSON, GeoJSON and GPX at 1 point/s). Start-up = the same command on "
        f"a {SHORT_S:g} s drive of the same scenario, subtracted (an upper bound of the time to the "
        "first sample). Kernel = `run_batch` alone on the same log in one process, "
        f"measured in the same run. Medians of {args.repeats} runs after a warm-up (warm numba cache); "
        "the long and the short drive alternated"
        + (", and the two trees alternated run by run" if len(trees) > 1 else "")
        + f". Machine: {machine()}; shared, so wall times are inflated: CPU times beside them. "
        "A target is met when both the wall and the CPU figure reach it. The `absfix` engine needs "
        "absolute fixes this drive does not have, and `fixes` uses the GNSS only "
        "(`benchmarks/bench_fixes.py`).",
        "",
        *_table(mine),
    ]
    for label, _ in trees[1:]:
        lines += [
            "",
            f"{label} (`{args.reference_src}`), in the same run, runs alternated with the table above; "
            "its in-process columns are this tree's:",
            "",
            *_table(rows[label]),
        ]
    lines += [
        "",
        f"`iotnav --help`: {help_wall:.2f} s wall, {help_cpu:.2f} s CPU (median of "
        f"{max(5, args.repeats)}; target under 1 s).",
        "",
    ]
    text = "\n".join(lines)
    print(text)
    if os.environ.get("IOTNAV_WRITE_RESULTS") == "1":
        RESULTS.parent.mkdir(parents=True, exist_ok=True)
        RESULTS.write_text(text)
        print(f"wrote {RESULTS}")


if __name__ == "__main__":
    main()
