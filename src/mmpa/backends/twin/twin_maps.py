"""The twin's maps: what a robot in the twin would have mapped, and its lidar mount.

``twin_map`` builds the occupancy grid the paper builds with Gmapping: here from the scene
geometry the lidar can see (every static and movable geom of the MuJoCo model that cuts the
lidar's scan plane), rasterized through the mapping distortion of the error model
(``world.map_warp``: a smooth displacement field, DESIGN.md "Error model v2"), with the
SURVEYED reflector positions (``world.map_reflectors``, off the true ones per the error model)
stored as landmarks. ``twin_nav_map`` (the planner's obstacles) stays undistorted.
``laser_pose2d`` is the NOMINAL lidar mount. (Twin tools: the navigation itself,
:mod:`mmpa.missions.navigate`, runs on the robot protocols.)
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import mujoco
import numpy as np

from mmpa.core.geometry import Array, T_to_se2
from mmpa.maps.occupancy import Box2D, OccupancyGrid, rasterize

if TYPE_CHECKING:  # pragma: no cover
    from mmpa.backends.twin.world import SimWorld

__all__ = ["laser_pose2d", "twin_map", "twin_nav_map"]


_GEOM_BOX = int(mujoco.mjtGeom.mjGEOM_BOX)
_GEOM_CYL = int(mujoco.mjtGeom.mjGEOM_CYLINDER)


def laser_pose2d(world: SimWorld) -> Array:
    """The NOMINAL lidar mount ``[x, y, yaw]`` in ``base_link``."""
    return T_to_se2(world.nominal.lidar.T_base_link_laser)


def twin_map(
    world: SimWorld,
    resolution: float = 0.05,
    margin: float = 0.5,
    z_band: tuple[float, float] | None = None,
    warped: bool = True,
) -> OccupancyGrid:
    """Occupancy grid of everything the lidar plane cuts (or, with ``z_band`` = (low, high),
    everything overlapping that height band), plus the surveyed reflector landmarks.

    ``warped``: draw it through the world's mapping distortion ``world.map_warp`` (a world
    point ``q`` lies at ``q + map_warp(q)`` in the map; zero in the ``reference`` profile), as
    a map made by SLAM at mapping time is; ``False``: the true geometry."""
    m, d = world.model, world.data
    z = float(world.nominal.lidar.T_base_link_laser[2, 3])
    lo, hi = z_band if z_band is not None else (z, z)
    boxes: list[Box2D] = []
    for g in range(m.ngeom):
        if m.geom_group[g] > 2 or m.geom_type[g] not in (_GEOM_BOX, _GEOM_CYL):
            continue
        R = d.geom_xmat[g].reshape(3, 3)
        if abs(R[2, 2]) < 0.99:  # tilted geoms (none in the default world) are skipped
            continue
        size = m.geom_size[g]
        pos = d.geom_xpos[g]
        half_h = size[2] if m.geom_type[g] == _GEOM_BOX else size[1]
        if pos[2] + half_h < lo or pos[2] - half_h > hi:
            continue
        if m.geom_type[g] == _GEOM_CYL:
            boxes.append(Box2D((float(pos[0]), float(pos[1])), radius=float(size[0])))
        else:
            yaw = float(np.arctan2(R[1, 0], R[0, 0]))
            boxes.append(
                Box2D((float(pos[0]), float(pos[1])), (2 * float(size[0]), 2 * float(size[1])), yaw)
            )
    sc = world.scene
    cx, cy = sc.floor_center
    sx, sy = sc.floor_size
    bounds = (
        cx - sx / 2 - margin,
        cy - sy / 2 - margin,
        cx + sx / 2 + margin,
        cy + sy / 2 + margin,
    )
    warp = getattr(world, "map_warp", None) if warped else None
    if warp is not None and getattr(warp, "sigma", 1.0) == 0:
        warp = None
    return rasterize(
        boxes,
        bounds,
        resolution,
        world.map_reflectors.copy(),
        float(sc.reflectors.radius),
        warp=warp,
    )


def twin_nav_map(world: SimWorld, resolution: float = 0.05) -> OccupancyGrid:
    """Obstacle map for planning: everything the base body could hit (between its ground
    clearance and its top), including low things the lidar plane misses (e.g. the fiducial
    artifact); the speed bump (lower than the clearance) stays traversable. Nav2 would get
    these from other sensors or a keep-out layer."""
    b = world.nominal.base
    return twin_map(
        world, resolution, z_band=(b.ground_clearance + 0.005, b.body_size[2]), warped=False
    )
