"""The twin's devices: the hardware-neutral protocols of ``mmpa.robot.interfaces`` on a
:class:`~mmpa.backends.twin.world.SimWorld` (its MuJoCo model and data, its low-level
controllers) and the TRUE poses for evaluation.

- :class:`SimBase`: differential drive, body velocity (m/s, rad/s) -> wheel speed targets
  ``w_l,r = (v -+ omega b / 2) / r`` (track ``b``, wheel radius ``r``);
- :class:`SimArm`: jerk-limited (ruckig) joint moves, checked path following and a limited
  streaming set-point (:mod:`mmpa.robot.limits`), with the arm's repeatability drawn from the
  world's seeded joint stream;
- :class:`SimGripper`: the two-finger parallel gripper;
- :class:`GroundTruth`: TRUE poses in map, for evaluation only.

Units: m, rad, s.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np
from ruckig import InputParameter, Result, Ruckig, Trajectory

from mmpa.backends.twin.sensors import CAMERA_NAME, T_world_camera_optical
from mmpa.core.errors import InvalidInputError, SimulationError
from mmpa.core.geometry import Array, T_to_se2, make_T
from mmpa.robot.interfaces import Odometry
from mmpa.robot.limits import (
    JointLimits,
    StreamLimitsSwitch,
    as_floats,
    check_path,
    check_target,
)

if TYPE_CHECKING:
    from mmpa.backends.twin.world import SimWorld

__all__ = ["ArmMotion", "GroundTruth", "SimArm", "SimBase", "SimGripper"]


def _T_from_xpos(xpos: np.ndarray, xmat: np.ndarray) -> Array:
    return make_T(np.asarray(xmat).reshape(3, 3), xpos)


@dataclass
class ArmMotion:
    """A joint trajectory being tracked: ``q(t)`` for ``t`` in ``[t0, t0 + duration]``."""

    t0: float
    duration: float
    sample: object  # Callable[[float], Array]


class SimBase:
    """Differential-drive base: body velocity commands become wheel velocity targets."""

    def __init__(self, world: SimWorld) -> None:
        self._w = world
        self.v = 0.0
        self.omega = 0.0

    def set_velocity(self, v: float, w: float) -> None:
        """``v`` m/s forward, ``w`` rad/s; clipped to the base's limits."""
        if not (np.isfinite(v) and np.isfinite(w)):
            raise InvalidInputError(f"base velocity must be finite, got v={v}, w={w}")
        b = self._w.true_robot.base
        v = float(np.clip(v, -b.max_linear_speed, b.max_linear_speed))
        w = float(np.clip(w, -b.max_angular_speed, b.max_angular_speed))
        self.v, self.omega = v, w
        wl = (v - w * b.track_width / 2) / b.wheel_radius
        wr = (v + w * b.track_width / 2) / b.wheel_radius
        d = self._w.data
        d.ctrl[self._w._wheel_act[0]] = wl
        d.ctrl[self._w._wheel_act[1]] = wr

    def stop(self) -> None:
        self.set_velocity(0.0, 0.0)

    def odometry(self) -> Odometry:
        return self._w.odometry.odometry()


