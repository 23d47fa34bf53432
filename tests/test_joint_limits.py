"""Joint limits enforced for every motion: the checks against closed forms, the streaming
limiter against its bounds, and the twin's arm refusing or limiting before anything moves."""

from __future__ import annotations

import numpy as np
import pytest

from mmpa.core.errors import InvalidInputError, JointLimitError
from mmpa.planning import retime
from mmpa.robot.description import ArmDescription, RobotDescription
from mmpa.robot.interfaces import RobotDevices
from mmpa.robot.limits import (
    JointLimits,
    check_path,
    limit_acceleration,
    limit_setpoint,
    path_accelerations,
    path_velocities,
    synchronized_limits,
)

ARM = ArmDescription()
LIM = JointLimits.from_description(ARM)
HOME = np.array(ARM.home)


def test_path_derivatives_closed_form() -> None:
    # q(t) = q0 + v0 t + a t^2 / 2 sampled at uneven times: exact finite differences
    rng = np.random.default_rng(0)
    t = np.cumsum(rng.uniform(0.005, 0.02, 40))
    v0, a = rng.normal(0, 0.3, 6), rng.normal(0, 1.0, 6)
    q = HOME + np.outer(t, v0) + 0.5 * np.outer(t**2, a)
    v = path_velocities(t, q)
    mid = 0.5 * (t[1:] + t[:-1])
    np.testing.assert_allclose(v, v0 + np.outer(mid, a), atol=1e-12)
    # the finite difference of a quadratic is exact only for even spacing: check its mean
    acc = path_accelerations(t, q)
    assert acc.shape == (38, 6)
    np.testing.assert_allclose(np.median(acc, axis=0), a, rtol=0.05)
    te = np.arange(40) * 0.01
    qe = HOME + np.outer(te, v0) + 0.5 * np.outer(te**2, a)
    np.testing.assert_allclose(path_accelerations(te, qe), np.tile(a, (38, 1)), atol=1e-9)


def test_check_path_refuses_each_limit_naming_it() -> None:
    t = np.arange(10) * 0.02
    q = np.tile(HOME, (10, 1))
    check_path(t, q, LIM)  # standing still is fine
    jump = q.copy()
    jump[5:, 0] += 1.5  # 1.5 rad in 20 ms: 75 rad/s
    with pytest.raises(JointLimitError, match=r"joint 1 velocity 75\.000 rad/s .* 23\.87x"):
        check_path(t, jump, LIM)
    out = q.copy()
    out[3, 2] = 5.0
    with pytest.raises(JointLimitError, match=r"sample 3: joint 3 = 5\.0000 rad is outside"):
        check_path(t, out, LIM)
    # velocity within limits but acceleration not: 0 -> 0.9 qd_max in one 20 ms step
    acc = q.copy()
    acc[5:, 1] += 0.9 * LIM.qd_max[1] * (t[5:] - t[4])
    with pytest.raises(JointLimitError, match="joint 2 acceleration"):
        check_path(t, acc, LIM)
    bad_t = t.copy()
    bad_t[4] = np.nan
    with pytest.raises(InvalidInputError, match="NaN"):
        check_path(bad_t, q, LIM)
    nan_q = q.copy()
    nan_q[2, 4] = np.nan
    with pytest.raises(InvalidInputError, match="NaN"):
        check_path(t, nan_q, LIM)


def test_retime_refuses_positions_and_fixes_speed() -> None:
    t = np.arange(10) * 0.02
    q = np.tile(HOME, (10, 1))
    q[4, 2] = 5.0
    with pytest.raises(JointLimitError, match="joint 3"):
        retime(t, q, ARM)
    q = np.tile(HOME, (10, 1))
    q[5:, 0] += 1.5
    path = retime(t, q, ARM)
    assert path.time_scale > 20
    check_path(path.t, path.q, LIM)  # the retimed path passes the executed-path check
    with pytest.raises(InvalidInputError, match="finite"):
        retime(np.array([0.0, np.nan, 0.04]), q[:3], ARM)


