"""Bring your own arm: implement mmpa's ``Arm`` protocol for your hardware, and mmpa's path
planning and limit checks drive it.

This example's arm is a FAKE (it integrates the commanded joints in memory, labelled as
such): replace the three methods with your controller's calls (e.g. ur-rtde's ``moveJ`` and
``servoJ``). Run: ``python examples/bring_your_own_arm.py``.
"""

from __future__ import annotations

import numpy as np

from mmpa.core.geometry import make_T
from mmpa.planning import plan_joint_path, retime
from mmpa.robot.description import default_robot
from mmpa.robot.interfaces import Arm
from mmpa.robot.kinematics import fk
from mmpa.robot.limits import JointLimits, check_path, check_positions


class FakeArm:
    """A fake arm (no hardware): it keeps the joint vector in memory. The limits contract of
    :class:`mmpa.robot.interfaces.Arm` is kept with mmpa's own checks, before anything
    'moves'."""

    def __init__(self, limits: JointLimits, q0: np.ndarray) -> None:
        self.limits = limits
        self._q = np.asarray(q0, float).copy()
        self.log: list[str] = []

    def joint_positions(self) -> np.ndarray:
        return self._q.copy()  # your encoders here

    def move_joints(self, q: np.ndarray, duration: float | None = None) -> None:
        q = check_positions(q, self.limits)  # refuse before moving
        self.log.append(f"move_joints to {np.round(q, 3)}")
        self._q = q  # your controller's point-to-point move here (it plans within limits)

    def follow(self, times: np.ndarray, q_path: np.ndarray, record_hz: float | None = None):
        check_path(times, q_path, self.limits)  # positions, velocities, accelerations
        self.log.append(f"follow {len(times)} samples over {times[-1] - times[0]:.2f} s")
        self._q = np.asarray(q_path[-1], float)  # your streaming (e.g. servoJ at 500 Hz) here
        return None


def main() -> None:
    robot = default_robot()  # or: mmpa.robot.robot_file.load_robot("robot.yaml")[0]
    arm = FakeArm(JointLimits.from_description(robot.arm), np.array(robot.arm.home))
    assert isinstance(arm, Arm)  # the protocol is all mmpa needs

    # a 10 cm straight line of the tool, 2 s, from where the tool is now
    tcp = robot.gripper.T_flange_tcp
    T0 = fk(robot.arm.dh, arm.joint_positions(), tcp)
    t = np.linspace(0.0, 2.0, 41)
    poses = np.array([make_T(T0[:3, :3], T0[:3, 3] + [0.1 * s, 0.0, 0.0]) for s in t / t[-1]])
    q_path = plan_joint_path(robot.arm, poses, arm.joint_positions(), tcp)
    path = retime(t, q_path, robot.arm)  # slowed down only if a limit demands it
    arm.move_joints(path.q[0])
    arm.follow(path.t, path.q)
    end = fk(robot.arm.dh, arm.joint_positions(), tcp)[:3, 3]
    print("\n".join(arm.log))
    moved = 1000 * np.linalg.norm(end - T0[:3, 3])
    print(f"tool moved {moved:.1f} mm (time scale {path.time_scale:.2f})")

    # a path that jumps is refused before anything moves
    bad = path.q.copy()
    bad[20:, 0] += 1.0
    try:
        arm.follow(path.t, bad)
    except Exception as e:  # JointLimitError
        print(f"refused: {e}")


if __name__ == "__main__":
    main()
