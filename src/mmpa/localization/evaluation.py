"""A localizer's estimates against a reference trajectory: the figures of ``mmpa benchmark
localization`` (pure numpy: arrays in, a dict out).

Per scan ``k``: the position error ``e_k = |p_k - q_k|`` (m; ``p`` the estimate, ``q`` the
reference, both ``[x, y]`` in ``map``) and the heading error ``h_k = |wrap(theta_k -
phi_k)|`` (rad, in [0, pi]). Over the run:

- mean, median, p95 (numpy's linear interpolation between order statistics), max of ``e``
  (mm) and of ``h`` (deg);
- the share of scans with ``e <= 0.05`` m and ``e <= 0.10`` m;
- divergence: the first scan ``k >= after`` (default 30: the first scans may still converge)
  with ``e_k > divergence`` (default 0.5 m); ``diverged_at_scan`` is that index (counted from
  the first scan evaluated) or None, ``diverged_at_s`` the time since the first scan;
- time per update (ms): mean, median, p95, max of the wall time each ``update`` took.
"""

from __future__ import annotations

import numpy as np

from mmpa.core.errors import InvalidInputError
from mmpa.core.geometry import Array, wrap_angle

__all__ = ["error_statistics", "trajectory_errors"]


def trajectory_errors(estimate: Array, truth: Array) -> tuple[Array, Array]:
    """Position errors (N,) m and heading errors (N,) rad of ``estimate`` against ``truth``
    (both (N, 3) ``[x, y, theta]``)."""
    est = np.asarray(estimate, float).reshape(-1, 3)
    ref = np.asarray(truth, float).reshape(-1, 3)
    if est.shape != ref.shape:
        raise InvalidInputError(f"{len(est)} estimates for {len(ref)} reference poses")
    pos = np.hypot(est[:, 0] - ref[:, 0], est[:, 1] - ref[:, 1])
    yaw = np.abs(np.asarray(wrap_angle(est[:, 2] - ref[:, 2]), float))
    return pos, yaw


def _stats(v: Array, scale: float, unit: str, prefix: str) -> dict[str, float]:
    s = np.asarray(v, float) * scale
    return {
        f"{prefix}_mean_{unit}": round(float(np.mean(s)), 3),
        f"{prefix}_median_{unit}": round(float(np.median(s)), 3),
        f"{prefix}_p95_{unit}": round(float(np.percentile(s, 95)), 3),
        f"{prefix}_max_{unit}": round(float(np.max(s)), 3),
    }


def error_statistics(
    estimate: Array,
    truth: Array,
    t: Array | None = None,
    update_s: Array | None = None,
    divergence: float = 0.5,
    after: int = 30,
) -> dict:
    """The figures of the module docstring for ``estimate`` against ``truth`` ((N, 3)
    each), stamps ``t`` (N,) s and per-update wall times ``update_s`` (N,) s."""
    pos, yaw = trajectory_errors(estimate, truth)
    if len(pos) == 0:
        raise InvalidInputError("no estimates to evaluate")
    out: dict = {"scans": len(pos)}
    out |= _stats(pos, 1e3, "mm", "error")
    out |= _stats(yaw, 180.0 / np.pi, "deg", "heading_error")
    out["within_5cm"] = round(float(np.mean(pos <= 0.05)), 4)
    out["within_10cm"] = round(float(np.mean(pos <= 0.10)), 4)
    late = np.flatnonzero(pos[after:] > divergence)
    k = int(late[0]) + after if late.size else None
    out["divergence_m"] = divergence
    out["divergence_after_scans"] = after
    out["diverged"] = k is not None
    out["diverged_at_scan"] = k
    out["diverged_at_s"] = None if k is None or t is None else round(float(t[k] - t[0]), 3)
    if update_s is not None and len(update_s):
        out |= _stats(update_s, 1e3, "ms", "update")
    return out
