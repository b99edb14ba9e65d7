"""``iotnav characterize`` recovers the simulator's configured noise (issue #6).

The simulator's ``static-imu-6h`` scenario (Microstrain 3DM-GX3-35 preset: gyro N = 30
mdps/sqrt(Hz), B = 18 deg/h; accel N = 80 ug/sqrt(Hz), B = 40 ug = 0.04 mg) models the in-run
bias as flicker noise (``bias_model="flicker"``), whose Allan deviation floor is 0.664 B, the
definition :mod:`iotnav.techniques.allan` uses. The configured values below are the datasheet
numbers, written out here. The logs are 6 h long at 10 Hz: the rate changes nothing at
tau >= 1 s, where N (read at 1 s) and B (a floor at ~100-2000 s) are read.

What a single 6-hour record gives (``benchmarks/bench_characterize_sim.py``, 40 seeds
1000-1039 at 10 Hz, ``benchmarks/results/characterize_sim.md``):

* N: every axis of every seed within 10 % (240/240), both sensors.
* B per axis: mean ratio recovered / configured 0.99 (gyro) and 0.98 (accel), scatter 9.0 % and
  8.2 % (1 sigma); within 10 % on 59/120 gyro and 84/120 accel axes. Gyro B is identified
  (``fit_allan``'s "ADEV has turned up" check) on only 82/120 axes: with N = 30 mdps/sqrt(Hz)
  the white noise crosses the 12 deg/h floor at tau ~ 80 s, so the ADEV is still 2 % above the
  floor at the longest tau of a 6 h log and often looks "still falling".
* Mean over the identified axes within 10 %: gyro 32/40 seeds, accel 35/40 (within 20 %: 38/40
  and 39/40); both sensors together 27/40.
* NoiseModel B (largest identified axis, the conservative value written to noise_model.toml):
  within 10 % on 26/40 (gyro) and 33/40 (accel) seeds.

So the issue's "within 10 %" holds for N on every log, and for B on average over logs (the
form :mod:`tests.test_allan` checks the estimator in), not on every single log:
:func:`test_bias_instability_within_10_percent_on_average_over_logs` checks that over 16 seeds,
:func:`test_characterize_cli_on_simulated_static_log` runs the real command on one seed.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
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


def test_characterize_cli_on_simulated_static_log(tmp_path: Path) -> None:
    """``iotnav characterize imu.csv`` on the written ``static-imu-6h`` log, seed 1000.

    * N (noise_model.toml, largest axis) within 10 % for both sensors (240/240 axes in the sweep).
    * B: every axis that identifies it (characterize.json) within 30 % of the configured value
      (three times the per-axis scatter of the sweep, ~9 %: the tolerance of one 6-hour record),
      the accelerometer identifies it on at least one axis, and noise_model.toml carries the
      largest identified axis (NaN when none).
    * Seed 1000 (fixed before any result) is one of the 8/40 seeds whose gyro B misses 10 %,
      and one of the 2/40 where no gyro axis identifies B at all (the ADEV still falls at
      2160 s), so noise_model.toml has ``gyro_bias_instability_dph = nan``. Its accel B: 41.4, 37.4, 43.5 ug per axis (mean
      40.8 ug, +2 %; NoiseModel 43.5 ug, +9 %).
    """
    r = sim.build("static-imu-6h", seed=SEED, overrides=OVERRIDES)
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
    assert np.any(np.isfinite(acc_b))
    for values, model_b, configured in (
        (gyro_b, model.gyro_bias_instability_dph, GYRO_B_DPH),
        (acc_b, model.accel_bias_instability_ug, ACC_B_UG),
    ):
        ok = np.isfinite(values)
        assert np.all(np.abs(values[ok] / configured - 1.0) < 0.30), values
        if np.any(ok):
            assert model_b == np.max(values[ok])
        else:
            assert np.isnan(model_b)


def test_bias_instability_within_10_percent_on_average_over_logs() -> None:
    """16 seeded 6-hour logs (seeds 1000-1015, Python API, no files).

    * Pooled over all identified axes of all logs, the mean of B recovered / configured is within
      10 % for both sensors (sweep: 0.99 gyro, 0.98 accel); so is the pooled N.
    * At least 60 % of the logs give the mean-over-identified-axes B within 10 % for each
      sensor (sweep: 32/40 = 80 % gyro, 35/40 = 88 % accel; 60 % is the gyro rate less two
      binomial sigmas of 16 logs, 2 x 10 %). These 16 seeds are the first of the sweep: 13/16
      gyro and 15/16 accel pass.
    """
    ratios: dict[str, list[float]] = {"gyro": [], "accel": []}
    means: dict[str, list[float]] = {"gyro": [], "accel": []}
    n_ratios: list[float] = []
    for seed in range(SEED, SEED + 16):
        imu = sim.build("static-imu-6h", seed=seed, overrides=OVERRIDES).imu
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
            ratios[kind].extend(b[np.isfinite(b)].tolist())
            means[kind].append(float(np.nanmean(b)) if np.any(np.isfinite(b)) else np.nan)
            n_ratios.extend(p.noise_density / n_conf for p in params)
    assert np.all(np.abs(np.array(n_ratios) - 1.0) < 0.10)
    for kind in ("gyro", "accel"):
        assert abs(np.mean(ratios[kind]) - 1.0) < 0.10, (kind, np.mean(ratios[kind]))
        assert np.mean(np.abs(np.array(means[kind]) - 1.0) < 0.10) >= 0.6, (kind, means[kind])
