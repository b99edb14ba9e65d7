"""eskf's windowed NIS consistency monitor (issue 16, "do no harm"): false alarms and recovery.

Part 1, false alarms: eskf with its defaults (the cases' profile settings) on every real case
of :mod:`iotnav.eval.cases` and on drive_0708 from rest (the outage study's degraded feed),
each with no outage and with the outage study's 15 s and 30 s windows all masked in one run,
and on simulator scenarios (seeds 0-2). Per run: fixes, mean position NIS per dof, fixes
rejected by the gate, gate resets, re-initialisations, and the largest window statistic over
its threshold (the monitor's window replayed on the run's NIS log; above 1 is an alarm).

Part 2, a real run locked out: the drive_0708 cuts with every 30 s outage of the study masked
in one run (not the study's one outage per continuation), the monitor off and on, the largest
error against the RTK after 110 s.

Part 3, recovery: the simulated car-tunnel (200 s, no outage) with the heading turned by 20, 90
and 180 deg at 100 s, and with the configured mount yaw 90 deg off from the start: fixes
rejected and gate resets after the fault, the re-initialisations, the horizontal RMS error of
the last 40 s; the monitor off (the code before it) and on.

Tuning and measurement: the defaults were set before this script from the simulator
(car-tunnel seeds 0-2) and the issue's factor-3 consistency target; the first version, with no
tolerance (``nis_tolerance=1``), fired 19-106 times on the drive_0708 runs (their NIS averages
1.4 per dof), which is why the tolerance exists. Measured on: the drive cuts start100-bias3,
start220-bias1, husky, walk_0827 and the simulator's other scenarios and seeds, which were
not looked at before the defaults were fixed.

An alarm also needs the predicted position off the fixes (mean distance over the window above
``max(10 m, 3 x`` the fixes' RMS sigma``)``): without it the monitor re-initialised eskf three
times on the 200 s drive_0708 segment of ``tests/test_eskf.py`` (a 60 s Gauss-Markov GNSS error
the filter does not model: NIS 12 per dof, 62 % of the fixes rejected, yet 1-4 m from the RTK)
and lost its mount; with it, none, and the recoveries below are unchanged but for the 20 deg
heading fault (20 -> 33 s).

Run: ``.venv/bin/python benchmarks/bench_eskf_nis.py``; with ``IOTNAV_WRITE_RESULTS=1`` the
markdown is written to ``benchmarks/results/eskf_nis.md``.
"""

from __future__ import annotations

import math
import os
import platform
import time
from pathlib import Path
from typing import Any

import numpy as np

from iotnav import sim
from iotnav.engines.base import run_batch
from iotnav.engines.eskf import EskfConfig, EskfEngine
from iotnav.engines.eskf.consistency import NisWindow
from iotnav.eval.cases import CASES, load_case
from iotnav.eval.metrics import track_errors
from iotnav.eval.outages import OutageConfig, rtk_truth
from iotnav.eval.outages_feed import degraded_feed, mask_windows, moving_part, outage_windows
from iotnav.geo import dcm_to_rpy, euler_to_dcm
from iotnav.io.log import Log

DRIVE = (
    Path(os.environ.get("IOTNAV_DATASETS", "/work/shared/datasets")) / "rtklibexplorer_gnss_imu/drive_0708"
)
SCENARIOS = ("car-tunnel", "car-magnetometer", "scooter-laps", "walk-cold-boot", "pedestrian-fixes")


def _worst_ratio(eng: EskfEngine) -> float:
    """Largest window statistic / threshold of the run's position NIS log (up to a re-initialisation)."""
    c = eng.config
    w = NisWindow(c.nis_window_fixes, c.nis_false_alarm, c.nis_cap_probability, c.nis_min_fixes)
    t_re = min((e["t"] for e in eng.events if e["type"] == "reinitialised"), default=math.inf)
    worst = 0.0
    for t, nis, dof, _ok in eng.nis_log.get("gnss_position", []):
        if t > t_re:
            break
        w.add(t, nis / c.nis_tolerance, dof)
        if len(w) >= w.min_fixes:
            worst = max(worst, w._sum / w.threshold(w._dof))
    return worst


