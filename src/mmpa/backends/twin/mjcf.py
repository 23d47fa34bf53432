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

Geom groups: 0 static world, 1 movable objects, 2 reflectors and fiducials, 3 robot
collision, 4 robot visual. Robot geoms never collide with each other.
"""

from __future__ import annotations

import xml.etree.ElementTree as ET
from dataclasses import dataclass, field

import mujoco
import numpy as np

from mmpa.backends.twin import textures
from mmpa.backends.twin.error_model import BaseCompliance
from mmpa.backends.twin.scene import DeskItem, GraspObject, SceneConfig, Workbench
from mmpa.core.geometry import Array, make_T, rot_x, rot_y, rot_z, trans
from mmpa.robot.description import RobotDescription

__all__ = [
    "GROUP",
    "MOUNT_JOINTS",
    "BuiltModel",
    "MountCompliance",
    "build_model",
    "desk_item_pose",
    "full_reach_configuration",
    "mount_compliance",
]

GROUP = {"world": 0, "objects": 1, "reflectors": 2, "robot": 3, "robot_visual": 4}

OPTICAL_FROM_MUJOCO = np.diag([1.0, -1.0, -1.0])  # MuJoCo cameras look along -z, y up
_ROBOT_COLLISION = {"contype": "2", "conaffinity": "1", "group": str(GROUP["robot"])}
_ROBOT_VISUAL = {"contype": "0", "conaffinity": "0", "group": str(GROUP["robot_visual"])}
MOUNT_JOINTS = ("mount_roll", "mount_pitch")  # hinges of the compliant arm mount, if any


@dataclass
class BuiltModel:
    """MJCF text plus the in-memory assets (PNG textures) it references."""

    xml: str
    assets: dict[str, bytes] = field(default_factory=dict)

    def compile(self) -> mujoco.MjModel:
        return mujoco.MjModel.from_xml_string(self.xml, self.assets)


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
    ``q = 0`` (arm base level). See :func:`mount_compliance`."""

    stiffness: float  # N m/rad, both hinges
    damping: float  # N m s/rad, both hinges
    springref: tuple[float, float]  # rad, (roll, pitch) rest angles of the springs
    tilt_full_reach: float = 0.0  # rad, the tilt change folded -> full reach it was made for


def _f(*xs: float) -> str:
    return " ".join(f"{float(x):.9g}" for x in xs)


def _pose_attrs(T: Array) -> dict[str, str]:
    """``pos`` and ``quat`` (w, x, y, z) attributes of a 4x4 transform."""
    return {"pos": _f(*T[:3, 3]), "quat": _f(*_quat_of(T[:3, :3]))}


def _yaw_quat(yaw: float) -> str:
    return _f(np.cos(yaw / 2), 0.0, 0.0, np.sin(yaw / 2))


def desk_item_pose(bench: Workbench, item: DeskItem) -> Array:
    """``T_map_item``: the item's frame on the desk top (z = desk height)."""
    T_map_desk = make_T(rot_z(np.deg2rad(bench.yaw_deg)), (*bench.center, bench.size[2]))
    T_desk_item = make_T(rot_z(np.deg2rad(item.yaw_deg)), (*item.xy, 0.0))
    return T_map_desk @ T_desk_item


