"""Simulated fleet days for the tracker's vocabulary: parked hours, stop-and-go, sparse drives.

GNSS fixes only (no IMU), from :func:`iotnav.sim.gnss_model.simulate_gnss` on a planar
trajectory built here, seeded. Each day returns the fixes, the truth and the truth's trips.

* ``parked-canyon``: 8 h parked in the ``urban-canyon`` environment (correlated multipath of
  metres to tens of metres, its own 15-60 m outliers) plus occasional large jumps: Poisson,
  3 an hour, each a constant offset of uniform size in 50-500 m and random direction lasting
  an exponential time of mean 5 s (the "jumps of kilometres" Traccar users report are the
  same mechanism, larger). No trip.
* ``stop-and-go``: 10 min parked, 30 min of traffic (runs at a uniform 1-5 m/s for 20-90 s,
  halts of 10-60 s, a turn of up to 90 degrees between runs), 10 min parked; ``urban-canyon``.
  One trip, from the first run's start to the last run's end.
* ``sparse-drive``: 10 min parked, 30 min driving at 8-15 m/s (speed changes and turns every
  20-120 s), 10 min parked, ``open-sky``, one fix every 30 s (the 1 Hz simulation thinned, as
  a power-saving tracker reports). One trip.

The speeds and durations are scenario choices (the issue's: parked hours, traffic at
1-5 m/s, a fix every 10-60 s), not fitted to anything.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import numpy.typing as npt
import pandas as pd

from iotnav.geo import LocalFrame
from iotnav.sim.config import GnssConfig
from iotnav.sim.gnss_model import simulate_gnss

FloatArray = npt.NDArray[np.float64]

FLEET_DAYS = ("parked-canyon", "stop-and-go", "sparse-drive")
ORIGIN = LocalFrame(45.0628, 7.662, 290.0)


@dataclass(frozen=True)
class FleetDay:
    """One simulated day.

    Attributes
    ----------
    name : str
    gnss : pandas.DataFrame
        Fixes, :data:`iotnav.io.schema.GNSS_COLUMNS`.
    truth : pandas.DataFrame
        ``t``, ``lat``, ``lon``, ``north``, ``east`` (m about :data:`ORIGIN`), ``speed`` (m/s), 1 Hz.
    trips : list of (float, float)
        Truth trips, start and end, s.
    distance_m : float
        Truth distance driven, m.
    """

    name: str
    gnss: pd.DataFrame
    truth: pd.DataFrame
    trips: list[tuple[float, float]]
    distance_m: float


def _speed_profile(name: str, rng: np.random.Generator) -> tuple[FloatArray, FloatArray]:
    """Speed (m/s) and heading (rad) per second of the day."""
    if name == "parked-canyon":
        n = 8 * 3600
        return np.zeros(n), np.zeros(n)
    lo, hi, halt = (1.0, 5.0, True) if name == "stop-and-go" else (8.0, 15.0, False)
    v: list[float] = [0.0] * 600
    psi: list[float] = [0.0] * 600
    heading = rng.uniform(0, 2 * np.pi)
    while len(v) < 600 + 1800:
        run = int(rng.uniform(20, 90 if halt else 120))
        v += [float(rng.uniform(lo, hi))] * run
        psi += [heading] * run
        if halt and len(v) < 600 + 1800 - 60:
            stop = int(rng.uniform(10, 60))
            v += [0.0] * stop
            psi += [heading] * stop
        heading += rng.uniform(-np.pi / 2, np.pi / 2)
    v = v[: 600 + 1800]
    psi = psi[: 600 + 1800]
    v += [0.0] * 600
    psi += [psi[-1]] * 600
    return np.asarray(v), np.asarray(psi)


def _jumps(err_t: FloatArray, rng: np.random.Generator) -> FloatArray:
    """North/East offsets of the large jumps (module docstring), ``(n, 2)``, m."""
    n = err_t.size
    out = np.zeros((n, 2))
    for _ in range(rng.poisson(3.0 * n / 3600.0)):
        i0 = int(rng.integers(0, n))
        k = max(1, round(rng.exponential(5.0)))
        size, ang = rng.uniform(50.0, 500.0), rng.uniform(0, 2 * np.pi)
        out[i0 : i0 + k] += size * np.array([np.cos(ang), np.sin(ang)])
    return out


def fleet_day(name: str, seed: int = 0) -> FleetDay:
    """Simulate one of :data:`FLEET_DAYS` (module docstring), seeded.

    Raises
    ------
    ValueError
        An unknown name.
    """
    if name not in FLEET_DAYS:
        raise ValueError(f"unknown fleet day {name!r}; expected one of {', '.join(FLEET_DAYS)}")
    rng = np.random.default_rng(seed)
    v, psi = _speed_profile(name, rng)
    t = np.arange(v.size, dtype=float)
    vn, ve = v * np.cos(psi), v * np.sin(psi)
    north = np.concatenate([[0.0], np.cumsum(vn[:-1])])
    east = np.concatenate([[0.0], np.cumsum(ve[:-1])])
    p_n = np.column_stack([north, east, np.zeros_like(t)])
    v_n = np.column_stack([vn, ve, np.zeros_like(t)])
    env = "open-sky" if name == "sparse-drive" else "urban-canyon"
    gnss, _ = simulate_gnss(GnssConfig(environment=env), t, p_n, v_n, ORIGIN, 1.7e9, rng)
    if name == "parked-canyon":
        jump = _jumps(t, rng)
        lat, lon, _ = ORIGIN.from_ned(
            np.column_stack(
                [
                    *(ORIGIN.to_ned(gnss["lat_deg"], gnss["lon_deg"], gnss["height_m"])[:, :2] + jump).T,
                    np.zeros_like(t),
                ]
            )
        )
        gnss["lat_deg"], gnss["lon_deg"] = lat, lon
    if name == "sparse-drive":
        gnss = gnss.iloc[::30].reset_index(drop=True)
    lat, lon, _ = ORIGIN.from_ned(p_n)
    truth = pd.DataFrame({"t": t, "lat": lat, "lon": lon, "north": north, "east": east, "speed": v})
    moving = np.flatnonzero(v > 0)
    trips = [(float(t[moving[0]]), float(t[moving[-1]] + 1.0))] if moving.size else []
    return FleetDay(name, gnss, truth, trips, float(v.sum()))
