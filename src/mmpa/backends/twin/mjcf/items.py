"""MJCF of the things on and around the desks: a desk (top and four legs) with its items,
each item kind a builder of its own (:data:`ITEM_BUILDERS`, kind -> builder), and the free
grasp objects.

An item sits in the desk-top frame (x along the desk, y away from the robot, z up from the
top; :func:`~mmpa.backends.twin.mjcf.common.desk_item_pose`). A fixed item's geoms are the
desk body's; a free or loose item is a world body of its own at its desk pose (a free one
moves by physics, a loose static one by the scene change). Units: m, rad.
"""

from __future__ import annotations

import xml.etree.ElementTree as ET
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from mmpa.backends.twin import textures
from mmpa.backends.twin.mjcf.common import (
    GROUP,
    ModelBuilder,
    desk_item_pose,
    fmt,
    pose_attrs,
    quat_of,
    yaw_quat,
)
from mmpa.backends.twin.scene import DeskItem, GraspObject, Workbench
from mmpa.core.geometry import Array, rot_x, rot_y, rot_z

__all__ = ["ITEM_BUILDERS", "ItemFrame", "build_desk", "build_grasp_object", "build_item"]


@dataclass
class ItemFrame:
    """Where an item's geoms go: the ``parent`` body, the item's model ``name``, its origin
    ``base`` (3,) and heading ``yaw`` (rad) in the parent body, and its geom ``group``."""

    parent: ET.Element
    name: str
    base: Array
    yaw: float
    group: str

    def geom(self, suffix: str, local_pos: tuple[float, float, float], **attrs: str) -> None:
        """A geom ``<name>_<suffix>`` at ``local_pos`` (item frame), turned with the item
        unless ``attrs`` has a ``quat`` of its own."""
        p = self.base + rot_z(self.yaw) @ np.asarray(local_pos, float)
        attrs.setdefault("quat", yaw_quat(self.yaw))
        ET.SubElement(
            self.parent,
            "geom",
            name=f"{self.name}_{suffix}",
            pos=fmt(*p),
            group=self.group,
            **attrs,
        )


#: an item kind's builder: (model, where its geoms go, the item, its rgba) -> None
ItemBuilder = Callable[[ModelBuilder, ItemFrame, DeskItem, str], None]


def _backboard(b: ModelBuilder, it: ItemFrame, item: DeskItem, rgba: str) -> None:
    lx, ly, lz = item.size or (1.1, 0.03, 0.45)
    mat = b.texture(f"{it.name}_poster", textures.backboard(b.rng))
    it.geom("board", (0, 0, lz / 2), type="box", size=fmt(lx / 2, ly / 2, lz / 2), material=mat)


def _poster(b: ModelBuilder, it: ItemFrame, item: DeskItem, rgba: str) -> None:
    # a colorful print lying on the desk (paper 000 Fig. A.1: textures on thin paper)
    lx, ly = (item.size or (0.2, 0.15))[:2]
    mat = b.texture(f"{it.name}_poster", textures.backboard(b.rng))
    it.geom("sheet", (0, 0, 0.0005), type="box", size=fmt(lx / 2, ly / 2, 0.0005), material=mat)


def _dot(b: ModelBuilder, it: ItemFrame, item: DeskItem, rgba: str) -> None:
    # paper 000 Fig. 6c/10: the red dot the needle points at (printed on thin paper)
    r = (item.size or (0.004,))[0]
    it.geom(
        "disc",
        (0, 0, 0.0005),
        type="cylinder",
        size=fmt(r, 0.0005),
        rgba=b.color(item.color or (0.85, 0.05, 0.05)),
    )


def _tape(b: ModelBuilder, it: ItemFrame, item: DeskItem, rgba: str) -> None:
    """A logo or letter tape stuck on the desk top."""
    lx, ly = (item.size or (0.2, 0.06))[:2]
    if item.kind == "logo_tape":
        img = textures.logo(b.rng)
    else:
        img = textures.letters(item.text or "MMPA", b.rng)
    mat = b.texture(f"{it.name}_print", img)
    it.geom("tape", (0, 0, 0.0008), type="box", size=fmt(lx / 2, ly / 2, 0.0008), material=mat)


