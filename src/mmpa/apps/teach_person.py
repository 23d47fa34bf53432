"""Teaching by a person on any robot (paper 000 §3.1; issue 36 item 2).

``mmpa --robot R teach SITE TASK`` on a hardware backend records what the operator does:

- the park pose ``L_i``: the localizer's estimate where the robot stands (a robot with a
  base: :func:`mmpa.apps.navigate.robot_on_map`, its own localizer or mmpa's from a rough
  pose) or, for a fixed base (a robot without a base), the identity: ``map`` is the arm's
  mounting;
- the wrist RGB-D view at the sampling pose (``q_sample``; None: where the arm stands);
- the tool path while the person guides the arm, from one of the sources below, through
  the NOMINAL kinematics of the robot file.

Sources of the demonstration (a :data:`~mmpa.missions.teach_repeat.Recorder`):

- a UR over RTDE: freedrive (teach mode) read every control period, kept at ``rate_hz``
  (:meth:`mmpa.backends.ur.URArm.record_freedrive`);
- a ROS 2 arm (``/joint_states`` while the person uses the teach pendant or guides it):
  every message between the presses, kept at ``rate_hz``, timed by its stamp
  (:meth:`mmpa.backends.ros2.devices.arm.Ros2Arm.record_joint_states`);
- any other arm: its ``joint_positions()`` sampled at ``rate_hz``
  (:func:`~mmpa.missions.teach_repeat.joint_recorder`);
- a recorded demonstration: ``/joint_states`` of a bag (:func:`bag_recorder`).

Start and stop: a key (Enter, :class:`KeyPresses`) or a digital input of the controller
(:class:`mmpa.backends.ur.DigitalInputButton`): the first press starts, the second stops.
The twin keeps its scripted operator (:func:`mmpa.apps.teach_run.teach_task`).
"""

from __future__ import annotations

import sys
import threading
from collections.abc import Callable
from pathlib import Path
from typing import TextIO

import numpy as np

from mmpa.apps.navigate import localize_robot, robot_on_map
from mmpa.backends.bag.reader import BagJointStates
from mmpa.backends.ur import DigitalInputButton, URArm
from mmpa.core.errors import ConfigError, InvalidInputError
from mmpa.core.geometry import Array, se2_to_T
from mmpa.missions.teach_repeat import (
    Button,
    Recorder,
    TeachConfig,
    joint_recorder,
    teach,
    trajectory_recorder,
)
from mmpa.robot.backend_config import UR_JOINT_NAMES
from mmpa.robot.interfaces import MobileManipulator, require
from mmpa.tasks import Task, TaskStore

__all__ = [
    "KeyPresses",
    "bag_recorder",
    "make_button",
    "person_recorder",
    "teach_on_hardware",
    "teach_on_robot",
]


class KeyPresses:
    """Enter on ``stream`` (stdin) as a button: calling it returns True once per line read
    since the last call (a daemon thread reads the lines)."""

    def __init__(self, stream: TextIO | None = None) -> None:
        self._stream = stream or sys.stdin
        self._count = 0
        self._seen = 0
        self._lock = threading.Lock()
        threading.Thread(target=self._read, daemon=True, name="teach-keys").start()

    def _read(self) -> None:
        while self._stream.readline():
            with self._lock:
                self._count += 1

    def __call__(self) -> bool:
        with self._lock:
            if self._count > self._seen:
                self._seen += 1
                return True
        return False


def make_button(spec: str, robot: MobileManipulator) -> Button:
    """The start/stop button named by ``spec``: ``key`` (Enter on stdin) or ``di:N`` (digital
    input N of a UR controller over RTDE)."""
    if spec == "key":
        return KeyPresses()
    if spec.startswith("di:") and spec[3:].isdigit():
        if not isinstance(robot.arm, URArm):
            raise ConfigError(f"--button {spec}: digital inputs are read from a UR over RTDE")
        return DigitalInputButton(robot.arm.receive, int(spec[3:]))
    raise InvalidInputError(f"--button must be 'key' or 'di:N' (a digital input), got {spec!r}")


def person_recorder(
    robot: MobileManipulator,
    rate_hz: float,
    button: Button,
    *,
    max_seconds: float = 600.0,
    gripper: Callable[[], float] | None = None,
) -> Recorder:
    """The demonstration of a person guiding ``robot``'s arm (module docstring): UR
    freedrive over RTDE for a :class:`URArm`; a ROS 2 arm's ``/joint_states`` messages
    between the presses, by their stamps (``record_joint_states``); else
    ``joint_positions()`` sampled at ``rate_hz`` on the robot's clock; from the first press
    of ``button`` to the second."""
    require(robot, "arm", mission="recording a demonstration")
    arm = robot.arm
    if isinstance(arm, URArm):

        def record() -> tuple[Array, Array, Array, float]:
            t, q, g = arm.record_freedrive(
                rate_hz, max_seconds=max_seconds, button=button, gripper=gripper
            )
            return trajectory_recorder(t, q, rate_hz, g)()

        return record
    on_topic = getattr(arm, "record_joint_states", None)  # a ROS 2 arm: by the stamps
    if on_topic is not None:

        def record_topic() -> tuple[Array, Array, Array, float]:
            t, q, g = on_topic(rate_hz, button, max_seconds=max_seconds, gripper=gripper)
            return trajectory_recorder(t, q, rate_hz, g)()

        return record_topic
    return joint_recorder(robot, rate_hz, button, max_seconds=max_seconds, gripper=gripper)


