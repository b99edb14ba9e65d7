"""Report figures (matplotlib, Agg): each a function taking tables and returning a Figure.

No file I/O and no pyplot state here: figures are built with :class:`matplotlib.figure.Figure`
and saved by :mod:`iotnav.report.page`. Positions come in the shared local frame of
:mod:`iotnav.report.prepare` (columns ``n_m``/``e_m``, metres); angles in radians are shown in
degrees, the only unit conversion done here.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from typing import Any, Literal

import matplotlib

matplotlib.use("Agg")

import numpy as np
import pandas as pd
from matplotlib.axes import Axes
from matplotlib.figure import Figure
from matplotlib.patches import Circle

from iotnav.eval.metrics import Errors

RUN_COLORS = ("#1f77b4", "#ff7f0e", "#2ca02c", "#9467bd", "#8c564b", "#e377c2", "#bcbd22", "#17becf")
GNSS_COLOR = "#7f7f7f"
TRUTH_COLOR = "#000000"
REJECT_COLOR = "#d62728"
OUTAGE_COLOR = "#f4a261"
STATIC_COLOR = "#8ecae6"


def run_color(i: int) -> str:
    """Colour of the ``i``-th run (cycles through :data:`RUN_COLORS`)."""
    return RUN_COLORS[i % len(RUN_COLORS)]


def _new(width: float, height: float) -> Figure:
    fig = Figure(figsize=(width, height), dpi=100, layout="constrained")
    return fig


def _shade(
    ax: Axes, spans: Sequence[tuple[float, float]], color: str, label: str | None, alpha: float = 0.3
) -> None:
    for k, (a, b) in enumerate(spans):
        ax.axvspan(a, b, color=color, alpha=alpha, lw=0, label=label if k == 0 else None)


def _deg(x: Any) -> np.ndarray:
    return np.degrees(np.asarray(x, float))


def _wrapped(t: np.ndarray, deg: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Angle in [-180, 180) with NaN inserted at wraps so lines do not jump across the plot."""
    a = (deg + 180.0) % 360.0 - 180.0
    if a.size < 2:
        return t, a
    jump = np.flatnonzero(np.abs(np.diff(a)) > 180.0) + 1
    return np.insert(t.astype(float), jump, np.nan), np.insert(a, jump, np.nan)


def _maybe_log(ax: Axes, decades: float = 1.5) -> None:
    """Log y scale when the drawn positive values span more than ``decades`` decades."""
    ys = [np.asarray(ln.get_ydata(), float) for ln in ax.get_lines()]
    y = np.concatenate(ys) if ys else np.zeros(0)
    y = y[np.isfinite(y) & (y > 0)]
    if y.size and np.log10(y.max() / y.min()) > decades:
        ax.set_yscale("log")
    else:
        ax.set_ylim(bottom=0.0)


def _equal(ax: Axes, adjustable: Literal["box", "datalim"] = "datalim") -> None:
    ax.set_aspect("equal", adjustable=adjustable)
    ax.set_xlabel("East, m")
    ax.set_ylabel("North, m")
    ax.grid(True, alpha=0.3)


def map_figure(
    tracks: Mapping[str, pd.DataFrame],
    fixes: pd.DataFrame,
    rejected: pd.DataFrame,
    truth: pd.DataFrame | None = None,
    outages: Sequence[tuple[float, float]] = (),
) -> Figure:
    """Track on a local East/North map.

    Parameters
    ----------
    tracks : mapping of label to DataFrame
        Fused outputs with ``t``, ``n_m``, ``e_m``; the first one gets its outage segments
        highlighted.
    fixes : pandas.DataFrame
        Valid raw GNSS fixes with ``n_m``, ``e_m``.
    rejected : pandas.DataFrame
        Rejected fixes with a position (``n_m``, ``e_m``).
    truth : pandas.DataFrame, optional
        Truth with ``n_m``, ``e_m``.
    outages : sequence of (start, end)
        GNSS outage windows, s.
    """
    fig = _new(9.0, 7.5)
    ax = fig.add_subplot()
    if truth is not None and len(truth):
        ax.plot(truth["e_m"], truth["n_m"], color=TRUTH_COLOR, lw=1.2, ls="--", label="truth", zorder=4)
    if len(fixes):
        ax.plot(
            fixes["e_m"],
            fixes["n_m"],
            ".",
            color=GNSS_COLOR,
            ms=4,
            alpha=0.7,
            label="raw GNSS fixes",
            zorder=2,
        )
    for i, (label, tr) in enumerate(tracks.items()):
        ax.plot(tr["e_m"], tr["n_m"], color=run_color(i), lw=1.3, label=f"fused: {label}", zorder=3)
        if i == 0 and outages:
            t = tr["t"].to_numpy(float)
            for k, (a, b) in enumerate(outages):
                sel = (t >= a) & (t <= b)
                if sel.any():
                    ax.plot(
                        tr["e_m"].to_numpy()[sel],
                        tr["n_m"].to_numpy()[sel],
                        color=OUTAGE_COLOR,
                        lw=3.5,
                        alpha=0.8,
                        zorder=2.5,
                        label="during GNSS outage" if k == 0 else None,
                    )
    if len(rejected):
        ax.plot(
            rejected["e_m"],
            rejected["n_m"],
            "x",
            color=REJECT_COLOR,
            ms=6,
            mew=1.5,
            label=f"rejected fixes ({len(rejected)})",
            zorder=5,
        )
    _equal(ax)
    ax.set_title("Track, local East/North (m)")
    ax.legend(loc="best", fontsize=9, framealpha=0.85)
    return fig


