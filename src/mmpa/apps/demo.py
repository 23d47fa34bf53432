"""The main job, first version: drive from Site 0 to Site 1 in the twin, look at the bench.

``run_demo`` builds the default world, localizes with the reflector-enhanced AMCL (paper 001
§3.1) on a map made from the scene, plans with A* and drives there on the ESTIMATE
(``localization="truth"`` keeps the old true-pose go-to-pose controller), captures a wrist
RGB-D frame and a lidar scan at the goal, and writes a run folder:

- ``color.png``, ``depth.png``: the wrist camera frame (noisy, as software sees it);
- ``topdown.png``: map with walls, desks, reflectors, the robot, its path and the scan;
- ``cloud.ply``: the colored point cloud in the camera frame (Open3D);
- ``summary.json`` / ``summary.md``: parking error against the truth and timings;
- ``config.yaml``: the final configuration.

``snapshot`` writes the same pictures for a robot placed at any site.
"""

from __future__ import annotations

import json
import time
from collections.abc import Callable
from contextlib import ExitStack
from pathlib import Path

import numpy as np
import open3d as o3d
from pydantic import BaseModel, ConfigDict, Field, field_validator

from mmpa.apps.view import FoxgloveView, Tee
from mmpa.backends.bag import BagWriter, Recorder
from mmpa.backends.bag.record import ARM_RATE_HZ
from mmpa.backends.twin.error_model import ErrorModelConfig
from mmpa.backends.twin.operator import get_demonstration, rough_initial_pose
from mmpa.backends.twin.scene import load_scene
from mmpa.backends.twin.twin_maps import twin_map, twin_nav_map
from mmpa.backends.twin.world import SimWorld
from mmpa.core.config import save_config
from mmpa.core.errors import MMPAError
from mmpa.core.geometry import Array, T_to_vec6, apply, inv, se2_to_T, wrap_angle
from mmpa.harness import plots
from mmpa.harness.ipe_eval import pose_errors
from mmpa.harness.twin_localization import twin_localizer
from mmpa.harness.twin_site import MMPAExperimentConfig, key_error, teach_in_world
from mmpa.localization.localizer import METHODS
from mmpa.missions.navigate import NavigateConfig, navigate
from mmpa.missions.teach_repeat import automate, execute_joint_path
from mmpa.navigation import GoToPoseConfig, go_to_pose_command
from mmpa.navigation.planner import CostMap
from mmpa.tasks import write_bundle

__all__ = ["DemoConfig", "run_demo", "snapshot"]

Progress = Callable[[str, float], None]


class DemoConfig(BaseModel):
    """Configuration of ``mmpa demo`` and ``mmpa sim snapshot``."""

    # site names look like numbers ("2"): --set goal_site=2 must stay a string
    # NaN / inf refused (timeout=inf would drive forever)
    model_config = ConfigDict(extra="forbid", coerce_numbers_to_str=True, allow_inf_nan=False)

    scene: str | None = None  # path of a scene YAML; None: the built-in world
    start_site: str = "0"
    goal_site: str = "1"
    control_rate: float = Field(20.0, gt=0)  # Hz
    timeout: float = Field(90.0, gt=0)  # s of simulated time
    controller: GoToPoseConfig = GoToPoseConfig()  # used only with localization="truth"
    # a method of mmpa.localization.localizer.METHODS, or "truth" (true-pose control)
    localization: str = "enhanced"
    navigate: NavigateConfig = NavigateConfig()
    arm_view: tuple[float, ...] | None = None  # joints for the bench view; None: view_bench
    # MMPA (paper 000): a demonstration taught at the goal site before the drive; after
    # parking there, IPE + the adapted tool path run and are scored against the truth
    mmpa_task: str | None = "needle_site1"
    errors: ErrorModelConfig = ErrorModelConfig()

    @field_validator("localization")
    @classmethod
    def _known_method(cls, v: str) -> str:

        if v != "truth" and v not in METHODS:
            raise ValueError(f"unknown localization {v!r}; valid: truth, {', '.join(METHODS)}")
        return v


