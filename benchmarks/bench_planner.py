"""Global planner on a real building's size: 76 m x 36 m at 5 cm (1540 x 740 cells with the
margin), rooms and corridors, corner to corner (issue 19.6).

    .venv/bin/python benchmarks/bench_planner.py [--old PATH_TO_OLD_PLANNER_PY]
        [--repeat N] [--random M]

Prints the first plan's time (it builds the search graph), then the median and best wall and
CPU time of ``N`` plans (default 5) and the path; ``--old`` also times another ``plan_path``
(e.g. a copy of ``planner.py`` before a change) on the same map, interleaved with ours so that
both see the same load; ``--random`` also times ``M`` random start/goal pairs (seed 0).

Measured on the shared 2-core machine, load average ~4 (``--old`` the one-sided Dijkstra,
``--repeat 7 --random 20``): corner to corner 0.222 s CPU median -> 0.186 s (path cost the
same; 99.08 m -> 99.19 m after the shortcut: another optimal cell path); 20 random pairs
median 0.228 s -> 0.078 s CPU (max 0.193 s); first plan 0.4-0.8 s for either (the graph
build; it varies with the machine's memory state).
"""

from __future__ import annotations

import argparse
import importlib.util
import os
import sys
import time

import numpy as np

from mmpa.core.errors import UnreachableError
from mmpa.maps.occupancy import Box2D, OccupancyGrid, rasterize
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


def timed(fn) -> tuple[float, float, np.ndarray]:
    """Wall-clock and CPU (this process) seconds of one call, and its result."""
    t0, c0 = time.perf_counter(), time.process_time()
    out = fn()
    return time.perf_counter() - t0, time.process_time() - c0, out


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--old", help="path of a module with another plan_path to compare")
    ap.add_argument("--repeat", type=int, default=5, help="timed plans per planner")
    ap.add_argument("--random", type=int, default=0, help="also N random start/goal pairs")
    args = ap.parse_args()
    print(f"load average {os.getloadavg()[0]:.2f} (1 min), {os.cpu_count()} CPUs")
    grid = building_map()
    start, goal = np.array([1.0, 1.0]), np.array([75.0, 35.0])
    planners = {"plan_path": (CostMap, plan_path)}
    if args.old:
        spec = importlib.util.spec_from_file_location("old_planner", args.old)
        assert spec is not None and spec.loader is not None
        mod = importlib.util.module_from_spec(spec)
        sys.modules["old_planner"] = mod
        spec.loader.exec_module(mod)
        planners["old plan_path"] = (mod.CostMap, mod.plan_path)
    maps, times = {}, {}
    for name, (cls, plan) in planners.items():
        t, _, cm = timed(lambda cls=cls: cls(grid))
        maps[name] = cm
        t1, c1, p = timed(lambda cm=cm, plan=plan: plan(cm, start, goal))
        print(
            f"{name}: map {grid.width} x {grid.height} cells, costmap {t:.3f} s, first plan "
            f"(builds the search graph) {t1:.3f} s wall, {c1:.3f} s CPU"
        )
        times[name] = []
    for _ in range(args.repeat):  # interleaved: the same load for every planner
        for name, (_, plan) in planners.items():
            t, c, p = timed(lambda name=name, plan=plan: plan(maps[name], start, goal))
            times[name].append((t, c, p))
    for name, ts in times.items():
        w, c = np.array([t[0] for t in ts]), np.array([t[1] for t in ts])
        p = ts[-1][2]
        print(
            f"{name}: median {np.median(w):.3f} s wall, {np.median(c):.3f} s CPU; best "
            f"{w.min():.3f} s wall, {c.min():.3f} s CPU ({len(ts)} plans); {len(p)} waypoints, "
            f"length {path_length(p):.2f} m"
        )
    if args.random:
        rng = np.random.default_rng(0)
        cm = next(iter(maps.values()))
        free = np.argwhere(cm.dist > 0.5)
        cpu: dict[str, list[float]] = {name: [] for name in planners}
        for _ in range(args.random):
            (r0, c0), (r1, c1) = free[rng.choice(len(free), 2)]
            a, b = grid.cell_to_world(c0, r0), grid.cell_to_world(c1, r1)
            for name, (_, plan) in planners.items():
                try:
                    _, c, _ = timed(lambda n=name, f=plan, a=a, b=b: f(maps[n], a, b))
                except UnreachableError:
                    continue
                cpu[name].append(c)
        for name, cs in cpu.items():
            print(
                f"{name}, {len(cs)} random pairs: median {np.median(cs):.3f} s CPU "
                f"(max {max(cs):.3f} s)"
            )
    print(f"load average {os.getloadavg()[0]:.2f} (1 min)")


if __name__ == "__main__":
    main()
