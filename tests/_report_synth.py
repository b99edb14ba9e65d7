"""A hand-built run directory with known errors, for the report tests.

Truth: static at the origin for 20 s, then East at 5 m/s to t = 100 s (10 Hz). Fused track:
truth + (3 m North, 4 m East), so every horizontal error is exactly 5 m. Raw fixes (1 Hz):
truth + ``k % 4`` m North at t = k, none in 31..39 s (one outage, 30 -> 40 s). Events: a
stored position 10 m South, three rejected high-PDOP fixes (one with a hostile reason
string), first fix at 3 s, static 0-20 s, mount estimates, one NIS rejection.
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pandas as pd

from iotnav.geo import LocalFrame

FRAME = LocalFrame(45.0, 7.6, 300.0)
OFFSET_N, OFFSET_E = 3.0, 4.0
GAP = (30.0, 40.0)
HOSTILE = "<script>alert(1)</script>"


def truth_ne(t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """True North/East (m) at times ``t``."""
    return np.zeros_like(t), np.where(t < 20.0, 0.0, 5.0 * (t - 20.0))


def gnss_times() -> np.ndarray:
    """Times of the raw fixes (1 Hz, gap 31..39 s)."""
    k = np.arange(0, 101, dtype=float)
    return k[(k <= GAP[0]) | (k >= GAP[1])]


def gnss_north_offsets() -> np.ndarray:
    """North error of each raw fix, m (``k % 4``)."""
    return gnss_times() % 4.0


def write_synthetic_run(root: Path, *, with_events: bool = True) -> tuple[Path, Path]:
    """Write ``root/run`` and ``root/sim/truth.csv``; return (run dir, truth path)."""
    run, sim = root / "run", root / "sim"
    run.mkdir(parents=True, exist_ok=True)
    sim.mkdir(parents=True, exist_ok=True)
    t = np.round(np.arange(0, 1001) * 0.1, 6)
    n, e = truth_ne(t)
    lat, lon, h = FRAME.from_ned(np.column_stack([n, e, np.zeros_like(t)]))
    moving = t >= 20.0
    yaw = np.where(moving, math.pi / 2, 0.0)
    pd.DataFrame(
        {
            "t": t,
            "lat": lat,
            "lon": lon,
            "height": h,
            "vn": 0.0,
            "ve": np.where(moving, 5.0, 0.0),
            "vd": 0.0,
            "roll": 0.0,
            "pitch": 0.0,
            "yaw": yaw,
        }
    ).to_csv(sim / "truth.csv", index=False, float_format="%.12g")
    (sim / "scenario.json").write_text(json.dumps({"mount_yaw_rad": 0.5}))

    lat_o, lon_o, h_o = FRAME.from_ned(np.column_stack([n + OFFSET_N, e + OFFSET_E, np.zeros_like(t)]))
    pd.DataFrame(
        {
            "t": t,
            "lat": lat_o,
            "lon": lon_o,
            "height": h_o,
            "north": n + OFFSET_N,
            "east": e + OFFSET_E,
            "down": 0.0,
            "vn": 0.0,
            "ve": np.where(moving, 5.0, 0.0),
            "vd": 0.0,
            "roll": 0.01,
            "pitch": -0.01,
            "yaw": yaw,
            "static": ~moving if with_events else np.zeros_like(moving),
            "std_north": 1.0,
            "std_east": 1.5,
            "source": np.where(moving, "fix", "lowpass"),
        }
    ).to_csv(run / "track.csv", index=False, float_format="%.12g")

    tg = gnss_times()
    ng, eg = truth_ne(tg)
    lat_g, lon_g, h_g = FRAME.from_ned(np.column_stack([ng + gnss_north_offsets(), eg, np.zeros_like(tg)]))
    pdop = np.where(tg < 3.0, 15.0, 2.0)
    pd.DataFrame(
        {
            "t": tg,
            "utc": tg + 1.6e9,
            "lat_deg": lat_g,
            "lon_deg": lon_g,
            "height_m": h_g,
            "quality": 1,
            "num_sv": 9,
            "pdop": pdop,
            "hdop": pdop / 2,
            "speed_mps": np.where(tg >= 20.0, 5.0, 0.0),
            "course_rad": math.pi / 2,
            "course_valid": tg >= 20.0,
            "valid": True,
            "source": "sim",
        }
    ).to_csv(run / "gnss.csv", index=False, float_format="%.12g")

    s_lat, s_lon, _ = FRAME.from_ned(np.array([-10.0, 0.0, 0.0]))
    events = [
        {
            "type": "boot",
            "t": None,
            "decision": "stored_position",
            "lat_deg": float(s_lat),
            "lon_deg": float(s_lon),
        },
        {"type": "static_start", "t": 0.0},
        {"type": "fix_rejected", "t": 0.0, "reason": "pdop", "pdop": 15.0},
        {"type": "fix_rejected", "t": 1.0, "reason": "pdop", "pdop": 15.0},
        {"type": "fix_rejected", "t": 2.0, "reason": HOSTILE, "pdop": 15.0},
        {"type": "first_fix", "t": 3.0, "pdop": 2.0, "num_sv": 9},
        {"type": "static_end", "t": 20.0},
        {
            "type": "mount_estimate",
            "t": 25.0,
            "accepted": True,
            "mount_yaw_rad": 0.4,
            "candidate_rad": 0.4,
            "std_rad": 0.1,
        },
        {
            "type": "mount_estimate",
            "t": 28.0,
            "accepted": False,
            "mount_yaw_rad": 0.4,
            "candidate_rad": 0.9,
            "std_rad": 0.3,
        },
        {
            "type": "mount_estimate",
            "t": 45.0,
            "accepted": True,
            "mount_yaw_rad": 0.5,
            "candidate_rad": 0.5,
            "std_rad": 0.05,
        },
        {"type": "fix_rejected", "t": 60.0, "reason": "nis", "nis": 31.5},
    ]
    (run / "events.json").write_text(json.dumps(events if with_events else []))
    summary = {
        "engine": "synthetic",
        "mount_yaw_rad": 0.5 if with_events else None,
        "counts": {"output_rows": len(t), "gnss_epochs_in": len(tg), "imu_samples_in": len(t)},
        "rates_hz": {"output": 10.0, "gnss": 1.0, "imu": 10.0},
        "runtime_s": 0.1,
        "engine_summary": {
            "config": {"last_position": {"max_pdop": 10.0}, "fusion": {"uere_m": 3.0}},
            "gyro_bias_rad_s": [0.001, -0.002, 0.003],
            "acc_bias_mps2": [0.01, 0.02, -0.03],
        },
    }
    (run / "summary.json").write_text(json.dumps(summary))
    return run, sim / "truth.csv"
