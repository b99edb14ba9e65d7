"""Energy model of a duty-cycled GNSS tracker (iotnav.eval.power): hand-computed values from the
anchor-node paper's figures and the datasheets, monotonicity, bad input."""

from __future__ import annotations

import itertools
import math
import re

import pytest

from conftest import REPO
from iotnav.eval import power as pw

PAPER = REPO.parent / "shared" / "papers" / "iot-mobile-anchor-node-localization.txt"


def test_paper_presets_are_the_papers_figures() -> None:
    # read the figures from the paper's text (the file must be there), not from the code
    text = PAPER.read_text()
    m = re.search(
        r"GPS module\s*=\s*([\d.]+) m watt.*?IMU sensor\s*=\s*([\d.]+) m watt.*?"
        r"micro-controller\s*=\s*([\d.]+) m watt.*?=\s*([\d.]+) m watt",
        text,
        re.S,
    )
    assert m is not None
    gps, imu, mcu, total = (float(x) for x in m.groups())
    assert (gps, imu, mcu, total) == (79.2, 10.56, 45.0, 134.76)
    assert pw.GNSS_PRESETS["paper"].tracking_mw == gps
    assert pw.IMU_PRESETS["paper"].active_mw == imu
    assert pw.MCU_PRESETS["paper"].active_mw == mcu


def test_always_on_paper_unit_on_a_2000_mah_cell_lasts_54_9_h() -> None:
    # by hand: 2000 mAh x 3.7 V = 7400 mWh; 79.2 + 10.56 + 45 = 134.76 mW; 7400 / 134.76 = 54.91 h
    b = pw.budget(pw.DevicePower(), pw.Battery(2000.0, 3.7), None, "anchor")
    assert b.total_mw == pytest.approx(134.76, abs=1e-9)
    assert b.life_h == pytest.approx(54.91, abs=0.005)
    assert b.gnss_on_fraction == 1.0


def test_fix_every_10_s_hand_computed() -> None:
    # paper receiver, hot start 1 s, backup 15 uA x 3.0 V = 0.045 mW:
    # GNSS (1 x 79.2 + 9 x 0.045) / 10 = 7.9605 mW
    dev = pw.DevicePower()
    assert pw.gnss_average_mw(dev.gnss, 10.0) == pytest.approx(7.9605, abs=1e-9)
    # inertial engine: IMU 10.56 and MCU 45 stay on -> 63.5205 mW; 7400 / 63.5205 = 116.50 h
    b = pw.budget(dev, pw.Battery(), 10.0, "eskf")
    assert b.total_mw == pytest.approx(63.5205, abs=1e-9)
    assert b.life_h == pytest.approx(116.50, abs=0.005)
    # GNSS only: IMU idle 5 uA x 3.3 V = 0.0165; MCU 0.1 x 45 + 0.9 x 0.045 = 4.5405 -> 12.5175 mW
    g = pw.budget(dev, pw.Battery(), 10.0, "fixes")
    assert (g.imu_mw, g.mcu_mw) == (pytest.approx(0.0165), pytest.approx(4.5405))
    assert g.life_h == pytest.approx(7400.0 / 12.5175, rel=1e-12)  # 591.17 h


def test_sam_m8q_every_60_s_and_time_on_after_the_fix() -> None:
    sam = pw.GNSS_PRESETS["sam-m8q"]
    # datasheet Table 8 at 3.0 V: acquisition 25 mA = 75 mW, tracking 23 mA = 69 mW
    assert (sam.acquisition_mw, sam.tracking_mw) == (pytest.approx(75.0), pytest.approx(69.0))
    # (1 x 75 + 59 x 0.045) / 60 = 1.29425 mW
    assert pw.gnss_average_mw(sam, 60.0) == pytest.approx(1.29425, abs=1e-9)
    # 2 s tracking after the fix: (75 + 2 x 69 + 57 x 0.045) / 60 = (75 + 138 + 2.565) / 60 = 3.59275 mW
    assert pw.gnss_average_mw(sam, 60.0, on_after_fix_s=2.0) == pytest.approx(3.59275, abs=1e-9)


def test_a_period_too_short_to_sleep_keeps_the_receiver_tracking() -> None:
    g = pw.GnssPower("x", 100.0, 60.0, 0.05, time_to_fix_s=2.0)
    assert pw.gnss_average_mw(g, 2.0) == 60.0
    assert pw.gnss_average_mw(g, 1.0) == 60.0
    assert pw.gnss_on_fraction(g, 1.5) == 1.0
    assert pw.gnss_average_mw(g, 4.0) == pytest.approx((2 * 100.0 + 2 * 0.05) / 4.0)


@pytest.mark.parametrize("engine", ["anchor", "fixes"])
@pytest.mark.parametrize("gnss", list(pw.GNSS_PRESETS))
def test_battery_life_grows_with_the_fix_period(engine: str, gnss: str) -> None:
    dev = pw.DevicePower(gnss=pw.GNSS_PRESETS[gnss])
    periods = [2.0, 5.0, 10.0, 30.0, 60.0, 300.0]
    bs = pw.budgets(dev, pw.Battery(), periods, engine)
    lives = [b.life_h for b in bs]
    powers = [b.gnss_mw for b in bs]
    assert all(a < b for a, b in itertools.pairwise(lives))
    assert all(a > b for a, b in itertools.pairwise(powers))
    always = pw.budget(dev, pw.Battery(), None, engine)
    assert always.life_h < lives[0]
    # the GNSS-only engine sleeps its IMU: it always lasts longer than an inertial one
    if engine == "fixes":
        inertial = pw.budgets(dev, pw.Battery(), periods, "anchor")
        assert all(f.life_h > i.life_h for f, i in zip(bs, inertial, strict=True))


def test_bad_input_is_a_clear_error() -> None:
    with pytest.raises(ValueError, match="capacity"):
        pw.Battery(-1.0, 3.7)
    with pytest.raises(ValueError, match="voltage"):
        pw.Battery(1000.0, 0.0)
    with pytest.raises(ValueError, match="usable"):
        pw.Battery(1000.0, 3.7, usable_fraction=1.5)
    with pytest.raises(ValueError, match="period"):
        pw.gnss_average_mw(pw.GNSS_PRESETS["paper"], 0.0)
    with pytest.raises(ValueError, match="mcu_busy"):
        pw.DevicePower(mcu_busy=2.0)
    with pytest.raises(ValueError, match="backup_mw"):
        pw.GnssPower("x", 1.0, 1.0, math.nan, 1.0)
    with pytest.raises(ValueError, match="average power"):
        pw.battery_life_h(pw.Battery(), -1.0)
