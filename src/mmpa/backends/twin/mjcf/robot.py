"""MJCF of the robot: the differential-drive base (body, ballast, bumper, two wheels with
integrated-velocity servos, a frictionless caster, the laser site), the 6-joint arm built
from its DH parameters (``A_i = Rz(theta_i) Tz(d_i) Tx(a_i) Rx(alpha_i)``, position servos,
gravity-compensated links) on an optionally compliant mount, and the tool on the flange
(TCP and photosensor sites, the wrist camera, the two-finger gripper). Units: m, rad, kg.
"""

from __future__ import annotations

import xml.etree.ElementTree as ET

import numpy as np

from mmpa.backends.twin.mjcf.common import (
    GROUP,
    MOUNT_JOINTS,
    OPTICAL_FROM_MUJOCO,
    ROBOT_COLLISION,
    ROBOT_VISUAL,
    ModelBuilder,
    MountCompliance,
    fmt,
    pose_attrs,
    yaw_quat,
)
from mmpa.core.geometry import Array, make_T, rot_x, rot_z, trans

__all__ = ["build_arm", "build_mount", "build_robot", "build_tool"]

_ARM_TORQUE = (150.0, 150.0, 150.0, 28.0, 28.0, 28.0)  # N m, actuator force range
_ARM_KP = (4000.0, 4000.0, 3000.0, 800.0, 800.0, 600.0)  # N m/rad, position servo gains


# --- base -------------------------------------------------------------------------------------
def _base_body(b: ModelBuilder, base: ET.Element) -> None:
    """The chassis box, its ballast and the bumper plate."""
    rb = b.robot.base
    bx, by, bz = rb.body_size
    clearance = rb.ground_clearance
    ET.SubElement(
        base,
        "geom",
        name="base_body",
        type="box",
        pos=fmt(rb.body_offset_x, 0, clearance + bz / 2),
        size=fmt(bx / 2, by / 2, bz / 2),
        mass=fmt(rb.mass - rb.ballast_mass),
        rgba="0.92 0.92 0.94 1",
        **ROBOT_COLLISION,
    )
    # batteries low and behind the axle keep the centre of mass over the wheel-caster
    # support when the arm reaches forward or the base brakes
    ET.SubElement(
        base,
        "geom",
        name="base_ballast",
        type="box",
        pos=fmt(rb.ballast_x, 0, clearance + 0.03),
        size=fmt(0.12, 0.15, 0.03),
        mass=fmt(rb.ballast_mass),
        rgba="0.3 0.3 0.3 1",
        **ROBOT_VISUAL,
    )
    ET.SubElement(
        base,
        "geom",
        name="base_bumper",
        type="box",
        contype="0",
        conaffinity="0",
        group=str(GROUP["robot_visual"]),
        pos=fmt(rb.body_offset_x, 0, clearance + bz + 0.005),
        size=fmt(bx / 2 - 0.01, by / 2 - 0.01, 0.005),
        rgba="0.1 0.3 0.7 1",
        mass="0",
    )


def _wheel(b: ModelBuilder, base: ET.Element, side: str, sgn: float) -> None:
    """The ``side`` wheel (``sgn`` +1 left, -1 right): hinge, tire and velocity servo."""
    rb = b.robot.base
    wheel = ET.SubElement(
        base,
        "body",
        name=f"wheel_{side}",
        pos=fmt(0, sgn * rb.track_width / 2, rb.wheel_radius),
    )
    ET.SubElement(
        wheel,
        "joint",
        name=f"wheel_{side}_joint",
        type="hinge",
        axis="0 1 0",
        damping="0.05",
        armature="0.01",
    )
    # an ellipsoid touches the floor at one point, like a crowned tire (a cylinder's
    # line contact scrubs when the base turns on the spot)
    ET.SubElement(
        wheel,
        "geom",
        name=f"wheel_{side}_tire",
        type="ellipsoid",
        size=fmt(rb.wheel_radius, rb.wheel_width / 2, rb.wheel_radius),
        mass="2.0",
        friction="1.2 0.005 0.0001",
        condim="3",
        rgba="0.1 0.1 0.1 1",
        **ROBOT_COLLISION,
    )
    # integrated-velocity servo: the wheel tracks the integral of the commanded
    # speed, so a stopped base holds its position on a slope (a plain velocity servo
    # lets it creep down the speed bump)
    ET.SubElement(
        b.actuators,
        "intvelocity",
        name=f"wheel_{side}_vel",
        joint=f"wheel_{side}_joint",
        kp="3000",
        kv="150",
        actrange="-1e9 1e9",
        ctrlrange=fmt(-rb.max_wheel_speed, rb.max_wheel_speed),
        forcerange="-60 60",
    )


