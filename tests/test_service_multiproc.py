"""``iotnav serve`` with ``processes = 2`` over real sockets and a real SQLite file.

The service runs in a subprocess (``python -m iotnav.service CONFIG.toml``); its Teltonika
connections are handed to two worker processes by IMEI (:mod:`iotnav.service.multiproc`).
Which process serves a device is read from the kernel, not from the service: the server side
of the device's TCP connection (``/proc/net/tcp``) and the process holding that socket
(``/proc/PID/fd``).
"""

from __future__ import annotations

import os
import socket
import sqlite3
import struct
import threading
import time
from pathlib import Path

from _service_helpers import Service, codec8_packet, imei_frame, recv_exact
from iotnav.service import checkpoint, store
from iotnav.service.ingest import Ingestor
from iotnav.service.multiproc import worker_of
from iotnav.service.protocols.teltonika import decode_avl

T0_MS = 1_700_000_000_000
N_PACKETS = 24


def _children(pid: int) -> list[int]:
    out: list[int] = []
    for task in Path(f"/proc/{pid}/task").iterdir():
        out += [int(c) for c in (task / "children").read_text().split()]
    return out


def _owner(server_port: int, client_port: int, pids: list[int]) -> int | None:
    """The process among ``pids`` holding the server side of the connection from ``client_port``."""
    inode = None
    for line in Path("/proc/net/tcp").read_text().splitlines()[1:]:
        f = line.split()
        if int(f[1].split(":")[1], 16) == server_port and int(f[2].split(":")[1], 16) == client_port:
            inode = f[9]
    if inode is None:
        return None
    for pid in pids:
        with_fds = Path(f"/proc/{pid}/fd")
        for fd in with_fds.iterdir():
            try:
                if os.readlink(fd) == f"socket:[{inode}]":
                    return pid
            except OSError:
                continue
    return None


def _packets(k: int) -> list[bytes]:
    """Device ``k``: one record per packet, 1 Hz, driving north at 10 m/s."""
    return [
        codec8_packet([(T0_MS + 1000 * i, 48.0 + k * 0.01 + 10.0 * i / 111_200.0, 16.37, 36, 9)])
        for i in range(N_PACKETS)
    ]


def _device(
    svc: Service,
    imei: str,
    packets: list[bytes],
    acked: list[int],
    owners: list[int | None],
    pids: list[int],
    stop: threading.Event,
) -> None:
    """A tracker: each packet until acknowledged; reconnects; the serving process of each connection."""
    i = 0
    while i < len(packets) and not stop.is_set():
        try:
            sock = socket.create_connection(("127.0.0.1", svc.tcp), timeout=10)
            sock.sendall(imei_frame(imei))
            if recv_exact(sock, 1) != b"\x01":
                raise ConnectionError("refused")
            owners.append(_owner(svc.tcp, sock.getsockname()[1], [*pids, svc.proc.pid]))  # type: ignore[union-attr]
            while i < len(packets):
                sock.sendall(packets[i])
                assert struct.unpack(">I", recv_exact(sock, 4))[0] == 1
                acked.append(i)
                i += 1
                time.sleep(0.03)
            sock.close()
        except (OSError, ConnectionError):
            time.sleep(0.1)  # the connection dropped: reconnect, resend the same packet


def _track(url: str, imei: str, engine: str) -> list[tuple]:
    db = store.make_engine(url)
    with db.connect() as conn:
        rows = conn.exec_driver_sql(
            "SELECT fix_time, latitude, longitude, speed_mps, course_rad, accuracy_m, p.attributes "
            "FROM positions p JOIN devices d ON d.id = p.device_id "
            f"WHERE engine = '{engine}' AND d.unique_id = '{imei}' ORDER BY p.id"
        ).all()
    db.dispose()
    return [tuple(r) for r in rows]


