"""Path-loss model, LoRa time on air and robust calibration (layer a, closed forms)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from iotnav.nodes.ranging import (
    RADIOS,
    distance_from_rssi,
    fit_path_loss,
    lora_time_on_air_s,
    radio,
    range_std_m,
    rssi_from_distance,
)


def test_log_distance_by_hand() -> None:
    m = radio("lora-sf7")
    # P0 = 14 dBm - FSPL(1 m, 868.1 MHz) = 14 - 31.21 dB
    assert m.p0_dbm == pytest.approx(-17.2)
    # -17.2 - 10 * 2.7 * log10(100) = -71.2 dBm
    assert float(rssi_from_distance(100.0, m)) == pytest.approx(-71.2)
    assert float(distance_from_rssi(-71.2, m)) == pytest.approx(100.0)
    # equation R2: 6 dB at n = 2.7 is a 51.2 % range spread
    assert float(range_std_m(100.0, m)) == pytest.approx(100.0 * math.log(10) * 6.0 / 27.0)


def test_presets_cover_lora_sf7_to_sf12_and_ble() -> None:
    for sf in range(7, 13):
        assert RADIOS[f"lora-sf{sf}"].spreading_factor == sf
    assert RADIOS["lora-sf12"].sensitivity_dbm == -137.0
    assert radio("BLE").p0_dbm == -59.0
    with pytest.raises(ValueError, match="expected one of"):
        radio("zigbee")


def test_lora_time_on_air_by_hand() -> None:
    # SF7/125 kHz, 12 bytes, CR 4/5, explicit header, CRC: 8 + ceil(112/28)*5 = 28 payload
    # symbols + 12.25 preamble = 40.25 symbols of 1.024 ms.
    assert lora_time_on_air_s(7, 12) == pytest.approx(40.25 * 1.024e-3)
    # SF12 (low data rate optimisation on): 8 + ceil(92/40)*5 = 23 symbols, +12.25, 32.768 ms each.
    assert lora_time_on_air_s(12, 12) == pytest.approx(35.25 * 32.768e-3)


def test_calibration_recovers_parameters_and_resists_nlos() -> None:
    rng = np.random.default_rng(11)
    d = rng.uniform(5.0, 800.0, 600)
    r = -20.0 - 10.0 * 3.1 * np.log10(d) + rng.normal(0.0, 5.0, d.size)
    nlos = rng.random(d.size) < 0.25
    r_bad = r - np.where(nlos, 25.0, 0.0)
    fit = fit_path_loss(d, r)
    assert fit.p0_dbm == pytest.approx(-20.0, abs=1.5)
    assert fit.n == pytest.approx(3.1, abs=0.07)
    assert fit.shadowing_db == pytest.approx(5.0, abs=0.5)
    robust = fit_path_loss(d, r_bad)
    ols = fit_path_loss(d, r_bad, huber_c=math.inf)
    # ordinary least squares absorbs the NLOS loss into P0; Huber stays much closer
    assert abs(ols.p0_dbm + 20.0) > 2.0
    assert abs(robust.p0_dbm + 20.0) < 0.5 * abs(ols.p0_dbm + 20.0)
    assert robust.n == pytest.approx(3.1, abs=0.15)
    assert np.sqrt(robust.cov[1, 1]) < 0.1


def test_calibration_rejects_bad_input() -> None:
    with pytest.raises(ValueError, match="three distinct"):
        fit_path_loss([10.0, 10.0, 20.0], [-50.0, -51.0, -60.0])
    with pytest.raises(ValueError, match="NaN"):
        fit_path_loss([10.0, 20.0, np.nan], [-50.0, -51.0, -60.0])
    with pytest.raises(ValueError, match="positive"):
        fit_path_loss([0.0, 20.0, 30.0], [-50.0, -51.0, -60.0])
