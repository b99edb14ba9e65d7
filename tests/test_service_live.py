"""``iotnav serve`` over real sockets and a real SQLite file.

The module's service runs ``python -m iotnav.service CONFIG.toml`` in a subprocess (the
service of ``iotnav serve``, without loading the rest of the command line); the ACK-after-
commit and limit tests run the TCP listener in-process so they can hold the database thread;
the kill -9 test starts the service twice on one data directory (SQLite, then PostgreSQL).
``test_cli_serve_options`` checks the ``iotnav serve`` options reach the service.
"""

from __future__ import annotations

import asyncio
import contextlib
import socket
import sqlite3
import struct
import threading
import time
from concurrent.futures import ThreadPoolExecutor

import httpx
import pytest

from _service_helpers import FlakyIngestor, Postgres, Service, codec8_packet, imei_frame, recv_exact
from iotnav.service import store
from iotnav.service.ingest import Ingestor
from iotnav.service.teltonika_tcp import TcpLimits, TeltonikaServer

T0_MS = 1_700_000_000_000
WIKI_C8_3 = bytes.fromhex(
    "000000000000004308020000016B40D57B480100000000000000000000000000000001010101000000000000016B40"
    "D5C198010000000000000000000000000000000101010101000000020000252C"
)  # Teltonika wiki, Codec 8 example 3 (two records)


@pytest.fixture(scope="module")
def svc(tmp_path_factory):
    s = Service(
        tmp_path_factory.mktemp("serve") / "data", retention_days=36500
    ).start()  # purge runs, keeps all
    yield s
    assert s.stop() == 0  # SIGTERM: a clean exit


def _connect(svc: Service, imei: str) -> socket.socket:
    sock = socket.create_connection(("127.0.0.1", svc.tcp), timeout=10)
    sock.sendall(imei_frame(imei))
    assert recv_exact(sock, 1) == b"\x01"
    return sock


def _count(svc: Service, sql: str, *args: object) -> int:
    con = sqlite3.connect(svc.data / "iotnav.sqlite", timeout=10)
    try:
        return int(con.execute(sql, args).fetchone()[0])
    finally:
        con.close()


def test_teltonika_handshake_packet_ack_and_resend(svc: Service) -> None:
    sock = _connect(svc, "356307042441013")
    sock.sendall(WIKI_C8_3)
    assert recv_exact(sock, 4) == struct.pack(">I", 2)
    # acknowledged means committed: another connection to the file sees both records
    q = "SELECT count(*) FROM positions p JOIN devices d ON d.id = p.device_id WHERE d.unique_id = ?"
    assert _count(svc, q, "356307042441013") == 2
    sock.close()
    sock = _connect(svc, "356307042441013")  # the device resends (our ACK was lost): stored once
    sock.sendall(WIKI_C8_3)
    assert recv_exact(sock, 4) == struct.pack(">I", 2)
    assert _count(svc, q, "356307042441013") == 2
    assert _count(svc, "SELECT count(*) FROM raw_messages WHERE payload = ?", WIKI_C8_3) == 1
    sock.close()


@pytest.mark.parametrize(
    "garbage",
    [
        b"\x00\x0f35630704244101\xff",  # IMEI not digits
        imei_frame("356307042441014") + b"\x00\x00\x00\x00\x7f\xff\xff\xff",  # huge length field
        imei_frame("356307042441014") + WIKI_C8_3[:-1] + b"\x00",  # wrong CRC
        imei_frame("356307042441014") + b"\x01\x02\x03\x04" * 8,  # no preamble
    ],
)
def test_teltonika_bad_input_closes_without_ack_and_service_lives(svc: Service, garbage: bytes) -> None:
    sock = socket.create_connection(("127.0.0.1", svc.tcp), timeout=10)
    sock.sendall(garbage)
    got = b""
    while chunk := sock.recv(64):
        got += chunk
    assert got in (b"", b"\x00", b"\x01")  # at most the handshake answer, never an ACK
    sock.close()
    sock = _connect(svc, "356307042441015")  # still serving
    sock.sendall(codec8_packet([(T0_MS, 1.0, 2.0, 0, 5)]))
    assert recv_exact(sock, 4) == struct.pack(">I", 1)
    sock.close()


