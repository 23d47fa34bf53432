"""A* on the inflated grid, pure pursuit, and navigation in the twin on the estimate."""

from __future__ import annotations

import itertools

import numpy as np
import pytest

from mmpa.errors import UnreachableError
from mmpa.localization.localizer import make_localizer
from mmpa.localization.maps import Box2D, rasterize
from mmpa.navigation.follower import FollowerConfig, PathFollower
from mmpa.navigation.mission import NavigateConfig, navigate
from mmpa.navigation.planner import CostMap, PlannerConfig, plan_path
from mmpa.sim.error_model import ErrorModelConfig
from mmpa.sim.twin_maps import laser_pose2d, twin_map, twin_nav_map
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


class _FakeBase:
    def __init__(self) -> None:
        self.v = self.w = 0.0

    def set_velocity(self, v: float, w: float) -> None:
        self.v, self.w = float(v), float(w)

    def stop(self) -> None:
        self.v = self.w = 0.0


class _FakeWorld:
    """A unicycle with perfect odometry and an empty scan: just what navigate() touches."""

    def __init__(self, pose: np.ndarray) -> None:
        from types import SimpleNamespace

        from mmpa.robot.interfaces import LaserScan

        self.time = 0.0
        self.pose = np.asarray(pose, float).copy()
        self.base = _FakeBase()
        n = 4
        self._scan = LaserScan(
            -np.pi, -np.pi + 3 * np.pi / 2, np.pi / 2, 0.0, 0.1, 0.1, 10.0,
            np.full(n, np.inf), np.zeros(n),
        )  # fmt: skip
        self.odometry = SimpleNamespace(odometry=lambda: SimpleNamespace(pose=self.pose.copy()))
        self.lidar = SimpleNamespace(scan=lambda: self._scan)
        self.truth = SimpleNamespace(base_pose2d=lambda: self.pose.copy())

    def step(self, dt: float) -> None:
        th = self.pose[2]
        self.pose += dt * np.array(
            [self.base.v * np.cos(th), self.base.v * np.sin(th), self.base.w]
        )
        self.time += dt


class _JumpyLocalizer:
    """Odometry plus a bias that jumps 2 cm each scan taken while the base stands still: the
    settle scans after every approach find the estimate out of tolerance."""

    name = "jumpy"

    def __init__(self) -> None:
        self.bias = np.zeros(3)
        self._last: np.ndarray | None = None

    def initialize(self, pose, cov=None) -> None:
        pass

    def update(self, odom_pose, scan, force=False):
        odom = np.asarray(odom_pose, float)
        if self._last is not None and np.allclose(odom, self._last):
            self.bias[0] += 0.02
        self._last = odom.copy()

    def pose_at(self, odom_pose) -> np.ndarray:
        return np.asarray(odom_pose, float) + self.bias


def test_navigate_is_not_reached_when_corrections_run_out_out_of_tolerance() -> None:
    """navigate() used to report reached=True once max_corrections ran out, whatever the
    final check said."""
    grid = rasterize([], (-1.0, -1.0, 2.0, 1.0), 0.05)
    cfg = NavigateConfig(initial_scans=0, settle_scans=2, max_corrections=1, timeout=60.0)
    world = _FakeWorld(np.array([0.0, 0.0, 0.0]))
    goal = np.array([0.6, 0.0, 0.0])
    res = navigate(world, _JumpyLocalizer(), grid, goal, cfg)  # type: ignore[arg-type]
    assert not res.reached
    # the same loop with an honest localizer reaches the goal (the fake world is sound)
    world = _FakeWorld(np.array([0.0, 0.0, 0.0]))

    class _Odom(_JumpyLocalizer):
        def update(self, odom_pose, scan, force=False):
            pass

    res = navigate(world, _Odom(), grid, goal, cfg)  # type: ignore[arg-type]
    assert res.reached and res.parking_error_xy < 0.01


def _old_astar(cost: np.ndarray, start: tuple[int, int], goal: tuple[int, int], cw: float):
    """The former pure-Python A* (octile heuristic) of ``plan_path``: cell path (row, col)
    and its cost, or None. Reference for the compiled search."""
    import heapq

    H, W = cost.shape
    blocked = cost >= 253.0
    step_cost = 1.0 + cw * cost / 252.0
    sq2 = np.sqrt(2.0)
    (sr, sc), (gr, gc) = start, goal
    gbest = np.full(cost.shape, np.inf)
    parent = np.full((*cost.shape, 2), -1, dtype=np.int64)
    gbest[sr, sc] = 0.0

    def h(r: int, q: int) -> float:
        dr, dq = abs(r - gr), abs(q - gc)
        return (dr + dq) + (sq2 - 2) * min(dr, dq)

    heap = [(h(sr, sc), 0.0, sr, sc)]
    closed = np.zeros(cost.shape, dtype=bool)
    while heap:
        _, gval, r, q = heapq.heappop(heap)
        if closed[r, q]:
            continue
        closed[r, q] = True
        if (r, q) == (gr, gc):
            break
        for dr, dq in itertools.product((-1, 0, 1), repeat=2):
            nr, nq = r + dr, q + dq
            if (dr, dq) == (0, 0) or not (0 <= nr < H and 0 <= nq < W):
                continue
            if blocked[nr, nq] or closed[nr, nq]:
                continue
            ng = gval + (sq2 if dr and dq else 1.0) * step_cost[nr, nq]
            if ng < gbest[nr, nq]:
                gbest[nr, nq] = ng
                parent[nr, nq] = (r, q)
                heapq.heappush(heap, (ng + h(nr, nq), ng, nr, nq))
    if not closed[gr, gc]:
        return None
    cells = [(gr, gc)]
    while cells[-1] != (sr, sc):
        cells.append(tuple(int(v) for v in parent[cells[-1]]))
    return cells[::-1], float(gbest[gr, gc])


