"""The Forno pipeline wired as one C99 engine (firmware/pipeline.c) beside the Python pipeline (issue 20).

The engine is built for the host with ``gcc -std=c99 -Wall -Wextra -Werror -pedantic`` (float32,
float64, and float32 with AddressSanitizer + UndefinedBehaviorSanitizer) as its replay program
(``firmware/host/replay_pipeline_wired.c``), fed the samples
:func:`~iotnav.engines.base.iter_samples` gives :func:`~iotnav.engines.base.run_batch`, and its
rows and events compared with :class:`~iotnav.engines.pipeline.Pipeline`'s: the real drive_0708
(300 s: static periods, 4 Hz RTK with NED velocity, mount estimates, re-anchored planes), the
simulator's car-tunnel (GNSS outages) and scooter laps (mount 88 deg, a stored position).
"""

from __future__ import annotations

import ctypes
import math
from pathlib import Path
from typing import Any, cast

import numpy as np
import pytest

from conftest import datasets_dir
from iotnav import sim
from iotnav.engines.base import SOURCES, GnssSample, ImuSample, MagSample, iter_samples, run_batch
from iotnav.engines.config import PipelineConfig
from iotnav.engines.pipeline import Pipeline
from iotnav.firmware import pipeline_engine as pe
from iotnav.io.log import Log
from iotnav.techniques.fusion_kf import FusionConfig
from iotnav.techniques.last_position import LastPositionStore, StoredPosition
from iotnav.techniques.mount import MountConfig

DRIVE = datasets_dir() / "rtklibexplorer_gnss_imu" / "drive_0708"
REPO = Path(__file__).resolve().parents[1]
#: Python events the C engine raises as PL_EV_* flags (the others: boot, input_skipped)
COMPARED = ("fix_rejected", "moved_while_off", "first_fix", "vertical_reset", "mount_estimate")
COMPARED += ("static_start", "static_end", "boot_movement_before_fix")


class _Saves:
    """A store that keeps what the pipeline saves (LastPositionStore's interface)."""

    def __init__(self) -> None:
        self.saved: list[StoredPosition] = []

    def load(self) -> StoredPosition | None:
        return None

    def save(self, p: StoredPosition) -> None:
        self.saved.append(p)


