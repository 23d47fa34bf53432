"""A* on the inflated grid, pure pursuit, and navigation in the twin on the estimate."""

from __future__ import annotations

import itertools

import numpy as np
import pytest

from mmpa.backends.twin.error_model import ErrorModelConfig
from mmpa.backends.twin.twin_maps import laser_pose2d, twin_map, twin_nav_map
from mmpa.backends.twin.world import SimWorld
from mmpa.core.errors import UnreachableError
from mmpa.localization.localizer import make_localizer
from mmpa.maps.occupancy import Box2D, rasterize
from mmpa.missions.navigate import NavigateConfig, navigate, staged_path
from mmpa.navigation.follower import PathFollower, within_tolerance
from mmpa.navigation.planner import CostMap, PlannerConfig, plan_path


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


def _drive_final(f: PathFollower, truth: np.ndarray, bias=None, jump_at=None, ticks=3000):
    """Unicycle at 20 Hz under ``f``; the follower sees ``truth + bias(truth)`` (and a 5 cm
    jump of the estimate at tick ``jump_at``). Returns (final truth, final estimate, ticks,
    the commands)."""
    dt = 0.05
    cmds = []
    for k in range(ticks):
        est = truth + (np.zeros(3) if bias is None else bias(truth))
        if k == jump_at:
            est = est + np.array([0.05, 0.05, 0.0])
        v, w, done = f.command(est)
        cmds.append((v, w, f.phase))
        if done:
            return truth, est, k, cmds
        truth = truth + dt * np.array([v * np.cos(truth[2]), v * np.sin(truth[2]), w])
    raise AssertionError("the final approach did not finish")


@pytest.mark.parametrize(
    ("start", "heading"),
    [((0.05, 0.12), 2.5), ((-0.1, -0.08), -1.0), ((0.14, 0.0), 3.1), ((0.002, 0.0045), 0.0)],
)
def test_final_approach_converges_from_any_side(start, heading) -> None:
    """From anywhere inside the approach radius (beside the goal, in front of it, behind it,
    the goal abeam 4.5 mm to the side), at any heading, the final approach ends with the
    pose inside the tolerance it reports (``within_tolerance``): a differential base removes
    a lateral offset by backing off along the goal line and creeping in (pure pursuit), not
    by creeping along its heading. Kinematic unicycle, exact estimate: no margin needed
    beyond the tolerance itself (3 mm, 0.17 deg)."""
    goal = np.array([1.0, 0.5, 0.7])
    c, s = np.cos(goal[2]), np.sin(goal[2])
    p0 = goal[:2] + start[0] * np.array([c, s]) + start[1] * np.array([-s, c])
    f = PathFollower(np.array([[0.0, 0.0], goal[:2]]), goal)
    truth, _, k, cmds = _drive_final(f, np.array([*p0, goal[2] + heading]))
    assert within_tolerance(truth, goal, f.cfg.final)
    assert k * 0.05 < f.cfg.final_timeout
    if start == (0.002, 0.0045):  # abeam: the lateral 4.5 mm needs a back-off
        assert any(ph == "backoff" and v < 0 for v, _, ph in cmds)


def test_final_approach_turns_before_it_creeps_and_survives_a_jump() -> None:
    """The turn on the spot happens where the approach begins (>= 10 cm from the goal), so
    a heading-dependent estimate bias (a lidar mount 4 mm off: ``R(theta) b``) shifts the
    estimate before the creep, which drives it out; a one-tick 7 cm jump of the estimate
    during the creep decides nothing (decisions on the mean of standing ticks)."""
    goal = np.array([0.0, 0.0, 0.0])
    b = np.array([0.004, -0.002])

    def bias(t):
        c, s = np.cos(t[2]), np.sin(t[2])
        return np.array([c * b[0] - s * b[1], s * b[0] + c * b[1], 0.0])

    f = PathFollower(np.array([[1.0, 1.0], [0.0, 0.0]]), goal)
    start = np.array([0.1, 0.08, 2.0])  # ahead and beside the goal, facing away
    _, est, _, cmds = _drive_final(f, start, bias=bias, jump_at=150)
    assert within_tolerance(est, goal, f.cfg.final)  # the robot believes it is there
    turns = [i for i, (v, w, _) in enumerate(cmds) if v == 0 and abs(w) > 0.1]
    assert turns and turns[-1] < next(i for i, (v, _, _) in enumerate(cmds) if v != 0)


