"""Teaching by a person on a ROS 2 robot (issue 36 item 2): the demonstration as
``/joint_states`` showed it (``Ros2Arm.record_joint_states`` behind
``apps.teach_person.person_recorder``), over real DDS.

Default (cheap, ~3 s): a driver in this process publishes ``/clock`` and ``/joint_states``
at 50 Hz of a closed-form motion in real time (in bursts when this process was not run for a
while, as on a loaded machine); a scripted button presses at a clock time and 1 s of the
clock after that press was seen: the recorded samples are every published message stamped
between the presses as the recorder saw them, to the sample (stamps, joints), every one at
50 Hz and every other at 25 Hz. The end to end (``mmpa --robot
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
    """``/clock`` then ``/joint_states`` every 20 ms of sim time, paced in real time; the
    joints' stamps ``lag`` ticks behind the clock (ahead when negative: the two topics'
    delivery latencies differ; changed between recordings); what was published, by stamp
    (ns)."""

    def __init__(self, s: graph.Session, lag: int = 0) -> None:
        mc = messages.message_class
        self.js = s.node.create_publisher(mc("sensor_msgs/msg/JointState"), "/joint_states", 50)
        self.clock = s.node.create_publisher(mc("rosgraph_msgs/msg/Clock"), "/clock", 50)
        self.lag = lag
        self.sent: dict[int, np.ndarray] = {}
        self._done = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()

    def _run(self) -> None:
        k, wall0 = 0, time.monotonic()
        clock = messages.message_class("rosgraph_msgs/msg/Clock")()
        while not self._done.is_set():
            sec, ns = divmod(round((1.0 + k * TICK) * 1e9), 1_000_000_000)
            clock.clock.sec, clock.clock.nanosec = sec, ns
            self.clock.publish(clock)
            if k >= self.lag:
                t = 1.0 + (k - self.lag) * TICK
                q = motion(t)
                msg = messages.to_rclpy(bag.joint_state(t, list(TWIN_JOINTS), q))
                self.sent[msg.header.stamp.sec * 1_000_000_000 + msg.header.stamp.nanosec] = q
                self.js.publish(msg)
            k += 1
            time.sleep(max(0.0, wall0 + k * TICK - time.monotonic()))

    def close(self) -> None:
        self._done.set()
        self._thread.join(5)


class Presses:
    """A button pressed when the robot's clock passes ``first``, then ``gap`` s of the clock
    after that press was seen; ``seen``: the clock when each press was returned."""

    def __init__(self, robot: object, first: float, gap: float) -> None:
        self.robot, self.at, self.gap = robot, first, gap
        self.seen: list[float] = []

    def __call__(self) -> bool:
        now = self.robot.time  # type: ignore[attr-defined]
        if len(self.seen) < 2 and now >= self.at:
            self.seen.append(now)
            self.at = now + self.gap
            return True
        return False


@pytest.fixture(autouse=True)
def _localhost(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")
    monkeypatch.setenv("RMW_IMPLEMENTATION", "rmw_fastrtps_cpp")


#: the topics the recording does not use, off
OFF = {"pose": "", "arm_trajectory": "", "arm_stream": ""}


def _robot_and_driver(tag: str):
    dom = domain(tag)
    cfg = backend(dom, connect_timeout_s=20.0, topics=OFF)
    os.environ["ROS_DOMAIN_ID"] = str(dom)
    try:
        peer = graph.Session(f"mmpa_test_{tag}_driver")
    finally:
        os.environ.pop("ROS_DOMAIN_ID")
    return cfg, peer, Driver(peer)


def test_demonstration_on_joint_states_is_recorded_to_the_sample() -> None:
    """Presses 1 s of the robot's clock apart (the second 1 s after the first was seen), at
    50 Hz with the joints 3 ticks behind the clock, then 25 Hz with them 3 ticks ahead: the
    kept samples are every published message stamped in the recorder's press window
    ``(t_on, t_off]`` (every one, every other), none missing or extra at either end whatever
    the joints' latency (deciding by the message current at a press missed 3 at one end and
    took 3 beyond the other); their times the stamps' differences (1e-12 s),
    their joints the published ones exactly. The recorder reads the clock just before the
    button does: ``t_on``, ``t_off`` at or before the button's own reads, which are >= 1 s
    apart."""
    cfg, peer, driver = _robot_and_driver("teach")
    try:
        with ros2_robot(cfg, default_robot(), name="mmpa_test_teach") as robot:
            robot.connect(["clock", "arm"])
            for rate, every, lag in ((50.0, 1, 3), (25.0, 2, -3)):
                driver.lag = lag
                presses = Presses(robot, robot.time + 0.3, 1.0)
                t, q, g, f = person_recorder(robot, rate, presses)()
                assert f == rate and len(t) == len(q) and np.all(g == 0.0)
                t_on, t_off = robot.arm.presses  # type: ignore[union-attr]
                on, off = presses.seen
                assert t_on <= on and t_off <= off and off >= on + 1.0, (t_on, t_off, on, off)
                ns_on, ns_off = round(t_on * 1e9), round(t_off * 1e9)
                window = [s for s in sorted(driver.sent) if ns_on < s <= ns_off]
                kept = np.array(window[::every])
                assert len(kept) == len(t) and len(t) >= 2, (len(kept), len(t))
                np.testing.assert_allclose(t, (kept - kept[0]) * 1e-9, rtol=0, atol=1e-12)
                for s, qk in zip(kept, q, strict=True):
                    np.testing.assert_array_equal(qk, driver.sent[int(s)])
                np.testing.assert_allclose(np.diff(t), every * TICK, rtol=0, atol=1e-9)
                assert t_off - t_on > 0.5, (t_on, t_off)  # not both presses at one poll
                print(
                    f"{rate:g} Hz: {len(t)} samples over {t[-1]:.3f} s; presses seen "
                    f"{t_on:.3f} / {t_off:.3f} s, the button's reads "
                    f"{on - t_on:.3f} / {off - t_off:.3f} s later"
                )
    finally:
        driver.close()
        peer.close()


def test_presses_without_samples_between_them_are_refused() -> None:
    """A button never pressed: the demonstration did not start within max_seconds; stamps
    in another time base than the robot's (the driver's sim-time stamps, the robot on the
    wall clock): refused, naming the clocks; both presses at once (the driver stopped: no
    message after the first press): fewer than two samples, an error naming the cause."""
    cfg, peer, driver = _robot_and_driver("teach_bad")
    wall = backend(domain("teach_bad"), use_sim_time=False, connect_timeout_s=20.0, topics=OFF)
    try:
        with (
            ros2_robot(cfg, default_robot(), name="mmpa_test_teach_bad") as robot,
            ros2_robot(wall, default_robot(), name="mmpa_test_teach_wall") as on_wall,
        ):
            robot.connect(["clock", "arm"])
            on_wall.connect(["arm"])
            arm = robot.arm
            with pytest.raises(MMPAError, match=r"did not start within 0\.2 s"):
                arm.record_joint_states(50.0, lambda: False, max_seconds=0.2)  # type: ignore[union-attr]
            with pytest.raises(MMPAError, match="synchronize the driver's clock"):
                on_wall.arm.record_joint_states(50.0, lambda: True)  # type: ignore[union-attr]
            driver.close()
            with pytest.raises(MMPAError, match=r"0 /joint_states sample\(s\) stamped between"):
                arm.record_joint_states(50.0, lambda: True)  # type: ignore[union-attr]
    finally:
        driver.close()
        peer.close()
