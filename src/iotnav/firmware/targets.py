"""Cost drivers of the firmware (``firmware/host/cycles_*.c``) built and run on the host and the emulated targets.

A cost driver is one C program that feeds a library block a fixed, self-generated input
sequence, times each call and prints ``key decimal`` lines (reals as their float32 IEEE bits,
``firmware/host/measure.h``). Built for the host with ``gcc`` it gives the reference final state
(the golden vector); built for the ATmega128 (``avr-gcc -Os``, run under ``simavr``: Timer1
cycles at :data:`~iotnav.firmware.avr.F_CPU`) or a Cortex-M board of
:data:`iotnav.firmware.arm.TARGETS` (``arm-none-eabi-gcc -O2`` with the replay programs'
startup, semihosting and linker script, run under ``qemu-system-arm -icount``: SysTick ticks,
see :func:`iotnav.firmware.arm.instructions`), its counts count only when its final state equals
the host float32 build's: the same integer counts and every real within the tolerance given per
key (:func:`check`). ``benchmarks/bench_firmware.py`` costs blocks 1-4 with
``firmware/host/cycles_pipeline.c`` this way and ``benchmarks/bench_firmware_blocks56.py`` blocks
5 and 6 with ``firmware/host/cycles_blocks56.c``; ``tests/test_firmware_blocks56_targets.py``
runs the blocks 5-6 check on the Cortex-M4F.
"""

from __future__ import annotations

import re
import struct
import subprocess
from collections.abc import Mapping, Sequence
from pathlib import Path

from iotnav.firmware import arm
from iotnav.firmware.avr import F_CPU
from iotnav.firmware.host import FIRMWARE_DIR, WARN_FLAGS

__all__ = [
    "BLOCKS56_SOURCES",
    "Tolerance",
    "blocks56_defines",
    "build_arm",
    "build_avr",
    "build_host",
    "check",
    "check_blocks56",
    "f32",
    "parse",
    "run",
    "run_arm",
    "run_avr",
]

#: Per key of a driver's final state: ``("abs", bound)`` or ``("rel", bound)`` (relative to
#: the host value, floored at 1e-6 in magnitude); keys absent here are integers compared exactly.
Tolerance = Mapping[str, tuple[str, float]]


def run(cmd: Sequence[str], timeout: float = 120.0, cwd: Path | None = None) -> str:
    """Run ``cmd``; its stdout and stderr. Raises RuntimeError when it fails or times out."""
    try:
        res = subprocess.run(list(cmd), capture_output=True, text=True, check=False, timeout=timeout, cwd=cwd)
    except subprocess.TimeoutExpired as e:
        raise RuntimeError(f"{' '.join(cmd)} did not finish in {timeout} s") from e
    if res.returncode != 0:
        raise RuntimeError(f"{' '.join(cmd)} failed ({res.returncode}):\n{res.stdout}\n{res.stderr}")
    return res.stdout + res.stderr


def parse(text: str) -> dict[str, int]:
    """``key number`` lines of a driver (simavr adds colour codes and a dot); ``done`` -> 1."""
    text = re.sub(r"\x1b\[[0-9;]*m", "", text)
    out = {m[1]: int(m[2]) for m in re.finditer(r"^(\w+) (\d+)\.?$", text, re.M)}
    if re.search(r"^done\.?$", text, re.M):
        out["done"] = 1
    return out


def f32(bits: int) -> float:
    """The float32 whose IEEE bits are ``bits``."""
    return float(struct.unpack("<f", struct.pack("<I", bits))[0])


def _src(sources: Sequence[str], src: Path) -> list[str]:
    return [str(src / s) for s in sources]


def build_host(
    out: Path, sources: Sequence[str], defines: Sequence[str] = (), src: Path = FIRMWARE_DIR
) -> Path:
    """``gcc -O2`` float32 build of a driver and its library sources (paths under ``src``)."""
    run(["gcc", *WARN_FLAGS, "-O2", *defines, *_src(sources, src), "-lm", "-o", str(out)])
    return out


