"""``mmpa --robot R calibrate reflectors`` on a hardware robot (a ``ros2`` or ``direct``
backend with a base, odometry and a lidar, or any :class:`~mmpa.robot.interfaces.
MobileManipulator` that has them): no truth.

The user gives the occupancy map (map_server YAML; its reflector landmarks, if any, are
never localized on), the robot's rough pose in it (``initial_pose``) and the route (poses
in the map). The laser-only localizer settles on standing scans from the rough pose, the
stops are planned every ``station_spacing`` m along the route on the map's cost map,
``confirm`` is asked before the base moves, then the survey drive
(:func:`mmpa.missions.survey_drive.survey_drive`) and the fit
(:func:`mmpa.calibration.reflector_survey.survey_reflectors`; the scanner's range walk on
tape from ``survey``, default :class:`~mmpa.calibration.reflector_survey.SurveyConfig`'s).
Placed by the poses, or (``anchor: reflector_map``) rigidly onto the map's own reflectors.
The summary holds what the robot measured: reflectors found, the fit's residuals, views per
reflector, the stops (reached / skipped). Files: ``reflectors.yaml``, ``observations.npz``,
``robot.yaml`` (the robot file's frames and backend kept, ``reflector_map`` set),
``summary.json``. Units: m in the files, mm in the summary.
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
from mmpa.apps.calibrate.reflectors import fit_survey, map_match_priors
from mmpa.calibration.reflector_survey import SurveyConfig, anchor_to
from mmpa.core.errors import ConfigError
from mmpa.core.geometry import Array, T_to_se2
from mmpa.localization.localizer import make_localizer
from mmpa.maps.map_server import load_map
from mmpa.maps.reflector_map import ReflectorMap, save_reflector_map
from mmpa.missions.navigate import localize_standing
from mmpa.missions.survey_drive import SurveyDriveConfig, survey_drive, survey_stations
from mmpa.navigation.planner import CostMap
from mmpa.robot.interfaces import MobileManipulator, require

__all__ = ["RobotSurveyConfig", "run_reflector_survey_on_robot"]

Pose = tuple[float, float, float]


class RobotSurveyConfig(SurveyDriveConfig):
    """The survey on a robot (module docstring): ``map`` (map_server YAML), ``initial_pose``
    and ``route`` (``[x, y, theta]`` m, rad in the map), ``station_spacing`` m,
    ``initial_scans``, the laser-only ``method``, the reflectors' ``radius`` (m; None: the
    map's reflector radius), ``anchor``, ``seed`` (the localizer's draws) and ``survey``
    (the fit)."""

    model_config = ConfigDict(extra="forbid")

    map: Path
    initial_pose: Pose
    route: tuple[Pose, ...] = Field(min_length=1)
    station_spacing: float = Field(1.0, gt=0)
    initial_scans: int = Field(30, ge=1)
    method: Literal["hector", "amcl"] = "hector"
    radius: float | None = Field(None, gt=0)
    anchor: Literal["poses", "reflector_map"] = "poses"
    seed: int = Field(0, ge=0)
    survey: SurveyConfig = SurveyConfig()


def _path_length(stations: list[Array], start: Array) -> float:
    pts = np.array([start[:2], *[s[:2] for s in stations]], float)
    return float(np.linalg.norm(np.diff(pts, axis=0), axis=1).sum())


def _placed(cfg: RobotSurveyConfig, xy: Array, marked: Array) -> Array:
    """``xy`` as surveyed, or moved rigidly onto the map's reflectors ``marked``."""
    if cfg.anchor == "poses":
        return xy
    if len(marked) < 2:
        raise ConfigError(f"{cfg.map}: anchor reflector_map needs the map's reflectors (>= 2)")
    return anchor_to(xy, marked)[0]


