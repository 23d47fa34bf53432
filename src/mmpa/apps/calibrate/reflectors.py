"""``mmpa calibrate reflectors`` in the twin: the survey drive (set-up: the laser-only map and
localizer, the stations along the route, :func:`mmpa.missions.survey_drive.survey_drive`),
the fit (:func:`mmpa.calibration.reflector_survey.survey_reflectors`), the placement (the
poses' frame, or rigidly onto the site's existing reflector map), the evaluation against the
twin's TRUE reflector positions (never used by the drive or the fit) and the files.
Units: m in the files, mm / deg in the summary.
"""

from __future__ import annotations

import dataclasses
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any, Literal

import numpy as np
from pydantic import ConfigDict, Field

from mmpa.apps.calibrate.files import log_default, write_robot_file_reflectors, write_summary
from mmpa.backends.twin.error_model import ErrorModelConfig, ProfileName
from mmpa.backends.twin.operator import rough_initial_pose
from mmpa.backends.twin.twin_maps import laser_pose2d, twin_map, twin_nav_map
from mmpa.backends.twin.world import SimWorld
from mmpa.calibration.reflector_survey import (
    ReflectorSurvey,
    SurveyConfig,
    SurveyError,
    SurveyObservations,
    anchor_to,
    laser_origin_heading,
    match_reflectors,
    survey_reflectors,
)
from mmpa.core.errors import MMPAError
from mmpa.core.geometry import Array, T_to_se2
from mmpa.localization.localizer import make_localizer
from mmpa.maps.reflector_map import ReflectorMap, save_reflector_map
from mmpa.missions.navigate import localize_standing
from mmpa.missions.survey_drive import (
    SurveyDrive,
    SurveyDriveConfig,
    survey_drive,
    survey_stations,
)
from mmpa.navigation.planner import CostMap

__all__ = ["ReflectorSurveyConfig", "fit_survey", "map_match_priors", "run_reflector_survey"]


class ReflectorSurveyConfig(SurveyDriveConfig):
    """``mmpa calibrate reflectors``: the robot instance ``seed`` of ``profile`` starts at
    ``site`` and drives the ``route`` (sites, in order), stopping at survey stations every
    ``station_spacing`` m along the planned path (and at each site); at each it stands
    ``scans`` scans, localizing with the laser-only ``method`` (on the occupancy map with
    the reflectors taken out: never the reflectors being surveyed, never the truth) and
    detecting reflectors in the same scans (the drive's settings:
    :class:`~mmpa.missions.survey_drive.SurveyDriveConfig`; the detector's radius,
    unless set, is the scene's reflectors'). ``survey``: the fit
    (:class:`~mmpa.calibration.reflector_survey.SurveyConfig`). ``anchor``: ``poses`` keeps
    the surveyed layout where the laser-only pose estimates put it (the occupancy map's
    frame, warped as mapped); ``reflector_map`` moves it rigidly (3 DOF) onto the site's
    existing reflector map (the twin's marked one), whose independent marking errors
    average over the reflectors; the layout itself stays the survey's."""

    model_config = ConfigDict(extra="forbid")

    site: str = "0"
    route: tuple[str, ...] = ("1", "2", "0")
    station_spacing: float = Field(1.0, gt=0)  # m along the path; inf: the sites only
    initial_scans: int = Field(30, ge=1)  # standing scans from the operator's rough pose
    method: str = "hector"  # laser-only localizer: hector | amcl
    map_resolution: float = Field(0.05, gt=0)  # m per cell of the occupancy map localized on
    # shift (m, both axes) of the map grid's origin: the twin's walls lie on 5 cm cell edges,
    # which hides most of the map's warp from a sub-cell matcher; 0.0137 puts them mid-cell
    # as in a map of a real building (a study of the twin, not of the method)
    map_grid_shift: float = 0.0
    # where the surveyed layout is placed: the frame of the laser-only pose estimates, or
    # rigidly onto the site's existing reflector map (its marked positions as control points)
    anchor: Literal["poses", "reflector_map"] = "poses"
    seed: int = Field(0, ge=0)
    profile: ProfileName = "realistic"
    survey: SurveyConfig = SurveyConfig()


@dataclasses.dataclass(frozen=True)
class _TwinSurvey:
    """The drive and what the evaluation needs of the twin: the nominal laser mount ``lp``
    and the TRUE one ``lp_true`` (``[x, y, yaw]``), the TRUE reflectors ``p_true`` (N, 2),
    the marked reflector map ``p_marked``, the map warp at the true reflectors, the error
    model's ``profile`` and ``seed`` and the reflectors' ``radius`` (m)."""

    drive: SurveyDrive
    lp: Array
    lp_true: Array
    p_true: Array
    p_marked: Array
    warp: Array
    profile: str
    seed: int
    radius: float


