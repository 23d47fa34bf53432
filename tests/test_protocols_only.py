"""The missions run over the robot protocols alone: the twin wrapped in objects that have
nothing but the protocol methods (no ``SimWorld``, no truth, no extra attributes) teaches a
task from a recorded joint trajectory, runs IPE + the adapted path, and grasps a ball. The
truth judges from outside."""

from __future__ import annotations

import os

os.environ.setdefault("MUJOCO_GL", "osmesa")
os.environ.setdefault("PYOPENGL_PLATFORM", "osmesa")

import numpy as np
import pytest

from mmpa.backends.twin.error_model import ErrorModelConfig
from mmpa.backends.twin.world import SimWorld
from mmpa.robot.interfaces import Arm, Base, Camera, Gripper, RobotDevices, StreamingArm


class OnlyArm:
    __slots__ = ("_a",)

    def __init__(self, arm) -> None:
        self._a = arm

    def joint_positions(self):
        return self._a.joint_positions()

    def move_joints(self, q, duration=None):
        return self._a.move_joints(q, duration)

    def follow(self, times, q_path, record_hz=None):
        return self._a.follow(times, q_path, record_hz)

    def command(self, q):
        return self._a.command(q)

    @property
    def limits(self):
        return self._a.limits

    @property
    def stream_limits(self):
        return self._a.stream_limits

    @property
    def stream_acceleration_limited(self):
        return self._a.stream_acceleration_limited

    @stream_acceleration_limited.setter
    def stream_acceleration_limited(self, on):
        self._a.stream_acceleration_limited = on

    def stopped(self):
        return self._a.stopped()


class OnlyCamera:
    __slots__ = ("_c",)

    def __init__(self, camera) -> None:
        self._c = camera

    @property
    def intrinsics(self):
        return self._c.intrinsics

    def capture(self):
        return self._c.capture()


class OnlyGripper:
    __slots__ = ("_g",)

    def __init__(self, gripper) -> None:
        self._g = gripper

    def open(self):
        return self._g.open()

    def close(self):
        return self._g.close()

    def width(self):
        return self._g.width()


class OnlyBase:
    __slots__ = ("_b",)

    def __init__(self, base) -> None:
        self._b = base

    def set_velocity(self, v, w):
        return self._b.set_velocity(v, w)

    def stop(self):
        return self._b.stop()

    def odometry(self):
        return self._b.odometry()


def test_teach_from_a_trajectory_then_ipe_over_protocols_only() -> None:
    from mmpa.backends.twin.operator import get_demonstration, sampling_joints
    from mmpa.missions.teach_repeat import AutomationConfig, automate, teach, trajectory_recorder
    from mmpa.planning import plan_joint_path, retime
    from mmpa.robot.kinematics import fk

    with SimWorld(site="1", errors=ErrorModelConfig(profile="reference")) as w:
        arm, cam = OnlyArm(w.arm), OnlyCamera(w.camera)
        assert isinstance(arm, Arm) and isinstance(cam, Camera)
        q_sample = sampling_joints(w, get_demonstration("needle_site1"))
        rb = w.nominal
        # a person's demonstration, here a 5 cm tool line recorded as joints (e.g. a bag)
        T0 = fk(rb.arm.dh, q_sample, rb.gripper.T_flange_tcp)
        t = np.linspace(0.0, 2.0, 101)
        poses = np.array([T0.copy() for _ in t])
        poses[:, 2, 3] -= 0.05 * t / t[-1]
        q = plan_joint_path(rb.arm, poses, q_sample, rb.gripper.T_flange_tcp)
        task = teach(
            "line",
            "1",
            RobotDevices(rb, arm=arm, camera=cam),
            T_map_base_park=w.truth.T_map_base_link(),
            q_sample=q_sample,
            record=trajectory_recorder(t, retime(t, q, rb.arm).q, 50.0),
        )
        T_map_Bo = w.truth.T_map_arm_base()
        w.reset(site="1", pose2d=w.truth.base_pose2d() + np.array([0.03, -0.02, 0.02]))
        res = automate(
            task,
            RobotDevices(rb, arm=arm, camera=cam, gripper=OnlyGripper(w.gripper)),
            cfg=AutomationConfig(execute=False),
        )
        assert res.ok, res.reason
        truth = np.linalg.inv(w.truth.T_map_arm_base()) @ T_map_Bo
        assert np.linalg.norm(res.ipe.dT_B[:3, 3] - truth[:3, 3]) < 2e-3


