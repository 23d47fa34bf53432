"""Settings of the particle filters: :class:`AMCLConfig` (Nav2 AMCL), :class:`ObserverConfig`
(reflector detection, identification and trilateration) and :class:`EnhancedConfig` (paper 001
Algorithm 1 and our improvements to it).

Paper-faithful behaviour is chosen one way: ``paper()`` on each config (``AMCLConfig.paper()``
is Nav2's defaults, which the paper ran). The measurements behind the defaults are in
``docs/localization.md``. Units: m, rad.
"""

from __future__ import annotations

from typing import Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field

from mmpa.localization.reflectors import DetectionConfig, IdentifyConfig

__all__ = ["AMCLConfig", "EnhancedConfig", "ObserverConfig"]


class AMCLConfig(BaseModel):
    """Nav2 AMCL parameters (names as in ``nav2_params.yaml``) and the scan refinement.

    Defaults: Nav2's, but for four (issue 34: Nav2's defaults diverge on real buildings whose
    scans are 0.7-1 m apart; measurements in ``docs/localization.md`` "Real logs"):
    ``laser_model_type = likelihood_field_prob`` (a likelihood, not Nav2's sum of cubes),
    ``sigma_hit = 0.1``, ``update_min_d`` / ``update_min_a`` 0.05 and ``scan_refine`` on;
    and two for ``--global`` / the beam model: ``global_search`` on (a whole-map search of
    the first scan seeds the cloud) and ``beam_form = "product"``. :meth:`paper` is Nav2's
    defaults throughout.
    """

    model_config = ConfigDict(extra="forbid")

    alpha1: float = Field(0.2, ge=0)  # rot noise from rot
    alpha2: float = Field(0.2, ge=0)  # rot noise from trans
    alpha3: float = Field(0.2, ge=0)  # trans noise from trans
    alpha4: float = Field(0.2, ge=0)  # trans noise from rot
    # the laser model (``mmpa.localization.amcl.LASER_MODELS``): Nav2's three.
    # "likelihood_field_prob" (the product of the beams' likelihoods) is the default: Nav2's
    # "likelihood_field" and "beam" score a pose by 1 + sum pz^3, which hardly tells a pose
    # 10 cm off from the true one (60 beams: 7.5 against 5.2) and cannot weigh the
    # refinement's particles (below)
    laser_model_type: Literal["likelihood_field", "likelihood_field_prob", "beam"] = (
        "likelihood_field_prob"
    )
    # the beam model's combination of its beams: "product" (Thrun et al. Table 6.1, a
    # likelihood like likelihood_field_prob; the default: the scan refinement's importance
    # weights need one, and with Nav2's sum of cubes AMCL at the other defaults lost the
    # track of the real logs from the true pose within 5-15 scans) or Nav2's "sum_of_cubes"
    beam_form: Literal["product", "sum_of_cubes"] = "product"
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
    # m, the beam's likelihood width. 0.1 (Nav2: 0.2): the endpoints of the real logs' scans
    # at their reference poses lie 35-41 mm (robust SD) from the 5 cm map's walls; 0.1 m is
    # that scaled by sqrt(60 / 10): the 60 beams are taken as ~10 independent ones (their
    # errors are shared: the map's cells, the reference, neighbouring beams)
    sigma_hit: float = Field(0.1, gt=0)
    # rad / m moved since the last filter update before the next (Nav2: 0.2 / 0.25). 0.05 /
    # 0.05: a 5 cm map cell, or a turn that moves an endpoint at 1 m by one. Between updates
    # the estimate follows the odometry alone: on freiburg-079 (scans ~9 cm apart) Nav2's
    # 0.25 m skips two scans in three, and where the wheels report 0.1 m forward per scan
    # while the reference moves 0.1 m back (scans 905-917) the filter was lost (1.3 m at scan
    # 915); standing still there is still no update (repeated scans are not independent)
    update_min_a: float = Field(0.05, ge=0)
    update_min_d: float = Field(0.05, ge=0)
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
    # improvement (issue 34; mmpa.localization.refine): the predicted cloud's estimate is
    # matched to the map by mmpa's Hector (HectorConfig's defaults: correlative search +-0.3
    # m / +-20 deg, damped Gauss-Newton on the distance field; its gates min_score and
    # max_jump) and ``refine_fraction`` of the particles are drawn around the match, the
    # rest from the motion model (a defensive mixture proposal, Hesterberg 1995), weighted
    # by the laser model times prior / proposal: a wrong match only wastes particles. Only
    # while the cloud's heaviest cluster is within ``refine_max_sd`` m (1 SD); off: Nav2.
    scan_refine: bool = True
    refine_fraction: float = Field(0.5, ge=0, le=1)
    # the proposal around the match: N(match, inflate^2 C + diag(floor^2)), C the match's
    # covariance (s^2 H^-1: a few mm, as if the 180 beams and the map were independent);
    # floors: a 5 cm map cell's SD (0.05 / sqrt(12) ~ 0.014 m, rounded up to 0.02) and
    # that over ~2 m of range (0.01 rad)
    refine_inflate: float = Field(2.0, ge=1)
    refine_floor_xy: float = Field(0.02, gt=0)
    refine_floor_theta: float = Field(0.01, gt=0)
    refine_max_sd: float = Field(1.0, gt=0)
    # improvement (issue 34; mmpa.localization.global_search): a global start
    # (global_localization()) seeds the cloud from a whole-map correlative search of the
    # first scan (branch and bound on a ``global_search_resolution`` grid, every pose within
    # ``global_search_ratio`` of the best score, the best of each KLD bin neighbourhood,
    # each refined by Hector; at most ``global_hypotheses``), max_particles shared among the
    # hypotheses, and while the cloud holds more than one cluster the scan refinement
    # matches every cluster. Off: Nav2's cloud uniform over the free space.
    global_search: bool = True
    # m: Hector's +-0.3 m correlative window takes a hypothesis half a 0.2 m cell off; the
    # search's time falls with the cube of the cell (0.1 m: 2-10 s on the real logs)
    global_search_resolution: float = Field(0.2, gt=0)
    global_search_ratio: float = Field(0.9, gt=0, le=1)
    global_hypotheses: int = Field(20, ge=1)

    @classmethod
    def paper(cls) -> AMCLConfig:
        """The AMCL paper 001 compares against and runs inside Algorithm 1: Nav2's defaults
        (Nav2's sum-of-cubes likelihood field, ``sigma_hit = 0.2``, no scan refinement)."""
        return cls(
            laser_model_type="likelihood_field",
            sigma_hit=0.2,
            update_min_a=0.2,
            update_min_d=0.25,
            scan_refine=False,
            global_search=False,
            beam_form="sum_of_cubes",
        )

    @classmethod
    def sparse_scans(cls) -> AMCLConfig:
        """Hand-set values for real logs whose scans are 0.7-1 m and 10-20 degrees apart
        (issue 34: the CARMEN logs, where Nav2's defaults diverge within 7-21 scans): the
        beam model, motion noise ``alpha1..4 = 0.05``, ``z_hit = 0.95``, ``z_rand = 0.05``,
        ``sigma_hit = 0.1`` m, no scan refinement (the issue's settings; the defaults do
        better). Measured: docs/localization.md "Real logs"."""
        return cls(
            laser_model_type="beam",
            alpha1=0.05,
            alpha2=0.05,
            alpha3=0.05,
            alpha4=0.05,
            z_hit=0.95,
            z_rand=0.05,
            sigma_hit=0.1,
            update_min_a=0.2,
            update_min_d=0.25,
            scan_refine=False,
            global_search=False,
            beam_form="sum_of_cubes",
        )


