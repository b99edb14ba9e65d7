"""Benchmark the scenario simulator: seconds to build and write two scenarios.

Prints a markdown snippet; with ``IOTNAV_WRITE_RESULTS=1`` also writes
``benchmarks/results/sim.md``. Targets: each under 10 s.
"""

from __future__ import annotations

import os
import platform
import tempfile
import time
from pathlib import Path

from iotnav import sim

CASES = (
    ("static-courtyard", {}, "90 min static, truth 200 Hz, IMU 4 Hz, GNSS 1 Hz"),
    ("car-tunnel", {}, "10 min driving, truth 200 Hz, IMU 100 Hz, GNSS 1 Hz"),
)


def main() -> None:
    rows = []
    for name, overrides, what in CASES:
        with tempfile.TemporaryDirectory() as d:
            t0 = time.perf_counter()
            r = sim.build(name, seed=0, overrides=overrides)
            t1 = time.perf_counter()
            sim.write(r, Path(d))
            t2 = time.perf_counter()
        rows.append(f"| `{name}` | {what} | {t1 - t0:.2f} | {t2 - t1:.2f} | {t2 - t0:.2f} |")
    text = "\n".join(
        [
            "## Simulator (`iotnav simulate`)",
            "",
            f"Machine: {platform.processor() or platform.machine()}, {os.cpu_count()} cores, "
            f"Python {platform.python_version()}.",
            "",
            "| scenario | content | build s | write s | total s (target < 10) |",
            "|---|---|---:|---:|---:|",
            *rows,
            "",
        ]
    )
    print(text)
    if os.environ.get("IOTNAV_WRITE_RESULTS") == "1":
        out = Path(__file__).parent / "results" / "sim.md"
        out.parent.mkdir(parents=True, exist_ok=True)
        out.write_text(text)


if __name__ == "__main__":
    main()
