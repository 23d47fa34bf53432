"""``mmpa --robot R calibrate hand-eye`` on a hardware robot (a ``ros2`` or ``direct`` backend,
or any :class:`~mmpa.robot.interfaces.MobileManipulator`): no truth, no set-up.

The user prints the board (its geometry in :class:`~mmpa.missions.hand_eye.
HandEyeProcedureConfig` ``board``: squares, square and marker size, ArUco dictionary), fixes
it in front of the arm and points the wrist camera at it. The procedure
(:func:`mmpa.missions.hand_eye.calibrate_hand_eye_on_robot` without a board guess) detects
the board from where the arm stands (nothing moves), plans the views around it near the
current configuration, asks ``confirm`` (the views, the largest joint move from here, the
distances), then visits them and fits. The summary holds what the robot measured: the
residuals of every OpenCV method (board corner spread, AX = XB), the joint fit's reprojection
RMS before and after, the change from the nominal hand-eye, the views; the files are those of
the twin's run (``hand_eye.yaml``, ``robot.yaml`` keeping the robot file's frames and
backend, ``calibration.conf`` for ``joint``). Units: mm, deg, px in the summary.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from mmpa.apps.calibrate.files import log_default, write_summary
from mmpa.apps.calibrate.hand_eye import write_hand_eye
from mmpa.calibration.charuco import BoardNotFoundError
from mmpa.calibration.hand_eye import Station, pose_error
from mmpa.missions.hand_eye import (
    HandEyeProcedureConfig,
    HandEyeProcedureResult,
    NotConfirmedError,
    calibrate_hand_eye_on_robot,
)
from mmpa.robot.interfaces import MobileManipulator, require

__all__ = ["run_hand_eye_on_robot", "views_message"]


def views_message(stations: list[Station], q_now: np.ndarray) -> str:
    """What the user confirms: the number of planned views, the camera's distances from the
    board (m) and the largest joint move from ``q_now`` (6,) rad to any view (deg)."""
    q = np.array([s.q for s in stations], float).reshape(-1, 6)
    step = float(np.rad2deg(np.abs(q - np.asarray(q_now, float)).max())) if len(q) else 0.0
    d = [s.distance for s in stations] or [float("nan")]
    return (
        f"the arm will visit {len(stations)} views of the board, the camera "
        f"{min(d):.2f}-{max(d):.2f} m from it, joints up to {step:.0f} deg from where they are "
        "now; keep the workspace clear. Move the arm?"
    )


def _summary(
    proc: HandEyeProcedureResult, robot: MobileManipulator, kind: str, t0: float
) -> dict[str, Any]:
    """The calibration as the robot measured it (module docstring)."""
    res, joint = proc.opencv, proc.joint
    best = res.methods[res.best]
    X, X_nom = proc.T_flange_camera, robot.description.camera.T_flange_camera
    dt, dr = pose_error(X, X_nom)
    return {
        "backend": kind,
        "ok": True,
        "reason": "calibrated",
        "stations_planned": len(proc.stations),
        "stations_used": len(proc.G),
        "method": proc.method,
        "opencv_method": res.best,
        "residuals": {
            **best.consistency.as_dict(),
            "axxb_trans_mm": best.axxb_trans_mm,
            "axxb_rot_deg": best.axxb_rot_deg,
        },
        "methods": {
            name: {
                **r.consistency.as_dict(),
                "axxb_trans_mm": r.axxb_trans_mm,
                "axxb_rot_deg": r.axxb_rot_deg,
            }
            for name, r in res.methods.items()
        },
        "failed_methods": res.failed,
        "kinematics": {**joint.summary(), "pixel_sigma": proc.pixel_sigma},
        "first_view": proc.first_view,
        "change_from_nominal_trans_mm": dt,
        "change_from_nominal_rot_deg": dr,
        "T_flange_camera": [[float(v) for v in row] for row in X],
        "T_flange_camera_nominal": [[float(v) for v in row] for row in X_nom],
        "stations": proc.stations,
        "wall_s": time.perf_counter() - t0,
    }


def run_hand_eye_on_robot(
    robot: MobileManipulator,
    cfg: HandEyeProcedureConfig,
    out: Path | None = None,
    *,
    kind: str = "hardware",
    confirm: Callable[[str], bool] | None = None,
    log: Callable[[str], None] | None = None,
    robot_file: Path | None = None,
) -> dict[str, Any]:
    """Calibrate the hand-eye of ``robot`` from the board in its camera's view (module
    docstring); ``kind`` names the backend in the summary; ``confirm(message)`` is asked
    before the arm moves (None: no question); ``robot_file``: the robot file whose frames and
    backend ``out/robot.yaml`` keeps. Returns the summary (also ``out/summary.json``): ``ok``
    False with a ``reason`` when the board is not in view or the views were declined
    (nothing moved; only ``summary.json`` written)."""
    log = log or log_default
    t0 = time.perf_counter()
    require(robot, "arm", "camera", mission="the hand-eye calibration")
    assert robot.arm is not None
    q_now = np.asarray(robot.arm.joint_positions(), float)

    def ask(stations: list[Station]) -> bool:
        return confirm is None or confirm(views_message(stations, q_now))

    try:
        proc = calibrate_hand_eye_on_robot(robot, None, None, cfg, log=log, confirm=ask)
    except (BoardNotFoundError, NotConfirmedError) as e:
        summary = {"backend": kind, "ok": False, "reason": str(e), "moved": False}
        if out is not None:
            Path(out).mkdir(parents=True, exist_ok=True)
            write_summary(Path(out), summary)
        return summary
    summary = _summary(proc, robot, kind, t0)
    if out is not None:
        write_hand_eye(Path(out), cfg, proc, summary, robot.description, robot_file)
    return summary
