"""Stochastic search points, paper 002 §2.1.2-2.1.3: a constant-velocity Kalman filter of the
base (eq. 2-5), samples from its position distribution (eq. 6), discretized on a grid of
resolution gamma and ordered by probability.

State ``x = [x_b, xdot_b, y_b, ydot_b]`` (m, m/s), eq. 2; observations ``z = [x_b, y_b]``
(m): the base position implied by intercepting the previous fiducial.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, field_validator

from mmpa.core.errors import InvalidInputError
from mmpa.core.geometry import Array

__all__ = [
    "C_MATRIX",
    "ConstantVelocityKF",
    "GridSamples",
    "StochasticConfig",
    "grid_samples",
    "transition",
]

#: Observation matrix C of eq. 2: only positions are observed.
C_MATRIX = np.array([[1.0, 0.0, 0.0, 0.0], [0.0, 0.0, 1.0, 0.0]])


class StochasticConfig(BaseModel):
    """Paper 002 §3: gamma = 14 mm, Sigma_ww = 1e-4 diag(3, 2, 3, 2), Sigma_vv = 1e-4 (1.8, 1.8)."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    gamma: float = Field(0.014, gt=0)  # m, grid resolution
    sigma_ww: tuple[float, float, float, float] = (3e-4, 2e-4, 3e-4, 2e-4)  # diag, see below
    # "per_step": Sigma_ww added once per prediction (eq. 3 as printed); "per_metre": Sigma_ww
    # per metre the base travels (odometry error grows with distance, not with observations)
    process_noise: Literal["per_step", "per_metre"] = "per_step"
    sigma_vv: tuple[float, float] = (1.8e-4, 1.8e-4)  # m^2, observation noise (diag)
    initial_position_sigma: float = Field(0.0033, ge=0)  # m: within 1 cm 99 % of the time
    initial_velocity_sigma: float = Field(0.002, ge=0)  # m/s
    initial_velocity_rel: float = Field(0.0, ge=0)  # plus this fraction of the speed
    n_draws: int = Field(4000, ge=1)  # samples of eq. 6 before discretization
    mass: float = Field(0.999, gt=0, le=1)  # keep the most probable cells up to this mass
    points_per_round: int = Field(20, ge=1)  # n_s planned at once (Algorithm 2 batch)

    @field_validator("sigma_ww")
    @classmethod
    def _ww(cls, v: tuple[float, ...]) -> tuple[float, ...]:
        if not all(np.isfinite(x) and x >= 0 for x in v):
            raise ValueError(f"Sigma_ww diagonal must be finite and >= 0, got {v}")
        return v

    @field_validator("sigma_vv")
    @classmethod
    def _vv(cls, v: tuple[float, ...]) -> tuple[float, ...]:
        if not all(np.isfinite(x) and x > 0 for x in v):
            raise ValueError(
                f"Sigma_vv diagonal must be positive (a singular observation noise makes the "
                f"innovation covariance singular), got {v}"
            )
        return v


def transition(dt: float) -> Array:
    """State transition ``A(dt)`` of eq. 2, shape (4, 4)."""
    if not np.isfinite(dt):
        raise InvalidInputError(f"Kalman time step must be finite, got {dt}")
    A = np.eye(4)
    A[0, 1] = A[2, 3] = dt
    return A


def _check_cov(S: Array, name: str, n: int) -> Array:
    S = np.asarray(S, dtype=float)
    if S.ndim == 1:
        S = np.diag(S)
    if S.shape != (n, n) or not np.all(np.isfinite(S)):
        raise InvalidInputError(f"{name} must be a finite {n}x{n} covariance, got shape {S.shape}")
    if not np.allclose(S, S.T, atol=1e-12):
        raise InvalidInputError(f"{name} must be symmetric")
    if np.linalg.eigvalsh(S).min() < -1e-12:
        raise InvalidInputError(f"{name} must be positive semi-definite")
    return S


