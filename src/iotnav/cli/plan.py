"""``iotnav plan power``: battery life per GNSS duty cycle beside the accuracy it costs (issue 20).

The energy model is :mod:`iotnav.eval.power`, the accuracy study :mod:`iotnav.eval.duty_cycle`,
the report section :mod:`iotnav.report.power`; this module reads the options, prints the tables
and writes the files.
"""

from __future__ import annotations

import dataclasses
import json
import math
from pathlib import Path
from typing import Annotated, Any

import typer
from rich.table import Table

from iotnav.cli._common import console, err_console, parse_positive_floats, user_errors

__all__ = ["register"]


def _num(x: float, digits: int = 2) -> str:
    return "-" if not math.isfinite(x) else f"{x:.{digits}f}"


def _pick(presets: dict[str, Any], name: str, what: str) -> Any:
    if name not in presets:
        raise ValueError(f"--{what} {name!r}: expected one of {', '.join(presets)}")
    return presets[name]


def register(app: typer.Typer) -> None:
    """Register the ``plan`` sub-app (``power``) on ``app``."""
    plan_app = typer.Typer(
        help="Plan a tracker: battery life per GNSS duty cycle beside the accuracy it costs.",
        no_args_is_help=True,
    )
    app.add_typer(plan_app, name="plan")

    @plan_app.command("power")
    @user_errors
    def power_cmd(
        engines: Annotated[
            str, typer.Option(help="Engines, comma separated (fixes: GNSS only).")
        ] = "fixes,anchor",
        logs: Annotated[
            str, typer.Option(help="Real logs, comma separated: drive_0708, walk_0827, husky ('' for none).")
        ] = "drive_0708,walk_0827,husky",
        scenario: Annotated[
            str | None, typer.Option(help="Also a simulator scenario (e.g. scooter-laps).")
        ] = None,
        seed: Annotated[int, typer.Option(help="Simulator seed.")] = 0,
        intervals: Annotated[str, typer.Option(help="Fix periods, s, comma separated.")] = "5,10,30,60",
        always_on: Annotated[bool, typer.Option(help="Include the receiver always on.")] = True,
        time_to_fix_s: Annotated[
            float | None,
            typer.Option(help="Time to fix after waking, s (default: the GNSS preset's hot start)."),
        ] = None,
        gnss: Annotated[str, typer.Option(help="GNSS preset: paper, sam-m8q.")] = "paper",
        imu: Annotated[str, typer.Option(help="IMU preset: paper, mpu6050.")] = "paper",
        mcu: Annotated[str, typer.Option(help="MCU preset: paper.")] = "paper",
        gnss_acq_mw: Annotated[float | None, typer.Option(help="GNSS acquisition power, mW.")] = None,
        gnss_track_mw: Annotated[float | None, typer.Option(help="GNSS tracking power, mW.")] = None,
        gnss_backup_mw: Annotated[float | None, typer.Option(help="GNSS backup (asleep) power, mW.")] = None,
        imu_mw: Annotated[float | None, typer.Option(help="IMU power on, mW.")] = None,
        imu_sleep_mw: Annotated[float | None, typer.Option(help="IMU power asleep, mW.")] = None,
        mcu_mw: Annotated[float | None, typer.Option(help="MCU power on, mW.")] = None,
        mcu_sleep_mw: Annotated[float | None, typer.Option(help="MCU power asleep, mW.")] = None,
        mcu_busy: Annotated[
            float, typer.Option(help="Fraction of time an inertial engine keeps the MCU on.")
        ] = 1.0,
        on_after_fix_s: Annotated[float, typer.Option(help="Receiver tracking after its fix, s.")] = 0.0,
        capacity_mah: Annotated[float, typer.Option(help="Battery capacity, mAh.")] = 2000.0,
        voltage_v: Annotated[float, typer.Option(help="Battery nominal voltage, V.")] = 3.7,
        usable: Annotated[float, typer.Option(help="Usable fraction of the battery's energy.")] = 1.0,
        max_duration_s: Annotated[
            float | None, typer.Option(help="Use only the first this many s of each real log.")
        ] = None,
        accuracy: Annotated[bool, typer.Option(help="Measure the accuracy (run the engines).")] = True,
        out: Annotated[
            Path | None,
            typer.Option(help="Write budget.csv, summary.json (and power.html, .png, .md, .csv) here."),
        ] = None,
    ) -> None:
        """Battery life for each GNSS duty cycle beside the horizontal error it costs on real logs."""
        from iotnav.eval import power as pw

        g = _pick(pw.GNSS_PRESETS, gnss, "gnss")
        g = dataclasses.replace(
            g,
            acquisition_mw=g.acquisition_mw if gnss_acq_mw is None else gnss_acq_mw,
            tracking_mw=g.tracking_mw if gnss_track_mw is None else gnss_track_mw,
            backup_mw=g.backup_mw if gnss_backup_mw is None else gnss_backup_mw,
            time_to_fix_s=g.time_to_fix_s if time_to_fix_s is None else time_to_fix_s,
        )
        i = _pick(pw.IMU_PRESETS, imu, "imu")
        i = dataclasses.replace(
            i,
            active_mw=i.active_mw if imu_mw is None else imu_mw,
            sleep_mw=i.sleep_mw if imu_sleep_mw is None else imu_sleep_mw,
        )
        m = _pick(pw.MCU_PRESETS, mcu, "mcu")
        m = dataclasses.replace(
            m,
            active_mw=m.active_mw if mcu_mw is None else mcu_mw,
            sleep_mw=m.sleep_mw if mcu_sleep_mw is None else mcu_sleep_mw,
        )
        device = pw.DevicePower(gnss=g, imu=i, mcu=m, on_after_fix_s=on_after_fix_s, mcu_busy=mcu_busy)
        battery = pw.Battery(capacity_mah, voltage_v, usable)
        periods: tuple[float | None, ...] = ((None,) if always_on else ()) + parse_positive_floats(
            intervals, "--intervals", "fix periods"
        )
        # hold (GNSS alone holding its latest fix) is always scored
        names = tuple(e.strip() for e in engines.split(",") if e.strip() and e.strip() != "hold")
        meta: dict[str, Any] = {
            "gnss": g.name,
            "imu": i.name,
            "mcu": m.name,
            "time_to_fix_s": g.time_to_fix_s,
            "capacity_mah": capacity_mah,
            "voltage_v": voltage_v,
            "usable_fraction": usable,
            "device": dataclasses.asdict(device),
            "periods_s": list(periods),
            "engines": list(names),
            "sources": {"gnss": g.source, "imu": i.source, "mcu": m.source},
            "accuracy": accuracy,
            "logs": logs,
            "scenario": scenario,
            "seed": seed,
            "max_duration_s": max_duration_s,
        }
        table = _print_budgets(device, battery, periods, names)
        if out is not None:
            out.mkdir(parents=True, exist_ok=True)
            table.to_csv(out / "budget.csv", index=False)
            (out / "summary.json").write_text(json.dumps(meta, indent=2, default=str) + "\n")
            console.print(f"wrote {out / 'budget.csv'}, {out / 'summary.json'}")
        if not accuracy:
            return
        df = _study(names, logs, scenario, seed, periods, g.time_to_fix_s, max_duration_s)
        from iotnav.eval.duty_cycle import with_budgets

        df = with_budgets(df, device, battery)
        _print_accuracy(df)
        if out is not None:
            from iotnav.report.power import write_power_report

            paths = write_power_report(df, out, meta)
            df.to_csv(out / "power.csv", index=False)
            for p in (*paths.values(), out / "power.csv"):
                console.print(f"wrote {p}")


