"""Colored point cloud global registration (paper 000 §3.2.2 II): FPFH + FGR, then colored ICP.

Given a source cloud ``X_s`` and a target cloud ``X_t`` (both in their camera's optical frame,
metres), estimate ``T = T_target_source`` such that ``p_t = T p_s`` (paper eq. 3 with
``[dR_Ck, dt_Ck] = T`` when the taught cloud X_i(O) is the source and the current X_i(k) the
target). Stages:

1. ``prepare`` (once per cloud): crop ``z`` to ``[min_depth, max_depth]``, drop non-finite points,
   voxel-average at the finest ICP voxel, remove statistical outliers with one k-NN search
   (kept: it also gives that level's normals), build the voxel pyramid of the ICP schedule;
   the normals of every level (only the ICP target needs them; the finest from the kept
   search) and FPFH (Rusu 2009) at the coarse voxel are computed on first use and kept with
   the cloud (a taught cloud pays for them once, a source cloud never for its normals).
2. Coarse: Fast Global Registration (Zhou et al. 2016): mutual FPFH matches and the tuple test
   (:func:`fgr_correspondences`, vectorized: one matrix product instead of Open3D's k-d tree
   in 33 dimensions, ~2x faster), then FGR's scaled Geman-McClure objective
   ``sum rho(||q - T p||)`` (:func:`mmpa.registration.fgr.fgr_solve`: Open3D's solver
   vectorized, ~10x faster, same result to 1e-12).
3. Fine: multi-scale colored ICP (Park et al. 2017). Per level it minimises
   ``E(T) = (1 - lambda) sum r_C^2 + lambda sum r_G^2`` with the geometric residual
   ``r_G = (T s - q) . n_q`` (point-to-plane) and the photometric residual
   ``r_C = C_q(f(T s)) - C(s)``, ``C_q`` the color of ``q`` extended linearly on its tangent
   plane by the gradient ``d_q`` and ``f`` the projection on that plane; lambda = 0.968.
   Without color (a cloud with constant color) it is point-to-plane ICP (paper Table A.7
   Ex A.0/B.0, footnote 14). ``color_mode="auto"`` (default, beyond the paper) runs
   point-to-plane ICP first and colored ICP only when geometry alone is weak (information
   below ``geometric_min_information``) or rejected; ``"paper"`` always uses colored ICP when
   both clouds carry color.
4. Validation: the pose is returned with ``ok=False`` and a reason unless the clouds are large
   enough, the fine stage has enough inlier correspondences, fitness and RMSE pass, the fine
   pose stays near the coarse (or given) pose, and the objective constrains all six degrees of
   freedom: with the linearised residual rows ``J_G = [((s - c) x n)/L, n]`` and
   ``J_C = [((s - c) x d)/L, d]`` (twist about the centroid ``c`` with rotations scaled by the
   cloud radius ``L``), the information matrix
   ``H = (lambda sum J_G^T J_G + (1 - lambda) sum J_C^T J_C) / N`` must have its smallest
   eigenvalue above ``min_information``; with color on both sides, the intensities must
   correlate over the correspondences (:func:`color_correlation`, ``min_color_correlation``,
   given an affine function of the position, so that exposure and a lighting gradient do not
   count: a geometric fit along a repeated structure puts different colors on top of each
   other).
   A single plane of one color leaves three directions
   with ``H`` ~ 0 (two in-plane translations, the rotation about the normal); texture on the
   plane fills them through ``d``.
"""

from __future__ import annotations

import re
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any, NamedTuple

import numpy as np
import open3d as o3d
from scipy.spatial import cKDTree
from scipy.spatial.distance import cdist

from mmpa.core.errors import ConfigError, InvalidInputError
from mmpa.core.geometry import Array
from mmpa.registration._blas import open3d_threads, single_threaded_blas
from mmpa.registration.config import IcpScale, RegistrationConfig
from mmpa.registration.fgr import fgr_solve

__all__ = [
    "Prepared",
    "Registration",
    "color_correlation",
    "fgr_correspondences",
    "information_matrix",
    "prepare",
    "register",
]

