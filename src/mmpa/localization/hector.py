"""Scan-to-map matching in the style of Hector SLAM (Kohlbrecher et al. 2011), on a known map.

Hector aligns each scan with the occupancy map by Gauss-Newton on
``sum_i (1 - M(S_i(xi)))^2``, ``M`` the bilinearly interpolated map value and ``S_i(xi)`` the
scan endpoint ``i`` moved by the pose ``xi = (x, y, theta)``, coarse to fine over a pyramid of
maps (here 3 levels: the map at 1x, 2x and 4x cell size). Hector SLAM also updates the map; the
paper's baseline localizes in an already built map, so the map stays fixed here. The initial
guess is the previous match moved by the odometry increment.

Map values are a blurred occupancy (Gaussian, one cell) so that the gradient reaches a little
beyond the walls, as Hector's interpolation of log-odds does.

Failure signal (improvement): Gauss-Newton always returns a pose, even for a scan that fits
nothing. The match's score is the mean map value at the matched endpoints on the finest level
(1 on the walls, 0 in free space); below ``min_score``, or farther than ``max_jump`` from the
odometry guess, the match is rejected: the estimate stays on odometry and the result says
``ok=False`` with the reason (``last_score``; ``failures`` counts them). Limits: a scan that
fits the map somewhere near is not caught by one scan's numbers. Measurements behind the
gates: ``docs/localization.md``.

Units: m, rad; poses ``[x, y, theta]`` in ``map``, the lidar mount in ``base_link``.
"""

from __future__ import annotations

import numpy as np
from pydantic import BaseModel, ConfigDict, Field
from scipy import ndimage

from mmpa.core.errors import InvalidInputError
from mmpa.core.geometry import Array
from mmpa.localization.amcl import (
    PoseEstimate,
    _wrap,
    check_scan,
    compose_odom,
    finite_cov,
    finite_pose,
)
from mmpa.maps.occupancy import OccupancyGrid
from mmpa.robot.interfaces import LaserScan

__all__ = ["HectorConfig", "HectorMatcher"]


class HectorConfig(BaseModel):
    model_config = ConfigDict(extra="forbid")

    levels: int = Field(3, ge=1, le=5)
    iterations: int = Field(8, ge=1)  # Gauss-Newton steps per level
    max_beams: int = Field(360, ge=10)
    blur_cells: float = Field(1.0, ge=0)
    # mean map value at the matched endpoints (1 on the walls, 0 in free space): below this a
    # match fits nothing
    min_score: float = Field(0.12, ge=0, le=1)
    # m: a match this far from the odometry guess is rejected
    max_jump: float = Field(1.0, gt=0)


class _Level:
    def __init__(self, occ: np.ndarray, res: float, origin: tuple[float, float], blur: float):
        m = occ.astype(float)
        if blur > 0:
            m = ndimage.gaussian_filter(m, blur)
            m = m / max(float(m.max()), 1e-9)
        self.m = m
        self.res = res
        self.origin = origin

    def value_grad(self, pts: Array) -> tuple[Array, Array]:
        """Bilinear map value (k,) and gradient (k, 2) (per m) at points (k, 2)."""
        gx = (pts[:, 0] - self.origin[0]) / self.res - 0.5
        gy = (pts[:, 1] - self.origin[1]) / self.res - 0.5
        h, w = self.m.shape
        x0 = np.clip(np.floor(gx).astype(int), 0, w - 2)
        y0 = np.clip(np.floor(gy).astype(int), 0, h - 2)
        fx = np.clip(gx - x0, 0, 1)
        fy = np.clip(gy - y0, 0, 1)
        m00 = self.m[y0, x0]
        m10 = self.m[y0, x0 + 1]
        m01 = self.m[y0 + 1, x0]
        m11 = self.m[y0 + 1, x0 + 1]
        val = fy * (fx * m11 + (1 - fx) * m01) + (1 - fy) * (fx * m10 + (1 - fx) * m00)
        dx = (fy * (m11 - m01) + (1 - fy) * (m10 - m00)) / self.res
        dy = (fx * (m11 - m10) + (1 - fx) * (m01 - m00)) / self.res
        return val, np.column_stack([dx, dy])


