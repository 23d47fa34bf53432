"""``mmpa experiment mobile-manipulation``: paper 001 §4.3.4, Table 4, in the twin.

One run (paper 001 §4.2.2, Fig. 15):

1. **Start**: the robot stands at a random pose in the corridor (footprint clear of obstacles)
   and is told a rough initial pose (truth + N(0, ``init_sigma_xy``) per axis, N(0,
   ``init_sigma_theta``); by default the operator's error of the error model ``errors``,
   whose seed, the robot instance, follows ``seed`` unless given); the target object and
   ``others`` other objects (plus distractors) lie on the grasp desk in the lobby, the target
   on the reachable part of it.
2. **Object name**: the operator sends the target's name (an unknown name fails at once).
3. **Navigate** to the work area: A* on the map plus pure pursuit, steering on the enhanced
   AMCL estimate (reflector trilateration, :mod:`mmpa.localization`), to the *entry pose*
   ``entry_back`` m behind the grasp pose, heading the way it came (the desk is off to one
   side).
4. **Find the desk by turning**: the base turns on the spot toward the desk (on the estimate)
   and looks for the desk's two front legs in the lidar scan where the MAP (nominal scene) puts
   them, from the current estimate: found when the desk's center is within +-``face_tol`` of
   the heading and both legs return ``leg_points`` points within ``leg_radius`` of their
   expected positions (the desk is there and the estimate agrees with it). Then it turns on
   the spot to the grasp pose's heading (:mod:`mmpa.missions.desk_search`, on the estimate, to
   ``align_tol``), still ``entry_back`` m from the grasp pose where the base has room to turn.
5. **Approach and localize**: the final approach to the grasp pose in front of the desk,
   stopping, settling scans and re-checks with the reflectors (the high-precision localization
   of Fig. 15 d, e). *Navigation success* is the paper's criterion (§4.3.1): the final
   position estimate within ``success_threshold`` (12 mm) of the truth, with the robot at the
   desk (truth within ``arrive_tol`` of the grasp pose). The go-to-pose controller's own
   ``reached`` flag (3 mm / 3 mrad) is recorded but not required. (Why the turn at the entry
   pose: docs/experiments.md.)
6. **Detect and grasp**: the arm looks down at the desk (the ``grasp`` experiment's first
   view) and runs the tracking grasp (:class:`mmpa.servo.grasp.TrackingGrasp`, unchanged).
   *Detection success*: the target detected in that first frame (Table 3's definition).
   *Grasp success*: the object held off the desk 2 s after the lift, in the physics.

Every run goes through all stages (a navigation "failure" by the 12 mm criterion still parks
the robot at the desk); the report gives each stage's success over all runs, as Table 4 does,
and the grasp success among runs with a detection.
"""

from __future__ import annotations

import time
from contextlib import ExitStack
from typing import Any

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, model_validator

from mmpa.backends.bag.record import ARM_RATE_HZ
from mmpa.backends.twin.error_model import ErrorModelConfig
from mmpa.backends.twin.lidar_noise import rough_pose
from mmpa.backends.twin.twin_maps import laser_pose2d, twin_map, twin_nav_map
from mmpa.backends.twin.world import SimWorld
from mmpa.core.errors import UnknownNameError
from mmpa.core.geometry import Array, inv, se2_to_T
from mmpa.experiments.paper001.grasp import (
    LOOK_HEIGHT,
    LOOK_TARGET,
    REGION,
    held_in_the_physics,
    make_grasper,
    run_grasp,
    run_jobs,
)
from mmpa.experiments.paper001.localization import corridor_start, initial_sigmas
from mmpa.harness.perception_data import DESK_PARK, _place_in_region, desk_frame, random_table_scene
from mmpa.harness.recording import recording_folder, trial_recorder
from mmpa.harness.runner import Context, Outcome, markdown_table, stats
from mmpa.harness.twin_localization import errors_follow_seed, twin_localizer
from mmpa.localization.localizer import METHODS, Localizer
from mmpa.maps.occupancy import OccupancyGrid
from mmpa.missions import desk_search
from mmpa.missions.desk_search import turn_to_heading
from mmpa.missions.navigate import NavigateConfig, NavigationResult, localize_standing, navigate
from mmpa.navigation.planner import CostMap, plan_path
from mmpa.perception import CLASSES
from mmpa.servo.grasp import look_configuration

