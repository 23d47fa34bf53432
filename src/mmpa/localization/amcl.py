"""Adaptive Monte Carlo localization, vectorized numpy, with the Nav2 AMCL feature set.

Follows Nav2 ``nav2_amcl`` (itself Thrun, Burgard, Fox, *Probabilistic Robotics* ch. 4-6 and 8):

- differential-drive odometry motion model (``alpha1..alpha4``, Table 5.6, with Nav2's
  reverse-driving handling of the rotation terms);
- likelihood-field laser model (``z_hit``, ``z_rand``, ``sigma_hit``, ``max_beams``,
  ``laser_likelihood_max_dist``; a precomputed distance field; Nav2's ``p = 1 + sum pz^3``) and
  the beam model (``z_hit``, ``z_short``, ``z_max``, ``z_rand``, ``lambda_short``; ray casting
  in the grid);
- KLD-sampling (``min_particles``, ``max_particles``, ``pf_err``, ``pf_z``; Nav2's histogram bins
  0.5 m x 0.5 m x 10 deg and its use of ``pf_z`` as the quantile) with low-variance resampling;
- recovery by random particles with ``recovery_alpha_slow`` / ``recovery_alpha_fast``;
- global localization (uniform over free space), initial pose with covariance, and the update
  thresholds ``update_min_d`` / ``update_min_a``.

The estimate is the weighted mean of the heaviest cluster (particles grouped by their
histogram bins, as Nav2 does, on a circular heading axis: :func:`cluster_labels`), with its
covariance; every heading mean is circular.

Units: m, rad. Poses ``[x, y, theta]`` in ``map``; odometry poses in ``odom``. All random draws
come from the ``numpy.random.Generator`` given to the filter.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field
from scipy import ndimage, sparse
from scipy.sparse import csgraph

from mmpa.core.errors import InvalidInputError
from mmpa.core.geometry import Array
from mmpa.localization.health import Health
from mmpa.maps.occupancy import OccupancyGrid
from mmpa.robot.interfaces import LaserScan

_RAY_BLOCK = 32768  # rays marched together by AMCL.raycast (their arrays fit the L2 cache)

__all__ = [
    "AMCL",
    "AMCLConfig",
    "PoseEstimate",
    "check_scan",
    "cluster_labels",
    "compose_odom",
    "finite_cov",
    "finite_pose",
    "odometry_delta",
    "sample_motion",
]


class AMCLConfig(BaseModel):
    """Nav2 AMCL parameters with Nav2's defaults (names as in ``nav2_params.yaml``)."""

    model_config = ConfigDict(extra="forbid")

    alpha1: float = Field(0.2, ge=0)  # rot noise from rot
    alpha2: float = Field(0.2, ge=0)  # rot noise from trans
    alpha3: float = Field(0.2, ge=0)  # trans noise from trans
    alpha4: float = Field(0.2, ge=0)  # trans noise from rot
    laser_model_type: Literal["likelihood_field", "beam"] = "likelihood_field"
    laser_likelihood_max_dist: float = Field(2.0, gt=0)
    laser_max_range: float = 100.0  # -1: use the scan's range_max
    laser_min_range: float = -1.0  # -1: use the scan's range_min
    max_beams: int = Field(60, ge=2)
    max_particles: int = Field(2000, ge=1)
    min_particles: int = Field(500, ge=1)
    pf_err: float = Field(0.05, gt=0)
    pf_z: float = Field(0.99, gt=0)
    recovery_alpha_fast: float = Field(0.0, ge=0, le=1)
    recovery_alpha_slow: float = Field(0.0, ge=0, le=1)
    resample_interval: int = Field(1, ge=1)
    sigma_hit: float = Field(0.2, gt=0)
    update_min_a: float = Field(0.2, ge=0)
    update_min_d: float = Field(0.25, ge=0)
    z_hit: float = Field(0.5, ge=0)
    z_max: float = Field(0.05, ge=0)
    z_rand: float = Field(0.5, ge=0)
    z_short: float = Field(0.05, ge=0)
    lambda_short: float = Field(0.1, gt=0)
    initial_cov_xx: float = Field(0.5 * 0.5, gt=0)
    initial_cov_yy: float = Field(0.5 * 0.5, gt=0)
    initial_cov_aa: float = Field((np.pi / 12) ** 2, gt=0)
    kld_bin_xy: float = Field(0.5, gt=0)  # Nav2 pf histogram cell (m)
    kld_bin_theta: float = Field(np.deg2rad(10.0), gt=0)


