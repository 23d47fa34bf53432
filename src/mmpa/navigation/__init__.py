"""Base navigation: controllers (and, later, planners) driven by pose estimates."""

from mmpa.navigation.controller import GoToPoseConfig, go_to_pose_command

__all__ = ["GoToPoseConfig", "go_to_pose_command"]