_reg = o3d.pipelines.registration
_KD = o3d.geometry.KDTreeSearchParamHybrid


@dataclass(frozen=True)
class Registration:
    """Result of :func:`register`.

    ``T`` (4, 4) is ``T_target_source`` (``p_target = T p_source``, metres); ``fitness`` the
    inlier fraction of the source at the finest ICP scale; ``rmse`` the inlier RMSE (m) there;
    ``ok`` whether every acceptance check passed, else ``reason`` says which failed (``T`` is
    then the last estimate, for diagnostics only: never act on it); ``n_correspondences`` the
    inlier pairs of the finest scale; ``seconds`` the wall time of the call; ``stages`` the
    per-stage timings and diagnostics (``min_information``, ``coarse_shift``...).
    """

    T: Array
    fitness: float
    rmse: float
    ok: bool
    reason: str
    n_correspondences: int
    seconds: float
    stages: dict[str, Any] = field(default_factory=dict)


@dataclass(frozen=True, eq=False)
class Prepared:
    """A cloud cleaned and downsampled once by :func:`prepare`, reusable across calls.

    ``levels`` maps each ICP voxel size (m) to an Open3D cloud (with colors when ``colored``);
    ``coarse`` is the cloud at ``coarse_voxel``; ``colored`` whether the cloud carries color;
    ``reason`` is non-empty when the cloud is unusable (too few points, non-finite points with
    ``nan_policy="reject"``); ``stats`` holds counts and timings. Normals (needed only where
    the cloud is the ICP target, and on the coarse cloud for FPFH) and FPFH descriptors are
    computed on first use and kept: a taught cloud prepared once pays for them once.
    """

    levels: dict[float, o3d.geometry.PointCloud]
    coarse: o3d.geometry.PointCloud
    colored: bool
    reason: str
    key: tuple
    stats: dict[str, Any]
    _cache: dict[str, Any] = field(default_factory=dict, repr=False)

    @property
    def n_points(self) -> int:
        """Points at the finest voxel level."""
        return len(self.levels[min(self.levels)].points) if self.levels else 0

    def with_normals(self, voxel: float, cfg: RegistrationConfig) -> o3d.geometry.PointCloud:
        """The cloud of level ``voxel`` (or the coarse cloud when ``voxel`` is
        ``cfg.coarse_voxel``) with unit normals oriented to the camera, estimated on first use
        from ``cfg.normal_max_nn`` neighbours within ``cfg.normal_radius_factor * voxel``."""
        pc = self.levels.get(voxel)
        if pc is None:
            if voxel != cfg.coarse_voxel:
                raise ConfigError(f"no level of {voxel} m in this prepared cloud")
            pc = self.coarse
        done = self._cache.setdefault("normals", set())
        if voxel not in done:
            t0 = time.perf_counter()
            knn = self._cache.get("fine_knn")
            if knn is not None and knn[0] == voxel:  # from prepare's outlier search
                del self._cache["fine_knn"]  # used once: the normals are kept on the cloud
                pc.normals = o3d.utility.Vector3dVector(_knn_normals(*knn[1:], voxel, cfg))
            else:
                _normals(pc, voxel, cfg)
            done.add(voxel)
            self.stats["normals_s"] = self.stats.get("normals_s", 0.0) + time.perf_counter() - t0
        return pc

    def fpfh(self, cfg: RegistrationConfig) -> o3d.pipelines.registration.Feature:
        """FPFH descriptors (33-d) of :attr:`coarse`, computed on first use and cached."""
        if "fpfh" not in self._cache:
            coarse = self.with_normals(cfg.coarse_voxel, cfg)
            t0 = time.perf_counter()
            r = cfg.fpfh_radius_factor * cfg.coarse_voxel
            self._cache["fpfh"] = _reg.compute_fpfh_feature(coarse, _KD(r, cfg.fpfh_max_nn))
            self.stats["fpfh_s"] = time.perf_counter() - t0
        return self._cache["fpfh"]


def _empty(key: tuple, reason: str, stats: dict[str, Any]) -> Prepared:
    return Prepared({}, o3d.geometry.PointCloud(), False, reason, key, stats)


