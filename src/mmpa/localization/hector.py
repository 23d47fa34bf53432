"""Scan-to-map matching in the style of Hector SLAM (Kohlbrecher et al. 2011), on a known map.

Hector aligns each scan with the occupancy map by Gauss-Newton on
``sum_i (1 - M(S_i(xi)))^2``, ``M`` the bilinearly interpolated map value and ``S_i(xi)`` the
scan endpoint ``i`` moved by the pose ``xi = (x, y, theta)``, coarse to fine over a pyramid of
maps (3 levels: the map at 1x, 2x and 4x cell size). Hector SLAM also updates the map; the
paper's baseline localizes in an already built map, so the map stays fixed here. The start of
each match is the previous match moved by the odometry increment (the odometry prediction).
:meth:`HectorConfig.paper` is that algorithm as published (undamped steps, blurred occupancy
pyramid); the defaults are improvements (:mod:`mmpa.localization.hector_match` has the math):

- the residual is the distance to the nearest occupied cell of the FINE map at every level,
  under a Geman-McClure loss whose scale halves from level to level (the coarse levels of the
  published pyramid move walls by up to half a coarse cell, and the blurred binary map's
  peaks depend on how thick a wall is: both pull a match off a correct start);
- damped Levenberg-Marquardt steps, each taken only when it lowers the cost (on the finest
  level: only when it raises the score), with convergence tests (undamped Gauss-Newton
  overshoots and oscillates on a real map while its score falls);
- a correlative search around the odometry prediction before the fit (real odometry between
  sparse scans is off by up to 0.45 m / 30 deg, beyond any gradient fit's reach).

Refusals (improvement): a fit always returns a pose, even for a scan that fits nothing. The
match's score is 0..1 (1 with every endpoint on a wall, ``hector_match``); below
``min_score``, farther than ``max_jump`` from the odometry prediction, not finite, or from
fewer than 10 valid beams, the match is refused: the estimate stays on odometry, the result
says ``ok=False`` with the reason, ``refusals`` counts them and ``last_refusal`` holds the last
reason ('' after an accepted match). Limits: a scan that fits the map somewhere near is not
caught by one scan's numbers. Measurements behind the gates and the defaults:
``docs/localization.md``.

Units: m, rad; poses ``[x, y, theta]`` in ``map``, the lidar mount in ``base_link``.
"""

from __future__ import annotations

from typing import Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field

from mmpa.core.errors import InvalidInputError
from mmpa.core.geometry import Array
from mmpa.localization.hector_match import (
    DistanceLevels,
    Fit,
    OccupancyLevels,
    correlative_search,
    gauss_newton,
    levenberg_marquardt,
    move,
)
from mmpa.localization.motion import compose_odom
from mmpa.localization.pose import PoseEstimate, check_scan, finite_cov, finite_pose
from mmpa.maps.occupancy import OccupancyGrid
from mmpa.robot.interfaces import LaserScan

__all__ = ["HectorConfig", "HectorMatcher"]


class HectorConfig(BaseModel):
    """Hector's settings; :meth:`paper` for the published algorithm. Units: m, rad."""

    model_config = ConfigDict(extra="forbid")

    # "distance": the fine map's distance field at every level (improvement); "occupancy":
    # the published blurred occupancy pyramid
    field: Literal["distance", "occupancy"] = "distance"
    levels: int = Field(3, ge=1, le=5)  # pyramid levels / loss scales (x2 per level)
    iterations: int = Field(10, ge=1)  # steps per level
    max_beams: int = Field(360, ge=10)
    blur_cells: float = Field(1.0, ge=0)  # occupancy field: Gaussian blur (cells)
    sigma_cells: float = Field(1.0, gt=0)  # distance field: finest loss scale (cells)
    # "lm": damped steps taken only when they lower the cost; "gauss_newton": as published
    step: Literal["lm", "gauss_newton"] = "lm"
    tol_xy: float = Field(1e-4, gt=0)  # lm: a smaller step ends a level
    tol_theta: float = Field(1e-4, gt=0)
    # correlative search around the odometry prediction (0 and 0: none): half-widths, step
    search_xy: float = Field(0.3, ge=0)
    search_theta: float = Field(0.35, ge=0)
    search_step: float = Field(0.1, gt=0)
    search_prior: float = Field(0.05, ge=0)  # score penalty at the window's edge
    # score (0..1) below which a match fits nothing (docs/localization.md)
    min_score: float = Field(0.3, ge=0, le=1)
    # m: a match this far from the odometry prediction is refused
    max_jump: float = Field(1.0, gt=0)

    @classmethod
    def paper(cls) -> HectorConfig:
        """Hector as published: occupancy pyramid of 3 levels blurred by one cell, 8
        undamped Gauss-Newton steps per level, no search; the former gates (score 0.12)."""
        return cls(
            field="occupancy",
            levels=3,
            iterations=8,
            blur_cells=1.0,
            step="gauss_newton",
            search_xy=0.0,
            search_theta=0.0,
            min_score=0.12,
        )


