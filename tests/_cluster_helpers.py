"""Helpers of the worker tests and benchmark: a throw-away nats-server with JetStream, workers."""

from __future__ import annotations

import asyncio
import atexit
import os
import shutil
import subprocess
import sys
import tempfile
import threading
from pathlib import Path
from typing import Any

from _service_helpers import SRC, Postgres, free_ports, wait_listening


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
        wait_listening(self.port, "nats-server", self.dir / "nats.log")
        return self

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


def start_worker_with(log_path: Path, go: Path) -> subprocess.Popen[bytes]:
    """A worker in a subprocess that imports its modules at once, then waits for the file ``go``:
    a JSON ``[config, cluster]`` for ``run_worker(WorkerConfig(**config), ClusterSettings(**cluster))``
    (settings the command line does not have, such as the stream's name; the imports overlap
    the test's own set-up)."""
    code = (
        "import asyncio, json, logging, os, sys, time\n"
        "from iotnav.service.workers import ClusterSettings, WorkerConfig, run_worker\n"
        "import iotnav.service.alerts_delivery, nats, alembic.command\n"
        "logging.basicConfig(level=logging.WARNING)\n"
        "while not os.path.exists(sys.argv[1]): time.sleep(0.02)\n"
        "time.sleep(0.02)\n"
        "c, k = json.loads(open(sys.argv[1]).read())\n"
        "asyncio.run(run_worker(WorkerConfig(**c), ClusterSettings(**k)))\n"
    )
    log = open(log_path, "wb")
    return subprocess.Popen([sys.executable, "-c", code, str(go)], env=worker_env(), stdout=log, stderr=log)


class InProcessWorker(threading.Thread):
    """A worker on an event loop of its own in this process (it shares the engine's kernels
    already loaded here: one process fewer to start); :meth:`stop` ends it as SIGTERM would."""

    def __init__(self, config: Any, cluster: Any) -> None:
        super().__init__(daemon=True)
        self.config, self.cluster = config, cluster
        self.ready = threading.Event()
        self.error: BaseException | None = None

    def run(self) -> None:
        try:
            asyncio.run(self._main())
        except BaseException as exc:
            self.error = exc

    async def _main(self) -> None:
        from iotnav.service.workers import run_worker

        self.loop = asyncio.get_running_loop()
        self.stop_event = asyncio.Event()
        self.ready.set()
        await run_worker(self.config, self.cluster, self.stop_event)

    def stop(self) -> None:
        self.ready.wait(10)
        self.loop.call_soon_threadsafe(self.stop_event.set)
        self.join(30)
        assert not self.is_alive() and self.error is None, self.error


_SHARED: list[Any] = []


def shared_cluster() -> tuple[NatsServer, Postgres]:
    """One nats-server and one PostgreSQL for every worker test of this process (started at the
    first call, stopped at exit): each test uses streams and databases of its own."""
    if not _SHARED:
        nats = NatsServer().start()
        pg = Postgres().start()
        _SHARED.extend([nats, pg])

        def stop() -> None:
            pg.stop()
            nats.stop()

        atexit.register(stop)
    return _SHARED[0], _SHARED[1]


def new_database(pg: Postgres, name: str) -> str:
    """A fresh database ``name`` on ``pg`` (dropped first if it exists); its SQLAlchemy URL."""
    import sqlalchemy as sa

    admin = sa.create_engine(pg.url, isolation_level="AUTOCOMMIT")
    with admin.connect() as con:
        con.exec_driver_sql(f'DROP DATABASE IF EXISTS "{name}" WITH (FORCE)')
        con.exec_driver_sql(f'CREATE DATABASE "{name}"')
    admin.dispose()
    return pg.url.replace("/postgres?", f"/{name}?")