def error_time_figure(
    errors: Mapping[str, Errors],
    baseline: str | None = None,
    sigma: pd.DataFrame | None = None,
    outages: Sequence[tuple[float, float]] = (),
    drift: Sequence[Mapping[str, float]] = (),
) -> Figure:
    """North, East and horizontal error over time.

    Parameters
    ----------
    errors : mapping of label to Errors
        One entry per solution; ``baseline`` (GNSS only) is drawn as grey dots.
    baseline : str, optional
        Key of the GNSS-only entry.
    sigma : pandas.DataFrame, optional
        ``t``, ``std_north``, ``std_east`` (1-sigma, m) of the first fused run: its +/-3 sigma
        band is shaded.
    outages : sequence of (start, end)
        Shaded GNSS outages, s.
    drift : sequence of dict
        :func:`iotnav.eval.metrics.outage_drift` rows of the first fused run (end errors marked).
    """
    fig = _new(11.0, 8.0)
    axes = fig.subplots(3, 1, sharex=True)
    names = ("North error, m", "East error, m", "horizontal error, m")
    for ax, name in zip(axes, names, strict=True):
        _shade(ax, outages, OUTAGE_COLOR, "GNSS outage")
        ax.set_ylabel(name)
        ax.grid(True, alpha=0.3)
    if sigma is not None and len(sigma):
        t = sigma["t"].to_numpy(float)
        for ax, col in zip(axes[:2], ("std_north", "std_east"), strict=True):
            s = 3.0 * sigma[col].to_numpy(float)
            ax.fill_between(t, -s, s, color=run_color(0), alpha=0.12, lw=0, label="fused ±3σ (first run)")
    i = 0
    for label, e in errors.items():
        if label == baseline:
            kw: dict[str, Any] = {"color": GNSS_COLOR, "ls": "none", "marker": ".", "ms": 3, "alpha": 0.8}
        else:
            kw = {"color": run_color(i), "lw": 1.0}
            i += 1
        for ax, y in zip(axes, (e.n_err, e.e_err, e.h_err), strict=True):
            ax.plot(e.t, y, label=label, **kw)
    for k, d in enumerate(drift):
        axes[2].plot(
            d["end"],
            d["end_error_m"],
            "v",
            color=REJECT_COLOR,
            ms=8,
            label="error at outage end" if k == 0 else None,
            zorder=5,
        )
        axes[2].annotate(
            f"{d['end_error_m']:.1f} m\n({d['drift_pct']:.1f} % of {d['distance_m']:.0f} m)",
            (d["end"], d["end_error_m"]),
            textcoords="offset points",
            xytext=(4, 6),
            fontsize=8,
        )
    for ax in axes[:2]:
        ax.axhline(0.0, color="k", lw=0.6)
    axes[2].set_ylim(bottom=0.0)
    axes[-1].set_xlabel("device time, s")
    axes[0].set_title("Position error against truth (track minus truth)")
    axes[0].legend(loc="upper right", fontsize=8, ncols=2, framealpha=0.85)
    if drift:
        axes[2].legend(loc="upper right", fontsize=8, framealpha=0.85)
    return fig


