"""A ROS 2 node of its own context, Nav2's QoS profiles, and waiting for endpoints to match.

Each :class:`Session` owns an ``rclpy`` context (``rclpy.init`` on it, not the global one),
one node and a single-threaded executor, so a process can open and close sessions (a test,
a node, a backend) without touching another's state. The domain and discovery range come
from the environment as for any ROS 2 process (``ROS_DOMAIN_ID``,
``ROS_AUTOMATIC_DISCOVERY_RANGE``).

QoS as Nav2 uses it: ``SENSOR_DATA`` (best effort, volatile, keep last 5: ``/scan``),
``LATCHED`` (reliable, transient local, keep last 1: ``/map``, ``/amcl_pose``, ``/tf_static``),
``RELIABLE`` (reliable, volatile, keep last 10: commands, ``/tf``'s publishers), ``TF`` (keep
last 100: a ``/tf`` listener, as tf2_ros's).
"""

from __future__ import annotations

import time
from typing import Any

import rclpy
from rclpy.executors import SingleThreadedExecutor
from rclpy.qos import (
    DurabilityPolicy,
    HistoryPolicy,
    QoSProfile,
    ReliabilityPolicy,
    qos_profile_sensor_data,
)

__all__ = [
    "LATCHED",
    "RELIABLE",
    "SENSOR_DATA",
    "TF",
    "Session",
    "matched",
    "wait_until_matched",
]

SENSOR_DATA = qos_profile_sensor_data
LATCHED = QoSProfile(
    history=HistoryPolicy.KEEP_LAST,
    depth=1,
    reliability=ReliabilityPolicy.RELIABLE,
    durability=DurabilityPolicy.TRANSIENT_LOCAL,
)
RELIABLE = QoSProfile(
    history=HistoryPolicy.KEEP_LAST,
    depth=10,
    reliability=ReliabilityPolicy.RELIABLE,
    durability=DurabilityPolicy.VOLATILE,
)

#: a ``/tf`` listener's (tf2_ros's ``DynamicListenerQoS``: reliable, volatile, keep last 100):
#: 10 would lose transforms while a callback runs long (2 s at 50 Hz)
TF = QoSProfile(
    history=HistoryPolicy.KEEP_LAST,
    depth=100,
    reliability=ReliabilityPolicy.RELIABLE,
    durability=DurabilityPolicy.VOLATILE,
)


def matched(endpoint: Any) -> int:
    """How many endpoints of the other side this publisher / subscription has matched (DDS
    discovery runs on its own threads: no spinning needed)."""
    if hasattr(endpoint, "get_subscription_count"):
        return int(endpoint.get_subscription_count())
    return int(endpoint.get_publisher_count())


def wait_until_matched(endpoint: Any, count: int = 1, timeout: float = 10.0) -> bool:
    """Poll every 10 ms until ``endpoint`` has matched ``count`` peers or ``timeout`` s passed;
    True when matched."""
    deadline = time.monotonic() + timeout
    while matched(endpoint) < count:
        if time.monotonic() > deadline:
            return False
        time.sleep(0.01)
    return True


class Session:
    """One node in its own ``rclpy`` context; a context manager (closes the node and the
    context on exit). ``args``: ROS arguments (``["--ros-args", ...]``)."""

    def __init__(self, name: str, args: list[str] | None = None) -> None:
        self.context = rclpy.Context()
        rclpy.init(args=args, context=self.context)
        self.node = rclpy.create_node(name, context=self.context)
        self.executor = SingleThreadedExecutor(context=self.context)
        self.executor.add_node(self.node)

    def spin_once(self, timeout: float = 0.01) -> None:
        """Run the ready callbacks, waiting up to ``timeout`` s for one."""
        self.executor.spin_once(timeout_sec=timeout)

    def spin_until(self, done: Any, timeout: float) -> bool:
        """Spin until ``done()`` is true or ``timeout`` s passed; True when done."""
        deadline = time.monotonic() + timeout
        while not done():
            if time.monotonic() > deadline:
                return False
            self.spin_once(0.01)
        return True

    def close(self) -> None:
        self.executor.shutdown()
        self.node.destroy_node()
        if self.context.ok():
            rclpy.shutdown(context=self.context)

    def __enter__(self) -> Session:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
