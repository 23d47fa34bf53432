"""``mmpa experiment grasp``: paper 001 Table 3, detection and grasp success per object and
light condition, in the twin.

Per trial: the robot parks in front of the grasp desk (seeded jitter), the target object and
up to three other objects plus distractors lie at random poses on the reachable part of the
desk, the light is set, the arm looks down at the desk; then the tracking grasp
(:class:`mmpa.servo.grasp.TrackingGrasp`) detects, servos, descends, closes and lifts.
Detection success: the target is detected in the first frame (``found_view`` in the rows: 0
the first view, k >= 1 after k second views, -1 never; ``views``: second views taken, see
``GraspConfig.search.views``). Grasp success: after the lift the object is still held off the
desk 2 s later, in the physics (not a distance threshold).
"""

from __future__ import annotations

import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from typing import Any

import numpy as np
from pydantic import BaseModel, Field

from mmpa.backends.bag.record import ARM_RATE_HZ
from mmpa.backends.twin.error_model import ErrorModelConfig
from mmpa.backends.twin.world import SimWorld
from mmpa.core.errors import UnknownNameError
from mmpa.harness.perception_data import (
    DESK_PARK,
    LOOK_HEIGHT,
    LOOK_TARGET,
    REGION,
    _footprint,
    boxes_from_segmentation,
    desk_frame,
    desk_object_names,
    random_table_scene,
)
from mmpa.harness.recording import recording_folder, trial_recorder
from mmpa.harness.runner import Context, Outcome, markdown_table, run_trials
from mmpa.perception import CLASSES, LIGHTING_CONDITIONS
from mmpa.robot.description import default_robot
from mmpa.servo.config import GraspConfig
from mmpa.servo.grasp import TrackingGrasp, look_configuration

PAPER = "paper 001 Table 3 (success rate per object and light condition, 20 trials each)"

#: Table 3 (paper object names mapped to ours): success per light condition
TABLE3 = {
    "yida_bottle": {"high": 0.90, "normal": 0.95, "dark": 0.80},
    "glue_stick": {"high": 0.80, "normal": 0.90, "dark": 0.80},
    "tennis_ball": {"high": 0.95, "normal": 0.95, "dark": 0.70},
    "cube": {"high": 0.85, "normal": 0.90, "dark": 0.75},
    "water_bottle": {"high": 0.75, "normal": 0.85, "dark": 0.75},
    "blue_stick": {"high": 0.85, "normal": 0.90, "dark": 0.50},
    "paper_cup": {"high": 0.90, "normal": 0.90, "dark": 0.65},
}
#: the wrist camera's stream profile in the tracking grasp (width, height): the detector's
#: input size, so each tick renders and corrupts a quarter of the 640x480 pixels (the servo
#: loop reaches 20 Hz in the twin, ``benchmarks/bench_perception.py``); detection success on
#: the grasp experiment's first views is the same as at 640x480 (measured, see the report)
SERVO_RESOLUTION = (320, 240)


class Config(BaseModel):
    seed: int = Field(0, ge=0)  # every random draw flows from it (numpy: >= 0)
    trials: int | None = None  # per object and light condition; None: the paper's 20
    objects: list[str] = Field(default_factory=lambda: list(CLASSES))
    lighting: list[str] = Field(default_factory=lambda: list(LIGHTING_CONDITIONS))
    weights: str | None = None  # detector weights; None: shipped model; "oracle": truth boxes
    preprocess_dark: bool = False  # measured: hurts the shipped detector (see perception)
    use_predictor: bool = True
    others: int = 2  # other objects on the desk besides the target
    max_time: float = 15.0  # s of simulated time per trial (all its attempts)
    threads: int = 1  # torch threads of the detector
    servo: GraspConfig = Field(default_factory=GraspConfig)  # the tracking grasp's settings
    errors: ErrorModelConfig = ErrorModelConfig()  # the twin robot (its seed: the instance)

    def n_trials(self) -> int:
        return 20 if self.trials is None else self.trials


