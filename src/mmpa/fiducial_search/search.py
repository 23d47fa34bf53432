"""Fiducial search with a moving base, paper 002 Algorithm 1, behind one strategy interface.

The base drives at a constant commanded speed ``v_b`` and heading ``theta_b``; when fiducial
``i`` comes within reach ``r`` of the (believed) arm base, the tool moves to the fiducial's
expected position; if the photosensor does not trigger, the strategy's search points are
compensated for the base velocity and planned (Algorithm 2) and the tool visits them until
the sensor triggers or the fiducial leaves the reach.

Strategies produce *tool-target offsets* ``d`` (map frame, m; plus roll/pitch offsets in rad
for the tilted search) around the fiducial's expected position: the tool aims at
``p_i + d[:2]`` as seen from the believed base pose. Each interception gives a measurement of
the base position (the base pose under which the tool was on the fiducial), which a
closed-loop strategy feeds to its Kalman filter (eq. 2-5).

This module talks to the robot only through :class:`MovingRobot`; it never imports the twin.
"""

from __future__ import annotations

import math
from abc import ABC, abstractmethod
from dataclasses import dataclass, field
from typing import Literal, Protocol

import numpy as np
from pydantic import BaseModel, ConfigDict, Field

from mmpa.core.errors import InvalidInputError
from mmpa.core.geometry import Array
from mmpa.fiducial_search.planning import (
    ArmLimits,
    PlanningConfig,
    ToolPointIK,
    iterative_plan,
    sample_path,
)
from mmpa.fiducial_search.spiral import SpiralConfig, spiral_points
from mmpa.fiducial_search.stochastic import ConstantVelocityKF, StochasticConfig, grid_samples
from mmpa.robot.description import RobotDescription

__all__ = [
    "TUNED_KF",
    "FiducialResult",
    "MovingRobot",
    "PassResult",
    "SearchConfig",
    "SearchStrategy",
    "Spiral",
    "Stochastic",
    "make_strategy",
    "run_pass",
]


class MovingRobot(Protocol):
    """What Algorithm 1 needs from a mobile manipulator (twin or hardware)."""

    def now(self) -> float:
        """Clock (s)."""
        ...

    def start_base(self, v: float, heading: float) -> None:
        """Drive at ``v`` m/s along map heading ``heading`` rad (held until the pass ends)."""
        ...

    def stop_base(self) -> None: ...

    def joint_positions(self) -> Array:
        """Arm encoders (6,) rad."""
        ...

    def idle(self, duration: float) -> None:
        """Let ``duration`` s pass, arm holding still."""
        ...

    def execute(self, times: Array, q: Array) -> tuple[bool, float, Array]:
        """Follow the joint path ``q`` (T, 6) at ``times`` (T,) s from now, polling the
        photosensor at every sample; stop at the first rising edge of its output. Returns
        ``(triggered, time of the trigger or of the end, joint positions there)``."""
        ...


# --- strategies ----------------------------------------------------------------------------
def _rot(theta: float) -> Array:
    c, s = math.cos(theta), math.sin(theta)
    return np.array([[c, -s], [s, c]])


class SearchStrategy(ABC):
    """Belief about the base plus an ordered stream of search offsets per fiducial."""

    name: str = "strategy"
    closed_loop: bool = False
    dims: int = 2  # 2: [dx, dy]; 4: [dx, dy, droll, dpitch]

    def __init__(self, kf_cfg: StochasticConfig | None = None, closed_loop: bool = False) -> None:
        self.kf_cfg = kf_cfg or StochasticConfig()
        self.closed_loop = closed_loop
        self.kf: ConstantVelocityKF | None = None

    def reset(self, start_xy: Array, velocity: Array, t0: float, rng: np.random.Generator) -> None:
        """Start a pass: the base believed at ``start_xy`` (m) at ``t0`` moving at ``velocity``."""
        self.start = np.asarray(start_xy, float).copy()
        self.v_cmd = np.asarray(velocity, float).copy()
        self.t0 = float(t0)
        self.rng = rng
        self.kf = ConstantVelocityKF.from_config(self.start, self.v_cmd, self.kf_cfg, self.t0)

    def dead_reckoned(self, t: float) -> Array:
        """Open-loop belief: commanded motion from the nominal start (m)."""
        return self.start + self.v_cmd * (t - self.t0)

    def base_estimate(self, t: float) -> Array:
        """Believed base position at ``t`` (KF mean when closed loop)."""
        if self.closed_loop and self.kf is not None:
            return self.kf.position(t)[0]
        return self.dead_reckoned(t)

    def velocity_estimate(self) -> Array:
        if self.closed_loop and self.kf is not None:
            return self.kf.velocity()
        return self.v_cmd.copy()

    def observe(self, t: float, z: Array) -> None:
        """An interception measured the base position ``z`` at ``t`` (eq. 4-5 update)."""
        assert self.kf is not None
        self.kf.predict(t)
        self.kf.update(z)

    def approach_offset(self) -> Array:
        """Offset (dims,) of the first move, to the expected fiducial position."""
        return np.zeros(self.dims)

    @abstractmethod
    def begin(self, t: float) -> None:
        """A new fiducial's search starts at ``t``."""

    @abstractmethod
    def next_offsets(self, n: int) -> Array:
        """Up to ``n`` next offsets (m, dims) in the map frame, most promising first."""


