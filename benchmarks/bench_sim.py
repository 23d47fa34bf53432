"""Speed and memory of the digital twin (run on purpose: ``python benchmarks/bench_sim.py``).

Measures
  (a) the real-time factor of base navigation (20 s of simulated driving), without sensors
      and with 2D lidar scans at 10 Hz;
  (b) the time of one RGB-D capture at 640x480 (render + depth/color noise + deprojection
      to a point cloud), averaged over 10 captures at Site 1 looking at the bench;
  (c) the peak resident memory of the process.

Every timing is printed next to a reference measured in the same run on the same model (a bare
``mj_step`` loop; a bare render without noise or deprojection), so that numbers taken on
different machines can be compared by their ratios. Always exits 0.
"""

from __future__ import annotations

import os

os.environ.setdefault("MUJOCO_GL", "osmesa")
if os.environ["MUJOCO_GL"] == "osmesa":
    os.environ.setdefault("PYOPENGL_PLATFORM", "osmesa")

import platform
import resource
import sys
import time
import traceback

import mujoco
import numpy as np

from mmpa.backends.twin.world import SimWorld

SIM_SECONDS = 20.0
N_CAPTURES = 10
TARGET_RTF = 5.0  # x real time
TARGET_CAPTURE = 0.3  # s per capture

# (v m/s, omega rad/s, duration s): a loop in the lobby from Site 0, 20 s in all
PATTERN = [
    (0.4, 0.0, 2.5),
    (0.0, 0.8, 2.0),
    (0.35, 0.3, 4.0),
    (0.0, -0.8, 2.0),
    (0.3, -0.2, 3.5),
    (-0.2, 0.0, 2.0),
    (0.25, 0.5, 4.0),
]
assert abs(sum(p[2] for p in PATTERN) - SIM_SECONDS) < 1e-9

rows: list[tuple[str, str, str, str]] = []  # (metric, value, target, verdict)
notes: list[str] = []


def verdict(ok: bool) -> str:
    return "PASS" if ok else "FAIL"


def drive(world: SimWorld, lidar: bool) -> tuple[float, int]:
    """Drive PATTERN; return (wall seconds, number of lidar scans)."""
    world.reset(site="0")
    scans = 0
    t0 = time.perf_counter()
    for v, w, dt in PATTERN:
        world.base.set_velocity(v, w)
        for _ in range(round(dt / 0.1)):  # 10 Hz: the lidar rate and the control tick
            world.step(0.1)
            if lidar:
                world.lidar.scan()
                scans += 1
    wall = time.perf_counter() - t0
    world.base.stop()
    return wall, scans


def bare_steps(model: mujoco.MjModel, n: int) -> float:
    """Reference: a bare mj_step loop on the same model (no controllers, no Python per tick)."""
    data = mujoco.MjData(model)
    mujoco.mj_forward(model, data)
    t0 = time.perf_counter()
    for _ in range(n):
        mujoco.mj_step(model, data)
    return time.perf_counter() - t0


def bench_navigation(world: SimWorld) -> None:
    n_steps = round(SIM_SECONDS / world.model.opt.timestep)
    drive(world, lidar=False)  # warm-up (caches, first-call overheads)
    t_ref = bare_steps(world.model, n_steps)
    t_plain, _ = drive(world, lidar=False)
    rtf_plain = SIM_SECONDS / t_plain
    rows.append(
        (
            "navigation RTF, no sensors",
            f"{rtf_plain:8.1f} x",
            f">= {TARGET_RTF:.0f} x",
            verdict(rtf_plain >= TARGET_RTF),
        )
    )
    rows.append(
        (
            "  reference: bare mj_step RTF",
            f"{SIM_SECONDS / t_ref:8.1f} x",
            "",
            f"twin/bare time {t_plain / t_ref:.2f}",
        )
    )
    try:
        _ = world.lidar
    except Exception as e:  # sensors not available in this checkout
        notes.append(f"lidar skipped: {type(e).__name__}: {e}")
        return
    t_lidar, scans = drive(world, lidar=True)
    rtf_lidar = SIM_SECONDS / t_lidar
    rows.append(
        (
            f"navigation RTF, lidar 10 Hz ({scans} scans)",
            f"{rtf_lidar:8.1f} x",
            f">= {TARGET_RTF:.0f} x",
            verdict(rtf_lidar >= TARGET_RTF),
        )
    )
    rows.append(
        (
            "  per lidar scan (1440 beams)",
            f"{1e3 * (t_lidar - t_plain) / scans:8.2f} ms",
            "",
            f"twin/bare time {t_lidar / t_ref:.2f}",
        )
    )