def _capture(world: SimWorld, out: Path, cfg: DemoConfig, q_view: Array) -> dict:
    """Point the camera at the bench, capture RGB-D + scan, write the pictures."""
    world.arm.move_joints(q_view)
    t0 = time.perf_counter()
    frame = world.camera.capture()
    cloud = frame.to_point_cloud(min_depth=0.2, max_depth=3.0)
    t_capture = time.perf_counter() - t0
    scan = world.lidar.scan()
    plots.save_color(out / "color.png", frame.color)
    plots.save_depth(out / "depth.png", frame.depth)
    _write_ply(out / "cloud.ply", cloud.points, cloud.colors)
    T_map_laser = world.truth.T_map_base_link() @ world.nominal.lidar.T_base_link_laser
    pts = scan.points()
    pts_map = apply(T_map_laser, np.column_stack([pts, np.zeros(len(pts))]))[:, :2]
    reflective = scan.intensities[scan.valid()] > 1000.0
    return {
        "cloud_points": len(cloud),
        "capture_seconds": round(t_capture, 4),
        "depth_invalid_fraction": round(float((frame.depth <= 0).mean()), 4),
        "scan_valid_beams": int(scan.valid().sum()),
        "scan_reflective_beams": int(reflective.sum()),
        "_scan_map": pts_map,
        "_reflective": reflective,
    }


def _write_ply(path: Path, points: Array, colors: Array) -> None:
    pc = o3d.geometry.PointCloud()
    pc.points = o3d.utility.Vector3dVector(points)
    pc.colors = o3d.utility.Vector3dVector(np.clip(colors, 0, 1))
    if not o3d.io.write_point_cloud(str(path), pc):
        raise MMPAError(f"could not write {path}")


def _topdown(
    world: SimWorld, out: Path, extra: dict, path_xy: Array | None, goal: Array | None, title: str
) -> None:
    plots.save_topdown(
        out / "topdown.png",
        world.scene,
        world.nominal,
        world.truth.base_pose2d(),
        scan_points_map=extra["_scan_map"],
        scan_reflective=extra["_reflective"],
        map_reflectors=world.map_reflectors,
        path_xy=path_xy,
        goal_pose2d=goal,
        title=title,
    )


def run_demo(
    cfg: DemoConfig,
    out: str | Path,
    progress: Progress | None = None,
    record: str | Path | None = None,
    view: int | None = None,
) -> dict:
    """Drive ``start_site`` -> ``goal_site``, capture, write the run folder; return the summary.

    ``record``: also record the run after teaching (the drive, MMPA, the capture) to this ROS 2
    bag (``FILE.mcap`` or a rosbag2 folder; :class:`mmpa.backends.bag.Recorder`), the arm's
    ``/joint_states`` and ``/tf`` every 20 ms of sim time
    (:data:`mmpa.backends.bag.record.ARM_RATE_HZ`)
    through the whole run, arm motions included. ``view``: serve the
    same topics live to Foxglove on ``ws://127.0.0.1:view`` (:class:`mmpa.apps.view.FoxgloveView`;
    0 picks a free port)."""
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    save_config(cfg, out / "config.yaml")
    scene = load_scene(cfg.scene)
    goal = scene.site(cfg.goal_site).pose2d
    wall0 = time.perf_counter()
    with (
        SimWorld(scene=scene, errors=cfg.errors, site=cfg.start_site) as world,
        ExitStack() as stack,
    ):
        q_view = np.array(
            cfg.arm_view if cfg.arm_view is not None else world.nominal.arm.view_bench
        )
        taught = _teach_first(world, cfg, progress)
        recorder, sinks, bag = _observers(stack, world, record, view, progress)
        if recorder is not None:
            world = recorder.world()
        start = world.truth.base_pose2d()
        done, path, loc_err, estimate = _drive(world, recorder, cfg, goal, start, progress)
        world.base.stop()
        world.step(0.5)
        drive_time = world.time
        mmpa_summary = (
            _run_mmpa(world, taught, estimate, out, progress) if taught is not None and done else {}
        )
        final = world.truth.base_pose2d()
        T_err = inv(se2_to_T(*goal)) @ world.truth.T_map_base_link()
        if progress is not None:
            progress("capturing", 1.0)
        extra = _capture(world, out, cfg, q_view)
        odo = world.base.odometry()
        path_xy = np.array(path)[:, :2]
        _topdown(
            world,
            out,
            extra,
            path_xy,
            goal,
            f"demo: site {cfg.start_site} -> {cfg.goal_site} ({cfg.localization} pose control)",
        )
        summary = {
            "profile": cfg.errors.profile,
            "start_site": cfg.start_site,
            "goal_site": cfg.goal_site,
            "reached": bool(done),
            "drive_sim_seconds": round(drive_time, 3),
            "wall_seconds": round(time.perf_counter() - wall0, 3),
            "parking_error_xy_m": round(float(np.hypot(*(final[:2] - goal[:2]))), 5),
            "parking_error_yaw_deg": round(float(np.rad2deg(wrap_angle(final[2] - goal[2]))), 4),
            "parking_error_6d": [round(float(x), 6) for x in T_to_vec6(T_err)],
            "localization": cfg.localization,
            "localization_error_xy_m": (
                None if loc_err is None else round(float(np.hypot(*loc_err[:2])), 5)
            ),
            "odometry_distance_m": round(float(np.hypot(*odo.pose[:2])), 4),
            "true_distance_m": round(float(np.hypot(*(final[:2] - start[:2]))), 4),
            **{k: v for k, v in extra.items() if not k.startswith("_")},
            **mmpa_summary,
        }
        if bag is not None:
            summary["bag"] = str(record)
            summary["bag_messages"] = sum(bag.counts.values())
        if view is not None:
            summary["view"] = f"ws://127.0.0.1:{sinks[-1].port}"
    _write_summary(out, summary)
    return summary