def _clean_and_normals(pts: Array, voxel: float, cfg: RegistrationConfig) -> tuple[Array, Array]:
    """Statistical outlier removal and normals from one k-nearest-neighbour search
    (:func:`_outliers` then :func:`_knn_normals`). Returns the keep mask (N,) and the normals
    (M, 3) of the M kept points."""
    keep, d, nb = _outliers(pts, cfg)
    kept = np.flatnonzero(keep)
    return keep, _knn_normals(pts, keep, d[kept], nb[kept], voxel, cfg)


def _outliers(pts: Array, cfg: RegistrationConfig) -> tuple[Array, Array, Array]:
    """Statistical outlier filter of the voxel cloud ``pts`` (N, 3) m.

    With ``d_ik`` the distance of point ``i`` to its ``k``-th nearest neighbour (``k = 0`` is
    the point itself, as in Open3D's filter), ``m_i = mean_{k < K} d_ik`` over
    ``K = outlier_neighbors``: point ``i`` is kept when
    ``m_i <= mean(m) + outlier_std_ratio * std(m)``. Returns the keep mask (N,) and the
    distances and indices (N, max(K, normal_max_nn)) of the search, for :func:`_knn_normals`.
    """
    k_out, k_nrm = min(cfg.outlier_neighbors, len(pts)), min(cfg.normal_max_nn, len(pts))
    # one worker: thread start-up and joins cost more than they save on ~6k points when
    # the machine is busy (measured 2x slower on 2 shared cores)
    d, nb = cKDTree(pts).query(pts, k=max(k_out, k_nrm))
    m = d[:, :k_out].mean(axis=1)
    keep = m <= m.mean() + cfg.outlier_std_ratio * m.std(ddof=1)
    return keep, d, nb


def _knn_normals(
    pts: Array, keep: Array, d: Array, nb: Array, voxel: float, cfg: RegistrationConfig
) -> Array:
    """Normals (M, 3) of the kept points of ``pts`` (N, 3) from their neighbours ``nb`` and
    distances ``d`` (M, K) (rows of :func:`_outliers`' search for the kept points).

    The normal of a kept point is the eigenvector of the smallest eigenvalue of the covariance
    of its kept neighbours among the first ``normal_max_nn`` within
    ``normal_radius_factor * voxel`` (itself included), oriented to the camera at the origin
    (``n . p < 0``); with fewer than 3 such neighbours, the viewing direction ``-p / |p|``.
    """
    k_nrm = min(cfg.normal_max_nn, len(pts))
    d, nb = d[:, :k_nrm], nb[:, :k_nrm]
    p = pts[np.flatnonzero(keep)]
    w = (d <= cfg.normal_radius_factor * voxel) & keep[nb]
    cnt = w.sum(axis=1)
    inv = 1.0 / np.maximum(cnt, 1)
    # neighbour offsets from the point itself (better conditioned than raw coordinates), one
    # contiguous (3, M, K) block: axis sums and the six second moments without strided views
    x = np.empty((3, *nb.shape))
    np.multiply(np.moveaxis(pts[nb] - p[:, None, :], 2, 0), w, out=x)
    mean = x.sum(axis=2) * inv
    xx, yy, zz = x

    def cov(a: Array, b: Array, i: int, j: int) -> Array:
        return np.einsum("nk,nk->n", a, b) * inv - mean[i] * mean[j]

    n = _smallest_eigenvector(
        cov(xx, xx, 0, 0),
        cov(yy, yy, 1, 1),
        cov(zz, zz, 2, 2),
        cov(xx, yy, 0, 1),
        cov(xx, zz, 0, 2),
        cov(yy, zz, 1, 2),
    )
    weak = cnt < 3
    n[weak] = -p[weak] / np.linalg.norm(p[weak], axis=1, keepdims=True)
    n[np.einsum("ij,ij->i", n, p) > 0] *= -1.0
    return n