PAPER = "paper 001 (Zhou et al. 2020) §4.3.4, Table 4 (mobile manipulation, 20 runs per object)"
#: the runner may run this experiment's trials on an executor (``--workers``, ``--executor``)
PARALLEL_TRIALS = True
#: every run can record itself to a bag of its own (``mmpa experiment --record DIR``)
RECORDS_TRIALS = True

#: Table 4: success rate per object (paper names mapped to ours)
TABLE4 = {
    "yida_bottle": {"navigation": 0.85, "detection": 0.88, "grasping": 0.93},
    "tennis_ball": {"navigation": 0.95, "detection": 0.95, "grasping": 0.94},
    "paper_cup": {"navigation": 0.90, "detection": 0.89, "grasping": 0.88},
}


class Config(BaseModel):
    model_config = ConfigDict(extra="forbid")

    seed: int = Field(0, ge=0)  # every random draw flows from it (numpy: >= 0)
    trials: int | None = None  # runs per object; None: the paper's 20
    objects: list[str] = Field(default_factory=lambda: list(TABLE4))
    method: str = "enhanced"  # localizer (mmpa.localization.localizer.METHODS)
    lighting: str = "normal"
    corridor_x: tuple[float, float] = (-10.5, -4.0)
    corridor_y: tuple[float, float] = (0.75, 1.65)
    start_clearance: float = Field(0.55, gt=0)  # m from obstacles
    # the rough initial pose's error (m, rad); None: the error model's operator section
    init_sigma_xy: float | None = Field(None, ge=0)
    init_sigma_theta: float | None = Field(None, ge=0)
    resolution: float = Field(0.05, gt=0)
    # rad (map): heading at the work-area entry pose; None: the direction the planned path
    # arrives in (why: docs/experiments.md)
    entry_heading: float | None = None
    # m: the entry pose is this far back from the grasp pose (where the base has room to turn)
    entry_back: float = Field(0.25, ge=0)
    search_w: float = Field(0.4, gt=0)  # rad/s, turning speed while looking for the desk
    search_timeout: float = Field(20.0, gt=0)  # s
    leg_radius: float = Field(0.05, gt=0)  # m
    leg_points: int = Field(2, ge=1)
    face_tol: float = Field(0.3, gt=0)  # rad
    # rad: after the search, turn to the grasp pose's heading within this tolerance before the
    # final approach (0: skip)
    align_tol: float = Field(0.003, ge=0)
    align_timeout: float = Field(10.0, gt=0)  # s
    success_threshold: float = Field(0.012, gt=0)  # m (paper: 12 mm)
    arrive_tol: float = Field(0.05, gt=0)  # m, truth to the grasp pose
    # the localization experiment's navigation settings
    navigate: NavigateConfig = NavigateConfig(scan_rate=5.0, timeout=150.0)
    weights: str | None = None  # detector weights; None: shipped; "oracle": truth boxes
    preprocess_dark: bool = False
    use_predictor: bool = True
    others: int = 2
    max_time: float = 15.0  # s of simulated time for the grasp

    errors: ErrorModelConfig = ErrorModelConfig()  # the twin (its seed: ``seed`` if not given)

    @model_validator(mode="after")
    def _robot_seed(self) -> Config:
        return errors_follow_seed(self)

    def n_trials(self) -> int:
        return 20 if self.trials is None else self.trials


def desk_front_legs(world: Any) -> Array:
    """Map positions (2, 2) of the grasp desk's two legs on the robot's side (nominal scene:
    legs 0.04 m in from the corners, see :mod:`mmpa.backends.twin.mjcf`), from the desk's center,
    yaw and size; the robot's side is -y in the desk frame (``DESK_PARK`` faces +y)."""
    d = world.scene.grasp_desk
    lx, ly = d.size[0], d.size[1]
    T = se2_to_T(d.center[0], d.center[1], np.deg2rad(d.yaw_deg))
    local = np.array([[lx / 2 - 0.04, -(ly / 2 - 0.04)], [-(lx / 2 - 0.04), -(ly / 2 - 0.04)]])
    return local @ T[:2, :2].T + T[:2, 3]