class ObserverConfig(BaseModel):
    """Detection, identification and trilateration settings."""

    model_config = ConfigDict(extra="forbid")

    detection: DetectionConfig = DetectionConfig()
    identify: IdentifyConfig = IdentifyConfig()
    range_sigma_beam: float = Field(0.015, gt=0)  # m, lidar range noise per beam
    range_sigma_floor: float = Field(0.002, ge=0)  # m, map error (the range fit is unbiased)
    # rad, bearing of one beam's edge (about the angular step, 0.25 deg), in base_link
    bearing_sigma_beam: float = Field(0.0035, gt=0)
    bearing_sigma_floor: float = Field(0.0005, ge=0)  # rad
    # rad, added to the bearing SD of redundant (3+ reflector) fixes only: the hit/miss edges
    # put a reflector's bearing within an interval of up to one beam step, an error (SD
    # step/6 = 0.73 mrad) that stays put while the robot stands still, so it does not average
    # out over the scans the filter fuses at rest; ranges (unbiased fit) do. Weighting bearings
    # down there lets the position follow the ranges. Tracked 2-reflector fixes need their
    # bearings.
    bearing_sigma_static: float = Field(0.001, ge=0)
    # rad: the lidar's angular step the bearing terms above were measured at (the twin's
    # 0.25 deg). A reflector's bearing is the middle of its first and last hit beams, each edge
    # uniform within one step ``a``: SD ``a / sqrt(24)`` however many beams hit. With
    # ``scale_with_scan`` the bearing SD is at least ``bearing_sigma_floor + sqrt((a^2 -
    # reference^2) / 24)``: nothing changes at the reference step (the twin) or finer, and a
    # coarse lidar's near reflectors (many beams, small ``1/sqrt(k)`` term) are not trusted
    # beyond its quantization.
    bearing_reference_step: float = Field(float(np.deg2rad(0.25)), gt=0)
    scale_with_scan: bool = True
    outlier_sigmas: float = Field(3.5, gt=0)  # drop reflectors with larger normalized residual
    # improvement: mu_G by a joint Gauss-Newton on ranges AND bearings weighted by the SDs
    # above (:func:`trilaterate` ``refine_heading``); False: eq. 1 (least squares on the
    # ranges) then eq. 2 (mean heading) as printed
    joint_refine: bool = True
    min_reflectors: int = Field(3, ge=3)
    # improvement: reflectors cut by something in front of them (a person) are not used; their
    # fitted centers are off by up to the radius
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

    @classmethod
    def paper(cls) -> ObserverConfig:
        """Eq. 1-2 as printed: least squares on the ranges, mean heading, no survey error or
        range bias."""
        return cls(joint_refine=False, survey_sigma=0.0, range_bias_scatter=0.0, range_bias=False)


