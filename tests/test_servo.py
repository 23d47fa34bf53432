"""IBVS, null space and predictor against independent computations."""

from __future__ import annotations

import numpy as np
import pytest

from mmpa.core.errors import InvalidInputError
from mmpa.core.geometry import apply, exp_se3
from mmpa.robot.description import default_robot
from mmpa.robot.interfaces import RobotDevices
from mmpa.robot.kinematics import jacobian, manipulability
from mmpa.servo.ibvs import (
    camera_velocity,
    desired_point,
    features,
    interaction_matrix,
    limit_velocity,
    pinv,
)
from mmpa.servo.nullspace import (
    manipulability_gradient,
    null_space_projector,
    null_space_velocity,
)
from mmpa.servo.predictor import ConstantVelocityKF, PredictorConfig


def test_interaction_matrix_matches_finite_differences():
    """ds/dt of (x, y, log Z) of a static point under a small camera motion."""
    P = np.array([0.05, -0.08, 0.4])
    L = interaction_matrix(*features(P)[:2], P[2])
    rng = np.random.default_rng(0)
    for _ in range(5):
        xi = rng.normal(0, 1, 6)
        h = 1e-6
        # the camera moves by exp(h xi): the point in the new camera frame is T^-1 P
        T = exp_se3(h * xi)
        P_new = apply(np.linalg.inv(T), P)
        ds = (features(P_new) - features(P)) / h
        assert L @ xi == pytest.approx(ds, rel=1e-4, abs=1e-6)


def test_camera_velocity_drives_error_to_zero():
    P = np.array([0.06, 0.02, 0.5])
    P_star = np.array([0.0, 0.1, 0.35])
    dt = 0.02
    for _ in range(300):
        v = camera_velocity(P, P_star, gain=2.0)
        P = P - v * dt  # camera translation moves the point the other way
    assert features(P) == pytest.approx(features(P_star), abs=1e-4)


def test_pinv_is_eq12_and_limits():
    rng = np.random.default_rng(1)
    J = rng.normal(size=(6, 6))
    assert pinv(J) == pytest.approx(np.linalg.inv(J.T @ J) @ J.T)
    Jw = rng.normal(size=(5, 6))
    assert Jw @ pinv(Jw) == pytest.approx(np.eye(5), abs=1e-10)
    assert pinv(Jw) == pytest.approx(np.linalg.pinv(Jw), abs=1e-10)
    qd = np.array([2.0, -6.0, 1.0, 0.0, 0.0, 0.5])
    lim = limit_velocity(qd, np.full(6, 3.0))
    assert np.max(np.abs(lim)) == pytest.approx(3.0)
    assert lim / np.linalg.norm(lim) == pytest.approx(qd / np.linalg.norm(qd))
    with pytest.raises(InvalidInputError):
        interaction_matrix(0.0, 0.0, 0.0)


def test_desired_point_is_below_the_tcp():
    rb = default_robot()
    P = desired_point(rb.camera.T_flange_camera, rb.gripper.T_flange_tcp, 0.25)
    # camera 0.095 m beside and 0.045 m along the flange z; TCP 0.15 m along z
    assert P == pytest.approx([0.0, 0.095, 0.15 - 0.045 + 0.25])


def test_null_space_motion_keeps_the_task_and_raises_manipulability():
    rb = default_robot()
    dh = rb.arm.dh
    q = np.array([0.3, -1.6, 1.9, -1.9, -1.5708, 0.2])
    T_tool = rb.gripper.T_flange_tcp
    J = jacobian(dh, q, rb.camera.T_flange_camera)
    Jt = J[:5]
    N = null_space_projector(Jt)
    assert Jt @ N == pytest.approx(np.zeros((5, 6)), abs=1e-9)
    g = manipulability_gradient(dh, q, T_tool)
    h = 1e-6
    fd = (
        manipulability(jacobian(dh, q + h * np.eye(6)[2], T_tool))
        - manipulability(jacobian(dh, q - h * np.eye(6)[2], T_tool))
    ) / (2 * h)
    assert g[2] == pytest.approx(fd, rel=1e-3)
    qd = null_space_velocity(dh, q, Jt, 1.0, T_tool)
    assert Jt @ qd == pytest.approx(np.zeros(5), abs=1e-9)
    w0 = manipulability(jacobian(dh, q, T_tool))
    w1 = manipulability(jacobian(dh, q + 0.01 * qd / max(np.linalg.norm(qd), 1e-12), T_tool))
    assert w1 > w0


