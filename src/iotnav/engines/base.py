"""Engine protocol, sample and output records, and the batch runner (STYLE §7).

Streaming and batch share one ``step()``: a device or gateway calls ``engine.step(sample)``
for each sample as it arrives; :func:`run_batch` merges a :class:`~iotnav.io.log.Log` by time
(GNSS, then magnetometer, then IMU at equal times) and loops over the same ``step()``,
collecting one :class:`Output` per IMU sample into a :class:`pandas.DataFrame` (samples with
non-finite values or out of order are skipped and counted, :class:`InputGuard`).
"""

from __future__ import annotations

import math
from collections.abc import Callable, Iterator
from typing import Any, NamedTuple, Protocol

import numba
import numpy as np
import numpy.typing as npt
import pandas as pd

from iotnav.engines.tangent_plane import REANCHOR_DISTANCE_M as REANCHOR_DISTANCE_M  # re-exported
from iotnav.engines.tangent_plane import TangentPlane as TangentPlane
from iotnav.io.log import Log
from iotnav.io.schema import IMU_COLUMNS, MAG_COLUMNS

FloatArray = npt.NDArray[np.float64]


class ImuSample(NamedTuple):
    """One IMU sample: device time (s), specific force in ``b`` (m/s^2), angular rate in ``b`` (rad/s)."""

    t: float
    acc_b: FloatArray
    gyro_b: FloatArray


class MagSample(NamedTuple):
    """One magnetometer sample: device time (s), field in ``b`` (microtesla)."""

    t: float
    mag_b_ut: FloatArray


class GnssSample(NamedTuple):
    """One GNSS epoch (columns of :data:`iotnav.io.schema.GNSS_COLUMNS`, SI / degrees).

    ``utc`` is s since 1970 (NaN unknown); ``motion`` and ``ignition`` are the device's flags
    (1 moving / on, 0 still / off, -1 unknown).
    """

    t: float
    lat_deg: float
    lon_deg: float
    height_m: float
    pdop: float = math.nan
    hdop: float = math.nan
    num_sv: int = -1
    speed_mps: float = math.nan
    course_rad: float = math.nan
    course_valid: bool = False
    valid: bool = True
    vn: float = math.nan
    ve: float = math.nan
    vd: float = math.nan
    h_acc_m: float = math.nan
    v_acc_m: float = math.nan
    s_acc_mps: float = math.nan
    quality: int = -1
    utc: float = math.nan
    motion: int = -1
    ignition: int = -1


Sample = ImuSample | GnssSample | MagSample

OUTPUT_COLUMNS: tuple[str, ...] = (
    "t",
    "lat",
    "lon",
    "height",
    "north",
    "east",
    "down",
    "vn",
    "ve",
    "vd",
    "roll",
    "pitch",
    "yaw",
    "static",
    "std_north",
    "std_east",
    "source",
)


#: Columns of :attr:`OutputBlock.floats`, in row order (``OUTPUT_COLUMNS`` without ``static``, ``source``).
FLOAT_COLUMNS: tuple[str, ...] = tuple(c for c in OUTPUT_COLUMNS if c not in ("static", "source"))
(
    C_T,
    C_LAT,
    C_LON,
    C_HEIGHT,
    C_NORTH,
    C_EAST,
    C_DOWN,
    C_VN,
    C_VE,
    C_VD,
    C_ROLL,
    C_PITCH,
    C_YAW,
    C_STD_NORTH,
    C_STD_EAST,
) = range(15)

#: Output ``source`` names; compiled kernels write their index (``SRC_*``) into ``OutputBlock.source``.
SOURCES: tuple[str, ...] = ("none", "fix", "dr", "lowpass", "last_position")
SRC_NONE, SRC_FIX, SRC_DR, SRC_LOWPASS, SRC_LAST_POSITION = range(5)


