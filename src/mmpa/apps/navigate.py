"""``mmpa navigate`` and ``mmpa map export``: drive from a site to another on the localizer's
estimate (the operator's rough pose to start), optionally recorded to a ROS 2 bag; write the
twin's occupancy map. The summary holds the parking error (truth vs goal), the localization
error (estimate vs truth) and the localizer's health over the drive.

:func:`navigate_twin` drives the twin in this process; :func:`navigate_robot` drives the robot
of a robot file's hardware backend (``mmpa --robot R.yaml navigate``,
:func:`mmpa.apps.robots.open_robot`) with the same mission: the base over its velocity topic,
the map from the robot (``/map`` and ``/reflectors``), localized by mmpa's localizer over its
scans and odometry, or by the robot's own running localizer (``backend.ros2.topics.pose``).
The truth is known only where the robot publishes it (the twin node's ``/truth/base_pose``)."""

from __future__ import annotations

from contextlib import ExitStack
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from mmpa.apps.localization_settings import load_localization_config
from mmpa.apps.robots import RobotLocalizer, open_robot
from mmpa.backends.bag import BagWriter, Recorder
from mmpa.backends.bag.record import ARM_RATE_HZ
from mmpa.backends.twin.error_model import ErrorModelConfig
from mmpa.backends.twin.operator import rough_initial_pose
from mmpa.backends.twin.scene import load_scene
from mmpa.backends.twin.twin_maps import twin_map, twin_nav_map
from mmpa.backends.twin.world import SimWorld
from mmpa.core.config import load_config
from mmpa.core.errors import ConfigError, InvalidInputError, UnknownNameError
from mmpa.core.geometry import Array, T_to_se2
from mmpa.harness.twin_localization import twin_localizer
from mmpa.localization.localizer import Localizer
from mmpa.localization.settings import LocalizationConfig, build_localizer, initial_covariance
from mmpa.maps.map_server import replace_reflectors, save_map
from mmpa.maps.occupancy import OccupancyGrid
from mmpa.missions.navigate import (
    NavigateConfig,
    NavigationResult,
    localize_standing,
    navigate,
)
from mmpa.navigation.planner import CostMap
from mmpa.robot.interfaces import MobileManipulator, require
from mmpa.robot.robot_file import robot_backend

__all__ = [
    "RobotOnMap",
    "drive_robot",
    "export_twin_map",
    "health_summary",
    "localize_robot",
    "navigate_robot",
    "navigate_twin",
    "robot_on_map",
    "site_or_pose",
    "twin_errors",
]


def twin_errors(seed: int, profile: str | None) -> ErrorModelConfig:
    """The twin's error model: ``profile`` (None: realistic) for robot instance ``seed`` (a
    ``ConfigError`` for an unknown profile)."""
    sets = [f"seed={seed}"] + ([] if profile is None else [f"profile={profile}"])
    return load_config(ErrorModelConfig, None, sets)


def health_summary(trace: dict) -> dict:
    """The localizer's health over a drive (:mod:`mmpa.localization.health`): updates that
    said ``ok=False`` and the least explained share (when any was judged)."""
    ok, expl = trace["ok"].astype(bool), trace["explained"]
    out: dict = {"localization_updates_not_ok": int(np.sum(~ok))}
    if np.isfinite(expl).any():
        out["localization_explained_min"] = round(float(np.nanmin(expl)), 3)
    return out


def _mm(x: float, scale: float = 1000.0, digits: int = 2) -> float | None:
    """``x * scale`` rounded, or None where the truth is unknown (NaN)."""
    return round(scale * float(x), digits) if np.isfinite(x) else None


def _summary(res: NavigationResult, start: str, to: str, method: str, profile: str) -> dict:
    e = res.localization_error
    deg = float(np.rad2deg(1.0))
    summary = {
        "from": start,
        "to": to,
        "method": method,
        "profile": profile,
        "reached": res.reached,
        "corrections": res.corrections,
        "sim_seconds": round(res.sim_time, 2),
        "parking_error_xy_mm": _mm(res.parking_error_xy),
        "parking_error_yaw_deg": _mm(res.parking_error_yaw, deg, 3),
        "localization_error_xy_mm": _mm(float(np.hypot(e[0], e[1]))),
        "localization_error_yaw_deg": _mm(abs(e[2]), deg, 3),
    }
    summary.update(health_summary(res.trace))
    if not res.reached:
        summary["reason"] = res.reason
    return summary


