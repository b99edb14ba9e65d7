"""Benchmark the tracker's vocabulary: raw fixes, Traccar's rules and iotnav side by side.

Prints a markdown section; with ``IOTNAV_WRITE_RESULTS=1`` also writes
``benchmarks/results/tracker.md``. Run: ``python benchmarks/bench_tracker.py``;
``--seed 0`` / ``--seed 2``: the fleet days the engine and the vocabulary were tuned on
(printed only; the results are seed 1).

Columns:

* **raw fixes**: every valid fix, a plain odometer (the apparent path), each fix tested
  against the fence;
* **Traccar defaults**: :func:`iotnav.eval.traccar.traccar_rules` with the documented
  defaults (all filters off, motion above 0.01 knot, trips 300 s / 500 m, stops 300 s);
* **Traccar tuned**: what a user does on each scenario: ``filter.enable``, ``invalid``,
  ``zero``, ``duplicate``, ``maxSpeed`` 100 kn, then the smallest ``filter.distance`` of
  5-200 m that holds the odometer's growth over the truth's parked periods to 1 % of the raw
  fixes' apparent path there, then the smallest ``event.motion.speedThreshold`` of 0.01-10 kn
  that leaves no trip outside the truth's trips; on the driving days also the thresholds
  tuned on the parked day (what they do to real slow movement);
* **iotnav**: the vocabulary (:func:`iotnav.tracker.describe`) of three tracks: the raw fixes
  as a track (:func:`iotnav.tracker.track_from_fixes`, no engine; odometer of gated chords,
  ``TrackerConfig(odometer="chords")``: the raw Doppler speed is noisy), the ``fixes`` engine's
  forward (live) output and its RTS-smoothed output (:mod:`iotnav.engines.fixes`, ``car``
  platform, defaults); on drive_0708 also the ``pipeline`` engine with the IMU (GNSS thinned
  to 1 Hz) under the same vocabulary.

The issue's targets (issue 17) are checked at the end against the ``fixes`` engine's columns.

Scenarios: the seeded fleet days of :mod:`iotnav.sim.fleet_days`; the gpsd corpus' static
captures (no truth: the fence is centred on the median fix, the p95 is about it); drive_0708
thinned to 1 Hz (truth: the 4 Hz RTK solution, :func:`iotnav.eval.outages.rtk_truth`).
"""

from __future__ import annotations

import itertools
import math
import os
import time
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from iotnav.engines.base import run_batch
from iotnav.engines.fixes import FixesConfig, FixesEngine, FixesKFConfig
from iotnav.eval import tracker_metrics as M
from iotnav.eval.traccar import TraccarConfig, TraccarFilter, TraccarResult, traccar_rules
from iotnav.geo import LocalFrame
from iotnav.io import ingest
from iotnav.io.log import Log
from iotnav.sim.fleet_days import FLEET_DAYS, fleet_day
from iotnav.tracker import TrackerConfig, describe, track_from_fixes

DATA = Path("/work/shared/datasets")
GPSD = DATA / "gpsd_nmea_corpus"
GPSD_STATIC = (
    "ublox-zed-f9p_hpg1.11.log",
    "nmea-rtk.log",
    "telit-he910.log",
    "quectel-l76k-dual.log",
    "sirfstarv-nmea.log",
    "skytraq-dgps.log",
    "ublox-8.log",
    "ublox-neo-m9n-nmea.log",
)
FENCE_M = 15.0
FWD = "iotnav `fixes` engine, forward"
SMOOTHED = "iotnav `fixes` engine, smoothed"
RAW_VOCAB = "iotnav (vocabulary on raw fixes)"
DIST_GRID = (0, 5, 10, 20, 30, 50, 75, 100, 150, 200)
SPEED_GRID = (0.01, 0.5, 1, 2, 3, 5, 10)


