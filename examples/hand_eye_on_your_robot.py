"""Calibrate the wrist camera on your robot: mmpa's hand-eye procedure over the ``Arm`` and
``Camera`` protocols, then a robot file with the result for ``mmpa --robot FILE``.

Print a ChArUco board (mmpa's default: 7 x 5 squares of 40 mm, 30 mm DICT_5X5_100 markers;
``mmpa.calibration.charuco.CharucoBoardSpec().image()`` at 2500 px/m), fix it in front of
the arm and measure roughly where it stands in the arm base frame (the board frame is
OpenCV's: origin at a corner, z into the board). The procedure plans 40 views around it,
moves the arm, detects the board in each frame and fits the hand-eye with the arm's DH
corrections.

Run:
- ``python examples/hand_eye_on_your_robot.py``: in the twin (its arm and camera as the
  hardware, the board where the twin puts it);
- ``python examples/hand_eye_on_your_robot.py --ur 192.168.1.10 --board-pose
  0.55,0.0,0.15,3.14,0,0 [--robot robot.yaml]``: a UR over RTDE (``pip install
  'mmpa[ur]'``) and a RealSense (``'mmpa[realsense]'``); the board pose is ``x, y, z`` (m)
  and a rotation vector (rad) in the arm base frame. The arm moves: keep the workspace
  clear and a hand on the protective stop.

Writes ``robot.yaml`` (``--out``, default ``hand_eye_robot.yaml``): the robot file with the
calibrated hand-eye and DH.
"""

from __future__ import annotations

import argparse
import os
from pathlib import Path

import numpy as np

from mmpa.apps.calibrate import write_robot_file
from mmpa.core.geometry import exp_se3
from mmpa.missions.hand_eye import HandEyeProcedureConfig, calibrate_hand_eye_on_robot
from mmpa.robot.description import RobotDescription, default_robot
from mmpa.robot.interfaces import RobotDevices, WallClock
from mmpa.robot.robot_file import load_robot


def _twin(cfg: HandEyeProcedureConfig, seed: int):
    """The twin as the hardware: its arm, camera, a settle on its clock, the board's rough
    pose where the twin places it (a tape measure's worth of knowledge)."""
    os.environ.setdefault("MUJOCO_GL", "osmesa")
    os.environ.setdefault("PYOPENGL_PLATFORM", "osmesa")
    from mmpa.backends.twin.calibration_board import BoardPlacement, board_world
    from mmpa.backends.twin.error_model import ErrorModelConfig
    from mmpa.backends.twin.scene import load_scene

    scene = load_scene()
    placement = BoardPlacement.for_site(scene, "0")
    errors = ErrorModelConfig.from_profile("realistic", seed=seed)
    world = board_world("0", cfg.board, placement, errors=errors, scene=scene)
    robot = world.nominal
    guess = placement.T_armbase_board(cfg.board, robot)
    return world, world.arm, world.camera, robot, guess, world.step


def _hardware(host: str, robot: RobotDescription):
    """A UR over RTDE and a RealSense (the optional extras)."""
    from mmpa.backends.realsense import RealSenseCamera
    from mmpa.backends.ur import URArm, URConfig
    from mmpa.robot.limits import JointLimits

    arm = URArm(JointLimits.from_description(robot.arm), URConfig(host=host))
    return arm, RealSenseCamera()


def main(argv: list[str] | None = None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--ur", default=None, help="the UR controller's address (else: the twin)")
    ap.add_argument("--board-pose", default=None, help="x,y,z,rx,ry,rz in the arm base")
    ap.add_argument("--robot", type=Path, default=None, help="your robot file (nominal)")
    ap.add_argument("--views", type=int, default=40)
    ap.add_argument("--seed", type=int, default=1, help="the twin's robot instance")
    ap.add_argument("--out", type=Path, default=Path("hand_eye_robot.yaml"))
    a = ap.parse_args(argv)
    cfg = HandEyeProcedureConfig(stations=a.views)
    robot = load_robot(a.robot)[0] if a.robot else default_robot()
    world = None
    if a.ur is None:
        world, arm, camera, robot, guess, wait = _twin(cfg, a.seed)
    else:
        if a.board_pose is None:
            raise SystemExit("--board-pose x,y,z,rx,ry,rz is needed with --ur")
        v = np.array([float(x) for x in a.board_pose.split(",")])
        if v.shape != (6,):
            raise SystemExit(f"--board-pose needs 6 numbers, got {a.board_pose!r}")
        guess = exp_se3(v)
        arm, camera = _hardware(a.ur, robot)
        wait = None
    try:
        kw = {"wait": wait} if wait is not None else {}
        devices = RobotDevices(robot, arm=arm, camera=camera, clock=WallClock())
        res = calibrate_hand_eye_on_robot(
            devices, guess, np.asarray(robot.arm.view_bench), cfg, log=print, **kw
        )
        out = {"T_flange_camera": res.T_flange_camera, "method": res.method, "result": res}
        if world is not None:  # the twin knows the truth: the hand-eye on the model's flange
            from mmpa.apps.calibrate import last_link_error
            from mmpa.calibration.hand_eye import pose_error

            E6 = last_link_error(robot.arm.dh, world.true_robot.arm.dh)
            X_eff = E6 @ world.true_robot.camera.T_flange_camera
            et, er = pose_error(res.T_flange_camera, X_eff)
            out["error_mm_deg"] = (et, er)
            print(f"error against the twin's identifiable hand-eye: {et:.2f} mm, {er:.3f} deg")
    finally:
        if world is not None:
            world.close()
    path = write_robot_file(res.T_flange_camera, a.out, dh=res.dh, robot=robot)
    print(f"hand-eye ({res.method}, {len(res.q)} views): wrote {path} (mmpa --robot {path} ...)")
    out["robot_file"] = path
    return out


if __name__ == "__main__":
    main()
