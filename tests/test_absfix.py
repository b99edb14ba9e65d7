"""absfix engine on the pedestrian-fixes scenario (Dabove et al. 2016): seeded effect tests."""

from __future__ import annotations

import json
from functools import lru_cache
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd
import pytest

from iotnav import sim
from iotnav.engines.absfix import (
    AbsfixConfig,
    AbsfixEngine,
    AbsFixSample,
    _merged,
    fixes_from_table,
    run_with_fixes,
)
from iotnav.engines.base import FLOAT_COLUMNS, OUTPUT_COLUMNS, SOURCES
from iotnav.eval.metrics import track_errors
from iotnav.io.log import Log

REFERENCE = Path(__file__).parent / "data" / "absfix_reference" / "absfix_reference.npz"
IMU_COLS = ("acc_x", "acc_y", "acc_z", "gyro_x", "gyro_y", "gyro_z")
SHORT = {"motion.laps": 1, "motion.wait_start_s": 5.0, "motion.wait_end_s": 2.0}
#: Total-station fixes as in the paper's tests: millimetre positions, a precise attitude.
TOTAL_STATION = {"fixes.sigma_pos_m": 0.002, "fixes.sigma_att_rad": 0.001, "fixes.latency_s": 0.0}


@lru_cache(maxsize=16)
def _sim(seed: int, items: tuple[tuple[str, Any], ...]) -> sim.SimResult:
    return sim.build("pedestrian-fixes", seed=seed, overrides={**SHORT, **TOTAL_STATION, **dict(items)})


def _errors(track: pd.DataFrame, truth: pd.DataFrame) -> dict[str, float]:
    err = track_errors(track[track["source"] != "none"], truth)
    return {
        "n_mean": float(np.mean(np.abs(err.n_err))),
        "e_mean": float(np.mean(np.abs(err.e_err))),
        "h_mean": float(np.mean(err.h_err)),
        "h_max": float(np.max(err.h_err)),
    }


def _run(res: sim.SimResult, fixes: Any = None, revised: bool = False, **cfg: Any) -> pd.DataFrame:
    fx = res.fixes if fixes is None else fixes
    return run_with_fixes(AbsfixEngine(AbsfixConfig(**cfg)), Log(imu=res.imu), fx, revised=revised)


def test_error_free_imu_and_exact_fixes_reproduce_the_truth() -> None:
    res = _sim(0, (("imu.errors", False), ("fixes.sigma_pos_m", 0.0), ("fixes.sigma_att_rad", 0.0)))
    e = _errors(_run(res, bias_mode="fixes", drift_mode="fixes"), res.truth)
    # only the tangent-plane approximation of the engine's NED frame and rounding remain
    assert e["h_max"] < 1e-3


@pytest.mark.parametrize(("interval", "bound"), [(1.0, 0.14), (2.0, 0.42), (5.0, 2.6)])
def test_microstrain_class_meets_the_paper_table_4(interval: float, bound: float) -> None:
    res = _sim(1, (("fixes.interval_s", interval),))
    e = _errors(_run(res, bias_mode="fixes", drift_mode="fixes"), res.truth)
    assert e["n_mean"] <= bound
    assert e["e_mean"] <= bound
    assert e["h_mean"] <= bound


def test_drift_and_bias_from_fixes_beat_no_estimation_at_5_s() -> None:
    res = _sim(2, (("fixes.interval_s", 5.0),))
    none = _errors(_run(res, bias_mode="none", drift_mode="none"), res.truth)
    fixes = _errors(_run(res, bias_mode="fixes", drift_mode="fixes"), res.truth)
    assert fixes["h_mean"] < 0.8 * none["h_mean"]


