"""RTS smoothing of the ``eskf`` engine: error-state Rauch-Tung-Striebel (1965) on the nominal
trajectory (seeded, deterministic).

Exactness: the recorded transitions are the propagation chain (``P-_k - Phi_k P+_{k-1} Phi_k^T``
is the diagonal ``Q_d`` of the noise model), a coarse log (a record every 10 propagations) is a
subset of the fine one (every propagation) with the products of its transitions, and RTS on
it gives the same smoothed states. Effect: car-tunnel and car-magnetometer (numbers in the
test docstrings).
"""

from __future__ import annotations

import functools
import math
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from iotnav import sim
from iotnav.engines import eskf_models as M
from iotnav.engines.base import TangentPlane, iter_samples, run_batch
from iotnav.engines.eskf import EskfConfig, EskfEngine
from iotnav.engines.registry import make_engine
from iotnav.engines.smoother import SmoothingLog, rts_backward, smooth_output
from iotnav.eval.metrics import Errors, track_errors
from iotnav.io import ingest
from iotnav.io.log import Log
from iotnav.sim import SimResult

#: MPU-6050 accelerometer white noise of the default configuration (400 ug/sqrt(Hz)) squared,
#: (m/s^2)^2/Hz: the velocity part of ``Q_d`` per second.
ACC_PSD = (400e-6 * 9.80665) ** 2


@functools.lru_cache(maxsize=1)
def _short_log() -> Log:
    """80 s car: static start, block-5 mount, NHC, a 10 s GNSS outage."""
    r = sim.build("car-tunnel", seed=1, overrides={"duration_s": 80.0, "gnss.outages_s": ((60.0, 70.0),)})
    return Log(gnss=r.gnss, imu=r.imu, mag=r.mag)


@functools.lru_cache(maxsize=4)
def _run(record_every: int | None) -> tuple[EskfEngine, pd.DataFrame]:
    cfg = EskfConfig() if record_every is None else EskfConfig(smoothing=True, record_every=record_every)
    eng = EskfEngine(cfg)
    return eng, run_batch(eng, _short_log())


def _log(eng: EskfEngine) -> SmoothingLog:
    log = eng.smoothing_log
    assert log is not None
    return log


def test_forward_output_unchanged_and_first_record_at_position_init() -> None:
    off, df_off = _run(None)
    e1, df1 = _run(1)
    e10, df10 = _run(10)
    assert off.smoothing_log is None
    assert df1.equals(df_off) and df10.equals(df_off)  # bit-identical forward output
    l1, l10 = _log(e1), _log(e10)
    assert len(l10) < 0.6 * len(l1)
    # the records start where the output becomes the nominal state (before: the last fix)
    t_init = next(e["t"] for e in e1.events if e["type"] == "position_initialised")
    assert l1.t[0] == l10.t[0] == t_init
    assert np.all(np.diff(l1.t) > 0.0)
    with pytest.raises(ValueError, match="record_every"):
        EskfEngine(EskfConfig(smoothing=True, record_every=0))


def test_records_are_the_propagation_chain() -> None:
    """A record at every propagation: ``P-_k = Phi_k P+_{k-1} Phi_k^T + Q_d`` with the noise model's ``Q_d``."""
    eng, _ = _run(1)
    log = _log(eng)
    assert not any(e["type"] == "gate_reset" for e in eng.events)  # no reset in this run
    t = np.asarray(log.t)
    n_checked = 0
    for k in range(2, len(log)):
        Phi = log.Phi[k]
        Q = log.P_prior[k] - Phi @ log.P_post[k - 1] @ Phi.T
        d = np.sqrt(np.diag(log.P_prior[k]))
        off = Q - np.diag(np.diag(Q))
        assert np.all(np.abs(off) <= 1e-12 * np.outer(d, d)), k  # Q_d is diagonal
        assert np.all(np.abs(np.diag(Q)[M.POS]) <= 1e-12), k  # no noise on position
        dt = t[k] - t[k - 1]
        np.testing.assert_allclose(np.diag(Q)[M.VEL], ACC_PSD * dt, rtol=1e-6)
        # the attitude block of Phi over a propagation is I (rotation errors in n do not rotate)
        assert np.array_equal(Phi[M.ATT, M.ATT], np.eye(3))
        n_checked += 1
    assert n_checked > 500
    # updates are in the records: the posterior differs from the prior at NHC / GNSS epochs
    n_upd = sum(not np.array_equal(a, b) for a, b in zip(log.P_prior, log.P_post, strict=True))
    assert n_upd > 300