def error_distribution_figure(errors: Mapping[str, Errors], baseline: str | None = None) -> Figure:
    """Empirical distributions of |North|, |East| and horizontal error (67 % and 95 % marked).

    Parameters
    ----------
    errors : mapping of label to Errors
        One entry per solution.
    baseline : str, optional
        Key of the GNSS-only entry (grey).
    """
    fig = _new(12.0, 4.2)
    axes = fig.subplots(1, 3, sharey=True)
    titles = ("|North error|", "|East error|", "horizontal error")
    i = 0
    for label, e in errors.items():
        color = GNSS_COLOR if label == baseline else run_color(i)
        if label != baseline:
            i += 1
        for ax, x in zip(axes, (np.abs(e.n_err), np.abs(e.e_err), e.h_err), strict=True):
            if x.size == 0:
                continue
            xs = np.sort(x)
            p = np.arange(1, xs.size + 1) / xs.size
            ax.step(xs, 100.0 * p, where="post", color=color, lw=1.4, label=label)
            ax.plot([np.mean(x)], [50.0], "o", color=color, ms=5)
    for ax, title in zip(axes, titles, strict=True):
        for q in (67.0, 95.0):
            ax.axhline(q, color="k", lw=0.7, ls=":")
            ax.text(ax.get_xlim()[1], q, f" {q:.0f} %", va="center", ha="left", fontsize=8)
        ax.set_xlabel(f"{title}, m")
        ax.set_title(title)
        ax.grid(True, alpha=0.3)
        ax.set_xlim(left=0.0)
    axes[0].set_ylabel("share of epochs, %  (dot: mean)")
    axes[0].set_ylim(0.0, 100.0)
    axes[2].legend(loc="lower right", fontsize=8, framealpha=0.85)
    return fig


def static_figure(
    fixes: pd.DataFrame,
    output: pd.DataFrame,
    center: tuple[float, float],
    fence_m: float,
    center_label: str,
    period: tuple[float, float],
) -> Figure:
    """The static cloud: raw fixes, filtered output, and a geofence circle.

    Parameters
    ----------
    fixes : pandas.DataFrame
        Valid raw fixes in the static period (``t``, ``n_m``, ``e_m``).
    output : pandas.DataFrame
        Fused output rows in the period (``t``, ``n_m``, ``e_m``).
    center : (north, east)
        Centre of the geofence, m.
    fence_m : float
        Geofence radius, m.
    center_label : str
        What the centre is (``truth`` or ``mean of the raw fixes``).
    period : (start, end)
        The static period, s.
    """
    fig = _new(12.0, 5.5)
    ax, bx = fig.subplots(1, 2, width_ratios=(1.0, 1.4))
    cn, ce = center
    ax.add_patch(Circle((ce, cn), fence_m, fill=False, color=REJECT_COLOR, lw=1.2, ls="--"))
    ax.plot([], [], color=REJECT_COLOR, ls="--", label=f"geofence {fence_m:g} m")
    ax.plot(
        fixes["e_m"], fixes["n_m"], ".", color=GNSS_COLOR, ms=5, alpha=0.7, label=f"raw fixes ({len(fixes)})"
    )
    ax.plot(output["e_m"], output["n_m"], "-", color=run_color(0), lw=1.2, label="filtered output")
    ax.plot([ce], [cn], "+", color=TRUTH_COLOR, ms=14, mew=2, label=center_label)
    _equal(ax, "box")
    span = max(
        fence_m * 1.15,
        float(np.nanmax(np.abs(np.r_[fixes["n_m"] - cn, fixes["e_m"] - ce, 0.0]))) * 1.05,
        float(np.nanmax(np.abs(np.r_[output["n_m"] - cn, output["e_m"] - ce, 0.0]))) * 1.05,
    )
    ax.set_xlim(ce - span, ce + span)
    ax.set_ylim(cn - span, cn + span)
    ax.set_title(f"Static cloud, {period[0]:.0f}–{period[1]:.0f} s")
    ax.legend(loc="upper right", fontsize=8, framealpha=0.85)
    d_fix = np.hypot(fixes["n_m"].to_numpy(float) - cn, fixes["e_m"].to_numpy(float) - ce)
    d_out = np.hypot(output["n_m"].to_numpy(float) - cn, output["e_m"].to_numpy(float) - ce)
    bx.plot(fixes["t"], d_fix, ".", color=GNSS_COLOR, ms=5, label="raw fixes")
    bx.plot(output["t"], d_out, "-", color=run_color(0), lw=1.2, label="filtered output")
    bx.axhline(fence_m, color=REJECT_COLOR, ls="--", lw=1.2, label=f"geofence {fence_m:g} m")
    bx.set_xlabel("device time, s")
    bx.set_ylabel(f"distance from {center_label}, m")
    bx.set_ylim(bottom=0.0)
    bx.grid(True, alpha=0.3)
    bx.set_title("Distance from the fence centre")
    bx.legend(loc="upper right", fontsize=8, framealpha=0.85)
    return fig


