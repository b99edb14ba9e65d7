"""IMU error model: Allan deviation of a long static simulation, mounting convention."""

from __future__ import annotations

import allantools
import numpy as np

from iotnav import sim
from iotnav.sim.imu_model import flicker_correlation_times

G0 = 9.80665


def _gm_avar(tau: np.ndarray, sigma: float, T: float) -> np.ndarray:
    # Allan variance of a first-order Gauss-Markov process (IEEE Std 952 / El-Sheimy et al. 2008)
    x = tau / T
    return 2 * sigma**2 * T / tau * (1 - T / (2 * tau) * (3 - 4 * np.exp(-x) + np.exp(-2 * x)))


def test_allan_deviation_shows_noise_density_and_bias_instability() -> None:
    """4 h static LSM6DS3 at 10 Hz with a 30 s bias correlation time.

    Checks (mean over 3 axes): ADEV(1 s) equals the noise density within 5 %; the ADEV near
    the Gauss-Markov peak (tau = 1.89 T) equals the configured bias instability (combined with
    the white part) within 15 %.
    """
    rate, T = 10.0, 30.0
    r = sim.build(
        "static-imu-6h",
        seed=11,
        overrides={
            "duration_s": 4 * 3600,
            "truth_rate_hz": rate,
            "imu.rate_hz": rate,
            "imu.preset": "lsm6ds3",
            "imu.bias_correlation_time_s": T,
            "imu.bias_model": "gauss-markov",  # static-imu-6h defaults to flicker since issue #6
        },
    )
    nd_acc = 90e-6 * G0  # LSM6DS3 datasheet value, m/s^2/sqrt(Hz)
    nd_gyro = np.radians(7e-3)  # rad/s/sqrt(Hz)
    bi_acc = 0.1e-3 * G0
    bi_gyro = np.radians(20.0) / 3600.0
    tau_peak = 1.89 * T
    # a GM whose ADEV peaks at B has sigma = B / max_x sqrt(avar(x)/sigma^2); computed here numerically
    xs = np.linspace(0.5, 5, 5001)
    peak = np.sqrt(np.max(_gm_avar(xs, 1.0, 1.0)))
    for cols, nd, bi in (
        (["acc_x", "acc_y", "acc_z"], nd_acc, bi_acc),
        (["gyro_x", "gyro_y", "gyro_z"], nd_gyro, bi_gyro),
    ):
        a1, ap = [], []
        for c in cols:
            taus, adev, _, _ = allantools.oadev(
                r.imu[c].to_numpy(), rate=rate, data_type="freq", taus=[1.0, tau_peak]
            )
            a1.append(adev[0])
            ap.append(adev[1])
        white1 = nd / np.sqrt(1.0)
        gm1 = np.sqrt(_gm_avar(np.array([1.0]), bi / peak, T))[0]
        assert abs(np.mean(a1) / np.hypot(white1, gm1) - 1) < 0.05
        expected_peak = np.sqrt(nd**2 / taus[1] + _gm_avar(np.array([taus[1]]), bi / peak, T)[0])
        assert abs(np.mean(ap) / expected_peak - 1) < 0.15
        # and it is the bias instability that dominates there
        assert np.mean(ap) > 2 * nd / np.sqrt(taus[1])


def test_mount_yaw_90_puts_forward_acceleration_on_minus_y() -> None:
    # scooter start: accelerating forward; IMU x axis 90 deg clockwise (to the right) of heading
    r = sim.build(
        "scooter-laps",
        seed=0,
        overrides={
            "imu.errors": False,
            "mount_roll_rad": 0.0,
            "mount_pitch_rad": 0.0,
            "mount_yaw_rad": np.pi / 2,
            "duration_s": 25,
            "gnss.enabled": False,
        },
    )
    imu = r.imu
    tr = r.truth
    acc_phase = (imu["t"] > 15.5) & (imu["t"] < 20.0)  # wait_start_s = 15, then accelerate
    t = imu["t"][acc_phase].to_numpy()
    speed = np.hypot(tr["vn"], tr["ve"]).to_numpy()
    a_fwd = np.interp(t + 0.0125, tr["t"].to_numpy()[1:], np.diff(speed) / np.diff(tr["t"].to_numpy()))
    assert np.all(a_fwd > 0.2)
    assert np.allclose(imu["acc_y"][acc_phase].to_numpy(), -a_fwd, atol=0.03)
    assert np.abs(imu["acc_x"][acc_phase].to_numpy()).max() < 1e-9
    assert np.allclose(imu["acc_z"].to_numpy()[:100], -9.806, atol=0.002)


