"""Universal Robots arm backend over RTDE (``ur-rtde``, the optional extra ``ur``).

:class:`URArm` implements :class:`mmpa.robot.interfaces.Arm` (plus the streaming
``command``) on a UR e-Series controller, keeping the limits contract of the protocol:

- every target and path is checked against the arm's position, velocity and acceleration
  limits (:mod:`mmpa.robot.limits`) before a single command is sent;
- ``speed_scale`` (the robot file's ``safety.speed_scale``, ``s`` in (0, 1]) slows every
  motion: ``moveJ`` at ``s`` times its speed and acceleration, paths played ``1/s`` times
  slower (joint velocities times ``s``, accelerations times ``s^2``), streamed set-points
  within ``s`` times the velocity and acceleration limits;
- ``move_joints`` is the controller's ``moveJ`` at ``speed_fraction * speed_scale`` of the
  slowest joint's velocity and acceleration limits;
- ``follow`` approaches the path's start with ``moveJ`` when the arm is away from it, then
  streams the path with ``servoJ`` at the controller's rate (``frequency``: 500 Hz on
  e-Series), timed by the controller's own ``initPeriod`` / ``waitPeriod``;
- ``command`` sets a streaming target that a background thread at the controller's rate
  follows through the same velocity and acceleration limiter as the twin
  (:func:`limit_setpoint`; ``qdd_max``, or the hard ``qdd_stream_max`` with
  ``stream_acceleration_limited`` off);
- a protective or emergency stop (read from RTDE receive) aborts a stream and refuses every
  motion with :class:`~mmpa.core.errors.MMPAError` until it is cleared on the pendant;
- a watchdog (``watchdog_s``, the robot file's ``safety.watchdog_s``): when the receive
  interface's controller timestamp has not moved for that long (counted in control
  periods), a stream, a path or a teaching recording stops with an error naming it;
- ``record_freedrive`` records a person's demonstration in teach mode (``teachMode`` /
  ``endTeachMode``), started and stopped by a key or a digital input
  (:class:`DigitalInputButton`).

``control`` and ``receive`` may be given (objects with ur-rtde's ``RTDEControlInterface`` /
``RTDEReceiveInterface`` methods); otherwise they are made from ``host``.
"""

from __future__ import annotations

import dataclasses
import logging
import threading
from collections.abc import Callable
from typing import Any

import numpy as np
from pydantic import BaseModel, ConfigDict, Field

from mmpa.core.errors import InvalidInputError, MMPAError
from mmpa.core.geometry import Array
from mmpa.robot.command_stream import CommandStream
from mmpa.robot.limits import (
    JointLimits,
    StreamLimitsSwitch,
    as_floats,
    check_path,
    check_target,
    limit_setpoint,
)

__all__ = ["DigitalInputButton", "URArm", "URConfig", "scaled_limits"]

_log = logging.getLogger(__name__)


class URConfig(BaseModel):
    """Connection and streaming parameters of :class:`URArm` (ur-rtde's names and units)."""

    model_config = ConfigDict(frozen=True, extra="forbid")

    host: str = "192.168.1.10"
    frequency: float = Field(500.0, gt=0, le=1000)  # Hz: e-Series 500, CB3 125
    speed_fraction: float = Field(0.5, gt=0, le=1)  # of the velocity/acceleration limits
    servo_lookahead: float = Field(0.1, ge=0.03, le=0.2)  # s, servoJ lookahead_time
    servo_gain: float = Field(300.0, ge=100, le=2000)  # servoJ gain
    approach_tolerance: float = Field(1e-3, gt=0)  # rad: farther from a path's start: moveJ
    stop_deceleration: float = Field(2.0, gt=0)  # rad/s^2 of servoStop / stopJ
    speed_scale: float = Field(1.0, gt=0, le=1)  # safety: of every speed and acceleration
    watchdog_s: float | None = Field(0.5, gt=0)  # s without new RTDE data: stop (None: off)


