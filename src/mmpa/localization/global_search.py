"""Global localization by a whole-map correlative scan search (improvement, issue 34): the
poses where one scan fits the map, the seeds of AMCL's global start.

Olson 2009 ("Real-time correlative scan matching") and Cartographer's
``FastCorrelativeScanMatcher2D`` (Hess et al. 2016): the scan's endpoints ``p_i`` (base frame)
are scored at every pose of a grid over the whole map,

    ``s(x, y, theta_a) = (1 / k) sum_i T[cy + oy_ai, cx + ox_ai]``,

``T = exp(-d^2 / (2 sigma^2))`` per cell of the search grid (``d`` the distance from the cell
to the nearest occupied cell, m; 0 off the map), ``(cx, cy)`` the cell whose centre is the
candidate's position, ``(ox_ai, oy_ai) = round(R(theta_a) p_i / res)`` the endpoint's cell
offset at the heading ``theta_a = -pi + a dtheta``, ``dtheta = res / r90`` (``r90`` the
90th percentile of the endpoints' ranges: a heading step moves those endpoints by at most
one cell). Candidates are the centres of the free cells (a robot stands in free space).

Branch and bound: a node at level ``h`` is a heading and a window of ``2^h x 2^h`` cells
anchored at ``(cx, cy)``; its bound is the same sum on ``P_h[y, x] = max T[y:y+2^h,
x:x+2^h]`` (max-pooled, :func:`pooled`), never below the score of any pose of the window
(each endpoint's cell lies in the pooled window of its offset). Nodes whose bound is below
``ratio`` times the best score found are dropped, the others split into their four child
windows, level by level (breadth first, every heading at once); a few greedy dives from the
best coarse nodes give the first best score. The leaves kept are EXACTLY every pose of the
grid whose score is at least ``ratio`` times the best (:func:`exhaustive_scores` is the
brute force it equals). Non-maximum suppression (:func:`distinct`) keeps the best pose of
each ``sep_xy`` x ``sep_theta`` neighbourhood (AMCL's cluster bins), and Hector
(:class:`~mmpa.localization.refine.ScanRefiner`) refines each to the map; its gates refuse
the poses that fit nothing.

Units: m, rad; poses ``[x, y, theta]`` of ``base_link`` in ``map``.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from mmpa.core.errors import InvalidInputError
from mmpa.core.geometry import Array
from mmpa.localization.pose import wrap
from mmpa.localization.refine import MIN_BEAMS, ScanRefiner, scan_endpoints
from mmpa.maps.occupancy import OccupancyGrid
from mmpa.robot.interfaces import LaserScan

__all__ = [
    "GlobalSearch",
    "Hypothesis",
    "SearchGrid",
    "SearchResult",
    "branch_and_bound",
    "distinct",
    "exhaustive_scores",
    "pooled",
]

_log = logging.getLogger(__name__)
CHUNK = 1 << 14  # nodes scored together (their (chunk, k) index arrays stay small)


def pooled(table: Array, levels: int, reduce: Callable = np.maximum) -> list[Array]:
    """``[P_0 .. P_levels]``: ``P_0 = table`` (H, W); ``P_h[y, x]`` the ``reduce`` (max) of
    ``table[y:y+2^h, x:x+2^h]`` (cells past the edge count as 0 / False)."""
    out = [table]
    for h in range(1, levels + 1):
        s = 1 << (h - 1)
        p = out[-1]
        q = np.zeros_like(p)
        q[:, : p.shape[1] - s] = p[:, s:]
        a = reduce(p, q)
        b = np.zeros_like(a)
        b[: a.shape[0] - s] = a[s:]
        out.append(reduce(a, b))
    return out


@dataclass(frozen=True)
class SearchGrid:
    """The score table ``T`` (H, W) of the search grid (module docstring), its free cells,
    cell size ``res`` (m) and the world position of cell ``(0, 0)``'s lower corner."""

    table: Array
    free: Array
    res: float
    origin: tuple[float, float]

    @classmethod
    def of(cls, grid: OccupancyGrid, res: float, sigma: float) -> SearchGrid:
        """The search grid of ``grid`` at ``res`` m (a whole multiple ``f`` of the map's cell;
        ``res`` below it: the map's): ``T`` the max and the free mask the any over each
        ``f x f`` block, ``d`` the map's distance field (clipped at ``4 sigma``)."""
        f = max(1, round(res / grid.resolution))
        d = grid.distance_field(max(4.0 * sigma, 2 * grid.resolution))
        t = np.exp(-0.5 * (d / sigma) ** 2)
        h, w = -(-t.shape[0] // f), -(-t.shape[1] // f)
        tp = np.zeros((h * f, w * f))
        tp[: t.shape[0], : t.shape[1]] = t
        fp = np.zeros((h * f, w * f), dtype=bool)
        fp[: t.shape[0], : t.shape[1]] = grid.free
        t_blk = tp.reshape(h, f, w, f).max(axis=(1, 3))
        f_blk = fp.reshape(h, f, w, f).any(axis=(1, 3))
        o = (float(grid.origin[0]), float(grid.origin[1]))
        return cls(t_blk, f_blk, grid.resolution * f, o)

    def offsets(self, pts: Array, n_theta: int) -> Array:
        """(A, k, 2) int cell offsets ``round(R(theta_a) p_i / res)`` of the endpoints ``pts``
        (k, 2) at the headings ``-pi + a 2 pi / n_theta``."""
        th = -np.pi + np.arange(n_theta) * (2 * np.pi / n_theta)
        c, s = np.cos(th)[:, None], np.sin(th)[:, None]
        x = (c * pts[None, :, 0] - s * pts[None, :, 1]) / self.res
        y = (s * pts[None, :, 0] + c * pts[None, :, 1]) / self.res
        return np.stack([np.rint(x), np.rint(y)], axis=-1).astype(np.int64)

    def pose(self, a: Array, cx: Array, cy: Array, n_theta: int) -> Array:
        """(n, 3) poses of the grid's heading indices ``a`` and cells ``(cx, cy)``."""
        x = self.origin[0] + (np.asarray(cx) + 0.5) * self.res
        y = self.origin[1] + (np.asarray(cy) + 0.5) * self.res
        th = -np.pi + np.asarray(a) * (2 * np.pi / n_theta)
        return np.column_stack([x, y, th])


def _scores(table: Array, pad: int, off: Array, a: Array, cx: Array, cy: Array) -> Array:
    """``(1 / k) sum_i table[cy + oy_ai + pad, cx + ox_ai + pad]`` per node, ``table`` padded
    with ``pad`` zero cells on every side (an index past it is clipped into the zero ring:
    ``pad`` >= the window of a level's table, so a window clipped there lies wholly off the
    map), in chunks."""
    h, w = table.shape
    flat = table.ravel()
    out = np.empty(len(a))
    for i in range(0, len(a), CHUNK):
        j = slice(i, i + CHUNK)
        o = off[a[j]]
        col = np.clip(cx[j, None] + o[:, :, 0] + pad, 0, w - 1)
        row = np.clip(cy[j, None] + o[:, :, 1] + pad, 0, h - 1)
        out[j] = flat[row * w + col].mean(axis=1)
    return out


def exhaustive_scores(sg: SearchGrid, pts: Array, n_theta: int) -> Array:
    """Brute force: the score (A, H, W) of every heading and cell (-inf off the free cells)."""
    off = sg.offsets(pts, n_theta)
    h, w = sg.table.shape
    cy, cx = np.mgrid[0:h, 0:w]
    out = np.full((n_theta, h, w), -np.inf)
    t = np.pad(sg.table, 1)
    for a in range(n_theta):
        s = _scores(t, 1, off, np.full(h * w, a), cx.ravel(), cy.ravel()).reshape(h, w)
        out[a][sg.free] = s[sg.free]
    return out


def _children(a: Array, cx: Array, cy: Array, s: int) -> tuple[Array, Array, Array]:
    """The four child windows (anchors ``+0 / +s`` in x and y) of each node."""
    dx = np.array([0, s, 0, s])
    dy = np.array([0, 0, s, s])
    return (
        np.repeat(a, 4),
        (cx[:, None] + dx).ravel(),
        (cy[:, None] + dy).ravel(),
    )


def _dive(
    tables: list[Array],
    pad: int,
    frees: list[Array],
    off: Array,
    node: tuple[int, int, int],
    top: int,
) -> float:
    """The score of the leaf reached from ``node`` = (a, cx, cy) at the top level by always
    entering the child of the highest bound (a lower bound of the best score)."""
    a, cx, cy = (np.array([v]) for v in node)
    for h in range(top, 0, -1):
        a, cx, cy = _children(a, cx, cy, 1 << (h - 1))
        ok = _inside_free(frees[h - 1], cx, cy)
        if not ok.any():
            return -np.inf
        a, cx, cy = a[ok], cx[ok], cy[ok]
        b = _scores(tables[h - 1], pad, off, a, cx, cy)
        k = int(np.argmax(b))
        a, cx, cy = a[k : k + 1], cx[k : k + 1], cy[k : k + 1]
    return float(_scores(tables[0], pad, off, a, cx, cy)[0])


def _inside_free(free: Array, cx: Array, cy: Array) -> Array:
    h, w = free.shape
    ok = (cx < w) & (cy < h)
    ok[ok] = free[cy[ok], cx[ok]]
    return ok


def branch_and_bound(
    sg: SearchGrid, pts: Array, n_theta: int, ratio: float, levels: int, dives: int = 8
) -> tuple[Array, Array, int]:
    """Every grid pose whose score is at least ``ratio`` times the best (module docstring):
    ``(poses (n, 3), scores (n,), nodes scored)``, best first."""
    if not 0 < ratio <= 1:
        raise InvalidInputError(f"ratio must be in (0, 1], got {ratio}")
    off = sg.offsets(pts, n_theta)
    s = 1 << levels
    tables = pooled(np.pad(sg.table, s), levels)  # s zero cells on every side: _scores
    frees = pooled(sg.free, levels, np.logical_or)
    h, w = sg.table.shape
    gy, gx = np.mgrid[0:h:s, 0:w:s]
    gx, gy = gx.ravel(), gy.ravel()
    keep = frees[levels][gy, gx]
    gx, gy = gx[keep], gy[keep]
    a = np.repeat(np.arange(n_theta), len(gx))
    cx, cy = np.tile(gx, n_theta), np.tile(gy, n_theta)
    bound = _scores(tables[levels], s, off, a, cx, cy)
    nodes = len(a)
    first = np.argsort(-bound)[:dives]
    best = max(_dive(tables, s, frees, off, (a[i], cx[i], cy[i]), levels) for i in first)
    for lv in range(levels, 0, -1):
        k = bound >= ratio * best
        a, cx, cy = _children(a[k], cx[k], cy[k], 1 << (lv - 1))
        ok = _inside_free(frees[lv - 1], cx, cy)
        a, cx, cy = a[ok], cx[ok], cy[ok]
        bound = _scores(tables[lv - 1], s, off, a, cx, cy)
        nodes += len(a)
        if lv == 1:
            best = max(best, float(bound.max(initial=-np.inf)))
    k = np.flatnonzero(bound >= ratio * best)
    k = k[np.argsort(-bound[k], kind="stable")]
    return sg.pose(a[k], cx[k], cy[k], n_theta), bound[k], nodes


def distinct(poses: Array, scores: Array, sep_xy: float, sep_theta: float, k: int) -> Array:
    """Indices of up to ``k`` poses, best score first, none within ``sep_xy`` (both axes) and
    ``sep_theta`` of a better one kept (non-maximum suppression)."""
    order = np.argsort(-np.asarray(scores), kind="stable")
    kept: list[int] = []
    for i in order:
        if kept:
            d = poses[kept] - poses[i]
            near = (
                (np.abs(d[:, 0]) < sep_xy)
                & (np.abs(d[:, 1]) < sep_xy)
                & (np.abs(wrap(d[:, 2])) < sep_theta)
            )
            if near.any():
                continue
        kept.append(int(i))
        if len(kept) >= k:
            break
    return np.array(kept, dtype=np.int64)


@dataclass(frozen=True)
class Hypothesis:
    """A pose where the scan fits: ``pose`` [x, y, theta], its covariance (3, 3) (Hector's
    ``s^2 H^-1``), the search's ``score`` (0..1) and Hector's ``match_score`` (0..1)."""

    pose: Array
    cov: Array
    score: float
    match_score: float


@dataclass(frozen=True)
class SearchResult:
    """The distinct ``hypotheses`` (best match first), the grid poses kept by the branch and
    bound (``candidates``), the nodes it scored, its wall time (s) and ``reason`` ('' when at
    least one hypothesis was found, else why none)."""

    hypotheses: list[Hypothesis]
    candidates: int
    nodes: int
    seconds: float
    reason: str

    @property
    def ok(self) -> bool:
        return not self.reason


class GlobalSearch:
    """The whole-map search of one scan (module docstring). ``res`` m the search grid's cell
    (``sigma = res / 2``: an endpoint lies up to half a cell from where the grid puts it),
    ``ratio`` the share of the best score a pose needs to be kept, ``k`` the most hypotheses,
    ``sep_xy`` / ``sep_theta`` the suppression distances, ``beams`` the endpoints scored, and
    the ``refiner`` that matches each hypothesis to the map (its gates refuse)."""

    def __init__(
        self,
        grid: OccupancyGrid,
        refiner: ScanRefiner,
        res: float,
        ratio: float,
        k: int,
        sep_xy: float,
        sep_theta: float,
        beams: int,
        levels: int = 4,
    ) -> None:
        self.grid = grid
        self.refiner = refiner
        self.res, self.ratio, self.k, self.beams, self.levels = res, ratio, k, beams, levels
        self.sep_xy, self.sep_theta = sep_xy, sep_theta
        self._sg: SearchGrid | None = None

    @property
    def search_grid(self) -> SearchGrid:
        if self._sg is None:
            self._sg = SearchGrid.of(self.grid, self.res, self.res / 2)
        return self._sg

    def search(self, scan: LaserScan) -> SearchResult:
        """The hypotheses of ``scan``: branch and bound, suppression, Hector's match of each
        (refused matches dropped, then suppressed again by match score)."""
        t0 = time.perf_counter()
        pts = scan_endpoints(scan, self.refiner.laser_pose, self.beams)
        if len(pts) < MIN_BEAMS:
            return SearchResult([], 0, 0, 0.0, f"{len(pts)} valid beams (< {MIN_BEAMS})")
        sg = self.search_grid
        r90 = max(float(np.percentile(np.hypot(pts[:, 0], pts[:, 1]), 90)), sg.res)
        n_theta = int(np.ceil(2 * np.pi * r90 / sg.res))
        poses, scores, nodes = branch_and_bound(sg, pts, n_theta, self.ratio, self.levels)
        keep = distinct(poses, scores, self.sep_xy, self.sep_theta, self.k)
        _log.info(
            "global search: %d headings, %d nodes scored, %d poses within %.2f of the best "
            "(%.3f), %d distinct, %.2f s", n_theta, nodes, len(scores), self.ratio,
            scores[0] if len(scores) else float("nan"), len(keep), time.perf_counter() - t0,
        )  # fmt: skip
        hyps = []
        for i in keep:
            m = self.refiner.match(poses[i], scan)
            if m.ok:
                hyps.append(Hypothesis(m.pose, m.cov, float(scores[i]), m.score))
        if hyps:
            order = distinct(
                np.array([h.pose for h in hyps]), np.array([h.match_score for h in hyps]),
                self.sep_xy, self.sep_theta, self.k,
            )  # fmt: skip
            hyps = [hyps[i] for i in order]
        dt = time.perf_counter() - t0
        reason = "" if hyps else f"no pose of the {len(keep)} searched fits the map"
        return SearchResult(hyps, len(scores), nodes, dt, reason)