def _caster_and_laser(b: ModelBuilder, base: ET.Element) -> None:
    rb = b.robot
    # caster: a frictionless sphere acts as the passive universal wheel
    ET.SubElement(
        base,
        "geom",
        name="caster",
        type="sphere",
        size=fmt(rb.base.caster_radius),
        pos=fmt(rb.base.caster_x, 0, rb.base.caster_radius),
        condim="1",
        priority="1",  # the contact takes the caster's condim (frictionless), not the floor's
        mass="1.0",
        rgba="0.2 0.2 0.2 1",
        **ROBOT_COLLISION,
    )
    ET.SubElement(
        base,
        "site",
        name="laser",
        **pose_attrs(rb.lidar.T_base_link_laser),
        size="0.03",
        rgba="1 0 0 1",
        group="4",
    )
    ET.SubElement(
        base,
        "geom",
        name="laser_housing",
        type="cylinder",
        size="0.04 0.03",
        pos=fmt(*rb.lidar.T_base_link_laser[:3, 3]),
        rgba="0.9 0.8 0.1 1",
        mass="0",
        **ROBOT_VISUAL,
    )


def build_robot(b: ModelBuilder, start_pose2d: Array, mount: MountCompliance | None = None) -> None:
    """The robot's free body ``base_link`` at ``start_pose2d`` (``[x, y, yaw]``), the base's
    parts, then the arm (on ``mount``, rigid for None) and its tool."""
    x, y, th = start_pose2d
    base = ET.SubElement(b.world, "body", name="base_link", pos=fmt(x, y, 0.002), quat=yaw_quat(th))
    ET.SubElement(base, "freejoint", name="base_free")
    _base_body(b, base)
    for side, sgn in (("left", 1.0), ("right", -1.0)):
        _wheel(b, base, side, sgn)
    _caster_and_laser(b, base)
    build_arm(b, base, mount)


# --- arm --------------------------------------------------------------------------------------
def _link(b: ModelBuilder, parent: ET.Element, i: int, child_T: Array) -> ET.Element:
    """Link ``i + 1``: its body, inertia, hinge, geoms and position servo; returns the body
    of the next frame (``flange`` after the sixth)."""
    arm = b.robot.arm
    kp, torque = _ARM_KP, _ARM_TORQUE
    link = ET.SubElement(
        parent, "body", name=f"link{i + 1}", pos="0 0 0", quat="1 0 0 0", gravcomp="1"
    )
    p_end = child_T[:3, 3]
    ET.SubElement(
        link,
        "inertial",
        pos=fmt(*(p_end / 2)),
        mass=fmt(arm.link_masses[i]),
        diaginertia=fmt(0.01, 0.01, 0.01),
    )
    ET.SubElement(
        link,
        "joint",
        name=f"joint{i + 1}",
        type="hinge",
        axis="0 0 1",
        range=fmt(arm.q_min[i], arm.q_max[i]),
        damping="2.0",
        armature="0.2",
    )
    ET.SubElement(
        link,
        "geom",
        name=f"link{i + 1}_joint_vis",
        type="cylinder",
        size="0.045 0.06",
        rgba="0.35 0.55 0.75 1",
        mass="0",
        **ROBOT_VISUAL,
    )
    if np.linalg.norm(p_end) > 1e-3:
        ET.SubElement(
            link,
            "geom",
            name=f"link{i + 1}_geom",
            type="capsule",
            fromto=fmt(0, 0, 0, *p_end),
            size="0.04",
            rgba="0.75 0.78 0.8 1",
            mass="0",
            **ROBOT_COLLISION,
        )
    ET.SubElement(
        b.actuators,
        "position",
        name=f"arm{i + 1}",
        joint=f"joint{i + 1}",
        kp=fmt(kp[i]),
        kv=fmt(2 * np.sqrt(kp[i] * 0.5)),
        ctrlrange=fmt(arm.q_min[i], arm.q_max[i]),
        forcerange=fmt(-torque[i], torque[i]),
    )
    return ET.SubElement(
        link,
        "body",
        name="flange" if i == 5 else f"_frame{i + 1}",
        **pose_attrs(child_T),
        gravcomp="1",
    )