def test_kalman_filter_tracks_constant_velocity():
    rng = np.random.default_rng(2)
    kf = ConstantVelocityKF(PredictorConfig(accel_sigma=0.1))
    v = np.array([0.2, -0.1, 0.0])
    p0 = np.array([0.5, 0.1, -0.05])
    dt = 0.05
    for k in range(60):
        kf.update(p0 + v * k * dt + rng.normal(0, 0.005, 3))
        kf.predict(dt)
    assert kf.velocity() == pytest.approx(v, abs=0.05)
    t = 60 * dt
    assert kf.position(ahead=0.5) == pytest.approx(p0 + v * (t + 0.5), abs=0.04)
    with pytest.raises(InvalidInputError):
        kf.update(np.array([np.nan, 0, 0]))


def test_top_surface_and_grasp_height_on_a_synthetic_depth_image():
    """An upright cylinder straight under a down-looking camera: the depth image is computed
    by ray casting (top disk at ``h``, desk at 0), the top center and heights come back."""
    from mmpa.core.geometry import make_T
    from mmpa.servo.target import desk_height, grasp_height, top_surface

    H, r, h, c = 0.45, 0.031, 0.20, np.array([0.012, -0.02])
    K = np.array([[615.0, 0, 319.5], [0, 615.0, 239.5], [0, 0, 1]])
    # optical z down (-z of arm_base), x along +x, y along -y; camera at (0, 0, H)
    T = make_T(np.diag([1.0, -1.0, -1.0]), [0.0, 0.0, H])
    vv, uu = np.mgrid[0:480, 0:640]
    rx, ry = (uu - 319.5) / 615.0, (vv - 239.5) / 615.0  # ray per unit optical depth
    d_top = H - h  # optical depth of the top plane
    on_top = np.hypot(rx * d_top - c[0], -ry * d_top - c[1]) <= r
    depth = np.where(on_top, d_top, H).astype(np.float32)
    cu, cv = 319.5 + 615 * c[0] / d_top, 239.5 - 615 * c[1] / d_top
    rp = 615 * r / d_top
    box = np.array([cu - rp - 3, cv - rp - 3, cu + rp + 3, cv + rp + 3])
    z_desk = desk_height(depth, K, T, box)
    assert z_desk == pytest.approx(0.0, abs=1e-6)
    top = top_surface(depth, K, T, box, z_desk)
    assert top is not None and top.axis_xy is None  # a disk has no long axis
    assert top.p_top[:2] == pytest.approx(c, abs=1.5e-3)
    assert top.p_top[2] == pytest.approx(h, abs=1e-6)
    # a tall object: the palm stays 65 mm over the top; a short one: pads 24 mm over the desk
    assert grasp_height(h, 0.0) == pytest.approx(h - 0.065)
    assert grasp_height(0.05, 0.0) == pytest.approx(0.025)
    assert grasp_height(0.03, 0.0) == pytest.approx(0.024)
    with pytest.raises(InvalidInputError):
        grasp_height(0.0, 0.1)
    # nothing above the desk in the box: no top
    assert top_surface(np.full_like(depth, H), K, T, box, 0.0) is None


