"""The report in a real headless browser: it loads offline, every figure decodes, no console errors.

Skips only when Chromium is not installed (CI installs Debian's ``chromium``).
"""

from __future__ import annotations

import io
import threading
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from _browser import chromium, load_page
from _report_synth import write_synthetic_run
from iotnav import sim
from iotnav.engines.base import run_batch
from iotnav.engines.registry import make_engine
from iotnav.io import ingest
from iotnav.report import build_report
from iotnav.runs import load_stored_position, write_run


@pytest.fixture(autouse=True)
def _needs_chromium() -> None:
    """Fail (not skip) without Chromium: the report's browser check is a shipped promise."""
    assert chromium() is not None, "chromium is not installed (apt-get install chromium)"


def _visible(png: Path) -> np.ndarray:
    im = np.asarray(Image.open(png).convert("RGB"), dtype=float)
    assert im.shape[0] > 500 and im.shape[1] >= 1000
    return im


def test_checker_catches_a_broken_page(tmp_path: Path) -> None:
    """The probe is not vacuous: a bad image and a script error are seen."""
    good = "iVBORw0KGgoAAAANSUhEUgAAAAEAAAABCAYAAAAfFcSJAAAADUlEQVR42mP8z8BQDwAEhQGAhKmMIQAAAABJRU5ErkJggg=="
    page = tmp_path / "bad.html"
    page.write_text(
        "<!DOCTYPE html><html><head><title>t</title></head><body>"
        f'<img src="data:image/png;base64,{good}"><img src="data:image/png;base64,AAAA">'
        "<script>no_such_function();</script></body></html>"
    )
    res = load_page(page, tmp_path / "bad.png", height=600)
    assert (res.images_ok, res.images_total) == (1, 2)
    assert res.errors >= 1
    assert any("no_such_function" in c for c in res.console)


def test_report_of_simulated_runs_renders_in_browser(tmp_path: Path) -> None:
    """A cold-boot walk fused by two engines, compared against truth, viewed in Chromium."""
    result = sim.build("walk-cold-boot", seed=3)
    sim_dir = tmp_path / "sim"
    sim.write(result, sim_dir)
    log = ingest([sim_dir / "gnss.nmea", sim_dir / "imu.csv"])
    stored = load_stored_position(sim_dir / "last_position.json")
    runs = []
    for name in ("pipeline", "eskf"):
        track = run_batch(make_engine(name, None, stored=stored, store=None), log)
        write_run(tmp_path / name, track, log, name, 0.0)
        runs.append(tmp_path / name)
    rep = build_report(runs, tmp_path / "report" / "index.html", sim_dir / "truth.csv")
    # the walk has a boot with rejected fixes, static periods and truth
    assert {"map", "errors", "boot", "static", "events"} <= {p.stem.split("_", 1)[1] for p in rep.figures}
    assert set(rep.accuracy) >= {"pipeline", "eskf"}

    shot = tmp_path / "shot.png"
    res = load_page(rep.html, shot)
    assert res.images_total == len(rep.figures) > 5
    assert res.images_ok == res.images_total, "some figure did not decode in the browser"
    assert res.errors == 0
    assert res.console == []
    im = _visible(shot)
    assert im.std() > 20.0  # not a blank page
    assert len(np.unique(im.reshape(-1, 3), axis=0)) > 100  # figures, not just text on white


def _tile_png() -> bytes:
    buf = io.BytesIO()
    Image.new("RGB", (256, 256), (40, 160, 60)).save(buf, format="PNG")
    return buf.getvalue()


def test_map_tiles_only_on_request_and_drawn_from_the_tile_server(tmp_path: Path) -> None:
    """Opened plainly, the page requests no tile; with ``#tiles`` (the button's action) it
    fetches the tiles around the track from the configured server and overlays the track."""
    tile = _tile_png()
    requests: list[str] = []

    class Tiles(BaseHTTPRequestHandler):
        def do_GET(self) -> None:
            requests.append(self.path)
            self.send_response(200)
            self.send_header("Content-Type", "image/png")
            self.send_header("Content-Length", str(len(tile)))
            self.end_headers()
            self.wfile.write(tile)

        def log_message(self, *args: object) -> None:
            pass

    server = ThreadingHTTPServer(("127.0.0.1", 0), Tiles)
    threading.Thread(target=server.serve_forever, daemon=True).start()
    try:
        run, truth = write_synthetic_run(tmp_path)
        url = f"http://127.0.0.1:{server.server_port}/{{z}}/{{x}}/{{y}}.png"
        rep = build_report(
            [run], tmp_path / "rep" / "index.html", truth, tile_url=url, tile_attribution="test tiles"
        )
        text = rep.html.read_text()
        assert 'id="tiles-button"' in text and "test tiles" in text
        plain = load_page(rep.html, tmp_path / "plain.png", height=1200)
        assert requests == []
        assert plain.images_total == len(rep.figures) and plain.errors == 0 and plain.console == []
        tiles = load_page(rep.html, tmp_path / "tiles.png", height=1200, fragment="tiles")
        assert plain.console == [] and tiles.errors == 0, tiles
        n_tiles = tiles.images_total - len(rep.figures)
        assert n_tiles >= 1 and tiles.images_ok == tiles.images_total
        assert len(requests) == n_tiles
        # the synthetic track (about 400 m East at 45 N) fits the 960 x 600 view at zoom 17-18,
        # so the requested tiles are the few around it
        z = {int(p.split("/")[1]) for p in requests}
        assert z <= {17, 18}, requests
    finally:
        server.shutdown()
