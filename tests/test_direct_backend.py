"""The direct backend (UR over RTDE + RealSense over its SDK): its devices from the robot
file's backend section, against the recording FAKE of RTDE (mmpa.backends.ur_fake) and a
RealSense recording played by the SDK; connection failures name the device and what was
tried."""

from __future__ import annotations

import threading
import time

import numpy as np
import pytest

pytest.importorskip("pyrealsense2", reason="the optional extra 'realsense'")

from tests.ros2_support import domain_number

from mmpa.backends import direct
from mmpa.backends.realsense import RealSenseCamera, record_frames
from mmpa.backends.ur import URArm
from mmpa.backends.ur_fake import FakeRTDE
from mmpa.core.errors import ConfigError, InvalidInputError, MMPAError
from mmpa.robot.backend_config import BackendConfig, DirectBackend, SafetyConfig
from mmpa.robot.description import CameraIntrinsics, default_robot
from mmpa.robot.interfaces import RGBDFrame, WallClock

ROBOT = default_robot()
HOME = np.array(ROBOT.arm.home)


def _cfg(**direct) -> BackendConfig:
    return BackendConfig(
        kind="direct",
        direct=DirectBackend(**direct),
        safety=SafetyConfig(speed_scale=0.5, watchdog_s=0.2),
    )


def _recording(path) -> str:
    k = CameraIntrinsics(width=32, height=24, fx=30.0, fy=30.0, cx=15.5, cy=11.5)
    frame = RGBDFrame(np.zeros((24, 32, 3), np.uint8), np.ones((24, 32), np.float32), k, 0.0)
    return str(record_frames([frame, frame], path))


def test_direct_devices_from_the_backend_section(tmp_path, monkeypatch) -> None:
    fake = FakeRTDE(HOME)
    tried = []

    def connect(host, frequency):
        tried.append((host, frequency))
        return fake, fake

    monkeypatch.setattr(direct, "connect_rtde", connect)
    cfg = _cfg(ur_host="10.0.0.7", ur_frequency=125.0, realsense_playback=_recording(
        tmp_path / "cam.db3"))  # fmt: skip
    with direct.open_direct(cfg, ROBOT) as robot:
        assert isinstance(robot.arm, URArm) and isinstance(robot.camera, RealSenseCamera)
        assert robot.base is None and robot.gripper is None and robot.lidar is None
        assert isinstance(robot.clock, WallClock)
        assert robot.arm.cfg.speed_scale == 0.5 and robot.arm.cfg.watchdog_s == 0.2
        assert robot.arm.cfg.frequency == 125.0
        np.testing.assert_allclose(robot.arm.joint_positions(), HOME)
        assert robot.camera.capture().depth[0, 0] == pytest.approx(1.0)
    assert tried == [("10.0.0.7", 125.0)]
    assert fake.calls[-1][1] == "disconnect"  # closed with the block
    with direct.open_direct(_cfg(ur_host="10.0.0.7", camera=False), ROBOT) as robot:
        assert robot.camera is None and robot.arm is not None


def test_connection_failures_name_the_device(tmp_path) -> None:
    missing = tmp_path / "none.db3"
    with (
        pytest.raises(InvalidInputError, match=rf"RealSense recording {missing}.*no RealSense"),
        direct.open_direct(_cfg(realsense_playback=missing), ROBOT),
    ):
        pass
    with (
        pytest.raises(MMPAError, match=r"UR (arm )?at 192\.0\.2\.1"),
        direct.open_direct(_cfg(ur_host="192.0.2.1", camera=False), ROBOT),
    ):
        pass  # here: no ur-rtde; with it: no controller at that (test-net) address
    with (
        pytest.raises(ConfigError, match="kind direct"),
        direct.open_direct(BackendConfig(), ROBOT),
    ):
        pass


def test_open_robot_opens_the_direct_kind(tmp_path, monkeypatch) -> None:
    """The mission commands' open_robot (apps.robots) hands a direct robot file to
    open_direct."""
    robots = pytest.importorskip("mmpa.apps.robots", reason="the hardware robots module")
    from mmpa.robot.robot_file import robot_to_yaml

    fake = FakeRTDE(HOME)
    monkeypatch.setattr(direct, "connect_rtde", lambda host, f: (fake, fake))
    path = tmp_path / "robot.yaml"
    path.write_text(robot_to_yaml(ROBOT, backend=_cfg(ur_host="10.0.0.7", camera=False)))
    with robots.open_robot(path) as robot:
        assert isinstance(robot.arm, URArm) and robot.camera is None
        np.testing.assert_allclose(robot.arm.joint_positions(), HOME)


def test_a_base_over_ros2_beside_the_rtde_arm(monkeypatch) -> None:
    """``direct.base: ros2``: the base (``/cmd_vel``) and odometry (``/odom``) over real DDS
    from a peer playing the base's driver, the arm over RTDE (the fake) in the same robot;
    the ROS 2 arm, camera and gripper topics are not read (no ``/joint_states`` needed)."""
    pytest.importorskip("rclpy", reason="the ros2 extra is not installed")

    from mmpa.backends.bag import messages as bag
    from mmpa.backends.ros2 import graph, messages
    from mmpa.backends.ros2.devices.robot import Ros2Robot
    from mmpa.robot.backend_config import Ros2Backend
    from mmpa.robot.interfaces import Odometry

    monkeypatch.setenv("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")
    dom = domain_number("direct-base")
    fake = FakeRTDE(HOME)
    monkeypatch.setattr(direct, "connect_rtde", lambda host, f: (fake, fake))
    ros2 = Ros2Backend(domain_id=dom, connect_timeout_s=20.0, topics={"scan": "", "pose": ""})
    cfg = _cfg(ur_host="10.0.0.7", camera=False, base="ros2").model_copy(update={"ros2": ros2})
    monkeypatch.setenv("ROS_DOMAIN_ID", str(dom))
    peer = graph.Session("mmpa_test_direct_base")
    mc = messages.message_class
    twists: list = []
    peer.node.create_subscription(mc("geometry_msgs/msg/Twist"), "/cmd_vel", twists.append, 10)
    odom = peer.node.create_publisher(mc("nav_msgs/msg/Odometry"), "/odom", 10)
    o = Odometry(np.array([1.0, 2.0, 0.3]), np.zeros(2), 5.0)
    done = threading.Event()

    def drive() -> None:
        while not done.is_set():
            odom.publish(messages.to_rclpy(bag.odometry(o)))
            peer.spin_once(0.05)

    thread = threading.Thread(target=drive, daemon=True)
    thread.start()
    try:
        with direct.open_direct(cfg, ROBOT) as robot:
            assert isinstance(robot, Ros2Robot) and isinstance(robot.arm, URArm)
            assert robot.camera is None and robot.gripper is None and robot.lidar is None
            np.testing.assert_allclose(robot.odometry.odometry().pose, o.pose)
            np.testing.assert_allclose(robot.arm.joint_positions(), HOME)
            robot.base.set_velocity(0.1, -0.2)
            deadline = time.monotonic() + 10.0
            while not any(t.linear.x == 0.1 for t in twists) and time.monotonic() < deadline:
                time.sleep(0.05)
            sent = next(t for t in twists if t.linear.x == 0.1)
            assert sent.angular.z == -0.2
        assert fake.calls[-1][1] == "disconnect"
    finally:
        done.set()
        thread.join(5)
        peer.close()
