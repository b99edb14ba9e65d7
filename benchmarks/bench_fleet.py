"""Benchmark ``iotnav run-many``: devices per minute with 1 and 2 local workers (and Dask).

Prints a markdown section; with ``IOTNAV_WRITE_RESULTS=1`` also writes
``benchmarks/results/fleet.md``.

A fleet of ``--devices`` simulated ``car-tunnel`` drives of ``--duration`` seconds (100 Hz IMU,
1 Hz GNSS, different seeds) is written once, then processed with :func:`iotnav.fleet.run_fleet`
(engine ``pipeline``) by a local pool of 1 and of 2 worker processes and, when Dask is
installed, by a local Dask cluster of 2 single-threaded worker processes. Wall time covers the
whole run, worker start-up (spawn and imports, about 2 s per worker) included; Dask's cluster
start-up is not. Median of ``--repeats`` runs, the configurations interleaved
(1, 2, Dask, 1, 2, Dask, ...) so that a change of load on a shared machine hits all alike.

Usage::

    python benchmarks/bench_fleet.py [--devices 8] [--duration 120] [--repeats 3]
"""

from __future__ import annotations

import argparse
import os
import shutil
import statistics
import tempfile
from contextlib import ExitStack
from pathlib import Path
from typing import Any

from assemble import machine
from iotnav import sim
from iotnav.fleet import FleetResult, discover_devices, run_fleet


def _row(label: str, runs: list[FleetResult], n: int) -> dict[str, Any]:
    walls = [r.wall_s for r in runs]
    w = statistics.median(walls)
    row = {
        "label": label,
        "workers": runs[0].workers,
        "wall_s": w,
        "walls": walls,
        "devices_per_min": 60.0 * n / w,
        "imu_sps": statistics.median(r.imu_samples_per_s for r in runs),
    }
    print(f"{label}: {row}")
    return row


def _measure(
    root: Path, work: Path, configs: dict[str, dict[str, Any]], repeats: int
) -> list[dict[str, Any]]:
    """Run every configuration ``repeats`` times, interleaved so that load drift hits all alike."""
    jobs = discover_devices([root])
    runs: dict[str, list[FleetResult]] = {label: [] for label in configs}
    for k in range(repeats):
        for label, kw in configs.items():
            out = work / f"run-{k}"
            res = run_fleet(jobs, out, "pipeline", **kw)
            if res.failed:
                raise RuntimeError(f"{label}: {res.failures()}")
            runs[label].append(res)
            shutil.rmtree(out)
    return [_row(label, r, len(jobs)) for label, r in runs.items()]


def main() -> None:
    """Run the benchmark and print (and optionally write) the markdown section."""
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--devices", type=int, default=8)
    ap.add_argument("--duration", type=float, default=120.0, help="simulated seconds per device")
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--no-dask", action="store_true")
    args = ap.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        work = Path(tmp)
        root = work / "fleet"
        for i in range(args.devices):
            sim.write(
                sim.build("car-tunnel", seed=i, overrides={"duration_s": args.duration}), root / f"car{i:03d}"
            )
        configs: dict[str, dict[str, Any]] = {
            "local pool, 1 worker": {"workers": 1},
            "local pool, 2 workers": {"workers": 2},
        }
        with ExitStack() as stack:
            if not args.no_dask:
                try:
                    from distributed import LocalCluster
                except ImportError:
                    print("Dask: not installed")
                else:
                    cluster = stack.enter_context(
                        LocalCluster(
                            n_workers=2, threads_per_worker=1, processes=True, dashboard_address=None
                        )
                    )
                    configs["Dask LocalCluster, 2 worker processes"] = {
                        "scheduler": cluster.scheduler_address
                    }
            rows = _measure(root, work, configs, args.repeats)
    base = rows[0]["devices_per_min"]
    imu_per_device = int(args.duration * 100)
    lines = [
        "## Fleet processing (`iotnav run-many`, `benchmarks/bench_fleet.py`)",
        "",
        f"Machine: {machine()}; shared with other jobs, so the scaling is a lower bound.",
        "",
        f"{args.devices} devices, each a simulated `car-tunnel` drive of {args.duration:g} s "
        f"({imu_per_device:,} IMU samples at 100 Hz, {int(args.duration) + 1} GNSS epochs), engine "
        f"`pipeline`, outputs written as `iotnav run` writes them. Median of {args.repeats} runs "
        "(configurations interleaved); "
        "wall time includes worker start-up (spawn and imports).",
        "",
        "| executor | workers | wall s | devices per minute | speed-up | IMU samples/s |",
        "|---|---:|---:|---:|---:|---:|",
    ]
    for r in rows:
        lines.append(
            f"| {r['label']} | {r['workers']} | {r['wall_s']:.1f} | {r['devices_per_min']:.1f} | "
            f"{r['devices_per_min'] / base:.2f} | {r['imu_sps']:,.0f} |"
        )
    lines.append("")
    text = "\n".join(lines)
    print(text)
    if os.environ.get("IOTNAV_WRITE_RESULTS") == "1":
        out = Path(__file__).parent / "results" / "fleet.md"
        out.parent.mkdir(parents=True, exist_ok=True)
        out.write_text(text)


if __name__ == "__main__":
    main()
