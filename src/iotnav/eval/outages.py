"""Real-data GNSS-outage study (issue #5): dead reckoning through masked GNSS on a real log.

Input: a :class:`~iotnav.io.log.Log` holding a real IMU and a cm-level RTK solution (the
rtklibexplorer ``drive_0708`` and ``walk_0827`` recordings). The RTK epochs are kept untouched
as the truth; the engines are fed a tracker-grade version of them.

Degraded GNSS (:func:`degrade_rtk`)
    The RTK epochs are thinned to ``gnss_rate_hz`` (1 Hz) and passed, as "true" antenna
    position and velocity, through the simulator's receiver model
    (:func:`iotnav.sim.gnss_model.simulate_gnss`, environment ``open-sky`` by default): per
    axis a Gauss-Markov error of minutes seen through the receiver's 2 s position filter
    (horizontal 1-sigma ``UERE HDOP / sqrt(2)`` = 1.27 m per axis, 1.8 m horizontal RMS,
    2.8 m vertical), slowly drifting DOPs, rare multipath jumps, and a velocity whose error is
    the derivative of the smoothed position error plus white Doppler noise (0.08 m/s per
    axis). The accuracies the receiver would report (``h_acc_m``, ``v_acc_m``, ``s_acc_mps``)
    come with it. Seeded.

Outage windows (:func:`outage_windows`)
    The moving part of the log is where the RTK speed exceeds ``moving_speed_mps`` (first to
    last such epoch; the static start and end are left out). For every length ``L`` in
    ``lengths_s`` a window ``[s, s + L)`` starts at every ``spacing_s`` (60 s) of the moving
    part, from ``first_offset_s`` (60 s) after it begins (without a magnetometer the heading
    is only known once the vehicle has moved), as long as it ends inside it. Starts are moved
    to the next fed fix, so a window removes exactly ``L`` fixes at 1 Hz.

One run per (length, start)
    Each window is a separate run with only that window masked (its fixes removed, as in a
    tunnel where the receiver outputs nothing). Masking all windows of one length in one run
    would leave no GNSS at all between back-to-back 60 s windows. The runs share their input up
    to the window start, so an engine is run once on the unmasked input (the *baseline*) and
    deep-copied at each window start; the copy continues on the masked input up to the next
    window start (``s + spacing_s``; the end of the log for the last window). This is
    bit-identical to running the masked log from the beginning, since the engines are
    deterministic.

Scores, per engine and length
    * drift: horizontal error at the last output before the window ends (``t < s + L``) as
      a percentage of the true horizontal distance travelled in the window (median and worst
      over the windows);
    * RMS outside outages: horizontal RMS error over every output not inside a window, each
      taken from the run of the window that precedes it (the recovery after that outage,
      until the next window starts), from the baseline before the first window;
    * the baseline RMS (no outage at all) for reference.
    Two baselines are in every table, both GNSS alone evaluated at the truth epochs:
    ``hold``, the latest fed fix held, and ``dr-velocity``, the latest fed fix moved on at its
    own reported velocity (:func:`gnss_dr_velocity_track`). Engine outputs before the engine has a position (``source == "none"``) are
    left out.

Mount
    The study reports the mounting rotation each engine found at the end of the baseline run
    (``eskf``: roll, pitch and yaw of ``C_vb``; the others: block 5's mount yaw, the yaw of
    the sensor x axis from the vehicle's forward axis) beside the author's values from the
    dataset README, converted to the same form (``pdr`` has none: NaN).

Platform engines
    A profile's ``extra_engines`` run besides the configured ones: on the walk, ``pdr``
    (:mod:`iotnav.engines.pdr`, steps along a gyro heading), the method that applies to a
    walker.

Everything here is a pure function of the log, the truth and the configuration; no file is
read (the CLI ingests the dataset).

Modules: the dataset profiles and the configuration are in :mod:`iotnav.eval.outages_config`,
the truth, the degraded feed, the windows and the baselines in :mod:`iotnav.eval.outages_feed`;
this module runs the engines and scores them (public names re-exported here).
"""

from __future__ import annotations

import copy
import math
from collections.abc import Callable, Mapping, Sequence
from dataclasses import asdict
from typing import Any

