"""The digital twin's physics and ground truth: the base parks, drives and turns as commanded,
the speed bump tilts it, runs are reproducible per seed, the arm reaches its targets within
its repeatability, the TRUE arm and camera differ from the NOMINAL belief by the configured
error model, and the gripper grasps."""

from __future__ import annotations

import math

import mujoco
import numpy as np
import pytest

from mmpa.backends.twin.error_model import ErrorModelConfig, KinematicsError
from mmpa.backends.twin.scene import SpeedBump, load_scene
from mmpa.backends.twin.world import SimWorld
from mmpa.core.errors import InvalidInputError, JointLimitError, UnknownNameError
from mmpa.core.geometry import T_to_vec6, inv

try:  # the nominal model's forward kinematics (fallback: the DH chain written out here)
    from mmpa.robot.kinematics import fk
except ImportError:  # pragma: no cover - kinematics is a sibling module being written

    def fk(dh, q):  # type: ignore[no-redef]
        a, d, alpha, off = dh.as_arrays()
        T = np.eye(4)
        for i in range(6):
            ct, st = np.cos(q[i] + off[i]), np.sin(q[i] + off[i])
            ca, sa = np.cos(alpha[i]), np.sin(alpha[i])
            T = T @ np.array(
                [
                    [ct, -st * ca, st * sa, a[i] * ct],
                    [st, ct * ca, -ct * sa, a[i] * st],
                    [0.0, sa, ca, d[i]],
                    [0.0, 0.0, 0.0, 1.0],
                ]
            )
        return T


Q_REACH = np.array([0.3, -1.5, 1.6, -1.7, -1.4, 0.5])  # a comfortable pose in free space
ZERO_KINEMATICS = ErrorModelConfig(
    kinematics=KinematicsError(
        dh_length_sigma=0.0,
        dh_angle_sigma_deg=0.0,
        joint_repeatability_tool=0.0,
        hand_eye_trans_sigma=0.0,
        hand_eye_rot_sigma_deg=0.0,
    )
)


def _rpy(world: SimWorld) -> np.ndarray:
    """``[z, roll, pitch, yaw]`` of the TRUE base_link."""
    return T_to_vec6(world.truth.T_map_base_link())[2:]


def _rot_angle(Ra: np.ndarray, Rb: np.ndarray) -> float:
    c = (np.trace(Ra @ Rb.T) - 1.0) / 2.0
    return float(np.arccos(np.clip(c, -1.0, 1.0)))


@pytest.fixture(scope="module")
def world():
    w = SimWorld(site="0")
    yield w
    w.close()


@pytest.fixture(scope="module")
def ideal_world():
    """A robot without kinematic or hand-eye errors: truth equals the nominal model."""
    w = SimWorld(site="0", errors=ZERO_KINEMATICS)
    yield w
    w.close()


# --- parking and driving --------------------------------------------------------------------


def test_constructed_world_starts_at_its_site():
    with SimWorld(site="1") as w:
        site = w.scene.site("1")
        p = w.truth.base_pose2d()
        assert np.hypot(*(p[:2] - site.pose2d[:2])) < 0.005
        assert abs(p[2] - site.yaw) < math.radians(0.5)
        assert w.time == pytest.approx(0.5)  # reset() let it settle for 0.5 s


@pytest.mark.parametrize("name", ["0", "1", "2"])
def test_reset_parks_flat_at_the_site_pose(world, name):
    world.reset(site=name)
    site = world.scene.site(name)
    p = world.truth.base_pose2d()
    assert np.hypot(*(p[:2] - site.pose2d[:2])) < 0.005
    assert abs(p[2] - site.yaw) < math.radians(0.5)
    z, roll, pitch, _ = _rpy(world)
    assert abs(roll) < math.radians(0.2)
    assert abs(pitch) < math.radians(0.2)
    assert abs(z) < 0.003
    assert not world.speed_bump_enabled
    # the arm starts at home, the gripper open
    assert world.arm.joint_positions() == pytest.approx(world.nominal.arm.home, abs=1e-3)
    assert world.gripper.width() == pytest.approx(0.085, abs=1e-4)