def test_two_processes_split_the_devices_and_a_killed_worker_loses_nothing(tmp_path) -> None:
    """6 devices over real TCP on ``processes = 2``: they are served by both workers (never by
    the main process); worker A is killed with SIGKILL mid-stream; its devices reconnect and are
    served by the other worker; every acknowledged record is stored exactly once, in order;
    the clean track of every device (the ``fixes`` engine, its state rebuilt from the checkpoint
    and the stored fixes on the other worker) equals an uninterrupted in-process run of the same
    packets; SIGTERM stops the service cleanly with every device's checkpoint written."""
    # IMEIs chosen so that both workers get devices (3 each) when both are live
    imeis, k = [], 0
    while len(imeis) < 6:
        imei = f"35620004{k:07d}"
        if sum(worker_of(m, [0, 1]) == worker_of(imei, [0, 1]) for m in imeis) < 3:
            imeis.append(imei)
        k += 1
    data = tmp_path / "data"
    svc = Service(data, engine="fixes", processes=2, checkpoint_interval_s=0.3).start(timeout=180)
    assert svc.proc is not None
    pids = _children(svc.proc.pid)
    packets = {m: _packets(j) for j, m in enumerate(imeis)}
    acked: dict[str, list[int]] = {m: [] for m in imeis}
    owners: dict[str, list[int | None]] = {m: [] for m in imeis}
    stop = threading.Event()
    threads = [
        threading.Thread(target=_device, args=(svc, m, packets[m], acked[m], owners[m], pids, stop))
        for m in imeis
    ]
    for t in threads:
        t.start()
    t_end = time.monotonic() + 60
    while min(map(len, acked.values())) < 8 and time.monotonic() < t_end:
        time.sleep(0.01)
    first = {m: owners[m][0] for m in imeis}
    assert len(set(first.values())) == 2 and svc.proc.pid not in first.values(), first
    assert all(p in pids for p in first.values())
    victim = first[imeis[0]]
    assert victim is not None
    os.kill(victim, 9)  # mid-stream: every device is sending
    before = {m: len(a) for m, a in acked.items()}
    for t in threads:
        t.join(90)
    stop.set()
    assert all(len(acked[m]) == N_PACKETS for m in imeis), {m: len(a) for m, a in acked.items()}
    assert all(n < N_PACKETS for n in before.values()), before
    moved = [m for m in imeis if first[m] == victim]
    assert len(moved) == 3
    for m in moved:  # reconnected, served by the surviving worker
        assert len(owners[m]) >= 2 and owners[m][-1] not in (victim, svc.proc.pid, None), owners[m]
    assert svc.stop() == 0  # SIGTERM: a clean exit of the main process and the workers
    survivor = next(p for p in first.values() if p != victim)
    t_end = time.monotonic() + 10
    while Path(f"/proc/{survivor}").exists() and time.monotonic() < t_end:
        time.sleep(0.05)
    assert not Path(f"/proc/{survivor}").exists()  # the worker stopped with the main process
    url = store.sqlite_url(data)
    for j, m in enumerate(imeis):
        fixes = _track(url, m, "none")
        lat = [48.0 + j * 0.01 + 10.0 * i / 111_200.0 for i in range(N_PACKETS)]  # this device's own
        assert max(abs(r[1] - x) for r, x in zip(fixes, lat, strict=True)) < 1e-7 + 1e-12
        assert [r[0] for r in fixes] == [T0_MS / 1000 + i for i in range(N_PACKETS)], m  # once each, in order
        assert {round(r[2], 7) for r in fixes} == {16.37}
    con = sqlite3.connect(data / "iotnav.sqlite", timeout=10)
    assert con.execute("SELECT count(*), count(DISTINCT dedup_key) FROM raw_messages").fetchone() == (
        6 * N_PACKETS,
        6 * N_PACKETS,
    )
    assert con.execute("SELECT count(DISTINCT device_id) FROM engine_states").fetchone() == (6,)
    con.close()
    # the reference: the same packets, one ingestor, uninterrupted
    ref = tmp_path / "ref"
    ref.mkdir()
    db = store.make_engine(store.sqlite_url(ref))
    store.upgrade(db)
    ing = Ingestor(db, "fixes", checkpoint_key=checkpoint.load_key(ref))
    for m in imeis:
        for p in packets[m]:
            ing.ingest("teltonika", m, p, decode_avl(p, m).records)
    ing.close()
    db.dispose()
    for m in imeis:
        clean = _track(url, m, "fixes")
        assert len(clean) == N_PACKETS and clean == _track(store.sqlite_url(ref), m, "fixes"), m
