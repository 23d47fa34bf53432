"""Second views of the object (improvement; paper 001 waits at the first view).

When the target has not been seen ``search.after`` s after the start, the weak boxes of its
class in the current view, then those of look-alike objects named otherwise, are candidates
(:func:`candidates`: each located as its top center in ``arm_base``, m, with the desk height
under it). The camera looks at each from the ``search.views`` (:func:`view_configuration`:
azimuth deg from the direction toward the arm base, horizontal distance m, height m above the
desk; the camera aims at the candidate's mid-height, image up toward +z), reached along the
joint-space straight line when that keeps the flange, camera and TCP ``search.clearance``
above the desk (:func:`lowest`); a detection there on the candidate (:func:`same_object`), or
one anywhere scoring ``detect.reinit_score``, starts the track.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import numpy as np

from mmpa.core.errors import UnreachableError
from mmpa.core.geometry import Array, apply, inv
from mmpa.perception.locate import look_at
from mmpa.robot.interfaces import Camera, RGBDFrame, StreamingArm
from mmpa.robot.kinematics import fk, ik_nearest
from mmpa.servo.config import GraspConfig, SearchConfig
from mmpa.servo.pose import ArmGeometry
from mmpa.servo.stream import Stream
from mmpa.servo.target import desk_height, top_surface
from mmpa.servo.tracker import Measurement, Perception

__all__ = ["Search", "candidates", "lowest", "same_object", "view_configuration"]


def candidates(
    perception: Perception, frame: RGBDFrame, name: str, q: Array, cfg: SearchConfig
) -> list[tuple[Array, float, float]]:
    """Where ``name`` may be although no detection reached the threshold: the boxes of its
    class scoring at least ``candidate_score`` in ``frame`` (camera at the encoder reading
    ``q``), best first, then those of other classes scoring at least
    ``other_candidate_score``, each located as its top center ``p`` (3,) ``arm_base`` with the
    desk height ``z_desk`` under it (:mod:`mmpa.servo.target`); returns ``(p, z_desk,
    score)``, one per ``gate`` (the boxes of one object)."""
    low = min(cfg.candidate_score, cfg.other_candidate_score)
    every = perception.detect(frame.color, low)
    dets = sorted((d for d in every if d.name == name), key=lambda d: -d.score)
    dets = [d for d in dets if d.score >= cfg.candidate_score] + sorted(
        (d for d in every if d.name != name and d.score >= cfg.other_candidate_score),
        key=lambda d: -d.score,
    )
    T_cam = perception.geom.T_camera(q)
    K = frame.intrinsics.K
    stride = max(1, frame.depth.shape[1] // 320)
    out: list[tuple[Array, float, float]] = []
    for d in dets:
        dz = desk_height(frame.depth, K, T_cam, d.box)
        if dz is None:
            continue
        top = top_surface(frame.depth, K, T_cam, d.box, dz, stride=stride)
        if top is None:  # nothing stands out of the desk in the box
            continue
        if all(np.linalg.norm(top.p_top[:2] - p[:2]) > cfg.gate for p, _, _ in out):
            out.append((top.p_top, dz, float(d.score)))
    return out


def view_configuration(
    geom: ArmGeometry, p: Array, z_desk: float, view: tuple[float, float, float], q_ref: Array
) -> Array:
    """Joint angles (6,) of a second view of the object with top center ``p`` (3,)
    ``arm_base`` on the desk at height ``z_desk``: ``view = (azimuth deg, r m, h m)``, the
    camera ``r`` from the object horizontally, in the direction toward the arm base turned by
    the azimuth (counter-clockwise seen from above), ``h`` above the desk, looking at the
    object's mid-height, image up toward +z. The IK solution nearest ``q_ref`` within
    ``geom``'s limits; raises UnreachableError."""
    az, r, h = view
    p = np.asarray(p, float)
    u = -p[:2] / max(float(np.linalg.norm(p[:2])), 1e-9)  # toward the arm base
    c, s = np.cos(np.radians(az)), np.sin(np.radians(az))
    d = np.array([c * u[0] - s * u[1], s * u[0] + c * u[1]])
    eye = np.array([*(p[:2] + r * d), z_desk + h])
    target = np.array([p[0], p[1], 0.5 * (p[2] + z_desk)])
    T_fl = look_at(eye, target, up_hint=(0.0, 0.0, 1.0)) @ inv(geom.T_fc)
    return ik_nearest(geom.dh, T_fl, q_ref, geom.q_lo, geom.q_hi)


