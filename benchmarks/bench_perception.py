"""Speed of the detector and the tracking servo loop (``python benchmarks/bench_perception.py
[weights.pt ...]``).

Measures
  (a) detector inference per 320x240 frame (network + decoding + NMS; batch 1, median of 30
      frames after warm-up) for each weights file (default: the shipped model, plus
      ``src/mmpa/perception/weights/ssd_pruned.pt`` when present), with parameters and MACs;
  (b) the tracking servo loop in the twin at 20 Hz control: wall time per tick including the
      RGB-D capture (render + noise) at the servo loop's stream profile (320x240,
      ``mmpa.experiments.paper001.grasp.SERVO_RESOLUTION``; and at 640x480 for comparison),
      detection, 3D location, IBVS + null space and 0.05 s of physics; and the part of it
      that is mmpa's own code (detection + location + control), which is what a real robot
      would run per frame.
Targets (issue 6): detector <= 30 ms per frame, servo loop >= 20 Hz. Always exits 0.
"""

from __future__ import annotations

import os

os.environ.setdefault("MUJOCO_GL", "osmesa")
if os.environ["MUJOCO_GL"] == "osmesa":
    os.environ.setdefault("PYOPENGL_PLATFORM", "osmesa")

import sys
import time
from pathlib import Path

import numpy as np

TARGET_MS = 30.0
TARGET_HZ = 20.0


def bench_detector(path: Path | None) -> None:
    import torch

    from mmpa.perception.prune import macs
    from mmpa.perception.ssd import Detector

    torch.set_num_threads(int(os.environ.get("MMPA_THREADS", "2")))
    det = Detector.load(path)
    rng = np.random.default_rng(0)
    img = rng.integers(0, 255, (240, 320, 3), dtype=np.uint8)
    for _ in range(5):
        det.detect(img)
    ts = []
    for _ in range(30):
        t = time.perf_counter()
        det.detect(img)
        ts.append(1000 * (time.perf_counter() - t))
    n = sum(p.numel() for p in det.model.parameters())
    name = path.name if path else "shipped ssd.pt"
    ms = float(np.median(ts))
    print(
        f"detector {name}: {ms:.1f} ms/frame median (p90 {np.percentile(ts, 90):.1f}), "
        f"{n / 1e3:.0f} k parameters, {macs(det.cfg) / 1e6:.0f} M MACs, channels "
        f"{det.cfg.channels} -> {'OK' if ms <= TARGET_MS else 'ABOVE'} target {TARGET_MS} ms"
    )


def bench_servo(resolution: tuple[int, int]) -> None:
    from mmpa.backends.twin.world import SimWorld
    from mmpa.experiments.paper001.grasp import Config, grasp_trial, make_grasper

    with SimWorld(site="0") as w:
        g = make_grasper(Config(), w)
        row = grasp_trial(
            w, g, "tennis_ball", "normal", np.random.default_rng(0), resolution=resolution
        )
    loop = row["loop_ms"]
    own = row["detect_ms"]
    cap = row["capture_ms"]
    print(
        f"servo loop in the twin at {resolution[0]}x{resolution[1]}: {loop:.0f} ms/tick wall "
        f"({1000 / loop:.1f} Hz): RGB-D capture "
        f"(render + noise, the twin) {cap:.0f} ms, detection + location {own:.0f} ms, control + "
        f"physics {loop - cap - own:.0f} ms; mmpa's own part {1000 / own:.0f} Hz; grasped "
        f"{row['grasped']} in {row['time_to_grasp']:.1f} s sim -> "
        f"{'OK' if 1000 / loop >= TARGET_HZ else 'BELOW'} target {TARGET_HZ} Hz"
    )


def main() -> None:
    paths: list[Path | None] = [Path(p) for p in sys.argv[1:]] or [None]
    pruned = Path(__file__).parents[1] / "src/mmpa/perception/weights/ssd_pruned.pt"
    if not sys.argv[1:] and pruned.is_file():
        paths.append(pruned)
    for p in paths:
        try:
            bench_detector(p)
        except Exception as e:  # keep going: a benchmark always reports
            print(f"detector {p}: failed: {e}")
    from mmpa.experiments.paper001.grasp import SERVO_RESOLUTION

    for res in (SERVO_RESOLUTION, (640, 480)):
        try:
            bench_servo(res)
        except Exception as e:
            print(f"servo loop at {res}: failed: {e}")


if __name__ == "__main__":
    main()
