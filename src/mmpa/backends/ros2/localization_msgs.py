"""The messages of a localization node, as Nav2's ``amcl`` publishes and reads them.

- :func:`from_occupancy_grid`: ``nav_msgs/OccupancyGrid`` (``/map``, row 0 at the bottom,
  -1 unknown, 0..100 occupied percent) -> :class:`~mmpa.maps.occupancy.OccupancyGrid`, with
  the surveyed reflectors (m, ``map``) the message cannot carry;
- :func:`pose_with_covariance`: ``geometry_msgs/PoseWithCovarianceStamped`` (``/amcl_pose``)
  of a planar pose ``[x, y, theta]`` and its (3, 3) covariance (rows x, y, yaw of ROS's 6x6);
  :func:`pose_with_covariance_cdr` the same as its serialized bytes (what the node publishes);
- :func:`particle_cloud`: ``nav2_msgs/ParticleCloud`` (``/particle_cloud``): planar poses
  (N, 3) with their weights; :func:`particle_cloud_cdr` the same as its serialized bytes,
  built with numpy (what the node publishes: 1000 particles as rclpy objects cost ~19 ms);
- :func:`from_reflector_markers`: ``visualization_msgs/MarkerArray`` (``/reflectors``, one
  cylinder per surveyed reflector, as :func:`mmpa.backends.bag.messages.reflector_markers`
  draws them) -> positions (N, 2) m in the markers' frame and the radius m;
- :func:`diagnostics`: ``diagnostic_msgs/DiagnosticArray`` with one status (OK / ERROR and
  the reason).

Built through :func:`mmpa.backends.ros2.messages.to_rclpy` on the bag backend's builders
where one exists (same bytes as a bag holds), else filled directly.
"""

from __future__ import annotations

import struct
from typing import Any

import numpy as np

from mmpa.backends.bag import messages as bag
from mmpa.backends.ros2.messages import message_class, to_rclpy, typestore
from mmpa.core.errors import InvalidInputError
from mmpa.core.geometry import Array
from mmpa.maps.occupancy import OccupancyGrid

__all__ = [
    "diagnostics",
    "from_occupancy_grid",
    "from_reflector_markers",
    "particle_cloud",
    "particle_cloud_cdr",
    "planar",
    "pose_with_covariance",
    "pose_with_covariance_cdr",
    "stamp_of",
]


def stamp_of(header: Any) -> float:
    """A header's stamp in seconds."""
    return float(header.stamp.sec) + 1e-9 * float(header.stamp.nanosec)


def planar(Tm: Array) -> Array:
    """``[x, y, yaw]`` of a 4x4 pose (the yaw of its x axis in the xy plane)."""
    Tm = np.asarray(Tm, float)
    return np.array([Tm[0, 3], Tm[1, 3], np.arctan2(Tm[1, 0], Tm[0, 0])])


def from_occupancy_grid(
    msg: Any, reflectors: Array | None = None, reflector_radius: float = 0.0
) -> OccupancyGrid:
    """``nav_msgs/OccupancyGrid`` -> :class:`OccupancyGrid` (InvalidInputError on a size
    mismatch, a rotated origin or cells outside -1..100)."""
    w, h = int(msg.info.width), int(msg.info.height)
    data = np.asarray(msg.data, dtype=np.int8)
    if data.size != w * h or w == 0 or h == 0:
        raise InvalidInputError(f"/map holds {data.size} cells for {w} x {h}")
    o = msg.info.origin
    yaw = planar(_T(o))
    return OccupancyGrid(
        data=data.reshape(h, w),
        resolution=float(msg.info.resolution),
        origin=(float(o.position.x), float(o.position.y), float(yaw[2])),
        reflectors=np.zeros((0, 2)) if reflectors is None else reflectors,
        reflector_radius=reflector_radius,
    )


def from_reflector_markers(msg: Any) -> tuple[Array, float]:
    """``/reflectors`` -> ``(positions (N, 2) m, radius m)``: each marker's x, y and half its
    diameter ``scale.x``; the largest radius is taken (the localizers take one). Markers with
    ``action`` DELETE / DELETEALL are skipped. InvalidInputError when none is left or a value
    is not finite."""
    keep = [m for m in msg.markers if m.action == 0]  # ADD / MODIFY
    xy = np.array([[m.pose.position.x, m.pose.position.y] for m in keep], float).reshape(-1, 2)
    radii = np.array([0.5 * m.scale.x for m in keep], float)
    if len(keep) == 0:
        raise InvalidInputError("/reflectors holds no reflector")
    if not (np.isfinite(xy).all() and np.isfinite(radii).all() and (radii > 0).all()):
        raise InvalidInputError("/reflectors: positions and radii must be finite, radii > 0")
    return xy, float(radii.max())


