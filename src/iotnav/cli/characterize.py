"""``iotnav characterize``: IMU noise from a static recording (Allan deviation, Table 2 RMS).

Reads an IMU file, keeps the static time window the user names, and prints the RMS of the
static residuals per axis in the form of Dabove et al. (2016) Table 2 and the Allan-variance
noise terms (IEEE Std 952) of :mod:`iotnav.techniques.allan`. Writes ``allan.png`` (the curves),
``allan.csv`` (the numbers), ``characterize.json`` (per-axis terms and notes) and
``noise_model.toml`` (what the Kalman engines and the simulator accept).

Input: ``.npz`` files with ``imu_acc`` (m/s^2), ``imu_gyr`` (rad/s) and ``sampling_rate`` (Hz)
(the BROAD layout; ``acc``/``gyr`` as in the VQF sample, optional ``t`` in s) are read directly;
every other file goes through :func:`iotnav.io.read_file` (IMU CSV, phone logs ...).
"""

from __future__ import annotations

import json
import math
from dataclasses import asdict
from pathlib import Path
from typing import Annotated, Any

import numpy as np
import numpy.typing as npt
import typer
from rich.table import Table

from iotnav.cli._common import console, user_errors
from iotnav.techniques.allan import AXES, G0_MPS2, AllanParams, Characterization, characterize

_ACC_UNITS = {"m/s^2": 1.0, "g": G0_MPS2, "mg": G0_MPS2 * 1e-3}
_GYRO_UNITS = {"rad/s": 1.0, "deg/s": math.pi / 180.0, "mdps": math.pi / 180.0 * 1e-3}
_DEG = math.pi / 180.0
_UG = 1e-6 * G0_MPS2


def _load_npz(path: Path, acc_unit: str | None, gyro_unit: str | None) -> tuple[np.ndarray, ...]:
    """``t`` (s), acc (m/s^2), gyro (rad/s) of a BROAD-style ``.npz``."""
    with np.load(path, allow_pickle=False) as d:
        keys = set(d.files)
        acc_key = "imu_acc" if "imu_acc" in keys else "acc"
        gyr_key = "imu_gyr" if "imu_gyr" in keys else "gyr"
        if acc_key not in keys or gyr_key not in keys:
            raise ValueError(
                f"{path}: an .npz needs imu_acc and imu_gyr (or acc and gyr); it has {sorted(keys)}"
            )
        acc = np.asarray(d[acc_key], dtype=np.float64)
        gyr = np.asarray(d[gyr_key], dtype=np.float64)
        if "t" in keys:
            t = np.asarray(d["t"], dtype=np.float64)
        elif "sampling_rate" in keys:
            t = np.arange(len(acc)) / float(d["sampling_rate"])
        else:
            raise ValueError(f"{path}: an .npz needs a time array t or a sampling_rate")
    acc_f = _ACC_UNITS[acc_unit] if acc_unit else 1.0
    gyr_f = _GYRO_UNITS[gyro_unit] if gyro_unit else 1.0
    return t, acc * acc_f, gyr * gyr_f


def _load(path: Path, acc_unit: str | None, gyro_unit: str | None) -> tuple[np.ndarray, ...]:
    """``t`` (s), acc (m/s^2), gyro (rad/s) of any IMU file."""
    for unit, table, what in ((acc_unit, _ACC_UNITS, "acc"), (gyro_unit, _GYRO_UNITS, "gyro")):
        if unit is not None and unit not in table:
            raise ValueError(f"unknown {what} unit {unit!r}; expected one of {', '.join(table)}")
    if not path.exists():
        raise FileNotFoundError(f"{path}: no such file")
    if path.suffix.lower() == ".npz":
        return _load_npz(path, acc_unit, gyro_unit)
    from iotnav.io import read_file

    options: dict[str, Any] = {}
    if acc_unit:
        options["acc_unit"] = acc_unit
    if gyro_unit:
        options["gyro_unit"] = gyro_unit
    part = read_file(path, **options)
    imu = part.imu
    if len(imu) == 0:
        raise ValueError(f"{path}: no IMU samples in this file (format {part.report.format})")
    return (
        imu["t"].to_numpy(dtype=np.float64),
        imu[["acc_x", "acc_y", "acc_z"]].to_numpy(dtype=np.float64),
        imu[["gyro_x", "gyro_y", "gyro_z"]].to_numpy(dtype=np.float64),
    )


