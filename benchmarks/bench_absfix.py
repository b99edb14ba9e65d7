"""absfix engine (Dabove et al. 2016): fix-interval tables in the paper's layout.

Prints markdown; with ``IOTNAV_WRITE_RESULTS=1`` also writes ``benchmarks/results/absfix.md``.
``--before SRC`` adds the speed of another checkout's engine (its ``src`` folder, e.g. main's
before the compiled kernel) beside this one's; ``--speed-only`` skips the error tables.

Scenario ``pedestrian-fixes`` (2 laps of a 30 m x 20 m courtyard loop, hand-held, 100 Hz IMU),
fixes every 1, 2 and 5 s. Errors are |North| and |East| of every output row after the first
fix (real-time track unless stated), pooled over the runs (seeds 0..RUNS-1).
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from pathlib import Path

import pandas as pd

from iotnav.eval.fix_interval import PAPER_TABLE_4, FixIntervalConfig, format_tables, study

RUNS = 3
TS = {"sigma_pos_m": 0.002, "sigma_att_rad": 0.001}  # total station + precise attitude
IRB = {"sigma_pos_m": 0.30, "sigma_att_rad": 0.0175}  # image-based: ~30 cm, 1 degree


def _paper() -> str:
    out = [
        "| axis | 1 s mean | 67 % | 95 % | 2 s mean | 67 % | 95 % | 5 s mean | 67 % | 95 % |",
        "|---" * 10 + "|",
    ]
    for axis in ("N", "E"):
        cells = " | ".join(f"{v:.2f}" for t in (1.0, 2.0, 5.0) for v in PAPER_TABLE_4[t][axis])
        out.append(f"| {axis} | {cells} |")
    return "\n".join(out)


def _hline(label: str, df: pd.DataFrame, mode: str = "fixes") -> str:
    sub = df[df["mode"] == mode].set_index("interval_s")
    cells = " | ".join(
        f"{sub.loc[t, 'n_mean']:.3f} / {sub.loc[t, 'e_mean']:.3f} / {sub.loc[t, 'h_mean']:.3f}"
        for t in (1.0, 2.0, 5.0)
    )
    return f"| {label} | {cells} |"


#: Speed run: ``pedestrian-fixes`` with this many laps (about 11 minutes of 100 Hz IMU),
#: image-based fixes every second arriving ``SPEED_LATENCY_S`` late (each fix re-propagates
#: that much of the buffer).
SPEED_LAPS = 6
SPEED_LATENCY_S = 0.5

_SPEED_CODE = """
import json, sys, time
from iotnav import sim
from iotnav.engines.absfix import AbsfixEngine, run_with_fixes
from iotnav.io.log import Log
laps, latency = int(sys.argv[1]), float(sys.argv[2])
r = sim.build("pedestrian-fixes", seed=0, overrides={"motion.laps": laps, "fixes.latency_s": latency})
log = Log(imu=r.imu)
run_with_fixes(AbsfixEngine(), log, r.fixes.iloc[:20])  # compile or load the kernels
res = {"samples": len(r.imu), "fixes": len(r.fixes)}
for revised in (False, True):
    best = float("inf")
    for _ in range(2):
        t0 = time.process_time()
        run_with_fixes(AbsfixEngine(), log, r.fixes, revised=revised)
        best = min(best, time.process_time() - t0)
    res["revised" if revised else "realtime"] = best
