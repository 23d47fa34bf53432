"""Overhead of recording a twin run to a ROS 2 bag (run on purpose:
``python benchmarks/bench_record.py [--repeats N] [--view | --demo]``; ``--view``: the
Foxglove live view with no client connected instead of a bag; ``--demo``: the whole
``mmpa demo`` instead of the drive below).

The run: the demo's drive without the MMPA stage -- Site 0 -> Site 1 on the enhanced AMCL
(``navigate``: scans at 10 Hz, control at 20 Hz), then the arm's move to the bench view and
``CAPTURES`` RGB-D captures at the goal. It is timed (world construction excluded) without
recording and with a :class:`mmpa.backends.bag.Recorder` writing MCAP as ``mmpa demo --record``
does (every topic of the recorder, particle clouds of up to 100 poses, the arm's
``/joint_states`` and ``/tf`` at :data:`mmpa.backends.bag.record.ARM_RATE_HZ` through the whole
run), alternating, ``--repeats`` times each; the medians are compared with the target
(recording adds <= 10 % wall time). Also checks that the recorded run IS the unrecorded run
(same final true pose, estimate and arm encoders, bit for bit; ``--demo``: the same summary
but for wall times) and prints the bag's size and message counts, and the machine's load
average (the wall times of a loaded machine scatter: the seconds spent in the recorder's
hooks are the load-independent estimate). Always exits 0.
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
    from mmpa.backends.bag.record import Recorder

    names = ("on_scan", "on_odometry", "on_frame", "on_initial", "on_estimate", "write_map")
    # the arm stream: sampled in the stepping hook (on_arm), written after each step
    for name in (*names, "on_arm", "_flush_arm", "write_static"):
        f = getattr(Recorder, name)

        def timed(self, *a, _f=f, **k):
            t = time.perf_counter()
            try:
                return _f(self, *a, **k)
            finally:
                HOOK_SECONDS[0] += time.perf_counter() - t

        setattr(Recorder, name, timed)


def one_run(bag: Path | None, view: bool = False) -> tuple[float, tuple, dict[str, int]]:
    """Wall seconds of the drive + arm move + captures, the run's outcome (final truth,
    final estimate, final encoders), sink counts. ``view``: the sink is the Foxglove live
    view with no client instead of a bag."""
    from mmpa.backends.bag import BagWriter, Recorder
    from mmpa.backends.bag.record import ARM_RATE_HZ
    from mmpa.backends.twin.operator import rough_initial_pose
    from mmpa.backends.twin.twin_maps import laser_pose2d, twin_map, twin_nav_map
    from mmpa.backends.twin.world import SimWorld
    from mmpa.localization.localizer import make_localizer
    from mmpa.missions.navigate import NavigateConfig, navigate
    from mmpa.navigation.planner import CostMap

    with SimWorld() as world:
        goal = world.scene.site("1").pose2d
        grid = twin_map(world)
        cfg = NavigateConfig(timeout=90.0)
        costmap = CostMap(twin_nav_map(world), cfg.planner)
        _ = world.camera  # the renderer is built outside the timing, in both runs
        t0 = time.perf_counter()
        if view:
            from mmpa.apps.view import FoxgloveView

            writer = FoxgloveView(port=0)
        else:
            writer = BagWriter(bag) if bag is not None else None
        w = world
        loc = make_localizer("enhanced", grid, laser_pose2d(world), np.random.default_rng(0))
        rec = None
        if writer is not None:
            rec = Recorder(writer, world, joint_rate_hz=ARM_RATE_HZ)
            w = rec.world()
            rec.write_map(grid)
            loc = rec.localizer(loc)
        loc.initialize(rough_initial_pose(world))
        res = navigate(w, loc, grid, goal, cfg, costmap=costmap, truth=world.truth.base_pose2d)
        w.arm.move_joints(np.asarray(world.nominal.arm.view_bench))
        for _ in range(CAPTURES):
            w.camera.capture()
        counts = {}
        if rec is not None:
            rec.close()
        if writer is not None:
            writer.close()
            counts = dict(writer.counts)
        wall = time.perf_counter() - t0
        outcome = (res.final_truth, res.final_estimate, world.arm.joint_positions())
        return wall, outcome, counts


#: summary entries that are wall times or name the bag (not the run)
DEMO_SKIP = {"bag", "bag_messages", "wall_seconds", "capture_seconds", "mmpa_ipe_compute_s"}


def one_demo(bag: Path | None, out: Path) -> tuple[float, dict, dict[str, int]]:
    """Wall seconds of ``mmpa demo`` (``run_demo``, all of it: world, teaching, drive, MMPA,
    capture, files), its summary less wall times, the bag's counts."""
    from mmpa.apps.demo import DemoConfig, run_demo
    from mmpa.backends.bag.reader import bag_topics

    t0 = time.perf_counter()
    summary = run_demo(DemoConfig(), out, record=bag)
    wall = time.perf_counter() - t0
    counts = {k: v[1] for k, v in bag_topics(bag).items()} if bag is not None else {}
    return wall, {k: v for k, v in summary.items() if k not in DEMO_SKIP}, counts


def _same(a: tuple | dict, b: tuple | dict) -> bool:
    if isinstance(a, dict):
        return a == b
    return all(np.array_equal(x, y) for x, y in zip(a, b, strict=True))


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--repeats", type=int, default=2)
    ap.add_argument(
        "--view", action="store_true", help="measure the live view (no client) instead of a bag"
    )
    ap.add_argument("--demo", action="store_true", help="time the whole `mmpa demo`")
    args = ap.parse_args()
    _timed_hooks()
    try:
        plain, recorded, hooks = [], [], []
        print(f"load average before: {' '.join(f'{x:.2f}' for x in os.getloadavg())}")
        with tempfile.TemporaryDirectory() as d:
            for i in range(args.repeats):
                bag = Path(d) / f"run{i}.mcap"
                if args.demo:
                    wall, out0, _ = one_demo(None, Path(d) / f"plain{i}")
                else:
                    wall, out0, _ = one_run(None)
                plain.append(wall)
                HOOK_SECONDS[0] = 0.0
                if args.demo:
                    wall, out1, counts = one_demo(bag, Path(d) / f"rec{i}")
                else:
                    wall, out1, counts = one_run(bag, view=args.view)
                recorded.append(wall)
                hooks.append(HOOK_SECONDS[0])
                size = 0 if args.view else bag.stat().st_size
                same = _same(out0, out1)
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
        print(f"load average after: {' '.join(f'{x:.2f}' for x in os.getloadavg())}")
    except Exception:  # a benchmark reports, it does not fail the caller
        traceback.print_exc()


if __name__ == "__main__":
    main()