def build_arm(b: ModelBuilder, base: ET.Element, mount: MountCompliance | None = None) -> None:
    """``arm_base`` on ``base`` (with the ``mount`` hinges, if any), its pedestal, the six
    links from the DH parameters, then the tool on the flange."""
    rb = b.robot
    a, d, alpha, off = rb.arm.dh.as_arrays()
    parent = ET.SubElement(base, "body", name="arm_base", **pose_attrs(rb.T_base_link_arm_base))
    if mount is not None:
        build_mount(b, parent, mount)
    ET.SubElement(
        parent,
        "geom",
        name="arm_pedestal",
        type="cylinder",
        size="0.075 0.045",
        pos="0 0 0.045",
        rgba="0.3 0.5 0.7 1",
        mass="0",
        **ROBOT_VISUAL,
    )
    A0 = [
        make_T(rot_z(off[i])) @ trans(z=d[i]) @ trans(x=a[i]) @ make_T(rot_x(alpha[i]))
        for i in range(6)
    ]
    for i in range(6):
        parent = _link(b, parent, i, A0[i])
    build_tool(b, parent)


def build_mount(b: ModelBuilder, arm_base: ET.Element, mount: MountCompliance) -> None:
    """The hinges of the compliant mount (:class:`MountCompliance`) in ``arm_base``.

    Their axes are base_link's x and y written in the arm_base frame. The arm's links
    carry ``gravcomp`` (their motors hold them up), which MuJoCo applies as a force on
    every ancestor joint; the mount is no motor, so its joints route that compensation
    to their actuator force and clamp it to zero (``actuatorgravcomp``,
    ``actuatorfrcrange``): the mount carries the arm's full weight."""
    R = b.robot.T_base_link_arm_base[:3, :3]
    # a thin mount plate: a body with joints needs a mass of its own
    ET.SubElement(arm_base, "inertial", pos="0 0 0.01", mass="0.2", diaginertia="2e-4 2e-4 4e-4")
    for name, axis, ref in zip(MOUNT_JOINTS, (R.T[:, 0], R.T[:, 1]), mount.springref, strict=True):
        ET.SubElement(
            arm_base,
            "joint",
            name=name,
            type="hinge",
            pos="0 0 0",
            axis=fmt(*axis),
            stiffness=fmt(mount.stiffness),
            springref=fmt(ref),
            damping=fmt(mount.damping),
            actuatorgravcomp="true",
            actuatorfrcrange="-1e-12 1e-12",
        )