class Output(NamedTuple):
    """One output row (per IMU sample).

    Attributes: ``t`` device time (s); ``lat``, ``lon`` degrees, ``height`` ellipsoidal m;
    ``north``, ``east``, ``down`` m about the NED origin; ``vn``, ``ve``, ``vd`` m/s; ``roll``,
    ``pitch``, ``yaw`` rad (vehicle attitude once the mount angle is known, else sensor);
    ``static`` block 3's decision; ``std_north``, ``std_east`` 1-sigma, m; ``source`` one of
    ``fix``, ``dr``, ``lowpass``, ``last_position`` (``none`` before any position).
    """

    t: float
    lat: float
    lon: float
    height: float
    north: float
    east: float
    down: float
    vn: float
    ve: float
    vd: float
    roll: float
    pitch: float
    yaw: float
    static: bool
    std_north: float
    std_east: float
    source: str


class Engine(Protocol):
    """What every engine offers."""

    events: list[dict[str, Any]]

    def step(self, sample: Sample) -> Output | None:
        """Process one sample; an :class:`Output` for an IMU sample, None otherwise (and for a
        sample the engine's :class:`InputGuard` rejects)."""
        ...

    @property
    def mount_yaw_rad(self) -> float:
        """Current mount-angle estimate, rad."""
        ...

    def summary(self) -> dict[str, Any]:
        """Configuration and final state, for ``summary.json``."""
        ...


class BlockEngine(Engine, Protocol):
    """An engine whose IMU step is a compiled kernel that also runs over blocks of samples.

    ``step(ImuSample)`` of such an engine runs :meth:`imu_block` on a one-sample block, so
    streaming and batch execute the same compiled code.
    """

    def imu_block(
        self,
        t: FloatArray,
        acc: tuple[FloatArray, FloatArray, FloatArray],
        gyro: tuple[FloatArray, FloatArray, FloatArray],
        out: OutputBlock,
        i0: int,
        i1: int,
    ) -> None:
        """Process IMU samples ``i0 .. i1-1`` in time order, writing row ``k`` of ``out`` for sample ``k``.

        ``t`` is device time (s); ``acc`` the specific force along sensor x, y, z (m/s^2) and
        ``gyro`` the angular rate about sensor x, y, z (rad/s), as separate 1-D float64 arrays.
        """
        ...


_GNSS_FIELDS = (
    "t",
    "lat_deg",
    "lon_deg",
    "height_m",
    "pdop",
    "hdop",
    "num_sv",
    "speed_mps",
    "course_rad",
    "course_valid",
    "valid",
    "vn",
    "ve",
    "vd",
    "h_acc_m",
    "v_acc_m",
    "s_acc_mps",
    "quality",
    "utc",
    "motion",
    "ignition",
)
_GNSS_INT = ("num_sv", "quality", "motion", "ignition")
_GNSS_BOOL = ("course_valid", "valid")


def _drop_nonfinite(df: pd.DataFrame, cols: tuple[str, ...], reason: str, guard: InputGuard) -> pd.DataFrame:
    """``df`` without the rows where one of ``cols`` is not finite (counted on ``guard``).

    For GNSS (``reason`` ``gnss_nonfinite``) a position is only required of valid epochs.
    """
    if len(df) == 0:
        return df
    ok = np.ones(len(df), bool)
    for c in cols:
        ok &= np.isfinite(df[c].to_numpy(float))
    if reason == "gnss_nonfinite":
        ok |= np.isfinite(df["t"].to_numpy(float)) & ~df["valid"].to_numpy(bool)
    if ok.all():
        return df
    bad = np.flatnonzero(~ok)
    guard.skip(reason, float(df["t"].iloc[bad[0]]), n=int(bad.size))
    return df.loc[ok]


#: An IMU sample later than this after the previous one is counted as an ``imu_gap``, s (the
#: gap eskf's kernel already refuses to integrate: a MEMS strapdown solution over 1 s without
#: samples has lost what a fix interval of dead reckoning can tell).
IMU_GAP_S = 1.0


