"""Teaching by a person on a hardware backend (issue 36 item 2): the twin operator's
demonstration replayed as a UR freedrive through the recording FAKE of RTDE
(mmpa.backends.ur_fake; started and stopped by a button on a digital input), the wrist view
from a RealSense recording (the twin camera's frames at the sampling pose, written by
record_frames and played by the SDK): the stored task equals the one taught in the twin, to
the sample (the cloud within the recording's depth quantization)."""

from __future__ import annotations

import os

os.environ.setdefault("MUJOCO_GL", "osmesa")
os.environ.setdefault("PYOPENGL_PLATFORM", "osmesa")


import io
import time

import numpy as np
import pytest

pytest.importorskip("pyrealsense2", reason="the optional extra 'realsense'")

from mmpa.apps.teach_person import (
    KeyPresses,
    bag_recorder,
    make_button,
    person_recorder,
    teach_on_robot,
)
from mmpa.backends.bag.messages import joint_state
from mmpa.backends.bag.writer import BagWriter
from mmpa.backends.realsense import RealSenseCamera, RealSenseConfig, record_frames
from mmpa.backends.twin.operator import load_demonstrations
from mmpa.backends.twin.scene import load_scene
from mmpa.backends.twin.world import SimWorld
from mmpa.backends.ur import DigitalInputButton, URArm, URConfig
from mmpa.backends.ur_fake import FakeRTDE
from mmpa.core.errors import ConfigError, InvalidInputError
from mmpa.harness.twin_site import MMPAExperimentConfig, teach_in_world
from mmpa.missions.teach_repeat import joint_recorder
from mmpa.robot.backend_config import UR_JOINT_NAMES
from mmpa.robot.interfaces import RobotDevices, WallClock
from mmpa.robot.limits import JointLimits
from mmpa.tasks import TaskStore

T0 = 0.5  # s of controller time: the person presses the button to start


@pytest.fixture(scope="module")
def taught(tmp_path_factory):
    """The needle task taught in the twin (mmpa teach 1 needle_site1's teaching), with the
    frames its camera gave at the sampling pose written as a RealSense recording."""
    cfg = MMPAExperimentConfig()
    w = SimWorld(load_scene(cfg.scene), errors=cfg.errors, site="1")
    cam, frames = w.camera, []
    capture = cam.capture

    def keep():
        f = capture()
        frames.append(f)
        return f

    cam.capture = keep
    tw = teach_in_world(w, load_demonstrations()["needle_site1"], "1", cfg)
    rec = record_frames(frames, tmp_path_factory.mktemp("rs") / "view.db3")
    yield tw.task, w, rec, frames
    w.close()


def _robot(w, rec, fake) -> RobotDevices:
    arm = URArm(JointLimits.from_description(w.nominal.arm), URConfig(), control=fake, receive=fake)
    cam = RealSenseCamera(RealSenseConfig(playback=rec, timeout_ms=2000))
    return RobotDevices(w.nominal, arm=arm, camera=cam, clock=WallClock())


def test_freedrive_teaching_equals_the_twin_task(taught, tmp_path) -> None:
    task, w, rec, _ = taught
    fake = FakeRTDE(w.arm.joint_positions())
    fake.replay_freedrive(T0 + task.path.t, task.path.q)
    t_end = float(task.path.t[-1])
    fake.digital_inputs([T0, T0 + 0.1, T0 + t_end, T0 + t_end + 0.1], [1, 0, 1, 0])
    robot = _robot(w, rec, fake)
    record = person_recorder(robot, task.path.rate_hz, DigitalInputButton(fake, 0))
    got, summary = teach_on_robot(
        robot, "1", task.name, record=record, q_sample=task.q_sample, db=tmp_path / "t.db",
        robot_id="direct",
    )  # fmt: skip
    robot.camera.close()
    with TaskStore(tmp_path / "t.db") as store:
        stored = store.load(task.name)
    np.testing.assert_array_equal(stored.path.q, got.path.q)
    # the path, to the sample: same count, times, joints, tool poses, rate, gripper
    assert len(stored.path.t) == len(task.path.t) == summary["path_waypoints"]
    np.testing.assert_allclose(stored.path.t, task.path.t, atol=1e-9, rtol=0)
    np.testing.assert_array_equal(stored.path.q, task.path.q)
    np.testing.assert_array_equal(stored.path.T_arm_base_tool, task.path.T_arm_base_tool)
    assert stored.path.rate_hz == task.path.rate_hz
    g_twin = np.zeros(len(task.path.t)) if task.path.gripper is None else task.path.gripper
    np.testing.assert_array_equal(stored.path.gripper, g_twin)
    np.testing.assert_array_equal(stored.q_sample, task.q_sample)
    np.testing.assert_array_equal(stored.T_arm_base_camera, task.T_arm_base_camera)
    np.testing.assert_array_equal(stored.T_map_base_park, np.eye(4))  # a fixed base
    # the cloud: the same pixels, each within the depth quantization (1 mm units, rounded:
    # 0.5 mm in z, and x, y in proportion); colors exact. Measured: 307200 points, |dz| at
    # most 0.346 mm, 0.060 mm mean (16 captures averaged: the rounding errors average too)
    assert len(stored.cloud) == len(task.cloud)
    dz = np.abs(stored.cloud.points[:, 2] - task.cloud.points[:, 2])
    print(f"cloud: {len(task.cloud)} points, |dz| max {dz.max() * 1e3:.3f} mm, mean "
          f"{dz.mean() * 1e3:.3f} mm; |dxyz| max "
          f"{np.abs(stored.cloud.points - task.cloud.points).max() * 1e3:.3f} mm")  # fmt: skip
    assert dz.max() <= 0.5e-3 + 1e-6, dz.max()
    z = task.cloud.points[:, 2]
    dxy = np.abs(stored.cloud.points[:, :2] - task.cloud.points[:, :2])
    assert np.all(dxy <= (np.abs(task.cloud.points[:, :2]) / z[:, None]) * (0.5e-3 + 1e-6) + 1e-6)
    np.testing.assert_allclose(stored.cloud.colors, task.cloud.colors, atol=1 / 255 / 2)
    # what was sent: one moveJ to the sampling pose, then teach mode on and off
    assert [n for _, n, _ in fake.motion_commands()] == ["moveJ", "teachMode"]
    assert fake.calls[-1][1] == "endTeachMode"