def test_osmand_get_and_json_then_api_positions(svc: Service) -> None:
    r = httpx.get(
        svc.url("/", svc.osmand),
        params={
            "id": "phone1",
            "lat": "48.1",
            "lon": "16.2",
            "timestamp": "1700000000",
            "speed": "10",
            "bearing": "90",
            "accuracy": "4.5",
            "altitude": "200",
        },
    )
    assert r.status_code == 200
    body = {
        "location": {
            "timestamp": "2023-11-14T22:13:21Z",
            "coords": {
                "latitude": 48.2,
                "longitude": 16.3,
                "accuracy": 3,
                "speed": 5.0,
                "heading": 180,
                "altitude": 210,
            },
        },
        "device_id": "phone1",
    }
    assert httpx.post(svc.url("/", svc.osmand), json=body).status_code == 200
    assert httpx.get(svc.url("/", svc.osmand), params={"lat": "1", "lon": "2"}).status_code == 400  # no id
    big = httpx.post(
        svc.url("/", svc.osmand), content=b"x" * 70000, headers={"Content-Type": "application/json"}
    )
    assert big.status_code == 413
    h = {"Authorization": f"Bearer {svc.admin_token}"}
    (dev,) = httpx.get(svc.url("/api/devices"), params={"uniqueId": "phone1"}, headers=h).json()
    pos = httpx.get(
        svc.url("/api/positions"),
        headers=h,
        params={"deviceId": dev["id"], "from": "2023-11-14T00:00:00Z", "to": "2023-11-15T00:00:00Z"},
    ).json()
    assert [p["fixTime"] for p in pos] == ["2023-11-14T22:13:20.000Z", "2023-11-14T22:13:21.000Z"]
    a, b = pos
    assert (a["latitude"], a["longitude"], a["altitude"], a["accuracy"]) == (48.1, 16.2, 200.0, 4.5)
    assert a["speed"] == pytest.approx(10.0) and a["course"] == pytest.approx(90.0)  # knots in, knots out
    assert b["speed"] == pytest.approx(5.0 * 3600 / 1852) and b["course"] == pytest.approx(180.0)  # m/s in
    assert a["attributes"]["engine"] == "none" and a["protocol"] == "osmand"
    window = {"deviceId": dev["id"], "from": "2023-11-14T00:00:00Z", "to": "2023-11-15T00:00:00Z"}
    gj = httpx.get(svc.url("/api/iotnav/track"), headers=h, params={**window, "format": "geojson"}).json()
    coords = [f["geometry"]["coordinates"] for f in gj["features"] if f["geometry"]["type"] == "LineString"]
    assert [c[:2] for c in coords[0]] == [[16.2, 48.1], [16.3, 48.2]]  # GeoJSON is lon, lat
    gpx = httpx.get(svc.url("/api/iotnav/track"), headers=h, params={**window, "format": "gpx"}).text
    assert gpx.count("<trkpt") == 2 and "2023-11-14T22:13:21" in gpx
    latest = httpx.get(svc.url("/api/positions"), headers=h, params={"deviceId": dev["id"]}).json()
    assert [p["fixTime"] for p in latest] == ["2023-11-14T22:13:21.000Z"]


def test_owntracks_http(svc: Service) -> None:
    msg = {"_type": "location", "lat": 48.85833, "lon": 2.29513, "tst": 1497476456, "tid": "JJ"}
    r = httpx.post(
        svc.url("/owntracks", svc.osmand), json=msg, headers={"X-Limit-U": "jane", "X-Limit-D": "phone"}
    )
    assert r.status_code == 200 and r.json() == []
    h = {"Authorization": f"Bearer {svc.admin_token}"}
    (dev,) = httpx.get(svc.url("/api/devices"), params={"uniqueId": "jane/phone"}, headers=h).json()
    (p,) = httpx.get(svc.url("/api/positions"), params={"deviceId": dev["id"]}, headers=h).json()
    assert (p["latitude"], p["longitude"], p["fixTime"]) == (48.85833, 2.29513, "2017-06-14T21:40:56.000Z")


