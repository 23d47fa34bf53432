"""Shared harness of the paper 000 experiments: teach in the twin, park, run IPE / paths.

Teaching happens at the site's nominal park pose (Site 2' is taught at Site 2, without the
speed bump, as in the paper). Every automation trial parks the robot with an offset (sampled
from paper Table 2 by default), then runs the mission code, which sees only sensors and the
NOMINAL robot. Evaluation uses the simulator's truth:

- parking offset, truth: ``dT_B* = inv(T_map_Bk) T_map_Bo`` (the paper's ``T0 T1^-1``);
- IPE error: ``E_R``, ``E_t`` (eq. 12-13) of the estimated ``dT_B`` against ``dT_B*``;
- tool accuracy: the TRUE tool tip at the key pose (the needle on the dot) against the TRUE
  tip position recorded at teaching.

Trials (:func:`run_trial_groups`): each task is taught once per run (a task bundle in the run
folder's ``taught/``), every trial runs in a site world built from that bundle and is seeded
on its own (:meth:`TwinSite.begin_trial`: parking offset, camera session and frame noise,
scene change, park estimates, from ``(errors.seed, stream, trial + 1)``), so a trial's row is
the same alone, inside a run, or on another worker (:mod:`mmpa.harness.executor`).
Inside :func:`~mmpa.harness.recording.record_trials` (``mmpa experiment NAME --record
DIR``) every trial also records itself to a ROS 2 bag of its own
(:meth:`TwinSite.recording`), its row unchanged.
"""

from __future__ import annotations

import dataclasses
import json
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, model_validator

from mmpa.backends.bag import BagWriter, Recorder
from mmpa.backends.bag.record import ARM_RATE_HZ
from mmpa.backends.twin.error_model import ErrorModelConfig
from mmpa.backends.twin.operator import (
    Demonstration,
    demonstrate,
    load_demonstrations,
    rough_initial_pose,
    sampling_joints,
    true_tcp_in_map,
)
from mmpa.backends.twin.scene import SceneConfig, load_scene
from mmpa.backends.twin.twin_maps import twin_map, twin_nav_map
from mmpa.backends.twin.world import SimWorld
from mmpa.core.errors import ConfigError, UnknownNameError
from mmpa.core.geometry import (
    Array,
    T_to_se2,
    T_to_vec6,
    inv,
    se2_compose,
    se2_inv,
    se2_to_T,
)
from mmpa.harness.twin_localization import errors_follow_seed, twin_localizer
from mmpa.maps.occupancy import OccupancyGrid
from mmpa.missions.navigate import NavigateConfig, localize_standing, navigate
from mmpa.missions.repark import repark
from mmpa.missions.teach_repeat import (
    AutomationConfig,
    TeachConfig,
    automate,
    execute_joint_path,
    replay_tmma,
    teach,
)
from mmpa.navigation.planner import CostMap
from mmpa.tasks import Task

__all__ = [
    "SITE_DEMOS",
    "MMPAExperimentConfig",
    "Taught",
    "TwinSite",
]

#: which demonstration each site uses by default (Site 2' reuses the task taught at Site 2)
SITE_DEMOS = {"1": "needle_site1", "2": "needle_site2", "2'": "needle_site2"}
#: where the task of each automation site was taught
TEACH_SITE = {"1": "1", "2": "2", "2'": "2"}
#: paper 000 §4.3: beta per site
PAPER_BETA = {"1": 5, "2": 5, "2'": 10}


class MMPAExperimentConfig(BaseModel):
    """Common settings of the paper 000 experiments."""

    # site names look like numbers: --set "sites=[1, 2]" must give strings
    model_config = ConfigDict(extra="forbid", coerce_numbers_to_str=True)

    seed: int = 0
    trials: int | None = None  # per site; None: the paper's 30
    sites: list[str] = ["1", "2", "2'"]
    # sampled: paper Table 2 offsets; physics: drive from near Site 0 with mmpa's navigation
    # on the localization estimate (``localizer``) and park where it stops
    parking: Literal["sampled", "physics"] = "sampled"
    # a method of mmpa.localization.localizer: the park estimates, physics parking, re-parks
    localizer: str = "enhanced"
    start_sigma: tuple[float, float] = (0.05, float(np.deg2rad(5.0)))  # m, rad around Site 0
    # the park pose estimates at teaching and automation come from the ``localizer`` run on
    # this many scans while the base stands still (teaching: from the operator's rough pose;
    # a sampled park: from the navigation goal, the pose the robot was sent to)
    park_scans: int = Field(5, ge=1)
    max_yaw_offset_deg: float = Field(45.0, gt=0)  # redraw parking offsets beyond this
    repark_staging: float = Field(0.4, ge=0)  # m behind the goal: a re-park's first leg
    beta_per_site: bool = True  # beta 10 at Site 2' as in the paper (else automation.ipe.beta)
    teach: TeachConfig = TeachConfig()
    automation: AutomationConfig = AutomationConfig()
    errors: ErrorModelConfig = ErrorModelConfig()
    scene: str | None = None

    @model_validator(mode="after")
    def _robot_seed(self) -> MMPAExperimentConfig:
        # --seed picks the twin's robot instance (and so every draw) unless errors.seed is given
        return errors_follow_seed(self)

    def n_trials(self, default: int = 30) -> int:
        return self.trials or default


