"""Compile the engines' numba kernels into the on-disk cache before they are first needed.

numba compiles a kernel the first time it is called and keeps the machine code in the cache
folder chosen by :func:`iotnav._numba_cache_dir`. From an empty cache the engines cost up to tens of
CPU-seconds each (:data:`COST_S`: eskf 40 s, qekf 23 s on a 2-core Xeon). Processes that
start together on an empty cache (the workers of ``pytest -n 2``, the workers of
``iotnav run-many``) each compile the same kernels. Running this once before them compiles each
kernel once, spread over ``jobs`` processes, and the later processes only load it.

``python -m iotnav.warmup [--jobs N] [TARGET ...]`` runs every engine (guarded, unguarded and
the stepping path; eskf's smoother; the fixes engine's own RTS smoother and resampling; qekf
without the magnetometer, its non-holonomic fallback) on a short simulated ``car-magnetometer``
drive, which has every input the engines take (IMU, GNSS with speed and course, magnetometer).
The ``techniques`` target compiles the kernels outside the engines that commands and tests
reach: the attitude filter :func:`iotnav.techniques.ahrs_eskf.run_ahrs_eskf` (6- and 9-axis,
batch and per sample; ``iotnav attitude`` and the attitude benchmark), the compiled cascade
loop and the tracker's odometer. Nothing is written but the cache.
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

#: The engines of :func:`iotnav.engines.registry.make_engine`.
ENGINES: tuple[str, ...] = ("eskf", "qekf", "pipeline", "fixes", "pdr", "anchor", "absfix")

#: Warm-up targets: every engine, and the kernels outside them (module docstring).
TARGETS: tuple[str, ...] = (*ENGINES, "techniques")

#: CPU seconds of each target from an empty cache, alone in a fresh process (2-core Xeon,
#: ``NUMBA_CACHE_DIR=<empty> python -m iotnav.warmup --jobs 1 TARGET``, the printed CPU time);
#: weights of :func:`split`. A target run after another in one process costs less (kernels they
#: share, such as the integrity guard's ``guard_rows`` and ``integrity_fix.fix_step``, which every
#: engine target compiles through the guarded run, are compiled once): pipeline after eskf about 7 s.
COST_S: dict[str, float] = {
    "eskf": 40.0,
    "techniques": 27.0,
    "qekf": 23.0,  # 21 + about 1.2 s compiling qekf_updates_kernel.attitude_corrections
    "fixes": 17.0,
    "anchor": 13.0,
    "pipeline": 12.0,
    "pdr": 6.0,
    "absfix": 3.0,
}

#: Seconds of simulated driving: enough for every engine to initialise and take GNSS updates
#: (car-magnetometer starts with 40 s static).
DURATION_S = 60.0


def warm_techniques() -> None:
    """Compile the kernels outside the engines (module docstring) on short synthetic inputs."""
    import numpy as np

    from iotnav.techniques.ahrs_eskf import run_ahrs_eskf, run_ahrs_eskf_streaming
    from iotnav.techniques.cascade import run_cascade_imu
    from iotnav.tracker.odometer import gated_increments, velocity_increments

    n, fs_hz = 400, 100.0
    rng = np.random.default_rng(0)
    gyr = rng.normal(0.0, 0.01, (n, 3))  # rad/s, at rest
    acc = np.array([0.0, 0.0, -9.81]) + rng.normal(0.0, 0.02, (n, 3))  # m/s^2, b = NED at rest
    mag = np.array([20.0, 0.0, 45.0]) + rng.normal(0.0, 0.3, (n, 3))  # uT
    for m in (None, mag):
        run_ahrs_eskf(gyr, acc, m, fs_hz)
        run_ahrs_eskf_streaming(gyr[:20], acc[:20], None if m is None else m[:20], fs_hz)
    static = np.arange(n) < n // 2
    run_cascade_imu(acc, gyr, fs_hz, static, 9.81)
    gated_increments(np.cumsum(np.ones(n)), np.zeros(n), np.ones(n), 2.0)
    velocity_increments(np.arange(n, dtype=float), np.zeros(n), np.zeros(n), np.ones(n), np.ones(n), static)


def warm_engines(targets: Sequence[str]) -> dict[str, tuple[float, float]]:
    """Run each target once (engines on a short simulated drive); seconds per target.

    Parameters
    ----------
    targets : sequence of str
        Names of :data:`TARGETS`: engine names of :func:`iotnav.engines.registry.make_engine`,
        or ``techniques``.

    Returns
    -------
    dict
        Target name to (wall, CPU) time of its runs, s.
    """
    from iotnav import sim
    from iotnav.engines.base import iter_samples, run_batch
    from iotnav.engines.registry import make_engine
    from iotnav.io import ingest
    from iotnav.io.log import Log

    out: dict[str, tuple[float, float]] = {}
    with tempfile.TemporaryDirectory(prefix="iotnav-warmup-") as tmp:
        r = sim.build("car-magnetometer", seed=0, overrides={"duration_s": DURATION_S})
        sim.write(r, Path(tmp))
        log = ingest([Path(tmp)])
        for name in targets:
            t0, c0 = time.perf_counter(), time.process_time()
            if name == "techniques":
                warm_techniques()
                out[name] = (time.perf_counter() - t0, time.process_time() - c0)
                continue
            run_batch(make_engine(name), log)
            run_batch(make_engine(name, integrity=False), log)
            eng = make_engine(name)
            for s in itertools.islice(iter_samples(log), 3000):
                eng.step(s)
            if name == "eskf":  # and the smoother's compiled backward pass
                from iotnav.engines.smoother import smooth_output

                sm = make_engine(name, smoothing=True)
                smooth_output(sm, run_batch(sm, log))  # type: ignore[arg-type]
            elif name == "absfix":  # with fixes: the kernel's stops, replays and the step path
                _warm_absfix()
            elif name == "fixes":  # its own compiled RTS smoother and resampling
                fixes = make_engine(name, smoothing=True)
                forward = run_batch(fixes, log)
                fixes.smoothed_output(forward)  # type: ignore[attr-defined]
                fixes.resample(1.0, smoothed=True, forward=forward)  # type: ignore[attr-defined]
            elif name == "qekf":  # without a magnetometer: the non-holonomic fallback
                run_batch(make_engine(name), Log(gnss=log.gnss, imu=log.imu, utc_offset_s=log.utc_offset_s))
                from iotnav.engines.smoother import smooth_output  # and the smoother's corrections

                sq = make_engine(name, smoothing=True)
                smooth_output(sq, run_batch(sq, log))  # type: ignore[arg-type]
            out[name] = (time.perf_counter() - t0, time.process_time() - c0)
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


def split(targets: Sequence[str], jobs: int) -> list[list[str]]:
    """Share ``targets`` over ``jobs`` lists: costliest first, each to the least loaded list.

    Parameters
    ----------
    targets : sequence of str
        Names of :data:`TARGETS`, weighed by :data:`COST_S` (unknown names weigh 1 s).
    jobs : int
        Number of processes (at least 1).

    Returns
    -------
    list of list of str
        Non-empty lists, at most ``jobs``, each in decreasing order of cost.
    """
    order = sorted(targets, key=lambda e: -COST_S.get(e, 1.0))  # stable: ties keep their order
    groups: list[list[str]] = [[] for _ in range(max(1, jobs))]
    load = [0.0] * len(groups)
    for name in order:
        i = load.index(min(load))
        groups[i].append(name)
        load[i] += COST_S.get(name, 1.0)
    return [g for g in groups if g]


def main(argv: Sequence[str] | None = None) -> int:
    """Command line: ``python -m iotnav.warmup [--jobs N] [TARGET ...]``; exit status."""
    ap = argparse.ArgumentParser(prog="python -m iotnav.warmup", description=__doc__.splitlines()[0])
    ap.add_argument(
        "engines", nargs="*", default=list(TARGETS), help="engines or 'techniques' (default: all)"
    )
    ap.add_argument("--jobs", default="1", help="processes, or 'auto' for one per CPU (default 1)")
    args = ap.parse_args(argv)
    unknown = sorted(set(args.engines) - set(TARGETS))
    if unknown:
        ap.error(f"unknown engine(s) {', '.join(unknown)}; expected some of {', '.join(TARGETS)}")
    if args.jobs == "auto":
        jobs = os.cpu_count() or 1
    elif args.jobs.isdigit():
        jobs = int(args.jobs)
    else:
        ap.error(f"--jobs {args.jobs!r}: expected a whole number or 'auto'")
    t0 = time.perf_counter()
    groups = split(args.engines, jobs)
    times: dict[str, tuple[float, float]] = {}
    if len(groups) == 1:
        times = warm_engines(groups[0])
    else:
        with ProcessPoolExecutor(len(groups)) as pool:
            for part in pool.map(warm_engines, groups):
                times.update(part)
    per = ", ".join(f"{k} {w:.0f} s" for k, (w, _) in times.items())
    groups_cpu = " + ".join(f"{sum(times[k][1] for k in g):.0f}" for g in groups)
    print(
        f"iotnav warm-up: kernels compiled or loaded in {time.perf_counter() - t0:.0f} s ({per}); "
        f"CPU s per process {groups_cpu}"
    )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
