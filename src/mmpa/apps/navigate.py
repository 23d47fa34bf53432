"""``mmpa navigate`` and ``mmpa map export`` on the twin: drive from a site to another on the
localizer's estimate (the operator's rough pose to start), optionally recorded to a ROS 2 bag;
write the twin's occupancy map. The summary holds the parking error (truth vs goal), the
localization error (estimate vs truth) and the localizer's health over the drive."""

from __future__ import annotations

from contextlib import ExitStack
from pathlib import Path

import numpy as np

from mmpa.backends.bag import BagWriter, Recorder
from mmpa.backends.bag.record import ARM_RATE_HZ
from mmpa.backends.twin.error_model import ErrorModelConfig
from mmpa.backends.twin.operator import rough_initial_pose
from mmpa.backends.twin.twin_maps import twin_map, twin_nav_map
from mmpa.backends.twin.world import SimWorld
from mmpa.core.config import load_config
from mmpa.harness.twin_localization import twin_localizer
from mmpa.localization.settings import LocalizationConfig, initial_covariance
from mmpa.maps.map_server import replace_reflectors, save_map
from mmpa.missions.navigate import NavigateConfig, NavigationResult, navigate
from mmpa.navigation.planner import CostMap

__all__ = ["export_twin_map", "health_summary", "navigate_twin", "twin_errors"]


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


def _summary(res: NavigationResult, start: str, to: str, method: str, profile: str) -> dict:
    e = res.localization_error
    summary = {
        "from": start,
        "to": to,
        "method": method,
        "profile": profile,
        "reached": res.reached,
        "corrections": res.corrections,
        "sim_seconds": round(res.sim_time, 2),
        "parking_error_xy_mm": round(1000 * res.parking_error_xy, 2),
        "parking_error_yaw_deg": round(float(np.rad2deg(res.parking_error_yaw)), 3),
        "localization_error_xy_mm": round(1000 * float(np.hypot(e[0], e[1])), 2),
        "localization_error_yaw_deg": round(float(np.rad2deg(abs(e[2]))), 3),
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


def export_twin_map(errors: ErrorModelConfig, out: Path, resolution: float = 0.05) -> tuple:
    """Write the occupancy map of the twin robot ``errors`` (warped as mapped, per the error
    model) with its surveyed reflector landmarks to ``out`` (map_server YAML + PGM). Returns
    ``(path, grid)``."""
    with SimWorld(errors=errors) as world:
        grid = twin_map(world, resolution)
    return save_map(grid, out), grid
