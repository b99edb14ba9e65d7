"""The Forno pipeline engine: streaming = batch, configuration, output rate, boot, geofence."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from _pipeline_synth import H0, K_N, LAT0, LON0, G, laps, make_log
from iotnav.engines import GnssSample, ImuSample, Pipeline, PipelineConfig, run_batch
from iotnav.engines.base import OUTPUT_COLUMNS
from iotnav.engines.config import EngineConfig
from iotnav.io.log import Log
from iotnav.io.schema import GNSS_COLUMNS, coerce
from iotnav.techniques.last_position import LastPositionStore, StoredPosition
from iotnav.techniques.static import StaticConfig

CFG = PipelineConfig(pipeline=EngineConfig(gravity_mps2=G))


def test_batch_and_streaming_identical() -> None:
    log, _ = make_log(laps(1), mount_yaw=math.radians(90.0), seed=7)
    batch = run_batch(Pipeline(CFG), log)
    eng = Pipeline(CFG)
    rows = []
    gi = 0
    g = log.gnss
    for k in range(len(log.imu)):
        r = log.imu.iloc[k]
        while gi < len(g) and g["t"].iat[gi] <= r["t"]:  # GNSS first at equal times
            e = g.iloc[gi]
            eng.step(
                GnssSample(
                    e.t,
                    e.lat_deg,
                    e.lon_deg,
                    e.height_m,
                    e.pdop,
                    e.hdop,
                    int(e.num_sv),
                    e.speed_mps,
                    e.course_rad,
                    bool(e.course_valid),
                    bool(e.valid),
                )
            )
            gi += 1
        acc = np.array([r.acc_x, r.acc_y, r.acc_z])
        gyr = np.array([r.gyro_x, r.gyro_y, r.gyro_z])
        rows.append(eng.step(ImuSample(r.t, acc, gyr)))
    stream = pd.DataFrame(rows, columns=list(OUTPUT_COLUMNS))
    num = [c for c in OUTPUT_COLUMNS if c not in ("source", "static")]
    np.testing.assert_allclose(stream[num].to_numpy(float), batch[num].to_numpy(float), atol=1e-9, rtol=0)
    assert (stream.source == batch.source).all() and (stream.static == batch.static).all()
    assert eng.events == batch.attrs["events"]


def test_output_rate_columns_and_30s_outage() -> None:
    log, _truth = make_log(laps(2), mount_yaw=0.4, imu_hz=20.0, seed=2, gnss_gap=(40.0, 70.0))
    df = run_batch(Pipeline(CFG), log)
    assert list(df.columns) == list(OUTPUT_COLUMNS)
    assert len(df) == len(log.imu)  # one row per IMU sample
    np.testing.assert_array_equal(df.t.to_numpy(), log.imu.t.to_numpy())
    gap = df[(df.t > 42.0) & (df.t < 70.0)]
    assert (gap.source == "dr").all()
    assert np.all(np.diff(gap.std_north.to_numpy()) > 0)
    assert df.attrs["summary"]["config"]["static"]["theta_a_mps2"] == 0.125


def test_config_toml_round_trip(tmp_path: Path) -> None:
    p = tmp_path / "c.toml"
    p.write_text('[static]\ntheta_a_mps2 = 0.2\n[lowpass3]\nn1 = 5\n[mount]\nmethod = "paper"\n')
    c = PipelineConfig.from_toml(p)
    assert c.static.theta_a_mps2 == 0.2 and c.lowpass3.n1 == 5 and c.mount.method == "paper"
    assert c.last_position.max_pdop == 10.0  # paper default kept
    assert PipelineConfig.from_dict(c.to_dict()) == c
    p.write_text("[static]\ntheta = 1\n")
    with pytest.raises(ValueError, match="theta"):
        PipelineConfig.from_toml(p)
    # a key of an earlier version says why it is gone
    p.write_text("[fusion]\nvertical_ratio = 2.0\n")
    with pytest.raises(ValueError, match=r"vertical_ratio was removed.*iotnav.gnss_accuracy"):
        PipelineConfig.from_toml(p)


def _gnss_table(t, n_m, e_m, pdop, speed=0.0):
    m = len(t)
    return coerce(
        pd.DataFrame(
            {
                "t": t,
                "lat_deg": LAT0 + np.asarray(n_m) / K_N,
                "lon_deg": LON0 + np.asarray(e_m) / (K_N * math.cos(math.radians(LAT0))),
                "height_m": np.full(m, H0),
                "pdop": pdop,
                "hdop": np.asarray(pdop) / 1.5,
                "num_sv": np.full(m, 7),
                "speed_mps": np.full(m, speed),
                "course_rad": np.zeros(m),
                "course_valid": np.zeros(m, bool),
                "valid": np.ones(m, bool),
            }
        ),
        GNSS_COLUMNS,
    )


def test_cold_boot_outputs_stored_position_until_good_fix(tmp_path: Path) -> None:
    log, _ = make_log([(60.0, 0.0, 0.0)], imu_hz=10.0, seed=3)
    t = log.gnss.t.to_numpy()
    bad = t < 30.0
    rng = np.random.default_rng(0)
    n = np.where(bad, 300.0 + rng.normal(0, 50, t.size), rng.normal(0, 1.0, t.size))
    e = np.where(bad, -200.0 + rng.normal(0, 50, t.size), rng.normal(0, 1.0, t.size))
    pdop = np.where(bad, 25.0, 1.8)
    log = Log(gnss=_gnss_table(t, n, e, pdop), imu=log.imu)
    store = LastPositionStore(tmp_path / "dev.json")
    store.save(StoredPosition(LAT0 + 2.0 / K_N, LON0, H0))
    df = run_batch(Pipeline(CFG, store=store), log)
    before = df[df.t < 30.0]
    assert (before.source == "last_position").all()
    assert np.all(np.hypot(before.north, before.east) < 5.0)
    ev = df.attrs["events"]
    assert sum(x["type"] == "fix_rejected" and x["reason"] == "pdop" for x in ev) == int(bad.sum())
    assert next(x for x in ev if x["type"] == "first_fix")["t"] == pytest.approx(30.0)
    assert not any(x["type"] == "moved_while_off" for x in ev)
    assert (tmp_path / "dev.json").exists()


def test_static_geofence_and_apparent_distance() -> None:
    # device at rest 10 minutes; GNSS wanders as a slow random walk with jumps (multipath)
    T = 600.0
    log, _ = make_log([(T, 0.0, 0.0)], imu_hz=4.0, seed=4)
    t = log.gnss.t.to_numpy()
    rng = np.random.default_rng(11)
    walk = np.cumsum(rng.normal(0, 0.8, (t.size, 2)), axis=0)
    walk -= walk.mean(axis=0)
    walk += np.where(rng.random((t.size, 1)) < 0.03, rng.normal(0, 15.0, (t.size, 2)), 0.0)
    log = Log(gnss=_gnss_table(t, walk[:, 0], walk[:, 1], np.full(t.size, 2.0), speed=0.1), imu=log.imu)
    cfg = PipelineConfig(pipeline=EngineConfig(gravity_mps2=G), static=StaticConfig())
    df = run_batch(Pipeline(cfg), log)
    raw_r = np.hypot(*walk.T)
    assert raw_r.max() > 15.0  # the raw GNSS leaves the 15 m geofence
    r = np.hypot(df.north, df.east)
    assert r.max() < 15.0
    raw_dist = np.hypot(*np.diff(walk, axis=0).T).sum()
    dist = np.hypot(np.diff(df.north), np.diff(df.east)).sum()
    assert dist < 0.05 * raw_dist
    assert np.percentile(r, 95) <= np.percentile(raw_r, 95)
    assert df.static.mean() > 0.95
