"""Fixed-interval Rauch-Tung-Striebel smoother over any engine's run (``iotnav run --smooth``).

Equations (Rauch, Tung and Striebel 1965; Bar-Shalom, Li and Kirubarajan 2001, sec. 8.6),
over the *record points* ``k = 0..K-1`` of a forward run::

    G_k   = P+_k Phi_{k+1}^T (P-_{k+1})^-1
    xs_k  = x+_k + G_k (xs_{k+1} - x-_{k+1}),   xs_{K-1} = x+_{K-1}
    Ps_k  = P+_k + G_k (Ps_{k+1} - P-_{k+1}) G_k^T

What an engine must expose to be smoothable (:class:`Smoothable`)
-----------------------------------------------------------------
1. ``smoothing_log``: a :class:`SmoothingLog` filled during the forward run with, per record
   point, the time, the prior ``x-_k, P-_k`` (before the updates at that time), the posterior
   ``x+_k, P+_k`` and the transition ``Phi_k`` from the previous record point. Record points are
   every measurement epoch (GNSS, magnetometer; the updates of one time form one record) and
   every ``record_every``-th output row. Between two record points there are only predictions,
   so ``Phi_k`` is the product of the per-step (linearised) transitions and ``P-_k`` the
   covariance the filter propagated -- RTS on the record points is then exact, with memory
   ``O(K n^2)`` instead of ``O(N n^2)`` for ``N`` IMU steps (``record_every = 1`` records every
   row).
2. ``smoothing_corrections(x_filt, x_smooth, P_smooth)``: the correction to apply to an output
   row at each record point, as ``(K, 11)`` columns ``dN, dE, dD`` (m), ``dvN, dvE, dvD`` (m/s),
   ``dtheta_n`` (rad, rotation vector with ``C_s = exp([dtheta x]) C_f``), smoothed
   ``std_north, std_east`` (m). ``P_smooth`` is ``(K, n, n)``, or only the diagonals
   ``(K, n)`` for an engine with the class attribute ``smoothing_takes_variances = True``
   (eskf, pipeline, anchor), which saves the ``O(K n^2)`` array.
3. ``ned_to_geodetic(r_n)``: the engine's NED origin, vectorised, to rewrite ``lat/lon/height``.

Rows between record points ``k`` and ``k+1`` receive corrections interpolated linearly in time
from ``xs_k - x+_k`` to ``xs_{k+1} - x-_{k+1}`` (a row is a prediction from ``x+_k`` and
reaches ``x-_{k+1}``, the prior before the next updates): exact at the record points; between
them the forward run is a pure prediction, whose RTS correction varies smoothly. The smoothed rows keep every other column of the forward output.

Time-correlated acceleration error (:class:`AccelErrorModel`)
-------------------------------------------------------------
RTS is exact for the engine's *model*, and inside a GNSS outage the shape of the correction is
the model's: with white acceleration noise (the anchor engine's ``q_a``) the smoothed
acceleration correction over an outage ``[0, T]`` is linear in time for a constant noise
density (the minimum-energy white noise given the exit mismatch ``dp_T, dv_T``), and its mean ``dv_T / T`` and moment
``dp_T = int (T - u) w(u) du`` force it to change sign when the error built up late in the
outage (``dp_T / dv_T`` well below the white-noise value ``T / 2``): the correction then pushes
the first half of the outage the wrong way. That is what a vehicle's attitude-induced error
does: a tilt or heading error ``dtheta`` turns the specific force into an acceleration error
``g dtheta + |f_h| dpsi`` that stays or grows for tens of seconds (in a turn the tilt filter
leans towards the centripetal acceleration), i.e. a time-correlated acceleration error, not
white noise. Engines whose state is a kinematic ``[p v]`` with the acceleration as a control
input (``anchor``) can therefore be smoothed with a random-walk acceleration error ``b`` in
``n`` added to the state, ``p'' = u + b + w``, ``b' = w_b`` (``E w_b w_b^T = s^2 I``, ``s`` in
m/s^2/sqrt(s)): :func:`augment_acceleration_error` re-runs the filter on the record points with
the state ``[x b]`` -- the recorded ``x-_{k+1} - Phi_{k+1} x+_k`` is the control input,
``P-_{k+1} - Phi_{k+1} P+_k Phi_{k+1}^T`` the engine's process noise and
``(P+_k)^-1 - (P-_k)^-1``, ``(P+_k)^-1 x+_k - (P-_k)^-1 x-_k`` the information of the updates at
record ``k`` (exact for linear updates) -- and RTS runs on that log. The corrections are still
taken against the engine's own records, so they apply to its output rows. Pass the model to
:func:`smooth_output` (``accel_error``) or expose it as the engine attribute
``smoothing_accel_error``. Cost: a second log of ``n + 3`` states and a Python loop over the
records (about 1 s for 600 s of 100 Hz data recorded every 10 rows).

Memory
------
:class:`SmoothingLog` stores the records exactly but compactly (covariance triangles, nonzero
patterns) and writes those past ``memory_bytes`` to an anonymous temporary file; the backward
pass is compiled and reads one chunk of records at a time
(:mod:`iotnav.engines.smoother_records`); :func:`smooth_output` corrects the output rows in
blocks. An eskf record (30 states, one every 0.1 s) takes about 8.8 KB instead of 21.8 KB,
in RAM up to 32 MB and on disk beyond; ``benchmarks/results/smoother_memory.md`` has the
measured peak memory and time per hour of data.

Plugging in other engines
-------------------------
Engines whose filter runs in a compiled kernel write record points into a buffer with
:func:`write_record` (layout :func:`record_size`) and move them to the log between kernel calls
with :func:`drain_records`; :func:`kinematic_corrections` and :func:`plane_to_geodetic` are the
two protocol methods of a KF with an NED ``[p v ...]`` state on a tangent plane
(:class:`KinematicRecords` bundles them for ``pipeline`` and ``anchor``).

* ``anchor`` (linear KF, state ``[p v]``): corrections are ``xs - x+`` directly; the state fits
  :class:`AccelErrorModel` (``POS``, ``VEL`` of :mod:`iotnav.engines.anchor`).
* ``pipeline`` (the fusion filter of block 6, linear KF, state ``[p v b_a]``, ``b_a`` in the
  sensor frame): corrections ``xs - x+`` of ``p`` and ``v``; the held steps while static are
  not kinematic, so :class:`AccelErrorModel` needs ``static_hold`` off
  (:mod:`iotnav.engines.pipeline`).
* ``qekf`` (total-state EKF, 22 states): ``Phi`` is the EKF Jacobian product; the position and
  velocity corrections are differences, the attitude correction the rotation between the
  normalised smoothed and filtered quaternions.
* ``eskf`` (error-state EKF): error-state RTS on the nominal trajectory. A record's prior is
  ``x-_k = 0`` (the error state is zero after every reset), its posterior ``x+_k = dx_k`` the
  summed corrections of the updates at that time, ``Phi_k`` the product of the error-state
  transitions, covariance resets included as transforms; the backward pass gives the smoothed
  error about the prior nominal, so ``xs_k - x_k`` is again the correction of what was output
  (:mod:`iotnav.engines.eskf`, "RTS smoothing").
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Literal, Protocol

import numpy as np
import numpy.typing as npt
import pandas as pd
from scipy.linalg import LinAlgError, cho_factor, cho_solve
from scipy.spatial.transform import Rotation

from iotnav.engines import smoother_records as REC
from iotnav.engines.base import Engine, TangentPlane, run_batch
from iotnav.engines.smoother_records import SmoothingLog, drain_records, record_size, write_record
from iotnav.io.log import Log
from iotnav.kalman import symmetrize, update

FloatArray = npt.NDArray[np.float64]

__all__ = [
    "AccelErrorModel",
    "KinematicRecords",
    "Smoothable",
    "SmoothingLog",
    "augment_acceleration_error",
    "drain_records",
    "kinematic_corrections",
    "plane_to_geodetic",
    "record_size",
    "rts_backward",
    "run_smoothed",
    "smooth_output",
    "write_record",
]

#: Columns of :meth:`Smoothable.smoothing_corrections`.
CORR_POS = slice(0, 3)
CORR_VEL = slice(3, 6)
CORR_ATT = slice(6, 9)
CORR_STD = slice(9, 11)


def kinematic_corrections(
    x_filt: FloatArray, x_smooth: FloatArray, P_smooth: FloatArray, pos: slice, vel: slice
) -> FloatArray:
    """:meth:`Smoothable.smoothing_corrections` of a linear KF whose state holds ``r_n, v_n``.

    Parameters
    ----------
    x_filt, x_smooth : numpy.ndarray
        Filtered and smoothed states ``(K, n)``.
    P_smooth : numpy.ndarray
        Smoothed covariances ``(K, n, n)``.
    pos, vel : slice
        NED position (m) and velocity (m/s) blocks of the state; ``pos`` starts with north, east.

    Returns
    -------
    numpy.ndarray
        ``(K, 11)``: ``xs - x`` for position and velocity, no attitude correction, smoothed
        ``std_north, std_east`` (m).
    """
    out = np.zeros((x_filt.shape[0], 11))
    out[:, CORR_POS] = x_smooth[:, pos] - x_filt[:, pos]
    out[:, CORR_VEL] = x_smooth[:, vel] - x_filt[:, vel]
    i_n = pos.start or 0
    out[:, CORR_STD] = smoothed_std(P_smooth, i_n, i_n + 1)
    return out


def smoothed_std(P_smooth: FloatArray, i_n: int, i_e: int) -> FloatArray:
    """``(K, 2)`` standard deviations of states ``i_n``, ``i_e`` from covariances ``(K, n, n)`` or variances ``(K, n)``."""
    P = np.asarray(P_smooth)
    if P.ndim == 3:
        v = np.stack([P[:, i_n, i_n], P[:, i_e, i_e]], axis=1)
    else:
        v = np.stack([P[:, i_n], P[:, i_e]], axis=1)
    return np.asarray(np.sqrt(np.maximum(v, 0.0)), dtype=np.float64)


def plane_to_geodetic(
    frame: TangentPlane | None, r_n: FloatArray
) -> tuple[FloatArray, FloatArray, FloatArray]:
    """:meth:`Smoothable.ned_to_geodetic` of an engine on a :class:`~iotnav.engines.tangent_plane.TangentPlane`.

    NED ``(N, 3)`` (m) about the plane's origin to lat, lon (deg), height (m).

    Raises
    ------
    ValueError
        Without a plane (no origin yet).
    """
    if frame is None:
        raise ValueError("no origin yet")
    return frame.from_ned_rows(r_n)


class KinematicRecords:
    """The smoothing side of an engine whose compiled kernel records a linear ``[r_n v_n ...]`` KF.

    Mixin of :class:`~iotnav.engines.pipeline.Pipeline` and
    :class:`~iotnav.engines.anchor.AnchorEngine`: :meth:`smoothing_corrections`
    (:func:`kinematic_corrections`), :meth:`ned_to_geodetic` (:func:`plane_to_geodetic`) and
    ``_drain_records`` (:func:`drain_records`). The engine sets the class attributes
    ``_kin_pos``, ``_kin_vel`` (state slices), ``_kin_states`` (state size) and ``_kin_n_rec``
    (index of the record count in its ``_st`` array), and has ``frame``, ``_st``, ``_rec`` and
    ``smoothing_log``.
    """

    #: :meth:`smoothing_corrections` reads only the smoothed variances (``smooth_output`` passes them)
    smoothing_takes_variances = True
    _kin_pos: slice
    _kin_vel: slice
    _kin_states: int
    _kin_n_rec: int
    frame: TangentPlane | None
    smoothing_log: SmoothingLog | None
    _st: FloatArray
    _rec: FloatArray

    def smoothing_corrections(
        self, x_filt: FloatArray, x_smooth: FloatArray, P_smooth: FloatArray
    ) -> FloatArray:
        """Corrections ``xs - x`` of position and velocity at the record points (module docstring)."""
        return kinematic_corrections(x_filt, x_smooth, P_smooth, self._kin_pos, self._kin_vel)

    def ned_to_geodetic(self, r_n: FloatArray) -> tuple[FloatArray, FloatArray, FloatArray]:
        """NED ``(N, 3)`` (m) about the origin to lat, lon (deg), height (m)."""
        return plane_to_geodetic(self.frame, r_n)

    def _drain_records(self) -> None:
        """Move the record points the kernels wrote into :attr:`smoothing_log`."""
        n = int(self._st[self._kin_n_rec])
        self._st[self._kin_n_rec] = 0.0
        drain_records(self.smoothing_log, self._rec, n, self._kin_states)


@dataclass(frozen=True)
class AccelErrorModel:
    """Random-walk acceleration error added to a kinematic ``[p v]`` state for smoothing.

    See the module docstring (time-correlated acceleration error).

    Attributes
    ----------
    pos, vel : slice
        Position (m) and velocity (m/s) blocks of the engine state, three components each in
        the same frame (``n``, NED); the recorded transitions must be kinematic over each
        record interval ``dt`` (``Phi[pos, vel] = dt I``, ``Phi[vel, vel] = I``).
    rw_mps2_sqrt_s : float
        ``s``: random-walk density of the acceleration error ``b`` per axis of ``n``,
        m/s^2/sqrt(s) (``b`` changes by ``s sqrt(tau)`` rms over ``tau`` seconds).
    init_std_mps2 : float
        Standard deviation of ``b`` per axis at the first record point, m/s^2.
    """

    pos: slice
    vel: slice
    rw_mps2_sqrt_s: float
    init_std_mps2: float = 1.0

    def __post_init__(self) -> None:
        if not (self.rw_mps2_sqrt_s >= 0.0 and self.init_std_mps2 > 0.0):
            raise ValueError("rw_mps2_sqrt_s must be >= 0 and init_std_mps2 > 0")


class Smoothable(Engine, Protocol):
    """An engine the RTS smoother can run over (see the module docstring)."""

    smoothing_log: SmoothingLog | None

    def smoothing_corrections(
        self, x_filt: FloatArray, x_smooth: FloatArray, P_smooth: FloatArray
    ) -> FloatArray:
        """``(K, 11)`` corrections at the record points (module docstring, item 2)."""
        ...

    def ned_to_geodetic(self, r_n: FloatArray) -> tuple[FloatArray, FloatArray, FloatArray]:
        """NED ``(N, 3)`` m about the engine's origin to lat, lon (deg) and height (m)."""
        ...


