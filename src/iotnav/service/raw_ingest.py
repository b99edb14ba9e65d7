"""Live IMU fusion of raw GNSS + IMU batches (:mod:`iotnav.service.protocols.iotnav_raw`).

:meth:`RawProcessor.ingest` stores one batch in one transaction (:meth:`~RawProcessor.ingest_many`
several, in order, with one commit: the MQTT subscriber passes those waiting in its queue), as
:meth:`~iotnav.service.ingest.Ingestor.ingest` does for fixes: the message as received in
``raw_messages`` (protocol ``iotnav_raw``, de-duplicated by device and bytes; append-only,
so a device-day can be re-run offline, :func:`raw_log`), its fixes as positions flagged
``engine = 'none'``, the clean positions of the device's IMU engine (``engine`` = its name),
its events and its checkpoint. The transport acknowledges (MQTT PUBACK) only after commit.

Engine per device: the device's ``attributes.engine`` (set through ``PUT /api/devices``),
else the first pattern of :attr:`RawSettings.engines` (``fnmatch`` on the unique id, e.g.
``"truck-*" = "eskf"``: a group) that matches, else :attr:`RawSettings.engine` (``pipeline``,
Forno et al.'s IMU + GNSS pipeline). The choice is made when the device's state is loaded.

Feeding: the samples of a batch are merged in time order, at equal times GNSS, then
magnetometer, then IMU (the order of :func:`iotnav.engines.base.run_batch`), and passed one
by one to the engine's ``step()``, the same call ``iotnav run`` loops over: the same samples
give the same outputs, bit for bit (``tests/test_service_raw_serve.py``). A sample earlier
than the last one of its stream fed to the device's engine (a batch resent out of order) is
not fed and is counted (``raw_imu_time_backwards``, ...); the batch is still stored.

Output rate: an engine gives one output per IMU sample (100 Hz); the database gets the first
output at or after each fix and one on every multiple of :attr:`RawSettings.output_interval_s`
of device time (1 s: fix times + 1 Hz); ``0`` stores every output.

Checkpoints: the device's state (:class:`RawDeviceState`: the engine, the last time fed per
stream, the output schedule) goes to ``engine_states`` (``engine`` = the engine's name) in the
transaction of the batch, with the HMAC and format check of :mod:`iotnav.service.checkpoint`,
so a restart resumes the filter where the last committed batch left it.
"""

from __future__ import annotations

import fnmatch
import hashlib
import json
import logging
import math
import struct
import time
from collections import OrderedDict
from collections.abc import Iterator, Sequence
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

import numpy as np
import numpy.typing as npt
import sqlalchemy as sa
from sqlalchemy.engine import Connection

from iotnav.service import checkpoint
from iotnav.service.checkpoint import CheckpointError, DeviceState
from iotnav.service.ingest import (
    NO_ENGINE,
    Ingestor,
    IngestResult,
    Message,
    checkpoint_discarded_event,
    clean_json,
    group_commit,
)
from iotnav.service.ingest_rows import _position_values, output_position_row
from iotnav.service.protocols.common import record_key
from iotnav.service.protocols.iotnav_raw import PROTOCOL, GnssRecord, RawBatch
from iotnav.service.store import devices, engine_states, events, raw_messages

if TYPE_CHECKING:
    from iotnav.engines.base import Engine as NavEngine
    from iotnav.engines.base import Output, OutputBlock, Sample
    from iotnav.io.log import Log

log = logging.getLogger("iotnav.service.raw")