def _path_cost(cells, cost: np.ndarray, cw: float) -> float:
    """Cost of a cell path under the planner's model (independent of both searches)."""
    c = np.array(cells)
    step = np.hypot(*np.diff(c, axis=0).T)
    assert np.all((step == 1) | np.isclose(step, np.sqrt(2)))  # 8-connected moves only
    return float((step * (1.0 + cw * cost[c[1:, 0], c[1:, 1]] / 252.0)).sum())


def _random_map(seed: int):
    rng = np.random.default_rng(seed)
    boxes = [
        Box2D(
            (rng.uniform(0, 6), rng.uniform(0, 4)), (rng.uniform(0.1, 2.0), rng.uniform(0.1, 1.5))
        )
        for _ in range(10)
    ]
    return rasterize(boxes, (0.0, 0.0, 6.0, 4.0), 0.05), rng


@pytest.mark.parametrize("seed", range(6))
def test_compiled_search_matches_the_old_astar_on_random_maps(seed: int) -> None:
    from mmpa.navigation.planner import _farthest_visible, _line_cells

    g, rng = _random_map(seed)
    cm = CostMap(g, PlannerConfig())
    # endpoints clear of the inscribed band by more than endpoint_clearance: plan_path then
    # solves the same problem as the bare search
    free = np.argwhere(cm.dist > 0.75)
    checked = 0
    for _ in range(4):
        (sr, sc), (gr, gc) = free[rng.choice(len(free), 2, replace=False)]
        old = _old_astar(cm.cost, (int(sr), int(sc)), (int(gr), int(gc)), 3.0)
        new = cm.graph(3.0).search((int(sr), int(sc)), (int(gr), int(gc)), [])
        if old is None:
            assert new is None
            continue
        assert new is not None and new[0] == (sr, sc) and new[-1] == (gr, gc)
        # same optimal cost (ties may differ); both evaluated independently of the searches
        assert _path_cost(new, cm.cost, 3.0) == pytest.approx(old[1], rel=1e-9)
        assert _path_cost(old[0], cm.cost, 3.0) == pytest.approx(old[1], rel=1e-9)
        # the vectorized shortcut keeps what checking j one by one from the end keeps
        arr = np.array(new)
        cc = cm.cost[arr[:, 0], arr[:, 1]]
        for i in range(0, len(new) - 1, max(1, len(new) // 7)):
            j = len(new) - 1
            while j > i + 1:
                r, q = _line_cells(new[i], new[j])
                if cm.cost[r, q].max() <= max(120.0, cc[i], cc[j]):
                    break
                j -= 1
            assert _farthest_visible(arr, i, cm.cost, 120.0, cc) == j
        # the final path's length: the old planner's (its A* path, shortcut) within 2 %
        keep, i, c_old = [0], 0, cm.cost[tuple(np.array(old[0]).T)]
        while i < len(old[0]) - 1:
            j = len(old[0]) - 1
            while j > i + 1:
                r, q = _line_cells(old[0][i], old[0][j])
                if cm.cost[r, q].max() <= max(120.0, c_old[i], c_old[j]):
                    break
                j -= 1
            keep.append(j)
            i = j
        lo = np.array([g.cell_to_world(old[0][k][1], old[0][k][0]) for k in keep])
        p = plan_path(cm, lo[0], lo[-1])
        length = np.linalg.norm(np.diff(p, axis=0), axis=1).sum()
        old_len = np.linalg.norm(np.diff(lo, axis=0), axis=1).sum()
        assert abs(length - old_len) <= 0.02 * old_len, (length, old_len)
        checked += 1
    assert checked >= 1


def test_start_in_the_inscribed_band_is_opened_for_that_search_only() -> None:
    g, _ = _random_map(3)
    cm = CostMap(g, PlannerConfig())
    band = np.argwhere((cm.cost == 253.0) & (cm.dist > 0.3))
    goal = np.argwhere(cm.dist > 0.75)[-1]
    before = cm.graph(3.0).csr.data.copy()
    rows, cols = np.mgrid[0 : g.height, 0 : g.width]
    for s in band[:: max(1, len(band) // 10)]:
        # the old planner's clearance: band cells within 0.35 m of the endpoints cost 200
        cost2 = cm.cost.copy()
        opened = []
        for r, q in (s, goal):
            near = ((rows - r) ** 2 + (cols - q) ** 2 <= (0.35 / 0.05) ** 2) & (cost2 == 253.0)
            cost2[near] = 200.0
            opened += [(int(a), int(b), 200.0) for a, b in zip(rows[near], cols[near], strict=True)]
        old = _old_astar(cost2, tuple(s), tuple(goal), 3.0)
        new = cm.graph(3.0).search(tuple(s), tuple(goal), opened)
        assert (old is None) == (new is None)
        if old is not None:
            break
    assert old is not None and new is not None
    assert _path_cost(new, cost2, 3.0) == pytest.approx(old[1], rel=1e-9)
    assert np.array_equal(cm.graph(3.0).csr.data, before)  # closed again afterwards
    p = plan_path(cm, g.cell_to_world(s[1], s[0]), g.cell_to_world(goal[1], goal[0]))
    assert np.allclose(p[0], g.cell_to_world(s[1], s[0]))
