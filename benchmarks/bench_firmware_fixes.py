"""Cost of the C GNSS-only engine (firmware/fixes.c) on Cortex-M3 and Cortex-M4F under qemu-system-arm (issue 20).

The float32 library and ``firmware/arm/replay_fixes.c`` (:mod:`iotnav.firmware.arm`,
``arm-none-eabi-gcc -O2``) replay, on the emulated MPS2 boards, the inputs the Python
:class:`~iotnav.engines.fixes.FixesEngine` was fed beside the host float32 build
(:mod:`iotnav.firmware.fixes_host`), for three streams: the simulated stop-and-go fleet day (1 Hz,
urban canyon, speed and course; 3000 fixes), the same day without velocity and with faults
(:func:`~iotnav.firmware.fixes_host.with_faults`: relocations, rollbacks, a clock jump; 1500
fixes) and the first 300 s of the real drive_0708 (1 Hz degraded RTK and its 100 Hz IMU). Each
board's output is checked against the Python track before its counts are reported. SysTick under
``-icount shift=6`` counts instructions (QEMU models no cycles); cycles assume
:data:`ASSUMED_CPI`. Needs the Debian packages ``gcc-arm-none-eabi libnewlib-arm-none-eabi
qemu-system-arm``.

Prints a markdown snippet; with ``IOTNAV_WRITE_RESULTS=1`` also writes
``benchmarks/results/firmware_fixes.md``.
"""

from __future__ import annotations

import os
import tempfile
from pathlib import Path

import numpy as np

from iotnav.engines.base import iter_samples
from iotnav.engines.fixes import FixesConfig, FixesEngine
from iotnav.eval import outages as O
from iotnav.firmware import arm, host
from iotnav.firmware import fixes_host as fh
from iotnav.io.log import Log
from iotnav.sim.fleet_days import fleet_day

DRIVE = (
    Path(os.environ.get("IOTNAV_DATASETS", "/work/shared/datasets"))
    / "rtklibexplorer_gnss_imu"
    / "drive_0708"
)
#: Assumed cycles per instruction of a Cortex-M3/M4 (as ``bench_firmware.py``; not measured).
ASSUMED_CPI = 1.5
CORTEX_M3_HZ = 72e6


def _streams() -> dict[str, object]:
    from iotnav.cli.outages import load_dataset

    log, prof = load_dataset(DRIVE)
    truth = O.rtk_truth(log.gnss).sort_values("t").reset_index(drop=True)
    truth = truth[truth.t < float(truth.t.iloc[0]) + 300.0].reset_index(drop=True)
    fed, _ = O.degraded_feed(log, truth, prof, O.OutageConfig(seed=3))
    drive = Log(gnss=fed.gnss, imu=fed.imu[fed.imu.t <= fed.gnss.t.max() + 0.5])
    sg = fleet_day("stop-and-go", seed=1).gnss
    return {
        "stop-and-go fleet day, 3000 fixes with speed/course": lambda: iter_samples(Log(gnss=sg.iloc[:3000])),
        "stop-and-go without velocity, with faults, 1500 fixes": lambda: fh.gnss_samples(
            fh.with_faults(fleet_day("stop-and-go", seed=2).gnss.iloc[:1500])
        ),
        "drive_0708 300 s, 1 Hz fixes + 100 Hz IMU": lambda: iter_samples(drive),
    }


def _max_pos_diff(res: dict, outputs: bytes, fw: fh.FixesFirmware) -> float:
    """Largest position difference (m) of a replay's rows from the Python rows; the decisions must match."""
    recs = fh.decode_stream(fw.inputs, outputs)
    gnss = [(rc, o) for rec, (rc, o) in zip(fw.inputs[1:], recs, strict=True) if rec[:1] == b"G"]
    if [fh.REASONS[rc] if rc > 0 else "" for rc, _ in gnss] != res["py_skip"]:
        raise RuntimeError("board decisions differ from Python")
    c_names = [[e[0] for e in fh.c_events(o)] for _, o in gnss if o is not None]
    if c_names != [[e[0] for e in ev] for ev in res["py_events"]]:
        raise RuntimeError("board events differ from Python")
    rows = np.array([o["ned"] for rc, o in gnss if rc == 0 and o is not None])
    return float(np.nanmax(np.linalg.norm(np.nan_to_num(rows - res["py"][:, :3]), axis=1)))


