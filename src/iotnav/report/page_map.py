"""Track map section of the run report (:mod:`iotnav.report.page`).

The local East/North view in metres, always drawn, and under it an optional button that draws
the tracks (decimated lat/lon embedded in the page) in Web Mercator over slippy-map tiles
fetched from ``tile_url`` only after a click: ``x = (lon + 180) / 360 * 256 * 2^z``,
``y = (1 - asinh(tan(lat)) / pi) / 2 * 256 * 2^z`` (the standard slippy-map tile numbering,
https://wiki.openstreetmap.org/wiki/Slippy_map_tilenames), with an SVG overlay and no map library.
"""

from __future__ import annotations

import json
import math
import re

import numpy as np
import pandas as pd

from iotnav.geo import LocalFrame
from iotnav.report import figures as F
from iotnav.report.load import Run, Truth
from iotnav.report.page_html import Section, esc
from iotnav.report.prepare import (
    local,
    positioned,
    rejected_fixes,
    valid_fixes,
)


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
