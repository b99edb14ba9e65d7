"""Leave-one-trial-out tuning of ``ahrs_eskf`` on BROAD, and the sustained-acceleration check.

For each of the shared BROAD trials, the filter's tunables are chosen on the *other* trials
(coarse grid, then a fine pass around the best point) and the held-out trial is scored with
them; VQF at its defaults runs beside it. The objective on a training set is the mean over its
trials of the 9-axis and 6-axis total RMSE (BROAD's metric, :mod:`iotnav.eval.attitude`). One
configuration serves 9-axis and 6-axis use (``use_mag`` aside): a per-axis search was tried and
gave a worse 6-axis held-out mean (see the README). The shipped default
(:class:`~iotnav.techniques.ahrs_eskf.AhrsEskfConfig`) is the same search on all trials; the
figures reported per trial are the held-out ones.

The robustness case: trial 05 (slow rotation with three rest breaks) with fast translation
strokes added during its motion phases (:func:`~iotnav.eval.attitude.translation_strokes`,
seed 1) and, during the breaks, a slow translation (0.3 m/s^2, 4 s period) plus a slow turn
about the vertical at 3 deg/s (:func:`~iotnav.eval.attitude.add_vertical_rotation`), which a
rest detector that checks the gyro against its own low-pass alone takes for rest. It is never
used for tuning.

Run: ``nice -n 10 python benchmarks/bench_attitude_loo.py`` (``IOTNAV_WRITE_RESULTS=1``
writes ``benchmarks/results/attitude_loo.md``). About 300 filter runs of 0.5 s each.
"""

from __future__ import annotations

import itertools
import math
import time
from collections.abc import Sequence
from dataclasses import replace

import numpy as np

from bench_attitude import data_dir, emit  # the sibling script (benchmarks/ is on the path)
from iotnav.eval.attitude import (
    ImuRecording,
    fast_translation_with_rest,
    load_broad,
    ned_to_enu_quat,
    rest_breaks,
    run_vqf,
    score,
)
from iotnav.techniques.ahrs_eskf import AhrsEskfConfig, run_ahrs_eskf

#: The parameters as they were before this study (tuned once over all five trials).
OLD = replace(
    AhrsEskfConfig(),
    acc_lp_tau_s=1.0,
    acc_noise_rad=0.01,
    mag_noise_rad=2.0,
    rest_max_rate_rad_s=0.1,
    rest_acc_drift_m_s2=math.inf,
    acc_dyn_m_s2=math.inf,
    acc_disagree_rad=math.inf,
    motion_bias_est=True,
)

#: Coarse grid (shared by every fold).
COARSE: dict[str, Sequence[object]] = {
    "acc_lp_tau_s": (1.0, 2.0, 3.0),
    "acc_noise_rad": (0.01, 0.02),
    "acc_dyn_m_s2": (math.inf, 2.0),
    "motion_bias_est": (True, False),
}


def _fine(best: AhrsEskfConfig) -> list[AhrsEskfConfig]:
    """The fine pass around a coarse optimum."""
    out = [replace(best, acc_lp_tau_s=best.acc_lp_tau_s * f) for f in (0.75, 1.25)]
    out += [replace(best, acc_disagree_rad=0.05)]
    out += [replace(best, mag_noise_rad=m) for m in (1.0, 4.0)]
    return out