def _valid(g: pd.DataFrame) -> pd.DataFrame:
    ok = g["valid"].to_numpy(bool) & np.isfinite(g["lat_deg"].to_numpy(float))
    return g.loc[ok].reset_index(drop=True)


PARKING_S = 300.0  # report.trip.minimalParkingDuration: a shorter halt is part of a trip


def _parked_mask(t: np.ndarray, trips: list[tuple[float, float]]) -> np.ndarray:
    """Rows outside the truth's trips in periods of at least ``PARKING_S`` (all rows without a trip)."""
    if not trips:
        return np.ones(t.size, dtype=bool)
    bounds = [(-math.inf, -math.inf), *sorted(trips), (math.inf, math.inf)]
    m = np.zeros(t.size, dtype=bool)
    for (_, a), (b, _) in itertools.pairwise(bounds):
        lo = a if math.isfinite(a) else (t[0] if t.size else 0.0)
        hi = b if math.isfinite(b) else (t[-1] if t.size else 0.0)
        if hi - lo >= PARKING_S:
            m |= (t > a) & (t < b)
    return m


def _growth(t: np.ndarray, odo: np.ndarray, parked: np.ndarray) -> float:
    """Odometer growth between successive parked rows, m."""
    both = parked[1:] & parked[:-1]
    return float(np.diff(odo)[both].sum())


def _raw_parked_path(g: pd.DataFrame, parked: np.ndarray) -> float:
    lat, lon = g["lat_deg"].to_numpy(float), g["lon_deg"].to_numpy(float)
    tot = 0.0
    idx = np.flatnonzero(parked)
    if idx.size < 2:
        return 0.0
    for run in np.split(idx, np.flatnonzero(np.diff(idx) > 1) + 1):
        tot += M.apparent_path_m(lat[run], lon[run])
    return tot


def tune_traccar(g: pd.DataFrame, truth_trips: list[tuple[float, float]]) -> TraccarConfig:
    """The user's tuning (module docstring)."""
    t = g["t"].to_numpy(float)
    parked_path = _raw_parked_path(g, _parked_mask(t, truth_trips))
    base = TraccarConfig(
        filter=TraccarFilter(enable=True, invalid=True, zero=True, duplicate=True, max_speed_kn=100)
    )
    cfg = base
    for d in DIST_GRID:
        cfg = replace(base, filter=replace(base.filter, distance_m=float(d)))
        r = traccar_rules(g, cfg)
        tp = r.positions["t"].to_numpy(float)
        grow = _growth(tp, r.positions["total_distance_m"].to_numpy(float), _parked_mask(tp, truth_trips))
        if M.growth_pct(grow, parked_path) <= 1.0 or parked_path == 0:
            break
    for v in SPEED_GRID:
        c2 = replace(cfg, speed_threshold_kn=float(v))
        if M.false_trips(traccar_rules(g, c2).trips, truth_trips) == 0:
            return c2
    return replace(cfg, speed_threshold_kn=SPEED_GRID[-1])


