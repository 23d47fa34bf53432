"""Survey the laser reflectors of a site from a drive: detections + pose estimates -> a map.

Input (:class:`SurveyObservations`): reflector centres detected in each scan, in the LASER
frame (``points`` (M, 2) m, :func:`mmpa.localization.reflectors.detect_reflectors`), the
pose index of each (``pose_index`` (M,)), the localizer's base pose estimates
``T_map_base`` as planar poses ``poses`` (S, 3) ``[x, y, theta]`` (m, rad), and the lidar
mount ``laser_pose`` ``[x, y, yaw]`` in ``base_link``. One pose may carry many scans (a
robot standing at a survey station); its pose error is then shared by all of them.

Steps (:func:`survey_reflectors`):

1. **to the map**: ``q = t_L + R(phi_L) z`` with the laser pose in the map ``(t_L, phi_L) =
   pose (+) laser_pose``; the ray of each view ``u = (q - t_L) / |q - t_L|``
   (:func:`laser_to_map`).
2. **associate**: detections closer than ``cluster_radius`` are linked, the connected
   components (single linkage) are the candidate reflectors (:func:`cluster_points`); a
   candidate seen in fewer than ``min_views`` scans or from fewer than ``min_poses`` poses is
   dropped (glare, a passer-by's reflective vest, a one-off).
3. **fit** each reflector (:func:`fit_reflector`). A retroreflective return's range is off
   by a bias ``beta`` (range walk, the scanner's published figure ``range_bias``, plus the
   reflector's own deviation ``delta``): the detected centre of view ``k`` is
   ``q_k = p + beta u_k + e_k``, ``beta = range_bias + delta``. Linear least squares in
   ``x = (p, delta)`` (3 unknowns)::

       min_x  sum_k w_k |q_k - range_bias u_k - [I2 u_k] x|^2 / s^2  +  delta^2 / s_b^2

   with the Gaussian prior ``delta ~ N(0, s_b)`` (``bias_sigma``; 0 fixes ``delta = 0``):
   views from many directions tell the bias from the position (``sum u_k`` small), views
   from one side leave it to the prior. Huber weights ``w_k`` (scale ``huber``) by
   iteratively reweighted least squares; views farther than ``outlier_gate`` from the fit
   are dropped.
4. **bundle adjustment** (``refine_poses``, :func:`bundle_adjust`): the poses, the positions
   and the biases together, Gauss-Newton (scipy ``least_squares``) on

       sum_{s,j} n_sj |m_sj - h(pose_s, p_j, beta_j)|^2 / s^2
         + sum_s |(pose_s - pose_s^0) / s_pose|^2 + sum_j (delta_j / s_b)^2

   with ``m_sj`` the mean laser-frame detection of reflector ``j`` at pose ``s`` (``n_sj``
   scans, counted at most ``max_scans_per_pose``), ``h`` the predicted detection
   ``z + beta z / |z|``, ``z = R(phi_L)^T (p - t_L)``. The poses' priors fix the gauge;
   the reflectors' layout follows the lidar's geometry, not each pose's error.

Also here (from :mod:`mmpa.calibration.survey_matching`): :func:`match_scan_to_map` on
:func:`signed_distance_map` (a standing stop's mean scan onto the occupancy map, sub-cell:
the survey runner's refinement of the localizer's stop poses), :func:`anchor_to` (place the
surveyed layout rigidly onto an earlier reflector map: control points) and
:func:`match_reflectors` (one-to-one matching, for evaluation against a truth).

Units: m, rad. Pure functions over numpy arrays; bad input raises
:class:`~mmpa.core.errors.InvalidInputError` (:class:`SurveyError` when nothing can be fitted).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from pydantic import BaseModel, ConfigDict, Field
from scipy.optimize import least_squares
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree

from mmpa.calibration.survey_matching import (
    ReflectorMatch,
    SurveyError,
    anchor_to,
    match_reflectors,
    match_scan_to_map,
    signed_distance_map,
)
from mmpa.core.errors import InvalidInputError
from mmpa.core.geometry import Array

__all__ = [
    "ReflectorFit",
    "ReflectorMatch",
    "ReflectorSurvey",
    "SurveyConfig",
    "SurveyError",
    "SurveyObservations",
    "anchor_to",
    "bundle_adjust",
    "cluster_points",
    "fit_reflector",
    "laser_origin_heading",
    "laser_to_map",
    "match_reflectors",
    "match_scan_to_map",
    "signed_distance_map",
    "survey_reflectors",
]

#: The default mean range bias on a retroreflective cylinder (m): the scanner's range walk
#: on retroreflective tape, -10 mm (Sedek et al. 2024; DESIGN.md "Error model v2"), plus the
#: incidence term ``+10 mm (1 - cos i)`` averaged over a cylinder's visible face
#: (``mean(1 - cos i) = 1 - pi/4`` for beams evenly spread across the chord).
DEFAULT_RANGE_BIAS = -0.010 + 0.010 * (1.0 - np.pi / 4.0)


class SurveyConfig(BaseModel):
    """Association, fit and bundle adjustment settings (m, rad)."""

    model_config = ConfigDict(extra="forbid")

    cluster_radius: float = Field(0.15, gt=0)  # m, detections this close are one reflector
    min_views: int = Field(5, ge=1)  # scans that saw a reflector
    min_poses: int = Field(2, ge=1)  # distinct poses (stations) that saw it
    max_range: float = Field(10.0, gt=0)  # m, farther detections are dropped
    range_bias: float = DEFAULT_RANGE_BIAS  # m, known mean range bias on a reflector
    bias_sigma: float = Field(0.005, ge=0)  # m, prior SD of a reflector's own bias; 0: fixed
    point_sigma: float = Field(0.015, gt=0)  # m, SD of one detected centre
    huber: float = Field(0.03, gt=0)  # m, Huber scale of the per-reflector fit
    outlier_gate: float = Field(0.10, gt=0)  # m, views farther from the fit are dropped
    refine_poses: bool = True  # the bundle adjustment of step 4
    pose_sigma_xy: float = Field(0.02, gt=0)  # m, prior SD of a pose estimate per axis
    pose_sigma_yaw: float = Field(0.005, gt=0)  # rad
    max_scans_per_pose: int = Field(10, ge=1)  # scans of one pose counted as independent


@dataclass(frozen=True)
class SurveyObservations:
    """Detections and pose estimates (module docstring). ``points`` (M, 2) m in the laser
    frame, ``pose_index`` (M,) int into ``poses`` (S, 3) ``[x, y, theta]`` T_map_base,
    ``laser_pose`` (3,) the lidar mount ``[x, y, yaw]`` in ``base_link``; ``scan_index``
    (M,) the scan of each detection (default: each detection its own scan)."""

    points: Array
    pose_index: np.ndarray
    poses: Array
    laser_pose: Array
    scan_index: np.ndarray | None = None

    def __post_init__(self) -> None:
        pts = np.asarray(self.points, float)
        if pts.ndim != 2 or pts.shape[1] != 2:
            raise InvalidInputError(f"points must be (M, 2) m, got shape {pts.shape}")
        m = len(pts)
        idx = np.asarray(self.pose_index)
        if idx.shape != (m,) or (m and not np.issubdtype(idx.dtype, np.integer)):
            raise InvalidInputError(
                f"pose_index must be ({m},) integers, got shape {idx.shape} {idx.dtype}"
            )
        poses = np.asarray(self.poses, float)
        if poses.ndim != 2 or poses.shape[1] != 3:
            raise InvalidInputError(f"poses must be (S, 3) [x, y, theta], got {poses.shape}")
        if m and (idx.min() < 0 or idx.max() >= len(poses)):
            raise InvalidInputError(
                f"pose_index must lie in [0, {len(poses)}), got [{idx.min()}, {idx.max()}]"
            )
        lp = np.asarray(self.laser_pose, float)
        if lp.shape != (3,) or not np.isfinite(lp).all():
            raise InvalidInputError(f"laser_pose must be a finite [x, y, yaw], got {lp}")
        if not np.isfinite(pts).all():
            bad = int(np.flatnonzero(~np.isfinite(pts).all(axis=1))[0])
            raise InvalidInputError(f"detection {bad} is not finite: {pts[bad]}")
        if not np.isfinite(poses).all():
            bad = int(np.flatnonzero(~np.isfinite(poses).all(axis=1))[0])
            raise InvalidInputError(f"pose {bad} is not finite: {poses[bad]}")
        scan = np.arange(m) if self.scan_index is None else np.asarray(self.scan_index)
        if scan.shape != (m,):
            raise InvalidInputError(f"scan_index must be ({m},), got {scan.shape}")
        for name, arr in (
            ("points", pts),
            ("pose_index", idx.astype(np.int64)),
            ("poses", poses),
            ("laser_pose", lp),
            ("scan_index", scan.astype(np.int64)),
        ):
            arr = arr.copy()
            arr.flags.writeable = False
            object.__setattr__(self, name, arr)

    def __len__(self) -> int:
        return int(self.points.shape[0])


@dataclass(frozen=True)
class ReflectorFit:
    """One reflector: ``position`` (2,) m, ``bias`` its range bias ``beta`` (m), ``inliers``
    (n,) bool over its views, ``rms`` m of the inliers' residuals."""

    position: Array
    bias: float
    inliers: np.ndarray
    rms: float


