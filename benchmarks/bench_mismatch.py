"""Mismatch grid: simulations whose errors the filters do not assume, every engine.

Each cell is ``car-tunnel`` (seed 0, first ``duration`` s, 200 by default: its first tunnel, 40 s) with one departure from
what the engines' defaults model: GNSS error correlation times of 30 s and 600 s; multipath
outliers (120 an hour); a 10 Hz receiver whose epochs are stamped at their arrival 0.2 s after
the fix; a phone-grade IMU (``smartphone`` preset) with 1 % scale factors and 2 ms timing
jitter; a raw gyro with a 3 deg/s turn-on bias per axis. Per engine and cell: output rows
without a position after the first one (``nan``), the largest horizontal error, and that
error over the largest error of holding the last fix (``x hold``; the issue's divergence
target is below 10). The simulator has no g-sensitivity model: not in the grid.

Run: ``.venv/bin/python benchmarks/bench_mismatch.py [duration_s]``; with
``IOTNAV_WRITE_RESULTS=1`` the markdown goes to ``benchmarks/results/mismatch.md``.
"""

from __future__ import annotations

import math
import os
import sys
import time
from pathlib import Path

import numpy as np

from iotnav import sim
from iotnav.engines.base import run_batch
from iotnav.engines.registry import make_engine
from iotnav.eval.metrics import track_errors
from iotnav.eval.outages import gnss_hold_track
from iotnav.io.log import Log

ENGINES = ("pipeline", "anchor", "qekf", "eskf")

CELLS: dict[str, dict[str, object]] = {
    "defaults (reference)": {},
    "GNSS error tau 30 s": {"gnss.tau_h_s": 30.0, "gnss.tau_v_s": 30.0},
    "GNSS error tau 600 s": {"gnss.tau_h_s": 600.0, "gnss.tau_v_s": 600.0},
    "multipath outliers 120/h": {"gnss.outliers_per_hour": 120.0},
    "10 Hz, arrival stamps +0.2 s": {"gnss.rate_hz": 10.0, "gnss.latency_s": 0.2},
    "phone IMU, 1 % scale, 2 ms jitter": {
        "imu.preset": "smartphone",
        "imu.acc_scale_factor_pct": 1.0,
        "imu.gyro_scale_factor_pct": 1.0,
        "imu.timestamp_jitter_ms": 2.0,
    },
    "gyro bias 3 deg/s": {"imu.gyro_turn_on_bias_dps": 3.0},
}


def cell(overrides: dict[str, object], duration: float) -> dict[str, tuple[int, float, float]]:
    """Per engine: NaN rows after the first position, largest error (m), ratio to hold's."""
    res = sim.build("car-tunnel", seed=0, overrides={"duration_s": duration, **overrides})
    log = Log(gnss=res.gnss, imu=res.imu, mag=res.mag)
    t_eval = res.imu["t"].to_numpy(float)
    hold = track_errors(gnss_hold_track(res.gnss, t_eval), res.truth)
    hold_max = float(np.max(hold.h_err))
    out: dict[str, tuple[int, float, float]] = {}
    for name in ENGINES:
        df = run_batch(make_engine(name), log)
        lat = df["lat"].to_numpy(float)
        ok = np.isfinite(lat)
        first = int(np.argmax(ok)) if ok.any() else len(lat)
        n_nan = int((~ok[first:]).sum())
        err = track_errors(df, res.truth)
        e_max = float(np.max(err.h_err)) if err.h_err.size else math.nan
        out[name] = (n_nan, e_max, e_max / hold_max)
    out["hold"] = (0, hold_max, 1.0)
    return out


def main() -> None:
    duration = float(sys.argv[1]) if len(sys.argv) > 1 else 200.0
    t0 = time.perf_counter()
    head = "| cell | " + " | ".join(f"{e} max (m) / x hold / nan" for e in ENGINES) + " | hold max (m) |"
    lines = [
        f"car-tunnel seed 0, first {duration:.0f} s; largest horizontal error (m), its ratio to "
        "holding the last fix, output rows without a position after the first one.",
        "",
        head,
        "|" + "---|" * (len(ENGINES) + 2),
    ]
    worst = 0.0
    for label, ov in CELLS.items():
        r = cell(ov, duration)
        cells = []
        for e in ENGINES:
            n_nan, e_max, ratio = r[e]
            worst = max(worst, ratio)
            flag = " **!**" if (ratio >= 10.0 or n_nan) else ""
            cells.append(f"{e_max:.1f} / {ratio:.2f} / {n_nan}{flag}")
        lines.append(f"| {label} | " + " | ".join(cells) + f" | {r['hold'][1]:.1f} |")
        print(lines[-1], flush=True)
        _write("## Mismatch grid (partial: the run is not finished)\n\n" + "\n".join(lines) + "\n")
    lines += [
        "",
        f"Largest ratio to hold over the grid: **{worst:.2f}** (target < 10; **!** marks a cell over it "
        f"or with positionless rows). Runtime {time.perf_counter() - t0:.0f} s.",
    ]
    text = "## Mismatch grid\n\n" + "\n".join(lines) + "\n"
    print(text)
    _write(text)


def _write(text: str) -> None:
    """``benchmarks/results/mismatch.md`` with ``IOTNAV_WRITE_RESULTS=1``."""
    if os.environ.get("IOTNAV_WRITE_RESULTS") == "1":
        (Path(__file__).parent / "results" / "mismatch.md").write_text(text)


if __name__ == "__main__":
    main()
