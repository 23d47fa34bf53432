"""Arm poses of the tracking grasp (nominal kinematics, ``arm_base`` frame, m and rad).

:class:`ArmGeometry`: the frames and joint limits every phase uses (flange -> camera, flange
-> TCP, the limits less a margin); :func:`look_configuration` (the camera straight down over a
point), :func:`tool_down` (tool z down, x along a yaw), :func:`grasp_yaw` (fingers across an
object's long axis) and :func:`intercept_goal` (the joint pose and velocity over a moving
object point, ``J^+ [v; 0]``).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from mmpa.core.geometry import Array, inv, make_T
from mmpa.perception.locate import look_at
from mmpa.robot.description import DHParameters, RobotDescription
from mmpa.robot.kinematics import fk, ik_nearest, jacobian
from mmpa.servo.ibvs import pinv

__all__ = ["ArmGeometry", "grasp_yaw", "intercept_goal", "look_configuration", "tool_down"]


@dataclass(frozen=True)
class ArmGeometry:
    """``robot``'s nominal frames for the servo: ``dh``, ``T_fc`` (flange -> camera) and
    ``T_ft`` (flange -> TCP), 4x4; ``q_lo``/``q_hi`` (6,) rad, the joint limits less the
    margin every set-point keeps."""

    robot: RobotDescription
    dh: DHParameters
    T_fc: Array
    T_ft: Array
    q_lo: Array
    q_hi: Array

    @classmethod
    def of(cls, robot: RobotDescription, joint_margin: float) -> ArmGeometry:
        q_min, q_max = robot.arm.q_limits
        return cls(
            robot,
            robot.arm.dh,
            robot.camera.T_flange_camera,
            robot.gripper.T_flange_tcp,
            q_min + joint_margin,
            q_max - joint_margin,
        )

    def T_camera(self, q: Array) -> Array:
        """Camera pose (4x4, ``arm_base``) at the joint angles ``q`` (6,)."""
        return fk(self.dh, q) @ self.T_fc


def look_configuration(
    robot: RobotDescription, target_arm_base: Array, height: float, q_ref: Array | None = None
) -> Array:
    """Joint angles (6,) with the wrist camera ``height`` m above ``target_arm_base`` looking
    straight down, image up = arm_base +x (nominal IK). Raises UnreachableError."""
    t = np.asarray(target_arm_base, float)
    T_cam = look_at(t + np.array([0.0, 0.0, height]), t, up_hint=(1.0, 0.0, 0.0))
    T_fl = T_cam @ inv(robot.camera.T_flange_camera)
    q_min, q_max = robot.arm.q_limits
    return ik_nearest(
        robot.arm.dh,
        T_fl,
        np.asarray(robot.arm.home if q_ref is None else q_ref, float),
        q_min,
        q_max,
    )


def tool_down(yaw: float) -> Array:
    """Tool rotation (3x3): z down, x along ``(cos yaw, sin yaw, 0)``."""
    x = np.array([np.cos(yaw), np.sin(yaw), 0.0])
    z = np.array([0.0, 0.0, -1.0])
    return np.column_stack([x, np.cross(z, x), z])


def grasp_yaw(geom: ArmGeometry, axis_xy: Array, q_cmd: Array) -> float:
    """Tool x along the object's horizontal long axis ``axis_xy`` (the fingers close across
    it): of the two equivalent headings, the one nearest the tool x at ``q_cmd``."""
    target = float(np.arctan2(axis_xy[1], axis_xy[0]))
    T = fk(geom.dh, q_cmd, geom.T_ft)
    now = float(np.arctan2(T[1, 0], T[0, 0]))
    k = np.round((now - target) / np.pi)
    return target + k * np.pi


def intercept_goal(
    geom: ArmGeometry,
    q_ref: Array,
    p_obj: Array,
    v_obj: Array | None,
    height: float,
    yaw: float | None,
    lead: float,
    damping: float,
    v_z: float = 0.0,
) -> tuple[Array, Array]:
    """The intercept's goal: joint angles (6,) with the TCP ``height`` m above the object
    point ``p_obj`` (3,) ``arm_base``, ``lead`` s ahead on its velocity ``v_obj`` (3,) m/s,
    the tool pointing down (x along ``yaw``; None: the heading at ``q_ref``), the IK solution
    nearest ``q_ref`` within ``geom``'s limits; and the joint velocity (6,) rad/s moving the
    TCP with the object there (``J^+ [v; 0]``, damped least squares ``damping``, ``v`` its
    horizontal velocity and ``v_z`` m/s vertically). Raises UnreachableError."""
    dh = geom.dh
    v = np.zeros(3) if v_obj is None else np.array([v_obj[0], v_obj[1], 0.0])
    v_lead = v.copy()
    v[2] = v_z
    p = np.asarray(p_obj, float) + v_lead * lead
    if yaw is None:  # the heading now, turned with the azimuth (joint 1 free of joint 6)
        T0 = fk(dh, q_ref, geom.T_ft)
        turn = np.arctan2(p[1], p[0]) - np.arctan2(T0[1, 3], T0[0, 3])
        yaw = float(np.arctan2(T0[1, 0], T0[0, 0]) + turn)
    T = make_T(tool_down(yaw), np.array([p[0], p[1], p[2] + height])) @ inv(geom.T_ft)
    q_goal = ik_nearest(dh, T, q_ref, geom.q_lo, geom.q_hi)
    J = jacobian(dh, q_goal, geom.T_ft)
    v_goal = pinv(J, damping) @ np.concatenate([v, np.zeros(3)])
    return q_goal, v_goal