def test_coarse_records_smooth_like_every_propagation() -> None:
    """``record_every = 10`` vs 1: same priors and posteriors, products of the transitions, same RTS."""
    e1, _ = _run(1)
    e10, _ = _run(10)
    fine, coarse = _log(e1), _log(e10)
    t1, t10 = np.asarray(fine.t), np.asarray(coarse.t)
    j = np.searchsorted(t1, t10)
    assert np.array_equal(t1[j], t10)  # coarse record times are fine record times
    xf, Pf = rts_backward(fine)
    xc, Pc = rts_backward(coarse)
    n = e1.n
    for c in range(len(coarse)):
        assert np.array_equal(fine.P_post[j[c]], coarse.P_post[c])
        assert np.array_equal(fine.x_post[j[c]], coarse.x_post[c])
        assert np.array_equal(fine.P_prior[j[c]], coarse.P_prior[c])
        if c > 0:
            prod = np.eye(n)
            for i in range(j[c - 1] + 1, j[c] + 1):
                prod = fine.Phi[i] @ prod
            np.testing.assert_allclose(coarse.Phi[c], prod, rtol=0.0, atol=1e-12)
    # RTS on the record points is exact with only predictions between them
    np.testing.assert_allclose(xc[:, :9], xf[j, :9], rtol=0.0, atol=1e-9)
    np.testing.assert_allclose(Pc, Pf[j], rtol=0.0, atol=1e-9)
    # and it does something: the smoothed position moves by decimetres to metres in the outage
    out = (t10 > 60.0) & (t10 < 70.0)
    assert np.max(np.abs(xc[out, 0:2])) > 0.1


def test_step_records_equal_batch_records() -> None:
    eng, _ = _run(10)
    batch = _log(eng)
    es = EskfEngine(EskfConfig(smoothing=True, record_every=10))
    rows = [o for s in iter_samples(_short_log()) if (o := es.step(s)) is not None]
    assert len(rows) == len(_short_log().imu)
    stream = _log(es)
    assert stream.t == batch.t
    for a, b in ((stream.P_post, batch.P_post), (stream.Phi, batch.Phi), (stream.x_post, batch.x_post)):
        np.testing.assert_allclose(np.asarray(a), np.asarray(b), rtol=0.0, atol=1e-12)


def test_make_engine_eskf_smoothing() -> None:
    eng = make_engine("eskf", smoothing=True)
    assert isinstance(eng, EskfEngine) and eng.config.smoothing
    assert eng.smoothing_log is not None and len(eng.smoothing_log) == 0
    assert not EskfEngine().config.smoothing


def _fix_error_after(r: SimResult, t0: float, t1: float) -> float:
    """Largest horizontal error (m) of the valid fixes in ``[t0, t1]`` against the truth."""
    g, tr = r.gnss, r.truth
    m = g["valid"].to_numpy(bool) & (g["t"] >= t0) & (g["t"] <= t1)
    fr = TangentPlane(float(tr["lat"].iloc[0]), float(tr["lon"].iloc[0]), 0.0)
    tt = g["t"].to_numpy()[m]
    dn = (g["lat_deg"].to_numpy()[m] - np.interp(tt, tr["t"], tr["lat"])) * fr.k_n
    de = (g["lon_deg"].to_numpy()[m] - np.interp(tt, tr["t"], tr["lon"])) * fr.k_e
    return float(np.max(np.hypot(dn, de)))


def _car_tunnel(
    tmp_path: Path, duration_s: float, scale: bool = True
) -> tuple[SimResult, EskfEngine, pd.DataFrame, pd.DataFrame, Errors, Errors]:
    """car-tunnel, seed 0, ``duration_s``, written and read back through ingest; forward and
    smoothed (``scale``: ``gnss_error_scales_with_accuracy``)."""
    r = sim.build("car-tunnel", seed=0, overrides={"duration_s": duration_s})
    sim.write(r, tmp_path)
    log = ingest([tmp_path])
    eng = EskfEngine(EskfConfig(smoothing=True, gnss_error_scales_with_accuracy=scale))
    fwd = run_batch(eng, log)
    sm = smooth_output(eng, fwd)
    assert sm.attrs["smoothed"] and len(sm) == len(fwd)
    ef = track_errors(fwd.dropna(subset=["lat"]), r.truth)
    es = track_errors(sm.dropna(subset=["lat"]), r.truth)
    assert np.array_equal(ef.t, es.t)
    return r, eng, fwd, sm, ef, es


