"""``mmpa ros2 twin`` over real DDS (docs/ros2.md "The twin as a ROS 2 robot"): the twin node
runs as its own process (the CLI, site 0, profile ideal, real time); this process is the
other side (an rclpy node of its own context). One twin serves the module's tests; each
test measures relative to the state it finds, so their order does not matter.

Skipped where the extra ``ros2`` is not installed.
"""

from __future__ import annotations

import os
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest

pytest.importorskip(
    "rclpy", reason="the ros2 extra is not installed (make setup installs it on x86-64 Linux)"
)

from tests.ros2_support import domain_id

from mmpa.backends.bag import messages as bag
from mmpa.backends.ros2 import graph, messages
from mmpa.backends.twin.scene import load_scene
from mmpa.core.geometry import T_to_se2
from mmpa.robot.description import default_robot

TIMEOUT = 60.0
TOPICS = {
    "/map": ("nav_msgs/msg/OccupancyGrid", graph.LATCHED),
    "/reflectors": ("visualization_msgs/msg/MarkerArray", graph.LATCHED),
    "/scan": ("sensor_msgs/msg/LaserScan", graph.SENSOR_DATA),
    "/odom": ("nav_msgs/msg/Odometry", graph.RELIABLE),
    "/truth/base_pose": ("geometry_msgs/msg/PoseStamped", graph.RELIABLE),
    "/joint_states": ("sensor_msgs/msg/JointState", graph.RELIABLE),
    "/clock": ("rosgraph_msgs/msg/Clock", graph.RELIABLE),
}
TRAJECTORY = "/scaled_joint_trajectory_controller/joint_trajectory"


def _stamp(header: Any) -> float:
    return float(header.stamp.sec) + 1e-9 * float(header.stamp.nanosec)


class Peer:
    """This process's node: keeps every message of :data:`TOPICS` (stamped ones by topic)."""

    def __init__(self, session: graph.Session) -> None:
        self.s = session
        self.got: dict[str, list[Any]] = {t: [] for t in TOPICS}
        for topic, (name, qos) in TOPICS.items():
            session.node.create_subscription(
                messages.message_class(name), topic, self.got[topic].append, qos
            )
        node = session.node
        self.cmd_vel = node.create_publisher(
            messages.message_class("geometry_msgs/msg/Twist"), "/cmd_vel", graph.RELIABLE
        )
        self.trajectory = node.create_publisher(
            messages.message_class("trajectory_msgs/msg/JointTrajectory"),
            TRAJECTORY,
            graph.RELIABLE,
        )

    def now(self) -> float:
        """The twin's time (s) of its last /clock."""
        self.s.spin_until(lambda: self.got["/clock"], TIMEOUT)
        c = self.got["/clock"][-1].clock
        return c.sec + 1e-9 * c.nanosec

    def wait_sim(self, seconds: float, tick: Any = None) -> float:
        """Spin until the twin's clock has advanced ``seconds``; ``tick()`` every 50 ms."""
        end = self.now() + seconds
        deadline = time.monotonic() + TIMEOUT
        while self.now() < end and time.monotonic() < deadline:
            if tick is not None:
                tick()
            self.s.spin_until(lambda: False, 0.05)
        return self.now()

    def truth(self) -> tuple[float, np.ndarray]:
        msg = self.got["/truth/base_pose"][-1]
        return _stamp(msg.header), T_to_se2(bag.from_pose(msg.pose))

    def joints(self) -> np.ndarray:
        msg = self.got["/joint_states"][-1]
        return np.array(
            [dict(zip(msg.name, msg.position, strict=True))[f"joint{i}"] for i in range(1, 7)]
        )

    def twist(self, v: float, w: float) -> Any:
        msg = messages.message_class("geometry_msgs/msg/Twist")()
        msg.linear.x, msg.angular.z = v, w
        return msg

    def at_rest(self) -> None:
        """Stop the base and wait until the true pose holds still (< 0.1 mm in 0.2 s)."""
        for _ in range(20):
            self.cmd_vel.publish(self.twist(0.0, 0.0))
            self.wait_sim(0.1)
            _, a = self.truth()
            self.wait_sim(0.2)
            _, b = self.truth()
            if np.hypot(*(b - a)[:2]) < 1e-4:
                return
        raise AssertionError("the base does not come to rest")


