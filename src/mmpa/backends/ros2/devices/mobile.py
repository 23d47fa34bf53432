"""The mobile part of a ROS 2 robot: its clock, odometry, base, lidar, a running localizer's
pose and the map.

- :class:`SimClock`: the robot's time from ``/clock`` (``use_sim_time``: a simulator, a bag);
  ``step(d)`` waits until ``/clock`` has advanced ``d`` s. Without ``use_sim_time`` the robot's
  clock is :class:`~mmpa.robot.interfaces.WallClock`.
- :class:`Ros2Odometry`: ``nav_msgs/Odometry`` on ``topics.odom`` as
  :class:`~mmpa.robot.interfaces.Odometry` (the planar part: ``[x, y, theta]`` in ``odom``,
  ``[v, w]``), with the last seconds kept to look up the pose at a stamp (:meth:`~Ros2Odometry.at`).
- :class:`Ros2Base`: ``set_velocity(v, w)`` -> ``geometry_msgs/Twist`` on ``topics.cmd_vel``
  (``linear.x`` m/s, ``angular.z`` rad/s, nothing else); a NaN is refused before it is sent; a
  watchdog stops the base when ``/odom`` is silent for ``safety.watchdog_s`` wall s.
- :class:`Ros2Lidar`: the latest ``sensor_msgs/LaserScan`` on ``topics.scan`` as
  :class:`~mmpa.robot.interfaces.LaserScan`. A message that is no valid scan (an angle
  increment of 0 or NaN, NaN limits, no ranges) is dropped with a log line and never
  returned; NaN ranges (REP 117: no measurement) stay NaN, which the scan's ``valid()``
  mask excludes.
- :class:`Ros2PoseSource`: a running localizer's ``PoseWithCovarianceStamped`` on
  ``topics.pose`` (Nav2 amcl's ``/amcl_pose``, transient local) and the ``map -> odom`` it
  implies: ``T_map_odom = P (+) O(t)^-1`` with ``O(t)`` the odometry at the pose's stamp.
- :func:`occupancy_grid`: the map on ``topics.map`` (``map_server``'s transient local) with the
  reflector landmarks of ``/reflectors`` (cylinder markers, as the twin node and mmpa's bags
  publish them) when published.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from mmpa.backends.bag import messages as bag
from mmpa.backends.ros2 import graph
from mmpa.backends.ros2.devices.node import DeviceTimeoutError, RobotNode, Topic
from mmpa.backends.ros2.localization_msgs import (
    from_occupancy_grid,
    from_pose_with_covariance,
    stamp_of,
)
from mmpa.backends.ros2.messages import message_class
from mmpa.core.errors import InvalidInputError
from mmpa.core.geometry import Array, se2_compose, se2_inv, wrap_angle
from mmpa.maps.occupancy import OccupancyGrid
from mmpa.robot.interfaces import LaserScan, Odometry

__all__ = [
    "REFLECTORS_TOPIC",
    "Ros2Base",
    "Ros2Lidar",
    "Ros2Odometry",
    "Ros2PoseSource",
    "SimClock",
    "occupancy_grid",
    "planar_pose",
    "truth_pose",
]

#: the reflector landmarks beside ``/map`` (``visualization_msgs/MarkerArray`` of cylinders)
REFLECTORS_TOPIC = "/reflectors"


def _clock_seconds(msg: Any) -> float:
    return float(msg.clock.sec) + 1e-9 * float(msg.clock.nanosec)


class SimClock:
    """The robot's time from ``rosgraph_msgs/Clock`` (module docstring). ``stall_s``: wall
    seconds without a new ``/clock`` before a wait gives up (:class:`DeviceTimeoutError`)."""

    def __init__(self, node: RobotNode, topic: str, stall_s: float) -> None:
        self._node, self._stall = node, stall_s
        self._t = node.subscribe("clock", topic, "rosgraph_msgs/msg/Clock", graph.SENSOR_DATA)

    @property
    def time(self) -> float:
        return _clock_seconds(self._node.first(self._t, self._stall))

    def step(self, duration: float) -> None:
        """Wait until the robot's clock has advanced ``duration`` s (>= 0)."""
        if not (math.isfinite(duration) and duration >= 0):
            raise InvalidInputError(f"a wait must be a finite duration >= 0 s, got {duration}")
        end = self.time + float(duration) - 1e-9
        t = self._t
        while _clock_seconds(t.msg) < end:
            seen = t.count
            if not t.wait(lambda seen=seen: t.count > seen, self._stall):
                raise DeviceTimeoutError(
                    f"clock: {t.topic} stopped at {_clock_seconds(t.msg):.3f} s: nothing for "
                    f"{self._stall:g} s ({self._node.where}); is the simulator running?"
                )