def _drive(
    cfg: ReflectorSurveyConfig, errors: ErrorModelConfig, log: Callable[[str], None]
) -> _TwinSurvey:
    """Set-up and drive: the laser-only map (the occupancy grid without its reflector
    landmarks) and localizer from the operator's rough pose, the stations along the route,
    the survey drive."""
    with SimWorld(errors=errors, site=cfg.site) as w:
        grid = dataclasses.replace(
            twin_map(w, cfg.map_resolution, margin=0.5 + cfg.map_grid_shift),
            reflectors=np.zeros((0, 2)),
        )
        lp = laser_pose2d(w)
        radius = float(w.scene.reflectors.radius)
        det_cfg = cfg.detection
        if "radius" not in det_cfg.model_fields_set:
            det_cfg = det_cfg.model_copy(update={"radius": radius})
        loc = make_localizer(cfg.method, grid, lp, np.random.default_rng([cfg.seed, 3]))
        loc.initialize(rough_initial_pose(w, np.random.default_rng([cfg.seed, 1])))
        localize_standing(w, loc, scans=cfg.initial_scans)
        cm = CostMap(twin_nav_map(w))
        est0 = loc.pose_at(w.odometry.odometry().pose)
        route = [w.scene.site(s).pose2d for s in cfg.route]
        stations = survey_stations(cm, est0, route, cfg.station_spacing)
        dcfg = cfg.model_copy(update={"detection": det_cfg})
        drive = survey_drive(
            w, loc, grid, lp, stations, dcfg, costmap=cm, truth=w.truth.base_pose2d, log=log
        )
        p_true = w.scene.reflector_positions()
        return _TwinSurvey(
            drive=drive,
            lp=lp,
            lp_true=T_to_se2(w.true_robot.lidar.T_base_link_laser),
            p_true=p_true,
            p_marked=np.asarray(w.map_reflectors, float),
            warp=w.map_warp(p_true),
            profile=w.error_model.config.profile,
            seed=w.error_model.config.seed,
            radius=radius,
        )


def fit_survey(
    obs: SurveyObservations, scfg: SurveyConfig
) -> tuple[ReflectorSurvey, ReflectorSurvey]:
    """The fit, and the same fit with the joint refinement switched the other way."""
    res = survey_reflectors(obs, scfg)
    if not res.ok:
        raise MMPAError(f"reflector survey failed: {res.reason}")
    alt = survey_reflectors(obs, scfg.model_copy(update={"refine_poses": not scfg.refine_poses}))
    return res, alt


def _evaluate(xy: Array, p_true: Array) -> dict[str, Any]:
    """Surveyed positions ``xy`` against the TRUE ones: mean and max error (mm), found,
    missed, spurious."""
    m = match_reflectors(xy, p_true)
    err = 1e3 * m.errors
    return {
        "error_mean_mm": float(err.mean()) if len(err) else float("nan"),
        "error_max_mm": float(err.max()) if len(err) else float("nan"),
        "found": len(m.pairs),
        "missed": len(m.missed),
        "spurious": len(m.spurious),
    }


def _place(
    cfg: ReflectorSurveyConfig, res: ReflectorSurvey, tw: _TwinSurvey
) -> tuple[Array, dict[str, Any] | None]:
    """Placement: the poses' (laser-only) frame as surveyed, or moved rigidly onto the site's
    existing reflector map (control points; the layout stays the survey's). Returns the
    positions of ``cfg.anchor`` and the reflector-map placement's evaluation (None when it
    cannot be made)."""
    try:
        xy_map, tf, n_ctrl = anchor_to(res.positions, tw.p_marked)
        anchor_diag: dict[str, Any] | None = _evaluate(xy_map, tw.p_true) | {
            "control_points": n_ctrl,
            "move_mm_mm_deg": [1e3 * tf[0], 1e3 * tf[1], float(np.rad2deg(tf[2]))],
        }
    except SurveyError:
        if cfg.anchor == "reflector_map":
            raise
        xy_map, anchor_diag = res.positions, None
    xy = xy_map if cfg.anchor == "reflector_map" else res.positions
    return xy, anchor_diag


