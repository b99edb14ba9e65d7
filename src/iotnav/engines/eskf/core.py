"""The ``eskf`` engine's state arrays and the plumbing to its compiled code (propagation, updates, records)."""

from __future__ import annotations

import math
from collections import deque
from collections.abc import Iterable
from typing import Any

import numpy as np
import numpy.typing as npt

from iotnav import kalman
from iotnav.engines.base import (
    CountSlot,
    FlagSlot,
    InputGuard,
    OneSampleBlock,
    StateSlot,
    TangentPlane,
)
from iotnav.engines.eskf import models as M
from iotnav.engines.eskf.config import G0, EskfConfig, noise_vector
from iotnav.engines.eskf.consistency import NisWindow
from iotnav.engines.eskf.kernel import (
    _apply_nb,
    _integrate_to_nb,
    _propagate_cov_nb,
    params,
)
from iotnav.engines.eskf.layout import (
    DEFAULT_RECORDED,
    E_A_MS,
    E_F_N_LP,
    E_F_PEND,
    E_FIX_ACC,
    E_FIX_REACH,
    E_FIX_SIG,
    E_FIX_SV,
    E_FIX_T,
    E_FIX_V,
    E_FIX_Z,
    E_H0,
    E_HAS_FIX,
    E_HAS_FRAME,
    E_HAVE_IMU,
    E_HEADING_OK,
    E_KE,
    E_KN,
    E_LAST_SPEED,
    E_LAT0,
    E_LEVEL_N,
    E_LEVEL_SUM,
    E_LEVEL_T0,
    E_LEVELLED,
    E_LON0,
    E_MOUNT_OK,
    E_N_IMU,
    E_NREC,
    E_POS_OK,
    E_SIZE,
    E_SIZE_V1,
    E_SM_N,
    E_SM_PEND,
    E_STATIC,
    E_STATIC_SEEN,
    E_T_A_GNSS,
    E_T_A_MS,
    E_T_FIX,
    E_T_NHC,
    E_T_PREFILT,
    E_T_SPEED,
    E_T_STATE,
    E_T_ZARU,
    E_T_ZUPT,
    E_W_PEND,
    E_ZARU_N,
    E_ZARU_SUM,
    MEAS_CODES,
    MEAS_NAMES,
    PRM_SIZE,
    Q_FIX_STD,
    R_ACC,
    R_DOF,
    R_KIND,
    R_MEAS,
    R_NIS,
    R_RATIO,
    R_T,
    REC_ROWS,
    REC_STATIC_START,
    REC_UPDATE,
    SM_ROWS,
)
from iotnav.engines.gnss_resolution import AccuracyScaling, PositionResolution
from iotnav.engines.smoother import (
    SmoothingLog,
    drain_records,
    record_size,
)
from iotnav.geo import euler_to_dcm
from iotnav.innovations import InnovationLog
from iotnav.techniques.mount3d import Mount3d
from iotnav.techniques.static import StaticDetector

FloatArray = npt.NDArray[np.float64]


def _hold_defaults(st: FloatArray, prm: FloatArray, c: EskfConfig) -> None:
    """The per-fix uncertainty slots before the first fix (:meth:`EskfGnss._hold_sigmas` sets them)."""
    st[E_FIX_SIG] = st[E_FIX_SIG + 1] = prm[Q_FIX_STD]
    st[E_FIX_SV] = c.gnss_speed_noise_mps
    st[E_FIX_ACC] = c.hold_accel_floor_mps2
    st[E_FIX_REACH] = math.inf  # no cap before a fix says what the vehicle did
    st[E_A_MS] = 0.0
    st[E_T_A_MS] = math.nan


def _nis_window(c: EskfConfig) -> NisWindow:
    """The monitor's window of a configuration (its ``nis_*`` fields)."""
    return NisWindow(
        c.nis_window_fixes,
        c.nis_false_alarm,
        c.nis_cap_probability,
        c.nis_min_fixes,
        c.reinit_min_distance_m,
        c.reinit_distance_sigmas,
    )


