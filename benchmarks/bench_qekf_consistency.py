"""Monte Carlo consistency study of the quaternion EKF: 20 runs per form, two seed sets.

Each row runs :func:`iotnav.eval.qekf_mc.monte_carlo` (75 s simulated car drives with a
magnetometer, positions only, NEES and NIS from 20 s on) for one form of the filter: the paper's
form with white GNSS errors; the paper's form on the simulator's correlated receiver error, with
and without the ``gnss_error_states`` option; :meth:`QekfConfig.consistent` on both kinds of
error. Seeds 100-119 were used while designing the filter (``triad_max_comp_mps2`` was chosen on
them); seeds 200-219 were looked at only afterwards. The test suite runs 8 of the held-out seeds
per form (``tests/test_qekf_consistency.py``); this is the whole study, about 15 CPU minutes.

Known (measured on seeds 100-119 when these were tests): the paper's form is not white,
Box-Pierce 94.5 / 52.4 / 21.8 (N / E / D) against 21.7, and with its GNSS error states on the
receiver error 443 / 957 / 22.9. Causes, switched one at a time (module docstring of
:mod:`iotnav.engines.qekf`): the World Magnetic Model reference 0.3 deg of declination off the
simulator's field (with the simulator's field 16.0 / 24.4 / 22.9, and 140 / 683 / 21.8 with the
error states), the accelerometer's turn-on bias through the TRIAD observations made while
driving (also without it 13.8 / 8.2 / 22.7; 48 / 144 / 23), the unmodelled cross-axis coupling
and the accelerometer white noise of 0.1 m/s^2/sqrt(Hz), too large, which makes the vertical
lags negative. The consistent form is white on the same runs.

Part ``seeds``: the full ``car-magnetometer`` drive (40 s static, 220 s of town driving, the
4 s gap, the magnetic disturbance) on seeds 0-8 for the paper's and the consistent form:
attitude RMS and the gap's largest error; the suite's ``tests/test_qekf.py`` runs the seeds
with the least margin (targets: roll/pitch below 1 deg, yaw below 2 deg, gap below 5 m).

Run: ``.venv/bin/python benchmarks/bench_qekf_consistency.py [--part mc,seeds] [--seeds 100,200]
[--runs 20]``;
with ``IOTNAV_WRITE_RESULTS=1`` the markdown is written to
``benchmarks/results/qekf_consistency.md``.
"""

from __future__ import annotations

import argparse
import os
import platform
import tempfile
import time
from pathlib import Path

import numpy as np

from iotnav.eval.consistency import innovation_autocorrelation
from iotnav.eval.qekf_mc import car_seed_run, monte_carlo

#: (name, receiver error, gnss_error_states, consistent form)
FORMS = (
    ("paper, white error", False, False, False),
    ("paper, receiver error", True, False, False),
    ("paper + GNSS error states, receiver error", True, True, False),
    ("consistent, white error", False, False, True),
    ("consistent + GNSS error states, receiver error", True, True, True),
)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", default="100,200", help="first seeds of the seed sets, comma-separated")
    ap.add_argument("--runs", type=int, default=20, help="runs per seed set")
    ap.add_argument("--part", default="mc,seeds", help="mc (Monte Carlo), seeds (full drives), or both")
    args = ap.parse_args()
    parts = set(args.part.split(","))
    header = (
        "| form | seeds | mean NEES (6 dof) | 95 % interval | mean NIS (3 dof) | 95 % interval "
        "| Box-Pierce N / E / D (lags 1-10) | threshold (N/E/D together, 95 %) | max abs lag corr | CPU (s) |"
    )
    md = [
        "# qekf Monte Carlo consistency (Bar-Shalom et al. 2001, sec. 5.4-5.5)",
        "",
        "Regenerate: `IOTNAV_WRITE_RESULTS=1 .venv/bin/python benchmarks/bench_qekf_consistency.py`.",
        f"Machine: {platform.machine()}, Python {platform.python_version()}.",
        "",
        f"{args.runs} runs per row (75 s simulated car drive with a magnetometer, positions only, from",
        "20 s on). Interval: the run-average of a chi-square statistic, `chi2(dof N) / N`. Box-Pierce",
        "`Q = sum_l n_l rho_l^2` of the whitened GNSS-position innovations against chi-square(10) with",
        "the three components together at 95 %. Seeds 100-119 were used in the design; 200-219 are held",
        "out. The paper's form is not white (known, see the module docstring of `iotnav.engines.qekf`);",
        "the consistent form is the one the tests hold to white innovations.",
        "",
        header,
        "|" + "---|" * (header.count("|") - 1),
    ]
    for first in (int(s) for s in args.seeds.split(",")) if "mc" in parts else ():
        for name, receiver, states, consistent in FORMS:
            t0 = time.process_time()
            mc = monte_carlo(first, args.runs, receiver, states, consistent)
            ac = innovation_autocorrelation(mc.white, np.arange(1, 11))
            lo6, hi6 = mc.interval(6)
            lo3, hi3 = mc.interval(3)
            bp = " / ".join(f"{q:.1f}" for q in ac.portmanteau)
            cells = [
                name,
                f"{first}-{first + args.runs - 1}",
                f"{mc.nees.mean():.2f}",
                f"{lo6:.2f}-{hi6:.2f}",
                f"{mc.nis.mean():.2f}",
                f"{lo3:.2f}-{hi3:.2f}",
                bp,
                f"{ac.portmanteau_threshold(familywise=True):.1f}",
                f"{np.abs(ac.rho).max():.2f}",
                f"{time.process_time() - t0:.0f}",
            ]
            md.append("| " + " | ".join(cells) + " |")
            print(md[-1], flush=True)
    if "seeds" in parts:
        md += [
            "",
            "Full car-magnetometer drives (forward filter, from 41 s): attitude RMS (deg) and the 4 s",
            "gap's largest horizontal error (m). Targets: roll/pitch < 1, yaw < 2, gap < 5.",
            "",
            "| form | seed | roll | pitch | yaw | gap max (m) | CPU (s) |",
            "|---|---|---|---|---|---|---|",
        ]
        with tempfile.TemporaryDirectory() as tmp:
            for consistent in (False, True):
                for seed in range(9):
                    t0 = time.process_time()
                    m = car_seed_run(Path(tmp) / f"{int(consistent)}_{seed}", seed, consistent)
                    cells = [
                        "consistent" if consistent else "paper",
                        str(seed),
                        *(f"{m[k]:.2f}" for k in ("roll", "pitch", "yaw", "gap_max_m")),
                        f"{time.process_time() - t0:.0f}",
                    ]
                    md.append("| " + " | ".join(cells) + " |")
                    print(md[-1], flush=True)
    text = "\n".join(md) + "\n"
    print(text)
    if os.environ.get("IOTNAV_WRITE_RESULTS") == "1":
        (Path(__file__).parent / "results" / "qekf_consistency.md").write_text(text)


if __name__ == "__main__":
    main()
