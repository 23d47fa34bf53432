"""The files the twin's calibrations write: ``hand_eye.yaml`` (the hand-eye as a 4x4 in m and
as the robot file's ``camera.T_flange_camera_vec``), a UR controller's ``calibration.conf``
(the DH corrections, rad and m), ``robot.yaml`` (the robot in use with the calibrated
hand-eye, kinematics, lidar mount or reflector map) and ``summary.json``.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from mmpa.calibration.kinematic import DH_GROUPS
from mmpa.core.geometry import Array, T_to_vec6
from mmpa.robot.description import DHParameters, RobotDescription, default_robot
from mmpa.robot.robot_file import load_robot, robot_backend, robot_to_yaml, save_robot

__all__ = [
    "hand_eye_yaml",
    "log_default",
    "ur_calibration_conf",
    "write_robot_file",
    "write_robot_file_lidar",
    "write_robot_file_reflectors",
    "write_summary",
]


def log_default(msg: str) -> None:
    print(msg, flush=True)


def write_summary(out: Path, summary: dict[str, Any]) -> None:
    """``out/summary.json`` (indented, newline-terminated)."""
    (out / "summary.json").write_text(json.dumps(summary, indent=2) + "\n")


def hand_eye_yaml(
    X: Array,
    method: str,
    frames: tuple[str, str] = ("flange", "camera_optical"),
    dh: DHParameters | None = None,
) -> str:
    """``hand_eye.yaml``: the estimate as a 4x4 (m) with its frames, and the robot file's
    ``camera: {T_flange_camera_vec: [...]}`` section (paste or merge into a robot file);
    with ``dh`` (the calibrated kinematics the hand-eye belongs to) also ``arm: {dh: ...}``."""
    X = np.asarray(X, float)
    doc: dict[str, Any] = {
        "hand_eye": {
            "parent_frame": frames[0],
            "child_frame": frames[1],
            "convention": "T_parent_child: p_parent = T p_child; metres; optical frame z "
            "forward, x right, y down",
            "method": method,
            "T_flange_camera": [[float(v) for v in row] for row in X],
        },
        "camera": {"T_flange_camera_vec": [float(v) for v in T_to_vec6(X)]},
    }
    if dh is not None:
        doc["arm"] = {"dh": {k: [float(v) for v in vals] for k, vals in dh.model_dump().items()}}
    return yaml.safe_dump(doc, sort_keys=False, default_flow_style=None, width=120)


def ur_calibration_conf(deltas: dict[str, Array]) -> str:
    """The DH corrections ``deltas`` (keys ``delta_theta, delta_a, delta_d, delta_alpha``,
    6 values each, rad and m) as a UR controller's ``calibration.conf`` (``[mounting]``):
    a robot file takes it with ``arm: {calibration: calibration.conf}``
    (:func:`mmpa.robot.robot_file.read_ur_calibration`)."""
    lines = ["[mounting]"]
    for k in DH_GROUPS:
        vals = np.asarray(deltas[k], float).reshape(6)
        lines.append(f"{k} = [{', '.join(repr(float(v)) for v in vals)}]")
    return "\n".join(lines) + "\n"


def write_robot_file(
    T_flange_camera: Array,
    path: str | Path,
    dh: DHParameters | None = None,
    robot: RobotDescription | None = None,
    robot_file: str | Path | None = None,
) -> Path:
    """``robot`` (default: the robot in use, ``mmpa --robot FILE``, else the twin's) with the
    calibrated ``camera.T_flange_camera`` and, when given, the calibrated arm kinematics
    ``dh``, written as a robot file: the next run takes it with ``mmpa --robot PATH``.
    ``robot_file``: the robot file of a hardware robot, whose ``frames`` and ``backend``
    sections the written file keeps (so it drives the same robot)."""

    robot = robot or default_robot()
    vec = tuple(float(v) for v in T_to_vec6(T_flange_camera))
    camera = robot.camera.model_copy(update={"T_flange_camera_vec": vec})
    updates: dict[str, Any] = {"camera": camera.model_dump()}
    if dh is not None:
        updates["arm"] = robot.arm.model_copy(update={"dh": dh}).model_dump()
    calibrated = robot.with_updates(**updates)
    if robot_file is None:
        return save_robot(calibrated, path)
    frames, backend = load_robot(robot_file)[1], robot_backend(robot_file)
    return _write_text(Path(path), robot_to_yaml(calibrated, frames, backend=backend))


def write_robot_file_lidar(mount: Array, path: Path) -> Path:
    """The robot in use with the calibrated lidar mount translation ``mount[:2]`` (m) in
    ``lidar.T_base_link_laser_vec`` (the nominal height, roll, pitch and yaw kept)."""
    robot = default_robot()
    vec = list(robot.lidar.T_base_link_laser_vec)
    vec[0], vec[1] = float(mount[0]), float(mount[1])
    lidar = robot.lidar.model_copy(update={"T_base_link_laser_vec": tuple(vec)})
    return save_robot(robot.with_updates(lidar=lidar.model_dump()), path)


def write_robot_file_reflectors(
    path: Path, reflector_map: str, robot_file: str | Path | None = None
) -> Path:
    """The robot in use (``mmpa --robot FILE``, else the twin's) as a robot file whose
    ``reflector_map`` names the surveyed map (relative: beside the robot file);
    ``robot_file``: a hardware robot's file, whose ``frames`` and ``backend`` it keeps."""

    if robot_file is None:
        return save_robot(default_robot(), path, reflector_map=reflector_map)
    robot, frames = load_robot(robot_file)
    text = robot_to_yaml(robot, frames, reflector_map, robot_backend(robot_file))
    return _write_text(Path(path), text)


def _write_text(p: Path, text: str) -> Path:
    """``text`` to ``p`` (a temporary file renamed: never half a robot file)."""
    p.parent.mkdir(parents=True, exist_ok=True)
    tmp = p.with_name(p.name + ".tmp")
    tmp.write_text(text, encoding="utf-8")
    tmp.replace(p)
    return p
