"""Configuration of the colored point cloud global registration (paper 000 §3.2.2 II).

Every length is in metres and every default is scaled to a workbench seen by the wrist camera
from 0.4-1.0 m (the paper's sampling distance), where a 640x480 depth frame holds ~300k points
with ~1 mm spacing.
"""

from __future__ import annotations

from typing import Literal

from pydantic import BaseModel, ConfigDict, Field, model_validator

__all__ = ["IcpScale", "ProjectiveConfig", "RegistrationConfig"]


class _Frozen(BaseModel):
    model_config = ConfigDict(frozen=True, extra="forbid")


class IcpScale(_Frozen):
    """One level of the multi-scale ICP (Park et al. 2017, §4 "multi-scale").

    ``voxel``: voxel size (m) of both clouds at this level; ``max_distance``: correspondence
    gate (m); ``max_iter``: Gauss-Newton iterations; the level stops early when the relative
    change of fitness and inlier RMSE drops below ``relative``.
    """

    voxel: float = Field(gt=0)
    max_distance: float = Field(gt=0)
    max_iter: int = Field(ge=1)
    relative: float = Field(default=1e-4, ge=0)


#: from the FGR pose: the 2 cm level takes the large correction; 4 iterations at 1 cm give
#: the same poses as 8 on the twin's 78 benchmark and parking-error pairs (same E_t to 1 um,
#: same accepted and refused pairs), ~10 % of a cold registration less
_COARSE_TO_FINE = (
    IcpScale(voxel=0.02, max_distance=0.03, max_iter=10),
    IcpScale(voxel=0.01, max_distance=0.012, max_iter=4),
)
_NEAR = (IcpScale(voxel=0.01, max_distance=0.012, max_iter=8),)


