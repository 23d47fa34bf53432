"""From a tool path to a joint trajectory the arm can follow (paper 000 §3.2.4).

``plan_joint_path`` solves IK for every waypoint of a tool path ``T_arm_base_tool`` (N, 4, 4),
each solution the one nearest the previous joint vector (branch continuity), inside the joint
limits, and refuses the whole path (before any motion) when a waypoint is unreachable or a
joint would jump between consecutive waypoints. ``retime`` stretches the path's time stamps
uniformly until a cubic spline through the joint samples respects the velocity and
acceleration limits (velocity scales with 1/s, acceleration with 1/s^2).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from pydantic import BaseModel, ConfigDict, Field
from scipy.interpolate import CubicSpline

from mmpa.core.errors import InvalidInputError, UnreachableError
from mmpa.core.geometry import Array
from mmpa.robot.description import ArmDescription
from mmpa.robot.kinematics import fk, ik_nearest
from mmpa.robot.limits import JointLimits, check_positions, path_accelerations, path_velocities

__all__ = ["JointPath", "PathPlanConfig", "plan_joint_path", "retime"]


class PathPlanConfig(BaseModel):
    """Limits for turning a tool path into a joint path."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    max_joint_step: float = Field(0.15, gt=0)  # rad between consecutive waypoints
    max_ik_error: float = Field(1e-5, gt=0)  # m: nominal FK of the solution vs the waypoint
    velocity_scale: float = Field(0.5, gt=0, le=1)  # fraction of the joint velocity limits
    acceleration_scale: float = Field(0.5, gt=0, le=1)  # fraction of the acceleration limits


@dataclass(frozen=True)
class JointPath:
    """A timed joint path: ``t`` (N,) s from 0, ``q`` (N, 6) rad; ``time_scale`` >= 1 is the
    factor by which the taught timing was stretched to respect the limits."""

    t: Array
    q: Array
    time_scale: float = 1.0

    @property
    def duration(self) -> float:
        return float(self.t[-1] - self.t[0])


def plan_joint_path(
    arm: ArmDescription,
    T_arm_base_tool: Array,
    q_start: Array,
    T_flange_tool: Array,
    cfg: PathPlanConfig | None = None,
) -> Array:
    """IK for every waypoint with branch continuity; returns ``q`` (N, 6).

    Raises :class:`UnreachableError` naming the first waypoint that has no solution inside the
    joint limits, or where a joint would jump by more than ``cfg.max_joint_step``.
    """
    cfg = cfg or PathPlanConfig()
    P = np.asarray(T_arm_base_tool, dtype=float)
    if P.ndim != 3 or P.shape[1:] != (4, 4) or len(P) == 0 or not np.all(np.isfinite(P)):
        raise InvalidInputError(f"tool path must be finite (N, 4, 4) poses, got {P.shape}")
    lo, hi = arm.q_limits
    q_prev = np.asarray(q_start, dtype=float)
    out = np.empty((len(P), 6))
    for i, T in enumerate(P):
        try:
            q = ik_nearest(arm.dh, T, q_prev, lo, hi, T_flange_point=T_flange_tool)
        except UnreachableError as e:
            raise UnreachableError(f"tool path waypoint {i}/{len(P)} is unreachable: {e}") from None
        if i > 0:
            step = np.abs(q - q_prev)
            if np.any(step > cfg.max_joint_step):
                j = int(np.argmax(step))
                raise UnreachableError(
                    f"tool path waypoint {i}/{len(P)}: joint {j + 1} would jump by "
                    f"{step[j]:.3f} rad (limit {cfg.max_joint_step} rad); the path crosses a "
                    "singularity or changes IK branch"
                )
        err = np.linalg.norm(fk(arm.dh, q, T_flange_tool)[:3, 3] - T[:3, 3])
        if err > cfg.max_ik_error:
            raise UnreachableError(f"tool path waypoint {i}: IK residual {err:.2e} m")
        out[i] = q_prev = q
    return out


def retime(t: Array, q: Array, arm: ArmDescription, cfg: PathPlanConfig | None = None) -> JointPath:
    """Uniform time scaling so that the cubic spline through ``(t, q)`` stays within
    ``velocity_scale * qd_max`` and ``acceleration_scale * qdd_max``.

    With ``q(t) = c(t / s)``: ``q' = c' / s`` and ``q'' = c'' / s^2``, so the smallest
    admissible ``s`` is ``max(1, max|c'|/v, sqrt(max|c''|/a))`` (sampled densely on the spline),
    taken over both the spline and the linear interpolation the arm executes (segment
    velocities and their finite-difference accelerations, :mod:`mmpa.robot.limits`).

    Raises :class:`JointLimitError` when a sample is outside the position limits (no timing
    can fix that) and :class:`InvalidInputError` on NaN or non-increasing time stamps.
    """
    cfg = cfg or PathPlanConfig()
    t = np.asarray(t, dtype=float)
    q = np.asarray(q, dtype=float)
    if t.ndim != 1 or q.shape != (len(t), 6) or len(t) < 2:
        raise InvalidInputError(f"need t (N,) and q (N, 6) with N >= 2, got {t.shape}, {q.shape}")
    if not np.all(np.isfinite(t)) or np.any(np.diff(t) <= 0):
        raise InvalidInputError("path time stamps must be finite and increase strictly")
    check_positions(q, JointLimits.from_description(arm), "joint path")
    t = t - t[0]
    spline = CubicSpline(t, q, axis=0, bc_type="clamped")
    ts = np.linspace(0.0, t[-1], max(10 * len(t), 200))
    v = np.abs(spline(ts, 1)).max(axis=0)
    a = np.abs(spline(ts, 2)).max(axis=0)
    v = np.maximum(v, np.abs(path_velocities(t, q)).max(axis=0))
    if len(t) > 2:
        a = np.maximum(a, np.abs(path_accelerations(t, q)).max(axis=0))
    vmax = np.asarray(arm.qd_max) * cfg.velocity_scale
    amax = np.asarray(arm.qdd_max) * cfg.acceleration_scale
    s = max(1.0, float(np.max(v / vmax)), float(np.sqrt(np.max(a / amax))))
    return JointPath(t * s, q.copy(), s)
