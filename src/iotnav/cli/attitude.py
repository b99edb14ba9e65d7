"""``iotnav attitude``: run an attitude filter on an IMU file; BROAD metrics when truth exists."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import numpy as np
import pandas as pd
import typer
from rich.table import Table

from iotnav.cli._common import console, user_errors
from iotnav.eval.attitude import (
    ImuRecording,
    available_filters,
    enu_to_ned_quat,
    load_broad,
    quat_to_euler_ned,
    score,
)


def _load(path: Path) -> ImuRecording:
    """A BROAD ``.npz``, or any IMU file :func:`iotnav.io.read_file` reads (no truth)."""
    if not path.exists():
        raise FileNotFoundError(f"{path}: no such file")
    if path.suffix == ".npz":
        return load_broad(path)
    from iotnav.io import read_file

    part = read_file(path)
    imu = part.imu
    if imu.empty:
        raise ValueError(f"{path}: no IMU samples (expected acc_x..gyro_z columns)")
    t = imu["t"].to_numpy(float)
    dt = np.diff(t)
    if len(dt) == 0 or not np.all(dt > 0):
        raise ValueError(f"{path}: IMU time stamps must increase")
    fs = float(1.0 / np.median(dt))
    gyr = imu[["gyro_x", "gyro_y", "gyro_z"]].to_numpy(float)
    acc = imu[["acc_x", "acc_y", "acc_z"]].to_numpy(float)
    mag = None
    if not part.mag.empty:
        m = part.mag
        mag = np.column_stack(
            [
                np.interp(t, m["t"].to_numpy(float), m[c].to_numpy(float))
                for c in ("mag_x_ut", "mag_y_ut", "mag_z_ut")
            ]
        )
    return ImuRecording(path.stem, fs, gyr, acc, mag)


def register(app: typer.Typer) -> None:
    """Register ``attitude`` on ``app``."""

    @app.command("attitude")
    @user_errors
    def attitude_cmd(
        imu_file: Annotated[Path, typer.Argument(help="A BROAD .npz, or an IMU file iotnav reads.")],
        filter_name: Annotated[
            str,
            typer.Option("--filter", help="eskf, eskf6, vqf, vqf6, imufusion, madgwick, mahony, cascade."),
        ] = "eskf",
        out: Annotated[
            Path | None, typer.Option(help="CSV with roll, pitch, yaw (NED, rad) per sample.")
        ] = None,
    ) -> None:
        """Estimate attitude per sample; print BROAD's RMSE metrics when the file has truth."""
        filters = available_filters()
        if filter_name not in filters:
            raise ValueError(f"unknown filter {filter_name!r}; choose one of {', '.join(filters)}")
        spec = filters[filter_name]
        rec = _load(imu_file)
        if spec.nine_axis and rec.mag_b is None:
            raise ValueError(f"{imu_file}: filter {filter_name!r} needs a magnetometer; try a 6-axis one")
        q_enu_b = spec.fn(rec)
        roll, pitch, yaw = quat_to_euler_ned(enu_to_ned_quat(q_enu_b))
        if out is not None:
            t = np.arange(len(roll)) / rec.fs_hz
            pd.DataFrame({"t": t, "roll": roll, "pitch": pitch, "yaw": yaw}).to_csv(out, index=False)
            console.print(f"wrote {out} ({len(roll)} samples)")
        if rec.q_ref_enu is not None and rec.movement is not None:
            e = score(rec, q_enu_b, spec.nine_axis)
            table = Table(title=f"{rec.name}: {spec.name} (BROAD metrics, movement samples)")
            for col in ("total, deg", "heading, deg", "inclination, deg"):
                table.add_column(col, justify="right")
            table.add_row(f"{e.total_deg:.2f}", f"{e.heading_deg:.2f}", f"{e.inclination_deg:.2f}")
            console.print(table)
            if not spec.nine_axis:
                console.print(f"6-axis: constant heading offset {e.heading_offset_deg:.1f} deg removed")