def search_desk(world: SimWorld, localizer: Localizer, cfg: Config) -> tuple[bool, float]:
    """Turn on the spot until the grasp desk's front legs (where the nominal scene puts them)
    are in the scan (:func:`mmpa.missions.desk_search.search_desk`)."""
    return desk_search.search_desk(
        world,
        localizer,
        desk_front_legs(world),
        world.scene.grasp_desk.center,
        laser_pose2d(world),
        cfg.face_tol,
        cfg.leg_radius,
        cfg.leg_points,
        cfg.search_w,
        cfg.search_timeout,
    )


def place_trial_objects(world: Any, rng: np.random.Generator, name: str, others: int) -> None:
    """The target in the reachable region (the ``grasp`` experiment's), ``others`` other
    detector classes and each distractor with p = 0.5 anywhere on the desk."""

    pool = [c for c in CLASSES if c != name]
    objs = rng.choice(pool, min(others, len(pool)), replace=False).tolist()
    dis = [n for n in ("distractor_book", "distractor_phone") if rng.random() < 0.5]
    placed = random_table_scene(world, rng, objs, dis)
    _place_in_region(world, rng, name, placed, REGION)


def mm_trial(
    cfg: Config, k: int, name: str, grasper: Any, record: str | None = None
) -> dict[str, Any]:
    """One run (module doc); truth read only for the evaluation columns. ``record``: a folder
    for the run's ROS 2 bag (``object-NAME-site-0-trial-k.mcap``: scans, odometry, the map,
    the estimates, every camera frame, the arm at 50 Hz, the truth; ``--record``)."""
    rng = np.random.default_rng([cfg.seed, k, CLASSES.index(name)])
    w0 = time.perf_counter()
    with SimWorld(errors=cfg.errors, site="0", episode=k) as world, ExitStack() as stack:
        rec = None
        if record is not None:  # the same run, observed: `world` is the recording stand-in
            label = {"object": name}
            rec = stack.enter_context(trial_recorder(record, label, "0", k, world, ARM_RATE_HZ))
            world = rec.world()
        start, loc, grid, costmap = _set_up_run(cfg, k, name, world, rng, rec)
        nav, r2 = _drive_to_desk(cfg, world, loc, grid, costmap)
        res, held = _detect_and_grasp(world, grasper, name, r2.final_estimate)
        sim_t = world.time
    return {
        "object": name,
        "trial": k,
        "start_x": start[0],
        "start_y": start[1],
        "start_theta": start[2],
        **nav,
        "detected": res.detected_first,
        "grasped": held,
        "reason": res.reason if held or res.reason != "grasped" else "dropped",
        "sim_seconds": sim_t,
        "wall_seconds": time.perf_counter() - w0,
    }


def _set_up_run(
    cfg: Config, k: int, name: str, world: Any, rng: np.random.Generator, rec: Any
) -> tuple[np.ndarray, Localizer, OccupancyGrid, CostMap]:
    """Stage 1: a clear corridor start and the operator's rough pose of it, the objects on
    the desk, the light; the map, the costmap and the localizer (from the rough pose).
    Returns ``(start, localizer, map, costmap)``."""
    nav = CostMap(twin_nav_map(world, cfg.resolution))
    start = corridor_start(nav, rng, cfg)
    guess = rough_pose(start, rng, *initial_sigmas(cfg))  # the operator's rough pose
    world.reset(pose2d=start, settle=0.2)
    place_trial_objects(world, rng, name, cfg.others)
    world.set_lighting(cfg.lighting)
    world.step(0.3)
    grid = twin_map(world, cfg.resolution)
    costmap = CostMap(twin_nav_map(world, cfg.resolution))
    loc = twin_localizer(world, cfg.method, np.random.default_rng([cfg.seed, k, 7]), grid=grid)
    if rec is not None:
        rec.write_map(grid)
        loc = rec.localizer(loc)
    loc.initialize(guess)
    return start, loc, grid, costmap