def rts_backward(log: SmoothingLog, *, full: bool = True) -> tuple[FloatArray, FloatArray]:
    """Backward RTS pass over a :class:`SmoothingLog`, compiled, one stored chunk at a time.

    Equivalent to :func:`iotnav.kalman.rts_smooth` on the stacked arrays (tested), without
    stacking the inputs: memory is one decoded chunk plus the results
    (:func:`~iotnav.engines.smoother_records.rts_backward_records`).

    Parameters
    ----------
    log : SmoothingLog
        The records.
    full : bool
        Return the smoothed covariances; else only their diagonals (``O(K n)`` memory instead
        of ``O(K n^2)``).

    Returns
    -------
    x_s : numpy.ndarray
        Smoothed states ``(K, n)``.
    P_s : numpy.ndarray
        Smoothed covariances ``(K, n, n)`` (``full``) or their diagonals ``(K, n)``.
    """
    K = len(log)
    if K == 0:
        return np.zeros((0, 0)), (np.zeros((0, 0, 0)) if full else np.zeros((0, 0)))
    n = log.n_states if log.n_states else np.asarray(log.x_post[0]).size
    return REC.rts_backward_records(log.chunks(), n, K, full)


def _update_information(log: SmoothingLog, k: int) -> tuple[FloatArray, FloatArray] | None:
    """Information ``(Y, y)`` of the measurement updates at record ``k``; None without update.

    ``Y = (P+)^-1 - (P-)^-1 = H^T R^-1 H`` and ``y = (P+)^-1 x+ - (P-)^-1 x- = H^T R^-1 z``
    for linear updates (any number, applied in sequence) of the recorded state.
    """
    xm, Pm, xp, Pp = log.x_prior[k], log.P_prior[k], log.x_post[k], log.P_post[k]
    if np.array_equal(Pm, Pp) and np.array_equal(xm, xp):
        return None
    Ip, Im = _inverse(Pp), _inverse(Pm)
    return symmetrize(Ip - Im), Ip @ xp - Im @ xm