def mount_figure(
    mounts: Mapping[str, pd.DataFrame],
    path: pd.DataFrame,
    t_calibrated: float,
    mount_yaw_rad: float,
    true_mount_yaw_rad: float = math.nan,
    n_arrows: int = 14,
    finals: Mapping[str, tuple[float, float]] | None = None,
) -> Figure:
    """Mount angle over time and the sensor x-axis drawn on the path.

    Parameters
    ----------
    mounts : mapping of label to DataFrame
        :func:`iotnav.report.prepare.mount_table` per run.
    path : pandas.DataFrame
        First run's output with ``t``, ``n_m``, ``e_m``, ``yaw`` (rad; sensor heading before the
        mount angle is known, vehicle heading after).
    t_calibrated : float
        Time of the first accepted mount estimate, s.
    mount_yaw_rad : float
        Mount angle used after calibration (sensor x from vehicle forward, clockwise), rad.
    true_mount_yaw_rad : float
        Simulator's mount angle, rad (NaN when unknown).
    n_arrows : int
        Arrows drawn on each side of ``t_calibrated``.
    finals : mapping of label to (t_end, mount_yaw_rad), optional
        End of each run and its final mount angle (``summary.json``), drawn as a diamond.
    """
    fig = _new(13.0, 5.8)
    ax, bx = fig.subplots(1, 2, width_ratios=(1.2, 1.0))
    for i, (label, m) in enumerate(mounts.items()):
        c = run_color(i)
        t_m = m["t"].to_numpy(float)
        cur = _deg(m["mount_yaw_rad"])
        t_end, mu_end = finals.get(label, (math.nan, math.nan)) if finals else (math.nan, math.nan)
        if math.isfinite(t_end) and t_m.size and t_end > t_m[-1]:
            t_m, cur = np.r_[t_m, t_end], np.r_[cur, cur[-1]]
        ax.step(t_m, cur, where="post", color=c, lw=1.6, label=f"{label}: angle in use")
        acc = m.loc[m["accepted"]]
        ax.plot(
            acc["t"], _deg(acc["candidate_rad"]), "o", color=c, ms=4, label=f"{label}: accepted estimates"
        )
        ref = m.loc[~m["accepted"]]
        if len(ref):
            ax.plot(
                ref["t"], _deg(ref["candidate_rad"]), "x", color=c, ms=5, alpha=0.6, label=f"{label}: refused"
            )
        s = m["std_rad"].where(m["accepted"]).ffill().to_numpy(float)
        if np.isfinite(s).any():
            s = np.r_[s, s[-1]] if t_m.size > len(m) else s
            ax.fill_between(
                t_m,
                cur - 3.0 * _deg(s),
                cur + 3.0 * _deg(s),
                step="post",
                color=c,
                alpha=0.12,
                lw=0,
                label=f"{label}: ±3σ",
            )
        if math.isfinite(mu_end) and math.isfinite(t_end):
            ax.plot(
                [t_end],
                [math.degrees(mu_end)],
                "D",
                color=c,
                ms=7,
                mec="k",
                label=f"{label}: final (summary)",
            )
    if math.isfinite(true_mount_yaw_rad):
        ax.axhline(
            math.degrees(true_mount_yaw_rad), color=TRUTH_COLOR, ls="--", lw=1.2, label="true mount angle"
        )
    ax.set_xlabel("device time, s")
    ax.set_ylabel("mount yaw (sensor x from vehicle forward), deg")
    ax.set_title("Mounting angle estimates")
    ax.grid(True, alpha=0.3)
    ax.legend(loc="best", fontsize=8, framealpha=0.85)

    bx.plot(path["e_m"], path["n_m"], color="#bbbbbb", lw=1.0, label="fused path", zorder=1)
    t = path["t"].to_numpy(float)
    span = (
        float(np.ptp(np.r_[path["e_m"].to_numpy(float), path["n_m"].to_numpy(float)])) if len(path) else 1.0
    )
    length = max(span / 18.0, 0.5)

    def arrows(sel: np.ndarray, yaw_offset: float, color: str, label: str, alpha: float = 1.0) -> None:
        idx = np.flatnonzero(sel)
        if idx.size == 0:
            return
        pick = idx[np.linspace(0, idx.size - 1, min(n_arrows, idx.size)).round().astype(int)]
        yaw = path["yaw"].to_numpy(float)[pick] + yaw_offset
        bx.quiver(
            path["e_m"].to_numpy(float)[pick],
            path["n_m"].to_numpy(float)[pick],
            length * np.sin(yaw),
            length * np.cos(yaw),
            angles="xy",
            scale_units="xy",
            scale=1.0,
            color=color,
            width=0.005,
            alpha=alpha,
            label=label,
            zorder=3,
        )

    moving = np.ones(len(t), bool)
    if {"vn", "ve"} <= set(path.columns):
        moving = np.hypot(path["vn"].to_numpy(float), path["ve"].to_numpy(float)) > 1.0
    arrows(moving & (t < t_calibrated), 0.0, REJECT_COLOR, "before: sensor x-axis, taken as forward")
    after = moving & (t >= t_calibrated)
    arrows(after, mount_yaw_rad, REJECT_COLOR, "after: sensor x-axis (heading + mount)", alpha=0.35)
    arrows(after, 0.0, run_color(2), "after: vehicle forward (sensor x rotated by −mount)")
    _equal(bx)
    bx.set_title(f"Sensor axis on the path (mount {math.degrees(mount_yaw_rad):.1f}°)")
    bx.legend(loc="best", fontsize=8, framealpha=0.85)
    return fig