def scaled_limits(limits: JointLimits, s: float) -> JointLimits:
    """``limits`` with the velocity and acceleration limits (and the hard stream limit)
    times ``s``; positions unchanged."""
    hard = None if limits.qdd_stream_max is None else limits.qdd_stream_max * s
    return dataclasses.replace(
        limits, qd_max=limits.qd_max * s, qdd_max=limits.qdd_max * s, qdd_stream_max=hard
    )


class DigitalInputButton:
    """A button on one of the controller's digital inputs: calling it returns True once per
    press (a rising edge of input ``index`` since the last call)."""

    def __init__(self, receive: Any, index: int) -> None:
        self._receive, self.index = receive, int(index)
        self._last = bool(receive.getDigitalInState(self.index))

    def __call__(self) -> bool:
        now = bool(self._receive.getDigitalInState(self.index))
        pressed = now and not self._last
        self._last = now
        return pressed


class _Watchdog:
    """Counts control periods since the receive interface's timestamp last moved; raises
    when they exceed ``watchdog_s``."""

    def __init__(self, receive: Any, watchdog_s: float | None, dt: float) -> None:
        self._receive = receive
        self._limit = None if watchdog_s is None else max(1, int(np.ceil(watchdog_s / dt)))
        self._watchdog_s = watchdog_s
        self._last = receive.getTimestamp() if self._limit is not None else None
        self._still = 0

    def tick(self) -> None:
        if self._limit is None:
            return
        ts = self._receive.getTimestamp()
        if ts != self._last:
            self._last, self._still = ts, 0
            return
        self._still += 1
        if self._still >= self._limit:
            raise MMPAError(
                f"the UR controller stopped answering: no new RTDE data for "
                f"{self._watchdog_s} s (safety.watchdog_s); the motion was stopped"
            )