def _inverse(P: FloatArray) -> FloatArray:
    """Inverse of a covariance (Cholesky; pseudo-inverse when not positive definite)."""
    try:
        return cho_solve(
            cho_factor(P, lower=True, check_finite=False), np.eye(P.shape[0]), check_finite=False
        )
    except LinAlgError:
        return np.asarray(np.linalg.pinv(P, hermitian=True), dtype=np.float64)


def augment_acceleration_error(log: SmoothingLog, model: AccelErrorModel) -> SmoothingLog:
    """Re-run the recorded filter with a random-walk acceleration error ``b`` in the state.

    Parameters
    ----------
    log : SmoothingLog
        Records of a kinematic ``[p v]`` engine (``n`` states; ``model.pos``, ``model.vel``).
    model : AccelErrorModel
        The acceleration error.

    Returns
    -------
    SmoothingLog
        Records of the filter with state ``[x b]`` (``n + 3``; ``b`` in m/s^2, frame of
        ``model.pos``): same times, control inputs and process noise as ``log`` plus those of
        ``b``, and the same measurement information (module docstring). Its first ``n``
        components estimate the engine state.

    Raises
    ------
    ValueError
        When a recorded transition is not kinematic over its record interval.
    """
    K = len(log)
    out = SmoothingLog(log.record_every)
    if K == 0:
        return out
    n = log.x_post[0].size
    na = n + 3
    ip, iv, ib = model.pos, model.vel, slice(n, na)
    s2 = model.rw_mps2_sqrt_s**2
    I3 = np.eye(3)
    x = np.zeros(na)
    P = np.zeros((na, na))
    x[:n] = log.x_prior[0]
    P[:n, :n] = log.P_prior[0]
    P[ib, ib] = model.init_std_mps2**2 * I3
    for k in range(K):
        Phi_a = np.eye(na)
        if k > 0:
            dt = log.t[k] - log.t[k - 1]
            Phi = log.Phi[k]
            tol = 1e-6 * (1.0 + dt)
            if not (
                np.allclose(Phi[ip, iv], dt * I3, rtol=0.0, atol=tol)
                and np.allclose(Phi[iv, iv], I3, rtol=0.0, atol=tol)
            ):
                raise ValueError(f"record {k}: the transition is not kinematic over {dt} s")
            u = log.x_prior[k] - Phi @ log.x_post[k - 1]  # control input (IMU acceleration)
            Q = log.P_prior[k] - Phi @ log.P_post[k - 1] @ Phi.T  # the engine's process noise
            Phi_a[:n, :n] = Phi
            Phi_a[ip, ib] = 0.5 * dt * dt * I3
            Phi_a[iv, ib] = dt * I3
            Qa = np.zeros((na, na))
            Qa[:n, :n] = Q
            # random walk b integrated twice over dt (per axis, s^2 times these)
            for r, c, v in (
                (ip, ip, dt**5 / 20.0),
                (ip, iv, dt**4 / 8.0),
                (ip, ib, dt**3 / 6.0),
                (iv, iv, dt**3 / 3.0),
                (iv, ib, dt**2 / 2.0),
                (ib, ib, dt),
            ):
                Qa[r, c] += s2 * v * I3
                if r != c:
                    Qa[c, r] += s2 * v * I3
            x = Phi_a @ x
            x[:n] += u
            P = symmetrize(Phi_a @ P @ Phi_a.T + Qa)
        x_prior, P_prior = x.copy(), P.copy()
        info = _update_information(log, k)
        if info is not None:
            # the information as independent scalar measurements: Y = V diag(lam) V^T
            lam, V = np.linalg.eigh(info[0])
            lam_max = max(float(lam.max()), 0.0)
            keep = lam > 1e-12 * lam_max
            scale = float(np.abs(lam).max())
            if float(lam.min()) < -1e-9 * scale:
                out.dropped_information.append((float(log.t[k]), float(lam.min()) / scale))
            if keep.any():
                H = np.zeros((int(keep.sum()), na))
                H[:, :n] = V[:, keep].T
                z = (V[:, keep].T @ info[1]) / lam[keep]
                res = update(x, P, z, H, np.diag(1.0 / lam[keep]))
                x, P = res.x, res.P
        out.record(log.t[k], x_prior, P_prior, Phi_a, x, P)
    return out


