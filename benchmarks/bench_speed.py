"""Benchmark engine speed and memory: batch samples/s per engine, step latency, peak RSS for a day.

Prints a markdown section; with ``IOTNAV_WRITE_RESULTS=1`` also writes
``benchmarks/results/speed.md``.

What is measured
----------------
* **Batch**: IMU samples per second per core of :func:`iotnav.engines.base.run_batch` (one
  process, numpy's BLAS limited to one thread: the script re-executes itself with
  ``OPENBLAS_NUM_THREADS=1`` and friends) on the ``car-tunnel`` scenario (100 Hz IMU, 1 Hz GNSS, tunnels), read
  from the files the simulator writes. Ingest is not included (see the ingest section).
  Median of ``--repeats`` runs, wall clock and CPU time. Targets (issue #7): ``pipeline`` and
  ``anchor`` >= 500,000 samples/s, ``eskf`` >= 200,000 samples/s, i.e. a day of 100 Hz data
  in under a minute.
* **Streaming**: time of each ``engine.step(sample)`` call from Python over the same log,
  IMU and GNSS samples apart; median and 99th percentile.
* **Memory**: peak RSS of a fresh Python process that loads a log and runs ``run_batch``. A day
  of 100 Hz data (8.64 M IMU samples, 86,400 GNSS epochs) is the 1-hour simulated drive
  repeated with its times shifted (positions jump back at each hour; irrelevant for memory).
  Engines with a compiled ``imu_block`` (``--memory-engines``) run the whole day. Engines that
  go through the per-sample Python ``step()`` (qekf, absfix) would need about an hour for a
  day, so that path is measured with a *recorder-only* stub engine (its ``step`` returns a
  fresh :class:`~iotnav.engines.base.Output`) on 1 and 4 hours and extrapolated linearly.
* **First call**: the first ``run_batch`` of each engine in a process loads (or, with a cold
  cache, compiles) its numba kernels; its time on a 2 s log is reported apart and not
  counted in the batch rate.

Usage::

    python benchmarks/bench_speed.py [--duration 600] [--repeats 3] [--engines pipeline eskf]
"""

from __future__ import annotations

import argparse
import json
import math
import os
import pickle
import statistics
import subprocess
import sys
import tempfile
import time
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from assemble import machine
from iotnav import sim
from iotnav.engines.base import (
    Engine,
    ImuSample,
    Output,
    Sample,
    iter_samples,
    run_batch,
)
from iotnav.engines.registry import ENGINE_NAMES, available_engines, make_engine
from iotnav.io import Log, ingest

TARGETS = {"pipeline": 500_000.0, "anchor": 500_000.0, "eskf": 200_000.0}
DAY_IMU = 86_400 * 100
ONE_THREAD = ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS")


def simulated_log(duration_s: float, workdir: Path, seed: int = 0) -> Log:
    """The car-tunnel scenario of ``duration_s`` written to files and ingested."""
    d = workdir / f"car-tunnel-{duration_s:g}s"
    sim.write(sim.build("car-tunnel", seed=seed, overrides={"duration_s": duration_s}), d)
    return ingest([d / "gnss.nmea", d / "imu.csv"])


# ---------------------------------------------------------------------------------- batch


