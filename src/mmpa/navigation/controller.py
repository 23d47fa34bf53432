"""Go-to-pose controller for a differential-drive base (turn, drive, turn).

A pure function of the current pose estimate and the goal; it never sees the simulator, so
the same controller runs on a localization estimate once that exists.
"""

from __future__ import annotations

import numpy as np
from pydantic import BaseModel, ConfigDict, Field

from mmpa.core.geometry import Array, wrap_angle

__all__ = ["GoToPoseConfig", "go_to_pose_command"]


class GoToPoseConfig(BaseModel):
    """Gains and tolerances (m, rad, m/s, rad/s)."""

    # NaN / inf refused: a NaN gain or limit would drive the base with NaN commands
    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)

    k_v: float = Field(0.8, gt=0)
    k_w: float = Field(2.0, gt=0)
    max_v: float = Field(0.4, gt=0)
    max_w: float = Field(0.8, gt=0)
    turn_in_place: float = Field(0.5, gt=0)  # rad: heading error above which it turns on the spot
    pos_tol: float = Field(0.01, ge=0)
    yaw_tol: float = Field(float(np.deg2rad(0.5)), ge=0)


def go_to_pose_command(pose: Array, goal: Array, cfg: GoToPoseConfig) -> tuple[float, float, bool]:
    """Velocity command ``(v, w, done)`` driving planar ``pose`` = ``[x, y, theta]`` to ``goal``.

    Far from the goal (``rho > pos_tol``): steer toward it, ``w = k_w * alpha`` with
    ``alpha`` the bearing error, and ``v = min(max_v, k_v rho) cos(alpha)`` (zero while
    ``|alpha| > turn_in_place``). At the goal position: turn to the goal heading. ``done`` once
    both tolerances hold.
    """
    x, y, th = np.asarray(pose, float)
    gx, gy, gth = np.asarray(goal, float)
    dx, dy = gx - x, gy - y
    rho = float(np.hypot(dx, dy))
    if rho > cfg.pos_tol:
        alpha = float(wrap_angle(np.arctan2(dy, dx) - th))
        # a goal just behind (overshoot) is approached in reverse instead of turning around
        if rho < 0.15 and abs(alpha) > np.pi / 2:
            alpha = float(wrap_angle(alpha + np.pi))
            sign = -1.0
        else:
            sign = 1.0
        w = float(np.clip(cfg.k_w * alpha, -cfg.max_w, cfg.max_w))
        v = 0.0 if abs(alpha) > cfg.turn_in_place else min(cfg.max_v, cfg.k_v * rho) * np.cos(alpha)
        return sign * float(v), w, False
    err = float(wrap_angle(gth - th))
    if abs(err) > cfg.yaw_tol:
        return 0.0, float(np.clip(cfg.k_w * err, -cfg.max_w, cfg.max_w)), False
    return 0.0, 0.0, True