@dataclass(frozen=True)
class PoseEstimate:
    """Filter output: ``pose`` ``[x, y, theta]`` (map), ``cov`` (3, 3), number of particles,
    and whether this call ran a filter update. ``ok`` False (with ``reason``) when the
    localizer knows this estimate failed (e.g. a scan match that fits nothing); ``health``
    the figures behind that judgement (:mod:`mmpa.localization.health`; default: not judged,
    as the bare filters return it)."""

    pose: Array
    cov: Array
    n_particles: int
    updated: bool
    source: str = "amcl"
    ok: bool = True
    reason: str = ""
    health: Health = field(default_factory=Health)


def finite_pose(pose: Array, what: str) -> Array:
    """``pose`` as a (3,) float array ``[x, y, theta]``; raises :class:`InvalidInputError`
    naming ``what`` (e.g. "odometry pose") if it has another size or holds NaN/inf."""
    try:
        p = np.asarray(pose, float).reshape(-1)
    except (TypeError, ValueError):
        raise InvalidInputError(f"{what} must be 3 numbers [x, y, theta], got {pose!r}") from None
    if p.shape != (3,):
        raise InvalidInputError(f"{what} must be [x, y, theta], got shape {np.shape(pose)}")
    if not np.all(np.isfinite(p)):
        raise InvalidInputError(f"{what} must be finite, got {p}")
    return p


def check_scan(scan: object) -> LaserScan:
    """``scan`` if it is a :class:`~mmpa.robot.interfaces.LaserScan`, else
    :class:`InvalidInputError` (None or an array would fail deep inside a localizer)."""
    if not isinstance(scan, LaserScan):
        raise InvalidInputError(f"scan must be a LaserScan, got {type(scan).__name__}")
    return scan


def finite_cov(cov: Array, what: str) -> Array:
    """``cov`` as a (3, 3) symmetric positive semi-definite float array of ``[x, y, theta]``;
    raises :class:`InvalidInputError` naming ``what`` otherwise (NaN, wrong shape, negative)."""
    try:
        c = np.asarray(cov, float)
    except (TypeError, ValueError):
        raise InvalidInputError(f"{what} must be a 3 x 3 matrix of numbers, got {cov!r}") from None
    if c.shape != (3, 3):
        raise InvalidInputError(f"{what} must be 3 x 3 (x, y, theta), got shape {c.shape}")
    if not np.all(np.isfinite(c)):
        raise InvalidInputError(f"{what} must be finite, got {c.tolist()}")
    if not np.allclose(c, c.T, rtol=1e-9, atol=1e-12):
        raise InvalidInputError(f"{what} must be symmetric, got {c.tolist()}")
    low = float(np.linalg.eigvalsh(c).min())
    if low < -1e-12 * max(1.0, float(np.abs(c).max())):
        raise InvalidInputError(
            f"{what} must be positive semi-definite, its smallest eigenvalue is {low:.3g}"
        )
    return c


def odometry_delta(prev: Array, cur: Array) -> tuple[float, float, float]:
    """Odometry increment ``(rot1, trans, rot2)`` between two odometry poses (Table 5.6)."""
    dx, dy = cur[0] - prev[0], cur[1] - prev[1]
    trans = float(np.hypot(dx, dy))
    rot1 = 0.0 if trans < 0.01 else float(_wrap(np.arctan2(dy, dx) - prev[2]))
    rot2 = float(_wrap(cur[2] - prev[2] - rot1))
    return rot1, trans, rot2


def compose_odom(pose: Array, odom_ref: Array, odom_now: Array) -> Array:
    """``pose`` moved by the odometry increment from ``odom_ref`` to ``odom_now`` (SE(2))."""
    c, s = np.cos(odom_ref[2]), np.sin(odom_ref[2])
    dx, dy = odom_now[0] - odom_ref[0], odom_now[1] - odom_ref[1]
    lx, ly = c * dx + s * dy, -s * dx + c * dy
    c2, s2 = np.cos(pose[2]), np.sin(pose[2])
    th = float(_wrap(pose[2] + odom_now[2] - odom_ref[2]))
    return np.array([pose[0] + c2 * lx - s2 * ly, pose[1] + s2 * lx + c2 * ly, th])


