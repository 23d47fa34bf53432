"""MJCF of the room: lights, the textured floor, the walls, the laser reflectors, the speed
bump (parked below the floor until a site asks for it), the desks with their items and the
grasp objects (:mod:`mmpa.backends.twin.mjcf.items`), and the fiducial artifact (reflector
discs at the bottom of walled tubes on a plate). Units: m, rad.
"""

from __future__ import annotations

import xml.etree.ElementTree as ET

import numpy as np

from mmpa.backends.twin import textures
from mmpa.backends.twin.mjcf.common import GROUP, ModelBuilder, fmt, yaw_quat
from mmpa.backends.twin.mjcf.items import build_desk, build_grasp_object

__all__ = ["build_fiducials", "build_speed_bump", "build_world"]


def _lights(w: ET.Element) -> None:
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


def _floor_and_walls(b: ModelBuilder) -> None:
    s, w = b.scene, b.world
    floor_mat = b.texture("floor", textures.floor(b.rng), repeat=(s.floor_size[0], s.floor_size[1]))
    ET.SubElement(
        w,
        "geom",
        name="floor",
        type="plane",
        material=floor_mat,
        pos=fmt(*s.floor_center, 0),
        size=fmt(s.floor_size[0] / 2, s.floor_size[1] / 2, 0.1),
        friction="1.0 0.005 0.0001",
        group="0",
    )
    wall_mat = b.texture("wall", textures.wall(b.rng))
    for i, wall in enumerate(s.walls):
        a, e = np.array(wall.start), np.array(wall.end)
        c, d = (a + e) / 2, e - a
        ET.SubElement(
            w,
            "geom",
            name=f"wall_{i}",
            type="box",
            material=wall_mat,
            group="0",
            pos=fmt(*c, wall.height / 2),
            quat=yaw_quat(np.arctan2(d[1], d[0])),
            size=fmt(
                np.linalg.norm(d) / 2 + wall.thickness / 2, wall.thickness / 2, wall.height / 2
            ),
        )


def _reflectors(b: ModelBuilder) -> None:
    r = b.scene.reflectors
    for i, (x, y) in enumerate(r.positions):
        ET.SubElement(
            b.world,
            "geom",
            name=f"reflector_{i}",
            type="cylinder",
            group=str(GROUP["reflectors"]),
            pos=fmt(x, y, r.height / 2),
            size=fmt(r.radius, r.height / 2),
            rgba="0.92 0.92 0.95 1",
            material=b.shiny(),
        )


def build_world(b: ModelBuilder) -> None:
    """Everything of the scene but the robot, in document order: lights, floor, walls,
    reflectors, speed bump, desks, the grasp desk, grasp objects, fiducials."""
    s = b.scene
    _lights(b.world)
    _floor_and_walls(b)
    _reflectors(b)
    build_speed_bump(b)
    for bench in s.workbenches:
        build_desk(b, bench)
    if s.grasp_desk is not None:
        build_desk(b, s.grasp_desk)
    for obj in s.grasp_objects:
        build_grasp_object(b, obj)
    if s.fiducial_artifact is not None:
        build_fiducials(b)


def build_speed_bump(b: ModelBuilder) -> None:
    """The static body ``speed_bump`` (a triangular prism mesh), parked 1 m below the floor."""
    sb = b.scene.speed_bump
    if sb is None:
        return
    L, W, H = sb.length / 2, sb.width / 2, sb.height
    verts = [(-L, -W, 0), (L, -W, 0), (-L, W, 0), (L, W, 0), (-L, 0, H), (L, 0, H)]
    ET.SubElement(b.asset, "mesh", name="speed_bump_mesh", vertex=" ".join(fmt(*v) for v in verts))
    # Parked below the floor until a site with a bump asks for it (SimWorld.set_speed_bump).
    body = ET.SubElement(
        b.world,
        "body",
        name="speed_bump",
        pos=fmt(*sb.center, -1.0),
        quat=yaw_quat(np.deg2rad(sb.yaw_deg)),
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


def build_fiducials(b: ModelBuilder) -> None:
    """The fiducial artifact: a plate, and per fiducial a reflector disc
    ``fiducial_<i>_reflector`` walled by 24 overlapping boxes ``fiducial_<i>_wall_<k>``."""
    fa = b.scene.fiducial_artifact
    assert fa is not None
    body = ET.SubElement(
        b.world,
        "body",
        name="fiducial_artifact",
        pos=fmt(*fa.origin, 0),
        quat=yaw_quat(np.deg2rad(fa.yaw_deg)),
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
        pos=fmt(cx, cy, fa.plate_height / 2),
        size=fmt(hx, hy, fa.plate_height / 2),
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
            pos=fmt(x, y, z0 + 0.0005),
            size=fmt(r_in, 0.0005),
            rgba="0.95 0.95 1 1",
            material=b.shiny(),
        )
        for k in range(n_seg):
            a = 2 * np.pi * k / n_seg
            ET.SubElement(
                body,
                "geom",
                name=f"fiducial_{i}_wall_{k}",
                type="box",
                group=grp,
                pos=fmt(x + r_mid * np.cos(a), y + r_mid * np.sin(a), z0 + fa.tube_height / 2),
                quat=yaw_quat(a),
                size=fmt(fa.tube_wall / 2, half_arc, fa.tube_height / 2),
                rgba="0.1 0.1 0.1 1",
                contype="0",
                conaffinity="0",
            )
