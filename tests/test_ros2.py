"""mmpa over ROS 2 Jazzy (the extra ``ros2``; docs/ros2.md): the converters against an
independent serializer (rosbags), the built interface packages' type hashes against rosbags'
Jazzy hashes, and messages crossing from one process to another over Fast DDS.

DDS tests: two processes (tests/ros2_peer.py), a ``ROS_DOMAIN_ID`` of their own per test
(from the pytest worker, the pid and the test), discovery on localhost only; the publisher
publishes once both sides have matched. Skipped where the extra is not installed.
"""

from __future__ import annotations

import json
import os
import selectors
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip(
    "rclpy", reason="the ros2 extra is not installed (make setup installs it on x86-64 Linux)"
)

from rclpy.serialization import deserialize_message, serialize_message
from tests.ros2_support import domain_id

from mmpa.backends.bag import messages as bag
from mmpa.backends.ros2 import messages
from mmpa.core.geometry import make_T
from mmpa.robot.interfaces import LaserScan

PEER = Path(__file__).with_name("ros2_peer.py")
TIMEOUT = 60.0


def _scan(seed: int = 7, n: int = 1440) -> LaserScan:
    """A 1440-beam scan with returns, misses (inf) and reflector intensities."""
    rng = np.random.default_rng(seed)
    ranges = rng.uniform(0.1, 29.0, n)
    ranges[rng.random(n) < 0.1] = np.inf
    inten = rng.uniform(0.0, 4000.0, n)
    inc = 2 * np.pi / n
    return LaserScan(
        angle_min=-np.pi,
        angle_max=-np.pi + inc * (n - 1),
        angle_increment=inc,
        time_increment=1e-5,
        scan_time=0.025,
        range_min=0.05,
        range_max=30.0,
        ranges=ranges,
        intensities=inten,
        stamp=12.345678901,
        frame_id="laser",
    )


def test_fast_scan_equals_the_cdr_bridge_bytes_and_reads_back() -> None:
    """rclpy's serializer on the fast path == rosbags' serializer on the bag builder."""
    scan = _scan()
    fast = messages.laser_scan(scan)
    name = "sensor_msgs/msg/LaserScan"
    ref = bytes(messages.typestore().serialize_cdr(bag.laser_scan(scan), name))
    assert serialize_message(fast) == ref
    assert serialize_message(messages.to_rclpy(bag.laser_scan(scan))) == ref
    back = messages.from_laser_scan(fast)
    np.testing.assert_array_equal(back.ranges, scan.ranges.astype(np.float32))
    np.testing.assert_array_equal(back.intensities, scan.intensities.astype(np.float32))
    assert np.isinf(back.ranges).sum() == np.isinf(scan.ranges).sum() > 0
    np.testing.assert_array_equal(messages.scan_ranges(fast), scan.ranges.astype(np.float32))
    assert back.angle_min == scan.angle_min  # rclpy keeps a double until it serializes
    wire = messages.from_laser_scan(deserialize_message(ref, type(fast)))
    assert wire.angle_min == float(np.float32(scan.angle_min)) != scan.angle_min
    np.testing.assert_array_equal(wire.ranges, back.ranges)
    assert (fast.header.stamp.sec, fast.header.stamp.nanosec) == (12, 345678901)
    assert messages.type_name(fast) == name


@pytest.mark.parametrize(
    "name",
    [
        "tf2_msgs/msg/TFMessage",
        "tf2_msgs/msg/TF2Error",
        "nav2_msgs/msg/ParticleCloud",
        "nav2_msgs/msg/Particle",
        "sensor_msgs/msg/LaserScan",
    ],
)
def test_built_type_hash_equals_rosbags(name: str) -> None:
    """The hash rosidl wrote for the type (share/PKG/msg/NAME.json, what rclpy announces)
    == the one rosbags computes from the Jazzy definitions (tf2_msgs: rosbags' own Jazzy
    store; nav2_msgs: the same .msg text, hashed by rosbags' independent implementation)."""
    pkg, _, cls = name.split("/")
    # the ros-* wheels and scripts/ros2-interfaces.sh install into the venv's prefix
    desc = json.loads((Path(sys.prefix) / "share" / pkg / "msg" / f"{cls}.json").read_text())
    built = {h["type_name"]: h["hash_string"] for h in desc["type_hashes"]}[name]
    assert built == messages.typestore().hash_rihs01(name)
    if name == "tf2_msgs/msg/TFMessage":  # the Jazzy hash, written down
        assert built.startswith("RIHS01_e369d0f05a23ae52508854b66f6aa0437f3449d652e8cbf22d5a")


def _env(tmp_path: Path, request: pytest.FixtureRequest) -> dict[str, str]:
    worker = os.environ.get("PYTEST_XDIST_WORKER", "gw-")
    key = f"{worker}:{os.getpid()}:{request.node.nodeid}".encode()
    env = dict(os.environ)
    env |= {
        "ROS_DOMAIN_ID": domain_id(key.decode()),
        "ROS_AUTOMATIC_DISCOVERY_RANGE": "LOCALHOST",
        "RMW_IMPLEMENTATION": "rmw_fastrtps_cpp",
        "ROS_LOG_DIR": str(tmp_path / "ros_log"),
    }
    return env


def _readline(proc: subprocess.Popen, timeout: float) -> str:
    with selectors.DefaultSelector() as sel:
        sel.register(proc.stdout, selectors.EVENT_READ)
        if not sel.select(timeout):
            return ""
    return proc.stdout.readline().strip()


