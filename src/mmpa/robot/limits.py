"""Joint limits: the one place every motion is checked against position, velocity and
acceleration limits before anything moves.

A timed joint path ``q`` (N, 6) at ``t`` (N,) s is executed by linear interpolation between
samples (what ``Arm.follow`` and a UR's ``servoJ`` stream do). Its velocity on segment ``k``
is ``v_k = (q_{k+1} - q_k) / (t_{k+1} - t_k)``, and its acceleration at sample ``k`` the
finite difference ``a_k = (v_k - v_{k-1}) / ((t_{k+1} - t_{k-1}) / 2)`` (exact for a path
sampled from a constant-acceleration motion). A streaming set-point (``Arm.command``) is
shaped by :func:`limit_setpoint`, a per-joint second-order limiter: the set-point moves
toward its target no faster than ``qd_max`` and changes speed no faster than ``qdd_max``,
braking early enough to stop at the target. A stream not held to ``qdd_max`` (a tracking
grasp of a moving object) is still held to the arm's hard stream limit ``qdd_stream_max``
(:meth:`JointLimits.stream`): no backend streams an unbounded acceleration.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import numpy as np

from mmpa.core.errors import InvalidInputError, JointLimitError
from mmpa.core.geometry import Array
from mmpa.robot.description import ArmDescription

__all__ = [
    "JointLimits",
    "StreamLimitsSwitch",
    "as_floats",
    "check_path",
    "check_positions",
    "check_target",
    "limit_acceleration",
    "limit_setpoint",
    "path_accelerations",
    "path_velocities",
    "synchronized_limits",
]


@dataclass(frozen=True)
class JointLimits:
    """Limits of a 6-joint arm, each shape (6,): ``q_min``/``q_max`` rad, ``qd_max`` rad/s,
    ``qdd_max`` rad/s^2. ``tolerance`` is the relative slack allowed on velocity and
    acceleration (rounding of time stamps). ``qdd_stream_max`` (rad/s^2, >= ``qdd_max``;
    None: ``qdd_max``): the hard acceleration limit of a servo stream that is not held to
    ``qdd_max`` (:meth:`stream`)."""

    q_min: Array
    q_max: Array
    qd_max: Array
    qdd_max: Array
    tolerance: float = 1e-6
    qdd_stream_max: Array | None = None

    @classmethod
    def from_description(cls, arm: ArmDescription) -> JointLimits:
        lo, hi = arm.q_limits
        return cls(
            lo,
            hi,
            np.asarray(arm.qd_max, float),
            np.asarray(arm.qdd_max, float),
            qdd_stream_max=np.asarray(arm.qdd_stream_max, float),
        )

    def stream(self, acceleration_limited: bool = True) -> JointLimits:
        """The limits of a servo stream's set-points: these limits (``acceleration_limited``)
        or, for a stream not held to ``qdd_max``, the same with ``qdd_max`` raised to the
        hard ``qdd_stream_max`` (never unbounded: without one, these limits)."""
        if acceleration_limited or self.qdd_stream_max is None:
            return self
        return dataclasses.replace(self, qdd_max=np.asarray(self.qdd_stream_max, float))


class StreamLimitsSwitch:
    """The ``stream_acceleration_limited`` switch of an arm backend's command stream, over
    its ``limits`` and ``stream_limits`` (:class:`JointLimits`, set by the backend): True
    (the default) keeps the streamed set-points within ``qdd_max`` (``stream_limits`` =
    ``limits``), False within the hard stream limit ``qdd_stream_max``
    (:meth:`JointLimits.stream`). The tracking grasp sets it from its config
    (``GraspConfig.stream.accel_limit``)."""

    limits: JointLimits
    stream_limits: JointLimits

    @property
    def stream_acceleration_limited(self) -> bool:
        return bool(np.array_equal(self.stream_limits.qdd_max, self.limits.qdd_max))

    @stream_acceleration_limited.setter
    def stream_acceleration_limited(self, on: bool) -> None:
        self.stream_limits = self.limits.stream(on)


def as_floats(x: object, what: str) -> Array:
    """``x`` as a float array, or :class:`InvalidInputError` naming ``what`` when it holds
    something that is not a number (text, None, ragged lists)."""
    try:
        return np.asarray(x, dtype=float)
    except (TypeError, ValueError):
        raise InvalidInputError(f"{what} must be numbers, got {x!r:.80}") from None


def check_target(q: Array, limits: JointLimits, what: str = "joint target") -> Array:
    """One joint target: ``q`` as a float array of shape (6,) within the limits
    (:func:`check_positions`), else :class:`InvalidInputError` / :class:`JointLimitError`."""
    q = as_floats(q, f"{what} (6 angles, rad)")
    if q.shape != (6,):
        raise InvalidInputError(f"{what} must be 6 angles, got shape {q.shape}")
    return check_positions(q, limits, what)


def check_positions(q: Array, limits: JointLimits, what: str = "joint target") -> Array:
    """Return ``q`` (6,) or (N, 6) as floats; raise if any value is not finite
    (:class:`InvalidInputError`) or outside ``[q_min, q_max]`` (:class:`JointLimitError`)."""
    q = as_floats(q, what)
    if q.shape[-1:] != (6,) or q.ndim not in (1, 2):
        raise InvalidInputError(f"{what} must have shape (6,) or (N, 6), got {q.shape}")
    if not np.all(np.isfinite(q)):
        raise InvalidInputError(f"{what} holds a NaN or infinite angle: {q[~np.isfinite(q)][:3]}")
    bad = (q < limits.q_min) | (q > limits.q_max)
    if np.any(bad):
        idx = np.argwhere(np.atleast_2d(bad))[0]
        k, j = int(idx[0]), int(idx[1])
        val = float(np.atleast_2d(q)[k, j])
        at = f" at sample {k}" if q.ndim == 2 else ""
        raise JointLimitError(
            f"{what}{at}: joint {j + 1} = {val:.4f} rad is outside its limits "
            f"[{limits.q_min[j]:.4f}, {limits.q_max[j]:.4f}]"
        )
    return q


def path_velocities(t: Array, q: Array) -> Array:
    """Segment velocities ``(q_{k+1} - q_k) / (t_{k+1} - t_k)``, shape (N-1, 6) rad/s."""
    return np.diff(q, axis=0) / np.diff(t)[:, None]


def path_accelerations(t: Array, q: Array) -> Array:
    """Accelerations at the inner samples, shape (N-2, 6) rad/s^2 (module docstring)."""
    v = path_velocities(t, q)
    return np.diff(v, axis=0) / (0.5 * (t[2:] - t[:-2]))[:, None]


def check_path(t: Array, q: Array, limits: JointLimits, what: str = "joint path") -> None:
    """Refuse a timed path that is not finite, not strictly increasing in time, or that
    breaks the position, velocity or acceleration limits; the message names the sample,
    the joint, the value and the limit, and how to fix it (``mmpa.planning.retime``).

    ``t`` (N,) s, ``q`` (N, 6) rad. Raises :class:`InvalidInputError` or
    :class:`JointLimitError`.
    """
    t = as_floats(t, f"{what}: its times")
    q = as_floats(q, f"{what}: its joint angles")
    if t.ndim != 1 or q.shape != (len(t), 6) or len(t) < 1:
        raise InvalidInputError(f"{what}: need t (N,) and q (N, 6), got {t.shape}, {q.shape}")
    if not np.all(np.isfinite(t)):
        raise InvalidInputError(f"{what}: a time stamp is NaN or infinite")
    if np.any(np.diff(t) <= 0):
        raise InvalidInputError(f"{what}: time stamps must increase strictly")
    check_positions(q, limits, what)
    slack = 1.0 + limits.tolerance
    for name, values, lim, unit in (
        ("velocity", path_velocities(t, q) if len(t) > 1 else None, limits.qd_max, "rad/s"),
        (
            "acceleration",
            path_accelerations(t, q) if len(t) > 2 else None,
            limits.qdd_max,
            "rad/s^2",
        ),
    ):
        if values is None:
            continue
        ratio = np.abs(values) / lim
        if np.any(ratio > slack):
            k, j = np.unravel_index(int(np.argmax(ratio)), ratio.shape)
            raise JointLimitError(
                f"{what}: joint {j + 1} {name} {values[k, j]:.3f} {unit} near sample {k + 1} "
                f"is {ratio[k, j]:.2f}x its limit {lim[j]:.3f} {unit}; slow the path down "
                "(mmpa.planning.retime) before sending it"
            )


def limit_setpoint(
    q: Array,
    v: Array,
    target: Array,
    dt: float,
    limits: JointLimits,
    v_target: Array | float = 0.0,
) -> tuple[Array, Array]:
    """One control period of the streaming limiter: from set-point ``q`` moving at ``v``
    (both (6,)) toward ``target`` (6,), the target's position at the end of this period,
    moving at ``v_target`` (rad/s, (6,) or 0), return the next ``(q, v)`` after ``dt`` s.

    Per joint, with ``e = target - q``: the desired velocity is ``v_target`` plus the speed
    from which braking by ``qdd_max dt`` per period closes ``e`` exactly (discrete braking:
    ``a dt (sqrt(1/4 + 2 |e| / (a dt^2)) - 1/2)``), at most ``qd_max`` in all; the velocity
    changes by at most ``qdd_max dt`` per period. The step that reaches the target lands on
    it exactly when that keeps within the limits (a held target is reached and held; a
    steady ramp is tracked without lag); a target moved inside the braking distance is
    overshot and returned to. With ``qdd_max = inf`` it is a pure velocity limiter.
    """
    e = target - q
    a, vmax = limits.qdd_max, limits.qd_max
    adt = a * dt
    v_t = np.broadcast_to(np.asarray(v_target, dtype=float), e.shape)
    with np.errstate(invalid="ignore", divide="ignore"):  # qdd_max = inf: no braking needed
        v_brake = np.where(
            np.isinf(a), np.abs(e) / dt, adt * (np.sqrt(0.25 + 2.0 * np.abs(e) / (adt * dt)) - 0.5)
        )
    v_goal = np.clip(v_t + np.sign(e) * v_brake, -vmax, vmax)
    v_new = v + np.clip(v_goal - v, -adt, adt)
    # land when the target is reachable this period at a velocity reachable from v and
    # close enough to the target's own for the next period
    v_land = e / dt
    land = (
        (np.abs(v_land) <= vmax)
        & (np.abs(v_land - v) <= adt * (1 + 1e-9))
        & (np.abs(v_land - v_t) <= adt * (1 + 1e-9))
    )
    q_new = np.where(land, target, q + v_new * dt)
    v_new = np.where(land, v_land, v_new)
    return q_new, v_new


def limit_acceleration(v: Array, v_des: Array, dt: float, limits: JointLimits) -> Array:
    """The joint velocity (6,) rad/s one period ``dt`` s after ``v`` (6,) on the way to the
    wanted velocity ``v_des`` (6,): ``v + s (v_des - v)`` with the largest ``s`` in [0, 1]
    that keeps every joint's change within ``qdd_max dt`` (the change keeps its direction:
    the tool's motion turns, it is not skewed joint by joint), then scaled into ``qd_max``
    as a whole. A stream ``q_{k+1} = q_k + v_{k+1} dt`` of such velocities keeps
    :func:`path_accelerations` within ``qdd_max`` and :func:`path_velocities` within
    ``qd_max``. Raises :class:`InvalidInputError` for a non-positive or non-finite ``dt``."""
    if not (np.isfinite(dt) and dt > 0):
        raise InvalidInputError(f"dt must be a positive finite period, got {dt}")
    v = np.asarray(v, dtype=float)
    dv = np.asarray(v_des, dtype=float) - v
    room = limits.qdd_max * dt
    with np.errstate(divide="ignore", invalid="ignore"):
        s = np.min(np.where(np.abs(dv) > room, room / np.abs(dv), 1.0))
    v_new = v + s * dv
    over = np.max(np.abs(v_new) / limits.qd_max)
    return v_new / over if over > 1.0 else v_new


def synchronized_limits(q_from: Array, q_to: Array, limits: JointLimits) -> JointLimits:
    """Limits for a rest-to-rest move from ``q_from`` to ``q_to`` (both (6,) rad) through
    :func:`limit_setpoint` along the joint-space straight line: each joint's ``qd_max`` and
    ``qdd_max`` become ``beta d_j`` and ``alpha d_j`` (``d_j = |q_to_j - q_from_j|``, at
    least 1e-9 rad), ``beta``, ``alpha`` the largest keeping every joint within
    ``limits``. The limiter's per-joint motion then scales with ``d_j``: every joint covers
    the same fraction of its way at every period (and all arrive together), at the speed
    and acceleration of the slowest joint."""
    d = np.maximum(np.abs(np.asarray(q_to, float) - np.asarray(q_from, float)), 1e-9)
    beta = float(np.min(limits.qd_max / d))
    alpha = float(np.min(limits.qdd_max / d))
    return JointLimits(limits.q_min, limits.q_max, beta * d, alpha * d, limits.tolerance)
