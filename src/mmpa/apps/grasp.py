"""``mmpa grasp OBJECT``: paper 001's tracking grasp (the detector and the IBVS servo,
:class:`mmpa.servo.grasp.TrackingGrasp`) as a command, on any backend.

- The twin (default, :func:`grasp_twin`): the trial of ``mmpa experiment grasp``
  (:func:`mmpa.experiments.paper001.grasp.grasp_trial`): the robot parks at the grasp desk
  (seeded jitter), OBJECT lies in the reachable region with ``others`` other objects and
  distractors around it, the light is set, the arm looks down at the desk; with ``speed``
  > 0 m/s an operator moves the object with random turns and lets go when the gripper
  closes (paper 001 §4.3.3). At ``speed`` 0 and the same ``seed`` it is the experiment's
  trial 0 of the cell (OBJECT, ``lighting``). The truth judges it: held off the desk 2 s
  after the lift (physics), and the grasp error, the object's center seen from the TCP at
  the close (``along_pads`` x, ``across_pads`` y along the closing fingers, ``height``,
  mm; tool frame).
- A hardware robot (:func:`grasp_on_robot`: any
  :class:`~mmpa.robot.interfaces.MobileManipulator` with a streaming arm, a gripper and a
  wrist camera; a fixed-base arm gets a base that never moves): the grasp starts where the
  arm stands (the camera looking at the object); one frame is detected first (nothing
  moves) and ``confirm`` is asked before the arm moves. No truth: the summary holds what the
  robot measured (the gripper's close result and width, the detection track: per detector
  call the robot time, the target's best score and box center in pixels) and the timings.
  A failure (not detected, lost track, unreachable, a limit or a stop) ends with ``ok``
  False and a ``reason``, the arm's stream held where it stands.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from typing import Any

import numpy as np
from pydantic import BaseModel, ConfigDict, Field

from mmpa.backends.twin.error_model import ErrorModelConfig
from mmpa.backends.twin.world import SimWorld
from mmpa.core.errors import InvalidInputError, MMPAError, UnknownNameError
from mmpa.core.geometry import Array
from mmpa.experiments.paper001.grasp import Config as GraspExperimentConfig
from mmpa.experiments.paper001.grasp import clear_twins, grasp_trial, make_grasper, twin_for
from mmpa.perception import CLASSES
from mmpa.robot.interfaces import (
    MobileManipulator,
    Odometry,
    RobotDevices,
    StreamingArm,
    require,
)
from mmpa.servo.config import GraspConfig
from mmpa.servo.grasp import GraspResult, TrackingGrasp
from mmpa.servo.tracker import Detector

__all__ = ["GraspRunConfig", "RecordingDetector", "grasp_on_robot", "grasp_twin"]


class GraspRunConfig(BaseModel):
    """``mmpa grasp``'s settings (``config.yaml``; ``--config`` / ``--set``). The twin only:
    ``seed`` (the scene's draw), ``speed`` (m/s of the operator moving the object; 0: it
    lies still), ``lighting``, ``others`` (other objects on the desk), ``errors`` (the
    robot instance and its error model). Every backend: ``weights`` (detector weights;
    None: the shipped model; "oracle": the twin's truth boxes, the twin only), ``threads``
    (the detector's torch threads), ``max_time`` (s of robot time for all attempts) and
    ``servo`` (the grasp's :class:`~mmpa.servo.config.GraspConfig`)."""

    model_config = ConfigDict(extra="forbid")

    seed: int = Field(0, ge=0)
    speed: float = Field(0.0, ge=0.0, le=0.5)  # m/s
    lighting: str = "normal"
    others: int = Field(2, ge=0, le=6)
    weights: str | None = None
    threads: int = Field(1, ge=1, le=64)
    max_time: float = Field(15.0, gt=0.0, le=600.0)  # s
    servo: GraspConfig = Field(default_factory=GraspConfig)
    errors: ErrorModelConfig = ErrorModelConfig()


def _experiment_config(cfg: GraspRunConfig) -> GraspExperimentConfig:
    """The experiment's config of the same grasp (its detector and servo settings taken from
    ``cfg.servo``, not overridden)."""
    return GraspExperimentConfig(
        seed=cfg.seed,
        weights=cfg.weights,
        preprocess_dark=cfg.servo.detect.preprocess_dark,
        use_predictor=cfg.servo.track.use_predictor,
        others=cfg.others,
        max_time=cfg.max_time,
        threads=cfg.threads,
        servo=cfg.servo,
        errors=cfg.errors,
    )


def _num(x: Any) -> float | None:
    """A float for JSON, None for NaN / inf."""
    v = float(x)
    return v if math.isfinite(v) else None


def _check_object(name: str) -> None:
    if name not in CLASSES:
        raise UnknownNameError("object", name, list(CLASSES))


def grasp_twin(name: str, cfg: GraspRunConfig) -> dict[str, Any]:
    """The grasp of ``name`` in the twin (module docstring); returns the summary: ``ok``
    (held in the physics), ``reason`` (the experiment's failure class when not held), the
    grasp error against the truth (mm), the detection and attempt figures and the timings
    (s; detector, capture and loop ms means)."""
    _check_object(name)
    lights = list(SimWorld.LIGHTING)
    if cfg.lighting not in lights:
        raise UnknownNameError("lighting condition", cfg.lighting, lights)
    t0 = time.perf_counter()
    try:
        world, grasper = twin_for(_experiment_config(cfg))
        cell = CLASSES.index(name) * len(lights) + lights.index(cfg.lighting)
        rng = np.random.default_rng([cfg.seed, cell, 0])  # the experiment's trial 0
        world.set_episode(cell * 100_000)
        row = grasp_trial(
            world, grasper, name, cfg.lighting, rng, speed=cfg.speed, others=cfg.others
        )
    finally:
        clear_twins()
    dx, dy, dz = (1e3 * float(row[k]) for k in ("close_dx", "close_dy", "close_dz"))
    held = bool(row["grasped"])
    return {
        "backend": "twin",
        "object": name,
        "ok": held,
        "reason": "grasped" if held else row["failure"] or row["reason"],
        "held_in_physics": held,
        "detected_first_view": bool(row["detected"]),
        "found_view": int(row["found_view"]),
        "attempts": int(row["attempts"]),
        "grasp_error_mm": {
            "along_pads": _num(dx),
            "across_pads": _num(dy),
            "height": _num(dz),
            "horizontal": _num(math.hypot(dx, dy)),
        },
        "closed_on": row["close_on"],
        "touched_before_close": row["touched_before_close"],
        "time_to_grasp_s": _num(row["time_to_grasp"]),
        "descent_s": _num(row["descent_s"]),
        "ticks": int(row["ticks"]),
        "lost_ticks": int(row["lost_ticks"]),
        "timings": {
            "detect_ms_mean": _num(row["detect_ms"]),
            "capture_ms_mean": _num(row["capture_ms"]),
            "loop_ms_mean": _num(row["loop_ms"]),
            "trial_wall_s": _num(row["wall_s"]),
            "wall_s": time.perf_counter() - t0,
        },
        "speed_m_s": cfg.speed,
        "lighting": cfg.lighting,
        "seed": cfg.seed,
        "profile": cfg.errors.profile,
        "robot_seed": cfg.errors.seed,
    }


class RecordingDetector:
    """A :class:`~mmpa.servo.tracker.Detector` that records, per call, the robot time
    ``clock()`` (s) and the best box of ``target`` (score, box center u, v px; None when
    not detected): the detection track of a run without truth."""

    def __init__(self, detector: Detector, target: str, clock: Callable[[], float]) -> None:
        self.det, self.target, self.clock = detector, target, clock
        self.cfg = detector.cfg
        self.track: list[dict[str, Any]] = []

    def detect(self, image: Array, score_threshold: float | None = None) -> list[Any]:
        dets = self.det.detect(image, score_threshold)
        mine = [d for d in dets if d.name == self.target]
        best = max(mine, key=lambda d: d.score) if mine else None
        row: dict[str, Any] = {"t": float(self.clock()), "score": None, "u": None, "v": None}
        if best is not None:
            c = np.asarray(best.center, float)
            row.update(score=float(best.score), u=float(c[0]), v=float(c[1]))
        self.track.append(row)
        return dets


class _StillBase:
    """A fixed-base arm's base for the grasp: it never moves (an object beyond
    ``track.reach_limit`` stays out of reach)."""

    def set_velocity(self, v: float, w: float) -> None:
        pass

    def stop(self) -> None:
        pass

    def odometry(self) -> Odometry:
        return Odometry(np.zeros(3), np.zeros(2), 0.0)


def _grasping_robot(robot: MobileManipulator) -> MobileManipulator:
    """``robot`` itself, or (no base) its devices with a :class:`_StillBase`."""
    if robot.base is not None:
        return robot
    return RobotDevices(
        robot.description,
        arm=robot.arm,
        camera=robot.camera,
        gripper=robot.gripper,
        base=_StillBase(),
        odometry=robot.odometry,
        lidar=robot.lidar,
        clock=robot,
    )


def _first_look(robot: MobileManipulator, det: Detector, name: str) -> dict[str, Any]:
    """One frame from where the arm stands, detected (nothing moves): the target's best
    score and box center (px), or None."""
    assert robot.camera is not None
    dets = [d for d in det.detect(robot.camera.capture().color) if d.name == name]
    if not dets:
        return {"seen": False, "score": None, "u": None, "v": None}
    best = max(dets, key=lambda d: d.score)
    c = np.asarray(best.center, float)
    return {"seen": True, "score": float(best.score), "u": float(c[0]), "v": float(c[1])}


def _question(name: str, first: dict[str, Any], cfg: GraspRunConfig, fixed: bool) -> str:
    seen = (
        f"the {name} is seen (score {first['score']:.2f})"
        if first["seen"]
        else f"the {name} is not seen from here (the grasp looks for it up to {cfg.max_time:g} s)"
    )
    base = "" if not fixed else " (no base: the object must be within the arm's reach)"
    return (
        f"{seen}; the arm will servo toward it, descend, close the gripper and lift "
        f"{1e3 * cfg.servo.close.lift:.0f} mm{base}. Move the arm?"
    )


def _hold(robot: MobileManipulator) -> str | None:
    """Stop after a failure: the base stopped, a streaming arm's target held at its measured
    configuration; returns the controller's stop state (protective / emergency) or None."""
    if robot.base is not None:
        robot.base.stop()
    arm = robot.arm
    if not isinstance(arm, StreamingArm):
        return None
    why = arm.stopped()
    if why is None:
        try:
            arm.command(np.asarray(arm.joint_positions(), float))
        except MMPAError as e:  # it will not take a command: say why
            return str(e)
    return why


_REASONS = {
    "not found": "the {name} was not detected",
    "unreachable": "the {name} is out of the arm's reach",
    "missed": "the gripper closed on nothing (every attempt)",
}


def _reason(res: GraspResult, name: str) -> str:
    """The run's ending in words; a timeout is a lost track when the object was out of view
    for most ticks, else it never aligned."""
    if res.reason == "timeout":
        return "lost track" if res.lost_ticks > 0.3 * max(res.ticks, 1) else "never aligned"
    return _REASONS.get(res.reason, res.reason).format(name=name)


def _robot_summary(
    res: GraspResult | None, rec: RecordingDetector, robot: MobileManipulator, t0: float
) -> dict[str, Any]:
    """What the robot measured (module docstring)."""
    assert robot.gripper is not None
    out: dict[str, Any] = {
        "gripper_width_mm": 1e3 * float(robot.gripper.width()),
        "detections": sum(r["score"] is not None for r in rec.track),
        "detector_calls": len(rec.track),
        "track": rec.track,
        "timings": {"wall_s": time.perf_counter() - t0},
    }
    if res is None:
        return out
    loop = 1e3 * np.asarray(res.loop_s, float)
    out.update(
        closed_on_object=bool(res.closed_on_object),
        detected_first_view=bool(res.detected_first),
        found_view=res.found_view,
        attempts=res.attempts,
        time_to_grasp_s=_num(res.time_to_grasp),
        descent_s=_num(res.descent_s),
        ticks=res.ticks,
        lost_ticks=res.lost_ticks,
    )
    out["timings"].update(
        detect_ms_mean=_num(np.mean(res.detect_ms)) if res.detect_ms else None,
        capture_ms_mean=_num(np.mean(res.capture_ms)) if res.capture_ms else None,
        loop_ms_mean=_num(loop.mean()) if len(loop) else None,
        loop_ms_p95=_num(np.percentile(loop, 95)) if len(loop) else None,
    )
    return out


def grasp_on_robot(
    robot: MobileManipulator,
    name: str,
    cfg: GraspRunConfig,
    *,
    kind: str = "hardware",
    detector: Detector | None = None,
    confirm: Callable[[str], bool] | None = None,
) -> dict[str, Any]:
    """The grasp of ``name`` on ``robot`` from where its arm stands (module docstring):
    ``kind`` names the backend in the summary; ``detector`` (default: ``cfg.weights``, the
    shipped model); ``confirm(question)`` before the arm moves (None: no question; False:
    ``ok`` False, nothing moved). Returns the summary: ``ok`` (the gripper holds something
    after the lift), ``reason``, ``moved``, the first look, what the robot measured."""
    _check_object(name)
    require(robot, "arm", "gripper", "camera", mission="the grasp")
    if detector is None:
        if cfg.weights == "oracle":
            raise InvalidInputError("weights 'oracle' (the twin's truth boxes) is the twin's only")
        detector = make_grasper(_experiment_config(cfg)).det
    gc = cfg.servo.model_copy(update={"max_time": cfg.max_time})
    rec = RecordingDetector(detector, name, lambda: robot.time)
    grasper = TrackingGrasp(rec, robot.description, gc)
    first = _first_look(robot, detector, name)
    head = {"backend": kind, "object": name, "first_look": first}
    question = _question(name, first, cfg, robot.base is None)
    if confirm is not None and not confirm(question):
        return {**head, "ok": False, "reason": "declined: nothing moved", "moved": False}
    t0 = time.perf_counter()
    run_robot = _grasping_robot(robot)
    res: GraspResult | None = None
    try:
        res = grasper.run(name, run_robot)
        ok, reason = res.closed_on_object, _reason(res, name)
    except MMPAError as e:  # a limit, a stop, a device that stopped answering
        ok, reason = False, f"stopped: {e}"
    stop = None if ok else _hold(run_robot)
    if stop:
        reason += f" ({stop})"
    measured = _robot_summary(res, rec, robot, t0)
    return {**head, "ok": bool(ok), "reason": reason, "moved": True, **measured}
