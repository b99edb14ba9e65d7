"""Cost of the whole wired Forno pipeline in C (``firmware/pipeline.c``, blocks 1-6) on the emulated targets (issue 20).

``firmware/host/cycles_pipeline_wired.c`` (90 s of a car with the sensor mounted 0.5 rad off its
axis, two static periods, 100 Hz IMU, 1 Hz GNSS; the pipeline's configuration
``PL_PIPELINE_CONFIG_DEFAULTS``; see its header) is built for the host (float32: the golden final
state) and for each target; a target's counts are reported only when its final state passes
:func:`iotnav.firmware.pipeline_engine.check_cost_run` (the same events, sources and counts; the
reals within 1 mm / 1e-5 rad of the host build):

* Cortex-M3 (soft float, ``mps2-an385``) and Cortex-M4F (FPU, ``mps2-an386``) under
  ``qemu-system-arm -icount``: instructions per call (:func:`iotnav.firmware.arm.instructions`);
  the load at 100 Hz IMU and 1 Hz GNSS on the issue's 72 MHz Cortex-M3 at an assumed CPI
  (:data:`bench_firmware.ASSUMED_CPI`: QEMU gives no cycles).
* ATmega1284P at 8 MHz (``avr-gcc -Os``, ``simavr``, Timer1 cycles; the ATmega128's 4 KB of SRAM
  cannot hold the pipeline's state: the link is tried and reported).

Flash: ``*-size`` of the library's objects and of the whole driver (with libm / soft float, the
startup and the driver); RAM: ``sizeof(pl_state)`` and the driver's measured stack high-water mark.
Issue 20's target: the whole pipeline in 64 KB of flash and 16 KB of RAM, under 10 % of a 72 MHz
Cortex-M3 at 100 Hz IMU and 1 Hz GNSS.

Prints markdown; with ``IOTNAV_WRITE_RESULTS=1`` writes ``benchmarks/results/firmware_pipeline.md``.
"""

from __future__ import annotations

import os
import sys
import tempfile
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

from bench_firmware import ASSUMED_CPI, CORTEX_M3_HZ, _size
from iotnav.firmware import arm
from iotnav.firmware import targets as tg
from iotnav.firmware.avr import F_CPU
from iotnav.firmware.host import FIRMWARE_DIR
from iotnav.firmware.pipeline_engine import COST_SOURCES, SOURCES, check_cost_run

FLASH_BUDGET, RAM_BUDGET, LOAD_BUDGET = 64 * 1024, 16 * 1024, 0.10
#: Per call of the driver: key, description, calls per second at 100 Hz IMU and 1 Hz GNSS.
CALLS = [
    ("imu", "`pl_step_imu` (blocks 2, 3, 5's sums, 6's predict), every IMU sample", 100),
    ("output", "`pl_output` (geodetic position, roll / pitch / yaw), every IMU sample", 100),
    ("gnss", "`pl_step_gnss` (blocks 1, 3, 2's aid, 5, 4 or 6's updates), every GNSS epoch", 1),
    ("gnss_buffer", "`pl_step_gnss` of the epochs that evaluate a block-5 buffer (1 in 8)", 0),
]


def _lib_size(tmp: Path, flags: list[str], size: object) -> tuple[int, int, int]:
    tot = [0, 0, 0]
    for s in SOURCES:
        obj = tmp / (Path(s).stem + ".o")
        tg.run([*flags, "-c", str(FIRMWARE_DIR / s), "-o", str(obj)])
        for i, v in enumerate(size(obj)):  # type: ignore[operator]
            tot[i] += v
    return tot[0], tot[1], tot[2]