def test_drive_forward_along_the_heading(world):
    world.reset(site="0")
    world.base.set_velocity(0.3, 0.0)
    world.step(0.5)  # wheel servo transient
    p0 = world.truth.base_pose2d()
    world.step(2.5)
    p1 = world.truth.base_pose2d()
    world.base.stop()
    h = np.array([math.cos(p0[2]), math.sin(p0[2])])
    d = p1[:2] - p0[:2]
    forward, lateral = float(d @ h), float(h[0] * d[1] - h[1] * d[0])
    assert forward == pytest.approx(0.3 * 2.5, rel=0.10)
    assert abs(lateral) < 0.02
    assert abs(p1[2] - p0[2]) < math.radians(1.0)
    assert world.time > 3.0


def test_turn_in_place(world):
    world.reset(site="0")
    p0 = world.truth.base_pose2d()
    world.base.set_velocity(0.0, 0.5)
    world.step(2.0)
    world.base.stop()
    world.step(0.3)
    p1 = world.truth.base_pose2d()
    turned = math.remainder(p1[2] - p0[2], 2 * math.pi)
    assert turned == pytest.approx(1.0, rel=0.10)
    assert np.hypot(*(p1[:2] - p0[:2])) < 0.02  # turns about the axle midpoint


def test_velocity_commands_are_clipped_to_the_base_limits(world):
    world.reset(site="0")
    b = world.true_robot.base
    world.base.set_velocity(5.0, -9.0)
    assert (world.base.v, world.base.omega) == (b.max_linear_speed, -b.max_angular_speed)
    world.base.stop()
    assert (world.base.v, world.base.omega) == (0.0, 0.0)


# --- speed bump -----------------------------------------------------------------------------


def test_site2_prime_puts_the_bump_under_the_base(world):
    world.reset(site="2")
    assert not world.speed_bump_enabled
    z2, r2, p2, _ = _rpy(world)
    world.reset(site="2'")
    assert world.speed_bump_enabled
    z, r, p, _ = _rpy(world)
    tilt = math.degrees(math.hypot(r, p))
    assert tilt > 0.3
    assert tilt < 15.0
    assert z - z2 > 0.002  # a wheel or the caster stands on the 50 mm bump
    assert math.degrees(math.hypot(r2, p2)) < 0.2
    world.reset(site="2")
    assert not world.speed_bump_enabled
    assert _rpy(world)[:3] == pytest.approx((z2, r2, p2), abs=1e-4)


def test_site2_prime_reset_is_settled(world):
    world.reset(site="2'")
    before = world.truth.T_map_base_link()
    world.step(1.0)
    after = world.truth.T_map_base_link()
    assert np.linalg.norm(after[:3, 3] - before[:3, 3]) < 0.001
    assert math.degrees(_rot_angle(after[:3, :3], before[:3, :3])) < 0.1


@pytest.mark.parametrize(
    "offset", [(0.139, -0.156, -10.7), (0.183, 0.141, 25.9), (0.115, -0.05, 7.0)]
)
def test_parked_on_the_bump_the_base_stays_where_placed(world, offset):
    """Placed with its wheels and caster on the bump, the base rests there (no drop, no slide
    off the ridge): the parking offset is the one asked for, the tilt comes from the bump."""
    site = world.scene.site("2'")
    pose = site.pose2d + np.array([offset[0], offset[1], np.deg2rad(offset[2])])
    world.reset(site="2'", pose2d=pose)
    got = world.truth.base_pose2d()
    assert np.hypot(*(got[:2] - pose[:2])) < 0.006
    assert abs(math.degrees(got[2] - pose[2])) < 1.5


def _drive_logging(world: SimWorld, v: float, duration: float) -> tuple[float, float, float]:
    """Drive straight; return max |roll|, max |pitch| (deg) and max base_link z (m)."""
    world.base.set_velocity(v, 0.0)
    mr = mp = mz = 0.0
    for _ in range(round(duration / 0.05)):
        world.step(0.05)
        z, r, p, _ = _rpy(world)
        mr, mp, mz = max(mr, abs(r)), max(mp, abs(p)), max(mz, z)
    world.base.stop()
    return math.degrees(mr), math.degrees(mp), mz


