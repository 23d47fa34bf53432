"""What every MJCF builder shares: the geom groups and collision classes, number formatting,
the pose attributes, the desk-item frame, and :class:`ModelBuilder`, the model being built
(the XML tree's sections, the PNG assets, the scene's seeded random stream).

Units: m, rad. Quaternions are MuJoCo's (w, x, y, z).
"""

from __future__ import annotations

import xml.etree.ElementTree as ET
from dataclasses import dataclass

import mujoco
import numpy as np

from mmpa.backends.twin import textures
from mmpa.backends.twin.scene import DeskItem, SceneConfig, Workbench
from mmpa.core.geometry import Array, make_T, rot_z
from mmpa.robot.description import RobotDescription

__all__ = [
    "GROUP",
    "MOUNT_JOINTS",
    "OPTICAL_FROM_MUJOCO",
    "ModelBuilder",
    "MountCompliance",
    "desk_item_pose",
]

GROUP = {"world": 0, "objects": 1, "reflectors": 2, "robot": 3, "robot_visual": 4}

OPTICAL_FROM_MUJOCO = np.diag([1.0, -1.0, -1.0])  # MuJoCo cameras look along -z, y up
ROBOT_COLLISION = {"contype": "2", "conaffinity": "1", "group": str(GROUP["robot"])}
ROBOT_VISUAL = {"contype": "0", "conaffinity": "0", "group": str(GROUP["robot_visual"])}
MOUNT_JOINTS = ("mount_roll", "mount_pitch")  # hinges of the compliant arm mount, if any


@dataclass(frozen=True)
class MountCompliance:
    """A compliant mount (sprung suspension, tyres, a compliant plate) between the chassis
    ``base_link`` and ``arm_base``: two hinges through the ``arm_base`` origin, ``mount_roll``
    about base_link x and ``mount_pitch`` about base_link y, each a torsion spring with
    damper:

        tau_j = -stiffness (q_j - springref_j) - damping qdot_j        (N m; q rad, qdot rad/s)

    The arm's weight loads the mount (its motors' gravity compensation does not: the mount
    joints take no actuator force), so at rest ``q = springref + tau_g(q_arm) / stiffness``
    with ``tau_g`` the gravity torque of everything above the mount about each hinge axis.
    ``springref`` is the spring's preload that puts the folded arm's equilibrium at
    ``q = 0`` (arm base level). See :func:`mmpa.backends.twin.mjcf.mount_compliance`."""

    stiffness: float  # N m/rad, both hinges
    damping: float  # N m s/rad, both hinges
    springref: tuple[float, float]  # rad, (roll, pitch) rest angles of the springs
    tilt_full_reach: float = 0.0  # rad, the tilt change folded -> full reach it was made for


def fmt(*xs: float) -> str:
    """Numbers as an MJCF attribute value (9 significant digits, space separated)."""
    return " ".join(f"{float(x):.9g}" for x in xs)


def quat_of(R: Array) -> Array:
    """MuJoCo's quaternion (w, x, y, z) of the rotation matrix ``R`` (3, 3)."""
    q = np.empty(4)
    mujoco.mju_mat2Quat(q, np.ascontiguousarray(R).ravel())
    return q


def pose_attrs(T: Array) -> dict[str, str]:
    """``pos`` and ``quat`` (w, x, y, z) attributes of a 4x4 transform."""
    return {"pos": fmt(*T[:3, 3]), "quat": fmt(*quat_of(T[:3, :3]))}


def yaw_quat(yaw: float) -> str:
    """The ``quat`` attribute of a rotation by ``yaw`` (rad) about z."""
    return fmt(np.cos(yaw / 2), 0.0, 0.0, np.sin(yaw / 2))


def desk_item_pose(bench: Workbench, item: DeskItem) -> Array:
    """``T_map_item``: the item's frame on the desk top (z = desk height)."""
    T_map_desk = make_T(rot_z(np.deg2rad(bench.yaw_deg)), (*bench.center, bench.size[2]))
    T_desk_item = make_T(rot_z(np.deg2rad(item.yaw_deg)), (*item.xy, 0.0))
    return T_map_desk @ T_desk_item


class ModelBuilder:
    """The model being built: the ``mujoco`` root with its compiler, option and visual
    settings, the ``asset``, ``worldbody``, ``actuator``, ``equality`` and ``contact``
    sections the builders append to, the PNG ``assets`` and the scene's random stream
    (``rng``, seeded by ``scene.seed``: the builders draw from it in document order)."""

    def __init__(self, scene: SceneConfig, robot: RobotDescription) -> None:
        self.scene = scene
        self.robot = robot
        self.rng = np.random.default_rng(scene.seed)
        self.assets: dict[str, bytes] = {}
        self.root = ET.Element("mujoco", model=f"mmpa_{scene.name}")
        ET.SubElement(self.root, "compiler", angle="radian", autolimits="true")
        ET.SubElement(
            self.root,
            "option",
            timestep="0.002",
            integrator="implicitfast",
            cone="elliptic",
            impratio="10",
            # no creep under sustained tangential load: without it a base parked on the speed
            # bump rocks 0.25 deg (a few mm at the tool) whenever the arm shifts its weight
            noslip_iterations="3",
        )
        vis = ET.SubElement(self.root, "visual")
        ET.SubElement(vis, "global", offwidth="1280", offheight="960")
        ET.SubElement(vis, "quality", shadowsize="2048")
        ET.SubElement(vis, "headlight", ambient="0.35 0.35 0.35", diffuse="0.4 0.4 0.4")
        # near plane = znear * extent (~20 m here): 4 cm, below the camera min range
        ET.SubElement(vis, "map", znear="0.002", zfar="3")
        self.asset = ET.SubElement(self.root, "asset")
        self.world = ET.SubElement(self.root, "worldbody")
        self.actuators = ET.SubElement(self.root, "actuator")
        self.equality = ET.SubElement(self.root, "equality")
        self.contact = ET.SubElement(self.root, "contact")
        self._materials: set[str] = set()

    def texture(self, name: str, img: np.ndarray, repeat: tuple[float, float] = (1, 1)) -> str:
        """Register a PNG texture and a material using it; returns the material name."""
        fname = f"{name}.png"
        self.assets[fname] = textures.png_bytes(img)
        ET.SubElement(self.asset, "texture", name=f"tex_{name}", type="2d", file=fname)
        ET.SubElement(
            self.asset,
            "material",
            name=f"mat_{name}",
            texture=f"tex_{name}",
            texrepeat=fmt(*repeat),
            specular="0.2",
        )
        return f"mat_{name}"

    def color(self, rgb: tuple[float, ...] | np.ndarray | None) -> str:
        """An ``rgba`` attribute: ``rgb`` opaque, or a seeded random colour for None."""
        c = np.asarray(rgb, float) if rgb is not None else self.rng.uniform(0.15, 0.95, 3)
        return fmt(*c, 1.0)

    def shiny(self) -> str:
        """The reflective material of reflectors (registered on first use)."""
        if "mat_reflective" not in self._materials:
            ET.SubElement(
                self.asset,
                "material",
                name="mat_reflective",
                specular="0.9",
                shininess="0.9",
                reflectance="0.2",
                rgba="0.92 0.92 0.95 1",
            )
            self._materials.add("mat_reflective")
        return "mat_reflective"

    def glossy(self) -> str:
        """The glossy material of glossy grasp objects (registered on first use)."""
        if "mat_glossy" not in self._materials:
            ET.SubElement(
                self.asset, "material", name="mat_glossy", specular="0.8", shininess="0.8"
            )
            self._materials.add("mat_glossy")
        return "mat_glossy"