def evaluate(
    g: pd.DataFrame,
    truth: pd.DataFrame | None,
    truth_trips: list[tuple[float, float]],
    true_distance: float,
    center: tuple[float, float],
    extra: dict[str, pd.DataFrame] | None = None,
    parked_tuning: TraccarConfig | None = None,
    exits_out: list[str] | None = None,
) -> tuple[dict[str, dict[str, Any]], TraccarConfig]:
    """Metrics per column for one scenario (``exits_out``: append :func:`exit_rows` of the engine)."""
    g = _valid(g)
    t = g["t"].to_numpy(float)
    lat, lon = g["lat_deg"].to_numpy(float), g["lon_deg"].to_numpy(float)
    parked = _parked_mask(t, truth_trips)
    parked_path = _raw_parked_path(g, parked)
    ref = truth if truth is not None else pd.DataFrame({"t": t, "lat": center[0], "lon": center[1]})
    out: dict[str, dict[str, Any]] = {}
    raw_inc = np.concatenate(
        [[0.0], [M.apparent_path_m(lat[i : i + 2], lon[i : i + 2]) for i in range(t.size - 1)]]
    )
    out["raw fixes"] = {
        "parked_growth_pct": M.growth_pct(_growth(t, np.cumsum(raw_inc), parked), parked_path),
        "false_trips": math.nan,
        "fence_exits": M.fence_exits(lat, lon, center, FENCE_M),
        "distance_err_pct": M.distance_error_pct(float(raw_inc[~parked].sum()), true_distance),
        "start_end_s": (math.nan, math.nan),
        "p95_m": M.h_err_p95(pd.DataFrame({"t": t, "lat": lat, "lon": lon}), ref),
    }
    tuned = tune_traccar(g, truth_trips)
    configs = [("Traccar defaults", TraccarConfig()), ("Traccar tuned", tuned)]
    if parked_tuning is not None:
        configs.append(("Traccar tuned on the parked day", parked_tuning))
    for name, cfg in configs:
        r: TraccarResult = traccar_rules(g, cfg)
        p = r.positions
        tp = p["t"].to_numpy(float)
        odo = p["total_distance_m"].to_numpy(float)
        held = r.track(t)
        trips_d = float(r.trips.loc[r.trips["kind"] == "trip", "distance_m"].sum())
        timing = M.trip_timing(r.trips, truth_trips)
        out[name] = {
            "parked_growth_pct": M.growth_pct(_growth(tp, odo, _parked_mask(tp, truth_trips)), parked_path),
            "false_trips": M.false_trips(r.trips, truth_trips),
            "fence_exits": M.fence_exits(p["lat"].to_numpy(float), p["lon"].to_numpy(float), center, FENCE_M),
            "distance_err_pct": M.distance_error_pct(trips_d, true_distance),
            "start_end_s": timing[0] if timing else (math.nan, math.nan),
            "p95_m": M.h_err_p95(held, ref),
        }
    eng = FixesEngine(FixesConfig(kf=FixesKFConfig(smoothing=True)))
    fwd = run_batch(eng, Log(gnss=g))
    smoothed = eng.smoothed_output(fwd)
    if exits_out is not None:
        exits_out.extend(exit_rows(g, {"forward": fwd, "smoothed": smoothed}, center))
    tracks = {
        RAW_VOCAB: track_from_fixes(g),
        FWD: fwd,
        SMOOTHED: smoothed,
        **(extra or {}),
    }
    zones = _zones(center)
    for name, track in tracks.items():
        # raw fixes: chords (a receiver's Doppler speed carries the multipath error's derivative)
        res = describe(track, zones, TrackerConfig(odometer="chords") if name == RAW_VOCAB else None)
        tr_t = track["t"].to_numpy(float)
        ot = res.odometer["t"].to_numpy(float)
        k = np.searchsorted(ot, t, side="right") - 1
        odo_rows = np.where(k >= 0, res.odometer["odometer_m"].to_numpy(float)[np.maximum(k, 0)], 0.0)
        timing = M.trip_timing(res.trips, truth_trips)
        out[name] = {
            "parked_growth_pct": M.growth_pct(_growth(t, odo_rows, parked), parked_path),
            "false_trips": M.false_trips(res.trips, truth_trips),
            "fence_exits": sum(e["type"] == "geofence_exit" for e in res.events),
            "distance_err_pct": M.distance_error_pct(
                float(res.trips.loc[res.trips["kind"] == "trip", "distance_m"].sum()), true_distance
            ),
            "start_end_s": timing[0] if timing else (math.nan, math.nan),
            "distance_chords_pct": M.distance_error_pct(_chords_distance(track, zones), true_distance),
            "p95_m": M.h_err_p95(track.loc[np.isfinite(track["lat"].to_numpy(float))], ref)
            if tr_t.size
            else math.nan,
        }
    return out, tuned


