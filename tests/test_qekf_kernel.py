"""The compiled qekf step (:mod:`iotnav.engines.qekf_kernel`) against its references.

* the prediction against :func:`iotnav.engines.qekf.propagate` (the readable reference form)
  and the process noise written out here from the module docstring of :mod:`iotnav.engines.qekf`;
* the output rows' ECEF -> geodetic conversion against pymap3d;
* whole runs, streaming (``step()``) and batch (:func:`~iotnav.engines.base.run_batch`, the
  compiled block path), against the runs stored from main's per-sample Python engine before
  the kernel existed (``tests/data/qekf_reference/``, made by its ``make_reference.py`` at
  commit 7f3bbd5): the paper's form with smoothing, the consistent form (28 states), and the
  no-magnetometer fallback.
"""

from __future__ import annotations

import importlib.util
import json
import math
from pathlib import Path
from types import ModuleType
from typing import Any

import numpy as np
import pandas as pd
import pytest

from iotnav import kalman
from iotnav.engines import qekf_kernel as K
from iotnav.engines import qekf_updates_kernel as KU
from iotnav.engines.base import FLOAT_COLUMNS, SOURCES, iter_samples, run_batch
from iotnav.engines.qekf import (
    QekfConfig,
    QekfEngine,
    gnss_error_transition,
    nhc_measurement,
    norm_measurement,
    propagate,
)
from iotnav.geo import ecef_to_geodetic, geodetic_to_ecef
from iotnav.io.log import Log

REFERENCE = Path(__file__).parent / "data" / "qekf_reference" / "qekf_reference.npz"


def _make_reference() -> ModuleType:
    """The script that made the stored runs (its ``record`` is how they were recorded)."""
    path = REFERENCE.with_name("make_reference.py")
    spec = importlib.util.spec_from_file_location("qekf_make_reference", path)
    assert spec is not None and spec.loader is not None
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def _state(rng: np.random.Generator, n: int = 22) -> np.ndarray:
    x = np.zeros(n)
    q = rng.normal(size=4)
    x[:4] = q / np.linalg.norm(q) * (1.0 + 1e-3 * rng.normal())  # |q| slightly off 1, as after updates
    x[4:7] = rng.normal(size=3) * 10.0
    x[7:10] = rng.normal(size=3) * 300.0
    x[10:13] = rng.normal(size=3) * 2e-3
    x[13:16] = rng.normal(size=3) * 0.2
    x[16:22] = 1.0 + rng.normal(size=6) * 0.01
    x[22:] = rng.normal(size=n - 22)
    return x


def _covariance(rng: np.random.Generator, n: int) -> np.ndarray:
    A = rng.normal(size=(n, n)) * np.geomspace(1e-4, 10.0, n)
    P = A @ A.T + np.eye(n) * 1e-9
    return 0.5 * (P + P.T)


@pytest.mark.parametrize("rate_scale", [1e-4, 1.0, 30.0], ids=["series", "turn", "spin"])
def test_propagate_kernel_equals_reference(rate_scale: float) -> None:
    """``propagate_into`` gives :func:`propagate`'s state and Jacobian (both branches of
    ``delta_quat``: the series below 1e-4 rad per step, the closed form above)."""
    rng = np.random.default_rng(7)
    for _ in range(5):
        x = _state(rng)
        acc = rng.normal(size=3) + np.array([0.0, 0.0, -9.8])
        gyro = rng.normal(size=3) * rate_scale
        x_ref, F_ref, _, _ = propagate(x, acc, gyro, 0.01, np.array([0.0, 0.0, 9.806]))
        x_new, F = np.empty(22), np.empty((22, 22))
        K.propagate_into(x, acc, gyro, 0.01, np.array([0.0, 0.0, 9.806]), x_new, F)
        np.testing.assert_allclose(x_new, x_ref, rtol=1e-13, atol=1e-13)
        np.testing.assert_allclose(F, F_ref, rtol=1e-12, atol=1e-14)


