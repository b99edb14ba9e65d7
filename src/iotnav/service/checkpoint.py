"""Checkpoints of a device's processing state, so a restart resumes where it stopped.

What a device's processing holds (:class:`DeviceState`): its engine (for ``fixes``: the
filter state, NED origin, gate and relocation candidates, static detector and low-pass
levels, boot logic and input guard), the device time of the last fix fed to it, and the
fixes waiting in the re-ordering window, and the id of the last raw message it has processed.
:class:`~iotnav.service.ingest.Ingestor` writes it to the ``engine_states`` table in a
transaction that stores messages, every ``checkpoint_interval_s`` of unsaved changes (and at
shutdown), not with every message: after a restart (or a kill -9) a device's state is this
checkpoint with the fixes stored after its raw message fed again (a replay of the
append-only storage), which is the state of the last committed message; a message whose
transaction failed is processed again from that state when the device resends it.

Format: the :class:`DeviceState` pickled (the engines keep their state in numpy arrays and
plain objects; they are pickled already for the fleet's worker processes) and compressed
with zlib, behind an HMAC-SHA256 tag keyed by a secret of the data directory
(:func:`load_key`). A checkpoint whose tag does not verify (written by another installation
or altered in the database) or whose format string differs (another version of iotnav,
another engine configuration) is never unpickled: it is discarded, counted and reported as
an event, and the device's engine starts afresh. So whoever can write the database cannot
make the service run code of their choosing without also holding the key file.
"""

from __future__ import annotations

import hashlib
import hmac
import math
import os
import pickle
import secrets
import zlib
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import iotnav
from iotnav.service.protocols.common import Fix

#: File of the checkpoint key in the data directory (32 random bytes, mode 0600).
KEY_FILE = "checkpoint_key"
_TAG = 32  # bytes of an HMAC-SHA256 tag


class CheckpointError(ValueError):
    """A checkpoint that cannot be used (bad tag, other format, unreadable)."""


@dataclass
class DeviceState:
    """The processing state of one device.

    Attributes
    ----------
    engine : object or None
        The device's engine (None: made on the next fix, after an engine error).
    last_t : float
        Device time of the last fix fed to the engine, s since 1970 (``-inf``: none yet).
    newest : float
        Newest fix time received, s (the re-ordering window ends here).
    pending : list
        Heap of ``(t, seq, fix, raw_id)``: fixes held by the re-ordering window.
    seq : int
        Arrival counter (keeps the heap stable at equal times).
    n_events : int
        Engine events already stored.
    unique_id : str
        The device's unique id.
    raw_id : int or None
        Id of the last raw message whose fixes this state has processed (the fixes stored
        after it are replayed on top of the checkpoint); None in a checkpoint of an earlier
        version, which was written with every message (nothing to replay).
    """

    engine: Any | None = None
    last_t: float = -math.inf
    newest: float = -math.inf
    pending: list[tuple[float, int, Fix, int]] = field(default_factory=list)
    seq: int = 0
    n_events: int = 0
    unique_id: str = ""
    raw_id: int | None = None


def format_tag(engine: str, engine_config: str | None) -> str:
    """Format string of a checkpoint: iotnav version, engine, digest of its configuration file."""
    cfg = b""
    if engine_config:
        try:
            cfg = Path(engine_config).read_bytes()
        except OSError:
            cfg = engine_config.encode()
    digest = hashlib.sha256(cfg).hexdigest()[:12]
    return f"{iotnav.__version__}/{engine}/{digest}"[:64]


def dumps(state: DeviceState, key: bytes) -> bytes:
    """``state`` as bytes: HMAC-SHA256 tag, then the zlib-compressed pickle."""
    body = zlib.compress(pickle.dumps(state, protocol=pickle.HIGHEST_PROTOCOL), 1)
    return hmac.digest(key, body, "sha256") + body


def loads(blob: bytes, key: bytes) -> DeviceState:
    """The state of :func:`dumps`; :class:`CheckpointError` when the tag does not verify."""
    tag, body = blob[:_TAG], blob[_TAG:]
    if len(tag) != _TAG or not hmac.compare_digest(tag, hmac.digest(key, body, "sha256")):
        raise CheckpointError("checkpoint tag does not verify (other key or altered)")
    try:
        state = pickle.loads(zlib.decompress(body))
    except Exception as exc:  # a verified blob that no longer loads (code changed): start afresh
        raise CheckpointError(f"checkpoint unreadable: {exc!r}"[:200]) from None
    if not isinstance(state, DeviceState):
        raise CheckpointError(f"checkpoint holds {type(state).__name__}, expected DeviceState")
    return state


def load_key(data_dir: str | Path) -> bytes:
    """The checkpoint key of ``data_dir`` (``checkpoint_key``), created on first use (mode 0600)."""
    path = Path(data_dir) / KEY_FILE
    try:
        key = path.read_bytes()
    except FileNotFoundError:
        key = secrets.token_bytes(32)
        fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600)
        with os.fdopen(fd, "wb") as fh:
            fh.write(key)
        return key
    if len(key) < 16:
        raise ValueError(f"{path}: {len(key)} bytes; expected a key of at least 16 random bytes")
    return key
