"""A real headless Chromium driven over its DevTools protocol, and a running ``iotnav serve`` beside
it: what the web map's browser tests (``tests/test_service_map*.py``) share.
"""

from __future__ import annotations

import base64
import contextlib
import functools
import itertools
import json
import subprocess
import tempfile
import threading
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import httpx
import numpy as np
from PIL import Image
from websockets.sync.client import connect

from _browser import chromium
from _service_helpers import Service
from iotnav.service import web

M_PER_DEG_LAT = 111_195.0  # mean Earth radius 6371.0088 km * pi / 180


class Page:
    """One Chromium tab driven over the DevTools protocol (a real browser, no mock)."""

    def __init__(self, exe: str, width: int = 1280, height: int = 800) -> None:
        self.profile = tempfile.TemporaryDirectory(prefix="iotnav-cdp-", ignore_cleanup_errors=True)
        self.proc = subprocess.Popen(
            [
                exe,
                "--headless",
                "--no-sandbox",
                "--disable-gpu",
                "--no-first-run",
                "--disable-background-networking",
                "--disable-component-update",
                "--disable-sync",
                "--remote-debugging-port=0",
                f"--user-data-dir={self.profile.name}",
                f"--window-size={width},{height}",
                "about:blank",
            ],
            stdout=subprocess.DEVNULL,
            stderr=subprocess.DEVNULL,
        )
        port_file = Path(self.profile.name) / "DevToolsActivePort"
        t_end = time.monotonic() + 30
        while not (port_file.exists() and len(port_file.read_text().split()) == 2):
            if time.monotonic() > t_end or self.proc.poll() is not None:
                raise RuntimeError("Chromium did not open its DevTools port")
            time.sleep(0.05)
        port = int(port_file.read_text().split()[0])
        targets = httpx.get(f"http://127.0.0.1:{port}/json/list", timeout=10).json()
        page = next(t for t in targets if t["type"] == "page")
        self.stack = contextlib.ExitStack()
        self.ws = self.stack.enter_context(
            connect(page["webSocketDebuggerUrl"], max_size=None, open_timeout=10)
        )
        self.ids = itertools.count(1)
        self.events: list[dict[str, Any]] = []
        for domain in ("Page", "Runtime", "Network", "Log"):
            self.send(f"{domain}.enable")

    def send(self, method: str, **params: Any) -> dict[str, Any]:
        """Call ``method``; its result (events seen meanwhile go to :attr:`events`)."""
        i = next(self.ids)
        self.ws.send(json.dumps({"id": i, "method": method, "params": params}))
        while True:
            msg = json.loads(self.ws.recv(timeout=30))
            if msg.get("id") == i:
                if "error" in msg:
                    raise RuntimeError(f"{method}: {msg['error']}")
                return dict(msg["result"])
            self.events.append(msg)

    def eval(self, expr: str) -> Any:
        """Value of the JavaScript ``expr`` in the page."""
        res = self.send("Runtime.evaluate", expression=expr, returnByValue=True, awaitPromise=True)
        if "exceptionDetails" in res:
            raise RuntimeError(f"{expr}: {res['exceptionDetails']}")
        return res["result"].get("value")

    def wait(self, expr: str, timeout: float = 10.0) -> tuple[Any, float]:
        """First truthy value of ``expr`` (polled every 10 ms) and how long it took, s."""
        t0 = time.monotonic()
        while True:
            v = self.eval(expr)
            if v:
                return v, time.monotonic() - t0
            if time.monotonic() - t0 > timeout:
                raise TimeoutError(f"{expr} still false after {timeout} s; page errors: {self.errors()}")
            time.sleep(0.01)

    def click(self, x: float, y: float, button: str = "left") -> None:
        """A mouse click (``button`` ``left`` or ``right``) at viewport pixel (x, y)."""
        for kind in ("mouseMoved", "mousePressed", "mouseReleased"):
            self.send("Input.dispatchMouseEvent", type=kind, x=x, y=y, button=button, clickCount=1)

    def drag(self, x0: float, y0: float, x1: float, y1: float, steps: int = 8) -> None:
        """Press the left button at (x0, y0), move in ``steps`` to (x1, y1), release there."""
        mouse = functools.partial(self.send, "Input.dispatchMouseEvent", button="left", clickCount=1)
        mouse(type="mouseMoved", x=x0, y=y0, buttons=0)
        mouse(type="mousePressed", x=x0, y=y0, buttons=1)
        for k in range(1, steps + 1):
            mouse(type="mouseMoved", x=x0 + (x1 - x0) * k / steps, y=y0 + (y1 - y0) * k / steps, buttons=1)
        mouse(type="mouseReleased", x=x1, y=y1, buttons=0)

    def centre_of(self, selector: str) -> tuple[float, float]:
        """Viewport pixel of the centre of the first element matching the CSS ``selector``."""
        x, y = self.eval(
            f"(function(){{var el=document.querySelector({json.dumps(selector)});"
            "el.scrollIntoView({block: 'nearest', inline: 'nearest'});"  # a sidebar grown past the window
            "var b=el.getBoundingClientRect();"
            "return [b.left + b.width / 2, b.top + b.height / 2];})()"
        )
        return float(x), float(y)

    def click_element(self, selector: str) -> None:
        """A left click at the centre of ``selector``, scrolled into view first; an error if
        something else (another element, or nothing: outside the window) is at that pixel."""
        x, y = self.centre_of(selector)
        hit = self.eval(
            f"(function(){{var el=document.querySelector({json.dumps(selector)}),"
            f"at=document.elementFromPoint({x}, {y});"
            "return at !== null && (at === el || el.contains(at));})()"
        )
        if not hit:
            raise RuntimeError(
                f"{selector} is not what is at pixel ({x:.0f}, {y:.0f}): the click would miss it"
            )
        self.click(x, y)

    def screenshot(self, path: Path) -> np.ndarray:
        path.write_bytes(base64.b64decode(self.send("Page.captureScreenshot", format="png")["data"]))
        return np.asarray(Image.open(path).convert("RGB"), dtype=np.int16)

    def errors(self) -> list[str]:
        """Uncaught exceptions and console errors the page raised so far."""
        out = []
        for e in self.events:
            if e.get("method") == "Runtime.exceptionThrown":
                out.append(str(e["params"]["exceptionDetails"]))
            elif e.get("method") == "Runtime.consoleAPICalled" and e["params"]["type"] == "error":
                out.append(str(e["params"]["args"]))
            elif e.get("method") == "Log.entryAdded" and e["params"]["entry"]["level"] == "error":
                out.append(e["params"]["entry"]["text"])
        return out

    def requested_urls(self) -> list[str]:
        return [
            e["params"]["request"]["url"]
            for e in self.events
            if e.get("method") == "Network.requestWillBeSent"
        ]

    def close(self) -> None:
        self.stack.close()
        self.proc.terminate()
        self.proc.wait(10)
        self.profile.cleanup()