def _T(pose: Any) -> Array:
    """4x4 of a ``geometry_msgs/Pose`` (rclpy)."""
    q = pose.orientation
    x, y, z, w = q.x, q.y, q.z, q.w
    R = np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
            [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
            [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
        ]
    )
    Tm = np.eye(4)
    Tm[:3, :3] = R
    Tm[:3, 3] = [pose.position.x, pose.position.y, pose.position.z]
    return Tm


def pose_with_covariance(stamp: float, frame_id: str, pose: Array, cov: Array | None) -> Any:
    """``geometry_msgs/PoseWithCovarianceStamped`` (rclpy) of a planar pose and covariance."""
    return to_rclpy(bag.pose_cov_stamped(stamp, frame_id, pose, cov))


def pose_with_covariance_cdr(stamp: float, frame_id: str, pose: Array, cov: Array | None) -> bytes:
    """:func:`pose_with_covariance`'s serialized bytes (the same bytes rclpy serializes), for
    raw publishing: 20 us instead of 60 us for the rclpy message and its conversion to C."""
    name = "geometry_msgs/msg/PoseWithCovarianceStamped"
    return bytes(typestore().serialize_cdr(bag.pose_cov_stamped(stamp, frame_id, pose, cov), name))


def from_pose_with_covariance(msg: Any) -> tuple[float, Array, Array]:
    """``PoseWithCovarianceStamped`` (rclpy) -> ``(stamp s, [x, y, yaw], (3, 3) cov)``."""
    cov = np.asarray(msg.pose.covariance, float).reshape(6, 6)[np.ix_([0, 1, 5], [0, 1, 5])]
    return stamp_of(msg.header), planar(_T(msg.pose.pose)), cov


def particle_cloud(stamp: float, frame_id: str, particles: Array, weights: Array) -> Any:
    """``nav2_msgs/ParticleCloud`` of planar particles (N, 3) and their weights (N,)."""
    cloud = message_class("nav2_msgs/msg/ParticleCloud")()
    Particle = message_class("nav2_msgs/msg/Particle")
    ns = bag.stamp_ns(stamp)
    cloud.header.stamp.sec, cloud.header.stamp.nanosec = divmod(ns, 1_000_000_000)
    cloud.header.frame_id = frame_id
    P = np.asarray(particles, float).reshape(-1, 3)
    half = 0.5 * P[:, 2]
    out = []
    for (x, y, _), qz, qw, wt in zip(
        P.tolist(),
        np.sin(half).tolist(),
        np.cos(half).tolist(),
        np.asarray(weights).tolist(),
        strict=True,
    ):
        p = Particle()
        p.pose.position.x, p.pose.position.y = x, y
        p.pose.orientation.z, p.pose.orientation.w = qz, qw
        p.weight = float(wt)
        out.append(p)
    cloud.particles = out
    return cloud


def particle_cloud_cdr(stamp: float, frame_id: str, particles: Array, weights: Array) -> bytes:
    """:func:`particle_cloud`'s serialized bytes (CDR little endian with its encapsulation
    header, as ``rclpy.serialization.serialize_message`` writes them, with zeros in the
    padding as ``rosbags`` writes it), for raw publishing.

    Layout (offsets from the end of the 4-byte encapsulation header, CDR aligns each
    primitive to its size): ``int32 sec, uint32 nanosec, uint32 len, frame_id + NUL``, pad to
    4, ``uint32 count``, pad to 8 (when there is a particle), then per particle 8 float64:
    position x, y, z, orientation x, y, z, w, weight."""
    P = np.asarray(particles, float).reshape(-1, 3)
    sec, nsec = divmod(bag.stamp_ns(stamp), 1_000_000_000)
    fid = frame_id.encode() + b"\0"
    body = struct.pack("<iII", sec, nsec, len(fid)) + fid
    body += b"\0" * (-len(body) % 4) + struct.pack("<I", len(P))
    body += b"\0" * (-len(body) % 8 if len(P) else 0)
    rows = np.zeros((len(P), 8))
    rows[:, :2] = P[:, :2]
    rows[:, 5], rows[:, 6] = np.sin(0.5 * P[:, 2]), np.cos(0.5 * P[:, 2])
    rows[:, 7] = np.asarray(weights, float).reshape(-1)
    return b"\x00\x01\x00\x00" + body + rows.astype("<f8").tobytes()


def diagnostics(stamp: float, name: str, ok: bool, message: str, values: dict[str, Any]) -> Any:
    """``diagnostic_msgs/DiagnosticArray`` (rclpy) with one status: OK (0) or ERROR (2)."""
    return to_rclpy(bag.diagnostics(stamp, name, ok, message, values))
