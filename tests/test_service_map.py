"""The web map of ``iotnav serve`` in a real headless Chromium against a real running service.

The module starts ``python -m iotnav.service`` (SQLite, real sockets) and Chromium with its
DevTools protocol on a local port, both at once. The service runs no engine, so the clean
positions are the fixes as sent (the ``fixes`` engine's first step compiles its kernels, about
20 s from an empty numba cache here, past this file's budget). The tests drive the page as a
person would (real mouse events through the DevTools protocol), post OsmAnd fixes over HTTP,
and read what the page shows: the DOM, the page's own state object ``window.iotnav`` and a
screenshot. Screenshots are written under the test's tmp folder (``map_*.png``) for a person
to look at.

The tests run in file order on one page: the first opens it and posts the device's fixes that
the later ones look at. Fails, not skips, when Chromium or the Leaflet files (``make setup``:
``npm ci``) are missing: the web map is a shipped feature.
"""

from __future__ import annotations

import json
import threading
import time
from collections.abc import Iterator
from datetime import datetime, timedelta
from typing import Any

import httpx
import numpy as np
import pytest
from fastapi import FastAPI, Response
from fastapi.testclient import TestClient
from PIL import Image

from _map_page import M_PER_DEG_LAT, M_PER_PX, Page, auth, colour_pixels, osmand, service_and_page
from _service_helpers import Service, free_ports
from iotnav.service import web

LAT0, LON0 = 48.2082, 16.3738  # Vienna, Stephansplatz


@pytest.fixture(scope="module")
def live(tmp_path_factory) -> Iterator[tuple[Service, Page]]:
    with service_and_page(Service(tmp_path_factory.mktemp("map") / "data")) as both:
        yield both
    _CLIENT.close()


_CLIENT = httpx.Client(timeout=10)  # one kept-alive connection, as a tracker app holds it


def _osmand(svc: Service, uid: str, lat: float, lon: float, t: float, acc: float) -> None:
    osmand(_CLIENT, svc, uid, lat, lon, t, acc)


def _tooltip_box(name: str) -> str:
    """JS: the on-screen box of the permanent label of device ``name`` inside the map, or null."""
    return (
        "(function(){var m=document.getElementById('map').getBoundingClientRect();"
        "var t=Array.prototype.find.call(document.querySelectorAll('.leaflet-tooltip'),"
        f"function(e){{return e.textContent.indexOf({json.dumps(name)})===0;}});"
        "if(!t){return null;}var b=t.getBoundingClientRect();"
        "return (b.left>=m.left&&b.right<=m.right&&b.top>=m.top&&b.bottom<=m.bottom)?[b.left,b.top]:null;})()"
    )


