"""Every named scenario runs (shortened), writes its files; motion facts; overrides; CLI."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
import typer
from typer.testing import CliRunner

from iotnav import sim
from iotnav.cli import simulate as simulate_cli

SHORT: dict[str, dict[str, object]] = {
    "static-courtyard": {"duration_s": 120},
    "scooter-laps": {"motion.laps": 1},
    "walk-cold-boot": {"duration_s": 150},
    "car-tunnel": {"duration_s": 120},
    "car-magnetometer": {},
    "pedestrian-fixes": {"motion.laps": 1},
    "static-imu-6h": {"duration_s": 300},
}


def test_every_scenario_is_covered() -> None:
    assert set(SHORT) == set(sim.list_scenarios())


@pytest.mark.parametrize("name", list(SHORT))
def test_scenario_runs_and_writes(name: str, tmp_path: Path) -> None:
    r = sim.build(name, seed=1, overrides=SHORT[name])
    files = {p.name for p in sim.write(r, tmp_path)}
    assert {"truth.csv", "scenario.json", "imu.csv"} <= files
    truth = pd.read_csv(tmp_path / "truth.csv")
    assert list(truth.columns) == [
        "t",
        "lat",
        "lon",
        "height",
        "north",
        "east",
        "down",
        "vn",
        "ve",
        "vd",
        "roll",
        "pitch",
        "yaw",
    ]
    assert np.allclose(np.diff(truth["t"]), 1.0 / max(r.config.imu.rate_hz, 10.0))
    doc = json.loads((tmp_path / "scenario.json").read_text())
    for k in (
        "seed",
        "origin",
        "utc_offset_s",
        "mount_roll_rad",
        "mount_pitch_rad",
        "mount_yaw_rad",
        "config",
    ):
        assert k in doc
    assert doc["seed"] == 1
    if r.config.gnss.enabled:
        assert "gnss.nmea" in files
    if name == "walk-cold-boot":
        assert "last_position.json" in files
    if name == "pedestrian-fixes":
        fx = pd.read_csv(tmp_path / "fixes.csv")
        assert list(fx.columns) == [
            "t_valid",
            "t_arrival",
            "lat",
            "lon",
            "height",
            "roll",
            "pitch",
            "yaw",
            "sigma_pos_m",
            "sigma_att_rad",
        ]
        assert np.allclose(fx["t_arrival"] - fx["t_valid"], 0.5)
        assert np.allclose(np.diff(fx["t_valid"]), 1.0)
    if name == "car-magnetometer":
        imu = pd.read_csv(tmp_path / "imu.csv")
        assert "mag_x_ut" in imu.columns
        rate = imu["mag_x_ut"].notna().sum() / imu["t"].iloc[-1]
        assert rate == pytest.approx(6.0, rel=0.02)


def test_scooter_track_geometry_and_speed() -> None:
    r = sim.build("scooter-laps", seed=0, overrides={"motion.laps": 3, "gnss.enabled": False})
    tr = r.truth
    speed = np.hypot(tr["vn"], tr["ve"]).to_numpy()
    t = tr["t"].to_numpy()
    moving = speed > 0.01
    dist = np.sum(speed[moving]) * (t[1] - t[0])
    # 3 laps of a 400 m track (the start acceleration is on the first straight) plus braking
    v = 17.6 / 3.6
    assert dist == pytest.approx(3 * 400.0 + 0.5 * v * v / 0.8, rel=0.002)
    lap_speed = speed[(speed > 4.8) & (speed < 5.0)]
    assert len(lap_speed) > 0.8 * moving.sum()
    assert np.median(speed[moving]) * 3.6 == pytest.approx(17.6, rel=0.01)
    # counter-clockwise: heading decreases through the curves
    yaw = np.unwrap(tr["yaw"].to_numpy())
    assert yaw[-1] - yaw[0] == pytest.approx(-6 * np.pi, abs=0.01)
    # the track closes: the scooter passes its start point after each lap (straight is 100 m long)
    ne = tr[["north", "east"]].to_numpy()
    start = ne[np.argmax(moving)]
    assert np.min(np.hypot(*(ne[moving][-500:] - start).T)) < 20.0
    # accel-brake straights keep the mean but vary the speed on the straights
    ab = sim.build(
        "scooter-laps",
        seed=0,
        overrides={"motion.laps": 2, "motion.straight_mode": "accel-brake", "gnss.enabled": False},
    )
    s2 = np.hypot(ab.truth["vn"], ab.truth["ve"]).to_numpy()
    assert s2.max() > 6.0


def test_walk_returns_near_start_and_stays_static_first() -> None:
    r = sim.build("walk-cold-boot", seed=2, overrides={"gnss.enabled": False})
    tr = r.truth
    ne = tr[["north", "east"]].to_numpy()
    assert np.abs(ne[tr["t"] < 60]).max() == 0.0
    assert np.hypot(*ne[-1]) < 2.0
    assert np.hypot(*ne.T).max() > 40.0


def test_overrides_typed_and_errors() -> None:
    cfg = sim.apply_overrides(
        sim.default_config("car-tunnel"),
        {
            "imu.preset": "lsm6ds3",
            "duration_s": "300",
            "gnss.outages_s": "[[10, 20]]",
            "imu.errors": "false",
            "imu.gyro_noise_density_mdps_rthz": "3",
        },
    )
    assert cfg.imu.preset == "lsm6ds3" and cfg.duration_s == 300.0 and cfg.gnss.outages_s == ((10.0, 20.0),)
    assert cfg.imu.errors is False and dict(cfg.imu.spec)["gyro_noise_density_mdps_rthz"] == 3.0
    with pytest.raises(ValueError, match=r"unknown parameter .imu\.nope."):
        sim.apply_overrides(cfg, {"imu.nope": 1})
    with pytest.raises(ValueError, match="duration_s: expected a number"):
        sim.apply_overrides(cfg, {"duration_s": "ten"})
    with pytest.raises(ValueError, match=r"motion\.laps"):
        sim.apply_overrides(cfg, {"motion.laps": 3})  # car motion has no laps
    with pytest.raises(ValueError, match="unknown scenario"):
        sim.build("nope")
    with pytest.raises(ValueError, match="must divide"):
        sim.build("car-tunnel", overrides={"imu.rate_hz": 30, "duration_s": 10})


def test_cli_list_and_simulate(tmp_path: Path) -> None:
    app = typer.Typer()
    simulate_cli.register(app)

    @app.command("noop")
    def _noop() -> None:  # a second command keeps typer in multi-command mode
        pass

    runner = CliRunner()
    res = runner.invoke(app, ["simulate", "--list"])
    assert res.exit_code == 0 and "scooter-laps" in res.output
    res = runner.invoke(
        app, ["simulate", "car-tunnel", "--out", str(tmp_path), "--seed", "4", "--set", "duration_s=30"]
    )
    assert res.exit_code == 0, res.output
    doc = json.loads((tmp_path / "scenario.json").read_text())
    assert doc["seed"] == 4 and doc["config"]["duration_s"] == 30.0
    res = runner.invoke(app, ["simulate", "car-tunnel", "--out", str(tmp_path), "--set", "imu.bogus=1"])
    assert res.exit_code == 2 and "unknown parameter" in res.output


def test_mag_calibration_is_the_drawn_hard_and_soft_iron() -> None:
    r = sim.build("car-magnetometer", seed=3, overrides={"duration_s": 5.0})
    hard, soft = r.mag_calibration()
    md = r.meta["mag_draw"]
    assert hard == tuple(md["hard_iron_ut"]) and len(soft) == 9
    assert soft == tuple(v for row in md["soft_iron"] for v in row)
    with pytest.raises(ValueError, match="no magnetometer"):
        sim.build("car-tunnel", seed=0, overrides={"duration_s": 5.0}).mag_calibration()
