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
divisions and comparisons it calls. Then the cycles of the Forno pipeline's ported blocks (1, 3,
4 and block 2's gyro-bias, tilt and yaw KFs: ``firmware/host/cycles_pipeline.c``, checked against
the host float32 build the same way).

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
import tempfile
from pathlib import Path
from typing import Any

import numpy as np

from iotnav.firmware import targets as tg

FW = Path(__file__).resolve().parents[1] / "firmware"
F_CPU = 8_000_000
FLAGS = ["-std=c99", "-Wall", "-Wextra", "-Werror", "-pedantic"]


def _run(cmd: list[str], timeout: float = 120.0) -> str:
    return tg.run(cmd, timeout=timeout)


#: ``key number`` lines of a driver (:func:`iotnav.firmware.targets.parse`).
_parse = tg.parse


def _size(path: Path) -> tuple[int, int, int]:
    line = _run(["avr-size", str(path)]).splitlines()[1].split()
    return int(line[0]), int(line[1]), int(line[2])


_f32 = tg.f32


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


def _avr_profile(
    tmp: Path,
    elf: Path,
    lib_obj: Path | list[Path],
    fns: tuple[str, ...] = ("anchor_step_imu", "anchor_step_gnss", "anchor_output"),
    mcu: str = "atmega128",
    ops_out: dict[str, dict[str, float]] | None = None,
) -> list[str]:
    """Per call of ``fns`` (default: the anchor's three API functions): cycles in avr-libc's
    routines and in the library's own code.

    ``firmware/avr/profile.c`` (built against Debian's ``libsimavr-dev``) runs ``elf`` under
    simavr (core ``mcu``) instruction by instruction and adds each instruction's cycles to its
    symbol while the function is active; the library's own symbols are those of ``lib_obj`` (one
    object or several). Returns markdown lines, or a line saying why there is no profile (the
    library missing); with ``ops_out``, also fills it with the operations per call of each function.
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
        for obj in (lib_obj if isinstance(lib_obj, list) else [lib_obj])
        for ln in _run(["avr-nm", str(obj)]).splitlines()
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
    for fn in fns:
        text = re.sub(r"\x1b\[[0-9;]*m", "", _run([str(exe), str(elf), str(syms), fn, mcu], timeout=600))
        head = re.search(rf"^{fn}: (\d+) calls, (\d+) cycles per call$", text, re.M)
        if head is None:
            raise RuntimeError(f"profile of {fn} incomplete:\n{text[-2000:]}")
        rows = {
            m[3]: (float(m[1]), float(m[2]))
            for m in re.finditer(r"^\s+([\d.]+)\s+([\d.]+)  (\S+)$", text, re.M)
        }
        mine = sum(c for name, (c, _) in rows.items() if name in own)
        libc = sum(c for name, (c, _) in rows.items() if name not in own and not name.startswith("__vector"))
        ops = {op: rows.get(sym, (0.0, 0.0))[1] for op, sym in _PROFILE_OPS.items()}
        if ops_out is not None:
            ops_out[fn] = ops
        lines.append(
            f"| `{fn}` | {head[2]} | {libc:.0f} | {mine:.0f} | "
            + " | ".join(f"{v:.1f}" for v in ops.values())
            + " |"
        )
    if fns[0] == "anchor_step_imu":
        lines += [
            "",
            "(`anchor_step_imu` and `anchor_step_gnss` are averaged over all their calls here, the first fix and "
            "the IMU step of a GNSS frame included.)",
        ]
    return lines


#: The ported Forno pipeline blocks (``firmware/pipeline_*.c``), in the pipeline's order.
PIPELINE_BLOCKS = ("lastpos", "gyrobias", "tilt", "yaw", "static", "lowpass3")
#: The driver's final state that must equal the host float32 build (float32 bit patterns, counts).
_PL_STATE = [
    "acc_h",
    "out0",
    "out1",
    "out2",
    "bias0",
    "bias_p00",
    "tilt0",
    "tilt_p01",
    "yaw0",
    "yaw_p01",
    "c5",
]
_PL_COUNTS = ["n_push", "n_changed", "n_static", "level", "n_ok", "n_due", "n_bias_updates"]
_PL_COUNTS += ["n_tilt_updates", "n_yaw_updates"]
#: Per call of ``host/cycles_pipeline.c``: the key of its mean (and max), the description, and how
#: often the pipeline calls it per second at 100 Hz IMU and 1 Hz GNSS (the driver stands still:
#: block 4 and the bias update run at every fix / sample, their worst case).
_PL_CALLS = [
    ("fix", "block 1: `pl_lastpos_check_fix` + first fix + `pl_lastpos_due`, per fix", 1),
    ("bias_predict", "block 2: `pl_gyrobias_predict`, every IMU sample", 100),
    ("bias_update", "block 2: `pl_gyrobias_update`, every static IMU sample", 100),
    ("tilt_predict", "block 2: `pl_tilt_predict`, every IMU sample", 100),
    ("tilt_update", "block 2: `pl_tilt_update`, every IMU sample", 100),
    ("yaw_predict", "block 2: `pl_yaw_predict`, every IMU sample", 100),
    ("yaw_update", "block 2: `pl_yaw_update_heading` (course aid), every GNSS epoch", 1),
    (
        "dcm",
        "block 2, the cascade's wiring: `pl_dcm_rows` (C_nb from the tilt and yaw rows), every IMU sample",
        100,
    ),
    ("step", "block 3: `pl_static_step`, every IMU sample", 100),
    ("speed", "block 3: `pl_static_update_speed`, every GNSS speed", 1),
    ("push", "block 4: `pl_lowpass3_push`, every fix while static (the max: a level-3 push)", 1),
]


#: ``firmware/host/cycles_pipeline.c`` and the sources of the blocks it drives (under ``firmware/``).
_PL_SOURCES = ("host/cycles_pipeline.c", *(f"pipeline_{b}.c" for b in PIPELINE_BLOCKS))


def _pl_state_equal(out: dict[str, int], host: dict[str, int], rel: float) -> float:
    """Worst relative difference of the driver's final state from the host float32 build's
    (:func:`iotnav.firmware.targets.check`); raises when a count differs or the state differs by
    more than ``rel``."""
    return max(tg.check(out, host, dict.fromkeys(_PL_STATE, ("rel", rel)), _PL_COUNTS).values())


def _mean_max(out: dict[str, int], key: str) -> tuple[int, int | None]:
    return out[f"{key}_mean"], out.get(f"{key}_max")


def _pipeline_avr(tmp: Path) -> list[str]:
    """Cycles of the ported Forno pipeline blocks on the ATmega128 (``firmware/host/cycles_pipeline.c``).

    The driver's final state under simavr must equal the host float32 build's (relative 1e-5, the
    same counts). Returns markdown lines.
    """
    host = tg.parse(tg.run([str(tg.build_host(tmp / "pl_host", _PL_SOURCES))]))
    avr = tg.avr_flags()
    out = tg.run_avr(tg.build_avr(tmp / "pl.elf", _PL_SOURCES), timeout=1200)
    worst = _pl_state_equal(out, host, 1e-5)
    objs, text_sum = [], 0
    for name in PIPELINE_BLOCKS:
        _run([*avr, "-c", str(FW / f"pipeline_{name}.c"), "-o", str(tmp / f"pipeline_{name}.o")])
        text, data, bss = _size(tmp / f"pipeline_{name}.o")
        text_sum += text
        objs.append(
            f"`pipeline_{name}.o` text {text} B" + (f", data {data} B, bss {bss} B" if data or bss else "")
        )
    prog = _size(tmp / "pl.elf")
    ram = sum(out[f"sizeof_{b}"] for b in PIPELINE_BLOCKS)

    def ms(c: float) -> str:
        return f"{c / F_CPU * 1e3:.2f}"

    rows, per_s = [], 0.0
    for key, what, rate in _PL_CALLS:
        mean, mx = _mean_max(out, key)
        per_s += rate * mean
        cyc = f"{mean}" + (f" / {mx}" if mx is not None else "")
        rows.append(f"| {what} | {cyc} | {ms(mean)} |")
    return [
        "## Firmware: the Forno pipeline's ported blocks on the ATmega128 at 8 MHz (simavr) and Cortex-M",
        "",
        "`firmware/host/cycles_pipeline.c` (130 s standing still with vibration: 100 Hz IMU, 1 Hz GNSS "
        "speed, position, PDOP converging from 6 to 2, a heading; blocks 1, 3 and 4 and block 2's gyro-bias, "
        "tilt and yaw KFs wired as the pipeline and the cascade wire them; not blocks 5 and 6) built "
        f"with `avr-gcc -Os`, Timer1 cycles under `simavr`; final state equal to the host float32 build "
        f"(relative {worst:.1e}; the same {out['n_push']} pushes, {out['n_changed']} new low-pass outputs, "
        f"level {out['level']}, {out['n_ok']} fixes accepted, {out['n_bias_updates']} bias, "
        f"{out['n_tilt_updates']} tilt and {out['n_yaw_updates']} yaw updates).",
        "",
        "| call | cycles (mean / max) | ms at 8 MHz |",
        "|---|---:|---:|",
        *rows,
        "",
        f"All of them at 100 Hz IMU and 1 Hz GNSS: {per_s:.0f} cycles per second, **{100 * per_s / F_CPU:.0f} % "
        "of the 8 MHz ATmega128** (soft float; above 100 % the ported blocks alone do not fit at 100 Hz). "
        f"Flash (`avr-size`): {', '.join(objs)}; {text_sum} B in all; the whole driver with avr-libc's float "
        f"routines text {prog[0]} B, data {prog[1]} B, bss {prog[2]} B. RAM of the states (float32): "
        + ", ".join(f"`pl_{b}_state` {out[f'sizeof_{b}']} B" for b in PIPELINE_BLOCKS)
        + f"; {ram} B in all, plus the stack (not measured on the AVR).",
        "",
        *_pipeline_arm(tmp, host),
    ]


def _pipeline_arm(tmp: Path, host: dict[str, int]) -> list[str]:
    """Instructions per call of the ported Forno blocks on the emulated Cortex-M3 and M4F.

    ``firmware/host/cycles_pipeline.c`` cross-compiled as the anchor's replay program is
    (:mod:`iotnav.firmware.arm`: its startup, semihosting and linker script) and run under
    ``qemu-system-arm -icount``; its final state must equal the host float32 build's ``host``
    bit for bit. Returns markdown lines.
    """
    from iotnav.firmware import arm

    head = "| call | " + " | ".join(f"{n} ({arm.TARGETS[n].machine})" for n in sorted(arm.TARGETS)) + " |"
    cols: dict[str, dict[str, int]] = {}
    worsts: dict[str, float] = {}
    sizes = []
    for name in sorted(arm.TARGETS):
        base = tg.arm_flags(name)
        out = tg.run_arm(tg.build_arm(tmp / f"pl_{name}.elf", name, _PL_SOURCES), name)
        # newlib's sinf / cosf / asinf / atan2f (the yaw KF) are not glibc's: not bit-equal there
        worsts[name] = _pl_state_equal(out, host, 1e-5)
        cols[name] = out
        text_sum = 0
        for b in PIPELINE_BLOCKS:
            obj = tmp / f"pl_{name}_{b}.o"
            _run([*base, "-c", str(FW / f"pipeline_{b}.c"), "-o", str(obj)])
            text_sum += arm.size(obj)[0]
        sizes.append(
            f"{name}: the six objects text {text_sum} B (no data or bss), driver stack {out['stack_bytes']} B"
        )
    rows, per_s = [], dict.fromkeys(cols, 0.0)
    for key, what, rate in _PL_CALLS:
        cells = []
        for name, out in cols.items():
            mean = arm.instructions(out[f"{key}_mean"])
            per_s[name] += rate * mean
            mx = out.get(f"{key}_max")
            cells.append(f"{mean:.0f}" + (f" / {arm.instructions(mx):.0f}" if mx is not None else ""))
        rows.append(f"| {what} | " + " | ".join(cells) + " |")
    rows.append(
        "| **instructions per second, all at 100 Hz IMU + 1 Hz GNSS** | "
        + " | ".join(f"{v:.0f}" for v in per_s.values())
        + " |"
    )
    rows.append(
        f"| share of the core at 72 MHz, CPI {ASSUMED_CPI} (assumed) | "
        + " | ".join(f"{100 * v * ASSUMED_CPI / CORTEX_M3_HZ:.2f} %" for v in per_s.values())
        + " |"
    )
    return [
        "Cortex-M3 and Cortex-M4F (`qemu-system-arm -icount`, `arm-none-eabi-gcc -O2`, the same driver; "
        "instructions per call, mean / max; final state equal to the host float32 build, the same counts, "
        "the float32 state within relative "
        + ", ".join(f"{v:.1e} ({k})" for k, v in worsts.items())
        + " of it: newlib's `sinf`, `cosf`, `asinf`, `atan2f` in the yaw KF are not glibc's):",
        "",
        head,
        "|---|" + "---:|" * len(cols),
        *rows,
        "",
        "Flash (`arm-none-eabi-size`): " + "; ".join(sizes) + ".",
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