def avr_flags(mcu: str = "atmega128") -> list[str]:
    """``avr-gcc`` flags of the AVR builds (``-Os``, the 8 MHz clock of the anchor paper's ATmega128)."""
    return ["avr-gcc", *WARN_FLAGS, "-Os", f"-mmcu={mcu}", f"-DF_CPU={F_CPU}UL"]


def build_avr(
    out: Path,
    sources: Sequence[str],
    defines: Sequence[str] = (),
    src: Path = FIRMWARE_DIR,
    mcu: str = "atmega128",
) -> Path:
    """AVR build (``avr-gcc -Os``, core ``mcu``). Raises RuntimeError when it does not link (e.g. RAM overflow)."""
    run([*avr_flags(mcu), *defines, *_src(sources, src), "-lm", "-o", str(out)])
    return out


def arm_flags(target: str) -> list[str]:
    """``arm-none-eabi-gcc`` flags of ``target``'s builds (``-O2``, its core, sections)."""
    t = arm.TARGETS[target]
    return ["arm-none-eabi-gcc", *WARN_FLAGS, "-O2", *t.cflags, "-ffunction-sections", "-fdata-sections"]


def build_arm(
    out: Path, target: str, sources: Sequence[str], defines: Sequence[str] = (), src: Path = FIRMWARE_DIR
) -> Path:
    """Cortex-M build of a driver with the replay programs' startup, semihosting and linker script."""
    cmd = [
        *arm_flags(target),
        *defines,
        "-nostartfiles",
        "-T",
        str(src / "arm" / "mps2.ld"),
        "-Wl,--gc-sections",
    ]
    cmd += _src(("arm/startup.c", "arm/semihost.c", *sources), src)
    run([*cmd, "-lm", "-o", str(out)])
    return out


def run_avr(elf: Path, timeout: float = 600.0, mcu: str = "atmega128") -> dict[str, int]:
    """Run an AVR driver under simavr at :data:`~iotnav.firmware.avr.F_CPU`: its parsed lines."""
    return parse(run(["simavr", "-m", mcu, "-f", str(F_CPU), str(elf)], timeout=timeout))


def run_arm(elf: Path, target: str, timeout: float = 600.0) -> dict[str, int]:
    """Run a Cortex-M driver under ``qemu-system-arm -icount``: its parsed lines (SysTick ticks).

    Raises RuntimeError when SysTick does not count one tick per :func:`arm.instructions` unit
    (the driver's calibration loop).
    """
    t = arm.TARGETS[target]
    qemu = ["qemu-system-arm", "-M", t.machine, "-nographic", "-monitor", "none", "-serial", "none"]
    qemu += ["-semihosting-config", "enable=on,target=native", "-icount", f"shift={arm.ICOUNT_SHIFT}"]
    out = parse(run([*qemu, "-kernel", str(elf)], timeout=timeout))
    if (
        "calib_ticks" not in out
        or abs(arm.instructions(out["calib_ticks"]) / (2 * out["calib_loops"]) - 1.0) > 1e-3
    ):
        raise RuntimeError(f"{target}: SysTick is not counting instructions ({out})")
    return out