def _valve_container(b: ModelBuilder, it: ItemFrame, item: DeskItem, rgba: str) -> None:
    r, hh = (item.size or (0.09, 0.30))[:2]
    yaw = it.yaw
    it.geom(
        "tank",
        (0, 0, hh / 2),
        type="cylinder",
        size=fmt(r, hh / 2),
        rgba=b.color((0.85, 0.88, 0.9)),
    )
    it.geom("band", (0, 0, hh * 0.7), type="cylinder", size=fmt(r + 0.002, 0.02), rgba=rgba)
    it.geom(
        "pipe",
        (0, -r - 0.035, 0.07),
        type="cylinder",
        size=fmt(0.015, 0.04),
        quat=fmt(*quat_of(rot_z(yaw) @ rot_x(np.pi / 2))),
        rgba="0.6 0.6 0.62 1",
    )
    it.geom(
        "wheel",
        (0, -r - 0.08, 0.07),
        type="cylinder",
        size=fmt(0.04, 0.006),
        quat=fmt(*quat_of(rot_z(yaw) @ rot_x(np.pi / 2))),
        rgba="0.8 0.1 0.1 1",
    )
    it.geom(
        "handle",
        (0, -r - 0.088, 0.07),
        type="box",
        size=fmt(0.045, 0.004, 0.008),
        rgba="0.15 0.15 0.15 1",
    )


def _cup(b: ModelBuilder, it: ItemFrame, item: DeskItem, rgba: str) -> None:
    r, hh = (item.size or (0.04, 0.09))[:2]
    it.geom("body", (0, 0, hh / 2), type="cylinder", size=fmt(r, hh / 2), rgba=rgba, mass="0.15")
    it.geom(
        "handle",
        (r + 0.012, 0, hh * 0.55),
        type="box",
        size=fmt(0.012, 0.005, 0.025),
        rgba=rgba,
        mass="0.01",
    )


_BOTTLE_SIZE = {
    "bottle": (0.035, 0.2),
    "small_bottle": (0.025, 0.10),
    "reagent_bottle": (0.04, 0.14),
}


def _bottle(b: ModelBuilder, it: ItemFrame, item: DeskItem, rgba: str) -> None:
    """A bottle, small bottle or reagent bottle: body, neck, a cap and a label of random
    colours."""
    r, hh = item.size or _BOTTLE_SIZE[item.kind]
    it.geom("body", (0, 0, hh / 2), type="cylinder", size=fmt(r, hh / 2), rgba=rgba)
    it.geom("neck", (0, 0, hh + 0.015), type="cylinder", size=fmt(r * 0.4, 0.015), rgba=rgba)
    it.geom(
        "cap",
        (0, 0, hh + 0.035),
        type="cylinder",
        size=fmt(r * 0.45, 0.008),
        rgba=b.color(None),
    )
    it.geom(
        "label",
        (0, 0, hh * 0.45),
        type="cylinder",
        size=fmt(r + 0.001, hh * 0.18),
        rgba=b.color(None),
    )


def _dropper(b: ModelBuilder, it: ItemFrame, item: DeskItem, rgba: str) -> None:
    it.geom(
        "tube",
        (0, 0, 0.007),
        type="capsule",
        size=fmt(0.006, 0.045),
        quat=fmt(*quat_of(rot_z(it.yaw) @ rot_y(np.pi / 2))),
        rgba="0.85 0.9 0.95 1",
    )
    it.geom("bulb", (0.055, 0, 0.011), type="sphere", size=fmt(0.011), rgba="0.9 0.3 0.2 1")


def _waste_container(b: ModelBuilder, it: ItemFrame, item: DeskItem, rgba: str) -> None:
    it.geom("bin", (0, 0, 0.08), type="box", size=fmt(0.06, 0.06, 0.08), rgba="0.35 0.35 0.38 1")
    it.geom("lid", (0, 0, 0.165), type="box", size=fmt(0.062, 0.062, 0.005), rgba="0.9 0.6 0.1 1")