class SimArm(StreamLimitsSwitch):
    """Position-controlled arm following jerk-limited (ruckig) joint trajectories.

    Every motion respects the joint limits (``limits``): ``move_joints`` plans within the
    velocity, acceleration and jerk limits; ``follow`` refuses a path that breaks the position,
    velocity or acceleration limits before anything moves, and first approaches the path's
    start along a jerk-limited move when the arm is more than ``approach_tolerance`` rad away;
    ``command`` streams through a set-point limited in velocity and acceleration
    (``stream_limits``: ``qdd_max``, or the hard ``qdd_stream_max`` with
    ``stream_acceleration_limited`` off).
    """

    #: rad: a path starting farther than this from the set-point gets an approach move first
    approach_tolerance = 1e-3

    def __init__(self, world: SimWorld) -> None:
        self._w = world
        a = world.nominal.arm
        self.q_min, self.q_max = a.q_limits
        self._vmax, self._amax, self._jmax = (
            np.array(x) for x in (a.qd_max, a.qdd_max, a.qddd_max)
        )
        #: the limits every motion of this arm is checked against (mmpa.robot.limits)
        self.limits = JointLimits.from_description(a)
        #: the limits of streamed set-points (``command``): the joint velocity and
        #: acceleration limits (issue 22: a real controller's servo stream refuses, or
        #: protective-stops on, a stream past them), or with ``stream_acceleration_limited``
        #: False the hard stream limit ``qdd_stream_max`` instead of ``qdd_max`` (as on a
        #: UR, whose acceleration limits are planning values, MoveIt's joint_limits.yaml;
        #: the actuators' force ranges bound the acceleration further)
        self.stream_limits = self.limits

    def joint_positions(self) -> Array:
        """Encoder readings (rad), shape (6,)."""
        return self._w.data.qpos[self._w._arm_qadr].copy()

    def joint_velocities(self) -> Array:
        return self._w.data.qvel[self._w._arm_dadr].copy()

    def stopped(self) -> str | None:
        """Why the arm will not move: never, in the twin (it has no safety controller)."""
        return None

    def _check(self, q: Array) -> Array:
        return check_target(q, self.limits)

    def plan(self, q_target: Array, min_duration: float = 0.0) -> tuple[float, object]:
        """Jerk-limited time-optimal trajectory from the current state to ``q_target``.

        Returns ``(duration, sample)`` where ``sample(t)`` gives the joint setpoint (6,).
        """
        q_target = self._check(q_target)
        otg = Ruckig(6)
        inp = InputParameter(6)
        inp.current_position = self._w.data.ctrl[self._w._arm_act].tolist()
        # from a stream: on from the streamed set-point's velocity (no jump in velocity)
        w = self._w
        inp.current_velocity = (w._stream_v if w._stream is not None else np.zeros(6)).tolist()
        inp.current_acceleration = [0.0] * 6
        inp.target_position = q_target.tolist()
        inp.max_velocity = self._vmax.tolist()
        inp.max_acceleration = self._amax.tolist()
        inp.max_jerk = self._jmax.tolist()
        if min_duration > 0:
            inp.minimum_duration = min_duration
        traj = Trajectory(6)
        res = otg.calculate(inp, traj)
        if res not in (Result.Working, Result.Finished):
            raise SimulationError(f"ruckig could not plan the arm motion: {res}")

        def sample(t: float) -> Array:
            return np.asarray(traj.at_time(t)[0])

        return float(traj.duration), sample

    def move_joints(self, q: Array, duration: float | None = None, settle: float = 0.3) -> None:
        """Move to ``q`` along a jerk-limited trajectory, then settle. The arm lands within its
        repeatability (seeded noise) of the target, as a real arm does."""
        q = self._check(q)
        if duration is not None and not (np.isfinite(duration) and duration >= 0):
            raise InvalidInputError(
                f"move duration must be a finite number of seconds >= 0 (or None), got {duration}"
            )
        T, sample = self.plan(q, min_duration=duration or 0.0)
        w = self._w
        noise = w._rng_joint.normal(0.0, w.error_model.joint_noise_sigma, 6)
        q_final = q + noise

        def sample_noisy(t: float) -> Array:
            return np.asarray(sample(t)) + noise * min(t / T, 1.0) if T > 0 else q_final  # type: ignore[operator]

        # from a moving stream the set-point goes on at once (the first physics step
        # samples the plan one step in), not held for a step
        moving = w._stream is not None and np.any(w._stream_v != 0)
        t0 = float(w.data.time) - (float(w.model.opt.timestep) if moving else 0.0)
        w._motion = ArmMotion(t0, T, sample_noisy)
        w._stream = None
        w.step(T + settle)

    def command(self, q: Array) -> None:
        """Servo set-point: the joints go to ``q`` (rad, (6,)) from now on (a streaming
        command, as URScript ``servoj``); cancels any trajectory. Targets outside the joint
        position limits are refused; the set-point moves toward the target within
        ``stream_limits`` (:func:`mmpa.robot.limits.limit_setpoint`, run every physics step),
        so no stream of commands can drive a joint past its velocity or acceleration limit
        (velocity only with ``stream_acceleration_limited`` off). Step the world to let the
        arm move."""
        q = self._check(q)
        w = self._w
        now = float(w.data.time)
        vmax = self.limits.qd_max
        if w._stream is None or now <= w._stream_t:  # a new stream (or two commands at once)
            if w._stream is None:
                w._stream_v = np.zeros(6)
            w._stream_vff, w._stream_hold = np.zeros(6), 0.0
        else:
            period = now - w._stream_t
            w._stream_vff = np.clip((q - w._stream) / period, -vmax, vmax)
            w._stream_hold = period
        w._motion = None
        w._stream, w._stream_t = q.copy(), now

    def follow(
        self, times: Array, q_path: Array, record_hz: float | None = None
    ) -> tuple[Array, Array] | None:
        """Track ``q_path`` (T, 6) at ``times`` (T,) s (linear interpolation between samples).

        With ``record_hz`` the encoders are read every ``1 / record_hz`` s while the arm moves
        (as a teach-in recorder does) and ``(t, q)`` is returned: ``t`` (M,) from 0, ``q`` (M, 6).
        """
        times = as_floats(times, "follow: times")
        q_path = as_floats(q_path, "follow: q_path")
        if q_path.ndim != 2 or q_path.shape[1] != 6 or times.shape != (q_path.shape[0],):
            raise InvalidInputError(
                f"need times (T,) and q_path (T, 6), got {times.shape}, {q_path.shape}"
            )
        if record_hz is not None and not (np.isfinite(record_hz) and record_hz > 0):
            raise InvalidInputError(f"record_hz must be a positive rate, got {record_hz}")
        check_path(times, q_path, self.limits)  # positions, velocities, accelerations
        w = self._w
        w._stream = None
        if np.max(np.abs(q_path[0] - w.data.ctrl[w._arm_act])) > self.approach_tolerance:
            self.move_joints(q_path[0], settle=0.0)  # a jerk-limited approach, not a jump
        t_rel = times - times[0]

        def sample(t: float) -> Array:
            return np.array([np.interp(t, t_rel, q_path[:, j]) for j in range(6)])

        w._motion = ArmMotion(float(w.data.time), float(t_rel[-1]), sample)
        if record_hz is None:
            w.step(float(t_rel[-1]) + 0.2)
            return None
        dt = 1.0 / record_hz
        n = int(np.floor(t_rel[-1] * record_hz + 1e-9)) + 1
        t_rec, q_rec = [0.0], [self.joint_positions()]
        for i in range(1, n):
            w.step(dt)
            t_rec.append(i * dt)
            q_rec.append(self.joint_positions())
        w.step(max(t_rel[-1] - (n - 1) * dt, 0.0) + 0.2)
        return np.array(t_rec), np.array(q_rec)


