"""Is the accepted pose the only one that fits? The competing-pose check (issue 34 item 4).

Why wrong poses passed the other checks: a wrong pose of a repeated structure (a row of
like objects one period off) or of a scene that slides along one axis (a corridor, a counter
along a wall) fits as well as the true one: fitness, inlier RMSE and colour correlation are
those of a correct fit. The degeneracy test (:func:`~mmpa.registration.checks.
min_information`) runs at the finest scale, on normals estimated from 8 neighbours of 1 cm
voxels: their noise gives a direction that nothing constrains an information of ~0.03-0.05,
fifteen times ``min_information`` (a corridor: 0.029 at 1 cm, 0.0011 at 2 cm). And the
Hessian is local: it cannot see a second minimum one period away, nor one that FGR's start
missed (a real desk pair: FGR 40-65 mm off, ICP stops 24 mm off at fitness 0.52 where the
true pose fits 0.73).

The check (after every other check passed) does two things:

1. the degeneracy test again at the first (coarsest, 2 cm) ICP scale, whose normals average
   the noise out (``stages["coarse_information"]``; refused below
   ``coarse_min_information``, 0.01: the real desk's pairs measure 0.022-0.09 there, the
   synthetic corridor 0.001-0.004);
2. it looks for the competitor. The fine stage's point-to-plane ICP is re-run from starts
   that a competing minimum would attract: ``T`` moved by ``+-ambiguity_shift`` (m) along
   the ``ambiguity_directions`` weakest eigenvectors of the coarse information (twist
   ``[w L, v]`` about the correspondences' centroid ``c``, rotations scaled by their RMS
   radius ``L``: the start is ``exp(shift w / L)`` about ``c`` followed by ``shift v``), and,
   with the global stage's mutual FPFH matches ``(p_i, q_i)``, ``T``'s rotation with the
   ``ambiguity_modes`` translations ``t = q_i - R p_i`` most voted by the matches (a vote: the
   matches within ``coarse_voxel``) away from ``T``'s own: the matches of a repeated
   structure vote for each copy.

Each start ends at a pose ``T_k``; it is a competitor when the RMS displacement of the
source's finest points between ``T_k`` and ``T`` exceeds ``ambiguity_distance`` (m, beyond
the registration's own scatter) and, with colour on both sides, its colours correlate
(``min_color_correlation``: else the texture tells the two apart). Fitness cannot judge the
two: the planes that both poses align (the table, the walls) dominate it, and a pose one
period off can see *more* overlap than the true one. What tells them apart are the points
that only one of them explains (within the finest ICP gate of a target point,
:func:`explained`): ``n_T`` explained by ``T`` alone, ``n_k`` by ``T_k`` alone. A competitor
with ``n_T < ambiguity_replace_ratio n_k`` is the better pose and replaces ``T`` (which must
then pass every check and face its own competitors, once); one with
``n_k >= ambiguity_rival_ratio n_T`` makes the pose ambiguous: refused.
"""

from __future__ import annotations

import time
from typing import Any, NamedTuple

import numpy as np
from scipy.spatial import cKDTree

from mmpa.core.geometry import Array
from mmpa.registration.checks import color_correlation, information_matrix, min_information
from mmpa.registration.config import RegistrationConfig
from mmpa.registration.icp import icp
from mmpa.registration.preprocess import Prepared

__all__ = [
    "Competitor",
    "competitors",
    "explained",
    "rms_displacement",
    "translation_modes",
    "weak_starts",
]


class Competitor(NamedTuple):
    """A pose ICP reached from ``start``: ``T`` (4, 4),
    its ``fitness`` (the share of the source's finest points it explains), its RMS
    ``distance`` (m) from the accepted pose over the source's finest points, the colour
    correlation of the points it explains with their nearest target points
    (:func:`~mmpa.registration.checks.color_correlation`; ``inf`` without colour), and how
    many source points it explains that the accepted pose does not (``only_this``) and the
    other way round (``only_accepted``), by :func:`explained` at the finest ICP gate."""

    start: str
    T: Array
    fitness: float
    distance: float
    color: float
    only_this: int
    only_accepted: int


def explained(tree: cKDTree, points: Array, T: Array, gate: float) -> tuple[Array, Array]:
    """Which ``points`` (N, 3) lie within ``gate`` (m) of a target point under ``T``
    (``tree`` over the target's points), the inliers that make a pose's fitness, and the
    index of each one's nearest target point (``tree.n`` where none)."""
    d, j = tree.query(points @ T[:3, :3].T + T[:3, 3], distance_upper_bound=gate)
    return np.isfinite(d), j


def rms_displacement(T_a: Array, T_b: Array, points: Array) -> float:
    """``sqrt(mean_i |T_a p_i - T_b p_i|^2)`` (m) over ``points`` (N, 3)."""
    d = points @ (T_a[:3, :3] - T_b[:3, :3]).T + (T_a[:3, 3] - T_b[:3, 3])
    return float(np.sqrt(np.einsum("ij,ij->i", d, d).mean()))


def _rotation(w: Array) -> Array:
    """Rodrigues: the rotation matrix of the rotation vector ``w`` (rad)."""
    a = float(np.linalg.norm(w))
    if a < 1e-12:
        return np.eye(3)
    k = w / a
    K = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    return np.eye(3) + np.sin(a) * K + (1 - np.cos(a)) * K @ K


