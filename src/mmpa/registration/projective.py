"""Projective point-to-plane refinement on an organized depth image (beyond the paper).

The fine stage of :mod:`mmpa.registration.pipeline` works on voxel-averaged clouds: at a 4 mm
voxel the two clouds are sampled on different grids and the averaged voxel centres of a slanted
or curved surface do not lie on the same surface, which biases the pose by 0.1-0.5 mm and
0.03-0.1 deg even without sensor noise (measured on the twin). When the two views are already
close (IPE after convergence: the camera is back within ``alpha`` of its taught pose), the
target can instead be used at full resolution as the organized depth image it came from
(KinectFusion's projective data association, Newcombe et al. 2011):

- target vertex map ``V(u, v) = z(u, v) K^-1 [u, v, 1]^T`` and normal map
  ``N = normalize((V(u+r, v) - V(u-r, v)) x (V(u, v+r) - V(u, v-r)))`` (central differences
  over ``r`` pixels, invalid across depth jumps larger than ``max_depth_jump``);
- each source point ``p`` maps to ``p' = s R p + t`` and is associated with the target pixel it
  projects to, ``(u, v) = round(K p' / z')``, i.e. ``q = V(u, v)``, ``n = N(u, v)``;
- Gauss-Newton on ``E = sum_i w_i (n_i . (p'_i - q_i))^2`` with Huber weights ``w_i`` of scale
  ``huber`` and a gate ``|r_i| < gate``; a left-multiplied twist ``[v, w]`` gives the residual
  Jacobian ``J_i = [n_i, p'_i x n_i]`` (and ``n_i . p'_i`` for ``log s`` when the scale is
  estimated).

Scale (``estimate_scale``): a stereo depth camera has a per-capture depth scale error (the
reference error model: 0.1 %); depth scaled by ``s`` scales every deprojected point about the
camera centre, so two captures of one scene differ by ``q = s R p + t``. Estimating ``s`` keeps
that error out of the rigid part (0.1 % of 0.45 m is 0.45 mm along the view direction). The
returned ``T`` is the rigid part ``[R, t]``. Over a shallow scene the scale and the disparity
offset below trade against each other; the gate on the depth scale (``max_scale_error``) is
on their product at the source's median depth ``z_m``, ``s / (1 + z_m a / (f b))``
(``stages["effective_scale"]``).

Disparity drift (``disparity_model``, with the depth sensor's ``f b``, focal length in pixels
times stereo baseline): a stereo camera's disparity drifts between sessions (temperature,
ambient light: an offset and a gradient across the image, librealsense #10476, #8434), which
a depth scale does not describe (``dz = -z^2 dd / (f b)``). After IPE converged the camera is
back at its taught viewpoint, so both captures see each scene point at nearly the same pixel
and their relative disparity error is a function of the source pixel:
``dd(x, y) = a + b_x x + b_y y`` (``"affine"``; ``"offset"``: ``a`` only), ``(x, y) =
(p_x / p_z, p_y / p_z)`` the normalized image coordinates of the source point. The source
point is moved along its ray to the depth that disparity gives,
``p(dd) = p / (1 + p_z dd / (f b))``, and ``dd``'s parameters join the Gauss-Newton
unknowns: ``dQ/dd = -s R p(dd) p_z(dd) / (f b)``, so ``J_a = -(p_z(dd) / (f b)) n . (Q - t)``
(and ``x``, ``y`` times it for ``b_x``, ``b_y``). The parameters are returned in
``stages["disparity_px"]`` (px of the native depth stream; ``b`` per unit of ``x``).

Photometric (beyond the paper; with ``source_colors`` and ``target_color``): near the taught
viewpoint a rotation of the camera about the scene it looks at, with the matching sideways
shift, tilts the scene's depth like a disparity gradient does, so over a shallow scene the
depth alone cannot tell them apart and the drift's prior decides (twin, realistic: 1-7 mrad
about the camera's y axis, 0.5-1.5 mm at the arm base). The colour image can: the taught
points' grey values ``c_i`` must reappear where the points project, whatever depth error
they carry (near the taught viewpoint the projection hardly depends on it). After the depth
pass, a joint Gauss-Newton pass adds the residuals
``r_i = I(pi(Q_i)) - ((1 + g) c_i + o + o_x x_i + o_y y_i)`` (``I`` the target's grey image,
bilinear; ``g, o, o_x, o_y`` the exposure and lighting-gradient change between the sessions,
estimated with the pose), with the Jacobian ``dr/dQ = grad I . dpi/dQ``
(``dpi/dQ = [[f_x / z, 0, -f_x x / z^2], [0, f_y / z, -f_y y / z^2]]``), so
``J = [g_Q, Q x g_Q]`` for the twist like the point-to-plane term (and the scale and
disparity chains through ``Q``), weighed ``(huber / photometric_sigma)^2`` against it, both
with the redescending ``photometric_kernel`` (the colour term's scale: ``photometric_sigma``,
or ``photometric_scale_mads`` robust SDs of the current colour residuals where that is
wider); coarse to fine over images blurred by
``photometric_blur_px`` (the source's grey values blurred alike by normalized convolution on
its own pixel grid). Two starts from the depth pass's estimate (``photometric_graduated``):
the kernel on every level (a region that changed since teaching stays out), and graduated,
Huber on the coarse levels (convex: it escapes a depth pass that the drift led several mrad
astray); the one with the lower objective at the finest level is kept (a point without a
residual counts at the kernel's saturation). Points projecting onto no depth, or one
``depth_gate`` away (occluded), are left out. Twin (realistic, 19 converged IPE views of
seed 0): E_t 1.23 -> 0.48 mm, E_R 0.0041 -> 0.0008, the scene-change outliers (4.3-4.5 mm)
0.2-0.8 mm; 9 views of seed 1 where the depth pass went astray (E_R 0.01-0.02): 3.78 ->
0.97 mm. The residual-scaled kernel (2 robust SDs): 0.43 -> 0.46 mm and 0.95 -> 0.69 mm on
the two sets, and on the real desk frames (3-view loops of neighbour pairs, 48 loops) the
closure went from 0.54 / 2.56 mm (median / max; worse than depth only, 0.46 / 1.24 mm) to
0.24 / 1.09 mm.

Holes: a depth image aligned to colour (or a sparse sensor) has invalid pixels, on real
frames a regular grid of 1-px holes with ~1/3 of the pixels valid; a projected point or one of
the four central-difference neighbours landing on a hole would drop the correspondence (then
~90 % of them). Each invalid pixel reads its vertex from the nearest valid pixel within
``hole_fill_px`` (chessboard distance, one distance transform per call) when at most
``hole_fill_max_valid`` of the pixels are valid; a dense image is unchanged.

The refinement is refused (``ok=False``, with a reason) when too few points associate, the
inlier RMSE is too large (above ``max_rmse``, or, ``rmse_gate="adaptive"``, the depth noise
``sigma_z = depth_noise_k z^2`` of two captures at the inliers' median depth times
``rmse_margin`` where that is larger), the pose moves too far from ``init`` or the geometric
objective is degenerate (smallest eigenvalue of
:func:`~mmpa.registration.pipeline.information_matrix` below ``min_information``: a plane,
where only texture could fix the pose).
"""

