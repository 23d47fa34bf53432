"""The twin's localizer set-up, written once: a localizer of any method on the twin's map and
its NOMINAL lidar mount (what the robot file would say), and the seed rule the twin
experiments share (the twin's robot instance follows ``--seed`` unless given)."""

from __future__ import annotations

from typing import Any

import numpy as np

from mmpa.backends.twin.twin_maps import laser_pose2d, twin_map
from mmpa.backends.twin.world import SimWorld
from mmpa.core.geometry import Array
from mmpa.localization.amcl import AMCLConfig
from mmpa.localization.config import EnhancedConfig
from mmpa.localization.hector import HectorConfig
from mmpa.localization.localizer import Localizer, make_localizer
from mmpa.maps.occupancy import OccupancyGrid

__all__ = ["errors_follow_seed", "twin_localizer"]


def twin_localizer(
    world: SimWorld,
    method: str,
    rng: np.random.Generator | None = None,
    *,
    grid: OccupancyGrid | None = None,
    mount: Array | None = None,
    amcl: AMCLConfig | None = None,
    enhanced: EnhancedConfig | None = None,
    hector: HectorConfig | None = None,
) -> Localizer:
    """:func:`~mmpa.localization.localizer.make_localizer` for the twin ``world``: on ``grid``
    (default :func:`~mmpa.backends.twin.twin_maps.twin_map` at 5 cm, reflectors included)
    with the lidar mount ``mount`` ``[x, y, yaw]`` in ``base_link`` (default the NOMINAL one,
    :func:`~mmpa.backends.twin.twin_maps.laser_pose2d`); ``rng`` draws its particles. Not
    initialized: the caller gives the initial pose (the operator's rough pose,
    :func:`~mmpa.backends.twin.operator.rough_initial_pose`, or an estimate)."""
    grid = twin_map(world) if grid is None else grid
    mount = laser_pose2d(world) if mount is None else mount
    return make_localizer(method, grid, mount, rng, amcl=amcl, enhanced=enhanced, hector=hector)


def errors_follow_seed(cfg: Any) -> Any:
    """Let ``cfg.errors.seed`` (the twin's robot instance) be ``cfg.seed`` unless it was given
    explicitly: ``--seed`` keeps picking the robot, as these experiments always did. ``cfg``:
    a pydantic model with ``seed`` and ``errors`` (an ``ErrorModelConfig``)."""
    if "seed" in cfg.errors.model_fields_set:
        return cfg
    given = "errors" in cfg.model_fields_set
    errors = cfg.errors.model_copy(update={"seed": cfg.seed})
    errors.__pydantic_fields_set__.discard("seed")  # derived, not given: a new --seed moves it
    cfg.errors = errors
    if not given:
        cfg.__pydantic_fields_set__.discard("errors")
    return cfg