def _chords_distance(track: pd.DataFrame, zones: list[Any]) -> float:
    """The trips' distance with the odometer of gated chords (the vocabulary's before the speed's), m."""
    trips = describe(track, zones, TrackerConfig(odometer="chords")).trips
    return float(trips.loc[trips["kind"] == "trip", "distance_m"].sum())


def exit_rows(g: pd.DataFrame, tracks: dict[str, pd.DataFrame], center: tuple[float, float]) -> list[str]:
    """What each 15 m fence exit of the ``fixes`` engine is (a parked day, truth at ``center``).

    Per exit: its time; the track's distance from the true point there and the fence's exit
    bound (15 m plus the vocabulary's margin, 3 x the row's per-axis sigma); the engine event
    at that time (a ``departure`` with its run's span); the raw fixes' error there: the median
    distance from the true point of the fixes of the 60 s before, and for how long before the
    exit the median of the fixes of the previous 20 s had stayed beyond 15 m; and the fix the
    track went to, against the median of the 20 s before it (a jump, or the drift itself).
    """
    frame = LocalFrame(center[0], center[1], 0.0)
    gt = g["t"].to_numpy(float)
    gne = frame.to_ned(g["lat_deg"].to_numpy(float), g["lon_deg"].to_numpy(float), np.zeros(len(g)))
    r_fix = np.hypot(gne[:, 0], gne[:, 1])
    idx = pd.to_timedelta(gt, unit="s")
    med_n = pd.Series(gne[:, 0], index=idx).rolling(pd.Timedelta(seconds=20)).median().to_numpy(float)
    med_e = pd.Series(gne[:, 1], index=idx).rolling(pd.Timedelta(seconds=20)).median().to_numpy(float)
    r_med = np.hypot(med_n, med_e)
    rows = []
    for name, track in tracks.items():
        res = describe(track, _zones(center))
        events = track.attrs.get("events", [])
        for ex in (e for e in res.events if e["type"] == "geofence_exit"):
            te = float(ex["t"])
            row = track.loc[track["t"].to_numpy(float) == te].iloc[0]
            ne = frame.to_ned(np.array([row["lat"]]), np.array([row["lon"]]), np.zeros(1))[0]
            sig = math.sqrt(0.5 * (row["std_north"] ** 2 + row["std_east"] ** 2))
            dep = [e for e in events if e["type"] == "departure" and abs(e["t"] - te) <= 5.0]
            dep_s = f"departure at {dep[-1]['t']:.0f} s (run {dep[-1]['since_s']:.0f} s)" if dep else "–"
            before = (gt > te - 60.0) & (gt <= te)
            k = int(np.searchsorted(gt, te, side="right")) - 1
            out = k
            while out > 0 and r_med[out - 1] > FENCE_M:
                out -= 1
            j = int(np.searchsorted(gt, float(dep[-1]["t"]) if dep else te))
            jump = math.hypot(gne[j, 0] - med_n[max(j - 1, 0)], gne[j, 1] - med_e[max(j - 1, 0)])
            rows.append(
                f"| {name} | {te:.0f} | {math.hypot(ne[0], ne[1]):.1f} / {FENCE_M + 3.0 * sig:.1f} | {dep_s} | "
                f"{np.median(r_fix[before]):.1f} | {gt[k] - gt[out]:.0f} | {r_fix[j]:.1f} / {jump:.1f} |"
            )
    return rows


