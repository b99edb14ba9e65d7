"""GNSS error model: statistics of the correlated error, cold start, outages, course flag."""

from __future__ import annotations

import numpy as np
import pytest

from iotnav import sim
from iotnav.geo import LocalFrame
from iotnav.sim.gnss_model import filtered_gm


def _acf(x: np.ndarray, lags: np.ndarray) -> np.ndarray:
    x = x - x.mean()
    v = np.mean(x * x)
    return np.array([np.mean(x[: len(x) - k] * x[k:]) / v for k in lags])


def _fit_tau(x: np.ndarray, dt: float, max_lag_s: float) -> float:
    lags = np.arange(10, int(max_lag_s / dt))
    rho = _acf(x, lags)
    ok = rho > 0.05
    # least squares slope of log(rho) against lag through the origin
    return float(-np.sum((lags[ok] * dt) ** 2) / np.sum(lags[ok] * dt * np.log(rho[ok])))


def test_filtered_gauss_markov_sigma_and_correlation_time() -> None:
    rng = np.random.default_rng(7)
    y, dy = filtered_gm(400_000, 1.0, 3.0, 120.0, 2.0, rng, 2)
    assert np.allclose(y.std(axis=0), 3.0, rtol=0.06)
    tau = _fit_tau(y[:, 0], 1.0, 120.0)
    assert tau == pytest.approx(120.0, rel=0.12)
    # derivative: var(dy/dt) = sigma^2 / (tf tau) for a GM seen through a first-order filter
    assert np.allclose(dy.std(axis=0), 3.0 / np.sqrt(2.0 * 120.0), rtol=0.15)


def test_static_receiver_error_matches_configuration() -> None:
    """20 h static courtyard receiver, no outliers, constant DOP: position error sigma and tau."""
    r = sim.build(
        "static-courtyard",
        seed=4,
        overrides={
            "duration_s": 20 * 3600,
            "truth_rate_hz": 10,
            "imu.enabled": False,
            "gnss.cold_start": False,
            "gnss.outliers_per_hour": 0,
            "gnss.dop_variation": 0,
        },
    )
    env = r.meta["gnss_environment"]
    sigma_h = env["uere_m"] * env["hdop"] / np.sqrt(2)
    sigma_v = env["uere_m"] * env["vdop"]
    assert sigma_h == pytest.approx(4.0 * 1.7 / np.sqrt(2))
    g = r.gnss
    cfg = r.config
    ned = LocalFrame(cfg.origin_lat_deg, cfg.origin_lon_deg, cfg.origin_height_m).to_ned(
        g["lat_deg"], g["lon_deg"], g["height_m"]
    )
    err = ned - ned.mean(axis=0) * 0  # the receiver sits at the origin: the fix is the error
    assert np.abs(r.truth[["north", "east", "down"]].to_numpy()).max() == 0.0
    assert err[:, 0].std() == pytest.approx(sigma_h, rel=0.15)
    assert err[:, 1].std() == pytest.approx(sigma_h, rel=0.15)
    assert err[:, 2].std() == pytest.approx(sigma_v, rel=0.15)
    assert _fit_tau(err[:, 0], 1.0, 300.0) == pytest.approx(300.0, rel=0.25)
    assert _fit_tau(err[:, 2], 1.0, 300.0) == pytest.approx(300.0, rel=0.25)
    # Doppler velocity: error derivative (sigma / sqrt(tf tau)) plus white Doppler noise
    v_expected = np.hypot(sigma_h / np.sqrt(2.0 * 300.0), 0.08)
    assert g["vn"].std() == pytest.approx(v_expected, rel=0.2)
    assert g["vn"].std() < 0.3
    # standstill: course flagged invalid
    assert not g["course_valid"].any()


def test_cold_start_walk() -> None:
    r = sim.build("walk-cold-boot", seed=1)
    g = r.gnss
    tr = r.truth
    assert not g.loc[g["t"] < 45, "valid"].any()
    first = g.loc[g["valid"], "t"].iloc[0]
    early = g[(g["t"] >= first) & (g["t"] < first + 30)]
    assert (early["pdop"] > 10).all()
    cfg = r.config
    frame = LocalFrame(cfg.origin_lat_deg, cfg.origin_lon_deg, cfg.origin_height_m)
    ned = frame.to_ned(g["lat_deg"], g["lon_deg"], g["height_m"])
    idx = np.searchsorted(tr["t"].to_numpy(), g["t"].to_numpy())
    herr = np.hypot(ned[:, 0] - tr["north"].to_numpy()[idx], ned[:, 1] - tr["east"].to_numpy()[idx])
    early_err = herr[(g["t"] >= first).to_numpy() & (g["t"] < first + 20).to_numpy()]
    assert np.median(early_err) > 20.0
    late = herr[(g["t"] > first + 150).to_numpy()]
    assert np.median(late) < 15.0
    assert (g.loc[g["t"] > first + 150, "pdop"] < 5).all()
    # last known position a few metres from the true start
    lp = r.last_position
    assert lp is not None
    d = frame.to_ned(lp["lat"], lp["lon"], lp["height"])
    assert np.hypot(d[0], d[1]) == pytest.approx(4.0, abs=1e-6)
    assert lp["t_saved_utc"] < r.utc_offset_s


def test_tunnel_outages_and_rates() -> None:
    r = sim.build(
        "car-tunnel", seed=2, overrides={"gnss.rate_hz": 20, "imu.enabled": False, "duration_s": 200}
    )
    g = r.gnss
    assert np.allclose(np.diff(g["t"]), 0.05)
    inside = (g["t"] >= 150) & (g["t"] < 190)
    assert inside.sum() == 800
    assert not g.loc[inside, "valid"].any() and (g.loc[inside, "quality"] == 0).all()
    assert g.loc[~inside, "valid"].all()
    silent = sim.build(
        "car-tunnel",
        seed=2,
        overrides={"gnss.outage_output": "silent", "imu.enabled": False, "duration_s": 200},
    )
    assert len(silent.gnss) == 201 - 40
    moving = g["valid"] & (g["speed_mps"] > 5)
    assert g.loc[moving, "course_valid"].all()