def test_servo_step_gain_schedule_moving_vs_static():
    """The IBVS gain is ``gain`` for an object the predictor sees static or slow and
    ``moving_gain`` above ``final_standoff_max_speed``: the step changes with ``moving_gain``
    only for the fast object."""
    from mmpa.robot.kinematics import fk
    from mmpa.servo.grasp import GraspConfig, TrackingGrasp
    from mmpa.servo.ibvs import IBVSConfig

    rb = default_robot()
    q = np.asarray(rb.arm.view_bench, float)
    T_cam = fk(rb.arm.dh, q) @ rb.camera.T_flange_camera
    p_obj = apply(T_cam, np.array([0.03, 0.02, 0.35]))  # in view, off the desired point

    def step(moving_gain: float, v_obj):
        cfg = GraspConfig(ibvs=IBVSConfig(gain=1.5, moving_gain=moving_gain))
        g = TrackingGrasp(None, rb, cfg)
        return g.servo_step(q, p_obj, v_obj, None, 0.02)[0] - q

    slow, fast = np.array([0.02, 0.0, 0.0]), np.array([0.2, 0.0, 0.0])
    np.testing.assert_allclose(step(1.5, slow), step(4.5, slow), atol=1e-12)
    np.testing.assert_allclose(step(1.5, None), step(4.5, None), atol=1e-12)
    d_lo, d_hi = step(1.5, fast), step(4.5, fast)
    assert np.linalg.norm(d_hi - d_lo) > 1e-4


def test_fit_line_matches_polyfit():
    """The least-squares line against numpy.polyfit per axis, at the last time and another."""
    from mmpa.servo.predictor import fit_line

    rng = np.random.default_rng(4)
    t = np.sort(rng.uniform(0.0, 1.0, 15))
    P = np.array([0.4, -0.1, 0.02]) + np.outer(t, [0.03, -0.02, 0.0]) + rng.normal(0, 0.01, (15, 3))
    p, v = fit_line(t, P)
    for i in range(3):
        slope, icpt = np.polyfit(t, P[:, i], 1)
        assert v[i] == pytest.approx(slope, abs=1e-12)
        assert p[i] == pytest.approx(icpt + slope * t[-1], abs=1e-12)
    p0, _ = fit_line(t, P, t_ref=0.2)
    assert p0 == pytest.approx(p + v * (0.2 - t[-1]), abs=1e-12)
    with pytest.raises(InvalidInputError):
        fit_line(np.zeros(3), P[:3])  # all times equal
    with pytest.raises(InvalidInputError):
        fit_line(t[:1], P[:1])


def test_still_line_tells_a_jittery_still_object_from_a_moving_one():
    """Measurements jittering 1 cm around a fixed point at 20 Hz: the predictor (tuned to
    follow turns) reports the object moving faster than ``final_standoff_max_speed`` at some
    tick, the 1 s least-squares line does not; an object moving at 0.1 m/s gets no line; too
    short a history tells nothing."""
    from mmpa.servo.config import TrackConfig
    from mmpa.servo.tracker import is_moving, still_line

    cfg = TrackConfig()
    rng = np.random.default_rng(7)
    c = np.array([0.5, 0.0, -0.02])
    kf = ConstantVelocityKF(PredictorConfig())
    hist, fast = [], 0
    for k in range(40):
        z = c + rng.normal(0, 0.01, 3) * [1, 1, 0.2]
        kf.update(z)
        hist = [h for h in [*hist, (0.05 * k, z)] if h[0] >= 0.05 * k - 1.0]
        fast += is_moving(kf.velocity(), cfg.final_standoff_max_speed)
        kf.predict(0.05)
    assert fast > 0  # the filter alone calls it moving at times
    line = still_line(hist, cfg)
    assert line is not None
    assert np.linalg.norm(line[1][:2]) < 0.05
    assert np.linalg.norm(line[0][:2] - c[:2]) < 0.01
    v = np.array([0.1, 0.0, 0.0])
    moving = [(0.05 * k, c + v * 0.05 * k + rng.normal(0, 0.01, 3)) for k in range(21)]
    assert still_line(moving, cfg) is None
    assert still_line(hist[-5:], cfg) is None  # 0.2 s of measurements: cannot tell


