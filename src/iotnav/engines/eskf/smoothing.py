"""RTS smoothing records of the ``eskf`` engine (package docstring, "RTS smoothing")."""

from __future__ import annotations

import math

import numpy as np
import numpy.typing as npt
from scipy.spatial.transform import Rotation

from iotnav.engines.eskf import models as M
from iotnav.engines.eskf.core import EskfCore
from iotnav.engines.eskf.kernel import _sm_close, _sm_open
from iotnav.engines.eskf.layout import (
    E_SM_COUNT,
    E_SM_N,
    E_SM_ON,
    E_SM_PEND,
    E_SM_T,
    Q_EST_MOUNT,
)
from iotnav.engines.smoother import (
    CORR_ATT,
    CORR_POS,
    CORR_STD,
    CORR_VEL,
    SmoothingLog,
    plane_to_geodetic,
    smoothed_std,
)

FloatArray = npt.NDArray[np.float64]


class EskfSmoothing(EskfCore):
    """Smoothing records and corrections (:class:`~iotnav.engines.smoother.Smoothable`)."""

    #: :meth:`smoothing_corrections` reads only the smoothed variances (``smooth_output`` passes them)
    smoothing_takes_variances = True

    # ------------------------------------------------------------------ smoothing
    @property
    def smoothing_log(self) -> SmoothingLog | None:
        """Records for the RTS smoother (:mod:`iotnav.engines.smoother`); None unless ``smoothing``.

        The records written so far plus, as the last one, the record still open (or, when
        none is, one at the latest covariance propagation, with the transition since the
        previous record), so that the log read after a run covers it to its end. Reading it
        does not change the engine.
        """
        log = self._sm_log
        if log is None:
            return None
        self._drain_smoothing()
        tail = self._smoothing_tail()
        if tail is None:
            return log
        return log.with_tail(*tail[:6])

    def _smoothing_tail(
        self,
    ) -> tuple[float, FloatArray, FloatArray, FloatArray, FloatArray, FloatArray, FloatArray] | None:
        """The open (or implicit last) record: ``t, x-, P-, Phi, x+, P+`` and its attitude map."""
        st, n = self.st, self.n
        if st[E_SM_ON] == 0.0:
            return None
        buf, Phi, _work, _rec, att = self.sm
        if st[E_SM_PEND] != 0.0:
            return (
                float(st[E_SM_T]),
                buf[0, :n].copy(),
                buf[0, n:].reshape(n, n).copy(),
                Phi.reshape(n, n).copy(),
                buf[1, :n].copy(),
                self.P.copy(),
                att[int(st[E_SM_N])].copy(),
            )
        if st[E_SM_COUNT] == 0.0:
            return None
        # propagations since the last record and no record open: P is the prior (and, with no
        # update, the posterior) at the latest propagation
        t_last = self._sm_log.t[-1] if self._sm_log is not None and len(self._sm_log) else -math.inf
        t = max(float(self.t_state - self.acc[M.ACC_T]), t_last)
        mount = self.nom.C_nb @ self.nom.C_vb.T if self.mount_ok else np.zeros((3, 3))
        z = np.zeros(n)
        return t, z, self.P.copy(), Phi.reshape(n, n).copy(), z, self.P.copy(), mount.reshape(-1)

    def _start_smoothing(self) -> None:
        """Position and heading known: the output is the nominal state from now on; first record."""
        if self._sm_log is None or self.st[E_SM_ON] != 0.0:
            return
        self.st[E_SM_ON] = 1.0
        self.st[E_SM_COUNT] = 0.0
        self.sm[1][:] = np.eye(self.n).reshape(-1)
        _sm_open(self.st, self.nom.arrays(), self.P, self.sm)

    def _smoothing_reset(self, T: FloatArray) -> None:
        """Record a covariance reset ``P <- T P T^T + Q_r`` (call before ``P`` is changed).

        The open record is written (its posterior is ``P`` before the reset) and ``T`` joins the
        transition to the next record, whose prior is then ``... T P+ T^T + Q_r ...``: the
        reset is one more linear step of the smoothing model (a re-initialised state has a
        zero row in ``T``, so nothing is carried back to it across the reset).
        """
        if self.st[E_SM_ON] == 0.0:
            return
        if self.st[E_SM_PEND] != 0.0:
            _sm_close(self.st, self.P, self.sm)
        Phi = self.sm[1].reshape(self.n, self.n)
        Phi[:] = T @ Phi
        self._drain_smoothing()

    def _smoothing_unwidened_prior(self, P_u: FloatArray, acc_u: FloatArray) -> None:
        """Open the forced fix's record with the prior the filter had *without* the gate reset.

        ``P_u`` and ``acc_u`` are the covariance and the covariance accumulator just before the
        position covariance was widened; ``P_u`` is propagated over the same interval (the same
        compiled arithmetic, and the fixed mount zeroed likewise) to the fix time, where the
        record is opened (if no record is open there yet) with that prior. The widening and
        the forced update then together form the record's update: its ``dx`` and ``P+`` are the
        filter's, and the transition to the record carries no reset.
        """
        n = self.n
        P = P_u.copy()
        M.propagate_covariance_phi(P, acc_u, self.noise, np.empty((n, n)))
        if self.prm[Q_EST_MOUNT] == 0.0:
            P[M.MNT, :] = 0.0
            P[:, M.MNT] = 0.0
        if self.st[E_SM_PEND] == 0.0:
            _sm_open(self.st, self.nom.arrays(), self.P, self.sm)
        self.sm[0][0, n:] = P.reshape(-1)

    def _reinit_rows(self, rows: slice | int) -> FloatArray:
        """``T`` of a reset that re-initialises the error states ``rows`` (their rows zeroed)."""
        T = np.eye(self.n)
        T[rows, :] = 0.0
        return T

    def _attitude_maps(self, K: int) -> FloatArray:
        """``(K, 3, 3)`` output-attitude maps of the first ``K`` records of :attr:`smoothing_log`."""
        parts = list(self._sm_att)
        have = sum(p.shape[0] for p in parts)
        if K > have:
            tail = self._smoothing_tail()
            if tail is not None:
                parts.append(tail[6].reshape(1, 9))
        A = np.concatenate(parts, axis=0) if parts else np.zeros((0, 9))
        if A.shape[0] < K:
            raise ValueError(f"{K} records asked, {A.shape[0]} recorded")
        return A[:K].reshape(K, 3, 3)

    def smoothing_corrections(
        self, x_filt: FloatArray, x_smooth: FloatArray, P_smooth: FloatArray
    ) -> FloatArray:
        """Corrections at the record points (:mod:`iotnav.engines.smoother`): error-state RTS.

        The smoothed error ``xs`` and the filter's ``x`` (``dx`` after the updates, 0 before)
        are both about the record's prior nominal state, so the correction of what was output
        is their difference.

        Parameters
        ----------
        x_filt, x_smooth : numpy.ndarray
            ``(K, n)`` filtered and smoothed error states of the records of :attr:`smoothing_log`.
        P_smooth : numpy.ndarray
            ``(K, n, n)`` smoothed covariances, or their diagonals ``(K, n)``.

        Returns
        -------
        numpy.ndarray
            ``(K, 11)``: position ``xs - x`` (NED, m), velocity (NED, m/s), the rotation
            ``dtheta`` in ``n`` (rad) with ``C_s = exp([dtheta x]) C_out``, smoothed ``std_north``,
            ``std_east`` (m). The output attitude is ``C_out = C_nb C_vb^T`` once the mount is
            known, whose error is ``dth - C_out dmu`` (``C_nb`` error ``dth`` in ``n``, mount error
            ``dmu`` in ``v``; :mod:`iotnav.engines.eskf.models`), else ``C_nb`` (error ``dth``).
        """
        K = x_filt.shape[0]
        out = np.zeros((K, 11))
        out[:, CORR_POS] = x_smooth[:, M.POS] - x_filt[:, M.POS]
        out[:, CORR_VEL] = x_smooth[:, M.VEL] - x_filt[:, M.VEL]
        A = self._attitude_maps(K)
        th_s = x_smooth[:, M.ATT] - np.einsum("kij,kj->ki", A, x_smooth[:, M.MNT])
        th_f = x_filt[:, M.ATT] - np.einsum("kij,kj->ki", A, x_filt[:, M.MNT])
        if K:
            out[:, CORR_ATT] = (Rotation.from_rotvec(th_s) * Rotation.from_rotvec(th_f).inv()).as_rotvec()
        out[:, CORR_STD] = smoothed_std(P_smooth, M.POS.start, M.POS.start + 1)
        return out

    def ned_to_geodetic(self, r_n: FloatArray) -> tuple[FloatArray, FloatArray, FloatArray]:
        """NED ``(N, 3)`` (m) about the origin to lat, lon (deg), height (m)."""
        return plane_to_geodetic(self.frame, r_n)
