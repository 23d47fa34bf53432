"""The robot, described in one place: UR5e-class arm on a differential-drive base.

Everything here is NOMINAL (what the software believes). The simulator builds its TRUE robot
from a perturbed copy (see ``mmpa.backends.twin.error_model``). Poses of mounted parts are stored as
6D vectors ``[tx, ty, tz, roll, pitch, yaw]`` (m, rad) and exposed as 4x4 ``T_a_b``
properties. Units: m, rad, s.
"""

from __future__ import annotations

from functools import cached_property
from typing import Annotated

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, field_validator, model_validator

from mmpa.core.errors import InvalidInputError
from mmpa.core.geometry import Array, vec6_to_T

Vec6 = tuple[float, float, float, float, float, float]

_PI = float(np.pi)

#: a finite value > 0 (lengths, masses, rates, focal lengths) / >= 0 / a count > 0
_Pos = Annotated[float, Field(gt=0, allow_inf_nan=False)]
_NonNeg = Annotated[float, Field(ge=0, allow_inf_nan=False)]
_Count = Annotated[int, Field(gt=0)]


def _check_below(lo: float, hi: float, lo_name: str, hi_name: str) -> None:
    """Raise ``ValueError`` naming both fields unless ``lo < hi`` (a sensor's range)."""
    if lo >= hi:
        raise ValueError(f"{lo_name} ({lo}) must be below {hi_name} ({hi})")


class _Frozen(BaseModel):
    model_config = ConfigDict(frozen=True, extra="forbid", arbitrary_types_allowed=True)


class DHParameters(_Frozen):
    """Standard (distal) Denavit-Hartenberg parameters of a 6-joint arm.

    Link transform ``A_i(q_i) = Rz(q_i + theta_offset_i) Tz(d_i) Tx(a_i) Rx(alpha_i)`` and
    ``T_arm_base_flange(q) = A_1 A_2 ... A_6``. Defaults: UR5e published values
    (Universal Robots, "DH parameters for calculations of kinematics and dynamics").
    """

    a: tuple[float, ...] = (0.0, -0.425, -0.3922, 0.0, 0.0, 0.0)
    d: tuple[float, ...] = (0.1625, 0.0, 0.0, 0.1333, 0.0997, 0.0996)
    alpha: tuple[float, ...] = (_PI / 2, 0.0, 0.0, _PI / 2, -_PI / 2, 0.0)
    theta_offset: tuple[float, ...] = (0.0, 0.0, 0.0, 0.0, 0.0, 0.0)

    @field_validator("a", "d", "alpha", "theta_offset")
    @classmethod
    def _six(cls, v: tuple[float, ...]) -> tuple[float, ...]:
        if len(v) != 6 or not all(np.isfinite(v)):
            raise ValueError(f"need 6 finite values, got {v}")
        return v

    @field_validator("a", "d")
    @classmethod
    def _link_length(cls, v: tuple[float, ...]) -> tuple[float, ...]:
        if any(abs(x) > 10.0 for x in v):  # m: an industrial arm's links are under 2 m
            raise ValueError(f"link lengths must be within 10 m, got {v}")
        return v

    def as_arrays(self) -> tuple[Array, Array, Array, Array]:
        """``(a, d, alpha, theta_offset)`` as float arrays of shape (6,)."""
        return (
            np.array(self.a),
            np.array(self.d),
            np.array(self.alpha),
            np.array(self.theta_offset),
        )