def _reference_predict(
    x: np.ndarray,
    P: np.ndarray,
    acc: np.ndarray,
    gyro: np.ndarray,
    dt: float,
    c: QekfConfig,
    var_gm: np.ndarray,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The prediction written out from the module docstring with :func:`propagate` (main's
    ``QekfEngine._predict_to``): ``F P F^T + Q`` symmetrised, and ``F`` (for ``Phi``)."""
    g_n = np.array([0.0, 0.0, 9.806])
    n = x.size
    x22, F22, G_g, G_a = propagate(x[:22], acc, gyro, dt, g_n)
    tau = c.cross_axis_corr_time_s
    k_w, k_a = 2.0 * c.gyro_misalignment**2 * tau, 2.0 * c.acc_misalignment**2 / tau
    d = np.zeros(22)
    d[10:13] = c.gyro_bias_rw_rad_s2_rthz**2 * dt
    d[13:16] = c.acc_bias_rw_mps3_rthz**2 * dt
    w = (gyro - x[10:13]) / x[16:19]
    qw, qx, qy, qz = x[:4]
    C = np.array(
        [
            [qw * qw + qx * qx - qy * qy - qz * qz, 2 * (qx * qy - qw * qz), 2 * (qx * qz + qw * qy)],
            [2 * (qx * qy + qw * qz), qw * qw - qx * qx + qy * qy - qz * qz, 2 * (qy * qz - qw * qx)],
            [2 * (qx * qz - qw * qy), 2 * (qy * qz + qw * qx), qw * qw - qx * qx - qy * qy + qz * qz],
        ]
    )
    a = (acc - x[13:16]) / x[19:22] + C.T @ g_n
    var_g = c.gyro_noise_rad_s_rthz**2 + k_w * (w @ w - w * w)
    d[13:16] += k_a * (a @ a - a * a) * dt
    d[16:22] = c.scale_rw_1_s_rthz**2 * dt
    Q = (G_g * (var_g / dt)) @ G_g.T + (c.acc_noise_mps2_rthz**2 / dt) * (G_a @ G_a.T) + np.diag(d)
    F = np.eye(n)
    F[:22, :22] = F22
    Qf = np.zeros((n, n))
    Qf[:22, :22] = Q
    x_new = x.copy()
    x_new[:22] = x22
    if n > 22:
        tf = c.gnss_receiver_filter_s
        for i, Te in enumerate((c.gnss_corr_time_s, c.gnss_corr_time_s, c.gnss_corr_time_v_s)):
            Phi2, Q2 = gnss_error_transition(dt, Te, tf)
            ie, ig = 22 + i, 25 + i
            F[np.ix_([ie, ig], [ie, ig])] = Phi2
            Qf[np.ix_([ie, ig], [ie, ig])] = Q2 * var_gm[i]
        x_new[22:] = F[22:, 22:] @ x[22:]
    M = F @ P @ F.T + Qf
    return x_new, 0.5 * (M + M.T), F


@pytest.mark.parametrize("form", ["paper", "consistent"])
def test_predict_kernel_equals_reference(form: str) -> None:
    """:func:`~iotnav.engines.qekf_kernel.predict` (state, covariance, smoother transition) equals
    the prediction written out with :func:`propagate`, for 22 states and for 28 with the GNSS
    error states and the cross-axis noise; two steps of different ``dt`` (the cached GNSS error
    transition must follow)."""
    c = QekfConfig(smoothing=True) if form == "paper" else QekfConfig.consistent(smoothing=True)
    eng = QekfEngine(c)
    rng = np.random.default_rng(3)
    x = _state(rng, eng.n)
    P = _covariance(rng, eng.n)
    Phi = np.eye(eng.n)
    var_gm = np.array([1.5, 1.5, 4.0])
    vec = eng._vec
    vec[K.V_VAR_GM : K.V_VAR_GM + 3] = var_gm
    xk, Pk, Phik = x.copy(), P.copy(), Phi.copy()
    for dt in (0.01, 0.0125):
        acc = rng.normal(size=3) + np.array([0.0, 0.0, -9.8])
        gyro = rng.normal(size=3) * 0.3
        x, P, F = _reference_predict(x, P, acc, gyro, dt, c, var_gm)
        Phi = F @ Phi
        Ff, Qf = np.empty((eng.n, eng.n)), np.empty((eng.n, eng.n))
        wm, ws = K.scratch()  # uninitialised: the kernel must not read what it did not write
        K.predict(
            xk, Pk, Phik, acc, gyro, dt, np.array([0.0, 0.0, 9.806]), eng._prm, vec, eng.st, Ff, Qf, wm, ws
        )
        np.testing.assert_allclose(Ff, F, rtol=1e-12, atol=1e-14)
        scale = np.sqrt(np.outer(np.diag(P), np.diag(P)))
        np.testing.assert_allclose(xk, x, rtol=1e-12, atol=1e-12)
        assert np.max(np.abs(Pk - P) / scale) < 1e-12
        np.testing.assert_array_equal(Pk, Pk.T)
        np.testing.assert_allclose(Phik, Phi, rtol=1e-12, atol=1e-13)


@pytest.mark.parametrize("m", [1, 2, 3, 4])
def test_update_kernel_equals_kalman_update(m: int) -> None:
    """:func:`~iotnav.engines.qekf_updates_kernel.update` gives :func:`iotnav.kalman.update`'s
    state, covariance, innovation, ``S`` and NIS (28 states, 1-4 rows, linear and with
    ``h(x)``), and its gate decision: rejected above the gate with the prior returned."""
    rng = np.random.default_rng(20 + m)
    n = 28
    for trial in range(4):
        x = _state(rng, n)
        P = _covariance(rng, n)
        H = rng.normal(size=(m, n)) * (rng.uniform(size=(m, n)) < 0.3)
        A = rng.normal(size=(m, m))
        R = A @ A.T + 0.1 * np.eye(m)
        z = H @ x + rng.normal(size=m) * 3.0
        h_x = None if trial % 2 == 0 else H @ x + 0.01 * rng.normal(size=m)
        ref = kalman.update(x, P, z, H, R, h_x=h_x)
        y, S = np.empty(m), np.empty((m, m))
        ok, nis, xn, Pn = KU.update(x, P, z, H, R, H @ x if h_x is None else h_x, math.inf, y, S)
        assert ok
        np.testing.assert_allclose(nis, ref.nis, rtol=1e-12)
        np.testing.assert_allclose(y, ref.innovation, rtol=1e-13, atol=1e-13)
        np.testing.assert_allclose(S, ref.S, rtol=1e-13, atol=1e-13)
        np.testing.assert_allclose(xn, ref.x, rtol=1e-11, atol=1e-11)
        _assert_cov_close(Pn, ref.P, 1e-11)
        np.testing.assert_array_equal(Pn, Pn.T)
        gate = 0.5 * ref.nis
        ok, nis, xg, Pg = KU.update(x, P, z, H, R, H @ x if h_x is None else h_x, gate, y, S)
        assert not ok and not kalman.update(x, P, z, H, R, h_x=h_x, gate=gate).accepted
        assert xg is x and Pg is P


def test_norm_and_nhc_models_equal_python_forms() -> None:
    """The compiled norm (Eq. 9) and non-holonomic models give ``H``, ``R`` and ``h(x)`` of
    :func:`~iotnav.engines.qekf.norm_measurement` and :func:`~iotnav.engines.qekf.nhc_measurement`
    (padded with zero columns to 28 states)."""
    rng = np.random.default_rng(5)
    for _ in range(10):
        x = _state(rng, 28)
        H, R, hx = np.empty((1, 28)), np.empty((1, 1)), np.empty(1)
        KU.norm_model(x, 1e-3, H, R, hx)
        _, H_ref, R_ref, hx_ref = norm_measurement(x[:22], 1e-3)
        np.testing.assert_allclose(H[:, :22], H_ref, rtol=1e-14, atol=1e-15)
        assert not H[:, 22:].any()
        np.testing.assert_allclose(R, R_ref, rtol=1e-15)
        np.testing.assert_allclose(hx, hx_ref, rtol=1e-12, atol=1e-15)
        mu = float(rng.uniform(-3.0, 3.0))
        KU.nhc_model(x, mu, 0.3, H, R, hx)
        _, H_ref, R_ref, hx_ref = nhc_measurement(x[:22], mu, 0.3)
        np.testing.assert_allclose(H[:, :22], H_ref, rtol=1e-13, atol=1e-13)
        assert not H[:, 22:].any()
        np.testing.assert_allclose(R, R_ref, rtol=1e-15)
        np.testing.assert_allclose(hx, hx_ref, rtol=1e-13, atol=1e-13)


def test_geodetic_conversion_equals_pymap3d() -> None:
    """The output rows' ECEF -> geodetic (Bowring's iteration) inverts the forward conversion to
    1e-12 deg and 1 um, and agrees with pymap3d (main's conversion, itself off by up to 1.1e-11
    deg here) to 1e-10 deg, from the poles to the equator, 10 km below to 100 km above the
    ellipsoid."""
    rng = np.random.default_rng(11)
    lat = np.r_[rng.uniform(-90.0, 90.0, 300), 90.0, -90.0, 0.0, 89.9999, 45.0]
    lon = rng.uniform(-180.0, 180.0, lat.size)
    h = rng.uniform(-1e4, 1e5, lat.size)
    r_e = geodetic_to_ecef(lat, lon, h)
    lat_r, lon_r, h_r = ecef_to_geodetic(r_e)
    for k in range(lat.size):
        la, lo, hh = K.ecef_to_geodetic(*r_e[k])
        assert abs(la - lat[k]) < 1e-12
        assert abs(la - lat_r[k]) < 1e-10
        if abs(la) < 89.9:  # longitude undefined at the poles
            assert abs(math.remainder(lo - lon[k], 360.0)) < 1e-12
            assert abs(math.remainder(lo - lon_r[k], 360.0)) < 1e-10
        assert abs(hh - h[k]) < 1e-6
        assert abs(hh - h_r[k]) < 1e-6


# ----------------------------------------------------------------------------- stored runs


@pytest.fixture(scope="module")
def reference() -> tuple[Any, dict[str, Any]]:
    ref = np.load(REFERENCE)
    return ref, json.loads(str(ref["meta"]))


def _case(ref: Any, meta: dict[str, Any], name: str) -> tuple[Log, QekfConfig]:
    m = meta[name]
    tables = {
        tb: pd.DataFrame({c: ref[f"{name}/{tb}/{c}"] for c in m[f"{tb}_columns"]}, columns=m[f"{tb}_columns"])
        for tb in ("imu", "gnss", "mag")
    }
    log = Log(gnss=tables["gnss"], imu=tables["imu"], mag=tables["mag"], utc_offset_s=m["utc_offset_s"])
    kw: dict[str, Any] = {"wmm_year": 2020.45, **m["config"]}
    if "mag_soft_iron" in m:
        kw.update(mag_soft_iron=tuple(m["mag_soft_iron"]), mag_hard_iron_ut=tuple(m["mag_hard_iron_ut"]))
    return log, (QekfConfig.consistent if m["form"] == "consistent" else QekfConfig)(**kw)


def _assert_cov_close(P: np.ndarray, P_ref: np.ndarray, tol: float = 1e-9) -> None:
    """Covariances equal to ``tol`` of the elements' scale ``sqrt(P_ii P_jj)``."""
    d = np.diagonal(P_ref, axis1=-2, axis2=-1)
    scale = np.sqrt(d[..., :, None] * d[..., None, :])
    err = float(np.max(np.abs(P - P_ref) / scale))
    assert err < tol, err


