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
:mod:`iotnav.kalman` implements the Joseph form, so the full table (:func:`full_table`) uses
it for "ours". The NIS (``y^T S^-1 y``, ``m(m+2)`` mults and ``m^2 - 1`` sums more) is not
counted, as in the paper.

The other blocks of Table I (:func:`full_table`; ``FLOPs = sums + mults`` as in the paper, a
division, square root or elementary function counts as one multiplication, a comparison as one
sum):

Block 1, load position
    Ours: 5 memory accesses (lat, lon, height, time, mount angle) and, once per boot, the
    haversine distance to the first fix and its threshold test (:func:`load_position_cost`):
    3 conversions to radians, 2 halvings, 2 sines, 2 squares, 2 cosines, 2 products, sqrt,
    asin, times ``2 R`` = 16 mults; ``dlat``, ``dlon``, the sum under the root, ``min(1, .)``
    and the threshold comparison = 5 sums. Paper: 4 FLOPs (memory access).
Block 4, static filter, mean of buffer (worst case)
    Mean of ``N`` vectors of dimension ``d``: ``d (N - 1)`` sums and ``d`` divisions
    (:func:`mean_cost`). Worst case of one :meth:`Lowpass3.push` (all three levels complete
    at once): ``d (n1 + n2 + n3 - 3)`` sums, ``3 d`` divisions, ``d = 3`` (NED positions).
    The paper's 40 FLOPs equal the mean of 20 two-dimensional positions
    (``2 * 19 + 2``); its buffer sizes are not given.
Block 5, yaw alignment (lsq method, :func:`mount_cost`; ``K`` IMU samples per GPS interval,
``B`` rows per buffer, ``M`` smoothing epochs)
    Mean of buffer (per GPS interval): yaw rate ``r = x3 . omega_b`` per sample (3 mults,
    2 sums), running sums of ``f_b`` (3) and ``r`` (1): ``4 (K - 1)`` sums, 4 divisions;
    total ``2 K + 4 (K - 1)`` sums, ``3 K + 4`` mults.
    Other processing: per interval, levelling against the gravity reference
    (``d = f - f_ref`` 3 sums; ``|f_ref|`` 3 mults 2 sums 1 sqrt; ``u`` 3 divisions;
    ``x = e_x - u_x u`` 3 mults 1 sum; ``|x|`` 3 mults 2 sums 1 sqrt; ``x /= |x|``
    3 divisions; ``y = u x x`` 6 mults 3 sums; two dot products 6 mults 4 sums: 15 sums,
    29 mults), the row (``dv`` 1 sum, mean speed 1 sum 1 mult, ``v r`` 1 mult, ``dv/dt``
    1 division: 2 sums, 3 mults) and the matched smoothing of its 5 used columns
    (``5 (2M - 2)`` sums, ``5 (2M - 1) + 5`` mults, ``M > 1`` only); per buffer the lsq sums
    (8 mults and 4 sums per row, ``4 (B - 1)`` sums to add the rows), the forgetting factor
    (``B - 1`` sums for the duration, 1 division, 1 power) and the fused sums (4 mults and
    4 sums; the weights 3 mults 2 sums), the outlier gate (wrap: 1 sum 3 mults; hypot: 2 mults
    1 sum 1 sqrt; 1 mult; 1 comparison), and three angle estimates (buffer, gate, fused:
    hypot 3 mults 1 sum, atan2 1, coherence 3 mults, residual 2 sums 2 mults, sigma 5 mults,
    excitation 2 mults: 3 sums, 16 mults each).
    Rotm conversion (per output sample): ``C_nv = C_nb R_z(mu)^T``, which mixes only the first
    two columns: cos, sin and 3 x 2 x 2 products = 14 mults, 6 sums.
    Total: the sum of the three portions, as in the paper (they run at different rates).
    The paper's split (50 / 64 / 20) is for its Eqs. 2-3; only its total (134) and the
    rotation (20, equal to ours) compare directly.
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


def mean_cost(n: int, d: int = 1) -> tuple[int, int]:
    """``(sums, mults)`` of the mean of ``n`` vectors of dimension ``d``: ``d(n-1)``, ``d``."""
    return d * (n - 1), d


def load_position_cost() -> tuple[int, int]:
    """``(sums, mults)`` of block 1's moved-while-off test (haversine and threshold): 5, 16."""
    return 5, 16


def lowpass3_worst_cost(n1: int, n2: int, n3: int, d: int = 3) -> tuple[int, int]:
    """``(sums, mults)`` of the worst-case :meth:`Lowpass3.push`: three means at once."""
    parts = [mean_cost(n, d) for n in (n1, n2, n3)]
    return sum(p[0] for p in parts), sum(p[1] for p in parts)