def bench_batch(log: Log, engines: list[str], repeats: int) -> list[dict[str, Any]]:
    """Median IMU samples/s of run_batch per engine (wall and CPU time)."""
    avail = set(available_engines())
    n_imu = len(log.imu)
    t_end = float(log.imu["t"].iloc[0]) + 2.0
    warm = replace(log, imu=log.imu[log.imu["t"] < t_end], gnss=log.gnss[log.gnss["t"] < t_end])
    rows: list[dict[str, Any]] = []
    for name in engines:
        if name not in avail:
            print(f"{name}: not available")
            rows.append({"engine": name, "status": "not available"})
            continue
        wall, cpu = [], []
        try:
            w0 = time.perf_counter()
            run_batch(make_engine(name), warm)
            first_s = time.perf_counter() - w0
            for _ in range(repeats):
                eng = make_engine(name)
                w0, c0 = time.perf_counter(), time.process_time()
                df = run_batch(eng, log)
                wall.append(time.perf_counter() - w0)
                cpu.append(time.process_time() - c0)
        except Exception as exc:  # an engine under construction must not stop the others
            print(f"{name}: error {type(exc).__name__}: {exc}")
            rows.append({"engine": name, "status": f"error: {type(exc).__name__}"})
            continue
        w, c = statistics.median(wall), statistics.median(cpu)
        row = {
            "engine": name,
            "status": "ok",
            "wall_sps": n_imu / w,
            "cpu_sps": n_imu / c,
            "runs_wall_s": wall,
            "day_min": DAY_IMU / (n_imu / c) / 60.0,
            "with_position": float(df["lat"].notna().mean()) if len(df) else 0.0,
            "first_call_s": first_s,
        }
        print(f"{name}: {row['wall_sps']:,.0f} samples/s wall, {row['cpu_sps']:,.0f} per CPU-s ({wall})")
        rows.append(row)
    return rows


# ------------------------------------------------------------------------------ streaming


def bench_streaming(log: Log, engines: list[str]) -> list[dict[str, Any]]:
    """Per-call time of engine.step over the log: median and p99, IMU and GNSS apart."""
    avail = set(available_engines())
    rows: list[dict[str, Any]] = []
    samples = list(iter_samples(log))
    is_imu = np.array([isinstance(s, ImuSample) for s in samples])
    for name in engines:
        if name not in avail:
            rows.append({"engine": name, "status": "not available"})
            continue
        eng = make_engine(name)
        dt = np.empty(len(samples), dtype=np.int64)
        dc = np.empty(len(samples), dtype=np.int64)
        clock, cpu = time.perf_counter_ns, time.thread_time_ns
        step = eng.step
        try:
            for k, s in enumerate(samples):
                c0 = cpu()
                t0 = clock()
                step(s)
                dt[k] = clock() - t0
                dc[k] = cpu() - c0
        except Exception as exc:
            rows.append({"engine": name, "status": f"error: {type(exc).__name__}"})
            continue
        us = dt / 1e3
        imu, other = us[is_imu], us[~is_imu]
        cpu_imu = dc[is_imu] / 1e3
        rows.append(
            {
                "engine": name,
                "status": "ok",
                "imu_median_us": float(np.median(imu)),
                "imu_p99_us": float(np.percentile(imu, 99)),
                "gnss_median_us": float(np.median(other)) if other.size else math.nan,
                "gnss_p99_us": float(np.percentile(other, 99)) if other.size else math.nan,
                "all_p99_us": float(np.percentile(us, 99)),
                "imu_cpu_median_us": float(np.median(cpu_imu)),
                "imu_cpu_p99_us": float(np.percentile(cpu_imu, 99)),
                "max_us": float(us.max()),
            }
        )
        print(f"{name}: step {rows[-1]}")
    return rows


# --------------------------------------------------------------------------------- memory


class RecorderOnly:
    """An engine stub: no filtering, a fresh :class:`Output` per IMU sample (15 new floats)."""

    def __init__(self) -> None:
        self.events: list[dict[str, Any]] = []

    def step(self, sample: Sample) -> Output | None:
        """Return an output row built from the sample's numbers."""
        if not isinstance(sample, ImuSample):
            return None
        t = sample.t
        a, g = sample.acc_b, sample.gyro_b
        return Output(
            t + 0.0,
            t * 1e-6 + 45.0,
            t * 1e-6 + 7.0,
            float(a[2]) + 100.0,
            float(a[0]) * t,
            float(a[1]) * t,
            float(a[2]) * 0.5,
            float(g[0]) + 1.0,
            float(g[1]) + 1.0,
            float(g[2]) + 1.0,
            float(g[0]) * 0.1,
            float(g[1]) * 0.1,
            float(g[2]) * 0.1,
            False,
            float(a[0]) + 3.0,
            float(a[1]) + 3.0,
            "dr",
        )

    @property
    def mount_yaw_rad(self) -> float:
        """No mount estimate."""
        return math.nan

    def summary(self) -> dict[str, Any]:
        """Nothing to report."""
        return {}