def _assert_rows_close(rows: np.ndarray, ref_rows: np.ndarray) -> None:
    """Output rows: times, NED positions (m), velocities (m/s), attitudes (rad) and sigmas (m) to
    1e-9 relative (and 1e-9 absolute near zero); latitude and longitude to 1e-10 deg (1 cm),
    height to 1e-6 m; the source exactly."""
    assert rows.shape == ref_rows.shape
    for i, col in enumerate(FLOAT_COLUMNS):
        a, b = rows[:, 1 + i], ref_rows[:, 1 + i]
        np.testing.assert_array_equal(np.isfinite(a), np.isfinite(b), err_msg=col)
        ok = np.isfinite(b)
        if col in ("lat", "lon"):
            np.testing.assert_allclose(a[ok], b[ok], rtol=0.0, atol=1e-10, err_msg=col)
        elif col == "height":
            np.testing.assert_allclose(a[ok], b[ok], rtol=0.0, atol=1e-6, err_msg=col)
        else:
            np.testing.assert_allclose(a[ok], b[ok], rtol=1e-9, atol=1e-9, err_msg=col)
    np.testing.assert_array_equal(rows[:, -1], ref_rows[:, -1], err_msg="source")


@pytest.mark.parametrize("name", ["paper", "consistent", "fallback"])
def test_engine_equals_stored_python_run(reference: tuple[Any, dict[str, Any]], name: str) -> None:
    """Streaming ``step()`` and the batch block path reproduce the stored run of main's
    per-sample Python engine: output rows, ``x`` and ``P`` at GNSS epochs and at the end, the
    NIS of every update, the event counts and (paper, fallback) the smoothing records."""
    ref, meta = reference
    m = meta[name]
    log, cfg = _case(ref, meta, name)
    eng = QekfEngine(cfg)
    rows, xs, Ps, n_imu = _make_reference().record(eng, log)  # the protocol that made the reference
    assert n_imu == m["n_imu"]
    _assert_rows_close(rows, ref[f"{name}/rows"])
    x_ref = ref[f"{name}/x"]
    np.testing.assert_array_equal(xs[:, 0], x_ref[:, 0])  # at the same samples
    np.testing.assert_allclose(xs[:, 1:], x_ref[:, 1:], rtol=1e-9, atol=1e-10)
    _assert_cov_close(Ps, ref[f"{name}/P"])
    np.testing.assert_allclose(eng.x, ref[f"{name}/x_end"], rtol=1e-9, atol=1e-10)
    _assert_cov_close(eng.P, ref[f"{name}/P_end"])
    nis = np.array([(t, v) for t, _, v, _ in eng.nis])
    np.testing.assert_allclose(nis, ref[f"{name}/nis"], rtol=1e-9, atol=1e-9)
    counts: dict[str, int] = {}
    for e in eng.events:
        counts[e["type"]] = counts.get(e["type"], 0) + 1
    assert counts == m["event_counts"]
    log_s = eng.smoothing_log
    assert (0 if log_s is None else len(log_s)) == m["smoothing_records"]
    if log_s is not None:
        np.testing.assert_array_equal(np.array(log_s.t), ref[f"{name}/smooth_t"])
        for part in ("x_prior", "x_post", "Phi"):
            np.testing.assert_allclose(
                np.sum(getattr(log_s, part), axis=0), ref[f"{name}/smooth_{part}_sum"], rtol=1e-9, atol=1e-9
            )
        for part in ("P_prior", "P_post"):
            _assert_cov_close(np.sum(getattr(log_s, part), axis=0), ref[f"{name}/smooth_{part}_sum"])
    # the batch path (compiled blocks between the GNSS and magnetometer samples) gives the same rows
    df = run_batch(QekfEngine(cfg), log)
    batch = np.column_stack(
        [np.arange(len(df)), df[list(FLOAT_COLUMNS)].to_numpy(), [SOURCES.index(s) for s in df["source"]]]
    )
    _assert_rows_close(batch[::4], ref[f"{name}/rows"])
    assert df.attrs["events"] == eng.events