def _window(t: npt.NDArray[np.float64], start: float | None, end: float | None) -> npt.NDArray[np.bool_]:
    rel = t - t[0]
    keep = np.ones(len(t), dtype=bool)
    if start is not None:
        keep &= rel >= start
    if end is not None:
        keep &= rel <= end
    return keep


def _fmt(value: float, digits: int = 4) -> str:
    return "n/a" if not math.isfinite(value) else f"{value:.{digits}g}"


def _print_tables(res: Characterization, title: str) -> None:
    t2 = Table(title=f"RMS of the static residuals (Dabove et al. Table 2 form) - {title}")
    t2.add_column("RMS")
    for ax in AXES:
        t2.add_column(ax.upper(), justify="right")
    t2.add_row("Acceleration (g)", *(f"{v / G0_MPS2:.4f}" for v in res.acc_rms))
    t2.add_row("Acceleration (m/s^2)", *(f"{v:.4f}" for v in res.acc_rms))
    t2.add_row("Gyro. (rad/s)", *(f"{v:.4f}" for v in res.gyro_rms))
    console.print(t2)

    tp = Table(title=f"Allan deviation terms (IEEE Std 952), {res.duration_s:.1f} s at {res.rate_hz:.2f} Hz")
    for col in ("axis", "N (white)", "B (bias instab.)", "tau_B, s", "K (rate RW)"):
        tp.add_column(col, justify="right" if col != "axis" else "left")
    for i, p in enumerate(res.gyro_params):
        b = (
            _fmt(p.bias_instability * 3600 / _DEG, 3)
            if math.isfinite(p.bias_instability)
            else f"<= {p.bias_instability_upper_bound * 3600 / _DEG:.3g}"
        )
        tp.add_row(
            f"gyro {AXES[i]}",
            f"{p.noise_density / _DEG:.4g} deg/s/rtHz" + ("" if p.noise_density_identified else " (?)"),
            f"{b} deg/h",
            _fmt(p.bias_instability_tau_s, 3),
            f"{_fmt(p.rate_random_walk / _DEG, 3)} deg/s/rts",
        )
    for i, p in enumerate(res.acc_params):
        b = (
            _fmt(p.bias_instability / _UG, 3)
            if math.isfinite(p.bias_instability)
            else f"<= {p.bias_instability_upper_bound / _UG:.3g}"
        )
        tp.add_row(
            f"accel {AXES[i]}",
            f"{p.noise_density / _UG:.4g} ug/rtHz" + ("" if p.noise_density_identified else " (?)"),
            f"{b} ug",
            _fmt(p.bias_instability_tau_s, 3),
            f"{_fmt(p.rate_random_walk / _UG, 3)} ug/rts",
        )
    console.print(tp)


def _plot(res: Characterization, dest: Path, title: str) -> None:
    from matplotlib.figure import Figure

    fig = Figure(figsize=(11, 4.5), constrained_layout=True)
    ax_g, ax_a = fig.subplots(1, 2)
    colors = ("tab:red", "tab:green", "tab:blue")
    for i in range(3):
        cg, pg = res.gyro_curves[i], res.gyro_params[i]
        ax_g.loglog(cg.tau_s, cg.adev / _DEG, color=colors[i], label=f"gyro {AXES[i]}")
        ax_g.loglog(cg.tau_s, pg.noise_density / np.sqrt(cg.tau_s) / _DEG, "--", color=colors[i], lw=0.8)
        ca, pa = res.acc_curves[i], res.acc_params[i]
        ax_a.loglog(ca.tau_s, ca.adev / _UG, color=colors[i], label=f"accel {AXES[i]}")
        ax_a.loglog(ca.tau_s, pa.noise_density / np.sqrt(ca.tau_s) / _UG, "--", color=colors[i], lw=0.8)
    ax_g.set(xlabel="averaging time tau, s", ylabel="Allan deviation, deg/s", title="gyroscope")
    ax_a.set(xlabel="averaging time tau, s", ylabel="Allan deviation, ug", title="accelerometer")
    for ax in (ax_g, ax_a):
        ax.grid(True, which="both", alpha=0.3)
        ax.legend(title="dashed: N / sqrt(tau)", fontsize=8)
    fig.suptitle(title)
    fig.savefig(dest, dpi=110)


