"""Helpers of the service tests: Teltonika packet builder, free ports, a service subprocess."""

from __future__ import annotations

import os
import socket
import struct
import subprocess
import sys
import threading
import time
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from pathlib import Path
from typing import Any

from sqlalchemy import exc as sa_exc

import iotnav
from iotnav.service.ingest import Ingestor
from iotnav.service.protocols.teltonika import crc16_ibm

SRC = str(Path(iotnav.__file__).resolve().parent.parent)


def imei_frame(imei: str) -> bytes:
    """The IMEI handshake: 2-byte length then ASCII digits."""
    return struct.pack(">H", len(imei)) + imei.encode()


def codec8_packet(records: list[tuple[int, float, float, int, int]]) -> bytes:
    """A Codec 8 AVL packet of ``(t_ms, lat_deg, lon_deg, speed_kmh, satellites)`` records.

    Each record carries one 1-byte IO element (240 movement = 1); layout of the Teltonika wiki.
    """
    body = bytes([0x08, len(records)])
    for t_ms, lat, lon, speed, sats in records:
        body += struct.pack(">QBiihHBH", t_ms, 0, round(lon * 1e7), round(lat * 1e7), 100, 90, sats, speed)
        body += bytes([0, 1, 1, 240, 1, 0, 0, 0])  # event 0, total 1, N1=1 (240=1), N2=N4=N8=0
    body += bytes([len(records)])
    return b"\0\0\0\0" + struct.pack(">I", len(body)) + body + struct.pack(">I", crc16_ibm(body))


def free_ports(n: int) -> list[int]:
    """``n`` TCP ports free on 127.0.0.1 right now."""
    socks = [socket.socket() for _ in range(n)]
    for s in socks:
        s.bind(("127.0.0.1", 0))
    ports = [s.getsockname()[1] for s in socks]
    for s in socks:
        s.close()
    return ports


def recv_exact(sock: socket.socket, n: int) -> bytes:
    """Exactly ``n`` bytes from ``sock`` (ConnectionError if it closes first)."""
    out = b""
    while len(out) < n:
        chunk = sock.recv(n - len(out))
        if not chunk:
            raise ConnectionError("closed")
        out += chunk
    return out


class Service:
    """``iotnav serve`` in a subprocess on free localhost ports, data in ``data``."""

    def __init__(self, data: Path, src: str | None = None, **settings: object) -> None:
        self.data = data
        self.src = (
            src or SRC
        )  # the iotnav source tree the service runs (another one: a benchmark's reference)
        self.tcp, self.osmand, self.api = free_ports(3)
        self.settings = {
            "data": str(data),
            "host": "127.0.0.1",
            "teltonika_port": self.tcp,
            "osmand_port": self.osmand,
            "api_port": self.api,
            "engine": "none",
            **settings,
        }
        self.proc: subprocess.Popen[bytes] | None = None

    def start(self, timeout: float = 90.0) -> Service:
        env = {**os.environ, "PYTHONPATH": self.src + os.pathsep + os.environ.get("PYTHONPATH", "")}
        env.pop("IOTNAV_ADMIN_TOKEN", None)
        cfg = self.data / "serve.toml"
        self.data.mkdir(parents=True, exist_ok=True)
        lines = ["[serve]"]
        for k, v in self.settings.items():
            if v == "":
                continue
            lines.append(
                f"{k} = {str(v).lower() if isinstance(v, bool) else repr(v) if isinstance(v, str) else v}"
            )
        cfg.write_text("\n".join(lines).replace("'", '"') + "\n")
        args = [sys.executable, "-m", "iotnav.service", str(cfg)]
        self.log = open(self.data.parent / f"{self.data.name}-{time.monotonic_ns()}.log", "wb")
        self.proc = subprocess.Popen(args, env=env, stdout=self.log, stderr=subprocess.STDOUT)
        t_end = time.monotonic() + timeout
        while time.monotonic() < t_end:
            if self.proc.poll() is not None:
                raise RuntimeError(
                    f"service exited {self.proc.returncode}: {Path(self.log.name).read_text()}"
                )
            try:
                for port in (self.tcp, self.osmand, self.api):
                    socket.create_connection(("127.0.0.1", port), timeout=1).close()
                return self
            except OSError:
                time.sleep(0.1)
        raise TimeoutError(f"service not ready after {timeout} s: {Path(self.log.name).read_text()}")

    def kill9(self) -> None:
        assert self.proc is not None
        self.proc.kill()  # SIGKILL
        self.proc.wait(10)
        self.log.close()

    def stop(self) -> int:
        assert self.proc is not None
        self.proc.terminate()
        try:
            return self.proc.wait(20)
        finally:
            self.log.close()

    @property
    def admin_token(self) -> str:
        return (self.data / "admin_token").read_text().strip()

    def url(self, path: str, port: int | None = None) -> str:
        return f"http://127.0.0.1:{port or self.api}{path}"


PG_BIN = Path("/usr/lib/postgresql/15/bin")