def boot_figure(
    epochs: pd.DataFrame,
    track: pd.DataFrame,
    stored: tuple[float, float] | None,
    first_fix: tuple[float, float, float] | None,
    max_pdop: float = math.nan,
    truth: pd.DataFrame | None = None,
) -> Figure:
    """The boot sequence: stored position, rejected fixes, first accepted fix, PDOP.

    Parameters
    ----------
    epochs : pandas.DataFrame
        GNSS epochs of the boot window with ``t``, ``pdop``, ``rejected`` (bool), ``reason``
        and, where they have a position, ``n_m``, ``e_m`` (NaN otherwise).
    track : pandas.DataFrame
        Fused output of the window (``t``, ``n_m``, ``e_m``, ``source``).
    stored : (north, east) or None
        Stored last position, m.
    first_fix : (t, north, east) or None
        First accepted fix.
    max_pdop : float
        Block 1's PDOP limit (NaN when unknown).
    truth : pandas.DataFrame, optional
        Truth of the window (``n_m``, ``e_m``).
    """
    fig = _new(12.0, 5.8)
    ax, bx = fig.subplots(1, 2, width_ratios=(1.0, 1.3))
    if truth is not None and len(truth):
        ax.plot(truth["e_m"], truth["n_m"], "--", color=TRUTH_COLOR, lw=1.0, label="truth")
    if len(track):
        ax.plot(track["e_m"], track["n_m"], "-", color=run_color(0), lw=1.2, label="fused output")
    rej = epochs.loc[epochs["rejected"] & np.isfinite(epochs["n_m"].to_numpy(float))]
    acc = epochs.loc[~epochs["rejected"] & np.isfinite(epochs["n_m"].to_numpy(float))]
    if len(acc):
        ax.plot(acc["e_m"], acc["n_m"], ".", color=GNSS_COLOR, ms=5, label="accepted fixes")
    if len(rej):
        ax.plot(
            rej["e_m"],
            rej["n_m"],
            "x",
            color=REJECT_COLOR,
            ms=6,
            mew=1.5,
            label=f"rejected fixes ({len(rej)})",
        )
    if stored is not None:
        ax.plot(
            [stored[1]],
            [stored[0]],
            "*",
            color="#6a4c93",
            ms=16,
            mec="k",
            label="stored last position",
            zorder=6,
        )
    if first_fix is not None:
        ax.plot(
            [first_fix[2]],
            [first_fix[1]],
            "o",
            color=run_color(2),
            ms=11,
            mec="k",
            label=f"first accepted fix ({first_fix[0]:.0f} s)",
            zorder=6,
        )
    _equal(ax)
    ax.set_title("Boot: positions")
    ax.legend(loc="best", fontsize=8, framealpha=0.85)

    pd_all = epochs["pdop"].to_numpy(float)
    okp = np.isfinite(pd_all)
    r = epochs["rejected"].to_numpy(bool)
    bx.plot(epochs["t"][okp & ~r], pd_all[okp & ~r], ".", color=run_color(2), ms=6, label="accepted")
    bx.plot(epochs["t"][okp & r], pd_all[okp & r], "x", color=REJECT_COLOR, ms=6, mew=1.5, label="rejected")
    no_pdop = ~okp & r
    if no_pdop.any():
        bx.plot(
            epochs["t"][no_pdop],
            np.zeros(int(no_pdop.sum())),
            "|",
            color=REJECT_COLOR,
            ms=10,
            label=f"rejected without PDOP / position ({int(no_pdop.sum())})",
            clip_on=False,
        )
    if math.isfinite(max_pdop):
        bx.axhline(max_pdop, color="k", ls="--", lw=1.0, label=f"PDOP limit {max_pdop:g}")
    if first_fix is not None:
        bx.axvline(first_fix[0], color=run_color(2), lw=1.2, label="first accepted fix")
    bx.set_xlabel("device time, s")
    bx.set_ylabel("PDOP")
    bx.set_ylim(bottom=0.0)
    bx.grid(True, alpha=0.3)
    bx.set_title("Boot: fixes and their PDOP")
    bx.legend(loc="upper right", fontsize=8, framealpha=0.85)
    return fig