class URArm(StreamLimitsSwitch, CommandStream):
    """A UR arm over RTDE as an mmpa ``Arm`` (module docstring)."""

    def __init__(
        self,
        limits: JointLimits,
        cfg: URConfig | None = None,
        *,
        control: Any = None,
        receive: Any = None,
    ) -> None:
        self.cfg = cfg = cfg or URConfig()
        self.limits = limits
        if control is None or receive is None:
            try:
                import rtde_control
                import rtde_receive
            except ImportError as e:  # pragma: no cover - depends on the install
                raise MMPAError("the UR backend needs ur-rtde: pip install 'mmpa[ur]'") from e
            try:
                control = control or rtde_control.RTDEControlInterface(cfg.host, cfg.frequency)
                receive = receive or rtde_receive.RTDEReceiveInterface(cfg.host, cfg.frequency)
            except RuntimeError as e:  # pragma: no cover - needs a controller
                raise MMPAError(f"cannot connect to the UR controller at {cfg.host}: {e}") from e
        self._control, self._receive = control, receive
        self.receive = receive  # the digital inputs of the controller (DigitalInputButton)
        self._dt = 1.0 / cfg.frequency
        self._init_stream()
        self.stream_error: Exception | None = None
        #: the limits of the streamed set-points (``command``): ``limits`` times the speed
        #: scale (velocity and acceleration)
        self.stream_limits = scaled_limits(limits, cfg.speed_scale)

    @property
    def stream_acceleration_limited(self) -> bool:
        """True: streamed set-points within ``qdd_max`` (times the speed scale); False:
        within the hard stream limit ``qdd_stream_max`` (times the speed scale)."""
        s = self.cfg.speed_scale
        return bool(np.array_equal(self.stream_limits.qdd_max, self.limits.qdd_max * s))

    @stream_acceleration_limited.setter
    def stream_acceleration_limited(self, on: bool) -> None:
        self.stream_limits = scaled_limits(self.limits.stream(on), self.cfg.speed_scale)

    # ------------------------------------------------------------------ state
    def joint_positions(self) -> Array:
        """Encoder readings (rad), shape (6,)."""
        return np.asarray(self._receive.getActualQ(), dtype=float)

    def stopped(self) -> str | None:
        """Why the controller will not move (protective / emergency stop), or None."""
        if self._receive.isEmergencyStopped():
            return "emergency stop"
        if self._receive.isProtectiveStopped():
            return "protective stop"
        return None

    def _check_can_move(self) -> None:
        why = self.stopped()
        if why is not None:
            raise MMPAError(f"the UR arm is in {why}: clear it on the pendant, then retry")

    # ------------------------------------------------------------------ motions
    def move_joints(self, q: Array, duration: float | None = None) -> None:
        """``moveJ`` to ``q`` at ``speed_fraction`` of the limits (``duration`` ignored: the
        controller times the move)."""
        q = check_target(q, self.limits)
        self.stop_stream()
        self._check_can_move()
        f = self.cfg.speed_fraction * self.cfg.speed_scale
        speed = f * float(np.min(self.limits.qd_max))
        accel = f * float(np.min(self.limits.qdd_max))
        if not self._control.moveJ(q.tolist(), speed, accel):
            raise MMPAError(f"the UR controller refused moveJ ({self.stopped() or 'no reason'})")

    def follow(
        self, times: Array, q_path: Array, record_hz: float | None = None
    ) -> tuple[Array, Array] | None:
        """Stream ``q_path`` (T, 6) at ``times`` (T,) s with ``servoJ`` at the controller's
        rate (linear interpolation between samples), ``1 / speed_scale`` times slower than
        ``times``; with ``record_hz`` also read the encoders at that rate (of the path's
        own time) and return ``(t (M,), q (M, 6))``, ``t`` in the path's time."""
        times = as_floats(times, "follow: times")
        q_path = as_floats(q_path, "follow: q_path")
        check_path(times, q_path, self.limits)  # before anything moves
        if record_hz is not None and not (np.isfinite(record_hz) and record_hz > 0):
            raise InvalidInputError(f"record_hz must be a positive rate, got {record_hz}")
        self.stop_stream()
        self._check_can_move()
        if np.max(np.abs(q_path[0] - self.joint_positions())) > self.cfg.approach_tolerance:
            self.move_joints(q_path[0])
        s = self.cfg.speed_scale
        t_rel = times - times[0]
        step = self._dt * s  # path time per control period
        n = int(np.floor(t_rel[-1] / step + 1e-9)) + 1
        every = None if record_hz is None else max(1, round(1.0 / (record_hz * step)))
        rec_t: list[float] = []
        rec_q: list[Array] = []
        c = self._control
        dog = _Watchdog(self._receive, self.cfg.watchdog_s, self._dt)
        try:
            for k in range(n):
                t_start = c.initPeriod()
                dog.tick()
                t = min(k * step, t_rel[-1])
                q = np.array([np.interp(t, t_rel, q_path[:, j]) for j in range(6)])
                c.servoJ(
                    q.tolist(), 0.0, 0.0, self._dt, self.cfg.servo_lookahead, self.cfg.servo_gain
                )
                if every is not None and k % every == 0:
                    rec_t.append(t)
                    rec_q.append(self.joint_positions())
                if k % 25 == 0 and self.stopped() is not None:
                    raise MMPAError(f"the UR arm stopped during the path: {self.stopped()}")
                c.waitPeriod(t_start)
        finally:
            c.servoStop(self.cfg.stop_deceleration)
        if every is None:
            return None
        return np.array(rec_t), np.array(rec_q)

    # ------------------------------------------------------------------ teaching
    def record_freedrive(
        self,
        rate_hz: float,
        done: Callable[[], bool] | None = None,
        max_seconds: float = 600.0,
        *,
        button: Callable[[], bool] | None = None,
        gripper: Callable[[], float] | None = None,
    ) -> tuple[Array, Array, Array]:
        """A person's demonstration: teach mode on (``teachMode``: the person guides the
        arm by hand), the encoders read every control period, kept at ``rate_hz`` (the
        controller's clock), teach mode off.

        With ``button`` (True once per press: a key, :class:`DigitalInputButton`) the
        recording starts at the first press (``t = 0`` there) and ends at the first kept
        sample at or after the second press; ``done()`` (checked at each kept sample) ends
        it too. More than ``max_seconds`` of teach mode: :class:`MMPAError` (nothing kept).
        Returns ``t`` (N,) s from 0, ``q`` (N, 6) rad and the gripper state (N,) in [0, 1]
        read from ``gripper`` (0 without), for
        :func:`mmpa.missions.teach_repeat.trajectory_recorder`."""
        if not (np.isfinite(rate_hz) and 0 < rate_hz <= self.cfg.frequency):
            raise InvalidInputError(f"rate_hz must be in (0, {self.cfg.frequency}], got {rate_hz}")
        if button is None and done is None:
            raise InvalidInputError("record_freedrive needs a button or a done() to stop")
        self.stop_stream()
        self._check_can_move()
        c = self._control
        every = max(1, round(self.cfg.frequency / rate_hz))
        rec: list[tuple[float, Array, float]] = []
        dog = _Watchdog(self._receive, self.cfg.watchdog_s, self._dt)
        if not c.teachMode():
            raise MMPAError("the UR controller refused teach mode (freedrive)")
        try:
            k, k0, stop = 0, None if button is not None else 0, False
            while True:
                t_start = c.initPeriod()
                dog.tick()
                q = self.joint_positions()
                if k0 is None:
                    k0 = k if button is not None and button() else None
                elif button is not None and button():
                    stop = True
                if k0 is not None and (k - k0) % every == 0:
                    rec.append(((k - k0) * self._dt, q, 0.0 if gripper is None else gripper()))
                    if stop or (done is not None and done()):
                        break
                if k * self._dt > max_seconds:
                    raise MMPAError(
                        f"the demonstration did not end within {max_seconds:g} s of teach "
                        "mode (press the stop button / key)"
                    )
                k += 1
                c.waitPeriod(t_start)
        finally:
            c.endTeachMode()
        return (
            np.array([r[0] for r in rec]),
            np.array([r[1] for r in rec]),
            np.array([r[2] for r in rec]),
        )

    # ------------------------------------------------------------------ streaming
    def command(self, q: Array) -> None:
        """Streaming target (as ``servoJ`` from a slower loop): a background thread at the
        controller's rate moves the set-point toward ``q`` within ``stream_limits``
        (velocity and acceleration)."""
        q = check_target(q, self.limits)
        if self.stream_error is not None:
            raise MMPAError(f"the command stream stopped: {self.stream_error}")
        with self._lock:
            self._target = q.copy()
        if self._stream is None:
            self._check_can_move()
            self._stop.clear()
            self._stream = threading.Thread(target=self._run_stream, daemon=True, name="ur-servo")
            self._stream.start()

    def _run_stream(self) -> None:
        c = self._control
        q = self.joint_positions()
        v = np.zeros(6)
        try:
            dog = _Watchdog(self._receive, self.cfg.watchdog_s, self._dt)
            k = 0
            while not self._stop.is_set():
                t_start = c.initPeriod()
                dog.tick()
                with self._lock:
                    target = self._target
                if target is not None:
                    q, v = limit_setpoint(q, v, target, self._dt, self.stream_limits)
                    c.servoJ(
                        q.tolist(), 0.0, 0.0, self._dt, self.cfg.servo_lookahead,
                        self.cfg.servo_gain,
                    )  # fmt: skip
                if k % 25 == 0 and self.stopped() is not None:
                    raise MMPAError(f"the UR arm stopped: {self.stopped()}")
                k += 1
                c.waitPeriod(t_start)
        except Exception as e:  # reported to the caller at its next command
            self.stream_error = e
            _log.error("UR command stream stopped: %s", e)
        finally:
            c.servoStop(self.cfg.stop_deceleration)

    def stop(self) -> None:
        """Stop any motion now (``stopJ``)."""
        self.stop_stream()
        self._control.stopJ(self.cfg.stop_deceleration)

    def close(self) -> None:
        self.stop_stream()
        self._control.disconnect()

    def __enter__(self) -> URArm:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
