"""Geodesy and rotation helpers against closed-form values (layer a)."""

from __future__ import annotations

import numpy as np
import pytest

from iotnav import geo

A = 6378137.0
B = 6356752.314245  # WGS84 semi-minor axis, m


def test_ecef_of_reference_points() -> None:
    np.testing.assert_allclose(geo.geodetic_to_ecef(0, 0, 0), [A, 0, 0], atol=1e-6)
    np.testing.assert_allclose(geo.geodetic_to_ecef(0, 90, 100), [0, A + 100, 0], atol=1e-6)
    np.testing.assert_allclose(geo.geodetic_to_ecef(90, 0, 0), [0, 0, B], atol=1e-5)


def test_ned_small_offsets_match_radii_of_curvature() -> None:
    lat0 = 45.0
    f = geo.LocalFrame(lat0, 7.0, 200.0)
    e2 = 6.69437999014e-3
    s2 = np.sin(np.radians(lat0)) ** 2
    m_radius = A * (1 - e2) / (1 - e2 * s2) ** 1.5
    n_radius = A / np.sqrt(1 - e2 * s2)
    d = 1e-5  # degrees
    ned = f.to_ned(lat0 + d, 7.0, 200.0)
    assert ned[0] == pytest.approx(np.radians(d) * (m_radius + 200.0), rel=1e-6)
    ned = f.to_ned(lat0, 7.0 + d, 200.0)
    assert ned[1] == pytest.approx(np.radians(d) * (n_radius + 200.0) * np.cos(np.radians(lat0)), rel=1e-6)
    ned = f.to_ned(lat0, 7.0, 210.0)
    np.testing.assert_allclose(ned, [0, 0, -10.0], atol=1e-6)


def test_round_trips_vectorised() -> None:
    rng = np.random.default_rng(1)
    f = geo.LocalFrame(-33.9, 151.2, 40.0)
    r = rng.normal(0, 2000, size=(100, 3))
    lat, lon, h = f.from_ned(r)
    np.testing.assert_allclose(f.to_ned(lat, lon, h), r, atol=1e-6)
    np.testing.assert_allclose(geo.ned_to_enu(geo.enu_to_ned(r)), r)
    x = geo.geodetic_to_ecef(lat, lon, h)
    np.testing.assert_allclose(f.ecef_to_ned(x), r, atol=1e-6)
    lat2, _lon2, h2 = geo.ecef_to_geodetic(x)
    np.testing.assert_allclose(lat2, lat, atol=1e-9)
    np.testing.assert_allclose(h2, h, atol=1e-6)


def test_c_en_columns_are_ned_axes_in_ecef() -> None:
    f = geo.LocalFrame(0.0, 0.0)
    # At lat=lon=0: North = +z_e, East = +y_e, Down = -x_e.
    np.testing.assert_allclose(f.C_en, [[0, 0, -1], [0, 1, 0], [1, 0, 0]], atol=1e-12)
    v = np.array([1.0, 2.0, 3.0])
    np.testing.assert_allclose(f.ecef_vector_to_ned(f.C_en @ v), v, atol=1e-12)


def test_normal_gravity_published_values() -> None:
    # WGS84 normal gravity on the ellipsoid: 9.7803253359 (equator), 9.8321849378 (poles).
    assert geo.normal_gravity(0.0) == pytest.approx(9.7803253359, abs=1e-9)
    assert geo.normal_gravity(90.0) == pytest.approx(9.8321849378, abs=1e-8)
    # Free-air gradient about -3.086e-6 s^-2.
    assert geo.normal_gravity(45.0, 1000.0) - geo.normal_gravity(45.0, 0.0) == pytest.approx(
        -3.086e-3, rel=2e-3
    )


def test_euler_dcm_conventions() -> None:
    # Yaw 90 deg (pointing East): body x maps to NED East.
    C = geo.euler_to_dcm(0.0, 0.0, np.pi / 2)
    np.testing.assert_allclose(C @ [1, 0, 0], [0, 1, 0], atol=1e-12)
    # Pitch up 30 deg: body x points up (negative down).
    C = geo.euler_to_dcm(0.0, np.radians(30), 0.0)
    np.testing.assert_allclose(C @ [1, 0, 0], [np.cos(np.radians(30)), 0, -0.5], atol=1e-12)
    # Roll right 90 deg: body y points down.
    C = geo.euler_to_dcm(np.pi / 2, 0.0, 0.0)
    np.testing.assert_allclose(C @ [0, 1, 0], [0, 0, 1], atol=1e-12)
    r, p, y = geo.dcm_to_euler(geo.euler_to_dcm([0.1, -0.2], [0.3, 0.1], [2.0, -3.0]))
    np.testing.assert_allclose(r, [0.1, -0.2])
    np.testing.assert_allclose(p, [0.3, 0.1])
    np.testing.assert_allclose(y, [2.0, -3.0])


def test_wrap_and_skew() -> None:
    np.testing.assert_allclose(geo.wrap_angle([3 * np.pi, -3 * np.pi / 2, 0.5]), [np.pi, np.pi / 2, 0.5])
    a, b = np.array([1.0, -2.0, 0.5]), np.array([0.3, 0.4, -1.0])
    np.testing.assert_allclose(geo.skew(a) @ b, np.cross(a, b))