def _reflector_rows(xy: Array, res: ReflectorSurvey, p_true: Array) -> list[dict[str, Any]]:
    """Per matched reflector (by true id): position, truth, error, views and fit figures."""
    m = match_reflectors(xy, p_true)
    order = np.argsort(m.pairs[:, 1])
    return [
        {
            "id": int(k),
            "x": float(xy[i, 0]),
            "y": float(xy[i, 1]),
            "true": [float(v) for v in p_true[k]],
            "error_mm": float(1e3 * m.errors[j]),
            "views": int(res.views[i]),
            "poses": int(res.poses_seen[i]),
            "bias_mm": float(1e3 * res.biases[i]),
            "residual_rms_mm": float(1e3 * res.residual_rms[i]),
        }
        for j in order
        for i, k in [m.pairs[j]]
    ]


def _diagnostic(
    res: ReflectorSurvey, alt: ReflectorSurvey, anchor_diag: dict[str, Any] | None, tw: _TwinSurvey
) -> dict[str, Any]:
    """The other refinement, the marked map, the layout's shape error, both placements, the
    error against the warped truth, and the station and laser pose errors."""
    p_true, warp = tw.p_true, tw.warp
    poses, truths = tw.drive.observations.poses, tw.drive.truths
    pe = np.array(poses) - np.array(truths)
    pose_err = 1e3 * np.hypot(pe[:, 0], pe[:, 1])
    # the laser's pose in map: estimated (nominal mount) vs true (true mount)
    lt_e, lh_e = laser_origin_heading(np.array(poses), tw.lp)
    lt_t, lh_t = laser_origin_heading(np.array(truths), tw.lp_true)
    lerr = np.column_stack([1e3 * (lt_e - lt_t), np.rad2deg(np.angle(np.exp(1j * (lh_e - lh_t))))])
    return {
        # the same fit with the joint refinement switched the other way
        "other_refinement": _evaluate(alt.positions, p_true) | {"refine_poses": alt.refined},
        "marked_map": _evaluate(tw.p_marked, p_true),  # the twin's reflector map (error model)
        # the layout alone: after the best rigid move onto the truth (evaluation only)
        "shape_error_mean_mm": _evaluate(anchor_to(res.positions, p_true)[0], p_true)[
            "error_mean_mm"
        ],
        # placed onto the twin's (marked) reflector map instead of the poses' mean
        "anchor_poses": _evaluate(res.positions, p_true),
        "anchor_reflector_map": anchor_diag,
        # against the true positions as the (warped) occupancy map draws them
        "error_mean_mm_vs_warped_truth": _eval_shift(res.positions, p_true + warp),
        "map_warp_at_reflectors_mean_mm": float(1e3 * np.linalg.norm(warp, axis=1).mean()),
        "station_pose_error_mm_mean": float(pose_err.mean()),
        "station_pose_error_mm_max": float(pose_err.max()),
        "laser_pose_error_mean_mm_mm_deg": [float(v) for v in lerr.mean(axis=0)],
        "laser_pose_error_sd_mm_mm_deg": [float(v) for v in lerr.std(axis=0)],
        "station_pose_error_refined_mm_mean": float(
            1e3 * np.hypot(*(res.poses - np.array(truths))[:, :2].T).mean()
        ),
    }


def _survey_summary(
    cfg: ReflectorSurveyConfig,
    scfg: SurveyConfig,
    tw: _TwinSurvey,
    fits: tuple[ReflectorSurvey, ReflectorSurvey],
    t0: float,
) -> tuple[dict[str, Any], Array]:
    """The summary (module docstring) and the placed positions (N, 2) m."""
    res, alt = fits
    xy, anchor_diag = _place(cfg, res, tw)
    ev = _evaluate(xy, tw.p_true)
    obs = tw.drive.observations
    summary: dict[str, Any] = {
        "profile": tw.profile,
        "seed": tw.seed,
        "site": cfg.site,
        "route": list(cfg.route),
        "method": cfg.method,
        "anchor": cfg.anchor,
        **ev,
        "target_mm": 3.0,
        "within_target": bool(ev["error_mean_mm"] <= 3.0 and ev["missed"] == 0),
        "residual_rms_mm": 1e3 * res.rms,
        "survey_config": scfg.model_dump(),
        "refined": res.refined,
        "stations": len(obs.poses),
        "scans": tw.drive.scans,
        "detections": len(obs),
        "dropped_candidates": res.dropped_clusters,
        "reflectors": _reflector_rows(xy, res, tw.p_true),
        "diagnostic": _diagnostic(res, alt, anchor_diag, tw),
        "wall_s": time.perf_counter() - t0,
    }
    return summary, xy