@dataclass
class Taught:
    """A task taught in the twin plus the truth needed to evaluate it."""

    task: Task
    demo: Demonstration
    T_map_Bo: Array  # TRUE arm base pose at teaching
    key_tcp_map: Array  # TRUE tool tip at the key pose (3,)
    key_index: int


def _truth_meta(taught_T_map_Bo: Array, key_tcp: Array, key_index: int, seed: int) -> dict:
    """Evaluation-only truth stored with a task taught in the twin (``twin_*`` meta keys; the
    algorithms never read them)."""
    return {
        "twin_T_map_arm_base": json.dumps(np.asarray(taught_T_map_Bo).tolist()),
        "twin_key_tcp_map": json.dumps(np.asarray(key_tcp).tolist()),
        "twin_key_index": int(key_index),
        "twin_seed": int(seed),
    }


def localize_parked(
    w: SimWorld,
    grid: OccupancyGrid,
    method: str,
    guess: Array,
    rng: np.random.Generator,
    cfg: MMPAExperimentConfig,
    wrap: Callable | None = None,
) -> Array:
    """The localization estimate ``[x, y, theta]`` of a parked robot: localizer ``method`` on
    ``grid``, initialized at ``guess`` (Nav2's initial covariance), run on ``cfg.park_scans``
    scans while the base stands still (:func:`~mmpa.missions.navigate.localize_standing`).
    ``wrap``: applied to the new localizer before use (a recorder's, to record it)."""
    loc = twin_localizer(w, method, rng, grid=grid)
    if wrap is not None:
        loc = wrap(loc)
    loc.initialize(np.asarray(guess, float))
    return localize_standing(w, loc, cfg.park_scans)


def teach_in_world(
    w: SimWorld, demo: Demonstration, teach_site: str, cfg: MMPAExperimentConfig
) -> Taught:
    """Park at ``teach_site``, let the twin's operator play ``demo`` while mmpa records the
    task (paper 000 §3.1); the truth for later scoring goes into the task's ``twin_*`` meta."""
    if demo.site != teach_site:
        raise ConfigError(
            f"demonstration {demo.name!r} belongs to site {demo.site!r}, not {teach_site!r}"
        )
    w.begin_session(0)  # the teaching session (DESIGN.md "Error model v2")
    w.reset(site=teach_site)
    rng = w.error_model.rng("teach_park_estimate")
    # the park pose estimate: the localizer, told the operator's rough pose, on a few scans
    est = localize_parked(w, twin_map(w), cfg.localizer, rough_initial_pose(w, rng), rng, cfg)
    q_sample = sampling_joints(w, demo)
    holder: dict = {}

    def record():
        rec = demonstrate(w, demo)
        holder["rec"] = rec
        return rec.t, rec.q, rec.gripper, rec.rate_hz

    task = teach(
        demo.name,
        teach_site,
        w,
        T_map_base_park=se2_to_T(*est),
        q_sample=q_sample,
        record=record,
        cfg=cfg.teach,
        description=demo.description,
    )
    rec = holder["rec"]
    key = true_tcp_in_map(w, rec.q[rec.key_index : rec.key_index + 1])[0]
    T_map_Bo = w.truth.T_map_arm_base()
    meta = _truth_meta(T_map_Bo, key, rec.key_index, cfg.errors.seed)
    task = dataclasses.replace(task, meta={**task.meta, **meta})
    return Taught(task, demo, T_map_Bo, key, rec.key_index)