def _summary(res: Characterization, source: str) -> dict[str, Any]:
    def num(v: float, scale: float) -> float | None:
        return v / scale if math.isfinite(v) else None

    def axis(
        p: AllanParams, rms: float, units: tuple[str, str, str], scales: tuple[float, float]
    ) -> dict[str, Any]:
        n_unit, b_unit, k_unit = units
        s_n, s_b = scales
        return {
            "rms_residual_si": rms,
            f"noise_density_{n_unit}": num(p.noise_density, s_n),
            "noise_density_identified": p.noise_density_identified,
            f"bias_instability_{b_unit}": num(p.bias_instability, s_b),
            "bias_instability_tau_s": num(p.bias_instability_tau_s, 1.0),
            f"bias_instability_upper_bound_{b_unit}": num(p.bias_instability_upper_bound, s_b),
            f"rate_random_walk_{k_unit}": num(p.rate_random_walk, s_n),
            "notes": list(p.notes),
        }

    gyro_units = ("dps_rthz", "dph", "dps_per_rts")
    acc_units = ("ug_rthz", "ug", "ug_per_rts")
    return {
        "source": source,
        "rate_hz": res.rate_hz,
        "duration_s": res.duration_s,
        "gyro": {
            ax: axis(p, float(r), gyro_units, (_DEG, _DEG / 3600.0))
            for ax, p, r in zip(AXES, res.gyro_params, res.gyro_rms, strict=True)
        },
        "accel": {
            ax: axis(p, float(r), acc_units, (_UG, _UG))
            for ax, p, r in zip(AXES, res.acc_params, res.acc_rms, strict=True)
        },
        "noise_model": {
            k: (v if not isinstance(v, float) or math.isfinite(v) else None)
            for k, v in asdict(res.model).items()
        },
        "notes": list(res.notes),
    }


def register(app: typer.Typer) -> None:
    """Register ``characterize`` on ``app``."""

    @app.command("characterize")
    @user_errors
    def characterize_cmd(
        imu_file: Annotated[
            Path, typer.Argument(help="IMU log of a static sensor (IMU CSV, phone log, BROAD .npz).")
        ],
        start: Annotated[
            float | None, typer.Option(help="Window start, s after the first sample (static part only).")
        ] = None,
        end: Annotated[float | None, typer.Option(help="Window end, s after the first sample.")] = None,
        out: Annotated[Path, typer.Option(help="Output directory.")] = Path("."),
        acc_unit: Annotated[
            str | None,
            typer.Option(help="Accelerometer unit in the file: g, mg or m/s^2 (detected if omitted)."),
        ] = None,
        gyro_unit: Annotated[
            str | None,
            typer.Option(help="Gyro unit in the file: deg/s, mdps or rad/s (detected if omitted)."),
        ] = None,
    ) -> None:
        """IMU noise from a static recording: Table 2 RMS, Allan terms, plot and noise_model.toml."""
        t, acc, gyro = _load(imu_file, acc_unit, gyro_unit)
        keep = _window(t, start, end)
        n = int(np.count_nonzero(keep))
        if n < 20:
            raise ValueError(
                f"{imu_file}: only {n} samples between --start {start} and --end {end} (s after start)"
            )
        window = f"{'' if start is None else start}..{'' if end is None else end} s"
        source = f"{imu_file.name} [{window}]"
        res = characterize(t[keep], acc[keep], gyro[keep], source=source)
        _print_tables(res, source)
        for note in res.notes:
            console.print(f"note: {note}")
        for name, params in (("gyro", res.gyro_params), ("accel", res.acc_params)):
            for ax, p in zip(AXES, params, strict=True):
                for note in p.notes:
                    console.print(f"note ({name} {ax}): {note}")
        out.mkdir(parents=True, exist_ok=True)
        (out / "noise_model.toml").write_text(res.model.to_toml())
        (out / "characterize.json").write_text(json.dumps(_summary(res, source), indent=1))
        cols = {"tau_s": res.gyro_curves[0].tau_s}
        for ax, cg, ca in zip(AXES, res.gyro_curves, res.acc_curves, strict=True):
            cols[f"adev_gyro_{ax}_rad_s"] = cg.adev
            cols[f"adev_acc_{ax}_mps2"] = ca.adev
        np.savetxt(
            out / "allan.csv",
            np.column_stack(list(cols.values())),
            delimiter=",",
            header=",".join(cols),
            comments="",
        )
        _plot(res, out / "allan.png", source)
        for name in ("noise_model.toml", "characterize.json", "allan.csv", "allan.png"):
            console.print(f"wrote {out / name}")