def test_drive_onto_the_site2_prime_bump(world):
    """Park the physics way: approach Site 2' along its heading from 1 m before the ridge."""
    site = world.scene.site("2'")
    yaw = site.yaw
    h = np.array([math.cos(yaw), math.sin(yaw)])
    start = site.pose2d[:2] - 1.15 * h  # the ridge lies 0.14 m ahead of the park position
    world.reset(site="2'", pose2d=np.array([*start, yaw]))
    assert world.speed_bump_enabled
    max_roll, max_pitch, max_z = _drive_logging(world, 0.2, 1.15 / 0.2)
    world.step(1.0)
    p = world.truth.base_pose2d()
    assert max(max_roll, max_pitch) > 1.0
    assert max_z > 0.005  # parked with the drive wheels on the bump's near slope (~10 mm up)
    assert float((p[:2] - site.pose2d[:2]) @ h) == pytest.approx(0.0, abs=0.05)
    assert abs(math.remainder(p[2] - yaw, 2 * math.pi)) < math.radians(3.0)


@pytest.fixture(scope="module")
def open_bump_world():
    """The default world with the bump moved to the open lobby (ridge 10 deg off the y axis),
    so that the robot can drive all the way across it without meeting furniture."""
    scene = load_scene()
    scene = scene.model_copy(update={"speed_bump": SpeedBump(center=(2.2, 0.3), yaw_deg=100.0)})
    w = SimWorld(scene=scene, site="0")
    yield w
    w.close()


def test_drive_across_the_bump(open_bump_world):
    w = open_bump_world
    w.set_speed_bump(True)
    w.reset(pose2d=np.array([1.2, 0.3, 0.0]))  # 1 m before the ridge, heading across it
    assert w.speed_bump_enabled
    max_roll, max_pitch, max_z = _drive_logging(w, 0.2, 10.0)
    w.step(0.5)
    z, roll, pitch, _ = _rpy(w)
    x = w.truth.base_pose2d()[0]
    assert max(max_roll, max_pitch) > 1.0
    assert max_z > 0.01
    assert x > 2.2 + 0.175 + 0.32 + 0.1  # the caster (0.28 m behind, r 4 cm) is past the bump
    assert x == pytest.approx(1.2 + 2.0, abs=0.2)  # ... and the base was not held back
    assert abs(z) < 0.005 and math.degrees(math.hypot(roll, pitch)) < 0.3  # flat again


# --- determinism ----------------------------------------------------------------------------


def _run_commands(seed: int) -> tuple[np.ndarray, np.ndarray, SimWorld]:
    w = SimWorld(site="0", errors=ErrorModelConfig(seed=seed))
    log = []
    for v, om, dt in [(0.25, 0.3, 0.6), (0.0, -0.8, 0.4), (-0.1, 0.2, 0.5)]:
        w.base.set_velocity(v, om)
        for _ in range(round(dt / 0.1)):
            w.step(0.1)
            log.append(np.concatenate([w.truth.base_pose2d(), w.data.qpos]))
    w.base.stop()
    w.arm.move_joints(Q_REACH, settle=0.1)
    log.append(np.concatenate([w.truth.base_pose2d(), w.data.qpos]))
    odo = w.base.odometry()
    return np.array(log), np.concatenate([odo.pose, odo.twist, [odo.stamp]]), w


def test_same_seed_same_run_different_seed_different_robot(world):
    log_a, odo_a, wa = _run_commands(5)
    log_b, odo_b, wb = _run_commands(5)
    assert log_a.shape[0] == 16
    assert np.array_equal(log_a, log_b)  # bitwise
    assert np.array_equal(odo_a, odo_b)
    assert wa.true_robot.arm.dh == wb.true_robot.arm.dh
    assert np.array_equal(wa.map_reflectors, wb.map_reflectors)
    # the run did move the base (a frozen world would pass the equality trivially)
    assert np.hypot(*(log_a[-1, :2] - log_a[0, :2])) > 0.05
    # world (seed 0) and seed 5 are different robot instances
    dh0, dh5 = world.true_robot.arm.dh.as_arrays(), wa.true_robot.arm.dh.as_arrays()
    for x0, x5 in zip(dh0, dh5, strict=True):
        assert not np.allclose(x0, x5, rtol=0, atol=1e-9)
    assert world.true_robot.camera.T_flange_camera_vec != wa.true_robot.camera.T_flange_camera_vec
    assert world.nominal == wa.nominal  # ... with the same nominal belief
    wa.close()
    wb.close()