class RegistrationConfig(_Frozen):
    """Parameters of :func:`mmpa.registration.prepare` and :func:`mmpa.registration.register`
    (lengths in m; the measurements behind the defaults: docs/registration.md).

    Preprocessing (applied once per cloud by ``prepare``)
        ``min_depth``/``max_depth`` crop on the optical axis z (m); ``nan_policy``: drop
        non-finite points (``"filter"``, counted in the diagnostics) or refuse the cloud
        (``"reject"``); every ``presample``-th point is kept (an RGB-D frame is far denser
        than the finest voxel; 640 not being a multiple of 6, 6 samples staggered columns
        where 8 would alias a textured plane's colours); the cloud is voxel-averaged at the
        finest ICP voxel and cleaned by a statistical outlier filter on that voxel cloud (a
        voxel whose mean distance to its ``outlier_neighbors`` nearest voxels exceeds the
        mean by ``outlier_std_ratio`` standard deviations is a flying pixel; 0 disables it);
        normals from ``normal_max_nn`` neighbours within ``normal_radius_factor`` voxels,
        oriented to the camera.
    Coarse stage (Zhou et al. 2016, FGR)
        FPFH at ``coarse_voxel`` with radius ``fpfh_radius_factor * coarse_voxel`` and at
        most ``fpfh_max_nn`` neighbours; FGR with ``fgr_distance_factor * coarse_voxel`` as
        its final correspondence distance, ``fgr_iterations`` iterations, ``fgr_max_tuples``
        tuples whose edge lengths agree within ``fgr_tuple_scale`` (Open3D's defaults).
    Fine stage (Park et al. 2017, colored ICP; point-to-plane ICP without color)
        ``scales`` from the coarse pose, ``init_scales`` when the caller gives ``init``;
        ``lambda_geometric`` weights the geometric against the photometric term (Park's 0.968).
        ``color_mode``: ``"paper"`` (:meth:`paper`) uses colored ICP whenever both clouds
        carry color (color std over the cloud above ``min_color_std``), else point-to-plane
        (paper 000); ``"auto"`` (beyond the paper) runs point-to-plane ICP first and colored
        ICP only when both clouds carry color and geometry alone is weak (smallest
        eigenvalue of the geometric information below ``geometric_min_information``) or
        rejected (the photometric term is biased by view-dependent shading and costlier);
        ``"colored"`` always uses colored ICP (refused without color); ``"geometric"`` never.
    Acceptance (the result is ``ok`` only if all hold)
        ``min_points`` voxels in each cloud; ``min_fitness`` inlier fraction at the finest
        scale; its inlier RMSE below ``max_rmse`` (``rmse_gate="fixed"``) or (``"adaptive"``,
        default) below the larger of ``max_rmse`` and ``rmse_margin`` times the RMSE expected
        of a correct fit, ``sqrt((rmse_spacing_factor s)^2 + 2 sigma_z^2)``: ``s`` the RMS
        nearest-neighbour spacing of the finest voxel level measured by ``prepare`` and
        ``sigma_z = depth_noise_k z^2`` the depth noise at the clouds' median depth ``z``,
        capped at ``rmse_max_fraction`` of the finest ICP gate; ``min_correspondences``
        inlier pairs; the fine pose within ``max_fine_shift``/``max_fine_rotation_deg`` of
        the FGR pose, or within ``max_init_shift``/``max_init_rotation_deg`` of a given
        ``init`` (tight on purpose: a fine-scale ICP started several cm off can slide along
        the bench planes into a wrong minimum). Beyond the FGR pose's limits,
        ``fine_motion_gate="support"`` (default) lets the feature matches vote: the fine pose
        is kept when at least ``min_fine_support`` and ``min_fine_support_ratio`` times as
        many of FGR's correspondences lie within ``coarse_voxel`` of each other under it as
        under the FGR pose; ``"fixed"``: the motion limits alone. The smallest eigenvalue of
        the per-correspondence information matrix of the ICP objective at least
        ``min_information`` (degenerate geometry: a plane, a cylinder...), where color
        gradients smaller than ``min_color_gradient`` (intensity per m) count as no texture;
        when both clouds carry color, the Pearson correlation of the two clouds'
        intensities over the fine stage's correspondences at least ``min_color_correlation``
        (beyond the paper; invariant to a gain and offset of the lighting; 0 disables it;
        skipped where either side's intensity standard deviation there is below
        ``color_check_min_std``).
    Competing poses (``ambiguity_check``: ``"global"`` registrations without ``init``,
        ``"always"``, ``"off"``; :mod:`mmpa.registration.ambiguity`): the degeneracy test
        again at the first ICP scale (normals of 2 cm voxels, whose noise does not hide a
        free direction) against ``coarse_min_information``, then ICP from the accepted pose
        moved by ``+-ambiguity_shift`` along its ``ambiguity_directions`` weakest directions
        and from the ``ambiguity_modes`` translations most voted by the FPFH matches. An end
        pose more than ``ambiguity_distance`` (RMS over the source) from the accepted one
        whose colours correlate competes by the source points only one of the two explains:
        with at least ``ambiguity_rival_ratio`` times the accepted pose's, it makes the pose
        ambiguous (refused), unless the accepted pose explains fewer than
        ``ambiguity_replace_ratio`` times its own: then it replaces the pose.
    ``seed`` seeds the random draws (FGR tuples). ``open3d_threads`` caps Open3D's worker
    threads during ``prepare`` and ``register`` (``None``: Open3D's default, all cores).
    """

    # preprocessing
    min_depth: float = Field(default=0.2, ge=0)
    max_depth: float = Field(default=1.5, gt=0)
    nan_policy: Literal["filter", "reject"] = "filter"
    presample: int = Field(default=6, ge=1)
    outlier_neighbors: int = Field(default=8, ge=0)
    outlier_std_ratio: float = Field(default=3.0, gt=0)
    normal_radius_factor: float = Field(default=2.0, gt=0)
    normal_max_nn: int = Field(default=8, ge=3)
    # coarse stage: FPFH + FGR
    coarse_voxel: float = Field(default=0.03, gt=0)
    fpfh_radius_factor: float = Field(default=4.0, gt=0)
    fpfh_max_nn: int = Field(default=50, ge=3)
    fgr_distance_factor: float = Field(default=0.5, gt=0)
    fgr_iterations: int = Field(default=64, ge=1)
    fgr_max_tuples: int = Field(default=1000, ge=10)
    fgr_tuple_scale: float = Field(default=0.95, gt=0, lt=1)
    # fine stage
    scales: tuple[IcpScale, ...] = Field(default=_COARSE_TO_FINE, min_length=1)
    init_scales: tuple[IcpScale, ...] = Field(default=_NEAR, min_length=1)
    lambda_geometric: float = Field(default=0.968, gt=0, le=1)
    color_mode: Literal["auto", "paper", "colored", "geometric"] = "auto"
    min_color_std: float = Field(default=1e-3, ge=0)
    # acceptance
    min_points: int = Field(default=200, ge=10)
    min_fitness: float = Field(default=0.5, ge=0, le=1)
    max_rmse: float = Field(default=0.006, gt=0)
    rmse_gate: Literal["adaptive", "fixed"] = "adaptive"
    # RMSE of a correct fit ~0.6 s (a uniform in-plane offset of two voxel grids: 0.41 voxel,
    # s ~0.7 voxel on a surface; measured: 3.5-5 mm on the twin, 5.2-6 mm on the desk)
    rmse_spacing_factor: float = Field(default=0.6, gt=0)
    depth_noise_k: float = Field(default=0.004, ge=0)
    rmse_margin: float = Field(default=1.5, gt=0)
    rmse_max_fraction: float = Field(default=0.75, gt=0, le=1)
    min_correspondences: int = Field(default=200, ge=6)
    max_fine_shift: float = Field(default=0.05, gt=0)
    max_fine_rotation_deg: float = Field(default=10.0, gt=0)
    max_init_shift: float = Field(default=0.02, gt=0)
    max_init_rotation_deg: float = Field(default=3.0, gt=0)
    fine_motion_gate: Literal["fixed", "support"] = "support"
    min_fine_support: int = Field(default=10, ge=0)
    min_fine_support_ratio: float = Field(default=0.5, ge=0)
    min_information: float = Field(default=2e-3, ge=0)
    geometric_min_information: float = Field(default=1e-2, ge=0)
    min_color_gradient: float = Field(default=2.0, ge=0)
    min_color_correlation: float = Field(default=0.7, ge=0, le=1)
    color_check_min_std: float = Field(default=0.02, ge=0)
    degeneracy_max_points: int = Field(default=3000, ge=100)
    # the competing-pose check (mmpa.registration.ambiguity; measurements: docs/registration.md)
    ambiguity_check: Literal["global", "always", "off"] = "global"
    coarse_min_information: float = Field(default=0.01, ge=0)
    ambiguity_shift: float = Field(default=0.03, gt=0)
    ambiguity_directions: int = Field(default=1, ge=0, le=6)
    ambiguity_modes: int = Field(default=2, ge=0)
    ambiguity_distance: float = Field(default=0.015, gt=0)
    ambiguity_rival_ratio: float = Field(default=0.9, gt=0)
    ambiguity_replace_ratio: float = Field(default=0.5, gt=0, le=1)
    seed: int = 0
    open3d_threads: int | None = Field(default=1, ge=1)

    @model_validator(mode="after")
    def _check(self) -> RegistrationConfig:
        if self.max_depth <= self.min_depth:
            raise ValueError(f"max_depth {self.max_depth} must exceed min_depth {self.min_depth}")
        return self

    @classmethod
    def paper(cls, **changes: object) -> RegistrationConfig:
        """The paper's own registration (paper 000 §3.2.2 II): colored ICP whenever both
        clouds carry colour (``color_mode="paper"``), else point-to-plane, without the
        competing-pose check (beyond the paper); ``changes`` on top.
        (FGR every iteration is the IPE loop's choice: :meth:`mmpa.ipe.IPEConfig.paper`.)"""
        return cls.model_validate({"color_mode": "paper", "ambiguity_check": "off", **changes})

    @property
    def fine_voxel(self) -> float:
        """The finest voxel of both ICP schedules: the resolution ``prepare`` keeps."""
        return min(s.voxel for s in (*self.scales, *self.init_scales))

    def preprocessing_key(self) -> tuple:
        """The fields that determine a :class:`~mmpa.registration.Prepared` cloud."""
        return (
            self.min_depth,
            self.max_depth,
            self.nan_policy,
            self.presample,
            self.outlier_neighbors,
            self.outlier_std_ratio,
            self.normal_radius_factor,
            self.normal_max_nn,
            self.coarse_voxel,
            self.fpfh_radius_factor,
            self.fpfh_max_nn,
            tuple(sorted({s.voxel for s in (*self.scales, *self.init_scales)})),
        )


