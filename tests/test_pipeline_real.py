"""The Forno pipeline on a real car drive (rtklibexplorer GNSS_IMU ``drive_0708``).

A consumer IMU (ICM-45686, ~100 Hz) mounted with its z axis up (roll ~180 deg) and its x axis
about backwards, and a 4 Hz RTK receiver reporting ~1 cm accuracies (``h_acc_m``, ``v_acc_m``)
and an NED velocity. The first 260 s (38 s parked, then residential streets on a hill) go
through :func:`iotnav.io.ingest` and :class:`iotnav.engines.Pipeline` with the default
configuration.

References, not computed by the code under test:

* positions: the RTK input itself, interpolated linearly to the output times, both converted
  to local north/east with a flat-earth approximation written out here;
* mount yaw: the dataset author's IMU rotation, RPY ``[180, 0, 180] + [0, -6.79, 5.35]`` deg
  (upstream ``src/drive_config.py``), i.e. a yaw of 185.35 deg = -174.65 deg; the ESKF engine
  finds -174.9 deg.

Block 5 on this drive (whole recording, default configuration): the gravity reference of the
mount aligner is only renewed at the three stops (the car is never unaccelerated for 5 GNSS
intervals while driving), so on the hilly streets a grade and bank unlike the reference's leak
gravity into whole buffers. The levelled buffers' angles then scatter by 25 deg rms about the
author's value, 3-5 times their own ``sigma``; the demeaned buffers by 6-11 deg, consistent
with theirs. ``auto_demean`` selects the demeaned form by its consistency (Birge ratio), and
the settled acceptance takes its estimate once it has stayed within 1 deg for 60 s although its
``sigma`` (1.2-1.7 deg at 1 Hz) does not reach 1 deg within the drive.
"""

from __future__ import annotations

import dataclasses
import math
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from iotnav.engines import Pipeline, PipelineConfig, run_batch
from iotnav.eval import outages as O
from iotnav.io import ingest
from iotnav.io.log import Log

DRIVE = "rtklibexplorer_gnss_imu/drive_0708"
SPAN_S = 260.0
AUTHOR_MOUNT_YAW_DEG = 180.0 + 5.35 - 360.0
R_EARTH_M = 6371008.8


def _dwrap_deg(a_deg: float, b_deg: float) -> float:
    return abs((a_deg - b_deg + 180.0) % 360.0 - 180.0)


def _flat_ne(lat: np.ndarray, lon: np.ndarray, lat0: float, lon0: float) -> np.ndarray:
    """North/east (m) of lat/lon (deg) about (lat0, lon0), flat earth (mm-level over 2 km)."""
    n = np.radians(lat - lat0) * R_EARTH_M
    e = np.radians(lon - lon0) * R_EARTH_M * math.cos(math.radians(lat0))
    return np.column_stack([n, e])


@pytest.fixture(scope="module")
def drive(datasets: Path) -> tuple[pd.DataFrame, pd.DataFrame, Pipeline]:
    d = datasets / DRIVE
    log = ingest([d / "gnss_1934_sf.pos", d / "imu_1934.csv"])
    t0 = float(log.gnss.t.iloc[0])
    log.gnss = log.gnss[log.gnss.t < t0 + SPAN_S].reset_index(drop=True)
    log.imu = log.imu[log.imu.t < t0 + SPAN_S].reset_index(drop=True)
    engine = Pipeline(PipelineConfig())
    return run_batch(engine, log), log.gnss, engine


@pytest.fixture(scope="module")
def whole(datasets: Path) -> tuple[Log, Log]:
    """The whole drive: as recorded (4 Hz RTK) and as the outage study feeds it (1 Hz, metres)."""
    from iotnav.cli.outages import load_dataset

    log, prof = load_dataset(datasets / DRIVE)
    return log, O.degraded_feed(log, O.rtk_truth(log.gnss), prof)[0]


def _mount_run(log: Log, **mount: object) -> tuple[Pipeline, list[dict]]:
    base = PipelineConfig()
    engine = Pipeline(base.replace(mount=dataclasses.replace(base.mount, **mount)))
    run_batch(engine, log)
    return engine, [e for e in engine.events if e["type"] == "mount_estimate"]


