"""Reflector-enhanced AMCL: paper 001 Algorithm 1, eq. 3-8, on top of :class:`AMCL`.

Per scan (Algorithm 1), one stage per module, composed by :class:`EnhancedAMCL`:

1. ``R, M_bar = LaserReflectorIdentification(z_t, u_t, M)``: detect reflectors, identify them by
   triangle matching, trilaterate ``mu_G`` (eq. 1-2): :mod:`mmpa.localization.observer`.
2. Fewer than three identified (``M_bar`` empty): plain AMCL (lines 4-10), or (improvement,
   ``track_partial``) tracking with the 1-2 reflectors still seen and the sharp laser:
   :mod:`mmpa.localization.tracking`.
3. Otherwise (lines 12-26): motion model; laser weight ``omega_t = omega_{t-1} p(z_t | x_t)``
   (eq. 5, normalized); position weight ``d`` (eq. 3); orientation weight ``s`` (eq. 4);
   fused ``omega_new = alpha s omega + beta d`` (eq. 6, alpha = 154, beta = 1), normalized;
   resampling on ``omega_new`` (``ParticleGeneration``); then each particle is replaced, with
   probability ``d`` if ``d > 0.01`` (eq. 8), by a new particle ``lambda Q + mu_G`` (eq. 7):
   :mod:`mmpa.localization.fusion` (eq. 3's metric, eq. 6 and eq. 7 each a strategy picked by
   ``position_metric``, ``fusion``, ``injection``) and :mod:`mmpa.localization.proposal`.

``EnhancedConfig.paper()`` is Algorithm 1 as printed (method ``enhanced-paper``); the default
adds our improvements (product fusion, honest fix with a common range bias, gating and
re-seeding after kidnapping, mixture and two-stage proposals, the sharp laser field, partial
tracking, landmark refinement). ``docs/localization.md`` gives each one's reasoning and the
measurements behind it.

Units: m, rad. Particles and ``mu_G`` ``[x, y, theta]`` in ``map``; odometry in ``odom``;
detections, ranges and bearings in ``base_link``; the lidar mount ``[x, y, yaw]`` in
``base_link``. All random draws come from the filter's ``numpy.random.Generator``.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from mmpa.core.errors import InvalidInputError
from mmpa.core.geometry import Array
from mmpa.localization.amcl import AMCL
from mmpa.localization.config import AMCLConfig, EnhancedConfig, ObserverConfig
from mmpa.localization.fusion import (
    EQ3_NORM,
    FUSIONS,
    INJECTIONS,
    POSITION_METRICS,
    injection_probability,
    orientation_weight,
    position_weight,
)
from mmpa.localization.observer import (
    ReflectorFix,
    ReflectorObserver,
    sensor_to_base,
    update_bias,
)
from mmpa.localization.pose import PoseEstimate, check_scan, finite_pose, wrap
from mmpa.localization.proposal import (
    gaussian_fit,
    log_gauss,
    mixture_proposal,
    refine_proposal,
)
from mmpa.localization.tracking import (
    associate,
    landmark_sd,
    landmark_update,
    partial_proposal,
    reflector_likelihood,
    tracked_fix,
)
from mmpa.maps.occupancy import OccupancyGrid
from mmpa.robot.interfaces import LaserScan

_EQ3_NORM = EQ3_NORM  # the former private name

__all__ = [
    "AMCLConfig",
    "EnhancedAMCL",
    "EnhancedConfig",
    "ObserverConfig",
    "ReflectorFix",
    "ReflectorObserver",
    "gaussian_fit",
    "landmark_update",
    "log_gauss",
    "orientation_weight",
    "position_weight",
    "refine_proposal",
    "sensor_to_base",
    "update_bias",
]


def _reflector_radius(
    grid: OccupancyGrid, landmarks: Array | None, n_landmarks: int, given: float | None
) -> float | None:
    """The reflector radius (m) detection fits: the caller's, else the map's; landmarks given
    without a radius on a map without one would silently use the config's default (4 cm):
    refused. None: keep the config's."""
    if given is not None:
        if not (np.isfinite(given) and given >= 0):
            raise InvalidInputError(f"reflector_radius must be finite and >= 0 m, got {given}")
        return float(given)
    if grid.reflector_radius > 0:
        return float(grid.reflector_radius)
    if landmarks is not None and n_landmarks > 0:
        raise InvalidInputError(
            "landmarks given without reflector_radius and the map has none: pass "
            "reflector_radius= (m, 0 for flat tape) so detection fits the right circle"
        )
    return None