@dataclass(frozen=True)
class RawSettings:
    """Engines and output rate of raw IMU devices.

    Attributes
    ----------
    engine : str
        Engine of IMU devices (``pipeline``: Forno et al.'s pipeline, the default).
    engine_config : str
        TOML configuration of ``engine`` (empty: its defaults).
    engines : dict
        ``fnmatch`` pattern of device unique ids -> engine, as ``name`` or
        ``name:config.toml``; the first match wins (a device's ``attributes.engine`` first).
    output_interval_s : float
        Clean positions stored: at each fix and every this many seconds of device time; 0:
        every engine output.
    max_devices_in_memory : int
        Device states kept in memory; the least recently used are reloaded from checkpoints.
    """

    engine: str = "pipeline"
    engine_config: str = ""
    engines: dict[str, str] = field(default_factory=dict)
    output_interval_s: float = 1.0
    max_devices_in_memory: int = 10_000

    def __post_init__(self) -> None:
        if not self.output_interval_s >= 0.0:
            raise ValueError(f"raw output_interval_s {self.output_interval_s}: expected >= 0 s")
        from iotnav.engines.registry import ENGINE_NAMES

        for spec in (self.engine, *self.engines.values()):
            name = spec.partition(":")[0]
            if name not in ENGINE_NAMES:
                raise ValueError(f"raw engine {name!r}: expected one of {', '.join(ENGINE_NAMES)}")

    def choose(self, unique_id: str, attributes: dict[str, Any] | None) -> tuple[str, str | None]:
        """Engine name and configuration file of the device ``unique_id``."""
        spec = (attributes or {}).get("engine")
        if not isinstance(spec, str) or not spec:
            spec = next((v for k, v in self.engines.items() if fnmatch.fnmatchcase(unique_id, k)), "")
        if not spec:
            return self.engine, self.engine_config or None
        name, _, cfg = spec.partition(":")
        return name, cfg or None


@dataclass
class RawDeviceState(DeviceState):
    """:class:`~iotnav.service.checkpoint.DeviceState` of a raw IMU device.

    ``last_t`` is the last IMU time fed (s, device time); ``t_gnss`` and ``t_mag`` those of
    the other streams; ``next_out`` the device time of the next scheduled output, s;
    ``want_out`` set after a fix (the next output is stored); ``engine_name``, ``config`` the
    engine in use.
    """

    t_gnss: float = -math.inf
    t_mag: float = -math.inf
    next_out: float = -math.inf
    want_out: bool = False
    engine_name: str = ""
    config: str | None = None


def _gnss_sample(g: GnssRecord, utc_offset_s: float) -> Sample:
    from iotnav.engines.base import GnssSample

    course_ok = math.isfinite(g.course_rad) and math.isfinite(g.speed_mps)
    return GnssSample(
        t=g.t,
        lat_deg=g.lat_deg,
        lon_deg=g.lon_deg,
        height_m=g.height_m,
        pdop=g.pdop,
        hdop=g.hdop,
        num_sv=g.num_sv,
        speed_mps=g.speed_mps,
        course_rad=g.course_rad if course_ok else math.nan,
        course_valid=course_ok,
        valid=g.valid,
        h_acc_m=g.h_acc_m,
        v_acc_m=g.v_acc_m,
        quality=g.quality,
        utc=g.t + utc_offset_s,
    )


def _readonly(a: npt.NDArray[np.float64]) -> npt.NDArray[np.float64]:
    """A read-only contiguous copy (the kind of column :func:`~iotnav.engines.base.run_batch` passes,
    so the kernel compiled for batch runs, not a second specialisation)."""
    c = np.ascontiguousarray(a, dtype=np.float64)
    c.flags.writeable = False
    return c