class TwinSite:
    """One world for one automation site: teaches its task once (or takes a task taught in the
    twin before, with its ``twin_*`` truth), then parks and runs trials."""

    def __init__(
        self,
        cfg: MMPAExperimentConfig,
        site: str,
        scene: SceneConfig | None = None,
        task: Task | None = None,
        demo: str | None = None,
    ):
        if site not in TEACH_SITE and task is None:
            raise ConfigError(f"no MMPA task is defined for site {site!r}; use {list(SITE_DEMOS)}")
        self.cfg = cfg
        self.site = site
        self.scene = scene or load_scene(cfg.scene)
        teach_site = task.site if task is not None else TEACH_SITE.get(site, site)
        self.world = SimWorld(self.scene, errors=cfg.errors, site=teach_site)
        self.rng = self.world.error_model.rng(f"mmpa_trials_{site}")
        self.T_map_base_estimate: Array | None = None  # localization estimate after parking
        # a mmpa.backends.bag.Recorder while recording (:meth:`recording`)
        self.recorder: Any = None
        self.tmma_time_scale: float | None = None  # of the last TMMA replay (run_tmma)
        self._map_recorded = False
        if task is None:
            demos = load_demonstrations()
            name = demo or SITE_DEMOS[site]
            if name not in demos:
                raise UnknownNameError("demonstration", name, sorted(demos))
            self.taught = self._teach(demos[name], teach_site)
        else:
            self.taught = _taught_from_task(task, load_demonstrations())

    def close(self) -> None:
        self.world.close()

    def __enter__(self) -> TwinSite:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    @contextmanager
    def recording(self, path: str | Path, joint_rate_hz: float | None = None) -> Iterator[Path]:
        """Record what runs inside the ``with`` block to the ROS 2 bag ``path`` (``FILE.mcap``
        or a rosbag2 folder; overwritten) with a :class:`mmpa.backends.bag.Recorder`: the scans and
        camera frames as the algorithms read them, ``/joint_states`` and the arm's ``/tf``
        every ``1 / joint_rate_hz`` s through every arm motion (default: the task's path rate,
        at least :data:`mmpa.backends.bag.record.ARM_RATE_HZ`), ``/map`` and ``/reflectors``
        (latched, the localizers' map, on the first localization), every localizer's
        ``/initialpose``, ``/amcl_pose`` and ``/particlecloud`` (parking estimate, physics
        parking, re-parks), ``/tf_static`` and the truth on ``/truth/...``.

        :attr:`world` is the recording stand-in inside the block, the world itself again
        after it. The recorder draws nothing and steps the same physics, so the run is the
        run without recording. Yields ``path``."""

        if self.recorder is not None:
            raise ConfigError(f"site {self.site!r} is being recorded already")
        rate = joint_rate_hz or max(float(self.taught.task.path.rate_hz), ARM_RATE_HZ)
        world = self.world
        with (
            BagWriter(path, overwrite=True) as bag,
            Recorder(bag, world, joint_rate_hz=rate) as rec,
        ):
            self.world = rec.world()  # the same world, its readings recorded
            self.recorder, self._map_recorded = rec, False
            try:
                yield Path(path)
            finally:
                self.world, self.recorder = world, None

    def _recorded(self, loc: Any, grid: OccupancyGrid) -> Any:
        """``loc`` recorded while :meth:`recording` (and the map, the first time); else
        ``loc``."""
        rec = self.recorder
        if rec is None:
            return loc
        if not self._map_recorded:
            rec.write_map(grid)
            self._map_recorded = True
        return rec.localizer(loc)

    def begin_trial(self, trial: int) -> None:
        """Seed trial ``trial`` (>= 0) on its own: the world's episode streams (camera and
        lidar frame noise, joint repeatability, odometry; :meth:`SimWorld.set_episode`) and
        the site's draws (parking offset, park estimates, re-parks) all restart from
        ``(errors.seed, stream, trial + 1)``, so the trial gives the same row whether it runs
        alone, after other trials, or in another process (episode 0 is the teaching). Call
        :meth:`park` with ``session=trial + 1`` next."""
        k = int(trial)
        if k < 0:
            raise ConfigError(f"trial must be >= 0, got {trial}")
        w = self.world
        w.set_episode(k + 1)
        # the odometry samples every _CONTROL_EVERY physics steps counted since the world was
        # built; SimWorld.reset restarts the clock but not that count: restart it too
        w._steps = 0
        self.rng = w.error_model.rng(f"mmpa_trials_{self.site}", k + 1)
        self._park_loc_rng = w.error_model.rng(f"mmpa_park_estimate_{self.site}", k + 1)
        self._repark_rng = w.error_model.rng(f"mmpa_repark_{self.site}", k + 1)
        self.T_map_base_estimate = None

    def automation_config(self) -> AutomationConfig:
        a = self.cfg.automation
        if self.cfg.beta_per_site and self.site in PAPER_BETA:
            a = a.model_copy(
                update={"ipe": a.ipe.model_copy(update={"beta": PAPER_BETA[self.site]})}
            )
        return a

    def _teach(self, demo: Demonstration, teach_site: str) -> Taught:
        return teach_in_world(self.world, demo, teach_site, self.cfg)

    def park_by_driving(self) -> Array:
        """Start near Site 0 (told the rough pose), navigate to the site on the localization
        estimate, stop; the parking error is whatever the physics and localization leave."""

        w = self.world
        grid, costmap = self._navigation()
        s0 = w.scene.site("0").pose2d
        sx, sth = self.cfg.start_sigma
        w.reset(site="0", pose2d=s0 + self.rng.normal(0, [sx, sx, sth]))
        w.set_speed_bump(w.scene.site(self.site).speed_bump)  # Site 2' drives onto the bump
        loc = twin_localizer(w, self.cfg.localizer, self.rng, grid=grid)
        loc = self._recorded(loc, grid)
        loc.initialize(rough_initial_pose(w, self._loc_rng()))  # the operator's rough pose
        goal = w.scene.site(self.site).pose2d
        res = navigate(
            w, loc, grid, goal, NavigateConfig(), costmap=costmap, truth=w.truth.base_pose2d
        )
        w.base.stop()
        w.step(0.5)
        est = res.trace["estimate"][-1] if len(res.trace["estimate"]) else goal
        self.T_map_base_estimate = se2_to_T(*est)
        self.parked_pose2d = w.truth.base_pose2d()
        self.nav_reached = bool(res.reached)
        return T_to_vec6(self.parking_truth())

    def park(self, session: int | None = None) -> Array:
        """Park with a Table 2 offset (planar part; z, roll, pitch come from the terrain);
        returns the sampled 6D offset. Offsets with |yaw| above ``max_yaw_offset_deg`` are
        redrawn (a navigation stack would not report such a pose as parked). With
        ``parking="physics"`` the base drives there instead (:meth:`park_by_driving`).

        Every park is a new repeat session of the twin (``SimWorld.begin_session``): the
        camera's session errors and the scene's loose objects change; ``session`` (>= 1)
        numbers it, by default the count of parks so far."""
        self._parks = getattr(self, "_parks", 0) + 1
        self.world.begin_session(self._parks if session is None else int(session))
        if self.cfg.parking == "physics":
            return self.park_by_driving()
        w = self.world
        site = w.scene.site(self.site)
        for _ in range(100):
            off = w.error_model.sample_parking_offset(self.site, self.rng)
            if abs(off[5]) <= np.deg2rad(self.cfg.max_yaw_offset_deg):
                break
        # Table 2 is the relative pose of the ARM BASE, dT_B* = inv(T_map_Bk) T_map_Bo: put the
        # arm base at Bo (+) inv(offset) in the plane, the base_link where that puts it
        arm = np.array([*w.nominal.T_base_link_arm_base[:2, 3], 0.0])
        Bk = se2_compose(se2_compose(site.pose2d, arm), se2_inv(np.array([off[0], off[1], off[5]])))
        pose = se2_compose(Bk, se2_inv(arm))
        w.reset(site=self.site, pose2d=pose)
        self.parked_pose2d = pose
        self.T_map_base_estimate = se2_to_T(*self._localize_at_goal())
        return off

    def _loc_rng(self) -> np.random.Generator:
        """The generator of the park estimates (localizer particles, the operator's rough
        pose): a stream of its own, so that the trials' other draws stay as they were."""
        if not hasattr(self, "_park_loc_rng"):
            self._park_loc_rng = self.world.error_model.rng(f"mmpa_park_estimate_{self.site}")
        return self._park_loc_rng

    def _localize_at_goal(self) -> Array:
        """The localizer's estimate of the parked robot, initialized at the navigation goal
        (the site's park pose: where the robot was sent), after ``park_scans`` standing
        scans."""
        grid, _ = self._navigation()
        goal = self.world.scene.site(self.site).pose2d
        return localize_parked(
            self.world,
            grid,
            self.cfg.localizer,
            goal,
            self._loc_rng(),
            self.cfg,
            wrap=lambda loc: self._recorded(loc, grid),
        )

    def _navigation(self):

        if not hasattr(self, "_nav"):
            w = self.world
            grid = twin_map(w)
            self._nav = (grid, CostMap(twin_nav_map(w), NavigateConfig().planner))
        return self._nav

    def repark(self, motion: Array) -> Array | None:
        """Re-park by ``motion`` = ``[dx, dy, dtheta]`` (base_link frame) with mmpa's navigation
        on the ``localizer``'s estimate (initialized at the current estimate), as the robot's
        navigation stack would: first to a staging pose ``repark_staging`` m behind the goal,
        then straight in (a differential base that turns in place next to the bench or on the
        Site 2' bump stalls), to 1 cm / 0.01 rad (IPE measures what is left). Returns the new
        localization estimate ``T_map_base``."""

        w = self.world
        grid, costmap = self._navigation()
        est0 = (
            T_to_se2(self.T_map_base_estimate)
            if self.T_map_base_estimate is not None
            else self._localize_at_goal()  # no estimate given: ask the localizer
        )
        if not hasattr(self, "_repark_rng"):  # its own stream: trials stay as they were
            self._repark_rng = w.error_model.rng(f"mmpa_repark_{self.site}")
        loc = twin_localizer(w, self.cfg.localizer, self._repark_rng, grid=grid)
        loc = self._recorded(loc, grid)
        res = repark(
            w,
            loc,
            grid,
            est0,
            motion,
            self.cfg.repark_staging,
            costmap=costmap,
            truth=w.truth.base_pose2d,
        )
        w.step(0.5)
        self.parked_pose2d = w.truth.base_pose2d()
        self.truth_after_repark = self.parking_truth()  # evaluation only
        self.T_map_base_estimate = se2_to_T(*res.final_estimate)
        return self.T_map_base_estimate

    def parking_truth(self) -> Array:
        """``dT_B*``: maps taught arm-base coordinates to the current ones (4x4)."""
        return inv(self.world.truth.T_map_arm_base()) @ self.taught.T_map_Bo

    def key_error(self, q_record: Array, t_record: Array, t_key: float) -> float:
        """Distance (m) of the TRUE tool tip at time ``t_key`` of an executed recording from
        the taught TRUE tip."""
        return key_error(self.world, self.taught, t_record, q_record, t_key)

    def run_ipe(self, cfg: AutomationConfig | None = None, execute: bool = False):
        a = (cfg or self.automation_config()).model_copy(update={"execute": execute})
        w = self.world
        return automate(
            self.taught.task,
            w,
            cfg=a,
            record_hz=self.taught.task.path.rate_hz if execute else None,
            T_map_base_now=self.T_map_base_estimate,
            repark=self.repark,
        )

    def execute(self, res) -> float:
        """Execute an automation result's planned path; the key-pose tool error (m)."""
        w = self.world
        rec = execute_joint_path(
            w.arm,
            w.gripper,
            res.joint_path,
            self.taught.task.path.gripper,
            record_hz=self.taught.task.path.rate_hz,
        )
        assert rec is not None
        return self.key_error(rec[1], rec[0], res.joint_path.t[self.taught.key_index])

    def run_tmma(self) -> float:
        """Replay the taught joints (TMMA); the key-pose tool error (m). The replayed path's
        time scale (> 1: slowed down to the joint limits) is kept in :attr:`tmma_time_scale`."""
        w = self.world
        path, rec = replay_tmma(
            self.taught.task,
            w,
            T_flange_tool=w.nominal.gripper.T_flange_tcp,
            record_hz=self.taught.task.path.rate_hz,
        )
        self.tmma_time_scale = path.time_scale
        assert rec is not None
        t_key = path.t[self.taught.key_index]
        return self.key_error(rec[1], rec[0], t_key)


def key_error(w: SimWorld, taught: Taught, t_record: Array, q_record: Array, t_key: float) -> float:
    """Distance (m) of the TRUE tool tip at time ``t_key`` of an executed recording (encoder
    samples at the current base pose) from the TRUE tip recorded at teaching."""
    i = int(np.argmin(np.abs(np.asarray(t_record) - t_key)))
    tip = true_tcp_in_map(w, np.asarray(q_record)[i : i + 1])[0]
    return float(np.linalg.norm(tip - taught.key_tcp_map))


def _taught_from_task(task: Task, demos: dict[str, Demonstration]) -> Taught:
    m = task.meta
    missing = [
        k for k in ("twin_T_map_arm_base", "twin_key_tcp_map", "twin_key_index") if k not in m
    ]
    if missing:
        raise ConfigError(
            f"task {task.name!r} was not taught in the twin (no {', '.join(missing)}): the twin "
            "cannot evaluate it against the truth"
        )
    demo = demos.get(task.name) or next(iter(demos.values()))
    return Taught(
        task,
        demo,
        np.array(json.loads(str(m["twin_T_map_arm_base"]))),
        np.array(json.loads(str(m["twin_key_tcp_map"]))),
        int(m["twin_key_index"]),
    )