def _study(
    names: tuple[str, ...],
    logs: str,
    scenario: str | None,
    seed: int,
    periods: tuple[float | None, ...],
    time_to_fix_s: float,
    max_duration_s: float | None,
) -> Any:
    import pandas as pd

    from iotnav.eval.duty_cycle import DutyCycleConfig, real_case, run_case, simulated_case
    from iotnav.eval.outages import engine_factories

    cfg = DutyCycleConfig(periods_s=periods, time_to_fix_s=time_to_fix_s, engines=names)
    cases = [c.strip() for c in logs.split(",") if c.strip()]
    if not cases and scenario is None:
        raise ValueError("nothing to measure: give --logs and/or --scenario (or --no-accuracy)")
    parts = []
    loaded = [(c, *real_case(c, max_duration_s)) for c in cases]
    if scenario is not None:
        loaded.append((f"sim:{scenario}", *simulated_case(scenario, seed)))
    for name, fed, truth, prof in loaded:
        makers = engine_factories(prof, names, integrity=True)
        missing = [n for n in names if n not in makers]
        if missing:
            raise ValueError(f"unknown or unavailable engine(s): {', '.join(missing)}")
        parts.append(
            run_case(name, fed, truth, makers, cfg, progress=lambda s: err_console.print(f"running {s}"))
        )
    return pd.concat(parts, ignore_index=True)


