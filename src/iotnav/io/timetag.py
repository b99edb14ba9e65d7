"""RTKLIB demo5 time-tag files (``*.tag``): GNSS time for a logger's own millisecond tick.

When RTKLIB (``str2str``/``strsvr`` of the demo5 branch) records a stream with time tags it
writes, next to the data file ``X``, a file ``X.tag``:

====================  ========================================================================
bytes                 content
====================  ========================================================================
0 .. 59               text header, ``TIMETAG RTKLIB demo5 ...`` padded with NUL bytes
60 .. 63              ``uint32`` host tick (ms) when recording started (host clock, unused here)
64 .. 67              ``uint32`` ``time_t``: start time, GPST written as Unix-style seconds
68 .. 75              ``double`` fractional seconds of the start time
76 ..                 pairs ``(uint32 tick_ms, uint32 file_pos)``: ms since the start (host clock)
                      at which the data file had grown to ``file_pos`` bytes
====================  ========================================================================

All integers are little-endian. "GPST written as Unix-style seconds" means the GPS calendar date
and time passed through ``timegm`` (the RTKLIB ``gtime_t`` convention); convert to UTC with
:func:`iotnav.io.timeutil.gpst_to_utc`.

Mapping a logger tick to GPST
-----------------------------
An IMU that writes its own millisecond counter (``tick``) has no absolute time. The upstream
converter of the rtklibexplorer GNSS_IMU project (``convert_imu_file.py``) maps the tick of every
sample linearly onto the recording interval of the tag file::

    start = time_t + frac                        (GPST, first byte recorded)
    end   = start + tick_ms[-1] / 1000           (GPST, last tag pair)
    t     = start + (tick - tick0) / 1000 * (end - start) / ((tickN - tick0) / 1000)

where ``tick0`` and ``tickN`` are the logger ticks of the first and last samples used. In words:
the first sample is placed at the start of the recording, the last at its end, and the logger's
tick is scaled so that its span equals the host's span. This removes the logger's oscillator rate
error relative to the host (GNSS-disciplined) clock, but it assumes the first and last samples
were written exactly at the start and end of the recording: any constant transport latency
(serial buffering, tens of ms) remains as an offset, which is why the data author applies an
extra ``imu_t_off`` of -0.125 s to the drive. :meth:`TimeTag.ticks_to_gpst` implements exactly
this map; :meth:`TimeTag.file_pos_to_gpst` is an independent, byte-offset based alternative
(host time at which the file reached a byte offset) useful for checks.
"""

from __future__ import annotations

import os
import struct
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from iotnav.io.errors import IngestError

HEADER_LEN = 60
_FIXED_LEN = HEADER_LEN + 4 + 4 + 8
_MAGIC = b"TIMETAG"


