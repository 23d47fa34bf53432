"""A base that drives a constant commanded speed and heading with real errors, in the twin's
kinematic mode (paper 002 passes; fast enough for 180 passes in minutes).

Truth model (all draws from the seeded generator handed in):

- the start is the nominal pose plus ``N(0, sigma^2 I)`` in x, y with
  ``sigma = r99 / sqrt(2 ln 100)``, so the base is within ``r99`` (1 cm) of nominal 99 % of the
  time (paper 002 §3.2);
- the motion follows the command up to a per-pass speed scale error and heading bias (wheel
  radius and alignment errors), and is cut into increments of ``increment`` m whose
  ``(rot1, trans, rot2)`` are perturbed by the odometry motion model of the error model
  (:func:`mmpa.backends.twin.noise.odometry_increment_noise`, Thrun Table 5.6) with its own alphas:
  the reference AMCL alphas (0.05) are a filter's deliberately pessimistic assumption and would
  put a straight-driving base decimetres off after a metre;
- an optional constant base tilt (roll, pitch) for an uneven floor (6-DOF search study).

The arm follows its commanded joint path exactly (position control; the true DH of the
twin differs from the nominal one). The photosensor is the twin's own ray cast against the
MJCF collimator tubes; the base and arm poses are set kinematically
(:meth:`SimWorld.set_kinematic_state`) at every control sample.
"""

from __future__ import annotations

import math
from collections.abc import Callable

import numpy as np
from pydantic import BaseModel, ConfigDict, Field

from mmpa.backends.twin.error_model import OdometryNoise
from mmpa.backends.twin.noise import odometry_increment_noise
from mmpa.backends.twin.world import SimWorld
from mmpa.core.errors import InvalidInputError
from mmpa.core.geometry import Array

__all__ = ["KinematicMovingBase", "MovingBaseNoise"]