def test_api_auth_devices_geofences_crud_and_openapi(svc: Service) -> None:
    assert httpx.get(svc.url("/api/devices")).status_code == 401
    assert httpx.get(svc.url("/api/devices"), headers={"Authorization": "Bearer wrong"}).status_code == 401
    from iotnav.service.app import create_token

    db = store.make_engine(store.sqlite_url(svc.data))
    read = create_token(db, "viewer", "read")
    db.dispose()
    admin, viewer = ({"Authorization": f"Bearer {t}"} for t in (svc.admin_token, read))
    assert httpx.get(svc.url("/api/devices"), headers=viewer).status_code == 200
    new = {"name": "truck 7", "uniqueId": "352093085698206"}
    assert httpx.post(svc.url("/api/devices"), json=new, headers=viewer).status_code == 403
    r = httpx.post(svc.url("/api/devices"), json=new, headers=admin)
    assert r.status_code == 200
    dev = r.json()
    assert (dev["name"], dev["uniqueId"]) == ("truck 7", "352093085698206")
    assert httpx.post(svc.url("/api/devices"), json=new, headers=admin).status_code == 400  # duplicate
    r = httpx.put(svc.url(f"/api/devices/{dev['id']}"), json={**dev, "name": "truck 8"}, headers=admin)
    assert r.status_code == 200 and r.json()["name"] == "truck 8"
    listed = httpx.get(svc.url("/api/devices"), params={"uniqueId": "352093085698206"}, headers=viewer).json()
    assert [d["name"] for d in listed] == ["truck 8"]
    assert httpx.delete(svc.url(f"/api/devices/{dev['id']}"), headers=admin).status_code == 204
    assert httpx.delete(svc.url(f"/api/devices/{dev['id']}"), headers=admin).status_code == 404
    g = {"name": "depot", "description": "yard", "area": "CIRCLE (48.2 16.37, 250)"}
    assert httpx.post(svc.url("/api/geofences"), json=g, headers=viewer).status_code == 403
    assert (
        httpx.post(svc.url("/api/geofences"), json={**g, "area": "CIRCLE (48 16)"}, headers=admin).status_code
        == 400
    )
    made = httpx.post(svc.url("/api/geofences"), json=g, headers=admin).json()
    assert (made["name"], made["description"], made["area"]) == ("depot", "yard", g["area"])
    moved = {**made, "area": "POLYGON ((48 16, 48.1 16, 48.1 16.1))"}
    assert (
        httpx.put(svc.url(f"/api/geofences/{made['id']}"), json=moved, headers=admin).json()["area"]
        == moved["area"]
    )
    assert [x["id"] for x in httpx.get(svc.url("/api/geofences"), headers=viewer).json()] == [made["id"]]
    assert httpx.delete(svc.url(f"/api/geofences/{made['id']}"), headers=admin).status_code == 204
    assert httpx.get(svc.url("/api/geofences"), headers=viewer).json() == []
    spec = httpx.get(svc.url("/openapi.json")).json()
    assert {"/api/devices", "/api/positions", "/api/devices/{device_id}", "/api/geofences"} <= set(
        spec["paths"]
    )


# --- ACK only after commit (in-process listener, held database thread) -----------------------


class _HeldIngestor(Ingestor):
    """Ingestor whose batches wait for ``release`` before storing (the database is slow)."""

    def __init__(self, *a, **k) -> None:
        super().__init__(*a, **k)
        self.release = threading.Event()
        self.entered = threading.Event()

    def ingest_batch(self, msgs):
        self.entered.set()
        assert self.release.wait(30)
        return super().ingest_batch(msgs)


@contextlib.contextmanager
def _listener(tmp_path, ingestor_cls=Ingestor, limits: TcpLimits | None = None):
    """A Teltonika listener on a background event loop; yields (port, ingestor, server)."""
    db = store.make_engine(store.sqlite_url(tmp_path))
    store.upgrade(db)
    ing = ingestor_cls(db, engine_name="none")
    loop = asyncio.new_event_loop()
    executor = ThreadPoolExecutor(max_workers=1)
    tcp = TeltonikaServer(ing, executor, limits or TcpLimits())
    server = loop.run_until_complete(tcp.start("127.0.0.1", 0))
    thread = threading.Thread(target=loop.run_forever, daemon=True)
    thread.start()

    async def shutdown() -> None:
        server.close()
        tasks = [t for t in asyncio.all_tasks() if t is not asyncio.current_task()]
        for t in tasks:
            t.cancel()
        await asyncio.gather(*tasks, return_exceptions=True)

    try:
        yield server.sockets[0].getsockname()[1], ing, tcp
    finally:
        asyncio.run_coroutine_threadsafe(shutdown(), loop).result(10)
        loop.call_soon_threadsafe(loop.stop)
        thread.join(10)
        loop.close()
        executor.shutdown()
        db.dispose()