class Spiral(SearchStrategy):
    """Deterministic spiral of eq. 1 around the expected position (paper: open loop, i.e.
    centred on the dead-reckoned base; ``closed_loop=True`` centres it on the KF estimate)."""

    name = "spiral"

    def __init__(
        self,
        cfg: SpiralConfig | None = None,
        kf_cfg: StochasticConfig | None = None,
        closed_loop: bool = False,
    ) -> None:
        super().__init__(kf_cfg, closed_loop)
        self.cfg = cfg or SpiralConfig()
        self._k = 0

    def begin(self, t: float) -> None:
        self._k = 0

    def next_offsets(self, n: int) -> Array:
        k = self._k + 1 + np.arange(n)
        pts = spiral_points(k, self.cfg)
        r = np.linalg.norm(pts, axis=1)
        if r[0] > self.cfg.max_radius:  # the spiral is exhausted: start again from the centre
            self._k = 0
            return self.next_offsets(n)
        pts = pts[r <= self.cfg.max_radius]
        self._k += len(pts)
        return pts


class Stochastic(SearchStrategy):
    """Kalman-filter search (eq. 2-6): grid cells of samples of the predicted base position,
    most probable first. Closed loop by construction (the paper's method)."""

    name = "stochastic"

    def __init__(
        self,
        kf_cfg: StochasticConfig | None = None,
        tilt_sigma: float = 0.0,
        tilt_gamma: float = float(np.deg2rad(2.0)),
    ) -> None:
        super().__init__(kf_cfg, closed_loop=True)
        self.tilt_sigma = float(tilt_sigma)
        self.tilt_gamma = float(tilt_gamma)
        self.dims = 4 if tilt_sigma > 0 else 2
        if self.dims == 4:
            self.name = "stochastic-6dof"
        self._queue = np.zeros((0, self.dims))
        self.last_samples: Array | None = None
        self.tilt_mean = np.zeros(2)  # believed [roll, pitch] correction (rad)
        self.tilt_sd = self.tilt_sigma

    def approach_offset(self) -> Array:
        out = np.zeros(self.dims)
        if self.dims == 4:
            out[2:] = self.tilt_mean
        return out

    def observe_tilt(self, roll: float, pitch: float) -> None:
        """The beam tilt (arm-base frame) under which a fiducial was intercepted: the base
        tilt is constant over a pass, so later searches centre their tilt hypotheses on it."""
        self.tilt_mean = np.array([roll, pitch])
        self.tilt_sd = min(self.tilt_sigma, self.tilt_gamma)

    def begin(self, t: float) -> None:
        assert self.kf is not None
        x, P = self.kf.predicted(t)  # eq. 3
        C = np.array([[1.0, 0, 0, 0], [0, 0, 1.0, 0]])
        mean, cov = C @ x, C @ P @ C.T
        cfg = self.kf_cfg
        if self.dims == 2:
            g = grid_samples(mean, cov, self.rng, cfg.gamma, cfg.n_draws, cfg.mass)
            off = -(g.points - mean)  # a base offset h makes the fiducial appear at p_i - h
        else:  # joint position x tilt grid, scaled so that one grid step is gamma / gamma_a
            k = cfg.gamma / self.tilt_gamma
            scale = np.array([1.0, 1.0, k, k])
            m4 = np.concatenate([mean, self.tilt_mean])
            c4 = np.zeros((4, 4))
            c4[:2, :2] = cov
            c4[2, 2] = c4[3, 3] = self.tilt_sd**2
            g = grid_samples(
                m4 * scale, c4 * np.outer(scale, scale), self.rng, cfg.gamma, cfg.n_draws, cfg.mass
            )
            cells = g.points / scale
            off = np.concatenate([-(cells[:, :2] - mean), cells[:, 2:]], axis=1)
            # first the most probable positions at the believed tilt: a beam within a few
            # degrees of the tube axis still gets through, and the 2D cells are 14 mm apart
            g2 = grid_samples(mean, cov, self.rng, cfg.gamma, cfg.n_draws, cfg.mass)
            n2 = min(len(g2.points), cfg.points_per_round)
            flat = np.concatenate(
                [-(g2.points[:n2] - mean), np.tile(self.tilt_mean, (n2, 1))], axis=1
            )
            off = np.concatenate([flat, off])
        self._queue = off
        self.last_samples = off

    def next_offsets(self, n: int) -> Array:
        if len(self._queue) == 0:
            assert self.last_samples is not None
            self._queue = self.last_samples  # every cell tried: go round again
        out, self._queue = self._queue[:n], self._queue[n:]
        return out


