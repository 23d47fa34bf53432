"""IPE math (paper 000 eq. 9-11) against the world-frame ground truth it is derived from."""

from __future__ import annotations

import numpy as np
import pytest

from mmpa.core.errors import InvalidInputError
from mmpa.core.geometry import apply, inv, make_T, rpy_to_R, vec6_to_T
from mmpa.ipe import (
    DEFAULT_ALPHA,
    alpha_vector,
    camera_target,
    converged,
    delta_T_B,
    pose_difference,
    transform_path,
)


def _rand_T(rng, t_scale=1.0, r_scale=np.pi):
    return make_T(rpy_to_R(*rng.uniform(-r_scale, r_scale, 3)), rng.normal(0, t_scale, 3))


@pytest.fixture
def scene():
    """Teaching and automation poses of arm base and camera in the world."""
    rng = np.random.default_rng(7)
    T_map_Bo = _rand_T(rng)
    T_map_Bk = T_map_Bo @ vec6_to_T([0.05, -0.09, 0.002, 0.01, -0.02, 0.2])  # parked elsewhere
    T_Bo_Co = _rand_T(rng, 0.5)
    T_Bk_Ck = T_Bo_Co @ vec6_to_T([0.02, 0.01, -0.03, 0.05, 0.0, -0.1])  # arm moved, too
    return T_map_Bo, T_map_Bk, T_Bo_Co, T_Bk_Ck


def test_eq_9_10_recover_the_parking_offset(scene):
    T_map_Bo, T_map_Bk, T_Bo_Co, T_Bk_Ck = scene
    # what registration measures: p_Ck = dT_C p_Co for every world point
    dT_C = inv(T_map_Bk @ T_Bk_Ck) @ (T_map_Bo @ T_Bo_Co)
    dT_B = delta_T_B(T_Bk_Ck, dT_C, T_Bo_Co)
    # ground truth: p_Bk = dT_B p_Bo for every world point
    np.testing.assert_allclose(dT_B, inv(T_map_Bk) @ T_map_Bo, atol=1e-12)
    # the paper's component form, eq. 9 and eq. 10, written out
    R_k, t_k = T_Bk_Ck[:3, :3], T_Bk_Ck[:3, 3]
    R_o, t_o = T_Bo_Co[:3, :3], T_Bo_Co[:3, 3]
    dR_C, dt_C = dT_C[:3, :3], dT_C[:3, 3]
    np.testing.assert_allclose(dT_B[:3, :3], R_k @ dR_C @ np.linalg.inv(R_o), atol=1e-12)
    eq10 = -R_k @ dR_C @ np.linalg.inv(R_o) @ t_o + R_k @ dt_C + t_k
    np.testing.assert_allclose(dT_B[:3, 3], eq10, atol=1e-12)


def test_camera_target_returns_camera_to_taught_world_pose(scene):
    T_map_Bo, T_map_Bk, T_Bo_Co, _ = scene
    dT_B = inv(T_map_Bk) @ T_map_Bo
    np.testing.assert_allclose(
        T_map_Bk @ camera_target(dT_B, T_Bo_Co), T_map_Bo @ T_Bo_Co, atol=1e-12
    )


def test_eq_11_maps_taught_tool_path_to_same_world_points(scene):
    T_map_Bo, T_map_Bk, _, _ = scene
    rng = np.random.default_rng(3)
    path = np.stack([_rand_T(rng, 0.4) for _ in range(7)])
    new = transform_path(inv(T_map_Bk) @ T_map_Bo, path)
    np.testing.assert_allclose(
        np.einsum("ij,njk->nik", T_map_Bk, new),
        np.einsum("ij,njk->nik", T_map_Bo, path),
        atol=1e-12,
    )
    # eq. 11 on positions alone
    dT_B = inv(T_map_Bk) @ T_map_Bo
    np.testing.assert_allclose(new[:, :3, 3], apply(dT_B, path[:, :3, 3]), atol=1e-12)


