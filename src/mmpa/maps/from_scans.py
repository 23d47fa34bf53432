"""An occupancy grid from scans taken at known poses (mapping with known poses, Thrun et al.
*Probabilistic Robotics* ch. 9, with counts instead of log odds).

Every valid beam marks the cell of its endpoint as hit and the cells its ray crosses before
it as passed (samples every ``resolution / 2`` along the ray; beams with no return mark
``free_range`` m as passed). A cell is occupied (100) if it was hit at least ``min_hits``
times and hit in at least ``occupied_ratio`` of the beams that reached it (``hits / (hits +
passes)``: a person walking by is passed far more often than hit), free (0) if passed and
not occupied, unknown (-1) otherwise. Pure: arrays in, an
:class:`~mmpa.maps.occupancy.OccupancyGrid` out.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from mmpa.core.errors import InvalidInputError
from mmpa.core.geometry import Array, se2_compose
from mmpa.maps.occupancy import OccupancyGrid
from mmpa.robot.interfaces import LaserScan

__all__ = ["occupancy_from_scans", "scan_endpoints"]


def scan_endpoints(pose: Array, scan: LaserScan, laser_pose: Array | None = None) -> Array:
    """Map-frame endpoints (M, 2) of the valid beams of ``scan`` taken at base pose ``pose``
    ``[x, y, theta]`` with the lidar mounted at ``laser_pose`` (base frame, default 0):
    ``p = o + r [cos(theta_l + a), sin(theta_l + a)]``."""
    ox, oy, th = se2_compose(pose, np.zeros(3) if laser_pose is None else laser_pose)
    m = scan.valid()
    a = scan.angles[m] + th
    r = scan.ranges[m]
    return np.column_stack([ox + r * np.cos(a), oy + r * np.sin(a)])


def occupancy_from_scans(
    poses: Array,
    scans: Sequence[LaserScan],
    resolution: float = 0.05,
    laser_pose: Array | None = None,
    max_range: float = 30.0,
    free_range: float = 0.0,
    min_hits: int = 1,
    occupied_ratio: float = 0.25,
    margin: float = 1.0,
) -> OccupancyGrid:
    """Occupancy grid (``resolution`` m cells, ``margin`` m around everything seen) from the
    ``scans`` taken at base poses ``poses`` (N, 3); beams past ``max_range`` m are ignored
    (and beams with no return mark ``free_range`` m as free). See the module docstring."""
    P = np.asarray(poses, float).reshape(-1, 3)
    if len(P) != len(scans) or len(P) == 0:
        raise InvalidInputError(f"{len(P)} poses for {len(scans)} scans")
    if not np.all(np.isfinite(P)):
        raise InvalidInputError("poses must be finite")
    if not (resolution > 0 and max_range > 0):
        raise InvalidInputError("resolution and max_range must be positive")
    lp = np.zeros(3) if laser_pose is None else np.asarray(laser_pose, float).reshape(3)
    rays = [_rays(P[k], scans[k], lp, max_range, free_range) for k in range(len(P))]
    o = np.concatenate([r[0] for r in rays])
    e = np.concatenate([r[1] for r in rays])
    hit = np.concatenate([r[2] for r in rays])
    lo = np.minimum(o.min(axis=0), e.min(axis=0)) - margin
    hi = np.maximum(o.max(axis=0), e.max(axis=0)) + margin
    w, h = (np.ceil((hi - lo) / resolution).astype(int) + 1).tolist()
    hits = np.zeros(h * w)
    passes = np.zeros(h * w)
    he = e[hit]
    col = ((he[:, 0] - lo[0]) / resolution).astype(np.int64)
    row = ((he[:, 1] - lo[1]) / resolution).astype(np.int64)
    np.add.at(hits, row * w + col, 1.0)
    # passes: samples every resolution / 2 up to one resolution short of the endpoint
    step = resolution / 2
    for i in range(0, len(o), 20000):
        oo, ee = o[i : i + 20000], e[i : i + 20000]
        d = ee - oo
        length = np.hypot(d[:, 0], d[:, 1])
        ns = np.maximum(((length - resolution) / step).astype(np.int64), 0)
        ray = np.repeat(np.arange(len(oo)), ns)
        k = np.arange(ns.sum()) - np.repeat(np.cumsum(ns) - ns, ns)
        t = (k * step / np.maximum(length, 1e-12)[ray])[:, None]
        pts = oo[ray] + t * d[ray]
        c = ((pts[:, 0] - lo[0]) / resolution).astype(np.int64)
        r = ((pts[:, 1] - lo[1]) / resolution).astype(np.int64)
        passes += np.bincount(r * w + c, minlength=h * w) * 0.5  # ~2 samples per cell
    occ = (hits >= min_hits) & (hits >= occupied_ratio * (hits + passes))
    data = np.full(h * w, -1, dtype=np.int8)
    data[passes > 0] = 0
    data[occ] = 100
    return OccupancyGrid(data.reshape(h, w), resolution, (float(lo[0]), float(lo[1]), 0.0))


def _rays(
    pose: Array, scan: LaserScan, lp: Array, max_range: float, free_range: float
) -> tuple[Array, Array, Array]:
    """Origins (B, 2), endpoints (B, 2) and hit flags (B,) of one scan's usable beams."""
    L = se2_compose(pose, lp)  # the lidar in the map
    o = L[:2]
    r = np.asarray(scan.ranges, float)
    hit = np.isfinite(r) & (r >= scan.range_min) & (r <= min(scan.range_max, max_range))
    miss = ~hit & ~np.isnan(r) & (r > max_range) & (free_range > 0)
    use = hit | miss
    rr = np.where(hit, r, free_range)[use]
    a = scan.angles[use] + L[2]
    e = o + rr[:, None] * np.column_stack([np.cos(a), np.sin(a)])
    return np.repeat(o[None, :], len(rr), axis=0), e, hit[use]
