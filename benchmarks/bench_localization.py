"""Localization speed and memory (run on purpose: ``python benchmarks/bench_localization.py``).

- one AMCL filter update: 2000 particles, 60 beams, likelihood field (target <= 5 ms median);
- one enhanced-AMCL update (detection + triangle matching + trilateration + Algorithm 1);
- reflector detection + identification alone;
- memory of a 100 m x 100 m map at 5 cm: grid + distance field as the filter holds them.
"""

from __future__ import annotations

import os
import resource
import time

os.environ.setdefault("MUJOCO_GL", "osmesa")

import numpy as np

from mmpa.backends.twin.twin_maps import laser_pose2d, twin_map
from mmpa.backends.twin.world import SimWorld
from mmpa.localization.amcl import AMCL, AMCLConfig
from mmpa.localization.enhanced import EnhancedAMCL
from mmpa.maps.occupancy import Box2D, rasterize


def _median_ms(fn, n: int = 50) -> float:
    ts = []
    for _ in range(n):
        t = time.perf_counter()
        fn()
        ts.append(time.perf_counter() - t)
    return 1000 * float(np.median(ts))


def main() -> None:
    with SimWorld(site="1") as w:
        grid = twin_map(w)
        lp = laser_pose2d(w)
        scan = w.lidar.scan()
        odom = w.odometry.odometry().pose
        cfg = AMCLConfig(min_particles=2000, max_particles=2000, max_beams=60)
        amcl = AMCL(grid, lp, cfg, np.random.default_rng(0))
        amcl.set_initial_pose(w.truth.base_pose2d())
        t_amcl = _median_ms(lambda: amcl.update(odom, scan, force=True))
        t_lf = _median_ms(lambda: amcl.likelihood_field(amcl.particles, *amcl._beams(scan)))
        enh = EnhancedAMCL(grid, lp, rng=np.random.default_rng(0))
        enh.set_initial_pose(w.truth.base_pose2d())
        t_enh = _median_ms(lambda: enh.update(odom, scan, force=True))
        t_obs = _median_ms(lambda: enh.observer.observe(scan))
        r, a = amcl._beams(scan, 90)
        t_prob = _median_ms(
            lambda: amcl.log_likelihood_field(amcl.particles, r, a, 0.03, 0.025, signed=True)
        )
        beam = AMCL(grid, lp, cfg.model_copy(update={"laser_model_type": "beam"}))
        beam.set_initial_pose(w.truth.base_pose2d())
        t_beam = _median_ms(lambda: beam.update(odom, scan, force=True), n=10)
    print(f"load average at start: {os.getloadavg()[0]:.1f} on {os.cpu_count()} cores")
    print(f"AMCL update (2000 particles, 60 beams, likelihood field): {t_amcl:.2f} ms median")
    print(f"  of which the likelihood field itself: {t_lf:.2f} ms")
    print(f"enhanced AMCL update (incl. reflector observation): {t_enh:.2f} ms median")
    print(f"  reflector detection + triangle matching + trilateration: {t_obs:.2f} ms")
    print(f"  product-form signed likelihood field (< 3 reflectors, 90 beams): {t_prob:.2f} ms")
    print(f"AMCL update with the beam model (2000 particles, 60 beams): {t_beam:.1f} ms median")
    rss0 = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    big = rasterize([Box2D((0.0, 0.0), (100.0, 0.1))], (-50, -50, 50, 50), 0.05)
    t = time.perf_counter()
    a = AMCL(big, np.zeros(3), AMCLConfig(), np.random.default_rng(0))
    t_build = time.perf_counter() - t
    mb = (big.data.nbytes + a._dist.nbytes + a._free_cells.nbytes) / 2**20
    mib = 2**20
    print(f"100 m x 100 m map at 5 cm: {big.width} x {big.height} cells")
    print(f"  grid {big.data.nbytes / mib:.1f} MiB, distance field {a._dist.nbytes / mib:.1f} MiB,")
    print(f"  likelihood table {a._pz3_table().nbytes / mib:.1f} MiB (built on the first scan),")
    sdf = a._signed_padded(0.025).nbytes / mib
    print(f"  signed distance field {sdf:.1f} MiB (enhanced AMCL, built when < 3 reflectors),")
    print(f"  free-cell index {a._free_cells.nbytes / mib:.1f} MiB; set-up {t_build:.2f} s")
    print(f"  total without the table {mb:.1f} MiB")
    rss1 = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    print(f"  peak RSS of this process: {rss0:.0f} MiB before the big map, {rss1:.0f} MiB after")
    print("Nav2 AMCL C++ (pip amcl, beam model only): see benchmarks/bench_amcl_cpp.py")


if __name__ == "__main__":
    main()
