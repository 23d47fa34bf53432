"""The digital twin: the TRUE world and robot in MuJoCo, driven through the robot interfaces.

``SimWorld`` owns the MuJoCo model and data, steps the physics with the low-level controllers
(wheel velocity, arm joint position, gripper position), and hands out simulated devices that
implement the hardware-neutral protocols of ``mmpa.robot.interfaces``. Software must only
use ``world.nominal`` (the robot it believes in), ``world.map_reflectors`` (surveyed, not
true), maps drawn through ``world.map_warp`` (the mapping distortion) and the devices;
``world.truth`` is for evaluation. The devices themselves (:class:`SimBase`, :class:`SimArm`,
:class:`SimGripper`, :class:`GroundTruth`) are in :mod:`mmpa.backends.twin.devices`, the
sensors in :mod:`mmpa.backends.twin.sensors`.

Units: m, rad, s. Every random draw comes from the error model's seeded streams.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import ClassVar

import mujoco
import numpy as np

from mmpa.backends.twin.devices import ArmMotion, GroundTruth, SimArm, SimBase, SimGripper
from mmpa.backends.twin.error_model import ErrorModel, ErrorModelConfig
from mmpa.backends.twin.lidar_noise import SmoothWarp
from mmpa.backends.twin.mjcf import MOUNT_JOINTS, BuiltModel, build_model
from mmpa.backends.twin.noise import (
    color_session_gain,
    depth_bias_pattern,
    session_disparity,
)
from mmpa.backends.twin.scene import SceneConfig, load_scene
from mmpa.backends.twin.scene_change import apply_scene_change
from mmpa.backends.twin.sensors import SimCamera, SimLidar, SimOdometry, SimPhotoSensor
from mmpa.core.errors import InvalidInputError, SimulationError, UnknownNameError
from mmpa.core.geometry import Array, rpy_to_R
from mmpa.robot.description import RobotDescription, default_robot
from mmpa.robot.limits import limit_setpoint

__all__ = ["GroundTruth", "SimArm", "SimBase", "SimGripper", "SimWorld"]

_ARM_JOINTS = [f"joint{i}" for i in range(1, 7)]
_CONTROL_EVERY = 5  # physics steps per odometry update (100 Hz at dt = 2 ms)


def _joint_names(m: mujoco.MjModel) -> set[str]:
    return {m.joint(i).name for i in range(m.njnt)}


def _has_ancestor(m: mujoco.MjModel, body: int, ancestor: int) -> bool:
    """Whether ``ancestor`` is ``body`` or one of its parents."""
    while body > 0:
        if body == ancestor:
            return True
        body = int(m.body_parentid[body])
    return False


class SimWorld:
    """The simulated world with one robot.

    Parameters
    ----------
    scene: the world (default: built-in ``default.yaml``).
    robot: NOMINAL robot description (default: :func:`default_robot`).
    errors: error model configuration; its seed fixes the robot instance.
    site: where the robot starts (a site name of the scene).
    episode: index that re-seeds per-episode noise streams (sensor noise, parking draws)
        without changing the robot instance.
    """

    def __init__(
        self,
        scene: SceneConfig | None = None,
        robot: RobotDescription | None = None,
        errors: ErrorModelConfig | None = None,
        site: str = "0",
        episode: int = 0,
        model_hook: Callable[[BuiltModel], BuiltModel] | None = None,
    ) -> None:
        """``model_hook`` edits the built MJCF before it is compiled (added geometry such
        as a calibration board; :mod:`mmpa.backends.twin.calibration_board`)."""
        self.scene = scene or load_scene()
        self.nominal = robot or default_robot()
        self.error_model = ErrorModel.sample(self.nominal, errors)
        self.true_robot = self.error_model.true
        self.episode = episode
        start = self.scene.site(site)
        built = build_model(
            self.scene, self.true_robot, start.pose2d, self.error_model.config.compliance
        )
        if model_hook is not None:
            built = model_hook(built)
        self.model = built.compile()
        self.data = mujoco.MjData(self.model)
        m = self.model
        self._base_qadr = m.jnt_qposadr[m.joint("base_free").id]
        self._base_dadr = m.jnt_dofadr[m.joint("base_free").id]
        self._arm_qadr = np.array([m.jnt_qposadr[m.joint(j).id] for j in _ARM_JOINTS])
        self._arm_dadr = np.array([m.jnt_dofadr[m.joint(j).id] for j in _ARM_JOINTS])
        self._arm_act = np.array([m.actuator(f"arm{i}").id for i in range(1, 7)])
        self._wheel_act = (m.actuator("wheel_left_vel").id, m.actuator("wheel_right_vel").id)
        self._grip_act = m.actuator("gripper").id
        self._finger_qadr = m.jnt_qposadr[m.joint("finger_left_joint").id]
        # compliant arm mount (base compliance of the error model; absent when rigid)
        names = _joint_names(m)
        mount = [m.joint(j).id for j in MOUNT_JOINTS if j in names]
        self._mount_jnt = np.array(mount, dtype=int)
        arm_base = m.body("arm_base").id
        self._mount_bodies = np.array(
            [b for b in range(m.nbody) if _has_ancestor(m, b, arm_base)], dtype=int
        )
        self._bump_body = m.body("speed_bump").id if self.scene.speed_bump else None
        self._bump_pos = m.body_pos[self._bump_body].copy() if self._bump_body is not None else None
        rng = self.error_model.rng
        self._rng_joint = rng("joint_repeatability", episode)
        self.map_reflectors = self.scene.reflector_positions() + rng("reflector_map").normal(
            0.0,
            self.error_model.config.lidar.reflector_map_sigma,
            (len(self.scene.reflectors.positions), 2),
        )
        li = self.error_model.config.lidar
        #: distortion of the occupancy map made at mapping time (error model v2, fixed per
        #: robot instance): a world point ``q`` appears in the map at ``q + map_warp(q)``
        self.map_warp = SmoothWarp.sample(rng("map_warp"), li.map_warp_sigma, li.map_warp_length)
        self._motion: ArmMotion | None = None
        #: streaming set-point (Arm.command): the last command, when it came (sim s), the
        #: command velocity (rad/s) held for one command period, and the limited
        #: set-point's velocity
        self._stream: Array | None = None
        self._stream_t = 0.0
        self._stream_vff = np.zeros(6)
        self._stream_hold = 0.0
        self._stream_v = np.zeros(6)
        self._steps = 0
        self.base = SimBase(self)
        self.arm = SimArm(self)
        self.gripper = SimGripper(self)
        self.truth = GroundTruth(self)
        self._camera: SimCamera | None = None
        self._lidar: SimLidar | None = None
        self._photosensor: SimPhotoSensor | None = None
        self._depth_bias: np.ndarray | None = None
        self._camera_session: tuple[np.ndarray | None, np.ndarray | None] = (None, None)
        self.session = 0
        self.scene_changes: dict[str, tuple[float, float, float]] = {}
        self.begin_session(0)
        self.reset(site)

    # --- devices --------------------------------------------------------------------------
    @property
    def camera(self) -> SimCamera:
        """Wrist RGB-D camera (created on first use: it needs an OpenGL context)."""
        if self._camera is None:
            self._camera = SimCamera(
                self.model,
                self.data,
                self.true_robot.camera,
                self.error_model.config.camera,
                self.error_model.rng("camera", self.episode),
                lambda: float(self.data.time),
            )
            self._camera.set_session(*self._camera_session)
        return self._camera

    @property
    def lidar(self) -> SimLidar:
        if self._lidar is None:
            self._lidar = SimLidar(
                self.model,
                self.data,
                self.true_robot.lidar,
                self.error_model.config.lidar,
                self.error_model.rng("lidar", self.episode),
                lambda: float(self.data.time),
                bias_rng=self.error_model.rng("reflector_bias"),  # fixed per robot instance
            )
        return self._lidar

    @property
    def photosensor(self) -> SimPhotoSensor:
        if self._photosensor is None:
            self._photosensor = SimPhotoSensor(self.model, self.data, self.true_robot.photosensor)
        return self._photosensor

    @property
    def odometry(self) -> SimOdometry:
        """Wheel odometry; every :meth:`reset` restarts it with its origin at the base."""
        return self._odometry

    @property
    def time(self) -> float:
        """Simulation time (s)."""
        return float(self.data.time)

    @property
    def description(self) -> RobotDescription:
        """The NOMINAL robot (what the software knows; :class:`MobileManipulator`)."""
        return self.nominal

    # --- scene state ----------------------------------------------------------------------
    def set_speed_bump(self, enabled: bool) -> None:
        """Put the speed bump of Site 2' in place (or park it below the floor)."""
        if self._bump_body is None:
            if enabled:
                raise InvalidInputError("this scene defines no speed bump")
            return
        pos = self._bump_pos.copy()
        pos[2] = 0.0 if enabled else -1.0
        self.model.body_pos[self._bump_body] = pos
        mujoco.mj_forward(self.model, self.data)

    # --- lighting and object placement (perception experiments, training data) -----------
    LIGHTING: ClassVar[dict[str, float]] = {"dark": 0.18, "normal": 1.0, "high": 2.2}

    def set_lighting(self, condition: str | float) -> None:
        """Scale every light and the headlight: ``"dark"``, ``"normal"``, ``"high"`` (paper 001
        Table 3's three conditions) or a positive factor relative to the built-in lights."""
        if isinstance(condition, str):
            if condition not in self.LIGHTING:
                raise UnknownNameError("lighting condition", condition, list(self.LIGHTING))
            k = self.LIGHTING[condition]
        else:
            k = float(condition)
            if not (np.isfinite(k) and k > 0):
                raise InvalidInputError(f"lighting factor must be positive, got {condition}")
        m = self.model
        if not hasattr(self, "_light0"):
            self._light0 = (
                m.light_diffuse.copy(),
                m.light_ambient.copy(),
                m.light_specular.copy(),
                np.array(m.vis.headlight.ambient),
                np.array(m.vis.headlight.diffuse),
            )
        d0, a0, s0, ha, hd = self._light0
        m.light_diffuse[:] = d0 * k
        m.light_ambient[:] = a0 * k
        m.light_specular[:] = np.clip(s0 * k, 0.0, 1.0)
        m.vis.headlight.ambient[:] = ha * k
        m.vis.headlight.diffuse[:] = hd * k
        self.lighting = k

    def object_names(self) -> list[str]:
        """Movable bodies: grasp objects and free desk items."""
        names = [o.name for o in self.scene.grasp_objects]
        for bench in [*self.scene.workbenches, self.scene.grasp_desk]:
            if bench is not None:
                names += [it.name for it in bench.items if it.free and it.name]
        return names

    def place_object(
        self, name: str, position: Array, yaw: float = 0.0, velocity: Array | None = None
    ) -> None:
        """Put a free body at ``position`` (map, m) with heading ``yaw`` (rad) about map z and
        linear ``velocity`` (m/s, default at rest). The object keeps its built-in tilt (lying
        sticks stay lying). Kinematic: no physics step is taken (call :meth:`step`)."""
        try:
            jid = self.model.joint(f"{name}_free").id
        except KeyError:
            raise UnknownNameError("object", name, self.object_names()) from None
        p = np.asarray(position, float)
        if p.shape != (3,) or not np.all(np.isfinite(p)) or not np.isfinite(yaw):
            raise InvalidInputError(f"object position must be finite (3,), got {position}")
        qa, da = self.model.jnt_qposadr[jid], self.model.jnt_dofadr[jid]
        self.data.qpos[qa : qa + 3] = p
        self.data.qpos[qa + 3 : qa + 7] = (np.cos(yaw / 2), 0.0, 0.0, np.sin(yaw / 2))
        self.data.qvel[da : da + 6] = 0.0
        if velocity is not None:
            self.data.qvel[da : da + 3] = np.asarray(velocity, float)
        mujoco.mj_forward(self.model, self.data)

    def set_arm_configuration(self, q: Array) -> None:
        """Teleport the arm to ``q`` (rad, (6,)) with zero velocity, holding it there: for
        rendering views (training data), not for motion (use ``arm``). A compliant arm
        mount is put at rest under the arm's new weight distribution."""
        q = self.arm._check(q)
        self.data.qpos[self._arm_qadr] = q
        self.data.qvel[self._arm_dadr] = 0.0
        self.data.ctrl[self._arm_act] = q
        self._motion = self._stream = None
        self._rest_mount()
        mujoco.mj_forward(self.model, self.data)

    @property
    def speed_bump_enabled(self) -> bool:
        return self._bump_body is not None and self.model.body_pos[self._bump_body][2] > -0.5

    def begin_session(self, session: int) -> dict[str, tuple[float, float, float]]:
        """Start session ``session`` (0: the teaching session, k > 0: the k-th repeat, a new
        park): draw the errors that are fixed within a session and change between sessions
        (DESIGN.md "Error model v2"), each from :meth:`ErrorModel.session_rng`, so a session
        is the same whatever ran before it:

        - the depth camera's correlated noise and disparity drift
          (:func:`~mmpa.backends.twin.noise.session_disparity`) on top of its fixed ring bias
          pattern
          (:func:`~mmpa.backends.twin.noise.depth_bias_pattern`, drawn once per robot instance), and
          the colour session (:func:`~mmpa.backends.twin.noise.color_session_gain`);
        - the scene change: loose objects back at their taught poses, then, in a repeat
          session, maybe some nudged (:func:`~mmpa.backends.twin.scene_change.apply_scene_change`).

        Returns what the scene change moved (name -> ``(dx, dy, dyaw)`` in map, m and rad;
        evaluation only). The robot's pose and the episode streams are unchanged."""

        k = int(session)
        if k < 0:
            raise InvalidInputError(f"session must be >= 0, got {session}")
        self.session = k
        cam = self.error_model.config.camera
        native = self.true_robot.camera.color
        shape = (native.height, native.width)
        if self._depth_bias is None:
            self._depth_bias = (
                depth_bias_pattern(
                    shape, self.error_model.rng("depth_bias_pattern"), cam.bias_pattern_px
                )
                if cam.bias_pattern_px > 0
                else np.zeros(shape, dtype=np.float32)
            )
        rng = self.error_model.session_rng("camera", k)
        disparity = session_disparity(shape, rng, cam) + self._depth_bias
        gain = color_session_gain(shape, rng, cam)
        self._camera_session = (
            disparity if np.any(disparity) else None,
            gain if np.any(gain != 1.0) else None,
        )
        if self._camera is not None:
            self._camera.set_session(*self._camera_session)

        self.scene_changes = apply_scene_change(self, k)
        return self.scene_changes

    def set_episode(self, episode: int) -> None:
        """Re-seed the per-episode noise streams (camera, lidar, joint repeatability, and the
        odometry from the next :meth:`reset`) as if the world had been built with
        ``episode``: a trial that calls it first does not depend on the trials run before it
        in the same world. The robot instance (the error model's seed) is unchanged."""
        if int(episode) < 0:
            raise InvalidInputError(f"episode must be >= 0, got {episode}")
        self.episode = int(episode)
        rng = self.error_model.rng
        self._rng_joint = rng("joint_repeatability", self.episode)
        if self._camera is not None:
            self._camera._rng = rng("camera", self.episode)
        if self._lidar is not None:
            self._lidar._rng = rng("lidar", self.episode)

    def reset(
        self,
        site: str | None = None,
        pose2d: Array | None = None,
        q_arm: Array | None = None,
        settle: float = 0.5,
    ) -> None:
        """Place the robot at a site's park pose (or at ``pose2d`` = ``[x, y, yaw]``), arm at
        ``q_arm`` (default: home), gripper open; enable the speed bump iff the site has one;
        let the physics settle for ``settle`` s."""
        if site is not None:
            s = self.scene.site(site)
            if pose2d is None:
                pose2d = s.pose2d
            self.set_speed_bump(s.speed_bump)
        if pose2d is None:
            pose2d = self.truth.base_pose2d()
        pose2d = np.asarray(pose2d, float)
        if pose2d.shape != (3,) or not np.all(np.isfinite(pose2d)):
            raise InvalidInputError(f"pose2d must be finite [x, y, yaw], got {pose2d}")
        q = np.asarray(self.nominal.arm.home if q_arm is None else q_arm, float)
        d = self.data
        mujoco.mj_resetData(self.model, d)
        z0, roll, pitch = self._bump_pose(pose2d) if self.speed_bump_enabled else (0.001, 0, 0)
        d.qpos[self._base_qadr : self._base_qadr + 3] = (pose2d[0], pose2d[1], z0)
        quat = np.empty(4)
        mujoco.mju_mat2Quat(quat, rpy_to_R(roll, pitch, pose2d[2]).ravel())
        d.qpos[self._base_qadr + 3 : self._base_qadr + 7] = quat
        d.qpos[self._arm_qadr] = q
        d.ctrl[self._arm_act] = q
        d.ctrl[self._grip_act] = 0.0
        self._motion = self._stream = None
        self._rest_mount()
        mujoco.mj_forward(self.model, d)
        self._odometry = SimOdometry(
            self.true_robot.base,
            self.error_model.config.odometry,
            self.error_model.rng("odometry", self.episode),
        )
        if settle > 0:
            self.step(settle)
            # a base dropped onto the speed bump rocks for a while: wait until it rests
            for _ in range(30):
                if np.linalg.norm(d.qvel[self._base_dadr : self._base_dadr + 6]) < 2e-3:
                    break
                self.step(0.1)
        self._odometry.reset()
        self._odometry.update(self.truth.base_pose2d(), float(d.time))

    def _rest_mount(self) -> None:
        """Put the compliant arm mount (if any) at rest under the arm's weight for the
        current base pose and arm configuration (quasi-static, zero velocity), as the
        physics would settle it: per hinge ``j`` (axis ``a_j`` through ``p_j``, map)

            q_j = springref_j + tau_j / k_j,   tau_j = a_j . sum_i (c_i - p_j) x (m_i g)

        over the bodies ``i`` above the mount (mass ``m_i`` kg at ``c_i`` m, gravity ``g``
        m/s^2; N m, rad, N m/rad). Runs ``mj_kinematics`` (two passes: the tilt moves the
        centres of mass by a negligible amount). No-op for a rigid mount."""
        if self._mount_jnt.size == 0:
            return
        m, d = self.model, self.data
        qadr, dadr = m.jnt_qposadr[self._mount_jnt], m.jnt_dofadr[self._mount_jnt]
        w = m.body_mass[self._mount_bodies][:, None] * m.opt.gravity
        for _ in range(2):
            mujoco.mj_kinematics(m, d)
            c = d.xipos[self._mount_bodies]
            for j, qa in zip(self._mount_jnt, qadr, strict=True):
                tau = d.xaxis[j] @ np.cross(c - d.xanchor[j], w).sum(axis=0)
                d.qpos[qa] = m.qpos_spring[qa] + tau / m.jnt_stiffness[j]
        d.qvel[dadr] = 0.0

    def _bump_pose(self, pose2d: Array) -> tuple[float, float, float]:
        """``(z, roll, pitch)`` that put both wheels and the caster on the ground/speed bump
        at ``pose2d`` (released level from above, the base would drop, tip and slide off)."""
        sb = self.scene.speed_bump
        b = self.true_robot.base
        if sb is None:
            return 0.001, 0.0, 0.0
        c, s_ = np.cos(pose2d[2]), np.sin(pose2d[2])
        yaw = np.deg2rad(sb.yaw_deg)

        def height(px: float, py: float) -> float:
            x = pose2d[0] + c * px - s_ * py - sb.center[0]
            y = pose2d[1] + s_ * px + c * py - sb.center[1]
            u = np.cos(yaw) * x + np.sin(yaw) * y  # along the ridge
            v = -np.sin(yaw) * x + np.cos(yaw) * y  # across it
            if abs(u) <= sb.length / 2 and abs(v) <= sb.width / 2:
                return sb.height * (1.0 - abs(v) / (sb.width / 2))
            return 0.0

        hl, hr = height(0.0, b.track_width / 2), height(0.0, -b.track_width / 2)
        hc = height(b.caster_x, 0.0)
        roll = float(np.arcsin(np.clip((hl - hr) / b.track_width, -0.5, 0.5)))
        pitch = float(np.arcsin(np.clip((hc - (hl + hr) / 2) / -b.caster_x, -0.5, 0.5)))
        return (hl + hr) / 2 + 0.002, roll, pitch

    def set_kinematic_state(
        self,
        pose2d: Array,
        q_arm: Array,
        roll: float = 0.0,
        pitch: float = 0.0,
        time: float | None = None,
    ) -> None:
        """Kinematic mode: place the base at ``pose2d`` = ``[x, y, yaw]`` (tilted by ``roll``,
        ``pitch`` rad, at its current height) and the arm at ``q_arm`` without running the
        dynamics, and bring body poses, cameras, sensors and ground truth level with it
        (``mj_kinematics`` and ``mj_camlight``, a few microseconds). A compliant arm mount
        is put at rest under the arm's weight (:meth:`_rest_mount`). For fast twins whose
        motion is prescribed (e.g. a base driving a known noisy trajectory); odometry is not
        updated."""
        pose2d = np.asarray(pose2d, float)
        q = np.asarray(q_arm, float)
        if pose2d.shape != (3,) or q.shape != (6,):
            raise InvalidInputError(
                f"need pose2d (3,) and q_arm (6,), got {pose2d.shape}, {q.shape}"
            )
        if not (np.all(np.isfinite(pose2d)) and np.all(np.isfinite(q))):
            raise InvalidInputError("kinematic state must be finite")
        d = self.data
        a = self._base_qadr
        d.qpos[a : a + 2] = pose2d[:2]
        quat = np.empty(4)
        mujoco.mju_euler2Quat(quat, np.array([roll, pitch, pose2d[2]]), "XYZ")
        d.qpos[a + 3 : a + 7] = quat
        d.qpos[self._arm_qadr] = q
        d.ctrl[self._arm_act] = q
        if time is not None:
            d.time = float(time)
        self._rest_mount()
        mujoco.mj_kinematics(self.model, d)
        mujoco.mj_camlight(self.model, d)  # cameras (and lights) follow their bodies

    # --- physics --------------------------------------------------------------------------
    def step(self, duration: float) -> None:
        """Advance the physics by ``duration`` s, running the low-level controllers."""
        if duration < 0 or not np.isfinite(duration):
            raise InvalidInputError(f"duration must be a finite non-negative time, got {duration}")
        n = round(duration / self.model.opt.timestep)
        m, d = self.model, self.data
        dt = float(m.opt.timestep)
        for _ in range(n):
            if self._motion is not None:
                t = d.time - self._motion.t0
                d.ctrl[self._arm_act] = self._motion.sample(min(t, self._motion.duration))  # type: ignore[operator]
                if t >= self._motion.duration:
                    self._motion = None
            elif self._stream is not None:
                # first-order hold: the target moves on at the command velocity for up to
                # one command period after the command (a steady stream is a ramp)
                # (the target still moves at the end of the hold's last step: a stream whose
                # next command comes then does not brake for a step, every period)
                ahead = min(d.time + dt - self._stream_t, self._stream_hold)
                moving = d.time + dt - self._stream_t < self._stream_hold + 0.5 * dt
                d.ctrl[self._arm_act], self._stream_v = limit_setpoint(
                    d.ctrl[self._arm_act],
                    self._stream_v,
                    self._stream + self._stream_vff * ahead,
                    dt,
                    self.arm.stream_limits,
                    self._stream_vff if moving else 0.0,
                )
            mujoco.mj_step(m, d)
            self._steps += 1
            if self._steps % _CONTROL_EVERY == 0:
                self._odometry.update(self.truth.base_pose2d(), float(d.time))
        if not np.all(np.isfinite(d.qpos)):
            raise SimulationError("physics diverged (NaN in state); check the commanded motion")
        # mj_step leaves body poses at the start of the last step; bring them (ground truth,
        # cameras, ray casts) level with the joint state the encoders report
        mujoco.mj_forward(m, d)

    def close(self) -> None:
        """Release the renderer (call before dropping the world)."""
        if self._camera is not None:
            self._camera.close()
            self._camera = None

    def __enter__(self) -> SimWorld:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
