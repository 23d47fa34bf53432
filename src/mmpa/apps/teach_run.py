"""``mmpa teach`` and ``mmpa run`` in the twin: one task, one automation run, with the truth.

``teach_task`` plays a demonstration (``backends/twin/worlds/demonstrations.yaml``) at its site and
saves
the recorded task in the store; ``run_task`` loads it, parks the robot with a paper Table 2
offset at the automation site (default: the task's site; Site 2' reuses Site 2's tasks), runs
the automation stage and reports the estimate and its error against the simulator's truth.
"""

from __future__ import annotations

from collections.abc import Callable
from contextlib import ExitStack
from pathlib import Path

import numpy as np

from mmpa.apps.navigate import drive_robot, localize_robot, robot_on_map
from mmpa.apps.path_report import check_adapted_path, write_dry_run
from mmpa.backends.bag.record import ARM_RATE_HZ
from mmpa.core.errors import MMPAError
from mmpa.core.geometry import Array, T_to_se2, T_to_vec6, se2_to_T
from mmpa.harness.ipe_eval import ipe_rows, offset_row
from mmpa.harness.twin_site import MMPAExperimentConfig, TwinSite
from mmpa.missions.teach_repeat import (
    AutomationConfig,
    AutomationResult,
    arm_stopped,
    automate,
    execute_joint_path,
)
from mmpa.robot.interfaces import MobileManipulator, require
from mmpa.robot.limits import JointLimits
from mmpa.tasks import Task, TaskStore

__all__ = [
    "RECORD_MIN_JOINT_HZ",
    "run_stored_task_on_robot",
    "run_task",
    "run_task_on_robot",
    "teach_task",
]

Progress = Callable[[str, float], None]

#: Hz: the least rate of the arm's /joint_states (and its /tf) in a recorded run; it runs at
#: the task path's rate (the rate the path is commanded and its execution's encoders are
#: read, 50 Hz in the twin's tasks) when that is higher
RECORD_MIN_JOINT_HZ = ARM_RATE_HZ


def teach_task(
    site: str,
    demo: str,
    *,
    db: str | Path | None = None,
    cfg: MMPAExperimentConfig | None = None,
    overwrite: bool = False,
) -> dict:
    """Teach demonstration ``demo`` at ``site`` in the twin and store it (name = ``demo``)."""
    cfg = cfg or MMPAExperimentConfig()
    with TwinSite(cfg, site, demo=demo) as ts, TaskStore(db) as store:
        task = ts.taught.task
        store.save(task, overwrite=overwrite)
        return {
            "profile": cfg.errors.profile,
            "task": task.name,
            "site": task.site,
            "store": str(store.path),
            "cloud_points": len(task.cloud),
            "path_waypoints": len(task.path.t),
            "path_seconds": round(float(task.path.t[-1]), 2),
            "rate_hz": task.path.rate_hz,
        }


def run_task(
    name: str,
    *,
    site: str | None = None,
    db: str | Path | None = None,
    cfg: MMPAExperimentConfig | None = None,
    trial: int = 0,
    tmma: bool = False,
    progress: Progress | None = None,
    record: str | Path | None = None,
) -> dict:
    """Park at ``site`` (default: the task's), run IPE + adapted path; errors vs the truth.

    ``record``: also record the run (parking, IPE, the executed path) to this ROS 2 bag
    (``FILE.mcap`` or a rosbag2 folder; overwritten; :meth:`TwinSite.recording`): the
    scans and camera frames as the algorithms read them, ``/joint_states`` and the arm's
    ``/tf`` at the task's path rate (at least :data:`RECORD_MIN_JOINT_HZ`) through every
    arm motion, ``/map`` and the parking localization (``/initialpose``, ``/amcl_pose``,
    ``/particlecloud``, ``map -> odom``), ``/tf_static`` and the ground truth on
    ``/truth/...``. The recorder draws nothing and steps the same physics, so the run and
    its summary are those of the run without ``record`` (plus ``bag``: the path)."""
    cfg = cfg or MMPAExperimentConfig()
    with TaskStore(db) as store:
        task = store.load(name)
    site = site or task.site
    with TwinSite(cfg, site, task=task) as ts, ExitStack() as stack:
        if record is not None:
            stack.enter_context(ts.recording(record))
        for _ in range(trial + 1):  # the trial-th parking draw of this seed
            ts.park()
        out: dict = {"profile": cfg.errors.profile, "task": name, "site": site, "trial": trial}
        if tmma:
            out["tmma_tool_error_mm"] = round(ts.run_tmma() * 1e3, 2)
            scale = ts.tmma_time_scale
            assert scale is not None
            out["tmma_time_scale"] = round(scale, 3)  # > 1: slowed down to the joint limits
            ts.world.reset(site=site, pose2d=ts.parked_pose2d)
        res = ts.run_ipe(execute=False)
        truth = ts.parking_truth()
        row, _ = ipe_rows(res.ipe, truth)
        park = offset_row(truth)
        out["parking_offset_6d"] = _vec(truth)
        out["parking_E_t_mm"] = round(park["park_E_t"] * 1e3, 1)
        out["ipe_ok"] = res.ipe.ok
        out["ipe_iterations"] = res.ipe.n_iterations
        out["ipe_compute_s"] = round(res.ipe.seconds_compute, 3)
        if res.ipe.dT_B is not None:
            out["estimate_6d"] = _vec(res.ipe.dT_B)
            out["estimate_E_t_mm"] = round(row["E_t"] * 1e3, 3)
            out["estimate_E_R"] = round(row["E_R"], 5)
        if res.ok:
            assert res.joint_path is not None
            out["path_time_scale"] = round(res.joint_path.time_scale, 3)  # > 1: slowed down
            out["tool_error_mm"] = round(ts.execute(res) * 1e3, 3)
            out["executed"] = True
        else:
            out["executed"] = False
            out["reason"] = res.reason
        if record is not None:
            out["bag"] = str(record)
        return out