class ProjectiveConfig(BaseModel):
    """Parameters of :func:`mmpa.registration.refine_projective` (lengths in m,
    ``normal_radius`` in pixels; the method: :mod:`mmpa.registration.projective`)."""

    model_config = ConfigDict(frozen=True, extra="forbid")

    max_points: int = Field(default=30000, ge=100)  # source points used (uniform stride)
    iterations: int = Field(default=8, ge=1)  # the error is flat after ~5 (twin)
    tolerance: float = Field(default=1e-5, gt=0)  # stop when |update| (m, rad) is below
    normal_radius: int = Field(default=5, ge=1)  # px, central-difference half width
    max_depth_jump: float = Field(default=0.01, gt=0)  # normals across larger jumps invalid
    # px (chessboard): an invalid pixel (a hole of the depth image) reads its vertex from the
    # nearest valid pixel within this distance, for the association and the normals' central
    # differences (a depth aligned to colour has a grid of 1-px holes: without it ~90 % of
    # the associations hit a hole); 0: holes stay holes (a dense image is unaffected).
    # Only in an image with at most ``hole_fill_max_valid`` valid pixels: a few scattered
    # dropouts lie where the depth is unreliable (edges, dark or specular spots), where a
    # neighbour's vertex is no safe stand-in, and cost
    # little (measurements: docs/registration.md)
    hole_fill_px: int = Field(default=2, ge=0)
    hole_fill_max_valid: float = Field(default=0.9, ge=0, le=1)
    gate: float = Field(default=0.005, gt=0)  # |point-to-plane residual| accepted
    depth_gate: float = Field(default=0.02, gt=0)  # |z' - z(u, v)| accepted (occlusions)
    huber: float = Field(default=0.001, gt=0)  # scale c of the robust residual weights
    # robust kernel of the residual weights: "huber" w = min(1, c / |r|); "geman_mcclure"
    # w = 1 / (1 + (r / c)^2)^2 (redescending: a region that changed since teaching pulls
    # less; measurements: docs/registration.md)
    kernel: Literal["huber", "geman_mcclure"] = "huber"
    estimate_scale: bool = True
    # |s - 1| accepted (s: the effective scale, mmpa.registration.projective). Realistic
    # sessions reach 1.1 % (docs/registration.md); a 3 % depth calibration fault moves dT_B
    # by ~1 cm and must be refused
    max_scale_error: float = Field(default=0.02, gt=0)
    # the relative disparity drift of the two captures, estimated with the pose
    # (mmpa.registration.projective); needs the sensor's f b (refine_projective's
    # disparity_fb), else "none"
    disparity_model: Literal["none", "offset", "affine"] = "affine"
    max_disparity_error: float = Field(default=1.0, gt=0)  # px, |a| and |b| accepted
    # zero-mean Gaussian priors (SD) of the relative drift of two sessions: [a] px and
    # [b_x, b_y] px per unit of x, y, and of log s. A disparity gradient tilts a fronto-
    # parallel scene like a rotation and s trades against a: where the geometry hardly tells
    # them apart, the prior holds them at a drift's published size (two D400 sessions differ
    # by ~0.1 px, librealsense #10476, #8434) instead of letting them absorb the misfit of a
    # changed region. Weighed against residuals of the kernel scale ``huber``; None: no prior
    disparity_prior_px: tuple[float, float] | None = (0.1, 0.2)
    scale_prior: float | None = Field(default=0.003, gt=0)
    min_inliers: int = Field(default=2000, ge=7)
    min_inlier_fraction: float = Field(default=0.3, ge=0, le=1)
    max_rmse: float = Field(default=0.003, gt=0)
    # the RMSE limit grows with the depth noise at the inliers' range (structured light /
    # stereo: sigma_z = depth_noise_k z^2, m^-1): max(max_rmse, rmse_margin sqrt(2) sigma_z)
    # at the inliers' median depth (two captures, each with sigma_z); "fixed": max_rmse
    rmse_gate: Literal["adaptive", "fixed"] = "adaptive"
    depth_noise_k: float = Field(default=0.004, ge=0)
    rmse_margin: float = Field(default=1.5, gt=0)
    max_shift: float = Field(default=0.01, gt=0)  # m of the source centroid from init
    max_rotation_deg: float = Field(default=2.0, gt=0)
    min_information: float = Field(default=2e-3, ge=0)
    # photometric term (mmpa.registration.projective, "Photometric"): the SD (grey levels
    # in [0, 1]) of the colour residual, which weighs it against the point-to-plane
    # residuals (whose scale is ``huber``); also the scale of its Huber weights. Used only
    # when refine_projective is given the source colours and the target colour image;
    # None: depth only
    photometric_sigma: float | None = Field(default=0.005, gt=0)
    # Gauss-Newton iterations per blur level of the joint (depth + colour) pass
    photometric_iterations: int = Field(default=8, ge=1)
    # the robust kernel of both terms in the joint pass (redescending: a region that changed
    # since teaching, whose colour and depth both disagree, stops pulling)
    photometric_kernel: Literal["huber", "geman_mcclure"] = "geman_mcclure"
    # a second start, Huber on every level but the finest (graduated non-convexity); the
    # start with the lower final objective wins (mmpa.registration.projective)
    photometric_graduated: bool = True
    # the joint pass runs on images blurred by these Gaussian SDs (px), coarse to fine
    photometric_blur_px: tuple[float, ...] = (2.0, 1.0, 0.0)
    # source points of the joint pass (a uniform subset of the ``max_points``)
    photometric_points: int = Field(default=4000, ge=100)
    # the depth-only pass before the joint one; False when ``init`` already is a depth-only
    # refinement's answer (IPE's converged view: the pass would find it again)
    photometric_depth_pass: bool = True
    # the photometric kernel's scale at each iteration: at least this many robust SDs of
    # the colour residuals (1.4826 MAD), ``photometric_sigma`` the floor (real frames' colour
    # residuals are wider than the twin's: a fixed scale down-weights most of them); None:
    # the fixed ``photometric_sigma``
    photometric_scale_mads: float | None = Field(default=2.0, gt=0)