def _smallest_eigenvector(
    c00: Array, c11: Array, c22: Array, c01: Array, c02: Array, c12: Array
) -> Array:
    """Unit eigenvectors (N, 3) of the smallest eigenvalue of the symmetric 3x3 matrices with
    entries ``c_ij`` (N,): the eigenvalue in closed form (trigonometric solution of the
    characteristic cubic), the vector as the largest cross product of two rows of
    ``C - lambda I``."""
    q = (c00 + c11 + c22) / 3.0
    a, b, c = c00 - q, c11 - q, c22 - q
    p = np.sqrt((a * a + b * b + c * c + 2.0 * (c01 * c01 + c02 * c02 + c12 * c12)) / 6.0)
    s = 1.0 / np.where(p > 0, p, 1.0)
    a, b, c, d, e, f = a * s, b * s, c * s, c01 * s, c02 * s, c12 * s
    det = a * (b * c - f * f) - d * (d * c - f * e) + e * (d * f - b * e)  # det(C - qI) / p^3
    r = np.clip(det / 2.0, -1.0, 1.0)
    lam = q + 2.0 * p * np.cos(np.arccos(r) / 3.0 + 2.0 * np.pi / 3.0)
    r0 = np.stack([c00 - lam, c01, c02], axis=1)
    r1 = np.stack([c01, c11 - lam, c12], axis=1)
    r2 = np.stack([c02, c12, c22 - lam], axis=1)
    cands = np.stack([np.cross(r0, r1), np.cross(r0, r2), np.cross(r1, r2)], axis=1)
    norms = np.einsum("nci,nci->nc", cands, cands)
    best = norms.argmax(axis=1)
    rows = np.arange(len(q))
    v, nv = cands[rows, best], np.sqrt(norms[rows, best])
    out = np.zeros_like(v)
    out[:, 2] = 1.0  # isotropic or empty neighbourhood: any direction
    good = nv > 1e-30
    out[good] = v[good] / nv[good, None]
    return out


def _normals(pc: o3d.geometry.PointCloud, voxel: float, cfg: RegistrationConfig) -> None:
    pc.estimate_normals(_KD(cfg.normal_radius_factor * voxel, cfg.normal_max_nn))
    pc.orient_normals_towards_camera_location(np.zeros(3))


def prepare(
    cloud: Any, cfg: RegistrationConfig | None = None, *, features: bool = True
) -> Prepared:
    """Crop, clean and downsample once (and with ``features`` the coarse normals and FPFH;
    everything else is computed on first use, see :class:`Prepared`).

    ``cloud`` is a :class:`mmpa.robot.interfaces.PointCloud` (or any object with ``points``
    (N, 3) m in the camera optical frame and ``colors`` (N, 3) in [0, 1] or ``None``). Raises
    :class:`InvalidInputError` for arrays of the wrong shape; an empty or non-finite cloud gives
    a :class:`Prepared` with a ``reason`` (``register`` then returns ``ok=False``).
    """
    cfg = cfg or RegistrationConfig()
    with open3d_threads(cfg.open3d_threads):
        return _prepare(cloud, cfg, features)


