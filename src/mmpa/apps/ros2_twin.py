"""The digital twin as a ROS 2 robot (``mmpa ros2 twin``; docs/ros2.md "The twin as a ROS 2
robot"), as a Gazebo bridge presents a simulated robot.

:class:`TwinNode` owns a :class:`~mmpa.backends.twin.world.SimWorld` and steps it in real
time (``speed`` sim seconds per wall second; 0: as fast as it can) in ticks of ``1 /
rate_hz`` sim seconds. After every tick it publishes ``/clock`` (the twin's time), ``/odom``
and ``/tf`` ``odom -> base_link`` (the wheel odometry), ``/joint_states`` and the arm's
``/tf`` (the nominal DH chain at the encoder angles), ``/truth/base_pose`` and
``/truth/tcp_pose``; the scan at the lidar's rate (``world.nominal.lidar.rate``), the camera
as ``realsense2_camera`` names it at ``camera_rate_hz`` (``camera``; the images are rendered
only while something subscribes to them, as Gazebo's camera plugins do; ``camera_info``
always), and once, latched (reliable + transient local, as ``map_server`` serves them):
``/map`` (the twin's occupancy map, drawn through the mapping distortion as SLAM made it),
``/reflectors`` (the surveyed reflector map), ``/tf_static`` (the nominal mounts) and
``/truth/reflectors``. Topic names and message builders are the bag recorder's
(:data:`mmpa.backends.bag.record.TOPICS`, :mod:`mmpa.backends.bag.messages` through the CDR
bridge of :mod:`mmpa.backends.ros2.messages`). Stamps: sim time (s).

Commands (taken on the executor's thread, applied by the stepping thread between ticks):

- ``/cmd_vel`` (``geometry_msgs/Twist``: ``linear.x`` m/s, ``angular.z`` rad/s) -> the base
  (clipped to its limits); the base stops when none came for ``cmd_vel_timeout`` sim s;
- ``/scaled_joint_trajectory_controller/joint_trajectory`` (``trajectory_msgs/
  JointTrajectory``, as ur_robot_driver takes it) -> :meth:`SimArm.follow`: joints by name,
  ``time_from_start`` from now; a path whose first point is later than 0 starts at the
  current set-point (the encoders) at 0, as ros2_control's trajectory controller does;
- ``/forward_position_controller/commands`` (``std_msgs/Float64MultiArray``, 6 angles rad)
  -> :meth:`SimArm.command` (the limited streaming set-point);
- ``/gripper/command`` (``std_msgs/Float64``: the finger gap in m, 0 closed .. stroke open).

Every command is checked before anything moves, as the Python backend checks it
(:func:`mmpa.robot.limits.check_target`, :func:`~mmpa.robot.limits.check_path`); a bad one is
refused with a log line saying why (``refused /topic: reason``) and nothing moves (a refused
``/cmd_vel`` also stops the base: its sender is broken). While a trajectory runs (its whole
motion is one :meth:`SimArm.follow`, whose steps this node paces and publishes tick by
tick), further arm commands are refused; ``/cmd_vel`` and the gripper still apply.
"""

from __future__ import annotations

import logging
import queue
import threading
import time
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from pydantic import BaseModel, ConfigDict, Field

from mmpa.backends.bag import messages as rm
from mmpa.backends.bag.record import ARM_FRAMES, JOINT_NAMES, TOPICS
from mmpa.backends.ros2 import graph, messages
from mmpa.backends.twin.error_model import ErrorModelConfig
from mmpa.backends.twin.twin_maps import twin_map
from mmpa.backends.twin.world import SimWorld
from mmpa.core.config import load_config
from mmpa.core.errors import InvalidInputError, MMPAError
from mmpa.robot.kinematics import link_steps
from mmpa.robot.limits import check_path

__all__ = [
    "COMMAND_TOPICS",
    "TwinNode",
    "TwinNodeConfig",
    "TwinStats",
    "run_twin_node",
    "twin_node_config",
]

log = logging.getLogger(__name__)

#: the topics the node subscribes to (name -> topic)
COMMAND_TOPICS = {
    "cmd_vel": "/cmd_vel",
    "trajectory": "/scaled_joint_trajectory_controller/joint_trajectory",
    "forward": "/forward_position_controller/commands",
    "gripper": "/gripper/command",
}
_TYPES = {
    "cmd_vel": "geometry_msgs/msg/Twist",
    "trajectory": "trajectory_msgs/msg/JointTrajectory",
    "forward": "std_msgs/msg/Float64MultiArray",
    "gripper": "std_msgs/msg/Float64",
}


