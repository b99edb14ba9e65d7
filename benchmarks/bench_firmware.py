"""Cost of the C anchor KF (firmware/) on an ATmega128 at 8 MHz, cycle-accurate under simavr (issue 20).

``firmware/host/cycles.c`` runs a fixed 10 s drive (100 Hz IMU steps, 1 Hz GNSS position +
velocity updates) through the library; built with ``avr-gcc -mmcu=atmega128 -Os`` it counts the
cycles of each call with Timer1 at the CPU clock and prints them on UART0, which ``simavr``
shows. The same driver built for the host with ``gcc`` gives the reference final state: the AVR
numbers count only if its final state equals the host float32 one (relative 1e-5; avr-libc's
``sin``/``cos`` differ from glibc's in the last bits). Flash and static RAM from ``avr-size``
(the library object alone and the whole program with avr-libc's float routines); the stack is
not measured. Needs the Debian packages ``gcc-avr avr-libc simavr``; with ``libsimavr-dev`` also
a cycle profile of the same build (``firmware/avr/profile.c``): per call, the cycles in avr-libc's
float routines and in the library's own instructions, and how many multiplications, additions,
divisions and comparisons it calls. Then the cycles of the Forno pipeline's blocks 3 and 4
(``firmware/host/cycles_pipeline.c``, checked against the host float32 build the same way).

Then the same library on a Cortex-M3 and a Cortex-M4F under ``qemu-system-arm``
(:mod:`iotnav.firmware.arm`; Debian ``gcc-arm-none-eabi libnewlib-arm-none-eabi
qemu-system-arm``): instructions per call, replaying the Python engine's inputs of a 60 s
scenario, its track checked against the host float32 build.

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
from typing import Any

import numpy as np

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


#: Assumed cycles per instruction of a Cortex-M3/M4 on this code (not measured: QEMU counts
#: instructions; most data-processing instructions take 1 cycle, loads and stores 2, taken
#: branches 2-4, per the Cortex-M3/M4 technical reference manuals; no flash wait states).
ASSUMED_CPI = 1.5
CORTEX_M3_HZ = 72e6  # the 72 MHz Cortex-M3


def _cortex_m() -> dict[str, Any]:
    """Instructions per call on the emulated Cortex-M3 and M4F for the test's replay (60 s car-tunnel)."""
    from iotnav import sim
    from iotnav.engines.anchor import AnchorConfig, AnchorEngine
    from iotnav.engines.base import iter_samples
    from iotnav.firmware import arm
    from iotnav.firmware import host as fw_host
    from iotnav.io import ingest

    with tempfile.TemporaryDirectory() as d:
        tmp = Path(d)
        sim.write(sim.build("car-tunnel", seed=1, overrides={"duration_s": 60.0}), tmp / "sim")
        cfg = AnchorConfig()
        fw = fw_host.AnchorFirmware(fw_host.build(tmp / "a.so"), cfg.kf, record=True)
        fw_host.run_beside(AnchorEngine(cfg), fw, iter_samples(ingest([tmp / "sim"])))
        inputs = b"".join(fw.inputs)
        host_rows, _ = arm.decode_outputs(fw.inputs, b"".join(fw.outputs))
        lines = [
            "## Firmware: anchor KF on Cortex-M3 and Cortex-M4F (qemu-system-arm)",
            "",
            "`benchmarks/bench_firmware.py`: `firmware/arm/replay.c` with the library, `arm-none-eabi-gcc -O2`, "
            "run on `qemu-system-arm -icount shift=6` (mps2-an385 Cortex-M3 soft float; mps2-an386 Cortex-M4F "
            "FPU), replaying the Python engine's inputs of the 60 s car-tunnel scenario (6000 IMU samples, "
            "1 Hz GNSS). QEMU does not model cycles and does not emulate the DWT cycle counter: SysTick under "
            "`-icount` counts instructions (checked on a loop of known length). Cycles below assume "
            f"{ASSUMED_CPI} cycles per instruction.",
            "",
            "| target | `anchor_step_imu` | `anchor_step_gnss` | `anchor_output` | instructions per second at "
            f"100 Hz IMU + 1 Hz GNSS | share of a 72 MHz Cortex-M3 at CPI {ASSUMED_CPI} | position vs host "
            "float32 build (max) |",
            "|---|---:|---:|---:|---:|---:|---:|",
        ]
        sizes = []
        state_bytes = 0
        for name in sorted(arm.TARGETS):
            run = arm.run(arm.build(tmp / f"{name}.elf", name), name, inputs)
            c = run.counts
            calib = arm.instructions(c["calib_ticks"]) / (2 * c["calib_loops"])
            if abs(calib - 1.0) > 1e-3:
                raise RuntimeError(f"{name}: SysTick is not counting instructions (ratio {calib:.4f})")
            rows, _ = arm.decode_outputs(fw.inputs, run.outputs)
            d_pos = float(np.abs(rows["r_n"].astype(float) - host_rows["r_n"]).max())

            def per(k: str, c: dict[str, int] = c) -> tuple[float, float]:
                return arm.instructions(c[k + "_sum"] / c[k + "_n"]), arm.instructions(c[k + "_max"])

            (imu, imu_mx), (gnss, gnss_mx), (out, out_mx) = per("imu"), per("gnss"), per("output")
            per_s = 100 * (imu + out) + gnss
            share = per_s * ASSUMED_CPI / CORTEX_M3_HZ
            lines.append(
                f"| {name} ({arm.TARGETS[name].machine}) | {imu:.0f} / {imu_mx:.0f} | {gnss:.0f} / {gnss_mx:.0f} | "
                f"{out:.0f} / {out_mx:.0f} | {per_s:.0f} | {100 * share:.2f} % | {d_pos:.1e} m |"
            )
            lib = arm.size(arm.build(tmp / f"{name}.o", name, library_only=True))
            prog = arm.size(tmp / f"{name}.elf")
            sizes.append(
                f"{name}: library `anchor.o` text {lib[0]} B (data {lib[1]} B, bss {lib[2]} B); whole test program "
                f"with newlib's libm text {prog[0]} B, data {prog[1]} B; stack high-water {c['stack_bytes']} B"
            )
            state_bytes = c["state_bytes"]
    lines += [
        "",
        "Instructions per call: mean / max over the replay (the GNSS column: updates after the first fix). "
        "Flash / RAM (`arm-none-eabi-size`; the stack measured by painting it before the replay): "
        + "; ".join(sizes)
        + f". RAM of the filter: one `anchor_state`, {state_bytes} B, plus that stack (the bss of the "
        "program is its reserved 16 KB stack and the state).",
        "",
    ]
    return {"lines": lines, "state_bytes": state_bytes}


