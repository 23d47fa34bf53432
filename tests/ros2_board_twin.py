"""The twin node (``mmpa ros2 twin``'s :func:`~mmpa.apps.ros2_twin.run_twin_node`) with a
ChArUco board in front of site 0, the arm at a view of it (where a user would jog it), for
``mmpa --robot R calibrate hand-eye`` over ROS 2 (tests/test_ros2_robot.py). The twin node
has no board of its own: this test helper swaps the world its module builds for
:func:`~mmpa.backends.twin.calibration_board.board_world`. The TRUE hand-eye (for the test's
judgement only) is written to ``TRUTH`` (JSON) before the node runs.

Usage: python tests/ros2_board_twin.py TRUTH DURATION (ROS_DOMAIN_ID etc. from the
environment)."""

from __future__ import annotations

import json
import sys

import numpy as np

import mmpa.apps.ros2_twin as ros2_twin
from mmpa.backends.twin.calibration_board import BoardPlacement, board_world
from mmpa.backends.twin.scene import load_scene
from mmpa.calibration.hand_eye import plan_stations
from mmpa.maps.board import CharucoBoardSpec

BOARD = CharucoBoardSpec()


def main(truth: str, duration: float) -> None:
    scene = load_scene()
    placement = BoardPlacement.for_site(scene, "0")

    def world(errors, site):  # SimWorld(errors=..., site=...) as the node builds it
        w = board_world(site, BOARD, placement, errors=errors, scene=scene)
        rd, k = w.nominal, w.camera.intrinsics
        guess = placement.T_armbase_board(BOARD, rd)
        first = plan_stations(
            rd.arm.dh, rd.arm.q_limits, guess, rd.camera.T_flange_camera, BOARD.corners(),
            k.K, (k.width, k.height), 3, np.asarray(rd.arm.view_bench), tilts_deg=(0.0, 10.0),
            rolls_deg=(0.0,), max_joint_step=2 * np.pi,
        )[0]  # fmt: skip
        w.arm.move_joints(first.q)
        w.step(0.5)
        with open(truth, "w") as f:
            json.dump({"T_flange_camera": w.true_robot.camera.T_flange_camera.tolist()}, f)
        return w

    ros2_twin.SimWorld = world  # type: ignore[assignment,misc]
    cfg = ros2_twin.twin_node_config(
        site="0", profile="realistic", seed=1, camera=True,
        **{"errors.kinematics.dh_length_sigma": 0.0, "errors.kinematics.dh_angle_sigma_deg": 0.0},
    )  # fmt: skip
    ros2_twin.run_twin_node(cfg, None, duration)


if __name__ == "__main__":
    main(sys.argv[1], float(sys.argv[2]))