from __future__ import annotations

import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any, Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field
from scipy import ndimage

from mmpa.core.errors import InvalidInputError
from mmpa.core.geometry import Array, exp_se3
from mmpa.registration._blas import single_threaded_blas
from mmpa.registration.pipeline import information_matrix
from mmpa.robot.description import CameraIntrinsics

__all__ = [
    "ProjectiveConfig",
    "ProjectiveResult",
    "normal_map",
    "refine_projective",
    "robust_weights",
    "vertex_map",
]


class ProjectiveConfig(BaseModel):
    """Parameters of :func:`refine_projective` (lengths in m, ``normal_radius`` in pixels)."""

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
    # dropouts (the twin's realistic profile: 2 %) lie where the depth is unreliable (edges,
    # dark or specular spots), where a neighbour's vertex is no safe stand-in, and cost
    # little (0.83 instead of 0.91 of the source associated there)
    hole_fill_px: int = Field(default=2, ge=0)
    hole_fill_max_valid: float = Field(default=0.9, ge=0, le=1)
    gate: float = Field(default=0.005, gt=0)  # |point-to-plane residual| accepted
    depth_gate: float = Field(default=0.02, gt=0)  # |z' - z(u, v)| accepted (occlusions)
    huber: float = Field(default=0.001, gt=0)  # scale c of the robust residual weights
    # robust kernel of the residual weights: "huber" w = min(1, c / |r|); "geman_mcclure"
    # w = 1 / (1 + (r / c)^2)^2 (redescending: a region that changed since teaching pulls
    # less). IPE under realistic, 30 parks: Site 1 1.26 -> 0.94 mm, Site 2 1.37 -> 1.49 mm
    kernel: Literal["huber", "geman_mcclure"] = "huber"
    estimate_scale: bool = True
    # |s - 1| accepted (s: the effective scale, module docstring). Realistic sessions reach
    # 1.1 % (twin, seed 1: 1.0102 and 1.0113 in 270 IPE runs); a 3 % depth calibration
    # fault moves dT_B by ~1 cm and must be refused
    max_scale_error: float = Field(default=0.02, gt=0)
    # the relative disparity drift of the two captures, estimated with the pose (module
    # docstring); needs the sensor's f b (refine_projective's disparity_fb), else "none"
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
    # photometric term (module docstring, "Photometric"): the SD (grey levels in [0, 1]) of
    # the colour residual, which weighs it against the point-to-plane residuals (whose scale
    # is ``huber``); also the scale of its Huber weights. Used only when refine_projective is
    # given the source colours and the target colour image; None: depth only
    photometric_sigma: float | None = Field(default=0.005, gt=0)
    # Gauss-Newton iterations per blur level of the joint (depth + colour) pass
    photometric_iterations: int = Field(default=8, ge=1)
    # the robust kernel of both terms in the joint pass (redescending: a region that changed
    # since teaching, whose colour and depth both disagree, stops pulling)
    photometric_kernel: Literal["huber", "geman_mcclure"] = "geman_mcclure"
    # a second start, Huber on every level but the finest (graduated non-convexity); the
    # start with the lower final objective wins (module docstring)
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


