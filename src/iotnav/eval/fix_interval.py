"""Fix-interval study: error of the ``absfix`` engine against the time between absolute fixes.

Reproduces the layout of Tables 3-7 of Dabove et al. (2016): for fixes every 1, 2 and 5 s, the
mean, 67 % and 95 % of the absolute North and East errors of the navigation solution, for each
way of obtaining the inner INS variables:

``none``
    accelerometer bias and gyro drift held at zero (paper Tables 3/6 "without bias estimation",
    Table 7 "without drift estimation"); the velocity still comes from the last two fixes.
``fixes``
    the decoupled estimates from the fixes themselves (three positions for velocity and
    accelerometer biases, two attitudes for the gyro drift; paper Table 4 "drift estimation
    coming from images").
``reference``
    the biases known from a reference unit. In the paper the Microstrain's own GPS/INS Kalman
    filter supplied them (Tables 5/6); here the simulator's true turn-on biases
    (``meta["imu_draw"]``) stand in for that calibration, which makes this mode an upper bound
    of what any bias estimate can give (the slow in-run bias is not included).

Each run simulates the scenario (default ``pedestrian-fixes``) with its own seed, runs the
engine with the fixes merged by arrival time (:func:`iotnav.engines.absfix.run_with_fixes`)
and compares every output row after the first fix with the truth
(:func:`iotnav.eval.metrics.track_errors`); errors of all runs are pooled before the
statistics.

Reference: P. Dabove, G. Ghinamo, A. M. Lingua, "Inertial sensors for smartphones navigation",
SpringerPlus 4:834, 2015 (cited in this project as Dabove et al. 2016), Results, Tables 3-7.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import pandas as pd

from iotnav import sim
from iotnav.engines.absfix import AbsfixConfig, AbsfixEngine, run_with_fixes
from iotnav.eval.metrics import track_errors
from iotnav.io.log import Log

__all__ = [
    "MODES",
    "PAPER_TABLE_4",
    "FixIntervalConfig",
    "engine_config",
    "format_tables",
    "run_once",
    "study",
]

#: Estimation modes (module docstring).
MODES: tuple[str, ...] = ("none", "fixes", "reference")

#: Table 4 of the paper (drift estimation from images): interval -> {"N"/"E": (mean, p67, p95)}, m.
PAPER_TABLE_4: dict[float, dict[str, tuple[float, float, float]]] = {
    1.0: {"N": (0.14, 0.16, 0.38), "E": (0.14, 0.16, 0.44)},
    2.0: {"N": (0.42, 0.47, 1.27), "E": (0.42, 0.50, 1.78)},
    5.0: {"N": (2.60, 2.70, 5.80), "E": (2.60, 2.90, 6.50)},
}


@dataclass(frozen=True)
class FixIntervalConfig:
    """What one study runs.

    Attributes
    ----------
    scenario : str
        Simulator scenario with fixes (``pedestrian-fixes``).
    intervals_s : tuple of float
        Times between fixes, s (paper: 1, 2, 5).
    modes : tuple of str
        Estimation modes (:data:`MODES`).
    runs : int
        Monte Carlo runs (seeds ``seed .. seed + runs - 1``).
    seed : int
        First seed.
    sigma_pos_m, sigma_att_rad : float
        Fix accuracy (default: total-station positions, millimetres; a precise attitude).
    latency_s : float
        ``t_arrival - t_valid`` of every fix, s.
    preset : str
        IMU preset (``3dm-gx3-35`` Microstrain class, or ``smartphone``).
    denoise : str
        Engine denoising (``off``, ``batch``, ``streaming``).
    revised : bool
        Evaluate the latency-compensated (revised) track instead of the real-time one.
    overrides : tuple of (str, object)
        Further scenario overrides (``("motion.laps", 1)``).
    """

    scenario: str = "pedestrian-fixes"
    intervals_s: tuple[float, ...] = (1.0, 2.0, 5.0)
    modes: tuple[str, ...] = MODES
    runs: int = 1
    seed: int = 0
    sigma_pos_m: float = 0.002
    sigma_att_rad: float = 0.001
    latency_s: float = 0.0
    preset: str = "3dm-gx3-35"
    denoise: str = "off"
    revised: bool = False
    overrides: tuple[tuple[str, Any], ...] = field(default_factory=tuple)


def engine_config(mode: str, meta: Mapping[str, Any], **changes: Any) -> AbsfixConfig:
    """Engine configuration of an estimation mode (``reference`` reads the simulator's biases).

    Parameters
    ----------
    mode : str
        ``none``, ``fixes`` or ``reference``.
    meta : Mapping
        ``SimResult.meta`` (``imu_draw`` holds the turn-on biases, SI).
    **changes
        Other :class:`AbsfixConfig` fields.

    Returns
    -------
    AbsfixConfig
    """
    if mode not in MODES:
        raise ValueError(f"mode: expected one of {', '.join(MODES)}, got {mode!r}")
    kw: dict[str, Any] = {"bias_mode": mode, "drift_mode": mode}
    if mode == "reference":
        draw = meta["imu_draw"]
        kw["reference_acc_bias_mps2"] = tuple(float(a) for a in draw["acc_turn_on_bias_mps2"])
        kw["reference_gyro_bias_rads"] = tuple(float(a) for a in draw["gyro_turn_on_bias_rads"])
    kw.update(changes)
    return AbsfixConfig(**kw)


def run_once(
    result: sim.SimResult, mode: str, *, denoise: str = "off", revised: bool = False, **changes: Any
) -> tuple[np.ndarray, np.ndarray]:
    """Run ``absfix`` on a simulated result; North and East errors (m) of the rows with a position.

    Parameters
    ----------
    result : SimResult
        A scenario with fixes.
    mode : str
        Estimation mode.
    denoise : str
        Engine denoising.
    revised : bool
        Evaluate the revised (latency-compensated) track.
    **changes
        Other engine configuration fields.

    Returns
    -------
    tuple of numpy.ndarray
        ``(n_err, e_err)``, m.
    """
    if result.fixes is None:
        raise ValueError(f"scenario {result.config.name!r} has no fixes (set fixes.enabled=true)")
    cfg = engine_config(mode, result.meta, denoise=denoise, **changes)
    track = run_with_fixes(AbsfixEngine(cfg), Log(imu=result.imu), result.fixes, revised=revised)
    track = track[track["source"] != "none"]
    err = track_errors(track, result.truth)
    return err.n_err, err.e_err


def _stats(x: np.ndarray) -> tuple[float, float, float]:
    a = np.abs(x)
    return float(np.mean(a)), float(np.percentile(a, 67)), float(np.percentile(a, 95))


def study(cfg: FixIntervalConfig) -> pd.DataFrame:
    """Run the study.

    Parameters
    ----------
    cfg : FixIntervalConfig
        What to run.

    Returns
    -------
    pandas.DataFrame
        One row per (mode, interval) with ``mode``, ``interval_s``, ``runs``, ``n``,
        ``n_mean``, ``n_p67``, ``n_p95``, ``e_mean``, ``e_p67``, ``e_p95``, ``h_mean`` (m).
    """
    rows = []
    pooled: dict[tuple[str, float], list[tuple[np.ndarray, np.ndarray]]] = {}
    for interval in cfg.intervals_s:
        for r in range(cfg.runs):
            ov: dict[str, Any] = {
                "fixes.enabled": True,
                "fixes.interval_s": interval,
                "fixes.latency_s": cfg.latency_s,
                "fixes.sigma_pos_m": cfg.sigma_pos_m,
                "fixes.sigma_att_rad": cfg.sigma_att_rad,
                "imu.preset": cfg.preset,
                **dict(cfg.overrides),
            }
            res = sim.build(cfg.scenario, seed=cfg.seed + r, overrides=ov)
            for mode in cfg.modes:
                pooled.setdefault((mode, interval), []).append(
                    run_once(res, mode, denoise=cfg.denoise, revised=cfg.revised)
                )
    for (mode, interval), parts in pooled.items():
        n = np.concatenate([p[0] for p in parts])
        e = np.concatenate([p[1] for p in parts])
        nm, n67, n95 = _stats(n)
        em, e67, e95 = _stats(e)
        rows.append(
            {
                "mode": mode,
                "interval_s": interval,
                "runs": len(parts),
                "n": int(n.size),
                "n_mean": nm,
                "n_p67": n67,
                "n_p95": n95,
                "e_mean": em,
                "e_p67": e67,
                "e_p95": e95,
                "h_mean": float(np.mean(np.hypot(n, e))),
            }
        )
    return pd.DataFrame(rows)


def format_tables(df: pd.DataFrame, modes: Sequence[str] | None = None) -> str:
    """Markdown tables in the paper's layout: per mode, rows N and E, Mean/67 %/95 % per interval.

    Parameters
    ----------
    df : pandas.DataFrame
        Output of :func:`study`.
    modes : sequence of str, optional
        Modes to print (default: those in ``df``).

    Returns
    -------
    str
        Markdown.
    """
    intervals = sorted(df["interval_s"].unique())
    out: list[str] = []
    for mode in modes or list(dict.fromkeys(df["mode"])):
        sub = df[df["mode"] == mode].set_index("interval_s")
        head = "| axis | " + " | ".join(f"{t:g} s mean | 67 % | 95 %" for t in intervals) + " |"
        sep = "|---|" + "---|---|---|" * len(intervals)
        out += [f"**{mode}** (m)", "", head, sep]
        for axis, key in (("N", "n"), ("E", "e")):
            cells = " | ".join(
                f"{sub.loc[t, f'{key}_mean']:.3f} | {sub.loc[t, f'{key}_p67']:.3f} | {sub.loc[t, f'{key}_p95']:.3f}"
                for t in intervals
            )
            out.append(f"| {axis} | {cells} |")
        out.append("")
    return "\n".join(out)