def test_device_appears_moves_track_and_geofence_show(live, tmp_path) -> None:
    """Open the page, a device posts fixes: it shows within 1 s, moves within 1 s; its track, raw
    fixes, uncertainty circles and a geofence are drawn; no request leaves the service."""
    svc, page = live
    # a geofence around the start, made through the API before the page opens
    area = f"CIRCLE ({LAT0} {LON0}, 120)"
    r = httpx.post(svc.url("/api/geofences"), json={"name": "depot", "area": area}, headers=auth(svc))
    assert r.status_code == 200, r.text
    page.send("Page.navigate", url=svc.url(f"/#token={svc.admin_token}"))
    page.wait("window.iotnav && iotnav.ready && iotnav.socketOpen && !iotnav.moving")
    assert page.eval("location.hash") == ""  # the token left the address bar

    now = time.time()
    _osmand(svc, "van-1", LAT0, LON0, now - 60, 8.0)
    box1, t_show = page.wait(_tooltip_box("van-1"))
    dlat = 60.0 / M_PER_DEG_LAT  # 60 m north
    _osmand(svc, "van-1", LAT0 + dlat, LON0, now - 50, 12.0)
    box2, t_move = page.wait(
        f"(function(b){{return b && b[1] < {box1[1]} - 5 ? b : null;}})({_tooltip_box('van-1')})"
    )
    print(f"device shown {t_show * 1000:.0f} ms, moved {t_move * 1000:.0f} ms after the fix was acknowledged")
    assert t_show < 1.0 and t_move < 1.0
    # the map's scale: 60 m north moved the label by 60 m / (metres per pixel) pixels
    m_per_px = page.eval(M_PER_PX)
    assert box1[1] - box2[1] == pytest.approx(60.0 / m_per_px, abs=2.0)
    latest = page.eval("iotnav.latest[Object.keys(iotnav.latest)[0]]")
    assert (latest["latitude"], latest["accuracy"]) == (pytest.approx(LAT0 + dlat, abs=1e-7), 12.0)

    # a walk north-east of 6 more fixes, then the person clicks the device to see its track
    lats = [LAT0 + dlat + 10.0 * k / M_PER_DEG_LAT for k in range(1, 7)]
    lons = [LON0 + 15.0 * k / (M_PER_DEG_LAT * np.cos(np.radians(LAT0))) for k in range(1, 7)]
    for k, (la, lo) in enumerate(zip(lats, lons, strict=True)):
        _osmand(svc, "van-1", la, lo, now - 40 + k, 5.0 + k)
    page.wait(f"iotnav.latest[Object.keys(iotnav.latest)[0]].latitude > {lats[-1] - 1e-6}")
    page.click_element("#devices li")
    track, _ = page.wait(
        "iotnav.track && iotnav.track.clean >= 8 && {clean: iotnav.track.clean, raw: iotnav.track.raw}"
    )
    assert track == {"clean": 8, "raw": 8}
    assert page.eval("document.querySelector('.grid-label').textContent").startswith("grid ")
    scale = page.eval("document.querySelector('.leaflet-control-scale-line').textContent")
    assert scale.endswith(" m") or scale.endswith(" km")
    page.wait("!iotnav.moving")  # the fit-to-track animation has ended
    im = page.screenshot(tmp_path / "map_track.png")
    m_per_px = page.eval(M_PER_PX)
    track_m = 60.0 + 6 * np.hypot(10.0, 15.0)
    # drawn, in pixels of their own colour: the clean line (3 px wide) at least one pixel along its
    # length; the 8 raw dots (radius 4 px; the latest marker covers one) at least 20 px each; the
    # geofence outline (2 px) along at least half its circumference (part is off the view)
    n_clean, n_raw, n_fence = (colour_pixels(im, c) for c in ("#1f5fbf", "#e8771a", "#2a9d3a"))
    print(f"pixels: clean {n_clean}, raw {n_raw}, geofence {n_fence}; {m_per_px:.2f} m/px")
    assert n_clean > track_m / m_per_px
    assert n_raw > 7 * 20
    assert n_fence > np.pi * 120.0 / m_per_px
    # the latest position's uncertainty: a circle of its accuracy radius (10 m) on screen
    width = page.eval("document.querySelector('.leaflet-latest-pane path').getBoundingClientRect().width")
    assert width == pytest.approx(2 * 10.0 / m_per_px, abs=3.0)
    assert page.eval("iotnav.geofences.length") == 1
    # every request went to the service itself (page, Leaflet, API, socket): no CDN, no tiles
    origin = svc.url("/")
    urls = [u for u in page.requested_urls() if not u.startswith("data:")]  # data: is no request
    assert urls and all(u.startswith(origin) for u in urls), [u for u in urls if not u.startswith(origin)]
    assert page.errors() == [] and page.eval("iotnav.errors") == []


def test_track_for_a_chosen_period(live) -> None:
    """The person types a period (UTC) and presses Show: the first two fixes only, not followed live."""
    svc, page = live
    wide = {"deviceId": 1, "from": "2000-01-01T00:00:00Z", "to": "2100-01-01T00:00:00Z"}
    rows = httpx.get(svc.url("/api/positions"), params=wide, headers=auth(svc)).json()
    assert len(rows) == 8
    t = [datetime.fromisoformat(r["fixTime"].replace("Z", "+00:00")) for r in rows]
    first, second = (x.replace(microsecond=0, tzinfo=None) for x in t[:2])
    page.eval(
        f"document.getElementById('track-from').value = '{first.isoformat()}';"
        f"document.getElementById('track-to').value = '{(second + timedelta(seconds=1)).isoformat()}'"
    )
    page.click_element("#track-form button")
    track, _ = page.wait(
        "iotnav.track && !iotnav.track.live && {clean: iotnav.track.clean, raw: iotnav.track.raw}"
    )
    assert track == {"clean": 2, "raw": 2}
    assert (
        page.eval("document.getElementById('track-info').textContent")
        == "2 clean positions (none), 2 raw fixes"
    )