def _start(svc: Service) -> Service | BaseException:
    try:
        return svc.start()
    except BaseException as exc:  # re-raised in the caller's thread
        return exc


@contextlib.contextmanager
def service_and_page(svc: Service) -> Iterator[tuple[Service, Page]]:
    """``svc`` started and a Chromium tab, both at once; both stopped at the end.

    Fails (not skips) when Chromium or the Leaflet files (``make setup``: ``npm ci``) are
    missing: the web map is a shipped feature.
    """
    exe = chromium()
    assert exe is not None, "chromium is not installed (apt-get install chromium)"
    assert web.VENDOR_PROBE.exists(), f"{web.VENDOR_PROBE} missing: run make setup (npm ci)"
    started: list[Service | BaseException] = []
    # the service (Python imports, migrations) and Chromium start at the same time
    th = threading.Thread(target=lambda: started.append(_start(svc)))
    th.start()
    page = Page(exe)
    th.join()
    if isinstance(started[0], BaseException):
        page.close()
        raise started[0]
    try:
        yield svc, page
    finally:  # both stop at the same time too
        closing = threading.Thread(target=page.close)
        closing.start()
        code = svc.stop()
        closing.join()
        assert code == 0


def osmand(
    client: httpx.Client, svc: Service, uid: str, lat: float, lon: float, t: float, acc: float, **extra: float
) -> None:
    """One OsmAnd fix (``extra``: more query fields, e.g. ``speed`` knots, ``bearing`` degrees), acknowledged."""
    q = {"id": uid, "lat": f"{lat:.7f}", "lon": f"{lon:.7f}", "timestamp": f"{t:.3f}", "accuracy": str(acc)}
    q.update({k: str(v) for k, v in extra.items()})
    r = client.get(svc.url("/", svc.osmand), params=q)
    assert r.status_code == 200, r.text


def auth(svc: Service) -> dict[str, str]:
    return {"Authorization": f"Bearer {svc.admin_token}"}


M_PER_PX = (
    "(function(){var m=iotnav.map,c=m.getSize().divideBy(2);"
    "return m.distance(m.containerPointToLatLng(c), m.containerPointToLatLng(c.add([100,0])))/100;})()"
)  # JS: metres per screen pixel at the map's centre


def colour_pixels(im: np.ndarray, hex_colour: str, tol: int = 40) -> int:
    """Pixels of ``im`` within ``tol`` of ``hex_colour`` in every channel."""
    rgb = np.array([int(hex_colour[i : i + 2], 16) for i in (1, 3, 5)], dtype=np.int16)
    return int((np.abs(im - rgb).max(axis=2) < tol).sum())
