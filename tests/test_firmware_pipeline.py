"""The Forno pipeline's blocks 3 and 4 in C (firmware/pipeline_*.c) beside their Python modules (issue 20).

The C blocks, built for the host with ``gcc -std=c99 -Wall -Wextra -Werror -pedantic`` in
float32 and float64 and loaded with ctypes (:mod:`iotnav.firmware.pipeline`), are wired as the
pipeline wires them (every GNSS speed into block 3; while static, the fix's NED position into
block 4; its buffers reset when the static state changes) on 280 s of the real rtklibexplorer
drive_0708 (its 100 Hz IMU and 4 Hz GNSS, with a 30 s gap in the GNSS speeds), and so are
:class:`~iotnav.techniques.static.StaticDetector` and :class:`~iotnav.techniques.lowpass3.Lowpass3`:
every static decision and every low-pass output must be the same.
"""

from __future__ import annotations

import dataclasses
import math
import struct
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from conftest import datasets_dir
from iotnav.engines.base import TangentPlane
from iotnav.firmware import pipeline as fp
from iotnav.firmware import pipeline_kf3 as fk3
from iotnav.techniques.lowpass3 import Lowpass3, Lowpass3Config
from iotnav.techniques.static import S_ACC_H, StaticConfig, StaticDetector

DRIVE = datasets_dir() / "rtklibexplorer_gnss_imu" / "drive_0708"
REPO = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def libs(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    d = tmp_path_factory.mktemp("fwpl")
    return {"f32": fp.build(d / "pl_f32.so"), "f64": fp.build(d / "pl_f64.so", double=True)}


@pytest.fixture(scope="module")
def replay_exe(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """host/replay_pipeline.c with the float32 blocks under ASan + UBSan, built once for the module."""
    return fp.build_replay(tmp_path_factory.mktemp("fwpl_replay") / "replay_pl")


@pytest.fixture(scope="module")
def drive() -> Any:
    """drive_0708's log, loaded once for the module."""
    from iotnav.cli.outages import load_dataset

    log, _ = load_dataset(DRIVE)  # fails (not skips) when the dataset is missing
    return log


@pytest.fixture(scope="module")
def stream(drive: Any) -> dict[str, Any]:
    """280 s of drive_0708: IMU times and horizontal specific force, GNSS times, speeds, NED fixes."""
    log = drive
    t0 = float(log.gnss.t.iloc[0])
    g = log.gnss[(log.gnss.t < t0 + 280.0) & log.gnss.valid.astype(bool)].reset_index(drop=True)
    imu = log.imu[(log.imu.t >= t0) & (log.imu.t < t0 + 280.0)].reset_index(drop=True)
    f = imu[["acc_x", "acc_y", "acc_z"]].to_numpy(float)
    # level the sensor with one rotation (the mean specific force is up): block 3 reads the norm
    # of the horizontal part only, so any horizontal basis gives the same decisions
    e3 = f.mean(axis=0) / np.linalg.norm(f.mean(axis=0))
    e1 = np.cross(e3, [0.0, 1.0, 0.0] if abs(e3[0]) > 0.5 else [1.0, 0.0, 0.0])
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(e3, e1)
    # NED about the fix at 264 s, 559 m from the start: the stops block 3 finds (at the start) are
    # that far from the origin, as on a long drive (float32 resolves 61 um there)
    o = int(np.argmin(np.abs(g.t.to_numpy(float) - (t0 + 264.0))))
    plane = TangentPlane(float(g.lat_deg[o]), float(g.lon_deg[o]), float(g.height_m[o]))
    r_n = np.array([plane.to_ned(a, b, h) for a, b, h in zip(g.lat_deg, g.lon_deg, g.height_m, strict=True)])
    speed = g.speed_mps.to_numpy(float).copy()
    gap = (g.t > t0 + 120.0) & (g.t < t0 + 150.0)
    speed[gap.to_numpy()] = math.nan  # no GPS speed for 30 s: the stale-speed rules
    return {
        "t_imu": imu.t.to_numpy(float),
        "acc": np.column_stack([f @ e1, f @ e2]),
        "t_gnss": g.t.to_numpy(float),
        "speed": speed,
        "r_n": r_n,
        "t0": t0,
    }


def _chain(det: Any, lp: Any, s: dict[str, Any], rec: list[bytes] | None = None) -> dict[str, list]:
    """Blocks 3 -> 4 as the pipeline wires them; the same calls for Python and C objects (with
    ``rec``: also the records of ``host/replay_pipeline.c``, which wires them the same way)."""
    out: dict[str, list] = {"static": [], "acc_h": [], "speed": [], "lp": [], "lp_n": [], "lp_level": []}
    t_i, t_g, acc, speed, r_n = s["t_imu"], s["t_gnss"], s["acc"], s["speed"], s["r_n"]
    j = 0
    was = False
    for k, t in enumerate(t_i):
        while j < len(t_g) and t_g[j] <= t:
            det.update_speed(float(t_g[j]), float(speed[j]))
            if rec is not None:
                rec.append(fp.replay_record("G", float(t_g[j]), (float(speed[j]), *map(float, r_n[j]))))
            if was:
                y = lp.push(r_n[j])
                out["lp"].append(None if y is None else np.asarray(y, float))
                out["lp_n"].append(lp.n_fixes)
                out["lp_level"].append(lp.level)
            j += 1
        # in the second half of the speed gap the caller has a fallback speed (the true one)
        fb = float(s.get("fallback", {}).get(k, math.nan))
        now = det.step(float(t), acc[k], fb)
        if rec is not None:
            rec.append(fp.replay_record("I", float(t), (float(acc[k, 0]), float(acc[k, 1]), fb)))
        if now != was:
            lp.reset()
        was = now
        out["static"].append(bool(now))
        out["acc_h"].append(float(det.state[S_ACC_H]) if isinstance(det, StaticDetector) else det.acc_h)
        out["speed"].append(float(det.speed))
    return out


def _compare(py: dict[str, list], c: dict[str, list], tol: float) -> None:
    """Same decisions and levels; low-pass outputs within ``tol`` m, the detector's filtered values
    within ``tol`` relative (float64) or 1e-5 (float32)."""
    rel = min(tol, 1e-5)
    assert c["static"] == py["static"]
    assert np.allclose(c["acc_h"], py["acc_h"], rtol=rel, atol=rel, equal_nan=True)
    assert np.allclose(c["speed"], py["speed"], rtol=rel, atol=rel, equal_nan=True)
    assert c["lp_n"] == py["lp_n"] and c["lp_level"] == py["lp_level"]
    assert [v is None for v in c["lp"]] == [v is None for v in py["lp"]]
    d = [np.abs(a - b).max() for a, b in zip(c["lp"], py["lp"], strict=True) if a is not None]
    assert d and max(d) < tol, max(d)


def _run(
    lib: Path, s: dict[str, Any], double: bool, sc: StaticConfig, lc: Lowpass3Config
) -> tuple[dict, dict]:
    det_c, lp_c = fp.StaticBlock(lib, sc, double=double), fp.Lowpass3Block(lib, lc, double=double)
    assert det_c.init_rc == 0 and lp_c.init_rc == 0
    py = _chain(StaticDetector(sc), Lowpass3(lc), s)
    c = _chain(det_c, lp_c, s)
    return py, c


def _with_fallback(s: dict[str, Any]) -> dict[str, Any]:
    """The GPS speed gap's second half with the hidden GPS speed as the caller's fallback."""
    t = s["t_imu"]
    ks = np.flatnonzero((t > s["t0"] + 135.0) & (t < s["t0"] + 150.0))
    true = np.interp(t[ks], s["t_gnss"], np.nan_to_num(s["speed"], nan=0.0))
    return {**s, "fallback": dict(zip(ks.tolist(), true.tolist(), strict=True))}


def test_generated_header_is_current() -> None:
    """The checked-in config header is exactly what the generator writes from the dataclasses."""
    assert (REPO / "firmware" / fp.HEADER_NAME).read_text() == fp.config_header()
    text = fp.config_header(StaticConfig(theta_a_mps2=0.2, speed_window=5), Lowpass3Config(n1=4))
    assert (
        "IOTNAV_R(0.2) /* theta_a_mps2 */" in text and "5 /* speed_window */" in text and "4 /* n1 */" in text
    )


def test_unsupported_sizes_are_refused(libs: dict[str, Path]) -> None:
    assert (
        fp.StaticBlock(libs["f32"], StaticConfig(speed_window=fp.STATIC_SPEED_WINDOW_MAX + 1)).init_rc == -1
    )
    assert fp.Lowpass3Block(libs["f32"], Lowpass3Config(n2=fp.LOWPASS3_N_MAX + 1)).init_rc == -1
    assert fp.Lowpass3Block(libs["f32"], Lowpass3Config(n3=0)).init_rc == -1


def test_static_and_lowpass_float32_and_float64_on_drive_0708(
    libs: dict[str, Path], stream: dict[str, Any]
) -> None:
    s = _with_fallback(stream)
    py, c32 = _run(libs["f32"], s, False, StaticConfig(), Lowpass3Config())
    st = np.array(py["static"])
    assert 0.05 < st.mean() < 0.95 and np.count_nonzero(np.diff(st.astype(int))) >= 4  # stops and starts
    assert max(py["lp_level"]) == 3  # a stop long enough for level 3
    far = [np.linalg.norm(y[:2]) for y in py["lp"] if y is not None]
    assert min(far) > 500.0
    _compare(py, c32, 1e-3)  # float32 state against float64: sub-millimetre, same decisions
    _, c64 = _run(libs["f64"], s, True, StaticConfig(), Lowpass3Config())
    _compare(py, c64, 1e-9)


def _decode(records: list[bytes], out: bytes) -> dict[str, list]:
    """The replay program's output, in :func:`_chain`'s form."""
    res: dict[str, list] = {"static": [], "acc_h": [], "speed": [], "lp": [], "lp_n": [], "lp_level": []}
    pos, was = 0, False
    for r in records:
        if r[:1] == b"I":
            now, acc_h, speed = struct.unpack_from("<iff", out, pos)
            pos += 12
            was = bool(now)
            res["static"].append(was)
            res["acc_h"].append(acc_h)
            res["speed"].append(speed)
        elif was:
            changed, x, y, z, n, level = struct.unpack_from("<ifffii", out, pos)
            pos += 24
            res["lp"].append(np.array([x, y, z]) if changed else None)
            res["lp_n"].append(n)
            res["lp_level"].append(level)
    assert pos == len(out)
    return res


def test_sanitized_build_replays_the_same_chain(
    replay_exe: Path, libs: dict[str, Path], stream: dict[str, Any]
) -> None:
    """The float32 blocks built with ASan + UBSan (host/replay_pipeline.c) replay the drive's first
    60 s (tuned: short rings that wrap) with no sanitizer report and the ctypes run's exact values."""
    from iotnav.firmware.host import replay_sanitized

    s = {**stream}
    s["t_imu"] = s["t_imu"][s["t_imu"] < s["t0"] + 60.0]
    sc, lc = StaticConfig(acc_tau_s=0.2), Lowpass3Config(n1=3, n2=2, n3=4)
    rec: list[bytes] = []
    c = _chain(fp.StaticBlock(libs["f32"], sc), fp.Lowpass3Block(libs["f32"], lc), s, rec)
    assert sum(v is not None for v in c["lp"]) >= 5
    out = replay_sanitized(replay_exe, fp.replay_config(sc, lc) + b"".join(rec))
    got = _decode(rec, out)
    assert got["static"] == c["static"] and got["lp_n"] == c["lp_n"] and got["lp_level"] == c["lp_level"]
    for k in ("acc_h", "speed"):
        assert np.array_equal(got[k], c[k], equal_nan=True)
    assert all(
        (a is None and b is None) or np.array_equal(a, b) for a, b in zip(got["lp"], c["lp"], strict=True)
    )


def test_tuned_blocks_float64(libs: dict[str, Path], stream: dict[str, Any]) -> None:
    """Hysteresis (the GPS speeds with a tracker's 0.4 m/s of seeded noise, so a stop's speed
    crosses the threshold), no low-pass on the acceleration, short levels (rings wrap): still
    equal to 1e-9, and the hysteresis decides some samples."""
    rng = np.random.default_rng(7)
    noisy = {**stream, "speed": np.abs(stream["speed"] + rng.normal(0.0, 0.4, len(stream["speed"])))}
    sc = StaticConfig(exit_speed_mps=1.0, speed_window=5, acc_tau_s=0.0, theta_a_mps2=0.3)
    lc = Lowpass3Config(n1=3, n2=2, n3=4)
    py, c64 = _run(libs["f64"], noisy, True, sc, lc)
    no_hyst = _chain(StaticDetector(dataclasses.replace(sc, exit_speed_mps=0.0)), Lowpass3(lc), noisy)
    assert py["static"] != no_hyst["static"]
    assert max(py["lp_n"]) == 3 * 2 * 4  # level 3 full
    _compare(py, c64, 1e-9)


# ---------------------------------------------------------------------------------------------
# Block 1: the last known position (iotnav.techniques.last_position, firmware/pipeline_lastpos.c)


def _damaged(g: Any, seed: int) -> dict[str, np.ndarray]:
    """A log's GNSS epochs (valid or not), a few damaged as a receiver damages them (seeded): 1 %
    declared invalid, 0.5 % without coordinates, 1 % with an unknown PDOP."""
    n = len(g)
    rng = np.random.default_rng(seed)
    valid = g.valid.astype(bool).to_numpy() & (rng.random(n) > 0.01)
    lat, lon = g.lat_deg.to_numpy(float).copy(), g.lon_deg.to_numpy(float).copy()
    lat[rng.random(n) < 0.005] = math.nan
    pdop = g.pdop.to_numpy(float).copy()
    pdop[rng.random(n) < 0.01] = math.nan
    num_sv = g.num_sv.fillna(0).to_numpy(int)
    return {"t": g.t.to_numpy(float), "valid": valid, "lat": lat, "lon": lon, "pdop": pdop, "num_sv": num_sv}


#: Real receiver logs with a PDOP (gpsd's regression captures; drive_0708 has none): a Telit
#: HE910 (2.25 to 4.0 over 186 s), a SkyTraq with DGPS (2.1 to 3.2), a SiRFstar V (1.0 to 1.8).
PDOP_LOGS = ("telit-he910.log", "skytraq-dgps.log", "sirfstarv-nmea.log")
NMEA_CORPUS = datasets_dir() / "gpsd_nmea_corpus" / "logs"


@pytest.fixture(scope="module")
def fixes(drive: Any) -> dict[str, np.ndarray]:
    """Every GNSS epoch of drive_0708 (damaged as :func:`_damaged` says)."""
    return _damaged(drive.gnss, 20)


@pytest.fixture(scope="module")
def pdop_fixes() -> list[dict[str, np.ndarray]]:
    """The epochs of :data:`PDOP_LOGS` (damaged as :func:`_damaged` says)."""
    import warnings

    from iotnav.io.nmea import read_nmea

    out = []
    for k, name in enumerate(PDOP_LOGS):
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")  # the captures' own damage, reported by the reader
            res = read_nmea(NMEA_CORPUS / name)  # fails (not skips) when the corpus is missing
        g = res.gnss if hasattr(res, "gnss") else res[0].gnss
        assert np.isfinite(g.pdop.to_numpy(float)).sum() > 50
        out.append(_damaged(g, 21 + k))
    return out


def _boot(logic: Any, f: dict[str, np.ndarray], declare_first: bool = True) -> dict[str, list]:
    """Block 1 as the pipeline drives it: every fix through check_fix; the first acceptable one
    through first_fix; every acceptable one through due. ``declare_first=False``: first_fix is
    never called, so the settling gate (without a stored position) judges every fix."""
    out: dict[str, list] = {"reason": [], "event": [], "due": []}
    for t, v, la, lo, p, ns in zip(
        f["t"], f["valid"], f["lat"], f["lon"], f["pdop"], f["num_sv"], strict=True
    ):
        r = logic.check_fix(bool(v), float(la), float(lo), float(p), int(ns), float(t))
        out["reason"].append(r)
        if r is not None:
            continue
        if declare_first and not logic.first_fix_seen:
            out["event"].append(logic.first_fix(float(t), float(la), float(lo)))
        out["due"].append(logic.due(float(t)))
    return out


def test_last_position_gate_on_real_logs(
    libs: dict[str, Path], fixes: dict[str, np.ndarray], pdop_fixes: list[dict[str, np.ndarray]]
) -> None:
    """Fix acceptance and the settling gate on every epoch of drive_0708 and of three receiver
    logs with a PDOP (the gate kept open all along, and tightened so that it refuses): every
    reason the same in float32 and float64; then the pipeline's use on the drive."""
    from iotnav.techniques.last_position import LastPositionConfig, LastPositionLogic

    seen: set[str | None] = set()
    n_settling = 0
    for f in [fixes, *pdop_fixes]:
        p = f["pdop"][np.isfinite(f["pdop"])]
        cfgs = [LastPositionConfig()]
        if len(p):
            # thresholds inside the log's own spread: "pdop", "num_sv", "pdop_unknown" and
            # "settling" (settle_max_pdop below the median: refused until the window is covered)
            cfgs.append(
                LastPositionConfig(
                    max_pdop=float(np.quantile(p, 0.9)),
                    min_num_sv=int(np.quantile(f["num_sv"], 0.2)),
                    accept_unknown_pdop=False,
                    settle_ratio=0.02,
                    settle_window_s=4.0,
                    settle_max_pdop=float(np.quantile(p, 0.3)),
                )
            )
        else:
            cfgs.append(LastPositionConfig(accept_unknown_pdop=False, min_num_sv=23))
        for cfg in cfgs:
            py = _boot(LastPositionLogic(cfg), f, declare_first=False)
            seen |= set(py["reason"])
            n_settling += py["reason"].count("settling")
            for lib, double in ((libs["f32"], False), (libs["f64"], True)):
                blk = fp.LastPositionBlock(lib, cfg, double=double)
                assert blk.init_rc == 0
                assert _boot(blk, f, declare_first=False) == py, (double, cfg)
                assert blk.n_hist_dropped == 0
    assert {None, "invalid", "no_position", "pdop", "pdop_unknown", "num_sv", "settling"} <= seen
    assert n_settling >= 20
    # the pipeline's use (first_fix ends the gate) with the defaults: same first fix, same saves
    py = _boot(LastPositionLogic(), fixes)
    assert py["event"] == [None] and sum(py["due"]) >= 3
    for lib, double in ((libs["f32"], False), (libs["f64"], True)):
        assert _boot(fp.LastPositionBlock(lib, double=double), fixes) == py


def test_last_position_moved_while_off(libs: dict[str, Path], fixes: dict[str, np.ndarray]) -> None:
    """A stored position near the first fix (no event) and one farther than the threshold (the
    "moved while off" event): float64 distance to 1e-9 relative; float32 within the round-off of
    float32 degrees (half a float32 ulp of each of the four coordinates, in metres)."""
    from iotnav.techniques.last_position import LastPositionLogic, StoredPosition

    ok = np.flatnonzero(fixes["valid"] & np.isfinite(fixes["lat"]) & ~(fixes["pdop"] > 10.0))
    la0, lo0 = fixes["lat"][ok[0]], fixes["lon"][ok[0]]
    far = ok[
        np.argmax(np.hypot(fixes["lat"][ok] - la0, (fixes["lon"][ok] - lo0) * math.cos(math.radians(la0))))
    ]
    m_per_deg = 6371008.8 * math.pi / 180.0
    bound = 2.0 * m_per_deg * float(np.spacing(np.float32(abs(la0))) + np.spacing(np.float32(abs(lo0))))
    for stored in ((float(la0) + 2e-5, float(lo0)), (float(fixes["lat"][far]), float(fixes["lon"][far]))):
        py = _boot(LastPositionLogic(stored=StoredPosition(*stored, 0.0)), fixes)
        for lib, double in ((libs["f32"], False), (libs["f64"], True)):
            c = _boot(fp.LastPositionBlock(lib, stored=stored, double=double), fixes)
            assert c["reason"] == py["reason"] and c["due"] == py["due"]
            assert [e is None for e in c["event"]] == [e is None for e in py["event"]]
            if py["event"][0] is not None:
                dp, dc = py["event"][0]["distance_m"], c["event"][0]["distance_m"]
                assert dp > 500.0
                assert abs(dc - dp) < (1e-9 * dp if double else bound), (double, dc, dp, bound)


# ---------------------------------------------------------------------------------------------
# Block 2's gyro-bias KF (iotnav.techniques.gyro_bias_kf, firmware/pipeline_gyrobias.c)


def _static_decisions(s: dict[str, Any], n: int) -> np.ndarray:
    """Block 3's (Python) decision at the stream's first ``n`` IMU samples."""
    det, j, out = StaticDetector(), 0, np.zeros(n, bool)
    t_i, t_g = s["t_imu"], s["t_gnss"]
    for k in range(n):
        while j < len(t_g) and t_g[j] <= t_i[k]:
            det.update_speed(float(t_g[j]), float(s["speed"][j]))
            j += 1
        out[k] = det.step(float(t_i[k]), s["acc"][k])
    return out


def _bias_run(kf: Any, dt: np.ndarray, gyro: np.ndarray, static: np.ndarray) -> tuple[np.ndarray, ...]:
    """The cascade's use: predict over every IMU interval, update while static; x, P, used per sample."""
    xs, ps, used = np.empty((len(dt), 3)), np.empty((len(dt), 9)), np.zeros(len(dt), bool)
    for k in range(len(dt)):
        kf.predict(float(dt[k]))
        if static[k]:
            used[k] = kf.update_static(gyro[k])
        xs[k] = kf.x
        ps[k] = np.asarray(kf.P).reshape(9)
    return xs, ps, used


def test_gyro_bias_kf_on_drive_0708(libs: dict[str, Path], drive: Any, stream: dict[str, Any]) -> None:
    """The drive's raw 100 Hz gyroscope (its first 40 s: a stop and driving) with block 3's
    static decisions (Python), a tight rate guard (some static samples refused): float64 bias and
    covariance equal to Python to the bit; float32 within 2e-7 rad/s of the bias (a few float32
    ulps of the 0.01 rad/s noise level the update averages) and P within one float32 rounding
    per sample, relative (the predict's q_b dt added to P at every sample)."""
    from iotnav.techniques.gyro_bias_kf import GyroBiasConfig, GyroBiasKF

    log = drive
    t0 = stream["t0"]
    imu = log.imu[(log.imu.t >= t0) & (log.imu.t < t0 + 40.0)].reset_index(drop=True)
    t = imu.t.to_numpy(float)
    gyro = imu[["gyro_x", "gyro_y", "gyro_z"]].to_numpy(float)
    dt = np.diff(t, prepend=t[0])
    n = len(t)
    assert np.array_equal(t, stream["t_imu"][:n])
    static = _static_decisions(stream, n)
    assert 0.05 < static.mean() < 0.95
    cfg = GyroBiasConfig(max_rate_rad_s=float(np.quantile(np.abs(gyro[static]).max(axis=1), 0.9)))
    b0 = np.array([0.003, -0.002, 0.001])
    xp, pp, up = _bias_run(GyroBiasKF(cfg, b0), dt, gyro, static)
    assert 0 < np.count_nonzero(static & ~up)  # the guard refuses some static samples
    x64, p64, u64 = _bias_run(fk3.GyroBiasBlock(libs["f64"], cfg, b0, double=True), dt, gyro, static)
    assert np.array_equal(u64, up) and np.array_equal(x64, xp) and np.array_equal(p64, pp)
    x32, p32, u32 = _bias_run(fk3.GyroBiasBlock(libs["f32"], cfg, b0), dt, gyro, static)
    assert np.array_equal(u32, up)
    assert np.abs(x32 - xp).max() < 2e-7, np.abs(x32 - xp).max()
    # P: one float32 rounding per predict (q_b dt added to P), accumulated over the samples
    assert np.allclose(p32, pp, rtol=n * float(np.finfo(np.float32).eps), atol=0.0)
    # a correlated covariance (as after a correlated start; the cascade's stays diagonal): every
    # term of the update matters, float64 still bit-equal
    m = np.array([[1.0, 0.0, 0.0], [0.6, 0.8, 0.0], [-0.3, 0.4, 0.7]]) * 0.05
    P0 = m @ m.T
    kfs = [GyroBiasKF(cfg, b0), fk3.GyroBiasBlock(libs["f64"], cfg, b0, double=True)]
    for kf in kfs:
        kf.P = P0
    (xq, pq, uq), (xd, pd, ud) = (_bias_run(kf, dt[:1000], gyro[:1000], static[:1000]) for kf in kfs)
    assert uq.any() and np.abs(pq[:, [1, 2, 5]]).min() > 0.0
    assert np.array_equal(ud, uq) and np.array_equal(xd, xq) and np.array_equal(pd, pq)


def test_sanitized_build_replays_blocks_1_and_2(
    replay_exe: Path,
    libs: dict[str, Path],
    drive: Any,
    fixes: dict[str, np.ndarray],
    stream: dict[str, Any],
) -> None:
    """The float32 blocks 1 and 2 (gyro bias) built with ASan + UBSan (host/replay_pipeline.c)
    replay the drive's damaged fixes (a stored position 0.6 km off: "moved while off") and its
    first 40 s of gyroscope with no sanitizer report and the ctypes run's exact values."""
    from iotnav.firmware.host import replay_sanitized
    from iotnav.techniques.gyro_bias_kf import GyroBiasConfig

    stored = (float(np.nanmean(fixes["lat"])) + 0.005, float(np.nanmean(fixes["lon"])))
    rec = [
        fp.replay_fix(float(t), bool(v), float(la), float(lo), float(p), int(ns))
        for t, v, la, lo, p, ns in zip(
            fixes["t"],
            fixes["valid"],
            fixes["lat"],
            fixes["lon"],
            fixes["pdop"],
            fixes["num_sv"],
            strict=True,
        )
    ]
    boot = fp.LastPositionBlock(libs["f32"], stored=stored)
    c = _boot(boot, fixes)
    assert c["event"][0] is not None
    log = drive
    t = stream["t_imu"][stream["t_imu"] < stream["t0"] + 40.0]
    gyro = log.imu[["gyro_x", "gyro_y", "gyro_z"]].to_numpy(float)[
        np.searchsorted(log.imu.t.to_numpy(float), t)
    ]
    dt = np.diff(t, prepend=t[0]).astype(np.float32)  # what the replay program reads
    static = _static_decisions(stream, len(t))
    assert static.any() and not static.all()
    gc, b0 = GyroBiasConfig(max_rate_rad_s=0.05), (0.003, -0.002, 0.001)
    rec += [fp.replay_gyro(float(dt[k]), gyro[k], bool(static[k])) for k in range(len(t))]
    xc, pc, uc = _bias_run(fk3.GyroBiasBlock(libs["f32"], gc, np.array(b0)), dt, gyro, static)
    cfg = fp.replay_config(StaticConfig(), Lowpass3Config(), stored=stored, gyro_bias=gc, b0=b0)
    out = replay_sanitized(replay_exe, cfg + b"".join(rec))
    n_f = len(fixes["t"])
    got = np.frombuffer(out[: 16 * n_f], dtype="<i4").reshape(n_f, 4)
    reasons = [fp.FIX_REASONS[r] for r in got[:, 0]]
    assert reasons == c["reason"]
    ok = got[:, 0] == 0
    assert got[ok, 3].astype(bool).tolist() == c["due"]
    first = np.flatnonzero(got[:, 1])
    assert first.tolist() == [reasons.index(None)] and got[first[0], 1] == 3
    d = got[first[0], 2:3].view("<f4")[0]
    assert d == np.float32(c["event"][0]["distance_m"])
    g = np.frombuffer(out[16 * n_f :], dtype="<f4").reshape(len(t), 13)
    assert g[:, 0].view("<i4").astype(bool).tolist() == uc.tolist() and uc.any()
    assert np.array_equal(g[:, 1:4], xc) and np.array_equal(g[:, 4:], pc)


# ---------------------------------------------------------------------------------------------
# Block 2's tilt KF (iotnav.techniques.tilt_kf, firmware/pipeline_tilt.c)


def _tilt_run(kf: Any, s: dict[str, np.ndarray]) -> tuple[np.ndarray, ...]:
    """The cascade's use: predict with the bias-corrected rate and the bias variance, then the
    accelerometer update; x, P, NIS, used per sample."""
    n = len(s["dt"])
    xs, ps, nis, used = np.empty((n, 3)), np.empty((n, 9)), np.empty(n), np.zeros(n, bool)
    for k in range(n):
        kf.predict(s["omega"][k], float(s["dt"][k]), float(s["bias_var"][k]))
        used[k] = kf.update(s["f"][k], 9.80665, float(s["a_veh"][k]))
        xs[k], ps[k], nis[k] = kf.x, np.asarray(kf.P).reshape(9), kf.last_nis
    return xs, ps, nis, used


def test_tilt_kf_on_drive_0708(
    replay_exe: Path, libs: dict[str, Path], drive: Any, stream: dict[str, Any]
) -> None:
    """The drive's raw 100 Hz IMU (its first 10 s), the rate corrected with
    the Python gyro-bias KF as the cascade does (its variance into the prediction), a vehicle
    acceleration crossing the dead band (seeded, |N(0, 0.4)| m/s^2) and a tight rejection (some
    samples refused): float64 down axis, covariance and NIS equal to Python to the bit; float32
    within 1e-5 of the unit vector; and the sanitized replay of the float32 build."""
    from iotnav.techniques.gyro_bias_kf import GyroBiasKF
    from iotnav.techniques.tilt_kf import TiltConfig, TiltKF

    imu = drive.imu
    t = stream["t_imu"][stream["t_imu"] < stream["t0"] + 10.0]
    idx = np.searchsorted(imu.t.to_numpy(float), t)
    gyro = imu[["gyro_x", "gyro_y", "gyro_z"]].to_numpy(float)[idx]
    f = imu[["acc_x", "acc_y", "acc_z"]].to_numpy(float)[idx]
    dt = np.diff(t, prepend=t[0])
    static = _static_decisions(stream, len(t))
    bias, omega, bias_var = GyroBiasKF(), np.empty_like(gyro), np.empty(len(t))
    for k in range(len(t)):
        bias.predict(float(dt[k]))
        if static[k]:
            bias.update_static(gyro[k])
        omega[k] = gyro[k] - bias.x
        bias_var[k] = float(np.trace(bias.P)) / 3.0
    a_veh = np.abs(np.random.default_rng(5).normal(0.0, 0.4, len(t)))
    s = {"dt": dt, "omega": omega, "bias_var": bias_var, "f": f, "a_veh": a_veh}
    dev = np.abs(np.linalg.norm(f, axis=1) - 9.80665)
    # the threshold midway between two samples' deviations near the 95th percentile (float32
    # round-off must not move a sample across it)
    srt = np.sort(dev)
    i = int(0.95 * len(srt))
    cfg = TiltConfig(reject_mps2=float(0.5 * (srt[i] + srt[i + 1])))
    xp, pp, np_, up = _tilt_run(TiltKF(cfg), s)
    assert 0 < np.count_nonzero(~up) < len(t) // 5 and np.abs(pp[:, [1, 2, 5]]).max() > 0.0
    x64, p64, n64, u64 = _tilt_run(fk3.TiltBlock(libs["f64"], cfg, double=True), s)
    assert np.array_equal(u64, up) and np.array_equal(x64, xp) and np.array_equal(p64, pp)
    assert np.array_equal(n64, np_, equal_nan=True)
    x32, p32, n32, u32 = _tilt_run(fk3.TiltBlock(libs["f32"], cfg), s)
    assert np.array_equal(u32, up)
    assert np.abs(x32 - xp).max() < 1e-5, np.abs(x32 - xp).max()
    # the float32 tilt KF built with ASan + UBSan (host/replay_pipeline.c, records T): no report,
    # the ctypes float32 values exactly (inputs rounded to float32 as the replay reads them)
    from iotnav.firmware.host import replay_sanitized

    s32 = {k: np.asarray(v, np.float32).astype(float) for k, v in s.items()}
    x32, p32, n32, u32 = _tilt_run(fk3.TiltBlock(libs["f32"], cfg), s32)
    rec = b"".join(
        fp.replay_tilt(
            s32["dt"][k], s32["omega"][k], s32["bias_var"][k], s32["f"][k], 9.80665, s32["a_veh"][k]
        )
        for k in range(len(t))
    )
    cfg_bytes = fp.replay_config(StaticConfig(), Lowpass3Config(), tilt=cfg)
    out = replay_sanitized(replay_exe, cfg_bytes + rec)
    got = np.frombuffer(out, dtype="<f4").reshape(len(t), 14)
    assert got[:, 0].view("<i4").astype(bool).tolist() == u32.tolist()
    assert np.array_equal(got[:, 1:4], x32) and np.array_equal(got[:, 4:13], p32)
    assert np.array_equal(got[:, 13], n32, equal_nan=True)


# ---------------------------------------------------------------------------------------------
# Block 2's yaw KF (iotnav.techniques.yaw_kf, firmware/pipeline_yaw.c)


@pytest.fixture(scope="module")
def yaw_inputs(drive: Any, stream: dict[str, Any]) -> dict[str, np.ndarray]:
    """The drive's first 60 s of raw 100 Hz IMU through the Python gyro-bias and tilt KFs as the
    cascade runs them: per sample the corrected rate, the bias variance and the tilt ``x3``; the
    GNSS epochs' courses (valid, above the yaw filter's minimum speed) at their IMU sample."""
    from iotnav.techniques.gyro_bias_kf import GyroBiasKF
    from iotnav.techniques.tilt_kf import TiltKF

    imu = drive.imu
    t = stream["t_imu"][stream["t_imu"] < stream["t0"] + 60.0]
    idx = np.searchsorted(imu.t.to_numpy(float), t)
    gyro = imu[["gyro_x", "gyro_y", "gyro_z"]].to_numpy(float)[idx]
    f = imu[["acc_x", "acc_y", "acc_z"]].to_numpy(float)[idx]
    dt = np.diff(t, prepend=t[0])
    static = _static_decisions(stream, len(t))
    bias, tilt = GyroBiasKF(), TiltKF()
    omega, bias_var, x3 = np.empty_like(gyro), np.empty(len(t)), np.empty_like(gyro)
    for k in range(len(t)):
        bias.predict(float(dt[k]))
        if static[k]:
            bias.update_static(gyro[k])
        omega[k] = gyro[k] - bias.x
        bias_var[k] = float(np.trace(bias.P)) / 3.0
        tilt.predict(omega[k], float(dt[k]), float(bias_var[k]))
        tilt.update(f[k], 9.80665)
        x3[k] = tilt.x
    g = drive.gnss
    ok = g.valid.astype(bool) & g.course_valid.astype(bool) & (g.speed_mps > 2.0)
    g = g[ok & (g.t >= t[0]) & (g.t < t[-1])]
    course = np.full(len(t), np.nan)
    course[np.searchsorted(t, g.t.to_numpy(float))] = g.course_rad.to_numpy(float)
    return {"dt": dt, "omega": omega, "bias_var": bias_var, "x3": x3, "course": course}


def _yaw_run(kf: Any, s: dict[str, np.ndarray], mount: float, m_b: np.ndarray | None = None) -> tuple:
    """The cascade's use of the yaw KF: predict every sample, the course + mount angle aid at the
    GNSS epochs (or the magnetometer ``m_b`` at every tenth sample); x, P, NIS, aid result and
    ``C_nb`` (``pl_dcm_rows`` / ``dcm_from_rows`` with the tilt) per sample."""
    from iotnav.techniques.yaw_kf import dcm_from_rows

    n = len(s["dt"])
    xs, ps, nis, used, C = np.empty((n, 3)), np.empty((n, 9)), np.empty(n), np.zeros(n, int), np.empty((n, 9))
    for k in range(n):
        kf.predict(s["omega"][k], float(s["dt"][k]), float(s["bias_var"][k]))
        if m_b is not None:
            if k % 10 == 0:
                used[k] = 1 + kf.update_mag(m_b[k], s["x3"][k])
        elif math.isfinite(s["course"][k]):
            used[k] = 1 + kf.update_heading(float(s["course"][k]) + mount, s["x3"][k])
        xs[k], ps[k], nis[k] = kf.x, np.asarray(kf.P).reshape(9), kf.last_nis
        C[k] = (kf.dcm(s["x3"][k]) if hasattr(kf, "dcm") else dcm_from_rows(kf.x, s["x3"][k])).reshape(9)
    return xs, ps, nis, used, C


#: float64 yaw KF against Python: numpy's arcsin and arctan2 (its own SIMD code in numpy 2) are
#: not glibc's asin and atan2 (they differ in the last bit for ~8 % of arguments), and the
#: magnetometer path's dot product is numpy's (BLAS); everything else is the same operations.
YAW_F64_TOL = 1e-9


def test_yaw_kf_on_drive_0708(libs: dict[str, Path], yaw_inputs: dict[str, np.ndarray]) -> None:
    """The drive's first 60 s (the Python bias and tilt KFs' outputs as inputs), the GPS course
    as the heading aid with a NIS gate that refuses some epochs: float64 North axis, covariance,
    NIS and C_nb within 1e-9 of Python (:data:`YAW_F64_TOL`; measured 2.2e-16, NIS 3.6e-14), the
    same epochs accepted; float32 within 2e-5 of the unit vector (10 x the 2.0e-6 measured: the
    float32 round-off of 6 000 predictions and 69 updates) and the same decisions."""
    from iotnav.techniques.yaw_kf import YawKF

    s = yaw_inputs
    n_aid = int(np.isfinite(s["course"]).sum())
    assert n_aid >= 50
    mount = 0.0
    cfg = _yaw_gated_config(s)
    xp, pp, np_, up, cp = _yaw_run(YawKF(cfg), s, mount)
    assert 2 <= np.count_nonzero(up == 1) < 10 and np.count_nonzero(up == 2) >= 50, np.bincount(up)
    blk = fk3.YawBlock(libs["f64"], cfg, double=True)
    assert blk.init_rc == 0
    x64, p64, n64, u64, c64 = _yaw_run(blk, s, mount)
    assert np.array_equal(u64, up)
    for a, b in ((x64, xp), (p64, pp), (n64, np_), (c64, cp)):
        assert np.allclose(a, b, rtol=YAW_F64_TOL, atol=YAW_F64_TOL, equal_nan=True), np.nanmax(np.abs(a - b))
    x32, _, _, u32, c32 = _yaw_run(fk3.YawBlock(libs["f32"], cfg), s, mount)
    assert np.array_equal(u32, up)
    assert np.abs(x32 - xp).max() < 2e-5 and np.abs(c32 - cp).max() < 2e-5, np.abs(x32 - xp).max()


def _yaw_gated_config(s: dict[str, np.ndarray]) -> Any:
    """A yaw configuration whose NIS gate lies midway between two epochs' NIS near the 95th
    percentile of the ungated run (float32 round-off must not move an epoch across it)."""
    from scipy.special import gammainc

    from iotnav.techniques.yaw_kf import YawConfig, YawKF

    _, _, nis0, u0, _ = _yaw_run(YawKF(), s, 0.0)
    srt = np.sort(nis0[u0 == 2][1:])
    i = int(0.95 * len(srt))
    return YawConfig(gate_probability=float(gammainc(1.5, 0.25 * (srt[i] + srt[i + 1]))))


def test_yaw_kf_magnetometer(libs: dict[str, Path], yaw_inputs: dict[str, np.ndarray]) -> None:
    """Magnetometer aiding (drive_0708 has no magnetometer): the field of Turin (47 uT, 62 deg
    inclination, 3 deg declination) seen through the Python course-aided attitude of the drive's
    first 20 s with seeded 0.5 uT noise, every tenth sample: float64 within 1e-9 of Python (its
    dot products are numpy's; measured bit-equal here), float32 within 2e-5 (measured 2.9e-7); a
    zero field is refused by both."""
    from iotnav.techniques.yaw_kf import YawConfig, YawKF

    n = 2000
    s = {k: v[:n] for k, v in yaw_inputs.items()}
    C = _yaw_run(YawKF(), s, 0.0)[4].reshape(n, 3, 3)
    inc, dec = math.radians(62.0), math.radians(3.0)
    m_n = 47.0 * np.array([math.cos(inc) * math.cos(dec), math.cos(inc) * math.sin(dec), math.sin(inc)])
    m_b = np.einsum("kji,j->ki", C, m_n) + np.random.default_rng(11).normal(0.0, 0.5, (n, 3))
    m_b[500] = 0.0
    cfg = YawConfig(declination_rad=dec, mag_noise=0.05)
    xp, pp, np_, up, cp = _yaw_run(YawKF(cfg), s, 0.0, m_b)
    assert up[500] == 1 and np.count_nonzero(up == 2) == n // 10 - 1
    x64, p64, n64, u64, c64 = _yaw_run(fk3.YawBlock(libs["f64"], cfg, double=True), s, 0.0, m_b)
    assert np.array_equal(u64, up)
    for a, b in ((x64, xp), (p64, pp), (n64, np_), (c64, cp)):
        assert np.allclose(a, b, rtol=YAW_F64_TOL, atol=YAW_F64_TOL, equal_nan=True), np.nanmax(np.abs(a - b))
    x32, _, _, u32, c32 = _yaw_run(fk3.YawBlock(libs["f32"], cfg), s, 0.0, m_b)
    assert np.array_equal(u32, up)
    assert np.abs(x32 - xp).max() < 2e-5 and np.abs(c32 - cp).max() < 2e-5, np.abs(x32 - xp).max()


def test_yaw_kf_sanitized_replay(
    replay_exe: Path, libs: dict[str, Path], yaw_inputs: dict[str, np.ndarray]
) -> None:
    """The float32 yaw KF built with ASan + UBSan (host/replay_pipeline.c, records Y) on the gated
    course-aided run of the drive's first 48 s: no report, the ctypes float32 values exactly."""
    from iotnav.firmware.host import replay_sanitized

    s32 = {k: np.asarray(v, np.float32).astype(float) for k, v in yaw_inputs.items()}
    cfg = _yaw_gated_config(s32)
    s32 = {k: v[:4800] for k, v in s32.items()}  # 48 s: two gated epochs (at 40 and 47 s)
    x32, p32, n32, u32, c32 = _yaw_run(fk3.YawBlock(libs["f32"], cfg), s32, 0.0)
    assert np.count_nonzero(u32 == 1) >= 1
    rec = b"".join(
        fp.replay_yaw(
            s32["dt"][k],
            s32["omega"][k],
            s32["bias_var"][k],
            s32["x3"][k],
            1 if math.isfinite(s32["course"][k]) else 0,
            (float(s32["course"][k]), math.nan, math.nan),
        )
        for k in range(len(s32["dt"]))
    )
    cfg_bytes = fp.replay_config(StaticConfig(), Lowpass3Config(), yaw=cfg)
    out = replay_sanitized(replay_exe, cfg_bytes + rec)
    got = np.frombuffer(out, dtype="<f4").reshape(len(s32["dt"]), 23)
    assert got[:, 0].view("<i4").tolist() == u32.tolist()
    assert np.array_equal(got[:, 1:4], x32) and np.array_equal(got[:, 4:13], p32)
    assert np.array_equal(got[:, 13], n32, equal_nan=True) and np.array_equal(got[:, 14:], c32)


# ---------------------------------------------------------------------------------------------
# Block 2's cascade (iotnav.techniques.cascade, firmware/pipeline_cascade.c)


def _cascade_run(kf: Any, s: dict[str, np.ndarray]) -> tuple[np.ndarray, ...]:
    """CascadeKF's use by the engines: a step per IMU sample, the course aid at the GNSS epochs,
    the heading rotated once (a mount estimate changing) at sample 3000; C_nb, omega_b, the
    filters' x and P, the aid results per sample."""
    n = len(s["dt"])
    C, om, fs, used = np.empty((n, 9)), np.empty((n, 3)), np.empty((n, 36)), np.zeros(n, int)
    for k in range(n):
        kf.step(
            s["f"][k], s["gyro"][k], float(s["dt"][k]), bool(s["static"][k]), 9.80665, float(s["a_veh"][k])
        )
        if math.isfinite(s["course"][k]):
            used[k] = 1 + kf.aid_heading(float(s["course"][k]))
        if k == 3000:
            kf.rotate_heading(0.05)
        C[k], om[k] = np.asarray(kf.C_nb).reshape(9), kf.omega_b
        if hasattr(kf, "filter_states"):
            fs[k] = kf.filter_states()
        else:
            fs[k] = np.concatenate([np.r_[f.x, np.asarray(f.P).ravel()] for f in (kf.bias, kf.tilt, kf.yaw)])
    return C, om, fs, used


def test_cascade_on_drive_0708(
    libs: dict[str, Path], drive: Any, stream: dict[str, Any], yaw_inputs: dict[str, np.ndarray]
) -> None:
    """Block 2 wired in C (pl_cascade_step, the course aid, a heading rotation) on the drive's
    first 60 s of raw 100 Hz IMU with block 3's decisions, a seeded vehicle acceleration and the
    GPS course with a NIS gate, beside CascadeKF: float64 C_nb, rate and the three filters' states
    within 1e-9 (:data:`YAW_F64_TOL`: numpy's arcsin / arctan2), the same aid decisions; float32
    C_nb within 2e-5."""
    from iotnav.techniques.cascade import CascadeConfig, CascadeKF

    imu = drive.imu
    n = len(yaw_inputs["dt"])
    t = stream["t_imu"][:n]
    idx = np.searchsorted(imu.t.to_numpy(float), t)
    s = {
        "dt": np.diff(t, prepend=t[0]),
        "gyro": imu[["gyro_x", "gyro_y", "gyro_z"]].to_numpy(float)[idx],
        "f": imu[["acc_x", "acc_y", "acc_z"]].to_numpy(float)[idx],
        "static": _static_decisions(stream, n),
        "a_veh": np.abs(np.random.default_rng(5).normal(0.0, 0.4, n)),
        "course": yaw_inputs["course"],
    }
    cfg = CascadeConfig(yaw=_yaw_gated_config(yaw_inputs))
    cp, op, fp_, up = _cascade_run(CascadeKF(cfg), s)
    assert np.count_nonzero(up == 1) >= 1 and np.count_nonzero(up == 2) >= 50, np.bincount(up)
    blk = fk3.CascadeBlock(libs["f64"], cfg, double=True)
    assert blk.init_rc == 0
    c64, o64, f64, u64 = _cascade_run(blk, s)
    assert np.array_equal(u64, up)
    for a, b in ((c64, cp), (o64, op), (f64, fp_)):
        assert np.allclose(a, b, rtol=YAW_F64_TOL, atol=YAW_F64_TOL), np.abs(a - b).max()
    c32, _, _, u32 = _cascade_run(fk3.CascadeBlock(libs["f32"], cfg), s)
    assert np.array_equal(u32, up)
    assert np.abs(c32 - cp).max() < 2e-5, np.abs(c32 - cp).max()


class _PyFrontEnd:
    """:func:`~iotnav.techniques.cascade.front_end_step` on a CascadeKF and a StaticDetector,
    with the C binding's call signature."""

    def __init__(self, cfg: Any) -> None:
        from iotnav.techniques.cascade import CascadeKF

        self.kf, self.det = CascadeKF(cfg), StaticDetector()

    def step(self, t: float, a: np.ndarray, w: np.ndarray, *rest: Any) -> tuple[float, float, float, bool]:
        from iotnav.techniques.cascade import front_end, front_end_step

        dt, static, g, a_long, v_gnss, t_speed, v_dr = rest
        return front_end_step(
            front_end(self.kf, self.det),
            t,
            *map(float, a),
            *map(float, w),
            float(dt),
            bool(static),
            g,
            a_long,
            v_gnss,
            t_speed,
            v_dr,
        )


def test_front_end_on_drive_0708(
    replay_exe: Path,
    libs: dict[str, Path],
    drive: Any,
    stream: dict[str, Any],
    yaw_inputs: dict[str, np.ndarray],
) -> None:
    """Blocks 2 and 3 as the pipeline runs them per IMU sample (pl_front_end_step: the vehicle
    acceleration from the GNSS speed rate and the yaw rate, the filter's speed while the GNSS
    speed is stale, block 3 on C_nb f_b) on 30 s of the drive (a stop, the start, a turn) with a
    6 s GNSS gap in the turn (the caller's v_dr: twice the last GNSS speed, as a drifting dead
    reckoning; checked to change the result) and the course aid, beside front_end_step: float64 y_n
    and C_nb within 1e-9 (measured bit-equal), every static decision the same, in
    float32 too (C_nb within 2e-5, y_n within 2e-5 |f_b|)."""
    from iotnav.techniques.cascade import CascadeConfig

    k0, k1 = 3000, len(yaw_inputs["dt"])  # 30 to 60 s: a stop, the start, a turn
    n = k1 - k0
    imu = drive.imu
    t = stream["t_imu"][k0:k1]
    idx = np.searchsorted(imu.t.to_numpy(float), t)
    gyro = imu[["gyro_x", "gyro_y", "gyro_z"]].to_numpy(float)[idx]
    f = imu[["acc_x", "acc_y", "acc_z"]].to_numpy(float)[idx]
    dt = np.diff(t, prepend=t[0])
    t_g, speed = stream["t_gnss"], stream["speed"]
    gap = (t_g > stream["t0"] + 50.0) & (t_g < stream["t0"] + 56.0)  # in the turn
    course_at = yaw_inputs["course"][k0:k1]
    cfg = CascadeConfig(yaw=_yaw_gated_config(yaw_inputs))

    def run(fe: Any, det: Any, kf: Any, dr_gain: float = 2.0) -> tuple[np.ndarray, ...]:
        ys, C, st, courses = np.empty((n, 3)), np.empty((n, 9)), np.zeros(n, bool), np.full(n, np.nan)
        j, was, t_speed, v_gnss, a_long, v_dr = 0, False, math.nan, 0.0, 0.0, math.nan
        for k in range(n):
            course = math.nan
            while j < len(t_g) and t_g[j] <= t[k]:
                if not gap[j] and math.isfinite(speed[j]):
                    if math.isfinite(t_speed):
                        a_long = (speed[j] - v_gnss) / (t_g[j] - t_speed)
                    det.update_speed(float(t_g[j]), float(speed[j]))
                    t_speed, v_gnss, v_dr = float(t_g[j]), float(speed[j]), float(speed[j])
                    course = course_at[k]
                elif gap[j]:
                    v_dr = dr_gain * v_gnss  # the caller's dead-reckoned speed, drifting in the gap
                j += 1
            *y, was = fe(
                float(t[k]), f[k], gyro[k], float(dt[k]), was, 9.80665, a_long, v_gnss, t_speed, v_dr
            )
            if math.isfinite(course):
                kf.aid_heading(float(course))
                courses[k] = course
            ys[k], C[k], st[k] = y, np.asarray(kf.C_nb).reshape(9), was
        return ys, C, st, courses

    py = _PyFrontEnd(cfg)
    yp, cp, sp, _ = run(py.step, py.det, py.kf)
    assert 0.05 < sp.mean() < 0.95
    other = _PyFrontEnd(cfg)
    assert np.abs(run(other.step, other.det, other.kf, 1.0)[0] - yp).max() > 1e-6  # v_dr matters
    for lib, double in ((libs["f64"], True), (libs["f32"], False)):
        kf, det = fk3.CascadeBlock(lib, cfg, double=double), fp.StaticBlock(lib, double=double)

        calls: list[tuple] = []

        def fe(
            t: float, *a: Any, kf: Any = kf, det: Any = det, calls: list = calls
        ) -> tuple[float, float, float, bool]:
            calls.append((t, *a))
            return kf.front_end_step(det, t, *a)

        yc, cc, sc, courses = run(fe, det, kf)
        assert np.array_equal(sc, sp), double
        # float32: C_nb within 2e-5, so y_n = C_nb f_b within 2e-5 |f_b|
        tol = YAW_F64_TOL if double else 2e-5 * float(np.linalg.norm(f, axis=1).max())
        assert np.abs(yc - yp).max() < tol and np.abs(cc - cp).max() < (tol if double else 2e-5), (
            double,
            np.abs(yc - yp).max(),
            np.abs(cc - cp).max(),
        )
    # the float32 run (the last) built with ASan + UBSan (host/replay_pipeline.c, records K): no
    # report, the ctypes values exactly
    from iotnav.firmware.host import replay_sanitized

    rec = b"".join(fp.replay_front_end(*c, float(courses[k])) for k, c in enumerate(calls))
    out = replay_sanitized(replay_exe, fp.replay_config(StaticConfig(), Lowpass3Config(), yaw=cfg.yaw) + rec)
    got = np.frombuffer(out, dtype="<f4").reshape(n, 13)
    assert got[:, 0].view("<i4").astype(bool).tolist() == sc.tolist()
    assert np.array_equal(got[:, 1:4], yc) and np.array_equal(got[:, 4:], cc)
