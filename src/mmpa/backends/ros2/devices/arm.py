"""The arm and gripper of a ROS 2 robot, as ``ur_robot_driver`` / ros2_control present them.

:class:`Ros2Arm` (a :class:`~mmpa.robot.interfaces.StreamingArm`):

- ``joint_positions()``: ``sensor_msgs/JointState`` on ``topics.joint_states``, the joints
  picked by name (``backend.ros2.joint_names``, the arm's order); a message with none of them
  (a gripper's own) is ignored, one lacking some is refused with a log line;
- ``move_joints(q)``: a minimum-jerk move from the encoders, ``s(tau) = 10 tau^3 - 15 tau^4 +
  6 tau^5``, whose duration ``T`` is the least that keeps every joint within the limits scaled
  by ``safety.speed_scale`` (peak velocity ``15/8 d/T``, peak acceleration ``10/sqrt(3) d/T^2``
  for a joint moving ``d`` rad; sampled at ``trajectory_rate_hz``, whose finite differences
  stay below those peaks), sent as one ``trajectory_msgs/JointTrajectory`` on
  ``topics.arm_trajectory`` (first point: the encoders at ``time_from_start`` 0);
- ``follow(times, q_path)``: the path checked against the limits
  (:func:`mmpa.robot.limits.check_path`), its times stretched by ``1 / speed_scale`` (the
  speed slider of ``scaled_joint_trajectory_controller``: velocities times ``s``,
  accelerations times ``s^2``), after an approach move when the arm is more than
  ``approach_tolerance`` from its start;
- each motion returns when the encoders are within ``goal_tolerance`` of its last point and
  have stayed there for the settle time; it fails (:class:`~mmpa.core.errors.MMPAError`) when
  they are not there ``goal_timeout_s`` after the planned end (a controller that refused the
  trajectory: see its log);
- ``command(q)``: the streaming target; a thread at ``stream_rate_hz`` moves the set-point
  toward it within ``stream_limits`` scaled by ``speed_scale``
  (:func:`mmpa.robot.limits.limit_setpoint`, ``dt`` the robot clock's elapsed time) and
  publishes each set-point as ``std_msgs/Float64MultiArray`` on ``topics.arm_stream`` (a
  ros2_control forward position controller applies it as it is);
- ``record_joint_states(rate_hz, button)``: a person's demonstration (the arm guided by
  hand or jogged on the teach pendant) as ``/joint_states`` showed it: every message stamped
  between two presses of a button (the robot's time when each press was seen), kept at
  ``rate_hz``, times from their stamps, whatever the messages' delivery latency;
- watchdog: ``/joint_states`` silent for ``safety.watchdog_s`` wall s stops the stream and
  fails any motion or command with a message naming the topic; ``stopped()`` says so.

Every target and path is checked against the limits before anything is sent
(:func:`~mmpa.robot.limits.check_target`, :func:`~mmpa.robot.limits.check_path`).

:class:`Ros2Gripper`: ``std_msgs/Float64`` on ``topics.gripper``, the finger gap in m (0
closed .. ``stroke`` open), as the twin node takes it; this topic has no feedback, so
``width()`` is the commanded gap and ``close()`` cannot tell a held object (False).
"""

from __future__ import annotations

import dataclasses
import math
import threading
import time
from collections import deque
from collections.abc import Callable
from typing import Any

import numpy as np
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy

from mmpa.backends.ros2.devices.node import DeviceTimeoutError, RobotNode, Ros2DeviceConfig
from mmpa.backends.ros2.localization_msgs import stamp_of
from mmpa.backends.ros2.messages import message_class
from mmpa.core.errors import InvalidInputError, MMPAError
from mmpa.core.geometry import Array
from mmpa.robot.backend_config import Ros2Topics, SafetyConfig
from mmpa.robot.command_stream import CommandStream
from mmpa.robot.interfaces import Clock, WallClock
from mmpa.robot.limits import (
    JointLimits,
    StreamLimitsSwitch,
    as_floats,
    check_path,
    check_target,
    limit_setpoint,
)

