"""The robot file's ``backend:`` section: which robot the mission commands drive.

- ``kind: twin`` (the default): the MuJoCo digital twin, today's behaviour; the truth is known.
- ``kind: ros2``: a robot whose drivers speak ROS 2 (a base taking ``/cmd_vel``, a lidar on
  ``/scan``, realsense2_camera, ur_robot_driver, a gripper); topic names in ``ros2.topics``,
  frame names in the robot file's ``frames`` section. ``mmpa ros2 twin`` is such a robot.
- ``kind: direct``: the arm over RTDE (``ur_rtde``, ``direct.ur_host``) and the camera over
  the RealSense SDK (``direct.realsense_serial``, or ``direct.realsense_playback``: a ``.bag``
  recording played by the SDK); the base over ROS 2 (``direct.base: ros2``, with the
  ``ros2`` section's topics) or none (``direct.base: none``: a fixed-base arm is a valid robot).

``safety`` holds what a hardware backend enforces (the twin ignores none of it either: its
limits are the description's): ``speed_scale`` scales every commanded joint speed and
acceleration (0-1], ``watchdog_s`` is how long a stream or a drive may go without an answer
from the controller / the node before it is stopped, ``confirm`` asks before the arm moves
on hardware (``--yes`` skips the question, ``--dry-run`` stops before it).

Example::

    backend:
      kind: direct
      direct: {ur_host: 192.168.1.10, realsense_serial: "123456789012", base: none}
      safety: {speed_scale: 0.25, watchdog_s: 0.2}
"""

from __future__ import annotations

from pathlib import Path
from typing import Literal

from pydantic import BaseModel, ConfigDict, Field

__all__ = [
    "UR_JOINT_NAMES",
    "BackendConfig",
    "DirectBackend",
    "Ros2Backend",
    "Ros2Topics",
    "SafetyConfig",
]

#: ur_robot_driver's joint names, in the arm's order (base to wrist 3)
UR_JOINT_NAMES: tuple[str, ...] = (
    "shoulder_pan_joint",
    "shoulder_lift_joint",
    "elbow_joint",
    "wrist_1_joint",
    "wrist_2_joint",
    "wrist_3_joint",
)


class Ros2Topics(BaseModel):
    """Topic names of a ROS 2 robot (the drivers' defaults). An empty name: the device is
    absent (e.g. ``cmd_vel: ""`` for a fixed base)."""

    model_config = ConfigDict(frozen=True, extra="forbid")

    cmd_vel: str = "/cmd_vel"  # geometry_msgs/Twist to the base
    odom: str = "/odom"  # nav_msgs/Odometry of the base
    scan: str = "/scan"  # sensor_msgs/LaserScan
    pose: str = "/amcl_pose"  # PoseWithCovarianceStamped of a running localizer ("": mmpa's own)
    map: str = "/map"  # nav_msgs/OccupancyGrid (transient local)
    joint_states: str = "/joint_states"
    arm_trajectory: str = "/scaled_joint_trajectory_controller/joint_trajectory"
    arm_stream: str = "/forward_position_controller/commands"  # Float64MultiArray
    gripper: str = "/gripper/command"
    color: str = "/camera/color/image_raw"
    depth: str = "/camera/aligned_depth_to_color/image_raw"
    camera_info: str = "/camera/color/camera_info"


class Ros2Backend(BaseModel):
    """A ROS 2 robot: topics, joint names, the DDS domain and how long to wait for it."""

    model_config = ConfigDict(frozen=True, extra="forbid")

    topics: Ros2Topics = Ros2Topics()
    joint_names: tuple[str, ...] = UR_JOINT_NAMES
    domain_id: int | None = Field(None, ge=0, le=232)  # None: $ROS_DOMAIN_ID
    use_sim_time: bool = False  # True: the robot's time from /clock (a simulator, a bag)
    connect_timeout_s: float = Field(10.0, gt=0)  # wait for each device's first message


class DirectBackend(BaseModel):
    """An arm over RTDE and a RealSense over its SDK; the base over ROS 2 or none."""

    model_config = ConfigDict(frozen=True, extra="forbid")

    ur_host: str | None = None  # the UR controller's address (None: no arm)
    ur_frequency: float = Field(500.0, gt=0, le=1000)  # Hz: e-Series 500, CB3 125
    realsense_serial: str | None = None  # which camera (None: the first one found)
    realsense_playback: Path | None = None  # a RealSense .bag recording instead of a device
    camera: bool = True  # False: no camera
    base: Literal["none", "ros2"] = "none"


class SafetyConfig(BaseModel):
    """What a hardware backend enforces before and while the arm or the base moves."""

    model_config = ConfigDict(frozen=True, extra="forbid")

    speed_scale: float = Field(0.25, gt=0, le=1)  # of the arm's joint speed/accel limits
    watchdog_s: float = Field(0.5, gt=0)  # s without an answer: stop streaming / driving
    confirm: bool = True  # ask before the arm moves on hardware


class BackendConfig(BaseModel):
    """The ``backend:`` section of a robot file (module docstring)."""

    model_config = ConfigDict(frozen=True, extra="forbid")

    kind: Literal["twin", "ros2", "direct"] = "twin"
    ros2: Ros2Backend = Ros2Backend()
    direct: DirectBackend = DirectBackend()
    safety: SafetyConfig = SafetyConfig()

    @property
    def hardware(self) -> bool:
        """True for a backend whose motions are real (not the twin): missions ask first."""
        return self.kind != "twin"
