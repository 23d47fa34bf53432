"""The robot file: round trip, UR presets, the UR factory calibration against an independent
forward kinematics, frame names, clear errors, and ``mmpa --robot FILE`` reaching the twin."""

from __future__ import annotations

import numpy as np
import pytest
from typer.testing import CliRunner

from mmpa.core.errors import ConfigError
from mmpa.robot.description import RobotDescription, default_robot, set_default_robot
from mmpa.robot.kinematics import fk
from mmpa.robot.robot_file import (
    UR_MODELS,
    FrameNames,
    frame_names,
    load_robot,
    read_ur_calibration,
    robot_backend,
    robot_to_yaml,
    save_robot,
)

CAL = """[mounting]
delta_theta = [ 1.2e-05, -0.00031, 0.0007, -0.0004, 2.1e-05, 0.0 ]
delta_a = [ 3.4e-05, 0.00021, 0.0011, 0.0, 0.0, 0.0 ]
delta_d = [ 0.00012, 5.0e-05, -0.0003, 0.00025, -2.0e-05, 0.0 ]
delta_alpha = [ -3.1e-05, 0.00011, -0.0002, 4.0e-05, 0.0, 0.0 ]
joint_checksum = [ 1, 2, 3, 4, 5, 6 ]
"""


def _dh_fk(a, d, alpha, theta, q) -> np.ndarray:
    """Standard DH chain written out here (independent of mmpa.robot.kinematics)."""
    T = np.eye(4)
    for i in range(6):
        ct, st = np.cos(q[i] + theta[i]), np.sin(q[i] + theta[i])
        ca, sa = np.cos(alpha[i]), np.sin(alpha[i])
        T = T @ np.array(
            [
                [ct, -st * ca, st * sa, a[i] * ct],
                [st, ct * ca, -ct * sa, a[i] * st],
                [0, sa, ca, d[i]],
                [0, 0, 0, 1],
            ]
        )
    return T


def test_round_trip_keeps_every_field(tmp_path) -> None:
    robot = RobotDescription().with_updates(name="custom")
    frames = FrameNames(prefix="robot1/", arm_prefix="ur_")
    path = save_robot(robot, tmp_path / "robot.yaml", frames)
    back, fr = load_robot(path)
    assert back == robot and fr == frames
    names = frame_names(fr)
    assert names["base_link"] == "robot1/base_link" and names["flange"] == "robot1/ur_tool0"
    assert names["arm_base"] == "robot1/ur_base" and names["map"] == "map"


@pytest.mark.parametrize("model", sorted(UR_MODELS))
def test_ur_presets_take_the_published_values(tmp_path, model) -> None:
    p = tmp_path / "r.yaml"
    p.write_text(f"arm: {{model: {model}}}\n")
    robot, _ = load_robot(p)
    spec = UR_MODELS[model]
    assert robot.arm.name == model
    assert robot.arm.dh.a == spec["a"] and robot.arm.dh.d == spec["d"]
    assert robot.arm.qd_max == spec["qd_max"] and robot.arm.reach == spec["reach"]
    # the shoulder-to-wrist length of the folded-out arm is the sum of the link lengths
    T = fk(robot.arm.dh, np.zeros(6))
    assert abs(T[0, 3]) == pytest.approx(-spec["a"][1] - spec["a"][2] + 0.0, abs=1e-9)


def test_factory_calibration_matches_an_independent_dh_chain(tmp_path) -> None:
    (tmp_path / "calibration.conf").write_text(CAL)
    p = tmp_path / "r.yaml"
    p.write_text("arm: {model: ur10e, calibration: calibration.conf}\n")
    robot, _ = load_robot(p)
    deltas = read_ur_calibration(tmp_path / "calibration.conf")
    spec = UR_MODELS["ur10e"]
    alpha0 = np.array([np.pi / 2, 0, 0, np.pi / 2, -np.pi / 2, 0])
    q = np.array([0.3, -1.2, 1.4, -0.8, 1.1, 0.5])
    expected = _dh_fk(
        np.array(spec["a"]) + deltas["delta_a"],
        np.array(spec["d"]) + deltas["delta_d"],
        alpha0 + deltas["delta_alpha"],
        np.array(deltas["delta_theta"]),
        q,
    )
    np.testing.assert_allclose(fk(robot.arm.dh, q), expected, atol=1e-12)
    nominal = fk(load_robot_text(tmp_path, "arm: {model: ur10e}\n").arm.dh, q)
    assert np.linalg.norm(expected[:3, 3] - nominal[:3, 3]) > 5e-4  # the deltas matter


