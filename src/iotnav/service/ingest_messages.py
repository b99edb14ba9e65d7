"""What the ingest takes and gives: the decoded message, its result, group commit.

Moved out of :mod:`iotnav.service.ingest` unchanged (which re-exports every name here):
the engine names :data:`NO_ENGINE` and :data:`FIXES_ENGINE`, :class:`Message` (a decoded
message handed to the ingest), :class:`IngestResult`, :class:`ConcurrentWriteError`, the
prepared batch ``_Plan`` and :func:`group_commit` (one transaction for a batch, one each when
it fails). The design is in :mod:`iotnav.service.ingest`'s docstring.
"""

from __future__ import annotations

import hashlib
import logging
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any, TypeVar

import sqlalchemy as sa

from iotnav.service.protocols.common import Fix

__all__ = [
    "FIXES_ENGINE",
    "NO_ENGINE",
    "ConcurrentWriteError",
    "IngestResult",
    "Message",
    "group_commit",
]

log = logging.getLogger("iotnav.service")

NO_ENGINE = "none"
#: The engine of devices that send fixes only (every input of this version).
FIXES_ENGINE = "fixes"


@dataclass
class Message:
    """A decoded message handed to the ingest.

    Attributes
    ----------
    protocol : str
        Input protocol (``teltonika``, ``osmand``, ``owntracks``, ...).
    device : str
        The device's unique id.
    payload : bytes
        The message as received (stored append-only in ``raw_messages``).
    fixes : list of Fix
        Its decoded records.
    remote : str or None
        Peer address or MQTT topic.
    received_at : float
        Server time of arrival, s since 1970 UTC.
    unique : bool
        The message is new whatever its bytes (an OsmAnd request without a timestamp repeats
        its bytes for every report); otherwise the same device and bytes are a duplicate.
    """

    protocol: str
    device: str
    payload: bytes
    fixes: list[Fix]
    remote: str | None = None
    received_at: float = field(default_factory=time.time)
    unique: bool = False

    def dedup_key(self) -> bytes:
        """De-duplication key of the raw message: SHA-256 of device id and bytes, the 32-byte
        digest (``raw_messages.dedup_key``)."""
        salt = repr(self.received_at).encode() if self.unique else b""
        return hashlib.sha256(self.device.encode("utf-8", "replace") + b"\x00" + self.payload + salt).digest()

    def digest(self) -> str:
        """:meth:`dedup_key` as hex text (the ``Nats-Msg-Id`` of :mod:`iotnav.service.workers`)."""
        return self.dedup_key().hex()


@dataclass(frozen=True)
class IngestResult:
    """What :meth:`~iotnav.service.ingest.Ingestor.ingest` did.

    ``accepted`` False: unknown device while registration is closed, or the message refused
    for ``reason`` (nothing stored; empty: the unknown device); ``duplicate``: the same message was stored before; ``n_new``: positions newly stored
    (``engine = 'none'``); ``n_engine``: engine positions stored.
    """

    accepted: bool
    duplicate: bool = False
    n_new: int = 0
    n_engine: int = 0
    device_id: int | None = None
    reason: str = ""


class ConcurrentWriteError(RuntimeError):
    """A raw message read as new before the write transaction was stored meanwhile (by another
    writer of the same device: the one-process-per-device rule was broken)."""


@dataclass
class _Plan:
    """A batch prepared before its write transaction (:meth:`~iotnav.service.ingest.Ingestor._prepare`).

    The messages to store (``new``, indices in arrival order: the order of their raw ids,
    which is the order of a replay) have provisional raw ids ``-1 - index`` in ``values`` (the
    positions rows' INSERT parameters), in ``notify`` and in the device states; the write
    transaction replaces them by the stored ids (:meth:`~iotnav.service.ingest.Ingestor._store`).
    """

    results: list[IngestResult]
    devs: list[int | None]
    digests: list[bytes]
    new: list[int]
    values: list[tuple[Any, ...]]
    evs: list[dict[str, Any]]
    notify: list[tuple[str, list[dict[str, Any]]]]
    last_update: dict[int, float]


T = TypeVar("T")


def group_commit(
    items: Sequence[T],
    store: Callable[[Sequence[T]], list[IngestResult]],
    on_split: Callable[[], None] | None = None,
    name: Callable[[T], str] = str,
) -> list[IngestResult | Exception]:
    """``store(items)`` (one transaction: the group commit); the result of each item, or its error.

    When that fails it is rolled back and, unless the database is unreachable
    (``OperationalError``: every item fails with it), each item is stored by ``store([item])``
    in a transaction of its own, so one bad item fails alone (``on_split`` is called once
    then; ``name`` labels an item in the log). Shared by the messages' ingest
    (:meth:`~iotnav.service.ingest.Ingestor.ingest_batch`) and the workers' raw batches
    (:meth:`iotnav.service.raw_ingest.RawProcessor.ingest_messages`).
    """
    if not items:
        return []
    try:
        return list(store(items))
    except Exception as exc:
        if len(items) == 1 or isinstance(exc, sa.exc.OperationalError):
            return [exc] * len(items)
        log.warning("a batch of %d failed (%r); storing them one by one", len(items), exc)
        if on_split is not None:
            on_split()
    out: list[IngestResult | Exception] = []
    for item in items:
        try:
            out += store([item])
        except Exception as exc:
            log.warning("%s: storing failed: %r", name(item), exc)
            out.append(exc)
    return out
