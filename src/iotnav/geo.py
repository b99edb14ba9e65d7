"""Geodesy and rotations: WGS84 geodetic <-> ECEF <-> local NED/ENU, Euler <-> ``C_nb``.

All ellipsoid maths goes through :mod:`pymap3d`; rotations through
:class:`scipy.spatial.transform.Rotation`. Functions are vectorised over array inputs.
Geodetic latitude/longitude are in degrees (the GNSS file convention), heights are ellipsoidal
metres, local coordinates metres in the frame named by the function.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt
import pymap3d
from scipy.spatial.transform import Rotation

ArrayLike = npt.ArrayLike
FloatArray = npt.NDArray[np.float64]

#: WGS84 constants used by the normal gravity formula (Somigliana, WGS84 TR8350.2).
_GE = 9.7803253359  # normal gravity at the equator, m/s^2
_K = 0.00193185265241
_E2 = 0.00669437999013
_A = 6378137.0
_F = 1.0 / 298.257223563
_GM = 3.986004418e14
_OMEGA_E = 7.292115e-5


def _arr(x: ArrayLike) -> FloatArray:
    return np.asarray(x, dtype=float)


def geodetic_to_ecef(lat_deg: ArrayLike, lon_deg: ArrayLike, height_m: ArrayLike) -> FloatArray:
    """WGS84 geodetic to ECEF.

    Parameters
    ----------
    lat_deg, lon_deg : array_like
        Geodetic latitude and longitude, degrees.
    height_m : array_like
        Ellipsoidal height, m.

    Returns
    -------
    numpy.ndarray
        ECEF ``[x, y, z]`` in m, shape ``(..., 3)``.
    """
    x, y, z = pymap3d.geodetic2ecef(_arr(lat_deg), _arr(lon_deg), _arr(height_m))
    return np.stack(np.broadcast_arrays(x, y, z), axis=-1)


def ecef_to_geodetic(r_e: ArrayLike) -> tuple[FloatArray, FloatArray, FloatArray]:
    """ECEF ``(..., 3)`` in m to geodetic latitude, longitude (degrees) and ellipsoidal height (m)."""
    r = _arr(r_e)
    lat, lon, h = pymap3d.ecef2geodetic(r[..., 0], r[..., 1], r[..., 2])
    return _arr(lat), _arr(lon), _arr(h)


@dataclass(frozen=True)
class LocalFrame:
    """A local tangent frame anchored at a geodetic origin.

    Attributes
    ----------
    lat0_deg, lon0_deg : float
        Origin latitude and longitude, degrees.
    h0_m : float
        Origin ellipsoidal height, m.
    """

    lat0_deg: float
    lon0_deg: float
    h0_m: float = 0.0

    def to_ned(self, lat_deg: ArrayLike, lon_deg: ArrayLike, height_m: ArrayLike) -> FloatArray:
        """Geodetic (degrees, m) to NED ``(..., 3)`` in m about the origin."""
        n, e, d = pymap3d.geodetic2ned(
            _arr(lat_deg), _arr(lon_deg), _arr(height_m), self.lat0_deg, self.lon0_deg, self.h0_m
        )
        return np.stack(np.broadcast_arrays(n, e, d), axis=-1).astype(float)

    def from_ned(self, r_n: ArrayLike) -> tuple[FloatArray, FloatArray, FloatArray]:
        """NED ``(..., 3)`` in m to geodetic latitude, longitude (degrees) and height (m)."""
        r = _arr(r_n)
        lat, lon, h = pymap3d.ned2geodetic(
            r[..., 0], r[..., 1], r[..., 2], self.lat0_deg, self.lon0_deg, self.h0_m
        )
        return _arr(lat), _arr(lon), _arr(h)

    def to_enu(self, lat_deg: ArrayLike, lon_deg: ArrayLike, height_m: ArrayLike) -> FloatArray:
        """Geodetic (degrees, m) to ENU ``(..., 3)`` in m about the origin."""
        ned = self.to_ned(lat_deg, lon_deg, height_m)
        return ned_to_enu(ned)

    def ecef_to_ned(self, r_e: ArrayLike) -> FloatArray:
        """ECEF position ``(..., 3)`` in m to NED about the origin, m."""
        r = _arr(r_e)
        n, e, d = pymap3d.ecef2ned(r[..., 0], r[..., 1], r[..., 2], self.lat0_deg, self.lon0_deg, self.h0_m)
        return np.stack(np.broadcast_arrays(n, e, d), axis=-1).astype(float)

    def ecef_vector_to_ned(self, v_e: ArrayLike) -> FloatArray:
        """Rotate an ECEF vector (e.g. a velocity, m/s) into the origin's NED axes."""
        return _arr(v_e) @ self.C_en

    @property
    def C_en(self) -> FloatArray:
        """Rotation from NED to ECEF at the origin (``v_e = C_en @ v_n``)."""
        lat = np.radians(self.lat0_deg)
        lon = np.radians(self.lon0_deg)
        sl, cl = np.sin(lat), np.cos(lat)
        so, co = np.sin(lon), np.cos(lon)
        return np.array(
            [
                [-sl * co, -so, -cl * co],
                [-sl * so, co, -cl * so],
                [cl, 0.0, -sl],
            ]
        )


