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

Outputs before and after (``--outputs``): both versions run the same logs in one process each
(:func:`dump`: car-tunnel and car-magnetometer of ``--outputs-duration`` s in six configurations,
walk_0827 and drive_0708 alone and guarded, 30,000 samples streamed through ``step()``), and the
output rows, final ``x`` and ``P``, NIS, events and smoothing records are compared: bitwise, or
the largest difference.

Usage::

    python benchmarks/bench_qekf.py --before /tmp/qekf-before [--duration 1800] [--repeats 3] [--walk]
    python benchmarks/bench_qekf.py --before /tmp/qekf-before --outputs [--outputs-duration 300]
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
from typing import Any

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


def dump(out: Path, seconds: float, datasets: Path) -> None:
    """Run the qekf cases of ``--outputs`` with the package on ``sys.path``; arrays into ``out`` (npz)."""
    import itertools

    import numpy as np

    from iotnav import sim
    from iotnav.engines.base import FLOAT_COLUMNS, iter_samples, run_batch
    from iotnav.engines.qekf import QekfConfig, QekfEngine
    from iotnav.engines.registry import make_engine
    from iotnav.io import ingest

    def simulated(name: str, extra: dict[str, float]) -> tuple[Path, Any]:
        d = out.parent / f"{name}-{seconds:g}"
        if not d.exists():
            sim.write(sim.build(name, seed=SEED, overrides={"duration_s": seconds, **extra}), d)
        return d, ingest([d])

    _d, tunnel = simulated("car-tunnel", {})
    d_mag, car_mag = simulated("car-magnetometer", {"imu.rate_hz": 100})
    draw = json.loads((d_mag / "scenario.json").read_text())["resolved"]["mag_draw"]
    mag = {
        "mag_hard_iron_ut": tuple(float(v) for v in draw["hard_iron_ut"]),
        "mag_soft_iron": tuple(float(v) for row in draw["soft_iron"] for v in row),
    }
    rk = datasets / "rtklibexplorer_gnss_imu"
    walk = ingest([rk / "walk_0827" / "gnss_1730_nmea.txt", rk / "walk_0827" / "imu_1730.csv"])
    drive = ingest([rk / "drive_0708" / "gnss_1934_sf.pos", rk / "drive_0708" / "imu_1934.csv"])
    cases: dict[str, tuple[Any, Any]] = {
        "car-tunnel": (tunnel, QekfConfig()),
        "car-tunnel smoothing": (tunnel, QekfConfig(smoothing=True)),
        "car-magnetometer": (car_mag, QekfConfig(**mag)),
        "car-magnetometer smoothing": (car_mag, QekfConfig(smoothing=True, **mag)),
        "car-magnetometer consistent form": (car_mag, QekfConfig.consistent(**mag)),
        "car-magnetometer jacobian coupling": (car_mag, QekfConfig(triad_state_coupling="jacobian", **mag)),
        "car-magnetometer noise coupling": (car_mag, QekfConfig(triad_state_coupling="noise", **mag)),
        "car-magnetometer 28 states": (car_mag, QekfConfig(gnss_error_states=True, **mag)),
        "walk_0827": (walk, QekfConfig()),
        "drive_0708": (drive, QekfConfig()),
    }
    res: dict[str, Any] = {}
    for name, (log, cfg) in cases.items():
        eng = QekfEngine(cfg)
        df = run_batch(eng, log)
        res[f"{name}|rows"] = df[list(FLOAT_COLUMNS)].to_numpy()
        res[f"{name}|x"], res[f"{name}|P"] = eng.x, eng.P
        res[f"{name}|nis"] = np.array([(t, v, m) for t, _, v, m in eng.nis]).reshape(-1, 3)
        res[f"{name}|events"] = np.array(json.dumps(eng.events, default=str))
        if eng.smoothing_log is not None:
            for part in ("x_prior", "x_post", "Phi", "P_prior", "P_post"):
                res[f"{name}|smoothing {part}"] = np.array(getattr(eng.smoothing_log, part))
    for name, log in (("walk_0827 guarded", walk), ("drive_0708 guarded", drive)):
        df = run_batch(make_engine("qekf"), log)
        res[f"{name}|rows"] = df[list(FLOAT_COLUMNS)].to_numpy()
        res[f"{name}|events"] = np.array(json.dumps(df.attrs["events"], default=str))
    eng = QekfEngine(QekfConfig(**mag))
    rows = [
        [getattr(o, c) for c in FLOAT_COLUMNS]
        for s in itertools.islice(iter_samples(car_mag), 30000)
        if (o := eng.step(s)) is not None
    ]
    res["car-magnetometer step()|rows"] = np.array(rows, float)
    np.savez(out, **res)


