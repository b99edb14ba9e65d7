"""Accelerometer sums between GNSS fixes for the ``fixes`` engine's static test (:mod:`iotnav.engines.fixes`).

Per fix the engine keeps ``[n, sum |f|, sum |f|^2]`` of the IMU specific-force samples (m/s^2)
since the previous fix; the kernel turns them into the standard deviation of ``|f_b|``.
"""

from __future__ import annotations

import math

import numba
import numpy as np
import numpy.typing as npt

FloatArray = npt.NDArray[np.float64]

__all__ = ["acc_add", "acc_between_fixes"]


@numba.njit(cache=True)
def acc_add(acc: FloatArray, ax: float, ay: float, az: float) -> None:
    """Add one accelerometer sample (m/s^2) to ``acc = [n, sum |f|, sum |f|^2]``."""
    a = math.sqrt(ax * ax + ay * ay + az * az)
    acc[0] += 1.0
    acc[1] += a
    acc[2] += a * a


@numba.njit(cache=True)
def acc_between_fixes(
    t_imu: FloatArray,
    ax: FloatArray,
    ay: FloatArray,
    az: FloatArray,
    t_fix: FloatArray,
    acc: FloatArray,
    out: FloatArray,
) -> None:
    """Per fix, ``[n, sum |f|, sum |f|^2]`` of the IMU samples since the previous fix (times sorted).

    A sample at a fix's time belongs to the next fix (GNSS first at equal times, as
    :func:`~iotnav.engines.base.run_batch`); ``acc`` holds the running sums before the first
    fix and receives those after the last, exactly as streaming :func:`acc_add` builds them.
    """
    i = 0
    for j in range(t_fix.size):
        while i < t_imu.size and t_imu[i] < t_fix[j]:
            acc_add(acc, ax[i], ay[i], az[i])
            i += 1
        out[j, 0], out[j, 1], out[j, 2] = acc[0], acc[1], acc[2]
        acc[:] = 0.0
    while i < t_imu.size:
        acc_add(acc, ax[i], ay[i], az[i])
        i += 1