def test_streaming_limiter_respects_limits_and_lands() -> None:
    dt = 0.002
    rng = np.random.default_rng(1)
    q, v = HOME.copy(), np.zeros(6)
    qs = [q]
    targets = HOME + rng.uniform(-1.0, 1.0, (6, 6))
    for target in targets:  # a new target every 0.3 s, some reversing the motion
        for _ in range(150):
            q, v = limit_setpoint(q, v, target, dt, LIM)
            qs.append(q)
    for _ in range(2000):  # hold the last target until reached
        q, v = limit_setpoint(q, v, targets[-1], dt, LIM)
        qs.append(q)
    qs = np.array(qs)
    t = np.arange(len(qs)) * dt
    assert np.all(np.abs(path_velocities(t, qs)) <= LIM.qd_max * (1 + 1e-6))
    assert np.all(np.abs(path_accelerations(t, qs)) <= LIM.qdd_max * (1 + 1e-6))
    np.testing.assert_array_equal(qs[-1], targets[-1])
    # qdd_max = inf: a pure velocity limiter
    vel_only = JointLimits(LIM.q_min, LIM.q_max, LIM.qd_max, np.full(6, np.inf))
    q1, v1 = limit_setpoint(HOME, np.zeros(6), HOME + 1.0, dt, vel_only)
    np.testing.assert_allclose(q1, HOME + LIM.qd_max * dt)
    q2, _ = limit_setpoint(HOME, v1, HOME + 1e-4, dt, vel_only)
    np.testing.assert_array_equal(q2, HOME + 1e-4)
    # time to reach a far target matches the trapezoid closed form within a few periods
    q, v = HOME.copy(), np.zeros(6)
    d = np.array([2.0, 0.1, 0, 0, 0, 0])
    n = 0
    while not np.array_equal(q, HOME + d):
        q, v = limit_setpoint(q, v, HOME + d, dt, LIM)
        n += 1
    vm, am = LIM.qd_max[0], LIM.qdd_max[0]
    t_trap = d[0] / vm + vm / am  # cruise reached: d > vm^2 / am
    assert abs(n * dt - t_trap) < 5 * dt


def test_stream_limits_raise_qdd_max_to_the_hard_limit_never_to_infinity() -> None:
    """Issue 22: a stream not held to qdd_max is held to the arm's qdd_stream_max (ur_rtde's
    40 rad/s^2 by default), a description cannot set it below qdd_max or to NaN, and limits
    without a stream limit stay as they are."""
    assert LIM.stream(True) is LIM
    free = LIM.stream(False)
    np.testing.assert_array_equal(free.qdd_max, np.full(6, 40.0))
    np.testing.assert_array_equal(free.qd_max, LIM.qd_max)
    np.testing.assert_array_equal(free.q_min, LIM.q_min)
    bare = JointLimits(LIM.q_min, LIM.q_max, LIM.qd_max, LIM.qdd_max)
    assert bare.stream(False) is bare
    with pytest.raises(ValueError, match=r"qdd_stream_max .* at least arm\.qdd_max"):
        ArmDescription(qdd_stream_max=(3.0,) * 6)
    with pytest.raises(ValueError, match="qdd_stream_max must be finite"):
        ArmDescription(qdd_stream_max=(float("nan"),) * 6)
    with pytest.raises(ValueError, match="qdd_max must be finite"):
        ArmDescription(qdd_max=(0.0,) * 6)


