"""Attitude from two vector observations: TRIAD and the improved (weighted) TRIAD.

Used by the ``qekf`` engine (Cavalcante et al., IMU-GPS-magnetometer quaternion EKF, Eq. 7) to
turn one accelerometer sample (gravity) and one magnetometer sample into an absolute attitude
``C_nb``, i.e. a quaternion observation ``q_nb``.

TRIAD (Black 1964; the paper's Eq. 7)
    For reference vectors ``r1, r2`` in ``n`` and the same vectors ``b1, b2`` measured in ``b``
    build the orthonormal triads anchored on the first vector::

        t1 = u1,  t2 = (u1 x u2) / |u1 x u2|,  t3 = t1 x t2      (u = unit vectors)
        [t1_n t2_n t3_n] = C_nb [t1_b t2_b t3_b]
        C_nb = T_n T_b^T

    The anchor vector is matched exactly; the second only fixes the rotation about it, so all
    the error of the anchor vector enters the solution ("great sensitivity to measurement
    errors", as the paper found).

Improved TRIAD (Li and Yuan 2005, cited by the paper; reconstructed here)
    The extracted paper text names the method but gives no equations. We implement the
    accuracy-weighted form (the "optimised TRIAD" of Bar-Itzhack and Harman 1997, which the
    improved TRIAD family shares): compute the TRIAD solution anchored on each vector,
    ``C1`` (anchor ``b1``) and ``C2`` (anchor ``b2``), average them with weights inversely
    proportional to the direction variances ``sigma1^2, sigma2^2`` (rad^2) of the two
    measurements, and return the nearest rotation (SVD projection onto SO(3))::

        C = (sigma2^2 C1 + sigma1^2 C2) / (sigma1^2 + sigma2^2)
        C_nb = U diag(1, 1, det(U V^T)) V^T,   C = U S V^T

    With ``sigma1 << sigma2`` the result tends to ``C1`` (the accurate vector is matched, the
    other only fixes the rotation about it); with equal sigmas both vectors share the error.

Covariance (for the EKF's measurement noise): for the anchored TRIAD with unit vectors and
direction noises ``sigma1`` (anchor), ``sigma2`` (Shuster and Oh 1981), the rotation-vector
error covariance in ``n`` is::

    P = sigma1^2 I + [(sigma2^2 - sigma1^2) r1 r1^T + sigma1^2 (r1 . r2)(r1 r2^T + r2 r1^T)] / |r1 x r2|^2

:func:`triad_covariance` returns it with the more accurate vector as anchor, an upper bound
for the weighted solution.

Jacobian with respect to the measured vectors (:func:`triad_jacobian`; used by ``qekf`` to
carry the dependence of the gravity vector on the accelerometer-bias estimate into the
measurement matrix). Write ``C = T_n T_b^T`` and perturb ``b1`` or ``b2``: ``T_n`` is fixed, so
``dC C^T = T_n (dT_b^T T_b) T_n^T``; ``Omega = dT_b^T T_b`` is skew, and the rotation-vector
perturbation in ``n`` (``C' = exp([dtheta x]) C``) is ``dtheta = T_n vee(Omega)`` with
``vee(Omega) = [t2 . dt3, t3 . dt1, t1 . dt2]`` (``t_i`` the columns of ``T_b``). For the anchor
``a = b1 / |b1|``, ``u = a x b2``, ``c = u / |u|``::

    da = (I - a a^T) / |b1| db1
    du = -[b2 x] da + [a x] db2,     dc = (I - c c^T) / |u| du
    d(a x c) = -[c x] da + [a x] dc

The weighted solution's perturbation is, to first order about consistent data (``C1 = C2``),
the weighted mean of the two anchored ones, ``(sigma2^2 dtheta_1 + sigma1^2 dtheta_2) /
(sigma1^2 + sigma2^2)`` (the SVD projection of a weighted mean of two nearby rotations is the
weighted mean of their rotation vectors to first order).
"""

from __future__ import annotations

import math

import numba
import numpy as np
import numpy.typing as npt

FloatArray = npt.NDArray[np.float64]

__all__ = ["dcm_to_quat", "improved_triad", "quat_to_dcm", "triad", "triad_covariance", "triad_jacobian"]