class TwinNodeConfig(BaseModel):
    """The twin node's settings (defaults in code; ``mmpa ros2 twin`` sets the first five)."""

    model_config = ConfigDict(extra="forbid")

    site: str = "0"  # where the robot starts (a site of the scene)
    # start pose [x, y, theta] (m, m, rad in map) instead of the site's park pose (a rough
    # parking near the site: `mmpa --robot R run` where the robot stands); None: the site's
    pose: tuple[float, float, float] | None = None
    errors: ErrorModelConfig = Field(default_factory=ErrorModelConfig)
    camera: bool = False  # publish the wrist camera
    camera_rate_hz: float = Field(15.0, gt=0)
    speed: float = Field(1.0, ge=0)  # sim s per wall s; 0: unpaced (as fast as it steps)
    rate_hz: float = Field(50.0, gt=0)  # ticks per sim s: /clock, /odom, /joint_states, /tf
    cmd_vel_timeout: float = Field(0.5, gt=0)  # sim s without /cmd_vel before the base stops
    map_resolution: float = Field(0.05, gt=0)  # m per cell of /map


@dataclass
class TwinStats:
    """What the node did: ticks stepped, sim and wall seconds (their ratio is the real-time
    factor), messages published per topic, commands refused (topic, reason)."""

    ticks: int = 0
    sim_s: float = 0.0
    wall_s: float = 0.0
    published: dict[str, int] = field(default_factory=dict)
    refused: list[tuple[str, str]] = field(default_factory=list)

    @property
    def real_time_factor(self) -> float:
        return self.sim_s / self.wall_s if self.wall_s > 0 else 0.0


def _tf(stamp: float, transforms: list[tuple[str, str, Any]]) -> Any:
    """``tf2_msgs/TFMessage`` (rosbags) of ``(parent, child, pose)`` triples at ``stamp``."""
    return rm.tf_message([rm.transform_stamped(stamp, p, c, Tm) for p, c, Tm in transforms])


