"""The live map page of ``iotnav serve``: ``GET /`` on the API port, its files under ``/web/``.

The page (``static/index.html``, ``map.js``, ``map.css``) draws with Leaflet, whose files are not in
git: ``make setup`` runs ``npm ci`` (``package.json`` / ``package-lock.json`` at the repository
root pin the version) and copies ``node_modules/leaflet/dist`` with its LICENSE into
``static/vendor/leaflet/`` here, so the wheel and an editable install carry them and the browser fetches
nothing from a CDN. The page reads everything through the API (``/api/devices``,
``/api/positions``, ``/api/geofences``, ``/api/reports/trips|stops|events``, the
``/api/socket`` WebSocket with positions and alerts) with the bearer token
given once in the address (``/#token=...``; the fragment never reaches the server or its logs).

Tiles come from ``tile_url`` (``[serve] tile_url``, ``iotnav serve --tile-url``), a
``{z}/{x}/{y}`` template as Leaflet takes it; with none the page draws on a plain metric grid with
a scale bar (the offline default).
"""

from __future__ import annotations

import json
import re
from pathlib import Path

from fastapi import FastAPI
from fastapi.responses import HTMLResponse, PlainTextResponse, Response
from fastapi.staticfiles import StaticFiles

WEB_DIR = Path(__file__).parent / "static"
#: The Leaflet file whose absence means ``make setup`` (``npm ci``) has not run.
VENDOR_PROBE = WEB_DIR / "vendor" / "leaflet" / "leaflet.js"
CONFIG_MARK = "/*IOTNAV_CONFIG*/{}"

_PLACEHOLDER = re.compile(r"\{[zxy]\}")


def check_tile_url(url: str) -> str:
    """``url`` when it is empty or an ``http(s)`` template with ``{z}``, ``{x}`` and ``{y}``.

    Raises
    ------
    ValueError
        Naming what is missing.
    """
    if not url:
        return url
    if not re.match(r"^https?://", url):
        raise ValueError(f"tile_url {url!r}: expected an http:// or https:// address")
    missing = sorted({"{z}", "{x}", "{y}"} - set(_PLACEHOLDER.findall(url)))
    if missing:
        raise ValueError(f"tile_url {url!r}: missing placeholder(s) {', '.join(missing)}")
    return url


def page_html(tile_url: str = "", tile_attribution: str = "") -> str:
    """``index.html`` with the page's settings (tile URL, attribution) written into it."""
    settings = json.dumps({"tileUrl": check_tile_url(tile_url), "tileAttribution": tile_attribution})
    # inside <script>: "</" would end the element, so it is escaped
    return (
        (WEB_DIR / "index.html")
        .read_text(encoding="utf-8")
        .replace(CONFIG_MARK, settings.replace("</", "<\\/"))
    )


def mount_web(app: FastAPI, tile_url: str = "", tile_attribution: str = "") -> None:
    """Add ``GET /`` (the page) and ``/web/`` (its files) to the API ``app``.

    Without the Leaflet files (``make setup`` not run) ``GET /`` answers 503 saying so; the
    API is unaffected.
    """
    html = page_html(tile_url, tile_attribution)
    app.mount("/web", StaticFiles(directory=WEB_DIR), name="web")

    @app.get("/", include_in_schema=False)
    def map_page() -> Response:
        if not VENDOR_PROBE.exists():
            return PlainTextResponse(
                f"the map's browser files are missing ({VENDOR_PROBE}): run `make setup` "
                "(npm ci copies Leaflet into the package)",
                status_code=503,
            )
        return HTMLResponse(html, headers={"Cache-Control": "no-store"})


__all__ = ["check_tile_url", "mount_web", "page_html"]
