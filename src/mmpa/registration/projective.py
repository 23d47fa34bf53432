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
returned ``T`` is the rigid part ``[R, t]``.

The refinement is refused (``ok=False``, with a reason) when too few points associate, the
inlier RMSE is too large, the pose moves too far from ``init`` or the geometric objective is
degenerate (smallest eigenvalue of :func:`~mmpa.registration.pipeline.information_matrix` below
``min_information``: a plane, where only texture could fix the pose).
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from pydantic import BaseModel, ConfigDict, Field

from mmpa.errors import InvalidInputError
from mmpa.geometry import Array, exp_se3
from mmpa.registration._blas import single_threaded_blas
from mmpa.registration.pipeline import information_matrix
from mmpa.robot.description import CameraIntrinsics

__all__ = [
    "ProjectiveConfig",
    "ProjectiveResult",
    "normal_map",
    "refine_projective",
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
    gate: float = Field(default=0.005, gt=0)  # |point-to-plane residual| accepted
    depth_gate: float = Field(default=0.02, gt=0)  # |z' - z(u, v)| accepted (occlusions)
    huber: float = Field(default=0.001, gt=0)  # Huber scale of the residual weights
    estimate_scale: bool = True
    max_scale_error: float = Field(default=0.01, gt=0)  # |s - 1| accepted
    min_inliers: int = Field(default=2000, ge=7)
    min_inlier_fraction: float = Field(default=0.3, ge=0, le=1)
    max_rmse: float = Field(default=0.003, gt=0)
    max_shift: float = Field(default=0.01, gt=0)  # m of the source centroid from init
    max_rotation_deg: float = Field(default=2.0, gt=0)
    min_information: float = Field(default=2e-3, ge=0)


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
) -> ProjectiveResult:
    """Refine ``T_target_source`` by projective point-to-plane ICP (see the module docstring).

    ``source_points`` (N, 3) m in the source camera frame; ``target_depth`` (H, W) m along the
    target camera's optical axis (0 where invalid) with ``intrinsics``; ``init`` (4, 4) a pose
    close to the answer (within a few mm: the association is by projection, not search).
    """
    with single_threaded_blas():  # small products: a second thread only costs (see _blas)
        return _refine_projective(source_points, target_depth, intrinsics, init, cfg)


