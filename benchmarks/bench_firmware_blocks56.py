"""Cost of the Forno pipeline's blocks 5 (mount aligner) and 6 (fusion KF) in C on the emulated targets (issue 20).

``firmware/host/cycles_blocks56.c`` (40 s of a car, sensor mounted 0.5 rad off its axis: 100 Hz
IMU, 4 Hz GNSS; see its header) is built for the host (float32, the golden final state) and for
each target, and a target's counts are reported only when its final state passes
:func:`iotnav.firmware.targets.check_blocks56` (the same decisions; the reals within the float32
tolerances of the host tests), the mechanism ``benchmarks/bench_firmware.py`` uses for blocks 1-4:

* ATmega128 at 8 MHz (``avr-gcc -Os``, ``simavr``, Timer1 cycles): the ATmega128 has 4 KB of SRAM.
  Both blocks together do not link (``.bss`` beyond the data region); block 6 alone is built, run
  and checked; block 5 alone links but its state leaves less RAM than its measured stack needs, so
  its cycles come from the same program on simavr's ATmega1284P (the same AVR core and
  instruction timings, 16 KB of SRAM), also checked. With ``libsimavr-dev`` a cycle profile
  (``firmware/avr/profile.c``): float operations per call beside Table I of Forno et al. 2020.
* Cortex-M3 (soft float) and Cortex-M4F (FPU) under ``qemu-system-arm -icount``: instructions per
  call (:mod:`iotnav.firmware.arm`).

Flash from ``avr-size`` / ``arm-none-eabi-size`` of each block's object; RAM: its state's
``sizeof`` plus the driver's measured stack high-water mark (stack painted at start).

Prints markdown; with ``IOTNAV_WRITE_RESULTS=1`` writes ``benchmarks/results/firmware_blocks56.md``.
"""

from __future__ import annotations

import os
import sys
import tempfile
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

from bench_firmware import _avr_profile, _size
from iotnav.firmware import arm
from iotnav.firmware import targets as tg
from iotnav.firmware.avr import F_CPU
from iotnav.firmware.host import FIRMWARE_DIR

#: SRAM of the ATmega128 (datasheet: 4096 bytes internal, 0x0100-0x10FF).
ATMEGA128_SRAM = 4096
#: Per call of the driver: its key, the description, calls per second at 100 Hz IMU and 1 Hz GNSS.
CALLS = [
    ("mount_imu", "block 5: `pl_mount_add_imu_body`, every IMU sample", 100),
    ("mount_gnss", "block 5: `pl_mount_add_gnss`, every GNSS epoch (all of them)", 1),
    ("mount_buffer", "block 5: `pl_mount_add_gnss` of the epochs that evaluate a buffer (1 in 8)", 0),
    ("fusion_predict", "block 6: `pl_fusion_predict` (IMU step), every IMU sample", 100),
    ("fusion_position", "block 6: `pl_fusion_update_position`, every GNSS epoch", 1),
    ("fusion_velocity", "block 6: `pl_fusion_update_velocity_ned`, every GNSS epoch", 1),
]
#: Table I of Forno et al. 2020 (sums + multiplications as FLOPs; big-O estimates from [29], the
#: sums and multiplications from [30] with a Cholesky inversion): block, portion, FLOPs, sums, muls.
TABLE_I = {
    "pl_fusion_predict": ("6", "KF Predict", 3078, 1476, 1566),
    "pl_fusion_update_position": ("6", "KF Update", 2165, 2493, 2869),
    "pl_mount_add_gnss": ("5", "Total (mean of buffer 50, other 64, rotm 20)", 134, None, None),
}


def _ms(c: float) -> str:
    return f"{c / F_CPU * 1e3:.2f}"


