"""Covariances of the ``eskf`` initial alignment: levelling and the heading reset."""

from __future__ import annotations

import math

import numpy as np
import numpy.typing as npt

from iotnav.engines.eskf.layout import ATT, GNE, GNM, POS, VEL

FloatArray = npt.NDArray[np.float64]


# ----------------------------------------------------------------------------- initialisation
def level_covariance(
    C_nb: FloatArray,
    f_b: FloatArray,
    g: float,
    var_ba_b: FloatArray,
    var_sa: FloatArray | None,
    tilt_white_std_rad: float,
) -> FloatArray:
    """Joint covariance of ``[ATT, BA(, SA)]`` right after accelerometer levelling.

    Levelling finds the ``C_nb`` that makes the mean measured specific force point up, so it
    absorbs the accelerometer error ``u_b = db_a + diag(f_b) ds_a``: at rest the horizontal
    velocity error rate ``-[f_n x] dth - C_nb u_b`` is zero, which with ``f_n = (0, 0, -g)``
    gives (Groves 2013, §14.3.1; Titterton & Weston 2004, §10.2)::

        dth = J u_b + w,   J = (1/g) [[0, 1, 0], [-1, 0, 0], [0, 0, 0]] C_nb

    i.e. the tilt error is the accelerometer error divided by gravity and fully correlated
    with it; ``w`` (``tilt_white_std_rad``) is the part not due to the sensor errors (noise
    of the mean, motion during the window). Yaw is not levelled (zero row).

    Parameters
    ----------
    C_nb : numpy.ndarray
        Levelled attitude.
    f_b : numpy.ndarray
        Mean measured specific force over the window, m/s^2.
    g : float
        Gravity, m/s^2.
    var_ba_b : numpy.ndarray
        Per-axis accelerometer bias variance, (m/s^2)^2.
    var_sa : numpy.ndarray or None
        Per-axis accelerometer scale-factor variance (None without scale-factor states).
    tilt_white_std_rad : float
        Independent tilt error, rad.

    Returns
    -------
    numpy.ndarray
        ``(6, 6)`` (``ATT``, ``BA``) or ``(9, 9)`` (``ATT``, ``BA``, ``SA``) covariance.
    """
    J = np.array([[0.0, 1.0, 0.0], [-1.0, 0.0, 0.0], [0.0, 0.0, 0.0]]) @ C_nb / g
    m = 6 if var_sa is None else 9
    # error sources s = [db_a, ds_a]; dth = [J, J diag(f_b)] s + w
    S = np.diag(np.concatenate([var_ba_b, [] if var_sa is None else var_sa]))
    B = np.zeros((m, m - 3))
    B[0:3, 0:3] = J
    if var_sa is not None:
        B[0:3, 3:6] = J * f_b[None, :]
    B[3:, :] = np.eye(m - 3)
    P = B @ S @ B.T
    P[0:2, 0:2] += tilt_white_std_rad**2 * np.eye(2)
    return 0.5 * (P + P.T)


def heading_reset_transform(dpsi: float, n: int) -> FloatArray:
    """Error-state transform when the nominal yaw is reset by ``dpsi`` (``C_nb <- R_z C_nb``).

    The filter runs before the heading is known in a navigation frame with an arbitrary yaw;
    resetting the yaw rotates that frame by ``R_z(dpsi)``, so every error resolved in ``n``
    (position, velocity, attitude, both GNSS error blocks) rotates with it: ``dx_n' = R_z dx_n``, and
    ``P' = T P T^T`` (the biases, mount and scale factors are in ``b``/``v`` and unchanged).
    Without it the tilt / accelerometer-bias correlation learnt at rest points the wrong way
    and makes the tilt spuriously observable.
    """
    c, s = math.cos(dpsi), math.sin(dpsi)
    R = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    T = np.eye(n)
    for sl in (POS, VEL, ATT, GNE, GNM):
        T[sl, sl] = R
    return T
