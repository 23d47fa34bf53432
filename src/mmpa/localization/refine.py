"""Scan-to-map refinement of AMCL (improvement, issue 34): a match of the filter's estimate
that draws part of the particles (``AMCLConfig.scan_refine``).

Between sparse scans (real buildings: 0.7-1 m and 10-20 deg apart) the motion model spreads
the cloud over decimetres while one scan pins the pose to centimetres, so hardly a particle
lands where the scan fits, and Nav2's AMCL loses the track. Here, per filter update:

1. the estimate of the PREDICTED cloud (its heaviest cluster's mean, only while that
   cluster's position SD is within ``refine_max_sd``: a tracking, not a global, cloud) is
   matched to the map by :class:`~mmpa.localization.hector.HectorMatcher` (correlative
   search, then damped Gauss-Newton on the distance field; HectorConfig's defaults), with its
   gates: score >= ``min_score``, within ``max_jump`` of the start, finite;
2. an accepted match ``m`` with covariance ``C`` gives the proposal ``q = N(m, inflate^2 C +
   diag(floor^2))`` (:func:`~mmpa.localization.proposal.defensive_mixture`): a share
   ``refine_fraction`` of the particles is drawn from ``q``, the rest resampled from the
   predicted cloud ``p``; every particle is weighted by the laser model times ``p(x) /
   (a p(x) + (1 - a) q(x))`` (deterministic mixture, ``p`` a Gaussian fit of the predicted
   cloud). The posterior is the laser model's: the match only puts particles where they
   count, and a wrong match's particles, far in ``p``'s tail, weigh nothing.

Units: m, rad; poses ``[x, y, theta]`` in ``map``; the lidar mount ``[x, y, yaw]`` in
``base_link``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from mmpa.core.geometry import Array
from mmpa.localization.hector import HectorConfig, HectorMatcher
from mmpa.maps.occupancy import OccupancyGrid
from mmpa.robot.interfaces import LaserScan

__all__ = ["Refinement", "ScanRefiner", "scan_endpoints"]

MIN_BEAMS = 10  # fewer valid beams: no match (Hector's own limit)


def scan_endpoints(scan: LaserScan, laser_pose: Array, max_beams: int) -> Array:
    """(k, 2) endpoints in ``base_link`` of up to ``max_beams`` valid beams picked evenly:
    ``t_l + r [cos(a + theta_l), sin(a + theta_l)]``."""
    idx = np.flatnonzero(scan.valid())
    if idx.size > max_beams:
        idx = idx[np.linspace(0, idx.size - 1, max_beams).astype(int)]
    a, r = scan.angles[idx], np.asarray(scan.ranges, float)[idx]
    lx, ly, lth = laser_pose
    return np.column_stack([r * np.cos(a + lth) + lx, r * np.sin(a + lth) + ly])


@dataclass(frozen=True)
class Refinement:
    """A match of the estimate ``start``: the pose ``[x, y, theta]``, its covariance (3, 3),
    the score (0..1), and ``reason`` ('' when accepted, else why it is refused)."""

    start: Array
    pose: Array
    cov: Array
    score: float
    reason: str

    @property
    def ok(self) -> bool:
        return not self.reason


class ScanRefiner:
    """The match of step 1 (module docstring); the matcher's fields are built on first use."""

    def __init__(
        self, grid: OccupancyGrid, laser_pose: Array, cfg: HectorConfig | None = None
    ) -> None:
        self.grid = grid
        self.laser_pose = np.asarray(laser_pose, float).reshape(3)
        self.cfg = cfg or HectorConfig()
        self._matcher: HectorMatcher | None = None

    @property
    def matcher(self) -> HectorMatcher:
        if self._matcher is None:
            self._matcher = HectorMatcher(self.grid, self.laser_pose, self.cfg)
        return self._matcher

    def match(self, start: Array, scan: LaserScan) -> Refinement:
        """The match of ``scan`` from the pose ``start``, judged by the matcher's gates."""
        start = np.asarray(start, float)
        pts = scan_endpoints(scan, self.laser_pose, self.cfg.max_beams)
        if len(pts) < MIN_BEAMS:
            nan = np.full(3, np.nan)
            return Refinement(start, nan, np.full((3, 3), np.nan), float("nan"),
                              f"{len(pts)} valid beams (< {MIN_BEAMS})")  # fmt: skip
        m = self.matcher
        pose, cov = m.match(start, pts)
        score = m.score(pose, pts) if np.all(np.isfinite(pose)) else float("nan")
        c = self.cfg
        reason = ""
        if not (np.all(np.isfinite(pose)) and np.all(np.isfinite(cov))):
            reason = "match not finite"
        elif not score >= c.min_score:
            reason = f"match score {score:.3f} < {c.min_score}"
        elif float(np.hypot(*(pose[:2] - start[:2]))) > c.max_jump:
            reason = f"match moved more than {c.max_jump} m"
        return Refinement(start, pose, cov, float(score), reason)