def test_errors_switch_and_determinism() -> None:
    ov = {"duration_s": 60, "gnss.enabled": False}
    a = sim.build("static-courtyard", seed=2, overrides=ov)
    b = sim.build("static-courtyard", seed=2, overrides=ov)
    c = sim.build("static-courtyard", seed=3, overrides=ov)
    assert a.imu.equals(b.imu) and a.truth.equals(b.truth)
    assert not a.imu.equals(c.imu)
    ideal = sim.build("static-courtyard", seed=2, overrides={**ov, "imu.errors": False})
    assert np.allclose(ideal.imu["gyro_z"], 0.0, atol=1e-15)
    # LSM6DS3 quantisation: outputs are multiples of the LSB (0.061 mg, 8.75 mdps)
    lsb = 0.061e-3 * G0
    k = a.imu["acc_x"].to_numpy() / lsb
    assert np.allclose(k, np.round(k), atol=1e-6)


LN2_FACTOR = np.sqrt(2.0 * np.log(2.0) / np.pi)  # IEEE Std 952: flicker ADEV floor = 0.664 B


def test_flicker_bias_model_has_flat_allan_floor_at_0664_b() -> None:
    """``bias_model="flicker"``: the ADEV of the in-run bias is flat at 0.664 B (IEEE Std 952).

    6 h of the 3DM-GX3-35 preset at 10 Hz with white noise switched off, so the ADEV is that
    of the bias process alone (turn-on bias, scale factor and gravity are constants, invisible
    to the ADEV). Expected value: ``sqrt(2 ln 2 / pi) B`` for the configured B (18 deg/h,
    0.04 mg), computed here. The ratio ADEV / (0.664 B), averaged over the 6 axes, must be
    within 3, 3, 4, 5, 6 and 12 % of 1 at tau = 1, 3, 10, 30, 100, 300 s: about 3.5 times the
    statistical scatter of that 6-axis mean on this record (per-axis scatter measured over
    seeds 5-7: 0.5, 0.7, 0.8, 2.5, 4 and 7.5 %), plus 0.5 % for the model's own flatness
    (the Gauss-Markov-sum construction is 0.664 B within 0.5 % for 1 s <= tau <= 300 s), and
    the mean over the taus within 3 %. A single Gauss-Markov process with the preset's
    T = 300 s, the ``gauss-markov`` model, is ~9 times too low at tau = 1 s (its ADEV rises as
    sqrt(tau) there: a hump, not a floor), which is checked too.
    """
    rate = 10.0
    ov: dict[str, object] = {
        "truth_rate_hz": rate,
        "imu.rate_hz": rate,
        "imu.gyro_noise_density_mdps_rthz": 0.0,
        "imu.acc_noise_density_ug_rthz": 0.0,
    }
    b_gyro = np.radians(18.0) / 3600.0  # rad/s
    b_acc = 0.04e-3 * G0  # m/s^2
    taus = np.array([1.0, 3.0, 10.0, 30.0, 100.0, 300.0])

    def ratios(model: str) -> np.ndarray:
        r = sim.build("static-imu-6h", seed=5, overrides={**ov, "imu.bias_model": model})
        out = []
        axes = [(f"gyro_{a}", b_gyro) for a in "xyz"] + [(f"acc_{a}", b_acc) for a in "xyz"]
        for c, b in axes:
            _, adev, _, _ = allantools.oadev(r.imu[c].to_numpy(), rate=rate, data_type="freq", taus=taus)
            out.append(adev / (LN2_FACTOR * b))
        return np.mean(out, axis=0)

    flicker = ratios("flicker")
    tol = np.array([0.03, 0.03, 0.04, 0.05, 0.06, 0.12])
    assert np.all(np.abs(flicker - 1.0) < tol), flicker
    assert abs(np.mean(flicker) - 1.0) < 0.03
    gm = ratios("gauss-markov")
    assert gm[0] < 0.3  # the single Gauss-Markov process has no floor at short tau


def test_flicker_construction_is_flat_at_0664_b_analytically() -> None:
    """The Gauss-Markov sum behind ``bias_model="flicker"``, checked in closed form.

    Each component of variance ``s^2 = B^2 Delta / pi`` (weights derived here: a Gauss-Markov
    PSD ``2 s^2 T / (1 + (2 pi f T)^2)`` integrated over ``ln T`` with density ``B^2 / pi`` is
    ``B^2 / (2 pi f)``) contributes the Gauss-Markov Allan variance ``_gm_avar``; their sum must
    be ``(0.664 B)^2`` within 2.5 % in deviation for 1 s <= tau <= duration / 10 (6 h at 100 Hz),
    and within 1 % for 1 s <= tau <= 300 s.
    """
    b, dt, duration = 1.0, 0.01, 6 * 3600.0
    corr_times, step = flicker_correlation_times(dt, duration)
    assert corr_times.min() < dt and corr_times.max() > duration / 2  # spans [1 / duration, fs / 2]
    tau = np.logspace(0.0, np.log10(duration / 10.0), 60)
    avar = sum(_gm_avar(tau, b * np.sqrt(step / np.pi), T) for T in corr_times)
    ratio = np.sqrt(avar) / (LN2_FACTOR * b)
    assert np.all(np.abs(ratio - 1.0) < 0.025), ratio
    assert np.all(np.abs(ratio[tau <= 300.0] - 1.0) < 0.01)