# --- arm ------------------------------------------------------------------------------------


def test_move_joints_reaches_the_target(world):
    world.reset(site="0")
    t0 = world.time
    world.arm.move_joints(Q_REACH)
    assert world.time - t0 > 0.3  # it took a real trajectory, not a teleport
    q = world.arm.joint_positions()
    assert np.abs(q - Q_REACH).max() < 1e-4
    assert np.abs(world.arm.joint_velocities()).max() < 1e-3
    # the seeded repeatability noise (~1e-5 rad) is there: not exactly the target
    assert np.abs(q - Q_REACH).max() > 1e-7


def test_joint_outside_limits_raises_and_the_arm_stays(world):
    world.reset(site="0")
    q0 = world.arm.joint_positions()
    bad = np.array(world.nominal.arm.home)
    bad[2] = 3.5  # joint 3 limit is +-pi
    with pytest.raises(JointLimitError, match="joint 3"):
        world.arm.move_joints(bad)
    world.step(0.3)
    assert world.arm.joint_positions() == pytest.approx(q0, abs=1e-5)


@pytest.mark.parametrize(
    "q",
    [
        [np.nan, -1.5, 1.6, -1.7, -1.4, 0.5],
        [0.0, -1.5, 1.6, -1.7, np.inf, 0.5],
        [0.0, -1.5, 1.6, -1.7, -1.4],
    ],
)
def test_bad_joint_target_raises_invalid_input(world, q):
    with pytest.raises(InvalidInputError):
        world.arm.move_joints(q)


def _random_q(rng: np.random.Generator) -> np.ndarray:
    """Joint targets that keep the arm above the base and away from the floor."""
    return np.array(
        [
            rng.uniform(-np.pi, np.pi),
            rng.uniform(-2.2, -1.0),
            rng.uniform(0.5, 2.0),
            rng.uniform(-2.5, -0.5),
            rng.uniform(-2.5, 2.5),
            rng.uniform(-np.pi, np.pi),
        ]
    )


def test_true_flange_differs_from_the_nominal_prediction_by_the_dh_error(world):
    world.reset(site="0")
    rng = np.random.default_rng(11)
    dpos, drot = [], []
    for _ in range(5):
        world.arm.move_joints(_random_q(rng))
        # derived kinematics (xpos) lag qpos by one physics step (see
        # test_truth_is_in_step_with_the_state); recompute them to compare at 1e-6
        mujoco.mj_forward(world.model, world.data)
        q = world.arm.joint_positions()  # belief uses the encoders, as a real controller does
        T_true = world.truth.T_map_flange()
        T_arm_base = world.truth.T_map_arm_base()
        # the twin's chain IS the true DH (to the precision of the MJCF text)
        T_model = T_arm_base @ fk(world.true_robot.arm.dh, q)
        assert np.linalg.norm(T_model[:3, 3] - T_true[:3, 3]) < 1e-6
        assert _rot_angle(T_model[:3, :3], T_true[:3, :3]) < 1e-6
        T_belief = T_arm_base @ fk(world.nominal.arm.dh, q)
        dpos.append(np.linalg.norm(T_belief[:3, 3] - T_true[:3, 3]))
        drot.append(math.degrees(_rot_angle(T_belief[:3, :3], T_true[:3, :3])))
    dpos, drot = np.array(dpos), np.array(drot)
    assert np.all(dpos > 0.05e-3), dpos
    assert np.all(dpos < 5e-3), dpos
    assert np.all(drot > 0.001), drot
    assert np.all(drot < 0.5), drot