@dataclass(frozen=True)
class ReflectorSurvey:
    """The survey. ``positions`` (N, 2) m in ``map``, ``biases`` (N,) m, ``views`` (N,)
    scans used per reflector, ``poses_seen`` (N,) distinct poses, ``residual_rms`` (N,) m
    per reflector and ``rms`` m over all; ``labels`` (M,) the reflector of each detection
    (-1: dropped); ``poses`` (S, 3) the poses after the bundle adjustment (the input ones
    without it); ``ok`` and ``reason`` (why not ok); ``dropped_clusters`` candidates
    rejected as spurious (too few views or poses)."""

    positions: Array
    biases: Array
    views: np.ndarray
    poses_seen: np.ndarray
    residual_rms: Array
    rms: float
    labels: np.ndarray
    poses: Array
    ok: bool
    reason: str
    dropped_clusters: int
    refined: bool

    def __len__(self) -> int:
        return int(self.positions.shape[0])


def _rot(th: Array) -> Array:
    """(..., 2, 2) rotation matrices of the angles ``th`` (...,)."""
    c, s = np.cos(th), np.sin(th)
    return np.stack([np.stack([c, -s], -1), np.stack([s, c], -1)], -2)


def laser_origin_heading(poses: Array, laser_pose: Array) -> tuple[Array, Array]:
    """Laser origins (S, 2) m and headings (S,) rad in ``map`` of base poses ``poses``
    (S, 3) with the lidar mount ``laser_pose`` ``[x, y, yaw]``: ``pose (+) laser_pose``."""
    poses = np.asarray(poses, float).reshape(-1, 3)
    R = _rot(poses[:, 2])
    t = poses[:, :2] + R @ np.asarray(laser_pose[:2], float)
    return t, poses[:, 2] + float(laser_pose[2])


