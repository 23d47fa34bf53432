"""Scan-to-pose latency of ``mmpa ros2 localization`` at 1440 beams against the library's own
update time on the same sequence.

    .venv/bin/python benchmarks/bench_ros2_localization.py [--scans 40] [--period 0.2]

The sequence and settings are the DDS test's (tests/test_ros2_localization.py: the synthetic
room, the params file, the beam model at 180 of the beams) with 1440-beam scans. The node runs
as ``mmpa ros2 localization`` in its own process; this process stamps ``time.monotonic()``
right before it publishes each scan and again when the ``/amcl_pose`` of that scan's stamp
has been received (its subscription callback ran and ``spin_until`` returned, 0.04 ms
later, measured: ``spin_once`` returns as soon as a callback ran, its 10 ms timeout is no
granularity). The node reports its own ``update()`` time of each scan on ``/diagnostics``
(``update_ms``), so the latency is also paired scan by scan with the library's update that
produced it. Then the library alone (``build_localizer`` and ``update`` on the same scans and
odometry, same seed) times ``update`` in this process. Prints the medians and p95, the
latency over the library's update (medians of two separate runs: the update's time swings
by ~10 % between runs of the same code on this machine) and, per scan, the latency minus and
over the node's own update (the node's overhead: DDS both ways, the scan's and tf's
conversion, the pose message).
"""

from __future__ import annotations

import argparse
import os
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # tests.* (its test module imports)
sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))

import test_ros2_localization as seq
from mmpa.backends.ros2 import graph, localization_msgs, messages
from mmpa.core.geometry import se2_to_T
from mmpa.localization.config import AMCLConfig
from mmpa.localization.settings import (
    LocalizationConfig,
    build_localizer,
    start_localizer,
)


def _update_ms(msg: object, into: dict[float, float]) -> None:
    """The node's ``update_ms`` on ``/diagnostics`` by the scan's stamp."""
    for st in msg.status:
        for kv in st.values:
            if kv.key == "update_ms":
                into[round(localization_msgs.stamp_of(msg.header), 6)] = 1e-3 * float(kv.value)


def _node_latencies(n: int, period: float, tmp: Path) -> tuple[list[float], list[float]]:
    """Per scan whose pose came back: scan published -> its ``/amcl_pose`` received (s),
    and the node's own ``update()`` on that scan (s, from ``/diagnostics``; nan if lost)."""
    node = seq._node(tmp / "amcl.yaml")
    sent: dict[float, float] = {}
    lat: dict[float, float] = {}
    upd: dict[float, float] = {}
    try:
        with graph.Session("mmpa_bench_player") as s:
            p = seq.Player(s)
            s.node.create_subscription(
                messages.message_class("diagnostic_msgs/msg/DiagnosticArray"),
                "/diagnostics",
                lambda m: _update_ms(m, upd),
                graph.TF,
            )
            assert p.ready(), "the node did not come up"
            grid = seq._grid()
            p.map.publish(messages.to_rclpy(seq.bag.occupancy_grid(grid, seq.T0)))
            mount = se2_to_T(*seq.MOUNT)
            p.static.publish(messages.tf_message(seq.T0, [("base_link", "lidar_mount", mount)]))
            s.spin_until(lambda: False, 1.0)
            rng = np.random.default_rng(3)
            for k in range(n):
                t = seq.T0 + seq.DT * k
                odom = se2_to_T(*seq._odom(k))
                p.tf.publish(messages.tf_message(t, [("odom", "base_link", odom)]))
                msg = messages.laser_scan(seq._scan(grid, k, rng))
                sent[round(t, 6)] = time.monotonic()
                p.scan.publish(msg)
                got = len(p.poses)
                s.spin_until(lambda got=got: len(p.poses) > got, period)
                if len(p.poses) > got and round(p.poses[-1][0], 6) in sent:
                    key = round(p.poses[-1][0], 6)
                    lat[key] = time.monotonic() - sent[key]
                s.spin_until(
                    lambda: False, max(0.0, period - (time.monotonic() - sent[round(t, 6)]))
                )
    finally:
        seq._stop(node)
    return list(lat.values()), [upd.get(k, np.nan) for k in lat]


def _library_times(n: int) -> list[float]:
    import yaml

    params = yaml.safe_load(seq.PARAMS)["amcl"]["ros__parameters"]
    cfg = LocalizationConfig(method="amcl", amcl=AMCLConfig(**params))
    grid = seq._grid()
    loc = build_localizer(cfg, grid, seq.MOUNT, np.random.default_rng(1))
    start_localizer(loc, "amcl", seq._truth(0) + seq.START_ERROR)
    rng = np.random.default_rng(3)
    out = []
    for k in range(n):
        scan = seq._scan(grid, k, rng)
        t0 = time.perf_counter()
        est = loc.update(seq._odom(k), scan)
        if est.updated:
            out.append(time.perf_counter() - t0)
    return out