def navigate_twin(
    errors: ErrorModelConfig,
    start: str,
    to: str,
    method: str = "enhanced",
    seed: int = 0,
    timeout: float = 120.0,
    reflector_map: Path | None = None,
    record: Path | None = None,
    settings: LocalizationConfig | None = None,
) -> dict:
    """Drive the twin robot ``errors`` from site ``start`` to site ``to`` with the localizer
    ``method`` (its particles from ``seed``; its settings ``settings.amcl`` / ``enhanced`` /
    ``hector`` and the initial covariance ``settings.initial_cov``, None: the defaults; its
    ``method`` is not used) on the twin's map, its reflectors replaced by those of
    ``reflector_map`` when given; record the drive to the bag ``record`` (FILE.mcap or a
    rosbag2 folder) when given. Returns the summary (``reached``; ``reason`` when not)."""
    st = settings or LocalizationConfig(method=method)
    bag = None
    with SimWorld(errors=errors, site=start) as world, ExitStack() as stack:
        goal = world.scene.site(to).pose2d
        grid = twin_map(world)
        if reflector_map is not None:
            grid = replace_reflectors(grid, reflector_map)
        rng = np.random.default_rng(seed)
        loc = twin_localizer(
            world, method, rng, grid=grid, amcl=st.amcl, enhanced=st.enhanced, hector=st.hector
        )
        robot = world
        if record is not None:  # the same run, observed (mmpa.backends.bag.Recorder)
            bag = stack.enter_context(BagWriter(record, overwrite=True))
            # /joint_states and the arm's /tf every 20 ms of sim time, as a robot's
            # joint_state_broadcaster publishes them
            recorder = stack.enter_context(Recorder(bag, world, joint_rate_hz=ARM_RATE_HZ))
            robot = recorder.world()
            recorder.write_map(grid)
            loc = recorder.localizer(loc)
        # the operator's rough pose
        loc.initialize(rough_initial_pose(world), initial_covariance(st))
        cm = CostMap(twin_nav_map(world))
        res = navigate(
            robot,
            loc,
            grid,
            goal,
            NavigateConfig(timeout=timeout),
            costmap=cm,
            truth=world.truth.base_pose2d,
        )
    summary = _summary(res, start, to, method, errors.profile)
    if reflector_map is not None:
        summary["reflector_map"] = str(reflector_map)
    if bag is not None:
        summary["bag"] = str(record)
        summary["bag_messages"] = sum(bag.counts.values())
    return summary


def site_or_pose(text: str) -> Array:
    """A goal or start: a site of the twin's scene (its park pose) or ``"x,y,theta"`` (m, m,
    rad in ``map``)."""
    parts = text.split(",")
    if len(parts) == 3:
        try:
            pose = np.array([float(p) for p in parts])
        except ValueError:
            pose = np.full(3, np.nan)
        if not np.all(np.isfinite(pose)):
            raise InvalidInputError(f"a pose is x,y,theta (finite numbers), got {text!r}")
        return pose
    try:
        return load_scene().site(text).pose2d
    except UnknownNameError as e:
        raise InvalidInputError(f"{e}; or give a pose x,y,theta (m, m, rad in map)") from None


@dataclass
class RobotOnMap:
    """A hardware robot on its map: the map it serves (reflectors from ``reflectors``:
    ``/reflectors``, a reflector map file or ``none``), the localizer tracking it and its
    name (``robot``: the robot's own running localizer)."""

    grid: OccupancyGrid
    reflectors: str
    localizer: Localizer
    method: str