class Operator:
    """Moves an object over the desk at ``speed`` m/s with random direction changes
    (every 0.5-1.5 s), bouncing off the region's edges, until :meth:`release`."""

    def __init__(self, world: Any, name: str, speed: float, rng: np.random.Generator) -> None:

        self.world, self.name, self.speed, self.rng = world, name, speed, rng
        self.T_desk, _, _ = desk_frame(world)
        p = world.truth.T_map_object(name)[:3, 3]
        self.xy = (np.linalg.inv(self.T_desk) @ np.append(p, 1.0))[:2]
        self.z = float(p[2])
        self.heading = float(rng.uniform(-np.pi, np.pi))
        self.next_turn = float(rng.uniform(0.5, 1.5))
        self.active = speed > 0

    def release(self) -> None:
        if self.active:
            self.active = False
            self._place(np.zeros(2))

    def resume(self) -> None:
        """Take the released object again where it lies (pulled back into the region) and go
        on moving it in a new random direction: the robot missed and tries again. An object
        knocked off the desk stays there."""
        if self.active or self.speed <= 0:
            return
        p = self.world.truth.T_map_object(self.name)[:3, 3]
        if p[2] < self.z - 0.02:  # fell off the desk (or lies in the gripper's way)
            return
        x0, x1, y0, y1 = REGION
        xy = (np.linalg.inv(self.T_desk) @ np.append(p, 1.0))[:2]
        self.xy = np.clip(xy, [x0, y0], [x1, y1])
        self.heading = float(self.rng.uniform(-np.pi, np.pi))
        self.next_turn = float(self.rng.uniform(0.5, 1.5))
        self.active = True

    def _place(self, v: np.ndarray) -> None:
        p = self.T_desk[:3, :3] @ np.array([*self.xy, 0.0]) + self.T_desk[:3, 3]
        p[2] = self.z
        vel = self.T_desk[:3, :3] @ np.array([*v, 0.0])
        self.world.place_object(self.name, p, velocity=vel)

    def step(self, dt: float) -> None:
        if not self.active:
            self.world.step(dt)
            return
        h = 0.01
        for _ in range(max(round(dt / h), 1)):
            self.next_turn -= h
            if self.next_turn <= 0:
                self.heading += float(self.rng.choice([-1, 1]) * self.rng.uniform(0.5, 1.6))
                self.next_turn = float(self.rng.uniform(0.5, 1.5))
            v = self.speed * np.array([np.cos(self.heading), np.sin(self.heading)])
            nxt = self.xy + v * h
            x0, x1, y0, y1 = REGION
            if not (x0 <= nxt[0] <= x1):
                self.heading = np.pi - self.heading
            if not (y0 <= nxt[1] <= y1):
                self.heading = -self.heading
            v = self.speed * np.array([np.cos(self.heading), np.sin(self.heading)])
            self.xy = np.clip(self.xy + v * h, [x0, y0], [x1, y1])
            self._place(v)
            self.world.step(h)


def run_grasp(
    world: Any,
    grasper: Any,
    name: str,
    wait: Callable[[float], None],
    on_event: Callable[..., None] | None = None,
    resolution: tuple[int, int] = SERVO_RESOLUTION,
) -> Any:
    """``grasper.run`` on the twin's robot, the wrist camera streaming ``resolution`` (the
    camera's own resolution restored after); ``wait(dt)`` advances the world."""
    before = world.camera.resolution
    world.camera.set_resolution(*resolution)
    try:
        return grasper.run(name, world, wait, on_event=on_event)
    finally:
        world.camera.set_resolution(*before)


def held_in_the_physics(world: Any, name: str, top: float, hold: float = 2.0) -> bool:
    """The experiments' grasp success (truth): after ``hold`` s more of physics the object
    ``name`` is over 4 cm above the desk top ``top`` (map z), within 12 cm of the TCP, and the
    fingers have not closed on nothing."""
    world.step(hold)
    p_obj = world.truth.T_map_object(name)[:3, 3]
    p_tcp = world.truth.T_map_tcp()[:3, 3]
    return bool(
        p_obj[2] > top + 0.04
        and np.linalg.norm(p_obj - p_tcp) < 0.12
        and world.gripper.width() > 0.004
    )


