"""The reflector survey's drive over the robot interfaces: any
:class:`~mmpa.missions.navigate.MobileRobot` (a base, odometry, a lidar with intensities and
a clock: the twin, or a real platform), a laser-only localizer on the occupancy map, nothing
of a simulator and no truth.

Steps (:func:`survey_drive`):

1. :func:`survey_stations`: stops every ``spacing`` m along the planned path through the
   route's poses (and at each);
2. at the current pose, then at each stop (driven to on the localization estimate,
   :func:`mmpa.missions.navigate.navigate`; an unplannable stop is skipped and reported):
   stand, take ``scans`` scans, update the localizer with each and detect the reflectors
   in it (:func:`mmpa.localization.reflectors.detect_reflectors`, occluded ones dropped);
3. with ``map_match``, refine the stop's pose: its mean scan, reflector beams left out, is
   matched onto the map's signed distance (:func:`mmpa.calibration.reflector_survey.
   match_scan_to_map`, sub-cell);
4. return the detections (laser frame) with their stop and scan:
   :class:`~mmpa.calibration.reflector_survey.SurveyObservations`, the input of
   :func:`~mmpa.calibration.reflector_survey.survey_reflectors`.

Units: m, rad.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np
from pydantic import BaseModel, ConfigDict, Field

from mmpa.calibration.reflector_survey import (
    SurveyError,
    SurveyObservations,
    laser_origin_heading,
    match_scan_to_map,
    signed_distance_map,
)
from mmpa.core.errors import InvalidInputError, MMPAError
from mmpa.core.geometry import Array
from mmpa.localization.localizer import Localizer
from mmpa.localization.reflectors import DetectionConfig, detect_reflectors
from mmpa.maps.occupancy import OccupancyGrid
from mmpa.missions.navigate import MobileRobot, NavigateConfig, navigate
from mmpa.navigation.follower import FollowerConfig
from mmpa.navigation.planner import CostMap, plan_path

__all__ = ["SurveyDrive", "SurveyDriveConfig", "survey_drive", "survey_stations"]


class SurveyDriveConfig(BaseModel):
    """The drive: ``scans`` scans per stop (localization and detection), the reflector
    ``detection`` (its ``radius`` must be the reflectors'), the stops' pose refinement
    ``map_match``, and ``leg_timeout`` s per leg."""

    model_config = ConfigDict(extra="forbid")

    # a standing robot's scans differ only by the range noise: 30 take the per-stop mean's
    # noise to ~1 mm (10 left ~1.6 mm, stop 23)
    scans: int = Field(30, ge=1)
    # the intensity-centroid bearing (sub-beam) by default: the mean beam angle moves in
    # whole 0.25 deg steps, up to 8 mm across the ray at 4 m, and a standing robot sees the
    # same step in every scan, so it does not average out
    detection: DetectionConfig = DetectionConfig(bearing="intensity")
    # refine each stop's pose: its mean scan (reflector beams left out) matched onto the
    # map's signed distance to the occupied/free boundary (sub-cell; the localizer's own
    # estimate is the start)
    map_match: bool = True
    leg_timeout: float = Field(40.0, gt=0)  # s per leg
    scan_period: float = Field(0.1, gt=0)  # s between the standing scans


@dataclass(frozen=True)
class SurveyDrive:
    """The drive's result: ``observations`` (the detections, the stops' poses ``T_map_base``
    and the lidar mount), ``scans`` taken in all, per stop its ``truths`` pose when a truth
    source was given (evaluation only; else empty), and the ``skipped`` stops' reasons."""

    observations: SurveyObservations
    scans: int
    truths: Array
    skipped: list[str]


def survey_stations(cm: Any, start: Array, route: list[Array], spacing: float) -> list[Array]:
    """Station poses ``[x, y, theta]`` along the planned path (on the cost map ``cm``) from
    ``start`` through the ``route`` poses: every ``spacing`` m (heading along the path) and
    each route pose."""

    out: list[Array] = []
    here = np.asarray(start, float)
    for goal in route:
        path = plan_path(cm, here[:2], goal[:2])
        seg = np.linalg.norm(np.diff(path, axis=0), axis=1)
        s = np.concatenate([[0.0], np.cumsum(seg)])
        if np.isfinite(spacing) and s[-1] > 1.5 * spacing:
            n = int(np.floor(s[-1] / spacing))
            for d in np.linspace(0, s[-1], n + 1)[1:-1]:
                k = min(int(np.searchsorted(s, d)), len(path) - 1)
                k0 = max(k - 1, 0)
                dxy = path[k] - path[k0]
                out.append(np.array([path[k][0], path[k][1], float(np.arctan2(dxy[1], dxy[0]))]))
        out.append(np.asarray(goal, float))
        here = np.asarray(goal, float)
    return out


