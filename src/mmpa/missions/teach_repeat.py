"""MMPA (paper 000 §3): one-shot teaching and the automation stage, over robot interfaces.

Teaching (§3.1) records a :class:`~mmpa.tasks.Task`: the park pose estimate ``L_i(vehicle)``,
the wrist camera's colored cloud ``X_i(O)`` at the sampling joints, the nominal ``T_B_C`` there,
and the tool path ``Path_i(O)`` from the encoders at ``f_i`` Hz through the NOMINAL kinematics.

Automation (§3.2, after the base has parked): IPE estimates ``dT_B``; the taught tool poses map
by eq. 11 (``T_Bk_tool = dT_B T_Bo_tool``); IK and time parameterization turn them into a
joint trajectory; the arm runs it. Nothing moves unless IPE returned True and every waypoint
is reachable without a joint jump. TMMA (Nair et al. 2019) replays the taught joints as they are.
"""

from __future__ import annotations

import itertools
import logging
import time
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np
from pydantic import BaseModel, ConfigDict, Field

from mmpa.core.errors import InvalidInputError, JointLimitError, MMPAError, UnreachableError
from mmpa.core.geometry import Array, T_to_se2, inv
from mmpa.ipe import transform_path
from mmpa.ipe.loop import IPE, IPEConfig, IPEResult, capture_cloud
from mmpa.planning import JointPath, PathPlanConfig, plan_joint_path, retime
from mmpa.robot.description import ArmDescription
from mmpa.robot.interfaces import Arm, Gripper, MobileManipulator, require
from mmpa.robot.kinematics import fk
from mmpa.tasks import Task, ToolPath

_log = logging.getLogger(__name__)

__all__ = [
    "MAX_TOOL_MISMATCH",
    "AutomationConfig",
    "AutomationResult",
    "TeachConfig",
    "arm_stopped",
    "automate",
    "check_tool_path",
    "execute_joint_path",
    "joint_recorder",
    "repark_motion",
    "replay_tmma",
    "teach",
    "tool_path_mismatch",
    "trajectory_recorder",
]

#: a start/stop button of a person's demonstration: True once per press (a key, an input)
Button = Callable[[], bool]

Progress = Callable[[str, float], None]
#: a re-park request: drive the base by ``[dx, dy, dtheta]`` (m, rad) in its current base_link
#: frame; returns the new localization estimate ``T_map_base`` (4x4) or None
Repark = Callable[[Array], "Array | None"]
#: a demonstration recorder: runs the demonstration, returns (t (M,), q (M, 6), gripper (M,), f)
Recorder = Callable[[], tuple[Array, Array, Array, float]]
#: the largest disagreement (m, rad) between a task's joint path (FK of the arm model) and its
#: tool path that still counts as one task: 0 for a task taught and run with one arm model;
#: up to 9.3 mm / 0.67 deg when the model differs by the twin's harsh DH error (1 mm,
#: 0.1 deg; 30 draws over a taught path; 4.6 mm / 0.34 deg realistic): twice that
MAX_TOOL_MISMATCH = (0.02, float(np.deg2rad(2.0)))


