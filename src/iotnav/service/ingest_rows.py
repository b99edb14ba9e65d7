"""The positions rows of the ingest: de-duplication of records, rows of fixes and engine outputs.

Moved out of :mod:`iotnav.service.ingest` unchanged (which re-exports the public names):
:func:`clean_json`, the per-device cache of recent record keys ``_RecentKeys``, the columns
and INSERT parameters of a positions row, :func:`fix_of_row` (the fix a stored row was made
from, for a replay), and :class:`IngestRows`, the methods of
:class:`~iotnav.service.ingest.Ingestor` that de-duplicate a message's fixes and build the
rows of fixes as sent (``engine = 'none'``) and of engine outputs. The design is in
:mod:`iotnav.service.ingest`'s docstring.
"""

from __future__ import annotations

import json
import math
import operator
from collections import OrderedDict
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

import sqlalchemy as sa
from sqlalchemy.engine import Connection

from iotnav.service.ingest_messages import NO_ENGINE
from iotnav.service.protocols.common import Fix
from iotnav.service.store import positions

if TYPE_CHECKING:
    from iotnav.engines.base import Output

__all__ = ["IngestRows", "clean_json", "fix_of_row"]


def clean_json(v: Any) -> Any:
    """``v`` with every non-finite float replaced by None (strict JSON)."""
    if isinstance(v, float):
        return v if math.isfinite(v) else None
    if isinstance(v, dict):
        return {str(k): clean_json(x) for k, x in v.items()}
    if isinstance(v, list | tuple):
        return [clean_json(x) for x in v]
    return v


def _none_if_nan(x: float) -> float | None:
    return x if math.isfinite(x) else None


@dataclass
class _RecentKeys:
    """The recent record keys of one device: every stored key of the device whose fix time is
    after ``horizon`` (s) is in ``keys`` (key -> fix time), so a fix newer than the horizon and
    not in ``keys`` is new without a query."""

    horizon: float
    keys: dict[str, float] = field(default_factory=dict)

    def add(self, key: str, t: float, bound: int) -> None:
        self.keys[key] = t
        while len(self.keys) > bound:  # forget the oldest key; the horizon moves past its time
            old = next(iter(self.keys))
            self.horizon = max(self.horizon, self.keys.pop(old))


_POSITION_COLUMNS = tuple(c.name for c in positions.columns if c.name != "id")


_position_tuple = operator.itemgetter(*_POSITION_COLUMNS)
_RAW_ID = _POSITION_COLUMNS.index("raw_id")
_ATTRIBUTES = _POSITION_COLUMNS.index("attributes")


def _position_values(row: dict[str, Any], attributes_json: str) -> tuple[Any, ...]:
    """The parameters of :data:`_POSITION_COLUMNS` of a positions row, its attributes as the JSON
    text ``attributes_json``."""
    values = _position_tuple(row)
    return (*values[:_ATTRIBUTES], attributes_json, *values[_ATTRIBUTES + 1 :])


def _strict_json(attrs: dict[str, Any]) -> tuple[dict[str, Any], str]:
    """``attrs`` as strict JSON (non-finite floats replaced by None) and its JSON text.

    Serialised once: the text of the usual case (every float finite) has no ``NaN`` or
    ``Infinity`` token; when it has one (also when a string merely contains it) the attributes
    are cleaned (:func:`clean_json`) and serialised again.
    """
    text = json.dumps(attrs)
    if "NaN" in text or "Infinity" in text:
        attrs = clean_json(attrs)
        text = json.dumps(attrs)
    return attrs, text


def fix_of_row(unique_id: str, r: Any) -> Fix:
    """The :class:`Fix` a stored ``engine = 'none'`` position was made from (for a replay)."""
    attrs = r.attributes or {}
    num_sv = attrs.get("num_sv")
    hdop = attrs.get("hdop")
    return Fix(
        device=unique_id,
        t=float(r.fix_time),
        lat_deg=float(r.latitude),
        lon_deg=float(r.longitude),
        height_m=math.nan if r.altitude is None else float(r.altitude),
        speed_mps=math.nan if r.speed_mps is None else float(r.speed_mps),
        course_rad=math.nan if r.course_rad is None else float(r.course_rad),
        h_acc_m=math.nan if r.accuracy_m is None else float(r.accuracy_m),
        num_sv=int(num_sv) if isinstance(num_sv, int) and not isinstance(num_sv, bool) else -1,
        hdop=float(hdop) if isinstance(hdop, int | float) and not isinstance(hdop, bool) else math.nan,
        valid=bool(r.valid),
        attributes=attrs,
        key=r.dedup_key,
    )


