"""The UR backend's command stream and limits, against a recording FAKE of the RTDE
interfaces (tests/ur_rtde_fake.py; no URSim here)."""

from __future__ import annotations

import time

import numpy as np
import pytest
from tests.ur_rtde_fake import FakeRTDE

from mmpa.backends.ur import URArm, URConfig
from mmpa.core.errors import InvalidInputError, JointLimitError, MMPAError
from mmpa.robot.description import ArmDescription
from mmpa.robot.interfaces import Arm
from mmpa.robot.limits import JointLimits, path_accelerations, path_velocities

ARM = ArmDescription()
LIM = JointLimits.from_description(ARM)
HOME = np.array(ARM.home)


def _arm(q0=HOME) -> tuple[URArm, FakeRTDE]:
    fake = FakeRTDE(q0)
    return URArm(LIM, URConfig(), control=fake, receive=fake), fake


def _ramp(n: int = 101, dt: float = 0.01) -> tuple[np.ndarray, np.ndarray]:
    t = np.arange(n) * dt
    s = 0.5 - 0.5 * np.cos(np.pi * t / t[-1])  # smooth start and stop
    return t, HOME + np.outer(s, [0.4, -0.2, 0.3, 0.0, 0.1, 0.0])


def test_follow_streams_servoj_at_the_controller_rate_within_limits() -> None:
    arm, fake = _arm()
    assert isinstance(arm, Arm)
    t, q = _ramp()
    rec_t, rec_q = arm.follow(t, q, record_hz=100)
    ts, qs = fake.servo_targets()
    assert len(qs) == 501  # 1 s at 500 Hz, both ends included
    np.testing.assert_allclose(np.diff(ts), 0.002)  # one servoJ per controller period
    np.testing.assert_allclose(qs[-1], q[-1], atol=1e-12)
    v = np.abs(path_velocities(ts, qs)).max(axis=0)
    # the accelerations at the path's own sample spacing (every 5th period: 10 ms), as the
    # limits contract measures them (the stream interpolates linearly between samples)
    a = np.abs(path_accelerations(ts[::5], qs[::5])).max(axis=0)
    assert np.all(v <= LIM.qd_max) and np.all(a <= LIM.qdd_max * 1.05)
    assert fake.calls[-1][1] == "servoStop"
    assert len(rec_t) == 101 and np.allclose(rec_q[-1], q[-1])
    assert not any(n == "moveJ" for _, n, _ in fake.calls)  # started where the arm was


def test_far_start_gets_a_movej_and_bad_paths_send_nothing() -> None:
    arm, fake = _arm(HOME + np.array([0.5, 0, 0, 0, 0, 0]))
    t, q = _ramp()
    arm.follow(t, q)
    first = fake.calls[0]
    assert first[1] == "moveJ" and np.allclose(first[2][0], q[0])
    assert first[2][1] <= LIM.qd_max.min() and first[2][2] <= LIM.qdd_max.min()
    n = len(fake.calls)
    jump = q.copy()
    jump[50:, 0] += 1.0
    with pytest.raises(JointLimitError, match="joint 1 velocity"):
        arm.follow(t, jump)
    out = q.copy()
    out[10, 2] = 4.0
    with pytest.raises(JointLimitError, match="joint 3"):
        arm.follow(t, out)
    with pytest.raises(InvalidInputError, match="NaN"):
        arm.move_joints(np.full(6, np.nan))
    with pytest.raises(InvalidInputError, match="6 angles"):  # text: was a numpy ValueError
        arm.move_joints("home")
    with pytest.raises(InvalidInputError, match="6 angles"):
        arm.command(["a"] * 6)
    with pytest.raises(InvalidInputError, match="q_path"):
        arm.follow(t, "path")
    assert len(fake.calls) == n  # nothing was sent


def test_protective_stop_aborts_the_stream_and_refuses_motion() -> None:
    arm, fake = _arm()
    t, q = _ramp()
    fake.protective_stop_at = 0.3
    with pytest.raises(MMPAError, match="protective stop"):
        arm.follow(t, q)
    ts, _ = fake.servo_targets()
    assert 0.3 <= ts[-1] < 0.36  # stopped within one check interval (25 periods)
    assert fake.calls[-1][1] == "servoStop"
    with pytest.raises(MMPAError, match="protective stop: clear it on the pendant"):
        arm.move_joints(HOME)


@pytest.mark.parametrize("limited", [True, False])
def test_command_stream_is_velocity_and_acceleration_limited(limited: bool) -> None:
    """Issue 22: the servoJ set-points keep qd_max and qdd_max (the default), or the hard
    stream limit qdd_stream_max (40 rad/s^2, ur_rtde's) when the stream is not held to
    qdd_max: never an unbounded acceleration (before: velocity-limited only)."""
    arm, fake = _arm()
    assert arm.stream_acceleration_limited
    arm.stream_acceleration_limited = limited
    target = HOME + np.array([1.0, 0, 0, 0, 0, 0])
    arm.command(target)
    deadline = time.monotonic() + 20
    while fake.clock < 1.0 and time.monotonic() < deadline:  # 1 s of virtual controller time
        time.sleep(0.01)
    arm.stop_stream()
    ts, qs = fake.servo_targets()
    v = np.abs(path_velocities(ts, qs))
    a = np.abs(path_accelerations(ts, qs))
    assert v.max() <= LIM.qd_max[0] * (1 + 1e-9)
    a_lim = LIM.qdd_max[0] if limited else LIM.qdd_stream_max[0]
    assert a.max() == pytest.approx(a_lim, rel=1e-6)  # it accelerates at the limit, no more
    # 1 rad: pi rad/s reached in 0.79 s at 4 rad/s^2 (triangle: 0.5 s each way, there by
    # 1.0 s), or in 0.08 s at 40 rad/s^2 (there by 0.4 s)
    assert qs[-1][0] == pytest.approx(HOME[0] + 1.0, abs=1e-3 if limited else 1e-12)
    assert fake.calls[-1][1] == "servoStop"