def _row(name: str, eng: EskfEngine) -> str:
    log = eng.nis_log.get("gnss_position", [])
    s = eng.summary()
    nis = np.mean([r[1] / r[2] for r in log]) if log else math.nan
    rej = sum(1 for r in log if not r[3])
    return (
        f"| {name} | {len(log)} | {nis:.2f} | {rej} | {s['event_counts'].get('gate_reset', 0)} "
        f"| {s['reinitialisations']} | {_worst_ratio(eng):.2f} |"
    )


def _run(cfg: EskfConfig, log: Log) -> EskfEngine:
    eng = EskfEngine(cfg)
    run_batch(eng, log)
    return eng


def _masked(log: Log, truth: Any, L: float, spacing: float, first: float, speed: float) -> Log:
    if L == 0.0:
        return log
    g = log.gnss
    m0, m1 = moving_part(truth, speed)
    w = outage_windows(m0, m1, [L], spacing, first, g["t"].to_numpy(float))
    return Log(gnss=mask_windows(g, w), imu=log.imu, mag=log.mag)


def false_alarms() -> list[str]:
    md = [
        "| run | fixes | mean NIS / dof | rejected | gate resets | re-initialisations | worst window NIS / threshold |",
        "|---|---|---|---|---|---|---|",
    ]
    from iotnav.cli.outages import load_dataset

    log, prof = load_dataset(DRIVE)
    truth = rtk_truth(log.gnss)
    ocfg = OutageConfig(engines=("eskf",), lengths_s=(15.0, 30.0))
    fed, _ = degraded_feed(log, truth, prof, ocfg)
    for L in (0.0, 15.0, 30.0):
        m = _masked(fed, truth, L, ocfg.spacing_s, ocfg.first_offset_s, ocfg.moving_speed_mps)
        md.append(_row(f"drive_0708-from-rest, outages {L:.0f} s", _run(EskfConfig(**dict(prof.eskf)), m)))
        print(md[-1], flush=True)
    for case in CASES:
        lc = load_case(case)
        oc = lc.config
        for L in (0.0, *oc.lengths_s):
            m = _masked(lc.fed, lc.truth, L, oc.spacing_s, oc.first_offset_s, oc.moving_speed_mps)
            md.append(_row(f"{case}, outages {L:.0f} s", _run(EskfConfig(**dict(lc.profile.eskf)), m)))
            print(md[-1], flush=True)
    for scen in SCENARIOS:
        for seed in (0, 1, 2):
            res = sim.build(scen, seed=seed)
            eng = _run(EskfConfig(), Log(gnss=res.gnss, imu=res.imu, mag=res.mag))
            md.append(_row(f"sim {scen} seed {seed}", eng))
            print(md[-1], flush=True)
    return md


def _part(res: Any, a: float, b: float) -> Log:
    def f(d: Any) -> Any:
        return None if d is None else d[(d.t >= a) & (d.t < b)].reset_index(drop=True)

    return Log(gnss=f(res.gnss), imu=f(res.imu), mag=f(res.mag))


def recovery() -> list[str]:
    md = [
        "| fault | monitor | rejected after | last rejected (s after) | gate resets | re-initialisations (s after; mount released) | RMS last 40 s (m) |",
        "|---|---|---|---|---|---|---|",
    ]
    res = sim.build("car-tunnel", seed=0, overrides={"duration_s": 200.0, "gnss.outages_s": ()})
    c = res.config
    t0 = float(res.imu.t.iloc[0])
    faults: list[tuple[str, float, float]] = [
        (f"heading +{r:.0f} deg at 100 s", r, 0.0) for r in (20, 90, 180)
    ]
    faults.append(("configured mount yaw 90 deg off", 0.0, 90.0))
    for name, rot, mount_off in faults:
        for mon in (False, True):
            kw: dict[str, Any] = {"nis_monitor": mon}
            if mount_off:
                kw["mount_rpy_rad"] = (
                    c.mount_roll_rad,
                    c.mount_pitch_rad,
                    c.mount_yaw_rad + math.radians(mount_off),
                )
            eng = EskfEngine(EskfConfig(**kw))
            tc = t0 + (100.0 if rot else 0.0)
            if rot:
                run_batch(eng, _part(res, -math.inf, tc))
                r, p, y = dcm_to_rpy(eng.nom.C_nb)
                eng.nom.C_nb[:] = euler_to_dcm(r, p, y + math.radians(rot))
            df = run_batch(eng, _part(res, tc, math.inf))
            err = track_errors(df[df.source != "none"], res.truth)
            sel = err.t > err.t[-1] - 40.0
            rej = [r[0] - tc for r in eng.nis_log["gnss_position"] if not r[3] and r[0] >= tc]
            re = [
                f"{e['t'] - tc:.0f}{' (released)' if e['mount_released'] else ''}"
                for e in eng.events
                if e["type"] == "reinitialised"
            ]
            md.append(
                f"| {name} | {'on' if mon else 'off'} | {len(rej)} | {max(rej) if rej else '-'} "
                f"| {eng.summary()['event_counts'].get('gate_reset', 0)} | {', '.join(re) or '-'} "
                f"| {float(np.sqrt(np.mean(err.h_err[sel] ** 2))):.2f} |"
            )
            print(md[-1], flush=True)
    return md


