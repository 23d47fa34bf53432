"""mmpa values <-> ``rclpy`` messages of ROS 2 Jazzy (the optional extra ``ros2``).

The field mapping is the one of :mod:`mmpa.backends.bag.messages` (frames REP-105 / REP-103;
units m, rad, s; stamps in seconds), reached two ways:

- **fast paths** for the streams: :func:`laser_scan` fills a ``sensor_msgs/LaserScan`` with the
  ranges and intensities as float32 buffers (no Python loop over the beams);
  :func:`from_laser_scan` is the bag reader's own, which reads any object with the ``.msg``
  field names (``rclpy``'s included); :func:`scan_ranges` views the ranges as a numpy array
  without a copy;
- **the CDR bridge** for every other type: :func:`to_rclpy` serializes a message built by
  :mod:`mmpa.backends.bag.messages` (``rosbags``) with the Jazzy type store and deserializes
  the bytes as the ``rclpy`` class of the same name, so each builder there is a builder here;
  :func:`from_rclpy` goes back. The bytes are the ones DDS carries and a bag stores.

A type is named as ``pkg/msg/Name``; its ``rclpy`` class comes from the installed interface
package (``tf2_msgs`` and ``nav2_msgs`` are built by ``scripts/ros2-interfaces.sh``).
"""

from __future__ import annotations

import array
import importlib
from functools import cache
from pathlib import Path
from typing import Any

import numpy as np
from rclpy.serialization import deserialize_message, serialize_message
from rosbags.typesys import Stores, get_types_from_msg, get_typestore

from mmpa.backends.bag import messages as bag
from mmpa.core.errors import InvalidInputError, MMPAError
from mmpa.core.geometry import Array
from mmpa.robot.interfaces import LaserScan

__all__ = [
    "INTERFACES",
    "InterfaceMissingError",
    "from_laser_scan",
    "from_rclpy",
    "from_tf_message",
    "laser_scan",
    "message_class",
    "scan_ranges",
    "tf_message",
    "to_rclpy",
    "type_name",
    "typestore",
]

#: the ``.msg`` sources of the interface packages mmpa builds (scripts/ros2-interfaces.sh)
INTERFACES = Path(__file__).resolve().parent / "interfaces"

#: the reader of the bag backend reads rclpy messages as they are (same field names)
from_laser_scan = bag.from_laser_scan


class InterfaceMissingError(MMPAError):
    """A message type's interface package is not installed in this environment."""


@cache
def typestore() -> Any:
    """The ROS 2 Jazzy type store of ``rosbags`` with the interfaces mmpa builds registered
    (``nav2_msgs/msg/Particle``, ``nav2_msgs/msg/ParticleCloud``) from the same ``.msg``
    files, so their type hashes can be computed independently of rosidl."""
    store = get_typestore(Stores.ROS2_JAZZY)
    extra: dict[str, Any] = {}
    for path in sorted(INTERFACES.glob("*/msg/*.msg")):
        name = f"{path.parents[1].name}/msg/{path.stem}"
        if name not in store.fielddefs:
            extra.update(get_types_from_msg(path.read_text(), name))
    store.register(extra)
    return store


@cache
def message_class(name: str) -> type:
    """The ``rclpy`` class of ``pkg/msg/Name`` (raises :class:`InterfaceMissingError` naming
    the package when it is not installed)."""
    parts = name.split("/")
    if len(parts) != 3 or parts[1] != "msg" or not all(parts):
        raise InvalidInputError(f"a message type is named pkg/msg/Name, got {name!r}")
    pkg, _, cls = parts
    try:
        module = importlib.import_module(f"{pkg}.msg")
    except ImportError as e:
        hint = (
            "build it with scripts/ros2-interfaces.sh (make setup)"
            if (INTERFACES / pkg).is_dir()
            else f"install the wheel ros-jazzy-{pkg.replace('_', '-')}"
        )
        raise InterfaceMissingError(f"the ROS 2 interface package {pkg} is missing: {hint}") from e
    try:
        return getattr(module, cls)
    except AttributeError as e:
        raise InterfaceMissingError(f"{pkg} has no message {cls}") from e


def type_name(msg: Any) -> str:
    """``pkg/msg/Name`` of an ``rclpy`` message (its class's module is ``pkg.msg._name``)."""
    cls = type(msg)
    return f"{cls.__module__.split('.')[0]}/msg/{cls.__name__}"


def to_rclpy(msg: Any, name: str | None = None) -> Any:
    """A ``rosbags`` message (e.g. built by :mod:`mmpa.backends.bag.messages`) -> the
    ``rclpy`` message of the same type, through its CDR bytes (Jazzy definitions; a field the
    Jazzy type lacks or adds fails here, not on the wire)."""
    name = name or msg.__msgtype__
    raw = typestore().serialize_cdr(msg, name)
    return deserialize_message(bytes(raw), message_class(name))


def from_rclpy(msg: Any) -> Any:
    """An ``rclpy`` message -> the ``rosbags`` message of the same type (the readers of
    :mod:`mmpa.backends.bag.messages` take either)."""
    return typestore().deserialize_cdr(serialize_message(msg), type_name(msg))


def _f32(values: Array) -> array.array:
    out = array.array("f")
    out.frombytes(np.ascontiguousarray(values, dtype=np.float32).tobytes())
    return out


def laser_scan(scan: LaserScan, frame_id: str | None = None) -> Any:
    """``sensor_msgs/LaserScan`` of a :class:`LaserScan` (fields as
    :func:`mmpa.backends.bag.messages.laser_scan`: float32 ranges and intensities, ``inf``
    kept; the stamp in integer nanoseconds)."""
    msg = message_class("sensor_msgs/msg/LaserScan")()
    ns = bag.stamp_ns(scan.stamp)
    msg.header.stamp.sec, msg.header.stamp.nanosec = divmod(ns, 1_000_000_000)
    msg.header.frame_id = frame_id or scan.frame_id
    msg.angle_min = float(scan.angle_min)
    msg.angle_max = float(scan.angle_max)
    msg.angle_increment = float(scan.angle_increment)
    msg.time_increment = float(scan.time_increment)
    msg.scan_time = float(scan.scan_time)
    msg.range_min = float(scan.range_min)
    msg.range_max = float(scan.range_max)
    msg.ranges = _f32(scan.ranges)
    msg.intensities = _f32(scan.intensities)
    return msg


def scan_ranges(msg: Any) -> np.ndarray:
    """The ranges of a ``sensor_msgs/LaserScan`` as a read-only float32 view (no copy; m,
    ``inf`` where nothing returned)."""
    return np.frombuffer(msg.ranges, dtype=np.float32)


def tf_message(stamp: float, transforms: list[tuple[str, str, Array]]) -> Any:
    """``tf2_msgs/TFMessage`` of ``(parent, child, pose)`` triples (``child``'s pose in
    ``parent``: 4x4 or planar ``[x, y, theta]``), all at ``stamp`` s."""
    parts = [bag.transform_stamped(stamp, p, c, Tm) for p, c, Tm in transforms]
    return to_rclpy(bag.tf_message(parts), "tf2_msgs/msg/TFMessage")


def from_tf_message(msg: Any) -> list[tuple[float, str, str, Array]]:
    """``tf2_msgs/TFMessage`` -> ``(stamp s, parent, child, 4x4)`` per transform."""
    out = []
    for ts in msg.transforms:
        parent, child, Tm = bag.from_transform(ts)
        stamp = float(ts.header.stamp.sec) + 1e-9 * float(ts.header.stamp.nanosec)
        out.append((stamp, parent, child, Tm))
    return out
