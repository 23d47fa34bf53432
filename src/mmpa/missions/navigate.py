"""Drive a mobile robot to a goal on the localization estimate, over the robot protocols.

The robot is any object with a ``base`` (:class:`~mmpa.robot.interfaces.Base`), ``odometry``
and ``lidar`` sources, a clock ``time`` and ``step(duration)`` (the twin advances its physics;
a real robot waits): :class:`MobileRobot`. The twin's maps come from
:mod:`mmpa.backends.twin.twin_maps`.

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
from typing import Any, Protocol

import numpy as np
from pydantic import BaseModel, ConfigDict, Field

from mmpa.core.errors import UnreachableError
from mmpa.core.geometry import Array, wrap_angle
from mmpa.localization.localizer import Localizer
from mmpa.maps.occupancy import OccupancyGrid
from mmpa.navigation.follower import FollowerConfig, PathFollower, within_tolerance
from mmpa.navigation.planner import CostMap, PlannerConfig, plan_path
from mmpa.robot.interfaces import Base, Lidar

__all__ = [
    "MobileRobot",
    "NavigateConfig",
    "NavigationResult",
    "localize_standing",
    "navigate",
    "staged_path",
]


class MobileRobot(Protocol):
    """What navigation drives: a base, odometry and lidar sources and a clock (``step``
    advances it by ``duration`` s: the twin's physics, a real robot's wait)."""

    @property
    def base(self) -> Base: ...

    @property
    def odometry(self) -> Any: ...  # .odometry() -> Odometry

    @property
    def lidar(self) -> Lidar: ...

    @property
    def time(self) -> float: ...

    def step(self, duration: float) -> None: ...


def localize_standing(
    world: MobileRobot, localizer: Localizer, scans: int = 5, scan_rate: float = 10.0
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

    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)  # NaN / inf refused

    control_rate: float = Field(20.0, gt=0)
    scan_rate: float = Field(10.0, gt=0)
    timeout: float = Field(120.0, gt=0)  # s of simulated time
    initial_scans: int = Field(5, ge=0)  # stationary scans before planning
    settle_scans: int = Field(10, ge=0)  # stationary scans after stopping, before re-checking
    max_corrections: int = Field(3, ge=0)
    # the settled estimate is accepted within settle_scale x the final approach's tolerances
    # (hysteresis over the estimate's jitter while standing: about +-1 mm in the twin)
    settle_scale: float = Field(1.5, ge=1.0)
    # the plan ends with a straight stretch of this length along the goal heading (from a
    # staging point behind the goal, else in front of it, where free): the base arrives on
    # the goal's heading line, as a docking approach does; 0: plan to the goal directly
    staging_distance: float = Field(0.5, ge=0)
    planner: PlannerConfig = PlannerConfig()
    follower: FollowerConfig = FollowerConfig()


@dataclass
class NavigationResult:
    """Outcome; errors are truth vs goal (parking) and estimate vs truth (localization).
    ``reason`` says why a drive did not reach (empty when it did), ``corrections`` counts the
    re-approaches after a settle check, ``settled_estimate`` is the estimate the last settle
    check judged (NaN if none ran)."""

    reached: bool
    goal: Array
    final_truth: Array
    final_estimate: Array
    sim_time: float
    path: Array
    trace: dict[str, Array] = field(default_factory=dict)
    reason: str = ""
    corrections: int = 0
    settled_estimate: Array = field(default_factory=lambda: np.full(3, np.nan))

    @property
    def settle_error_xy(self) -> float:
        """Distance (m) of the settled estimate from the goal: what the robot believes."""
        return float(np.hypot(*(self.settled_estimate[:2] - self.goal[:2])))

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


def _segment_free(cm: CostMap, p0: Array, p1: Array) -> bool:
    """Whether the straight segment ``p0 -> p1`` crosses no lethal or inscribed cell (the
    goal's own cell may be inscribed: a robot parked at a desk)."""
    g = cm.grid
    n = max(2, int(np.ceil(np.linalg.norm(p1 - p0) / (0.5 * g.resolution))) + 1)
    pts = np.linspace(p0, p1, n)[:-1]
    c, r = g.world_to_cell(pts)
    c, r = np.asarray(c, int), np.asarray(r, int)
    if np.any((c < 0) | (c >= g.width) | (r < 0) | (r >= g.height)):
        return False
    cost = cm.cost[r, c]
    near_goal = np.linalg.norm(pts - p1, axis=1) <= cm.cfg.endpoint_clearance
    return bool(np.all((cost < 253.0) | (near_goal & (cost < 254.0))))


def staged_path(
    cm: CostMap, start: Array, goal: Array, staging: float, cfg: PlannerConfig | None = None
) -> Array:
    """A plan (K, 2) from ``start`` to ``goal`` = ``[x, y, theta]`` whose last stretch runs
    ``staging`` m along the goal heading ``h``: through the staging point ``goal - staging h``
    (driving in forward), else ``goal + staging h`` (backing in), whichever is free with a
    free straight stretch to the goal; else (or when ``start`` is within ``2 staging`` of the
    goal: a short re-park) the plain plan to the goal."""
    goal = np.asarray(goal, float)
    if staging > 0 and np.hypot(*(np.asarray(start[:2], float) - goal[:2])) > 2 * staging:
        h = np.array([np.cos(goal[2]), np.sin(goal[2])])
        for side in (1.0, -1.0):
            st = goal[:2] - side * staging * h
            if not _segment_free(cm, st, goal[:2]):
                continue
            try:
                path = plan_path(cm, start, st, cfg)
            except UnreachableError:
                continue
            return np.vstack([path, goal[:2]])
    return plan_path(cm, start, goal[:2], cfg)


def _how_far(est: Array, goal: Array, cfg: NavigateConfig) -> str:
    """``": the estimate is X mm / Y deg from the goal (tolerance ...)"``: how far a drive
    that did not reach stopped, by the robot's own estimate, against the settle check's
    tolerance."""
    fin, k = cfg.follower.final, cfg.settle_scale
    e = est - goal
    return (
        f": the estimate is {1000 * np.hypot(e[0], e[1]):.1f} mm / "
        f"{np.rad2deg(abs(wrap_angle(e[2]))):.2f} deg from the goal (tolerance "
        f"{1000 * k * fin.pos_tol:.1f} mm / {np.rad2deg(k * fin.yaw_tol):.2f} deg)"
    )


def navigate(
    world: MobileRobot,
    localizer: Localizer,
    grid: OccupancyGrid,
    goal: Array,
    cfg: NavigateConfig | None = None,
    on_tick: Callable[[Any, float], None] | None = None,
    progress: Callable[[str, float], None] | None = None,
    costmap: CostMap | None = None,
    truth: Callable[[], Array] | None = None,
) -> NavigationResult:
    """Drive to ``goal`` = ``[x, y, theta]`` on the localization estimate (see module doc).

    The loop: scans at ``scan_rate`` into the localizer, a plan from the estimate, pure
    pursuit, final approach with position and heading tolerances, settle and re-check (up to
    ``max_corrections`` times); it steers only on ``localizer.pose_at(odometry)``.
    ``on_tick(world, t)`` runs every control tick (e.g. to move occluders); the localizer must
    already be initialized (rough initial pose). ``truth()`` (the twin's ground truth, given by
    the evaluation; None on a real robot) is read only for the evaluation trace and
    ``final_truth`` (NaN without a truth).
    """
    cfg = cfg or NavigateConfig()
    goal = np.asarray(goal, float).reshape(3)
    d = _Drive(world, localizer, cfg, on_tick, truth)
    est = d.stationary(cfg.initial_scans) if cfg.initial_scans else d.sense(force=True)
    cm = costmap or CostMap(grid, cfg.planner)
    path = staged_path(cm, est[:2], goal, cfg.staging_distance, cfg.planner)
    follower = PathFollower(path, goal, cfg.follower)
    total = float(np.sum(np.linalg.norm(np.diff(path, axis=0), axis=1))) or 1.0
    reached, reason, corrections, settled = _follow(d, follower, goal, total, progress)
    world.base.stop()
    world.step(0.2)
    final_est = localizer.pose_at(world.odometry.odometry().pose)
    if not reached:
        reason += _how_far(final_est, goal, cfg)
    return NavigationResult(
        reached=reached,
        goal=goal,
        final_truth=truth() if truth else d.no_truth,
        final_estimate=final_est,
        sim_time=world.time - d.t0,
        path=path,
        trace={k: np.asarray(v) for k, v in d.trace.items()},
        reason=reason,
        corrections=corrections,
        settled_estimate=settled,
    )


class _Drive:
    """A drive's clock, sensing and trace: scans into the localizer every ``scan_every``
    control ticks of ``dt`` s; the trace records time, truth (evaluation only), estimate,
    reflectors seen and the localizer's health verdict at every scan."""

    KEYS = ("t", "truth", "estimate", "reflectors", "ok", "explained")

    def __init__(
        self,
        world: MobileRobot,
        localizer: Localizer,
        cfg: NavigateConfig,
        on_tick: Callable[[Any, float], None] | None,
        truth: Callable[[], Array] | None,
    ) -> None:
        self.world, self.localizer, self.cfg = world, localizer, cfg
        self.on_tick, self.truth = on_tick, truth
        self.no_truth = np.full(3, np.nan)
        self.dt = 1.0 / cfg.control_rate
        self.scan_every = max(1, round(cfg.control_rate / cfg.scan_rate))
        self.t0 = world.time
        self.trace: dict[str, list[Any]] = {k: [] for k in self.KEYS}
        self.tick = 0

    def sense(self, force: bool = False) -> Array:
        """One scan into the localizer; the estimate at the current odometry."""
        world, localizer, trace = self.world, self.localizer, self.trace
        odom = world.odometry.odometry().pose
        scan = world.lidar.scan()
        pe = localizer.update(odom, scan, force=force)
        est = localizer.pose_at(odom)
        # the localizer's own verdict (mmpa.localization.health): ok and the explained share
        trace["ok"].append(bool(getattr(pe, "ok", True)))
        trace["explained"].append(float(getattr(getattr(pe, "health", None), "explained", np.nan)))
        trace["t"].append(world.time - self.t0)
        trace["truth"].append(self.truth() if self.truth else self.no_truth)  # evaluation only
        trace["estimate"].append(est)
        obs = getattr(localizer, "observer", None)
        trace["reflectors"].append(len(obs.last_detections) if obs is not None else -1)
        return est

    def advance(self) -> None:
        """One control tick of the clock (``on_tick`` first)."""
        if self.on_tick is not None:
            self.on_tick(self.world, self.world.time - self.t0)
        self.world.step(self.dt)
        self.tick += 1

    def stationary(self, n: int) -> Array:
        """Stop and take ``n`` scans standing; the last estimate."""
        self.world.base.stop()
        est = self.localizer.pose_at(self.world.odometry.odometry().pose)
        for _ in range(n):
            for _ in range(self.scan_every):
                self.advance()
            est = self.sense(force=False)
        return est


def _follow(
    d: _Drive,
    follower: PathFollower,
    goal: Array,
    total: float,
    progress: Callable[[str, float], None] | None,
) -> tuple[bool, str, int, Array]:
    """Follow the plan to ``goal`` on the estimate, settle and re-check (up to
    ``max_corrections`` times) until reached, the final approach's timeout or the drive's.
    Returns ``(reached, reason, corrections, settled estimate)``."""
    world, cfg = d.world, d.cfg
    reached = False
    corrections = 0
    settled = np.full(3, np.nan)
    reason = f"navigation timed out after {cfg.timeout:g} s"
    final_t0: float | None = None
    fin = cfg.follower.final
    while world.time - d.t0 < cfg.timeout:
        if d.tick % d.scan_every == 0:
            d.sense()
        est = d.localizer.pose_at(world.odometry.odometry().pose)
        v, w, done = follower.command(est)
        if follower.final_phase and final_t0 is None:
            final_t0 = world.time
        if final_t0 is not None and world.time - final_t0 > cfg.follower.final_timeout:
            reason = f"the final approach timed out after {cfg.follower.final_timeout:g} s"
            break
        if done:
            settled = est = d.stationary(cfg.settle_scans)
            ok = within_tolerance(est, goal, fin, cfg.settle_scale)
            if ok or corrections >= cfg.max_corrections:
                reached = bool(ok)  # corrections used up out of tolerance: not reached
                reason = "" if ok else f"not settled after {corrections} corrections"
                break
            corrections += 1
            follower.restart_final(est)
            continue
        world.base.set_velocity(v, w)
        d.advance()
        if progress is not None and d.tick % 20 == 0:
            progress("driving", 1.0 - float(np.hypot(*(goal[:2] - est[:2]))) / total)
    return reached, reason, corrections, settled