class WebhookReceiver:
    """A webhook receiver on 127.0.0.1: answers 500 to the first ``fail_first`` requests, 200 after.

    ``got``: one ``(monotonic time, headers, body, status answered)`` per request, in order.
    """

    def __init__(self, fail_first: int = 0) -> None:
        self.got: list[tuple[float, dict[str, str], bytes, int]] = []
        self.lock = threading.Lock()
        outer = self

        class Handler(BaseHTTPRequestHandler):
            def do_POST(self) -> None:
                body = self.rfile.read(int(self.headers["Content-Length"]))
                with outer.lock:
                    code = 500 if len(outer.got) < fail_first else 200
                    outer.got.append((time.monotonic(), dict(self.headers), body, code))
                self.send_response(code)
                self.send_header("Content-Length", "0")
                self.end_headers()

            def log_message(self, *_: Any) -> None:
                pass

        self.server = ThreadingHTTPServer(("127.0.0.1", 0), Handler)
        self.url = f"http://127.0.0.1:{self.server.server_address[1]}/hook"
        threading.Thread(target=self.server.serve_forever, daemon=True).start()


class FetchedMessage:
    """A JetStream message as :meth:`iotnav.service.workers.Worker._process` takes one from a
    fetch (its body, AckAll, in-progress), for tests that call it in-process; the acks are
    appended to ``acks``."""

    def __init__(self, data: bytes, acks: list[bytes]) -> None:
        self.data, self._acks = data, acks

    async def ack(self) -> None:
        self._acks.append(self.data)

    async def in_progress(self) -> None:
        pass


class Postgres:
    """A throw-away PostgreSQL cluster (Debian package ``postgresql``) on a Unix socket.

    ``initdb`` refuses to run as root, so as root the cluster runs as the ``postgres`` user.
    """

    def __init__(self) -> None:
        import shutil
        import tempfile

        bins = [PG_BIN, *sorted(Path("/usr/lib/postgresql").glob("*/bin"), reverse=True)]
        found = next((b for b in bins if (b / "initdb").exists()), None)
        if found is None:
            raise RuntimeError("PostgreSQL server binaries not found: install the Debian package postgresql")
        self.bin = found
        self.dir = Path(tempfile.mkdtemp(prefix="iotnav-pg-", dir="/tmp"))
        self.port = free_ports(1)[0]
        self.as_user: list[str] = []
        if os.geteuid() == 0:
            shutil.chown(self.dir, "postgres", "postgres")
            self.as_user = ["runuser", "-u", "postgres", "--"]

    def _run(self, *args: str) -> None:
        subprocess.run([*self.as_user, *args], check=True, capture_output=True, timeout=120)

    def start(self) -> Postgres:
        data = str(self.dir / "data")
        self._run(
            str(self.bin / "initdb"), "-D", data, "-A", "trust", "-U", "iotnav", "--no-sync", "-E", "UTF8"
        )
        opts = f"-k {self.dir} -p {self.port} -c listen_addresses='' -c fsync=on"
        self._run(
            str(self.bin / "pg_ctl"), "-D", data, "-o", opts, "-l", str(self.dir / "log"), "-w", "start"
        )
        return self

    @property
    def url(self) -> str:
        return f"postgresql+psycopg://iotnav@/postgres?host={self.dir}&port={self.port}"

    def stop(self) -> None:
        import shutil

        try:
            self._run(str(self.bin / "pg_ctl"), "-D", str(self.dir / "data"), "-m", "immediate", "-w", "stop")
        finally:
            shutil.rmtree(self.dir, ignore_errors=True)


def wait_listening(port: int, what: str, log_path: Path, timeout_s: float = 20.0) -> None:
    """Wait until a server started by a test accepts TCP connections on 127.0.0.1:``port``.

    Raises TimeoutError with the server's log when it does not within ``timeout_s`` seconds.
    """
    t_end = time.monotonic() + timeout_s
    while time.monotonic() < t_end:
        try:
            socket.create_connection(("127.0.0.1", port), timeout=1).close()
            return
        except OSError:
            time.sleep(0.05)
    raise TimeoutError(f"{what} not ready: {log_path.read_text()}")


class Mosquitto:
    """A throw-away mosquitto broker (Debian package ``mosquitto``) on a free localhost port."""

    def __init__(self, workdir: Path) -> None:
        import shutil

        exe = shutil.which("mosquitto") or "/usr/sbin/mosquitto"
        if not Path(exe).exists():
            raise RuntimeError("mosquitto not found: install the Debian package mosquitto")
        self.exe = exe
        self.port = free_ports(1)[0]
        self.dir = workdir
        self.dir.mkdir(parents=True, exist_ok=True)
        conf = [f"listener {self.port} 127.0.0.1", "allow_anonymous true", "persistence false"]
        if os.geteuid() == 0:
            conf.append("user root")
        (self.dir / "mosquitto.conf").write_text("\n".join(conf) + "\n")
        self.proc: subprocess.Popen[bytes] | None = None

    def start(self) -> Mosquitto:
        self.log = open(self.dir / "mosquitto.log", "wb")
        self.proc = subprocess.Popen(
            [self.exe, "-c", str(self.dir / "mosquitto.conf")], stdout=self.log, stderr=subprocess.STDOUT
        )
        wait_listening(self.port, "mosquitto", self.dir / "mosquitto.log")
        return self

    @property
    def url(self) -> str:
        return f"mqtt://127.0.0.1:{self.port}"

    def stop(self) -> None:
        assert self.proc is not None
        self.proc.terminate()
        self.proc.wait(10)
        self.log.close()


class FlakyIngestor(Ingestor):
    """Ingestor whose database is down (``OperationalError``) while ``down`` is set."""

    def __init__(self, *a, **k) -> None:
        super().__init__(*a, **k)
        self.down = threading.Event()

    def ingest_batch(self, msgs):
        if self.down.is_set():
            return [sa_exc.OperationalError("INSERT", {}, Exception("database is down"))] * len(msgs)
        return super().ingest_batch(msgs)