def _feed(
    eng: NavEngine,
    imu: npt.NDArray[np.float64],
    mag: npt.NDArray[np.float64],
    gnss: list[GnssRecord],
    off: float,
) -> tuple[OutputBlock, npt.NDArray[np.intp]]:
    """Run ``eng`` over the samples in time order (ties: GNSS, magnetometer, IMU); outputs per IMU sample.

    As :func:`iotnav.engines.base.run_batch` does: an engine with a compiled ``imu_block`` gets
    the IMU samples between two other samples in one call (the kernel its ``step()`` runs),
    others get ``step()`` per sample. Returns the output block (row ``k`` for IMU sample ``k``)
    and, per fix, the index of the first IMU sample fed after it.
    """
    from iotnav.engines.base import IMU_GAP_S, ImuSample, MagSample, OutputBlock, output_without_position

    n = len(imu)
    t_imu = _readonly(imu[:, 0])
    other_t = np.array([g.t for g in gnss] + mag[:, 0].tolist())
    other_kind = np.concatenate([np.zeros(len(gnss), np.intp), np.ones(len(mag), np.intp)])
    order = np.lexsort((other_kind, other_t))
    cuts = np.searchsorted(t_imu, other_t[order], side="left")
    out = OutputBlock(n)
    block = getattr(eng, "imu_block", None)
    guard = getattr(eng, "guard", None)
    if block is not None and n and guard is not None and t_imu[0] < guard.t_imu:
        block = None  # step() checks each sample
    if block is not None:
        acc = tuple(_readonly(imu[:, c]) for c in (1, 2, 3))
        gyro = tuple(_readonly(imu[:, c]) for c in (4, 5, 6))
        if guard is not None and n:  # the block bypasses admit(): count its gaps (as run_batch)
            gaps = int((np.diff(t_imu) > IMU_GAP_S).sum())
            gaps += int(t_imu[0] - guard.t_imu > IMU_GAP_S and guard.t_imu > -math.inf)
            if gaps:
                guard.skip("imu_gap", float(t_imu[0]), n=gaps)

    def run_imu(i0: int, i1: int) -> None:
        if i1 <= i0:
            return
        if block is not None:
            block(t_imu, acc, gyro, out, i0, i1)
            out.n = i1
            return
        for i in range(i0, i1):
            o = eng.step(ImuSample(float(t_imu[i]), imu[i, 1:4].copy(), imu[i, 4:7].copy()))
            if o is None:  # rejected by the engine's guard: a row without a position
                o = output_without_position(float(t_imu[i]), (0.0, 0.0, 0.0), False)
            out.add(o)

    i = 0
    fix_at = []
    for j, c in zip(order.tolist(), cuts.tolist(), strict=True):
        run_imu(i, c)
        i = max(i, c)
        if other_kind[j] == 0:
            eng.step(_gnss_sample(gnss[j], off))
            fix_at.append(i)
        else:
            r = mag[j - len(gnss)]
            eng.step(MagSample(float(r[0]), r[1:4].copy()))
    run_imu(i, n)
    if block is not None and guard is not None and n:
        guard.t_imu = float(t_imu[-1])
    return out, np.array(fix_at, np.intp)


