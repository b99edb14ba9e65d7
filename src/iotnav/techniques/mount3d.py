"""Sensor-to-vehicle mount in 3D, committed only once it is observable (issue 16, item 2).

One estimator for every engine that needs the mount: it wraps block 5's yaw aligner
(:class:`iotnav.techniques.mount.MountAligner`, Forno et al. 2020, with the least-squares
form over longitudinal and centripetal acceleration) and adds what an engine needs on top:

Commitment
    Block 5's yaw is observable only from horizontal accelerations of the vehicle (speed
    changes and turns); on a straight at constant speed nothing measurable depends on it
    (:mod:`iotnav.techniques.mount`). Its fused 1-sigma says how well the data seen so far
    determine it, so the yaw is *committed* (handed to the engine) only once that sigma is at
    most ``commit_std_rad``. Before, :meth:`Mount3d.report` says ``unobservable`` and gives no
    angle; the engine keeps its own fallback (eskf: the last fix moved on at its velocity).
    Block 5's own acceptance rule (``MountConfig.max_std_rad``, infinite by default) is
    kept for the engines that use it directly; the commitment bound applies on top.

Roll and pitch (the level-vehicle assumption)
    At the commit epoch the vehicle is taken as level (roll, pitch zero within the road's
    crossfall and grade), so the mount's roll and pitch are the sensor's:
    ``C_vb = R_z(mu) R_y(theta_b) R_x(phi_b)`` with the sensor's roll ``phi_b`` and pitch
    ``theta_b`` from ``C_nb`` (:func:`mount_from_tilt`; any mounting, upside down included).
    A windshield phone's pitch or a tracker lying on its side is then in ``C_vb`` from the
    start; a filter with mount states (eskf) refines all three with the non-holonomic
    constraint, whose rows see pitch and yaw but not roll (a rotation about the direction of
    travel), so the roll stays tied to the sensor roll.

Per-axis status (:func:`axis_status`)
    From a mount covariance (3x3, rad^2, in ``v``): an axis whose 1-sigma is at most
    ``observable_std_rad`` is ``observable``, else ``unobservable``; a mount not committed is
    ``unobservable`` on every axis. Engines report it in their summary instead of an angle
    they do not know.

The qekf, anchor and pipeline engines use block 5's yaw alone; :func:`mount_from_tilt` gives
them the 3D ``C_vb`` from that yaw and their own attitude, and :class:`Mount3d` the same
commitment rule, without any change to block 5.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
import numpy.typing as npt

from iotnav.geo import dcm_to_rpy, euler_to_dcm
from iotnav.techniques.mount import MountAligner, MountConfig

FloatArray = npt.NDArray[np.float64]

OBSERVABLE = "observable"
UNOBSERVABLE = "unobservable"


def mount_from_tilt(C_nb: FloatArray, mount_yaw_rad: float) -> FloatArray:
    """``C_vb`` from block 5's yaw and the sensor tilt, the vehicle taken as level.

    Parameters
    ----------
    C_nb : numpy.ndarray
        Sensor attitude (``b`` to ``n``); only its roll and pitch are used.
    mount_yaw_rad : float
        Yaw of the sensor x axis from the vehicle forward axis (clockwise), rad.

    Returns
    -------
    numpy.ndarray
        ``C_vb = R_z(mu) R_y(theta_b) R_x(phi_b)`` (maps ``b`` vectors to ``v``).
    """
    r_b, p_b, _ = dcm_to_rpy(C_nb)
    return euler_to_dcm(r_b, p_b, mount_yaw_rad)


def axis_status(cov_rad2: FloatArray | None, committed: bool, observable_std_rad: float) -> list[str]:
    """Per-axis (roll, pitch, yaw) status of a mount estimate.

    Parameters
    ----------
    cov_rad2 : numpy.ndarray or None
        ``(3, 3)`` covariance of the mount rotation error in ``v``, rad^2 (None: unknown).
    committed : bool
        The mount has been committed (an angle is in use).
    observable_std_rad : float
        Largest 1-sigma of an ``observable`` axis, rad.

    Returns
    -------
    list of str
        ``observable`` or ``unobservable`` per axis.
    """
    if not committed or cov_rad2 is None:
        return [UNOBSERVABLE] * 3
    sd = np.sqrt(np.maximum(np.diag(np.asarray(cov_rad2, float)), 0.0))
    return [OBSERVABLE if s <= observable_std_rad else UNOBSERVABLE for s in sd]


class Mount3d:
    """Block 5's yaw aligner with the commitment rule and the 3D report (module docstring).

    Parameters
    ----------
    config : MountConfig, optional
        Block 5's settings.
    commit_std_rad : float
        Block 5's fused 1-sigma at or below which its yaw is committed, rad.

    Attributes
    ----------
    aligner : MountAligner
        The yaw aligner (engines feed it directly; its ``imu_sums`` are compiled-kernel
        arrays).
    """

    def __init__(self, config: MountConfig | None = None, commit_std_rad: float = 0.1) -> None:
        self.aligner = MountAligner(config)
        self.commit_std_rad = float(commit_std_rad)

    @property
    def yaw_std_rad(self) -> float:
        """Block 5's fused 1-sigma of its latest applied yaw, rad (inf before any)."""
        if not self.aligner.known:
            return math.inf
        return float(self.aligner.quality.get("std_rad", math.inf))

    @property
    def committable(self) -> bool:
        """Block 5 has a yaw whose 1-sigma is within the commitment bound."""
        return self.aligner.known and self.yaw_std_rad <= self.commit_std_rad

    @property
    def mount_yaw_rad(self) -> float:
        """Block 5's latest applied yaw, rad (NaN before any)."""
        return float(self.aligner.mount_yaw_rad) if self.aligner.known else math.nan

    def report(
        self,
        C_vb: FloatArray | None,
        cov_rad2: FloatArray | None,
        observable_std_rad: float,
    ) -> dict[str, Any]:
        """Status for a summary: ``status``, per-axis ``axes``, ``rpy_rad`` and ``std_rad``.

        Parameters
        ----------
        C_vb : numpy.ndarray or None
            The mount in use (None: none committed).
        cov_rad2 : numpy.ndarray or None
            Its ``(3, 3)`` error covariance in ``v``, rad^2.
        observable_std_rad : float
            Largest 1-sigma of an ``observable`` axis, rad.

        Returns
        -------
        dict
            ``status`` is ``unobservable`` with no angle (``rpy_rad`` None) before the
            commitment, else ``observable`` when its yaw is, with the per-axis ``axes``.
        """
        committed = C_vb is not None
        axes = axis_status(cov_rad2, committed, observable_std_rad)
        std = (
            np.sqrt(np.maximum(np.diag(np.asarray(cov_rad2, float)), 0.0)).tolist()
            if committed and cov_rad2 is not None
            else None
        )
        return {
            "status": axes[2] if committed else UNOBSERVABLE,
            "axes": dict(zip(("roll", "pitch", "yaw"), axes, strict=True)),
            "rpy_rad": list(dcm_to_rpy(C_vb)) if C_vb is not None else None,
            "std_rad": std,
            "block5_yaw_rad": self.mount_yaw_rad,
            "block5_std_rad": self.yaw_std_rad,
        }
