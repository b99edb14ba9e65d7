"""In-process CPU time of ``run_batch`` and of the guard's ``on_fix`` on one drive, for A/B runs.

Run it once per source tree, alternating (``PYTHONPATH=TREE/src python benchmarks/bench_fuse_ab.py
DRIVE_DIR``), to compare two trees in the same window on a shared machine: whole-process figures
do not resolve tens of milliseconds there (``benchmarks/results/e2e.md``).

Prints, per engine, the minimum and median CPU seconds of ``repeats`` ``run_batch`` calls after
a warm-up call, and the CPU milliseconds of :meth:`iotnav.engines.integrity.IntegrityGuard.on_fix`
over the drive's valid fixes (the watch enabled from the first fix).
"""

from __future__ import annotations

import argparse
import statistics
import time
from pathlib import Path

from iotnav.engines import integrity
from iotnav.engines.base import GnssSample, iter_samples, run_batch
from iotnav.engines.registry import make_engine
from iotnav.io import ingest


def fuse_cpu(log: object, engine: str, repeats: int) -> list[float]:
    """CPU seconds of ``repeats`` ``run_batch`` calls of ``engine`` on ``log`` (after a warm-up)."""
    run_batch(make_engine(engine), log)  # type: ignore[arg-type]
    out = []
    for _ in range(repeats):
        c = time.process_time()
        run_batch(make_engine(engine), log)  # type: ignore[arg-type]
        out.append(time.process_time() - c)
    return out


def on_fix_cpu(fixes: list[GnssSample]) -> float:
    """CPU seconds of one guard taking every fix (the consistency watch on from the start)."""
    g = integrity.IntegrityGuard()
    g.st[integrity.S_LAST_OK] = 1.0
    c = time.process_time()
    for s in fixes:
        g.on_fix(s)
    return time.process_time() - c


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("drive", type=Path, help="Folder with gnss.nmea and imu.csv (iotnav simulate).")
    ap.add_argument("--engines", nargs="+", default=["pipeline", "eskf"])
    ap.add_argument("--repeats", type=int, default=5)
    args = ap.parse_args()
    log = ingest([args.drive / "gnss.nmea", args.drive / "imu.csv"])
    for e in args.engines:
        ts = fuse_cpu(log, e, args.repeats)
        print(f"{e}: run_batch CPU-s min {min(ts):.3f} median {statistics.median(ts):.3f}")
    fixes = [s for s in iter_samples(log) if isinstance(s, GnssSample) and s.valid]
    on_fix_cpu(fixes)
    ms = [1e3 * on_fix_cpu(fixes) for _ in range(args.repeats)]
    print(f"on_fix over {len(fixes)} fixes: CPU ms median {statistics.median(ms):.1f}")


if __name__ == "__main__":
    main()
