"""Accuracy a GNSS duty cycle costs, on real logs and on the simulator (issue 20).

The energy side is :mod:`iotnav.eval.power`; this module measures the other side: how far the
engines' positions are from the truth when the receiver only gives a fix every ``T`` seconds.

Thinning (:func:`thin_to_duty_cycle`)
    The receiver wakes at ``t0 + k T`` (``t0``: the first fed fix) and delivers the first fed
    fix at or after ``wake + time_to_fix_s`` and before the next wake; every other fix is
    removed (as if the receiver were asleep). Always on (``None``) keeps every fix. The fixes
    kept are the fed ones, unchanged: their error is that of a receiver tracking continuously
    (the degraded RTK of :mod:`iotnav.eval.outages` on the rtklibexplorer logs, the recorded
    SBAS fixes on the Husky, the simulator's receiver model on a scenario). A hot-start fix of a
    real receiver can be somewhat worse than a tracking fix; that is not modelled (stated).
    One fix per wake: the further fixes a receiver kept on ``on_after_fix_s``
    (:class:`iotnav.eval.power.DevicePower`) would give are not fed (that setting costs energy
    only, a conservative reading).

Scores (:func:`run_case`)
    Every engine runs on the thinned log (:func:`iotnav.engines.base.run_batch`). Its track is
    read like a device that reports its latest estimate: at each truth epoch from the first
    fed fix on, the latest output at or before it (:func:`held_at`; an inertial engine's 100 Hz
    output is then at most one IMU period old, the ``fixes`` engine's is its latest fix
    estimate). Horizontal error against the truth: median (p50), p95, RMS and maximum over
    those epochs, with the number of epochs and the coverage (epochs with an output / all).
    The baseline ``hold`` is GNSS alone holding its latest fix
    (:func:`iotnav.eval.outages.gnss_hold_track`), the fallback an engine must beat ("do no
    harm"): ``worse_than_hold`` flags an engine whose p95 exceeds the hold's by more than
    :data:`HOLD_MARGIN` (1 %) at the same duty cycle (smaller differences are rounding: the
    ``fixes`` engine between sparse fixes is its latest estimate, almost the fix itself).

Cases (:func:`real_case`, :func:`simulated_case`)
    ``drive_0708`` and ``walk_0827`` (rtklibexplorer, RTK truth, GNSS degraded to 1 Hz tracker
    grade) and ``husky`` (SBAS fixes at 2.5 Hz that are also the truth, about 1 m good: errors
    under about 1 m there are noise), loaded by :func:`iotnav.eval.cases.load_case`; any named
    simulator scenario (its own truth and receiver model).
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
import numpy.typing as npt
import pandas as pd

from iotnav.engines.base import Engine, run_batch
from iotnav.eval.metrics import track_errors
from iotnav.eval.outages import HOLD, DatasetProfile, gnss_hold_track
from iotnav.eval.power import Battery, DevicePower, budget
from iotnav.io.log import Log

FloatArray = npt.NDArray[np.float64]

__all__ = [
    "HOLD_MARGIN",
    "REAL_CASES",
    "DutyCycleConfig",
    "held_at",
    "periods_label",
    "real_case",
    "run_case",
    "simulated_case",
    "thin_to_duty_cycle",
    "with_budgets",
]

#: Relative margin above the hold's p95 before an engine is flagged ``worse_than_hold``.
HOLD_MARGIN = 0.01

#: Real logs of the study (names accepted by :func:`real_case`).
REAL_CASES: tuple[str, ...] = ("drive_0708", "walk_0827", "husky")


@dataclass(frozen=True)
class DutyCycleConfig:
    """What the study runs.

    Attributes
    ----------
    periods_s : tuple of float or None
        Times between fixes, s; None: always on.
    time_to_fix_s : float
        Time to fix after waking, s (the receiver's hot start).
    engines : tuple of str
        Engines (:func:`iotnav.eval.outages.engine_factories` names); ``hold`` is always scored.
    """

    periods_s: tuple[float | None, ...] = (None, 5.0, 10.0, 30.0, 60.0)
    time_to_fix_s: float = 1.0
    engines: tuple[str, ...] = ("fixes",)

    def __post_init__(self) -> None:
        for p in self.periods_s:
            if p is not None and not (math.isfinite(p) and p > 0.0):
                raise ValueError(f"fix period must be a positive number of seconds, got {p}")
        if not (math.isfinite(self.time_to_fix_s) and self.time_to_fix_s >= 0.0):
            raise ValueError(f"time to fix must be >= 0 s, got {self.time_to_fix_s}")


def thin_to_duty_cycle(
    gnss: pd.DataFrame, period_s: float | None, time_to_fix_s: float, t0: float | None = None
) -> pd.DataFrame:
    """The fixes a receiver woken every ``period_s`` would deliver (module docstring).

    Parameters
    ----------
    gnss : pandas.DataFrame
        Fed GNSS table (:data:`iotnav.io.schema.GNSS_COLUMNS`, sorted by ``t``; not modified).
    period_s : float or None
        Time between wakes, s; None (always on) or a period no longer than ``time_to_fix_s``
        (the receiver cannot sleep) keeps every fix.
    time_to_fix_s : float
        Time from waking to the fix, s.
    t0 : float, optional
        First wake, s (default: the first valid fix).

    Returns
    -------
    pandas.DataFrame
        The valid fixes kept, re-indexed; at most one per period.
    """
    g = gnss[gnss["valid"].to_numpy(bool)].reset_index(drop=True)
    if period_s is None or period_s <= time_to_fix_s or len(g) == 0:
        return g
    t = g["t"].to_numpy(float)
    start = float(t[0]) if t0 is None else float(t0)
    k = np.floor((t - start) / period_s + 1e-9)
    since_wake = t - (start + k * period_s)
    ok = (k >= 0) & (since_wake >= time_to_fix_s - 1e-9)
    idx = np.flatnonzero(ok)
    # first eligible fix of each cycle
    first = idx[np.r_[True, k[idx][1:] != k[idx][:-1]]] if idx.size else idx
    return g.iloc[first].reset_index(drop=True)


def held_at(track: pd.DataFrame, t_eval: FloatArray) -> pd.DataFrame:
    """The latest track row at or before each ``t_eval`` (``t``, ``lat``, ``lon``, ``height``).

    The track read as :func:`iotnav.eval.outages.gnss_hold_track` reads fixes. Rows before the
    track's first output are left out; the track must be sorted by ``t``.
    """
    as_fixes = pd.DataFrame(
        {
            "t": track["t"].to_numpy(float),
            "lat_deg": track["lat"].to_numpy(float),
            "lon_deg": track["lon"].to_numpy(float),
            "height_m": track["height"].to_numpy(float),
            "valid": True,
        }
    )
    return gnss_hold_track(as_fixes, t_eval).drop(columns="source")


def _positioned(track: pd.DataFrame) -> pd.DataFrame:
    ok = (track["source"].to_numpy() != "none") & np.isfinite(track["lat"].to_numpy(float))
    return track.loc[ok].sort_values("t", kind="stable").reset_index(drop=True)


def _scores(held: pd.DataFrame, truth: pd.DataFrame, n_eval: int) -> dict[str, float]:
    if len(held) == 0:
        nan = float("nan")
        return {"n": 0, "coverage": 0.0, "h_p50": nan, "h_p95": nan, "h_rms": nan, "h_max": nan}
    h = track_errors(held, truth[["t", "lat", "lon", "height"]]).h_err
    return {
        "n": int(h.size),
        "coverage": float(h.size / n_eval) if n_eval else 0.0,
        "h_p50": float(np.percentile(h, 50)),
        "h_p95": float(np.percentile(h, 95)),
        "h_rms": float(np.sqrt(np.mean(h**2))),
        "h_max": float(np.max(h)),
    }


def run_case(
    name: str,
    fed: Log,
    truth: pd.DataFrame,
    engines: Mapping[str, Callable[[], Engine]],
    config: DutyCycleConfig,
    progress: Callable[[str], None] | None = None,
) -> pd.DataFrame:
    """Horizontal error of ``hold`` and each engine at each duty cycle of one log.

    Parameters
    ----------
    name : str
        Case name (the ``case`` column).
    fed : Log
        What the engines are fed (its GNSS is thinned per duty cycle).
    truth : pandas.DataFrame
        ``t``, ``lat``, ``lon``, ``height`` (deg, m) of the reference.
    engines : mapping
        Engine name -> builder of a fresh engine.
    config : DutyCycleConfig
        Duty cycles and time to fix.
    progress : callable, optional
        Called with a short description before each engine run.

    Returns
    -------
    pandas.DataFrame
        One row per (engine, period): ``case``, ``engine``, ``period_s`` (NaN: always on),
        ``fixes`` (fed after thinning), ``n``, ``coverage``, ``h_p50``, ``h_p95``, ``h_rms``,
        ``h_max`` (m), ``worse_than_hold``.

    Raises
    ------
    ValueError
        When the log has no valid fix or no truth epoch after the first fix.
    """
    t_fix = fed.gnss["t"].to_numpy(float)[fed.gnss["valid"].to_numpy(bool)]
    if t_fix.size == 0:
        raise ValueError(f"{name}: no valid GNSS fix in the log")
    t0 = float(t_fix[0])
    tt = truth["t"].to_numpy(float)
    t_eval = tt[tt >= t0]
    if t_eval.size == 0:
        raise ValueError(f"{name}: no truth epoch after the first fix (t = {t0:.1f} s)")
    rows: list[dict[str, Any]] = []
    for period in config.periods_s:
        sparse = thin_to_duty_cycle(fed.gnss, period, config.time_to_fix_s, t0)
        if len(sparse) == 0:
            raise ValueError(f"{name}: no fix left every {period} s")
        base = {"case": name, "period_s": math.nan if period is None else float(period), "fixes": len(sparse)}
        hold = _scores(gnss_hold_track(sparse, t_eval), truth, t_eval.size)
        rows.append({**base, "engine": HOLD, **hold, "worse_than_hold": False})
        log_p = dataclasses.replace(fed, gnss=sparse)
        for eng, make in engines.items():
            if progress is not None:
                progress(f"{name} {eng} {'always on' if period is None else f'every {period:g} s'}")
            track = _positioned(run_batch(make(), log_p))
            s = _scores(held_at(track, t_eval), truth, t_eval.size)
            rows.append(
                {
                    **base,
                    "engine": eng,
                    **s,
                    "worse_than_hold": bool(s["h_p95"] > (1.0 + HOLD_MARGIN) * hold["h_p95"]),
                }
            )
    cols = ["case", "engine", "period_s", "fixes", "n", "coverage", "h_p50", "h_p95", "h_rms", "h_max"]
    return pd.DataFrame(rows)[[*cols, "worse_than_hold"]]


def with_budgets(acc: pd.DataFrame, device: DevicePower, battery: Battery) -> pd.DataFrame:
    """The accuracy table with each row's average powers (mW) and battery life (h) beside it.

    Adds ``gnss_mw``, ``imu_mw``, ``mcu_mw``, ``total_mw`` and ``life_h`` from
    :func:`iotnav.eval.power.budget` for the row's engine and period.
    """
    out = acc.copy()
    recs = []
    for r in acc.to_dict("records"):
        p = None if math.isnan(float(r["period_s"])) else float(r["period_s"])
        b = budget(device, battery, p, str(r["engine"]))
        recs.append((b.gnss_mw, b.imu_mw, b.mcu_mw, b.total_mw, b.life_h))
    arr = np.array(recs, float).reshape(-1, 5)
    for k, c in enumerate(("gnss_mw", "imu_mw", "mcu_mw", "total_mw", "life_h")):
        out[c] = arr[:, k]
    return out


def real_case(name: str, max_duration_s: float | None = None) -> tuple[Log, pd.DataFrame, DatasetProfile]:
    """A real log of :data:`REAL_CASES`: what the engines are fed, the truth and the profile.

    ``drive_0708`` is the recording as made (from its first sample); ``walk_0827`` and ``husky``
    the named cases of :mod:`iotnav.eval.cases`. ``max_duration_s`` keeps only the first that
    many seconds (short runs), s.

    Raises
    ------
    ValueError
        For an unknown name; FileNotFoundError when a dataset file is missing.
    """
    from iotnav.eval.cases import CASES, Case, load_case

    if name not in REAL_CASES:
        raise ValueError(f"unknown real log {name!r}; expected one of {', '.join(REAL_CASES)}")
    case = CASES[name] if name in CASES else Case(name=name, dataset=name)
    lc = load_case(case, max_duration_s=max_duration_s)
    return lc.fed, lc.truth, lc.profile


def simulated_case(
    scenario: str, seed: int = 0, overrides: Mapping[str, Any] | None = None
) -> tuple[Log, pd.DataFrame, DatasetProfile]:
    """A simulator scenario as a fed log, its truth and a default profile (car, default ESKF)."""
    from iotnav import sim

    res = sim.build(scenario, seed=seed, overrides=dict(overrides or {}))
    log = Log(gnss=res.gnss, imu=res.imu, mag=res.mag, utc_offset_s=res.utc_offset_s)
    truth = res.truth[["t", "lat", "lon", "height"]].copy()
    prof = DatasetProfile(
        name=scenario,
        pos_file="",
        imu_file="",
        vehicle="car",
        imu_time_offset_s=0.0,
        author_mount_rpy_deg=(0.0, 0.0, 0.0),
    )
    return log, truth, prof


def periods_label(periods_s: Sequence[float | None]) -> str:
    """``always on, 5, 10, 30, 60 s`` for headings."""
    parts = ["always on" if p is None else f"{p:g}" for p in periods_s]
    return ", ".join(parts) + (" s" if any(p is not None for p in periods_s) else "")