def test_convergence_test_per_component():
    a = np.asarray(DEFAULT_ALPHA)
    assert converged(np.eye(4), a)
    assert converged(vec6_to_T([0.0019, -0.0019, 0.0019, 0, 0, 0]), a)
    assert not converged(vec6_to_T([0.0021, 0, 0, 0, 0, 0]), a)
    assert not converged(vec6_to_T([0, 0, 0, 0, 0, np.deg2rad(0.51)]), a)
    d = pose_difference(vec6_to_T([-0.001, 0.002, -0.003, 0.01, -0.02, 0.03]))
    np.testing.assert_allclose(d, [0.001, 0.002, 0.003, 0.01, 0.02, 0.03], atol=1e-12)


def test_bad_inputs():
    with pytest.raises(InvalidInputError, match="alpha"):
        alpha_vector((0.002, 0.002, 0.002, 0.01, 0.01))
    with pytest.raises(InvalidInputError, match="alpha"):
        alpha_vector((0.002, 0.002, -0.002, 0.01, 0.01, 0.01))
    with pytest.raises(InvalidInputError, match="T_Bo_tool"):
        transform_path(np.eye(4), np.zeros((3, 4)))
    bad = np.eye(4)
    bad[0, 0] = np.nan
    with pytest.raises(InvalidInputError):
        delta_T_B(bad, np.eye(4), np.eye(4))


def test_repark_motion_returns_the_arm_base_to_its_taught_pose():
    from mmpa.core.geometry import se2_compose, se2_inv, se2_to_T
    from mmpa.missions.teach_repeat import repark_motion

    rng = np.random.default_rng(3)
    M = make_T(rpy_to_R(0.0, 0.0, 0.3), [0.2, -0.05, 0.4])  # arm mounting T_base_link_arm_base
    for _ in range(5):
        taught = rng.uniform([-2, -2, -np.pi], [2, 2, np.pi])  # base_link at teaching (x, y, th)
        parked = se2_compose(taught, rng.normal(0, [0.15, 0.15, 0.3]))
        dT_B = inv(se2_to_T(*parked) @ M) @ (se2_to_T(*taught) @ M)
        motion = repark_motion(dT_B, M)
        # closed form: the base_link must move by inv(parked) o taught, in its own frame
        expect = se2_compose(se2_inv(parked), taught)
        np.testing.assert_allclose(motion, expect, atol=1e-12)
        # and after moving, the arm base is where it was taught
        T_map_B_new = se2_to_T(*se2_compose(parked, motion)) @ M
        np.testing.assert_allclose(T_map_B_new, se2_to_T(*taught) @ M, atol=1e-12)


def test_view_consistency_closed_forms():
    """Two offset estimates that differ by a translation t disagree by |t| at any camera;
    by a rotation theta about the taught camera's position, by 0 m and theta rad there, and
    by the chord 2 sin(theta / 2) r at a camera a lever arm r away (about z)."""
    from mmpa.ipe.loop import view_consistency

    T_Bo_Co = make_T(rpy_to_R(0.3, -0.2, 1.0), [0.4, 0.1, 0.5])
    t = np.array([0.003, -0.001, 0.002])
    d, a = view_consistency(make_T(np.eye(3), t), np.eye(4), T_Bo_Co)
    assert d == pytest.approx(np.linalg.norm(t)) and a == pytest.approx(0.0, abs=1e-7)
    theta = 0.01
    c = T_Bo_Co[:3, 3]
    R = rpy_to_R(0.0, 0.0, theta)
    about_c = make_T(R, c - R @ c)  # a rotation about the point c
    d, a = view_consistency(about_c, np.eye(4), T_Bo_Co)
    assert d == pytest.approx(0.0, abs=1e-12) and a == pytest.approx(theta)
    other = make_T(np.eye(3), [0.5, -0.2, 0.3])
    d, _ = view_consistency(about_c, np.eye(4), other)
    r = np.linalg.norm((other[:3, 3] - c)[:2])  # the lever arm about z
    assert d == pytest.approx(2 * np.sin(theta / 2) * r)