#: What the ATmega128 profile counts per call: avr-libc's entry points (``__addsf3x`` also takes
#: the subtractions, ``__fp_cmp`` every comparison).
_PROFILE_OPS = {"mul": "__mulsf3x", "add/sub": "__addsf3x", "div": "__divsf3", "compare": "__fp_cmp"}


def _avr_profile(tmp: Path, elf: Path, lib_obj: Path) -> list[str]:
    """Per call of the three API functions: cycles in avr-libc's routines and in the library's own code.

    ``firmware/avr/profile.c`` (built against Debian's ``libsimavr-dev``) runs ``elf`` under
    simavr instruction by instruction and adds each instruction's cycles to its symbol while the
    function is active; the library's own symbols are those of ``lib_obj``. Returns markdown
    lines, or a line saying why there is no profile (the library missing).
    """
    exe = tmp / "profile"
    try:
        _run(
            ["gcc", "-O2", str(FW / "avr" / "profile.c"), "-I/usr/include/simavr", "-lsimavr", "-o", str(exe)]
        )
    except (RuntimeError, FileNotFoundError) as e:
        return [
            f"No cycle profile: `firmware/avr/profile.c` does not build here (needs `libsimavr-dev`): {e}"[
                :300
            ]
        ]
    syms = tmp / "cycles.sym"
    syms.write_text(_run(["avr-nm", "-n", str(elf)]))
    own = {
        ln.split()[-1]
        for ln in _run(["avr-nm", str(lib_obj)]).splitlines()
        if ln.split()[-2:-1] in (["T"], ["t"])
    }
    lines = [
        "Where the cycles go (`firmware/avr/profile.c` under libsimavr, cycles per call of the same build; "
        "avr-libc's float routines include their call and return):",
        "",
        "| call | cycles | in avr-libc float routines | in the library's own instructions | "
        + " | ".join(_PROFILE_OPS)
        + " |",
        "|---|---:|---:|---:|" + "---:|" * len(_PROFILE_OPS),
    ]
    for fn in ("anchor_step_imu", "anchor_step_gnss", "anchor_output"):
        text = re.sub(r"\x1b\[[0-9;]*m", "", _run([str(exe), str(elf), str(syms), fn], timeout=600))
        head = re.search(rf"^{fn}: (\d+) calls, (\d+) cycles per call$", text, re.M)
        if head is None:
            raise RuntimeError(f"profile of {fn} incomplete:\n{text[-2000:]}")
        rows = {
            m[3]: (float(m[1]), float(m[2]))
            for m in re.finditer(r"^\s+([\d.]+)\s+([\d.]+)  (\S+)$", text, re.M)
        }
        mine = sum(c for name, (c, _) in rows.items() if name in own)
        libc = sum(c for name, (c, _) in rows.items() if name not in own and not name.startswith("__vector"))
        ops = " | ".join(f"{rows.get(sym, (0.0, 0.0))[1]:.1f}" for sym in _PROFILE_OPS.values())
        lines.append(f"| `{fn}` | {head[2]} | {libc:.0f} | {mine:.0f} | {ops} |")
    lines += [
        "",
        "(`anchor_step_imu` and `anchor_step_gnss` are averaged over all their calls here, the first fix and "
        "the IMU step of a GNSS frame included.)",
    ]
    return lines


