"""Adaptive Monte Carlo localization, vectorized numpy, with the Nav2 AMCL feature set.

Follows Nav2 ``nav2_amcl`` (itself Thrun, Burgard, Fox, *Probabilistic Robotics* ch. 4-6 and 8),
one module per stage, composed by the thin class :class:`AMCL`:

- motion: differential-drive odometry model (``alpha1..alpha4``, Table 5.6, with Nav2's
  reverse-driving handling of the rotation terms): :mod:`mmpa.localization.motion`;
- sensor: the laser model picked by ``laser_model_type`` from :data:`LASER_MODELS`: the
  likelihood field (``z_hit``, ``z_rand``, ``sigma_hit``, ``max_beams``,
  ``laser_likelihood_max_dist``; Nav2's ``p = 1 + sum pz^3``,
  :mod:`mmpa.localization.likelihood_field`), its product form ``likelihood_field_prob``
  (``p = prod pz``, the default) or the beam model (``z_hit``, ``z_short``,
  ``z_max``, ``z_rand``, ``lambda_short``; ray casting in the grid,
  :mod:`mmpa.localization.beam_model`);
- resampling: KLD-sampling (``min_particles``, ``max_particles``, ``pf_err``, ``pf_z``; Nav2's
  histogram bins 0.5 m x 0.5 m x 10 deg and its use of ``pf_z`` as the quantile) with
  low-variance resampling and recovery by random particles (``recovery_alpha_slow`` /
  ``recovery_alpha_fast``): :mod:`mmpa.localization.resampling`;
- global localization (uniform over free space), initial pose with covariance, and the update
  thresholds ``update_min_d`` / ``update_min_a``;
- improvement (``scan_refine``, :mod:`mmpa.localization.refine`): a scan-to-map match of the
  predicted cloud's estimate draws part of the particles (a defensive mixture proposal).

The estimate is the weighted mean of the heaviest cluster (particles grouped by their
histogram bins, as Nav2 does, on a circular heading axis: :func:`cluster_labels`), with its
covariance; every heading mean is circular.

Units: m, rad. Poses ``[x, y, theta]`` in ``map``; odometry poses in ``odom``; the lidar mount
``[x, y, yaw]`` in ``base_link``. All random draws come from the ``numpy.random.Generator``
given to the filter.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from mmpa.core.errors import InvalidInputError
from mmpa.core.geometry import Array
from mmpa.localization.beam_model import (
    RAY_BLOCK,
    beam_pz,
    beam_weights,
    march,
    raycast,
    skip_table,
)
from mmpa.localization.config import AMCLConfig
from mmpa.localization.global_search import GlobalSearch, SearchResult
from mmpa.localization.likelihood_field import (
    laser_origin,
    likelihood_field,
    log_likelihood_field,
    padded,
    pz3_table,
    subsample_beams,
)
from mmpa.localization.motion import compose_odom, moved_enough, odometry_delta, sample_motion
from mmpa.localization.multimodal import cluster_weights, draw_clusters, seed_weights
from mmpa.localization.pose import PoseEstimate, check_scan, finite_cov, finite_pose, wrap
from mmpa.localization.proposal import defensive_mixture
from mmpa.localization.refine import Refinement, ScanRefiner
from mmpa.localization.resampling import (
    cluster_labels,
    cluster_mean,
    kld_bins,
    kld_limit,
    kld_size,
    low_variance_resample,
    normalize,
    recovery_averages,
)
from mmpa.maps.occupancy import OccupancyGrid
from mmpa.robot.interfaces import LaserScan

_RAY_BLOCK = RAY_BLOCK
_wrap = wrap  # the former private name, kept for callers

__all__ = [
    "AMCL",
    "LASER_MODELS",
    "AMCLConfig",
    "LaserModel",
    "PoseEstimate",
    "check_scan",
    "cluster_labels",
    "compose_odom",
    "finite_cov",
    "finite_pose",
    "odometry_delta",
    "sample_motion",
]

#: A laser model: ``(filter, particles (N, 3), ranges (B,), angles (B,)) -> weights (N,)``.
LaserModel = Callable[["AMCL", Array, Array, Array], Array]


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
        self.refiner = ScanRefiner(grid, self.laser_pose)
        self.last_refinement: Refinement | None = None  # None: not tried at the last update
        self.refinements = 0  # accepted matches so far
        c = self.cfg
        self.global_search = GlobalSearch(
            grid, self.refiner, c.global_search_resolution, c.global_search_ratio,
            c.global_hypotheses, c.kld_bin_xy, c.kld_bin_theta, c.max_beams,
        )  # fmt: skip
        self.last_search: SearchResult | None = None  # the last global start's search
        self._seed_pending = False  # the next update seeds the cloud by the global search
        self.multimodal = False  # seeded from several hypotheses, not yet one cluster

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
        self.particles[:, 2] = wrap(self.particles[:, 2])
        self.weights = np.full(n, 1.0 / n)
        self._reset_bookkeeping()

    def global_localization(self) -> None:
        """Particles uniform over the free space of the map, uniform headings (Nav2); with
        ``global_search`` the next update replaces them by particles around the poses where
        its scan fits the map (:meth:`_seed`)."""
        n = self.cfg.max_particles
        self.particles = self._random_free_poses(n)
        self.weights = np.full(n, 1.0 / n)
        self._reset_bookkeeping()
        self._seed_pending = self.cfg.global_search

    def _reset_bookkeeping(self) -> None:
        self.w_slow = self.w_fast = 0.0
        self._force_update = True
        self._estimate = None
        self._seed_pending = self.multimodal = False

    def _seed(self, odom_pose: Array, scan: LaserScan) -> PoseEstimate:
        """The global start (``global_search``): the whole-map search of ``scan``
        (:class:`~mmpa.localization.global_search.GlobalSearch`); ``max_particles`` shared
        evenly among its hypotheses, each drawn from ``N(h, inflate^2 C_h + diag(floor^2))``
        (the refinement's proposal, :meth:`_proposal_cov`), weighted by
        :func:`~mmpa.localization.multimodal.seed_weights`, resampled. No hypothesis (too
        few beams, nothing fits): the uniform cloud stays and the next scan is searched."""
        res = self.global_search.search(scan)
        self.last_search = res
        self._odom_prev = odom_pose.copy()
        if not res.ok:
            return self._current(updated=False)
        hyps = res.hypotheses
        n = self.cfg.max_particles
        groups = np.arange(n) % len(hyps)
        poses = np.array([h.pose for h in hyps])
        covs = [self._proposal_cov(h.cov) for h in hyps]
        x = np.empty((n, 3))
        for k, cov in enumerate(covs):
            sel = groups == k
            x[sel] = self.rng.standard_normal((int(sel.sum()), 3)) @ np.linalg.cholesky(cov).T
            x[sel] += poses[k]
        x[:, 2] = wrap(x[:, 2])
        lik = self.measurement_weights(np.concatenate([x, poses]), scan)
        self.particles = x
        self.weights = seed_weights(x, groups, poses, covs, lik)
        self._seed_pending = False
        self.multimodal = len(hyps) > 1
        self.resample()
        return self._finish_update(odom_pose)

    def _random_free_poses(self, n: int) -> Array:
        cells = self._free_cells[self.rng.integers(0, len(self._free_cells), n)]
        g = self.grid
        xy = g.cell_to_world(cells % g.width, cells // g.width)
        xy += self.rng.uniform(-0.5, 0.5, (n, 2)) * g.resolution
        th = self.rng.uniform(-np.pi, np.pi, n)
        return np.column_stack([xy, th])

    # --- sensor models ---------------------------------------------------------------------
    def _beams(
        self, scan: LaserScan, max_beams: int | None = None, offset: int = 0
    ) -> tuple[Array, Array]:
        """Valid subsampled beams (Nav2 ``max_beams`` stepping, every ``step``-th beam from
        beam ``offset mod step``): ranges and angles (:func:`subsample_beams`)."""
        c = self.cfg
        mb = c.max_beams if max_beams is None else max_beams
        r, a, self._rmax = subsample_beams(scan, mb, offset, c.laser_max_range, c.laser_min_range)
        return r, a

    def _laser_origin(self, particles: Array) -> tuple[Array, Array, Array]:
        return laser_origin(particles, self.laser_pose)

    def likelihood_field(self, particles: Array, ranges: Array, angles: Array) -> Array:
        """Nav2 ``LikelihoodFieldModel``: ``p = 1 + sum_beams pz^3`` with
        ``pz = z_hit exp(-z^2 / (2 sigma_hit^2)) + z_rand / range_max`` and ``z`` the distance
        from the beam endpoint to the nearest obstacle (``max_dist`` off the map)."""
        table = self._pz3_table()
        return likelihood_field(self.grid, table, self._laser_origin(particles), ranges, angles)

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
        c = self.cfg
        origin = self._laser_origin(particles)
        field = self._signed_padded(offset) if signed else self._dist_padded()
        return log_likelihood_field(
            self.grid, field, origin, ranges, angles, sigma, offset, signed,
            c.z_hit, c.z_rand, self._rmax,
        )  # fmt: skip

    def _dist_padded(self) -> Array:
        """Flattened (H+2)(W+2) distance field with a ``max_dist`` border (cached)."""
        if self._dist_pad is None:
            self._dist_pad = padded(self._dist, self.cfg.laser_likelihood_max_dist)
        return self._dist_pad

    def _signed_padded(self, offset: float) -> Array:
        """Flattened (H+2)(W+2) signed distance field (surface ``offset`` m out from the
        occupied cell centers) with a ``max_dist`` border (cached per offset)."""
        if self._sdf_key != offset or self._sdf_pad is None:
            md = self.cfg.laser_likelihood_max_dist
            phi = self.grid.signed_distance_field(md, offset / self.grid.resolution)
            self._sdf_pad = padded(phi.astype(np.float32), md)
            self._sdf_key = offset
        return self._sdf_pad

    def _pz3_table(self) -> Array:
        """Flattened (H+2)(W+2) table of ``pz^3`` per cell (border: off the map)."""
        key = float(self._rmax)
        if self._table_key != key:
            c = self.cfg
            self._table = pz3_table(
                self._dist, c.laser_likelihood_max_dist, c.z_hit, c.z_rand, c.sigma_hit, key
            )
            self._table_key = key
        return self._table

    def likelihood_field_prob(self, particles: Array, ranges: Array, angles: Array) -> Array:
        """Nav2 ``LikelihoodFieldModelProb`` without beam skipping: ``p = prod_b pz_b``,
        ``pz = z_hit exp(-d^2 / (2 sigma_hit^2)) + z_rand / range_max``, ``d`` the distance
        from the endpoint to the nearest occupied cell's center (Nav2's field, but
        bilinearly interpolated: smooth in the pose; :meth:`log_likelihood_field`). Returned
        divided by the largest (the product of 60 beams underflows): (N,) in (0, 1]."""
        ll = self.log_likelihood_field(particles, ranges, angles, self.cfg.sigma_hit)
        return np.exp(ll - ll.max())

    def raycast(self, particles: Array, angles: Array, max_range: float) -> Array:
        """Expected ranges (N, B) by sphere tracing (:func:`~.beam_model.raycast`);
        ``max_range`` where no occupied cell is hit."""
        return raycast(self.grid, self._skip_table(), particles, self.laser_pose, angles, max_range)

    def _march(self, particles: Array, angles: Array, max_range: float) -> Array:
        """:meth:`raycast` on one block of particles (:func:`~.beam_model.march`)."""
        return march(self.grid, self._skip_table(), particles, self.laser_pose, angles, max_range)

    def _skip_table(self) -> Array:
        """The ray-casting table (cached): :func:`mmpa.localization.beam_model.skip_table`."""
        if self._skip is None:
            self._skip = skip_table(self.grid)
        return self._skip

    def beam_model(self, particles: Array, ranges: Array, angles: Array) -> Array:
        """The beam model with the four-part mixture of ch. 6.3, ``pz = z_hit exp(-z^2 / (2
        sigma_hit^2)) + [z < 0] z_short lambda_short exp(-lambda_short r) + z_rand / z_max``
        for ``z = r - r_expected`` (the ``z_max`` part never applies: beams at or past
        ``z_max`` are dropped by :meth:`_beams`): ``beam_form`` "product" multiplies the
        beams (Thrun et al. Table 6.1; returned divided by the largest: (0, 1]),
        "sum_of_cubes" is Nav2's ``BeamModel``, ``p = 1 + sum pz^3``. (N, 3) particles, (B,)
        ranges and angles -> (N,)."""
        c = self.cfg
        zmax = self._rmax
        z = self.raycast(particles, angles, zmax)
        args = (z, ranges, c.z_hit, c.z_short, c.z_rand, c.lambda_short, c.sigma_hit, zmax)
        if c.beam_form == "sum_of_cubes":
            return beam_weights(*args)
        ll = np.log(beam_pz(*args)).sum(axis=1)
        return np.exp(ll - ll.max())

    def measurement_weights(self, particles: Array, scan: LaserScan) -> Array:
        """The weights (N,) of the laser model ``laser_model_type`` (:data:`LASER_MODELS`)."""
        ranges, angles = self._beams(scan)
        if ranges.size == 0:
            return np.ones(particles.shape[0])
        return LASER_MODELS[self.cfg.laser_model_type](self, particles, ranges, angles)

    # --- filter steps ----------------------------------------------------------------------
    def _should_update(self, odom_pose: Array) -> bool:
        if self._force_update or self._odom_last_update is None:
            return True
        c = self.cfg
        return moved_enough(self._odom_last_update, odom_pose, c.update_min_d, c.update_min_a)

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
        if self._seed_pending:
            return self._seed(odom_pose, scan)
        self.predict(odom_pose)
        if self.multimodal and self.cfg.scan_refine:
            self._refine_clusters(scan)
        elif not (self.cfg.scan_refine and self._refined_weights(scan)):
            p = self.measurement_weights(self.particles, scan)
            self._apply_weights(p)
        self._resample_count += 1
        if self._resample_count % self.cfg.resample_interval == 0:
            self.resample()
        if self.multimodal:
            c = self.cfg
            self.multimodal = bool(
                cluster_labels(self.particles, c.kld_bin_xy, c.kld_bin_theta).max() > 0
            )
        return self._finish_update(odom_pose)

    def _proposal_cov(self, cov: Array) -> Array:
        """``inflate^2 C + diag(floor^2)`` of a match's covariance ``C``, its eigenvalues
        clipped to ``[0, refine_max_sd^2]`` (a match along a corridor has a near-singular
        ``H``: ``C`` huge or, by rounding, indefinite; the proposal stays a cluster's width)."""
        c = self.cfg
        ev, vec = np.linalg.eigh(0.5 * (cov + cov.T))
        ev = np.clip(np.nan_to_num(ev, nan=0.0), 0.0, c.refine_max_sd**2)
        floor = [c.refine_floor_xy**2, c.refine_floor_xy**2, c.refine_floor_theta**2]
        return c.refine_inflate**2 * (vec * ev) @ vec.T + np.diag(floor)

    def _refine_clusters(self, scan: LaserScan) -> None:
        """The scan refinement of every cluster while the cloud is multi-modal
        (:mod:`mmpa.localization.multimodal`): the ``global_hypotheses`` heaviest clusters
        within ``refine_max_sd`` are matched from their means; the laser model at all
        particles and matches in one call, so that the clusters compare."""
        c = self.cfg
        labels = cluster_labels(self.particles, c.kld_bin_xy, c.kld_bin_theta)

        def match(mean: Array, cov: Array, rank: int) -> Refinement | None:
            sd = np.sqrt(max(np.linalg.eigvalsh(cov[:2, :2]).max(), 0.0))
            if rank >= c.global_hypotheses or sd > c.refine_max_sd:
                return None
            return self.refiner.match(mean, scan)

        floor = np.array([c.refine_floor_xy, c.refine_floor_xy, c.refine_floor_theta])
        draws = draw_clusters(
            self.particles, self.weights, labels, match, self._proposal_cov,
            c.refine_fraction, floor, self.rng,
        )  # fmt: skip
        self.last_refinement = draws[0].ref
        self.refinements += sum(d.peak is not None for d in draws)
        self.particles = np.concatenate([d.x for d in draws])
        peaks = [d.peak for d in draws if d.peak is not None]
        lik = self.measurement_weights(
            np.concatenate([self.particles, *[p[None] for p in peaks]]), scan
        )
        self.weights = cluster_weights(draws, lik)

    def _refined_weights(self, scan: LaserScan) -> bool:
        """The scan refinement (:mod:`mmpa.localization.refine`): match the predicted cloud's
        estimate; if accepted, draw ``refine_fraction`` of the particles around the match and
        weight all by the laser model times the mixture's importance factor. False (nothing
        changed) when the cloud is not one tight cluster or the match is refused."""
        c = self.cfg
        self.last_refinement = None
        start, cov = self._cluster_mean()
        if np.sqrt(max(np.linalg.eigvalsh(cov[:2, :2]).max(), 0.0)) > c.refine_max_sd:
            return False
        ref = self.refiner.match(start, scan)
        self.last_refinement = ref
        if not ref.ok:
            return False
        self.refinements += 1
        q = c.refine_inflate**2 * ref.cov + np.diag(
            [c.refine_floor_xy**2, c.refine_floor_xy**2, c.refine_floor_theta**2]
        )
        x, log_f = defensive_mixture(
            self.particles, self.weights, ref.pose, q, c.refine_fraction, self.rng
        )
        p = self.measurement_weights(x, scan)
        self.particles = x
        self.weights = np.full(len(x), 1.0 / len(x))
        self._apply_weights(p * np.exp(log_f - log_f.max()))
        return True

    def _finish_update(self, odom_pose: Array) -> PoseEstimate:
        """Bookkeeping after a filter update at ``odom_pose``; the new estimate."""
        self._odom_last_update = odom_pose.copy()
        self._force_update = False
        self._estimate = None
        return self._current(updated=True)

    def _apply_weights(self, p: Array) -> None:
        """Multiply weights by ``p``, normalize, update ``w_slow`` / ``w_fast``."""
        w = normalize(self.weights, p)
        if w is None:
            self.weights = np.full(len(self.weights), 1.0 / len(self.weights))
            return
        self.weights = w
        c = self.cfg
        self.w_slow, self.w_fast = recovery_averages(
            self.w_slow, self.w_fast, float(np.mean(p)), c.recovery_alpha_slow,
            c.recovery_alpha_fast,
        )  # fmt: skip

    def _kld_limit(self, k: np.ndarray) -> np.ndarray:
        """Nav2 ``pf_resample_limit``: particles needed for ``k`` occupied bins."""
        c = self.cfg
        return kld_limit(k, c.pf_err, c.pf_z, c.min_particles, c.max_particles)

    def _bins(self, particles: Array) -> Array:
        return kld_bins(particles, self.cfg.kld_bin_xy, self.cfg.kld_bin_theta)

    def resample(self, weights: Array | None = None) -> None:
        """Low-variance resampling with KLD-adaptive size and random recovery particles."""
        c = self.cfg
        w = self.weights if weights is None else weights
        m = c.max_particles
        w_diff = 0.0
        if self.w_slow > 0:
            w_diff = max(0.0, 1.0 - self.w_fast / self.w_slow)
        new = low_variance_resample(self.particles, w, m, w_diff, self.rng, self._random_free_poses)
        n = kld_size(new, c.kld_bin_xy, c.kld_bin_theta, c.pf_err, c.pf_z, c.min_particles, m)
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
        return cluster_mean(
            self.particles, self.weights, self.cfg.kld_bin_xy, self.cfg.kld_bin_theta
        )


#: The laser models by ``AMCLConfig.laser_model_type``: one interface (:data:`LaserModel`).
LASER_MODELS: dict[str, LaserModel] = {
    "likelihood_field": AMCL.likelihood_field,
    "likelihood_field_prob": AMCL.likelihood_field_prob,
    "beam": AMCL.beam_model,
}
