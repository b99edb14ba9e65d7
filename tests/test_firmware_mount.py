"""Block 5 of the Forno pipeline in C (firmware/pipeline_mount.c, bound by
:mod:`iotnav.firmware.pipeline_mount`) against :class:`iotnav.techniques.mount.MountAligner`.

Both are fed the same calls: every IMU sample of a log (sensor-frame specific force and the yaw
rate ``r = u . (omega_b - b_g)`` about the down axis ``u`` of the first 3 s at rest, with that
rest's gyro mean ``b_g`` removed: a stand-in for the cascade's ``x3 . omega_b``) and every
valid GNSS epoch (speed, course, its flag, and "static" when the speed is below 0.5 m/s: a
stand-in for block 3). Logs: the whole rtklibexplorer car drive drive_0708 (549 s, 100 Hz IMU,
4 Hz GNSS, sensor mounted backwards) with the pipeline's :data:`PIPELINE_MOUNT_NAV` (auto
demean, gate, settle, provisional estimates: 233 buffers, every rule taken), and two laps of the
simulated scooter (mount 88 deg) with the pipeline's and a second configuration (per-buffer
forgetting, demeaned buffers, one-off, a stored gravity reference). float64: every event value
equal to 1e-9 and every decision the same; float32: the same decisions and the values within
the tolerances of :func:`test_mount_float32_within_tolerance`.
"""

from __future__ import annotations

import ctypes
import dataclasses
import math
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd
import pytest

from conftest import datasets_dir
from iotnav import sim
from iotnav.engines.config import PIPELINE_MOUNT_NAV
from iotnav.firmware import pipeline_blocks56 as pb
from iotnav.firmware import pipeline_mount as pm
from iotnav.firmware.host import replay_sanitized
from iotnav.techniques.mount import MountAligner, MountConfig, wrap

DRIVE = datasets_dir() / "rtklibexplorer_gnss_imu" / "drive_0708"
REPO = Path(__file__).resolve().parents[1]
#: A second configuration for the branches the pipeline's does not take: forgetting per buffer,
#: demeaned buffers only, no matched smoothing, acceptance at 2 deg, one-off calibration.
OTHER = MountConfig(
    min_speed_mps=1.0,
    require_course=False,
    demean_buffers=True,
    max_std_rad=math.radians(2.0),
    one_off=True,
    buffer_epochs=6,
)
ANGLES = ("mount_yaw_rad", "candidate_rad", "buffer_mount_yaw_rad")