class ConstantVelocityKF:
    """Linear Kalman filter of eq. 2-5 for the planar base position and velocity."""

    def __init__(
        self,
        x0: Array,
        P0: Array,
        sigma_ww: Array,
        sigma_vv: Array,
        t0: float = 0.0,
        per_metre: bool = False,
    ) -> None:
        x0 = np.asarray(x0, dtype=float)
        self.per_metre = bool(per_metre)
        if x0.shape != (4,) or not np.all(np.isfinite(x0)):
            raise InvalidInputError(f"x0 must be 4 finite values [x, xdot, y, ydot], got {x0}")
        self.x = x0.copy()
        self.P = _check_cov(P0, "initial covariance P0", 4)
        self.Q = _check_cov(sigma_ww, "process noise Sigma_ww", 4)
        self.R = _check_cov(sigma_vv, "observation noise Sigma_vv", 2)
        self.t = float(t0)

    @classmethod
    def from_config(
        cls, position: Array, velocity: Array, cfg: StochasticConfig, t0: float = 0.0
    ) -> ConstantVelocityKF:
        p, v = np.asarray(position, float), np.asarray(velocity, float)
        sp = cfg.initial_position_sigma**2
        sv = (cfg.initial_velocity_sigma + cfg.initial_velocity_rel * float(np.hypot(*v))) ** 2
        return cls(
            np.array([p[0], v[0], p[1], v[1]]),
            np.diag([sp, sv, sp, sv]),
            np.array(cfg.sigma_ww),
            np.array(cfg.sigma_vv),
            t0,
            per_metre=cfg.process_noise == "per_metre",
        )

    def predicted(self, t: float) -> tuple[Array, Array]:
        """Eq. 3 to time ``t`` without changing the filter: ``(x(t|t-1), Sigma(t|t-1))``."""
        dt = float(t) - self.t
        A = transition(dt)
        Q = self.Q * (abs(dt) * float(np.hypot(self.x[1], self.x[3]))) if self.per_metre else self.Q
        return A @ self.x, A @ self.P @ A.T + Q

    def predict(self, t: float) -> None:
        """Eq. 3: propagate to time ``t`` (s); adds Sigma_ww once (one step per observation),
        or Sigma_ww times the distance travelled (``per_metre``)."""
        self.x, self.P = self.predicted(t)
        self.t = float(t)

    def update(self, z: Array) -> Array:
        """Eq. 4-5 with observation ``z = [x_b, y_b]``; returns the innovation e(t)."""
        z = np.asarray(z, dtype=float)
        if z.shape != (2,) or not np.all(np.isfinite(z)):
            raise InvalidInputError(f"observation must be 2 finite values, got {z}")
        C = C_MATRIX
        e = z - C @ self.x
        S = C @ self.P @ C.T + self.R
        try:
            K = np.linalg.solve(S.T, (self.P @ C.T).T).T  # P C^T S^-1
        except np.linalg.LinAlgError:
            raise InvalidInputError(
                "innovation covariance is singular (zero observation noise and a certain "
                "prediction); give Sigma_vv a positive diagonal"
            ) from None
        self.x = self.x + K @ e
        self.P = (np.eye(4) - K @ C) @ self.P
        self.P = 0.5 * (self.P + self.P.T)
        return e

    def position(self, t: float | None = None) -> tuple[Array, Array]:
        """Position mean (2,) and covariance (2, 2) at ``t`` (default: filter time)."""
        if t is None:
            x, P = self.x, self.P
        else:
            A = transition(float(t) - self.t)
            x, P = A @ self.x, A @ self.P @ A.T
        return C_MATRIX @ x, C_MATRIX @ P @ C_MATRIX.T

    def velocity(self) -> Array:
        return self.x[[1, 3]].copy()


@dataclass(frozen=True)
class GridSamples:
    """Grid cells of eq. 6 samples, most probable first: ``points`` (m, 2) cell centres (m),
    ``probability`` (m,) fraction of the draws in each cell, ``counts`` (m,)."""

    points: Array
    probability: Array
    counts: Array


def grid_samples(
    mean: Array,
    cov: Array,
    rng: np.random.Generator,
    gamma: float = 0.014,
    n_draws: int = 4000,
    mass: float = 0.999,
    anchor: Array | None = None,
) -> GridSamples:
    """Eq. 6 then §2.1.3: draw ``n_draws`` samples ``s ~ N(mean, cov)``, snap them to a grid
    of spacing ``gamma`` (m) anchored at ``anchor`` (default: the mean, so the most likely
    cell is centred on it), and return the occupied cells ordered by their count (ties: nearer
    the mean first), keeping the most probable cells up to ``mass``.

    A singular (PSD) covariance is fine: draws are made through its eigen-decomposition, so a
    zero covariance gives the single cell at the mean. A non-PSD or non-finite one raises.
    """
    mean = np.asarray(mean, dtype=float).reshape(-1)
    d = mean.size
    if not np.all(np.isfinite(mean)):
        raise InvalidInputError(f"sample mean must be finite, got {mean}")
    cov = _check_cov(cov, "sample covariance", d)
    if not (np.isfinite(gamma) and gamma > 0):
        raise InvalidInputError(f"grid resolution gamma must be positive, got {gamma}")
    if n_draws < 1:
        raise InvalidInputError(f"n_draws must be >= 1, got {n_draws}")
    w, V = np.linalg.eigh(cov)
    L = V * np.sqrt(np.clip(w, 0.0, None))
    s = mean + rng.standard_normal((n_draws, d)) @ L.T
    a = mean if anchor is None else np.asarray(anchor, dtype=float).reshape(d)
    cells = np.round((s - a) / gamma).astype(np.int64)
    uniq, counts = np.unique(cells, axis=0, return_counts=True)
    centres = a + uniq * gamma
    dist = np.linalg.norm(centres - mean, axis=1)
    order = np.lexsort((dist, -counts))
    counts = counts[order]
    centres = centres[order]
    cum = np.cumsum(counts) / n_draws
    keep = int(np.searchsorted(cum, mass - 1e-12) + 1)
    keep = min(keep, len(counts))
    return GridSamples(centres[:keep], counts[:keep] / n_draws, counts[:keep])