def _targets(name: str, res: dict[str, dict[str, Any]], driving: bool) -> list[str]:
    """Rows of the targets table for one fleet day."""
    raw_p95 = res["raw fixes"]["p95_m"]
    fw, sm = res[FWD], res[SMOOTHED]
    rows: list[tuple[str, str, Any, Any, Any]] = [
        ("parked odometer growth <= 1 %", "parked_growth_pct", lambda v: v <= 1.0, "{:.2f} %", None),
        ("no false trip", "false_trips", lambda v: v == 0, "{:.0f}", None),
        # the fence is around the first truth point: a day that drives off has one real exit
        (
            f"{int(driving)} exit(s) of the 15 m fence (the truth's)",
            "fence_exits",
            lambda v: v == int(driving),
            "{:.0f}",
            None,
        ),
        (f"horizontal p95 <= raw ({raw_p95:.1f} m)", "p95_m", lambda v: v <= raw_p95, "{:.1f} m", None),
    ]
    if driving:
        rows += [
            ("driving distance within 2 %", "distance_err_pct", lambda v: abs(v) <= 2.0, "{:+.1f} %", None),
            (
                "(driving distance, odometer of gated chords)",
                "distance_chords_pct",
                lambda v: abs(v) <= 2.0,
                "{:+.1f} %",
                None,
            ),
            ("trip start within 30 s", "start_end_s", lambda v: v[0] <= 30.0, "{:.0f} s", 0),
            ("trip end within 30 s", "start_end_s", lambda v: v[1] <= 30.0, "{:.0f} s", 1),
        ]
    out = []
    for label, key, ok, fmt, idx in rows:
        a, b = fw[key], sm[key]
        va = a[idx] if idx is not None else a
        vb = b[idx] if idx is not None else b

        def cell(v: Any, fmt: str = fmt) -> str:
            return _f(float(v), fmt)

        def met(v: Any, full: Any, ok: Any = ok) -> str:
            if not (isinstance(v, int | float) and math.isfinite(float(v))):
                return "no (no trip)"
            return "yes" if ok(full) else "**no**"

        out.append(f"| {name} | {label} | {cell(va)} | {cell(vb)} | {met(va, a)} / {met(vb, b)} |")
    return out


def _zones(center: tuple[float, float]) -> list[Any]:
    from iotnav.tracker import zones_from_geojson

    return zones_from_geojson(
        {
            "type": "Feature",
            "properties": {"name": "parked", "radius": FENCE_M},
            "geometry": {"type": "Point", "coordinates": [center[1], center[0]]},
        }
    )


def _f(x: float, fmt: str = "{:.1f}") -> str:
    return "–" if x is None or (isinstance(x, float) and not math.isfinite(x)) else fmt.format(x)


def _table(title: str, res: dict[str, dict[str, Any]], tuned: TraccarConfig, note: str) -> list[str]:
    lines = [f"### {title}", "", note, ""]
    lines.append(
        "| column | parked odometer growth, % of raw path | false trips | 15 m fence exits | "
        "driving distance error, % | trip start / end error, s | horizontal p95, m |"
    )
    lines.append("|---|---:|---:|---:|---:|---:|---:|")
    for name, m in res.items():
        se = m["start_end_s"]
        lines.append(
            f"| {name} | {_f(m['parked_growth_pct'], '{:.2f}')} | {_f(float(m['false_trips']), '{:.0f}')} | "
            f"{m['fence_exits']} | {_f(m['distance_err_pct'])} | {_f(se[0], '{:.0f}')} / {_f(se[1], '{:.0f}')} | "
            f"{_f(m['p95_m'])} |"
        )
    lines += [
        "",
        f"Traccar tuned here: filter.distance {tuned.filter.distance_m:g} m, "
        f"event.motion.speedThreshold {tuned.speed_threshold_kn:g} kn.",
        "",
    ]
    return lines