def check(
    out: Mapping[str, int], host: Mapping[str, int], reals: Tolerance, counts: Sequence[str]
) -> dict[str, float]:
    """Compare a target run's final state with the host float32 build's (the golden vector).

    Parameters
    ----------
    out, host : mapping
        Parsed lines (:func:`parse`) of the target and host runs.
    reals : mapping
        Float32 keys and their tolerance (:data:`Tolerance`).
    counts : sequence of str
        Integer keys that must be equal.

    Returns
    -------
    dict
        Per real key, its difference (absolute or relative, as its tolerance).

    Raises
    ------
    RuntimeError
        When the run is incomplete, a count differs or a real is beyond its tolerance.
    """
    missing = [k for k in ("done", *reals, *counts) if k not in out or k not in host]
    if missing:
        raise RuntimeError(f"driver run incomplete (missing {missing}): {dict(out)}")
    diffs: dict[str, float] = {}
    bad = [f"{k} {out[k]} != {host[k]}" for k in counts if out[k] != host[k]]
    for k, (kind, bound) in reals.items():
        a, b = f32(out[k]), f32(host[k])
        d = abs(a - b) if kind == "abs" else abs(a - b) / max(abs(b), 1e-6)
        diffs[k] = d
        if not d <= bound:
            bad.append(f"{k}: {a!r} vs host {b!r} ({kind} {d:.2e} > {bound:.0e})")
    if bad:
        raise RuntimeError("final state differs from the host float32 build: " + "; ".join(bad))
    return diffs


#: ``firmware/host/cycles_blocks56.c`` and the library sources of blocks 5 and 6.
BLOCKS56_SOURCES = ("host/cycles_blocks56.c", "pipeline_mount.c", "pipeline_fusion.c")
#: Its final state and the float32 tolerances of the host tests (``tests/test_firmware_mount.py``:
#: angles 1e-5 rad, quality figures 1e-4 absolute, here also the gravity reference in m/s^2;
#: ``tests/test_firmware_blocks56.py``: position 1e-4 m,
#: velocity 1e-5 m/s, bias 1e-6 m/s^2, covariance diagonal 1e-4 and NIS 1e-3 relative).
BLOCK5_REALS: dict[str, tuple[str, float]] = {
    "mount_yaw": ("abs", 1e-5),
    "candidate": ("abs", 1e-5),
    "std": ("abs", 1e-4),
    "coherence": ("abs", 1e-4),
    **{f"fref{i}": ("abs", 1e-4) for i in range(3)},
}
BLOCK5_COUNTS: tuple[str, ...] = ("n_gnss", "n_eval", "n_accepted", "n_applied", "n_provisional")
BLOCK5_COUNTS += ("n_settled", "n_outlier", "n_demeaned", "known", "have_ref", "n_hist_dropped")
BLOCK6_REALS: dict[str, tuple[str, float]] = {
    **{f"x{i}": ("abs", 1e-4) for i in range(3)},
    **{f"x{i}": ("abs", 1e-5) for i in range(3, 6)},
    **{f"x{i}": ("abs", 1e-6) for i in range(6, 9)},
    **{f"p{i}": ("rel", 1e-4) for i in range(9)},
    "nis": ("rel", 1e-3),
}
BLOCK6_COUNTS = ("n_pos_ok", "n_pos_rejected", "n_vel_ok")


def blocks56_defines(block5: bool = True, block6: bool = True) -> list[str]:
    """Compiler definitions of ``cycles_blocks56.c``: which blocks, and block 6's position gate
    (:func:`iotnav.kalman.gate_threshold` of ``FusionConfig().gate_probability``, 3 dof)."""
    from iotnav import kalman
    from iotnav.techniques.fusion_kf import FusionConfig

    gate = kalman.gate_threshold(3, FusionConfig().gate_probability)
    return [f"-DPL_FUSION_GATE_NIS={gate!r}", f"-DCOST_BLOCK5={int(block5)}", f"-DCOST_BLOCK6={int(block6)}"]


def check_blocks56(
    out: Mapping[str, int], host: Mapping[str, int], block5: bool = True, block6: bool = True
) -> dict[str, float]:
    """:func:`check` of a ``cycles_blocks56.c`` run with the blocks it was built with."""
    reals = {**(BLOCK5_REALS if block5 else {}), **(BLOCK6_REALS if block6 else {})}
    counts = (*(BLOCK5_COUNTS if block5 else ()), *(BLOCK6_COUNTS if block6 else ()))
    return check(out, host, reals, counts)
