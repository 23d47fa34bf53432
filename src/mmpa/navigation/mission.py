"""Drive the twin (or any robot with the same devices) to a goal on the localization estimate.

``twin_map`` builds the occupancy grid the paper builds with Gmapping: here from the scene
geometry the lidar can see (every static and movable geom of the MuJoCo model that cuts the
lidar's scan plane), rasterized through the mapping distortion of the error model
(``world.map_warp``: a smooth displacement field, DESIGN.md "Error model v2"), with the
SURVEYED reflector positions (``world.map_reflectors``, off the true ones per the error model)
stored as landmarks. ``twin_nav_map`` (the planner's obstacles) stays undistorted.

``localize_standing`` runs a localizer on scans while the base stands still: how a parked
robot (or one just told its rough pose) gets its pose estimate.

``navigate`` runs the loop: scans at ``scan_rate`` into the localizer, plan A* from the
estimate, pure pursuit, final approach with position and heading tolerances, settle and
re-check (up to ``max_corrections`` times). It steers only on ``localizer.pose_at(odometry)``;
the ground truth is read only to record the evaluation trace.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

import mujoco
import numpy as np
from pydantic import BaseModel, ConfigDict, Field

from mmpa.geometry import Array, T_to_se2, wrap_angle
from mmpa.localization.localizer import Localizer
from mmpa.localization.maps import Box2D, OccupancyGrid, rasterize
from mmpa.navigation.follower import FollowerConfig, PathFollower
from mmpa.navigation.planner import CostMap, PlannerConfig, plan_path

if TYPE_CHECKING:  # pragma: no cover
    from mmpa.sim.world import SimWorld

__all__ = [
    "NavigateConfig",
    "NavigationResult",
    "laser_pose2d",
    "localize_standing",
    "navigate",
    "twin_map",
    "twin_nav_map",
]

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


def localize_standing(
    world: SimWorld, localizer: Localizer, scans: int = 5, scan_rate: float = 10.0
) -> Array:
    """Feed ``scans`` scans taken ``1 / scan_rate`` s apart to an initialized ``localizer``
    while the base stands still (each update forced: Nav2 AMCL would wait for motion), and
    return its estimate ``[x, y, theta]`` at the current odometry. The truth is not read."""
    world.base.stop()
    for _ in range(scans):
        world.step(1.0 / scan_rate)
        odom = world.odometry.odometry().pose
        localizer.update(odom, world.lidar.scan(), force=True)
    return localizer.pose_at(world.odometry.odometry().pose)


class NavigateConfig(BaseModel):
    """Navigation loop settings (Hz, s, m, rad)."""

    model_config = ConfigDict(extra="forbid")

    control_rate: float = Field(20.0, gt=0)
    scan_rate: float = Field(10.0, gt=0)
    timeout: float = Field(120.0, gt=0)  # s of simulated time
    initial_scans: int = Field(5, ge=0)  # stationary scans before planning
    settle_scans: int = Field(10, ge=0)  # stationary scans after stopping, before re-checking
    max_corrections: int = Field(3, ge=0)
    planner: PlannerConfig = PlannerConfig()
    follower: FollowerConfig = FollowerConfig()


@dataclass
class NavigationResult:
    """Outcome; errors are truth vs goal (parking) and estimate vs truth (localization)."""

    reached: bool
    goal: Array
    final_truth: Array
    final_estimate: Array
    sim_time: float
    path: Array
    trace: dict[str, Array] = field(default_factory=dict)

    @property
    def parking_error_xy(self) -> float:
        return float(np.hypot(*(self.final_truth[:2] - self.goal[:2])))

    @property
    def parking_error_yaw(self) -> float:
        return float(abs(wrap_angle(self.final_truth[2] - self.goal[2])))

    @property
    def localization_error(self) -> Array:
        """``[ex, ey, e_theta]`` of the final estimate against the truth."""
        e = self.final_estimate - self.final_truth
        return np.array([e[0], e[1], float(wrap_angle(e[2]))])


def navigate(
    world: SimWorld,
    localizer: Localizer,
    grid: OccupancyGrid,
    goal: Array,
    cfg: NavigateConfig | None = None,
    on_tick: Callable[[SimWorld, float], None] | None = None,
    progress: Callable[[str, float], None] | None = None,
    costmap: CostMap | None = None,
) -> NavigationResult:
    """Drive to ``goal`` = ``[x, y, theta]`` on the localization estimate (see module doc).

    ``on_tick(world, t)`` runs every control tick (e.g. to move occluders); the localizer must
    already be initialized (rough initial pose).
    """
    cfg = cfg or NavigateConfig()
    goal = np.asarray(goal, float).reshape(3)
    dt = 1.0 / cfg.control_rate
    scan_every = max(1, round(cfg.control_rate / cfg.scan_rate))
    t0 = world.time
    trace: dict[str, list[Any]] = {"t": [], "truth": [], "estimate": [], "reflectors": []}
    tick = 0

    def sense(force: bool = False) -> Array:
        odom = world.odometry.odometry().pose
        scan = world.lidar.scan()
        localizer.update(odom, scan, force=force)
        est = localizer.pose_at(odom)
        trace["t"].append(world.time - t0)
        trace["truth"].append(world.truth.base_pose2d())  # evaluation only
        trace["estimate"].append(est)
        obs = getattr(localizer, "observer", None)
        trace["reflectors"].append(len(obs.last_detections) if obs is not None else -1)
        return est

    def advance() -> None:
        nonlocal tick
        if on_tick is not None:
            on_tick(world, world.time - t0)
        world.step(dt)
        tick += 1

    def stationary(n: int) -> Array:
        world.base.stop()
        est = localizer.pose_at(world.odometry.odometry().pose)
        for _ in range(n):
            for _ in range(scan_every):
                advance()
            est = sense(force=False)
        return est

    est = stationary(cfg.initial_scans) if cfg.initial_scans else sense(force=True)
    cm = costmap or CostMap(grid, cfg.planner)
    path = plan_path(cm, est[:2], goal[:2], cfg.planner)
    follower = PathFollower(path, goal, cfg.follower)
    total = float(np.sum(np.linalg.norm(np.diff(path, axis=0), axis=1))) or 1.0
    reached = False
    corrections = 0
    final_t0: float | None = None
    while world.time - t0 < cfg.timeout:
        if tick % scan_every == 0:
            sense()
        est = localizer.pose_at(world.odometry.odometry().pose)
        v, w, done = follower.command(est)
        if follower.final_phase and final_t0 is None:
            final_t0 = world.time
        if final_t0 is not None and world.time - final_t0 > cfg.follower.final_timeout:
            world.base.stop()
            break
        if done:
            est = stationary(cfg.settle_scans)
            ok = (
                np.hypot(*(est[:2] - goal[:2])) <= cfg.follower.final.pos_tol * 1.5
                and abs(wrap_angle(est[2] - goal[2])) <= cfg.follower.final.yaw_tol * 1.5
            )
            if ok or corrections >= cfg.max_corrections:
                reached = bool(ok)  # corrections used up out of tolerance: not reached
                break
            corrections += 1
            follower.restart_final()
            continue
        world.base.set_velocity(v, w)
        advance()
        if progress is not None and tick % 20 == 0:
            progress("driving", 1.0 - float(np.hypot(*(goal[:2] - est[:2]))) / total)
    world.base.stop()
    world.step(0.2)
    final_est = localizer.pose_at(world.odometry.odometry().pose)
    return NavigationResult(
        reached=reached,
        goal=goal,
        final_truth=world.truth.base_pose2d(),
        final_estimate=final_est,
        sim_time=world.time - t0,
        path=path,
        trace={k: np.asarray(v) for k, v in trace.items()},
    )
