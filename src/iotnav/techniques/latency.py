"""Latency compensation of delayed absolute fixes by re-propagation from buffered IMU samples.

In the cloud architecture of Dabove et al. (2016) an image taken at ``t_valid`` is localised
remotely and its position (and attitude) arrives at ``t_arrival > t_valid``; "it is thus
necessary to compensate for the latencies of calculation by the cloud" and the INS bridges them
("INS measurements can be coupled with image based positioning to reduce latencies of a cloud
architecture, if these latencies are less than 2 s").

Method
------
The engine keeps a bounded ring buffer, one entry per IMU sample ``k``: the sample, the state
*snapshot* at ``t_k`` taken after propagating to ``t_k`` and before applying any fix there, and the
fixes applied at that epoch. A fix valid at ``t_v`` is attached to the buffered epoch nearest
``t_v`` (at most half a sample period away), and then::

    restore(snapshot_j)                           # state at t_j, before its fixes
    for k = j, j+1, ..., now:
        if k > j: propagate(sample_k); snapshot_k = snapshot()
        apply the fixes of epoch k in t_valid order
        output_k = output(t_k)                    # revised output of epoch k

so the current state is what it would have been had the fix arrived on time. Fixes arriving
out of order are applied in ``t_valid`` order (an older fix replays from its own epoch and
re-applies the newer ones on the way); a fix valid later than the newest IMU sample waits
(``pending``) until the IMU stream reaches it; a fix older than the buffer is *rejected* and
reported. The buffer keeps ``max_latency_s`` of samples (2 s by default, the paper's bound),
capped at ``capacity`` entries.

Interface for engines (absfix here; the Kalman engines later)
-------------------------------------------------------------
An engine that implements :class:`Replayable`

* ``snapshot() -> object`` and ``restore(snap)``: its whole mutable state (copies; state in
  numpy arrays keeps this cheap: one array copy per sample),
* ``propagate(sample)``: advance the state to ``sample.t`` (no outputs, no events),
* ``apply_fix(fix)``: the measurement update (a Kalman ``update``; a reset for absfix),
* ``output(t, fixed) -> Output | None``: the output row at the current state,

routes its IMU samples through :meth:`LatencyBuffer.process_imu` and its fixes through
:meth:`LatencyBuffer.process_fix`. A Kalman engine puts ``x`` and ``P`` (and its nominal state)
into the snapshot; its update must not write events (the buffer's caller reports them once).

Reference: P. Dabove, G. Ghinamo, A. M. Lingua, "Inertial sensors for smartphones navigation",
SpringerPlus 4:834, 2015 (cited in this project as Dabove et al. 2016), Background and
Conclusions.
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass, field
from typing import Any, Literal, Protocol

__all__ = ["BufferEntry", "FixOutcome", "LatencyBuffer", "Replayable", "TimedFix"]

#: An IMU sample (anything with ``t`` in s, e.g. :class:`iotnav.engines.base.ImuSample`) and an
#: engine output row (e.g. :class:`iotnav.engines.base.Output`); kept opaque here so that this
#: technique imports no engine module.
ImuSample = Any
Output = Any


class TimedFix(Protocol):
    """Anything with a validity time (s)."""

    @property
    def t_valid(self) -> float:
        """Device time the fix refers to, s."""
        ...


class Replayable(Protocol):
    """What an engine provides to use :class:`LatencyBuffer` (module docstring)."""

    def snapshot(self) -> Any:
        """A copy of the whole mutable state."""
        ...

    def restore(self, snap: Any) -> None:
        """Return to a snapshot (the snapshot may be restored again later: do not alias it)."""
        ...

    def propagate(self, sample: ImuSample) -> None:
        """Advance the state to ``sample.t``."""
        ...

    def apply_fix(self, fix: Any) -> None:
        """Apply one fix to the current state (assumed valid now)."""
        ...

    def output(self, t: float, fixed: bool) -> Output | None:
        """Output row for the current state at time ``t`` (``fixed``: a fix was applied at ``t``)."""
        ...


@dataclass
class BufferEntry:
    """One buffered IMU epoch."""

    t: float
    sample: ImuSample
    snap: Any
    fixes: list[Any] = field(default_factory=list)


@dataclass(frozen=True)
class FixOutcome:
    """What happened to a fix handed to :meth:`LatencyBuffer.process_fix`.

    Attributes
    ----------
    status : {"applied", "pending", "rejected"}
        Applied at a buffered epoch (with replay), waiting for the IMU to reach ``t_valid``, or
        rejected.
    reason : str
        Why it was rejected (empty otherwise).
    epoch_t : float
        Time of the epoch it was applied at, s (NaN unless applied).
    replayed : tuple of Output
        Revised outputs of the epochs from ``epoch_t`` to now (oldest first).
    """

    status: Literal["applied", "pending", "rejected"]
    reason: str = ""
    epoch_t: float = math.nan
    replayed: tuple[Output, ...] = ()


class LatencyBuffer:
    """Ring buffer of IMU samples and state snapshots for fixes that arrive late.

    Parameters
    ----------
    max_latency_s : float
        How far back a fix may be valid, s (the buffer holds this much IMU history).
    capacity : int
        Hard bound on the number of buffered epochs.
    """

    def __init__(self, max_latency_s: float = 2.0, capacity: int = 4096) -> None:
        if max_latency_s < 0.0 or capacity < 1:
            raise ValueError("max_latency_s must be >= 0 and capacity >= 1")
        self.max_latency_s = float(max_latency_s)
        self.capacity = int(capacity)
        self.entries: deque[BufferEntry] = deque()
        self.pending: list[Any] = []
        self.dt_s = math.nan  # latest IMU period
        self.n_replayed = 0

    # ----------------------------------------------------------------- helpers
    def _half(self) -> float:
        return 0.5 * self.dt_s if math.isfinite(self.dt_s) else 0.0

    def _evict(self) -> None:
        if not self.entries:
            return
        t_now = self.entries[-1].t
        limit = t_now - self.max_latency_s - self._half()
        while len(self.entries) > 1 and (len(self.entries) > self.capacity or self.entries[0].t < limit):
            self.entries.popleft()

    # ----------------------------------------------------------------- IMU path
    def process_imu(self, engine: Replayable, sample: ImuSample) -> Output | None:
        """Propagate to ``sample.t``, buffer the epoch, apply the fixes due, return the output.

        Parameters
        ----------
        engine : Replayable
            The engine.
        sample : ImuSample
            The new IMU sample.

        Returns
        -------
        Output or None
            ``engine.output`` at ``sample.t``.
        """
        if self.entries:
            dt = sample.t - self.entries[-1].t
            if dt > 0.0:
                self.dt_s = dt
        engine.propagate(sample)
        entry = BufferEntry(sample.t, sample, engine.snapshot())
        if self.pending:
            lim = sample.t + self._half()
            due = [f for f in self.pending if f.t_valid <= lim]
            if due:
                self.pending = [f for f in self.pending if f.t_valid > lim]
                entry.fixes = sorted(due, key=lambda f: f.t_valid)
        self.entries.append(entry)
        for f in entry.fixes:
            engine.apply_fix(f)
        out = engine.output(sample.t, bool(entry.fixes))
        self._evict()
        return out

    # ----------------------------------------------------------------- fix path
    def process_fix(self, engine: Replayable, fix: TimedFix) -> FixOutcome:
        """Apply a fix at the epoch it is valid at, re-propagating to now.

        Parameters
        ----------
        engine : Replayable
            The engine (its current state is the newest buffered epoch).
        fix : TimedFix
            The fix (``t_valid`` in s).

        Returns
        -------
        FixOutcome
            ``applied`` (with the revised outputs), ``pending`` or ``rejected``.
        """
        tv = float(fix.t_valid)
        if not math.isfinite(tv):
            return FixOutcome("rejected", "t_valid is not finite")
        half = self._half()
        if not self.entries or tv > self.entries[-1].t + half:
            self.pending.append(fix)
            return FixOutcome("pending")
        if tv < self.entries[0].t - half:
            return FixOutcome(
                "rejected",
                f"valid {self.entries[-1].t - tv:.3f} s before the newest IMU sample; the buffer "
                f"holds {self.entries[-1].t - self.entries[0].t:.3f} s (max_latency_s {self.max_latency_s:g})",
            )
        # epoch nearest t_valid (entries are in time order)
        j = min(range(len(self.entries)), key=lambda i: abs(self.entries[i].t - tv))
        ej = self.entries[j]
        ej.fixes.append(fix)
        ej.fixes.sort(key=lambda f: f.t_valid)
        replayed: list[Output] = []
        engine.restore(ej.snap)
        for i in range(j, len(self.entries)):
            e = self.entries[i]
            if i > j:
                engine.propagate(e.sample)
                e.snap = engine.snapshot()
                self.n_replayed += 1
            for f in e.fixes:
                engine.apply_fix(f)
            out = engine.output(e.t, bool(e.fixes))
            if out is not None:
                replayed.append(out)
        return FixOutcome("applied", epoch_t=ej.t, replayed=tuple(replayed))
