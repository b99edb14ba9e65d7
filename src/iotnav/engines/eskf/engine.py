"""The ``eskf`` engine: streaming ``step()``, the batch IMU block, magnetometer, summary."""

from __future__ import annotations

import math
from typing import Any

import numpy as np
import numpy.typing as npt

from iotnav.engines.base import (
    GnssSample,
    ImuSample,
    MagSample,
    Output,
    OutputBlock,
    Sample,
)
from iotnav.engines.eskf import models as M
from iotnav.engines.eskf.gnss import EskfGnss
from iotnav.engines.eskf.kernel import _imu_kernel
from iotnav.engines.eskf.layout import E_GRAV_RESETS, K_DONE, K_LEVEL
from iotnav.geo import dcm_to_rpy, euler_to_dcm

FloatArray = npt.NDArray[np.float64]

#: ``source`` of the rows that are the last fix moved on at its velocity (before the heading;
#: the same solution and name as :data:`iotnav.engines.integrity.DR_VELOCITY_SOURCE`).
DR_VELOCITY_SOURCE = "dr_velocity"


class EskfEngine(EskfGnss):
    """Streaming ESKF engine (see the package docstring).

    The IMU step is the compiled kernel ``_imu_kernel``: :meth:`imu_block` runs it over a
    block of samples and :meth:`step` over a one-sample block, so batch and streaming execute
    the same code. GNSS and magnetometer samples are handled in Python, with the same compiled
    propagation and measurement update.

    Parameters
    ----------
    config : EskfConfig, optional
        Tunables (MPU-6050 datasheet defaults).
    record_innovations : bool or iterable of str, optional
        Keep the innovation vector and its covariance ``S`` of every attempted update of these
        measurements (names of :data:`MEAS_NAMES` handled in Python: ``gnss_position``,
        ``gnss_velocity``, ``mag_heading``) in :attr:`innovations`; True: the GNSS position and
        velocity (:data:`DEFAULT_RECORDED`). Off by default; when on, it costs one ``H P H^T``
        per recorded update and does not change the estimates.

    Attributes
    ----------
    nom : Nominal
        Nominal state.
    P : numpy.ndarray
        Error-state covariance (layout of :mod:`iotnav.engines.eskf.models`).
    st : numpy.ndarray
        Hot scalar state of the IMU path (``E_*`` layout); flags and times such as
        :attr:`levelled`, :attr:`static`, :attr:`t_state` are views of it.
    events : list of dict
        Static transitions, alignment, mount estimates, rejected updates.
    nis_log : dict of list
        Per measurement name: ``(t, nis, dof, accepted)`` of every attempted update.
    innovations : dict of InnovationLog
        Per recorded measurement name (see ``record_innovations``): time, innovation ``y``,
        ``S`` and acceptance of every attempted update; empty when not recording.
    smoothing_log : SmoothingLog or None
        Records of the RTS smoother when ``config.smoothing`` (package docstring, "RTS
        smoothing"); :meth:`smoothing_corrections` and :meth:`ned_to_geodetic` complete the
        :class:`~iotnav.engines.smoother.Smoothable` interface.
    """

    # ------------------------------------------------------------------ protocol
    @property
    def mount_yaw_rad(self) -> float:
        """Mount yaw (sensor x from vehicle forward, clockwise), rad; NaN while not committed."""
        if not self.mount_ok:
            return math.nan
        C = self.nom.C_vb
        return math.atan2(C[1, 0], C[0, 0])

    @property
    def mount_rpy_rad(self) -> tuple[float, float, float]:
        """Current mounting rotation ``C_vb`` as roll, pitch, yaw, rad; NaN while not committed
        (``unobservable``, :mod:`iotnav.techniques.mount3d`), not the identity it starts from."""
        if not self.mount_ok:
            return (math.nan, math.nan, math.nan)
        return dcm_to_rpy(self.nom.C_vb)

    def summary(self) -> dict[str, Any]:
        """Configuration, final state and statistics (for ``summary.json``)."""
        counts: dict[str, int] = {}
        for e in self.events:
            counts[e["type"]] = counts.get(e["type"], 0) + 1
        nis = {
            k: {
                "count": len(v),
                "accepted": int(sum(1 for r in v if r[3])),
                "mean_nis_per_dof": float(np.mean([r[1] / r[2] for r in v])) if v else math.nan,
            }
            for k, v in self.nis_log.items()
        }
        return {
            "skipped": dict(self.guard.skipped),
            "engine": "eskf",
            "mag_unused": self.mag_unused,
            "mag_reference": self._mag_reference_summary(),
            "config": self.config.to_dict(),
            "n_states": self.n,
            "gnss_resolution": self.resolution.to_dict(),
            "mount_rpy_rad": list(self.mount_rpy_rad),
            "mount_known": self.mount_ok,
            "mount": self.mount3d.report(
                self.nom.C_vb if self.mount_ok else None,
                self.P[M.MNT, M.MNT] if self.mount_ok else None,
                self.config.mount_commit_std_rad,
            ),
            "gyro_bias_rad_s": self.nom.b_g.tolist(),
            "acc_bias_mps2": self.nom.b_a.tolist(),
            "gyro_scale": self.nom.s_g.tolist(),
            "acc_scale": self.nom.s_a.tolist(),
            "origin": None
            if self.frame is None
            else {
                "lat_deg": self.frame.lat0_deg,
                "lon_deg": self.frame.lon0_deg,
                "height_m": self.frame.h0_m,
            },
            "event_counts": counts,
            # the windowed NIS monitor's re-initialisations (package docstring, "Consistency monitor")
            "reinitialisations": counts.get("reinitialised", 0),
            "nis": nis,
            "imu_samples": self.n_imu,
            "gravity_resets": int(self.st[E_GRAV_RESETS]),
        }

    def step(self, sample: Sample) -> Output | None:
        """Process one sample (streaming; batch runs the same code, see :meth:`imu_block`).

        An IMU sample runs the compiled kernel on a one-sample block and returns its row.
        """
        sample = self.guard.admit(sample)
        if sample is None:
            return None
        if isinstance(sample, ImuSample):
            return self._one.run(self.imu_block, sample)
        if isinstance(sample, GnssSample):
            self._gnss(sample)
        elif isinstance(sample, MagSample):
            self._mag(sample)
        if self._sm_log is not None:
            self._drain_smoothing()
        return None

    def imu_block(
        self,
        t: FloatArray,
        acc: tuple[FloatArray, FloatArray, FloatArray],
        gyro: tuple[FloatArray, FloatArray, FloatArray],
        out: OutputBlock,
        i0: int,
        i1: int,
    ) -> None:
        """Process IMU samples ``i0 .. i1-1`` in time order, writing row ``k`` of ``out`` for sample ``k``.

        Parameters
        ----------
        t : numpy.ndarray
            Device times, s.
        acc, gyro : tuple of numpy.ndarray
            Specific force along sensor x, y, z (m/s^2) and angular rate about them (rad/s),
            one 1-D float64 array per axis.
        out : OutputBlock
            Output rows (columns of :data:`iotnav.engines.base.FLOAT_COLUMNS`).
        i0, i1 : int
            Sample range.

        Notes
        -----
        Everything per IMU sample runs in the compiled kernel: strapdown, covariance
        propagation, static detection (block 3), ZUPT/ZARU and NHC updates, block 5's
        accumulation and the output row. The kernel stops for Python only when the levelling
        window completes (once) and when its record buffer (events, NIS log) is full.
        """
        # the code of the ``dr_velocity`` source: registered in ``out`` once a row uses it
        code_dr = out.codes.get(DR_VELOCITY_SOURCE, len(out.names))
        k = i0
        resume = False
        while True:
            k, code = _imu_kernel(
                t,
                acc,
                gyro,
                out.floats,
                out.static,
                out.source,
                k,
                i1,
                resume,
                self.st,
                self.prm,
                self.nom.arrays(),
                self.P,
                self.acc,
                self.noise,
                self.g_n,
                self.static_det.state,
                self.static_det.speeds,
                self.static_det.params,
                self.aligner.imu_sums,
                self.rec,
                self.sm,
                code_dr,
            )
            self._flush()
            if DR_VELOCITY_SOURCE not in out.codes and bool(np.any(out.source[i0:k] == code_dr)):
                out.codes[DR_VELOCITY_SOURCE] = code_dr
                out.names.append(DR_VELOCITY_SOURCE)
            if code == K_DONE:
                return
            resume = code == K_LEVEL
            if resume:
                self._level_finish(float(t[k]))

    # ------------------------------------------------------------------ magnetometer
    def _mag_reference_summary(self) -> dict[str, Any]:
        """The declination used (degrees) and where it came from, for ``summary()``."""
        if self.mag_reference is not None:
            return self.mag_reference
        d = self.mag_declination_rad
        return {
            "declination_deg": None if d is None else math.degrees(d),
            "from": "no fix yet" if d is None else "config",
        }

    def _mag(self, s: MagSample) -> None:
        c = self.config
        if not c.use_mag or not self.levelled:
            return
        if not self.mag_usable:
            if self.mag_unused == 0:
                self.events.append({"type": "mag_unused", "t": s.t, "reason": "uncalibrated"})
            self.mag_unused += 1
            return
        decl = self.mag_declination_rad
        if decl is None:
            self.guard.skip("mag_before_declination", s.t)
            return
        m_b = self.mag_Winv @ (np.asarray(s.mag_b_ut, float) - self.mag_h)
        self._integrate_to(s.t)
        if not self.heading_ok:
            r, p, _ = dcm_to_rpy(self.nom.C_nb)
            C_tilt = euler_to_dcm(r, p, 0.0)
            m = C_tilt @ m_b
            yaw = decl - math.atan2(m[1], m[0])
            self._set_heading(s.t, yaw, c.mag_heading_noise_rad, "magnetometer")
            self.t_mag = s.t
            return
        if s.t - self.t_mag >= c.mag_interval_s:
            self.t_mag = s.t
            self._apply(s.t, M.mag_heading(self.nom, m_b, decl, c.mag_heading_noise_rad, self.n))
