"""The ``direct`` backend: a UR arm over RTDE and a RealSense over its SDK, as one robot.

:func:`open_direct` opens the devices named by a robot file's ``backend:`` section
(:class:`mmpa.robot.backend_config.BackendConfig`, ``kind: direct``) and yields them as a
:class:`~mmpa.robot.interfaces.RobotDevices` (a ``MobileManipulator``):

- ``arm``: :class:`mmpa.backends.ur.URArm` at ``direct.ur_host`` (``ur_frequency`` Hz), its
  limits the description's, slowed by ``safety.speed_scale`` and watched by
  ``safety.watchdog_s`` (:mod:`mmpa.backends.ur`); None without ``ur_host``;
- ``camera``: :class:`mmpa.backends.realsense.RealSenseCamera` from ``realsense_serial``
  (None: the first device found) or ``realsense_playback`` (a recording played by the SDK);
  None with ``camera: false``;
- ``base``: none (``base: none``, a fixed-base arm: missions take the park pose as the
  identity; no lidar or odometry either); ``base: ros2``: the base, odometry, lidar, map
  and a running localizer over ROS 2, as the ``ros2`` section names them
  (:mod:`mmpa.backends.ros2.devices`, the extra ``ros2``): the robot is then a
  :class:`~mmpa.backends.ros2.devices.robot.Ros2Robot` holding the RTDE arm and the
  RealSense camera;
- no gripper; the clock is the wall clock (:class:`WallClock`; ``ros2.use_sim_time`` with
  ``base: ros2``: the base's ``/clock``).

A device that cannot be reached is a :class:`~mmpa.core.errors.MMPAError` naming the device
and what was tried (the host and rate, the serial or the recording). Every device is closed
when the block ends (the arm's stream stopped, the camera's pipeline stopped).
"""

from __future__ import annotations

from collections.abc import Iterable, Iterator
from contextlib import ExitStack, contextmanager
from typing import Any

from mmpa.backends.realsense import RealSenseCamera, RealSenseConfig
from mmpa.backends.ur import URArm, URConfig
from mmpa.core.errors import ConfigError, InvalidInputError, MMPAError
from mmpa.robot.backend_config import BackendConfig
from mmpa.robot.description import RobotDescription
from mmpa.robot.interfaces import RobotDevices, WallClock
from mmpa.robot.limits import JointLimits

__all__ = ["BASE_DEVICES", "connect_rtde", "open_direct"]


def connect_rtde(host: str, frequency: float) -> tuple[Any, Any]:
    """ur-rtde's control and receive interfaces to the controller at ``host``
    (:class:`MMPAError` naming the host and rate when it cannot be reached). Tests replace
    this function to hand in :class:`mmpa.backends.ur_fake.FakeRTDE`."""
    try:
        import rtde_control
        import rtde_receive
    except ImportError as e:
        raise MMPAError(
            f"the direct backend's arm (UR at {host}) needs ur-rtde: pip install 'mmpa[ur]'"
        ) from e
    try:
        receive = rtde_receive.RTDEReceiveInterface(host, frequency)
        control = rtde_control.RTDEControlInterface(host, frequency)
    except RuntimeError as e:
        raise MMPAError(
            f"cannot connect to the UR arm at {host} (RTDE at {frequency:g} Hz, ports "
            f"30004 and 50002): {e}. Check the address (direct.ur_host), that the arm is on "
            "and in remote control, and that the External Control URCap is not running"
        ) from e
    return control, receive


def _open_arm(cfg: BackendConfig, description: RobotDescription, stack: ExitStack) -> URArm:
    d, s = cfg.direct, cfg.safety
    assert d.ur_host is not None
    control, receive = connect_rtde(d.ur_host, d.ur_frequency)
    ucfg = URConfig(
        host=d.ur_host,
        frequency=d.ur_frequency,
        speed_scale=s.speed_scale,
        watchdog_s=s.watchdog_s,
    )
    arm = URArm(
        JointLimits.from_description(description.arm), ucfg, control=control, receive=receive
    )
    stack.enter_context(arm)
    return arm


def _open_camera(cfg: BackendConfig, stack: ExitStack) -> RealSenseCamera:
    d = cfg.direct
    if d.realsense_playback is not None:
        what = f"the RealSense recording {d.realsense_playback}"
    else:
        what = f"the RealSense camera {d.realsense_serial or '(the first one found)'}"
    rcfg = RealSenseConfig(serial=d.realsense_serial, playback=d.realsense_playback)
    try:
        cam = RealSenseCamera(rcfg)
    except MMPAError as e:
        kind = InvalidInputError if isinstance(e, InvalidInputError) else MMPAError
        raise kind(
            f"cannot open {what} (direct.realsense_serial / direct.realsense_playback): {e}"
        ) from e
    stack.enter_context(cam)
    return cam


#: the devices of a ``base: ros2`` direct robot that come over ROS 2
BASE_DEVICES = ("clock", "odometry", "base", "lidar")


@contextmanager
def open_direct(
    cfg: BackendConfig, description: RobotDescription, devices: Iterable[str] | None = None
) -> Iterator[RobotDevices]:
    """The direct backend's devices (module docstring) as one robot, closed on exit.
    ``devices``: with ``base: ros2``, the ROS 2 devices waited for (names of
    :data:`BASE_DEVICES`; None: all of them that the topics name)."""
    if cfg.kind != "direct":
        raise ConfigError(
            f"open_direct needs a robot file with backend kind direct, not {cfg.kind}"
        )
    with ExitStack() as stack:
        arm = None if cfg.direct.ur_host is None else _open_arm(cfg, description, stack)
        camera = _open_camera(cfg, stack) if cfg.direct.camera else None
        if cfg.direct.base == "none":
            yield RobotDevices(description, arm=arm, camera=camera, clock=WallClock())
            return
        yield _ros2_base(cfg, description, stack, arm, camera, devices)


def _ros2_base(
    cfg: BackendConfig,
    description: RobotDescription,
    stack: ExitStack,
    arm: URArm | None,
    camera: RealSenseCamera | None,
    devices: Iterable[str] | None,
) -> RobotDevices:
    """``base: ros2``: a :class:`~mmpa.backends.ros2.devices.robot.Ros2Robot` of the ``ros2``
    section's base, odometry, lidar, map, clock and running localizer (its arm, camera and
    gripper topics not read), holding the RTDE arm and the RealSense camera."""
    from mmpa.backends.ros2.devices.robot import ros2_robot  # the ros2 extra

    off = {k: "" for k in _NOT_BASE}
    topics = cfg.ros2.topics.model_copy(update=off)
    base_cfg = cfg.model_copy(update={"ros2": cfg.ros2.model_copy(update={"topics": topics})})
    robot = stack.enter_context(ros2_robot(base_cfg, description, name="mmpa_direct_base"))
    wanted = BASE_DEVICES if devices is None else [d for d in devices if d in BASE_DEVICES]
    robot.connect(wanted)
    robot.arm, robot.camera = arm, camera
    return robot


#: the ``ros2`` topics a direct robot takes over RTDE and the RealSense SDK instead
_NOT_BASE = (
    "joint_states",
    "arm_trajectory",
    "arm_stream",
    "gripper",
    "color",
    "depth",
    "camera_info",
)