def _wrap(a: Array | float) -> Array | float:
    return (np.asarray(a) + np.pi) % (2 * np.pi) - np.pi


def sample_motion(
    particles: Array,
    delta: tuple[float, float, float],
    alphas: tuple[float, float, float, float],
    rng: np.random.Generator,
) -> Array:
    """Nav2 ``DifferentialMotionModel::odometryUpdate`` for all particles (N, 3) at once."""
    rot1, trans, rot2 = delta
    a1, a2, a3, a4 = alphas
    r1n = min(abs(float(_wrap(rot1))), abs(float(_wrap(rot1 - np.pi))))
    r2n = min(abs(float(_wrap(rot2))), abs(float(_wrap(rot2 - np.pi))))
    n = particles.shape[0]
    e = rng.standard_normal((3, n))
    r1 = rot1 - np.sqrt(a1 * r1n**2 + a2 * trans**2) * e[0]
    t = trans - np.sqrt(a3 * trans**2 + a4 * r1n**2 + a4 * r2n**2) * e[1]
    r2 = rot2 - np.sqrt(a1 * r2n**2 + a2 * trans**2) * e[2]
    out = particles.copy()
    out[:, 0] += t * np.cos(particles[:, 2] + r1)
    out[:, 1] += t * np.sin(particles[:, 2] + r1)
    out[:, 2] = _wrap(particles[:, 2] + r1 + r2)
    return out


