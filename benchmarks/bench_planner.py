"""Global planner on a real building's size: 76 m x 36 m at 5 cm (1520 x 720 cells), rooms
and corridors, corner to corner (issue 19.6).

    .venv/bin/python benchmarks/bench_planner.py [--old PATH_TO_OLD_PLANNER_MODULE]

Prints the planning time (best of 3) and the path length; ``--old`` also times another
``plan_path`` (e.g. a copy of the pure-Python A*) on the same map.
"""

from __future__ import annotations

import argparse
import importlib.util
import time

import numpy as np

from mmpa.localization.maps import Box2D, OccupancyGrid, rasterize
from mmpa.navigation.planner import CostMap, plan_path


def building_map(seed: int = 0) -> OccupancyGrid:
    """76 m x 36 m: outer walls, two 2.4 m corridors along x joined by cross corridors, rows
    of rooms (doors 1 m) on both sides, furniture in the rooms."""
    rng = np.random.default_rng(seed)
    W, H, t = 76.0, 36.0, 0.15
    boxes = [
        Box2D((W / 2, 0.0), (W, t)),
        Box2D((W / 2, H), (W, t)),
        Box2D((0.0, H / 2), (t, H)),
        Box2D((W, H / 2), (t, H)),
    ]
    corridors = (12.0, 24.0)  # center lines (y) of the two corridors, 2.4 m wide
    bands = [(0.0, 10.8), (13.2, 22.8), (25.2, 36.0)]  # room rows between the corridors
    for cy in corridors:
        for y in (cy - 1.2, cy + 1.2):  # corridor walls, doors every room
            x = 0.0
            while x < W:
                width = rng.uniform(5.0, 8.0)
                door = x + rng.uniform(1.0, width - 2.0)
                boxes.append(Box2D(((x + door) / 2, y), (door - x, t)))
                end = min(x + width, W)
                boxes.append(Box2D(((door + 1.0 + end) / 2, y), (end - door - 1.0, t)))
                x = end
    for y0, y1 in bands:  # room partitions and furniture
        x = 0.0
        while x < W - 4:
            x += rng.uniform(5.0, 8.0)
            if x < W - 1:
                gap = rng.uniform(y0 + 1.0, y1 - 2.0)  # a connecting door between rooms
                boxes.append(Box2D((x, (y0 + gap) / 2), (t, gap - y0)))
                boxes.append(Box2D((x, (gap + 1.0 + y1) / 2), (t, y1 - gap - 1.0)))
            for _ in range(2):
                cx, cy = x - rng.uniform(1.5, 4.0), rng.uniform(y0 + 1.5, y1 - 1.5)
                boxes.append(Box2D((cx, cy), (rng.uniform(0.6, 1.6), rng.uniform(0.5, 1.0))))
    # cross corridors between the corridors (no walls at x ~ 2 and x ~ 74)
    return rasterize(boxes, (-0.5, -0.5, W + 0.5, H + 0.5), 0.05)


def path_length(p: np.ndarray) -> float:
    return float(np.linalg.norm(np.diff(p, axis=0), axis=1).sum())


def best_of(fn, n: int = 3) -> tuple[float, float, np.ndarray]:
    """Best wall-clock and CPU (this process) seconds of ``n`` calls, and the last result."""
    best, best_cpu, out = np.inf, np.inf, None
    for _ in range(n):
        t0, c0 = time.perf_counter(), time.process_time()
        out = fn()
        best = min(best, time.perf_counter() - t0)
        best_cpu = min(best_cpu, time.process_time() - c0)
    assert out is not None
    return best, best_cpu, out


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--old", help="path of a module with another plan_path to compare")
    args = ap.parse_args()
    grid = building_map()
    t0 = time.perf_counter()
    cm = CostMap(grid)
    t_cm = time.perf_counter() - t0
    start, goal = np.array([1.0, 1.0]), np.array([75.0, 35.0])
    print(f"map {grid.width} x {grid.height} cells, costmap {t_cm:.3f} s")
    t, c, p = best_of(lambda: plan_path(cm, start, goal), 1)
    print(f"plan_path, first call (builds the search graph): {t:.3f} s wall, {c:.3f} s CPU")
    t, c, p = best_of(lambda: plan_path(cm, start, goal))
    print(
        f"plan_path: {t:.3f} s wall, {c:.3f} s CPU (best of 3), {len(p)} waypoints, "
        f"length {path_length(p):.2f} m"
    )
    if args.old:
        spec = importlib.util.spec_from_file_location("old_planner", args.old)
        assert spec is not None and spec.loader is not None
        mod = importlib.util.module_from_spec(spec)
        spec.loader.exec_module(mod)
        cm_old = mod.CostMap(grid)
        t, c, p = best_of(lambda: mod.plan_path(cm_old, start, goal), 1)
        print(
            f"old plan_path: {t:.3f} s wall, {c:.3f} s CPU, {len(p)} waypoints, "
            f"length {path_length(p):.2f} m"
        )


if __name__ == "__main__":
    main()