class Scorer:
    """Runs and caches ``ahrs_eskf`` scores per (configuration, trial, axes)."""

    def __init__(self, recs: list[ImuRecording]) -> None:
        self.recs = recs
        self.cache: dict[tuple[AhrsEskfConfig, int, bool], tuple[float, float, float]] = {}
        self.runs = 0

    def get(self, c: AhrsEskfConfig, i: int, nine: bool) -> tuple[float, float, float]:
        """Total / heading / inclination RMSE (deg) of config ``c`` on trial ``i``."""
        key_c = c if nine else replace(c, mag_noise_rad=OLD.mag_noise_rad)  # mag unused in 6D
        key = (key_c, i, nine)
        if key not in self.cache:
            r = self.recs[i]
            res = run_ahrs_eskf(
                r.gyr_b, r.acc_b, r.mag_b if nine else None, r.fs_hz, replace(c, use_mag=nine)
            )
            e = score(r, ned_to_enu_quat(res.q_nb), nine)
            self.cache[key] = (e.total_deg, e.heading_deg, e.inclination_deg)
            self.runs += 1
        return self.cache[key]

    def objective(self, c: AhrsEskfConfig, idx: Sequence[int]) -> float:
        """Mean over ``idx`` of the 9-axis and 6-axis total RMSE, deg."""
        return float(np.mean([0.5 * (self.get(c, i, True)[0] + self.get(c, i, False)[0]) for i in idx]))


def tune(sc: Scorer, idx: Sequence[int]) -> AhrsEskfConfig:
    """Coarse-to-fine search on the trials ``idx``."""
    names = list(COARSE)
    grid = [replace(OLD, **dict(zip(names, v, strict=True))) for v in itertools.product(*COARSE.values())]
    # the rest detector of this study (sources in AhrsEskfConfig), not tuned
    base = AhrsEskfConfig()
    grid = [
        replace(g, rest_max_rate_rad_s=base.rest_max_rate_rad_s, rest_acc_drift_m_s2=base.rest_acc_drift_m_s2)
        for g in grid
    ]
    best = min(grid, key=lambda c: sc.objective(c, idx))
    for _ in range(2):
        cand = [best, *_fine(best)]
        best = min(cand, key=lambda c: sc.objective(c, idx))
    return best


def _changed(c: AhrsEskfConfig) -> str:
    keys = (*COARSE, "acc_disagree_rad", "mag_noise_rad")
    return ", ".join(
        f"`{k}={getattr(c, k):g}`" if not isinstance(getattr(c, k), bool) else f"`{k}={getattr(c, k)}`"
        for k in keys
    )


def _cell(e: tuple[float, float, float]) -> str:
    return f"{e[0]:.2f} / {e[1]:.2f} / {e[2]:.2f}"