#: Kalman filter tuned to a base whose odometry error grows with distance (beyond the paper):
#: Sigma_ww per metre travelled (1 cm/sqrt(m) in position), Sigma_vv from the catch disc of a
#: 12.7 mm tube (uniform disc of radius r: sigma = r / 2 per axis), speed known to ~1.2 %.
TUNED_KF = StochasticConfig(
    sigma_ww=(1e-4, 1e-8, 1e-4, 1e-8),
    process_noise="per_metre",
    sigma_vv=(1.0e-5, 1.0e-5),
    initial_velocity_sigma=0.0,
    initial_velocity_rel=0.012,
)


def make_strategy(
    name: Literal["spiral", "stochastic", "spiral-closed", "stochastic-tuned", "stochastic-6dof"],
    spiral: SpiralConfig | None = None,
    stochastic: StochasticConfig | None = None,
    tilt_sigma: float = float(np.deg2rad(2.0)),
) -> SearchStrategy:
    if name == "spiral":
        return Spiral(spiral, stochastic)
    if name == "spiral-closed":
        s = Spiral(spiral, stochastic or TUNED_KF, closed_loop=True)
        s.name = "spiral-closed"
        return s
    if name == "stochastic":
        return Stochastic(stochastic)
    if name == "stochastic-tuned":
        s = Stochastic(stochastic or TUNED_KF)
        s.name = "stochastic-tuned"
        return s
    if name == "stochastic-6dof":
        return Stochastic(stochastic or TUNED_KF, tilt_sigma=tilt_sigma)
    raise InvalidInputError(
        f"unknown search strategy {name!r}; choose spiral, spiral-closed, stochastic, "
        "stochastic-tuned, stochastic-6dof"
    )


# --- Algorithm 1 ---------------------------------------------------------------------------
class SearchConfig(BaseModel):
    """Algorithm 1 settings."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    reach: float | None = Field(None, gt=0)  # m, r; None: from the nominal IK minus margin
    reach_margin: float = Field(0.08, ge=0)  # m kept free for the search pattern
    standoff: float = Field(0.03, gt=0)  # m, sensor above the tube's top
    points_per_round: int = Field(20, ge=1)  # n_s per Algorithm 2 batch
    max_search_time: float = Field(60.0, gt=0)  # s per fiducial (bounds a standing base)
    retry_wait: float = Field(0.5, gt=0)  # s to wait when no search point is reachable
    gate: float = Field(0.10, gt=0)  # m: a trigger implying a base this far off is another tube
    planning: PlanningConfig = PlanningConfig()


@dataclass
class FiducialResult:
    """One fiducial of a pass. ``status``: intercepted | missed | out_of_reach.
    ``search_time`` s from the start of the approach to the trigger; ``position_error`` m
    between the base position measured by the interception and the dead-reckoned one (the
    positioning error e_i); ``z`` the measured base position (map, m) at ``t_hit``."""

    index: int
    status: str
    search_time: float = math.nan
    position_error: float = math.nan
    t_start: float = math.nan
    t_hit: float = math.nan
    z: Array | None = None
    estimate_before: Array | None = None  # believed base position at t_hit, before the update
    q_hit: Array | None = None  # joint positions latched at the trigger
    n_points: int = 0
    n_rounds: int = 0
    spurious: int = 0  # triggers rejected by the gate (a neighbouring tube)
    planning_rmse: list[list[float]] = field(default_factory=list)


@dataclass
class PassResult:
    strategy: str
    speed: float
    heading: float
    fiducials: list[FiducialResult]
    duration: float

    @property
    def n_intercepted(self) -> int:
        return sum(f.status == "intercepted" for f in self.fiducials)

    def search_times(self) -> list[float]:
        return [f.search_time for f in self.fiducials if f.status == "intercepted"]


def _reach_interval(
    a0: Array, v: Array, p: Array, r: float, t_now: float, t_ref: float
) -> tuple[float, float] | None:
    """Times ``t >= t_now`` with ``|a0 + v (t - t_ref) - p| <= r`` (an interval or None)."""
    d0 = a0 - p
    vv = float(v @ v)
    if vv < 1e-18:
        return (t_now, math.inf) if float(np.linalg.norm(d0)) <= r else None
    b = float(d0 @ v)
    c = float(d0 @ d0) - r * r
    disc = b * b - vv * c
    if disc < 0:
        return None
    sq = math.sqrt(disc)
    t1, t2 = t_ref + (-b - sq) / vv, t_ref + (-b + sq) / vv
    if t2 < t_now:
        return None
    return max(t1, t_now), t2


@dataclass(frozen=True)
class _PassGeometry:
    """What every fiducial's search of a pass shares: the tool-point IK at the tubes' height,
    the arm limits, the reach ``r`` (m), the base heading's rotation ``R`` (map <- base), the
    arm mount's xy in the base frame (m), the reflectors' height and the arm base's (m)."""

    ik: ToolPointIK
    lim: ArmLimits
    r: float
    R: Array
    mount: Array
    z_reflector: float
    z_arm: float