class InputGuard:
    """Rejects samples an engine cannot use, counts them by reason, records the first of each.

    Every engine's ``step()`` passes its sample through :meth:`admit` first; a rejected sample
    changes nothing and gives no output (``step()`` returns None). Reasons:

    * ``imu_nonfinite`` / ``mag_nonfinite``: time or a value (specific force, rate, field) is
      NaN or infinite;
    * ``gnss_nonfinite``: time is NaN or infinite, or the epoch claims a valid fix whose
      latitude or longitude is (an epoch without a fix passes; a missing height, velocity or
      quality figure is the engines' to handle);
    * ``imu_time_backwards`` / ``gnss_time_backwards`` / ``mag_time_backwards``: earlier than
      the previous accepted sample of the same stream (equal times pass).

    Not a rejection but counted the same way: ``imu_gap``, an IMU sample more than
    :data:`IMU_GAP_S` after the previous one (the sample is used; how the engine bridges the
    gap is its own: eskf does not integrate it, absfix and pdr skip it over their
    ``max_imu_gap_s``, anchor and the pipeline extrapolate; the count says it happened). The
    batch runner counts the gaps of its compiled block path too (:func:`run_batch`).

    Engines add their own reasons through :meth:`skip`. ``skipped`` (reason -> count) goes into
    ``summary()["skipped"]``; the first skip of each reason is an ``input_skipped`` event.

    Parameters
    ----------
    events : list of dict
        The engine's event list (appended to).
    """

    def __init__(self, events: list[dict[str, Any]]) -> None:
        self.events = events
        self.skipped: dict[str, int] = {}
        self.t_imu = -math.inf
        self.t_gnss = -math.inf
        self.t_mag = -math.inf

    def skip(self, reason: str, t: float, n: int = 1) -> None:
        """Count ``n`` skipped samples for ``reason``; the first of a reason becomes an event (t in s)."""
        k = self.skipped.get(reason, 0)
        self.skipped[reason] = k + n
        if k == 0:
            self.events.append({"type": "input_skipped", "t": float(t), "reason": reason})

    def admit(self, s: Any) -> Any:
        """``s`` if it may be used (a GNSS sample possibly repaired), else None (counted).

        The one repair: a GNSS course flagged valid whose course or speed is not finite is
        marked invalid (counted as ``gnss_course_nonfinite``; the position is still used).
        """
        if isinstance(s, ImuSample):
            t, a, w = s.t, s.acc_b, s.gyro_b
            # a sum of finite values is finite (short of overflow, itself bad input)
            if not math.isfinite(t + a[0] + a[1] + a[2] + w[0] + w[1] + w[2]):
                self.skip("imu_nonfinite", t)
                return None
            if t < self.t_imu:
                self.skip("imu_time_backwards", t)
                return None
            if t - self.t_imu > IMU_GAP_S and self.t_imu > -math.inf:
                self.skip("imu_gap", t)
            self.t_imu = t
            return s
        if isinstance(s, GnssSample):
            if not math.isfinite(s.t) or (s.valid and not math.isfinite(s.lat_deg + s.lon_deg)):
                self.skip("gnss_nonfinite", s.t)
                return None
            if s.t < self.t_gnss:
                self.skip("gnss_time_backwards", s.t)
                return None
            self.t_gnss = s.t
            if s.course_valid and not math.isfinite(s.course_rad + s.speed_mps):
                self.skip("gnss_course_nonfinite", s.t)
                return s._replace(course_valid=False)
            return s
        if isinstance(s, MagSample):
            m = s.mag_b_ut
            if not math.isfinite(s.t + m[0] + m[1] + m[2]):
                self.skip("mag_nonfinite", s.t)
                return None
            if s.t < self.t_mag:
                self.skip("mag_time_backwards", s.t)
                return None
            self.t_mag = s.t
            return s
        return s


