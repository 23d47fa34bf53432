"""The robot of a robot file's ``backend:`` section, for the mission commands
(``mmpa --robot FILE navigate | run | ...``; :mod:`mmpa.robot.backend_config`).

:func:`open_robot` opens a hardware kind as a :class:`~mmpa.robot.interfaces.MobileManipulator`
and closes it after: ``ros2`` -> :class:`~mmpa.backends.ros2.devices.robot.Ros2Robot` (its
devices over ROS 2, connected before it is handed over). The ``twin`` kind is not opened here:
each mission command drives the twin on its own twin path (it checks ``backend.kind`` first).

:class:`RobotLocalizer` is a :class:`~mmpa.localization.localizer.Localizer` that reads the
pose of the robot's own running localizer (``topics.pose``, e.g. Nav2 amcl's ``/amcl_pose``)
instead of localizing: ``pose_at(o) = T_map_odom (+) o`` with ``T_map_odom`` from the latest
pose and the odometry at its stamp.
"""

from __future__ import annotations

from collections.abc import Iterable, Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import numpy as np

from mmpa.backends.direct import open_direct
from mmpa.core.errors import ConfigError
from mmpa.core.geometry import Array, se2_compose
from mmpa.localization.pose import PoseEstimate
from mmpa.robot.description import RobotDescription, default_robot
from mmpa.robot.interfaces import LaserScan, MobileManipulator
from mmpa.robot.robot_file import load_robot, robot_backend

__all__ = ["RobotLocalizer", "open_robot", "robot_description"]


def robot_description(robot_file: Path | None) -> RobotDescription:
    """The robot file's description (None: mmpa's default robot, or the one ``mmpa --robot``
    set)."""
    return default_robot() if robot_file is None else load_robot(robot_file)[0]


@contextmanager
def open_robot(
    robot_file: Path | None, devices: Iterable[str] | None = None
) -> Iterator[MobileManipulator]:
    """The hardware robot of ``robot_file``'s backend section, its ``devices`` connected
    (names of :data:`mmpa.backends.ros2.devices.robot.DEVICES`; None: all it has), closed
    on exit. Refuses the ``twin`` kind (the commands' own twin path drives it) with a
    :class:`ConfigError`."""
    backend = robot_backend(robot_file)
    if backend.kind == "twin":
        raise ConfigError(
            "the twin is driven by each command's own twin path (no --robot, or a robot file "
            "with backend.kind: twin); open_robot opens the hardware kinds ros2 and direct"
        )
    if backend.kind == "direct":  # the UR arm over RTDE, the RealSense over its SDK
        with open_direct(backend, robot_description(robot_file), devices) as robot:
            yield robot
        return
    from mmpa.backends.ros2.devices.robot import ros2_robot

    with ros2_robot(backend, robot_description(robot_file)) as robot:
        robot.connect(devices)
        yield robot


class RobotLocalizer:
    """The robot's own localizer read over ROS 2 (module docstring). ``source``: a
    :class:`~mmpa.backends.ros2.devices.mobile.Ros2PoseSource` (``latest()`` and
    ``map_odom()``). ``initialize`` does nothing: that localizer has its own initial pose
    (RViz's "2D Pose Estimate", ``set_initial_pose``)."""

    name = "robot"

    def __init__(self, source: Any) -> None:
        self.source = source

    def initialize(self, pose: Array, cov: Array | None = None) -> None:
        return None

    def update(self, odom_pose: Array, scan: LaserScan, force: bool = False) -> PoseEstimate:
        """The latest pose of the robot's localizer, moved to ``odom_pose`` (no update runs
        here: ``updated`` False)."""
        _, _, cov = self.source.latest()
        return PoseEstimate(self.pose_at(odom_pose), cov, 0, False, self.name)

    def pose_at(self, odom_pose: Array) -> Array:
        return se2_compose(self.source.map_odom(), np.asarray(odom_pose, float))
