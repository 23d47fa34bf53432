"""Re-park: move the parked base by a small planar offset with the navigation stack, as a
mobile manipulator does when IPE says the arm cannot reach its taught path from where the
base stands (paper 000 §4.3, Site 2': repark and measure again).

The base first drives to a staging pose ``staging`` m behind the goal (to 3 cm / 0.05 rad),
then straight in to the goal (to 1 cm / 0.01 rad): a differential base that turns in place
next to a bench or on a bump stalls. Frames: ``motion`` = ``[dx, dy, dtheta]`` in
``base_link`` of the current estimate; poses ``[x, y, theta]`` in ``map`` (m, rad)."""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from mmpa.core.geometry import Array, se2_compose
from mmpa.localization.localizer import Localizer
from mmpa.maps.occupancy import OccupancyGrid
from mmpa.missions.navigate import MobileRobot, NavigateConfig, NavigationResult, navigate
from mmpa.navigation.planner import CostMap

__all__ = ["repark"]


def repark(
    robot: MobileRobot,
    localizer: Localizer,
    grid: OccupancyGrid,
    est0: Array,
    motion: Array,
    staging: float,
    costmap: CostMap | None = None,
    nav: NavigateConfig | None = None,
    truth: Callable[[], Array] | None = None,
) -> NavigationResult:
    """Drive the base from the estimate ``est0`` by ``motion`` on ``localizer`` (initialized
    here at ``est0``) through the staging pose (module docstring); stop the base. Returns the
    last leg's navigation result (its ``final_estimate`` is the new estimate). ``truth`` is
    read only for the evaluation trace (:func:`~mmpa.missions.navigate.navigate`)."""
    localizer.initialize(est0)
    goal = se2_compose(est0, np.asarray(motion, float))
    nav = nav or NavigateConfig()
    f = nav.follower
    legs = [
        (se2_compose(goal, np.array([-staging, 0.0, 0.0])), 0.03, 0.05),
        (goal, 0.01, 0.01),
    ]
    res = None
    for target, pos_tol, yaw_tol in legs:
        final = f.final.model_copy(update={"pos_tol": pos_tol, "yaw_tol": yaw_tol})
        cfg = nav.model_copy(update={"follower": f.model_copy(update={"final": final})})
        res = navigate(robot, localizer, grid, target, cfg, costmap=costmap, truth=truth)
    assert res is not None
    robot.base.stop()
    return res