def _test_tube_stand(b: ModelBuilder, it: ItemFrame, item: DeskItem, rgba: str) -> None:
    white = "0.95 0.95 0.95 1"
    it.geom("base", (0, 0, 0.005), type="box", size=fmt(0.12, 0.035, 0.005), rgba=white)
    it.geom("post_l", (-0.115, 0, 0.045), type="box", size=fmt(0.005, 0.03, 0.04), rgba=white)
    it.geom("post_r", (0.115, 0, 0.045), type="box", size=fmt(0.005, 0.03, 0.04), rgba=white)
    it.geom("rack", (0, 0, 0.085), type="box", size=fmt(0.12, 0.035, 0.005), rgba="0.2 0.5 0.85 1")
    for t in range(6):
        tint = b.color(None)
        it.geom(
            f"tube{t}",
            (-0.09 + 0.036 * t, 0, 0.07),
            type="cylinder",
            size=fmt(0.008, 0.06),
            rgba=tint,
        )


def _box(b: ModelBuilder, it: ItemFrame, item: DeskItem, rgba: str) -> None:
    lx, ly, lz = item.size or (0.08, 0.08, 0.08)
    it.geom("box", (0, 0, lz / 2), type="box", size=fmt(lx / 2, ly / 2, lz / 2), rgba=rgba)


#: desk item kind -> its builder (a kind missing here gets no geometry)
ITEM_BUILDERS: dict[str, ItemBuilder] = {
    "backboard": _backboard,
    "poster": _poster,
    "dot": _dot,
    "logo_tape": _tape,
    "letter_tape": _tape,
    "valve_container": _valve_container,
    "cup": _cup,
    "bottle": _bottle,
    "small_bottle": _bottle,
    "reagent_bottle": _bottle,
    "dropper": _dropper,
    "waste_container": _waste_container,
    "test_tube_stand": _test_tube_stand,
    "box": _box,
}


def _item_frame(
    b: ModelBuilder, bench: Workbench, desk: ET.Element, item: DeskItem, j: int
) -> ItemFrame:
    """Where item ``j`` of ``bench`` goes: a free or loose item gets its own world body at its
    desk pose (a free one moves by physics, a loose static one by the scene change:
    mmpa.backends.twin.scene_change sets its body_pos / body_quat), a fixed one is part of
    the ``desk`` body."""
    name = bench.item_name(j)
    if item.free or item.loose:
        T = desk_item_pose(bench, item)
        parent = ET.SubElement(b.world, "body", name=name, **pose_attrs(T))
        if item.free:
            ET.SubElement(parent, "freejoint", name=f"{name}_free")
        group = str(GROUP["objects"]) if item.free else "0"
        return ItemFrame(parent, name, np.zeros(3), 0.0, group)
    base = np.array([*item.xy, bench.size[2]])
    return ItemFrame(desk, name, base, np.deg2rad(item.yaw_deg), "0")


def build_item(b: ModelBuilder, bench: Workbench, desk: ET.Element, item: DeskItem, j: int) -> None:
    """Item ``j`` of ``bench`` (:data:`ITEM_BUILDERS`); its colour is drawn first (a seeded
    random one when the item has none), whether its kind uses it or not."""
    it = _item_frame(b, bench, desk, item, j)
    rgba = b.color(item.color)
    builder = ITEM_BUILDERS.get(item.kind)
    if builder is not None:
        builder(b, it, item, rgba)