def _pipeline_avr(tmp: Path) -> list[str]:
    """Cycles of the Forno pipeline's blocks 3 and 4 on the ATmega128 (``firmware/host/cycles_pipeline.c``).

    The driver's final state under simavr must equal the host float32 build's (relative 1e-5).
    Returns markdown lines.
    """
    src = [
        str(FW / "host" / "cycles_pipeline.c"),
        str(FW / "pipeline_static.c"),
        str(FW / "pipeline_lowpass3.c"),
        str(FW / "pipeline_lastpos.c"),
        str(FW / "pipeline_gyrobias.c"),
        str(FW / "pipeline_tilt.c"),
    ]
    _run(["gcc", *FLAGS, "-O2", *src, "-lm", "-o", str(tmp / "pl_host")])
    host = _parse(_run([str(tmp / "pl_host")]))
    avr = ["avr-gcc", *FLAGS, "-Os", "-mmcu=atmega128", f"-DF_CPU={F_CPU}UL"]
    _run([*avr, *src, "-lm", "-o", str(tmp / "pl.elf")])
    out = _parse(_run(["simavr", "-m", "atmega128", "-f", str(F_CPU), str(tmp / "pl.elf")], timeout=600))
    keys = ["acc_h", "out0", "out1", "out2"]
    if "done" not in out or any(k not in out for k in keys):
        raise RuntimeError(f"simavr run of cycles_pipeline incomplete: {out}")
    worst = max(abs(_f32(out[k]) - _f32(host[k])) / max(abs(_f32(host[k])), 1e-6) for k in keys)
    counts = ["n_push", "n_changed", "n_static", "level"]
    if worst > 1e-5 or any(out[k] != host[k] for k in counts):
        raise RuntimeError(f"AVR pipeline state differs from the host float32 build (relative {worst:.2e})")
    objs = []
    for name in ("pipeline_static", "pipeline_lowpass3"):
        _run([*avr, "-c", str(FW / f"{name}.c"), "-o", str(tmp / f"{name}.o")])
        objs.append(f"`{name}.o` text {_size(tmp / f'{name}.o')[0]} B")

    def ms(c: int) -> str:
        return f"{c / F_CPU * 1e3:.2f}"

    return [
        "## Firmware: the Forno pipeline's blocks 3 and 4 on the ATmega128 at 8 MHz (simavr) and Cortex-M",
        "",
        "`firmware/host/cycles_pipeline.c` (130 s standing still with vibration: 100 Hz IMU, 1 Hz GNSS "
        "speed and position; blocks wired as the pipeline wires them) built with `avr-gcc -Os`, Timer1 "
        f"cycles under `simavr`; final state equal to the host float32 build (relative {worst:.1e}, the "
        f"same {out['n_push']} pushes, {out['n_changed']} new low-pass outputs, level {out['level']}).",
        "",
        "| call | cycles (mean / max) | ms at 8 MHz |",
        "|---|---:|---:|",
        f"| `pl_static_step` (block 3, every IMU sample) | {out['step_mean']} / {out['step_max']} | "
        f"{ms(out['step_mean'])} |",
        f"| `pl_static_update_speed` (every GNSS speed) | {out['speed_mean']} | {ms(out['speed_mean'])} |",
        f"| `pl_lowpass3_push` (block 4, every fix while static; the max a level-3 push) | {out['push_mean']} / "
        f"{out['push_max']} | {ms(out['push_mean'])} |",
        "",
        f"Flash (`avr-size`): {', '.join(objs)}; no data or bss. At 100 Hz, block 3 alone takes "
        f"{100 * out['step_mean'] / F_CPU * 100:.1f} % of the 8 MHz ATmega128.",
        "",
        *_pipeline_arm(tmp, host),
    ]


