"""Real-data outage study (issue #5) on the first 250 s of rtklibexplorer drive_0708.

Shortened but real: eskf and GNSS alone with 15 s and 30 s outages; the full study (all
engines, 60 s outages, the walk) is benchmarks/bench_outages.py.
"""

from __future__ import annotations

import itertools
import math
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
import typer
from typer.testing import CliRunner

from conftest import datasets_dir
from iotnav.engines.base import run_batch
from iotnav.eval import outages as O
from iotnav.io.log import Log

DRIVE = datasets_dir() / "rtklibexplorer_gnss_imu" / "drive_0708"

CFG = O.OutageConfig(lengths_s=(15.0, 30.0), engines=("eskf",), max_duration_s=250.0, seed=3)


@pytest.fixture(scope="module")
def drive() -> tuple[Log, pd.DataFrame]:
    from iotnav.cli.outages import load_dataset

    log, _ = load_dataset(DRIVE)
    return log, O.rtk_truth(log.gnss)


@pytest.fixture(scope="module")
def result(drive: tuple[Log, pd.DataFrame]) -> tuple[O.OutageResult, pd.DataFrame]:
    log, truth = drive
    before = truth.copy()
    res = O.study(log, truth, O.DATASETS["drive_0708"], CFG)
    return res, before


def test_truth_is_the_untouched_rtk(drive: tuple[Log, pd.DataFrame], result: tuple) -> None:
    log, truth = drive
    _, before = result
    ok = log.gnss.valid.to_numpy(bool)
    np.testing.assert_array_equal(truth.lat.to_numpy(), log.gnss.lat_deg.to_numpy()[ok])
    np.testing.assert_array_equal(truth.lon.to_numpy(), log.gnss.lon_deg.to_numpy()[ok])
    pd.testing.assert_frame_equal(truth, before)  # the study did not modify it
    assert (truth.quality == 4).mean() > 0.99  # RTK fixed


def test_degraded_gnss_has_the_configured_statistics() -> None:
    # a long static "RTK" track so that minutes-long correlation averages out
    n = 40_000
    truth = pd.DataFrame(
        {
            "t": np.arange(n, dtype=float),
            "lat": np.full(n, 40.0),
            "lon": np.full(n, -105.0),
            "height": np.full(n, 1600.0),
            "vn": 0.0,
            "ve": 0.0,
            "vd": 0.0,
            "quality": 4,
        }
    )
    g, ex = O.degrade_rtk(truth, O.OutageConfig(seed=1))
    assert len(g) == n and g.valid.all()
    sig = 2.0 * 0.9 / math.sqrt(2.0)  # open sky: UERE 2 m x HDOP 0.9 per horizontal axis
    err = ex["err_n"]
    no_jump = ~ex["outlier"].astype(bool)
    for k in (0, 1):
        assert np.std(err[no_jump, k]) == pytest.approx(sig, rel=0.15)
    # the reported fix carries exactly that error
    from iotnav.geo import LocalFrame

    ned = LocalFrame(40.0, -105.0, 1600.0).to_ned(g.lat_deg, g.lon_deg, g.height_m)
    np.testing.assert_allclose(ned[:, :2], err[:, :2], atol=1e-6)
    # velocity: Doppler noise (0.08 m/s) plus the derivative of the smoothed error
    assert np.std(g.vn) == pytest.approx(math.hypot(0.08, sig / math.sqrt(2.0 * 150.0)), rel=0.1)
    # seeded
    g2, _ = O.degrade_rtk(truth, O.OutageConfig(seed=1))
    np.testing.assert_array_equal(g.lat_deg.to_numpy(), g2.lat_deg.to_numpy())


def test_degraded_drive_gnss_is_1hz_and_metres_off(drive: tuple[Log, pd.DataFrame]) -> None:
    _, truth = drive
    g, ex = O.degrade_rtk(truth, CFG)
    dt = np.diff(g.t.to_numpy())
    assert np.median(dt) == pytest.approx(1.0, abs=1e-3)
    h = np.hypot(ex["err_n"][:, 0], ex["err_n"][:, 1])
    assert 0.7 < np.sqrt(np.mean(h**2)) < 4.0


