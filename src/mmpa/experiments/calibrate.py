"""``mmpa calibrate hand-eye`` in the twin: a ChArUco board in front of a site, the arm
visits planned stations, the wrist camera measures the board, ``cv2.calibrateHandEye``
with every method, the best by residuals; evaluated against the TRUE hand-eye.

Procedure (only NOMINAL knowledge is used to calibrate):

1. a first view of the board from where the board is meant to stand (the placement in the
   site's park frame, the nominal arm mount, nominal IK): detect it and estimate the board
   pose in the arm base ``Y0 = fk(q) X_nominal C`` (nominal kinematics and hand-eye);
2. plan ``stations`` views around ``Y0`` (:func:`mmpa.calibration.hand_eye.plan_stations`);
3. at each: ``arm.move_joints``, read the encoders ``q_i``, capture a frame, detect the board
   and solve PnP (``C_i``); ``G_i = fk(nominal dh, q_i)``;
4. solve with every method, pick the smallest board-corner spread.

Evaluation (ground truth, never used above): the picked ``X`` against the TRUE robot's
``T_flange_camera``, each method's error, the PnP error per station against the true board
pose, and a diagnostic solve with the TRUE flange poses in map (no kinematic or mount
error: what the camera measurements alone allow).

Outputs in ``out``: ``summary.json`` (``error_trans_mm``, ``error_rot_deg``, the method
table, residuals, stations) and ``hand_eye.yaml`` (the estimate: 4x4 and the robot file's
``camera.T_flange_camera_vec``).
"""

from __future__ import annotations

import json
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import yaml
from pydantic import BaseModel, ConfigDict, Field

from mmpa.calibration.charuco import BoardNotFoundError, board_pose
from mmpa.calibration.hand_eye import (
    calibrate_hand_eye,
    pair_motion_stats,
    plan_stations,
    pose_error,
)
from mmpa.errors import MMPAError
from mmpa.geometry import Array, T_to_vec6, inv
from mmpa.robot.description import DHParameters
from mmpa.sim.calibration_board import BoardPlacement, CharucoBoardSpec, T_map_board_truth
from mmpa.sim.error_model import ErrorModelConfig, ProfileName

__all__ = [
    "HandEyeConfig",
    "hand_eye_yaml",
    "last_link_error",
    "run_hand_eye",
    "run_lidar_mount",
    "write_robot_file",
]


class HandEyeConfig(BaseModel):
    """The run: ``site``, ``stations`` views, the twin's error ``profile`` and ``seed`` (the
    robot instance), the board and where it stands, frames averaged per station."""

    model_config = ConfigDict(extra="forbid")

    site: str = "0"
    stations: int = Field(15, ge=3, le=100)
    seed: int = Field(0, ge=0)
    profile: ProfileName = "realistic"
    board: CharucoBoardSpec = CharucoBoardSpec()
    placement: BoardPlacement | None = None  # None: BoardPlacement.for_site(scene, site)
    min_corners: int = Field(12, ge=4)
    settle_s: float = Field(0.5, ge=0)


