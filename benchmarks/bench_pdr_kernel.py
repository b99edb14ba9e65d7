"""Benchmark the compiled pdr engine beside main's per-sample Python one, in the same run.

The Python engine is main's ``src/iotnav/engines/pdr.py`` at commit 3ec104d (read with
``git show``, loaded as a module next to today's package); the compiled one is today's
:class:`~iotnav.engines.pdr.PdrEngine` (its IMU step :func:`iotnav.engines.pdr_kernel.imu_run`).
Both run the same logs, one process, BLAS limited to one thread:

* **Batch**: IMU samples per second of :func:`iotnav.engines.base.run_batch` (median of
  ``--repeats``, wall and CPU time) on the simulated ``car-tunnel`` drive of ``--duration``
  seconds (the input of ``bench_speed.py``) and on the real walk ``walk_0827`` (135 s,
  166 Hz: what the engine is for); the first call (kernel load) apart.
* **Streaming**: the time of each ``engine.step(sample)`` on the walk, IMU samples, median
  and 99th percentile.
* The two engines' outputs on the walk compared (largest difference of north/east, m).

Prints a markdown section; with ``IOTNAV_WRITE_RESULTS=1`` also writes
``benchmarks/results/pdr_kernel.md``.

Usage::

    IOTNAV_DATASETS=... python benchmarks/bench_pdr_kernel.py [--duration 600] [--repeats 3]
"""

from __future__ import annotations

import argparse
import importlib.util
import os
import statistics
import subprocess
import sys
import tempfile
import time
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np

from assemble import machine
from bench_speed import ONE_THREAD, simulated_log
from iotnav.engines.base import ImuSample, iter_samples, run_batch
from iotnav.engines.pdr import PdrEngine
from iotnav.io import Log, ingest

MAIN_COMMIT = "3ec104d"
REPO = Path(__file__).resolve().parents[1]


def main_engine_class() -> Any:
    """``PdrEngine`` of main at :data:`MAIN_COMMIT` (the per-sample Python engine)."""
    src = subprocess.run(
        ["git", "-C", str(REPO), "show", f"{MAIN_COMMIT}:src/iotnav/engines/pdr.py"],
        check=True,
        capture_output=True,
        text=True,
    ).stdout
    path = Path(tempfile.mkdtemp()) / "pdr_main.py"
    path.write_text(src)
    spec = importlib.util.spec_from_file_location("pdr_main", path)
    assert spec is not None and spec.loader is not None
    mod = importlib.util.module_from_spec(spec)
    sys.modules["pdr_main"] = mod  # dataclasses look their module up
    spec.loader.exec_module(mod)
    return mod.PdrEngine


def walk_log() -> Log:
    """The real hand-held walk (RTK positions, raw IMU)."""
    folder = Path(os.environ["IOTNAV_DATASETS"]) / "rtklibexplorer_gnss_imu" / "walk_0827"
    return ingest([folder / "gnss_1730_sf.pos", folder / "imu_1730.csv"])


def batch(cls: Any, log: Log, repeats: int) -> dict[str, float]:
    """Median wall and CPU samples/s of run_batch, and the first call's time on 2 s."""
    t_end = float(log.imu.t.iloc[0]) + 2.0
    warm = replace(log, imu=log.imu[log.imu.t < t_end], gnss=log.gnss[log.gnss.t < t_end])
    w0 = time.perf_counter()
    run_batch(cls(), warm)
    first = time.perf_counter() - w0
    wall, cpu = [], []
    for _ in range(repeats):
        w0, c0 = time.perf_counter(), time.process_time()
        run_batch(cls(), log)
        wall.append(time.perf_counter() - w0)
        cpu.append(time.process_time() - c0)
    n = len(log.imu)
    return {"wall_sps": n / statistics.median(wall), "cpu_sps": n / statistics.median(cpu), "first_s": first}


def streaming(cls: Any, log: Log) -> dict[str, float]:
    """Median and p99 of one ``step()`` call on IMU samples, us."""
    samples = list(iter_samples(log))
    eng = cls()
    us = []
    clock = time.perf_counter_ns
    for s in samples:
        t0 = clock()
        eng.step(s)
        if isinstance(s, ImuSample):
            us.append((clock() - t0) / 1e3)
    a = np.array(us)
    return {"median_us": float(np.median(a)), "p99_us": float(np.percentile(a, 99))}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--duration", type=float, default=600.0)
    ap.add_argument("--repeats", type=int, default=3)
    args = ap.parse_args()
    if any(os.environ.get(v) != "1" for v in ONE_THREAD):  # one BLAS thread: per-core figures
        env = {**os.environ, **dict.fromkeys(ONE_THREAD, "1")}
        sys.exit(subprocess.call([sys.executable, *sys.argv], env=env))
    engines = {f"main {MAIN_COMMIT} (Python)": main_engine_class(), "compiled (this branch)": PdrEngine}
    walk = walk_log()
    with tempfile.TemporaryDirectory() as tmp:
        car = simulated_log(args.duration, Path(tmp))
    lines = [
        "## pdr: compiled IMU step beside main's Python engine",
        "",
        f"Machine: {machine()}. One process, one BLAS thread, both engines in the same run "
        f"(`benchmarks/bench_pdr_kernel.py --duration {args.duration:g} --repeats {args.repeats}`).",
        "",
        "| engine | car-tunnel batch, samples/s (wall / CPU) | walk batch, samples/s (wall / CPU) "
        "| first call, s | step() IMU median / p99, us |",
        "|---|---|---|---|---|",
    ]
    outs = {}
    for name, cls in engines.items():
        bc, bw = batch(cls, car, args.repeats), batch(cls, walk, args.repeats)
        st = streaming(cls, walk)
        outs[name] = run_batch(cls(), walk)
        lines.append(
            f"| {name} | {bc['wall_sps']:,.0f} / {bc['cpu_sps']:,.0f} | {bw['wall_sps']:,.0f} / "
            f"{bw['cpu_sps']:,.0f} | {bw['first_s']:.2f} | {st['median_us']:.1f} / {st['p99_us']:.1f} |"
        )
        print(lines[-1], flush=True)
    a, b = outs.values()
    diff = float(np.nanmax(np.abs(a[["north", "east"]].to_numpy() - b[["north", "east"]].to_numpy())))
    same_src = bool((a.source.to_numpy() == b.source.to_numpy()).all())
    lines += [
        "",
        f"Outputs on the walk ({len(a)} rows): largest north/east difference {diff:.2e} m, "
        f"sources {'identical' if same_src else 'DIFFERENT'}. Car-tunnel: {len(car.imu):,} IMU samples "
        f"(100 Hz, {args.duration:g} s); walk: {len(walk.imu):,} (166 Hz, 135 s). The machine is shared "
        "(about 8 agents on 2 cores): compare the rows, not with other runs.",
    ]
    text = "\n".join(lines) + "\n"
    print(text)
    if os.environ.get("IOTNAV_WRITE_RESULTS") == "1":
        out = Path(__file__).resolve().parent / "results" / "pdr_kernel.md"
        out.write_text(text)
        print(f"wrote {out}")


if __name__ == "__main__":
    main()