def _avr(tmp: Path, host: dict[str, dict[str, int]]) -> tuple[list[str], dict[str, dict[str, float]]]:
    src = tg.BLOCKS56_SOURCES
    lines: list[str] = []
    # both blocks on the ATmega128: does it link?
    try:
        tg.build_avr(tmp / "both128.elf", src, tg.blocks56_defines())
        both_links = "links"
    except RuntimeError as e:
        msg = [ln for ln in str(e).splitlines() if "not within region" in ln]
        both_links = "does not link: " + (msg[0].split("ld: ")[-1] if msg else str(e)[:200])
        both_links = both_links.replace(f"{tmp}/", "")  # the build's temporary folder: not a result
    b6 = tg.build_avr(tmp / "b6.elf", src, tg.blocks56_defines(block5=False))
    out6 = tg.run_avr(b6)
    d6 = tg.check_blocks56(out6, host["b6"], block5=False)
    b5 = tg.build_avr(tmp / "b5.elf", src, tg.blocks56_defines(block6=False))
    b5big = tg.build_avr(tmp / "b5_1284.elf", src, tg.blocks56_defines(block6=False), mcu="atmega1284p")
    out5 = tg.run_avr(b5big, mcu="atmega1284p")
    d5 = tg.check_blocks56(out5, host["b5"], block6=False)
    both = tg.build_avr(tmp / "both1284.elf", src, tg.blocks56_defines(), mcu="atmega1284p")
    outb = tg.run_avr(both, mcu="atmega1284p")
    db = tg.check_blocks56(outb, host["both"])
    objs = {}
    for name in ("mount", "fusion"):
        obj = tmp / f"pipeline_{name}.o"
        tg.run([*tg.avr_flags(), "-c", str(FIRMWARE_DIR / f"pipeline_{name}.c"), "-o", str(obj)])
        objs[name] = _size(obj)
    s6, s5 = _size(b6), _size(b5)
    room5 = ATMEGA128_SRAM - s5[1] - s5[2]
    fits5 = room5 >= out5["stack_bytes"]
    # block 5 alone on the ATmega128 itself: it runs in under a second on the ATmega1284P
    try:
        tg.check_blocks56(tg.run_avr(b5, timeout=30.0), host["b5"], block6=False)
        on128 = "on the ATmega128 it nevertheless runs and passes the golden check"
    except RuntimeError as e:
        on128 = "its run on the ATmega128 " + (
            "does not finish in 30 s (as a stack overflowing into the state would do)"
            if "did not finish" in str(e)
            else f"fails the golden check ({str(e)[:160]})"
        )
    ram6 = s6[1] + s6[2] + out6["stack_bytes"]
    rows, per_s = [], {"5": 0.0, "6": 0.0}
    for key, what, rate in CALLS:
        o = out6 if key.startswith("fusion") else out5
        mean, mx = o[f"{key}_mean"], o[f"{key}_max"]
        per_s["6" if key.startswith("fusion") else "5"] += rate * mean
        where = (
            "ATmega128" if key.startswith("fusion") else "ATmega1284P (block 5 does not fit the ATmega128)"
        )
        rows.append(f"| {what} | {mean} / {mx} | {_ms(mean)} / {_ms(mx)} | {where} |")
    frame6 = out6["fusion_predict_mean"] + out6["fusion_position_mean"] + out6["fusion_velocity_mean"]
    lines += [
        "## Firmware: blocks 5 (mount aligner) and 6 (fusion KF) on the ATmega128 at 8 MHz (simavr)",
        "",
        "`benchmarks/bench_firmware_blocks56.py`: `firmware/host/cycles_blocks56.c` (40 s car drive, sensor "
        "mounted 0.5 rad off the vehicle axis, 100 Hz IMU, 4 Hz GNSS; block 5 with the pipeline's "
        "`PIPELINE_MOUNT_NAV`, block 6 with `FusionConfig`'s defaults) built with `avr-gcc -Os`, Timer1 "
        "cycles under `simavr`. Golden check: each run's final state equals the host float32 build's "
        f"(the same {out5['n_eval']} buffers evaluated, {out5['n_accepted']} accepted, mount angle "
        f"{tg.f32(out5['mount_yaw']):.4f} rad; {out6['n_pos_ok']} fixes and {out6['n_vel_ok']} velocities "
        f"taken; largest difference: block 6 alone on the ATmega128 {max(d6.values()):.1e}, block 5 alone "
        f"on the ATmega1284P {max(d5.values()):.1e}, both on the ATmega1284P {max(db.values()):.1e}; "
        "absolute in rad, m, m/s, m/s^2 and for the quality figures, relative for the covariance and NIS; "
        "tolerances: `iotnav.firmware.targets`). Counts are emulator cycles: deterministic, not load-dependent.",
        "",
        "| call | cycles (mean / max) | ms at 8 MHz (mean / max) | measured on |",
        "|---|---:|---:|---|",
        *rows,
        f"| block 6, one GNSS frame: predict + position + velocity update (means) | {frame6} | {_ms(frame6)} | "
        "ATmega128 |",
        "",
        "Paper (ATmega128 at 8 MHz, logic analyser, anchor-node KF): Kalman filter 8 ms, frame 10.223 ms. "
        f"At 100 Hz IMU and 1 Hz GNSS: block 6 {per_s['6']:.0f} cycles per second "
        f"(**{100 * per_s['6'] / F_CPU:.0f} %** of the 8 MHz core), block 5 {per_s['5']:.0f} "
        f"({100 * per_s['5'] / F_CPU:.1f} %; its buffer epochs cost more, the mean over all epochs is counted).",
        "",
        f"Flash / RAM (`avr-size`): `pipeline_mount.o` text {objs['mount'][0]} B, `pipeline_fusion.o` text "
        f"{objs['fusion'][0]} B (no data or bss in either). States (float32): `pl_mount_state` "
        f"{out5['sizeof_mount']} B, `pl_fusion_state` {out6['sizeof_fusion']} B.",
        "",
        "What fits the ATmega128's 4096 B of SRAM (data + bss of the whole driver with avr-libc, plus its "
        "stack high-water mark, painted at start):",
        "",
        f"* blocks 5 and 6 together: {both_links}; on the ATmega1284P the same program uses data "
        f"{_size(both)[1]} B + bss {_size(both)[2]} B + stack {outb['stack_bytes']} B = "
        f"{_size(both)[1] + _size(both)[2] + outb['stack_bytes']} B.",
        f"* block 5 alone: data {s5[1]} B + bss {s5[2]} B leave {room5} B for the stack; it needs "
        f"{out5['stack_bytes']} B (measured on the ATmega1284P): "
        + (
            "fits."
            if fits5
            else f"**does not fit** ({out5['stack_bytes'] - room5} B short; {on128}; the data are avr-libc's "
            "and the driver's strings: with none at all, "
            f"{ATMEGA128_SRAM - s5[2]} B would remain for that {out5['stack_bytes']} B stack, room for "
            "nothing else). Its buffers "
            "(`PL_MOUNT_BUF_MAX` 32, "
            "`PL_MOUNT_HIST_MAX` 128: 1.5 KB of settle history) are the pipeline's configuration and were "
            "not shrunk here."
        ),
        f"* block 6 alone: data {s6[1]} B + bss {s6[2]} B + stack {out6['stack_bytes']} B = {ram6} B: "
        + ("fits" if ram6 <= ATMEGA128_SRAM else "does not fit")
        + f" (flash: whole driver text {s6[0]} B of 128 KB).",
        "",
    ]
    ops: dict[str, dict[str, float]] = {}
    prof6 = _avr_profile(
        tmp,
        b6,
        [tmp / "pipeline_fusion.o"],
        ("pl_fusion_predict", "pl_fusion_update_position", "pl_fusion_update_velocity_ned"),
        ops_out=ops,
    )
    prof5 = _avr_profile(
        tmp,
        b5big,
        [tmp / "pipeline_mount.o"],
        ("pl_mount_add_imu_body", "pl_mount_add_gnss"),
        "atmega1284p",
        ops,
    )
    lines += [
        "Block 6 on the ATmega128, " + prof6[0][0].lower() + prof6[0][1:],
        *prof6[1:],
        "",
        "Block 5 on the ATmega1284P (the same program, same core):",
        "",
        *prof5[2:],
        "",
    ]
    return lines, ops


