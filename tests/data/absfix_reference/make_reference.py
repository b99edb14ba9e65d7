"""Regenerate the stored absfix reference runs (``absfix_reference.npz``) of ``tests/test_absfix.py``.

Made with main's per-sample Python engine (commit 23c36cc, before the compiled kernel of
issue 21) and kept so that the compiled engine can be checked against the behaviour it
replaced. Re-running this script with a later engine overwrites the reference with that
engine's own output (which then proves nothing): do it only after a deliberate change of the
engine's numerics, and say so in the commit.

Each case stores its input (the IMU table, specific force and rate rounded to float32 so the
file stays small, and the fixes table), the configuration and what
:func:`iotnav.engines.absfix.run_with_fixes` produced: every 8th output row of the real-time
and of the revised track (float columns of :data:`iotnav.engines.base.FLOAT_COLUMNS` and the
source code), the final bias and drift, the counts and the event types.

Usage (from a checkout of the engine to record)::

    PYTHONPATH=src python tests/data/absfix_reference/make_reference.py
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from iotnav import sim
from iotnav.engines.absfix import AbsfixConfig, AbsfixEngine, run_with_fixes
from iotnav.engines.base import FLOAT_COLUMNS, SOURCES
from iotnav.io.log import Log

OUT = Path(__file__).resolve().parent / "absfix_reference.npz"
IMU_COLS = ("acc_x", "acc_y", "acc_z", "gyro_x", "gyro_y", "gyro_z")
BASE = {"motion.laps": 1, "motion.wait_start_s": 5.0, "motion.wait_end_s": 2.0, "duration_s": 20.0}


def _inputs(seed: int, overrides: dict[str, Any]) -> tuple[pd.DataFrame, pd.DataFrame]:
    r = sim.build("pedestrian-fixes", seed=seed, overrides={**BASE, **overrides})
    imu = r.imu[["t", *IMU_COLS]].copy()
    for c in IMU_COLS:
        imu[c] = imu[c].to_numpy(float).astype(np.float32).astype(float)
    return imu.reset_index(drop=True), r.fixes.reset_index(drop=True)


def cases() -> dict[str, tuple[pd.DataFrame, pd.DataFrame, dict[str, Any]]]:
    """Name -> (IMU table, fixes table, AbsfixConfig keywords)."""
    out: dict[str, tuple[pd.DataFrame, pd.DataFrame, dict[str, Any]]] = {}
    # late, out-of-order geodetic fixes with attitude; an IMU gap; one fix too late for the buffer
    imu, fx = _inputs(4, {"fixes.latency_s": 1.0})
    imu = imu[(imu["t"] < 9.0) | (imu["t"] > 9.7)].reset_index(drop=True)
    ta = fx["t_arrival"].to_numpy().copy()
    ta[0:-1:2], ta[1::2] = ta[1::2] + 0.0, ta[0:-1:2] + 0.3
    ta = np.maximum(ta, fx["t_valid"].to_numpy())
    ta[7] = fx["t_valid"].iloc[7] + 3.0
    out["late_shuffled"] = (imu, fx.assign(t_arrival=ta), {})
    # position-only fixes in NED (no origin): alignment, rejections before it, known drift
    imu, fx = _inputs(7, {"fixes.latency_s": 0.0})
    yaw0 = float(fx["yaw"].iloc[0])
    ned = pd.DataFrame(
        {
            "t_valid": fx["t_valid"],
            "t_arrival": fx["t_arrival"],
            "north_m": (fx["lat"] - fx["lat"].iloc[0]) * 111_000.0,
            "east_m": (fx["lon"] - fx["lon"].iloc[0]) * 78_000.0,
            "down_m": fx["height"].iloc[0] - fx["height"],
        }
    )
    cfg = {"bias_mode": "fixes", "drift_mode": "none", "initial_yaw_rad": yaw0, "align_s": 3.0}
    out["ned_position_only"] = (imu, ned, cfg)
    # reference bias and drift, more fixes in the windows, fixes valid ahead of the IMU (pending)
    imu, fx = _inputs(2, {"fixes.latency_s": 0.5, "fixes.interval_s": 2.0})
    early = fx.assign(t_arrival=fx["t_valid"] - 0.35)
    cfg = {
        "bias_mode": "reference",
        "drift_mode": "fixes",
        "drift_window_fixes": 3,
        "reference_acc_bias_mps2": (0.01, -0.02, 0.03),
        "attitude_reset": False,
    }
    out["pending_reference"] = (imu, early, cfg)
    cfg2 = {"bias_window_fixes": 4, "drift_window_fixes": 3}
    out["windows_late"] = (imu, fx, cfg2)
    return out


def _track(df: pd.DataFrame) -> tuple[np.ndarray, np.ndarray]:
    floats = df[list(FLOAT_COLUMNS)].to_numpy(float)[::8]
    src = np.array([SOURCES.index(s) for s in df["source"].astype(str)], dtype=np.int8)[::8]
    return floats, src


def main() -> None:
    arrays: dict[str, np.ndarray] = {}
    meta: dict[str, Any] = {}
    seen: dict[str, pd.DataFrame] = {}
    for name, (imu, fx, cfg) in cases().items():
        same = next((k for k, v in seen.items() if v is imu), None)
        if same is None:
            seen[name] = imu
            arrays[f"{name}/imu_t"] = imu["t"].to_numpy(float)
            arrays[f"{name}/imu_v"] = imu[list(IMU_COLS)].to_numpy(float).astype(np.float32)
        arrays[f"{name}/fixes"] = fx.to_numpy(float)
        log = Log(imu=imu)
        for revised in (False, True):
            eng = AbsfixEngine(AbsfixConfig(**cfg))
            df = run_with_fixes(eng, log, fx, revised=revised)
            f, s = _track(df)
            key = f"{name}/{'revised' if revised else 'realtime'}"
            arrays[f"{key}/floats"] = f
            arrays[f"{key}/source"] = s
            arrays[f"{key}/bias"] = np.array(eng.x[15:21])
            meta[key] = {
                "rows": len(df),
                "counts": eng.summary()["counts"],
                "events": [e["type"] for e in eng.events],
            }
        meta[name] = {
            "imu": same or name,
            "fix_columns": list(fx.columns),
            "config": {k: v for k, v in cfg.items()},
        }
    arrays["meta"] = np.array(json.dumps(meta))
    np.savez_compressed(OUT, **arrays)
    print(f"written {OUT} ({OUT.stat().st_size} bytes)")


if __name__ == "__main__":
    main()