def test_surfaces_split_at_depth_steps():
    """Two flat patches side by side, one 5 cm above the other, and a hole: two surfaces
    (labels agree within each patch), -1 where there is no point; with a gap larger than the
    step they join."""
    from mmpa.servo.target import surfaces

    h, w = 6, 8
    z = np.full((h, w), 0.40)
    z[:, 4:] = 0.35
    z[0, 0] = 0.0  # no depth
    vv, uu = np.mgrid[0:h, 0:w]
    P = np.stack([uu * 0.002, vv * 0.002, -z], axis=-1)
    n, lab = surfaces(P, z, 0.01)
    assert n == 2 and lab[0, 0] == -1
    assert len(set(lab[:, :4].ravel()) - {-1}) == 1 and len(set(lab[:, 4:].ravel())) == 1
    assert lab[1, 0] != lab[1, 5]
    n, lab = surfaces(P, z, 0.06)
    assert n == 1


def test_ramp_profile_closed_form():
    """Trapezoid (cruise reached) and triangle (too short): the duration, the distance at
    the end, the speed and acceleration bounds by finite differences, the peak speed."""
    from mmpa.servo.descent import ramp_profile

    for d, v, a, t_expect, v_peak in (
        (0.3, 0.5, 2.0, 0.3 / 0.5 + 0.5 / 2.0, 0.5),  # d > v^2 / a: cruises at v
        (0.1, 1.2, 1.0, 2 * np.sqrt(0.1 / 1.0), np.sqrt(0.1 * 1.0)),  # triangle
    ):
        duration, s = ramp_profile(d, v, a)
        assert duration == pytest.approx(t_expect)
        h = 1e-4
        t = np.arange(0.0, duration + 5 * h, h)
        x = np.array([s(ti) for ti in t])
        assert x[0] == 0.0 and x[-1] == pytest.approx(d)
        vel = np.diff(x) / h
        assert vel.max() == pytest.approx(v_peak, rel=1e-3) and vel.min() >= -1e-9
        assert np.abs(np.diff(vel) / h).max() <= a * (1 + 1e-3)
    assert ramp_profile(0.0, 1.0, 1.0)[0] == 0.0
    with pytest.raises(InvalidInputError):
        ramp_profile(-0.1, 1.0, 1.0)


def test_ramp_profile_without_an_acceleration_limit_is_constant_speed():
    from mmpa.servo.descent import ramp_profile

    duration, s = ramp_profile(0.3, 1.2, np.inf)
    assert duration == pytest.approx(0.25)
    assert s(0.1) == pytest.approx(0.12) and s(1.0) == pytest.approx(0.3) and s(-1.0) == 0.0
    with pytest.raises(InvalidInputError):
        ramp_profile(0.3, np.inf, 1.0)


class _RecordingArm:
    """A streaming arm that records ``(clock s, set-point (6,))`` of each command."""

    def __init__(self, clock):
        self.clock = clock
        self.sent: list[tuple[float, np.ndarray]] = []
        self.stream_acceleration_limited = True

    def command(self, q):
        self.sent.append((self.clock[0], np.array(q, float)))

    def stopped(self):
        return None