import numpy as np
import numpy.typing as npt
import pandas as pd

from iotnav.engines.base import OUTPUT_COLUMNS, Engine, GnssSample, iter_samples
from iotnav.eval.metrics import path_length, track_errors
from iotnav.eval.outages_config import (
    BASELINES,
    DATASETS,
    DR_VELOCITY,
    GNSS_HOLD,
    HOLD,
    DatasetProfile,
    OutageConfig,
    OutageResult,
)
from iotnav.eval.outages_feed import (
    _truth_ned,
    degrade_rtk,
    degraded_feed,
    gnss_dr_velocity_track,
    gnss_hold_track,
    mask_windows,
    moving_part,
    outage_windows,
    rtk_truth,
)
from iotnav.eval.outages_feed import (  # re-exported
    fix_velocity_ne as fix_velocity_ne,
)
from iotnav.geo import dcm_to_rpy, euler_to_dcm
from iotnav.io.log import Log
from iotnav.sim.gnss_model import resolve_environment

FloatArray = npt.NDArray[np.float64]

__all__ = [
    "BASELINES",
    "DATASETS",
    "DR_VELOCITY",
    "GNSS_HOLD",
    "HOLD",
    "DatasetProfile",
    "OutageConfig",
    "OutageResult",
    "degrade_rtk",
    "degraded_feed",
    "engine_factories",
    "format_markdown",
    "gnss_dr_velocity_track",
    "gnss_hold_track",
    "mask_windows",
    "moving_part",
    "outage_windows",
    "rtk_truth",
    "study",
]


# --------------------------------------------------------------------------- engines


def engine_factories(
    profile: DatasetProfile, names: Sequence[str], integrity: bool = False
) -> dict[str, Callable[[], Engine]]:
    """Engine builders: ``eskf`` with the profile's configuration, ``qekf-consistent``
    (:meth:`iotnav.engines.qekf.QekfConfig.consistent`) with the profile's IMU noise densities,
    the others with defaults.

    With ``integrity`` each engine is wrapped by :class:`iotnav.engines.integrity.IntegrityEngine`
    (what :func:`iotnav.engines.registry.make_engine` builds by default), with the engine's
    builder as its re-initialisation. Names that are not available in this installation are
    skipped.
    """
    from iotnav.engines.registry import available_engines, make_engine

    avail = set(available_engines())
    out: dict[str, Callable[[], Engine]] = {}
    for name in names:
        if name == "qekf-consistent" and "qekf" in avail:
            from iotnav.engines.qekf import QekfConfig, QekfEngine, datasheet_noises

            keys = ("acc_noise_density_ug_rthz", "gyro_noise_density_mdps_rthz")
            qcfg = QekfConfig.consistent(
                **datasheet_noises(**{k: float(profile.eskf[k]) for k in keys if k in profile.eskf})
            )
            out[name] = lambda qcfg=qcfg: QekfEngine(qcfg)  # type: ignore[misc]
        elif name not in avail:
            continue
        elif name == "eskf":
            from iotnav.engines.eskf import EskfConfig, EskfEngine

            cfg = EskfConfig(**dict(profile.eskf))
            out[name] = lambda cfg=cfg: EskfEngine(cfg)  # type: ignore[misc]
        else:
            out[name] = lambda name=name: make_engine(name, integrity=False)  # type: ignore[misc]
    if integrity:
        from iotnav.engines.integrity import IntegrityEngine

        out = {k: (lambda f=f: IntegrityEngine(f)) for k, f in out.items()}  # type: ignore[misc]
    return out


def _rows_to_df(rows: list[Any]) -> pd.DataFrame:
    df = pd.DataFrame(rows, columns=list(OUTPUT_COLUMNS))
    return df[(df["source"] != "none") & np.isfinite(df["lat"].to_numpy(float))].reset_index(drop=True)


