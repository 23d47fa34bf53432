"""The tracking grasp (paper 001 §3.2.2, Fig. 5, §4.3.3): detect, servo, approach, close, lift.

:class:`TrackingGrasp` runs over the robot interfaces (a
:class:`~mmpa.robot.interfaces.StreamingArm`, a gripper, an RGB-D camera, a base) and a
``wait(dt)`` clock (the twin steps its physics; a real robot sleeps). Each tick
(``track.rate_hz``): capture, detect the named object and locate it in ``arm_base`` (m,
nominal kinematics; :mod:`mmpa.servo.tracker`), update the constant-velocity Kalman filter,
and run IBVS (eq. 10-12, :mod:`mmpa.servo.ibvs`) toward the tracking point ``ibvs.standoff``
above the object with the object's estimated velocity as feed-forward, plus the null-space
manipulability term (eq. 13-14, :mod:`mmpa.servo.nullspace`). When the error stays small
(and, with the predictor, the object has moved predictably for ``track.steady_ticks``) the
tracking goes on at ``track.final_standoff``, then the TCP descends to the grasp height
(:mod:`mmpa.servo.descent`), the gripper closes as soon as the encoders say the TCP arrived,
and the arm lifts. An object out of view: wait for it to reappear (the paper's behaviour),
backing up to the tracking standoff over where it was last seen (``track.reacquire``), after
following the prediction for ``track.coast_time``; not seen at all: second views
(:mod:`mmpa.servo.search`). The base creeps forward when the object lies beyond
``track.reach_limit``. Every set-point is streamed within the joint limits
(:mod:`mmpa.servo.stream`). A missed grasp is tried again (``close.max_attempts``).

Settings: :class:`mmpa.servo.config.GraspConfig` (:meth:`~mmpa.servo.config.GraspConfig.paper`
for the paper's grasp). Measurements and trial notes: ``docs/servo.md``.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from mmpa.core.errors import InvalidInputError, MMPAError, UnknownNameError, UnreachableError
from mmpa.core.geometry import Array, apply, inv
from mmpa.robot.description import RobotDescription
from mmpa.robot.interfaces import Base, Camera, Gripper, MobileManipulator, StreamingArm, require
from mmpa.robot.kinematics import fk, ik_nearest, jacobian
from mmpa.servo.config import GraspConfig
from mmpa.servo.descent import Descent
from mmpa.servo.ibvs import (
    camera_velocity,
    desired_point,
    limit_velocity,
    orientation_velocity,
    pinv,
)
from mmpa.servo.nullspace import manipulability_gradient, null_space_projector
from mmpa.servo.pose import ArmGeometry, grasp_yaw, intercept_goal, look_configuration, tool_down
from mmpa.servo.predictor import ConstantVelocityKF
from mmpa.servo.search import Search
from mmpa.servo.stream import Stream
from mmpa.servo.tracker import (
    SYMMETRIC,
    Detector,
    Measurement,
    Perception,
    intercepting,
    is_fast,
    is_moving,
    still_line,
)

__all__ = ["GraspConfig", "GraspResult", "TrackingGrasp", "look_configuration"]

Wait = Callable[[float], None]


@dataclass
class GraspResult:
    """``closed_on_object``: the fingers stopped on something and still hold it after the
    lift (the last attempt); ``reason``: "grasped", "missed", "not found", "unreachable",
    "timeout", "depth"; times in s. ``found_view``: where the target was first found: 0 the
    starting view, k >= 1 the k-th second view taken
    (``GraspConfig.search.views``), -1 never; ``views``: second views taken; ``descent_s``:
    s from the start of the (last) descent to its close (NaN: no descent); ``attempts``:
    closes of the gripper (``GraspConfig.close.max_attempts``)."""

    closed_on_object: bool
    reason: str
    detected_first: bool
    time_to_grasp: float
    ticks: int
    lost_ticks: int
    detect_ms: list[float] = field(default_factory=list)
    capture_ms: list[float] = field(default_factory=list)
    loop_s: list[float] = field(default_factory=list)
    found_view: int = -1
    views: int = 0
    descent_s: float = float("nan")
    attempts: int = 0


@dataclass
class _Devices:
    """One run's devices, clock and event callback."""

    name: str
    arm: StreamingArm
    gripper: Gripper
    camera: Camera
    base: Base
    wait: Wait
    clock: Callable[[], float]
    on_event: Callable[[str], None] | None