def _drive_to_desk(
    cfg: Config, world: Any, loc: Localizer, grid: OccupancyGrid, costmap: CostMap
) -> tuple[dict[str, Any], NavigationResult]:
    """Stages 3-5: navigate to the entry pose, find the desk by turning, turn to the grasp
    pose's heading, the final approach. Returns the navigation columns of the run's row and
    the final approach's result."""
    park = np.array(DESK_PARK)
    back = cfg.entry_back * np.array([np.cos(park[2]), np.sin(park[2])])
    entry = np.array([*(park[:2] - back), 0.0])
    if cfg.entry_heading is None:  # planned from the localizer's first estimate
        n0 = max(cfg.navigate.initial_scans, 1)
        est0 = localize_standing(world, loc, n0, cfg.navigate.scan_rate)
        path = plan_path(costmap, est0[:2], entry[:2])
        d = path[-1] - path[max(len(path) - 2, 0)]
        entry[2] = float(np.arctan2(d[1], d[0]))
    else:
        entry[2] = cfg.entry_heading
    r1 = navigate(
        world, loc, grid, entry, cfg.navigate, costmap=costmap, truth=world.truth.base_pose2d
    )
    found, t_search = search_desk(world, loc, cfg)
    aligned = (
        turn_to_heading(world, loc, float(park[2]), cfg.align_tol, cfg.align_timeout)[0]
        if cfg.align_tol > 0
        else False
    )
    r2 = navigate(
        world, loc, grid, park, cfg.navigate, costmap=costmap, truth=world.truth.base_pose2d
    )
    e = r2.localization_error
    loc_err = float(np.hypot(e[0], e[1]))
    nav_ok = bool(loc_err < cfg.success_threshold and r2.parking_error_xy < cfg.arrive_tol)
    nav = {
        "entry_reached": r1.reached,
        "entry_err_m": r1.parking_error_xy,
        "entry_loc_err_m": float(np.hypot(*r1.localization_error[:2])),
        "desk_found": found,
        "search_s": t_search,
        "aligned": aligned,
        "nav_reached": r2.reached,
        "loc_err_m": loc_err,
        "loc_err_theta_rad": abs(float(e[2])),
        "parking_err_m": r2.parking_error_xy,
        "parking_err_yaw_rad": r2.parking_error_yaw,
        "navigation": nav_ok,
    }
    return nav, r2


def _detect_and_grasp(
    world: Any, grasper: Any, name: str, final_estimate: np.ndarray
) -> tuple[Any, bool]:
    """Stage 6: the arm to the grasp experiment's first view, then the tracking grasp of
    ``name``. Returns the grasp's result and whether the object is held in the physics."""
    # detection and grasp from the grasp experiment's first view, aimed with the
    # localization estimate: the point the first view sees from the grasp pose (the
    # base may stop 0.1-0.3 rad off its heading next to the desk, where it cannot turn on
    # the spot; a fixed arm-base target then leaves objects near the region's edge out)
    park = np.array(DESK_PARK)
    _, top, _ = desk_frame(world)
    rb = world.nominal
    T_ba = rb.T_base_link_arm_base
    p_look = se2_to_T(*park) @ T_ba @ np.array([*LOOK_TARGET, 0.0, 1.0])
    look_xy = (inv(se2_to_T(*final_estimate) @ T_ba) @ p_look)[:2]
    look = np.array([*look_xy, top - T_ba[2, 3]])
    q_look = look_configuration(rb, look, LOOK_HEIGHT)
    world.arm.move_joints(q_look)
    res = run_grasp(world, grasper, name, world.step)
    held = held_in_the_physics(world, name, top)
    return res, held


#: this process's grasper (a worker keeps it between runs): settings -> grasper
_GRASPERS: dict[str, Any] = {}


def mm_job(cfg_json: str, k: int, name: str, record: str | None) -> dict[str, Any]:
    """Run ``k`` for object ``name`` (a worker job): its row. The world, the scene and
    every draw are the run's own (``episode=k``, ``[seed, k, object]``)."""

    cfg = Config.model_validate_json(cfg_json)
    key = cfg.model_dump_json(exclude={"seed", "trials", "objects"})
    if key not in _GRASPERS:
        _GRASPERS.clear()
        _GRASPERS[key] = make_grasper(cfg)
    return mm_trial(cfg, k, name, _GRASPERS[key], record)


def run(cfg: Config, ctx: Context) -> Outcome:
    """The runs on ``ctx``'s executor, the success rates per object beside Table 4, the
    report with the failures."""
    _check_names(cfg)
    n = cfg.n_trials()
    cfg_json = cfg.model_dump_json()
    rec = recording_folder()  # mmpa experiment --record
    jobs = [
        ({"object": obj, "trial": k}, mm_job, (cfg_json, k, obj, rec))
        for obj in cfg.objects
        for k in range(n)
    ]
    rows = run_jobs(ctx, jobs, "runs")
    summary: dict[str, Any] = {"runs_per_object": n, "objects": {}}
    table = _object_table(cfg, rows, summary)
    for key in ("navigation", "detected", "grasped"):
        summary[key] = float(np.mean([x[key] for x in rows]))
    return Outcome(rows=rows, summary=summary, report=_report(cfg, n, rows, table))


