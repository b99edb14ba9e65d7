"""Run directories: where a run's inputs are found and how its outputs are written.

Shared by ``iotnav run``, ``iotnav run-many`` (:mod:`iotnav.fleet`) and ``iotnav demo``; no
terminal code here. A run writes ``track.csv``, ``events.json``, ``summary.json``, ``gnss.csv``,
``track.geojson``, ``track.gpx`` and ``trips.csv`` (the tracker's vocabulary,
:mod:`iotnav.tracker`) into its output directory.
"""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from iotnav.io import Log
from iotnav.io.export import MAP_RATE_HZ, export_track, write_csv, write_table
from iotnav.techniques.last_position import StoredPosition
from iotnav.tracker import Zone, describe, zones_from_geojson

#: Files that make a directory a Sensor Logger export (:func:`iotnav.io.phone.read_sensor_logger`).
SENSOR_LOGGER_FILES = (
    "Location.csv",
    "Gyroscope.csv",
    "TotalAcceleration.csv",
    "Accelerometer.csv",
    "Magnetometer.csv",
)


def load_stored_position(path: Path) -> StoredPosition | None:
    """Read a last-known-position file: iotnav's store (``lat_deg``...) or the simulator's (``lat``...).

    Returns None when the file does not exist; raises ValueError when it exists but is unusable.
    """
    if not path.is_file():
        return None
    try:
        d = json.loads(path.read_text())
        lat = float(d.get("lat_deg", d.get("lat")))
        lon = float(d.get("lon_deg", d.get("lon")))
        h = float(d.get("height_m", d.get("height", 0.0)))
    except (ValueError, TypeError, AttributeError) as exc:
        raise ValueError(f"{path}: not a last-position file (need lat/lon[/height]): {exc}") from None
    if not (math.isfinite(lat) and math.isfinite(lon) and abs(lat) <= 90 and abs(lon) <= 180):
        raise ValueError(f"{path}: last position out of range ({lat}, {lon})")
    return StoredPosition(lat, lon, h, float(d.get("t", math.nan)), float(d.get("mount_yaw_rad", math.nan)))


def _json_default(o: Any) -> Any:
    if isinstance(o, (np.floating, np.integer)):
        return o.item()
    if isinstance(o, np.ndarray):
        return o.tolist()
    if isinstance(o, float) and not math.isfinite(o):
        return None
    return str(o)


def _clean(o: Any) -> Any:
    """Replace NaN/inf with None recursively so the JSON is standard."""
    if isinstance(o, dict):
        return {k: _clean(v) for k, v in o.items()}
    if isinstance(o, (list, tuple)):
        return [_clean(v) for v in o]
    if isinstance(o, float) and not math.isfinite(o):
        return None
    return o


def events_json(events: list[dict[str, Any]]) -> str:
    """The text of events.json: a JSON array with one event per line.

    Each event is encoded compactly (``json.dumps`` without ``indent`` uses the C encoder; with
    an indent Python 3.11 falls back to its pure-Python one, which took seconds on runs with
    tens of thousands of events); NaN and infinity are written as ``null``.
    """
    if not events:
        return "[]\n"
    lines = (json.dumps(_clean(e), default=_json_default) for e in events)
    return "[\n" + ",\n".join(lines) + "\n]\n"


def load_zones(path: Path) -> list[Zone]:
    """Geofences of a GeoJSON file (:func:`iotnav.tracker.zones_from_geojson`).

    Raises
    ------
    ValueError
        The file is not JSON or not a zone collection (the message names the file and feature).
    """
    try:
        obj = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError) as exc:
        raise ValueError(f"{path}: cannot read the geofence file: {exc}") from None
    except json.JSONDecodeError as exc:
        raise ValueError(f"{path}: not JSON (line {exc.lineno}, column {exc.colno}): {exc.msg}") from None
    return zones_from_geojson(obj, source=str(path))


def write_run(
    out: Path,
    track: pd.DataFrame,
    log: Log,
    engine_name: str,
    runtime_s: float,
    *,
    zones: list[Zone] | None = None,
    engine_choice: dict[str, Any] | None = None,
    track_format: str = "csv",
    map_rate_hz: float = MAP_RATE_HZ,
    map_at_fixes: bool = False,
) -> dict[str, Any]:
    """Write track.csv, events.json, summary.json, gnss.csv, GeoJSON/GPX and trips.csv of a run.

    ``zones`` (geofences) add their enter/exit events; the vocabulary's trips, stops and
    odometer (:func:`iotnav.tracker.describe`) are always written. ``engine_choice`` (why this
    engine, when it was chosen for the user) goes into summary.json. ``track_format="parquet"``
    writes track.parquet instead of track.csv; the GeoJSON and GPX hold one point per
    ``1 / map_rate_hz`` seconds (every point when 0), or with ``map_at_fixes`` one point at
    each fix time of the log (the row nearest to it, :func:`iotnav.io.export.nearest_rows`).
    """
    out.mkdir(parents=True, exist_ok=True)
    # the engine's metadata is read once and the track is written without it: pandas deep-copies
    # ``attrs`` (with every event) into each frame an operation derives, which dominated the
    # writers' time on long runs (qekf21's profile of ``iotnav run``: about 1.6 s in deepcopy)
    meta: dict[Any, Any] = track.attrs
    track.attrs = {}
    try:
        summary = _write_run(
            out,
            track,
            meta,
            log,
            engine_name,
            runtime_s,
            zones,
            engine_choice,
            track_format,
            0.0 if map_at_fixes else map_rate_hz,
            map_at_fixes,
        )
    finally:
        track.attrs = meta
    return summary


