"""Assemble BENCHMARKS.md from the sections the benchmark scripts wrote to benchmarks/results/.

Each ``benchmarks/bench_*.py`` script, run with ``IOTNAV_WRITE_RESULTS=1``, writes its own
markdown section to ``benchmarks/results/<name>.md``; this script puts them together in a fixed
order under a header that notes the machine. Run ``make bench`` to regenerate everything.
"""

from __future__ import annotations

import os
import platform
from datetime import UTC, datetime
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
RESULTS = ROOT / "benchmarks" / "results"
ORDER = [
    "ingest",
    "nmea",
    "imu_csv",
    "gpsd_conformance",
    "sim",
    "pipeline",
    "engines",
    "attitude",
    "attitude_loo",
    "characterize",
    "nodes",
]


def machine() -> str:
    """One line describing the machine (CPU model, cores, Python); the benchmark scripts share it."""
    cpu = platform.processor() or platform.machine()
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                cpu = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    return f"{cpu}, {os.cpu_count()} cores, Python {platform.python_version()}"


def main() -> None:
    """Write BENCHMARKS.md."""
    # *_history.md are records of past experiments (moved out of the engines' docstrings), not
    # figures of the current code: they stay beside the results, out of BENCHMARKS.md.
    files = {p.stem: p for p in RESULTS.glob("*.md") if not p.stem.endswith("_history")}
    names = [n for n in ORDER if n in files] + sorted(n for n in files if n not in ORDER)
    parts = [
        "# iotnav benchmarks\n",
        "Measured figures only: every section below is written by the script named in it "
        "(`benchmarks/bench_*.py`, or `make bench` for all). Machines are shared and noisy: "
        "speed figures are medians of repeated runs, compared side by side within one run.\n",
        f"Assembled {datetime.now(UTC):%Y-%m-%d %H:%M} UTC. Machine: {machine()}, {platform.system()}.\n",
    ]
    for n in names:
        parts.append(files[n].read_text().strip() + "\n")
    (ROOT / "BENCHMARKS.md").write_text("\n".join(parts))
    print(f"wrote BENCHMARKS.md ({len(names)} sections: {', '.join(names)})")


if __name__ == "__main__":
    main()
