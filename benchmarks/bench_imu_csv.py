"""Benchmark: read a day of 100 Hz IMU CSV (8.64 million rows) with :func:`read_imu_csv`.

Generates a seeded header-less file in the rtklibexplorer layout (g, deg/s, ms tick) in a
temporary directory, reads it three times (each in a fresh process, so peak RSS is per read),
and prints a markdown snippet with rows/s, wall time (median of 3) and peak RSS. With
``IOTNAV_WRITE_RESULTS=1`` the snippet is written to ``benchmarks/results/imu_csv.md``.

Run: ``.venv/bin/python benchmarks/bench_imu_csv.py [n_rows]``
"""

from __future__ import annotations

import json
import os
import platform
import statistics
import subprocess
import sys
import tempfile
from pathlib import Path
from typing import Any

import numpy as np
import pyarrow as pa
import pyarrow.csv as pacsv

N_ROWS = 8_640_000  # 24 h at 100 Hz
SEED = 20250708

_CHILD = r"""
import json, resource, sys, time
from iotnav.io.imu_csv import read_imu_csv
t0 = time.perf_counter()
part = read_imu_csv(sys.argv[1], preset="rtklib-demo5")
wall = time.perf_counter() - t0
rss_mb = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0
print(json.dumps({"wall_s": wall, "rows": len(part.imu), "peak_rss_mb": rss_mb,
                  "skipped": dict(part.report.skipped)}))
"""


def make_file(path: Path, n: int, seed: int = SEED) -> None:
    """Write ``n`` rows: acc (g), gyro (deg/s) with 3 decimals, tick in ms at 100 Hz, plus the
    damage a real logger produces: a truncated first and last line."""
    rng = np.random.default_rng(seed)
    cols = {}
    for i, mean in enumerate((0.1, 0.02, 1.0)):
        cols[f"a{i}"] = pa.array(np.round(rng.normal(mean, 0.02, n), 3))
    for i in range(3):
        cols[f"w{i}"] = pa.array(np.round(rng.normal(0.0, 0.5, n), 3))
    cols["tick"] = pa.array(261906 + 10 * np.arange(n, dtype=np.int64))
    with open(path, "wb") as f:
        f.write(b"0.007,1.011,0.038,-0.160,0.160,261896\n")  # truncated first line (6 fields)
        pacsv.write_csv(pa.table(cols), f, write_options=pacsv.WriteOptions(include_header=False))
        f.write(b"0.012,-0.042,1.009,0.015,-0.084,")  # truncated last line


def measure(n: int = N_ROWS) -> dict[str, Any]:
    """Write the file, read it 3 times in fresh processes; median wall time and peak RSS."""
    with tempfile.TemporaryDirectory() as d:
        path = Path(d) / "imu_day.csv"
        make_file(path, n)
        size_mb = path.stat().st_size / 1e6
        runs = []
        for _ in range(3):
            out = subprocess.run(
                [sys.executable, "-c", _CHILD, str(path)], check=True, capture_output=True, text=True
            ).stdout
            runs.append(json.loads(out.strip().splitlines()[-1]))
    assert all(r["rows"] == n for r in runs), runs
    wall = statistics.median(r["wall_s"] for r in runs)
    rss = max(r["peak_rss_mb"] for r in runs)
    return {
        "rows": n,
        "size_mb": size_mb,
        "wall_s": wall,
        "peak_rss_mb": rss,
        "runs": [r["wall_s"] for r in runs],
    }


def main() -> None:
    n = int(sys.argv[1]) if len(sys.argv) > 1 else N_ROWS
    r = measure(n)
    size_mb, wall, rss = r["size_mb"], r["wall_s"], r["peak_rss_mb"]
    runs = [{"wall_s": w} for w in r["runs"]]
    snippet = "\n".join(
        [
            "## read_imu_csv: a day of 100 Hz IMU CSV",
            "",
            f"- rows: {n:,} ({size_mb:.0f} MB, header-less rtklib-demo5 layout, 2 truncated lines)",
            f"- wall time (median of 3, fresh process each): {wall:.2f} s",
            f"- throughput: {n / wall / 1e6:.2f} M rows/s",
            f"- peak RSS (max of 3, includes interpreter and libraries): {rss:.0f} MB",
            "- runs: " + ", ".join(f"{r['wall_s']:.2f} s" for r in runs),
            f"- machine: {platform.machine()}, {os.cpu_count()} CPUs, Python {platform.python_version()}, "
            f"pyarrow {pa.__version__}",
            "",
        ]
    )
    print(snippet)


if __name__ == "__main__":
    main()
