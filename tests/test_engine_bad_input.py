"""Bad input to every engine: counted, reported skips, never NaN for the rest of the run.

A NaN IMU sample passed straight to ``step()`` used to leave ``pipeline``, ``anchor`` and
``eskf`` outputting NaN for the rest of the run and made ``qekf`` raise; a GNSS course flagged
valid but NaN did the same to ``pipeline``/``anchor``/``qekf``, a fix without height to
``pipeline``. Every engine now passes samples through one :class:`~iotnav.engines.base.InputGuard`.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from iotnav import sim
from iotnav.engines.base import GnssSample, ImuSample, MagSample, Output, Sample, iter_samples, run_batch
from iotnav.engines.registry import ENGINE_NAMES, make_engine
from iotnav.io import ingest
from iotnav.io.log import Log

G = 9.80665
T_BAD = 50.0  # bad samples go in after the qekf's 40 s static initialisation


@pytest.fixture(scope="module")
def log(tmp_path_factory: pytest.TempPathFactory) -> Log:
    d = tmp_path_factory.mktemp("car_mag")
    r = sim.build("car-magnetometer", seed=0, overrides={"duration_s": 60.0})
    sim.write(r, d)
    return ingest([Path(d)])


def _final(outs: list[Output]) -> np.ndarray:
    o = outs[-1]
    return np.array([o.t, o.north, o.east, o.down, o.vn, o.ve, o.roll, o.pitch, o.yaw, o.std_north])


def _run(name: str, samples: list[Sample]) -> tuple[list[Output], dict[str, int]]:
    eng = make_engine(name)
    outs = [o for s in samples if (o := eng.step(s)) is not None]
    return outs, eng.summary()["skipped"]


@pytest.mark.parametrize("name", ENGINE_NAMES)
def test_rejected_samples_change_nothing(name: str, log: Log) -> None:
    """NaN / infinite values and times, samples out of order: no output for them, counted by
    reason, and the run ends exactly where the clean run ends."""
    samples = list(iter_samples(log))
    k = next(i for i, s in enumerate(samples) if s.t > T_BAD)
    t0 = samples[k].t
    up = np.array([0.0, 0.0, -G])
    bad: list[Sample] = [
        ImuSample(t0, np.array([math.nan, 0.0, -G]), np.zeros(3)),
        ImuSample(t0, up, np.array([0.0, math.inf, 0.0])),
        ImuSample(math.nan, up, np.zeros(3)),
        ImuSample(t0 - 5.0, up, np.zeros(3)),
        GnssSample(t0, math.nan, 7.0, 300.0),
        GnssSample(math.nan, 45.0, 7.0, 300.0),
        GnssSample(t0 - 3.0, 45.0, 7.0, 300.0, num_sv=9, pdop=1.0, h_acc_m=2.0),
        MagSample(t0, np.array([math.nan, 0.0, 40.0])),
        MagSample(t0 - 2.0, np.array([20.0, 0.0, 40.0])),
    ]
    clean, sk_clean = _run(name, samples)
    dirty, sk = _run(name, samples[:k] + bad + samples[k:])
    assert sk_clean == {}
    assert sk == {
        "imu_nonfinite": 3,
        "imu_time_backwards": 1,
        "gnss_nonfinite": 2,
        "gnss_time_backwards": 1,
        "mag_nonfinite": 1,
        "mag_time_backwards": 1,
    }
    # one row per IMU sample; the GNSS-only engine gives one per GNSS epoch
    assert len(dirty) == len(clean) == (len(log.gnss) if name == "fixes" else len(log.imu))
    np.testing.assert_array_equal(_final(dirty), _final(clean))


@pytest.mark.parametrize("name", ["pipeline", "anchor", "qekf", "eskf", "pdr"])
def test_gnss_fields_missing_keep_the_output_finite(name: str, log: Log) -> None:
    """Fixes without height, velocity, accuracy or DOP, or with a NaN course flagged valid
    (10 s of them): positions, attitude and sigmas stay finite; the bad course is counted."""
    samples, n_bad = [], 0
    for s in iter_samples(log):
        if isinstance(s, GnssSample) and T_BAD < s.t < T_BAD + 10.0:
            n_bad += 1
            nan = math.nan
            s = s._replace(height_m=nan, vn=nan, ve=nan, vd=nan, h_acc_m=nan, pdop=nan, hdop=nan)
            s = s._replace(course_rad=nan, course_valid=True)
        samples.append(s)
    outs, sk = _run(name, samples)
    tail = pd.DataFrame(outs[-200:])
    cols = ["north", "east", "roll", "pitch", "std_north"]
    assert np.isfinite(tail[cols].to_numpy()).all(), tail[cols].describe()
    assert n_bad >= 9 and sk == {"gnss_course_nonfinite": n_bad}


@pytest.mark.parametrize("name", ["pipeline", "eskf", "qekf"])
def test_run_batch_drops_and_counts_nonfinite_rows(name: str, log: Log) -> None:
    """A log built by hand with NaN rows (readers drop them): run_batch leaves them out, counts
    them, and gives the clean log's result."""
    imu, gnss, mag = log.imu.copy(), log.gnss.copy(), log.mag.copy()
    rows = np.flatnonzero(imu["t"].to_numpy() > T_BAD)[[0, 7, 30]]
    imu.loc[rows[0], "acc_x"] = math.nan
    imu.loc[rows[1], "gyro_z"] = math.inf
    imu.loc[rows[2], "acc_z"] = math.nan
    g = np.flatnonzero(gnss["t"].to_numpy() > T_BAD)[2]
    gnss.loc[g, "lat_deg"] = math.nan
    mag.loc[np.flatnonzero(mag["t"].to_numpy() > T_BAD)[1], "mag_y_ut"] = math.nan
    dirty_log = Log(gnss=gnss, imu=imu, mag=mag, utc_offset_s=log.utc_offset_s)
    clean_log = Log(
        gnss=gnss.drop(index=g), imu=imu.drop(index=rows), mag=mag.dropna(), utc_offset_s=log.utc_offset_s
    )
    dirty = run_batch(make_engine(name), dirty_log)
    clean = run_batch(make_engine(name), clean_log)
    assert dirty.attrs["summary"]["skipped"] == {"gnss_nonfinite": 1, "imu_nonfinite": 3, "mag_nonfinite": 1}
    assert clean.attrs["summary"]["skipped"] == {}
    assert len(dirty) == len(log.imu) - 3
    pd.testing.assert_frame_equal(dirty, clean)


