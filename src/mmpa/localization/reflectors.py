"""Laser-reflector detection and identification by triangle matching (paper 001 §3.1.1-3.1.2).

Detection: beams with intensity above a threshold are grouped into clusters of adjacent beams
(the scan wraps around at +-pi for a 360 deg lidar); the bearing ``phi`` of the reflector
CENTER is the cluster's mean beam angle (paper 001; ``bearing="mean"``, the default) or the
centroid of the intensity profile over the cluster and its partly lit neighbours
(``bearing="intensity"``: sub-beam, :func:`_intensity_bearing`), its range ``r`` the
maximum-likelihood distance of a circle of the known reflector radius under range noise along
each beam (``_fit_radial``; unbiased, where a circle fit to the hit points is ~3.5 mm short
under 15 mm range noise).

Template library ``M`` (§3.1.1, Fig. 1b): every triangle of three landmarks, with side lengths
``l1 >= l2 >= l3`` and vertex ids ordered as in §3.1.2 (``l1 = |AB|``, ``l2 = |AC|``,
``l3 = |BC|``), sorted by the longest side. Lookup (§3.1.2): binary search on ``l1``, then
filter on ``l2`` and ``l3`` within a tolerance.

Identification: every detected triangle is matched in ``M``; each match with a well-defined
vertex order proposes a rigid transform (detections -> map), scored by how many detections land
on a landmark. The best hypothesis wins only if it explains at least three detections and no
other hypothesis with a different pose explains as many (symmetric layouts, mirror triangles):
otherwise nothing is identified and the caller falls back to plain AMCL. Never a confident wrong
identification.
"""

from __future__ import annotations

from dataclasses import dataclass
from itertools import combinations
from typing import Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field

from mmpa.core.errors import InvalidInputError
from mmpa.core.geometry import Array
from mmpa.robot.interfaces import LaserScan

__all__ = [
    "DetectionConfig",
    "Identification",
    "IdentifyConfig",
    "ReflectorDetections",
    "TriangleLibrary",
    "detect_reflectors",
    "identify_reflectors",
    "rigid_fit_2d",
]


class DetectionConfig(BaseModel):
    """Reflector detection parameters (m, rad, intensity units of the scan)."""

    model_config = ConfigDict(extra="forbid")

    intensity_threshold: float = Field(1000.0, gt=0)
    radius: float = Field(0.04, ge=0)  # reflector radius (scene YAML); 0 = flat tape
    max_gap_beams: int = Field(2, ge=1)  # beams between returns of one cluster
    max_range_jump: float = Field(0.15, gt=0)  # m, between adjacent beams of one cluster
    min_beams: int = Field(1, ge=1)
    max_width: float = Field(0.3, gt=0)  # m, wider clusters are not reflectors (glare, walls)
    # a cluster whose neighbouring beam returns this much closer than the reflector is cut by
    # something in front of it (a person): its center is biased by up to ``radius``
    occlusion_margin: float = Field(0.08, gt=0)  # m
    occlusion_beams: int = Field(2, ge=1)  # beams checked on each side of a cluster
    # the bearing of a reflector's centre: "mean" of the cluster's beam angles (paper 001;
    # quantized to the beam spacing) or the "intensity" centroid over the cluster and its
    # partly lit neighbours (sub-beam: a beam whose spot half covers the reflector returns
    # about half the intensity)
    bearing: Literal["mean", "intensity"] = "mean"
    edge_beams: int = Field(2, ge=0)  # neighbours on each side in the intensity centroid


