"""Constant-velocity Kalman filter on an object's 3D position (improvement over paper 001,
which loses objects faster than 0.1 m/s).

State ``[p (3), v (3)]`` (m, m/s); motion ``p += v dt`` with white acceleration noise of
spectral density ``accel_sigma^2`` (the discrete Wiener-process model: ``Q = q [[dt^3/3,
dt^2/2], [dt^2/2, dt]]`` per axis); measurement ``z = p + N(0, meas_sigma^2 I)``.

:func:`fit_line` is the least-squares constant-velocity line through a window of measurements:
on a static object whose located point jitters (a lying stick's box moves along it from frame
to frame) its velocity stays near zero where the filter's, tuned to follow turns, does not.
"""

from __future__ import annotations

import numpy as np
from pydantic import BaseModel, ConfigDict, Field

from mmpa.core.errors import InvalidInputError
from mmpa.core.geometry import Array

__all__ = ["ConstantVelocityKF", "PredictorConfig", "fit_line"]


class PredictorConfig(BaseModel):
    model_config = ConfigDict(extra="forbid")
    accel_sigma: float = Field(1.0, gt=0)  # m/s^2 / sqrt(Hz)
    meas_sigma: float = Field(0.005, gt=0)  # m
    init_speed_sigma: float = Field(0.3, gt=0)  # m/s
    gate: float = Field(0.15, gt=0)  # m: a measurement this far from the prediction resets


class ConstantVelocityKF:
    def __init__(self, cfg: PredictorConfig | None = None) -> None:
        self.cfg = cfg or PredictorConfig()
        self.x: Array | None = None
        self.P = np.eye(6)
        #: ``|z - p_predicted|`` (m) of the last update; ``inf`` after a (re)initialization
        self.innovation = float("inf")

    @property
    def initialized(self) -> bool:
        return self.x is not None

    def reset(self) -> None:
        self.x = None
        self.innovation = float("inf")

    def predict(self, dt: float) -> None:
        if dt < 0 or not np.isfinite(dt):
            raise InvalidInputError(f"dt must be >= 0, got {dt}")
        if self.x is None:
            return
        F = np.eye(6)
        F[:3, 3:] = dt * np.eye(3)
        q = self.cfg.accel_sigma**2
        Q = np.zeros((6, 6))
        Q[:3, :3] = q * dt**3 / 3 * np.eye(3)
        Q[:3, 3:] = Q[3:, :3] = q * dt**2 / 2 * np.eye(3)
        Q[3:, 3:] = q * dt * np.eye(3)
        self.x = F @ self.x
        self.P = F @ self.P @ F.T + Q

    def update(self, z: Array) -> None:
        z = np.asarray(z, float)
        if z.shape != (3,) or not np.all(np.isfinite(z)):
            raise InvalidInputError(f"measurement must be finite (3,), got {z}")
        r2 = self.cfg.meas_sigma**2
        if self.x is None or np.linalg.norm(z - self.x[:3]) > self.cfg.gate:
            self.x = np.concatenate([z, np.zeros(3)])
            self.P = np.diag([r2] * 3 + [self.cfg.init_speed_sigma**2] * 3)
            self.innovation = float("inf")
            return
        self.innovation = float(np.linalg.norm(z - self.x[:3]))
        H = np.hstack([np.eye(3), np.zeros((3, 3))])
        S = H @ self.P @ H.T + r2 * np.eye(3)
        K = self.P @ H.T @ np.linalg.inv(S)
        self.x = self.x + K @ (z - H @ self.x)
        self.P = (np.eye(6) - K @ H) @ self.P

    def position(self, ahead: float = 0.0) -> Array:
        if self.x is None:
            raise InvalidInputError("the predictor has no measurement yet")
        return self.x[:3] + ahead * self.x[3:]

    def velocity(self) -> Array:
        if self.x is None:
            raise InvalidInputError("the predictor has no measurement yet")
        return self.x[3:].copy()


def fit_line(t: Array, P: Array, t_ref: float | None = None) -> tuple[Array, Array]:
    """Least-squares line ``p(t) = p_ref + v (t - t_ref)`` through the points ``P`` (N, 3) m
    measured at the times ``t`` (N,) s (``t_ref``: default the last time). Returns ``(p_ref
    (3,), v (3,) m/s)``; N >= 2 and the times must not all be equal."""
    t = np.asarray(t, float)
    P = np.asarray(P, float)
    if t.ndim != 1 or P.shape != (len(t), 3) or len(t) < 2:
        raise InvalidInputError(f"need times (N,) and points (N, 3), N >= 2: {t.shape}, {P.shape}")
    if not (np.all(np.isfinite(t)) and np.all(np.isfinite(P))):
        raise InvalidInputError("times and points must be finite")
    tr = float(t[-1]) if t_ref is None else float(t_ref)
    dt = t - t.mean()
    s = float(dt @ dt)
    if s <= 0:
        raise InvalidInputError("the times must not all be equal")
    v = dt @ (P - P.mean(axis=0)) / s
    return P.mean(axis=0) + v * (tr - t.mean()), v