def test_true_camera_differs_from_the_nominal_by_the_hand_eye_error(world):
    world.reset(site="0")
    T_flange = world.truth.T_map_flange()
    T_cam = world.truth.T_map_camera()
    # the twin mounts the TRUE camera ...
    T_true = T_flange @ world.true_robot.camera.T_flange_camera
    assert np.linalg.norm(T_cam[:3, 3] - T_true[:3, 3]) < 1e-6
    assert _rot_angle(T_cam[:3, :3], T_true[:3, :3]) < 1e-6
    # ... which is off the NOMINAL calibration by the configured N(0, s_t) / N(0, s_r) per
    # axis (realistic: 1 mm, 0.5 deg); the norm of 3 axes stays below 4 sqrt(3) sigma
    k = world.error_model.config.kinematics
    T_nom = T_flange @ world.nominal.camera.T_flange_camera
    dp = np.linalg.norm(T_cam[:3, 3] - T_nom[:3, 3])
    dr = math.degrees(_rot_angle(T_cam[:3, :3], T_nom[:3, :3]))
    assert 0.1 * k.hand_eye_trans_sigma < dp < 4 * math.sqrt(3) * k.hand_eye_trans_sigma
    assert 0.05 * k.hand_eye_rot_sigma_deg < dr < 4 * math.sqrt(3) * k.hand_eye_rot_sigma_deg
    # the full belief chain (nominal DH and nominal hand-eye) is off by the same order
    q = world.arm.joint_positions()
    T_belief = world.truth.T_map_arm_base() @ fk(world.nominal.arm.dh, q)
    T_belief = T_belief @ world.nominal.camera.T_flange_camera
    assert 0.1e-3 < np.linalg.norm(T_cam[:3, 3] - T_belief[:3, 3]) < 10e-3
    # the optical frame convention: z forward = the MuJoCo camera's -z
    R_mj = world.data.cam("wrist_camera").xmat.reshape(3, 3)
    assert T_cam[:3, 2] == pytest.approx(-R_mj[:, 2], abs=1e-12)
    assert T_cam[:3, 0] == pytest.approx(R_mj[:, 0], abs=1e-12)


def test_without_kinematic_errors_truth_equals_belief(ideal_world):
    w = ideal_world
    w.reset(site="0")
    assert w.true_robot.arm.dh == w.nominal.arm.dh
    rng = np.random.default_rng(3)
    for _ in range(3):
        target = _random_q(rng)
        w.arm.move_joints(target)
        mujoco.mj_forward(w.model, w.data)  # see test_truth_is_in_step_with_the_state
        q = w.arm.joint_positions()
        assert np.abs(q - target).max() < 1e-4
        T_true = w.truth.T_map_flange()
        T_belief = w.truth.T_map_arm_base() @ fk(w.nominal.arm.dh, q)
        assert np.linalg.norm(T_belief[:3, 3] - T_true[:3, 3]) < 1e-6
        assert _rot_angle(T_belief[:3, :3], T_true[:3, :3]) < 1e-5
        T_cam_belief = T_belief @ w.nominal.camera.T_flange_camera
        T_cam = w.truth.T_map_camera()
        assert np.linalg.norm(T_cam_belief[:3, 3] - T_cam[:3, 3]) < 1e-6
        assert _rot_angle(T_cam_belief[:3, :3], T_cam[:3, :3]) < 1e-5
        # TCP at the nominal gripper length along the flange z axis
        T_tcp = T_true @ w.nominal.gripper.T_flange_tcp
        assert w.truth.T_map_tcp()[:3, 3] == pytest.approx(T_tcp[:3, 3], abs=1e-6)


# --- gripper --------------------------------------------------------------------------------

Q_GRASP = np.array([0.0, -1.2, 1.5, -1.87, -np.pi / 2, 0.0])  # tool pointing down


def test_gripper_open_and_close_on_nothing_width(world):
    world.reset(site="0")
    assert world.gripper.width() == pytest.approx(0.085, abs=1e-4)
    world.gripper.close()
    assert world.gripper.width() < 0.003
    world.gripper.open()
    assert world.gripper.width() == pytest.approx(0.085, abs=1e-3)


def test_close_on_nothing_reports_no_object(world):
    world.reset(site="0")
    assert world.gripper.close() is False


