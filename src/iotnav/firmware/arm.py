"""Build the firmware's anchor KF for Cortex-M boards and run it under ``qemu-system-arm``.

The library (``firmware/anchor.c``) is cross-compiled with ``arm-none-eabi-gcc`` (Debian
``gcc-arm-none-eabi`` + ``libnewlib-arm-none-eabi`` for ``libm``) together with the test
program ``firmware/arm/replay.c`` (semihosting I/O, its own startup and linker script, no
libc beyond ``<math.h>``) for one of :data:`TARGETS`, and run on the board QEMU emulates
(``qemu-system-arm``). The program replays the input stream of
:class:`~iotnav.firmware.host.AnchorFirmware` (``record=True``), which a float32 host build and
the ARM build read alike: every member of the structs is four bytes, little-endian.

Cost: QEMU does not model cycles, and the Cortex-M cycle counter (DWT ``CYCCNT``) is not
emulated. With ``-icount shift=N`` the virtual clock advances exactly ``2**N`` ns per executed
instruction, so the board's SysTick, counting the 25 MHz MPS2 system clock (ARM AN385 / AN386),
counts ``2**N * 25e6 / 1e9`` ticks per instruction (1.6 for :data:`ICOUNT_SHIFT` = 6). The
program checks that factor on a loop of known length (``calib_*``); :func:`instructions`
converts. These are instructions, not cycles: a Cortex-M3/M4 takes one cycle for most of them,
more for loads, branches, divisions and (M4F) ``vdiv``/``vsqrt`` (14 cycles).
"""

from __future__ import annotations

import re
import shutil
import subprocess
import tempfile
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import numpy.typing as npt

from iotnav.firmware.host import FIRMWARE_DIR, WARN_FLAGS

__all__ = [
    "ICOUNT_SHIFT",
    "OUTPUT_DTYPE",
    "TARGETS",
    "ArmRun",
    "ArmTarget",
    "build",
    "decode_outputs",
    "instructions",
    "run",
    "size",
]


@dataclass(frozen=True)
class ArmTarget:
    """A Cortex-M core, its compiler flags and the QEMU board that emulates it."""

    name: str
    machine: str
    cflags: tuple[str, ...]


#: The emulated targets: ARM MPS2 FPGA images (Cortex-M3 soft float; Cortex-M4F with its FPU).
TARGETS = {
    "cortex-m3": ArmTarget("cortex-m3", "mps2-an385", ("-mcpu=cortex-m3", "-mthumb", "-mfloat-abi=soft")),
    "cortex-m4f": ArmTarget(
        "cortex-m4f",
        "mps2-an386",
        ("-mcpu=cortex-m4", "-mthumb", "-mfpu=fpv4-sp-d16", "-mfloat-abi=hard"),
    ),
}
#: ``-icount shift``: 2**6 ns of virtual time per instruction (1.6 SysTick ticks at 25 MHz).
ICOUNT_SHIFT = 6
#: MPS2 system clock driving SysTick (ARM AN385 / AN386), Hz.
BOARD_CLOCK_HZ = 25_000_000
#: Struct ``anchor_output_t`` of a float32 build (anchor.h).
OUTPUT_DTYPE = np.dtype(
    [
        ("has_position", "<i4"),
        ("source", "<i4"),
        ("r_n", "<f4", 3),
        ("v_n", "<f4", 3),
        ("std_ne", "<f4", 2),
        ("lat_e7", "<i4"),
        ("lon_e7", "<i4"),
        ("frac_e7", "<f4", 2),
        ("height_m", "<f4"),
    ]
)
#: Per engine: the replay program and the library source (``firmware/``).
_ARM_SRC = {"anchor": ("arm/replay.c", "anchor.c"), "fixes": ("arm/replay_fixes.c", "fixes.c")}
_ARM_RUNTIME = ("arm/startup.c", "arm/semihost.c")


def _tool(name: str) -> str:
    path = shutil.which(name)
    if path is None:
        raise RuntimeError(
            f"{name} not found: install the Debian packages gcc-arm-none-eabi, libnewlib-arm-none-eabi "
            "and qemu-system-arm"
        )
    return path


def _run(cmd: list[str], cwd: Path | None = None, timeout: float = 120.0) -> subprocess.CompletedProcess[str]:
    res = subprocess.run(cmd, capture_output=True, text=True, check=False, cwd=cwd, timeout=timeout)
    if res.returncode != 0:
        raise RuntimeError(f"{' '.join(cmd)} failed ({res.returncode}):\n{res.stdout}\n{res.stderr}")
    return res