def _place_at(page: Page, lat: float, lon: float) -> float:
    """Press the form's place button, click the map at (lat, lon); metres per pixel of the view."""
    page.click_element("#gf-place")
    page.wait("!iotnav.moving")  # the view stands still where the person aims
    px = page.eval(f"iotnav.toPixel({lat}, {lon})")
    m_per_px = float(page.eval(M_PER_PX))
    page.click(px["x"], px["y"])
    return m_per_px


def _circle(fence: dict[str, Any]) -> tuple[float, float, float]:
    lat, lon, radius = fence["area"].removeprefix("CIRCLE (").rstrip(")").replace(",", " ").split()
    return float(lat), float(lon), float(radius)


def _miss_m(lat: float, lon: float, target: tuple[float, float]) -> float:
    return float(
        np.hypot(
            (lat - target[0]) * M_PER_DEG_LAT, (lon - target[1]) * M_PER_DEG_LAT * np.cos(np.radians(LAT0))
        )
    )


def test_geofence_placed_moved_and_deleted_with_the_mouse(live, tmp_path) -> None:
    """The person names a circle, clicks "place", clicks the map: the API has the circle there;
    "edit", a new radius and a click elsewhere move it (same geofence); "delete" removes it."""
    svc, page = live
    target = (LAT0 - 40.0 / M_PER_DEG_LAT, LON0 + 0.0004)
    page.eval(
        "document.getElementById('gf-name').value = 'gate'; document.getElementById('gf-radius').value = '25'"
    )
    m_per_px = _place_at(page, *target)
    page.wait("iotnav.geofences.length === 2")
    fences = httpx.get(svc.url("/api/geofences"), headers=auth(svc)).json()
    gate = next(f for f in fences if f["name"] == "gate")
    lat, lon, radius = _circle(gate)
    assert radius == 25.0
    assert _miss_m(lat, lon, target) < 1.5 * m_per_px  # within a pixel or so of where it was aimed
    page.screenshot(tmp_path / "map_geofence.png")

    moved = (LAT0 + 20.0 / M_PER_DEG_LAT, LON0 - 0.0006)
    page.click_element(f"#geofences li[data-geofence-id='{gate['id']}'] button")  # edit
    assert page.eval("document.getElementById('gf-radius').value") == "25"
    page.eval("document.getElementById('gf-radius').value = '40'")
    m_per_px = _place_at(page, *moved)
    page.wait("iotnav.geofences.some(function (g) { return g.area.indexOf(', 40)') > 0; })")
    fences = httpx.get(svc.url("/api/geofences"), headers=auth(svc)).json()
    assert [f["name"] for f in fences] == ["depot", "gate"]
    (after,) = (f for f in fences if f["id"] == gate["id"])
    lat, lon, radius = _circle(after)
    assert radius == 40.0 and _miss_m(lat, lon, moved) < 1.5 * m_per_px

    page.click_element(f"#geofences li[data-geofence-id='{gate['id']}'] button:last-child")  # delete
    page.wait("iotnav.geofences.length === 1")
    assert [f["name"] for f in httpx.get(svc.url("/api/geofences"), headers=auth(svc)).json()] == ["depot"]
    assert page.errors() == []


def test_device_names_are_shown_as_text(live) -> None:
    """A device's id is any text an OsmAnd client sends: it is shown, never run as markup."""
    svc, page = live
    name = "<img src=x onerror=window.__pwned=1>van-2"
    _osmand(svc, name, LAT0 + 0.0001, LON0 - 0.0002, time.time() - 5, 6.0)
    page.wait(_tooltip_box(name))
    assert page.eval("document.querySelectorAll('.leaflet-tooltip img, #devices img').length") == 0
    assert page.eval("window.__pwned === undefined")
    assert page.errors() == []


