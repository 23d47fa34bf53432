"""Jerk-limited online intercept of a moving joint-space target (issue 22).

A streamed set-point is a joint state ``(q, v, a)`` (each (6,): rad, rad/s, rad/s^2). The
target is a joint position ``q_goal`` (rad) now, moving on at the constant velocity ``v_goal``
(rad/s): the grasp pose over a moving object in joint space and the object's velocity mapped
through the Jacobian. :func:`intercept_step` plans, with ruckig's online trajectory generator
(time-optimal, each joint within ``qd_max``, ``qdd_max`` and ``qddd_max``, all joints arriving
together) in the target's moving frame: the state relative to the target goes to rest at 0
(the plan meets the target where the target will be, not where it is), and returns the
state ``h`` s along that plan. Replanned every period from the state it returned, the stream
is a concatenation of plan openings whose position, velocity and acceleration are continuous
and within the limits (ruckig's guarantee), and it meets a target that moves at constant
velocity exactly (then moves with it). A target velocity beyond ``speed_fraction`` of
``qd_max`` is scaled into it (ruckig needs a reachable target state).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from ruckig import InputParameter, Result, Ruckig, Trajectory

from mmpa.core.errors import InvalidInputError, MMPAError
from mmpa.core.geometry import Array

__all__ = ["InterceptError", "InterceptLimits", "StreamState", "intercept_step"]


class InterceptError(MMPAError):
    """The online planner found no trajectory (a state outside its limits)."""


@dataclass(frozen=True)
class StreamState:
    """A streamed set-point: ``q`` rad, ``v`` rad/s, ``a`` rad/s^2, each (6,)."""

    q: Array
    v: Array
    a: Array

    @classmethod
    def at_rest(cls, q: Array) -> StreamState:
        q = np.asarray(q, float)
        return cls(q.copy(), np.zeros_like(q), np.zeros_like(q))


@dataclass(frozen=True)
class InterceptLimits:
    """Per-joint limits (6,) of the plan: ``q_min``/``q_max`` rad, ``qd_max`` rad/s,
    ``qdd_max`` rad/s^2, ``qddd_max`` rad/s^3 (all positive and finite)."""

    q_min: Array
    q_max: Array
    qd_max: Array
    qdd_max: Array
    qddd_max: Array

    def __post_init__(self) -> None:
        for name in ("qd_max", "qdd_max", "qddd_max"):
            x = np.asarray(getattr(self, name), float)
            if x.shape != (6,) or not np.all(np.isfinite(x) & (x > 0)):
                raise InvalidInputError(f"intercept limit {name} must be 6 positive numbers")


def _plan(
    e: StreamState, v_goal: Array, lim: InterceptLimits, vmax: Array, min_duration: float
) -> Trajectory:
    """Ruckig from the state ``e`` relative to the target to the target (relative state 0),
    the velocity limits shifted by the target's velocity ``v_goal``."""
    otg = Ruckig(6)
    inp = InputParameter(6)
    inp.current_position = e.q.tolist()
    inp.current_velocity = e.v.tolist()
    inp.current_acceleration = e.a.tolist()
    inp.target_position = [0.0] * 6
    inp.target_velocity = [0.0] * 6
    inp.target_acceleration = [0.0] * 6
    inp.max_velocity = (vmax - v_goal).tolist()
    inp.min_velocity = (-vmax - v_goal).tolist()
    inp.max_acceleration = np.asarray(lim.qdd_max, float).tolist()
    inp.max_jerk = np.asarray(lim.qddd_max, float).tolist()
    if min_duration > 0:
        inp.minimum_duration = min_duration
    traj = Trajectory(6)
    res = otg.calculate(inp, traj)
    if res not in (Result.Working, Result.Finished):
        raise InterceptError(f"ruckig found no intercept trajectory: {res}")
    return traj


def intercept_step(
    state: StreamState,
    q_goal: Array,
    v_goal: Array,
    h: float,
    limits: InterceptLimits,
    speed_fraction: float = 0.9,
    min_duration: float = 0.0,
) -> tuple[StreamState, float]:
    """The stream's state ``h`` s (> 0) after ``state`` on the time-optimal jerk-limited plan
    that meets the target (``q_goal`` (6,) rad now, moving at ``v_goal`` (6,) rad/s): ruckig
    plans the state relative to the target, ``(q - q_goal, v - v_goal, a)``, to rest at 0,
    with the velocity limits ``[-qd_max - v_goal, qd_max - v_goal]`` (the target moves at
    constant velocity, so the relative acceleration and jerk are the absolute ones): the
    absolute plan ``relative + q_goal + v_goal t`` keeps ``qd_max``, ``qdd_max``,
    ``qddd_max`` and ends on the target, moving with it, in the least time ``T``. The
    target velocity is scaled (direction kept) into ``speed_fraction`` of ``qd_max``, its
    position clipped into the joint limits (a clipped joint's target stands still).
    ``min_duration`` s > 0: plans take at least that long (a softer catch-up: replanned
    every period, the gap closes over about that time instead of at the limits). Returns
    ``(new state, T s)``; past ``T`` the state moves on with the target. Raises
    :class:`InvalidInputError` on a non-finite input or ``h <= 0``, :class:`InterceptError`
    when ruckig finds no plan."""
    q_goal = np.asarray(q_goal, float)
    v_goal = np.asarray(v_goal, float)
    if not (np.isfinite(h) and h > 0):
        raise InvalidInputError(f"the stream period must be positive, got {h}")
    for name, x in (
        ("q_goal", q_goal),
        ("v_goal", v_goal),
        ("q", state.q),
        ("v", state.v),
        ("a", state.a),
    ):
        if np.shape(x) != (6,) or not np.all(np.isfinite(x)):
            raise InvalidInputError(f"intercept {name} must be 6 finite numbers, got {x}")
    vmax = np.asarray(limits.qd_max, float)
    over = float(np.max(np.abs(v_goal) / (speed_fraction * vmax)))
    if over > 1.0:
        v_goal = v_goal / over
    q_t = np.clip(q_goal, limits.q_min, limits.q_max)
    v_t = np.where(q_t != q_goal, 0.0, v_goal)
    rel = StreamState(state.q - q_t, state.v - v_t, np.asarray(state.a, float))
    traj = _plan(rel, v_t, limits, vmax, min_duration)
    e, ev, ea = (np.asarray(x, float) for x in traj.at_time(h))
    if h >= traj.duration:  # arrived: on with the target
        e, ev, ea = np.zeros(6), np.zeros(6), np.zeros(6)
    return StreamState(q_t + v_t * h + e, v_t + ev, ea), float(traj.duration)
