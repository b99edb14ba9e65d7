"""Pedestrian dead reckoning: step detection, Weinberg step length, the ``pdr`` engine.

Layers (STYLE §11): closed-form and seeded synthetic tests of :mod:`iotnav.techniques.steps`;
the engine through GNSS outages on the real rtklibexplorer walk (the ``datasets`` fixture:
fails when the shared datasets are absent); bad input.
"""

from __future__ import annotations

import dataclasses
import math
from pathlib import Path

import numpy as np
import pytest

from iotnav.engines.base import GnssSample, ImuSample, MagSample
from iotnav.engines.pdr import PdrConfig, PdrEngine
from iotnav.engines.registry import make_engine
from iotnav.techniques.steps import StepConfig, StepDetector, StepLengthCalibrator, weinberg_length

G = 9.80665


def _walk_signal(
    rng: np.random.Generator,
    step_times: np.ndarray,
    amplitudes: np.ndarray,
    duration_s: float,
    noise_mps2: float,
    rate_hz: float = 100.0,
) -> tuple[np.ndarray, np.ndarray]:
    """Specific force (m/s^2, ``b`` = z up) of a walker: per step a heel-strike pulse at its time
    (Gaussian, 70 ms) and a softer trough half a step later, plus seeded white noise per axis."""
    t = np.arange(0.0, duration_s, 1.0 / rate_hz) + rng.uniform(-1e-3, 1e-3)
    dyn = np.zeros_like(t)
    for ts, a in zip(step_times, amplitudes, strict=True):
        dyn += a * np.exp(-0.5 * ((t - ts) / 0.07) ** 2)
        dyn -= 0.6 * a * np.exp(-0.5 * ((t - ts - 0.28) / 0.1) ** 2)
    acc = np.zeros((t.size, 3))
    acc[:, 2] = G + dyn
    acc += rng.normal(0.0, noise_mps2, acc.shape)
    return t, acc


def _detect(t: np.ndarray, acc: np.ndarray, cfg: StepConfig | None = None) -> list:
    det = StepDetector(cfg)
    return [ev for k in range(t.size) if (ev := det.update(float(t[k]), acc[k])) is not None]


def test_weinberg_closed_form() -> None:
    """``L = K (a_max - a_min)^(1/4)``: 16 m/s^2 peak to trough with K = 0.5 gives 1 m."""
    assert weinberg_length(20.0, 4.0, 0.5) == pytest.approx(1.0)
    assert weinberg_length(10.0, 10.0, 0.5) == 0.0
    assert weinberg_length(9.0, 10.0, 0.5) == 0.0  # never NaN for a reversed pair


def test_steps_detected_at_their_times() -> None:
    """100 steps at a cadence varying between 1.6 and 2.2 Hz, 3 s still before and after,
    noise 0.3 m/s^2 per axis: every step is found once, none while still, each reported within
    the two low-pass stages' group delay (2 / (2 pi 3 Hz) = 0.11 s) plus half a pulse width
    after the true impact."""
    rng = np.random.default_rng(7)
    intervals = 1.0 / rng.uniform(1.6, 2.2, 100)
    step_times = 3.0 + np.cumsum(intervals)
    amp = rng.uniform(2.0, 4.0, step_times.size)
    t, acc = _walk_signal(rng, step_times, amp, step_times[-1] + 3.0, 0.3)
    events = _detect(t, acc, StepConfig(threshold_mps2=0.6, release_mps2=0.0))
    got = np.array([e.t for e in events])
    assert got.size == step_times.size
    lag = got - step_times
    assert np.all(lag > -0.02) and np.all(lag < 0.15), (lag.min(), lag.max())
    assert np.all(np.isfinite([e.root for e in events]))


def test_step_root_scales_as_fourth_root_of_amplitude() -> None:
    """The low-pass is linear, so doubling the impact doubles ``a_max - a_min`` and the Weinberg
    root grows by ``2^(1/4)`` (noise-free signal)."""
    rng = np.random.default_rng(3)
    step_times = 2.0 + np.arange(60) * 0.5
    amp = np.where(np.arange(60) < 30, 2.0, 4.0)
    t, acc = _walk_signal(rng, step_times, amp, step_times[-1] + 2.0, 0.0)
    roots = np.array([e.root for e in _detect(t, acc)])
    assert roots.size == 60
    ratio = np.median(roots[35:]) / np.median(roots[5:25])
    assert ratio == pytest.approx(2.0**0.25, rel=0.02)


def test_calibrator_recovers_k() -> None:
    """Steps of root 1.2 at 2 steps/s and a GNSS speed of 1.2 m/s (0.05 m/s noise): K = v / (2 root) = 0.5."""
    rng = np.random.default_rng(11)
    cal = StepLengthCalibrator(k0=0.8, interval_s=5.0, forget=0.9)
    for n in range(120):  # 60 s
        t = 0.5 * n
        cal.add_step(1.2)
        if n % 2 == 0:
            cal.add_speed(t, 1.2 + rng.normal(0.0, 0.05))
    assert cal.n_intervals >= 10
    assert cal.k == pytest.approx(0.5, rel=0.03)


