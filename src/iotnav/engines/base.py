"""Engine protocol, sample and output records, and the batch runner (STYLE §7).

Streaming and batch share one ``step()``: a device or gateway calls ``engine.step(sample)``
for each sample as it arrives; :func:`run_batch` merges a :class:`~iotnav.io.log.Log` by time
(GNSS, then magnetometer, then IMU at equal times) and loops over the same ``step()``,
collecting one :class:`Output` per IMU sample into a :class:`pandas.DataFrame`.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Iterator
from typing import Any, NamedTuple, Protocol

import numpy as np
import numpy.typing as npt
import pandas as pd

from iotnav.io.log import Log

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
    """One GNSS epoch (columns of :data:`iotnav.io.schema.GNSS_COLUMNS`, SI / degrees)."""

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
        """Process one sample; an :class:`Output` for IMU samples, None otherwise."""
        ...

    @property
    def mount_yaw_rad(self) -> float:
        """Current mount-angle estimate, rad."""
        ...

    def summary(self) -> dict[str, Any]:
        """Configuration and final state, for ``summary.json``."""
        ...


def iter_samples(log: Log) -> Iterator[Sample]:
    """Samples of a log in time order; at equal times GNSS, then magnetometer, then IMU."""
    g, imu, mg = log.gnss, log.imu, log.mag
    parts: list[tuple[np.ndarray, int]] = []
    if len(g):
        parts.append((g["t"].to_numpy(float), 0))
    if len(mg):
        parts.append((mg["t"].to_numpy(float), 1))
    if len(imu):
        parts.append((imu["t"].to_numpy(float), 2))
    if not parts:
        return
    t_all = np.concatenate([p[0] for p in parts])
    kind = np.concatenate([np.full(p[0].size, p[1]) for p in parts])
    idx = np.concatenate([np.arange(p[0].size) for p in parts])
    order = np.lexsort((kind, t_all))
    if len(g):
        gcols = {
            c: g[c].to_numpy()
            for c in (
                "t",
                "lat_deg",
                "lon_deg",
                "height_m",
                "pdop",
                "hdop",
                "num_sv",
                "speed_mps",
                "course_rad",
                "vn",
                "ve",
                "vd",
                "h_acc_m",
                "v_acc_m",
                "s_acc_mps",
                "quality",
            )
        }
        gcv = g["course_valid"].to_numpy(bool)
        gv = g["valid"].to_numpy(bool)
    if len(imu):
        acc = imu[["acc_x", "acc_y", "acc_z"]].to_numpy(float)
        gyr = imu[["gyro_x", "gyro_y", "gyro_z"]].to_numpy(float)
        it = imu["t"].to_numpy(float)
    if len(mg):
        mag = mg[["mag_x_ut", "mag_y_ut", "mag_z_ut"]].to_numpy(float)
        magt = mg["t"].to_numpy(float)
    for k in order:
        j = int(idx[k])
        kd = int(kind[k])
        if kd == 2:
            yield ImuSample(float(it[j]), acc[j], gyr[j])
        elif kd == 0:
            yield GnssSample(
                float(gcols["t"][j]),
                float(gcols["lat_deg"][j]),
                float(gcols["lon_deg"][j]),
                float(gcols["height_m"][j]),
                float(gcols["pdop"][j]),
                float(gcols["hdop"][j]),
                int(gcols["num_sv"][j]),
                float(gcols["speed_mps"][j]),
                float(gcols["course_rad"][j]),
                bool(gcv[j]),
                bool(gv[j]),
                float(gcols["vn"][j]),
                float(gcols["ve"][j]),
                float(gcols["vd"][j]),
                float(gcols["h_acc_m"][j]),
                float(gcols["v_acc_m"][j]),
                float(gcols["s_acc_mps"][j]),
                int(gcols["quality"][j]),
            )
        else:
            yield MagSample(float(magt[j]), mag[j])


class _ColumnRecorder:
    """Collects :class:`Output` rows into preallocated numpy columns (about 130 bytes a row).

    A list of NamedTuples costs about 1 KB a row (tuple, 15 float objects, then the
    DataFrame conversion); a day of 100 Hz data would need about 9 GB that way.
    """

    _FLOAT = tuple(k for k, c in enumerate(OUTPUT_COLUMNS) if c not in ("static", "source"))

    def __init__(self, capacity: int) -> None:
        n = max(capacity, 16)
        self.n = 0
        self.floats = np.empty((len(self._FLOAT), n))
        self.static = np.empty(n, dtype=bool)
        self.source = np.empty(n, dtype=np.int16)
        self.names: list[str] = []
        self.codes: dict[str, int] = {}

    def add(self, out: Output) -> None:
        """Append one row (the arrays double when full)."""
        i = self.n
        if i == self.static.size:
            self.floats = np.concatenate([self.floats, np.empty_like(self.floats)], axis=1)
            self.static = np.concatenate([self.static, np.empty_like(self.static)])
            self.source = np.concatenate([self.source, np.empty_like(self.source)])
        col = self.floats
        for j, k in enumerate(self._FLOAT):
            col[j, i] = out[k]
        self.static[i] = out.static
        src = out.source
        code = self.codes.get(src)
        if code is None:
            code = self.codes[src] = len(self.names)
            self.names.append(src)
        self.source[i] = code
        self.n = i + 1

    def frame(self) -> pd.DataFrame:
        """The rows as a DataFrame with :data:`OUTPUT_COLUMNS` (``source`` as str objects)."""
        n = self.n
        data: dict[str, Any] = {OUTPUT_COLUMNS[k]: self.floats[j, :n] for j, k in enumerate(self._FLOAT)}
        data["static"] = self.static[:n]
        data["source"] = np.asarray(self.names or [""], dtype=object)[self.source[:n]]
        return pd.DataFrame({c: data[c] for c in OUTPUT_COLUMNS}, copy=False)


def run_batch(engine: Engine, log: Log, progress: Callable[[int], None] | None = None) -> pd.DataFrame:
    """Run ``engine.step`` over every sample of ``log``.

    Parameters
    ----------
    engine : Engine
        Any engine.
    log : Log
        The merged input.
    progress : callable, optional
        Called with the number of samples processed since the previous call (every 10,000).

    Returns
    -------
    pandas.DataFrame
        One row per IMU sample with :data:`OUTPUT_COLUMNS`; ``df.attrs`` carries ``events``
        (list of dicts), ``mount_yaw_rad`` (final) and ``summary``.
    """
    rec = _ColumnRecorder(len(log.imu))
    add = rec.add
    for k, s in enumerate(iter_samples(log), start=1):
        out = engine.step(s)
        if out is not None:
            add(out)
        if progress is not None and k % 10_000 == 0:
            progress(10_000)
    df = rec.frame()
    df.attrs["events"] = list(engine.events)
    df.attrs["mount_yaw_rad"] = float(engine.mount_yaw_rad)
    df.attrs["summary"] = engine.summary()
    return df


class TangentPlane:
    """Local NED about a geodetic origin with the meridian/prime-vertical radii at the origin.

    ``north = dlat (M + h0)``, ``east = dlon (N + h0) cos(lat0)``, ``down = -(h - h0)``: exact
    inverse pair, per-sample cheap, within centimetres of the rigorous transform over a few km
    (curvature of the Earth is neglected in ``down``).
    """

    def __init__(self, lat0_deg: float, lon0_deg: float, h0_m: float) -> None:
        a, e2 = 6378137.0, 6.69437999014e-3
        s = math.sin(math.radians(lat0_deg))
        w = math.sqrt(1.0 - e2 * s * s)
        self.lat0_deg, self.lon0_deg, self.h0_m = lat0_deg, lon0_deg, h0_m
        self.k_n = math.radians(1.0) * (a * (1.0 - e2) / w**3 + h0_m)
        self.k_e = math.radians(1.0) * (a / w + h0_m) * math.cos(math.radians(lat0_deg))

    def to_ned(self, lat_deg: float, lon_deg: float, height_m: float) -> FloatArray:
        """Geodetic (degrees, m) to NED (m)."""
        return np.array(
            [(lat_deg - self.lat0_deg) * self.k_n, (lon_deg - self.lon0_deg) * self.k_e, self.h0_m - height_m]
        )

    def from_ned(self, r_n: FloatArray) -> tuple[float, float, float]:
        """NED (m) to geodetic (degrees, m)."""
        return (
            self.lat0_deg + float(r_n[0]) / self.k_n,
            self.lon0_deg + float(r_n[1]) / self.k_e,
            self.h0_m - float(r_n[2]),
        )


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
