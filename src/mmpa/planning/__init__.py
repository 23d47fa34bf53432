"""Arm motion planning for taught paths: IK with branch continuity, time parameterization."""

from mmpa.planning.path import JointPath, PathPlanConfig, plan_joint_path, retime

__all__ = ["JointPath", "PathPlanConfig", "plan_joint_path", "retime"]
