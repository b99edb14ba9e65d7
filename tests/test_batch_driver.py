"""run_batch's block path hands the engine the same samples in the same order as iter_samples."""

from __future__ import annotations

import copy
import itertools
import math
import pickle
from typing import Any

import numpy as np
import pandas as pd
import pytest

from iotnav import sim
from iotnav.engines.base import (
    C_NORTH,
    C_T,
    OUTPUT_COLUMNS,
    SRC_DR,
    GnssSample,
    ImuSample,
    MagSample,
    Output,
    OutputBlock,
    Sample,
    iter_samples,
    run_batch,
)
from iotnav.engines.registry import make_engine
from iotnav.io.log import Log
from iotnav.io.schema import GNSS_COLUMNS, IMU_COLUMNS, MAG_COLUMNS, coerce


def _log(seed: int = 3) -> Log:
    rng = np.random.default_rng(seed)
    t_imu = np.round(np.cumsum(rng.uniform(0.005, 0.015, 400)), 3)
    t_g = np.sort(np.concatenate([rng.choice(t_imu, 5, replace=False), rng.uniform(0, 4, 5)]))
    t_m = np.sort(np.concatenate([t_g[:2], rng.choice(t_imu, 3, replace=False), rng.uniform(0, 4, 4)]))
    imu = pd.DataFrame({"t": t_imu, **{c: rng.normal(size=t_imu.size) for c in list(IMU_COLUMNS)[1:]}})
    g = pd.DataFrame(
        {"t": t_g, "lat_deg": 45.0 + t_g * 1e-6, "lon_deg": 7.0, "height_m": 1.0, "num_sv": 7, "valid": True}
    )
    m = pd.DataFrame({"t": t_m, "mag_x_ut": 20.0, "mag_y_ut": 0.0, "mag_z_ut": 40.0})
    return Log(gnss=coerce(g, GNSS_COLUMNS), imu=coerce(imu, IMU_COLUMNS), mag=coerce(m, MAG_COLUMNS))


class _Recorder:
    """Counts what it sees; without ``imu_block`` run_batch falls back to step() per sample."""

    def __init__(self) -> None:
        self.seen: list[tuple[str, float]] = []
        self.events: list[dict[str, Any]] = []
        self.n_gnss = 0

    mount_yaw_rad = 0.0

    def summary(self) -> dict[str, Any]:
        return {}

    def _row(self, t: float, acc_x: float) -> Output:
        nan = math.nan
        vals = [t, nan, nan, nan, acc_x, float(self.n_gnss), nan, nan, nan, nan, 0.0, 0.0, 0.0]
        return Output(*vals, False, nan, nan, "dr")

    def step(self, s: Sample) -> Output | None:
        if isinstance(s, ImuSample):
            self.seen.append(("imu", s.t))
            return self._row(s.t, float(s.acc_b[0]))
        if isinstance(s, GnssSample):
            self.seen.append(("gnss", s.t))
            self.n_gnss += 1
        elif isinstance(s, MagSample):
            self.seen.append(("mag", s.t))
        return None


class _BlockRecorder(_Recorder):
    def imu_block(self, t, acc, gyro, out: OutputBlock, i0: int, i1: int) -> None:  # type: ignore[no-untyped-def]
        for k in range(i0, i1):
            self.seen.append(("imu", float(t[k])))
            out.floats[C_T, k] = t[k]
            out.floats[C_NORTH, k] = acc[0][k]
            out.floats[C_NORTH + 1, k] = self.n_gnss
            out.floats[C_NORTH + 2 :, k] = math.nan
            out.floats[C_NORTH - 3 : C_NORTH, k] = math.nan
            out.floats[C_NORTH + 6 : C_NORTH + 9, k] = 0.0
            out.source[k] = SRC_DR


def test_block_path_sees_the_samples_of_iter_samples_in_order() -> None:
    log = _log()
    order = [
        ("imu" if isinstance(s, ImuSample) else "gnss" if isinstance(s, GnssSample) else "mag", s.t)
        for s in iter_samples(log)
    ]
    assert len(order) == len(log.imu) + len(log.gnss) + len(log.mag)
    kinds = [k for k, _ in order]
    times = [t for _, t in order]
    assert times == sorted(times)
    # ties: GNSS before magnetometer before IMU
    rank = {"gnss": 0, "mag": 1, "imu": 2}
    for a, b in itertools.pairwise(order):
        if a[1] == b[1]:
            assert rank[a[0]] <= rank[b[0]]
    assert kinds.count("gnss") == 10
    slow, fast = _Recorder(), _BlockRecorder()
    df_slow = run_batch(slow, log)
    df_fast = run_batch(fast, log)
    assert slow.seen == order
    assert fast.seen == order
    assert list(df_fast.columns) == list(OUTPUT_COLUMNS)
    pd.testing.assert_frame_equal(df_fast, df_slow)
    # the row of an IMU sample carries the number of GNSS epochs seen before it
    n_before = np.searchsorted(log.gnss["t"].to_numpy(), log.imu["t"].to_numpy(), side="right")
    np.testing.assert_array_equal(df_fast["east"].to_numpy(), n_before)
    np.testing.assert_array_equal(df_fast["north"].to_numpy(), log.imu["acc_x"].to_numpy())


def test_output_block_round_trips_rows() -> None:
    out = OutputBlock(1)
    rows = [
        Output(
            float(k),
            45.0,
            7.0,
            1.0,
            1.0,
            2.0,
            3.0,
            0.1,
            0.2,
            0.3,
            0.01,
            0.02,
            0.03,
            k % 2 == 0,
            1.5,
            2.5,
            src,
        )
        for k, src in enumerate(["fix", "dr", "something_new", "fix"])
    ]
    for r in rows:
        out.add(r)
    assert out.n == 4
    assert [out.row(k) for k in range(4)] == rows
    df = out.frame()
    assert list(df.columns) == list(OUTPUT_COLUMNS)
    assert df["source"].tolist() == ["fix", "dr", "something_new", "fix"]
    assert df["static"].tolist() == [True, False, True, False]


@pytest.mark.parametrize("name", ["pipeline", "anchor", "eskf", "qekf", "pdr"])
@pytest.mark.parametrize("how", ["deepcopy", "pickle"])
def test_engine_copied_mid_run_continues_like_the_original(name: str, how: str) -> None:
    """The outage study snapshots engines with ``copy.deepcopy`` and the fleet pickles them: a
    copy taken mid-run must give the original's outputs from there on (compiled engines keep
    views of their buffers, which a naive copy would detach)."""
    res = sim.build("car-tunnel", seed=1, overrides={"duration_s": 60.0})
    samples = list(iter_samples(Log(gnss=res.gnss, imu=res.imu, mag=res.mag)))
    eng = make_engine(name)
    half = len(samples) // 2
    for s in samples[:half]:
        eng.step(s)
    twin = copy.deepcopy(eng) if how == "deepcopy" else pickle.loads(pickle.dumps(eng))
    rows_a, rows_b = [], []
    for s in samples[half:]:
        a, b = eng.step(s), twin.step(s)
        if a is not None:
            rows_a.append(a)
            rows_b.append(b)
    assert len(rows_a) > 2000
    assert rows_a == rows_b or np.allclose(
        [r[:13] for r in rows_a], [r[:13] for r in rows_b], rtol=0.0, atol=1e-9, equal_nan=True
    )