def _rms(x: np.ndarray) -> float:
    return float(np.sqrt(np.mean(x**2)))


def _check_gate_reset_records(r: SimResult, eng: EskfEngine) -> list[float]:
    """Every ``gate_reset`` is recorded without a reset: un-widened prior, forced fix as the update.

    The record of the forced fix is at the fix time; its transition keeps the position rows
    (identity over the last propagation), its prior is the previous posterior propagated
    (``P- - Phi P+ Phi^T`` positive semi-definite) with the position still correlated with the
    GNSS error and far below the widened ``(3 sigma_p)^2``, and its posterior holds the forced
    correction.
    """
    slog = _log(eng)
    t_rec = np.asarray(slog.t)
    resets = [float(e["t"]) for e in eng.events if e["type"] == "gate_reset"]
    g = r.gnss
    for tr_ in resets:
        k = int(np.searchsorted(t_rec, tr_))
        assert t_rec[k] == tr_
        Phi = slog.Phi[k]
        assert np.all(np.diag(Phi[M.POS, M.POS]) == 1.0), tr_
        Q = slog.P_prior[k] - Phi @ slog.P_post[k - 1] @ Phi.T
        assert np.linalg.eigvalsh(0.5 * (Q + Q.T)).min() > -1e-9, tr_
        h_acc = float(g["h_acc_m"].to_numpy()[np.argmin(np.abs(g["t"].to_numpy() - tr_))])
        widened = (3.0 * h_acc / math.sqrt(2.0)) ** 2
        P_pos = slog.P_prior[k][M.POS, M.POS]
        assert P_pos[0, 0] < 0.25 * widened and P_pos[1, 1] < 0.25 * widened, (tr_, P_pos, widened)
        assert slog.P_prior[k][M.POS.start, M.GNE.start] < -0.5, tr_  # not decorrelated
        assert np.linalg.norm(slog.x_post[k][M.POS]) > 1.0, tr_  # the forced correction
    return resets


def test_smoother_on_eskf_car_tunnel(tmp_path: Path) -> None:
    """car-tunnel, 330 s, seed 0 (tunnels 150-190 s and 255-315 s), read back through ingest.

    Observed: horizontal RMS 5.45 -> 1.43 m; largest error in the tunnels 14.9 -> 2.0 m (ratio
    0.13) and 22.1 -> 2.5 m (0.11). The fixes after each tunnel are 4.7 and 4.9 m off (the
    simulated receiver re-converges over ~10 s, and reports it in its accuracy): with the
    GNSS error states scaled by the reported accuracy no fix is gated out. Without that
    scaling (:func:`test_gate_reset_recorded_against_the_unwidened_prior`) the first fix was
    accepted, the next five rejected and the gate re-opened, smoothed RMS 2.09 m.
    """
    r, eng, fwd, sm, ef, es = _car_tunnel(tmp_path, 330.0)
    assert len(_log(eng)) < len(fwd) / 5
    rms_f, rms_s = _rms(ef.h_err), _rms(es.h_err)
    assert rms_s < 0.35 * rms_f, (rms_f, rms_s)
    outages = [(a, b) for a, b in r.config.gnss.outages_s if b < 330.0]
    assert len(outages) == 2
    for a, b in outages:
        m = (ef.t >= a) & (ef.t <= b + 0.5)
        f_max, s_max = float(ef.h_err[m].max()), float(es.h_err[m].max())
        floor = _fix_error_after(r, b, b + 5.0)
        assert f_max > 10.0 and floor > 3.0, (a, b, f_max, floor)
        assert s_max < 0.25 * f_max, (a, b, s_max, f_max)
        assert s_max <= floor, (a, b, s_max, floor)
        # the smoothed uncertainty inside the tunnel is below the forward one
        mid = (sm["t"] > a + 10.0) & (sm["t"] < b - 5.0)
        assert (sm.loc[mid, "std_north"] < fwd.loc[mid, "std_north"]).all()
    assert not any(e["type"] == "gate_reset" for e in eng.events)