def grasp_trial(
    world: Any,
    grasper: Any,
    name: str,
    lighting: str,
    rng: np.random.Generator,
    speed: float = 0.0,
    others: int = 2,
    resolution: tuple[int, int] = SERVO_RESOLUTION,
) -> dict[str, Any]:
    """One trial in the twin with the wrist camera streaming ``resolution`` (restored after);
    returns a result row (truth used only for evaluation)."""

    x, y, th = DESK_PARK
    pose = np.array([x, y, th]) + rng.uniform(-1, 1, 3) * np.array([0.05, 0.03, 0.05])
    world.reset(pose2d=pose, settle=0.2)
    world.set_lighting(lighting)
    pool = [c for c in CLASSES if c != name]
    objs = [name, *rng.choice(pool, min(others, len(pool)), replace=False).tolist()]
    dis = [n for n in ("distractor_book", "distractor_phone") if rng.random() < 0.5]
    _, top, _ = desk_frame(world)
    placed = random_table_scene(world, rng, objs[1:], dis)  # others anywhere on the desk
    random_table_scene_keep(world, rng, name, placed)  # the target in the reachable region
    world.step(0.3)
    rb = world.nominal
    T_ab = rb.T_base_link_arm_base
    look = np.array([*LOOK_TARGET, top - T_ab[2, 3] - 0.0])
    q_look = look_configuration(rb, look, LOOK_HEIGHT)
    world.arm.move_joints(q_look)
    op = Operator(world, name, speed, rng)
    probe = _Probe(world, name)
    t0 = time.perf_counter()

    def on_event(e: str) -> None:
        if e == "close":
            op.release()
            probe.at_close()
        elif e == "retry":
            probe.reopen()
            op.resume()

    def wait(dt: float) -> None:
        op.step(dt)
        probe.check()

    res = run_grasp(world, grasper, name, wait, on_event, resolution)
    op.release()
    held = held_in_the_physics(world, name, top)
    reason = res.reason if held or res.reason != "grasped" else "dropped"
    return {
        "object": name,
        "lighting": lighting,
        "speed": speed,
        "detected": res.detected_first,
        "found_view": res.found_view,
        "views": res.views,
        "grasped": held,
        "reason": reason,
        "failure": "" if held else probe.failure(reason, res),
        "time_to_grasp": res.time_to_grasp,
        "ticks": res.ticks,
        "lost_ticks": res.lost_ticks,
        "descent_s": res.descent_s,
        "attempts": res.attempts,
        "first_attempt": bool(held and res.attempts == 1),
        "detect_ms": float(np.mean(res.detect_ms)) if res.detect_ms else float("nan"),
        "capture_ms": float(np.mean(res.capture_ms)) if res.capture_ms else float("nan"),
        "loop_ms": 1000 * float(np.mean(res.loop_s)) if res.loop_s else float("nan"),
        "wall_s": time.perf_counter() - t0,
        **probe.row(),
    }