class ArmDescription(_Frozen):
    """UR5e-class arm: kinematics and motion limits (UR5e datasheet)."""

    name: str = "ur5e"
    dh: DHParameters = DHParameters()
    q_min: tuple[float, ...] = (-2 * _PI, -2 * _PI, -_PI, -2 * _PI, -2 * _PI, -2 * _PI)
    q_max: tuple[float, ...] = (2 * _PI, 2 * _PI, _PI, 2 * _PI, 2 * _PI, 2 * _PI)
    qd_max: tuple[float, ...] = (_PI, _PI, _PI, _PI, _PI, _PI)  # 180 deg/s
    qdd_max: tuple[float, ...] = (4.0, 4.0, 4.0, 6.0, 6.0, 6.0)  # rad/s^2, conservative
    # rad/s^2: the hard acceleration limit of a servo stream (``Arm.command``), which every
    # backend enforces on its set-points even when the stream is not held to ``qdd_max``
    # (the tracking grasp of a moving object). A UR has no joint acceleration limit of its
    # own, only torques: ``qdd_max`` are planning values, like the 5 rad/s^2 of UR's
    # ur_moveit_config joint_limits.yaml; ur_rtde refuses joint accelerations above
    # 40 rad/s^2 (``UR_JOINT_ACCELERATION_MAX``), the value here
    qdd_stream_max: tuple[float, ...] = (40.0, 40.0, 40.0, 40.0, 40.0, 40.0)
    qddd_max: tuple[float, ...] = (40.0, 40.0, 40.0, 60.0, 60.0, 60.0)  # rad/s^3, for ruckig
    reach: _Pos = 0.85  # m, from the shoulder axis
    link_masses: tuple[float, ...] = (3.761, 8.058, 2.846, 1.37, 1.3, 0.365)  # kg
    home: tuple[float, ...] = (0.0, -1.8, 1.9, -1.67, -1.5708, 0.0)  # tucked, tool down
    # wrist camera 0.40 m ahead of and 0.85 m above the arm base, looking at the point 0.80 m
    # ahead and 0.40 m up (the back of a 0.72 m desk 0.75 m ahead of base_link): nominal IK
    view_bench: tuple[float, ...] = (2.532, -1.964, 1.165, -1.401, -1.181, -0.481)

    @model_validator(mode="after")
    def _limits(self) -> ArmDescription:
        for name in (
            "q_min",
            "q_max",
            "qd_max",
            "qdd_max",
            "qdd_stream_max",
            "qddd_max",
            "home",
            "view_bench",
            "link_masses",
        ):
            if len(getattr(self, name)) != 6:
                raise ValueError(f"arm.{name} needs 6 values")
        if any(lo >= hi for lo, hi in zip(self.q_min, self.q_max, strict=True)):
            raise ValueError("arm.q_min must be below arm.q_max for every joint")
        for name in ("qd_max", "qdd_max", "qdd_stream_max", "qddd_max"):
            if not all(np.isfinite(v) and v > 0 for v in getattr(self, name)):
                raise ValueError(f"arm.{name} must be finite and positive for every joint")
        for name in ("home", "view_bench"):
            q = getattr(self, name)
            if not all(lo <= x <= hi for x, lo, hi in zip(q, self.q_min, self.q_max, strict=True)):
                raise ValueError(f"arm.{name} {list(q)} is outside the joint limits")
        if any(s < a for s, a in zip(self.qdd_stream_max, self.qdd_max, strict=True)):
            raise ValueError(
                "arm.qdd_stream_max (the servo stream's hard acceleration limit) must be at "
                "least arm.qdd_max for every joint"
            )
        return self

    @property
    def q_limits(self) -> tuple[Array, Array]:
        """Joint limits ``(q_min, q_max)``, each shape (6,) rad."""
        return np.array(self.q_min), np.array(self.q_max)


class BaseDescription(_Frozen):
    """Two-wheel differential drive base with a rear caster (Gagabot DR-03 class).

    ``base_link`` sits on the floor midway between the wheel contact points, x forward,
    z up (REP-105 ``base_footprint`` convention, so planar poses are ``T_map_base_link``).
    """

    wheel_radius: _Pos = 0.08
    track_width: _Pos = 0.46  # distance between wheel contact points
    wheel_width: _Pos = 0.04
    caster_radius: _Pos = 0.04
    caster_x: float = -0.28  # caster position along x in base_link
    body_size: tuple[float, float, float] = (0.70, 0.52, 0.34)  # box, m
    body_offset_x: float = -0.05  # body box center along x in base_link
    mass: _Pos = 60.0  # total, of which ballast_mass sits low behind the axle
    ballast_mass: _NonNeg = 35.0
    ballast_x: float = -0.18
    ground_clearance: _NonNeg = 0.08  # clears the 50 mm speed bump of Site 2'
    max_wheel_speed: _Pos = 12.0  # rad/s
    max_linear_speed: _Pos = 0.6  # m/s
    max_angular_speed: _Pos = 1.2  # rad/s