def _triad_frame(u1: FloatArray, u2: FloatArray) -> FloatArray:
    a = u1 / np.linalg.norm(u1)
    c = np.cross(a, u2)
    nc = np.linalg.norm(c)
    if nc < 1e-9 * np.linalg.norm(u2):
        raise ValueError("TRIAD: the two vectors are (nearly) collinear")
    c = c / nc
    return np.column_stack([a, c, np.cross(a, c)])


def triad(b1: FloatArray, b2: FloatArray, r1: FloatArray, r2: FloatArray) -> FloatArray:
    """Classic TRIAD, anchored on the first vector.

    Parameters
    ----------
    b1, b2 : numpy.ndarray
        The two vectors measured in ``b`` (any units, only directions matter).
    r1, r2 : numpy.ndarray
        The same vectors in ``n``.

    Returns
    -------
    numpy.ndarray
        ``C_nb`` (3, 3), with ``C_nb @ b1 / |b1| == r1 / |r1|`` exactly.

    Raises
    ------
    ValueError
        When a pair of vectors is collinear.
    """
    Tb = _triad_frame(np.asarray(b1, float), np.asarray(b2, float))
    Tn = _triad_frame(np.asarray(r1, float), np.asarray(r2, float))
    return Tn @ Tb.T


def improved_triad(
    b1: FloatArray, b2: FloatArray, r1: FloatArray, r2: FloatArray, sigma1: float, sigma2: float
) -> FloatArray:
    """Accuracy-weighted TRIAD (see the module docstring).

    Parameters
    ----------
    b1, b2 : numpy.ndarray
        Measured vectors in ``b``.
    r1, r2 : numpy.ndarray
        Reference vectors in ``n``.
    sigma1, sigma2 : float
        Direction standard deviations of ``b1`` and ``b2``, rad (> 0).

    Returns
    -------
    numpy.ndarray
        ``C_nb`` (3, 3), a proper rotation.
    """
    C1 = triad(b1, b2, r1, r2)
    C2 = triad(b2, b1, r2, r1)
    w1, w2 = sigma2 * sigma2, sigma1 * sigma1
    C = (w1 * C1 + w2 * C2) / (w1 + w2)
    U, _s, Vt = np.linalg.svd(C)
    d = 1.0 if np.linalg.det(U @ Vt) > 0 else -1.0
    return U @ np.diag([1.0, 1.0, d]) @ Vt


def _skew(v: FloatArray) -> FloatArray:
    return np.array([[0.0, -v[2], v[1]], [v[2], 0.0, -v[0]], [-v[1], v[0], 0.0]])


def _anchored_jacobian(b1: FloatArray, b2: FloatArray, T_n: FloatArray) -> tuple[FloatArray, FloatArray]:
    """``d theta_n / d b1`` and ``d theta_n / d b2`` of TRIAD anchored on ``b1`` (module docstring)."""
    n1 = float(np.linalg.norm(b1))
    a = b1 / n1
    u = np.cross(a, b2)
    nu = float(np.linalg.norm(u))
    c = u / nu
    e = np.cross(a, c)
    da1 = (np.eye(3) - np.outer(a, a)) / n1  # d a / d b1
    Pc = (np.eye(3) - np.outer(c, c)) / nu
    Sa, Sc = _skew(a), _skew(c)
    du1 = -_skew(b2) @ da1
    dc1 = Pc @ du1
    dc2 = Pc @ Sa  # d c / d b2
    de1 = -Sc @ da1 + Sa @ dc1
    de2 = Sa @ dc2
    J1 = np.vstack([c @ de1, e @ da1, a @ dc1])
    J2 = np.vstack([c @ de2, np.zeros(3), a @ dc2])
    return T_n @ J1, T_n @ J2


def triad_jacobian(
    b1: FloatArray, b2: FloatArray, r1: FloatArray, r2: FloatArray, sigma1: float, sigma2: float
) -> tuple[FloatArray, FloatArray]:
    """First-order sensitivity of :func:`improved_triad` to the measured vectors.

    Parameters
    ----------
    b1, b2 : numpy.ndarray
        Measured vectors in ``b``.
    r1, r2 : numpy.ndarray
        Reference vectors in ``n``.
    sigma1, sigma2 : float
        Direction standard deviations, rad (the weights of :func:`improved_triad`).

    Returns
    -------
    J1, J2 : numpy.ndarray
        ``d theta_n / d b1`` and ``d theta_n / d b2`` (3, 3), rad per unit of the vectors, with
        ``C_nb(b + db) = exp([dtheta_n x]) C_nb(b)`` (exact derivative for consistent vectors,
        see the module docstring).
    """
    b1 = np.asarray(b1, float)
    b2 = np.asarray(b2, float)
    A1, A2 = _anchored_jacobian(b1, b2, _triad_frame(np.asarray(r1, float), np.asarray(r2, float)))
    B2, B1 = _anchored_jacobian(b2, b1, _triad_frame(np.asarray(r2, float), np.asarray(r1, float)))
    w1, w2 = sigma2 * sigma2, sigma1 * sigma1
    return (w1 * A1 + w2 * B1) / (w1 + w2), (w1 * A2 + w2 * B2) / (w1 + w2)


