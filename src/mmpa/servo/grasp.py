"""The tracking grasp (paper 001 §3.2.2, Fig. 5, §4.3.3): detect, servo, approach, close, lift.

:class:`TrackingGrasp` runs over the robot interfaces (an arm that accepts streaming set-points
``command(q)``, a gripper, an RGB-D camera, a base) and a ``wait(dt)`` clock (the twin steps
its physics; a real robot sleeps). Each tick (``rate_hz``): capture, detect the named object,
locate its center in ``arm_base`` (nominal kinematics), update the constant-velocity Kalman
filter, and run IBVS (eq. 10-12) toward the tracking point ``standoff`` above the object with
the object's estimated velocity as feed-forward, plus the null-space manipulability term
(eq. 13-14). When the error stays small the gripper descends along a straight line to the
(predicted) grasp point, closes and lifts. When the object leaves the view the arm holds
still and waits for it to reappear (the paper's behaviour); with the predictor it first keeps
following the prediction for ``coast_time``. The base creeps forward when the object lies
beyond ``reach_limit``. Every set-point is checked against the joint limits and the joint
speed limits before it is sent.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from pydantic import BaseModel, ConfigDict, Field

from mmpa.errors import InvalidInputError, MMPAError, UnknownNameError, UnreachableError
from mmpa.geometry import Array, apply, inv, make_T
from mmpa.perception.locate import DepthMissingError, deproject, locate, look_at
from mmpa.perception.preprocess import dark_preprocess, is_dark
from mmpa.robot.description import RobotDescription
from mmpa.robot.kinematics import fk, ik_nearest, jacobian
from mmpa.servo.ibvs import (
    IBVSConfig,
    camera_velocity,
    desired_point,
    limit_velocity,
    orientation_velocity,
    pinv,
)
from mmpa.servo.nullspace import manipulability_gradient, null_space_projector
from mmpa.servo.predictor import ConstantVelocityKF, PredictorConfig

__all__ = ["GraspConfig", "GraspResult", "TrackingGrasp", "look_configuration"]

SYMMETRIC = {"tennis_ball", "yida_bottle", "water_bottle", "paper_cup", "glue_stick"}


class GraspConfig(BaseModel):
    model_config = ConfigDict(extra="forbid")
    ibvs: IBVSConfig = IBVSConfig()
    predictor: PredictorConfig = PredictorConfig()
    use_predictor: bool = True
    rate_hz: float = Field(20.0, gt=0)
    align_tol: float = Field(0.012, gt=0)  # m, lateral error of the tracking point
    align_ticks: int = Field(3, ge=1)
    final_standoff: float = Field(0.16, gt=0)  # m: last tracking height before the descent
    descend_time: float = Field(0.3, gt=0)  # s, blind straight-line descent
    close_delay: float = Field(0.05, ge=0)  # s from the end of the descent to closing
    coast_time: float = Field(1.0, ge=0)  # s of following the prediction without detections
    max_time: float = Field(25.0, gt=0)  # s
    lift: float = Field(0.12, gt=0)  # m
    pad_clearance: float = Field(0.024, gt=0)  # m, TCP above the desk at the lowest
    null_gain: float = Field(2.0, ge=0)
    reach_limit: float = Field(0.72, gt=0)  # m, horizontal from the arm base
    base_speed: float = Field(0.08, ge=0)
    # the paper's dark preprocessing; off: measured to hurt a detector trained on dark images
    preprocess_dark: bool = False
    center_correction: bool = True  # improvement: object center behind the surface point
    axis_from_depth: bool = True  # improvement: principal axis of the depth foreground
    joint_margin: float = Field(0.05, ge=0)  # rad kept from the joint limits


@dataclass
class GraspResult:
    """``closed_on_object``: the fingers stopped on something; ``reason``: "grasped",
    "not found", "unreachable", "timeout", "depth"; times in s."""

    closed_on_object: bool
    reason: str
    detected_first: bool
    time_to_grasp: float
    ticks: int
    lost_ticks: int
    detect_ms: list[float] = field(default_factory=list)
    loop_s: list[float] = field(default_factory=list)


def look_configuration(
    robot: RobotDescription, target_arm_base: Array, height: float, q_ref: Array | None = None
) -> Array:
    """Joint angles (6,) with the wrist camera ``height`` m above ``target_arm_base`` looking
    straight down, image up = arm_base +x (nominal IK). Raises UnreachableError."""
    t = np.asarray(target_arm_base, float)
    T_cam = look_at(t + np.array([0.0, 0.0, height]), t, up_hint=(1.0, 0.0, 0.0))
    T_fl = T_cam @ inv(robot.camera.T_flange_camera)
    q_min, q_max = robot.arm.q_limits
    return ik_nearest(
        robot.arm.dh,
        T_fl,
        np.asarray(robot.arm.home if q_ref is None else q_ref, float),
        q_min,
        q_max,
    )


def _tool_down(yaw: float) -> Array:
    """Tool rotation: z down, x along ``(cos yaw, sin yaw, 0)``."""
    x = np.array([np.cos(yaw), np.sin(yaw), 0.0])
    z = np.array([0.0, 0.0, -1.0])
    return np.column_stack([x, np.cross(z, x), z])


class TrackingGrasp:
    def __init__(self, detector: Any, robot: RobotDescription, cfg: GraspConfig | None = None):
        self.det = detector
        self.robot = robot
        self.cfg = cfg or GraspConfig()
        rb = robot
        self._T_fc = rb.camera.T_flange_camera
        self._T_ft = rb.gripper.T_flange_tcp
        self._P_star = desired_point(self._T_fc, self._T_ft, self.cfg.ibvs.standoff)
        q_min, q_max = rb.arm.q_limits
        self._q_lo = q_min + self.cfg.joint_margin
        self._q_hi = q_max - self.cfg.joint_margin
        self._qd = np.asarray(rb.arm.qd_max) * self.cfg.ibvs.joint_speed_fraction
        self._axis_ok = False

    # ------------------------------------------------------------------ perception
    def _measure(self, frame: Any, name: str, q: Array, kf: ConstantVelocityKF) -> tuple[Any, Any]:
        img = frame.color
        if self.cfg.preprocess_dark and is_dark(img):
            img = dark_preprocess(img)
        dets = [d for d in self.det.detect(img) if d.name == name]
        if not dets:
            return None, None
        T_cam = fk(self.robot.arm.dh, q) @ self._T_fc
        K = frame.intrinsics.K
        if kf.initialized:  # the detection nearest the prediction
            p = kf.position()
            P = apply(inv(T_cam), p)
            if P[2] > 0:
                uv = K[:2, :2] @ (P[:2] / P[2]) + K[:2, 2]
                dets.sort(key=lambda d: float(np.linalg.norm(d.center - uv)))
        d = dets[0]
        try:
            loc = locate(d.box, frame.depth, K, T_cam)
        except DepthMissingError:
            return d, None
        # desk height: depth on a ring just outside the box (improvement)
        dz = self._desk_z(frame, d.box, K, T_cam)
        self._axis_ok = False
        if self.cfg.axis_from_depth and dz is not None:
            axis = self._axis_from_depth(frame, d.box, K, T_cam, dz)
            if axis is not None:
                loc = locate(d.box, frame.depth, K, T_cam, axis_2d=axis)
                self._axis_ok = True
        return d, (loc, dz)

    @staticmethod
    def _axis_from_depth(
        frame: Any, box: Array, K: Array, T_cam: Array, desk_z: float
    ) -> Array | None:
        """Improvement over the longest box side: the principal axis of the pixels in the box
        that stand above the desk (depth image), so diagonal objects get the right axis."""
        h, w = frame.depth.shape
        x1, y1, x2, y2 = np.clip(np.round(box), 0, [w, h, w, h]).astype(int)
        d = frame.depth[y1:y2, x1:x2]
        if d.size < 9:
            return None
        vv, uu = np.mgrid[y1:y2, x1:x2]
        rays = np.stack([(uu - K[0, 2]) / K[0, 0], (vv - K[1, 2]) / K[1, 1], np.ones_like(d)], -1)
        z_arm = (rays * d[..., None]) @ T_cam[2, :3] + T_cam[2, 3]
        mask = (d > 0) & (z_arm > desk_z + 0.008)
        if mask.sum() < 20:
            return None
        c = np.cov(np.stack([uu[mask], vv[mask]]).astype(float))
        ev, V = np.linalg.eigh(c)
        if ev[1] < 1.5 * max(ev[0], 1e-9):  # no clear long axis (ball, cube, upright cylinder)
            return None
        return V[:, 1]

    @staticmethod
    def _desk_z(frame: Any, box: Array, K: Array, T_cam: Array) -> float | None:
        h, w = frame.depth.shape
        x1, y1, x2, y2 = box
        m = 0.15 * max(x2 - x1, y2 - y1) + 4
        xs = np.clip(np.array([x1 - m, x2 + m]), 0, w - 1).astype(int)
        ys = np.clip(np.array([y1 - m, y2 + m]), 0, h - 1).astype(int)
        pts = []
        for u in np.linspace(xs[0], xs[1], 12).astype(int):
            for v in (ys[0], ys[1]):
                z = frame.depth[v, u]
                if z > 0:
                    pts.append(apply(T_cam, deproject(u, v, float(z), K))[2])
        for v in np.linspace(ys[0], ys[1], 12).astype(int):
            for u in (xs[0], xs[1]):
                z = frame.depth[v, u]
                if z > 0:
                    pts.append(apply(T_cam, deproject(u, v, float(z), K))[2])
        if len(pts) < 5:
            return None
        return float(np.percentile(pts, 30))

    # ------------------------------------------------------------------ control
    def _send(self, arm: Any, q_cmd: Array) -> Array:
        q_cmd = np.clip(q_cmd, self._q_lo, self._q_hi)
        arm.command(q_cmd)
        return q_cmd

    def servo_step(
        self,
        q_cmd: Array,
        p_obj: Array,
        v_obj: Array | None,
        yaw: float | None,
        dt: float,
        standoff: float | None = None,
    ) -> tuple[Array, Array]:
        """One IBVS + null-space step from set-point ``q_cmd`` toward object ``p_obj``
        (arm_base) with the tracking point ``standoff`` m above it (default: the config's);
        returns ``(q_next, [lateral error, depth error] m)``."""
        cfg = self.cfg
        dh = self.robot.arm.dh
        T_fl = fk(dh, q_cmd)
        T_cam = T_fl @ self._T_fc
        P = apply(inv(T_cam), p_obj)
        if P[2] <= 0.05:
            raise UnreachableError("the object is behind or too close to the camera")
        P_star = (
            self._P_star if standoff is None else desired_point(self._T_fc, self._T_ft, standoff)
        )
        v_cam = camera_velocity(P, P_star, cfg.ibvs.gain)
        n = np.linalg.norm(v_cam)
        if n > cfg.ibvs.max_linear_speed:
            v_cam *= cfg.ibvs.max_linear_speed / n
        R_tool = T_fl[:3, :3] @ self._T_ft[:3, :3]
        if yaw is None:  # keep the current heading of the tool x axis
            x = R_tool[:, 0]
            yaw_now = float(np.arctan2(x[1], x[0]))
        else:
            yaw_now = yaw
        w = orientation_velocity(R_tool, _tool_down(yaw_now), cfg.ibvs.orientation_gain)
        v = T_cam[:3, :3] @ v_cam
        if v_obj is not None:
            v = v + v_obj
        J = jacobian(dh, q_cmd, self._T_fc)
        if yaw is None and cfg.null_gain > 0:  # 5-D task, eq. 13 in the free yaw
            Jt = J[:5]
            qdot = pinv(Jt, cfg.ibvs.damping) @ np.concatenate([v, w[:2]])
            g = manipulability_gradient(dh, q_cmd, self._T_ft)
            qdot += null_space_projector(Jt, cfg.ibvs.damping) @ (cfg.null_gain * g)
        else:
            qdot = pinv(J, cfg.ibvs.damping) @ np.concatenate([v, w])
        qdot = limit_velocity(qdot, self._qd)
        lateral = P[:2] - P_star[:2] * P[2] / P_star[2]
        return q_cmd + qdot * dt, np.array([np.linalg.norm(lateral), abs(P[2] - P_star[2])])

    def run(
        self,
        name: str,
        arm: Any,
        gripper: Any,
        camera: Any,
        base: Any,
        wait: Callable[[float], None],
        clock: Callable[[], float],
        on_event: Callable[[str], None] | None = None,
    ) -> GraspResult:
        """Track and grasp the object called ``name``; the arm starts at a view of the desk."""
        import time

        classes = self.det.cfg.classes
        if name not in classes:
            raise UnknownNameError("object", name, list(classes))
        if not hasattr(arm, "command"):
            raise InvalidInputError("the tracking grasp needs an arm with streaming command(q)")
        cfg = self.cfg
        dt = 1.0 / cfg.rate_hz
        kf = ConstantVelocityKF(cfg.predictor)
        q_cmd = np.asarray(arm.joint_positions(), float)
        t0 = clock()
        last_seen = -np.inf
        p_meas = None
        desk_z: float | None = None
        top_z: float | None = None
        center_z = np.inf
        yaw = None
        aligned = 0
        standoff = cfg.ibvs.standoff
        ticks = lost = 0
        first = None
        res = GraspResult(False, "timeout", False, float("nan"), 0, 0)
        gripper.open()
        while clock() - t0 < cfg.max_time:
            w0 = time.perf_counter()
            ticks += 1
            q_meas = np.asarray(arm.joint_positions(), float)
            frame = camera.capture()
            d0 = time.perf_counter()
            d, meas = self._measure(frame, name, q_meas, kf)
            res.detect_ms.append(1000 * (time.perf_counter() - d0))
            if first is None:
                first = d is not None
            now = clock()
            if meas is not None:
                loc, dz = meas
                p_meas = loc.center_arm_base if cfg.center_correction else loc.p_arm_base
                kf.update(p_meas)
                top_z = float(loc.p_arm_base[2])
                center_z = float(p_meas[2])
                if dz is not None:
                    desk_z = dz if desk_z is None else 0.7 * desk_z + 0.3 * dz
                if name not in SYMMETRIC:
                    yaw = self._grasp_yaw(loc, d.box, q_cmd, yaw)
                last_seen = now
            else:
                lost += 1
            coasting = cfg.use_predictor and kf.initialized and now - last_seen < cfg.coast_time
            if now - last_seen > 1e-9 and not coasting and meas is None:
                # paper: stop and wait for the object to reappear
                q_cmd = self._send(arm, q_cmd)
                base.stop()
                aligned = 0
                standoff = cfg.ibvs.standoff
                wait(dt)
                kf.predict(dt)
                res.loop_s.append(time.perf_counter() - w0)
                continue
            if cfg.use_predictor:
                p_obj = kf.position(ahead=dt)
                v_obj = kf.velocity()
            else:
                p_obj, v_obj = p_meas, None
            assert p_obj is not None
            reach = float(np.hypot(p_obj[0], p_obj[1]))
            if reach > cfg.reach_limit:
                base.set_velocity(cfg.base_speed, 0.0)
            else:
                base.stop()
            try:
                q_next, err = self.servo_step(q_cmd, p_obj, v_obj, yaw, dt, standoff)
            except UnreachableError:
                res.reason = "unreachable"
                break
            q_cmd = self._send(arm, q_next)
            aligned = aligned + 1 if (err[0] < cfg.align_tol and err[1] < 0.03) else 0
            wait(dt)
            kf.predict(dt)
            res.loop_s.append(time.perf_counter() - w0)
            if aligned >= cfg.align_ticks and standoff > cfg.final_standoff:
                standoff, aligned = cfg.final_standoff, 0  # closer, still in view
                continue
            if aligned >= cfg.align_ticks and desk_z is not None and top_z is not None:
                base.stop()
                try:
                    q_cmd = self._descend(
                        arm,
                        q_cmd,
                        kf,
                        p_meas,
                        top_z,
                        desk_z,
                        center_z,
                        yaw,
                        wait,
                        clock,
                        camera,
                        name,
                    )
                except (UnreachableError, MMPAError):
                    res.reason = "unreachable"
                    break
                if on_event:
                    on_event("close")
                held = bool(gripper.close())
                self._lift(arm, q_cmd)
                res.closed_on_object = held
                res.reason = "grasped" if held else "missed"
                res.time_to_grasp = clock() - t0
                break
        base.stop()
        res.detected_first = bool(first)
        res.ticks, res.lost_ticks = ticks, lost
        if res.reason == "timeout" and p_meas is None:
            res.reason = "not found"
        return res

    def _grasp_yaw(self, loc: Any, box: Array, q_cmd: Array, yaw: float | None) -> float | None:
        """Tool x along the graspable edge (fingers close across it), the equivalent modulo pi
        nearest the current tool heading; kept when the box is nearly square."""
        b = np.asarray(box)
        bw, bh = b[2] - b[0], b[3] - b[1]
        if self.cfg.axis_from_depth and not self._axis_ok:
            return yaw
        if not self.cfg.axis_from_depth and max(bw, bh) < 1.3 * min(bw, bh):
            return yaw
        a = loc.axis_arm_base
        if abs(a[2]) > 0.9:
            return yaw
        target = float(np.arctan2(a[1], a[0]))
        T = fk(self.robot.arm.dh, q_cmd, self._T_ft)
        now = float(np.arctan2(T[1, 0], T[0, 0]))
        k = np.round((now - target) / np.pi)
        return target + k * np.pi

    def _grasp_z(self, top_z: float, desk_z: float, center_z: float = np.inf) -> float:
        return max(desk_z + self.cfg.pad_clearance, min(0.5 * (top_z + desk_z), center_z))

    def _descend(
        self,
        arm: Any,
        q_cmd: Array,
        kf: ConstantVelocityKF,
        p_meas: Array | None,
        top_z: float,
        desk_z: float,
        center_z: float,
        yaw: float | None,
        wait: Callable[[float], None],
        clock: Callable[[], float],
        camera: Any,
        name: str,
    ) -> Array:
        """Straight-line descent of the TCP onto the (predicted) grasp point."""
        cfg = self.cfg
        dh = self.robot.arm.dh
        dt = 1.0 / cfg.rate_hz
        T0 = fk(dh, q_cmd, self._T_ft)
        R = T0[:3, :3]
        if yaw is not None:
            R = _tool_down(yaw)
        z0 = T0[2, 3]
        zg = self._grasp_z(top_z, desk_z, center_z)
        n = max(int(np.ceil(cfg.descend_time / dt)), 1)
        q_min, q_max = self.robot.arm.q_limits
        for k in range(1, n + 1):
            remaining = (n - k) * dt
            if cfg.use_predictor and kf.initialized:
                p = kf.position(ahead=remaining + cfg.close_delay)
            else:
                p = p_meas
            s = k / n
            target = np.array([p[0], p[1], z0 + s * (zg - z0)])
            T = make_T(R, target) @ inv(self._T_ft)
            q = ik_nearest(dh, T, q_cmd, q_min, q_max)
            if np.max(np.abs(q - q_cmd)) > 0.5:
                raise UnreachableError("the descent needs a jump in joint space")
            qdot = limit_velocity((q - q_cmd) / dt, self._qd)
            q_cmd = self._send(arm, q_cmd + qdot * dt)
            wait(dt)
            kf.predict(dt)
        wait(cfg.close_delay)
        return q_cmd

    def _lift(self, arm: Any, q_cmd: Array) -> None:
        dh = self.robot.arm.dh
        T = fk(dh, q_cmd)
        T[2, 3] += self.cfg.lift
        q_min, q_max = self.robot.arm.q_limits
        q = ik_nearest(dh, T, q_cmd, q_min, q_max)
        arm.move_joints(q)