@pytest.fixture(scope="module")
def grasp(world):
    """Teleport the 50 mm cube between the open fingers (held weightless until the fingers
    close), close, restore gravity, lift the arm with joint 2. Returns the measurements."""
    w = world
    w.reset(site="0")
    w.arm.move_joints(Q_GRASP)
    m, d = w.model, w.data
    cube = m.body("cube").id
    jnt = m.joint("cube_free").id
    qa, da = m.jnt_qposadr[jnt], m.jnt_dofadr[jnt]
    T_tcp = w.truth.T_map_tcp()
    quat = np.empty(4)
    mujoco.mju_mat2Quat(quat, np.ascontiguousarray(T_tcp[:3, :3]).ravel())
    d.qpos[qa : qa + 3] = T_tcp[:3, 3]
    d.qpos[qa + 3 : qa + 7] = quat
    d.qvel[da : da + 6] = 0.0
    m.body_gravcomp[cube] = 1.0
    try:
        mujoco.mj_forward(m, d)
        closed = w.gripper.close()
    finally:
        m.body_gravcomp[cube] = 0.0
    w.step(0.3)
    width = w.gripper.width()
    z_cube0, z_tcp0 = d.xpos[cube][2], w.truth.T_map_tcp()[2, 3]
    q_up = Q_GRASP.copy()
    q_up[1] -= 0.3  # shoulder up
    w.arm.move_joints(q_up)
    result = {
        "closed": closed,
        "width": width,
        "tcp_rise": w.truth.T_map_tcp()[2, 3] - z_tcp0,
        "cube_rise": d.xpos[cube][2] - z_cube0,
        "cube_to_tcp": np.linalg.norm(d.xpos[cube] - w.truth.T_map_tcp()[:3, 3]),
        "width_after_lift": w.gripper.width(),
    }
    w.gripper.open()
    return result


def test_grasp_reports_an_object(grasp):
    assert grasp["closed"] is True
    assert 0.03 < grasp["width"] < 0.0505  # stopped on the 50 mm cube, far from closed


def test_grasped_cube_rises_with_the_gripper(grasp):
    assert grasp["tcp_rise"] > 0.1
    assert grasp["cube_rise"] == pytest.approx(grasp["tcp_rise"], abs=0.005)
    assert grasp["cube_to_tcp"] < 0.01
    assert grasp["width_after_lift"] == pytest.approx(grasp["width"], abs=0.002)


def test_grasp_width_measures_the_cube(grasp):
    assert grasp["width"] == pytest.approx(0.05, abs=0.005)


# --- bad input ------------------------------------------------------------------------------


def test_unknown_site_lists_the_valid_sites(world):
    with pytest.raises(UnknownNameError) as e:
        world.scene.site("nope")
    assert set(e.value.valid) == {"0", "1", "2", "2'"}
    with pytest.raises(UnknownNameError, match=r"'nope'.*0, 1, 2, 2'"):
        SimWorld(site="nope")
    with pytest.raises(UnknownNameError, match="2'"):
        world.reset(site="nope")


@pytest.mark.parametrize(("v", "w"), [(np.nan, 0.0), (0.0, np.inf), (-np.inf, 0.0)])
def test_non_finite_base_velocity_raises(world, v, w):
    world.reset(site="0", settle=0.0)
    with pytest.raises(InvalidInputError):
        world.base.set_velocity(v, w)
    assert (world.base.v, world.base.omega) == (0.0, 0.0)


@pytest.mark.parametrize("dt", [-1.0, np.nan, np.inf])
def test_bad_step_duration_raises(world, dt):
    t = world.time
    with pytest.raises(InvalidInputError):
        world.step(dt)
    assert world.time == t


def test_bad_reset_pose_raises(world):
    with pytest.raises(InvalidInputError):
        world.reset(pose2d=np.array([np.nan, 0.0, 0.0]))
    with pytest.raises(InvalidInputError):
        world.reset(pose2d=np.array([0.0, 0.0]))


