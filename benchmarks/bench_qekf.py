"""End-to-end speed of ``iotnav run --engine qekf``, two code versions side by side (issue 21).

Prints a markdown section; with ``IOTNAV_WRITE_RESULTS=1`` also writes
``benchmarks/results/qekf.md``.

What is measured
----------------
Whole ``iotnav run FILES --engine qekf --out O`` processes (start-up, ingest, the engine, the
outputs), wall and CPU time (user + sys of the child), each code version run alternately in the
same benchmark run (median of ``--repeats`` after one warm-up run per version, which fills its
numba cache): *before* is the source tree given by ``--before`` (e.g. ``git archive COMMIT src |
tar -x -C /tmp/qekf-before``), *after* this tree. The engine's own time is the ``runtime_s``
that ``iotnav run`` writes into summary.json (wall).

Drives (issue 21's target: >= 100,000 IMU samples/s end to end on a held-out 30-minute 100 Hz
drive, start-up subtracted), seed 2101 (no test or tuning uses it):

* ``iotnav simulate car-tunnel --set duration_s=D`` (MPU-6050 at 100 Hz, GNSS 1 Hz, tunnels; the
  drive of ``bench_e2e.py``): no magnetometer, so qekf's no-magnetometer fallback (mount
  aligner, horizontal re-initialisations, heading reset, non-holonomic observations);
* ``iotnav simulate car-magnetometer --set duration_s=D --set imu.rate_hz=100`` (the paper's
  case: HMC5883L at 6 Hz, TRIAD observations), run with the simulator's magnetometer
  calibration in a ``--config`` TOML (the paper's sensors are "previously calibrated"; without
  it most samples are refused as disturbed);
* the bundled real walk ``rtklibexplorer_gnss_imu/walk_0827`` (NMEA + ICM-45686 at 100 Hz, no
  magnetometer), process times only (``--walk``).

Start-up = the same command on a 3 s drive of the same scenario, seed and configuration,
subtracted: ``samples/s = N_imu / (t_full - t_start-up)``, wall and CPU.

Usage::

    python benchmarks/bench_qekf.py --before /tmp/qekf-before [--duration 1800] [--repeats 3] [--walk]
"""

from __future__ import annotations

import argparse
import json
import math
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
SHORT_S = 3.0
TARGET = 100_000.0
CLI = "import sys; from iotnav.cli import main; sys.argv[0] = 'iotnav'; main()"


def run_once(src: Path, args: list[str], out: Path) -> tuple[float, float, float, int]:
    """Wall and CPU seconds of one ``iotnav`` process on the package in ``src``, its engine
    ``runtime_s`` and IMU sample count (summary.json)."""
    wall, cpu = timed(["env", f"PYTHONPATH={src}", sys.executable, "-c", CLI, *args, "--out", str(out)])
    summary = json.loads((out / "summary.json").read_text())
    return wall, cpu, float(summary["runtime_s"]), int(summary["counts"]["imu_samples_in"])


def simulate(src: Path, scenario: str, out: Path, seconds: float, extra: list[str]) -> None:
    """``iotnav simulate`` with the package in ``src``."""
    subprocess.run(
        [sys.executable, "-c", CLI, "simulate", scenario, "--out", str(out), "--seed", str(SEED),
         "--set", f"duration_s={seconds:g}", *extra],
        env={**os.environ, "PYTHONPATH": str(src)}, check=True, capture_output=True,
    )  # fmt: skip


