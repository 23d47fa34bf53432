"""Issue 32: nothing silent on a real robot's data. A twin value never stands in for a real one
(the lidar mount of a bag), input outside its range is refused instead of wrapped (map cells),
and what was used is recorded (``laser_pose_source``). See docs/silent_defaults.md."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest

from mmpa.apps.localize import LocalizeConfig, _laser_pose, run_localize
from mmpa.backends.bag import BagWriter
from mmpa.backends.bag import messages as rm
from mmpa.backends.bag.reader import BagPlayback
from mmpa.core.errors import InvalidInputError
from mmpa.core.geometry import make_T
from mmpa.maps.occupancy import OccupancyGrid
from mmpa.robot.interfaces import LaserScan, Odometry, RobotDevices

# ----------------------------------------------------------------------- the lidar mount


def _scan(stamp: float, frame: str, n: int = 61) -> LaserScan:
    a0, inc = -math.pi / 2, math.pi / (n - 1)
    r = np.full(n, 1.2)
    return LaserScan(
        a0, a0 + inc * (n - 1), inc, 0.0, 0.1, 0.05, 10.0, r, np.zeros(n), stamp, frame
    )


def _rz(yaw: float) -> np.ndarray:
    c, s = math.cos(yaw), math.sin(yaw)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


#: a rear lidar 0.2 m behind base_link, turned by pi, through an intermediate plate: the
#: twin's mount (0.3 m ahead, yaw 0) is 0.5 m and pi away from it
PLATE = make_T(np.eye(3), [-0.15, 0.02, 0.3])
LASER_ON_PLATE = make_T(_rz(math.pi), [-0.05, 0.0, -0.05])
REAR = (-0.2, 0.02, math.pi)


def _pb(frame: str, static: dict | None = None) -> BagPlayback:
    pb = BagPlayback(Path("robot.mcap"))
    pb.scans = [_scan(0.1, frame), _scan(0.2, frame)]
    pb.static_transforms = static if static is not None else {}
    return pb


def test_the_mount_comes_from_tf_static_by_the_scans_frame_through_a_chain() -> None:
    static = {("base_link", "plate"): PLATE, ("/plate", "base_laser_link"): LASER_ON_PLATE}
    pose, source = _laser_pose(_pb("base_laser_link", static), LocalizeConfig())
    assert source == "tf_static"
    np.testing.assert_allclose(pose[:2], REAR[:2], atol=1e-12)
    assert abs(math.remainder(pose[2] - REAR[2], 2 * math.pi)) < 1e-12
    # recorded the other way round (laser -> base_link): tf2 inverts it, so do we
    inv = {("base_laser_link", "base_link"): np.linalg.inv(PLATE @ LASER_ON_PLATE)}
    pose2, _ = _laser_pose(_pb("base_laser_link", inv), LocalizeConfig())
    np.testing.assert_allclose(pose2[:2], REAR[:2], atol=1e-12)


def test_user_mount_wins_and_the_robot_file_is_the_last_resort() -> None:
    static = {("base_link", "base_laser_link"): PLATE @ LASER_ON_PLATE}
    cfg = LocalizeConfig(laser_pose=(0.1, 0.0, 0.0), robot_laser_pose=(0.7, 0.0, 0.0))
    pose, source = _laser_pose(_pb("base_laser_link", static), cfg)
    assert source == "user" and pose.tolist() == [0.1, 0.0, 0.0]
    cfg = LocalizeConfig(robot_laser_pose=(0.7, 0.0, 0.0))
    pose, source = _laser_pose(_pb("base_laser_link", static), cfg)  # the bag's over the file
    assert source == "tf_static" and pose[0] == pytest.approx(-0.2)
    pose, source = _laser_pose(_pb("base_laser_link"), cfg)  # no /tf_static: the robot file
    assert source == "robot_file" and pose.tolist() == [0.7, 0.0, 0.0]


def test_no_mount_anywhere_is_refused_naming_the_options() -> None:
    # the twin's own frame names, but recorded for another frame: not base_link -> laser
    static = {("base_link", "camera_link"): PLATE}
    with pytest.raises(InvalidInputError, match=r"'base_laser_link'.*--laser-pose.*--robot"):
        _laser_pose(_pb("base_laser_link", static), LocalizeConfig())
    with pytest.raises(InvalidInputError, match="static frames: base_link, camera_link"):
        _laser_pose(_pb("base_laser_link", static), LocalizeConfig())
    mixed = _pb("front_laser")
    mixed.scans.append(_scan(0.3, "rear_laser"))
    with pytest.raises(InvalidInputError, match="several frames"):
        _laser_pose(mixed, LocalizeConfig(robot_laser_pose=(0.3, 0.0, 0.0)))


def _room() -> OccupancyGrid:
    data = np.zeros((60, 60), np.int8)
    data[[0, -1], :] = 100
    data[:, [0, -1]] = 100
    return OccupancyGrid(data, 0.05)


def _bag(path: Path, static: bool) -> Path:
    with BagWriter(path) as bag:
        bag.write("/map", rm.occupancy_grid(_room(), 0.0))
        if static:
            tfs = [
                rm.transform_stamped(0.0, "base_link", "plate", PLATE),
                rm.transform_stamped(0.0, "plate", "base_laser_link", LASER_ON_PLATE),
            ]
            bag.write("/tf_static", rm.tf_message(tfs), 0.0)
        bag.write("/initialpose", rm.pose_cov_stamped(0.0, "map", [1.5, 1.5, 0.0], None))
        for t in (0.0, 0.1, 0.2):
            o = Odometry(np.zeros(3), np.zeros(2), t, "odom", "base_link")
            bag.write("/odom", rm.odometry(o))
        for t in (0.05, 0.15):
            bag.write("/scan", rm.laser_scan(_scan(t, "base_laser_link")))
    return path


def test_the_run_summary_says_which_mount_was_used(tmp_path) -> None:
    bag = _bag(tmp_path / "rear.mcap", static=True)
    s = run_localize(bag, tmp_path / "run", cfg=LocalizeConfig(method="amcl"))
    assert s["laser_pose_source"] == "tf_static"
    np.testing.assert_allclose(s["laser_pose"][:2], REAR[:2], atol=1e-6)
    on_disk = json.loads((tmp_path / "run" / "summary.json").read_text())
    assert on_disk["laser_pose_source"] == "tf_static"


def test_cli_refuses_a_bag_without_the_mount_in_one_line(tmp_path) -> None:
    from typer.testing import CliRunner

    from mmpa.cli.main import app

    bag = _bag(tmp_path / "bare.mcap", static=False)
    res = CliRunner().invoke(app, ["localize", "--bag", str(bag), "--out", str(tmp_path / "o")])
    assert res.exit_code == 2, res.output
    assert "Traceback" not in res.output
    assert "no lidar mount" in res.output and "--laser-pose" in res.output
    args = ["localize", "--bag", str(bag), "--out", str(tmp_path / "o"), "--method", "amcl"]
    res = CliRunner().invoke(app, [*args, "--laser-pose", "-0.2,0.02,3.14159"])
    assert res.exit_code == 0, res.output
    s = json.loads((tmp_path / "o" / "summary.json").read_text())
    assert s["laser_pose_source"] == "user" and s["laser_pose"] == [-0.2, 0.02, 3.14159]


# ------------------------------------------------------------------------- map cells


@pytest.mark.parametrize(
    ("data", "shown"),
    [
        (np.full((2, 2), 200), "200"),  # an int8 cast would give -56
        (np.full((2, 2), 101, np.int8), "101"),
        (np.array([[0, -2]]), "-2"),
        (np.array([[0.0, 50.7]]), "50.7"),  # a cast would give 50
        (np.array([[0.0, np.nan]]), "nan"),
        (np.array([[np.inf, 0.0]]), "inf"),
    ],
)
def test_map_cells_outside_the_ros_range_are_refused(data, shown) -> None:
    with pytest.raises(InvalidInputError, match=rf"got {shown}\b"):
        OccupancyGrid(data, 0.05)


def test_map_cells_in_range_are_kept_exactly() -> None:
    for data in ([[-1, 0, 100]], np.array([[-1.0, 0.0, 100.0]]), np.array([[0, 7, 100]], np.uint8)):
        g = OccupancyGrid(data, 0.05)
        assert g.data.dtype == np.int8
        assert g.data.tolist() == np.asarray(data).astype(int).tolist()
    with pytest.raises(InvalidInputError, match="got 255"):  # map_server's raw 'unknown'
        OccupancyGrid(np.array([[255, 0]], np.uint8), 0.05)
    with pytest.raises(InvalidInputError, match="dtype"):
        OccupancyGrid([["a", "b"]], 0.05)


# ------------------------------------------------------------------------- scene seed


@pytest.mark.parametrize("seed", [-1, True, 1.5, "7"])
def test_a_scene_seed_numpy_cannot_take_is_refused_at_load(seed) -> None:
    from mmpa.backends.twin.scene import load_scene, parse_scene
    from mmpa.core.errors import ConfigError

    doc = load_scene().model_dump(mode="json")
    doc["seed"] = seed
    with pytest.raises(ConfigError, match=r"(?s)scene.yaml: invalid scene.*\bseed:"):
        parse_scene(doc, "scene.yaml")
    doc["seed"] = 2**40  # any non-negative integer is a numpy seed
    assert parse_scene(doc, "scene.yaml").seed == 2**40


def test_snapshot_of_a_negative_seed_scene_is_one_clear_line(tmp_path) -> None:
    import yaml
    from typer.testing import CliRunner

    from mmpa.backends.twin.scene import load_scene
    from mmpa.cli.main import app

    doc = load_scene().model_dump(mode="json")
    doc["seed"] = -1
    (tmp_path / "s.yaml").write_text(yaml.safe_dump(doc))
    args = ["sim", "snapshot", "--set", f"scene={tmp_path / 's.yaml'}", "--out", str(tmp_path)]
    res = CliRunner().invoke(app, args)
    assert res.exit_code == 2 and "Traceback" not in res.output
    assert "seed: Input should be greater than or equal to 0" in " ".join(res.output.split())
    assert not (tmp_path / "summary.json").exists()


# ------------------------------------------------------------------------- task store


@pytest.fixture
def store_db(tmp_path: Path) -> Path:
    from mmpa.tasks import TaskStore
    from test_tasks import make_task

    p = tmp_path / "t.db"
    with TaskStore(p) as s:
        s.save(make_task("valve"))
        s.save(make_task("cup"))
    return p


@pytest.mark.parametrize(
    ("sql", "said"),
    [
        ("DELETE FROM clouds WHERE task = 'valve'", "row in table 'clouds' is missing"),
        ("DELETE FROM paths WHERE task = 'valve'", "row in table 'paths' is missing"),
        (
            "UPDATE clouds SET ply = substr(ply, 1, length(ply) - 1) WHERE task = 'valve'",
            "truncated or padded",
        ),
        ("UPDATE clouds SET ply = substr(ply, 1, 20) WHERE task = 'valve'", "not a PLY"),
        ("UPDATE clouds SET ply = 'text' WHERE task = 'valve'", "clouds.ply is not a blob"),
        ("UPDATE clouds SET ply = ply || x'00' WHERE task = 'valve'", "clouds.ply is not a blob"),
        (
            "UPDATE clouds SET ply = CAST(ply || x'0000' AS BLOB) WHERE task = 'valve'",
            "truncated or padded",
        ),
        (
            "UPDATE paths SET q = substr(q, 1, length(q) - 48) WHERE task = 'valve'",
            "paths.q has",
        ),
        ("UPDATE paths SET t = 3.5 WHERE task = 'valve'", "paths.t is not a blob"),
    ],
)
def test_tasks_list_refuses_a_task_whose_blobs_are_missing_or_cut(store_db, sql, said) -> None:
    import sqlite3

    from typer.testing import CliRunner

    from mmpa.cli.main import app
    from mmpa.core.errors import CorruptTaskError
    from mmpa.tasks import TaskStore

    with TaskStore(store_db) as s:
        assert [i.name for i in s.list()] == ["cup", "valve"]
    con = sqlite3.connect(store_db)
    con.execute(sql)
    con.commit()
    con.close()
    with TaskStore(store_db) as s:
        with pytest.raises(CorruptTaskError, match="task 'valve'"):
            s.load("valve")  # show refuses it ...
        with pytest.raises(CorruptTaskError, match=rf"task 'valve' in .*{said}"):
            s.list()  # ... and so does list, instead of listing it as fine
        s.load("cup")  # the other task is intact
    res = CliRunner().invoke(app, ["tasks", "list", "--db", str(store_db)])
    assert res.exit_code == 2 and "Traceback" not in res.output
    assert said in " ".join(res.output.split())


# ------------------------------------------------------------------- TMMA replay checks


class _RecordingArm:
    """An ``Arm`` that records what it is told and moves nowhere else."""

    def __init__(self, q: np.ndarray) -> None:
        self.q = np.asarray(q, float).copy()
        self.calls: list[str] = []

    def joint_positions(self) -> np.ndarray:
        return self.q.copy()

    def move_joints(self, q, duration=None) -> None:
        self.calls.append("move_joints")
        self.q = np.asarray(q, float).copy()

    def follow(self, t, q, record_hz=None):
        self.calls.append("follow")
        self.q = np.asarray(q, float)[-1].copy()
        return None


def _task(q: np.ndarray, T: np.ndarray, name: str = "jump"):
    from mmpa.robot.interfaces import PointCloud
    from mmpa.tasks import Task, ToolPath

    t = np.arange(len(q)) * 0.02
    cloud = PointCloud(np.random.default_rng(0).normal(size=(10, 3)), None)
    return Task(name, "0", np.eye(4), q[0], np.eye(4), cloud, ToolPath(t, q, T, 50.0))


def _jump_path() -> np.ndarray:
    from mmpa.robot.description import ArmDescription

    q = np.tile(np.array(ArmDescription().home), (20, 1))
    q[10:, 0] += 1.5  # joint 1 jumps 1.5 rad in 20 ms
    return q


def test_a_tmma_replay_that_must_be_slowed_says_so(caplog) -> None:
    from mmpa.missions.teach_repeat import replay_tmma
    from mmpa.robot.description import RobotDescription
    from mmpa.robot.kinematics import fk

    rob = RobotDescription()
    tcp = rob.gripper.T_flange_tcp
    q = _jump_path()
    task = _task(q, fk(rob.arm.dh, q, tcp))  # consistent: only too fast
    arm = _RecordingArm(q[0])
    with caplog.at_level("WARNING", logger="mmpa"):
        path, _ = replay_tmma(task, RobotDevices(rob, arm=arm), T_flange_tool=tcp)
    assert path.time_scale > 20  # 1.5 rad in 20 ms is 24x joint 1's velocity limit
    (rec,) = [r for r in caplog.records if "slowed" in r.getMessage()]
    assert rec.levelname == "WARNING" and rec.name == "mmpa.missions.teach_repeat"
    assert f"slowed {path.time_scale:.2f}x" in rec.getMessage() and "task jump" in rec.getMessage()
    assert arm.calls[0] == "move_joints" and "follow" in arm.calls
    # a path within the limits replays at its own pace, with no warning
    caplog.clear()
    slow = _task(q[:10], fk(rob.arm.dh, q[:10], tcp), "calm")
    path, _ = replay_tmma(slow, RobotDevices(rob, arm=_RecordingArm(q[0])), T_flange_tool=tcp)
    assert path.time_scale == 1.0
    assert not [r for r in caplog.records if "slowed" in r.getMessage()]


def test_tmma_refuses_joints_that_are_not_the_tool_path_before_moving() -> None:
    from mmpa.missions.teach_repeat import replay_tmma, tool_path_mismatch
    from mmpa.robot.description import RobotDescription
    from mmpa.robot.kinematics import fk

    rob = RobotDescription()
    tcp = rob.gripper.T_flange_tcp
    q = _jump_path()
    T = fk(rob.arm.dh, np.tile(q[0], (len(q), 1)), tcp)  # the tool path never jumps
    task = _task(q, T)
    d, ang, i = tool_path_mismatch(task, rob.arm, tcp)
    # joint 1 turns the tool about the base z axis: a chord of 1.5 rad at the tool's radius
    chord = 2 * np.hypot(*T[0, :2, 3]) * math.sin(0.75)
    assert i >= 10 and d == pytest.approx(chord, abs=1e-9) and ang == pytest.approx(1.5)
    arm = _RecordingArm(q[0])
    with pytest.raises(
        InvalidInputError, match=rf"disagree by {chord * 1e3:.1f} mm .*waypoint 1\d"
    ):
        replay_tmma(task, RobotDevices(rob, arm=arm), T_flange_tool=tcp)
    assert arm.calls == []  # nothing moved


def test_tmma_accepts_a_task_taught_with_a_slightly_different_arm_model() -> None:
    """A task taught with the nominal DH and replayed with a DH off by the twin's harsh
    kinematic error (1 mm on a and d, 0.1 deg on the angles): the disagreement is real but
    within MAX_TOOL_MISMATCH (measured over 30 harsh draws on a taught path: <= 9.3 mm /
    0.67 deg; here one draw on the jump path)."""
    from mmpa.backends.twin.error_model import ErrorModel, ErrorModelConfig
    from mmpa.missions.teach_repeat import MAX_TOOL_MISMATCH, check_tool_path
    from mmpa.robot.description import RobotDescription
    from mmpa.robot.kinematics import fk

    rob = RobotDescription()
    tcp = rob.gripper.T_flange_tcp
    q = _jump_path()
    task = _task(q, fk(rob.arm.dh, q, tcp))
    assert check_tool_path(task, rob.arm, tcp) == (0.0, 0.0)  # the arm model it was taught with
    other = ErrorModel.sample(rob, ErrorModelConfig(profile="harsh", seed=3)).true.arm
    mm, deg = check_tool_path(task, other, tcp)
    assert 0.3 < mm < MAX_TOOL_MISMATCH[0] * 1e3 and 0.0 < deg < np.rad2deg(MAX_TOOL_MISMATCH[1])
    with pytest.raises(InvalidInputError, match="another arm model or tool"):
        check_tool_path(task, rob.arm, np.eye(4))  # the flange, not the TCP: 150 mm off


# ------------------------------------------------------------------- camera intrinsics


def test_an_uncalibrated_camera_info_is_refused_and_distortion_is_logged(caplog) -> None:
    import dataclasses

    from mmpa.robot.description import CameraIntrinsics

    k = CameraIntrinsics(fx=600.0, fy=601.0, cx=320.0, cy=240.0)
    msg = rm.camera_info(k, 1.0, "cam_optical")
    assert rm.from_camera_info(msg) == k
    with pytest.raises(InvalidInputError, match=r"'cam_optical' is not a calibrated .*--intrin"):
        rm.from_camera_info(dataclasses.replace(msg, k=np.zeros(9)))  # driver, no calibration
    with caplog.at_level("WARNING", logger="mmpa"):
        got = rm.from_camera_info(dataclasses.replace(msg, d=np.array([0.1, -0.2, 0, 0, 0])))
    assert got == k
    assert "plumb_bob distortion [0.1, -0.2, 0.0, 0.0, 0.0]" in caplog.text
