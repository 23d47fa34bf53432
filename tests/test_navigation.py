"""A* on the inflated grid, pure pursuit, and navigation in the twin on the estimate."""

from __future__ import annotations

import itertools

import numpy as np
import pytest

from mmpa.errors import UnreachableError
from mmpa.localization.localizer import make_localizer
from mmpa.localization.maps import Box2D, rasterize
from mmpa.navigation.follower import FollowerConfig, PathFollower
from mmpa.navigation.mission import (
    NavigateConfig,
    laser_pose2d,
    navigate,
    twin_map,
    twin_nav_map,
)
from mmpa.navigation.planner import CostMap, PlannerConfig, plan_path
from mmpa.sim.error_model import ErrorModelConfig
from mmpa.sim.world import SimWorld


def test_astar_goes_around_a_wall_and_keeps_clear() -> None:
    walls = [
        Box2D((0.0, 0.0), (0.1, 3.0)),
        Box2D((0.0, 2.5), (8.0, 0.1)),
        Box2D((0.0, -2.5), (8.0, 0.1)),
    ]
    g = rasterize(walls, (-4, -3, 4, 3), 0.05)
    cm = CostMap(g, PlannerConfig())
    path = plan_path(cm, np.array([-2.0, 0.0]), np.array([2.0, 0.0]))
    assert np.allclose(path[0], [-2, 0]) and np.allclose(path[-1], [2, 0])
    # densify and check every point stays >= inscribed radius from obstacles
    pts = np.vstack([np.linspace(a, b, 50) for a, b in itertools.pairwise(path)])
    c, r = g.world_to_cell(pts)
    assert cm.dist[r, c].min() >= 0.3 - 0.05
    length = np.sum(np.linalg.norm(np.diff(path, axis=0), axis=1))
    assert 2 * np.hypot(2.0, 1.8) - 0.1 < length < 8.0  # around the wall end, not through it
    blocked = rasterize([Box2D((0.0, 0.0), (0.1, 6.0))], (-4, -3, 4, 3), 0.05)
    with pytest.raises(UnreachableError):
        plan_path(CostMap(blocked), np.array([-2.0, 0.0]), np.array([2.0, 0.0]))


def test_pure_pursuit_follows_a_line() -> None:
    f = PathFollower(np.array([[0.0, 0.0], [5.0, 0.0]]), np.array([5.0, 0.0, 0.0]))
    pose = np.array([0.0, 0.3, 0.0])
    for _ in range(600):
        v, w, _done = f.command(pose)
        pose = pose + 0.05 * np.array([v * np.cos(pose[2]), v * np.sin(pose[2]), w])
        if f.final_phase:
            break
    assert f.final_phase and abs(pose[1]) < 0.05


def test_final_approach_ends_with_the_goal_abeam() -> None:
    """A diff-drive base cannot creep sideways: with the goal abeam (|ex| <= pos_tol) and 4.5
    mm to the side (inside the creeping band, 2 pos_tol), the position phase ends and the base
    turns to the goal heading (the caller's settle check judges the pose), instead of creeping
    back and forth along its heading until the final timeout. Off: the old creep."""
    goal = np.array([1.0, 0.0, 0.5])
    pose = np.array([1.0005, -0.0045, 0.0])  # robot frame: ex = -0.5 mm, ey = 4.5 mm
    for abeam_done, moves in ((True, False), (False, True)):
        f = PathFollower(
            np.array([[0.0, 0.0], [1.0, 0.0]]), goal, FollowerConfig(abeam_done=abeam_done)
        )
        v, w, done = f.command(pose)
        assert f.final_phase and not done
        assert (abs(v) > 0) == moves and (abs(w) > 0) != moves, (v, w)


# realistic (the default): the 10 mm reflector survey, the range walk and the lidar mount
# error (nominal mount here, 4 mm off for seed 0) leave 8.4 mm of localization error at site 2
# (seed 0; 9.6 mm before the honest reflector fix; DESIGN.md expects 1.5-9.3 mm for this class
# of twin), 7.9 mm parking; the reference profile keeps the filter's own 6 mm (0.7 measured)
@pytest.mark.parametrize(("profile", "loc_tol"), [("realistic", 0.02), ("reference", 0.006)])
def test_navigate_on_the_estimate_parks_at_the_site(profile: str, loc_tol: float) -> None:
    with SimWorld(site="0", errors=ErrorModelConfig(profile=profile)) as world:
        grid = twin_map(world)
        loc = make_localizer("enhanced", grid, laser_pose2d(world), np.random.default_rng(0))
        loc.initialize(world.truth.base_pose2d() + np.array([0.05, -0.05, 0.03]))
        goal = world.scene.site("2").pose2d
        cm = CostMap(twin_nav_map(world))
        res = navigate(
            world, loc, grid, goal, NavigateConfig(scan_rate=5.0, timeout=60.0), costmap=cm
        )
    assert res.reached
    assert res.parking_error_xy < 0.01 and res.parking_error_yaw < 0.01
    assert np.hypot(*res.localization_error[:2]) < loc_tol