class TwinNode:
    """The twin on ROS 2 (module docstring). ``args``: ROS arguments (``--ros-args ...``).

    :meth:`run` steps until :meth:`stop` (or ``duration`` sim s); the executor spins on a
    thread of its own and only queues commands, so the world is touched by one thread."""

    def __init__(self, cfg: TwinNodeConfig, args: list[str] | None = None) -> None:
        self.cfg = cfg
        self.world = SimWorld(errors=cfg.errors, site=cfg.site)
        if cfg.pose is not None:
            self.world.reset(site=cfg.site, pose2d=np.asarray(cfg.pose, float))
        self.session = graph.Session("mmpa_twin", args)
        self.stats = TwinStats()
        self._commands: queue.SimpleQueue[tuple[str, Any]] = queue.SimpleQueue()
        self._stop = threading.Event()
        self._busy = False  # a trajectory is running
        self._last_cmd_vel = -np.inf
        self._tick = 1.0 / cfg.rate_hz
        self._next_scan = self.world.time
        self._next_frame = self.world.time
        self._anchor = (time.monotonic(), self.world.time)
        grip = self.world.model.actuator("gripper").id
        self._grip = (grip, float(self.world.model.actuator_ctrlrange[grip, 1]))
        self._pubs = self._publishers()
        for name, topic in COMMAND_TOPICS.items():
            self.session.node.create_subscription(
                messages.message_class(_TYPES[name]),
                topic,
                lambda msg, name=name: self._commands.put((name, msg)),
                graph.RELIABLE,
            )
        self._step = self.world.step  # the class's method, bound
        self.world.step = self._paced_step  # type: ignore[method-assign]
        self._publish_latched()
        self._thread = threading.Thread(target=self._spin, daemon=True)
        self._thread.start()

    # --- graph ----------------------------------------------------------------------------
    def _publishers(self) -> dict[str, Any]:
        S, L, R = graph.SENSOR_DATA, graph.LATCHED, graph.RELIABLE
        kinds = {
            "clock": ("/clock", "rosgraph_msgs/msg/Clock", R),
            "scan": (TOPICS["scan"], "sensor_msgs/msg/LaserScan", S),
            "odom": (TOPICS["odom"], "nav_msgs/msg/Odometry", R),
            "tf": (TOPICS["tf"], "tf2_msgs/msg/TFMessage", R),
            "tf_static": (TOPICS["tf_static"], "tf2_msgs/msg/TFMessage", L),
            "joint_states": (TOPICS["joint_states"], "sensor_msgs/msg/JointState", R),
            "map": (TOPICS["map"], "nav_msgs/msg/OccupancyGrid", L),
            "reflectors": (TOPICS["reflectors"], "visualization_msgs/msg/MarkerArray", L),
            "truth_reflectors": (
                TOPICS["truth_reflectors"],
                "visualization_msgs/msg/MarkerArray",
                L,
            ),
            "truth_base": (TOPICS["truth_base"], "geometry_msgs/msg/PoseStamped", R),
            "truth_tcp": (TOPICS["truth_tcp"], "geometry_msgs/msg/PoseStamped", R),
        }
        if self.cfg.camera:
            kinds |= {
                "color": (TOPICS["color"], "sensor_msgs/msg/Image", S),
                "depth": (TOPICS["depth"], "sensor_msgs/msg/Image", S),
                "camera_info": (TOPICS["camera_info"], "sensor_msgs/msg/CameraInfo", S),
                "truth_camera": (TOPICS["truth_camera"], "geometry_msgs/msg/PoseStamped", R),
            }
        node = self.session.node
        return {
            k: node.create_publisher(messages.message_class(t), topic, qos)
            for k, (topic, t, qos) in kinds.items()
        }

    def _publish(self, kind: str, msg: Any) -> None:
        """Publish ``msg`` on the ``kind`` topic: an rclpy message as it is, a rosbags one as
        its CDR bytes (raw publishing: no rclpy message is built, the image's pixels are
        copied once, into the bytes)."""
        if not hasattr(msg, "get_fields_and_field_types"):
            msg = bytes(messages.typestore().serialize_cdr(msg, msg.__msgtype__))
        self._pubs[kind].publish(msg)
        self.stats.published[kind] = self.stats.published.get(kind, 0) + 1

    def _spin(self) -> None:
        try:
            self.session.executor.spin()
        except Exception:  # the context was shut down under the spin: the node is closing
            if not self._stop.is_set():
                raise

    # --- publishing -------------------------------------------------------------------------
    def _publish_latched(self) -> None:
        """``/map``, ``/reflectors``, ``/tf_static`` (nominal mounts), ``/truth/reflectors``."""
        w, F, t = self.world, rm.FRAMES, self.world.time
        rob = w.nominal
        grid = twin_map(w, self.cfg.map_resolution)
        self.grid = grid
        self._publish("map", rm.occupancy_grid(grid, t))
        self._publish("reflectors", rm.reflector_markers(t, grid.reflectors, grid.reflector_radius))
        tfs = [
            (F["base"], F["laser"], rob.lidar.T_base_link_laser),
            (F["base"], F["arm_base"], rob.T_base_link_arm_base),
            (F["flange"], F["tcp"], rob.gripper.T_flange_tcp),
            (F["flange"], F["camera"], rob.camera.T_flange_camera),
        ]
        self._publish("tf_static", _tf(t, tfs))
        radius = float(w.scene.reflectors.radius)
        truth = w.truth.reflector_positions()[:, :2]
        self._publish("truth_reflectors", rm.reflector_markers(t, truth, radius, "truth"))

    def _publish_tick(self) -> None:
        """``/clock``, ``/odom``, ``/tf`` (odom -> base_link, the arm's links),
        ``/joint_states``, ``/truth/base_pose``, ``/truth/tcp_pose``; the scan and camera when
        due."""
        w, F = self.world, rm.FRAMES
        t = w.time
        clock = messages.message_class("rosgraph_msgs/msg/Clock")()
        clock.clock.sec, clock.clock.nanosec = divmod(rm.stamp_ns(t), 1_000_000_000)
        self._publish("clock", clock)
        odo = w.odometry.odometry()
        self._publish("odom", rm.odometry(odo))
        q, qd = w.arm.joint_positions(), w.arm.joint_velocities()
        self._publish("joint_states", rm.joint_state(t, JOINT_NAMES, q, qd))
        A = link_steps(w.nominal.arm.dh, q)  # each link in its parent's frame
        parents = [F["arm_base"], *ARM_FRAMES[:-1]]
        tfs = [(F["odom"], F["base"], odo.pose)]
        tfs += [(parents[i], ARM_FRAMES[i], A[i]) for i in range(6)]
        self._publish("tf", _tf(t, tfs))
        self._publish("truth_base", rm.pose_stamped(t, F["map"], w.truth.T_map_base_link()))
        self._publish("truth_tcp", rm.pose_stamped(t, F["map"], w.truth.T_map_tcp()))
        eps = 1e-9
        if t >= self._next_scan - eps:
            self._next_scan = max(self._next_scan + 1.0 / w.nominal.lidar.rate, t)
            self._publish("scan", messages.laser_scan(w.lidar.scan(), F["laser"]))
        if self.cfg.camera and t >= self._next_frame - eps:
            self._next_frame = max(self._next_frame + 1.0 / self.cfg.camera_rate_hz, t)
            if self._images_watched():  # rendered for a subscriber only (module docstring)
                frame = w.camera.capture()
                self._publish("color", rm.rgb_image(frame))
                self._publish("depth", rm.depth_image(frame))
            self._publish("camera_info", rm.camera_info(w.camera.intrinsics, t))
            self._publish("truth_camera", rm.pose_stamped(t, F["map"], w.truth.T_map_camera()))

    def _images_watched(self) -> bool:
        return any(self._pubs[k].get_subscription_count() > 0 for k in ("color", "depth"))

    # --- commands ---------------------------------------------------------------------------
    def _refuse(self, kind: str, reason: str) -> None:
        topic = COMMAND_TOPICS[kind]
        self.stats.refused.append((topic, reason))
        self.session.node.get_logger().warning(f"refused {topic}: {reason}")

    def _apply_commands(self) -> None:
        """Apply the queued commands in arrival order (module docstring); a stale
        ``/cmd_vel`` stops the base."""
        while True:
            try:
                kind, msg = self._commands.get_nowait()
            except queue.Empty:
                break
            try:
                getattr(self, f"_on_{kind}")(msg)
            except MMPAError as e:  # InvalidInputError, JointLimitError: nothing moved
                self._refuse(kind, str(e))
                if kind == "cmd_vel":
                    self.world.base.stop()
        base = self.world.base
        stale = self.world.time - self._last_cmd_vel > self.cfg.cmd_vel_timeout
        if stale and (base.v != 0.0 or base.omega != 0.0):
            base.stop()

    def _on_cmd_vel(self, msg: Any) -> None:
        parts = [msg.linear.x, msg.linear.y, msg.linear.z, msg.angular.x, msg.angular.y]
        values = np.array([*parts, msg.angular.z], float)
        if not np.all(np.isfinite(values)):
            raise InvalidInputError(f"a velocity is NaN or infinite: {values.tolist()}")
        self.world.base.set_velocity(float(msg.linear.x), float(msg.angular.z))
        self._last_cmd_vel = self.world.time

    def _arm_order(self, names: list[str]) -> np.ndarray:
        """Index of each of :data:`JOINT_NAMES` in the message's ``names``."""
        if sorted(names) != sorted(JOINT_NAMES):
            raise InvalidInputError(f"joint_names must be {JOINT_NAMES} (any order), got {names}")
        return np.array([list(names).index(j) for j in JOINT_NAMES])

    def _on_trajectory(self, msg: Any) -> None:
        if self._busy:
            raise InvalidInputError("a trajectory is running (wait for it to end)")
        order = self._arm_order(list(msg.joint_names))
        if not msg.points:
            raise InvalidInputError("the trajectory has no points")
        for p in msg.points:
            if len(p.positions) != len(order):
                raise InvalidInputError("every point needs one position per joint")
        q = np.array([np.asarray(p.positions, float)[order] for p in msg.points])
        t = np.array([p.time_from_start.sec + 1e-9 * p.time_from_start.nanosec for p in msg.points])
        if t[0] > 0:  # from the current state at 0, as ros2_control's trajectory controller
            t = np.concatenate([[0.0], t])
            q = np.vstack([self.world.arm.joint_positions(), q])
        check_path(t, q, self.world.arm.limits, "joint trajectory")
        self._busy = True
        try:
            self.world.arm.follow(t, q)  # steps the world: paced and published tick by tick
        finally:
            self._busy = False

    def _on_forward(self, msg: Any) -> None:
        if self._busy:
            raise InvalidInputError("a trajectory is running (wait for it to end)")
        self.world.arm.command(np.asarray(msg.data, float))  # check_target inside

    def _on_gripper(self, msg: Any) -> None:
        gap = float(msg.data)
        stroke = float(self.world.true_robot.gripper.stroke)
        if not (np.isfinite(gap) and 0.0 <= gap <= stroke):
            raise InvalidInputError(f"the finger gap must be in [0, {stroke}] m, got {gap}")
        act, top = self._grip
        self.world.data.ctrl[act] = float(np.clip((stroke - gap) / 2.0, 0.0, top))

    # --- stepping ---------------------------------------------------------------------------
    def _paced_step(self, duration: float) -> None:
        """The world's ``step`` while the node runs: the same physics steps, in ticks; after
        each, publish, take the commands and wait for the wall clock (``speed``)."""
        if not (np.isfinite(duration) and duration >= 0):
            return self._step(duration)  # the world's own error
        dt = float(self.world.model.opt.timestep)
        per_tick = max(1, round(self._tick / dt))
        left = round(duration / dt)
        while left > 0:
            n = min(per_tick, left)
            self._step(n * dt)
            left -= n
            self.stats.ticks += 1
            self._publish_tick()
            self._apply_commands()
            self._pace()
        return None

    def _pace(self) -> None:
        """Sleep until wall time catches up with sim time / ``speed``; re-anchor after
        falling more than 0.5 s behind (no rush to catch up)."""
        if self.cfg.speed == 0:
            return
        wall0, sim0 = self._anchor
        target = wall0 + (self.world.time - sim0) / self.cfg.speed
        now = time.monotonic()
        if now < target:
            time.sleep(target - now)
        elif now > target + 0.5:
            self._anchor = (now, self.world.time)

    def run(self, duration: float | None = None) -> TwinStats:
        """Step until :meth:`stop` is called (or ``duration`` sim s passed)."""
        w = self.world
        t0, wall0 = w.time, time.monotonic()
        self._anchor = (wall0, t0)
        end = np.inf if duration is None else t0 + duration
        try:
            self._publish_tick()
            while not self._stop.is_set() and w.time < end - 1e-9:
                w.step(self._tick)
        finally:
            self.stats.sim_s += w.time - t0
            self.stats.wall_s += time.monotonic() - wall0
        return self.stats

    def stop(self) -> None:
        self._stop.set()

    def close(self) -> None:
        self._stop.set()
        vars(self.world).pop("step", None)
        self.session.close()
        self._thread.join(timeout=5.0)
        self.world.close()

    def __enter__(self) -> TwinNode:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def twin_node_config(
    site: str = "0",
    profile: str | None = None,
    seed: int = 0,
    pose: tuple[float, float, float] | None = None,
    **fields: Any,
) -> TwinNodeConfig:
    """The node's settings for robot instance ``seed`` of error profile ``profile`` (None:
    realistic) at ``site`` (at ``pose`` near it when given); ``fields``: other
    :class:`TwinNodeConfig` fields. An unknown profile or a bad value raises
    ``ConfigError``."""
    sets = [f"errors.seed={seed}"]
    sets += [] if profile is None else [f"errors.profile={profile}"]
    sets += [f"{k}={v}" for k, v in fields.items()]
    cfg = load_config(TwinNodeConfig, None, sets).model_copy(update={"site": str(site)})
    if pose is not None:
        p = np.asarray(pose, float)
        if p.shape != (3,) or not np.all(np.isfinite(p)):
            raise InvalidInputError(f"the start pose is x, y, theta (3 finite numbers), got {pose}")
        cfg = cfg.model_copy(update={"pose": (float(p[0]), float(p[1]), float(p[2]))})
    return cfg


def run_twin_node(
    cfg: TwinNodeConfig, args: list[str] | None = None, duration: float | None = None
) -> TwinStats:
    """Run the twin node until interrupted (Ctrl-C) or ``duration`` sim s; returns its
    stats. ``args``: the ROS arguments (``--ros-args ...``)."""
    with TwinNode(cfg, args) as node:
        log.info("twin node: site %s, profile %s", cfg.site, cfg.errors.profile)
        try:
            node.run(duration)
        except KeyboardInterrupt:
            pass
        return node.stats