class MovingBaseNoise(BaseModel):
    """Errors of a base driving straight at constant speed."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    initial_radius_99: float = Field(0.01, ge=0)  # m: start within this of nominal 99 %
    speed_scale_sigma: float = Field(0.01, ge=0)  # relative, per pass
    heading_bias_sigma_deg: float = Field(0.3, ge=0)  # per pass
    increment: float = Field(0.05, gt=0)  # m of travel per noisy increment
    motion: OdometryNoise = OdometryNoise(alpha1=1e-3, alpha2=1e-3, alpha3=1e-3, alpha4=1e-3)
    tilt_sigma_deg: float = Field(0.0, ge=0)  # constant base roll/pitch per pass


class KinematicMovingBase:
    """:class:`~mmpa.fiducial_search.search.MovingRobot` on the twin in kinematic mode."""

    def __init__(
        self,
        world: SimWorld,
        start_pose2d: Array,
        noise: MovingBaseNoise | None = None,
        rng: np.random.Generator | None = None,
        q_arm: Array | None = None,
        max_distance: float = 6.0,
        on_state: Callable[[], None] | None = None,
    ) -> None:
        self.world = world
        #: called after every state the twin is set to (e.g. a recorder's ``on_kinematic``)
        self.on_state = on_state
        self.noise = noise or MovingBaseNoise()
        self.rng = rng or np.random.default_rng(0)
        n = self.noise
        start = np.asarray(start_pose2d, float)
        if start.shape != (3,) or not np.all(np.isfinite(start)):
            raise InvalidInputError(f"start pose must be finite [x, y, yaw], got {start}")
        sigma = n.initial_radius_99 / math.sqrt(2 * math.log(100.0))
        self.true_start = start.copy()
        self.true_start[:2] += self.rng.normal(0.0, sigma, 2)
        tilt = np.deg2rad(n.tilt_sigma_deg)
        self.roll, self.pitch = (float(x) for x in self.rng.normal(0.0, tilt, 2))
        self._scale = 1.0 + self.rng.normal(0.0, n.speed_scale_sigma)
        self._bias = self.rng.normal(0.0, np.deg2rad(n.heading_bias_sigma_deg))
        self._max_distance = float(max_distance)
        self._t = 0.0
        self._q = np.asarray(world.nominal.arm.home if q_arm is None else q_arm, float).copy()
        self._knots_t = np.array([0.0])
        self._knots = self.true_start[None].copy()
        self._v = 0.0
        self._set(0.0)

    # --- truth ----------------------------------------------------------------------------
    def _build(self, v: float, heading: float) -> None:
        n = self.noise
        pose = self.true_start.copy()
        pose[2] = heading + self._bias
        knots, times = [pose.copy()], [0.0]
        if v > 0:
            steps = math.ceil(self._max_distance / n.increment)
            dt = n.increment / v
            for k in range(steps):
                r1, tr, r2 = odometry_increment_noise(0.0, n.increment, 0.0, self.rng, n.motion)
                tr *= self._scale
                th = pose[2] + r1
                pose = np.array([pose[0] + tr * math.cos(th), pose[1] + tr * math.sin(th), th + r2])
                knots.append(pose.copy())
                times.append((k + 1) * dt)
        self._knots = np.array(knots)
        self._knots_t = np.array(times)

    def true_base_pose(self, t: float | None = None) -> Array:
        """TRUE ``[x, y, yaw]`` of base_link at time ``t`` (default now); evaluation only."""
        t = self._t if t is None else float(t)
        kt, K = self._knots_t, self._knots
        if t >= kt[-1]:
            if self._v > 0:
                raise InvalidInputError(
                    f"the pass ran past the {self._max_distance} m of simulated drive"
                )
            return K[-1].copy()
        j = int(np.searchsorted(kt, t, side="right")) - 1
        w = (t - kt[j]) / (kt[j + 1] - kt[j])
        out = K[j] + w * (K[j + 1] - K[j])
        return out

    def _set(self, t: float) -> None:
        self._t = t
        self.world.set_kinematic_state(
            self.true_base_pose(t), self._q, self.roll, self.pitch, time=t
        )
        if self.on_state is not None:
            self.on_state()

    # --- MovingRobot ----------------------------------------------------------------------
    def now(self) -> float:
        return self._t

    def start_base(self, v: float, heading: float) -> None:
        if not (np.isfinite(v) and v >= 0 and np.isfinite(heading)):
            raise InvalidInputError(f"need a finite speed >= 0 and heading, got {v}, {heading}")
        self._v = float(v)
        self._build(self._v, float(heading))
        self._set(0.0)

    def stop_base(self) -> None:
        pose = self.true_base_pose()
        keep = self._knots_t < self._t
        self._knots = np.concatenate([self._knots[keep], pose[None]])
        self._knots_t = np.concatenate([self._knots_t[keep], [self._t]])
        self._v = 0.0

    def joint_positions(self) -> Array:
        return self._q.copy()

    def idle(self, duration: float) -> None:
        if not (np.isfinite(duration) and duration >= 0):
            raise InvalidInputError(f"idle duration must be finite and >= 0, got {duration}")
        self._set(self._t + duration)

    def execute(self, times: Array, q: Array) -> tuple[bool, float, Array]:
        times = np.asarray(times, float)
        q = np.asarray(q, float)
        lo, hi = self.world.arm.q_min, self.world.arm.q_max
        if np.any(q < lo - 1e-9) or np.any(q > hi + 1e-9):
            raise InvalidInputError("commanded joint path leaves the joint limits")
        ps = self.world.photosensor
        t0 = self._t
        was = ps.triggered()  # a real sensor input latches on the rising edge
        for t, qk in zip(times, q, strict=True):
            self._q = qk
            self._set(t0 + float(t))
            now = ps.triggered()
            if now and not was:
                return True, self._t, self._q.copy()
            was = now
        return False, self._t, self._q.copy()

    def true_beam_hit(self) -> str | None:
        """Name of the geom the beam hits now (evaluation)."""
        return self.world.photosensor.hit()[0]
