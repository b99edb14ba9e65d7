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
"""

from __future__ import annotations

import base64
import html
import io
import json
import math
import re
from collections.abc import Sequence
from dataclasses import dataclass, field
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd
from matplotlib.figure import Figure

from iotnav import __version__
from iotnav.geo import LocalFrame
from iotnav.report import figures as F
from iotnav.report.load import Run, Truth, load_run, load_truth
from iotnav.report.prepare import (
    GNSS_ONLY,
    accuracy,
    boot_info,
    drift_table,
    gnss_outages,
    local,
    make_frame,
    mount_table,
    nis_table,
    positioned,
    rejected_fixes,
    static_periods,
    trips_table,
    valid_fixes,
)

STAT_COLUMNS = ("mean", "rms", "p67", "p95", "max")


@dataclass
class Section:
    """One part of the page: a figure and/or HTML, or a note saying why it is left out."""

    key: str
    title: str
    figure: Figure | None = None
    caption: str = ""
    body: str = ""
    note: str = ""
    png: Path | None = None


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


# ---------------------------------------------------------------------------- html helpers
def esc(x: Any) -> str:
    """HTML-escape ``str(x)``."""
    return html.escape(str(x), quote=True)


def fmt(x: Any, digits: int = 3) -> str:
    """A number for a table: NaN/None as an en dash, floats to ``digits`` significant digits."""
    if x is None:
        return "–"
    if isinstance(x, bool):
        return "yes" if x else "no"
    if isinstance(x, (int, np.integer)):
        return str(int(x))
    if isinstance(x, (float, np.floating)):
        v = float(x)
        if not math.isfinite(v):
            return "–"
        if v != 0.0 and (abs(v) >= 1e5 or abs(v) < 1e-3):
            return f"{v:.{digits}g}"
        return f"{v:.{max(0, digits - 1 - math.floor(math.log10(abs(v))) if v else 2)}f}"
    return str(x)


def table(header: Sequence[str], rows: Sequence[Sequence[Any]], cls: str = "") -> str:
    """An HTML table; cells are escaped and numbers formatted with :func:`fmt`."""
    h = "".join(f"<th>{esc(c)}</th>" for c in header)
    body = "".join("<tr>" + "".join(f"<td>{esc(fmt(c))}</td>" for c in r) + "</tr>" for r in rows)
    return f'<table class="{esc(cls)}"><thead><tr>{h}</tr></thead><tbody>{body}</tbody></table>'


def _flatten(d: Any, prefix: str = "") -> list[tuple[str, Any]]:
    if isinstance(d, dict):
        out: list[tuple[str, Any]] = []
        for k, v in d.items():
            out += _flatten(v, f"{prefix}.{k}" if prefix else str(k))
        return out
    if isinstance(d, list) and all(not isinstance(v, (dict, list)) for v in d):
        return [(prefix, ", ".join(fmt(v) for v in d))]
    if isinstance(d, list):
        out = []
        for k, v in enumerate(d):
            out += _flatten(v, f"{prefix}[{k}]")
        return out
    return [(prefix, d)]


def png_bytes(fig: Figure) -> bytes:
    """Render a figure to PNG bytes (100 dpi)."""
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=100)
    return buf.getvalue()


def _slug(s: str) -> str:
    return re.sub(r"[^a-z0-9]+", "-", s.lower()).strip("-")


# ---------------------------------------------------------------------------- sections
def _xy(df: pd.DataFrame, frame: LocalFrame, lat: str = "lat", lon: str = "lon") -> pd.DataFrame:
    return local(df, frame, lat, lon)


#: OpenStreetMap's standard tile layer and the attribution its tile usage policy requires.
OSM_TILES = "https://tile.openstreetmap.org/{z}/{x}/{y}.png"
OSM_ATTRIBUTION = "© OpenStreetMap contributors"
_TILE_COLORS = ("#d62728", "#1f77b4", "#2ca02c", "#9467bd", "#ff7f0e", "#8c564b")

TILE_SCRIPT = """<script>
(function () {
  var box = document.getElementById('tiles');
  if (!box) { return; }
  var data = JSON.parse(document.getElementById('tiles-data').textContent);
  var button = document.getElementById('tiles-button');
  function px(la, lo, z) {
    var n = 256 * Math.pow(2, z), r = la * Math.PI / 180;
    return [(lo + 180) / 360 * n, (1 - Math.log(Math.tan(r) + 1 / Math.cos(r)) / Math.PI) / 2 * n];
  }
  function show() {
    button.disabled = true;
    var W = Math.min(960, box.clientWidth || 960), H = 600, lat = [], lon = [], z, a, b;
    data.series.forEach(function (s) { lat = lat.concat(s.lat); lon = lon.concat(s.lon); });
    var n = Math.max.apply(null, lat), s = Math.min.apply(null, lat);
    var w = Math.min.apply(null, lon), e = Math.max.apply(null, lon);
    for (z = 19; z > 1; z--) {
      a = px(n, w, z); b = px(s, e, z);
      if (b[0] - a[0] < W - 40 && b[1] - a[1] < H - 40) { break; }
    }
    var x0 = (a[0] + b[0]) / 2 - W / 2, y0 = (a[1] + b[1]) / 2 - H / 2, failed = 0;
    var map = document.createElement('div');
    map.className = 'tilemap';
    map.style.width = W + 'px'; map.style.height = H + 'px';
    var note = document.createElement('p');
    note.className = 'note';
    for (var tx = Math.floor(x0 / 256); tx <= Math.floor((x0 + W) / 256); tx++) {
      for (var ty = Math.floor(y0 / 256); ty <= Math.floor((y0 + H) / 256); ty++) {
        var img = document.createElement('img');
        img.alt = '';
        img.style.left = (tx * 256 - x0) + 'px'; img.style.top = (ty * 256 - y0) + 'px';
        img.onerror = function () {
          failed += 1;
          note.textContent = failed + ' tile(s) could not be fetched (offline?): the figure above is the map.';
        };
        img.src = data.tile_url.replace('{z}', z).replace('{x}', tx).replace('{y}', ty);
        map.appendChild(img);
      }
    }
    var ns = 'http://www.w3.org/2000/svg', svg = document.createElementNS(ns, 'svg');
    svg.setAttribute('width', W); svg.setAttribute('height', H);
    data.series.forEach(function (t) {
      var pts = t.lat.map(function (la, i) {
        var p = px(la, t.lon[i], z);
        return (p[0] - x0).toFixed(1) + ',' + (p[1] - y0).toFixed(1);
      });
      var el = document.createElementNS(ns, t.points ? 'g' : 'polyline');
      if (t.points) {
        pts.forEach(function (q) {
          var c = document.createElementNS(ns, 'circle'), xy = q.split(',');
          c.setAttribute('cx', xy[0]); c.setAttribute('cy', xy[1]); c.setAttribute('r', 2);
          c.setAttribute('fill', t.color);
          el.appendChild(c);
        });
      } else {
        el.setAttribute('points', pts.join(' '));
        el.setAttribute('fill', 'none'); el.setAttribute('stroke', t.color); el.setAttribute('stroke-width', 2);
      }
      svg.appendChild(el);
    });
    map.appendChild(svg);
    var attr = document.createElement('div');
    attr.className = 'attribution'; attr.textContent = data.attribution;
    map.appendChild(attr);
    box.appendChild(map);
    box.appendChild(note);
  }
  button.addEventListener('click', show);
  if (location.hash === '#tiles') { show(); }
})();
</script>"""


def _decimated(df: pd.DataFrame, lat: str, lon: str, n_max: int = 1500) -> dict[str, list[float]]:
    """Every k-th finite position (at most ``n_max``), degrees rounded to 1e-7 (1 cm)."""
    ok = df[[lat, lon]].dropna()
    step = max(1, math.ceil(len(ok) / n_max))
    sub = ok.iloc[::step]
    return {
        "lat": np.round(sub[lat].to_numpy(float), 7).tolist(),
        "lon": np.round(sub[lon].to_numpy(float), 7).tolist(),
    }


def _tiles_body(runs: list[Run], truth: Truth | None, tile_url: str, attribution: str) -> str:
    """The button, the embedded decimated tracks and the tile script (see the module docstring)."""
    series = []
    fixes = valid_fixes(runs[0])
    if len(fixes):
        series.append(
            {
                "name": "raw fixes",
                "color": "#7f7f7f",
                "points": True,
                **_decimated(fixes, "lat_deg", "lon_deg"),
            }
        )
    if truth is not None:
        series.append({"name": "truth", "color": "#000000", **_decimated(truth.table, "lat", "lon")})
    for k, r in enumerate(runs):
        series.append(
            {
                "name": r.label,
                "color": _TILE_COLORS[k % len(_TILE_COLORS)],
                **_decimated(positioned(r.track), "lat", "lon"),
            }
        )
    series = [t for t in series if t["lat"]]
    if not series:
        return ""
    data = {"tile_url": tile_url, "attribution": attribution, "series": series}
    payload = json.dumps(data, separators=(",", ":")).replace("</", "<\\/")
    legend = ", ".join(f'<span style="color:{t["color"]}">{esc(t["name"])}</span>' for t in series)
    host = re.sub(r"^[a-z]+://([^/]+).*$", r"\1", tile_url)
    return (
        f'<div id="tiles"><p><button id="tiles-button" type="button">Show on map tiles</button> '
        f'<span class="note">fetches tiles from {esc(host)} (online only); {legend}</span></p></div>'
        f'<script type="application/json" id="tiles-data">{payload}</script>{TILE_SCRIPT}'
    )


def _map_section(
    runs: list[Run],
    truth: Truth | None,
    frame: LocalFrame,
    outages: list[tuple[float, float]],
    tile_url: str | None = OSM_TILES,
    attribution: str = OSM_ATTRIBUTION,
) -> Section:
    tracks = {r.label: _xy(positioned(r.track), frame) for r in runs}
    fixes = _xy(valid_fixes(runs[0]), frame, "lat_deg", "lon_deg")
    rej = rejected_fixes(runs[0])
    rej_xy = _xy(rej, frame, "lat_deg", "lon_deg")
    tr = _xy(truth.table, frame) if truth is not None else None
    no_pos = len(rej) - len(rej_xy)
    lat0, lon0 = frame.lat0_deg, frame.lon0_deg
    osm = f"https://www.openstreetmap.org/?mlat={lat0:.6f}&mlon={lon0:.6f}#map=17/{lat0:.6f}/{lon0:.6f}"
    caption = (
        f"Origin {lat0:.6f}°, {lon0:.6f}° ({'first truth point' if truth is not None else 'first valid fix'}). "
        f"{len(fixes)} valid raw fixes; {len(rej)} rejected fixes"
        + (f" ({no_pos} without a position, not drawn)" if no_pos else "")
        + (f"; {len(outages)} GNSS outage(s) highlighted on the first run" if outages else "")
        + ". "
    )
    body = (
        '<p class="note">This page fetches nothing by itself and works offline. '
        f'<a href="{esc(osm)}">Open the origin on openstreetmap.org</a> (online), or load '
        "<code>track.geojson</code> / <code>track.gpx</code> of the run into a GIS.</p>"
    )
    if tile_url:
        body += _tiles_body(runs, truth, tile_url, attribution)
    return Section("map", "Track", F.map_figure(tracks, fixes, rej_xy, tr, outages), caption, body)


def _accuracy_sections(
    runs: list[Run], truth: Truth | None, outages: list[tuple[float, float]]
) -> tuple[list[Section], dict[str, dict[str, float]]]:
    if truth is None:
        note = "No truth given (--truth): error figures and the accuracy table are left out."
        return [Section("errors", "Error against truth", note=note)], {}
    errs, stats = accuracy(runs, truth)
    base = GNSS_ONLY if GNSS_ONLY in errs else None
    rows = []
    for name, st in stats.items():
        rows.append(
            [name, int(st["n"])]
            + [st[f"h_err_{c}"] for c in STAT_COLUMNS]
            + [st[f"{a}_err_{c}"] for a in ("n", "e") for c in ("mean", "p67", "p95")]
        )
    header = ["solution", "epochs", *(f"h {c}" for c in STAT_COLUMNS)]
    header += [f"{a} {c}" for a in ("|N|", "|E|") for c in ("mean", "p67", "p95")]
    acc_table = table(header, rows, "stats")
    first = runs[0]
    pos = positioned(first.track)
    sigma = pos[["t", "std_north", "std_east"]] if {"std_north", "std_east"} <= set(pos.columns) else None
    drift = drift_table(errs[first.label], truth, outages)
    outside = {k: int(v["outside_truth"]) for k, v in stats.items() if v["outside_truth"] > 0}
    cap = (
        "Errors in metres, track minus truth interpolated to the track times, in the local NED frame of "
        "the first truth point (iotnav.eval.metrics). Grey: raw GNSS fixes. "
        + ("Shaded: GNSS outages; ▼ error at each outage end (dead-reckoning drift). " if outages else "")
        + (
            "Rows outside the truth's time span left out: "
            + ", ".join(f"{k} {v}" for k, v in outside.items())
            if outside
            else ""
        )
    )
    sec_t = Section(
        "errors",
        "Error against truth",
        F.error_time_figure(errs, base, sigma, outages, drift),
        cap,
        "<h3>Statistics, m</h3>" + acc_table,
    )
    sec_d = Section(
        "error-distribution",
        "Error distribution",
        F.error_distribution_figure(errs, base),
        "Share of epochs with an error below x (67 % and 95 % lines; dot: mean). Same statistics as the table above.",
    )
    secs = [sec_t, sec_d]
    if outages:
        if drift:
            rows_d = [
                [
                    d["start"],
                    d["end"],
                    d["length_s"],
                    d["distance_m"],
                    d["end_error_m"],
                    d["max_error_m"],
                    d["drift_pct"],
                ]
                for d in drift
            ]
            body = table(
                [
                    "start, s",
                    "end, s",
                    "length, s",
                    "distance, m",
                    "error at end, m",
                    "max error, m",
                    "drift, %",
                ],
                rows_d,
                "stats",
            )
        else:
            body = '<p class="note">No output epochs inside the outages.</p>'
        secs.append(Section("outages", f"GNSS outages: dead-reckoning drift ({first.label})", body=body))
    return secs, stats


def _outage_note(outages: list[tuple[float, float]], factor: float, run: Run) -> Section:
    if run.gnss is None:
        return Section("outage-list", "GNSS outages", note="No gnss.csv in the run: outages cannot be found.")
    if not outages:
        return Section(
            "outage-list",
            "GNSS outages",
            note=f"No gap between valid fixes longer than {factor:g} × the median interval.",
        )
    rows = [[a, b, b - a] for a, b in outages]
    return Section(
        "outage-list",
        "GNSS outages",
        body=f"<p>Gaps between valid fixes longer than {factor:g} × the median fix interval "
        "(a gap running to the end of the run ends at the last output):</p>"
        + table(["last fix before, s", "first fix after (or end), s", "gap, s"], rows, "stats"),
    )


def _static_section(run: Run, truth: Truth | None, frame: LocalFrame, fence_m: float) -> Section:
    per = static_periods(run)
    title = "Static cloud and geofence"
    if not per:
        return Section("static", title, note="No static period in this run: figure left out.")
    fixes_all = _xy(valid_fixes(run), frame, "lat_deg", "lon_deg")
    ft = fixes_all["t"].to_numpy(float)
    counts = [int(((ft >= a) & (ft <= b)).sum()) for a, b in per]
    k = int(np.argmax([(b - a) if c >= 3 else -1.0 for (a, b), c in zip(per, counts, strict=True)]))
    if counts[k] < 3:
        return Section("static", title, note="No static period holds three valid fixes: figure left out.")
    a, b = per[k]
    fixes = fixes_all.loc[(ft >= a) & (ft <= b)]
    out = _xy(positioned(run.track), frame)
    out = out.loc[(out["t"] >= a) & (out["t"] <= b)]
    if truth is not None:
        tr = _xy(truth.table, frame)
        tr = tr.loc[(tr["t"] >= a) & (tr["t"] <= b)]
    if truth is not None and len(tr):
        center = (float(tr["n_m"].mean()), float(tr["e_m"].mean()))
        what = "truth"
    else:
        center = (float(fixes["n_m"].mean()), float(fixes["e_m"].mean()))
        what = "mean of the raw fixes"
    d_fix = np.hypot(fixes["n_m"] - center[0], fixes["e_m"] - center[1])
    d_out = np.hypot(out["n_m"] - center[0], out["e_m"] - center[1])
    rows = [
        [
            "raw fixes",
            len(fixes),
            float(np.mean(d_fix)),
            float(np.percentile(d_fix, 95)),
            float(d_fix.max()),
            int((d_fix > fence_m).sum()),
        ],
    ]
    if len(out):
        rows.append(
            [
                "filtered output",
                len(out),
                float(np.mean(d_out)),
                float(np.percentile(d_out, 95)),
                float(d_out.max()),
                int((d_out > fence_m).sum()),
            ]
        )
    body = table(
        ["positions", "count", "mean distance, m", "p95, m", "max, m", f"outside {fence_m:g} m"],
        rows,
        "stats",
    )
    cap = (
        f"Longest static period of {run.label} ({len(per)} static period(s) in the run), {a:.1f}–{b:.1f} s; "
        f"geofence {fence_m:g} m around the {what}."
    )
    fig = F.static_figure(fixes, out, center, fence_m, what, (a, b))
    return Section("static", title, fig, cap, body)


def _trips_section(run: Run, frame: LocalFrame) -> Section:
    """Trips, stops, odometer and geofence events of the main run (``trips.csv``, events)."""
    title = "Trips, stops and geofences"
    trips, from_file = trips_table(run)
    tk = (run.summary.get("tracker") or {}) if from_file else {}
    rows = [
        [r.kind, r.t_start, r.t_end, r.duration_s, r.distance_m, r.max_speed_mps, r.open]
        for r in trips.itertuples(index=False)
    ]
    body = table(
        ["kind", "start, s", "end, s", "duration, s", "distance, m", "max speed, m/s", "open"], rows, "stats"
    )
    fence = [e for e in run.events if str(e.get("type", "")).startswith("geofence_")]
    if fence:
        body += table(
            ["event", "zone", "t, s", "border distance, m"],
            [[e["type"], e.get("zone", "?"), e["t"], e.get("border_m")] for e in fence],
            "stats",
        )
    passed = [e for e in run.events if e.get("type") in ("moved_while_off", "fix_rejected")]
    n_trip = int((trips["kind"] == "trip").sum())
    cap = (
        f"{n_trip} trip(s) and {int((trips['kind'] == 'stop').sum())} stop(s); odometer "
        f"{fmt(float(tk.get('odometer_m', trips.loc[trips['kind'] == 'trip', 'distance_m'].sum())))} m "
        f"(counted in trips only); {len(fence)} geofence event(s); "
        f"{sum(e['type'] == 'fix_rejected' for e in passed)} rejected fix(es), "
        f"{sum(e['type'] == 'moved_while_off' for e in passed)} moved-while-off event(s)."
        + ("" if from_file else " No trips.csv in the run: trips and stops computed from track.csv.")
    )
    tr = _xy(positioned(run.track), frame)
    if not n_trip or not len(tr):
        # no trip: the track figure above shows the stop; no figure, and nothing omitted
        return Section("trips", title, body=f"<p>{esc(cap)}</p>{body}")
    fig = F._new(8.0, 6.5)
    ax = fig.add_subplot()
    ax.plot(tr["e_m"], tr["n_m"], color="#bbbbbb", lw=0.8, label="track")
    t = tr["t"].to_numpy(float)
    for k, r in enumerate(trips.loc[trips["kind"] == "trip"].itertuples(index=False)):
        m = (t >= r.t_start) & (t <= r.t_end)
        ax.plot(tr["e_m"][m], tr["n_m"][m], lw=1.8, label=f"trip {k + 1}")
    stops = trips.loc[trips["kind"] == "stop"]
    if len(stops):
        ne = frame.to_ned(
            stops["lat_start"].to_numpy(float), stops["lon_start"].to_numpy(float), np.zeros(len(stops))
        )
        ax.scatter(ne[:, 1], ne[:, 0], marker="s", s=60, color="#d62728", zorder=5, label="stops")
        for j, (e, n) in enumerate(zip(ne[:, 1], ne[:, 0], strict=True)):
            ax.annotate(f"S{j + 1}", (e, n), textcoords="offset points", xytext=(5, 5), fontsize=8)
    ax.set_xlabel("East, m")
    ax.set_ylabel("North, m")
    ax.set_aspect("equal", adjustable="datalim")
    ax.legend(loc="best", fontsize=8)
    return Section("trips", title, fig, cap, body)


def _mount_section(runs: list[Run], truth: Truth | None, frame: LocalFrame) -> Section:
    title = "Mounting angle"
    mounts = {r.label: mount_table(r) for r in runs}
    mounts = {k: v for k, v in mounts.items() if len(v)}
    if not mounts:
        return Section(
            "mount", title, note="No mount-angle estimate in the events of the run(s): figure left out."
        )
    first = runs[0]
    m0 = mount_table(first)
    acc = m0.loc[m0["accepted"]]
    if not len(acc):
        return Section(
            "mount", title, note=f"{first.label}: no accepted mount-angle estimate: figure left out."
        )
    t_cal = float(acc["t"].iloc[0])
    mu = float(first.summary.get("mount_yaw_rad", math.nan))
    if not math.isfinite(mu):
        mu = float(acc["mount_yaw_rad"].iloc[-1])
    path = _xy(positioned(first.track), frame)
    true_mu = truth.mount_yaw_rad if truth is not None else math.nan
    finals = {}
    for r in runs:
        if r.label in mounts and len(r.track):
            finals[r.label] = (float(r.track["t"].max()), float(r.summary.get("mount_yaw_rad", math.nan)))
    fig = F.mount_figure(mounts, path, t_cal, mu, true_mu, finals=finals)
    cap = (
        f"{first.label}: first accepted estimate at {t_cal:.1f} s, final {math.degrees(mu):.2f}°"
        + (f" (true {math.degrees(true_mu):.2f}°)" if math.isfinite(true_mu) else "")
        + f"; {len(acc)} of {len(m0)} estimates accepted. Arrows: the output yaw is the sensor heading "
        "before the angle is known and the vehicle heading after; after calibration the faint arrows show "
        "the sensor x-axis (vehicle heading + mount angle)."
    )
    return Section("mount", title, fig, cap)


def _boot_section(run: Run, truth: Truth | None, frame: LocalFrame) -> Section:
    title = "Boot sequence"
    boot = boot_info(run)
    if not boot.interesting:
        when = f"at {boot.first_fix_t:.1f} s" if math.isfinite(boot.first_fix_t) else "never"
        return Section(
            "boot",
            title,
            note=f"No stored position and no rejected fix before the first accepted fix ({when}): figure left out.",
        )
    t_ff = boot.first_fix_t
    t_end = t_ff + 30.0 if math.isfinite(t_ff) else float(run.track["t"].max())
    g = (
        run.gnss
        if run.gnss is not None
        else pd.DataFrame({"t": [], "lat_deg": [], "lon_deg": [], "pdop": []})
    )
    rej = rejected_fixes(run)
    ep = g.loc[
        g["t"] <= t_end, ["t", "lat_deg", "lon_deg"] + (["pdop"] if "pdop" in g.columns else [])
    ].copy()
    if "pdop" not in ep.columns:
        ep["pdop"] = np.nan
    rej_t = rej["t"].to_numpy(float)
    ep["rejected"] = np.isin(np.round(ep["t"].to_numpy(float), 3), np.round(rej_t, 3))
    if "valid" in g.columns:
        ep.loc[~g.loc[ep.index, "valid"].to_numpy(bool), "rejected"] = True
    ep["reason"] = ""
    pos = np.isfinite(ep["lat_deg"].to_numpy(float)) & np.isfinite(ep["lon_deg"].to_numpy(float))
    ep["n_m"] = np.nan
    ep["e_m"] = np.nan
    if pos.any():
        xy = _xy(ep.loc[pos], frame, "lat_deg", "lon_deg")
        ep.loc[pos, "n_m"] = xy["n_m"].to_numpy()
        ep.loc[pos, "e_m"] = xy["e_m"].to_numpy()
    tr = _xy(positioned(run.track), frame)
    tr = tr.loc[tr["t"] <= t_end]
    stored = None
    if boot.stored is not None:
        ned = frame.to_ned(boot.stored[0], boot.stored[1], 0.0)
        stored = (float(ned[0]), float(ned[1]))
    ff = None
    if math.isfinite(t_ff):
        hit = ep.loc[(np.abs(ep["t"] - t_ff) < 1e-3) & np.isfinite(ep["n_m"])]
        if len(hit):
            ff = (t_ff, float(hit["n_m"].iloc[0]), float(hit["e_m"].iloc[0]))
    max_pdop = (
        float(run.config.get("last_position", {}).get("max_pdop", math.nan)) if run.config else math.nan
    )
    tru = None
    if truth is not None:
        tru = _xy(truth.table, frame)
        tru = tru.loc[tru["t"] <= t_end]
    fig = F.boot_figure(ep, tr, stored, ff, max_pdop, tru)
    reasons = rej.loc[rej["t"] < t_ff] if math.isfinite(t_ff) else rej
    by_reason = reasons["reason"].value_counts().to_dict()
    cap = (
        ("Stored last position loaded at boot. " if boot.stored is not None else "No stored position. ")
        + f"{len(boot.rejected_before)} fixes rejected before the first accepted one"
        + (" (" + ", ".join(f"{k}: {v}" for k, v in by_reason.items()) + ")" if by_reason else "")
        + (f"; first accepted fix at {t_ff:.1f} s" if math.isfinite(t_ff) else "; no fix accepted")
        + (f"; moved while off: {boot.moved_m:.0f} m" if math.isfinite(boot.moved_m) else "")
        + f". Window: start to {t_end:.0f} s."
    )
    return Section("boot", title, fig, cap)


def _states_section(runs: list[Run], truth: Truth | None, outages: list[tuple[float, float]]) -> Section:
    tracks = {r.label: r.track for r in runs}
    need = {"roll", "pitch", "yaw", "vn", "ve"}
    lacking = [r.label for r in runs if not need <= set(r.track.columns)]
    if lacking:
        return Section(
            "states",
            "Attitude and speed",
            note=f"Track lacks attitude/velocity columns ({', '.join(lacking)}).",
        )
    g = valid_fixes(runs[0])
    fig = F.states_figure(tracks, truth.table if truth is not None else None, g if len(g) else None, outages)
    return Section(
        "states",
        "Attitude, speed and uncertainty",
        fig,
        "Roll, pitch, yaw of the output (vehicle attitude once the mount angle is known), horizontal speed, "
        "and 3σ of the North/East position from the track's std_north/std_east.",
    )


def _bias_section(runs: list[Run]) -> Section:
    rows = []
    keys = (
        ("gyro_bias_rad_s", "gyro bias, rad/s"),
        ("acc_bias_mps2", "accelerometer bias, m/s²"),
        ("gyro_scale", "gyro scale factor"),
        ("acc_scale", "accelerometer scale factor"),
    )
    for r in runs:
        es = r.summary.get("engine_summary") or {}
        for k, name in keys:
            v = es.get(k)
            if isinstance(v, list) and v:
                rows.append([r.label, name, *[fmt(x, 3) for x in v[:3]]])
    note = (
        '<p class="note">Bias time series and their σ are not recorded by runs (track.csv has no bias columns), '
        "so no bias plot with 3σ bounds is drawn; the final estimates from summary.json are listed.</p>"
    )
    if not rows:
        return Section("biases", "Sensor biases", note="No bias estimate in summary.json.")
    return Section(
        "biases",
        "Sensor biases (final estimates)",
        body=note + table(["run", "quantity", "x", "y", "z"], rows, "stats"),
    )


def _nis_section(runs: list[Run]) -> Section:
    nis = {r.label: nis_table(r) for r in runs}
    nis = {k: v for k, v in nis.items() if len(v)}
    rows = []
    for r in runs:
        es = r.summary.get("engine_summary") or {}
        for meas, d in (es.get("nis") or {}).items():
            if isinstance(d, dict):
                rows.append([r.label, meas, d.get("count"), d.get("accepted"), d.get("mean_nis_per_dof")])
    body = (
        table(["run", "measurement", "updates", "accepted", "mean NIS per dof"], rows, "stats")
        if rows
        else ""
    )
    if not nis and not rows:
        return Section("nis", "NIS", note="No NIS in the events or summary of the run(s): left out.")
    fig = F.nis_figure(nis) if nis else None
    note = "" if nis else "No event carries a NIS value: only the summary table is shown."
    return Section(
        "nis",
        "Normalised innovation squared",
        fig,
        "NIS of the updates whose events carry one (gated rejections). A consistent filter has a mean NIS per "
        "degree of freedom near 1.",
        body,
        note,
    )


def _timeline_section(run: Run, outages: list[tuple[float, float]]) -> Section:
    per = static_periods(run)
    t = run.track["t"].to_numpy(float)
    t_range = (float(np.nanmin(t)), float(np.nanmax(t))) if t.size else (0.0, 1.0)
    counts: dict[str, int] = {}
    for e in run.events:
        counts[e["type"]] = counts.get(e["type"], 0) + 1
    fig = F.timeline_figure(run.events, per, outages, t_range) if run.events or per or outages else None
    listing = []
    for e in run.events[:2000]:
        extra = {k: v for k, v in e.items() if k not in ("type", "t")}
        listing.append([e.get("t"), e["type"], json.dumps(extra, default=str)[:300]])
    more = f"<p>… {len(run.events) - 2000} more in events.json</p>" if len(run.events) > 2000 else ""
    body = (
        table(["event type", "count"], sorted(counts.items()), "stats")
        + f"<details><summary>All {len(run.events)} events of {esc(run.label)}</summary>"
        + table(["t, s", "type", "details"], listing, "events")
        + more
        + "</details>"
    )
    note = "" if fig is not None else "No events, static periods or outages: nothing on the timeline."
    return Section(
        "events",
        f"Events ({run.label})",
        fig,
        "Boot events without a time are listed below only.",
        body,
        note,
    )


def _config_section(runs: list[Run]) -> Section:
    parts = []
    for r in runs:
        s = r.summary
        c = s.get("counts", {}) or {}
        rates = s.get("rates_hz", {}) or {}
        mu = s.get("mount_yaw_rad")
        info: list[list[Any]] = [
            ["directory", str(r.path)],
            ["engine", r.engine],
            ["output rows", c.get("output_rows")],
            ["output rate, Hz", rates.get("output")],
            ["GNSS epochs in / rate, Hz", f"{c.get('gnss_epochs_in', '–')} / {fmt(rates.get('gnss'))}"],
            ["IMU samples in / rate, Hz", f"{c.get('imu_samples_in', '–')} / {fmt(rates.get('imu'))}"],
            ["rows by source", ", ".join(f"{k} {v}" for k, v in (c.get("rows_by_source") or {}).items())],
            ["static rows", c.get("static_rows")],
            ["mount yaw, deg", math.degrees(mu) if isinstance(mu, (int, float)) else None],
            ["runtime, s", s.get("runtime_s")],
        ]
        if r.missing:
            info.append(["missing files", ", ".join(r.missing)])
        cfg = _flatten(r.config)
        cfg_html = (
            table(["parameter", "value"], cfg, "config")
            if cfg
            else '<p class="note">No configuration in summary.json.</p>'
        )
        notes = []
        for f in (s.get("ingest") or {}).get("files", []) or []:
            for n in f.get("notes", []) or []:
                notes.append(f"{f.get('path', '?')}: {n}")
        notes_html = "<ul>" + "".join(f"<li>{esc(n)}</li>" for n in notes) + "</ul>" if notes else ""
        parts.append(
            f"<h3>{esc(r.label)}</h3>"
            + table(["what", "value"], info, "kv")
            + "<h4>Engine configuration</h4>"
            + cfg_html
            + (f"<h4>Ingest notes</h4>{notes_html}" if notes_html else "")
            + f"<details><summary>summary.json of {esc(r.label)}</summary><pre>{esc(json.dumps(s, indent=1))}</pre></details>"
        )
    return Section("config", "Runs and configuration used", body="".join(parts))


# ---------------------------------------------------------------------------- page
CSS = """
body{font-family:system-ui,-apple-system,'Segoe UI',Roboto,sans-serif;margin:0;color:#222;background:#fafafa}
header{background:#1f3b57;color:#fff;padding:1rem 2rem}
header h1{margin:0 0 .3rem 0;font-size:1.5rem}
header p{margin:.1rem 0;opacity:.9}
nav{padding:.5rem 2rem;background:#e9eef3;font-size:.9rem}
nav a{margin-right:1rem;color:#1f3b57}
main{padding:0 2rem 2rem 2rem;max-width:1400px}
section{background:#fff;border:1px solid #ddd;border-radius:6px;padding:.5rem 1.2rem 1rem;margin:1rem 0}
h2{font-size:1.2rem;border-bottom:1px solid #eee;padding-bottom:.3rem}
figure{margin:.5rem 0}
figure img{max-width:100%;height:auto;border:1px solid #eee}
figcaption{font-size:.88rem;color:#444;margin-top:.3rem}
table{border-collapse:collapse;margin:.6rem 0;font-size:.85rem}
th,td{border:1px solid #ddd;padding:.2rem .5rem;text-align:right}
th{background:#f0f3f6}
td:first-child,th:first-child{text-align:left}
table.config td,table.kv td,table.events td{text-align:left}
table.events td:last-child{font-family:monospace;font-size:.78rem}
.note{color:#666;font-style:italic}
pre{font-size:.75rem;max-height:30rem;overflow:auto;background:#f6f6f6;padding:.5rem}
.tilemap{position:relative;overflow:hidden;border:1px solid #ddd;background:#eef}
.tilemap img{position:absolute;width:256px;height:256px}
.tilemap svg{position:absolute;left:0;top:0}
.tilemap .attribution{position:absolute;right:0;bottom:0;background:rgba(255,255,255,.8);font-size:.7rem;padding:0 .3rem}
"""


def _render(sections: list[Section], title: str, subtitle: str) -> str:
    nav = "".join(f'<a href="#{esc(s.key)}">{esc(s.title)}</a>' for s in sections)
    out = []
    for s in sections:
        parts = [f'<section id="{esc(s.key)}"><h2>{esc(s.title)}</h2>']
        if s.note:
            parts.append(f'<p class="note omitted">{esc(s.note)}</p>')
        if s.png is not None and s.figure is not None:
            data = base64.b64encode(s.png.read_bytes()).decode("ascii")
            parts.append(
                f'<figure><img src="data:image/png;base64,{data}" alt="{esc(s.title)}" '
                f'data-file="{esc(s.png.name)}"><figcaption>{esc(s.caption)}</figcaption></figure>'
            )
        parts.append(s.body)
        parts.append("</section>")
        out.append("".join(parts))
    return (
        '<!DOCTYPE html>\n<html lang="en"><head><meta charset="utf-8">'
        '<meta name="viewport" content="width=device-width, initial-scale=1">'
        f"<title>{esc(title)}</title><style>{CSS}</style></head><body>"
        f"<header><h1>{esc(title)}</h1>{subtitle}</header><nav>{nav}</nav><main>"
        + "\n".join(out)
        + "</main></body></html>\n"
    )


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