def _arm(tmp: Path, host: dict[str, int]) -> list[str]:
    cols, lines, load = {}, [], {}
    for name in sorted(arm.TARGETS):
        elf = tg.build_arm(tmp / f"{name}.elf", name, COST_SOURCES)
        out = tg.run_arm(elf, name)
        d = check_cost_run(out, host)
        lib = _lib_size(tmp, tg.arm_flags(name), arm.size)
        whole = arm.size(elf)
        cols[name] = (out, max(d.values()), lib, whole)
    rows = []
    for key, what, _ in CALLS:
        cells = [
            f"{arm.instructions(o[f'{key}_mean']):.0f} / {arm.instructions(o[f'{key}_max']):.0f}"
            for o, *_ in cols.values()
        ]
        rows.append(f"| {what} | " + " | ".join(cells) + " |")
    for name, (o, *_) in cols.items():
        load[name] = sum(rate * arm.instructions(o[f"{k}_mean"]) for k, _, rate in CALLS)
    rows.append(
        "| **instructions per second at 100 Hz IMU + 1 Hz GNSS (IMU step, output, GNSS)** | "
        + " | ".join(f"{v:.0f}" for v in load.values())
        + " |"
    )
    m3 = load["cortex-m3"]
    pct = 100 * m3 * ASSUMED_CPI / CORTEX_M3_HZ
    pct_no_out = (
        100 * (m3 - 100 * arm.instructions(cols["cortex-m3"][0]["output_mean"])) * ASSUMED_CPI / CORTEX_M3_HZ
    )
    pct_cpi1 = 100 * m3 / CORTEX_M3_HZ
    o3, d3, lib3, whole3 = cols["cortex-m3"]
    flash3 = whole3[0] + whole3[1]
    ram3 = o3["sizeof_state"] + o3["stack_bytes"]
    lines += [
        "## Firmware: the whole wired pipeline on Cortex-M3 / Cortex-M4F (qemu-system-arm -icount)",
        "",
        "`benchmarks/bench_firmware_pipeline.py`: `firmware/host/cycles_pipeline_wired.c` (90 s car drive, "
        "sensor mounted 0.5 rad off the vehicle axis, a start from rest and a 10 s stop, 100 Hz IMU, 1 Hz GNSS "
        "with hAcc / sAcc and NED velocity; the pipeline's `PL_PIPELINE_CONFIG_DEFAULTS` = `PipelineConfig()`) "
        "built with `arm-none-eabi-gcc -O2`, run under `qemu-system-arm -icount shift=6` (instructions, "
        "deterministic, not load-dependent). Golden check: each target's final state equals the host "
        f"float32 build's (the same {o3['n_imu']} IMU steps and {o3['n_gnss']} fixes, {o3['ev_mount']} mount "
        f"estimates (mount known: {o3['mount_known']}, angle {tg.f32(o3['mount_yaw']):.4f} rad against 0.5), "
        f"{o3['ev_static_start']} static periods, every source count the same; largest real difference "
        + ", ".join(f"{n} {c[1]:.1e}" for n, c in cols.items())
        + "; tolerances `iotnav.firmware.pipeline_engine.COST_REALS`).",
        "",
        "| call | Cortex-M3 instructions (mean / max) | Cortex-M4F instructions (mean / max) |",
        "|---|---:|---:|",
        *rows,
        "",
        f"Issue 20's target on the 72 MHz Cortex-M3 at 100 Hz IMU and 1 Hz GNSS, at an assumed "
        f"{ASSUMED_CPI} cycles per instruction (an assumption: QEMU counts instructions; most Cortex-M3 "
        "instructions take one cycle, loads two, taken branches two to four, no flash wait states): "
        f"**{pct:.1f} % of the core** ({pct_no_out:.1f} % without `pl_output` at every sample, "
        f"{pct_cpi1:.1f} % at one cycle per instruction): "
        + ("**met**" if pct < 100 * LOAD_BUDGET else "**not met** (budget 10 %)")
        + f". Cortex-M4F (FPU): {100 * load['cortex-m4f'] * ASSUMED_CPI / CORTEX_M3_HZ:.2f} % of a 72 MHz core.",
        "",
        "Flash and RAM (`arm-none-eabi-size`, `-O2 -ffunction-sections`, linked with `--gc-sections`):",
        "",
        "| | Cortex-M3 | Cortex-M4F |",
        "|---|---:|---:|",
        "| library objects (`pipeline.c` and the blocks), text / data / bss | "
        + " | ".join(f"{c[2][0]} / {c[2][1]} / {c[2][2]} B" for c in cols.values())
        + " |",
        "| whole driver program (library, libm and soft-float routines, startup, driver), text + data | "
        + " | ".join(f"{c[3][0] + c[3][1]} B" for c in cols.values())
        + " |",
        "| RAM: `sizeof(pl_state)` + measured stack high-water mark | "
        + " | ".join(
            f"{c[0]['sizeof_state']} + {c[0]['stack_bytes']} = {c[0]['sizeof_state'] + c[0]['stack_bytes']} B"
            for c in cols.values()
        )
        + " |",
        "",
        f"Against the 64 KB flash / 16 KB RAM budget (Cortex-M3): flash {flash3} B "
        + ("fits" if flash3 <= FLASH_BUDGET else "**does not fit**")
        + f", RAM {ram3} B "
        + ("fits" if ram3 <= RAM_BUDGET else "**does not fit**")
        + " (the driver's own `.bss` is its stack region in `arm/mps2.ld`, not counted). "
        f"`pl_state` holds a copy of its configuration ({o3['sizeof_config']} B).",
        "",
    ]
    del d3, lib3
    return lines


