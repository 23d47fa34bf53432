"""The descent of the tracking grasp onto the object (paper 001 §3.2.2, Fig. 5).

The TCP descends to the grasp height (:func:`mmpa.servo.target.grasp_height`, from the top
and the desk, ``arm_base`` z in m) along a vertical :func:`ramp_profile` (at most
``descent.speed`` m/s and ``descent.accel`` m/s^2, less where a joint would need more than
``descent.joint_margin`` of its limits at the start or the end pose: the joint rates of a
unit vertical TCP speed there are ``u = |J^+ e_z|``, :func:`vertical_limits`; a stream not
held to qdd_max descends at ``descent.speed`` throughout, the paper's way). Horizontally the
TCP follows the object: each set-point (``descent.rate_hz``) lies over its predicted position
``arm_lag`` s after it is sent, or on a still object's line, or over the last measurement
without the predictor. For a moving object the predictor keeps taking detections on the upper
part of the descent (``descent.updates``); an acceleration-limited descent stops when one lies
``descent.abort_innovation`` off the prediction (the object turned: ``aborted``). The
encoders say when the TCP arrived (``descent.settle_tol``).

"intercept" (:meth:`Descent.descend_intercept`): every set-point is the next state of a
jerk-limited plan (:mod:`mmpa.servo.intercept`) toward the tool pose over the predicted object
on the vertical ramp, moving with both.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from mmpa.core.errors import InvalidInputError, UnreachableError
from mmpa.core.geometry import Array, inv, make_T
from mmpa.robot.interfaces import Camera, StreamingArm
from mmpa.robot.kinematics import fk, ik_nearest, jacobian
from mmpa.robot.limits import JointLimits
from mmpa.servo.config import GraspConfig
from mmpa.servo.pose import ArmGeometry, intercept_goal, tool_down
from mmpa.servo.predictor import ConstantVelocityKF, fit_line
from mmpa.servo.stream import Segment, Stream
from mmpa.servo.target import grasp_height
from mmpa.servo.tracker import Perception, is_moving

__all__ = ["Descent", "ramp_profile", "vertical_limits"]


def ramp_profile(distance: float, v_max: float, a_max: float) -> tuple[float, Callable]:
    """Rest-to-rest motion over ``distance`` m (>= 0) at most ``v_max`` m/s and ``a_max``
    m/s^2 (trapezoidal speed, triangular when too short to reach ``v_max``): returns
    ``(duration s, s(t))``, ``s(t)`` the distance covered at ``t`` s (``distance`` from the
    duration on); ``a_max = inf``: at ``v_max`` throughout. Raises
    :class:`InvalidInputError` on a negative distance, a non-positive limit or an infinite
    ``v_max``."""
    if not (distance >= 0 and 0 < v_max < np.inf and a_max > 0):
        raise InvalidInputError(
            f"a ramp needs distance >= 0 and positive limits, got {distance}, {v_max}, {a_max}"
        )
    if np.isinf(a_max):
        T = distance / v_max
        return T, lambda t: v_max * min(max(t, 0.0), T)
    v = min(v_max, float(np.sqrt(distance * a_max)))  # peak speed
    t_acc = v / a_max
    duration = distance / v + t_acc if v > 0 else 0.0

    def s(t: float) -> float:
        t = min(max(t, 0.0), duration)
        if t < t_acc:
            return 0.5 * a_max * t * t
        if t > duration - t_acc:
            return distance - 0.5 * a_max * (duration - t) ** 2
        return 0.5 * a_max * t_acc * t_acc + v * (t - t_acc)

    return duration, s


def vertical_limits(
    geom: ArmGeometry,
    q_a: Array,
    q_b: Array,
    qd_max: Array,
    qdd_max: Array,
    v_cap: float,
    a_cap: float,
    margin: float,
) -> tuple[float, float]:
    """The vertical TCP speed (m/s) and acceleration (m/s^2) of a descent between the joint
    poses ``q_a`` and ``q_b`` (6,) that keep every joint within ``margin`` of ``qd_max`` /
    ``qdd_max`` (6,) at both ends, capped at ``v_cap`` / ``a_cap``: with ``u = max(|J^+
    e_z|)`` over the two poses (the joint rates of a unit vertical TCP speed), ``v_z =
    min(v_cap, margin min(qd_max / u))`` and alike for the acceleration."""
    u = np.zeros(6)
    for q_ in (q_a, q_b):
        J = jacobian(geom.dh, q_, geom.T_ft)
        u = np.maximum(u, np.abs(np.linalg.pinv(J) @ np.array([0, 0, 1.0, 0, 0, 0])))
    with np.errstate(divide="ignore"):
        v_z = min(v_cap, margin * float(np.min(qd_max / u)))
        a_z = min(a_cap, margin * float(np.min(qdd_max / u)))
    return v_z, a_z


@dataclass(frozen=True)
class _Plan:
    """A descent's plan: tool rotation ``R`` (3x3), start and grasp heights ``z0``/``zg``
    (m), the ramp ``(duration s, s(t))``, its ``n`` set-points then ``n_settle`` more while
    settling, the set-points' ``limits``, the path-offset time constant ``tau`` (s) and
    whether the object moves."""

    R: Array
    z0: float
    zg: float
    ramp: Callable[[float], float]
    n: int
    n_settle: int
    limits: JointLimits
    tau: float
    moving: bool


class Descent:
    """The descents (``descent`` and ``intercept`` settings) streamed by ``stream``;
    ``aborted``: the last descent stopped on a turn of the object."""

    def __init__(
        self, geom: ArmGeometry, perception: Perception, stream: Stream, cfg: GraspConfig
    ) -> None:
        self.geom = geom
        self.perception = perception
        self.stream = stream
        self.cfg = cfg
        self.aborted = False

    def _join(self, arm: StreamingArm, q_cmd: Array, wait: Callable[[float], None]) -> Callable:
        """The stream from ``q_cmd`` (a new one when called on its own, not from the run),
        and the streaming ``wait``."""
        s = self.stream
        if s.q is None or np.max(np.abs(s.q - q_cmd)) > 1e-6:
            s.start(q_cmd)  # called on its own (not from run)
        return s.streaming(arm, wait)

    def _plan(
        self,
        q_cmd: Array,
        kf: ConstantVelocityKF,
        top_z: float,
        desk_z: float,
        yaw: float | None,
        line: tuple[Array, Array] | None,
    ) -> _Plan:
        """The vertical profile the joints can give (``J^+ e_z`` at the start and the end
        pose) and the set-points' limits."""
        cfg, geom = self.cfg, self.geom
        dh = geom.dh
        dt = 1.0 / cfg.descent.rate_hz
        T0 = fk(dh, q_cmd, geom.T_ft)
        R = T0[:3, :3] if yaw is None else tool_down(yaw)
        z0 = T0[2, 3]
        zg = grasp_height(top_z, desk_z, cfg.descent.pad_clearance, cfg.descent.palm_clearance)
        q_min, q_max = geom.robot.arm.q_limits
        n_settle = int(np.ceil(cfg.descent.settle_max / dt))
        moving = (
            cfg.track.use_predictor
            and kf.initialized
            and is_moving(kf.velocity(), cfg.track.final_standoff_max_speed)
            and line is None
        )
        fraction = (
            cfg.descent.moving_joint_speed_fraction if moving else cfg.descent.joint_speed_fraction
        )
        qd_descend = np.asarray(geom.robot.arm.qd_max) * fraction
        lim = dataclasses.replace(self.stream.limits, qd_max=qd_descend)
        T_end = make_T(R, np.array([T0[0, 3], T0[1, 3], zg])) @ inv(geom.T_ft)
        q_end = ik_nearest(dh, T_end, q_cmd, q_min, q_max)
        d = cfg.descent
        v_z, a_z = vertical_limits(
            geom, q_cmd, q_end, qd_descend, lim.qdd_max, d.speed, d.accel, d.joint_margin
        )
        if not self.stream.limited:  # at constant speed (the joints' speed scaled into qd_max)
            v_z, a_z = cfg.descent.speed, np.inf
        t_down, ramp = ramp_profile(abs(z0 - zg), v_z, a_z)
        n = max(int(np.ceil(t_down / dt - 1e-9)), 1)
        tau = max(cfg.descent.track_time, dt) if self.stream.limited else dt
        return _Plan(R, z0, zg, ramp, n, n_settle, lim, tau, bool(moving))

    def descend(
        self,
        arm: StreamingArm,
        q_cmd: Array,
        kf: ConstantVelocityKF,
        p_meas: Array | None,
        top_z: float,
        desk_z: float,
        yaw: float | None,
        wait: Callable[[float], None],
        camera: Camera | None = None,
        name: str | None = None,
        line: tuple[Array, Array] | None = None,
    ) -> Array:
        """Descent of the TCP to the grasp height along the vertical ramp, set-points at
        ``descent.rate_hz`` (the descent's joint speed, the stream's acceleration limits),
        each over the predicted position ``arm_lag`` s after it is sent (the last measured
        position ``p_meas`` (3,) without the predictor; a still object's ``line``: position
        now (3,), velocity (3,)). For a moving object with ``descent.updates`` (and a
        ``camera``) the predictor keeps taking detections at ``track.rate_hz`` on the upper
        part. Returns the last set-point."""
        cfg, geom = self.cfg, self.geom
        dh = geom.dh
        dt = 1.0 / cfg.descent.rate_hz
        wait = self._join(arm, q_cmd, wait)
        plan = self._plan(q_cmd, kf, top_z, desk_z, yaw, line)
        R, z0, zg, n = plan.R, plan.z0, plan.zg, plan.n
        q_min, q_max = geom.robot.arm.q_limits
        q_ik = q_cmd  # the planned set-point now (the IK branch followed)
        look = plan.moving and cfg.descent.updates and camera is not None and name is not None
        every = max(1, round(cfg.descent.rate_hz / cfg.track.rate_hz))
        for k in range(1, n + 1 + plan.n_settle):
            if look and k % every == 0 and k <= n:
                assert camera is not None and name is not None
                if self._turned(arm, camera, name, kf, zg):
                    self.aborted = True  # the object turned: track on from here
                    return q_cmd
            if cfg.track.use_predictor and line is not None:
                p = line[0] + line[1] * (k * dt + cfg.descent.arm_lag)
            elif cfg.track.use_predictor and kf.initialized:
                p = kf.position(ahead=dt + cfg.descent.arm_lag)
            else:
                p = p_meas
            assert p is not None
            if k > n:  # arrived? (encoders, nominal kinematics): close as soon as it is there
                z_meas = fk(dh, np.asarray(arm.joint_positions(), float), geom.T_ft)[2, 3]
                if abs(z_meas - zg) < cfg.descent.settle_tol:
                    break
            z = zg if k >= n else z0 + np.sign(zg - z0) * plan.ramp(k * dt)
            T = make_T(R, np.array([p[0], p[1], z])) @ inv(geom.T_ft)
            q = ik_nearest(dh, T, q_ik, q_min, q_max)
            if np.max(np.abs(q - q_ik)) > 0.5:
                raise UnreachableError("the descent needs a jump in joint space")
            # the path's joint velocity, plus closing the set-point's offset from the path
            qdot = (q - q_ik) / dt + (q_ik - q_cmd) / plan.tau
            q_cmd = self.stream.plan(Segment(dt, qdot, plan.limits))
            q_ik = q
            wait(dt)
            kf.predict(dt)
        if cfg.descent.close_delay > 0:
            wait(cfg.descent.close_delay)
        return q_cmd

    def _turned(
        self, arm: StreamingArm, camera: Camera, name: str, kf: ConstantVelocityKF, zg: float
    ) -> bool:
        """A detection on the way down (the TCP more than ``update_height`` above ``zg``)
        updated the predictor and lies ``abort_innovation`` off the prediction while the
        stream is acceleration-limited: the object turned."""
        cfg = self.cfg.descent
        q_now = np.asarray(arm.joint_positions(), float)
        z_now = fk(self.geom.dh, q_now, self.geom.T_ft)[2, 3]
        if z_now - zg > cfg.update_height:
            inn = self.update(camera, name, q_now, kf)
            abort = cfg.abort_innovation
            if self.stream.limited and abort > 0 and inn is not None and inn > abort:
                return True
        return False

    def update(self, camera: Camera, name: str, q: Array, kf: ConstantVelocityKF) -> float | None:
        """One detection during the descent: the predictor takes it when the box keeps
        ``descent.update_margin`` of the image clear and lies within the gate; returns its
        innovation (m), None when not taken."""
        frame = camera.capture()
        det, meas = self.perception.measure(frame, name, q, kf)
        if meas is None or det is None:
            return None
        h, w = frame.color.shape[:2]
        x1, y1, x2, y2 = det.box
        m = self.cfg.descent.update_margin
        if min(x1 / w, y1 / h) < m or max(x2 / w, y2 / h) > 1.0 - m:
            return None
        if np.linalg.norm(meas.p - kf.position()) <= self.cfg.predictor.gate:
            kf.update(meas.p)
            return kf.innovation
        return None

    def descend_intercept(
        self,
        arm: StreamingArm,
        q_cmd: Array,
        kf: ConstantVelocityKF,
        top_z: float,
        desk_z: float,
        yaw: float | None,
        wait: Callable[[float], None],
        camera: Camera | None = None,
        name: str | None = None,
        hist: list[tuple[float, Array]] | None = None,
        clock: Callable[[], float] | None = None,
    ) -> Array:
        """Descent onto a moving object by the online intercept ("intercept"): every
        ``1 / descent.rate_hz`` s the goal is the tool pose over the predicted object position
        (the predictor, or the line of ``intercept.line_window``) at the height of the
        vertical ramp down to the grasp height (within ``descent.joint_margin`` of the
        intercept's joint limits at the start and the end pose), moving with the object and
        the ramp (:func:`mmpa.servo.pose.intercept_goal`), the set-points the jerk-limited
        plans toward it; the predictor keeps taking detections (``descent.updates``) above
        ``intercept.update_height``. Ends when the encoders say the TCP is near the grasp
        height (``intercept.settle_tol``), at most ``intercept.descend_max`` s, or stops
        (``aborted``) when a detection lies ``intercept.abort_innovation`` off the
        prediction (the object turned)."""
        cfg, geom = self.cfg, self.geom
        ic = cfg.intercept
        dh = geom.dh
        dt = 1.0 / cfg.descent.rate_hz
        wait = self._join(arm, q_cmd, wait)
        zg = grasp_height(top_z, desk_z, cfg.descent.pad_clearance, cfg.descent.palm_clearance)
        if yaw is None:
            R0 = fk(dh, q_cmd, geom.T_ft)[:3, :3]
            yaw = float(np.arctan2(R0[1, 0], R0[0, 0]))
        look = cfg.descent.updates and camera is not None and name is not None
        every = max(1, round(cfg.descent.rate_hz / cfg.track.rate_hz))
        z0, sign, ramp, n_max = self._intercept_ramp(q_cmd, zg, yaw, dt)
        line = _descent_line(hist, ic.line_window) if clock is not None else None
        for k in range(1, n_max + 1):
            z_now = fk(dh, np.asarray(arm.joint_positions(), float), geom.T_ft)[2, 3]
            if abs(z_now - zg) < ic.settle_tol:
                break
            if look and k % every == 0 and z_now - zg > ic.update_height:
                assert camera is not None and name is not None
                inn = self._intercept_update(arm, camera, name, kf)
                abort = ic.abort_innovation
                if abort > 0 and inn is not None and inn > abort:
                    self.aborted = True  # the object turned: track on from here
                    return q_cmd
            if line is not None and clock is not None:
                p = line[0] + line[1] * (clock() - line[2])
                v_obj = line[1]
            else:
                p, v_obj = kf.position(), kf.velocity()
            # the goal's TCP on the ramp (the object point is its top)
            t_k = k * dt
            z_k = z0 + sign * ramp(t_k)
            vz_k = sign * (ramp(t_k + 1e-3) - ramp(t_k)) / 1e-3
            q_goal, v_goal = intercept_goal(
                geom, q_cmd, np.array([p[0], p[1], z_k]), v_obj, 0.0, yaw,
                ic.lead, cfg.ibvs.damping, vz_k,
            )  # fmt: skip
            q_cmd = self.stream.send_intercept(q_goal, v_goal, dt, ic.descend_time)
            wait(dt)
            kf.predict(dt)
        if cfg.descent.close_delay > 0:
            wait(cfg.descent.close_delay)
        return q_cmd

    def _intercept_ramp(
        self, q_cmd: Array, zg: float, yaw: float, dt: float
    ) -> tuple[float, float, Callable[[float], float], int]:
        """The intercept descent's vertical ramp from the TCP's height at ``q_cmd`` down to
        ``zg`` (a joint-space plan straight to the grasp pose bows the TCP 2 cm sideways on
        the way and the pads hit the ball), as fast as ``descent.joint_margin`` of the
        intercept's joint limits allow at the start and the end pose: ``(z0 m, sign, s(t),
        set-points at most)``."""
        cfg, geom = self.cfg, self.geom
        lim = self.stream.ilim
        n_max = int(np.ceil(cfg.intercept.descend_max / dt))
        T0 = fk(geom.dh, q_cmd, geom.T_ft)
        z0 = float(T0[2, 3])
        T_end = make_T(tool_down(yaw), np.array([T0[0, 3], T0[1, 3], zg])) @ inv(geom.T_ft)
        q_end = ik_nearest(geom.dh, T_end, q_cmd, geom.q_lo, geom.q_hi)
        d = cfg.descent
        v_z, a_z = vertical_limits(
            geom, q_cmd, q_end, lim.qd_max, lim.qdd_max, d.speed, d.accel, d.joint_margin
        )
        t_down, ramp = ramp_profile(abs(z0 - zg), v_z, a_z)
        sign = float(np.sign(zg - z0))
        n_max = max(n_max, int(np.ceil((t_down + cfg.descent.settle_max) / dt)))
        return z0, sign, ramp, n_max

    def _intercept_update(
        self, arm: StreamingArm, camera: Camera, name: str, kf: ConstantVelocityKF
    ) -> float | None:
        """A detection on the intercept descent: with ``intercept.weak_updates`` the weak
        boxes on the track count too (as the tracking's); returns the innovation (m) when
        the predictor took it."""
        cfg = self.cfg
        q_now = np.asarray(arm.joint_positions(), float)
        if not cfg.intercept.weak_updates:
            return self.update(camera, name, q_now, kf)
        _, meas = self.perception.measure(camera.capture(), name, q_now, kf, track=[kf.position()])
        if meas is not None and np.linalg.norm(meas.p - kf.position()) <= cfg.predictor.gate:
            kf.update(meas.p)
            return kf.innovation
        return None


def _descent_line(
    hist: list[tuple[float, Array]] | None, window: float
) -> tuple[Array, Array, float] | None:
    """The prediction of the intercept descent: the least-squares line ``(p (3,), v (3,),
    time of p s)`` through the measurements of the last ``window`` s (``hist``: (time,
    point)) when there are enough, else None (the predictor, whose velocity follows turns,
    and noise with them)."""
    if not (window > 0 and hist):
        return None
    recent = [h for h in hist if h[0] >= hist[-1][0] - window]
    t_r = np.array([h[0] for h in recent])
    if len(recent) >= 4 and t_r[-1] - t_r[0] >= 0.5 * window:
        p_l, v_l = fit_line(t_r, np.array([h[1] for h in recent]))
        return (p_l, v_l, float(t_r[-1]))
    return None