def _domain() -> str:
    return domain_id("twin")


@pytest.fixture(scope="module")
def twin(tmp_path_factory: pytest.TempPathFactory) -> Iterator[tuple[Peer, Path]]:
    """The twin node (``mmpa ros2 twin``) in its own process, and this process's peer."""
    logs = tmp_path_factory.mktemp("twin")
    env = {
        "ROS_DOMAIN_ID": _domain(),
        "ROS_AUTOMATIC_DISCOVERY_RANGE": "LOCALHOST",
        "RMW_IMPLEMENTATION": "rmw_fastrtps_cpp",
        "ROS_LOG_DIR": str(logs / "ros_log"),
    }
    saved = {k: os.environ.get(k) for k in env}
    os.environ.update(env)
    log = logs / "twin.log"
    cmd = "from mmpa.cli.main import main; main()"
    args = ["ros2", "twin", "--profile", "ideal", "--site", "0", "--duration", "300"]
    proc = subprocess.Popen(
        [sys.executable, "-c", cmd, *args], stdout=log.open("w"), stderr=subprocess.STDOUT
    )
    try:
        with graph.Session("mmpa_test_twin_peer") as s:
            peer = Peer(s)
            ok = s.spin_until(lambda: peer.got["/map"] and peer.got["/clock"], TIMEOUT)
            assert ok, f"no /map from the twin: {log.read_text()[-3000:]}"
            assert graph.wait_until_matched(peer.cmd_vel, 1, TIMEOUT)
            assert graph.wait_until_matched(peer.trajectory, 1, TIMEOUT)
            yield peer, log
    finally:
        proc.terminate()
        try:
            proc.wait(10)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()
        for k, v in saved.items():
            if v is None:
                os.environ.pop(k, None)
            else:
                os.environ[k] = v


def test_map_latched_with_the_scene_size_and_reflectors(twin: tuple[Peer, Path]) -> None:
    """/map reaches a late subscriber (transient local) with the size of the scene's floor
    plus the 0.5 m margin at 5 cm (computed here from the scene file), and /reflectors holds
    one marker per surveyed reflector."""
    peer, _ = twin
    grid = peer.got["/map"][0]
    sc = load_scene()
    (cx, cy), (sx, sy) = sc.floor_center, sc.floor_size
    assert grid.info.resolution == pytest.approx(0.05)
    assert (grid.info.width, grid.info.height) == (
        int(np.ceil((sx + 1.0) / 0.05)),
        int(np.ceil((sy + 1.0) / 0.05)),
    )
    assert len(grid.data) == grid.info.width * grid.info.height
    o = grid.info.origin.position
    assert (o.x, o.y) == pytest.approx((cx - sx / 2 - 0.5, cy - sy / 2 - 0.5))
    assert grid.header.frame_id == "map"
    peer.s.spin_until(lambda: peer.got["/reflectors"], TIMEOUT)
    assert len(peer.got["/reflectors"][0].markers) == len(sc.reflectors.positions)


def test_scan_arrives_with_the_lidar_beams(twin: tuple[Peer, Path]) -> None:
    peer, _ = twin
    assert peer.s.spin_until(lambda: len(peer.got["/scan"]) >= 2, TIMEOUT)
    scan = messages.from_laser_scan(peer.got["/scan"][-1])
    n = default_robot().lidar.num_beams
    assert n == 1440 and len(scan.ranges) == n
    assert scan.frame_id == "laser"
    assert np.isfinite(scan.ranges).sum() > n // 2  # the walls around site 0 return


def test_cmd_vel_drives_odom_and_truth_at_v(twin: tuple[Peer, Path]) -> None:
    """0.2 m/s forward: after a 0.5 s ramp, the true pose and /odom advance v * dt over the
    next ~1 s of sim time (dt from the stamps). Measured: 0.30-0.31 mm short of v * dt, both
    (ideal profile: odometry without error; two runs); the margin 3 mm is 10x that."""
    peer, _ = twin
    peer.at_rest()
    v = 0.2

    def drive() -> None:
        peer.cmd_vel.publish(peer.twist(v, 0.0))

    peer.wait_sim(0.5, drive)
    t1, p1 = peer.truth()
    odom = {_stamp(m.header): m for m in peer.got["/odom"]}
    peer.wait_sim(1.0, drive)
    t2, p2 = peer.truth()
    peer.cmd_vel.publish(peer.twist(0.0, 0.0))
    odom |= {_stamp(m.header): m for m in peer.got["/odom"]}
    dt = t2 - t1
    assert 0.9 < dt < 1.3
    assert np.hypot(*(p2 - p1)[:2]) == pytest.approx(v * dt, abs=0.003)
    o1, o2 = (T_to_se2(bag.from_pose(odom[t].pose.pose)) for t in (t1, t2))
    assert np.hypot(*(o2 - o1)[:2]) == pytest.approx(v * dt, abs=0.003)