def test_windows_and_mask(drive: tuple[Log, pd.DataFrame]) -> None:
    _, truth = drive
    g, _ = O.degrade_rtk(truth, CFG)
    m0, m1 = O.moving_part(truth, 0.5)
    assert 30.0 < m0 - truth.t.iloc[0] < 45.0  # the static start (~38 s) is left out
    tg = g.t.to_numpy()
    wins = O.outage_windows(m0, m1, (15.0, 30.0, 60.0), 60.0, 60.0, tg)
    for L in (15.0, 30.0, 60.0):
        w = sorted(s for s, length in wins if length == L)
        assert w and w[0] >= m0 + 60.0 and all(s + L <= m1 for s in w)
        assert all(b - a >= L for a, b in itertools.pairwise(w))  # no overlap
    for s, L in wins:
        masked = O.mask_windows(g, [(s, L)])
        gone = set(tg) - set(masked.t.to_numpy())
        assert len(gone) == int(L)  # exactly L fixes at 1 Hz
        assert all(s <= t < s + L for t in gone)
    with pytest.raises(ValueError, match="spacing"):
        O.outage_windows(m0, m1, (90.0,), 60.0)


def test_eskf_beats_gnss_hold_on_every_window(result: tuple) -> None:
    res, _ = result
    w = res.windows
    assert set(w.engine) == {O.HOLD, O.DR_VELOCITY, "eskf"}
    assert (w.fixes_masked == w.length_s).all()
    e = w[w.engine == "eskf"].set_index(["length_s", "start"])
    h = w[w.engine == O.GNSS_HOLD].set_index(["length_s", "start"])
    assert len(e) >= 5 and list(e.index) == list(h.index)
    assert (e.distance_m > 50.0).all()
    # dead reckoning: at least 5x smaller than holding the last fix, on every window
    assert (5.0 * e.drift_pct < h.drift_pct).all()
    s = res.summary.set_index(["engine", "length_s"])
    assert s.loc[("eskf", 30.0), "median_drift_pct"] < 5.0
    # outside the outages the fused track is better than the raw 1 Hz fixes held
    assert s.loc[("eskf", 15.0), "rms_outside_m"] < s.loc[(O.GNSS_HOLD, 15.0), "rms_outside_m"]


def test_study_reports_the_mount(result: tuple) -> None:
    res, _ = result
    m = res.mount.set_index("engine").loc["eskf"]
    assert m.kind == "C_vb"
    # the author's [180, 0, 180] + [0, -6.79, 5.35] deg, found by the engine itself
    assert m.author_pitch_deg == pytest.approx(6.76, abs=0.02)
    assert m.apart_deg < 3.0
    md = O.format_markdown(res)
    assert "Mount found" in md and "| eskf | C_vb |" in md


def test_continuation_equals_a_full_masked_run(drive: tuple[Log, pd.DataFrame], result: tuple) -> None:
    """The deep-copy shortcut gives the same track as running the masked log from the start."""
    from iotnav.engines.eskf import EskfConfig, EskfEngine

    log, truth = drive
    res, _ = result
    prof = O.DATASETS["drive_0708"]
    tr = truth[truth.t < truth.t.iloc[0] + 250.0]
    fed = O.degraded_feed(log, tr, prof, CFG)[0]
    g, imu = fed.gnss, fed.imu
    row = res.windows[(res.windows.engine == "eskf") & (res.windows.length_s == 30.0)].iloc[0]
    s = row.start + res.meta["t0"]
    df = run_batch(EskfEngine(EskfConfig(**prof.eskf)), Log(gnss=O.mask_windows(g, [(s, 30.0)]), imu=imu))
    df = df[df.source != "none"]
    from iotnav.eval.metrics import track_errors

    err = track_errors(df, tr[["t", "lat", "lon", "height"]])
    sel = (err.t >= s) & (err.t < s + 30.0)
    assert float(err.h_err[sel][-1]) == pytest.approx(row.end_error_m, abs=1e-9)


def test_cli_outages_registers_and_runs(tmp_path: Path) -> None:
    from iotnav.cli.outages import register

    app = typer.Typer()
    register(app)

    @app.command("noop")
    def _noop() -> None:  # a second command keeps typer from collapsing the group
        pass

    out = tmp_path / "o.md"
    r = CliRunner().invoke(
        app,
        [
            "outages",
            str(DRIVE),
            "--engines",
            "eskf",
            "--lengths",
            "15",
            "--max-duration-s",
            "130",
            "--markdown",
            str(out),
        ],
    )
    assert r.exit_code == 0, r.output
    assert "eskf" in out.read_text() and "Mount found" in out.read_text()
    bad = CliRunner().invoke(app, ["outages", str(tmp_path)])
    assert bad.exit_code == 2 and "unknown recording" in " ".join(bad.output.split())
