"""The Gauss-Newton stages of the projective refinement (:mod:`mmpa.registration.projective`).

Unknowns: a left-multiplied twist ``[v, w]`` on ``T = [R, t]`` (m, rad), ``log s`` (the
relative depth scale, with ``estimate_scale``), the disparity drift ``dd = a + b_x x + b_y y``
(px; ``x, y`` the source point's normalized image coordinates) and, in the photometric pass,
the brightness model ``[g, o, o_x, o_y]``. Each stage is a function of the constant
:class:`Problem` and the current :class:`Estimate` (never changed in place: a stage returns a
new one):

- :func:`corrected`: the source points moved along their rays by the drift,
  ``p(dd) = p / (1 + p_z dd / (f b))``;
- :func:`associate`: projective data association, ``Q = s R p + t`` to the pixel
  ``round(K Q / Q_z)``, point-to-plane residuals ``r = (Q - q) . n`` gated by ``gate`` and
  ``depth_gate``;
- :func:`chain`: the Jacobian columns ``[g, Q x g]``, ``g . (Q - t)`` (``log s``),
  ``-(p_z(dd) / (f b)) g . (Q - t)`` times ``[1, x, y]`` (drift) of residuals with gradient
  ``g`` in ``Q``;
- :func:`photometric`: ``r = I(pi(Q)) - ((1 + g) c + o + o_x x + o_y y)`` with
  ``dr/dQ = grad I . dpi/dQ``;
- :func:`solve_round`: IRLS Gauss-Newton (robust weights, zero-mean priors ``(c / sd)^2``),
  stopped at ``|dx| < tolerance``;
- :func:`objective` and :func:`photometric_pass`: the joint depth + colour pass coarse to
  fine over blurred images, two starts (the kernel throughout, graduated), the lower
  objective kept.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from typing import Any, NamedTuple

import numpy as np
from scipy import ndimage

from mmpa.core.geometry import Array, exp_se3
from mmpa.registration.config import ProjectiveConfig
from mmpa.registration.projective_maps import (
    TargetMap,
    bilinear,
    robust_weights,
    source_grey_levels,
    target_at,
)
from mmpa.robot.description import CameraIntrinsics

__all__ = [
    "Estimate",
    "Problem",
    "associate",
    "chain",
    "corrected",
    "objective",
    "photometric",
    "photometric_pass",
    "problem",
    "rho",
    "solve_round",
]


@dataclass(frozen=True)
class Problem:
    """The constants of one refinement: the source points ``P`` (N, 3) m, their disparity
    regressors ``Xd`` (N, n_disp) and normalized image coordinates ``xs_f, ys_f`` (N,; 0
    where undefined), ``fb`` (px m), the parameter counts, the intrinsics, the target map,
    and the zero-mean priors ``(parameter index, SD, disparity index or -1 for log s)``."""

    cfg: ProjectiveConfig
    P: Array
    Xd: Array
    xs_f: Array
    ys_f: Array
    fb: float
    n_par: int
    n_disp: int
    fx: float
    fy: float
    cx: float
    cy: float
    target: TargetMap
    prior_terms: tuple[tuple[int, float, int], ...]

    @property
    def n_all(self) -> int:
        return self.n_par + self.n_disp


class Estimate(NamedTuple):
    """The current estimate: ``R`` (3, 3), ``t`` (3,) m, ``log_s``, ``disp`` (n_disp,) px
    ``[a, b_x, b_y]``, ``bright`` (4,) ``[g, o, o_x, o_y]``."""

    R: Array
    t: Array
    log_s: float
    disp: Array
    bright: Array


def problem(
    P: Array,
    cfg: ProjectiveConfig,
    intrinsics: CameraIntrinsics,
    disparity_fb: float | None,
    target: TargetMap,
) -> Problem:
    """The :class:`Problem` of the source points ``P`` (N, 3) against ``target``."""
    n_par = 7 if cfg.estimate_scale else 6
    n_disp = 0
    if disparity_fb is not None:
        n_disp = {"none": 0, "offset": 1, "affine": 3}[cfg.disparity_model]
    # the disparity's regressors per source point: 1, x, y (normalized image coordinates)
    with np.errstate(divide="ignore", invalid="ignore"):
        xs, ys = P[:, 0] / P[:, 2], P[:, 1] / P[:, 2]
    Xd = np.column_stack([np.ones(len(P)), xs, ys])[:, :n_disp]
    fb = float(disparity_fb) if disparity_fb is not None else 1.0
    # (parameter index, prior SD, which value) of the parameters with a zero-mean prior
    prior_terms: list[tuple[int, float, int]] = []
    if cfg.estimate_scale and cfg.scale_prior is not None:
        prior_terms.append((6, cfg.scale_prior, -1))
    if n_disp and cfg.disparity_prior_px is not None:
        for j in range(n_disp):
            sd = cfg.disparity_prior_px[0 if j == 0 else 1]
            prior_terms.append((n_par + j, sd, j))
    fx, fy, cx, cy = intrinsics.fx, intrinsics.fy, intrinsics.cx, intrinsics.cy
    xs_f, ys_f = np.nan_to_num(xs), np.nan_to_num(ys)
    return Problem(
        cfg, P, Xd, xs_f, ys_f, fb, n_par, n_disp, fx, fy, cx, cy, target, tuple(prior_terms)
    )


def _prior_value(est: Estimate, which: int) -> Any:
    """The current value of a prior's parameter: ``log s`` (``which`` -1) or ``disp[which]``."""
    return est.log_s if which < 0 else est.disp[which]