def run() -> str:
    """Run the study; return the markdown section."""
    files = sorted(data_dir().glob("[0-9][0-9]_*.npz"))
    if len(files) < 2:
        raise SystemExit(f"need the BROAD trials in {data_dir()}; set IOTNAV_DATASETS")
    t0 = time.perf_counter()
    recs = [load_broad(f) for f in files]
    names = [r.name[:2] for r in recs]
    sc = Scorer(recs)
    vqf = {(i, nine): score(r, run_vqf(r, nine), nine) for i, r in enumerate(recs) for nine in (True, False)}
    folds = {}
    for i in range(len(recs)):
        folds[i] = tune(sc, [j for j in range(len(recs)) if j != i])
        print(f"fold {names[i]}: {_changed(folds[i])}", flush=True)
    shipped = tune(sc, list(range(len(recs))))
    print(f"all: {_changed(shipped)}", flush=True)

    lines = ["## Attitude: leave-one-trial-out (BROAD)", ""]
    lines.append(
        "Each trial scored with `ahrs_eskf` parameters tuned on the other four (objective: mean of "
        "the 9-axis and 6-axis total RMSE; coarse grid "
        + ", ".join(f"`{k}` in {{{', '.join(str(v) for v in vals)}}}" for k, vals in COARSE.items())
        + ", then a fine pass: `acc_lp_tau_s` x0.75 / x1.25, `acc_disagree_rad=0.05`, "
        "`mag_noise_rad` in {1, 4}). VQF at its defaults. RMSE in degrees over the `movement` samples, "
        "total / heading / inclination; 9-axis raw, 6-axis after one constant heading offset. "
        "Produced by `benchmarks/bench_attitude_loo.py`."
    )
    lines.append("")
    for nine in (True, False):
        ax = "9D" if nine else "6D"
        lines += [
            f"### {ax}",
            "",
            f"| trial | ahrs_eskf {ax} held-out | vqf {ax} | total - vqf | ahrs_eskf {ax}, old parameters |",
            "|---|---|---|---|---|",
        ]
        held, vq, old = [], [], []
        for i, nm in enumerate(names):
            e = sc.get(folds[i], i, nine)
            v = vqf[(i, nine)]
            o = sc.get(OLD, i, nine)
            vt = (v.total_deg, v.heading_deg, v.inclination_deg)
            held.append(e)
            vq.append(vt)
            old.append(o)
            lines.append(f"| {nm} | {_cell(e)} | {_cell(vt)} | {e[0] - vt[0]:+.2f} | {_cell(o)} |")
        m = [tuple(np.mean(np.array(x), axis=0)) for x in (held, vq, old)]
        lines.append(
            f"| mean | **{_cell(m[0])}** | {_cell(m[1])} | {m[0][0] - m[1][0]:+.2f} | {_cell(m[2])} |"
        )
        lines.append("")
    lines += [
        "### Parameters per fold",
        "",
        "| held-out trial | parameters tuned on the others |",
        "|---|---|",
    ]
    lines += [f"| {names[i]} | {_changed(c)} |" for i, c in folds.items()]
    lines += [f"| (shipped default: all five) | {_changed(shipped)} |", ""]
    for nine in (True, False):
        fit = [sc.get(shipped, i, nine)[0] for i in range(len(recs))]
        old_mean = np.mean([sc.get(OLD, i, nine)[0] for i in range(len(recs))])
        lines.append(
            f"Shipped default, {'9D' if nine else '6D'}, on the five trials it was tuned on (in-sample): "
            + ", ".join(f"{nm} {v:.2f}" for nm, v in zip(names, fit, strict=True))
            + f", mean {np.mean(fit):.3f} (old parameters, also in-sample: {old_mean:.3f})."
        )
    lines.append("")

    # robustness case (never tuned on)
    syn = fast_translation_with_rest(recs[names.index("05")])
    lines += [
        "### Sustained acceleration and fooled rest (synthetic, from trial 05; not tuned on)",
        "",
        "Trial 05 plus fast translation strokes in its motion phases (bang-bang, 2-5 m/s^2 for "
        "0.4-1.5 s each way, random directions, seed 1) and, in its three rest breaks, a slow "
        "translation (0.3 m/s^2, 4 s period) with a slow turn about the vertical (3 deg/s): "
        "`iotnav.eval.attitude.fast_translation_with_rest`.",
        "",
        "| filter | 9D total / heading / inclination | 6D | rest flagged in the breaks (6D) |",
        "|---|---|---|---|",
    ]
    brk = rest_breaks(syn)
    for label, c in (("ahrs_eskf, shipped default", shipped), ("ahrs_eskf, old parameters", OLD)):
        cells = []
        rest_frac = 0.0
        for nine in (True, False):
            res = run_ahrs_eskf(
                syn.gyr_b, syn.acc_b, syn.mag_b if nine else None, syn.fs_hz, replace(c, use_mag=nine)
            )
            e = score(syn, ned_to_enu_quat(res.q_nb), nine)
            cells.append(_cell((e.total_deg, e.heading_deg, e.inclination_deg)))
            rest_frac = float(res.rest[brk].mean())
        lines.append(f"| {label} | {cells[0]} | {cells[1]} | {rest_frac:.0%} |")
    cells = []
    for nine in (True, False):
        e = score(syn, run_vqf(syn, nine), nine)
        cells.append(_cell((e.total_deg, e.heading_deg, e.inclination_deg)))
    lines.append(f"| vqf (defaults) | {cells[0]} | {cells[1]} | |")
    lines.append("")
    lines.append(f"{sc.runs} ahrs_eskf runs, {time.perf_counter() - t0:.0f} s.")
    lines.append("")
    return "\n".join(lines)


def main() -> None:
    """Print the table; write it with ``IOTNAV_WRITE_RESULTS=1``."""
    emit(run(), "attitude_loo")


if __name__ == "__main__":
    main()
