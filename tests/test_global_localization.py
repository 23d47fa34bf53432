"""AMCL's global start (issue 34 item 3): the whole-map search's pieces against brute force
on a small synthetic map (max pooling, the branch and bound equal to the exhaustive search,
non-maximum suppression), the search on a room with and without symmetry, AMCL's global
start with either laser model there and on the twin, and Nav2's uniform start kept in
``paper()``. The real logs: tests/test_localization_real.py."""

from __future__ import annotations

import numpy as np
import pytest

from mmpa.backends.twin.error_model import ErrorModelConfig
from mmpa.backends.twin.twin_maps import laser_pose2d, twin_map
from mmpa.backends.twin.world import SimWorld
from mmpa.core.errors import InvalidInputError
from mmpa.localization.amcl import AMCL
from mmpa.localization.config import AMCLConfig
from mmpa.localization.global_search import (
    GlobalSearch,
    SearchGrid,
    branch_and_bound,
    distinct,
    exhaustive_scores,
    pooled,
)
from mmpa.localization.pose import wrap
from mmpa.localization.refine import ScanRefiner, scan_endpoints
from mmpa.maps.occupancy import OccupancyGrid
from test_amcl_refine import _scan  # a 180 deg scan ray cast in the grid

RES = 0.05


def _room(symmetric: bool = False) -> OccupancyGrid:
    """8 m x 6 m, 5 cm cells, walls one cell thick; an L-shaped wall and a pillar (no
    symmetry), or two pillars placed point-symmetric about the centre (a 180 deg turn about
    it maps the room onto itself)."""
    h, w = 120, 160
    d = np.zeros((h, w), np.int8)
    d[0, :] = d[-1, :] = d[:, 0] = d[:, -1] = 100
    if symmetric:  # pillars at x 1.0-1.3, y 4.5-4.8 m and at the image of that
        d[90:96, 20:26] = 100
        d[h - 96 : h - 90, w - 26 : w - 20] = 100
    else:
        d[30:70, 100] = 100
        d[69, 60:101] = 100
        d[20:23, 30:33] = 100
    return OccupancyGrid(d, RES)


def test_pooled_is_the_window_max() -> None:
    """``P_h[y, x] = max table[y:y+2^h, x:x+2^h]`` (0 past the edge) against a loop."""
    t = np.random.default_rng(0).uniform(size=(13, 9))
    for h, p in enumerate(pooled(t, 3)):
        s = 1 << h
        want = np.array([[t[y : y + s, x : x + s].max() for x in range(9)] for y in range(13)])
        np.testing.assert_array_equal(p, want)
    f = pooled(t > 0.95, 2, np.logical_or)[2]
    assert f[0, 0] == (t[:4, :4] > 0.95).any() and f.dtype == bool


@pytest.mark.parametrize("ratio", [1.0, 0.8])
def test_branch_and_bound_equals_the_exhaustive_search(ratio: float) -> None:
    """Every pose of the grid (20 cm cells, 48 headings) is scored by brute force; the branch
    and bound keeps exactly those within ``ratio`` of the best, with the same scores."""
    grid = _room()
    amcl = AMCL(grid, np.zeros(3), AMCLConfig(), np.random.default_rng(0))
    truth = np.array([2.3, 4.1, 0.7])
    pts = scan_endpoints(_scan(amcl, truth, 91), np.zeros(3), 45)
    sg = SearchGrid.of(grid, 0.2, 0.1)
    n_theta = 48
    full = exhaustive_scores(sg, pts, n_theta)
    best = full.max()
    want = np.argwhere(full >= ratio * best)  # (a, cy, cx)
    poses, scores, nodes = branch_and_bound(sg, pts, n_theta, ratio, levels=3)
    assert scores[0] == best and len(scores) == len(want)
    got = sg.pose(want[:, 0], want[:, 2], want[:, 1], n_theta)
    key = lambda p: sorted(map(tuple, np.round(p, 9)))  # noqa: E731
    assert key(poses) == key(got)
    np.testing.assert_allclose(np.sort(scores), np.sort(full[tuple(want.T)]))
    assert nodes < full.size  # it pruned (the exhaustive search scores every pose)
    # the best grid pose is the truth to a cell and a heading step
    d = poses[0] - truth
    assert np.hypot(d[0], d[1]) < 0.2 and abs(wrap(d[2])) < 2 * np.pi / n_theta
    with pytest.raises(InvalidInputError):
        branch_and_bound(sg, pts, n_theta, 0.0, levels=3)


def test_distinct_keeps_the_best_of_each_neighbourhood() -> None:
    poses = np.array(
        [[0, 0, 0], [0.3, 0, 0], [0.6, 0, 0], [0, 0, 0.3], [0, 0, np.pi - 0.05],
         [0, 0, -np.pi + 0.05]]  # the last two are 0.1 rad apart across +-pi
    )  # fmt: skip
    scores = np.array([0.9, 1.0, 0.8, 0.7, 0.6, 0.5])
    keep = distinct(poses, scores, 0.5, 0.2, 10)
    # 1 (best) suppresses 0 and 2 (< 0.5 m); 3 is 0.3 rad off; 5 is 0.1 rad from 4
    assert keep.tolist() == [1, 3, 4]
    assert distinct(poses, scores, 0.5, 0.2, 2).tolist() == [1, 3]


def _search(grid: OccupancyGrid) -> GlobalSearch:
    c = AMCLConfig()
    return GlobalSearch(
        grid, ScanRefiner(grid, np.zeros(3)), c.global_search_resolution,
        c.global_search_ratio, c.global_hypotheses, c.kld_bin_xy, c.kld_bin_theta, 60,
    )  # fmt: skip