def _print_budgets(
    device: Any, battery: Any, periods: tuple[float | None, ...], names: tuple[str, ...]
) -> Any:
    """Print the energy table of an inertial engine and of the GNSS-only one; return it as a frame."""
    import pandas as pd

    from iotnav.eval.power import budgets, uses_imu

    inertial = next((n for n in names if uses_imu(n)), "anchor")
    t = Table(title=f"Battery life, {battery.capacity_mah:g} mAh at {battery.voltage_v:g} V")
    for col in (
        "engine",
        "fix every",
        "GNSS on %",
        "GNSS mW",
        "IMU mW",
        "MCU mW",
        "total mW",
        "life (h)",
        "(days)",
    ):
        t.add_column(col, justify="left" if col in ("engine", "fix every") else "right")
    rows = []
    for eng in (inertial, "fixes"):
        for b in budgets(device, battery, periods, eng):
            rows.append(
                {
                    "engine": eng,
                    "period_s": math.nan if b.period_s is None else b.period_s,
                    "gnss_on_fraction": b.gnss_on_fraction,
                    "gnss_mw": b.gnss_mw,
                    "imu_mw": b.imu_mw,
                    "mcu_mw": b.mcu_mw,
                    "total_mw": b.total_mw,
                    "life_h": b.life_h,
                }
            )
            t.add_row(
                eng if eng != "fixes" else "fixes/hold",
                b.label,
                _num(100 * b.gnss_on_fraction, 1),
                _num(b.gnss_mw),
                _num(b.imu_mw),
                _num(b.mcu_mw),
                _num(b.total_mw),
                _num(b.life_h, 1),
                _num(b.life_h / 24.0, 1),
            )
    console.print(t)
    return pd.DataFrame(rows)


def _print_accuracy(df: Any) -> None:
    for case in dict.fromkeys(df["case"]):
        t = Table(title=f"{case}: battery life beside horizontal error (m)")
        for col in (
            "fix every",
            "engine",
            "life (h)",
            "p50",
            "p95",
            "RMS",
            "max",
            "fixes",
            "worse than hold",
        ):
            t.add_column(col, justify="left" if col in ("fix every", "engine") else "right")
        for r in df[df["case"] == case].to_dict("records"):
            p = float(r["period_s"])
            t.add_row(
                "always on" if math.isnan(p) else f"{p:g} s",
                str(r["engine"]),
                _num(float(r["life_h"]), 1),
                *(_num(float(r[k])) for k in ("h_p50", "h_p95", "h_rms", "h_max")),
                str(r["fixes"]),
                "[red]yes[/]" if r["worse_than_hold"] else "no",
            )
        console.print(t)