class IngestRows:
    """De-duplication of a message's fixes and the positions rows (mixed into ``Ingestor``).

    Attributes read (set by :class:`~iotnav.service.ingest.Ingestor`): ``engine_name`` (the
    engine in use), ``max_devices_in_memory``, ``_recent`` (device id -> its recent record
    keys, least recently used first), ``_created`` (devices created for the open batch) and
    ``_output_json`` (the attributes texts of engine rows, cached).
    """

    engine_name: str
    max_devices_in_memory: int
    _recent: OrderedDict[int, _RecentKeys]
    _created: set[int]
    _output_json: dict[tuple[str, bool], str]

    #: Recent record keys kept per device (the de-duplication cache).
    RECENT_KEYS = 128

    if TYPE_CHECKING:  # defined by Ingestor

        def _count_on_commit(self, what: str, n: int = 1) -> None: ...

    def _recent_of(self, conn: Connection, dev: int) -> _RecentKeys:
        """The recent-keys cache of ``dev`` (a new one's horizon: its newest stored fix time)."""
        rec = self._recent.get(dev)
        if rec is not None:
            self._recent.move_to_end(dev)
            return rec
        newest = None
        if dev not in self._created:
            newest = conn.execute(
                sa.select(sa.func.max(positions.c.fix_time)).where(
                    positions.c.device_id == dev, positions.c.engine == NO_ENGINE
                )
            ).scalar()
        rec = self._recent[dev] = _RecentKeys(-math.inf if newest is None else float(newest))
        while len(self._recent) > max(1, self.max_devices_in_memory):
            self._recent.popitem(last=False)
        return rec

    def _new_fixes(self, conn: Connection, dev: int, fixes: list[Fix]) -> list[Fix]:
        """The fixes of ``fixes`` not stored yet for ``dev`` (and not repeated within the message).

        A fix newer than the cache's horizon is new unless its key is in the cache; only older
        fixes not in the cache are looked up in the database.
        """
        rec = self._recent_of(conn, dev)
        doubt = [f.key for f in fixes if f.key not in rec.keys and f.t <= rec.horizon]
        seen: set[str] = set()
        for i in range(0, len(doubt), 500):
            seen.update(
                conn.execute(
                    sa.select(positions.c.dedup_key).where(
                        positions.c.device_id == dev,
                        positions.c.engine == NO_ENGINE,
                        positions.c.dedup_key.in_(doubt[i : i + 500]),
                    )
                ).scalars()
            )
        out = []
        for f in fixes:
            if f.key not in seen and f.key not in rec.keys:
                rec.add(f.key, f.t, self.RECENT_KEYS)
                out.append(f)
        if len(out) < len(fixes):
            self._count_on_commit("duplicate_record", len(fixes) - len(out))
        return out

    @classmethod
    def _row(
        cls, dev: int, raw_id: int | None, engine: str, f: Fix, now: float, late: bool
    ) -> dict[str, Any]:
        """A positions row of a fix as sent; ``late``: older than what the engine had seen (flagged).

        ``num_sv`` and ``hdop`` go to the attributes (with ``hdop`` also when the satellites
        are unknown): a replay rebuilds the fix from the row (:func:`fix_of_row`).
        """
        return cls._row_values(dev, raw_id, engine, f, now, late)[0]

    @staticmethod
    def _row_values(
        dev: int, raw_id: int | None, engine: str, f: Fix, now: float, late: bool
    ) -> tuple[dict[str, Any], tuple[Any, ...]]:
        """:meth:`_row` and its INSERT parameters (:data:`_POSITION_COLUMNS`; attributes serialised once)."""
        if f.num_sv >= 0:
            attrs = {**f.attributes, "num_sv": f.num_sv, "hdop": _none_if_nan(f.hdop)}
        else:
            attrs = dict(f.attributes)
            if math.isfinite(f.hdop):
                attrs["hdop"] = f.hdop
        if late:
            attrs["late"] = True
        attrs, text = _strict_json(attrs)
        row = {
            "device_id": dev,
            "raw_id": raw_id,
            "engine": engine,
            "fix_time": f.t,
            "server_time": now,
            "valid": bool(f.valid),
            "latitude": f.lat_deg,
            "longitude": f.lon_deg,
            "altitude": _none_if_nan(f.height_m),
            "speed_mps": _none_if_nan(f.speed_mps),
            "course_rad": _none_if_nan(f.course_rad),
            "accuracy_m": _none_if_nan(f.h_acc_m),
            "attributes": attrs,
            "dedup_key": f.key,
        }
        return row, _position_values(row, text)

    def _output_values(self, row: dict[str, Any]) -> tuple[Any, ...]:
        """The INSERT parameters of an engine row of :meth:`_output_row` (its few attribute texts cached)."""
        attrs = row["attributes"]
        key = (attrs["source"], attrs["static"])
        text = self._output_json.get(key)
        if text is None:
            text = self._output_json[key] = json.dumps(attrs)
        return _position_values(row, text)

    def _output_row(self, dev: int, raw_id: int, f: Fix, out: Output, now: float) -> dict[str, Any]:
        """A positions row of an engine output (:func:`output_position_row`), keyed by the fix."""
        attributes = {"source": str(out.source), "static": bool(out.static)}
        return output_position_row(dev, raw_id, self.engine_name, out.t, out, now, attributes, f.key)


def output_position_row(
    dev: int,
    raw_id: int,
    engine: str,
    fix_time: float,
    out: Output,
    now: float,
    attributes: dict[str, Any],
    dedup_key: str,
) -> dict[str, Any]:
    """A positions row of an engine output ``out`` of device ``dev``, stored from raw message ``raw_id``.

    ``fix_time`` Unix time of the row, s; ``now`` server time, s. Speed (m/s) and course (rad
    from North, in ``[0, 2 pi)``, None without a speed) from ``vn``, ``ve``; accuracy the 2D RMS
    radius ``sqrt(std_north**2 + std_east**2)``, m; NaN stored as None. ``dedup_key``: the row's
    de-duplication key (the fix's, or the device and output time's).
    """
    speed = math.hypot(out.vn, out.ve)
    course = math.atan2(out.ve, out.vn) % (2 * math.pi)
    std = math.hypot(out.std_north, out.std_east)
    return {
        "device_id": dev,
        "raw_id": raw_id,
        "engine": engine,
        "fix_time": fix_time,
        "server_time": now,
        "valid": True,
        "latitude": out.lat,
        "longitude": out.lon,
        "altitude": _none_if_nan(out.height),
        "speed_mps": _none_if_nan(speed),
        "course_rad": _none_if_nan(course) if math.isfinite(speed) else None,
        "accuracy_m": _none_if_nan(std),
        "attributes": attributes,
        "dedup_key": dedup_key,
    }