# --- tool -------------------------------------------------------------------------------------
def _sensors_on_flange(b: ModelBuilder, flange: ET.Element) -> None:
    """The ``tcp`` and ``photosensor`` sites, the ``wrist_camera`` and its housing."""
    rb = b.robot
    ET.SubElement(
        flange, "site", name="tcp", **pose_attrs(rb.gripper.T_flange_tcp), size="0.005", group="4"
    )
    ET.SubElement(
        flange,
        "site",
        name="photosensor",
        **pose_attrs(rb.photosensor.T_flange_sensor),
        size="0.004",
        rgba="1 0 0 1",
        group="4",
    )
    T_cam_mj = rb.camera.T_flange_camera.copy()
    T_cam_mj[:3, :3] = T_cam_mj[:3, :3] @ OPTICAL_FROM_MUJOCO
    ET.SubElement(
        flange,
        "camera",
        name="wrist_camera",
        fovy=fmt(np.rad2deg(rb.camera.color.fovy)),
        **pose_attrs(T_cam_mj),
    )
    ET.SubElement(
        flange,
        "geom",
        name="camera_housing",
        type="box",
        size="0.045 0.0125 0.0125",
        **pose_attrs(rb.camera.T_flange_camera @ trans(z=-0.015)),
        rgba="0.2 0.2 0.22 1",
        mass="0.07",
        **ROBOT_VISUAL,
    )


def _finger(flange: ET.Element, side: str, sgn: float, half: float, z_pad: float) -> None:
    """The ``side`` finger (``sgn`` +1 left, -1 right): slide joint, pad and link."""
    pad_len = 0.025
    finger = ET.SubElement(
        flange, "body", name=f"finger_{side}", pos=fmt(0, sgn * half, z_pad), gravcomp="1"
    )
    ET.SubElement(
        finger,
        "joint",
        name=f"finger_{side}_joint",
        type="slide",
        axis=fmt(0, -sgn, 0),
        range=fmt(0, half - 0.001),
        damping="5",
        armature="0.01",
    )
    ET.SubElement(
        finger,
        "geom",
        name=f"finger_{side}_pad",
        type="box",
        size=fmt(0.011, 0.006, pad_len),
        pos=fmt(0, sgn * 0.006, 0),
        mass="0.05",
        friction="1.5 0.02 0.001",
        condim="4",
        solref="0.004 1",  # stiff pads: a 110 N grip sinks < 1.5 mm into the object
        solimp="0.99 0.999 0.001",
        rgba="0.25 0.25 0.25 1",
        **ROBOT_COLLISION,
    )
    ET.SubElement(
        finger,
        "geom",
        name=f"finger_{side}_link",
        type="box",
        size=fmt(0.011, 0.006, 0.035),
        pos=fmt(0, sgn * 0.012, -0.045),
        mass="0.05",
        rgba="0.3 0.3 0.3 1",
        **ROBOT_VISUAL,
    )


def build_tool(b: ModelBuilder, flange: ET.Element) -> None:
    """The tool on ``flange``: sites and camera, the gripper palm, two coupled fingers (an
    equality makes the right follow the left) and the gripper's position servo."""
    g = b.robot.gripper
    _sensors_on_flange(b, flange)
    ET.SubElement(
        flange,
        "geom",
        name="gripper_palm",
        type="box",
        size="0.04 0.055 0.045",
        pos=fmt(0, 0, 0.05),
        mass="0.9",
        rgba="0.15 0.15 0.15 1",
        **ROBOT_COLLISION,
    )
    half = g.stroke / 2
    z_pad = g.length - 0.005
    for side, sgn in (("left", 1.0), ("right", -1.0)):
        _finger(flange, side, sgn, half, z_pad)
    ET.SubElement(
        b.equality,
        "joint",
        joint1="finger_right_joint",
        joint2="finger_left_joint",
        polycoef="0 1 0 0 0",
        solref="0.005 1",
    )
    ET.SubElement(
        b.actuators,
        "position",
        name="gripper",
        joint="finger_left_joint",
        kp="2500",
        kv="40",
        ctrlrange=fmt(0, half - 0.001),
        forcerange=fmt(-g.max_force, g.max_force),
    )
