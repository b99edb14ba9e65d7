"""The C99 GNSS-only engine (firmware/fixes.c) beside the Python ``fixes`` engine (issues 17, 20).

Built for the host with ``gcc -std=c99 -Wall -Wextra -Werror -pedantic`` in float32, float64 and
float32 with AddressSanitizer + UndefinedBehaviorSanitizer, loaded with ctypes and fed the same
samples as :class:`~iotnav.engines.fixes.FixesEngine`'s ``step()``
(:func:`iotnav.firmware.fixes_host.run_beside`): the real drive_0708 (its IMU for the
accelerometer test, its RTK degraded to 1 Hz tracker fixes), a simulated stop-and-go fleet day,
and the same day without velocity and with every kind of bad epoch, a relocation, scattered
jumps and a clock jump (rollbacks, relocations, forced re-initialisations, clock resets). Then
the float32 library on a Cortex-M3 under qemu-system-arm.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from conftest import datasets_dir
from iotnav.engines.base import iter_samples
from iotnav.engines.fixes import FixesConfig, FixesEngine, FixesGateConfig, FixesKFConfig
from iotnav.eval import outages as O
from iotnav.firmware import arm, gen, host
from iotnav.firmware import fixes_host as fh
from iotnav.io.log import Log
from iotnav.sim.fleet_days import fleet_day
from iotnav.techniques.lowpass3 import Lowpass3Config

DRIVE = datasets_dir() / "rtklibexplorer_gnss_imu" / "drive_0708"
REPO = Path(__file__).resolve().parents[1]
#: relocation after 3 rejected fixes, a forced re-initialisation after 4 (the faults' scattered jumps)
TUNED = FixesConfig(gate=FixesGateConfig(max_rejections=4, relocation_fixes=3, relocation_min_s=2.0))


@pytest.fixture(scope="module")
def libs(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    d = tmp_path_factory.mktemp("fwfixes")
    return {
        "f32": host.build(d / "fixes_f32.so", engine="fixes"),
        "f64": host.build(d / "fixes_f64.so", double=True, engine="fixes"),
    }


@pytest.fixture(scope="module")
def faults() -> pd.DataFrame:
    return fh.with_faults(fleet_day("stop-and-go", seed=2).gnss.iloc[:1500])


def _check(res: dict, pos_rms: float, pos_max: float, other: float, events: set[str] = frozenset()) -> None:
    """The same decisions, events and sources; positions within the tolerances; ``events`` seen."""
    assert res["c_skip"] == res["py_skip"]
    assert res["imu_c"] == res["imu_py"]
    names = [[e[0] for e in ev] for ev in res["py_events"]]
    assert [[e[0] for e in ev] for ev in res["c_events"]] == names
    seen = {n for ev in names for n in ev}
    assert events <= seen, events - seen
    vals = np.array(
        [
            (a[1], b[1])
            for pa, pc in zip(res["py_events"], res["c_events"], strict=True)
            for a, b in zip(pa, pc, strict=True)
        ]
    )
    if vals.size:
        assert np.array_equal(np.isnan(vals[:, 0]), np.isnan(vals[:, 1]))
        ok = ~np.isnan(vals[:, 0])
        assert np.all(np.abs(vals[ok, 0] - vals[ok, 1]) <= other * np.maximum(1.0, np.abs(vals[ok, 0])))
    assert res["c_source"] == res["py_source"] and res["c_static"] == res["py_static"]
    py, c = res["py"], res["c"]
    assert len(py) > 100 and np.array_equal(np.isnan(py), np.isnan(c))
    err = np.linalg.norm(np.nan_to_num(c[:, :3] - py[:, :3]), axis=1)
    assert np.sqrt(np.mean(err**2)) < pos_rms, np.sqrt(np.mean(err**2))
    assert err.max() < pos_max, err.max()
    assert np.nanmax(np.abs(c[:, 3:8] - py[:, 3:8])) < other
    m_per_deg = np.radians(1.0) * 6.371e6
    d_ll = np.hypot(
        (c[:, 8] - py[:, 8]) * m_per_deg, (c[:, 9] - py[:, 9]) * m_per_deg * np.cos(np.radians(py[:, 8]))
    )
    assert d_ll.max() < max(pos_max, 5e-9), d_ll.max()


def _beside(lib: Path, samples, cfg: FixesConfig = FixesConfig(), double: bool = False, record: bool = False):
    fw = fh.FixesFirmware(lib, cfg, double=double, record=record)
    assert fw.init_rc == 0
    return fh.run_beside(FixesEngine(cfg), fw, samples), fw


ALL_FAULTS = {
    "fix_rejected",
    "relocated",
    "fixes_retracted",
    "clock_reset",
    "static_start",
    "static_end",
    "first_fix",
    "filter_initialised",
    "departure",
}


@pytest.fixture(scope="module")
def faults_f32(libs: dict[str, Path], faults: pd.DataFrame) -> tuple[dict, fh.FixesFirmware]:
    return _beside(libs["f32"], fh.gnss_samples(faults), record=True)


def test_generated_fixes_header_is_current() -> None:
    assert (REPO / "firmware" / gen.FIXES_HEADER_NAME).read_text() == gen.fixes_header()


def test_fixes_header_carries_tuned_values() -> None:
    cfg = FixesConfig(kf=FixesKFConfig(platform="pedestrian"), gate=FixesGateConfig(max_rejections=7))
    text = gen.fixes_header(cfg)
    assert "IOTNAV_R(1.0) /* q_h */" in text and "IOTNAV_R(7.0) /* max_rej */" in text
    # the gate is the chi-square quantile (2 dof): -2 ln(1 - p)
    assert f"IOTNAV_R({-2.0 * math.log(1.0 - 0.9973)!r}) /* gate */" in text


def test_unsupported_configuration_is_refused(libs: dict[str, Path]) -> None:
    big = FixesConfig(lowpass3=Lowpass3Config(n1=gen.FIXES_LP_MAX + 1))
    assert fh.FixesFirmware(libs["f32"], big).init_rc == -1
    assert gen.fixes_unsupported(big) and gen.fixes_unsupported(FixesConfig(kf=FixesKFConfig(smoothing=True)))


def test_faults_float32(faults_f32: tuple) -> None:
    res, _ = faults_f32
    skips = set(res["py_skip"])
    assert {"gnss_duplicate", "gnss_time_repeat", "gnss_time_backwards", "gnss_invalid"} <= skips
    assert {"gnss_zero_position", "gnss_pdop", "gnss_nonfinite", "gnss_future", "gnss_past"} <= skips
    _check(res, 0.01, 0.05, 0.01, ALL_FAULTS)


def test_faults_tuned_float64(libs: dict[str, Path], faults: pd.DataFrame) -> None:
    res, _ = _beside(libs["f64"], fh.gnss_samples(faults), TUNED, double=True)
    # the scattered jumps fall in a parked period: held as multipath (no forced reset while parked)
    _check(res, 1e-9, 1e-9, 1e-9, ALL_FAULTS)


@pytest.fixture(scope="module")
def fleet() -> Log:
    return Log(gnss=fleet_day("stop-and-go", seed=1).gnss.iloc[:1200])


@pytest.mark.parametrize(("build", "tol"), [("f32", (0.01, 0.05, 0.01)), ("f64", (1e-9, 1e-9, 1e-9))])
def test_fleet_day(libs: dict[str, Path], fleet: Log, build: str, tol: tuple) -> None:
    """A simulated stop-and-go day (urban canyon, speed and course): the settling gate, static periods."""
    res, _ = _beside(libs[build], iter_samples(fleet), double=build == "f64")
    assert "gnss_settling" in res["py_skip"]
    _check(res, *tol, {"static_start", "static_end", "fix_rejected", "departure"})


@pytest.fixture(scope="module")
def parked() -> Log:
    """20 min of the parked fleet day (seed 0) around its multipath outlier of 4367 s (the
    departure test's jump tracking: the outlier's fixes are held, not a departure)."""
    return Log(gnss=fleet_day("parked-canyon", seed=0).gnss.iloc[3600:4800])


@pytest.mark.parametrize(("build", "tol"), [("f32", (0.01, 0.05, 0.01)), ("f64", (1e-9, 1e-9, 1e-9))])
def test_parked_day_jumps(libs: dict[str, Path], parked: Log, build: str, tol: tuple) -> None:
    """Parked in the canyon with its jumps and drifts: the departure test in C as in Python."""
    res, _ = _beside(libs[build], iter_samples(parked), double=build == "f64")
    _check(res, *tol, {"static_start", "static_end", "fix_rejected", "departure"})


@pytest.fixture(scope="module")
def drive() -> Log:
    """The first 120 s of drive_0708: IMU and 1 Hz degraded RTK, as the outage study feeds it."""
    from iotnav.cli.outages import load_dataset

    log, prof = load_dataset(DRIVE)  # fails (not skips) when the dataset is missing
    truth = O.rtk_truth(log.gnss).sort_values("t").reset_index(drop=True)
    truth = truth[truth.t < float(truth.t.iloc[0]) + 120.0].reset_index(drop=True)
    fed, _ = O.degraded_feed(log, truth, prof, O.OutageConfig(seed=3))
    return Log(gnss=fed.gnss, imu=fed.imu[fed.imu.t <= fed.gnss.t.max() + 0.5])


@pytest.mark.parametrize(("build", "tol"), [("f32", (0.01, 0.05, 0.01)), ("f64", (1e-9, 1e-9, 1e-9))])
def test_drive_0708(libs: dict[str, Path], drive: Log, build: str, tol: tuple) -> None:
    """The real drive with its accelerometer between fixes (the static test's IMU rule)."""
    res, _ = _beside(libs[build], iter_samples(drive), double=build == "f64")
    assert len(res["imu_c"]) > 10_000
    assert np.abs(res["py"][:, :2]).max() > 100.0  # it drove
    _check(res, *tol, {"static_start", "static_end"})


def _replayed(res: dict, fw: fh.FixesFirmware, outputs: bytes) -> dict:
    """``res`` with the C columns replaced by a replay's outputs (host or board)."""
    recs = fh.decode_stream(fw.inputs, outputs)
    gnss = [(rc, o) for rec, (rc, o) in zip(fw.inputs[1:], recs, strict=True) if rec[:1] == b"G"]
    out = dict(res)
    out["c_skip"] = [fh.REASONS[rc] if rc > 0 else "" for rc, _ in gnss]
    out["imu_c"] = [
        fh.IMU_REASONS[rc] for rec, (rc, _) in zip(fw.inputs[1:], recs, strict=True) if rec[:1] == b"I"
    ]
    out["c_events"] = [fh.c_events(o) for _, o in gnss]
    rows = [o for rc, o in gnss if rc == 0]
    out["c"] = np.array([[*o["ned"], *o["vel"], *o["std"], o["lat"], o["lon"], o["height"]] for o in rows])
    out["c_source"] = [o["source"] for o in rows]
    out["c_static"] = [o["static"] for o in rows]
    return out


def test_sanitized_build_replays_the_same_track(tmp_path: Path, faults_f32: tuple) -> None:
    """The float32 source with ASan + UBSan (firmware/host/replay_fixes.c, at -O0: a quarter of the
    compile time of -O2) replays the ctypes run's inputs with no sanitizer report, into the same
    output bytes (C99 does not contract floating-point expressions: -O0 and -O2 round alike)."""
    exe = host.build(tmp_path / "replay_fixes_asan", sanitize=True, replay=True, engine="fixes", opt="-O0")
    res, fw = faults_f32
    out = host.replay_sanitized(exe, b"".join(fw.inputs))
    assert len(fw.outputs) > 1500 and out == b"".join(fw.outputs)
    _check(_replayed(res, fw, out), 0.01, 0.05, 0.01, ALL_FAULTS)


def test_cortex_m3_under_qemu_equals_python(tmp_path: Path, faults_f32: tuple) -> None:
    """The float32 library cross-compiled for a Cortex-M3 (soft float, mps2-an385) replays under
    qemu-system-arm the inputs the Python engine fed the ctypes run and writes the Python track
    (decisions, events, sources; positions within 1 cm RMS / 5 cm max)."""
    res, fw = faults_f32
    elf = arm.build(tmp_path / "replay_fixes_m3.elf", "cortex-m3", engine="fixes")
    run = arm.run(elf, "cortex-m3", b"".join(fw.inputs))
    _check(_replayed(res, fw, run.outputs), 0.01, 0.05, 0.01, ALL_FAULTS)
    assert arm.instructions(run.counts["calib_ticks"]) == pytest.approx(2 * run.counts["calib_loops"], abs=8)
    assert run.counts["gnss_n"] > 1400


def test_cli_export_fixes(tmp_path: Path) -> None:
    """``iotnav firmware export --engine fixes``: the tuned TOML's parameters in fixes_config.h; the folder builds."""
    from typer.testing import CliRunner

    from iotnav.cli import app

    toml = tmp_path / "tuned.toml"
    toml.write_text('[kf]\nplatform = "bike"\n[gate]\nmax_rejections = 12\n')
    out = tmp_path / "out"
    r = CliRunner().invoke(
        app, ["firmware", "export", "--engine", "fixes", "--config", str(toml), "--out", str(out)]
    )
    assert r.exit_code == 0, r.output
    tuned = FixesConfig.from_toml(toml)
    assert (out / gen.FIXES_HEADER_NAME).read_text() == gen.fixes_header(tuned)
    assert "IOTNAV_R(3.0) /* q_h */" in (out / gen.FIXES_HEADER_NAME).read_text()
    assert host.build(tmp_path / "exported.so", src=out, engine="fixes", opt="-O0").is_file()  # it compiles
    toml.write_text("[kf]\nsmoothing = true\n")
    r = CliRunner().invoke(
        app, ["firmware", "export", "--engine", "fixes", "--config", str(toml), "--out", str(out)]
    )
    assert r.exit_code == 2 and "does not implement" in r.output, r.output
