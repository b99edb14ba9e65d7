"""Time faults of real loggers, repaired once on the way in and counted.

* **Counter wrap and device reset** (:func:`rebase_segments`): a logger's tick counter wraps at
  ``2**16``, ``2**24`` or ``2**32`` ticks (a 32-bit millisecond counter after 49.7 days), and a
  device that reboots restarts its clock near zero. Either makes the time drop in the middle
  of a file; read naively every later row is "non-monotonic" and the rest of the file is lost.
  A drop larger than ``10`` median steps after which the time runs on regularly for
  ``confirm`` rows starts a new segment. When the drop plus one step is a wrap modulus (within
  the gap allowance) the segment is unwrapped by exactly that modulus (no time lost); otherwise
  it is a reset and the segment is rebased to continue one median step after the previous row
  (the time the device was down is unknown: a reset is reported so, and the engines then see a
  short gap). A single row out of order is not a segment: it stays the reader's
  ``non-monotonic`` skip.
* **GNSS week rollover** (:func:`rollover_shift`, applied by :func:`iotnav.io.log.merge`):
  receivers that count the GPS week in 10 bits report dates 1024 weeks (19.6 years) early
  after a rollover (the last on 2019-04-06/07). A date can only be told for a rolled-over one
  by when it is read: a GPS date before that rollover which, moved on by 1024 weeks, falls in
  the year before ``now`` (the system clock, or given) is moved on (counted). A log that old
  read later, or a genuine pre-2019 log, is left alone: the ambiguity (a real 2001 date and a
  rolled-over 2021 one look the same) is resolved in favour of the data as written.
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

FloatArray = npt.NDArray[np.float64]

#: Tick-counter moduli tried for a wrap, in the file's own time unit.
WRAP_MODULI: tuple[float, ...] = (2.0**16, 2.0**24, 2.0**31, 2.0**32)

#: 1024 GPS weeks, s.
WEEK_ROLLOVER_S = 1024 * 7 * 86400.0
#: How long before ``now`` a moved-on date may lie (a log read within a year of recording).
MAX_AGE_S = 366 * 86400.0
#: The GPS time origin, 1980-01-06 00:00 UTC: earlier dates are not GPS dates at all.
GPS_EPOCH_UTC_S = 315964800.0
#: The last 10-bit GPS week rollover, 2019-04-07 00:00 GPST (as UTC seconds since 1970, -18 s).
LAST_ROLLOVER_UTC_S = 1554595200.0 - 18.0


@dataclass(frozen=True)
class TimeJump:
    """One repaired drop of the time: at ``index`` (first row of the new segment), ``kind``
    ``"wrap"`` or ``"reset"``, the ``shift`` added to that row and the later ones (file units)."""

    index: int
    kind: str
    shift: float


def rebase_segments(t: FloatArray, confirm: int = 5) -> tuple[FloatArray, list[TimeJump]]:
    """Unwrap counter wraps and rebase device resets in a time column (any unit).

    Parameters
    ----------
    t : numpy.ndarray
        Times in file order (finite), in the file's unit.
    confirm : int
        Rows after a drop that must run on regularly for it to start a segment.

    Returns
    -------
    tuple of (numpy.ndarray, list of TimeJump)
        The repaired times (a copy when something was repaired) and what was done.
    """
    t = np.asarray(t, float)
    if t.size < confirm + 2:
        return t, []
    d = np.diff(t)
    pos = d[d > 0]
    if pos.size == 0:
        return t, []
    med = float(np.median(pos))
    drops = np.flatnonzero(d < -10.0 * med)
    if drops.size == 0:
        return t, []
    out = t.copy()
    jumps: list[TimeJump] = []
    shift = 0.0
    for i in drops.tolist():
        j = i + 1  # first row of the candidate segment
        seg = t[j : j + confirm + 1]
        if seg.size < confirm + 1:
            continue
        sd = np.diff(seg)
        if not (np.all(sd > 0) and np.all(sd < 10.0 * med)):
            continue  # a glitch row, not a segment: left to the monotonic check
        prev = out[i]  # already shifted
        gap = t[j] + shift - prev
        kind, extra = "reset", med - gap
        for m in WRAP_MODULI:
            if 0.0 < gap + m <= 100.0 * med:
                kind, extra = "wrap", m
                break
        shift += extra
        out[j:] = t[j:] + shift
        jumps.append(TimeJump(j, kind, extra))
    return out, jumps


def rollover_shift(utc_s: FloatArray, now_s: float | None = None) -> float:
    """The multiple of 1024 GPS weeks (s) that moves a log's rolled-over dates on, else 0.

    Decided on the median known date: a GPS date (after 1980-01-06) before the last rollover
    which, moved on (once or more), lies within :data:`MAX_AGE_S` before ``now``.

    Parameters
    ----------
    utc_s : numpy.ndarray
        UTC seconds since 1970 of the log's GNSS epochs (NaN where unknown).
    now_s : float, optional
        The present (UTC s); the system clock by default.
    """
    u = np.asarray(utc_s, float)
    u = u[np.isfinite(u)]
    if u.size == 0:
        return 0.0
    now = time.time() if now_s is None else float(now_s)
    med = float(np.median(u))
    shift = 0.0
    if med < GPS_EPOCH_UTC_S:
        return 0.0  # not a GPS date (a synthetic or relative clock)
    while med + shift < LAST_ROLLOVER_UTC_S and med + shift + WEEK_ROLLOVER_S <= now:
        shift += WEEK_ROLLOVER_S
    return shift if shift and now - (med + shift) <= MAX_AGE_S else 0.0


def describe(jumps: list[TimeJump], unit: str) -> str:
    """A report note for the repaired jumps."""
    parts = [f"sample {j.index + 1}: {j.kind} (+{j.shift:.6g} {unit})" for j in jumps[:5]]
    more = f" and {len(jumps) - 5} more" if len(jumps) > 5 else ""
    return "time drops repaired (counter wrap unwrapped, device reset rebased): " + "; ".join(parts) + more