def _avr(tmp: Path) -> list[str]:
    try:
        tg.build_avr(tmp / "pl128.elf", COST_SOURCES)
        on128 = "links"
    except RuntimeError as e:
        msg = [ln for ln in str(e).splitlines() if "not within region" in ln]
        on128 = "does not link: " + (msg[0].split("ld: ")[-1] if msg else str(e)[:200])
        on128 = on128.replace(f"{tmp}/", "")
    host = tg.parse(tg.run([str(tg.build_host(tmp / "host_avr", COST_SOURCES))]))
    elf = tg.build_avr(tmp / "pl1284.elf", COST_SOURCES, mcu="atmega1284p")
    out = tg.run_avr(elf, timeout=1200.0, mcu="atmega1284p")
    d = check_cost_run(out, host)
    text, data, bss = _size(elf)
    lib = _lib_size(tmp, tg.avr_flags("atmega1284p"), _size)

    def ms(c: float) -> str:
        return f"{c / F_CPU * 1e3:.2f}"

    rows = [
        f"| {what} | {out[f'{k}_mean']} / {out[f'{k}_max']} | {ms(out[f'{k}_mean'])} / {ms(out[f'{k}_max'])} |"
        for k, what, _ in CALLS
    ]
    per_s = sum(rate * out[f"{k}_mean"] for k, _, rate in CALLS)
    return [
        "## Firmware: the whole wired pipeline on an 8 MHz AVR (simavr)",
        "",
        f"The same driver with `avr-gcc -Os`. On the ATmega128 (4 KB SRAM) it {on128}. On the ATmega1284P "
        "(same AVR core and instruction timings, 16 KB SRAM), Timer1 cycles at 8 MHz; golden check against "
        f"the host float32 build passed (largest real difference {max(d.values()):.1e}).",
        "",
        "| call | cycles (mean / max) | ms at 8 MHz (mean / max) |",
        "|---|---:|---:|",
        *rows,
        "",
        f"At 100 Hz IMU and 1 Hz GNSS: {per_s:.0f} cycles per second, **{100 * per_s / F_CPU:.0f} % of the "
        "8 MHz core**: the pipeline does not run at 100 Hz on an 8 MHz AVR in soft float. Flash: library "
        f"objects text {lib[0]} B, whole program text {text} B + data {data} B; RAM: data {data} B + bss "
        f"{bss} B + stack {out['stack_bytes']} B = {data + bss + out['stack_bytes']} B.",
        "",
    ]


def main() -> None:
    with tempfile.TemporaryDirectory() as d:
        tmp = Path(d)
        host = tg.parse(tg.run([str(tg.build_host(tmp / "host", COST_SOURCES))]))
        lines = _arm(tmp, host) + _avr(tmp)
    text = "\n".join(lines)
    print(text)
    if os.environ.get("IOTNAV_WRITE_RESULTS") == "1":
        out = Path(__file__).resolve().parent / "results" / "firmware_pipeline.md"
        out.write_text(text, encoding="utf-8")


if __name__ == "__main__":
    main()
