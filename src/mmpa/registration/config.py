"""Configuration of the colored point cloud global registration (paper 000 §3.2.2 II).

Every length is in metres and every default is scaled to a workbench seen by the wrist camera
from 0.4-1.0 m (the paper's sampling distance), where a 640x480 depth frame holds ~300k points
with ~1 mm spacing.
"""

from __future__ import annotations

from typing import Literal

from pydantic import BaseModel, ConfigDict, Field, model_validator

__all__ = ["IcpScale", "RegistrationConfig"]


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
    """Parameters of :func:`mmpa.registration.prepare` and :func:`mmpa.registration.register`.

    Preprocessing (applied once per cloud by ``prepare``)
        ``min_depth``/``max_depth`` crop on the optical axis z (m); ``nan_policy``: drop
        non-finite points (``"filter"``, counted in the diagnostics) or refuse the cloud
        (``"reject"``); every ``presample``-th point is kept (an RGB-D frame is far denser
        than the finest voxel: 1 mm spacing at 0.6 m; 6 still gives ~6k voxels of 1 cm for a
        640x480 frame of the bench, and, 640 not being a multiple of 6, samples staggered
        columns: 8 keeps the same columns of every row, whose colours alias on a textured
        plane (Table A.7 A.3: 5/6 trials vs 6/6 with 4, 6, 7 or 9; E_t 1.1 mm with 6, 1.3 mm
        with 4)); the cloud is voxel-averaged at the finest ICP voxel and cleaned by a
        statistical outlier filter on that voxel cloud (a voxel whose mean distance to its
        ``outlier_neighbors`` nearest voxels exceeds the mean by ``outlier_std_ratio``
        standard deviations is a flying pixel; 0 disables it); normals from
        ``normal_max_nn`` neighbours within ``normal_radius_factor`` voxels, oriented to the
        camera. (8 neighbours instead of 12 and presample 6 instead of 4: ~20 % less time for
        a cold pair, as accurate and as robust on the twin's bench: see the coarse stage.)
    Coarse stage (Zhou et al. 2016, FGR)
        FPFH at ``coarse_voxel`` (3 cm: ~60 % fewer points than at Open3D's 2 cm, so ~40 %
        less time for the descriptors and the matching than at 2.5 cm, as robust on the
        twin's bench: 70 parking-error pairs at Sites 1 and 2 (3-6 cm and 3 degrees
        standard deviation), 64/70 registered within 5 mm against 63/70 with the former
        2.5 cm / 12.5 cm / 12 neighbours / presample 4, mean E_t 0.75 vs 0.76 mm, and two
        wrong poses accepted by both, at 9-14 cm of parking error) with radius
        ``fpfh_radius_factor * coarse_voxel`` (12 cm) and at most ``fpfh_max_nn``
        neighbours; FGR with ``fgr_distance_factor *
        coarse_voxel`` as its final correspondence distance,
        ``fgr_iterations`` iterations, ``fgr_max_tuples`` tuples whose edge lengths agree
        within ``fgr_tuple_scale`` (Open3D's defaults).
    Fine stage (Park et al. 2017, colored ICP; point-to-plane ICP without color)
        ``scales`` from the coarse pose, ``init_scales`` when the caller gives ``init``;
        ``lambda_geometric`` weights the geometric against the photometric term (Park's 0.968).
        ``color_mode``: ``"paper"`` uses colored ICP whenever both clouds carry color (color std
        over the cloud above ``min_color_std``), else point-to-plane (paper 000); ``"auto"``
        (beyond the paper) runs point-to-plane ICP first and colored ICP only when both clouds
        carry color and geometry alone is weak (smallest eigenvalue of the geometric
        information below ``geometric_min_information``) or rejected: on the twin's bench the
        geometric objective alone is 1.5-3x more accurate in rotation than Park's (the
        photometric term is biased by view-dependent shading) and ~4x cheaper (Open3D
        re-estimates the target's color gradients on every call); ``"colored"`` always uses
        colored ICP (refused without color); ``"geometric"`` never does.
    Acceptance (the result is ``ok`` only if all hold)
        ``min_points`` voxels in each cloud; ``min_fitness`` inlier fraction at the finest
        scale; its inlier RMSE below ``max_rmse`` (``rmse_gate="fixed"``, the former
        behaviour) or (``"adaptive"``, default) below the larger of ``max_rmse`` and
        ``rmse_margin`` times the RMSE expected of a correct fit between these two clouds,
        ``sqrt((rmse_spacing_factor s)^2 + 2 sigma_z^2)``: ``s`` the RMS nearest-neighbour
        spacing of the finest voxel level measured by ``prepare`` (the sampling term: a
        point lands between the other cloud's voxels; larger where the depth image has
        holes) and ``sigma_z = depth_noise_k z^2`` the depth noise of a structured-light or
        stereo sensor at the clouds' median depth ``z`` (``depth_noise_k`` 0.004 /m: a
        D4xx-class stereo camera, 0.08 px subpixel at f b ~ 20 px m; a Kinect-class
        structured-light sensor is ~0.0015), capped at ``rmse_max_fraction`` of the finest
        ICP gate (inliers lie within it: a limit close to it tests nothing). The 6 mm
        ``max_rmse`` was tuned on the twin's dense clouds (1 cm voxels full); on real frames
        with a grid of holes (~1/3 valid pixels, tests/data/desk) correct neighbours fit at
        5.2-6.3 mm, and the adaptive limit there is ~6.8 mm, on the twin ~7 mm where correct
        fits are at 3.5-5 mm (the RMSE separates little: fitness, the fine-vs-coarse motion and
        the photometric check refuse the wrong poses); ``min_correspondences`` inlier pairs;
        the fine pose within ``max_fine_shift``/``max_fine_rotation_deg`` of the FGR pose, or
        within ``max_init_shift``/``max_init_rotation_deg`` of a given ``init`` (tight on purpose: a
        single fine-scale ICP started several cm off can slide along the bench planes into a
        wrong minimum with normal fitness; measured on the twin, 8 cm off gave a 32 mm error
        at fitness 0.79, so farther starts must use the global stage). Beyond the FGR pose's
        limits, ``fine_motion_gate="support"`` (default) lets the feature matches vote: the
        fine pose is kept when at least ``min_fine_support`` and ``min_fine_support_ratio``
        times as many of FGR's correspondences lie within ``coarse_voxel`` of each other under
        it as under the FGR pose (FGR misled by weak features is off by several cm and 10-30
        deg on real frames while ICP finds the pose its matches agree with; an ICP that slid
        along a repeated structure leaves the matches behind). ``"fixed"``: the motion limits
        alone. Desk set (``benchmarks/bench_desk.py``): wide pairs refused 9 -> 2 of 87, none
        wrong, the non-overlapping pairs all refused; twin robustness pairs unchanged;
        smallest eigenvalue of the per-correspondence information matrix of the ICP objective
        at least ``min_information`` (degenerate geometry: a plane, a cylinder...), where color
        gradients smaller than ``min_color_gradient`` (intensity per m) count as no texture;
        when both clouds carry color, the Pearson correlation of the two clouds' intensities
        over the fine stage's correspondences at least ``min_color_correlation`` (beyond the
        paper; invariant to a gain and offset of the lighting; 0 disables it; skipped where
        either side's intensity standard deviation there is below ``color_check_min_std``).
        A geometric fit that slid along a repeated structure has normal fitness and RMSE but
        puts different colors on top of each other: on the twin's robustness pairs the
        correct poses correlate 0.96-0.99, the two wrong ones (104 and 150 mm off, Site 2
        after 10-14 cm parking errors) 0.26 and 0.38.
    ``seed`` seeds the random draws (FGR tuples). ``open3d_threads`` caps Open3D's worker
    threads during ``prepare`` and ``register`` (1: on 2 shared cores a second worker costs
    more than it saves, 10-15 % of a cold registration under load; ``None``: Open3D's
    default, all cores).
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
    seed: int = 0
    open3d_threads: int | None = Field(default=1, ge=1)

    @model_validator(mode="after")
    def _check(self) -> RegistrationConfig:
        if self.max_depth <= self.min_depth:
            raise ValueError(f"max_depth {self.max_depth} must exceed min_depth {self.min_depth}")
        return self

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
