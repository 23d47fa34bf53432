"""A ROS 2 robot as one :class:`~mmpa.robot.interfaces.MobileManipulator`: the devices of the
robot file's ``backend.ros2`` section on one node (:class:`~.node.RobotNode`).

A device whose topic is ``""`` is absent (None): ``cmd_vel`` the base, ``odom`` the odometry,
``scan`` the lidar, ``joint_states`` the arm, ``gripper`` the gripper, any of ``color`` /
``depth`` / ``camera_info`` the camera; ``pose`` ``""``: no running localizer (mmpa localizes
itself). The clock is ``/clock`` with ``use_sim_time``, else the wall clock.
:meth:`Ros2Robot.connect` waits (one deadline, ``connect_timeout_s`` wall s) for the devices
a mission needs: each one's first message, and a subscriber on each command topic; what did
not answer is named in one :class:`~.node.DeviceTimeoutError`.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field

import rclpy

from mmpa.backends.bag.record import TOPICS
from mmpa.backends.ros2.devices.arm import Ros2Arm, Ros2Gripper
from mmpa.backends.ros2.devices.camera import Ros2Camera
from mmpa.backends.ros2.devices.mobile import (
    Ros2Base,
    Ros2Lidar,
    Ros2Odometry,
    Ros2PoseSource,
    SimClock,
    occupancy_grid,
    planar_pose,
    truth_pose,
)
from mmpa.backends.ros2.devices.node import DeviceTimeoutError, RobotNode, Ros2DeviceConfig
from mmpa.core.errors import ConfigError
from mmpa.core.geometry import Array
from mmpa.maps.occupancy import OccupancyGrid
from mmpa.robot.backend_config import BackendConfig
from mmpa.robot.description import RobotDescription
from mmpa.robot.interfaces import RobotDevices, WallClock
from mmpa.robot.limits import JointLimits

__all__ = ["DEVICES", "Ros2Robot", "ros2_robot"]

#: the device names :meth:`Ros2Robot.connect` knows
DEVICES = ("clock", "odometry", "base", "lidar", "camera", "arm", "gripper")


@dataclass
class Ros2Robot(RobotDevices):
    """The devices of a ROS 2 robot (module docstring); a context manager that closes its
    node. ``pose``: a running localizer's pose (None: none configured)."""

    node: RobotNode | None = None
    backend: BackendConfig = field(default_factory=BackendConfig)
    pose: Ros2PoseSource | None = None
    cfg: Ros2DeviceConfig = field(default_factory=Ros2DeviceConfig)

    @property
    def ok(self) -> bool:
        """Whether the node's ROS 2 context is up."""
        return self.node is not None and rclpy.ok(context=self.node.context)

    def _check(self, name: str, wait: float) -> None:
        node, dev = self.node, getattr(self, name, None)
        assert node is not None
        if name == "clock" and isinstance(dev, SimClock):
            dev.time  # noqa: B018 (waits for the first /clock)
        elif name == "odometry" and isinstance(dev, Ros2Odometry):
            node.first(dev.topic, wait)
        elif name == "base" and isinstance(dev, Ros2Base):
            node.wait_subscriber("base", dev.pub, wait)
        elif name == "lidar" and isinstance(dev, Ros2Lidar):
            node.first(dev.topic, wait)
        elif name == "camera" and isinstance(dev, Ros2Camera):
            node.first(dev.info, wait)
        elif name == "arm" and isinstance(dev, Ros2Arm):
            node.first(dev.joints, wait)
            if dev._traj is not None:
                node.wait_subscriber("arm", dev._traj, wait)
        elif name == "gripper" and isinstance(dev, Ros2Gripper):
            node.wait_subscriber("gripper", dev.pub, wait)

    def connect(self, devices: Iterable[str] | None = None) -> None:
        """Wait for ``devices`` (names of :data:`DEVICES`; None: every one present) to answer
        (module docstring); the absent ones are skipped (a mission's
        :func:`~mmpa.robot.interfaces.require` names them)."""
        names = list(DEVICES if devices is None else devices)
        unknown = sorted(set(names) - set(DEVICES))
        if unknown:
            raise ConfigError(f"unknown ROS 2 devices {unknown}; known: {', '.join(DEVICES)}")
        timeout = self.backend.ros2.connect_timeout_s
        deadline = time.monotonic() + timeout
        missing = []
        for name in names:
            try:
                self._check(name, max(0.05, deadline - time.monotonic()))
            except DeviceTimeoutError as e:
                missing.append(str(e))
        if missing:
            raise DeviceTimeoutError(
                f"the ROS 2 robot did not answer within {timeout:g} s: " + "; ".join(missing)
            )

    def occupancy_grid(self) -> tuple[OccupancyGrid, str]:
        """The map on ``topics.map`` with the reflectors of ``/reflectors`` when published;
        and where the reflectors came from (``"/reflectors"`` or ``"none"``)."""
        tp, node = self.backend.ros2, self.node
        assert node is not None
        if not tp.topics.map:
            raise ConfigError("this ROS 2 robot has no map topic (backend.ros2.topics.map)")
        return occupancy_grid(node, tp.topics.map, tp.connect_timeout_s, self.cfg.reflector_wait_s)

    def truth(self) -> Callable[[], Array] | None:
        """The twin node's true base pose ``[x, y, theta]`` in ``map`` (``/truth/base_pose``,
        evaluation only) as a function, or None when nothing publishes it."""
        assert self.node is not None
        t = truth_pose(self.node, TOPICS["truth_base"], self.cfg.truth_wait_s)
        return None if t is None else (lambda: planar_pose(t.msg)[1])

    def close(self) -> None:
        for dev in (self.arm,):
            if isinstance(dev, Ros2Arm):
                dev.close()
        if isinstance(self.base, Ros2Base) and self.ok:
            self.base.stop()
        if self.node is not None:
            self.node.close()
            self.node = None

    def __enter__(self) -> Ros2Robot:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def ros2_robot(
    backend: BackendConfig,
    description: RobotDescription,
    cfg: Ros2DeviceConfig | None = None,
    name: str = "mmpa_robot",
) -> Ros2Robot:
    """The devices of ``backend.ros2`` (module docstring) for the robot ``description`` (its
    arm's limits, the gripper's stroke), on a node named ``name``; nothing is waited for
    (:meth:`Ros2Robot.connect`)."""
    cfg = cfg or Ros2DeviceConfig()
    r, safety = backend.ros2, backend.safety
    tp, timeout = r.topics, r.connect_timeout_s
    node = RobotNode(name, r.domain_id)
    try:
        sim = SimClock(node, "/clock", timeout) if r.use_sim_time else None
        clock = sim if sim is not None else WallClock()
        odom = Ros2Odometry(node, tp.odom, timeout) if tp.odom else None
        base = Ros2Base(node, tp.cmd_vel, odom, safety.watchdog_s) if tp.cmd_vel else None
        lidar = Ros2Lidar(node, tp.scan, timeout) if tp.scan else None
        has_camera = bool(tp.color and tp.depth and tp.camera_info)
        camera = Ros2Camera(node, tp, sim, timeout) if has_camera else None
        limits = JointLimits.from_description(description.arm)
        arm = (
            Ros2Arm(node, tp, r.joint_names, limits, clock, safety, cfg, timeout)
            if tp.joint_states
            else None
        )
        stroke = description.gripper.stroke
        gripper = Ros2Gripper(node, tp.gripper, stroke, clock, cfg, timeout) if tp.gripper else None
        pose = Ros2PoseSource(node, tp.pose, odom, timeout) if tp.pose and odom else None
    except BaseException:
        node.close()
        raise
    return Ros2Robot(
        description, arm, camera, gripper, base, odom, lidar, clock, node, backend, pose, cfg
    )