def compare_outputs(before: Path, after: Path) -> list[str]:
    """Markdown rows: per case and quantity, bitwise or the largest difference."""
    import numpy as np

    from iotnav.engines.base import FLOAT_COLUMNS

    a, b = np.load(before), np.load(after)
    if set(a.files) != set(b.files):
        raise RuntimeError(f"different outputs: {sorted(set(a.files) ^ set(b.files))}")
    lines = []
    for key in sorted(a.files):
        case, what = key.split("|")
        x, y = a[key], b[key]
        if what == "events":
            ea, eb = json.loads(str(x)), json.loads(str(y))
            same_kinds = [e["type"] for e in ea] == [e["type"] for e in eb]
            if ea == eb:
                note = f"equal ({len(ea)})"
            else:
                worst = max(
                    (abs(u[k] - v[k]) / max(abs(u[k]), 1e-300) for u, v in zip(ea, eb, strict=True) for k in u
                     if isinstance(u[k], float) and u[k] != v[k]),
                    default=0.0,
                )  # fmt: skip
                note = (
                    f"same {len(ea)} events in order: {same_kinds}; float fields within {worst:.1g} relative"
                )
            lines.append(f"| {case} | events | {note} |")
            continue
        if x.shape != y.shape:
            lines.append(f"| {case} | {what} | shape {x.shape} -> {y.shape} |")
            continue
        if np.array_equal(x, y, equal_nan=True):
            lines.append(f"| {case} | {what} | bitwise |")
            continue
        d = np.abs(x - y)
        if what == "rows":
            worst = np.nanmax(d, axis=0)
            parts = [f"{c} {v:.1g}" for c, v in zip(FLOAT_COLUMNS, worst, strict=True) if v > 0]
            lines.append(f"| {case} | rows | max abs difference: {', '.join(parts)} |")
        else:
            rel = float(np.nanmax(d / np.maximum(np.abs(x), 1e-300)))
            lines.append(f"| {case} | {what} | max abs {float(np.nanmax(d)):.1g}, relative {rel:.1g} |")
    return lines


def outputs_section(versions: dict[str, Path], seconds: float, datasets: Path) -> str:
    """Both versions' :func:`dump` (a process each) compared: the markdown section."""
    work = Path(tempfile.mkdtemp(prefix="iotnav-qekf-out-"))
    try:
        files = {}
        for v, src in versions.items():
            files[v] = work / f"{v}.npz"
            code = (
                "import sys; sys.path.insert(0, sys.argv[4]); import bench_qekf as b; "
                "b.dump(b.Path(sys.argv[1]), float(sys.argv[2]), b.Path(sys.argv[3]))"
            )
            subprocess.run(
                [sys.executable, "-c", code, str(files[v]), str(seconds), str(datasets), str(Path(__file__).parent)],
                env={**os.environ, "PYTHONPATH": str(src)}, check=True,
            )  # fmt: skip
        rows = compare_outputs(files["before"], files["after"])
    finally:
        shutil.rmtree(work, ignore_errors=True)
    return "\n".join(
        [
            "## qekf outputs, before and after",
            "",
            f"`benchmarks/bench_qekf.py --outputs --outputs-duration {seconds:g}`: the same logs through both "
            "versions (simulated drives of the held-out seed, the real walk_0827 and drive_0708), output "
            "rows, final state and covariance, NIS, events and smoothing records compared.",
            "",
            "| case | output | before -> after |",
            "| --- | --- | --- |",
            *rows,
            "",
        ]
    )


