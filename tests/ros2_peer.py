"""One side of a ROS 2 exchange for tests/test_ros2.py, run as its own process.

    python tests/ros2_peer.py pub scan|tf IN.(npz|json)    publish what IN holds, once
    python tests/ros2_peer.py sub scan|tf OUT.(npz|json)   write what arrives to OUT

Each prints ``matched`` once its publisher / subscription has matched the other side. The
publisher then waits for a line on stdin before it publishes (the test sends it when both
sides have matched), and stays until the subscriber has left. The subscriber records the
type hash that the remote publisher announced during discovery.
"""

from __future__ import annotations

import json
import sys
import time

import numpy as np

from mmpa.backends.ros2 import graph, messages
from mmpa.robot.interfaces import LaserScan

TOPICS = {"scan": ("/scan", "sensor_msgs/msg/LaserScan"), "tf": ("/tf", "tf2_msgs/msg/TFMessage")}
TIMEOUT = 20.0


def _message(kind: str, path: str) -> object:
    if kind == "scan":
        d = np.load(path)
        meta = json.loads(str(d["meta"]))
        scan = LaserScan(ranges=d["ranges"], intensities=d["intensities"], **meta)
        return messages.laser_scan(scan)
    d = json.loads(open(path).read())
    tfs = [(p, c, np.asarray(Tm, float)) for p, c, Tm in d["transforms"]]
    return messages.tf_message(d["stamp"], tfs)


def publish(kind: str, path: str) -> int:
    topic, name = TOPICS[kind]
    msg = _message(kind, path)
    with graph.Session(f"mmpa_test_pub_{kind}") as s:
        pub = s.node.create_publisher(messages.message_class(name), topic, graph.RELIABLE)
        if not graph.wait_until_matched(pub, 1, TIMEOUT):
            print("no subscriber matched", file=sys.stderr)
            return 1
        print("matched", flush=True)
        sys.stdin.readline()
        pub.publish(msg)
        # reliable delivery: stay until the subscriber has received it and left
        deadline = time.monotonic() + TIMEOUT
        while graph.matched(pub) > 0 and time.monotonic() < deadline:
            time.sleep(0.01)
    return 0


def _record(kind: str, msg: object, path: str, hashes: list[str]) -> None:
    if kind == "scan":
        scan = messages.from_laser_scan(msg)
        meta = {k: getattr(scan, k) for k in ("angle_min", "angle_max", "angle_increment")}
        meta |= {k: getattr(scan, k) for k in ("time_increment", "scan_time", "range_min")}
        meta |= {"range_max": scan.range_max, "stamp": scan.stamp, "frame_id": scan.frame_id}
        meta["hashes"] = hashes
        np.savez(path, ranges=scan.ranges, intensities=scan.intensities, meta=json.dumps(meta))
        return
    out = [(t, p, c, Tm.tolist()) for t, p, c, Tm in messages.from_tf_message(msg)]
    with open(path, "w") as f:
        json.dump({"transforms": out, "hashes": hashes}, f)


def subscribe(kind: str, path: str) -> int:
    topic, name = TOPICS[kind]
    got: list[object] = []
    with graph.Session(f"mmpa_test_sub_{kind}") as s:
        sub = s.node.create_subscription(
            messages.message_class(name), topic, got.append, graph.RELIABLE
        )
        if not graph.wait_until_matched(sub, 1, TIMEOUT):
            print("no publisher matched", file=sys.stderr)
            return 1
        hashes = [str(i.topic_type_hash) for i in s.node.get_publishers_info_by_topic(topic)]
        print("matched", flush=True)
        if not s.spin_until(lambda: bool(got), TIMEOUT):
            print("nothing arrived", file=sys.stderr)
            return 1
        _record(kind, got[0], path, hashes)
    return 0


if __name__ == "__main__":
    role, kind, file = sys.argv[1:4]
    sys.exit(publish(kind, file) if role == "pub" else subscribe(kind, file))