@dataclass(frozen=True)
class ReflectorDetections:
    """Detected reflector centers in the SENSOR frame.

    ``ranges`` (n,) m and ``bearings`` (n,) rad from the sensor origin; ``points`` (n, 2) m;
    ``beams`` (n,) number of returns per reflector (more beams, better center); ``occluded``
    (n,) bool: the cluster is cut by a closer return next to it (or by the edge of the scan),
    so only part of the reflector was seen and its center is biased by up to the radius.
    """

    ranges: Array
    bearings: Array
    points: Array
    beams: np.ndarray
    occluded: np.ndarray | None = None

    def __post_init__(self) -> None:
        if self.occluded is None:
            object.__setattr__(self, "occluded", np.zeros(len(self.ranges), dtype=bool))

    @property
    def cut(self) -> np.ndarray:
        """(n,) bool, ``occluded`` as a typed array."""
        assert self.occluded is not None
        return self.occluded

    def select(self, keep: np.ndarray) -> ReflectorDetections:
        """The detections where ``keep`` (bool or index array) holds."""
        return ReflectorDetections(
            self.ranges[keep],
            self.bearings[keep],
            self.points[keep],
            self.beams[keep],
            self.cut[keep],
        )

    def __len__(self) -> int:
        return int(self.ranges.shape[0])

    def transformed(self, pose: Array) -> ReflectorDetections:
        """The same detections seen from a frame in which the sensor sits at planar ``pose``
        ``[x, y, theta]`` (e.g. ``base_link`` given the lidar mount)."""
        x, y, th = np.asarray(pose, float)
        c, s = np.cos(th), np.sin(th)
        p = self.points @ np.array([[c, s], [-s, c]]) + np.array([x, y])
        return ReflectorDetections(
            np.hypot(p[:, 0], p[:, 1]), np.arctan2(p[:, 1], p[:, 0]), p, self.beams, self.cut
        )

    def range_corrected(self, bias: float) -> ReflectorDetections:
        """The same detections with ``bias`` (m) taken off every range, each center moved
        along its ray: ``r' = r - bias``, bearing unchanged. Only meaningful in the SENSOR
        frame, where a range bias of the scanner is a bias of the range."""
        r = self.ranges - bias
        u = np.stack([np.cos(self.bearings), np.sin(self.bearings)], axis=1)
        return ReflectorDetections(r, self.bearings.copy(), r[:, None] * u, self.beams, self.cut)

    @staticmethod
    def empty() -> ReflectorDetections:
        z = np.zeros(0)
        return ReflectorDetections(z, z, np.zeros((0, 2)), np.zeros(0, dtype=int))


def _check_scan(scan: LaserScan) -> tuple[Array, Array]:
    r = np.asarray(scan.ranges, float)
    inten = np.asarray(scan.intensities, float)
    if inten.shape != r.shape or inten.size == 0:
        raise InvalidInputError(
            "reflector detection needs scan intensities (one per beam); this scan has "
            f"{inten.size} intensities for {r.size} ranges"
        )
    return r, inten


def _fit_radial(r: Array, beta: Array, R: float, D0: float, iters: int = 10) -> float:
    """Distance ``D`` (m) of the centre of a reflector of radius ``R`` from the ranges ``r``
    (k,) its beams returned at bearings ``beta`` (k,) rad relative to the cluster's mean
    bearing (unbiased for a symmetric cluster, and less noisy than fitting the bearing too).

    Maximum likelihood for range noise along each beam: beam ``i`` hits a circle of radius
    ``R`` centred at distance ``D`` at the range ``f_i = D cos(beta_i) - sqrt(R^2 - D^2
    sin^2(beta_i))``; Gauss-Newton on ``sum (r_i - f_i)^2``. A beam the model circle misses
    counts at its tangent range ``D cos(beta_i)``. Fitting a circle of known radius to the hit
    points instead (``sum (|p_i - D u| - R)^2``) is biased short by ~sigma^2/R under range
    noise sigma (3.4 mm at 2 m with sigma 15 mm, R 40 mm); this estimator is not (< 0.1 mm)."""
    r = np.asarray(r, float)
    c, sn = np.cos(beta), np.sin(beta)
    if R <= 0:
        return float(np.mean(r * c))
    D = D0
    for _ in range(iters):
        disc = R**2 - (D * sn) ** 2
        hit = disc > (1e-3 * R) ** 2
        sq = np.sqrt(np.where(hit, disc, 1.0))
        f = np.where(hit, D * c - sq, D * c)
        J = np.where(hit, c + D * sn**2 / sq, c)
        step = float(J @ (r - f)) / max(float(J @ J), 1e-12)
        D += step
        if abs(step) < 1e-8:
            break
    return float(D)


def _fit_circle(pts: Array, R: float, c0: Array, iters: int = 8) -> Array:
    """Center of a circle of known radius ``R`` through points ``pts`` (k, 2), Gauss-Newton
    on ``sum (|p - c| - R)^2`` starting from ``c0``. With one point it returns ``c0``."""
    c = c0.copy()
    if len(pts) < 2 or R <= 0:
        return c
    for _ in range(iters):
        d = c - pts
        n = np.linalg.norm(d, axis=1)
        n = np.maximum(n, 1e-9)
        res = n - R
        J = d / n[:, None]
        H = J.T @ J
        if np.linalg.cond(H) > 1e8:  # all points on a line through c: radial only
            break
        step = np.linalg.solve(H, J.T @ res)
        c = c - step
        if np.linalg.norm(step) < 1e-7:
            break
    return c