def ned_to_enu(r_n: ArrayLike) -> FloatArray:
    """Swap NED ``(..., 3)`` to ENU (and back: the map is its own inverse)."""
    r = _arr(r_n)
    return np.stack([r[..., 1], r[..., 0], -r[..., 2]], axis=-1)


enu_to_ned = ned_to_enu


def normal_gravity(lat_deg: float, height_m: float = 0.0) -> float:
    """Magnitude of WGS84 normal gravity, m/s^2 (Somigliana with a free-air height term).

    Parameters
    ----------
    lat_deg : float
        Geodetic latitude, degrees.
    height_m : float
        Ellipsoidal height, m.

    Returns
    -------
    float
        Gravity magnitude, m/s^2 (``g_n = [0, 0, g]``).
    """
    s2 = np.sin(np.radians(lat_deg)) ** 2
    g0 = _GE * (1.0 + _K * s2) / np.sqrt(1.0 - _E2 * s2)
    m = _OMEGA_E**2 * _A**2 * (_A * (1 - _F)) / _GM
    return float(
        g0 * (1.0 - 2.0 / _A * (1.0 + _F + m - 2.0 * _F * s2) * height_m + 3.0 / _A**2 * height_m**2)
    )


def euler_to_dcm(roll: ArrayLike, pitch: ArrayLike, yaw: ArrayLike) -> FloatArray:
    """``C_nb`` from roll, pitch, yaw (rad, ZYX aerospace sequence).

    Returns
    -------
    numpy.ndarray
        ``(..., 3, 3)`` rotation matrices mapping ``b`` to ``n``.
    """
    angles = np.stack(np.broadcast_arrays(_arr(yaw), _arr(pitch), _arr(roll)), axis=-1)
    return Rotation.from_euler("ZYX", angles.reshape(-1, 3)).as_matrix().reshape((*angles.shape[:-1], 3, 3))


def dcm_to_euler(C_nb: ArrayLike) -> tuple[FloatArray, FloatArray, FloatArray]:
    """Roll, pitch, yaw (rad; yaw in (-pi, pi]) of ``C_nb`` ``(..., 3, 3)``."""
    C = _arr(C_nb)
    shape = C.shape[:-2]
    ypr = Rotation.from_matrix(C.reshape(-1, 3, 3)).as_euler("ZYX")
    ypr = ypr.reshape((*shape, 3))
    return ypr[..., 2], ypr[..., 1], ypr[..., 0]


def wrap_angle(a: ArrayLike) -> FloatArray:
    """Wrap angles (rad) to (-pi, pi]."""
    x = _arr(a)
    return np.pi - np.mod(np.pi - x, 2.0 * np.pi)


def skew(v: ArrayLike) -> FloatArray:
    """Cross-product matrix ``[v x]`` of a 3-vector (``skew(a) @ b == cross(a, b)``)."""
    x, y, z = _arr(v)
    return np.array([[0.0, -z, y], [z, 0.0, -x], [-y, x, 0.0]])


def dcm_to_rpy(C: FloatArray) -> tuple[float, float, float]:
    """Roll, pitch, yaw (rad) of one ``C_nb`` (ZYX), for per-sample use in the engines' steps.

    Scalar and allocation-free; :func:`dcm_to_euler` is the vectorised form.
    """
    return (
        float(math.atan2(C[2, 1], C[2, 2])),
        float(math.asin(max(-1.0, min(1.0, -C[2, 0])))),
        float(math.atan2(C[1, 0], C[0, 0])),
    )


def rot_z(a: float) -> FloatArray:
    """Rotation matrix about the down axis by ``a`` rad (clockwise seen from above)."""
    c, s = math.cos(a), math.sin(a)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