def robot_on_map(
    robot: MobileManipulator,
    robot_file: Path | None,
    start: str | None,
    settings: LocalizationConfig | None = None,
    seed: int = 0,
    reflector_map: Path | None = None,
) -> RobotOnMap:
    """The map ``robot`` serves (its reflectors replaced by ``reflector_map``'s when given)
    and a localizer on it: the robot's own (``backend.ros2.topics.pose``) when it runs one,
    else mmpa's of ``settings`` (default: the robot file's localization section; particles
    from ``seed``) started at ``start`` (a site or ``x,y,theta``: where it stands, roughly;
    a :class:`ConfigError` when None)."""
    st = settings or load_localization_config(LocalizationConfig, robot_file)
    served = getattr(robot, "occupancy_grid", None)
    if served is None:
        raise ConfigError("this robot serves no map: localizing it needs one (/map)")
    grid, refl_src = served()
    if reflector_map is not None:
        grid, refl_src = replace_reflectors(grid, reflector_map), str(reflector_map)
    source = getattr(robot, "pose", None)
    if source is not None:
        require(robot, "odometry", mission="reading the robot's localizer")
        return RobotOnMap(grid, refl_src, RobotLocalizer(source), "robot")
    require(robot, "odometry", "lidar", mission="localization")
    if start is None:
        raise ConfigError(
            "localizing this robot needs where it stands, roughly: --from SITE or x,y,theta "
            "(m, m, rad in map), or a running localizer (backend.ros2.topics.pose)"
        )
    mount = T_to_se2(robot.description.lidar.T_base_link_laser)
    loc = build_localizer(st, grid, mount, np.random.default_rng(seed))
    loc.initialize(site_or_pose(start), initial_covariance(st))
    return RobotOnMap(grid, refl_src, loc, st.method)


def localize_robot(robot: MobileManipulator, on: RobotOnMap, scans: int = 5) -> Array:
    """Where ``robot`` stands: ``on``'s localizer after ``scans`` scans standing still
    (:func:`~mmpa.missions.navigate.localize_standing`), ``[x, y, theta]`` in ``map``."""
    return localize_standing(robot, on.localizer, scans)  # type: ignore[arg-type]


def drive_robot(
    robot: MobileManipulator, on: RobotOnMap, goal: Array, timeout: float = 120.0
) -> tuple[NavigationResult, bool]:
    """Drive ``robot``'s base to ``goal`` ``[x, y, theta]`` on ``on``'s estimate (the
    navigate mission); the result and whether the robot published its truth (the twin
    node's ``/truth/base_pose``: the parking error judged by it)."""
    require(robot, "base", "odometry", mission="navigate")
    truth_of = getattr(robot, "truth", None)
    truth = truth_of() if truth_of is not None else None
    cfg = NavigateConfig(timeout=timeout)
    return navigate(robot, on.localizer, on.grid, goal, cfg, truth=truth), truth is not None


def navigate_robot(
    robot_file: Path,
    start: str,
    to: str,
    settings: LocalizationConfig | None = None,
    seed: int = 0,
    timeout: float = 120.0,
    reflector_map: Path | None = None,
) -> dict:
    """Drive the robot of ``robot_file`` (a hardware backend) to ``to`` (a site of the scene
    or ``x,y,theta``) on the localization estimate (module docstring): mmpa's localizer of
    ``settings`` (particles from ``seed``) starts at ``start`` (where the robot stands,
    roughly); the map's reflectors replaced by ``reflector_map``'s when given. ``timeout``:
    s of the robot's clock. Returns the summary (truth-based errors None without a truth)."""
    st = settings or LocalizationConfig()
    goal = site_or_pose(to)
    devices = ("clock", "odometry", "base", "lidar")
    with open_robot(robot_file, devices) as robot:
        require(robot, "base", "odometry", "lidar", mission="navigate")
        on = robot_on_map(robot, robot_file, start, st, seed, reflector_map)
        res, has_truth = drive_robot(robot, on, goal, timeout)
    summary = _summary(res, start, to, on.method, robot_backend(robot_file).kind)
    summary["reflectors"] = on.reflectors
    summary["truth"] = "/truth/base_pose" if has_truth else "none"
    return summary


def export_twin_map(errors: ErrorModelConfig, out: Path, resolution: float = 0.05) -> tuple:
    """Write the occupancy map of the twin robot ``errors`` (warped as mapped, per the error
    model) with its surveyed reflector landmarks to ``out`` (map_server YAML + PGM). Returns
    ``(path, grid)``."""
    with SimWorld(errors=errors) as world:
        grid = twin_map(world, resolution)
    return save_map(grid, out), grid