def test_grasp_over_protocols_only() -> None:
    from tests.test_servo_twin import _ball_under_the_look_view

    from mmpa.experiments.paper001.grasp import SERVO_RESOLUTION, OracleDetector
    from mmpa.servo.config import GraspConfig
    from mmpa.servo.grasp import TrackingGrasp

    with SimWorld(site="0") as w:
        rb = _ball_under_the_look_view(w, 0.3)
        top = w.truth.T_map_object("tennis_ball")[2, 3]
        w.camera.set_resolution(*SERVO_RESOLUTION)
        g = TrackingGrasp(OracleDetector(w), rb, GraspConfig())
        base, grip, arm = OnlyBase(w.base), OnlyGripper(w.gripper), OnlyArm(w.arm)
        assert isinstance(base, Base) and isinstance(grip, Gripper)
        assert isinstance(arm, StreamingArm)
        robot = RobotDevices(
            rb, arm=arm, gripper=grip, camera=OnlyCamera(w.camera), base=base, clock=w
        )
        res = g.run("tennis_ball", robot)
        assert res.reason == "grasped", res.reason
        w.step(1.0)
        assert w.truth.T_map_object("tennis_ball")[2, 3] > top + 0.04  # held off the desk


@pytest.mark.parametrize("cls", [OnlyArm, OnlyCamera, OnlyGripper, OnlyBase])
def test_wrappers_expose_nothing_else(cls) -> None:
    assert not hasattr(cls(None), "__dict__")  # __slots__: no world can hide in them


class OnlyMobileRobot:
    """A mobile robot with nothing but what navigation uses: base, odometry, lidar, a clock."""

    __slots__ = ("_w",)

    def __init__(self, world) -> None:
        self._w = world

    @property
    def base(self):
        return OnlyBase(self._w.base)

    @property
    def odometry(self):
        return self._w.odometry

    @property
    def lidar(self):
        return self._w.lidar

    @property
    def time(self) -> float:
        return self._w.time

    def step(self, duration: float) -> None:
        self._w.step(duration)


def test_navigation_over_protocols_only() -> None:
    """navigate() drives the twin through an object without truth or world: it reaches the
    site on the estimate; the truth, given only for the evaluation, scores it."""
    from mmpa.backends.twin.operator import rough_initial_pose
    from mmpa.backends.twin.twin_maps import laser_pose2d, twin_map
    from mmpa.localization.localizer import make_localizer
    from mmpa.missions.navigate import NavigateConfig, navigate

    with SimWorld(site="0", errors=ErrorModelConfig(profile="reference")) as w:
        grid = twin_map(w)
        loc = make_localizer("enhanced", grid, laser_pose2d(w), np.random.default_rng(0))
        loc.initialize(rough_initial_pose(w))
        goal = w.scene.site("1").pose2d
        robot = OnlyMobileRobot(w)
        res = navigate(robot, loc, grid, goal, NavigateConfig(timeout=90.0))
        assert np.all(np.isnan(res.final_truth))  # no truth in the robot object
        truth = w.truth.base_pose2d()
    assert res.reached
    assert np.hypot(*(truth[:2] - goal[:2])) < 0.03  # parked at the site (truth, from outside)
    assert np.hypot(*(res.final_estimate[:2] - truth[:2])) < 0.01


def test_hand_eye_calibration_over_protocols_only() -> None:
    """``calibrate_hand_eye_on_robot`` with nothing but the protocol arm and camera, the
    nominal description, a rough board pose and a wait: realistic seed 1, 12 views. Judged
    from outside against the truth: the hand-eye on the model's flange (``E6 X_true``, what
    flange-mounted sensors can determine) within 1 mm / 0.1 deg (measured 0.42 mm, 0.013
    deg; 12 views identify the depth axis less well than the default 40), far better than
    the nominal one (2.86 mm, 1.32 deg); the arm settled after every move."""
    from mmpa.apps.calibrate import last_link_error
    from mmpa.backends.twin.calibration_board import BoardPlacement, board_world
    from mmpa.backends.twin.scene import load_scene
    from mmpa.calibration.hand_eye import pose_error
    from mmpa.missions.hand_eye import HandEyeProcedureConfig, calibrate_hand_eye_on_robot

    scene = load_scene()
    cfg = HandEyeProcedureConfig(stations=12)
    placement = BoardPlacement.for_site(scene, "0")
    errors = ErrorModelConfig.from_profile("realistic", seed=1)
    world = board_world("0", cfg.board, placement, errors=errors, scene=scene)
    try:
        robot = world.nominal
        guess = placement.T_armbase_board(cfg.board, robot)
        waits: list[float] = []

        def wait(s: float) -> None:  # the user's own settle (here: the twin's clock)
            waits.append(s)
            world.step(s)

        devices = RobotDevices(robot, arm=OnlyArm(world.arm), camera=OnlyCamera(world.camera))
        res = calibrate_hand_eye_on_robot(
            devices, guess, np.asarray(robot.arm.view_bench), cfg, wait=wait
        )
        X_true = world.true_robot.camera.T_flange_camera
        E6 = last_link_error(robot.arm.dh, world.true_robot.arm.dh)
    finally:
        world.close()
    assert res.method == "joint" and len(res.q) == sum(r["used"] for r in res.stations) >= 10
    assert len(waits) == len(res.stations) + 1 and set(waits) == {cfg.settle_s}
    et, er = pose_error(res.T_flange_camera, E6 @ X_true)
    nt, nr = pose_error(robot.camera.T_flange_camera, E6 @ X_true)
    assert et < 1.0 and er < 0.1, (et, er)
    assert nt > 2 * et and nr > 5 * er
    assert res.dh is res.joint.dh and res.joint.rms_px < res.joint.rms_px_start


