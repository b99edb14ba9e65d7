"""Process the logs of many devices: one :func:`process_device` per device, run by an executor.

A fleet run is a list of device log directories, each fused on its own with one engine and
written to ``OUT/<device>/`` with exactly the files ``iotnav run`` writes (``track.csv``,
``events.json``, ``summary.json``, ``gnss.csv``, ``track.geojson``, ``track.gpx``), plus
``OUT/fleet_summary.json`` for the whole run.

Which directories are devices (:func:`discover_devices`)
--------------------------------------------------------
Each path given is looked at once, not recursively:

1. a directory that directly holds a log file is **one device**, named after the directory.
   Log files are ``gnss.nmea``, ``gnss.ubx`` and ``imu.csv`` (as ``iotnav simulate`` writes;
   read exactly as ``iotnav run DIR`` reads them, ``gnss.nmea`` preferred over ``gnss.ubx``,
   ``last_position.json`` used as the boot position), or, when none of those is there, every
   non-hidden file whose suffix is in :data:`LOG_SUFFIXES` (the formats ``iotnav run``
   accepts, detected by content);
2. a directory holding no log file is a **parent**: each of its non-hidden subdirectories is
   one device by rule 1. A subdirectory with no log file is still listed, and fails with the
   reason "no log files", so nothing is dropped silently. The output directory is skipped when
   it sits inside a parent.

Two devices with the same directory name are an error (their outputs would collide).

Executors
---------
:func:`run_fleet` hands :func:`process_device` calls to one of

* ``workers=0``: the calling process, one device after the other (debugging, tests);
* ``workers=N`` (N >= 1): a local pool of N worker processes (``spawn`` start method);
* ``scheduler="tcp://host:8786"``: a Dask cluster (``dask.distributed.Client``). The workers
  need iotnav installed, and the log and output directories must be on a file system they all
  see under the same paths.

:func:`process_device` never raises for a device's own problem: the error is captured in its
result so one bad device does not stop the fleet. A worker process that dies (crash, killed
for memory) fails the devices it was running with the reason given by the executor.
"""

from __future__ import annotations

import json
import math
import os
import socket
import time
import traceback
from collections.abc import Callable, Iterable, Iterator, Sequence
from concurrent.futures import ProcessPoolExecutor, as_completed
from contextlib import contextmanager
from dataclasses import dataclass
from multiprocessing import get_context
from pathlib import Path
from typing import Any, Protocol

__all__ = [
    "FLEET_SUMMARY",
    "LOG_SUFFIXES",
    "STANDARD_NAMES",
    "THREAD_ENV",
    "DaskExecutor",
    "DeviceJob",
    "Executor",
    "FleetResult",
    "InlineExecutor",
    "LocalPoolExecutor",
    "device_files",
    "discover_devices",
    "make_executor",
    "process_device",
    "run_fleet",
]

#: Names ``iotnav simulate`` writes and ``iotnav run DIR`` reads, in that order of preference.
STANDARD_NAMES: tuple[str, ...] = ("gnss.nmea", "gnss.ubx", "imu.csv")

#: Suffixes of log files taken from a device directory that holds none of :data:`STANDARD_NAMES`.
LOG_SUFFIXES: tuple[str, ...] = (".nmea", ".ubx", ".pos", ".csv", ".npz", ".txt", ".log")

FLEET_SUMMARY = "fleet_summary.json"


@dataclass(frozen=True)
class DeviceJob:
    """One device of a fleet run.

    Attributes
    ----------
    name : str
        Device name (its directory name); the output goes to ``out_root / name``.
    log_dir : Path
        The device's log directory.
    """

    name: str
    log_dir: Path


