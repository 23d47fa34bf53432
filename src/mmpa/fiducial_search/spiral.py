"""Deterministic spiral search points, paper 002 eq. 1.

``x_k = R' phi_k cos(phi_k)``, ``y_k = R' phi_k sin(phi_k)`` with ``phi_k = k phi``
(``k = 1 .. n_s``): an Archimedean spiral sampled at a constant angular interval ``phi``.

The paper gives ``R = 4 cm`` and ``phi = pi/5`` "which translates to a constant interpoint
spacing of approximately 12 mm". Read literally (``R'`` = 4 cm per radian) the second point
would already lie 5 cm out and consecutive points 2.5 cm+ apart, which contradicts that
sentence. With ``R`` as the radial growth per full turn (``R' = R / 2 pi``) the first turn
reaches ``R`` = 4 cm and its consecutive points are 4 to 24 mm apart, ~13 mm on average: this
is the reading we use by default (``radius_per="turn"``); ``radius_per="radian"`` gives the
literal one. Offsets are relative to the expected fiducial position, metres, shape (n, 2).
"""

from __future__ import annotations

from typing import Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field

from mmpa.core.errors import InvalidInputError
from mmpa.core.geometry import Array

__all__ = ["SpiralConfig", "spiral_growth", "spiral_points"]


class SpiralConfig(BaseModel):
    """Spiral search parameters (paper 002 §3: R = 4 cm, phi = pi / 5)."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    R: float = Field(0.04, gt=0)  # m (per turn by default, see the module docstring)
    phi: float = Field(float(np.pi / 5), gt=0, lt=float(np.pi))  # rad between samples
    radius_per: Literal["turn", "radian"] = "turn"
    max_radius: float = Field(0.08, gt=0)  # m: the spiral restarts beyond this radius
    points_per_round: int = Field(20, ge=1)  # n_s planned at once (Algorithm 2 batch)


def spiral_growth(cfg: SpiralConfig) -> float:
    """``R'`` of eq. 1 in m/rad."""
    return cfg.R / (2 * np.pi) if cfg.radius_per == "turn" else cfg.R


def spiral_points(k: Array | int, cfg: SpiralConfig | None = None) -> Array:
    """Eq. 1 for sample indices ``k`` (int n -> ``k = 1..n``; or an array of indices >= 0).

    Returns ``(len(k), 2)`` offsets ``[R' phi_k cos phi_k, R' phi_k sin phi_k]`` (m).
    """
    cfg = cfg or SpiralConfig()
    if np.isscalar(k):
        n = int(k)  # type: ignore[arg-type]
        if n < 0:
            raise InvalidInputError(f"number of spiral samples must be >= 0, got {n}")
        idx = np.arange(1, n + 1, dtype=float)
    else:
        idx = np.asarray(k, dtype=float).reshape(-1)
        if np.any(idx < 0) or not np.all(np.isfinite(idx)):
            raise InvalidInputError("spiral sample indices must be finite and >= 0")
    phik = idx * cfg.phi
    r = spiral_growth(cfg) * phik
    return np.stack([r * np.cos(phik), r * np.sin(phik)], axis=1)
