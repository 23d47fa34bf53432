"""One ``Localizer`` interface for every method compared in paper 001 (Table 2, Fig. 10).

- ``amcl``: :class:`~mmpa.localization.amcl.AMCL` (Nav2 AMCL);
- ``enhanced``: :class:`~mmpa.localization.enhanced.EnhancedAMCL` (Algorithm 1, ours);
- ``enhanced-paper``: Algorithm 1 with the coefficients exactly as printed;
- ``trilateration``: eq. 1-2 only (:class:`TrilaterationLocalizer`); it has no answer while
  fewer than three reflectors are identified and keeps its last fix;
- ``tamcl``: T-AMCL (:class:`TAMCL`): trilateration when available; when reflectors drop out,
  AMCL re-initialized at the last fix with its initial covariance;
- ``hector``: :class:`~mmpa.localization.hector.HectorMatcher` (Hector-style scan matching).

Use :func:`make_localizer` to build one from a map with reflector landmarks.
"""

from __future__ import annotations

from typing import Protocol, runtime_checkable

import numpy as np

from mmpa.core.errors import InvalidInputError, UnknownNameError
from mmpa.core.geometry import Array
from mmpa.localization.amcl import (
    AMCL,
    AMCLConfig,
    PoseEstimate,
    check_scan,
    compose_odom,
    finite_cov,
    finite_pose,
)
from mmpa.localization.enhanced import (
    EnhancedAMCL,
    EnhancedConfig,
    ObserverConfig,
    ReflectorFix,
    ReflectorObserver,
)
from mmpa.localization.health import HealthConfig
from mmpa.localization.hector import HectorConfig, HectorMatcher
from mmpa.localization.monitor import MonitoredLocalizer
from mmpa.maps.occupancy import OccupancyGrid
from mmpa.robot.interfaces import LaserScan

__all__ = ["METHODS", "TAMCL", "Localizer", "TrilaterationLocalizer", "make_localizer"]

METHODS = ("amcl", "enhanced", "enhanced-paper", "trilateration", "tamcl", "hector")


@runtime_checkable
class Localizer(Protocol):
    """Pose tracking from odometry and scans. Poses ``[x, y, theta]`` in ``map``."""

    name: str

    def initialize(self, pose: Array, cov: Array | None = None) -> None:
        """Rough initial pose (the operator's "2D pose estimate")."""
        ...

    def update(self, odom_pose: Array, scan: LaserScan, force: bool = False) -> PoseEstimate:
        """Process one scan taken at odometry pose ``odom_pose`` (``odom`` frame)."""
        ...

    def pose_at(self, odom_pose: Array) -> Array:
        """Current best pose: the last estimate moved by the odometry since."""
        ...


def _observer(
    grid: OccupancyGrid, laser_pose: Array, cfg: ObserverConfig | None
) -> ReflectorObserver:
    cfg = cfg or ObserverConfig()
    if grid.reflector_radius > 0:
        cfg = cfg.model_copy(
            update={"detection": cfg.detection.model_copy(update={"radius": grid.reflector_radius})}
        )
    if len(grid.reflectors) < 3:
        raise InvalidInputError(f"the map holds {len(grid.reflectors)} reflectors; need >= 3")
    return ReflectorObserver(grid.reflectors, laser_pose, cfg)


class TrilaterationLocalizer:
    """Eq. 1-2 alone. ``valid`` is False while no fix is available (the last fix is kept)."""

    name = "trilateration"

    def __init__(self, grid: OccupancyGrid, laser_pose: Array, cfg: ObserverConfig | None = None):
        self.observer = _observer(grid, laser_pose, cfg)
        self._pose: Array | None = None
        self._cov = np.eye(3)
        self.valid = False
        self.last_fix: ReflectorFix | None = None

    def initialize(self, pose: Array, cov: Array | None = None) -> None:
        self._pose = finite_pose(pose, "initial pose").copy()
        if cov is not None:  # unused (the next fix sets it), but checked like AMCL's
            finite_cov(cov, "initial covariance")
        self.valid = False

    def update(self, odom_pose: Array, scan: LaserScan, force: bool = False) -> PoseEstimate:
        finite_pose(odom_pose, "odometry pose")  # unused, but a NaN says the caller is broken
        fix = self.observer.observe(check_scan(scan))
        self.last_fix = fix
        self.valid = fix is not None
        if fix is not None:
            self._pose, self._cov = fix.pose.copy(), fix.trilateration.cov
        if self._pose is None:
            raise InvalidInputError("no reflector fix yet and no initial pose given")
        return PoseEstimate(self._pose.copy(), self._cov, 0, self.valid, self.name)

    def pose_at(self, odom_pose: Array) -> Array:
        finite_pose(odom_pose, "odometry pose")  # unused, but a NaN says the caller is broken
        if self._pose is None:
            raise InvalidInputError("no reflector fix yet and no initial pose given")
        return self._pose.copy()