def _write(out: Path, summary: dict[str, Any], xy: Array, tw: _TwinSurvey) -> None:
    """``reflectors.yaml``, ``observations.npz`` (the survey's input, to refit without the
    twin, with the true station poses and reflectors), ``robot.yaml``, ``summary.json``."""
    out.mkdir(parents=True, exist_ok=True)
    obs = tw.drive.observations
    rm = ReflectorMap(
        np.arange(len(xy), dtype=np.int64),
        xy,
        np.full(len(xy), tw.radius),
    )
    path = save_reflector_map(rm, out / "reflectors.yaml")
    np.savez(  # the survey's input, to refit without the twin
        out / "observations.npz",
        points=obs.points,
        pose_index=obs.pose_index,
        poses=obs.poses,
        laser_pose=obs.laser_pose,
        scan_index=obs.scan_index,
        poses_true=np.array(tw.drive.truths),
        reflectors_true=tw.p_true,
    )
    summary["reflector_map"] = str(path)
    summary["robot_file"] = str(write_robot_file_reflectors(out / "robot.yaml", path.name))
    write_summary(out, summary)


def run_reflector_survey(
    cfg: ReflectorSurveyConfig,
    out: str | Path | None = None,
    log: Callable[[str], None] | None = None,
) -> dict[str, Any]:
    """Survey the reflectors in the twin (:class:`ReflectorSurveyConfig`) and fit them
    (:func:`mmpa.calibration.reflector_survey.survey_reflectors`); evaluated against the
    twin's TRUE reflector positions (never used above). With ``out``: ``reflectors.yaml``
    (the reflector map file), ``summary.json`` (``error_mean_mm``, ``error_max_mm``,
    found / missed / spurious, diagnostics), ``robot.yaml`` (the robot in use, with
    ``reflector_map: reflectors.yaml``) and ``observations.npz`` (the survey's input:
    :class:`~mmpa.calibration.reflector_survey.SurveyObservations` fields, plus the true
    station poses and reflectors for evaluation)."""
    log = log or log_default
    if cfg.method not in ("hector", "amcl"):
        raise MMPAError(
            f"reflector survey localizer {cfg.method!r}: use a laser-only one, hector or amcl"
        )
    t0 = time.perf_counter()
    errors = ErrorModelConfig.from_profile(cfg.profile, seed=cfg.seed)
    scfg = _survey_defaults(cfg, errors)
    tw = _drive(cfg, errors, log)
    fits = fit_survey(tw.drive.observations, scfg)
    summary, xy = _survey_summary(cfg, scfg, tw, fits, t0)
    if out is not None:
        _write(Path(out), summary, xy, tw)
    return summary


def _survey_defaults(cfg: ReflectorSurveyConfig, errors: ErrorModelConfig) -> SurveyConfig:
    """``cfg.survey`` with the fields not set explicitly taken from what the robot knows:
    the scanner's published range walk on reflective tape (the error model's figures for
    every robot of the profile: ``reflector_bias_mean`` plus the incidence term averaged
    over a cylinder's face, prior SD ``reflector_bias_sd``; never a reflector's own draw),
    and, with ``map_match``, no joint refinement (pose priors of 5 mm / 1 mrad when asked
    for one: the map-matched stops are within ~1 mm; docs/calibration.md "Reflector
    survey")."""
    sc = cfg.survey
    given = sc.model_fields_set
    li = errors.lidar
    upd: dict[str, Any] = {}
    if "range_bias" not in given:
        upd["range_bias"] = li.reflector_bias_mean + li.reflector_incidence_bias * (1 - np.pi / 4)
    if "bias_sigma" not in given:
        upd["bias_sigma"] = li.reflector_bias_sd
    return map_match_priors(sc.model_copy(update=upd), cfg.map_match, given)


def map_match_priors(
    sc: SurveyConfig, map_match: bool, given: set[str] | None = None
) -> SurveyConfig:
    """With ``map_match``, the fit's fields not set explicitly (``given``, default
    ``sc.model_fields_set``): no joint refinement, pose priors of 5 mm / 1 mrad (the
    map-matched stops are within ~1 mm; docs/calibration.md "Reflector survey")."""
    given = sc.model_fields_set if given is None else given
    upd: dict[str, Any] = {}
    if map_match and "refine_poses" not in given:
        upd["refine_poses"] = False
    if map_match and "pose_sigma_xy" not in given:
        upd["pose_sigma_xy"] = 0.005
    if map_match and "pose_sigma_yaw" not in given:
        upd["pose_sigma_yaw"] = 0.001
    return sc.model_copy(update=upd)


def _eval_shift(est: Array, ref: Array) -> float:
    """Mean distance (mm) of ``est`` to its one-to-one match in ``ref``."""

    m = match_reflectors(est, ref)
    return float(1e3 * m.errors.mean()) if len(m.errors) else float("nan")