@dataclass
class FleetResult:
    """Outcome of :func:`run_fleet`.

    Attributes
    ----------
    devices : list of dict
        One :func:`process_device` result per device, sorted by device name.
    wall_s : float
        Wall-clock time of the whole run, s.
    executor : str
        ``inline``, ``local-pool`` or ``dask``.
    workers : int
        Worker processes (local pool), 0 inline, the number of Dask workers for a cluster.
    """

    devices: list[dict[str, Any]]
    wall_s: float
    executor: str
    workers: int

    @property
    def ok(self) -> int:
        """Devices processed without error."""
        return sum(1 for d in self.devices if d["ok"])

    @property
    def failed(self) -> int:
        """Devices that failed."""
        return len(self.devices) - self.ok

    @property
    def devices_per_min(self) -> float:
        """Devices (ok or failed) finished per minute of wall-clock time."""
        return 60.0 * len(self.devices) / self.wall_s if self.wall_s > 0 else math.nan

    @property
    def imu_samples_per_s(self) -> float:
        """IMU samples of the successful devices per second of wall-clock time."""
        n = sum(d["counts"].get("imu_samples_in", 0) for d in self.devices if d["ok"])
        return n / self.wall_s if self.wall_s > 0 else math.nan

    def failures(self) -> list[tuple[str, str]]:
        """``(device, reason)`` of every failed device."""
        return [(d["device"], d["error"]["reason"]) for d in self.devices if not d["ok"]]

    def to_dict(self, engine: str, config_path: str | Path | None) -> dict[str, Any]:
        """The content of ``fleet_summary.json``."""
        return {
            "engine": engine,
            "config": str(config_path) if config_path is not None else None,
            "executor": self.executor,
            "workers": self.workers,
            "devices_total": len(self.devices),
            "devices_ok": self.ok,
            "devices_failed": self.failed,
            "wall_s": self.wall_s,
            "devices_per_min": self.devices_per_min,
            "imu_samples_per_s": self.imu_samples_per_s,
            "failures": [{"device": n, "reason": r} for n, r in self.failures()],
            "devices": self.devices,
        }


def _log_files(d: Path) -> tuple[list[Path], Path | None]:
    """Log files of a device directory and its ``last_position.json`` (rule 1 of the module doc)."""
    std = [d / n for n in STANDARD_NAMES if (d / n).is_file()]
    if std:
        if d / "gnss.nmea" in std and d / "gnss.ubx" in std:
            std.remove(d / "gnss.ubx")  # the simulator writes both; one GNSS stream, as iotnav run
        state = d / "last_position.json"
        return std, state if state.is_file() else None
    files = sorted(
        p
        for p in d.iterdir()
        if p.is_file() and not p.name.startswith(".") and p.suffix.lower() in LOG_SUFFIXES
    )
    return files, None


def device_files(log_dir: str | os.PathLike[str]) -> tuple[list[Path], Path | None]:
    """The files :func:`process_device` reads for a device directory.

    Parameters
    ----------
    log_dir : path-like
        A device directory.

    Returns
    -------
    files : list of Path
        Log files, in reading order.
    last_position : Path or None
        ``last_position.json`` when the directory has one next to the standard names.

    Raises
    ------
    FileNotFoundError
        When the directory does not exist or holds no log file.
    """
    d = Path(log_dir)
    if not d.is_dir():
        raise FileNotFoundError(f"{d}: not a directory")
    files, state = _log_files(d)
    if not files:
        raise FileNotFoundError(
            f"{d}: no log files (expected gnss.nmea / gnss.ubx / imu.csv, or files ending in "
            f"{', '.join(LOG_SUFFIXES)})"
        )
    return files, state


def discover_devices(
    paths: Sequence[str | os.PathLike[str]], out: str | os.PathLike[str] | None = None
) -> list[DeviceJob]:
    """Expand LOG_DIRS into device jobs (the rule is in the module docstring).

    Parameters
    ----------
    paths : sequence of path-like
        Device directories or parents of device directories.
    out : path-like, optional
        The fleet output directory; skipped when it sits inside a parent.

    Returns
    -------
    list of DeviceJob
        Sorted by device name.

    Raises
    ------
    FileNotFoundError
        For a path that is not a directory, or a directory with neither log files nor
        subdirectories.
    ValueError
        When no path is given or two devices share a name.
    """
    if not paths:
        raise ValueError("give at least one log directory")
    skip = Path(out).resolve() if out is not None else None
    jobs: list[DeviceJob] = []
    for raw in paths:
        p = Path(raw)
        if not p.is_dir():
            raise FileNotFoundError(
                f"{p}: not a directory (run-many takes device directories or their parents)"
            )
        if _log_files(p)[0]:
            jobs.append(DeviceJob(p.resolve().name, p))
            continue
        subs = sorted(
            s for s in p.iterdir() if s.is_dir() and not s.name.startswith(".") and s.resolve() != skip
        )
        if not subs:
            raise FileNotFoundError(f"{p}: neither log files nor device subdirectories in this directory")
        jobs.extend(DeviceJob(s.name, s) for s in subs)
    seen: dict[str, Path] = {}
    for j in jobs:
        if j.name in seen:
            raise ValueError(f"two devices named {j.name!r}: {seen[j.name]} and {j.log_dir}; rename one")
        seen[j.name] = j.log_dir
    return sorted(jobs, key=lambda j: j.name)