def test_limit_acceleration_keeps_the_limits_and_the_direction() -> None:
    """Closed form: a wanted velocity within reach is taken at once; one beyond it is
    approached along ``v_des - v`` by exactly ``qdd_max dt`` on the binding joint; a stream
    of such velocities passes ``check_path``'s velocity and acceleration checks."""
    dt = 0.05
    v0 = np.array([0.1, -0.2, 0.0, 0.3, 0.0, 0.0])
    near = v0 + 0.5 * LIM.qdd_max * dt
    np.testing.assert_array_equal(limit_acceleration(v0, near, dt, LIM), near)
    far = v0 + np.array([2.0, 1.0, 0.0, -0.5, 0.0, 0.0])
    v1 = limit_acceleration(v0, far, dt, LIM)
    s = LIM.qdd_max[0] * dt / 2.0  # joint 1 binds: its change is 2.0 rad/s
    np.testing.assert_allclose(v1, v0 + s * (far - v0))
    fast = np.full(6, 10.0)  # past qd_max: scaled into it as a whole
    v = np.zeros(6)
    for _ in range(200):
        v = limit_acceleration(v, fast, dt, LIM)
    np.testing.assert_allclose(v, fast / np.max(fast / LIM.qd_max))
    rng = np.random.default_rng(7)
    q, v, qs = HOME.copy(), np.zeros(6), [HOME.copy()]
    for _ in range(300):
        v = limit_acceleration(v, rng.uniform(-4.0, 4.0, 6), dt, LIM)
        q = q + v * dt
        qs.append(q)
    t = np.arange(len(qs)) * dt
    qs = np.array(qs)
    assert np.all(np.abs(path_velocities(t, qs)) <= LIM.qd_max * (1 + 1e-9))
    assert np.all(np.abs(path_accelerations(t, qs)) <= LIM.qdd_max * (1 + 1e-9))
    with pytest.raises(InvalidInputError, match="dt"):
        limit_acceleration(v0, far, 0.0, LIM)


def test_synchronized_limits_move_along_the_straight_line() -> None:
    """Rest to rest through ``limit_setpoint`` with :func:`synchronized_limits`: every
    sample lies on the joint-space segment, all joints arrive in the same period, and the
    limits of ``LIM`` hold (the slowest joint at its own limits)."""
    q0 = HOME.copy()
    q1 = HOME + np.array([1.2, -0.3, 0.05, 0.0, 0.9, -0.6])
    lim = synchronized_limits(q0, q1, LIM)
    assert np.all(lim.qd_max <= LIM.qd_max * (1 + 1e-12))
    assert np.all(lim.qdd_max <= LIM.qdd_max * (1 + 1e-12))
    dt = 0.05
    q, v, qs = q0.copy(), np.zeros(6), [q0.copy()]
    while not np.array_equal(q, q1) and len(qs) < 500:
        q, v = limit_setpoint(q, v, q1, dt, lim)
        qs.append(q)
    qs = np.array(qs)
    frac = (qs - q0) / (q1 - q0 + (q1 == q0))  # fraction of the way per joint
    moving = q1 != q0
    assert np.ptp(frac[:, moving], axis=1).max() < 1e-9  # on the straight line
    np.testing.assert_array_equal(qs[-1], q1)
    t = np.arange(len(qs)) * dt
    assert np.all(np.abs(path_accelerations(t, qs)) <= LIM.qdd_max * (1 + 1e-6))
    # joint 1 binds (the longest way for its limits): the triangle/trapezoid closed form
    vm, am = lim.qd_max[0], lim.qdd_max[0]
    d = abs(q1[0] - q0[0])
    t_move = d / vm + vm / am if d > vm**2 / am else 2 * np.sqrt(d / am)
    assert abs(t[-1] - t_move) < 3 * dt


# ------------------------------------------------------------------ the twin's arm


@pytest.fixture(scope="module")
def world():
    from mmpa.backends.twin.world import SimWorld

    w = SimWorld(site="0")
    yield w
    w.close()


def _peak_speed(world, seconds: float) -> np.ndarray:
    """Largest |qdot| per joint (rad/s) seen while stepping ``seconds`` of physics."""
    peak = np.zeros(6)
    for _ in range(round(seconds / 0.004)):
        world.step(0.004)
        peak = np.maximum(peak, np.abs(world.arm.joint_velocities()))
    return peak


