"""``absfix``: strapdown INS reset by absolute fixes, the decoupled method of Dabove et al. (2016).

Absolute fixes -- position and, when available, attitude, valid at ``t_valid`` and arriving at
``t_arrival`` (image-based positioning in the cloud, a total station, a UWB/visual system) --
are fused with a 6-axis IMU without any noise model:

1. **Alignment** (about 3 s, ``align_s``): the mean specific force of the first samples (the
   device is assumed still) gives roll and pitch, ``roll = atan2(-f_y, -f_z)``,
   ``pitch = atan2(f_x, sqrt(f_y^2 + f_z^2))``; used when the first fix carries no attitude
   (yaw is then ``initial_yaw_rad``). A fix *with* attitude initialises the attitude directly.
2. **Between fixes**: strapdown integration (:mod:`iotnav.strapdown`, flat-earth NED) of the
   bias-corrected accelerations and angular rates (paper eq. (1)-(2))::

       x_{k+1} = x_k + v_k dt + 1/2 (C_nb (f_b - b_a) + g_n) dt^2,   v_{k+1} = v_k + (...) dt
       C_nb,k+1 = C_nb,k exp([(omega_b - d_g) dt x])

   while accumulating the interval integrals ``V, D, W, M, Gamma, G`` of
   :mod:`iotnav.techniques.decoupled_bias`.
3. **At each fix** (epoch ``n + 2``): the gyro drift ``d_g`` from the attitudes of the last two
   fixes (three equations, paper eq. (4)); the velocity at epoch ``n`` and the three
   accelerometer biases ``b_a`` from the positions of the last three fixes (six linear
   equations, bias constant over the two intervals, paper eq. (3)); the velocity at the new fix
   ``v_{n+2} = v_n + V - W b_a``; the position (and, with ``attitude_reset``, the attitude) is
   reset to the fix. See :mod:`iotnav.techniques.decoupled_bias` for the equations.
4. **Latency**: fixes are applied at ``t_valid`` and the state re-propagated to now from a ring
   buffer of IMU samples and state snapshots (:mod:`iotnav.techniques.latency`, up to
   ``max_latency_s`` = 2 s); out-of-order fixes are applied in ``t_valid`` order, fixes older than
   the buffer are rejected and reported (``events``: ``fix_rejected``).
5. **Denoising** (optional, ``denoise``): the paper's Daubechies-4 level-7 wavelet denoising
   (:mod:`iotnav.techniques.wavelet`) of the six IMU channels, ``batch`` (whole log, by
   :func:`run_with_fixes`) or ``streaming`` (sliding window, delays the output by
   ``denoise_delay`` samples).

Estimation modes (``bias_mode`` for ``b_a``, ``drift_mode`` for ``d_g``), as the paper's Tables
3-7 compare them: ``none`` (held at zero; the velocity still comes from the last two fixes),
``fixes`` (the decoupled estimates above) and ``reference`` (the values of
``reference_acc_bias_mps2`` / ``reference_gyro_bias_rads``: the calibration of the unit against a
reference, the paper's Microstrain; the simulator's turn-on biases in the study of
:mod:`iotnav.eval.fix_interval`). With ``none`` or ``reference`` the velocity at a fix is solved
from the last two fixes with the bias known (:func:`~iotnav.techniques.decoupled_bias.velocity_known_bias`).
Before the second fix the velocity is taken as zero (the alignment assumes a still device).

Outputs: one :class:`~iotnav.engines.base.Output` per IMU sample, ``source`` ``fix`` at the epoch
a fix was applied, ``dr`` between fixes, ``none`` before the first fix; ``std_north`` and
``std_east`` are NaN (the method has no covariance). ``roll``, ``pitch``, ``yaw`` are those of
the sensor frame ``b``.

Using fixes with the other engines: a fix is a position (+ attitude) measurement valid at
``t_valid``; a Kalman engine takes it as ``z = X`` with ``H = [I 0 ...]`` and ``R = sigma_pos^2 I``
(and ``z = log(C_nb^T C_fix)`` for the attitude error states, ``R = sigma_att^2 I``), applied
through the same :class:`~iotnav.techniques.latency.LatencyBuffer` (its ``snapshot``/``restore``
holding ``x`` and ``P``). Until then ``iotnav run --fixes`` uses this engine.

Reference: P. Dabove, G. Ghinamo, A. M. Lingua, "Inertial sensors for smartphones navigation",
SpringerPlus 4:834, 2015 (cited in this project as Dabove et al. 2016).
"""

from __future__ import annotations

