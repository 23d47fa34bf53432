"""Reflector-enhanced AMCL: paper 001 Algorithm 1, eq. 3-8, on top of :class:`AMCL`.

Per scan (Algorithm 1):

1. ``R, M_bar = LaserReflectorIdentification(z_t, u_t, M)``: detect reflectors, identify them by
   triangle matching, trilaterate ``mu_G`` (eq. 1-2) -> :class:`ReflectorObserver`.
2. Fewer than three identified (``M_bar`` empty): plain AMCL (lines 4-10).
3. Otherwise (lines 12-26): motion model; laser weight ``omega_t = omega_{t-1} p(z_t | x_t)``
   (eq. 5, normalized); position weight ``d`` (eq. 3); orientation weight ``s`` (eq. 4);
   fused ``omega_new = alpha s omega + beta d`` (eq. 6, alpha = 154, beta = 1), normalized;
   resampling on ``omega_new`` (``ParticleGeneration``); then each particle is replaced, with
   probability ``d`` if ``d > 0.01`` (eq. 8), by a new particle ``lambda Q + mu_G`` (eq. 7).

Interpretations (the paper leaves them open):

- eq. 3 uses ``(2 pi)^{-3/2} exp(-1/2 e^T e)`` with ``e = x - mu_G`` in m and rad (identity
  covariance). ``position_metric="trilateration"`` (the default, our improvement) whitens ``e``
  with the trilateration covariance (plus a floor), so the weight reflects how well ``mu_G``
  is actually known; the normalizer stays ``(2 pi)^{-3/2}`` so eq. 8's 0.01 threshold keeps its
  meaning (``e^T Sigma^-1 e < 3.7``).
- eq. 4 averages, over the identified reflectors, a Gaussian of the difference between the
  observed bearing ``phi_i`` and the bearing ``mu`` the particle predicts for that landmark,
  with ``sigma = bearing_sigma``.
- eq. 7 with ``lambda = 1`` (paper) spreads new particles by 1 m / 1 rad; the default
  ``injection="trilateration"`` draws them from ``N(mu_G, Sigma)`` instead.
- ``fusion="product"`` (default, our improvement): eq. 6's sum lets the ``alpha s omega`` term
  outweigh ``beta d`` by two orders of magnitude, so the trilateration barely sharpens the
  cloud; the product ``s omega d`` is the Bayes posterior of the three independent cues.
  ``fusion="paper"`` is eq. 6 as printed.
- eq. 8's probability always uses eq. 3 as printed (identity metric), so particles up to
  ~1.9 m from ``mu_G`` can trigger an injection even with the sharper eq. 3 weight.
- gating and kidnapping (improvement): a fix farther than ``kidnap_distance`` from every
  particle is not fused; ``kidnap_fixes`` consecutive such fixes (from at least
  ``kidnap_min_reflectors`` reflectors) re-seed the cloud at ``N(mu_G, Sigma)``.
- partial tracking (improvement): with fewer than three identified reflectors, the ones
  still detected are associated with landmarks through the current estimate (gate
  ``track_gate``). Two or more give a pose by Gauss-Newton on their ranges and bearings,
  used as ``mu_G``; a single one weights the particles by its range/bearing likelihood.
- occluded reflectors (improvement): a reflector cut by something in front of it (a person
  at its edge, :func:`~mmpa.localization.reflectors.detect_reflectors`'s ``occluded``) is
  not used; its fitted center is off by up to the radius (17-58 mm measured in the twin).
- sharp laser with < 3 reflectors (improvement): Nav2's likelihood field ``1 + sum pz^3``
  with ``sigma_hit = 0.2`` hardly tells poses 5 cm / 20 mrad apart, and the twin's odometry
  jumps by ~56 mm / 56 mrad (SD) each time it closes a 25 cm segment. While a fix is
  tracked from 2 reflectors, or only 1 or none is seen, the laser weight is the tempered
  product-form field ``exp(partial_laser_power * log p)``
  (:meth:`AMCL.log_likelihood_field`, bilinear, ``partial_laser_beams`` beams) on the SIGNED
  distance to the obstacle surfaces (``partial_laser_signed``, the cell edges: an endpoint
  behind a surface is penalized like one in front; the unsigned field is 0 inside obstacles,
  so long beams cost nothing and the fit leans away from the walls in view, 2-5 mm measured
  at the truth, which the 2-reflector fix could not outweigh); with one
  reflector part of the particles are drawn on the poses its range and bearing allow
  (heading spread ``partial_heading_sigma``), with none (and a converged cloud) around the
  odometry prediction, so that an odometry heading jump is covered and the laser picks the
  heading. Tracked fixes draw only ``track_inject_scale`` of the proposal and injection.
- mixture proposal (improvement): before weighting, ``proposal_fraction`` of the predicted
  particles are redrawn from ``N(mu_G, Sigma)``, so that a cloud spread by the motion model
  (Nav2's alphas are 0.2) still holds particles where the fix is; without it the sharp
  product weight lands on a handful of particles.
- two-stage proposal (improvement, ``refine``): with fewer than three reflectors (and at weak
  fixes, below) the motion model spreads the cloud by ~27 mm / 27 mrad per scan (Nav2's
  alphas) while the sharp laser pins the pose to a few mm / mrad, so only a handful of
  predicted particles carry weight and the estimate jumps by the particle spacing (the
  ``reflector-dropout`` experiment's p95 spikes). :func:`refine_proposal` draws
  ``refine_fraction`` of the particles from a Gaussian fitted to the first stage's posterior
  (SD x ``refine_inflate``) and weights both sets by deterministic-mixture importance sampling
  against a Gaussian fit of the predicted cloud.
- weak fixes (improvement): a 3+ reflector fix whose position SD exceeds ``weak_fix_sd``
  (reflectors nearly in a line, as along the corridor: lateral SD 20-60 mm, errors up to
  115 mm measured) is fused like a tracked one: sharp laser (the corridor walls pin the lateral
  position), two-stage proposal, injection scaled by ``track_inject_scale``. With Nav2's
  laser field the estimate followed such fixes (113 mm lateral error in the corridor).
- landmark refinement (improvement, ``landmark_refine``): the map stores SURVEYED reflector
  positions (the twin: N(0, 10 mm) per axis under ``realistic``, 2 mm under ``reference``). At
  every redundant fix (``landmark_min_reflectors``
  or more, not weak) each identified reflector's position seen from ``mu_G`` minus its map
  position observes that landmark's offset from the map's consensus (:func:`landmark_update`,
  a per-landmark Kalman filter with prior ``N(0, landmark_map_sigma^2 I)``). The refined
  positions are used only where one or two reflectors carry the pose (tracked fixes, the
  one-reflector update), where a 4 mm landmark error moves the estimate by ~3 mm; the
  trilateration of redundant fixes keeps the map's positions, so nothing feeds back.
- ``update_when_stationary``: reflector fixes also update the filter while the base stands
  still (Nav2 waits for ``update_min_d``); the motion model then adds no noise, and the
  injected particles keep the cloud from collapsing.
- honest fix (improvement, ``ObserverConfig.honest_fix``, error model v2): ``mu_G`` comes
  from :func:`~mmpa.localization.trilateration.trilaterate_bias` in the scanner's frame, with
  a range bias common to all reflectors as a fourth unknown (the range walk of the scanner on
  the tape, about -10 mm; a running estimate, :func:`update_bias`, is the prior of every fix
  and corrects every detection) and each landmark's survey error (``survey_sigma``, 10 mm)
  and per-reflector walk (``range_bias_scatter``) in the weights, so that eq. 3's covariance
  is how well ``mu_G`` is known (5 mm per axis at site 1, where the beam noise alone said
  2.6 mm). Realistic twin, parked at site 1, seeds 0-2: the running bias -9.0 / -7.7 /
  -9.3 mm against -7.6 / -9.6 / -9.1 mm measured from the truth. Tracked (1-2 reflector)
  fixes get the same terms with the refined landmarks' SD (``track_honest``).
- sharp laser at redundant fixes (improvement, ``sharp_laser_with_fix``): the scan weighs in
  with its tempered product-form field (and the two-stage proposal) also while 3+ reflectors
  are seen, so that the scan and the honest fix are fused by their uncertainties; with
  Nav2's field the estimate was the fix. The subset of beams moves from scan to scan
  (``partial_laser_rotate``) so that a standing robot does not weigh the same wall points'
  map errors again and again. ``reflector-dropout`` (realistic, seeds 0-2, 5 runs each),
  mean error with all reflectors in view: 12.95 / 5.91 / 7.64 mm -> 2.70 / 2.50 / 3.98 mm
  (mount calibrated), during the dropout 8.01 / 5.41 / 4.16 -> 3.66 / 3.36 / 3.33 mm.
- the lidar mount is what the localizer is given: the experiments calibrate it by a turn on
  the spot (:mod:`mmpa.localization.calibration`, :mod:`mmpa.navigation.mount_calibration`).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field

from mmpa.core.errors import InvalidInputError
from mmpa.core.geometry import Array
from mmpa.localization.amcl import (
    AMCL,
    AMCLConfig,
    PoseEstimate,
    _wrap,
    check_scan,
    finite_pose,
)
from mmpa.localization.reflectors import (
    DetectionConfig,
    IdentifyConfig,
    ReflectorDetections,
    TriangleLibrary,
    detect_reflectors,
    identify_reflectors,
)
from mmpa.localization.trilateration import (
    BiasedTrilateration,
    TrilaterationResult,
    trilaterate,
    trilaterate_bias,
)
from mmpa.maps.occupancy import OccupancyGrid
from mmpa.robot.interfaces import LaserScan

__all__ = [
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
]

_EQ3_NORM = (2 * np.pi) ** -1.5


class ObserverConfig(BaseModel):
    """Detection, identification and trilateration settings."""

    model_config = ConfigDict(extra="forbid")

    detection: DetectionConfig = DetectionConfig()
    identify: IdentifyConfig = IdentifyConfig()
    range_sigma_beam: float = Field(0.015, gt=0)  # m, lidar range noise per beam
    range_sigma_floor: float = Field(0.002, ge=0)  # m, map error (the range fit is unbiased)
    # rad, bearing of one beam's edge (about the angular step, 0.25 deg); measured in the twin:
    # bearing SD 0.5-0.6 mrad at 8-11 beams per reflector, 1.5-1.7 mrad at 4-5 beams; in
    # base_link (10 % less with the unbiased range fit: normalized RMS 0.39 at 0.0044)
    bearing_sigma_beam: float = Field(0.0035, gt=0)
    bearing_sigma_floor: float = Field(0.0005, ge=0)  # rad
    # rad, added to the bearing SD of redundant (3+ reflector) fixes only: the hit/miss edges
    # put a reflector's bearing within an interval of up to one beam step, an error (SD
    # step/6 = 0.73 mrad) that stays put while the robot stands still, so it does not average
    # out over the scans the filter fuses at rest; ranges (unbiased fit) do. Weighting bearings
    # down there lets the position follow the ranges: parked near site 1, 25 scans, 8 poses,
    # seeds 0/1: 1.54/1.50 mm -> 1.22/1.11 mm. Tracked 2-reflector fixes need their bearings.
    bearing_sigma_static: float = Field(0.001, ge=0)
    # rad: the lidar's angular step the bearing terms above were measured at (the twin's
    # 0.25 deg). A reflector's bearing is the middle of its first and last hit beams, each edge
    # uniform within one step ``a``: SD ``a / sqrt(24)`` however many beams hit (synthetic
    # scans: 0.89 mrad at 0.25 deg for 4-10 beams, 3.2-3.6 mrad at 1 deg for 1-2 beams). With
    # ``scale_with_scan`` the bearing SD is at least ``bearing_sigma_floor + sqrt((a^2 -
    # reference^2) / 24)``: nothing changes at the reference step (the twin) or finer, and a
    # coarse lidar's near reflectors (many beams, small ``1/sqrt(k)`` term) are not trusted
    # beyond its quantization. Scaling the SDs by ``a / reference`` instead was tried: 1 deg
    # fixes got worse (5.91 -> 8.23 mm mean: bearings trusted too little, ranges too much;
    # the ``1/sqrt(k)`` terms already grow as fewer beams hit). The range SD follows the beams
    # per reflector the same way (measured 15.5 / 11.2 mm at 1 / 2 beams, model 17 / 12.6).
    bearing_reference_step: float = Field(float(np.deg2rad(0.25)), gt=0)
    scale_with_scan: bool = True
    outlier_sigmas: float = Field(3.5, gt=0)  # drop reflectors with larger normalized residual
    # improvement: mu_G by a joint Gauss-Newton on ranges AND bearings weighted by the SDs
    # above (:func:`trilaterate` ``refine_heading``); False: eq. 1 (least squares on the
    # ranges) then eq. 2 (mean heading) as printed
    joint_refine: bool = True
    min_reflectors: int = Field(3, ge=3)
    # improvement: reflectors cut by something in front of them (a person) are not used; their
    # fitted centers are off by up to the radius (measured in the twin: 17-58 mm at 1-4 beams)
    drop_occluded: bool = True
    # improvement, honest fix (:func:`~mmpa.localization.trilateration.trilaterate_bias`, in
    # the scanner's frame, with ``joint_refine``): every reflector's range variance gets
    # ``survey_sigma^2 + range_bias_scatter^2`` and its bearing variance ``(survey_sigma /
    # r)^2`` on top of :meth:`ReflectorObserver.sigmas`, so that the fix's covariance (eq. 3's
    # metric) says how well ``mu_G`` is known against a map whose reflectors were surveyed to
    # ``survey_sigma`` (paper 001 marks them on a Gmapping map: cm level) and a scanner whose
    # range walk differs from reflector to reflector by ``range_bias_scatter``. 0 and 0 with
    # ``range_bias`` off: the fix of before (beam noise and floors only).
    survey_sigma: float = Field(0.010, ge=0)  # m per axis, reflector map vs the world
    range_bias_scatter: float = Field(0.005, ge=0)  # m, per-reflector part of the range walk
    # improvement: a range bias common to all reflectors (range walk of the scanner on the
    # tape: one unknown) is a fourth unknown of every fix, under the prior of a running
    # estimate ``N(b, 1 / info)`` that starts at ``N(range_bias_prior, range_bias_sigma^2)``
    # and is updated by every fix of ``range_bias_min_reflectors`` or more reflectors
    # (:func:`update_bias`; information capped at ``1 / range_bias_sigma_min^2``: what a
    # parked robot sees again and again is not new). Detections are corrected by it before
    # any use (tracking with 1-2 reflectors too).
    range_bias: bool = True
    range_bias_prior: float = 0.0  # m (no calibration assumed)
    range_bias_sigma: float = Field(0.02, gt=0)  # m, prior SD
    range_bias_sigma_min: float = Field(0.002, gt=0)  # m, floor of the running estimate's SD
    range_bias_min_reflectors: int = Field(4, ge=3)
    range_bias_gate: float = Field(3.0, gt=0)  # SDs: an estimate this far off is not learned

    @property
    def honest_fix(self) -> bool:
        """Whether fixes come from :func:`trilaterate_bias` (see ``survey_sigma``)."""
        return self.joint_refine and (
            self.range_bias or self.survey_sigma > 0 or self.range_bias_scatter > 0
        )


@dataclass(frozen=True)
class ReflectorFix:
    """Identified reflectors (in ``base_link``) and the trilateration ``mu_G`` (eq. 1-2)."""

    ids: np.ndarray  # (n,) landmark ids
    ranges: Array  # (n,) m from base_link
    bearings: Array  # (n,) rad in base_link
    trilateration: TrilaterationResult
    detected: int  # reflectors detected (identified or not)
    beams: np.ndarray | None = None  # (n,) returns per identified reflector
    bias_fit: BiasedTrilateration | None = None  # the honest fix (scanner frame), if any

    @property
    def pose(self) -> Array:
        return self.trilateration.pose


def sensor_to_base(pose: Array, cov: Array, mount: Array) -> tuple[Array, Array]:
    """The ``base_link`` pose ``X`` (3,) and its covariance (3, 3) from the pose ``S`` (3,) of
    a sensor mounted at ``mount`` = ``[m_x, m_y, m_theta]`` in ``base_link`` (``S = X (+)
    mount``): ``X_theta = S_theta - m_theta``, ``X_xy = S_xy - R(X_theta) m_xy``; covariance
    ``J cov J^T`` with ``J = [[1, 0, -dR/dtheta m_xy], [0, 1, .], [0, 0, 1]]``. m, rad."""
    S = np.asarray(pose, float).reshape(3)
    mx, my, mt = np.asarray(mount, float).reshape(3)
    th = float(_wrap(S[2] - mt))
    c, s_ = np.cos(th), np.sin(th)
    X = np.array([S[0] - (c * mx - s_ * my), S[1] - (s_ * mx + c * my), th])
    J = np.eye(3)
    J[0, 2] = s_ * mx + c * my
    J[1, 2] = -(c * mx - s_ * my)
    return X, J @ np.asarray(cov, float) @ J.T


def update_bias(
    mean: float,
    info: float,
    post_mean: float,
    info_meas: float,
    sigma_min: float,
    gate: float,
) -> tuple[float, float, bool]:
    """One step of the running common range bias estimate (improvement, ``range_bias``).

    The estimate ``N(mean, 1 / info)`` was the prior of a fix that returned the posterior mean
    ``post_mean`` and carried ``info_meas`` (1/m^2) on the bias by itself
    (:class:`~mmpa.localization.trilateration.BiasedTrilateration`). The fix's own estimate is
    ``b_meas = ((info + info_meas) post_mean - info mean) / info_meas``; if its innovation
    ``|b_meas - mean|`` exceeds ``gate sqrt(1 / info + 1 / info_meas)`` (a wrong
    identification, an occluded edge) nothing is learned. Otherwise the posterior becomes the
    estimate, its information capped at ``1 / sigma_min^2`` (the errors of one place, the
    survey and the per-reflector walk, repeat scan after scan: they must not make the bias
    certain). Returns ``(mean, info, learned)`` in m and 1/m^2."""
    if info_meas <= 0 or not np.isfinite(post_mean):
        return mean, info, False
    post_info = info + info_meas
    b_meas = (post_info * post_mean - info * mean) / info_meas
    if abs(b_meas - mean) > gate * np.sqrt(1.0 / info + 1.0 / info_meas):
        return mean, info, False
    return float(post_mean), float(min(post_info, 1.0 / sigma_min**2)), True


class ReflectorObserver:
    """``LaserReflectorIdentification`` of Algorithm 1 plus eq. 1-2 with outlier rejection;
    with ``cfg.honest_fix`` the fix is :func:`trilaterate_bias` (common range bias, survey
    error) in the scanner's frame, mapped to ``base_link`` by :func:`sensor_to_base`."""

    def __init__(
        self, landmarks: Array, laser_pose: Array, cfg: ObserverConfig | None = None
    ) -> None:
        self.cfg = cfg or ObserverConfig()
        self.landmarks = np.asarray(landmarks, float).reshape(-1, 2)
        self.library = TriangleLibrary(self.landmarks)
        self.laser_pose = np.asarray(laser_pose, float).reshape(3)
        self.last_detections: ReflectorDetections = ReflectorDetections.empty()
        self.last_occluded = 0  # detections of the last scan dropped as occluded
        self.last_status = "none"
        #: running estimate of the common range bias (m) and its information (1/m^2)
        self.bias = self.cfg.range_bias_prior if self.cfg.range_bias else 0.0
        self.bias_info = 1.0 / self.cfg.range_bias_sigma**2
        self.bias_updates = 0
        #: rad, lower bound of bearing SDs for the last scan's step (``scale_with_scan``)
        self.step_floor = 0.0

    def sigmas(self, beams: np.ndarray, redundant: bool = False) -> tuple[Array, Array]:
        """Range and bearing SD (m, rad) of reflector centers fitted from ``beams`` (n,) hits:
        ``sigma_r = floor_r + sigma_r_beam / sqrt(k)``, ``sigma_phi = floor_phi +
        sigma_phi_beam / sqrt(k)`` (the fit averages ``k`` beams), plus
        ``bearing_sigma_static`` for a ``redundant`` (3+ reflector) fix; with
        ``scale_with_scan`` the bearing SD is at least :attr:`step_floor` (the last scan's
        angular step, if coarser than ``bearing_reference_step``)."""
        c = self.cfg
        k = np.sqrt(np.maximum(np.asarray(beams, float), 1.0))
        static = c.bearing_sigma_static if redundant else 0.0
        sb = np.maximum(c.bearing_sigma_floor + static + c.bearing_sigma_beam / k, self.step_floor)
        return c.range_sigma_floor + c.range_sigma_beam / k, sb

    def observe(self, scan: LaserScan) -> ReflectorFix | None:
        """The fix of this scan, or None if fewer than ``min_reflectors`` are identified."""
        c = self.cfg
        if c.scale_with_scan and np.isfinite(scan.angle_increment):
            a, a0 = abs(float(scan.angle_increment)), c.bearing_reference_step
            self.step_floor = c.bearing_sigma_floor + float(np.sqrt(max(a * a - a0 * a0, 0) / 24))
        raw = detect_reflectors(scan, c.detection)  # sensor frame
        self.last_occluded = int(raw.cut.sum())
        if c.drop_occluded and self.last_occluded:
            raw = raw.select(~raw.cut)
        if c.range_bias and self.bias != 0.0:
            det = raw.range_corrected(self.bias).transformed(self.laser_pose)
        else:
            det = raw.transformed(self.laser_pose)
        self.last_detections = det
        if len(det) < c.min_reflectors:
            self.last_status = "too_few"
            return None
        ident = identify_reflectors(det.points, self.library, c.identify)
        self.last_status = ident.status
        keep = ident.ids >= 0
        while keep.sum() >= c.min_reflectors:
            k = np.flatnonzero(keep)
            L = self.landmarks[ident.ids[k]]
            sr, sb = self.sigmas(det.beams[k], redundant=True)
            bias_fit: BiasedTrilateration | None = None
            try:
                if c.honest_fix:
                    tri, bias_fit, used, res_r, res_b = self._honest_fix(raw.select(k), L, sr, sb)
                else:
                    used = det.select(k)
                    tri = trilaterate(
                        L, used.ranges, used.bearings, sr, sb, refine_heading=c.joint_refine
                    )
                    d = L - tri.pose[:2]
                    res_r = (np.linalg.norm(d, axis=1) - used.ranges) / sr
                    res_b = _wrap(np.arctan2(d[:, 1], d[:, 0]) - tri.pose[2] - used.bearings) / sb
            except (ValueError, np.linalg.LinAlgError):
                self.last_status = "degenerate"
                return None
            worst = int(np.argmax(np.maximum(np.abs(res_r), np.abs(res_b))))
            if max(abs(res_r[worst]), abs(res_b[worst])) <= c.outlier_sigmas:
                if bias_fit is not None and c.range_bias and len(k) >= c.range_bias_min_reflectors:
                    self.bias, self.bias_info, learned = update_bias(
                        self.bias,
                        self.bias_info,
                        bias_fit.bias,
                        bias_fit.bias_info_meas,
                        c.range_bias_sigma_min,
                        c.range_bias_gate,
                    )
                    self.bias_updates += int(learned)
                return ReflectorFix(
                    ident.ids[k], used.ranges, used.bearings, tri, len(det), used.beams, bias_fit
                )
            keep[k[worst]] = False
        self.last_status = "too_few_consistent"
        return None

    def _honest_fix(
        self, raw: ReflectorDetections, L: Array, sr: Array, sb: Array
    ) -> tuple[TrilaterationResult, BiasedTrilateration, ReflectorDetections, Array, Array]:
        """:func:`trilaterate_bias` on the sensor-frame detections ``raw`` of the landmarks
        ``L`` (n, 2) under the running bias (``cfg.honest_fix``): range SD ``sqrt(sr^2 +
        range_bias_scatter^2)``, bearing SD ``sb``, landmark SD ``survey_sigma``. Returns the
        ``base_link`` fix (:func:`sensor_to_base`), the scanner-frame fit, the detections in
        ``base_link`` corrected by the fitted bias, and the range and bearing residuals at the
        solution normalized by their total SDs (n,)."""
        c = self.cfg
        b0, bs = (self.bias, float(np.sqrt(1.0 / self.bias_info))) if c.range_bias else (0.0, 1e-6)
        s_r = np.sqrt(sr**2 + c.range_bias_scatter**2)
        bt = trilaterate_bias(L, raw.ranges, raw.bearings, s_r, sb, b0, bs, c.survey_sigma)
        d = L - bt.pose[:2]
        rho = np.linalg.norm(d, axis=1)
        res_r = (rho + bt.bias - raw.ranges) / np.sqrt(s_r**2 + c.survey_sigma**2)
        s_b = np.sqrt(sb**2 + (c.survey_sigma / rho) ** 2)
        res_b = _wrap(np.arctan2(d[:, 1], d[:, 0]) - bt.pose[2] - raw.bearings) / s_b
        X, cov = sensor_to_base(bt.pose, bt.pose_cov, self.laser_pose)
        tri = TrilaterationResult(X, cov, bt.rms, bt.n)
        used = raw.range_corrected(bt.bias).transformed(self.laser_pose)
        return tri, bt, used, res_r, res_b


