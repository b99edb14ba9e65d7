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

Modules: the state layout, configuration and fix samples are in :mod:`iotnav.engines.absfix_config`,
the batch runner in :mod:`iotnav.engines.absfix_run` (public names re-exported here).
"""

from __future__ import annotations

import math
from collections import deque
from typing import Any

import numpy as np
import numpy.typing as npt

from iotnav.engines import absfix_kernel as K
from iotnav.engines.absfix_config import (
    ACC,
    ALIGN_F,
    ALIGN_N,
    ALIGN_T0,
    ATT,
    BA,
    BG,
    GAPS,
    N_STATE,
    POS,
    VEL,
    AbsfixConfig,
    AbsFixSample,
    _FixRecord,
)
from iotnav.engines.absfix_config import (  # re-exported
    fixes_from_table as fixes_from_table,
)
from iotnav.engines.absfix_run import (  # re-exported
    _merged as _merged,
)
from iotnav.engines.absfix_run import (
    denoise_log as denoise_log,
)
from iotnav.engines.absfix_run import (
    run_with_fixes as run_with_fixes,
)
from iotnav.engines.base import (
    FlagSlot,
    GnssSample,
    ImuSample,
    InputGuard,
    MagSample,
    OneSampleBlock,
    Output,
    OutputBlock,
    TangentPlane,
    output_at,
    output_without_position,
)
from iotnav.geo import euler_to_dcm, normal_gravity
from iotnav.techniques import decoupled_bias as db
from iotnav.techniques.wavelet import StreamingDenoiser

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