def _run_windows(
    make: Callable[[], Engine],
    log: Log,
    windows: Sequence[tuple[float, float]],
    spacing_s: float,
) -> tuple[pd.DataFrame, dict[tuple[float, float], pd.DataFrame], Engine]:
    """Baseline run and one continuation per window (see the module docstring)."""
    samples = list(iter_samples(log))
    ts = np.array([s.t for s in samples])
    starts = sorted({s for s, _ in windows})
    engine = make()
    snaps: dict[float, Engine] = {}
    rows: list[Any] = []
    j = 0
    for s in samples:
        while j < len(starts) and s.t >= starts[j]:
            snaps[starts[j]] = copy.deepcopy(engine)
            j += 1
        out = engine.step(s)
        if out is not None:
            rows.append(out)
    for st in starts[j:]:  # windows starting after the last sample (none in practice)
        snaps[st] = copy.deepcopy(engine)
    baseline = _rows_to_df(rows)
    runs: dict[tuple[float, float], pd.DataFrame] = {}
    for st, L in windows:
        eng = copy.deepcopy(snaps[st])
        i0 = int(np.searchsorted(ts, st, side="left"))
        i1 = int(np.searchsorted(ts, st + spacing_s, side="left"))
        if st + spacing_s > starts[-1]:
            i1 = len(samples)
        rws = []
        for s in samples[i0:i1]:
            if isinstance(s, GnssSample) and st <= s.t < st + L:
                continue
            out = eng.step(s)
            if out is not None:
                rws.append(out)
        runs[(st, L)] = _rows_to_df(rws)
    return baseline, runs, engine


def _window_drift(
    track: pd.DataFrame, truth: pd.DataFrame, t_ned: FloatArray, start: float, length: float
) -> dict[str, float]:
    err = track_errors(track, truth[["t", "lat", "lon", "height"]])
    sel = (err.t >= start) & (err.t < start + length)
    tt = truth["t"].to_numpy(float)
    tsel = (tt >= start) & (tt <= start + length)
    dist = path_length(t_ned[tsel, 0], t_ned[tsel, 1])
    if not sel.any():
        return {
            "distance_m": dist,
            "end_error_m": math.nan,
            "end_sigma_m": math.nan,
            "max_error_m": math.nan,
            "drift_pct": math.nan,
        }
    e_end = float(err.h_err[sel][-1])
    # the horizontal 1-sigma the output claimed at that row (NaN for tracks without one)
    at_end = track[track.t.to_numpy(float) == float(err.t[sel][-1])].tail(1)
    sig = (
        float(np.hypot(at_end.std_north.iloc[0], at_end.std_east.iloc[0]))
        if "std_north" in track.columns and len(at_end)
        else math.nan
    )
    return {
        "distance_m": dist,
        "end_error_m": e_end,
        "end_sigma_m": sig,
        "max_error_m": float(err.h_err[sel].max()),
        "drift_pct": 100.0 * e_end / dist if dist > 0 else math.nan,
    }


def _stitched_outside(
    baseline: pd.DataFrame,
    runs: Mapping[tuple[float, float], pd.DataFrame],
    length: float,
    spacing_s: float,
) -> pd.DataFrame:
    """Outputs outside the windows of one length: recovery of each run, baseline before."""
    keys = sorted(k for k in runs if k[1] == length)
    if not keys:
        return baseline
    parts = [baseline[baseline.t < keys[0][0]]]
    for n, (st, L) in enumerate(keys):
        r = runs[(st, L)]
        stop = keys[n + 1][0] if n + 1 < len(keys) else math.inf
        parts.append(r[(r.t >= st + L) & (r.t < stop)])
    return pd.concat(parts, ignore_index=True)


def _rms(track: pd.DataFrame, truth: pd.DataFrame) -> float:
    if len(track) == 0:
        return math.nan
    err = track_errors(track, truth[["t", "lat", "lon", "height"]])
    return float(np.sqrt(np.mean(err.h_err**2))) if err.h_err.size else math.nan


def _rpy_deg(C: FloatArray) -> tuple[float, float, float]:
    r, p, y = dcm_to_rpy(C)
    return math.degrees(r), math.degrees(p), math.degrees(y)