class HectorMatcher:
    """Hector-style scan matcher behind the Localizer interface (module docstring)."""

    name = "hector"

    def __init__(
        self, grid: OccupancyGrid, laser_pose: Array, cfg: HectorConfig | None = None
    ) -> None:
        self.cfg = c = cfg or HectorConfig()
        self.laser_pose = np.asarray(laser_pose, float).reshape(3)
        occ = grid.occupied
        res = float(grid.resolution)
        origin = (float(grid.origin[0]), float(grid.origin[1]))
        self._res, self._origin = res, origin
        self.field: OccupancyLevels | DistanceLevels
        if c.field == "occupancy":
            self.field = OccupancyLevels(occ, res, origin, c.levels, c.blur_cells)
        else:
            self.field = DistanceLevels(occ, res, origin, c.levels, c.sigma_cells * res)
        self._table: Array | None = None
        if c.search_xy > 0 or c.search_theta > 0:
            d = grid.distance_field(max(4 * c.search_step, 2 * res))
            self._table = np.exp(-0.5 * (d / c.search_step) ** 2)
        self._pose: Array | None = None
        self._odom: Array | None = None
        self._cov = np.diag([0.01, 0.01, 0.01])
        self.last_score = float("nan")  # score of the last match (see min_score)
        self.last_fit: Fit | None = None
        self.refusals = 0  # refused matches so far
        self.last_refusal = ""  # why the last match was refused ('' if accepted)

    @property
    def failures(self) -> int:
        """The former name of :attr:`refusals`."""
        return self.refusals

    def initialize(self, pose: Array, cov: Array | None = None) -> None:
        self._pose = finite_pose(pose, "initial pose").copy()
        if cov is not None:  # unused (a scan match sets it), but checked like AMCL's
            finite_cov(cov, "initial covariance")
        self._odom = None

    def pose_at(self, odom_pose: Array) -> Array:
        odom_pose = finite_pose(odom_pose, "odometry pose")
        if self._pose is None:
            raise InvalidInputError("initialize the matcher with a pose first")
        if self._odom is None:
            return self._pose.copy()
        return compose_odom(self._pose, self._odom, odom_pose)

    def _endpoints_base(self, scan: LaserScan) -> Array:
        """(k, 2) endpoints of up to ``max_beams`` valid beams (evenly picked) in
        ``base_link``: ``t_l + r [cos(a + theta_l), sin(a + theta_l)]``."""
        m = scan.valid()
        idx = np.flatnonzero(m)
        if idx.size > self.cfg.max_beams:
            idx = idx[np.linspace(0, idx.size - 1, self.cfg.max_beams).astype(int)]
        a, r = scan.angles[idx], scan.ranges[idx]
        lx, ly, lth = self.laser_pose
        px, py = r * np.cos(a + lth) + lx, r * np.sin(a + lth) + ly
        return np.column_stack([px, py])

    def fit(self, guess: Array, pts: Array) -> Fit:
        """Search (if set) and fit from ``guess`` (module docstring) for the endpoints
        ``pts`` (k, 2) in ``base_link``."""
        c = self.cfg
        start = np.asarray(guess, float)
        if self._table is not None:
            start = correlative_search(
                self._table,
                self._res,
                self._origin,
                start,
                pts,
                c.search_xy,
                c.search_theta,
                c.search_step,
                c.search_prior,
            )
        if c.step == "gauss_newton":
            return gauss_newton(self.field, start, pts, c.iterations)
        return levenberg_marquardt(self.field, start, pts, c.iterations, c.tol_xy, c.tol_theta)

    def match(self, guess: Array, pts: Array) -> tuple[Array, Array]:
        """The fitted pose and its covariance (:meth:`_covariance`) from ``guess``."""
        f = self.fit(guess, pts)
        return f.pose, self._covariance(f)

    def _covariance(self, f: Fit) -> Array:
        """``H^-1`` as published (occupancy field: dimensionless residuals); on the distance
        field ``s^2 H^-1``, ``s^2`` the weighted residual variance (m^2)."""
        try:
            Hi = np.linalg.inv(f.H)
        except np.linalg.LinAlgError:
            return np.full((3, 3), np.nan)
        return Hi if self.cfg.field == "occupancy" else max(f.s2, 1e-8) * Hi

    def score(self, pose: Array, pts: Array) -> float:
        """The score (0..1, ``hector_match``) of the endpoints ``pts`` (k, 2) (base frame)
        moved by ``pose``: near 1 when the scan lies on the walls."""
        return self.field.score(move(np.asarray(pose, float), pts))

    def _judge(self, guess: Array, pose: Array, cov: Array) -> str:
        """Why the match ``pose`` (from the prediction ``guess``) is refused; '' if not."""
        c = self.cfg
        if not (np.all(np.isfinite(pose)) and np.all(np.isfinite(cov))):
            return "scan match diverged (NaN)"
        if self.last_score < c.min_score:
            return f"match score {self.last_score:.3f} < min_score {c.min_score}"
        jump = float(np.hypot(*(pose[:2] - guess[:2])))
        if jump > c.max_jump:
            return f"match moved {jump:.3f} m from odometry (max_jump {c.max_jump})"
        return ""

    def update(self, odom_pose: Array, scan: LaserScan, force: bool = False) -> PoseEstimate:
        odom_pose = finite_pose(odom_pose, "odometry pose")
        guess = self.pose_at(odom_pose)
        pts = self._endpoints_base(check_scan(scan))
        if len(pts) >= 10:
            self.last_fit = f = self.fit(guess, pts)
            pose, cov = f.pose, self._covariance(f)
            self.last_score = f.score
            reason = self._judge(guess, pose, cov)
        else:
            self.last_fit, self.last_score = None, float("nan")
            reason = f"{len(pts)} valid beams (< 10): no match"
        if reason:
            self.refusals += 1
            self._pose = guess
        else:
            self._pose, self._cov = pose, cov
        self.last_refusal = reason
        self._odom = odom_pose.copy()
        return PoseEstimate(self._pose.copy(), self._cov, 0, True, self.name, not reason, reason)

    def estimate(self) -> PoseEstimate:
        if self._pose is None:
            raise InvalidInputError("initialize the matcher with a pose first")
        return PoseEstimate(self._pose.copy(), self._cov, 0, False, self.name)
