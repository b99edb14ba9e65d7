"""Helpers of the service tests: Teltonika packet builder, free ports, a service subprocess."""

from __future__ import annotations

import os
import socket
import struct
import subprocess
import sys
import time
from pathlib import Path

import iotnav
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

    def __init__(self, data: Path, cli: bool = False, **settings: object) -> None:
        self.data = data
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
        self.cli = cli
        self.proc: subprocess.Popen[bytes] | None = None

    def start(self, timeout: float = 90.0) -> Service:
        env = {**os.environ, "PYTHONPATH": SRC + os.pathsep + os.environ.get("PYTHONPATH", "")}
        env.pop("IOTNAV_ADMIN_TOKEN", None)
        if self.cli:
            s = self.settings
            args = [
                sys.executable,
                "-c",
                "from iotnav.cli import main; main()",
                "serve",
                "--data",
                s["data"],
                "--host",
                "127.0.0.1",
                "--teltonika-port",
                str(self.tcp),
                "--osmand-port",
                str(self.osmand),
                "--api-port",
                str(self.api),
                "--engine",
                str(s["engine"]),
            ]
        else:
            cfg = self.data / "serve.toml"
            self.data.mkdir(parents=True, exist_ok=True)
            lines = ["[serve]"]
            for k, v in self.settings.items():
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
