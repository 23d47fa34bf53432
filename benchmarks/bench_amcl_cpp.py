"""Nav2-derived AMCL C++ (pip package ``amcl``) on the same map and scans as our AMCL.

Two steps, because ``amcl`` is not a dependency of mmpa (keep it in a throwaway venv):

    .venv/bin/python benchmarks/bench_amcl_cpp.py record /tmp/amcl_scans.npz
    python3 -m venv /tmp/amclvenv && /tmp/amclvenv/bin/pip install amcl numpy
    /tmp/amclvenv/bin/python benchmarks/bench_amcl_cpp.py replay /tmp/amcl_scans.npz

``record`` drives the twin on a short loop (60 scans at 5 Hz) and stores the occupancy grid,
the lidar mount, the odometry and the scans, and times OUR AMCL on them (2000 particles fixed,
60 beams, Nav2 defaults otherwise) with both laser models. ``replay`` feeds the same data to
the C++ filter and prints its median update time and final position error. To time ours
again on the recorded file, without the simulator (and, interleaved with it, the beam model
of another copy of ``amcl.py``, e.g. the version before a change), alternating with
``replay`` so that both see the same load:

    .venv/bin/python benchmarks/bench_amcl_cpp.py ours /tmp/amcl_scans.npz [OLD_AMCL_PY]

What the C++ side is: ``amcl`` 0.1.2 (nanobind bindings of Nav2's ``pf`` library, the
``DifferentialMotionModel`` and the ``BeamModel``). It compiles in the BEAM model only (no
likelihood field), its ``update`` runs the filter on every call (no ``update_min_d`` gating,
like our ``force=True``), and it takes a ``0/100/-1`` grid with rows along ``y``. So the
like-for-like figure is our beam model against it; our likelihood field is printed beside.

Measured on the shared 2-core dev machine (load average ~4, medians of 60 updates; ``ours``
and ``replay`` alternated 3 times): C++ beam model 21.1-21.8 ms (final error 17.7 cm); ours
87 ms stepping every point, 39-44 ms with the former skip table, 11.9-12.2 ms now (the
clearance of each cell's square, unclipped, ceil; compacted block-wise march:
``AMCL.raycast``), final error 7.4 cm both (the same ranges); our likelihood field
2.4-2.5 ms (7.5 cm).
"""

from __future__ import annotations

import os
import sys
import time

import numpy as np

N_PARTICLES = 2000
MAX_BEAMS = 60


def record(path: str) -> None:
    os.environ.setdefault("MUJOCO_GL", "osmesa")
    from mmpa.backends.twin.twin_maps import laser_pose2d, twin_map
    from mmpa.backends.twin.world import SimWorld

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
        scan_meta=np.array(  # LaserScan's angle_min ... range_max, in its order
            [
                s0.angle_min,
                s0.angle_max,
                s0.angle_increment,
                s0.time_increment,
                s0.scan_time,
                s0.range_min,
                s0.range_max,
            ]
        ),
        truth=np.array(truth),
    )
    print(f"recorded {len(odo)} scans, grid {grid.width} x {grid.height} -> {path}")
    ours(path)


