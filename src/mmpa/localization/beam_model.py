"""The beam model of AMCL (Thrun et al. ch. 6.3, as Nav2's ``BeamModel``) and its ray casting.

:func:`raycast` finds the expected range of every (particle, beam) by sphere tracing in the
occupancy grid (:func:`skip_table`); :func:`beam_weights` turns expected and measured ranges
into Nav2's ``p = 1 + sum_b pz_b^3`` (:func:`beam_pz`: each beam's ``pz``, whose logs sum to
the textbook product's ``log p``), with the mixture ``pz = z_hit exp(-z^2 / (2 sigma_hit^2)) +
[z < 0] z_short lambda_short exp(-lambda_short r) + z_rand / z_max``, ``z = r - r_expected``.

Units: m, rad. Particles ``[x, y, theta]`` in ``map``, the lidar mount ``[x, y, yaw]`` in
``base_link``, beam angles in the lidar frame. Grid tables are flattened (H+2)(W+2) arrays with
a one-cell border (off the map).
"""

from __future__ import annotations

import numpy as np
from scipy import ndimage

from mmpa.core.geometry import Array
from mmpa.localization.likelihood_field import laser_origin
from mmpa.maps.occupancy import OccupancyGrid

RAY_BLOCK = 32768  # rays marched together by raycast (their arrays fit the L2 cache)

__all__ = [
    "RAY_BLOCK",
    "beam_pz",
    "beam_weights",
    "march",
    "raycast",
    "skip_table",
]


def skip_table(grid: OccupancyGrid) -> Array:
    """Flattened (H+2)(W+2) float table for :func:`raycast`: 0 in occupied cells and the
    one-cell border (off the map: the march stops), else the half-cell steps ``h`` a ray may
    jump from any point of the cell, ``n = max(ceil(D / h), 1)`` (the ``n - 1`` points passed
    over lie nearer than ``(n - 1) h < D``). ``D`` is the cell's clearance: the least distance
    between its square and the square of an occupied or border cell, ``res sqrt(max(|di| - 1,
    0)^2 + max(|dj| - 1, 0)^2)`` for cell offsets ``(di, dj)``, i.e. the distance transform to
    the occupied cells dilated by one cell (3 x 3), unclipped."""
    occ = np.pad(grid.occupied, 1, constant_values=True)
    near = ndimage.binary_dilation(occ, np.ones((3, 3), dtype=bool))
    clear = ndimage.distance_transform_edt(~near) * 2.0  # in half-cell steps h
    n = np.maximum(np.ceil(clear), 1.0)
    n[occ] = 0.0
    return n.ravel()


