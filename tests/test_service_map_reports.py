"""The web map's trips, stops, event timeline and polygon geofences, in a real headless Chromium
against a real running ``iotnav serve`` (alerts on, engine ``none``: the clean positions are the
fixes as sent; see ``test_service_map.py`` for why).

A person draws a polygon around a car park with the mouse (four clicks, one corner dragged
into place), saves it, reloads the page (it is still there, from the API), edits it (a corner
added on a side, removed by right-click, added again). A truck then reports a scripted
drive-park-drive over OsmAnd HTTP: 400 s east at 10 m/s, 600 s parked in the polygon, 400 s
north at 10 m/s, a fix every 40 s driving and 60 s parked (accuracy 5 m). The person shows the truck's period: two trips
and a stop are listed and drawn, the polygon's enter and exit alerts are on the timeline, and a
click on the exit centres the map where it happened. The expected times and places come from
the script (the fence margin is 3 sigmas normal to the border: 10.6 m at accuracy 5 m, well
inside the 150 m or more between the fixes and the border). Screenshots go to the tests' tmp folders
(``map_polygon*.png``, ``map_trips.png``, ``map_stop.png``, ``map_event.png``). The tests run in file order on one page.
"""

from __future__ import annotations

import json
import math
import time
from collections.abc import Iterator
from datetime import UTC, datetime
from typing import Any

import httpx
import numpy as np
import pytest

from _map_page import M_PER_DEG_LAT, M_PER_PX, Page, auth, colour_pixels, osmand, service_and_page
from _service_helpers import Service

LAT0, LON0 = 47.0707, 15.4395  # Graz: the truck's start
M_PER_DEG_LON = M_PER_DEG_LAT * math.cos(math.radians(LAT0))
PARK_E = 4000.0  # m east of the start: the car park
HALF = 150.0  # m: half the side of the square drawn around it
DRIVE_DT, PARK_DT, V_MPS, ACC_M = 40.0, 60.0, 10.0, 5.0  # s between fixes driving / parked
NAME = "yard <img src=x onerror=window.__pwned=1>"  # a geofence name is any text
FENCE = "#2a9d3a"


def _ll(north_m: float, east_m: float) -> tuple[float, float]:
    """Latitude, longitude (degrees) ``north_m``, ``east_m`` from the start (flat Earth, < 5 km)."""
    return LAT0 + north_m / M_PER_DEG_LAT, LON0 + east_m / M_PER_DEG_LON


def _ne(lat: float, lon: float) -> tuple[float, float]:
    return (lat - LAT0) * M_PER_DEG_LAT, (lon - LON0) * M_PER_DEG_LON


def _script() -> list[tuple[float, float, float, float, float]]:
    """``(t_s, north_m, east_m, speed_mps, bearing_deg)`` of the drive-park-drive, t from its start."""
    rng = np.random.default_rng(19)
    times = [
        *np.arange(0.0, 400.1, DRIVE_DT),
        *np.arange(460.0, 1000.1, PARK_DT),
        *np.arange(1040.0, 1400.1, DRIVE_DT),
    ]
    out = []
    for t in map(float, times):
        if t <= 400.0:
            out.append((t, 0.0, V_MPS * t, V_MPS if t < 400 else 0.0, 90.0))
        elif t <= 1000.0:
            n, e = rng.normal(0.0, 2.0, 2)
            out.append((t, float(n), PARK_E + float(e), 0.0, 0.0))
        else:
            out.append((t, V_MPS * (t - 1000.0), PARK_E, V_MPS, 0.0))
    return out


T_ENTER, T_EXIT = 400.0, 1040.0  # the first fixes beyond the margin: 150 m inside, 250 m outside
_RUN: dict[str, Any] = {}  # what the drive test leaves for the next one: its start time, the device


@pytest.fixture(scope="module")
def live(tmp_path_factory) -> Iterator[tuple[Service, Page]]:
    root = tmp_path_factory.mktemp("map_reports")
    alerts = root / "alerts.toml"
    alerts.write_text(
        "[alerts]\npoll_interval_s = 0.2\ngeofence_reload_s = 0.2\n[alerts.groups.default]\ngeofences = true\n"
    )
    with service_and_page(Service(root / "data", alerts=str(alerts))) as both:
        yield both


def _view(page: Page, lat: float, lon: float, zoom: int) -> float:
    """The person brings the map to (lat, lon) at ``zoom``; metres per pixel there."""
    page.eval(f"iotnav.map.setView([{lat}, {lon}], {zoom}, {{animate: false}}); null")
    page.wait("!iotnav.moving")
    return float(page.eval(M_PER_PX))


