"""The engines' local NED plane about a geodetic origin, re-linearised along long routes.

Moved out of :mod:`iotnav.engines.base` (which re-exports both names) unchanged.
"""

from __future__ import annotations

import math

import numpy as np
import numpy.typing as npt

FloatArray = npt.NDArray[np.float64]


class TangentPlane:
    """Local NED coordinates about a geodetic origin, linearised at an anchor point.

    ``north = n_a + (lat - lat_a) k_n``, ``east = e_a + (lon - lon_a) k_e``, ``down = h0 - h``
    with ``k_n = M + h_a`` and ``k_e = (N + h_a) cos(lat_a)`` (meridian and prime-vertical radii,
    per degree) at the anchor ``(lat_a, lon_a, h_a)``, whose coordinates are ``(n_a, e_a)``. At
    first the anchor is the origin (``n_a = e_a = 0``). Written with the virtual origin
    ``lat0 = lat_a - n_a / k_n``, ``lon0 = lon_a - e_a / k_e`` the map is
    ``north = (lat - lat0) k_n``: an exact inverse pair, per-sample cheap, and what the
    compiled kernels evaluate (:meth:`constants`).

    Long routes (:meth:`follow`): the engines integrate their velocity, which is along the
    local North and East of the vehicle, into ``north`` and ``east``; that is exact only where
    the scale factors fit the vehicle's latitude and height. With one linearisation for a whole
    drive the east scale is off by ``tan(lat) * dnorth / R`` (3 % at 200 km North of a
    mid-latitude origin: a 1 m/s position error at highway speed). An engine calls
    :meth:`follow` at each fix; farther than :data:`REANCHOR_DISTANCE_M` from the anchor the
    plane is linearised again at the fix, whose coordinates stay unchanged, so the engine's
    state (position, velocity, attitude, covariance) carries over as it is: the axes are the
    local North, East and down everywhere, and the position is the same geodetic point in both
    planes. ``h0`` and so ``down`` never change. Earlier anchors are kept
    (:meth:`from_ned_rows` maps each row with its nearest one, as a smoother needs).
    """

    def __init__(self, lat0_deg: float, lon0_deg: float, h0_m: float) -> None:
        self.h0_m = h0_m
        self._linearise(lat0_deg, lon0_deg, h0_m, 0.0, 0.0)
        #: ``[n_a, e_a, lat0, lon0, k_n, k_e]`` of every linearisation so far, oldest first
        self.anchors: list[tuple[float, float, float, float, float, float]] = [self._anchor_row()]

    def _linearise(self, lat_a: float, lon_a: float, h_a: float, n_a: float, e_a: float) -> None:
        a, e2 = 6378137.0, 6.69437999014e-3
        s = math.sin(math.radians(lat_a))
        w = math.sqrt(1.0 - e2 * s * s)
        self.k_n = math.radians(1.0) * (a * (1.0 - e2) / w**3 + h_a)
        self.k_e = math.radians(1.0) * (a / w + h_a) * math.cos(math.radians(lat_a))
        self.n_a, self.e_a = n_a, e_a
        self.lat0_deg = lat_a - n_a / self.k_n
        self.lon0_deg = lon_a - e_a / self.k_e

    def _anchor_row(self) -> tuple[float, float, float, float, float, float]:
        return (self.n_a, self.e_a, self.lat0_deg, self.lon0_deg, self.k_n, self.k_e)

    def constants(self) -> FloatArray:
        """``[lat0_deg, lon0_deg, h0_m, k_n, k_e]`` (degrees, m, m/degree) for compiled kernels."""
        return np.array([self.lat0_deg, self.lon0_deg, self.h0_m, self.k_n, self.k_e])

    def to_ned(self, lat_deg: float, lon_deg: float, height_m: float) -> FloatArray:
        """Geodetic (degrees, m) to NED (m)."""
        return np.array(
            [(lat_deg - self.lat0_deg) * self.k_n, (lon_deg - self.lon0_deg) * self.k_e, self.h0_m - height_m]
        )

    def from_ned(self, r_n: FloatArray) -> tuple[float, float, float]:
        """NED (m) to geodetic (degrees, m)."""
        return (
            self.lat0_deg + float(r_n[0]) / self.k_n,
            self.lon0_deg + float(r_n[1]) / self.k_e,
            self.h0_m - float(r_n[2]),
        )

    def follow(self, r_n: FloatArray, distance_m: float | None = None) -> bool:
        """Re-linearise at ``r_n`` when it is farther than ``distance_m`` from the anchor.

        Parameters
        ----------
        r_n : numpy.ndarray
            The vehicle's (or its fix's) NED position in this plane, m.
        distance_m : float, optional
            Horizontal distance that triggers it (:data:`REANCHOR_DISTANCE_M` by default).

        Returns
        -------
        bool
            True when the plane moved: ``r_n`` keeps its coordinates (and its geodetic
            point), the scale factors are now those at ``r_n``, and the caller must refresh
            the copies of :meth:`constants` its kernels hold.
        """
        d = REANCHOR_DISTANCE_M if distance_m is None else distance_m
        n, e = float(r_n[0]), float(r_n[1])
        if not (math.hypot(n - self.n_a, e - self.e_a) > d):  # also False for NaN
            return False
        lat, lon, h = self.from_ned(r_n)
        self._linearise(lat, lon, h, n, e)
        self.anchors.append(self._anchor_row())
        return True

    def from_ned_rows(self, r_n: FloatArray) -> tuple[FloatArray, FloatArray, FloatArray]:
        """NED rows ``(N, 3)`` (m) to lat, lon (degrees), height (m), each by its nearest anchor."""
        r = np.asarray(r_n, float).reshape(-1, 3)
        a = np.asarray(self.anchors)
        if len(a) == 1:
            k = np.zeros(len(r), dtype=np.intp)
        else:
            from scipy.spatial import cKDTree

            ok = np.isfinite(r[:, 0]) & np.isfinite(r[:, 1])
            k = np.zeros(len(r), dtype=np.intp)
            if ok.any():
                k[ok] = cKDTree(a[:, :2]).query(r[ok, :2])[1]
        return a[k, 2] + r[:, 0] / a[k, 4], a[k, 3] + r[:, 1] / a[k, 5], self.h0_m - r[:, 2]


#: Horizontal distance from a plane's anchor beyond which an engine's fix re-anchors it, m.
#: At 200 m the scale factors fit the vehicle within ``200 m / 6371 km * tan(lat)`` (5e-5 at
#: 55 deg): 1.5 mm on a 30 m step between fixes; re-anchoring costs a few microseconds.
REANCHOR_DISTANCE_M = 200.0
