"""The streamed set-points of the tracking grasp and their limits (issue 22).

Each control period (a tick at ``track.rate_hz``, or a descent step) plans a :class:`Segment`:
toward a joint velocity ``v_des`` at the stream's acceleration limits
(:func:`mmpa.robot.limits.limit_acceleration`, the direction of the change kept), toward a
goal ``q_goal`` moving at ``v_goal`` (:func:`mmpa.robot.limits.limit_setpoint`: lands on it
when reachable, else brakes in time), or along the jerk-limited online intercept of such a
goal (:func:`mmpa.servo.intercept.intercept_step`). The waits stream it at ``stream.rate_hz``
(``h = 1 / rate_hz`` s apart, one sub-step ahead: the arm's interface holds a set-point's
velocity until the next one), past the segment's end braking to rest. Every set-point is
clipped to the joint limits less ``stream.joint_margin``; a clipped joint's velocity is the
clipped step over ``h``.

Limits (rad, rad/s, rad/s^2, 6 joints): ``limited`` -> qd_max and
``stream.joint_accel_fraction`` x qdd_max (the arm's interface told to enforce qdd_max);
not ``limited`` -> qd_max and the arm's hard stream limit ``qdd_stream_max``; the intercept's
plans -> ``intercept.accel_fraction`` x qdd_max and ``intercept.jerk_scale`` x qddd_max.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from mmpa.core.errors import InvalidInputError
from mmpa.core.geometry import Array
from mmpa.robot.interfaces import StreamingArm
from mmpa.robot.limits import (
    JointLimits,
    limit_acceleration,
    limit_setpoint,
    synchronized_limits,
)
from mmpa.servo.config import InterceptConfig, StreamConfig
from mmpa.servo.intercept import (
    InterceptError,
    InterceptLimits,
    StreamState,
    intercept_step,
)
from mmpa.servo.pose import ArmGeometry

__all__ = ["Segment", "Stream"]


@dataclass(frozen=True)
class Segment:
    """One control period of the stream: ``duration`` s toward the joint velocity ``v_des``
    (6,) rad/s, or, with ``q_goal`` (6,), toward that goal at the period's end moving at
    ``v_goal`` (6,) rad/s; within ``limits``."""

    duration: float
    v_des: Array
    limits: JointLimits
    q_goal: Array | None = None
    v_goal: Array = field(default_factory=lambda: np.zeros(6))
    #: toward ``q_goal`` (at the period's start, moving at ``v_goal``) by the online
    #: intercept (:func:`mmpa.servo.intercept.intercept_step`), also past ``duration``
    intercept: bool = False
    min_duration: float = 0.0  # s, of each intercept plan


class Stream:
    """The set-point stream to a :class:`~mmpa.robot.interfaces.StreamingArm`: its state
    (the last set-point sent ``q`` (6,) rad, its velocity and acceleration, when, its period)
    and the pending :class:`Segment`."""

    def __init__(self, geom: ArmGeometry, cfg: StreamConfig, icfg: InterceptConfig) -> None:
        arm = geom.robot.arm
        self.cfg = cfg
        self.q_lo, self.q_hi = geom.q_lo, geom.q_hi
        #: limits of the streamed set-points: the arm's qd_max, ``joint_accel_fraction`` of
        #: its qdd_max (issue 22)
        qd = np.asarray(arm.qd_max, float)
        qdd = np.asarray(arm.qdd_max, float) * cfg.joint_accel_fraction
        self._lim_acc = JointLimits(self.q_lo, self.q_hi, qd, qdd)
        # not ``limited``: qd_max and the arm's hard stream limit ``qdd_stream_max``, streamed
        # at ``rate_hz`` too
        qdd_hard = np.asarray(arm.qdd_stream_max, float)
        self._lim_hard = JointLimits(self.q_lo, self.q_hi, qd, qdd_hard)
        #: limits of the intercept plans ("intercept"): the stream's, and the jerk limit
        jerk = np.asarray(arm.qddd_max, float) * icfg.jerk_scale
        qdd_i = np.asarray(arm.qdd_max, float) * icfg.accel_fraction
        self.ilim = InterceptLimits(self.q_lo, self.q_hi, qd, qdd_i, jerk)
        #: whether the stream keeps qdd_max now (``accel_limit``)
        self.limited = cfg.accel_limit != "never"
        self.q: Array | None = None  # the last set-point sent (None: no stream)
        self.v = np.zeros(6)  # its velocity (rad/s)
        self.a = np.zeros(6)  # the stream's acceleration (rad/s^2)
        self.t: float | None = None  # when it was sent (clock s; None: not yet)
        self.h = 0.0  # its period (s)
        self.seg: Segment | None = None  # the pending control period (None: brake)
        self.seg_t = 0.0  # s streamed of it
        self.clock: Callable[[], float] | None = None

    @property
    def limits(self) -> JointLimits:
        """Limits of the streamed set-points now: the arm's qd_max, and
        ``joint_accel_fraction`` of its qdd_max while ``limited``, else its hard stream
        limit ``qdd_stream_max`` (issue 22)."""
        return self._lim_acc if self.limited else self._lim_hard

    def set_limited(self, arm: StreamingArm, on: bool) -> None:
        """Stream within qdd_max (``on``) or qd_max and the hard ``qdd_stream_max`` from now
        on, the arm's streaming interface told the same."""
        self.limited = bool(on)
        arm.stream_acceleration_limited = self.limited

    def start(self, q: Array) -> Array:
        """A new stream of set-points from ``q`` (6,) at rest (the arm stands there)."""
        self.q = np.clip(np.asarray(q, float), self.q_lo, self.q_hi)
        self.v = np.zeros(6)
        self.a = np.zeros(6)
        self.t = None
        self.seg = None
        return self.q.copy()

    def sub_steps(self, duration: float) -> tuple[int, float]:
        """``(m, h)``: the set-points streamed over ``duration`` s, ``h = duration / m`` s
        apart (``rate_hz``, at least one)."""
        m = max(1, round(duration * self.cfg.rate_hz))
        return m, duration / m

    def _clip(self, q: Array, q_new: Array, v_new: Array, h: float) -> tuple[Array, Array]:
        """``q_new`` clipped to the limits; a clipped joint's velocity the clipped step from
        ``q`` over ``h``."""
        q_clip = np.clip(q_new, self.q_lo, self.q_hi)
        return q_clip, np.where(q_clip != q_new, (q_clip - q) / h, v_new)

    def _intercept_step(
        self, seg: Segment, q: Array, v: Array, t: float, h: float, a: Array | None
    ) -> tuple[Array, Array, Array]:
        """The intercept segment's next set-point (:meth:`step`); on an
        :class:`InterceptError` the second-order limiter toward the moving goal."""
        assert seg.q_goal is not None
        acc = np.zeros(6) if a is None else a
        lim = self.ilim
        state = StreamState(
            q,
            np.clip(v, -lim.qd_max, lim.qd_max),
            np.clip(acc, -lim.qdd_max, lim.qdd_max),
        )
        try:
            new, _ = intercept_step(
                state,
                seg.q_goal + seg.v_goal * t,
                seg.v_goal,
                h,
                lim,
                min_duration=seg.min_duration,
            )
            q_clip, v_new = self._clip(q, new.q, new.v, h)
            return q_clip, v_new, new.a
        except InterceptError:  # fall back on the second-order limiter
            goal = seg.q_goal + seg.v_goal * (t + h)
            q_new, v_new = limit_setpoint(q, v, goal, h, self.limits, seg.v_goal)
            q_clip, v_new = self._clip(q, q_new, v_new, h)
            return q_clip, v_new, (v_new - v) / h

    def step(
        self, q: Array, v: Array, t: float, h: float, a: Array | None = None
    ) -> tuple[Array, Array, Array]:
        """The stream's set-point and velocity ``h`` s after ``(q, v)`` (both (6,)), ``t`` s
        into the pending segment: toward its velocity at the acceleration limits
        (:func:`limit_acceleration`, the direction of the change kept), or toward its goal
        (:func:`limit_setpoint`, the goal ``q_goal - v_goal (T - t')`` at the sub-step's end
        ``t'``); past the segment's duration ``T`` (no new one sent): braking to rest; an
        intercept segment (``a`` the stream's acceleration (6,)) goes on meeting its moving
        goal. Returns ``(q, v, a)``."""
        seg = self.seg
        if seg is not None and seg.intercept and seg.q_goal is not None:
            return self._intercept_step(seg, q, v, t, h, a)
        if seg is None or t >= seg.duration - 1e-9:
            v_new = limit_acceleration(v, np.zeros(6), h, self.limits)
            q_new = q + v_new * h
        elif seg.q_goal is None:
            v_new = limit_acceleration(v, seg.v_des, h, seg.limits)
            q_new = q + v_new * h
        else:
            goal = seg.q_goal - seg.v_goal * (seg.duration - (t + h))
            q_new, v_new = limit_setpoint(q, v, goal, h, seg.limits, seg.v_goal)
        q_clip, v_new = self._clip(q, q_new, v_new, h)
        return q_clip, v_new, (v_new - v) / h

    def resync(self) -> None:
        """When the clock moved on without the stream (the world stepped elsewhere: the
        gripper, a planned move) the arm held the last set-point's velocity one sub-step and
        stopped: the stream goes on from there at rest."""
        if self.clock is None or self.t is None or self.q is None:
            return
        if self.clock() - self.t > 1.5 * self.h + 1e-9:
            self.q = np.clip(self.q + self.v * self.h, self.q_lo, self.q_hi)
            self.v = np.zeros(6)
            self.a = np.zeros(6)
            self.t = None

    def plan(self, seg: Segment) -> Array:
        """Make ``seg`` the pending segment; returns the set-point at its end (the waits
        stream it, :meth:`streaming`)."""
        if self.q is None:
            raise InvalidInputError("no stream started")
        self.resync()
        self.seg, self.seg_t = seg, 0.0
        m, h = self.sub_steps(seg.duration)
        q, v, a = self.q, self.v, self.a
        for i in range(m):
            q, v, a = self.step(q, v, i * h, h, a)
        return q.copy()

    def send(self, qdot: Array, dt: float) -> Array:
        """Stream toward the joint velocity ``qdot`` (6,) rad/s for the control period ``dt``
        s, reached at the stream's acceleration limits (:func:`limit_acceleration`); the
        waits stream the set-points. Returns the set-point at the end of the period."""
        return self.plan(Segment(dt, np.asarray(qdot, float), self.limits))

    def send_toward(
        self, q_goal: Array, v_goal: Array | float, limits: JointLimits, dt: float
    ) -> Array:
        """Stream toward ``q_goal`` (6,) at the end of the control period ``dt`` s, a goal
        moving at ``v_goal`` (rad/s), within ``limits`` (:func:`limit_setpoint` every
        sub-step: lands on it when reachable, else brakes in time). Returns the set-point at
        the end of the period."""
        v_g = np.broadcast_to(np.asarray(v_goal, float), (6,)).copy()
        return self.plan(Segment(dt, np.zeros(6), limits, np.asarray(q_goal, float), v_g))

    def send_intercept(
        self, q_goal: Array, v_goal: Array, dt: float, min_duration: float = 0.0
    ) -> Array:
        """Stream the online intercept of ``q_goal`` (6,) moving at ``v_goal`` (6,) rad/s for
        the control period ``dt`` s (and on, until the next segment), each plan at least
        ``min_duration`` s; returns the set-point at the period's end."""
        seg = Segment(dt, np.zeros(6), self.limits, q_goal, v_goal, True, min_duration)
        return self.plan(seg)

    def streaming(
        self, arm: StreamingArm, wait: Callable[[float], None]
    ) -> Callable[[float], None]:
        """``wait`` that streams the pending segment meanwhile: every ``1 / rate_hz`` s
        (about) the next set-point goes to ``arm.command``, sent one sub-step ahead (the
        arm's interface holds a set-point's velocity until the next one)."""
        if getattr(wait, "streams", False):
            return wait

        def streaming_wait(duration: float) -> None:
            if self.q is None or duration <= 0:
                wait(duration)
                return
            self.resync()
            m, h = self.sub_steps(duration)
            for _ in range(m):
                self.q, self.v, self.a = self.step(self.q, self.v, self.seg_t, h, self.a)
                self.seg_t += h
                self.h = h
                arm.command(self.q)
                wait(h)
                self.t = self.clock() if self.clock is not None else None

        streaming_wait.streams = True  # type: ignore[attr-defined]
        return streaming_wait

    def move_to(
        self,
        arm: StreamingArm,
        q_cmd: Array,
        q_goal: Array,
        qd_max: Array,
        dt: float,
        wait: Callable[[float], None],
        until: Callable[[], bool],
    ) -> Array:
        """Stream set-points (control periods of ``dt`` s) from the stream's set-point
        (``q_cmd`` when none yet) to ``q_goal`` within the joint speed limits ``qd_max`` (6,)
        and the stream's acceleration limits, along the joint-space straight line when
        starting at rest (:func:`synchronized_limits`), braking to stop there; until there
        or ``until()``; returns the last set-point."""
        if self.q is None:
            self.start(q_cmd)
        assert self.q is not None
        wait = self.streaming(arm, wait)
        q_goal = np.clip(q_goal, self.q_lo, self.q_hi)
        lim = dataclasses.replace(self.limits, qd_max=qd_max)
        if np.all(np.abs(self.v) <= lim.qdd_max * dt):  # at rest: a straight line
            lim = synchronized_limits(self.q, q_goal, lim)
        q_cmd = self.q
        while np.max(np.abs(q_goal - q_cmd)) > 1e-6 and not until():
            q_cmd = self.send_toward(q_goal, 0.0, lim, dt)
            wait(dt)
        return q_cmd