def test_teaching_from_a_bag_equals_the_twin_task(taught, tmp_path) -> None:
    """--from-bag: the twin demonstration's joints as /joint_states in a bag (stamped from
    100 s, with another joint group's messages between them): the same path."""
    task, w, rec, _ = taught
    bag = tmp_path / "demo.mcap"
    with BagWriter(bag) as b:
        for t, q in zip(task.path.t, task.path.q, strict=True):
            b.write("/joint_states", joint_state(100.0 + t, list(UR_JOINT_NAMES), q))
            b.write("/joint_states", joint_state(100.0 + t + 1e-3, ["finger"], np.zeros(1)))
    fake = FakeRTDE(w.arm.joint_positions())
    robot = _robot(w, rec, fake)
    got, _ = teach_on_robot(
        robot, "1", task.name, record=bag_recorder(bag), q_sample=task.q_sample,
        db=tmp_path / "t.db",
    )  # fmt: skip
    robot.camera.close()
    assert got.path.rate_hz == pytest.approx(task.path.rate_hz, rel=1e-6)
    np.testing.assert_allclose(got.path.t, task.path.t, atol=1e-8, rtol=0)  # ns stamps
    np.testing.assert_array_equal(got.path.q, task.path.q)
    assert [n for _, n, _ in fake.motion_commands()] == ["moveJ"]  # no teach mode
    with pytest.raises(InvalidInputError, match="needs two"):
        bag_recorder(bag, window=(0.0, 1.0))


class _Clock:
    def __init__(self) -> None:
        self.time = 0.0

    def step(self, dt: float) -> None:
        self.time = round(self.time + dt, 9)


class _Arm:
    """An arm a person moves: joint 1 at 0.1 rad/s of the clock."""

    def __init__(self, clock: _Clock) -> None:
        self.clock = clock

    def joint_positions(self) -> np.ndarray:
        return np.array([0.1 * self.clock.time, 0, 0, 0, 0, 0])


def test_joint_recorder_samples_any_arm_between_two_presses() -> None:
    clock = _Clock()
    presses = iter([False] * 30 + [True] + [False] * 49 + [True] + [False] * 100)
    robot = RobotDevices(w_desc(), arm=_Arm(clock), clock=clock)
    t, q, g, rate = joint_recorder(robot, 50.0, lambda: next(presses))()
    # pressed at the 31st check (0.6 s), stopped 50 samples later (at t = 1.0 s)
    assert rate == 50.0 and len(t) == 51 and np.all(g == 0)
    np.testing.assert_allclose(t, np.arange(51) * 0.02, atol=1e-12)
    np.testing.assert_allclose(q[:, 0], 0.1 * (0.6 + t), atol=1e-9)


def test_buttons_and_refusals() -> None:
    keys = KeyPresses(io.StringIO("\n\n"))
    for _ in range(100):
        if keys._count == 2:
            break
        time.sleep(0.01)
    assert [keys(), keys(), keys()] == [True, True, False]
    robot = RobotDevices(w_desc(), arm=_Arm(_Clock()), clock=_Clock())
    with pytest.raises(ConfigError, match="UR over RTDE"):
        make_button("di:3", robot)
    with pytest.raises(InvalidInputError, match="'key' or 'di:N'"):
        make_button("pedal", robot)
    mobile = RobotDevices(w_desc(), arm=_Arm(_Clock()), camera=object(), base=object())
    with pytest.raises(ConfigError, match="park pose from the localizer"):
        teach_on_robot(mobile, "1", "x", record=lambda: None)


def w_desc():
    from mmpa.robot.description import default_robot

    return default_robot()