class TAMCL:
    """T-AMCL: trilateration while >= 3 reflectors are identified, else AMCL re-initialized at
    the last trilateration fix (Nav2 initial covariance), which has to converge again."""

    name = "tamcl"

    def __init__(
        self,
        grid: OccupancyGrid,
        laser_pose: Array,
        amcl_cfg: AMCLConfig | None = None,
        observer_cfg: ObserverConfig | None = None,
        rng: np.random.Generator | None = None,
    ) -> None:
        self.observer = _observer(grid, laser_pose, observer_cfg)
        self.amcl = AMCL(grid, laser_pose, amcl_cfg, rng)
        self._pose: Array | None = None
        self._odom: Array | None = None
        self._cov = np.eye(3)
        self.mode = "init"

    def initialize(self, pose: Array, cov: Array | None = None) -> None:
        self._pose = finite_pose(pose, "initial pose").copy()
        self.amcl.set_initial_pose(self._pose, cov)
        self.mode = "amcl"

    def update(self, odom_pose: Array, scan: LaserScan, force: bool = False) -> PoseEstimate:
        odom_pose = finite_pose(odom_pose, "odometry pose")
        fix = self.observer.observe(check_scan(scan))
        if fix is not None:
            self._pose, self._cov, self._odom = fix.pose.copy(), fix.trilateration.cov, odom_pose
            self.mode = "trilateration"
            return PoseEstimate(self._pose.copy(), self._cov, 0, True, "trilateration")
        if self.mode == "trilateration":  # fix lost: re-initialize AMCL at the last fix
            assert self._pose is not None and self._odom is not None
            self.amcl.set_initial_pose(compose_odom(self._pose, self._odom, odom_pose))
            self.amcl._odom_prev = None
            self.mode = "amcl"
        est = self.amcl.update(odom_pose, scan, force)
        self._pose, self._cov, self._odom = est.pose.copy(), est.cov, None
        return PoseEstimate(est.pose, est.cov, est.n_particles, est.updated, "amcl")

    def pose_at(self, odom_pose: Array) -> Array:
        if self.mode == "amcl":
            return self.amcl.pose_at(odom_pose)
        if self._pose is None:
            raise InvalidInputError("initialize T-AMCL with a pose first")
        if self._odom is None:
            return self._pose.copy()
        return compose_odom(self._pose, self._odom, np.asarray(odom_pose, float))


def make_localizer(
    method: str,
    grid: OccupancyGrid,
    laser_pose: Array,
    rng: np.random.Generator | None = None,
    amcl: AMCLConfig | None = None,
    enhanced: EnhancedConfig | None = None,
    health: HealthConfig | None = None,
    monitor: bool = True,
    hector: HectorConfig | None = None,
) -> Localizer:
    """Build the localizer called ``method`` (one of :data:`METHODS`); with ``monitor`` (the
    default) wrapped in a :class:`~mmpa.localization.monitor.MonitoredLocalizer`, so that
    every estimate carries its health and says ``ok=False`` when lost (``health``: its
    thresholds). ``amcl`` / ``enhanced`` / ``hector``: the settings of those methods (None:
    their defaults; ``amcl`` is also the AMCL inside enhanced and tamcl)."""
    loc = _make_bare(method, grid, laser_pose, rng, amcl, enhanced, hector)
    return MonitoredLocalizer(loc, grid, laser_pose, health) if monitor else loc


def _make_bare(
    method: str,
    grid: OccupancyGrid,
    laser_pose: Array,
    rng: np.random.Generator | None,
    amcl: AMCLConfig | None,
    enhanced: EnhancedConfig | None,
    hector: HectorConfig | None = None,
) -> Localizer:
    laser_pose = finite_pose(laser_pose, "laser pose")
    if method == "amcl":
        return AMCL(grid, laser_pose, amcl, rng)
    if method == "enhanced":
        cfg = enhanced or EnhancedConfig()
        if amcl is not None:
            cfg = cfg.model_copy(update={"amcl": amcl})
        return EnhancedAMCL(grid, laser_pose, cfg, rng)
    if method == "enhanced-paper":
        cfg = EnhancedConfig.paper()
        if amcl is not None:
            cfg = cfg.model_copy(update={"amcl": amcl})
        return EnhancedAMCL(grid, laser_pose, cfg, rng)
    if method == "trilateration":
        return TrilaterationLocalizer(grid, laser_pose)
    if method == "tamcl":
        return TAMCL(grid, laser_pose, amcl, None, rng)
    if method == "hector":
        return HectorMatcher(grid, laser_pose, hector)
    raise UnknownNameError("localization method", method, list(METHODS))
