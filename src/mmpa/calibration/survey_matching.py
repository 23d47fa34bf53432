"""Matching for the reflector survey (:mod:`mmpa.calibration.reflector_survey`): a standing
stop's scan onto the occupancy map (:func:`match_scan_to_map` on the signed distance field
of :func:`signed_distance_map`: ``min sum_i rho(sdf(t + R(phi) z_i))``, Huber ``rho``),
the surveyed layout rigidly onto an earlier reflector map (:func:`anchor_to`, Kabsch on
one-to-one pairs) and the one-to-one matching itself (:func:`match_reflectors`, Hungarian on
distance, also the evaluation against a truth); and :class:`SurveyError`.

Units: m, rad. Pure functions over numpy arrays.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import ndimage
from scipy.optimize import least_squares, linear_sum_assignment

from mmpa.core.errors import InvalidInputError
from mmpa.core.geometry import Array
from mmpa.localization.reflectors import rigid_fit_2d

__all__ = [
    "ReflectorMatch",
    "SurveyError",
    "anchor_to",
    "match_reflectors",
    "match_scan_to_map",
    "signed_distance_map",
]


class SurveyError(InvalidInputError):
    """The survey cannot be computed from these observations (none, or none usable)."""


@dataclass(frozen=True)
class ReflectorMatch:
    """Estimated reflectors matched one-to-one to reference ones: ``pairs`` (F, 2) indices
    (estimate, reference), ``errors`` (F,) m, ``missed`` reference indices without an
    estimate, ``spurious`` estimate indices without a reference."""

    pairs: np.ndarray
    errors: Array
    missed: np.ndarray
    spurious: np.ndarray


def match_reflectors(est: Array, ref: Array, gate: float = 0.25) -> ReflectorMatch:
    """One-to-one matching (Hungarian, on distance) of ``est`` (N, 2) to ``ref`` (K, 2);
    pairs farther than ``gate`` m are not matched. Evaluation against a truth."""
    est = np.asarray(est, float).reshape(-1, 2)
    ref = np.asarray(ref, float).reshape(-1, 2)
    if len(est) == 0 or len(ref) == 0:
        none = np.zeros((0, 2), dtype=np.int64)
        return ReflectorMatch(none, np.zeros(0), np.arange(len(ref)), np.arange(len(est)))
    D = np.linalg.norm(est[:, None, :] - ref[None, :, :], axis=2)
    r, c = linear_sum_assignment(np.where(D <= gate, D, 1e6))
    ok = D[r, c] <= gate
    r, c = r[ok], c[ok]
    return ReflectorMatch(
        np.stack([r, c], axis=1).astype(np.int64),
        D[r, c],
        np.setdiff1d(np.arange(len(ref)), c),
        np.setdiff1d(np.arange(len(est)), r),
    )


def anchor_to(est: Array, ref: Array, gate: float = 0.25) -> tuple[Array, Array, int]:
    """Move the surveyed layout ``est`` (N, 2) rigidly onto reference positions ``ref``
    (K, 2) (an earlier reflector map: control points): match one-to-one within ``gate`` m
    (:func:`match_reflectors`), then the least-squares rotation and translation
    ``est R^T + t`` of the matched pairs (Kabsch, no scale). The layout's shape (from the
    lidar) is kept; only its placement comes from ``ref``, whose independent errors
    ``s`` average to about ``s / sqrt(K)``. Returns (the moved ``est``, the transform
    ``[tx, ty, theta]``, the number of pairs). Raises :class:`SurveyError` with fewer than
    two pairs."""

    est = np.asarray(est, float).reshape(-1, 2)
    m = match_reflectors(est, ref, gate)
    if len(m.pairs) < 2:
        raise SurveyError(
            f"anchoring needs at least 2 surveyed reflectors within {gate} m of the reference "
            f"map, got {len(m.pairs)}"
        )
    R, t = rigid_fit_2d(est[m.pairs[:, 0]], np.asarray(ref, float)[m.pairs[:, 1]])
    th = float(np.arctan2(R[1, 0], R[0, 0]))
    return est @ R.T + t, np.array([t[0], t[1], th]), len(m.pairs)


def signed_distance_map(occupied: np.ndarray, resolution: float) -> Array:
    """Signed distance (H, W) m at the cell centres of an occupancy grid ``occupied`` (H, W)
    bool to the boundary between occupied and free cells: ``+`` in free space, ``-`` inside
    obstacles. A grid that marks every cell whose centre lies in an obstacle has its
    surface between the last occupied and the first free centre; the boundary midway is
    its unbiased estimate (uniform error within +- half a cell), so the field is
    ``edt(free) - 1/2`` cells outside and ``-(edt(occupied) - 1/2)`` inside."""
    occ = np.asarray(occupied, bool)
    if occ.ndim != 2 or not occ.any() or occ.all():
        raise InvalidInputError("the map needs both occupied and free cells (a 2D grid)")
    out = ndimage.distance_transform_edt(~occ) - 0.5
    inside = ndimage.distance_transform_edt(occ) - 0.5
    return np.where(occ, -inside, out) * float(resolution)


def match_scan_to_map(
    sdf: Array,
    resolution: float,
    origin: tuple[float, float],
    points: Array,
    guess: Array,
    huber: float = 0.05,
    max_dist: float = 0.3,
) -> tuple[Array, float, int]:
    """The laser pose ``[x, y, phi]`` in ``map`` that puts the scan ``points`` (K, 2, laser
    frame) on the map's surfaces: ``min sum_i rho(sdf(t + R(phi) z_i))`` with ``sdf`` the
    signed distance field (:func:`signed_distance_map`, (H, W) m, cell (row 0, col 0) centred
    at ``origin + resolution / 2``), cubic-spline interpolated, ``rho`` Huber (scale
    ``huber`` m), from ``guess``; points farther than ``max_dist`` m from any surface at the
    guess (things not in the map) are left out. Returns (pose, RMS m of the inlying
    distances, number of points used)."""
    pts = np.asarray(points, float).reshape(-1, 2)
    g = np.asarray(guess, float)
    if g.shape != (3,) or not np.isfinite(g).all() or not np.isfinite(pts).all():
        raise InvalidInputError(f"need a finite guess [x, y, phi] and points, got {g}")
    coef = ndimage.spline_filter(np.asarray(sdf, float), order=3, mode="nearest")
    ox, oy = float(origin[0]), float(origin[1])

    def dist(v: Array, z: Array) -> Array:
        c, sn = np.cos(v[2]), np.sin(v[2])
        x = v[0] + c * z[:, 0] - sn * z[:, 1]
        y = v[1] + sn * z[:, 0] + c * z[:, 1]
        rc = np.stack([(y - oy) / resolution - 0.5, (x - ox) / resolution - 0.5])
        return ndimage.map_coordinates(coef, rc, order=3, mode="nearest", prefilter=False)

    use = pts[np.abs(dist(g, pts)) <= max_dist]
    if len(use) < 10:
        raise SurveyError(f"only {len(use)} scan points lie near the map's surfaces")
    sol = least_squares(
        lambda v: dist(v, use), g, loss="huber", f_scale=huber, x_scale=[0.01, 0.01, 0.005]
    )
    r = dist(sol.x, use)
    inl = np.abs(r) <= huber
    return sol.x, float(np.sqrt(np.mean(r[inl] ** 2))) if inl.any() else float("nan"), len(use)
