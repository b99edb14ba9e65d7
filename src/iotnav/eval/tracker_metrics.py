"""Fleet metrics of trips, stops, odometer and geofences against a truth (pure functions).

Definitions (used by ``benchmarks/bench_tracker.py``; times s, distances m):

* **apparent path** of raw fixes: the sum of the distances between successive valid fixes
  (what a plain odometer counts);
* **parked odometer growth**: the odometer's growth over a parked period as a percentage of
  the raw fixes' apparent path over it;
* **false trips**: reported trips that overlap no truth trip in time;
* **fence exits**: inside-to-outside transitions of a circle (15 m in the benchmark) around
  the true parked point, for positions taken one by one (raw fixes, Traccar: its geofences
  have no hysteresis) or as the vocabulary reports them (iotnav);
* **driving distance error**: ``100 (reported - true) / true`` over the truth's trips;
* **trip start / end error**: for each truth trip, the reported trip overlapping it most, the
  absolute differences of the starts and of the ends (NaN when none overlaps);
* **horizontal error p95**: 95th percentile of :func:`iotnav.eval.metrics.track_errors`.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np
import numpy.typing as npt
import pandas as pd

from iotnav.eval.metrics import track_errors
from iotnav.geo import LocalFrame

FloatArray = npt.NDArray[np.float64]


def apparent_path_m(lat_deg: FloatArray, lon_deg: FloatArray) -> float:
    """Sum of successive distances of the finite positions, m (tangent plane at the first)."""
    ok = np.isfinite(lat_deg) & np.isfinite(lon_deg)
    if ok.sum() < 2:
        return 0.0
    la, lo = lat_deg[ok], lon_deg[ok]
    ne = LocalFrame(float(la[0]), float(lo[0]), 0.0).to_ned(la, lo, np.zeros(la.size))
    return float(np.hypot(np.diff(ne[:, 0]), np.diff(ne[:, 1])).sum())


def growth_pct(odometer_growth_m: float, apparent_path: float) -> float:
    """Odometer growth as a percentage of the apparent path (NaN when the path is 0)."""
    return 100.0 * odometer_growth_m / apparent_path if apparent_path > 0 else math.nan


def _trips(table: pd.DataFrame) -> list[tuple[float, float]]:
    tr = table.loc[table["kind"] == "trip"]
    return list(zip(tr["t_start"].astype(float), tr["t_end"].astype(float), strict=True))


def false_trips(table: pd.DataFrame, truth_trips: Sequence[tuple[float, float]]) -> int:
    """Reported trips overlapping no truth trip."""
    return sum(not any(a < d and c < b for c, d in truth_trips) for a, b in _trips(table))


def trip_timing(table: pd.DataFrame, truth_trips: Sequence[tuple[float, float]]) -> list[tuple[float, float]]:
    """``(|start error|, |end error|)`` per truth trip, s (NaN, NaN when no reported trip overlaps)."""
    out = []
    rep = _trips(table)
    for c, d in truth_trips:
        ov = [(min(b, d) - max(a, c), a, b) for a, b in rep if a < d and c < b]
        if not ov:
            out.append((math.nan, math.nan))
            continue
        _, a, b = max(ov)
        out.append((abs(a - c), abs(b - d)))
    return out


def distance_error_pct(reported_m: float, true_m: float) -> float:
    """``100 (reported - true) / true`` (NaN when the truth is 0)."""
    return 100.0 * (reported_m - true_m) / true_m if true_m > 0 else math.nan


def fence_exits(
    lat_deg: FloatArray, lon_deg: FloatArray, center: tuple[float, float], radius_m: float
) -> int:
    """Inside-to-outside transitions of positions taken one by one (NaN rows skipped)."""
    ok = np.isfinite(lat_deg) & np.isfinite(lon_deg)
    if not ok.any():
        return 0
    ne = LocalFrame(center[0], center[1], 0.0).to_ned(lat_deg[ok], lon_deg[ok], np.zeros(int(ok.sum())))
    inside = np.hypot(ne[:, 0], ne[:, 1]) <= radius_m
    return int(np.sum(inside[:-1] & ~inside[1:]))


def h_err_p95(track: pd.DataFrame, truth: pd.DataFrame) -> float:
    """95th percentile of the horizontal error of ``track`` (``t``, ``lat``, ``lon``) against ``truth``, m."""
    # horizontal only: both on the ellipsoid, whatever heights either carries
    err = track_errors(track[["t", "lat", "lon"]], truth[["t", "lat", "lon"]])
    return float(np.percentile(err.h_err, 95)) if err.h_err.size else math.nan