class _Probe:
    """Evaluation only (truth): the gripper-object geometry when the gripper starts to close
    (in the tool frame: ``close_dx`` along the pads, ``close_dy`` along the closing fingers,
    ``close_dz`` object center minus TCP height; large when the gripper closed on something
    else: ``close_on`` names the desk object nearest the TCP then, ``target_on_desk`` says
    whether the target was still on the desk), the first touch of the gripper on the object
    before that (``touched_before_close``: the object was knocked) and a failure class."""

    def __init__(self, world: Any, name: str) -> None:

        self.world, self.name = world, name
        m = world.model
        self.body = m.body(name).id
        self.gripper_geoms = {
            m.geom(g).id for g in ("finger_left_pad", "finger_right_pad", "gripper_palm")
        }
        self.radius = _footprint(world, name)[0]
        self.desk_objects = desk_object_names(world)
        _, self.desk_top, _ = desk_frame(world)
        self.closing = False
        self.touch_before: str = ""
        self.touch_last: str = ""  # touch_before of the attempt before a reopen
        self.close: dict[str, float] = {}
        self.close_on = ""
        self.target_on_desk = True

    def check(self) -> None:
        if self.closing or self.touch_before:
            return
        d, m = self.world.data, self.world.model
        for i in range(d.ncon):
            c = d.contact[i]
            g1, g2 = int(c.geom1), int(c.geom2)
            for a, b in ((g1, g2), (g2, g1)):
                if a in self.gripper_geoms and m.geom_bodyid[b] == self.body:
                    self.touch_before = m.geom(a).name
                    return

    def reopen(self) -> None:
        """The gripper opens for another attempt: touches count again. The row describes the
        last close (with the touch before it, ``touched``) until another close."""
        self.closing = False
        self.touch_last = self.touch_before
        self.touch_before = ""

    @property
    def touched(self) -> str:
        """The gripper's first touch of the object before the last close (or, without a
        close since, before any)."""
        return self.touch_before or self.touch_last

    def at_close(self) -> None:
        self.closing = True
        self.touch_last = ""
        truth = self.world.truth
        T_tcp = truth.T_map_tcp()
        p_obj = truth.T_map_object(self.name)[:3, 3]
        d = T_tcp[:3, :3].T @ (p_obj - T_tcp[:3, 3])
        self.close = {"close_dx": float(d[0]), "close_dy": float(d[1]), "close_dz": float(-d[2])}
        self.target_on_desk = bool(p_obj[2] > self.desk_top)
        dist = {
            n: float(np.linalg.norm(truth.T_map_object(n)[:2, 3] - T_tcp[:2, 3]))
            for n in self.desk_objects
        }
        near = min(dist, key=dist.__getitem__)
        self.close_on = near if dist[near] < 0.08 else ""

    def row(self) -> dict[str, Any]:
        nan = float("nan")
        return {
            "close_dx": self.close.get("close_dx", nan),
            "close_dy": self.close.get("close_dy", nan),
            "close_dz": self.close.get("close_dz", nan),
            "close_on": self.close_on,
            "target_on_desk": self.target_on_desk,
            "touched_before_close": self.touched,
        }

    def failure(self, reason: str, res: Any) -> str:
        """Why a trial failed: not found / lost track (timeout while the object was out of
        view for most ticks) / never aligned / unreachable / target off the desk (knocked off
        before the close) / wrong object (closed on another desk object, the target over
        0.15 m away: the track had jumped to it) / knocked (the
        gripper touched the object before closing) / off-center (the object center outside
        the open fingers at the close) / missed / dropped (held at the close, fell in the lift
        or hold)."""
        if reason in ("not found", "unreachable"):
            return reason
        if reason == "timeout":
            return "lost track" if res.lost_ticks > 0.3 * max(res.ticks, 1) else "never aligned"
        if self.closing and not self.target_on_desk:
            return "target off the desk"
        far = float(np.hypot(self.close.get("close_dx", 0.0), self.close.get("close_dy", 0.0)))
        if self.close_on and self.close_on != self.name and far > 0.15:
            return f"wrong object ({self.close_on})"
        if self.touched:
            return f"knocked ({self.touched})"
        stroke = self.world.true_robot.gripper.stroke
        dx, dy = self.close.get("close_dx", 0.0), self.close.get("close_dy", 0.0)
        if abs(dy) > stroke / 2 - 0.3 * self.radius or abs(dx) > 0.011 + 0.5 * self.radius:
            return "off-center"
        return reason


def random_table_scene_keep(
    world: Any, rng: np.random.Generator, name: str, placed: dict[str, np.ndarray]
) -> None:
    """Place ``name`` in :data:`REGION` away from the already placed objects."""

    T_desk, _, _ = desk_frame(world)
    r, h = _footprint(world, name)
    local = {k: (np.linalg.inv(T_desk) @ np.append(p, 1.0))[:2] for k, p in placed.items()}
    x0, x1, y0, y1 = REGION
    for _ in range(300):
        xy = np.array([rng.uniform(x0, x1), rng.uniform(y0, y1)])
        if all(np.linalg.norm(xy - q) > r + 0.1 for q in local.values()):
            break
    p = T_desk[:3, :3] @ np.array([*xy, h + 0.001]) + T_desk[:3, 3]
    world.place_object(name, p, yaw=float(rng.uniform(-np.pi, np.pi)))