def ours(path: str, old: str | None = None) -> None:
    """Time our AMCL (and, with ``old``, the AMCL of another copy of ``amcl.py``) on the
    recorded scans: both laser models, then the beam model of each module interleaved."""
    import importlib.util

    from mmpa.localization import amcl as new_mod
    from mmpa.maps.occupancy import OccupancyGrid
    from mmpa.robot.interfaces import LaserScan

    d = np.load(path)
    grid = OccupancyGrid(d["occ"], float(d["res"]), tuple(float(v) for v in d["origin"]))
    meta = d["scan_meta"]
    mods = {"mmpa": new_mod}
    if old:
        spec = importlib.util.spec_from_file_location("old_amcl", old)
        assert spec is not None and spec.loader is not None
        mods["old"] = importlib.util.module_from_spec(spec)
        sys.modules["old_amcl"] = mods["old"]
        spec.loader.exec_module(mods["old"])
    runs = [("mmpa", "likelihood_field")] + [(name, "beam") for name in mods]
    filters, times = {}, {}
    for name, model in runs:
        m = mods[name]
        cfg = m.AMCLConfig(
            min_particles=N_PARTICLES,
            max_particles=N_PARTICLES,
            max_beams=MAX_BEAMS,
            laser_model_type=model,
        )
        f = m.AMCL(grid, d["laser"], cfg, np.random.default_rng(0))
        f.set_initial_pose(d["truth"][0])
        filters[name, model], times[name, model] = f, []
    for o, r in zip(d["odom"], d["ranges"], strict=True):  # interleaved: the same load
        sc = LaserScan(*meta[:7], ranges=r, intensities=np.zeros_like(r))
        for key, f in filters.items():
            t = time.perf_counter()
            f.update(o, sc, force=True)
            times[key].append(time.perf_counter() - t)
    for (name, model), f in filters.items():
        e = f.pose_at(d["odom"][-1]) - d["truth"][-1]
        ts = times[name, model]
        print(
            f"{name} AMCL ({model}, {N_PARTICLES} particles, {MAX_BEAMS} beams, "
            f"{len(ts)} scans): {1000 * np.median(ts):.2f} ms median update, "
            f"final error {100 * np.hypot(*e[:2]):.1f} cm"
        )
    print(f"load average {os.getloadavg()[0]:.2f} (1 min)")


def replay(path: str) -> None:
    import amcl  # type: ignore[import-not-found]

    d = np.load(path)
    occ = d["occ"]
    # amcl.OccupancyGrid data: 0 free, 100 occupied, -1 unknown; list rows are y (size_y)
    state = np.where(occ >= 65, 100, np.where(occ < 0, -1, 0)).astype(int)
    grid = amcl.create_occupancy_grid_from_list(
        state.tolist(), float(d["res"]), float(d["origin"][0]), float(d["origin"][1])
    )
    f = amcl.AMCL(
        N_PARTICLES,
        N_PARTICLES,
        0.0,  # alpha_slow (Nav2 default 0: no random recovery particles)
        0.0,  # alpha_fast
        amcl.MotionParameters(0.2, 0.2, 0.2, 0.2, 0.2),  # Nav2 alpha1..alpha5
        # z_hit, z_short, z_max, z_rand, sigma_hit, lambda_short, chi_outlier, max_beams
        amcl.LaserParameters(0.5, 0.05, 0.05, 0.5, 0.2, 0.1, 0.05, MAX_BEAMS),
        "differential",
    )
    f.set_map(grid)
    f.set_laser_pose(amcl.Vector3D(*map(float, d["laser"])))
    f.set_initial_pose(
        amcl.Vector3D(*map(float, d["truth"][0])),
        amcl.create_diagonal_covariance(0.25, 0.25, 0.068),
    )
    ts = []
    rmax = float(d["range_max"])
    for o, r in zip(d["odom"], d["ranges"], strict=True):
        ok = np.isfinite(r)
        pairs = np.column_stack([np.where(ok, r, rmax), d["angles"]]).tolist()
        sc = amcl.create_laser_scan_from_list(pairs, rmax)
        t = time.perf_counter()
        f.update(sc, amcl.Vector3D(*map(float, o)))
        ts.append(time.perf_counter() - t)
    p = f.get_pose_mean()
    e = np.array([p.x, p.y]) - d["truth"][-1][:2]
    print(
        f"C++ AMCL (pip amcl 0.1.2, Nav2 pf + BeamModel, {N_PARTICLES} particles, "
        f"{MAX_BEAMS} beams, {len(ts)} scans): {1000 * np.median(ts):.2f} ms median update, "
        f"final error {100 * np.hypot(*e):.1f} cm"
    )


if __name__ == "__main__":
    {"record": record, "replay": replay, "ours": ours}[sys.argv[1]](*sys.argv[2:])