print(json.dumps(res))
"""


def _speed_of(src: Path) -> dict[str, float]:
    """CPU seconds of :func:`run_with_fixes` with the engine of ``src`` (a fresh process)."""
    env = {**os.environ, "PYTHONPATH": str(src)}
    cmd = [sys.executable, "-c", _SPEED_CODE, str(SPEED_LAPS), str(SPEED_LATENCY_S)]
    res = subprocess.run(cmd, env=env, capture_output=True, text=True, check=True)
    return dict(json.loads(res.stdout.strip().splitlines()[-1]))


def speed(before: Path | None, label: str = "") -> str:
    """Markdown: IMU samples per CPU-second of the batch run, this checkout (and ``before``)."""
    here = Path(__file__).resolve().parents[1] / "src"
    runs = [("this checkout (compiled kernel)", _speed_of(here))]
    if before is not None:
        runs.insert(0, (f"before: {label or before}", _speed_of(before)))
    n = runs[-1][1]["samples"]
    out = [
        "## Speed: `run_with_fixes`, IMU samples per CPU-second",
        "",
        f"`pedestrian-fixes`, {SPEED_LAPS} laps, seed 0: {n:.0f} IMU samples at 100 Hz, a fix every "
        f"second arriving {SPEED_LATENCY_S:g} s late (each re-propagates {SPEED_LATENCY_S:g} s of the "
        "buffer); best of 2 runs, CPU time (`time.process_time`), kernels compiled beforehand, "
        "measured on a shared machine.",
        "",
        "| engine | real-time track | revised track |",
        "|---|---|---|",
    ]
    for name, r in runs:
        out.append(f"| {name} | {r['samples'] / r['realtime']:,.0f} | {r['samples'] / r['revised']:,.0f} |")
    return "\n".join(out) + "\n"


def main(before: Path | None = None, speed_only: bool = False, label: str = "") -> str:
    t0 = time.time()
    out = ["# absfix: INS reset by absolute fixes (Dabove et al. 2016)", ""]
    if speed_only:
        return "\n".join([*out, speed(before, label)])
    out.append(__doc__.split("\n\n", 2)[2].strip() if __doc__ else "")
    out += [
        "",
        "Modes: `none` (bias and drift zero), `fixes` (decoupled estimates from the fixes: the paper's "
        "method), `reference` (true turn-on biases from the simulator, standing in for the paper's "
        "calibration against the Microstrain).",
        "",
    ]
    ms = study(FixIntervalConfig(runs=RUNS, preset="3dm-gx3-35", **TS))
    sp = study(FixIntervalConfig(runs=RUNS, preset="smartphone", **TS))
    irb = study(FixIntervalConfig(runs=RUNS, preset="3dm-gx3-35", latency_s=0.0, **IRB))
    out += ["## Summary: mean |N| / |E| / planimetric error, m (mode `fixes`)", ""]
    out += ["| setting | 1 s | 2 s | 5 s |", "|---|---|---|---|"]
    out.append("| **target** (paper Table 4, N and E mean) | 0.14 | 0.42 | 2.6 |")
    out.append(_hline("Microstrain class, total-station fixes (0.002 m, 0.001 rad)", ms))
    out.append(_hline("smartphone class, total-station fixes", sp))
    out.append(_hline("Microstrain class, image-based fixes (0.30 m, 1 deg)", irb))
    for lat in (0.5, 1.0, 2.0):
        lt = study(FixIntervalConfig(runs=RUNS, preset="3dm-gx3-35", latency_s=lat, modes=("fixes",), **IRB))
        out.append(_hline(f"image-based, latency {lat:g} s, real-time track", lt))
        lr = study(
            FixIntervalConfig(
                runs=RUNS, preset="3dm-gx3-35", latency_s=lat, modes=("fixes",), revised=True, **IRB
            )
        )
        out.append(_hline(f"image-based, latency {lat:g} s, revised (compensated) track", lr))
    for lat in (0.5, 1.0, 2.0):
        lt = study(FixIntervalConfig(runs=RUNS, preset="3dm-gx3-35", latency_s=lat, modes=("fixes",), **TS))
        out.append(_hline(f"total station, latency {lat:g} s, real-time track", lt))
    out += ["", "## Paper, Table 4 (drift estimation from images), m", "", _paper(), ""]
    out += ["## Microstrain class (3dm-gx3-35), total-station fixes", "", format_tables(ms)]
    out += ["## Smartphone class (BMI160-like), total-station fixes", "", format_tables(sp)]
    out += ["## Microstrain class, image-based fixes (0.30 m, 1 deg), no latency", "", format_tables(irb)]
    out += ["## Wavelet denoising (db4 level 7, whole log), mode `fixes`, mean planimetric error, m", ""]
    out += ["| preset | fixes | denoise | 1 s | 2 s | 5 s |", "|---|---|---|---|---|---|"]
    for preset in ("3dm-gx3-35", "smartphone"):
        for name, fx in (("total station", TS), ("image-based", IRB)):
            for den in ("off", "batch"):
                df = study(FixIntervalConfig(runs=RUNS, preset=preset, denoise=den, modes=("fixes",), **fx))
                sub = df.set_index("interval_s")
                cells = " | ".join(f"{sub.loc[t, 'h_mean']:.3f}" for t in (1.0, 2.0, 5.0))
                out.append(f"| {preset} | {name} | {den} | {cells} |")
    out += ["", speed(before, label)]
    out += ["", f"runtime {time.time() - t0:.0f} s", ""]
    return "\n".join(out)


if __name__ == "__main__":
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0] if __doc__ else None)
    ap.add_argument("--before", type=Path, help="src folder of another checkout to time beside this one")
    ap.add_argument("--before-label", default="", help="name of --before in the table")
    ap.add_argument("--speed-only", action="store_true", help="only the speed table")
    args = ap.parse_args()
    text = main(args.before, args.speed_only, args.before_label)
    print(text)
    if os.environ.get("IOTNAV_WRITE_RESULTS") == "1":
        p = Path(__file__).parent / "results" / "absfix.md"
        p.write_text(text)
        print(f"written {p}")