def mount_cost(k_imu: int, b_rows: int, m_smooth: int) -> dict[str, tuple[int, int]]:
    """``(sums, mults)`` of block 5's portions (module docstring), keyed as in Table I.

    Parameters
    ----------
    k_imu : int
        IMU samples per GPS interval.
    b_rows : int
        Rows per buffer (``buffer_epochs``).
    m_smooth : int
        Matched-smoothing epochs ``M`` (1: none).
    """
    K, B, M = k_imu, b_rows, m_smooth
    mean = (2 * K + 4 * (K - 1), 3 * K + 4)
    lev = (15, 29)
    row = (2, 3)
    smooth = (5 * (2 * M - 2), 5 * (2 * M - 1) + 5) if M > 1 else (0, 0)
    per_interval = tuple(a + b + c for a, b, c in zip(lev, row, smooth, strict=True))
    lsq = (4 * B + 4 * (B - 1), 8 * B)
    forget = ((B - 1) + 4 + 2, 2 + 4 + 3)
    gate = (1 + 1 + 1, 3 + 3 + 1)
    est = (3 * 3, 3 * 16)
    other = (
        B * per_interval[0] + lsq[0] + forget[0] + gate[0] + est[0],
        B * per_interval[1] + lsq[1] + forget[1] + gate[1] + est[1],
    )
    rotm = (6, 14)
    total = (mean[0] + other[0] + rotm[0], mean[1] + other[1] + rotm[1])
    return {"mean_of_buffer": mean, "other_processing": other, "rotm_conversion": rotm, "total": total}


#: Paper values of the rows of :func:`full_table` (FLOPs [29], sums [30], mults [30]).
PAPER_ROWS: dict[str, dict[str, float]] = {
    "load_position": {"flops": 4},
    "kf333_predict": PAPER_TABLE_I["kf333_predict"],
    "kf333_update": PAPER_TABLE_I["kf333_update"],
    "tilt_total": {"flops": 423, "sums": 267, "mults": 333},
    "yaw_total": {"flops": 423, "sums": 267, "mults": 333},
    "gyro_bias_total": {"flops": 303, "sums": 213, "mults": 270},
    "static_mean": {"flops": 40},
    "mount_mean": {"flops": 50},
    "mount_other": {"flops": 64},
    "mount_rotm": {"flops": 20},
    "mount_total": {"flops": 134},
    "kf953_predict": PAPER_TABLE_I["kf953_predict"],
    "kf953_update": PAPER_TABLE_I["kf953_update"],
    "fusion_total": {"flops": 5243, "sums": 3969, "mults": 4435},
}


def full_table(
    config: Any | None = None, imu_rate_hz: float = 100.0, gnss_rate_hz: float = 1.0
) -> list[dict[str, Any]]:
    """Table I in the paper's layout: one dict per row, ours next to the paper's.

    Parameters
    ----------
    config : PipelineConfig, optional
        The configured pipeline (buffer sizes, velocity measurement); defaults when omitted.
    imu_rate_hz, gnss_rate_hz : float
        Rates that set ``K``, the IMU samples per GPS interval of block 5, Hz.

    Returns
    -------
    list of dict
        Keys ``block, module, portion, key, shape_ours, shape_paper, sums, mults, flops``
        (ours; None where not applicable) and ``paper`` (dict with ``flops`` and, for the
        filters, ``sums`` and ``mults``). Totals are per IMU sample with every update applied
        (ours: one predict per filter; the paper lists two predicts for tilt and yaw).
    """
    if config is None:
        from iotnav.engines.config import PipelineConfig

        config = PipelineConfig()
    rows: list[dict[str, Any]] = []

    def add(block: str, module: str, portion: str, key: str, sm: tuple[int, int] | None, **kw: Any) -> None:
        rows.append(
            {
                "block": block,
                "module": module,
                "portion": portion,
                "key": key,
                "sums": None if sm is None else sm[0],
                "mults": None if sm is None else sm[1],
                "flops": None if sm is None else sm[0] + sm[1],
                "paper": PAPER_ROWS.get(kw.pop("paper_key", key), {}),
                "shape_ours": kw.get("shape_ours", ""),
                "shape_paper": kw.get("shape_paper", ""),
            }
        )

    add("1", "Load position", "Memory access + moved test", "load_position", load_position_cost())
    p333 = kf_predict_cost(3, 0)
    u333 = kf_update_cost(3, 3, joseph=True)
    tot333 = (p333[0] + u333[0], p333[1] + u333[1])
    for module, key in (("Tilt KF", "tilt"), ("Yaw KF", "yaw"), ("Gyro bias KF", "gyro_bias")):
        sh = {"shape_ours": "[3,3,0]", "shape_paper": "[3,3,3]"}
        add("2", module, "KF Predict", f"{key}_predict", p333, paper_key="kf333_predict", **sh)
        add("2", module, "KF Update", f"{key}_update", u333, paper_key="kf333_update", **sh)
        add("2", module, "Total", f"{key}_total", tot333, **sh)
    lp = config.lowpass3
    add(
        "4",
        "Static filter",
        f"Mean of buffer (worst case, n={lp.n1},{lp.n2},{lp.n3})",
        "static_mean",
        lowpass3_worst_cost(lp.n1, lp.n2, lp.n3),
    )
    k = max(1, round(imu_rate_hz / gnss_rate_hz))
    m = config.mount
    mc = mount_cost(k, m.buffer_epochs, m.smooth_epochs)
    add("5", "Yaw alignment", f"Mean of buffer (per interval, K={k})", "mount_mean", mc["mean_of_buffer"])
    add(
        "5",
        "Yaw alignment",
        f"Other processing (per buffer, B={m.buffer_epochs}, M={m.smooth_epochs})",
        "mount_other",
        mc["other_processing"],
    )
    add("5", "Yaw alignment", "Rotm conversion", "mount_rotm", mc["rotm_conversion"])
    add("5", "Yaw alignment", "Total (sum of the portions)", "mount_total", mc["total"])
    p9 = kf_predict_cost(9, 3)
    m_vel = 3 if config.fusion.use_ned_velocity else 2
    u9p = kf_update_cost(9, 3, joseph=True)
    u9v = kf_update_cost(9, m_vel, joseph=True)
    u9 = (u9p[0] + u9v[0], u9p[1] + u9v[1])
    sh9 = {"shape_ours": f"[9,3+{m_vel},3]", "shape_paper": "[9,5,3]"}
    add("6", "Fusion KF", "KF Predict", "fusion_predict", p9, paper_key="kf953_predict", **sh9)
    add(
        "6",
        "Fusion KF",
        f"KF Update (3 + {m_vel} rows, sequential)",
        "fusion_update",
        u9,
        paper_key="kf953_update",
        **sh9,
    )
    add("6", "Fusion KF", "Total", "fusion_total", (p9[0] + u9[0], p9[1] + u9[1]), **sh9)
    return rows