def detect_reflectors(scan: LaserScan, cfg: DetectionConfig | None = None) -> ReflectorDetections:
    """Reflector centers from the high-intensity returns of ``scan`` (sensor frame).

    Beams with NaN/inf or ranges outside ``[range_min, range_max]`` are ignored. Raises
    :class:`InvalidInputError` if the scan carries no intensities.
    """
    cfg = cfg or DetectionConfig()
    r, inten = _check_scan(scan)
    a = scan.angles
    ok = scan.valid() & np.isfinite(inten) & (inten >= cfg.intensity_threshold)
    idx = np.flatnonzero(ok)
    if idx.size == 0:
        return ReflectorDetections.empty()
    n = r.shape[0]
    full_circle = (n * scan.angle_increment) >= 2 * np.pi - 1.5 * scan.angle_increment
    # split where the beam gap or the range jump is too large
    gaps = np.diff(idx) > cfg.max_gap_beams
    jumps = np.abs(np.diff(r[idx])) > cfg.max_range_jump
    starts = np.concatenate([[0], np.flatnonzero(gaps | jumps) + 1])
    clusters = [idx[s:e] for s, e in zip(starts, [*starts[1:], idx.size], strict=True)]
    if full_circle and len(clusters) > 1:
        first, last = clusters[0], clusters[-1]
        wrap_gap = first[0] + n - last[-1]
        if wrap_gap <= cfg.max_gap_beams and abs(r[first[0]] - r[last[-1]]) <= cfg.max_range_jump:
            clusters = [np.concatenate([last, first]), *clusters[1:-1]]
    valid = scan.valid()
    rng_out, brg, pts, beams, cut = [], [], [], [], []
    for cl in clusters:
        if cl.size < cfg.min_beams:
            continue
        p = np.column_stack([r[cl] * np.cos(a[cl]), r[cl] * np.sin(a[cl])])
        if np.linalg.norm(p[0] - p[-1]) > cfg.max_width:
            continue
        bearing = float(np.angle(np.exp(1j * a[cl]).mean()))
        if cfg.bearing == "intensity":
            bearing = _intensity_bearing(cl, a, inten, r, valid, bearing, n, full_circle, cfg)
        rr = float(np.mean(r[cl]))
        u = np.array([np.cos(bearing), np.sin(bearing)])
        beta = np.angle(np.exp(1j * (a[cl] - bearing)))
        D = _fit_radial(r[cl], beta, cfg.radius, rr + cfg.radius * np.pi / 4)
        # a degenerate fit (glare, too few points) falls back to the mean hit plus the radius
        if not np.isfinite(D) or abs(D - rr - cfg.radius) > cfg.radius:
            D = rr + cfg.radius
        c = D * u
        rng_out.append(float(np.hypot(*c)))
        brg.append(float(np.arctan2(c[1], c[0])))
        pts.append(c)
        beams.append(cl.size)
        cut.append(_occluded(cl, r, valid, n, full_circle, cfg))
    if not pts:
        return ReflectorDetections.empty()
    return ReflectorDetections(
        np.array(rng_out),
        np.array(brg),
        np.array(pts),
        np.array(beams, dtype=int),
        np.array(cut, dtype=bool),
    )


def _intensity_bearing(
    cl: np.ndarray,
    a: Array,
    inten: Array,
    r: Array,
    valid: np.ndarray,
    bearing: float,
    n: int,
    full_circle: bool,
    cfg: DetectionConfig,
) -> float:
    """Bearing (rad) of a reflector's centre as the centroid of the intensity profile over
    cluster ``cl`` and its partly lit neighbours: ``phi = sum_i w_i a_i / sum_i w_i`` with
    ``w_i = I_i - I_bg`` (clipped at 0). The neighbours are up to ``edge_beams`` valid beams
    on each side below the threshold whose range is within ``max_range_jump`` of the
    cluster's (a mixed return is pulled to the bright reflector; a closer object in front
    ends the window); ``I_bg`` is the lowest intensity among all ``edge_beams`` beams on
    either side (the background surface). The profile is the reflector's angular extent
    blurred by the beam's spot; for a symmetric spot its centroid is the reflector's
    centre, and the partly lit edge beams place it between beams, where the cluster's mean
    angle moves in whole beam steps. Falls back to ``bearing`` (the mean angle) if the
    weights vanish."""
    r_cl = float(np.median(r[cl]))
    side: list[np.ndarray] = []
    bg: list[float] = []
    for start, step in ((cl[0], -1), (cl[-1], 1)):
        nb = start + step * np.arange(1, cfg.edge_beams + 1)
        if full_circle:
            nb = nb % n
        else:
            nb = nb[(nb >= 0) & (nb < n)]
        lit = valid[nb] & np.isfinite(inten[nb])
        dim = lit & (inten[nb] < cfg.intensity_threshold)  # lit, below the threshold
        bg.extend(inten[nb][dim].tolist())
        ok = dim & (np.abs(np.where(lit, r[nb], np.inf) - r_cl) <= cfg.max_range_jump)
        # the window ends at the first beam that is not a plain neighbour
        stop = np.flatnonzero(~ok)
        side.append(nb[: stop[0]] if stop.size else nb)
    win = np.concatenate([side[0][::-1], cl, side[1]])
    i_bg = min(bg) if bg else float(inten[win].min())
    w = np.clip(inten[win] - i_bg, 0.0, None)
    if not np.isfinite(w).all() or w.sum() <= 0:
        return bearing
    d = np.angle(np.exp(1j * (a[win] - bearing)))
    return float(bearing + (w @ d) / w.sum())