class _SampleSource:
    """Builds sample records from a log's columns without copying the IMU data.

    With a ``guard``, rows whose time or values are not finite are left out and counted
    (readers already drop them; a log built by hand may still hold some): the IMU columns are
    then copied.
    """

    def __init__(self, log: Log, guard: InputGuard | None = None) -> None:
        g, imu, mg = log.gnss, log.imu, log.mag
        if guard is not None:
            g, imu, mg = (
                _drop_nonfinite(g, ("t", "lat_deg", "lon_deg"), "gnss_nonfinite", guard),
                _drop_nonfinite(imu, tuple(IMU_COLUMNS), "imu_nonfinite", guard),
                _drop_nonfinite(mg, tuple(MAG_COLUMNS), "mag_nonfinite", guard),
            )
        # a table built by hand may lack the optional columns: their defaults (NaN, -1)
        self.gcols: list[np.ndarray] = (
            [
                g[c].to_numpy(bool if c in _GNSS_BOOL else None)
                if c in g.columns
                else np.full(len(g), GnssSample._field_defaults[c])
                for c in _GNSS_FIELDS
            ]
            if len(g)
            else []
        )
        self.imu_t = imu["t"].to_numpy(float) if len(imu) else np.empty(0)
        self.acc = tuple(imu[c].to_numpy(float) for c in ("acc_x", "acc_y", "acc_z")) if len(imu) else ()
        self.gyro = tuple(imu[c].to_numpy(float) for c in ("gyro_x", "gyro_y", "gyro_z")) if len(imu) else ()
        self.mag_t = mg["t"].to_numpy(float) if len(mg) else np.empty(0)
        self.mag = mg[["mag_x_ut", "mag_y_ut", "mag_z_ut"]].to_numpy(float) if len(mg) else np.empty((0, 3))

    def gnss(self, j: int) -> GnssSample:
        vals: list[Any] = [
            int(col[j]) if name in _GNSS_INT else bool(col[j]) if name in _GNSS_BOOL else float(col[j])
            for name, col in zip(_GNSS_FIELDS, self.gcols, strict=True)
        ]
        return GnssSample(*vals)

    def imu(self, j: int) -> ImuSample:
        acc = np.array([self.acc[0][j], self.acc[1][j], self.acc[2][j]])
        gyro = np.array([self.gyro[0][j], self.gyro[1][j], self.gyro[2][j]])
        return ImuSample(float(self.imu_t[j]), acc, gyro)

    def magnetometer(self, j: int) -> MagSample:
        return MagSample(float(self.mag_t[j]), self.mag[j])

    def sample(self, kind: int, j: int) -> Sample:
        """Kind 0 GNSS, 1 magnetometer, 2 IMU."""
        if kind == 2:
            return self.imu(j)
        return self.gnss(j) if kind == 0 else self.magnetometer(j)


def _order(times: list[np.ndarray]) -> tuple[npt.NDArray[np.int8], npt.NDArray[np.int32]]:
    """Kinds and indices of the samples of several streams in time order (ties: stream order).

    A stable sort of the concatenated times keeps the streams' order at equal times and
    their own order within each stream; transient memory is about 17 bytes per sample.
    """
    sizes = [t.size for t in times]
    if sum(sizes) == 0:
        return np.empty(0, np.int8), np.empty(0, np.int32)
    t_all = np.concatenate(times)
    order = np.argsort(t_all, kind="stable")
    del t_all
    starts = np.cumsum([0, *sizes[:-1]])
    kind = np.zeros(order.size, dtype=np.int8)
    for start in starts[1:]:
        kind += order >= start
    order -= starts[kind]
    return kind, order.astype(np.int32)