def run_task_on_robot(
    robot: MobileManipulator,
    task: Task,
    *,
    cfg: AutomationConfig | None = None,
    confirm: Callable[[str], bool] | None = None,
    dry_run: Path | None = None,
    T_map_base_now: Array | None = None,
    progress: Progress | None = None,
    record_hz: float | None = None,
) -> dict:
    """The automation stage on any robot (the twin, ROS 2, the direct backend), standing
    where it was parked (a mobile base: navigated to the task's park pose before; a fixed
    base: where it is): IPE with the robot's camera and arm (its views move the arm), the
    adapted path (eq. 11, IK, retiming), then, BEFORE the arm moves along it, the check
    (:class:`~mmpa.apps.path_report.PathCheck`: the estimate, the adapted path's clearance
    from the taught one, the limits):

    - ``dry_run`` (a folder): write the adapted path (CSV, JSON) and a picture there and
      stop: nothing moves after the IPE views;
    - ``confirm`` (given): asked with the check's text; False: nothing moves;
    - a failed estimate, a path out of reach or beyond the limits, or an arm in protective
      or emergency stop: nothing moves (``reason`` says why).

    ``T_map_base_now``: the localization estimate of the base (IPE's first guess; None for a
    fixed base). Returns the summary (``executed``, ``reason``, the estimate, the check, the
    files written)."""
    require(robot, "arm", "camera", mission="running a task")
    cfg = (cfg or AutomationConfig()).model_copy(update={"execute": False})
    out: dict = {"task": task.name, "executed": False}
    why = arm_stopped(robot.arm)
    if why is not None:
        out["reason"] = f"the arm is in {why}: clear it, then run again"
        return out
    res = automate(task, robot, cfg=cfg, T_map_base_now=T_map_base_now, progress=progress)
    _ipe_summary(res, out)
    if not res.ok:
        out["reason"] = res.reason
        return out
    assert res.joint_path is not None and res.T_arm_base_tool is not None
    assert res.ipe is not None and res.ipe.dT_B is not None
    arm, rd = robot.arm, robot.description
    assert arm is not None
    check = check_adapted_path(
        task.path.T_arm_base_tool,
        res.T_arm_base_tool,
        res.joint_path,
        arm.joint_positions(),
        JointLimits.from_description(rd.arm),
    )
    text = "\n".join([f"task {task.name}: estimate dT_B {out['estimate_6d']}", *check.lines()])
    out["check"] = text
    if dry_run is not None:
        files = write_dry_run(
            dry_run, task.name, task.path.T_arm_base_tool, res.T_arm_base_tool,
            res.joint_path, res.ipe.dT_B, check,
        )  # fmt: skip
        out.update(reason="dry run: nothing moved after the IPE views", files=files)
        return out
    if not check.limits_ok:
        out["reason"] = f"the adapted path breaks the limits: {check.limits_reason}"
        return out
    if confirm is not None and not confirm(f"{text}\nmove the arm along the adapted path?"):
        out["reason"] = "not confirmed: nothing moved after the IPE views"
        return out
    return _execute(robot, task, res, out, record_hz)


