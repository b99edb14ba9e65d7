"""Benchmark the Forno et al. 2020 pipeline on the simulator's three dataset scenarios.

* ``scooter-laps`` (dataset B): mount-angle estimates per lap for mounts of 0, 45, 90, 135
  and -90 degrees, straights driven at constant speed (``cruise``) or accelerating then
  braking (``accel-brake``), 5 laps;
* ``static-courtyard`` (dataset A, 90 min): maximum and 95th-percentile horizontal error and
  apparent distance travelled (sum of position steps) of the raw fixes, the pipeline output
  and the best averaging estimator (mean of all fixes since the stop);
* ``walk-cold-boot`` (dataset C): output error before the first PDOP <= 10 fix.

Prints markdown tables; with ``IOTNAV_WRITE_RESULTS=1`` also writes
``benchmarks/results/pipeline.md``.
"""

from __future__ import annotations

import math
import os
import platform
import time
from pathlib import Path

import numpy as np
import pandas as pd

from iotnav import sim
from iotnav.engines import Pipeline, PipelineConfig, run_batch
from iotnav.geo import LocalFrame
from iotnav.io.log import Log
from iotnav.sim.config import TrackMotion
from iotnav.techniques.last_position import StoredPosition

MOUNTS_DEG = (0.0, 45.0, 90.0, 135.0, -90.0)
MODES = ("cruise", "accel-brake")
LAPS = 5
SEED = 1


def _run(res: sim.SimResult, stored: StoredPosition | None = None) -> pd.DataFrame:
    return run_batch(Pipeline(PipelineConfig(), stored=stored), Log(gnss=res.gnss, imu=res.imu, mag=res.mag))


def _dwrap_deg(a: float, b: float) -> float:
    return (math.degrees(a - b) + 180.0) % 360.0 - 180.0


def scooter() -> list[str]:
    """One row per (mode, mount): first estimate time and the error at the end of each lap."""
    m = sim.default_config("scooter-laps").motion
    assert isinstance(m, TrackMotion)
    rows = []
    for mode in MODES:
        for mount in MOUNTS_DEG:
            res = sim.build(
                "scooter-laps",
                seed=SEED,
                overrides={
                    "motion.laps": LAPS,
                    "mount_yaw_rad": math.radians(mount),
                    "motion.straight_mode": mode,
                },
            )
            t0 = time.perf_counter()
            df = _run(res)
            dt = time.perf_counter() - t0
            est = [e for e in df.attrs["events"] if e["type"] == "mount_estimate" and e["accepted"]]
            lap_s = (2.0 * m.straight_m + 2.0 * math.pi * m.radius_m) / (m.mean_speed_kmh / 3.6)
            t_start = m.wait_start_s
            per_lap = []
            for k in range(1, LAPS + 1):
                upto = [e for e in est if e["t"] <= t_start + k * lap_s]
                per_lap.append(
                    f"{_dwrap_deg(upto[-1]['mount_yaw_rad'], math.radians(mount)):+.2f}" if upto else "-"
                )
            worst = max(
                (abs(_dwrap_deg(e["mount_yaw_rad"], math.radians(mount))) for e in est), default=math.nan
            )
            first = f"{est[0]['t']:.0f}" if est else "-"
            final = math.degrees(df.attrs["mount_yaw_rad"])
            rows.append(
                f"| {mode} | {mount:+.0f} | {first} | {' | '.join(per_lap)} | {worst:.2f} | {len(est)} "
                f"| {final:.2f} | {dt:.1f} |"
            )
    lap_cols = " | ".join(f"lap {k}" for k in range(1, LAPS + 1))
    return [
        f"### scooter-laps: mount angle ({LAPS} laps, seed {SEED})",
        "",
        "Error (estimate minus truth, degrees) of the latest accepted estimate at the end of each lap; "
        "worst = largest |error| over all accepted estimates; first = time (s) of the first accepted "
        f"estimate (lap 1 ends at {m.wait_start_s + (2 * m.straight_m + 2 * math.pi * m.radius_m) / (m.mean_speed_kmh / 3.6):.0f} s).",
        "",
        f"| straights | mount deg | first s | {lap_cols} | worst | accepted | final deg | run s |",
        "|---|---:|---:|" + "---:|" * LAPS + "---:|---:|---:|---:|",
        *rows,
        "",
    ]


def _errors(lf: LocalFrame, lat: np.ndarray, lon: np.ndarray, h: np.ndarray) -> np.ndarray:
    return lf.to_ned(lat, lon, h)