def states_figure(
    tracks: Mapping[str, pd.DataFrame],
    truth: pd.DataFrame | None = None,
    gnss: pd.DataFrame | None = None,
    outages: Sequence[tuple[float, float]] = (),
) -> Figure:
    """Attitude, speed and position 3-sigma over time.

    Parameters
    ----------
    tracks : mapping of label to DataFrame
        Outputs with ``t``, ``roll``, ``pitch``, ``yaw`` (rad), ``vn``, ``ve`` (m/s),
        ``std_north``, ``std_east`` (m).
    truth : pandas.DataFrame, optional
        Truth with the same attitude/velocity columns where available.
    gnss : pandas.DataFrame, optional
        Valid raw fixes with ``t``, ``speed_mps``.
    outages : sequence of (start, end)
        Shaded GNSS outages, s.
    """
    fig = _new(11.0, 10.0)
    axes = fig.subplots(4, 1, sharex=True)
    for ax in axes:
        _shade(ax, outages, OUTAGE_COLOR, None)
        ax.grid(True, alpha=0.3)
    if truth is not None:
        tt = truth["t"].to_numpy(float)
        for col, ls in (("roll", "--"), ("pitch", ":")):
            if col in truth.columns:
                axes[0].plot(tt, _deg(truth[col]), ls, color=TRUTH_COLOR, lw=1.0, label=f"truth {col}")
        if "yaw" in truth.columns:
            axes[1].plot(*_wrapped(tt, _deg(truth["yaw"])), "--", color=TRUTH_COLOR, lw=1.0, label="truth")
        if {"vn", "ve"} <= set(truth.columns):
            axes[2].plot(
                tt, np.hypot(truth["vn"], truth["ve"]), "--", color=TRUTH_COLOR, lw=1.0, label="truth"
            )
    if gnss is not None and "speed_mps" in gnss.columns and len(gnss):
        axes[2].plot(gnss["t"], gnss["speed_mps"], ".", color=GNSS_COLOR, ms=4, label="GNSS speed")
    for i, (label, tr) in enumerate(tracks.items()):
        c = run_color(i)
        t = tr["t"].to_numpy(float)
        axes[0].plot(t, _deg(tr["roll"]), "-", color=c, lw=1.0, label=f"{label} roll")
        axes[0].plot(t, _deg(tr["pitch"]), "-", color=c, lw=1.0, alpha=0.55, label=f"{label} pitch")
        axes[1].plot(*_wrapped(t, _deg(tr["yaw"])), "-", color=c, lw=1.0, label=label)
        axes[2].plot(t, np.hypot(tr["vn"], tr["ve"]), "-", color=c, lw=1.0, label=label)
        if {"std_north", "std_east"} <= set(tr.columns):
            axes[3].plot(t, 3.0 * tr["std_north"], "-", color=c, lw=1.0, label=f"{label} 3σ North")
            axes[3].plot(t, 3.0 * tr["std_east"], "--", color=c, lw=1.0, label=f"{label} 3σ East")
    axes[0].set_ylabel("roll / pitch, deg")
    axes[1].set_ylabel("yaw, deg")
    axes[1].set_ylim(-180.0, 180.0)
    axes[1].set_yticks([-180, -90, 0, 90, 180])
    axes[2].set_ylabel("horizontal speed, m/s")
    axes[3].set_ylabel("position 3σ, m")
    _maybe_log(axes[3])
    axes[-1].set_xlabel("device time, s")
    axes[0].set_title("Attitude, speed and position uncertainty (shaded: GNSS outages)")
    for ax in axes:
        ax.legend(loc="upper right", fontsize=7, ncols=2, framealpha=0.85)
    return fig