import dataclasses
import heapq
import math
from collections import deque
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any, NamedTuple, cast

import numpy as np
import numpy.typing as npt
import pandas as pd

from iotnav.engines import absfix_kernel as K
from iotnav.engines.base import (
    C_T,
    IMU_GAP_S,
    OUTPUT_COLUMNS,
    FlagSlot,
    GnssSample,
    ImuSample,
    InputGuard,
    MagSample,
    OneSampleBlock,
    Output,
    OutputBlock,
    TangentPlane,
    _order,
    _SampleSource,
    iter_samples,
    output_at,
    output_without_position,
)
from iotnav.engines.config import config_from_toml, dataclass_from_dict
from iotnav.geo import euler_to_dcm, normal_gravity
from iotnav.io.log import Log
from iotnav.techniques import decoupled_bias as db
from iotnav.techniques.wavelet import StreamingDenoiser, denoise, min_length

FloatArray = npt.NDArray[np.float64]

__all__ = [
    "ACC",
    "ATT",
    "BA",
    "BG",
    "N_STATE",
    "POS",
    "VEL",
    "AbsFixSample",
    "AbsfixConfig",
    "AbsfixEngine",
    "denoise_log",
    "fixes_from_table",
    "run_with_fixes",
]

#: Named state layout of the flat state array (STYLE §5; indices of :mod:`~iotnav.engines.absfix_kernel`).
POS = slice(K.X_POS, K.X_POS + 3)  # p_n, m
VEL = slice(K.X_VEL, K.X_VEL + 3)  # v_n, m/s
ATT = slice(K.X_ATT, K.X_ATT + 9)  # C_nb, row-major
BA = slice(K.X_BA, K.X_BA + 3)  # accelerometer bias b_a, m/s^2, in b
BG = slice(K.X_BG, K.X_BG + 3)  # gyro drift d_g, rad/s, in b
ACC = slice(K.X_ACC, K.X_ACC + db.N_ACC)  # interval integrals since the last fix (decoupled_bias.ACC_*)
ALIGN_T0 = K.X_ALIGN_T0  # time of the first IMU sample, s
ALIGN_N = K.X_ALIGN_N  # samples averaged for the alignment
ALIGN_F = slice(K.X_ALIGN_F, K.X_ALIGN_F + 3)  # sum of f_b over the alignment, m/s^2
GAPS = K.X_GAPS  # IMU gaps skipped
N_STATE = K.N_X  # then the started flag, the previous IMU sample and the fix-history version

_MODES = ("none", "fixes", "reference")
_DENOISE = ("off", "batch", "streaming")


