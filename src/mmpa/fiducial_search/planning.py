"""Iterative search planning, paper 002 Algorithm 2, with a real time parameterization.

The tool visits the search points one after the other along jerk-limited, time-optimal
rest-to-rest joint trajectories (ruckig, with the arm's velocity, acceleration and jerk
limits from :class:`~mmpa.robot.description.RobotDescription`). Algorithm 2:

1. plan through the uncompensated samples, giving segment times ``delta^0``;
2. for ``j = 1 .. n_i``: compensate the samples with eq. 7 using ``delta^{j-1}``, map them to
   joint space (nominal IK, tool facing down), re-plan, and take the new ``delta^j``.

The RMSE between the compensated points of consecutive iterations measures convergence
(paper Fig. 3c).

Search points live in the arm-base frame at the planning start: ``[x, y]`` (m) of the beam
at a fixed height, or ``[x, y, roll, pitch]`` (m, rad) for the tilted (6-DOF) search.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from pydantic import BaseModel, ConfigDict, Field
from ruckig import InputParameter, Result, Ruckig, Trajectory

from mmpa.core.errors import InvalidInputError, UnreachableError
from mmpa.core.geometry import Array, inv, make_T, rot_x, rot_y, rot_z
from mmpa.fiducial_search.compensation import arrival_times, compensate
from mmpa.robot import kinematics as kin
from mmpa.robot.description import RobotDescription

__all__ = [
    "ArmLimits",
    "PlanningConfig",
    "SearchPlan",
    "ToolPointIK",
    "iterative_plan",
    "sample_path",
    "segment_durations",
    "segment_trajectory",
]


class PlanningConfig(BaseModel):
    """Algorithm 2 settings (paper: n_i = 5 iterations)."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    n_iter: int = Field(5, ge=0)
    control_dt: float = Field(0.004, gt=0)  # s, path sampling / sensor polling period


@dataclass(frozen=True)
class ArmLimits:
    """Joint limits (6,) each: position, velocity, acceleration, jerk."""

    q_min: Array
    q_max: Array
    v_max: Array
    a_max: Array
    j_max: Array

    @classmethod
    def from_description(cls, robot: RobotDescription) -> ArmLimits:
        a = robot.arm
        lo, hi = a.q_limits
        return cls(lo, hi, np.array(a.qd_max), np.array(a.qdd_max), np.array(a.qddd_max))


def segment_trajectory(q0: Array, q1: Array, lim: ArmLimits) -> Trajectory:
    """Time-optimal jerk-limited rest-to-rest trajectory ``q0 -> q1`` (ruckig)."""
    for q, name in ((q0, "start"), (q1, "target")):
        q = np.asarray(q, dtype=float)
        if q.shape != (6,) or not np.all(np.isfinite(q)):
            raise InvalidInputError(f"{name} configuration must be 6 finite angles")
        if np.any(q < lim.q_min - 1e-9) or np.any(q > lim.q_max + 1e-9):
            raise UnreachableError(f"{name} configuration {np.round(q, 4)} is outside the limits")
    otg = Ruckig(6)
    inp = InputParameter(6)
    inp.current_position = np.asarray(q0, float).tolist()
    inp.target_position = np.asarray(q1, float).tolist()
    inp.max_velocity = lim.v_max.tolist()
    inp.max_acceleration = lim.a_max.tolist()
    inp.max_jerk = lim.j_max.tolist()
    traj = Trajectory(6)
    res = otg.calculate(inp, traj)
    if res not in (Result.Working, Result.Finished):
        raise InvalidInputError(f"ruckig could not time-parameterize the segment: {res}")
    return traj


def segment_durations(q_start: Array, q_points: Array, lim: ArmLimits) -> Array:
    """``delta_k`` (n,) s of the rest-to-rest segments ``q_start -> q_1 -> ... -> q_n``."""
    q_points = np.asarray(q_points, dtype=float).reshape(-1, 6)
    prev = np.asarray(q_start, dtype=float)
    out = np.empty(len(q_points))
    for k, q in enumerate(q_points):
        out[k] = segment_trajectory(prev, q, lim).duration
        prev = q
    return out