def test_fix_rows_follow_rtk(drive: tuple[pd.DataFrame, pd.DataFrame, Pipeline]) -> None:
    df, gnss, _ = drive
    fix = df[df.source == "fix"]
    assert len(fix) > 0.6 * len(df)
    lat0, lon0 = float(gnss.lat_deg.iloc[0]), float(gnss.lon_deg.iloc[0])
    ref = _flat_ne(gnss.lat_deg.to_numpy(), gnss.lon_deg.to_numpy(), lat0, lon0)
    t = fix.t.to_numpy()
    ref_t = np.column_stack([np.interp(t, gnss.t, ref[:, 0]), np.interp(t, gnss.t, ref[:, 1])])
    out = _flat_ne(fix.lat.to_numpy(), fix.lon.to_numpy(), lat0, lon0)
    err = np.hypot(*(out - ref_t).T)
    assert np.percentile(err, 95) < 0.5, np.percentile(err, [50, 95, 100])


@pytest.mark.parametrize("feed", ["rtk_4hz", "degraded_1hz"])
def test_mount_found_near_author_yaw(whole: tuple[Log, Log], feed: str) -> None:
    log = whole[0] if feed == "rtk_4hz" else whole[1]
    engine, est = _mount_run(log)
    cfg = engine.config.mount
    accepted = [e for e in est if e["accepted"]]
    assert accepted, "mount never accepted"
    for e in accepted:
        assert _dwrap_deg(math.degrees(e["mount_yaw_rad"]), AUTHOR_MOUNT_YAW_DEG) < 2.0
        bound = cfg.max_std_rad * (cfg.settle_std_factor if e["settled"] else 1.0)
        assert e["std_rad"] <= bound
    assert engine.mount.known
    assert _dwrap_deg(math.degrees(engine.mount_yaw_rad), AUTHOR_MOUNT_YAW_DEG) < 1.5
    # the demeaned form carries the estimate, and is consistent across buffers
    assert est[-1]["demeaned"] == 1.0 and est[-1]["consistency"] < 1.5
    # the fused standard deviation shrinks as buffers accumulate
    stds = [e["std_rad"] for e in est]
    assert stds[-1] < 0.5 * stds[0]


def test_provisional_mount_before_acceptance(whole: tuple[Log, Log]) -> None:
    """On the 1 Hz feed the mount is accepted late (settled, about 380 s in); before that the
    fused estimate already rejects the initial 0 deg at 3 sigma and is applied provisionally.
    Accepted estimates do not change (the aligner levels against its own gravity reference)."""
    log = whole[1]
    t0 = float(log.gnss.t.iloc[0])
    _, est = _mount_run(log)
    _, est_off = _mount_run(log, provisional_sigmas=0.0)
    firm = [(e["t"], e["mount_yaw_rad"]) for e in est if e["accepted"]]
    assert firm and firm == [(e["t"], e["mount_yaw_rad"]) for e in est_off if e["accepted"]]
    prov = [e for e in est if e["provisional"]]
    assert prov and all(e["t"] < firm[0][0] and not e["accepted"] and e["applied"] for e in prov)
    assert prov[0]["t"] - t0 < 70.0, prov[0]["t"] - t0
    for e in prov:  # each within 3 of its sigma, and 8 deg, of the author's angle
        err = _dwrap_deg(math.degrees(e["mount_yaw_rad"]), AUTHOR_MOUNT_YAW_DEG)
        assert err < min(8.0, 3.0 * math.degrees(e["std_rad"])), (e["t"] - t0, err)


