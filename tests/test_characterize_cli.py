"""``iotnav characterize`` end to end: a synthetic 6-hour static log and real static segments.

The synthetic log uses the generator of ``test_allan.py`` (white + flicker + rate random walk, see
its module docstring for the model and why the recovered N and B must match the configured ones).
The real segments are short (35 s BROAD rest, 28 s of the parked car): only the white-noise
density is identifiable from them, and the command must say so.
"""

from __future__ import annotations

import json
import math
import tomllib
from pathlib import Path

import numpy as np
import pytest
import typer
from typer.testing import CliRunner

from iotnav.cli.characterize import register
from test_allan import LN2_FACTOR, synth_rate_noise

G0 = 9.80665
DEG = math.pi / 180.0
UG = 1e-6 * G0

runner = CliRunner()


def _app() -> typer.Typer:
    app = typer.Typer()

    @app.callback()
    def main() -> None:
        """Test shell."""

    register(app)
    return app


def _run(*args: str) -> tuple[int, str]:
    res = runner.invoke(_app(), ["characterize", *args])
    return res.exit_code, res.output


# configured parameters (datasheet units)
GYRO_N_DPS = (0.004, 0.005, 0.006)  # deg/s/rtHz
GYRO_B_DPH = (8.0, 10.0, 12.0)  # deg/h
ACC_N_UG = (80.0, 100.0, 120.0)  # ug/rtHz
ACC_B_UG = (40.0, 50.0, 60.0)  # ug
FS = 50.0


@pytest.fixture(scope="module")
def six_hour_run(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, str]:
    """A seeded 6-hour static log at 50 Hz (BROAD-style .npz) through the command."""
    rng = np.random.default_rng(2024)
    n = int(6 * 3600 * FS)
    gyro, acc = [], []
    for nd, bi in zip(GYRO_N_DPS, GYRO_B_DPH, strict=True):
        N, B = nd * DEG, bi * DEG / 3600.0
        K = LN2_FACTOR * B / math.sqrt(1000.0)  # RRW reaches the floor at tau ~ 3000 s
        gyro.append(synth_rate_noise(rng, n, FS, N, B, K) + 7.3e-5 * 0.5)  # plus a constant bias
    for nd, bi in zip(ACC_N_UG, ACC_B_UG, strict=True):
        N, B = nd * UG, bi * UG
        K = LN2_FACTOR * B / math.sqrt(1000.0)
        acc.append(synth_rate_noise(rng, n, FS, N, B, K))
    acc_arr = np.column_stack(acc)
    acc_arr[:, 2] += G0
    d = tmp_path_factory.mktemp("six_hours")
    np.savez(d / "static6h.npz", imu_acc=acc_arr, imu_gyr=np.column_stack(gyro), sampling_rate=FS)
    code, out = _run(str(d / "static6h.npz"), "--out", str(d / "out"))
    assert code == 0, out
    return d / "out", out


