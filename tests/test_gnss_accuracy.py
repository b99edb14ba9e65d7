"""One reading of the receiver's accuracy figures (``iotnav.gnss_accuracy``) in every engine."""

from __future__ import annotations

import math

import numpy as np
import pytest

from iotnav.engines.anchor import gnss_position_noise
from iotnav.engines.base import GnssSample
from iotnav.engines.eskf import EskfConfig, EskfEngine
from iotnav.geo import LocalFrame
from iotnav.gnss_accuracy import VDOP_PER_HDOP, h_acc_from_radius, position_sigmas
from iotnav.sim.config import GnssConfig
from iotnav.sim.gnss_model import simulate_gnss
from iotnav.techniques.fusion_kf import FusionConfig, gnss_noise

nan = math.nan


def test_h_acc_is_the_2d_figure_and_the_dops_fill_in() -> None:
    """Hand-computed from the module's rules: hAcc 2D, UERE x HDOP 2D, VDOP from PDOP and HDOP,
    VDOP = 1.5 HDOP when either is missing, the default HDOP last."""
    s = position_sigmas(2.0, 3.0, 1.2, 2.0, 4.0, 2.0)
    assert s.north_east_m == pytest.approx(math.sqrt(2.0)) and s.down_m == 3.0
    assert s.source == ("h_acc", "v_acc")
    s = position_sigmas(2.0, nan, 1.2, 2.0, 4.0, 2.0)
    assert s.down_m == pytest.approx(3.0) and s.source == ("h_acc", "h_acc")
    s = position_sigmas(nan, -1.0, 1.2, 2.0, 4.0, 2.0)  # a non-positive figure is missing
    assert s.north_east_m == pytest.approx(4.0 * 1.2 / math.sqrt(2.0))
    assert s.down_m == pytest.approx(4.0 * 1.6) and s.source == ("hdop", "pdop")
    s = position_sigmas(nan, nan, nan, math.sqrt(1.0 + VDOP_PER_HDOP**2), 4.0, 2.0)
    assert s.north_east_m == pytest.approx(4.0 / math.sqrt(2.0))
    assert s.down_m == pytest.approx(4.0 * 1.5) and s.source == ("pdop", "pdop")
    s = position_sigmas(nan, nan, 1.0, 0.9, 4.0, 2.0)  # PDOP below HDOP: not a geometry
    assert s.down_m == pytest.approx(6.0) and s.source == ("hdop", "hdop")
    s = position_sigmas(nan, nan, nan, nan, 4.0, 2.0)
    assert s.north_east_m == pytest.approx(8.0 / math.sqrt(2.0))
    assert s.down_m == pytest.approx(12.0) and s.source == ("default", "default")


@pytest.mark.parametrize(
    ("h_acc", "v_acc", "hdop", "pdop"),
    [(2.0, 3.0, 1.2, 2.0), (2.0, nan, 1.2, 2.0), (nan, nan, 1.2, 2.0), (nan, nan, nan, 1.9), (nan,) * 4],
)
def test_every_engine_reads_the_figures_alike(h_acc: float, v_acc: float, hdop: float, pdop: float) -> None:
    """anchor / qekf, pipeline and eskf give one R for one fix (they once differed by 2x: anchor
    and qekf read hAcc per axis, the pipeline UERE x HDOP per axis)."""
    uere, dflt = 3.0, 2.0
    s = GnssSample(10.0, 45.0, 7.0, 250.0, pdop=pdop, hdop=hdop, h_acc_m=h_acc, v_acc_m=v_acc)
    ref = position_sigmas(h_acc, v_acc, hdop, pdop, uere, dflt)
    want = np.array([ref.north_east_m, ref.north_east_m, ref.down_m]) ** 2
    np.testing.assert_allclose(np.diag(gnss_position_noise(s, uere, dflt)), want)
    R, _ = gnss_noise(
        h_acc, v_acc, nan, pdop, hdop, FusionConfig(uere_m=uere, default_dop=dflt, min_pos_std_m=0.0)
    )
    np.testing.assert_allclose(np.diag(R), want)
    eng = EskfEngine(EskfConfig(uere_m=uere, default_hdop=dflt))
    sig, _, source = eng._gnss_noise(s)
    np.testing.assert_allclose(sig**2, want)
    assert source == ref.source


def test_simulator_error_matches_the_reading_of_its_h_acc() -> None:
    """The simulator's reported hAcc / vAcc are the 2D / vertical sigma of its own errors: the
    per-axis error normalised by ``h_acc / sqrt(2)`` has unit variance. Open sky, static, four
    seeded 11 h runs at 1 Hz, outliers left out. One run's variance scatters by 0.09-0.10
    (30 seeds: 1.04 / 1.00 / 0.97 mean N / E / D, 0.83-1.28 range), so four pooled have about
    0.035 (horizontal, N and E) and 0.045 (vertical). Read per axis, hAcc would give 0.5."""
    n = 40_000
    t = np.arange(n, dtype=float)
    zeros = np.zeros((n, 3))
    frame = LocalFrame(45.0, 7.0, 250.0)
    zh, zv = [], []
    for seed in range(4):
        df, extras = simulate_gnss(GnssConfig(), t, zeros, zeros, frame, 0.0, np.random.default_rng(seed))
        ok = df.valid.to_numpy() & ~extras["outlier"]
        e = extras["err_n"][ok]
        zh.append(e[:, :2] / (df.h_acc_m.to_numpy()[ok, None] / math.sqrt(2.0)))
        zv.append(e[:, 2] / df.v_acc_m.to_numpy()[ok])
    var_h = float(np.mean(np.concatenate(zh) ** 2))
    var_v = float(np.mean(np.concatenate(zv) ** 2))
    assert 0.85 < var_h < 1.15 and 0.8 < var_v < 1.2, (var_h, var_v)


def test_h_acc_from_a_68_percent_radius() -> None:
    """A circular Gaussian error: the radius holding 68 % of 200 000 seeded samples, converted,
    is their 2D RMS (the definition of ``h_acc_m``), within 1 %."""
    e = np.random.default_rng(4).normal(0.0, 2.0, (200_000, 2))
    r = np.hypot(e[:, 0], e[:, 1])
    assert h_acc_from_radius(float(np.quantile(r, 0.68))) == pytest.approx(math.sqrt(np.mean(r**2)), rel=0.01)
    assert h_acc_from_radius(float(np.quantile(r, 0.95)), 0.95) == pytest.approx(
        math.sqrt(np.mean(r**2)), rel=0.01
    )
    with pytest.raises(ValueError, match="confidence"):
        h_acc_from_radius(1.0, 1.0)