def _mount_row(name: str, engine: Engine, profile: DatasetProfile) -> dict[str, Any]:
    Ca = profile.author_C_vb()
    ra, pa, ya = _rpy_deg(Ca)
    row: dict[str, Any] = {
        "engine": name,
        "author_roll_deg": ra,
        "author_pitch_deg": pa,
        "author_yaw_deg": ya,
    }
    rpy = getattr(engine, "mount_rpy_rad", None)
    if rpy is not None and all(math.isfinite(a) for a in rpy):
        C = euler_to_dcm(*rpy)
        r, p, y = _rpy_deg(C)
        # rotation angle between the found and the author's C_vb
        c = (np.trace(C @ Ca.T) - 1.0) / 2.0
        apart = math.degrees(math.acos(max(-1.0, min(1.0, c))))
        row.update(roll_deg=r, pitch_deg=p, yaw_deg=y, apart_deg=apart, kind="C_vb")
    else:
        y = math.degrees(float(engine.mount_yaw_rad))
        apart = (y - ya + 180.0) % 360.0 - 180.0 if math.isfinite(y) else math.nan
        row.update(roll_deg=math.nan, pitch_deg=math.nan, yaw_deg=y, apart_deg=abs(apart), kind="yaw")
    return row


# --------------------------------------------------------------------------- study