def test_engine_copy_keeps_its_kernel_state(reference: tuple[Any, dict[str, Any]]) -> None:
    """A deep copy mid-run (as :mod:`iotnav.eval.outages` snapshots engines) carries on exactly as
    the original: its vector attributes stay views of its own kernel state."""
    import copy

    ref, meta = reference
    log, cfg = _case(ref, meta, "fallback")
    samples = list(iter_samples(log))
    eng = QekfEngine(cfg)
    half = len(samples) // 2
    for s in samples[:half]:
        eng.step(s)
    twin = copy.deepcopy(eng)
    assert twin.acc.base is twin._vec and twin._r_nhc.base is twin._vec
    for s in samples[half:]:
        a, b = eng.step(s), twin.step(s)
        assert a == b
    np.testing.assert_array_equal(twin.P, eng.P)


@pytest.mark.parametrize("coupling", ["jacobian", "noise", "accelerometer"])
def test_triad_model_equals_triad_measurement(coupling: str) -> None:
    """The compiled TRIAD observation (:func:`~iotnav.engines.qekf_updates_kernel.triad_model`)
    gives :func:`~iotnav.engines.qekf.triad_measurement`'s ``z``, ``H`` (padded with zero columns
    to 28 states) and ``R`` to the rounding of the matrix products, for each state coupling."""
    from iotnav.engines.qekf_mag import _COUPLING
    from iotnav.engines.qekf_models import _ACC_COLS, triad_measurement
    from iotnav.techniques.triad import quat_to_dcm

    rng = np.random.default_rng(5)
    g_n, m_n = np.array([0.0, 0.0, 9.80665]), np.array([22.4, 1.1, 41.3])
    for _ in range(20):
        q = rng.normal(size=4)
        q /= np.linalg.norm(q)
        C = quat_to_dcm(q)
        g_b = C.T @ g_n + rng.normal(size=3) * 0.2
        m_b = C.T @ m_n + rng.normal(size=3)
        D = rng.normal(size=(3, 22))
        P = _covariance(rng, 22)
        z, H, R = triad_measurement(
            q, g_b, m_b, g_n, m_n, 0.03, 0.015, 1e-3, D,
            None if coupling == "jacobian" else P, _ACC_COLS if coupling == "accelerometer" else None,
        )  # fmt: skip
        z2, H2, R2 = np.empty(4), np.empty((4, 28)), np.empty((4, 4))
        assert KU.triad_model(q, g_b, m_b, g_n, m_n, 0.03, 0.015, 1e-3, D, P, _COUPLING[coupling], z2, H2, R2)
        np.testing.assert_allclose(z2, z, rtol=0.0, atol=1e-14)
        np.testing.assert_allclose(H2[:, :22], H, rtol=0.0, atol=1e-14 * np.abs(H).max())
        assert np.all(H2[:, 22:] == 0.0)
        np.testing.assert_allclose(R2, R, rtol=0.0, atol=1e-14 * np.abs(R).max())
    # collinear gravity and field: flagged (the engine raises triad's ValueError)
    assert not KU.triad_model(q, g_b, 3.0 * g_b, g_n, m_n, 0.03, 0.015, 1e-3, D, P, 0, z2, H2, R2)