class RawProcessor:
    """Stores raw batches and runs each device's IMU engine on them (module docstring).

    Parameters
    ----------
    ingestor : Ingestor
        The service's ingestor (its database, device registration, counters, listeners).
    settings : RawSettings
        Engines and output rate.
    """

    def __init__(self, ingestor: Ingestor, settings: RawSettings | None = None) -> None:
        self.ingestor = ingestor
        self.settings = settings or RawSettings()
        self._devices: OrderedDict[int, RawDeviceState] = OrderedDict()

    def warm_up(self) -> float:
        """Run the default engine on a fix and two IMU samples, as a batch is fed (loads or compiles
        its kernels before the first device waits on them); seconds taken."""
        t0 = time.perf_counter()
        eng = self._new_engine(self.settings.engine, self.settings.engine_config or None)
        imu = np.array([[1e9, 0.0, 0.0, 9.81, 0.0, 0.0, 0.0], [1e9 + 0.01, 0.0, 0.0, 9.81, 0.0, 0.0, 0.0]])
        _feed(eng, imu, np.empty((0, 4)), [GnssRecord(1e9, 0.5, 0.5, 0.0, 5.0)], 0.0)
        return time.perf_counter() - t0

    @staticmethod
    def _new_engine(name: str, config: str | None) -> NavEngine:
        from iotnav.engines.registry import make_engine

        return make_engine(name, config)

    # --- the transaction ------------------------------------------------------------------

    def ingest(
        self, payload: bytes, batch: RawBatch, remote: str | None = None, received_at: float | None = None
    ) -> IngestResult:
        """Store one batch and what its device's engine makes of it, in one transaction."""
        return self.ingest_many([(payload, batch, remote)], received_at)[0]

    def ingest_many(
        self,
        items: list[tuple[bytes, RawBatch, str | None]],
        received_at: float | Sequence[float] | None = None,
    ) -> list[IngestResult]:
        """Store several ``(payload, batch, remote)`` in order, in one transaction (one commit).

        What :meth:`ingest` does for each; the MQTT subscriber hands over the raw batches
        waiting in its queue together, so that a hundred devices do not cost a hundred
        ``fsync`` a second. ``received_at``: server time of arrival (s since 1970 UTC) of all
        of them or of each; None: now. Nothing is stored when the transaction fails. On a
        worker with alerts (:class:`iotnav.service.workers.AlertingIngestor`) the clean
        positions go through its rules in the same transaction, as its fixes do.
        """
        ing = self.ingestor
        now = time.time() if received_at is None else received_at
        times = [now] * len(items) if isinstance(now, float | int) else [float(t) for t in now]
        touched: set[int] = set()
        results: list[IngestResult] = []
        done: list[tuple[RawBatch, int, list[dict[str, Any]]]] = []
        # a worker's alert rules (iotnav.service.workers.AlertingIngestor): in this transaction
        alerts = getattr(ing, "alerts", None)
        msgs = [Message(PROTOCOL, b.device or "", p, [], r) for p, b, r in items]
        try:
            with ing.db.begin() as conn:
                floors = alerts.floors(conn, msgs) if alerts is not None else None
                for (payload, batch, remote), t in zip(items, times, strict=True):
                    res, rows = self._store(conn, payload, batch, remote, t, touched)
                    results.append(res)
                    if res.accepted and not res.duplicate:
                        done.append((batch, res.n_new, rows))
                if alerts is not None:
                    alerts.evaluate(conn, msgs, floors, time.time(), [(PROTOCOL, r) for _, _, r in done])
        except BaseException:  # not committed: the states are reloaded from their committed checkpoints
            for dev in touched:
                self._devices.pop(dev, None)
            if alerts is not None:
                alerts.rolled_back()
            raise
        if alerts is not None:
            alerts.committed()
        for dev in touched:
            self._devices.move_to_end(dev)
        while len(self._devices) > max(1, self.settings.max_devices_in_memory):
            self._devices.popitem(last=False)
        for batch, n_new, rows in done:
            for reason, n in batch.skipped.items():
                ing.count(f"raw_{reason}", n)
            ing.count("records", n_new)
            ing.count("raw_imu_samples", len(batch.imu))
            ing._notify(PROTOCOL, rows)
        return results

    def ingest_messages(self, msgs: Sequence[Message]) -> list[IngestResult | Exception]:
        """Store raw batches that came through JetStream (:mod:`iotnav.service.workers`: the
        payload as the edge received it, its topic as ``remote``) in one transaction; the
        result of each, or its error, as :meth:`Ingestor.ingest_batch` gives them.

        A payload that does not decode fails alone (ValueError); when the transaction fails
        and the database is reachable (not ``OperationalError``), each batch is stored in a
        transaction of its own, so one bad batch fails alone. Runs on the database thread.
        """
        from iotnav.service.protocols.iotnav_raw import decode

        out: list[IngestResult | Exception | None] = []
        items: list[tuple[bytes, RawBatch, str | None, float]] = []
        for m in msgs:
            b = decode(m.payload, m.device)
            if isinstance(b, RawBatch):
                out.append(None)
                items.append((m.payload, b, m.remote, m.received_at))
            else:
                out.append(ValueError(f"raw batch of {m.device!r} rejected: {b.reason} ({b.detail})"))
        done = group_commit(
            items,
            lambda xs: self.ingest_many([(p, b, r) for p, b, r, _ in xs], [t for *_, t in xs]),
            name=lambda x: f"{PROTOCOL} {x[1].device}",
        )
        it = iter(done)
        return [next(it) if r is None else r for r in out]

    def _store(
        self,
        conn: Connection,
        payload: bytes,
        batch: RawBatch,
        remote: str | None,
        now: float,
        touched: set[int],
    ) -> tuple[IngestResult, list[dict[str, Any]]]:
        """One batch inside the caller's transaction: the result and the clean rows stored."""
        ing = self.ingestor
        device = batch.device or ""
        digest = hashlib.sha256(device.encode("utf-8", "replace") + b"\x00" + payload).digest()
        dev = ing.device_id(conn, device, PROTOCOL, now)
        if dev is None:
            ing.count("device_refused")
            return IngestResult(accepted=False), []
        # the hot statements through the driver's cursor, as the fixes' ingest does (one
        # INSERT ... ON CONFLICT DO NOTHING RETURNING: no row back for a batch stored before)
        cur = conn.connection.cursor()
        cur.execute(
            ing._sql_raw.format(values=ing._raw_values),
            (dev, PROTOCOL, now, remote, payload, digest, batch.n_samples),
        )
        got = cur.fetchall()
        if not got:
            cur.close()
            ing.count("duplicate_message")
            return IngestResult(accepted=True, duplicate=True, device_id=dev), []
        raw_id = int(got[0][0])
        new = ing._new_fixes(conn, dev, batch.fixes())
        if new:
            cur.executemany(
                ing._sql_positions, [ing._row_values(dev, raw_id, NO_ENGINE, f, now, False)[1] for f in new]
            )
        fresh = {f.key for f in new}
        gnss = [g for g, k in zip(batch.gnss, batch.keys, strict=True) if k in fresh]
        touched.add(dev)
        st = self._state(conn, dev, device, now)
        rows = self._process(conn, dev, raw_id, st, batch, gnss, now)
        cur.execute(ing._sql_last_update, (now, dev))
        cur.close()
        return IngestResult(accepted=True, n_new=len(new), n_engine=len(rows), device_id=dev), rows

    def _state(self, conn: Connection, dev: int, unique_id: str, now: float) -> RawDeviceState:
        """The state of ``dev``: in memory, else its checkpoint, else a fresh one."""
        st = self._devices.get(dev)
        if st is not None and st.unique_id == unique_id:
            return st
        attrs = conn.execute(sa.select(devices.c.attributes).where(devices.c.id == dev)).scalar()
        name, cfg = self.settings.choose(unique_id, attrs if isinstance(attrs, dict) else None)
        fmt = checkpoint.format_tag(name, cfg)
        row = conn.execute(
            sa.select(engine_states.c.format, engine_states.c.state).where(
                engine_states.c.device_id == dev, engine_states.c.engine == name
            )
        ).first()
        st = None
        if row is not None:
            try:
                if row.format != fmt:
                    raise CheckpointError(f"checkpoint format {row.format!r}, this service {fmt!r}")
                loaded = checkpoint.loads(bytes(row.state), self.ingestor._key)
                if not isinstance(loaded, RawDeviceState):
                    raise CheckpointError("checkpoint of another kind of device")
                st = loaded
                self.ingestor.count("checkpoint_restored")
            except CheckpointError as exc:
                self.ingestor.count("checkpoint_discarded")
                log.warning("device %d: %s; its engine starts afresh", dev, exc)
                checkpoint_discarded_event(conn, dev, now, exc)
        if st is None:
            st = RawDeviceState(engine_name=name, config=cfg)
        st.unique_id = unique_id
        self._devices[dev] = st
        return st

    def _process(
        self,
        conn: Connection,
        dev: int,
        raw_id: int,
        st: RawDeviceState,
        batch: RawBatch,
        gnss: list[GnssRecord],
        now: float,
    ) -> list[dict[str, Any]]:
        """Feed the batch to the device's engine; store the scheduled outputs, events, checkpoint."""
        ing = self.ingestor
        evs: list[dict[str, Any]] = []
        if st.engine is None:
            st.engine, st.n_events = self._new_engine(st.engine_name, st.config), 0
            if hasattr(st.engine, "utc_offset_s"):
                setattr(st.engine, "utc_offset_s", batch.utc_offset_s)  # noqa: B010
        eng = st.engine
        imu, mag = batch.imu, batch.mag
        # what an earlier batch already fed is not fed again (equal times pass, as in InputGuard)
        for name, last, n_before in (
            ("imu", st.last_t, len(imu)),
            ("mag", st.t_mag, len(mag)),
            ("gnss", st.t_gnss, len(gnss)),
        ):
            if name == "imu":
                imu = imu[imu[:, 0] >= last]
                n_after = len(imu)
            elif name == "mag":
                mag = mag[mag[:, 0] >= last]
                n_after = len(mag)
            else:
                gnss = [g for g in gnss if g.t >= last]
                n_after = len(gnss)
            if n_after < n_before:
                ing.count(f"raw_{name}_time_backwards", n_before - n_after)
        try:
            out, fix_at = _feed(eng, imu, mag, gnss, batch.utc_offset_s)
        except Exception as exc:  # an engine bug must not block the device's stream
            ing.count("engine_error")
            log.exception("engine %s, device %d: step failed; the engine restarts", st.engine_name, dev)
            evs.append({"type": "engine_error", "event_time": now, "attributes": {"error": repr(exc)[:200]}})
            st.engine, out, fix_at = None, None, np.empty(0, np.intp)
        rows = []
        if out is not None and len(imu):
            st.last_t = float(imu[-1, 0])
            rows = self._scheduled(dev, raw_id, st, batch, out, fix_at, now)
        if len(mag):
            st.t_mag = float(mag[-1, 0])
        if gnss:
            st.t_gnss = gnss[-1].t
            st.want_out = st.want_out or (fix_at.size > 0 and int(fix_at[-1]) >= len(imu))
        if st.engine is not None:
            ing._drain_events(st, st.engine, now, evs)
        if rows:
            cur = conn.connection.cursor()
            cur.executemany(
                ing._sql_positions, [_position_values(r, json.dumps(r["attributes"])) for r in rows]
            )
            cur.close()
        if evs:
            conn.execute(events.insert(), [{**e, "device_id": dev, "server_time": now} for e in evs])
        values = {
            "saved_at": now,
            "last_t": st.last_t + batch.utc_offset_s if math.isfinite(st.last_t) else None,
            "format": checkpoint.format_tag(st.engine_name, st.config),
            "state": checkpoint.dumps(st, ing._key),
        }
        where = (engine_states.c.device_id == dev) & (engine_states.c.engine == st.engine_name)
        if not conn.execute(engine_states.update().where(where).values(**values)).rowcount:
            conn.execute(engine_states.insert().values(device_id=dev, engine=st.engine_name, **values))
        return rows

    def _scheduled(
        self,
        dev: int,
        raw_id: int,
        st: RawDeviceState,
        batch: RawBatch,
        out: OutputBlock,
        fix_at: npt.NDArray[np.intp],
        now: float,
    ) -> list[dict[str, Any]]:
        """Rows of the outputs due: the first usable one at or after each fix, one per interval."""
        from iotnav.engines.base import C_LAT, C_LON, C_T, SRC_NONE

        interval = self.settings.output_interval_s
        f = out.floats
        t, lat, lon = f[C_T, : out.n], f[C_LAT, : out.n], f[C_LON, : out.n]
        usable = np.isfinite(lat + lon) & (out.source[: out.n] != SRC_NONE)
        wanted = np.zeros(out.n + 1, bool)
        wanted[np.minimum(fix_at, out.n)] = True
        rows = []
        for k in range(out.n):
            st.want_out = st.want_out or bool(wanted[k])
            if not usable[k]:
                continue
            if st.want_out or interval == 0.0 or t[k] >= st.next_out:
                rows.append(self._output_row(dev, raw_id, st, batch, out.row(k), now))
                st.want_out = False
                if interval > 0.0:
                    st.next_out = (math.floor(t[k] / interval) + 1.0) * interval
        return rows

    @staticmethod
    def _output_row(
        dev: int, raw_id: int, st: RawDeviceState, batch: RawBatch, out: Output, now: float
    ) -> dict[str, Any]:
        """A positions row of an engine output (fix time = device time + UTC offset)."""
        attributes = clean_json(
            {"source": out.source, "static": bool(out.static), "t_device": out.t, "yaw": out.yaw}
        )
        key = record_key(st.unique_id, struct.pack("<d", out.t))
        return output_position_row(
            dev, raw_id, st.engine_name, out.t + batch.utc_offset_s, out, now, attributes, key
        )