def iter_samples(log: Log) -> Iterator[Sample]:
    """Samples of a log in time order; at equal times GNSS, then magnetometer, then IMU."""
    src = _SampleSource(log)
    kind, idx = _order([src.gcols[0] if src.gcols else np.empty(0), src.mag_t, src.imu_t])
    for c0 in range(0, kind.size, 10_000):
        for kd, j in zip(kind[c0 : c0 + 10_000].tolist(), idx[c0 : c0 + 10_000].tolist(), strict=True):
            yield src.sample(kd, j)


class OutputBlock:
    """Output rows in preallocated numpy columns (about 130 bytes a row).

    ``floats[c, k]`` holds column :data:`FLOAT_COLUMNS` ``[c]`` of row ``k``; ``static[k]`` the
    static decision; ``source[k]`` an index into :attr:`names` (which starts with
    :data:`SOURCES`). Compiled engine kernels write rows in place; :meth:`add` appends an
    :class:`Output` (a list of NamedTuples would cost about 1 KB a row; a day of 100 Hz data
    would need about 9 GB that way).
    """

    def __init__(self, capacity: int) -> None:
        n = max(capacity, 1)
        self.n = 0
        self.floats = np.full((len(FLOAT_COLUMNS), n), np.nan)
        self.static = np.zeros(n, dtype=np.bool_)
        self.source = np.zeros(n, dtype=np.int8)
        self.names: list[str] = list(SOURCES)
        self.codes: dict[str, int] = {name: k for k, name in enumerate(SOURCES)}

    def add(self, out: Output) -> None:
        """Append one row (the arrays double when full)."""
        i = self.n
        if i == self.static.size:
            self.floats = np.concatenate([self.floats, np.empty_like(self.floats)], axis=1)
            self.static = np.concatenate([self.static, np.empty_like(self.static)])
            self.source = np.concatenate([self.source, np.empty_like(self.source)])
        col = self.floats
        for j, k in enumerate(_FLOAT_INDEX):
            col[j, i] = out[k]
        self.static[i] = out.static
        src = out.source
        code = self.codes.get(src)
        if code is None:
            code = self.codes[src] = len(self.names)
            self.names.append(src)
        self.source[i] = code
        self.n = i + 1

    def row(self, k: int) -> Output:
        """Row ``k`` as an :class:`Output`."""
        f = self.floats[:, k].tolist()
        name = self.names[self.source[k]]
        return Output._make([*f[:C_STD_NORTH], bool(self.static[k]), f[C_STD_NORTH], f[C_STD_EAST], name])

    def frame(self) -> pd.DataFrame:
        """The first :attr:`n` rows as a DataFrame with :data:`OUTPUT_COLUMNS`.

        The float columns are views of :attr:`floats` (no copy); ``source`` is categorical (one
        byte a row; a column of strings would cost 10-60 bytes a row at its peak).
        """
        n = self.n
        df = pd.DataFrame(self.floats[:, :n].T, columns=list(FLOAT_COLUMNS), copy=False)
        df.insert(OUTPUT_COLUMNS.index("static"), "static", self.static[:n])
        source = pd.Categorical.from_codes(self.source[:n], categories=pd.Index(self.names))
        df.insert(OUTPUT_COLUMNS.index("source"), "source", pd.Series(source, copy=False))
        return df


_FLOAT_INDEX = tuple(OUTPUT_COLUMNS.index(c) for c in FLOAT_COLUMNS)