def _check_names(cfg: Config) -> None:
    """Raises :class:`UnknownNameError` on an unknown object or localization method, or the
    oracle detector (the run detects with the trained one)."""
    for o in cfg.objects:
        if o not in CLASSES:
            raise UnknownNameError("object", o, list(CLASSES))
    if cfg.method not in METHODS:
        raise UnknownNameError("localization method", cfg.method, list(METHODS))
    if cfg.weights == "oracle":
        raise UnknownNameError("weights", "oracle", ["a weights file", "None (shipped)"])


def _object_table(
    cfg: Config, rows: list[dict[str, Any]], summary: dict[str, Any]
) -> list[list[Any]]:
    """Per object into ``summary["objects"]``: the stage success rates, the grasp success
    given a detection, the errors at the desk; the table's lines beside Table 4."""
    table = []
    for obj in cfg.objects:
        r = [x for x in rows if x["object"] == obj]
        nav = float(np.mean([x["navigation"] for x in r]))
        det = float(np.mean([x["detected"] for x in r]))
        ok = float(np.mean([x["grasped"] for x in r]))
        rd = [x for x in r if x["detected"]]
        ok_given = float(np.mean([x["grasped"] for x in rd])) if rd else float("nan")
        p = TABLE4.get(obj, {})
        summary["objects"][obj] = {
            "navigation": nav,
            "detection": det,
            "grasping": ok,
            "grasping_given_detection": ok_given,
            "desk_found": float(np.mean([x["desk_found"] for x in r])),
            "loc_err_mm": stats(1000 * x["loc_err_m"] for x in r),
            "parking_err_mm": stats(1000 * x["parking_err_m"] for x in r),
            "parking_err_yaw_rad": stats(x["parking_err_yaw_rad"] for x in r),
            "nav_reached": float(np.mean([x["nav_reached"] for x in r])),
        }
        table.append(
            [
                obj,
                nav,
                p.get("navigation", float("nan")),
                det,
                p.get("detection", float("nan")),
                ok,
                ok_given,
                p.get("grasping", float("nan")),
            ]
        )
    return table


def _report(cfg: Config, n: int, rows: list[dict[str, Any]], table: list[list[Any]]) -> str:
    """report.md: the definitions, Table 4, the errors at the desk, the failures."""
    header = [
        "object",
        "navigation",
        "paper",
        "detection",
        "paper",
        "grasping",
        "grasping given detected",
        "paper",
    ]
    err = stats(1000 * x["loc_err_m"] for x in rows)
    park = stats(1000 * x["parking_err_m"] for x in rows)
    yaw = stats(x["parking_err_yaw_rad"] for x in rows)
    return (
        f"{n} runs per object (seed {cfg.seed}, {cfg.method} localization, {cfg.lighting} "
        "light). Navigation = final position estimate within "
        f"{1000 * cfg.success_threshold:.0f} mm of the truth at the desk (paper §4.3.1); "
        "detection = target found in the first frame of the working view; grasping = held off "
        "the desk 2 s after the lift (physics). Rates over all runs, like Table 4; "
        "'grasping given detected' over the runs with a detection.\n\n"
        + markdown_table(header, table, digits=2)
        + f"\nLocalization error at the desk: mean {err['mean']:.1f} mm, max {err['max']:.1f} mm; "
        f"parking error (truth vs goal): mean {park['mean']:.1f} mm, max {park['max']:.1f} mm, "
        f"heading mean {yaw['mean']:.4f} rad, max {yaw['max']:.4f} rad; go-to-pose reached "
        f"(3 mm / 3 mrad on the estimate) in {sum(x['nav_reached'] for x in rows)}/{len(rows)}; "
        f"desk found by turning in {sum(x['desk_found'] for x in rows)}/{len(rows)} runs.\n"
        + "\nFailures:\n"
        + "".join(
            f"- {r['object']} run {r['trial']}: navigation {'ok' if r['navigation'] else 'FAIL'}"
            f" ({1000 * r['loc_err_m']:.1f} mm), detection "
            f"{'ok' if r['detected'] else 'FAIL'}, grasp: {r['reason']}\n"
            for r in rows
            if not (r["navigation"] and r["detected"] and r["grasped"])
        )
    )
