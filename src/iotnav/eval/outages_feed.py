"""Inputs of the real-data GNSS-outage study (:mod:`iotnav.eval.outages`): truth, degraded feed, windows.

The RTK epochs as truth (:func:`rtk_truth`), the tracker-grade GNSS made from them through the
simulator's receiver model (:func:`degrade_rtk`, :func:`degraded_feed`), the outage windows
over the moving part of the log (:func:`outage_windows`, :func:`mask_windows`) and the two
GNSS-only baselines evaluated at the truth epochs (:func:`gnss_hold_track`,
:func:`gnss_dr_velocity_track`). The rules are stated in :mod:`iotnav.eval.outages`. Times in
seconds, positions as WGS-84 degrees and metres, velocities in m/s (NED).
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import numpy.typing as npt
import pandas as pd

from iotnav.eval.outages_config import DatasetProfile, OutageConfig
from iotnav.geo import LocalFrame
from iotnav.io.log import Log
from iotnav.io.schema import GNSS_COLUMNS, coerce
from iotnav.sim.gnss_model import simulate_gnss

FloatArray = npt.NDArray[np.float64]


# --------------------------------------------------------------------------- inputs


def rtk_truth(rtk: pd.DataFrame) -> pd.DataFrame:
    """The untouched RTK epochs as a truth table (``t``, ``lat``, ``lon``, ``height``, velocity).

    Parameters
    ----------
    rtk : pandas.DataFrame
        GNSS table of the RTK solution (:data:`iotnav.io.schema.GNSS_COLUMNS`).

    Returns
    -------
    pandas.DataFrame
        Valid epochs, copied, with ``t``, ``lat``, ``lon``, ``height``, ``vn``, ``ve``, ``vd``,
        ``quality``.
    """
    ok = rtk["valid"].to_numpy(bool) & np.isfinite(rtk["lat_deg"].to_numpy(float))
    g = rtk.loc[ok]
    return pd.DataFrame(
        {
            "t": g["t"].to_numpy(float),
            "lat": g["lat_deg"].to_numpy(float),
            "lon": g["lon_deg"].to_numpy(float),
            "height": g["height_m"].to_numpy(float),
            "vn": g["vn"].to_numpy(float),
            "ve": g["ve"].to_numpy(float),
            "vd": g["vd"].to_numpy(float),
            "quality": g["quality"].to_numpy(),
        }
    ).reset_index(drop=True)


def _truth_ned(truth: pd.DataFrame) -> tuple[LocalFrame, FloatArray]:
    frame = LocalFrame(float(truth.lat.iloc[0]), float(truth.lon.iloc[0]), float(truth.height.iloc[0]))
    return frame, frame.to_ned(truth.lat.to_numpy(), truth.lon.to_numpy(), truth.height.to_numpy())


def degrade_rtk(truth: pd.DataFrame, config: OutageConfig) -> tuple[pd.DataFrame, dict[str, FloatArray]]:
    """Tracker-grade GNSS from RTK epochs with the simulator's receiver model.

    Parameters
    ----------
    truth : pandas.DataFrame
        Output of :func:`rtk_truth` (not modified).
    config : OutageConfig
        Rate, environment, seed.

    Returns
    -------
    pandas.DataFrame
        Fixes in :data:`iotnav.io.schema.GNSS_COLUMNS` form at ``gnss_rate_hz``, on the RTK
        epochs (the first epoch, then every ``1 / gnss_rate_hz``).
    dict
        ``err_n`` (position error added, NED, m), ``verr_n`` (velocity error, m/s), ``idx``
        (row of ``truth`` used for each fix), from :func:`iotnav.sim.gnss_model.simulate_gnss`.
    """
    t = truth["t"].to_numpy(float)
    period = 1.0 / config.gnss_rate_hz
    slot = np.floor((t - t[0]) / period + 1e-6).astype(int)
    idx = np.flatnonzero(np.r_[True, slot[1:] != slot[:-1]])
    frame, ned = _truth_ned(truth)
    v_n = truth[["vn", "ve", "vd"]].to_numpy(float)[idx]
    v_n = np.where(np.isfinite(v_n), v_n, 0.0)
    rng = np.random.default_rng(config.seed)
    df, extras = simulate_gnss(config.gnss_config(), t[idx], ned[idx], v_n, frame, 0.0, rng)
    df = df.copy()
    df["source"] = "degraded-rtk"
    out = dict(extras)
    out["idx"] = idx.astype(float)
    return coerce(df, GNSS_COLUMNS), out


def degraded_feed(
    log: Log, truth: pd.DataFrame, profile: DatasetProfile, config: OutageConfig | None = None
) -> tuple[Log, dict[str, FloatArray]]:
    """What the engines are fed: the recording's IMU, the truth degraded to tracker-grade GNSS.

    Parameters
    ----------
    log : Log
        The recording (its GNSS is not used).
    truth : pandas.DataFrame
        The RTK truth (:func:`rtk_truth`), sorted by time.
    profile : DatasetProfile
        Its ``imu_time_offset_s`` (s) is added to the IMU times.
    config : OutageConfig, optional
        Degradation settings (:func:`degrade_rtk`).

    Returns
    -------
    fed : Log
        GNSS from :func:`degrade_rtk`; IMU shifted and cut to the truth's time span.
    extras : dict
        The degradation's errors (:func:`degrade_rtk`).
    """
    t0, t1 = float(truth.t.iloc[0]), float(truth.t.iloc[-1])
    imu = log.imu.copy()
    imu["t"] = imu["t"].to_numpy(float) + profile.imu_time_offset_s
    imu = imu[(imu.t >= t0) & (imu.t <= t1)].reset_index(drop=True)
    gnss, extras = degrade_rtk(truth, config or OutageConfig())
    return Log(gnss=gnss, imu=imu), extras


def moving_part(truth: pd.DataFrame, min_speed_mps: float) -> tuple[float, float]:
    """First and last truth epoch faster than ``min_speed_mps`` (horizontal RTK velocity), s."""
    speed = np.hypot(truth["vn"].to_numpy(float), truth["ve"].to_numpy(float))
    moving = np.flatnonzero(speed > min_speed_mps)
    if moving.size == 0:
        raise ValueError(f"the truth never moves faster than {min_speed_mps} m/s")
    t = truth["t"].to_numpy(float)
    return float(t[moving[0]]), float(t[moving[-1]])


def outage_windows(
    t_start: float,
    t_end: float,
    lengths_s: Sequence[float],
    spacing_s: float,
    first_offset_s: float = 0.0,
    fix_times: FloatArray | None = None,
) -> list[tuple[float, float]]:
    """Windows ``(start, length)``: one per length at every ``spacing_s`` of ``[t_start, t_end]``.

    Nominal starts are ``t_start + first_offset_s + k spacing_s``; with ``fix_times`` each is
    moved to the first fix at or after it, so that a window of length ``L`` removes exactly the
    fixes of ``L`` seconds at 1 Hz and the next fix comes at its end. Only windows that end by
    ``t_end`` are kept; sorted by length, then start.

    Raises
    ------
    ValueError
        When a length exceeds the spacing (windows of one length would overlap).
    """
    out = []
    for L in lengths_s:
        if L > spacing_s:
            raise ValueError(f"outage length {L} s exceeds the window spacing {spacing_s} s")
        k = 0
        while (s := t_start + first_offset_s + k * spacing_s) + L <= t_end:
            if fix_times is not None:
                j = int(np.searchsorted(fix_times, s - 1e-9))
                if j >= len(fix_times):
                    break
                s = float(fix_times[j])
            if s + L > t_end:
                break
            out.append((s, float(L)))
            k += 1
    return out


def mask_windows(gnss: pd.DataFrame, windows: Sequence[tuple[float, float]]) -> pd.DataFrame:
    """GNSS table without the fixes inside any ``[start, start + length)`` window."""
    t = gnss["t"].to_numpy(float)
    drop = np.zeros(len(t), dtype=bool)
    for s, L in windows:
        drop |= (t >= s) & (t < s + L)
    return gnss.loc[~drop].reset_index(drop=True)


def gnss_hold_track(gnss: pd.DataFrame, t_eval: FloatArray) -> pd.DataFrame:
    """GNSS alone with last-position hold: the latest fix at or before each ``t_eval``.

    Rows before the first fix are left out.
    """
    g = gnss[gnss["valid"].to_numpy(bool)]
    tg = g["t"].to_numpy(float)
    k = np.searchsorted(tg, t_eval, side="right") - 1
    ok = k >= 0
    k = k[ok]
    return pd.DataFrame(
        {
            "t": t_eval[ok],
            "lat": g["lat_deg"].to_numpy(float)[k],
            "lon": g["lon_deg"].to_numpy(float)[k],
            "height": g["height_m"].to_numpy(float)[k],
            "source": "fix",
        }
    )


def fix_velocity_ne(gnss: pd.DataFrame) -> FloatArray:
    """North and East velocity (m/s) each fix reports: ``vn``/``ve``, else speed and course, else 0."""
    vn = gnss["vn"].to_numpy(float)
    ve = gnss["ve"].to_numpy(float)
    sp = gnss["speed_mps"].to_numpy(float)
    co = gnss["course_rad"].to_numpy(float)
    cv = gnss["course_valid"].to_numpy(bool) & np.isfinite(sp + co)
    ok = np.isfinite(vn + ve)
    n = np.where(ok, vn, np.where(cv, sp * np.cos(np.where(cv, co, 0.0)), 0.0))
    e = np.where(ok, ve, np.where(cv, sp * np.sin(np.where(cv, co, 0.0)), 0.0))
    return np.column_stack([n, e])


def gnss_dr_velocity_track(gnss: pd.DataFrame, t_eval: FloatArray) -> pd.DataFrame:
    """GNSS alone, the latest fix moved on at its own reported velocity to each ``t_eval``.

    ``p(t) = p_k + v_k (t - t_k)`` horizontally (flat about fix ``k``, height held), with
    ``v_k`` from :func:`fix_velocity_ne`. Rows before the first fix are left out.
    """
    g = gnss[gnss["valid"].to_numpy(bool)].reset_index(drop=True)
    tg = g["t"].to_numpy(float)
    k = np.searchsorted(tg, t_eval, side="right") - 1
    ok = k >= 0
    k = k[ok]
    te = t_eval[ok]
    v = fix_velocity_ne(g)[k]
    lat = g["lat_deg"].to_numpy(float)[k]
    lon = g["lon_deg"].to_numpy(float)[k]
    dt = te - tg[k]
    h = g["height_m"].to_numpy(float)[k]
    a, e2 = 6378137.0, 6.69437999014e-3  # WGS84
    w = np.sqrt(1.0 - e2 * np.sin(np.radians(lat)) ** 2)
    m_rad = a * (1.0 - e2) / w**3 + h  # meridian radius, m
    n_rad = (a / w + h) * np.cos(np.radians(lat))  # parallel radius, m
    lat2 = lat + np.degrees(v[:, 0] * dt / m_rad)
    lon2 = lon + np.degrees(v[:, 1] * dt / n_rad)
    return pd.DataFrame({"t": te, "lat": lat2, "lon": lon2, "height": h, "source": "dr_velocity"})