def _prepare(cloud: Any, cfg: RegistrationConfig, features: bool) -> Prepared:
    t0 = time.perf_counter()
    key = cfg.preprocessing_key()
    pts = np.asarray(getattr(cloud, "points", None), dtype=float)
    cols = getattr(cloud, "colors", None)
    if pts.ndim != 2 or pts.shape[1] != 3:
        raise InvalidInputError(f"cloud points must be (N, 3), got {pts.shape}")
    if cols is not None:
        cols = np.asarray(cols, dtype=float)
        if cols.shape != pts.shape:
            raise InvalidInputError(f"cloud colors {cols.shape} do not match points {pts.shape}")
    stats: dict[str, Any] = {"n_input": len(pts)}
    # one reduction over the whole array is ~10x cheaper than a per-row test
    all_finite = np.isfinite(pts.sum()) and (cols is None or np.isfinite(cols.sum()))
    finite = np.ones(len(pts), bool)
    if not all_finite:
        finite = np.isfinite(pts).all(axis=1)
        if cols is not None:
            finite &= np.isfinite(cols).all(axis=1)
    n_bad = int(len(pts) - np.count_nonzero(finite))
    stats["n_nonfinite"] = n_bad
    if n_bad and cfg.nan_policy == "reject":
        return _empty(key, f"cloud has {n_bad} non-finite points (nan_policy='reject')", stats)
    step = cfg.presample
    z = pts[::step, 2]
    keep = finite[::step] & (z >= cfg.min_depth) & (z <= cfg.max_depth)
    stats["n_cropped"] = int(np.count_nonzero(keep))
    if stats["n_cropped"] < cfg.min_points:
        what = f"{stats['n_input']} points" + (f", {n_bad} non-finite" if n_bad else "")
        return _empty(
            key,
            f"too few points: {stats['n_cropped']} of {what} in depth "
            f"[{cfg.min_depth}, {cfg.max_depth}] m (need {cfg.min_points})",
            stats,
        )
    # rows of the contiguous input (a boolean mask on the strided view is ~1.5x slower)
    rows = np.flatnonzero(keep) * step
    pts = pts.take(rows, axis=0)
    colored = False
    if cols is not None:
        cols = cols.take(rows, axis=0)
        np.clip(cols, 0.0, 1.0, out=cols)
        sample = cols[:: max(1, len(cols) // 5000)]
        colored = bool((sample.std(axis=0) > cfg.min_color_std).any())
    raw = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(pts))
    if colored:
        raw.colors = o3d.utility.Vector3dVector(cols)
    voxels = sorted({s.voxel for s in (*cfg.scales, *cfg.init_scales)})
    fine = raw.voxel_down_sample(voxels[0])
    knn = None
    if cfg.outlier_neighbors > 0 and len(fine.points) > cfg.outlier_neighbors + 1:
        fine_pts = np.asarray(fine.points).copy()
        keep_v, d, nb = _outliers(fine_pts, cfg)
        kept = np.flatnonzero(keep_v)
        fine = fine.select_by_index(kept)
        # the search is kept for the normals of this level, computed if it is an ICP target
        knn = (fine_pts, keep_v, d[kept], nb[kept])
    stats["n_fine"] = len(fine.points)
    if len(fine.points) >= 2:
        fp = np.asarray(fine.points)
        if knn is not None:  # the distance to the nearest other voxel, from the kept search
            d1 = knn[2][:, 1]
        else:
            d1 = cKDTree(fp).query(fp, k=2)[0][:, 1]
        # RMS nearest-neighbour spacing (m) and median depth (m) of the finest level: what a
        # correct fit's inlier RMSE is made of (RegistrationConfig's RMSE gate)
        stats["spacing"] = float(np.sqrt(np.mean(np.square(d1))))
        stats["median_depth"] = float(np.median(fp[:, 2]))
    if len(fine.points) < cfg.min_points:
        return _empty(
            key,
            f"too few points: {len(fine.points)} voxels of {voxels[0]} m after cleaning "
            f"(need {cfg.min_points})",
            stats,
        )
    levels = {voxels[0]: fine}
    for v in voxels[1:]:
        levels[v] = fine.voxel_down_sample(v)
    coarse = levels.get(cfg.coarse_voxel)
    if coarse is None:
        coarse = fine.voxel_down_sample(cfg.coarse_voxel)
    stats["n_coarse"] = len(coarse.points)
    prep = Prepared(levels, coarse, colored, "", key, stats)
    if knn is not None:
        prep._cache["fine_knn"] = (voxels[0], *knn)
    if features:
        prep.fpfh(cfg)
    stats["prepare_s"] = time.perf_counter() - t0
    return prep


def _as_prepared(x: Any, cfg: RegistrationConfig, features: bool, name: str) -> Prepared:
    if isinstance(x, Prepared):
        if x.key != cfg.preprocessing_key():
            raise ConfigError(
                f"{name} was prepared with other preprocessing settings than this config; "
                "call prepare() again with the same RegistrationConfig"
            )
        return x
    return prepare(x, cfg, features=features)


def _feature_matrix(p: Prepared, f: o3d.pipelines.registration.Feature) -> Array:
    """The FPFH descriptors of ``p`` as a float32 (N, 33) array (cached with the cloud)."""
    if "fpfh_matrix" not in p._cache:
        p._cache["fpfh_matrix"] = np.ascontiguousarray(np.asarray(f.data, np.float32).T)
    return p._cache["fpfh_matrix"]


def fgr_correspondences(
    f_src: Array,
    f_tgt: Array,
    p_src: Array,
    p_tgt: Array,
    max_tuples: int,
    tuple_scale: float,
    rng: np.random.Generator,
) -> Array:
    """Correspondences of Fast Global Registration (Zhou et al. 2016, §3 "initial
    correspondences" and the tuple test), vectorized.

    ``f_src`` (N, d), ``f_tgt`` (M, d) descriptors of the points ``p_src`` (N, 3) and
    ``p_tgt`` (M, 3). Mutual nearest neighbours in descriptor space, with the squared
    distances ``|a_i|^2 - 2 a_i . b_j + |b_j|^2`` from one matrix product: pairs ``(i, j)``
    with ``j = argmin_j' |a_i - b_j'|`` and ``i = argmin_i' |a_i' - b_j|``. Tuple test: of
    up to ``100 K`` random triples of the ``K`` mutual pairs (drawn from ``rng``), keep those
    whose three edge lengths agree, ``tuple_scale < l_tgt / l_src < 1 / tuple_scale`` for
    every edge, until ``max_tuples`` triples pass. Returns the (3 T, 2) int32 index pairs
    ``(source, target)`` of the ``T`` accepted triples (the input of Open3D's
    ``registration_fgr_based_on_correspondence`` without its own tuple test).
    """
    a = np.asarray(f_src, np.float32)
    b = np.asarray(f_tgt, np.float32)
    if len(a) == 0 or len(b) == 0:
        return np.zeros((0, 2), np.int32)
    # row-wise argmins of contiguous matrices (a column-wise argmin is ~15x slower)
    with single_threaded_blas():
        j_of_i = ((b * b).sum(axis=1)[None, :] - 2.0 * (a @ b.T)).argmin(axis=1)
        i_of_j = ((a * a).sum(axis=1)[None, :] - 2.0 * (b @ a.T)).argmin(axis=1)
    i = np.flatnonzero(i_of_j[j_of_i] == np.arange(len(a)))
    pairs = np.stack([i, j_of_i[i]], axis=1)
    k = len(pairs)
    if k < 3:
        return np.zeros((0, 2), np.int32)
    ps, pt = np.asarray(p_src, float)[pairs[:, 0]], np.asarray(p_tgt, float)[pairs[:, 1]]
    # edge lengths between all mutual pairs, flattened for the lookups
    d_s = cdist(ps, ps).astype(np.float32).ravel()
    d_t = cdist(pt, pt).astype(np.float32).ravel()
    found: list[Array] = []
    n_found, trials, batch = 0, 100 * k, 20000
    for start in range(0, trials, batch):
        r = rng.integers(0, k, (min(batch, trials - start), 3))
        ok = np.ones(len(r), bool)
        for e0, e1 in ((0, 1), (1, 2), (2, 0)):
            e = r[:, e0] * k + r[:, e1]
            ls, lt = d_s[e], d_t[e]
            ok &= (ls * tuple_scale < lt) & (lt * tuple_scale < ls)
        sel = r[ok][: max_tuples - n_found]
        found.append(sel)
        n_found += len(sel)
        if n_found >= max_tuples:
            break
    return pairs[np.concatenate(found).reshape(-1)].astype(np.int32)


def _feature_support(src: Array, tgt: Array, corr: Array, radius: float) -> Callable[[Array], int]:
    """``support(T)``: how many of the feature correspondences ``corr`` (K, 2) between the
    coarse points ``src`` (N, 3) and ``tgt`` (M, 3) a pose ``T`` (4, 4) maps within
    ``radius`` (m) of each other, ``|R p_s + t - p_t| < radius``."""
    c = np.asarray(corr, dtype=np.int64).reshape(-1, 2)
    ps, pt = src[c[:, 0]], tgt[c[:, 1]]

    def support(T: Array) -> int:
        d = ps @ T[:3, :3].T + T[:3, 3] - pt
        return int(np.count_nonzero(np.einsum("ij,ij->i", d, d) < radius * radius))

    return support


def _centroid_motion(T_a: Array, T_b: Array, c: Array) -> tuple[float, float]:
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


def _icp(
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


def register(
    source: Any,
    target: Any,
    cfg: RegistrationConfig | None = None,
    *,
    init: Array | None = None,
) -> Registration:
    """Estimate ``T_target_source`` (``p_target = T p_source``) between two colored clouds.

    ``source``/``target``: :class:`~mmpa.robot.interfaces.PointCloud` or :class:`Prepared`
    (prepared with the same ``cfg``). Without ``init`` the coarse pose comes from FPFH + FGR;
    with ``init`` (4, 4) the global stage is skipped and the fine stage runs ``init_scales``
    from it. The result is always validated; failures return ``ok=False`` with a reason.
    """
    cfg = cfg or RegistrationConfig()
    with open3d_threads(cfg.open3d_threads):
        return _register(source, target, cfg, init)


def _register(
    source: Any, target: Any, cfg: RegistrationConfig, init: Array | None
) -> Registration:
    t0 = time.perf_counter()
    stages: dict[str, Any] = {}
    if init is not None:
        init = np.asarray(init, dtype=float)
        if init.shape != (4, 4) or not np.isfinite(init).all():
            raise InvalidInputError(f"init must be a finite 4x4 transform, got shape {init.shape}")
        R = init[:3, :3]
        if not np.allclose(R @ R.T, np.eye(3), atol=1e-6) or np.linalg.det(R) < 0:
            raise InvalidInputError("init rotation block is not a proper rotation")
    need_features = init is None
    src = _as_prepared(source, cfg, need_features, "source")
    tgt = _as_prepared(target, cfg, need_features, "target")
    stages["prepare_s"] = time.perf_counter() - t0

    def result(
        T: Array, ok: bool, reason: str, fit: float = 0.0, rmse: float = np.inf, n: int = 0
    ) -> Registration:
        return Registration(
            T=np.asarray(T, float),
            fitness=float(fit),
            rmse=float(rmse),
            ok=ok,
            reason=reason,
            n_correspondences=int(n),
            seconds=time.perf_counter() - t0,
            stages=stages,
        )

    for name, p in (("source", src), ("target", tgt)):
        if p.reason:
            return result(np.eye(4), False, f"{name}: {p.reason}")
    both = src.colored and tgt.colored
    if cfg.color_mode == "colored" and not both:
        return result(np.eye(4), False, "color_mode='colored' but a cloud has no color")
    if cfg.color_mode == "geometric":
        methods: tuple[bool, ...] = (False,)
    elif cfg.color_mode in ("colored", "paper"):
        methods = (both,)
    else:  # auto: geometry first, the photometric term only where geometry is weak
        methods = (False, True) if both else (False,)

    if init is None:
        t1 = time.perf_counter()
        fs, ft = src.fpfh(cfg), tgt.fpfh(cfg)
        stages["features_s"] = time.perf_counter() - t1
        t1 = time.perf_counter()
        corr = fgr_correspondences(
            _feature_matrix(src, fs),
            _feature_matrix(tgt, ft),
            np.asarray(src.coarse.points),
            np.asarray(tgt.coarse.points),
            cfg.fgr_max_tuples,
            cfg.fgr_tuple_scale,
            np.random.default_rng(cfg.seed),
        )
        stages["matching_s"] = time.perf_counter() - t1
        stages["fgr_correspondences"] = len(corr)
        t1 = time.perf_counter()
        T0 = fgr_solve(
            np.asarray(src.coarse.points),
            np.asarray(tgt.coarse.points),
            corr,
            cfg.fgr_distance_factor * cfg.coarse_voxel,
            cfg.fgr_iterations,
        )
        stages["coarse_s"] = time.perf_counter() - t1
        scales = cfg.scales
        limits = (cfg.max_fine_shift, cfg.max_fine_rotation_deg, "coarse")
        support = _feature_support(
            np.asarray(src.coarse.points), np.asarray(tgt.coarse.points), corr, cfg.coarse_voxel
        )
    else:
        T0 = init
        scales = cfg.init_scales
        limits = (cfg.max_init_shift, cfg.max_init_rotation_deg, "initial")
        support = None
    stages["T_coarse"] = T0
    t1 = time.perf_counter()
    for sc in scales:  # the fine stage needs the target's normals
        tgt.with_normals(sc.voxel, cfg)
    stages["normals_s"] = time.perf_counter() - t1

    accepted: _Fine | None = None
    fine = None
    for j, colored in enumerate(methods):
        stages["method"] = "colored_icp" if colored else "point_to_plane_icp"
        prefix = "colored_" if j else ""
        fine = _fine_stage(
            src, tgt, T0, scales, colored, cfg, stages, prefix, limits, init, support
        )
        if fine.ok:
            accepted = fine
        if fine.ok and (colored or fine.information >= cfg.geometric_min_information):
            break
        if j + 1 < len(methods):
            stages["geometric_information"] = fine.information
            stages["geometric_reason"] = fine.reason or (
                f"geometric information {fine.information:.2e} < "
                f"{cfg.geometric_min_information:.1e}"
            )
    assert fine is not None
    if accepted is not None and not fine.ok:  # colored ICP failed where geometry passed
        fine = accepted
        stages["method"] = "point_to_plane_icp"
    stages["min_information"] = fine.information
    return result(fine.T, fine.ok, fine.reason, fine.fitness, fine.rmse, fine.n)


class _Fine(NamedTuple):
    T: Array
    ok: bool
    reason: str
    fitness: float
    rmse: float
    n: int
    information: float


def _fine_stage(
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
) -> _Fine:
    """Multi-scale (colored or point-to-plane) ICP from ``T0`` and its acceptance checks."""
    try:
        T, res, last = _icp(src, tgt, T0, scales, colored, cfg, stages, prefix)
    except RuntimeError as e:  # Open3D refuses e.g. clouds without enough neighbours
        return _Fine(T0, False, f"fine stage failed: {_open3d_message(e)}", 0.0, np.inf, 0, 0.0)
    corr = np.asarray(res.correspondence_set)
    fit, rmse, n = float(res.fitness), float(res.inlier_rmse), len(corr)
    src_fine = np.asarray(src.levels[last.voxel].points)
    c = src_fine.mean(axis=0)
    shift, rot = _centroid_motion(T, T0, c)
    stages["fine_shift_m"], stages["fine_rotation_deg"] = shift, rot
    max_shift, max_rot, what = limits

    def fail(reason: str, lam: float = 0.0) -> _Fine:
        return _Fine(T, False, reason, fit, rmse, n, lam)

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
    lam_min, weak = _min_information(src, tgt, T, corr, last, colored, cfg)
    stages[f"{prefix}degeneracy_s"] = time.perf_counter() - t1
    if lam_min < cfg.min_information:
        method = "colored_icp" if colored else "point_to_plane_icp"
        return fail(
            f"degenerate geometry: the {method} objective does not "
            f"constrain the direction {weak} (information {lam_min:.2e} < "
            f"{cfg.min_information:.1e}; a single plane without texture?)",
            lam_min,
        )
    return _Fine(T, True, "", fit, rmse, n, lam_min)


_DOF = ("rx", "ry", "rz", "x", "y", "z")


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


def _open3d_message(e: Exception) -> str:
    """Open3D's error text without terminal colors and C++ signatures."""
    msg = re.sub(r"\x1b\[[0-9;]*m", "", str(e)).strip()
    return msg.rsplit(": ", 1)[-1] if "open3d::" in msg else msg


def _direction(v: Array) -> str:
    parts = [f"{v[i]:+.2f}{_DOF[i]}" for i in np.argsort(-np.abs(v))[:2] if abs(v[i]) > 0.2]
    return "[" + " ".join(parts) + "] (camera frame, twist about the centroid)"


def _min_information(
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
