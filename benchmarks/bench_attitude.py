"""Attitude benchmark on BROAD: iotnav's filters beside VQF, Fusion, Madgwick and Mahony.

Runs every filter on every trial in ``$IOTNAV_DATASETS/broad_attitude`` (default
``../shared/datasets/broad_attitude`` beside the repository), scores them with BROAD's metric
(total / heading / inclination RMSE, degrees, movement samples; 9-axis raw, 6-axis after one
constant heading offset) and prints a markdown table. With ``IOTNAV_WRITE_RESULTS=1`` it also
writes ``benchmarks/results/attitude.md``.
"""

from __future__ import annotations

import os
import time
from importlib import metadata
from pathlib import Path

import numpy as np

from iotnav.eval.attitude import (
    BROAD_MADGWICK_BETA,
    BROAD_MAHONY_KI,
    BROAD_MAHONY_KP,
    FilterSpec,
    evaluate,
    iotnav_filters,
    load_broad,
    peer_filters,
)
from iotnav.techniques.ahrs_eskf import default_config

ROOT = Path(__file__).resolve().parents[1]

#: Upstream reference total/heading/inclination RMSE (deg) of BROAD's own C baselines.
UPSTREAM = {
    "Madgwick β=0.12": {
        "02": (1.50, 1.26, 0.80),
        "05": (1.79, 1.63, 0.72),
        "07": (5.00, 4.33, 2.50),
        "15": (12.30, 11.41, 4.62),
        "24": (1.77, 1.24, 1.26),
    },
    "Mahony Kp=0.74 Ki=0.0012": {
        "02": (2.97, 2.89, 0.66),
        "05": (4.01, 3.93, 0.78),
        "07": (5.23, 4.90, 1.84),
        "15": (9.20, 6.95, 6.04),
        "24": (2.15, 1.89, 1.01),
    },
}


def data_dir() -> Path:
    """The BROAD folder."""
    env = os.environ.get("IOTNAV_DATASETS")
    base = Path(env) if env else ROOT.parent / "shared" / "datasets"
    return base / "broad_attitude"


def _version(pkg: str) -> str:
    try:
        return metadata.version(pkg)
    except metadata.PackageNotFoundError:
        return "not installed"


def run() -> str:
    """Run the benchmark; return the markdown section."""
    files = sorted(data_dir().glob("[0-9][0-9]_*.npz"))
    if not files:
        raise SystemExit(f"no BROAD trials in {data_dir()}; set IOTNAV_DATASETS")
    recs = [load_broad(f) for f in files]
    trials = [r.name[:2] for r in recs]
    groups: list[tuple[str, list[FilterSpec]]] = [
        ("9-axis (magnetometer; raw error, no alignment)", iotnav_filters(True) + peer_filters(True)),
        (
            "6-axis (no magnetometer; inclination raw, total/heading after one constant heading offset)",
            iotnav_filters(False) + peer_filters(False),
        ),
    ]
    lines = ["## Attitude (BROAD)", ""]
    lines.append(
        "BROAD (Laidig et al. 2021, CC BY 4.0), 5 trials at 285.7 Hz; RMSE in degrees over the "
        "`movement` samples as total / heading / inclination. Peers at their documented defaults "
        f"and, where BROAD gives them, at BROAD's tuned values (Madgwick β={BROAD_MADGWICK_BETA}, "
        f"Mahony Kp={BROAD_MAHONY_KP} Ki={BROAD_MAHONY_KI}). Versions: vqf {_version('vqf')}, "
        f"imufusion {_version('imufusion')}, ahrs {_version('ahrs')}."
    )
    lines.append("")
    best: dict[str, tuple[str, float]] = {}
    for title, specs in groups:
        lines += [f"### {title}", ""]
        head = "| filter | " + " | ".join(trials) + " | mean | time, s |"
        lines += [head, "|" + "---|" * (len(trials) + 3)]
        for spec in specs:
            t0 = time.perf_counter()
            try:
                errs = [evaluate(r, spec) for r in recs]
            except Exception as exc:  # a peer package missing or failing: report, go on
                lines.append(f"| {spec.name} | failed: {type(exc).__name__}: {exc} |")
                continue
            dt = time.perf_counter() - t0
            arr = np.array([(e.total_deg, e.heading_deg, e.inclination_deg) for e in errs])
            cells = [f"{a:.2f} / {b:.2f} / {c:.2f}" for a, b, c in arr]
            m = arr.mean(axis=0)
            lines.append(
                f"| {spec.name} | "
                + " | ".join(cells)
                + f" | **{m[0]:.2f}** / {m[1]:.2f} / {m[2]:.2f} | {dt:.1f} |"
            )
            key = title[:6]
            if not spec.name.startswith("iotnav") and (key not in best or m[0] < best[key][1]):
                best[key] = (spec.name, float(m[0]))
            print(lines[-1], flush=True)
        lines.append("")
    lines += ["### Upstream reference (BROAD's own C baselines, 9-axis)", ""]
    lines += ["| filter | " + " | ".join(trials) + " | mean |", "|" + "---|" * (len(trials) + 2)]
    for name, rows in UPSTREAM.items():
        vals = [rows.get(t, (np.nan,) * 3) for t in trials]
        mean = np.nanmean(np.array(vals), axis=0)
        lines.append(
            f"| {name} | "
            + " | ".join(f"{a:.2f} / {b:.2f} / {c:.2f}" for a, b, c in vals)
            + f" | {mean[0]:.2f} / {mean[1]:.2f} / {mean[2]:.2f} |"
        )
    lines.append("")
    lines.append(
        "Best peer by mean total RMSE: " + "; ".join(f"{k}: {n} ({v:.2f}°)" for k, (n, v) in best.items())
    )
    lines.append("")
    lines.append(
        "iotnav ahrs_eskf parameters (the shipped defaults, tuned on all five trials; the "
        "leave-one-trial-out figures are in the next section), 9-axis: "
        + ", ".join(f"`{k}={v}`" for k, v in default_config(True).as_dict().items())
        + "; 6-axis differs in: "
        + ", ".join(
            f"`{k}={v}`"
            for k, v in default_config(False).as_dict().items()
            if v != default_config(True).as_dict()[k]
        )
    )
    lines.append("")
    return "\n".join(lines)


def emit(md: str, name: str) -> None:
    """Print a section; with ``IOTNAV_WRITE_RESULTS=1`` also write ``benchmarks/results/<name>.md``."""
    print(md)
    if os.environ.get("IOTNAV_WRITE_RESULTS") == "1":
        dest = ROOT / "benchmarks" / "results" / f"{name}.md"
        dest.parent.mkdir(parents=True, exist_ok=True)
        dest.write_text(md + "\n")
        print(f"wrote {dest}")


def main() -> None:
    """Print the table; write it with ``IOTNAV_WRITE_RESULTS=1``."""
    emit(run(), "attitude")


if __name__ == "__main__":
    main()