def _refine_projective(
    source_points: Array,
    target_depth: Array,
    intrinsics: CameraIntrinsics,
    init: Array,
    cfg: ProjectiveConfig | None,
) -> ProjectiveResult:
    cfg = cfg or ProjectiveConfig()
    t0 = time.perf_counter()
    P = np.asarray(source_points, dtype=float)
    if P.ndim != 2 or P.shape[1] != 3:
        raise InvalidInputError(f"source points must be (N, 3), got {P.shape}")
    T0 = np.asarray(init, dtype=float)
    if T0.shape != (4, 4) or not np.isfinite(T0).all():
        raise InvalidInputError(f"init must be a finite 4x4 transform, got shape {T0.shape}")
    if not np.isfinite(P.sum()):  # one reduction; the per-row test only when needed
        P = P[np.isfinite(P).all(axis=1)]
    if len(P) > cfg.max_points:
        P = P[:: int(np.ceil(len(P) / cfg.max_points))]
    z_img = np.asarray(target_depth, dtype=float)
    if z_img.shape != (intrinsics.height, intrinsics.width):
        raise InvalidInputError(
            f"depth {z_img.shape} does not match the intrinsics "
            f"{intrinsics.height}x{intrinsics.width}"
        )
    H, W = z_img.shape
    # depth image flattened, 0 where invalid; the vertex map V(u, v) = z (x_u, y_v, 1) is
    # evaluated only at the pixels used (x_u = (u - cx)/fx, y_v = (v - cy)/fy)
    zf = np.where(np.isfinite(z_img) & (z_img > 0), z_img, 0.0).ravel()
    rad = cfg.normal_radius
    fx, fy, cx, cy = intrinsics.fx, intrinsics.fy, intrinsics.cx, intrinsics.cy
    xu = (np.arange(W) - cx) / fx
    yv = (np.arange(H) - cy) / fy
    stages: dict[str, Any] = {"maps_s": time.perf_counter() - t0, "n_source": len(P)}

    R, t, log_s = T0[:3, :3].copy(), T0[:3, 3].copy(), 0.0
    n_par = 7 if cfg.estimate_scale else 6

    def associate(R: Array, t: Array, log_s: float) -> tuple[Array, Array, Array]:
        """Project the moved source into the target image; the inlier points ``Q`` (M, 3),
        the target normals ``n`` (M, 3) (:func:`normal_map`'s central differences, at the
        associated pixels only) and the point-to-plane residuals ``r`` (M,)."""
        Q = np.exp(log_s) * (P @ R.T) + t
        z = Q[:, 2]
        with np.errstate(divide="ignore", invalid="ignore"):
            u = np.rint(fx * Q[:, 0] / z + cx)
            v = np.rint(fy * Q[:, 1] / z + cy)
        inside = (z > 0) & (u >= rad) & (u < W - rad) & (v >= rad) & (v < H - rad)
        idx = np.flatnonzero(inside)
        ui, vi = u[idx].astype(np.intp), v[idx].astype(np.intp)
        pix = vi * W + ui
        zc = zf[pix]
        zl, zr, zu, zd = zf[pix - rad], zf[pix + rad], zf[pix - rad * W], zf[pix + rad * W]
        ok = zc > 0
        for zj in (zl, zr, zu, zd):
            ok &= (zj > 0) & (np.abs(zj - zc) < cfg.max_depth_jump)
        # dx = V(u+r, v) - V(u-r, v), dy = V(u, v+r) - V(u, v-r), n = dx x dy
        xc, yc = xu[ui], yv[vi]
        ax, ay, az = zr * xu[ui + rad] - zl * xu[ui - rad], (zr - zl) * yc, zr - zl
        bx, by, bz = (zd - zu) * xc, zd * yv[vi + rad] - zu * yv[vi - rad], zd - zu
        n = np.empty((len(idx), 3))
        n[:, 0] = ay * bz - az * by
        n[:, 1] = az * bx - ax * bz
        n[:, 2] = ax * by - ay * bx
        norm = np.sqrt(np.einsum("ij,ij->i", n, n))
        ok &= norm > 0
        Qi = Q[idx]
        # r = (Q - q) . n / |n| with q = V(u, v) = zc (xc, yc, 1)
        with np.errstate(divide="ignore", invalid="ignore"):
            r = (
                (Qi[:, 0] - zc * xc) * n[:, 0]
                + (Qi[:, 1] - zc * yc) * n[:, 1]
                + (Qi[:, 2] - zc) * n[:, 2]
            ) / norm
        keep = ok & (np.abs(r) < cfg.gate) & (np.abs(Qi[:, 2] - zc) < cfg.depth_gate)
        return Qi[keep], n[keep] / norm[keep, None], r[keep]

    k = 0
    while k < cfg.iterations:
        k += 1
        Q, n, r = associate(R, t, log_s)
        if len(r) < max(cfg.min_inliers, n_par):
            break
        a = np.abs(r)
        w = np.where(a <= cfg.huber, 1.0, cfg.huber / np.maximum(a, 1e-12))
        J = np.empty((len(r), n_par))
        J[:, :3] = n
        J[:, 3:6] = np.cross(Q, n)
        if cfg.estimate_scale:
            # d/d(log s) of s R p + t at the current estimate: s R p = Q - t
            J[:, 6] = np.einsum("ij,ij->i", Q - t, n)
        Jw = J * w[:, None]
        A = Jw.T @ J
        b = -Jw.T @ r
        dx = np.linalg.solve(A + 1e-12 * np.eye(n_par), b)
        dT = exp_se3(dx[:6])
        R, t = dT[:3, :3] @ R, dT[:3, :3] @ t + dT[:3, 3]
        if cfg.estimate_scale:
            log_s += float(dx[6])
        if np.linalg.norm(dx) < cfg.tolerance:
            break
    Q, n, r = associate(R, t, log_s)
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = R, t
    scale = float(np.exp(log_s))
    n_in = len(r)
    frac = n_in / max(len(P), 1)
    rmse = float(np.sqrt(np.mean(r**2))) if n_in else float("inf")
    c = P.mean(axis=0)
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
    if rmse > cfg.max_rmse:
        return result(False, f"inlier RMSE {rmse * 1e3:.2f} mm > {cfg.max_rmse * 1e3:.2f} mm")
    if abs(scale - 1.0) > cfg.max_scale_error:
        return result(False, f"depth scale {scale:.4f} beyond 1 +- {cfg.max_scale_error}")
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
