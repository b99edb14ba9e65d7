"""Batch runner of the ``absfix`` engine (:mod:`iotnav.engines.absfix`): a log and its fixes.

:func:`run_with_fixes` merges the log's samples with the fixes by time (fixes by
``t_arrival``, before samples at equal times) and feeds them to an
:class:`~iotnav.engines.absfix.AbsfixEngine`, running the IMU samples between two fixes through
its compiled block step; with ``denoise = "batch"`` the six IMU channels are first denoised
over the whole log (:func:`denoise_log`, the Daubechies-4 level-7 wavelet of Dabove et al. 2015).
"""

from __future__ import annotations

import dataclasses
import heapq
import math
from collections.abc import Callable, Iterator
from typing import TYPE_CHECKING, Any, cast

import numpy as np
import numpy.typing as npt
import pandas as pd

from iotnav.engines.absfix_config import AbsFixSample, fixes_from_table
from iotnav.engines.base import (
    C_T,
    IMU_GAP_S,
    OUTPUT_COLUMNS,
    Output,
    OutputBlock,
    _order,
    _SampleSource,
    iter_samples,
)
from iotnav.io.log import Log
from iotnav.techniques.wavelet import denoise, min_length

FloatArray = npt.NDArray[np.float64]

if TYPE_CHECKING:  # the engine module imports this one (it re-exports the runner)
    from iotnav.engines.absfix import AbsfixEngine


# ---------------------------------------------------------------------------- batch runner


def denoise_log(log: Log) -> Log:
    """A copy of ``log`` with the six IMU channels wavelet-denoised (whole-signal, batch).

    Raises
    ------
    ValueError
        When the IMU table is shorter than a level-7 db4 decomposition needs.
    """
    imu = log.imu.copy()
    need = min_length()
    if len(imu) < need:
        raise ValueError(f"wavelet denoising needs at least {need} IMU samples, the log has {len(imu)}")
    for col in ("acc_x", "acc_y", "acc_z", "gyro_x", "gyro_y", "gyro_z"):
        imu[col] = denoise(np.array(imu[col], dtype=float))  # a writable copy for PyWavelets
    return dataclasses.replace(log, imu=imu)


def _merged(log: Log, fixes: list[AbsFixSample]) -> Iterator[Any]:
    """Log samples and fixes by time; fixes by ``t_arrival``, before samples at equal times."""
    order = sorted(range(len(fixes)), key=lambda i: (fixes[i].t_arrival, i))
    fx = ((fixes[i].t_arrival, 0, i, fixes[i]) for i in order)
    sx = ((s.t, 1, k, s) for k, s in enumerate(iter_samples(log)))
    for item in heapq.merge(fx, sx, key=lambda a: (a[0], a[1], a[2])):
        yield item[3]


def run_with_fixes(
    engine: AbsfixEngine,
    log: Log,
    fixes: pd.DataFrame | list[AbsFixSample],
    progress: Callable[[int], None] | None = None,
    *,
    revised: bool = False,
) -> pd.DataFrame:
    """Run an engine over a log with absolute fixes merged in by arrival time.

    Like :func:`iotnav.engines.base.run_batch`, plus the fixes (merged by ``t_arrival``,
    before the samples of the same time). With ``config.denoise == "batch"`` the IMU channels
    are wavelet-denoised first (:func:`denoise_log`). An :class:`AbsfixEngine` runs the IMU
    samples between two fixes (or other samples) through its compiled :meth:`~AbsfixEngine.imu_block`
    when the IMU table is finite and in time order; otherwise (and with the streaming
    denoiser, or another engine) every sample goes through ``step()``. Both give the same rows.

    Parameters
    ----------
    engine : AbsfixEngine
        The engine (or any engine with the same ``step`` / ``last_revision`` contract).
    log : Log
        IMU (and other) samples.
    fixes : pandas.DataFrame or list of AbsFixSample
        Fixes (:func:`fixes_from_table` is applied to a table).
    progress : callable, optional
        Called with the number of samples processed since the previous call (about every 10,000).
    revised : bool
        False: the real-time track (what the device output at each time). True: the track
        after latency compensation, each row replaced by its last re-propagation.

    Returns
    -------
    pandas.DataFrame
        One row per output with :data:`~iotnav.engines.base.OUTPUT_COLUMNS`; ``df.attrs``
        carries ``events``, ``mount_yaw_rad`` and ``summary``.
    """
    from iotnav.engines.absfix import AbsfixEngine  # here: iotnav.engines.absfix imports this module

    fx = fixes_from_table(fixes) if isinstance(fixes, pd.DataFrame) else list(fixes)
    if getattr(engine, "config", None) is not None and getattr(engine.config, "denoise", "off") == "batch":
        log = denoise_log(log)
    if isinstance(engine, AbsfixEngine) and engine.config.denoise != "streaming":
        out = _run_blocks(engine, log, fx, progress, revised)
        if out is not None:
            df = out.frame()
            df.attrs["events"] = list(engine.events)
            df.attrs["mount_yaw_rad"] = float(engine.mount_yaw_rad)
            df.attrs["summary"] = engine.summary()
            return df
    rows: list[Output] = []
    for k, s in enumerate(_merged(log, fx), start=1):
        out_row = engine.step(s)
        if out_row is not None:
            rows.extend(engine.released)
        elif revised and isinstance(s, AbsFixSample) and engine.last_revision:
            rev = engine.last_revision
            n = len(rev)
            if n and rows and n <= len(rows) and rows[-n].t == rev[0].t:
                rows[-n:] = list(rev)
            engine.last_revision = ()
        if progress is not None and k % 10_000 == 0:
            progress(10_000)
    rows.extend(engine.flush())
    df = (
        pd.DataFrame(rows, columns=list(OUTPUT_COLUMNS))
        if rows
        else pd.DataFrame(columns=list(OUTPUT_COLUMNS))
    )
    df.attrs["events"] = list(engine.events)
    df.attrs["mount_yaw_rad"] = float(engine.mount_yaw_rad)
    df.attrs["summary"] = engine.summary()
    return df


