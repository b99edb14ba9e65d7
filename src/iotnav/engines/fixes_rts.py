"""RTS pass of the ``fixes`` engine over its smoothing records, and the state between records.

The records are those :func:`iotnav.engines.fixes_kernel.fixes_kernel` writes (layout ``REC_*``
there); :class:`iotnav.engines.fixes.FixesEngine` calls :func:`retract_records`,
:func:`rts_records` and :func:`interpolate_records` for its smoothed and resampled outputs.
The axis blocks are the kernel's ``kf`` layout (``[p, v, P_pp, P_pv, P_vv]`` per axis; m, m/s,
m^2, m^2/s, m^2/s^2).
"""

from __future__ import annotations

import math

import numba
import numpy as np
import numpy.typing as npt

from iotnav.engines.fixes_kernel import (
    AX_D,
    AX_E,
    AX_N,
    K_BOOT,
    K_FILTER,
    K_ROLLBACK,
    KF_SIZE,
    REC_KIND,
    REC_POST,
    REC_PRIOR,
    REC_QF,
    REC_SNAP_T,
    REC_T,
    predict_axis,
)

FloatArray = npt.NDArray[np.float64]


@numba.njit(cache=True)
def _solve2(a00: float, a01: float, a11: float, b0: float, b1: float) -> tuple[float, float]:
    """Solve the symmetric positive 2 x 2 system ``A x = b`` by its Cholesky factor."""
    l00 = math.sqrt(a00)
    l10 = a01 / l00
    l11 = math.sqrt(max(a11 - l10 * l10, 1e-300))
    w0 = b0 / l00
    w1 = (b1 - l10 * w0) / l11
    x1 = w1 / l11
    x0 = (w0 - l10 * x1) / l00
    return x0, x1


@numba.njit(cache=True)
def rts_gain(
    post: FloatArray, a: int, dt: float, prior_next: FloatArray
) -> tuple[float, float, float, float]:
    """RTS gain ``G = P+_k F^T (P-_{k+1})^-1`` of axis block ``a`` for a step ``dt`` (row-major 2 x 2)."""
    p00, p01, p11 = post[a + 2], post[a + 3], post[a + 4]
    # M = P+ F^T, F = [[1, dt], [0, 1]]: M = [[p00 + dt p01, p01], [p01 + dt p11, p11]]
    m00, m01 = p00 + dt * p01, p01
    m10, m11 = p01 + dt * p11, p11
    q00, q01, q11 = prior_next[a + 2], prior_next[a + 3], prior_next[a + 4]
    # G = M Q^-1: each row g solves Q g^T = m^T (Q symmetric)
    g00, g01 = _solve2(q00, q01, q11, m00, m01)
    g10, g11 = _solve2(q00, q01, q11, m10, m11)
    return g00, g01, g10, g11


@numba.njit(cache=True)
def rts_step(
    post: FloatArray, a: int, dt: float, prior_next: FloatArray, sm_next: FloatArray, out: FloatArray
) -> None:
    """Smoothed axis block ``a`` at ``k`` from its filtered ``post`` and the smoothed ``sm_next`` at ``k+1``.

    ``xs_k = x+_k + G (xs_{k+1} - x-_{k+1})``, ``Ps_k = P+_k + G (Ps_{k+1} - P-_{k+1}) G^T``.
    """
    g00, g01, g10, g11 = rts_gain(post, a, dt, prior_next)
    d0 = sm_next[a] - prior_next[a]
    d1 = sm_next[a + 1] - prior_next[a + 1]
    out[a] = post[a] + g00 * d0 + g01 * d1
    out[a + 1] = post[a + 1] + g10 * d0 + g11 * d1
    e00 = sm_next[a + 2] - prior_next[a + 2]
    e01 = sm_next[a + 3] - prior_next[a + 3]
    e11 = sm_next[a + 4] - prior_next[a + 4]
    # G E G^T
    t00 = g00 * e00 + g01 * e01
    t01 = g00 * e01 + g01 * e11
    t10 = g10 * e00 + g11 * e01
    t11 = g10 * e01 + g11 * e11
    out[a + 2] = post[a + 2] + t00 * g00 + t01 * g01
    out[a + 3] = post[a + 3] + 0.5 * ((t00 * g10 + t01 * g11) + (t10 * g00 + t11 * g01))
    out[a + 4] = post[a + 4] + t10 * g10 + t11 * g11


