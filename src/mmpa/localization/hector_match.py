"""The scan-to-map fit of :class:`~mmpa.localization.hector.HectorMatcher`: map fields, the
damped (Levenberg-Marquardt) and undamped (Gauss-Newton) solvers, and a correlative search.

A scan's endpoints ``p_i`` (base frame, m) are moved by a pose ``x = [x, y, theta]``:
``S_i(x) = R(theta) p_i + [x, y]``, with ``dS_i/dtheta = R'(theta) p_i``. A field gives each
moved endpoint a residual ``r_i``, its gradient ``dr_i/dS`` (per m) and a weight ``w_i``;
the fit minimizes ``C(x) = sum_i rho(r_i)`` level by level, coarse to fine:

- :class:`OccupancyLevels` (Hector as published, Kohlbrecher et al. 2011): ``r_i = 1 -
  M(S_i)``, ``M`` the bilinearly interpolated occupancy of a map pyramid (level ``k``: cells
  ``2^k`` times larger, a cell occupied if any of its fine cells is, blurred by a Gaussian of
  ``blur`` cells and divided by its maximum), ``rho(r) = r^2``, ``w_i = 1``.
- :class:`DistanceLevels` (improvement): ``r_i = d(S_i)``, ``d`` the bilinearly
  interpolated Euclidean distance (m) from a cell centre to the nearest occupied cell centre
  of the FINE grid at every level; ``rho`` Geman-McClure ``q / (1 + q)``, ``q = (r /
  sigma_k)^2``, with the scale doubling per coarser level (``sigma_k = sigma 2^k``); IRLS
  weights ``w_i = 1 / (1 + q_i)^2``. No down-sampling moves a wall, and the field's slope is
  1 on every side of every wall, however thick or isolated.

Solvers, per level: :func:`gauss_newton` (the published step ``dx = (J^T J)^-1 J^T (1 - M)``,
always taken); :func:`levenberg_marquardt`: ``dx = -(H + lambda diag H)^-1 g`` with
``H = sum w J^T J``, ``g = sum w J^T r``, taken only when it lowers ``C`` (else ``lambda`` x 10,
retried; after a taken step ``lambda`` / 10), stopping when a step is below ``tol`` or no
step lowers ``C``. On the finest distance level ``C = n - n * score`` (the score below), so
a taken step never lowers the score.

Score of a match (0..1, 1 with every endpoint on a wall): the mean of ``M`` on the finest
occupancy level, or of ``1 / (1 + (d / sigma)^2)`` on the distance field.

:func:`correlative_search` (improvement, Olson 2009, "Real-time correlative scan matching"):
before the fit, every pose of a grid around the prediction (``+-window_xy`` in steps of
``step``, ``+-window_theta`` in steps of ``step / r90``, ``r90`` the 90th percentile of the
ranges) is scored by the mean of ``exp(-d^2 / (2 step^2))`` at its endpoints (nearest cell)
less a prior ``prior ((dx^2 + dy^2) / window_xy^2 + dtheta^2 / window_theta^2)``; the best
is the fit's start. The prior keeps a pose the scan cannot tell apart (along a corridor) at
the prediction.

Units: m, rad; poses in ``map``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import ndimage

from mmpa.core.geometry import Array
from mmpa.localization.pose import wrap as _wrap

__all__ = [
    "DistanceLevels",
    "Fit",
    "OccupancyLevels",
    "correlative_search",
    "gauss_newton",
    "levenberg_marquardt",
    "move",
]


def move(x: Array, pts: Array) -> Array:
    """``R(theta) p + [x, y]`` for the endpoints ``pts`` (k, 2)."""
    c, s = np.cos(x[2]), np.sin(x[2])
    return pts @ np.array([[c, s], [-s, c]]) + x[:2]


def pose_jacobian(x: Array, pts: Array, grad: Array) -> Array:
    """(k, 3) ``dr_i/dx``: the field's gradient ``grad`` (k, 2) at the moved endpoints times
    ``dS_i/dx`` (identity in x, y; ``R'(theta) p_i`` in theta)."""
    c, s = np.cos(x[2]), np.sin(x[2])
    dth = np.column_stack([-s * pts[:, 0] - c * pts[:, 1], c * pts[:, 0] - s * pts[:, 1]])
    return np.column_stack([grad[:, 0], grad[:, 1], np.sum(grad * dth, axis=1)])


def bilinear(
    field: Array, res: float, origin: tuple[float, float], pts: Array
) -> tuple[Array, Array]:
    """Bilinear value (k,) and gradient (k, 2) (per m) of ``field`` (H, W; value ``[i, j]``
    at the centre of cell row ``i``, column ``j``) at ``pts`` (k, 2); clamped at the edge."""
    gx = (pts[:, 0] - origin[0]) / res - 0.5
    gy = (pts[:, 1] - origin[1]) / res - 0.5
    h, w = field.shape
    x0 = np.clip(np.floor(gx).astype(int), 0, w - 2)
    y0 = np.clip(np.floor(gy).astype(int), 0, h - 2)
    fx = np.clip(gx - x0, 0, 1)
    fy = np.clip(gy - y0, 0, 1)
    m00 = field[y0, x0]
    m10 = field[y0, x0 + 1]
    m01 = field[y0 + 1, x0]
    m11 = field[y0 + 1, x0 + 1]
    val = fy * (fx * m11 + (1 - fx) * m01) + (1 - fy) * (fx * m10 + (1 - fx) * m00)
    dx = (fy * (m11 - m01) + (1 - fy) * (m10 - m00)) / res
    dy = (fx * (m11 - m10) + (1 - fx) * (m01 - m00)) / res
    return val, np.column_stack([dx, dy])


class OccupancyLevels:
    """Hector's map pyramid (module docstring). ``occ`` (H, W) bool, ``res`` m per cell."""

    def __init__(
        self, occ: Array, res: float, origin: tuple[float, float], levels: int, blur: float
    ) -> None:
        self.origin = origin
        self.maps: list[tuple[Array, float]] = []
        for k in range(levels):
            f = 2**k
            h, w = occ.shape[0] // f, occ.shape[1] // f
            o = occ[: h * f, : w * f].reshape(h, f, w, f).any(axis=(1, 3))
            m = o.astype(float)
            if blur > 0:
                m = ndimage.gaussian_filter(m, blur)
                m = m / max(float(m.max()), 1e-9)
            self.maps.append((m, res * f))

    @property
    def levels(self) -> int:
        return len(self.maps)

    def residuals(self, level: int, wp: Array) -> tuple[Array, Array, Array]:
        """``r = 1 - M``, ``dr/dS = -grad M``, weights 1 at the moved endpoints ``wp``."""
        m, res = self.maps[level]
        val, g = bilinear(m, res, self.origin, wp)
        return 1.0 - val, -g, np.ones_like(val)

    def cost(self, level: int, wp: Array) -> float:
        r, _, _ = self.residuals(level, wp)
        return float(r @ r)

    def score(self, wp: Array) -> float:
        val, _ = bilinear(*self.maps[0], self.origin, wp)
        return float(np.mean(val)) if val.size else 0.0


class DistanceLevels:
    """The distance field with a Geman-McClure scale per level (module docstring).
    ``occ`` (H, W) bool, ``res`` m per cell, ``sigma`` m the finest scale."""

    def __init__(
        self,
        occ: Array,
        res: float,
        origin: tuple[float, float],
        levels: int,
        sigma: float,
        max_dist: float = 2.0,
    ) -> None:
        self.origin = origin
        self.res = res
        if occ.any():
            d = ndimage.distance_transform_edt(~occ) * res
        else:
            d = np.full(occ.shape, max_dist)
        self.dist = np.minimum(d, max_dist)
        self.sigmas = [sigma * 2**k for k in range(levels)]

    @property
    def levels(self) -> int:
        return len(self.sigmas)

    def residuals(self, level: int, wp: Array) -> tuple[Array, Array, Array]:
        """``r = d``, ``dr/dS = grad d``, IRLS weights ``1 / (1 + q)^2``."""
        d, g = bilinear(self.dist, self.res, self.origin, wp)
        q = (d / self.sigmas[level]) ** 2
        return d, g, 1.0 / (1.0 + q) ** 2

    def cost(self, level: int, wp: Array) -> float:
        d, _ = bilinear(self.dist, self.res, self.origin, wp)
        q = (d / self.sigmas[level]) ** 2
        return float(np.sum(q / (1.0 + q)))

    def score(self, wp: Array) -> float:
        d, _ = bilinear(self.dist, self.res, self.origin, wp)
        return float(np.mean(1.0 / (1.0 + (d / self.sigmas[0]) ** 2))) if d.size else 0.0


Field = OccupancyLevels | DistanceLevels


@dataclass
class Fit:
    """A fitted pose ``[x, y, theta]``, the finest level's ``H = sum w J^T J`` (its inverse:
    the published Hector covariance), the weighted residual variance ``s2`` (m^2 for the
    distance field), the score (module docstring), and the steps taken / tried."""

    pose: Array
    H: Array
    s2: float
    score: float
    steps: int
    tries: int


def _normal_equations(field: Field, level: int, x: Array, pts: Array) -> tuple[Array, Array, float]:
    r, g, w = field.residuals(level, move(x, pts))
    J = pose_jacobian(x, pts, g)
    Jw = J * w[:, None]
    s2 = float(np.sum(w * r * r) / max(len(r) - 3, 1))
    return Jw.T @ J, Jw.T @ r, s2


def gauss_newton(field: Field, guess: Array, pts: Array, iterations: int) -> Fit:
    """Hector's undamped Gauss-Newton, coarse to fine, ``iterations`` steps per level (a
    step below 1e-5 m / rad ends the level); ``H`` of the last step (+ 1e-6 I)."""
    x = np.asarray(guess, float).copy()
    H, s2, steps = np.eye(3), float("nan"), 0
    for level in reversed(range(field.levels)):
        for _ in range(iterations):
            H, b, s2 = _normal_equations(field, level, x, pts)
            H = H + 1e-6 * np.eye(3)
            step = -np.linalg.solve(H, b)
            x = x + step
            x[2] = float(_wrap(x[2]))
            steps += 1
            if np.linalg.norm(step[:2]) < 1e-5 and abs(step[2]) < 1e-5:
                break
    return Fit(x, H, s2, field.score(move(x, pts)), steps, steps)


def levenberg_marquardt(
    field: Field,
    guess: Array,
    pts: Array,
    iterations: int,
    tol_xy: float = 1e-4,
    tol_theta: float = 1e-4,
    lam0: float = 1e-3,
    trace: list[tuple[int, Array, float]] | None = None,
) -> Fit:
    """Damped steps, taken only when they lower the level's cost (module docstring), at most
    ``iterations`` taken steps per level; a step below ``tol_xy`` m and ``tol_theta`` rad, or
    ``lambda`` past 1e8, ends the level. ``trace``: gets ``(level, pose, cost)`` at each
    level's start and after every taken step."""
    x = np.asarray(guess, float).copy()
    steps = tries = 0
    for level in reversed(range(field.levels)):
        lam = lam0
        cost = field.cost(level, move(x, pts))
        if trace is not None:
            trace.append((level, x.copy(), cost))
        for _ in range(iterations):
            H, b, _ = _normal_equations(field, level, x, pts)
            damp = np.diag(np.maximum(np.diag(H), 1e-12))
            taken = False
            while lam <= 1e8:
                tries += 1
                step = -np.linalg.solve(H + lam * damp, b)
                cand = x + step
                c_new = field.cost(level, move(cand, pts))
                if c_new < cost:
                    x, cost, taken = cand, c_new, True
                    lam = max(lam / 10, 1e-9)
                    steps += 1
                    if trace is not None:
                        trace.append((level, x.copy(), cost))
                    break
                lam *= 10
            if not taken or (np.abs(step[:2]).max() < tol_xy and abs(step[2]) < tol_theta):
                break
    x[2] = float(_wrap(x[2]))
    H, _, s2 = _normal_equations(field, 0, x, pts)
    return Fit(x, H, s2, field.score(move(x, pts)), steps, tries)


def correlative_search(
    table: Array,
    res: float,
    origin: tuple[float, float],
    guess: Array,
    pts: Array,
    window_xy: float,
    window_theta: float,
    step: float,
    prior: float,
) -> Array:
    """The best pose of the search grid around ``guess`` (module docstring). ``table`` (H,
    W): ``exp(-d^2 / (2 step^2))`` per cell; endpoints off the map score 0."""
    r90 = float(np.percentile(np.hypot(pts[:, 0], pts[:, 1]), 90)) if len(pts) else 1.0
    dth = step / max(r90, 1.0)
    n_th = int(np.ceil(window_theta / dth))
    k = max(1, round(step / res))
    n_xy = int(np.floor(window_xy / (k * res)))
    shifts = np.arange(-n_xy, n_xy + 1) * k
    off = shifts * res
    pen_xy = (off[:, None] ** 2 + off[None, :] ** 2) / max(window_xy, 1e-9) ** 2
    h, w = table.shape
    best, best_pose = -np.inf, np.asarray(guess, float).copy()
    for j in range(-n_th, n_th + 1):
        th = guess[2] + j * dth
        wp = move(np.array([guess[0], guess[1], th]), pts)
        ix = np.floor((wp[:, 0] - origin[0]) / res).astype(int)
        iy = np.floor((wp[:, 1] - origin[1]) / res).astype(int)
        X = ix[None, None, :] + shifts[None, :, None]
        Y = iy[None, None, :] + shifts[:, None, None]
        inside = (X >= 0) & (X < w) & (Y >= 0) & (Y < h)
        vals = np.where(inside, table[np.clip(Y, 0, h - 1), np.clip(X, 0, w - 1)], 0.0)
        s = vals.mean(axis=-1) - prior * (pen_xy + (j * dth / max(window_theta, 1e-9)) ** 2)
        a, b = np.unravel_index(int(np.argmax(s)), s.shape)
        if s[a, b] > best:
            best = float(s[a, b])
            best_pose = np.array([guess[0] + off[b], guess[1] + off[a], th])
    return best_pose
