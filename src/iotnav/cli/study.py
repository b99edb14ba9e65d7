"""``iotnav study``: parametric studies on simulated scenarios (``fix-interval``; more to come).

Also holds :func:`run_fixes`, the code behind ``iotnav run --fixes FILE``.
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from typing import Annotated, Any

import pandas as pd
import typer
from rich.table import Table

from iotnav.cli._common import console, parse_positive_floats, parse_sets, progress, user_errors

__all__ = ["register", "run_fixes", "study_app"]

#: The ``study`` sub-app; other modules add their studies with ``@study_app.command(...)``.
study_app = typer.Typer(
    name="study",
    help="Studies: paper tables on simulated scenarios, outages on real drives.",
    no_args_is_help=True,
)


def run_fixes(
    log: Any,
    fixes_path: Path,
    engine: str = "absfix",
    config: Path | None = None,
    advance: Callable[[int], None] | None = None,
) -> pd.DataFrame:
    """Fuse a log with an absolute-fix file (``iotnav run --fixes FILE``).

    Parameters
    ----------
    log : iotnav.io.Log
        The ingested IMU (and other) samples.
    fixes_path : Path
        Fixes file (:func:`iotnav.io.fixes.read_fixes`: CSV or JSON lines).
    engine : str
        ``absfix`` (the only engine that takes fixes in this version).
    config : Path, optional
        ``[absfix]`` TOML configuration.
    advance : callable, optional
        Progress hook.

    Returns
    -------
    pandas.DataFrame
        The track (:func:`iotnav.engines.absfix.run_with_fixes`); ``attrs["summary"]`` also holds
        ``fixes_ingest`` (the fixes file report).

    Raises
    ------
    ValueError
        For another engine, or when the log has no IMU samples.
    """
    from iotnav.engines.absfix import AbsfixConfig, AbsfixEngine, run_with_fixes
    from iotnav.io.fixes import read_fixes

    if engine != "absfix":
        raise ValueError(
            f"--fixes is used by the absfix engine; engine {engine!r} does not take absolute fixes yet "
            "(use --engine absfix)"
        )
    if len(log.imu) == 0:
        raise ValueError("--fixes needs IMU samples (give an IMU file or a log directory with imu.csv)")
    fx = read_fixes(fixes_path)
    cfg = AbsfixConfig.from_toml(config) if config is not None else AbsfixConfig()
    track = run_with_fixes(AbsfixEngine(cfg), log, fx.table, progress=advance)
    summary = dict(track.attrs.get("summary", {}))
    summary["fixes_ingest"] = fx.report.to_dict()
    summary["fixes_position_frame"] = fx.position_frame
    track.attrs["summary"] = summary
    return track


def register(app: typer.Typer) -> None:
    """Add the ``study`` sub-app (fix-interval, outages) to ``app``."""
    from iotnav.cli import outages

    outages.register(study_app)
    app.add_typer(study_app, name="study")


@study_app.command("fix-interval")
@user_errors
def fix_interval_cmd(
    scenario: Annotated[str, typer.Option(help="Scenario with absolute fixes.")] = "pedestrian-fixes",
    seed: Annotated[int, typer.Option(help="First seed.")] = 0,
    runs: Annotated[int, typer.Option(min=1, help="Monte Carlo runs per interval.")] = 1,
    intervals: Annotated[str, typer.Option(help="Times between fixes, s, comma separated.")] = "1,2,5",
    preset: Annotated[
        str, typer.Option(help="IMU preset: 3dm-gx3-35 (Microstrain) or smartphone.")
    ] = "3dm-gx3-35",
    sigma_pos_m: Annotated[
        float, typer.Option(help="Fix position 1-sigma, m (total station: 0.002).")
    ] = 0.002,
    sigma_att_rad: Annotated[float, typer.Option(help="Fix attitude 1-sigma, rad.")] = 0.001,
    latency_s: Annotated[float, typer.Option(help="Fix latency t_arrival - t_valid, s.")] = 0.0,
    denoise: Annotated[str, typer.Option(help="off, batch or streaming wavelet denoising.")] = "off",
    revised: Annotated[bool, typer.Option(help="Evaluate the latency-compensated track.")] = False,
    set_: Annotated[
        list[str] | None, typer.Option("--set", help="Scenario override key=value (repeatable).")
    ] = None,
    markdown: Annotated[Path | None, typer.Option(help="Also write the tables as markdown here.")] = None,
) -> None:
    """Errors of the absfix engine with fixes every 1, 2 and 5 s (Dabove et al. 2016, Tables 3-7)."""
    from iotnav.eval.fix_interval import PAPER_TABLE_4, FixIntervalConfig, format_tables, study

    ivals = parse_positive_floats(intervals, "--intervals", "times")
    cfg = FixIntervalConfig(
        scenario=scenario,
        intervals_s=ivals,
        runs=runs,
        seed=seed,
        sigma_pos_m=sigma_pos_m,
        sigma_att_rad=sigma_att_rad,
        latency_s=latency_s,
        preset=preset,
        denoise=denoise,
        revised=revised,
        overrides=tuple(parse_sets(set_).items()),
    )
    with progress("fix-interval study", total=None):
        df = study(cfg)
    for mode in cfg.modes:
        sub = df[df["mode"] == mode].set_index("interval_s")
        table = Table(title=f"absfix, bias/drift from {mode}: |error| in m ({runs} run(s), {preset})")
        table.add_column("axis")
        for t in ivals:
            for what in ("mean", "67 %", "95 %"):
                table.add_column(f"{t:g} s {what}", justify="right")
        for axis, key in (("N", "n"), ("E", "e")):
            table.add_row(
                axis,
                *(f"{sub[f'{key}_{s}'].to_dict()[t]:.3f}" for t in ivals for s in ("mean", "p67", "p95")),
            )
        console.print(table)
    paper = Table(title="paper, Table 4 (drift estimation from images), m")
    paper.add_column("axis")
    for t in sorted(PAPER_TABLE_4):
        for what in ("mean", "67 %", "95 %"):
            paper.add_column(f"{t:g} s {what}", justify="right")
    for axis in ("N", "E"):
        paper.add_row(axis, *(f"{v:.2f}" for t in sorted(PAPER_TABLE_4) for v in PAPER_TABLE_4[t][axis]))
    console.print(paper)
    if markdown is not None:
        markdown.parent.mkdir(parents=True, exist_ok=True)
        markdown.write_text(format_tables(df) + "\n")
        console.print(f"tables written to {markdown}")
