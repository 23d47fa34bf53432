"""mmpa values <-> ROS 2 messages (``rosbags`` message classes; no hand-written serializer).

Every builder returns a message object of the ROS 2 Humble type store
(:func:`typestore`), ready for :meth:`mmpa.backends.bag.writer.BagWriter.write`. Every reader takes
a deserialized message of ROS 1 or ROS 2 (``rosbags`` names fields as the ``.msg`` does, so
ROS 1 ``CameraInfo.K`` is ROS 2 ``k``) and returns mmpa's own value.

Frames follow REP-105 / REP-103: ``map`` -> ``odom`` -> ``base_link`` -> ``laser``,
``arm_base`` -> ``link1`` .. ``link6`` (= ``flange``) -> ``tcp``,
``camera_color_optical_frame`` (z forward, x right, y down). Stamps are seconds of sim time.

Units: m, rad, s; depth images ``16UC1`` in millimetres (0: no return), as a RealSense
publishes its aligned depth.
"""

from __future__ import annotations

import logging
import math
from functools import cache
from typing import Any

import numpy as np
from rosbags.typesys import Stores, get_typestore

from mmpa.core.errors import InvalidInputError
from mmpa.core.geometry import Array, make_T, quat_xyzw_to_R
from mmpa.robot.description import CameraIntrinsics
from mmpa.robot.interfaces import LaserScan, Odometry, RGBDFrame

__all__ = [
    "FRAMES",
    "T",
    "camera_info",
    "depth_image",
    "diagnostics",
    "from_camera_info",
    "from_depth_image",
    "from_image_rgb",
    "from_joint_state",
    "from_laser_scan",
    "from_odometry",
    "from_pose",
    "from_pose_cov",
    "from_transform",
    "joint_state",
    "laser_scan",
    "occupancy_grid",
    "odometry",
    "pose_array",
    "pose_cov_stamped",
    "pose_stamped",
    "range_msg",
    "reflector_markers",
    "rgb_image",
    "stamp_ns",
    "tf_message",
    "transform_stamped",
    "typestore",
]

#: REP-105 frame names used by the recorder
FRAMES = {
    "map": "map",
    "odom": "odom",
    "base": "base_link",
    "laser": "laser",
    "arm_base": "arm_base",
    "flange": "flange",
    "tcp": "tcp",
    "camera": "camera_color_optical_frame",
    "photosensor": "photosensor",
}


@cache
def typestore() -> Any:
    """The ROS 2 Humble type store of ``rosbags`` (message classes, CDR serialization)."""

    return get_typestore(Stores.ROS2_HUMBLE)


@cache
def T(name: str) -> Any:
    """The message class ``name`` (e.g. ``"sensor_msgs/msg/LaserScan"``)."""
    return typestore().types[name]


def stamp_ns(t: float) -> int:
    """Seconds -> integer nanoseconds (rounded)."""
    if not math.isfinite(t) or t < 0:
        raise InvalidInputError(f"a bag stamp must be a finite time >= 0 s, got {t}")
    return round(t * 1e9)


