"""The ``fixes`` engine's forward (live) sigma: at least the last fix's own, grown by the model
between accepted fixes; checkpoints of the state before those slots (issue 17)."""

from __future__ import annotations

import math
import pickle

import numpy as np
import pandas as pd
import pytest

from iotnav.engines import fixes_kernel as fk
from iotnav.engines.base import TangentPlane, iter_samples, run_batch
from iotnav.engines.fixes import FixesConfig, FixesEngine, FixesKFConfig
from iotnav.io.log import Log
from iotnav.io.schema import GNSS_COLUMNS, coerce

ORIGIN = TangentPlane(45.0, 7.0, 100.0)
#: per-axis sigma of a fix reporting h_acc = 4 m (h_acc / sqrt 2, iotnav.gnss_accuracy)
SIG_AXIS = 4.0 / math.sqrt(2.0)
#: the car preset's acceleration PSD, m^2/s^3 (Groves 2013, sec. 9.4.2.2: "10 m^2 s^-3 for a car")
Q_CAR = 10.0


def _table(t: np.ndarray, n: np.ndarray, e: np.ndarray) -> pd.DataFrame:
    """1 Hz GNSS epochs at NED ``n, e`` (m) about :data:`ORIGIN`, h_acc 4 m."""
    return coerce(
        pd.DataFrame(
            {
                "t": t,
                "utc": 1.7e9 + t,
                "lat_deg": ORIGIN.lat0_deg + n / ORIGIN.k_n,
                "lon_deg": ORIGIN.lon0_deg + e / ORIGIN.k_e,
                "height_m": 100.0,
                "h_acc_m": 4.0,
                "v_acc_m": 6.0,
                "pdop": 1.5,
                "num_sv": 10,
                "valid": True,
            }
        ),
        GNSS_COLUMNS,
    )


def _gauss_markov(seed: int, n: int, sig: float, tau: float) -> np.ndarray:
    """``(n, 2)`` first-order Gauss-Markov errors at 1 Hz, stationary sigma ``sig`` (m), correlation time ``tau`` (s)."""
    rng = np.random.default_rng(seed)
    phi = math.exp(-1.0 / tau)
    err = np.zeros((n, 2))
    err[0] = rng.normal(0.0, sig, 2)
    w = rng.normal(0.0, sig * math.sqrt(1.0 - phi * phi), (n, 2))
    for k in range(1, n):
        err[k] = phi * err[k - 1] + w[k]
    return err


@pytest.mark.parametrize("seed", [0, 1])
def test_forward_sigma_covers_time_correlated_errors(seed: int) -> None:
    """A pedestrian walking north at 1.2 m/s, 600 fixes with speed and course (speed noise 0.1 m/s)
    whose position errors are Gauss-Markov (tau 120 s, the fixes' claimed sigma 2.83 m per axis).
    The measured velocity lets the white-noise posterior average the fixes down to a claimed
    1.19 m per axis, whose 95 % circle held 0.48 / 0.34 of the true errors (seeds 0 / 1; the
    track's rms error 3.8 / 4.3 m); with the floor at least 0.85 (0.97 / 0.93)."""
    t = np.arange(600, dtype=float)
    err = _gauss_markov(seed, t.size, SIG_AXIS, 120.0)
    speed = 1.2 + np.random.default_rng(seed + 10).normal(0.0, 0.1, t.size)
    g = _table(t, 1.2 * t + err[:, 0], err[:, 1]).assign(speed_mps=speed, course_rad=0.0, course_valid=True)
    fwd = run_batch(FixesEngine(FixesConfig(kf=FixesKFConfig(platform="pedestrian"))), Log(gnss=g))
    assert (fwd["source"] == "fix").all()
    n = (fwd["lat"].to_numpy() - ORIGIN.lat0_deg) * ORIGIN.k_n
    e = (fwd["lon"].to_numpy() - ORIGIN.lon0_deg) * ORIGIN.k_e
    miss = np.hypot(n - 1.2 * fwd["t"].to_numpy(), e)
    cover = float(np.mean(miss <= 2.4477 * fwd["std_north"].to_numpy()))
    assert cover >= 0.85, cover