class EnhancedConfig(BaseModel):
    """Algorithm 1 coefficients. Paper values: ``alpha=154``, ``beta=1``, ``lambda=1``,
    identity covariance in eq. 3 (``EnhancedConfig.paper()``)."""

    model_config = ConfigDict(extra="forbid")

    amcl: AMCLConfig = AMCLConfig()
    observer: ObserverConfig = ObserverConfig()
    alpha: float = Field(154.0, ge=0)  # eq. 6
    beta: float = Field(1.0, ge=0)  # eq. 6
    bearing_sigma: float = Field(0.01, gt=0)  # rad, eq. 4 (sigma of the observation angle)
    position_metric: Literal["identity", "trilateration"] = "trilateration"  # eq. 3
    position_cov_floor: tuple[float, float, float] = (0.002**2, 0.002**2, 0.001**2)
    injection: Literal["paper", "trilateration"] = "trilateration"  # eq. 7
    injection_lambda: float = Field(1.0, gt=0)  # eq. 7 (paper: 1)
    injection_threshold: float = Field(0.01, ge=0)  # eq. 8
    update_when_stationary: bool = True
    fusion: Literal["paper", "product"] = "product"  # eq. 6 as printed, or Bayes product
    position_weight_floor: float = Field(1e-4, ge=0)  # product fusion: keeps far particles alive
    kidnap_distance: float = Field(0.5, gt=0)  # m, fix farther than this from every particle
    kidnap_fixes: int = Field(3, ge=0)  # consecutive such fixes re-seed the cloud; 0 = off
    kidnap_min_reflectors: int = Field(4, ge=3)  # only redundant fixes count toward re-seeding
    proposal_fraction: float = Field(0.1, ge=0, le=1)  # improvement: mixture proposal at mu_G
    track_partial: bool = True  # use 1-2 reflectors (associated by the estimate) when < 3
    track_gate: float = Field(0.8, gt=0)  # m (odometry: ~56 mm / 56 mrad per 25 cm)
    track_pair_tol: float = Field(0.05, gt=0)  # m, detected vs map distance of tracked pairs
    track_max_turn: float = Field(0.3, gt=0)  # rad, largest heading change of a tracked fix
    track_sigma_range: float = Field(0.015, gt=0)  # m
    track_sigma_bearing: float = Field(0.01, gt=0)  # rad
    # proposal + injection at tracked (2-reflector) fixes scaled down: their mu_G is weaker
    # than a 3+ reflector fix, the laser and the position weight do the rest
    track_inject_scale: float = Field(0.3, ge=0, le=1)
    # m: a 3+ reflector fix whose position SD (largest axis) exceeds this is treated like a
    # tracked one (reflectors nearly in a line, e.g. along a corridor)
    weak_fix_sd: float = Field(0.01, gt=0)
    # tracked / weak fixes: factor on eq. 3's covariance. The sigma model treats per-reflector
    # errors as independent, but with 2 reflectors what is left of a landmark's survey error
    # (after ``landmark_refine``, ~1 mm) and the 5 cm map's pull on the sharp laser do not
    # average out. 4 (SD x 2) measured best of 0.25/1/4/6/16/100 with the old circle fit
    # (reflector-dropout, seed 1, 10 runs); with the unbiased fit and landmark refinement 1, 2
    # and 4 are within 0.1 of each other in during/before ratio (seeds 1 and 2). Realistic
    # profile, honest tracked covariance (``track_honest``), seeds 0-2 x 2 runs, mean / p95
    # during the dropout: 1: 4.30 / 7.26 mm, 4: 3.45 / 6.15 mm
    track_cov_scale: float = Field(4.0, gt=0)
    # improvement: with the observer's ``honest_fix``, a tracked fix's covariance carries the
    # landmarks' uncertainty (:meth:`EnhancedAMCL.landmark_sd`), the per-reflector range walk
    # and the common bias's remaining SD, like the redundant fixes' (then scaled by
    # ``track_cov_scale``)
    track_honest: bool = True
    # improvement: with < 3 reflectors the laser is weighted with the product-form likelihood
    # field (sharp; Nav2's sum of cubes hardly tells 5 cm apart) on more beams, tempered by
    # ``partial_laser_power`` because neighbouring beams are not independent
    partial_laser: bool = True
    # improvement: the sharp laser (``partial_laser``'s tempered product-form field) and the
    # two-stage proposal (``refine``) also at redundant (3+ reflector, not weak) fixes, so
    # that the scan and the reflectors are fused by their real uncertainties: with Nav2's
    # field (sigma_hit 0.2 m) the scan tells nothing at the mm level there and the estimate is
    # the reflector fix, survey error and range walk included
    sharp_laser_with_fix: bool = True
    partial_laser_sigma: float = Field(0.03, gt=0)  # m (the map's 5 cm cells)
    partial_laser_beams: int = Field(90, ge=2)
    partial_laser_offset: float = Field(0.5, ge=0, le=1)  # cells: surfaces at the cell edge
    # signed distance to that surface (an endpoint inside an obstacle is penalized too)
    partial_laser_signed: bool = True
    partial_laser_power: float = Field(0.6, gt=0, le=1)
    # improvement: the sharp laser's beam subset moves by ``partial_laser_rotate`` beams (mod
    # the subsampling step) from scan to scan, so that a robot standing still weighs other
    # points of the walls each scan: the map's errors at the points one fixed subset hits
    # (5 cm cells, the warp) are static and do not average over scans; other points' do.
    # 0: Nav2's fixed subset. Parked at site 1, 8 scans x 90 beams, seeds 0-2: fixed 1.6 /
    # 0.8 / 4.5 mm, moving 1.4 / 2.7 / 2.0 mm, all 720 even beams 1.6 / 1.7 / 1.5 mm.
    partial_laser_rotate: int = Field(7, ge=0)
    # one reflector: this fraction of the particles is drawn on the poses it allows (its range
    # and bearing, heading spread by ``partial_heading_sigma``), so that an odometry heading
    # jump (the twin's closes a segment with ~56 mrad SD) is still covered by particles
    partial_proposal_fraction: float = Field(0.3, ge=0, le=1)
    partial_heading_sigma: float = Field(0.15, gt=0)  # rad
    partial_position_sigma: float = Field(0.02, gt=0)  # m, no reflector: proposal spread
    partial_converged_sd: float = Field(0.1, gt=0)  # m, no reflector: laser-only tracking below
    # improvement (fewer than three reflectors): a second, Gaussian importance-sampling stage
    # around the first stage's posterior (:func:`refine_proposal`); the motion model spreads
    # the cloud by ~27 mm / 27 mrad per scan (Nav2 alphas) while the sharp laser pins it to a
    # few mm / mrad, so the first stage keeps only a handful of particles
    refine: bool = True
    refine_fraction: float = Field(0.8, gt=0, le=1)  # share of the particles drawn in stage 2
    refine_inflate: float = Field(2.0, ge=1)  # stage-2 proposal SD / stage-1 posterior SD
    refine_floor: tuple[float, float, float] = (0.002, 0.002, 0.001)  # m, m, rad: SD floor
    # improvement: the map holds SURVEYED reflector positions (error ~2 mm per axis). While a
    # redundant fix (>= ``landmark_min_reflectors``, not weak) is available, each landmark's
    # offset from the fix's consensus is estimated (:func:`landmark_update`) and used where
    # one or two reflectors carry the pose (tracked fixes, one-reflector updates): there a
    # 4 mm landmark error moves the estimate by ~3 mm (reflector-dropout, seed 1)
    landmark_refine: bool = True
    # m, prior SD of a surveyed position: the survey's accuracy (paper 001 marks the reflectors
    # on a Gmapping map: cm level). Realistic, seeds 0-2 x 2 dropout runs, mean / p95 during:
    # 2 mm 4.16 / 7.08 mm, 10 mm 3.88 / 6.66 mm
    landmark_map_sigma: float = Field(0.010, gt=0)
    landmark_min_reflectors: int = Field(4, ge=3)
    landmark_sigma_min: float = Field(0.0005, gt=0)  # m: posterior SD floor (static errors)
    # a map with fewer than three reflectors (a building mapped without them): False refuses
    # to start (InvalidInputError), True runs plain AMCL (Algorithm 1 lines 4-10) throughout
    fallback_to_amcl: bool = False

    @classmethod
    def paper(cls) -> EnhancedConfig:
        """Algorithm 1 exactly as printed (eq. 1-2 for ``mu_G``, identity eq. 3, lambda = 1,
        Nav2 updates only)."""
        return cls(
            observer=ObserverConfig(
                joint_refine=False, survey_sigma=0.0, range_bias_scatter=0.0, range_bias=False
            ),
            position_metric="identity",
            injection="paper",
            update_when_stationary=False,
            fusion="paper",
            kidnap_fixes=0,
            track_partial=False,
            proposal_fraction=0.0,
            partial_laser=False,
            partial_laser_rotate=0,
            sharp_laser_with_fix=False,
            refine=False,
            landmark_refine=False,
        )