def process_device(
    log_dir: str | os.PathLike[str],
    out_dir: str | os.PathLike[str],
    engine: str = "pipeline",
    config_path: str | os.PathLike[str] | None = None,
) -> dict[str, Any]:
    """Ingest, fuse and write one device, as ``iotnav run LOG_DIR --out OUT_DIR`` does.

    Never raises for a problem of the device (unreadable file, engine error, ...): the error is
    returned in the result.

    Parameters
    ----------
    log_dir : path-like
        The device directory (see :func:`device_files`).
    out_dir : path-like
        Where ``track.csv``, ``events.json``, ``summary.json``, ``gnss.csv``, GeoJSON and GPX go.
    engine : str
        Engine name (:func:`iotnav.engines.registry.available_engines`).
    config_path : path-like, optional
        Engine configuration (TOML).

    Returns
    -------
    dict
        ``device`` (directory name), ``log_dir``, ``out_dir``, ``ok``; ``error`` (None, or
        ``{"type", "reason", "traceback"}``); ``timings_s`` (``ingest``, ``run``, ``write``,
        ``total``; the stages reached); ``counts`` (``summary.json`` counts, empty on failure);
        ``host`` and ``pid`` of the worker.
    """
    t_start = time.perf_counter()
    log_dir, out_dir = Path(log_dir), Path(out_dir)
    result: dict[str, Any] = {
        "device": log_dir.name,
        "log_dir": str(log_dir),
        "out_dir": str(out_dir),
        "ok": False,
        "error": None,
        "timings_s": {},
        "counts": {},
        "host": socket.gethostname(),
        "pid": os.getpid(),
    }
    timings = result["timings_s"]
    try:
        # Imported here: workers pay for these once, and the module stays cheap to import.
        # write_run and load_stored_position live in the CLI today; they are plain functions
        # (no terminal) and should move below the CLI (see the fleet report).
        from iotnav.engines.base import run_batch
        from iotnav.engines.registry import make_engine
        from iotnav.io import ingest
        from iotnav.runs import load_stored_position, write_run

        t0 = time.perf_counter()
        files, state_file = device_files(log_dir)
        log = ingest(files)
        stored = load_stored_position(state_file) if state_file is not None else None
        t1 = time.perf_counter()
        timings["ingest"] = t1 - t0
        eng = make_engine(engine, Path(config_path) if config_path is not None else None, stored=stored)
        track = run_batch(eng, log)
        t2 = time.perf_counter()
        timings["run"] = t2 - t1
        summary = write_run(out_dir, track, log, engine, t2 - t1)
        timings["write"] = time.perf_counter() - t2
        result["counts"] = summary["counts"]
        result["ok"] = True
    except Exception as exc:  # one bad device must not stop the fleet; the reason is reported
        result["error"] = {
            "type": type(exc).__name__,
            "reason": f"{type(exc).__name__}: {exc}",
            "traceback": traceback.format_exc(),
        }
    timings["total"] = time.perf_counter() - t_start
    return result


def _failed(job: DeviceJob, out_dir: Path, exc: BaseException, where: str) -> dict[str, Any]:
    """Result of a device whose worker failed outside :func:`process_device`."""
    return {
        "device": job.name,
        "log_dir": str(job.log_dir),
        "out_dir": str(out_dir),
        "ok": False,
        "error": {
            "type": type(exc).__name__,
            "reason": f"{where}: {type(exc).__name__}: {exc}",
            "traceback": "".join(traceback.format_exception(exc)),
        },
        "timings_s": {},
        "counts": {},
        "host": None,
        "pid": None,
    }


Call = tuple[str, str, str, str | None]
"""Arguments of one :func:`process_device` call: log_dir, out_dir, engine, config_path."""