def test_forward_sigma_floor_at_fixes_and_growth_over_a_rejected_fix() -> None:
    """Accepted rows report at least the fix's per-axis sigma; a 300 m glitch's row (rejected, a
    prediction) at least that plus the model's one-second growth ``q dt^3 / 3``."""
    t = np.arange(60, dtype=float)
    rng = np.random.default_rng(3)
    n, e = 10.0 * t + rng.normal(0.0, 1.0, t.size), rng.normal(0.0, 1.0, t.size)
    e[40] += 300.0
    eng = FixesEngine()
    fwd = run_batch(eng, Log(gnss=_table(t, n, e)))
    assert [x["t"] for x in eng.events if x["type"] == "fix_rejected"] == [40.0]
    src = fwd["source"].to_numpy()
    sn, se = fwd["std_north"].to_numpy(), fwd["std_east"].to_numpy()
    fix = src == "fix"
    assert (
        fix.sum() == 59
        and np.all(sn[fix] >= SIG_AXIS * (1 - 1e-12))
        and np.all(se[fix] >= SIG_AXIS * (1 - 1e-12))
    )
    k = int(np.flatnonzero(fwd["t"].to_numpy() == 40.0)[0])
    assert src[k] == "dr"
    assert sn[k] ** 2 >= SIG_AXIS**2 + Q_CAR / 3.0 and se[k] ** 2 >= SIG_AXIS**2 + Q_CAR / 3.0
    assert sn[k] > sn[k - 1] and sn[k + 1] == pytest.approx(SIG_AXIS, rel=1e-9)


def test_a_checkpoint_of_the_state_before_the_floor_loads_and_another_size_is_refused() -> None:
    """A pickled engine whose scalar state has the earlier 57 entries streams on with the same
    positions as the original and the floor from the next accepted fix; 58 entries are refused."""
    t = np.arange(80, dtype=float)
    rng = np.random.default_rng(5)
    samples = list(
        iter_samples(Log(gnss=_table(t, 10.0 * t + rng.normal(0, 1, t.size), rng.normal(0, 1, t.size))))
    )
    a = FixesEngine()
    for s in samples[:40]:
        a.step(s)
    assert fk.ST_SIZE_V1 == 57 and a._st.shape == (fk.ST_SIZE,)
    old = FixesEngine()
    for s in samples[:40]:
        old.step(s)
    old._st = old._st[: fk.ST_SIZE_V1].copy()  # as the earlier version pickled it
    b = pickle.loads(pickle.dumps(old))
    assert b._st.shape == (fk.ST_SIZE,) and b._st[fk.S_FLOOR_N] == 0.0
    rows_a = [a.step(s) for s in samples[40:]]
    rows_b = [b.step(s) for s in samples[40:]]
    assert all(r is not None for r in rows_a) and all(r is not None for r in rows_b)
    assert [r[:4] for r in rows_a] == [r[:4] for r in rows_b]  # t, lat, lon, height
    assert [r.std_north for r in rows_a] == [r.std_north for r in rows_b]  # each row follows an accepted fix
    bad = FixesEngine()
    bad._st = np.zeros(fk.ST_SIZE_V1 + 1)
    with pytest.raises(ValueError, match=r"scalar state of shape \(58,\); this version reads \(66,\)"):
        pickle.loads(pickle.dumps(bad))


def test_a_checkpoint_of_the_state_before_the_jump_tracking_loads() -> None:
    """A state of ``ST_SIZE_V2`` (59 entries, before the departure test's jump tracking) loads:
    the seven slots start as a fresh engine's (no jump) and the engine streams on."""
    t = np.arange(60, dtype=float)
    rng = np.random.default_rng(7)
    samples = list(iter_samples(Log(gnss=_table(t, rng.normal(0, 1, t.size), rng.normal(0, 1, t.size)))))
    old = FixesEngine()
    for s in samples[:30]:
        old.step(s)
    assert fk.ST_SIZE_V2 == 59 and fk.ST_SIZE == 66
    old._st = old._st[: fk.ST_SIZE_V2].copy()  # as the earlier version pickled it
    b = pickle.loads(pickle.dumps(old))
    assert b._st.shape == (fk.ST_SIZE,) and b._st[fk.S_IN_JUMP] == 0.0 and b._st[fk.S_GOOD_T] == 0.0
    assert all(b.step(s) is not None for s in samples[30:])