__all__ = ["Ros2Arm", "Ros2Gripper", "min_jerk_path", "scaled_limits"]

#: ``/joint_states``: best effort, volatile (matches any driver's publisher) as the sensor
#: data profile, but keep last 100 (2 s at 50 Hz, 0.2 s at 500 Hz): a recorded demonstration
#: loses no message while the executor catches up
JOINT_STATES_QOS = QoSProfile(
    depth=100, reliability=ReliabilityPolicy.BEST_EFFORT, durability=DurabilityPolicy.VOLATILE
)

#: peak |velocity| and |acceleration| of the minimum-jerk profile over a unit move in unit time
MIN_JERK_V = 15.0 / 8.0
MIN_JERK_A = 10.0 / math.sqrt(3.0)


def scaled_limits(limits: JointLimits, s: float) -> JointLimits:
    """``limits`` with the velocity and acceleration limits (and the hard stream limit)
    times ``s``; positions unchanged."""
    hard = None if limits.qdd_stream_max is None else np.asarray(limits.qdd_stream_max) * s
    return dataclasses.replace(
        limits, qd_max=limits.qd_max * s, qdd_max=limits.qdd_max * s, qdd_stream_max=hard
    )


def min_jerk_path(
    q0: Array, q1: Array, limits: JointLimits, min_duration: float, rate_hz: float
) -> tuple[Array, Array]:
    """A rest-to-rest minimum-jerk move ``q0 -> q1`` (module docstring) sampled at
    ``rate_hz``: ``(t (N,), q (N, 6))`` from ``t = 0`` at ``q0``; its duration the least
    within ``limits``, at least ``min_duration`` s."""
    d = np.abs(np.asarray(q1, float) - np.asarray(q0, float))
    T = max(
        float(min_duration),
        float(np.max(MIN_JERK_V * d / limits.qd_max)),
        float(np.max(np.sqrt(MIN_JERK_A * d / limits.qdd_max))),
    )
    if T <= 0.0:
        return np.array([0.0]), np.asarray(q1, float)[None]
    n = max(2, math.ceil(T * rate_hz))
    t = np.linspace(0.0, T, n + 1)
    tau = t / T
    s = tau**3 * (10.0 - 15.0 * tau + 6.0 * tau**2)
    return t, np.asarray(q0, float) + s[:, None] * (np.asarray(q1, float) - q0)


def _joint_reader(names: tuple[str, ...]) -> Any:
    """A ``JointState`` -> ``(stamp s, q (6,))`` in ``names``' order (None: none of them)."""

    def read(msg: Any) -> tuple[float, Array] | None:
        idx = {n: i for i, n in enumerate(msg.name)}
        missing = [n for n in names if n not in idx]
        if len(missing) == len(names):
            return None  # another device's joints (a gripper's own message)
        if missing:
            raise InvalidInputError(
                f"lacks the joints {missing} (it names {list(msg.name)}): set "
                "backend.ros2.joint_names in the robot file"
            )
        pos = np.asarray(msg.position, float)
        q = pos[[idx[n] for n in names]]
        if not np.all(np.isfinite(q)):
            raise InvalidInputError(f"a joint position is NaN or infinite: {q.tolist()}")
        return stamp_of(msg.header), q

    return read


def _between(msgs: list[Any], t_on: float, t_off: float, dt: float) -> list[Any]:
    """The ``(stamp, q)`` of ``msgs`` stamped in ``(t_on, t_off]``, in stamp order, each
    object once, thinned: one is kept when its stamp is at least ``0.75 dt`` after the last
    kept one."""
    seen: set[int] = set()
    window = []
    for m in msgs:
        if id(m) not in seen and t_on < m[0] <= t_off:
            seen.add(id(m))
            window.append(m)
    kept: list[Any] = []
    for m in sorted(window, key=lambda m: m[0]):
        if not kept or m[0] - kept[-1][0] >= dt * 0.75:
            kept.append(m)
    return kept


