"""TRIAD and improved TRIAD: closed-form recovery and accuracy weighting (seeded)."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from iotnav.techniques.triad import (
    dcm_to_quat,
    improved_triad,
    quat_to_dcm,
    triad,
    triad_covariance,
    triad_jacobian,
)

G_N = np.array([0.0, 0.0, 9.81])
M_N = np.array([22.4, 1.1, 41.3])  # Turin-like field, uT


def _angle(C1: np.ndarray, C2: np.ndarray) -> float:
    return float(np.linalg.norm(Rotation.from_matrix(C1 @ C2.T).as_rotvec()))


def _tilt_error(C: np.ndarray, C_true: np.ndarray) -> float:
    """Angle between the true and the estimated down axis of ``b`` seen in ``n``, rad."""
    u = C[2] / np.linalg.norm(C[2])
    return float(np.arccos(min(1.0, u @ C_true[2])))


@pytest.mark.parametrize("seed", range(5))
def test_exact_pairs_recover_rotation(seed: int) -> None:
    C_true = Rotation.random(random_state=seed).as_matrix()
    b1, b2 = C_true.T @ G_N, C_true.T @ M_N
    assert np.allclose(triad(b1, b2, G_N, M_N), C_true, atol=1e-12)
    assert np.allclose(triad(b2, b1, M_N, G_N), C_true, atol=1e-12)
    for s1, s2 in ((0.01, 0.03), (0.05, 0.001), (0.02, 0.02)):
        assert np.allclose(improved_triad(b1, b2, G_N, M_N, s1, s2), C_true, atol=1e-12)


def test_closed_form_quarter_turn() -> None:
    # body axes: b x = n East, b y = n North... a 90 deg yaw: C_nb maps b x to n y (East)
    C = triad(
        np.array([0.0, 0.0, 1.0]),
        np.array([0.0, -1.0, 0.0]),
        np.array([0.0, 0.0, 1.0]),
        np.array([1.0, 0.0, 0.0]),
    )
    expected = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
    assert np.allclose(C, expected, atol=1e-15)


def test_collinear_vectors_refused() -> None:
    with pytest.raises(ValueError, match="collinear"):
        triad(G_N, 2 * G_N, G_N, M_N)


def test_improved_triad_weights_the_more_accurate_vector() -> None:
    rng = np.random.default_rng(7)
    C_true = Rotation.from_euler("ZYX", [0.5, 0.05, -0.03]).as_matrix()
    err_anchor_acc, err_anchor_mag, err_imp = [], [], []
    for _ in range(400):
        # gravity accurate (0.2 deg), magnetometer poor (3 deg)
        s_g, s_m = np.radians(0.2), np.radians(3.0)
        b1 = Rotation.from_rotvec(rng.normal(0, s_g, 3)).apply(C_true.T @ G_N)
        b2 = Rotation.from_rotvec(rng.normal(0, s_m, 3)).apply(C_true.T @ M_N)
        err_anchor_acc.append(_tilt_error(triad(b1, b2, G_N, M_N), C_true))
        err_anchor_mag.append(_tilt_error(triad(b2, b1, M_N, G_N), C_true))
        C = improved_triad(b1, b2, G_N, M_N, s_g, s_m)
        err_imp.append(_tilt_error(C, C_true))
        # the accurate vector is (almost) matched exactly
        u = C @ b1 / np.linalg.norm(b1)
        assert np.degrees(np.arccos(min(1.0, u @ G_N / np.linalg.norm(G_N)))) < 0.05
        assert np.allclose(C.T @ C, np.eye(3), atol=1e-12) and np.linalg.det(C) > 0
    rms = lambda e: float(np.sqrt(np.mean(np.square(e))))  # noqa: E731
    # tilt: the weighted solution keeps the accuracy of gravity, unlike TRIAD anchored on the field
    assert rms(err_imp) < 0.2 * rms(err_anchor_mag)
    assert rms(err_imp) <= 1.05 * rms(err_anchor_acc)
    # swapping the sigmas makes the magnetometer the anchor
    b1 = C_true.T @ G_N + np.array([0.3, 0.0, 0.0])
    b2 = C_true.T @ M_N
    C = improved_triad(b1, b2, G_N, M_N, 1.0, 1e-4)
    u = C @ b2 / np.linalg.norm(b2)
    assert np.degrees(np.arccos(min(1.0, u @ M_N / np.linalg.norm(M_N)))) < 0.01


def test_triad_covariance_matches_monte_carlo() -> None:
    rng = np.random.default_rng(3)
    C_true = Rotation.from_euler("ZYX", [1.0, 0.1, 0.2]).as_matrix()
    s1, s2 = 0.01, 0.03
    errs = []
    for _ in range(3000):
        # direction noise perpendicular to each vector, sigma per axis
        b1 = Rotation.from_rotvec(rng.normal(0, s1, 3)).apply(C_true.T @ G_N)
        b2 = Rotation.from_rotvec(rng.normal(0, s2, 3)).apply(C_true.T @ M_N)
        errs.append(Rotation.from_matrix(C_true @ triad(b1, b2, G_N, M_N).T).as_rotvec())
    P_mc = np.cov(np.array(errs).T)
    P = triad_covariance(G_N, M_N, s1, s2)
    # compare the standard deviations on the three n axes within 15 %
    assert np.allclose(np.sqrt(np.diag(P_mc)), np.sqrt(np.diag(P)), rtol=0.15)


@pytest.mark.parametrize("seed", range(6))
def test_quaternion_round_trip(seed: int) -> None:
    R = Rotation.random(random_state=seed)
    x, y, z, w = R.as_quat()
    q = np.array([w, x, y, z]) * (1 if w >= 0 else -1)
    assert np.allclose(quat_to_dcm(q), R.as_matrix(), atol=1e-14)
    assert np.allclose(dcm_to_quat(R.as_matrix()), q, atol=1e-12)


@pytest.mark.parametrize("sigmas", [(0.02, 0.015), (1e-3, 0.1), (0.1, 1e-3)])
def test_triad_jacobian_matches_finite_differences(sigmas: tuple[float, float]) -> None:
    C_true = Rotation.from_euler("ZYX", [0.7, 0.2, -0.3]).as_matrix()
    b1, b2 = C_true.T @ G_N, C_true.T @ M_N
    s1, s2 = sigmas
    J1, J2 = triad_jacobian(b1, b2, G_N, M_N, s1, s2)
    for J, which in ((J1, 0), (J2, 1)):
        num = np.zeros((3, 3))
        for i in range(3):
            h = 1e-6 * np.linalg.norm((b1, b2)[which])
            bp, bm = [b1.copy(), b2.copy()], [b1.copy(), b2.copy()]
            bp[which][i] += h
            bm[which][i] -= h
            Cp = improved_triad(bp[0], bp[1], G_N, M_N, s1, s2)
            Cm = improved_triad(bm[0], bm[1], G_N, M_N, s1, s2)
            num[:, i] = Rotation.from_matrix(Cp @ Cm.T).as_rotvec() / (2 * h)
        assert np.allclose(J, num, atol=1e-8)


@pytest.mark.parametrize("seed", range(3))
def test_compiled_forms_equal_the_numpy_forms(seed: int) -> None:
    """The compiled forms (used by qekf's TRIAD observation) give the numpy forms' results to
    the rounding of the small matrix products; collinear vectors are flagged, not solved."""
    from iotnav.techniques.triad import (
        dcm_to_quat_nb,
        improved_triad_nb,
        triad_covariance_nb,
        triad_jacobian_nb,
    )

    rng = np.random.default_rng(seed)
    for k in range(20):
        C_true = Rotation.random(random_state=100 * seed + k).as_matrix()
        b1 = C_true.T @ G_N + rng.normal(size=3) * 0.3
        b2 = C_true.T @ M_N + rng.normal(size=3) * 2.0
        s1, s2 = rng.uniform(0.001, 0.05, size=2)
        C, ok = improved_triad_nb(b1, b2, G_N, M_N, s1, s2)
        assert ok
        np.testing.assert_allclose(C, improved_triad(b1, b2, G_N, M_N, s1, s2), rtol=0.0, atol=1e-14)
        np.testing.assert_allclose(dcm_to_quat_nb(C), dcm_to_quat(C), rtol=0.0, atol=1e-15)
        for A, B in zip(
            triad_jacobian_nb(b1, b2, G_N, M_N, s1, s2), triad_jacobian(b1, b2, G_N, M_N, s1, s2), strict=True
        ):
            np.testing.assert_allclose(A, B, rtol=0.0, atol=1e-15 * np.abs(B).max())
        np.testing.assert_allclose(
            triad_covariance_nb(G_N, M_N, s1, s2), triad_covariance(G_N, M_N, s1, s2), rtol=1e-14, atol=0.0
        )
    # every branch of Shepperd's method (trace, then the largest diagonal element)
    for q in np.eye(4):
        np.testing.assert_allclose(dcm_to_quat_nb(quat_to_dcm(q)), dcm_to_quat(quat_to_dcm(q)), atol=1e-15)
    _C, ok = improved_triad_nb(G_N, 2.0 * G_N, G_N, M_N, 0.01, 0.01)
    assert not ok