def laser_to_map(points: Array, poses: Array, laser_pose: Array) -> tuple[Array, Array]:
    """Detections ``points`` (M, 2) in the laser frame seen from base poses ``poses``
    (M, 3) (one per detection) -> (their map positions (M, 2), the laser origins (M, 2)):
    ``q = t_L + R(phi_L) z`` with ``(t_L, phi_L) = pose (+) laser_pose``."""
    t, phi = laser_origin_heading(poses, laser_pose)
    return t + np.einsum("mij,mj->mi", _rot(phi), np.asarray(points, float)), t


def cluster_points(xy: Array, radius: float) -> np.ndarray:
    """Connected components (single linkage) of points ``xy`` (M, 2) within ``radius`` m:
    a label (M,) per point, 0 .. K-1, numbered by first appearance."""
    xy = np.asarray(xy, float)
    if len(xy) == 0:
        return np.zeros(0, dtype=np.int64)
    pairs = cKDTree(xy).query_pairs(radius, output_type="ndarray")
    g = coo_matrix(
        (np.ones(len(pairs)), (pairs[:, 0], pairs[:, 1])) if len(pairs) else ([], ([], [])),
        shape=(len(xy), len(xy)),
    )
    _, lab = connected_components(g, directed=False)
    _, first, inv = np.unique(lab, return_index=True, return_inverse=True)
    order = np.argsort(np.argsort(first))
    return order[inv].astype(np.int64)