@dataclass(frozen=True)
class AbsfixConfig:
    """Configuration of :class:`AbsfixEngine` (``[absfix]`` table of a TOML file).

    Attributes
    ----------
    align_s : float
        Initial alignment, s (paper: about 3 s).
    bias_mode, drift_mode : {"none", "fixes", "reference"}
        How the accelerometer bias and the gyro drift are obtained (module docstring).
    bias_window_fixes : int
        Fixes used for velocity and bias (paper: 3; more gives least squares).
    drift_window_fixes : int
        Fixes whose attitudes give the drift (paper: 2, consecutive; more: longer baseline).
    reference_acc_bias_mps2 : tuple of float
        Accelerometer bias for ``bias_mode = "reference"``, m/s^2, in ``b``.
    reference_gyro_bias_rads : tuple of float
        Gyro drift for ``drift_mode = "reference"``, rad/s, in ``b``.
    attitude_reset : bool
        Reset the attitude to the fix attitude at each fix (paper: yes).
    initial_yaw_rad : float
        Yaw when the first fix has no attitude, rad.
    max_latency_s : float
        Oldest fix validity accepted, s before the newest IMU sample (paper: up to 2 s).
    buffer_capacity : int
        Maximum IMU epochs buffered for latency compensation.
    max_imu_gap_s : float
        Longer gaps between IMU samples are not integrated (counted in the summary).
    denoise : {"off", "batch", "streaming"}
        Wavelet denoising of the IMU channels (Daubechies 4, level 7).
    denoise_window, denoise_delay : int
        Streaming denoiser window and output delay, samples.
    origin_lat_deg, origin_lon_deg, origin_height_m : float
        Geodetic origin of NED fixes (for lat/lon output and gravity); NaN: outputs in NED only.
    """

    align_s: float = 3.0
    bias_mode: str = "fixes"
    drift_mode: str = "fixes"
    bias_window_fixes: int = 3
    drift_window_fixes: int = 2
    reference_acc_bias_mps2: tuple[float, float, float] = (0.0, 0.0, 0.0)
    reference_gyro_bias_rads: tuple[float, float, float] = (0.0, 0.0, 0.0)
    attitude_reset: bool = True
    initial_yaw_rad: float = 0.0
    max_latency_s: float = 2.0
    buffer_capacity: int = 4096
    max_imu_gap_s: float = 0.5
    denoise: str = "off"
    denoise_window: int = 1024
    denoise_delay: int = 256
    origin_lat_deg: float = math.nan
    origin_lon_deg: float = math.nan
    origin_height_m: float = 0.0

    def __post_init__(self) -> None:
        for name in ("bias_mode", "drift_mode"):
            if getattr(self, name) not in _MODES:
                raise ValueError(f"{name}: expected one of {', '.join(_MODES)}, got {getattr(self, name)!r}")
        if self.denoise not in _DENOISE:
            raise ValueError(f"denoise: expected one of {', '.join(_DENOISE)}, got {self.denoise!r}")
        if self.bias_window_fixes < 3:
            raise ValueError("bias_window_fixes must be >= 3 (six equations need three fixes)")
        if self.drift_window_fixes < 2:
            raise ValueError("drift_window_fixes must be >= 2")
        if self.align_s < 0 or self.max_latency_s < 0:
            raise ValueError("align_s and max_latency_s must be >= 0")
        for name in ("reference_acc_bias_mps2", "reference_gyro_bias_rads"):
            if len(getattr(self, name)) != 3:
                raise ValueError(f"{name}: expected three values")

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> AbsfixConfig:
        """Build from a mapping (unknown keys raise ValueError)."""
        return cast(AbsfixConfig, dataclass_from_dict(cls(), data, "absfix"))

    @classmethod
    def from_toml(cls, path: str | Path) -> AbsfixConfig:
        """Load ``[absfix]`` (or top-level keys) from a TOML file."""
        return cast(AbsfixConfig, config_from_toml(path, cls(), "absfix"))

    def to_dict(self) -> dict[str, Any]:
        """Plain dict (for ``summary.json``)."""
        return {k: (list(v) if isinstance(v, tuple) else v) for k, v in dataclasses.asdict(self).items()}

    def replace(self, **changes: Any) -> AbsfixConfig:
        """Copy with some fields replaced."""
        return dataclasses.replace(self, **changes)


class AbsFixSample(NamedTuple):
    """One absolute fix.

    Attributes
    ----------
    t_valid : float
        Device time the fix refers to, s.
    t_arrival : float
        Device time it became available, s (``>= t_valid``).
    pos_n : numpy.ndarray
        Position in the local NED frame ``n``, m, ``(3,)``; NaN when given geodetically.
    lat_deg, lon_deg, height_m : float
        Geodetic position (degrees, ellipsoidal m); NaN when given in NED.
    att : numpy.ndarray
        Roll, pitch, yaw of ``b`` in ``n`` (ZYX), rad, ``(3,)``; NaN without attitude.
    sigma_pos_m, sigma_att_rad : float
        Stated 1-sigma accuracies (informative: the decoupled method uses no noise model).
    """

    t_valid: float
    t_arrival: float
    pos_n: FloatArray
    lat_deg: float
    lon_deg: float
    height_m: float
    att: FloatArray
    sigma_pos_m: float = math.nan
    sigma_att_rad: float = math.nan

    @property
    def t(self) -> float:
        """Merge time in a sample stream: the arrival time, s."""
        return self.t_arrival

    @property
    def has_attitude(self) -> bool:
        """True when roll, pitch and yaw are all given."""
        return bool(np.all(np.isfinite(self.att)))

    @property
    def geodetic(self) -> bool:
        """True when the position is given as latitude / longitude / height."""
        return math.isfinite(self.lat_deg) and math.isfinite(self.lon_deg)