def test_bias_from_fixes_finds_the_turn_on_bias_of_a_smartphone_imu() -> None:
    """Only a turn-on bias (no noise, no scale factor): the solved bias is the drawn one."""
    spec = {
        f"imu.{k}": 0.0
        for k in (
            "acc_noise_density_ug_rthz",
            "gyro_noise_density_mdps_rthz",
            "acc_bias_instability_mg",
            "gyro_bias_instability_dph",
            "acc_scale_factor_pct",
            "gyro_scale_factor_pct",
            "acc_misalignment_pct",
            "gyro_misalignment_pct",
            "acc_lsb_mg",
            "gyro_lsb_mdps",
            "timestamp_jitter_ms",
        )
    }
    items = (("imu.preset", "smartphone"), ("fixes.sigma_pos_m", 0.0), ("fixes.sigma_att_rad", 0.0))
    res = _sim(3, (*items, *spec.items()))
    tr = _run(res, bias_mode="fixes", drift_mode="fixes")
    s = tr.attrs["summary"]
    np.testing.assert_allclose(s["acc_bias_mps2"], res.meta["imu_draw"]["acc_turn_on_bias_mps2"], atol=1e-4)
    np.testing.assert_allclose(
        s["gyro_drift_rads"], res.meta["imu_draw"]["gyro_turn_on_bias_rads"], atol=1e-5
    )


def test_latency_compensated_track_stays_within_10_percent_of_zero_latency() -> None:
    res0 = _sim(4, ())
    e0 = _errors(_run(res0, revised=True), res0.truth)
    for latency in (0.5, 1.0, 2.0):
        resl = _sim(4, (("fixes.latency_s", latency),))
        assert np.array_equal(res0.imu.to_numpy(), resl.imu.to_numpy())
        el = _errors(_run(resl, revised=True), resl.truth)
        for k in ("n_mean", "e_mean", "h_mean"):
            assert el[k] <= 1.10 * e0[k]


def test_real_time_track_needs_the_compensation() -> None:
    """Applying 2 s-late fixes as if valid on arrival is worse than applying them at t_valid."""
    res = _sim(4, (("fixes.latency_s", 2.0),))
    rt = _errors(_run(res), res.truth)
    naive = res.fixes.assign(t_valid=res.fixes["t_arrival"])
    stale = _errors(_run(res, fixes=naive), res.truth)
    assert rt["h_mean"] < 0.5 * stale["h_mean"]


def test_out_of_order_arrivals_give_the_same_revised_track() -> None:
    res = _sim(5, (("fixes.latency_s", 1.0),))
    fx = res.fixes.copy()
    # swap the arrival times of every other pair: later fix first
    ta = fx["t_arrival"].to_numpy().copy()
    ta[0:-1:2], ta[1::2] = ta[1::2] + 0.0, ta[0:-1:2] + 0.3
    shuffled = fx.assign(t_arrival=np.maximum(ta, fx["t_valid"].to_numpy()))
    a = _run(res, revised=True)
    b = _run(res, fixes=shuffled, revised=True)
    assert any(e["type"] == "fix_out_of_order" for e in b.attrs["events"])
    # the NED origin is the first fix to arrive, which differs: compare geodetic positions
    for col in ("lat", "lon"):
        np.testing.assert_allclose(b[col].to_numpy(float), a[col].to_numpy(float), atol=1e-10, equal_nan=True)


def test_fixes_older_than_the_buffer_are_rejected_and_reported() -> None:
    res = _sim(6, (("fixes.latency_s", 3.0),))
    fx = res.fixes[res.fixes["t_arrival"] <= res.imu["t"].max()]  # arriving while the IMU runs
    tr = _run(res, fixes=fx, max_latency_s=2.0)
    rej = [e for e in tr.attrs["events"] if e["type"] == "fix_rejected"]
    assert len(rej) == len(fx) > 0
    assert tr.attrs["summary"]["counts"]["rejected"] == len(fx)
    assert (tr["source"] == "none").all()