def fit_reflector(
    q: Array,
    rays: Array,
    range_bias: float = DEFAULT_RANGE_BIAS,
    bias_sigma: float = 0.005,
    point_sigma: float = 0.015,
    huber: float = 0.03,
    outlier_gate: float = 0.10,
    iters: int = 10,
) -> ReflectorFit:
    """Position and range bias of one reflector from its detected centres ``q`` (n, 2) m
    in ``map`` and the unit rays ``rays`` (n, 2) from the laser to them: the regularised,
    Huber-weighted least squares of the module docstring (step 3). Raises
    :class:`SurveyError` with no views."""
    q = np.asarray(q, float).reshape(-1, 2)
    u = np.asarray(rays, float).reshape(-1, 2)
    if len(q) == 0:
        raise SurveyError("a reflector fit needs at least one view")
    if u.shape != q.shape or not (np.isfinite(q).all() and np.isfinite(u).all()):
        raise InvalidInputError(f"need finite q and rays of one shape, got {q.shape}, {u.shape}")
    y = q - range_bias * u
    A = np.zeros((len(q), 2, 3))
    A[:, 0, 0] = A[:, 1, 1] = 1.0
    A[:, :, 2] = u
    prior = np.zeros((3, 3))
    fix_bias = bias_sigma <= 0
    prior[2, 2] = 1e12 if fix_bias else (point_sigma / bias_sigma) ** 2
    keep = np.ones(len(q), bool)
    w = np.ones(len(q))
    x = np.concatenate([np.median(y, axis=0), [0.0]])
    for it in range(iters + 1):
        ww = w * keep
        H = np.einsum("k,kia,kib->ab", ww, A, A) + prior
        g = np.einsum("k,kia,ki->a", ww, A, y)
        x_new = np.linalg.solve(H, g)
        r = np.linalg.norm(y - np.einsum("kia,a->ki", A, x_new), axis=1)
        w = np.where(r <= huber, 1.0, huber / np.maximum(r, 1e-12))
        # the gate only after a first robust fit; never drop below one view
        if it >= 2:
            new_keep = r <= outlier_gate
            if new_keep.any():
                keep = new_keep
        done = np.linalg.norm(x_new - x) < 1e-7
        x = x_new
        if done and it >= 2:
            break
    r = np.linalg.norm(y - np.einsum("kia,a->ki", A, x), axis=1)
    rms = float(np.sqrt(np.mean(r[keep] ** 2)))
    return ReflectorFit(x[:2].copy(), float(range_bias + x[2]), keep, rms)