def _write_run(
    out: Path,
    track: pd.DataFrame,
    meta: dict[Any, Any],
    log: Log,
    engine_name: str,
    runtime_s: float,
    zones: list[Zone] | None,
    engine_choice: dict[str, Any] | None,
    track_format: str,
    map_rate_hz: float,
    map_at_fixes: bool = False,
) -> dict[str, Any]:
    """:func:`write_run` on a track without ``attrs``; the engine's metadata in ``meta``."""
    write_table(track, out / f"track.{track_format}")
    vocab = describe(track, zones or [], engine_events=meta.get("events", []))
    write_csv(vocab.trips, out / "trips.csv", exact=("t_start", "t_end"))
    events = [*meta.get("events", []), *vocab.events]
    (out / "events.json").write_text(events_json(events))
    write_csv(log.gnss, out / "gnss.csv")
    offset = log.utc_offset_s if math.isfinite(log.utc_offset_s) else None
    g = log.gnss  # a Log's tables always have their schema's columns (io.log.Log)
    fix_t = g["t"].to_numpy(float)[g["valid"].to_numpy(bool)] if map_at_fixes else None
    for ext in ("geojson", "gpx"):
        export_track(
            track,
            out / f"track.{ext}",
            name=f"iotnav {engine_name}",
            utc_offset_s=offset,
            rate_hz=map_rate_hz,
            at_times=fix_t,
        )
    src_counts = (
        {k: v for k, v in track["source"].value_counts().to_dict().items() if v} if len(track) else {}
    )
    t = track["t"].to_numpy(float)
    summary = {
        "engine": engine_name,
        **({"engine_choice": engine_choice} if engine_choice else {}),
        "mount_yaw_rad": float(meta.get("mount_yaw_rad", math.nan)),
        "counts": {
            "output_rows": len(track),
            "gnss_epochs_in": len(log.gnss),
            "imu_samples_in": len(log.imu),
            "mag_samples_in": len(log.mag),
            "rows_by_source": src_counts,
            "static_rows": int(track["static"].sum()) if len(track) else 0,
            "events": len(events),
        },
        "rates_hz": {
            "output": float(1.0 / np.median(np.diff(t))) if t.size > 2 else math.nan,
            "gnss": log.report.timeline.get("gnss", {}).get("rate_hz", math.nan),
            "imu": log.report.timeline.get("imu", {}).get("rate_hz", math.nan),
        },
        "utc_offset_s": log.utc_offset_s,
        "runtime_s": runtime_s,
        "engine_summary": meta.get("summary", {}),
        "tracker": vocab.summary(),
        "ingest": log.report.to_dict(),
    }
    (out / "summary.json").write_text(json.dumps(_clean(summary), indent=1, default=_json_default))
    return summary


def why_no_rows(summary: dict[str, Any]) -> str:
    """Why a run wrote no output rows, from its ``summary`` (:func:`write_run`), for the user."""
    c = summary["counts"]
    engine = summary["engine"]
    skipped = summary.get("engine_summary", {}).get("skipped", {})
    parts = [f"the run produced no output rows (engine {engine}"]
    parts.append(f"{c['gnss_epochs_in']} GNSS epochs, {c['imu_samples_in']} IMU samples in)")
    head = ", ".join(parts)
    if engine != "fixes" and c["imu_samples_in"] == 0:
        return (
            f"{head}: engine {engine} outputs one row per IMU sample and the log has none; use --engine fixes"
        )
    if c["gnss_epochs_in"] == 0:
        return f"{head}: the log has no GNSS epochs"
    if skipped:
        reasons = ", ".join(f"{k} {v}" for k, v in sorted(skipped.items()))
        return f"{head}: no GNSS epoch was usable (skipped: {reasons})"
    return f"{head}: no epoch was accepted (see events.json)"


def find_inputs(
    inputs: list[Path], gnss: Path | None, imu: Path | None, mag: Path | None
) -> tuple[list[Path], Path | None]:
    """The log files of one run and its stored last position, if any.

    Parameters
    ----------
    inputs : list of Path
        Files, or directories holding ``gnss.nmea`` / ``gnss.ubx`` / ``imu.csv`` (as
        ``iotnav simulate`` writes; ``gnss.nmea`` is preferred when both GNSS files exist), or
        a Sensor Logger export directory (read as one input).
    gnss, imu, mag : Path, optional
        Files given by option.

    Returns
    -------
    files, state_file
        Files to ingest, and a directory's ``last_position.json`` when present.

    Raises
    ------
    FileNotFoundError
        A directory without any log file.
    ValueError
        Nothing given at all.
    """
    files: list[Path] = []
    state_file: Path | None = None
    for p in inputs:
        if p.is_dir():
            found = [p / n for n in ("gnss.nmea", "gnss.ubx", "imu.csv") if (p / n).exists()]
            if (p / "gnss.nmea").exists() and (p / "gnss.ubx").exists():
                found.remove(p / "gnss.ubx")  # the simulator writes both; one GNSS stream
            if not found and any((p / n).exists() for n in SENSOR_LOGGER_FILES):
                found = [p]  # a Sensor Logger export folder, as `iotnav ingest DIR` reads it
            if not found:
                raise FileNotFoundError(
                    f"{p}: no gnss.nmea / gnss.ubx / imu.csv in this directory, and not a Sensor "
                    f"Logger export ({', '.join(SENSOR_LOGGER_FILES)})"
                )
            files.extend(found)
            if (p / "last_position.json").exists():
                state_file = p / "last_position.json"
        else:
            files.append(p)
    files += [f for f in (gnss, imu, mag) if f is not None]
    if not files:
        raise ValueError("give a log directory or --gnss/--imu files")
    return files, state_file
