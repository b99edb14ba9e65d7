"""Decoupled inner-state estimation from absolute fixes (Dabove et al. 2016).

Between two absolute fixes (image-based positioning, IRB: position and attitude valid at an
epoch ``n``) the position and attitude are propagated by strapdown integration of the IMU
accelerations and angular rates. The paper writes (its equations (1)-(4), lost in the text
extraction of the paper and restated here in iotnav's notation: ``C_nb`` maps ``b`` to ``n``,
``f_b`` is the specific force, ``g_n = [0, 0, g]``, ``k`` the IMU index, ``n`` the fix index)::

    (1) x_{k+1} = x_k + v_k dt + 1/2 (C_nb,k (f_b,k - b_a) + g_n) dt^2
        v_{k+1} = v_k + (C_nb,k (f_b,k - b_a) + g_n) dt
    (2) phi_{k+1} = phi_k + (omega_k - d_g) dt

with ``b_a`` the accelerometer bias (m/s^2, in ``b``) and ``d_g`` the gyro drift (rad/s, in
``b``), both held constant between fixes. Summing (1) from fix epoch ``t_n`` to ``t``::

    x(t) = X_n + v_n (t - t_n) + D_n(t) - M_n(t) b_a
    v(t) = v_n + V_n(t) - W_n(t) b_a

where the *interval integrals*, computed from the IMU alone, are (matrices in capitals)::

    V_n(t) = int_{t_n}^{t} (C_nb f_b + g_n) ds                 (m/s)
    D_n(t) = int_{t_n}^{t} V_n(s) ds                            (m)
    W_n(t) = int_{t_n}^{t} C_nb ds                               (s)
    M_n(t) = int_{t_n}^{t} W_n(s) ds                             (s^2)

Accelerometer bias and velocity (paper eq. (3)): with three consecutive fixes ``X_n``,
``X_{n+1}``, ``X_{n+2}`` (``T_1 = t_{n+1} - t_n``, ``T_2 = t_{n+2} - t_n``) and the bias constant
over the two intervals, the six unknowns ``v_n`` (3) and ``b_a`` (3) solve the linear system of
six equations::

    [ T_1 I   -M_n(t_{n+1}) ] [ v_n ]   [ X_{n+1} - X_n - D_n(t_{n+1}) ]
    [ T_2 I   -M_n(t_{n+2}) ] [ b_a ] = [ X_{n+2} - X_n - D_n(t_{n+2}) ]

For a constant attitude ``C`` this is, per axis, ``v T_i - (C b)_axis T_i^2 / 2 = r_i``, whose
determinant ``T_1 T_2 (T_2 - T_1) / 2`` never vanishes: the system is always solvable.
:func:`solve_velocity_bias` also accepts ``K > 3`` fixes (least squares on ``3 (K - 1)``
equations, an iotnav extension that averages the noise of imprecise fixes); ``K = 3`` is the
paper's square system. The velocity at the newest fix follows as
``v(t_{n+K-1}) = v_n + V - W b_a`` over the whole window.

Gyro drift (paper eq. (4)): the attitudes ``C_n``, ``C_{n+1}`` of two consecutive fixes give
three equations in the three drifts. Integrating (2) as rotations, ``C_{n+1} = C_n Gamma`` with
``Gamma = prod_k exp([(omega_k - d) dt x])``. Linearised about the drifts ``d_k`` used by the
integration (a perturbation ``delta`` at step ``k`` moves to the end of the interval rotated by
the later increments)::

    phi = log(Gamma_used^T C_n^T C_{n+1}) = -(G d - Gd)
    G  = sum_k Gamma_{k+1 -> end}^T dt,    Gd = sum_k Gamma_{k+1 -> end}^T d_k dt
    =>  d = G^{-1} (Gd - phi)                                   (three equations)

With small rotations over the interval ``G = T I`` and this is the paper's Euler-angle form
``d = (sum_k omega_k dt - (phi_{n+1} - phi_n)) / T``. No noise model is needed: the paper
stresses that, unlike a Kalman filter, the method needs neither the noise of accelerometers and
gyros nor the dynamics of the motion.

Intervals compose (:func:`compose`), so windows of several fixes reuse per-interval records;
the discrete sums follow the strapdown discretisation of :mod:`iotnav.strapdown` exactly
(specific force rotated with the mid-step attitude, trapezoidal position), so that for
error-free data the solved bias and velocity are exact to rounding.

Reference: P. Dabove, G. Ghinamo, A. M. Lingua, "Inertial sensors for smartphones navigation",
SpringerPlus 4:834, 2015 (cited in this project as Dabove et al. 2016), section "The
methodology for relative position and attitude estimation based on INS measurements".
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import NamedTuple

import numpy as np
import numpy.typing as npt
from scipy.spatial.transform import Rotation

FloatArray = npt.NDArray[np.float64]

__all__ = [
    "ACC_D",
    "ACC_G",
    "ACC_GAMMA",
    "ACC_GD",
    "ACC_M",
    "ACC_T",
    "ACC_V",
    "ACC_W",
    "N_ACC",
    "IntervalIntegrals",
    "accumulate",
    "compose",
    "compose_all",
    "empty_interval",
    "interval_from_flat",
    "reset_flat",
    "solve_gyro_drift",
    "solve_velocity_bias",
    "velocity_known_bias",
]

_I3 = np.eye(3)

#: Layout of the flat accumulator array used in the per-sample hot loop (:func:`accumulate`).
ACC_T = 0
ACC_V = slice(1, 4)
ACC_D = slice(4, 7)
ACC_W = slice(7, 16)
ACC_M = slice(16, 25)
ACC_GAMMA = slice(25, 34)
ACC_G = slice(34, 43)
ACC_GD = slice(43, 46)
N_ACC = 46


class IntervalIntegrals(NamedTuple):
    """IMU integrals over one interval ``[t_a, t_b]`` (see the module docstring).

    Attributes
    ----------
    dt_s : float
        ``t_b - t_a``, s.
    V : numpy.ndarray
        ``int (C_nb f_b + g_n) ds``, m/s, ``(3,)`` in ``n``.
    D : numpy.ndarray
        ``int V ds``, m, ``(3,)`` in ``n``.
    W : numpy.ndarray
        ``int C_nb ds``, s, ``(3, 3)``.
    M : numpy.ndarray
        ``int W ds``, s^2, ``(3, 3)``.
    Gamma : numpy.ndarray
        Gyro-integrated rotation ``C_{b_a b_b}`` (body at ``t_b`` to body at ``t_a``), ``(3, 3)``.
    G : numpy.ndarray
        Drift sensitivity ``sum Gamma_{k+1->b}^T dt``, s, ``(3, 3)``.
    Gd : numpy.ndarray
        ``sum Gamma_{k+1->b}^T d_k dt`` for the drifts ``d_k`` used, rad, ``(3,)``.
    """

    dt_s: float
    V: FloatArray
    D: FloatArray
    W: FloatArray
    M: FloatArray
    Gamma: FloatArray
    G: FloatArray
    Gd: FloatArray


def empty_interval() -> IntervalIntegrals:
    """The integrals of a zero-length interval."""
    z3 = np.zeros(3)
    z33 = np.zeros((3, 3))
    return IntervalIntegrals(0.0, z3.copy(), z3.copy(), z33.copy(), z33.copy(), _I3.copy(), z33.copy(), z3)


def compose(a: IntervalIntegrals, b: IntervalIntegrals) -> IntervalIntegrals:
    """Integrals over ``[t0, t2]`` from those over ``[t0, t1]`` (``a``) and ``[t1, t2]`` (``b``).

    ``V = V_a + V_b``, ``D = D_a + V_a T_b + D_b``, ``W = W_a + W_b``, ``M = M_a + W_a T_b + M_b``,
    ``Gamma = Gamma_a Gamma_b``, ``G = Gamma_b^T G_a + G_b``, ``Gd = Gamma_b^T Gd_a + Gd_b``.

    Parameters
    ----------
    a, b : IntervalIntegrals
        Consecutive intervals.

    Returns
    -------
    IntervalIntegrals
        The integrals over the union.
    """
    tb = b.dt_s
    gt = b.Gamma.T
    return IntervalIntegrals(
        a.dt_s + tb,
        a.V + b.V,
        a.D + a.V * tb + b.D,
        a.W + b.W,
        a.M + a.W * tb + b.M,
        a.Gamma @ b.Gamma,
        gt @ a.G + b.G,
        gt @ a.Gd + b.Gd,
    )


def compose_all(intervals: Sequence[IntervalIntegrals]) -> IntervalIntegrals:
    """Compose consecutive intervals left to right (:func:`compose`)."""
    out = intervals[0]
    for b in intervals[1:]:
        out = compose(out, b)
    return out


def solve_velocity_bias(
    positions_n: npt.ArrayLike, intervals: Sequence[IntervalIntegrals]
) -> tuple[FloatArray, FloatArray, FloatArray]:
    """Velocity at the first fix and accelerometer bias from ``K >= 3`` consecutive fixes.

    Solves (least squares for ``K > 3``; exact for the paper's ``K = 3``)::

        X_j - X_0 - D_{0->j} = v_0 T_{0j} - M_{0->j} b_a,   j = 1 .. K-1

    Parameters
    ----------
    positions_n : array_like
        Fix positions ``X_0 .. X_{K-1}`` in ``n``, m, ``(K, 3)``.
    intervals : sequence of IntervalIntegrals
        ``K - 1`` consecutive intervals, ``intervals[j]`` from fix ``j`` to fix ``j + 1``.

    Returns
    -------
    v0_n : numpy.ndarray
        Velocity at fix 0 in ``n``, m/s.
    b_a : numpy.ndarray
        Accelerometer bias in ``b``, m/s^2.
    v_last_n : numpy.ndarray
        Velocity at the last fix, ``v0 + V - W b_a`` over the whole window, m/s.

    Raises
    ------
    ValueError
        With fewer than three fixes or a mismatched number of intervals.
    """
    X = np.asarray(positions_n, dtype=float)
    k = X.shape[0]
    if k < 3 or len(intervals) != k - 1:
        raise ValueError(f"need K >= 3 fixes and K - 1 intervals, got {k} fixes, {len(intervals)} intervals")
    A = np.zeros((3 * (k - 1), 6))
    r = np.zeros(3 * (k - 1))
    acc = intervals[0]
    for j in range(1, k):
        if j > 1:
            acc = compose(acc, intervals[j - 1])
        rows = slice(3 * (j - 1), 3 * j)
        A[rows, 0:3] = acc.dt_s * _I3
        A[rows, 3:6] = -acc.M
        r[rows] = X[j] - X[0] - acc.D
    if k == 3:
        sol = np.linalg.solve(A, r)
    else:
        sol = np.linalg.lstsq(A, r, rcond=None)[0]
    v0, b = sol[0:3], sol[3:6]
    return v0, b, v0 + acc.V - acc.W @ b


def velocity_known_bias(
    p0_n: npt.ArrayLike, p1_n: npt.ArrayLike, interval: IntervalIntegrals, b_a: npt.ArrayLike
) -> tuple[FloatArray, FloatArray]:
    """Velocity from two consecutive fixes when the accelerometer bias is known (or taken as 0).

    ``v_0 = (X_1 - X_0 - D + M b_a) / T`` (three equations), ``v_1 = v_0 + V - W b_a``.

    Parameters
    ----------
    p0_n, p1_n : array_like
        Fix positions in ``n``, m.
    interval : IntervalIntegrals
        Integrals from fix 0 to fix 1 (``dt_s > 0``).
    b_a : array_like
        Accelerometer bias in ``b``, m/s^2.

    Returns
    -------
    tuple of numpy.ndarray
        ``(v0_n, v1_n)``, m/s.
    """
    b = np.asarray(b_a, dtype=float)
    if interval.dt_s <= 0.0:
        raise ValueError("the interval between the two fixes must be positive")
    v0 = (np.asarray(p1_n, float) - np.asarray(p0_n, float) - interval.D + interval.M @ b) / interval.dt_s
    return v0, v0 + interval.V - interval.W @ b


def solve_gyro_drift(C0_nb: npt.ArrayLike, C1_nb: npt.ArrayLike, interval: IntervalIntegrals) -> FloatArray:
    """Gyro drift from the attitudes of two fixes (three equations, module docstring).

    Parameters
    ----------
    C0_nb, C1_nb : array_like
        Attitudes of the first and last fix, ``(3, 3)``, ``b`` to ``n``.
    interval : IntervalIntegrals
        Integrals between the two fixes (possibly composed over several intervals).

    Returns
    -------
    numpy.ndarray
        Drift ``d`` in ``b``, rad/s (subtract from the gyro output).
    """
    C0 = np.asarray(C0_nb, dtype=float)
    C1 = np.asarray(C1_nb, dtype=float)
    phi = Rotation.from_matrix(interval.Gamma.T @ C0.T @ C1).as_rotvec()
    return np.asarray(np.linalg.solve(interval.G, interval.Gd - phi), dtype=float)


def reset_flat(acc: FloatArray) -> None:
    """Set a flat accumulator (layout ``ACC_*``) to the zero-length interval, in place."""
    acc[:] = 0.0
    acc[ACC_GAMMA] = _I3.ravel()


def accumulate(
    acc: FloatArray,
    C_half_nb: FloatArray,
    R_step: FloatArray,
    f_b: FloatArray,
    d_used: FloatArray,
    dt: float,
    g_n: FloatArray,
) -> None:
    """Add one strapdown step to a flat accumulator (layout ``ACC_*``), in place.

    Discretisation of :mod:`iotnav.strapdown`: ``V += (C_half f_b + g_n) dt``, ``D += (V_old +
    V_new) dt / 2``, ``W += C_half dt``, ``M += (W_old + W_new) dt / 2``, ``Gamma = Gamma R_step``,
    ``G = R_step^T G + I dt``, ``Gd = R_step^T Gd + d_used dt``.

    Parameters
    ----------
    acc : numpy.ndarray
        Flat accumulator, ``(N_ACC,)``.
    C_half_nb : numpy.ndarray
        Mid-step attitude (``b`` to ``n``), ``(3, 3)``.
    R_step : numpy.ndarray
        Attitude increment of the step, ``exp([(omega - d_used) dt x])``, ``(3, 3)``.
    f_b : numpy.ndarray
        Raw (not bias-corrected) specific force, m/s^2, ``(3,)``.
    d_used : numpy.ndarray
        Gyro drift subtracted by the integration, rad/s, ``(3,)``.
    dt : float
        Step, s.
    g_n : numpy.ndarray
        Gravity in ``n``, m/s^2.
    """
    v_old = acc[ACC_V].copy()
    acc[ACC_V] += (C_half_nb @ f_b + g_n) * dt
    acc[ACC_D] += (v_old + acc[ACC_V]) * (0.5 * dt)
    w_old = acc[ACC_W].copy()
    acc[ACC_W] += C_half_nb.ravel() * dt
    acc[ACC_M] += (w_old + acc[ACC_W]) * (0.5 * dt)
    acc[ACC_GAMMA] = (acc[ACC_GAMMA].reshape(3, 3) @ R_step).ravel()
    rt = R_step.T
    G = rt @ acc[ACC_G].reshape(3, 3)
    G[0, 0] += dt
    G[1, 1] += dt
    G[2, 2] += dt
    acc[ACC_G] = G.ravel()
    acc[ACC_GD] = rt @ acc[ACC_GD] + d_used * dt
    acc[ACC_T] += dt


def interval_from_flat(acc: FloatArray) -> IntervalIntegrals:
    """An :class:`IntervalIntegrals` (copies) from a flat accumulator (layout ``ACC_*``)."""
    return IntervalIntegrals(
        float(acc[ACC_T]),
        acc[ACC_V].copy(),
        acc[ACC_D].copy(),
        acc[ACC_W].reshape(3, 3).copy(),
        acc[ACC_M].reshape(3, 3).copy(),
        acc[ACC_GAMMA].reshape(3, 3).copy(),
        acc[ACC_G].reshape(3, 3).copy(),
        acc[ACC_GD].copy(),
    )
