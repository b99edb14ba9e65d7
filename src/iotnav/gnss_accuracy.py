"""One reading of a receiver's position accuracy figures, for every engine.

A fix carries some of: ``h_acc_m`` / ``v_acc_m`` (u-blox ``hAcc`` / ``vAcc``, RTKLIB's
``sqrt(sdn^2 + sde^2)`` / ``sdu``, the simulator's), HDOP and PDOP (NMEA GGA / GSA). iotnav
reads them one way everywhere (:func:`position_sigmas`):

* ``h_acc_m`` is the **horizontal (2D) 1-sigma**, the root of the sum of the north and east
  variances, so each horizontal axis has ``h_acc / sqrt(2)``. This is how HDOP works
  (``UERE x HDOP`` is the 2D root-sum-square, Kaplan and Hegarty, "Understanding GPS/GNSS",
  3rd ed., §11.2.1), how RTKLIB's per-axis sigmas combine, and how Android's
  ``Location.getAccuracy`` (a 68 % horizontal radius) reads. PX4 EKF2 and the ROS u-blox
  driver take ``hAcc`` per axis instead: for them ``R`` is twice iotnav's.
* DOPs: ``sigma_h (2D) = UERE x HDOP``, ``sigma_v = UERE x VDOP`` with
  ``VDOP = sqrt(PDOP^2 - HDOP^2)``. A missing HDOP is taken from PDOP, a missing VDOP from
  HDOP, through the typical open-sky geometry ``VDOP = 1.5 HDOP``
  (:data:`VDOP_PER_HDOP`); no DOP at all: the caller's default HDOP.
* ``v_acc_m`` is the vertical 1-sigma; without it, the horizontal figure x
  :data:`VDOP_PER_HDOP` (``h_acc`` is ``UERE x HDOP`` in effect).

Each sigma comes with the name of the figure it was taken from (``h_acc``, ``v_acc``,
``hdop``, ``pdop``, ``default``): :class:`iotnav.engines.gnss_resolution.AccuracyScaling`
compares like with like and finds each figure's rounding by that name.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np
import numpy.typing as npt

FloatArray = npt.NDArray[np.float64]

VDOP_PER_HDOP = 1.5
"""Typical open-sky ratio VDOP / HDOP (GPS alone 1.5-1.8, multi-constellation about 1.5)."""


class PositionSigmas(NamedTuple):
    """1-sigma of a fix's position error, m, and the figures each was taken from."""

    north_east_m: float
    """Per horizontal axis (north and east alike), m."""
    down_m: float
    """Vertical, m."""
    source: tuple[str, str]
    """Figure behind the horizontal and the vertical sigma: ``h_acc``, ``v_acc``, ``hdop``,
    ``pdop`` or ``default``."""

    @property
    def ned_m(self) -> FloatArray:
        """North, east, down sigma, m, ``(3,)``."""
        return np.array([self.north_east_m, self.north_east_m, self.down_m])


def h_acc_from_radius(radius_m: npt.ArrayLike, confidence: float = 0.68) -> FloatArray:
    """The 2D 1-sigma (``h_acc_m``) of a horizontal accuracy given as a confidence radius, m.

    Android's ``Location.getAccuracy`` is the radius of 68 % confidence. For a circular
    Gaussian error of per-axis sigma ``s``, ``P(r <= R) = 1 - exp(-R^2 / (2 s^2))``, so
    ``R = s sqrt(-2 ln(1 - p))`` (1.51 s at 68 %) and ``h_acc = sqrt(2) s = 0.937 R``.

    Parameters
    ----------
    radius_m : array_like
        Confidence radius, m.
    confidence : float
        Probability of the radius, in (0, 1).

    Returns
    -------
    numpy.ndarray
        Horizontal 2D 1-sigma, m, shaped as ``radius_m``.
    """
    if not 0.0 < confidence < 1.0:
        raise ValueError(f"confidence must be in (0, 1), got {confidence}")
    return np.asarray(radius_m, dtype=np.float64) * (
        math.sqrt(2.0) / math.sqrt(-2.0 * math.log1p(-confidence))
    )


def _positive(x: float) -> bool:
    return math.isfinite(x) and x > 0.0


def position_sigmas(
    h_acc_m: float,
    v_acc_m: float,
    hdop: float,
    pdop: float,
    uere_m: float,
    default_hdop: float,
) -> PositionSigmas:
    """Per-axis NED 1-sigma of a fix from the receiver's figures (module docstring).

    Parameters
    ----------
    h_acc_m, v_acc_m : float
        Receiver's horizontal (2D) and vertical accuracy, m; NaN or <= 0 when not reported.
    hdop, pdop : float
        Dilutions of precision; NaN or <= 0 when not reported.
    uere_m : float
        User-equivalent range error the DOPs are multiplied by, m.
    default_hdop : float
        HDOP assumed when the fix carries neither an accuracy nor a DOP.

    Returns
    -------
    PositionSigmas
        North/east sigma (each), down sigma (m) and the figures they were taken from.
    """
    has_hdop, has_pdop = _positive(hdop), _positive(pdop)
    if has_hdop:
        h_dop, src_dop = hdop, "hdop"
    elif has_pdop:
        h_dop, src_dop = pdop / math.hypot(1.0, VDOP_PER_HDOP), "pdop"
    else:
        h_dop, src_dop = default_hdop, "default"
    if has_hdop and has_pdop and pdop > hdop:
        v_dop, src_v_dop = math.sqrt(pdop * pdop - hdop * hdop), "pdop"
    else:
        v_dop, src_v_dop = VDOP_PER_HDOP * h_dop, src_dop
    if _positive(h_acc_m):
        h2d, src_h = h_acc_m, "h_acc"
        v, src_v = VDOP_PER_HDOP * h_acc_m, "h_acc"
    else:
        h2d, src_h = uere_m * h_dop, src_dop
        v, src_v = uere_m * v_dop, src_v_dop
    if _positive(v_acc_m):
        v, src_v = v_acc_m, "v_acc"
    return PositionSigmas(h2d / math.sqrt(2.0), v, (src_h, src_v))