def test_stream_reaches_a_joint_velocity_at_the_acceleration_limit_between_ticks():
    """Limited ("always"): a step in the wanted joint velocity at a 20 Hz tick is streamed
    at ``stream.rate_hz`` (100 Hz) as a ramp at ``joint_accel_fraction`` of qdd_max of the
    joint that needs the longest (the others scaled: the direction kept), reached after
    ``max_j |qdot_j| / (a_j h)`` set-points (closed form), the set-point the tick returned
    being the one streamed at the tick's end. "never": the same at the arm's hard stream
    limit ``qdd_stream_max`` (40 rad/s^2: 2 set-points; before issue 22's hard limit, one
    set-point per tick, the velocity at once); the arm's limiter is switched to match each
    time."""
    from mmpa.servo.config import GraspConfig
    from mmpa.servo.pose import ArmGeometry
    from mmpa.servo.stream import Stream

    rb = default_robot()
    q0 = np.array(rb.arm.home, float)
    qdot = np.array([0.6, -0.3, 0.2, 0.5, 0.0, -0.4])
    for mode in ("always", "never"):
        cfg = GraspConfig(stream={"accel_limit": mode})
        g = Stream(ArmGeometry.of(rb, cfg.stream.joint_margin), cfg.stream, cfg.intercept)
        clock = [0.0]
        arm = _RecordingArm(clock)
        arm.stream_acceleration_limited = mode == "never"  # the grasp sets it

        def tick(duration, clock=clock):
            clock[0] += duration

        g.clock = lambda clock=clock: clock[0]
        g.set_limited(arm, cfg.stream.accel_limit != "never")
        assert arm.stream_acceleration_limited == (mode == "always")
        wait = g.streaming(arm, tick)
        g.start(q0)
        for _ in range(6):  # 0.3 s at 20 Hz
            q_end = g.send(qdot, 0.05)
            wait(0.05)
            np.testing.assert_allclose(arm.sent[-1][1], q_end, atol=1e-12)
        t = np.array([s[0] for s in arm.sent])
        q = np.array([q0] + [s[1] for s in arm.sent])
        h = 1.0 / cfg.stream.rate_hz
        np.testing.assert_allclose(np.diff(t), h)
        assert len(arm.sent) == 30
        v = np.diff(q, axis=0) / h
        if mode == "never":
            a_lim = np.asarray(rb.arm.qdd_stream_max)
        else:
            a_lim = np.asarray(rb.arm.qdd_max) * cfg.stream.joint_accel_fraction
        assert np.all(np.abs(np.diff(v, axis=0)) / h <= a_lim * (1 + 1e-9))
        n = int(np.ceil(np.max(np.abs(qdot) / (a_lim * h)) - 1e-9))
        np.testing.assert_allclose(v[n - 1 :], np.tile(qdot, (len(v) - n + 1, 1)), atol=1e-12)
        assert not np.allclose(v[n - 2], qdot)
        ratio = v[: n - 1] / np.where(qdot == 0, 1, qdot)  # every joint the same fraction
        np.testing.assert_allclose(ratio[:, qdot != 0], ratio[:, [0]] * np.ones((1, 5)))


def test_a_moving_object_is_told_from_its_measurements_line():
    """``is_fast``: 1 s of measurements at 20 Hz moving at 0.1 m/s: moving; jittering 1 cm
    around a point, or too short a history: not (the stream stays acceleration-limited);
    over 0.5 s, 0.07 m/s (a still object's measurements shifting as the camera comes
    closer): not, 0.2 m/s: moving."""
    from mmpa.servo.config import TrackConfig
    from mmpa.servo.tracker import is_fast

    cfg = TrackConfig()
    rng = np.random.default_rng(3)
    c = np.array([0.5, 0.0, -0.02])
    v = np.array([0.1, 0.0, 0.0])
    moving = [(0.05 * k, c + v * 0.05 * k + rng.normal(0, 0.005, 3)) for k in range(21)]
    still = [(0.05 * k, c + rng.normal(0, 0.01, 3) * [1, 1, 0.2]) for k in range(21)]
    assert is_fast(moving, cfg) and not is_fast(still, cfg) and not is_fast(moving[-5:], cfg)
    # half the window: twice the speed needed (a still object's first measurements shift)
    shift = [(0.05 * k, c + np.array([0.0, 0.07, 0.0]) * 0.05 * k) for k in range(11)]
    fast = [(0.05 * k, c + np.array([0.0, 0.2, 0.0]) * 0.05 * k) for k in range(11)]
    assert not is_fast(shift, cfg) and is_fast(fast, cfg)