def build_desk(b: ModelBuilder, bench: Workbench) -> None:
    """The desk body ``desk_<name>``: its top (wood texture or a plain colour), four legs,
    then its items in order."""
    lx, ly, h = bench.size
    yaw = np.deg2rad(bench.yaw_deg)
    body = ET.SubElement(
        b.world,
        "body",
        name=f"desk_{bench.name}",
        pos=fmt(*bench.center, 0),
        quat=yaw_quat(yaw),
    )
    if bench.top_color is None:
        top_look = {"material": b.texture(f"wood_{bench.name}", textures.wood(b.rng))}
    else:
        top_look = {"rgba": b.color(bench.top_color)}
    top = 0.03
    ET.SubElement(
        body,
        "geom",
        name=f"desk_{bench.name}_top",
        type="box",
        **top_look,
        pos=fmt(0, 0, h - top / 2),
        size=fmt(lx / 2, ly / 2, top / 2),
        group="0",
    )
    for k, (sx, sy) in enumerate([(1, 1), (1, -1), (-1, 1), (-1, -1)]):
        ET.SubElement(
            body,
            "geom",
            name=f"desk_{bench.name}_leg{k}",
            type="box",
            pos=fmt(sx * (lx / 2 - 0.04), sy * (ly / 2 - 0.04), (h - top) / 2),
            size=fmt(0.02, 0.02, (h - top) / 2),
            rgba="0.3 0.3 0.32 1",
            group="0",
        )
    for j, item in enumerate(bench.items):
        build_item(b, bench, body, item, j)


def build_grasp_object(b: ModelBuilder, obj: GraspObject) -> None:
    """A free grasp object: a cube, a ball, or a cylinder (bottle, cup, stick; upright or
    lying along the body x axis) with an optional label and cap (decoration, no contact)."""
    body = ET.SubElement(b.world, "body", name=obj.name, pos=fmt(*obj.position))
    ET.SubElement(body, "freejoint", name=f"{obj.name}_free")
    rgba = fmt(*obj.color, 1.0)
    look = {"rgba": rgba}
    if obj.glossy:
        look["material"] = b.glossy()
    common = {
        "group": str(GROUP["objects"]),
        "mass": fmt(obj.mass),
        "friction": "1.0 0.01 0.001",
        # a lying cylinder also gets rolling friction (condim 6; 1 mm): the convex
        # cylinder-box contact is one point, so without it 8 of 20 blue sticks placed at
        # rest rolled 6-163 mm in 3 s (one rolled off the reachable region); with it <= 8 mm
        "condim": "6" if obj.lying else "4",
        **look,
    }
    if obj.kind == "cube":
        ET.SubElement(
            body,
            "geom",
            name=f"{obj.name}_geom",
            type="box",
            size=fmt(*[obj.size[0]] * 3),
            **common,
        )
    elif obj.kind == "ball":
        ET.SubElement(
            body, "geom", name=f"{obj.name}_geom", type="sphere", size=fmt(obj.size[0]), **common
        )
    else:  # bottle, cup, stick: cylinders, upright or lying along the body x axis
        _grasp_cylinder(body, obj, common)


def _grasp_cylinder(body: ET.Element, obj: GraspObject, common: dict[str, str]) -> None:
    deco = {"group": str(GROUP["objects"]), "contype": "0", "conaffinity": "0", "mass": "0"}
    r, hh = obj.size[0], obj.size[1]
    axis = {"euler": "0 1.5707963 0"} if obj.lying else {}
    ET.SubElement(
        body,
        "geom",
        name=f"{obj.name}_geom",
        type="cylinder",
        size=fmt(r, hh),
        **axis,
        **common,
    )
    if obj.label is not None:
        ET.SubElement(
            body,
            "geom",
            name=f"{obj.name}_label",
            type="cylinder",
            size=fmt(r * 1.03, hh * 0.35),
            rgba=fmt(*obj.label, 1.0),
            **axis,
            **deco,
        )
    if obj.cap is not None:
        bottle = obj.kind == "bottle"
        cap_r, cap_h = (0.45 * r, 0.1 * hh) if bottle else (1.02 * r, 0.25 * hh)
        c = hh + cap_h if obj.kind == "bottle" else hh - cap_h * 0.99
        pos = fmt(c, 0, 0) if obj.lying else fmt(0, 0, c)
        ET.SubElement(
            body,
            "geom",
            name=f"{obj.name}_cap",
            type="cylinder",
            size=fmt(cap_r, cap_h),
            pos=pos,
            rgba=fmt(*obj.cap, 1.0),
            **axis,
            **deco,
        )