@pytest.mark.parametrize("name", ["pipeline", "anchor", "eskf"])
def test_fixes_without_height_then_with(log: Log, name: str) -> None:
    """The first 15 fixes are 2D (no height): the origin gets height 0, and the first fix with
    a height re-initialises the vertical (``vertical_reset``) instead of being rejected as
    300 m off; later 2D fixes update the horizontal only (``pipeline``: with the filter's own
    height). Before: ``pipeline`` rejected five fixes (NIS 2782 -> 869, ``down`` jumping by
    290 m, horizontal 1.9 m off); on car-tunnel with 30 such fixes ``eskf`` rejected five and
    re-opened its gate (down 15 m off a minute later) and ``anchor`` pulled its height towards
    the origin's 0 m (26 m off)."""
    gnss = log.gnss.copy()
    first = gnss.index[gnss["valid"].to_numpy(bool)][:15]
    gnss.loc[first, "height_m"] = math.nan
    later = gnss.index[(gnss["t"] > T_BAD) & gnss["valid"].to_numpy(bool)][:3]
    gnss.loc[later, "height_m"] = math.nan
    two_d = Log(gnss=gnss, imu=log.imu, mag=log.mag, utc_offset_s=log.utc_offset_s)
    eng = make_engine(name)
    df = run_batch(eng, two_d)
    clean = run_batch(make_engine(name), log)
    resets = [e for e in eng.events if e["type"] == "vertical_reset"]
    assert len(resets) == 1
    rejected = [e for e in eng.events if e["type"] == "fix_rejected" and e.get("reason") == "nis"]
    assert not rejected
    after = df["t"].to_numpy() > resets[0]["t"] + 1.0
    h_err = np.hypot(df["north"] - clean["north"], df["east"] - clean["east"]).to_numpy()
    assert np.nanmax(h_err[after]) < 0.5, np.nanmax(h_err[after])
    # heights follow the clean run's once re-initialised (the origins differ: compare heights;
    # observed median 0.16 m, largest 7.5 m while the vertical velocity re-converges)
    dh = np.abs(df["height"].to_numpy()[after] - clean["height"].to_numpy()[after])
    assert np.nanmedian(dh) < 2.0 and np.nanmax(dh) < 10.0, (np.nanmedian(dh), np.nanmax(dh))


@pytest.mark.parametrize("name", ["pipeline", "anchor", "eskf"])
def test_step_after_run_batch_rejects_an_earlier_imu_sample(name: str, log: Log) -> None:
    """``run_batch`` of a compiled engine (its block path) leaves the guard at the last IMU time,
    so a later ``step()`` with an earlier sample is rejected, as for the Python engines."""
    eng = make_engine(name)
    run_batch(eng, log)
    t_last = float(log.imu["t"].iloc[-1])
    assert eng.step(ImuSample(t_last - 5.0, np.array([0.0, 0.0, -G]), np.zeros(3))) is None
    assert eng.summary()["skipped"] == {"imu_time_backwards": 1}
    assert eng.step(ImuSample(t_last + 0.02, np.array([0.0, 0.0, -G]), np.zeros(3))) is not None