def test_nan_cmd_vel_is_refused_and_nothing_moves(twin: tuple[Peer, Path]) -> None:
    """At rest, NaN /cmd_vel for 0.5 s: refused (logged), the base holds (< 0.1 mm); driving
    at 0.2 m/s, one NaN stops it as a zero twist does."""
    peer, log = twin
    peer.at_rest()
    _, p1 = peer.truth()
    peer.wait_sim(0.5, lambda: peer.cmd_vel.publish(peer.twist(0.3, float("nan"))))
    _, p2 = peer.truth()
    assert np.hypot(*(p2 - p1)[:2]) < 1e-4
    assert "refused /cmd_vel: a velocity is NaN" in log.read_text()
    # while driving at 0.2 m/s: one NaN stops the base as a zero twist does, not after the
    # 0.5 s timeout of /cmd_vel (which would leave it 0.2 m/s * 0.5 s = 100 mm further)
    coast = {}
    for stop in (0.0, float("nan")):
        peer.at_rest()
        peer.wait_sim(0.5, lambda: peer.cmd_vel.publish(peer.twist(0.2, 0.0)))
        _, a = peer.truth()
        peer.cmd_vel.publish(peer.twist(stop, 0.0))
        peer.wait_sim(0.6)
        _, b = peer.truth()
        coast[str(stop)] = float(np.hypot(*(b - a)[:2]))
    # measured: 3.2 mm after the NaN, 8.3 mm after the zero twist (where in the tick each
    # lands); a base that ran on to the timeout would coast >= 90 mm
    assert coast["nan"] < 0.04 and coast["0.0"] < 0.04, coast


def _trajectory(q: np.ndarray, times: list[float]) -> Any:
    JT = messages.message_class("trajectory_msgs/msg/JointTrajectory")
    JP = messages.message_class("trajectory_msgs/msg/JointTrajectoryPoint")
    msg = JT()
    msg.joint_names = [f"joint{i}" for i in range(1, 7)]
    for qi, t in zip(q, times, strict=True):
        p = JP()
        p.positions = [float(x) for x in qi]
        p.time_from_start.sec, p.time_from_start.nanosec = int(t), round(t % 1 * 1e9)
        msg.points.append(p)
    return msg


def test_trajectories_past_the_limits_are_refused_a_good_one_runs(
    twin: tuple[Peer, Path],
) -> None:
    """joint 1 by 1 rad in 0.1 s (10 rad/s, past every UR joint's limit) and a path whose
    times do not increase are refused: the joints hold (< 1 mrad); then joint 1 by 0.05 rad
    in 1 s is followed (measured: within 1e-6 rad of the target 0.5 s after its end; 1 mrad)."""
    peer, log = twin
    peer.wait_sim(0.1)
    q0 = peer.joints()
    fast = q0 + np.array([1.0, 0, 0, 0, 0, 0])
    peer.trajectory.publish(_trajectory(np.array([fast]), [0.1]))
    peer.trajectory.publish(_trajectory(np.array([q0, q0]), [0.5, 0.5]))
    peer.wait_sim(0.5)
    np.testing.assert_allclose(peer.joints(), q0, atol=1e-3)
    text = log.read_text()
    assert f"refused {TRAJECTORY}: joint trajectory: joint 1 velocity" in text
    assert f"refused {TRAJECTORY}: joint trajectory: time stamps must increase" in text
    good = q0 + np.array([0.05, 0, 0, 0, 0, 0])
    peer.trajectory.publish(_trajectory(np.array([good]), [1.0]))
    peer.wait_sim(1.5)
    np.testing.assert_allclose(peer.joints(), good, atol=1e-3)