@dataclass(frozen=True)
class TimeTag:
    """Contents of an RTKLIB demo5 ``.tag`` file.

    Attributes
    ----------
    path : str
        The file as given.
    header : str
        The text header (NUL padding removed).
    host_tick_ms : int
        Host tick at the start of recording, ms (host clock; not used for timing).
    start_gpst : float
        Start of recording, GPST written as Unix-style seconds (``time_t + frac``).
    tag_tick_ms : numpy.ndarray
        ``uint32`` ms since the start at each tag (host clock), one per pair.
    file_pos : numpy.ndarray
        ``uint32`` size of the data file in bytes at each tag.
    trailing_bytes : int
        Bytes after the last complete pair (a truncated pair), normally 0.
    """

    path: str
    header: str
    host_tick_ms: int
    start_gpst: float
    tag_tick_ms: npt.NDArray[np.uint32]
    file_pos: npt.NDArray[np.uint32]
    trailing_bytes: int = 0

    @property
    def end_gpst(self) -> float:
        """End of recording, GPST Unix-style seconds: ``start_gpst + tag_tick_ms[-1] / 1000``."""
        if self.tag_tick_ms.size == 0:
            raise IngestError(self.path, "time-tag file holds no (tick, file_pos) pairs; no end time")
        return self.start_gpst + float(self.tag_tick_ms[-1]) / 1000.0

    def ticks_to_gpst(
        self,
        tick_ms: npt.ArrayLike,
        tick0_ms: float | None = None,
        tick_end_ms: float | None = None,
    ) -> npt.NDArray[np.float64]:
        """Map logger ticks (ms) to GPST seconds the way the upstream converter does.

        ``t = start + (tick - tick0) * (end - start) / (tickN - tick0)`` (ticks in ms, times in s).

        Parameters
        ----------
        tick_ms : array_like
            Logger ticks, ms since logger power-up.
        tick0_ms, tick_end_ms : float, optional
            Ticks of the first and last samples of the log (defaults: first and last element of
            ``tick_ms``). A reader passes the first and last *valid* samples of the file.

        Returns
        -------
        numpy.ndarray
            GPST written as Unix-style seconds.

        Raises
        ------
        IngestError
            When the tag file has no pairs or the tick span is not positive.
        """
        ticks = np.asarray(tick_ms, dtype=np.float64)
        if ticks.size == 0:
            return np.empty(0, dtype=np.float64)
        t0 = float(ticks[0]) if tick0_ms is None else float(tick0_ms)
        tn = float(ticks[-1]) if tick_end_ms is None else float(tick_end_ms)
        span_tick = tn - t0
        span_host = self.end_gpst - self.start_gpst
        if not span_tick > 0.0 or not span_host > 0.0:
            raise IngestError(
                self.path,
                f"cannot scale logger ticks: tick span {span_tick:g} ms, recording span {span_host:g} s "
                "(both must be positive)",
            )
        return self.start_gpst + (ticks - t0) * (span_host / span_tick)

    def file_pos_to_gpst(self, pos: npt.ArrayLike) -> npt.NDArray[np.float64]:
        """GPST (Unix-style s) at which the data file reached byte offset ``pos``.

        Linear interpolation of the tag pairs ``(file_pos, tick_ms)``; offsets beyond the last tag
        are clamped. Tags with equal ``file_pos`` (no data between tags) keep the first tick.

        Parameters
        ----------
        pos : array_like
            Byte offsets in the data file.

        Returns
        -------
        numpy.ndarray
            GPST written as Unix-style seconds.
        """
        if self.tag_tick_ms.size == 0:
            raise IngestError(self.path, "time-tag file holds no (tick, file_pos) pairs")
        fp = self.file_pos.astype(np.float64)
        tk = self.tag_tick_ms.astype(np.float64)
        keep = np.concatenate(([True], np.diff(fp) > 0))
        return self.start_gpst + np.interp(np.asarray(pos, dtype=np.float64), fp[keep], tk[keep]) / 1000.0


def read_timetag(path: str | os.PathLike[str]) -> TimeTag:
    """Read an RTKLIB demo5 time-tag file.

    Parameters
    ----------
    path : str or os.PathLike
        The ``.tag`` file.

    Returns
    -------
    TimeTag
        Start time (GPST) and the (tick, file position) pairs.

    Raises
    ------
    IngestError
        When the file is missing, too short, or lacks the ``TIMETAG`` header.
    """
    p = os.fspath(path)
    try:
        with open(p, "rb") as f:
            raw = f.read()
    except OSError as exc:
        raise IngestError(p, f"cannot open time-tag file ({exc.strerror})") from None
    if len(raw) < _FIXED_LEN or not raw.startswith(_MAGIC):
        raise IngestError(
            p,
            f"not an RTKLIB time-tag file: expected a {HEADER_LEN}-byte header starting with 'TIMETAG' "
            f"followed by tick, time_t and fraction ({_FIXED_LEN} bytes at least), got {len(raw)} bytes",
        )
    header = raw[:HEADER_LEN].split(b"\0", 1)[0].decode("ascii", errors="replace").strip()
    host_tick, time_t = struct.unpack_from("<II", raw, HEADER_LEN)
    (frac,) = struct.unpack_from("<d", raw, HEADER_LEN + 8)
    if not np.isfinite(frac) or not 0.0 <= frac < 1.0:
        raise IngestError(p, f"time-tag start fraction {frac!r} is not in [0, 1)")
    body = raw[_FIXED_LEN:]
    n_pairs = len(body) // 8
    trailing = len(body) - 8 * n_pairs
    pairs = np.frombuffer(body, dtype="<u4", count=2 * n_pairs).reshape(n_pairs, 2)
    return TimeTag(
        path=p,
        header=header,
        host_tick_ms=int(host_tick),
        start_gpst=float(time_t) + float(frac),
        tag_tick_ms=pairs[:, 0].astype(np.uint32),
        file_pos=pairs[:, 1].astype(np.uint32),
        trailing_bytes=trailing,
    )
