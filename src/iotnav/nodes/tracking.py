"""Tracking filter for a slowly moving node that hears (moving) anchors over time.

Mobile-anchor localization (Zorkany et al. 2022, section 1 and Fig. 3; Han et al. 2016): a
single anchor driving past gives, over time, ranges from many positions, so even one anchor
determines a node. An extended Kalman filter processes the reports one at a time.

State layout (local NED frame ``n``, metres and m/s): ``x = [p_N, p_E, v_N, v_E]`` with
``POS = slice(0, 2)``, ``VEL = slice(2, 4)``. Nearly-constant-velocity motion with white
acceleration of power spectral density ``q`` (m^2/s^3) per axis:

.. math::

    F = \\begin{bmatrix} I & \\Delta t\\, I \\\\ 0 & I \\end{bmatrix}, \\qquad
    Q = q \\begin{bmatrix} \\Delta t^3/3\\, I & \\Delta t^2/2\\, I \\\\
                          \\Delta t^2/2\\, I & \\Delta t\\, I \\end{bmatrix}         \\quad (T1)

Each report is a scalar measurement with the model of
:mod:`iotnav.nodes.multilateration` (M1-M3): ``z = RSSI``, ``h(x) = P0 - 10 n log10(d/d0)``,
``H = [g^T, 0, 0]`` and ``R = sigma^2 + g^T Sigma_a g``, applied by
:func:`iotnav.kalman.update` (Cholesky, Joseph form) behind a chi-square NIS gate. The
update is iterated (IEKF, Bell and Cathey 1993): ``x_{i+1} = x^- + K_i (z - h(x_i) - H_i (x^- -
x_i))`` relinearised at each iterate, which matters because the log-distance model is strongly
curved at the ranges where a passing anchor is most informative.

Initialisation: the first reports are buffered until a batch WLS fit of them
(:func:`iotnav.nodes.multilateration.solve_position`) is ``ok`` (determined, not ambiguous);
the filter then starts from that fix with its covariance (inflated by the motion the window
allows) and zero velocity with standard deviation ``init_speed_std_mps``. A linearised filter
started far from the truth on a log-distance model can lock onto a wrong basin; the batch fix
avoids that.

Streaming and batch share :meth:`NodeTracker.step`; :func:`track_node` loops over it.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import numpy.typing as npt

from iotnav import kalman
from iotnav.nodes.multilateration import (
    SolverConfig,
    Status,
    effective_variance,
    predict_rssi,
    solve_position,
)
from iotnav.nodes.ranging import PathLossModel

FloatArray = npt.NDArray[np.float64]

POS = slice(0, 2)
VEL = slice(2, 4)
N_STATE = 4


@dataclass(frozen=True)
class TrackerConfig:
    """Tunables of :class:`NodeTracker`.

    Attributes
    ----------
    accel_psd : float
        White-acceleration power spectral density ``q`` per axis, m^2/s^3 (0.01 suits a node
        carried at walking pace with rare changes of direction).
    init_min_reports : int
        Reports buffered before a start-up fix is attempted.
    init_speed_std_mps : float
        Initial velocity standard deviation, m/s.
    gate_probability : float
        NIS gate probability (chi-square, 1 degree of freedom).
    iterations : int
        Relinearisations of each update (iterated EKF; 1 is the plain EKF).
    solver : SolverConfig
        Settings of the start-up batch fix.
    """

    accel_psd: float = 0.01
    init_min_reports: int = 12
    init_speed_std_mps: float = 0.5
    gate_probability: float = 0.9973
    iterations: int = 3
    solver: SolverConfig = field(default_factory=SolverConfig)


def transition(dt: float, accel_psd: float) -> tuple[FloatArray, FloatArray]:
    """``F`` and ``Q`` of equation T1 for a step of ``dt`` seconds."""
    I2 = np.eye(2)
    F = np.eye(N_STATE)
    F[POS, VEL] = dt * I2
    Q = np.zeros((N_STATE, N_STATE))
    Q[POS, POS] = accel_psd * dt**3 / 3.0 * I2
    Q[POS, VEL] = accel_psd * dt**2 / 2.0 * I2
    Q[VEL, POS] = Q[POS, VEL]
    Q[VEL, VEL] = accel_psd * dt * I2
    return F, Q


@dataclass(frozen=True)
class StepOutput:
    """What :meth:`NodeTracker.step` reports.

    Attributes
    ----------
    t : float
        Time of the report, s.
    x : numpy.ndarray
        State after the step (NaN while initialising).
    P : numpy.ndarray
        Covariance after the step.
    initialised : bool
        False while reports are still buffered.
    accepted : bool
        Whether this report updated the state.
    nis : float
        NIS of the report (NaN while initialising).
    """

    t: float
    x: FloatArray
    P: FloatArray
    initialised: bool
    accepted: bool
    nis: float


class NodeTracker:
    """EKF over one node's RSSI reports (equations T1 and M1-M3).

    Parameters
    ----------
    model : PathLossModel
        Radio.
    node_down_m : float
        Node down coordinate in the local frame, m.
    config : TrackerConfig, optional
        Tunables.
    """

    def __init__(self, model: PathLossModel, node_down_m: float = 0.0, config: TrackerConfig | None = None):
        self.model = model
        self.node_down_m = float(node_down_m)
        self.cfg = config if config is not None else TrackerConfig()
        self.gate = kalman.gate_threshold(1, self.cfg.gate_probability)
        self.x = np.full(N_STATE, np.nan)
        self.P = np.full((N_STATE, N_STATE), np.nan)
        self.t = np.nan
        self.initialised = False
        self._buf_t: list[float] = []
        self._buf_a: list[FloatArray] = []
        self._buf_c: list[FloatArray] = []
        self._buf_r: list[float] = []

    def _try_init(self) -> None:
        A = np.asarray(self._buf_a)
        C = np.asarray(self._buf_c)
        est = solve_position(
            A, np.asarray(self._buf_r), self.model, C, self.node_down_m, config=self.cfg.solver
        )
        if est.status is not Status.OK:
            return
        span = self._buf_t[-1] - self._buf_t[0]
        self.x = np.zeros(N_STATE)
        self.x[POS] = est.p_ne
        self.P = np.zeros((N_STATE, N_STATE))
        # the node may have moved during the window: add the position spread that speed allows
        self.P[POS, POS] = est.P + (0.5 * span * self.cfg.init_speed_std_mps) ** 2 * np.eye(2)
        self.P[VEL, VEL] = self.cfg.init_speed_std_mps**2 * np.eye(2)
        self.t = self._buf_t[-1]
        self.initialised = True
        self._buf_t.clear()
        self._buf_a.clear()
        self._buf_c.clear()
        self._buf_r.clear()

    def step(self, t: float, anchor_n: FloatArray, anchor_cov_ne: FloatArray, rssi_dbm: float) -> StepOutput:
        """Process one report.

        Parameters
        ----------
        t : float
            Report time, s (non-decreasing).
        anchor_n : numpy.ndarray
            Anchor NED position at ``t``, m.
        anchor_cov_ne : numpy.ndarray
            ``(2, 2)`` horizontal anchor covariance, m^2.
        rssi_dbm : float
            RSSI, dBm.

        Returns
        -------
        StepOutput
            State after the report.
        """
        if not self.initialised:
            self._buf_t.append(float(t))
            self._buf_a.append(np.asarray(anchor_n, dtype=float))
            self._buf_c.append(np.asarray(anchor_cov_ne, dtype=float))
            self._buf_r.append(float(rssi_dbm))
            if len(self._buf_r) >= self.cfg.init_min_reports:
                self._try_init()
            return StepOutput(float(t), self.x.copy(), self.P.copy(), self.initialised, False, np.nan)
        dt = float(t) - self.t
        if dt < 0:
            raise ValueError(f"time went backwards ({t} s after {self.t} s)")
        if dt > 0:
            F, Q = transition(dt, self.cfg.accel_psd)
            self.x, self.P = kalman.predict(self.x, self.P, F, Q)
            self.t = float(t)
        A = np.asarray(anchor_n, dtype=float).reshape(1, 3)
        C = np.asarray(anchor_cov_ne, dtype=float).reshape(1, 2, 2)
        z = np.array([float(rssi_dbm)])
        x_prior, P_prior = self.x, self.P
        xi = x_prior
        res: kalman.UpdateResult | None = None
        nis0 = np.nan
        for i in range(max(self.cfg.iterations, 1)):
            h, G, _ = predict_rssi(xi[POS], A, self.model, self.node_down_m)
            R = effective_variance(G, C, self.model.shadowing_db).reshape(1, 1)
            H = np.zeros((1, N_STATE))
            H[0, POS] = G[0]
            # iterated EKF: relinearise at x_i, h(x-) ~ h(x_i) + H (x- - x_i)
            h_lin = h + H @ (x_prior - xi)
            res = kalman.update(x_prior, P_prior, z, H, R, h_x=h_lin, gate=self.gate if i == 0 else None)
            if i == 0:
                nis0 = res.nis
                if not res.accepted:
                    break
            xi = res.x
        assert res is not None
        self.x, self.P = res.x, res.P
        return StepOutput(
            float(t), self.x.copy(), self.P.copy(), True, bool(np.isfinite(nis0) and res.accepted), nis0
        )


@dataclass(frozen=True)
class TrackResult:
    """Output of :func:`track_node`.

    Attributes
    ----------
    t : numpy.ndarray
        ``(N,)`` report times, s.
    x : numpy.ndarray
        ``(N, 4)`` states after each report (NaN before initialisation).
    P : numpy.ndarray
        ``(N, 4, 4)`` covariances.
    accepted : numpy.ndarray
        ``(N,)`` whether each report updated the state.
    nis : numpy.ndarray
        ``(N,)`` NIS per report.
    """

    t: FloatArray
    x: FloatArray
    P: FloatArray
    accepted: npt.NDArray[np.bool_]
    nis: FloatArray


def track_node(
    t: npt.ArrayLike,
    anchor_n: npt.ArrayLike,
    anchor_cov_ne: npt.ArrayLike,
    rssi_dbm: npt.ArrayLike,
    model: PathLossModel,
    node_down_m: float = 0.0,
    config: TrackerConfig | None = None,
) -> TrackResult:
    """Run :class:`NodeTracker` over a node's reports (batch form of the same ``step``).

    Parameters
    ----------
    t : array_like
        ``(N,)`` report times, s, non-decreasing.
    anchor_n : array_like
        ``(N, 3)`` anchor NED positions, m.
    anchor_cov_ne : array_like
        ``(N, 2, 2)`` horizontal anchor covariances, m^2.
    rssi_dbm : array_like
        ``(N,)`` RSSI, dBm.
    model : PathLossModel
        Radio.
    node_down_m : float
        Node down coordinate, m.
    config : TrackerConfig, optional
        Tunables.

    Returns
    -------
    TrackResult
        States and covariances after every report.
    """
    tt = np.asarray(t, dtype=float)
    A = np.asarray(anchor_n, dtype=float).reshape(-1, 3)
    C = np.asarray(anchor_cov_ne, dtype=float).reshape(-1, 2, 2)
    r = np.asarray(rssi_dbm, dtype=float)
    trk = NodeTracker(model, node_down_m, config)
    N = tt.size
    xs = np.full((N, N_STATE), np.nan)
    Ps = np.full((N, N_STATE, N_STATE), np.nan)
    acc = np.zeros(N, dtype=bool)
    nis = np.full(N, np.nan)
    for k in range(N):
        out = trk.step(tt[k], A[k], C[k], r[k])
        xs[k], Ps[k], acc[k], nis[k] = out.x, out.P, out.accepted, out.nis
    return TrackResult(tt, xs, Ps, acc, nis)