class _Builder:
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

    # --- assets -------------------------------------------------------------------------
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
            texrepeat=_f(*repeat),
            specular="0.2",
        )
        return f"mat_{name}"

    def color(self, rgb: tuple[float, ...] | np.ndarray | None) -> str:
        c = np.asarray(rgb, float) if rgb is not None else self.rng.uniform(0.15, 0.95, 3)
        return _f(*c, 1.0)

    # --- world --------------------------------------------------------------------------
    def build_world(self) -> None:
        s = self.scene
        w = self.world
        ET.SubElement(
            w,
            "light",
            name="sun",
            directional="true",
            pos="0 0 6",
            dir="0.3 0.2 -1",
            diffuse="0.6 0.6 0.6",
            castshadow="false",
        )
        ET.SubElement(
            w,
            "light",
            name="lobby",
            pos="1.3 -0.3 3.0",
            dir="0 0 -1",
            diffuse="0.35 0.35 0.35",
            castshadow="false",
        )
        floor_mat = self.texture(
            "floor", textures.floor(self.rng), repeat=(s.floor_size[0], s.floor_size[1])
        )
        ET.SubElement(
            w,
            "geom",
            name="floor",
            type="plane",
            material=floor_mat,
            pos=_f(*s.floor_center, 0),
            size=_f(s.floor_size[0] / 2, s.floor_size[1] / 2, 0.1),
            friction="1.0 0.005 0.0001",
            group="0",
        )
        wall_mat = self.texture("wall", textures.wall(self.rng))
        for i, wall in enumerate(s.walls):
            a, b = np.array(wall.start), np.array(wall.end)
            c, d = (a + b) / 2, b - a
            ET.SubElement(
                w,
                "geom",
                name=f"wall_{i}",
                type="box",
                material=wall_mat,
                group="0",
                pos=_f(*c, wall.height / 2),
                quat=_yaw_quat(np.arctan2(d[1], d[0])),
                size=_f(
                    np.linalg.norm(d) / 2 + wall.thickness / 2, wall.thickness / 2, wall.height / 2
                ),
            )
        r = s.reflectors
        for i, (x, y) in enumerate(r.positions):
            ET.SubElement(
                w,
                "geom",
                name=f"reflector_{i}",
                type="cylinder",
                group=str(GROUP["reflectors"]),
                pos=_f(x, y, r.height / 2),
                size=_f(r.radius, r.height / 2),
                rgba="0.92 0.92 0.95 1",
                material=self._shiny(),
            )
        self.build_speed_bump()
        for bench in s.workbenches:
            self.build_desk(bench)
        if s.grasp_desk is not None:
            self.build_desk(s.grasp_desk)
        for obj in s.grasp_objects:
            self.build_grasp_object(obj)
        if s.fiducial_artifact is not None:
            self.build_fiducials()

    def _shiny(self) -> str:
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

    def build_speed_bump(self) -> None:
        sb = self.scene.speed_bump
        if sb is None:
            return
        L, W, H = sb.length / 2, sb.width / 2, sb.height
        verts = [(-L, -W, 0), (L, -W, 0), (-L, W, 0), (L, W, 0), (-L, 0, H), (L, 0, H)]
        ET.SubElement(
            self.asset, "mesh", name="speed_bump_mesh", vertex=" ".join(_f(*v) for v in verts)
        )
        # Parked below the floor until a site with a bump asks for it (SimWorld.set_speed_bump).
        body = ET.SubElement(
            self.world,
            "body",
            name="speed_bump",
            pos=_f(*sb.center, -1.0),
            quat=_yaw_quat(np.deg2rad(sb.yaw_deg)),
        )
        ET.SubElement(
            body,
            "geom",
            name="speed_bump_geom",
            type="mesh",
            mesh="speed_bump_mesh",
            rgba="0.95 0.75 0.1 1",
            friction="1.2 0.005 0.0001",
            group="0",
        )

    def build_desk(self, bench: Workbench) -> None:
        lx, ly, h = bench.size
        yaw = np.deg2rad(bench.yaw_deg)
        body = ET.SubElement(
            self.world,
            "body",
            name=f"desk_{bench.name}",
            pos=_f(*bench.center, 0),
            quat=_yaw_quat(yaw),
        )
        if bench.top_color is None:
            top_look = {"material": self.texture(f"wood_{bench.name}", textures.wood(self.rng))}
        else:
            top_look = {"rgba": self.color(bench.top_color)}
        top = 0.03
        ET.SubElement(
            body,
            "geom",
            name=f"desk_{bench.name}_top",
            type="box",
            **top_look,
            pos=_f(0, 0, h - top / 2),
            size=_f(lx / 2, ly / 2, top / 2),
            group="0",
        )
        for k, (sx, sy) in enumerate([(1, 1), (1, -1), (-1, 1), (-1, -1)]):
            ET.SubElement(
                body,
                "geom",
                name=f"desk_{bench.name}_leg{k}",
                type="box",
                pos=_f(sx * (lx / 2 - 0.04), sy * (ly / 2 - 0.04), (h - top) / 2),
                size=_f(0.02, 0.02, (h - top) / 2),
                rgba="0.3 0.3 0.32 1",
                group="0",
            )
        for j, item in enumerate(bench.items):
            self.build_item(bench, body, item, j)

    def build_item(self, bench: Workbench, desk: ET.Element, item: DeskItem, j: int) -> None:
        name = bench.item_name(j)
        if item.free or item.loose:
            # its own body at the item's desk pose: a free one moves by physics, a loose static
            # one by the scene change (mmpa.backends.twin.scene_change sets its body_pos /
            # body_quat)
            T = desk_item_pose(bench, item)
            parent = ET.SubElement(self.world, "body", name=name, **_pose_attrs(T))
            if item.free:
                ET.SubElement(parent, "freejoint", name=f"{name}_free")
            group = str(GROUP["objects"]) if item.free else "0"
            base = np.zeros(3)
            yaw = 0.0
        else:
            parent = desk
            group = "0"
            base = np.array([*item.xy, bench.size[2]])
            yaw = np.deg2rad(item.yaw_deg)

        def geom(suffix: str, local_pos: tuple[float, float, float], **attrs: str) -> None:
            p = base + rot_z(yaw) @ np.asarray(local_pos, float)
            attrs.setdefault("quat", _yaw_quat(yaw))
            ET.SubElement(parent, "geom", name=f"{name}_{suffix}", pos=_f(*p), group=group, **attrs)

        rgba = self.color(item.color)
        k = item.kind
        if k == "backboard":
            lx, ly, lz = item.size or (1.1, 0.03, 0.45)
            mat = self.texture(f"{name}_poster", textures.backboard(self.rng))
            geom("board", (0, 0, lz / 2), type="box", size=_f(lx / 2, ly / 2, lz / 2), material=mat)
        elif k == "poster":
            # a colorful print lying on the desk (paper 000 Fig. A.1: textures on thin paper)
            lx, ly = (item.size or (0.2, 0.15))[:2]
            mat = self.texture(f"{name}_poster", textures.backboard(self.rng))
            geom("sheet", (0, 0, 0.0005), type="box", size=_f(lx / 2, ly / 2, 0.0005), material=mat)
        elif k == "dot":
            # paper 000 Fig. 6c/10: the red dot the needle points at (printed on thin paper)
            r = (item.size or (0.004,))[0]
            geom(
                "disc",
                (0, 0, 0.0005),
                type="cylinder",
                size=_f(r, 0.0005),
                rgba=self.color(item.color or (0.85, 0.05, 0.05)),
            )
        elif k in ("logo_tape", "letter_tape"):
            lx, ly = (item.size or (0.2, 0.06))[:2]
            if k == "logo_tape":
                img = textures.logo(self.rng)
            else:
                img = textures.letters(item.text or "MMPA", self.rng)
            mat = self.texture(f"{name}_print", img)
            geom("tape", (0, 0, 0.0008), type="box", size=_f(lx / 2, ly / 2, 0.0008), material=mat)
        elif k == "valve_container":
            r, hh = (item.size or (0.09, 0.30))[:2]
            geom(
                "tank",
                (0, 0, hh / 2),
                type="cylinder",
                size=_f(r, hh / 2),
                rgba=self.color((0.85, 0.88, 0.9)),
            )
            geom("band", (0, 0, hh * 0.7), type="cylinder", size=_f(r + 0.002, 0.02), rgba=rgba)
            geom(
                "pipe",
                (0, -r - 0.035, 0.07),
                type="cylinder",
                size=_f(0.015, 0.04),
                quat=_f(*_quat_of(rot_z(yaw) @ rot_x(np.pi / 2))),
                rgba="0.6 0.6 0.62 1",
            )
            geom(
                "wheel",
                (0, -r - 0.08, 0.07),
                type="cylinder",
                size=_f(0.04, 0.006),
                quat=_f(*_quat_of(rot_z(yaw) @ rot_x(np.pi / 2))),
                rgba="0.8 0.1 0.1 1",
            )
            geom(
                "handle",
                (0, -r - 0.088, 0.07),
                type="box",
                size=_f(0.045, 0.004, 0.008),
                rgba="0.15 0.15 0.15 1",
            )
        elif k == "cup":
            r, hh = (item.size or (0.04, 0.09))[:2]
            geom(
                "body", (0, 0, hh / 2), type="cylinder", size=_f(r, hh / 2), rgba=rgba, mass="0.15"
            )
            geom(
                "handle",
                (r + 0.012, 0, hh * 0.55),
                type="box",
                size=_f(0.012, 0.005, 0.025),
                rgba=rgba,
                mass="0.01",
            )
        elif k in ("bottle", "small_bottle", "reagent_bottle"):
            r, hh = (
                item.size
                or {
                    "bottle": (0.035, 0.2),
                    "small_bottle": (0.025, 0.10),
                    "reagent_bottle": (0.04, 0.14),
                }[k]
            )
            geom("body", (0, 0, hh / 2), type="cylinder", size=_f(r, hh / 2), rgba=rgba)
            geom("neck", (0, 0, hh + 0.015), type="cylinder", size=_f(r * 0.4, 0.015), rgba=rgba)
            geom(
                "cap",
                (0, 0, hh + 0.035),
                type="cylinder",
                size=_f(r * 0.45, 0.008),
                rgba=self.color(None),
            )
            geom(
                "label",
                (0, 0, hh * 0.45),
                type="cylinder",
                size=_f(r + 0.001, hh * 0.18),
                rgba=self.color(None),
            )
        elif k == "dropper":
            geom(
                "tube",
                (0, 0, 0.007),
                type="capsule",
                size=_f(0.006, 0.045),
                quat=_f(*_quat_of(rot_z(yaw) @ rot_y(np.pi / 2))),
                rgba="0.85 0.9 0.95 1",
            )
            geom("bulb", (0.055, 0, 0.011), type="sphere", size=_f(0.011), rgba="0.9 0.3 0.2 1")
        elif k == "waste_container":
            geom(
                "bin", (0, 0, 0.08), type="box", size=_f(0.06, 0.06, 0.08), rgba="0.35 0.35 0.38 1"
            )
            geom(
                "lid", (0, 0, 0.165), type="box", size=_f(0.062, 0.062, 0.005), rgba="0.9 0.6 0.1 1"
            )
        elif k == "test_tube_stand":
            geom(
                "base",
                (0, 0, 0.005),
                type="box",
                size=_f(0.12, 0.035, 0.005),
                rgba="0.95 0.95 0.95 1",
            )
            geom(
                "post_l",
                (-0.115, 0, 0.045),
                type="box",
                size=_f(0.005, 0.03, 0.04),
                rgba="0.95 0.95 0.95 1",
            )
            geom(
                "post_r",
                (0.115, 0, 0.045),
                type="box",
                size=_f(0.005, 0.03, 0.04),
                rgba="0.95 0.95 0.95 1",
            )
            geom(
                "rack",
                (0, 0, 0.085),
                type="box",
                size=_f(0.12, 0.035, 0.005),
                rgba="0.2 0.5 0.85 1",
            )
            for t in range(6):
                tint = self.color(None)
                geom(
                    f"tube{t}",
                    (-0.09 + 0.036 * t, 0, 0.07),
                    type="cylinder",
                    size=_f(0.008, 0.06),
                    rgba=tint,
                )
        elif k == "box":
            lx, ly, lz = item.size or (0.08, 0.08, 0.08)
            geom("box", (0, 0, lz / 2), type="box", size=_f(lx / 2, ly / 2, lz / 2), rgba=rgba)

    def build_grasp_object(self, obj: GraspObject) -> None:
        body = ET.SubElement(self.world, "body", name=obj.name, pos=_f(*obj.position))
        ET.SubElement(body, "freejoint", name=f"{obj.name}_free")
        rgba = _f(*obj.color, 1.0)
        look = {"rgba": rgba}
        if obj.glossy:
            look["material"] = self._glossy()
        common = {
            "group": str(GROUP["objects"]),
            "mass": _f(obj.mass),
            "friction": "1.0 0.01 0.001",
            # a lying cylinder also gets rolling friction (condim 6; 1 mm): the convex
            # cylinder-box contact is one point, so without it 8 of 20 blue sticks placed at
            # rest rolled 6-163 mm in 3 s (one rolled off the reachable region); with it <= 8 mm
            "condim": "6" if obj.lying else "4",
            **look,
        }
        deco = {"group": str(GROUP["objects"]), "contype": "0", "conaffinity": "0", "mass": "0"}
        if obj.kind == "cube":
            ET.SubElement(
                body,
                "geom",
                name=f"{obj.name}_geom",
                type="box",
                size=_f(*[obj.size[0]] * 3),
                **common,
            )
        elif obj.kind == "ball":
            ET.SubElement(
                body, "geom", name=f"{obj.name}_geom", type="sphere", size=_f(obj.size[0]), **common
            )
        else:  # bottle, cup, stick: cylinders, upright or lying along the body x axis
            r, hh = obj.size[0], obj.size[1]
            axis = {"euler": "0 1.5707963 0"} if obj.lying else {}
            ET.SubElement(
                body,
                "geom",
                name=f"{obj.name}_geom",
                type="cylinder",
                size=_f(r, hh),
                **axis,
                **common,
            )
            if obj.label is not None:
                ET.SubElement(
                    body,
                    "geom",
                    name=f"{obj.name}_label",
                    type="cylinder",
                    size=_f(r * 1.03, hh * 0.35),
                    rgba=_f(*obj.label, 1.0),
                    **axis,
                    **deco,
                )
            if obj.cap is not None:
                bottle = obj.kind == "bottle"
                cap_r, cap_h = (0.45 * r, 0.1 * hh) if bottle else (1.02 * r, 0.25 * hh)
                c = hh + cap_h if obj.kind == "bottle" else hh - cap_h * 0.99
                pos = _f(c, 0, 0) if obj.lying else _f(0, 0, c)
                ET.SubElement(
                    body,
                    "geom",
                    name=f"{obj.name}_cap",
                    type="cylinder",
                    size=_f(cap_r, cap_h),
                    pos=pos,
                    rgba=_f(*obj.cap, 1.0),
                    **axis,
                    **deco,
                )

    def _glossy(self) -> str:
        if "mat_glossy" not in self._materials:
            ET.SubElement(
                self.asset, "material", name="mat_glossy", specular="0.8", shininess="0.8"
            )
            self._materials.add("mat_glossy")
        return "mat_glossy"

    def build_fiducials(self) -> None:
        fa = self.scene.fiducial_artifact
        assert fa is not None
        body = ET.SubElement(
            self.world,
            "body",
            name="fiducial_artifact",
            pos=_f(*fa.origin, 0),
            quat=_yaw_quat(np.deg2rad(fa.yaw_deg)),
        )
        xs = np.array([p[0] for p in fa.fiducials])
        ys = np.array([p[1] for p in fa.fiducials])
        cx, cy = (xs.min() + xs.max()) / 2, (ys.min() + ys.max()) / 2
        hx, hy = (xs.max() - xs.min()) / 2 + 0.08, (ys.max() - ys.min()) / 2 + 0.06
        ET.SubElement(
            body,
            "geom",
            name="fiducial_plate",
            type="box",
            group="0",
            pos=_f(cx, cy, fa.plate_height / 2),
            size=_f(hx, hy, fa.plate_height / 2),
            rgba="0.25 0.25 0.28 1",
        )
        r_in = fa.tube_inner_diameter / 2
        n_seg = 24
        r_mid = r_in + fa.tube_wall / 2
        half_arc = np.pi * r_mid / n_seg * 1.15  # overlap so that no ray slips between segments
        z0 = fa.plate_height
        grp = str(GROUP["reflectors"])
        for i, (x, y) in enumerate(fa.fiducials):
            ET.SubElement(
                body,
                "geom",
                name=f"fiducial_{i}_reflector",
                type="cylinder",
                group=grp,
                pos=_f(x, y, z0 + 0.0005),
                size=_f(r_in, 0.0005),
                rgba="0.95 0.95 1 1",
                material=self._shiny(),
            )
            for k in range(n_seg):
                a = 2 * np.pi * k / n_seg
                ET.SubElement(
                    body,
                    "geom",
                    name=f"fiducial_{i}_wall_{k}",
                    type="box",
                    group=grp,
                    pos=_f(x + r_mid * np.cos(a), y + r_mid * np.sin(a), z0 + fa.tube_height / 2),
                    quat=_yaw_quat(a),
                    size=_f(fa.tube_wall / 2, half_arc, fa.tube_height / 2),
                    rgba="0.1 0.1 0.1 1",
                    contype="0",
                    conaffinity="0",
                )

    # --- robot --------------------------------------------------------------------------
    def build_robot(self, start_pose2d: Array, mount: MountCompliance | None = None) -> None:
        rb = self.robot
        b = rb.base
        x, y, th = start_pose2d
        base = ET.SubElement(
            self.world, "body", name="base_link", pos=_f(x, y, 0.002), quat=_yaw_quat(th)
        )
        ET.SubElement(base, "freejoint", name="base_free")
        bx, by, bz = b.body_size
        clearance = b.ground_clearance
        ET.SubElement(
            base,
            "geom",
            name="base_body",
            type="box",
            pos=_f(b.body_offset_x, 0, clearance + bz / 2),
            size=_f(bx / 2, by / 2, bz / 2),
            mass=_f(b.mass - b.ballast_mass),
            rgba="0.92 0.92 0.94 1",
            **_ROBOT_COLLISION,
        )
        # batteries low and behind the axle keep the centre of mass over the wheel-caster
        # support when the arm reaches forward or the base brakes
        ET.SubElement(
            base,
            "geom",
            name="base_ballast",
            type="box",
            pos=_f(b.ballast_x, 0, clearance + 0.03),
            size=_f(0.12, 0.15, 0.03),
            mass=_f(b.ballast_mass),
            rgba="0.3 0.3 0.3 1",
            **_ROBOT_VISUAL,
        )
        ET.SubElement(
            base,
            "geom",
            name="base_bumper",
            type="box",
            contype="0",
            conaffinity="0",
            group=str(GROUP["robot_visual"]),
            pos=_f(b.body_offset_x, 0, clearance + bz + 0.005),
            size=_f(bx / 2 - 0.01, by / 2 - 0.01, 0.005),
            rgba="0.1 0.3 0.7 1",
            mass="0",
        )
        for side, sgn in (("left", 1.0), ("right", -1.0)):
            wheel = ET.SubElement(
                base,
                "body",
                name=f"wheel_{side}",
                pos=_f(0, sgn * b.track_width / 2, b.wheel_radius),
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
                size=_f(b.wheel_radius, b.wheel_width / 2, b.wheel_radius),
                mass="2.0",
                friction="1.2 0.005 0.0001",
                condim="3",
                rgba="0.1 0.1 0.1 1",
                **_ROBOT_COLLISION,
            )
            # integrated-velocity servo: the wheel tracks the integral of the commanded
            # speed, so a stopped base holds its position on a slope (a plain velocity servo
            # lets it creep down the speed bump)
            ET.SubElement(
                self.actuators,
                "intvelocity",
                name=f"wheel_{side}_vel",
                joint=f"wheel_{side}_joint",
                kp="3000",
                kv="150",
                actrange="-1e9 1e9",
                ctrlrange=_f(-b.max_wheel_speed, b.max_wheel_speed),
                forcerange="-60 60",
            )
        # caster: a frictionless sphere acts as the passive universal wheel
        ET.SubElement(
            base,
            "geom",
            name="caster",
            type="sphere",
            size=_f(b.caster_radius),
            pos=_f(b.caster_x, 0, b.caster_radius),
            condim="1",
            priority="1",  # the contact takes the caster's condim (frictionless), not the floor's
            mass="1.0",
            rgba="0.2 0.2 0.2 1",
            **_ROBOT_COLLISION,
        )
        ET.SubElement(
            base,
            "site",
            name="laser",
            **_pose_attrs(rb.lidar.T_base_link_laser),
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
            pos=_f(*rb.lidar.T_base_link_laser[:3, 3]),
            rgba="0.9 0.8 0.1 1",
            mass="0",
            **_ROBOT_VISUAL,
        )
        self.build_arm(base, mount)

    def build_arm(self, base: ET.Element, mount: MountCompliance | None = None) -> None:
        rb = self.robot
        arm = rb.arm
        a, d, alpha, off = arm.dh.as_arrays()
        parent = ET.SubElement(
            base, "body", name="arm_base", **_pose_attrs(rb.T_base_link_arm_base)
        )
        if mount is not None:
            self.build_mount(parent, mount)
        ET.SubElement(
            parent,
            "geom",
            name="arm_pedestal",
            type="cylinder",
            size="0.075 0.045",
            pos="0 0 0.045",
            rgba="0.3 0.5 0.7 1",
            mass="0",
            **_ROBOT_VISUAL,
        )
        torque = (150.0, 150.0, 150.0, 28.0, 28.0, 28.0)
        kp = (4000.0, 4000.0, 3000.0, 800.0, 800.0, 600.0)
        A0 = [
            make_T(rot_z(off[i])) @ trans(z=d[i]) @ trans(x=a[i]) @ make_T(rot_x(alpha[i]))
            for i in range(6)
        ]
        for i in range(6):
            child_T = A0[i]
            link = ET.SubElement(
                parent, "body", name=f"link{i + 1}", pos="0 0 0", quat="1 0 0 0", gravcomp="1"
            )
            p_end = child_T[:3, 3]
            ET.SubElement(
                link,
                "inertial",
                pos=_f(*(p_end / 2)),
                mass=_f(arm.link_masses[i]),
                diaginertia=_f(0.01, 0.01, 0.01),
            )
            ET.SubElement(
                link,
                "joint",
                name=f"joint{i + 1}",
                type="hinge",
                axis="0 0 1",
                range=_f(arm.q_min[i], arm.q_max[i]),
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
                **_ROBOT_VISUAL,
            )
            if np.linalg.norm(p_end) > 1e-3:
                ET.SubElement(
                    link,
                    "geom",
                    name=f"link{i + 1}_geom",
                    type="capsule",
                    fromto=_f(0, 0, 0, *p_end),
                    size="0.04",
                    rgba="0.75 0.78 0.8 1",
                    mass="0",
                    **_ROBOT_COLLISION,
                )
            ET.SubElement(
                self.actuators,
                "position",
                name=f"arm{i + 1}",
                joint=f"joint{i + 1}",
                kp=_f(kp[i]),
                kv=_f(2 * np.sqrt(kp[i] * 0.5)),
                ctrlrange=_f(arm.q_min[i], arm.q_max[i]),
                forcerange=_f(-torque[i], torque[i]),
            )
            nxt = ET.SubElement(
                link,
                "body",
                name="flange" if i == 5 else f"_frame{i + 1}",
                **_pose_attrs(child_T),
                gravcomp="1",
            )
            parent = nxt
        self.build_tool(parent)

    def build_mount(self, arm_base: ET.Element, mount: MountCompliance) -> None:
        """The hinges of the compliant mount (:class:`MountCompliance`) in ``arm_base``.

        Their axes are base_link's x and y written in the arm_base frame. The arm's links
        carry ``gravcomp`` (their motors hold them up), which MuJoCo applies as a force on
        every ancestor joint; the mount is no motor, so its joints route that compensation
        to their actuator force and clamp it to zero (``actuatorgravcomp``,
        ``actuatorfrcrange``): the mount carries the arm's full weight."""
        R = self.robot.T_base_link_arm_base[:3, :3]
        # a thin mount plate: a body with joints needs a mass of its own
        ET.SubElement(
            arm_base, "inertial", pos="0 0 0.01", mass="0.2", diaginertia="2e-4 2e-4 4e-4"
        )
        for name, axis, ref in zip(
            MOUNT_JOINTS, (R.T[:, 0], R.T[:, 1]), mount.springref, strict=True
        ):
            ET.SubElement(
                arm_base,
                "joint",
                name=name,
                type="hinge",
                pos="0 0 0",
                axis=_f(*axis),
                stiffness=_f(mount.stiffness),
                springref=_f(ref),
                damping=_f(mount.damping),
                actuatorgravcomp="true",
                actuatorfrcrange="-1e-12 1e-12",
            )

    def build_tool(self, flange: ET.Element) -> None:
        rb = self.robot
        g = rb.gripper
        ET.SubElement(
            flange, "site", name="tcp", **_pose_attrs(g.T_flange_tcp), size="0.005", group="4"
        )
        ET.SubElement(
            flange,
            "site",
            name="photosensor",
            **_pose_attrs(rb.photosensor.T_flange_sensor),
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
            fovy=_f(np.rad2deg(rb.camera.color.fovy)),
            **_pose_attrs(T_cam_mj),
        )
        ET.SubElement(
            flange,
            "geom",
            name="camera_housing",
            type="box",
            size="0.045 0.0125 0.0125",
            **_pose_attrs(rb.camera.T_flange_camera @ trans(z=-0.015)),
            rgba="0.2 0.2 0.22 1",
            mass="0.07",
            **_ROBOT_VISUAL,
        )
        ET.SubElement(
            flange,
            "geom",
            name="gripper_palm",
            type="box",
            size="0.04 0.055 0.045",
            pos=_f(0, 0, 0.05),
            mass="0.9",
            rgba="0.15 0.15 0.15 1",
            **_ROBOT_COLLISION,
        )
        half = g.stroke / 2
        pad_len = 0.025
        z_pad = g.length - 0.005
        for side, sgn in (("left", 1.0), ("right", -1.0)):
            f = ET.SubElement(
                flange, "body", name=f"finger_{side}", pos=_f(0, sgn * half, z_pad), gravcomp="1"
            )
            ET.SubElement(
                f,
                "joint",
                name=f"finger_{side}_joint",
                type="slide",
                axis=_f(0, -sgn, 0),
                range=_f(0, half - 0.001),
                damping="5",
                armature="0.01",
            )
            ET.SubElement(
                f,
                "geom",
                name=f"finger_{side}_pad",
                type="box",
                size=_f(0.011, 0.006, pad_len),
                pos=_f(0, sgn * 0.006, 0),
                mass="0.05",
                friction="1.5 0.02 0.001",
                condim="4",
                solref="0.004 1",  # stiff pads: a 110 N grip sinks < 1.5 mm into the object
                solimp="0.99 0.999 0.001",
                rgba="0.25 0.25 0.25 1",
                **_ROBOT_COLLISION,
            )
            ET.SubElement(
                f,
                "geom",
                name=f"finger_{side}_link",
                type="box",
                size=_f(0.011, 0.006, 0.035),
                pos=_f(0, sgn * 0.012, -0.045),
                mass="0.05",
                rgba="0.3 0.3 0.3 1",
                **_ROBOT_VISUAL,
            )
        ET.SubElement(
            self.equality,
            "joint",
            joint1="finger_right_joint",
            joint2="finger_left_joint",
            polycoef="0 1 0 0 0",
            solref="0.005 1",
        )
        ET.SubElement(
            self.actuators,
            "position",
            name="gripper",
            joint="finger_left_joint",
            kp="2500",
            kv="40",
            ctrlrange=_f(0, half - 0.001),
            forcerange=_f(-g.max_force, g.max_force),
        )


def _quat_of(R: Array) -> Array:
    q = np.empty(4)
    mujoco.mju_mat2Quat(q, np.ascontiguousarray(R).ravel())
    return q


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
    b = _Builder(scene, robot)
    b.build_robot(np.zeros(3), MountCompliance(1.0, 0.0, (0.0, 0.0)))
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
    b = _Builder(scene, robot)
    b.build_world()
    if start_pose2d is None:
        start_pose2d = scene.sites["0"].pose2d if "0" in scene.sites else np.zeros(3)
    mount = (
        mount_compliance(scene, robot, compliance.tilt_full_reach_deg)
        if compliance is not None
        else None
    )
    b.build_robot(np.asarray(start_pose2d, float), mount)
    ET.indent(b.root)
    return BuiltModel(ET.tostring(b.root, encoding="unicode"), b.assets)