def _pipeline_arm(tmp: Path, host: dict[str, int]) -> list[str]:
    """Instructions per call of the Forno blocks 3 and 4 on the emulated Cortex-M3 and M4F.

    ``firmware/host/cycles_pipeline.c`` cross-compiled as the anchor's replay program is
    (:mod:`iotnav.firmware.arm`: its startup, semihosting and linker script) and run under
    ``qemu-system-arm -icount``; its final state must equal the host float32 build's ``host``.
    Returns markdown lines.
    """
    from iotnav.firmware import arm

    rows = []
    for name in sorted(arm.TARGETS):
        t = arm.TARGETS[name]
        elf = tmp / f"pl_{name}.elf"
        cmd = ["arm-none-eabi-gcc", *FLAGS, "-O2", *t.cflags, "-ffunction-sections", "-fdata-sections"]
        cmd += ["-nostartfiles", "-T", str(FW / "arm" / "mps2.ld"), "-Wl,--gc-sections"]
        cmd += [str(FW / f) for f in ("arm/startup.c", "arm/semihost.c", "host/cycles_pipeline.c")]
        cmd += [str(FW / f"pipeline_{b}.c") for b in ("static", "lowpass3", "lastpos", "gyrobias", "tilt")]
        cmd += ["-lm", "-o", str(elf)]
        _run(cmd)
        qemu = ["qemu-system-arm", "-M", t.machine, "-nographic", "-monitor", "none", "-serial", "none"]
        qemu += ["-semihosting-config", "enable=on,target=native", "-icount", f"shift={arm.ICOUNT_SHIFT}"]
        out = _parse(_run([*qemu, "-kernel", str(elf)]))
        if abs(arm.instructions(out["calib_ticks"]) / (2 * out["calib_loops"]) - 1.0) > 1e-3:
            raise RuntimeError(f"{name}: SysTick is not counting instructions")
        same = ["acc_h", "out0", "out1", "out2", "n_push", "n_changed", "n_static", "level"]
        if any(out[k] != host[k] for k in same):
            raise RuntimeError(f"{name}: final state of cycles_pipeline differs from the host float32 build")
        step, speed, push, push_mx = (
            arm.instructions(out[k]) for k in ("step_mean", "speed_mean", "push_mean", "push_max")
        )
        per_s = 100 * step + speed + push
        share = per_s * ASSUMED_CPI / CORTEX_M3_HZ
        rows.append(
            f"| {name} ({t.machine}) | {step:.0f} / {arm.instructions(out['step_max']):.0f} | {speed:.0f} | "
            f"{push:.0f} / {push_mx:.0f} | {per_s:.0f} | {100 * share:.2f} % | {out['stack_bytes']} B |"
        )
    return [
        "Cortex-M3 and Cortex-M4F (`qemu-system-arm -icount`, `arm-none-eabi-gcc -O2`, the same driver; "
        "instructions per call, final state bit-equal to the host float32 build):",
        "",
        "| target | `pl_static_step` | `pl_static_update_speed` | `pl_lowpass3_push` (mean / max) | "
        f"instructions per second at 100 Hz IMU + 1 Hz GNSS, static | share of a 72 MHz Cortex-M3 at CPI "
        f"{ASSUMED_CPI} | stack high-water of the driver |",
        "|---|---:|---:|---:|---:|---:|---:|",
        *rows,
        "",
    ]


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
        profile = _avr_profile(tmp, tmp / "cycles.elf", tmp / "anchor.o")
        pipeline = _pipeline_avr(tmp)
    keys = [f"x{i}" for i in range(6)] + ["p00", "p44"]
    if "done" not in out or any(k not in out for k in keys):
        raise RuntimeError(f"simavr run incomplete: {out}")
    worst = max(abs(_f32(out[k]) - _f32(host[k])) / max(abs(_f32(host[k])), 1e-6) for k in keys)
    if worst > 1e-5:
        raise RuntimeError(f"AVR final state differs from the host float32 build (relative {worst:.2e})")

    def ms(c: int) -> str:
        return f"{c / F_CPU * 1e3:.2f}"

    frame = out["gnss_mean"] + out["imu_mean"] + out["output_mean"]
    cortex = _cortex_m()
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
            f"| sum of the three means above | {frame} | {ms(frame)} | |",
            f"| frame with a GNSS epoch, measured (GNSS update, IMU step and output of that sample; the "
            "update predicts to the sample's time, so its IMU step does not predict again) | "
            f"{out['frame_mean']} / {out['frame_max']} | {ms(out['frame_mean'])} | frame 10.223 ms "
            "(issue 20 target: under 2 ms) |",
            "",
            f"Flash / RAM (`avr-size`): library object `anchor.o` text {lib_size[0]} B, data {lib_size[1]} B, "
            f"bss {lib_size[2]} B; whole driver with avr-libc float routines text {prog_size[0]} B, data "
            f"{prog_size[1]} B, bss {prog_size[2]} B. One `anchor_state` is {cortex['state_bytes']} B in float32 "
            "(on the stack of the driver, not in bss); stack use not measured on the AVR.",
            "",
            *profile,
            "",
            *cortex["lines"],
            *pipeline,
        ]
    )
    print(text)
    if os.environ.get("IOTNAV_WRITE_RESULTS") == "1":
        path = Path(__file__).parent / "results" / "firmware.md"
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(text)


if __name__ == "__main__":
    main()