def test_compiled_nhc_step_equals_python_step(tmp_path: Path, monkeypatch: Any) -> None:
    """The fallback's non-holonomic step inside the compiled IMU loop
    (:func:`~iotnav.engines.qekf_updates_kernel.nhc_step`) gives bitwise the run of its Python
    form (:func:`~iotnav.engines.qekf_fallback.nhc`): rows, final ``x`` and ``P``, NIS, events.
    car-tunnel (no magnetometer) shortened to 80 s: heading reset near 46 s, then NHC at 1 Hz."""
    from iotnav import sim
    from iotnav.engines import qekf_fallback as FB
    from iotnav.io import ingest

    sim.write(sim.build("car-tunnel", seed=0, overrides={"duration_s": 80.0}), tmp_path)
    log = ingest([tmp_path])
    cfg = QekfConfig(smoothing=False)
    compiled_calls = []
    inputs = FB.nhc_kernel_inputs

    def counted(eng: QekfEngine) -> None:
        inputs(eng)
        compiled_calls.append(eng.st[K.S_NHC_COMPILED])

    monkeypatch.setattr(FB, "nhc_kernel_inputs", counted)
    eng_c = QekfEngine(cfg)
    df_c = run_batch(eng_c, log)
    assert max(compiled_calls) == 1.0  # the kernel's step ran

    def python_only(eng: QekfEngine) -> None:
        eng.st[K.S_NHC_COMPILED] = 0.0

    monkeypatch.setattr(FB, "nhc_kernel_inputs", python_only)
    eng_p = QekfEngine(cfg)
    df_p = run_batch(eng_p, log)
    n_nhc = sum(1 for _, kind, _, _ in eng_p.nis if kind == "nhc")
    assert n_nhc >= 10, n_nhc
    np.testing.assert_array_equal(df_c[list(FLOAT_COLUMNS)].to_numpy(), df_p[list(FLOAT_COLUMNS)].to_numpy())
    assert list(df_c["source"]) == list(df_p["source"])
    np.testing.assert_array_equal(eng_c.x, eng_p.x)
    np.testing.assert_array_equal(eng_c.P, eng_p.P)
    assert eng_c.nis == eng_p.nis
    assert eng_c.events == eng_p.events