def _time(t: float) -> Any:
    ns = stamp_ns(t)
    return T("builtin_interfaces/msg/Time")(sec=ns // 1_000_000_000, nanosec=ns % 1_000_000_000)


def _header(t: float, frame_id: str) -> Any:
    return T("std_msgs/msg/Header")(stamp=_time(t), frame_id=frame_id)


def _stamp_of(header: Any) -> float:
    """Seconds of a ROS 1 or ROS 2 header stamp."""
    s = header.stamp
    return float(s.sec) + 1e-9 * float(s.nanosec)


def _quat_xyzw(R: Array) -> tuple[float, float, float, float]:
    """Unit quaternion ``(x, y, z, w)`` with ``w >= 0`` of a rotation matrix (Shepperd's
    method, largest-diagonal branch: fast for one matrix, unlike a batched routine)."""
    m = np.asarray(R, float).tolist()
    (r00, r01, r02), (r10, r11, r12), (r20, r21, r22) = m
    tr = r00 + r11 + r22
    if tr > 0:
        s = 2.0 * math.sqrt(1.0 + tr)
        q = ((r21 - r12) / s, (r02 - r20) / s, (r10 - r01) / s, 0.25 * s)
    elif r00 > r11 and r00 > r22:
        s = 2.0 * math.sqrt(1.0 + r00 - r11 - r22)
        q = (0.25 * s, (r01 + r10) / s, (r02 + r20) / s, (r21 - r12) / s)
    elif r11 > r22:
        s = 2.0 * math.sqrt(1.0 + r11 - r00 - r22)
        q = ((r01 + r10) / s, 0.25 * s, (r12 + r21) / s, (r02 - r20) / s)
    else:
        s = 2.0 * math.sqrt(1.0 + r22 - r00 - r11)
        q = ((r02 + r20) / s, (r12 + r21) / s, 0.25 * s, (r10 - r01) / s)
    n = math.sqrt(sum(v * v for v in q))
    sign = -1.0 if q[3] < 0 else 1.0
    return (sign * q[0] / n, sign * q[1] / n, sign * q[2] / n, sign * q[3] / n)


def _quat(R: Array) -> Any:
    x, y, z, w = _quat_xyzw(R)
    return T("geometry_msgs/msg/Quaternion")(x=x, y=y, z=z, w=w)


def _yaw_quat(theta: float) -> Any:
    return T("geometry_msgs/msg/Quaternion")(
        x=0.0, y=0.0, z=math.sin(theta / 2), w=math.cos(theta / 2)
    )


def _pose_T(Tm: Array) -> Any:
    p = T("geometry_msgs/msg/Point")(x=float(Tm[0, 3]), y=float(Tm[1, 3]), z=float(Tm[2, 3]))
    return T("geometry_msgs/msg/Pose")(position=p, orientation=_quat(Tm[:3, :3]))


def _pose2d(pose: Array) -> Any:
    x, y, th = (float(v) for v in np.asarray(pose, float).reshape(3))
    p = T("geometry_msgs/msg/Point")(x=x, y=y, z=0.0)
    return T("geometry_msgs/msg/Pose")(position=p, orientation=_yaw_quat(th))


def _pose_any(pose: Array) -> Any:
    a = np.asarray(pose, float)
    return _pose2d(a) if a.shape == (3,) else _pose_T(a)


def _R_of(q: Any) -> Array:
    return quat_xyzw_to_R([q.x, q.y, q.z, q.w])


def from_pose(pose: Any) -> Array:
    """``geometry_msgs/Pose`` -> 4x4 transform."""
    p = pose.position
    return make_T(_R_of(pose.orientation), [p.x, p.y, p.z])


def _planar(Tm: Array) -> Array:
    return np.array([Tm[0, 3], Tm[1, 3], math.atan2(Tm[1, 0], Tm[0, 0])])


# --- sensors ---------------------------------------------------------------------------------


def laser_scan(scan: LaserScan, frame_id: str | None = None) -> Any:
    """``sensor_msgs/LaserScan`` (ranges and intensities as float32, ``inf`` kept)."""
    return T("sensor_msgs/msg/LaserScan")(
        header=_header(scan.stamp, frame_id or scan.frame_id),
        angle_min=float(scan.angle_min),
        angle_max=float(scan.angle_max),
        angle_increment=float(scan.angle_increment),
        time_increment=float(scan.time_increment),
        scan_time=float(scan.scan_time),
        range_min=float(scan.range_min),
        range_max=float(scan.range_max),
        ranges=np.asarray(scan.ranges, dtype=np.float32),
        intensities=np.asarray(scan.intensities, dtype=np.float32),
    )


def from_laser_scan(msg: Any) -> LaserScan:
    """``sensor_msgs/LaserScan`` -> :class:`LaserScan` (float64 arrays; a scan without
    intensities gets zeros). The beam count comes from the ranges; ``angle_max`` is set to
    the last beam's angle so the value is consistent even when a driver rounds it."""
    r = np.asarray(msg.ranges, dtype=np.float64)
    n = r.shape[0]
    if n == 0:
        raise InvalidInputError("a LaserScan message with no ranges")
    inten = np.asarray(msg.intensities, dtype=np.float64)
    if inten.shape != r.shape:
        inten = np.zeros_like(r)
    inc = float(msg.angle_increment)
    return LaserScan(
        angle_min=float(msg.angle_min),
        angle_max=float(msg.angle_min) + inc * (n - 1),
        angle_increment=inc,
        time_increment=float(msg.time_increment),
        scan_time=float(msg.scan_time),
        range_min=float(msg.range_min),
        range_max=float(msg.range_max),
        ranges=r,
        intensities=inten,
        stamp=_stamp_of(msg.header),
        frame_id=str(msg.header.frame_id),
    )


def _cov6(cov3: Array | None) -> np.ndarray:
    """Planar (3, 3) covariance of ``[x, y, theta]`` -> ROS 6x6 row-major (x y z R P Y)."""
    out = np.zeros((6, 6))
    if cov3 is not None:
        idx = [0, 1, 5]
        out[np.ix_(idx, idx)] = np.asarray(cov3, float).reshape(3, 3)
    return out.reshape(36)


def _cov3(cov36: Any) -> Array:
    c = np.asarray(cov36, float).reshape(6, 6)
    idx = [0, 1, 5]
    return c[np.ix_(idx, idx)].copy()


def odometry(odo: Odometry) -> Any:
    """``nav_msgs/Odometry``: planar pose in ``odom``, body twist ``[v, w]``."""
    tw = T("geometry_msgs/msg/Twist")(
        linear=T("geometry_msgs/msg/Vector3")(x=float(odo.twist[0]), y=0.0, z=0.0),
        angular=T("geometry_msgs/msg/Vector3")(x=0.0, y=0.0, z=float(odo.twist[1])),
    )
    return T("nav_msgs/msg/Odometry")(
        header=_header(odo.stamp, odo.frame_id),
        child_frame_id=odo.child_frame_id,
        pose=T("geometry_msgs/msg/PoseWithCovariance")(
            pose=_pose2d(odo.pose), covariance=np.zeros(36)
        ),
        twist=T("geometry_msgs/msg/TwistWithCovariance")(twist=tw, covariance=np.zeros(36)),
    )


def from_odometry(msg: Any) -> Odometry:
    """``nav_msgs/Odometry`` -> :class:`Odometry` (the planar part of the pose)."""
    pose = _planar(from_pose(msg.pose.pose))
    tw = msg.twist.twist
    return Odometry(
        pose=pose,
        twist=np.array([float(tw.linear.x), float(tw.angular.z)]),
        stamp=_stamp_of(msg.header),
        frame_id=str(msg.header.frame_id),
        child_frame_id=str(msg.child_frame_id),
    )


def _image(stamp: float, frame_id: str, encoding: str, pixels: np.ndarray) -> Any:
    """``sensor_msgs/Image`` of ``pixels`` (H, W[, C]), little-endian, rows packed."""
    px = np.ascontiguousarray(pixels)
    h, w = px.shape[:2]
    return T("sensor_msgs/msg/Image")(
        header=_header(stamp, frame_id),
        height=h,
        width=w,
        encoding=encoding,
        is_bigendian=0,
        step=px.strides[0],
        data=px.reshape(-1).view(np.uint8),
    )


def rgb_image(frame: RGBDFrame, frame_id: str = FRAMES["camera"]) -> Any:
    """``sensor_msgs/Image`` ``rgb8`` of the colour image."""
    return _image(frame.stamp, frame_id, "rgb8", np.asarray(frame.color, dtype=np.uint8))


def depth_image(frame: RGBDFrame, frame_id: str = FRAMES["camera"]) -> Any:
    """``sensor_msgs/Image`` ``16UC1``: depth in millimetres (rounded; 0 where invalid),
    aligned to colour, so it shares the colour optical frame."""
    d = np.asarray(frame.depth, dtype=np.float64)
    mm = np.where(np.isfinite(d) & (d > 0), np.rint(d * 1000.0), 0.0)
    return _image(frame.stamp, frame_id, "16UC1", np.clip(mm, 0, 65535).astype("<u2"))


def from_image_rgb(msg: Any) -> np.ndarray:
    """``rgb8`` / ``bgr8`` ``sensor_msgs/Image`` -> (H, W, 3) uint8 RGB."""
    enc = str(msg.encoding)
    if enc not in ("rgb8", "bgr8"):
        raise InvalidInputError(f"colour image encoding {enc!r} is not supported (rgb8, bgr8)")
    h, w, step = int(msg.height), int(msg.width), int(msg.step)
    buf = np.asarray(msg.data, dtype=np.uint8).reshape(h, step)[:, : 3 * w]
    img = buf.reshape(h, w, 3)
    return np.ascontiguousarray(img[..., ::-1] if enc == "bgr8" else img)


def from_depth_image(msg: Any) -> np.ndarray:
    """``16UC1`` (mm) or ``32FC1`` (m) ``sensor_msgs/Image`` -> (H, W) float32 m, 0 invalid."""
    enc = str(msg.encoding)
    h, w, step = int(msg.height), int(msg.width), int(msg.step)
    raw = np.asarray(msg.data, dtype=np.uint8).reshape(h, step)
    end = ">" if msg.is_bigendian else "<"
    if enc in ("16UC1", "mono16"):
        d = raw[:, : 2 * w].copy().view(end + "u2").astype(np.float32) / 1000.0
    elif enc == "32FC1":
        d = raw[:, : 4 * w].copy().view(end + "f4").astype(np.float32)
        d[~np.isfinite(d)] = 0.0
    else:
        raise InvalidInputError(f"depth image encoding {enc!r} is not supported (16UC1, 32FC1)")
    return d.reshape(h, w)


def camera_info(k: CameraIntrinsics, stamp: float, frame_id: str = FRAMES["camera"]) -> Any:
    """``sensor_msgs/CameraInfo`` of an ideal pinhole (``plumb_bob``, zero distortion)."""
    K = k.K
    P = np.zeros((3, 4))
    P[:, :3] = K
    roi = T("sensor_msgs/msg/RegionOfInterest")(
        x_offset=0, y_offset=0, height=0, width=0, do_rectify=False
    )
    return T("sensor_msgs/msg/CameraInfo")(
        header=_header(stamp, frame_id),
        height=k.height,
        width=k.width,
        distortion_model="plumb_bob",
        d=np.zeros(5),
        k=K.reshape(9).astype(float),
        r=np.eye(3).reshape(9),
        p=P.reshape(12),
        binning_x=0,
        binning_y=0,
        roi=roi,
    )


def from_camera_info(msg: Any) -> CameraIntrinsics:
    """``sensor_msgs/CameraInfo`` (ROS 1 ``K`` or ROS 2 ``k``) -> :class:`CameraIntrinsics`.
    An uncalibrated camera (``K`` zero, as drivers publish it without a calibration) or a
    size of 0 is refused (InvalidInputError); a distortion model mmpa ignores is logged."""
    K = np.asarray(getattr(msg, "k", None) if hasattr(msg, "k") else msg.K, float).reshape(3, 3)
    fx, fy, cx, cy = float(K[0, 0]), float(K[1, 1]), float(K[0, 2]), float(K[1, 2])
    w, h = int(msg.width), int(msg.height)
    if (
        not all(math.isfinite(v) for v in (fx, fy, cx, cy))
        or fx <= 0
        or fy <= 0
        or w <= 0
        or h <= 0
    ):
        raise InvalidInputError(
            f"camera info of frame {msg.header.frame_id!r} is not a calibrated camera "
            f"({w}x{h}, fx {fx}, fy {fy}): calibrate it (camera_calibration) or give the "
            "intrinsics (mmpa register --intrinsics)"
        )
    D = np.asarray(getattr(msg, "d", None) if hasattr(msg, "d") else msg.D, float)
    if D.size and np.abs(D).max() > 1e-9:
        logging.getLogger(__name__).warning(
            "camera info of frame %r has %s distortion %s; mmpa assumes a pinhole",
            str(msg.header.frame_id),
            str(msg.distortion_model),
            np.round(D, 5).tolist(),
        )
    return CameraIntrinsics(width=w, height=h, fx=fx, fy=fy, cx=cx, cy=cy)


def range_msg(
    stamp: float, frame_id: str, distance: float, max_range: float, fov: float = 0.0
) -> Any:
    """``sensor_msgs/Range`` of a single-beam infrared (laser) sensor: ``distance`` m to the
    first surface on the beam, ``+inf`` when none within ``max_range`` (REP-117)."""
    return T("sensor_msgs/msg/Range")(
        header=_header(stamp, frame_id),
        radiation_type=1,  # INFRARED
        field_of_view=float(fov),
        min_range=0.0,
        max_range=float(max_range),
        range=float(distance) if math.isfinite(distance) else math.inf,
    )


def joint_state(stamp: float, names: list[str], q: Array, qd: Array | None = None) -> Any:
    """``sensor_msgs/JointState`` (rad, rad/s; no effort)."""
    q = np.ascontiguousarray(q, dtype=float).reshape(-1)  # CDR needs packed arrays
    if len(names) != q.shape[0]:
        raise InvalidInputError(f"{len(names)} joint names for {q.shape[0]} positions")
    v = np.zeros(0) if qd is None else np.ascontiguousarray(qd, dtype=float).reshape(-1)
    return T("sensor_msgs/msg/JointState")(
        header=_header(stamp, ""), name=list(names), position=q, velocity=v, effort=np.zeros(0)
    )


def from_joint_state(msg: Any) -> tuple[float, list[str], Array, Array | None]:
    """``sensor_msgs/JointState`` (ROS 1 or ROS 2) -> ``(stamp s, names, positions (n,) rad,
    velocities (n,) rad/s or None when the message carries none)``."""
    names = [str(n) for n in msg.name]
    q = np.asarray(msg.position, dtype=np.float64).reshape(-1)
    if q.shape[0] != len(names):
        raise InvalidInputError(f"a JointState with {len(names)} names and {q.shape[0]} positions")
    v = np.asarray(msg.velocity, dtype=np.float64).reshape(-1)
    return _stamp_of(msg.header), names, q, (v if v.shape == q.shape else None)


# --- transforms and poses --------------------------------------------------------------------


def transform_stamped(stamp: float, parent: str, child: str, Tm: Array) -> Any:
    """``geometry_msgs/TransformStamped``: ``child``'s pose in ``parent`` (4x4 or planar
    ``[x, y, theta]``)."""
    a = np.asarray(Tm, float)
    if a.shape == (3,):
        tr = T("geometry_msgs/msg/Vector3")(x=float(a[0]), y=float(a[1]), z=0.0)
        rot = _yaw_quat(float(a[2]))
    else:
        tr = T("geometry_msgs/msg/Vector3")(x=float(a[0, 3]), y=float(a[1, 3]), z=float(a[2, 3]))
        rot = _quat(a[:3, :3])
    return T("geometry_msgs/msg/TransformStamped")(
        header=_header(stamp, parent),
        child_frame_id=child,
        transform=T("geometry_msgs/msg/Transform")(translation=tr, rotation=rot),
    )


def from_transform(ts: Any) -> tuple[str, str, Array]:
    """``geometry_msgs/TransformStamped`` -> ``(parent, child, 4x4)``."""
    tr = ts.transform
    t = tr.translation
    return (
        str(ts.header.frame_id),
        str(ts.child_frame_id),
        make_T(_R_of(tr.rotation), [t.x, t.y, t.z]),
    )


def diagnostics(stamp: float, name: str, ok: bool, message: str, values: dict[str, Any]) -> Any:
    """``diagnostic_msgs/DiagnosticArray`` (``/diagnostics``) with one status ``name``:
    level OK (0) or ERROR (2) by ``ok``, ``message`` (the reason), ``values`` as key/value
    strings (floats with 4 significant digits)."""
    kv = T("diagnostic_msgs/msg/KeyValue")
    st = T("diagnostic_msgs/msg/DiagnosticStatus")
    items = [
        kv(key=str(k), value=f"{v:.4g}" if isinstance(v, float) else str(v))
        for k, v in values.items()
    ]
    status = st(level=0 if ok else 2, name=name, message=message, hardware_id="", values=items)
    return T("diagnostic_msgs/msg/DiagnosticArray")(header=_header(stamp, ""), status=[status])


def tf_message(transforms: list[Any]) -> Any:
    """``tf2_msgs/TFMessage`` of ``TransformStamped`` messages."""
    return T("tf2_msgs/msg/TFMessage")(transforms=list(transforms))


def pose_stamped(stamp: float, frame_id: str, pose: Array) -> Any:
    """``geometry_msgs/PoseStamped`` of a 4x4 pose or a planar ``[x, y, theta]``."""
    return T("geometry_msgs/msg/PoseStamped")(header=_header(stamp, frame_id), pose=_pose_any(pose))


def pose_cov_stamped(stamp: float, frame_id: str, pose: Array, cov: Array | None) -> Any:
    """``geometry_msgs/PoseWithCovarianceStamped`` (``/amcl_pose``, ``/initialpose``) of a
    planar pose and its (3, 3) covariance (x, y, theta; None: zeros)."""
    return T("geometry_msgs/msg/PoseWithCovarianceStamped")(
        header=_header(stamp, frame_id),
        pose=T("geometry_msgs/msg/PoseWithCovariance")(pose=_pose2d(pose), covariance=_cov6(cov)),
    )


def from_pose_cov(msg: Any) -> tuple[float, Array, Array]:
    """``PoseWithCovarianceStamped`` -> ``(stamp s, [x, y, theta], (3, 3) covariance)``."""
    return (
        _stamp_of(msg.header),
        _planar(from_pose(msg.pose.pose)),
        _cov3(msg.pose.covariance),
    )


def pose_array(stamp: float, frame_id: str, poses: Array) -> Any:
    """``geometry_msgs/PoseArray`` (``/particlecloud``) of planar poses (N, 3)."""
    P = np.asarray(poses, float).reshape(-1, 3)
    Pose, Point, Quat = (
        T("geometry_msgs/msg/Pose"),
        T("geometry_msgs/msg/Point"),
        T("geometry_msgs/msg/Quaternion"),
    )
    half = 0.5 * P[:, 2]
    c, s = np.cos(half).tolist(), np.sin(half).tolist()
    rows = zip(P[:, 0].tolist(), P[:, 1].tolist(), s, c, strict=True)
    out = [
        Pose(position=Point(x=x, y=y, z=0.0), orientation=Quat(x=0.0, y=0.0, z=qz, w=qw))
        for x, y, qz, qw in rows
    ]
    return T("geometry_msgs/msg/PoseArray")(header=_header(stamp, frame_id), poses=out)


def occupancy_grid(grid: Any, stamp: float, frame_id: str = FRAMES["map"]) -> Any:
    """``nav_msgs/OccupancyGrid`` of a :class:`~mmpa.maps.occupancy.OccupancyGrid` (same
    layout: row 0 at the bottom, -1 / 0..100)."""
    ox, oy, _ = grid.origin
    info = T("nav_msgs/msg/MapMetaData")(
        map_load_time=_time(stamp),
        resolution=float(grid.resolution),
        width=int(grid.width),
        height=int(grid.height),
        origin=_pose2d([ox, oy, 0.0]),
    )
    return T("nav_msgs/msg/OccupancyGrid")(
        header=_header(stamp, frame_id),
        info=info,
        data=np.ascontiguousarray(grid.data, dtype=np.int8).reshape(-1),
    )


def reflector_markers(
    stamp: float,
    positions: Array,
    radius: float,
    ns: str = "reflectors",
    frame_id: str = FRAMES["map"],
    rgba: tuple[float, float, float, float] = (1.0, 0.85, 0.0, 1.0),
    height: float = 1.0,
) -> Any:
    """``visualization_msgs/MarkerArray``: one cylinder per reflector (``positions`` (N, 2) m,
    ``radius`` m, ``height`` m tall, standing on the floor)."""
    P = np.asarray(positions, float).reshape(-1, 2)
    d = 2.0 * max(float(radius), 0.005)
    markers = []
    for i, (x, y) in enumerate(P):
        Mk = T("visualization_msgs/msg/Marker")
        markers.append(
            Mk(
                header=_header(stamp, frame_id),
                ns=ns,
                id=i,
                type=Mk.CYLINDER,
                action=Mk.ADD,
                pose=_pose_T(make_T(None, [x, y, 0.5 * height])),  # standing on the floor
                scale=T("geometry_msgs/msg/Vector3")(x=d, y=d, z=height),
                color=T("std_msgs/msg/ColorRGBA")(r=rgba[0], g=rgba[1], b=rgba[2], a=rgba[3]),
                lifetime=T("builtin_interfaces/msg/Duration")(sec=0, nanosec=0),
                frame_locked=False,
                points=[],
                colors=[],
                texture_resource="",
                texture=T("sensor_msgs/msg/CompressedImage")(
                    header=_header(stamp, ""), format="", data=np.zeros(0, np.uint8)
                ),
                uv_coordinates=[],
                text="",
                mesh_resource="",
                mesh_file=T("visualization_msgs/msg/MeshFile")(
                    filename="", data=np.zeros(0, np.uint8)
                ),
                mesh_use_embedded_materials=False,
            )
        )
    return T("visualization_msgs/msg/MarkerArray")(markers=markers)