def test_staged_path_ends_along_the_goal_heading() -> None:
    """The plan's last stretch runs ``staging`` m along the goal heading (behind the goal
    when free, in front of it when a wall is behind), else the plain plan."""
    g = rasterize([Box2D((-0.2, -3.0), (0.1, 6.0))], (-4, -3, 4, 3), 0.05)  # wall at x = -0.2
    cm = CostMap(g, PlannerConfig())
    start = np.array([3.0, 2.0])
    for goal, side in (((1.5, 0.0, 0.0), 1.0), ((0.6, 0.0, 0.0), -1.0)):
        goal = np.array(goal)
        path = staged_path(cm, start, goal, 0.5)
        last = path[-1] - path[-2]
        assert np.allclose(path[-1], goal[:2])
        h = np.array([np.cos(goal[2]), np.sin(goal[2])])
        # behind the goal (driving in forward), or in front (backing in) where the wall is
        assert np.allclose(last, side * 0.5 * h, atol=1e-9), (last, side)
    assert len(staged_path(cm, np.array([1.3, 0.1]), np.array([1.5, 0.0, 0.0]), 0.5)) >= 2


# realistic (the default): the 10 mm reflector survey, the range walk and the lidar mount
# error (nominal mount here, 4 mm off for seed 0) leave 8-10 mm of localization error at site 2
# (seed 0; DESIGN.md expects 1.5-9.3 mm for this class of twin); the reference profile keeps
# the filter's own error (0.7 mm measured). The drive settles by construction (the final
# approach along the goal line, benchmarks/bench_drives.py: 200 seeded drives), so the
# parking error is the localization error plus at most the settle tolerance (4.5 mm): the
# triangle inequality, no CPU-dependent margin
# reference slow (5 s: the suite budget); the default profile, realistic, stays in the default run
@pytest.mark.parametrize(
    ("profile", "loc_tol"),
    [("realistic", 0.02), pytest.param("reference", 0.006, marks=pytest.mark.slow)],
)
def test_navigate_on_the_estimate_parks_at_the_site(profile: str, loc_tol: float) -> None:
    with SimWorld(site="0", errors=ErrorModelConfig(profile=profile)) as world:
        grid = twin_map(world)
        loc = make_localizer("enhanced", grid, laser_pose2d(world), np.random.default_rng(0))
        loc.initialize(world.truth.base_pose2d() + np.array([0.05, -0.05, 0.03]))
        goal = world.scene.site("2").pose2d
        cm = CostMap(twin_nav_map(world))
        res = navigate(
            world,
            loc,
            grid,
            goal,
            NavigateConfig(scan_rate=5.0, timeout=60.0),
            costmap=cm,
            truth=world.truth.base_pose2d,
        )
    assert res.reached, res.reason
    assert res.reason == "" and res.settle_error_xy <= 1.5 * 0.003
    loc_xy = float(np.hypot(*res.localization_error[:2]))
    assert loc_xy < loc_tol
    # truth - goal <= (truth - estimate) + (estimate - goal); 0.5 mm for the last 0.2 s step
    assert res.parking_error_xy <= loc_xy + 1.5 * 0.003 + 0.0005
    assert res.parking_error_yaw < 0.01


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
    res = navigate(world, _JumpyLocalizer(), grid, goal, cfg, truth=world.truth.base_pose2d)  # type: ignore[arg-type]
    assert not res.reached
    # the same loop with an honest localizer reaches the goal (the fake world is sound)
    world = _FakeWorld(np.array([0.0, 0.0, 0.0]))

    class _Odom(_JumpyLocalizer):
        def update(self, odom_pose, scan, force=False):
            pass

    res = navigate(world, _Odom(), grid, goal, cfg, truth=world.truth.base_pose2d)  # type: ignore[arg-type]
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