def hand_eye_yaml(
    X: Array, method: str, frames: tuple[str, str] = ("flange", "camera_optical")
) -> str:
    """``hand_eye.yaml``: the estimate as a 4x4 (m) with its frames, and the robot file's
    ``camera: {T_flange_camera_vec: [...]}`` section (paste or merge into a robot file)."""
    X = np.asarray(X, float)
    doc = {
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
    return yaml.safe_dump(doc, sort_keys=False, default_flow_style=None, width=120)


def last_link_error(dh_nominal: DHParameters, dh_true: DHParameters) -> Array:
    """``E6 = A6_nom(q6)^-1 A6_true(q6)`` (4, 4): the true last DH link seen from the nominal
    one. With ``A = Rz(q + theta) Tz(d) Tx(a) Rx(alpha)`` the ``Rz(q)`` factors cancel, so
    ``E6`` does not depend on ``q6`` (evaluated at 0). It is a constant factor on the flange
    side of ``fk``, so it cannot be separated from the hand-eye by any data taken with the
    nominal model (evaluation only: it needs the true DH)."""
    from mmpa.robot.kinematics import link_transforms

    F_nom = link_transforms(dh_nominal, np.zeros(6))
    F_true = link_transforms(dh_true, np.zeros(6))
    return inv(inv(F_nom[5]) @ F_nom[6]) @ (inv(F_true[5]) @ F_true[6])


def _log_default(msg: str) -> None:
    print(msg, flush=True)


def run_hand_eye(
    cfg: HandEyeConfig,
    out: Path | None = None,
    log: Callable[[str], None] | None = None,
    errors: ErrorModelConfig | None = None,
) -> dict[str, Any]:
    """Run the calibration in the twin (module docstring); returns the summary (also written
    to ``out/summary.json`` with ``out/hand_eye.yaml`` when ``out`` is given). ``errors``
    replaces the error model of ``cfg.profile`` / ``cfg.seed`` (studies of one source)."""
    from mmpa.sim.calibration_board import board_world

    log = log or _log_default
    t0 = time.perf_counter()
    if errors is None:
        errors = ErrorModelConfig.from_profile(cfg.profile, seed=cfg.seed)
    from mmpa.sim.scene import load_scene

    scene = load_scene()
    placement = cfg.placement or BoardPlacement.for_site(scene, cfg.site)
    world = board_world(cfg.site, cfg.board, placement, errors=errors, scene=scene)
    try:
        return _run(world, cfg, placement, out, log, t0)
    finally:
        world.close()


def _run(
    world: Any,
    cfg: HandEyeConfig,
    placement: BoardPlacement,
    out: Path | None,
    log: Callable[[str], None],
    t0: float,
) -> dict[str, Any]:
    from mmpa.robot.kinematics import fk

    nominal = world.nominal
    dh = nominal.arm.dh
    X_nom = nominal.camera.T_flange_camera
    X_true = world.true_robot.camera.T_flange_camera
    q_lim = nominal.arm.q_limits
    spec = cfg.board
    board = spec.cv_board()
    corners = spec.corners()
    K = world.camera.intrinsics.K
    size = (world.camera.intrinsics.width, world.camera.intrinsics.height)

    # 1. first view, planned from where the board is meant to stand (nominal)
    T_armbase_park = inv(nominal.T_base_link_arm_base)
    Y_plan = T_armbase_park @ placement.T_park_geom(spec) @ spec.T_geom_board
    q_ref = np.asarray(nominal.arm.view_bench, float)
    first = plan_stations(
        dh,
        q_lim,
        Y_plan,
        X_nom,
        corners,
        K,
        size,
        3,
        q_ref,
        tilts_deg=(0.0, 10.0),
        rolls_deg=(0.0,),
        max_joint_step=2 * np.pi,
    )[0]
    world.arm.move_joints(first.q, settle=cfg.settle_s)
    q0 = world.arm.joint_positions()
    pose0 = board_pose(world.camera.capture().color, board, K, cfg.min_corners)
    Y0 = fk(dh, q0) @ X_nom @ pose0.T_camera_board
    log(f"board found: {pose0.n_corners} corners, {pose0.rms_px:.3f} px RMS")

    # 2. stations around the measured board
    stations = plan_stations(dh, q_lim, Y0, X_nom, corners, K, size, cfg.stations, q0)

    # 3. visit them
    G, C, G_true_map, G_true_ab, rows = [], [], [], [], []
    T_map_board = T_map_board_truth(world, spec)
    for i, st in enumerate(stations):
        world.arm.move_joints(st.q, settle=cfg.settle_s)
        q = world.arm.joint_positions()
        frame = world.camera.capture()
        try:
            pose = board_pose(frame.color, board, K, cfg.min_corners)
        except BoardNotFoundError as e:
            log(f"station {i}: skipped ({e})")
            rows.append({"station": i, "used": False, "reason": str(e)})
            continue
        C_true = inv(world.truth.T_map_camera()) @ T_map_board
        pnp_t, pnp_r = pose_error(pose.T_camera_board, C_true)
        G.append(fk(dh, q))
        C.append(pose.T_camera_board)
        G_true_map.append(world.truth.T_map_flange())
        G_true_ab.append(inv(world.truth.T_map_arm_base()) @ G_true_map[-1])
        rows.append(
            {
                "station": i,
                "used": True,
                "tilt_deg": st.tilt_deg,
                "azimuth_deg": st.azimuth_deg,
                "roll_deg": st.roll_deg,
                "distance_m": st.distance,
                "corners": pose.n_corners,
                "reproj_rms_px": pose.rms_px,
                "pnp_error_trans_mm": pnp_t,
                "pnp_error_rot_deg": pnp_r,
                "q": [float(v) for v in q],
            }
        )
        log(
            f"station {i}: {pose.n_corners} corners, {pose.rms_px:.3f} px, PnP error "
            f"{pnp_t:.2f} mm {pnp_r:.3f} deg"
        )
    if len(G) < 3:
        raise MMPAError(f"only {len(G)} stations saw the board; need at least 3")
    G, C, G_true_map = np.array(G), np.array(C), np.array(G_true_map)

    # 4. solve, compare, pick
    res = calibrate_hand_eye(G, C, corners)
    table = {}
    for name, r in res.methods.items():
        et, er = pose_error(r.T_flange_camera, X_true)
        table[name] = {
            "error_trans_mm": et,
            "error_rot_deg": er,
            **r.consistency.as_dict(),
            "axxb_trans_mm": r.axxb_trans_mm,
            "axxb_rot_deg": r.axxb_rot_deg,
        }
    X = res.T_flange_camera
    err_t, err_r = pose_error(X, X_true)
    nom_t, nom_r = pose_error(X_nom, X_true)
    # diagnostic: the TRUE flange poses in map (no DH, mount or base error)
    diag = calibrate_hand_eye(G_true_map, C, corners)
    dt, dr = pose_error(diag.T_flange_camera, X_true)
    # how far nominal kinematics are from the truth at the stations (flange in arm base)
    fk_err = [pose_error(g, gt) for g, gt in zip(G, G_true_ab, strict=True)]
    # the last link's DH error is a constant flange-side factor E6 (fk_true = fk_nom E6 when
    # only link 6 differs): no camera data can tell E6 X from X, so with nominal kinematics
    # every method can at best find X_eff = E6 X_true
    E6 = last_link_error(dh, world.true_robot.arm.dh)
    eff_t, eff_r = pose_error(X, E6 @ X_true)
    e6_t, e6_r = pose_error(E6, np.eye(4))
    summary: dict[str, Any] = {
        "site": cfg.site,
        "profile": world.error_model.config.profile,
        "seed": world.error_model.config.seed,
        "stations_planned": len(stations),
        "stations_used": len(G),
        "method": res.best,
        "error_trans_mm": err_t,
        "error_rot_deg": err_r,
        "target": {"trans_mm": 0.5, "rot_deg": 0.1},
        "within_target": bool(err_t <= 0.5 and err_r <= 0.1),
        "nominal_error_trans_mm": nom_t,
        "nominal_error_rot_deg": nom_r,
        "residuals": {
            **res.methods[res.best].consistency.as_dict(),
            "axxb_trans_mm": res.methods[res.best].axxb_trans_mm,
            "axxb_rot_deg": res.methods[res.best].axxb_rot_deg,
        },
        "methods": table,
        "failed_methods": res.failed,
        "pose_selection": pair_motion_stats(G),
        "diagnostic": {
            "true_flange_poses": {
                "method": diag.best,
                "error_trans_mm": dt,
                "error_rot_deg": dr,
            },
            "last_link_dh_error_trans_mm": e6_t,
            "last_link_dh_error_rot_deg": e6_r,
            "error_vs_effective_trans_mm": eff_t,
            "error_vs_effective_rot_deg": eff_r,
            "nominal_fk_error_trans_mm_max": float(max(e[0] for e in fk_err)),
            "nominal_fk_error_rot_deg_max": float(max(e[1] for e in fk_err)),
            "pnp_error_trans_mm_rms": float(
                np.sqrt(np.mean([r["pnp_error_trans_mm"] ** 2 for r in rows if r["used"]]))
            ),
            "pnp_error_rot_deg_rms": float(
                np.sqrt(np.mean([r["pnp_error_rot_deg"] ** 2 for r in rows if r["used"]]))
            ),
        },
        "T_flange_camera": [[float(v) for v in row] for row in X],
        "T_flange_camera_true": [[float(v) for v in row] for row in X_true],
        "stations": rows,
        "wall_s": time.perf_counter() - t0,
    }
    if out is not None:
        out = Path(out)
        out.mkdir(parents=True, exist_ok=True)
        (out / "summary.json").write_text(json.dumps(summary, indent=2) + "\n")
        (out / "hand_eye.yaml").write_text(hand_eye_yaml(X, res.best))
        summary["robot_file"] = str(write_robot_file(X, out / "robot.yaml"))
    return summary


def write_robot_file(T_flange_camera: Array, path: str | Path) -> Path:
    """The robot in use (``mmpa --robot FILE``, else the twin's) with the calibrated
    ``camera.T_flange_camera``, written as a robot file: the next run takes it with
    ``mmpa --robot PATH``."""
    from mmpa.geometry import T_to_vec6
    from mmpa.robot.description import default_robot
    from mmpa.robot.robot_file import save_robot

    robot = default_robot()
    vec = tuple(float(v) for v in T_to_vec6(T_flange_camera))
    camera = robot.camera.model_copy(update={"T_flange_camera_vec": vec})
    return save_robot(robot.with_updates(camera=camera.model_dump()), path)


def run_lidar_mount(
    site: str = "0",
    seed: int = 0,
    profile: ProfileName = "realistic",
    out: str | Path | None = None,
) -> dict[str, Any]:
    """Calibrate the lidar mount in the twin: the robot instance ``seed`` turns once on the
    spot at ``site`` and fits its mount translation from its odometry and scans against the
    map (:func:`mmpa.navigation.mount_calibration.calibrate_lidar_mount`, from the operator's
    rough pose); compared with the TRUE mount. With ``out``: ``summary.json`` and a
    ``robot.yaml`` with the calibrated ``lidar.T_base_link_laser_vec`` (the nominal height,
    roll, pitch and yaw kept: a turn on the spot observes the translation only)."""
    from mmpa.geometry import T_to_se2
    from mmpa.navigation.mount_calibration import calibrate_lidar_mount
    from mmpa.robot.description import default_robot
    from mmpa.robot.robot_file import save_robot
    from mmpa.sim.operator import rough_initial_pose
    from mmpa.sim.twin_maps import laser_pose2d, twin_map
    from mmpa.sim.world import SimWorld

    t0 = time.perf_counter()
    errors = ErrorModelConfig.from_profile(profile, seed=seed)
    with SimWorld(errors=errors, site=site) as w:
        grid = twin_map(w)
        nominal = laser_pose2d(w)
        true = T_to_se2(w.true_robot.lidar.T_base_link_laser)
        guess = rough_initial_pose(w, np.random.default_rng([seed, 1]))
        cal = calibrate_lidar_mount(w, grid, nominal, guess, rng=np.random.default_rng([seed, 2]))
    if cal.mount is None:
        raise MMPAError(
            f"the lidar mount fit was not trusted (circle fit RMS {1e3 * cal.fit.rms:.1f} mm): "
            "turn where the map is rich in walls, or check the map"
        )
    summary: dict[str, Any] = {
        "profile": profile,
        "seed": seed,
        "site": site,
        "mount": [float(v) for v in cal.mount],
        "mount_nominal": [float(v) for v in nominal],
        "mount_true": [float(v) for v in true],
        "error_mm": float(1e3 * np.hypot(*(cal.mount[:2] - true[:2]))),
        "nominal_error_mm": float(1e3 * np.hypot(*(nominal[:2] - true[:2]))),
        "fit_rms_mm": float(1e3 * cal.fit.rms),
        "scans": len(cal.poses),
        "wall_s": time.perf_counter() - t0,
    }
    if out is not None:
        out = Path(out)
        out.mkdir(parents=True, exist_ok=True)
        robot = default_robot()
        vec = list(robot.lidar.T_base_link_laser_vec)
        vec[0], vec[1] = float(cal.mount[0]), float(cal.mount[1])
        lidar = robot.lidar.model_copy(update={"T_base_link_laser_vec": tuple(vec)})
        path = save_robot(robot.with_updates(lidar=lidar.model_dump()), out / "robot.yaml")
        summary["robot_file"] = str(path)
        (out / "summary.json").write_text(json.dumps(summary, indent=2) + "\n")
    return summary
