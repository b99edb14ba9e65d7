"""Time faults (issue 16 item 6): counter wraps and device resets, GNSS week rollover, fix
latency, IMU gaps. Each repaired once where the data comes in, and counted."""

from __future__ import annotations

from datetime import UTC, datetime
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from iotnav.engines.base import IMU_GAP_S, ImuSample, run_batch
from iotnav.engines.registry import make_engine
from iotnav.io.imu_csv import read_imu_csv
from iotnav.io.log import Log, Part, merge
from iotnav.io.report import FileReport
from iotnav.io.timefaults import WEEK_ROLLOVER_S, rebase_segments, rollover_shift


def test_counter_wrap_is_unwrapped_exactly() -> None:
    t = (np.arange(100) * 10.0 + 2.0**32 - 500.0) % 2.0**32  # a 32-bit ms counter wraps
    fixed, jumps = rebase_segments(t)
    assert [j.kind for j in jumps] == ["wrap"]
    np.testing.assert_allclose(np.diff(fixed), 10.0)


def test_device_reset_is_rebased_and_a_glitch_is_not() -> None:
    t = np.r_[np.arange(50) * 0.01 + 100.0, np.arange(50) * 0.01 + 0.2]  # reboot: clock restarts
    fixed, jumps = rebase_segments(t)
    assert [j.kind for j in jumps] == ["reset"]
    assert np.all(np.diff(fixed) > 0) and np.diff(fixed)[49] == pytest.approx(0.01)
    glitch = np.arange(100) * 0.01
    glitch[40] = 0.05  # one row out of order: the reader's non-monotonic skip, not a segment
    assert rebase_segments(glitch)[1] == []


def test_imu_csv_keeps_the_rows_after_a_wrap(tmp_path: Path) -> None:
    """The whole file is read (none lost as non-monotonic) and the wrap is counted."""
    ticks = (np.arange(400) * 10 + 65536 - 2000) % 65536  # 16-bit ms tick counter
    rows = ["t_ms,acc_x,acc_y,acc_z,gyro_x,gyro_y,gyro_z"]
    rows += [f"{int(k)},0.0,0.0,-9.81,0.001,0.0,0.0" for k in ticks]
    p = tmp_path / "imu.csv"
    p.write_text("\n".join(rows) + "\n")
    part = read_imu_csv(p, acc_unit="m/s^2", gyro_unit="rad/s")
    assert len(part.imu) == 400
    assert part.report.n_skipped == 0 and part.report.time_faults["wrap"] == 1
    np.testing.assert_allclose(np.diff(part.imu["t"].to_numpy()), 0.01, atol=1e-9)


def _gnss_part(utc0: float, clock: str) -> Part:
    t = np.arange(5.0)
    utc = utc0 + t
    df = pd.DataFrame(
        {
            "t": utc if clock == "utc" else t + 7.0,
            "utc": utc,
            "lat_deg": 50.0,
            "lon_deg": 8.0,
            "height_m": 0.0,
            "valid": True,
        }
    )
    imu = pd.DataFrame(
        {"t": df["t"], **{c: 0.0 for c in ("acc_x", "acc_y", "gyro_x", "gyro_y", "gyro_z")}, "acc_z": -9.81}
    )
    return Part.make(FileReport("x", "test"), clock, gnss=df, imu=imu)  # type: ignore[arg-type]


def test_week_rollover_is_detected_and_moved_on() -> None:
    now = datetime(2026, 12, 1, tzinfo=UTC).timestamp()
    true = datetime(2026, 11, 20, 12, tzinfo=UTC).timestamp()
    log = merge([_gnss_part(true - WEEK_ROLLOVER_S, "utc")], now_utc_s=now)  # a 2007 date
    assert log.gnss["utc"].iloc[0] == pytest.approx(true)
    assert log.imu["t"].iloc[0] == pytest.approx(true)  # the part's whole clock moves
    assert log.report.files[0].time_faults["week_rollover"] == 1
    # a genuine 2016 log is not moved into the future, a 2026 one not at all
    assert rollover_shift(np.array([datetime(2016, 5, 1, tzinfo=UTC).timestamp()]), now) == 0.0
    assert rollover_shift(np.array([true]), now) == 0.0
    # read five years later, the same dates are taken as written (a genuine 2007 log is possible)
    assert rollover_shift(np.array([true - WEEK_ROLLOVER_S]), now + 5 * 365 * 86400.0) == 0.0


def test_gnss_latency_moves_device_stamps_back_to_the_fix_epoch() -> None:
    utc0 = datetime(2026, 11, 20, tzinfo=UTC).timestamp()
    log = merge([_gnss_part(utc0, "device")], gnss_latency_s=0.2, now_utc_s=utc0)
    np.testing.assert_allclose(log.gnss["t"].to_numpy(), np.arange(5.0) + 6.8)
    assert log.utc_offset_s == pytest.approx(utc0 - 6.8)  # utc = fix epoch on the device clock
    assert log.imu["t"].iloc[0] == 7.0  # IMU stamps untouched
    same = merge([_gnss_part(utc0, "utc")], gnss_latency_s=0.2, now_utc_s=utc0)
    assert same.gnss["t"].iloc[0] == utc0  # UTC stamps are the epoch's own time


@pytest.mark.parametrize("name", ["anchor", "pipeline", "eskf", "qekf", "pdr", "absfix"])
def test_imu_gaps_are_counted_by_every_engine(name: str) -> None:
    """A 5 s hole in the IMU stream is in summary()['skipped'] and events, batch and streaming."""
    t = np.r_[np.arange(0.0, 3.0, 0.01), np.arange(8.0, 10.0, 0.01)]
    imu = pd.DataFrame(
        {"t": t, "acc_x": 0.0, "acc_y": 0.0, "acc_z": -9.81, "gyro_x": 0.0, "gyro_y": 0.0, "gyro_z": 0.0}
    )
    log = Log(imu=imu)
    eng = make_engine(name)
    run_batch(eng, log)
    assert eng.summary()["skipped"].get("imu_gap") == 1, name
    assert any(e.get("reason") == "imu_gap" for e in eng.events)
    live = make_engine(name)
    for tk in t:
        live.step(ImuSample(float(tk), np.array([0.0, 0.0, -9.81]), np.zeros(3)))
    assert live.summary()["skipped"].get("imu_gap") == 1, name
    assert IMU_GAP_S < 5.0