class TeachConfig(BaseModel):
    """One-shot teaching: how the scene cloud is sampled."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    frames: int = Field(16, ge=1)  # captures averaged into X_i(O) (once per task: 0.5 s at 30 fps)
    min_depth: float = Field(0.2, gt=0)
    max_depth: float = Field(1.5, gt=0)


def trajectory_recorder(
    t: Array, q: Array, rate_hz: float, gripper: Array | None = None
) -> Recorder:
    """A teach-in ``record`` source from a recorded joint trajectory (a person's freedrive
    demonstration read from a bag or a file): ``t`` (N,) s, ``q`` (N, 6) rad, ``gripper``
    (N,) in [0, 1] or None (open). Checked when called; times are taken from 0."""
    t = np.asarray(t, dtype=float)
    q = np.asarray(q, dtype=float)
    if t.ndim != 1 or q.shape != (len(t), 6) or len(t) < 2:
        raise InvalidInputError(f"need t (N,) and q (N, 6) with N >= 2, got {t.shape}, {q.shape}")
    g = np.zeros(len(t)) if gripper is None else np.asarray(gripper, dtype=float)

    def record() -> tuple[Array, Array, Array, float]:
        return t - t[0], q.copy(), g.copy(), float(rate_hz)

    return record


def joint_recorder(
    robot: MobileManipulator,
    rate_hz: float,
    button: Button,
    *,
    max_seconds: float = 600.0,
    gripper: Callable[[], float] | None = None,
) -> Recorder:
    """A teach-in ``record`` source for any backend: a person guides the arm (a teach
    pendant's freedrive, a hand-guided cobot) while ``robot.arm.joint_positions()`` is
    sampled every ``1 / rate_hz`` s of the robot's clock (``robot.step``), from the first
    press of ``button`` (``t = 0``) to the first sample at or after the second press.
    ``gripper`` (optional) gives the gripper state in [0, 1] at each sample. More than
    ``max_seconds``: :class:`MMPAError`. For a UR over RTDE,
    :meth:`mmpa.backends.ur.URArm.record_freedrive` does the same at the controller's rate."""
    require(robot, "arm", mission="recording a demonstration")
    arm = robot.arm
    assert arm is not None
    if not (np.isfinite(rate_hz) and rate_hz > 0):
        raise InvalidInputError(f"rate_hz must be a positive rate, got {rate_hz}")
    dt = 1.0 / float(rate_hz)

    def record() -> tuple[Array, Array, Array, float]:
        t0 = robot.time
        while not button():
            if robot.time - t0 > max_seconds:
                raise MMPAError(f"the demonstration did not start within {max_seconds:g} s")
            robot.step(dt)
        t: list[float] = []
        q: list[Array] = []
        g: list[float] = []
        stop, k = False, 0
        while True:
            t.append(k * dt)
            q.append(np.asarray(arm.joint_positions(), dtype=float))
            g.append(0.0 if gripper is None else float(gripper()))
            if stop:
                break
            if k * dt > max_seconds:
                raise MMPAError(f"the demonstration did not end within {max_seconds:g} s")
            robot.step(dt)
            k += 1
            stop = button()
        return np.array(t), np.array(q), np.array(g), float(rate_hz)

    return record


def arm_stopped(arm: Arm | None) -> str | None:
    """Why ``arm``'s controller will not move (a protective or emergency stop: a
    :class:`~mmpa.robot.interfaces.StreamingArm`'s ``stopped()``), or None (an arm that
    does not report it: None)."""
    stopped = getattr(arm, "stopped", None)
    return None if stopped is None else stopped()


def teach(
    name: str,
    site: str,
    robot: MobileManipulator,
    *,
    T_map_base_park: Array,
    q_sample: Array,
    record: Recorder,
    cfg: TeachConfig | None = None,
    description: str = "",
    robot_id: str = "twin",
    meta: dict | None = None,
) -> Task:
    """Record a task (paper 000 §3.1): sample the scene at ``q_sample``, then record the
    demonstration with ``robot``'s arm and camera (its nominal description gives the
    kinematics). ``T_map_base_park`` is the localization estimate of the park pose."""
    require(robot, "arm", "camera", mission="teaching")
    arm, camera, rd = robot.arm, robot.camera, robot.description
    assert arm is not None and camera is not None
    cfg = cfg or TeachConfig()
    arm.move_joints(np.asarray(q_sample, dtype=float))
    q_meas = arm.joint_positions()
    cloud = capture_cloud(camera, cfg.frames, cfg.min_depth, cfg.max_depth)
    if len(cloud) < 1000:
        raise InvalidInputError(
            f"the camera sees only {len(cloud)} points at the sampling pose: point it at the "
            f"work area (within {cfg.min_depth}-{cfg.max_depth} m)"
        )
    T_B_C = fk(rd.arm.dh, q_meas) @ rd.camera.T_flange_camera
    t, q, g, rate = record()
    T_B_tool = fk(rd.arm.dh, q, rd.gripper.T_flange_tcp)
    path = ToolPath(t=t, q=q, T_arm_base_tool=T_B_tool, rate_hz=rate, gripper=g)
    return Task(
        name=name,
        site=site,
        T_map_base_park=np.asarray(T_map_base_park, dtype=float),
        q_sample=q_meas,
        T_arm_base_camera=T_B_C,
        cloud=cloud,
        path=path,
        robot_id=robot_id,
        description=description,
        meta=meta or {},
    )


class AutomationConfig(BaseModel):
    """The automation stage after parking: IPE, then path adaptation and execution."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    ipe: IPEConfig = IPEConfig()
    plan: PathPlanConfig = PathPlanConfig()
    execute: bool = True
    localization_prior: bool = True  # first IPE view from the base localization (paper: no)
    # when IPE succeeded but the adapted path is out of the arm's reach (a parking far off),
    # stow the arm, drive the base by the IPE estimate and run IPE again, at most this often
    # (paper: no re-park; 0 turns it off). Only with a ``repark`` callback.
    max_reparks: int = Field(1, ge=0)

    @classmethod
    def paper(cls, beta: int | None = None) -> AutomationConfig:
        """The paper's automation stage: :meth:`IPEConfig.paper` (with ``beta`` when given),
        no localization prior for the first view, no re-park."""
        ipe = IPEConfig.paper(**({} if beta is None else {"beta": beta}))
        return cls(ipe=ipe, localization_prior=False, max_reparks=0)


@dataclass
class AutomationResult:
    """``ok`` when IPE converged and the path was planned (and executed when asked);
    ``reason`` says why not. ``record``: encoder samples while executing (when recorded)."""

    ok: bool
    reason: str
    ipe: IPEResult | None
    T_arm_base_tool: Array | None = None  # adapted path (N, 4, 4)
    joint_path: JointPath | None = None
    executed: bool = False
    record: tuple[Array, Array] | None = None
    seconds: dict[str, float] = field(default_factory=dict)
    #: base motions ``[dx, dy, dtheta]`` requested by re-parks, and the IPE results before them
    reparks: list[Array] = field(default_factory=list)
    ipe_before_repark: list[IPEResult] = field(default_factory=list)


def repark_motion(dT_B: Array, T_base_link_arm_base: Array) -> Array:
    """Planar base motion that undoes a parking offset: ``[dx, dy, dtheta]`` (m, rad) in the
    CURRENT base_link frame.

    ``dT_B = inv(T_map_Bk) T_map_Bo`` (eq. 9-10) maps taught arm-base coordinates to the
    current ones, so the arm base returns to its taught pose when ``T_map_Bk' = T_map_Bk dT_B``;
    with ``T_bl_B`` the arm's mounting, the base_link moves by
    ``T_bl_B dT_B inv(T_bl_B)`` (expressed in the current base_link frame), of which the
    planar part (x, y, yaw) is what a differential base can do.
    """
    M = np.asarray(T_base_link_arm_base, dtype=float)
    return T_to_se2(M @ np.asarray(dT_B, dtype=float) @ inv(M))


def automate(
    task: Task,
    robot: MobileManipulator,
    *,
    cfg: AutomationConfig | None = None,
    record_hz: float | None = None,
    progress: Progress | None = None,
    T_map_base_now: Array | None = None,
    repark: Repark | None = None,
) -> AutomationResult:
    """IPE (Fig. 4), eq. 11, IK + time parameterization, execution (§3.2.2-3.2.4).

    ``T_map_base_now``: the localization estimate of the current park pose. With
    ``cfg.localization_prior`` it gives IPE its first guess,
    ``dT_B ~ inv(T_map_base_now T_base_arm) (T_map_base_park T_base_arm)``.

    ``repark``: when IPE succeeded but the adapted path is out of reach, the arm goes home and
    the base is asked to move by :func:`repark_motion` of the estimate; then IPE runs again
    (at most ``cfg.max_reparks`` times). Nothing runs on the path until a plan succeeded."""
    require(robot, "arm", "camera", mission="the automation stage (IPE and the adapted path)")
    arm, camera, gripper, rd = robot.arm, robot.camera, robot.gripper, robot.description
    assert arm is not None and camera is not None
    cfg = cfg or AutomationConfig()
    t0 = time.perf_counter()
    T_ba = rd.T_base_link_arm_base
    out = AutomationResult(False, "", None, seconds={"ipe": 0.0})
    while True:
        prior = None
        if T_map_base_now is not None and cfg.localization_prior:
            prior = inv(np.asarray(T_map_base_now, float) @ T_ba) @ (task.T_map_base_park @ T_ba)
        t_ipe = time.perf_counter()
        ipe = IPE(rd, cfg.ipe).run(
            arm, camera, task.q_sample, task.T_arm_base_camera, task.cloud, progress, prior
        )
        out.seconds["ipe"] += time.perf_counter() - t_ipe
        out.ipe = ipe
        if not ipe.ok or ipe.dT_B is None:
            out.reason = f"IPE failed: {ipe.reason}"
            _log.warning("task %s: %s; the arm does not move", task.name, out.reason)
            return out
        _log.info(
            "task %s: IPE converged in %d iterations, parking offset %.1f mm / %.2f deg",
            task.name,
            ipe.n_iterations,
            1e3 * float(np.linalg.norm(ipe.dT_B[:3, 3])),
            float(np.rad2deg(np.arccos(np.clip((np.trace(ipe.dT_B[:3, :3]) - 1) / 2, -1, 1)))),
        )
        T_new = transform_path(ipe.dT_B, task.path.T_arm_base_tool)
        out.T_arm_base_tool = T_new
        try:
            q_path = plan_joint_path(
                rd.arm, T_new, arm.joint_positions(), rd.gripper.T_flange_tcp, cfg.plan
            )
            out.joint_path = retime(task.path.t, q_path, rd.arm, cfg.plan)
            _warn_slowed(task, out.joint_path, "the adapted path")
            break
        except (UnreachableError, JointLimitError) as e:
            out.reason = f"path planning failed: {e}"
            _log.warning("task %s: %s", task.name, out.reason)
            if repark is None or len(out.reparks) >= cfg.max_reparks:
                return out
        except InvalidInputError as e:
            out.reason = f"path planning failed: {e}"
            return out
        motion = repark_motion(ipe.dT_B, T_ba)
        if progress is not None:
            progress(
                f"path out of reach: re-parking by ({motion[0]:+.3f} m, {motion[1]:+.3f} m, "
                f"{np.rad2deg(motion[2]):+.1f} deg)",
                0.0,
            )
        _log.info("task %s: re-parking by %s (x m, y m, yaw rad)", task.name, np.round(motion, 3))
        arm.move_joints(np.asarray(rd.arm.home, dtype=float))
        out.reparks.append(motion)
        out.ipe_before_repark.append(ipe)
        T_map_base_now = repark(motion)
    out.reason = ""
    out.ok = True
    if cfg.execute:
        out.record = execute_joint_path(
            arm, gripper, out.joint_path, task.path.gripper, record_hz=record_hz
        )
        out.executed = True
        _log.info("task %s: executed the adapted path (%.1f s)", task.name, out.joint_path.duration)
    out.seconds["total"] = time.perf_counter() - t0
    return out


def execute_joint_path(
    arm: Arm,
    gripper: Gripper | None,
    path: JointPath,
    gripper_states: Array | None,
    record_hz: float | None = None,
) -> tuple[Array, Array] | None:
    """Move to the path start (jerk-limited), then follow it; the gripper closes or opens
    between segments where the taught gripper state changes. Returns the recording (time from
    the path start, joints) when ``record_hz`` is given."""
    q, t = path.q, path.t
    g = None if gripper_states is None else np.asarray(gripper_states, dtype=float)
    if g is not None and (g.shape != (len(q),)):
        raise InvalidInputError(f"gripper states must have shape ({len(q)},), got {g.shape}")
    if g is not None and gripper is None and np.any(g > 0.5):
        raise MMPAError("the taught path uses the gripper but this robot has none")
    arm.move_joints(q[0])
    if gripper is not None and g is not None:
        (gripper.close if g[0] > 0.5 else gripper.open)()
    cuts = [0] if g is None else [0, *(np.flatnonzero(np.diff(g > 0.5)) + 1).tolist()]
    cuts.append(len(q))
    rec_t, rec_q = [], []
    for a, b in itertools.pairwise(cuts):
        lo = max(a - 1, 0)
        if b - lo >= 2:
            r = arm.follow(t[lo:b], q[lo:b], record_hz=record_hz)
            if r is not None:
                rec_t.append(r[0] + t[lo])
                rec_q.append(r[1])
        if gripper is not None and g is not None and b < len(q):
            (gripper.close if g[b] > 0.5 else gripper.open)()
    if record_hz is None or not rec_t:
        return None
    return np.concatenate(rec_t), np.concatenate(rec_q)


def replay_tmma(
    task: Task,
    robot: MobileManipulator,
    *,
    T_flange_tool: Array,
    record_hz: float | None = None,
    max_mismatch: tuple[float, float] = MAX_TOOL_MISMATCH,
) -> tuple[JointPath, tuple[Array, Array] | None]:
    """TMMA baseline: replay the taught joint sequence without correction (the sampling pose,
    then the recorded joint path), as Nair et al. 2019 replay a recorded arm motion.

    First the joints must be the taught tool path: :func:`check_tool_path` with
    ``T_flange_tool`` (the tool the path was taught with) refuses a task whose joint path
    disagrees with its tool path by more than ``max_mismatch`` before anything moves. The
    recorded path is then retimed to the full joint limits of ``robot``'s arm model (a taught path
    recorded from the arm itself needs no stretch: ``time_scale`` 1; an edited or corrupted
    one is slowed down, with a warning, never played past the limits). Returns the executed
    ``JointPath`` (its ``time_scale``) and the recording (``None`` without ``record_hz``).
    """
    require(robot, "arm", mission="the TMMA replay")
    arm, gripper, arm_model = robot.arm, robot.gripper, robot.description.arm
    assert arm is not None
    mismatch = check_tool_path(task, arm_model, T_flange_tool, max_mismatch)
    full = PathPlanConfig(velocity_scale=1.0, acceleration_scale=1.0)
    path = retime(task.path.t, task.path.q, arm_model, full)
    _warn_slowed(task, path, "the TMMA replay")
    _log.info("task %s: joints vs tool path %.2f mm / %.3f deg", task.name, *mismatch)
    arm.move_joints(task.q_sample)
    rec = execute_joint_path(arm, gripper, path, task.path.gripper, record_hz=record_hz)
    return path, rec


def tool_path_mismatch(
    task: Task, arm_model: ArmDescription, T_flange_tool: Array
) -> tuple[float, float, int]:
    """How far the task's joint path is from its tool path: the largest position (m) and
    rotation (rad) difference between ``fk(arm_model.dh, q_i) T_flange_tool`` and the stored
    ``T_arm_base_tool[i]``, and the waypoint ``i`` of the largest position difference."""
    T = fk(arm_model.dh, task.path.q, np.asarray(T_flange_tool, dtype=float))
    P = task.path.T_arm_base_tool
    d = np.linalg.norm(T[:, :3, 3] - P[:, :3, 3], axis=1)
    cos = (np.einsum("nij,nij->n", T[:, :3, :3], P[:, :3, :3]) - 1.0) / 2.0
    i = int(np.argmax(d))
    return float(d[i]), float(np.arccos(np.clip(cos, -1.0, 1.0)).max()), i


def check_tool_path(
    task: Task,
    arm_model: ArmDescription,
    T_flange_tool: Array,
    max_mismatch: tuple[float, float] = MAX_TOOL_MISMATCH,
) -> tuple[float, float]:
    """Refuse (InvalidInputError) a task whose joint path and tool path disagree by more
    than ``max_mismatch`` (m, rad; :func:`tool_path_mismatch`): edited or damaged, or taught
    with another arm model or tool. Returns the disagreement (mm, deg)."""
    d, ang, i = tool_path_mismatch(task, arm_model, T_flange_tool)
    if d > max_mismatch[0] or ang > max_mismatch[1]:
        raise InvalidInputError(
            f"task {task.name!r}: its joint path and its tool path disagree by {d * 1e3:.1f} mm"
            f" / {np.rad2deg(ang):.2f} deg (waypoint {i}; the arm model's FK of the joints vs "
            f"the stored tool poses; allowed {max_mismatch[0] * 1e3:g} mm / "
            f"{np.rad2deg(max_mismatch[1]):g} deg): the task was edited or damaged, or taught "
            "with another arm model or tool; re-teach it or use the robot file it was taught with"
        )
    return d * 1e3, float(np.rad2deg(ang))


def _warn_slowed(task: Task, path: JointPath, what: str) -> None:
    """Log (warning) that ``path`` had to be slowed down to respect the joint limits."""
    if path.time_scale > 1.0 + 1e-9:
        _log.warning(
            "task %s: %s is slowed %.2fx to respect the joint limits (taught %.2f s, runs %.2f s)",
            task.name,
            what,
            path.time_scale,
            path.duration / path.time_scale,
            path.duration,
        )
