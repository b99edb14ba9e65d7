"""Compile the engines' numba kernels into the on-disk cache before they are first needed.

numba compiles a kernel the first time it is called and keeps the machine code in the cache
folder chosen by :func:`iotnav._numba_cache_dir`. From an empty cache the engines cost tens of
CPU-seconds each (eskf about 55 s, qekf 28 s, pipeline 23 s on a 2-core Xeon). Processes that
start together on an empty cache (the workers of ``pytest -n 2``, the workers of
``iotnav run-many``) each compile the same kernels. Running this once before them compiles each
kernel once, spread over ``jobs`` processes, and the later processes only load it.

``python -m iotnav.warmup [--jobs N] [ENGINE ...]`` runs every engine (guarded, unguarded and
the stepping path, and eskf's smoother) on a short simulated ``car-magnetometer`` drive, which
has every input the engines take (IMU, GNSS with speed and course, magnetometer). Nothing is
written but the cache.
"""

from __future__ import annotations

import argparse
import itertools
import os
import tempfile
import time
from collections.abc import Sequence
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

#: Engines in decreasing order of compile time (measured from an empty cache), so that a greedy
#: split over the jobs balances them.
ENGINES: tuple[str, ...] = ("eskf", "qekf", "pipeline", "fixes", "pdr", "anchor", "absfix")

#: Seconds of simulated driving: enough for every engine to initialise and take GNSS updates
#: (car-magnetometer starts with 40 s static).
DURATION_S = 60.0


def warm_engines(engines: Sequence[str]) -> dict[str, float]:
    """Run each engine once on a short simulated drive; wall seconds per engine.

    Parameters
    ----------
    engines : sequence of str
        Engine names of :func:`iotnav.engines.registry.make_engine`.

    Returns
    -------
    dict
        Engine name to wall time of its runs, s.
    """
    from iotnav import sim
    from iotnav.engines.base import iter_samples, run_batch
    from iotnav.engines.registry import make_engine
    from iotnav.io import ingest

    out: dict[str, float] = {}
    with tempfile.TemporaryDirectory(prefix="iotnav-warmup-") as tmp:
        r = sim.build("car-magnetometer", seed=0, overrides={"duration_s": DURATION_S})
        sim.write(r, Path(tmp))
        log = ingest([Path(tmp)])
        for name in engines:
            t0 = time.perf_counter()
            run_batch(make_engine(name), log)
            run_batch(make_engine(name, integrity=False), log)
            eng = make_engine(name)
            for s in itertools.islice(iter_samples(log), 3000):
                eng.step(s)
            if name == "eskf":  # and the smoother's compiled backward pass
                from iotnav.engines.smoother import smooth_output

                sm = make_engine(name, smoothing=True)
                smooth_output(sm, run_batch(sm, log))  # type: ignore[arg-type]
            if name == "absfix":  # with fixes: the kernel's stops, replays and the step path
                _warm_absfix()
            out[name] = time.perf_counter() - t0
    return out


def _warm_absfix() -> None:
    """absfix with late fixes (``pedestrian-fixes``, 20 s): batch, revised and ``step()``."""
    from iotnav import sim
    from iotnav.engines.absfix import AbsfixEngine, _merged, fixes_from_table, run_with_fixes
    from iotnav.io.log import Log

    r = sim.build("pedestrian-fixes", seed=0, overrides={"duration_s": 20.0, "fixes.latency_s": 0.5})
    assert r.fixes is not None
    log = Log(imu=r.imu)
    run_with_fixes(AbsfixEngine(), log, r.fixes)
    run_with_fixes(AbsfixEngine(), log, r.fixes, revised=True)
    eng = AbsfixEngine()
    for s in _merged(log, fixes_from_table(r.fixes)):
        eng.step(s)


def split(engines: Sequence[str], jobs: int) -> list[list[str]]:
    """Share ``engines`` (in :data:`ENGINES` order of cost) over ``jobs`` lists, round-robin.

    Parameters
    ----------
    engines : sequence of str
        Engine names.
    jobs : int
        Number of processes (at least 1).

    Returns
    -------
    list of list of str
        Non-empty lists, at most ``jobs``.
    """
    order = sorted(engines, key=lambda e: ENGINES.index(e) if e in ENGINES else len(ENGINES))
    groups: list[list[str]] = [[] for _ in range(max(1, jobs))]
    for i, name in enumerate(order):
        groups[i % len(groups)].append(name)
    return [g for g in groups if g]


def main(argv: Sequence[str] | None = None) -> int:
    """Command line: ``python -m iotnav.warmup [--jobs N] [ENGINE ...]``; exit status."""
    ap = argparse.ArgumentParser(prog="python -m iotnav.warmup", description=__doc__.splitlines()[0])
    ap.add_argument("engines", nargs="*", default=list(ENGINES), help="engines (default: all)")
    ap.add_argument("--jobs", default="1", help="processes, or 'auto' for one per CPU (default 1)")
    args = ap.parse_args(argv)
    unknown = sorted(set(args.engines) - set(ENGINES))
    if unknown:
        ap.error(f"unknown engine(s) {', '.join(unknown)}; expected some of {', '.join(ENGINES)}")
    if args.jobs == "auto":
        jobs = os.cpu_count() or 1
    elif args.jobs.isdigit():
        jobs = int(args.jobs)
    else:
        ap.error(f"--jobs {args.jobs!r}: expected a whole number or 'auto'")
    t0 = time.perf_counter()
    groups = split(args.engines, jobs)
    if len(groups) == 1:
        times = warm_engines(groups[0])
    else:
        times = {}
        with ProcessPoolExecutor(len(groups)) as pool:
            for part in pool.map(warm_engines, groups):
                times.update(part)
    per = ", ".join(f"{k} {v:.0f} s" for k, v in times.items())
    print(f"iotnav warm-up: kernels compiled or loaded in {time.perf_counter() - t0:.0f} s ({per})")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