def _last_poll(polls: list[tuple[float, float]], stamp: float) -> float:
    """The value of the last poll ``(stamp, value)`` at or before ``stamp`` (the first
    one before them all)."""
    k = max(0, int(np.searchsorted([p[0] for p in polls], stamp, side="right")) - 1)
    return polls[k][1] if polls else 0.0


def _duration(msg: Any, t: float) -> None:
    ns = round(t * 1e9)
    msg.sec, msg.nanosec = divmod(ns, 1_000_000_000)


class Ros2Arm(StreamLimitsSwitch, CommandStream):
    """The arm of a ROS 2 robot (module docstring). ``limits``: the arm's joint limits
    (checked before sending); ``clock``: the robot's clock; ``timeout``: wall s to wait for
    the first ``/joint_states`` and for the controllers' subscriptions."""

    def __init__(
        self,
        node: RobotNode,
        topics: Ros2Topics,
        joint_names: tuple[str, ...],
        limits: JointLimits,
        clock: Clock,
        safety: SafetyConfig,
        cfg: Ros2DeviceConfig,
        timeout: float,
    ) -> None:
        if len(joint_names) != 6:
            raise InvalidInputError(f"the arm needs 6 joint names, got {list(joint_names)}")
        self._node, self._clock, self._cfg, self._timeout = node, clock, cfg, timeout
        self.names = tuple(joint_names)
        self.limits = limits
        self.stream_limits = limits
        self.speed_scale = float(safety.speed_scale)
        self.watchdog_s = float(safety.watchdog_s)
        self.joints = node.subscribe(
            "arm", topics.joint_states, "sensor_msgs/msg/JointState", JOINT_STATES_QOS,
            keep=JOINT_STATES_QOS.depth, convert=_joint_reader(self.names),
        )  # fmt: skip
        traj, stream = topics.arm_trajectory, topics.arm_stream
        T = "trajectory_msgs/msg/JointTrajectory"
        self._traj = node.publisher(traj, T) if traj else None
        self._stream_pub = (
            node.publisher(stream, "std_msgs/msg/Float64MultiArray") if stream else None
        )
        self._matched: set[str] = set()
        self._init_stream()
        self.stream_error: Exception | None = None
        #: what was published, newest last: ``(kind, t, q)``, kind "trajectory" or "stream"
        self.sent: deque[tuple[str, Array, Array]] = deque(maxlen=10_000)
        #: the last recording's presses ``(t_on, t_off)``, s in the stamps' time base
        self.presses: tuple[float, float] | None = None

    # ------------------------------------------------------------------ state
    def joint_positions(self) -> Array:
        """Encoder readings (rad), shape (6,)."""
        self._node.first(self.joints, self._timeout)
        self._watch()
        return self.joints.msg[1].copy()

    def _silent(self) -> str | None:
        age = self.joints.age()
        if self.joints.count and age > self.watchdog_s:
            return (
                f"no {self.joints.topic} for {age:.2f} s (watchdog {self.watchdog_s:g} s): "
                "the controller or its node stopped answering"
            )
        return None

    def _watch(self) -> None:
        why = self._silent()
        if why is not None:
            self.stop_stream()
            raise DeviceTimeoutError(f"arm: {why}")

    def stopped(self) -> str | None:
        """Why the arm will not move: the watchdog's reason or the stream's error, or None
        (this backend reads no safety-mode topic)."""
        if self.stream_error is not None:
            return f"the command stream stopped: {self.stream_error}"
        return self._silent()

    def _publisher(self, pub: Any, what: str) -> Any:
        if pub is None:
            raise InvalidInputError(f"arm: this robot has no {what} topic (it is '')")
        if pub.topic_name not in self._matched:
            self._node.wait_subscriber("arm", pub, self._timeout)
            self._matched.add(pub.topic_name)
        return pub

    # ------------------------------------------------------------------ motions
    def move_joints(self, q: Array, duration: float | None = None) -> None:
        """A minimum-jerk move to ``q`` (rad, (6,)) within the scaled limits (at least
        ``duration`` s), waited for (module docstring)."""
        q = check_target(q, self.limits)
        if duration is not None and not (np.isfinite(duration) and duration >= 0):
            raise InvalidInputError(
                f"move duration must be a finite number of seconds >= 0 (or None), got {duration}"
            )
        self.stop_stream()
        q0 = self.joint_positions()
        lim = scaled_limits(self.limits, self.speed_scale)
        t, path = min_jerk_path(q0, q, lim, duration or 0.0, self._cfg.trajectory_rate_hz)
        self._run(t, path, self._cfg.move_settle_s)

    def follow(
        self, times: Array, q_path: Array, record_hz: float | None = None
    ) -> tuple[Array, Array] | None:
        """Track ``q_path`` (T, 6) at ``times`` (T,) s, stretched by ``1 / speed_scale``;
        with ``record_hz`` also the encoders at that rate (at most ``/joint_states``'),
        ``(t (M,) s from the start, q (M, 6))``."""
        times = as_floats(times, "follow: times")
        q_path = as_floats(q_path, "follow: q_path")
        if q_path.ndim != 2 or q_path.shape[1] != 6 or times.shape != (q_path.shape[0],):
            raise InvalidInputError(
                f"need times (T,) and q_path (T, 6), got {times.shape}, {q_path.shape}"
            )
        if record_hz is not None and not (np.isfinite(record_hz) and record_hz > 0):
            raise InvalidInputError(f"record_hz must be a positive rate, got {record_hz}")
        check_path(times, q_path, self.limits)  # before anything is sent
        self.stop_stream()
        if np.max(np.abs(q_path[0] - self.joint_positions())) > self._cfg.approach_tolerance:
            self.move_joints(q_path[0])
        t = (times - times[0]) / self.speed_scale
        return self._run(t, q_path, self._cfg.follow_settle_s, record_hz)

    def _message(self, t: Array, q: Array) -> Any:
        msg = message_class("trajectory_msgs/msg/JointTrajectory")()
        Point = message_class("trajectory_msgs/msg/JointTrajectoryPoint")
        msg.joint_names = list(self.names)
        points = []
        for tk, qk in zip(t.tolist(), q.tolist(), strict=True):
            p = Point()
            p.positions = qk
            _duration(p.time_from_start, tk)
            points.append(p)
        msg.points = points
        return msg

    def _run(
        self, t: Array, q: Array, settle: float, record_hz: float | None = None
    ) -> tuple[Array, Array] | None:
        """Send the trajectory ``(t, q)`` (``t[0] = 0``) and wait for its end (module
        docstring); the encoders at ``record_hz`` while it runs when asked."""
        if len(t) < 2:  # already there
            return None if record_hz is None else (np.zeros(1), self.joint_positions()[None])
        check_path(t, q, self.limits, "arm trajectory")
        pub = self._publisher(self._traj, "trajectory")
        self._watch()
        t0 = self._clock.time
        pub.publish(self._message(t, q))
        self.sent.append(("trajectory", t.copy(), q.copy()))
        return self._wait(t0, float(t[-1]), q[-1], settle, record_hz)

    def _wait(
        self, t0: float, t_end: float, q_end: Array, settle: float, record_hz: float | None
    ) -> tuple[Array, Array] | None:
        cfg, J = self._cfg, self.joints
        rec_t: list[float] = []
        rec_q: list[Array] = []
        arrived: float | None = None
        while True:
            seen = J.count
            if not J.wait(lambda seen=seen: J.count > seen, self.watchdog_s):
                self._watch()
            now = self._clock.time - t0
            q_enc = J.msg[1]
            if record_hz is not None and now <= t_end and now >= len(rec_t) / record_hz:
                rec_t.append(now)
                rec_q.append(q_enc.copy())
            err = float(np.max(np.abs(q_enc - q_end)))
            if now >= t_end and err <= cfg.goal_tolerance:
                arrived = now if arrived is None else arrived
                if now - arrived >= settle:
                    break
            else:
                arrived = None
            if now > t_end + cfg.goal_timeout_s + settle:
                j = int(np.argmax(np.abs(q_enc - q_end)))
                raise MMPAError(
                    f"arm: not at the trajectory's end {now - t_end:.1f} s after it: joint "
                    f"{j + 1} ({self.names[j]}) is {err:.4f} rad off (tolerance "
                    f"{cfg.goal_tolerance:g}); did the controller on {self._traj.topic_name} "
                    "refuse it (see its log)?"
                )
        return None if record_hz is None else (np.array(rec_t), np.array(rec_q))

    # ------------------------------------------------------------------ teaching
    def record_joint_states(
        self,
        rate_hz: float,
        button: Callable[[], bool],
        max_seconds: float = 600.0,
        gripper: Callable[[], float] | None = None,
    ) -> tuple[Array, Array, Array]:
        """A person's demonstration seen on ``/joint_states`` (module docstring).

        ``button`` (True once per press) is polled every ``1 / rate_hz`` s of the robot's
        clock; a press's time ``t_on`` / ``t_off`` is :meth:`stamp_time` when it is seen
        (:attr:`presses`). Kept: every message stamped in ``(t_on, t_off]`` (decided by the
        stamps, not by arrival: the last ``JOINT_STATES_QOS.depth`` messages before the first
        press count too, and after the second the recording waits up to
        ``safety.watchdog_s`` wall s for a message stamped at or after ``t_off``), thinned to
        ``rate_hz`` (kept when its stamp is at least ``1 / rate_hz`` minus a quarter period
        after the last kept one: every message when the arm publishes at ``rate_hz`` or
        slower). Returns ``t`` (N,) s from the first kept stamp, ``q`` (N, 6) rad, and the
        gripper state (N,) in [0, 1] polled from ``gripper`` (0 without) at the last poll at
        or before each sample's stamp. Over ``max_seconds`` of the robot's clock:
        :class:`MMPAError`; the watchdog as every motion's."""
        if not (np.isfinite(rate_hz) and rate_hz > 0):
            raise InvalidInputError(f"rate_hz must be a positive rate, got {rate_hz}")
        dt = 1.0 / float(rate_hz)
        self.stop_stream()
        _, t_on = self._wait_press(button, dt, max_seconds, "start")
        J = self.joints
        tapped = J.tap()
        try:
            before = [m for _, m in J.snapshot()]  # arrived before the tap: stamped later?
            self._check_time_base(t_on, float(J.msg[0]))
            polls, t_off = self._wait_press(button, dt, max_seconds, "end", gripper)
            J.wait(lambda: J.msg[0] >= t_off, self.watchdog_s)  # the last one on its way
            self._watch()
        finally:
            J.untap(tapped)
        self.presses = (t_on, t_off)
        kept = _between(before + tapped, t_on, t_off, dt)
        if len(kept) < 2:
            raise MMPAError(
                f"arm: {len(kept)} /joint_states sample(s) stamped between the presses "
                f"({t_on:.3f} s, {t_off:.3f} s; the latest message is stamped "
                f"{float(J.msg[0]):.3f} s): press, guide the arm, press again (is the driver "
                "publishing, are its clock and this computer's synchronized?)"
            )
        t = np.array([m[0] for m in kept])
        q = np.array([np.asarray(m[1], float) for m in kept])
        g = np.array([_last_poll(polls, stamp) for stamp in t])
        return t - t[0], q, g

    def _check_time_base(self, now: float, stamp: float) -> None:
        """Refuse stamps more than ``safety.watchdog_s`` from :meth:`stamp_time` (another
        time base: unsynchronized clocks, a simulator's stamps without ``use_sim_time``)."""
        if abs(now - stamp) > self.watchdog_s:
            raise MMPAError(
                f"arm: the latest /joint_states is stamped {stamp:.3f} s, {now - stamp:+.3f} s "
                f"from the robot's time {now:.3f} s (over the watchdog's {self.watchdog_s:g} "
                "s): synchronize the driver's clock with this computer's, or set "
                "backend.ros2.use_sim_time for a simulator's /clock"
            )

    def stamp_time(self) -> float:
        """Now in the time base of the messages' stamps (s): the robot's clock when it is
        ``/clock`` (a simulator, a bag), else ROS time (the system clock, as a driver stamps
        with it: its computer and this one synchronized)."""
        return time.time() if isinstance(self._clock, WallClock) else self._clock.time

    def _wait_press(
        self,
        button: Callable[[], bool],
        dt: float,
        max_seconds: float,
        what: str,
        gripper: Callable[[], float] | None = None,
    ) -> tuple[list[tuple[float, float]], float]:
        """Poll ``button`` every ``dt`` s of the robot's clock until it is pressed: the
        gripper's polls ``(stamp time, state)`` on the way, and the press's stamp time (read
        just before the button: at or before the press was seen)."""
        start = self._clock.time
        polls: list[tuple[float, float]] = []
        while True:
            self.joint_positions()  # the first message waited for, the watchdog checked
            now = self.stamp_time()
            polls.append((now, 0.0 if gripper is None else gripper()))
            if button():
                return polls, now
            if self._clock.time - start > max_seconds:
                raise MMPAError(f"arm: the demonstration did not {what} within {max_seconds:g} s")
            self._clock.step(dt)

    # ------------------------------------------------------------------ streaming
    def command(self, q: Array) -> None:
        """Streaming target ``q`` (rad, (6,)); returns at once (module docstring)."""
        q = check_target(q, self.limits)
        if self.stream_error is not None:
            raise MMPAError(f"arm: the command stream stopped: {self.stream_error}")
        self._publisher(self._stream_pub, "streaming (arm_stream)")
        self._watch()
        with self._lock:
            self._target = q.copy()
        if self._stream is None:
            self._stop.clear()
            self._stream = threading.Thread(target=self._run_stream, daemon=True, name="ros2-arm")
            self._stream.start()

    def _run_stream(self) -> None:
        q, v = self.joint_positions(), np.zeros(6)
        t_prev = self._clock.time
        msg = message_class("std_msgs/msg/Float64MultiArray")()
        period = 1.0 / self._cfg.stream_rate_hz
        try:
            while not self._stop.is_set():
                why = self._silent()
                if why is not None:
                    raise DeviceTimeoutError(f"arm: {why}")
                now = self._clock.time
                with self._lock:
                    target = self._target
                if target is not None and now > t_prev:
                    lim = scaled_limits(self.stream_limits, self.speed_scale)
                    q, v = limit_setpoint(q, v, target, now - t_prev, lim)
                    msg.data = q.tolist()
                    self._stream_pub.publish(msg)
                    self.sent.append(("stream", np.array([now]), q[None].copy()))
                t_prev = now
                time.sleep(period)
        except MMPAError as e:  # reported at the next command
            self.stream_error = e
            self._node.node.get_logger().error(f"arm command stream stopped: {e}")

    def stop(self) -> None:
        self.stop_stream()

    def close(self) -> None:
        self.stop_stream()


class Ros2Gripper:
    """A gripper over ``std_msgs/Float64`` finger gaps (module docstring)."""

    def __init__(
        self,
        node: RobotNode,
        topic: str,
        stroke: float,
        clock: Clock,
        cfg: Ros2DeviceConfig,
        timeout: float,
    ) -> None:
        self._node, self._clock, self._cfg, self._timeout = node, clock, cfg, timeout
        self.stroke = float(stroke)
        self.pub = node.publisher(topic, "std_msgs/msg/Float64")
        self._gap = self.stroke
        self._matched = False

    def _send(self, gap: float) -> None:
        if not self._matched:
            self._node.wait_subscriber("gripper", self.pub, self._timeout)
            self._matched = True
        msg = message_class("std_msgs/msg/Float64")()
        msg.data = float(gap)
        self.pub.publish(msg)
        self._gap = float(gap)
        self._clock.step(self._cfg.gripper_s)

    def open(self) -> None:
        self._send(self.stroke)

    def close(self) -> bool:
        """Close; False: this topic tells nothing of a held object."""
        self._send(0.0)
        return False

    def width(self) -> float:
        """The commanded finger gap (m): the topic has no feedback."""
        return self._gap