def landmark_update(
    info: Array,
    vec: Array,
    pose: Array,
    landmarks: Array,
    ranges: Array,
    bearings: Array,
    sigma_range: Array,
    sigma_bearing: Array,
    pose_var: float,
    sigma_min: float,
) -> tuple[Array, Array]:
    """One information-form Kalman update of landmark offsets (improvement).

    The reflectors seen at ``ranges`` (n,) m and ``bearings`` (n,) rad from ``pose`` (3,)
    ``[x, y, theta]`` (a redundant fix, computed on the map's positions ``landmarks`` (n, 2))
    lie at ``o_i = pose (+) (r_i cos b_i, r_i sin b_i)`` in ``map``; the residual
    ``z_i = o_i - L_i`` observes the landmark's offset ``delta_i`` (true minus surveyed,
    relative to the fix's consensus frame) with covariance ``R_i = U diag(sigma_r^2,
    (r sigma_b)^2) U^T + pose_var I`` (``U`` the radial/tangential axes). ``info`` (n, 2, 2)
    and ``vec`` (n, 2) are each landmark's information matrix ``Lambda`` and vector ``eta``
    (offset ``delta = Lambda^-1 eta``); returns the updated pair. ``Lambda`` is capped at
    ``I / sigma_min^2`` (both scaled down together, i.e. older scans are forgotten) so that
    static per-pose errors of a parked robot do not become certain."""
    pose = np.asarray(pose, float)
    a = pose[2] + np.asarray(bearings, float)
    u = np.stack([np.cos(a), np.sin(a)], axis=1)  # (n, 2) radial, map frame
    t = np.stack([-u[:, 1], u[:, 0]], axis=1)
    r = np.asarray(ranges, float)
    z = pose[:2] + r[:, None] * u - np.asarray(landmarks, float)
    var_r = np.asarray(sigma_range, float) ** 2 + pose_var
    var_t = (r * np.asarray(sigma_bearing, float)) ** 2 + pose_var
    Rinv = (
        u[:, :, None] * u[:, None, :] / var_r[:, None, None]
        + t[:, :, None] * t[:, None, :] / var_t[:, None, None]
    )
    info = info + Rinv
    vec = vec + np.einsum("nij,nj->ni", Rinv, z)
    cap = 1.0 / sigma_min**2
    top = np.linalg.eigvalsh(info)[:, -1]
    f = np.where(top > cap, cap / top, 1.0)
    return info * f[:, None, None], vec * f[:, None]