class OracleDetector:
    """Ground-truth "detector" from the twin's segmentation rendering (evaluation only): boxes
    of the visible pixels of each object in the wrist camera's current view. Separates
    servo/grasp failures from detection failures."""

    def __init__(self, world: Any, min_pixels: int = 40) -> None:  # pixels of a 640x480 view
        from mmpa.perception.ssd import SSDConfig

        self.world = world
        self.cfg = SSDConfig()
        self.min_pixels = min_pixels
        self.ids = {world.model.body(n).id: i for i, n in enumerate(CLASSES)}

    def detect(self, image: np.ndarray, score_threshold: float | None = None) -> list[Any]:
        """Truth boxes of the visible objects (``score_threshold`` ignored: every box scores 1)."""
        from mmpa.perception.ssd import Detection

        seg = self.world.camera.segmentation()
        n_min = max(1, round(self.min_pixels * seg.size / (640 * 480)))  # per 640x480 pixels
        b, lab = boxes_from_segmentation(seg, self.ids, n_min)
        return [
            Detection(int(c), CLASSES[int(c)], 1.0, bb.astype(float))
            for bb, c in zip(b, lab, strict=True)
        ]


def make_grasper(cfg: Any, world: Any = None) -> Any:
    from mmpa.perception.ssd import Detector

    if cfg.weights == "oracle":
        det = OracleDetector(world)
    else:
        import torch

        torch.set_num_threads(getattr(cfg, "threads", 1))
        det = Detector.load(cfg.weights)
    gc = getattr(cfg, "servo", None) or GraspConfig()
    gc = gc.model_copy(
        update={
            "detect": gc.detect.model_copy(update={"preprocess_dark": cfg.preprocess_dark}),
            "track": gc.track.model_copy(update={"use_predictor": cfg.use_predictor}),
            "max_time": getattr(cfg, "max_time", 15.0),
        }
    )
    return TrackingGrasp(det, default_robot(), gc)


#: the runner may run this experiment's trials on an executor (``--workers``, ``--executor``)
PARALLEL_TRIALS = True
#: every trial can record itself to a bag of its own (``mmpa experiment --record DIR``)
RECORDS_TRIALS = True

#: this process's twins for grasp trials (a worker keeps them between trials): the world per
#: error model, the grasper per (world, grasp settings)
_TWINS: dict[str, Any] = {}
_GRASPERS: dict[str, Any] = {}


def twin_for(cfg: Any) -> tuple[Any, Any]:
    """This process's (world, grasper) for ``cfg`` (a grasp experiment :class:`Config`):
    built on first use, then kept. Trials reseed the world themselves (``set_episode`` and
    their own generator), so which trials ran in it before does not change a trial."""

    wkey = cfg.errors.model_dump_json()
    if wkey not in _TWINS:
        _TWINS[wkey] = SimWorld(site="0", errors=cfg.errors)
    gkey = wkey + cfg.model_dump_json(exclude={"seed", "trials", "objects", "lighting"})
    if gkey not in _GRASPERS:
        _GRASPERS[gkey] = make_grasper(cfg, _TWINS[wkey])
    return _TWINS[wkey], _GRASPERS[gkey]


def clear_twins() -> None:
    """Close the worlds this process keeps between trials."""
    _GRASPERS.clear()
    while _TWINS:
        _TWINS.popitem()[1].close()


@contextmanager
def recorded(world: Any, folder: str | None, label: dict, trial: int) -> Iterator[Any]:
    """``world`` itself, or (``folder`` given: ``mmpa experiment --record``) its recording
    stand-in writing the trial's ROS 2 bag ``folder/<label>site-0-trial-<n>.mcap``: every
    camera frame the servo loop used, ``/joint_states`` and the arm's ``/tf`` at
    :data:`~mmpa.backends.bag.record.ARM_RATE_HZ`, the truth. The trial is the same trial."""
    if folder is None:
        yield world
        return

    with trial_recorder(folder, label, "0", trial, world, ARM_RATE_HZ) as rec:
        yield rec.world()


