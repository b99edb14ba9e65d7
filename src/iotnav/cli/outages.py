"""``iotnav study outages DATASET``: real-data GNSS-outage benchmark (issue #5).

The study itself is :func:`iotnav.eval.outages.study`; this module reads the dataset folder
and prints / writes the tables.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Annotated

import typer
from rich.table import Table

from iotnav.cli._common import console, parse_positive_floats, progress, user_errors
from iotnav.eval.outages import DATASETS, DatasetProfile, OutageConfig, OutageResult
from iotnav.io.log import Log

__all__ = ["load_dataset", "register"]


def load_dataset(folder: Path, profile: str | None = None) -> tuple[Log, DatasetProfile]:
    """Ingest one rtklibexplorer recording (RTK ``.pos`` and raw IMU csv with its ``.tag``).

    Parameters
    ----------
    folder : Path
        ``drive_0708`` or ``walk_0827`` folder.
    profile : str, optional
        Profile name (default: the folder name).

    Returns
    -------
    Log, DatasetProfile
        The merged log (GNSS = the RTK solution) and the recording's profile.

    Raises
    ------
    ValueError
        For an unknown profile; FileNotFoundError when a file is missing.
    """
    from iotnav.io import ingest

    name = profile or folder.name
    if name not in DATASETS:
        raise ValueError(
            f"{folder}: unknown recording {name!r}; expected a folder named one of {', '.join(DATASETS)} "
            "(or give --profile)"
        )
    prof = DATASETS[name]
    files = [folder / prof.pos_file, folder / prof.imu_file]
    for f in files:
        if not f.exists():
            raise FileNotFoundError(f"{f}: missing (expected the rtklibexplorer {name} files)")
    return ingest(files), prof


def _num(v: object) -> str:
    x = float(v)  # type: ignore[arg-type]
    return "-" if math.isnan(x) else f"{x:.2f}"


def _print(res: OutageResult) -> None:
    t = Table(title=f"{res.meta['dataset']}: horizontal error through GNSS outages")
    for col in ("engine", "outage (s)", "windows", "RMS outside (m)", "median drift %", "worst drift %"):
        t.add_column(col, justify="left" if col == "engine" else "right")
    for _, r in res.summary.iterrows():
        t.add_row(
            str(r["engine"]),
            f"{float(r['length_s']):g}",
            str(r["n_windows"]),
            *(_num(r[k]) for k in ("rms_outside_m", "median_drift_pct", "worst_drift_pct")),
        )
    console.print(t)
    m = Table(title="mount found vs the author's (deg)")
    cols = (
        "roll_deg",
        "pitch_deg",
        "yaw_deg",
        "author_roll_deg",
        "author_pitch_deg",
        "author_yaw_deg",
        "apart_deg",
    )
    m.add_column("engine")
    for col in cols:
        m.add_column(col.removesuffix("_deg").replace("_", " "), justify="right")
    for _, r in res.mount.iterrows():
        m.add_row(str(r["engine"]), *(_num(r[k]) for k in cols))
    console.print(m)


def register(study_app: typer.Typer) -> None:
    """Add the ``outages`` command to the ``iotnav study`` sub-app."""

    @study_app.command("outages")
    @user_errors
    def outages_cmd(
        dataset: Annotated[Path, typer.Argument(help="drive_0708 or walk_0827 folder (rtklibexplorer).")],
        engines: Annotated[
            str, typer.Option(help="Engines, comma separated (qekf-consistent: QekfConfig.consistent).")
        ] = "pipeline,anchor,qekf,qekf-consistent,eskf",
        lengths: Annotated[str, typer.Option(help="Outage lengths, s, comma separated.")] = "15,30,60",
        spacing_s: Annotated[float, typer.Option(help="A window starts every this many s.")] = 60.0,
        first_offset_s: Annotated[
            float, typer.Option(help="The first window starts this long after motion begins, s.")
        ] = 60.0,
        seed: Annotated[int, typer.Option(help="Seed of the GNSS degradation.")] = 0,
        environment: Annotated[str, typer.Option(help="Simulator GNSS environment.")] = "open-sky",
        max_duration_s: Annotated[
            float | None, typer.Option(help="Use only the first this many s of the recording.")
        ] = None,
        profile: Annotated[str | None, typer.Option(help="Recording profile (default: folder name).")] = None,
        markdown: Annotated[Path | None, typer.Option(help="Also write the tables as markdown here.")] = None,
    ) -> None:
        """Dead reckoning through 15/30/60 s GNSS outages on a real drive or walk (RTK as truth)."""
        from iotnav.eval.outages import format_markdown, rtk_truth, study

        lens = parse_positive_floats(lengths, "--lengths", "outage lengths")
        cfg = OutageConfig(
            lengths_s=lens,
            spacing_s=spacing_s,
            first_offset_s=first_offset_s,
            seed=seed,
            environment=environment,
            engines=tuple(e.strip() for e in engines.split(",") if e.strip()),
            max_duration_s=max_duration_s,
        )
        log, prof = load_dataset(dataset, profile)
        with progress("outage study", total=None):
            res = study(log, rtk_truth(log.gnss), prof, cfg)
        _print(res)
        if markdown is not None:
            markdown.parent.mkdir(parents=True, exist_ok=True)
            markdown.write_text(format_markdown(res) + "\n")
            console.print(f"tables written to {markdown}")