def test_twin_arm_refuses_text_targets_and_bad_durations_before_moving(world) -> None:
    """The audit's twin-arm cases: a target given as text (was a numpy ValueError), a
    move duration of inf (was a RuckigError), NaN or -1 s (was silently ignored: the arm
    moved): each a clear InvalidInputError, and the arm has not moved."""
    arm = world.arm
    arm.move_joints(HOME)
    q0 = arm.joint_positions()
    for bad in ("home", ["a"] * 6):
        with pytest.raises(InvalidInputError, match="6 angles"):
            arm.command(bad)
        with pytest.raises(InvalidInputError, match="6 angles"):
            arm.move_joints(bad)
    with pytest.raises(InvalidInputError, match="q_path must be numbers"):
        arm.follow(np.arange(3) * 0.1, "path")
    for duration in (float("inf"), float("nan"), -1.0):
        with pytest.raises(InvalidInputError, match="move duration"):
            arm.move_joints(HOME + 0.1, duration=duration)
    world.step(0.1)
    np.testing.assert_allclose(arm.joint_positions(), q0, atol=1e-6)


def test_follow_refuses_a_jump_before_moving(world) -> None:
    arm = world.arm
    arm.move_joints(HOME)
    q0 = arm.joint_positions()
    t = np.arange(10) * 0.02
    q = np.tile(HOME, (10, 1))
    q[5:, 0] += 1.5
    with pytest.raises(JointLimitError, match="joint 1 velocity"):
        arm.follow(t, q)
    bad_t = t.copy()
    bad_t[3] = np.nan
    with pytest.raises(InvalidInputError, match="NaN"):
        arm.follow(bad_t, np.tile(HOME, (10, 1)))
    with pytest.raises(InvalidInputError, match="NaN"):
        arm.command(np.full(6, np.nan))
    world.step(0.2)
    np.testing.assert_allclose(arm.joint_positions(), q0, atol=1e-3)  # nothing moved


def test_follow_approaches_a_far_start_within_limits(world) -> None:
    arm = world.arm
    arm.move_joints(HOME)
    start = HOME + np.array([1.5, 0, 0, 0, 0, 0])
    t = np.arange(5) * 0.1
    q = np.tile(start, (5, 1))
    rec_t, rec_q = arm.follow(t, q, record_hz=250)
    # recorded encoders: the approach happened before the path (the path starts at its start)
    np.testing.assert_allclose(rec_q[0], start, atol=2e-3)
    v = np.abs(path_velocities(rec_t, rec_q)).max(axis=0)
    assert np.all(v <= LIM.qd_max * 1.02)


@pytest.mark.parametrize("accel", [False, True])
def test_command_stream_is_rate_limited(world, accel: bool) -> None:
    arm = world.arm
    arm.move_joints(HOME)
    target = HOME + np.array([1.5, -0.5, 0.5, 0, 0, 0])
    saved = arm.stream_limits
    # issue 22: the stream keeps the acceleration limits by default
    np.testing.assert_array_equal(saved.qdd_max, LIM.qdd_max)
    np.testing.assert_array_equal(saved.qd_max, LIM.qd_max)
    assert arm.stream_acceleration_limited
    # the applied set-points (d.ctrl of the arm's actuators), every physics step
    ctrl, dt = [], world.model.opt.timestep
    real_step = world.step

    def step(seconds: float) -> None:
        for _ in range(round(seconds / dt)):
            real_step(dt)
            ctrl.append(world.data.ctrl[world._arm_act].copy())

    world.step = step
    arm.stream_acceleration_limited = accel
    try:
        arm.command(target)  # a 1.5 rad jump as one servo set-point
        peak = _peak_speed(world, 2.0)
    finally:
        arm.stream_acceleration_limited = True
        del world.step
    assert arm.stream_limits == saved
    assert np.all(peak <= LIM.qd_max * 1.05), peak / LIM.qd_max
    a = np.abs(np.diff(np.array(ctrl), n=2, axis=0)).max(axis=0) / dt**2
    if accel:  # a triangular profile (1.5 rad < qd_max^2 / qdd_max): peak sqrt(qdd_max d)
        assert peak[0] == pytest.approx(np.sqrt(LIM.qdd_max[0] * 1.5), rel=0.05)
        assert a[0] == pytest.approx(LIM.qdd_max[0], rel=1e-6)
    else:  # cruising at the velocity limit, not crawling, reached at the hard stream limit
        assert peak[0] > 0.95 * LIM.qd_max[0]
        assert a[0] == pytest.approx(40.0, rel=1e-6)  # UR_JOINT_ACCELERATION_MAX of ur_rtde
        assert np.all(a <= LIM.qdd_stream_max * (1 + 1e-6))
    np.testing.assert_allclose(arm.joint_positions(), target, atol=2e-3)