class EnhancedAMCL(AMCL):
    """AMCL with Algorithm 1 (see the module docstring)."""

    name = "enhanced"

    def __init__(
        self,
        grid: OccupancyGrid,
        laser_pose: Array,
        cfg: EnhancedConfig | None = None,
        rng: np.random.Generator | None = None,
        landmarks: Array | None = None,
        reflector_radius: float | None = None,
    ) -> None:
        self.ecfg = cfg or EnhancedConfig()
        super().__init__(grid, laser_pose, self.ecfg.amcl, rng)
        lm = grid.reflectors if landmarks is None else np.asarray(landmarks, float).reshape(-1, 2)
        obs_cfg = self.ecfg.observer
        radius = _reflector_radius(grid, landmarks, len(lm), reflector_radius)
        if radius is not None:
            det = obs_cfg.detection.model_copy(update={"radius": radius})
            obs_cfg = obs_cfg.model_copy(update={"detection": det})
        #: True: fewer than three reflectors and ``fallback_to_amcl``, plain AMCL throughout
        self.plain_amcl = False
        if len(lm) < 3:
            if not self.ecfg.fallback_to_amcl:
                src = "the map" if landmarks is None else "landmarks="
                raise InvalidInputError(
                    f"enhanced AMCL needs >= 3 reflector landmarks; {src} holds {len(lm)}. "
                    "Use the 'amcl' method, or set EnhancedConfig.fallback_to_amcl=True to run "
                    "plain AMCL on this map"
                )
            self.plain_amcl = True
        self.observer = ReflectorObserver(lm, laser_pose, obs_cfg)
        self.last_fix: ReflectorFix | None = None
        self._far_fixes = 0
        self.kidnap_resets = 0
        self.track_status = "none"  # why the last partial tracking fix was (not) made
        self.last_fix_weak = False  # the last fused fix was tracked or weak (weak_fix_sd)
        self._scans_seen = 0
        self._beam_offset = 0  # first beam of the sharp laser's subset (partial_laser_rotate)
        # landmark offsets (improvement, landmark_refine): information form, prior N(0, s^2 I)
        n_lm = len(self.observer.landmarks)
        self._lm_info = np.tile(np.eye(2) / self.ecfg.landmark_map_sigma**2, (n_lm, 1, 1))
        self._lm_vec = np.zeros((n_lm, 2))

    # --- landmarks (improvement, landmark_refine) ------------------------------------------
    @property
    def landmark_offsets(self) -> Array:
        """(n, 2) m: estimated true minus surveyed position of each landmark (zeros without
        ``landmark_refine`` or before a redundant fix)."""
        return np.linalg.solve(self._lm_info, self._lm_vec[:, :, None])[:, :, 0]

    @property
    def tracking_landmarks(self) -> Array:
        """(n, 2) landmark positions used with fewer than three reflectors: the map's, plus
        :attr:`landmark_offsets` with ``landmark_refine``."""
        L = self.observer.landmarks
        return L + self.landmark_offsets if self.ecfg.landmark_refine else L

    def landmark_sd(self, ids: np.ndarray) -> Array:
        """(n,) m: how well the positions :attr:`tracking_landmarks` gives for the landmarks
        ``ids`` are known in ``map`` (:func:`~mmpa.localization.tracking.landmark_sd`)."""
        e = self.ecfg
        return landmark_sd(
            self._lm_info, ids, self.observer.cfg.survey_sigma, e.landmark_refine,
            e.landmark_min_reflectors,
        )  # fmt: skip

    def _learn_landmarks(self, fix: ReflectorFix) -> None:
        """:func:`landmark_update` with a redundant fix (see ``landmark_refine``)."""
        e = self.ecfg
        ids = fix.ids
        beams = fix.beams if fix.beams is not None else np.ones(len(ids))
        sr, sb = self.observer.sigmas(beams, redundant=True)
        pose_var = float(np.trace(fix.trilateration.cov[:2, :2])) / 2
        info, vec = landmark_update(
            self._lm_info[ids], self._lm_vec[ids], fix.pose, self.observer.landmarks[ids],
            fix.ranges, fix.bearings, sr, sb, pose_var, e.landmark_sigma_min,
        )  # fmt: skip
        self._lm_info[ids] = info
        self._lm_vec[ids] = vec

    # --- laser weights ----------------------------------------------------------------------
    def _laser_weights(self, scan: LaserScan, partial: bool) -> Array:
        """Laser likelihood of every particle: Nav2's likelihood field, or with ``partial`` (and
        ``partial_laser``) the tempered product-form field ``exp(power (log p - max log p))``
        (:meth:`AMCL.log_likelihood_field`)."""
        e = self.ecfg
        if not (partial and e.partial_laser):
            return self.measurement_weights(self.particles, scan)
        ranges, angles = self._beams(scan, e.partial_laser_beams, self._beam_offset)
        if ranges.size == 0:
            return np.ones(len(self.particles))
        off = e.partial_laser_offset * self.grid.resolution
        ll = self.log_likelihood_field(
            self.particles, ranges, angles, e.partial_laser_sigma, off, e.partial_laser_signed
        )
        return np.exp(e.partial_laser_power * (ll - ll.max()))

    def _laser_loglik(self, particles: Array, scan: LaserScan) -> Array:
        """Unnormalized log laser likelihood of the partial modes: ``power log p`` (product-form
        field), or the log of Nav2's field without ``partial_laser``. Returns (N,)."""
        e = self.ecfg
        if not e.partial_laser:
            return np.log(self.measurement_weights(particles, scan))
        ranges, angles = self._beams(scan, e.partial_laser_beams, self._beam_offset)
        if ranges.size == 0:
            return np.zeros(len(particles))
        off = e.partial_laser_offset * self.grid.resolution
        ll = self.log_likelihood_field(
            particles, ranges, angles, e.partial_laser_sigma, off, e.partial_laser_signed
        )
        return e.partial_laser_power * ll

    def _refined(self, loglik: Callable[[Array], Array], lp: Array) -> None:
        """Replace the (predicted) particles by :func:`refine_proposal`'s weighted set for the
        partial-mode log likelihood ``loglik`` (``lp``: its values on the particles) and
        resample it (improvement)."""
        e = self.ecfg
        if not np.all(np.isfinite(lp)):
            lp = np.where(np.isfinite(lp), lp, -np.inf)
            if not np.isfinite(lp).any():
                return
        x, w = refine_proposal(
            self.particles, lp, loglik, e.refine_fraction, e.refine_inflate,
            np.asarray(e.refine_floor), self.rng,
        )  # fmt: skip
        self.particles = x
        self.weights = w
        self.resample(w)

    # --- partial tracking (improvement, track_partial) ---------------------------------------
    def _associate(self, pose: Array) -> tuple[np.ndarray, np.ndarray]:
        """Detections (base_link) -> landmark ids by proximity to where ``pose`` predicts the
        landmarks; returns (detection indices, landmark ids) within ``track_gate``."""
        det = self.observer.last_detections
        return associate(det.points, self.observer.landmarks, pose, self.ecfg.track_gate)

    def _tracked_fix(self, odom_pose: Array) -> ReflectorFix | None:
        """Two or more reflectors associated by the estimate: a pose from their ranges and
        bearings (Gauss-Newton from the estimate), used like a trilateration fix."""
        pose = self.pose_at(odom_pose)
        di, li = self._associate(pose)
        if len(di) < 2:
            self.track_status = "too_few_associated"
            return None
        fix, self.track_status = tracked_fix(
            pose, di, li, self.observer, self.tracking_landmarks, self.landmark_sd, self.ecfg
        )
        return fix

    def _partial_update(
        self, odom_pose: Array, scan: LaserScan, force: bool
    ) -> PoseEstimate | None:
        """Improvement for fewer than two usable reflectors, every scan (no update thresholds).

        - one reflector, associated with its landmark through the current estimate: its range
          and bearing weight the particles together with the sharp laser likelihood
          (:meth:`_laser_weights`); ``partial_proposal_fraction`` of the particles are first
          drawn on the poses the reflector allows (:func:`partial_proposal`);
        - none, while the filter is converged (position SD < ``partial_converged_sd``): the
          sharp laser likelihood alone, with that fraction of the particles' headings spread
          by ``partial_heading_sigma`` and positions by ``partial_position_sigma`` (an odometry
          heading jump must be covered);
        - otherwise None: the caller runs plain AMCL (Algorithm 1, lines 4-10).

        No fix, no injection."""
        e = self.ecfg
        prior = self.pose_at(odom_pose)  # before predict: moved by odometry
        di, li = self._associate(prior)
        if len(di) == 0:
            est = self._current(updated=False)
            if float(np.trace(est.cov[:2, :2])) > e.partial_converged_sd**2:
                return None
        self.predict(odom_pose)
        det = self.observer.last_detections
        L = self.tracking_landmarks[li]
        if len(di):
            r0, b0 = det.ranges[di[0]], det.bearings[di[0]]
            partial_proposal(self.particles, prior, e, self.rng, L[0], r0, b0)
        else:
            partial_proposal(self.particles, prior, e, self.rng)
        r_obs, b_obs = det.ranges[di], det.bearings[di]

        def reflector_lik(P: Array) -> Array:  # (N,), 1 without reflectors
            return reflector_likelihood(
                P, L, r_obs, b_obs, e.track_sigma_range, e.track_sigma_bearing
            )

        if not self._weigh_partial(scan, reflector_lik):
            return None
        est = self._finish_update(odom_pose)
        src = "enhanced-partial" if len(di) else "enhanced-laser"
        return PoseEstimate(est.pose, est.cov, est.n_particles, True, src)

    def _weigh_partial(self, scan: LaserScan, reflector_lik: Callable[[Array], Array]) -> bool:
        """Weight (sharp laser times ``reflector_lik``) and resample the predicted particles of
        :meth:`_partial_update`, by the two-stage proposal with ``refine``; False if no
        particle carries weight."""
        if self.ecfg.refine:
            lp = self._laser_loglik(self.particles, scan)
            self._apply_weights(np.exp(lp - lp.max()))  # w_slow / w_fast bookkeeping
            self._refined(
                lambda P: self._laser_loglik(P, scan) + np.log(reflector_lik(P) + 1e-12),
                lp + np.log(reflector_lik(self.particles) + 1e-12),
            )
            return True
        ll = reflector_lik(self.particles)
        p = self._laser_weights(scan, partial=True)
        self._apply_weights(p)
        w = self.weights * (ll + 1e-12)
        total = float(w.sum())
        if not np.isfinite(total) or total <= 0:
            return False
        self.weights = w / total
        self.resample(self.weights)
        return True

    # --- Algorithm 1 -------------------------------------------------------------------------
    def update(self, odom_pose: Array, scan: LaserScan, force: bool = False) -> PoseEstimate:
        """One cycle of Algorithm 1: the reflector fix of ``scan`` (or partial tracking), then
        the fused update (:meth:`_fuse`), else plain AMCL (lines 4-10)."""
        if self.particles.shape[0] == 0:
            raise InvalidInputError("set an initial pose or call global_localization() first")
        odom_pose = finite_pose(odom_pose, "odometry pose")
        check_scan(scan)
        if self.plain_amcl:  # fallback_to_amcl on a map with < 3 reflectors
            self.last_fix = None
            return self._plain_update(odom_pose, scan, force)
        fix, tracked, est = self._observe(odom_pose, scan, force)
        if est is not None:
            return est
        if fix is None:  # Algorithm 1 lines 4-10: original AMCL
            return self._plain_update(odom_pose, scan, force)
        return self._fuse(np.asarray(odom_pose, float).reshape(3), scan, force, fix, tracked)

    def _plain_update(self, odom_pose: Array, scan: LaserScan, force: bool) -> PoseEstimate:
        """Algorithm 1 lines 4-10: an AMCL update, its estimate labelled "amcl"."""
        est = AMCL.update(self, odom_pose, scan, force)
        return PoseEstimate(est.pose, est.cov, est.n_particles, est.updated, "amcl")

    def _observe(
        self, odom_pose: Array, scan: LaserScan, force: bool
    ) -> tuple[ReflectorFix | None, bool, PoseEstimate | None]:
        """Line 2: the reflector fix of ``scan``; with fewer than three reflectors (and
        ``track_partial``) a tracked fix, else the partial update's estimate. Returns (fix,
        whether it is tracked, the estimate if the partial update already made one)."""
        self._scans_seen += 1
        self._beam_offset = self._scans_seen * self.ecfg.partial_laser_rotate
        fix = self.observer.observe(scan)
        self.last_fix = fix
        tracked = False
        if fix is None and self.ecfg.track_partial and self.particles.shape[0] > 0:
            odom_arr = np.asarray(odom_pose, float).reshape(3)
            if len(self.observer.last_detections) > 0:
                fix = self._tracked_fix(odom_arr)
                tracked = fix is not None
            if fix is None:
                est = self._partial_update(odom_arr, scan, force)
                if est is not None:
                    return None, False, est
        return fix, tracked, None

    def _fuse(
        self, odom_pose: Array, scan: LaserScan, force: bool, fix: ReflectorFix, tracked: bool
    ) -> PoseEstimate:
        """Lines 12-26: predict, weigh by eq. 3-6, resample, inject by eq. 7-8."""
        e = self.ecfg
        if not (force or e.update_when_stationary or self._should_update(odom_pose)):
            return self._current(updated=False)
        gate = self._gate(fix)
        if gate == "outlier":
            self.last_fix = None
            est = AMCL.update(self, odom_pose, scan, force=True)
            return PoseEstimate(est.pose, est.cov, est.n_particles, est.updated, "amcl")
        self.predict(odom_pose)  # line 12
        if gate == "reseed":
            self._reseed(fix)
        tracked, cov, lm_fix = self._fix_terms(fix, tracked, gate)
        mu = fix.pose
        frac = e.proposal_fraction * (e.track_inject_scale if tracked else 1.0)
        if frac > 0:  # mixture proposal: some predicted particles drawn at mu_G
            mixture_proposal(self.particles, frac, mu, cov, self.rng)
        sharp = tracked or (e.sharp_laser_with_fix and e.partial_laser)
        refine = sharp and e.refine and e.fusion == "product"
        p, lasl = self._fix_laser(scan, sharp, refine)
        s, d = self._fused_weights(p, fix, mu, cov, lm_fix)
        if refine:  # improvement: two-stage proposal (see _partial_update)
            assert lasl is not None  # _laser_loglik on these particles (computed above)
            self._refine_fused(scan, fix, mu, cov, lm_fix, s, d, lasl)
        else:
            self.resample(self.weights)  # ParticleGeneration(omega_new)
        self._inject(mu, cov, tracked)  # lines 20-26
        est = self._finish_update(odom_pose)
        return PoseEstimate(est.pose, est.cov, est.n_particles, True, "enhanced")

    def _gate(self, fix: ReflectorFix) -> str:
        """``"ok"``, ``"outlier"`` or ``"reseed"`` for a fix (improvement). A fix farther than
        ``kidnap_distance`` from every particle is not fused (a wrong identification must not
        drag the cloud away); ``kidnap_fixes`` consecutive such fixes from at least
        ``kidnap_min_reflectors`` reflectors mean the robot was carried off: re-seed the cloud
        at ``N(mu_G, Sigma)`` (eq. 8 alone cannot reach a cloud that is lost)."""
        e = self.ecfg
        if e.kidnap_fixes <= 0:
            return "ok"
        dxy = np.hypot(*(self.particles[:, :2] - fix.pose[:2]).T)
        if float(dxy.min()) <= e.kidnap_distance:
            self._far_fixes = 0
            return "ok"
        if fix.trilateration.n >= e.kidnap_min_reflectors:
            self._far_fixes += 1
        if self._far_fixes >= e.kidnap_fixes:
            self._far_fixes = 0
            return "reseed"
        return "outlier"

    def _reseed(self, fix: ReflectorFix) -> None:
        """Kidnapped (:meth:`_gate`): the cloud re-drawn at ``N(mu_G, Sigma + floor)``."""
        e = self.ecfg
        self.particles = self.rng.multivariate_normal(
            fix.pose, fix.trilateration.cov + np.diag(e.position_cov_floor), len(self.particles)
        )
        self.particles[:, 2] = wrap(self.particles[:, 2])
        self.weights = np.full(len(self.particles), 1.0 / len(self.particles))
        self.kidnap_resets += 1

    def _fix_terms(
        self, fix: ReflectorFix, tracked: bool, gate: str
    ) -> tuple[bool, Array | None, Array]:
        """Whether the fix is weak (tracked, or 3+ reflectors nearly in a line: a corridor,
        lateral SD up to ~60 mm; the sharp laser, the two-stage proposal and the scaled-down
        injection of the tracked case then apply), eq. 3's metric (:data:`POSITION_METRICS`)
        and the landmarks of the fix; learns the landmarks from a redundant fix."""
        e = self.ecfg
        fix_sd = float(np.sqrt(np.linalg.eigvalsh(fix.trilateration.cov[:2, :2]).max()))
        weak = e.track_partial and fix_sd > e.weak_fix_sd
        if (
            e.landmark_refine
            and not (tracked or weak)
            and gate == "ok"
            and fix.trilateration.n >= e.landmark_min_reflectors
        ):
            self._learn_landmarks(fix)
        lm_fix = (self.tracking_landmarks if tracked else self.observer.landmarks)[fix.ids]
        tracked = tracked or weak
        self.last_fix_weak = tracked
        cov = POSITION_METRICS[e.position_metric](fix, e, tracked)
        return tracked, cov, lm_fix

    def _fix_laser(self, scan: LaserScan, sharp: bool, refine: bool) -> tuple[Array, Array | None]:
        """The laser weight ``p`` (N,) of eq. 5 (the sharp field if ``sharp``) and, for the
        two-stage proposal (``refine``), its log likelihood (reused by the second stage)."""
        if refine and self.ecfg.partial_laser:
            lasl = self._laser_loglik(self.particles, scan)
            return np.exp(lasl - lasl.max()), lasl
        p = self._laser_weights(scan, partial=sharp)
        # with refine (so partial_laser off) p is Nav2's field: _laser_loglik = log p
        with np.errstate(divide="ignore"):
            lasl = np.log(p) if refine else None
        return p, lasl

    def _fused_weights(
        self, p: Array, fix: ReflectorFix, mu: Array, cov: Array | None, lm_fix: Array
    ) -> tuple[Array, Array]:
        """Eq. 5, 3, 4 and 6 (lines 13-19): sets the normalized ``omega_new`` as the weights
        (AMCL's ``w_slow`` / ``w_fast`` kept on ``p``); returns ``s`` and ``d``."""
        e = self.ecfg
        omega = self.weights * p  # eq. 5
        omega = omega / max(float(omega.sum()), 1e-300)
        self._apply_weights(p)  # keeps w_slow / w_fast bookkeeping of AMCL
        d = position_weight(self.particles, mu, cov)  # eq. 3 (line 14)
        s = orientation_weight(
            self.particles, lm_fix, fix.bearings, e.bearing_sigma
        )  # eq. 4 (line 15)
        w_new = FUSIONS[e.fusion](s, omega, d, e)  # eq. 6 (line 16)
        total = float(w_new.sum())
        if not np.isfinite(total) or total <= 0:
            w_new = np.full(len(w_new), 1.0 / len(w_new))
        else:
            w_new = w_new / total  # line 19
        self.weights = w_new
        return s, d

    def _refine_fused(
        self,
        scan: LaserScan,
        fix: ReflectorFix,
        mu: Array,
        cov: Array | None,
        lm_fix: Array,
        s: Array,
        d: Array,
        lasl: Array,
    ) -> None:
        """The two-stage proposal (:meth:`_refined`) on eq. 3 x eq. 4 x the laser."""
        e = self.ecfg
        b_fix = fix.bearings
        floor = e.position_weight_floor * EQ3_NORM

        def tracked_loglik(P: Array) -> Array:
            s_ = orientation_weight(P, lm_fix, b_fix, e.bearing_sigma)
            d_ = position_weight(P, mu, cov)
            return np.log(s_ + 1e-300) + self._laser_loglik(P, scan) + np.log(d_ + floor)

        self._refined(tracked_loglik, np.log(s + 1e-300) + np.log(d + floor) + lasl)

    def _inject(self, mu: Array, cov: Array | None, tracked: bool) -> None:
        """Lines 20-26: each particle replaced with probability ``d`` (eq. 8, on eq. 3 as
        printed: particles within ~1.9 m / rad of ``mu_G``) by a new one (eq. 7,
        :data:`INJECTIONS`)."""
        e = self.ecfg
        scale = e.track_inject_scale if tracked else None
        prob = injection_probability(self.particles, mu, e.injection_threshold, scale)
        inject = self.rng.uniform(size=len(prob)) <= prob
        k = int(inject.sum())
        if k:
            q = self.rng.standard_normal((k, 3))
            new = INJECTIONS[e.injection](q, mu, cov, e)
            new[:, 2] = wrap(new[:, 2])
            self.particles[inject] = new