def test_gate_reset_recorded_against_the_unwidened_prior(tmp_path: Path) -> None:
    """The same run with the GNSS error states *not* scaled by the reported accuracy (a receiver
    whose error does not follow it): after each tunnel five fixes are rejected and the sixth
    forced (``gate_reset`` at 196 and 321 s), recorded against the un-widened prior so that its
    information reaches back into the tunnel. Observed RMS 5.82 -> 2.09 m, tunnels 14.3 -> 2.3
    and 22.5 -> 3.6 m. Recorded as re-initialisations (before) the tunnel maxima were 4.1 and
    5.0 m: the forced fix barely corrected the tunnel."""
    r, eng, _fwd, _sm, ef, es = _car_tunnel(tmp_path, 330.0, scale=False)
    assert _rms(es.h_err) < 0.4 * _rms(ef.h_err)
    outages = [(a, b) for a, b in r.config.gnss.outages_s if b < 330.0]
    for a, b in outages:
        m = (ef.t >= a) & (ef.t <= b + 0.5)
        assert float(es.h_err[m].max()) < 0.2 * float(ef.h_err[m].max()), (a, b)
    resets = _check_gate_reset_records(r, eng)
    assert len(resets) == 2 and all(any(b < t_ < b + 10.0 for _, b in outages) for t_ in resets), resets


def test_smoother_on_eskf_car_tunnel_600s(tmp_path: Path) -> None:
    """car-tunnel, 600 s, seed 0: five tunnels; the issue's target, the largest smoothed error
    in each outage at most a quarter of the forward one, in every tunnel.

    Observed forward -> smoothed: horizontal RMS 2.62 -> 1.01 m; outside the outages (from 60
    s) 1.23 -> 0.92 m, 330-380 s (open sky after the second tunnel) 1.64 -> 0.84 m; largest
    error per tunnel 8.1 -> 0.6, 8.9 -> 2.0, 4.8 -> 0.8, 5.9 -> 1.1, 8.8 -> 1.1 m (ratios
    0.07-0.23), though the fixes after the third and fourth tunnels are 10.5 and 11.1 m off.
    With the DOPs' rounding steps followed at once instead of low-passed (which made the
    filter over-confident, :class:`iotnav.engines.gnss_resolution.AccuracyScaling`): 2.79 ->
    0.86, 1.02 -> 0.72, 1.45 -> 0.55 m, ratios 0.06-0.19.
    The scaling of the GNSS error states is a step of the transition into the fix's record;
    recorded inside it, as an update, RTS carried the smoothed estimate back in the wrong
    units: RMS 0.97 m, 330-380 s 1.12 m (ratio 0.77 to the forward run, bound 0.6 below).
    Before the GNSS error states followed the reported accuracy the forward filter accepted one
    such fix and rejected the next five good ones (four gate resets): RMS 3.62 -> 2.39 m,
    ratios 0.13-0.54.
    """
    r, eng, _fwd, _sm, ef, es = _car_tunnel(tmp_path, 600.0)
    rms_f, rms_s = _rms(ef.h_err), _rms(es.h_err)
    assert rms_s < 0.5 * rms_f, (rms_f, rms_s)
    outages = list(r.config.gnss.outages_s)
    assert len(outages) == 5
    open_sky = ef.t >= 60.0
    for a, b in outages:
        m = (ef.t >= a) & (ef.t <= b + 0.5)
        open_sky &= ~m
        f_max, s_max = float(ef.h_err[m].max()), float(es.h_err[m].max())
        assert s_max < 0.25 * f_max, (a, b, s_max, f_max)
    assert _rms(es.h_err[open_sky]) < 0.8 * _rms(ef.h_err[open_sky])
    after = (ef.t >= 330.0) & (ef.t < 380.0)
    assert _rms(es.h_err[after]) < 0.6 * _rms(ef.h_err[after])
    assert not any(e["type"] == "gate_reset" for e in eng.events)


def _wrap(a: np.ndarray) -> np.ndarray:
    return (a + np.pi) % (2.0 * np.pi) - np.pi


def _car_magnetometer_smoothed(
    res: sim.SimResult, scale: bool = True
) -> tuple[EskfEngine, pd.DataFrame, pd.DataFrame]:
    """eskf with the user's magnetometer calibration and smoothing over a car-magnetometer run:
    the engine, the forward and the smoothed output (``scale``: ``gnss_error_scales_with_accuracy``)."""
    hard, soft = res.mag_calibration()
    cfg = EskfConfig(
        mag_hard_iron_ut=hard,
        mag_soft_iron=soft,
        mag_declination_rad=math.radians(res.config.mag.declination_deg),
        smoothing=True,
        gnss_error_scales_with_accuracy=scale,
    )
    eng = EskfEngine(cfg)
    fwd = run_batch(eng, Log(gnss=res.gnss, imu=res.imu, mag=res.mag))
    return eng, fwd, smooth_output(eng, fwd)


