"""The fine stage of the registration: multi-scale colored ICP (Park et al. 2017) and its
acceptance checks (paper 000 §3.2.2 II).

Per level (voxel m, correspondence gate m, iterations) it minimises
``E(T) = (1 - lambda) sum r_C^2 + lambda sum r_G^2`` with the geometric residual
``r_G = (T s - q) . n_q`` (point-to-plane) and the photometric residual
``r_C = C_q(f(T s)) - C(s)``, ``C_q`` the color of ``q`` extended linearly on its tangent
plane by the gradient ``d_q`` and ``f`` the projection on that plane; lambda = 0.968 (Open3D's
``registration_colored_icp``). Without color it is point-to-plane ICP (paper Table A.7
Ex A.0/B.0, footnote 14). The result, ``T_target_source``, is accepted only if it has enough
correspondences, fitness, an inlier RMSE below :func:`~mmpa.registration.checks.rmse_gate`,
stays near the coarse or given pose (or the feature matches vote for it), its colours
correlate and its information is not degenerate (:mod:`mmpa.registration.checks`).
"""

from __future__ import annotations

import re
import time
from collections.abc import Callable
from typing import Any, NamedTuple

import numpy as np
import open3d as o3d

from mmpa.core.geometry import Array
from mmpa.registration.checks import (
    centroid_motion,
    color_correlation,
    min_information,
    rmse_gate,
)
from mmpa.registration.config import IcpScale, RegistrationConfig
from mmpa.registration.preprocess import Prepared

__all__ = ["Fine", "fine_stage", "icp"]

_reg = o3d.pipelines.registration


def icp(
    src: Prepared,
    tgt: Prepared,
    T: Array,
    scales: tuple[IcpScale, ...],
    colored: bool,
    cfg: RegistrationConfig,
    stages: dict[str, Any],
    prefix: str = "",
) -> tuple[Array, Any, IcpScale]:
    est = (
        _reg.TransformationEstimationForColoredICP(lambda_geometric=cfg.lambda_geometric)
        if colored
        else _reg.TransformationEstimationPointToPlane()
    )
    res = None
    for i, sc in enumerate(scales):
        t0 = time.perf_counter()
        crit = _reg.ICPConvergenceCriteria(sc.relative, sc.relative, sc.max_iter)
        a, b = src.levels[sc.voxel], tgt.with_normals(sc.voxel, cfg)
        if colored:
            res = _reg.registration_colored_icp(a, b, sc.max_distance, T, est, crit)
        else:
            res = _reg.registration_icp(a, b, sc.max_distance, T, est, crit)
        T = np.asarray(res.transformation).copy()
        stages[f"{prefix}icp{i}_s"] = time.perf_counter() - t0
        stages[f"{prefix}icp{i}_fitness"] = float(res.fitness)
    return T, res, scales[-1]


class Fine(NamedTuple):
    T: Array
    ok: bool
    reason: str
    fitness: float
    rmse: float
    n: int
    information: float


def fine_stage(
    src: Prepared,
    tgt: Prepared,
    T0: Array,
    scales: tuple[IcpScale, ...],
    colored: bool,
    cfg: RegistrationConfig,
    stages: dict[str, Any],
    prefix: str,
    limits: tuple[float, float, str],
    init: Array | None,
    support: Callable[[Array], int] | None = None,
) -> Fine:
    """Multi-scale (colored or point-to-plane) ICP from ``T0`` and its acceptance checks."""
    try:
        T, res, last = icp(src, tgt, T0, scales, colored, cfg, stages, prefix)
    except RuntimeError as e:  # Open3D refuses e.g. clouds without enough neighbours
        return Fine(T0, False, f"fine stage failed: {_open3d_message(e)}", 0.0, np.inf, 0, 0.0)
    corr = np.asarray(res.correspondence_set)
    fit, rmse, n = float(res.fitness), float(res.inlier_rmse), len(corr)
    src_fine = np.asarray(src.levels[last.voxel].points)
    c = src_fine.mean(axis=0)
    shift, rot = centroid_motion(T, T0, c)
    stages["fine_shift_m"], stages["fine_rotation_deg"] = shift, rot
    max_shift, max_rot, what = limits

    def fail(reason: str, lam: float = 0.0) -> Fine:
        return Fine(T, False, reason, fit, rmse, n, lam)

    if n < cfg.min_correspondences:
        return fail(f"too few correspondences: {n} < {cfg.min_correspondences} (no overlap?)")
    if fit < cfg.min_fitness:
        return fail(f"low fitness {fit:.3f} < {cfg.min_fitness} (little overlap or wrong pose)")
    max_rmse = rmse_gate(src, tgt, cfg)
    stages["max_rmse"] = max_rmse
    if rmse > max_rmse:
        return fail(f"inlier RMSE {rmse * 1e3:.2f} mm > {max_rmse * 1e3:.2f} mm")
    moved = shift > max_shift or rot > max_rot
    if moved and support is not None:
        # the feature matches vote: how many agree with the fine pose, how many with FGR's
        n_fine, n_coarse = support(T), support(T0)
        stages[f"{prefix}fine_support"], stages[f"{prefix}coarse_support"] = n_fine, n_coarse
        need = max(cfg.min_fine_support_ratio * n_coarse, cfg.min_fine_support)
        if cfg.fine_motion_gate == "support" and n_fine >= need:
            moved = False
    if moved:
        return fail(
            f"fine stage moved {shift * 1e3:.1f} mm / {rot:.2f} deg from the "
            f"{what} pose (limits {max_shift * 1e3:.0f} mm / {max_rot:.1f} deg): "
            f"{what} pose rejected" + ("; register without init" if init is not None else "")
        )
    if src.colored and tgt.colored and cfg.min_color_correlation > 0:
        rho = color_correlation(
            np.asarray(src.levels[last.voxel].colors)[corr[:, 0]],
            np.asarray(tgt.levels[last.voxel].colors)[corr[:, 1]],
            cfg.color_check_min_std,
            np.asarray(tgt.levels[last.voxel].points)[corr[:, 1]],
        )
        stages[f"{prefix}color_correlation"] = rho
        if rho < cfg.min_color_correlation:
            return fail(
                f"photometric check failed: the intensities at the {n} correspondences "
                f"correlate {rho:.2f} < {cfg.min_color_correlation} (the geometry fits but "
                "the colors do not: a wrong pose along a repeated structure?)"
            )
    t1 = time.perf_counter()
    lam_min, weak = min_information(src, tgt, T, corr, last, colored, cfg)
    stages[f"{prefix}degeneracy_s"] = time.perf_counter() - t1
    if lam_min < cfg.min_information:
        method = "colored_icp" if colored else "point_to_plane_icp"
        return fail(
            f"degenerate geometry: the {method} objective does not "
            f"constrain the direction {weak} (information {lam_min:.2e} < "
            f"{cfg.min_information:.1e}; a single plane without texture?)",
            lam_min,
        )
    return Fine(T, True, "", fit, rmse, n, lam_min)


def _open3d_message(e: Exception) -> str:
    """Open3D's error text without terminal colors and C++ signatures."""
    msg = re.sub(r"\x1b\[[0-9;]*m", "", str(e)).strip()
    return msg.rsplit(": ", 1)[-1] if "open3d::" in msg else msg