def load_robot_text(tmp_path, text: str) -> RobotDescription:
    p = tmp_path / "other.yaml"
    p.write_text(text)
    return load_robot(p)[0]


@pytest.mark.parametrize(
    ("text", "message"),
    [
        ("arm: {model: ur7}\n", "arm.model 'ur7' is not known; valid: ur3e"),
        ("arm: {qd_max: [1, 2]}\n", "arm"),
        ("camera: {T_flange_camera_vec: [0, 0, .nan, 0, 0, 0]}\n", "camera"),
        ("arm: {calibration: missing.conf}\n", "arm.calibration: cannot read UR calibration"),
        ("frames: {prefix: 3, bogus: x}\n", "frames"),
        ("- a list\n", "must be a YAML mapping"),
        ("a: &x [1]\nb: *x\n", "alias"),
        ("backend: {kind: moon}\n", "backend.kind"),
        ("backend: [twin]\n", "backend: must be a mapping"),
        ("backend: {safety: {speed_scale: 1.5}}\n", "backend.safety.speed_scale"),
        ("backend: {ros2: {topics: {scna: /scan}}}\n", "backend.ros2.topics.scna"),
    ],
)
def test_bad_robot_files_name_the_file_and_field(tmp_path, text, message) -> None:
    p = tmp_path / "bad.yaml"
    p.write_text(text)
    with pytest.raises(ConfigError, match=r"bad\.yaml") as e:
        load_robot(p)
    assert message in str(e.value)


def test_bad_calibration_file(tmp_path) -> None:
    c = tmp_path / "c.conf"
    c.write_text("[mounting]\ndelta_theta = [1, 2, 3, 4, 5, 6]\n")
    with pytest.raises(ConfigError, match="delta_a"):
        read_ur_calibration(c)
    c.write_text(CAL.replace("0.0007", "nan"))
    with pytest.raises(ConfigError, match="delta_theta: need 6 finite"):
        read_ur_calibration(c)


def test_robot_option_reaches_the_twin(tmp_path, monkeypatch) -> None:
    from mmpa.cli.main import app

    p = tmp_path / "r.yaml"
    p.write_text("name: my-robot\ngripper: {length: 0.2}\n")
    monkeypatch.chdir(tmp_path)
    try:
        res = CliRunner().invoke(app, ["--robot", str(p), "robot", "show"])
        assert res.exit_code == 0, res.output
        assert "name: my-robot" in res.output and "length: 0.2" in res.output
        assert default_robot().gripper.length == 0.2
        from mmpa.backends.twin.world import SimWorld

        with SimWorld() as w:  # the twin builds the robot of the file
            assert w.nominal.name == "my-robot"
            assert w.true_robot.gripper.length == pytest.approx(0.2, abs=0.01)
        bad = CliRunner().invoke(app, ["--robot", str(tmp_path / "none.yaml"), "robot", "show"])
        assert bad.exit_code == 2 and "none.yaml" in bad.output
    finally:
        set_default_robot(None)
    assert default_robot() == RobotDescription()


def test_backend_section(tmp_path) -> None:
    assert robot_backend(None).kind == "twin" and not robot_backend(None).hardware
    p = tmp_path / "r.yaml"
    p.write_text(
        "name: fixed-arm\n"
        "backend:\n"
        "  kind: direct\n"
        "  direct: {ur_host: 10.0.0.2, realsense_playback: rec/desk.bag, base: none}\n"
        "  safety: {speed_scale: 0.1}\n"
    )
    b = robot_backend(p)
    assert b.kind == "direct" and b.hardware
    assert b.direct.ur_host == "10.0.0.2" and b.safety.speed_scale == 0.1
    assert b.direct.realsense_playback == tmp_path / "rec" / "desk.bag"  # beside the file
    assert b.ros2.topics.scan == "/scan" and b.ros2.joint_names[0] == "shoulder_pan_joint"
    robot, frames = load_robot(p)  # the section is not part of the description
    assert robot.name == "fixed-arm"
    q = tmp_path / "again.yaml"  # a written template reads back with the same backend
    q.write_text(robot_to_yaml(robot, frames, backend=b))
    assert robot_backend(q) == b and load_robot(q)[0] == robot