class EskfCore:
    """Arrays and compiled-code plumbing of :class:`~iotnav.engines.eskf.EskfEngine`."""

    have_imu = FlagSlot(E_HAVE_IMU, "st")
    t_state = StateSlot(E_T_STATE, "st")
    levelled = FlagSlot(E_LEVELLED, "st")
    level_n = CountSlot(E_LEVEL_N, "st")
    level_t0 = StateSlot(E_LEVEL_T0, "st")
    heading_ok = FlagSlot(E_HEADING_OK, "st")
    pos_ok = FlagSlot(E_POS_OK, "st")
    mount_ok = FlagSlot(E_MOUNT_OK, "st")
    static = FlagSlot(E_STATIC, "st")
    static_seen = FlagSlot(E_STATIC_SEEN, "st")
    t_speed = StateSlot(E_T_SPEED, "st")
    last_speed = StateSlot(E_LAST_SPEED, "st")
    t_prefilt = StateSlot(E_T_PREFILT, "st")
    t_nhc = StateSlot(E_T_NHC, "st")
    t_zupt = StateSlot(E_T_ZUPT, "st")
    zaru_n = CountSlot(E_ZARU_N, "st")
    t_zaru = StateSlot(E_T_ZARU, "st")
    t_fix = StateSlot(E_T_FIX, "st")
    n_imu = CountSlot(E_N_IMU, "st")

    def __init__(
        self, config: EskfConfig | None = None, *, record_innovations: bool | Iterable[str] = False
    ) -> None:
        self.config = c = config or EskfConfig()
        names: tuple[str, ...] = (
            DEFAULT_RECORDED
            if record_innovations is True
            else (() if record_innovations is False else tuple(record_innovations))
        )
        for name in names:
            if name not in ("gnss_position", "gnss_velocity", "mag_heading"):
                raise ValueError(f"record_innovations: {name!r} is not recorded (GNSS, magnetometer only)")
        self.innovations: dict[str, InnovationLog] = {name: InnovationLog() for name in names}
        self.n = M.n_states(c.estimate_scale_factors)
        self.nom = M.Nominal()
        self.P = np.eye(self.n) * 1e-6
        self.noise = noise_vector(c)
        self.lever_b = np.asarray(c.gnss_lever_arm_b_m, float)
        W = np.asarray(c.mag_soft_iron, float).reshape(3, 3)
        self.mag_Winv = np.linalg.inv(W)
        self.mag_h = np.asarray(c.mag_hard_iron_ut, float)
        #: the magnetometer is calibrated (configured, or declared calibrated): usable
        self.mag_usable = c.mag_calibrated or bool(np.any(self.mag_h != 0.0) or np.any(W != np.eye(3)))
        self.mag_unused = 0  # magnetometer samples left out, uncalibrated
        #: ``utc = t + utc_offset_s`` (set by :func:`run_batch` from the log): the WMM's date
        self.utc_offset_s = math.nan
        self.mag_declination_rad = c.mag_declination_rad
        self.mag_reference: dict[str, Any] | None = None
        self.static_det = StaticDetector(c.static)
        #: block 5 with the commitment rule (:mod:`iotnav.techniques.mount3d`)
        self.mount3d = Mount3d(c.mount, c.mount_commit_std_rad)
        self.aligner = self.mount3d.aligner
        self._mount_unobservable_reported = False
        self.events: list[dict[str, Any]] = []
        self.guard = InputGuard(self.events)
        self.nis_log: dict[str, list[tuple[float, float, int, bool]]] = {}
        self._gates = {d: kalman.gate_threshold(d, c.gate_probability) for d in (1, 2, 3)}
        self.prm = params(c, self._gates)
        self.st = np.zeros(E_SIZE)
        self.rec = np.zeros((REC_ROWS, 7))
        self._frame: TangentPlane | None = None
        self._last_fix: tuple[float, FloatArray, FloatArray] | None = None
        self.g_n = np.array([0.0, 0.0, c.gravity_mps2 if c.gravity_mps2 > 0 else G0])
        self.acc = np.zeros(M.ACC_SIZE)
        self.t_state = math.nan
        self.f_pend = self.st[E_F_PEND : E_F_PEND + 3]  # raw IMU sample being integrated
        self.w_pend = self.st[E_W_PEND : E_W_PEND + 3]
        self.have_imu = False
        # initialisation flags
        self.levelled = False
        self.level_sum = self.st[E_LEVEL_SUM : E_LEVEL_SUM + 7]  # sum f (3), sum w (3), sum |f|^2
        self.level_n = 0
        self.level_t0 = math.nan
        self.heading_ok = False
        self.pos_ok = False
        self.mount_ok = c.mount_rpy_rad is not None
        if c.mount_rpy_rad is not None:
            self.nom.C_vb[:] = euler_to_dcm(*c.mount_rpy_rad)
        self.static = False
        self.static_seen = False
        self.f_n_lp = self.st[E_F_N_LP : E_F_N_LP + 3]
        self.t_speed = -math.inf
        self.last_speed = math.nan
        self.t_prefilt = -math.inf
        # scheduling
        self.t_nhc = -math.inf
        self.t_zupt = -math.inf
        self.t_mag = -math.inf
        self.zaru_sum = self.st[E_ZARU_SUM : E_ZARU_SUM + 3]
        self.zaru_n = 0
        self.t_zaru = -math.inf
        self.t_fix = -math.inf
        self.n_rejected_fix = 0
        #: the windowed NIS monitor of the GNSS positions (:mod:`~iotnav.engines.eskf.consistency`)
        self._nis_window = _nis_window(c)
        self._t_reinit = -math.inf  # time of the latest re-initialisation, s
        self._reinit_request: str | None = None  # reason of a request_reinitialise, until a fix
        #: recent fixes' (t, v_N, v_E) for the GNSS-derived acceleration (:meth:`_gnss_accel`)
        self._v_hist: list[tuple[float, float, float]] = []
        #: recent fixes' (t, speed), decreasing speeds: the top speed of the last hold_window_s
        self._speed_top: deque[tuple[float, float]] = deque()
        self.st[E_T_A_GNSS] = -math.inf
        _hold_defaults(self.st, self.prm, c)
        self._t_valid = math.nan  # time of the latest valid fix, s
        self._t_long_gap_end = -math.inf  # first valid fix after a long gap, s
        #: the origin came from a fix without a height: the vertical is unknown until a 3D fix
        self._vertical_unknown = False
        self.sigma_e = np.array([1.0, 1.0, 1.5])  # current sigma of the smoothed GNSS error, m
        #: which receiver figures gave the latest fix's position sigma (:meth:`_gnss_noise`)
        self._scaling = AccuracyScaling()
        self._fix_source: tuple[str, str] = ("", "")  # figures behind the latest fix's sigma
        #: output rounding of the fixes (NMEA decimals), the white part of the position noise
        self.resolution = PositionResolution()
        self.n_imu = 0
        # one-sample block for step(ImuSample)
        self._one = OneSampleBlock()  # step(ImuSample): the batch kernel on one sample
        # RTS smoothing (package docstring): the records drained from the kernels' buffer, with
        # the output-attitude map of each record
        if c.smoothing and c.record_every < 1:
            raise ValueError(f"eskf.record_every must be >= 1, got {c.record_every}")
        self._sm_log: SmoothingLog | None = SmoothingLog(c.record_every) if c.smoothing else None
        self._sm_att: list[FloatArray] = []
        #: Smoothing arrays of the compiled code: ``(buf, Phi, work, rec, att)``: the open
        #: record's prior and posterior (``x`` then ``P`` row-major, 2 rows), the transition
        #: since the previous record (``n^2``, row-major), two ``(n, n)`` work matrices, the
        #: record buffer (:func:`~iotnav.engines.smoother.record_size` columns) and each
        #: buffered record's output-attitude map (9). Placeholders when not smoothing.
        n, rows = (self.n, SM_ROWS) if c.smoothing else (1, 1)
        self.sm: tuple[FloatArray, FloatArray, FloatArray, FloatArray, FloatArray] = (
            np.zeros((2, n + n * n)),
            np.eye(n).reshape(-1),
            np.zeros((2, n, n)),
            np.zeros((rows, record_size(n))),
            np.zeros((rows, 9)),
        )

    # ------------------------------------------------------------------ copies, checkpoints
    def __setstate__(self, state: dict[str, Any]) -> None:
        """Unpickling (checkpoints of :mod:`iotnav.service.checkpoint`, the fleet's workers, copies).

        The views into :attr:`st` (``f_pend``, ``w_pend``, ``level_sum``, ``f_n_lp``,
        ``zaru_sum``) are bound to it again (a pickle or a deep copy detaches them). A hot
        state of an earlier layout (:data:`~iotnav.engines.eskf.layout.E_SIZE_V1` entries,
        before the per-fix uncertainty slots) is completed: the slots get the values a fresh
        engine starts with and are set at the next fix. Any other size is refused.

        Raises
        ------
        ValueError
            For a hot state whose size is neither this layout's nor an earlier one's
            (:class:`~iotnav.service.checkpoint.CheckpointError` then discards the checkpoint).
        """
        st = state.get("st")
        if not isinstance(st, np.ndarray) or st.ndim != 1 or st.shape[0] not in (E_SIZE, E_SIZE_V1):
            size = st.shape if isinstance(st, np.ndarray) else type(st).__name__
            raise ValueError(
                f"eskf state: hot state of shape {size}; this version reads ({E_SIZE},) "
                f"(or ({E_SIZE_V1},), written before the per-fix uncertainty slots)"
            )
        prm = state.get("prm")
        if not isinstance(prm, np.ndarray) or prm.shape != (PRM_SIZE,):
            raise ValueError(f"eskf state: parameters not of shape ({PRM_SIZE},)")
        self.__dict__.update(state)
        if "_speed_top" not in state:  # written before the reach bound
            self._speed_top = deque()
        if "_nis_window" not in state:  # written before the NIS monitor
            self._nis_window = _nis_window(self.config)
            self._t_reinit = -math.inf
        self.__dict__.setdefault("_reinit_request", None)  # written before request_reinitialise
        if st.shape[0] == E_SIZE_V1:
            self.st = st = np.concatenate([st, np.zeros(E_SIZE - E_SIZE_V1)])
            _hold_defaults(st, prm, self.config)
        for name, sl in (
            ("f_pend", slice(E_F_PEND, E_F_PEND + 3)),
            ("w_pend", slice(E_W_PEND, E_W_PEND + 3)),
            ("level_sum", slice(E_LEVEL_SUM, E_LEVEL_SUM + 7)),
            ("f_n_lp", slice(E_F_N_LP, E_F_N_LP + 3)),
            ("zaru_sum", slice(E_ZARU_SUM, E_ZARU_SUM + 3)),
        ):
            setattr(self, name, st[sl])

    # ------------------------------------------------------------------ state kept in st
    @property
    def frame(self) -> TangentPlane | None:
        """NED origin (set at the first fix)."""
        return self._frame

    @frame.setter
    def frame(self, fr: TangentPlane | None) -> None:
        self._frame = fr
        st = self.st
        st[E_HAS_FRAME] = 0.0 if fr is None else 1.0
        if fr is not None:
            st[E_LAT0], st[E_LON0], st[E_H0], st[E_KN], st[E_KE] = (
                fr.lat0_deg,
                fr.lon0_deg,
                fr.h0_m,
                fr.k_n,
                fr.k_e,
            )

    @property
    def last_fix(self) -> tuple[float, FloatArray, FloatArray] | None:
        """Time (s), NED position (m) and velocity (m/s) of the latest valid fix."""
        return self._last_fix

    @last_fix.setter
    def last_fix(self, fix: tuple[float, FloatArray, FloatArray] | None) -> None:
        self._last_fix = fix
        st = self.st
        st[E_HAS_FIX] = 0.0 if fix is None else 1.0
        if fix is not None:
            st[E_FIX_T] = fix[0]
            st[E_FIX_Z : E_FIX_Z + 3] = fix[1]
            st[E_FIX_V : E_FIX_V + 3] = fix[2]

    def _drain_smoothing(self) -> None:
        """Move the records the compiled code wrote into the log (and their attitude maps)."""
        st = self.st
        count = int(st[E_SM_N])
        if count == 0 or self._sm_log is None:
            return
        _buf, _Phi, _work, rec, att = self.sm
        drain_records(self._sm_log, rec, count, self.n)
        self._sm_att.append(att[:count].copy())
        if st[E_SM_PEND] != 0.0:
            att[0] = att[count]  # the open record's map moves with it to row 0
        st[E_SM_N] = 0.0

    def _flush(self) -> None:
        """Turn the compiled code's records into ``events`` and ``nis_log`` entries, in order.

        Smoothing records are moved to the log too (:meth:`_drain_smoothing`).
        """
        if self._sm_log is not None:
            self._drain_smoothing()
        n = int(self.st[E_NREC])
        if n == 0:
            return
        for row in self.rec[:n].tolist():
            kind, t = int(row[R_KIND]), row[R_T]
            if kind == REC_UPDATE:
                name = MEAS_NAMES[int(row[R_MEAS])]
                ok = bool(row[R_ACC])
                self.nis_log.setdefault(name, []).append((t, row[R_NIS], int(row[R_DOF]), ok))
                if not ok and name != "gnss_position":
                    self.events.append(
                        {
                            "type": "update_rejected",
                            "t": t,
                            "measurement": name,
                            "nis": row[R_NIS],
                            "test_ratio": row[R_RATIO],
                        }
                    )
            else:
                self.events.append(
                    {"type": "static_start" if kind == REC_STATIC_START else "static_end", "t": t}
                )
        self.st[E_NREC] = 0.0

    # ------------------------------------------------------------------ propagation
    def _integrate_to(self, t: float) -> None:
        """Integrate the pending IMU sample from ``t_state`` to ``t`` (compiled)."""
        _integrate_to_nb(
            float(t),
            self.st,
            self.prm,
            self.nom.arrays(),
            self.g_n,
            self.acc,
            self.P,
            self.noise,
            np.empty(6),
            self.sm,
        )

    def _propagate_cov(self) -> None:
        """Propagate the covariance over the accumulated interval (compiled)."""
        _propagate_cov_nb(self.P, self.acc, self.noise, self.nom.arrays(), self.st, self.prm, self.sm)

    # ------------------------------------------------------------------ updates
    def _apply(self, t: float, meas: M.Meas | None, force: bool = False) -> bool:
        """Gate and apply one measurement (compiled update); returns True when accepted."""
        if meas is None:
            return False
        m = meas.y.size
        y = np.zeros(3)
        y[:m] = meas.y
        H = np.zeros((3, self.n))
        H[:m] = meas.H
        R = np.zeros((3, 3))
        R[:m, :m] = meas.R
        gate = -1.0 if force else self._gates[m]  # m is 1, 2 or 3
        log = self.innovations.get(meas.name) if self.innovations else None
        S = None
        if log is not None:
            # P to now (the compiled update then finds the interval empty, as without recording)
            self._propagate_cov()
            HP = meas.H @ self.P
            S = HP @ meas.H.T + meas.R
        ok = _apply_nb(
            float(t),
            MEAS_CODES[meas.name],
            y,
            H,
            R,
            m,
            gate,
            self.P,
            self.nom.arrays(),
            self.acc,
            self.noise,
            self.st,
            self.prm,
            self.rec,
            self.sm,
        )
        self._flush()
        if log is not None and S is not None:
            log.append(float(t), meas.y, S, bool(ok))
        return bool(ok)