class Ros2Odometry:
    """The base's odometry on ``topic`` (module docstring); ``keep`` messages kept for
    :meth:`at`. ``timeout``: wall s to wait for the first message."""

    def __init__(self, node: RobotNode, topic: str, timeout: float, keep: int = 500) -> None:
        self._node, self._timeout = node, timeout
        self.topic = node.subscribe(
            "odometry", topic, "nav_msgs/msg/Odometry", graph.SENSOR_DATA, keep, bag.from_odometry
        )

    def odometry(self) -> Odometry:
        return self._node.first(self.topic, self._timeout)

    def at(self, stamp: float) -> Array:
        """The odometry pose ``[x, y, theta]`` at ``stamp`` s: interpolated between the kept
        readings around it (the nearest one outside their span)."""
        self.odometry()
        kept = [o for _, o in self.topic.snapshot()]
        ts = np.array([o.stamp for o in kept])
        k = int(np.searchsorted(ts, stamp))
        if k == 0 or k == len(kept):
            return kept[min(k, len(kept) - 1)].pose.copy()
        a, b = kept[k - 1], kept[k]
        s = (stamp - a.stamp) / (b.stamp - a.stamp) if b.stamp > a.stamp else 1.0
        d = b.pose - a.pose
        d[2] = wrap_angle(d[2])
        out = a.pose + s * d
        out[2] = wrap_angle(out[2])
        return out


class Ros2Base:
    """A differential base over ``/cmd_vel`` (module docstring). ``odometry``: its odometry
    (None: the robot publishes none; :meth:`odometry` then refuses)."""

    def __init__(
        self,
        node: RobotNode,
        topic: str,
        odometry: Ros2Odometry | None,
        watchdog_s: float,
    ) -> None:
        self._node, self._odom, self._watchdog = node, odometry, watchdog_s
        self.pub = node.publisher(topic, "geometry_msgs/msg/Twist", graph.RELIABLE)

    def _send(self, v: float, w: float) -> None:
        msg = message_class("geometry_msgs/msg/Twist")()
        msg.linear.x, msg.angular.z = float(v), float(w)
        self.pub.publish(msg)

    def set_velocity(self, v: float, w: float) -> None:
        """Command ``v`` m/s forward, ``w`` rad/s counter-clockwise (refused when not finite;
        refused and stopped when the odometry has been silent for the watchdog's time)."""
        if not (math.isfinite(v) and math.isfinite(w)):
            self._send(0.0, 0.0)
            raise InvalidInputError(f"base velocity must be finite, got v={v}, w={w}")
        if self._odom is not None and self._odom.topic.age() > self._watchdog:
            self._send(0.0, 0.0)
            raise DeviceTimeoutError(
                f"base: no odometry on {self._odom.topic.topic} for "
                f"{self._odom.topic.age():.2f} s (watchdog {self._watchdog:g} s): stopped"
            )
        self._send(v, w)

    def stop(self) -> None:
        self._send(0.0, 0.0)

    def odometry(self) -> Odometry:
        if self._odom is None:
            raise InvalidInputError("base: this robot has no odometry topic (topics.odom is '')")
        return self._odom.odometry()


def _scan(msg: Any) -> LaserScan:
    """A ``sensor_msgs/LaserScan`` that is a valid scan (InvalidInputError otherwise)."""
    for f in ("range_min", "range_max", "angle_min", "angle_increment"):
        v = float(getattr(msg, f))
        if not math.isfinite(v) and not (f == "range_max" and v == math.inf):
            raise InvalidInputError(f"scan {f} is {v}")
    return bag.from_laser_scan(msg)