@dataclass(frozen=True)
class ProjectiveResult:
    """``T`` (4, 4) rigid ``T_target_source``; ``scale`` the relative depth scale ``s``;
    ``rmse`` (m) and ``n_inliers`` of the last association; ``ok``/``reason`` as in
    :class:`~mmpa.registration.Registration`; ``min_information`` the degeneracy measure."""

    T: Array
    scale: float
    rmse: float
    n_inliers: int
    inlier_fraction: float
    min_information: float
    ok: bool
    reason: str
    seconds: float
    iterations: int
    stages: dict[str, Any] = field(default_factory=dict)


def robust_weights(r: Array, c: float, kernel: str = "huber") -> Array:
    """IRLS weights of residuals ``r`` (m) for a robust kernel of scale ``c`` (m):
    ``"huber"`` ``w = min(1, c / |r|)``; ``"geman_mcclure"`` ``w = 1 / (1 + (r / c)^2)^2``
    (the weight of ``rho(r) = (r^2 / 2) / (1 + (r / c)^2)``, ``w = rho'(r) / r``)."""
    a = np.abs(np.asarray(r, dtype=float))
    if kernel == "huber":
        return np.where(a <= c, 1.0, c / np.maximum(a, 1e-300))
    if kernel == "geman_mcclure":
        return 1.0 / np.square(1.0 + np.square(a / c))
    raise InvalidInputError(f"unknown robust kernel {kernel!r}; use 'huber' or 'geman_mcclure'")


def vertex_map(depth: Array, intr: CameraIntrinsics) -> Array:
    """``V(u, v) = z (u - cx)/fx, z (v - cy)/fy, z`` (H, W, 3) m; zero where ``depth <= 0``."""
    z = np.asarray(depth, dtype=float)
    if z.shape != (intr.height, intr.width):
        raise InvalidInputError(
            f"depth {z.shape} does not match the intrinsics {intr.height}x{intr.width}"
        )
    z = np.where(np.isfinite(z) & (z > 0), z, 0.0)
    u = (np.arange(intr.width) - intr.cx) / intr.fx
    v = (np.arange(intr.height) - intr.cy) / intr.fy
    return np.stack([z * u[None, :], z * v[:, None], z], axis=-1)


def normal_map(V: Array, radius: int, max_jump: float) -> tuple[Array, Array]:
    """Unit normals (H, W, 3) of a vertex map by central differences over ``radius`` px,
    oriented toward the camera, and the validity mask (H, W): all four neighbours valid and
    within ``max_jump`` in depth of the centre."""
    r = int(radius)
    H, W, _ = V.shape
    z = V[..., 2]
    valid = np.zeros((H, W), bool)
    N = np.zeros_like(V)
    c = (slice(r, H - r), slice(r, W - r))
    zc = z[c]
    zl, zr = z[r : H - r, : W - 2 * r], z[r : H - r, 2 * r :]
    zu, zd = z[: H - 2 * r, r : W - r], z[2 * r :, r : W - r]
    ok = (zc > 0) & (zl > 0) & (zr > 0) & (zu > 0) & (zd > 0)
    for zz in (zl, zr, zu, zd):
        ok &= np.abs(zz - zc) < max_jump
    dx = V[r : H - r, 2 * r :] - V[r : H - r, : W - 2 * r]
    dy = V[2 * r :, r : W - r] - V[: H - 2 * r, r : W - r]
    n = np.cross(dx, dy)
    norm = np.linalg.norm(n, axis=-1)
    ok &= norm > 0
    n = n / np.where(norm > 0, norm, 1.0)[..., None]
    flip = np.einsum("hwi,hwi->hw", n, V[c]) > 0
    n[flip] *= -1.0
    N[c] = n
    valid[c] = ok
    return N, valid


def refine_projective(
    source_points: Array,
    target_depth: Array,
    intrinsics: CameraIntrinsics,
    init: Array,
    cfg: ProjectiveConfig | None = None,
    disparity_fb: float | None = None,
    source_colors: Array | None = None,
    target_color: Array | None = None,
) -> ProjectiveResult:
    """Refine ``T_target_source`` by projective point-to-plane ICP (see the module docstring).

    ``source_points`` (N, 3) m in the source camera frame; ``target_depth`` (H, W) m along the
    target camera's optical axis (0 where invalid) with ``intrinsics``; ``init`` (4, 4) a pose
    close to the answer (within a few mm: the association is by projection, not search).
    ``disparity_fb`` (px m): the depth sensor's focal length (native depth stream, px) times
    its stereo baseline, for ``cfg.disparity_model``; ``None``: no disparity drift estimated.
    ``source_colors`` (N, 3) RGB of the source points (uint8, or floats in [0, 1]) and
    ``target_color`` (H, W, 3) the target's colour image (pixel-aligned with its depth): with
    both (and ``cfg.photometric_sigma``) the photometric term joins the refinement.
    """
    if disparity_fb is not None and not (np.isfinite(disparity_fb) and disparity_fb > 0):
        raise InvalidInputError(f"disparity_fb must be positive (f b, px m), got {disparity_fb}")
    if (source_colors is None) != (target_color is None):
        raise InvalidInputError(
            "the photometric term needs both the source colours and the target colour image"
        )
    photo = None
    if source_colors is not None and target_color is not None:
        photo = _photometric_inputs(source_points, source_colors, target_color, intrinsics)
    with single_threaded_blas():  # small products: a second thread only costs (see _blas)
        return _refine_projective(
            source_points, target_depth, intrinsics, init, cfg, disparity_fb, photo
        )