class EnhancedConfig(BaseModel):
    """Algorithm 1 coefficients. Paper values: ``alpha=154``, ``beta=1``, ``lambda=1``,
    identity covariance in eq. 3 (``EnhancedConfig.paper()``)."""

    model_config = ConfigDict(extra="forbid")

    amcl: AMCLConfig = AMCLConfig.paper()  # Nav2's AMCL, as the paper ran it
    observer: ObserverConfig = ObserverConfig()
    alpha: float = Field(154.0, ge=0)  # eq. 6
    beta: float = Field(1.0, ge=0)  # eq. 6
    bearing_sigma: float = Field(0.01, gt=0)  # rad, eq. 4 (sigma of the observation angle)
    # eq. 3's metric (``mmpa.localization.fusion.POSITION_METRICS``)
    position_metric: Literal["identity", "trilateration"] = "trilateration"
    position_cov_floor: tuple[float, float, float] = (0.002**2, 0.002**2, 0.001**2)
    # eq. 7's new particles (``mmpa.localization.fusion.INJECTIONS``)
    injection: Literal["paper", "trilateration"] = "trilateration"
    injection_lambda: float = Field(1.0, gt=0)  # eq. 7 (paper: 1)
    injection_threshold: float = Field(0.01, ge=0)  # eq. 8
    update_when_stationary: bool = True
    # eq. 6 as printed, or Bayes product (``mmpa.localization.fusion.FUSIONS``)
    fusion: Literal["paper", "product"] = "product"
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
    # average out
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
    # 0: Nav2's fixed subset.
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
    # one or two reflectors carry the pose (tracked fixes, one-reflector updates)
    landmark_refine: bool = True
    # m, prior SD of a surveyed position: the survey's accuracy (paper 001 marks the reflectors
    # on a Gmapping map: cm level)
    landmark_map_sigma: float = Field(0.010, gt=0)
    landmark_min_reflectors: int = Field(4, ge=3)
    landmark_sigma_min: float = Field(0.0005, gt=0)  # m: posterior SD floor (static errors)
    # a map with fewer than three reflectors (a building mapped without them): False refuses
    # to start (InvalidInputError), True runs plain AMCL (Algorithm 1 lines 4-10) throughout
    fallback_to_amcl: bool = False

    @classmethod
    def paper(cls) -> EnhancedConfig:
        """Algorithm 1 exactly as printed (eq. 1-2 for ``mu_G``, identity eq. 3, lambda = 1,
        Nav2 updates only; the AMCL inside it keeps Nav2's defaults, ``AMCLConfig.paper()``)."""
        return cls(
            observer=ObserverConfig.paper(),
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