class OneSampleBlock:
    """Reusable one-sample input and output block for ``step(ImuSample)`` of a :class:`BlockEngine`.

    ``t``, ``acc`` and ``gyro`` are read-only one-element views of one buffer, like the columns
    :func:`run_batch` passes (pandas gives read-only arrays), so that streaming calls the
    kernel already compiled for batch instead of compiling a second specialisation.
    """

    def __init__(self) -> None:
        self._buf = np.zeros(7)
        views = [self._buf[i : i + 1] for i in range(7)]
        for v in views:
            v.flags.writeable = False
        self.t = views[0]
        self.acc = (views[1], views[2], views[3])
        self.gyro = (views[4], views[5], views[6])
        self.out = OutputBlock(1)

    def __reduce__(self) -> tuple[type[OneSampleBlock], tuple[()]]:
        # copies and pickles get a fresh block: the views must stay views of their own buffer
        # (a deep copy would detach them and the kernel would read stale input)
        return (OneSampleBlock, ())

    def run(self, imu_block: Callable[..., None], s: ImuSample) -> Output:
        """``imu_block`` (a :meth:`BlockEngine.imu_block`) on the one sample ``s``; its output row."""
        self.load(s)
        imu_block(self.t, self.acc, self.gyro, self.out, 0, 1)
        return self.out.row(0)

    def load(self, s: ImuSample) -> None:
        """Copy one sample's time (s), specific force (m/s^2) and rate (rad/s) into the views."""
        b = self._buf
        b[0] = s.t
        a, w = s.acc_b, s.gyro_b
        b[1], b[2], b[3] = a[0], a[1], a[2]
        b[4], b[5], b[6] = w[0], w[1], w[2]


def run_batch(engine: Engine, log: Log, progress: Callable[[int], None] | None = None) -> pd.DataFrame:
    """Run ``engine.step`` over every sample of ``log``.

    Samples are processed in time order; at equal times GNSS, then magnetometer, then IMU.
    For a :class:`BlockEngine` the IMU samples between two other samples go to its compiled
    :meth:`~BlockEngine.imu_block` in one call (the same kernel its ``step()`` runs), the IMU
    columns are read in place and the output is written straight into the result's columns.

    Parameters
    ----------
    engine : Engine
        Any engine.
    log : Log
        The merged input.
    progress : callable, optional
        Called with the number of samples processed since the previous call (about every
        10,000).

    Returns
    -------
    pandas.DataFrame
        One row per usable IMU sample (rejected ones are counted in ``summary["skipped"]``)
        with :data:`OUTPUT_COLUMNS`; ``df.attrs`` carries ``events``
        (list of dicts), ``mount_yaw_rad`` (final) and ``summary``. An engine with a
        ``run_log(log, progress)`` method (the GNSS-only ``fixes`` engine: one row per
        processed epoch) runs the log itself through its compiled step.
    """
    run_log = getattr(engine, "run_log", None)
    if run_log is not None:
        df = run_log(log, progress).frame()
        df.attrs["events"] = list(engine.events)
        df.attrs["mount_yaw_rad"] = float(engine.mount_yaw_rad)
        df.attrs["summary"] = engine.summary()
        return df
    guard: InputGuard | None = getattr(engine, "guard", None)
    if hasattr(engine, "utc_offset_s"):  # the log's date, for engines that need one (the WMM's)
        setattr(engine, "utc_offset_s", log.utc_offset_s)  # noqa: B010
    src = _SampleSource(log, guard)
    n_imu = src.imu_t.size
    block = getattr(engine, "imu_block", None)
    g_t = src.gcols[0] if src.gcols else np.empty(0)
    # the block path bypasses the guard's time check: only for IMU times in order and not
    # before what the engine already saw (otherwise step() checks each sample)
    in_order = n_imu > 0 and bool(np.all(np.diff(src.imu_t) >= 0.0))
    if in_order and guard is not None:
        in_order = src.imu_t[0] >= guard.t_imu
    if block is not None and in_order:
        if guard is not None:  # the block path bypasses admit(): count its gaps here
            gaps = np.flatnonzero(np.diff(src.imu_t) > IMU_GAP_S) + 1
            n_gaps = int(gaps.size) + int(src.imu_t[0] - guard.t_imu > IMU_GAP_S and guard.t_imu > -math.inf)
            if n_gaps:
                t_first = float(src.imu_t[gaps[0]] if gaps.size else src.imu_t[0])
                guard.skip("imu_gap", t_first, n=n_gaps)
        kind, idx = _order([g_t, src.mag_t])
        out = OutputBlock(n_imu)
        is_g = kind == 0
        t_other = np.empty(kind.size)
        t_other[is_g] = g_t[idx[is_g]]
        t_other[~is_g] = src.mag_t[idx[~is_g]]
        # a GNSS or magnetometer sample comes before the IMU samples of its time
        cut = np.searchsorted(src.imu_t, t_other, side="left")
        i = 0
        done = 0
        for kd, j, c in zip(kind.tolist(), idx.tolist(), cut.tolist(), strict=True):
            while i < c:
                i1 = min(c, i + 10_000)
                block(src.imu_t, src.acc, src.gyro, out, i, i1)
                i = i1
                if progress is not None and i - done >= 10_000:
                    progress(i - done)
                    done = i
            engine.step(src.sample(kd, j))
        while i < n_imu:
            i1 = min(n_imu, i + 10_000)
            block(src.imu_t, src.acc, src.gyro, out, i, i1)
            i = i1
            if progress is not None:
                progress(i - done)
                done = i
        out.n = n_imu
        if guard is not None:
            guard.t_imu = float(src.imu_t[-1])
    else:
        kind, idx = _order([g_t, src.mag_t, src.imu_t])  # before the output block: lower peak
        out = OutputBlock(n_imu)
        add = out.add
        for c0 in range(0, kind.size, 10_000):  # Python ints for a chunk at a time (memory)
            c1 = min(kind.size, c0 + 10_000)
            for kd, j in zip(kind[c0:c1].tolist(), idx[c0:c1].tolist(), strict=True):
                o = engine.step(src.sample(kd, j))
                if o is not None:
                    add(o)
            if progress is not None:
                progress(c1 - c0)
    df = out.frame()
    df.attrs["events"] = list(engine.events)
    df.attrs["mount_yaw_rad"] = float(engine.mount_yaw_rad)
    df.attrs["summary"] = engine.summary()
    return df


