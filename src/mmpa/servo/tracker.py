"""Detection -> target estimate for the tracking grasp (paper 001 §3.2.2).

:class:`Perception` detects the named object in an RGB-D frame and locates it in ``arm_base``
(m) with the nominal kinematics at the encoder reading: by default its top center and top
height from all the box's depth pixels (:mod:`mmpa.servo.target`), or the paper's box center
deprojected at its depth (``detect.grasp_point="box"``); with a track, weak boxes
(``detect.track_score``) within ``detect.track_gate`` of it count too.

The estimate: the constant-velocity Kalman filter (:mod:`mmpa.servo.predictor`), and for a
still object the least-squares line through the measurements of the last
``track.still_window`` s (:func:`still_line`; its jitter is no motion). An object whose
horizontal speed exceeds ``track.final_standoff_max_speed`` is moving (:func:`is_moving`);
:func:`is_fast` tells a moving object from its measurements' line.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Protocol

import numpy as np

from mmpa.core.geometry import Array, apply, inv
from mmpa.perception.locate import DepthMissingError, locate
from mmpa.perception.preprocess import dark_preprocess, is_dark
from mmpa.robot.interfaces import RGBDFrame
from mmpa.servo.config import DetectConfig, GraspConfig, TrackConfig
from mmpa.servo.pose import ArmGeometry
from mmpa.servo.predictor import ConstantVelocityKF, fit_line
from mmpa.servo.target import box_points, desk_height, top_surface

__all__ = [
    "SYMMETRIC",
    "Detector",
    "Measurement",
    "Perception",
    "intercepting",
    "is_fast",
    "is_moving",
    "still_line",
]

#: objects without a grasp axis (the tool keeps its heading)
SYMMETRIC = {"tennis_ball", "yida_bottle", "water_bottle", "paper_cup", "glue_stick"}


class Detector(Protocol):
    """An object detector: ``detect(image, score_threshold)`` -> boxes (each with ``name``,
    ``score``, ``box`` (x1, y1, x2, y2) and ``center`` (2,) pixels); ``cfg`` its settings
    (``score_threshold``, ``classes``)."""

    cfg: Any

    def detect(self, image: Array, score_threshold: float | None = None) -> list[Any]: ...


@dataclass(frozen=True)
class Measurement:
    """One located detection: ``p`` (3,) the tracked object point in ``arm_base`` (m; the top
    center, or the paper's box center), ``top_z``/``desk_z`` heights (m; ``desk_z`` NaN when
    unknown), ``axis`` (2,) unit horizontal grasp axis in ``arm_base`` or None."""

    p: Array
    top_z: float
    desk_z: float
    axis: Array | None


class Perception:
    """The detector and the object's location from a frame (``detect`` settings)."""

    def __init__(self, detector: Detector, geom: ArmGeometry, cfg: DetectConfig) -> None:
        self.det = detector
        self.geom = geom
        self.cfg = cfg

    def detect(self, img: Array, score_threshold: float | None = None) -> list[Any]:
        """The detector on ``img`` (the dark preprocessing first when configured); boxes
        scoring at least ``score_threshold`` (default: the detector's)."""
        if self.cfg.preprocess_dark and is_dark(img):
            img = dark_preprocess(img)
        if score_threshold is None:
            return list(self.det.detect(img))
        return list(self.det.detect(img, score_threshold))

    def measure(
        self,
        frame: RGBDFrame,
        name: str,
        q: Array,
        kf: ConstantVelocityKF | None = None,
        near: Array | None = None,
        track: list[Array] | None = None,
    ) -> tuple[Any, Measurement | None]:
        """Detect ``name`` in ``frame`` (when several: the detection nearest ``near`` (3,)
        ``arm_base``, by default the prediction of ``kf``) and locate it with the nominal
        kinematics at the encoder reading ``q``. With ``track`` (points (3,) ``arm_base``:
        the prediction, the last measurement) and no detection at the detector's threshold,
        the boxes scoring ``track_score`` or more are tried, nearest first, and the first
        located within ``track_gate`` of a track point is taken."""
        cfg = self.cfg
        th = float(self.det.cfg.score_threshold)
        weak_ok = bool(track) and cfg.track_score < th
        dets = [
            d
            for d in self.detect(frame.color, cfg.track_score if weak_ok else None)
            if d.name == name
        ]
        strong = [d for d in dets if d.score >= th]
        if not dets or (not strong and not weak_ok):
            return None, None
        T_cam = self.geom.T_camera(q)
        K = frame.intrinsics.K
        if near is None and kf is not None and kf.initialized:
            near = kf.position()
        if near is not None and len(dets) > 1:  # the detection nearest the expected place
            P = apply(inv(T_cam), near)
            if P[2] > 0:
                uv = K[:2, :2] @ (P[:2] / P[2]) + K[:2, 2]
                dets.sort(key=lambda d: float(np.linalg.norm(d.center - uv)))
                strong = [d for d in dets if d.score >= th]
        if strong:
            return self.locate(frame, strong[0], T_cam)
        assert track is not None
        for d in dets:  # weak boxes only: the first on the track
            d_, m = self.locate(frame, d, T_cam)
            if m is not None and min(np.linalg.norm(m.p - t) for t in track) < cfg.track_gate:
                return d_, m
        return None, None

    def locate(self, frame: RGBDFrame, d: Any, T_cam: Array) -> tuple[Any, Measurement | None]:
        """Locate detection ``d`` in ``frame`` taken from the camera pose ``T_cam``
        (``arm_base``): ``grasp_point`` "top" or the paper's "box" center."""
        K = frame.intrinsics.K
        dz = desk_height(frame.depth, K, T_cam, d.box)
        if self.cfg.grasp_point == "top":
            if dz is None:
                return d, None
            # every pixel of a 320-wide frame, every 2nd of a 640-wide one (same rays)
            stride = max(1, frame.depth.shape[1] // 320)
            top = top_surface(frame.depth, K, T_cam, d.box, dz, stride=stride)
            if top is None:
                return d, None
            return d, Measurement(top.p_top, float(top.p_top[2]), dz, top.axis_xy)
        return d, self._box_center(frame, d, K, T_cam, dz)

    def _box_center(
        self, frame: RGBDFrame, d: Any, K: Array, T_cam: Array, dz: float | None
    ) -> Measurement | None:
        """The paper's box center (+ the center correction and the principal axis of the
        depth foreground in the image); None without depth."""
        try:
            loc = locate(d.box, frame.depth, K, T_cam)
        except DepthMissingError:
            return None
        axis = None
        if self.cfg.axis_from_depth and dz is not None:
            a2 = axis_from_depth(frame.depth, d.box, K, T_cam, dz)
            if a2 is not None:
                loc = locate(d.box, frame.depth, K, T_cam, axis_2d=a2)
                axis = loc.axis_arm_base[:2] / max(np.linalg.norm(loc.axis_arm_base[:2]), 1e-9)
        elif not self.cfg.axis_from_depth:
            bw, bh = d.box[2] - d.box[0], d.box[3] - d.box[1]
            if max(bw, bh) >= 1.3 * min(bw, bh) and abs(loc.axis_arm_base[2]) < 0.9:
                axis = loc.axis_arm_base[:2] / max(np.linalg.norm(loc.axis_arm_base[:2]), 1e-9)
        p = loc.center_arm_base if self.cfg.center_correction else loc.p_arm_base
        z_desk = dz if dz is not None else float("nan")
        return Measurement(np.asarray(p, float), float(loc.p_arm_base[2]), z_desk, axis)


def axis_from_depth(
    depth: Array, box: Array, K: Array, T_cam: Array, desk_z: float
) -> Array | None:
    """The principal image axis (2,) of the pixels in ``box`` of the ``depth`` image (m)
    that stand 8 mm above the desk height ``desk_z`` (m, ``arm_base``); None without a clear
    long axis (ball, cube, upright cylinder) or with fewer than 20 such pixels."""
    h, w = depth.shape
    x1, y1, x2, y2 = np.clip(np.round(box), 0, [w, h, w, h]).astype(int)
    vv, uu = np.mgrid[y1:y2, x1:x2]
    uu, vv = uu.ravel(), vv.ravel()
    p, keep = box_points(depth, K, T_cam, uu, vv)
    mask = p[:, 2] > desk_z + 0.008
    if mask.sum() < 20:
        return None
    c = np.cov(np.stack([uu[keep][mask], vv[keep][mask]]).astype(float))
    ev, V = np.linalg.eigh(c)
    if ev[1] < 1.5 * max(ev[0], 1e-9):  # no clear long axis (ball, cube, upright cylinder)
        return None
    return V[:, 1]


def is_moving(v_obj: Array | None, max_speed: float) -> bool:
    """An object whose (predicted) velocity ``v_obj`` (3,) m/s exceeds ``max_speed`` m/s in
    the desk plane counts as moving (gain, standoff and descent speed switch to their
    ``moving_`` values)."""
    return v_obj is not None and float(np.linalg.norm(np.asarray(v_obj)[:2])) > max_speed


def still_line(hist: list[tuple[float, Array]], cfg: TrackConfig) -> tuple[Array, Array] | None:
    """The least-squares line ``(p at the last measurement (3,), v (3,))`` through the
    measurements ``hist`` ((time s, point (3,) m) of the last ``still_window`` s) when it
    shows a still object (horizontal speed at most ``final_standoff_max_speed``); None when
    it does not, or too few measurements span too short a time to tell."""
    if cfg.still_window <= 0 or len(hist) < cfg.still_min_measurements:
        return None
    t = np.array([h[0] for h in hist])
    if t[-1] - t[0] < 0.5 * cfg.still_window:
        return None
    p, v = fit_line(t, np.array([h[1] for h in hist]))
    return None if is_moving(v, cfg.final_standoff_max_speed) else (p, v)


def is_fast(hist: list[tuple[float, Array]], cfg: TrackConfig) -> bool:
    """The measurements ``hist`` ((time, point) of the last ``still_window`` s) show a
    moving object: enough of them (``still_min_measurements``) on a least-squares line
    faster than ``final_standoff_max_speed`` when they span (90 % of) the window, twice that
    when they span at least half of it (the first measurements of a still object, taken as
    the camera comes closer, shift by up to 3 cm)."""
    if len(hist) < max(cfg.still_min_measurements, 2):
        return False
    t = np.array([h[0] for h in hist])
    span = t[-1] - t[0]
    if span < 0.5 * cfg.still_window:
        return False
    v = fit_line(t, np.array([h[1] for h in hist]))[1]
    factor = 1.0 if span >= 0.9 * cfg.still_window else 2.0
    return bool(np.hypot(v[0], v[1]) > factor * cfg.final_standoff_max_speed)


def intercepting(
    cfg: GraspConfig, kf: ConstantVelocityKF, line: tuple[Array, Array] | None
) -> bool:
    """Whether the stream follows the online intercept now: ``stream.accel_limit``
    "intercept" and a moving object (the predictor's velocity, no still line)."""
    return (
        cfg.stream.accel_limit == "intercept"
        and cfg.track.use_predictor
        and kf.initialized
        and line is None
        and is_moving(kf.velocity(), cfg.track.final_standoff_max_speed)
    )