def _status_kb(key: str) -> int:
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith(key + ":"):
            return int(line.split()[1])
    return -1


def tile_log(log: Log, copies: int) -> Log:
    """``copies`` repetitions of a log, each shifted by the log's span (plus one IMU period)."""
    if copies == 1:
        return log
    span = float(log.imu["t"].iloc[-1] - log.imu["t"].iloc[0]) + float(np.median(np.diff(log.imu["t"][:100])))
    parts: dict[str, pd.DataFrame] = {}
    for kind in ("imu", "gnss"):
        df = getattr(log, kind)
        t = df["t"].to_numpy()
        big = pd.concat([df] * copies, ignore_index=True)
        big["t"] = np.concatenate([t + k * span for k in range(copies)])
        if "utc" in big:
            big["utc"] = big["t"] + (log.utc_offset_s if math.isfinite(log.utc_offset_s) else 0.0)
        parts[kind] = big
    return replace(log, imu=parts["imu"], gnss=parts["gnss"])


def memory_child(log_pickle: str, hours: int, engine: str) -> dict[str, Any]:
    """Run in a fresh process: load, tile, run; RSS figures in MB."""
    with open(log_pickle, "rb") as fh:
        hour: Log = pickle.load(fh)
    log = tile_log(hour, hours)
    del hour
    rss_log = _status_kb("VmRSS") / 1024
    log_mb = (log.imu.memory_usage(deep=True).sum() + log.gnss.memory_usage(deep=True).sum()) / 2**20
    eng: Engine = RecorderOnly() if engine == "recorder-only" else make_engine(engine)
    if engine != "recorder-only":  # load the compiled kernels before the high-water mark is reset
        run_batch(make_engine(engine), replace(log, imu=log.imu.iloc[:200], gnss=log.gnss.iloc[:2]))
    try:  # reset the high-water mark so the peak is that of the run (Linux >= 4.0)
        Path("/proc/self/clear_refs").write_text("5")
        reset = True
    except OSError:
        reset = False
    t0 = time.perf_counter()
    df = run_batch(eng, log)
    run_s = time.perf_counter() - t0
    return {
        "hours": hours,
        "engine": engine,
        "path": "step" if engine == "recorder-only" else "imu_block",
        "imu_samples": len(log.imu),
        "gnss_epochs": len(log.gnss),
        "log_mb": log_mb,
        "rss_after_log_mb": rss_log,
        "peak_rss_mb": _status_kb("VmHWM") / 1024,
        "peak_is_run_only": reset,
        "track_mb": df.memory_usage(deep=True).sum() / 2**20,
        "run_s": run_s,
    }


def _child(log_pickle: Path, hours: int, engine: str) -> dict[str, Any]:
    cmd = [sys.executable, __file__, "--memory-child", str(log_pickle), str(hours), engine]
    res = subprocess.run(cmd, capture_output=True, text=True, check=False)
    if res.returncode != 0:
        raise RuntimeError(f"memory child {hours} h {engine} failed:\n{res.stderr[-2000:]}")
    out = json.loads(res.stdout.strip().splitlines()[-1])
    print(f"memory: {out}")
    return out


def bench_memory(workdir: Path, engines: list[str]) -> dict[str, Any]:
    """Peak RSS of a day for the compiled engines, and the step path's extrapolation."""
    hour = simulated_log(3600.0, workdir, seed=1)
    pkl = workdir / "hour.pkl"
    with open(pkl, "wb") as fh:
        pickle.dump(hour, fh, protocol=pickle.HIGHEST_PROTOCOL)
    runs = [_child(pkl, 24, e) for e in engines]
    runs += [_child(pkl, h, "recorder-only") for h in (1, 4)]
    return {"runs": runs}