def position_weight(particles: Array, mu: Array, cov: Array | None = None) -> Array:
    """Eq. 3: ``d = (2 pi)^{-3/2} exp(-1/2 e^T S^-1 e)``, ``e = x - mu_G`` (heading wrapped);
    ``S = I`` as printed unless ``cov`` (3, 3) is given. Returns (N,)."""
    e = particles - mu
    e[:, 2] = _wrap(e[:, 2])
    if cov is None:
        m2 = np.einsum("ij,ij->i", e, e)
    else:
        m2 = np.einsum("ij,jk,ik->i", e, np.linalg.inv(cov), e)
    return _EQ3_NORM * np.exp(-0.5 * m2)


def orientation_weight(particles: Array, landmarks: Array, bearings: Array, sigma: float) -> Array:
    """Eq. 4: ``s = (1/n) sum_i N(phi_i; mu_i, sigma)`` with ``mu_i`` the bearing of landmark
    ``i`` predicted from each particle (``base_link`` frame). Returns (N,)."""
    dx = landmarks[None, :, 0] - particles[:, 0:1]
    dy = landmarks[None, :, 1] - particles[:, 1:2]
    mu = np.arctan2(dy, dx) - particles[:, 2:3]
    err = _wrap(bearings[None, :] - mu)
    g = np.exp(-(err**2) / (2 * sigma**2)) / (sigma * np.sqrt(2 * np.pi))
    return g.mean(axis=1)