def bench_camera(world: SimWorld) -> None:
    world.reset(site="1")
    q_view = getattr(world.nominal.arm, "view_bench", None)
    if q_view is not None:
        world.arm.move_joints(q_view)
    else:
        notes.append("robot description has no view_bench pose: capturing from home")
    try:
        t0 = time.perf_counter()
        camera = world.camera
        first = camera.capture()
        t_first = time.perf_counter() - t0
    except Exception as e:  # no GL context, or sensors not available
        notes.append(f"camera skipped: {type(e).__name__}: {e}")
        return
    k = first.intrinsics
    times, npts = [], []
    for _ in range(N_CAPTURES):
        t0 = time.perf_counter()
        frame = camera.capture()
        cloud = frame.to_point_cloud(min_depth=0.2, max_depth=4.0)
        times.append(time.perf_counter() - t0)
        npts.append(len(cloud))
    # reference: the renderer alone (color + depth, no noise, no deprojection)
    ref = []
    for _ in range(N_CAPTURES):
        t0 = time.perf_counter()
        camera.capture_truth()
        ref.append(time.perf_counter() - t0)
    t_cap, t_ref = float(np.mean(times)), float(np.mean(ref))
    rows.append(
        (
            f"RGB-D capture + cloud {k.width}x{k.height} (mean of {N_CAPTURES})",
            f"{t_cap:8.3f} s",
            f"<= {TARGET_CAPTURE} s",
            verdict(t_cap <= TARGET_CAPTURE),
        )
    )
    rows.append(
        (
            "  reference: bare render (color + depth)",
            f"{t_ref:8.3f} s",
            "",
            f"capture/render {t_cap / t_ref:.2f}",
        )
    )
    rows.append(("  first capture (creates the GL context)", f"{t_first:8.3f} s", "", ""))
    rows.append(("  points per cloud (mean)", f"{np.mean(npts):8.0f}", "", ""))
    world.close()


def main() -> int:
    print("mmpa twin benchmark")
    print(
        f"  python {platform.python_version()}, mujoco {mujoco.__version__}, "
        f"MUJOCO_GL={os.environ.get('MUJOCO_GL')}, {platform.machine()}, "
        f"{os.cpu_count()} CPUs"
    )
    t0 = time.perf_counter()
    world = SimWorld(site="0")
    t_build = time.perf_counter() - t0
    m = world.model
    print(f"  model: {m.nbody} bodies, {m.ngeom} geoms, {m.nv} dofs, dt {m.opt.timestep} s")
    rows.append(("build SimWorld (MJCF + compile)", f"{t_build:8.3f} s", "", ""))
    for name, fn in (("navigation", bench_navigation), ("camera", bench_camera)):
        try:
            fn(world)
        except Exception:
            notes.append(f"{name} benchmark crashed:\n{traceback.format_exc()}")
    peak_kib = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss  # KiB on Linux
    peak_mib = peak_kib / (1024.0 * 1024.0) if sys.platform == "darwin" else peak_kib / 1024.0
    rows.append(("peak memory (ru_maxrss)", f"{peak_mib:8.0f} MiB", "", ""))

    w0 = max(len(r[0]) for r in rows)
    w1 = max(len(r[1]) for r in rows)
    print()
    print(f"{'metric':<{w0}}  {'value':>{w1}}  {'target':<10}  result")
    print(f"{'-' * w0}  {'-' * w1}  {'-' * 10}  {'-' * 22}")
    for metric, value, target, result in rows:
        print(f"{metric:<{w0}}  {value:>{w1}}  {target:<10}  {result}")
    failed = [r[0] for r in rows if r[3] == "FAIL"]
    print()
    print(f"targets: {'all met' if not failed else 'NOT met: ' + '; '.join(failed)}")
    for n in notes:
        print(f"note: {n}")
    return 0


if __name__ == "__main__":
    try:
        main()
    except Exception:
        traceback.print_exc()
    sys.exit(0)
