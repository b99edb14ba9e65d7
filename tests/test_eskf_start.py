"""eskf started anywhere (issue 16, items 1 and 2): in motion, raw gyro, unknown 3D mount.

Seeded and short: a real in-motion cut of drive_0708 (150 s), a simulated car cut at speed
(120 s), and a synthetic straight at constant speed where the mount is not observable.
Thresholds are the measured values with the margin stated at each assertion; the dataset
must be present (the test fails, not skips, without it).
"""

from __future__ import annotations

import math

import numpy as np
import pandas as pd
import pytest

from iotnav import sim
from iotnav.engines.base import run_batch
from iotnav.engines.eskf import EskfConfig, EskfEngine
from iotnav.eval.cases import cut_log, load_case
from iotnav.eval.metrics import track_errors
from iotnav.geo import euler_to_dcm
from iotnav.io.log import Log
from iotnav.io.schema import GNSS_COLUMNS, IMU_COLUMNS, coerce
from iotnav.techniques.mount3d import OBSERVABLE, UNOBSERVABLE, Mount3d, axis_status, mount_from_tilt


def _apart_deg(C: np.ndarray, C_ref: np.ndarray) -> float:
    """Rotation angle between two DCMs, deg."""
    c = (np.trace(C @ C_ref.T) - 1.0) / 2.0
    return math.degrees(math.acos(max(-1.0, min(1.0, c))))


def _longest_rejected_run(eng: EskfEngine) -> int:
    best = run = 0
    for rec in eng.nis_log.get("gnss_position", []):
        run = 0 if rec[3] else run + 1
        best = max(best, run)
    return best


@pytest.mark.parametrize("case", ["drive_0708-start100-bias1", "drive_0708-start100-bias3"])
def test_real_start_in_motion_finds_mount_and_keeps_fixes(case: str) -> None:
    """drive_0708 from 100 s (10.6 m/s), gyro bias 1 / 3 deg/s per axis, sensor turned 5 / 10 deg.

    Measured (150 s): mount committed at 12 / 28 s, 3.8 / 1.0 deg from the author's (turned)
    mount, longest run of rejected fixes 2 / 1, no gate reset, horizontal RMS after the commit
    1.48 / 1.33 m. Before the gravity aiding and the commitment bound, the 3 deg/s case put
    the mount 113 deg off, reset the gate 20 times and ran 2.3 km RMS off.
    """
    lc = load_case(case, max_duration_s=150.0)
    eng = EskfEngine(EskfConfig(**dict(lc.profile.eskf)))
    df = run_batch(eng, lc.fed)
    s = eng.summary()
    assert s["mount"]["status"] == OBSERVABLE
    assert _apart_deg(eng.nom.C_vb, lc.profile.author_C_vb()) < 6.0  # 3.8 measured, +50 %
    assert _longest_rejected_run(eng) <= 3  # 2 measured; the gate re-opens at 5
    assert s["event_counts"].get("gate_reset", 0) == 0
    t_commit = next(e["t"] for e in eng.events if e["type"] == "mount_initialised")
    assert t_commit - float(lc.truth.t.iloc[0]) < 40.0  # 12 / 28 s measured
    err = track_errors(df[df.source != "none"], lc.truth[["t", "lat", "lon", "height"]])
    after = err.h_err[err.t > t_commit]
    assert float(np.sqrt(np.mean(after**2))) < 2.5  # 1.48 / 1.33 m measured
    # the gyro bias is learnt while moving: the added bias plus the sensor's own, seen in the
    # turned sensor frame (b' = C_bb'^T b). The sensor's own: the raw gyro mean over the static
    # start of the full log, 0.00 / -0.06 / 0.09-0.17 deg/s (2-36 s and 5-30 s).
    own = np.array([0.0, -0.06, 0.13])
    C = euler_to_dcm(*np.radians(lc.case.rotate_rpy_deg))
    expected = C.T @ (lc.case.gyro_bias_dps + own)
    # measured 0.78 / 1.04 / 1.24 and 2.40 / 3.24 / 3.37 deg/s against 0.77 / 1.05 / 1.21
    # and 2.39 / 3.25 / 3.34: within 0.03; bound 0.15 (z: the in-run spread of its own bias)
    np.testing.assert_allclose(np.degrees(eng.nom.b_g), expected, atol=0.15)


def test_simulated_start_at_speed() -> None:
    """car-tunnel (MPU-6050, mount yaw -90 deg) cut at 40 s, at 5.6 m/s on an urban street.

    Measured (seed 0): heading at 74 s, mount 1.0 deg off, no gate reset, RMS 1.98 m from
    10 s after the heading. Before (a cruising levelling window taken as static, its mean rate
    as the gyro bias; any block-5 angle committed): mount 34 deg off, 18 gate resets, RMS 94 m.
    """
    res = sim.build("car-tunnel", seed=0, overrides={"duration_s": 160.0, "gnss.outages_s": ()})
    log = cut_log(Log(gnss=res.gnss, imu=res.imu, mag=res.mag), 40.0 - float(res.imu.t.iloc[0]))
    eng = EskfEngine(EskfConfig())
    df = run_batch(eng, log)
    levelled = next(e for e in eng.events if e["type"] == "levelled")
    assert not levelled["quiet"]  # in motion: the gyro bias is not the window's mean rate
    c = res.config
    C_true = euler_to_dcm(c.mount_roll_rad, c.mount_pitch_rad, c.mount_yaw_rad)
    assert _apart_deg(eng.nom.C_vb, C_true) < 3.0  # 1.0 measured (seeds 0-3: 0.2-1.0)
    s = eng.summary()
    assert s["event_counts"].get("gate_reset", 0) == 0
    t_h = next(e["t"] for e in eng.events if e["type"] == "heading_initialised")
    err = track_errors(df[df.source != "none"], res.truth)
    sel = err.t > t_h + 10.0
    assert sel.sum() > 1000
    assert float(np.sqrt(np.mean(err.h_err[sel] ** 2))) < 3.0  # 1.98 m measured (seeds 1-3: 1.1-1.2)