def _floor_map(seed: int):
    """A 20 m x 10 m floor: a corridor along x with 1 m doors into rows of rooms on both sides
    (one room closed off), furniture in the rooms."""
    rng = np.random.default_rng(seed)
    W, H, t = 20.0, 10.0, 0.15
    boxes = [
        Box2D((W / 2, 0.0), (W, t)),
        Box2D((W / 2, H), (W, t)),
        Box2D((0.0, H / 2), (t, H)),
        Box2D((W, H / 2), (t, H)),
    ]
    for y in (4.0, 6.0):  # corridor walls, a door per room except the first room below
        for k, x in enumerate(np.arange(0.0, W, 5.0)):
            door = x + rng.uniform(1.0, 3.5)
            if y == 4.0 and k == 0:
                boxes.append(Box2D((x + 2.5, y), (5.0, t)))
                continue
            boxes.append(Box2D(((x + door) / 2, y), (door - x, t)))
            boxes.append(Box2D(((door + 1.0 + x + 5.0) / 2, y), (x + 4.0 - door, t)))
    for x in np.arange(5.0, W, 5.0):  # partitions
        boxes += [Box2D((x, 2.0), (t, 4.0)), Box2D((x, 8.0), (t, 4.0))]
    for _ in range(8):
        boxes.append(
            Box2D(
                (rng.uniform(0.5, W - 0.5), rng.choice([rng.uniform(1, 3), rng.uniform(7, 9)])),
                (rng.uniform(0.4, 1.2), rng.uniform(0.4, 1.0)),
            )
        )
    return rasterize(boxes, (-0.3, -0.3, W + 0.3, H + 0.3), 0.05), rng


def _reference_costs(cost: np.ndarray, start: tuple[int, int], cw: float) -> np.ndarray:
    """Cheapest cost from ``start`` to every cell (H, W) by a plain full Dijkstra on a graph
    built here from the planner's model (independent of its graph, radii and proofs)."""
    from scipy import sparse
    from scipy.sparse import csgraph

    H, W = cost.shape
    rr, qq = np.mgrid[0:H, 0:W]
    src, dst, w = [], [], []
    for dr, dq in itertools.product((-1, 0, 1), repeat=2):
        if (dr, dq) == (0, 0):
            continue
        r2, q2 = rr + dr, qq + dq
        ok = (r2 >= 0) & (r2 < H) & (q2 >= 0) & (q2 < W) & (cost < 254)
        ok[ok] &= cost[r2[ok], q2[ok]] < 253  # moves into the inscribed band: never
        src.append((rr * W + qq)[ok])
        dst.append((r2 * W + q2)[ok])
        w.append(np.hypot(dr, dq) * (1.0 + cw * cost[r2[ok], q2[ok]] / 252.0))
    m = sparse.csr_matrix(
        (np.concatenate(w), (np.concatenate(src), np.concatenate(dst))), shape=(H * W, H * W)
    )
    return csgraph.dijkstra(m, indices=start[0] * W + start[1]).reshape(H, W)