#: Measured timings (keys of :func:`time_blocks`) that make up each row of :func:`full_table`.
TIMING_KEYS: dict[str, tuple[str, ...]] = {
    "load_position": ("load_position",),
    "tilt_predict": ("tilt_predict",),
    "tilt_update": ("tilt_update",),
    "tilt_total": ("tilt_predict", "tilt_update"),
    "yaw_predict": ("yaw_predict",),
    "yaw_update": ("yaw_update",),
    "yaw_total": ("yaw_predict", "yaw_update"),
    "gyro_bias_predict": ("gyro_bias_predict",),
    "gyro_bias_update": ("gyro_bias_update",),
    "gyro_bias_total": ("gyro_bias_predict", "gyro_bias_update"),
    "static_mean": ("lowpass3_worst_push",),
    "mount_mean": ("mount_add_imu_body",),
    "mount_other": ("mount_evaluate",),
    "mount_rotm": ("mount_rotm",),
    "mount_total": ("mount_add_imu_body", "mount_evaluate", "mount_rotm"),
    "fusion_predict": ("fusion_predict",),
    "fusion_update": ("fusion_update_position", "fusion_update_velocity"),
    "fusion_total": ("fusion_predict", "fusion_update_position", "fusion_update_velocity"),
}


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
    from iotnav.engines.config import PIPELINE_MOUNT
    from iotnav.geo import rot_z
    from iotnav.techniques.cascade import CascadeKF
    from iotnav.techniques.fusion_kf import FusionKF
    from iotnav.techniques.gyro_bias_kf import GyroBiasKF
    from iotnav.techniques.last_position import LastPositionLogic, horizontal_distance_m
    from iotnav.techniques.lowpass3 import Lowpass3
    from iotnav.techniques.mount import DT, MountAligner
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
        "fusion_update_velocity": _time(lambda: fus.update_velocity_ned(np.zeros(3), 0.1), n_calls),
        "load_position": _time(lambda: horizontal_distance_m(45.0, 7.0, 45.001, 7.001), n_calls),
        "mount_add_imu_body": _time(lambda: mnt.add_imu_body(acc, 0.01), n_calls),
        "mount_rotm": _time(lambda: C @ rot_z(0.3).T, n_calls),
    }
    lpc = lp.config

    def worst_push() -> None:  # the push that completes all three levels
        lp.k1, lp.since2 = lpc.n1 - 1, lpc.n2 - 1
        lp.push(acc)

    res["lowpass3_worst_push"] = _time(worst_push, n_calls)
    lsq = MountAligner(PIPELINE_MOUNT)
    lsq.buf[:] = rng.normal(0.0, 1.0, lsq.buf.shape)
    lsq.buf[:, DT] = 1.0
    res["mount_evaluate"] = _time(lambda: lsq._evaluate(0.0, 5.0), n_calls)
    return res