def triad_covariance(r1: FloatArray, r2: FloatArray, sigma1: float, sigma2: float) -> FloatArray:
    """Rotation-vector error covariance (rad^2, in ``n``) of TRIAD anchored on the better vector.

    Parameters
    ----------
    r1, r2 : numpy.ndarray
        Reference vectors in ``n``.
    sigma1, sigma2 : float
        Direction standard deviations of the two measurements, rad.

    Returns
    -------
    numpy.ndarray
        (3, 3) covariance of ``delta_theta`` in ``C_nb_true = exp([delta_theta x]) C_nb``.
    """
    if sigma2 < sigma1:
        r1, r2, sigma1, sigma2 = r2, r1, sigma2, sigma1
    u1 = np.asarray(r1, float) / np.linalg.norm(r1)
    u2 = np.asarray(r2, float) / np.linalg.norm(r2)
    s2 = float(np.sum(np.cross(u1, u2) ** 2))
    c = float(u1 @ u2)
    return (
        sigma1**2 * np.eye(3)
        + ((sigma2**2 - sigma1**2) * np.outer(u1, u1) + sigma1**2 * c * (np.outer(u1, u2) + np.outer(u2, u1)))
        / s2
    )


def dcm_to_quat(C: FloatArray) -> FloatArray:
    """Unit quaternion ``[w, x, y, z]`` (``w >= 0``) of a rotation matrix (Shepperd's method)."""
    tr = C[0, 0] + C[1, 1] + C[2, 2]
    cand = (tr, C[0, 0], C[1, 1], C[2, 2])
    i = int(np.argmax(cand))
    if i == 0:
        s = 2.0 * math.sqrt(max(1.0 + tr, 0.0))
        q = np.array([0.25 * s, (C[2, 1] - C[1, 2]) / s, (C[0, 2] - C[2, 0]) / s, (C[1, 0] - C[0, 1]) / s])
    elif i == 1:
        s = 2.0 * math.sqrt(max(1.0 + C[0, 0] - C[1, 1] - C[2, 2], 0.0))
        q = np.array([(C[2, 1] - C[1, 2]) / s, 0.25 * s, (C[0, 1] + C[1, 0]) / s, (C[0, 2] + C[2, 0]) / s])
    elif i == 2:
        s = 2.0 * math.sqrt(max(1.0 - C[0, 0] + C[1, 1] - C[2, 2], 0.0))
        q = np.array([(C[0, 2] - C[2, 0]) / s, (C[0, 1] + C[1, 0]) / s, 0.25 * s, (C[1, 2] + C[2, 1]) / s])
    else:
        s = 2.0 * math.sqrt(max(1.0 - C[0, 0] - C[1, 1] + C[2, 2], 0.0))
        q = np.array([(C[1, 0] - C[0, 1]) / s, (C[0, 2] + C[2, 0]) / s, (C[1, 2] + C[2, 1]) / s, 0.25 * s])
    q = q / np.linalg.norm(q)
    return q if q[0] >= 0 else -q


def quat_to_dcm(q: FloatArray) -> FloatArray:
    """``C_nb`` of a quaternion ``[w, x, y, z]``; quadratic form, exact rotation for ``|q| = 1``.

    ``C(q) = (w^2 - v.v) I + 2 v v^T + 2 w [v x]`` (scaled by ``|q|^2`` otherwise).
    """
    w, x, y, z = float(q[0]), float(q[1]), float(q[2]), float(q[3])
    return np.array(
        [
            [w * w + x * x - y * y - z * z, 2.0 * (x * y - w * z), 2.0 * (x * z + w * y)],
            [2.0 * (x * y + w * z), w * w - x * x + y * y - z * z, 2.0 * (y * z - w * x)],
            [2.0 * (x * z - w * y), 2.0 * (y * z + w * x), w * w - x * x - y * y + z * z],
        ]
    )


