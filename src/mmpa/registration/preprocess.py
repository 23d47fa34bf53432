"""Preprocessing and features of the registration (paper 000 §3.2.2 II, stage 1).

``prepare`` (once per cloud; points in the camera optical frame, m): crop ``z`` to
``[min_depth, max_depth]``, drop non-finite points, keep every ``presample``-th point,
voxel-average at the finest ICP voxel, remove statistical outliers with one k-NN search (kept:
it also gives that level's normals), build the voxel pyramid of the ICP schedule. The normals
of every level (only the ICP target needs them; the finest from the kept search, the
smallest eigenvector of the neighbours' covariance, oriented to the camera) and FPFH (Rusu
2009) at the coarse voxel are computed on first use and kept with the cloud
(:class:`Prepared`: a taught cloud pays for them once, a source cloud never for its normals).
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import open3d as o3d
from scipy.spatial import cKDTree

from mmpa.core.errors import ConfigError, InvalidInputError
from mmpa.core.geometry import Array
from mmpa.registration._blas import open3d_threads
from mmpa.registration.config import RegistrationConfig

__all__ = ["Prepared", "as_prepared", "feature_matrix", "prepare"]

_reg = o3d.pipelines.registration
_KD = o3d.geometry.KDTreeSearchParamHybrid


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


def _checked_arrays(cloud: Any) -> tuple[Array, Array | None]:
    """The cloud's points (N, 3) and colours (N, 3) or None, shapes checked."""
    pts = np.asarray(getattr(cloud, "points", None), dtype=float)
    cols = getattr(cloud, "colors", None)
    if pts.ndim != 2 or pts.shape[1] != 3:
        raise InvalidInputError(f"cloud points must be (N, 3), got {pts.shape}")
    if cols is not None:
        cols = np.asarray(cols, dtype=float)
        if cols.shape != pts.shape:
            raise InvalidInputError(f"cloud colors {cols.shape} do not match points {pts.shape}")
    return pts, cols


def _finite(pts: Array, cols: Array | None) -> Array:
    """The mask (N,) of the rows whose point and colour are finite."""
    # one reduction over the whole array is ~10x cheaper than a per-row test
    all_finite = np.isfinite(pts.sum()) and (cols is None or np.isfinite(cols.sum()))
    finite = np.ones(len(pts), bool)
    if not all_finite:
        finite = np.isfinite(pts).all(axis=1)
        if cols is not None:
            finite &= np.isfinite(cols).all(axis=1)
    return finite


def _raw_cloud(
    pts: Array, cols: Array | None, rows: Array, cfg: RegistrationConfig
) -> tuple[o3d.geometry.PointCloud, bool]:
    """The Open3D cloud of the kept ``rows`` (with colours when they vary: ``colored``)."""
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
    return raw, colored


def _fine_level(
    raw: o3d.geometry.PointCloud, voxel: float, cfg: RegistrationConfig, stats: dict[str, Any]
) -> tuple[o3d.geometry.PointCloud, tuple | None]:
    """The finest voxel level, cleaned of statistical outliers, and the kept k-NN search
    (for its normals; None without the filter); ``stats`` gets its size, RMS nearest-neighbour
    spacing and median depth."""
    fine = raw.voxel_down_sample(voxel)
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
    return fine, knn


def _prepare(cloud: Any, cfg: RegistrationConfig, features: bool) -> Prepared:
    t0 = time.perf_counter()
    key = cfg.preprocessing_key()
    pts, cols = _checked_arrays(cloud)
    stats: dict[str, Any] = {"n_input": len(pts)}
    finite = _finite(pts, cols)
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
    raw, colored = _raw_cloud(pts, cols, np.flatnonzero(keep) * step, cfg)
    voxels = sorted({s.voxel for s in (*cfg.scales, *cfg.init_scales)})
    fine, knn = _fine_level(raw, voxels[0], cfg, stats)
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


def as_prepared(x: Any, cfg: RegistrationConfig, features: bool, name: str) -> Prepared:
    if isinstance(x, Prepared):
        if x.key != cfg.preprocessing_key():
            raise ConfigError(
                f"{name} was prepared with other preprocessing settings than this config; "
                "call prepare() again with the same RegistrationConfig"
            )
        return x
    return prepare(x, cfg, features=features)


def feature_matrix(p: Prepared, f: o3d.pipelines.registration.Feature) -> Array:
    """The FPFH descriptors of ``p`` as a float32 (N, 33) array (cached with the cloud)."""
    if "fpfh_matrix" not in p._cache:
        p._cache["fpfh_matrix"] = np.ascontiguousarray(np.asarray(f.data, np.float32).T)
    return p._cache["fpfh_matrix"]
