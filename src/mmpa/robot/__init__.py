"""Robot description, kinematics and hardware-neutral interfaces (no simulator imports)."""

from mmpa.robot.description import RobotDescription, default_robot

__all__ = ["RobotDescription", "default_robot"]
