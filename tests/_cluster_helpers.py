"""Helpers of the worker tests and benchmark: a throw-away nats-server with JetStream, workers."""

from __future__ import annotations

import asyncio
import os
import shutil
import socket
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from _service_helpers import SRC, free_ports


class NatsServer:
    """``nats-server -js`` (Debian package ``nats-server``) on a free localhost port, file storage in a temp dir."""

    def __init__(self) -> None:
        exe = shutil.which("nats-server") or "/usr/sbin/nats-server"
        if not Path(exe).exists():
            raise RuntimeError("nats-server not found: install the Debian package nats-server")
        self.exe = exe
        self.port = free_ports(1)[0]
        self.dir = Path(tempfile.mkdtemp(prefix="iotnav-nats-", dir="/tmp"))
        self.proc: subprocess.Popen[bytes] | None = None

    def start(self) -> NatsServer:
        self.log = open(self.dir / "nats.log", "wb")
        args = [self.exe, "-js", "-a", "127.0.0.1", "-p", str(self.port), "-sd", str(self.dir / "js")]
        self.proc = subprocess.Popen(args, stdout=self.log, stderr=subprocess.STDOUT)
        t_end = time.monotonic() + 20
        while time.monotonic() < t_end:
            try:
                socket.create_connection(("127.0.0.1", self.port), timeout=1).close()
                return self
            except OSError:
                time.sleep(0.05)
        raise TimeoutError(f"nats-server not ready: {(self.dir / 'nats.log').read_text()}")

    @property
    def url(self) -> str:
        return f"nats://127.0.0.1:{self.port}"

    def stop(self) -> None:
        assert self.proc is not None
        self.proc.terminate()
        self.proc.wait(10)
        self.log.close()
        shutil.rmtree(self.dir, ignore_errors=True)


def worker_env() -> dict[str, str]:
    env = {**os.environ, "PYTHONPATH": SRC + os.pathsep + os.environ.get("PYTHONPATH", "")}
    return env


def start_worker(log_path: Path, *args: str) -> subprocess.Popen[bytes]:
    """``iotnav worker ARGS`` in a subprocess (stdout and stderr to ``log_path``)."""
    code = "import sys, faulthandler, signal; faulthandler.register(signal.SIGUSR1); from iotnav.cli import main; sys.argv = ['iotnav', 'worker', *sys.argv[1:]]; main()"
    log = open(log_path, "wb")
    return subprocess.Popen([sys.executable, "-c", code, *args], env=worker_env(), stdout=log, stderr=log)


def lease_owners(url: str, bucket: str = "iotnav_leases") -> dict[int, str]:
    """Partition -> worker id of every lease in the bucket (empty when there is none yet)."""

    async def read() -> dict[int, str]:
        import nats
        from nats.js.errors import BucketNotFoundError, KeyNotFoundError, NoKeysError

        nc = await nats.connect(url)
        try:
            kv = await nc.jetstream().key_value(bucket)
            out = {}
            for k in await kv.keys():
                if k.startswith("p."):
                    try:
                        out[int(k[2:])] = (await kv.get(k)).value.decode()
                    except KeyNotFoundError:
                        pass
            return out
        except (BucketNotFoundError, NoKeysError):
            return {}
        finally:
            await nc.close()

    return asyncio.run(read())