def _px(page: Page, north_m: float, east_m: float) -> tuple[float, float]:
    p = page.eval(f"iotnav.toPixel({_ll(north_m, east_m)[0]}, {_ll(north_m, east_m)[1]})")
    return float(p["x"]), float(p["y"])


def _polygon(fence: dict[str, Any]) -> list[tuple[float, float]]:
    """The (north, east) corners, m, of a stored ``POLYGON ((lat lon, ...))``, closing point included."""
    body = fence["area"].removeprefix("POLYGON ((").removesuffix("))")
    return [_ne(*map(float, p.split())) for p in body.split(",")]


def _fences(svc: Service) -> list[dict[str, Any]]:
    r = httpx.get(svc.url("/api/geofences"), headers=auth(svc))
    assert r.status_code == 200, r.text
    return list(r.json())


def test_polygon_drawn_dragged_saved_reloaded_and_edited(live, tmp_path) -> None:
    svc, page = live
    page.send("Page.navigate", url=svc.url(f"/#token={svc.admin_token}"))
    page.wait("window.iotnav && iotnav.ready && iotnav.socketOpen")
    m_per_px = _view(page, *_ll(0.0, PARK_E), 16)
    square = [(-HALF, PARK_E - HALF), (-HALF, PARK_E + HALF), (HALF, PARK_E + HALF), (HALF, PARK_E - HALF)]
    page.eval(f"document.getElementById('gf-name').value = {json.dumps(NAME)}")
    page.click_element("#gf-draw")
    assert page.eval("iotnav.polygon !== null && document.getElementById('gf-poly-actions').hidden") is False
    wrong = (HALF - 60.0, PARK_E + HALF - 40.0)  # the third corner clicked off its place...
    for n, e in [square[0], square[1], wrong, square[3]]:
        page.click(*_px(page, n, e))
    page.wait("iotnav.polygon.points.length === 4")
    page.drag(*_px(page, *wrong), *_px(page, *square[2]))  # ...and dragged to it
    page.wait("document.querySelectorAll('.corner').length === 4")
    page.screenshot(tmp_path / "map_polygon_drawn.png")
    page.click_element("#gf-save")
    page.wait("iotnav.geofences.length === 1 && iotnav.polygon === null")
    (fence,) = _fences(svc)
    assert fence["name"] == NAME and fence["area"].startswith("POLYGON ((")
    got = _polygon(fence)
    assert len(got) == 5 and got[0] == got[-1]  # the ring, closed
    for (n, e), (tn, te) in zip(got[:4], square, strict=True):
        assert math.hypot(n - tn, e - te) < 1.5 * m_per_px  # within a pixel or so of the aim

    # after a reload the polygon comes back from the API, drawn, with its name as text
    page.eval("window.__old = true")
    page.send("Page.reload")
    page.wait("!window.__old && window.iotnav && iotnav.ready && !iotnav.moving")
    assert page.eval("iotnav.geofences.map(function (g) { return g.area; })") == [fence["area"]]
    assert page.eval("document.querySelectorAll('.leaflet-fences-pane path').length") == 1
    labels = page.eval(
        "Array.prototype.map.call(document.querySelectorAll('.leaflet-tooltip'), e => e.textContent)"
    )
    assert labels == [NAME]
    m_per_px = float(page.eval(M_PER_PX))
    im = page.screenshot(tmp_path / "map_polygon_reloaded.png")
    n_fence = colour_pixels(im, FENCE)
    print(f"polygon outline {n_fence} px at {m_per_px:.2f} m/px")
    assert n_fence > 0.8 * 8 * HALF / m_per_px  # the 2 px outline along the whole perimeter, at least

    # edit: a click beside the south side adds a corner on it, a right-click removes it, again
    page.click_element(f"#geofences li[data-geofence-id='{fence['id']}'] button")
    page.wait("iotnav.polygon && iotnav.polygon.points.length === 4")
    edited_outline = "document.querySelectorAll('.leaflet-fences-pane path').length"
    assert page.eval(edited_outline) == 0  # its outline gave way to the editable one
    south = (-HALF - 50.0, PARK_E)
    page.click(*_px(page, *south))
    page.wait("iotnav.polygon.points.length === 5")
    page.click(*_px(page, *south), button="right")  # on the new corner
    page.wait("iotnav.polygon.points.length === 4")
    page.click(*_px(page, *south))
    page.wait("iotnav.polygon.points.length === 5")
    page.click_element("#gf-save")
    page.wait("iotnav.polygon === null && iotnav.geofences[0].area.split(',').length === 6")
    (edited,) = _fences(svc)
    assert edited["id"] == fence["id"] and edited["name"] == NAME
    got = _polygon(edited)
    want = [square[0], south, *square[1:]]  # inserted between the two southern corners
    assert len(got) == 6
    for (n, e), (tn, te) in zip(got[:5], want, strict=True):
        assert math.hypot(n - tn, e - te) < 1.5 * m_per_px
    assert page.eval("document.querySelectorAll('#geofences img, .leaflet-tooltip img').length") == 0
    assert page.eval("window.__pwned === undefined") and page.errors() == []
    # the API refuses a ring that encloses nothing (two corners, closed), saying why
    flat = {"name": "flat", "area": "POLYGON ((47 15, 47.1 15, 47 15))"}
    r = httpx.post(svc.url("/api/geofences"), json=flat, headers=auth(svc))
    assert r.status_code == 400 and "2 distinct corners" in r.text