def _observers(
    stack: ExitStack,
    world: SimWorld,
    record: str | Path | None,
    view: int | None,
    progress: Progress | None,
) -> tuple[Recorder | None, list, BagWriter | None]:
    """The run's recorder into the bag ``record`` and/or the live view on port ``view``
    (None, [], None without either): ``(recorder, sinks, bag)``."""
    if record is None and view is None:
        return None, [], None
    sinks: list = []
    bag = None
    if record is not None:
        bag = stack.enter_context(BagWriter(record, overwrite=True))
        sinks.append(bag)
    if view is not None:
        sinks.append(stack.enter_context(FoxgloveView(port=view)))
        if progress:
            progress(f"live view: open ws://127.0.0.1:{sinks[-1].port} in Foxglove", 0.0)
    sink = sinks[0] if len(sinks) == 1 else Tee(*sinks)
    # the arm at 50 Hz through every motion (MMPA's path, the capture's view move)
    recorder = stack.enter_context(Recorder(sink, world, joint_rate_hz=ARM_RATE_HZ))
    return recorder, sinks, bag


def _drive(
    world: SimWorld,
    recorder: Recorder | None,
    cfg: DemoConfig,
    goal: Array,
    start: Array,
    progress: Progress | None,
) -> tuple[bool, list, Array | None, Array | None]:
    """Drive to ``goal`` on the true pose or on the localizer ``cfg.localization`` (from the
    operator's rough pose): ``(reached, true path, localization error, last estimate)``."""
    if cfg.localization == "truth":
        done, path = _drive_true_pose(world, goal, cfg, progress)
        return done, path, None, None
    grid = twin_map(world)
    rng = np.random.default_rng(cfg.errors.seed)
    loc = twin_localizer(world, cfg.localization, rng, grid=grid)
    if recorder is not None:
        recorder.write_map(grid)
        loc = recorder.localizer(loc)
    loc.initialize(rough_initial_pose(world))  # the operator's rough pose (truth + error)
    nav_cfg = cfg.navigate.model_copy(update={"timeout": cfg.timeout})
    res = navigate(
        world,
        loc,
        grid,
        goal,
        nav_cfg,
        progress=progress,
        costmap=CostMap(twin_nav_map(world), nav_cfg.planner),
        truth=world.truth.base_pose2d,
    )
    path = list(res.trace["truth"]) or [start]
    estimate = res.trace["estimate"][-1] if len(res.trace["estimate"]) else None
    return res.reached, path, res.localization_error, estimate


def _teach_first(world: SimWorld, cfg: DemoConfig, progress: Progress | None):
    """One-shot teaching of ``cfg.mmpa_task`` at the goal site, then back to the start."""
    if cfg.mmpa_task is None:
        return None

    demo = get_demonstration(cfg.mmpa_task)
    if progress is not None:
        progress(f"teaching {demo.name} at site {cfg.goal_site}", 0.0)
    taught = teach_in_world(world, demo, cfg.goal_site, MMPAExperimentConfig(errors=cfg.errors))
    world.begin_session(1)  # the repeat: another day for the camera and the bench
    world.reset(site=cfg.start_site)
    return taught