def main(seed: int = 1) -> None:
    """Print the section for the fleet days of ``seed`` (1: the reported days; 0 and 2 tuned on)."""
    t0 = time.perf_counter()
    md = [
        "## Trips, stops, odometer and geofences: raw fixes, Traccar's rules, iotnav",
        "",
        "`python benchmarks/bench_tracker.py` (seeded). Columns: see the script's docstring. "
        "**iotnav** is the vocabulary applied to the raw fixes themselves (no engine; its horizontal "
        "p95 is the raw fixes'), and to the `fixes` engine's forward and smoothed tracks; on "
        "drive_0708 the `pipeline` engine (IMU + 1 Hz GNSS) is shown too. Parked growth "
        "is measured over the truth's parked periods; '–' where a figure does not apply.",
        "",
    ]
    parked_cfg: TraccarConfig | None = None
    checks: list[str] = []
    exits: list[str] = []
    for name in FLEET_DAYS:
        day = fleet_day(name, seed=seed)
        center = (float(day.truth["lat"].iloc[0]), float(day.truth["lon"].iloc[0]))
        res, tuned = evaluate(
            day.gnss,
            day.truth,
            day.trips,
            day.distance_m,
            center,
            parked_tuning=parked_cfg,
            exits_out=exits if not day.trips else None,
        )
        if name == "parked-canyon":
            parked_cfg = tuned  # the thresholds that stop the parked drift, then used in traffic
        checks += _targets(name, res, bool(day.trips))
        md += _table(
            f"Simulated: {name}",
            res,
            tuned,
            f"{len(day.gnss)} fixes, {len(day.trips)} truth trip(s), {day.distance_m:.0f} m driven; fence "
            "around the first truth point.",
        )
    # gpsd static captures, pooled row per file
    rows = []
    for fname in GPSD_STATIC:
        path = GPSD / "logs" / fname
        if not path.exists():
            rows.append(f"| {fname} | not found |")
            continue
        log = ingest([path])
        g = _valid(log.gnss)
        if len(g) < 10:
            rows.append(f"| {fname} | {len(g)} valid fixes: skipped |")
            continue
        center = (float(np.median(g["lat_deg"])), float(np.median(g["lon_deg"])))
        res, _ = evaluate(g, None, [], 0.0, center)
        cells = [
            f"{_f(res[c]['parked_growth_pct'], '{:.2f}')} / {_f(float(res[c]['false_trips']), '{:.0f}')} / {res[c]['fence_exits']}"
            for c in res
        ]
        rows.append(f"| {fname} ({len(g)} fixes) | " + " | ".join(cells) + " |")
    md += [
        "### gpsd corpus: static captures",
        "",
        "Cells: parked odometer growth, % of the raw path / false trips / exits of a 15 m fence "
        "around the median fix.",
        "",
        "| capture | raw fixes | Traccar defaults | Traccar tuned | iotnav on raw fixes | "
        "`fixes` forward | `fixes` smoothed |",
        "|---|---|---|---|---|---|---|",
        *rows,
        "",
    ]
    folder = DATA / "rtklibexplorer_gnss_imu" / "drive_0708"
    if folder.exists():
        from iotnav.cli.outages import load_dataset
        from iotnav.engines.registry import make_engine
        from iotnav.eval.outages import rtk_truth

        log, _ = load_dataset(folder)
        truth = rtk_truth(log.gnss)
        sp = np.hypot(truth["vn"].to_numpy(float), truth["ve"].to_numpy(float))
        mv = np.flatnonzero(sp > 0.5)
        trips = [(float(truth["t"].iloc[mv[0]]), float(truth["t"].iloc[mv[-1]]))]
        dist = M.apparent_path_m(truth["lat"].to_numpy(float), truth["lon"].to_numpy(float))
        g = _valid(log.gnss)
        g1 = g.loc[np.concatenate([[True], np.diff(np.floor(g["t"].to_numpy(float))) > 0])].reset_index(
            drop=True
        )
        thin = replace(log, gnss=g1)
        track = run_batch(make_engine("pipeline", None), thin)
        center = (float(truth["lat"].iloc[0]), float(truth["lon"].iloc[0]))
        res, tuned = evaluate(g1, truth, trips, dist, center, {"pipeline engine (IMU + 1 Hz fixes)": track})
        md += _table(
            "Real: drive_0708 (1 Hz RTK fixes)",
            res,
            tuned,
            f"{len(g1)} fixes, 548 s, static 38 s at the start and 19 s at the end (shorter than the "
            f"300 s parking: the trip stays open); {dist:.0f} m driven (RTK path). The fixes are RTK "
            "(cm): this log shows the trip logic, not noise handling.",
        )
    md += [
        "### Issue 17's targets, `fixes` engine (forward / smoothed)",
        "",
        "Parked: odometer growth <= 1 % of the raw fixes' apparent path, no false trip, 0 exits of the "
        "15 m fence (1 on a day that drives off: the departure); driving: distance within 2 %, trip "
        "start and end within 30 s; horizontal p95 no worse than the raw fixes. Parked, the engine "
        "holds its position until the departure test (`iotnav.engines.fixes`, module docstring) "
        "confirms a departure: neither the canyon's reported speed (0.7 m/s median while parked, up "
        "to 2-3 m/s) nor its 10-20 m wander nor its 50-500 m jumps end the static state. Before that "
        "test the parked day's track left the fence 41 times (smoothed 40; 2701 static starts in 8 "
        f"h). The test was tuned on the fleet days with seeds 0 and 2; the days here are seed {seed}.",
        "",
        "| scenario | target | forward | smoothed | met (forward / smoothed) |",
        "|---|---|---|---|---|",
        *checks,
        "",
        "Driving distance: the odometer is the engine's path from its speed "
        "(`iotnav.tracker.odometer.velocity_increments`: the trapezoid of the rows' speeds, 0 "
        "between static rows, the jump where the static state ends counted beyond its noise, a "
        "speed 9.81 m/s off its 5 s median taken as that median), not the chords between rows "
        "gated by the rows' absolute sigma (the row in brackets: the odometer before, "
        '`TrackerConfig(odometer="chords")`, the same trips).',
        "",
        f"#### What the parked day's fence exits are (`fixes` engine, seed {seed})",
        "",
        "Columns: the track's distance from the true point at the exit / the exit bound (15 m + 3 "
        "sigma of the row); the engine's event; the raw fixes' median distance from the true point "
        "over the 60 s before (their error: the truth does not move); how long before the exit "
        "the 20 s median of the fixes had been beyond 15 m; the fix the track went to: its "
        "distance from the true point / from the median of the 20 s of fixes before it (a jump "
        "off the drift, or the drift itself). An exit at a fix a few metres from the median of "
        "the fixes before it, those fixes beyond 15 m for about the errors' correlation time (120 s "
        "in the urban canyon) or longer, is the receiver's own error: its fixes and their Doppler "
        "are those of a device creeping away at a few tenths of a m/s, and nothing in a "
        "fixes-only stream tells them apart (an ignition or motion flag or an accelerometer "
        "would; this day has none).",
        "",
        "| track | exit at, s | track from truth / bound, m | engine event | fixes' error, 60 s median, m "
        "| fixes' 20 s median beyond 15 m for, s | fix taken: from truth / jump, m |",
        "|---|---:|---|---|---:|---:|---|",
        *(exits or ["| – | no exit | | | | | |"]),
        "",
        f"Run time {time.perf_counter() - t0:.0f} s.",
        "",
    ]
    text = "\n".join(md)
    print(text)
    if os.environ.get("IOTNAV_WRITE_RESULTS") == "1" and seed == 1:
        out = Path(__file__).parent / "results" / "tracker.md"
        out.parent.mkdir(parents=True, exist_ok=True)
        out.write_text(text)


if __name__ == "__main__":
    import argparse

    ap = argparse.ArgumentParser(description="Trips, stops, odometer, geofences: raw fixes, Traccar, iotnav.")
    ap.add_argument("--seed", type=int, default=1, help="fleet days' seed (1 reported; 0 and 2 tuned on)")
    main(ap.parse_args().seed)