def _interp_corrections(
    t_rec: FloatArray, c_post: FloatArray, c_prior: FloatArray, t: FloatArray
) -> FloatArray:
    """Corrections at times ``t``: from ``c_post[k]`` at ``t_rec[k]`` to ``c_prior[k+1]`` just before ``t_rec[k+1]``.

    A row between two record points is a prediction from the posterior at ``t_rec[k]``; at
    ``t_rec[k+1]`` (before that record's updates) it equals the prior there, whose correction
    is ``xs - x-``. Rows at or after the last record use the last posterior correction.
    """
    k = np.searchsorted(t_rec, t, side="right") - 1
    k = np.clip(k, 0, t_rec.size - 1)
    last = k >= t_rec.size - 1
    k1 = np.minimum(k + 1, t_rec.size - 1)
    span = t_rec[k1] - t_rec[k]
    w = np.where(span > 0, (t - t_rec[k]) / np.where(span > 0, span, 1.0), 0.0)
    w = np.where(last, 0.0, np.clip(w, 0.0, 1.0))[:, None]
    return (1.0 - w) * c_post[k] + w * c_prior[k1]


def smooth_output(
    engine: Smoothable,
    forward: pd.DataFrame,
    accel_error: AccelErrorModel | Literal["engine"] | None = "engine",
) -> pd.DataFrame:
    """Apply the RTS smoother of a finished forward run to its output rows.

    Parameters
    ----------
    engine : Smoothable
        The engine after the forward run (its ``smoothing_log`` filled).
    forward : pandas.DataFrame
        The forward output (:func:`iotnav.engines.base.run_batch`).
    accel_error : AccelErrorModel or "engine" or None
        Smooth with this random-walk acceleration error in the state
        (:func:`augment_acceleration_error`); None: RTS on the engine's own model; ``"engine"``
        (default): the engine's ``smoothing_accel_error`` attribute when it has one, else None.

    Returns
    -------
    pandas.DataFrame
        Same rows and columns; position, velocity, attitude, ``std_north``/``std_east`` and
        geodetic coordinates smoothed where the filter was running (rows before the first
        record point are left unchanged). ``attrs["smoothed"] = True``.
    """
    log = engine.smoothing_log
    if log is None:
        raise ValueError("the engine was run without a smoothing log (smoothing disabled in its config)")
    out = forward.copy()
    out.attrs = dict(forward.attrs)
    out.attrs["smoothed"] = True
    if len(log) < 2 or len(out) == 0:
        return out
    model = getattr(engine, "smoothing_accel_error", None) if accel_error == "engine" else accel_error
    if not (model is None or isinstance(model, AccelErrorModel)):
        raise TypeError(f"accel_error: expected an AccelErrorModel, 'engine' or None, got {model!r}")
    run_log = log if model is None else augment_acceleration_error(log, model)
    if run_log.dropped_information:
        dropped = run_log.dropped_information
        t_first = dropped[0][0]
        event = {
            "type": "smoothing_information_dropped",
            "t": t_first,
            "count": len(dropped),
            "worst_ratio": min(r for _, r in dropped),
        }
        events = list(forward.attrs.get("events", []))
        at = next((i for i, e in enumerate(events) if float(e.get("t", -math.inf)) > t_first), len(events))
        out.attrs["events"] = [*events[:at], event, *events[at:]]
    # engines whose corrections read only the smoothed variances get the diagonals: O(K n)
    diagonal = bool(getattr(engine, "smoothing_takes_variances", False))
    x_s, P_s = rts_backward(run_log, full=not diagonal)
    n = log.n_states
    x_s, P_s = x_s[:, :n], (P_s[:, :n] if diagonal else P_s[:, :n, :n])
    c_post = engine.smoothing_corrections(np.asarray(log.x_post), x_s, P_s)
    c_prior = engine.smoothing_corrections(np.asarray(log.x_prior), x_s, P_s)
    t_rec = np.asarray(log.t)
    t = out["t"].to_numpy(float)
    sel = (t >= t_rec[0]) & np.isfinite(out["north"].to_numpy(float))
    if not sel.any():
        return out
    rows = np.flatnonzero(sel)
    # the rows in blocks (bounded temporaries); the attitude is rewritten wherever any
    # correction of it is nonzero (as one pass over all rows would decide)
    blocks = [rows[i : i + _ROW_BLOCK] for i in range(0, rows.size, _ROW_BLOCK)]
    rotate = any(
        np.any(_interp_corrections(t_rec, c_post[:, CORR_ATT], c_prior[:, CORR_ATT], t[b]) != 0.0)
        for b in blocks
    )
    names = ["north", "east", "down", "vn", "ve", "vd", "std_north", "std_east", "lat", "lon", "height"]
    if rotate:
        names += ["yaw", "pitch", "roll"]
    attrs, out.attrs = out.attrs, {}  # pandas deep-copies attrs at every column access
    col = {name: out[name].to_numpy(float, copy=True) for name in names}
    for b in blocks:
        c = _interp_corrections(t_rec, c_post, c_prior, t[b])
        ned = np.stack([col["north"][b], col["east"][b], col["down"][b]], axis=1) + c[:, CORR_POS]
        vel = np.stack([col["vn"][b], col["ve"][b], col["vd"][b]], axis=1) + c[:, CORR_VEL]
        for j, name in enumerate(("north", "east", "down")):
            col[name][b] = ned[:, j]
        for j, name in enumerate(("vn", "ve", "vd")):
            col[name][b] = vel[:, j]
        col["std_north"][b] = c[:, CORR_STD.start]
        col["std_east"][b] = c[:, CORR_STD.start + 1]
        lat, lon, h = engine.ned_to_geodetic(ned)
        col["lat"][b], col["lon"][b], col["height"][b] = lat, lon, h
        if rotate:
            eul = np.stack([col["yaw"][b], col["pitch"][b], col["roll"][b]], axis=1)
            ok = np.all(np.isfinite(eul), axis=1)
            if ok.any():
                C_s = Rotation.from_rotvec(c[ok][:, CORR_ATT]) * Rotation.from_euler("ZYX", eul[ok])
                ypr = C_s.as_euler("ZYX")
                col["yaw"][b[ok]], col["pitch"][b[ok]], col["roll"][b[ok]] = ypr[:, 0], ypr[:, 1], ypr[:, 2]
    for name in names:
        out[name] = col[name]
    out.attrs = attrs
    return out


#: Output rows corrected at a time by :func:`smooth_output` (bounds its temporaries).
_ROW_BLOCK = 1 << 16


def run_smoothed(
    engine: Smoothable, log: Log, accel_error: AccelErrorModel | Literal["engine"] | None = "engine"
) -> tuple[pd.DataFrame, pd.DataFrame]:
    """Forward run with :func:`~iotnav.engines.base.run_batch` (the streaming ``step()``), then RTS.

    ``accel_error`` is passed to :func:`smooth_output`.

    Returns
    -------
    forward, smoothed : pandas.DataFrame
        The forward-filter output and its smoothed version.
    """
    fwd = run_batch(engine, log)
    return fwd, smooth_output(engine, fwd, accel_error)
