"""``mmpa calibrate hand-eye`` in the twin: a ChArUco board in front of a site (set-up), the
calibration procedure over the robot interfaces
(:func:`mmpa.missions.hand_eye.calibrate_hand_eye_on_robot`: plan views from where the
board is meant to stand, visit them with the twin's arm and camera, OpenCV's five methods,
then the joint DH + hand-eye fit; only NOMINAL knowledge is used), the evaluation against
the TRUE hand-eye (:mod:`mmpa.apps.calibrate.hand_eye_truth`) and the files
(:mod:`mmpa.apps.calibrate.files`).

Outputs in ``out``: ``summary.json`` (``error_trans_mm``, ``error_rot_deg``,
``error_identifiable_trans_mm``, ``error_identifiable_rot_deg``, the method table,
residuals, stations), ``hand_eye.yaml`` (the estimate: 4x4 and the robot file's
``camera.T_flange_camera_vec``), ``robot.yaml`` and, for ``joint``, ``calibration.conf``.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
from pydantic import Field

from mmpa.apps.calibrate.files import (
    hand_eye_yaml,
    log_default,
    ur_calibration_conf,
    write_robot_file,
    write_summary,
)
from mmpa.apps.calibrate.hand_eye_truth import TruthRecorder, hand_eye_summary
from mmpa.backends.twin.calibration_board import BoardPlacement, T_map_board_truth, board_world
from mmpa.backends.twin.error_model import ErrorModelConfig, ProfileName
from mmpa.backends.twin.scene import load_scene
from mmpa.backends.twin.world import SimWorld
from mmpa.missions.hand_eye import (
    HandEyeProcedureConfig,
    HandEyeProcedureResult,
    calibrate_hand_eye_on_robot,
)
from mmpa.robot.description import RobotDescription

__all__ = ["HandEyeConfig", "run_hand_eye", "write_hand_eye"]


class HandEyeConfig(HandEyeProcedureConfig):
    """The twin run: the procedure's settings (:class:`HandEyeProcedureConfig`: views,
    board, ``method``, the joint fit's priors, the view grid), the ``site`` the board stands
    at (``placement``; None: :meth:`BoardPlacement.for_site`), the twin's error ``profile``
    and ``seed`` (the robot instance), and the configurations the calibrated kinematics are
    evaluated over against the TRUE arm."""

    site: str = "0"
    seed: int = Field(0, ge=0)
    profile: ProfileName = "realistic"
    placement: BoardPlacement | None = None  # None: BoardPlacement.for_site(scene, site)
    fk_eval_configurations: int = Field(500, ge=1, le=100000)


def run_hand_eye(
    cfg: HandEyeConfig,
    out: Path | None = None,
    log: Callable[[str], None] | None = None,
    errors: ErrorModelConfig | None = None,
) -> dict[str, Any]:
    """Run the calibration in the twin (module docstring); returns the summary (also written
    to ``out/summary.json`` with ``out/hand_eye.yaml`` when ``out`` is given). ``errors``
    replaces the error model of ``cfg.profile`` / ``cfg.seed`` (studies of one source)."""

    log = log or log_default
    t0 = time.perf_counter()
    if errors is None:
        errors = ErrorModelConfig.from_profile(cfg.profile, seed=cfg.seed)

    scene = load_scene()
    placement = cfg.placement or BoardPlacement.for_site(scene, cfg.site)
    world = board_world(cfg.site, cfg.board, placement, errors=errors, scene=scene)
    try:
        return _run(world, cfg, placement, out, log, t0)
    finally:
        world.close()


def _calibrate(
    world: SimWorld, cfg: HandEyeConfig, placement: BoardPlacement, truth: TruthRecorder
) -> HandEyeProcedureResult:
    """The procedure with the twin's arm and camera, from where the board is meant to stand
    (nominal, as a user measures it roughly); ``truth`` records each view's ground truth."""
    nominal = world.nominal
    Y_plan = placement.T_armbase_board(cfg.board, nominal)
    return calibrate_hand_eye_on_robot(
        world,
        Y_plan,
        np.asarray(nominal.arm.view_bench, float),
        cfg,  # a HandEyeProcedureConfig; the twin's fields are not the procedure's business
        wait=world.step,
        log=truth.log,
        on_view=truth,
    )


def write_hand_eye(
    out: Path,
    cfg: HandEyeProcedureConfig,
    proc: HandEyeProcedureResult,
    summary: dict[str, Any],
    robot: RobotDescription | None = None,
    robot_file: Path | None = None,
) -> None:
    """``summary.json``, ``hand_eye.yaml``, ``robot.yaml`` (its path joins ``summary``, after
    the JSON is written) and, for ``joint``, ``calibration.conf``; ``robot`` and
    ``robot_file``: a hardware robot's description and robot file (its frames and backend
    kept, :func:`~mmpa.apps.calibrate.files.write_robot_file`)."""
    out.mkdir(parents=True, exist_ok=True)
    write_summary(out, summary)
    joint = proc.joint
    (out / "hand_eye.yaml").write_text(
        hand_eye_yaml(
            proc.T_flange_camera, proc.method, dh=joint.dh if cfg.method == "joint" else None
        )
    )
    path = write_robot_file(
        proc.T_flange_camera, out / "robot.yaml", dh=proc.dh, robot=robot, robot_file=robot_file
    )
    summary["robot_file"] = str(path)
    if cfg.method == "joint":
        (out / "calibration.conf").write_text(ur_calibration_conf(joint.deltas))


def _run(
    world: SimWorld,
    cfg: HandEyeConfig,
    placement: BoardPlacement,
    out: Path | None,
    log: Callable[[str], None],
    t0: float,
) -> dict[str, Any]:
    truth = TruthRecorder(world, T_map_board_truth(world, cfg.board), log)
    proc = _calibrate(world, cfg, placement, truth)
    fk_eval = (cfg.fk_eval_configurations, cfg.seed)
    summary = hand_eye_summary(world, cfg, cfg.site, fk_eval, proc, truth, t0)
    if out is not None:
        write_hand_eye(Path(out), cfg, proc, summary)
    return summary