@pytest.fixture(scope="module")
def exes(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    d = tmp_path_factory.mktemp("fwpl")
    return {
        "f32": pe.build(d / "replay_f32", replay=True),
        "f64": pe.build(d / "replay_f64", double=True, replay=True),
    }


@pytest.fixture(scope="module")
def drive_log() -> Log:
    """The first 300 s of drive_0708 as iotnav ingests it (RTK 4 Hz with NED velocity, 100 Hz IMU)."""
    from iotnav.cli.outages import load_dataset

    log, _ = load_dataset(DRIVE)  # fails (not skips) when the dataset is missing
    t0 = float(log.gnss.t.iloc[0])
    return Log(
        gnss=log.gnss[log.gnss.t < t0 + 300.0].reset_index(drop=True),
        imu=log.imu[log.imu.t < t0 + 300.0].reset_index(drop=True),
    )


@pytest.fixture(scope="module")
def degraded_log() -> Log:
    """The first 120 s of drive_0708 as a tracker would see it: its RTK degraded to 1 Hz
    tracker-grade fixes (the outage study's feed), no fix over 40-60 s (a 20 s outage)."""
    from iotnav.cli.outages import load_dataset
    from iotnav.eval import outages as O

    log, prof = load_dataset(DRIVE)  # fails (not skips) when the dataset is missing
    truth = O.rtk_truth(log.gnss).sort_values("t").reset_index(drop=True)
    truth = truth[truth.t < float(truth.t.iloc[0]) + 120.0].reset_index(drop=True)
    fed, _ = O.degraded_feed(log, truth, prof, O.OutageConfig(seed=3))
    t0 = float(truth.t.iloc[0])
    return Log(gnss=O.mask_windows(fed.gnss, [(t0 + 40.0, 20.0)]), imu=fed.imu)


@pytest.fixture(scope="module")
def tunnel_log() -> Log:
    """60 s of the simulator's car in tunnels, a few fixes made invalid or with a high PDOP."""
    r = sim.build("car-tunnel", seed=1, overrides={"duration_s": 60.0})
    g = r.gnss.copy()
    g.loc[10:12, "valid"] = False
    g.loc[20:21, "pdop"] = 25.0
    return Log(gnss=g, imu=r.imu)


@pytest.fixture(scope="module")
def laps_log() -> Log:
    """Two simulated scooter laps (mount 88 deg), the receiver's first fix 5 s after the IMU's start."""
    r = sim.build("scooter-laps", seed=1, overrides={"motion.laps": 2, "mount_yaw_rad": math.radians(88.0)})
    g = r.gnss[r.gnss.t >= float(r.imu.t.iloc[0]) + 5.0].reset_index(drop=True)
    return Log(gnss=g, imu=r.imu)


_PY: dict[tuple[int, bool], dict[str, Any]] = {}


def _run(
    log: Log, exe: Path, double: bool, cfg: PipelineConfig, stored: StoredPosition | None = None
) -> dict[str, Any]:
    """The Python pipeline (run once per log and boot, kept) and the C replay of the same samples."""
    key = (id(log), stored is not None)
    if key not in _PY:
        saves = _Saves()
        eng = Pipeline(cfg, stored=stored, store=cast(LastPositionStore, saves))
        df = run_batch(eng, log)
        _PY[key] = {
            "df": df,
            "events": eng.events,
            "saves": saves.saved,
            "samples": list(iter_samples(log)),
            "engine": eng,
        }
    py = _PY[key]
    res = pe.replay(exe, pe.replay_input(cfg, py["samples"], double=double, stored=stored), double=double)
    assert res["rc"] == pe.PL_OK
    return {**py, "c": res}


def _c_events(run: dict[str, Any]) -> list[tuple[float, str]]:
    """(t, type) of the C engine's events, from the flags of each record and the record's time."""
    out = []
    i_imu = i_gnss = 0
    for s, kind in zip(run["samples"], run["c"]["order"], strict=True):
        if kind == "I":
            flags = run["c"]["imu"][i_imu][0]
            i_imu += 1
        elif kind == "G":
            flags = run["c"]["gnss"][i_gnss][0]
            i_gnss += 1
        else:
            continue
        out += [(float(s.t), n) for n in COMPARED if flags & pe.EV[n]]
    return sorted(out)


def _check(
    run: dict[str, Any], pos_rms: float, pos_max: float, att_deg: float, other: float
) -> dict[str, float]:
    """Same rows (source, static, position known), same events and values; the differences."""
    df, c = run["df"], run["c"]
    rows = [o for _, o in c["imu"]]
    assert len(rows) == len(df)
    assert [SOURCES[o.source] for o in rows] == df.source.tolist()
    assert [bool(o.is_static) for o in rows] == df.static.astype(bool).tolist()
    py_ev = sorted((float(e["t"]), e["type"]) for e in run["events"] if e["type"] in COMPARED)
    assert _c_events(run) == py_ev
    # event values: rejections' reasons, mount estimates, "moved while off"
    g_ev = [
        g
        for g in c["gnss"]
        if g[0] & (pe.EV["fix_rejected"] | pe.EV["mount_estimate"] | pe.EV["moved_while_off"])
    ]
    py_rej = [e for e in run["events"] if e["type"] == "fix_rejected"]
    assert [pe.FIX_REASONS[g[1]] for g in g_ev if g[0] & pe.EV["fix_rejected"]] == [
        e["reason"] for e in py_rej
    ]
    py_mount = [e for e in run["events"] if e["type"] == "mount_estimate"]
    c_mount = [g[5] for g in g_ev if g[0] & pe.EV["mount_estimate"]]
    for a, b in zip(py_mount, c_mount, strict=True):
        assert (bool(b.accepted), bool(b.applied), bool(b.settled)) == (
            a["accepted"],
            a["applied"],
            a["settled"],
        )
        assert abs(pe_wrap(b.mount_yaw_rad - a["mount_yaw_rad"])) < math.radians(att_deg)
    py_moved = [e["distance_m"] for e in run["events"] if e["type"] == "moved_while_off"]
    c_moved = [g[3] for g in g_ev if g[0] & pe.EV["moved_while_off"]]
    assert np.allclose(c_moved, py_moved, rtol=1e-6, atol=1.0)  # float32 degrees: 0.85 m at 120 deg
    # saves: the same times, the same positions
    saves = [g[6] for g in c["gnss"] if g[0] & pe.EV["save"]]
    assert [s.t.s + float(s.t.frac) for s in saves] == pytest.approx([p.t for p in run["saves"]], abs=1e-6)
    # the rows
    has = np.array([bool(o.has_position) for o in rows])
    assert (has == np.isfinite(df.north.to_numpy())).all()
    P = df[["north", "east", "down"]].to_numpy()[has]
    C = np.array([list(o.r_n) for o in rows])[has]
    err = np.linalg.norm(C - P, axis=1)
    V = df[["vn", "ve", "vd"]].to_numpy()[has]
    Cv = np.array([list(o.v_n) for o in rows])[has]
    S = df[["std_north", "std_east"]].to_numpy()[has]
    Cs = np.array([[o.std_north, o.std_east] for o in rows])[has]
    A = df[["roll", "pitch", "yaw"]].to_numpy()
    Ca = np.array([[o.roll, o.pitch, o.yaw] for o in rows])
    d_att = np.degrees(np.abs(pe_wrap(Ca - A)))
    ll = np.array(
        [[(o.geo.lat_e7 + o.geo.lat_frac_e7) * 1e-7, (o.geo.lon_e7 + o.geo.lon_frac_e7) * 1e-7] for o in rows]
    )[has]
    ll_py = df[["lat", "lon"]].to_numpy()[has]
    m_per_deg = math.radians(1.0) * 6.371e6
    d_ll = np.hypot(
        (ll[:, 0] - ll_py[:, 0]) * m_per_deg,
        (ll[:, 1] - ll_py[:, 1]) * m_per_deg * np.cos(np.radians(ll_py[:, 0])),
    )
    got = {
        "pos_rms": float(np.sqrt(np.mean(err**2))),
        "pos_max": float(err.max()),
        "vel_max": float(np.abs(Cv - V).max()),
        "std_max": float(np.abs(Cs - S).max()),
        "att_deg": float(d_att.max()),
        "geo_max": float(d_ll.max()),
    }
    assert got["pos_rms"] < pos_rms and got["pos_max"] < pos_max, got
    assert got["att_deg"] < att_deg, got
    assert got["vel_max"] < other and got["std_max"] < other, got
    assert got["geo_max"] < max(pos_max, 2e-8), got  # a float64 degree is 0.8 nm at 40 deg
    return got


def pe_wrap(a: Any) -> Any:
    """Angle difference(s) to (-pi, pi]."""
    return (np.asarray(a) + np.pi) % (2.0 * np.pi) - np.pi


def _anchor_bound(eng: Pipeline) -> float:
    """Python's own rounding of its re-anchored planes: each moves the virtual origin
    (``lat0``, ``lon0``, float64 degrees) by up to half an ulp of each, m."""
    frame = eng.frame
    assert frame is not None
    b = 0.0
    for _n, _e, lat0, lon0, k_n, k_e in frame.anchors[1:]:
        b += 0.5 * (math.ulp(lat0) * k_n + math.ulp(lon0) * k_e)
    return b


def test_generated_header_is_current() -> None:
    assert (REPO / "firmware" / pe.ENGINE_HEADER_NAME).read_text() == pe.engine_config_header()


def test_drive_float64_equals_python(exes: dict[str, Path], drive_log: Log) -> None:
    run = _run(drive_log, exes["f64"], True, PipelineConfig())
    eng = run["engine"]
    assert len(eng.frame.anchors) >= 3  # a drive over 200 m: re-anchored
    assert sum(e["type"] == "mount_estimate" for e in run["events"]) > 50
    assert sum(e["type"] == "static_start" for e in run["events"]) >= 3
    bound = _anchor_bound(eng)
    assert 1e-9 < bound < 1e-8
    got = _check(run, bound, bound, 1e-9, 1e-9)
    # before the first re-anchoring Python's origin is not rounded: 1e-9 m
    rows = run["c"]["imu"]
    df = run["df"]
    first = int(np.searchsorted(df.t.to_numpy(), _first_reanchor_t(run)))
    assert first > 1000
    P = df[["north", "east", "down"]].to_numpy()[:first]
    C = np.array([list(o.r_n) for _, o in rows[:first]])
    ok = np.isfinite(P[:, 0])
    assert np.abs(C[ok] - P[ok]).max() < 1e-9
    assert got["pos_max"] < bound


def _first_reanchor_t(run: dict[str, Any]) -> float:
    """Time of the first fix farther than REANCHOR_DISTANCE_M from the origin (the plane's first move), s."""
    from iotnav.engines.base import GnssSample
    from iotnav.engines.tangent_plane import REANCHOR_DISTANCE_M

    _n, _e, lat0, lon0, k_n, k_e = run["engine"].frame.anchors[0]
    for s in run["samples"]:
        if isinstance(s, GnssSample) and s.valid:
            if math.hypot((s.lat_deg - lat0) * k_n, (s.lon_deg - lon0) * k_e) > REANCHOR_DISTANCE_M:
                return float(s.t)
    raise AssertionError("the run never re-anchored")


def test_drive_float32_within_contract(exes: dict[str, Path], drive_log: Log) -> None:
    run = _run(drive_log, exes["f32"], False, PipelineConfig())
    _check(run, 0.01, 0.05, 0.01, 0.01)


@pytest.mark.parametrize("double", [True, False])
def test_degraded_drive_with_outage_beside_python(
    exes: dict[str, Path], degraded_log: Log, double: bool
) -> None:
    """1 Hz degraded fixes and a 20 s outage on the real drive: dead reckoning through the outage,
    the first fix after it taken at once (``reacquire_after_s``), the same rows and events."""
    run = _run(degraded_log, exes["f64" if double else "f32"], double, PipelineConfig())
    assert (run["df"].source == "dr").sum() > 1000  # the outage is dead-reckoned
    if double:
        b = 1e-9 + _anchor_bound(run["engine"])
        _check(run, b, b, 1e-9, 1e-9)
    else:
        _check(run, 0.01, 0.05, 0.01, 0.01)


@pytest.mark.parametrize("double", [True, False])
def test_tunnel_beside_python(exes: dict[str, Path], tunnel_log: Log, double: bool) -> None:
    run = _run(tunnel_log, exes["f64" if double else "f32"], double, PipelineConfig())
    kinds = {e["type"] for e in run["events"]}
    assert "fix_rejected" in kinds
    assert {e.get("reason") for e in run["events"] if e["type"] == "fix_rejected"} >= {"invalid", "pdop"}
    if double:
        _check(run, 1e-9 + _anchor_bound(run["engine"]), 1e-9 + _anchor_bound(run["engine"]), 1e-9, 1e-9)
    else:
        _check(run, 0.01, 0.05, 0.01, 0.01)


@pytest.mark.parametrize("double", [True, False])
def test_laps_stored_position_beside_python(exes: dict[str, Path], laps_log: Log, double: bool) -> None:
    """Boot from a stored position 80 m away (moved while off, last_position / dr rows before the
    first fix), the mount found and applied on the laps."""
    g = laps_log.gnss
    lat, lon = float(g.lat_deg.iloc[0]), float(g.lon_deg.iloc[0])
    stored = StoredPosition(
        lat + 80.0 / 111_000.0, lon, float(g.height_m.iloc[0]), float(g.t.iloc[0]) - 600.0, math.nan
    )
    run = _run(laps_log, exes["f64" if double else "f32"], double, PipelineConfig(), stored=stored)
    kinds = [e["type"] for e in run["events"]]
    assert "moved_while_off" in kinds
    assert any(e["type"] == "mount_estimate" and e["applied"] for e in run["events"])
    assert "last_position" in set(run["df"].source)
    if double:
        b = 1e-9 + _anchor_bound(run["engine"])
        _check(run, b, b, 1e-9, 1e-9)
    else:
        _check(run, 0.01, 0.05, 0.01, 0.01)


def test_sanitized_replay(tmp_path: Path, tunnel_log: Log, exes: dict[str, Path]) -> None:
    """The float32 engine under ASan + UBSan: no report, the same bytes as the plain build."""
    exe = pe.build(tmp_path / "replay_asan", sanitize=True, replay=True, opt="-O0")
    samples = list(iter_samples(tunnel_log))
    stdin = pe.replay_input(PipelineConfig(), samples)
    a = pe.replay(exe, stdin)
    b = pe.replay(exes["f32"], stdin)
    assert len(a["imu"]) == len(samples) - len(b["gnss"]) - len(b["mag"])
    for (fa, oa), (fb, ob) in zip(a["imu"], b["imu"], strict=True):
        assert fa == fb and bytes(oa) == bytes(ob)


def test_unsupported_configurations_refused(tmp_path: Path) -> None:
    """pl_init refuses what the C does not implement; the export refuses the same."""
    lib = pe.build(tmp_path / "pl.so")
    base = PipelineConfig()
    cases = {
        "paper": base.replace(mount=MountConfig(method="paper")),
        "smoothing": base.replace(fusion=FusionConfig(smoothing=True)),
    }
    for name, cfg in cases.items():
        assert pe.refusal(cfg) is not None, name
        with pytest.raises(RuntimeError, match="pl_init refused"):
            pe.PipelineFirmware(lib, cfg)
        with pytest.raises(ValueError, match="refuses"):
            pe.export(tmp_path / name, cfg)
    # a fusion gate without its quantile (a caller editing the C struct): refused, not ungated
    c = pe.config_struct_of(base, ctypes.c_float)
    c.fusion_gate_nis = 0.0
    lib_c = ctypes.CDLL(str(lib))
    lib_c.pl_sizeof.restype = ctypes.c_int32
    state = ctypes.create_string_buffer(int(lib_c.pl_sizeof(ctypes.c_int32(0))))
    assert lib_c.pl_init(state, ctypes.byref(c)) == pe.PL_ERR_UNSUPPORTED
    fw = pe.PipelineFirmware(lib, base)  # the default is implemented
    assert pe.refusal(base) is None and fw.output()["source"] == 0


def test_cli_export_pipeline(tmp_path: Path) -> None:
    """``iotnav firmware export --engine pipeline``: the tuned TOML's values in the generated
    headers; the exported folder compiles and its engine runs with them; refused configurations
    give a clear message."""
    from typer.testing import CliRunner

    from iotnav.cli import app

    toml = tmp_path / "tuned.toml"
    toml.write_text(
        "[static]\ntheta_a_mps2 = 0.123\n[fusion]\nacc_psd_m2_s3 = 0.75\n[pipeline]\nfix_hold_s = 2.25\n"
    )
    out = tmp_path / "out"
    args = ["firmware", "export", "--engine", "pipeline", "--config", str(toml), "--out", str(out)]
    r = CliRunner().invoke(app, args)
    assert r.exit_code == 0, r.output
    tuned = PipelineConfig.from_toml(toml)
    text = (out / pe.ENGINE_HEADER_NAME).read_text()
    assert text == pe.engine_config_header(tuned)
    assert (
        "IOTNAV_R(2.25) /* fix_hold_s */" in text and "IOTNAV_R(0.75)" in text and "IOTNAV_R(0.123)" in text
    )
    assert "IOTNAV_R(0.123) /* theta_a_mps2 */" in (out / "pipeline_config.h").read_text()
    # the exported folder compiles on its own, and its defaults are the tuned values
    main = tmp_path / "main.c"
    main.write_text(
        '#include "pipeline.h"\n#include <stdio.h>\nstatic pl_state st;\n'
        "int main(void) { const pl_pipeline_config c = PL_PIPELINE_CONFIG_DEFAULTS;\n"
        '  int rc = pl_init(&st, &c); printf("%d %.4f %.4f %.4f", rc, (double)st.cfg.pipeline.fix_hold_s,\n'
        "  (double)st.det.cfg.theta_a_mps2, (double)st.fus.cfg.acc_psd_m2_s3); return 0; }\n"
    )
    from iotnav.firmware.host import WARN_FLAGS, run_gcc

    exe = run_gcc(
        [
            *WARN_FLAGS,
            "-O0",
            "-I",
            str(out),
            str(main),
            *(str(out / s) for s in pe.SOURCES),
            "-lm",
            "-o",
            str(tmp_path / "m"),
        ],
        tmp_path / "m",
    )
    import subprocess

    assert (
        subprocess.run([str(exe)], capture_output=True, text=True, check=True).stdout
        == "0 2.2500 0.1230 0.7500"
    )
    toml.write_text('[mount]\nmethod = "paper"\n')
    r = CliRunner().invoke(app, args)
    assert r.exit_code == 2 and "refuses" in r.output and "paper" in r.output, r.output


def test_cortex_m3_cost_driver_equals_host_float32(tmp_path: Path) -> None:
    """The wired pipeline's cost driver (90 s car, mount 0.5 rad) on the emulated Cortex-M3 (soft
    float, qemu mps2-an385): the host float32 build's events, sources and final state (the golden
    check ``benchmarks/bench_firmware_pipeline.py`` makes before it reports counts); and the run
    exercised the blocks: static periods, mount estimates with the angle found, a save."""
    from iotnav.firmware import targets as tg

    host = tg.parse(tg.run([str(tg.build_host(tmp_path / "host", pe.COST_SOURCES))]))
    elf = tg.build_arm(tmp_path / "m3.elf", "cortex-m3", pe.COST_SOURCES)
    m3 = tg.run_arm(elf, "cortex-m3", timeout=120.0)
    diffs = pe.check_cost_run(m3, host)
    assert max(diffs.values()) < 1e-5
    assert host["ev_static_start"] == 2 and host["ev_mount"] >= 5 and host["mount_known"] == 1
    assert abs(tg.f32(host["mount_yaw"]) - 0.5) < 0.01 and host["ev_save"] >= 1
    assert host["src_lowpass"] > 0 and host["src_fix"] > 0 and host["init_rc"] == 100  # pl_init: PL_OK


def test_bad_input_beside_python(exes: dict[str, Path], tunnel_log: Log) -> None:
    """InputGuard's rules in C: a non-finite IMU sample, one earlier than the previous, a 1.5 s
    IMU gap, a valid fix without coordinates, a valid course that is not a number, a GNSS epoch
    earlier than the previous: the same skips and repairs as ``Pipeline.step``, the same rows."""
    samples = [s for s in iter_samples(tunnel_log) if s.t < 20.0]
    imu = [i for i, s in enumerate(samples) if isinstance(s, ImuSample)]
    gnss = [i for i, s in enumerate(samples) if isinstance(s, GnssSample)]
    samples[imu[200]] = samples[imu[200]]._replace(t=math.nan)
    samples[imu[300]] = samples[imu[300]]._replace(acc_b=(math.nan, 0.0, -9.8))
    samples[imu[500]] = samples[imu[500]]._replace(t=samples[imu[499]].t - 0.5)
    samples[gnss[3]] = samples[gnss[3]]._replace(lat_deg=math.nan)
    samples[gnss[5]] = samples[gnss[5]]._replace(course_rad=math.nan, course_valid=True)
    samples[gnss[8]] = samples[gnss[8]]._replace(t=samples[gnss[7]].t - 0.1)
    gap = {i for i in imu[800:950]}
    samples = [s for i, s in enumerate(samples) if i not in gap]
    eng = Pipeline(PipelineConfig())
    rows = [o for o in (eng.step(s) for s in samples) if o is not None]
    want = {
        "imu_nonfinite": 2,
        "imu_time_backwards": 1,
        "imu_gap": 1,
        "gnss_nonfinite": 1,
        "gnss_course_nonfinite": 1,
        "gnss_time_backwards": 1,
    }
    assert eng.guard.skipped == want
    c = pe.replay(exes["f64"], pe.replay_input(PipelineConfig(), samples, double=True), double=True)
    imu_flags = [f for f, _ in c["imu"]]
    gnss_flags = [g[0] for g in c["gnss"]]
    skipped = pe.EV["skipped"]
    assert sum(1 for f in imu_flags if f & skipped) == 3 and sum(1 for f in gnss_flags if f & skipped) == 2
    assert sum(1 for f in imu_flags if f & pe.EV["imu_gap"]) == 1
    assert sum(1 for f in gnss_flags if f & pe.EV["course_repaired"]) == 1
    c_rows = [o for f, o in c["imu"] if not f & skipped]
    assert len(c_rows) == len(rows)
    assert [SOURCES[o.source] for o in c_rows] == [r.source for r in rows]
    P = np.array([[r.north, r.east, r.down] for r in rows])
    C = np.array([list(o.r_n) for o in c_rows])
    ok = np.isfinite(P[:, 0])
    assert (ok == np.array([bool(o.has_position) for o in c_rows])).all()
    assert np.abs(C[ok] - P[ok]).max() < 1e-9


def test_ctypes_binding_with_magnetometer(tmp_path: Path, tunnel_log: Log) -> None:
    """:class:`~iotnav.firmware.pipeline_engine.PipelineFirmware` (the library through ctypes, one
    call per sample, a stored position, a magnetometer at 10 Hz aiding the yaw filter:
    ``yaw.use_mag``) gives the replay program's flags and rows exactly, and ``Pipeline.step``'s
    rows (float64, 1e-9 m and rad plus Python's re-anchoring rounding)."""
    lib = pe.build(tmp_path / "pl64.so", double=True)
    exe = pe.build(tmp_path / "replay64", double=True, replay=True)
    rng = np.random.default_rng(5)
    samples: list[Any] = []
    for s in iter_samples(tunnel_log):
        if s.t >= 15.0:
            break
        samples.append(s)
        if isinstance(s, ImuSample) and len(samples) % 10 == 0:  # a seeded field, about Turin's 47 uT
            samples.append(MagSample(s.t, np.array([21.0, 4.0, 41.5]) + rng.normal(0.0, 0.5, 3)))
    g0 = next(s for s in samples if isinstance(s, GnssSample))
    stored = StoredPosition(g0.lat_deg + 1e-3, g0.lon_deg, g0.height_m, -100.0, 0.1)
    cfg = PipelineConfig()
    assert cfg.yaw.use_mag
    fw = pe.PipelineFirmware(lib, cfg, double=True)
    fw.set_stored(stored.lat_deg, stored.lon_deg, stored.height_m, stored.mount_yaw_rad)
    eng = Pipeline(cfg, stored=stored)
    flags, rows, py = [], [], []
    for s in samples:
        out = eng.step(s)
        if isinstance(s, ImuSample):
            flags.append(fw.step_imu(s))
            rows.append(fw.output())
            py.append(out)
        elif isinstance(s, GnssSample):
            flags.append(fw.step_gnss(s))
        else:
            flags.append(fw.step_mag(s))
    c = pe.replay(exe, pe.replay_input(cfg, samples, double=True, stored=stored), double=True)
    it, ig, im = iter(c["imu"]), iter(c["gnss"]), iter(c["mag"])
    want = [next(it)[0] if k == "I" else next(ig)[0] if k == "G" else next(im) for k in c["order"]]
    assert flags == want and len(c["mag"]) > 100
    assert any(f & pe.EV["moved_while_off"] for f in flags)
    bound = 1e-9 + _anchor_bound(eng)
    for r, (_, o), p in zip(rows, c["imu"], py, strict=True):
        assert r["source"] == o.source and r["static"] == bool(o.is_static) and SOURCES[o.source] == p.source
        assert [r["north"], r["east"], r["down"], r["yaw"]] == [o.r_n[0], o.r_n[1], o.r_n[2], o.yaw]
        if math.isfinite(p.north):
            assert abs(r["north"] - p.north) < bound and abs(r["east"] - p.east) < bound
        assert abs(pe_wrap(r["yaw"] - p.yaw)) < 1e-9
