"""The ``fixes`` engine's columns of ``bench_tracker.py`` per fleet-day seed (the departure test's study).

For each seed, the three simulated fleet days of :mod:`iotnav.sim.fleet_days`, the ``fixes``
engine's forward and smoothed tracks under the vocabulary, as ``benchmarks/bench_tracker.py``
scores them (its helpers): parked-canyon 15 m fence exits (and their times), parked odometer
growth (% of the raw path), false trips, departure events of the forward pass; stop-and-go and
sparse-drive trip start / end errors (s) and driving distance error (%). Seeds 0 and 2 are the
ones the departure test was tuned on, 1 the reported one, the others held out. Prints one line
per seed. Run: ``python benchmarks/bench_departure_seeds.py 0,1,2,3,4,5,6``.
"""

from __future__ import annotations

import math
import sys
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

sys.path.insert(0, str(Path(__file__).parent))
import bench_tracker as B
from iotnav.engines.base import run_batch
from iotnav.engines.fixes import FixesConfig, FixesEngine, FixesKFConfig
from iotnav.eval import tracker_metrics as M
from iotnav.io.log import Log
from iotnav.sim.fleet_days import FLEET_DAYS, fleet_day
from iotnav.tracker import describe


def engine_columns(
    g: pd.DataFrame, trips: list[tuple[float, float]], distance_m: float, center: tuple[float, float]
) -> dict[str, Any]:
    """Forward and smoothed metrics of the ``fixes`` engine on one day (``bench_tracker.evaluate``'s)."""
    g = B._valid(g)
    t = g["t"].to_numpy(float)
    parked = B._parked_mask(t, trips)
    parked_path = B._raw_parked_path(g, parked)
    eng = FixesEngine(FixesConfig(kf=FixesKFConfig(smoothing=True)))
    fwd = run_batch(eng, Log(gnss=g))
    out: dict[str, Any] = {"departures": sum(e["type"] == "departure" for e in fwd.attrs.get("events", []))}
    for name, track in (("fwd", fwd), ("sm", eng.smoothed_output(fwd))):
        res = describe(track, B._zones(center))
        ot = res.odometer["t"].to_numpy(float)
        k = np.searchsorted(ot, t, side="right") - 1
        odo = np.where(k >= 0, res.odometer["odometer_m"].to_numpy(float)[np.maximum(k, 0)], 0.0)
        timing = M.trip_timing(res.trips, trips)
        trip_d = float(res.trips.loc[res.trips["kind"] == "trip", "distance_m"].sum())
        out[name] = {
            "growth": M.growth_pct(B._growth(t, odo, parked), parked_path),
            "false": M.false_trips(res.trips, trips),
            "exits": [float(e["t"]) for e in res.events if e["type"] == "geofence_exit"],
            "start_end": timing[0] if timing else (math.nan, math.nan),
            "dist": M.distance_error_pct(trip_d, distance_m) if distance_m else math.nan,
        }
    return out


def main(seeds: list[int]) -> None:
    """Print one line per seed (module docstring)."""
    for s in seeds:
        parts = []
        for name in FLEET_DAYS:
            day = fleet_day(name, seed=s)
            c = (float(day.truth["lat"].iloc[0]), float(day.truth["lon"].iloc[0]))
            r = engine_columns(day.gnss, day.trips, day.distance_m, c)
            f, m = r["fwd"], r["sm"]
            common = (
                f"exits {len(f['exits'])}/{len(m['exits'])} growth {f['growth']:.2f}/{m['growth']:.2f} % "
                f"false {f['false']}/{m['false']}"
            )
            if not day.trips:
                at = ", ".join(f"{x:.0f}" for x in f["exits"] + m["exits"])
                parts.append(f"{name}: {common} (at {at or '-'} s), departures {r['departures']}")
            else:
                se = "/".join(f"{a:.0f}, {b:.0f}" for a, b in (f["start_end"], m["start_end"]))
                parts.append(
                    f"{name}: start, end {se} s, distance {f['dist']:+.1f}/{m['dist']:+.1f} %, {common}"
                )
        print(f"seed {s} (forward/smoothed) | " + " | ".join(parts), flush=True)


if __name__ == "__main__":
    main([int(x) for x in (sys.argv[1] if len(sys.argv) > 1 else "0,1,2").split(",")])