def raw_log(db: sa.engine.Engine, unique_id: str, t_from: float = -math.inf, t_to: float = math.inf) -> Log:
    """A device's stored raw batches (received in ``[t_from, t_to]``, server time) as a :class:`~iotnav.io.log.Log`.

    What :func:`iotnav.engines.base.run_batch` (``iotnav run``) takes: the same samples the
    service fed, so a device-day can be re-run offline with any engine.
    """
    import pandas as pd

    from iotnav.io.log import Log
    from iotnav.io.schema import GNSS_COLUMNS, IMU_COLUMNS, MAG_COLUMNS, coerce, empty_table
    from iotnav.service.protocols.iotnav_raw import decode

    q = (
        sa.select(raw_messages.c.payload)
        .join(devices, devices.c.id == raw_messages.c.device_id)
        .where(
            devices.c.unique_id == unique_id,
            raw_messages.c.protocol == PROTOCOL,
            raw_messages.c.received_at >= t_from,
            raw_messages.c.received_at <= t_to,
        )
        .order_by(raw_messages.c.id)
    )
    imu: list[npt.NDArray[np.float64]] = []
    mag: list[npt.NDArray[np.float64]] = []
    gnss: list[GnssRecord] = []
    offset = math.nan
    seen: set[str] = set()
    with db.connect() as conn:
        for (payload,) in conn.execute(q):
            b = decode(bytes(payload), unique_id)
            if isinstance(b, RawBatch):
                imu.append(b.imu)
                mag.append(b.mag)
                gnss.extend(g for g, k in zip(b.gnss, b.keys, strict=True) if k not in seen)
                seen.update(b.keys)
                offset = b.utc_offset_s if math.isnan(offset) else offset
    off = 0.0 if math.isnan(offset) else offset
    # what the service did not feed (earlier than its stream's last sample) is left out too
    imu_a, mag_a = (np.concatenate(x) if x else np.empty((0, w)) for x, w in ((imu, 7), (mag, 4)))
    imu_a, mag_a = (a[a[:, 0] >= np.maximum.accumulate(a[:, 0])] if len(a) else a for a in (imu_a, mag_a))
    g_t = np.array([g.t for g in gnss])
    gnss = [g for g, ok in zip(gnss, g_t >= np.maximum.accumulate(g_t) if gnss else [], strict=True) if ok]
    imu_df = pd.DataFrame(imu_a, columns=list(IMU_COLUMNS))
    mag_df = pd.DataFrame(mag_a, columns=list(MAG_COLUMNS))
    g = pd.DataFrame([s._asdict() for s in (_gnss_sample(r, off) for r in gnss)]) if gnss else None
    gnss_df = coerce(g, GNSS_COLUMNS) if g is not None else empty_table(GNSS_COLUMNS)
    return Log(
        gnss=gnss_df, imu=coerce(imu_df, IMU_COLUMNS), mag=coerce(mag_df, MAG_COLUMNS), utc_offset_s=off
    )


