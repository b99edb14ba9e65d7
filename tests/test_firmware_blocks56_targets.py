"""Blocks 5 and 6 of the Forno pipeline in C on an emulated Cortex-M4F (issue 20's target costs).

``firmware/host/cycles_blocks56.c`` (40 s of a car with the sensor mounted 0.5 rad off its axis:
100 Hz IMU into the mount aligner and the fusion KF's predict, 4 Hz GNSS into the aligner and
the fusion KF's position and velocity updates) is built for the host (float32, ``gcc``) and for
the Cortex-M4F board ``qemu-system-arm`` emulates (mps2-an386, FPU); the target's final state must
equal the host build's: the same decisions (buffers evaluated, accepted, fixes gated, ...) and the
reals within the float32 tolerances of the host tests (:mod:`iotnav.firmware.targets`). This is
the check ``benchmarks/bench_firmware_blocks56.py`` makes before it reports a target's counts.
Needs ``gcc-arm-none-eabi``, ``libnewlib-arm-none-eabi`` and ``qemu-system-arm`` (``.ci/run``
installs them): fails, not skips, without them.
"""

from __future__ import annotations

import dataclasses
import math
import re
import struct

import pytest

from iotnav.engines.config import PIPELINE_MOUNT_NAV
from iotnav.firmware import arm
from iotnav.firmware import targets as tg
from iotnav.firmware.host import FIRMWARE_DIR
from iotnav.techniques.mount import MountConfig


@pytest.fixture(scope="module")
def runs(tmp_path_factory: pytest.TempPathFactory) -> dict[str, dict[str, int]]:
    d = tmp_path_factory.mktemp("blocks56")
    defs = tg.blocks56_defines()
    host = tg.parse(tg.run([str(tg.build_host(d / "host", tg.BLOCKS56_SOURCES, defs))]))
    elf = tg.build_arm(d / "m4f.elf", "cortex-m4f", tg.BLOCKS56_SOURCES, defs)
    return {"host": host, "m4f": tg.run_arm(elf, "cortex-m4f", timeout=60.0)}


def test_driver_uses_the_pipeline_mount_configuration() -> None:
    """The driver's block 5 settings are PIPELINE_MOUNT_NAV's fields that differ from MountConfig's
    defaults (the generated header's PL_MOUNT_CONFIG_DEFAULTS), value for value."""
    text = (FIRMWARE_DIR / "host" / "cycles_blocks56.c").read_text()
    set_in_c = {m[1]: m[2] for m in re.finditer(r"^\s*mc\.(\w+) = ([^;]+);", text, re.M)}
    default = dataclasses.asdict(MountConfig())
    wanted = {k: v for k, v in dataclasses.asdict(PIPELINE_MOUNT_NAV).items() if v != default[k]}
    assert set(set_in_c) == set(wanted)
    for k, v in wanted.items():
        c = re.sub(r"IOTNAV_R\((.*)\)", r"\1", set_in_c[k])
        assert float(c) == pytest.approx(float(v), rel=1e-15), k


def test_cortex_m4f_equals_host_float32(runs: dict[str, dict[str, int]]) -> None:
    """Same decisions, float32 state within the host tests' tolerances; and the run exercised both
    blocks: buffers evaluated and accepted, the angle found (0.5 rad mount, to 0.01 rad), every
    fix taken."""
    host, m4f = runs["host"], runs["m4f"]
    diffs = tg.check_blocks56(m4f, host)
    assert max(diffs.values()) < 1e-4
    assert host["n_eval"] >= 10 and host["n_accepted"] >= 1 and host["known"] == 1
    assert abs(tg.f32(host["mount_yaw"]) - 0.5) < 0.01
    assert host["n_pos_ok"] == host["n_gnss"] - 1 == 160
    # the per-call counts are there and plausible: a 9-state update costs more than an IMU sum
    assert arm.instructions(m4f["fusion_position_mean"]) > 10 * arm.instructions(m4f["mount_imu_mean"]) > 0


def test_check_refuses_a_different_state(runs: dict[str, dict[str, int]]) -> None:
    """The golden check is not vacuous: one decision or one real beyond its tolerance fails it."""
    host = runs["host"]
    with pytest.raises(RuntimeError, match="n_accepted"):
        tg.check_blocks56({**host, "n_accepted": host["n_accepted"] + 1}, host)
    moved = tg.f32(host["x0"]) + 1e-3  # 1 mm: beyond the 0.1 mm of the position
    bits = int.from_bytes(struct.pack("<f", moved), "little")
    with pytest.raises(RuntimeError, match="x0"):
        tg.check_blocks56({**host, "x0": bits}, host)
    with pytest.raises(RuntimeError, match="incomplete"):
        tg.check_blocks56({k: v for k, v in host.items() if k != "done"}, host)
    assert math.isfinite(tg.f32(host["nis"]))
