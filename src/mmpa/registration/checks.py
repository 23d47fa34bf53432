"""Failure detection of the registration (paper 000 §3.2.2 II, beyond the paper): the checks
that decide ``Registration.ok`` besides fitness and correspondences.

- :func:`rmse_gate`: the inlier-RMSE limit (m) from the clouds' sampling and depth noise;
- :func:`information_matrix` and :func:`min_information`: degeneracy. With the linearised
  residual rows ``J_G = [((s - c) x n)/L, n]`` and ``J_C = [((s - c) x d)/L, d]`` (twist
  about the centroid ``c`` with rotations scaled by the cloud radius ``L``; ``d`` the
  tangent-plane colour gradient, Park et al. 2017 eq. 10), the information
  ``H = (lambda sum J_G^T J_G + (1 - lambda) sum J_C^T J_C) / N`` must have its smallest
  eigenvalue above ``min_information``: a single plane of one color leaves three
  directions with ``H`` ~ 0 (two in-plane translations, the rotation about the normal);
  texture on the plane fills them through ``d``;
- :func:`color_correlation`: the intensities of corresponding points must correlate (given
  an affine function of the position: exposure and a lighting gradient do not count), else
  a geometric fit along a repeated structure put different colors on top of each other;
- :func:`centroid_motion`: how far the fine pose moved from the coarse (or given) one.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

from mmpa.core.errors import InvalidInputError
from mmpa.core.geometry import Array
from mmpa.registration.config import IcpScale, RegistrationConfig
from mmpa.registration.preprocess import Prepared

__all__ = [
    "centroid_motion",
    "color_correlation",
    "information_matrix",
    "min_information",
    "rmse_gate",
]


def centroid_motion(T_a: Array, T_b: Array, c: Array) -> tuple[float, float]:
    """Displacement (m) of point ``c`` and rotation angle (deg) between two poses."""
    d = float(np.linalg.norm((T_a[:3, :3] - T_b[:3, :3]) @ c + T_a[:3, 3] - T_b[:3, 3]))
    R = T_a[:3, :3] @ T_b[:3, :3].T
    ang = float(np.degrees(np.arccos(np.clip((np.trace(R) - 1) / 2, -1.0, 1.0))))
    return d, ang


def _color_gradients(
    pts: Array, normals: Array, intensity: Array, idx: Array, radius: float, k: int
) -> Array:
    """Park et al. 2017 eq. 10: the tangent-plane gradient ``d_q`` of the color intensity at
    the points ``idx`` (least squares over neighbours within ``radius``, with ``d . n = 0``)."""
    tree = cKDTree(pts)
    dist, nb = tree.query(pts[idx], k=k, distance_upper_bound=radius)
    valid = np.isfinite(dist)
    nb = np.where(valid, nb, idx[:, None])
    A = pts[nb] - pts[idx][:, None, :]  # (M, k, 3)
    b = intensity[nb] - intensity[idx][:, None]  # (M, k)
    w = valid.astype(float)
    n = normals[idx]
    kk = w.sum(axis=1)[:, None, None]
    AtA = np.einsum("mki,mkj,mk->mij", A, A, w) + kk * np.einsum("mi,mj->mij", n, n)
    Atb = np.einsum("mki,mk,mk->mi", A, b, w)
    AtA += 1e-12 * np.eye(3)
    return np.linalg.solve(AtA, Atb[..., None])[..., 0]


def information_matrix(
    src_points: Array,
    tgt_normals: Array,
    color_gradients: Array | None = None,
    lambda_geometric: float = 0.968,
) -> Array:
    """The per-correspondence 6x6 Gauss-Newton information of the (colored) ICP objective.

    ``src_points`` (N, 3) m: transformed source points of the inlier pairs; ``tgt_normals``
    (N, 3) unit normals of their targets; ``color_gradients`` (N, 3) intensity/m, or ``None``
    for point-to-plane ICP. The twist is ``[w, v]`` about the centroid ``c`` of the points with
    rotations scaled by the RMS radius ``L``: rows ``J_G = [((s - c) x n)/L, n]``,
    ``J_C = [((s - c) x d)/L, d]``; returns ``(lambda J_G^T J_G + (1 - lambda) J_C^T J_C) / N``
    (dimensionless for the geometric part: 1 means every pair fully constrains a direction).
    """
    s = np.asarray(src_points, float)
    c = s.mean(axis=0)
    r = s - c
    L = max(float(np.sqrt((r**2).sum(axis=1).mean())), 1e-9)
    J = np.hstack([np.cross(r, tgt_normals) / L, tgt_normals])
    H = lambda_geometric * J.T @ J
    if color_gradients is not None:
        Jc = np.hstack([np.cross(r, color_gradients) / L, color_gradients])
        H = H + (1.0 - lambda_geometric) * Jc.T @ Jc
    return H / max(len(s), 1)


def rmse_gate(src: Prepared, tgt: Prepared, cfg: RegistrationConfig) -> float:
    """The inlier-RMSE limit (m) of a registration of ``src`` onto ``tgt``.

    ``cfg.rmse_gate == "fixed"``: ``cfg.max_rmse``. ``"adaptive"``: the inlier RMSE of a
    correct fit between two voxel clouds is the distance from a source voxel to the nearest
    target voxel, made of the sampling of the two clouds and of the depth noise,
    ``e^2 = (a s)^2 + 2 sigma_z^2`` with ``s`` the larger RMS nearest-neighbour spacing of
    the two finest levels (measured by ``prepare``: sparser where the depth image has holes),
    ``a = rmse_spacing_factor`` and ``sigma_z = depth_noise_k z^2`` at the larger median depth
    ``z`` of the two clouds (structured-light / stereo noise); the limit is
    ``max(max_rmse, rmse_margin * e)``, capped at ``rmse_max_fraction`` of the finest ICP
    gate (inliers are within that gate: a limit near it tests nothing).
    """
    if cfg.rmse_gate == "fixed":
        return cfg.max_rmse
    s = max(src.stats.get("spacing", 0.0), tgt.stats.get("spacing", 0.0))
    z = max(src.stats.get("median_depth", 0.0), tgt.stats.get("median_depth", 0.0))
    sigma = cfg.depth_noise_k * z * z
    e = float(np.hypot(cfg.rmse_spacing_factor * s, np.sqrt(2.0) * sigma))
    cap = cfg.rmse_max_fraction * min(sc.max_distance for sc in (*cfg.scales, *cfg.init_scales))
    return float(min(max(cfg.max_rmse, cfg.rmse_margin * e), cap))


def color_correlation(
    colors_s: Array, colors_t: Array, min_std: float = 0.02, points: Array | None = None
) -> float:
    """Pearson correlation of the intensities (mean of RGB in [0, 1]) of corresponding
    points, ``colors_s`` and ``colors_t`` (N, 3), row i of one matching row i of the other.

    ``rho = cov(I_s, I_t) / (std(I_s) std(I_t))``, invariant to ``I -> a I + b`` on either
    side (a change of exposure). With ``points`` (N, 3), the correspondences' positions (m,
    either cloud's frame), it is the partial correlation given an affine function of the
    position: both intensities are first replaced by their residuals of a least-squares fit
    on ``[1, x, y, z]``, so a lighting gradient across the scene (``I_t = a I_s + b + g . p``)
    leaves it unchanged too. Returns ``+inf`` (nothing to check) when either standard
    deviation is below ``min_std`` (an untextured scene) or there are fewer than 3 pairs
    (with ``points``: 6).
    """
    a = np.asarray(colors_s, float).reshape(-1, 3).mean(axis=1)
    b = np.asarray(colors_t, float).reshape(-1, 3).mean(axis=1)
    if len(a) != len(b):
        raise InvalidInputError(f"color_correlation: {len(a)} vs {len(b)} rows")
    if points is not None:
        p = np.asarray(points, float).reshape(-1, 3)
        if len(p) != len(a):
            raise InvalidInputError(f"color_correlation: {len(p)} points for {len(a)} rows")
        if len(a) < 6:
            return float("inf")
        X = np.column_stack([np.ones(len(p)), p - p.mean(axis=0)])
        coef, *_ = np.linalg.lstsq(X, np.column_stack([a, b]), rcond=None)
        a, b = (np.column_stack([a, b]) - X @ coef).T
    if len(a) < 3:
        return float("inf")
    sa, sb = float(a.std()), float(b.std())
    if sa < min_std or sb < min_std:
        return float("inf")
    return float(np.mean((a - a.mean()) * (b - b.mean())) / (sa * sb))


_DOF = ("rx", "ry", "rz", "x", "y", "z")


def _direction(v: Array) -> str:
    parts = [f"{v[i]:+.2f}{_DOF[i]}" for i in np.argsort(-np.abs(v))[:2] if abs(v[i]) > 0.2]
    return "[" + " ".join(parts) + "] (camera frame, twist about the centroid)"


def min_information(
    src: Prepared,
    tgt: Prepared,
    T: Array,
    corr: Array,
    sc: IcpScale,
    colored: bool,
    cfg: RegistrationConfig,
) -> tuple[float, str]:
    """Smallest eigenvalue (and its direction) of :func:`information_matrix` at ``T``."""
    if len(corr) > cfg.degeneracy_max_points:
        corr = corr[:: int(np.ceil(len(corr) / cfg.degeneracy_max_points))]
    a, b = src.levels[sc.voxel], tgt.with_normals(sc.voxel, cfg)
    s = np.asarray(a.points)[corr[:, 0]] @ T[:3, :3].T + T[:3, 3]
    n_t = np.asarray(b.normals)[corr[:, 1]]
    lam = cfg.lambda_geometric
    w, V = np.linalg.eigh(information_matrix(s, n_t, None, lam))
    if w[0] >= cfg.min_information or not colored:
        return float(w[0]), _direction(V[:, 0])
    pts_t = np.asarray(b.points)
    intensity = np.asarray(b.colors).mean(axis=1)
    d = _color_gradients(
        pts_t,
        np.asarray(b.normals),
        intensity,
        corr[:, 1],
        cfg.normal_radius_factor * sc.voxel,
        min(cfg.normal_max_nn, 12),
    )
    d[np.linalg.norm(d, axis=1) < cfg.min_color_gradient] = 0.0
    w, V = np.linalg.eigh(information_matrix(s, n_t, d, lam))
    return float(w[0]), _direction(V[:, 0])