def test_intercept_stream_meets_a_goal_moving_at_constant_velocity():
    """ "intercept": goals sent at 20 Hz (the goal at the tick, moving at ``v_goal``) are
    streamed at ``stream.rate_hz`` along the online intercept: the set-points keep qd_max and
    qdd_max (finite differences) and, after the catch-up, lie on the goal's line
    ``q_goal0 + v_goal t`` (closed form) at every sub-step."""
    from mmpa.robot.limits import path_accelerations, path_velocities
    from mmpa.servo.config import GraspConfig
    from mmpa.servo.pose import ArmGeometry
    from mmpa.servo.stream import Stream

    rb = default_robot()
    q0 = np.array(rb.arm.home, float)
    cfg = GraspConfig(stream={"accel_limit": "intercept"})
    g = Stream(ArmGeometry.of(rb, cfg.stream.joint_margin), cfg.stream, cfg.intercept)
    clock = [0.0]
    arm = _RecordingArm(clock)

    def tick(duration, clock=clock):
        clock[0] += duration

    g.clock = lambda clock=clock: clock[0]
    g.set_limited(arm, True)
    wait = g.streaming(arm, tick)
    g.start(q0)
    q_goal0 = q0 + np.array([0.3, -0.2, 0.25, 0.1, -0.1, 0.2])
    v_goal = np.array([0.2, 0.1, -0.15, 0.0, 0.05, -0.1])
    for _ in range(40):  # 2 s at 20 Hz
        g.send_intercept(q_goal0 + v_goal * clock[0], v_goal, 0.05)
        wait(0.05)
    t = np.array([0.0] + [s[0] + 0.01 for s in arm.sent])  # each set-point for its sub-step
    q = np.array([q0] + [s[1] for s in arm.sent])
    np.testing.assert_allclose(np.diff(t), 1.0 / cfg.stream.rate_hz)
    v = path_velocities(t, q)
    a = path_accelerations(t, q)
    assert np.max(np.abs(v) / np.asarray(rb.arm.qd_max)) <= 1 + 1e-6
    assert np.max(np.abs(a) / np.asarray(rb.arm.qdd_max)) <= 1 + 1e-6
    late = t >= 1.5
    np.testing.assert_allclose(q[late], q_goal0 + np.outer(t[late], v_goal), atol=1e-6)


def test_paper_config_turns_the_improvements_off():
    """``GraspConfig.paper()``: the paper's grasp in one place (no predictor, box center,
    dark preprocessing, no second views, hold still when lost, an unlimited constant-speed
    descent, one close); the defaults keep the improvements."""
    from mmpa.servo.config import GraspConfig

    p, d = GraspConfig.paper(), GraspConfig()
    assert not p.track.use_predictor and not p.track.reacquire
    assert p.detect.grasp_point == "box" and p.detect.preprocess_dark
    assert p.search.views == [] and p.close.max_attempts == 1
    assert p.stream.accel_limit == "never"
    assert d.track.use_predictor and d.search.views and d.close.max_attempts == 3
    assert GraspConfig.model_validate(p.model_dump()) == p


def test_run_refuses_an_arm_without_streaming():
    """The tracking grasp needs a StreamingArm: an arm with only the planned moves is
    refused before anything moves (InvalidInputError naming the protocol)."""
    from types import SimpleNamespace

    from mmpa.servo.grasp import TrackingGrasp

    class PlannedOnlyArm:
        def __init__(self):
            self.moved = False

        def joint_positions(self):
            return np.zeros(6)

        def move_joints(self, q, duration=None):
            self.moved = True

        def follow(self, times, q_path, record_hz=None):
            self.moved = True

    det = SimpleNamespace(cfg=SimpleNamespace(classes=["cube"], score_threshold=0.3))
    g = TrackingGrasp(det, default_robot())
    arm = PlannedOnlyArm()
    other = SimpleNamespace()  # gripper, camera and base: never reached
    robot = RobotDevices(default_robot(), arm=arm, gripper=other, camera=other, base=other)
    with pytest.raises(InvalidInputError, match="StreamingArm"):
        g.run("cube", robot, lambda dt: None)
    assert not arm.moved
    # a robot without a gripper is refused by name, before anything moves
    with pytest.raises(InvalidInputError, match="needs the robot's gripper"):
        g.run("cube", RobotDevices(default_robot(), arm=arm, camera=other, base=other))
    assert not arm.moved