def _run_blocks(
    engine: AbsfixEngine,
    log: Log,
    fx: list[AbsFixSample],
    progress: Callable[[int], None] | None,
    revised: bool,
) -> OutputBlock | None:
    """:func:`run_with_fixes` with the IMU in compiled blocks; None when the IMU table does not allow it.

    The order of :func:`_merged` is kept: a fix before the IMU samples of its arrival time and
    after the earlier ones, GNSS and magnetometer samples (ignored, counted) likewise, and the
    guard's ``imu_gap`` counted at the sample after the gap, as ``step()`` would.
    """
    src = _SampleSource(log)
    t = src.imu_t
    n = t.size
    if n == 0 or not np.all(np.isfinite(t)) or not all(np.all(np.isfinite(c)) for c in (*src.acc, *src.gyro)):
        return None
    guard = engine.guard
    if not (bool(np.all(np.diff(t) >= 0.0)) and t[0] >= guard.t_imu):
        return None
    # (cut, rank, order, kind, index): the item is handled before IMU sample ``cut``
    items: list[tuple[int, int, float, int, int, int]] = []
    ta = np.array([f.t_arrival for f in fx], dtype=float)
    order = sorted(range(len(fx)), key=lambda i: (fx[i].t_arrival, i))
    cut_f = np.searchsorted(t, ta, side="left")
    for r, i in enumerate(order):
        items.append((int(cut_f[i]), 0, float(ta[i]), 0, r, i))
    g_t = src.gcols[0] if src.gcols else np.empty(0)
    kind, idx = _order([g_t, src.mag_t])
    for r, (kd, j) in enumerate(zip(kind.tolist(), idx.tolist(), strict=True)):
        tj = float(g_t[j] if kd == 0 else src.mag_t[j])
        items.append((int(np.searchsorted(t, tj, side="left")), 0, tj, 1, r, j * 2 + kd))
    prev = guard.t_imu
    gaps = np.flatnonzero(np.diff(t) > IMU_GAP_S) + 1
    if t[0] - prev > IMU_GAP_S and prev > -math.inf:
        gaps = np.concatenate([[0], gaps])
    for g in gaps.tolist():
        items.append((g, 1, float(t[g]), 2, 0, g))
    items.sort()
    out = OutputBlock(n)
    i = done = 0
    acc = cast(tuple[FloatArray, FloatArray, FloatArray], src.acc)
    gyro = cast(tuple[FloatArray, FloatArray, FloatArray], src.gyro)

    def advance(c: int) -> None:
        nonlocal i, done
        while i < c:
            i1 = min(c, i + 10_000)
            engine.imu_block(t, acc, gyro, out, i, i1)
            i = i1
            if progress is not None and i - done >= 10_000:
                progress(i - done)
                done = i

    for c, _rank, _t, kd, _r, j in items:
        advance(c)
        if kd == 2:
            guard.skip("imu_gap", float(t[j]))
            continue
        if kd == 1:
            engine.step(src.sample(j % 2, j // 2))
            continue
        engine.step(fx[j])
        n_rev = engine._n_rev
        if revised and n_rev:
            rev = engine._rev
            if n_rev <= i and out.floats[C_T, i - n_rev] == rev.floats[C_T, 0]:
                out.floats[:, i - n_rev : i] = rev.floats[:, :n_rev]
                out.static[i - n_rev : i] = rev.static[:n_rev]
                out.source[i - n_rev : i] = rev.source[:n_rev]
            engine.last_revision = ()
    advance(n)
    out.n = n
    guard.t_imu = float(t[-1])
    if progress is not None and i > done:
        progress(i - done)
    return out