def test_position_only_fixes_wait_for_the_alignment() -> None:
    res = _sim(7, ())
    fx = res.fixes.drop(columns=["roll", "pitch", "yaw"])
    yaw0 = float(res.fixes["yaw"].iloc[0])
    tr = _run(res, fixes=fx, bias_mode="fixes", drift_mode="none", initial_yaw_rad=yaw0, align_s=3.0)
    rej = [e for e in tr.attrs["events"] if e["type"] == "fix_rejected"]
    # fixes up to 3 s arrive before the IMU sample that completes the 3 s alignment
    assert [e["t_valid"] for e in rej] == [1.0, 2.0, 3.0]
    assert _errors(tr, res.truth)["h_mean"] <= 0.14


def test_streaming_denoiser_outputs_every_sample() -> None:
    res = _sim(8, (("motion.laps", 1), ("duration_s", 20.0)))
    tr = _run(res, denoise="streaming", denoise_window=1024, denoise_delay=128)
    assert len(tr) == len(res.imu)
    assert np.all(np.isfinite(tr["north"].to_numpy(float)[-100:]))


def test_batch_denoising_runs_on_the_whole_log() -> None:
    res = _sim(8, (("motion.laps", 1), ("duration_s", 20.0)))
    tr = _run(res, denoise="batch")
    assert len(tr) == len(res.imu)
    assert np.all(np.isfinite(tr["north"].to_numpy(float)[-100:]))


def test_config_from_toml_and_bad_values(tmp_path: Path) -> None:
    p = tmp_path / "absfix.toml"
    p.write_text('[absfix]\nbias_mode = "none"\nreference_gyro_bias_rads = [0.1, 0.2, 0.3]\n')
    cfg = AbsfixConfig.from_toml(p)
    assert cfg.bias_mode == "none"
    assert cfg.reference_gyro_bias_rads == (0.1, 0.2, 0.3)
    p.write_text('[absfix]\nbias_mode = "kalman"\n')
    with pytest.raises(ValueError, match="bias_mode"):
        AbsfixConfig.from_toml(p)
    p.write_text("[absfix]\nwindow = 3\n")
    with pytest.raises(ValueError, match="unknown key"):
        AbsfixConfig.from_toml(p)
    with pytest.raises(ValueError, match="bias_window_fixes"):
        AbsfixConfig(bias_window_fixes=2)


def test_fixes_from_reader_table_and_ned_fixes() -> None:
    df = pd.DataFrame(
        {
            "t_valid": [1.0],
            "t_arrival": [1.5],
            "north_m": [3.0],
            "east_m": [4.0],
            "down_m": [0.0],
            "roll": [np.nan],
            "pitch": [np.nan],
            "yaw": [np.nan],
        }
    )
    (f,) = fixes_from_table(df)
    assert isinstance(f, AbsFixSample)
    assert not f.geodetic and not f.has_attitude
    assert f.t == 1.5
    np.testing.assert_array_equal(f.pos_n, [3.0, 4.0, 0.0])


def _reference_case(
    z: Any, meta: dict[str, Any], name: str
) -> tuple[pd.DataFrame, pd.DataFrame, dict[str, Any]]:
    m = meta[name]
    imu = pd.DataFrame(z[f"{m['imu']}/imu_v"].astype(float), columns=list(IMU_COLS))
    imu.insert(0, "t", z[f"{m['imu']}/imu_t"])
    fx = pd.DataFrame(z[f"{name}/fixes"], columns=m["fix_columns"])
    cfg = {k: tuple(v) if isinstance(v, list) else v for k, v in m["config"].items()}
    return imu, fx, cfg