class Executor(Protocol):
    """Runs :func:`process_device` calls somewhere; :func:`run_fleet` knows nothing more.

    Attributes
    ----------
    name : str
        ``inline``, ``local-pool`` or ``dask``.
    workers : int
        Worker processes available (0 for inline).
    """

    name: str
    workers: int

    def map_unordered(self, calls: Sequence[Call]) -> Iterator[tuple[int, dict[str, Any] | BaseException]]:
        """Yield ``(index into calls, result)`` as calls finish; an exception when the worker failed."""
        ...

    def close(self) -> None:
        """Release workers and connections."""
        ...


class InlineExecutor:
    """Every call in the calling process, one after the other."""

    name = "inline"
    workers = 0

    def map_unordered(self, calls: Sequence[Call]) -> Iterator[tuple[int, dict[str, Any] | BaseException]]:
        """Run the calls in order."""
        for i, c in enumerate(calls):
            yield i, process_device(*c)

    def close(self) -> None:
        """Nothing to release."""


#: Thread-count variables of BLAS / OpenMP runtimes, set to 1 in worker processes.
THREAD_ENV: tuple[str, ...] = (
    "OMP_NUM_THREADS",
    "OPENBLAS_NUM_THREADS",
    "MKL_NUM_THREADS",
    "VECLIB_MAXIMUM_THREADS",
    "NUMEXPR_NUM_THREADS",
)


@contextmanager
def _single_threaded_libraries() -> Iterator[None]:
    """Set :data:`THREAD_ENV` to 1 (unless the user set them) while worker processes start.

    Each worker is one core's worth of work; a multi-threaded BLAS in each of N workers
    oversubscribes the cores (measured here: 2 workers took twice as long as 1 until this was
    set). Dask's nanny does the same for its workers.
    """
    added = [k for k in THREAD_ENV if k not in os.environ]
    for k in added:
        os.environ[k] = "1"
    try:
        yield
    finally:
        for k in added:
            os.environ.pop(k, None)


class LocalPoolExecutor:
    """A pool of ``workers`` local processes (``spawn`` start method), BLAS single-threaded.

    ``spawn`` rather than ``fork``: the parent holds threads (progress bar, Dask) that must
    not be forked, and the behaviour is the same on every OS. Each worker pays the imports once
    and runs numpy's BLAS on one thread (see :data:`THREAD_ENV`).
    """

    name = "local-pool"

    def __init__(self, workers: int) -> None:
        self.workers = workers
        self._pool = ProcessPoolExecutor(max_workers=workers, mp_context=get_context("spawn"))

    def map_unordered(self, calls: Sequence[Call]) -> Iterator[tuple[int, dict[str, Any] | BaseException]]:
        """Submit every call; yield results as they complete."""
        with _single_threaded_libraries():  # workers are spawned during the submits
            futures = {self._pool.submit(process_device, *c): i for i, c in enumerate(calls)}
        for fut in as_completed(futures):
            try:
                yield futures[fut], fut.result()
            except Exception as exc:  # BrokenProcessPool: a worker died
                yield futures[fut], exc

    def close(self) -> None:
        """Shut the pool down (waits for running calls)."""
        self._pool.shutdown(wait=True, cancel_futures=True)


class DaskExecutor:
    """A Dask cluster reached through its scheduler address.

    The workers need iotnav (same version) installed, and every log and output path must be
    valid on them (a shared file system).
    """

    name = "dask"

    def __init__(self, address: str) -> None:
        try:
            from distributed import Client
        except ImportError:
            raise ValueError(
                "--scheduler needs Dask: pip install 'dask[distributed]' (here and on the workers)"
            ) from None
        try:
            self._client = Client(address, set_as_default=False, timeout=30)
        except OSError as exc:
            raise ValueError(f"--scheduler {address}: cannot reach a Dask scheduler ({exc})") from None
        self.workers = len(self._client.scheduler_info(n_workers=-1).get("workers", {}))

    def map_unordered(self, calls: Sequence[Call]) -> Iterator[tuple[int, dict[str, Any] | BaseException]]:
        """Submit every call to the cluster; yield results as they complete."""
        from distributed import as_completed as dask_as_completed

        futures = [self._client.submit(process_device, *c, pure=False) for c in calls]
        index = {f.key: i for i, f in enumerate(futures)}
        for fut in dask_as_completed(futures, loop=self._client.loop):
            try:
                yield index[fut.key], fut.result()
            except Exception as exc:  # KilledWorker, lost connection, ...
                yield index[fut.key], exc

    def close(self) -> None:
        """Close the client (the cluster keeps running)."""
        self._client.close()