@pytest.mark.slow
def test_walk_outages_pdr_far_below_strapdown(datasets: Path) -> None:
    """Real hand-held walk (ICM-45686, RTK truth), 15 s and 30 s outages every 30 s.

    Measured (seed 0): pdr median / worst drift 15.3 / 15.4 % (15 s), 10.2 / 11.4 % (30 s),
    RMS without outage 1.64 m; eskf 117.8 / 128.2 % and 100.5 / 103.4 %; GNSS hold 78 / 85 %
    and 17 / 24 %. Bounds, physical: a step-and-heading system whose step length is within
    10 % and whose heading is within 10 degrees (17 % cross-track), starting from a fix 1-2 m
    off, stays under 30 % of the distance walked; a strapdown consumer IMU has drifted by
    about the distance walked, so pdr must be under a third of eskf; with GNSS the output
    stays within the fed GNSS's accuracy (1.8 m horizontal RMS; 3 m).
    """
    from iotnav.cli.outages import load_dataset
    from iotnav.eval.outages import OutageConfig, rtk_truth, study

    log, prof = load_dataset(datasets / "rtklibexplorer_gnss_imu" / "walk_0827")
    cfg = OutageConfig(lengths_s=(15.0, 30.0), spacing_s=30.0, first_offset_s=30.0, engines=("eskf",))
    res = study(log, rtk_truth(log.gnss), prof, cfg)
    sm = res.summary.set_index(["engine", "length_s"])
    assert "pdr" in res.meta["engines"]  # the walk profile adds it
    for L in (15.0, 30.0):
        pdr, eskf = sm.loc[("pdr", L)], sm.loc[("eskf", L)]
        assert pdr.n_windows == 2
        assert pdr.worst_drift_pct < 30.0
        assert pdr.worst_drift_pct < eskf.median_drift_pct / 3.0
        assert pdr.median_drift_pct < sm.loc[("hold", L)].median_drift_pct
        assert pdr.rms_no_outage_m < 3.0
    m = res.mount.set_index("engine")
    assert math.isnan(m.loc["pdr", "yaw_deg"])


def _imu(t: float, acc: tuple[float, float, float] = (0.0, 0.0, G)) -> ImuSample:
    return ImuSample(t, np.array(acc), np.array([0.0, 0.0, 0.01]))


def _fix(t: float, north_m: float = 0.0, valid: bool = True) -> GnssSample:
    return GnssSample(t, 45.0 + north_m / 111_132.0, 7.0, 300.0, h_acc_m=2.0, vn=0.0, ve=0.0, valid=valid)


def test_bad_input_counted_not_fatal() -> None:
    """NaN samples, time going backwards, invalid / out-of-order fixes: no exception, every
    skipped sample counted by reason, the first of each as an event; a rejected IMU sample gives
    no output, a gap still does."""
    eng = PdrEngine()
    outs = []
    rejected = [
        _imu(0.5, (math.nan, 0.0, G)),  # NaN accelerometer
        ImuSample(0.51, np.array([0.0, 0.0, G]), np.array([math.nan, 0.0, 0.0])),  # NaN gyro
        ImuSample(math.nan, np.array([0.0, 0.0, G]), np.zeros(3)),  # NaN time
        _imu(0.2),  # backwards
    ]
    seq = [
        _fix(0.0),
        *[_imu(0.01 * k) for k in range(1, 50)],
        *rejected,
        _imu(0.52),
        _fix(0.53, valid=False),
        GnssSample(0.54, math.nan, 7.0, 300.0),  # NaN latitude
        _fix(1.0, 0.5),
        _fix(0.9, 0.5),  # backwards
        MagSample(1.0, np.array([20.0, 0.0, 40.0])),
        _imu(1.01),
        _imu(3.0),  # a 2 s gap
    ]
    for s in seq:
        o = eng.step(s)
        if isinstance(s, ImuSample) and not any(s is r for r in rejected):
            assert o is not None
            outs.append(o)
        else:
            assert o is None
    assert len(outs) == sum(isinstance(s, ImuSample) for s in seq) - len(rejected)
    sk = eng.summary()["skipped"]
    assert sk == {
        "imu_nonfinite": 3,
        "imu_time_backwards": 1,
        "gnss_invalid": 1,
        "gnss_nonfinite": 1,
        "gnss_time_backwards": 1,
        "imu_gap": 1,  # the shared count (InputGuard, over 1 s)
        "imu_gap_not_integrated": 1,  # pdr's own, over max_imu_gap_s
    }
    reasons = [e["reason"] for e in eng.events if e["type"] == "input_skipped"]
    assert sorted(reasons) == sorted(sk)
    assert all(math.isfinite(o.north) and o.source in ("fix", "dr") for o in outs)
    assert eng.summary()["fixes_applied"] == 2
    assert outs[-1].static and outs[-1].vn == 0.0


def test_registry_and_toml(tmp_path: Path) -> None:
    """``make_engine("pdr")`` with a TOML file: ``[pdr]`` and ``[pdr.steps]`` tables; typos raise."""
    p = tmp_path / "pdr.toml"
    p.write_text("[pdr]\nheading_rw_rad_rsqrt_s = 0.02\n[pdr.steps]\nweinberg_k = 0.6\n")
    eng = make_engine("pdr", config_path=p, integrity=False)  # the engine itself, not the guard
    assert isinstance(eng, PdrEngine)
    steps = dataclasses.replace(PdrConfig().steps, weinberg_k=0.6)
    assert eng.config == PdrConfig(heading_rw_rad_rsqrt_s=0.02, steps=steps)
    p.write_text("[pdr]\nheading_rw = 0.02\n")
    with pytest.raises(ValueError, match="heading_rw"):
        make_engine("pdr", config_path=p)
