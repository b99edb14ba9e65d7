"""Re-processing many device-days from the service's database, in parallel on Dask.

The live service stores every message as received (``raw_messages``) and its decoded records
as the fixes as sent (``positions`` with ``engine = 'none'``, each pointing at its raw
message). A device-day is re-run from those records: rebuilt as :class:`Fix` by the ingest's
own :func:`iotnav.service.ingest.fix_of_row` (the function the live replay uses), fed in
device-time order to a fresh engine (:func:`iotnav.engines.registry.make_engine`, any engine
that works on fixes) through its streaming ``step()`` (:func:`iotnav.service.ingest.fix_to_sample`),
and written to ``OUT/<device>/<YYYY-MM-DD>.csv``. Nothing is written to the database.

Parallelism: :func:`reprocess` runs the device-days inline, or on a Dask cluster (the
scheduler address, as ``iotnav run-many --scheduler``) or a local Dask cluster of ``workers``
processes; each task opens its own database connection, so the workers need the database URL
to be reachable and ``out_dir`` to be a shared file system.
"""

from __future__ import annotations

import csv
import math
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import sqlalchemy as sa

from iotnav.service.ingest import NO_ENGINE, fix_of_row, fix_to_sample
from iotnav.service.store import devices, positions, raw_messages

DAY_S = 86400.0


@dataclass(frozen=True)
class DeviceDay:
    """One device's UTC day: the device's id and unique id, the day's start (Unix s)."""

    device_id: int
    unique_id: str
    day_start: float

    @property
    def day(self) -> str:
        """The day as ``YYYY-MM-DD`` (UTC)."""
        return datetime.fromtimestamp(self.day_start, UTC).strftime("%Y-%m-%d")


def list_device_days(
    db: sa.engine.Engine,
    since: float | None = None,
    until: float | None = None,
    unique_ids: Sequence[str] | None = None,
) -> list[DeviceDay]:
    """Every (device, UTC day) with stored fixes, fix time in [``since``, ``until``) (Unix s),
    of the devices whose unique id (IMEI, OsmAnd id, ...) is in ``unique_ids`` (all without)."""
    day = sa.func.floor(positions.c.fix_time / DAY_S)
    q = (
        sa.select(positions.c.device_id, devices.c.unique_id, day.label("day"))
        .join(devices, devices.c.id == positions.c.device_id)
        .where(positions.c.engine == NO_ENGINE)
        .group_by(positions.c.device_id, devices.c.unique_id, day)
        .order_by(positions.c.device_id, day)
    )
    if since is not None:
        q = q.where(positions.c.fix_time >= since)
    if until is not None:
        q = q.where(positions.c.fix_time < until)
    if unique_ids is not None:
        q = q.where(devices.c.unique_id.in_(list(unique_ids)))
    with db.connect() as con:
        return [DeviceDay(int(r.device_id), str(r.unique_id), float(r.day) * DAY_S) for r in con.execute(q)]


def reprocess_device_day(
    db_url: str, job: DeviceDay, engine: str, out_dir: str | None, config: str | None = None
) -> dict[str, Any]:
    """Run ``engine`` (configured by the TOML file ``config``, its defaults without one) over the
    fixes of ``job`` (from the database) and write its track CSV.

    Returns ``device``, ``day``, ``fixes`` (read), ``raw_messages`` (they came from),
    ``outputs`` (engine outputs with a position), ``seconds`` and ``csv`` (path or None).
    The CSV columns: ``t`` (Unix s), ``lat``, ``lon`` (degrees WGS84), ``height`` (m),
    ``vn``, ``ve`` (m/s), ``std_north``, ``std_east`` (m), ``source``.
    """
    from iotnav.engines.registry import make_engine
    from iotnav.service.store import make_engine as make_db

    t0 = time.perf_counter()
    db = make_db(db_url)
    cols = [positions.c[c] for c in ("raw_id", "fix_time", "latitude", "longitude", "altitude", "speed_mps")]
    cols += [positions.c[c] for c in ("course_rad", "accuracy_m", "valid", "attributes", "dedup_key")]
    q = (
        sa.select(*cols)
        .join(raw_messages, raw_messages.c.id == positions.c.raw_id)
        .where(
            positions.c.device_id == job.device_id,
            positions.c.engine == NO_ENGINE,
            positions.c.fix_time >= job.day_start,
            positions.c.fix_time < job.day_start + DAY_S,
        )
        .order_by(positions.c.fix_time, positions.c.id)
    )
    try:
        with db.connect() as con:
            rows = con.execute(q).all()
    finally:
        db.dispose()
    eng = make_engine(engine, config)
    out = []
    for r in rows:
        o = eng.step(fix_to_sample(fix_of_row(job.unique_id, r)))
        if o is not None and o.source != "none" and math.isfinite(o.lat + o.lon):
            out.append(o)
    path = None
    if out_dir is not None:
        target = Path(out_dir) / job.unique_id
        target.mkdir(parents=True, exist_ok=True)
        path = target / f"{job.day}.csv"
        with open(path, "w", newline="") as fh:
            w = csv.writer(fh)
            w.writerow(["t", "lat", "lon", "height", "vn", "ve", "std_north", "std_east", "source"])
            for o in out:
                w.writerow([o.t, o.lat, o.lon, o.height, o.vn, o.ve, o.std_north, o.std_east, o.source])
    return {
        "device": job.unique_id,
        "day": job.day,
        "fixes": len(rows),
        "raw_messages": len({r.raw_id for r in rows}),
        "outputs": len(out),
        "lat_lon": [(o.t, o.lat, o.lon) for o in out],
        "seconds": time.perf_counter() - t0,
        "csv": None if path is None else str(path),
    }


def reprocess(
    db_url: str,
    jobs: Sequence[DeviceDay],
    engine: str = "fixes",
    out_dir: str | None = None,
    scheduler: str | None = None,
    workers: int = 0,
    config: str | None = None,
    on_done: Callable[[], None] | None = None,
) -> list[dict[str, Any] | BaseException]:
    """Re-process ``jobs``: inline (``workers`` 0, no ``scheduler``), on the Dask scheduler at
    ``scheduler``, or on a local Dask cluster of ``workers`` processes; results in job order
    (an exception in place of a device-day that failed). ``config``: the engine's TOML file
    (a path every worker can read); ``on_done`` is called once per finished device-day (a
    progress bar)."""
    if scheduler is None and workers <= 0:
        results: list[dict[str, Any] | BaseException] = []
        for job in jobs:
            try:
                results.append(reprocess_device_day(db_url, job, engine, out_dir, config))
            except Exception as exc:
                results.append(exc)
            if on_done is not None:
                on_done()
        return results
    try:
        from distributed import Client, LocalCluster, as_completed
    except ImportError:
        raise ValueError("Dask is needed: pip install 'dask[distributed]'") from None
    cluster = None
    if scheduler is None:
        cluster = LocalCluster(
            n_workers=workers, threads_per_worker=1, processes=True, dashboard_address=None
        )
    client = Client(scheduler or cluster, set_as_default=False)
    try:
        futures = [
            client.submit(reprocess_device_day, db_url, job, engine, out_dir, config, pure=False)
            for job in jobs
        ]
        if on_done is not None:
            for _ in as_completed(futures):
                on_done()
        out: list[dict[str, Any] | BaseException] = []
        for fut in futures:
            try:
                out.append(fut.result())
            except Exception as exc:  # KilledWorker, a database error, ...
                out.append(exc)
        return out
    finally:
        client.close()
        if cluster is not None:
            cluster.close()
