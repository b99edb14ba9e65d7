"""Long routes: the engines' tangent plane follows the vehicle (``TangentPlane.follow``).

A 200 km route at 50 deg North is built as geodetic points one second apart; what a perfect
inertial solution adds to its position between two of them is the vehicle's local
displacement, the second point in the local NED frame of the first (pymap3d's rigorous
``geodetic2ned``). The frame's own error is the distance between that displacement added in
the engine's plane and the fix the plane maps the second point to: through one fix interval,
and through a 30 s outage (30 displacements added without a fix). Without re-anchoring the
error grows with the distance from the origin (east scale off by ``tan(lat) dnorth / R``).
"""

from __future__ import annotations

import math

import numpy as np
import pymap3d
import pytest

from iotnav.engines.base import REANCHOR_DISTANCE_M, GnssSample, ImuSample, TangentPlane
from iotnav.engines.registry import make_engine

N_STEPS = 7000  # one second apart, 26-36 m each (up to 130 km/h)


def _route() -> tuple[np.ndarray, np.ndarray]:
    """Geodetic points ``(N+1, 3)`` (deg, deg, m) and the local NED step to each next point (m)."""
    k = np.arange(N_STEPS + 1) / N_STEPS
    lat = 50.0 + 0.25 * np.sin(2.0 * np.pi * k)  # +-28 km North-South
    lon = 8.0 + 2.5 * k + 0.02 * np.sin(6.0 * np.pi * k)
    h = 300.0 + 200.0 * k
    n, e, d = pymap3d.geodetic2ned(lat[1:], lon[1:], h[1:], lat[:-1], lon[:-1], h[:-1])
    return np.column_stack([lat, lon, h]), np.column_stack([n, e, d])


ROUTE, STEPS = _route()


def _frame_error(window: int, follow: bool) -> float:
    """Largest horizontal error (m) of ``window`` local steps added in the plane, over the route."""
    plane = TangentPlane(*ROUTE[0])
    worst = 0.0
    for k0 in range(0, N_STEPS - window + 1, window):
        r = plane.to_ned(*ROUTE[k0])
        if follow:
            plane.follow(r)
        r = r + STEPS[k0 : k0 + window].sum(axis=0)
        z = plane.to_ned(*ROUTE[k0 + window])
        worst = max(worst, float(np.hypot(r[0] - z[0], r[1] - z[1])))
    return worst


def test_route_is_long() -> None:
    length = float(np.hypot(STEPS[:, 0], STEPS[:, 1]).sum())
    assert length > 200e3


@pytest.mark.parametrize("window", [1, 30])
def test_frame_error_below_a_decimetre_on_200_km(window: int) -> None:
    """< 0.1 m through a fix interval and through a 30 s outage, anywhere on the route."""
    err = _frame_error(window, follow=True)
    assert err < 0.1, err
    # the check can fail: one plane for the whole drive is metres off far from the origin
    assert _frame_error(window, follow=False) > (0.1 if window == 1 else 1.0)


def test_follow_keeps_the_position_and_its_coordinates() -> None:
    """Re-anchoring moves neither the vehicle's coordinates nor its geodetic point."""
    plane = TangentPlane(50.0, 8.0, 300.0)
    assert not plane.follow(np.array([REANCHOR_DISTANCE_M * 0.9, 0.0, 0.0]))
    r = plane.to_ned(50.9, 9.2, 450.0)  # ~110 km away
    before = plane.from_ned(r)
    k_e = plane.k_e
    assert plane.follow(r)
    np.testing.assert_allclose(plane.to_ned(*before), r, atol=1e-7)
    np.testing.assert_allclose(plane.from_ned(r), before, rtol=0, atol=1e-12)
    # the east scale is now the one at 50.9 deg, and down still about the first origin
    assert plane.k_e == pytest.approx(
        k_e * math.cos(math.radians(50.9)) / math.cos(math.radians(50.0)), rel=1e-4
    )
    assert plane.h0_m == 300.0 and len(plane.anchors) == 2
    # rows recorded near either anchor map back through their own linearisation
    lat, lon, _ = plane.from_ned_rows(np.array([[0.0, 0.0, 0.0], r]))
    np.testing.assert_allclose([lat[0], lon[0]], [50.0, 8.0], atol=1e-12)
    np.testing.assert_allclose([lat[1], lon[1]], before[:2], atol=1e-12)


@pytest.mark.parametrize("name", ["anchor", "pipeline", "eskf", "pdr"])
def test_engines_follow_their_fixes(name: str) -> None:
    """Every engine on a TangentPlane re-anchors it as its fixes move on (one call each)."""
    # the engine's own plane: behind the (default) guard, pdr -- no steps in these still IMU
    # readings while its fixes move at 30 m/s -- is 90 m behind them and re-initialised twice
    eng = make_engine(name, integrity=False)
    t = 0.0
    for k in range(40):  # 40 s at 30 m/s East, 1 Hz fixes, still IMU readings
        lat, lon, h = pymap3d.ned2geodetic(0.0, 30.0 * k, 0.0, 50.0, 8.0, 300.0)
        eng.step(
            GnssSample(
                t,
                float(lat),
                float(lon),
                float(h),
                hdop=0.8,
                num_sv=9,
                speed_mps=30.0,
                course_rad=math.pi / 2,
                course_valid=True,
                vn=0.0,
                ve=30.0,
                vd=0.0,
            )
        )
        for j in range(10):
            eng.step(ImuSample(t + 0.1 * j, np.array([0.0, 0.0, -9.81]), np.zeros(3)))
        t += 1.0
    frame = eng.frame  # type: ignore[attr-defined]
    assert frame is not None and len(frame.anchors) >= 4, name