def bundle_adjust(
    poses: Array,
    laser_pose: Array,
    pose_of: np.ndarray,
    refl_of: np.ndarray,
    z: Array,
    counts: Array,
    positions: Array,
    deltas: Array,
    cfg: SurveyConfig,
) -> tuple[Array, Array, Array]:
    """Step 4 of the module docstring: refine ``poses`` (S, 3), ``positions`` (N, 2) and the
    reflectors' bias deviations ``deltas`` (N,) from per (pose, reflector) mean detections
    ``z`` (P, 2) in the laser frame, pair ``p`` seen from pose ``pose_of[p]`` of reflector
    ``refl_of[p]`` in ``counts[p]`` scans. Returns the three, refined."""
    poses0 = np.asarray(poses, float)
    S, N = len(poses0), len(positions)
    lp = np.asarray(laser_pose, float)
    sq = np.sqrt(np.minimum(counts, cfg.max_scans_per_pose)) / cfg.point_sigma
    fix_bias = cfg.bias_sigma <= 0
    sig_pose = np.array([cfg.pose_sigma_xy, cfg.pose_sigma_xy, cfg.pose_sigma_yaw])

    def unpack(v: Array) -> tuple[Array, Array, Array]:
        P = v[: 3 * S].reshape(S, 3)
        X = v[3 * S : 3 * S + 2 * N].reshape(N, 2)
        d = np.zeros(N) if fix_bias else v[3 * S + 2 * N :]
        return P, X, d

    def resid(v: Array) -> Array:
        P, X, d = unpack(v)
        t, phi = laser_origin_heading(P[pose_of], lp)
        zz = np.einsum("mji,mj->mi", _rot(phi), X[refl_of] - t)  # R^T (p - t)
        beta = cfg.range_bias + d[refl_of]
        h = zz + beta[:, None] * zz / np.linalg.norm(zz, axis=1, keepdims=True)
        parts = [((z - h) * sq[:, None]).ravel(), ((P - poses0) / sig_pose).ravel()]
        if not fix_bias:
            parts.append(d / cfg.bias_sigma)
        return np.concatenate(parts)

    v0 = np.concatenate(
        [poses0.ravel(), np.asarray(positions, float).ravel()]
        + ([] if fix_bias else [np.asarray(deltas, float)])
    )
    # sparsity: a pair's 2 residuals depend on its pose (3), reflector (2) and bias (1)
    n_res = 2 * len(z) + 3 * S + (0 if fix_bias else N)
    sp = np.zeros((n_res, len(v0)), dtype=bool)
    for k, (s, j) in enumerate(zip(pose_of, refl_of, strict=True)):
        rows = [2 * k, 2 * k + 1]
        sp[np.ix_(rows, range(3 * s, 3 * s + 3))] = True
        sp[np.ix_(rows, range(3 * S + 2 * j, 3 * S + 2 * j + 2))] = True
        if not fix_bias:
            sp[rows, 3 * S + 2 * N + j] = True
    base = 2 * len(z)
    sp[base + np.arange(3 * S), np.arange(3 * S)] = True
    if not fix_bias:
        sp[base + 3 * S + np.arange(N), 3 * S + 2 * N + np.arange(N)] = True
    sol = least_squares(resid, v0, jac_sparsity=sp, method="trf", x_scale="jac", xtol=1e-10)
    P, X, d = unpack(sol.x)
    return P, X, d


def _fit_clusters(
    obs: SurveyObservations, cfg: SurveyConfig, q: Array, t: Array, rng_all: Array, use: Array
) -> tuple[list[ReflectorFit], list[np.ndarray], int]:
    """Steps 2-3: cluster the used detections' map points ``q`` (views from ``t``, ranges
    ``rng_all``), drop candidates seen too rarely and fit the others; returns the fits, each
    fit's inlier detections (indices into ``obs``) and the number of candidates dropped."""
    lab_use = cluster_points(q[use], cfg.cluster_radius)
    idx_use = np.flatnonzero(use)
    fits: list[ReflectorFit] = []
    members: list[np.ndarray] = []
    dropped = 0
    for c in range(int(lab_use.max()) + 1 if len(lab_use) else 0):
        m = idx_use[lab_use == c]
        n_scans = len(np.unique(obs.scan_index[m]))
        n_poses = len(np.unique(obs.pose_index[m]))
        if n_scans < cfg.min_views or n_poses < cfg.min_poses:
            dropped += 1
            continue
        u = (q[m] - t[m]) / rng_all[m, None]
        f = fit_reflector(
            q[m],
            u,
            cfg.range_bias,
            cfg.bias_sigma,
            cfg.point_sigma,
            cfg.huber,
            cfg.outlier_gate,
        )
        fits.append(f)
        members.append(m[f.inliers])
    return fits, members, dropped