def test_world_without_speed_bump_refuses_to_enable_it():
    scene = load_scene()
    scene = scene.model_copy(
        update={
            "speed_bump": None,
            "sites": {k: v for k, v in scene.sites.items() if not v.speed_bump},
        }
    )
    w = SimWorld(scene=scene, site="1")
    try:
        with pytest.raises(InvalidInputError, match="no speed bump"):
            w.set_speed_bump(True)
        w.set_speed_bump(False)  # a no-op
        assert not w.speed_bump_enabled
        with pytest.raises(UnknownNameError):
            w.reset(site="2'")
    finally:
        w.close()


def test_truth_is_in_step_with_the_state(world):
    world.reset(site="0")
    world.base.set_velocity(0.6, 0.0)
    world.step(1.0)
    world.base.stop()
    qa = world.model.jnt_qposadr[world.model.joint("base_free").id]
    # a free joint's qpos IS its body's origin in the world
    assert world.truth.T_map_base_link()[:3, 3] == pytest.approx(
        world.data.qpos[qa : qa + 3], abs=1e-6
    )


def test_ground_truth_frames_are_consistent(world):
    world.reset(site="1")
    T_base = world.truth.T_map_base_link()
    T_arm = world.truth.T_map_arm_base()
    assert inv(T_base) @ T_arm == pytest.approx(world.true_robot.T_base_link_arm_base, abs=1e-6)
    fid = world.truth.fiducial_positions()
    assert fid.shape == (6, 3)
    assert world.truth.reflector_positions() == pytest.approx(world.scene.reflector_positions())
    # the map the software gets is the surveyed one: N(0, sigma) per axis off the truth (2D
    # norm beyond 4 sigma: probability exp(-8) per reflector), not equal
    sigma = world.error_model.config.lidar.reflector_map_sigma
    err = np.linalg.norm(world.map_reflectors - world.scene.reflector_positions(), axis=1)
    assert np.all(err > 0) and err.max() < 4 * sigma
    assert world.truth.T_map_object("cube")[:3, 3] == pytest.approx(
        world.scene.grasp_objects[0].position, abs=0.01
    )


def test_a_lying_stick_placed_at_rest_stays_put(world):
    """The blue stick lies on its side; placed at rest on the grasp desk at 12 random poses,
    the physics (simulator truth) keeps it within 15 mm after 3 s (rolling friction: without
    it a third of the placements rolled 6-163 mm)."""
    from mmpa.harness.perception_data import _footprint, desk_frame

    world.reset(pose2d=np.array([2.7, 0.85, np.pi / 2]), settle=0.1)
    T, _, _ = desk_frame(world)
    _, h = _footprint(world, "blue_stick")
    rng = np.random.default_rng(0)
    moved = []
    for _ in range(12):
        xy = rng.uniform(-0.15, 0.15, 2)
        p = T[:3, :3] @ np.array([*xy, h + 0.001]) + T[:3, 3]
        world.place_object("blue_stick", p, yaw=float(rng.uniform(-np.pi, np.pi)))
        world.step(3.0)
        moved.append(np.hypot(*(world.truth.T_map_object("blue_stick")[:2, 3] - p[:2])))
    world.place_object("blue_stick", np.array([3.9, -2.9, h + 0.002]))
    assert max(moved) < 0.015, np.round(moved, 4)


def test_remembered_textures_equal_a_fresh_drawing_and_advance_the_generator_alike() -> None:
    """The textures' memo against the undecorated functions: the same pixels, and the
    generator left in the state a drawing leaves it (the next draw agrees too)."""
    from mmpa.backends.twin import textures

    for name, args in [("logo", ()), ("letters", ("AB12",)), ("wood", ()), ("backboard", ())]:
        fn = getattr(textures, name)
        for _ in range(2):  # the second call is a memo hit
            a, b = np.random.default_rng(11), np.random.default_rng(11)
            img = fn(*args, rng=a) if name == "letters" else fn(a)
            want = fn.__wrapped__(*args, rng=b) if name == "letters" else fn.__wrapped__(b)
            assert np.array_equal(img, want), name
            assert a.bit_generator.state == b.bit_generator.state
            assert a.uniform() == b.uniform()
    png = textures.png_bytes(want)
    assert png == textures.png_bytes(want.copy()) and png.startswith(b"\x89PNG")
