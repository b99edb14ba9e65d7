"""Scenario-level effects of the Forno pipeline on the simulator (enabled when iotnav.sim imports).

Each scenario is shortened by overrides to keep the file well under two minutes.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from iotnav import sim
from iotnav.engines import Pipeline, PipelineConfig, run_batch
from iotnav.io.log import Log
from iotnav.techniques.last_position import StoredPosition


def _run(res, stored=None, cfg=None):
    log = Log(gnss=res.gnss, imu=res.imu, mag=res.mag)
    return run_batch(Pipeline(cfg or PipelineConfig(), stored=stored), log)


def _truth_at(res, t):
    tr = res.truth
    return {c: np.interp(t, tr.t, tr[c]) for c in ("north", "east", "vn", "ve")}


def _dwrap_deg(a: float, b: float) -> float:
    return abs((math.degrees(a - b) + 180.0) % 360.0 - 180.0)


@pytest.mark.slow
@pytest.mark.parametrize("mode", ["cruise", "accel-brake"])
@pytest.mark.parametrize("mount_deg", [0.0, 45.0, 90.0, 135.0, -90.0])
def test_scooter_laps_mount(mount_deg: float, mode: str) -> None:
    res = sim.build(
        "scooter-laps",
        seed=1,
        overrides={
            "motion.laps": 2,
            "mount_yaw_rad": math.radians(mount_deg),
            "motion.straight_mode": mode,
        },
    )
    df = _run(res)
    est = [e for e in df.attrs["events"] if e["type"] == "mount_estimate" and e["accepted"]]
    assert est, "no mount estimate"
    lap_s = 400.0 / (17.6 / 3.6)
    assert est[0]["t"] < 15.0 + lap_s  # during lap 1
    assert est[-1]["t"] > 15.0 + lap_s  # estimates continue over the following lap
    errs = [_dwrap_deg(e["mount_yaw_rad"], math.radians(mount_deg)) for e in est]
    assert max(errs) < 2.0, errs
    assert _dwrap_deg(df.attrs["mount_yaw_rad"], math.radians(mount_deg)) < 2.0


@pytest.mark.slow
def test_scooter_laps_static_agreement_and_rate() -> None:
    res = sim.build("scooter-laps", seed=2, overrides={"motion.laps": 1})
    df = _run(res)
    assert len(df) == len(res.imu)
    v = _truth_at(res, df.t.to_numpy())
    truth_static = np.hypot(v["vn"], v["ve"]) < 0.05
    assert np.mean(df.static.to_numpy() == truth_static) >= 0.95


def _path_length(p: np.ndarray) -> float:
    return float(np.hypot(*np.diff(p[:, :2], axis=0).T).sum())


@pytest.mark.slow
def test_static_courtyard_geofence() -> None:
    # the full 90 min of dataset A; GNSS errors correlated over minutes (courtyard: 300 s)
    res = sim.build("static-courtyard", seed=3)
    assert res.config.duration_s == 5400.0
    df = _run(res)
    assert df.static.mean() > 0.99
    df = df[df.source != "none"]  # no position before the first fix (no stored position here)
    fence = 15.0
    tr = res.truth
    from iotnav.geo import LocalFrame

    lf = LocalFrame(float(tr.lat.iloc[0]), float(tr.lon.iloc[0]), float(tr.height.iloc[0]))
    g = res.gnss[res.gnss.valid]
    raw = lf.to_ned(g.lat_deg.to_numpy(), g.lon_deg.to_numpy(), g.height_m.to_numpy())
    out = lf.to_ned(df.lat.to_numpy(), df.lon.to_numpy(), df.height.to_numpy())
    raw_r = np.hypot(raw[:, 0], raw[:, 1])
    out_r = np.hypot(out[:, 0], out[:, 1])
    # best averaging estimator on the same data: the mean of all fixes since the stop
    avg = np.cumsum(raw[:, :2], axis=0) / np.arange(1, len(raw) + 1)[:, None]
    avg_r = np.hypot(avg[:, 0], avg[:, 1])
    report = (
        f"max/p95 raw {raw_r.max():.1f}/{np.percentile(raw_r, 95):.1f} m, "
        f"filtered {out_r.max():.1f}/{np.percentile(out_r, 95):.1f} m, "
        f"best average {avg_r.max():.1f}/{np.percentile(avg_r, 95):.1f} m"
    )
    assert raw_r.max() > fence, report  # the raw GNSS leaves the geofence
    assert out_r.max() < fence, report
    assert _path_length(out) < 0.05 * _path_length(raw), report
    assert np.percentile(out_r, 95) <= np.percentile(raw_r, 95), report


@pytest.mark.slow
def test_walk_cold_boot_last_position() -> None:
    res = sim.build("walk-cold-boot", seed=4)
    lp = res.last_position
    assert lp is not None
    stored = StoredPosition(lp["lat"], lp["lon"], lp["height"])
    df = _run(res, stored=stored)
    ev = df.attrs["events"]
    first = next(e for e in ev if e["type"] == "first_fix")["t"]
    before = df[df.t < first]
    from iotnav.geo import LocalFrame

    tr = res.truth
    lf = LocalFrame(float(tr.lat.iloc[0]), float(tr.lon.iloc[0]), float(tr.height.iloc[0]))
    p = lf.to_ned(before.lat.to_numpy(), before.lon.to_numpy(), before.height.to_numpy())
    assert np.all(np.hypot(p[:, 0], p[:, 1]) < 5.0 + 0.0)
    g = res.gnss
    good = g[(g.valid) & (g.pdop <= 10.0)]
    assert first == pytest.approx(float(good.t.iloc[0]))
    v = _truth_at(res, df.t.to_numpy())
    truth_static = np.hypot(v["vn"], v["ve"]) < 0.05
    assert np.mean(df.static.to_numpy() == truth_static) >= 0.95


@pytest.mark.slow
def test_car_tunnel_outage_output_continues() -> None:
    res = sim.build("car-tunnel", seed=5)
    df = _run(res)
    assert len(df) == len(res.imu)
    dt = np.diff(df.t.to_numpy())
    assert dt.max() < 0.5
    assert (df.source == "dr").any()