def test_ack_is_sent_only_after_commit(tmp_path) -> None:
    with _listener(tmp_path, _HeldIngestor) as (port, ing, _):
        sock = socket.create_connection(("127.0.0.1", port), timeout=10)
        sock.sendall(imei_frame("356307042441013") + WIKI_C8_3)
        assert recv_exact(sock, 1) == b"\x01"
        assert ing.entered.wait(10)
        sock.settimeout(0.5)
        with pytest.raises(TimeoutError):
            sock.recv(4)  # storing has not finished: no ACK
        con = sqlite3.connect(tmp_path / "iotnav.sqlite")
        assert con.execute("SELECT count(*) FROM positions").fetchone() == (0,)
        ing.release.set()
        sock.settimeout(10)
        assert recv_exact(sock, 4) == struct.pack(">I", 2)
        assert con.execute("SELECT count(*) FROM positions").fetchone() == (2,)
        sock.close()


def test_database_outage_no_ack_then_the_resend_is_stored(tmp_path) -> None:
    with _listener(tmp_path, FlakyIngestor) as (port, ing, _):
        ing.down.set()
        sock = socket.create_connection(("127.0.0.1", port), timeout=10)
        sock.sendall(imei_frame("356307042441013") + WIKI_C8_3)
        assert recv_exact(sock, 1) == b"\x01"
        assert sock.recv(4) == b""  # closed without an ACK: the device keeps the records
        assert ing.counts["teltonika_errors"] == 1
        ing.down.clear()  # the database is back; the device resends
        sock = socket.create_connection(("127.0.0.1", port), timeout=10)
        sock.sendall(imei_frame("356307042441013") + WIKI_C8_3)
        assert recv_exact(sock, 5) == b"\x01" + struct.pack(">I", 2)
        con = sqlite3.connect(tmp_path / "iotnav.sqlite")
        assert con.execute("SELECT count(*) FROM positions").fetchone() == (2,)
        sock.close()


def _closed_within(sock: socket.socket, seconds: float) -> bool:
    sock.settimeout(seconds)
    try:
        while sock.recv(64):
            pass
    except TimeoutError:
        return False
    except ConnectionError:
        pass
    return True


def test_limits_slow_sender_idle_connection_and_connections_per_address(tmp_path) -> None:
    limits = TcpLimits(
        max_packet_bytes=1024, idle_timeout_s=0.5, packet_timeout_s=0.5, max_connections_per_address=2
    )
    with _listener(tmp_path, limits=limits) as (port, ing, tcp):
        # slowloris: a packet dripping one byte every 0.1 s never completes within 0.5 s
        slow = socket.create_connection(("127.0.0.1", port), timeout=5)
        slow.sendall(imei_frame("356307042441013"))
        assert recv_exact(slow, 1) == b"\x01"
        t0 = time.monotonic()
        with contextlib.suppress(OSError):
            for b in WIKI_C8_3:
                slow.sendall(bytes([b]))
                time.sleep(0.1)
        assert time.monotonic() - t0 < 0.1 * len(WIKI_C8_3)  # cut off before the end
        assert _closed_within(slow, 2.0)
        idle = socket.create_connection(("127.0.0.1", port), timeout=5)
        assert _closed_within(idle, 2.0)  # nothing sent: closed after the idle timeout
        big = socket.create_connection(("127.0.0.1", port), timeout=5)
        big.sendall(imei_frame("356307042441013") + b"\0\0\0\0" + struct.pack(">I", 2000))
        assert recv_exact(big, 1) == b"\x01" and _closed_within(big, 2.0)  # above max_packet_bytes
        held = [socket.create_connection(("127.0.0.1", port), timeout=5) for _ in range(2)]
        while sum(tcp.per_address.values()) < 2:
            time.sleep(0.01)
        third = socket.create_connection(("127.0.0.1", port), timeout=5)
        assert _closed_within(third, 1.0)  # a third connection from 127.0.0.1 is refused
        for s in held:
            s.close()
    counts = ing.counts
    assert counts["teltonika_rejected_too_many_connections"] == 1
    assert counts["teltonika_rejected_length"] == 1


