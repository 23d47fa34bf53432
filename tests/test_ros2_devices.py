"""The ROS 2 backend's devices (mmpa.backends.ros2.devices) over real DDS.

Against ``mmpa ros2 twin`` (its own process: profile ideal, site 0, the camera at 5 Hz, real
time): the base's odometry and the lidar and camera agree with the twin's truth, the arm's
motions reach their targets (the encoders and ``/truth/tcp_pose`` agree), commands past the
limits are refused before anything is sent and the twin node refuses nothing. Without a
twin: a missing robot times out naming each device and topic; a peer in this process plays
a driver (``/joint_states``, ``/scan``) to test the watchdog and the scan refusals.

Each module uses a ``ROS_DOMAIN_ID`` of its own (215..232, apart from the other DDS tests'
1..100) and discovery on localhost; skipped where the extra ``ros2`` is not installed.
"""

from __future__ import annotations

import os
import subprocess
import sys
import threading
import time
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip(
    "rclpy", reason="the ros2 extra is not installed (make setup installs it on x86-64 Linux)"
)

from tests.ros2_support import domain_number

from mmpa.backends.bag import messages as bag
from mmpa.backends.ros2 import graph, messages
from mmpa.backends.ros2.devices.arm import min_jerk_path, scaled_limits
from mmpa.backends.ros2.devices.mobile import planar_pose
from mmpa.backends.ros2.devices.node import DeviceTimeoutError
from mmpa.backends.ros2.devices.robot import Ros2Robot, ros2_robot
from mmpa.core.errors import InvalidInputError, JointLimitError, MMPAError
from mmpa.core.geometry import T_to_se2, se2_compose, se2_inv, wrap_angle
from mmpa.localization.amcl import AMCL
from mmpa.robot.backend_config import BackendConfig, Ros2Backend, SafetyConfig
from mmpa.robot.description import default_robot
from mmpa.robot.interfaces import LaserScan
from mmpa.robot.kinematics import fk
from mmpa.robot.limits import path_velocities

TWIN_JOINTS = tuple(f"joint{i}" for i in range(1, 7))


def domain(tag: str) -> int:
    """A DDS domain for this process and ``tag`` (tests.ros2_support.domain_number: never
    one a test in another pytest worker uses at the same time)."""
    return domain_number(tag)


def backend(dom: int, use_sim_time: bool = True, **ros2: object) -> BackendConfig:
    """A ``ros2`` backend for the twin node on domain ``dom`` (its joint names, no running
    localizer), full speed, a 2 s watchdog (this 2-core machine is shared)."""
    fields: dict[str, object] = {
        "joint_names": TWIN_JOINTS,
        "use_sim_time": use_sim_time,
        "domain_id": dom,
        "connect_timeout_s": 60.0,
        "topics": {"pose": ""},
    }
    fields.update(ros2)
    return BackendConfig(
        kind="ros2",
        ros2=Ros2Backend.model_validate(fields),
        safety=SafetyConfig(speed_scale=1.0, watchdog_s=2.0),
    )


def start_twin(log: Path, dom: int, *args: str) -> subprocess.Popen:
    """``mmpa ros2 twin ARGS`` in its own process on domain ``dom``, output to ``log``."""
    env = dict(os.environ)
    env |= {
        "ROS_DOMAIN_ID": str(dom),
        "ROS_AUTOMATIC_DISCOVERY_RANGE": "LOCALHOST",
        "RMW_IMPLEMENTATION": "rmw_fastrtps_cpp",
        "ROS_LOG_DIR": str(log.parent / "ros_log"),
        "MUJOCO_GL": env.get("MUJOCO_GL", "osmesa"),
    }
    cmd = "from mmpa.cli.main import main; main()"
    return subprocess.Popen(
        [sys.executable, "-c", cmd, "ros2", "twin", *args],
        stdout=log.open("w"),
        stderr=subprocess.STDOUT,
        env=env,
    )