def weak_starts(
    src_points: Array, tgt_normals: Array, T: Array, shift: float, n_dirs: int
) -> list[tuple[str, Array]]:
    """The starts ``T`` moved by ``+-shift`` along the ``n_dirs`` weakest eigenvectors of the
    geometric information (module docstring); ``src_points`` (N, 3) the transformed source
    points of the inlier pairs, ``tgt_normals`` (N, 3) their targets' normals."""
    H = information_matrix(src_points, tgt_normals, None, 1.0)
    _, V = np.linalg.eigh(H)
    c = src_points.mean(axis=0)
    L = max(float(np.sqrt(((src_points - c) ** 2).sum(axis=1).mean())), 1e-9)
    out = []
    for j in range(n_dirs):
        for sign, name in ((1.0, "+"), (-1.0, "-")):
            e = sign * shift * V[:, j]
            R = _rotation(e[:3] / L)
            D = np.eye(4)
            D[:3, :3] = R
            D[:3, 3] = c - R @ c + e[3:]
            out.append((f"weak{j}{name}", D @ T))
    return out


def translation_modes(
    p_src: Array, p_tgt: Array, matches: Array, T: Array, radius: float, n_modes: int
) -> list[tuple[str, Array]]:
    """``T``'s rotation with the ``n_modes`` translations most voted by the ``matches``
    (K, 2) between ``p_src`` and ``p_tgt`` (module docstring), each more than ``2 radius``
    from ``T``'s translation and from the modes before it, with at least 3 votes."""
    m = np.asarray(matches, dtype=np.int64).reshape(-1, 2)
    if len(m) < 3:
        return []
    R = T[:3, :3]
    t = p_tgt[m[:, 1]] - p_src[m[:, 0]] @ R.T
    votes = np.array([len(x) for x in cKDTree(t).query_ball_point(t, radius)])
    alive = np.linalg.norm(t - T[:3, 3], axis=1) > 2 * radius
    out = []
    while len(out) < n_modes and alive.any():
        i = int(np.argmax(np.where(alive, votes, -1)))
        if votes[i] < 3:
            break
        S = T.copy()
        S[:3, 3] = t[i]
        out.append((f"mode{len(out)}({votes[i]} votes)", S))
        alive &= np.linalg.norm(t - t[i], axis=1) > 2 * radius
    return out


def competitors(
    src: Prepared,
    tgt: Prepared,
    T: Array,
    cfg: RegistrationConfig,
    matches: Array | None,
    stages: dict[str, Any],
) -> list[Competitor]:
    """ICP (point-to-plane, ``cfg.scales``) from every start of the module docstring around
    the accepted ``T``, ``matches`` the global stage's mutual FPFH matches (None: no modes).
    The weak directions come from the information at the first (coarsest) ICP scale: the
    normals of 1 cm voxels are noisy enough to hide a free direction (a corridor: 0.047 at
    1 cm where 2 cm gives 0.001 along its axis). Returns the moved starts along the weak
    directions themselves and every end pose, each compared with ``T``."""
    t0 = time.perf_counter()
    fine, first = cfg.scales[-1], cfg.scales[0]
    a, b = src.levels[fine.voxel], tgt.with_normals(fine.voxel, cfg)
    pts = np.asarray(a.points)
    a0, b0 = np.asarray(src.levels[first.voxel].points), tgt.with_normals(first.voxel, cfg)
    ok0, j0 = explained(cKDTree(np.asarray(b0.points)), a0, T, first.max_distance)
    step = max(1, int(np.ceil(ok0.sum() / cfg.degeneracy_max_points)))
    s = (a0[ok0] @ T[:3, :3].T + T[:3, 3])[::step]
    starts = []
    if len(s) >= 6:
        n = np.asarray(b0.normals)[j0[ok0]][::step]
        starts = weak_starts(s, n, T, cfg.ambiguity_shift, cfg.ambiguity_directions)
    corr0 = np.column_stack([np.flatnonzero(ok0), j0[ok0]])
    colored = src.colored and tgt.colored
    coarse_cfg = cfg.model_copy(update={"min_information": cfg.coarse_min_information})
    lam, weak = min_information(src, tgt, T, corr0, first, colored, coarse_cfg)
    stages["coarse_information"], stages["coarse_weak_direction"] = lam, weak
    if matches is not None and cfg.ambiguity_modes > 0:
        starts += translation_modes(
            np.asarray(src.coarse.points),
            np.asarray(tgt.coarse.points),
            matches,
            T,
            cfg.coarse_voxel,
            cfg.ambiguity_modes,
        )
    tree = cKDTree(np.asarray(b.points))
    ok_T, _ = explained(tree, pts, T, fine.max_distance)
    ends = [(name, icp(src, tgt, S, cfg.scales, False, cfg, {})[0]) for name, S in starts]
    out = []
    for name, Tk in ends:
        ok_k, j = explained(tree, pts, Tk, fine.max_distance)
        rho = float("inf")
        if colored and ok_k.any():
            rho = color_correlation(
                np.asarray(a.colors)[ok_k],
                np.asarray(b.colors)[j[ok_k]],
                cfg.color_check_min_std,
                np.asarray(b.points)[j[ok_k]],
            )
        out.append(
            Competitor(
                name,
                Tk,
                float(ok_k.mean()),
                rms_displacement(Tk, T, pts),
                rho,
                int(np.count_nonzero(ok_k & ~ok_T)),
                int(np.count_nonzero(ok_T & ~ok_k)),
            )
        )
    stages["ambiguity_s"] = stages.get("ambiguity_s", 0.0) + time.perf_counter() - t0
    return out
