"""Assemble a self-contained HTML report of one run, optionally compared with others.

:func:`build_report` reads the run directories (and a truth file), draws the figures of
:mod:`iotnav.report.figures`, writes each as a PNG beside the HTML (``<stem>_<name>.png``) and
embeds the same bytes as base64 ``<img>`` in one HTML file with inline CSS and no external
resource: it opens offline in any browser and fetches nothing by itself.

Map tiles, when online: the track figure is the local East/North view in metres (it always
works); under it a button "Show on map tiles" draws the tracks (decimated lat/lon embedded in
the page) in Web Mercator over slippy-map tiles fetched from ``tile_url`` (default
OpenStreetMap's, with its attribution; ``tile_url=None`` leaves the button out). Nothing is
requested before the click (or before opening the page with ``#tiles``); tiles that cannot be
fetched leave a note, and the metres view above stays the map. No map library: about forty
lines of inline script compute the tile grid (``x = (lon + 180) / 360 * 256 * 2^z``,
``y = (1 - asinh(tan(lat)) / pi) / 2 * 256 * 2^z``) and an SVG overlay.

Figures that do not apply (no truth, no static period, nothing at boot, no mount estimate,
no NIS) are left out with a one-line note saying why.

Modules: the HTML building blocks and the page layout are in :mod:`iotnav.report.page_html`,
the track map in :mod:`iotnav.report.page_map`, the other sections in
:mod:`iotnav.report.page_sections` (public names re-exported here).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from datetime import UTC, datetime
from pathlib import Path

import numpy as np

from iotnav import __version__
from iotnav.report.load import load_run, load_truth
from iotnav.report.page_html import (  # re-exported
    CSS as CSS,
)
from iotnav.report.page_html import (
    Section,
    _render,
    _slug,
    esc,
    png_bytes,
)
from iotnav.report.page_html import (
    fmt as fmt,
)
from iotnav.report.page_html import (
    table as table,
)
from iotnav.report.page_map import (
    OSM_ATTRIBUTION,
    OSM_TILES,
    _map_section,
)
from iotnav.report.page_map import (  # re-exported
    TILE_SCRIPT as TILE_SCRIPT,
)
from iotnav.report.page_sections import (  # re-exported
    STAT_COLUMNS as STAT_COLUMNS,
)
from iotnav.report.page_sections import (
    _accuracy_sections,
    _bias_section,
    _boot_section,
    _config_section,
    _mount_section,
    _nis_section,
    _outage_note,
    _states_section,
    _static_section,
    _timeline_section,
    _trips_section,
)
from iotnav.report.prepare import (
    gnss_outages,
    make_frame,
)


@dataclass(frozen=True)
class Report:
    """What :func:`build_report` wrote.

    Attributes
    ----------
    html : pathlib.Path
        The HTML file.
    figures : list of pathlib.Path
        PNG files written beside it, in page order.
    omitted : dict of str to str
        Section key to the note explaining why its figure is left out.
    accuracy : dict of str to dict
        :func:`iotnav.eval.metrics.error_stats` per solution (empty without truth).
    """

    html: Path
    figures: list[Path]
    omitted: dict[str, str] = field(default_factory=dict)
    accuracy: dict[str, dict[str, float]] = field(default_factory=dict)


def build_report(
    run_dirs: Sequence[Path | str],
    html_path: Path | str | None = None,
    truth_path: Path | str | None = None,
    *,
    labels: Sequence[str] | None = None,
    gap_factor: float = 3.0,
    fence_m: float = 15.0,
    tile_url: str | None = OSM_TILES,
    tile_attribution: str = OSM_ATTRIBUTION,
) -> Report:
    """Write the HTML report of one run (the first) compared with the others.

    Parameters
    ----------
    run_dirs : sequence of path
        Run directories written by ``iotnav run``; the first is the main run, the others are
        overlaid (``--compare``).
    html_path : path, optional
        Where to write the page; default ``<first run>/report.html``. PNGs go beside it as
        ``<stem>_<figure>.png``.
    truth_path : path, optional
        Truth table (``truth.csv`` of the simulator).
    labels : sequence of str, optional
        Names of the runs (default: directory names, made unique).
    gap_factor : float
        A gap between valid fixes longer than ``gap_factor`` times the median interval is a
        GNSS outage.
    fence_m : float
        Geofence radius drawn around the static point, m.
    tile_url : str or None
        Slippy-map tile URL template with ``{z}``, ``{x}``, ``{y}`` for the opt-in tile view
        (default OpenStreetMap's standard layer); None: no tile view.
    tile_attribution : str
        Attribution drawn on the tiles (the tile server's terms).

    Returns
    -------
    Report
        Paths written, omitted figures with their reasons, accuracy statistics.
    """
    if not run_dirs:
        raise ValueError("give at least one run directory")
    names = list(labels) if labels is not None else _unique_labels([Path(p) for p in run_dirs])
    runs = [load_run(p, n) for p, n in zip(run_dirs, names, strict=True)]
    truth = load_truth(truth_path) if truth_path is not None else None
    out = Path(html_path) if html_path is not None else runs[0].path / "report.html"
    out.parent.mkdir(parents=True, exist_ok=True)
    frame = make_frame(runs, truth)
    first = runs[0]
    t_end = float(first.track["t"].max()) if len(first.track) else math.nan
    outages = gnss_outages(first.gnss, gap_factor, t_end)

    sections: list[Section] = [_map_section(runs, truth, frame, outages, tile_url, tile_attribution)]
    acc_secs, stats = _accuracy_sections(runs, truth, outages)
    sections += acc_secs
    sections.append(_outage_note(outages, gap_factor, first))
    sections.append(_static_section(first, truth, frame, fence_m))
    sections.append(_trips_section(first, frame))
    sections.append(_mount_section(runs, truth, frame))
    sections.append(_boot_section(first, truth, frame))
    sections.append(_states_section(runs, truth, outages))
    sections.append(_bias_section(runs))
    sections.append(_nis_section(runs))
    sections.append(_timeline_section(first, outages))
    sections.append(_config_section(runs))

    written: list[Path] = []
    for s in sections:
        if s.figure is not None:
            s.png = out.with_name(f"{out.stem}_{_slug(s.key)}.png")
            s.png.write_bytes(png_bytes(s.figure))
            written.append(s.png)
    t = first.track["t"].to_numpy(float)
    span = f"{np.nanmin(t):.1f}–{np.nanmax(t):.1f} s" if t.size else "empty track"
    title = f"iotnav report: {first.label}" + (
        f" vs {', '.join(r.label for r in runs[1:])}" if runs[1:] else ""
    )
    subtitle = (
        f"<p>Engine {esc(first.engine)}, {len(first.track)} output rows, {esc(span)}"
        + (f"; truth {esc(truth.path)}" if truth is not None else "; no truth")
        + f"</p><p>Generated by iotnav {esc(__version__)} on {datetime.now(UTC):%Y-%m-%d %H:%M} UTC.</p>"
    )
    if first.missing:
        subtitle += f"<p>Missing in {esc(first.path)}: {esc(', '.join(first.missing))}</p>"
    out.write_text(_render(sections, title, subtitle), encoding="utf-8")
    omitted = {s.key: s.note for s in sections if s.figure is None and s.note}
    return Report(out, written, omitted, stats)


def _unique_labels(paths: list[Path]) -> list[str]:
    names = [p.resolve().name for p in paths]
    if len(set(names)) == len(names):
        return names
    return [f"{p.resolve().parent.name}/{p.resolve().name}" for p in paths]
