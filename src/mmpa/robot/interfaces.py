"""Hardware-neutral interfaces (``typing.Protocol``) and the sensor data types they return.

Missions talk to a robot only through these, so a hardware backend can replace the simulator
without touching them. Data types carry ROS-like fields and are plain numpy arrays.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field
from numbers import Real
from typing import Protocol, runtime_checkable

import numpy as np

from mmpa.core.errors import InvalidInputError
from mmpa.core.geometry import Array, apply
from mmpa.robot.description import CameraIntrinsics, RobotDescription
from mmpa.robot.limits import JointLimits

__all__ = [
    "Arm",
    "Base",
    "Camera",
    "Clock",
    "Gripper",
    "LaserScan",
    "Lidar",
    "MobileManipulator",
    "NoClockError",
    "Odometry",
    "OdometrySource",
    "PhotoSensor",
    "PointCloud",
    "RGBDFrame",
    "RobotDevices",
    "StreamingArm",
    "WallClock",
    "deproject",
    "mean_frame",
    "require",
]


@dataclass(frozen=True)
class PointCloud:
    """A colored point cloud: ``points`` (N, 3) m in ``frame``, ``colors`` (N, 3) in [0, 1]
    or None for a colorless cloud (e.g. a depth-only sensor)."""

    points: Array
    colors: Array | None
    frame: str = "camera"

    def __post_init__(self) -> None:
        p = np.asarray(self.points)
        c = p if self.colors is None else np.asarray(self.colors)
        if p.ndim != 2 or p.shape[1] != 3 or c.shape != p.shape:
            raise InvalidInputError(
                f"point cloud needs points (N,3) and colors (N,3); got {p.shape} and {c.shape}"
            )
        for name, a in (("points", p), ("colors", c)):
            if a.dtype.kind not in "biuf":
                raise InvalidInputError(f"point cloud {name} must be numbers, got dtype {a.dtype}")

    def __len__(self) -> int:
        return int(self.points.shape[0])

    def transformed(self, T_new_old: Array, frame: str) -> PointCloud:
        """The same cloud expressed in another frame: ``p_new = T_new_old p_old``."""
        return PointCloud(apply(T_new_old, self.points), self.colors, frame)


@dataclass(frozen=True)
class RGBDFrame:
    """One RGB-D capture, depth aligned to color.

    ``color`` (H, W, 3) uint8 RGB; ``depth`` (H, W) float32 metres along the optical axis,
    0 where invalid; ``intrinsics`` of both; ``stamp`` seconds (sensor clock).
    """

    color: np.ndarray
    depth: np.ndarray
    intrinsics: CameraIntrinsics
    stamp: float
    frame_id: str = "camera"

    def __post_init__(self) -> None:
        h, w = self.intrinsics.height, self.intrinsics.width
        if self.color.shape != (h, w, 3) or self.depth.shape != (h, w):
            raise InvalidInputError(
                f"RGB-D frame shapes color {self.color.shape}, depth {self.depth.shape} do not "
                f"match intrinsics {w}x{h}"
            )

    def to_point_cloud(
        self, min_depth: float = 0.0, max_depth: float = np.inf, stride: int = 1
    ) -> PointCloud:
        """Deproject valid pixels to a colored cloud in the camera optical frame."""
        return deproject(self.depth, self.color, self.intrinsics, min_depth, max_depth, stride)


def mean_frame(frames: list[RGBDFrame]) -> RGBDFrame:
    """Average several captures from one viewpoint into one frame.

    Depth: per-pixel mean over the captures where it is valid, kept where at least half of
    them are valid (averages sensor noise and per-capture depth-scale error by ``1/sqrt(n)``);
    color: per-pixel mean. The stamp is the last capture's.
    """
    if not frames:
        raise InvalidInputError("mean_frame needs at least one RGB-D frame")
    if len(frames) == 1:
        return frames[0]
    # the sums run over the captures in order, in float64 (exact for the uint8 colors)
    D = np.stack([f.depth for f in frames])
    valid = (D > 0) & (D < np.inf)  # False for NaN and inf
    n = valid.sum(axis=0, dtype=np.int32)
    depth = np.where(valid, D, D.dtype.type(0)).sum(axis=0, dtype=np.float64) / np.maximum(n, 1)
    depth[n * 2 < len(frames)] = 0.0
    C = np.stack([f.color for f in frames])
    color = C.sum(axis=0, dtype=np.int32).astype(np.float64) / len(frames)
    f0 = frames[-1]
    return RGBDFrame(
        np.clip(np.rint(color), 0, 255).astype(np.uint8),
        depth.astype(np.float32),
        f0.intrinsics,
        f0.stamp,
        f0.frame_id,
    )


def deproject(
    depth: np.ndarray,
    color: np.ndarray | None,
    intrinsics: CameraIntrinsics,
    min_depth: float = 0.0,
    max_depth: float = np.inf,
    stride: int = 1,
) -> PointCloud:
    """Pinhole deprojection: ``x = (u - cx) z / fx``, ``y = (v - cy) z / fy``, ``z = depth``.

    Pixels with ``depth <= 0``, non-finite, or outside ``[min_depth, max_depth]`` are dropped.
    Returns a :class:`PointCloud` in the camera optical frame (z forward, x right, y down).
    """
    depth = np.asarray(depth)
    if depth.ndim != 2:
        raise InvalidInputError(f"depth must be (H, W), got {depth.shape}")
    v, u = np.mgrid[0 : depth.shape[0] : stride, 0 : depth.shape[1] : stride]
    z = depth[::stride, ::stride].astype(float)
    ok = np.isfinite(z) & (z > 0) & (z >= min_depth) & (z <= max_depth)
    z, u, v = z[ok], u[ok], v[ok]
    x = (u - intrinsics.cx) * z / intrinsics.fx
    y = (v - intrinsics.cy) * z / intrinsics.fy
    pts = np.stack([x, y, z], axis=1)
    if color is None:
        cols = np.full_like(pts, 0.5)
    else:
        cols = color[::stride, ::stride][ok].astype(float) / 255.0
    return PointCloud(pts, cols, "camera")


@dataclass(frozen=True)
class LaserScan:
    """A 2D scan with the fields of ROS ``sensor_msgs/LaserScan``.

    ``ranges`` (N,) m, ``inf`` where nothing returned within ``range_max``; ``intensities``
    (N,) (reflective tape returns > 1000, ordinary surfaces < 300).
    """

    angle_min: float
    angle_max: float
    angle_increment: float
    time_increment: float
    scan_time: float
    range_min: float
    range_max: float
    ranges: Array
    intensities: Array
    stamp: float = 0.0
    frame_id: str = "laser"

    def __post_init__(self) -> None:
        for f in ("angle_min", "angle_max", "angle_increment", "range_min", "range_max"):
            v = getattr(self, f)
            if isinstance(v, bool) or not isinstance(v, Real) or math.isnan(v):
                raise InvalidInputError(f"scan {f} must be a number, got {v!r}")
            if f.startswith("angle") and not math.isfinite(v):
                raise InvalidInputError(f"scan {f} must be finite, got {v!r}")
        if self.angle_increment == 0.0:
            raise InvalidInputError("scan angle_increment must not be 0")
        for f in ("ranges", "intensities"):
            if not isinstance(getattr(self, f), np.ndarray):
                raise InvalidInputError(
                    f"scan {f} must be a numpy array, got {type(getattr(self, f)).__name__}"
                )
        n = round((self.angle_max - self.angle_min) / self.angle_increment) + 1
        if n < 1:
            raise InvalidInputError(
                f"scan angles [{self.angle_min}, {self.angle_max}] step "
                f"{self.angle_increment} hold no beam"
            )
        if self.ranges.shape != (n,) or self.intensities.shape != (n,):
            raise InvalidInputError(
                f"scan has {self.ranges.shape} ranges and {self.intensities.shape} intensities, "
                f"expected {n} from the angle fields"
            )

    @property
    def angles(self) -> Array:
        """Beam angles (rad), shape (N,)."""
        return self.angle_min + self.angle_increment * np.arange(self.ranges.shape[0])

    def valid(self) -> Array:
        """Mask of beams with a finite range inside ``[range_min, range_max]``."""
        r = self.ranges
        return np.isfinite(r) & (r >= self.range_min) & (r <= self.range_max)

    def points(self) -> Array:
        """Valid returns as (M, 2) points in the laser frame."""
        m = self.valid()
        a, r = self.angles[m], self.ranges[m]
        return np.stack([r * np.cos(a), r * np.sin(a)], axis=1)


@dataclass(frozen=True)
class Odometry:
    """Wheel odometry: pose ``[x, y, theta]`` in ``odom`` and body twist ``[v, w]``."""

    pose: Array
    twist: Array
    stamp: float
    frame_id: str = "odom"
    child_frame_id: str = "base_link"
    extra: dict[str, float] = field(default_factory=dict)


@runtime_checkable
class Base(Protocol):
    """A differential-drive mobile base."""

    def set_velocity(self, v: float, w: float) -> None:
        """Command body velocity: ``v`` m/s forward, ``w`` rad/s counter-clockwise."""
        ...

    def stop(self) -> None: ...

    def odometry(self) -> Odometry: ...


@runtime_checkable
class Arm(Protocol):
    """A 6-DOF position-controlled arm.

    Limits contract (every backend): no motion may exceed the arm's joint position, velocity
    or acceleration limits (:class:`mmpa.robot.limits.JointLimits`). A target or path sample
    outside the position limits, a NaN, or a path whose velocity or acceleration breaks the
    limits is refused with :class:`~mmpa.core.errors.JointLimitError` /
    :class:`~mmpa.core.errors.InvalidInputError` before anything moves (callers slow a path down
    with :func:`mmpa.planning.retime`); a path whose start is away from the arm gets a
    limit-respecting approach move, never a jump; streaming set-points (``command``, where a
    backend has it) are velocity- and acceleration-limited by the backend: within ``qdd_max``
    by default, and never beyond the arm's hard stream limit ``qdd_stream_max`` (a backend
    with a ``stream_acceleration_limited`` switch lets a servo loop trade the one for the
    other, :meth:`mmpa.robot.limits.JointLimits.stream`).
    """

    def joint_positions(self) -> Array:
        """Measured joint angles (rad), shape (6,)."""
        ...

    def move_joints(self, q: Array, duration: float | None = None) -> None:
        """Move to ``q`` (rad, shape (6,)) and wait until there (within ``duration`` s)."""
        ...

    def follow(
        self, times: Array, q_path: Array, record_hz: float | None = None
    ) -> tuple[Array, Array] | None:
        """Track a time-parameterized joint path ``q_path`` (T, 6) at ``times`` (T,) s.

        With ``record_hz``, also read the encoders at that rate while moving and return
        ``(t (M,), q (M, 6))``.
        """
        ...


@runtime_checkable
class StreamingArm(Arm, Protocol):
    """An :class:`Arm` that also takes streaming joint set-points (URScript ``servoj``, a
    ros2_control forward position controller): what a visual servo loop drives.

    Streaming contract: ``command(q)`` sets the target ``q`` (rad, (6,)) from now on and
    returns at once; the backend moves its set-point toward it every control period within
    ``stream_limits`` (velocity and acceleration, :func:`mmpa.robot.limits.limit_setpoint`),
    so no stream of commands can drive a joint past them; targets outside the position
    limits are refused before anything moves. ``stream_acceleration_limited`` True (the
    default) keeps the stream within ``limits.qdd_max``; False allows the hard stream limit
    ``qdd_stream_max`` (:meth:`mmpa.robot.limits.JointLimits.stream`). ``stopped()`` says why
    the controller will not move (protective or emergency stop), or None: a mission stops
    with that message."""

    limits: JointLimits
    stream_limits: JointLimits
    stream_acceleration_limited: bool

    def command(self, q: Array) -> None:
        """Streaming target ``q`` (rad, (6,)); returns at once."""
        ...

    def stopped(self) -> str | None:
        """Why the controller will not move (protective / emergency stop), or None."""
        ...


@runtime_checkable
class Gripper(Protocol):
    """A two-finger parallel gripper."""

    def open(self) -> None: ...

    def close(self) -> bool:
        """Close; True if an object is held (fingers stopped before fully closed)."""
        ...

    def width(self) -> float:
        """Current finger gap (m)."""
        ...


@runtime_checkable
class Camera(Protocol):
    """An RGB-D camera (depth aligned to color)."""

    @property
    def intrinsics(self) -> CameraIntrinsics: ...

    def capture(self) -> RGBDFrame: ...


@runtime_checkable
class Lidar(Protocol):
    """A 2D laser scanner."""

    def scan(self) -> LaserScan: ...


@runtime_checkable
class PhotoSensor(Protocol):
    """A photoelectric (retroreflective) sensor: True when its beam returns."""

    def triggered(self) -> bool: ...


@runtime_checkable
class OdometrySource(Protocol):
    """Wheel odometry of a mobile base."""

    def odometry(self) -> Odometry: ...


@runtime_checkable
class Clock(Protocol):
    """The robot's time (s) and a wait of ``duration`` s: the twin steps its physics, a real
    robot sleeps while its drivers run."""

    @property
    def time(self) -> float: ...

    def step(self, duration: float) -> None: ...


@runtime_checkable
class MobileManipulator(Protocol):
    """One robot as every mission takes it: the NOMINAL description the software knows
    (kinematics, mounts, limits: the robot file), its devices (None where the robot has
    none: a fixed-base arm has no base, odometry or lidar) and its clock. The twin
    (``SimWorld``) is one; :class:`RobotDevices` bundles the devices of any other backend.
    A mission checks what it needs with :func:`require`."""

    @property
    def description(self) -> RobotDescription: ...

    @property
    def arm(self) -> Arm | None: ...

    @property
    def camera(self) -> Camera | None: ...

    @property
    def gripper(self) -> Gripper | None: ...

    @property
    def base(self) -> Base | None: ...

    @property
    def odometry(self) -> OdometrySource | None: ...

    @property
    def lidar(self) -> Lidar | None: ...

    @property
    def time(self) -> float: ...

    def step(self, duration: float) -> None: ...


class NoClockError(InvalidInputError, AttributeError):
    """The robot has no clock (an ``AttributeError`` too: such a robot has no ``time``)."""


@dataclass
class RobotDevices:
    """A :class:`MobileManipulator` made of given devices (hardware backends, recordings,
    tests that swap one device): ``clock`` None means the robot has no clock of its own
    (a mission that waits refuses it)."""

    description: RobotDescription
    arm: Arm | None = None
    camera: Camera | None = None
    gripper: Gripper | None = None
    base: Base | None = None
    odometry: OdometrySource | None = None
    lidar: Lidar | None = None
    clock: Clock | None = None

    @property
    def time(self) -> float:
        if self.clock is None:
            raise NoClockError("this robot has no clock (RobotDevices(clock=...))")
        return self.clock.time

    def step(self, duration: float) -> None:
        if self.clock is None:
            raise NoClockError("this robot has no clock (RobotDevices(clock=...))")
        self.clock.step(duration)


class WallClock:
    """A real robot's :class:`Clock`: monotonic wall time (s); ``step`` sleeps while the
    robot's drivers run."""

    @property
    def time(self) -> float:
        return time.monotonic()

    def step(self, duration: float) -> None:
        time.sleep(max(0.0, float(duration)))


def require(robot: MobileManipulator, *devices: str, mission: str = "this mission") -> None:
    """Refuse ``robot`` with :class:`InvalidInputError` naming the ``devices`` (``"arm"``,
    ``"camera"``, ``"gripper"``, ``"base"``, ``"odometry"``, ``"lidar"``) it lacks."""
    missing = [d for d in devices if getattr(robot, d, None) is None]
    if missing:
        raise InvalidInputError(f"{mission} needs the robot's {', '.join(missing)}; it has none")