# ----------------------------------------------------------------------------- compiled forms
# The same equations, compiled (numba) for the ``qekf`` engine's TRIAD observation
# (:func:`iotnav.engines.qekf_updates_kernel.triad_model`); tests/test_triad.py checks them
# against the forms above. They differ from them only by the rounding of the small matrix
# products (numpy's go through BLAS), at the 1e-16 level.


@numba.njit(cache=True)
def _norm3(v: FloatArray) -> float:
    return math.sqrt(v[0] * v[0] + v[1] * v[1] + v[2] * v[2])


@numba.njit(cache=True)
def _cross3(a: FloatArray, b: FloatArray) -> FloatArray:
    return np.array([a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]])


@numba.njit(cache=True)
def _mm(A: FloatArray, B: FloatArray) -> FloatArray:
    """``A @ B`` for small matrices."""
    n, k = A.shape
    m = B.shape[1]
    out = np.zeros((n, m))
    for i in range(n):
        for j in range(m):
            s = 0.0
            for q in range(k):
                s += A[i, q] * B[q, j]
            out[i, j] = s
    return out


@numba.njit(cache=True)
def _skew_nb(v: FloatArray) -> FloatArray:
    return np.array([[0.0, -v[2], v[1]], [v[2], 0.0, -v[0]], [-v[1], v[0], 0.0]])


@numba.njit(cache=True)
def triad_frame_nb(u1: FloatArray, u2: FloatArray) -> tuple[FloatArray, bool]:
    """The TRIAD frame ``[a, c, a x c]`` (columns) anchored on ``u1``; False (and NaN) when
    the vectors are (nearly) collinear (:func:`triad` raises then)."""
    a = u1 / _norm3(u1)
    c = _cross3(a, u2)
    nc = _norm3(c)
    T = np.empty((3, 3))
    if nc < 1e-9 * _norm3(u2):
        T[:, :] = np.nan
        return T, False
    c = c / nc
    e = _cross3(a, c)
    for i in range(3):
        T[i, 0], T[i, 1], T[i, 2] = a[i], c[i], e[i]
    return T, True


@numba.njit(cache=True)
def improved_triad_nb(
    b1: FloatArray, b2: FloatArray, r1: FloatArray, r2: FloatArray, sigma1: float, sigma2: float
) -> tuple[FloatArray, bool]:
    """:func:`improved_triad`, compiled; False when a pair of vectors is collinear."""
    Tb1, ok1 = triad_frame_nb(b1, b2)
    Tn1, ok2 = triad_frame_nb(r1, r2)
    Tb2, ok3 = triad_frame_nb(b2, b1)
    Tn2, ok4 = triad_frame_nb(r2, r1)
    if not (ok1 and ok2 and ok3 and ok4):
        return np.full((3, 3), np.nan), False
    C1 = _mm(Tn1, Tb1.T)
    C2 = _mm(Tn2, Tb2.T)
    w1, w2 = sigma2 * sigma2, sigma1 * sigma1
    C = (w1 * C1 + w2 * C2) / (w1 + w2)
    U, _s, Vt = np.linalg.svd(C)
    UV = _mm(U, Vt)
    d = 1.0 if np.linalg.det(UV) > 0 else -1.0
    D = np.eye(3)
    D[2, 2] = d
    return _mm(_mm(U, D), Vt), True


@numba.njit(cache=True)
def _anchored_jacobian_nb(b1: FloatArray, b2: FloatArray, T_n: FloatArray) -> tuple[FloatArray, FloatArray]:
    """:func:`_anchored_jacobian`, compiled."""
    n1 = _norm3(b1)
    a = b1 / n1
    u = _cross3(a, b2)
    nu = _norm3(u)
    c = u / nu
    e = _cross3(a, c)
    da1 = (np.eye(3) - np.outer(a, a)) / n1
    Pc = (np.eye(3) - np.outer(c, c)) / nu
    Sa, Sc = _skew_nb(a), _skew_nb(c)
    du1 = _mm(-_skew_nb(b2), da1)
    dc1 = _mm(Pc, du1)
    dc2 = _mm(Pc, Sa)
    de1 = -_mm(Sc, da1) + _mm(Sa, dc1)
    de2 = _mm(Sa, dc2)
    J1 = np.zeros((3, 3))
    J2 = np.zeros((3, 3))
    for j in range(3):
        s0, s1, s2, t0, t2 = 0.0, 0.0, 0.0, 0.0, 0.0
        for k in range(3):
            s0 += c[k] * de1[k, j]
            s1 += e[k] * da1[k, j]
            s2 += a[k] * dc1[k, j]
            t0 += c[k] * de2[k, j]
            t2 += a[k] * dc2[k, j]
        J1[0, j], J1[1, j], J1[2, j] = s0, s1, s2
        J2[0, j], J2[2, j] = t0, t2
    return _mm(T_n, J1), _mm(T_n, J2)