def test_registration_closed_answers_00(tmp_path) -> None:
    db = store.make_engine(store.sqlite_url(tmp_path))
    store.upgrade(db)
    ing = Ingestor(db, engine_name="none", registration_open=False)

    async def main() -> tuple[bytes, bytes]:
        tcp = TeltonikaServer(ing, ThreadPoolExecutor(1))
        server = await tcp.start("127.0.0.1", 0)
        port = server.sockets[0].getsockname()[1]
        reader, writer = await asyncio.open_connection("127.0.0.1", port)
        writer.write(imei_frame("356307042441013"))
        answer = await reader.read(1)
        rest = await reader.read(10)  # then closed
        writer.close()
        await writer.wait_closed()
        while tcp.per_address:  # the handler has finished
            await asyncio.sleep(0.01)
        server.close()
        return answer, rest

    assert asyncio.run(main()) == (b"\x00", b"")
    db.dispose()


# --- kill -9 mid-stream --------------------------------------------------------------------


def _device(svc: Service, imei: str, packets: list[bytes], acked: list[int], stop: threading.Event) -> None:
    """A simulated tracker: sends its packets in order, each until acknowledged; reconnects."""
    i = 0
    while i < len(packets) and not stop.is_set():
        try:
            sock = socket.create_connection(("127.0.0.1", svc.tcp), timeout=5)
            sock.sendall(imei_frame(imei))
            if recv_exact(sock, 1) != b"\x01":
                raise ConnectionError("refused")
            while i < len(packets):
                sock.sendall(packets[i])
                n = struct.unpack(">I", recv_exact(sock, 4))[0]
                assert n == 3
                acked.append(i)
                i += 1
                time.sleep(0.02)  # a tracker paces its packets; the kill lands mid-stream
            sock.close()
        except (OSError, ConnectionError):
            time.sleep(0.1)  # the service is down: retry the same packet later


@pytest.fixture(scope="module")
def postgres():
    pg = Postgres().start()
    yield pg
    pg.stop()


@pytest.mark.parametrize("backend", ["sqlite", "postgresql"])
def test_kill9_mid_stream_loses_and_duplicates_nothing_acknowledged(tmp_path, request, backend: str) -> None:
    data = tmp_path / "data"
    url = store.sqlite_url(data) if backend == "sqlite" else request.getfixturevalue("postgres").url
    svc = Service(data, db=url if backend != "sqlite" else "").start()
    imeis = [f"35000000000{k:04d}" for k in range(4)]
    packets = {
        imei: [
            codec8_packet([(T0_MS + 1000 * (3 * j + r), 48 + k, 16.0, 30, 8) for r in range(3)])
            for j in range(15)
        ]
        for k, imei in enumerate(imeis)
    }
    acked: dict[str, list[int]] = {imei: [] for imei in imeis}
    stop = threading.Event()
    threads = [threading.Thread(target=_device, args=(svc, m, packets[m], acked[m], stop)) for m in imeis]
    for t in threads:
        t.start()
    t_end = time.monotonic() + 60
    while sum(map(len, acked.values())) < 12 and time.monotonic() < t_end:
        time.sleep(0.02)
    svc.kill9()  # mid-stream: devices are sending
    before = {m: len(a) for m, a in acked.items()}
    assert 12 <= sum(before.values()) < 60
    svc.start()
    for t in threads:
        t.join(90)
    stop.set()
    assert all(len(acked[m]) == 15 for m in imeis), {m: len(a) for m, a in acked.items()}
    db = store.make_engine(url)
    with db.connect() as con:
        for k, imei in enumerate(imeis):
            rows = con.exec_driver_sql(
                "SELECT p.fix_time, p.latitude FROM positions p JOIN devices d ON d.id = p.device_id "
                f"WHERE d.unique_id = '{imei}' AND p.engine = 'none' ORDER BY p.fix_time"
            ).all()
            assert [r[0] for r in rows] == [T0_MS / 1000 + i for i in range(45)], imei  # each exactly once
            assert {r[1] for r in rows} == {48.0 + k}
        q = "SELECT count(*), count(DISTINCT dedup_key) FROM raw_messages"
        assert tuple(con.exec_driver_sql(q).one()) == (60, 60)
    db.dispose()
    assert svc.stop() == 0