def _exchange(kind: str, src: Path, dst: Path, env: dict[str, str], logs: Path) -> None:
    """Subscriber and publisher as two processes; ``go`` once both have matched."""
    procs = {}
    for role, file in (("sub", dst), ("pub", src)):
        procs[role] = subprocess.Popen(
            [sys.executable, str(PEER), role, kind, str(file)],
            stdin=subprocess.PIPE,
            stdout=subprocess.PIPE,
            stderr=(logs / f"{role}.log").open("w"),
            text=True,
            env=env,
        )
    try:
        lines = {role: _readline(p, TIMEOUT) for role, p in procs.items()}
        assert lines == {"sub": "matched", "pub": "matched"}, (lines, _logs(logs))
        procs["pub"].stdin.write("go\n")
        procs["pub"].stdin.flush()
        for role, p in procs.items():
            assert p.wait(TIMEOUT) == 0, (role, _logs(logs))
    finally:
        for p in procs.values():
            if p.poll() is None:
                p.kill()
                p.wait()


def _logs(logs: Path) -> str:
    return "\n".join(f"{f.name}: {f.read_text()[-2000:]}" for f in sorted(logs.glob("*.log")))


def test_scan_crosses_processes_over_dds(tmp_path: Path, request: pytest.FixtureRequest) -> None:
    scan = _scan(seed=11)
    meta = {k: getattr(scan, k) for k in ("angle_min", "angle_max", "angle_increment")}
    meta |= {k: getattr(scan, k) for k in ("time_increment", "scan_time", "range_min")}
    meta |= {"range_max": scan.range_max, "stamp": scan.stamp, "frame_id": scan.frame_id}
    np.savez(
        tmp_path / "in.npz",
        ranges=scan.ranges,
        intensities=scan.intensities,
        meta=json.dumps(meta),
    )
    _exchange("scan", tmp_path / "in.npz", tmp_path / "out.npz", _env(tmp_path, request), tmp_path)
    got = np.load(tmp_path / "out.npz")
    gmeta = json.loads(str(got["meta"]))
    np.testing.assert_array_equal(got["ranges"], scan.ranges.astype(np.float32))
    np.testing.assert_array_equal(got["intensities"], scan.intensities.astype(np.float32))
    f32 = {k: float(np.float32(meta[k])) for k in ("angle_min", "angle_increment", "range_max")}
    assert {k: gmeta[k] for k in f32} == f32
    assert gmeta["frame_id"] == "laser"
    assert round(gmeta["stamp"] * 1e9) == round(scan.stamp * 1e9)
    assert gmeta["hashes"] == [messages.typestore().hash_rihs01("sensor_msgs/msg/LaserScan")]


def test_tf_message_crosses_processes_over_dds(
    tmp_path: Path, request: pytest.FixtureRequest
) -> None:
    a = 0.7
    R = np.array([[np.cos(a), 0, np.sin(a)], [0, 1, 0], [-np.sin(a), 0, np.cos(a)]])
    sent = [
        ("map", "odom", [0.25, -1.5, 0.3]),  # planar [x, y, theta]
        ("base_link", "laser", make_T(R, [0.2, 0.0, 0.35]).tolist()),
    ]
    (tmp_path / "in.json").write_text(json.dumps({"stamp": 3.5, "transforms": sent}))
    _exchange("tf", tmp_path / "in.json", tmp_path / "out.json", _env(tmp_path, request), tmp_path)
    got = json.loads((tmp_path / "out.json").read_text())
    assert got["hashes"] == [messages.typestore().hash_rihs01("tf2_msgs/msg/TFMessage")]
    (t0, p0, c0, T0), (t1, p1, c1, T1) = got["transforms"]
    assert (t0, p0, c0, t1, p1, c1) == (3.5, "map", "odom", 3.5, "base_link", "laser")
    c, s = np.cos(0.3), np.sin(0.3)
    planar = make_T([[c, -s, 0], [s, c, 0], [0, 0, 1]], [0.25, -1.5, 0.0])
    # rotation -> quaternion -> rotation in float64: ~1e-16; 1e-12 leaves a margin of 1e4
    np.testing.assert_allclose(T0, planar, rtol=0, atol=1e-12)
    np.testing.assert_allclose(T1, make_T(R, [0.2, 0.0, 0.35]), rtol=0, atol=1e-12)


@pytest.mark.parametrize(("n", "frame_id"), [(0, "map"), (1, "m"), (7, "abcdefgh"), (1000, "map")])
def test_particle_cloud_bytes_equal_the_serializers(n: int, frame_id: str) -> None:
    """The numpy-built ParticleCloud bytes == rosbags' serialization of rclpy's message (which
    zeroes the padding rclpy leaves as it finds it), and rclpy reads them back to the same
    particles."""
    from mmpa.backends.ros2 import localization_msgs as lm

    rng = np.random.default_rng(n)
    P, w = rng.normal(size=(n, 3)), rng.random(n)
    ref = lm.particle_cloud(12.3456789, frame_id, P, w)
    raw = lm.particle_cloud_cdr(12.3456789, frame_id, P, w)
    name = "nav2_msgs/msg/ParticleCloud"
    assert raw == bytes(messages.typestore().serialize_cdr(messages.from_rclpy(ref), name))
    back = deserialize_message(raw, type(ref))
    assert back == ref