def output_at(
    t: float,
    frame: TangentPlane,
    r_n: FloatArray,
    v_n: FloatArray,
    attitude: tuple[float, float, float],
    static: bool,
    std_ne: tuple[float, float],
    source: str,
) -> Output:
    """An :class:`Output` row from an NED position and velocity about ``frame``.

    Parameters
    ----------
    t : float
        Device time, s.
    frame : TangentPlane
        The engine's NED origin.
    r_n, v_n : numpy.ndarray
        NED position (m) and velocity (m/s).
    attitude : tuple of float
        Roll, pitch, yaw, rad.
    static : bool
        Static decision.
    std_ne : tuple of float
        1-sigma North and East position uncertainty, m.
    source : str
        ``fix``, ``dr``, ``lowpass`` or ``last_position``.
    """
    lat, lon, h = frame.from_ned(r_n)
    return Output(
        t,
        lat,
        lon,
        h,
        float(r_n[0]),
        float(r_n[1]),
        float(r_n[2]),
        float(v_n[0]),
        float(v_n[1]),
        float(v_n[2]),
        attitude[0],
        attitude[1],
        attitude[2],
        static,
        std_ne[0],
        std_ne[1],
        source,
    )


def output_without_position(t: float, attitude: tuple[float, float, float], static: bool) -> Output:
    """An :class:`Output` row before any position is known (``source="none"``, NaN position)."""
    nan = math.nan
    return Output(t, nan, nan, nan, nan, nan, nan, nan, nan, nan, *attitude, static, nan, nan, "none")


class StateSlot:
    """Float attribute backed by one element of the owner's float64 state array.

    Engines whose IMU step is a compiled kernel keep the scalars that the kernel and their
    Python (GNSS-rate) code share in one array (attribute ``array``, default ``_st``); these
    descriptors keep them readable and writable as ordinary attributes.
    """

    def __init__(self, index: int, array: str = "_st") -> None:
        self.index = index
        self.array = array

    def __get__(self, obj: Any, owner: Any = None) -> float:
        return float(getattr(obj, self.array)[self.index])

    def __set__(self, obj: Any, value: float) -> None:
        getattr(obj, self.array)[self.index] = value