def real_recovery() -> list[str]:
    """The drive cuts with their 30 s outages all masked in one run: monitor off and on, errors vs RTK."""
    md = [
        "| case (30 s outages every 60 s, one run) | monitor | rejected | last rejected (s) | gate resets "
        "| re-initialisations (s) | max error after 110 s, outages included (m) |",
        "|---|---|---|---|---|---|---|",
    ]
    for case in (k for k in CASES if k.startswith("drive_0708")):
        lc = load_case(case)
        oc = lc.config
        t0 = float(lc.truth.t.iloc[0])
        m = _masked(lc.fed, lc.truth, 30.0, oc.spacing_s, oc.first_offset_s, oc.moving_speed_mps)
        for mon in (False, True):
            eng = EskfEngine(EskfConfig(**dict(lc.profile.eskf), nis_monitor=mon))
            df = run_batch(eng, m)
            err = track_errors(df[df.source != "none"], lc.truth[["t", "lat", "lon", "height"]])
            rej = [r[0] - t0 for r in eng.nis_log["gnss_position"] if not r[3]]
            re = [f"{e['t'] - t0:.0f}" for e in eng.events if e["type"] == "reinitialised"]
            md.append(
                f"| {case} | {'on' if mon else 'off'} | {len(rej)} | {max(rej) if rej else 0:.0f} "
                f"| {eng.summary()['event_counts'].get('gate_reset', 0)} | {', '.join(re) or '-'} "
                f"| {float(err.h_err[err.t - t0 > 110.0].max()):.1f} |"
            )
            print(md[-1], flush=True)
    return md


def main() -> None:
    t0 = time.perf_counter()
    c = EskfConfig()
    md = [
        "# eskf windowed NIS consistency monitor (issue 16)",
        "",
        "Regenerate: `.venv/bin/python benchmarks/bench_eskf_nis.py` (`IOTNAV_WRITE_RESULTS=1` writes this file).",
        f"Machine: {platform.machine()}, Python {platform.python_version()}. Monitor: window "
        f"{c.nis_window_fixes} fixes (tested from {c.nis_min_fixes}), false alarm {c.nis_false_alarm:g} per test, "
        f"NIS capped at its {c.nis_cap_probability} quantile, tolerance {c.nis_tolerance:g} x S.",
        "",
        "## Re-initialisations on consistent and real runs",
        "",
        "Every re-initialisation here was looked at: the one on drive_0708-start220-bias1 with 30 s",
        "outages is a true detection (next table: without the monitor that run rejects fixes in",
        "cycles of five to the end of the log). husky and walk_0827 (and the simulated walks) show no",
        "position NIS: eskf never gets a heading there (issue 16's item (c)), so it outputs the last",
        "fix moved on and runs no position update.",
        "",
        *false_alarms(),
        "",
        "## A real run locked out (drive_0708 cuts, one run with every 30 s outage masked)",
        "",
        *real_recovery(),
        "",
        "## Recovery from a wrong state (simulated car-tunnel, seed 0, 200 s, fixes throughout)",
        "",
        *recovery(),
        "",
        f"({time.perf_counter() - t0:.0f} s)",
    ]
    text = "\n".join(md) + "\n"
    print(text)
    if os.environ.get("IOTNAV_WRITE_RESULTS") == "1":
        (Path(__file__).parent / "results" / "eskf_nis.md").write_text(text)


if __name__ == "__main__":
    main()
