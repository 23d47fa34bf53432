"""``mmpa ros2 localization``: mmpa's localizer as a drop-in for Nav2's ``amcl`` node.

Topics and QoS as Nav2's amcl (docs/ros2.md "The localization node"): subscribes ``/scan``
(sensor data), ``/map`` (reliable, transient local), ``/initialpose``, ``/tf`` and
``/tf_static``; publishes ``/amcl_pose`` (transient local), ``/particle_cloud``
(``nav2_msgs/ParticleCloud``, sensor data), ``map -> odom`` on ``/tf`` and the localizer's
health on ``/diagnostics``; serves ``reinitialize_global_localization`` (``std_srvs/Empty``).

Frames (REP-105): the scan's pose in ``base_frame_id`` (the lidar mount) comes from tf, never a
default; odometry is ``base_frame_id``'s pose in ``odom_frame_id`` from tf at the scan's stamp
(or ``/odom``'s latest when ``use_odom_topic``). The published ``map -> odom`` is
``T_map_odom = T_map_base T_odom_base^-1``, stamped scan stamp + ``transform_tolerance`` as
Nav2 stamps it. Until the map, the mount, the odometry and a pose (``set_initial_pose``,
``/initialpose`` or the global-localization service) are there the node logs (throttled)
what it waits for and publishes nothing; a scan the library refuses (e.g. an
``angle_increment`` of 0) is logged and dropped. Parameters: :data:`NODE_PARAMS` and the
:class:`~mmpa.localization.config.AMCLConfig` names (Nav2's).
"""

from __future__ import annotations

import dataclasses
import time
from collections import deque
from dataclasses import dataclass
from typing import Any

import numpy as np
from pydantic import ValidationError
from rcl_interfaces.msg import ParameterDescriptor
from std_srvs.srv import Empty

from mmpa.backends.bag.messages import from_odometry
from mmpa.backends.ros2 import graph, localization_msgs, messages
from mmpa.backends.ros2.tf_buffer import TfBuffer
from mmpa.core.errors import ConfigError, MMPAError
from mmpa.core.geometry import Array, se2_compose, se2_inv, se2_to_T
from mmpa.localization.config import AMCLConfig
from mmpa.localization.settings import LocalizationConfig, build_localizer, start_localizer
from mmpa.maps.reflector_map import load_reflector_map

__all__ = ["NODE_PARAMS", "LocalizationNode", "config_from_params", "main"]

#: the node's own parameters (Nav2's names where Nav2 has them) with their defaults
NODE_PARAMS: dict[str, Any] = {
    "base_frame_id": "base_footprint",
    "odom_frame_id": "odom",
    "global_frame_id": "map",
    "scan_topic": "scan",
    "transform_tolerance": 1.0,
    "tf_broadcast": True,
    "set_initial_pose": False,
    "initial_pose.x": 0.0,
    "initial_pose.y": 0.0,
    "initial_pose.z": 0.0,
    "initial_pose.yaw": 0.0,
    "alpha5": 0.2,  # Nav2: the omni model's; mmpa's differential model has alpha1..4 only
    "method": "amcl",  # mmpa: amcl, enhanced, hector (localizer.METHODS)
    "reflector_map": "",  # mmpa: reflector map file (enhanced)
    "use_odom_topic": False,  # mmpa: odometry from /odom instead of tf
    "seed": 0,  # mmpa: the particle filter's random seed
}
THROTTLE_S = 2.0
HELD_SCANS = 5  # scans held for the odometry at their stamps (the /scan QoS depth)
#: the methods that need the surveyed reflectors (``reflector_map`` or ``/reflectors``)
REFLECTOR_METHODS = ("enhanced", "enhanced-paper", "trilateration", "tamcl")


@dataclass
class NodeSettings:
    """The node's parameters other than the localizer's."""

    base_frame_id: str
    odom_frame_id: str
    global_frame_id: str
    scan_topic: str
    transform_tolerance: float
    tf_broadcast: bool
    initial_pose: Array | None
    reflector_map: str
    use_odom_topic: bool
    seed: int


