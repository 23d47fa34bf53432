"""Laser likelihood fields of AMCL (Thrun et al. ch. 6.4, as Nav2's ``LikelihoodFieldModel``)
and the beam subsampling every laser model shares.

- :func:`likelihood_field`: Nav2's ``p = 1 + sum_b pz_b^3``, ``pz = z_hit exp(-z^2 / (2
  sigma_hit^2)) + z_rand / range_max``, ``z`` the distance from the beam endpoint to the nearest
  obstacle in the endpoint's cell (a precomputed ``pz^3`` table, :func:`pz3_table`);
- :func:`log_likelihood_field`: the product form ``log p = sum_b log pz_b`` on the BILINEARLY
  interpolated (optionally signed) distance field: smooth in the pose.

Units: m, rad. Particles ``[x, y, theta]`` in ``map``; the lidar mount ``[x, y, yaw]`` in
``base_link``; beam angles in the lidar frame. Distance tables are flattened (H+2)(W+2) arrays
with a one-cell border holding ``max_dist`` (off the map).
"""

from __future__ import annotations

import numpy as np

from mmpa.core.geometry import Array
from mmpa.maps.occupancy import OccupancyGrid
from mmpa.robot.interfaces import LaserScan

__all__ = [
    "laser_origin",
    "likelihood_field",
    "log_likelihood_field",
    "padded",
    "pz3_table",
    "subsample_beams",
]