def stop(proc: subprocess.Popen) -> None:
    proc.terminate()
    try:
        proc.wait(10)
    except subprocess.TimeoutExpired:
        proc.kill()
        proc.wait()


@pytest.fixture(autouse=True)
def _localhost(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")
    monkeypatch.setenv("RMW_IMPLEMENTATION", "rmw_fastrtps_cpp")


@pytest.fixture(scope="module")
def twin(tmp_path_factory: pytest.TempPathFactory) -> Iterator[tuple[Ros2Robot, Path]]:
    """The twin node with its camera, and this process's ROS 2 robot connected to it."""
    log = tmp_path_factory.mktemp("twin") / "twin.log"
    dom = domain("devices")
    os.environ.setdefault("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")
    args = ["--profile", "ideal", "--site", "0", "--camera", "--camera-rate", "5"]
    proc = start_twin(log, dom, *args, "--duration", "600")
    try:
        with ros2_robot(backend(dom), default_robot(), name="mmpa_test_devices") as robot:
            try:
                robot.connect()
            except DeviceTimeoutError as e:
                raise AssertionError(f"{e}\n{log.read_text()[-3000:]}") from None
            yield robot, log
    finally:
        stop(proc)


def _at_rest(robot: Ros2Robot) -> np.ndarray:
    """Stop the base, wait until the truth holds still (< 0.1 mm in 0.2 s); its pose."""
    truth = robot.truth()
    assert truth is not None
    robot.base.stop()
    for _ in range(30):
        a = truth()
        robot.step(0.2)
        b = truth()
        if np.hypot(*(b - a)[:2]) < 1e-4:
            return b
    raise AssertionError("the base does not come to rest")


def test_base_drives_odometry_and_truth_alike(twin: tuple[Ros2Robot, Path]) -> None:
    """0.2 m/s for 1 s of the robot's clock, then at rest: the motion /odom saw (its end
    in its start's frame) equals the truth's (ideal profile: odometry without error).
    Measured: 0.0002 mm and 0.001 mrad apart; the margins 1 mm and 2 mrad."""
    robot, _ = twin
    p0, o0 = _at_rest(robot), robot.odometry.odometry().pose
    t_end = robot.time + 1.0
    while robot.time < t_end:
        robot.base.set_velocity(0.2, 0.0)
        robot.step(0.05)
    p1, o1 = _at_rest(robot), robot.odometry.odometry().pose
    truth = se2_compose(se2_inv(p0), p1)
    odom = se2_compose(se2_inv(o0), o1)
    assert 0.15 < truth[0] < 0.3
    assert np.hypot(*(odom - truth)[:2]) < 1e-3
    assert abs(wrap_angle(odom[2] - truth[2])) < 2e-3


def test_lidar_agrees_with_the_map_at_the_true_pose(twin: tuple[Ros2Robot, Path]) -> None:
    """The latest /scan against ranges ray-cast in /map from the true laser pose (the
    nominal mount; ideal profile: the map is not warped). Measured: median |difference|
    12.3 mm over all 1440 beams (the map's 5 cm cells); the bound 30 mm."""
    robot, _ = twin
    p = _at_rest(robot)
    scan = robot.lidar.scan()
    assert isinstance(scan, LaserScan) and len(scan.ranges) == 1440
    grid, src = robot.occupancy_grid()
    assert src == "/reflectors" and len(grid.reflectors) >= 3
    mount = T_to_se2(default_robot().lidar.T_base_link_laser)
    expected = AMCL(grid, mount).raycast(p[None], scan.angles, scan.range_max)[0]
    both = scan.valid() & (expected < scan.range_max - 0.1)
    assert both.sum() > 700
    assert np.median(np.abs(scan.ranges[both] - expected[both])) < 0.03


def test_camera_sees_the_floor_where_the_truth_says(twin: tuple[Ros2Robot, Path]) -> None:
    """A fresh frame (stamped no earlier than the call) of camera_info's size; its depth
    against the floor plane z = 0 seen from /truth/camera_pose (the arm at home looks
    straight down). Measured: |depth - plane| median 0.34 mm, p95 0.48 mm (16-bit mm
    depth); the bound on the p95 2 mm, and 95 % of the pixels on the floor."""
    robot, _ = twin
    assert robot.node is not None
    pose = "geometry_msgs/msg/PoseStamped"
    cam = robot.node.subscribe("truth", "/truth/camera_pose", pose, keep=20)
    robot.node.first(cam, 30.0)
    t_call = robot.time
    frame = robot.camera.capture()
    k = robot.camera.intrinsics
    assert frame.stamp >= t_call
    assert frame.color.shape == (k.height, k.width, 3) and frame.depth.shape == (k.height, k.width)
    ok = cam.wait(lambda: any(planar_pose(m)[0] == frame.stamp for _, m in cam.history), 30)
    assert ok, "no /truth/camera_pose of the frame's stamp"
    msg = next(m for _, m in cam.snapshot() if planar_pose(m)[0] == frame.stamp)
    T = bag.from_pose(msg.pose)
    v, u = np.mgrid[0 : k.height, 0 : k.width]
    rays = np.stack([(u - k.cx) / k.fx, (v - k.cy) / k.fy, np.ones(u.shape)], -1) @ T[:3, :3].T
    plane = -T[2, 3] / rays[..., 2]  # depth along the optical axis where the ray meets z = 0
    diff = np.abs(frame.depth - plane)
    floor = (frame.depth > 0) & (diff < 0.05)
    assert floor.mean() > 0.95
    assert np.percentile(diff[floor], 95) < 0.002
    # the images are unsubscribed once the camera is idle, and no more of them arrive (the
    # twin node renders for a subscriber only); camera_info keeps coming
    from mmpa.backends.ros2.devices.camera import IDLE_S

    color, info = robot.camera.color, robot.camera.info
    deadline = time.monotonic() + IDLE_S + 5.0
    while color.subscription is not None and time.monotonic() < deadline:
        time.sleep(0.05)
    assert color.subscription is None
    n_color, n_info = color.count, info.count
    assert info.wait(lambda: info.count > n_info + 3, 30.0)
    assert color.count == n_color


def _tcp_truth(robot: Ros2Robot, T_map_base: np.ndarray) -> np.ndarray:
    """The TCP position (m, map) the encoders imply on the true base pose (4x4: the base
    sits 0.25 mm low and tilted 0.3 mrad on its wheels; nominal = true kinematics in the
    ideal profile)."""
    d = default_robot()
    q = robot.arm.joint_positions()
    return (T_map_base @ d.T_base_link_arm_base @ fk(d.arm.dh, q, d.gripper.T_flange_tcp))[:3, 3]


def test_arm_follow_reaches_its_target_the_truth_agrees(twin: tuple[Ros2Robot, Path]) -> None:
    """A 1.5 s minimum-jerk path (joints 1 and 6) sent on the trajectory topic: the encoders
    end within the goal tolerance (1 mrad; measured 3e-7 rad), with ``record_hz`` the
    recorded encoders start at the path's start, and /truth/tcp_pose equals the forward
    kinematics of the encoders on the true base pose (measured 3e-16 m; bound 10 um)."""
    robot, log = twin
    arm = robot.arm
    assert robot.node is not None
    tcp = robot.node.subscribe("truth", "/truth/tcp_pose", "geometry_msgs/msg/PoseStamped")
    base = robot.node.subscribe("truth", "/truth/base_pose", "geometry_msgs/msg/PoseStamped")
    robot.node.first(tcp, 30.0)
    robot.node.first(base, 30.0)
    q0 = arm.joint_positions()
    q1 = q0 + np.array([0.15, 0.0, 0.0, 0.0, 0.0, -0.2])
    t, path = min_jerk_path(q0, q1, scaled_limits(arm.limits, 0.2), 1.5, 50.0)
    n_sent = len(arm.sent)
    rec = arm.follow(t, path, record_hz=10.0)
    assert len(arm.sent) == n_sent + 1 and arm.sent[-1][0] == "trajectory"
    assert np.max(np.abs(arm.joint_positions() - q1)) < 1e-3
    assert rec is not None and len(rec[0]) >= 10
    assert np.max(np.abs(rec[1][0] - q0)) < 2e-3
    robot.step(0.1)
    T, T_base = bag.from_pose(tcp.msg.pose), bag.from_pose(base.msg.pose)
    assert np.linalg.norm(T[:3, 3] - _tcp_truth(robot, T_base)) < 1e-5
    arm.move_joints(q0)
    assert np.max(np.abs(arm.joint_positions() - q0)) < 1e-3
    assert "refused" not in log.read_text()


def test_commands_past_the_limits_are_refused_before_sending(
    twin: tuple[Ros2Robot, Path],
) -> None:
    """A target past joint 1's upper limit, a NaN, and a path at 10x joint 1's speed
    limit are refused here (JointLimitError / InvalidInputError) with nothing published
    and the joints still; a NaN velocity stops the base; the twin node refused nothing."""
    robot, log = twin
    arm = robot.arm
    q0 = arm.joint_positions()
    n_sent = len(arm.sent)
    over = q0.copy()
    over[0] = arm.limits.q_max[0] + 0.01
    with pytest.raises(JointLimitError, match="joint 1"):
        arm.move_joints(over)
    with pytest.raises(InvalidInputError, match="NaN"):
        arm.command(np.full(6, np.nan))
    fast = q0 + np.array([10 * arm.limits.qd_max[0] * 0.1, 0, 0, 0, 0, 0])
    with pytest.raises(JointLimitError, match="joint 1 velocity"):
        arm.follow(np.array([0.0, 0.1]), np.array([q0, fast]))
    with pytest.raises(InvalidInputError, match="finite"):
        robot.base.set_velocity(float("nan"), 0.0)
    assert len(arm.sent) == n_sent
    robot.step(0.3)
    assert np.max(np.abs(arm.joint_positions() - q0)) < 1e-4
    assert "refused" not in log.read_text()


def test_stream_reaches_its_target_within_the_limits(twin: tuple[Ros2Robot, Path]) -> None:
    """``command(q)`` streams set-points toward q (joint 6 by 0.1 rad): the encoders arrive
    within 1 mrad in 3 s of the robot's clock, and the published set-points' speeds keep
    within the stream limits (the robot clock's 20 ms ticks as their times)."""
    robot, log = twin
    arm = robot.arm
    q0 = arm.joint_positions()
    q1 = q0 + np.array([0, 0, 0, 0, 0, 0.1])
    n_sent = len(arm.sent)
    end = robot.time + 3.0
    arm.command(q1)
    while robot.time < end and np.max(np.abs(arm.joint_positions() - q1)) > 1e-3:
        robot.step(0.1)
    arm.stop_stream()
    assert np.max(np.abs(arm.joint_positions() - q1)) < 1e-3
    sent = [s for s in list(arm.sent)[n_sent:] if s[0] == "stream"]
    t = np.array([s[1][0] for s in sent])
    q = np.array([s[2][0] for s in sent])
    assert len(sent) > 5 and np.all(np.diff(t) > 0)
    v = np.abs(path_velocities(t, q))
    assert np.all(v <= arm.stream_limits.qd_max * (1 + 1e-6))
    arm.move_joints(q0)
    assert "refused" not in log.read_text()


def test_a_missing_robot_times_out_naming_each_device() -> None:
    """No robot on the domain: connect fails after the timeout with one message naming
    each device, its topic, the wait and the domain."""
    dom = domain("missing")
    cfg = backend(dom, connect_timeout_s=1.0)
    with ros2_robot(cfg, default_robot(), name="mmpa_test_missing") as robot:
        t0 = time.monotonic()
        with pytest.raises(DeviceTimeoutError) as e:
            robot.connect(["clock", "lidar", "arm", "base", "camera"])
        assert time.monotonic() - t0 < 5.0
    msg = str(e.value)
    for part in (
        "within 1 s",
        f"ROS_DOMAIN_ID {dom}",
        "clock: no message on /clock",
        "lidar: no message on /scan",
        "arm: no message on /joint_states",
        "base: nothing subscribes to /cmd_vel",
        "camera: no message on /camera/color/camera_info",
    ):
        assert part in msg, msg


class Driver:
    """A driver played in this process (a node of its own context): publishes
    ``/joint_states`` at 50 Hz while ``running`` and scans on demand, listens to the
    streaming topic."""

    def __init__(self, s: graph.Session) -> None:
        self.s = s
        mc = messages.message_class
        self.js = s.node.create_publisher(mc("sensor_msgs/msg/JointState"), "/joint_states", 10)
        self.scan = s.node.create_publisher(mc("sensor_msgs/msg/LaserScan"), "/scan", 10)
        self.stream: list[object] = []
        s.node.create_subscription(
            mc("std_msgs/msg/Float64MultiArray"),
            "/forward_position_controller/commands",
            self.stream.append,
            10,
        )
        self.running = threading.Event()
        self.running.set()
        self._done = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()

    def _run(self) -> None:
        q = np.zeros(6)
        while not self._done.is_set():
            if self.running.is_set():
                self.js.publish(
                    messages.to_rclpy(bag.joint_state(time.time(), list(TWIN_JOINTS), q))
                )
            self.s.spin_once(0.02)

    def close(self) -> None:
        self._done.set()
        self._thread.join(5)


def test_watchdog_stops_the_stream_and_bad_scans_are_dropped() -> None:
    """A peer's /joint_states stop: within the watchdog (0.3 s) the stream stops,
    ``stopped()`` names the topic and the next command fails; a scan with an angle
    increment of 0 is dropped (counted, logged), the next good one is returned."""
    dom = domain("watchdog")
    topics = {"pose": "", "arm_trajectory": ""}
    cfg = backend(dom, use_sim_time=False, connect_timeout_s=20.0, topics=topics)
    cfg = cfg.model_copy(update={"safety": SafetyConfig(speed_scale=1.0, watchdog_s=0.3)})
    os.environ["ROS_DOMAIN_ID"] = str(dom)
    try:
        peer = graph.Session("mmpa_test_driver")
    finally:
        os.environ.pop("ROS_DOMAIN_ID")
    driver = Driver(peer)
    try:
        with ros2_robot(cfg, default_robot(), name="mmpa_test_watchdog") as robot:
            robot.connect(["arm"])
            arm = robot.arm
            arm.command(np.array([0.0, 0, 0, 0, 0, 0.05]))
            assert peer.spin_until(lambda: len(driver.stream) > 3, 10.0) or driver.stream
            driver.running.clear()
            time.sleep(0.8)
            assert "no /joint_states" in (arm.stopped() or "")
            with pytest.raises(MMPAError, match="/joint_states"):
                arm.command(np.zeros(6))
            n = len(driver.stream)
            time.sleep(0.3)
            assert len(driver.stream) == n  # nothing more streamed
            assert graph.wait_until_matched(driver.scan, 1, 10.0)
            good = LaserScan(-1.0, 1.0, 0.5, 0.0, 0.1, 0.1, 10.0, np.ones(5), np.zeros(5), 1.0)
            bad = messages.laser_scan(good)
            bad.angle_increment = 0.0
            driver.scan.publish(bad)
            driver.scan.publish(messages.laser_scan(good))
            scan = robot.lidar.scan()
            assert scan.angle_increment == 0.5 and len(scan.ranges) == 5
            assert robot.lidar.topic.refused == 1 and robot.lidar.topic.count == 1
    finally:
        driver.close()
        peer.close()
