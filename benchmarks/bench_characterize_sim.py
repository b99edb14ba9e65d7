"""Benchmark: ``characterize`` on the simulator's ``static-imu-6h`` log, over many seeds (issue #6).

The simulator's ``static-imu-6h`` scenario (Microstrain 3DM-GX3-35 preset, in-run bias as flicker
noise, :func:`iotnav.sim.imu_model.flicker_noise`) is built for ``SEEDS`` seeds, each 6 hours
long, and :func:`iotnav.techniques.allan.characterize` is run on its IMU table. For every seed the
recovered noise density ``N`` and bias instability ``B`` (whole-curve weighted least-squares fit,
:func:`iotnav.techniques.allan.fit_allan`) are compared with the configured preset
values (datasheet: gyro N = 30 mdps/sqrt(Hz), B = 18 deg/h; accel N = 80 ug/sqrt(Hz), B = 40 ug).

Reported per sensor: per-axis ``B`` within 10 % (fraction of identified axes and of all axes),
the fraction of axes where ``B`` is identified at all, the :class:`NoiseModel` value (largest
identified axis) within 10 %, the mean over identified axes within 10 % (and 20 %), and the mean and spread
of the per-axis ratio. The sample rate is lowered to 10 Hz (second argument) to keep the sweep short:
it changes nothing at ``tau >= 1 s``, where ``N`` and ``B`` are determined.

Run: ``.venv/bin/python benchmarks/bench_characterize_sim.py [n_seeds] [rate_hz]``; with
``IOTNAV_WRITE_RESULTS=1`` the markdown goes to ``benchmarks/results/characterize_sim.md``;
``IOTNAV_BENCH_QUICK=1`` uses 8 seeds.
"""

from __future__ import annotations

import math
import os
import sys
import time
from pathlib import Path

import numpy as np

from iotnav import sim
from iotnav.techniques.allan import characterize

DEG = math.pi / 180.0
UG = 9.80665e-6
#: Configured (preset) values, written out from the datasheet, not read from the code.
CONFIGURED = {
    "gyro": {"N": 30e-3 * DEG, "B": 18.0 * DEG / 3600.0, "unit_n": DEG * 1e-3, "unit_b": DEG / 3600.0},
    "accel": {"N": 80.0 * UG, "B": 40.0 * UG, "unit_n": UG, "unit_b": UG},
}
FIRST_SEED = 1000


def run(n_seeds: int, rate_hz: float) -> str:
    """Sweep ``n_seeds`` seeds and return the markdown section."""
    rows: dict[str, dict[str, list[float]]] = {
        k: {"b_axis": [], "n_axis": [], "b_model": [], "b_mean": [], "n_model": [], "b_rel_sd": []}
        for k in CONFIGURED
    }
    t0 = time.perf_counter()
    for seed in range(FIRST_SEED, FIRST_SEED + n_seeds):
        r = sim.build(
            "static-imu-6h", seed=seed, overrides={"truth_rate_hz": rate_hz, "imu.rate_hz": rate_hz}
        )
        imu = r.imu
        res = characterize(
            imu["t"].to_numpy(),
            imu[["acc_x", "acc_y", "acc_z"]].to_numpy(),
            imu[["gyro_x", "gyro_y", "gyro_z"]].to_numpy(),
        )
        for kind, params, model_b, model_n in (
            ("gyro", res.gyro_params, res.model.gyro_bias_instability, res.model.gyro_noise_density),
            ("accel", res.acc_params, res.model.accel_bias_instability, res.model.accel_noise_density),
        ):
            c = CONFIGURED[kind]
            b = np.array([p.bias_instability for p in params]) / c["B"]
            rows[kind]["b_axis"].extend(b.tolist())
            rows[kind]["b_rel_sd"].extend(p.bias_instability_sigma / p.bias_instability_fit for p in params)
            rows[kind]["n_axis"].extend((np.array([p.noise_density for p in params]) / c["N"]).tolist())
            rows[kind]["b_model"].append(model_b / c["B"])
            rows[kind]["n_model"].append(model_n / c["N"])
            rows[kind]["b_mean"].append(float(np.nanmean(b)) if np.any(np.isfinite(b)) else math.nan)
    elapsed = time.perf_counter() - t0

    def within(x: list[float], tol: float = 0.10) -> str:
        a = np.array(x)
        return f"{int(np.sum(np.abs(a - 1.0) < tol))}/{len(a)}"

    lines = [
        "## characterize on the simulator's static-imu-6h log (seed sweep)",
        "",
        f"{n_seeds} seeds ({FIRST_SEED}..{FIRST_SEED + n_seeds - 1}), 6 h at {rate_hz:g} Hz each, "
        f"3DM-GX3-35 preset with flicker bias instability; {elapsed:.1f} s in all. Ratios are "
        "recovered / configured (gyro N 30 mdps/rtHz, B 18 deg/h; accel N 80 ug/rtHz, B 40 ug); "
        '"within 10 %" counts |ratio - 1| < 0.10, NaN (not identified) counts as a miss.',
        "",
        "| sensor | N per axis within 10 % | B identified (axes) | B per axis within 10 % "
        "| B per-axis ratio mean +/- std | NoiseModel B (max over axes) within 10 % "
        "| mean-over-axes B within 10 % | within 20 % | B reported 1-sigma (mean, relative) |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for kind, d in rows.items():
        b = np.array(d["b_axis"])
        ok = np.isfinite(b)
        lines.append(
            f"| {kind} | {within(d['n_axis'])} | {int(ok.sum())}/{len(b)} | {within(d['b_axis'])} "
            f"| {np.mean(b[ok]):.3f} +/- {np.std(b[ok]):.3f} | {within(d['b_model'])} "
            f"| {within(d['b_mean'])} | {within(d['b_mean'], 0.20)} | {np.mean(d['b_rel_sd']):.3f} |"
        )
    both = np.mean(
        (np.abs(np.array(rows["gyro"]["b_mean"]) - 1.0) < 0.10)
        & (np.abs(np.array(rows["accel"]["b_mean"]) - 1.0) < 0.10)
    )
    lines += ["", f"Seeds where the mean-over-axes B of both sensors is within 10 %: {both:.0%}."]
    for kind, d in rows.items():
        bm = np.array(d["b_model"])
        fails = [FIRST_SEED + i for i, v in enumerate(d["b_mean"]) if not abs(v - 1.0) < 0.10]
        lines.append(
            f"NoiseModel {kind} B / configured: median {np.nanmedian(bm):.3f}, range "
            f"{np.nanmin(bm):.3f}..{np.nanmax(bm):.3f}; not identified on any axis in "
            f"{int(np.sum(~np.isfinite(bm)))}/{len(bm)} seeds; seeds whose mean-over-axes {kind} B "
            f"misses 10 %: {fails}."
        )
    text = "\n".join(lines) + "\n"
    if os.environ.get("IOTNAV_WRITE_RESULTS") == "1":
        (Path(__file__).resolve().parent / "results" / "characterize_sim.md").write_text(text)
    return text


if __name__ == "__main__":
    quick = os.environ.get("IOTNAV_BENCH_QUICK") == "1"
    n = int(sys.argv[1]) if len(sys.argv) > 1 else (8 if quick else 40)
    rate = float(sys.argv[2]) if len(sys.argv) > 2 else 10.0
    print(run(n, rate))