def grasp_job(
    cfg_json: str, obj: str, light: str, t: int, record: str | None = None
) -> dict[str, Any]:
    """Trial ``t`` of the cell (``obj``, ``light``) (a worker job): its row. Every draw (scene,
    sensor noise) from the trial's own seed, so a trial alone is the same as in the table.
    ``record``: a folder for the trial's bag (:func:`recorded`)."""

    cfg = Config.model_validate_json(cfg_json)
    world, grasper = twin_for(cfg)
    lights = list(SimWorld.LIGHTING)
    cell = CLASSES.index(obj) * len(lights) + lights.index(light)
    rng = np.random.default_rng([cfg.seed, cell, t])
    world.set_episode(cell * 100_000 + t)
    with recorded(world, record, {"object": obj, "lighting": light}, t) as w:
        row = grasp_trial(w, grasper, obj, light, rng, others=cfg.others)
    row["trial"] = t
    return row


def run_jobs(ctx: Context, jobs: list, stage: str) -> list[dict[str, Any]]:
    """``jobs`` on ``ctx.executor`` (:func:`~mmpa.harness.runner.run_trials`): their rows
    in job order, each with the trial's wall time ``trial_s`` and its worker's peak memory
    ``worker_rss_mb``; this process's twins closed after."""
    try:
        recs = run_trials(ctx, jobs, stage)
    finally:
        clear_twins()
    return [
        {**r["result"], "trial_s": r["trial_s"], "worker_rss_mb": r["worker_rss_mb"]} for r in recs
    ]


def run(cfg: Config, ctx: Context, progress: Callable[[str, float], None] | None = None) -> Outcome:

    for o in cfg.objects:
        if o not in CLASSES:
            raise UnknownNameError("object", o, list(CLASSES))
    for li in cfg.lighting:
        if li not in SimWorld.LIGHTING:
            raise UnknownNameError("lighting condition", li, list(SimWorld.LIGHTING))

    n = cfg.n_trials()
    cfg_json = cfg.model_dump_json()
    rec = recording_folder()  # mmpa experiment --record
    jobs = [
        (
            {"object": obj, "lighting": light, "trial": t},
            grasp_job,
            (cfg_json, obj, light, t, rec),
        )
        for obj in cfg.objects
        for light in cfg.lighting
        for t in range(n)
    ]
    rows = run_jobs(ctx, jobs, "grasp")
    table, summary = [], {}
    for obj in cfg.objects:
        line: list[Any] = [obj]
        for light in cfg.lighting:
            r = [x for x in rows if x["object"] == obj and x["lighting"] == light]
            det = float(np.mean([x["detected"] for x in r]))
            ok = float(np.mean([x["grasped"] for x in r]))
            summary[f"{obj}/{light}"] = {"detection": det, "grasp": ok}
            line += [det, ok, TABLE3.get(obj, {}).get(light, float("nan"))]
        table.append(line)
    header = ["object"]
    for light in cfg.lighting:
        header += [f"{light} detect", f"{light} grasp", f"{light} paper"]
    summary["detection"] = float(np.mean([x["detected"] for x in rows]))
    summary["grasp"] = float(np.mean([x["grasped"] for x in rows]))
    summary["first_attempt"] = float(np.mean([x["first_attempt"] for x in rows]))
    retried = [x for x in rows if x["attempts"] > 1]
    report = (
        f"{n} trials per object and light condition (seed {cfg.seed}); detection = target "
        "found in the first frame; grasp = held off the desk 2 s after the lift (physics), "
        "after at most "
        f"{cfg.servo.close.max_attempts} attempts (a missed grasp is tried "
        "again). Paper: Table 3 success rate (20 trials each).\n\n"
        + markdown_table(header, table, digits=2)
        + f"\nGrasped at the first attempt: {summary['first_attempt']:.3f} of all trials "
        f"(grasp {summary['grasp']:.3f}); trials with more than one attempt: {len(retried)}"
        + "".join(
            f"\n- {r['object']} / {r['lighting']} trial {r['trial']}: {r['attempts']} attempts, "
            + ("held" if r["grasped"] else "not held")
            for r in retried
        )
        + "\n\nFailures:\n"
        + "".join(
            f"- {r['object']} / {r['lighting']} trial {r['trial']}: {r['failure']} "
            f"(close offset x {1000 * r['close_dx']:.0f} mm, y {1000 * r['close_dy']:.0f} mm)\n"
            for r in rows
            if not r["grasped"]
        )
    )
    return Outcome(rows=rows, summary=summary, report=report)