@pytest.mark.parametrize("radii", ["estimated", "redo", "full"])
def test_two_ended_search_is_optimal_on_a_floor(monkeypatch, radii: str) -> None:
    """The search from both ends with its optimality proof finds the optimal cost of a plain
    Dijkstra, also between cells in the inscribed band (opened, as plan_path does), and None
    into the closed room; the graph is closed again afterwards. ``redo``: radii that just
    miss the proof (``a + b = d* + w_max - 0.5``: the balls meet, the proof fails, the
    searches are redone); ``full``: radii too small to meet (the full search decides)."""
    import mmpa.navigation.planner as planner

    if radii != "estimated":
        monkeypatch.setattr(planner, "_ESTIMATE_SCALE", 1.0 if radii == "redo" else 0.0)
        monkeypatch.setattr(planner, "_ESTIMATE_MARGIN", 0.0)
    calls: list[int] = []
    real = planner.csgraph.dijkstra

    def counting(*args, **kwargs):
        calls[-1] += 1
        return real(*args, **kwargs)

    monkeypatch.setattr(planner, "csgraph", type("Counted", (), {"dijkstra": counting}))
    g, rng = _floor_map(1)
    cm = CostMap(g, PlannerConfig())
    graph = cm.graph(3.0)
    data0, rev0 = graph.csr.data.copy(), graph.rev.data.copy()
    free = np.argwhere(cm.dist > 0.5)
    band = np.argwhere((cm.cost == 253.0) & (cm.dist > 0.25))
    pairs = [tuple(free[rng.choice(len(free), 2)]) for _ in range(10)]
    pairs += [tuple(band[rng.choice(len(band), 2)]) for _ in range(4)]
    xy = g.cell_to_world(free[:, 1], free[:, 0])
    closed = free[(xy[:, 0] < 4.5) & (xy[:, 1] < 3.5)]  # the room without a door
    pairs.append((closed[0], free[-1]))
    rows, cols = np.mgrid[0 : g.height, 0 : g.width]
    n_unreachable = 0
    for s, e in pairs:
        s, e = (int(s[0]), int(s[1])), (int(e[0]), int(e[1]))
        cost2, opened = cm.cost.copy(), []
        for r, q in (s, e):  # plan_path's endpoint clearance
            near = ((rows - r) ** 2 + (cols - q) ** 2 <= (0.35 / 0.05) ** 2) & (cost2 == 253.0)
            cost2[near] = 200.0
            opened += [(int(a), int(b), 200.0) for a, b in zip(rows[near], cols[near], strict=True)]
        truth = _reference_costs(cost2, s, 3.0)[e]
        if radii == "redo":  # the search's total radius a + b = estimate + w_max
            monkeypatch.setattr(graph, "estimate", lambda *_, t=truth: t - 0.5)
        calls.append(0)
        cells = graph.search(s, e, opened)
        if not np.isfinite(truth):
            assert cells is None
            n_unreachable += 1
            continue
        assert cells is not None and cells[0] == s and cells[-1] == e
        assert _path_cost(cells, cost2, 3.0) == pytest.approx(truth, rel=1e-9)
        assert np.array_equal(graph.csr.data, data0) and np.array_equal(graph.rev.data, rev0)
    assert n_unreachable >= 1
    # which branches ran (dijkstra calls: estimate, forward, backward, redo x2, full)
    if radii == "estimated":
        assert calls.count(3) >= 8  # most pairs proven on the first try
    elif radii == "redo":
        # forward and backward twice (the estimate is patched): redone with mu + w_max
        assert calls.count(4) >= 8
    else:
        assert calls.count(4) >= 8  # the balls never met: the full search


def test_plan_path_on_a_floor_is_optimal_and_clear() -> None:
    """plan_path (two-ended search + shortcut) between rooms: the path's cost (cells of the
    optimal search path) equals the reference Dijkstra's, and the shortcut path keeps to the
    non-lethal cells."""
    g, rng = _floor_map(2)
    cm = CostMap(g, PlannerConfig())
    free = np.argwhere(cm.dist > 0.6)
    for _ in range(3):
        s, e = free[rng.choice(len(free), 2)]
        truth = _reference_costs(cm.cost, (int(s[0]), int(s[1])), 3.0)[int(e[0]), int(e[1])]
        if not np.isfinite(truth):
            with pytest.raises(UnreachableError):
                plan_path(cm, g.cell_to_world(s[1], s[0]), g.cell_to_world(e[1], e[0]))
            continue
        cells = cm.graph(3.0).search((int(s[0]), int(s[1])), (int(e[0]), int(e[1])), [])
        assert _path_cost(cells, cm.cost, 3.0) == pytest.approx(truth, rel=1e-9)
        p = plan_path(cm, g.cell_to_world(s[1], s[0]), g.cell_to_world(e[1], e[0]))
        for a, b in itertools.pairwise(p):
            pts = a + np.linspace(0, 1, 200)[:, None] * (b - a)
            c, r = g.world_to_cell(pts)
            assert cm.cost[r, c].max() < 254
