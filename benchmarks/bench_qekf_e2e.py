"""qekf end to end beside its kernel, for one or two code trees in the same run (issue 21).

* **End to end**: CPU (user + sys) and wall seconds of a whole ``iotnav run DIR --engine qekf
  --out O`` process on ``iotnav simulate car-tunnel --seed 2101 --set duration_s=D`` (held-out
  seed; read gnss.nmea and imu.csv, fuse, write every output).
* **Start-up**: the same command on a 3 s drive of the same scenario and seed, subtracted:
  samples/s = IMU samples / (end to end - start-up).
* **Kernel**: :func:`iotnav.engines.base.run_batch` of ``make_engine("qekf")`` alone on the
  same log in one process of the same tree (the second call; the first loads the numba cache).

Each tree (``--trees``, directories holding ``src/iotnav``; default this checkout) runs with
``PYTHONPATH=<tree>/src``; the trees alternate within each repeat, so load on a shared machine
falls on both. Medians of ``--repeats``. Usage::

    python benchmarks/bench_qekf_e2e.py [--duration 1800] [--repeats 3] [--trees /tmp/old .]
"""

from __future__ import annotations

import argparse
import os
import resource
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

RESULTS = Path(__file__).resolve().parent / "results" / "qekf_e2e.md"
SEED = 2101
SHORT_S = 3.0
TARGET = 100_000.0

KERNEL = """
import sys, time
from iotnav.engines.base import run_batch
from iotnav.engines.registry import make_engine
from iotnav.io import ingest
d = sys.argv[1]
log = ingest([d + "/gnss.nmea", d + "/imu.csv"])
run_batch(make_engine("qekf"), log)
t, c = time.perf_counter(), time.process_time()
run_batch(make_engine("qekf"), log)
print(time.perf_counter() - t, time.process_time() - c, len(log.imu))
"""


def _env(tree: Path) -> dict[str, str]:
    return {**os.environ, "PYTHONPATH": str(tree / "src")}


def _cli(tree: Path, *args: str) -> tuple[float, float]:
    """Wall and CPU (user + sys of the child) seconds of one ``iotnav`` process of ``tree``."""
    cmd = [
        sys.executable,
        "-c",
        "import sys; from iotnav.cli import main; sys.argv[0] = 'iotnav'; main()",
        *args,
    ]
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    t0 = time.perf_counter()
    res = subprocess.run(cmd, capture_output=True, text=True, env=_env(tree))
    wall = time.perf_counter() - t0
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    if res.returncode != 0:
        raise RuntimeError(f"{' '.join(args)} failed ({res.returncode}): {res.stderr[-2000:]}")
    return wall, (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)


def _kernel(tree: Path, drive: Path) -> tuple[float, float, int]:
    res = subprocess.run(
        [sys.executable, "-c", KERNEL, str(drive)], capture_output=True, text=True, env=_env(tree), check=True
    )
    wall, cpu, n = res.stdout.split()[-3:]
    return float(wall), float(cpu), int(n)


def main() -> None:
    """Run the comparison and write ``benchmarks/results/qekf_e2e.md``."""
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--duration", type=float, default=1800.0, help="drive length, s")
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--trees", nargs="+", type=Path, default=[Path(__file__).resolve().parents[1]])
    ap.add_argument("--out", type=Path, default=RESULTS)
    args = ap.parse_args()
    trees = [t.resolve() for t in args.trees]
    with tempfile.TemporaryDirectory() as tmp:
        work = Path(tmp)
        drive, short = work / "drive", work / "short"
        for d, dur in ((drive, args.duration), (short, SHORT_S)):
            _cli(
                trees[-1],
                "simulate",
                "car-tunnel",
                "--seed",
                str(SEED),
                "--set",
                f"duration_s={dur}",
                "--out",
                str(d),
            )
        runs: dict[Path, dict[str, list[float]]] = {
            t: {k: [] for k in "fw fc uw uc kw kc".split()} for t in trees
        }
        n = 0
        for t in trees:  # warm-up: numba cache per tree
            _cli(t, "run", str(short), "--engine", "qekf", "--out", str(work / "warm"))
        for rep in range(args.repeats):
            for t in trees:
                r = runs[t]
                fw, fc = _cli(t, "run", str(drive), "--engine", "qekf", "--out", str(work / f"o{rep}"))
                uw, uc = _cli(t, "run", str(short), "--engine", "qekf", "--out", str(work / f"s{rep}"))
                kw, kc, n = _kernel(t, drive)
                for k, v in zip("fw fc uw uc kw kc".split(), (fw, fc, uw, uc, kw, kc), strict=True):
                    r[k].append(v)
                print(
                    f"{t}: e2e {fw:.2f}/{fc:.2f} s, start-up {uw:.2f}/{uc:.2f} s, kernel {kw:.2f}/{kc:.2f} s"
                )
    load = os.getloadavg()[0]
    lines = [
        "## qekf end to end beside the kernel (issue 21)",
        "",
        f"`benchmarks/bench_qekf_e2e.py --duration {args.duration:g} --repeats {args.repeats}`: whole "
        f"`iotnav run DIR --engine qekf` processes on `iotnav simulate car-tunnel --seed {SEED} --set "
        f"duration_s={args.duration:g}` ({n:,} IMU samples), start-up (the same command on a {SHORT_S:g} s "
        "drive) subtracted; kernel = `run_batch` alone in one process of the same tree (second call). "
        f"Trees alternated per repeat; medians. Machine: 2 cores, shared (load {load:.1f} at the end): "
        "CPU times are the figures to read.",
        "",
        "| tree | end to end, s (wall / CPU) | start-up, s (wall / CPU) | samples/s end to end "
        "(wall / CPU) | kernel samples/s (wall / CPU) | end to end / kernel (CPU) | target |",
        "| --- | ---: | ---: | ---: | ---: | ---: | ---: |",
    ]
    for t in trees:
        m = {k: statistics.median(v) for k, v in runs[t].items()}
        e2e_w, e2e_c = n / max(m["fw"] - m["uw"], 1e-9), n / max(m["fc"] - m["uc"], 1e-9)
        k_w, k_c = n / m["kw"], n / m["kc"]
        lines.append(
            f"| {t} | {m['fw']:.2f} / {m['fc']:.2f} | {m['uw']:.2f} / {m['uc']:.2f} | {e2e_w:,.0f} / "
            f"{e2e_c:,.0f} | {k_w:,.0f} / {k_c:,.0f} | {e2e_c / k_c:.2f} | >= {TARGET:,.0f} |"
        )
    args.out.write_text("\n".join(lines) + "\n")
    print("\n".join(lines))


if __name__ == "__main__":
    main()
