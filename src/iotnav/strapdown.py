"""Strapdown inertial mechanisation in a local-level, flat-earth NED frame.

The navigation frame ``n`` is the North-East-Down tangent frame at a fixed geodetic origin
(:class:`iotnav.geo.LocalFrame`), treated as inertial. The state is the attitude ``C_nb``
(maps ``b`` to ``n``), the velocity ``v_n`` (m/s) and the position ``p_n`` (m) of the IMU;
the inputs are the specific force ``f_b`` (m/s^2) and the angular rate ``omega_ib_b`` (rad/s)
measured in ``b``, and the constant gravity ``g_n = [0, 0, normal_gravity(lat0, h0)]``.

Approximations (flat earth)
---------------------------
No Earth rate, no transport rate, no Coriolis term, constant gravity vector. Their size for
the land vehicles and pedestrians iotnav targets (latitude 45 deg):

* Earth rate, 7.29e-5 rad/s (15 deg/h): below the in-run bias instability of consumer MEMS
  gyros (MPU-6050, LSM6DS3) and comparable to that of a Microstrain 3DM-GX3-35 (18 deg/h).
* Coriolis acceleration ``2 Omega_ie x v``: at most 4.4e-3 m/s^2 (0.45 mg) at 30 m/s; alone
  it would displace a dead-reckoned position by 0.5 * 4.4e-3 * t^2 = 7.9 m after a 60 s
  outage at motorway speed, but that is below the effect of the 1-40 mg residual
  accelerometer biases of these sensors.
* Transport rate ``v / R``: 4.7e-6 rad/s at 30 m/s, negligible.
* Gravity direction: the local vertical tilts by ``d / R`` relative to the origin's, i.e. a
  horizontal gravity component of ``g d / R`` = 1.5e-3 m/s^2 at d = 1 km from the origin.
  The simulator :mod:`iotnav.sim` uses the same flat-earth model, so simulated data and this
  mechanisation agree exactly; against real data the approximation holds within a few km of
  the origin.

Discretisation
--------------
One step from ``t_k`` to ``t_{k+1} = t_k + dt`` uses the IMU sample stamped ``t_k``, read as
the mean angular rate and mean specific force over ``[t_k, t_{k+1})`` (the convention of the
simulator, which writes "integrate-and-dump" samples stamped at the start of their interval):

* attitude, exact for a constant rate over the step (rotation-vector exponential, Rodrigues)::

      C_nb(k+1) = C_nb(k) @ exp([omega dt x])

* velocity, specific force rotated with the mid-interval attitude (second order; sculling
  neglected)::

      v_n(k+1) = v_n(k) + (C_nb(k) @ exp([omega dt/2 x]) @ f_b + g_n) dt

* position, trapezoidal::

      p_n(k+1) = p_n(k) + (v_n(k) + v_n(k+1)) dt / 2

The simulator derives ``omega_b`` from consecutive true attitudes and ``f_b`` from
consecutive true velocities with exactly these relations, so integrating error-free simulated
samples reproduces the simulated truth to rounding error (``tests/test_strapdown.py``).

All functions take and return plain ``numpy`` arrays (no Python objects in the step), so the
step can be compiled with numba without a rewrite; :func:`rodrigues` (the rotation-vector
exponential) is compiled already and shared with the engines' compiled IMU kernels.
"""

from __future__ import annotations

import math

import numba
import numpy as np
import numpy.typing as npt

FloatArray = npt.NDArray[np.float64]

__all__ = ["gravity_n", "integrate", "rodrigues", "rotvec_to_dcm", "step"]


@numba.njit(cache=True)
def rodrigues(
    x: float, y: float, z: float
) -> tuple[float, float, float, float, float, float, float, float, float]:
    """Elements of ``exp([theta x])`` row by row for ``theta = (x, y, z)`` (rad); compiled.

    Rodrigues' formula ``I + s K + c K^2`` with ``K = [theta x]``, ``s = sin(a)/a``,
    ``c = (1 - cos(a))/a^2``, ``a = |theta|`` (4th-order Taylor series below ``a = 1e-6``).
    Scalar and allocation-free, for the engines' compiled IMU kernels; :func:`rotvec_to_dcm`
    returns it as a matrix.

    Parameters
    ----------
    x, y, z : float
        Rotation vector components, rad.

    Returns
    -------
    tuple of float
        ``(R00, R01, R02, R10, ..., R22)``, the rotation matrix row by row.
    """
    a2 = x * x + y * y + z * z
    if a2 < 1e-12:
        # Taylor series to 4th order: sin(a)/a and (1-cos(a))/a^2
        s = 1.0 - a2 / 6.0 + a2 * a2 / 120.0
        c = 0.5 - a2 / 24.0 + a2 * a2 / 720.0
    else:
        a = math.sqrt(a2)
        s = math.sin(a) / a
        c = (1.0 - math.cos(a)) / a2
    # I + s K + c K^2 written out (K = [theta x], K^2 = theta theta^T - |theta|^2 I)
    return (
        1.0 - c * (y * y + z * z),
        c * x * y - s * z,
        c * x * z + s * y,
        c * x * y + s * z,
        1.0 - c * (x * x + z * z),
        c * y * z - s * x,
        c * x * z - s * y,
        c * y * z + s * x,
        1.0 - c * (x * x + y * y),
    )


