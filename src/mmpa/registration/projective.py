"""Projective point-to-plane refinement on an organized depth image (beyond the paper).

A close pose (IPE after convergence: the camera back within ``alpha`` of its taught pose) is
refined against the target at full resolution, as the organized depth image it came from
(KinectFusion's projective data association, Newcombe et al. 2011), free of the voxel
aliasing of :mod:`mmpa.registration.pipeline`'s fine stage. Frames: source points in the
source camera's optical frame, the target depth (m along the optical axis) in the target
camera's, ``T = T_target_source``; lengths in m, angles in rad, disparities in px.

- target vertex map ``V(u, v) = z(u, v) K^-1 [u, v, 1]^T`` and normal map
  ``N = normalize((V(u+r, v) - V(u-r, v)) x (V(u, v+r) - V(u, v-r)))`` over ``r`` pixels,
  invalid across depth jumps above ``max_depth_jump``; holes read the nearest valid pixel
  within ``hole_fill_px`` when at most ``hole_fill_max_valid`` of the pixels are valid
  (:mod:`~mmpa.registration.projective_maps`);
- each source point ``p`` maps to ``p' = s R p + t`` and is associated with the pixel it
  projects to, ``(u, v) = round(K p' / z')``: ``q = V(u, v)``, ``n = N(u, v)``;
- Gauss-Newton on ``E = sum_i w_i (n_i . (p'_i - q_i))^2``, robust weights of scale
  ``huber``, gate ``|r_i| < gate``; a left twist ``[v, w]`` gives ``J_i = [n_i, p'_i x n_i]``
  (and ``n_i . p'_i`` for ``log s``) (:mod:`~mmpa.registration.projective_solve`).

Scale (``estimate_scale``): depth scaled by ``s`` (a per-capture depth scale error) scales
every point about the camera centre, ``q = s R p + t``; the returned ``T`` is the rigid part.
Disparity drift (``disparity_model``, with the sensor's ``f b``): ``dd(x, y) = a + b_x x +
b_y y`` px over the normalized source coordinates moves a point along its ray,
``p(dd) = p / (1 + p_z dd / (f b))``, ``J_a = -(p_z(dd) / (f b)) n . (Q - t)``
(``stages["disparity_px"]``). The depth-scale gate (``max_scale_error``) is on
``s / (1 + z_m a / (f b))`` at the source's median depth ``z_m``
(``stages["effective_scale"]``).

Photometric (``source_colors`` and ``target_color``): a joint pass adds
``r_i = I(pi(Q_i)) - ((1 + g) c_i + o + o_x x_i + o_y y_i)`` (``I`` the target's grey image,
bilinear; ``g, o, o_x, o_y`` exposure and lighting gradient), ``J = [g_Q, Q x g_Q]`` with
``g_Q = grad I . dpi/dQ``, weighed ``(huber / photometric_sigma)^2``, kernel
``photometric_kernel`` (scale at least ``photometric_scale_mads`` robust SDs), coarse to fine
over ``photometric_blur_px``; two starts (the kernel throughout; graduated, Huber on the
coarse levels), the lower objective kept. Occluded points (``depth_gate``) are left out.

Refused (``ok=False`` and a reason) when too few points associate, the inlier RMSE is above
``max_rmse`` (``"adaptive"``: or ``rmse_margin sqrt(2) depth_noise_k z^2``), the depth scale or
drift is beyond its limit, the pose moved too far from ``init``, or the geometry is degenerate
(smallest eigenvalue of :func:`~mmpa.registration.checks.information_matrix` below
``min_information``). Measurements: docs/registration.md.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from mmpa.core.errors import InvalidInputError
from mmpa.core.geometry import Array
from mmpa.registration._blas import single_threaded_blas
from mmpa.registration.checks import information_matrix
from mmpa.registration.config import ProjectiveConfig
from mmpa.registration.projective_maps import (
    grey,
    normal_map,
    photometric_inputs,
    robust_weights,
    target_map,
    vertex_map,
)
from mmpa.registration.projective_solve import (
    Estimate,
    Problem,
    associate,
    corrected,
    photometric_pass,
    problem,
    solve_round,
)
from mmpa.robot.description import CameraIntrinsics

__all__ = [
    "ProjectiveConfig",
    "ProjectiveResult",
    "grey",
    "normal_map",
    "refine_projective",
    "robust_weights",
    "vertex_map",
]


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
        photo = photometric_inputs(source_points, source_colors, target_color, intrinsics)
    with single_threaded_blas():  # small products: a second thread only costs (see _blas)
        return _refine_projective(
            source_points, target_depth, intrinsics, init, cfg, disparity_fb, photo
        )


def _checked_source(
    source_points: Array, init: Array, src_grey: Array | None, max_points: int
) -> tuple[Array, Array, Array | None, Array, Array | None, int]:
    """The finite source points (N, 3), ``init`` as a checked (4, 4), the points' grey
    values, and the points before the uniform subsample to ``max_points`` (with their grey
    values and the stride)."""
    P = np.asarray(source_points, dtype=float)
    if P.ndim != 2 or P.shape[1] != 3:
        raise InvalidInputError(f"source points must be (N, 3), got {P.shape}")
    T0 = np.asarray(init, dtype=float)
    if T0.shape != (4, 4) or not np.isfinite(T0).all():
        raise InvalidInputError(f"init must be a finite 4x4 transform, got shape {T0.shape}")
    if not np.isfinite(P.sum()):  # one reduction; the per-row test only when needed
        fin = np.isfinite(P).all(axis=1)
        P = P[fin]
        src_grey = src_grey[fin] if src_grey is not None else None
    P_all, grey_all, stride = P, src_grey, 1
    if len(P) > max_points:
        stride = int(np.ceil(len(P) / max_points))
        P = P[::stride]
        src_grey = src_grey[::stride] if src_grey is not None else None
    return P, T0, src_grey, P_all, grey_all, stride


def _refine_projective(
    source_points: Array,
    target_depth: Array,
    intrinsics: CameraIntrinsics,
    init: Array,
    cfg: ProjectiveConfig | None,
    disparity_fb: float | None = None,
    photo: tuple[Array, Array] | None = None,
) -> ProjectiveResult:
    """The refinement (:func:`refine_projective`'s inputs checked, ``photo`` the source grey
    values and the target grey image): the depth pass, the photometric pass, the result."""
    cfg = cfg or ProjectiveConfig()
    if cfg.photometric_sigma is None:
        photo = None
    t0 = time.perf_counter()
    src_grey = photo[0] if photo is not None else None
    P, T0, src_grey, P_all, grey_all, stride = _checked_source(
        source_points, init, src_grey, cfg.max_points
    )
    tm = target_map(
        target_depth,
        intrinsics,
        cfg.normal_radius,
        cfg.max_depth_jump,
        cfg.hole_fill_px,
        cfg.hole_fill_max_valid,
    )
    stages: dict[str, Any] = {
        "maps_s": time.perf_counter() - t0,
        "n_source": len(P),
        "valid_pixel_fraction": tm.n_valid / (tm.H * tm.W),
    }
    pb = problem(P, cfg, intrinsics, disparity_fb, tm)
    est = Estimate(T0[:3, :3].copy(), T0[:3, 3].copy(), 0.0, np.zeros(pb.n_disp), np.zeros(4))
    act = np.arange(len(P))
    k = 0
    if not (photo is not None and not cfg.photometric_depth_pass):
        est, k = solve_round(pb, est, act)
    if photo is not None and src_grey is not None and grey_all is not None:
        # beyond the depth: the colour image pins what the depth cannot tell from a drift of
        # the disparity (a rotation about the scene; module docstring, "Photometric")
        est, k_ph = photometric_pass(
            pb, est, act, photo[1], P_all, grey_all, stride, intrinsics, stages
        )
        k += k_ph
    return _result(pb, est, T0, k, stages, t0)


def _result(
    pb: Problem, est: Estimate, T0: Array, k: int, stages: dict[str, Any], t0: float
) -> ProjectiveResult:
    """The result at the estimate ``est``: its last association over every source point,
    the diagnostics in ``stages`` and the acceptance checks (:func:`_refusal`)."""
    cfg, P, R, t, log_s, disp = pb.cfg, pb.P, est.R, est.t, est.log_s, est.disp
    Pc = corrected(pb, disp)
    Q, n, r, _ = associate(pb, R, t, log_s, Pc)
    if pb.n_disp:
        stages["disparity_px"] = [float(x) for x in disp]
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = R, t
    scale = float(np.exp(log_s))
    # the relative depth change the estimate describes at the source's median depth z_m:
    # the disparity offset moves it by 1 / (1 + z_m a / (f b)), the scale by s (s and a
    # trade against each other over a shallow depth range; their product does not)
    z_m = float(np.median(P[:, 2])) if len(P) else 0.0
    stages["effective_scale"] = scale / (1.0 + z_m * disp[0] / pb.fb) if pb.n_disp else scale
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
    reason = _refusal(cfg, pb.n_disp, disp, Q, n_in, frac, rmse, shift, rot, lam, stages)
    return ProjectiveResult(
        T, scale, rmse, n_in, frac, lam, not reason, reason, time.perf_counter() - t0, k, stages
    )


def _refusal(
    cfg: ProjectiveConfig,
    n_disp: int,
    disp: Array,
    Q: Array,
    n_in: int,
    frac: float,
    rmse: float,
    shift: float,
    rot: float,
    lam: float,
    stages: dict[str, Any],
) -> str:
    """Why the refinement is refused (the first check that fails), "" when accepted."""
    if n_in < cfg.min_inliers or frac < cfg.min_inlier_fraction:
        return (
            f"too few projective correspondences: {n_in} ({frac:.2f} of the source; need "
            f"{cfg.min_inliers} and {cfg.min_inlier_fraction})"
        )
    max_rmse = cfg.max_rmse
    if cfg.rmse_gate == "adaptive" and n_in:
        z_med = float(np.median(Q[:, 2]))
        max_rmse = max(max_rmse, cfg.rmse_margin * np.sqrt(2.0) * cfg.depth_noise_k * z_med**2)
    stages["max_rmse"] = max_rmse
    if rmse > max_rmse:
        return f"inlier RMSE {rmse * 1e3:.2f} mm > {max_rmse * 1e3:.2f} mm"
    if abs(stages["effective_scale"] - 1.0) > cfg.max_scale_error:
        return f"depth scale {stages['effective_scale']:.4f} beyond 1 +- {cfg.max_scale_error}"
    if n_disp and not np.all(np.abs(disp) <= cfg.max_disparity_error):
        return (
            f"disparity drift {np.round(disp, 3).tolist()} px beyond +-{cfg.max_disparity_error} px"
        )
    if shift > cfg.max_shift or rot > cfg.max_rotation_deg:
        return (
            f"refinement moved {shift * 1e3:.1f} mm / {rot:.2f} deg from the initial pose "
            f"(limits {cfg.max_shift * 1e3:.0f} mm / {cfg.max_rotation_deg:.1f} deg)"
        )
    if not lam >= cfg.min_information:
        return (
            f"degenerate geometry for point-to-plane refinement (information {lam:.2e} < "
            f"{cfg.min_information:.1e})"
        )
    return ""