def run_pass(
    robot: MovingRobot,
    description: RobotDescription,
    fiducials: Array,
    z_reflector: float,
    tube_height: float,
    start_pose2d: Array,
    speed: float,
    heading: float,
    strategy: SearchStrategy,
    cfg: SearchConfig | None = None,
    rng: np.random.Generator | None = None,
) -> PassResult:
    """Algorithm 1 over the fiducials (n, 2) map xy (m), with reflectors at height
    ``z_reflector`` (m) at the bottom of tubes ``tube_height`` (m) tall; the base starts at the
    nominal ``start_pose2d`` and drives at ``speed`` m/s (>= 0) along ``heading`` rad.

    A fiducial that never comes within reach is reported ``out_of_reach`` without moving the
    arm; a standing base (speed 0) searches the fiducials in reach for at most
    ``cfg.max_search_time`` s each. The base faces its direction of travel (differential
    drive), so the yaw of ``start_pose2d`` is taken to be ``heading``.
    """
    cfg = cfg or SearchConfig()
    rng = rng or np.random.default_rng(0)
    P, start = _checked_inputs(fiducials, speed, heading, start_pose2d)
    geo = _pass_geometry(description, z_reflector, tube_height, heading, cfg)
    u = np.array([math.cos(heading), math.sin(heading)])
    robot.start_base(speed, heading)
    t0 = robot.now()
    strategy.reset(start[:2], speed * u, t0, rng)
    results: list[FiducialResult] = []
    for i, p in enumerate(P):
        results.append(_search_fiducial(robot, strategy, geo, cfg, i, p))
    robot.stop_base()
    return PassResult(strategy.name, float(speed), float(heading), results, robot.now() - t0)


def _checked_inputs(
    fiducials: Array, speed: float, heading: float, start_pose2d: Array
) -> tuple[Array, Array]:
    """The fiducials (n, 2) and the start pose (3,) as float arrays; raises
    :class:`InvalidInputError` on a non-finite or malformed input or a negative speed."""
    P = np.asarray(fiducials, dtype=float)
    if P.ndim != 2 or P.shape[1] != 2 or not np.all(np.isfinite(P)):
        raise InvalidInputError(f"fiducials must be finite (n, 2) map positions, got {P.shape}")
    if not (np.isfinite(speed) and speed >= 0):
        raise InvalidInputError(
            f"base speed must be finite and >= 0 m/s, got {speed} (drive backwards by turning "
            "the heading by pi)"
        )
    if not np.isfinite(heading):
        raise InvalidInputError(f"heading must be finite, got {heading}")
    start = np.asarray(start_pose2d, dtype=float)
    if start.shape != (3,) or not np.all(np.isfinite(start)):
        raise InvalidInputError(f"start pose must be finite [x, y, yaw], got {start}")
    return P, start


def _pass_geometry(
    description: RobotDescription,
    z_reflector: float,
    tube_height: float,
    heading: float,
    cfg: SearchConfig,
) -> _PassGeometry:
    """The IK with the sensor ``cfg.standoff`` above the tubes' top and the pivot at half
    their height (arm-base frame), the reach (``cfg.reach`` or the IK's minus the margin)."""
    T_mount = description.T_base_link_arm_base
    z_top = z_reflector + tube_height
    z_arm = T_mount[2, 3]
    ik = ToolPointIK(
        description,
        z_sensor=z_top + cfg.standoff - z_arm,
        z_pivot=z_top - tube_height / 2 - z_arm,
        yaw=0.0,
    )
    lim = ArmLimits.from_description(description)
    r = cfg.reach if cfg.reach is not None else ik.reach_radius() - cfg.reach_margin
    R = _rot(heading)  # a differential drive faces its direction of travel
    return _PassGeometry(ik, lim, r, R, T_mount[:2, 3], z_reflector, z_arm)