def config_from_params(params: dict[str, Any]) -> tuple[LocalizationConfig, NodeSettings]:
    """Parameter values by name -> the localizer's settings and the node's (pydantic checks
    the AMCL ones: a ConfigError names the parameter)."""
    amcl = {k: params[k] for k in AMCLConfig.model_fields if k in params}
    try:
        cfg = LocalizationConfig(method=params.get("method", "amcl"), amcl=AMCLConfig(**amcl))
    except ValidationError as e:
        bad = "; ".join(f"{'.'.join(map(str, x['loc']))}: {x['msg']}" for x in e.errors())
        raise ConfigError(f"invalid parameters: {bad}") from None
    p = NODE_PARAMS | {k: v for k, v in params.items() if k in NODE_PARAMS}
    init = None
    if p["set_initial_pose"]:
        names = ("initial_pose.x", "initial_pose.y", "initial_pose.yaw")
        try:
            init = np.array([float(p[k]) for k in names])
        except (TypeError, ValueError):
            got = {k: p[k] for k in names}
            msg = f"invalid parameters: initial_pose takes numbers, got {got}"
            raise ConfigError(msg) from None
    node = NodeSettings(
        base_frame_id=str(p["base_frame_id"]),
        odom_frame_id=str(p["odom_frame_id"]),
        global_frame_id=str(p["global_frame_id"]),
        scan_topic=str(p["scan_topic"]),
        transform_tolerance=float(p["transform_tolerance"]),
        tf_broadcast=bool(p["tf_broadcast"]),
        initial_pose=init,
        reflector_map=str(p["reflector_map"]),
        use_odom_topic=bool(p["use_odom_topic"]),
        seed=int(p["seed"]),
    )
    return cfg, node


def _declare(node: Any) -> dict[str, Any]:
    """Declare every parameter (Nav2's defaults) and read back the values given. Typed
    dynamically, so that ``alpha1: 0`` (an integer in a Nav2 YAML) is taken as 0.0; the
    values are checked by :func:`config_from_params` (pydantic)."""
    defaults = AMCLConfig().model_dump() | NODE_PARAMS
    out = {}
    for name, value in defaults.items():
        v = float(value) if isinstance(value, float) else value
        desc = ParameterDescriptor(dynamic_typing=True)
        got = node.declare_parameter(name, v, desc).value
        out[name] = float(got) if isinstance(v, float) and isinstance(got, int) else got
    return out