def study(
    log: Log,
    truth: pd.DataFrame,
    profile: DatasetProfile,
    config: OutageConfig | None = None,
    factories: Mapping[str, Callable[[], Engine]] | None = None,
    progress: Callable[[str], None] | None = None,
    fed: Log | None = None,
) -> OutageResult:
    """Run the outage study on one recording.

    Parameters
    ----------
    log : Log
        The recording: its IMU is used (shifted by ``profile.imu_time_offset_s``), its GNSS is
        ignored (the degraded GNSS replaces it).
    truth : pandas.DataFrame
        The untouched RTK (:func:`rtk_truth`).
    profile : DatasetProfile
        Platform, author's mount and time offset, eskf settings.
    config : OutageConfig, optional
        Study settings (defaults: 15/30/60 s every 60 s, open sky, seed 0).
    factories : mapping, optional
        Engine builders by name (default :func:`engine_factories` for ``config.engines``).
    progress : callable, optional
        Called with a short message as each engine starts.
    fed : Log, optional
        What the engines are fed, as it is (:func:`iotnav.eval.cases.load_case`): no shift, no
        degradation; ``log`` is then not used. The fed GNSS error is measured against
        ``truth``.

    Returns
    -------
    OutageResult
        The tables.
    """
    cfg = config or OutageConfig()
    truth = truth.sort_values("t").reset_index(drop=True)
    if cfg.max_duration_s is not None:
        truth = truth[truth.t < float(truth.t.iloc[0]) + cfg.max_duration_s].reset_index(drop=True)
    t0, t1 = float(truth.t.iloc[0]), float(truth.t.iloc[-1])
    extras: dict[str, FloatArray] | None = None
    if fed is None:
        fed, extras = degraded_feed(log, truth, profile, cfg)
    gnss = fed.gnss
    m0, m1 = moving_part(truth, cfg.moving_speed_mps)
    windows = outage_windows(
        m0, m1, cfg.lengths_s, cfg.spacing_s, cfg.first_offset_s, gnss["t"].to_numpy(float)
    )
    if not windows:
        raise ValueError(f"the moving part ({m1 - m0:.0f} s) is shorter than every outage length")
    _, t_ned = _truth_ned(truth)
    names = cfg.engines + tuple(e for e in profile.extra_engines if e not in cfg.engines)
    facts = dict(factories) if factories is not None else engine_factories(profile, names)

    win_rows: list[dict[str, Any]] = []
    sum_rows: list[dict[str, Any]] = []
    mount_rows: list[dict[str, Any]] = []
    tg = gnss["t"].to_numpy(float)

    def score(name: str, baseline: pd.DataFrame, runs: Mapping[tuple[float, float], pd.DataFrame]) -> None:
        for st, L in windows:
            d = _window_drift(runs[(st, L)], truth, t_ned, st, L)
            masked = int(((tg >= st) & (tg < st + L)).sum())
            win_rows.append(
                {
                    "engine": name,
                    "length_s": L,
                    "start": st - t0,
                    "end": st + L - t0,
                    **d,
                    "fixes_masked": masked,
                }
            )
        rms0 = _rms(baseline, truth)
        for L in cfg.lengths_s:
            dr = np.array([r["drift_pct"] for r in win_rows if r["engine"] == name and r["length_s"] == L])
            dr = dr[np.isfinite(dr)]
            sum_rows.append(
                {
                    "engine": name,
                    "length_s": float(L),
                    "rms_outside_m": _rms(_stitched_outside(baseline, runs, L, cfg.spacing_s), truth),
                    "median_drift_pct": float(np.median(dr)) if dr.size else math.nan,
                    "worst_drift_pct": float(np.max(dr)) if dr.size else math.nan,
                    "n_windows": int(dr.size),
                    "rms_no_outage_m": rms0,
                }
            )

    # GNSS alone, last-position hold, evaluated at the truth epochs
    t_eval = truth["t"].to_numpy(float)
    hold_base = gnss_hold_track(gnss, t_eval)
    hold_runs = {}
    for st, L in windows:
        tr = gnss_hold_track(mask_windows(gnss, [(st, L)]), t_eval)
        hold_runs[(st, L)] = tr[tr.t >= st]
    score(HOLD, hold_base, hold_runs)
    dr_runs = {}
    for st, L in windows:
        tr = gnss_dr_velocity_track(mask_windows(gnss, [(st, L)]), t_eval)
        dr_runs[(st, L)] = tr[tr.t >= st]
    score(DR_VELOCITY, gnss_dr_velocity_track(gnss, t_eval), dr_runs)

    for name, make in facts.items():
        if progress is not None:
            progress(name)
        baseline, runs, engine = _run_windows(make, fed, windows, cfg.spacing_s)
        score(name, baseline, runs)
        mount_rows.append(_mount_row(name, engine, profile))

    if extras is not None:
        err, verr = extras["err_n"], extras["verr_n"]
        env, sig_h, sig_v, tau_h, tau_v, _ = resolve_environment(cfg.gnss_config())
        env_name = env.name
    else:  # fed as given: its error against the truth at the fix epochs
        err, verr = _fed_gnss_errors(gnss, truth)
        env_name, sig_h, sig_v, tau_h, tau_v = "as fed", math.nan, math.nan, math.nan, math.nan
    gnss_info = {
        "epochs": len(gnss),
        "environment": env_name,
        "sigma_h_axis_m": sig_h,
        "sigma_v_m": sig_v,
        "tau_h_s": tau_h,
        "tau_v_s": tau_v,
        "std_north_m": float(np.std(err[:, 0])),
        "std_east_m": float(np.std(err[:, 1])),
        "rms_h_m": float(np.sqrt(np.mean(err[:, 0] ** 2 + err[:, 1] ** 2))),
        "rms_v_m": float(np.sqrt(np.mean(err[:, 2] ** 2))),
        "vel_rms_axis_mps": float(np.sqrt(np.mean(verr[:, :2] ** 2))),
    }
    meta = {
        "dataset": profile.name,
        "vehicle": profile.vehicle,
        "config": asdict(cfg),
        "imu_time_offset_s": profile.imu_time_offset_s,
        "t0": t0,
        "duration_s": t1 - t0,
        "moving_part_s": (m0 - t0, m1 - t0),
        "windows": [(st - t0, L) for st, L in windows],
        "engines": list(facts),
        "truth_epochs": len(truth),
        "truth_fix_epochs": int((truth["quality"].to_numpy() == 4).sum()),
    }
    return OutageResult(
        windows=pd.DataFrame(win_rows),
        summary=pd.DataFrame(sum_rows),
        mount=pd.DataFrame(mount_rows),
        gnss=gnss_info,
        meta=meta,
    )


def _fed_gnss_errors(gnss: pd.DataFrame, truth: pd.DataFrame) -> tuple[FloatArray, FloatArray]:
    """NED position and velocity errors of fed fixes against the truth interpolated at their times."""
    frame, t_ned = _truth_ned(truth)
    g = gnss[gnss["valid"].to_numpy(bool)]
    tg = g["t"].to_numpy(float)
    tt = truth["t"].to_numpy(float)
    inside = (tg >= tt[0]) & (tg <= tt[-1])
    g, tg = g[inside], tg[inside]
    ned = frame.to_ned(g.lat_deg.to_numpy(float), g.lon_deg.to_numpy(float), g.height_m.to_numpy(float))
    ref = np.column_stack([np.interp(tg, tt, t_ned[:, i]) for i in range(3)])
    tv = truth[["vn", "ve", "vd"]].to_numpy(float)
    vref = np.column_stack([np.interp(tg, tt, tv[:, i]) for i in range(3)])
    v = g[["vn", "ve", "vd"]].to_numpy(float)
    verr = v - vref
    return ned - ref, np.where(np.isfinite(verr), verr, 0.0)