class GripperDescription(_Frozen):
    """Two-finger parallel gripper (Robotiq 2F-85 class)."""

    stroke: _Pos = 0.085  # m, fully open finger gap
    length: _Pos = 0.15  # m, flange to fingertip center (the TCP)
    max_force: _Pos = 110.0  # N

    @property
    def T_flange_tcp(self) -> Array:
        """TCP between the fingertips, along the flange z axis."""
        return vec6_to_T([0.0, 0.0, self.length, 0.0, 0.0, 0.0])


class CameraIntrinsics(_Frozen):
    """Pinhole intrinsics: ``u = fx x/z + cx``, ``v = fy y/z + cy`` (pixels)."""

    width: _Count = 640
    height: _Count = 480
    fx: _Pos = 615.0
    fy: _Pos = 615.0
    cx: float = 319.5
    cy: float = 239.5

    @property
    def K(self) -> Array:
        """3x3 camera matrix."""
        return np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])

    @property
    def fovy(self) -> float:
        """Vertical field of view (rad) of an ideal centered pinhole with these intrinsics."""
        return float(2.0 * np.arctan2(self.height / 2.0, self.fy))

    def resized(self, width: int, height: int) -> CameraIntrinsics:
        """The same camera streaming ``width`` x ``height`` (e.g. a D435 at 320x240): pixels
        scaled by ``s = width / self.width``, ``f' = s f``, ``c' = s (c + 1/2) - 1/2`` (pixel
        centers at integer coordinates), so every ray keeps its direction and the field of
        view is unchanged. The aspect ratio must be kept exactly."""
        if width <= 0 or height <= 0:
            raise InvalidInputError(f"image size must be positive, got {width}x{height}")
        if width * self.height != height * self.width:
            raise InvalidInputError(
                f"{width}x{height} changes the aspect ratio of {self.width}x{self.height}"
            )
        s = width / self.width
        return CameraIntrinsics(
            width=width,
            height=height,
            fx=self.fx * s,
            fy=self.fy * s,
            cx=s * (self.cx + 0.5) - 0.5,
            cy=s * (self.cy + 0.5) - 0.5,
        )


class CameraDescription(_Frozen):
    """Wrist RGB-D camera (Intel RealSense D435 class), depth aligned to color.

    ``T_flange_camera`` is the optical frame (z forward, x right, y down) in the flange frame.
    """

    T_flange_camera_vec: Vec6 = (0.0, -0.095, 0.045, 0.0, 0.0, 0.0)
    color: CameraIntrinsics = CameraIntrinsics()
    depth: CameraIntrinsics = CameraIntrinsics()  # aligned to color
    depth_focal_native: _Pos = 385.0  # px, of the stereo depth imager (noise model)
    baseline: _Pos = 0.050  # m, stereo baseline (noise model)
    min_range: _Pos = 0.2
    max_range: _Pos = 4.0
    rate: _Pos = 30.0  # Hz

    @model_validator(mode="after")
    def _ranges(self) -> CameraDescription:
        _check_below(self.min_range, self.max_range, "camera.min_range", "camera.max_range")
        return self

    @cached_property
    def T_flange_camera(self) -> Array:
        return vec6_to_T(self.T_flange_camera_vec)


