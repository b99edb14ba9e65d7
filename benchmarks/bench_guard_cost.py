"""What the do-no-harm guard costs: ``iotnav run`` with and without it, side by side, same run.

Run: ``.venv/bin/python benchmarks/bench_guard_cost.py [--repeats 3] [--engines eskf anchor ...]``;
with ``IOTNAV_WRITE_RESULTS=1`` the markdown is written to ``benchmarks/results/guard_cost.md``.

Input: the real drive ``rtklibexplorer_gnss_imu/drive_0708`` as shipped (``gnss_1934_sf.pos``, 4 Hz
RTK fixes, and ``imu_1934_gpst.csv``, 100 Hz ICM-45686; 549 s, 54,860 IMU samples). Each engine
runs ``iotnav run --engine NAME`` in this process with ``--integrity`` (the default) and
``--no-integrity``, alternately, ``--repeats`` times each after one untimed warm-up of both
(numba kernels loaded). Timed: the engine's run as ``summary.json`` reports it (``runtime_s``:
``run_batch`` and nothing else) and the wall clock of the whole command (ingest, run, writing
every output file). Medians. Also shown: how many output rows the guard replaced and how often it
re-initialised the engine (``engine_summary.integrity``), and the largest horizontal difference
between the two tracks.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import statistics
import tempfile
import time
from pathlib import Path

import numpy as np
import pandas as pd
from typer.testing import CliRunner

from assemble import machine
from iotnav.cli import app
from iotnav.engines.base import C_LAT, C_LON, FLOAT_COLUMNS, SRC_DR, GnssSample, OutputBlock, iter_samples
from iotnav.engines.integrity import FLAG_NEED_FRAME, IntegrityGuard, guard_rows
from iotnav.io import ingest

RESULTS = Path(__file__).parent / "results"
DRIVE = (
    Path(os.environ.get("IOTNAV_DATASETS", "/work/shared/datasets")) / "rtklibexplorer_gnss_imu/drive_0708"
)


def run_once(engine: str, guarded: bool, out: Path) -> tuple[float, float, dict]:  # type: ignore[type-arg]
    """One ``iotnav run``: engine runtime (s), wall clock (s), summary.json."""
    args = ["run", str(DRIVE / "gnss_1934_sf.pos"), str(DRIVE / "imu_1934_gpst.csv")]
    args += ["--engine", engine, "--out", str(out), "--integrity" if guarded else "--no-integrity"]
    t0 = time.perf_counter()
    res = CliRunner().invoke(app, args)
    wall = time.perf_counter() - t0
    if res.exit_code != 0:
        raise RuntimeError(f"iotnav {' '.join(args)} failed:\n{res.output}")
    summary = json.loads((out / "summary.json").read_text())
    return float(summary["runtime_s"]), wall, summary


def guard_alone_s(track: pd.DataFrame) -> float:
    """Time (s) of the guard by itself over an engine's track: ``on_fix`` at each fix and
    :func:`guard_rows` over the rows between fixes, as the guarded block path runs them (its
    decisions are applied to the rows; the engine is not re-run)."""
    log = ingest([DRIVE / "gnss_1934_sf.pos", DRIVE / "imu_1934_gpst.csv"])
    fixes = [s for s in iter_samples(log) if isinstance(s, GnssSample)]
    out = OutputBlock(len(track))
    out.floats[:, : len(track)] = track[list(FLOAT_COLUMNS)].to_numpy(float).T
    out.source[: len(track)] = [out.codes.get(x, SRC_DR) for x in track.source.astype(str)]
    out.n = len(track)
    cuts = np.searchsorted(track.t.to_numpy(float), [f.t for f in fixes], side="left").tolist()
    g = IntegrityGuard()
    code_dr = len(out.names)

    def rows(i0: int, i1: int) -> None:
        k = i0
        while k < i1:
            k, flag, _ = guard_rows(out.floats, out.source, k, i1, g.st, g.prm, code_dr)
            if flag == FLAG_NEED_FRAME:
                g.set_frame(float(out.floats[C_LAT, k]), float(out.floats[C_LON, k]), 0.0)

    rows(0, 1)  # compiled before the clock starts
    g = IntegrityGuard()
    t0 = time.perf_counter()
    i = 0
    for f, c in zip(fixes, cuts, strict=True):
        rows(i, c)
        i = max(i, c)
        g.on_fix(f)
    rows(i, out.n)
    return time.perf_counter() - t0


def _apart_m(a: pd.DataFrame, b: pd.DataFrame) -> float:
    if len(a) != len(b):
        return math.inf
    k = math.radians(1.0) * 6.371e6
    dn = (a.lat.to_numpy() - b.lat.to_numpy()) * k
    de = (a.lon.to_numpy() - b.lon.to_numpy()) * k * math.cos(math.radians(float(a.lat.iloc[0])))
    return float(np.nanmax(np.hypot(dn, de)))


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--engines", nargs="+", default=["eskf", "anchor", "pipeline", "qekf"])
    a = ap.parse_args()
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for eng in a.engines:
            times: dict[bool, list[tuple[float, float]]] = {True: [], False: []}
            summ = {}
            for k in range(a.repeats + 1):
                for guarded in (False, True):
                    out = Path(tmp) / f"{eng}-{guarded}"
                    rt, wall, summ[guarded] = run_once(eng, guarded, out)
                    if k > 0:  # the first round loads the kernels
                        times[guarded].append((rt, wall))
            tracks = {g: pd.read_csv(Path(tmp) / f"{eng}-{g}" / "track.csv") for g in (False, True)}
            integ = summ[True]["engine_summary"].get("integrity", {})
            med = {g: [statistics.median(x[i] for x in times[g]) for i in (0, 1)] for g in (False, True)}
            row = {
                "engine": eng,
                "samples": summ[True]["counts"]["imu_samples_in"],
                "raw_runtime_s": med[False][0],
                "guarded_runtime_s": med[True][0],
                "raw_wall_s": med[False][1],
                "guarded_wall_s": med[True][1],
                "fallback_rows": integ.get("fallback_rows", 0),
                "reinitialised": integ.get("reinitialised", 0),
                "apart_max_m": _apart_m(tracks[False], tracks[True]),
                "guard_alone_s": statistics.median(guard_alone_s(tracks[False]) for _ in range(a.repeats)),
            }
            print(row, flush=True)
            rows.append(row)
    md = [
        "# Cost of the do-no-harm guard (`iotnav run`, guarded by default)",
        "",
        f"Machine: {machine()}. Regenerate: `IOTNAV_WRITE_RESULTS=1 .venv/bin/python "
        f"benchmarks/bench_guard_cost.py --repeats {a.repeats}`.",
        "",
        "Real drive_0708 as shipped (4 Hz RTK fixes, 100 Hz IMU, 549 s). Median of "
        f"{a.repeats} alternating runs of each variant in one process after a warm-up. Engine: "
        "`run_batch` time (summary.json `runtime_s`); command: the whole `iotnav run` (ingest, "
        "run, every output file). Rows replaced and re-initialisations: the guarded run's "
        "`engine_summary.integrity`; apart: largest horizontal distance between the two tracks. "
        "Guard by itself: the guard's fix step and row kernel replayed over the engine-alone track "
        "(median of the same number of repeats), the part of the difference that is the guard's; "
        "the machine is shared with other jobs, so the two columns before it carry their noise.",
        "",
        "| engine | IMU samples | engine alone (s) | guarded (s) | ratio | guard by itself (s) | "
        "command alone (s) | command guarded (s) | rows replaced | re-initialisations | apart (m) |",
        "|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        md.append(
            f"| {r['engine']} | {r['samples']} | {r['raw_runtime_s']:.2f} | {r['guarded_runtime_s']:.2f} | "
            f"{r['guarded_runtime_s'] / r['raw_runtime_s']:.2f} | {r['guard_alone_s']:.2f} | {r['raw_wall_s']:.2f} | "
            f"{r['guarded_wall_s']:.2f} | {r['fallback_rows']} | {r['reinitialised']} | {r['apart_max_m']:.3f} |"
        )
    md.append("")
    text = "\n".join(md)
    print(text)
    if os.environ.get("IOTNAV_WRITE_RESULTS") == "1":
        (RESULTS / "guard_cost.md").write_text(text)


if __name__ == "__main__":
    main()