def _table_i(ops: dict[str, dict[str, float]]) -> list[str]:
    rows = []
    for fn, (block, portion, flops, sums, muls) in TABLE_I.items():
        o = ops.get(fn)
        if o is None:
            continue
        meas = o["mul"] + o["add/sub"]
        rows.append(
            f"| {block} | {portion} | {flops} | {sums if sums is not None else ''} | "
            f"{muls if muls is not None else ''} | `{fn}` | {o['add/sub']:.1f} | {o['mul']:.1f} | {o['div']:.1f} | "
            f"{meas:.1f} |"
        )
    if "pl_fusion_update_velocity_ned" in ops and "pl_fusion_update_position" in ops:
        o, p = ops["pl_fusion_update_velocity_ned"], ops["pl_fusion_update_position"]
        rows.append(
            "| 6 | (the velocity update: Table I's one update takes m = 5 measurements at once, C updates "
            f"position and velocity in turn) | | | | `pl_fusion_update_velocity_ned` | {o['add/sub']:.1f} | "
            f"{o['mul']:.1f} | {o['div']:.1f} | {o['mul'] + o['add/sub']:.1f} |"
        )
        both = {k: o[k] + p[k] for k in o}
        rows.append(
            "| 6 | KF Update (one GNSS epoch: position + velocity) | 2165 | 2493 | 2869 | both updates | "
            f"{both['add/sub']:.1f} | {both['mul']:.1f} | {both['div']:.1f} | {both['mul'] + both['add/sub']:.1f} |"
        )
    return [
        "Beside Table I of Forno et al. 2020 (its counts are analytic estimates; ours are the float calls "
        "avr-libc's `__addsf3x` (add and sub), `__mulsf3x`, `__divsf3` entered per call in the profile above, "
        "sqrt and comparisons not counted; C exploits the structure of F and the sequential scalar updates, "
        "Table I counts dense matrix products):",
        "",
        "| block | Table I portion | FLOPs [29] | sum [30] | mul [30] | C call | add/sub | mul | div | add/sub + mul |",
        "|---|---|---:|---:|---:|---|---:|---:|---:|---:|",
        *rows,
        "",
        "(Block 5's count is per GNSS epoch, averaged over all epochs; an evaluated buffer costs more, see the "
        "cycles above.)",
        "",
    ]


