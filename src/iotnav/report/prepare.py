"""Tables a report draws, derived from runs: one local frame, gaps, periods, event tables.

Nothing here is navigation maths: positions are only re-expressed in one local NED frame
(:class:`iotnav.geo.LocalFrame`) so that every run, the raw fixes and the truth share axes;
statistics come from :mod:`iotnav.eval.metrics`.

Frame of the figures: anchored at the first truth point when a truth is given (the frame of
:func:`iotnav.eval.metrics.track_errors`), else at the first valid GNSS fix of the first run,
else at its first output position. Columns ``n_m``/``e_m`` are North/East in that frame, m.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np
import pandas as pd

from iotnav.eval.metrics import Errors, error_stats, outage_drift, track_errors
from iotnav.geo import LocalFrame
from iotnav.report.load import Run, Truth

GNSS_ONLY = "GNSS only (valid fixes)"


def make_frame(runs: list[Run], truth: Truth | None) -> LocalFrame:
    """The local frame all figures share (see the module docstring).

    Raises
    ------
    ValueError
        When no position exists anywhere (no truth, no valid fix, no output position).
    """
    if truth is not None:
        r = truth.table.iloc[0]
        return LocalFrame(float(r["lat"]), float(r["lon"]), float(r.get("height", 0.0) or 0.0))
    for run in runs:
        g = valid_fixes(run)
        if len(g):
            h = float(g["height_m"].iloc[0]) if "height_m" in g.columns else 0.0
            return LocalFrame(
                float(g["lat_deg"].iloc[0]), float(g["lon_deg"].iloc[0]), h if math.isfinite(h) else 0.0
            )
    for run in runs:
        tr = positioned(run.track)
        if len(tr):
            h = float(tr["height"].iloc[0]) if "height" in tr.columns else 0.0
            return LocalFrame(
                float(tr["lat"].iloc[0]), float(tr["lon"].iloc[0]), h if math.isfinite(h) else 0.0
            )
    raise ValueError("nothing to draw: no truth, no valid GNSS fix and no output position in the run(s)")


def positioned(track: pd.DataFrame) -> pd.DataFrame:
    """Rows of a track with a finite latitude and longitude."""
    ok = np.isfinite(track["lat"].to_numpy(float)) & np.isfinite(track["lon"].to_numpy(float))
    return track.loc[ok]


def valid_fixes(run: Run) -> pd.DataFrame:
    """Valid GNSS epochs of a run with a position (empty when ``gnss.csv`` is missing)."""
    g = run.gnss
    if g is None:
        return pd.DataFrame({"t": [], "lat_deg": [], "lon_deg": []})
    ok = g["valid"].to_numpy(bool) & np.isfinite(g["lat_deg"].to_numpy(float))
    return g.loc[ok & np.isfinite(g["lon_deg"].to_numpy(float))]


def local(df: pd.DataFrame, frame: LocalFrame, lat: str = "lat", lon: str = "lon") -> pd.DataFrame:
    """A copy of ``df`` (rows with a position) with ``n_m``, ``e_m`` in ``frame``, m."""
    ok = np.isfinite(df[lat].to_numpy(float)) & np.isfinite(df[lon].to_numpy(float))
    out = df.loc[ok].copy()
    hcol = next((c for c in ("height", "height_m") if c in out.columns), None)
    h = out[hcol].to_numpy(float) if hcol else np.zeros(len(out))
    h = np.where(np.isfinite(h), h, frame.h0_m)
    ned = frame.to_ned(out[lat].to_numpy(float), out[lon].to_numpy(float), h)
    out["n_m"] = ned[..., 0] if len(out) else np.zeros(0)
    out["e_m"] = ned[..., 1] if len(out) else np.zeros(0)
    return out


def gnss_outages(
    gnss: pd.DataFrame | None, factor: float = 3.0, t_end: float = math.nan
) -> list[tuple[float, float]]:
    """Gaps between consecutive valid fixes longer than ``factor`` times the median interval.

    A gap after the last valid fix up to ``t_end`` (the end of the run) counts too; the time
    before the first valid fix does not (that is the boot).

    Parameters
    ----------
    gnss : pandas.DataFrame or None
        GNSS epochs with ``t`` and ``valid`` (and ``lat_deg``).
    factor : float
        A gap counts as an outage when it exceeds ``factor * median(dt)``.
    t_end : float
        End of the run, s (NaN: no trailing outage).

    Returns
    -------
    list of (start, end)
        Device time (s) of the last fix before and the first fix after each gap (``t_end``
        for a trailing one).
    """
    if gnss is None or len(gnss) < 3:
        return []
    ok = gnss["valid"].to_numpy(bool) & np.isfinite(gnss["lat_deg"].to_numpy(float))
    t = np.sort(gnss["t"].to_numpy(float)[ok])
    if t.size < 3:
        return []
    dt = np.diff(t)
    med = float(np.median(dt))
    if not med > 0:
        return []
    idx = np.flatnonzero(dt > factor * med)
    out = [(float(t[i]), float(t[i + 1])) for i in idx]
    if math.isfinite(t_end) and t_end - t[-1] > factor * med:
        out.append((float(t[-1]), float(t_end)))
    return out


def periods(t: np.ndarray, flag: np.ndarray) -> list[tuple[float, float]]:
    """Contiguous runs of ``flag`` True as (first, last) times."""
    f = np.asarray(flag, bool)
    if f.size == 0:
        return []
    edges = np.diff(np.concatenate([[0], f.astype(np.int8), [0]]))
    starts, ends = np.flatnonzero(edges == 1), np.flatnonzero(edges == -1) - 1
    return [(float(t[a]), float(t[b])) for a, b in zip(starts, ends, strict=True)]


def static_periods(run: Run) -> list[tuple[float, float]]:
    """Periods the engine declared static (``static`` column of the track)."""
    if "static" not in run.track.columns:
        return []
    return periods(run.track["t"].to_numpy(float), run.track["static"].to_numpy(bool))


def events_of(run: Run, *types: str) -> list[dict[str, Any]]:
    """Events of the given types, in file order."""
    return [e for e in run.events if e.get("type") in types]


def rejected_fixes(run: Run) -> pd.DataFrame:
    """``fix_rejected`` events joined with the GNSS epoch at the same time (position, PDOP).

    Returns
    -------
    pandas.DataFrame
        ``t``, ``reason`` and, where the epoch is found in ``gnss.csv`` (time within 1 ms),
        ``lat_deg``, ``lon_deg``, ``pdop`` (NaN otherwise).
    """
    ev = events_of(run, "fix_rejected")
    df = pd.DataFrame(
        {"t": [e["t"] for e in ev], "reason": [str(e.get("reason", "?")) for e in ev]},
        columns=["t", "reason"],
    )
    for c in ("lat_deg", "lon_deg", "pdop"):
        df[c] = np.nan
    g = run.gnss
    if g is None or not len(df) or not len(g):
        return df
    gt = g["t"].to_numpy(float)
    order = np.argsort(gt, kind="stable")
    gt = gt[order]
    t = df["t"].to_numpy(float)
    i = np.clip(np.searchsorted(gt, t), 1, len(gt) - 1) if len(gt) > 1 else np.zeros(len(t), int)
    if len(gt) > 1:
        i = np.where(np.abs(gt[i - 1] - t) <= np.abs(gt[i] - t), i - 1, i)
    hit = np.abs(gt[i] - t) <= 1e-3
    for c in ("lat_deg", "lon_deg", "pdop"):
        if c in g.columns:
            vals = g[c].to_numpy(float)[order][i]
            df[c] = np.where(hit, vals, np.nan)
    return df


def mount_table(run: Run) -> pd.DataFrame:
    """``mount_estimate`` events: ``t``, ``accepted``, ``mount_yaw_rad`` (current), ``candidate_rad``, ``std_rad``."""
    ev = events_of(run, "mount_estimate")
    return pd.DataFrame(
        {
            "t": [e["t"] for e in ev],
            "accepted": [bool(e.get("accepted", False)) for e in ev],
            "mount_yaw_rad": [_f(e.get("mount_yaw_rad")) for e in ev],
            "candidate_rad": [_f(e.get("candidate_rad", e.get("mount_yaw_rad"))) for e in ev],
            "std_rad": [_f(e.get("std_rad")) for e in ev],
        },
        columns=["t", "accepted", "mount_yaw_rad", "candidate_rad", "std_rad"],
    )


def nis_table(run: Run) -> pd.DataFrame:
    """Events carrying a finite ``nis``: ``t``, ``measurement`` (or the event type), ``nis``."""
    rows = [
        (e["t"], str(e.get("measurement", e.get("reason", e["type"]))), _f(e.get("nis")))
        for e in run.events
        if math.isfinite(_f(e.get("nis")))
    ]
    return pd.DataFrame(rows, columns=["t", "measurement", "nis"])


def _f(v: Any) -> float:
    try:
        return float(v)
    except (TypeError, ValueError):
        return math.nan


@dataclass(frozen=True)
class Boot:
    """What happened at boot.

    Attributes
    ----------
    stored : tuple of (lat_deg, lon_deg) or None
        Stored last position loaded at boot.
    first_fix_t : float
        Time of the first accepted fix (NaN when none).
    rejected_before : pandas.DataFrame
        Rejected fixes before the first accepted one (see :func:`rejected_fixes`).
    moved_m : float
        ``moved_while_off`` distance, m (NaN when not raised).
    """

    stored: tuple[float, float] | None
    first_fix_t: float
    rejected_before: pd.DataFrame
    moved_m: float

    @property
    def interesting(self) -> bool:
        """True when there is something to draw (stored position or rejected fixes)."""
        return self.stored is not None or len(self.rejected_before) > 0


def boot_info(run: Run) -> Boot:
    """Collect the boot sequence of a run from its events."""
    stored = None
    for e in events_of(run, "boot"):
        lat, lon = _f(e.get("lat_deg", e.get("lat"))), _f(e.get("lon_deg", e.get("lon")))
        if math.isfinite(lat) and math.isfinite(lon):
            stored = (lat, lon)
    ff = events_of(run, "first_fix")
    t_ff = float(ff[0]["t"]) if ff else math.nan
    rej = rejected_fixes(run)
    before = rej.loc[rej["t"] < t_ff] if math.isfinite(t_ff) else rej
    moved = events_of(run, "moved_while_off")
    return Boot(
        stored, t_ff, before.reset_index(drop=True), _f(moved[0].get("distance_m")) if moved else math.nan
    )


def gnss_only_errors(run: Run, truth: Truth) -> Errors | None:
    """Errors of the run's valid raw fixes against truth (None without ``gnss.csv``)."""
    g = valid_fixes(run)
    if not len(g):
        return None
    cols = ["t", "lat_deg", "lon_deg"] + (["height_m"] if "height_m" in g.columns else [])
    return track_errors(g[cols], truth.table)