def test_freedrive_demonstration_becomes_a_teach_recording() -> None:
    from mmpa.missions.teach_repeat import trajectory_recorder

    arm, fake = _arm()
    t_hand = np.arange(0, 3.0, 0.002)
    hand = HOME + np.outer(np.minimum(t_hand, 2.0) / 2.0, [0.2, 0.0, 0.1, 0.0, 0.0, 0.0])
    fake.replay_freedrive(t_hand, hand)
    t, q, g = arm.record_freedrive(50.0, done=lambda: fake.clock >= 2.5)
    names = [n for _, n, _ in fake.calls]
    assert names[0] == "teachMode" and names[-1] == "endTeachMode"
    np.testing.assert_allclose(np.diff(t), 0.02)  # 50 Hz on the controller's clock
    assert t[-1] == pytest.approx(2.5, abs=0.025)  # within one sample
    np.testing.assert_allclose(q[-1], HOME + np.array([0.2, 0, 0.1, 0, 0, 0]), atol=1e-12)
    tt, qq, gg, rate = trajectory_recorder(t, q, 50.0, g)()
    assert rate == 50.0 and tt[0] == 0.0 and np.all(gg == 0) and np.array_equal(qq, q)
    with pytest.raises(InvalidInputError, match="N >= 2"):
        trajectory_recorder(t[:1], q[:1], 50.0)


def test_freedrive_starts_and_stops_on_a_digital_input() -> None:
    """A button on digital input 2: pressed at 0.3 s (start), released, pressed again at
    1.31 s (stop): the samples run from the first press on the 50 Hz grid of the press
    (t = 0 there) to the first grid sample at or after the second press (1.32 s: 52 samples),
    and read the replayed hand exactly."""
    from mmpa.backends.ur import DigitalInputButton

    arm, fake = _arm()
    t_hand = np.arange(0, 2.0, 0.002)
    hand = HOME + np.outer(t_hand, [0.1, 0, 0, 0, 0, 0])
    fake.replay_freedrive(t_hand, hand)
    fake.digital_inputs([0.3, 0.4, 1.31, 1.4], [4, 0, 4, 0])
    t, q, _ = arm.record_freedrive(50.0, button=DigitalInputButton(fake, 2))
    assert len(t) == 52 and t[-1] == pytest.approx(1.02, abs=1e-12)
    np.testing.assert_allclose(q[:, 0], HOME[0] + 0.1 * (0.3 + t), atol=1e-12)
    assert fake.motion_commands() == [c for c in fake.calls if c[1] == "teachMode"]


def test_watchdog_stops_a_stream_when_the_controller_stops_answering() -> None:
    """RTDE receive frozen at 0.2 s of the path: the stream stops within watchdog_s (0.1 s
    = 50 periods) with an error naming it, and servoStop is sent."""
    fake = FakeRTDE(HOME)
    arm = URArm(LIM, URConfig(watchdog_s=0.1), control=fake, receive=fake)
    fake.stop_answering(0.2)
    t, q = _ramp()
    with pytest.raises(MMPAError, match=r"stopped answering.*0\.1 s"):
        arm.follow(t, q)
    ts, _ = fake.servo_targets()
    assert 0.2 < ts[-1] <= 0.3 + 1e-9
    assert fake.calls[-1][1] == "servoStop"


def test_speed_scale_slows_every_motion() -> None:
    """safety.speed_scale 0.25: moveJ at a quarter of the speed and acceleration, a path
    played 4x slower (velocities x 0.25, accelerations x 0.0625), the stream limits x 0.25."""
    fake = FakeRTDE(HOME + np.array([0.5, 0, 0, 0, 0, 0]))
    full = URArm(LIM, URConfig(), control=FakeRTDE(HOME), receive=FakeRTDE(HOME))
    arm = URArm(LIM, URConfig(speed_scale=0.25), control=fake, receive=fake)
    t, q = _ramp()
    arm.follow(t, q)
    mv = fake.calls[0]
    assert mv[1] == "moveJ"
    assert mv[2][1] == pytest.approx(0.25 * 0.5 * LIM.qd_max.min())
    assert mv[2][2] == pytest.approx(0.25 * 0.5 * LIM.qdd_max.min())
    ts, qs = fake.servo_targets()
    assert len(qs) == 2001 and ts[-1] == pytest.approx(4.0)  # 1 s path, 4 s at 500 Hz
    v = np.abs(path_velocities(ts, qs)).max(axis=0)
    v_path = np.abs(path_velocities(t, q)).max(axis=0)
    np.testing.assert_allclose(v, 0.25 * v_path, rtol=0.02)
    np.testing.assert_allclose(arm.stream_limits.qd_max, 0.25 * full.stream_limits.qd_max)
    assert arm.stream_acceleration_limited
    arm.stream_acceleration_limited = False
    np.testing.assert_allclose(arm.stream_limits.qdd_max, 0.25 * LIM.qdd_stream_max)