def gaussian_fit(particles: Array, weights: Array) -> tuple[Array, Array]:
    """Weighted mean ``m`` (3,) (circular mean of the heading) and covariance ``C`` (3, 3) of
    ``particles`` (N, 3) under normalized ``weights`` (N,)."""
    m = np.array(
        [
            float(weights @ particles[:, 0]),
            float(weights @ particles[:, 1]),
            float(np.arctan2(weights @ np.sin(particles[:, 2]), weights @ np.cos(particles[:, 2]))),
        ]
    )
    d = particles - m
    d[:, 2] = _wrap(d[:, 2])
    return m, (d * weights[:, None]).T @ d


def log_gauss(particles: Array, mean: Array, cov: Array) -> Array:
    """``log N(x; mean, cov)`` of every particle (N,), heading difference wrapped."""
    d = particles - mean
    d[:, 2] = _wrap(d[:, 2])
    L = np.linalg.cholesky(cov)
    z = np.linalg.solve(L, d.T)
    return -0.5 * np.einsum("ij,ij->j", z, z) - np.log(np.diag(L)).sum() - 1.5 * np.log(2 * np.pi)


def refine_proposal(
    prior: Array,
    loglik_prior: Array,
    loglik: Callable[[Array], Array],
    fraction: float,
    inflate: float,
    floor: Array,
    rng: np.random.Generator,
) -> tuple[Array, Array]:
    """Two-stage (adaptive) importance sampling of ``p(x | z) ~ p(z | x) p(x)`` (improvement).

    Stage 1: the predicted particles ``prior`` (N, 3), drawn from ``p(x)``, with weights
    ``w1 ~ p(z | x)`` (``loglik_prior``). Stage 2: ``n2 = fraction N`` particles drawn from
    ``q = N(m1, inflate^2 C1 + diag(floor^2))``, ``(m1, C1)`` the Gaussian fit of stage 1's
    posterior. Both sets are combined by deterministic-mixture weighting (Owen and Zhou 2000)
    with ``p(x)`` approximated by ``N(mp, Cp)`` fitted to ``prior``:
    ``w(x) = p(z | x) p(x) / ((n1 p(x) + n2 q(x)) / (n1 + n2))``, ``n1 = N - n2`` stage-1
    particles kept at random. Returns (particles (N, 3), normalized weights (N,))."""
    n = prior.shape[0]
    n2 = round(fraction * n)
    n1 = n - n2
    w1 = np.exp(loglik_prior - loglik_prior.max())
    w1 /= w1.sum()
    m1, c1 = gaussian_fit(prior, w1)
    mp, cp = gaussian_fit(prior, np.full(n, 1.0 / n))
    fl = np.diag(np.asarray(floor, float) ** 2)
    cq = inflate**2 * c1 + fl
    cp = cp + fl
    x2 = rng.standard_normal((n2, 3)) @ np.linalg.cholesky(cq).T + m1
    x2[:, 2] = _wrap(x2[:, 2])
    keep = rng.choice(n, n1, replace=False) if n1 < n else np.arange(n)
    x = np.concatenate([prior[keep], x2])
    ll = np.concatenate([loglik_prior[keep], loglik(x2)])
    lp = log_gauss(x, mp, cp)
    lq = log_gauss(x, m1, cq)
    lmix = np.logaddexp(np.log(n1 / n) + lp, np.log(n2 / n) + lq) if n1 else lq
    lw = ll + lp - lmix
    w = np.exp(lw - lw.max())
    return x, w / w.sum()


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
        # reflector radius: the caller's, else the map's; landmarks given without a radius on a
        # map without one would silently use the config's default (4 cm): refused
        if reflector_radius is not None:
            if not (np.isfinite(reflector_radius) and reflector_radius >= 0):
                raise InvalidInputError(
                    f"reflector_radius must be finite and >= 0 m, got {reflector_radius}"
                )
            radius: float | None = float(reflector_radius)
        elif grid.reflector_radius > 0:
            radius = float(grid.reflector_radius)
        elif landmarks is not None and len(lm) > 0:
            raise InvalidInputError(
                "landmarks given without reflector_radius and the map has none: pass "
                "reflector_radius= (m, 0 for flat tape) so detection fits the right circle"
            )
        else:
            radius = None
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
        ``ids`` are known in ``map`` (isotropic SD). Without ``landmark_refine`` the survey's
        ``observer.survey_sigma``; with it the refined offset's SD (largest axis of its
        posterior) combined with the consensus's own error, ``survey_sigma / sqrt(
        landmark_min_reflectors)`` (the offsets are relative to the fixes' consensus frame,
        whose translation is the mean of the survey errors of the reflectors in it)."""
        s = self.observer.cfg.survey_sigma
        ids = np.asarray(ids, int)
        if not self.ecfg.landmark_refine:
            return np.full(len(ids), s)
        post = 1.0 / np.linalg.eigvalsh(self._lm_info[ids])[:, 0]
        return np.sqrt(np.minimum(post, s**2) + s**2 / self.ecfg.landmark_min_reflectors)

    def _learn_landmarks(self, fix: ReflectorFix) -> None:
        """:func:`landmark_update` with a redundant fix (see ``landmark_refine``)."""
        e = self.ecfg
        ids = fix.ids
        beams = fix.beams if fix.beams is not None else np.ones(len(ids))
        sr, sb = self.observer.sigmas(beams, redundant=True)
        pose_var = float(np.trace(fix.trilateration.cov[:2, :2])) / 2
        info, vec = landmark_update(
            self._lm_info[ids],
            self._lm_vec[ids],
            fix.pose,
            self.observer.landmarks[ids],
            fix.ranges,
            fix.bearings,
            sr,
            sb,
            pose_var,
            e.landmark_sigma_min,
        )
        self._lm_info[ids] = info
        self._lm_vec[ids] = vec

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
            self.particles,
            lp,
            loglik,
            e.refine_fraction,
            e.refine_inflate,
            np.asarray(e.refine_floor),
            self.rng,
        )
        self.particles = x
        self.weights = w
        self.resample(w)

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

    def _associate(self, pose: Array) -> tuple[np.ndarray, np.ndarray]:
        """Detections (base_link) -> landmark ids by proximity to where ``pose`` predicts the
        landmarks; returns (detection indices, landmark ids) within ``track_gate``."""
        det = self.observer.last_detections
        L = self.observer.landmarks
        if len(det) == 0 or len(L) == 0:
            return np.zeros(0, dtype=np.int64), np.zeros(0, dtype=np.int64)
        c, s_ = np.cos(pose[2]), np.sin(pose[2])
        pm = det.points @ np.array([[c, s_], [-s_, c]]) + pose[:2]
        d = np.linalg.norm(pm[:, None, :] - L[None, :, :], axis=2)
        nn = d.argmin(axis=1)
        ok = d[np.arange(len(pm)), nn] <= self.ecfg.track_gate
        di, li = np.flatnonzero(ok), nn[ok]
        _, first = np.unique(li, return_index=True)  # one detection per landmark
        return di[first], li[first]

    def _tracked_fix(self, odom_pose: Array) -> ReflectorFix | None:
        """Two or more reflectors associated by the estimate: a pose from their ranges and
        bearings (Gauss-Newton from the estimate), used like a trilateration fix."""
        pose = self.pose_at(odom_pose)
        di, li = self._associate(pose)
        if len(di) < 2:
            self.track_status = "too_few_associated"
            return None
        det = self.observer.last_detections
        c = self.observer.cfg
        LM = self.tracking_landmarks
        # rigid check (a two-point "triangle match"): detected and map distances must agree
        P, L = det.points[di], LM[li]
        i, j = np.triu_indices(len(di), 1)
        dd = np.abs(np.linalg.norm(P[i] - P[j], axis=1) - np.linalg.norm(L[i] - L[j], axis=1))
        if dd.max() > self.ecfg.track_pair_tol:
            self.track_status = "pair_distance"
            return None
        sr, sb = self.observer.sigmas(det.beams[di])
        try:
            if self.ecfg.track_honest and c.honest_fix:
                # honest covariance: the landmarks' own uncertainty, the per-reflector range
                # walk and what is left of the common bias (the ranges are corrected by it)
                bsd = float(np.sqrt(1.0 / self.observer.bias_info)) if c.range_bias else 1e-6
                bt = trilaterate_bias(
                    LM[li],
                    det.ranges[di],
                    det.bearings[di],
                    np.sqrt(sr**2 + c.range_bias_scatter**2),
                    sb,
                    0.0,
                    bsd,
                    self.landmark_sd(li),
                    initial=pose,
                )
                tri = TrilaterationResult(bt.pose, bt.pose_cov, bt.rms, bt.n)
            else:
                tri = trilaterate(LM[li], det.ranges[di], det.bearings[di], sr, sb, initial=pose)
        except (ValueError, np.linalg.LinAlgError):
            self.track_status = "degenerate"
            return None
        if not np.all(np.isfinite(tri.pose)) or np.hypot(*(tri.pose[:2] - pose[:2])) > 0.3:
            self.track_status = "jump"
            return None
        if abs(float(_wrap(tri.pose[2] - pose[2]))) > self.ecfg.track_max_turn:
            self.track_status = "turn"
            return None
        # consistency: every reflector within outlier_sigmas of the refined pose
        d = LM[li] - tri.pose[:2]
        res_r = (np.linalg.norm(d, axis=1) - det.ranges[di]) / sr
        res_b = _wrap(np.arctan2(d[:, 1], d[:, 0]) - tri.pose[2] - det.bearings[di]) / sb
        if max(np.abs(res_r).max(), np.abs(res_b).max()) > c.outlier_sigmas:
            self.track_status = "inconsistent"
            return None
        self.track_status = "ok"
        return ReflectorFix(li, det.ranges[di], det.bearings[di], tri, len(det), det.beams[di])

    def _partial_update(
        self, odom_pose: Array, scan: LaserScan, force: bool
    ) -> PoseEstimate | None:
        """Improvement for fewer than two usable reflectors, every scan (no update thresholds).

        - one reflector, associated with its landmark through the current estimate: its range
          and bearing weight the particles together with the sharp laser likelihood
          (:meth:`_laser_weights`); ``partial_proposal_fraction`` of the particles are first
          drawn on the poses the reflector allows (heading ``N(theta_prior,
          partial_heading_sigma)``, position from the landmark, range and bearing);
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
        k = round(e.partial_proposal_fraction * len(self.particles))
        if k > 0:
            idx = self.rng.choice(len(self.particles), k, replace=False)
            th = prior[2] + e.partial_heading_sigma * self.rng.standard_normal(k)
            if len(di):  # on the circle of poses that see the landmark at this range/bearing
                r = det.ranges[di[0]] + e.track_sigma_range * self.rng.standard_normal(k)
                b = det.bearings[di[0]] + e.track_sigma_bearing * self.rng.standard_normal(k)
                self.particles[idx, 0] = L[0, 0] - r * np.cos(th + b)
                self.particles[idx, 1] = L[0, 1] - r * np.sin(th + b)
            else:
                self.particles[idx, :2] = prior[:2] + e.partial_position_sigma * (
                    self.rng.standard_normal((k, 2))
                )
            self.particles[idx, 2] = _wrap(th)
        r_obs, b_obs = det.ranges[di], det.bearings[di]

        def reflector_lik(P: Array) -> Array:  # (N,), 1 without reflectors
            dx = L[None, :, 0] - P[:, 0:1]
            dy = L[None, :, 1] - P[:, 1:2]
            rng_err = np.hypot(dx, dy) - r_obs[None, :]
            brg_err = _wrap(np.arctan2(dy, dx) - P[:, 2:3] - b_obs[None, :])
            return np.exp(
                -0.5
                * ((rng_err / e.track_sigma_range) ** 2 + (brg_err / e.track_sigma_bearing) ** 2)
            ).prod(axis=1)

        if e.refine:
            lp = self._laser_loglik(self.particles, scan)
            self._apply_weights(np.exp(lp - lp.max()))  # w_slow / w_fast bookkeeping
            self._refined(
                lambda P: self._laser_loglik(P, scan) + np.log(reflector_lik(P) + 1e-12),
                lp + np.log(reflector_lik(self.particles) + 1e-12),
            )
        else:
            ll = reflector_lik(self.particles)
            p = self._laser_weights(scan, partial=True)
            self._apply_weights(p)
            w = self.weights * (ll + 1e-12)
            total = float(w.sum())
            if not np.isfinite(total) or total <= 0:
                return None
            self.weights = w / total
            self.resample(self.weights)
        self._odom_last_update = odom_pose.copy()
        self._force_update = False
        self._estimate = None
        est = self._current(updated=True)
        src = "enhanced-partial" if len(di) else "enhanced-laser"
        return PoseEstimate(est.pose, est.cov, est.n_particles, True, src)

    def update(self, odom_pose: Array, scan: LaserScan, force: bool = False) -> PoseEstimate:
        if self.particles.shape[0] == 0:
            raise InvalidInputError("set an initial pose or call global_localization() first")
        odom_pose = finite_pose(odom_pose, "odometry pose")
        check_scan(scan)
        if self.plain_amcl:  # fallback_to_amcl on a map with < 3 reflectors
            self.last_fix = None
            est = super().update(odom_pose, scan, force)
            return PoseEstimate(est.pose, est.cov, est.n_particles, est.updated, "amcl")
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
                    return est
        if fix is None:
            # Algorithm 1 lines 4-10: original AMCL
            est = super().update(odom_pose, scan, force)
            return PoseEstimate(est.pose, est.cov, est.n_particles, est.updated, "amcl")
        odom_pose = np.asarray(odom_pose, float).reshape(3)
        if not (force or self.ecfg.update_when_stationary or self._should_update(odom_pose)):
            return self._current(updated=False)
        e = self.ecfg
        gate = self._gate(fix)
        if gate == "outlier":
            self.last_fix = None
            est = AMCL.update(self, odom_pose, scan, force=True)
            return PoseEstimate(est.pose, est.cov, est.n_particles, est.updated, "amcl")
        self.predict(odom_pose)  # line 12
        if gate == "reseed":
            self.particles = self.rng.multivariate_normal(
                fix.pose, fix.trilateration.cov + np.diag(e.position_cov_floor), len(self.particles)
            )
            self.particles[:, 2] = _wrap(self.particles[:, 2])
            self.weights = np.full(len(self.particles), 1.0 / len(self.particles))
            self.kidnap_resets += 1
        mu = fix.pose
        # improvement: a fix from two tracked reflectors, or from reflectors nearly in a line
        # (a corridor: lateral SD up to ~60 mm), is weak; the sharp laser, the two-stage
        # proposal and the scaled-down injection of the tracked case then apply
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
        cov = None
        if e.position_metric == "trilateration":
            cov = fix.trilateration.cov + np.diag(e.position_cov_floor)
            if tracked:
                cov = cov * e.track_cov_scale
        frac = e.proposal_fraction * (e.track_inject_scale if tracked else 1.0)
        if frac > 0:  # mixture proposal: some predicted particles drawn at mu_G
            k = round(frac * len(self.particles))
            idx = self.rng.choice(len(self.particles), k, replace=False)
            Lc = np.linalg.cholesky(cov if cov is not None else np.eye(3))
            self.particles[idx] = self.rng.standard_normal((k, 3)) @ Lc.T + mu
            self.particles[idx, 2] = _wrap(self.particles[idx, 2])
        sharp = tracked or (e.sharp_laser_with_fix and e.partial_laser)
        refine = sharp and e.refine and e.fusion == "product"
        if refine and e.partial_laser:  # the log likelihood is reused by the second stage
            lasl = self._laser_loglik(self.particles, scan)
            p = np.exp(lasl - lasl.max())
        else:
            p = self._laser_weights(scan, partial=sharp)
            # with refine (so partial_laser off) p is Nav2's field: _laser_loglik = log p
            with np.errstate(divide="ignore"):
                lasl = np.log(p) if refine else None
        omega = self.weights * p  # eq. 5
        omega = omega / max(float(omega.sum()), 1e-300)
        self._apply_weights(p)  # keeps w_slow / w_fast bookkeeping of AMCL
        d = position_weight(self.particles, mu, cov)  # eq. 3 (line 14)
        s = orientation_weight(
            self.particles, lm_fix, fix.bearings, e.bearing_sigma
        )  # eq. 4 (line 15)
        if e.fusion == "paper":
            w_new = e.alpha * s * omega + e.beta * d  # eq. 6 (line 16)
        else:  # improvement: all three likelihoods multiplied (d floored for robustness)
            w_new = s * omega * (d + e.position_weight_floor * _EQ3_NORM)
        total = float(w_new.sum())
        if not np.isfinite(total) or total <= 0:
            w_new = np.full(len(w_new), 1.0 / len(w_new))
        else:
            w_new = w_new / total  # line 19
        self.weights = w_new
        if refine:  # improvement: two-stage proposal (see _partial_update)
            b_fix = fix.bearings
            floor = e.position_weight_floor * _EQ3_NORM

            def tracked_loglik(P: Array) -> Array:
                s_ = orientation_weight(P, lm_fix, b_fix, e.bearing_sigma)
                d_ = position_weight(P, mu, cov)
                return np.log(s_ + 1e-300) + self._laser_loglik(P, scan) + np.log(d_ + floor)

            assert lasl is not None  # _laser_loglik on these particles (computed above)
            self._refined(tracked_loglik, np.log(s + 1e-300) + np.log(d + floor) + lasl)
        else:
            self.resample(w_new)  # ParticleGeneration(omega_new)
        # lines 20-26: inject new particles around mu_G with probability d (eq. 8)
        # eq. 8 on eq. 3 as printed (identity metric): particles within ~1.9 m / rad of mu_G
        d_new = position_weight(self.particles, mu, None)
        prob = np.where(d_new > e.injection_threshold, d_new, 0.0)
        if tracked:
            prob = prob * e.track_inject_scale
        inject = self.rng.uniform(size=len(prob)) <= prob
        k = int(inject.sum())
        if k:
            q = self.rng.standard_normal((k, 3))
            if e.injection == "paper":
                new = e.injection_lambda * q + mu  # eq. 7
            else:
                Lc = np.linalg.cholesky(cov if cov is not None else np.eye(3))
                new = q @ Lc.T + mu
            new[:, 2] = _wrap(new[:, 2])
            self.particles[inject] = new
        self._odom_last_update = odom_pose.copy()
        self._force_update = False
        self._estimate = None
        est = self._current(updated=True)
        return PoseEstimate(est.pose, est.cov, est.n_particles, True, "enhanced")
