"""Algorithm 1 in the twin: interceptions checked against ground truth; bad input."""

from __future__ import annotations

import numpy as np
import pytest

from mmpa.backends.twin.moving_base import KinematicMovingBase, MovingBaseNoise
from mmpa.backends.twin.world import SimWorld
from mmpa.core.errors import InvalidInputError
from mmpa.fiducial_search import SearchConfig, make_strategy, run_pass


@pytest.fixture(scope="module")
def world():
    w = SimWorld(site="0")
    yield w
    w.close()


def _setup(world: SimWorld) -> tuple[np.ndarray, np.ndarray, float, float]:
    fa = world.scene.fiducial_artifact
    assert fa is not None
    origin = np.array(fa.origin)
    P = origin + np.array(fa.fiducials)  # nominal, from the scene (yaw 0)
    start = np.array([origin[0], origin[1], 0.0])
    return P, start, fa.plate_height, fa.tube_height


@pytest.mark.parametrize("strategy", ["stochastic-tuned", "stochastic"])
def test_one_pass_intercepts_fiducials_confirmed_by_ground_truth(world, strategy) -> None:
    P, start, z_ref, h = _setup(world)
    truth = world.truth.fiducial_positions()
    np.testing.assert_allclose(truth[:, :2], P, atol=1e-9)
    rob = KinematicMovingBase(world, start, MovingBaseNoise(), np.random.default_rng(11))
    # the disturbed start really is off the nominal one
    assert 0 < np.linalg.norm(rob.true_start[:2] - start[:2]) < 0.02
    res = run_pass(
        rob,
        world.nominal,
        P,
        z_ref,
        h,
        start,
        0.02,
        0.0,
        make_strategy(strategy),
        SearchConfig(),
        np.random.default_rng(0),
    )
    assert res.n_intercepted >= 5
    for f in res.fiducials:
        if f.status != "intercepted":
            continue
        # replay the latched state in the twin: the TRUE beam is on this fiducial's reflector
        world.set_kinematic_state(rob.true_base_pose(f.t_hit), f.q_hit)
        name, _ = world.photosensor.hit()
        assert name == f"fiducial_{f.index}_reflector"
        # the nominal arm FK from the TRUE base pose puts the beam on the fiducial within the
        # tube's catch radius (6.35 mm) plus the arm's kinematic error
        pose = rob.true_base_pose(f.t_hit)
        c, s_ = np.cos(pose[2]), np.sin(pose[2])
        mount = world.nominal.T_base_link_arm_base[:2, 3]
        beam = P[f.index] - (f.z + np.array([[1.0, 0], [0, 1.0]]) @ mount)  # R(heading=0)
        on_floor = pose[:2] + np.array([[c, -s_], [s_, c]]) @ (mount + beam)
        assert np.linalg.norm(on_floor - P[f.index]) < 0.008
        # the measured base position is the true one up to that and the base's yaw error
        lever = np.linalg.norm(mount + beam)
        assert np.linalg.norm(f.z - pose[:2]) < 0.008 + abs(pose[2]) * lever
        assert 0 <= f.search_time < 60
    # open loop the base drifts; the interceptions measure that drift (e_i)
    assert np.nanmax([f.position_error for f in res.fiducials]) > 0.001


def test_out_of_reach_zero_and_negative_speed(world) -> None:
    P, start, z_ref, h = _setup(world)
    far = np.vstack([P[:2], P[0] + [0.3, 2.5]])  # the last one is 2.5 m beside the track
    rob = KinematicMovingBase(world, start, MovingBaseNoise(), np.random.default_rng(2))
    res = run_pass(rob, world.nominal, far, z_ref, h, start, 0.03, 0.0, make_strategy("spiral"))
    assert res.fiducials[2].status == "out_of_reach"
    assert res.fiducials[2].n_rounds == 0
    # a standing base: nothing is in reach from the start, reported without moving the arm
    rob = KinematicMovingBase(world, start, MovingBaseNoise(), np.random.default_rng(3))
    q0 = rob.joint_positions()
    res = run_pass(rob, world.nominal, P, z_ref, h, start, 0.0, 0.0, make_strategy("stochastic"))
    assert [f.status for f in res.fiducials] == ["out_of_reach"] * 6
    np.testing.assert_array_equal(rob.joint_positions(), q0)
    # standing next to fiducial 0: it is searched for at most max_search_time
    near = start + np.array([0.8, 0.0, 0.0])
    rob = KinematicMovingBase(world, near, MovingBaseNoise(), np.random.default_rng(4))
    cfg = SearchConfig(max_search_time=5.0)
    res = run_pass(
        rob,
        world.nominal,
        P[:1],
        z_ref,
        h,
        near,
        0.0,
        0.0,
        make_strategy("stochastic-tuned"),
        cfg,
    )
    assert res.fiducials[0].status in ("intercepted", "missed")
    assert res.duration <= 5.0 + 1.0
    with pytest.raises(InvalidInputError, match="speed"):
        run_pass(rob, world.nominal, P, z_ref, h, start, -0.01, 0.0, make_strategy("spiral"))
    with pytest.raises(InvalidInputError, match="fiducials"):
        run_pass(rob, world.nominal, P[:, :1], z_ref, h, start, 0.01, 0.0, make_strategy("spiral"))
    with pytest.raises(InvalidInputError, match="unknown search strategy"):
        make_strategy("zigzag")  # type: ignore[arg-type]


def test_kinematic_mode_keeps_truth_consistent(world) -> None:
    q = np.array(world.nominal.arm.home)
    world.set_kinematic_state(np.array([1.0, 2.0, 0.3]), q, roll=0.01, pitch=-0.02, time=5.0)
    pose = world.truth.base_pose2d()
    np.testing.assert_allclose(pose, [1.0, 2.0, 0.3], atol=1e-9)
    np.testing.assert_allclose(world.arm.joint_positions(), q)
    assert world.time == 5.0
    with pytest.raises(InvalidInputError):
        world.set_kinematic_state(np.array([np.nan, 0, 0]), q)


def test_twin_refuses_joint_paths_outside_limits(world) -> None:
    _, start, _, _ = _setup(world)
    rob = KinematicMovingBase(world, start, MovingBaseNoise(), np.random.default_rng(5))
    q = rob.joint_positions()
    bad = np.vstack([q, q + np.array([0.0, 0.0, 4.0, 0.0, 0.0, 0.0])])  # joint 3 beyond pi
    with pytest.raises(InvalidInputError, match="limits"):
        rob.execute(np.array([0.0, 0.1]), bad)
    np.testing.assert_array_equal(rob.joint_positions(), q)