def test_provisional_mount_dead_reckons_the_right_way(whole: tuple[Log, Log]) -> None:
    """Effect: a 30 s GNSS outage 60 s into the moving part, long before acceptance. With the
    provisional mount the end error is a fraction of the distance driven; without it the
    accelerations are integrated about 175 deg off and the error exceeds the distance.
    Observed: 148 m vs 487 m over 205 m."""
    log = whole[1]
    truth = O.rtk_truth(whole[0].gnss).sort_values("t").reset_index(drop=True)
    m0, _ = O.moving_part(truth, 0.5)
    start = m0 + 60.0
    masked = Log(gnss=O.mask_windows(log.gnss, [(start, 30.0)]), imu=log.imu)
    base = PipelineConfig()
    end_err = {}
    for k in (3.0, 0.0):
        cfg = base.replace(mount=dataclasses.replace(base.mount, provisional_sigmas=k))
        df = run_batch(Pipeline(cfg), masked)
        row = df[df.t < start + 30.0].iloc[-1]
        lat0 = float(truth.lat.iloc[0])
        lon0 = float(truth.lon.iloc[0])
        ref = _flat_ne(
            np.array([np.interp(row.t, truth.t, truth.lat)]),
            np.array([np.interp(row.t, truth.t, truth.lon)]),
            lat0,
            lon0,
        )
        out = _flat_ne(np.array([row.lat]), np.array([row.lon]), lat0, lon0)
        end_err[k] = float(np.hypot(*(out - ref)[0]))
    sel = (truth.t >= start) & (truth.t <= start + 30.0)
    ne = _flat_ne(
        truth.lat[sel].to_numpy(),
        truth.lon[sel].to_numpy(),
        float(truth.lat.iloc[0]),
        float(truth.lon.iloc[0]),
    )
    dist = float(np.hypot(*np.diff(ne, axis=0).T).sum())
    assert end_err[3.0] < 0.9 * dist, (end_err, dist)
    assert end_err[0.0] > dist, (end_err, dist)
    assert end_err[3.0] < 0.4 * end_err[0.0], end_err


def _buffer_scatter(est: list[dict]) -> float:
    """Rms of the useful buffers' angle errors (about the author's yaw) over their own sigma."""
    useful = [e for e in est if e["buffer_coherence"] >= 0.7 and e["buffer_excitation_mps2"] >= 0.3]
    err = np.radians(
        [_dwrap_deg(math.degrees(e["buffer_mount_yaw_rad"]), AUTHOR_MOUNT_YAW_DEG) for e in useful]
    )
    sig = np.array([e["buffer_std_rad"] for e in useful])
    return float(np.sqrt(np.mean((err / sig) ** 2)))


def test_levelled_form_alone_is_inconsistent_on_the_hilly_drive(whole: tuple[Log, Log]) -> None:
    """The cause: with the levelled form alone (the behaviour before ``auto_demean``) the 1 Hz
    feed never reaches an accepted mount, and its buffers disagree beyond their sigma; the
    demeaned buffers do not."""
    engine, est = _mount_run(whole[1], auto_demean=False)
    assert not engine.mount.accepted_once
    assert est[-1]["std_rad"] > math.radians(3.0)
    _, est_dm = _mount_run(whole[1], auto_demean=False, demean_buffers=True)
    assert _buffer_scatter(est) > 2.0
    assert _buffer_scatter(est_dm) < 0.6 * _buffer_scatter(est)


def test_upside_down_sensor_levels(drive: tuple[pd.DataFrame, pd.DataFrame, Pipeline]) -> None:
    df, _, engine = drive
    # parked at the start, sensor z up: |roll| near 180 deg from the first sample on
    first = df.iloc[:300]
    assert np.all(np.abs(np.degrees(first.roll.to_numpy())) > 170.0)
    assert engine.cascade.tilt.x[2] < -0.95  # down axis along -z of the sensor


def test_provisional_mount_is_not_stored(whole: tuple[Log, Log], tmp_path: Path) -> None:
    """The last-known-position store keeps only an accepted mount: a provisional angle would come
    back at the next boot as a calibration (with ``one_off``, for good). The first 300 s of the
    1 Hz feed: provisional from about 60 s, no acceptance yet."""
    from iotnav.techniques.last_position import LastPositionStore

    full = whole[1]
    t0 = float(full.gnss.t.iloc[0])
    log = Log(gnss=full.gnss[full.gnss.t < t0 + 300.0], imu=full.imu[full.imu.t < t0 + 300.0])
    store = LastPositionStore(tmp_path / "dev.json")
    engine = Pipeline(PipelineConfig(), store=store)
    run_batch(engine, log)
    assert engine.mount.known and engine.mount.provisional and not engine.mount.accepted_once
    saved = store.load()
    assert saved is not None and math.isnan(saved.mount_yaw_rad)
