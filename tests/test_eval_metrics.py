"""Error statistics against hand-made truth (layer a)."""

from __future__ import annotations

import numpy as np
import pandas as pd
import pytest

from iotnav.eval.metrics import error_stats, outage_drift, track_errors
from iotnav.geo import LocalFrame


def _table(frame: LocalFrame, t: np.ndarray, n: np.ndarray, e: np.ndarray) -> pd.DataFrame:
    lat, lon, h = frame.from_ned(np.column_stack([n, e, np.zeros_like(n)]))
    return pd.DataFrame({"t": t, "lat": lat, "lon": lon, "height": h})


def test_constant_offset_gives_exact_statistics() -> None:
    f = LocalFrame(45.0, 7.0, 0.0)
    t = np.arange(0.0, 100.0, 0.5)
    truth = _table(f, t, 10.0 * t, np.zeros_like(t))  # 10 m/s North
    track = _table(f, t[10:-10] + 0.25, 10.0 * (t[10:-10] + 0.25) + 3.0, np.full(t.size - 20, -4.0))
    err = track_errors(track, truth)
    s = error_stats(err)
    assert s["h_err_mean"] == pytest.approx(5.0, abs=1e-3)
    assert s["h_err_p95"] == pytest.approx(5.0, abs=1e-3)
    assert s["n_err_mean"] == pytest.approx(3.0, abs=1e-3)
    assert s["e_err_bias"] == pytest.approx(-4.0, abs=1e-3)
    assert s["outside_truth"] == 0


def test_percentiles_of_known_distribution() -> None:
    f = LocalFrame(0.0, 0.0, 0.0)
    t = np.arange(100.0)
    truth = _table(f, t, np.zeros_like(t), np.zeros_like(t))
    track = _table(f, t, np.arange(100.0) / 10.0, np.zeros_like(t))  # errors 0.0 .. 9.9 m
    s = error_stats(track_errors(track, truth))
    assert s["h_err_max"] == pytest.approx(9.9, abs=1e-4)
    assert s["h_err_p50"] == pytest.approx(4.95, abs=1e-4)
    assert s["h_err_rms"] == pytest.approx(np.sqrt(np.mean((np.arange(100) / 10.0) ** 2)), abs=1e-4)


def test_outage_drift() -> None:
    f = LocalFrame(45.0, 7.0, 0.0)
    t = np.arange(0.0, 60.0, 0.1)
    truth = _table(f, t, 20.0 * t, np.zeros_like(t))
    # Error grows linearly from 0 to 6 m inside [10, 40] s: 600 m driven -> 1 %.
    drift = np.clip((t - 10.0) / 30.0, 0, 1) * 6.0 * ((t >= 10) & (t <= 40))
    track = _table(f, t, 20.0 * t, drift)
    res = outage_drift(track_errors(track, truth), truth, [(10.0, 40.0)])
    assert len(res) == 1
    assert res[0]["distance_m"] == pytest.approx(600.0, rel=1e-3)
    assert res[0]["end_error_m"] == pytest.approx(6.0, abs=0.05)
    assert res[0]["drift_pct"] == pytest.approx(1.0, abs=0.01)