@numba.njit(cache=True)
def retract_records(rec: FloatArray, n: int, q_h: float, q_v: float) -> None:
    """Rewrite the records a rollback retracted, so that RTS sees them as rejected fixes.

    For each rollback row, the rows from its snapshot's time up to it get, as prior and
    posterior, the snapshot (the prior of the snapshot row) predicted to their time with the
    unraised ``q``, as the kernel predicted it at the rollback; the rollback row then continues
    that chain and becomes a filter row.
    """
    for k in range(n):
        if rec[k, REC_KIND] != K_ROLLBACK:
            continue
        j = k - 1
        while j > 0 and rec[j, REC_T] > rec[k, REC_SNAP_T]:
            j -= 1
        for i in range(KF_SIZE):
            rec[j, REC_POST + i] = rec[j, REC_PRIOR + i]
        for m in range(j + 1, k):
            dt = rec[m, REC_T] - rec[m - 1, REC_T]
            for i in range(KF_SIZE):
                rec[m, REC_PRIOR + i] = rec[m - 1, REC_POST + i]
            x = rec[m, REC_PRIOR : REC_PRIOR + KF_SIZE]
            predict_axis(x, AX_N, dt, q_h)
            predict_axis(x, AX_E, dt, q_h)
            predict_axis(x, AX_D, dt, q_v)
            for i in range(KF_SIZE):
                rec[m, REC_POST + i] = x[i]
            rec[m, REC_QF] = 1.0
            rec[m, REC_KIND] = K_FILTER
        rec[k, REC_QF] = 1.0
        rec[k, REC_KIND] = K_FILTER


@numba.njit(cache=True)
def rts_records(rec: FloatArray, n: int, sm: FloatArray) -> None:
    """RTS over the first ``n`` records (``REC_*`` layout) into ``sm`` (``(n, 15)``, NaN for boot rows).

    A segment (re-initialisation) starts a new backward recursion at its last row.
    """
    for k in range(n - 1, -1, -1):
        kind = rec[k, REC_KIND]
        if kind == K_BOOT:
            sm[k, :] = math.nan
            continue
        post = rec[k, REC_POST : REC_POST + KF_SIZE]
        if k == n - 1 or rec[k + 1, REC_KIND] != K_FILTER:
            sm[k, :] = post  # last row, or the next starts a segment or a rollback
            continue
        dt = rec[k + 1, REC_T] - rec[k, REC_T]
        prior_next = rec[k + 1, REC_PRIOR : REC_PRIOR + KF_SIZE]
        for a in (AX_N, AX_E, AX_D):
            rts_step(post, a, dt, prior_next, sm[k + 1], sm[k])


@numba.njit(cache=True)
def interpolate_records(
    rec: FloatArray,
    sm: FloatArray,
    n: int,
    times: FloatArray,
    q_h: float,
    q_v: float,
    smoothed: bool,
    out: FloatArray,
) -> None:
    """State and covariance at ``times`` (sorted) between records, into ``out`` (``(m, 15)``; NaN outside).

    Between filter records ``k`` and ``k+1`` (same segment) the state at ``tau`` is the
    prediction from ``x+_k`` over ``tau - t_k``; smoothed, that prediction is a record point
    without a measurement, and one RTS step from ``xs_{k+1}`` gives it (the prior at ``k+1``
    from ``tau`` equals the recorded one for the constant-velocity model), so the covariance
    grows away from the fixes. At a record time the record itself is used.
    """
    k = 0
    tmp = np.empty(KF_SIZE)
    for i in range(times.size):
        tau = times[i]
        out[i, :] = math.nan
        while k + 1 < n and rec[k + 1, REC_T] <= tau:
            k += 1
        if k >= n or rec[k, REC_T] > tau or rec[k, REC_KIND] == K_BOOT:
            continue
        src = sm[k] if smoothed else rec[k, REC_POST : REC_POST + KF_SIZE]
        if tau == rec[k, REC_T]:
            out[i, :] = src
            continue
        if k + 1 >= n or rec[k + 1, REC_KIND] != K_FILTER:
            continue  # after the last record of a segment: no interpolation across a reset
        for q in range(KF_SIZE):
            tmp[q] = rec[k, REC_POST + q]
        dt1 = tau - rec[k, REC_T]
        qf = rec[k + 1, REC_QF]
        predict_axis(tmp, AX_N, dt1, q_h * qf)
        predict_axis(tmp, AX_E, dt1, q_h * qf)
        predict_axis(tmp, AX_D, dt1, q_v * qf)
        if not smoothed:
            out[i, :] = tmp
            continue
        dt2 = rec[k + 1, REC_T] - tau
        prior_next = rec[k + 1, REC_PRIOR : REC_PRIOR + KF_SIZE]
        res = out[i]
        for a in (AX_N, AX_E, AX_D):
            rts_step(tmp, a, dt2, prior_next, sm[k + 1], res)
