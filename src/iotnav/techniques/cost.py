"""Computational cost of the pipeline's blocks (Forno et al. 2020, Table I).

Analytic operation counts of a Kalman filter with state size ``n``, measurement size ``m`` and
control size ``p`` (scalar sums and multiplications; a subtraction is a sum, a division or a
square root counts as a multiplication), and wall-clock timing of each block's step.

Predict (``x = F x + B u``, ``P = F P F^T + Q``, dense matrices)::

    F x          n^2 mul   n(n-1) sum
    B u          n p mul   n(p-1) sum,  + n sums to add it      (only when p > 0)
    F P          n^3 mul   n^2(n-1) sum
    (F P) F^T    n^3 mul   n^2(n-1) sum
    + Q                    n^2 sum
    total        2n^3 + n^2 + n p  mul,   2n^3 - n + n p  sum   (p > 0)

This reproduces the paper's fusion-filter predict exactly: [9, 5, 3] -> 1476 sums,
1566 mults. For the [3, 3, 3] filters the paper's 63 mults equal ``2n^3 + n^2`` (no control
product: the tilt/yaw propagation ``x = (I - dt [omega x]) x`` has none) while its 54 sums
equal ``2n^3``, three more than our ``2n^3 - n`` (51): the paper's table does not say how.

Update (``y = z - H x``, ``S = H P H^T + R``, Cholesky ``S = L L^T``, ``K = P H^T S^-1`` by
forward and back substitution, ``x += K y`` and the simple ``P -= K (H P)``)::

    H x, z - H x         m n mul        m n sum
    P H^T                n^2 m mul      n m (n-1) sum
    H (P H^T) + R        m^2 n mul      m^2 n sum
    Cholesky of S        m(m-1)(m+4)/6 + m mul (incl. m sqrt and divisions)   m(m-1)(m+1)/6 sum
    K: 2 triangular solves with n right-hand sides   n m (m+1) mul   n m (m-1) sum
    x + K y              n m mul        n m sum
    K (H P), P - ...     n^2 m mul      n^2 m sum

The paper's update counts (159 / 207 for [3, 3, 3], 2493 / 2869 for [9, 5, 3]) are not
reproduced by this or by the Joseph-form variant (added as ``joseph=True``: ``(I-KH) P
(I-KH)^T + K R K^T``); both are returned by :func:`table_i` side by side with the paper.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from typing import Any

import numpy as np

#: Table I of the paper: (block, portion) -> (FLOPs [29], sums [30], mults [30]).
PAPER_TABLE_I: dict[str, dict[str, float]] = {
    "kf333_predict": {"flops": 120, "sums": 54, "mults": 63},
    "kf333_update": {"flops": 183, "sums": 159, "mults": 207},
    "kf953_predict": {"flops": 3078, "sums": 1476, "mults": 1566},
    "kf953_update": {"flops": 2165, "sums": 2493, "mults": 2869},
    "load_position": {"flops": 4},
    "static_filter_mean": {"flops": 40},
    "yaw_alignment": {"flops": 134},
}


def kf_predict_cost(n: int, p: int = 0) -> tuple[int, int]:
    """``(sums, mults)`` of one dense predict (formulas in the module docstring)."""
    sums = n * (n - 1) + 2 * n * n * (n - 1) + n * n
    mults = n * n + 2 * n**3
    if p > 0:
        sums += n * (p - 1) + n
        mults += n * p
    return sums, mults


def cholesky_cost(m: int) -> tuple[int, int]:
    """``(sums, mults)`` of the Cholesky factorisation of an ``m x m`` matrix (sqrt counted as mult)."""
    sums = mults = 0
    for j in range(m):
        sums += j  # diagonal: a_jj - sum L_jk^2
        mults += j + 1  # squares + sqrt
        for _ in range(j + 1, m):
            sums += j
            mults += j + 1  # products + division
    return sums, mults


def kf_update_cost(n: int, m: int, joseph: bool = False) -> tuple[int, int]:
    """``(sums, mults)`` of one dense update with a Cholesky solve."""
    cs, cm = cholesky_cost(m)
    sums = m * n + n * m * (n - 1) + m * m * n + cs + n * m * (m - 1) + n * m
    mults = m * n + n * n * m + m * m * n + cm + n * m * (m + 1) + n * m
    if joseph:
        # I - K H; (I-KH) P; (.)(I-KH)^T; K R; (K R) K^T; sum of the two
        sums += n * n * (m - 1) + n + 2 * n * n * (n - 1) + n * m * (m - 1) + n * n * (m - 1) + n * n
        mults += n * n * m + 2 * n**3 + n * m * m + n * n * m
    else:
        sums += n * n * m
        mults += n * n * m
    return sums, mults


def table_i() -> dict[str, dict[str, Any]]:
    """Our counts next to the paper's for the two filter shapes of Table I."""
    out: dict[str, dict[str, Any]] = {}
    for key, (n, m, p) in {"kf333": (3, 3, 0), "kf953": (9, 5, 3)}.items():
        ps, pm = kf_predict_cost(n, p)
        us, um = kf_update_cost(n, m)
        js, jm = kf_update_cost(n, m, joseph=True)
        out[f"{key}_predict"] = {"ours": {"sums": ps, "mults": pm}, "paper": PAPER_TABLE_I[f"{key}_predict"]}
        out[f"{key}_update"] = {
            "ours": {"sums": us, "mults": um},
            "ours_joseph": {"sums": js, "mults": jm},
            "paper": PAPER_TABLE_I[f"{key}_update"],
        }
    return out


