"""Nav2-derived AMCL C++ (pip package ``amcl``) on the same map and scans as our AMCL.

Two steps, because ``amcl`` is not a dependency of mmpa:

    .venv/bin/python benchmarks/bench_amcl_cpp.py record /tmp/amcl_scans.npz
    <env with numpy + amcl>/bin/python benchmarks/bench_amcl_cpp.py replay /tmp/amcl_scans.npz

``record`` drives the twin on a short loop and stores the occupancy grid, the lidar mount, the
odometry and the scans (and times our AMCL on them, 2000 particles / 60 beams); ``replay``
feeds the same data to the C++ filter and prints its median update time and final error.
"""

from __future__ import annotations

import os
import sys
import time

import numpy as np


def record(path: str) -> None:
    os.environ.setdefault("MUJOCO_GL", "osmesa")
    from mmpa.localization.amcl import AMCL, AMCLConfig
    from mmpa.navigation.mission import laser_pose2d, twin_map
    from mmpa.sim.world import SimWorld

    with SimWorld(site="1") as w:
        grid = twin_map(w)
        lp = laser_pose2d(w)
        odo, scans, truth = [], [], []
        for k in range(60):
            w.base.set_velocity(0.25, 0.3 if k < 30 else -0.3)
            w.step(0.2)
            odo.append(w.odometry.odometry().pose)
            scans.append(w.lidar.scan().ranges)
            truth.append(w.truth.base_pose2d())
        w.base.stop()
        s0 = w.lidar.scan()
    cfg = AMCLConfig(min_particles=2000, max_particles=2000, max_beams=60)
    amcl = AMCL(grid, lp, cfg, np.random.default_rng(0))
    amcl.set_initial_pose(truth[0] - (np.asarray(odo[0]) - odo[0]))
    ts = []
    import dataclasses

    for o, r in zip(odo, scans, strict=True):
        sc = dataclasses.replace(s0, ranges=r)
        t = time.perf_counter()
        amcl.update(o, sc, force=True)
        ts.append(time.perf_counter() - t)
    e = amcl.pose_at(odo[-1]) - truth[-1]
    err = np.hypot(*e[:2]) * 100
    print(f"mmpa AMCL: {1000 * np.median(ts):.2f} ms median update, final error {err:.1f} cm")
    np.savez(
        path,
        occ=grid.data,
        res=grid.resolution,
        origin=np.array(grid.origin),
        laser=lp,
        odom=np.array(odo),
        ranges=np.array(scans),
        angles=s0.angles,
        range_max=s0.range_max,
        truth=np.array(truth),
    )


def replay(path: str) -> None:
    import amcl  # type: ignore[import-not-found]

    d = np.load(path)
    occ = d["occ"]
    # ROS amcl map_t cell states: -1 free, 0 unknown, +1 occupied; rows are y
    state = np.where(occ >= 65, 1, np.where(occ < 0, 0, -1))
    grid = amcl.create_occupancy_grid_from_list(
        state.tolist(), float(d["res"]), float(d["origin"][0]), float(d["origin"][1])
    )
    f = amcl.AMCL(
        2000,
        2000,
        0.0,
        0.0,
        amcl.MotionParameters(0.2, 0.2, 0.2, 0.2, 0.2),
        amcl.LaserParameters(0.5, 0.05, 0.05, 0.5, 0.2, 0.1, 0.05, 60),
        "differential",
    )
    f.set_map(grid)
    f.set_laser_pose(amcl.Vector3D(*map(float, d["laser"])))
    f.set_initial_pose(
        amcl.Vector3D(*map(float, d["truth"][0])),
        amcl.create_diagonal_covariance(0.25, 0.25, 0.068),
    )
    ts = []
    for o, r in zip(d["odom"], d["ranges"], strict=True):
        ok = np.isfinite(r)
        pairs = np.column_stack([np.where(ok, r, float(d["range_max"])), d["angles"]]).tolist()
        sc = amcl.create_laser_scan_from_list(pairs, float(d["range_max"]))
        t = time.perf_counter()
        f.update(sc, amcl.Vector3D(*map(float, o)))
        ts.append(time.perf_counter() - t)
    p = f.pose
    e = np.array([p.x, p.y]) - d["truth"][-1][:2]
    err = np.hypot(*e) * 100
    print(f"C++ AMCL (pip amcl): {1000 * np.median(ts):.2f} ms median update, error {err:.1f} cm")


if __name__ == "__main__":
    {"record": record, "replay": replay}[sys.argv[1]](sys.argv[2])