def main() -> None:
    lines = [
        "## Firmware: the GNSS-only `fixes` engine on Cortex-M3 and Cortex-M4F (qemu-system-arm)",
        "",
        "`benchmarks/bench_firmware_fixes.py`: `firmware/arm/replay_fixes.c` with `fixes.c`, `arm-none-eabi-gcc "
        "-O2`, on `qemu-system-arm -icount shift=6` (mps2-an385 Cortex-M3 soft float, mps2-an386 Cortex-M4F), "
        "replaying the inputs the Python engine was fed; each board's track checked against Python first "
        "(same skip reasons and events; the largest position difference in the last column). Instructions "
        "per call, mean / max (`fixes_step_gnss`: the filter steps, not the first fix or skipped epochs). "
        f"Share of a 72 MHz Cortex-M3 at 1 Hz fixes and 100 Hz IMU at an assumed {ASSUMED_CPI} cycles per "
        "instruction.",
        "",
        "| stream | target | `fixes_step_gnss` | `fixes_step_imu` | share of 72 MHz M3 | position vs Python (max) |",
        "|---|---|---:|---:|---:|---:|",
    ]
    sizes: list[str] = []
    state_bytes = 0
    with tempfile.TemporaryDirectory() as d:
        tmp = Path(d)
        lib = host.build(tmp / "fixes.so", engine="fixes")
        elfs = {t: arm.build(tmp / f"{t}.elf", t, engine="fixes") for t in sorted(arm.TARGETS)}
        for name, make in _streams().items():
            fw = fh.FixesFirmware(lib, FixesConfig(), record=True)
            res = fh.run_beside(FixesEngine(), fw, make())  # type: ignore[operator]
            for t, elf in elfs.items():
                run = arm.run(elf, t, b"".join(fw.inputs), timeout=600)
                c = run.counts
                if abs(arm.instructions(c["calib_ticks"]) / (2 * c["calib_loops"]) - 1.0) > 1e-3:
                    raise RuntimeError(f"{t}: SysTick is not counting instructions")
                dpos = _max_pos_diff(res, run.outputs, fw)
                if dpos > 0.05:
                    raise RuntimeError(f"{t}: track {dpos:.3f} m from Python")
                g = arm.instructions(c["gnss_sum"] / c["gnss_n"]), arm.instructions(c["gnss_max"])
                imu = (
                    (arm.instructions(c["imu_sum"] / c["imu_n"]), arm.instructions(c["imu_max"]))
                    if c["imu_n"]
                    else None
                )
                share = (g[0] + 100 * (imu[0] if imu else 0.0)) * ASSUMED_CPI / CORTEX_M3_HZ
                imu_txt = f"{imu[0]:.0f} / {imu[1]:.0f}" if imu else "-"
                lines.append(
                    f"| {name} | {t} | {g[0]:.0f} / {g[1]:.0f} | {imu_txt} | {100 * share:.3f} % | {dpos:.1e} m |"
                )
                state_bytes = c["state_bytes"]
                if not any(s.startswith(t) for s in sizes):
                    o = arm.size(arm.build(tmp / f"{t}.o", t, library_only=True, engine="fixes"))
                    sizes.append(
                        f"{t}: `fixes.o` text {o[0]} B (data {o[1]}, bss {o[2]}), stack high-water {c['stack_bytes']} B"
                    )
    lines += [
        "",
        "Flash / RAM (`arm-none-eabi-size`; stack measured by painting): "
        + "; ".join(sizes)
        + f". One `fixes_state` "
        f"is {state_bytes} B in float32, most of it the spread test's ring of 256 fixes and its scratch "
        "(`FIXES_RING_MAX`, from `fixes_kernel.RING_MAX`).",
        "",
    ]
    text = "\n".join(lines)
    print(text)
    if os.environ.get("IOTNAV_WRITE_RESULTS") == "1":
        path = Path(__file__).parent / "results" / "firmware_fixes.md"
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(text)


if __name__ == "__main__":
    main()