_GNSS_JSON = {
    "t": "t",
    "lat_deg": "lat",
    "lon_deg": "lon",
    "height_m": "alt",
    "h_acc_m": "acc",
    "v_acc_m": "vacc",
    "speed_mps": "speed",
    "hdop": "hdop",
    "pdop": "pdop",
}


def log_batches(log: Log, batch_s: float = 1.0) -> Iterator[bytes]:
    """A log as JSON raw batches of ``batch_s`` seconds of device time (the inverse of :func:`raw_log`).

    Batch ``k`` holds the samples with ``t0 + k batch_s <= t < t0 + (k + 1) batch_s``, so a
    fix travels with the IMU samples from its time on. A course flagged invalid is left out.
    What a device or a gateway replaying a recorded log sends.
    """
    from iotnav.service.protocols.iotnav_raw import encode_json

    g, imu, mag = log.gnss, log.imu, log.mag
    imu_a = imu[list(IMU_ROW)].to_numpy(float) if len(imu) else np.empty((0, 7))
    mag_a = mag[["t", "mag_x_ut", "mag_y_ut", "mag_z_ut"]].to_numpy(float) if len(mag) else np.empty((0, 4))
    times = np.concatenate([g["t"].to_numpy(float), imu_a[:, 0], mag_a[:, 0]])
    if times.size == 0:
        return
    t0, t1 = float(times.min()), float(times.max())
    fixes = []
    records: list[dict[str, Any]] = g.to_dict("records")  # type: ignore[assignment]
    for r in records:
        d = {v: float(r[k]) for k, v in _GNSS_JSON.items()}
        if r["course_valid"] and math.isfinite(r["course_rad"]):
            d["course"] = float(r["course_rad"])
        d.update(nsat=int(r["num_sv"]), quality=int(r["quality"]), valid=bool(r["valid"]))
        fixes.append(
            {k: (None if isinstance(v, float) and not math.isfinite(v) else v) for k, v in d.items()}
        )
    g_t = g["t"].to_numpy(float)
    off = log.utc_offset_s if math.isfinite(log.utc_offset_s) else 0.0
    for k in range(int((t1 - t0) // batch_s) + 1):
        lo, hi = t0 + k * batch_s, t0 + (k + 1) * batch_s

        def cut(t: np.ndarray, lo: float = lo, hi: float = hi) -> np.ndarray:
            return (t >= lo) & (t < hi)

        sel = np.flatnonzero(cut(g_t))
        yield encode_json(
            imu_a[cut(imu_a[:, 0])],
            [fixes[i] for i in sel.tolist()],
            mag_a[cut(mag_a[:, 0])] if len(mag_a) else None,
            utc_offset_s=off,
        )


IMU_ROW = ("t", "acc_x", "acc_y", "acc_z", "gyro_x", "gyro_y", "gyro_z")