def _arm(tmp: Path, host: dict[str, int]) -> list[str]:
    cols, diffs, sizes = {}, {}, []
    for name in sorted(arm.TARGETS):
        elf = tg.build_arm(tmp / f"{name}.elf", name, tg.BLOCKS56_SOURCES, tg.blocks56_defines())
        out = tg.run_arm(elf, name)
        diffs[name] = max(tg.check_blocks56(out, host).values())
        cols[name] = out
        objs = []
        for b in ("mount", "fusion"):
            obj = tmp / f"{name}_{b}.o"
            tg.run([*tg.arm_flags(name), "-c", str(FIRMWARE_DIR / f"pipeline_{b}.c"), "-o", str(obj)])
            t, d, s = arm.size(obj)
            objs.append(f"`pipeline_{b}.o` text {t} B" + (f", data {d} B, bss {s} B" if d or s else ""))
        sizes.append(f"{name}: " + ", ".join(objs) + f"; driver stack high-water {out['stack_bytes']} B")
    rows, per_s = [], dict.fromkeys(cols, 0.0)
    for key, what, rate in CALLS:
        cells = []
        for name, out in cols.items():
            mean, mx = arm.instructions(out[f"{key}_mean"]), arm.instructions(out[f"{key}_max"])
            per_s[name] += rate * mean
            cells.append(f"{mean:.0f} / {mx:.0f}")
        rows.append(f"| {what} | " + " | ".join(cells) + " |")
    rows.append(
        "| **instructions per second, both blocks at 100 Hz IMU + 1 Hz GNSS** | "
        + " | ".join(f"{v:.0f}" for v in per_s.values())
        + " |"
    )
    return [
        "## Firmware: blocks 5 and 6 on Cortex-M3 and Cortex-M4F (qemu-system-arm)",
        "",
        "The same driver, both blocks in one program, `arm-none-eabi-gcc -O2`, `qemu-system-arm -icount` "
        "(SysTick counts instructions, checked on a loop of known length); instructions per call, mean / max. "
        "Golden check passed: the same decisions as the host float32 build, largest difference "
        + ", ".join(f"{v:.1e} ({k})" for k, v in diffs.items())
        + ".",
        "",
        "| call | " + " | ".join(f"{n} ({arm.TARGETS[n].machine})" for n in cols) + " |",
        "|---|" + "---:|" * len(cols),
        *rows,
        "",
        "Flash (`arm-none-eabi-size`): " + "; ".join(sizes) + ". RAM: the states above (`pl_mount_state` "
        f"{cols['cortex-m4f']['sizeof_mount']} B, `pl_fusion_state` {cols['cortex-m4f']['sizeof_fusion']} B) "
        "plus that stack.",
        "",
    ]


def main() -> None:
    with tempfile.TemporaryDirectory() as d:
        tmp = Path(d)
        host = {}
        for key, b5, b6 in (("both", True, True), ("b5", True, False), ("b6", False, True)):
            exe = tg.build_host(tmp / f"host_{key}", tg.BLOCKS56_SOURCES, tg.blocks56_defines(b5, b6))
            host[key] = tg.parse(tg.run([str(exe)]))
        avr_lines, ops = _avr(tmp, host)
        text = "\n".join([*avr_lines, *_table_i(ops), *_arm(tmp, host["both"])])
    print(text)
    if os.environ.get("IOTNAV_WRITE_RESULTS") == "1":
        path = Path(__file__).parent / "results" / "firmware_blocks56.md"
        path.write_text(text)


if __name__ == "__main__":
    main()