class Ros2Lidar:
    """The latest valid scan on ``topic`` (module docstring)."""

    def __init__(self, node: RobotNode, topic: str, timeout: float) -> None:
        self._node, self._timeout = node, timeout
        self.topic = node.subscribe(
            "lidar", topic, "sensor_msgs/msg/LaserScan", graph.SENSOR_DATA, convert=_scan
        )

    def scan(self) -> LaserScan:
        return self._node.first(self.topic, self._timeout)


class Ros2PoseSource:
    """A running localizer's pose on ``topic`` (module docstring)."""

    def __init__(self, node: RobotNode, topic: str, odometry: Ros2Odometry, timeout: float) -> None:
        self._node, self._odom, self._timeout = node, odometry, timeout

        def keep(msg: Any) -> tuple[float, Array, Array, Array]:
            stamp, pose, cov = from_pose_with_covariance(msg)
            if not (np.all(np.isfinite(pose)) and np.all(np.isfinite(cov))):
                raise InvalidInputError(f"a pose with NaN: {pose.tolist()}")
            return stamp, pose, cov, self._odom.at(stamp)

        self.topic = node.subscribe(
            "localizer", topic, "geometry_msgs/msg/PoseWithCovarianceStamped", graph.LATCHED,
            convert=keep,
        )  # fmt: skip

    def latest(self) -> tuple[float, Array, Array]:
        """``(stamp s, [x, y, theta] in map, (3, 3) covariance)`` of the latest pose."""
        hint = (
            ": is a localizer running (mmpa ros2 localization, Nav2 amcl)? Or set "
            "backend.ros2.topics.pose to '' to localize with mmpa's own"
        )
        stamp, pose, cov, _ = self._node.first(self.topic, self._timeout, hint)
        return stamp, pose.copy(), cov.copy()

    def map_odom(self) -> Array:
        """``map -> odom`` ``[x, y, theta]`` of the latest pose: ``P (+) O(stamp)^-1``."""
        self.latest()
        _, pose, _, odom = self.topic.msg
        return se2_compose(pose, se2_inv(odom))


def _reflectors(msg: Any) -> tuple[Array, float]:
    mk = msg.markers
    pts = np.array([[k.pose.position.x, k.pose.position.y] for k in mk], float).reshape(-1, 2)
    return pts, (float(mk[0].scale.x) / 2 if len(mk) else 0.0)


def occupancy_grid(
    node: RobotNode, topic: str, timeout: float, reflector_wait: float
) -> tuple[OccupancyGrid, str]:
    """The map on ``topic`` with the reflectors of :data:`REFLECTORS_TOPIC` when they come
    within ``reflector_wait`` wall s after it; and where the reflectors came from
    (``"/reflectors"`` or ``"none"``)."""
    m = node.subscribe("map", topic, "nav_msgs/msg/OccupancyGrid", graph.LATCHED)
    r = node.subscribe("map", REFLECTORS_TOPIC, "visualization_msgs/msg/MarkerArray", graph.LATCHED)
    msg = node.first(m, timeout, ": is a map server running (latched, transient local)?")
    refl, radius, src = None, 0.0, "none"
    if r.wait(lambda: r.count > 0, reflector_wait):
        refl, radius = _reflectors(r.msg)
        src = REFLECTORS_TOPIC
    grid = from_occupancy_grid(msg, refl, radius)
    res = float(str(np.float32(grid.resolution)))  # float32 on the wire: its shortest decimal
    grid = OccupancyGrid(grid.data, res, grid.origin, grid.reflectors, grid.reflector_radius)
    return grid, src


def truth_pose(node: RobotNode, topic: str, wait: float) -> Topic | None:
    """The twin node's true base pose (``geometry_msgs/PoseStamped``, evaluation only) when
    it is published within ``wait`` wall s, else None."""
    t = node.subscribe("truth", topic, "geometry_msgs/msg/PoseStamped", graph.SENSOR_DATA)
    return t if t.wait(lambda: t.count > 0, wait) else None


def planar_pose(msg: Any) -> tuple[float, Array]:
    """``(stamp s, [x, y, yaw])`` of a ``geometry_msgs/PoseStamped``."""
    Tm = bag.from_pose(msg.pose)
    return stamp_of(msg.header), np.array([Tm[0, 3], Tm[1, 3], math.atan2(Tm[1, 0], Tm[0, 0])])