def _time(fn: Callable[[], object], n_calls: int) -> float:
    fn()
    t0 = time.perf_counter()
    for _ in range(n_calls):
        fn()
    return (time.perf_counter() - t0) / n_calls


def time_blocks(n_calls: int = 2000, seed: int = 0) -> dict[str, float]:
    """Wall-clock seconds per call of each block's step (for the CLI; not used in unit tests).

    Parameters
    ----------
    n_calls : int
        Calls timed per block.
    seed : int
        Seed of the random inputs.

    Returns
    -------
    dict
        Block name -> mean seconds per call.
    """
    from iotnav.techniques.cascade import CascadeKF
    from iotnav.techniques.fusion_kf import FusionKF
    from iotnav.techniques.gyro_bias_kf import GyroBiasKF
    from iotnav.techniques.last_position import LastPositionLogic
    from iotnav.techniques.lowpass3 import Lowpass3
    from iotnav.techniques.mount import MountAligner
    from iotnav.techniques.static import StaticDetector
    from iotnav.techniques.tilt_kf import TiltKF
    from iotnav.techniques.yaw_kf import YawKF

    rng = np.random.default_rng(seed)
    acc = np.array([0.0, 0.0, -9.81]) + rng.normal(0, 0.02, 3)
    gyr = rng.normal(0, 0.01, 3)
    x3 = np.array([0.0, 0.0, 1.0])
    tilt, yaw, bias, casc = TiltKF(), YawKF(), GyroBiasKF(), CascadeKF()
    yaw.reset_heading(0.3, x3)
    det, lp, mnt, boot = StaticDetector(), Lowpass3(), MountAligner(), LastPositionLogic()
    fus = FusionKF()
    fus.initialise(np.zeros(3), np.eye(3))
    C = np.eye(3)
    R = np.eye(3)
    res = {
        "tilt_predict": _time(lambda: tilt.predict(gyr, 0.01), n_calls),
        "tilt_update": _time(lambda: tilt.update(acc, 9.81), n_calls),
        "yaw_predict": _time(lambda: yaw.predict(gyr, 0.01), n_calls),
        "yaw_update": _time(lambda: yaw.update_heading(0.3, x3), n_calls),
        "gyro_bias_predict": _time(lambda: bias.predict(0.01), n_calls),
        "gyro_bias_update": _time(lambda: bias.update_static(gyr), n_calls),
        "cascade_step": _time(lambda: casc.step(acc, gyr, 0.01, False, 9.81), n_calls),
        "static_step": _time(lambda: det.step(0.0, acc), n_calls),
        "lowpass3_push": _time(lambda: lp.push(acc), n_calls),
        "mount_add_imu": _time(lambda: mnt.add_imu(acc[:2], 0.0), n_calls),
        "last_position_check": _time(lambda: boot.check_fix(True, 45.0, 7.0, 2.0, 8), n_calls),
        "fusion_predict": _time(lambda: fus.predict(acc, C, 0.01), n_calls),
        "fusion_update_position": _time(lambda: fus.update_position(np.zeros(3), R), n_calls),
    }
    return res