def courtyard() -> list[str]:
    """Raw fixes, pipeline output and the mean of all fixes since the stop, 90 min."""
    rows = []
    for seed in (3, 1, 2):
        res = sim.build("static-courtyard", seed=seed)
        t0 = time.perf_counter()
        df = _run(res)
        dt = time.perf_counter() - t0
        out_df = df[df.source != "none"]
        tr = res.truth
        lf = LocalFrame(float(tr.lat.iloc[0]), float(tr.lon.iloc[0]), float(tr.height.iloc[0]))
        g = res.gnss[res.gnss.valid]
        raw = _errors(lf, g.lat_deg.to_numpy(), g.lon_deg.to_numpy(), g.height_m.to_numpy())[:, :2]
        out = _errors(lf, out_df.lat.to_numpy(), out_df.lon.to_numpy(), out_df.height.to_numpy())[:, :2]
        avg = np.cumsum(raw, axis=0) / np.arange(1, len(raw) + 1)[:, None]
        used = g.t.to_numpy() >= float(out_df.t.iloc[0]) - 1e-6
        raw_u = raw[used]
        avg_u = np.cumsum(raw_u, axis=0) / np.arange(1, len(raw_u) + 1)[:, None]
        dist_raw = float(np.hypot(*np.diff(raw, axis=0).T).sum())
        for name, p in (
            ("raw fixes", raw),
            ("pipeline output", out),
            ("mean of fixes since the stop", avg),
            ("mean of fixes since the first used fix", avg_u),
        ):
            r = np.hypot(p[:, 0], p[:, 1])
            d = float(np.hypot(*np.diff(p, axis=0).T).sum())
            rows.append(
                f"| {seed} | {name} | {r.max():.1f} | {np.percentile(r, 95):.1f} | {np.mean(r):.1f} | {d:.1f} "
                f"| {100.0 * d / dist_raw:.2f} | {r.max() < 15.0} |"
            )
        first = next(e for e in df.attrs["events"] if e["type"] == "first_fix")["t"]
        rows.append(f"| {seed} | (first fix used at {first:.0f} s; pipeline {dt:.1f} s) | | | | | | |")
    return [
        "### static-courtyard: 90 min static, courtyard multipath (errors correlated over 300 s)",
        "",
        "Horizontal error about the true point (m); apparent distance = sum of position steps (m) and "
        "its percentage of the raw fixes'; fence = inside a 15 m geofence throughout.",
        "",
        "| seed | estimator | max m | p95 m | mean m | distance m | % of raw | fence |",
        "|---:|---|---:|---:|---:|---:|---:|---|",
        *rows,
        "",
    ]


def walk() -> list[str]:
    """Output before the first acceptable fix with the stored last position."""
    rows = []
    for seed in (4, 5):
        res = sim.build("walk-cold-boot", seed=seed)
        lp = res.last_position
        assert lp is not None
        df = _run(res, StoredPosition(lp["lat"], lp["lon"], lp["height"]))
        ev = df.attrs["events"]
        first = next(e for e in ev if e["type"] == "first_fix")["t"]
        tr = res.truth
        lf = LocalFrame(float(tr.lat.iloc[0]), float(tr.lon.iloc[0]), float(tr.height.iloc[0]))
        before = df[df.t < first]
        p = lf.to_ned(before.lat.to_numpy(), before.lon.to_numpy(), before.height.to_numpy())
        g = res.gnss[res.gnss.valid]
        graw = g[g.t < first]
        q = lf.to_ned(graw.lat_deg.to_numpy(), graw.lon_deg.to_numpy(), graw.height_m.to_numpy())
        n_rej = sum(e["type"] == "fix_rejected" and e.get("reason") == "pdop" for e in ev)
        rows.append(
            f"| {seed} | {float(g.t.iloc[0]):.0f} | {first:.0f} | {n_rej} "
            f"| {np.hypot(q[:, 0], q[:, 1]).max() if len(q) else math.nan:.1f} "
            f"| {np.hypot(p[:, 0], p[:, 1]).max():.1f} |"
        )
    return [
        "### walk-cold-boot: last known position until the first PDOP <= 10 fix",
        "",
        "| seed | first valid fix s | first used fix s | fixes refused (PDOP) | max raw error before, m "
        "| max output error before, m |",
        "|---:|---:|---:|---:|---:|---:|",
        *rows,
        "",
    ]


def main() -> None:
    text = "\n".join(
        [
            "## Forno et al. 2020 pipeline on the simulator",
            "",
            f"Machine: {platform.processor() or platform.machine()}, {os.cpu_count()} cores, "
            f"Python {platform.python_version()}. Default `PipelineConfig()`.",
            "",
            *scooter(),
            *courtyard(),
            *walk(),
        ]
    )
    print(text)
    if os.environ.get("IOTNAV_WRITE_RESULTS") == "1":
        out = Path(__file__).parent / "results" / "pipeline.md"
        out.parent.mkdir(parents=True, exist_ok=True)
        out.write_text(text)


if __name__ == "__main__":
    main()
