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

from mmpa.core.errors import InvalidInputError
from mmpa.core.geometry import Array, wrap_angle
from mmpa.navigation.controller import GoToPoseConfig

__all__ = ["FollowerConfig", "PathFollower", "goal_frame_error", "within_tolerance"]


class FollowerConfig(BaseModel):
    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)  # NaN / inf refused

    lookahead: float = Field(0.6, gt=0)  # m
    max_v: float = Field(0.4, gt=0)  # m/s
    max_w: float = Field(0.8, gt=0)  # rad/s
    turn_in_place: float = Field(0.8, gt=0)  # rad
    slow_radius: float = Field(0.8, gt=0)  # m: v ramps down inside this distance to the goal
    approach_radius: float = Field(0.15, gt=0)  # m: switch to the final approach
    # final approach along the goal's heading line (see PathFollower._final): the carrot is
    # ``final_lookahead`` m ahead of the robot's projection on the line; a lateral offset left
    # at the goal is removed by backing off ``backoff`` m along the line and creeping in again
    final_lookahead: float = Field(0.03, gt=0)  # m
    backoff: float = Field(0.05, gt=0)  # m
    min_creep: float = Field(0.004, gt=0)  # m/s: the slowest creep (a base's deadband)
    confirm_ticks: int = Field(4, ge=1)  # standing ticks averaged before a phase decision
    max_reentries: int = Field(3, ge=0)  # back-off and creep-in cycles allowed
    final_timeout: float = Field(60.0, gt=0)  # s in the final approach before giving up
    final: GoToPoseConfig = GoToPoseConfig(
        k_v=0.6, k_w=1.5, max_v=0.08, max_w=0.3, turn_in_place=0.35, pos_tol=0.003, yaw_tol=0.003
    )


def goal_frame_error(pose: Array, goal: Array) -> tuple[float, float, float]:
    """``(a, l, e_theta)``: the goal ``a`` m ahead of ``pose`` along the goal heading
    ``h = (cos th_g, sin th_g)``, the robot ``l`` m to the left of the goal's heading line
    (``n = (-sin th_g, cos th_g)``) and the heading error ``wrap(th_g - th)`` (rad)."""
    d = np.asarray(goal[:2], float) - np.asarray(pose[:2], float)
    c, s = np.cos(goal[2]), np.sin(goal[2])
    return (
        float(c * d[0] + s * d[1]),
        float(s * d[0] - c * d[1]),
        float(wrap_angle(goal[2] - pose[2])),
    )


