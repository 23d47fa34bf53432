"""Base velocity compensation, paper 002 eq. 7: ``s_hat_k = s_k + v_b delta_k``.

With the base moving, a search point planned at time 0 must be shifted by how far the base
(and so every point expressed relative to it) has moved when the tool gets there. ``delta``
are the per-segment durations of Algorithm 2 (segment k: from point k-1 to point k, segment 1
from the start configuration); the shift uses the arrival time ``T_k = t0 + sum_{j<=k}
delta_j``, i.e. the "time elapsed" of eq. 7 counted from the start of the planned motion (a
per-segment shift alone would forget the motion of the earlier segments).

Samples and ``velocity`` must be in the same frame: base-position hypotheses in the map with
the base velocity (the paper's form), or tool targets in the arm-base frame with the velocity
of the world seen from the base (``-R^T v_b``).
"""

from __future__ import annotations

import numpy as np

from mmpa.core.errors import InvalidInputError
from mmpa.core.geometry import Array

__all__ = ["arrival_times", "compensate"]


def arrival_times(delta: Array, t0: float = 0.0) -> Array:
    """``T_k = t0 + cumsum(delta)_k`` (s), shape (n,)."""
    delta = np.asarray(delta, dtype=float).reshape(-1)
    if not np.all(np.isfinite(delta)) or np.any(delta < 0):
        raise InvalidInputError("segment durations delta must be finite and >= 0")
    return float(t0) + np.cumsum(delta)


def compensate(samples: Array, velocity: Array, delta: Array, t0: float = 0.0) -> Array:
    """Eq. 7: ``s_hat_k = s_k + v T_k`` for samples (n, d), velocity (d,), delta (n,) s."""
    s = np.asarray(samples, dtype=float)
    v = np.asarray(velocity, dtype=float).reshape(-1)
    if s.ndim != 2 or v.shape != (s.shape[1],):
        raise InvalidInputError(
            f"need samples (n, d) and velocity (d,), got {s.shape} and {v.shape}"
        )
    if not (np.all(np.isfinite(s)) and np.all(np.isfinite(v))):
        raise InvalidInputError("samples and velocity must be finite")
    T = arrival_times(delta, t0)
    if T.shape != (s.shape[0],):
        raise InvalidInputError(f"need one delta per sample: {T.shape[0]} vs {s.shape[0]}")
    return s + T[:, None] * v[None, :]
