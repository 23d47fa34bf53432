"""Global path planning: A* on an inflated occupancy grid (Nav2 ``NavFn`` / ``Smac`` 2D style).

The grid is inflated by the robot's inscribed radius (lethal) and a decaying cost out to
``inflation_radius`` (Nav2 ``inflation_layer``: ``cost = 252 exp(-cost_scaling_factor (d -
inscribed))``), so paths keep off the walls. A* runs on the 8-connected cell graph with cost
``step length * (1 + cost_weight * cost / 252)`` and the octile-distance heuristic; the
resulting cell path is shortcut where the straight line stays in cells of low cost.

Units: m. Never imports the simulator.
"""

from __future__ import annotations

import heapq

import numpy as np
from pydantic import BaseModel, ConfigDict, Field
from scipy import ndimage

from mmpa.errors import InvalidInputError, UnreachableError
from mmpa.geometry import Array
from mmpa.localization.maps import OccupancyGrid

__all__ = ["CostMap", "PlannerConfig", "plan_path"]


class PlannerConfig(BaseModel):
    model_config = ConfigDict(extra="forbid")

    inscribed_radius: float = Field(0.36, ge=0)  # m, lethal inflation
    inflation_radius: float = Field(0.9, ge=0)  # m
    cost_scaling_factor: float = Field(4.0, gt=0)  # 1/m
    cost_weight: float = Field(3.0, ge=0)
    endpoint_clearance: float = Field(0.35, ge=0)  # m around start/goal that may be inflated
    shortcut_max_cost: float = Field(120.0, ge=0)


class CostMap:
    """Inflated costs (H, W) float in [0, 254]: 254 occupied, 253 inside the inscribed radius."""

    def __init__(self, grid: OccupancyGrid, cfg: PlannerConfig | None = None) -> None:
        self.grid = grid
        self.cfg = c = cfg or PlannerConfig()
        occ = grid.occupied | (grid.data < 0)
        d = ndimage.distance_transform_edt(~occ) * grid.resolution
        cost = 252.0 * np.exp(-c.cost_scaling_factor * np.maximum(d - c.inscribed_radius, 0.0))
        cost[d > c.inflation_radius] = 0.0
        cost[d <= c.inscribed_radius] = 253.0
        cost[occ] = 254.0
        self.cost = cost
        self.dist = d


def _line_cells(c0: tuple[int, int], c1: tuple[int, int]) -> tuple[np.ndarray, np.ndarray]:
    n = max(abs(c1[0] - c0[0]), abs(c1[1] - c0[1])) + 1
    r = np.rint(np.linspace(c0[0], c1[0], n)).astype(int)
    c = np.rint(np.linspace(c0[1], c1[1], n)).astype(int)
    return r, c


def plan_path(
    costmap: CostMap, start: Array, goal: Array, cfg: PlannerConfig | None = None
) -> Array:
    """Path (K, 2) of map points from ``start`` to ``goal`` (x, y); raises
    :class:`UnreachableError` if no collision-free path exists."""
    c = cfg or costmap.cfg
    g = costmap.grid
    start, goal = np.asarray(start, float)[:2], np.asarray(goal, float)[:2]
    if not (np.all(np.isfinite(start)) and np.all(np.isfinite(goal))):
        raise InvalidInputError("start and goal must be finite")
    (sc, sr), (gc, gr) = g.world_to_cell(start), g.world_to_cell(goal)
    sc, sr, gc, gr = int(sc), int(sr), int(gc), int(gr)
    for name, cc, rr in (("start", sc, sr), ("goal", gc, gr)):
        if not (0 <= cc < g.width and 0 <= rr < g.height):
            raise UnreachableError(f"{name} {start if name == 'start' else goal} is off the map")
    cost = costmap.cost.copy()
    # start and goal may sit inside the inflation (a robot parked at a desk): clear the
    # inscribed band around them, never the obstacles themselves
    H, W = cost.shape
    rows, cols = np.mgrid[0:H, 0:W]
    rad = c.endpoint_clearance / g.resolution
    for cc, rr in ((sc, sr), (gc, gr)):
        near = ((rows - rr) ** 2 + (cols - cc) ** 2 <= rad * rad) & (cost == 253.0)
        cost[near] = 200.0
    if cost[sr, sc] >= 254 or cost[gr, gc] >= 254:
        raise UnreachableError("start or goal lies in an obstacle")
    blocked = cost >= 253.0
    step_cost = 1.0 + c.cost_weight * cost / 252.0
    nbrs = [(-1, -1), (-1, 0), (-1, 1), (0, -1), (0, 1), (1, -1), (1, 0), (1, 1)]
    sq2 = np.sqrt(2.0)
    gbest = np.full(cost.shape, np.inf)
    parent = np.full((*cost.shape, 2), -1, dtype=np.int64)
    gbest[sr, sc] = 0.0

    def h(r: int, q: int) -> float:
        dr, dq = abs(r - gr), abs(q - gc)
        return (dr + dq) + (sq2 - 2) * min(dr, dq)

    heap: list[tuple[float, float, int, int]] = [(h(sr, sc), 0.0, sr, sc)]
    closed = np.zeros(cost.shape, dtype=bool)
    while heap:
        _, gval, r, q = heapq.heappop(heap)
        if closed[r, q]:
            continue
        closed[r, q] = True
        if r == gr and q == gc:
            break
        for dr, dq in nbrs:
            nr, nq = r + dr, q + dq
            if not (0 <= nr < H and 0 <= nq < W) or blocked[nr, nq] or closed[nr, nq]:
                continue
            ng = gval + (sq2 if dr and dq else 1.0) * step_cost[nr, nq]
            if ng < gbest[nr, nq]:
                gbest[nr, nq] = ng
                parent[nr, nq] = (r, q)
                heapq.heappush(heap, (ng + h(nr, nq), ng, nr, nq))
    if not closed[gr, gc]:
        raise UnreachableError(f"no collision-free path from {start} to {goal}")
    cells = [(gr, gc)]
    while cells[-1] != (sr, sc):
        pr, pq = parent[cells[-1]]
        cells.append((int(pr), int(pq)))
    cells.reverse()
    # shortcut: keep a waypoint only where the straight line would cross costly cells
    keep = [0]
    i = 0
    while i < len(cells) - 1:
        j = len(cells) - 1
        while j > i + 1:
            rr, cc = _line_cells(cells[i], cells[j])
            if cost[rr, cc].max() <= max(c.shortcut_max_cost, cost[cells[i]], cost[cells[j]]):
                break
            j -= 1
        keep.append(j)
        i = j
    pts = np.array([g.cell_to_world(cells[k][1], cells[k][0]) for k in keep])
    pts[0], pts[-1] = start, goal
    return pts