def nis_figure(nis: Mapping[str, pd.DataFrame]) -> Figure:
    """NIS values carried by events (mostly rejected updates), log scale.

    Parameters
    ----------
    nis : mapping of label to DataFrame
        :func:`iotnav.report.prepare.nis_table` per run.
    """
    fig = _new(11.0, 3.8)
    ax = fig.add_subplot()
    markers = ("o", "s", "^", "D", "v", "P")
    for i, (label, df) in enumerate(nis.items()):
        for k, (meas, g) in enumerate(df.groupby("measurement", sort=True)):
            ax.plot(
                g["t"],
                g["nis"],
                markers[k % len(markers)],
                color=run_color(i),
                ms=5,
                alpha=0.8,
                label=f"{label}: {meas} ({len(g)})",
            )
    _maybe_log(ax)
    ax.set_xlabel("device time, s")
    ax.set_ylabel("NIS")
    ax.grid(True, alpha=0.3, which="both")
    ax.set_title("Normalised innovation squared reported in events")
    ax.legend(loc="best", fontsize=8, framealpha=0.85)
    return fig


def timeline_figure(
    events: Sequence[Mapping[str, Any]],
    static: Sequence[tuple[float, float]],
    outages: Sequence[tuple[float, float]],
    t_range: tuple[float, float],
) -> Figure:
    """Events of one run on a time line: one row per event type (reason for rejections).

    Parameters
    ----------
    events : sequence of dict
        Events with ``type`` and ``t`` (those without a finite ``t`` are left out).
    static : sequence of (start, end)
        Static periods, s (drawn as a bar).
    outages : sequence of (start, end)
        GNSS outages, s (drawn as a bar).
    t_range : (start, end)
        Time span of the run, s.
    """
    rows: dict[str, list[float]] = {}
    for e in events:
        t = float(e.get("t", math.nan)) if e.get("t") is not None else math.nan
        if not math.isfinite(t):
            continue
        key = str(e["type"])
        if key == "fix_rejected":
            key = f"fix_rejected: {e.get('reason', '?')}"
        elif key == "mount_estimate":
            key = "mount_estimate: " + ("accepted" if e.get("accepted") else "refused")
        elif key == "update_rejected":
            key = f"update_rejected: {e.get('measurement', '?')}"
        rows.setdefault(key, []).append(t)
    names = sorted(rows)
    bars = [("static", static, STATIC_COLOR), ("GNSS outage", outages, OUTAGE_COLOR)]
    n = len(names) + len(bars)
    fig = _new(11.0, 1.2 + 0.32 * n)
    ax = fig.add_subplot()
    for k, (_name, spans, color) in enumerate(bars):
        y = n - 1 - k
        ax.broken_barh([(a, max(b - a, 1e-3)) for a, b in spans], (y - 0.35, 0.7), color=color)
    for k, name in enumerate(names):
        y = n - 1 - len(bars) - k
        color = REJECT_COLOR if "rejected" in name or "refused" in name else run_color(0)
        ax.plot(rows[name], np.full(len(rows[name]), y), "|", color=color, ms=12, mew=1.5)
    labels = [b[0] for b in bars] + [f"{nm} ({len(rows[nm])})" for nm in names]
    ax.set_yticks(range(n - 1, -1, -1), labels, fontsize=8)
    ax.set_ylim(-0.7, n - 0.3)
    pad = 0.01 * max(t_range[1] - t_range[0], 1.0)
    ax.set_xlim(t_range[0] - pad, t_range[1] + pad)
    ax.set_xlabel("device time, s")
    ax.grid(True, axis="x", alpha=0.3)
    ax.set_title("Events timeline")
    return fig