def subsample_beams(
    scan: LaserScan, max_beams: int, offset: int, max_range: float, min_range: float
) -> tuple[Array, Array, float]:
    """Valid subsampled beams (Nav2 ``max_beams`` stepping, every ``step``-th beam from beam
    ``offset mod step``): ranges, angles and the range limit used (``max_range`` / ``min_range``
    < 0: the scan's own)."""
    r = np.asarray(scan.ranges, float)
    mb = max_beams
    rmax = scan.range_max if max_range < 0 else min(max_range, scan.range_max)
    rmin = scan.range_min if min_range < 0 else max(min_range, scan.range_min)
    n = r.shape[0]
    step = max(1, (n - 1) // (mb - 1)) if mb > 1 else n
    idx = np.arange(offset % step, n, step)[:mb]
    rr, aa = r[idx], scan.angles[idx]
    ok = np.isfinite(rr) & (rr >= rmin) & (rr < rmax)
    return rr[ok], aa[ok], rmax


def laser_origin(particles: Array, laser_pose: Array) -> tuple[Array, Array, Array]:
    """The lidar's position ``(x, y)`` and heading in ``map`` for every particle (N,) each."""
    lx, ly, lth = laser_pose
    c, s = np.cos(particles[:, 2]), np.sin(particles[:, 2])
    ox = particles[:, 0] + c * lx - s * ly
    oy = particles[:, 1] + s * lx + c * ly
    return ox, oy, particles[:, 2] + lth


def padded(field: Array, border: float) -> Array:
    """Flattened (H+2)(W+2) copy of ``field`` (H, W) with a one-cell ``border``."""
    return np.pad(field, 1, constant_values=border).ravel()


def pz3_table(
    dist: Array, max_dist: float, z_hit: float, z_rand: float, sigma_hit: float, rmax: float
) -> Array:
    """Flattened (H+2)(W+2) float32 table of ``pz^3`` per cell of the distance field ``dist``
    (border: off the map, ``max_dist``)."""
    d = np.pad(dist, 1, constant_values=max_dist).astype(float)
    pz = z_hit * np.exp(-(d * d) / (2 * sigma_hit**2)) + z_rand / rmax
    return (pz**3).ravel().astype(np.float32)


def likelihood_field(
    grid: OccupancyGrid,
    table: Array,
    origin: tuple[Array, Array, Array],
    ranges: Array,
    angles: Array,
) -> Array:
    """Nav2 ``LikelihoodFieldModel``: ``p = 1 + sum_beams pz^3`` looked up in ``table``
    (:func:`pz3_table`) at the beam endpoints from the lidar poses ``origin``
    (:func:`laser_origin`). Returns (N,)."""
    g = grid
    ox, oy, oth = origin
    # endpoints without trig on the (N, B) grid: rotate the beam endpoints per particle
    bx, by = ranges * np.cos(angles), ranges * np.sin(angles)
    c, s = np.cos(oth)[:, None], np.sin(oth)[:, None]
    inv = 1.0 / g.resolution
    fx = (ox - g.origin[0])[:, None] * inv + (c * bx - s * by) * inv
    fy = (oy - g.origin[1])[:, None] * inv + (s * bx + c * by) * inv
    # the table has a one-cell border holding max_dist's value: clip into it
    col = np.clip(np.floor(fx), -1, g.width).astype(np.int32) + 1
    row = np.clip(np.floor(fy), -1, g.height).astype(np.int32) + 1
    return 1.0 + table[row * (g.width + 2) + col].sum(axis=1)


def endpoint_cells(
    grid: OccupancyGrid, origin: tuple[Array, Array, Array], ranges: Array, angles: Array
) -> tuple[Array, Array, Array]:
    """Beam endpoints (N, B) in continuous padded cell coordinates (cell centers at integers,
    +1 for the border), clipped into the border: ``(fx, fy)`` and the lidar headings."""
    g = grid
    ox, oy, oth = origin
    bx, by = ranges * np.cos(angles), ranges * np.sin(angles)
    cs, sn = np.cos(oth)[:, None], np.sin(oth)[:, None]
    inv = 1.0 / g.resolution
    # (o - origin) / res + (R b) / res + 1/2, evaluated in place in that order
    tmp = sn * by
    fx = cs * bx
    fx -= tmp
    fx *= inv
    fx += (ox - g.origin[0])[:, None] * inv
    fx += 0.5
    np.multiply(cs, by, out=tmp)
    fy = sn * bx
    fy += tmp
    fy *= inv
    fy += (oy - g.origin[1])[:, None] * inv
    fy += 0.5
    np.clip(fx, 0.0, g.width + 0.999, out=fx)
    np.clip(fy, 0.0, g.height + 0.999, out=fy)
    return fx, fy, oth


def log_likelihood_field(
    grid: OccupancyGrid,
    field: Array,
    origin: tuple[Array, Array, Array],
    ranges: Array,
    angles: Array,
    sigma: float,
    offset: float,
    signed: bool,
    z_hit: float,
    z_rand: float,
    rmax: float,
) -> Array:
    """Product-form field ``log p = sum_b log(z_hit exp(-d_b^2 / (2 sigma^2)) + z_rand / rmax)``
    with ``d_b`` the padded distance ``field`` (unsigned, or ``signed`` to the surface
    ``offset`` m out) bilinearly interpolated at the endpoints; unsigned, less ``offset`` and
    floored at 0; signed, its absolute value. Returns (N,)."""
    g = grid
    fx, fy, _ = endpoint_cells(g, origin, ranges, angles)
    k = _cell_index(fx, g.width + 2, fy)  # fx, fy now the fractions tx, ty in the cell
    tx, ty = fx, fy
    d, w2 = field, g.width + 2
    # (d00 (1 - tx) + d10 tx) (1 - ty) + (d01 (1 - tx) + d11 tx) ty, in place in that order
    ux = 1 - tx
    f64 = np.float64  # the products in float64 whatever the field's dtype (float32 or 64)
    dist = d.take(k).astype(f64, copy=False)
    dist *= ux
    part = d[1:].take(k).astype(f64, copy=False)
    part *= tx
    dist += part
    dist *= 1 - ty
    low = d[w2:].take(k).astype(f64, copy=False)
    low *= ux
    part = d[w2 + 1 :].take(k).astype(f64, copy=False)
    part *= tx
    low += part
    low *= ty
    dist += low
    if signed:
        np.abs(dist, out=dist)
    elif offset > 0:
        dist -= offset
        np.maximum(dist, 0.0, out=dist)
    # z_hit exp(-(d^2) / (2 sigma^2)) + z_rand / rmax
    np.multiply(dist, dist, out=dist)
    np.negative(dist, out=dist)
    dist /= 2 * sigma * sigma
    np.exp(dist, out=dist)
    dist *= z_hit
    dist += z_rand / rmax
    np.log(dist, out=dist)
    return dist.sum(axis=1)


def _cell_index(fx: Array, w2: int, fy: Array) -> Array:
    """Flat index ``j0 w2 + i0`` of the cells holding ``(fx, fy)`` (``i0 = floor fx``,
    ``j0 = floor fy``), ``fx`` and ``fy`` replaced by their fractions ``fx - i0``, ``fy - j0``."""
    f = np.floor(fx)
    i0 = f.astype(np.int32)
    fx -= f
    np.floor(fy, out=f)
    k = f.astype(np.int32)
    fy -= f
    k *= w2
    k += i0
    return k
