"""Duty-cycle accuracy study (iotnav.eval.duty_cycle) and ``iotnav plan power`` on a short slice
of the real Husky log (GNSS-only ``fixes`` engine: no inertial kernel to compile)."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
from typer.testing import CliRunner

from iotnav.cli import app
from iotnav.eval import duty_cycle as dc
from iotnav.eval.power import Battery, DevicePower
from iotnav.io.schema import GNSS_COLUMNS, coerce, empty_table
from iotnav.report.power import power_markdown

runner = CliRunner()


def _gnss(t: np.ndarray, valid: np.ndarray | None = None) -> pd.DataFrame:
    g = empty_table(GNSS_COLUMNS).reindex(range(len(t)))
    g = g.assign(
        t=t, lat_deg=45.0 + 1e-5 * t, lon_deg=7.0, height_m=0.0, valid=True if valid is None else valid
    )
    return coerce(g, GNSS_COLUMNS)


def test_thinning_keeps_the_first_fix_after_each_wake_plus_time_to_fix() -> None:
    g = _gnss(np.arange(0.0, 100.0, 1.0))  # 1 Hz, t = 0..99
    kept = dc.thin_to_duty_cycle(g, 10.0, 1.0)
    assert kept["t"].tolist() == [1.0, 11.0, 21.0, 31.0, 41.0, 51.0, 61.0, 71.0, 81.0, 91.0]
    assert dc.thin_to_duty_cycle(g, 30.0, 2.5)["t"].tolist() == [3.0, 33.0, 63.0, 93.0]
    assert len(dc.thin_to_duty_cycle(g, None, 1.0)) == 100  # always on
    assert len(dc.thin_to_duty_cycle(g, 1.0, 1.0)) == 100  # cannot sleep: stays on
    # an invalid fix is never delivered: the next valid one in the same cycle is
    valid = np.ones(100, bool)
    valid[11] = False
    assert dc.thin_to_duty_cycle(_gnss(np.arange(0.0, 100.0), valid), 10.0, 1.0)["t"].tolist()[:3] == [
        1.0,
        12.0,
        21.0,
    ]
    assert len(g) == 100  # input untouched


def test_held_at_reads_the_latest_output_before_each_epoch() -> None:
    track = pd.DataFrame({"t": [1.0, 2.0, 5.0], "lat": [1.0, 2.0, 5.0], "lon": 0.0, "height": 0.0})
    h = dc.held_at(track, np.array([0.5, 1.0, 1.5, 4.9, 5.0, 9.0]))
    assert h["t"].tolist() == [1.0, 1.5, 4.9, 5.0, 9.0]  # 0.5 s is before the first output
    assert h["lat"].tolist() == [1.0, 1.0, 2.0, 5.0, 5.0]


def test_markdown_table_puts_battery_life_beside_the_error() -> None:
    acc = pd.DataFrame(
        {
            "case": "c",
            "engine": ["hold", "anchor"],
            "period_s": [math.nan, 10.0],
            "fixes": [100, 10],
            "n": [100, 100],
            "coverage": [1.0, 1.0],
            "h_p50": [1.0, 2.0],
            "h_p95": [2.0, 5.0],
            "h_rms": [1.2, 2.5],
            "h_max": [3.0, 8.0],
            "worse_than_hold": [False, True],
        }
    )
    df = dc.with_budgets(acc, DevicePower(), Battery())
    # hold always on: GNSS-only 124.2165 mW -> 59.57 h; anchor every 10 s: 63.5205 mW -> 116.50 h
    assert df["life_h"].round(2).tolist() == [59.57, 116.5]
    md = power_markdown(df, {"gnss": "paper", "imu": "paper", "mcu": "paper", "time_to_fix_s": 1.0})
    rows = [line for line in md.splitlines() if line.startswith("| ")]
    assert rows[1].startswith("| always on | hold | 79.2 | 124 | 59.6 |")
    assert rows[2].startswith("| 10 s | anchor | 7.96 | 63.5 | 116 |") and rows[2].endswith("| yes |")


def test_plan_power_on_husky_error_grows_with_the_fix_period(tmp_path: Path) -> None:
    out = tmp_path / "plan"
    args = ["plan", "power", "--logs", "husky", "--max-duration-s", "60", "--engines", "fixes"]
    res = runner.invoke(app, [*args, "--intervals", "5,30", "--out", str(out)])  # the dataset must be there
    assert res.exit_code == 0, res.output
    for f in ("power.html", "power.png", "power.md", "power.csv", "budget.csv", "summary.json"):
        assert (out / f).stat().st_size > 0
    df = pd.read_csv(out / "power.csv")
    assert len(df) == 6 and set(df["engine"]) == {"hold", "fixes"}  # (always on, 5 s, 30 s) x 2
    hold = df[df["engine"] == "hold"].reset_index(drop=True)
    assert math.isnan(hold["period_s"].iloc[0]) and hold["period_s"].tolist()[1:] == [5.0, 30.0]
    assert hold["fixes"].tolist() == [150, 12, 2]  # 60 s of 2.5 Hz fixes; one each 5 / 30 s
    # the Husky's truth is its own fixes: holding every fix is exact at the fix epochs
    assert hold["h_p95"].iloc[0] == 0.0
    p95 = hold["h_p95"].to_numpy()
    assert p95[0] < p95[1] < p95[2] and p95[2] > 10.0  # a robot at ~1 m/s, 30 s between fixes
    assert (df["coverage"] > 0.95).all()
    assert np.isfinite(df[["h_p50", "h_p95", "h_rms", "h_max"]].to_numpy()).all()
    # GNSS only, always on: 79.2 + 0.0165 + 45 = 124.2165 mW; 7400 mWh / 124.2165 mW = 59.57 h
    assert float(df["life_h"].iloc[0]) == pytest.approx(59.57, abs=0.005)
    assert hold["life_h"].is_monotonic_increasing
    html = (out / "power.html").read_text()
    assert "data:image/png;base64," in html and "husky" in html
    summary = json.loads((out / "summary.json").read_text())
    assert summary["periods_s"] == [None, 5.0, 30.0] and summary["gnss"] == "paper"
    assert "anchor-node paper" in summary["sources"]["gnss"]


def test_plan_power_energy_only_and_bad_input(tmp_path: Path) -> None:
    res = runner.invoke(app, ["plan", "power", "--no-accuracy", "--gnss", "sam-m8q", "--out", str(tmp_path)])
    assert res.exit_code == 0, res.output
    b = pd.read_csv(tmp_path / "budget.csv")
    assert not (tmp_path / "power.csv").exists()  # no accuracy measured
    # SAM-M8Q always on with the paper's IMU and MCU: 69 + 10.56 + 45 = 124.56 mW -> 7400 / 124.56 = 59.41 h
    row = b[(b["engine"] == "anchor") & b["period_s"].isna()].iloc[0]
    assert row["total_mw"] == pytest.approx(124.56) and row["life_h"] == pytest.approx(59.41, abs=0.005)
    assert sorted(set(b["engine"])) == ["anchor", "fixes"]
    bad = runner.invoke(app, ["plan", "power", "--no-accuracy", "--intervals", "0,10"])
    assert bad.exit_code == 2 and "positive" in bad.output
    bad = runner.invoke(app, ["plan", "power", "--no-accuracy", "--gnss", "nope"])
    assert bad.exit_code == 2 and "sam-m8q" in bad.output


def test_simulated_scooter_error_grows_with_the_fix_period() -> None:
    from iotnav.eval.outages import engine_factories

    fed, truth, prof = dc.simulated_case("scooter-laps", seed=0, overrides={"motion.laps": 1})
    cfg = dc.DutyCycleConfig(periods_s=(None, 10.0), engines=("fixes",))
    df = dc.run_case("sim", fed, truth, engine_factories(prof, cfg.engines, integrity=True), cfg)
    hold = df[df["engine"] == "hold"]["h_p95"].to_numpy()
    # the simulated receiver's own error always on (metres), then 10 s of riding at ~5 m/s
    assert 0.5 < hold[0] < 15.0 and hold[1] > 2.0 * hold[0]
    fixes = df[df["engine"] == "fixes"]
    assert len(fixes) == 2 and (fixes["coverage"] > 0.95).all()
    assert df["fixes"].tolist()[2] < df["fixes"].tolist()[0] / 5  # 1 Hz thinned to one per 10 s