def _occluded(
    cl: np.ndarray, r: Array, valid: np.ndarray, n: int, full_circle: bool, cfg: DetectionConfig
) -> bool:
    """True if a valid return within ``occlusion_beams`` beams on either side of cluster ``cl``
    is closer than the cluster's nearest hit by more than ``occlusion_margin`` (an object in
    front cuts the reflector), or the cluster touches the edge of a partial scan."""
    near = float(r[cl].min()) - cfg.occlusion_margin
    for side in (
        cl[0] - np.arange(1, cfg.occlusion_beams + 1),
        cl[-1] + np.arange(1, cfg.occlusion_beams + 1),
    ):
        if full_circle:
            side = side % n
        elif side.min() < 0 or side.max() >= n:
            return True
        ok = valid[side]
        if ok.any() and float(r[side][ok].min()) < near:
            return True
    return False


# --- template library --------------------------------------------------------------------------


class TriangleLibrary:
    """The matching template library ``M`` of §3.1.1.

    ``sides`` (T, 3) ``l1 >= l2 >= l3`` (m), ``ids`` (T, 3) landmark ids of vertices A, B, C with
    ``l1 = |AB|``, ``l2 = |AC|``, ``l3 = |BC|``; rows sorted by ``l1``.
    """

    def __init__(self, landmarks: Array) -> None:
        L = np.asarray(landmarks, float)
        if L.ndim != 2 or L.shape[1] != 2 or not np.all(np.isfinite(L)):
            raise InvalidInputError(f"landmarks must be finite (N, 2), got shape {L.shape}")
        self.landmarks = L
        tri = np.array(list(combinations(range(len(L)), 3)), dtype=int).reshape(-1, 3)
        if len(tri) == 0:
            self.sides = np.zeros((0, 3))
            self.ids = np.zeros((0, 3), dtype=int)
            return
        sides, ids = _order_triangles(L, tri)
        order = np.argsort(sides[:, 0], kind="stable")
        self.sides, self.ids = sides[order], ids[order]

    def __len__(self) -> int:
        return int(self.sides.shape[0])

    def lookup(self, sides: Array, tol: float) -> np.ndarray:
        """Indices of library triangles whose three sides match ``sides`` = (l1, l2, l3)
        (sorted, descending) within ``tol`` m: binary search on ``l1``, then ``l2``, ``l3``."""
        lo = np.searchsorted(self.sides[:, 0], sides[0] - tol, "left")
        hi = np.searchsorted(self.sides[:, 0], sides[0] + tol, "right")
        cand = np.arange(lo, hi)
        ok = (np.abs(self.sides[cand, 1] - sides[1]) <= tol) & (
            np.abs(self.sides[cand, 2] - sides[2]) <= tol
        )
        return cand[ok]


def _order_triangles(P: Array, tri: np.ndarray) -> tuple[Array, np.ndarray]:
    """Side lengths (l1 >= l2 >= l3) and vertices (A, B, C) with l1=AB, l2=AC, l3=BC."""
    i, j, k = tri[:, 0], tri[:, 1], tri[:, 2]
    # side opposite each vertex: opp[i] = |jk| etc.
    opp = np.stack(
        [
            np.linalg.norm(P[j] - P[k], axis=1),
            np.linalg.norm(P[i] - P[k], axis=1),
            np.linalg.norm(P[i] - P[j], axis=1),
        ],
        axis=1,
    )
    # vertex opposite the longest side is C, opposite the middle is B, opposite shortest is A
    order = np.argsort(-opp, axis=1, kind="stable")  # longest first
    rows = np.arange(len(tri))[:, None]
    sides = opp[rows, order]
    verts = tri[rows, order]  # verts[:,0] opposite l1 = C, [:,1] opposite l2 = B, [:,2] = A
    ids = np.stack([verts[:, 2], verts[:, 1], verts[:, 0]], axis=1)
    return sides, ids