def test_compiled_engine_reproduces_the_python_engine_it_replaced() -> None:
    """Stored runs of the per-sample Python engine (tests/data/absfix_reference): late,
    out-of-order, pending and rejected fixes, an IMU gap, NED position-only fixes, the modes."""
    z = np.load(REFERENCE)
    meta = json.loads(str(z["meta"]))
    for name in ("late_shuffled", "ned_position_only", "pending_reference", "windows_late"):
        imu, fx, cfg = _reference_case(z, meta, name)
        for track in ("realtime", "revised"):
            eng = AbsfixEngine(AbsfixConfig(**cfg))
            df = run_with_fixes(eng, Log(imu=imu), fx, revised=track == "revised")
            key = f"{name}/{track}"
            assert len(df) == meta[key]["rows"], key
            got, ref = df[list(FLOAT_COLUMNS)].to_numpy(float)[::8], z[f"{key}/floats"]
            assert np.array_equal(np.isnan(got), np.isnan(ref)), key
            # round-off only (3x3 products summed in another order): measured 7.5e-14
            np.testing.assert_allclose(got, ref, rtol=0.0, atol=1e-11, equal_nan=True, err_msg=key)
            codes = np.array([SOURCES.index(s) for s in df["source"].astype(str)], dtype=np.int8)[::8]
            assert np.array_equal(codes, z[f"{key}/source"]), key
            assert eng.summary()["counts"] == meta[key]["counts"], key
            assert [e["type"] for e in eng.events] == meta[key]["events"], key
            np.testing.assert_allclose(eng.x[15:21], z[f"{key}/bias"], rtol=0.0, atol=1e-12)


def test_step_gives_the_rows_of_the_compiled_batch_path() -> None:
    """Streaming (one sample at a time through ``step()``) equals the block path bit for bit,
    the revised track (``last_revision``) included."""
    z = np.load(REFERENCE)
    imu, fx, cfg = _reference_case(z, json.loads(str(z["meta"])), "late_shuffled")
    log = Log(imu=imu)
    batch = run_with_fixes(AbsfixEngine(AbsfixConfig(**cfg)), log, fx, revised=True)
    eng = AbsfixEngine(AbsfixConfig(**cfg))
    rows: list[Any] = []
    n_revised = 0
    for s in _merged(log, fixes_from_table(fx)):
        out = eng.step(s)
        if out is not None:
            rows.append(out)
        elif eng.last_revision:
            rev = eng.last_revision
            assert rows[-len(rev)].t == rev[0].t
            rows[-len(rev) :] = list(rev)
            n_revised += len(rev)
            eng.last_revision = ()
    assert n_revised > 500
    stream = pd.DataFrame(rows, columns=list(OUTPUT_COLUMNS))
    a, b = stream[list(FLOAT_COLUMNS)].to_numpy(float), batch[list(FLOAT_COLUMNS)].to_numpy(float)
    assert np.array_equal(a, b, equal_nan=True)
    assert (stream["source"].to_numpy() == batch["source"].astype(str).to_numpy()).all()
    assert eng.summary() | {"latency_s": None} == batch.attrs["summary"] | {"latency_s": None}


def test_the_latency_ring_grows_without_changing_the_track() -> None:
    """Fixes 6 s late (1,000 buffered samples, over the ring's first 512 slots): growing the
    ring mid-run gives the rows of a ring allocated large from the start."""
    res = _sim(9, (("fixes.latency_s", 6.0), ("duration_s", 30.0)))
    cfg = AbsfixConfig(max_latency_s=8.0)
    grown = AbsfixEngine(cfg)
    a = run_with_fixes(grown, Log(imu=res.imu), res.fixes, revised=True)
    big = AbsfixEngine(cfg)
    while big._r_t.size < cfg.buffer_capacity + 1:
        big._grow_ring()
    b = run_with_fixes(big, Log(imu=res.imu), res.fixes, revised=True)
    assert grown._r_t.size == 1026 and grown.counts["applied"] > 15  # grown once from 513 slots
    assert grown.summary()["replayed_samples"] > 15 * 590
    assert np.array_equal(
        a[list(FLOAT_COLUMNS)].to_numpy(float), b[list(FLOAT_COLUMNS)].to_numpy(float), equal_nan=True
    )