def split(seconds: float) -> str:
    """CPU seconds of ``run_batch`` of the guarded engine on the car-tunnel drive, and of the
    functions inside it that take the most (each wrapped by a timer); markdown lines."""
    import time

    from iotnav import sim
    from iotnav.engines import qekf as Q
    from iotnav.engines.base import run_batch
    from iotnav.engines.registry import make_engine
    from iotnav.io import ingest
    from iotnav.techniques import mount

    spent: dict[str, float] = {}

    def wrap(obj: Any, name: str, label: str) -> None:
        f = getattr(obj, name)

        def timed_call(*a: Any, **k: Any) -> Any:
            t = time.process_time()
            try:
                return f(*a, **k)
            finally:
                spent[label] = spent.get(label, 0.0) + time.process_time() - t

        setattr(obj, name, timed_call)

    wrap(Q.K, "imu_run", "compiled IMU kernel (imu_run)")
    wrap(Q.QekfEngine, "_gnss", "GNSS epochs (QekfEngine._gnss, all)")
    wrap(mount.MountAligner, "add_gnss", "  of which the mount aligner (MountAligner.add_gnss)")
    wrap(Q, "geodetic_to_ecef", "  of which geodetic_to_ecef (pymap3d)")
    wrap(Q.QekfEngine, "_nhc", "non-holonomic observations (QekfEngine._nhc)")
    with tempfile.TemporaryDirectory(prefix="iotnav-qekf-split-") as tmp:
        sim.write(sim.build("car-tunnel", seed=SEED, overrides={"duration_s": seconds}), Path(tmp))
        log = ingest([Path(tmp)])
    run_batch(make_engine("qekf"), log)  # kernels loaded
    spent.clear()
    t0 = time.process_time()
    run_batch(make_engine("qekf"), log)
    total = time.process_time() - t0
    n = len(log.imu)
    lines = [f"| run_batch, guarded (make_engine default) | {total:.2f} | {n / total:,.0f} samples/s |"]
    order = [  # the wrapped functions in the order they were wrapped
        "compiled IMU kernel (imu_run)",
        "GNSS epochs (QekfEngine._gnss, all)",
        "  of which the mount aligner (MountAligner.add_gnss)",
        "  of which geodetic_to_ecef (pymap3d)",
        "non-holonomic observations (QekfEngine._nhc)",
    ]
    lines += [f"| {k} | {spent[k]:.2f} | {100 * spent[k] / total:.0f} % |" for k in order if k in spent]
    return "\n".join(
        [
            f"`benchmarks/bench_qekf.py --split --duration {seconds:g}` (car-tunnel, seed {SEED}, one process, "
            "the second run): CPU seconds.",
            "",
            "| part | CPU, s | share |",
            "| --- | ---: | ---: |",
            *lines,
            "",
        ]
    )


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--before", type=Path, help="Source tree of the code before (its src/).")
    ap.add_argument("--outputs", action="store_true", help="Compare the outputs instead of timing.")
    ap.add_argument("--split", action="store_true", help="Where run_batch spends its time (this tree).")
    ap.add_argument("--outputs-duration", type=float, default=300.0, help="Simulated drives of --outputs, s.")
    ap.add_argument("--duration", type=float, default=1800.0, help="Simulated drive length, s.")
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--walk", action="store_true", help="Also the real walk_0827 (process times).")
    args = ap.parse_args()
    datasets = Path(os.environ.get("IOTNAV_DATASETS", "/work/shared/datasets"))
    if args.split:
        print(split(args.duration))
        return
    if args.before is None:
        ap.error("--before is required (except with --split)")
    versions = {"before": args.before.resolve() / "src", "after": HERE / "src"}
    if args.outputs:
        text = outputs_section(versions, args.outputs_duration, datasets)
        print(text)
        if os.environ.get("IOTNAV_WRITE_RESULTS") == "1":
            out = RESULTS.with_name("qekf_outputs.md")
            out.write_text(text)
            print(f"wrote {out}")
        return
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