def test_attitude_corrections_equal_the_rotation_vector() -> None:
    """The compiled smoother attitude correction equals ``rotvec(C(q_s) C(q_f)^T)`` written out
    with numpy (normalised quaternions, quadratic-form DCM, axis-angle from the trace), for
    large angles, small ones (below the 1e-6 rad branch) and unnormalised inputs."""
    from iotnav.techniques.triad import quat_to_dcm

    def _rotvec(C: np.ndarray) -> np.ndarray:  # the Python loop the kernel replaced
        c = max(-1.0, min(1.0, 0.5 * (np.trace(C) - 1.0)))
        ang = math.acos(c)
        v = np.array([C[2, 1] - C[1, 2], C[0, 2] - C[2, 0], C[1, 0] - C[0, 1]])
        if ang < 1e-6:
            return 0.5 * v
        return v * (ang / (2.0 * math.sin(ang)))

    rng = np.random.default_rng(7)
    qf = rng.normal(size=(40, 4)) * 3.0
    qs = rng.normal(size=(40, 4))
    qs[:10] = qf[:10] * 2.0 + rng.normal(size=(10, 4)) * 1e-9  # tiny rotations
    out = np.empty((40, 3))
    KU.attitude_corrections(qf, qs, out)
    for k in range(40):
        a = qf[k] / np.linalg.norm(qf[k])
        b = qs[k] / np.linalg.norm(qs[k])
        ref = _rotvec(quat_to_dcm(b) @ quat_to_dcm(a).T)
        np.testing.assert_allclose(out[k], ref, rtol=1e-9, atol=1e-12)
    assert np.all(np.linalg.norm(out[:10], axis=1) < 1e-6)
    assert np.all(np.linalg.norm(out[10:], axis=1) > 1e-3)