def grey(rgb: Array) -> Array:
    """Luma ``0.299 R + 0.587 G + 0.114 B`` in [0, 1] of RGB values (uint8 or floats in [0, 1]),
    shape ``rgb.shape[:-1]``."""
    c = np.asarray(rgb)
    f = c.astype(float) / 255.0 if c.dtype == np.uint8 else c.astype(float)
    return f @ np.array([0.299, 0.587, 0.114])


def _photometric_inputs(
    points: Array, colors: Array, target_color: Array, intr: CameraIntrinsics
) -> tuple[Array, Array]:
    """Checked photometric inputs: the source points' grey values (N,) and the target's grey
    image (H, W)."""
    P = np.asarray(points)
    c = np.asarray(colors)
    if c.ndim != 2 or c.shape != (len(P), 3):
        raise InvalidInputError(
            f"source colours must be (N, 3) for the {len(P)} source points, got {c.shape}"
        )
    img = np.asarray(target_color)
    if img.shape != (intr.height, intr.width, 3):
        raise InvalidInputError(
            f"target colour image {img.shape} does not match the intrinsics "
            f"{intr.height}x{intr.width}x3"
        )
    g = grey(c)
    if not np.isfinite(g).all():
        raise InvalidInputError("source colours hold NaN or inf")
    return g, grey(img)


def _bilinear(img: Array, u: Array, v: Array) -> Array:
    """Bilinear samples of ``img`` (H, W, C) at continuous pixel coordinates (callers keep
    ``0 <= u < W - 1``, ``0 <= v < H - 1``); shape (M, C)."""
    H, W, C = img.shape
    flat = img.reshape(H * W, C)
    u0 = np.floor(u).astype(np.intp)
    v0 = np.floor(v).astype(np.intp)
    a = (u - u0)[:, None]
    b = (v - v0)[:, None]
    i = v0 * W + u0
    return (1 - b) * ((1 - a) * flat[i] + a * flat[i + 1]) + b * (
        (1 - a) * flat[i + W] + a * flat[i + W + 1]
    )


def _source_grey_levels(
    P: Array, g: Array, intr: CameraIntrinsics, sds: Sequence[float], keep: Array
) -> list[Array]:
    """The source's grey values ``g`` (N,) blurred like the target image by a Gaussian of
    each SD in ``sds`` (px; 0: unblurred), at the points ``keep`` (K,) of ``P`` (N, 3): the
    points (taken from the source camera's pixel grid) are put back on it once, blurred by
    normalized convolution (holes do not darken), and read back at their pixels; one (K,)
    array per SD."""
    H, W = intr.height, intr.width
    with np.errstate(divide="ignore", invalid="ignore"):
        u = np.rint(intr.fx * P[:, 0] / P[:, 2] + intr.cx)
        v = np.rint(intr.fy * P[:, 1] / P[:, 2] + intr.cy)
    ok = (P[:, 2] > 0) & (u >= 0) & (u < W) & (v >= 0) & (v < H)
    pix = v[ok].astype(np.intp) * W + u[ok].astype(np.intp)
    S = np.bincount(pix, weights=g[ok], minlength=H * W).astype(float).reshape(H, W)
    M = np.bincount(pix, minlength=H * W).astype(float).reshape(H, W)
    ok_k = ok[keep]
    uk, vk = u[keep][ok_k].astype(np.intp), v[keep][ok_k].astype(np.intp)
    out = []
    for sd in sds:
        gk = g[keep].copy()
        if sd > 0:
            Sb = ndimage.gaussian_filter(S, sd)
            Mb = ndimage.gaussian_filter(M, sd)
            with np.errstate(divide="ignore", invalid="ignore"):
                blurred = Sb[vk, uk] / Mb[vk, uk]
            gk[ok_k] = np.where(np.isfinite(blurred), blurred, gk[ok_k])
        out.append(gk)
    return out


