"""Fusion Kalman filter: 9-state linear GPS/INS integration (Forno et al. 2020, block 6).

[n, m, p] = [9, 5, 3] as in Table I (the linear filter of Zihajehzadeh et al. 2015).

State (named layout ``POS``, ``VEL``, ``BA``)::

    x = [r_n (3, m), v_n (3, m/s), b_a (3, m/s^2)]

Control input: the navigation-frame acceleration from blocks 2 and 5,
``u = C_nb f_b + g_n`` (m/s^2, ``g_n = [0, 0, g]``).

Accelerometer-bias model (chosen here; the paper does not say). The bias is a property of
the sensor, so it lives in ``b``: ``f_b = f_true_b + b_a + noise``. The true acceleration is
then ``a_n = u - C_nb b_a``; with ``C_nb`` known from block 2 at each step the model stays
linear in the state but time-varying (``F`` depends on ``C_nb``)::

    r_k = r + dt v + dt^2/2 (u - C_nb b_a)
    v_k = v + dt (u - C_nb b_a)
    b_k = b_a                                   (random walk)

    F = [[I, dt I, -dt^2/2 C_nb], [0, I, -dt C_nb], [0, 0, I]],  B = [[dt^2/2 I], [dt I], [0]]
    Q = q_a [[dt^3/3 I, dt^2/2 I], [dt^2/2 I, dt I]] (+) q_b dt I

``q_a`` (m^2/s^3) is the spectral density of the acceleration error (sensor noise plus the
attitude errors of block 2), ``q_b`` (m^2/s^5) the bias random walk. A bias in ``n`` (the
time-invariant alternative) would be wrong as soon as the vehicle turns.

Measurements (5 as in the paper): GNSS position (3) and horizontal velocity (2) from speed and
course::

    z_r = r_n(fix),  H = [I 0 0],  R = diag(s_h^2, s_h^2, s_v^2)
    z_v = speed [cos(course), sin(course)],  H = [0 [I2 0] 0],  R = sigma_v^2 I2

Position noise (:func:`gnss_noise`): the receiver's figures as every iotnav engine reads them
(:func:`iotnav.gnss_accuracy.position_sigmas`): ``s_h = h_acc / sqrt(2)`` per horizontal axis
(``h_acc_m`` is the 2D figure, see :mod:`iotnav.io.schema`) and ``s_v = v_acc``; else the DOPs
times the user-equivalent range error, ``s_h = uere HDOP / sqrt(2)``,
``s_v = uere sqrt(PDOP^2 - HDOP^2)``; else ``default_dop`` in place of HDOP. The paper gives no
``R``; it gates fixes on PDOP (its ref. [16] scales ``R`` with PDOP).

Both are floored at ``min_pos_std_m`` (an RTK receiver reports 1 cm while the antenna moves by
more than that between the IMU samples that the filter integrates, and the IMU model has its
own errors). Velocity: when the receiver reports a NED velocity (``vn, ve, vd``) all three
components are used (``H = [0 I 0]``, a departure from the paper's 2-D form, which has no
vertical velocity), else speed and course as above; the 1-sigma per component is
``s_acc_mps`` when finite, else ``speed_noise_mps``.

Position and velocity are applied as sequential updates (equivalent to one update with a
block-diagonal R). Between fixes the filter dead-reckons at the IMU rate and its covariance
grows.

Implementation: the state lives in one float64 array (``F_*`` layout). The IMU-rate prediction
is the compiled :func:`fusion_predict` (``F`` and ``Q`` above written out per 3 x 3 block; the
dense :func:`transition` and :func:`process_noise` remain as the reference forms), called by
:meth:`FusionKF.predict` and the pipeline's IMU kernel; the GNSS updates use
:func:`iotnav.kalman.update_selected` (``H`` selects states).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numba
import numpy as np
import numpy.typing as npt

from iotnav import kalman
from iotnav.gnss_accuracy import position_sigmas

FloatArray = npt.NDArray[np.float64]

POS = slice(0, 3)
VEL = slice(3, 6)
BA = slice(6, 9)
N_STATES = 9
VEL_H = slice(3, 5)
#: The filter's state array: ``x`` (9), ``P`` (9 x 9 row-major), initialised flag.
F_X, F_P, F_INIT = 0, 9, 90
STATE_SIZE = 91
_IDX_POS = np.arange(0, 3)
_IDX_VEL = np.arange(3, 6)
_IDX_VEL_H = np.arange(3, 5)
#: Parameter vector of :func:`fusion_predict`: ``q_a`` (m^2/s^3), ``q_b`` (m^2/s^5).
FP_QA, FP_QB = range(2)


@dataclass(frozen=True)
class FusionConfig:
    """Fusion-filter tunables (SI).

    Attributes
    ----------
    acc_psd_m2_s3 : float
        ``q_a``: acceleration error spectral density, m^2/s^3.
    acc_bias_rw_m2_s5 : float
        ``q_b``: accelerometer bias random walk spectral density, m^2/s^5.
    acc_bias_init_mps2 : float
        Initial bias standard deviation, m/s^2.
    uere_m : float
        User-equivalent range error multiplying the DOPs, m.
    default_dop : float
        HDOP assumed when the receiver reports neither an accuracy nor a DOP.
    speed_noise_mps : float
        Standard deviation of each GPS velocity component, m/s.
    init_vel_std_mps : float
        Initial velocity standard deviation, m/s.
    gate_probability : float
        Chi-square probability of the position NIS gate (0 disables it).
    max_rejections : int
        After this many consecutive gated fixes the next one is accepted (re-convergence).
    reacquire_after_s : float
        The first fix after a GNSS outage longer than this is accepted at once the same way, s.
    min_pos_std_m : float
        Floor of the per-axis position standard deviation, m.
    use_ned_velocity : bool
        Use the receiver's NED velocity (3 components) when it reports one.
    smoothing : bool
        Keep a :class:`~iotnav.engines.smoother.SmoothingLog` of this filter for the RTS
        smoother (``iotnav run --smooth`` turns it on; :mod:`iotnav.engines.pipeline`): about
        2 KB a record (9 states), one every ``record_every`` output rows and one per GNSS
        epoch, so about 2 GB for a day of 100 Hz data; off by default.
    record_every : int
        Output rows between smoothing records without a GNSS epoch.
    smoothing_accel_rw_mps2_sqrt_s : float
        Random-walk density of an acceleration error (in ``n``) the RTS smoother adds to the
        state (:class:`~iotnav.engines.smoother.AccelErrorModel`), m/s^2/sqrt(s); 0 (default)
        smooths with the filter's own model. Needs ``pipeline.static_hold = false`` (a held step
        is not kinematic; see :mod:`iotnav.engines.pipeline`).
    smoothing_accel_init_std_mps2 : float
        Standard deviation of that acceleration error at the first fix, m/s^2.
    """

    acc_psd_m2_s3: float = 0.5
    acc_bias_rw_m2_s5: float = 1e-6
    acc_bias_init_mps2: float = 0.05
    uere_m: float = 3.0
    default_dop: float = 2.0
    speed_noise_mps: float = 0.3
    init_vel_std_mps: float = 1.0
    gate_probability: float = 0.99999
    max_rejections: int = 5
    reacquire_after_s: float = 10.0
    min_pos_std_m: float = 0.02
    use_ned_velocity: bool = True
    smoothing: bool = False
    record_every: int = 10
    smoothing_accel_rw_mps2_sqrt_s: float = 0.0
    smoothing_accel_init_std_mps2: float = 1.0


def transition(C_nb: FloatArray, dt: float) -> tuple[FloatArray, FloatArray]:
    """``F`` (9, 9) and ``B`` (9, 3) for one step of ``dt`` seconds (dense reference form)."""
    F = np.eye(N_STATES)
    eye = np.eye(3)
    F[POS, VEL] = dt * eye
    F[POS, BA] = -0.5 * dt * dt * C_nb
    F[VEL, BA] = -dt * C_nb
    B = np.zeros((N_STATES, 3))
    B[POS] = 0.5 * dt * dt * eye
    B[VEL] = dt * eye
    return F, B


def process_noise(dt: float, q_a: float, q_b: float) -> FloatArray:
    """``Q`` (9, 9) of the white-acceleration plus bias random-walk model (dense reference form)."""
    Q = np.zeros((N_STATES, N_STATES))
    eye = np.eye(3)
    Q[POS, POS] = q_a * dt**3 / 3.0 * eye
    Q[POS, VEL] = Q[VEL, POS] = q_a * dt**2 / 2.0 * eye
    Q[VEL, VEL] = q_a * dt * eye
    Q[BA, BA] = q_b * dt * eye
    return Q


def gnss_noise(
    h_acc_m: float,
    v_acc_m: float,
    s_acc_mps: float,
    pdop: float,
    hdop: float,
    config: FusionConfig,
) -> tuple[FloatArray, float]:
    """``R`` (3, 3) of a GNSS position (NED, m^2) and the velocity sigma per component (m/s).

    Receiver accuracy first, then DOP x UERE, then ``default_dop`` (module docstring), floored
    at ``min_pos_std_m`` per axis.
    """
    c = config
    sig = position_sigmas(h_acc_m, v_acc_m, hdop, pdop, c.uere_m, c.default_dop)
    R = np.diag(np.maximum(sig.ned_m, c.min_pos_std_m) ** 2)
    sigma_v = s_acc_mps if math.isfinite(s_acc_mps) and s_acc_mps > 0.0 else c.speed_noise_mps
    return R, sigma_v


@numba.njit(cache=True)
def fusion_predict(
    s: FloatArray, p: FloatArray, an0: float, an1: float, an2: float, C: FloatArray, dt: float
) -> None:
    """Dead-reckon the state array ``s`` one IMU step (compiled, in place; module docstring).

    ``x- = F x + B u``, ``P- = sym(F P F^T + Q)`` with the block structure of ``F`` written
    out (no 9 x 9 products).

    Parameters
    ----------
    s : numpy.ndarray
        State array (``F_*`` layout); nothing happens before it is initialised.
    p : numpy.ndarray
        ``[q_a, q_b]``.
    an0, an1, an2 : float
        ``u = C_nb f_b + g_n`` in NED, m/s^2.
    C : numpy.ndarray
        ``C_nb`` row-major (9,).
    dt : float
        Step, s.
    """
    if dt <= 0.0 or s[F_INIT] == 0.0:
        return
    h = 0.5 * dt * dt
    # C b_a (NED), the bias seen in n
    cb0 = C[0] * s[6] + C[1] * s[7] + C[2] * s[8]
    cb1 = C[3] * s[6] + C[4] * s[7] + C[5] * s[8]
    cb2 = C[6] * s[6] + C[7] * s[7] + C[8] * s[8]
    s[0] += dt * s[3] - h * cb0 + h * an0
    s[1] += dt * s[4] - h * cb1 + h * an1
    s[2] += dt * s[5] - h * cb2 + h * an2
    s[3] += -dt * cb0 + dt * an0
    s[4] += -dt * cb1 + dt * an1
    s[5] += -dt * cb2 + dt * an2
    # M = F P (rows), then P- = M F^T (columns); F = [[I, dt I, -h C], [0, I, -dt C], [0, 0, I]]
    M = np.empty((9, 9))
    for j in range(9):
        b0 = s[F_P + 54 + j]
        b1 = s[F_P + 63 + j]
        b2 = s[F_P + 72 + j]
        for i in range(3):
            cbj = C[3 * i] * b0 + C[3 * i + 1] * b1 + C[3 * i + 2] * b2
            M[i, j] = s[F_P + 9 * i + j] + dt * s[F_P + 9 * (3 + i) + j] - h * cbj
            M[3 + i, j] = s[F_P + 9 * (3 + i) + j] - dt * cbj
            M[6 + i, j] = s[F_P + 9 * (6 + i) + j]
    qa, qb = p[FP_QA], p[FP_QB]
    for i in range(9):
        b0, b1, b2 = M[i, 6], M[i, 7], M[i, 8]
        for j in range(3):
            cbj = C[3 * j] * b0 + C[3 * j + 1] * b1 + C[3 * j + 2] * b2
            s[F_P + 9 * i + j] = M[i, j] + dt * M[i, 3 + j] - h * cbj
            s[F_P + 9 * i + 3 + j] = M[i, 3 + j] - dt * cbj
            s[F_P + 9 * i + 6 + j] = M[i, 6 + j]
    for i in range(3):
        s[F_P + 10 * i] += qa * dt**3 / 3.0
        s[F_P + 9 * i + 3 + i] += qa * dt**2 / 2.0
        s[F_P + 9 * (3 + i) + i] += qa * dt**2 / 2.0
        s[F_P + 10 * (3 + i)] += qa * dt
        s[F_P + 10 * (6 + i)] += qb * dt
    for i in range(9):
        for j in range(i + 1, 9):
            v = 0.5 * (s[F_P + 9 * i + j] + s[F_P + 9 * j + i])
            s[F_P + 9 * i + j] = v
            s[F_P + 9 * j + i] = v


@numba.njit(cache=True)
def fusion_transition_step(Phi: FloatArray, C: FloatArray, dt: float) -> None:
    """``Phi <- F Phi`` in place with the ``F`` of one :func:`fusion_predict` step (compiled).

    Accumulates the transition between two smoothing record points exactly as the filter
    propagates it, bias coupling included: ``F = [[I, dt I, -dt^2/2 C_nb], [0, I, -dt C_nb],
    [0, 0, I]]`` (module docstring; :func:`transition` is the dense form).

    Parameters
    ----------
    Phi : numpy.ndarray
        Transition (9 x 9 row-major, 81,), updated in place.
    C : numpy.ndarray
        ``C_nb`` row-major (9,) of the step.
    dt : float
        Step, s (the caller skips the steps :func:`fusion_predict` skips).
    """
    h = 0.5 * dt * dt
    for c in range(9):
        b0 = Phi[54 + c]
        b1 = Phi[63 + c]
        b2 = Phi[72 + c]
        for i in range(3):
            cb = C[3 * i] * b0 + C[3 * i + 1] * b1 + C[3 * i + 2] * b2
            v = Phi[9 * (3 + i) + c]
            Phi[9 * i + c] += dt * v - h * cb
            Phi[9 * (3 + i) + c] = v - dt * cb


class FusionKF:
    """Block 6; hot state in :attr:`state` (``F_*`` layout).

    ``x`` (9,) and ``P`` (9, 9) are views of :attr:`state`; assigning to them copies in place.
    """

    H_POS = np.hstack([np.eye(3), np.zeros((3, 6))])
    H_VEL = np.hstack([np.zeros((2, 3)), np.eye(2), np.zeros((2, 4))])
    H_VEL3 = np.hstack([np.zeros((3, 3)), np.eye(3), np.zeros((3, 3))])

    def __init__(self, config: FusionConfig | None = None) -> None:
        self.config = c = config or FusionConfig()
        self.params = np.array([c.acc_psd_m2_s3, c.acc_bias_rw_m2_s5])
        self.state = np.zeros(STATE_SIZE)
        self.P = np.eye(N_STATES)
        self.n_rejected = 0
        self._gate = (
            kalman.gate_threshold(3, self.config.gate_probability)
            if self.config.gate_probability > 0.0
            else None
        )

    @property
    def x(self) -> FloatArray:
        """State ``[r_n, v_n, b_a]`` (view)."""
        return self.state[F_X : F_X + N_STATES]

    @x.setter
    def x(self, value: FloatArray) -> None:
        self.state[F_X : F_X + N_STATES] = value

    @property
    def P(self) -> FloatArray:
        """Covariance (view)."""
        return self.state[F_P : F_P + N_STATES * N_STATES].reshape(N_STATES, N_STATES)

    @P.setter
    def P(self, value: FloatArray) -> None:
        self.state[F_P : F_P + N_STATES * N_STATES] = np.asarray(value, float).reshape(-1)

    @property
    def initialised(self) -> bool:
        """True after :meth:`initialise`."""
        return bool(self.state[F_INIT] != 0.0)

    @initialised.setter
    def initialised(self, value: bool) -> None:
        self.state[F_INIT] = 1.0 if value else 0.0

    def initialise(self, r_n: FloatArray, R_pos: FloatArray, v_n: FloatArray | None = None) -> None:
        """Start at a position (m) with covariance ``R_pos`` (m^2) and optional velocity (m/s)."""
        c = self.config
        x = np.zeros(N_STATES)
        x[POS] = r_n
        if v_n is not None:
            x[VEL] = v_n
        self.x = x
        P = np.zeros((N_STATES, N_STATES))
        P[POS, POS] = R_pos
        P[VEL, VEL] = np.eye(3) * c.init_vel_std_mps**2
        P[BA, BA] = np.eye(3) * c.acc_bias_init_mps2**2
        self.P = P
        self.initialised = True

    def predict(self, acc_n: FloatArray, C_nb: FloatArray, dt: float) -> None:
        """Dead-reckon one IMU step: ``acc_n`` = C_nb f_b + g_n (m/s^2), ``dt`` s (:func:`fusion_predict`)."""
        a = np.asarray(acc_n, float)
        C = np.ascontiguousarray(C_nb, dtype=float).reshape(9)
        fusion_predict(self.state, self.params, float(a[0]), float(a[1]), float(a[2]), C, float(dt))

    def _update(
        self, z: FloatArray, idx: npt.NDArray[np.int64], R: FloatArray, gate: float | None
    ) -> kalman.UpdateResult:
        """Compiled update of the selected states (:func:`iotnav.kalman.update_selected`)."""
        m = idx.size
        y = np.empty(m)
        S = np.empty((m, m))
        nis, ok = kalman.update_selected(
            self.x,
            self.P,
            idx,
            np.asarray(z, float),
            np.asarray(R, float),
            math.inf if gate is None else gate,
            y,
            S,
        )
        ratio = nis / gate if gate is not None else math.nan
        return kalman.UpdateResult(self.x.copy(), self.P.copy(), y, S, float(nis), bool(ok), ratio)

    def update_position(self, r_n: FloatArray, R: FloatArray, stale: bool = False) -> kalman.UpdateResult:
        """GNSS position update (NED, m); gated by NIS with re-convergence after repeated rejections.

        ``stale``: the first fix after a GNSS outage longer than ``reacquire_after_s`` (the
        engine knows the times): it is taken at once, like a forced one. A forced fix first widens the
        position covariance by ``R`` and by the outer product of its innovation, so it is taken
        nearly whole (adding ``R`` alone halved a dead-reckoning error per forced fix).
        """
        forced = self._gate is not None and (self.n_rejected >= self.config.max_rejections or stale)
        gate = None if forced else self._gate
        if forced:  # forced re-convergence: forget the old position
            y = r_n - self.x[POS]
            self.P[POS, POS] += R + np.outer(y, y)
        res = self._update(r_n, _IDX_POS, R, gate)
        if res.accepted:
            self.n_rejected = 0
        else:
            self.n_rejected += 1
        return res

    def update_velocity(self, v_ne: FloatArray, sigma_mps: float) -> kalman.UpdateResult:
        """Horizontal velocity update ``[v_N, v_E]`` (m/s)."""
        return self._update(v_ne, _IDX_VEL_H, np.eye(2) * sigma_mps**2, None)

    def update_velocity_ned(self, v_n: FloatArray, sigma_mps: float) -> kalman.UpdateResult:
        """Velocity update with all three NED components ``[v_N, v_E, v_D]`` (m/s)."""
        return self._update(v_n, _IDX_VEL, np.eye(3) * sigma_mps**2, None)
