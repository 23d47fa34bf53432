"""Tests of mmpa.core.geometry: conventions checked against scipy, group axioms, error metrics."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.linalg import expm
from scipy.spatial.transform import Rotation

from mmpa.core import geometry as g
from mmpa.core.errors import InvalidInputError


def _random_T(rng: np.random.Generator) -> np.ndarray:
    return g.make_T(Rotation.random(random_state=rng).as_matrix(), rng.uniform(-2, 2, 3))


def _twist_matrix(xi: np.ndarray) -> np.ndarray:
    """4x4 matrix [[hat(w), v], [0, 0]] of a twist [v, w] (written out by hand, no g.hat)."""
    v, w = xi[:3], xi[3:]
    return np.array(
        [
            [0.0, -w[2], w[1], v[0]],
            [w[2], 0.0, -w[0], v[1]],
            [-w[1], w[0], 0.0, v[2]],
            [0.0, 0.0, 0.0, 0.0],
        ]
    )


# --- 6D vectors and RPY -------------------------------------------------------------------


def test_vec6_round_trip_random() -> None:
    rng = np.random.default_rng(0)
    for _ in range(200):
        v = np.concatenate(
            [
                rng.uniform(-3, 3, 3),
                rng.uniform(-np.pi, np.pi, 1),
                rng.uniform(-np.pi / 2 + 1e-3, np.pi / 2 - 1e-3, 1),
                rng.uniform(-np.pi, np.pi, 1),
            ]
        )
        v2 = g.T_to_vec6(g.vec6_to_T(v))
        np.testing.assert_allclose(v2[:3], v[:3], atol=1e-12)
        np.testing.assert_allclose(g.wrap_angle(v2[3:] - v[3:]), 0.0, atol=1e-9)


def test_T_to_vec6_round_trip_random_T() -> None:
    rng = np.random.default_rng(1)
    for _ in range(200):
        T = _random_T(rng)
        np.testing.assert_allclose(g.vec6_to_T(g.T_to_vec6(T)), T, atol=1e-12)


def test_rpy_matches_scipy_extrinsic_xyz() -> None:
    rng = np.random.default_rng(2)
    for _ in range(100):
        r, p, y = rng.uniform(-np.pi, np.pi, 3)
        R_ref = Rotation.from_euler("xyz", [r, p, y]).as_matrix()  # lower case: extrinsic
        np.testing.assert_allclose(g.rpy_to_R(r, p, y), R_ref, atol=1e-14)


def test_rpy_elementary_axes() -> None:
    a = 0.3
    np.testing.assert_allclose(g.rpy_to_R(a, 0, 0), Rotation.from_rotvec([a, 0, 0]).as_matrix())
    np.testing.assert_allclose(g.rpy_to_R(0, a, 0), Rotation.from_rotvec([0, a, 0]).as_matrix())
    np.testing.assert_allclose(g.rpy_to_R(0, 0, a), Rotation.from_rotvec([0, 0, a]).as_matrix())
    # yaw 90 deg maps x to y
    np.testing.assert_allclose(g.rpy_to_R(0, 0, np.pi / 2) @ [1, 0, 0], [0, 1, 0], atol=1e-15)


def test_R_to_rpy_gimbal_lock_reconstructs_R() -> None:
    for pitch in (np.pi / 2, -np.pi / 2):
        R = g.rpy_to_R(0.4, pitch, -1.1)
        rpy = g.R_to_rpy(R)
        assert rpy[1] == pytest.approx(pitch)
        np.testing.assert_allclose(g.rpy_to_R(*rpy), R, atol=1e-12)


def test_quaternion_site1_yaw() -> None:
    # paper 000 §4.2, Site 1 orientation (x, y, z, w) = (0, 0, -0.2970, 0.9548)
    R = g.quat_xyzw_to_R([0.0, 0.0, -0.2970, 0.9548])
    roll, pitch, yaw = g.R_to_rpy(R)
    assert roll == pytest.approx(0.0, abs=1e-12)
    assert pitch == pytest.approx(0.0, abs=1e-12)
    assert np.rad2deg(yaw) == pytest.approx(-34.55, abs=0.1)  # 2 atan2(-0.2970, 0.9548)


def test_quaternion_round_trip_and_sign() -> None:
    rng = np.random.default_rng(3)
    for _ in range(50):
        R = Rotation.random(random_state=rng).as_matrix()
        q = g.R_to_quat_xyzw(R)
        assert q[3] >= 0.0
        assert np.linalg.norm(q) == pytest.approx(1.0)
        np.testing.assert_allclose(g.quat_xyzw_to_R(q), R, atol=1e-12)
        np.testing.assert_allclose(g.quat_xyzw_to_R(-q), R, atol=1e-12)


# --- group operations ---------------------------------------------------------------------


def test_inv_compose_group_axioms() -> None:
    rng = np.random.default_rng(4)
    for _ in range(50):
        A, B, C = _random_T(rng), _random_T(rng), _random_T(rng)
        np.testing.assert_allclose(A @ g.inv(A), np.eye(4), atol=1e-12)
        np.testing.assert_allclose(g.inv(A) @ A, np.eye(4), atol=1e-12)
        np.testing.assert_allclose(g.inv(A), np.linalg.inv(A), atol=1e-12)
        np.testing.assert_allclose(g.inv(A @ B), g.inv(B) @ g.inv(A), atol=1e-12)
        np.testing.assert_allclose((A @ B) @ C, A @ (B @ C), atol=1e-12)
        assert g.is_rotation((A @ B)[:3, :3])


def test_apply_maps_points_from_b_to_a() -> None:
    T_a_b = g.make_T(g.rot_z(np.pi / 2), [1.0, 0.0, 0.0])
    # point at x=1 in b: rotated to y=1, then shifted by +1 in x
    np.testing.assert_allclose(g.apply(T_a_b, [1.0, 0.0, 0.0]), [1.0, 1.0, 0.0], atol=1e-15)
    pts = np.random.default_rng(5).normal(size=(10, 3))
    homog = (T_a_b @ np.c_[pts, np.ones(10)].T).T[:, :3]
    np.testing.assert_allclose(g.apply(T_a_b, pts), homog, atol=1e-14)


def test_rot_xyz_are_right_handed() -> None:
    np.testing.assert_allclose(g.rot_x(np.pi / 2) @ [0, 1, 0], [0, 0, 1], atol=1e-15)
    np.testing.assert_allclose(g.rot_y(np.pi / 2) @ [0, 0, 1], [1, 0, 0], atol=1e-15)
    np.testing.assert_allclose(g.rot_z(np.pi / 2) @ [1, 0, 0], [0, 1, 0], atol=1e-15)
    assert not g.is_rotation(np.diag([1.0, 1.0, -1.0]))
    assert g.is_rotation(g.rot_x(0.7) @ g.rot_y(-0.2))


# --- exp / log / adjoint ------------------------------------------------------------------


def test_exp_matches_expm_and_log_round_trip() -> None:
    rng = np.random.default_rng(6)
    for scale in (0.0, 1e-12, 1e-6, 1e-3, 9.99e-3, 1.001e-2, 0.5, 2.0, 3.1):
        for _ in range(20):
            w = rng.normal(size=3)
            w *= scale / np.linalg.norm(w)  # rotation angle = scale
            xi = np.concatenate([rng.normal(size=3), w])
            T = g.exp_se3(xi)
            np.testing.assert_allclose(T, expm(_twist_matrix(xi)), atol=1e-12)
            np.testing.assert_allclose(g.log_se3(T), xi, atol=1e-9)


def test_log_exp_round_trip_random_T() -> None:
    rng = np.random.default_rng(7)
    for _ in range(100):
        T = _random_T(rng)
        np.testing.assert_allclose(g.exp_se3(g.log_se3(T)), T, atol=1e-10)


def test_hat_is_cross_product() -> None:
    a, b = np.array([0.3, -1.2, 2.0]), np.array([-0.7, 0.4, 1.1])
    np.testing.assert_allclose(g.hat(a) @ b, np.cross(a, b), atol=1e-15)


def test_adjoint_property() -> None:
    rng = np.random.default_rng(8)
    for _ in range(50):
        T = _random_T(rng)
        xi = rng.normal(size=6)
        lhs = T @ g.exp_se3(xi) @ g.inv(T)
        rhs = g.exp_se3(g.adjoint(T) @ xi)
        np.testing.assert_allclose(lhs, rhs, atol=1e-10)


# --- error metrics ------------------------------------------------------------------------


def test_rotation_error_closed_form() -> None:
    rng = np.random.default_rng(9)
    for phi in (0.0, 1e-4, 0.1, 1.0, 2.5, np.pi):
        axis = rng.normal(size=3)
        axis /= np.linalg.norm(axis)
        R_gt = Rotation.random(random_state=rng).as_matrix()
        R_est = Rotation.from_rotvec(phi * axis).as_matrix() @ R_gt
        expected = 2.0 * np.sqrt(2.0) * abs(np.sin(phi / 2.0))
        assert g.rotation_error(R_gt, R_est) == pytest.approx(expected, abs=1e-12)
        # also accepts 4x4 transforms
        assert g.rotation_error(g.make_T(R_gt), g.make_T(R_est)) == pytest.approx(
            expected, abs=1e-12
        )
    assert g.rotation_error(np.eye(3), np.eye(3)) == 0.0


def test_translation_error() -> None:
    assert g.translation_error([1.0, 2.0, 3.0], [1.0, 2.0, 3.0]) == 0.0
    assert g.translation_error([0.0, 0.0, 0.0], [3.0, 4.0, 0.0]) == pytest.approx(5.0)
    A = g.make_T(g.rot_z(1.0), [1.0, 1.0, 1.0])
    B = g.make_T(np.eye(3), [1.0, 1.0, 3.0])
    assert g.translation_error(A, B) == pytest.approx(2.0)


def test_wrap_angle() -> None:
    assert g.wrap_angle(np.pi) == pytest.approx(-np.pi)  # [-pi, pi)
    assert g.wrap_angle(-np.pi) == pytest.approx(-np.pi)
    assert g.wrap_angle(3 * np.pi / 2) == pytest.approx(-np.pi / 2)
    assert g.wrap_angle(-7.0) == pytest.approx(-7.0 + 2 * np.pi)
    assert isinstance(g.wrap_angle(0.5), float)
    w = g.wrap_angle(np.linspace(-20, 20, 101))
    assert np.all(w >= -np.pi) and np.all(w < np.pi)
    np.testing.assert_allclose(np.sin(w), np.sin(np.linspace(-20, 20, 101)), atol=1e-12)


# --- SE(2) ----------------------------------------------------------------------------------


def test_se2_compose_and_inverse_match_matrices() -> None:
    rng = np.random.default_rng(10)
    for _ in range(50):
        a = np.array([*rng.uniform(-5, 5, 2), rng.uniform(-np.pi, np.pi)])
        b = np.array([*rng.uniform(-5, 5, 2), rng.uniform(-np.pi, np.pi)])
        Ta, Tb = g.se2_to_T(*a), g.se2_to_T(*b)
        c = g.se2_compose(a, b)
        np.testing.assert_allclose(g.se2_to_T(*c), Ta @ Tb, atol=1e-12)
        np.testing.assert_allclose(g.T_to_se2(Ta @ Tb), c, atol=1e-12)
        ai = g.se2_inv(a)
        np.testing.assert_allclose(g.se2_to_T(*ai), np.linalg.inv(Ta), atol=1e-12)
        np.testing.assert_allclose(g.se2_compose(a, ai), [0.0, 0.0, 0.0], atol=1e-12)


def test_se2_batched() -> None:
    rng = np.random.default_rng(11)
    A = np.c_[rng.uniform(-5, 5, (20, 2)), rng.uniform(-np.pi, np.pi, 20)]
    B = np.c_[rng.uniform(-5, 5, (20, 2)), rng.uniform(-np.pi, np.pi, 20)]
    C = g.se2_compose(A, B)
    assert C.shape == (20, 3)
    for a, b, c in zip(A, B, C, strict=True):
        np.testing.assert_allclose(c, g.se2_compose(a, b), atol=1e-14)
    np.testing.assert_allclose(g.se2_compose(A, g.se2_inv(A)), 0.0, atol=1e-12)


def test_T_to_se2_projects_yaw() -> None:
    T = g.make_T(g.rpy_to_R(0.0, 0.0, 0.8), [1.0, -2.0, 0.5])
    np.testing.assert_allclose(g.T_to_se2(T), [1.0, -2.0, 0.8], atol=1e-14)


# --- input validation ---------------------------------------------------------------------


@pytest.mark.parametrize(
    ("fn", "arg"),
    [
        (g.vec6_to_T, np.zeros(5)),
        (g.vec6_to_T, np.zeros((2, 6))),
        (g.vec6_to_T, [0.0, 0.0, np.nan, 0.0, 0.0, 0.0]),
        (g.T_to_vec6, np.eye(3)),
        (g.T_to_vec6, np.full((4, 4), np.nan)),
        (g.log_se3, np.eye(3)),
        (g.log_se3, np.where(np.eye(4) > 0, np.inf, 0.0)),
        (g.T_to_se2, np.zeros((4, 3))),
        (g.exp_se3, np.zeros(5)),
        (g.exp_se3, [0.0, 0.0, 0.0, np.nan, 0.0, 0.0]),
    ],
)
def test_invalid_input_raises(fn, arg) -> None:
    with pytest.raises(InvalidInputError):
        fn(arg)


def test_invalid_input_error_is_a_value_error() -> None:
    with pytest.raises(ValueError, match="shape"):
        g.vec6_to_T(np.zeros(3))


def test_rotation_log_matches_the_closed_form_over_the_whole_range() -> None:
    """``log_so3`` against the rotation built from a known axis and angle (Rodrigues, written
    out here), from 1e-12 rad to just under pi (scipy's route near pi), and ``exp_so3`` back."""
    from mmpa.core.geometry import exp_so3, log_so3

    rng = np.random.default_rng(5)
    for theta in [1e-12, 1e-9, 1e-6, 1e-3, 0.1, 1.0, 2.0, 3.0, 3.1, np.pi - 1e-6]:
        u = rng.normal(size=3)
        u /= np.linalg.norm(u)
        K = np.array([[0, -u[2], u[1]], [u[2], 0, -u[0]], [-u[1], u[0], 0]])
        R = np.eye(3) + np.sin(theta) * K + (1 - np.cos(theta)) * K @ K
        np.testing.assert_allclose(log_so3(R), theta * u, atol=1e-9 if theta > 3 else 1e-14)
        np.testing.assert_allclose(exp_so3(theta * u), R, atol=1e-14)