def test_cli_serve_options(tmp_path, monkeypatch) -> None:
    from typer.testing import CliRunner

    import iotnav.service.app as app_mod
    from iotnav.cli import app

    seen = []

    async def fake_serve(cfg) -> None:
        seen.append(cfg)

    monkeypatch.setattr(app_mod, "serve", fake_serve)
    toml = tmp_path / "serve.toml"
    toml.write_text('[serve]\napi_port = 9000\nengine = "none"\nidle_timeout_s = 30\n')
    args = [
        "serve",
        "--data",
        str(tmp_path / "d"),
        "--config",
        str(toml),
        "--teltonika-port",
        "6000",
        "--registration",
        "closed",
    ]
    r = CliRunner().invoke(app, args)
    assert r.exit_code == 0, r.output
    (cfg,) = seen
    assert (cfg.data, cfg.teltonika_port, cfg.osmand_port, cfg.api_port) == (
        str(tmp_path / "d"),
        6000,
        5055,
        9000,
    )
    assert (cfg.engine, cfg.idle_timeout_s, cfg.registration_open) == ("none", 30, False)
    toml.write_text("[serve]\napi_prot = 1\n")  # a typo is a clear error, exit code 2
    r = CliRunner().invoke(app, ["serve", "--config", str(toml)])
    assert r.exit_code == 2 and "api_prot" in r.output


def test_live_socket_pushes_positions_after_commit(svc: Service) -> None:
    import json

    from websockets.exceptions import ConnectionClosed
    from websockets.sync.client import connect

    ws_url = f"ws://127.0.0.1:{svc.api}/api/socket"
    with pytest.raises((ConnectionClosed, Exception)) as bad:  # wrong token: refused
        with connect(ws_url + "?token=wrong", open_timeout=10) as ws:
            ws.recv(timeout=5)
    assert "1008" in str(bad.value) or "403" in str(bad.value)
    with connect(
        ws_url, additional_headers={"Authorization": f"Bearer {svc.admin_token}"}, open_timeout=10
    ) as ws:
        time.sleep(0.2)
        q = {"id": "socket-phone", "lat": "47.5", "lon": "19.05", "timestamp": "1700000500", "speed": "2"}
        assert httpx.get(svc.url("/", svc.osmand), params=q).status_code == 200
        msg = json.loads(ws.recv(timeout=10))
    (p,) = msg["positions"]
    assert (p["latitude"], p["longitude"], p["fixTime"]) == (47.5, 19.05, "2023-11-14T22:21:40.000Z")
    assert p["speed"] == pytest.approx(2.0) and p["protocol"] == "osmand"


def test_pipelined_packets_in_one_segment_are_each_acknowledged_in_order(tmp_path) -> None:
    """The handshake and three packets (1, 2 and 3 records) in one TCP write: each packet is
    stored and acknowledged with its own record count, in order (the buffered bytes wait while
    the packet before them is stored)."""
    with _listener(tmp_path) as (port, _ing, _):
        packets = [
            codec8_packet([(T0_MS + 1000 * (2 * j + r), 48.0, 16.0, 30, 8) for r in range(j + 1)])
            for j in range(3)
        ]
        sock = socket.create_connection(("127.0.0.1", port), timeout=10)
        sock.sendall(imei_frame("356307042441013") + b"".join(packets))
        assert recv_exact(sock, 13) == b"\x01" + b"".join(struct.pack(">I", j + 1) for j in range(3))
        con = sqlite3.connect(tmp_path / "iotnav.sqlite")
        assert con.execute("SELECT count(*) FROM positions").fetchone() == (6,)
        sock.close()