def mag_config(drive: Path, out: Path) -> Path:
    """A qekf TOML with the simulated magnetometer's calibration (scenario.json's draw)."""
    draw = json.loads((drive / "scenario.json").read_text())["resolved"]["mag_draw"]
    soft = [v for row in draw["soft_iron"] for v in row]
    out.write_text(
        "[qekf]\n"
        f"mag_hard_iron_ut = [{', '.join(repr(float(v)) for v in draw['hard_iron_ut'])}]\n"
        f"mag_soft_iron = [{', '.join(repr(float(v)) for v in soft)}]\n"
    )
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--before", type=Path, required=True, help="Source tree of the code before (its src/).")
    ap.add_argument("--duration", type=float, default=1800.0, help="Simulated drive length, s.")
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--walk", action="store_true", help="Also the real walk_0827 (process times).")
    args = ap.parse_args()
    datasets = Path(os.environ.get("IOTNAV_DATASETS", "/work/shared/datasets"))
    versions = {"before": args.before.resolve() / "src", "after": HERE / "src"}
    work = Path(tempfile.mkdtemp(prefix="iotnav-qekf-"))
    rows = []
    try:
        # name -> (full command, start-up command or None)
        logs: dict[str, tuple[list[str], list[str] | None]] = {}
        for scen, extra in (("car-tunnel", []), ("car-magnetometer", ["--set", "imu.rate_hz=100"])):
            runs = []
            for tag, seconds in (("full", args.duration), ("short", SHORT_S)):
                d = work / f"{scen}-{tag}"
                simulate(versions["after"], scen, d, seconds, extra)
                cmd = ["run", str(d), "--engine", "qekf"]
                if scen == "car-magnetometer":
                    cmd += ["--config", str(mag_config(d, work / f"{scen}-{tag}.toml"))]
                runs.append(cmd)
            logs[f"{scen} {args.duration:g} s, 100 Hz (simulated)"] = (runs[0], runs[1])
        if args.walk:
            walk = datasets / "rtklibexplorer_gnss_imu" / "walk_0827"
            files = [str(walk / "gnss_1730_nmea.txt"), str(walk / "imu_1730.csv")]
            logs["walk_0827 (real, no magnetometer)"] = (["run", *files, "--engine", "qekf"], None)
        for name, (cmd, short) in logs.items():
            res: dict[str, list[tuple[float, float, float, int]]] = {v: [] for v in versions}
            up: dict[str, list[tuple[float, float, float, int]]] = {v: [] for v in versions}
            for v, src in versions.items():  # warm-up: numba caches
                run_once(src, cmd, work / f"warm-{v}")
            for k in range(args.repeats):  # alternate, so both see the same load
                for v, src in versions.items():
                    res[v].append(run_once(src, cmd, work / f"{v}-{k}"))
                    if short is not None:
                        up[v].append(run_once(src, short, work / f"up-{v}-{k}"))
            med = {}
            for v in versions:
                m = [statistics.median(r[i] for r in res[v]) for i in range(3)]
                n = res[v][0][3]
                u = [statistics.median(r[i] for r in up[v]) for i in range(2)] if up[v] else [math.nan] * 2
                sps = [n / (m[i] - u[i]) if m[i] > u[i] else math.nan for i in range(2)]
                med[v] = (*m, *u, *sps, n)
            rows.append((name, med))
            print(name, {v: [round(x, 2) for x in m] for v, m in med.items()}, flush=True)
    finally:
        shutil.rmtree(work, ignore_errors=True)

    def sps(x: float) -> str:
        return "-" if math.isnan(x) else f"{x:,.0f}"

    lines = [
        "## qekf end to end, before and after",
        "",
        f"`benchmarks/bench_qekf.py --duration {args.duration:g} --repeats {args.repeats}`: whole "
        "`iotnav run FILES --engine qekf` processes (start-up, ingest, engine, outputs) of two code "
        "versions (before: `--before`; after: this tree), alternated in one run; medians of "
        f"{args.repeats} after a warm-up run each (warm numba cache). Start-up = the same command on "
        f"a {SHORT_S:g} s drive, subtracted for samples/s (issue 21's target >= {TARGET:,.0f} end to "
        "end). Engine = `runtime_s` of summary.json (wall). Held-out seed "
        f"{SEED}. Machine: {machine()}; shared, so wall times are inflated: CPU times beside them.",
        "",
        "| log | version | process wall / CPU, s | start-up wall / CPU, s | samples/s end to end "
        "wall / CPU | engine wall, s |",
        "| --- | --- | ---: | ---: | ---: | ---: |",
    ]
    for name, med in rows:
        for v, m in med.items():
            up = "-" if math.isnan(m[3]) else f"{m[3]:.2f} / {m[4]:.2f}"
            lines.append(
                f"| {name} | {v} | {m[0]:.2f} / {m[1]:.2f} | {up} | {sps(m[5])} / {sps(m[6])} | {m[2]:.2f} |"
            )
    text = "\n".join([*lines, ""])
    print(text)
    if os.environ.get("IOTNAV_WRITE_RESULTS") == "1":
        RESULTS.parent.mkdir(parents=True, exist_ok=True)
        RESULTS.write_text(text)
        print(f"wrote {RESULTS}")


if __name__ == "__main__":
    main()