def lowest(geom: ArmGeometry, q0: Array, q1: Array, n: int = 12) -> float:
    """Lowest height (m, ``arm_base`` z) of the flange, camera and TCP on the joint-space
    straight line from ``q0`` to ``q1`` (``n`` + 1 samples, nominal kinematics)."""
    low = np.inf
    for a in np.linspace(0.0, 1.0, n + 1):
        T = fk(geom.dh, (1 - a) * np.asarray(q0) + a * np.asarray(q1))
        for T_f in (np.eye(4), geom.T_fc, geom.T_ft):
            low = min(low, float((T @ T_f)[2, 3]))
    return low


def same_object(
    geom: ArmGeometry,
    frame: RGBDFrame,
    q: Array,
    box: Array,
    p_det: Array,
    p_cand: Array,
    gate: float,
) -> bool:
    """A detection (``box`` in ``frame`` at the encoder reading ``q``, located at ``p_det``)
    is of the candidate at ``p_cand`` (both (3,) ``arm_base``): their top centers lie within
    ``gate`` m horizontally, or the candidate's top center projects into the box (a long
    object the first view saw in part)."""
    if np.linalg.norm(np.asarray(p_det)[:2] - np.asarray(p_cand)[:2]) < gate:
        return True
    T_cam = geom.T_camera(q)
    P = apply(inv(T_cam), p_cand)
    if P[2] <= 0:
        return False
    K = frame.intrinsics.K
    u, v = K[:2, :2] @ (P[:2] / P[2]) + K[:2, 2]
    x1, y1, x2, y2 = box
    return bool(x1 <= u <= x2 and y1 <= v <= y2)


class Search:
    """The second views of the candidates, streamed by ``stream`` at the tracking's joint
    speed ``qd`` (6,) rad/s."""

    def __init__(self, perception: Perception, stream: Stream, cfg: GraspConfig, qd: Array) -> None:
        self.perception = perception
        self.geom = perception.geom
        self.stream = stream
        self.cfg = cfg
        self.qd = qd

    def move_to(
        self,
        arm: StreamingArm,
        q_cmd: Array,
        q_goal: Array,
        wait: Callable[[float], None],
        until: Callable[[], bool],
    ) -> Array:
        """To ``q_goal`` (6,) by control ticks at ``track.rate_hz``
        (:meth:`mmpa.servo.stream.Stream.move_to`); returns the last set-point."""
        dt = 1.0 / self.cfg.track.rate_hz
        return self.stream.move_to(arm, q_cmd, q_goal, self.qd, dt, wait, until)

    def run(
        self,
        name: str,
        frame: RGBDFrame,
        q_meas: Array,
        q_cmd: Array,
        arm: StreamingArm,
        camera: Camera,
        wait: Callable[[float], None],
        until: Callable[[], bool],
    ) -> tuple[Array, Any, Measurement | None, int]:
        """Second views of the candidates of ``name`` in ``frame`` (taken at the encoder
        reading ``q_meas``): returns ``(set-point, detection, measurement, views taken)``, the
        measurement None when no view confirmed a candidate (the arm is then at the last
        view)."""
        cfg = self.cfg.search
        views = 0
        cands = candidates(self.perception, frame, name, q_meas, cfg)[: cfg.candidates]
        for p, dz, _ in cands:
            for view in cfg.views:
                if until():
                    return q_cmd, None, None, views
                try:
                    q_view = view_configuration(self.geom, p, dz, view, q_cmd)
                except UnreachableError:
                    continue
                if np.max(np.abs(q_view - q_cmd)) > cfg.joint_step:
                    continue  # another arm configuration: a long detour past the desk
                if lowest(self.geom, q_cmd, q_view) < dz + cfg.clearance:
                    continue  # the arm would sweep through the objects on the desk
                q_cmd = self.move_to(arm, q_cmd, q_view, wait, until)
                views += 1
                wait(cfg.settle)
                det, meas = self._look(name, p, arm, camera, wait)
                if meas is not None:
                    return q_cmd, det, meas, views
        return q_cmd, None, None, views

    def _look(
        self,
        name: str,
        p: Array,
        arm: StreamingArm,
        camera: Camera,
        wait: Callable[[float], None],
    ) -> tuple[Any, Measurement | None]:
        """Up to ``search.frames`` frames at a view of the candidate at ``p`` (3,): the first
        detection on it (or sure enough to restart a track), else ``(None, None)``."""
        cfg = self.cfg
        for _ in range(cfg.search.frames):
            q_now = np.asarray(arm.joint_positions(), float)
            fr = camera.capture()
            det, meas = self.perception.measure(fr, name, q_now, near=p)
            if meas is not None and (
                det.score >= cfg.detect.reinit_score  # as sure as a track restart needs
                or same_object(self.geom, fr, q_now, det.box, meas.p, p, cfg.search.gate)
            ):
                return det, meas
            wait(1.0 / cfg.track.rate_hz)
        return None, None