class LidarDescription(_Frozen):
    """2D lidar on the base (SICK NAV350 class: reflector-capable, 360 deg)."""

    T_base_link_laser_vec: Vec6 = (0.30, 0.0, 0.22, 0.0, 0.0, 0.0)
    angle_min: float = -_PI
    angle_increment: _Pos = float(np.deg2rad(0.25))
    num_beams: _Count = 1440
    range_min: _NonNeg = 0.05
    range_max: _Pos = 20.0
    rate: _Pos = 10.0  # Hz

    @model_validator(mode="after")
    def _ranges(self) -> LidarDescription:
        _check_below(self.range_min, self.range_max, "lidar.range_min", "lidar.range_max")
        return self

    @property
    def angle_max(self) -> float:
        return self.angle_min + (self.num_beams - 1) * self.angle_increment

    @property
    def angles(self) -> Array:
        """Beam angles (rad), shape (num_beams,), in the laser frame."""
        return self.angle_min + self.angle_increment * np.arange(self.num_beams)

    @cached_property
    def T_base_link_laser(self) -> Array:
        return vec6_to_T(self.T_base_link_laser_vec)


class PhotoSensorDescription(_Frozen):
    """Photoelectric laser sensor on the tool; the beam runs along the sensor's +z axis."""

    T_flange_sensor_vec: Vec6 = (0.0, 0.0, 0.02, 0.0, 0.0, 0.0)
    max_range: _Pos = 0.5  # m, beyond that a reflector does not trigger it

    @cached_property
    def T_flange_sensor(self) -> Array:
        return vec6_to_T(self.T_flange_sensor_vec)


class RobotDescription(_Frozen):
    """Everything the software knows about the robot (nominal values)."""

    name: str = "mmpa-ur5e-diffdrive"
    arm: ArmDescription = ArmDescription()
    base: BaseDescription = BaseDescription()
    T_base_link_arm_base_vec: Vec6 = (0.12, 0.0, 0.40, 0.0, 0.0, 0.0)
    gripper: GripperDescription = GripperDescription()
    camera: CameraDescription = CameraDescription()
    lidar: LidarDescription = LidarDescription()
    photosensor: PhotoSensorDescription = PhotoSensorDescription()

    @model_validator(mode="after")
    def _finite(self) -> RobotDescription:
        def walk(value: object, where: str) -> None:
            if isinstance(value, dict):
                for k, v in value.items():
                    walk(v, f"{where}.{k}" if where else str(k))
            elif isinstance(value, list | tuple):
                for i, v in enumerate(value):
                    walk(v, f"{where}[{i}]")
            elif isinstance(value, float) and not np.isfinite(value):
                raise ValueError(f"{where} must be finite, got {value}")

        walk(self.model_dump(), "")
        return self

    @cached_property
    def T_base_link_arm_base(self) -> Array:
        """Arm mount on the base."""
        return vec6_to_T(self.T_base_link_arm_base_vec)

    def with_updates(self, **changes: object) -> RobotDescription:
        """A copy with some top-level fields replaced (validated)."""
        return RobotDescription.model_validate({**self.model_dump(), **changes})


_default: RobotDescription | None = None


def default_robot() -> RobotDescription:
    """The nominal robot: the one set by :func:`set_default_robot` (the CLI's ``--robot
    FILE``), else mmpa's digital twin (UR5e on a differential drive)."""
    return _default if _default is not None else RobotDescription()


def set_default_robot(robot: RobotDescription | None) -> None:
    """Make ``robot`` the nominal robot of this process (``None``: back to the twin's)."""
    global _default
    if robot is not None and not isinstance(robot, RobotDescription):
        raise InvalidInputError(f"need a RobotDescription, got {type(robot).__name__}")
    _default = robot


__all__ = [
    "ArmDescription",
    "BaseDescription",
    "CameraDescription",
    "CameraIntrinsics",
    "DHParameters",
    "GripperDescription",
    "LidarDescription",
    "PhotoSensorDescription",
    "RobotDescription",
    "default_robot",
    "set_default_robot",
]