def test_six_hour_log_recovers_configured_density_and_bias_instability(
    six_hour_run: tuple[Path, str],
) -> None:
    """N and B within 10 % of the configured values on every axis: the whole-curve fit recovers B
    itself (not the ADEV minimum / 0.664, which white noise and rate random walk lift by ~5 %)."""
    out, text = six_hour_run
    summary = json.loads((out / "characterize.json").read_text())
    b_ratios = []
    for i, ax in enumerate("xyz"):
        g = summary["gyro"][ax]
        b_exp_dph = GYRO_B_DPH[i]
        assert g["noise_density_dps_rthz"] == pytest.approx(GYRO_N_DPS[i], rel=0.10)
        b_ratios.append(g["bias_instability_dph"] / b_exp_dph)
        a = summary["accel"][ax]
        B = ACC_B_UG[i] * UG
        b_exp_ug = B / UG
        assert a["noise_density_ug_rthz"] == pytest.approx(ACC_N_UG[i], rel=0.10)
        b_ratios.append(a["bias_instability_ug"] / b_exp_ug)
    assert np.all(np.abs(np.array(b_ratios) - 1.0) < 0.10), b_ratios
    assert abs(np.mean(b_ratios[0::2]) - 1.0) < 0.10 and abs(np.mean(b_ratios[1::2]) - 1.0) < 0.10
    model = tomllib.loads((out / "noise_model.toml").read_text())["imu_noise"]
    # the model keeps the worst (largest) axis
    assert model["gyro_noise_density_dps_rthz"] == pytest.approx(max(GYRO_N_DPS), rel=0.10)
    assert model["accel_noise_density_ug_rthz"] == pytest.approx(max(ACC_N_UG), rel=0.10)
    assert model["gyro_bias_instability_dph"] == max(
        summary["gyro"][ax]["bias_instability_dph"] for ax in "xyz"
    )
    assert model["accel_bias_instability_ug"] == max(
        summary["accel"][ax]["bias_instability_ug"] for ax in "xyz"
    )
    assert model["duration_s"] == pytest.approx(6 * 3600, rel=1e-3)
    assert (out / "allan.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert (out / "allan.csv").read_text().startswith("tau_s,")
    assert "Table 2" in text and "Allan" in text


def test_real_broad_rest_segment(datasets: Path, tmp_path: Path) -> None:
    """BROAD trial 02, first 35 s at rest (285.7 Hz, myon aktos-t): plausible consumer-MEMS
    figures, B only bounded."""
    f = datasets / "broad_attitude" / "02_undisturbed_slow_rotation_B.npz"
    code, text = _run(str(f), "--end", "35", "--out", str(tmp_path))
    assert code == 0, text
    s = json.loads((tmp_path / "characterize.json").read_text())
    assert s["duration_s"] == pytest.approx(35.0, abs=0.01)
    for ax in "xyz":
        assert 0.002 < s["gyro"][ax]["noise_density_dps_rthz"] < 0.1
        assert 20.0 < s["accel"][ax]["noise_density_ug_rthz"] < 2000.0
        assert s["gyro"][ax]["bias_instability_dph"] is None
        assert s["gyro"][ax]["bias_instability_upper_bound_dph"] > 0.0
    model = tomllib.loads((tmp_path / "noise_model.toml").read_text())["imu_noise"]
    assert math.isnan(model["gyro_bias_instability_dph"])
    assert "not identifiable" in text


def test_real_drive_static_start(datasets: Path, tmp_path: Path) -> None:
    """rtklibexplorer drive, first 28 s parked with the engine running (ICM-45686, ~100 Hz, CSV
    read through iotnav.io.read_file). The z gyro shows the sensor's own white noise; x and y
    carry engine vibration, which the Allan curve exposes (periodic structure) and inflates."""
    f = datasets / "rtklibexplorer_gnss_imu" / "drive_0708" / "imu_1934_gpst.csv"
    code, text = _run(str(f), "--start", "0", "--end", "28", "--out", str(tmp_path))
    assert code == 0, text
    s = json.loads((tmp_path / "characterize.json").read_text())
    assert s["rate_hz"] == pytest.approx(100.0, rel=0.01)
    assert 0.002 < s["gyro"]["z"]["noise_density_dps_rthz"] < 0.1
    assert s["gyro"]["y"]["noise_density_dps_rthz"] > 0.1  # vibration, not sensor noise
    assert any("periodic" in note for note in s["gyro"]["y"]["notes"])
    assert s["noise_model"]["gyro_bias_instability_dph"] is None


@pytest.mark.parametrize(
    ("args", "match"),
    [
        (["nope.csv"], "no such file"),
        (["{broad}", "--end", "0.02"], "only"),
        (["{broad}", "--acc-unit", "furlong"], "unknown acc unit"),
    ],
)
def test_user_errors_exit_2(datasets: Path, tmp_path: Path, args: list[str], match: str) -> None:
    broad = str(datasets / "broad_attitude" / "02_undisturbed_slow_rotation_B.npz")
    code, text = _run(*[a.replace("{broad}", broad) for a in args], "--out", str(tmp_path))
    assert code == 2
    assert match in text