def sample_path(
    q_start: Array, q_points: Array, lim: ArmLimits, dt: float
) -> tuple[Array, Array, Array]:
    """Sample the segment chain every ``dt`` s: ``(times (T,), q (T, 6), segment index (T,))``,
    times from 0 (the start configuration) to the end of the last segment."""
    if not (np.isfinite(dt) and dt > 0):
        raise InvalidInputError(f"sampling period must be positive, got {dt}")
    q_points = np.asarray(q_points, dtype=float).reshape(-1, 6)
    times, qs, seg = [np.zeros(1)], [np.asarray(q_start, float)[None]], [np.zeros(1, int)]
    t0, prev = 0.0, np.asarray(q_start, dtype=float)
    for k, q in enumerate(q_points):
        tr = segment_trajectory(prev, q, lim)
        T = float(tr.duration)
        n = max(int(np.ceil(T / dt)), 1)
        ts = np.linspace(T / n, T, n)
        qs.append(np.array([tr.at_time(t)[0] for t in ts]))
        times.append(t0 + ts)
        seg.append(np.full(n, k))
        t0 += T
        prev = q
    return np.concatenate(times), np.concatenate(qs), np.concatenate(seg)


class ToolPointIK:
    """Search point ``[x, y]`` or ``[x, y, roll, pitch]`` (arm-base frame, m / rad) -> joint
    configuration by the NOMINAL analytic IK, nearest the previous configuration, within the
    joint limits.

    The beam points down, tilted by ``Rx(roll) Ry(pitch)``, and passes through the pivot
    ``(x, y, z_pivot)`` (e.g. the tube's mid-height, where a tilt costs the least); the sensor
    sits on the beam at height ``z_sensor``. Sensor orientation
    ``R = Rx(roll) Ry(pitch) Rx(pi) Rz(yaw)``; flange target ``T_sensor inv(T_flange_sensor)``.
    """

    def __init__(
        self, robot: RobotDescription, z_sensor: float, z_pivot: float, yaw: float = 0.0
    ) -> None:
        if not (np.isfinite(z_sensor) and np.isfinite(z_pivot)) or z_sensor <= z_pivot:
            raise InvalidInputError(
                f"the sensor (z={z_sensor}) must be above the pivot (z={z_pivot})"
            )
        self.robot = robot
        self.z_sensor, self.z_pivot = float(z_sensor), float(z_pivot)
        self.lim = ArmLimits.from_description(robot)
        self._T_sensor_flange = inv(robot.photosensor.T_flange_sensor)
        self._R0 = rot_x(np.pi)[:3, :3] @ rot_z(yaw)[:3, :3]

    def T_arm_base_sensor(self, p: Array) -> Array:
        p = np.asarray(p, dtype=float).reshape(-1)
        roll, pitch = (p[2], p[3]) if p.size >= 4 else (0.0, 0.0)
        R = rot_x(roll)[:3, :3] @ rot_y(pitch)[:3, :3] @ self._R0
        d = R[:, 2]
        pivot = np.array([p[0], p[1], self.z_pivot])
        s = (self.z_pivot - self.z_sensor) / d[2]
        return make_T(R, pivot - s * d)

    def __call__(self, p: Array, q_ref: Array) -> Array:
        """Raises :class:`UnreachableError` when the point is out of reach."""
        T = self.T_arm_base_sensor(p) @ self._T_sensor_flange
        return kin.ik_nearest(self.robot.arm.dh, T, q_ref, self.lim.q_min, self.lim.q_max)

    def beam(self, q: Array) -> tuple[Array, Array]:
        """Nominal FK: beam origin (3,) and direction (3,) in the arm-base frame."""
        T = kin.fk(self.robot.arm.dh, q, self.robot.photosensor.T_flange_sensor)
        return T[:3, 3], T[:3, 2]

    def beam_point(self, q: Array, z: float) -> Array:
        """Where the beam crosses the plane at height ``z`` (arm-base frame xy, m)."""
        o, d = self.beam(q)
        if abs(d[2]) < 1e-9:
            return o[:2]
        return (o + (z - o[2]) / d[2] * d)[:2]

    def reach_radius(self, direction: float = np.pi / 2, tol: float = 1e-3) -> float:
        """Largest horizontal distance (m) from the arm-base axis along ``direction`` (rad)
        at which the vertical beam is reachable (bisection on the nominal IK)."""
        u = np.array([np.cos(direction), np.sin(direction)])
        q_ref = np.array(self.robot.arm.home)

        def ok(r: float) -> bool:
            try:
                self(r * u, q_ref)
            except UnreachableError:
                return False
            return True

        lo, hi = 0.3, 2.0
        if not ok(lo):
            raise UnreachableError(
                f"the sensor height {self.z_sensor:.3f} m (arm-base frame) is out of reach"
            )
        while hi - lo > tol:
            mid = 0.5 * (lo + hi)
            lo, hi = (mid, hi) if ok(mid) else (lo, mid)
        return lo


