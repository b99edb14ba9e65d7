"""Real-data GNSS-outage benchmark (issue #5): rtklibexplorer drive_0708 and walk_0827.

Run: ``.venv/bin/python benchmarks/bench_outages.py``; with ``IOTNAV_WRITE_RESULTS=1`` the
markdown is written to ``benchmarks/results/outages.md``. The same tables come from
``iotnav study outages DATASET --markdown FILE`` (one recording per call).
"""

from __future__ import annotations

import os
import platform
import time
from pathlib import Path

from iotnav.cli.outages import load_dataset
from iotnav.eval.outages import OutageConfig, format_markdown, rtk_truth, study

DATA = Path("/work/shared/datasets/rtklibexplorer_gnss_imu")

# the walk's moving part is ~100 s: 15 and 30 s windows every 30 s from 30 s in
RUNS = {
    "drive_0708": OutageConfig(),
    "walk_0827": OutageConfig(lengths_s=(15.0, 30.0), spacing_s=30.0, first_offset_s=30.0),
}
COMMANDS = {
    "drive_0708": "iotnav study outages {d}/drive_0708",
    "walk_0827": "iotnav study outages {d}/walk_0827 --lengths 15,30 --spacing-s 30 --first-offset-s 30",
}


def main() -> None:
    md = [
        "# Real-data GNSS outages (issue #5)",
        "",
        "Regenerate: `IOTNAV_WRITE_RESULTS=1 .venv/bin/python benchmarks/bench_outages.py`, or per recording",
        "",
        *(f"    {c.format(d=DATA)} --markdown FILE" for c in COMMANDS.values()),
        "",
        f"Machine: {platform.machine()}, Python {platform.python_version()}.",
        "",
        "Protocol (:mod:`iotnav.eval.outages`): the RTK solution is the truth, untouched; the engines get it",
        "thinned to 1 Hz and degraded by the simulator's `open-sky` receiver model (Gauss-Markov error of",
        "minutes through a 2 s receiver filter, Doppler-like velocity noise), seeded. One run per (length,",
        "start): only that window's fixes are removed; windows start every 60 s of the moving part (RTK",
        "speed > 0.5 m/s; static start and end left out), the first 60 s after motion begins (no",
        "magnetometer: the heading is unknown before the vehicle has moved). Drift = horizontal error at",
        "the last output before the window ends, in % of the true distance travelled in it. RMS outside",
        "outages: every output outside a window, from the run of the preceding window (its recovery).",
        "`gnss-hold`: GNSS alone holding the last fix (at the 4 Hz truth epochs). Target for `eskf`:",
        "median drift <= 2 % on 30 s outages (drive).",
        "",
    ]
    for name, cfg in RUNS.items():
        folder = DATA / name
        if not folder.exists():
            md += [f"({name} not available)", ""]
            continue
        log, prof = load_dataset(folder)
        t0 = time.perf_counter()
        res = study(log, rtk_truth(log.gnss), prof, cfg)
        md += [format_markdown(res), f"({time.perf_counter() - t0:.0f} s for this recording)", ""]
        print(md[-3], flush=True)
    text = "\n".join(md)
    print(text)
    if os.environ.get("IOTNAV_WRITE_RESULTS") == "1":
        (Path(__file__).parent / "results" / "outages.md").write_text(text)


if __name__ == "__main__":
    main()