def accuracy(runs: list[Run], truth: Truth) -> tuple[dict[str, Errors], dict[str, dict[str, float]]]:
    """Per-run errors and :func:`iotnav.eval.metrics.error_stats`, GNSS-only baseline first.

    The baseline uses the first run's ``gnss.csv``; a run whose GNSS input differs gets its own
    baseline row (``GNSS only (label)``).
    """
    errs: dict[str, Errors] = {}
    base_gnss: list[pd.DataFrame] = []
    for run in runs:
        g = valid_fixes(run)
        if not len(g):
            continue
        same = any(
            len(b) == len(g) and np.array_equal(b["t"].to_numpy(), g["t"].to_numpy()) for b in base_gnss
        )
        if same:
            continue
        name = GNSS_ONLY if not base_gnss else f"GNSS only ({run.label})"
        e = gnss_only_errors(run, truth)
        if e is not None:
            errs[name] = e
            base_gnss.append(g)
    for run in runs:
        errs[run.label] = track_errors(positioned(run.track), truth.table)
    return errs, {k: error_stats(v) for k, v in errs.items()}


def drift_table(err: Errors, truth: Truth, outages: list[tuple[float, float]]) -> list[dict[str, float]]:
    """:func:`iotnav.eval.metrics.outage_drift` for the report (empty when no outage)."""
    if not outages:
        return []
    return outage_drift(err, truth.table, outages)


def trips_table(run: Run) -> tuple[pd.DataFrame, bool]:
    """The run's trips and stops: ``trips.csv``, or the vocabulary of ``track.csv`` without one.

    Returns
    -------
    table : pandas.DataFrame
        :data:`iotnav.tracker.TRIP_COLUMNS`.
    from_file : bool
        False when computed here (:func:`iotnav.tracker.describe` of the track).

    Raises
    ------
    ValueError
        When the file exists but lacks columns of :data:`iotnav.tracker.TRIP_COLUMNS`.
    """
    from iotnav.tracker import TRIP_COLUMNS, describe

    path = run.path / "trips.csv"
    if not path.is_file():
        return describe(run.track, engine_events=[]).trips, False
    df = pd.read_csv(path)
    missing = [c for c in TRIP_COLUMNS if c not in df.columns]
    if missing:
        raise ValueError(f"{path}: missing column(s) {', '.join(missing)}")
    df["open"] = df["open"].astype(str).str.lower().isin(("true", "1", "1.0"))
    return df, True