def _rot_angle(R: Array) -> float:
    return float(np.arctan2(R[1, 0], R[0, 0]))


def rigid_fit_2d(src: Array, dst: Array) -> tuple[Array, Array]:
    """Least-squares rotation R (2, 2), det +1, and translation t with ``dst ~ src R^T + t``
    (Kabsch / Umeyama without scale)."""
    ms, md = src.mean(axis=0), dst.mean(axis=0)
    H = (src - ms).T @ (dst - md)
    U, _, Vt = np.linalg.svd(H)
    D = np.diag([1.0, np.sign(np.linalg.det(Vt.T @ U.T)) or 1.0])
    R = Vt.T @ D @ U.T
    return R, md - R @ ms


class IdentifyConfig(BaseModel):
    """Triangle matching tolerances."""

    model_config = ConfigDict(extra="forbid")

    side_tol: float = Field(0.06, gt=0)  # m, |l_detected - l_library| per side
    ambiguity_margin: float = Field(0.06, gt=0)  # m: sides closer than this give no vertex order
    inlier_tol: float = Field(0.08, gt=0)  # m, detection to landmark after the fitted transform
    same_pose_tol: float = Field(0.15, gt=0)  # m: hypotheses closer than this agree
    max_triangles: int = Field(20, ge=1)  # detected triangles tried (nearest reflectors first)


@dataclass(frozen=True)
class Identification:
    """``ids`` (n,) landmark id of each detection, -1 where unidentified; ``status`` says why
    nothing was identified ("ok", "too_few", "no_match", "ambiguous")."""

    ids: np.ndarray
    status: str

    @property
    def count(self) -> int:
        return int((self.ids >= 0).sum())


def identify_reflectors(
    det_xy: Array, library: TriangleLibrary, cfg: IdentifyConfig | None = None
) -> Identification:
    """Identify detections ``det_xy`` (n, 2), in any robot-fixed frame, against ``library``.

    See the module docstring for the hypothesis scoring and the ambiguity rule.
    """
    cfg = cfg or IdentifyConfig()
    P = np.asarray(det_xy, float).reshape(-1, 2)
    n = len(P)
    none = np.full(n, -1, dtype=int)
    if n < 3 or len(library) == 0:
        return Identification(none, "too_few")
    L = library.landmarks
    order = np.argsort(np.linalg.norm(P, axis=1))  # near reflectors are measured best
    tri = np.array(list(combinations(order.tolist(), 3)), dtype=int)[: cfg.max_triangles]
    sides, verts = _order_triangles(P, tri)
    hyps: list[tuple[int, float, Array, Array, np.ndarray]] = []
    for s, v in zip(sides, verts, strict=True):
        if min(s[0] - s[1], s[1] - s[2]) < cfg.ambiguity_margin:
            continue  # isosceles within noise: vertex order undefined
        for m in library.lookup(s, cfg.side_tol):
            R, t = rigid_fit_2d(P[v], L[library.ids[m]])
            q = P @ R.T + t
            d = np.linalg.norm(q[:, None, :] - L[None, :, :], axis=2)
            nn = d.argmin(axis=1)
            inl = d[np.arange(n), nn] <= cfg.inlier_tol
            ids = np.where(inl, nn, -1)
            # a landmark claimed twice: keep the closer detection
            for lm in np.unique(ids[ids >= 0]):
                dup = np.flatnonzero(ids == lm)
                if len(dup) > 1:
                    keep = dup[np.argmin(d[dup, lm])]
                    ids[dup[dup != keep]] = -1
            cnt = int((ids >= 0).sum())
            if cnt >= 3:
                err = float(np.mean(d[ids >= 0, ids[ids >= 0]]))
                hyps.append((cnt, err, R, t, ids))
    if not hyps:
        return Identification(none, "no_match")
    best = max(hyps, key=lambda h: (h[0], -h[1]))
    for h in hyps:
        if h[0] == best[0] and (
            np.linalg.norm(h[3] - best[3]) > cfg.same_pose_tol
            or abs(_rot_angle(h[2].T @ best[2])) > 0.05
        ):
            return Identification(none, "ambiguous")
    return Identification(best[4], "ok")