def _callback_times(n: int) -> tuple[list[float], list[float]]:
    """The node's scan callback in this process, fed the same messages directly (no DDS):
    its wall time per scan and the localizer's update time inside it."""
    import yaml

    from mmpa.apps.ros2_localization import LocalizationNode

    params = yaml.safe_load(seq.PARAMS)["amcl"]["ros__parameters"]
    start = seq._truth(0) + seq.START_ERROR
    params |= {"base_frame_id": "base_link", "set_initial_pose": True, "seed": 1}
    params |= {"initial_pose.x": start[0], "initial_pose.y": start[1]}
    params["initial_pose.yaw"] = start[2]
    args = ["bench", "--ros-args"]
    for k, v in params.items():
        args += ["-p", f"{k}:={v}"]
    grid = seq._grid()
    with graph.Session("amcl", args) as s:
        node = LocalizationNode(s)
        node.on_map(messages.to_rclpy(seq.bag.occupancy_grid(grid, seq.T0)))
        mount = se2_to_T(*seq.MOUNT)
        node.on_tf(messages.tf_message(seq.T0, [("base_link", "lidar_mount", mount)]), True)
        rng = np.random.default_rng(3)
        wall = []
        for k in range(n):
            t = seq.T0 + seq.DT * k
            node.on_tf(
                messages.tf_message(t, [("odom", "base_link", se2_to_T(*seq._odom(k)))]), False
            )
            msg = messages.laser_scan(seq._scan(grid, k, rng))
            t0 = time.perf_counter()
            node.on_scan(msg)
            wall.append(time.perf_counter() - t0)
        return wall[1:], list(node.update_times)[1:]  # the first builds the localizer


def _scan_to_numpy(reps: int = 2000) -> tuple[float, float]:
    """Median s of ``from_laser_scan`` (the whole LaserScan) and ``scan_ranges`` (the ranges
    as a numpy view) on a 1440-beam message."""
    msg = messages.laser_scan(seq._scan(seq._grid(), 0, np.random.default_rng(0)))
    out = []
    for f in (messages.from_laser_scan, messages.scan_ranges):
        ts = []
        for _ in range(reps):
            t0 = time.perf_counter()
            f(msg)
            ts.append(time.perf_counter() - t0)
        out.append(float(np.median(ts)))
    return out[0], out[1]


def _row(name: str, xs: list[float]) -> str:
    a = 1e3 * np.asarray(xs)
    med, p95 = np.median(a), np.percentile(a, 95)
    return f"{name:34s} n={a.size:3d}  median {med:7.2f} ms  p95 {p95:7.2f} ms"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scans", type=int, default=40)
    ap.add_argument("--period", type=float, default=0.2, help="s between scans (wall)")
    a = ap.parse_args()
    seq.N_BEAMS = 1440
    os.environ.setdefault("ROS_DOMAIN_ID", "61")
    os.environ.setdefault("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")
    with tempfile.TemporaryDirectory() as tmp:
        os.environ.setdefault("ROS_LOG_DIR", tmp)
        lat, node_upd = _node_latencies(a.scans, a.period, Path(tmp))
    lib = _library_times(a.scans)
    cb, cb_update = _callback_times(a.scans)
    full, view = _scan_to_numpy()
    print(f"1440 beams, {a.scans} scans, one every {a.period} s")
    print(_row("node: scan published -> /amcl_pose", lat))
    print(_row("library: update()", lib))
    print(f"node overhead (medians): {1e3 * (np.median(lat) - np.median(lib)):.2f} ms")
    print(f"latency / library (medians): {np.median(lat) / np.median(lib):.2f}")
    paired = np.asarray(lat) - np.asarray(node_upd)
    ok = np.isfinite(paired)
    print(_row("  its update() in the node", list(np.asarray(node_upd)[ok])))
    print(_row("  latency - its update, per scan", list(paired[ok])))
    ratio = np.median(np.asarray(lat)[ok] / np.asarray(node_upd)[ok])
    print(f"latency / its update in the node (median per scan): {ratio:.2f}")
    print(_row("node callback (no DDS): on_scan", cb))
    print(_row("  its update() inside", cb_update))
    print(f"callback / its update (medians): {np.median(cb) / np.median(cb_update):.2f}")
    print(f"scan -> numpy: from_laser_scan {1e6 * full:.1f} us, scan_ranges {1e6 * view:.2f} us")


if __name__ == "__main__":
    main()