def rotvec_to_dcm(theta: FloatArray) -> FloatArray:
    """Rotation matrix ``exp([theta x])`` of a rotation vector (Rodrigues' formula, :func:`rodrigues`).

    Parameters
    ----------
    theta : numpy.ndarray
        Rotation vector, rad, shape ``(3,)``.

    Returns
    -------
    numpy.ndarray
        ``(3, 3)`` rotation matrix.
    """
    return np.array(rodrigues(float(theta[0]), float(theta[1]), float(theta[2]))).reshape(3, 3)


def gravity_n(lat0_deg: float, h0_m: float = 0.0) -> FloatArray:
    """Flat-earth gravity vector ``g_n = [0, 0, g]`` (m/s^2, NED) at the frame origin."""
    from iotnav.geo import normal_gravity

    return np.array([0.0, 0.0, normal_gravity(lat0_deg, h0_m)])


def step(
    C_nb: FloatArray,
    v_n: FloatArray,
    p_n: FloatArray,
    f_b: FloatArray,
    omega_ib_b: FloatArray,
    dt: float,
    g_n: FloatArray,
) -> tuple[FloatArray, FloatArray, FloatArray]:
    """Propagate attitude, velocity and position over one IMU interval.

    Parameters
    ----------
    C_nb : numpy.ndarray
        Attitude at ``t_k``, ``(3, 3)``, maps ``b`` to ``n``.
    v_n : numpy.ndarray
        Velocity at ``t_k`` in ``n``, m/s, ``(3,)``.
    p_n : numpy.ndarray
        Position at ``t_k`` in ``n`` (NED about the origin), m, ``(3,)``.
    f_b : numpy.ndarray
        Mean specific force over the interval in ``b``, m/s^2, ``(3,)``.
    omega_ib_b : numpy.ndarray
        Mean angular rate of ``b`` over the interval, in ``b``, rad/s, ``(3,)``.
    dt : float
        Interval, s.
    g_n : numpy.ndarray
        Gravity in ``n``, m/s^2 (``[0, 0, +g]``: gravity points down).

    Returns
    -------
    tuple of numpy.ndarray
        ``(C_nb, v_n, p_n)`` at ``t_k + dt``.
    """
    R_half = rotvec_to_dcm((0.5 * dt) * omega_ib_b)
    C_half = C_nb @ R_half
    C_new = C_half @ R_half  # exp([theta x]) = exp([theta/2 x])^2
    v_new = v_n + (C_half @ f_b + g_n) * dt
    p_new = p_n + 0.5 * (v_n + v_new) * dt
    return C_new, v_new, p_new


def integrate(
    C0: FloatArray,
    v0: FloatArray,
    p0: FloatArray,
    t: FloatArray,
    f_b: FloatArray,
    omega_b: FloatArray,
    g_n: FloatArray,
) -> tuple[FloatArray, FloatArray, FloatArray]:
    """Integrate a sequence of IMU samples with :func:`step`.

    Parameters
    ----------
    C0, v0, p0 : numpy.ndarray
        Initial attitude ``C_nb`` ``(3, 3)``, velocity ``v_n`` (m/s) and position ``p_n`` (m)
        at ``t[0]``.
    t : numpy.ndarray
        Sample times, s, ``(N,)``, increasing.
    f_b, omega_b : numpy.ndarray
        Specific force (m/s^2) and angular rate (rad/s) in ``b``, ``(N, 3)``; sample ``k`` is
        used over ``[t[k], t[k+1])`` (the last sample is unused).
    g_n : numpy.ndarray
        Gravity in ``n``, m/s^2.

    Returns
    -------
    tuple of numpy.ndarray
        ``C_nb`` ``(N, 3, 3)``, ``v_n`` ``(N, 3)``, ``p_n`` ``(N, 3)`` at the times ``t``.
    """
    n = len(t)
    C = np.empty((n, 3, 3))
    v = np.empty((n, 3))
    p = np.empty((n, 3))
    C[0], v[0], p[0] = C0, v0, p0
    f = np.asarray(f_b, dtype=float)
    w = np.asarray(omega_b, dtype=float)
    g = np.asarray(g_n, dtype=float)
    for k in range(n - 1):
        C[k + 1], v[k + 1], p[k + 1] = step(C[k], v[k], p[k], f[k], w[k], float(t[k + 1] - t[k]), g)
    return C, v, p
