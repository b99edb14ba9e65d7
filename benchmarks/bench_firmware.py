"""Cost of the C anchor KF (firmware/) on an ATmega128 at 8 MHz, cycle-accurate under simavr (issue 20).

``firmware/host/cycles.c`` runs a fixed 10 s drive (100 Hz IMU steps, 1 Hz GNSS position +
velocity updates) through the library; built with ``avr-gcc -mmcu=atmega128 -Os`` it counts the
cycles of each call with Timer1 at the CPU clock and prints them on UART0, which ``simavr``
shows. The same driver built for the host with ``gcc`` gives the reference final state: the AVR
numbers count only if its final state equals the host float32 one (relative 1e-5; avr-libc's
``sin``/``cos`` differ from glibc's in the last bits). Flash and static RAM from ``avr-size``
(the library object alone and the whole program with avr-libc's float routines); the stack is
not measured. Needs the Debian packages ``gcc-avr avr-libc simavr``.

Prints a markdown snippet; with ``IOTNAV_WRITE_RESULTS=1`` also writes
``benchmarks/results/firmware.md``. Paper (ATmega128 at 8 MHz, logic analyser): Kalman filter
8 ms, IMU and GPS computation 1.7 ms, frame 10.223 ms.
"""

from __future__ import annotations

import os
import re
import struct
import subprocess
import tempfile
from pathlib import Path

FW = Path(__file__).resolve().parents[1] / "firmware"
F_CPU = 8_000_000
FLAGS = ["-std=c99", "-Wall", "-Wextra", "-Werror", "-pedantic"]


def _run(cmd: list[str], timeout: float = 120.0) -> str:
    res = subprocess.run(cmd, capture_output=True, text=True, check=False, timeout=timeout)
    if res.returncode != 0:
        raise RuntimeError(f"{' '.join(cmd)} failed ({res.returncode}):\n{res.stdout}\n{res.stderr}")
    return res.stdout + res.stderr


def _parse(text: str) -> dict[str, int]:
    """``key number`` lines of the driver (simavr adds colour codes and a dot); ``done`` -> 1."""
    text = re.sub(r"\x1b\[[0-9;]*m", "", text)
    out = {m[1]: int(m[2]) for m in re.finditer(r"^(\w+) (\d+)\.?$", text, re.M)}
    if re.search(r"^done\.?$", text, re.M):
        out["done"] = 1
    return out


def _size(path: Path) -> tuple[int, int, int]:
    line = _run(["avr-size", str(path)]).splitlines()[1].split()
    return int(line[0]), int(line[1]), int(line[2])


def _f32(bits: int) -> float:
    return float(struct.unpack("<f", struct.pack("<I", bits))[0])


def main() -> None:
    with tempfile.TemporaryDirectory() as d:
        tmp = Path(d)
        src = [str(FW / "host" / "cycles.c"), str(FW / "anchor.c")]
        _run(["gcc", *FLAGS, "-O2", *src, "-lm", "-o", str(tmp / "host")])
        host = _parse(_run([str(tmp / "host")]))
        avr = ["avr-gcc", *FLAGS, "-Os", "-mmcu=atmega128", f"-DF_CPU={F_CPU}UL"]
        _run([*avr, *src, "-lm", "-o", str(tmp / "cycles.elf")])
        _run([*avr, "-c", str(FW / "anchor.c"), "-o", str(tmp / "anchor.o")])
        out = _parse(
            _run(["simavr", "-m", "atmega128", "-f", str(F_CPU), str(tmp / "cycles.elf")], timeout=600)
        )
        lib_size, prog_size = _size(tmp / "anchor.o"), _size(tmp / "cycles.elf")
    keys = [f"x{i}" for i in range(6)] + ["p00", "p44"]
    if "done" not in out or any(k not in out for k in keys):
        raise RuntimeError(f"simavr run incomplete: {out}")
    worst = max(abs(_f32(out[k]) - _f32(host[k])) / max(abs(_f32(host[k])), 1e-6) for k in keys)
    if worst > 1e-5:
        raise RuntimeError(f"AVR final state differs from the host float32 build (relative {worst:.2e})")

    def ms(c: int) -> str:
        return f"{c / F_CPU * 1e3:.2f}"

    frame = out["gnss_mean"] + out["imu_mean"] + out["output_mean"]
    text = "\n".join(
        [
            "## Firmware: anchor KF on the ATmega128 at 8 MHz (simavr)",
            "",
            "`benchmarks/bench_firmware.py`: `firmware/host/cycles.c` (10 s drive, 100 Hz IMU, 1 Hz GNSS "
            "position + 3D velocity) built with `avr-gcc -Os -mmcu=atmega128`, cycles from Timer1 under "
            f"`simavr`; final state equal to the host float32 build (worst relative difference {worst:.1e}).",
            "",
            "| call | cycles (mean / max) | ms at 8 MHz | paper (ATmega128, 8 MHz) |",
            "|---|---:|---:|---|",
            f"| `anchor_step_imu` (predict + control input) | {out['imu_mean']} / {out['imu_max']} | "
            f"{ms(out['imu_mean'])} | |",
            f"| `anchor_step_gnss` (position + velocity update) | {out['gnss_mean']} / {out['gnss_max']} | "
            f"{ms(out['gnss_mean'])} | Kalman filter 8 ms |",
            f"| `anchor_output` | {out['output_mean']} | {ms(out['output_mean'])} | |",
            f"| frame with a GNSS epoch (the three above) | {frame} | {ms(frame)} | frame 10.223 ms "
            "(target: under 2 ms) |",
            "",
            f"Flash / RAM (`avr-size`): library object `anchor.o` text {lib_size[0]} B, data {lib_size[1]} B, "
            f"bss {lib_size[2]} B; whole driver with avr-libc float routines text {prog_size[0]} B, data "
            f"{prog_size[1]} B, bss {prog_size[2]} B. One `anchor_state` is 336 B (x86-64 float32; on the stack "
            "of the driver, not in bss); stack use not measured.",
            "",
        ]
    )
    print(text)
    if os.environ.get("IOTNAV_WRITE_RESULTS") == "1":
        path = Path(__file__).parent / "results" / "firmware.md"
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(text)


if __name__ == "__main__":
    main()
