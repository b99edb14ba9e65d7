"""The devices of the ingest: ids, registration, the cache of device rows.

Moved out of :mod:`iotnav.service.ingest` unchanged: :class:`IngestDevices`, the methods of
:class:`~iotnav.service.ingest.Ingestor` that find a message's device (by its unique id,
cached ``device_cache_s``), refuse a disabled or unknown one, and create the unknown ones
when registration is open. The design is in :mod:`iotnav.service.ingest`'s docstring.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import sqlalchemy as sa
from sqlalchemy.engine import Connection, Engine

from iotnav.service.ingest_messages import Message
from iotnav.service.store import devices, inserted_id

__all__ = ["IngestDevices"]


class IngestDevices:
    """Device ids, admission and registration (mixed into ``Ingestor``).

    Attributes read (set by :class:`~iotnav.service.ingest.Ingestor`): ``db``,
    ``registration_open``, ``device_cache_s`` (s), ``max_devices_in_memory``,
    ``_device_rows`` (unique id -> (device id or None when disabled, monotonic time read)),
    ``_created`` (devices created for the open batch) and the SQL text of the devices'
    multi-row INSERT (``_sql_devices``, ``_device_values``).
    """

    db: Engine
    registration_open: bool
    device_cache_s: float
    max_devices_in_memory: int
    _device_rows: dict[str, tuple[int | None, float]]
    _created: set[int]
    _sql_devices: str
    _device_values: str

    def device_id(self, conn: Connection, unique_id: str, protocol: str | None, now: float) -> int | None:
        """Id of the device ``unique_id``, created when registration is open; None if refused."""
        row = conn.execute(
            sa.select(devices.c.id, devices.c.disabled).where(devices.c.unique_id == unique_id)
        ).first()
        if row is not None:
            return None if row.disabled else int(row.id)
        return self._create_device(conn, unique_id, protocol, now) if self.registration_open else None

    @staticmethod
    def _create_device(conn: Connection, unique_id: str, protocol: str | None, now: float) -> int:
        """Insert the device ``unique_id`` (named after it); its id."""
        res = conn.execute(
            devices.insert().values(
                unique_id=unique_id, name=unique_id, protocol=protocol, created_at=now, attributes={}
            )
        )
        return inserted_id(res)

    def device_allowed(self, unique_id: str) -> bool:
        """True when ``unique_id`` is a known, enabled device or registration is open."""
        with self.db.connect() as conn:
            row = conn.execute(sa.select(devices.c.disabled).where(devices.c.unique_id == unique_id)).first()
        return (row is None and self.registration_open) or (row is not None and not row.disabled)

    def _create_missing(self, missing: Sequence[Message], clock: float) -> None:
        """Create the devices of ``missing`` (registration open), in a write transaction of their
        own committed before the batch's: a batch that fails after it leaves them registered,
        with nothing stored for them yet (as a first contact whose message failed)."""
        with self.db.begin() as conn:
            created = self._create_devices(conn, missing)
        for unique_id, dev in created.items():  # created now: nothing is stored for them yet
            self._device_rows[unique_id] = (dev, clock)
            self._created.add(dev)

    def _device_ids(self, msgs: Sequence[Message], clock: float) -> list[int | None]:
        """The device id of each message (None: refused) from the rows read since ``clock - device_cache_s``."""
        rows = self._device_rows
        out: list[int | None] = []
        for m in msgs:
            entry = rows.get(m.device)
            out.append(entry[0] if entry is not None and clock - entry[1] <= self.device_cache_s else None)
        return out

    def _read_devices(self, conn: Connection, msgs: Sequence[Message], clock: float) -> list[Message]:
        """Read the device rows of ``msgs`` not cached since ``clock - device_cache_s`` (monotonic
        s); the first message of each device not in the table."""
        rows = self._device_rows
        if len(rows) > 4 * max(self.max_devices_in_memory, 1000):
            rows.clear()
        stale = sorted(
            {m.device for m in msgs if clock - rows.get(m.device, (None, -math.inf))[1] > self.device_cache_s}
        )
        for i in range(0, len(stale), 500):
            for r in conn.execute(
                sa.select(devices.c.id, devices.c.unique_id, devices.c.disabled).where(
                    devices.c.unique_id.in_(stale[i : i + 500])
                )
            ):
                rows[r.unique_id] = (None if r.disabled else int(r.id), clock)
        missing: dict[str, Message] = {}  # not in the table: the first message of each
        for m in msgs:
            entry = rows.get(m.device)
            if entry is None or clock - entry[1] > self.device_cache_s:
                missing.setdefault(m.device, m)
        return list(missing.values())

    def _create_devices(self, conn: Connection, msgs: Sequence[Message]) -> dict[str, int]:
        """Insert the devices of ``msgs`` (one each, named after its unique id); unique id -> id.

        Multi-row ``INSERT ... RETURNING`` on the driver's cursor: a fleet's first contact
        (10,000 devices within seconds) costs one statement per 200 devices, not one each.
        """
        ids: dict[str, int] = {}
        cur = conn.connection.cursor()
        for b in range(0, len(msgs), 200):
            chunk = msgs[b : b + 200]
            sql = self._sql_devices.format(values=", ".join([self._device_values] * len(chunk)))
            cur.execute(
                sql, tuple(v for m in chunk for v in (m.device, m.device, m.protocol, m.received_at, "{}"))
            )
            for dev, unique_id in cur.fetchall():
                ids[unique_id] = int(dev)
        cur.close()
        if len(ids) != len(msgs):
            raise RuntimeError(f"{len(msgs)} devices inserted, {len(ids)} returned")
        return ids