def corrected(pb: Problem, disp: Array, idx: Array | None = None) -> Array:
    """The source points ``P[idx]`` (None: all) moved along their rays by the disparity
    drift ``disp``."""
    Pi = pb.P if idx is None else pb.P[idx]
    if pb.n_disp == 0:
        return Pi
    dd = (pb.Xd if idx is None else pb.Xd[idx]) @ disp
    return Pi / (1.0 + Pi[:, 2] * dd / pb.fb)[:, None]


def associate(
    pb: Problem, R: Array, t: Array, log_s: float, Pa: Array
) -> tuple[Array, Array, Array, Array]:
    """Project the moved source points ``Pa`` (the drift-corrected points of the active
    set, K x 3) into the target image; the inlier points ``Q`` (M, 3), the target
    normals ``n`` (M, 3) (``tgt``), the point-to-plane residuals ``r`` (M,) and the
    inliers' rows (M,) in ``Pa``."""
    cfg, rad, H, W = pb.cfg, pb.target.rad, pb.target.H, pb.target.W
    Q = np.exp(log_s) * (Pa @ R.T) + t
    z = Q[:, 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        u = np.rint(pb.fx * Q[:, 0] / z + pb.cx)
        v = np.rint(pb.fy * Q[:, 1] / z + pb.cy)
    inside = (z > 0) & (u >= rad) & (u < W - rad) & (v >= rad) & (v < H - rad)
    idx = np.flatnonzero(inside)
    ui, vi = u[idx].astype(np.intp), v[idx].astype(np.intp)
    pix = vi * W + ui
    g, g_ok = target_at(pb.target, pix)  # q = V(u, v) and the unit normal n there
    Qi = Q[idx]
    d = Qi - g[:, :3]
    r = d[:, 0] * g[:, 3] + d[:, 1] * g[:, 4] + d[:, 2] * g[:, 5]  # (Q - q) . n
    keep = g_ok & (np.abs(r) < cfg.gate) & (np.abs(d[:, 2]) < cfg.depth_gate)
    return Qi[keep], g[keep, 3:], r[keep], idx[keep]


def chain(pb: Problem, t: Array, J: Array, Q: Array, g: Array, pz: Array, xd: Array) -> None:
    """Fill the pose, scale and disparity columns of ``J`` (M, >= n_all) for residuals
    whose gradient with respect to the moved point ``Q`` (M, 3) is ``g`` (M, 3): the
    left twist ``[g, Q x g]``; ``log s``: ``g . (Q - t)`` (``s R p = Q - t``); the
    disparity: ``dQ/d(dd) = -s R p(dd) p_z(dd) / (f b)`` times its regressors;
    ``pz`` (M,) the rows' corrected source depths ``p_z(dd)``, ``xd`` (M, n_disp) their
    disparity regressors."""
    J[:, :3] = g
    J[:, 3:6] = np.cross(Q, g)
    j_s = np.einsum("ij,ij->i", Q - t, g)
    if pb.cfg.estimate_scale:
        J[:, 6] = j_s
    if pb.n_disp:
        J[:, pb.n_par : pb.n_all] = (-(pz / pb.fb) * j_s)[:, None] * xd


def photometric(
    pb: Problem, est: Estimate, Pa: Array, act: Array, cg: Array, img: Array, kernel: str
) -> tuple[Array, Array, Array] | None:
    """The photometric residuals ``r`` (M,) = target grey at the projection of the moved
    source point - the brightness model of its source grey, their Jacobians (M, n_all + 4)
    and the robust weights (M,) of ``kernel``; points projecting outside, onto no depth or
    onto a depth ``depth_gate`` away (occluded) are left out. ``Pa`` (K, 3): the corrected
    points ``act`` (K,); ``cg`` (N,) the source grey values, ``img`` (H, W, 3) the target's
    ``[grey, d/du, d/dv]``."""
    cfg, H, W, n_all = pb.cfg, pb.target.H, pb.target.W, pb.n_all
    R, t, log_s, bright = est.R, est.t, est.log_s, est.bright
    fx, fy = pb.fx, pb.fy
    Q = np.exp(log_s) * (Pa @ R.T) + t
    z = Q[:, 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        u = fx * Q[:, 0] / z + pb.cx
        v = fy * Q[:, 1] / z + pb.cy
    keep = (z > 0) & (u >= 1) & (u < W - 2) & (v >= 1) & (v < H - 2)
    idx = np.flatnonzero(keep)
    zt = pb.target.fill_z[np.rint(v[idx]).astype(np.intp) * W + np.rint(u[idx]).astype(np.intp)]
    idx = idx[(zt > 0) & (np.abs(zt - z[idx]) < cfg.depth_gate)]
    if len(idx) < n_all + 4:
        return None
    s_ = bilinear(img, u[idx], v[idx])
    Qi, zi, src = Q[idx], z[idx], act[idx]
    c, x_, y_ = cg[src], pb.xs_f[src], pb.ys_f[src]
    r = s_[:, 0] - ((1.0 + bright[0]) * c + bright[1] + bright[2] * x_ + bright[3] * y_)
    # d(grey)/dQ = grad I . d(pi)/dQ
    gx, gy = s_[:, 1] * fx / zi, s_[:, 2] * fy / zi
    gq = np.column_stack([gx, gy, -(gx * Qi[:, 0] + gy * Qi[:, 1]) / zi])
    J = np.zeros((len(idx), n_all + 4))
    chain(pb, t, J, Qi, gq, Pa[idx, 2], pb.Xd[src])
    J[:, n_all:] = -np.column_stack([c, np.ones(len(idx)), x_, y_])
    assert cfg.photometric_sigma is not None
    sig = cfg.photometric_sigma
    if cfg.photometric_scale_mads is not None:  # the residuals' robust SD, 1.4826 MAD
        mad = float(np.median(np.abs(r - np.median(r))))
        sig = max(sig, cfg.photometric_scale_mads * 1.4826 * mad)
    return r, J, robust_weights(r, sig, kernel)


def _normal_equations(
    pb: Problem, est: Estimate, Pa: Array, act: Array, ph: tuple[Array, Array] | None, kernel: str
) -> tuple[Array, Array] | None:
    """The weighted normal equations ``A dx = b`` of one Gauss-Newton iteration at ``est``
    (point-to-plane rows, the photometric rows with ``ph``, the priors); None when too few
    points associate or the photometric term has too few rows."""
    cfg, n_all = pb.cfg, pb.n_all
    n_x = n_all + (4 if ph is not None else 0)
    Q, n, r, rows = associate(pb, est.R, est.t, est.log_s, Pa)
    if len(r) < max(cfg.min_inliers, n_all):
        return None
    w = robust_weights(r, cfg.huber, kernel if ph is not None else cfg.kernel)
    J = np.zeros((len(r), n_x))
    chain(pb, est.t, J, Q, n, Pa[rows, 2], pb.Xd[act[rows]])
    Jw = J * w[:, None]
    A = Jw.T @ J
    b = -Jw.T @ r
    if ph is not None:
        pr = photometric(pb, est, Pa, act, *ph, kernel)
        if pr is None:
            return None
        rp, Jp, wp = pr
        # weighed against the point-to-plane residuals: (c / sigma_I)^2
        lam = (cfg.huber / cfg.photometric_sigma) ** 2  # type: ignore[operator]
        Jpw = Jp * (lam * wp)[:, None]
        A += Jpw.T @ Jp
        b -= Jpw.T @ rp
    # priors: (c / sigma)^2 (x - 0)^2 per parameter, c the residual scale (m)
    for j, sd, which in pb.prior_terms:
        A[j, j] += (cfg.huber / sd) ** 2
        b[j] -= (cfg.huber / sd) ** 2 * _prior_value(est, which)
    return A, b


def _step(pb: Problem, est: Estimate, dx: Array, photometric_on: bool) -> Estimate:
    """``est`` updated by the Gauss-Newton step ``dx`` (twist left-multiplied)."""
    R, t, log_s, disp, bright = est
    dT = exp_se3(dx[:6])
    R, t = dT[:3, :3] @ R, dT[:3, :3] @ t + dT[:3, 3]
    if pb.cfg.estimate_scale:
        log_s += float(dx[6])
    if pb.n_disp:
        disp = disp + dx[pb.n_par : pb.n_all]
    if photometric_on:
        bright = bright + dx[pb.n_all :]
    return Estimate(R, t, log_s, disp, bright)


def _converged(pb: Problem, dx: Array) -> bool:
    """The step is below ``tolerance`` (pose and scale) and 1e-4 px (drift)."""
    return bool(
        np.linalg.norm(dx[: pb.n_par]) < pb.cfg.tolerance
        and (not pb.n_disp or np.max(np.abs(dx[pb.n_par : pb.n_all])) < 1e-4)
    )


def solve_round(
    pb: Problem,
    est: Estimate,
    act: Array,
    ph: tuple[Array, Array] | None = None,
    iters: int = 0,
    kernel: str = "",
) -> tuple[Estimate, int]:
    """Gauss-Newton on the source points ``act`` from ``est`` (with the photometric data
    ``ph`` = (source grey (N,), target [grey, d/du, d/dv] (H, W, 3)) the brightness too,
    both terms with ``kernel``; without, the point-to-plane term with ``cfg.kernel``); the
    new estimate and the number of iterations taken."""
    n_x = pb.n_all + (4 if ph is not None else 0)
    k = 0
    while k < (iters or pb.cfg.iterations):
        k += 1
        Pa = corrected(pb, est.disp, act)
        eq = _normal_equations(pb, est, Pa, act, ph, kernel)
        if eq is None:
            break
        A, b = eq
        dx = np.linalg.solve(A + 1e-12 * np.eye(n_x), b)
        est = _step(pb, est, dx, ph is not None)
        if _converged(pb, dx):
            break
    return est, k


def rho(r: Array, c: float, kernel: str) -> Array:
    """The robust loss whose IRLS weights :func:`robust_weights` gives."""
    a = np.abs(r)
    if kernel == "huber":
        return np.where(a <= c, 0.5 * a * a, c * a - 0.5 * c * c)
    return 0.5 * a * a / (1.0 + (a / c) ** 2)


def objective(
    pb: Problem, est: Estimate, act: Array, ph: tuple[Array, Array], kernel: str
) -> float:
    """The joint pass's objective at ``est`` (units of m^2 like the point-to-plane term):
    robust losses of both terms, a point without a residual (unassociated, gated,
    occluded) counted at the kernel's saturation ``c^2 / 2`` (``c`` = ``huber``; the
    redescending kernel's limit), and the priors."""
    cfg = pb.cfg
    Pa = corrected(pb, est.disp, act)
    _, _, r, _ = associate(pb, est.R, est.t, est.log_s, Pa)
    c = cfg.huber
    f = float(np.sum(rho(r, c, kernel))) + 0.5 * c * c * (len(act) - len(r))
    pr = photometric(pb, est, Pa, act, *ph, kernel)
    n_p = 0
    if pr is not None:
        sig = cfg.photometric_sigma
        assert sig is not None
        lam = (c / sig) ** 2
        f += lam * float(np.sum(rho(pr[0], sig, kernel)))
        n_p = len(pr[0])
    f += 0.5 * c * c * (len(act) - n_p)
    for _, sd, which in pb.prior_terms:
        f += 0.5 * (c / sd) ** 2 * float(_prior_value(est, which)) ** 2
    return f


def photometric_levels(
    P_all: Array,
    grey_all: Array,
    target_grey: Array,
    intrinsics: CameraIntrinsics,
    sds: tuple[float, ...],
    keep: Array,
) -> list[tuple[Array, Array]]:
    """(source grey (N,), target [grey, d/du, d/dv] (H, W, 3)) per blur SD, coarse to fine."""
    levels = []  # (blur SD, photometric data) coarse to fine
    greys = source_grey_levels(P_all, grey_all, intrinsics, sds, keep)
    for sd, cg in zip(sds, greys, strict=True):
        img = ndimage.gaussian_filter(target_grey, sd) if sd > 0 else target_grey
        gv, gu = np.gradient(img)
        levels.append((cg, np.stack([img, gu, gv], axis=-1)))
    return levels


def run_levels(
    pb: Problem,
    est: Estimate,
    act_ph: Array,
    levels: list[tuple[Array, Array]],
    graduated: bool,
) -> tuple[Estimate, int, float]:
    """The coarse-to-fine joint pass from ``est``; the estimate, the iterations and its
    objective at the finest level. ``graduated``: Huber on every level but the finest
    (convex: a start several mrad off still finds its way), else the kernel throughout."""
    cfg = pb.cfg
    k = 0
    kernel = cfg.photometric_kernel
    for level, ph in enumerate(levels):
        last = level == len(levels) - 1
        kernel = cfg.photometric_kernel if last or not graduated else "huber"
        est, n = solve_round(pb, est, act_ph, ph, cfg.photometric_iterations, kernel)
        k += n
    return est, k, objective(pb, est, act_ph, levels[-1], kernel)


def photometric_pass(
    pb: Problem,
    est: Estimate,
    act: Array,
    target_grey: Array,
    P_all: Array,
    grey_all: Array,
    stride: int,
    intrinsics: CameraIntrinsics,
    stages: dict[str, Any],
) -> tuple[Estimate, int]:
    """The joint depth + colour pass from ``est`` (:mod:`~mmpa.registration.projective`,
    "Photometric"): the kept estimate and the
    iterations of both starts; fills ``stages``."""
    cfg = pb.cfg
    t_ph = time.perf_counter()
    act_ph = act[:: int(np.ceil(len(act) / cfg.photometric_points))]
    keep = np.arange(0, len(P_all), stride)  # P = P_all[keep]
    levels = photometric_levels(
        P_all, grey_all, target_grey, intrinsics, cfg.photometric_blur_px, keep
    )
    start = est
    est, k, cost0 = run_levels(pb, start, act_ph, levels, False)
    best = (cost0, est)
    if cfg.photometric_graduated:
        # a second start, graduated; the two local minima of one objective: keep the
        # lower (the redescending kernel from the depth pass keeps a changed region
        # out; the graduated pass escapes a depth pass that the drift led astray)
        est, k2, cost = run_levels(pb, start, act_ph, levels, True)
        k += k2
        stages["photometric_costs"] = [best[0], cost]
        if cost < best[0]:
            best = (cost, est)
    est = best[1]
    stages["photometric_s"] = time.perf_counter() - t_ph
    stages["brightness"] = [float(x) for x in est.bright]
    return est, k
