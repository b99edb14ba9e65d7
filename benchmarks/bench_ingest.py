"""Ingest speed: a day of 1 Hz NMEA and a day of 100 Hz IMU CSV, side by side in one run.

Targets (issue #2): about 500,000 NMEA sentences in under 5 s; 8.6 million IMU CSV rows in
under 10 s and under 2 GB of memory. The inputs are synthesised from real layouts (see
``bench_nmea.py`` and ``bench_imu_csv.py``). Prints a markdown section; with
``IOTNAV_WRITE_RESULTS=1`` writes it to ``benchmarks/results/ingest.md``.

Run: ``.venv/bin/python benchmarks/bench_ingest.py``
"""

from __future__ import annotations

import os
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).parent))

import bench_imu_csv
import bench_nmea


def main() -> None:
    """Measure both readers and print (and optionally write) the section."""
    nm = bench_nmea.measure()
    imu = bench_imu_csv.measure()
    n, w = nm["sentences"], nm["wall_s"]
    rows, wi, rss = imu["rows"], imu["wall_s"], imu["peak_rss_mb"]
    lines = [
        "## Ingest speed (`benchmarks/bench_ingest.py`)",
        "",
        "| input | size | median wall time (3 runs) | rate | peak memory | target | met |",
        "|---|---|---|---|---|---|---|",
        f"| a day of 1 Hz NMEA (`read_nmea`, GGA+GSA+RMC+GSV) | {n:,} sentences | {w:.2f} s | "
        f"{n / w:,.0f} sentences/s | - | < 5 s | {'yes' if w < 5 else 'no'} |",
        f"| a day of 100 Hz IMU CSV (`read_imu_csv`) | {rows:,} rows, {imu['size_mb']:.0f} MB | {wi:.2f} s | "
        f"{rows / wi / 1e6:.2f} M rows/s | {rss:.0f} MB | < 10 s, < 2 GB | "
        f"{'yes' if wi < 10 and rss < 2048 else 'no'} |",
        "",
        f"NMEA runs: {', '.join(f'{x:.2f}' for x in nm['runs'])} s; pynmeagps alone parses "
        f"{nm['pynmeagps_rate']:,.0f} sentences/s ({n / nm['pynmeagps_rate']:.1f} s for the day), which is why "
        "GGA/RMC/GSA/VTG take a vectorised path tested equal to pynmeagps on the gpsd corpus. "
        f"IMU runs: {', '.join(f'{x:.2f}' for x in imu['runs'])} s, each in a fresh process (peak RSS includes "
        "the interpreter and libraries).",
        "",
    ]
    text = "\n".join(lines)
    print(text)
    if os.environ.get("IOTNAV_WRITE_RESULTS") == "1":
        out = Path(__file__).parent / "results" / "ingest.md"
        out.parent.mkdir(parents=True, exist_ok=True)
        out.write_text(text)


if __name__ == "__main__":
    main()
