"""The power-plan section of a report: battery life beside the accuracy each GNSS duty cycle costs.

Input: the table of :func:`iotnav.eval.duty_cycle.with_budgets` (one row per case, engine and
duty cycle, with ``life_h``, ``total_mw``, ``h_p50``, ``h_p95`` ...). :func:`power_figure` draws
it (matplotlib, no pyplot state), :func:`power_markdown` and :func:`power_section` write it as
markdown and as a :class:`iotnav.report.page.Section`, and :func:`write_power_report` writes a
self-contained ``power.html`` (the figure embedded), ``power.png`` and ``power.md``.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import pandas as pd
from matplotlib.figure import Figure

from iotnav.report import figures as F
from iotnav.report.page import Section, _render, esc, fmt, png_bytes, table

__all__ = ["power_figure", "power_markdown", "power_section", "write_power_report"]

_HEADER = (
    "fix every",
    "engine",
    "GNSS (mW)",
    "total (mW)",
    "battery life (h)",
    "(days)",
    "p50 (m)",
    "p95 (m)",
    "RMS (m)",
    "max (m)",
    "fixes",
    "coverage",
    "p95 worse than hold",
)


def _period(p: float) -> str:
    return "always on" if math.isnan(p) else f"{p:g} s"


def _rows(sub: pd.DataFrame) -> list[list[Any]]:
    out = []
    for r in sub.to_dict("records"):
        life = float(r["life_h"])
        out.append(
            [
                _period(float(r["period_s"])),
                r["engine"],
                float(r["gnss_mw"]),
                float(r["total_mw"]),
                life,
                life / 24.0,
                *(float(r[k]) for k in ("h_p50", "h_p95", "h_rms", "h_max")),
                int(r["fixes"]),
                float(r["coverage"]),
                bool(r["worse_than_hold"]),
            ]
        )
    return out


def power_figure(df: pd.DataFrame) -> Figure:
    """Horizontal error p95 (m) against battery life (h), one panel per case, a line per engine.

    Each point is a duty cycle, labelled with its fix period; p50 is drawn dashed. An inertial
    engine keeps its IMU and MCU on, so its points sit at shorter lives than ``hold``'s.
    """
    cases = list(dict.fromkeys(df["case"]))
    ncols = min(2, max(1, len(cases)))
    nrows = max(1, math.ceil(len(cases) / ncols))
    fig = Figure(figsize=(5.2 * ncols, 3.8 * nrows), layout="constrained")
    grid = fig.subplots(nrows, ncols, squeeze=False)
    axes = [ax for row in grid for ax in row]
    for ax in axes[len(cases) :]:
        ax.set_visible(False)
    for ax, case in zip(axes, cases, strict=False):
        sub = df[df["case"] == case]
        for i, eng in enumerate(dict.fromkeys(sub["engine"])):
            e = sub[sub["engine"] == eng].sort_values("life_h")
            color = F.GNSS_COLOR if eng == "hold" else F.run_color(i)
            x = e["life_h"].to_numpy(float)
            ax.plot(x, e["h_p95"].to_numpy(float), "o-", color=color, label=str(eng))
            ax.plot(x, e["h_p50"].to_numpy(float), "--", color=color, alpha=0.6)
            for xx, yy, p in zip(x, e["h_p95"].to_numpy(float), e["period_s"].to_numpy(float), strict=True):
                ax.annotate(_period(p), (xx, yy), textcoords="offset points", xytext=(4, 4), fontsize=6)
        ax.set_xscale("log")
        ax.set_yscale("symlog", linthresh=1.0)  # metres; linear below 1 m (a hold of every fix is 0)
        ax.set_ylim(bottom=0.0)
        ax.set_xlabel("battery life (h)")
        ax.set_ylabel("horizontal error p95 / p50 (m)")
        ax.set_title(str(case))
        ax.grid(True, alpha=0.3)
        ax.legend(fontsize=7)
    return fig


def power_markdown(df: pd.DataFrame, meta: Mapping[str, Any]) -> str:
    """Markdown tables, one per case, with the device and battery stated above them."""
    lines = [
        f"Device: GNSS `{meta.get('gnss', '')}`, IMU `{meta.get('imu', '')}`, MCU `{meta.get('mcu', '')}`; "
        f"time to fix after waking {fmt(meta.get('time_to_fix_s'))} s; battery {fmt(meta.get('capacity_mah'))} mAh "
        f"at {fmt(meta.get('voltage_v'))} V (usable {fmt(meta.get('usable_fraction'))}).",
        "",
    ]
    for case in dict.fromkeys(df["case"]):
        sub = df[df["case"] == case]
        lines += [f"**{case}**", "", "| " + " | ".join(_HEADER) + " |", "|" + "---|" * len(_HEADER)]
        lines += ["| " + " | ".join(fmt(c) for c in row) + " |" for row in _rows(sub)]
        lines.append("")
    return "\n".join(lines)


def power_section(
    df: pd.DataFrame, meta: Mapping[str, Any], png: Path | None = None, figure: Figure | None = None
) -> Section:
    """The report section (figure, caption, one table per case); ``png``: where its figure is saved."""
    body = []
    for case in dict.fromkeys(df["case"]):
        body.append(f"<h3>{esc(case)}</h3>")
        body.append(table(_HEADER, _rows(df[df["case"] == case])))
    sources = meta.get("sources", {})
    if sources:
        body.append(
            "<p class='note'>Sources: "
            + "; ".join(f"{esc(k)}: {esc(v)}" for k, v in sources.items())
            + "</p>"
        )
    return Section(
        key="power",
        title="Power: battery life for the accuracy you need",
        figure=figure if figure is not None else power_figure(df),
        caption=(
            "Horizontal error p95 (solid) and p50 (dashed) against battery life, one point per GNSS "
            "duty cycle; 'hold' is GNSS alone holding its latest fix."
        ),
        body="".join(body),
        png=png,
    )


def write_power_report(df: pd.DataFrame, out: Path, meta: Mapping[str, Any]) -> dict[str, Path]:
    """Write ``power.html`` (self-contained), ``power.png`` and ``power.md`` into ``out``.

    Returns
    -------
    dict
        ``html``, ``png``, ``md`` paths.
    """
    out.mkdir(parents=True, exist_ok=True)
    paths = {"html": out / "power.html", "png": out / "power.png", "md": out / "power.md"}
    fig = power_figure(df)
    paths["png"].write_bytes(png_bytes(fig))
    sec = power_section(df, meta, png=paths["png"], figure=fig)
    subtitle = f"<p>{esc(power_markdown(df, meta).splitlines()[0])}</p>"
    paths["html"].write_text(_render([sec], "iotnav power plan", subtitle))
    paths["md"].write_text(power_markdown(df, meta) + "\n")
    return paths
