"""``mmpa calibrate hand-eye`` on a hardware backend (issue 36 item 4): a robot file of kind
``ros2`` whose robot is the twin's own arm and camera (``RobotDevices``: no truth reaches
the code path). The board is pointed at from where the arm stands, the views are planned
around it, the question comes before the arm moves; the test alone reads the twin's truth."""

from __future__ import annotations

import json
from contextlib import contextmanager

import numpy as np
import pytest
import yaml
from typer.testing import CliRunner

from mmpa.backends.twin.calibration_board import BoardPlacement, board_world
from mmpa.backends.twin.error_model import ErrorModelConfig
from mmpa.backends.twin.scene import load_scene
from mmpa.calibration.hand_eye import plan_stations, pose_error
from mmpa.cli import robot as cli_robot
from mmpa.cli.main import app
from mmpa.core.geometry import vec6_to_T
from mmpa.maps.board import CharucoBoardSpec
from mmpa.robot.backend_config import BackendConfig
from mmpa.robot.description import default_robot, set_default_robot
from mmpa.robot.interfaces import RobotDevices
from mmpa.robot.robot_file import robot_backend, robot_to_yaml

BOARD = CharucoBoardSpec()


@pytest.fixture(scope="module")
def board():
    """The twin with its board at site 0 (exact arm DH: the hand-eye alone is to be found;
    realistic camera noise, hand-eye error and mount compliance) and the arm at a view of the
    board: where a user would jog it."""
    scene = load_scene()
    placement = BoardPlacement.for_site(scene, "0")
    errors = ErrorModelConfig(
        profile="realistic", seed=1, kinematics={"dh_length_sigma": 0.0, "dh_angle_sigma_deg": 0.0}
    )
    w = board_world("0", BOARD, placement, errors=errors, scene=scene)
    rd = w.nominal
    k = w.camera.intrinsics
    guess = placement.T_armbase_board(BOARD, rd)
    first = plan_stations(
        rd.arm.dh, rd.arm.q_limits, guess, rd.camera.T_flange_camera, BOARD.corners(), k.K,
        (k.width, k.height), 3, np.asarray(rd.arm.view_bench), tilts_deg=(0.0, 10.0),
        rolls_deg=(0.0,), max_joint_step=2 * np.pi,
    )[0]  # fmt: skip
    w.arm.move_joints(first.q)
    w.step(0.5)
    yield w
    w.close()


@pytest.fixture
def hardware(tmp_path, monkeypatch, board):
    """A ``ros2`` robot file (the twin's nominal robot, a frame prefix of its own) whose
    robot, opened by the CLI, is the twin's arm and camera on the twin's clock."""
    path = tmp_path / "robot.yaml"
    doc = yaml.safe_load(robot_to_yaml(default_robot(), backend=BackendConfig(kind="ros2")))
    doc["frames"]["prefix"] = "r1_"
    path.write_text(yaml.safe_dump(doc))
    devices = RobotDevices(board.nominal, arm=board.arm, camera=board.camera, clock=board)

    @contextmanager
    def open_hardware(p):
        assert p == path
        yield devices

    monkeypatch.setattr("mmpa.cli.calibrate.open_hardware", open_hardware)
    yield path
    set_default_robot(None)
    cli_robot._path = None
    cli_robot._frames = None


def test_hand_eye_on_hardware_asks_first_and_a_no_moves_nothing(board, hardware, tmp_path):
    q0 = board.arm.joint_positions().copy()
    out = tmp_path / "no"
    args = ["--robot", str(hardware), "calibrate", "hand-eye", "--out", str(out)]
    r = CliRunner().invoke(app, [*args, "--stations", "8"], input="n\n")
    assert r.exit_code == 1, r.output
    assert "visit 8 views of the board" in r.output and "Move the arm?" in r.output
    s = json.loads((out / "summary.json").read_text())
    assert s == {
        "backend": "ros2",
        "ok": False,
        "reason": "the 8 planned views were declined; nothing moved",
        "moved": False,
    }
    np.testing.assert_array_equal(board.arm.joint_positions(), q0)
    assert not (out / "robot.yaml").exists()


def test_hand_eye_on_hardware_refuses_a_board_it_does_not_see(board, hardware, tmp_path):
    """A board of another dictionary than the one printed: not found from here, nothing
    moves, no question asked."""
    q0 = board.arm.joint_positions().copy()
    out = tmp_path / "other"
    args = ["--robot", str(hardware), "calibrate", "hand-eye", "--out", str(out), "--yes"]
    r = CliRunner().invoke(app, [*args, "--board-dict", "DICT_4X4_50"])
    assert r.exit_code == 1, r.output
    s = json.loads((out / "summary.json").read_text())
    assert not s["ok"] and "corner" in s["reason"], s
    np.testing.assert_array_equal(board.arm.joint_positions(), q0)
    bad = CliRunner().invoke(app, [*args, "--board-squares", "7by5"])
    assert bad.exit_code == 2 and "7by5" in bad.output


def test_hand_eye_on_hardware_calibrates_without_truth(board, hardware, tmp_path):
    """--yes: 8 views planned from where the arm stands, visited, opencv's methods; the
    summary holds residuals only (no truth key); the hand-eye written to robot.yaml, which
    keeps the robot file's backend and frames, is within the issue's 0.5 mm / 0.1 deg of the
    TRUE one (read here only; measured 0.21 mm, 0.014 deg), and its residuals are small."""
    out = tmp_path / "yes"
    args = ["--robot", str(hardware), "calibrate", "hand-eye", "--out", str(out), "--yes"]
    r = CliRunner().invoke(app, [*args, "--stations", "8", "--method", "opencv"])
    assert r.exit_code == 0, r.output
    assert "Move the arm?" not in r.output
    s = json.loads((out / "summary.json").read_text())
    assert s["ok"] and s["backend"] == "ros2" and s["stations_used"] == 8
    assert not any("error" in k and "true" in k for k in s)  # no truth on hardware
    assert "error_trans_mm" not in s
    assert s["residuals"]["point_rms_mm"] < 1.0 and s["residuals"]["rot_rms_deg"] < 0.1
    X = np.array(s["T_flange_camera"])
    et, er = pose_error(X, board.true_robot.camera.T_flange_camera)
    assert et < 0.5 and er < 0.1, (et, er)
    # the change reported equals the estimate against the nominal, computed here
    dt, dr = pose_error(X, board.nominal.camera.T_flange_camera)
    assert s["change_from_nominal_trans_mm"] == pytest.approx(dt, abs=1e-9)
    assert s["change_from_nominal_rot_deg"] == pytest.approx(dr, abs=1e-9)
    written = yaml.safe_load((out / "robot.yaml").read_text())
    X_file = vec6_to_T(np.array(written["camera"]["T_flange_camera_vec"]))
    np.testing.assert_allclose(X_file, X, atol=1e-9)
    assert robot_backend(out / "robot.yaml").kind == "ros2"
    assert written["frames"]["prefix"] == "r1_"