_CENTRE = "(function(){var c=iotnav.map.getCenter();return [c.lat,c.lng];})()"  # JS: the map's centre


def _iso(t: float) -> str:
    return datetime.fromtimestamp(t, UTC).isoformat(timespec="seconds").replace("+00:00", "")


def test_drive_park_drive_trips_stop_and_geofence_events(live, tmp_path) -> None:
    svc, page = live
    t0 = float(math.floor(time.time())) - 1600.0  # the drive ended 200 s ago
    fixes = _script()
    t_post = time.monotonic()
    with httpx.Client(timeout=10) as http:
        for t, n, e, v, crs in fixes:
            osmand(http, svc, "truck-9", *_ll(n, e), t0 + t, ACC_M, speed=v / 0.514444, bearing=crs)
    t_post = time.monotonic() - t_post
    (dev,) = httpx.get(svc.url("/api/devices"), params={"uniqueId": "truck-9"}, headers=auth(svc)).json()
    period = {"deviceId": dev["id"], "from": _iso(t0 - 60) + "Z", "to": _iso(t0 + 1500) + "Z"}
    t_wait = time.monotonic()
    while True:  # the alert rules run on the committed rows, every 0.2 s
        evs = httpx.get(svc.url("/api/reports/events"), params=period, headers=auth(svc)).json()
        if len(evs) >= 2 or time.monotonic() - t_wait > 5:
            break
        time.sleep(0.05)
    print(
        f"{len(fixes)} fixes posted in {t_post:.2f} s; alerts stored {time.monotonic() - t_wait:.2f} s later"
    )

    # the person picks the truck and the period (UTC) and presses Show
    page.eval(
        f"document.getElementById('track-device').value = '{dev['id']}';"
        f"document.getElementById('track-from').value = '{_iso(t0 - 60)}';"
        f"document.getElementById('track-to').value = '{_iso(t0 + 1500)}'"
    )
    page.click_element("#track-form button")
    page.wait("iotnav.report && iotnav.track && !iotnav.moving")
    report = page.eval("iotnav.report")
    trips, stops, events = report["trips"], report["stops"], report["events"]

    # what the script did: two trips of 4 km, a 10 min stop at the car park, in and out of the yard
    def at(iso: str) -> float:
        return datetime.fromisoformat(iso.replace("Z", "+00:00")).timestamp() - t0

    assert len(trips) == 2 and len(stops) == 1, (trips, stops)
    for trip, (a, b) in zip(trips, [(0.0, 400.0), (1000.0, 1400.0)], strict=True):
        assert abs(at(trip["startTime"]) - a) <= DRIVE_DT and abs(at(trip["endTime"]) - b) <= DRIVE_DT
        # a boundary may fall on the next fix (the second trip starts with its first moving fix)
        assert abs(trip["distance"] - 4000.0) <= V_MPS * DRIVE_DT + 20.0
    (stop,) = stops
    assert abs(at(stop["startTime"]) - 400.0) <= DRIVE_DT and abs(at(stop["endTime"]) - 1000.0) <= DRIVE_DT
    n, e = _ne(stop["latitude"], stop["longitude"])
    assert math.hypot(n, e - PARK_E) < 3.0  # the median of 10 fixes of 2 m noise per axis
    kinds = [(ev["type"], at(ev["eventTime"])) for ev in events]
    assert kinds == [("alert_geofence_enter", T_ENTER), ("alert_geofence_exit", T_EXIT)]

    # ... and what the page shows of it: the list, in time order, with the report's figures
    items = page.eval(
        "Array.prototype.map.call(document.querySelectorAll('#segments li'), e => [e.className, e.textContent])"
    )
    assert [c for c, _ in items] == ["trip", "stop", "trip"]
    assert f"{trips[0]['distance'] / 1000:.2f} km" in items[0][1]
    assert items[1][1].startswith("Stop " + stop["startTime"].replace("T", " ").replace(".000Z", "Z"))
    assert f"{stop['duration'] // 60000} min" in items[1][1]
    # the map: the stop's marker on the stop, a start and an end marker per trip, one per event
    sx, sy = page.centre_of(".stop-icon")
    px = page.eval(f"iotnav.toPixel({stop['latitude']}, {stop['longitude']})")
    assert math.hypot(sx - px["x"], sy - px["y"]) < 1.5
    assert page.eval("document.querySelectorAll('.leaflet-marks-pane path').length") == 2 * 2 + 2
    # the timeline: two trip bars, a stop bar, the two events with their times and zone, as text
    assert page.eval("document.querySelectorAll('.tl-seg.trip').length") == 2
    assert page.eval("document.querySelectorAll('.tl-seg.stop').length") == 1
    labels = page.eval("Array.prototype.map.call(document.querySelectorAll('.tl-event'), e => e.textContent)")
    clock = [datetime.fromtimestamp(t0 + t, UTC).strftime("%H:%M:%S") for t in (T_ENTER, T_EXIT)]
    assert labels == [f"{clock[0]} entered {NAME}", f"{clock[1]} left {NAME}"]
    page.screenshot(tmp_path / "map_trips.png")
    page.click_element("#segments li.stop")  # the stop in the list: the map goes to it
    page.wait("!iotnav.moving")
    assert page.eval("iotnav.map.getZoom()") >= 17
    m_per_px = float(page.eval(M_PER_PX))
    assert math.hypot(*np.subtract(_ne(*page.eval(_CENTRE)), (n, e))) < 1.5 * m_per_px
    # there, the clean positions' uncertainty circles (radius: the accuracy, 5 m), one per fix
    widths = page.eval(
        "(function(){var m=document.getElementById('map').getBoundingClientRect();"
        "return Array.prototype.slice.call(document.querySelectorAll('.leaflet-clean-pane path'))"
        ".map(e => e.getBoundingClientRect()).filter(b => b.width > 0 && b.width < 100 && b.left > m.left"
        " && b.right < m.right && b.top > m.top && b.bottom < m.bottom).map(b => b.width);})()"
    )
    n_paths = page.eval("document.querySelectorAll('.leaflet-clean-pane path').length")
    assert n_paths == len(fixes) + 1  # and the line
    assert len(widths) >= 10 and all(w == pytest.approx(2 * ACC_M / m_per_px, abs=2.0) for w in widths), (
        widths
    )
    page.screenshot(tmp_path / "map_stop.png")
    assert page.errors() == [] and page.eval("iotnav.errors") == []
    _RUN.update(t0=t0, events=events)


