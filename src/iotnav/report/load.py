"""Read what ``iotnav run`` wrote, and a simulator's truth, for a report.

A run directory holds ``track.csv`` (required), ``events.json``, ``summary.json`` and
``gnss.csv`` (each optional: a report says what is missing rather than failing). A truth file
is a table with ``t`` (device time, s) and ``lat``/``lon`` (degrees), optionally ``height``,
``vn``/``ve``/``vd`` (m/s) and ``roll``/``pitch``/``yaw`` (rad, vehicle attitude); the
simulator writes one as ``truth.csv`` beside ``scenario.json``, whose ``mount_yaw_rad`` is
read when present.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

TRACK_REQUIRED = ("t", "lat", "lon")


@dataclass(frozen=True)
class Run:
    """One run directory, as read from disk.

    Attributes
    ----------
    path : pathlib.Path
        The run directory.
    label : str
        Name shown in legends and tables.
    track : pandas.DataFrame
        ``track.csv`` (columns of :class:`iotnav.engines.base.Output`).
    events : list of dict
        ``events.json`` (``t`` NaN when the run wrote null); empty when missing.
    summary : dict
        ``summary.json``; empty when missing.
    gnss : pandas.DataFrame or None
        ``gnss.csv`` (schema :data:`iotnav.io.schema.GNSS_COLUMNS`), None when missing.
    missing : tuple of str
        Names of the optional files that were not found.
    """

    path: Path
    label: str
    track: pd.DataFrame
    events: list[dict[str, Any]]
    summary: dict[str, Any]
    gnss: pd.DataFrame | None
    missing: tuple[str, ...] = field(default=())

    @property
    def engine(self) -> str:
        """Engine name from ``summary.json`` (``?`` when unknown)."""
        return str(self.summary.get("engine", "?"))

    @property
    def config(self) -> dict[str, Any]:
        """The engine configuration echoed in ``summary.json`` (empty when absent)."""
        es = self.summary.get("engine_summary") or {}
        cfg = es.get("config") if isinstance(es, dict) else None
        return cfg if isinstance(cfg, dict) else {}


@dataclass(frozen=True)
class Truth:
    """A truth trajectory.

    Attributes
    ----------
    path : pathlib.Path
        The file read.
    table : pandas.DataFrame
        ``t``, ``lat``, ``lon`` and whatever else the file has, sorted by ``t``.
    mount_yaw_rad : float
        True mount yaw from ``scenario.json`` beside the file, NaN when unknown.
    """

    path: Path
    table: pd.DataFrame
    mount_yaw_rad: float = math.nan


def _read_json(path: Path) -> Any:
    try:
        return json.loads(path.read_text())
    except json.JSONDecodeError as exc:
        raise ValueError(f"{path}: not valid JSON (line {exc.lineno}: {exc.msg})") from None


def _read_csv(path: Path, required: tuple[str, ...]) -> pd.DataFrame:
    try:
        df = pd.read_csv(path)
    except (pd.errors.ParserError, pd.errors.EmptyDataError, UnicodeDecodeError) as exc:
        raise ValueError(f"{path}: not a readable CSV table ({exc})") from None
    lacking = [c for c in required if c not in df.columns]
    if lacking:
        raise ValueError(f"{path}: missing column(s) {', '.join(lacking)}; found {list(df.columns)[:12]}")
    return df


def _num(v: Any) -> float:
    try:
        return float(v)
    except (TypeError, ValueError):
        return math.nan


def load_run(path: Path | str, label: str | None = None) -> Run:
    """Read a run directory written by ``iotnav run``.

    Parameters
    ----------
    path : pathlib.Path or str
        The directory (``OUT`` of ``iotnav run --out OUT``).
    label : str, optional
        Legend name; defaults to the directory name.

    Returns
    -------
    Run

    Raises
    ------
    FileNotFoundError
        When ``path`` is not a directory or has no ``track.csv``.
    ValueError
        When a file exists but cannot be read (the message names the file).
    """
    p = Path(path)
    if not p.is_dir():
        raise FileNotFoundError(f"{p}: not a directory (give the OUT directory of `iotnav run`)")
    if not (p / "track.csv").is_file():
        raise FileNotFoundError(f"{p}: no track.csv here (is this the OUT directory of `iotnav run`?)")
    track = _read_csv(p / "track.csv", TRACK_REQUIRED)
    if "static" in track.columns:
        track["static"] = track["static"].astype(str).str.lower().isin(("true", "1", "1.0"))
    missing: list[str] = []
    events: list[dict[str, Any]] = []
    if (p / "events.json").is_file():
        raw = _read_json(p / "events.json")
        if not isinstance(raw, list):
            raise ValueError(f"{p / 'events.json'}: expected a list of events, got {type(raw).__name__}")
        for e in raw:
            if isinstance(e, dict) and "type" in e:
                events.append({**e, "t": _num(e.get("t"))})
    else:
        missing.append("events.json")
    summary: dict[str, Any] = {}
    if (p / "summary.json").is_file():
        raw = _read_json(p / "summary.json")
        if not isinstance(raw, dict):
            raise ValueError(f"{p / 'summary.json'}: expected an object, got {type(raw).__name__}")
        summary = raw
    else:
        missing.append("summary.json")
    gnss: pd.DataFrame | None = None
    if (p / "gnss.csv").is_file():
        gnss = _read_csv(p / "gnss.csv", ("t", "lat_deg", "lon_deg"))
        if "valid" in gnss.columns:
            gnss["valid"] = gnss["valid"].astype(str).str.lower().isin(("true", "1", "1.0"))
        else:
            gnss["valid"] = np.isfinite(gnss["lat_deg"].to_numpy(float))
    else:
        missing.append("gnss.csv")
    return Run(
        path=p,
        label=label or p.resolve().name,
        track=track,
        events=events,
        summary=summary,
        gnss=gnss,
        missing=tuple(missing),
    )


def load_truth(path: Path | str) -> Truth:
    """Read a truth table (the simulator's ``truth.csv``).

    Parameters
    ----------
    path : pathlib.Path or str
        CSV with ``t`` (s), ``lat``, ``lon`` (degrees) and optional further columns.

    Returns
    -------
    Truth
        Sorted by time; ``mount_yaw_rad`` read from ``scenario.json`` beside the file.

    Raises
    ------
    FileNotFoundError
        When the file does not exist.
    ValueError
        When it is not a table with ``t``, ``lat``, ``lon`` and at least two rows.
    """
    p = Path(path)
    if not p.is_file():
        raise FileNotFoundError(f"{p}: truth file not found")
    df = _read_csv(p, TRACK_REQUIRED)
    df = df.loc[np.isfinite(df["lat"].to_numpy(float)) & np.isfinite(df["lon"].to_numpy(float))]
    if len(df) < 2:
        raise ValueError(f"{p}: a truth table needs at least two rows with lat/lon")
    df = df.sort_values("t", kind="stable").reset_index(drop=True)
    mount = math.nan
    scen = p.parent / "scenario.json"
    if scen.is_file():
        try:
            mount = _num(json.loads(scen.read_text()).get("mount_yaw_rad"))
        except (json.JSONDecodeError, AttributeError):
            mount = math.nan
    return Truth(path=p, table=df, mount_yaw_rad=mount)
