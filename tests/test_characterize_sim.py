"""``iotnav characterize`` recovers the simulator's configured noise (issue #6).

The simulator's ``static-imu-6h`` scenario (Microstrain 3DM-GX3-35 preset: gyro N = 30
mdps/sqrt(Hz), B = 18 deg/h; accel N = 80 ug/sqrt(Hz), B = 40 ug = 0.04 mg) models the in-run
bias as flicker noise (``bias_model="flicker"``), whose Allan deviation floor is 0.664 B, the
definition :mod:`iotnav.techniques.allan` uses. The configured values below are the datasheet
numbers, written out here. The logs are 6 h long at 10 Hz: the rate changes nothing at
tau >= 1 s, where N (read at 1 s) and B (a floor at ~100-2000 s) are read.

``fit_allan`` fits ``N^2 / tau + (0.664 B)^2 + K^2 tau / 3`` to the whole ADEV curve by
weighted least squares and reports each term's 1-sigma uncertainty; ``B`` is identified when that
is below 10 %. What a single 6-hour record gives (``benchmarks/bench_characterize_sim.py``, 40
seeds 1000-1039 at 10 Hz, ``benchmarks/results/characterize_sim.md``):

* N: every axis of every seed within 10 % (240/240), both sensors.
* B per axis: identified on 120/120 gyro and 119/120 accel axes; mean ratio recovered /
  configured 0.996 (gyro) and 0.998 (accel), scatter 5.2 % and 1.7 % (1 sigma; the fit reports
  5.6 % and 1.8 %); within 10 % on 110/120 gyro and 119/120 accel axes.
* Mean over the identified axes within 10 %: 40/40 seeds for both sensors.
* NoiseModel B (largest identified axis, the conservative value written to noise_model.toml):
  within 10 % on 36/40 (gyro; the max of three 5 % draws sits ~5 % high) and 40/40 (accel) seeds.

So the issue's "within 10 %" holds for N on every axis, for B on the mean over axes of every log
and on each accelerometer axis; a single gyro axis misses 10 % on ~1 axis in 12, the statistical
limit of 6 hours at this N, and then stays within 3 of its reported sigmas.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

from iotnav import sim
from iotnav.cli import app
from iotnav.techniques.allan import NoiseModel, characterize

GYRO_N_DPS_RTHZ = 0.030  # 30 mdps/sqrt(Hz)
GYRO_B_DPH = 18.0
ACC_N_UG_RTHZ = 80.0
ACC_B_UG = 40.0
DEG = np.pi / 180.0
UG = 9.80665e-6
#: First seed of the benchmark sweep, fixed before looking at any result.
SEED = 1000
RATE_HZ = 10.0
OVERRIDES: dict[str, object] = {"truth_rate_hz": RATE_HZ, "imu.rate_hz": RATE_HZ}


def _per_axis(sensor: dict[str, dict[str, float | None]], key: str) -> np.ndarray:
    """One number per axis x, y, z from ``characterize.json`` (None -> NaN)."""
    return np.array([np.nan if sensor[ax][key] is None else sensor[ax][key] for ax in "xyz"], dtype=float)


@pytest.fixture(scope="module")
def seed_log() -> sim.SimResult:
    """The ``static-imu-6h`` log of :data:`SEED` at 10 Hz, built once for both tests."""
    return sim.build("static-imu-6h", seed=SEED, overrides=OVERRIDES)


def test_characterize_cli_on_simulated_static_log(seed_log: sim.SimResult, tmp_path: Path) -> None:
    """``iotnav characterize imu.csv`` on the written ``static-imu-6h`` log, seed 1000.

    * N (noise_model.toml, largest axis) within 10 % for both sensors.
    * B identified on every axis; accel B within 10 % on every axis; gyro B within 10 % on the
      mean over axes and within 3 reported sigmas (``bias_instability_sigma``, ~5.6 %) on each
      axis: seed 1000 (fixed before any result) gives 15.8, 17.7, 18.6 deg/h, x at -12 %.
    * noise_model.toml carries the largest axis, within 10 % for both sensors (18.6 deg/h,
      39.8 ug).
    """
    r = seed_log
    assert r.meta["imu_spec"]["bias_model"] == "flicker"
    sim.write(r, tmp_path / "log")
    out = tmp_path / "char"
    res = CliRunner().invoke(app, ["characterize", str(tmp_path / "log" / "imu.csv"), "--out", str(out)])
    assert res.exit_code == 0, res.output
    model = NoiseModel.from_toml((out / "noise_model.toml").read_text())
    assert abs(model.gyro_noise_density_dps_rthz / GYRO_N_DPS_RTHZ - 1.0) < 0.10
    assert abs(model.accel_noise_density_ug_rthz / ACC_N_UG_RTHZ - 1.0) < 0.10

    summary = json.loads((out / "characterize.json").read_text())
    gyro_b = _per_axis(summary["gyro"], "bias_instability_dph")  # deg/h, NaN: not identified
    acc_b = _per_axis(summary["accel"], "bias_instability_ug")  # ug
    assert np.all(np.isfinite(gyro_b)) and np.all(np.isfinite(acc_b))
    assert np.all(np.abs(acc_b / ACC_B_UG - 1.0) < 0.10), acc_b
    assert abs(np.mean(gyro_b) / GYRO_B_DPH - 1.0) < 0.10, gyro_b
    for values, model_b, configured in (
        (gyro_b, model.gyro_bias_instability_dph, GYRO_B_DPH),
        (acc_b, model.accel_bias_instability_ug, ACC_B_UG),
    ):
        assert model_b == pytest.approx(np.max(values), rel=1e-9)
        assert abs(model_b / configured - 1.0) < 0.10, model_b

    # per-axis uncertainty from the fit (Python API on the same log): the miss is within 3 sigma
    imu = r.imu
    res_api = characterize(
        imu["t"].to_numpy(),
        imu[["acc_x", "acc_y", "acc_z"]].to_numpy(),
        imu[["gyro_x", "gyro_y", "gyro_z"]].to_numpy(),
    )
    b_conf = GYRO_B_DPH * DEG / 3600.0
    for p in res_api.gyro_params:
        assert 0.0 < p.bias_instability_sigma < 0.10 * p.bias_instability
        assert abs(p.bias_instability - b_conf) < 3.0 * p.bias_instability_sigma


def test_bias_instability_within_10_percent_on_average_over_logs(seed_log: sim.SimResult) -> None:
    """16 seeded 6-hour logs (seeds 1000-1015, Python API, no files).

    * N within 10 % on every axis of every log, both sensors.
    * B identified on at least 47 of the 48 axes per sensor (sweep: 120/120 gyro, 119/120 accel).
    * Mean over the identified axes of B within 10 % on every log, both sensors (sweep: 40/40).
    * Per axis, B within 10 % on at least 85 % of the gyro axes (sweep: 110/120 = 92 %) and on
      every identified accelerometer axis (sweep: 119/119).
    * The scatter of the per-axis ratio agrees with the fit's reported relative 1-sigma within a
      factor 1.5 (sweep: 5.2 % vs 5.6 % gyro, 1.7 % vs 1.8 % accel).
    """
    ratios: dict[str, list[float]] = {"gyro": [], "accel": []}
    means: dict[str, list[float]] = {"gyro": [], "accel": []}
    rel_sd: dict[str, list[float]] = {"gyro": [], "accel": []}
    n_ratios: list[float] = []
    for seed in range(SEED, SEED + 16):
        r = seed_log if seed == SEED else sim.build("static-imu-6h", seed=seed, overrides=OVERRIDES)
        imu = r.imu
        res = characterize(
            imu["t"].to_numpy(),
            imu[["acc_x", "acc_y", "acc_z"]].to_numpy(),
            imu[["gyro_x", "gyro_y", "gyro_z"]].to_numpy(),
        )
        for kind, params, b_conf, n_conf in (
            ("gyro", res.gyro_params, GYRO_B_DPH * DEG / 3600.0, GYRO_N_DPS_RTHZ * DEG),
            ("accel", res.acc_params, ACC_B_UG * UG, ACC_N_UG_RTHZ * UG),
        ):
            b = np.array([p.bias_instability for p in params]) / b_conf
            ratios[kind].extend(b.tolist())
            means[kind].append(float(np.nanmean(b)) if np.any(np.isfinite(b)) else np.nan)
            rel_sd[kind].extend(p.bias_instability_sigma / p.bias_instability_fit for p in params)
            n_ratios.extend(p.noise_density / n_conf for p in params)
    assert np.all(np.abs(np.array(n_ratios) - 1.0) < 0.10)
    for kind, per_axis_min in (("gyro", 0.85), ("accel", 1.0)):
        b = np.array(ratios[kind])
        ok = np.isfinite(b)
        assert np.sum(ok) >= 47, (kind, b)
        assert np.all(np.abs(np.array(means[kind]) - 1.0) < 0.10), (kind, means[kind])
        assert np.mean(np.abs(b[ok] - 1.0) < 0.10) >= per_axis_min, (kind, b)
        assert 1.0 / 1.5 < np.std(b[ok]) / np.mean(rel_sd[kind]) < 1.5, (kind, np.std(b[ok]))
