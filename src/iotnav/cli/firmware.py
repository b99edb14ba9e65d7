"""``iotnav firmware export``: the C library of an engine with the user's tuned parameters.

The maths lives in ``firmware/`` (C99) and :mod:`iotnav.firmware.gen` (the generated
configuration header); this module reads the TOML and writes the files.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import Annotated

import typer

from iotnav.cli._common import console, user_errors

__all__ = ["register"]


def register(app: typer.Typer) -> None:
    """Register the ``firmware`` sub-app (``export``) on ``app``."""
    fw_app = typer.Typer(help="C99 firmware library of the engines (firmware/).", no_args_is_help=True)
    app.add_typer(fw_app, name="firmware")

    @fw_app.command("export")
    @user_errors
    def export_cmd(
        out: Annotated[
            Path, typer.Option(help="Folder to write the library and its configuration header into.")
        ],
        engine: Annotated[str, typer.Option(help="Engine: anchor, fixes or pipeline.")] = "anchor",
        config: Annotated[
            Path | None,
            typer.Option(
                help="Tuned TOML, as iotnav run reads it (anchor: [anchor.kf]; fixes: [kf], [gate], ...; "
                "pipeline: [static], [mount], [fusion], [pipeline], ...)."
            ),
        ] = None,
    ) -> None:
        """Write the engine's C library with the configuration header holding CONFIG's parameters."""
        from iotnav.engines.anchor import AnchorConfig
        from iotnav.engines.config import config_from_toml
        from iotnav.firmware.gen import export
        from iotnav.firmware.host import FIRMWARE_DIR

        if engine == "fixes":
            from iotnav.engines.fixes import FixesConfig

            fcfg = FixesConfig() if config is None else FixesConfig.from_toml(config)
            for f in export(out, fcfg, FIRMWARE_DIR, engine="fixes"):
                console.print(f"wrote {f}")
            return
        if engine == "pipeline":
            from iotnav.engines.config import PipelineConfig
            from iotnav.firmware import pipeline_engine

            pcfg = PipelineConfig() if config is None else PipelineConfig.from_toml(config)
            for f in pipeline_engine.export(out, pcfg, FIRMWARE_DIR):
                console.print(f"wrote {f}")
            return
        if engine != "anchor":
            raise ValueError(f"engine {engine!r} has no C library; available: anchor, fixes, pipeline")
        cfg = AnchorConfig() if config is None else config_from_toml(config, AnchorConfig(), "anchor")
        files = export(out, cfg.kf, FIRMWARE_DIR)
        default = AnchorConfig()
        left = [
            f.name
            for f in dataclasses.fields(cfg)
            if f.name != "kf" and getattr(cfg, f.name) != getattr(default, f.name)
        ]
        for f in files:
            console.print(f"wrote {f}")
        if left:
            tables = ", ".join(f"anchor.{n}" for n in left)
            console.print(
                f"[yellow]not exported:[/] tuned tables {tables}: the attitude cascade is not in the C "
                "library (anchor_step_imu takes C_nb and the tilt / yaw covariance traces as input)"
            )