def fixes_from_table(df: pd.DataFrame) -> list[AbsFixSample]:
    """Fixes from a :func:`iotnav.io.fixes.read_fixes` table or a simulator ``fixes`` table.

    Parameters
    ----------
    df : pandas.DataFrame
        Columns ``t_valid``, ``t_arrival`` and either ``lat_deg, lon_deg, height_m`` (or ``lat,
        lon, height``) or ``north_m, east_m, down_m``; optional ``roll, pitch, yaw`` (rad),
        ``sigma_pos_m``, ``sigma_att_rad``.

    Returns
    -------
    list of AbsFixSample
        In table order.
    """
    n = len(df)

    def col(*names: str) -> FloatArray:
        for c in names:
            if c in df.columns:
                return df[c].to_numpy(dtype=float)
        return np.full(n, math.nan)

    tv, ta = col("t_valid"), col("t_arrival")
    lat, lon, h = col("lat_deg", "lat"), col("lon_deg", "lon"), col("height_m", "height")
    ned = np.column_stack([col("north_m", "north"), col("east_m", "east"), col("down_m", "down")])
    att = np.column_stack([col("roll"), col("pitch"), col("yaw")])
    sp, sa = col("sigma_pos_m"), col("sigma_att_rad")
    h = np.where(np.isfinite(lat) & ~np.isfinite(h), 0.0, h)
    return [
        AbsFixSample(
            float(tv[i]),
            float(ta[i]),
            ned[i].copy(),
            float(lat[i]),
            float(lon[i]),
            float(h[i]),
            att[i].copy(),
            float(sp[i]),
            float(sa[i]),
        )
        for i in range(n)
    ]


class _FixRecord(NamedTuple):
    """A fix as remembered for the decoupled solution (immutable)."""

    t: float
    X: FloatArray
    C: FloatArray | None
    interval: db.IntervalIntegrals | None  # from the previous fix to this one


_Snap = tuple[FloatArray, tuple[_FixRecord, ...]]