@pytest.fixture(scope="module")
def libs(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    d = tmp_path_factory.mktemp("mount")
    return {"f32": pm.build_mount(d / "m32.so"), "f64": pm.build_mount(d / "m64.so", double=True)}


def _calls(imu: pd.DataFrame, gnss: pd.DataFrame, t_rest: float = 3.0) -> list[tuple[Any, ...]]:
    """The aligner calls of a log (module docstring), in time order."""
    t = imu.t.to_numpy(float)
    f = imu[["acc_x", "acc_y", "acc_z"]].to_numpy(float)
    w = imu[["gyro_x", "gyro_y", "gyro_z"]].to_numpy(float)
    rest = t < t[0] + t_rest
    u = -f[rest].mean(axis=0)
    u /= np.linalg.norm(u)
    r = (w - w[rest].mean(axis=0)) @ u
    g = gnss[gnss.valid.astype(bool)]
    out: list[tuple[Any, ...]] = []
    k = 0
    for tg, sp, co, cv in zip(g.t, g.speed_mps, g.course_rad, g.course_valid.astype(bool), strict=True):
        while k < len(t) and t[k] < tg:
            out.append(("I", f[k], float(r[k])))
            k += 1
        out.append(("G", float(tg), float(sp), float(co), bool(cv), bool(sp < 0.5)))
    return out


def _drive(al: Any, calls: list[tuple[Any, ...]]) -> list[dict[str, Any]]:
    """Feed ``calls`` to a MountAligner or a MountBlock; its events."""
    evs = []
    for c in calls:
        if c[0] == "I":
            al.add_imu_body(c[1], c[2])
        elif c[0] == "R":
            al.set_gravity_reference(c[1], c[2])
        else:
            e = al.add_gnss(*c[1:])
            if e is not None:
                evs.append(e)
    return evs


@pytest.fixture(scope="module")
def drive_calls() -> list[tuple[Any, ...]]:
    from iotnav.cli.outages import load_dataset

    log, _ = load_dataset(DRIVE)  # fails (not skips) when the dataset is missing
    return _calls(log.imu, log.gnss)


@pytest.fixture(scope="module")
def sim_calls() -> list[tuple[Any, ...]]:
    res = sim.build("scooter-laps", seed=1, overrides={"motion.laps": 2, "mount_yaw_rad": math.radians(88.0)})
    calls = _calls(res.imu, res.gnss)
    # a stored gravity reference (an initialisation's static mean) before the first sample
    f0 = np.mean([c[1] for c in calls[:100] if c[0] == "I"], axis=0)
    return [("R", f0, float(res.imu.t.iloc[0])), *calls]


CASES = {
    "drive": ("drive_calls", PIPELINE_MOUNT_NAV),
    "sim": ("sim_calls", PIPELINE_MOUNT_NAV),
    "sim_other": ("sim_calls", OTHER),
}


def _both(request: pytest.FixtureRequest, lib: Path, case: str, double: bool) -> tuple[list, list, Any]:
    name, cfg = CASES[case]
    calls = request.getfixturevalue(name)
    block = pm.MountBlock(lib, cfg, double=double)
    assert block.init_rc == pm.MOUNT_OK
    al = MountAligner(cfg)
    py, c = _drive(al, calls), _drive(block, calls)
    assert block.n_hist_dropped == 0
    assert (block.known, block.provisional, block.done) == (al.known, al.provisional, al.done)
    return py, c, (al, block)


def _diffs(py: list[dict[str, Any]], c: list[dict[str, Any]]) -> dict[str, float]:
    """Same number of events and the same decisions; the largest difference of each value."""
    assert len(c) == len(py) > 0
    for key in pm.EVENT_FLAGS:
        assert [bool(e[key]) for e in c] == [bool(e[key]) for e in py], key
    out = {}
    for key in pm.EVENT_VALUES:
        a = np.array([e.get(key, math.nan) for e in py])
        b = np.array([e[key] for e in c])
        assert np.array_equal(np.isnan(a), np.isnan(b)), key
        ok = ~np.isnan(a)
        d = a[ok] - b[ok]
        if key in ANGLES:
            d = np.array([wrap(float(x)) for x in d])
        out[key] = float(np.abs(d).max()) if d.size else 0.0
    return out


def test_nav_config_header_is_current() -> None:
    """The checked-in header is exactly what the generator writes from FusionConfig and MountConfig."""
    assert (REPO / "firmware" / pb.NAV_HEADER_NAME).read_text() == pb.nav_config_header()
    text = pb.nav_config_header(mount=MountConfig(buffer_epochs=12, method="paper", max_std_rad=0.02))
    assert "12 /* buffer_epochs */" in text and "1 /* method */" in text
    assert "IOTNAV_R(0.02) /* max_std_rad */" in text
    assert "((IOTNAV_REAL)INFINITY) /* max_std_rad */" in pb.nav_config_header()


def test_mount_config_struct_follows_the_dataclass() -> None:
    """One C member per MountConfig field, in order, with its value (the method as an index)."""
    names = [n for n, _ in pb.nav_fields(MountConfig)]
    assert names == [f.name for f in dataclasses.fields(MountConfig)]
    c = pb.nav_config_type("pl_mount", ctypes.c_double)(*pb.nav_values(PIPELINE_MOUNT_NAV))
    for n in names:
        want = getattr(PIPELINE_MOUNT_NAV, n)
        assert getattr(c, n) == (pb.MOUNT_METHODS.index(want) if n == "method" else want), n


def test_unsupported_configurations_are_refused(libs: dict[str, Path]) -> None:
    for cfg in (
        MountConfig(method="paper"),
        MountConfig(buffer_epochs=pb.MOUNT_BUF_MAX + 1),
        MountConfig(ref_window_epochs=pb.MOUNT_REF_MAX + 1),
        MountConfig(smooth_epochs=(pb.MOUNT_SMOOTH_ROWS_MAX + 3) // 2),
    ):
        assert pm.MountBlock(libs["f64"], cfg, double=True).init_rc == pm.MOUNT_ERR_UNSUPPORTED
    assert pm.MountBlock(libs["f64"], MountConfig(buffer_epochs=pb.MOUNT_BUF_MAX), double=True).init_rc == 0


@pytest.mark.parametrize("case", list(CASES))
def test_mount_float64_equals_python(
    libs: dict[str, Path], request: pytest.FixtureRequest, case: str
) -> None:
    py, c, (al, block) = _both(request, libs["f64"], case, double=True)
    d = _diffs(py, c)
    assert max(d.values()) < 1e-9, d
    assert abs(wrap(block.mount_yaw_rad - al.mount_yaw_rad)) < 1e-9
    accepted = [e for e in py if e["accepted"]]
    if case == "drive":
        # every rule of the pipeline's configuration is exercised on the real drive
        assert len(py) > 200 and accepted and any(e["settled"] for e in py)
        assert any(e["provisional"] for e in py) and any(e["buffer_outlier"] for e in py)
        assert any(e["demeaned"] for e in py) and not all(e["demeaned"] for e in py)
    elif case == "sim":
        assert accepted and abs(math.degrees(wrap(al.mount_yaw_rad - math.radians(88.0)))) < 2.0
    else:  # one-off: nothing after the first accepted estimate
        assert al.done and py[-1]["accepted"] and len(accepted) == 1


@pytest.mark.parametrize("case", list(CASES))
def test_mount_float32_within_tolerance(
    libs: dict[str, Path], request: pytest.FixtureRequest, case: str
) -> None:
    """float32 against the float64 Python: the same decisions; the mount angle in use and the fused
    candidate within 1e-5 rad (6e-4 deg: the issue's attitude target is 0.01 deg), a buffer's own
    angle within 1.7e-4 rad (0.01 deg; its rows are float32 means of 25-400 samples and a
    low-coherence buffer amplifies their rounding), the quality figures within 1e-4 (measured,
    worst case: 1.7e-7 rad, 1.7e-7 rad, 4.7e-5 rad, and at most 2.7e-5)."""
    py, c, (al, block) = _both(request, libs["f32"], case, double=False)
    d = _diffs(py, c)
    assert d["mount_yaw_rad"] < 1e-5 and d["candidate_rad"] < 1e-5, d
    assert d["buffer_mount_yaw_rad"] < math.radians(0.01), d
    assert max(v for k, v in d.items() if k not in ANGLES) < 1e-4, d
    assert abs(wrap(block.mount_yaw_rad - al.mount_yaw_rad)) < 1e-5


@pytest.mark.parametrize("case", ["drive", "sim_other"])
def test_mount_sanitized_replay(tmp_path: Path, request: pytest.FixtureRequest, case: str) -> None:
    """host/replay_mount.c with block 5 under ASan + UBSan on the real drive and the simulated laps:
    no report, and the float32 decisions and angles of the ctypes build (float32 arithmetic, -O0)."""
    name, cfg = CASES[case]
    calls = request.getfixturevalue(name)
    exe = pm.build_replay_mount(tmp_path / "replay_mount")
    evs = pm.parse_replay(replay_sanitized(exe, pm.replay_stream(cfg, calls)))
    py = _drive(MountAligner(cfg), calls)
    d = _diffs(py, evs)
    assert d["mount_yaw_rad"] < 1e-5 and d["candidate_rad"] < 1e-5, d
