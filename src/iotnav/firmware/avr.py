"""Build the firmware's anchor KF for the ATmega128 and run it under ``simavr``.

The library (``firmware/anchor.c``) is compiled with ``avr-gcc -Os -mmcu=atmega128`` (Debian
``gcc-avr`` + ``avr-libc``) with the test program ``firmware/avr/replay.c`` and a stream of
recorded inputs compiled into flash (:func:`stream_source`; the ATmega128's 4 KB of RAM cannot
hold it, and an AVR object is at most 32 KB), and run on ``simavr`` (cycle-accurate). The stream
is :class:`~iotnav.firmware.host.AnchorFirmware`'s (``record=True``): every member of the structs
is four bytes, little-endian, so the AVR and the host read it alike. The program prints each
result in hex on UART0, which simavr shows on its console.
"""

from __future__ import annotations

import re
import shutil
import subprocess
import tempfile
from pathlib import Path

import numpy as np
import numpy.typing as npt

from iotnav.firmware.arm import OUTPUT_DTYPE
from iotnav.firmware.host import FIRMWARE_DIR, WARN_FLAGS

__all__ = ["F_CPU", "MAX_STREAM_BYTES", "build", "run", "stream_source"]

#: Clock of the anchor-node paper's ATmega128, Hz.
F_CPU = 8_000_000
#: Largest stream one AVR array holds (its size_t is 16 bits; objects stop at 32767 bytes).
MAX_STREAM_BYTES = 32_767


def _tool(name: str) -> str:
    path = shutil.which(name)
    if path is None:
        raise RuntimeError(f"{name} not found: install the Debian packages gcc-avr, avr-libc and simavr")
    return path


def stream_source(stream: bytes) -> str:
    """C source defining ``anchor_stream`` (in flash) and ``anchor_stream_len`` for ``stream``.

    Raises
    ------
    ValueError
        When ``stream`` exceeds :data:`MAX_STREAM_BYTES`.
    """
    if len(stream) > MAX_STREAM_BYTES:
        raise ValueError(f"{len(stream)} bytes: an AVR array holds at most {MAX_STREAM_BYTES}")
    rows = [",".join(str(b) for b in stream[i : i + 32]) for i in range(0, len(stream), 32)]
    return "\n".join(
        [
            "#include <avr/pgmspace.h>",
            "#include <stdint.h>",
            "const uint8_t anchor_stream[] PROGMEM = {",
            ",\n".join(rows),
            "};",
            f"const uint16_t anchor_stream_len = {len(stream)}u;",
            "",
        ]
    )


def build(out: Path, stream: bytes, src: Path = FIRMWARE_DIR) -> Path:
    """Compile ``avr/replay.c``, the library and ``stream`` (:func:`stream_source`) into the ELF ``out``.

    Raises
    ------
    RuntimeError
        When the toolchain is missing or the compilation fails.
    """
    data = out.with_suffix(".stream.c")
    data.write_text(stream_source(stream))
    cmd = [_tool("avr-gcc"), *WARN_FLAGS, "-Os", "-mmcu=atmega128", f"-DF_CPU={F_CPU}UL"]
    cmd += [str(src / "avr" / "replay.c"), str(src / "anchor.c"), str(data), "-lm", "-o", str(out)]
    res = subprocess.run(cmd, capture_output=True, text=True, check=False)
    if res.returncode != 0:
        raise RuntimeError(f"{' '.join(cmd)} failed:\n{res.stderr}")
    return out


def run(elf: Path, timeout: float = 120.0) -> tuple[npt.NDArray[np.void], npt.NDArray[np.int32]]:
    """Run ``elf`` on simavr's ATmega128 at :data:`F_CPU`: the ``anchor_output_t`` rows and GNSS return codes.

    Raises
    ------
    RuntimeError
        When simavr fails or the program does not print ``done``.
    """
    with tempfile.TemporaryDirectory() as d:
        res = subprocess.run(
            [_tool("simavr"), "-m", "atmega128", "-f", str(F_CPU), str(elf)],
            capture_output=True,
            text=True,
            check=False,
            timeout=timeout,
            cwd=d,
        )
    text = re.sub(r"\x1b\[[0-9;]*m", "", res.stdout + res.stderr)
    lines = [m[1] for m in re.finditer(r"^([OGd][0-9a-fone]*)\.?$", text, re.M)]
    if not lines or lines[-1] != "done":
        raise RuntimeError(f"{elf} under simavr did not finish ({res.returncode}):\n{text[-2000:]}")
    outs = [bytes.fromhex(ln[1:]) for ln in lines if ln[0] == "O"]
    rcs = [int.from_bytes(bytes.fromhex(ln[1:]), "little", signed=True) for ln in lines if ln[0] == "G"]
    rows = np.frombuffer(b"".join(outs), OUTPUT_DTYPE) if outs else np.empty(0, OUTPUT_DTYPE)
    return rows, np.array(rcs, np.int32)