def test_search_finds_the_pose_and_its_mirror() -> None:
    """No symmetry: one hypothesis, the truth (Hector on the ray-cast scan, quantized to
    half a 5 cm cell: measured 16 mm, 0.41 deg). The room turned onto itself by 180 deg
    about its centre: the truth and its image, both kept (19 mm, 0.12 deg each)."""
    for symmetric in (False, True):
        grid = _room(symmetric)
        amcl = AMCL(grid, np.zeros(3), AMCLConfig(), np.random.default_rng(0))
        truth = np.array([2.3, 1.9, 0.4])
        res = _search(grid).search(_scan(amcl, truth))
        assert res.ok and res.seconds < 5
        poses = np.array([h.pose for h in res.hypotheses])
        images = [truth] + ([np.array([8 - 2.3, 6 - 1.9, wrap(0.4 + np.pi)])] if symmetric else [])
        for t in images:
            d = poses - t
            err = np.hypot(d[:, 0], d[:, 1])
            i = int(np.argmin(err))
            assert err[i] < 0.05 and abs(wrap(d[i, 2])) < np.deg2rad(1.0)
        assert len(poses) == len(images)


def test_search_refuses_a_scan_without_beams() -> None:
    grid = _room()
    amcl = AMCL(grid, np.zeros(3), AMCLConfig(), np.random.default_rng(0))
    scan = _scan(amcl, np.array([2.0, 2.0, 0.0]))
    scan.ranges[:] = np.inf
    res = _search(grid).search(scan)
    assert not res.ok and "valid beams" in res.reason and not res.hypotheses


def _drive_room(amcl: AMCL, grid: OccupancyGrid, n: int) -> np.ndarray:
    """A straight drive of ``n`` scans, 0.2 m apart, odometry exact; the position errors."""
    start = np.array([1.5, 1.5, 0.35])
    err = []
    for k in range(n):
        pose = start + k * 0.2 * np.array([np.cos(0.35), np.sin(0.35), 0.0])
        est = amcl.update(pose.copy(), _scan(amcl, pose))
        err.append(np.hypot(*(est.pose[:2] - pose[:2])))
    return np.array(err)


@pytest.mark.parametrize("model", ["likelihood_field_prob", "beam"])
def test_global_start_converges_with_either_laser_model(model: str) -> None:
    """At the defaults the first scan seeds the cloud at the search's hypotheses: within 5
    cm from the first update on (measured at most 24 mm, likelihood field, and 13 mm, beam;
    the ray-cast scans are quantized to half a 5 cm cell); ``paper()`` keeps Nav2's cloud
    uniform over the free space (no search)."""
    grid = _room()
    amcl = AMCL(grid, np.zeros(3), AMCLConfig(laser_model_type=model), np.random.default_rng(1))
    amcl.global_localization()
    err = _drive_room(amcl, grid, 5)
    assert amcl.last_search is not None and amcl.last_search.ok
    assert err.max() < 0.05, err
    nav2 = AMCL(
        grid, np.zeros(3), AMCLConfig.paper().model_copy(update={"laser_model_type": model}),
        np.random.default_rng(1),
    )  # fmt: skip
    nav2.global_localization()
    assert np.std(nav2.particles[:, 0]) > 1.0  # 8 m room: uniform SD 2.3 m
    nav2.update(np.array([1.5, 1.5, 0.35]), _scan(nav2, np.array([1.5, 1.5, 0.35])))
    assert nav2.last_search is None


def test_symmetric_room_keeps_both_hypotheses_until_a_scan_tells() -> None:
    """The symmetric room: after the first scan the cloud holds two clusters (the truth and
    its image) and stays multi-modal while every scan fits both: each keeps about half the
    particles (measured 0.51 / 0.49 after 1 scan, 0.48 / 0.52 after 3 and 0.49 / 0.51 after
    5; with the clusters' masses summed from their particles instead, one cluster had 0.6 %
    after 3 scans: :mod:`mmpa.localization.multimodal`)."""
    grid = _room(symmetric=True)
    amcl = AMCL(grid, np.zeros(3), AMCLConfig(), np.random.default_rng(2))
    amcl.global_localization()
    _drive_room(amcl, grid, 3)
    assert amcl.multimodal
    near = [np.hypot(*(amcl.particles[:, :2] - t).T) < 0.3 for t in ([1.9, 1.7], [6.1, 4.3])]
    assert all(0.3 < m.mean() < 0.7 for m in near)


@pytest.fixture(scope="module")
def world():
    with SimWorld(site="1", errors=ErrorModelConfig(profile="realistic")) as w:
        yield w


def test_global_start_on_the_twin(world) -> None:
    """The twin (realistic profile, its map with the survey warp): AMCL at its defaults
    started globally, the robot driving a 0.3 rad/s arc at 0.2 m/s from site 1: within 5 cm
    of the truth from the first scan on (measured 13-25 mm over 10 scans), one cluster."""
    world.reset("1")
    grid = twin_map(world)
    amcl = AMCL(grid, laser_pose2d(world), AMCLConfig(), np.random.default_rng(0))
    amcl.global_localization()
    errs = []
    for _ in range(10):
        world.base.set_velocity(0.2, 0.3)
        world.step(0.2)
        est = amcl.update(world.odometry.odometry().pose, world.lidar.scan())
        errs.append(np.hypot(*(est.pose[:2] - world.truth.base_pose2d()[:2])))
    world.base.stop()
    assert amcl.last_search is not None and amcl.last_search.ok
    assert max(errs) < 0.05, errs
    assert not amcl.multimodal