def build(
    out: Path, target: str, src: Path = FIRMWARE_DIR, library_only: bool = False, engine: str = "anchor"
) -> Path:
    """Cross-compile the engine's replay program (or with ``library_only`` the library object) for ``target``.

    ``engine``: ``anchor`` (``arm/replay.c`` + ``anchor.c``) or ``fixes`` (``arm/replay_fixes.c``
    + ``fixes.c``).

    ``arm-none-eabi-gcc`` with :data:`~iotnav.firmware.host.WARN_FLAGS`, ``-O2``, the target's
    core flags, sections garbage-collected at link time.

    Raises
    ------
    KeyError
        Unknown ``target`` (see :data:`TARGETS`).
    RuntimeError
        When the toolchain is missing or the compilation fails.
    """
    t = TARGETS[target]
    cmd = [
        _tool("arm-none-eabi-gcc"),
        *WARN_FLAGS,
        "-O2",
        *t.cflags,
        "-ffunction-sections",
        "-fdata-sections",
    ]
    replay, lib = _ARM_SRC[engine]
    if library_only:
        cmd += ["-c", str(src / lib)]
    else:
        cmd += ["-nostartfiles", "-T", str(src / "arm" / "mps2.ld"), "-Wl,--gc-sections"]
        cmd += [str(src / f) for f in (*_ARM_RUNTIME, replay, lib)] + ["-lm"]
    _run([*cmd, "-o", str(out)])
    return out


def size(path: Path) -> tuple[int, int, int]:
    """``text``, ``data``, ``bss`` bytes of an object or ELF file (``arm-none-eabi-size``)."""
    line = _run([_tool("arm-none-eabi-size"), str(path)]).stdout.splitlines()[1].split()
    return int(line[0]), int(line[1]), int(line[2])


@dataclass(frozen=True)
class ArmRun:
    """What the replay program wrote (``outputs``: the bytes of ``replay_out.bin``) and printed."""

    outputs: bytes
    counts: dict[str, int]
    console: str


def run(elf: Path, target: str, inputs: bytes, timeout: float = 60.0) -> ArmRun:
    """Run ``elf`` on the target's QEMU board with ``inputs`` as ``replay_in.bin``.

    Raises
    ------
    RuntimeError
        When QEMU fails, the program reports an error or does not finish.
    """
    t = TARGETS[target]
    with tempfile.TemporaryDirectory() as d:
        wd = Path(d)
        (wd / "replay_in.bin").write_bytes(inputs)
        cmd = [_tool("qemu-system-arm"), "-M", t.machine, "-nographic", "-monitor", "none", "-serial", "none"]
        cmd += ["-semihosting-config", "enable=on,target=native", "-icount", f"shift={ICOUNT_SHIFT}"]
        res = _run([*cmd, "-kernel", str(elf)], cwd=wd, timeout=timeout)
        text = res.stdout + res.stderr
        if not re.search(r"^done$", text, re.M):
            raise RuntimeError(f"{elf} on {t.machine} did not finish:\n{text}")
        out = (wd / "replay_out.bin").read_bytes()
    counts = {m[1]: int(m[2]) for m in re.finditer(r"^(\w+) (\d+)$", text, re.M)}
    return ArmRun(out, counts, text)


def instructions(ticks: float) -> float:
    """Instructions executed for ``ticks`` SysTick counts under ``-icount shift=``:data:`ICOUNT_SHIFT`."""
    return float(ticks) * 1e9 / (2**ICOUNT_SHIFT * BOARD_CLOCK_HZ)


def decode_outputs(inputs: list[bytes], outputs: bytes) -> tuple[npt.NDArray[np.void], npt.NDArray[np.int32]]:
    """Split the replay output stream by the input records: ``anchor_output_t`` rows and GNSS return codes.

    Parameters
    ----------
    inputs : list of bytes
        The configuration, then ``b"I" + ...`` / ``b"G" + ...`` records.
    outputs : bytes
        What the program wrote for them.

    Raises
    ------
    ValueError
        When ``outputs`` does not hold exactly one result per record.
    """
    n_imu = sum(1 for r in inputs[1:] if r[:1] == b"I")
    n_gnss = len(inputs) - 1 - n_imu
    if len(outputs) != n_imu * OUTPUT_DTYPE.itemsize + 4 * n_gnss:
        raise ValueError(f"{len(outputs)} output bytes for {n_imu} IMU and {n_gnss} GNSS records")
    rows = np.empty(n_imu, OUTPUT_DTYPE)
    rcs = np.empty(n_gnss, np.int32)
    pos = i = j = 0
    for r in inputs[1:]:
        if r[:1] == b"I":
            rows[i] = np.frombuffer(outputs, OUTPUT_DTYPE, 1, pos)[0]
            pos += OUTPUT_DTYPE.itemsize
            i += 1
        else:
            rcs[j] = np.frombuffer(outputs, "<i4", 1, pos)[0]
            pos += 4
            j += 1
    return rows, rcs