def run_reflector_survey_on_robot(
    robot: MobileManipulator,
    cfg: RobotSurveyConfig,
    out: Path | None = None,
    *,
    kind: str = "hardware",
    confirm: Callable[[str], bool] | None = None,
    log: Callable[[str], None] | None = None,
    robot_file: Path | None = None,
) -> dict[str, Any]:
    """Survey the reflectors with ``robot`` (module docstring); ``confirm(question)`` before
    the base moves (False: ``ok`` False, nothing moved). Returns the summary (also
    ``out/summary.json``)."""
    log = log or log_default
    t0 = time.perf_counter()
    require(robot, "base", "odometry", "lidar", mission="the reflector survey")
    full = load_map(cfg.map)
    radius = cfg.radius or full.reflector_radius
    if not radius > 0:
        raise ConfigError(f"{cfg.map} has no reflector radius: give the reflectors' radius")
    grid = dataclasses.replace(full, reflectors=np.zeros((0, 2)))
    lp = T_to_se2(robot.description.lidar.T_base_link_laser)
    loc = make_localizer(cfg.method, grid, lp, np.random.default_rng([cfg.seed, 3]))
    loc.initialize(np.asarray(cfg.initial_pose, float))
    est0 = localize_standing(robot, loc, scans=cfg.initial_scans)  # type: ignore[arg-type]
    cm = CostMap(grid)
    route = [np.asarray(p, float) for p in cfg.route]
    stations = survey_stations(cm, est0, route, cfg.station_spacing)
    head = {"backend": kind, "start_estimate": [float(v) for v in est0]}
    question = (
        f"the base will drive to {len(stations)} survey stops, {_path_length(stations, est0):.1f}"
        f" m along the route, standing {cfg.scans} scans at each. Move the base?"
    )
    if confirm is not None and not confirm(question):
        summary = {**head, "ok": False, "reason": "declined: nothing moved", "moved": False}
        if out is not None:
            Path(out).mkdir(parents=True, exist_ok=True)
            write_summary(Path(out), summary)
        return summary
    det = cfg.detection
    if "radius" not in det.model_fields_set:
        det = det.model_copy(update={"radius": radius})
    dcfg = cfg.model_copy(update={"detection": det})
    drive = survey_drive(robot, loc, grid, lp, stations, dcfg, costmap=cm, log=log)  # type: ignore[arg-type]
    scfg = map_match_priors(cfg.survey, cfg.map_match)
    res, _ = fit_survey(drive.observations, scfg)
    xy = _placed(cfg, res.positions, np.asarray(full.reflectors, float))
    obs = drive.observations
    summary = {
        **head,
        "ok": True,
        "reason": "surveyed",
        "moved": True,
        "found": len(xy),
        "residual_rms_mm": 1e3 * res.rms,
        "refined": res.refined,
        "anchor": cfg.anchor,
        "stations": len(obs.poses),
        "skipped": drive.skipped,
        "scans": drive.scans,
        "detections": len(obs),
        "dropped_candidates": res.dropped_clusters,
        "reflectors": [
            {
                "x": float(xy[i, 0]),
                "y": float(xy[i, 1]),
                "views": int(res.views[i]),
                "poses": int(res.poses_seen[i]),
                "bias_mm": float(1e3 * res.biases[i]),
                "residual_rms_mm": float(1e3 * res.residual_rms[i]),
            }
            for i in range(len(xy))
        ],
        "survey_config": scfg.model_dump(),
        "wall_s": time.perf_counter() - t0,
    }
    if out is not None:
        _write(Path(out), summary, xy, radius, obs, robot_file)
    return summary


def _write(
    out: Path, summary: dict[str, Any], xy: Array, radius: float, obs: Any, robot_file: Any
) -> None:
    """``reflectors.yaml``, ``observations.npz`` (to refit), ``robot.yaml``, ``summary.json``."""
    out.mkdir(parents=True, exist_ok=True)
    rm = ReflectorMap(np.arange(len(xy), dtype=np.int64), xy, np.full(len(xy), radius))
    path = save_reflector_map(rm, out / "reflectors.yaml")
    np.savez(
        out / "observations.npz",
        points=obs.points,
        pose_index=obs.pose_index,
        poses=obs.poses,
        laser_pose=obs.laser_pose,
        scan_index=obs.scan_index,
    )
    summary["reflector_map"] = str(path)
    rf = write_robot_file_reflectors(out / "robot.yaml", path.name, robot_file=robot_file)
    summary["robot_file"] = str(rf)
    write_summary(out, summary)