class HectorMatcher:
    """Hector-style scan matcher behind the Localizer interface."""

    name = "hector"

    def __init__(
        self, grid: OccupancyGrid, laser_pose: Array, cfg: HectorConfig | None = None
    ) -> None:
        self.cfg = cfg or HectorConfig()
        self.laser_pose = np.asarray(laser_pose, float).reshape(3)
        occ = grid.occupied
        self.levels: list[_Level] = []
        for k in range(self.cfg.levels):
            f = 2**k
            h, w = occ.shape[0] // f, occ.shape[1] // f
            o = occ[: h * f, : w * f].reshape(h, f, w, f).any(axis=(1, 3))
            self.levels.append(
                _Level(o, grid.resolution * f, grid.origin[:2], self.cfg.blur_cells)  # type: ignore[arg-type]
            )
        self._pose: Array | None = None
        self._odom: Array | None = None
        self._cov = np.diag([0.01, 0.01, 0.01])
        self.last_score = float("nan")  # score of the last match (see min_score)
        self.failures = 0  # rejected matches so far

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
        m = scan.valid()
        idx = np.flatnonzero(m)
        if idx.size > self.cfg.max_beams:
            idx = idx[np.linspace(0, idx.size - 1, self.cfg.max_beams).astype(int)]
        a, r = scan.angles[idx], scan.ranges[idx]
        lx, ly, lth = self.laser_pose
        px, py = r * np.cos(a + lth) + lx, r * np.sin(a + lth) + ly
        return np.column_stack([px, py])

    def match(self, guess: Array, pts: Array) -> tuple[Array, Array]:
        """Gauss-Newton coarse to fine from ``guess``; returns the pose and ``H^-1``."""
        x = np.asarray(guess, float).copy()
        H = np.eye(3)
        for lev in reversed(self.levels):
            for _ in range(self.cfg.iterations):
                c, s = np.cos(x[2]), np.sin(x[2])
                wp = pts @ np.array([[c, s], [-s, c]]) + x[:2]
                val, g = lev.value_grad(wp)
                dS = np.column_stack(
                    [-s * pts[:, 0] - c * pts[:, 1], c * pts[:, 0] - s * pts[:, 1]]
                )
                J = np.column_stack([g[:, 0], g[:, 1], g[:, 0] * dS[:, 0] + g[:, 1] * dS[:, 1]])
                r = 1.0 - val
                H = J.T @ J + 1e-6 * np.eye(3)
                step = np.linalg.solve(H, J.T @ r)
                x = x + step
                x[2] = float(_wrap(x[2]))
                if np.linalg.norm(step[:2]) < 1e-5 and abs(step[2]) < 1e-5:
                    break
        return x, np.linalg.inv(H)

    def score(self, pose: Array, pts: Array) -> float:
        """Mean finest-level map value (0..1) at the endpoints ``pts`` (k, 2) (base frame)
        moved by ``pose``: near 1 when the scan lies on the walls."""
        c, s = np.cos(pose[2]), np.sin(pose[2])
        val, _ = self.levels[0].value_grad(pts @ np.array([[c, s], [-s, c]]) + pose[:2])
        return float(np.mean(val)) if val.size else 0.0

    def update(self, odom_pose: Array, scan: LaserScan, force: bool = False) -> PoseEstimate:
        odom_pose = finite_pose(odom_pose, "odometry pose")
        guess = self.pose_at(odom_pose)
        pts = self._endpoints_base(check_scan(scan))
        ok, reason = True, ""
        if len(pts) >= 10:
            pose, cov = self.match(guess, pts)
            self.last_score = self.score(pose, pts)
            c = self.cfg
            jump = float(np.hypot(*(pose[:2] - guess[:2])))
            if not (np.all(np.isfinite(pose)) and np.all(np.isfinite(cov))):
                ok, reason = False, "scan match diverged (NaN)"
            elif self.last_score < c.min_score:
                ok, reason = False, f"match score {self.last_score:.3f} < min_score {c.min_score}"
            elif jump > c.max_jump:
                ok, reason = (
                    False,
                    f"match moved {jump:.3f} m from odometry (max_jump {c.max_jump})",
                )
            if ok:
                self._pose, self._cov = pose, cov
            else:
                self.failures += 1
                self._pose = guess
        else:
            self.last_score = float("nan")
            ok, reason = False, f"{len(pts)} valid beams (< 10): no match"
            self._pose = guess
        self._odom = odom_pose.copy()
        return PoseEstimate(self._pose.copy(), self._cov, 0, True, self.name, ok, reason)

    def estimate(self) -> PoseEstimate:
        if self._pose is None:
            raise InvalidInputError("initialize the matcher with a pose first")
        return PoseEstimate(self._pose.copy(), self._cov, 0, False, self.name)