def test_page_settings_and_missing_files(monkeypatch) -> None:
    """The tile URL is checked and written into the page; without Leaflet ``GET /`` says what to run."""
    html = web.page_html("https://tiles.example.org/{z}/{x}/{y}.png", "© example </script>")
    cfg = json.loads(
        html.split('type="application/json">', 1)[1].split("</script>", 1)[0].replace("<\\/", "</")
    )
    assert cfg == {
        "tileUrl": "https://tiles.example.org/{z}/{x}/{y}.png",
        "tileAttribution": "© example </script>",
    }
    assert web.page_html().count("{z}") == 0 and '"tileUrl": ""' in web.page_html()
    with pytest.raises(ValueError, match=r"missing placeholder\(s\) \{y\}"):
        web.check_tile_url("https://tiles.example.org/{z}/{x}.png")
    with pytest.raises(ValueError, match="http"):
        web.check_tile_url("ftp://tiles.example.org/{z}/{x}/{y}.png")
    app = FastAPI()
    web.mount_web(app)
    client = TestClient(app)
    assert client.get("/").status_code == 200
    assert client.get("/web/vendor/leaflet/leaflet.js").status_code == 200
    monkeypatch.setattr(web, "VENDOR_PROBE", web.VENDOR_PROBE.with_name("absent.js"))
    r = client.get("/")
    assert r.status_code == 503 and "make setup" in r.text


def test_tiles_from_the_configured_url(live, tmp_path) -> None:
    """With a tile URL the page loads its tiles from there (a local tile server here) and shows
    the provider's credit instead of the grid. The API is the real one, in this process."""
    import io

    from iotnav.service import store
    from iotnav.service.app import _uvicorn_server, create_token
    from iotnav.service.http import api_app
    from iotnav.service.ingest import Ingestor

    _, page = live
    db = store.make_engine(store.sqlite_url(tmp_path))
    store.upgrade(db)
    token = create_token(db, "map test", "read")
    port = free_ports(1)[0]
    app = api_app(db, Ingestor(db, "none", True))
    web.mount_web(app, f"http://127.0.0.1:{port}/tiles/{{z}}/{{x}}/{{y}}.png", "tiles: test server")
    tile = io.BytesIO()
    Image.new("RGB", (256, 256), (200, 120, 220)).save(tile, format="PNG")
    asked: list[tuple[int, int, int]] = []

    @app.get("/tiles/{z}/{x}/{y}.png")
    def tiles(z: int, x: int, y: int) -> Response:
        asked.append((z, x, y))
        return Response(tile.getvalue(), media_type="image/png")

    server = _uvicorn_server(app, "127.0.0.1", port)
    th = threading.Thread(target=server.run, daemon=True)
    th.start()
    try:
        while not server.started:
            time.sleep(0.02)
        page.send("Page.navigate", url=f"http://127.0.0.1:{port}/#token={token}")
        page.wait("window.iotnav && iotnav.ready")
        n_tiles, _ = page.wait("document.querySelectorAll('.leaflet-tile-loaded').length")
        assert n_tiles >= 4 and len(asked) >= n_tiles and {z for z, _, _ in asked} == {2}
        assert page.eval("document.querySelector('.grid-label')") is None
        assert "tiles: test server" in page.eval(
            "document.querySelector('.leaflet-control-attribution').textContent"
        )
        # Leaflet fades each tile in over 0.2 s: the screenshot waits until every tile asked
        # for has loaded and is opaque (a tile caught mid-fade is a paler colour)
        page.wait(
            "Array.from(document.querySelectorAll('.leaflet-tile')).every("
            "t => t.classList.contains('leaflet-tile-loaded') && getComputedStyle(t).opacity === '1')"
        )
        im = page.screenshot(tmp_path / "map_tiles.png")
        assert colour_pixels(im, "#c878dc", tol=8) > 0.3 * im.shape[0] * im.shape[1]
        assert page.errors() == []
    finally:
        server.should_exit = True
        th.join(10)
        db.dispose()


def test_cli_serve_tile_url(tmp_path, monkeypatch) -> None:
    """``iotnav serve --tile-url`` reaches the service; a URL without placeholders is a clear error."""
    from typer.testing import CliRunner

    import iotnav.service.app as app_mod
    from iotnav.cli import app

    seen = []

    async def fake_serve(cfg) -> None:
        seen.append(cfg)

    monkeypatch.setattr(app_mod, "serve", fake_serve)
    url = "https://tile.example.org/{z}/{x}/{y}.png"
    r = CliRunner().invoke(app, ["serve", "--data", str(tmp_path), "--tile-url", url])
    assert r.exit_code == 0, r.output
    assert seen[0].tile_url == url
    r = CliRunner().invoke(
        app, ["serve", "--data", str(tmp_path), "--tile-url", "https://tile.example.org/a.png"]
    )
    assert r.exit_code == 2 and "missing placeholder" in r.output
