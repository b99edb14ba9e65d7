"""Cases of issue 16 (:mod:`iotnav.eval.cases`): transforms, the Husky loader, named cases, baselines."""

from __future__ import annotations

import math

import numpy as np
import pandas as pd
import pytest

from iotnav.eval import cases as C
from iotnav.eval import outages as O
from iotnav.geo import dcm_to_rpy, euler_to_dcm
from iotnav.io.log import Log
from iotnav.io.schema import GNSS_COLUMNS, IMU_COLUMNS, coerce, empty_table


def _log(n: int = 50, seed: int = 1) -> Log:
    rng = np.random.default_rng(seed)
    t = np.arange(n) * 0.01 + 5.0
    imu = pd.DataFrame({"t": t, **{c: rng.normal(size=n) for c in list(IMU_COLUMNS)[1:]}})
    g = empty_table(GNSS_COLUMNS).reindex(range(3))
    g = g.assign(t=[5.0, 5.2, 5.4], lat_deg=45.0, lon_deg=7.0, height_m=100.0, valid=True)
    return Log(gnss=coerce(g, GNSS_COLUMNS), imu=coerce(imu, IMU_COLUMNS))


def test_rotate_then_rotate_back_gives_the_log() -> None:
    log = _log()
    rpy = (math.radians(5.0), math.radians(10.0), math.radians(-30.0))
    back = dcm_to_rpy(euler_to_dcm(*rpy).T)
    out = C.rotate_sensor(C.rotate_sensor(log, rpy), back)
    np.testing.assert_allclose(out.imu.to_numpy(float), log.imu.to_numpy(float), atol=1e-12)


def test_rotate_sensor_expresses_vectors_in_the_turned_axes() -> None:
    # gravity's reaction (specific force) on +z_b up: f_b = (0, 0, -g) in NED-like axes (z down).
    # Turn the sensor +90 deg in pitch (nose up): its x axis now points up, so f along x is -g.
    log = _log(3)
    log.imu[["acc_x", "acc_y", "acc_z"]] = [0.0, 0.0, -9.81]
    out = C.rotate_sensor(log, (0.0, math.radians(90.0), 0.0))
    np.testing.assert_allclose(
        out.imu[["acc_x", "acc_y", "acc_z"]].to_numpy()[0], [9.81, 0.0, 0.0], atol=1e-9
    )
    # the mount follows: C_vb' = C_vb C_bb' with the profile storing C(rpy) = C_vb^T
    rpy = C.rotated_mount_rpy_deg((0.0, 0.0, 0.0), (0.0, math.radians(10.0), 0.0))
    np.testing.assert_allclose(rpy, (0.0, -10.0, 0.0), atol=1e-9)


def test_cut_bias_and_arrival_stamps() -> None:
    log = _log()
    cut = C.cut_log(log, 0.2)
    assert cut.imu.t.iloc[0] >= 5.2 - 1e-12 and len(cut.imu) == 30
    assert list(cut.gnss.t) == [5.2, 5.4]
    assert len(log.imu) == 50  # input untouched
    b = C.add_gyro_bias(log, (0.01, -0.02, 0.03))
    np.testing.assert_allclose(
        (b.imu[["gyro_x", "gyro_y", "gyro_z"]] - log.imu[["gyro_x", "gyro_y", "gyro_z"]]).to_numpy(),
        np.tile([0.01, -0.02, 0.03], (50, 1)),
    )
    np.testing.assert_array_equal(b.imu.acc_x, log.imu.acc_x)
    late = C.gnss_arrival_stamps(log.gnss, 0.2)
    np.testing.assert_allclose(late.t, log.gnss.t + 0.2)
    np.testing.assert_array_equal(late.lat_deg, log.gnss.lat_deg)
    with pytest.raises(ValueError):
        C.gnss_arrival_stamps(log.gnss, -0.1)


def test_dr_velocity_track_moves_the_last_fix_on() -> None:
    g = empty_table(GNSS_COLUMNS).reindex(range(1))
    g = coerce(
        g.assign(t=0.0, lat_deg=45.0, lon_deg=7.0, height_m=0.0, vn=10.0, ve=-5.0, valid=True), GNSS_COLUMNS
    )
    tr = O.gnss_dr_velocity_track(g, np.array([-1.0, 0.0, 10.0]))
    assert len(tr) == 2  # before the first fix: no row
    # 100 m north = 100 / 111132 deg at 45 deg (meridian degree), 50 m west
    assert tr.lat.iloc[1] - 45.0 == pytest.approx(100.0 / 111_132.0, rel=1e-3)
    assert tr.lon.iloc[1] - 7.0 == pytest.approx(-50.0 / (111_412.0 * math.cos(math.radians(45.0))), rel=2e-3)


def test_husky_loads_with_gravity_on_plus_y_and_the_mount() -> None:
    log, truth = C.load_husky()  # the dataset must be there: fails otherwise
    assert len(log.imu) == 11865 and len(log.gnss) == 989 and len(truth) == 989
    # at the 10.5 s stop (236.5-247 s after the start), specific force on +y, norm ~9.8
    t0 = log.imu.t.iloc[0]
    s = log.imu[(log.imu.t > t0 + 238) & (log.imu.t < t0 + 245)]
    f = s[["acc_x", "acc_y", "acc_z"]].mean().to_numpy()
    assert f[1] > 9.7 and abs(f[0]) < 0.5 and abs(f[2]) < 0.5
    # the profile's mount puts it on -z of the vehicle (up), as reaction to gravity: f_v = (0, 0, -g)
    f_v = C.HUSKY.author_C_vb() @ f
    assert f_v[2] < -9.7
    # the fix velocity: about 1 m/s while moving (README: mean 0.94 m/s)
    sp = log.gnss.speed_mps.to_numpy()
    assert 0.8 < np.nanmedian(sp) < 1.1
    assert log.gnss.h_acc_m.min() == pytest.approx(math.sqrt(2 * 0.64))


@pytest.mark.parametrize("name", ["drive_0708-start100-bias3", "husky", "walk_0827"])
def test_named_cases_load_and_carry_both_baselines(name: str) -> None:
    lc = C.load_case(name, max_duration_s=200.0 if name != "walk_0827" else None)
    info = C.case_summary(lc)
    if name.startswith("drive"):
        assert info["start_speed_mps"] > 5.0  # starts in motion
        assert lc.fed.imu.t.iloc[0] >= lc.truth.t.iloc[0] - 0.02
        # the bias is in: the raw gyro mean over the case is near 3 deg/s on each axis
        assert np.all(
            np.abs(lc.fed.imu[["gyro_x", "gyro_y", "gyro_z"]].mean().to_numpy()) > math.radians(1.5)
        )
    res = O.study(lc.fed, lc.truth, lc.profile, lc.config, factories={}, fed=lc.fed)
    eng = set(res.summary.engine)
    assert eng == {O.HOLD, O.DR_VELOCITY}
    s = res.summary.set_index(["engine", "length_s"])
    for L in lc.config.lengths_s:
        assert s.loc[(O.HOLD, L), "n_windows"] >= 1
        assert np.isfinite(s.loc[(O.DR_VELOCITY, L), "median_drift_pct"])
