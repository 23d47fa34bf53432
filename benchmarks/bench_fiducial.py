"""Speed of the paper 002 fiducial-search passes (run on purpose:
``python benchmarks/bench_fiducial.py``).

Measures the wall time of one pass (Algorithm 1 in the kinematic twin) per strategy at 1, 2 and
3 cm/s, its real-time factor (simulated pass time / wall time), and, as a reference measured in
the same run, the same simulated time spent in a bare ``mj_step`` physics loop, so that numbers
from different machines compare by their ratios. Target: the 180-pass sweep of the paper's two
strategies in <= 10 minutes, i.e. <= ~3.3 s per pass. Always exits 0.
"""

from __future__ import annotations

import os

os.environ.setdefault("MUJOCO_GL", "osmesa")

import time

import mujoco
import numpy as np

from mmpa.backends.twin.moving_base import KinematicMovingBase, MovingBaseNoise
from mmpa.backends.twin.world import SimWorld
from mmpa.fiducial_search import SearchConfig, make_strategy, run_pass

TARGET_PASS_S = 600.0 / 180


def main() -> None:
    with SimWorld(site="0") as w:
        fa = w.scene.fiducial_artifact
        assert fa is not None
        origin = np.array(fa.origin)
        P = origin + np.array(fa.fiducials)
        start = np.array([origin[0], origin[1], 0.0])
        sim_total, wall_total, n = 0.0, 0.0, 0
        for name in ("stochastic", "spiral", "stochastic-tuned"):
            for v in (0.01, 0.02, 0.03):
                rob = KinematicMovingBase(w, start, MovingBaseNoise(), np.random.default_rng(1))
                t0 = time.perf_counter()
                res = run_pass(
                    rob,
                    w.nominal,
                    P,
                    fa.plate_height,
                    fa.tube_height,
                    start,
                    v,
                    0.0,
                    make_strategy(name),
                    SearchConfig(),
                    np.random.default_rng(2),
                )
                wall = time.perf_counter() - t0
                sim_total += res.duration
                wall_total += wall
                n += 1
                print(
                    f"{name:17s} {v * 100:.0f} cm/s: {res.n_intercepted}/6, sim {res.duration:6.1f}"
                    f" s, wall {wall:5.2f} s, x{res.duration / wall:6.0f} real time"
                )
        m, d = w.model, w.data
        steps = 5000
        t0 = time.perf_counter()
        for _ in range(steps):
            mujoco.mj_step(m, d)
        per_step = (time.perf_counter() - t0) / steps
        physics = sim_total / n / m.opt.timestep * per_step
    print(
        f"mean pass {wall_total / n:.2f} s wall (target <= {TARGET_PASS_S:.2f} s); the same "
        f"simulated time in bare mj_step physics: {physics:.2f} s "
        f"(ratio {physics / (wall_total / n):.1f}x)"
    )


if __name__ == "__main__":
    main()