def within_tolerance(pose: Array, goal: Array, cfg: GoToPoseConfig, scale: float = 1.0) -> bool:
    """Whether ``pose`` is at ``goal``: position within ``scale * pos_tol`` (m) and heading
    within ``scale * yaw_tol`` (rad). The follower ends its final approach at ``scale = 1``;
    the navigation loop accepts a settled estimate at a looser ``scale`` (its hysteresis)."""
    rho = float(np.hypot(goal[0] - pose[0], goal[1] - pose[1]))
    return (
        rho <= scale * cfg.pos_tol
        and abs(float(wrap_angle(goal[2] - pose[2]))) <= scale * cfg.yaw_tol
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
        self._phase = "lineup"
        self._reentries = 0
        self._backoff_to = self.cfg.backoff
        self._held: list[tuple[float, float]] = []

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

    def restart_final(self, pose: Array) -> None:
        """One more back-off and creep along the goal line, then the heading (after the
        caller's settle check found the settled estimate ``pose`` off tolerance). Not limited
        by ``max_reentries``: the caller bounds its own corrections."""
        self._start_line(goal_frame_error(np.asarray(pose, float), self.goal)[1])

    @property
    def phase(self) -> str:
        """The final approach's phase: ``lineup``, ``creep``, ``align`` or ``backoff``."""
        return self._phase

    def _line_needed(self, lat: float) -> float:
        """The distance (m) along the goal line over which pure pursuit brings the lateral
        offset ``lat`` down to ``pos_tol / 2``: ``s = L ln(|lat| / (pos_tol / 2))``."""
        half_tol = 0.5 * self.cfg.final.pos_tol
        return self.cfg.final_lookahead * float(np.log(max(abs(lat), 1e-9) / half_tol))

    def _start_line(self, lat: float) -> None:
        """Back off along the goal line far enough that pure pursuit removes the lateral
        offset ``lat`` on the way back and in (:meth:`_line_needed` each way, at least
        ``backoff``)."""
        c = self.cfg
        self._backoff_to = float(np.clip(self._line_needed(lat), c.backoff, c.approach_radius))
        self._phase = "backoff"

    def _confirmed(self, a: float, lat: float) -> tuple[float, float] | None:
        """Standing still, the mean ``(a, lat)`` over ``confirm_ticks`` ticks (None until
        then): one estimate, possibly a jump of a scan update, never decides a phase."""
        self._held.append((a, lat))
        if len(self._held) < self.cfg.confirm_ticks:
            return None
        m = np.mean(self._held, axis=0)
        self._held = []
        return float(m[0]), float(m[1])

    def _final(self, pose: Array) -> tuple[float, float, bool]:
        """Final approach along the goal's heading line: (1) ``lineup``: turn on the spot to
        the goal heading where the approach begins (``approach_radius`` from the goal), so
        that the turn's shift of the estimate (a lidar mount error is a heading-dependent
        position bias) is driven out afterwards; (2) ``creep`` to the goal along the line,
        forward or backward, by pure pursuit on the line (a lateral offset decays as
        ``exp(-s / final_lookahead)`` over the distance ``s`` driven); (3) ``align`` the
        heading; done if the position holds within ``pos_tol`` (the mean over
        ``confirm_ticks`` standing ticks), else (4) ``backoff`` along the line and creep in
        again (at most ``max_reentries`` times). A lateral offset too large for the distance
        left starts with (4)."""
        f, c = self.cfg.final, self.cfg
        a, lat, eth = goal_frame_error(pose, self.goal)
        if self._phase == "lineup":
            if abs(eth) > f.yaw_tol:
                return self._turn(eth)
            self._phase = "creep"
            if abs(lat) > f.pos_tol and abs(a) < self._line_needed(lat):
                self._start_line(lat)
        if self._phase == "backoff":
            if a < self._backoff_to - 0.5 * f.pos_tol:  # back until the goal is that far ahead
                speed = float(np.clip(f.k_v * (self._backoff_to - a), 4 * c.min_creep, f.max_v))
                return self._on_line(lat, eth, -1.0, speed)
            self._phase = "creep"
        if self._phase == "creep":
            if abs(a) > 0.5 * f.pos_tol:
                self._held = []
                speed = float(np.clip(f.k_v * abs(a), c.min_creep, f.max_v))
                return self._on_line(lat, eth, float(np.sign(a)), speed)
            held = self._confirmed(a, lat)
            if held is None or abs(held[0]) > 0.5 * f.pos_tol:
                return 0.0, 0.0, False
            self._phase = "align"
        if abs(eth) > f.yaw_tol:
            self._held = []
            return self._turn(eth)
        held = self._confirmed(a, lat)
        if held is None:
            return 0.0, 0.0, False
        if np.hypot(*held) <= f.pos_tol or self._reentries >= c.max_reentries:
            return 0.0, 0.0, True
        self._reentries += 1
        self._start_line(held[1])
        return self._final(pose)

    def _turn(self, eth: float) -> tuple[float, float, bool]:
        """Turn on the spot by ``eth`` (rad): ``w = k_w eth`` within ``[0.01, max_w]``."""
        f = self.cfg.final
        w = float(np.clip(f.k_w * eth, -f.max_w, f.max_w))
        return 0.0, float(w if abs(w) >= 0.01 else 0.01 * np.sign(eth)), False

    def _on_line(
        self, lat: float, eth: float, direction: float, speed: float
    ) -> tuple[float, float, bool]:
        """Pure pursuit along the goal's heading line, facing the goal heading, travelling
        forward (``direction`` +1) or backward (-1) at ``speed`` m/s. The carrot lies on the
        line ``L = final_lookahead`` m ahead of the robot's projection in the direction of
        travel; ``alpha`` is its bearing from the travel heading (``th`` or ``th + pi``),
        curvature ``k = 2 sin(alpha) / d`` with ``d = hypot(L, lat)``; ``w = speed k``."""
        f, L = self.cfg.final, self.cfg.final_lookahead
        # the carrot in the goal frame relative to the robot: (direction L, -lat); the travel
        # heading in the goal frame: -eth (forward) or -eth + pi (backward)
        travel = -eth + (0.0 if direction > 0 else np.pi)
        alpha = float(wrap_angle(np.arctan2(-lat, direction * L) - travel))
        if abs(alpha) > f.turn_in_place:
            return 0.0, float(np.clip(f.k_w * alpha, -f.max_w, f.max_w)), False
        w = speed * 2.0 * np.sin(alpha) / float(np.hypot(L, lat))
        if abs(w) > f.max_w:
            speed *= f.max_w / abs(w)
            w = float(np.sign(w) * f.max_w)
        return direction * speed, float(w), False

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
