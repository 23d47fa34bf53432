"""Overhead of recording a twin run to a ROS 2 bag (run on purpose:
``python benchmarks/bench_record.py [--repeats N] [--view]``; ``--view``: the Foxglove live
view with no client connected instead of a bag).

The run: the demo's drive without the MMPA stage -- Site 0 -> Site 1 on the enhanced AMCL
(``navigate``: scans at 10 Hz, control at 20 Hz), then ``CAPTURES`` RGB-D captures at the
goal. It is timed (world construction excluded) without recording and with a
:class:`mmpa.bags.Recorder` writing MCAP (every topic of the recorder, particle clouds of
up to 100 poses), alternating, ``--repeats`` times each; the medians are compared with the
target (recording adds <= 10 % wall time). Also checks that the recorded run IS the
unrecorded run (same final true pose and estimate, bit for bit) and prints the bag's size
and message counts. Always exits 0.
"""

from __future__ import annotations

import os

os.environ.setdefault("MUJOCO_GL", "osmesa")
if os.environ["MUJOCO_GL"] == "osmesa":
    os.environ.setdefault("PYOPENGL_PLATFORM", "osmesa")

import argparse
import statistics
import tempfile
import time
import traceback
from pathlib import Path

import numpy as np

CAPTURES = 3
TARGET_OVERHEAD = 0.10


#: seconds spent inside the recorder's hooks (serializing and writing), per run
HOOK_SECONDS = [0.0]


def _timed_hooks() -> None:
    """Time the Recorder's on_* hooks (the recording work proper, whatever the machine's
    load does to the wall time of the whole run)."""
    from mmpa.bags.record import Recorder

    for name in ("on_scan", "on_odometry", "on_frame", "on_initial", "on_estimate", "write_map"):
        f = getattr(Recorder, name)

        def timed(self, *a, _f=f, **k):
            t = time.perf_counter()
            try:
                return _f(self, *a, **k)
            finally:
                HOOK_SECONDS[0] += time.perf_counter() - t

        setattr(Recorder, name, timed)


def one_run(
    bag: Path | None, view: bool = False
) -> tuple[float, np.ndarray, np.ndarray, dict[str, int]]:
    """Wall seconds of the drive + captures, final truth, final estimate, sink counts.
    ``view``: the sink is the Foxglove live view with no client instead of a bag."""
    from mmpa.bags import BagWriter, Recorder
    from mmpa.localization.localizer import make_localizer
    from mmpa.navigation.mission import NavigateConfig, navigate
    from mmpa.navigation.planner import CostMap
    from mmpa.sim.operator import rough_initial_pose
    from mmpa.sim.twin_maps import laser_pose2d, twin_map, twin_nav_map
    from mmpa.sim.world import SimWorld

    with SimWorld() as world:
        goal = world.scene.site("1").pose2d
        grid = twin_map(world)
        cfg = NavigateConfig(timeout=90.0)
        costmap = CostMap(twin_nav_map(world), cfg.planner)
        _ = world.camera  # the renderer is built outside the timing, in both runs
        t0 = time.perf_counter()
        if view:
            from mmpa.bags.view import FoxgloveView

            writer = FoxgloveView(port=0)
        else:
            writer = BagWriter(bag) if bag is not None else None
        w = world
        loc = make_localizer("enhanced", grid, laser_pose2d(world), np.random.default_rng(0))
        if writer is not None:
            rec = Recorder(writer, world)
            w = rec.world()
            rec.write_map(grid)
            loc = rec.localizer(loc)
        loc.initialize(rough_initial_pose(world))
        res = navigate(w, loc, grid, goal, cfg, costmap=costmap)
        for _ in range(CAPTURES):
            w.camera.capture()
        counts = {}
        if writer is not None:
            writer.close()
            counts = dict(writer.counts)
        wall = time.perf_counter() - t0
        return wall, res.final_truth, res.final_estimate, counts


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--repeats", type=int, default=2)
    ap.add_argument(
        "--view", action="store_true", help="measure the live view (no client) instead of a bag"
    )
    args = ap.parse_args()
    _timed_hooks()
    try:
        plain, recorded, hooks = [], [], []
        with tempfile.TemporaryDirectory() as d:
            for i in range(args.repeats):
                wall, truth0, est0, _ = one_run(None)
                plain.append(wall)
                bag = Path(d) / f"run{i}.mcap"
                HOOK_SECONDS[0] = 0.0
                wall, truth1, est1, counts = one_run(bag, view=args.view)
                recorded.append(wall)
                hooks.append(HOOK_SECONDS[0])
                size = 0 if args.view else bag.stat().st_size
                same = np.array_equal(truth0, truth1) and np.array_equal(est0, est1)
                print(
                    f"repeat {i}: plain {plain[-1]:.2f} s, recorded {recorded[-1]:.2f} s "
                    f"(in the recorder: {hooks[-1]:.2f} s), same run: {same}"
                )
        p, r = statistics.median(plain), statistics.median(recorded)
        over = r / p - 1.0
        h = statistics.median(hooks)
        print(
            f"recorder work: median {h:.2f} s = {100 * h / p:.1f} % of the plain run "
            "(load-independent estimate of the overhead)"
        )
        what = "view (no client): serialized" if args.view else f"bag: {size / 1e6:.1f} MB,"
        print(f"{what} {sum(counts.values())} messages: {counts}")
        print(
            f"median wall: plain {p:.2f} s, recorded {r:.2f} s -> overhead {100 * over:+.1f} % "
            f"(target <= {100 * TARGET_OVERHEAD:.0f} %): "
            f"{'OK' if over <= TARGET_OVERHEAD else 'ABOVE TARGET'}"
        )
    except Exception:  # a benchmark reports, it does not fail the caller
        traceback.print_exc()


if __name__ == "__main__":
    main()
