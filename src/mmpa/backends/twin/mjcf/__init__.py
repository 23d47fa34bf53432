"""Generate the MuJoCo model (MJCF) from a scene and a (TRUE) robot description.

The generator is the single source of truth for the twin's geometry; nothing is hand-edited.
Names are a contract with ``mmpa.backends.twin.sensors`` and ``mmpa.backends.twin.world``:

- bodies ``base_link`` (free joint ``base_free``), ``wheel_left``/``wheel_right`` (hinges
  ``wheel_left_joint``/``wheel_right_joint``), ``arm_base`` (with a compliant mount: hinges
  ``mount_roll``/``mount_pitch``, see :class:`MountCompliance`), ``link1``..``link6``
  (hinges ``joint1``..``joint6``), ``flange``, ``finger_left``/``finger_right``
  (slides ``finger_left_joint``/``finger_right_joint``, 0 = open);
- camera ``wrist_camera``; sites ``laser`` (base), ``photosensor`` and ``tcp`` (tool);
- actuators ``wheel_left_vel``, ``wheel_right_vel``, ``arm1``..``arm6``, ``gripper``;
- geoms ``reflector_<i>``, ``fiducial_<i>_reflector``, ``fiducial_<i>_wall_<k>``;
- the static body ``speed_bump``; free bodies named after movable items and grasp objects;
  a body per loose desk item (static unless also free), named after the item.

Built in document order by :mod:`~mmpa.backends.twin.mjcf.room` (lights, floor, walls,
reflectors, speed bump, fiducials), :mod:`~mmpa.backends.twin.mjcf.items` (desks, desk items,
grasp objects) and :mod:`~mmpa.backends.twin.mjcf.robot` (base, arm, tool), sharing
:class:`~mmpa.backends.twin.mjcf.common.ModelBuilder` (the scene's seeded random stream:
the same scene gives the same XML, byte for byte).

Geom groups: 0 static world, 1 movable objects, 2 reflectors and fiducials, 3 robot
collision, 4 robot visual. Robot geoms never collide with each other.
"""

from __future__ import annotations

import xml.etree.ElementTree as ET
from dataclasses import dataclass, field

import mujoco
import numpy as np

from mmpa.backends.twin.error_model import BaseCompliance
from mmpa.backends.twin.mjcf.common import (
    GROUP,
    MOUNT_JOINTS,
    OPTICAL_FROM_MUJOCO,
    ModelBuilder,
    MountCompliance,
    desk_item_pose,
)
from mmpa.backends.twin.mjcf.robot import build_robot
from mmpa.backends.twin.mjcf.room import build_world
from mmpa.backends.twin.scene import SceneConfig
from mmpa.core.geometry import Array
from mmpa.robot.description import RobotDescription

__all__ = [
    "GROUP",
    "MOUNT_JOINTS",
    "OPTICAL_FROM_MUJOCO",
    "BuiltModel",
    "MountCompliance",
    "build_model",
    "desk_item_pose",
    "full_reach_configuration",
    "mount_compliance",
]


@dataclass
class BuiltModel:
    """MJCF text plus the in-memory assets (PNG textures) it references."""

    xml: str
    assets: dict[str, bytes] = field(default_factory=dict)

    def compile(self) -> mujoco.MjModel:
        return mujoco.MjModel.from_xml_string(self.xml, self.assets)


def full_reach_configuration(robot: RobotDescription) -> Array:
    """The arm at full reach (rad, (6,)): ``home`` (the folded pose) with shoulder and elbow
    straight (``q2 = q3 = 0``: upper arm and forearm horizontal, stretched out in the
    direction ``q1`` of home), the wrist as at home."""
    q = np.array(robot.arm.home, float)
    q[1:3] = 0.0
    return q


def mount_compliance(
    scene: SceneConfig,
    robot: RobotDescription,
    tilt_full_reach_deg: float,
    damping_ratio: float = 1.0,
) -> MountCompliance | None:
    """The compliant mount that tilts the arm base by ``tilt_full_reach_deg`` (deg) when the
    arm moves from its folded pose (``robot.arm.home``) to full reach
    (:func:`full_reach_configuration`); ``None`` (a rigid mount) for a tilt of 0.

    With ``tau_f``, ``tau_r`` (N m, (2,)) the gravity torques about the (roll, pitch) hinges
    in the folded and full-reach configurations (base level, from the model's own masses and
    centres of mass: ``tau = -qfrc_bias`` at rest) and ``theta`` the tilt (rad):

        stiffness = |tau_r - tau_f| / theta                                   (N m/rad)
        springref = -tau_f / stiffness      (folded arm at rest: q = 0, arm base level)
        damping   = 2 zeta sqrt(stiffness I)                                  (N m s/rad)

    with ``I`` (kg m^2) the largest inertia about a hinge of the two configurations (full
    reach), so the mount is ``damping_ratio`` (``zeta``) times critically damped at full
    reach and more than that when the arm is folded. ``scene`` only names the model built
    for the computation (the robot alone, nothing of the world)."""
    theta = float(np.deg2rad(tilt_full_reach_deg))
    if not (np.isfinite(theta) and theta >= 0):
        raise ValueError(f"tilt must be a finite non-negative angle, got {tilt_full_reach_deg}")
    if theta == 0.0:
        return None
    b = ModelBuilder(scene, robot)
    build_robot(b, np.zeros(3), MountCompliance(1.0, 0.0, (0.0, 0.0)))
    model = mujoco.MjModel.from_xml_string(ET.tostring(b.root, encoding="unicode"))
    data = mujoco.MjData(model)
    dofs = [model.jnt_dofadr[model.joint(n).id] for n in MOUNT_JOINTS]
    arm_q = [model.jnt_qposadr[model.joint(f"joint{i}").id] for i in range(1, 7)]
    M = np.zeros((model.nv, model.nv))
    torques, inertia = [], []
    for q in (np.array(robot.arm.home, float), full_reach_configuration(robot)):
        data.qpos[:] = model.qpos0
        data.qpos[arm_q] = q
        data.qvel[:] = 0.0
        mujoco.mj_forward(model, data)
        torques.append(-data.qfrc_bias[dofs].copy())
        mujoco.mj_fullM(model, data, M)
        inertia.append(M[dofs, dofs].copy())
    tau_f, tau_r = torques
    k = float(np.linalg.norm(tau_r - tau_f)) / theta
    c = 2.0 * damping_ratio * float(np.sqrt(k * np.max(inertia)))
    ref = -tau_f / k
    return MountCompliance(k, c, (float(ref[0]), float(ref[1])), theta)


def build_model(
    scene: SceneConfig,
    robot: RobotDescription,
    start_pose2d: Array | None = None,
    compliance: BaseCompliance | None = None,
) -> BuiltModel:
    """MJCF for ``scene`` with ``robot`` (pass the TRUE robot) parked at ``start_pose2d``
    (``[x, y, yaw]``; default: site "0"). With ``compliance`` of a non-zero tilt the arm
    sits on a compliant mount (:func:`mount_compliance`); otherwise (and by default) the
    arm base is rigidly fixed to the chassis and the model has no mount joints."""
    b = ModelBuilder(scene, robot)
    build_world(b)
    if start_pose2d is None:
        start_pose2d = scene.sites["0"].pose2d if "0" in scene.sites else np.zeros(3)
    mount = (
        mount_compliance(scene, robot, compliance.tilt_full_reach_deg)
        if compliance is not None
        else None
    )
    build_robot(b, np.asarray(start_pose2d, float), mount)
    ET.indent(b.root)
    return BuiltModel(ET.tostring(b.root, encoding="unicode"), b.assets)