def make_executor(workers: int = 1, scheduler: str | None = None) -> Executor:
    """The executor for ``--workers`` / ``--scheduler``.

    Parameters
    ----------
    workers : int
        0: in this process; N >= 1: a local pool of N processes. Ignored with ``scheduler``.
    scheduler : str, optional
        Address of a Dask scheduler (``tcp://host:8786``).

    Returns
    -------
    Executor

    Raises
    ------
    ValueError
        ``workers < 0``; ``scheduler`` unreachable or Dask not installed.
    """
    if scheduler is not None:
        return DaskExecutor(scheduler)
    if workers < 0:
        raise ValueError(f"--workers {workers}: expected 0 (in this process) or more")
    return InlineExecutor() if workers == 0 else LocalPoolExecutor(workers)


def run_fleet(
    jobs: Iterable[DeviceJob],
    out: str | os.PathLike[str],
    engine: str = "pipeline",
    config_path: str | os.PathLike[str] | None = None,
    *,
    workers: int = 1,
    scheduler: str | None = None,
    on_done: Callable[[dict[str, Any]], None] | None = None,
    write_summary: bool = True,
) -> FleetResult:
    """Process every device of a fleet and write ``OUT/<device>/`` and ``OUT/fleet_summary.json``.

    Parameters
    ----------
    jobs : iterable of DeviceJob
        Devices (:func:`discover_devices`).
    out : path-like
        Output root; device ``d`` goes to ``out / d``.
    engine : str
        Engine name; checked (with its configuration) before any device is started.
    config_path : path-like, optional
        Engine configuration (TOML), the same for every device.
    workers : int
        0: in this process; N >= 1: a local pool of ``min(N, devices)`` processes.
        Ignored with ``scheduler``.
    scheduler : str, optional
        Address of a Dask scheduler (``tcp://host:8786``); the work goes to its cluster.
    on_done : callable, optional
        Called in this process with each device's result as it finishes (progress bars).
    write_summary : bool
        Write ``OUT/fleet_summary.json``.

    Returns
    -------
    FleetResult

    Raises
    ------
    ValueError
        Unknown or unavailable engine, unreadable configuration, ``workers < 0``, or an
        unusable ``scheduler``.
    """
    from iotnav.engines.registry import make_engine

    jobs = list(jobs)
    config = str(Path(config_path).resolve()) if config_path is not None else None
    make_engine(engine, config)  # fail fast on a bad engine name or configuration
    out_root = Path(out)
    out_root.mkdir(parents=True, exist_ok=True)
    calls: list[Call] = [
        (str(j.log_dir.resolve()), str((out_root / j.name).resolve()), engine, config) for j in jobs
    ]
    t0 = time.perf_counter()
    executor = make_executor(min(workers, max(len(jobs), 1)) if workers > 0 else workers, scheduler)
    results: list[dict[str, Any]] = []
    try:
        for i, res in executor.map_unordered(calls):
            job = jobs[i]
            if isinstance(res, BaseException):
                res = _failed(job, Path(calls[i][1]), res, f"{executor.name} worker failed")
            res["device"] = job.name
            results.append(res)
            if on_done is not None:
                on_done(res)
    finally:
        executor.close()
    result = FleetResult(
        sorted(results, key=lambda d: d["device"]), time.perf_counter() - t0, executor.name, executor.workers
    )
    if write_summary:
        (out_root / FLEET_SUMMARY).write_text(json.dumps(_finite(result.to_dict(engine, config)), indent=1))
    return result


def _finite(o: Any) -> Any:
    """Replace NaN/inf with None recursively so the JSON is standard."""
    if isinstance(o, dict):
        return {k: _finite(v) for k, v in o.items()}
    if isinstance(o, list | tuple):
        return [_finite(v) for v in o]
    if isinstance(o, float) and not math.isfinite(o):
        return None
    return o