def _slope(runs: list[dict[str, Any]]) -> tuple[float, float]:
    """Peak RSS per IMU sample (bytes) and intercept (MB), recorder-only 1 h and 4 h."""
    a, b = (next(r for r in runs if r["engine"] == "recorder-only" and r["hours"] == h) for h in (1, 4))
    per_sample_mb = (b["peak_rss_mb"] - a["peak_rss_mb"]) / (b["imu_samples"] - a["imu_samples"])
    return per_sample_mb * 2**20, a["peak_rss_mb"] - per_sample_mb * a["imu_samples"]


# ----------------------------------------------------------------------------------- text


def _duration(seconds: float) -> str:
    return f"{seconds:.0f} s" if seconds < 120 else f"{seconds / 60:.0f} min"


def render(
    batch: list[dict[str, Any]],
    streaming: list[dict[str, Any]],
    memory: dict[str, Any] | None,
    n_imu: int,
    n_gnss: int,
    duration_s: float,
    repeats: int,
) -> str:
    """The markdown section."""
    lines = [
        "## Engine speed and memory (`benchmarks/bench_speed.py`)",
        "",
        f"Machine: {machine()}, numpy {np.__version__}. Shared machine (other jobs running), so CPU-time figures are the "
        "better per-core estimate; wall figures are given beside them.",
        "",
        f"### Batch: IMU samples per second per core (`run_batch`, median of {repeats} runs)",
        "",
        f"Log: simulated `car-tunnel`, {duration_s:g} s, {n_imu:,} IMU samples at 100 Hz, "
        f"{n_gnss:,} GNSS epochs, read from the simulator's files (ingest not timed). A day "
        f"is {DAY_IMU:,} IMU samples; its time is extrapolated from the CPU rate.",
        "",
        "| engine | samples/s (CPU) | samples/s (wall) | target | met | a day of 100 Hz takes | rows with a position | first call s |",
        "|---|---:|---:|---:|---|---:|---:|---:|",
    ]
    for r in batch:
        tgt = TARGETS.get(r["engine"])
        if r["status"] != "ok":
            lines.append(f"| `{r['engine']}` | {r['status']} | | {f'{tgt:,.0f}' if tgt else '-'} | | | | |")
            continue
        met = "-" if tgt is None else ("yes" if r["cpu_sps"] >= tgt else f"no ({r['cpu_sps'] / tgt:.1%})")
        lines.append(
            f"| `{r['engine']}` | {r['cpu_sps']:,.0f} | {r['wall_sps']:,.0f} | "
            f"{f'{tgt:,.0f}' if tgt else '-'} | {met} | {_duration(r['day_min'] * 60.0)} | {r['with_position']:.0%} | {r['first_call_s']:.1f} |"
        )
    lines += [
        "",
        "### Streaming: time per `step()` call from Python, microseconds",
        "",
        "Every sample of the same log passed to `engine.step` one by one and timed with "
        "`perf_counter_ns` (wall; includes preemption by other jobs on this shared machine) and "
        "`thread_time_ns` (CPU time of the calling thread, about 1 us resolution and overhead).",
        "",
        "| engine | IMU median | IMU p99 | IMU p99 (thread CPU) | GNSS median | GNSS p99 | all p99 | max |",
        "|---|---:|---:|---:|---:|---:|---:|---:|",
    ]
    for r in streaming:
        if r["status"] != "ok":
            lines.append(f"| `{r['engine']}` | {r['status']} | | | | | | |")
            continue
        lines.append(
            f"| `{r['engine']}` | {r['imu_median_us']:.1f} | {r['imu_p99_us']:.1f} | {r['imu_cpu_p99_us']:.1f} | "
            f"{r['gnss_median_us']:.1f} | {r['gnss_p99_us']:.1f} | {r['all_p99_us']:.1f} | {r['max_us']:.0f} |"
        )
    if memory is not None:
        runs = memory["runs"]
        lines += [
            "",
            "### Memory: peak RSS of `run_batch` in a fresh process",
            "",
            "Log: the 1-hour simulated `car-tunnel` drive (360,000 IMU, 3,600 GNSS), repeated with "
            "shifted times for a day. Engines with a compiled `imu_block` run the whole day; the "
            "per-sample `step()` path (qekf, absfix) is measured with `recorder-only`, a stub "
            "engine returning a fresh `Output` per IMU sample, on 1 h and 4 h. Peak RSS is that "
            "of the run (high-water mark reset after loading the log and the kernels) and "
            "includes the log, which stays in memory.",
            "",
            "| engine | path | hours | IMU samples | log in memory MB | RSS after loading MB | peak RSS MB | output frame MB | run s |",
            "|---|---|---:|---:|---:|---:|---:|---:|---:|",
        ]
        for r in runs:
            lines.append(
                f"| `{r['engine']}` | {r['path']} | {r['hours']} | {r['imu_samples']:,} | "
                f"{r['log_mb']:.0f} | {r['rss_after_log_mb']:.0f} | {r['peak_rss_mb']:.0f} | "
                f"{r['track_mb']:.0f} | {r['run_s']:.1f} |"
            )
        lines += [""]
        for r in runs:
            if r["hours"] == 24:
                gb = r["peak_rss_mb"] / 1024
                verdict = "under" if gb < 2.0 else "over"
                lines.append(
                    f"* `{r['engine']}`, a day measured directly: **{gb:.2f} GB** peak ({verdict} the 2 GB target)."
                )
        per, icpt = _slope(runs)
        day = icpt + per * DAY_IMU / 2**20
        lines.append(
            f"* `step()` path: {per:.0f} bytes of peak RSS per IMU sample; a day extrapolated: "
            f"**{day / 1024:.2f} GB** {'(under' if day < 2048 else '(over'} the 2 GB target)."
        )
    lines.append("")
    return "\n".join(lines)