def test_smoother_on_eskf_car_magnetometer_attitude() -> None:
    """car-magnetometer, seed 0, calibrated magnetometer: attitude RMS after 41 s.

    Observed forward -> smoothed, roll / pitch / yaw: 0.13 / 0.33 / 0.24 -> 0.24 / 0.11 / 0.06
    deg (seed 2: 0.26 / 0.16 / 0.32 -> 0.49 / 0.06 / 0.11). The roll gets worse: the output is
    the vehicle's attitude ``C_nb C_vb^T`` and its roll is not observable (the mount roll
    follows the sensor roll; the filter's vehicle-roll sigma stays 2.8 deg, the level-road
    assumption at the mount initialisation), so the smoother carries the forward filter's
    final roll, 0.2 deg off, back over the run. The mount initialisation from magnetometer
    and course (43 s) is a reset recorded with its transform: the mount-yaw row of that
    record's transition is zero.
    """
    res = sim.build("car-magnetometer", seed=0)
    eng, fwd, sm = _car_magnetometer_smoothed(res)
    tr = res.truth
    t = fwd.t.to_numpy()
    ok = t > 41.0
    rms: dict[str, tuple[float, float]] = {}
    for c in ("roll", "pitch", "yaw"):
        ref = np.interp(t[ok], tr.t, np.unwrap(tr[c].to_numpy()))
        ef = _wrap(fwd[c].to_numpy()[ok] - ref)
        es = _wrap(sm[c].to_numpy()[ok] - ref)
        rms[c] = (math.degrees(float(np.sqrt(np.mean(ef**2)))), math.degrees(float(np.sqrt(np.mean(es**2)))))
    assert rms["pitch"][1] < 0.6 * rms["pitch"][0], rms
    assert rms["yaw"][1] < 0.6 * rms["yaw"][0], rms
    assert rms["roll"][1] < 0.5, rms
    # the mount initialisation (mag + course) is recorded with its transform
    slog = _log(eng)
    t_m = next(e["t"] for e in eng.events if e["type"] == "mount_initialised" and e["source"] == "mag_course")
    t_rec = np.asarray(slog.t)
    k = int(np.searchsorted(t_rec, t_m))
    km = M.MNT.start + 2
    assert np.array_equal(slog.Phi[k][km], np.zeros(eng.n))
    others = [slog.Phi[i][km, km] for i in range(1, len(slog)) if i != k]
    assert np.all(np.asarray(others) == 1.0)


@pytest.mark.parametrize("seed", [0, 4])
def test_forced_fix_after_a_short_gap_is_a_restart(seed: int) -> None:
    """car-magnetometer with the GNSS error states not scaled by the reported accuracy: after
    the 4 s gap the re-acquiring receiver's fixes are rejected five times and the sixth is
    forced (a gate reset; seed 4 twice). After a gap this short the disagreement is the fixes',
    not a drift: the reset is recorded as a position re-initialisation (nothing carried back),
    ``smoothing_drift_gap_s``. Observed horizontal RMS after 45 s forward -> smoothed, seeds
    0 / 4: 2.04 -> 2.06 / 1.56 -> 1.18 m (with the default scaling no fix is rejected: 1.15 ->
    0.65 / 0.79 -> 0.76 m); recorded against the un-widened prior instead (as after a tunnel;
    ``smoothing_drift_gap_s = 3``) it was worse than forward (3.07 m on seed 0)."""
    res = sim.build("car-magnetometer", seed=seed)
    eng, fwd, sm = _car_magnetometer_smoothed(res, scale=False)
    resets = [e["t"] for e in eng.events if e["type"] == "gate_reset"]
    gap = res.config.gnss.outages_s[0]
    assert resets and all(gap[1] < t_ < gap[1] + 15.0 for t_ in resets), resets
    # the reset's record transition does not carry the position back
    slog = _log(eng)
    k = int(np.searchsorted(np.asarray(slog.t), resets[0]))
    assert not np.any(slog.Phi[k + 1][M.POS, M.POS]) or not np.any(slog.Phi[k][M.POS, M.POS])
    ef = track_errors(fwd.dropna(subset=["lat"]), res.truth)
    es = track_errors(sm.dropna(subset=["lat"]), res.truth)
    late = ef.t > 45.0
    rms_f = float(np.sqrt(np.mean(ef.h_err[late] ** 2)))
    rms_s = float(np.sqrt(np.mean(es.h_err[late] ** 2)))
    assert rms_s < 1.05 * rms_f, (rms_f, rms_s)