def _run_mmpa(world: SimWorld, taught, estimate: Array | None, out: Path, progress) -> dict:
    """Automation stage at the parked pose: IPE, eq. 11, execution; scored on the truth."""

    if progress is not None:
        progress("MMPA: IPE and the taught path", 1.0)
    write_bundle(taught.task, out / "task", overwrite=True)
    res = automate(
        taught.task,
        world,
        T_map_base_now=None if estimate is None else se2_to_T(*estimate),
    )
    truth = inv(world.truth.T_map_arm_base()) @ taught.T_map_Bo
    e_r, e_t = pose_errors(res.ipe.dT_B if res.ipe is not None else None, truth)
    out_d = {
        "mmpa_task": taught.task.name,
        "mmpa_parking_offset_mm": round(float(np.linalg.norm(truth[:3, 3])) * 1e3, 2),
        "mmpa_ipe_ok": bool(res.ipe is not None and res.ipe.ok),
        "mmpa_ipe_iterations": res.ipe.n_iterations if res.ipe is not None else 0,
        "mmpa_ipe_compute_s": round(res.ipe.seconds_compute, 3) if res.ipe is not None else None,
        "mmpa_ipe_E_t_mm": None if np.isnan(e_t) else round(e_t * 1e3, 3),
        "mmpa_ipe_E_R": None if np.isnan(e_r) else round(e_r, 5),
    }
    if res.ok and res.joint_path is not None:
        rec = execute_joint_path(
            world.arm, world.gripper, res.joint_path, taught.task.path.gripper, record_hz=50.0
        )
        assert rec is not None
        err = key_error(world, taught, rec[0], rec[1], res.joint_path.t[taught.key_index])
        out_d["mmpa_tool_error_mm"] = round(err * 1e3, 3)
    else:
        out_d["mmpa_reason"] = res.reason
    return out_d


def _drive_true_pose(
    world: SimWorld, goal: Array, cfg: DemoConfig, progress: Progress | None
) -> tuple[bool, list[Array]]:
    """The first demo's controller: go-to-pose on the TRUE pose (a reference, not a robot)."""
    dt = 1.0 / cfg.control_rate
    start = world.truth.base_pose2d()
    dist0 = float(np.hypot(*(goal[:2] - start[:2])))
    path = [start]
    done = False
    while world.time < cfg.timeout:
        pose = world.truth.base_pose2d()
        v, w, done = go_to_pose_command(pose, goal, cfg.controller)
        if done:
            break
        world.base.set_velocity(v, w)
        world.step(dt)
        path.append(world.truth.base_pose2d())
        if progress is not None:
            progress("driving", 1.0 - float(np.hypot(*(goal[:2] - pose[:2]))) / max(dist0, 1e-9))
    return done, path


def snapshot(cfg: DemoConfig, site: str, out: str | Path) -> dict:
    """The demo's pictures for the robot parked exactly at ``site``."""
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    save_config(cfg, out / "config.yaml")
    scene = load_scene(cfg.scene)
    scene.site(site)  # unknown names fail here, listing the valid ones
    with SimWorld(scene=scene, errors=cfg.errors, site=site) as world:
        q_view = np.array(
            cfg.arm_view if cfg.arm_view is not None else world.nominal.arm.view_bench
        )
        extra = _capture(world, out, cfg, q_view)
        _topdown(world, out, extra, None, None, f"snapshot at site {site}")
        summary = {
            "profile": cfg.errors.profile,
            "site": site,
            "base_pose_6d": [round(float(x), 6) for x in T_to_vec6(world.truth.T_map_base_link())],
            "speed_bump": bool(world.speed_bump_enabled),
            **{k: v for k, v in extra.items() if not k.startswith("_")},
        }
    _write_summary(out, summary)
    return summary


def _view(cfg: DemoConfig, world: SimWorld) -> Array:
    return np.array(cfg.arm_view if cfg.arm_view is not None else world.nominal.arm.view_bench)


def _write_summary(out: Path, summary: dict) -> None:
    (out / "summary.json").write_text(json.dumps(summary, indent=2))
    lines = ["# mmpa run summary", "", "| quantity | value |", "|---|---|"]
    lines += [f"| {k} | {v} |" for k, v in summary.items()]
    files = sorted(p.name for p in out.iterdir())
    lines += ["", "Files: " + ", ".join(files)]
    (out / "summary.md").write_text("\n".join(lines) + "\n")