def main() -> None:
    """Run the benchmark and print (and optionally write) the markdown section."""
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--duration", type=float, default=600.0, help="simulated seconds for batch and streaming")
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--engines", nargs="*", default=list(ENGINE_NAMES))
    ap.add_argument(
        "--memory-engines", nargs="*", default=["pipeline", "anchor", "eskf"], help="engines run on a day"
    )
    ap.add_argument("--no-memory", action="store_true")
    ap.add_argument("--memory-child", nargs=3, metavar=("PICKLE", "HOURS", "ENGINE"))
    args = ap.parse_args()
    if any(os.environ.get(v) != "1" for v in ONE_THREAD):
        # per core: numpy's BLAS on one thread, which must be set before numpy is loaded
        os.environ.update(dict.fromkeys(ONE_THREAD, "1"))
        os.execv(sys.executable, [sys.executable, __file__, *sys.argv[1:]])
    if args.memory_child:
        p, h, e = args.memory_child
        print(json.dumps(memory_child(p, int(h), e)))
        return
    with tempfile.TemporaryDirectory() as tmp:
        work = Path(tmp)
        log = simulated_log(args.duration, work)
        batch = bench_batch(log, args.engines, args.repeats)
        streaming = bench_streaming(log, args.engines)
        memory = None if args.no_memory else bench_memory(work, args.memory_engines)
    text = render(batch, streaming, memory, len(log.imu), len(log.gnss), args.duration, args.repeats)
    print(text)
    if os.environ.get("IOTNAV_WRITE_RESULTS") == "1":
        out = Path(__file__).parent / "results" / "speed.md"
        out.parent.mkdir(parents=True, exist_ok=True)
        out.write_text(text)


if __name__ == "__main__":
    main()
