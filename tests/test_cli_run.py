"""iotnav run / eval / cost end to end on a simulated directory (layer c)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
from typer.testing import CliRunner

from iotnav.cli import app
from iotnav.engines.base import OUTPUT_COLUMNS

runner = CliRunner()


@pytest.fixture(scope="module")
def sim_dir(tmp_path_factory: pytest.TempPathFactory) -> Path:
    d = tmp_path_factory.mktemp("walk")
    res = runner.invoke(app, ["simulate", "walk-cold-boot", "--out", str(d), "--seed", "3"])
    assert res.exit_code == 0, res.output
    return d


def test_run_writes_outputs_at_imu_rate(sim_dir: Path, tmp_path: Path) -> None:
    out = tmp_path / "out"
    res = runner.invoke(app, ["run", str(sim_dir), "--engine", "pipeline", "--out", str(out)])
    assert res.exit_code == 0, res.output
    track = pd.read_csv(out / "track.csv")
    assert list(track.columns)[: len(OUTPUT_COLUMNS)] == list(OUTPUT_COLUMNS)
    imu_rows = sum(1 for _ in open(sim_dir / "imu.csv")) - 1  # independent: lines minus header
    assert len(track) == imu_rows
    summary = json.loads((out / "summary.json").read_text())
    assert summary["engine"] == "pipeline"
    assert "config" in summary["engine_summary"]
    assert summary["rates_hz"]["output"] == pytest.approx(4.0, rel=0.01)  # scenario: IMU at 4 Hz
    events = json.loads((out / "events.json").read_text())
    assert any(e["type"] == "boot" for e in events)
    for name in ("track.geojson", "track.gpx", "gnss.csv"):
        assert (out / name).stat().st_size > 0
    res = runner.invoke(app, ["eval", str(out), "--truth", str(sim_dir / "truth.csv")])
    assert res.exit_code == 0, res.output
    ev = json.loads((out / "eval.json").read_text())
    for key in (
        "h_err_mean",
        "h_err_rms",
        "h_err_p50",
        "h_err_p67",
        "h_err_p95",
        "h_err_max",
        "n_err_p95",
        "e_err_mean",
    ):
        assert key in ev and ev[key] >= 0


def test_run_parquet_and_map_rate(sim_dir: Path, tmp_path: Path) -> None:
    csv_out, pq_out = tmp_path / "csv", tmp_path / "pq"
    res = runner.invoke(app, ["run", str(sim_dir), "--out", str(csv_out), "--map-rate-hz", "0"])
    assert res.exit_code == 0, res.output
    res = runner.invoke(app, ["run", str(sim_dir), "--out", str(pq_out), "--format", "parquet"])
    assert res.exit_code == 0, res.output
    assert not (pq_out / "track.csv").exists()
    pq = pd.read_parquet(pq_out / "track.parquet")
    csv = pd.read_csv(csv_out / "track.csv")
    assert list(pq.columns) == list(csv.columns) and len(pq) == len(csv)
    np.testing.assert_allclose(pq["lat"], csv["lat"], rtol=1e-9, atol=0)  # csv: 10 digits
    # map files: every row with a position on request, else one point per second (IMU at 4 Hz)
    n_pos = int(csv["lat"].notna().sum())
    every = json.loads((csv_out / "track.geojson").read_text())["features"][0]["properties"]["points"]
    thin = json.loads((pq_out / "track.geojson").read_text())["features"][0]["properties"]["points"]
    assert every == n_pos
    span_s = csv.loc[csv["lat"].notna(), "t"].agg(np.ptp)
    assert abs(thin - (span_s + 1)) <= 2
    res = runner.invoke(app, ["eval", str(pq_out), "--truth", str(sim_dir / "truth.csv")])
    assert res.exit_code == 0, res.output
    res = runner.invoke(app, ["run", str(sim_dir), "--out", str(pq_out), "--format", "xlsx"])
    assert res.exit_code == 2 and "expected csv or parquet" in res.output


def test_run_map_at_fix_times(sim_dir: Path, tmp_path: Path) -> None:
    out = tmp_path / "fixes"
    res = runner.invoke(
        app, ["run", str(sim_dir), "--engine", "pipeline", "--out", str(out), "--map-at-fixes"]
    )
    assert res.exit_code == 0, res.output
    track = pd.read_csv(out / "track.csv")
    gnss = pd.read_csv(out / "gnss.csv")
    pos = track[track["lat"].notna()].reset_index(drop=True)
    t0, t1 = pos["t"].iloc[0], pos["t"].iloc[-1]
    fix_t = gnss.loc[gnss["valid"].astype(bool), "t"]
    inside = fix_t[(fix_t >= t0) & (fix_t <= t1)].to_numpy()
    # the map's points are the rows nearest to each fix time (brute force here), and the ends
    tt = pos["t"].to_numpy()
    want = sorted({0, len(pos) - 1, *(int(np.argmin(np.abs(tt - f))) for f in inside)})
    gj = json.loads((out / "track.geojson").read_text())["features"][0]
    coords = np.array(gj["geometry"]["coordinates"])[:, :2]
    assert gj["properties"]["points"] == len(want) == (out / "track.gpx").read_text().count("<trkpt ")
    np.testing.assert_allclose(coords, pos.loc[want, ["lon", "lat"]].to_numpy(), rtol=0, atol=1e-8)
    res = runner.invoke(app, ["run", str(sim_dir), "--out", str(out), "--map-at-fixes", "--map-rate-hz", "2"])
    assert res.exit_code == 0, res.output  # --map-at-fixes wins; the rate is ignored


def test_nearest_rows() -> None:
    from iotnav.io.export import nearest_rows

    t = np.array([0.0, 1.0, 2.0, 3.0, 4.0])
    # 1.4 -> row 1, 1.5 -> row 1 (the earlier on a tie), 2.6 -> row 3, 9 and NaN: outside / none
    assert nearest_rows(t, np.array([1.4, 1.5, 2.6, 9.0, np.nan])).tolist() == [0, 1, 3, 4]
    assert nearest_rows(t, np.array([])).tolist() == [0, 4]
    assert nearest_rows(np.array([5.0]), np.array([5.0])).tolist() == [0]
    assert nearest_rows(np.array([]), np.array([1.0])).tolist() == []


def test_run_state_dir_saves_last_position(sim_dir: Path, tmp_path: Path) -> None:
    state = tmp_path / "state"
    res = runner.invoke(
        app,
        ["run", str(sim_dir), "--engine", "pipeline", "--out", str(tmp_path / "o"), "--state", str(state)],
    )
    assert res.exit_code == 0, res.output
    saved = json.loads((state / "last_position.json").read_text())
    truth = pd.read_csv(sim_dir / "truth.csv")
    # The saved position is the device's (the walk returns near its start): within 50 m of the truth track.
    d_lat = (truth["lat"] - saved["lat_deg"]).abs().min() * 111_000
    assert d_lat < 50


def test_run_rejects_bad_requests(tmp_path: Path, sim_dir: Path) -> None:
    res = runner.invoke(app, ["run", str(sim_dir), "--engine", "nosuch", "--out", str(tmp_path)])
    assert res.exit_code == 2 and "unknown engine" in res.output
    res = runner.invoke(app, ["run", str(tmp_path / "empty_dir_missing")])
    assert res.exit_code == 2
    bad = tmp_path / "bad.toml"
    bad.write_text("[fusion]\nno_such_key = 1\n")
    res = runner.invoke(
        app, ["run", str(sim_dir), "--engine", "pipeline", "--config", str(bad), "--out", str(tmp_path / "o")]
    )
    assert res.exit_code == 2 and "no_such_key" in res.output


def test_run_without_engine_picks_one_and_says_why(sim_dir: Path, tmp_path: Path) -> None:
    out = tmp_path / "o"
    res = runner.invoke(app, ["run", str(sim_dir), "--out", str(out)])
    assert res.exit_code == 0, res.output
    summary = json.loads((out / "summary.json").read_text())
    choice = summary["engine_choice"]
    assert choice["default"] is True and choice["name"] == summary["engine"]
    assert choice["reason"] and f"engine: {choice['name']}" in res.output
    # walk-cold-boot is a simulated walker: slow, with a step cadence
    assert choice["name"] == "pdr" and "steps/s" in choice["reason"]


def test_cost_table_shows_paper_values() -> None:
    res = runner.invoke(app, ["cost", "--calls", "20"])
    assert res.exit_code == 0, res.output
    # Paper Table I, [9,5,3] fusion filter predict: 1476 sums / 1566 multiplications (ours equal);
    # update: 2493 sums / 2869 multiplications; blocks 1, 4, 5 by their FLOPs (ours / paper).
    assert "1476 / 1476" in res.output
    assert "1566 / 1566" in res.output
    assert "/ 2493" in res.output and "/ 2869" in res.output
    assert "20 / 20" in res.output  # rotation-matrix conversion of block 5
    for paper_flops in ("/ 4 ", "/ 40 ", "/ 134 ", "/ 5243 "):
        assert paper_flops in res.output


def test_run_smooth_writes_forward_and_smoothed(sim_dir: Path, tmp_path: Path) -> None:
    out = tmp_path / "s"
    res = runner.invoke(app, ["run", str(sim_dir), "--engine", "anchor", "--smooth", "--out", str(out)])
    assert res.exit_code == 0, res.output
    fwd = pd.read_csv(out / "forward" / "track.csv")
    smo = pd.read_csv(out / "track.csv")
    assert len(fwd) == len(smo)
    assert (fwd["north"] - smo["north"]).abs().max() > 0  # the smoother changed the track
    res = runner.invoke(app, ["run", str(sim_dir), "--engine", "pdr", "--smooth", "--out", str(out)])
    assert res.exit_code == 2 and "does not support --smooth" in res.output


def test_run_pipeline_smooth(sim_dir: Path, tmp_path: Path) -> None:
    out = tmp_path / "p"
    res = runner.invoke(app, ["run", str(sim_dir), "--engine", "pipeline", "--smooth", "--out", str(out)])
    assert res.exit_code == 0, res.output
    fwd = pd.read_csv(out / "forward" / "track.csv")
    smo = pd.read_csv(out / "track.csv")
    assert len(fwd) == len(smo) == sum(1 for _ in open(sim_dir / "imu.csv")) - 1
    assert (fwd["source"] == smo["source"]).all()
    kf = fwd["source"].isin(["fix", "dr", "lowpass"]).to_numpy() & fwd["north"].notna().to_numpy()
    assert kf.sum() > 100 and (fwd["north"] - smo["north"]).abs().max() > 0  # the smoother changed the track
    # rows before the fusion filter starts (the cold boot waits for a fix) are left alone
    first = int(np.argmax(kf))
    assert first > 100
    pd.testing.assert_frame_equal(fwd.iloc[:first], smo.iloc[:first])
    assert json.loads((out / "summary.json").read_text())["engine"] == "pipeline"


def test_bench_lists_scripts_and_rejects_unknown() -> None:
    from iotnav.cli.bench import ORDER, benchmarks_dir

    d = benchmarks_dir()
    assert (d / "assemble.py").is_file()
    assert all((d / f"{n}.py").is_file() for n in ("bench_ingest", "bench_sim", "bench_pipeline"))
    assert ORDER[0] == "bench_ingest"
    res = runner.invoke(app, ["bench", "--only", "bench_nosuch"])
    assert res.exit_code == 2 and "bench_nosuch" in res.output


@pytest.mark.parametrize(
    ("engine", "good", "bad"),
    [
        ("anchor", "[anchor.kf]\nmin_satellites = 3\n", "[anchor.kf]\nmin_satelites = 3\n"),
        ("eskf", "[eskf]\nuere_m = 4.0\n", "[eskf]\nuere = 4.0\n"),
        ("pipeline", "[static]\ntheta_a_mps2 = 0.2\n", "[statics]\ntheta_a_mps2 = 0.2\n"),
    ],
)
def test_engine_configs_load_from_toml(engine: str, good: str, bad: str, tmp_path: Path) -> None:
    from iotnav.engines.registry import make_engine

    ok = tmp_path / "ok.toml"
    ok.write_text(good)
    eng = make_engine(engine, ok)
    cfg = eng.config  # type: ignore[attr-defined]
    # The value written in the file reached the engine's configuration.
    text = json.dumps(cfg.to_dict(), default=str)
    key, value = good.strip().splitlines()[1].split(" = ")
    assert f'"{key}": {float(value) if "." in value else int(value)}' in text
    wrong = tmp_path / "bad.toml"
    wrong.write_text(bad)
    with pytest.raises(ValueError, match="unknown"):
        make_engine(engine, wrong)


def test_run_eskf_smooth(tmp_path: Path) -> None:
    """``iotnav run --engine eskf --smooth`` on a 60 s simulated car (heading and position at ~21 s)."""
    d = tmp_path / "car"
    res = runner.invoke(
        app, ["simulate", "car-tunnel", "--out", str(d), "--seed", "1", "--set", "duration_s=60"]
    )
    assert res.exit_code == 0, res.output
    out = tmp_path / "s"
    res = runner.invoke(app, ["run", str(d), "--engine", "eskf", "--smooth", "--out", str(out)])
    assert res.exit_code == 0, res.output
    fwd = pd.read_csv(out / "forward" / "track.csv")
    smo = pd.read_csv(out / "track.csv")
    assert len(fwd) == len(smo) == sum(1 for _ in open(d / "imu.csv")) - 1
    moved = (fwd["north"] - smo["north"]).abs()
    assert moved.max() > 0.01  # the smoother changed the track
    early = fwd["t"] < 20.0  # before the heading is known the output is the last fix, unsmoothed
    assert early.sum() > 100 and moved[early].fillna(0.0).max() == 0.0


def test_run_reports_unused_magnetometer_and_rounding(tmp_path: Path) -> None:
    """The run table tells the user what the engine left out: a raw magnetometer (no calibration
    configured) and the GNSS position rounding it found (the simulator writes 7-decimal NMEA
    minutes: continuous for the filter)."""
    d = tmp_path / "car"
    res = runner.invoke(
        app, ["simulate", "car-magnetometer", "--out", str(d), "--seed", "0", "--set", "duration_s=50"]
    )
    assert res.exit_code == 0, res.output
    out = tmp_path / "e"
    res = runner.invoke(app, ["run", str(d), "--engine", "eskf", "--out", str(out)], terminal_width=200)
    assert res.exit_code == 0, res.output
    es = json.loads((out / "summary.json").read_text())["engine_summary"]
    assert es["mag_unused"] > 0 and es["gnss_resolution"]["continuous"]
    assert f"{es['mag_unused']} samples unused" in res.output
    assert "GNSS position rounding" in res.output and "continuous" in res.output
