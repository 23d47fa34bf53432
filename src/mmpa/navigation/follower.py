"""Path following for the differential base: pure pursuit, then a final approach to the goal.

Pure pursuit (Coulter 1992): the carrot is the point ``lookahead`` m ahead along the path from
the projection of the robot; curvature ``k = 2 sin(alpha) / L``, ``w = v k``; the robot turns on
the spot when the carrot is more than ``turn_in_place`` rad off its heading; ``v`` slows down
toward the end of the path. Within ``approach_radius`` of the goal the follower hands over to
the go-to-pose controller (:mod:`mmpa.navigation.controller`) with tight tolerances.

A pure function of the pose ESTIMATE (never the truth) plus a little state (progress index).
"""

from __future__ import annotations

import numpy as np
from pydantic import BaseModel, ConfigDict, Field

from mmpa.errors import InvalidInputError
from mmpa.geometry import Array, wrap_angle
from mmpa.navigation.controller import GoToPoseConfig, go_to_pose_command

__all__ = ["FollowerConfig", "PathFollower"]


class FollowerConfig(BaseModel):
    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)  # NaN / inf refused

    lookahead: float = Field(0.6, gt=0)  # m
    max_v: float = Field(0.4, gt=0)  # m/s
    max_w: float = Field(0.8, gt=0)  # rad/s
    turn_in_place: float = Field(0.8, gt=0)  # rad
    slow_radius: float = Field(0.8, gt=0)  # m: v ramps down inside this distance to the goal
    approach_radius: float = Field(0.15, gt=0)  # m: switch to the final approach
    max_reentries: int = Field(3, ge=0)  # align -> position phase switches allowed
    final_timeout: float = Field(25.0, gt=0)  # s in the final approach before giving up
    # creeping along the heading cannot remove a lateral error: with the goal abeam (|ex| <=
    # pos_tol) and within the creeping band to the side (|ey| <= 2 pos_tol), the position
    # phase ends (the caller's settle check and corrections judge the pose). Without it a
    # steady estimate 3-6 mm to the side makes the base creep back and forth until
    # ``final_timeout`` (an estimate that jitters by a few mm gets out by chance)
    abeam_done: bool = True
    final: GoToPoseConfig = GoToPoseConfig(
        k_v=0.6, k_w=1.5, max_v=0.08, max_w=0.3, turn_in_place=0.35, pos_tol=0.003, yaw_tol=0.003
    )


class PathFollower:
    """Follow ``path`` (K, 2) and stop at ``goal`` = ``[x, y, theta]``."""

    def __init__(self, path: Array, goal: Array, cfg: FollowerConfig | None = None) -> None:
        self.path = np.asarray(path, float).reshape(-1, 2)
        if len(self.path) < 2:
            self.path = np.vstack([self.path, self.path[-1:]])
        self.goal = np.asarray(goal, float).reshape(3)
        if not (np.all(np.isfinite(self.path)) and np.all(np.isfinite(self.goal))):
            raise InvalidInputError("path and goal must be finite")
        self.cfg = cfg or FollowerConfig()
        seg = np.diff(self.path, axis=0)
        self._seglen = np.linalg.norm(seg, axis=1)
        self._s = np.concatenate([[0.0], np.cumsum(self._seglen)])
        self._progress = 0.0
        self.final_phase = False
        self._align = False
        self._reentries = 0

    def _project(self, xy: Array) -> float:
        best, best_s = np.inf, self._progress
        for i in range(len(self._seglen)):
            if self._s[i + 1] < self._progress - 1e-9:
                continue
            a, L = self.path[i], self._seglen[i]
            t = 0.0 if L < 1e-9 else float(np.clip((xy - a) @ (self.path[i + 1] - a) / L**2, 0, 1))
            p = a + t * (self.path[i + 1] - a)
            d = float(np.linalg.norm(xy - p))
            if d < best - 1e-9:
                best, best_s = d, self._s[i] + t * L
            if self._s[i] > self._progress + 3.0:
                break
        return max(best_s, self._progress)

    def _point_at(self, s: float) -> Array:
        s = min(s, self._s[-1])
        i = int(np.clip(np.searchsorted(self._s, s) - 1, 0, len(self._seglen) - 1))
        L = self._seglen[i]
        t = 0.0 if L < 1e-9 else (s - self._s[i]) / L
        return self.path[i] + t * (self.path[i + 1] - self.path[i])

    def restart_final(self) -> None:
        """Re-enter the final approach (after a re-check found the pose off tolerance)."""
        self._align = False

    def _final(self, pose: Array) -> tuple[float, float, bool]:
        """Final approach with hysteresis: reach the position within ``pos_tol`` (turning
        toward it only while it is further than 3 ``pos_tol`` to the side, else creeping
        along the heading), then turn to the goal heading; back to the position phase only if
        the position drifts beyond 3 ``pos_tol``."""
        f = self.cfg.final
        g = self.goal
        dx, dy = g[0] - pose[0], g[1] - pose[1]
        rho = float(np.hypot(dx, dy))
        c, s = np.cos(pose[2]), np.sin(pose[2])
        ex, ey = c * dx + s * dy, -s * dx + c * dy  # goal in the robot frame
        if self._align and rho > 3 * f.pos_tol and self._reentries < self.cfg.max_reentries:
            self._align = False
            self._reentries += 1
        if not self._align:
            if rho <= f.pos_tol or (abs(ey) <= f.pos_tol and abs(ex) <= f.pos_tol):
                self._align = True
            elif self.cfg.abeam_done and abs(ex) <= f.pos_tol and abs(ey) <= 2 * f.pos_tol:
                self._align = True
            elif abs(ey) <= 2 * f.pos_tol or (rho < 0.01 and abs(ey) < 0.5 * abs(ex)):
                v = float(np.clip(f.k_v * ex, -f.max_v, f.max_v))
                if abs(v) < 0.004:
                    v = 0.004 * np.sign(ex)
                return v, 0.0, False
            else:
                return (*go_to_pose_command(pose, np.array([g[0], g[1], pose[2]]), f)[:2], False)
        err = float(wrap_angle(g[2] - pose[2]))
        if abs(err) <= f.yaw_tol:
            return 0.0, 0.0, True
        w = float(np.clip(f.k_w * err, -f.max_w, f.max_w))
        if abs(w) < 0.01:
            w = 0.01 * np.sign(err)
        return 0.0, w, False

    def command(self, pose: Array) -> tuple[float, float, bool]:
        """``(v, w, done)`` for the estimated pose ``[x, y, theta]``."""
        c = self.cfg
        pose = np.asarray(pose, float)
        dist_goal = float(np.hypot(*(self.goal[:2] - pose[:2])))
        if self.final_phase or dist_goal < c.approach_radius:
            self.final_phase = True
            return self._final(pose)
        self._progress = self._project(pose[:2])
        carrot = self._point_at(self._progress + c.lookahead)
        d = carrot - pose[:2]
        alpha = float(wrap_angle(np.arctan2(d[1], d[0]) - pose[2]))
        if abs(alpha) > c.turn_in_place:
            return 0.0, float(np.clip(2.0 * alpha, -c.max_w, c.max_w)), False
        v = c.max_v * min(1.0, max(dist_goal / c.slow_radius, 0.15))
        L = max(float(np.hypot(*d)), 1e-6)
        w = v * 2.0 * np.sin(alpha) / L
        if abs(w) > c.max_w:
            v *= c.max_w / abs(w)
            w = float(np.sign(w) * c.max_w)
        return float(v), float(w), False
