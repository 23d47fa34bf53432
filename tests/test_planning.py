"""Tool path -> joint path: IK continuity, refusal before motion, limits after retiming."""

from __future__ import annotations

import numpy as np
import pytest

from mmpa.core.errors import UnreachableError
from mmpa.core.geometry import make_T, rot_x
from mmpa.planning import PathPlanConfig, plan_joint_path, retime
from mmpa.robot.description import default_robot
from mmpa.robot.kinematics import fk

ROBOT = default_robot()
TCP = ROBOT.gripper.T_flange_tcp


def _line(p0, p1, n=60):
    R = rot_x(np.pi)  # tool down
    return np.stack([make_T(R, p0 + s * (np.asarray(p1) - p0)) for s in np.linspace(0, 1, n)])


def test_plan_follows_the_tool_path_within_limits():
    path = _line(np.array([0.45, -0.15, 0.25]), np.array([0.45, 0.15, 0.10]))
    q0 = np.array([0.0, -1.57, 1.57, -1.57, -1.57, 0.0])
    q = plan_joint_path(ROBOT.arm, path, q0, TCP)
    T = fk(ROBOT.arm.dh, q, TCP)
    np.testing.assert_allclose(T[:, :3, 3], path[:, :3, 3], atol=1e-8)
    np.testing.assert_allclose(T[:, :3, :3], path[:, :3, :3], atol=1e-8)
    assert np.abs(np.diff(q, axis=0)).max() < 0.1  # one IK branch all along
    lo, hi = ROBOT.arm.q_limits
    assert np.all(q >= lo) and np.all(q <= hi)


def test_unreachable_waypoint_is_named_before_any_motion():
    path = _line(np.array([0.45, 0.0, 0.2]), np.array([1.4, 0.0, 0.2]), n=20)
    with pytest.raises(UnreachableError, match=r"waypoint \d+/20"):
        plan_joint_path(ROBOT.arm, path, np.array([0.0, -1.57, 1.57, -1.57, -1.57, 0.0]), TCP)


def test_joint_jump_is_refused():
    # two waypoints that need the wrist to turn half a revolution
    a = make_T(rot_x(np.pi), [0.45, 0.0, 0.2])
    b = a.copy()
    b[:3, :3] = a[:3, :3] @ np.diag([-1.0, -1.0, 1.0])  # 180 deg about the tool axis
    with pytest.raises(UnreachableError, match="jump"):
        plan_joint_path(
            ROBOT.arm,
            np.stack([a, b]),
            np.array([0.0, -1.57, 1.57, -1.57, -1.57, 0.0]),
            TCP,
            PathPlanConfig(max_joint_step=0.5),
        )


def test_retime_respects_velocity_and_acceleration_limits():
    t = np.linspace(0, 0.5, 26)  # far too fast for a 1.2 rad swing
    q = np.zeros((26, 6))
    q[:, 0] = 1.2 * (1 - np.cos(np.pi * t / 0.5)) / 2
    cfg = PathPlanConfig(velocity_scale=0.5, acceleration_scale=0.5)
    jp = retime(t, q, ROBOT.arm, cfg)
    assert jp.time_scale > 1
    # independent check: finite differences of the retimed samples
    v = np.abs(np.diff(jp.q[:, 0]) / np.diff(jp.t)).max()
    assert v <= 0.5 * ROBOT.arm.qd_max[0] * 1.01
    # closed form for this cosine: peak velocity 1.2*pi/(2*0.5*s), peak acceleration
    # 1.2*pi^2/(2*0.25*s^2); the binding one sets s exactly
    s_v = 1.2 * np.pi / (2 * 0.5) / (0.5 * ROBOT.arm.qd_max[0])
    s_a = np.sqrt(1.2 * np.pi**2 / (2 * 0.25) / (0.5 * ROBOT.arm.qdd_max[0]))
    assert jp.time_scale == pytest.approx(max(s_v, s_a), rel=0.03)
    slow = retime(t * 100, q, ROBOT.arm, cfg)
    assert slow.time_scale == 1.0
