"""Teaching by a person on a ROS 2 robot (issue 36 item 2): the demonstration as
``/joint_states`` showed it (``Ros2Arm.record_joint_states`` behind
``apps.teach_person.person_recorder``), over real DDS.

Default (cheap, ~3 s): a driver in this process publishes ``/clock`` and ``/joint_states``
at 50 Hz of a closed-form motion in real time; a scripted button presses at two clock times:
the recorded samples are the published ones between the presses, to the sample (stamps,
joints), every one at 50 Hz and every other at 25 Hz. The end to end (``mmpa --robot
ros2.yaml teach`` against the twin node, the twin operator's motion played into its arm) is
slow: tests/test_ros2_robot.py.

DDS domains of their own (215..232), discovery on localhost; skipped without the extra.
"""

from __future__ import annotations

import os
import threading
import time

import numpy as np
import pytest

pytest.importorskip(
    "rclpy", reason="the ros2 extra is not installed (make setup installs it on x86-64 Linux)"
)

from mmpa.apps.teach_person import person_recorder
from mmpa.backends.bag import messages as bag
from mmpa.backends.ros2 import graph, messages
from mmpa.backends.ros2.devices.robot import ros2_robot
from mmpa.core.errors import MMPAError
from mmpa.robot.description import default_robot
from test_ros2_devices import TWIN_JOINTS, backend, domain

TICK = 0.02  # s: the driver's period (sim time)


def motion(t: float) -> np.ndarray:
    """The demonstrated joints at time ``t`` (rad): a different sine per joint."""
    k = np.arange(1, 7)
    return 0.1 * k + 0.05 * np.sin(0.7 * k * t)


class Driver:
    """``/joint_states`` then ``/clock`` every 20 ms of sim time, paced in real time; what
    was published, by stamp (ns)."""

    def __init__(self, s: graph.Session) -> None:
        mc = messages.message_class
        self.js = s.node.create_publisher(mc("sensor_msgs/msg/JointState"), "/joint_states", 50)
        self.clock = s.node.create_publisher(mc("rosgraph_msgs/msg/Clock"), "/clock", 50)
        self.sent: dict[int, np.ndarray] = {}
        self._done = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()

    def _run(self) -> None:
        k, wall0 = 0, time.monotonic()
        clock = messages.message_class("rosgraph_msgs/msg/Clock")()
        while not self._done.is_set():
            t = 1.0 + k * TICK
            q = motion(t)
            msg = messages.to_rclpy(bag.joint_state(t, list(TWIN_JOINTS), q))
            self.sent[msg.header.stamp.sec * 1_000_000_000 + msg.header.stamp.nanosec] = q
            self.js.publish(msg)
            clock.clock = msg.header.stamp
            self.clock.publish(clock)
            k += 1
            time.sleep(max(0.0, wall0 + k * TICK - time.monotonic()))

    def close(self) -> None:
        self._done.set()
        self._thread.join(5)


class Presses:
    """A button pressed when the robot's clock passes each of ``times`` (once each)."""

    def __init__(self, robot: object, times: list[float]) -> None:
        self.robot, self.times = robot, list(times)

    def __call__(self) -> bool:
        if self.times and self.robot.time >= self.times[0]:  # type: ignore[attr-defined]
            self.times.pop(0)
            return True
        return False


@pytest.fixture(autouse=True)
def _localhost(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")
    monkeypatch.setenv("RMW_IMPLEMENTATION", "rmw_fastrtps_cpp")


def _robot_and_driver(tag: str):
    dom = domain(tag)
    topics = {"pose": "", "arm_trajectory": "", "arm_stream": ""}
    cfg = backend(dom, connect_timeout_s=20.0, topics=topics)
    os.environ["ROS_DOMAIN_ID"] = str(dom)
    try:
        peer = graph.Session(f"mmpa_test_{tag}_driver")
    finally:
        os.environ.pop("ROS_DOMAIN_ID")
    return cfg, peer, Driver(peer)


def test_demonstration_on_joint_states_is_recorded_to_the_sample() -> None:
    """Presses 1 s of the robot's clock apart, at 50 Hz then 25 Hz: the kept samples are
    consecutive published messages (every one, every other), their times the stamps'
    differences (1e-12 s), their joints the published ones exactly; the window 1 s within
    the polls (a 20 ms poll and a tick at each end; 0.1 s allowed for a loaded machine)."""
    cfg, peer, driver = _robot_and_driver("teach")
    try:
        with ros2_robot(cfg, default_robot(), name="mmpa_test_teach") as robot:
            robot.connect(["clock", "arm"])
            for rate, every in ((50.0, 1), (25.0, 2)):
                t0 = robot.time
                t, q, g, f = person_recorder(robot, rate, Presses(robot, [t0 + 0.3, t0 + 1.3]))()
                assert f == rate and len(t) == len(q) and np.all(g == 0.0)
                stamps = sorted(driver.sent)
                k0 = next(k for k, s in enumerate(stamps) if np.array_equal(driver.sent[s], q[0]))
                kept = np.array(stamps[k0::every][: len(t)])
                assert len(kept) == len(t)
                np.testing.assert_allclose(t, (kept - kept[0]) * 1e-9, rtol=0, atol=1e-12)
                for s, qk in zip(kept, q, strict=True):
                    np.testing.assert_array_equal(qk, driver.sent[int(s)])
                np.testing.assert_allclose(np.diff(t), every * TICK, rtol=0, atol=1e-9)
                assert 1.0 - 0.1 <= t[-1] <= 1.0 + 0.1, t[-1]
                print(f"{rate:g} Hz: {len(t)} samples over {t[-1]:.3f} s")
    finally:
        driver.close()
        peer.close()


def test_presses_without_samples_between_them_are_refused() -> None:
    """Both presses at once (the second seen at the next poll, before a new message can
    come after the first): fewer than two samples, an error naming the cause; a button
    never pressed: the demonstration did not start within max_seconds."""
    cfg, peer, driver = _robot_and_driver("teach_bad")
    try:
        with ros2_robot(cfg, default_robot(), name="mmpa_test_teach_bad") as robot:
            robot.connect(["clock", "arm"])
            arm = robot.arm
            with pytest.raises(MMPAError, match="between the presses"):
                arm.record_joint_states(50.0, lambda: True)  # type: ignore[union-attr]
            with pytest.raises(MMPAError, match=r"did not start within 0\.2 s"):
                arm.record_joint_states(50.0, lambda: False, max_seconds=0.2)  # type: ignore[union-attr]
    finally:
        driver.close()
        peer.close()