def _f(x: Any, nd: int = 2) -> str:
    v = float(x)
    return "-" if not math.isfinite(v) else f"{v:.{nd}f}"


def format_markdown(res: OutageResult, target_pct: float = 2.0) -> str:
    """Markdown tables of a result: summary, per-window drift, mount, the fed GNSS."""
    m = res.meta
    g = res.gnss
    lines = [
        f"### {m['dataset']} ({m['vehicle']}; {m['duration_s']:.0f} s, moving part "
        f"{m['moving_part_s'][0]:.0f}-{m['moving_part_s'][1]:.0f} s)",
        "",
        f"Fed GNSS: {g['epochs']} fixes at {m['config']['gnss_rate_hz']:g} Hz, simulator model "
        f"`{g['environment']}` (per-axis horizontal sigma {g['sigma_h_axis_m']:.2f} m, tau "
        f"{g['tau_h_s']:.0f} s; vertical {g['sigma_v_m']:.2f} m), seed {m['config']['seed']}; achieved "
        f"horizontal RMS {g['rms_h_m']:.2f} m (N std {g['std_north_m']:.2f}, E std {g['std_east_m']:.2f} m), "
        f"vertical RMS {g['rms_v_m']:.2f} m, velocity error RMS {g['vel_rms_axis_mps']:.3f} m/s per axis. "
        f"Truth: the untouched RTK ({m['truth_epochs']} epochs, {m['truth_fix_epochs']} fixed).",
        "",
        "| engine | outage (s) | windows | RMS outside outages (m) | RMS, no outage (m) | "
        "median drift (% of distance) | worst drift (%) |",
        "|---|---|---|---|---|---|---|",
    ]
    for r in res.summary.itertuples():
        lines.append(
            f"| {r.engine} | {r.length_s:g} | {r.n_windows} | {_f(r.rms_outside_m)} | {_f(r.rms_no_outage_m)} | "
            f"{_f(r.median_drift_pct)} | {_f(r.worst_drift_pct)} |"
        )
    es = res.summary[(res.summary.engine == "eskf") & (res.summary.length_s == 30.0)]
    if len(es) and res.meta.get("vehicle", "car") == "car":  # the target is a car's (issue #5)
        v = float(es.median_drift_pct.iloc[0])
        verdict = "meets" if v <= target_pct else "misses"
        lines += [
            "",
            f"eskf, 30 s outages: median drift {_f(v)} % ({verdict} the target of {target_pct:g} %).",
        ]
    lines += [
        "",
        "Mount found at the end of the baseline run (deg) beside the author's (dataset README, as C_vb):",
        "",
        "| engine | estimate | roll | pitch | yaw | author roll | author pitch | author yaw | apart (deg) |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for r in res.mount.itertuples():
        lines.append(
            f"| {r.engine} | {r.kind} | {_f(r.roll_deg)} | {_f(r.pitch_deg)} | {_f(r.yaw_deg)} | "
            f"{_f(r.author_roll_deg)} | {_f(r.author_pitch_deg)} | {_f(r.author_yaw_deg)} | {_f(r.apart_deg)} |"
        )
    lines += [
        "",
        "<details><summary>Per window: start (s from the log start), distance, end error, drift</summary>",
        "",
        "| engine | outage (s) | start (s) | fixes masked | distance (m) | end error (m) | max error (m) | drift (%) |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for r in res.windows.itertuples():
        lines.append(
            f"| {r.engine} | {r.length_s:g} | {r.start:.0f} | {r.fixes_masked} | {r.distance_m:.0f} | "
            f"{_f(r.end_error_m)} | {_f(r.max_error_m)} | {_f(r.drift_pct)} |"
        )
    lines += ["", "</details>", ""]
    return "\n".join(lines)
