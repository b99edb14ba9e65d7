"""Alerts with ``iotnav serve`` on ``processes = 2`` (SQLite), over real sockets.

The Teltonika devices are stored by two worker processes (:mod:`iotnav.service.multiproc`);
the alerts are evaluated in the main process from what the workers committed
(:mod:`iotnav.service.alerts_delivery`, a tail of the rows by id). Four devices, two on each
worker, drive from 1 km outside a geofence to its centre: each must raise exactly one
``geofence_enter``, stored once in ``events`` and delivered once to a webhook receiver here.
"""

from __future__ import annotations

import json
import socket
import sqlite3
import struct
import time

import httpx
import pytest

from _service_helpers import Service, WebhookReceiver, codec8_packet, imei_frame, recv_exact
from iotnav.service.app import ServiceConfig
from iotnav.service.multiproc import worker_of

T0_MS = 1_700_000_000_000
DEPOT = (48.0, 16.0)
M_PER_DEG_LAT = 111_195.0  # mean Earth radius 6371.0088 km * pi / 180


def _drive(svc: Service, imei: str) -> None:
    """One fix 1 km north of the depot, then three at its centre, 60 s apart, each acknowledged."""
    lats = [DEPOT[0] + 1000.0 / M_PER_DEG_LAT] + [DEPOT[0]] * 3
    sock = socket.create_connection(("127.0.0.1", svc.tcp), timeout=10)
    try:
        sock.sendall(imei_frame(imei))
        assert recv_exact(sock, 1) == b"\x01"
        for i, lat in enumerate(lats):
            sock.sendall(codec8_packet([(T0_MS + 60_000 * i, lat, DEPOT[1], 0, 9)]))
            assert struct.unpack(">I", recv_exact(sock, 4))[0] == 1
            if i == 0:
                time.sleep(0.3)  # the outside fix is evaluated first: the zone state "outside"
    finally:
        sock.close()


def test_two_processes_raise_each_geofence_alert_once(tmp_path) -> None:
    imeis, k = [], 0
    while len(imeis) < 4:  # two devices on each worker
        imei = f"35620005{k:07d}"
        if sum(worker_of(m, [0, 1]) == worker_of(imei, [0, 1]) for m in imeis) < 2:
            imeis.append(imei)
        k += 1
    receiver = WebhookReceiver()
    alerts = tmp_path / "alerts.toml"
    alerts.write_text(
        "[alerts]\n"
        f'webhook_url = "{receiver.url}"\n'
        'webhook_secret = "s3cret-for-the-test"\n'
        "poll_interval_s = 0.05\n"
        "geofence_reload_s = 0.05\n"
        "[alerts.groups.default]\n"
        "geofences = true\n"
    )
    data = tmp_path / "data"
    svc = Service(data, processes=2, alerts=str(alerts)).start(timeout=180)
    try:
        token = (data / "admin_token").read_text().strip()
        r = httpx.post(
            f"http://127.0.0.1:{svc.api}/api/geofences",
            json={"name": "depot", "area": f"CIRCLE ({DEPOT[0]} {DEPOT[1]}, 100)"},
            headers={"Authorization": f"Bearer {token}"},
            timeout=10,
        )
        assert r.is_success, r.text
        time.sleep(0.3)  # the geofence is read by the alerts' poll
        for m in imeis:
            _drive(svc, m)
        t_end = time.monotonic() + 20
        while len(receiver.got) < len(imeis) and time.monotonic() < t_end:
            time.sleep(0.05)
        time.sleep(1.0)  # twenty more polls: a second alert of any device would arrive now
    finally:
        assert svc.stop() == 0
        receiver.server.shutdown()

    bodies = [json.loads(g[2]) for g in receiver.got]
    assert sorted(b["uniqueId"] for b in bodies) == sorted(imeis), bodies
    assert {b["kind"] for b in bodies} == {"geofence_enter"}
    assert {b["attributes"]["zone"] for b in bodies} == {"depot"}
    assert [g[3] for g in receiver.got] == [200] * len(imeis)
    assert len({g[1]["X-Iotnav-Delivery"] for g in receiver.got}) == len(imeis)
    for b in bodies:  # the alert's time is the device's first fix at the centre
        assert b["eventTime"] == "2023-11-14T22:14:20.000Z"
    con = sqlite3.connect(data / "iotnav.sqlite", timeout=10)
    rows = con.execute(
        "SELECT d.unique_id, e.id FROM events e JOIN devices d ON d.id = e.device_id "
        "WHERE e.type = 'alert_geofence_enter' ORDER BY d.unique_id"
    ).fetchall()
    con.close()
    assert rows == sorted((b["uniqueId"], b["id"]) for b in bodies)


def test_a_refused_alerts_file_ends_the_service_before_its_workers_start(tmp_path) -> None:
    """A setting refused at start (a webhook without its secret) exits the service with the
    reason; it must not leave worker processes behind that keep the service from exiting."""
    alerts = tmp_path / "alerts.toml"
    alerts.write_text('[alerts]\nwebhook_url = "http://127.0.0.1:9/hook"\n')
    t0 = time.monotonic()
    with pytest.raises(RuntimeError, match="needs webhook_secret"):
        Service(tmp_path / "data", processes=2, alerts=str(alerts)).start(timeout=120)
    assert time.monotonic() - t0 < 60


def test_processes_with_alerts_on_postgresql_are_refused() -> None:
    """On PostgreSQL the workers' ids are not committed in order: the tail could miss rows."""
    with pytest.raises(ValueError, match="needs SQLite"):
        ServiceConfig(db="postgresql://localhost/iotnav", processes=2, alerts={"webhook_url": "http://x/"})
    ServiceConfig(processes=2, alerts={"webhook_url": "http://127.0.0.1:9/hook"})  # SQLite: accepted