@numba.njit(cache=True)
def triad_jacobian_nb(
    b1: FloatArray, b2: FloatArray, r1: FloatArray, r2: FloatArray, sigma1: float, sigma2: float
) -> tuple[FloatArray, FloatArray]:
    """:func:`triad_jacobian`, compiled (the vectors not collinear)."""
    Tn1, _ok1 = triad_frame_nb(r1, r2)
    Tn2, _ok2 = triad_frame_nb(r2, r1)
    A1, A2 = _anchored_jacobian_nb(b1, b2, Tn1)
    B2, B1 = _anchored_jacobian_nb(b2, b1, Tn2)
    w1, w2 = sigma2 * sigma2, sigma1 * sigma1
    return (w1 * A1 + w2 * B1) / (w1 + w2), (w1 * A2 + w2 * B2) / (w1 + w2)


@numba.njit(cache=True)
def triad_covariance_nb(r1: FloatArray, r2: FloatArray, sigma1: float, sigma2: float) -> FloatArray:
    """:func:`triad_covariance`, compiled."""
    if sigma2 < sigma1:
        r1, r2, sigma1, sigma2 = r2, r1, sigma2, sigma1
    u1 = r1 / _norm3(r1)
    u2 = r2 / _norm3(r2)
    x = _cross3(u1, u2)
    s2 = x[0] * x[0] + x[1] * x[1] + x[2] * x[2]
    c = u1[0] * u2[0] + u1[1] * u2[1] + u1[2] * u2[2]
    P = np.empty((3, 3))
    for i in range(3):
        for j in range(3):
            P[i, j] = (sigma1 * sigma1 if i == j else 0.0) + (
                (sigma2 * sigma2 - sigma1 * sigma1) * (u1[i] * u1[j])
                + sigma1 * sigma1 * c * (u1[i] * u2[j] + u2[i] * u1[j])
            ) / s2
    return P


@numba.njit(cache=True)
def dcm_to_quat_nb(C: FloatArray) -> FloatArray:
    """:func:`dcm_to_quat`, compiled."""
    tr = C[0, 0] + C[1, 1] + C[2, 2]
    i = 0
    best = tr
    for k, v in ((1, C[0, 0]), (2, C[1, 1]), (3, C[2, 2])):
        if v > best:
            i, best = k, v
    if i == 0:
        s = 2.0 * math.sqrt(max(1.0 + tr, 0.0))
        q = np.array([0.25 * s, (C[2, 1] - C[1, 2]) / s, (C[0, 2] - C[2, 0]) / s, (C[1, 0] - C[0, 1]) / s])
    elif i == 1:
        s = 2.0 * math.sqrt(max(1.0 + C[0, 0] - C[1, 1] - C[2, 2], 0.0))
        q = np.array([(C[2, 1] - C[1, 2]) / s, 0.25 * s, (C[0, 1] + C[1, 0]) / s, (C[0, 2] + C[2, 0]) / s])
    elif i == 2:
        s = 2.0 * math.sqrt(max(1.0 - C[0, 0] + C[1, 1] - C[2, 2], 0.0))
        q = np.array([(C[0, 2] - C[2, 0]) / s, (C[0, 1] + C[1, 0]) / s, 0.25 * s, (C[1, 2] + C[2, 1]) / s])
    else:
        s = 2.0 * math.sqrt(max(1.0 - C[0, 0] - C[1, 1] + C[2, 2], 0.0))
        q = np.array([(C[1, 0] - C[0, 1]) / s, (C[0, 2] + C[2, 0]) / s, (C[1, 2] + C[2, 1]) / s, 0.25 * s])
    q = q / math.sqrt(q[0] * q[0] + q[1] * q[1] + q[2] * q[2] + q[3] * q[3])
    return q if q[0] >= 0 else -q