class SimGripper:
    """Two-finger parallel gripper, 85 mm stroke; slide joints coupled by an equality."""

    def __init__(self, world: SimWorld) -> None:
        self._w = world
        self._stroke = world.true_robot.gripper.stroke

    def width(self) -> float:
        q = self._w.data.qpos[self._w._finger_qadr]
        return float(self._stroke - 2.0 * q)

    def open(self) -> None:
        self._w.data.ctrl[self._w._grip_act] = 0.0
        self._w.step(0.6)

    def close(self) -> bool:
        """Close the fingers; True if they stopped on an object (gap > 5 mm; empty: 2 mm)."""
        self._w.data.ctrl[self._w._grip_act] = self._w.model.actuator_ctrlrange[
            self._w._grip_act, 1
        ]
        self._w.step(0.8)
        return self.width() > 0.005


class GroundTruth:
    """TRUE poses, for evaluation only. Algorithm code must never call these."""

    def __init__(self, world: SimWorld) -> None:
        self._w = world

    def _body(self, name: str) -> Array:
        b = self._w.data.body(name)
        return _T_from_xpos(b.xpos, b.xmat)

    def T_map_base_link(self) -> Array:
        return self._body("base_link")

    def base_pose2d(self) -> Array:
        """``[x, y, yaw]`` of base_link in map."""
        return T_to_se2(self.T_map_base_link())

    def T_map_arm_base(self) -> Array:
        return self._body("arm_base")

    def T_map_flange(self) -> Array:
        return self._body("flange")

    def T_map_tcp(self) -> Array:
        s = self._w.data.site("tcp")
        return _T_from_xpos(s.xpos, s.xmat)

    def T_map_camera(self) -> Array:
        """Optical frame of the wrist camera (z forward, x right, y down)."""
        return T_world_camera_optical(self._w.model, self._w.data, CAMERA_NAME)

    def T_map_object(self, name: str) -> Array:
        return self._body(name)

    def reflector_positions(self) -> Array:
        return self._w.scene.reflector_positions()

    def fiducial_positions(self) -> Array:
        """(N, 3) centers of the fiducial reflector discs in map."""
        fa = self._w.scene.fiducial_artifact
        if fa is None:
            return np.zeros((0, 3))
        return np.array(
            [self._w.data.geom(f"fiducial_{i}_reflector").xpos for i in range(len(fa.fiducials))]
        )
