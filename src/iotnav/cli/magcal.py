"""``iotnav calibrate-mag``: magnetometer hard and soft iron from a log that turns the device.

Reads the magnetometer of a log (a directory or file :func:`iotnav.io.ingest` takes, or a BROAD
``.npz`` with ``imu_mag``), fits the calibration of :mod:`iotnav.techniques.mag_calibration` and
writes it as engine configuration (``mag_hard_iron_ut``, ``mag_soft_iron``: pass the file to
``iotnav run --config``).
"""

from __future__ import annotations

import zipfile
from pathlib import Path
from typing import Annotated

import numpy as np
import typer
from rich.table import Table

from iotnav.cli._common import console, user_errors
from iotnav.techniques.mag_calibration import fit_mag_calibration


def _load_mag(path: Path) -> np.ndarray:
    """Raw magnetometer samples ``(N, 3)``, uT."""
    if path.suffix == ".npz":
        try:
            with np.load(path, allow_pickle=False) as d:
                if "imu_mag" not in d.files:
                    raise ValueError(f"{path}: an .npz needs imu_mag; it has {sorted(d.files)}")
                return np.asarray(d["imu_mag"], dtype=np.float64)
        except (OSError, EOFError, zipfile.BadZipFile) as exc:
            raise ValueError(f"{path}: not a readable .npz archive ({exc})") from exc
        except ValueError as exc:
            if str(path) in str(exc):
                raise
            raise ValueError(f"{path}: not a readable .npz archive ({exc})") from exc
    from iotnav.io import ingest

    log = ingest([path])
    if len(log.mag) == 0:
        raise ValueError(f"{path}: the log has no magnetometer samples")
    return log.mag[["mag_x_ut", "mag_y_ut", "mag_z_ut"]].to_numpy(dtype=np.float64)


def register(app: typer.Typer) -> None:
    """Register ``calibrate-mag`` on ``app``."""

    @app.command("calibrate-mag")
    @user_errors
    def calibrate_mag_cmd(
        log_path: Annotated[
            Path, typer.Argument(help="Log with magnetometer samples (directory, file, BROAD .npz).")
        ],
        out: Annotated[Path, typer.Option(help="Engine configuration to write (TOML).")] = Path(
            "mag_calibration.toml"
        ),
        min_coverage: Annotated[
            float, typer.Option(help="Smallest accepted coverage of directions (at most 1/3).")
        ] = 0.05,
    ) -> None:
        """Fit hard and soft iron (the device must turn about all its axes) and write them as config."""
        cal = fit_mag_calibration(_load_mag(log_path), min_coverage=min_coverage)
        cfg = cal.to_config()
        lines = ["# iotnav calibrate-mag: m_cal = inv(W) (m_raw - h); for eskf, qekf (--config)"]
        lines.append("mag_hard_iron_ut = [" + ", ".join(f"{v:.6g}" for v in cfg["mag_hard_iron_ut"]) + "]")
        lines.append("mag_soft_iron = [" + ", ".join(f"{v:.6g}" for v in cfg["mag_soft_iron"]) + "]")
        out.write_text("\n".join(lines) + "\n")
        table = Table(title=f"iotnav calibrate-mag: {log_path}")
        table.add_column("what")
        table.add_column("value", justify="right")
        skipped = f" ({cal.n_nonfinite} non-finite left out)" if cal.n_nonfinite else ""
        table.add_row("samples", f"{cal.n_samples}{skipped}")
        table.add_row("hard iron, uT", " ".join(f"{v:+.2f}" for v in cal.hard_iron_ut))
        table.add_row("field after calibration, uT", f"{cal.field_ut:.2f}")
        table.add_row(
            "norm spread raw -> calibrated, uT", f"{cal.raw_spread_ut:.2f} -> {cal.residual_ut:.2f}"
        )
        table.add_row("coverage (1/3 at best)", f"{cal.coverage:.3f}")
        table.add_row("written", str(out))
        console.print(table)