def test_tmma_replay_retimes_a_path_that_jumps(world) -> None:
    from mmpa.missions.teach_repeat import replay_tmma
    from mmpa.robot.interfaces import PointCloud
    from mmpa.robot.kinematics import fk
    from mmpa.tasks import Task, ToolPath

    n = 20
    t = np.arange(n) * 0.02
    q = np.tile(HOME, (n, 1))
    q[10:, 0] += 1.5  # joint 1 jumps 1.5 rad in 20 ms: 24x its velocity limit
    T = np.array([fk(ARM.dh, qi) for qi in q])
    cloud = PointCloud(np.random.default_rng(0).normal(size=(10, 3)), None)
    task = Task("jump", "0", np.eye(4), HOME, np.eye(4), cloud, ToolPath(t, q, T, 50.0))
    path, (rec_t, rec_q) = replay_tmma(
        task,
        RobotDevices(RobotDescription(arm=ARM), arm=world.arm),
        T_flange_tool=np.eye(4),
        record_hz=250,
    )
    assert path.time_scale > 20
    check_path(path.t, path.q, LIM)
    np.testing.assert_allclose(path.q, q)  # the same positions, slower
    v = np.abs(path_velocities(rec_t, rec_q)).max(axis=0)
    assert np.all(v <= LIM.qd_max * 1.02)
    np.testing.assert_allclose(rec_q[-1], q[-1], atol=2e-3)


def test_command_stream_follows_an_accelerating_stream_within_limits(world) -> None:
    """Set-points every 10 ms along ``q(t) = q0 + A t^2 / 2`` on joints 1-3 (A = 0.8
    qdd_max, within the limits): the applied set-point (``d.ctrl``) stays within 3 mrad of
    the stream's closed form all the way (the hold braked the last physics step of every
    period: it then reached only 0.6 qdd_max and lagged 66 mrad after 0.4 s). Switching
    ``stream_acceleration_limited`` off raises qdd_max to the hard ``qdd_stream_max`` only,
    on restores it."""
    arm = world.arm
    arm.move_joints(HOME)
    d = world.data
    q0 = d.ctrl[world._arm_act].copy()
    A = np.zeros(6)
    A[:3] = 0.8 * LIM.qdd_max[:3]
    lag = 0.0
    for k in range(41):
        arm.command(q0 + 0.5 * A * (0.01 * k) ** 2)
        for i in range(5):
            world.step(0.002)
            t = 0.01 * k + 0.002 * (i + 1)
            lag = max(lag, float(np.abs(d.ctrl[world._arm_act] - (q0 + 0.5 * A * t * t)).max()))
    assert lag < 3e-3, lag
    assert arm.stream_acceleration_limited
    arm.stream_acceleration_limited = False
    try:
        np.testing.assert_array_equal(arm.stream_limits.qdd_max, LIM.qdd_stream_max)
        np.testing.assert_array_equal(arm.stream_limits.qd_max, LIM.qd_max)
    finally:
        arm.stream_acceleration_limited = True
    np.testing.assert_array_equal(arm.stream_limits.qdd_max, LIM.qdd_max)
    arm.move_joints(HOME)