def bag_recorder(
    bag: str | Path,
    joint_names: tuple[str, ...] = UR_JOINT_NAMES,
    window: tuple[float, float] | None = None,
) -> Recorder:
    """A recorded demonstration: the arm's ``/joint_states`` of ``bag`` (the joints
    ``joint_names``, in the arm's order), optionally only the samples stamped within
    ``window`` (s, the bag's clock); times from 0, the rate the median sample rate."""
    js = BagJointStates.open(bag, names=joint_names)
    t, q = js.times, js.positions
    if window is not None:
        keep = (t >= window[0]) & (t <= window[1])
        t, q = t[keep], q[keep]
    if len(t) < 2:
        raise InvalidInputError(
            f"{bag}: {len(t)} joint state(s) in the window {window}: a demonstration needs two"
        )
    rate = float(1.0 / np.median(np.diff(t)))
    return trajectory_recorder(t - t[0], q, rate)


def teach_on_robot(
    robot: MobileManipulator,
    site: str,
    name: str,
    *,
    record: Recorder,
    q_sample: Array | None = None,
    T_map_base_park: Array | None = None,
    cfg: TeachConfig | None = None,
    db: str | Path | None = None,
    overwrite: bool = False,
    robot_id: str = "robot",
    description: str = "",
) -> tuple[Task, dict]:
    """Teach task ``name`` at ``site`` on ``robot`` (module docstring) and store it.

    ``T_map_base_park``: the localizer's estimate of the park pose (4x4); None on a fixed
    base (the identity), refused on a robot with a base (teaching there needs the
    estimate). ``q_sample``: the sampling joints (rad); None: where the arm stands.
    Returns the task and a summary."""
    require(robot, "arm", "camera", mission="teaching")
    if T_map_base_park is None:
        if robot.base is not None:
            raise ConfigError(
                "teaching on a mobile base needs the park pose from the localizer; "
                "a fixed-base arm (no base) takes the identity"
            )
        T_map_base_park = np.eye(4)
    arm = robot.arm
    assert arm is not None
    q = arm.joint_positions() if q_sample is None else np.asarray(q_sample, dtype=float)
    task = teach(
        name,
        site,
        robot,
        T_map_base_park=T_map_base_park,
        q_sample=q,
        record=record,
        cfg=cfg,
        description=description,
        robot_id=robot_id,
    )
    with TaskStore(db) as store:
        store.save(task, overwrite=overwrite)
        where = str(store.path)
    return task, {
        "task": task.name,
        "site": task.site,
        "robot": robot_id,
        "store": where,
        "cloud_points": len(task.cloud),
        "path_waypoints": len(task.path.t),
        "path_seconds": round(float(task.path.t[-1]), 2),
        "rate_hz": round(task.path.rate_hz, 3),
    }


def teach_on_hardware(
    robot: MobileManipulator,
    site: str,
    name: str,
    *,
    kind: str = "robot",
    from_bag: Path | None = None,
    sample_q: Array | None = None,
    rate_hz: float = 50.0,
    button: str = "key",
    max_seconds: float = 600.0,
    db: str | Path | None = None,
    overwrite: bool = False,
    say: Callable[[str], None] = print,
    robot_file: Path | None = None,
    start: str | None = None,
    seed: int = 0,
) -> dict:
    """``mmpa --robot R teach SITE TASK`` on a hardware backend (``kind``): the
    demonstration from ``from_bag`` or from the person (``button``: ``key`` or ``di:N``,
    :func:`make_button`), the view at ``sample_q`` (None: where the arm stands), stored as
    task ``name``; ``say`` tells the person what to do. A robot with a base: the park pose
    is the localizer's estimate where it stands (:func:`mmpa.apps.navigate.robot_on_map`:
    its own localizer, or mmpa's of ``robot_file`` started at ``start``, particles from
    ``seed``). Returns the summary."""
    park, where = None, {}
    if robot.base is not None:
        on = robot_on_map(robot, robot_file, start, seed=seed)
        est = localize_robot(robot, on)
        park = se2_to_T(*est)
        where = {"localizer": on.method, "park_pose": [round(float(v), 4) for v in est]}
    if from_bag is not None:  # the arm's joints by its names (a ROS 2 arm's, else UR's)
        record = bag_recorder(from_bag, tuple(getattr(robot.arm, "names", UR_JOINT_NAMES)))
    else:
        record = _announced(person_recorder(
            robot, rate_hz, make_button(button, robot), max_seconds=max_seconds
        ), button, say)  # fmt: skip
    _, summary = teach_on_robot(
        robot, site, name,
        record=record, T_map_base_park=park,
        q_sample=sample_q, db=db, overwrite=overwrite, robot_id=kind,
        description=f"taught by a person on the {kind} backend"
        + (f" from {Path(from_bag).name}" if from_bag is not None else ""),
    )  # fmt: skip
    return {"backend": kind, **where, **summary}


def _announced(record: Recorder, button: str, say: Callable[[str], None]) -> Recorder:
    """``record``, telling the person first how to start and stop it."""
    press = "Enter" if button == "key" else f"the button on digital input {button[3:]}"

    def announced() -> tuple[Array, Array, Array, float]:
        say(f"guide the arm by hand: press {press} to start recording, {press} again to stop")
        return record()

    return announced