@dataclass(frozen=True)
class SearchPlan:
    """Algorithm 2 output: compensated points (n, d), joint targets (n, 6), segment times
    ``delta`` (n,) s, arrival times (n,) s, ``reachable`` mask of the input samples (the plan
    skips unreachable ones), ``rmse`` (n_iter,) m between consecutive iterations, and
    ``history`` (n_iter + 1, n, d) of the compensated points per iteration."""

    points: Array
    q: Array
    delta: Array
    arrival: Array
    reachable: Array
    rmse: Array
    history: Array

    @property
    def duration(self) -> float:
        return float(self.arrival[-1]) if len(self.arrival) else 0.0


IKFn = Callable[[Array, Array], Array]


def _to_joints(points: Array, q_start: Array, ik: IKFn) -> tuple[Array, Array]:
    q = np.full((len(points), 6), np.nan)
    ok = np.zeros(len(points), bool)
    prev = np.asarray(q_start, float)
    for k, p in enumerate(points):
        try:
            q[k] = ik(p, prev)
        except UnreachableError:
            continue
        ok[k] = True
        prev = q[k]
    return q, ok


def iterative_plan(
    samples: Array,
    velocity: Array,
    q_start: Array,
    ik: IKFn,
    lim: ArmLimits,
    n_iter: int = 5,
    t0: float = 0.0,
) -> SearchPlan:
    """Algorithm 2 for ``samples`` (n, d) in the arm-base frame at the planning start,
    ``velocity`` (d,) of the world seen from the arm base (m/s; zeros for angle components),
    starting at rest at ``q_start``; ``t0`` (s) is when the motion starts after planning.

    Unreachable points (after compensation) are skipped: they get ``delta = 0`` and are left
    out of ``q``/``points``. The RMSE of iteration j compares the compensated points of
    iteration j with those of j - 1 (the first with the uncompensated samples).
    """
    s = np.asarray(samples, dtype=float)
    if s.ndim != 2 or len(s) == 0:
        raise InvalidInputError(f"need samples of shape (n, d) with n >= 1, got {s.shape}")
    if n_iter < 0:
        raise InvalidInputError(f"n_iter must be >= 0, got {n_iter}")
    q_start = np.asarray(q_start, dtype=float)

    def times(points: Array) -> tuple[Array, Array, Array]:
        q, ok = _to_joints(points, q_start, ik)
        delta = np.zeros(len(points))
        if ok.any():
            delta[ok] = segment_durations(q_start, q[ok], lim)
        return q, ok, delta

    q, ok, delta = times(s)
    history = [s]
    rmse = []
    pts = s
    for _ in range(n_iter):
        new = compensate(s, velocity, delta, t0)
        rmse.append(float(np.sqrt(np.mean(np.sum((new - pts) ** 2, axis=1)))))
        pts = new
        history.append(pts)
        q, ok, delta = times(pts)
    return SearchPlan(
        points=pts[ok],
        q=q[ok],
        delta=delta[ok],
        arrival=arrival_times(delta[ok], t0),
        reachable=ok,
        rmse=np.array(rmse),
        history=np.array(history),
    )
