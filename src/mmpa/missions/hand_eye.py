"""The hand-eye calibration procedure over the robot interfaces: any :class:`~mmpa.robot.
interfaces.Arm` and :class:`~mmpa.robot.interfaces.Camera` (the twin's, a UR over RTDE with a
RealSense, a fake of your own), nothing of a simulator and no truth.

Steps (:func:`calibrate_hand_eye_on_robot`; only the robot's NOMINAL model is known):

1. a first view of the board planned from a rough guess of where it stands in the arm base
   frame (``T_armbase_board_guess``: a tape measure will do, views keep the whole board in
   the image), near ``q_ref``: move there, detect the board, and estimate its pose
   ``Y0 = fk(q) X_nominal C``; without a guess (a real robot whose camera the user pointed
   at the board), the first view is where the arm stands: nothing moves in this step;
2. plan ``stations`` views around ``Y0`` (:func:`mmpa.calibration.hand_eye.plan_stations`:
   four distances, tilts, rolls) near the first view's configuration; ``confirm(stations)``
   (a hardware backend asks its user) may decline them: :class:`NotConfirmedError`, the arm
   has not moved since step 1;
3. at each: ``arm.move_joints``, wait ``settle_s``, read the encoders ``q_i``, capture, detect
   the board and solve PnP (``C_i``); ``G_i = fk(nominal dh, q_i)``; a view without the
   board is skipped (and reported);
4. OpenCV's five ``calibrateHandEye`` methods, the one with the smallest board-corner spread
   picked (:func:`mmpa.calibration.hand_eye.calibrate_hand_eye`);
5. from it, the joint MAP fit of the DH corrections, the hand-eye, the board pose and a small
   arm-base displacement per view over the board corners
   (:func:`mmpa.calibration.kinematic.calibrate_kinematics_hand_eye`), with the corner noise
   the views' pooled PnP reprojection RMS.

``method`` picks the result (``joint``: the hand-eye with the calibrated DH it belongs to;
``opencv``: step 4's with the nominal DH). The last DH link's error cannot be told from the
hand-eye by any flange-mounted sensor (:mod:`mmpa.calibration.kinematic`), so either is the
hand-eye on the model's flange. Units: m, rad, px.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any, Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field

from mmpa.calibration.charuco import (
    BoardNotFoundError,
    CharucoBoardSpec,
    CharucoPose,
    board_pose,
)
from mmpa.calibration.hand_eye import (
    HandEyeResult,
    Station,
    board_consistency,
    calibrate_hand_eye,
    plan_stations,
)
from mmpa.calibration.kinematic import (
    BoardObservations,
    JointCalibrationConfig,
    JointCalibrationResult,
    calibrate_kinematics_hand_eye,
)
from mmpa.core.errors import InvalidInputError, MMPAError
from mmpa.core.geometry import Array
from mmpa.robot.description import DHParameters, RobotDescription
from mmpa.robot.interfaces import Arm, Camera, MobileManipulator, require
from mmpa.robot.kinematics import fk

__all__ = [
    "HandEyeProcedureConfig",
    "HandEyeProcedureResult",
    "NotConfirmedError",
    "calibrate_hand_eye_on_robot",
]


class NotConfirmedError(MMPAError):
    """The user declined the planned views: the arm did not move toward them."""


class HandEyeProcedureConfig(BaseModel):
    """The procedure's settings (module docstring): ``stations`` views of ``board``, each
    needing ``min_corners`` detected corners, ``settle_s`` of waiting after each move; the
    ``method`` written out; the joint fit's priors (``joint``; the corner noise
    ``pixel_sigma``, px, is the views' pooled PnP reprojection RMS unless given); the view
    grid: camera ``distances`` (m) from the board centre, cone ``tilts_deg`` from its normal,
    ``rolls_deg`` about the optical axis."""

    model_config = ConfigDict(extra="forbid")

    stations: int = Field(40, ge=3, le=100)
    board: CharucoBoardSpec = CharucoBoardSpec()
    min_corners: int = Field(12, ge=4)
    settle_s: float = Field(0.5, ge=0)
    # joint by default (docs/calibration.md "Hand-eye: the procedure's defaults")
    method: Literal["joint", "opencv"] = "joint"
    # per-station arm-base displacement priors: 0.03 deg / 0.3 mm, the mount's tilt and the
    # chassis rocking about the floor contact (docs/calibration.md, the procedure's defaults)
    joint: JointCalibrationConfig = JointCalibrationConfig(
        station_rot_sigma_deg=0.03, station_shift_sigma_mm=0.3
    )
    pixel_sigma: float | None = Field(None, gt=0)
    # four distances from 0.32 to 0.62 m, tilts to 45 deg and rolls of +-60 deg: the views'
    # spread in reach and orientation separates the camera's depth axis from the arm's
    # lengths a2, a3 and the board's place (docs/calibration.md, the procedure's defaults)
    distances: tuple[float, ...] = (0.32, 0.42, 0.52, 0.62)
    tilts_deg: tuple[float, ...] = (0.0, 15.0, 30.0, 45.0)
    rolls_deg: tuple[float, ...] = (-60.0, 0.0, 60.0)


@dataclass(frozen=True)
class HandEyeProcedureResult:
    """The calibration: ``T_flange_camera`` (4, 4) of ``method`` (``joint``, or the picked
    OpenCV method's name) with the kinematics ``dh`` it belongs to; every OpenCV method
    (``opencv``), the joint fit (``joint``) and its corner noise ``pixel_sigma`` (px); per
    planned view a row (``stations``: used or why not, PnP figures, ``q``); the used views'
    encoder readings ``q`` (N, 6) rad, nominal flange poses ``G`` (N, 4, 4) and board poses
    in the camera ``C`` (N, 4, 4); ``first_view`` (corners, RMS px); ``joint_s`` the joint
    fit's compute time (s)."""

    T_flange_camera: Array
    dh: DHParameters
    method: str
    opencv: HandEyeResult
    joint: JointCalibrationResult
    pixel_sigma: float
    stations: list[dict[str, Any]]
    q: Array
    G: Array
    C: Array
    first_view: dict[str, float]
    joint_s: float


def _capture_board(camera: Camera, cfg: HandEyeProcedureConfig) -> CharucoPose:
    K = camera.intrinsics.K
    return board_pose(camera.capture().color, cfg.board.cv_board(), K, cfg.min_corners)


def _check_inputs(T_armbase_board_guess: Array, q_ref: Array) -> tuple[Array, Array]:
    """The board pose guess (4, 4) and ``q_ref`` (6,) as float arrays, checked."""
    guess = np.asarray(T_armbase_board_guess, float)
    if guess.shape != (4, 4) or not np.isfinite(guess).all():
        raise InvalidInputError(
            f"the board pose guess must be a finite 4x4 transform, got shape {guess.shape}"
        )
    R = guess[:3, :3]
    if not np.allclose(R @ R.T, np.eye(3), atol=1e-6) or np.linalg.det(R) < 0:
        raise InvalidInputError("the board pose guess's rotation is not a rotation matrix")
    q_ref = np.asarray(q_ref, float)
    if q_ref.shape != (6,) or not np.isfinite(q_ref).all():
        raise InvalidInputError(f"q_ref must be 6 finite joint angles (rad), got {q_ref!r}")
    return guess, q_ref


def _camera_geometry(camera: Camera) -> tuple[Array, tuple[int, int]]:
    intr = camera.intrinsics
    return intr.K, (intr.width, intr.height)


def _first_view(
    arm: Arm,
    camera: Camera,
    robot: RobotDescription,
    guess: Array,
    q_ref: Array,
    cfg: HandEyeProcedureConfig,
    wait: Callable[[float], None],
    log: Callable[[str], None],
) -> tuple[Array, CharucoPose, Array]:
    """Step 1: a view planned from the guess; returns the encoder reading ``q0`` (6,) rad,
    the board seen there and its pose ``Y0 = fk(q0) X_nominal C`` (4, 4) in the arm base."""
    dh, X_nom = robot.arm.dh, robot.camera.T_flange_camera
    K, size = _camera_geometry(camera)
    first = plan_stations(
        dh,
        robot.arm.q_limits,
        guess,
        X_nom,
        cfg.board.corners(),
        K,
        size,
        3,
        q_ref,
        tilts_deg=(0.0, 10.0),
        rolls_deg=(0.0,),
        max_joint_step=2 * np.pi,
    )[0]
    arm.move_joints(first.q)
    wait(cfg.settle_s)
    q0 = arm.joint_positions()
    pose0 = _capture_board(camera, cfg)
    Y0 = fk(dh, q0) @ X_nom @ pose0.T_camera_board
    log(f"board found: {pose0.n_corners} corners, {pose0.rms_px:.3f} px RMS")
    return q0, pose0, Y0


def _board_in_view(
    arm: Arm,
    camera: Camera,
    robot: RobotDescription,
    cfg: HandEyeProcedureConfig,
    log: Callable[[str], None],
) -> tuple[Array, CharucoPose, Array]:
    """Step 1 without a move: the board seen from where the arm stands; returns the encoder
    reading ``q0`` (6,) rad, the board seen and its pose ``Y0 = fk(q0) X_nominal C`` (4, 4)
    in the arm base. Raises :class:`~mmpa.calibration.charuco.BoardNotFoundError` when the
    camera does not see it."""
    q0 = np.asarray(arm.joint_positions(), float)
    pose0 = _capture_board(camera, cfg)
    Y0 = fk(robot.arm.dh, q0) @ robot.camera.T_flange_camera @ pose0.T_camera_board
    log(f"board in view: {pose0.n_corners} corners, {pose0.rms_px:.3f} px RMS")
    return q0, pose0, Y0


@dataclass
class _Views:
    """Step 3's harvest: per planned view a row (``rows``), per used view the encoder
    reading, the nominal flange pose, the board pose in the camera, the corners' board
    points and pixels and the PnP reprojection RMS (px)."""

    rows: list[dict[str, Any]] = field(default_factory=list)
    qs: list[Array] = field(default_factory=list)
    G: list[Array] = field(default_factory=list)
    C: list[Array] = field(default_factory=list)
    P: list[Array] = field(default_factory=list)
    uv: list[Array] = field(default_factory=list)
    rms: list[float] = field(default_factory=list)

    def add(self, i: int, st: Station, q: Array, G: Array, pose: CharucoPose) -> dict[str, Any]:
        """A used view ``i`` at station ``st``; returns its row (appended by the caller)."""
        self.qs.append(q)
        self.G.append(G)
        self.C.append(pose.T_camera_board)
        self.P.append(pose.detection.object_points)
        self.uv.append(pose.detection.image_points)
        self.rms.append(pose.rms_px)
        return {
            "station": i,
            "used": True,
            "tilt_deg": st.tilt_deg,
            "azimuth_deg": st.azimuth_deg,
            "roll_deg": st.roll_deg,
            "distance_m": st.distance,
            "corners": pose.n_corners,
            "reproj_rms_px": pose.rms_px,
        }


def _visit(
    arm: Arm,
    camera: Camera,
    dh: DHParameters,
    stations: list[Station],
    cfg: HandEyeProcedureConfig,
    wait: Callable[[float], None],
    log: Callable[[str], None],
    on_view: Callable[[int, CharucoPose], dict[str, Any]] | None,
) -> _Views:
    """Step 3: move to each station, settle, read the encoders, capture and detect the board
    (a view without it is skipped and reported)."""
    views = _Views()
    for i, st in enumerate(stations):
        arm.move_joints(st.q)
        wait(cfg.settle_s)
        q = arm.joint_positions()
        try:
            pose = _capture_board(camera, cfg)
        except BoardNotFoundError as e:
            log(f"station {i}: skipped ({e})")
            views.rows.append({"station": i, "used": False, "reason": str(e)})
            continue
        row = views.add(i, st, q, fk(dh, q), pose)
        if on_view is not None:
            row.update(on_view(i, pose))
        row["q"] = [float(v) for v in q]
        views.rows.append(row)
        log(f"station {i}: {pose.n_corners} corners, {pose.rms_px:.3f} px")
    if len(views.G) < 3:
        raise MMPAError(f"only {len(views.G)} stations saw the board; need at least 3")
    return views


def _fit(
    dh: DHParameters,
    views: _Views,
    K: Array,
    cfg: HandEyeProcedureConfig,
    log: Callable[[str], None],
) -> tuple[HandEyeResult, JointCalibrationResult, float, float]:
    """Steps 4 and 5: OpenCV's five methods (the best by residuals), then the joint
    kinematic + hand-eye fit from the best; returns both, the corner noise (px) and the
    joint fit's compute time (s)."""
    corners = cfg.board.corners()
    G_a, C_a = np.array(views.G), np.array(views.C)
    res = calibrate_hand_eye(G_a, C_a, corners)
    obs = BoardObservations.from_lists(views.qs, views.P, views.uv)
    pix = cfg.pixel_sigma or max(float(np.sqrt(np.mean(np.square(views.rms)))), 0.05)
    t = time.perf_counter()
    Y_cv = board_consistency(G_a, C_a, res.T_flange_camera, corners).T_base_board
    jcfg = cfg.joint.model_copy(update={"pixel_sigma": pix})
    joint = calibrate_kinematics_hand_eye(dh, obs, K, res.T_flange_camera, Y_cv, jcfg)
    joint_s = time.perf_counter() - t
    log(
        f"joint calibration: {joint.rms_px_start:.3f} -> {joint.rms_px:.3f} px RMS, "
        f"{joint.n_identified} DH directions identified, {joint_s:.1f} s"
    )
    return res, joint, pix, joint_s


def _plan(
    rd: RobotDescription,
    Y0: Array,
    q0: Array,
    K: Array,
    size: tuple[int, int],
    cfg: HandEyeProcedureConfig,
) -> list[Station]:
    """Step 2: ``cfg.stations`` views around the board pose ``Y0`` (4, 4, arm base) near the
    configuration ``q0`` (6,) rad."""
    return plan_stations(
        rd.arm.dh,
        rd.arm.q_limits,
        Y0,
        rd.camera.T_flange_camera,
        cfg.board.corners(),
        K,
        size,
        cfg.stations,
        q0,
        distances=cfg.distances,
        tilts_deg=cfg.tilts_deg,
        rolls_deg=cfg.rolls_deg,
    )


def calibrate_hand_eye_on_robot(
    robot: MobileManipulator,
    T_armbase_board_guess: Array | None,
    q_ref: Array | None,
    cfg: HandEyeProcedureConfig | None = None,
    *,
    wait: Callable[[float], None] | None = None,
    log: Callable[[str], None] | None = None,
    on_view: Callable[[int, CharucoPose], dict[str, Any]] | None = None,
    confirm: Callable[[list[Station]], bool] | None = None,
) -> HandEyeProcedureResult:
    """Calibrate the wrist camera of ``robot`` (its arm and camera; module docstring) from its
    nominal description, a rough board pose ``T_armbase_board_guess`` (4, 4) in the arm
    base frame and the configuration ``q_ref`` (6,) rad the views stay near (no wrist flip);
    ``T_armbase_board_guess`` None: the board is in view now, the first view is the arm's
    current configuration (``q_ref`` unused). ``confirm(stations)`` is asked before the arm
    moves to the planned views (None: no question).
    ``wait(s)`` lets the arm settle after each move (default ``robot.step``: the twin steps
    its physics, a :class:`~mmpa.robot.interfaces.WallClock` sleeps); ``on_view(i, pose)``
    is called after each detected view and its dict joins the view's row (an evaluation's
    ground truth; nothing here uses it).
    Raises :class:`~mmpa.core.errors.InvalidInputError` on a malformed guess or ``q_ref``,
    :class:`~mmpa.core.errors.UnreachableError` when the views cannot be planned,
    :class:`~mmpa.calibration.charuco.BoardNotFoundError` when the first view shows no
    board, :class:`NotConfirmedError` when ``confirm`` declines, and :class:`MMPAError`
    when fewer than 3 views saw it."""
    cfg = cfg or HandEyeProcedureConfig()
    log = log or (lambda m: None)
    if T_armbase_board_guess is not None:
        guess, q_ref = _check_inputs(T_armbase_board_guess, q_ref)
    require(robot, "arm", "camera", mission="the hand-eye calibration")
    arm, camera, rd = robot.arm, robot.camera, robot.description
    assert arm is not None and camera is not None
    wait = robot.step if wait is None else wait
    dh = rd.arm.dh
    K, size = _camera_geometry(camera)
    # 1. first view: planned from the guess, or where the arm stands
    if T_armbase_board_guess is None:
        q0, pose0, Y0 = _board_in_view(arm, camera, rd, cfg, log)
    else:
        q0, pose0, Y0 = _first_view(arm, camera, rd, guess, q_ref, cfg, wait, log)
    # 2. stations around the measured board
    stations = _plan(rd, Y0, q0, K, size, cfg)
    if confirm is not None and not confirm(stations):
        raise NotConfirmedError(f"the {len(stations)} planned views were declined; nothing moved")
    # 3. visit them; 4.-5. the fits
    views = _visit(arm, camera, dh, stations, cfg, wait, log, on_view)
    res, joint, pix, joint_s = _fit(dh, views, K, cfg, log)
    use_joint = cfg.method == "joint"
    return HandEyeProcedureResult(
        T_flange_camera=joint.T_flange_camera if use_joint else res.T_flange_camera,
        dh=joint.dh if use_joint else dh,
        method="joint" if use_joint else res.best,
        opencv=res,
        joint=joint,
        pixel_sigma=pix,
        stations=views.rows,
        q=np.array(views.qs),
        G=np.array(views.G),
        C=np.array(views.C),
        first_view={"corners": float(pose0.n_corners), "rms_px": float(pose0.rms_px)},
        joint_s=joint_s,
    )