def test_hand_eye_procedure_refuses_bad_input_before_moving() -> None:
    """A malformed board guess or reference configuration is refused with a clear error,
    before the arm moves (a recording fake arm: no motion logged)."""
    from mmpa.core.errors import InvalidInputError
    from mmpa.missions.hand_eye import calibrate_hand_eye_on_robot
    from mmpa.robot.description import default_robot

    class NoMotion:  # a fake arm that records what it is asked
        def __init__(self) -> None:
            self.moves: list = []

        def joint_positions(self):
            return np.zeros(6)

        def move_joints(self, q, duration=None):
            self.moves.append(q)

        def follow(self, times, q_path, record_hz=None):
            self.moves.append(q_path)

    robot = default_robot()
    arm = NoMotion()
    q = np.asarray(robot.arm.view_bench)
    bad_rot = np.eye(4)
    bad_rot[:3, :3] *= 2.0
    nan_pose = np.eye(4)
    nan_pose[0, 3] = np.nan
    for guess, qr, match in [
        (np.eye(3), q, "4x4"),
        (nan_pose, q, "finite 4x4"),
        (bad_rot, q, "rotation"),
        (np.eye(4), q[:5], "6 finite"),
        (np.eye(4), np.full(6, np.nan), "6 finite"),
    ]:
        with pytest.raises(InvalidInputError, match=match):
            calibrate_hand_eye_on_robot(RobotDevices(robot, arm=arm), guess, qr)  # type: ignore[arg-type]
    assert arm.moves == []
    # a robot without a camera is refused by name, before the arm moves
    with pytest.raises(InvalidInputError, match="needs the robot's camera"):
        calibrate_hand_eye_on_robot(RobotDevices(robot, arm=arm), np.eye(4), q)  # type: ignore[arg-type]
    assert arm.moves == []


def test_reflector_survey_drive_over_protocols_only() -> None:
    """``survey_drive`` with nothing but a base, odometry, a lidar and a clock (realistic,
    seed 0): stands at site 0, drives to site 1 and stands there, localizing with hector on
    the map without reflectors. No truth reaches it (none given: ``truths`` is empty). Judged
    from outside: the 6 reflectors seen from both stops lie within 10 mm mean of the TRUE ones
    (measured 3.3 mm mean, 5.0 max: two stops of 10 scans only)."""
    import dataclasses

    from mmpa.backends.twin.operator import rough_initial_pose
    from mmpa.backends.twin.twin_maps import laser_pose2d, twin_map, twin_nav_map
    from mmpa.calibration.reflector_survey import SurveyConfig, match_reflectors, survey_reflectors
    from mmpa.localization.localizer import make_localizer
    from mmpa.missions.navigate import localize_standing
    from mmpa.missions.survey_drive import SurveyDriveConfig, survey_drive, survey_stations
    from mmpa.navigation.planner import CostMap

    errors = ErrorModelConfig.from_profile("realistic", seed=0)
    with SimWorld(site="0", errors=errors) as w:
        grid = dataclasses.replace(twin_map(w), reflectors=np.zeros((0, 2)))
        lp = laser_pose2d(w)
        loc = make_localizer("hector", grid, lp, np.random.default_rng(3))
        loc.initialize(rough_initial_pose(w, np.random.default_rng(1)))
        robot = OnlyMobileRobot(w)
        est0 = localize_standing(robot, loc, scans=30)
        cm = CostMap(twin_nav_map(w))
        stations = survey_stations(cm, est0, [w.scene.site("1").pose2d], float("inf"))
        cfg = SurveyDriveConfig(scans=10, detection={"radius": 0.04, "bearing": "intensity"})
        drive = survey_drive(robot, loc, grid, lp, stations, cfg, costmap=cm)
        p_true = w.scene.reflector_positions()
    assert len(stations) == 1 and drive.skipped == [] and drive.truths.shape == (0, 3)
    obs = drive.observations
    assert len(obs.poses) == 2 and drive.scans == 20 and len(obs) > 40
    fit = survey_reflectors(obs, SurveyConfig(refine_poses=False))
    assert fit.ok and len(fit) >= 5
    m = match_reflectors(fit.positions, p_true)
    assert len(m.spurious) == 0 and 1e3 * m.errors.mean() < 10.0