def run_stored_task_on_robot(
    robot: MobileManipulator,
    name: str,
    *,
    db: str | Path | None = None,
    kind: str = "robot",
    confirm: Callable[[str], bool] | None = None,
    dry_run: Path | None = None,
    progress: Progress | None = None,
    robot_file: Path | None = None,
    start: str | None = None,
    drive: bool = True,
    seed: int = 0,
    timeout: float = 120.0,
) -> dict:
    """``mmpa --robot R run TASK`` on a hardware backend: load task ``name`` from the store
    and :func:`run_task_on_robot`. A robot with a base is localized first (its own
    localizer, or mmpa's of the robot file started at ``start``: where it stands, roughly;
    particles from ``seed``) and, with ``drive``, driven to the task's park pose (asked
    first with ``confirm``; at most ``timeout`` s of its clock); the estimate where it
    stands is IPE's first guess. ``drive`` False: from where it stands (localized when
    ``start`` is given or the robot runs its own localizer, else IPE without a first
    guess). A fixed base: where it is. Nothing moves after a drive that did not arrive."""
    with TaskStore(db) as store:
        task = store.load(name)
    out: dict = {"backend": kind}
    T_now = None
    localize = drive or start is not None or getattr(robot, "pose", None) is not None
    if robot.base is not None and localize:
        T_now = _park_on_robot(robot, task, robot_file, start, drive, confirm, seed, timeout, out)
        if T_now is None:
            return {**out, "task": task.name, "executed": False}
    out.update(
        run_task_on_robot(
            robot, task, confirm=confirm, dry_run=dry_run, progress=progress, T_map_base_now=T_now
        )
    )
    return out


def _park_on_robot(
    robot: MobileManipulator,
    task: Task,
    robot_file: Path | None,
    start: str | None,
    drive: bool,
    confirm: Callable[[str], bool] | None,
    seed: int,
    timeout: float,
    out: dict,
) -> Array | None:
    """Localize a robot with a base and, with ``drive``, drive it to ``task``'s park pose
    (:func:`mmpa.apps.navigate.drive_robot`); the estimate where it then stands (4x4), or
    None with ``out["reason"]`` (not confirmed, not arrived)."""
    on = robot_on_map(robot, robot_file, start, seed=seed)
    out["localizer"] = on.method
    goal = T_to_se2(task.T_map_base_park)
    out["park_goal"] = _pose2(goal)
    if drive:
        here = localize_robot(robot, on)
        question = f"drive the base from {_pose2(here)} to task {task.name}'s park pose?"
        if confirm is not None and not confirm(question):
            out["reason"] = "not confirmed: the base did not move"
            return None
        res, has_truth = drive_robot(robot, on, goal, timeout)
        out["drive_reached"] = res.reached
        out["drive_seconds"] = round(res.sim_time, 2)
        if has_truth:
            out["drive_parking_error_xy_mm"] = round(1e3 * float(res.parking_error_xy), 2)
            out["drive_parking_error_yaw_deg"] = round(float(np.rad2deg(res.parking_error_yaw)), 3)
        if not res.reached:
            out["reason"] = f"the base did not reach the park pose: {res.reason}"
            return None
    est = localize_robot(robot, on)
    out["park_estimate"] = _pose2(est)
    return se2_to_T(*est)


def _pose2(p: Array) -> str:
    return f"[{p[0]:.3f} m, {p[1]:.3f} m, {np.rad2deg(p[2]):.2f} deg]"


def _ipe_summary(res: AutomationResult, out: dict) -> None:
    ipe = res.ipe
    out["ipe_ok"] = bool(ipe is not None and ipe.ok)
    if ipe is not None:
        out["ipe_iterations"] = ipe.n_iterations
        if ipe.dT_B is not None:
            out["estimate_6d"] = _vec(ipe.dT_B)
    if res.joint_path is not None:
        out["path_time_scale"] = round(res.joint_path.time_scale, 3)


def _execute(
    robot: MobileManipulator,
    task: Task,
    res: AutomationResult,
    out: dict,
    record_hz: float | None,
) -> dict:
    """Run the adapted path; a stop or a refusal on the way ends it with the reason."""
    arm = robot.arm
    assert arm is not None and res.joint_path is not None
    why = arm_stopped(arm)
    if why is not None:
        out["reason"] = f"the arm is in {why}: clear it, then run again"
        return out
    try:
        rec = execute_joint_path(
            arm, robot.gripper, res.joint_path, task.path.gripper, record_hz=record_hz
        )
    except MMPAError as e:
        out["reason"] = f"stopped while moving: {e}"
        return out
    out["executed"] = True
    if rec is not None:
        out["record"] = rec
    return out


def _vec(T: np.ndarray) -> str:
    v = T_to_vec6(T)
    return (
        f"[{v[0] * 1e3:.1f}, {v[1] * 1e3:.1f}, {v[2] * 1e3:.1f}] mm, "
        f"[{np.rad2deg(v[3]):.2f}, {np.rad2deg(v[4]):.2f}, {np.rad2deg(v[5]):.2f}] deg"
    )
