"""Error statistics of a track against a truth track.

Both tables carry ``t`` (device time, s) and geodetic ``lat``/``lon`` (degrees) with an
optional ``height`` (m). Truth is interpolated linearly to the track's times (only inside the
truth's time span; outside rows are left out and counted). Errors are expressed in a local NED
frame anchored at the first truth point:

    n_err = north_track - north_truth,   e_err = east_track - east_truth,
    h_err = sqrt(n_err^2 + e_err^2).

:func:`error_stats` returns, in metres, ``h_err_mean``, ``h_err_rms``, ``h_err_p50``,
``h_err_p67``, ``h_err_p95``, ``h_err_max`` and the same statistics of ``|n_err|`` and
``|e_err|`` (``n_err_*``, ``e_err_*``) as the seed papers tabulate them (mean, 67 % and 95 % of
the absolute North and East errors), plus the signed means ``n_err_bias``/``e_err_bias``.
These key names are stable: scripts depend on them.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import numpy.typing as npt
import pandas as pd

from iotnav.geo import LocalFrame
from iotnav.io.export import track_columns

FloatArray = npt.NDArray[np.float64]


@dataclass(frozen=True)
class Errors:
    """Per-epoch errors of a track against truth.

    Attributes
    ----------
    t : numpy.ndarray
        Device time, s.
    n_err, e_err, d_err : numpy.ndarray
        North, East, Down error, m (track minus truth).
    h_err : numpy.ndarray
        Horizontal error, m.
    outside_truth : int
        Track rows outside the truth's time span (left out).
    """

    t: FloatArray
    n_err: FloatArray
    e_err: FloatArray
    d_err: FloatArray
    h_err: FloatArray
    outside_truth: int


def _geodetic(df: pd.DataFrame) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray]:
    tcol, lat, lon, h = track_columns(df)
    t = df["t"].to_numpy(dtype=float) if "t" in df.columns else df[tcol].to_numpy(dtype=float)
    height = df[h].to_numpy(dtype=float) if h else np.zeros(len(df))
    return t, df[lat].to_numpy(dtype=float), df[lon].to_numpy(dtype=float), height


def track_errors(track: pd.DataFrame, truth: pd.DataFrame) -> Errors:
    """Errors of ``track`` against ``truth`` interpolated to the track times.

    Parameters
    ----------
    track, truth : pandas.DataFrame
        Tables with ``t`` (s), ``lat``/``lon`` (deg) and optionally ``height`` (m).

    Returns
    -------
    Errors
        NED and horizontal errors, m.
    """
    tt, lat_t, lon_t, h_t = _geodetic(truth)
    order = np.argsort(tt, kind="stable")
    tt, lat_t, lon_t, h_t = tt[order], lat_t[order], lon_t[order], h_t[order]
    frame = LocalFrame(float(lat_t[0]), float(lon_t[0]), float(h_t[0]))
    truth_ned = frame.to_ned(lat_t, lon_t, h_t)
    t, lat, lon, h = _geodetic(track)
    inside = (t >= tt[0]) & (t <= tt[-1]) & np.isfinite(lat) & np.isfinite(lon)
    t = t[inside]
    ned = frame.to_ned(lat[inside], lon[inside], np.where(np.isfinite(h[inside]), h[inside], 0.0))
    ref = np.column_stack([np.interp(t, tt, truth_ned[:, k]) for k in range(3)])
    err = ned - ref
    return Errors(
        t=t,
        n_err=err[:, 0],
        e_err=err[:, 1],
        d_err=err[:, 2],
        h_err=np.hypot(err[:, 0], err[:, 1]),
        outside_truth=int((~inside).sum()),
    )


def _stats(prefix: str, x: FloatArray) -> dict[str, float]:
    if x.size == 0:
        return {f"{prefix}_{k}": float("nan") for k in ("mean", "rms", "p50", "p67", "p95", "max")}
    return {
        f"{prefix}_mean": float(np.mean(x)),
        f"{prefix}_rms": float(np.sqrt(np.mean(x**2))),
        f"{prefix}_p50": float(np.percentile(x, 50)),
        f"{prefix}_p67": float(np.percentile(x, 67)),
        f"{prefix}_p95": float(np.percentile(x, 95)),
        f"{prefix}_max": float(np.max(x)),
    }


def error_stats(err: Errors) -> dict[str, float]:
    """Summary statistics of :class:`Errors` (metres; keys documented in the module)."""
    out: dict[str, float] = {"n": float(err.t.size), "outside_truth": float(err.outside_truth)}
    out.update(_stats("h_err", err.h_err))
    out.update(_stats("n_err", np.abs(err.n_err)))
    out.update(_stats("e_err", np.abs(err.e_err)))
    out["n_err_bias"] = float(np.mean(err.n_err)) if err.t.size else float("nan")
    out["e_err_bias"] = float(np.mean(err.e_err)) if err.t.size else float("nan")
    return out


def path_length(north: FloatArray, east: FloatArray) -> float:
    """Horizontal length of a polyline, m (sum of step lengths)."""
    return float(np.sum(np.hypot(np.diff(north), np.diff(east))))


def outage_drift(
    err: Errors, truth: pd.DataFrame, outages: list[tuple[float, float]]
) -> list[dict[str, float]]:
    """Horizontal error at the end of each outage and the distance driven during it.

    Parameters
    ----------
    err : Errors
        Track errors (from :func:`track_errors`).
    truth : pandas.DataFrame
        Truth with ``t``, ``lat``, ``lon`` (used for the distance travelled).
    outages : list of (start, end)
        Outage windows, device time s.

    Returns
    -------
    list of dict
        Per outage: ``start``, ``end``, ``length_s``, ``distance_m`` (true horizontal path
        length), ``end_error_m`` (horizontal error at the last track epoch inside the window),
        ``max_error_m`` and ``drift_pct`` = 100 * end error / distance.
    """
    tt, lat, lon, h = _geodetic(truth)
    frame = LocalFrame(float(lat[0]), float(lon[0]), float(h[0]))
    ned = frame.to_ned(lat, lon, h)
    out = []
    for start, end in outages:
        sel = (err.t >= start) & (err.t <= end)
        tsel = (tt >= start) & (tt <= end)
        if not sel.any() or tsel.sum() < 2:
            continue
        dist = path_length(ned[tsel, 0], ned[tsel, 1])
        e_end = float(err.h_err[sel][-1])
        out.append(
            {
                "start": float(start),
                "end": float(end),
                "length_s": float(end - start),
                "distance_m": dist,
                "end_error_m": e_end,
                "max_error_m": float(err.h_err[sel].max()),
                "drift_pct": 100.0 * e_end / dist if dist > 0 else float("nan"),
            }
        )
    return out