def test_event_click_centres_the_map_and_live_alerts_join_the_timeline(live, tmp_path) -> None:
    svc, page = live
    t0, events = _RUN["t0"], _RUN["events"]
    # a click on the exit centres the map on it
    exit_ev = events[1]
    page.click_element(f".tl-event[data-event-id='{exit_ev['id']}']")
    page.wait("iotnav.selectedEvent && !iotnav.moving")
    assert page.eval("iotnav.selectedEvent.id") == exit_ev["id"]
    m_per_px = float(page.eval(M_PER_PX))
    n, e = _ne(*page.eval(_CENTRE))
    assert page.eval("iotnav.map.getZoom()") >= 17
    assert math.hypot(n - V_MPS * (T_EXIT - 1000.0), e - PARK_E) < 1.5 * m_per_px  # the fix that left
    page.screenshot(tmp_path / "map_event.png")

    # live: a click on the truck follows it (the last hour); its next alert joins the timeline
    page.click_element("#devices li")
    page.wait("iotnav.track.live && iotnav.report && document.querySelectorAll('.tl-event').length === 2")
    with httpx.Client(timeout=10) as http:  # back into the yard (no engine: nothing rejects a jump)
        osmand(http, svc, "truck-9", *_ll(0.0, PARK_E), t0 + 1420.0, ACC_M, speed=0.0, bearing=0.0)
    label, dt = page.wait(
        "(function(){var e=document.querySelectorAll('.tl-event');return e.length === 3 && e[2].textContent;})()"
    )
    clock = datetime.fromtimestamp(t0 + 1420.0, UTC).strftime("%H:%M:%S")
    assert label == f"{clock} entered {NAME}"
    print(f"live alert on the timeline {dt:.2f} s after the fix was acknowledged")
    assert (
        page.eval("document.querySelectorAll('#timeline img, .leaflet-tooltip img, #segments img').length")
        == 0
    )
    assert page.eval("window.__pwned === undefined")
    assert page.errors() == [] and page.eval("iotnav.errors") == []