@dataclass
class _RunState:
    """One run's track: the set-point ``q_cmd`` (6,) rad, the predictor, the last measured
    point ``p_meas`` (3,) m ``arm_base``, the object's top and desk heights (m), the grasp
    ``yaw`` (rad), the tracking ``standoff`` (m), the innovations (m) and the measurements of
    the still window ``hist`` ((time s, point))."""

    res: GraspResult
    kf: ConstantVelocityKF
    q_cmd: Array
    t0: float
    standoff: float
    last_seen: float = -np.inf
    p_meas: Array | None = None
    desk_z: float | None = None
    top_z: float | None = None
    yaw: float | None = None
    aligned: int = 0
    lost_close: bool = False
    ticks: int = 0
    lost: int = 0
    first: bool | None = None
    searched: bool = False
    innovations: list[float] = field(default_factory=list)
    hist: list[tuple[float, Array]] = field(default_factory=list)


class TrackingGrasp:
    """The tracking grasp: :class:`~mmpa.servo.tracker.Perception`,
    :class:`~mmpa.servo.search.Search`, :class:`~mmpa.servo.descent.Descent` over one
    :class:`~mmpa.servo.stream.Stream`, composed by :meth:`run`."""

    def __init__(
        self, detector: Detector, robot: RobotDescription, cfg: GraspConfig | None = None
    ) -> None:
        self.robot = robot
        self.cfg = cfg = cfg or GraspConfig()
        self.geom = ArmGeometry.of(robot, cfg.stream.joint_margin)
        self._P_star = desired_point(self.geom.T_fc, self.geom.T_ft, cfg.ibvs.standoff)
        self._qd = np.asarray(robot.arm.qd_max) * cfg.ibvs.joint_speed_fraction
        self.perception = Perception(detector, self.geom, cfg.detect)
        self.stream = Stream(self.geom, cfg.stream, cfg.intercept)
        self.search = Search(self.perception, self.stream, cfg, self._qd)
        self.descent = Descent(self.geom, self.perception, self.stream, cfg)

    @property
    def det(self) -> Detector:
        return self.perception.det

    @property
    def limited(self) -> bool:
        """Whether the stream keeps qdd_max now (``stream.accel_limit``)."""
        return self.stream.limited

    def _moving(self, v_obj: Array | None) -> bool:
        return is_moving(v_obj, self.cfg.track.final_standoff_max_speed)

    def servo_step(
        self,
        q_cmd: Array,
        p_obj: Array,
        v_obj: Array | None,
        yaw: float | None,
        dt: float,
        standoff: float | None = None,
    ) -> tuple[Array, Array]:
        """One IBVS + null-space step from set-point ``q_cmd`` toward object ``p_obj``
        (arm_base) with the tracking point ``standoff`` m above it (default: the config's);
        returns ``(q_next, [lateral error, depth error] m)``."""
        cfg, geom = self.cfg, self.geom
        dh = geom.dh
        T_fl = fk(dh, q_cmd)
        T_cam = T_fl @ geom.T_fc
        P = apply(inv(T_cam), p_obj)
        if P[2] <= 0.05:
            raise UnreachableError("the object is behind or too close to the camera")
        P_star = self._P_star if standoff is None else desired_point(geom.T_fc, geom.T_ft, standoff)
        gain = cfg.ibvs.moving_gain if self._moving(v_obj) else cfg.ibvs.gain
        v_cam = camera_velocity(P, P_star, gain)
        n = np.linalg.norm(v_cam)
        if n > cfg.ibvs.max_linear_speed:
            v_cam *= cfg.ibvs.max_linear_speed / n
        R_tool = T_fl[:3, :3] @ geom.T_ft[:3, :3]
        if yaw is None:  # keep the current heading of the tool x axis
            x = R_tool[:, 0]
            yaw_now = float(np.arctan2(x[1], x[0]))
        else:
            yaw_now = yaw
        w = orientation_velocity(R_tool, tool_down(yaw_now), cfg.ibvs.orientation_gain)
        v = T_cam[:3, :3] @ v_cam
        if v_obj is not None:
            v = v + v_obj
        J = jacobian(dh, q_cmd, geom.T_fc)
        if yaw is None and cfg.track.null_gain > 0:  # 5-D task, eq. 13 in the free yaw
            Jt = J[:5]
            qdot = pinv(Jt, cfg.ibvs.damping) @ np.concatenate([v, w[:2]])
            g = manipulability_gradient(dh, q_cmd, geom.T_ft)
            qdot += null_space_projector(Jt, cfg.ibvs.damping) @ (cfg.track.null_gain * g)
        else:
            qdot = pinv(J, cfg.ibvs.damping) @ np.concatenate([v, w])
        qdot = limit_velocity(qdot, self._qd)
        lateral = P[:2] - P_star[:2] * P[2] / P_star[2]
        return q_cmd + qdot * dt, np.array([np.linalg.norm(lateral), abs(P[2] - P_star[2])])

    def run(
        self,
        name: str,
        robot: MobileManipulator,
        wait: Wait | None = None,
        on_event: Callable[[str], None] | None = None,
    ) -> GraspResult:
        """Track and grasp the object called ``name``; the arm starts at a view of the desk.

        Phases: track at ``ibvs.standoff`` above the object's top, then at the final standoff
        once aligned; when aligned again, the descent (the object's predicted motion
        followed, the grasp height from the top and the desk), close, lift. ``on_event`` gets
        "descend" and "close" when those phases start, and "retry" when the gripper opens
        again after a missed grasp (``close.max_attempts``). Raises
        :class:`~mmpa.core.errors.InvalidInputError` for a robot without an arm, gripper,
        wrist camera or base, or whose arm is no :class:`~mmpa.robot.interfaces.StreamingArm`.
        ``wait(dt)`` advances the robot's time by ``dt`` s (default ``robot.step``; a caller
        that moves things meanwhile passes its own); the base is held still."""
        classes = self.det.cfg.classes
        if name not in classes:
            raise UnknownNameError("object", name, list(classes))
        require(robot, "arm", "gripper", "camera", "base", mission="the tracking grasp")
        arm, gripper, camera, base = robot.arm, robot.gripper, robot.camera, robot.base
        assert gripper is not None and camera is not None and base is not None
        wait = robot.step if wait is None else wait

        def clock() -> float:
            return robot.time

        if not isinstance(arm, StreamingArm):
            raise InvalidInputError(
                "the tracking grasp needs a StreamingArm (streaming command(q), limits, "
                f"stream_limits, stream_acceleration_limited, stopped()), got {type(arm).__name__}"
            )
        cfg = self.cfg
        self.stream.clock = clock
        self.stream.set_limited(arm, cfg.stream.accel_limit != "never")
        wait = self.stream.streaming(arm, wait)  # set-points at stream.rate_hz between ticks
        q_cmd = self.stream.start(arm.joint_positions())
        res = GraspResult(False, "timeout", False, float("nan"), 0, 0)
        s = _RunState(res, ConstantVelocityKF(cfg.predictor), q_cmd, clock(), cfg.ibvs.standoff)
        dev = _Devices(name, arm, gripper, camera, base, wait, clock, on_event)
        gripper.open()
        while clock() - s.t0 < cfg.max_time:
            if self._tick(s, dev):
                break
        base.stop()
        res.detected_first = bool(s.first)
        res.ticks, res.lost_ticks = s.ticks, s.lost
        if res.reason == "timeout" and res.attempts:
            res.reason = "missed"  # and no time left for another attempt
        if res.reason == "timeout" and s.p_meas is None:
            res.reason = "not found"
        return res

    def _out_of_time(self, s: _RunState, dev: _Devices) -> bool:
        return dev.clock() - s.t0 >= self.cfg.max_time

    def _tick(self, s: _RunState, dev: _Devices) -> bool:
        """One control tick: observe, then wait for a lost object or track it (and grasp
        when aligned). True: the run ends."""
        cfg = self.cfg
        dt = 1.0 / cfg.track.rate_hz
        w0 = time.perf_counter()
        meas = self._observe(s, dev)
        now = dev.clock()
        if meas is not None:
            self._take(s, meas, dev.name, now)
        else:
            s.lost += 1
            s.innovations.append(float("inf"))
        tc = cfg.track
        coasting = tc.use_predictor and s.kf.initialized and now - s.last_seen < tc.coast_time
        line = still_line(s.hist, tc) if tc.use_predictor else None
        # a still object unseen for a while stays where its line says (improvement)
        still_coasting = line is not None and now - s.last_seen < tc.still_coast
        if meas is None and not (coasting or still_coasting):
            self._wait_lost(s, dev, dt)
            s.res.loop_s.append(time.perf_counter() - w0)
            return False
        return self._track(s, dev, meas is not None or still_coasting, line, now, dt, w0)

    def _observe(self, s: _RunState, dev: _Devices) -> Measurement | None:
        """Capture, detect and locate the object (a weak detection away from the track is
        not taken for it); before the first sighting, the second views. The timings go to
        the result."""
        cfg, res, kf = self.cfg, s.res, s.kf
        s.ticks += 1
        q_meas = np.asarray(dev.arm.joint_positions(), float)
        c0 = time.perf_counter()
        frame = dev.camera.capture()
        d0 = time.perf_counter()
        res.capture_ms.append(1000 * (d0 - c0))
        track = None
        if s.p_meas is not None:  # points of the track for weak detections
            track = [s.p_meas, kf.position()] if kf.initialized else [s.p_meas]
        det, meas = self.perception.measure(frame, dev.name, q_meas, kf, track=track)
        if (
            meas is not None
            and kf.initialized
            and det.score < cfg.detect.reinit_score
            and np.linalg.norm(meas.p - kf.position()) > cfg.predictor.gate
        ):
            meas = None  # a weak detection away from the track: not taken for the object
        res.detect_ms.append(1000 * (time.perf_counter() - d0))
        if s.first is None:
            s.first = meas is not None
        if (
            meas is None
            and s.p_meas is None
            and not s.searched
            and cfg.search.views
            and cfg.search.candidates > 0
            and dev.clock() - s.t0 >= cfg.search.after
        ):
            # improvement: look at the weak candidates from other viewpoints
            s.searched = True
            q_start = s.q_cmd

            def until() -> bool:
                return self._out_of_time(s, dev)

            s.q_cmd, det, meas, res.views = self.search.run(
                dev.name, frame, q_meas, s.q_cmd, dev.arm, dev.camera, dev.wait, until
            )
            if meas is None:  # back to the first view, wait there (the paper's way)
                s.q_cmd = self.search.move_to(dev.arm, s.q_cmd, q_start, dev.wait, until)
        if meas is not None and s.p_meas is None:
            res.found_view = res.views
        return meas

    def _take(self, s: _RunState, meas: Measurement, name: str, now: float) -> None:
        """The predictor, the still window, the heights and the grasp yaw take ``meas``."""
        kf = s.kf
        s.p_meas = meas.p
        kf.update(s.p_meas)
        s.innovations.append(kf.innovation)
        if not np.isfinite(kf.innovation):  # the track (re)started
            s.hist.clear()
        s.hist.append((now, s.p_meas))
        s.hist[:] = [h for h in s.hist if h[0] >= now - self.cfg.track.still_window]
        s.top_z = meas.top_z
        if np.isfinite(meas.desk_z):
            dz = meas.desk_z
            s.desk_z = dz if s.desk_z is None else 0.7 * s.desk_z + 0.3 * dz
        if name not in SYMMETRIC and meas.axis is not None:
            s.yaw = grasp_yaw(self.geom, meas.axis, s.q_cmd)
        s.last_seen = now

    def _wait_lost(self, s: _RunState, dev: _Devices, dt: float) -> None:
        """The object is lost. Paper: stop and wait for it to reappear; improvement
        (``track.reacquire``): first back up to the tracking standoff over where it was last
        seen (it left the view at the closer final standoff, or moved out of it)."""
        cfg = self.cfg
        s.aligned = 0
        if s.standoff < cfg.ibvs.standoff:
            s.lost_close = True  # lost at the final standoff: descend from farther
        s.standoff = cfg.ibvs.standoff
        qdot = np.zeros(6)  # stop (at the stream's acceleration limits)
        if cfg.track.reacquire and s.p_meas is not None:
            try:
                q_back, _ = self.servo_step(s.q_cmd, s.p_meas, None, s.yaw, dt, s.standoff)
                qdot = (q_back - s.q_cmd) / dt
            except UnreachableError:
                pass
        s.q_cmd = self.stream.send(qdot, dt)
        dev.base.stop()
        dev.wait(dt)
        s.kf.predict(dt)

    def _target(
        self, s: _RunState, line: tuple[Array, Array] | None, now: float, dt: float
    ) -> tuple[Array, Array | None]:
        """The object's position (3,) m and velocity (3,) m/s to servo on, a tick ahead: a
        still object's line (extrapolated at most ``coast_time`` past the last measurement:
        the slope of a still object's line is mostly jitter), the prediction, or the last
        measurement (no velocity) without the predictor."""
        cfg = self.cfg
        if line is not None:  # a still object: its least-squares line
            p_obj = line[0] + line[1] * (min(now - s.hist[-1][0], cfg.track.coast_time) + dt)
            return p_obj, line[1]
        if cfg.track.use_predictor:
            return s.kf.position(ahead=dt), s.kf.velocity()
        assert s.p_meas is not None
        return s.p_meas, None

    def _track(
        self,
        s: _RunState,
        dev: _Devices,
        seen: bool,
        line: tuple[Array, Array] | None,
        now: float,
        dt: float,
        w0: float,
    ) -> bool:
        """A tracking tick: the base toward a far object, the IBVS step (or the intercept)
        toward the tracking point, then closer or the grasp when aligned. True: the run
        ends."""
        cfg, kf = self.cfg, s.kf
        p_obj, v_obj = self._target(s, line, now, dt)
        reach = float(np.hypot(p_obj[0], p_obj[1]))
        if reach > cfg.track.reach_limit:
            dev.base.set_velocity(cfg.track.base_speed, 0.0)
        else:
            dev.base.stop()
        try:
            q_next, err = self.servo_step(s.q_cmd, p_obj, v_obj, s.yaw, dt, s.standoff)
        except UnreachableError:
            s.res.reason = "unreachable"
            return True
        if cfg.stream.accel_limit == "still":  # qdd_stream_max while the object moves
            self.stream.set_limited(dev.arm, not is_fast(s.hist, cfg.track))
        if cfg.intercept.track and intercepting(cfg, kf, line):  # intercept the pose
            # the goal now (the segment moves it on): the prediction at this tick
            q_goal, v_goal = intercept_goal(
                self.geom, s.q_cmd, kf.position(), kf.velocity(), s.standoff, s.yaw,
                cfg.intercept.lead, cfg.ibvs.damping,
            )  # fmt: skip
            s.q_cmd = self.stream.send_intercept(q_goal, v_goal, dt, cfg.intercept.track_time)
        else:
            s.q_cmd = self.stream.send((q_next - s.q_cmd) / dt, dt)
        ok = seen and err[0] < cfg.track.align_tol and err[1] < 0.03
        s.aligned = s.aligned + 1 if ok else 0
        steady = self._steady(s, line)
        dev.wait(dt)
        kf.predict(dt)
        s.res.loop_s.append(time.perf_counter() - w0)
        moving = cfg.track.use_predictor and self._moving(kf.velocity()) and line is None
        final = cfg.track.moving_final_standoff if moving else cfg.track.final_standoff
        if moving and cfg.stream.accel_limit == "intercept":
            final = cfg.intercept.standoff
        aligned = s.aligned >= cfg.track.align_ticks
        if aligned and s.standoff > final and not s.lost_close:
            s.standoff, s.aligned = final, 0  # closer, still in view
            return False
        if aligned and steady and s.desk_z is not None and s.top_z is not None:
            return self._attempt(s, dev, line)
        return False

    def _steady(self, s: _RunState, line: tuple[Array, Array] | None) -> bool:
        """The object moves predictably: the last ``steady_ticks`` innovations below
        ``steady_tol`` (with the predictor); a still object always (jitter is no motion)."""
        tc = self.cfg.track
        recent = s.innovations[-tc.steady_ticks :] if tc.steady_ticks else []
        steady = not (tc.use_predictor and recent) or max(recent) < tc.steady_tol
        if tc.use_predictor and len(recent) < tc.steady_ticks:
            steady = False
        if line is not None:  # still: no turn to wait out (jitter is not motion)
            steady = True
        return steady

    def _attempt(self, s: _RunState, dev: _Devices, line: tuple[Array, Array] | None) -> bool:
        """Descend, close and lift; after a miss, open and track on from here while
        attempts and time remain. True: the run ends."""
        cfg, res = self.cfg, s.res
        dev.base.stop()
        if dev.on_event:
            dev.on_event("descend")
        if line is not None:  # the line at the descent's start
            ahead = min(dev.clock() - s.hist[-1][0], cfg.track.coast_time)
            line = (line[0] + line[1] * ahead, line[1])
        t_descend = dev.clock()
        self.descent.aborted = False
        try:
            s.q_cmd = self._descend(s, dev, line)
        except (UnreachableError, MMPAError):
            res.reason = "unreachable"
            return True
        if self.descent.aborted:  # the object turned on the way down: track on
            s.aligned = 0
            s.innovations.append(float("inf"))  # steady again before the next descent
            return False
        res.descent_s = dev.clock() - t_descend
        if dev.on_event:
            dev.on_event("close")
        held = bool(dev.gripper.close())
        self._lift(dev.arm, s.q_cmd)
        res.attempts += 1
        held = held and dev.gripper.width() > cfg.close.held_min_width  # still held, lifted
        res.closed_on_object = held
        res.reason = "grasped" if held else "missed"
        res.time_to_grasp = dev.clock() - s.t0
        if held or res.attempts >= cfg.close.max_attempts or self._out_of_time(s, dev):
            return True
        # improvement: missed (closed on nothing, or lost on the lift): open and track again
        # from here; the reacquire backs up over the last measurement
        if dev.on_event:
            dev.on_event("retry")
        dev.gripper.open()
        s.q_cmd = self.stream.start(dev.arm.joint_positions())
        s.kf.reset()
        s.hist.clear()
        s.innovations.clear()
        s.aligned, s.standoff, s.lost_close = 0, cfg.ibvs.standoff, False
        s.last_seen = -np.inf
        res.reason = "timeout"
        return False

    def _descend(self, s: _RunState, dev: _Devices, line: tuple[Array, Array] | None) -> Array:
        """The descent: by the online intercept onto a moving object ("intercept"), else
        along the vertical ramp; returns the last set-point."""
        assert s.top_z is not None and s.desk_z is not None
        if intercepting(self.cfg, s.kf, line):
            return self.descent.descend_intercept(
                dev.arm, s.q_cmd, s.kf, s.top_z, s.desk_z, s.yaw, dev.wait, dev.camera,
                dev.name, s.hist, dev.clock,
            )  # fmt: skip
        return self.descent.descend(
            dev.arm, s.q_cmd, s.kf, s.p_meas, s.top_z, s.desk_z, s.yaw, dev.wait, dev.camera,
            dev.name, line,
        )  # fmt: skip

    def _lift(self, arm: StreamingArm, q_cmd: Array) -> None:
        """Lift the TCP ``close.lift`` m from the set-point ``q_cmd`` (a planned move)."""
        dh = self.geom.dh
        T = fk(dh, q_cmd)
        T[2, 3] += self.cfg.close.lift
        q_min, q_max = self.robot.arm.q_limits
        q = ik_nearest(dh, T, q_cmd, q_min, q_max)
        arm.move_joints(q)