def _refine(
    obs: SurveyObservations,
    poses: Array,
    labels: np.ndarray,
    X: Array,
    beta: Array,
    cfg: SurveyConfig,
) -> tuple[Array, Array]:
    """Step 4: the bundle adjustment over the poses that saw a fitted reflector, on the mean
    laser-frame detection per (pose, reflector); updates ``poses`` in place and returns the
    positions and biases."""
    n = len(X)
    keep = labels >= 0
    key = obs.pose_index[keep] * n + labels[keep]
    pairs, inv, cnt = np.unique(key, return_inverse=True, return_counts=True)
    zmean = np.zeros((len(pairs), 2))
    np.add.at(zmean, inv, obs.points[keep])
    zmean /= cnt[:, None]
    used_poses = np.unique(pairs // n)
    remap = np.full(len(poses), -1)
    remap[used_poses] = np.arange(len(used_poses))
    P, X, d = bundle_adjust(
        poses[used_poses],
        obs.laser_pose,
        remap[pairs // n],
        pairs % n,
        zmean,
        cnt.astype(float),
        X,
        beta - cfg.range_bias,
        cfg,
    )
    poses[used_poses] = P
    return X, cfg.range_bias + d


def _residuals(
    obs: SurveyObservations,
    poses: Array,
    labels: np.ndarray,
    X: Array,
    beta: Array,
    rng_all: Array,
) -> tuple[Array, np.ndarray, np.ndarray, float]:
    """Every used view against the final positions (and poses): per reflector the residual
    RMS (m), the scans and poses that saw it, and the RMS over all views (m)."""
    qf, tf = laser_to_map(obs.points, poses[obs.pose_index], obs.laser_pose)
    res_rms = np.zeros(len(X))
    views = np.zeros(len(X), dtype=np.int64)
    seen = np.zeros(len(X), dtype=np.int64)
    sq_all: list[Array] = []
    for j in range(len(X)):
        m = np.flatnonzero(labels == j)
        u = (qf[m] - tf[m]) / rng_all[m, None]
        r = np.linalg.norm(qf[m] - beta[j] * u - X[j], axis=1)
        res_rms[j] = float(np.sqrt(np.mean(r**2)))
        sq_all.append(r**2)
        views[j] = len(np.unique(obs.scan_index[m]))
        seen[j] = len(np.unique(obs.pose_index[m]))
    rms = float(np.sqrt(np.mean(np.concatenate(sq_all))))
    return res_rms, views, seen, rms


def survey_reflectors(obs: SurveyObservations, cfg: SurveyConfig | None = None) -> ReflectorSurvey:
    """The reflector survey of the module docstring (steps 1-4). Raises
    :class:`SurveyError` when there are no detections; a survey in which no candidate
    passes the association gates comes back with ``ok=False`` and its ``reason``."""
    cfg = cfg or SurveyConfig()
    if len(obs) == 0:
        raise SurveyError("no reflector detections: nothing to survey (did the lidar see any?)")
    z_all = obs.points
    rng_all = np.linalg.norm(z_all, axis=1)
    use = (rng_all <= cfg.max_range) & (rng_all > 1e-6)
    if not use.any():
        raise SurveyError(f"no reflector detection within max_range {cfg.max_range} m")
    q, t = laser_to_map(z_all, obs.poses[obs.pose_index], obs.laser_pose)
    labels = np.full(len(obs), -1, dtype=np.int64)
    fits, members, dropped = _fit_clusters(obs, cfg, q, t, rng_all, use)
    poses = obs.poses.copy()
    if not fits:
        return ReflectorSurvey(
            np.zeros((0, 2)),
            np.zeros(0),
            np.zeros(0, dtype=np.int64),
            np.zeros(0, dtype=np.int64),
            np.zeros(0),
            float("nan"),
            labels,
            poses,
            False,
            f"no reflector seen in >= {cfg.min_views} scans from >= {cfg.min_poses} poses "
            f"({dropped} candidates dropped)",
            dropped,
            False,
        )
    X = np.array([f.position for f in fits])
    beta = np.array([f.bias for f in fits])
    for j, m in enumerate(members):
        labels[m] = j
    refined = False
    if cfg.refine_poses:
        X, beta = _refine(obs, poses, labels, X, beta, cfg)
        refined = True
    res_rms, views, seen, rms = _residuals(obs, poses, labels, X, beta, rng_all)
    return ReflectorSurvey(
        X,
        beta,
        views,
        seen,
        res_rms,
        rms,
        labels,
        poses,
        True,
        "ok",
        dropped,
        refined,
    )
