"""Real-time factor of the twin as a ROS 2 robot (``mmpa ros2 twin``; docs/ros2.md).

Runs :class:`mmpa.apps.ros2_twin.TwinNode` in this process unpaced (``speed`` 0: it steps as
fast as it can, publishing every topic as in real time) for ``--seconds`` of sim time, once
without the camera and once with it at ``--camera-rate`` Hz, and reports sim s / wall s (the
real-time factor it could sustain; >= 1 keeps up with the wall clock) and the messages
published, and the sim seconds per CPU second of the process (all its threads): on this
shared 2-core machine the wall clock counts other people's work too, the CPU time does not.
With the camera it also reports the cost of one frame (``SimCamera.capture``: render and
noise) in CPU ms (the process's, all threads, while it runs) and wall ms.
A subscriber process (``--subscribe``) takes the scan, /odom, /tf and the images
over DDS as a localization node would (so DDS serializes and sends them); the camera run
always has it (the node renders its images only for a subscriber).

    MUJOCO_GL=osmesa PYOPENGL_PLATFORM=osmesa OMP_NUM_THREADS=1 \\
        .venv/bin/python benchmarks/bench_ros2_twin.py [--seconds 10] [--profile realistic]
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import time

SUBSCRIBER = r"""
import sys, time
from mmpa.backends.ros2 import graph, messages
topics = [("/scan", "sensor_msgs/msg/LaserScan", graph.SENSOR_DATA),
          ("/odom", "nav_msgs/msg/Odometry", graph.RELIABLE),
          ("/tf", "tf2_msgs/msg/TFMessage", graph.RELIABLE),
          ("/camera/color/image_raw", "sensor_msgs/msg/Image", graph.SENSOR_DATA),
          ("/camera/aligned_depth_to_color/image_raw", "sensor_msgs/msg/Image", graph.SENSOR_DATA)]
n = {t: 0 for t, _, _ in topics}
with graph.Session("bench_twin_sub") as s:
    for t, name, qos in topics:
        s.node.create_subscription(messages.message_class(name), t,
                                   lambda m, t=t: n.__setitem__(t, n[t] + 1), qos)
    end = time.monotonic() + float(sys.argv[1])
    while time.monotonic() < end:
        s.spin_once(0.05)
print(n, flush=True)
"""


def _timed(obj: object, name: str) -> list[tuple[float, float]]:
    """Wrap the method ``obj.name`` (on the instance) to record (CPU s, wall s) per call."""
    calls: list[tuple[float, float]] = []
    method = getattr(obj, name)

    def timed(*args, **kwargs):
        c0, t0 = time.process_time(), time.perf_counter()
        try:
            return method(*args, **kwargs)
        finally:
            calls.append((time.process_time() - c0, time.perf_counter() - t0))

    setattr(obj, name, timed)
    return calls


def run(seconds: float, profile: str, camera: bool, rate: float, subscribe: bool) -> dict:
    from mmpa.apps.ros2_twin import TwinNode, twin_node_config

    cfg = twin_node_config("0", profile, 0, camera=camera, camera_rate_hz=rate, speed=0.0)
    sub = None
    if subscribe or camera:  # the node renders its images only for a subscriber
        sub = subprocess.Popen(
            [sys.executable, "-c", SUBSCRIBER, "600"], stdout=subprocess.PIPE, text=True
        )
    with TwinNode(cfg) as node:
        if sub is not None:
            time.sleep(3.0)  # discovery
        frames: list[tuple[float, float]] = []
        if camera:
            node.world.camera.capture()  # the renderer's first frame (context creation)
            frames = _timed(node.world.camera, "capture")
        cpu0 = time.process_time()
        stats = node.run(seconds)
        cpu = time.process_time() - cpu0
    if sub is not None:
        sub.terminate()
        sub.wait()
    return {
        "camera": f"{rate:g} Hz" if camera else "off",
        "sim_s": round(stats.sim_s, 2),
        "wall_s": round(stats.wall_s, 2),
        "rtf": round(stats.real_time_factor, 2),
        "cpu_s": round(cpu, 2),
        "rtf_cpu": round(stats.sim_s / cpu, 2),
        "published": stats.published,
        # mean (CPU ms, wall ms) of one camera frame
        "frame_ms": tuple(round(1e3 * sum(f[k] for f in frames) / len(frames), 1) for k in (0, 1))
        if frames
        else (),
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seconds", type=float, default=10.0, help="sim seconds per run")
    ap.add_argument("--profile", default="realistic")
    ap.add_argument("--camera-rate", type=float, default=15.0)
    ap.add_argument("--subscribe", action="store_true", help="a subscriber process takes them")
    a = ap.parse_args()
    os.environ.setdefault("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")
    os.environ.setdefault("ROS_DOMAIN_ID", "91")
    for camera in (False, True):
        r = run(a.seconds, a.profile, camera, a.camera_rate, a.subscribe)
        print(
            f"camera {r['camera']:>6}: {r['sim_s']} sim s in {r['wall_s']} s -> "
            f"real-time factor {r['rtf']}; {r['cpu_s']} s of CPU (all threads) -> "
            f"{r['rtf_cpu']} sim s per CPU s  ({r['published']})",
            flush=True,
        )
        if r["frame_ms"]:
            cpu_ms, wall_ms = r["frame_ms"]
            print(f"  one camera frame: {cpu_ms} ms CPU, {wall_ms} ms wall", flush=True)


if __name__ == "__main__":
    main()