def _map_matched(
    est: Array, ranges: list[Array], angles: Array, lp: Array, sdf: Array, grid: Any
) -> Array:
    """The stop's base pose from its mean scan (NaN beams left out) matched onto ``sdf``."""
    rr = np.array(ranges)
    n_ok = np.isfinite(rr).sum(axis=0)
    r_mean = np.where(n_ok > 0, np.nansum(rr, axis=0) / np.maximum(n_ok, 1), np.nan)
    ok = np.isfinite(r_mean)
    a = angles[ok]
    pts = r_mean[ok, None] * np.column_stack([np.cos(a), np.sin(a)])
    t_l, h_l = laser_origin_heading(est, lp)
    guess = np.array([t_l[0, 0], t_l[0, 1], h_l[0]])
    v, _, _ = match_scan_to_map(sdf, grid.resolution, grid.origin[:2], pts, guess)
    th = v[2] - lp[2]
    c, sn = np.cos(th), np.sin(th)
    return np.array([v[0] - c * lp[0] + sn * lp[1], v[1] - sn * lp[0] - c * lp[1], th])


def _stop_navigation(leg_timeout: float) -> NavigateConfig:
    """How the drive reaches a survey stop: a stop needs a pose estimate, not a precise
    park: 2 cm / 2 deg, no staging stretch (the stops lie on the path, 1 m apart), no
    re-approach; ``leg_timeout`` s per leg."""

    fin = FollowerConfig().final.model_copy(update={"pos_tol": 0.02, "yaw_tol": np.deg2rad(2.0)})
    return NavigateConfig(
        timeout=leg_timeout,
        initial_scans=0,
        settle_scans=3,
        max_corrections=0,
        staging_distance=0.0,
        follower=FollowerConfig(final=fin),
    )


def survey_drive(
    robot: MobileRobot,
    localizer: Localizer,
    grid: OccupancyGrid,
    laser_pose: Array,
    stations: list[Array],
    cfg: SurveyDriveConfig | None = None,
    *,
    costmap: CostMap | None = None,
    truth: Callable[[], Array] | None = None,
    log: Callable[[str], None] | None = None,
) -> SurveyDrive:
    """Survey from the current pose and then each of ``stations`` (module docstring) with
    ``robot`` (a :class:`~mmpa.missions.navigate.MobileRobot`), an initialized laser-only
    ``localizer`` on ``grid`` (an occupancy grid without the reflectors being surveyed), the
    lidar mount ``laser_pose`` ``[x, y, yaw]`` in ``base_link``. ``truth()`` (evaluation
    only; never steers) gives the base's true pose per stop. Raises
    :class:`~mmpa.core.errors.InvalidInputError` on a malformed mount or station."""

    cfg = cfg or SurveyDriveConfig()
    log = log or (lambda m: None)
    lp = np.asarray(laser_pose, float)
    if lp.shape != (3,) or not np.isfinite(lp).all():
        raise InvalidInputError(f"laser_pose must be a finite [x, y, yaw], got {laser_pose!r}")
    for k, st in enumerate(stations):
        st = np.asarray(st, float)
        if st.shape != (3,) or not np.isfinite(st).all():
            raise InvalidInputError(f"station {k} must be a finite [x, y, theta], got {st!r}")
    sdf = signed_distance_map(grid.occupied, grid.resolution) if cfg.map_match else None
    nav = _stop_navigation(cfg.leg_timeout)
    det_cfg = cfg.detection
    points: list[Array] = []
    pose_idx: list[int] = []
    scan_idx: list[int] = []
    poses: list[Array] = []
    truths: list[Array] = []
    skipped: list[str] = []
    n_scan = 0
    for i, goal in enumerate([None, *stations]):
        if goal is not None:
            try:
                navigate(robot, localizer, grid, goal, nav, costmap=costmap, truth=truth)
            except MMPAError as e:  # an unplannable station: skip it
                log(f"station {i}: skipped ({e})")
                skipped.append(f"station {i}: {e}")
                continue
        robot.base.stop()
        found = []
        ranges = []
        scan = None
        for _ in range(cfg.scans):
            robot.step(cfg.scan_period)
            odom = robot.odometry.odometry().pose
            scan = robot.lidar.scan()
            localizer.update(odom, scan, force=True)
            det = detect_reflectors(scan, det_cfg)
            det = det.select(~det.cut)
            found.append(det.points)
            keep = scan.valid() & (np.asarray(scan.intensities) < det_cfg.intensity_threshold)
            ranges.append(np.where(keep, scan.ranges, np.nan))
        est = localizer.pose_at(robot.odometry.odometry().pose)
        if sdf is not None and scan is not None:
            try:
                est = _map_matched(est, ranges, scan.angles, lp, sdf, grid)
            except SurveyError as e:
                log(f"station {i}: map match skipped ({e})")
        for p in found:
            points.extend(p)
            pose_idx.extend([len(poses)] * len(p))
            scan_idx.extend([n_scan] * len(p))
            n_scan += 1
        poses.append(est)
        msg = f"station {i}: {sum(len(p) for p in found)} detections in {cfg.scans} scans"
        if truth is not None:
            truths.append(np.asarray(truth(), float))
            msg += f", pose error {1e3 * np.hypot(*(est[:2] - truths[-1][:2])):.1f} mm"
        log(msg)
    obs = SurveyObservations(
        np.array(points, float).reshape(-1, 2),
        np.array(pose_idx, dtype=np.int64),
        np.array(poses, float).reshape(-1, 3),
        lp,
        np.array(scan_idx, dtype=np.int64),
    )
    return SurveyDrive(obs, n_scan, np.array(truths, float).reshape(-1, 3), skipped)