def _straight_log(seed: int = 0, duration_s: float = 90.0, speed_mps: float = 15.0) -> Log:
    """Level straight road at constant speed, heading north; sensor yawed 90 deg on its mount.

    MPU-6050-like noise (0.4 mg/rtHz at 100 Hz: 0.04 m/s^2; 5 mdps/rtHz), a 0.5 deg/s gyro
    bias, 1 Hz fixes of 1.5 m hAcc with 0.1 m/s velocity noise. Nothing here depends on the
    mount yaw (module docstring of :mod:`iotnav.techniques.mount`).
    """
    rng = np.random.default_rng(seed)
    g = 9.80665
    C_vb = euler_to_dcm(0.0, 0.0, math.pi / 2)
    C_nb = C_vb.T  # vehicle level, heading north: C_nv = I
    t = np.arange(0.0, duration_s, 0.01)
    f_b = C_nb.T @ np.array([0.0, 0.0, -g])
    acc = f_b[None, :] + rng.normal(0.0, 0.04, (t.size, 3))
    gyro = np.radians(0.5) + rng.normal(0.0, 0.0009, (t.size, 3))
    imu = coerce(
        pd.DataFrame(
            {
                "t": t,
                "acc_x": acc[:, 0],
                "acc_y": acc[:, 1],
                "acc_z": acc[:, 2],
                "gyro_x": gyro[:, 0],
                "gyro_y": gyro[:, 1],
                "gyro_z": gyro[:, 2],
            }
        ),
        IMU_COLUMNS,
    )
    tg = np.arange(0.5, duration_s, 1.0)
    north = speed_mps * tg + rng.normal(0.0, 1.0, tg.size)
    east = rng.normal(0.0, 1.0, tg.size)
    lat0, lon0 = 40.0, -105.0
    vn = speed_mps + rng.normal(0.0, 0.1, tg.size)
    ve = rng.normal(0.0, 0.1, tg.size)
    gnss = coerce(
        pd.DataFrame(
            {
                "t": tg,
                "lat_deg": lat0 + np.degrees(north / 6378137.0),
                "lon_deg": lon0 + np.degrees(east / (6378137.0 * math.cos(math.radians(lat0)))),
                "height_m": 1600.0 + rng.normal(0.0, 1.5, tg.size),
                "quality": 1,
                "num_sv": 12,
                "speed_mps": np.hypot(vn, ve),
                "course_rad": np.arctan2(ve, vn),
                "course_valid": True,
                "vn": vn,
                "ve": ve,
                "vd": rng.normal(0.0, 0.1, tg.size),
                "h_acc_m": 1.5,
                "v_acc_m": 2.5,
                "s_acc_mps": 0.1,
                "valid": True,
            }
        ),
        GNSS_COLUMNS,
    )
    return Log(gnss=gnss, imu=imu)


def test_mount_unobservable_on_a_straight_at_constant_speed() -> None:
    """No angle is reported where none is observable: status ``unobservable``, no mount, the
    output is the fix moved on at its velocity (source ``fix``), never dead reckoning."""
    eng = EskfEngine(EskfConfig())
    df = run_batch(eng, _straight_log())
    s = eng.summary()
    assert s["mount"]["status"] == UNOBSERVABLE
    assert s["mount"]["rpy_rad"] is None
    assert set(s["mount"]["axes"].values()) == {UNOBSERVABLE}
    assert all(math.isnan(a) for a in eng.mount_rpy_rad) and math.isnan(eng.mount_yaw_rad)
    assert not any(e["type"] in ("mount_initialised", "heading_initialised") for e in eng.events)
    out = df[df.source != "none"]
    assert len(out) > 8000 and set(out.source) == {"fix"}


def test_mount3d_commitment_and_axis_status() -> None:
    """The commitment bound and the per-axis status (closed form)."""
    m = Mount3d(commit_std_rad=0.1)
    assert not m.committable and math.isinf(m.yaw_std_rad) and math.isnan(m.mount_yaw_rad)
    m.aligner.known = True
    m.aligner.mount_yaw_rad = 1.0
    m.aligner.quality = {"std_rad": 0.3}
    assert not m.committable
    m.aligner.quality = {"std_rad": 0.05}
    assert m.committable
    cov = np.diag([0.5**2, 0.02**2, 0.05**2])
    assert axis_status(cov, True, 0.1) == [UNOBSERVABLE, OBSERVABLE, OBSERVABLE]
    assert axis_status(cov, False, 0.1) == [UNOBSERVABLE] * 3
    rep = m.report(None, None, 0.1)
    assert rep["status"] == UNOBSERVABLE and rep["rpy_rad"] is None
    # the level-vehicle mount keeps the sensor's roll and pitch, takes the given yaw
    C_nb = euler_to_dcm(0.1, -0.2, 2.0)
    C_vb = mount_from_tilt(C_nb, -0.5)
    np.testing.assert_allclose(C_vb, euler_to_dcm(0.1, -0.2, -0.5), atol=1e-12)