class LocalizationNode:
    """The node's state and callbacks (module docstring); ``session``: a
    :class:`~mmpa.backends.ros2.graph.Session`."""

    def __init__(self, session: graph.Session) -> None:
        self.node = node = session.node
        self.loc_odom: Array = np.zeros(3)
        self._published = False
        self.cfg, self.s = config_from_params(_declare(node))
        self.tf = TfBuffer()
        self.grid = None
        self.loc: Any = None
        self.pending: tuple[str, Array | None, Array | None] | None = None
        if self.s.initial_pose is not None:
            self.pending = ("pose", self.s.initial_pose, None)
        self.odom_msg: Array | None = None
        self.held: deque[Any] = deque(maxlen=HELD_SCANS)  # scans waiting for the odometry
        self.last_log: dict[str, float] = {}
        self.update_times: deque[float] = deque(maxlen=1000)  # the last update() times, s
        self.reflectors = self._reflectors()
        self._endpoints(node)

    def _reflectors(self) -> tuple[Array, float] | None:
        """The reflector map file's (``reflector_map``), else None: from ``/reflectors``."""
        if not self.s.reflector_map:
            return None
        rm = load_reflector_map(self.s.reflector_map)
        return rm.xy, float(np.max(rm.radius))

    def _endpoints(self, node: Any) -> None:
        mc = messages.message_class
        tf_cls = mc("tf2_msgs/msg/TFMessage")
        pcs = mc("geometry_msgs/msg/PoseWithCovarianceStamped")
        node.create_subscription(
            mc("sensor_msgs/msg/LaserScan"), self.s.scan_topic, self.on_scan, graph.SENSOR_DATA
        )
        node.create_subscription(
            mc("nav_msgs/msg/OccupancyGrid"), "map", self.on_map, graph.LATCHED
        )
        node.create_subscription(pcs, "initialpose", self.on_initialpose, graph.RELIABLE)
        node.create_subscription(tf_cls, "/tf", lambda m: self.on_tf(m, False), graph.TF)
        node.create_subscription(tf_cls, "/tf_static", lambda m: self.on_tf(m, True), graph.LATCHED)
        if self.s.use_odom_topic:
            node.create_subscription(
                mc("nav_msgs/msg/Odometry"), "odom", self.on_odom, graph.RELIABLE
            )
        self.pose_pub = node.create_publisher(pcs, "amcl_pose", graph.LATCHED)
        self.cloud_pub = node.create_publisher(
            mc("nav2_msgs/msg/ParticleCloud"), "particle_cloud", graph.SENSOR_DATA
        )
        self.tf_pub = node.create_publisher(tf_cls, "/tf", graph.RELIABLE)
        self.diag_pub = node.create_publisher(
            mc("diagnostic_msgs/msg/DiagnosticArray"), "/diagnostics", graph.RELIABLE
        )
        node.create_service(Empty, "reinitialize_global_localization", self.on_global)
        if self.cfg.method in REFLECTOR_METHODS and not self.s.reflector_map:
            node.create_subscription(
                mc("visualization_msgs/msg/MarkerArray"),
                "reflectors",
                self.on_reflectors,
                graph.LATCHED,
            )

    def log(self, key: str, text: str, level: str = "warn") -> None:
        """``text`` at most once per :data:`THROTTLE_S` per ``key``."""
        now = time.monotonic()
        if now - self.last_log.get(key, -1e9) < THROTTLE_S:
            return
        self.last_log[key] = now
        logger = self.node.get_logger()  # rclpy: one severity per call site
        if level == "error":
            logger.error(text)
        elif level == "warn":
            logger.warning(text)
        else:
            logger.info(text)

    # --- inputs -----------------------------------------------------------------------
    def on_tf(self, msg: Any, static: bool) -> None:
        for stamp, parent, child, Tm in messages.from_tf_message(msg):
            self.tf.set(stamp, parent, child, Tm, static)
        while self.held and not self._odometry_behind(self.held[0]):
            self._process(self.held.popleft())

    def on_odom(self, msg: Any) -> None:
        self.odom_msg = from_odometry(msg).pose

    def on_map(self, msg: Any) -> None:
        try:
            refl, radius = self.reflectors or (None, 0.0)
            self.grid = localization_msgs.from_occupancy_grid(msg, refl, radius)
        except MMPAError as e:
            self.log("map", f"/map refused: {e}", "error")
            return
        self.node.get_logger().info(
            f"map {self.grid.width} x {self.grid.height} at {self.grid.resolution} m"
        )
        self._rebuild()

    def on_reflectors(self, msg: Any) -> None:
        """The surveyed reflector map on ``/reflectors`` (used when no ``reflector_map``)."""
        try:
            xy, radius = localization_msgs.from_reflector_markers(msg)
        except MMPAError as e:
            self.log("reflectors", f"/reflectors refused: {e}", "error")
            return
        self.reflectors = xy, radius
        self.node.get_logger().info(f"{len(xy)} reflectors of radius {radius} m from /reflectors")
        if self.grid is not None:
            self.grid = dataclasses.replace(self.grid, reflectors=xy, reflector_radius=radius)
            self._rebuild()

    def _rebuild(self) -> None:
        """A new map or reflector map: rebuild the localizer on the next scan, at the current
        pose."""
        if self.loc is not None:
            self.pending = ("pose", self.loc.pose_at(self.loc_odom), None)
            self.loc = None

    def on_initialpose(self, msg: Any) -> None:
        _, pose, cov = localization_msgs.from_pose_with_covariance(msg)
        self.node.get_logger().info(f"initial pose {np.round(pose, 3).tolist()}")
        self.pending = ("pose", pose, cov if np.any(cov) else None)

    def on_global(self, request: Any, response: Any) -> Any:
        self.node.get_logger().info(
            "global localization (AMCL.global_localization): the next scan is searched over "
            "the whole map (amcl.global_search; off: particles over the free space)"
        )
        self.pending = ("global", None, None)
        return response

    # --- the scan ---------------------------------------------------------------------
    def _inputs(self, msg: Any) -> tuple[Any, Array, Array] | None:
        """The scan, the lidar mount and the odometry pose, or None (logged why)."""
        if self.grid is None:
            self.log("map", "waiting for /map (reliable, transient local)")
            return None
        if self.cfg.method in REFLECTOR_METHODS and self.reflectors is None:
            self.log("reflectors", f"waiting for /reflectors (method {self.cfg.method})")
            return None
        try:
            scan = messages.from_laser_scan(msg)
        except MMPAError as e:
            self.log("scan", f"scan refused, nothing published from it: {e}", "error")
            return None
        mount = self.tf.lookup(self.s.base_frame_id, scan.frame_id)
        if mount is None:
            self.log(
                "mount",
                f"waiting for the transform {self.s.base_frame_id} -> {scan.frame_id} "
                "(the lidar mount, on /tf_static or /tf); not localizing",
            )
            return None
        if self.s.use_odom_topic:
            odom = self.odom_msg
            why = "waiting for /odom"
        else:
            T = self.tf.lookup(
                self.s.odom_frame_id, self.s.base_frame_id, scan.stamp, self.s.transform_tolerance
            )
            odom = None if T is None else localization_msgs.planar(T)
            why = (
                f"waiting for the transform {self.s.odom_frame_id} -> {self.s.base_frame_id} "
                f"at the scan's stamp {scan.stamp:.3f} s {self.tf.why()}"
            )
        if odom is None:
            self.log("odom", why)
            return None
        return scan, localization_msgs.planar(mount), odom

    def _start(self, mount: Array) -> bool:
        """Build the localizer on the first usable scan; apply a pending start."""
        if self.loc is None:
            if self.pending is None:
                self.log(
                    "pose",
                    "waiting for an initial pose (/initialpose, set_initial_pose "
                    "or reinitialize_global_localization)",
                )
                return False
            rng = np.random.default_rng(self.s.seed)
            self.loc = build_localizer(self.cfg, self.grid, mount, rng)
        if self.pending is not None:
            kind, pose, cov = self.pending
            self.pending = None
            start_localizer(self.loc, self.cfg.method, pose, cov, kind == "global")
        return True

    def _odometry_behind(self, msg: Any) -> bool:
        """Whether the odometry on tf has not reached the scan's stamp yet, by less than
        ``transform_tolerance`` (tf2's message filter: such a scan waits for it)."""
        if self.s.use_odom_topic:
            return False
        last = self.tf.latest_stamp(self.s.base_frame_id)
        t = localization_msgs.stamp_of(msg.header)
        return last is not None and 0.0 < t - last <= self.s.transform_tolerance

    def on_scan(self, msg: Any) -> None:
        """Process the scan, or hold it (in arrival order, at most :data:`HELD_SCANS`) until
        tf has the odometry at its stamp."""
        if not self.held and not self._odometry_behind(msg):
            self._process(msg)
            return
        if len(self.held) == HELD_SCANS:
            self.log("held", f"dropped a scan: {HELD_SCANS} wait for the odometry on tf")
        self.held.append(msg)

    def _process(self, msg: Any) -> None:
        inputs = self._inputs(msg)
        if inputs is None:
            return
        scan, mount, odom = inputs
        try:
            if not self._start(mount):
                return
            t0 = time.perf_counter()
            est = self.loc.update(odom, scan)
            self.update_times.append(time.perf_counter() - t0)
        except MMPAError as e:
            self.log("update", f"scan at {scan.stamp:.3f} s refused: {e}", "error")
            return
        self.loc_odom = odom
        self._publish(scan.stamp, est, odom)

    def _publish(self, stamp: float, est: Any, odom: Array) -> None:
        """``/amcl_pose`` first (what a follower waits for), then ``/diagnostics``,
        ``/particle_cloud`` and ``map -> odom`` on ``/tf``; a pose not ok: the diagnostics
        only."""
        s = self.s
        if not est.ok:  # withheld: nothing downstream moves on it
            self._diagnostics(stamp, est)
            self.log(
                "health",
                f"localization not ok at {stamp:.3f} s, no pose published: {est.reason}",
                "error",
            )
            return
        pose = np.asarray(self.loc.pose_at(odom), float)
        if est.updated or not self._published:
            self.pose_pub.publish(  # its bytes (raw publishing: no rclpy message to convert)
                localization_msgs.pose_with_covariance_cdr(stamp, s.global_frame_id, pose, est.cov)
            )
            self._published = True
        self._diagnostics(stamp, est)
        parts = getattr(self.loc, "particles", None)
        if parts is not None and len(parts):
            self.cloud_pub.publish(  # the bytes, built with numpy (raw publishing)
                localization_msgs.particle_cloud_cdr(
                    stamp, s.global_frame_id, parts, self.loc.weights
                )
            )
        if s.tf_broadcast:
            map_odom = se2_compose(pose, se2_inv(odom))
            self.tf_pub.publish(
                messages.tf_message(
                    stamp + s.transform_tolerance,
                    [(s.global_frame_id, s.odom_frame_id, se2_to_T(*map_odom))],
                )
            )

    def _diagnostics(self, stamp: float, est: Any) -> None:
        h = est.health
        values = {"method": self.cfg.method, "particles": int(est.n_particles)}
        values |= {k: v for k, v in vars(h).items() if isinstance(v, float | int)}
        values["update_ms"] = 1e3 * self.update_times[-1]  # the library's update() on it
        self.diag_pub.publish(
            localization_msgs.diagnostics(
                stamp, "mmpa localization", est.ok, est.reason or "ok", values
            )
        )


def main(args: list[str] | None = None) -> int:
    """Run the node until interrupted; ``args``: the ``--ros-args ...`` given."""
    with graph.Session("amcl", ["mmpa_localization", *(args or [])]) as session:
        LocalizationNode(session)
        session.node.get_logger().info("mmpa localization node up")
        try:
            while session.context.ok():
                session.spin_once(0.1)
        except KeyboardInterrupt:
            pass
    return 0