def _search_fiducial(
    robot: MovingRobot,
    strategy: SearchStrategy,
    geo: _PassGeometry,
    cfg: SearchConfig,
    i: int,
    p: Array,
) -> FiducialResult:
    """Fiducial ``i`` at ``p`` (map xy, m): wait until it is in reach, move to its expected
    position, then search batches of the strategy's points (Algorithm 2 plans) until the
    sensor triggers on it (within the gate), it leaves the reach or the time is up."""
    R, mount = geo.R, geo.mount
    t = robot.now()
    a_t = strategy.base_estimate(t) + R @ mount
    iv = _reach_interval(a_t, strategy.velocity_estimate(), p, geo.r, t, t)
    if iv is None:
        return FiducialResult(i, "out_of_reach")
    t_in, t_out = iv
    if t_in > t:
        robot.idle(t_in - t)
    t_start = robot.now()
    t_end = min(t_out, t_start + cfg.max_search_time)
    res = FiducialResult(i, "missed", t_start=t_start)
    strategy.begin(t_start)
    hit = False
    first = True
    while not hit and robot.now() < t_end:
        offs = (
            strategy.approach_offset()[None]
            if first
            else strategy.next_offsets(cfg.points_per_round)
        )
        first = False
        tn = robot.now()
        base = strategy.base_estimate(tn)
        a_now = base + R @ mount
        tgt = R.T @ ((p + offs[:, :2]) - a_now).T  # arm-base frame, (2, n)
        pts = np.concatenate([tgt.T, offs[:, 2:]], axis=1)
        vel = np.zeros(strategy.dims)
        vel[:2] = -(R.T @ strategy.velocity_estimate())
        q0 = robot.joint_positions()
        plan = iterative_plan(pts, vel, q0, geo.ik, geo.lim, cfg.planning.n_iter)
        res.planning_rmse.append(plan.rmse.tolist())
        res.n_rounds += 1
        if len(plan.q) == 0:
            robot.idle(min(cfg.retry_wait, max(t_end - robot.now(), 0.0)))
            continue
        times, qs, _ = sample_path(q0, plan.q, geo.lim, cfg.planning.control_dt)
        keep = times <= (t_end - tn)
        if not keep[1:].any():
            break
        res.n_points += len(plan.q)
        hit, t_hit, q_hit = robot.execute(times[keep], qs[keep])
        if hit:
            hit = _intercepted(strategy, geo, cfg, res, p, t_start, t_hit, q_hit)
    return res


def _intercepted(
    strategy: SearchStrategy,
    geo: _PassGeometry,
    cfg: SearchConfig,
    res: FiducialResult,
    p: Array,
    t_start: float,
    t_hit: float,
    q_hit: Array,
) -> bool:
    """A trigger at ``t_hit`` with the arm at ``q_hit``: the base position it measures (the
    beam on the fiducial ``p``); beyond ``cfg.gate`` of the estimate it is a neighbouring tube
    (counted spurious, False); else ``res`` is intercepted, the strategy observes the base
    (and the beam's tilt, 6-DOF search) and True."""
    beam = geo.ik.beam_point(q_hit, geo.z_reflector - geo.z_arm)
    z = p - geo.R @ (geo.mount + beam)
    est = strategy.base_estimate(t_hit)
    if float(np.linalg.norm(z - est)) > cfg.gate:
        res.spurious += 1  # the beam found a neighbouring tube: keep searching
        return False
    res.status = "intercepted"
    res.t_hit = t_hit
    res.search_time = t_hit - t_start
    res.z = z
    res.estimate_before = est
    res.q_hit = q_hit
    res.position_error = float(np.linalg.norm(z - strategy.dead_reckoned(t_hit)))
    strategy.observe(t_hit, z)
    if isinstance(strategy, Stochastic) and strategy.dims == 4:
        d = geo.ik.beam(q_hit)[1]  # d = Rx(roll) Ry(pitch) (0, 0, -1)
        strategy.observe_tilt(math.atan2(d[1], -d[2]), math.asin(float(np.clip(-d[0], -1, 1))))
    return True