def _refine_projective(
    source_points: Array,
    target_depth: Array,
    intrinsics: CameraIntrinsics,
    init: Array,
    cfg: ProjectiveConfig | None,
    disparity_fb: float | None = None,
    photo: tuple[Array, Array] | None = None,
) -> ProjectiveResult:
    cfg = cfg or ProjectiveConfig()
    if cfg.photometric_sigma is None:
        photo = None
    t0 = time.perf_counter()
    P = np.asarray(source_points, dtype=float)
    if P.ndim != 2 or P.shape[1] != 3:
        raise InvalidInputError(f"source points must be (N, 3), got {P.shape}")
    T0 = np.asarray(init, dtype=float)
    if T0.shape != (4, 4) or not np.isfinite(T0).all():
        raise InvalidInputError(f"init must be a finite 4x4 transform, got shape {T0.shape}")
    src_grey = photo[0] if photo is not None else None
    if not np.isfinite(P.sum()):  # one reduction; the per-row test only when needed
        fin = np.isfinite(P).all(axis=1)
        P = P[fin]
        src_grey = src_grey[fin] if src_grey is not None else None
    P_all, grey_all, stride = P, src_grey, 1
    if len(P) > cfg.max_points:
        stride = int(np.ceil(len(P) / cfg.max_points))
        P = P[::stride]
        src_grey = src_grey[::stride] if src_grey is not None else None
    z_img = np.asarray(target_depth, dtype=float)
    if z_img.shape != (intrinsics.height, intrinsics.width):
        raise InvalidInputError(
            f"depth {z_img.shape} does not match the intrinsics "
            f"{intrinsics.height}x{intrinsics.width}"
        )
    H, W = z_img.shape
    # depth image flattened, 0 where invalid; the vertex map V(u, v) = z (x_u, y_v, 1)
    # (x_u = (u - cx)/fx, y_v = (v - cy)/fy)
    zf = np.where(np.isfinite(z_img) & (z_img > 0), z_img, 0.0).ravel()
    rad = cfg.normal_radius
    fx, fy, cx, cy = intrinsics.fx, intrinsics.fy, intrinsics.cx, intrinsics.cy
    xu = (np.arange(W) - cx) / fx
    yv = (np.arange(H) - cy) / fy
    valid = zf > 0
    n_valid = int(np.count_nonzero(valid))
    if n_valid < cfg.hole_fill_max_valid * H * W and cfg.hole_fill_px > 0:
        # holes (a sparse or hole-gridded depth image): each pixel's vertex is that of the
        # nearest valid pixel within hole_fill_px (none beyond)
        dist, (iy, ix) = ndimage.distance_transform_cdt(
            ~valid.reshape(H, W), metric="chessboard", return_indices=True
        )
        fill = np.where(dist.ravel() <= cfg.hole_fill_px, (iy * W + ix).ravel(), -1)
        fill_z = np.where(fill >= 0, zf[np.maximum(fill, 0)], 0.0)
        fill_x = fill_z * xu[np.maximum(fill, 0) % W]
        fill_y = fill_z * yv[np.maximum(fill, 0) // W]
    else:
        fill_z = zf
        fill_x = (zf.reshape(H, W) * xu[None, :]).ravel()
        fill_y = (zf.reshape(H, W) * yv[:, None]).ravel()

    # the target's vertex q = V(u, v) and unit normal n = dx x dy / |dx x dy| at a pixel,
    # dx = V(u+r, v) - V(u-r, v), dy = V(u, v+r) - V(u, v-r) (r = normal_radius, each vertex
    # at the nearest valid pixel within hole_fill_px), kept as rows [q, n] of ``tgt`` once
    # computed (the refinement's iterations hit nearly the same pixels again); tgt_ok: all
    # five vertices valid, the four within max_depth_jump of the centre, the normal defined
    tgt = np.empty((H * W, 6))
    tgt_ok = np.zeros(H * W, bool)
    have = np.zeros(H * W, bool)

    def target_at(pix: Array) -> tuple[Array, Array]:
        """``tgt`` rows (M, 6) and ``tgt_ok`` (M,) at the flat pixels ``pix`` (M,), each at
        least ``r`` px inside the image."""
        new = pix[~have[pix]]
        if len(new):
            zc, xc, yc = fill_z[new], fill_x[new], fill_y[new]
            ok = zc > 0
            nb = []
            for d in (-rad, rad, -rad * W, rad * W):  # left, right, up, down
                z_, x_, y_ = fill_z[new + d], fill_x[new + d], fill_y[new + d]
                ok &= (z_ > 0) & (np.abs(z_ - zc) < cfg.max_depth_jump)
                nb.append((x_, y_, z_))
            (xl, yl, zl), (xr, yr, zr), (xu_, yu, zu), (xd, yd, zd) = nb
            ax, ay, az = xr - xl, yr - yl, zr - zl
            bx, by, bz = xd - xu_, yd - yu, zd - zu
            nx, ny, nz = ay * bz - az * by, az * bx - ax * bz, ax * by - ay * bx
            norm = np.sqrt(nx * nx + ny * ny + nz * nz)
            ok &= norm > 0
            norm[~ok] = 1.0
            tgt[new] = np.column_stack([xc, yc, zc, nx / norm, ny / norm, nz / norm])
            tgt_ok[new] = ok
            have[new] = True
        return tgt[pix], tgt_ok[pix]

    stages: dict[str, Any] = {
        "maps_s": time.perf_counter() - t0,
        "n_source": len(P),
        "valid_pixel_fraction": n_valid / (H * W),
    }

    R, t, log_s = T0[:3, :3].copy(), T0[:3, 3].copy(), 0.0
    n_par = 7 if cfg.estimate_scale else 6
    n_disp = 0
    if disparity_fb is not None:
        n_disp = {"none": 0, "offset": 1, "affine": 3}[cfg.disparity_model]
    disp = np.zeros(n_disp)  # [a, b_x, b_y] px
    # the disparity's regressors per source point: 1, x, y (normalized image coordinates)
    with np.errstate(divide="ignore", invalid="ignore"):
        xs, ys = P[:, 0] / P[:, 2], P[:, 1] / P[:, 2]
    Xd = np.column_stack([np.ones(len(P)), xs, ys])[:, :n_disp]
    fb = float(disparity_fb) if disparity_fb is not None else 1.0
    # (parameter index, prior SD, current value) of the parameters with a zero-mean prior
    prior_terms: list[tuple[int, float, Any]] = []
    if cfg.estimate_scale and cfg.scale_prior is not None:
        prior_terms.append((6, cfg.scale_prior, lambda: log_s))
    if n_disp and cfg.disparity_prior_px is not None:
        for j in range(n_disp):
            sd = cfg.disparity_prior_px[0 if j == 0 else 1]
            prior_terms.append((n_par + j, sd, lambda j=j: disp[j]))

    def corrected(disp: Array, idx: Array | None = None) -> Array:
        """The source points ``P[idx]`` (None: all) moved along their rays by the disparity
        drift ``disp``."""
        Pi = P if idx is None else P[idx]
        if n_disp == 0:
            return Pi
        dd = (Xd if idx is None else Xd[idx]) @ disp
        return Pi / (1.0 + Pi[:, 2] * dd / fb)[:, None]

    def associate(R: Array, t: Array, log_s: float, Pa: Array) -> tuple[Array, Array, Array, Array]:
        """Project the moved source points ``Pa`` (the drift-corrected points of the active
        set, K x 3) into the target image; the inlier points ``Q`` (M, 3), the target
        normals ``n`` (M, 3) (``tgt``), the point-to-plane residuals ``r`` (M,) and the
        inliers' rows (M,) in ``Pa``."""
        Q = np.exp(log_s) * (Pa @ R.T) + t
        z = Q[:, 2]
        with np.errstate(divide="ignore", invalid="ignore"):
            u = np.rint(fx * Q[:, 0] / z + cx)
            v = np.rint(fy * Q[:, 1] / z + cy)
        inside = (z > 0) & (u >= rad) & (u < W - rad) & (v >= rad) & (v < H - rad)
        idx = np.flatnonzero(inside)
        ui, vi = u[idx].astype(np.intp), v[idx].astype(np.intp)
        pix = vi * W + ui
        g, g_ok = target_at(pix)  # q = V(u, v) and the unit normal n there
        Qi = Q[idx]
        d = Qi - g[:, :3]
        r = d[:, 0] * g[:, 3] + d[:, 1] * g[:, 4] + d[:, 2] * g[:, 5]  # (Q - q) . n
        keep = g_ok & (np.abs(r) < cfg.gate) & (np.abs(d[:, 2]) < cfg.depth_gate)
        return Qi[keep], g[keep, 3:], r[keep], idx[keep]

    n_all = n_par + n_disp
    # the photometric term's brightness model: target grey = (1 + g) source grey + o
    # + o_x x + o_y y (exposure / white balance, and a lighting gradient across the image)
    bright = np.zeros(4)
    kernel_now = cfg.photometric_kernel
    xs_f, ys_f = np.nan_to_num(xs), np.nan_to_num(ys)

    def chain(J: Array, Q: Array, g: Array, pz: Array, xd: Array) -> None:
        """Fill the pose, scale and disparity columns of ``J`` (M, >= n_all) for residuals
        whose gradient with respect to the moved point ``Q`` (M, 3) is ``g`` (M, 3): the
        left twist ``[g, Q x g]``; ``log s``: ``g . (Q - t)`` (``s R p = Q - t``); the
        disparity: ``dQ/d(dd) = -s R p(dd) p_z(dd) / (f b)`` times its regressors (module
        docstring); ``pz`` (M,) the rows' corrected source depths ``p_z(dd)``, ``xd`` (M,
        n_disp) their disparity regressors."""
        J[:, :3] = g
        J[:, 3:6] = np.cross(Q, g)
        j_s = np.einsum("ij,ij->i", Q - t, g)
        if cfg.estimate_scale:
            J[:, 6] = j_s
        if n_disp:
            J[:, n_par:n_all] = (-(pz / fb) * j_s)[:, None] * xd

    def photometric(
        Pa: Array, act: Array, cg: Array, img: Array
    ) -> tuple[Array, Array, Array] | None:
        """The photometric residuals ``r`` (M,) = target grey at the projection of the moved
        source point - the brightness model of its source grey, their Jacobians (M, n_all + 4)
        and the Huber weights (M,); points projecting outside, onto no depth or onto a depth
        ``depth_gate`` away (occluded) are left out. ``Pa`` (K, 3): the corrected points
        ``act`` (K,)."""
        Q = np.exp(log_s) * (Pa @ R.T) + t
        z = Q[:, 2]
        with np.errstate(divide="ignore", invalid="ignore"):
            u = fx * Q[:, 0] / z + cx
            v = fy * Q[:, 1] / z + cy
        keep = (z > 0) & (u >= 1) & (u < W - 2) & (v >= 1) & (v < H - 2)
        idx = np.flatnonzero(keep)
        zt = fill_z[np.rint(v[idx]).astype(np.intp) * W + np.rint(u[idx]).astype(np.intp)]
        idx = idx[(zt > 0) & (np.abs(zt - z[idx]) < cfg.depth_gate)]
        if len(idx) < n_all + 4:
            return None
        s_ = _bilinear(img, u[idx], v[idx])
        Qi, zi, src = Q[idx], z[idx], act[idx]
        c, x_, y_ = cg[src], xs_f[src], ys_f[src]
        r = s_[:, 0] - ((1.0 + bright[0]) * c + bright[1] + bright[2] * x_ + bright[3] * y_)
        # d(grey)/dQ = grad I . d(pi)/dQ
        gx, gy = s_[:, 1] * fx / zi, s_[:, 2] * fy / zi
        gq = np.column_stack([gx, gy, -(gx * Qi[:, 0] + gy * Qi[:, 1]) / zi])
        J = np.zeros((len(idx), n_all + 4))
        chain(J, Qi, gq, Pa[idx, 2], Xd[src])
        J[:, n_all:] = -np.column_stack([c, np.ones(len(idx)), x_, y_])
        assert cfg.photometric_sigma is not None
        sig = cfg.photometric_sigma
        if cfg.photometric_scale_mads is not None:  # the residuals' robust SD, 1.4826 MAD
            mad = float(np.median(np.abs(r - np.median(r))))
            sig = max(sig, cfg.photometric_scale_mads * 1.4826 * mad)
        return r, J, robust_weights(r, sig, kernel_now)

    def solve_round(act: Array, ph: tuple[Array, Array] | None = None, iters: int = 0) -> int:
        """Gauss-Newton on the source points ``act`` from the current estimate (updates
        ``R, t, log_s, disp`` and, with the photometric data ``ph`` = (source grey (N,),
        target [grey, d/du, d/dv] (H, W, 3)), ``bright``); the number of iterations taken."""
        nonlocal R, t, log_s, disp, bright
        n_x = n_all + (4 if ph is not None else 0)
        k = 0
        while k < (iters or cfg.iterations):
            k += 1
            Pa = corrected(disp, act)
            Q, n, r, rows = associate(R, t, log_s, Pa)
            if len(r) < max(cfg.min_inliers, n_all):
                break
            w = robust_weights(r, cfg.huber, kernel_now if ph is not None else cfg.kernel)
            J = np.zeros((len(r), n_x))
            chain(J, Q, n, Pa[rows, 2], Xd[act[rows]])
            Jw = J * w[:, None]
            A = Jw.T @ J
            b = -Jw.T @ r
            if ph is not None:
                pr = photometric(Pa, act, *ph)
                if pr is None:
                    break
                rp, Jp, wp = pr
                # weighed against the point-to-plane residuals: (c / sigma_I)^2
                lam = (cfg.huber / cfg.photometric_sigma) ** 2  # type: ignore[operator]
                Jpw = Jp * (lam * wp)[:, None]
                A += Jpw.T @ Jp
                b -= Jpw.T @ rp
            # priors: (c / sigma)^2 (x - 0)^2 per parameter, c the residual scale (m)
            for j, sd, val in prior_terms:
                A[j, j] += (cfg.huber / sd) ** 2
                b[j] -= (cfg.huber / sd) ** 2 * val()
            dx = np.linalg.solve(A + 1e-12 * np.eye(n_x), b)
            dT = exp_se3(dx[:6])
            R, t = dT[:3, :3] @ R, dT[:3, :3] @ t + dT[:3, 3]
            if cfg.estimate_scale:
                log_s += float(dx[6])
            if n_disp:
                disp = disp + dx[n_par:n_all]
            if ph is not None:
                bright = bright + dx[n_all:]
            if np.linalg.norm(dx[:n_par]) < cfg.tolerance and (
                not n_disp or np.max(np.abs(dx[n_par:n_all])) < 1e-4
            ):
                break
        return k

    def rho(r: Array, c: float, kernel: str) -> Array:
        """The robust loss whose IRLS weights :func:`robust_weights` gives."""
        a = np.abs(r)
        if kernel == "huber":
            return np.where(a <= c, 0.5 * a * a, c * a - 0.5 * c * c)
        return 0.5 * a * a / (1.0 + (a / c) ** 2)

    def objective(act: Array, ph: tuple[Array, Array]) -> float:
        """The joint pass's objective at the current estimate (units of m^2 like the
        point-to-plane term): robust losses of both terms, a point without a residual
        (unassociated, gated, occluded) counted at the kernel's saturation ``c^2 / 2``
        (``c`` = ``huber``; the redescending kernel's limit), and the priors."""
        Pa = corrected(disp, act)
        _, _, r, _ = associate(R, t, log_s, Pa)
        c = cfg.huber
        f = float(np.sum(rho(r, c, kernel_now))) + 0.5 * c * c * (len(act) - len(r))
        pr = photometric(Pa, act, *ph)
        n_p = 0
        if pr is not None:
            sig = cfg.photometric_sigma
            assert sig is not None
            lam = (c / sig) ** 2
            f += lam * float(np.sum(rho(pr[0], sig, kernel_now)))
            n_p = len(pr[0])
        f += 0.5 * c * c * (len(act) - n_p)
        for _, sd, val in prior_terms:
            f += 0.5 * (c / sd) ** 2 * float(val()) ** 2
        return f

    act = np.arange(len(P))
    k = 0 if photo is not None and not cfg.photometric_depth_pass else solve_round(act)
    if photo is not None and src_grey is not None and grey_all is not None:
        # beyond the depth: the colour image pins what the depth cannot tell from a drift of
        # the disparity (a rotation about the scene; module docstring, "Photometric")
        t_ph = time.perf_counter()
        act_ph = act[:: int(np.ceil(len(act) / cfg.photometric_points))]
        levels = []  # (blur SD, photometric data) coarse to fine
        sds = cfg.photometric_blur_px
        keep = np.arange(0, len(P_all), stride)  # P = P_all[keep]
        greys = _source_grey_levels(P_all, grey_all, intrinsics, sds, keep)
        for sd, cg in zip(sds, greys, strict=True):
            img = ndimage.gaussian_filter(photo[1], sd) if sd > 0 else photo[1]
            gv, gu = np.gradient(img)
            levels.append((cg, np.stack([img, gu, gv], axis=-1)))

        def run_levels(graduated: bool) -> float:
            """The coarse-to-fine joint pass from the current estimate; its objective at the
            finest level. ``graduated``: Huber on every level but the finest (convex: a
            start several mrad off still finds its way), else the kernel throughout."""
            nonlocal k, kernel_now
            for level, ph in enumerate(levels):
                last = level == len(levels) - 1
                kernel_now = cfg.photometric_kernel if last or not graduated else "huber"
                k += solve_round(act_ph, ph, cfg.photometric_iterations)
            return objective(act_ph, levels[-1])

        start = (R.copy(), t.copy(), log_s, disp.copy(), bright.copy())
        best = (run_levels(False), R, t, log_s, disp, bright)
        if cfg.photometric_graduated:
            # a second start, graduated; the two local minima of one objective: keep the
            # lower (the redescending kernel from the depth pass keeps a changed region
            # out; the graduated pass escapes a depth pass that the drift led astray)
            R, t, log_s, disp, bright = (x.copy() if hasattr(x, "copy") else x for x in start)
            cost = run_levels(True)
            stages["photometric_costs"] = [best[0], cost]
            if cost < best[0]:
                best = (cost, R, t, log_s, disp, bright)
        _, R, t, log_s, disp, bright = best
        stages["photometric_s"] = time.perf_counter() - t_ph
        stages["brightness"] = [float(x) for x in bright]
    Pc = corrected(disp)
    Q, n, r, _ = associate(R, t, log_s, Pc)
    if n_disp:
        stages["disparity_px"] = [float(x) for x in disp]
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = R, t
    scale = float(np.exp(log_s))
    # the relative depth change the estimate describes at the source's median depth z_m:
    # the disparity offset moves it by 1 / (1 + z_m a / (f b)), the scale by s (s and a
    # trade against each other over a shallow depth range; their product does not)
    z_m = float(np.median(P[:, 2])) if len(P) else 0.0
    stages["effective_scale"] = scale / (1.0 + z_m * disp[0] / fb) if n_disp else scale
    n_in = len(r)
    frac = n_in / max(len(P), 1)
    rmse = float(np.sqrt(np.mean(r**2))) if n_in else float("inf")
    c = Pc.mean(axis=0)
    shift = float(np.linalg.norm((R - T0[:3, :3]) @ c + t - T0[:3, 3]))
    dR = R @ T0[:3, :3].T
    rot = float(np.degrees(np.arccos(np.clip((np.trace(dR) - 1) / 2, -1.0, 1.0))))
    stages.update(shift_m=shift, rotation_deg=rot)
    lam = float("nan")
    if n_in >= 7:
        sub = slice(None, None, max(1, n_in // 5000))
        lam = float(np.linalg.eigvalsh(information_matrix(Q[sub], n[sub], None, 1.0))[0])

    def result(ok: bool, reason: str = "") -> ProjectiveResult:
        return ProjectiveResult(
            T, scale, rmse, n_in, frac, lam, ok, reason, time.perf_counter() - t0, k, stages
        )

    if n_in < cfg.min_inliers or frac < cfg.min_inlier_fraction:
        return result(
            False,
            f"too few projective correspondences: {n_in} ({frac:.2f} of the source; need "
            f"{cfg.min_inliers} and {cfg.min_inlier_fraction})",
        )
    max_rmse = cfg.max_rmse
    if cfg.rmse_gate == "adaptive" and n_in:
        z_med = float(np.median(Q[:, 2]))
        max_rmse = max(max_rmse, cfg.rmse_margin * np.sqrt(2.0) * cfg.depth_noise_k * z_med**2)
    stages["max_rmse"] = max_rmse
    if rmse > max_rmse:
        return result(False, f"inlier RMSE {rmse * 1e3:.2f} mm > {max_rmse * 1e3:.2f} mm")
    if abs(stages["effective_scale"] - 1.0) > cfg.max_scale_error:
        return result(
            False,
            f"depth scale {stages['effective_scale']:.4f} beyond 1 +- {cfg.max_scale_error}",
        )
    if n_disp and not np.all(np.abs(disp) <= cfg.max_disparity_error):
        return result(
            False,
            f"disparity drift {np.round(disp, 3).tolist()} px beyond "
            f"+-{cfg.max_disparity_error} px",
        )
    if shift > cfg.max_shift or rot > cfg.max_rotation_deg:
        return result(
            False,
            f"refinement moved {shift * 1e3:.1f} mm / {rot:.2f} deg from the initial pose "
            f"(limits {cfg.max_shift * 1e3:.0f} mm / {cfg.max_rotation_deg:.1f} deg)",
        )
    if not lam >= cfg.min_information:
        return result(
            False,
            f"degenerate geometry for point-to-plane refinement (information {lam:.2e} < "
            f"{cfg.min_information:.1e})",
        )
    return result(True)