def raycast(
    grid: OccupancyGrid,
    table: Array,
    particles: Array,
    laser_pose: Array,
    angles: Array,
    max_range: float,
) -> Array:
    """Expected ranges (N, B): the first of the points ``k h`` (``h`` half a cell,
    ``k = 1 .. floor(max_range / h)``) along each beam that lies in an occupied cell or
    off the map; ``max_range`` if none.

    Sphere tracing: from a point in a cell, no point nearer than the cell's clearance ``D``
    (``table``, :func:`skip_table`) lies in an occupied cell or off the map, so the march
    jumps ``max(ceil(D / h), 1)`` half-cell steps at once (the points it passes over lie
    nearer than ``D``; the one it lands on is checked): same result as visiting every point
    (but for a point within float rounding, ~1e-13 cells, of a cell edge), far fewer visits.
    Rays are marched in blocks of :data:`RAY_BLOCK` (their arrays stay in the cache)."""
    n, nb = particles.shape[0], angles.shape[0]
    out = np.empty((n, nb))
    step = max(1, RAY_BLOCK // max(nb, 1))
    for i in range(0, n, step):
        out[i : i + step] = march(
            grid, table, particles[i : i + step], laser_pose, angles, max_range
        )
    return out


def march(
    grid: OccupancyGrid,
    table: Array,
    particles: Array,
    laser_pose: Array,
    angles: Array,
    max_range: float,
) -> Array:
    """:func:`raycast` on one block of particles. The march runs in padded cell units
    (``x = (ox - x0) / res + 1 + k cos(a) / 2`` for step ``k``; every point after the
    first lies in the map or its one-cell border, where the table stops it, so float ->
    int truncation is the floor) and keeps only the step ``k`` per ray: the table gives
    0 where a point hits, so ``k`` stops there; ``k`` is capped at ``k_max + 1`` (no hit
    within range). Finished rays are dropped once they are half of those marching."""
    g = grid
    nb = angles.shape[0]
    ox, oy, oth = laser_origin(particles, laser_pose)
    inv = 1.0 / g.resolution
    # padded cell coordinates of the origins and the half-cell step per beam (the
    # direction by the angle sum: N + B sines and cosines instead of N B)
    x = np.repeat((ox - g.origin[0]) * inv + 1.0, nb)
    y = np.repeat((oy - g.origin[1]) * inv + 1.0, nb)
    c, s = 0.5 * np.cos(oth)[:, None], 0.5 * np.sin(oth)[:, None]
    ca, sa = np.cos(angles)[None, :], np.sin(angles)[None, :]
    dx = (c * ca - s * sa).ravel()
    dy = (s * ca + c * sa).ravel()
    k_cap = float(int(max_range / (g.resolution / 2)) + 1)
    w2 = g.width + 2
    # first point: the origin may be off the map, so clip it into the border ring
    col = np.clip(x + dx, 0.0, w2 - 0.5).astype(np.int32)
    row = np.clip(y + dy, 0.0, g.height + 1.5).astype(np.int32)
    k_all = np.minimum(1.0 + table.take(row * w2 + col), k_cap)
    ray = np.flatnonzero(k_all > 1.0)  # still marching
    x, y, dx, dy, k = x[ray], y[ray], dx[ray], dy[ray], k_all[ray]
    fx, fy = np.empty_like(x), np.empty_like(y)
    while ray.size:
        np.multiply(k, dx, out=fx)
        fx += x
        np.multiply(k, dy, out=fy)
        fy += y
        idx = fy.astype(np.int32)
        idx *= w2
        idx += fx.astype(np.int32)
        k_new = table.take(idx)
        k_new += k
        np.minimum(k_new, k_cap, out=k_new)
        moving = k_new != k
        k = k_new
        m = np.count_nonzero(moving)
        if 2 * m < ray.size:
            k_all[ray] = k
            keep = np.flatnonzero(moving)
            ray, x, y, dx, dy, k = ray[keep], x[keep], y[keep], dx[keep], dy[keep], k[keep]
            fx, fy = fx[:m], fy[:m]
    out = np.where(k_all < k_cap, k_all * (g.resolution / 2), float(max_range))
    return out.reshape(particles.shape[0], nb)


def beam_weights(
    expected: Array,
    ranges: Array,
    z_hit: float,
    z_short: float,
    z_rand: float,
    lambda_short: float,
    sigma_hit: float,
    zmax: float,
) -> Array:
    """Nav2 ``BeamModel``'s ``p = 1 + sum pz^3`` (N,) from the ``expected`` ranges (N, B)
    (overwritten) and the measured ``ranges`` (B,). The ``z_max`` part never applies: beams at
    or past ``z_max`` are dropped before."""
    pz = beam_pz(expected, ranges, z_hit, z_short, z_rand, lambda_short, sigma_hit, zmax)
    return 1.0 + np.einsum("ij,ij,ij->i", pz, pz, pz)


def beam_pz(
    expected: Array,
    ranges: Array,
    z_hit: float,
    z_short: float,
    z_rand: float,
    lambda_short: float,
    sigma_hit: float,
    zmax: float,
) -> Array:
    """The mixture ``pz`` (N, B) of every beam (module docstring), in ``expected``'s array."""
    z = expected
    np.subtract(ranges[None, :], z, out=z)
    # the short and random parts per beam: [z < 0] picks the first row
    rest = z_rand / zmax + np.stack(
        [z_short * lambda_short * np.exp(-lambda_short * ranges), np.zeros_like(ranges)]
    )
    part = np.where(z < 0, rest[0], rest[1])
    np.multiply(z, z, out=z)
    z *= -1.0 / (2 * sigma_hit**2)
    pz = np.exp(z, out=z)
    pz *= z_hit
    pz += part
    return pz
