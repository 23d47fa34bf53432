"""Drives that settle: seeded drives over every ordered pair of the twin's sites (issue 32).

Drive ``i`` is robot instance ``seed0 + i`` (its own error model draw: DH, mounts, map warp,
reflector survey, operator's rough pose) from site ``PAIRS[i % 6][0]`` to ``PAIRS[i % 6][1]``
on the default localizer (``enhanced``) under ``--profile`` (default ``realistic``), exactly as
``mmpa navigate --to B --from A --seed S`` drives it. Prints the share that reached and settled
within the final approach's tolerance, the reasons of those that did not, and the parking and
localization error distributions (truth vs goal; estimate vs truth).

Run::

    MUJOCO_GL=osmesa .venv/bin/python benchmarks/bench_drives.py [--n 200] [--workers 2]
        [--seed0 0] [--profile realistic] [--out drives.json]

About 10 s of one core per drive (200 drives: ~17 min on 2 workers).
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from concurrent.futures import ProcessPoolExecutor, as_completed

os.environ.setdefault("MUJOCO_GL", "osmesa")
os.environ.setdefault("PYOPENGL_PLATFORM", "osmesa")

import numpy as np

PAIRS = [("0", "1"), ("0", "2"), ("1", "0"), ("1", "2"), ("2", "0"), ("2", "1")]


def drive(seed: int, start: str, to: str, profile: str) -> dict:
    """One drive as ``mmpa navigate`` runs it; its outcome and errors (mm, deg)."""
    from mmpa.backends.twin.error_model import ErrorModelConfig
    from mmpa.backends.twin.operator import rough_initial_pose
    from mmpa.backends.twin.twin_maps import laser_pose2d, twin_map, twin_nav_map
    from mmpa.backends.twin.world import SimWorld
    from mmpa.core.config import load_config
    from mmpa.localization.localizer import make_localizer
    from mmpa.missions.navigate import NavigateConfig, navigate
    from mmpa.navigation.planner import CostMap

    errors = load_config(ErrorModelConfig, None, [f"seed={seed}", f"profile={profile}"])
    t0 = time.perf_counter()
    with SimWorld(errors=errors, site=start) as world:
        goal = world.scene.site(to).pose2d
        grid = twin_map(world)
        loc = make_localizer("enhanced", grid, laser_pose2d(world), np.random.default_rng(seed))
        loc.initialize(rough_initial_pose(world))
        cm = CostMap(twin_nav_map(world))
        res = navigate(
            world, loc, grid, goal, NavigateConfig(), costmap=cm, truth=world.truth.base_pose2d
        )
    e = res.localization_error
    return {
        "seed": seed,
        "from": start,
        "to": to,
        "reached": bool(res.reached),
        "reason": res.reason,
        "corrections": res.corrections,
        "sim_s": round(res.sim_time, 2),
        "wall_s": round(time.perf_counter() - t0, 2),
        "park_xy_mm": 1000 * res.parking_error_xy,
        "park_yaw_deg": float(np.rad2deg(res.parking_error_yaw)),
        "loc_xy_mm": 1000 * float(np.hypot(e[0], e[1])),
        "settle_xy_mm": 1000 * res.settle_error_xy,
    }


def _table(rows: list[dict]) -> None:
    n = len(rows)
    ok = sum(r["reached"] for r in rows)
    print(f"\nreached and settled: {ok} / {n}")
    for r in rows:
        if not r["reached"]:
            print(f"  seed {r['seed']} {r['from']} -> {r['to']}: {r['reason']}")
    qs = (0, 50, 90, 95, 99, 100)
    print(f"\n{'quantity':<26}" + "".join(f"{'p' + str(q):>9}" for q in qs) + f"{'mean':>9}")
    for key, label in (
        ("park_xy_mm", "parking error xy (mm)"),
        ("park_yaw_deg", "parking error yaw (deg)"),
        ("loc_xy_mm", "localization error (mm)"),
        ("settle_xy_mm", "estimate vs goal (mm)"),
        ("sim_s", "drive time (sim s)"),
    ):
        v = np.array([r[key] for r in rows], float)
        print(
            f"{label:<26}" + "".join(f"{np.percentile(v, q):9.2f}" for q in qs) + f"{v.mean():9.2f}"
        )
    print(f"\n{'pair':<10}{'n':>4}{'reached':>9}{'park p50':>10}{'park max':>10}")
    for a, b in PAIRS:
        sub = [r for r in rows if (r["from"], r["to"]) == (a, b)]
        if sub:
            p = np.array([r["park_xy_mm"] for r in sub])
            ok_ab = sum(r["reached"] for r in sub)
            print(f"{a + ' -> ' + b:<10}{len(sub):>4}{ok_ab:>9}{np.median(p):10.2f}{p.max():10.2f}")


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--n", type=int, default=200)
    ap.add_argument("--seed0", type=int, default=0)
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--profile", default="realistic")
    ap.add_argument("--out", default=None)
    a = ap.parse_args()
    jobs = [(a.seed0 + i, *PAIRS[i % len(PAIRS)], a.profile) for i in range(a.n)]
    rows: list[dict] = []
    t0 = time.perf_counter()
    with ProcessPoolExecutor(a.workers) as ex:
        futs = [ex.submit(drive, *j) for j in jobs]
        for k, f in enumerate(as_completed(futs), 1):
            r = f.result()
            rows.append(r)
            mark = "ok " if r["reached"] else "NOT"
            print(
                f"[{k:3d}/{a.n}] {mark} seed {r['seed']:3d} {r['from']} -> {r['to']}: park "
                f"{r['park_xy_mm']:.2f} mm, loc {r['loc_xy_mm']:.2f} mm, {r['sim_s']:.1f} s",
                flush=True,
            )
    rows.sort(key=lambda r: r["seed"])
    _table(rows)
    print(f"\n{a.n} drives in {time.perf_counter() - t0:.0f} s on {a.workers} workers")
    if a.out:
        with open(a.out, "w") as fh:
            json.dump(rows, fh, indent=1)
    return 0 if sum(r["reached"] for r in rows) >= 0.995 * len(rows) else 1


if __name__ == "__main__":
    sys.exit(main())