class AbsfixEngine:
    """Strapdown INS reset by absolute fixes with decoupled bias/drift estimation.

    The IMU step is compiled (:mod:`iotnav.engines.absfix_kernel`): :meth:`imu_block` runs it
    over a block of samples (batch), ``step(ImuSample)`` over a one-sample block (streaming)
    and a late fix re-propagates the buffered samples with the same code. The fixes are
    applied in Python (:meth:`apply_fix`), in time order: the kernel stops at the sample where
    a pending fix is due; a late fix restores the buffered snapshot of its epoch and replays.

    Parameters
    ----------
    config : AbsfixConfig, optional
        Configuration (defaults: the paper's method).

    Attributes
    ----------
    x : numpy.ndarray
        Flat state, layout ``POS, VEL, ATT, BA, BG, ACC, ALIGN_*`` (module constants), then
        the kernel's bookkeeping (:mod:`~iotnav.engines.absfix_kernel` ``X_*``).
    events : list of dict
        ``first_fix``, ``fix_rejected`` (with ``reason``), ``fix_out_of_order``, ``attitude_missing``.
    last_revision : tuple of Output
        Revised outputs of the epochs re-propagated by the last applied fix (oldest first).
    released : list of Output
        Every output released by the last IMU step (several at once when the streaming
        denoiser's window first fills; ``step`` returns the newest).
    """

    started = FlagSlot(K.X_STARTED, "x")

    def __init__(self, config: AbsfixConfig | None = None) -> None:
        self.config = c = config or AbsfixConfig()
        if c.max_latency_s < 0.0 or c.buffer_capacity < 1:
            raise ValueError("max_latency_s must be >= 0 and buffer_capacity >= 1")
        self.x = np.zeros(N_STATE)
        self.x[ATT] = np.eye(3).ravel()
        self.x[ALIGN_T0] = math.nan
        self.x[K.X_LAST_T] = math.nan
        db.reset_flat(self.x[ACC])
        #: fix histories by version (``x[X_HIST]``; the ring's snapshots refer to them)
        self._hists: dict[int, tuple[_FixRecord, ...]] = {0: ()}
        self._next_hist = 1
        self.frame: TangentPlane | None = None
        self._geo = np.full(5, math.nan)  # the frame's constants() for the kernel
        self.g_n = np.array([0.0, 0.0, normal_gravity(45.0, 0.0)])
        if math.isfinite(c.origin_lat_deg) and math.isfinite(c.origin_lon_deg):
            self._set_frame(c.origin_lat_deg, c.origin_lon_deg, c.origin_height_m)
        self._prm = np.empty(K.N_PRM)
        self._prm[K.P_ALIGN_S] = c.align_s
        self._prm[K.P_MAX_GAP] = c.max_imu_gap_s
        self._prm[K.P_MAX_LATENCY] = c.max_latency_s
        self._prm[K.P_CAPACITY] = c.buffer_capacity
        # latency ring (absfix_kernel docstring): 5 s at 100 Hz to start, grown when full
        size = min(c.buffer_capacity, 512) + 1
        self._r_t = np.zeros(size)
        self._r_imu = np.zeros((size, 6))
        self._r_snap = np.zeros((size, N_STATE))
        self._rb = np.zeros(K.N_RB)
        self._rb[K.RB_DT] = math.nan
        self._pending: list[AbsFixSample] = []
        self._t_due = math.inf
        self._fixes_at: dict[int, list[AbsFixSample]] = {}  # ring serial -> fixes applied there
        self._rev = OutputBlock(c.buffer_capacity + 1)  # revised rows of the last replay
        self._n_rev = 0
        self._one = OneSampleBlock()
        self.events: list[dict[str, Any]] = []
        self.guard = InputGuard(self.events)
        self.released: list[Output] = []
        # fixes: applied late (with re-propagation), pending (applied when the IMU reached them)
        self.counts = {"imu": 0, "fixes_in": 0, "applied": 0, "pending": 0, "rejected": 0, "ignored": 0}
        self._max_tv = -math.inf
        self._first_reported = False
        self._latencies: list[float] = []
        self._den: list[StreamingDenoiser] | None = None
        self._den_t: deque[float] = deque()
        if c.denoise == "streaming":
            self._den = [StreamingDenoiser(c.denoise_window, c.denoise_delay) for _ in range(6)]

    def _set_frame(self, lat: float, lon: float, h: float) -> None:
        self.frame = TangentPlane(lat, lon, h)
        self._geo[:] = self.frame.constants()
        self.g_n = np.array([0.0, 0.0, normal_gravity(lat, h)])

    @property
    def hist(self) -> tuple[_FixRecord, ...]:
        """The fixes remembered for the decoupled solution (newest last)."""
        return self._hists[int(self.x[K.X_HIST])]

    @hist.setter
    def hist(self, value: tuple[_FixRecord, ...]) -> None:
        k = self._next_hist
        self._next_hist += 1
        self._hists[k] = value
        self.x[K.X_HIST] = k

    @property
    def last_revision(self) -> tuple[Output, ...]:
        """Revised outputs of the epochs re-propagated by the last applied fix (oldest first)."""
        return tuple(self._rev.row(i) for i in range(self._n_rev))

    @last_revision.setter
    def last_revision(self, value: tuple[Output, ...]) -> None:
        if value:
            raise ValueError("last_revision can only be cleared")
        self._n_rev = 0

    # ------------------------------------------------------------------ protocol
    @property
    def mount_yaw_rad(self) -> float:
        """Not estimated by this engine (outputs are in the sensor frame): NaN."""
        return math.nan

    def summary(self) -> dict[str, Any]:
        """Configuration, final inner state and counts (for ``summary.json``)."""
        lat = np.asarray(self._latencies)
        return {
            "skipped": dict(self.guard.skipped),
            "engine": "absfix",
            "config": self.config.to_dict(),
            "acc_bias_mps2": self.x[BA].tolist(),
            "gyro_drift_rads": self.x[BG].tolist(),
            "counts": dict(self.counts),
            "imu_gaps_skipped": int(self.x[GAPS]),
            "replayed_samples": int(self._rb[K.RB_REPLAYED]),
            "latency_s": {
                "mean": float(lat.mean()) if lat.size else math.nan,
                "max": float(lat.max()) if lat.size else math.nan,
            },
            "origin": None
            if self.frame is None
            else {
                "lat_deg": self.frame.lat0_deg,
                "lon_deg": self.frame.lon0_deg,
                "height_m": self.frame.h0_m,
            },
        }

    def step(self, sample: Any) -> Output | None:
        """Process one sample: an :class:`ImuSample` (returns an Output) or an :class:`AbsFixSample`.

        GNSS and magnetometer samples are ignored (counted).
        """
        sample = self.guard.admit(sample)
        if sample is None:
            return None
        if isinstance(sample, ImuSample):
            self.counts["imu"] += 1
            out: Output | None
            if self._den is None:
                out = self._one.run(self._imu_run, sample)
                self.released = [out]
            else:
                self.released = self._denoised(sample)
                out = self.released[-1] if self.released else None
            self._check_started(sample.t)
            return out
        if isinstance(sample, AbsFixSample):
            self._fix_arrived(sample)
            self._check_started(sample.t_arrival)
            return None
        if isinstance(sample, (GnssSample, MagSample)):
            self.counts["ignored"] += 1
            return None
        raise TypeError(f"absfix: unsupported sample {type(sample).__name__}")

    def imu_block(
        self,
        t: FloatArray,
        acc: tuple[FloatArray, FloatArray, FloatArray],
        gyro: tuple[FloatArray, FloatArray, FloatArray],
        out: OutputBlock,
        i0: int,
        i1: int,
    ) -> None:
        """Process IMU samples ``i0 .. i1-1`` (compiled), writing row ``k`` of ``out`` for sample ``k``.

        ``t`` device time (s); ``acc`` specific force along sensor x, y, z (m/s^2); ``gyro``
        angular rate about sensor x, y, z (rad/s), in time order (the caller's
        :class:`~iotnav.engines.base.InputGuard` checks). Not with the streaming denoiser
        (its samples come out delayed): ``step()`` handles that.
        """
        if self._den is not None:
            raise ValueError("imu_block: the streaming denoiser needs step()")
        self.counts["imu"] += i1 - i0
        self._imu_run(t, acc, gyro, out, i0, i1)

    def _imu_run(
        self,
        t: FloatArray,
        acc: tuple[FloatArray, FloatArray, FloatArray],
        gyro: tuple[FloatArray, FloatArray, FloatArray],
        out: OutputBlock,
        i0: int,
        i1: int,
    ) -> None:
        """The kernel over ``i0 .. i1-1``; the pending fixes due at a sample applied there."""
        k = i0
        while k < i1:
            k, flags = K.imu_run(
                t,
                acc[0],
                acc[1],
                acc[2],
                gyro[0],
                gyro[1],
                gyro[2],
                out.floats,
                out.static,
                out.source,
                k,
                i1,
                self.x,
                self.g_n,
                self._prm,
                self._r_t,
                self._r_imu,
                self._r_snap,
                self._rb,
                self._geo,
                self._t_due,
            )
            if flags & K.EV_FULL:
                self._grow_ring()
                continue
            if flags & K.EV_DUE:
                tk = float(t[k])
                lim = tk + self._half()
                due = sorted((f for f in self._pending if f.t_valid <= lim), key=lambda f: f.t_valid)
                self._pending = [f for f in self._pending if f.t_valid > lim]
                self._t_due = min((f.t_valid for f in self._pending), default=math.inf)
                self._fixes_at[self._newest_serial()] = due
                for f in due:
                    self.apply_fix(f)
                K.write_row(out.floats, out.static, out.source, k, tk, self.x, self._geo, True)
                K.evict(self._r_t, self._rb, self._prm)
                if self._den is None:  # step() reports it at the input sample's time
                    self._check_started(tk)
                k += 1

    def flush(self) -> list[Output]:
        """Outputs still held by the streaming denoiser (end of stream)."""
        if self._den is None:
            return []
        chans = [d.flush() for d in self._den]
        outs = []
        for k in range(len(chans[0])):
            t = self._den_t.popleft()
            s = ImuSample(
                t, np.array([chans[i][k] for i in range(3)]), np.array([chans[i][k] for i in range(3, 6)])
            )
            outs.append(self._one.run(self._imu_run, s))
        return outs

    def _denoised(self, s: ImuSample) -> list[Output]:
        assert self._den is not None
        self._den_t.append(s.t)
        vals = np.concatenate([s.acc_b, s.gyro_b])
        chans = [d.push(vals[i]) for i, d in enumerate(self._den)]
        outs: list[Output] = []
        for k in range(len(chans[0])):
            t = self._den_t.popleft()
            ds = ImuSample(
                t, np.array([chans[i][k] for i in range(3)]), np.array([chans[i][k] for i in range(3, 6)])
            )
            outs.append(self._one.run(self._imu_run, ds))
        return outs

    # ------------------------------------------------------------------ latency ring
    def _grow_ring(self) -> None:
        """Twice the slots (at most ``buffer_capacity + 1``), the entries moved to their new slots."""
        old = self._r_t.size
        size = min(2 * old, self.config.buffer_capacity + 1)
        if size <= old:  # pragma: no cover - eviction keeps count <= capacity
            raise RuntimeError("absfix: latency ring full at its capacity")
        head, count = int(self._rb[K.RB_HEAD]), int(self._rb[K.RB_COUNT])
        s = head + np.arange(count)
        r_t, r_imu, r_snap = np.zeros(size), np.zeros((size, 6)), np.zeros((size, N_STATE))
        r_t[s % size], r_imu[s % size], r_snap[s % size] = (
            self._r_t[s % old],
            self._r_imu[s % old],
            self._r_snap[s % old],
        )
        self._r_t, self._r_imu, self._r_snap = r_t, r_imu, r_snap

    def _half(self) -> float:
        dt = float(self._rb[K.RB_DT])
        return 0.5 * dt if math.isfinite(dt) else 0.0

    def _newest_serial(self) -> int:
        return int(self._rb[K.RB_HEAD]) + int(self._rb[K.RB_COUNT]) - 1

    def _ring_times(self) -> FloatArray:
        head, count = int(self._rb[K.RB_HEAD]), int(self._rb[K.RB_COUNT])
        return self._r_t[(head + np.arange(count)) % self._r_t.size]

    def _process_fix(self, fix: AbsFixSample) -> tuple[str, str]:
        """:meth:`iotnav.techniques.latency.LatencyBuffer.process_fix` on the compiled ring: status, reason."""
        tv = float(fix.t_valid)
        if not math.isfinite(tv):
            return "rejected", "t_valid is not finite"
        half = self._half()
        ts = self._ring_times()
        if ts.size == 0 or tv > ts[-1] + half:
            self._pending.append(fix)
            self._t_due = min(self._t_due, tv)
            return "pending", ""
        if tv < ts[0] - half:
            return (
                "rejected",
                f"valid {ts[-1] - tv:.3f} s before the newest IMU sample; the buffer "
                f"holds {ts[-1] - ts[0]:.3f} s (max_latency_s {self.config.max_latency_s:g})",
            )
        head = int(self._rb[K.RB_HEAD])
        for s in [s for s in self._fixes_at if s < head]:
            del self._fixes_at[s]
        sj = head + int(np.argmin(np.abs(ts - tv)))  # epoch nearest t_valid (the first on ties)
        at = self._fixes_at.setdefault(sj, [])
        at.append(fix)
        at.sort(key=lambda f: f.t_valid)
        self._replay(sj, head + ts.size)
        return "applied", ""

    def _replay(self, sj: int, end: int) -> None:
        """Restore epoch ``sj``'s snapshot and re-propagate to the newest epoch, applying the fixes on the way."""
        size = self._r_t.size
        self.x[:] = self._r_snap[sj % size]
        rev = self._rev
        args = (self.x, self.g_n, self._prm, self._r_t, self._r_imu, self._r_snap, self._rb, self._geo)
        rows = (rev.floats, rev.static, rev.source)
        s = sj
        for fs in sorted(k for k in self._fixes_at if sj <= k < end):
            if fs > s:
                K.replay_run(*args, s, fs, True, *rows, s - sj)
            if fs > sj:
                K.replay_run(*args, fs, fs + 1, False, *rows, 0)
            for f in self._fixes_at[fs]:
                self.apply_fix(f)
            K.write_row(*rows, fs - sj, self._r_t[fs % size], self.x, self._geo, True)
            s = fs + 1
        K.replay_run(*args, s, end, True, *rows, s - sj)
        self._n_rev = end - sj
        head = int(self._rb[K.RB_HEAD])
        live = {int(v) for v in self._r_snap[(head + np.arange(end - head)) % size, K.X_HIST]}
        live.add(int(self.x[K.X_HIST]))
        for k in [k for k in self._hists if k not in live]:
            del self._hists[k]

    def _fix_arrived(self, f: AbsFixSample) -> None:
        self.counts["fixes_in"] += 1
        if self.frame is None:
            if f.geodetic:
                self._set_frame(f.lat_deg, f.lon_deg, f.height_m)
        if not f.geodetic and not np.all(np.isfinite(f.pos_n)):
            self._reject(f, "no position")
            return
        if f.geodetic and self.frame is None:  # pragma: no cover - frame set above
            self._reject(f, "no frame")
            return
        if not self.started and not f.has_attitude:
            t_now = float(self._ring_times()[-1]) if self._rb[K.RB_COUNT] > 0 else math.nan
            if not (math.isfinite(t_now) and t_now - self.x[ALIGN_T0] >= self.config.align_s):
                self._reject(f, "alignment not complete and the fix has no attitude")
                return
        status, reason = self._process_fix(f)
        if status == "rejected":
            self._reject(f, reason)
            return
        self.counts[status] += 1
        if status == "applied":
            self._latencies.append(f.t_arrival - f.t_valid)
            if f.t_valid < self._max_tv:
                self.events.append({"type": "fix_out_of_order", "t": f.t_arrival, "t_valid": f.t_valid})
        elif status == "pending":
            self._latencies.append(f.t_arrival - f.t_valid)
        self._max_tv = max(self._max_tv, f.t_valid)

    def _check_started(self, t: float) -> None:
        if self.started and not self._first_reported:
            self._first_reported = True
            self.events.append({"type": "first_fix", "t": t, "t_valid": self.hist[0].t})

    def _reject(self, f: AbsFixSample, reason: str) -> None:
        self.counts["rejected"] += 1
        self.events.append({"type": "fix_rejected", "t": f.t_arrival, "t_valid": f.t_valid, "reason": reason})

    # ------------------------------------------------------------------ Replayable
    def snapshot(self) -> _Snap:
        """Copy of the whole mutable state (:class:`~iotnav.techniques.latency.Replayable`)."""
        return (self.x.copy(), self.hist)

    def restore(self, snap: _Snap) -> None:
        """Return to a snapshot."""
        x, hist = snap
        self.x[:] = x
        self.hist = hist

    def propagate(self, sample: ImuSample) -> None:
        """Advance the state to ``sample.t`` with the previous sample (:func:`~iotnav.engines.absfix_kernel.propagate`)."""
        a, w = sample.acc_b, sample.gyro_b
        K.propagate(self.x, self.g_n, self._prm, float(sample.t), a[0], a[1], a[2], w[0], w[1], w[2])

    def _position(self, f: AbsFixSample) -> FloatArray:
        if f.geodetic:
            assert self.frame is not None
            r = self.frame.to_ned(f.lat_deg, f.lon_deg, f.height_m)
            if self.frame.follow(r):  # long routes: the plane re-linearised at the fix (same coordinates)
                self._geo[:] = self.frame.constants()
            return r
        return np.asarray(f.pos_n, dtype=float)

    def _levelled(self) -> FloatArray:
        x = self.x
        n = max(x[ALIGN_N], 1.0)
        fx, fy, fz = x[ALIGN_F] / n
        roll = math.atan2(-fy, -fz)
        pitch = math.atan2(fx, math.hypot(fy, fz))
        return np.asarray(euler_to_dcm(roll, pitch, self.config.initial_yaw_rad), dtype=float)

    def apply_fix(self, f: AbsFixSample) -> None:
        """Reset to a fix valid now and update the drift, bias and velocity (module docstring)."""
        c = self.config
        x = self.x
        X = self._position(f)
        C_fix = np.asarray(euler_to_dcm(*f.att), dtype=float) if f.has_attitude else None
        if not self.started:
            self.started = True
            x[POS] = X
            x[VEL] = 0.0
            x[ATT] = (C_fix if C_fix is not None else self._levelled()).ravel()
            x[BA] = c.reference_acc_bias_mps2 if c.bias_mode == "reference" else 0.0
            x[BG] = c.reference_gyro_bias_rads if c.drift_mode == "reference" else 0.0
            db.reset_flat(x[ACC])
            self.hist = (_FixRecord(f.t_valid, X, C_fix, None),)
            return
        interval = db.interval_from_flat(x[ACC])
        keep = max(c.bias_window_fixes, c.drift_window_fixes)
        hist = (*self.hist, _FixRecord(f.t_valid, X, C_fix, interval))[-keep:]
        self.hist = hist
        if c.drift_mode == "fixes":
            m = min(c.drift_window_fixes, len(hist))
            first, last = hist[-m], hist[-1]
            if m >= 2 and first.C is not None and last.C is not None:
                ivs = [r.interval for r in hist[-m + 1 :] if r.interval is not None]
                comp = db.compose_all(ivs)
                if comp.dt_s > 0.0:
                    x[BG] = db.solve_gyro_drift(first.C, last.C, comp)
        if c.bias_mode == "fixes" and len(hist) >= 3:
            k = min(c.bias_window_fixes, len(hist))
            recs = hist[-k:]
            ivs = [r.interval for r in recs[1:] if r.interval is not None]
            _, b, v_last = db.solve_velocity_bias(np.array([r.X for r in recs]), ivs)
            x[BA] = b
            x[VEL] = v_last
        elif interval.dt_s > 0.0:
            _, v1 = db.velocity_known_bias(hist[-2].X, X, interval, x[BA])
            x[VEL] = v1
        x[POS] = X
        if C_fix is not None and c.attitude_reset:
            x[ATT] = C_fix.ravel()
        db.reset_flat(x[ACC])

    def output(self, t: float, fixed: bool) -> Output:
        """Output row of the current state at ``t``."""
        nan = math.nan
        x = self.x
        if not self.started:
            return output_without_position(t, (nan, nan, nan), False)
        r, v = x[POS], x[VEL]
        C = x[ATT]  # row-major C_nb; ZYX Euler angles written out (cheap per sample)
        roll = math.atan2(C[7], C[8])
        pitch = -math.asin(max(-1.0, min(1.0, float(C[6]))))
        yaw = math.atan2(C[3], C[0])
        frame = self.frame if self.frame is not None else TangentPlane(nan, nan, nan)
        return output_at(t, frame, r, v, (roll, pitch, yaw), False, (nan, nan), "fix" if fixed else "dr")


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
