"""The hand-eye calibration against the twin's truth (evaluation only: nothing here feeds the
procedure). Per view the PnP error against the TRUE board pose and the true flange and arm
base poses (:class:`TruthRecorder`); after the fit every OpenCV method and the joint fit
against the TRUE hand-eye ``X_true`` and its identifiable part ``E6 X_true``
(:func:`last_link_error`), the kinematics against the TRUE arm over random configurations,
and a diagnostic solve with the TRUE flange poses in map (no kinematic or mount error: what
the camera measurements alone allow). Units of the summary: mm, deg.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from typing import Any

import numpy as np

from mmpa.backends.twin.world import SimWorld
from mmpa.calibration.charuco import CharucoPose
from mmpa.calibration.hand_eye import (
    HandEyeResult,
    calibrate_hand_eye,
    pair_motion_stats,
    pose_error,
)
from mmpa.calibration.kinematic import JointCalibrationResult, fk_point_error, random_configurations
from mmpa.core.geometry import Array, inv
from mmpa.missions.hand_eye import HandEyeProcedureConfig, HandEyeProcedureResult
from mmpa.robot.description import DHParameters, RobotDescription
from mmpa.robot.kinematics import link_transforms

__all__ = ["TruthRecorder", "hand_eye_summary", "last_link_error"]


def last_link_error(dh_nominal: DHParameters, dh_true: DHParameters) -> Array:
    """``E6 = A6_nom(q6)^-1 A6_true(q6)`` (4, 4): the true last DH link seen from the nominal
    one. With ``A = Rz(q + theta) Tz(d) Tx(a) Rx(alpha)`` the ``Rz(q)`` factors cancel, so
    ``E6`` does not depend on ``q6`` (evaluated at 0). It is a constant factor on the flange
    side of ``fk``, so it cannot be separated from the hand-eye by any data taken with the
    nominal model (evaluation only: it needs the true DH)."""

    F_nom = link_transforms(dh_nominal, np.zeros(6))
    F_true = link_transforms(dh_true, np.zeros(6))
    return inv(inv(F_nom[5]) @ F_nom[6]) @ (inv(F_true[5]) @ F_true[6])


class TruthRecorder:
    """The procedure's ``on_view`` hook in the twin: per detected view the PnP error against
    the TRUE board pose ``T_map_board`` (logged, joins the view's row) and the TRUE flange
    and arm base poses (``G_true_map``, ``T_ab``, ``G_true_ab``: flange in map, arm base in
    map, flange in arm base; the procedure never sees them)."""

    def __init__(self, world: SimWorld, T_map_board: Array, log: Callable[[str], None]) -> None:
        self.world = world
        self.T_map_board = T_map_board
        self.log = log
        self.G_true_map: list[Array] = []
        self.G_true_ab: list[Array] = []
        self.T_ab: list[Array] = []

    def __call__(self, i: int, pose: CharucoPose) -> dict[str, Any]:
        truth = self.world.truth
        C_true = inv(truth.T_map_camera()) @ self.T_map_board
        pnp_t, pnp_r = pose_error(pose.T_camera_board, C_true)
        self.G_true_map.append(truth.T_map_flange())
        self.T_ab.append(truth.T_map_arm_base())
        self.G_true_ab.append(inv(self.T_ab[-1]) @ self.G_true_map[-1])
        self.log(f"station {i}: PnP error {pnp_t:.2f} mm {pnp_r:.3f} deg (against the truth)")
        return {"pnp_error_trans_mm": pnp_t, "pnp_error_rot_deg": pnp_r}


def _method_errors(X: Array, X_true: Array, E6: Array) -> dict[str, float]:
    """A hand-eye estimate against the TRUE one and against the effective one ``E6 X_true``
    (the most any camera data can give with the nominal last link, :func:`last_link_error`)."""
    et, er = pose_error(X, X_true)
    ft, fr = pose_error(X, E6 @ X_true)
    return {
        "error_trans_mm": et,
        "error_rot_deg": er,
        "error_vs_effective_trans_mm": ft,
        "error_vs_effective_rot_deg": fr,
    }


def _true_deltas(dh: DHParameters, true_dh: DHParameters) -> dict[str, list[float]]:
    """The TRUE DH errors (true - nominal) in the units of the calibration summary (mm, deg)."""
    a, d, al, th = (t - n for t, n in zip(true_dh.as_arrays(), dh.as_arrays(), strict=True))
    return {
        "delta_theta": [float(v) for v in np.rad2deg(th)],
        "delta_a": [float(v) for v in a * 1e3],
        "delta_d": [float(v) for v in d * 1e3],
        "delta_alpha": [float(v) for v in np.rad2deg(al)],
    }


def _spread(Ts: list[Array]) -> list[float]:
    """The largest translation (mm) and rotation (deg) of the poses ``Ts`` from their first."""
    errs = [pose_error(T, Ts[0]) for T in Ts]
    return [float(max(e[0] for e in errs)), float(max(e[1] for e in errs))]


def _method_table(res: HandEyeResult, X_true: Array) -> dict[str, Any]:
    """Every OpenCV method against the truth, with its residuals."""
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
    return table


def _fk_evaluation(
    n: int,
    seed: int,
    nominal: RobotDescription,
    true: RobotDescription,
    proc: HandEyeProcedureResult,
) -> dict[str, Any]:
    """The nominal and calibrated kinematics against the TRUE arm over ``n`` random
    configurations (seeded by ``seed``): flange, tool point and camera."""
    dh, true_dh, joint = nominal.arm.dh, true.arm.dh, proc.joint
    qs = random_configurations(n, seed, *nominal.arm.q_limits)
    X_cv, X_dh = proc.opencv.T_flange_camera, joint.T_flange_camera
    X_true = true.camera.T_flange_camera
    tcp = nominal.gripper.T_flange_tcp
    tcp_true = true.gripper.T_flange_tcp
    return {
        "configurations": len(qs),
        "flange": {
            "nominal": fk_point_error(dh, true_dh, qs),
            "calibrated": fk_point_error(joint.dh, true_dh, qs),
        },
        "tcp": {
            "nominal": fk_point_error(dh, true_dh, qs, tcp, tcp_true),
            "calibrated": fk_point_error(joint.dh, true_dh, qs, tcp, tcp_true),
        },
        "camera": {
            "nominal_opencv": fk_point_error(dh, true_dh, qs, X_cv, X_true),
            "calibrated_joint": fk_point_error(joint.dh, true_dh, qs, X_dh, X_true),
        },
    }


def _diagnostic(
    proc: HandEyeProcedureResult,
    truth: TruthRecorder,
    X_true: Array,
    E6: Array,
    corners: Array,
) -> dict[str, Any]:
    """The solve with the TRUE flange poses in map (no DH, mount or base error), the last
    link's DH error, the true arm base's motion, the nominal kinematics' error at the
    stations (flange in arm base) and the PnP errors' RMS."""
    rows = proc.stations
    diag = calibrate_hand_eye(np.array(truth.G_true_map), proc.C, corners)
    dt, dr = pose_error(diag.T_flange_camera, X_true)
    fk_err = [pose_error(g, gt) for g, gt in zip(proc.G, truth.G_true_ab, strict=True)]
    # the last link's DH error is a constant flange-side factor E6 (fk_true = fk_nom E6 when
    # only link 6 differs): no camera data can tell E6 X from X, so with nominal kinematics
    # every method can at best find X_eff = E6 X_true
    eff_t, eff_r = pose_error(proc.T_flange_camera, E6 @ X_true)
    e6_t, e6_r = pose_error(E6, np.eye(4))
    return {
        "true_flange_poses": {
            "method": diag.best,
            "error_trans_mm": dt,
            "error_rot_deg": dr,
        },
        "last_link_dh_error_trans_mm": e6_t,
        "last_link_dh_error_rot_deg": e6_r,
        "error_vs_effective_trans_mm": eff_t,
        "error_vs_effective_rot_deg": eff_r,
        # the TRUE arm base's motion between stations (mount compliance, wheel settling)
        # against the first station's: what the per-station displacement priors stand for
        "arm_base_motion_mm_deg_max": _spread(truth.T_ab),
        "nominal_fk_error_trans_mm_max": float(max(e[0] for e in fk_err)),
        "nominal_fk_error_rot_deg_max": float(max(e[1] for e in fk_err)),
        "pnp_error_trans_mm_rms": float(
            np.sqrt(np.mean([r["pnp_error_trans_mm"] ** 2 for r in rows if r["used"]]))
        ),
        "pnp_error_rot_deg_rms": float(
            np.sqrt(np.mean([r["pnp_error_rot_deg"] ** 2 for r in rows if r["used"]]))
        ),
    }


def _kinematics(
    joint: JointCalibrationResult,
    pix: float,
    dh: DHParameters,
    true_dh: DHParameters,
    fk: dict[str, Any],
) -> dict[str, Any]:
    """The joint fit's summary, its corner noise (px), the TRUE DH errors and the FK errors."""
    return {
        **joint.summary(),
        "pixel_sigma": pix,
        "true_deltas": _true_deltas(dh, true_dh),
        "fk_error": fk,
    }


def hand_eye_summary(
    world: SimWorld,
    cfg: HandEyeProcedureConfig,
    site: str,
    fk_eval: tuple[int, int],
    proc: HandEyeProcedureResult,
    truth: TruthRecorder,
    t0: float,
) -> dict[str, Any]:
    """The summary of a calibration in the twin (module docstring; ``fk_eval``: the number of
    random configurations and their seed); ``wall_s`` since ``t0`` (``time.perf_counter``)."""
    nominal, true = world.nominal, world.true_robot
    X_nom, X_true = nominal.camera.T_flange_camera, true.camera.T_flange_camera
    res, joint, X = proc.opencv, proc.joint, proc.T_flange_camera
    E6 = last_link_error(nominal.arm.dh, true.arm.dh)
    by_method: dict[str, Any] = {
        "opencv": _method_errors(res.T_flange_camera, X_true, E6) | {"opencv_method": res.best},
        "joint": _method_errors(joint.T_flange_camera, X_true, E6) | {"solve_s": proc.joint_s},
    }
    fk = _fk_evaluation(fk_eval[0], fk_eval[1], nominal, true, proc)
    err_t, err_r = pose_error(X, X_true)
    nom_t, nom_r = pose_error(X_nom, X_true)
    diagnostic = _diagnostic(proc, truth, X_true, E6, cfg.board.corners())
    eff_t, eff_r = (
        diagnostic["error_vs_effective_trans_mm"],
        diagnostic["error_vs_effective_rot_deg"],
    )
    best = res.methods[res.best]
    return {
        "site": site,
        "profile": world.error_model.config.profile,
        "seed": world.error_model.config.seed,
        "stations_planned": len(proc.stations),
        "stations_used": len(proc.G),
        "method": proc.method,
        "opencv_method": res.best,
        "error_trans_mm": err_t,
        "error_rot_deg": err_r,
        # against E6 X_true: the hand-eye on the arm model's flange, all that flange-mounted
        # sensors can observe (the last DH link's error E6 is indistinguishable from it)
        "error_identifiable_trans_mm": eff_t,
        "error_identifiable_rot_deg": eff_r,
        "target": {"trans_mm": 0.5, "rot_deg": 0.1},
        "within_target": bool(err_t <= 0.5 and err_r <= 0.1),
        "within_target_identifiable": bool(eff_t <= 0.5 and eff_r <= 0.1),
        "nominal_error_trans_mm": nom_t,
        "nominal_error_rot_deg": nom_r,
        "residuals": {
            **best.consistency.as_dict(),
            "axxb_trans_mm": best.axxb_trans_mm,
            "axxb_rot_deg": best.axxb_rot_deg,
        },
        "by_method": by_method,
        "methods": _method_table(res, X_true),
        "failed_methods": res.failed,
        "pose_selection": pair_motion_stats(proc.G),
        "diagnostic": diagnostic,
        "kinematics": _kinematics(joint, proc.pixel_sigma, nominal.arm.dh, true.arm.dh, fk),
        "T_flange_camera": [[float(v) for v in row] for row in X],
        "T_flange_camera_true": [[float(v) for v in row] for row in X_true],
        "stations": proc.stations,
        "wall_s": time.perf_counter() - t0,
    }