class AMCL:
    """The particle filter. ``laser_pose`` is the lidar mount ``[x, y, yaw]`` in ``base_link``.

    Typical loop: ``set_initial_pose`` (or ``global_localization``), then per scan
    ``update(odom_pose, scan)``; ``estimate()`` any time.
    """

    name = "amcl"

    def __init__(
        self,
        grid: OccupancyGrid,
        laser_pose: Array,
        cfg: AMCLConfig | None = None,
        rng: np.random.Generator | None = None,
    ) -> None:
        self.cfg = cfg or AMCLConfig()
        if self.cfg.min_particles > self.cfg.max_particles:
            raise InvalidInputError("min_particles must not exceed max_particles")
        self.grid = grid
        self.laser_pose = np.asarray(laser_pose, float).reshape(3)
        self.rng = rng if rng is not None else np.random.default_rng(0)
        self._dist = grid.distance_field(self.cfg.laser_likelihood_max_dist).astype(np.float32)
        self._free_cells = np.flatnonzero(grid.free).astype(np.int32)  # row * W + col
        self._table: Array = np.zeros(0)
        self._dist_pad: Array | None = None
        self._sdf_pad: Array | None = None
        self._sdf_key: float | None = None
        self._table_key: float | None = None
        self._skip: Array | None = None
        self._rmax = 20.0
        if len(self._free_cells) == 0:
            raise InvalidInputError("the map has no free cells to localize in")
        self.particles = np.zeros((0, 3))
        self.weights = np.zeros(0)
        self._odom_last_update: Array | None = None
        self._odom_prev: Array | None = None
        self._resample_count = 0
        self.w_slow = 0.0
        self.w_fast = 0.0
        self._force_update = True
        self._estimate: PoseEstimate | None = None

    # --- initialization -----------------------------------------------------------------
    def set_initial_pose(self, pose: Array, cov: Array | None = None) -> None:
        """Gaussian particle cloud around ``pose`` (Nav2 ``initial_pose`` + default cov)."""
        pose = finite_pose(pose, "initial pose")
        c = self.cfg
        cov = (
            np.diag([c.initial_cov_xx, c.initial_cov_yy, c.initial_cov_aa])
            if cov is None
            else finite_cov(cov, "initial covariance")
        )
        n = c.max_particles
        self.particles = self.rng.multivariate_normal(pose, cov, n)
        self.particles[:, 2] = _wrap(self.particles[:, 2])
        self.weights = np.full(n, 1.0 / n)
        self._reset_bookkeeping()

    def global_localization(self) -> None:
        """Particles uniform over the free space of the map, uniform headings."""
        n = self.cfg.max_particles
        self.particles = self._random_free_poses(n)
        self.weights = np.full(n, 1.0 / n)
        self._reset_bookkeeping()

    def _reset_bookkeeping(self) -> None:
        self.w_slow = self.w_fast = 0.0
        self._force_update = True
        self._estimate = None

    def _random_free_poses(self, n: int) -> Array:
        cells = self._free_cells[self.rng.integers(0, len(self._free_cells), n)]
        g = self.grid
        xy = g.cell_to_world(cells % g.width, cells // g.width)
        xy += self.rng.uniform(-0.5, 0.5, (n, 2)) * g.resolution
        th = self.rng.uniform(-np.pi, np.pi, n)
        return np.column_stack([xy, th])

    # --- models ----------------------------------------------------------------------------
    def _beams(
        self, scan: LaserScan, max_beams: int | None = None, offset: int = 0
    ) -> tuple[Array, Array]:
        """Valid subsampled beams (Nav2 ``max_beams`` stepping, every ``step``-th beam from
        beam ``offset mod step``): ranges and angles."""
        r = np.asarray(scan.ranges, float)
        c = self.cfg
        mb = c.max_beams if max_beams is None else max_beams
        rmax = scan.range_max if c.laser_max_range < 0 else min(c.laser_max_range, scan.range_max)
        rmin = scan.range_min if c.laser_min_range < 0 else max(c.laser_min_range, scan.range_min)
        n = r.shape[0]
        step = max(1, (n - 1) // (mb - 1)) if mb > 1 else n
        idx = np.arange(offset % step, n, step)[:mb]
        rr, aa = r[idx], scan.angles[idx]
        ok = np.isfinite(rr) & (rr >= rmin) & (rr < rmax)
        self._rmax = rmax
        return rr[ok], aa[ok]

    def _laser_origin(self, particles: Array) -> tuple[Array, Array, Array]:
        lx, ly, lth = self.laser_pose
        c, s = np.cos(particles[:, 2]), np.sin(particles[:, 2])
        ox = particles[:, 0] + c * lx - s * ly
        oy = particles[:, 1] + s * lx + c * ly
        return ox, oy, particles[:, 2] + lth

    def likelihood_field(self, particles: Array, ranges: Array, angles: Array) -> Array:
        """Nav2 ``LikelihoodFieldModel``: ``p = 1 + sum_beams pz^3`` with
        ``pz = z_hit exp(-z^2 / (2 sigma_hit^2)) + z_rand / range_max`` and ``z`` the distance
        from the beam endpoint to the nearest obstacle (``max_dist`` off the map)."""
        g = self.grid
        table = self._pz3_table()
        ox, oy, oth = self._laser_origin(particles)
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

    def log_likelihood_field(
        self,
        particles: Array,
        ranges: Array,
        angles: Array,
        sigma: float,
        offset: float = 0.0,
        signed: bool = False,
    ) -> Array:
        """Product-form likelihood field (Nav2's ``likelihood_field_prob`` without beam
        skipping): ``log p = sum_b log(z_hit exp(-d_b^2 / (2 sigma^2)) + z_rand / range_max)``
        with ``d_b`` the distance field BILINEARLY interpolated at the beam endpoint (smooth in
        the pose, unlike the nearest-cell lookup), ``max_dist`` off the map, less ``offset``
        (``resolution / 2``: distance to the edge of the occupied cell, where the surface lies
        on average, instead of its center), floored at 0. With ``signed``, ``d_b`` is the
        absolute value of the interpolated SIGNED distance to that surface
        (:meth:`OccupancyGrid.signed_distance_field`, ``offset`` in m): an endpoint behind
        the surface, inside the obstacle, is penalized like one in front of it (unsigned, the
        field is 0 inside obstacles, so long beams cost nothing and the fit leans away from the
        walls seen). Returns (N,)."""
        g = self.grid
        c = self.cfg
        ox, oy, oth = self._laser_origin(particles)
        bx, by = ranges * np.cos(angles), ranges * np.sin(angles)
        cs, sn = np.cos(oth)[:, None], np.sin(oth)[:, None]
        inv = 1.0 / g.resolution
        # continuous cell coordinates, cell centers at integers (+1: one-cell border)
        fx = (ox - g.origin[0])[:, None] * inv + (cs * bx - sn * by) * inv + 0.5
        fy = (oy - g.origin[1])[:, None] * inv + (sn * bx + cs * by) * inv + 0.5
        fx = np.clip(fx, 0.0, g.width + 0.999)
        fy = np.clip(fy, 0.0, g.height + 0.999)
        i0, j0 = np.floor(fx).astype(np.int32), np.floor(fy).astype(np.int32)
        tx, ty = fx - i0, fy - j0
        d = self._signed_padded(offset) if signed else self._dist_padded()
        w2 = g.width + 2
        k = j0 * w2 + i0
        dist = (d[k] * (1 - tx) + d[k + 1] * tx) * (1 - ty) + (
            d[k + w2] * (1 - tx) + d[k + w2 + 1] * tx
        ) * ty
        if signed:
            dist = np.abs(dist)
        elif offset > 0:
            dist = np.maximum(dist - offset, 0.0)
        pz = c.z_hit * np.exp(-(dist * dist) / (2 * sigma * sigma)) + c.z_rand / self._rmax
        return np.log(pz).sum(axis=1)

    def _dist_padded(self) -> Array:
        """Flattened (H+2)(W+2) distance field with a ``max_dist`` border (cached)."""
        if self._dist_pad is None:
            self._dist_pad = np.pad(
                self._dist, 1, constant_values=self.cfg.laser_likelihood_max_dist
            ).ravel()
        return self._dist_pad

    def _signed_padded(self, offset: float) -> Array:
        """Flattened (H+2)(W+2) signed distance field (surface ``offset`` m out from the
        occupied cell centers) with a ``max_dist`` border (cached per offset)."""
        if self._sdf_key != offset or self._sdf_pad is None:
            md = self.cfg.laser_likelihood_max_dist
            phi = self.grid.signed_distance_field(md, offset / self.grid.resolution)
            self._sdf_pad = np.pad(phi.astype(np.float32), 1, constant_values=md).ravel()
            self._sdf_key = offset
        return self._sdf_pad

    def _pz3_table(self) -> Array:
        """Flattened (H+2)(W+2) table of ``pz^3`` per cell (border: off the map)."""
        key = float(self._rmax)
        if self._table_key != key:
            c = self.cfg
            d = np.pad(self._dist, 1, constant_values=c.laser_likelihood_max_dist).astype(float)
            pz = c.z_hit * np.exp(-(d * d) / (2 * c.sigma_hit**2)) + c.z_rand / key
            self._table = (pz**3).ravel().astype(np.float32)
            self._table_key = key
        return self._table

    def raycast(self, particles: Array, angles: Array, max_range: float) -> Array:
        """Expected ranges (N, B): the first of the points ``k h`` (``h`` half a cell,
        ``k = 1 .. floor(max_range / h)``) along each beam that lies in an occupied cell or
        off the map; ``max_range`` if none.

        Sphere tracing: from a point in a cell, no point nearer than the cell's clearance
        ``D`` (the least distance between the cell's square and an occupied cell's square or
        the map's outside, :meth:`_skip_table`) lies in an occupied cell or off the map, so the
        march jumps ``max(ceil(D / h), 1)`` half-cell steps at once (the points it passes over
        lie nearer than ``D``; the one it lands on is checked): same result as
        visiting every point (but for a point within float rounding, ~1e-13 cells, of a cell
        edge), far fewer visits. Rays are marched in blocks of ``_RAY_BLOCK`` (their arrays
        stay in the cache). The twin's beam model per update (2000 particles x 60 beams,
        ``benchmarks/bench_amcl_cpp.py``): 87 ms visiting every point, 39-44 ms with the
        former skip table (the 2 m-clipped distance field less ``sqrt(2) res``, masked
        gathers), now 12 ms (Nav2's C++ 21.1-21.8 ms on the same scans, interleaved, load
        average ~4).
        """
        n, nb = particles.shape[0], angles.shape[0]
        out = np.empty((n, nb))
        step = max(1, _RAY_BLOCK // max(nb, 1))
        for i in range(0, n, step):
            out[i : i + step] = self._march(particles[i : i + step], angles, max_range)
        return out

    def _march(self, particles: Array, angles: Array, max_range: float) -> Array:
        """:meth:`raycast` on one block of particles. The march runs in padded cell units
        (``x = (ox - x0) / res + 1 + k cos(a) / 2`` for step ``k``; every point after the
        first lies in the map or its one-cell border, where the table stops it, so float ->
        int truncation is the floor) and keeps only the step ``k`` per ray: the table gives
        0 where a point hits, so ``k`` stops there; ``k`` is capped at ``k_max + 1`` (no hit
        within range). Finished rays are dropped once they are half of those marching."""
        g = self.grid
        nb = angles.shape[0]
        ox, oy, oth = self._laser_origin(particles)
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
        table = self._skip_table()
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

    def _skip_table(self) -> Array:
        """Flattened (H+2)(W+2) float table for :meth:`raycast` (cached): 0 in occupied cells
        and the one-cell border (off the map: the march stops), else the half-cell steps
        ``h`` a ray may jump from any point of the cell, ``n = max(ceil(D / h), 1)`` (the
        ``n - 1`` points passed over lie nearer than ``(n - 1) h < D``). ``D`` is the cell's
        clearance: the least distance between its square and the square of an occupied or
        border cell, ``res sqrt(max(|di| - 1, 0)^2 + max(|dj| - 1, 0)^2)`` for cell offsets
        ``(di, dj)``, i.e. the distance transform to the occupied cells dilated by one cell
        (3 x 3), unclipped."""
        if self._skip is None:
            g = self.grid
            occ = np.pad(g.occupied, 1, constant_values=True)
            near = ndimage.binary_dilation(occ, np.ones((3, 3), dtype=bool))
            clear = ndimage.distance_transform_edt(~near) * 2.0  # in half-cell steps h
            n = np.maximum(np.ceil(clear), 1.0)
            n[occ] = 0.0
            self._skip = n.ravel()
        return self._skip

    def beam_model(self, particles: Array, ranges: Array, angles: Array) -> Array:
        """Nav2 ``BeamModel``: ``p = 1 + sum pz^3`` with the four-part mixture of ch. 6.3,
        ``pz = z_hit exp(-z^2 / (2 sigma_hit^2)) + [z < 0] z_short lambda_short
        exp(-lambda_short r) + z_rand / z_max`` for ``z = r - r_expected`` (the ``z_max``
        part never applies: beams at or past ``z_max`` are dropped by :meth:`_beams`).
        (N, 3) particles, (B,) ranges and angles -> (N,)."""
        c = self.cfg
        zmax = self._rmax
        z = self.raycast(particles, angles, zmax)
        np.subtract(ranges[None, :], z, out=z)
        # the short and random parts per beam: [z < 0] picks the first row
        rest = c.z_rand / zmax + np.stack(
            [c.z_short * c.lambda_short * np.exp(-c.lambda_short * ranges), np.zeros_like(ranges)]
        )
        part = np.where(z < 0, rest[0], rest[1])
        np.multiply(z, z, out=z)
        z *= -1.0 / (2 * c.sigma_hit**2)
        pz = np.exp(z, out=z)
        pz *= c.z_hit
        pz += part
        return 1.0 + np.einsum("ij,ij,ij->i", pz, pz, pz)

    def measurement_weights(self, particles: Array, scan: LaserScan) -> Array:
        ranges, angles = self._beams(scan)
        if ranges.size == 0:
            return np.ones(particles.shape[0])
        if self.cfg.laser_model_type == "beam":
            return self.beam_model(particles, ranges, angles)
        return self.likelihood_field(particles, ranges, angles)

    # --- filter steps ----------------------------------------------------------------------
    def _should_update(self, odom_pose: Array) -> bool:
        if self._force_update or self._odom_last_update is None:
            return True
        _rot1, trans, _rot2 = odometry_delta(self._odom_last_update, odom_pose)
        dth = abs(float(_wrap(odom_pose[2] - self._odom_last_update[2])))
        return trans >= self.cfg.update_min_d or dth >= self.cfg.update_min_a

    def predict(self, odom_pose: Array) -> None:
        """Apply the motion model for the odometry change since the last prediction."""
        odom_pose = np.asarray(odom_pose, float).reshape(3)
        if self._odom_prev is not None:
            delta = odometry_delta(self._odom_prev, odom_pose)
            if delta[1] > 0 or abs(delta[0]) + abs(delta[2]) > 0:
                c = self.cfg
                self.particles = sample_motion(
                    self.particles, delta, (c.alpha1, c.alpha2, c.alpha3, c.alpha4), self.rng
                )
        self._odom_prev = odom_pose.copy()

    def update(self, odom_pose: Array, scan: LaserScan, force: bool = False) -> PoseEstimate:
        """One AMCL cycle: if the base moved past the update thresholds (or ``force``), apply
        the motion model, weight with the laser model, maybe resample; return the estimate."""
        if self.particles.shape[0] == 0:
            raise InvalidInputError("set an initial pose or call global_localization() first")
        odom_pose = finite_pose(odom_pose, "odometry pose")
        check_scan(scan)
        if not (force or self._should_update(odom_pose)):
            return self._current(updated=False)
        self.predict(odom_pose)
        p = self.measurement_weights(self.particles, scan)
        self._apply_weights(p)
        self._resample_count += 1
        if self._resample_count % self.cfg.resample_interval == 0:
            self.resample()
        self._odom_last_update = odom_pose.copy()
        self._force_update = False
        self._estimate = None
        return self._current(updated=True)

    def _apply_weights(self, p: Array) -> None:
        """Multiply weights by ``p``, normalize, update ``w_slow`` / ``w_fast``."""
        w = self.weights * p
        total = float(w.sum())
        if not np.isfinite(total) or total <= 0:
            self.weights = np.full(len(w), 1.0 / len(w))
            return
        self.weights = w / total
        w_avg = float(np.mean(p))
        c = self.cfg
        if self.w_slow == 0.0:
            self.w_slow = w_avg
        else:
            self.w_slow += c.recovery_alpha_slow * (w_avg - self.w_slow)
        if self.w_fast == 0.0:
            self.w_fast = w_avg
        else:
            self.w_fast += c.recovery_alpha_fast * (w_avg - self.w_fast)

    def _kld_limit(self, k: np.ndarray) -> np.ndarray:
        """Nav2 ``pf_resample_limit``: particles needed for ``k`` occupied bins."""
        c = self.cfg
        k = np.asarray(k, float)
        km1 = np.maximum(k - 1, 1e-9)
        b = 2.0 / (9.0 * km1)
        x = 1.0 - b + np.sqrt(b) * c.pf_z
        n = np.ceil(km1 / (2.0 * c.pf_err) * x**3)
        n = np.where(k <= 1, c.max_particles, n)
        return np.clip(n, c.min_particles, c.max_particles).astype(int)

    def _bins(self, particles: Array) -> Array:
        c = self.cfg
        return np.column_stack(
            [
                np.floor(particles[:, 0] / c.kld_bin_xy),
                np.floor(particles[:, 1] / c.kld_bin_xy),
                np.floor(particles[:, 2] / c.kld_bin_theta),
            ]
        ).astype(np.int64)

    def resample(self, weights: Array | None = None) -> None:
        """Low-variance resampling with KLD-adaptive size and random recovery particles."""
        c = self.cfg
        w = self.weights if weights is None else weights
        m = c.max_particles
        w_diff = 0.0
        if self.w_slow > 0:
            w_diff = max(0.0, 1.0 - self.w_fast / self.w_slow)
        cdf = np.cumsum(w)
        cdf /= cdf[-1]
        u = (self.rng.uniform() + np.arange(m)) / m
        idx = np.minimum(np.searchsorted(cdf, u), len(w) - 1)
        new = self.particles[idx]
        new = new[self.rng.permutation(m)]  # KLD counts bins along a random order
        if w_diff > 0:
            rand = self.rng.uniform(size=m) < w_diff
            if rand.any():
                new[rand] = self._random_free_poses(int(rand.sum()))
        b = self._bins(new)
        b -= b.min(axis=0)
        keys = (b[:, 0] * (b[:, 1].max() + 1) + b[:, 1]) * (b[:, 2].max() + 1) + b[:, 2]
        _, first = np.unique(keys, return_index=True)  # 1D keys: much faster than axis=0
        is_first = np.zeros(m, dtype=bool)
        is_first[first] = True
        k = np.cumsum(is_first)
        limit = self._kld_limit(k)
        n_idx = np.flatnonzero(np.arange(1, m + 1) >= limit)
        n = int(n_idx[0]) + 1 if n_idx.size else m
        n = max(min(n, m), c.min_particles)
        self.particles = new[:n]
        self.weights = np.full(n, 1.0 / n)
        if w_diff > 0:
            self.w_slow = self.w_fast = 0.0  # Nav2 resets after injecting random particles

    # --- estimate --------------------------------------------------------------------------
    def estimate(self) -> PoseEstimate:
        return self._current(updated=False)

    def initialize(self, pose: Array, cov: Array | None = None) -> None:
        """:class:`~mmpa.localization.localizer.Localizer` spelling of ``set_initial_pose``."""
        self.set_initial_pose(pose, cov)

    def pose_at(self, odom_pose: Array) -> Array:
        """The estimate carried forward by the odometry since the last filter update (what
        Nav2 publishes through the ``map -> odom`` transform)."""
        odom_pose = finite_pose(odom_pose, "odometry pose")
        est = self.estimate().pose
        ref = self._odom_prev
        if ref is None:
            return est.copy()
        return compose_odom(est, ref, odom_pose)

    def _current(self, updated: bool) -> PoseEstimate:
        if self._estimate is None:
            pose, cov = self._cluster_mean()
            self._estimate = PoseEstimate(pose, cov, len(self.particles), False, self.name)
        e = self._estimate
        return PoseEstimate(e.pose, e.cov, e.n_particles, updated, e.source)

    def _cluster_mean(self) -> tuple[Array, Array]:
        """Weighted mean and covariance of the heaviest cluster (connected histogram bins,
        heading circular: the bins just below +pi and just above -pi are neighbours)."""
        P, w = self.particles, self.weights
        labels = cluster_labels(P, self.cfg.kld_bin_xy, self.cfg.kld_bin_theta)
        sums = np.bincount(labels, weights=w)
        best = int(np.argmax(sums))
        sel = labels == best
        ws = w[sel] / max(float(w[sel].sum()), 1e-300)
        Ps = P[sel]
        mx = float(ws @ Ps[:, 0])
        my = float(ws @ Ps[:, 1])
        cth = float(ws @ np.cos(Ps[:, 2]))
        sth = float(ws @ np.sin(Ps[:, 2]))
        th = float(np.arctan2(sth, cth))
        d = np.column_stack([Ps[:, 0] - mx, Ps[:, 1] - my, _wrap(Ps[:, 2] - th)])
        cov = (d * ws[:, None]).T @ d
        return np.array([mx, my, th]), cov


def cluster_labels(
    particles: Array, bin_xy: float, bin_theta: float, max_cells: int = 2_000_000
) -> np.ndarray:
    """Cluster id (N,) int of every particle (N, 3): particles are binned ``bin_xy`` m x
    ``bin_xy`` m x ``bin_theta`` rad (Nav2's pf histogram) and occupied bins that touch
    (26-connectivity) form a cluster. The heading axis is CIRCULAR: the bin holding headings
    just below +pi touches the one just above -pi, so a cloud straddling +-pi is one cluster
    (split in two, the heavier half's mean was off by up to half the cloud's width). A cloud
    spanning more than ``max_cells`` bins is one cluster (0 for all)."""
    P = np.asarray(particles, float)
    n_th = max(1, int(np.ceil(2 * np.pi / bin_theta - 1e-9)))
    bx = np.floor(P[:, 0] / bin_xy).astype(np.int64)
    by = np.floor(P[:, 1] / bin_xy).astype(np.int64)
    bt = np.floor((_wrap(P[:, 2]) + np.pi) / bin_theta).astype(np.int64) % n_th
    bx -= bx.min()
    by -= by.min()
    shape = (int(bx.max()) + 1, int(by.max()) + 1, n_th)
    if shape[0] * shape[1] * shape[2] > max_cells:
        return np.zeros(len(P), dtype=np.int64)
    occ = np.zeros(shape, dtype=bool)
    occ[bx, by, bt] = True
    lab, n_lab = ndimage.label(occ, structure=np.ones((3, 3, 3)))
    if n_th > 2 and occ[:, :, 0].any() and occ[:, :, -1].any():
        # join the first and last heading layers: label pairs that touch across the wrap
        first = np.pad(lab[:, :, 0], 1)
        last = lab[:, :, -1]
        a_list, b_list = [], []
        for dx in (-1, 0, 1):
            for dy in (-1, 0, 1):
                nb = first[1 + dx : 1 + dx + shape[0], 1 + dy : 1 + dy + shape[1]]
                both = (nb > 0) & (last > 0)
                a_list.append(nb[both])
                b_list.append(last[both])
        a, b = np.concatenate(a_list), np.concatenate(b_list)
        if a.size:
            g = sparse.coo_matrix((np.ones(a.size), (a, b)), shape=(n_lab + 1, n_lab + 1))
            _, comp = csgraph.connected_components(g, directed=False)
            lab = comp[lab]
    return lab[bx, by, bt].astype(np.int64)