class FlagSlot(StateSlot):
    """Boolean attribute backed by one element (0.0 / 1.0) of the owner's state array."""

    def __get__(self, obj: Any, owner: Any = None) -> bool:  # type: ignore[override]
        return bool(getattr(obj, self.array)[self.index] != 0.0)

    def __set__(self, obj: Any, value: bool) -> None:  # type: ignore[override]
        getattr(obj, self.array)[self.index] = 1.0 if value else 0.0


class CountSlot(StateSlot):
    """Integer attribute backed by one element of the owner's state array."""

    def __get__(self, obj: Any, owner: Any = None) -> int:  # type: ignore[override]
        return int(getattr(obj, self.array)[self.index])

    def __set__(self, obj: Any, value: int) -> None:  # type: ignore[override]
        getattr(obj, self.array)[self.index] = float(value)


@numba.njit(cache=True)
def write_attitude(
    floats: FloatArray, k: int, C: FloatArray, cos_mu: float, sin_mu: float, known: bool
) -> None:
    """Roll, pitch, yaw (rad) of ``C_nb`` (row-major, 9) into row ``k`` of an output block.

    With ``known`` the vehicle attitude ``C_nv = C_nb R_z(mount_yaw)^T`` (``cos_mu``, ``sin_mu``
    of the mount angle) is written, else the sensor's (compiled twin of :func:`output_at`'s
    attitude with :func:`iotnav.geo.dcm_to_rpy`).
    """
    if known:
        c00 = C[0] * cos_mu - C[1] * sin_mu
        c10 = C[3] * cos_mu - C[4] * sin_mu
        c20 = C[6] * cos_mu - C[7] * sin_mu
        c21 = C[6] * sin_mu + C[7] * cos_mu
    else:
        c00, c10, c20, c21 = C[0], C[3], C[6], C[7]
    floats[C_ROLL, k] = math.atan2(c21, C[8])
    floats[C_PITCH, k] = math.asin(max(-1.0, min(1.0, -c20)))
    floats[C_YAW, k] = math.atan2(c10, c00)


@numba.njit(cache=True)
def write_position(
    floats: FloatArray,
    k: int,
    r: FloatArray,
    v: FloatArray,
    std_n: float,
    std_e: float,
    frame: FloatArray,
) -> None:
    """NED position ``r`` (m), velocity ``v`` (m/s), their geodetic position and the 1-sigma into row ``k``.

    ``frame`` is ``[lat0_deg, lon0_deg, h0_m, k_n, k_e]`` of a :class:`TangentPlane`
    (:meth:`TangentPlane.constants`); ``lat = lat0 + north / k_n``, ``lon = lon0 + east / k_e``,
    ``h = h0 - down``.
    """
    floats[C_LAT, k] = frame[0] + r[0] / frame[3]
    floats[C_LON, k] = frame[1] + r[1] / frame[4]
    floats[C_HEIGHT, k] = frame[2] - r[2]
    floats[C_NORTH, k] = r[0]
    floats[C_EAST, k] = r[1]
    floats[C_DOWN, k] = r[2]
    floats[C_VN, k] = v[0]
    floats[C_VE, k] = v[1]
    floats[C_VD, k] = v[2]
    floats[C_STD_NORTH, k] = std_n
    floats[C_STD_EAST, k] = std_e


@numba.njit(cache=True)
def write_no_position(floats: FloatArray, k: int) -> None:
    """NaN position, velocity and sigma in row ``k`` (before any position is known)."""
    for c in (C_LAT, C_LON, C_HEIGHT, C_NORTH, C_EAST, C_DOWN, C_VN, C_VE, C_VD, C_STD_NORTH, C_STD_EAST):
        floats[c, k] = math.nan
