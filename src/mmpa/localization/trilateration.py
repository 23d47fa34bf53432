"""Robot pose from identified reflectors: trilateration (paper 001 eq. 1) and heading (eq. 2).

Eq. 1: ``(x_G - x_i)^2 + (y_G - y_i)^2 = r_i^2`` for the ``n`` identified reflectors; solved by
linear least squares after subtracting the last equation from the others, then refined by
Gauss-Newton on the range residuals (the linearized form weights far reflectors wrongly).

Eq. 2: ``theta_G = mean_i [atan(dy_i / dx_i) - phi_i]`` with the quadrant cases of the paper;
here ``atan2`` covers every case and the mean is circular, so headings near +-pi do not average
to zero.

Improvement (``refine_heading=True``): a final joint Gauss-Newton on ``(x, y, theta)`` using
ranges and bearings together, weighted by their standard deviations; it returns the covariance
``(J^T W J)^-1`` that the enhanced AMCL uses to scale eq. 3 and eq. 7.

Improvement (:func:`trilaterate_bias`): the same fit with a fourth unknown, a range bias ``b``
common to every reflector (the scanner's range walk on retroreflective tape), under a Gaussian
prior, and with the map (survey) error of each landmark in the weights, so that the returned
covariance is the honest one of ``mu_G`` (the bias marginalized).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from mmpa.core.errors import InvalidInputError
from mmpa.core.geometry import Array

__all__ = [
    "BiasedTrilateration",
    "TrilaterationResult",
    "heading_eq2",
    "trilaterate",
    "trilaterate_bias",
    "trilaterate_eq1",
]


@dataclass(frozen=True)
class TrilaterationResult:
    """``pose`` = ``mu_G`` = ``[x_G, y_G, theta_G]`` (m, m, rad) of the frame the ranges and
    bearings were measured from; ``cov`` (3, 3); ``rms`` range residual (m); ``n`` reflectors."""

    pose: Array
    cov: Array
    rms: float
    n: int


def _check(landmarks: Array, ranges: Array, bearings: Array | None = None) -> tuple[Array, Array]:
    L = np.asarray(landmarks, float).reshape(-1, 2)
    r = np.asarray(ranges, float).reshape(-1)
    if len(L) != len(r):
        raise InvalidInputError(f"{len(L)} landmarks but {len(r)} ranges")
    if len(L) < 3:
        raise InvalidInputError(f"trilateration needs at least 3 reflectors, got {len(L)}")
    if not (np.all(np.isfinite(L)) and np.all(np.isfinite(r)) and np.all(r > 0)):
        raise InvalidInputError("trilateration input contains NaN/inf or non-positive ranges")
    if bearings is not None and (
        np.asarray(bearings).shape != r.shape or not np.all(np.isfinite(bearings))
    ):
        raise InvalidInputError("bearings must be finite and one per range")
    return L, r


def trilaterate_eq1(landmarks: Array, ranges: Array, iters: int = 10) -> tuple[Array, float]:
    """Eq. 1 by least squares: ``(x_G, y_G)`` and the RMS range residual (m).

    Linear step: ``2 (x_n - x_i) x + 2 (y_n - y_i) y = r_i^2 - r_n^2 - |p_i|^2 + |p_n|^2``;
    then Gauss-Newton on ``|G - p_i| - r_i``. Raises on collinear reflectors.
    """
    L, r = _check(landmarks, ranges)
    A = 2.0 * (L[-1] - L[:-1])
    b = r[:-1] ** 2 - r[-1] ** 2 - (L[:-1] ** 2).sum(1) + (L[-1] ** 2).sum()
    sv = np.linalg.svd(A, compute_uv=False)
    if sv[-1] < 1e-6 * max(sv[0], 1e-12):
        raise InvalidInputError("reflectors are collinear: trilateration is ill-posed")
    G = np.linalg.lstsq(A, b, rcond=None)[0]
    for _ in range(iters):
        d = G - L
        rho = np.maximum(np.linalg.norm(d, axis=1), 1e-9)
        J = d / rho[:, None]
        step = np.linalg.lstsq(J, rho - r, rcond=None)[0]
        G = G - step
        if np.linalg.norm(step) < 1e-9:
            break
    rms = float(np.sqrt(np.mean((np.linalg.norm(G - L, axis=1) - r) ** 2)))
    return G, rms


def heading_eq2(position: Array, landmarks: Array, bearings: Array) -> float:
    """Eq. 2: ``theta_G`` as the circular mean of ``atan2(y_i - y_G, x_i - x_G) - phi_i``."""
    L = np.asarray(landmarks, float).reshape(-1, 2)
    phi = np.asarray(bearings, float).reshape(-1)
    G = np.asarray(position, float)
    th = np.arctan2(L[:, 1] - G[1], L[:, 0] - G[0]) - phi
    return float(np.angle(np.exp(1j * th).mean()))


def trilaterate(
    landmarks: Array,
    ranges: Array,
    bearings: Array,
    sigma_range: float | Array = 0.01,
    sigma_bearing: float | Array = 0.003,
    refine_heading: bool = True,
    initial: Array | None = None,
) -> TrilaterationResult:
    """``mu_G`` from eq. 1 + eq. 2, optionally refined jointly (see module docstring).

    ``landmarks`` (n, 2) map positions of the identified reflectors, ``ranges`` (n,) m and
    ``bearings`` (n,) rad measured from the robot frame (e.g. ``base_link``); sigmas per
    reflector or scalar. With ``initial`` (a pose guess, e.g. from tracking) eq. 1-2 are
    skipped and two reflectors suffice (ranges and bearings give four equations).
    """
    if initial is not None:  # tracking: two reflectors with ranges and bearings suffice
        L = np.asarray(landmarks, float).reshape(-1, 2)
        r = np.asarray(ranges, float).reshape(-1)
        if len(L) < 2 or len(r) != len(L) or not np.all(np.isfinite(r)):
            raise InvalidInputError("pose refinement needs >= 2 reflectors with finite ranges")
        phi = np.asarray(bearings, float).reshape(-1)
        x = np.asarray(initial, float).reshape(-1).copy()
        if x.shape != (3,) or not np.all(np.isfinite(x)):
            raise InvalidInputError(f"initial pose must be a finite [x, y, theta], got {x}")
        if phi.shape != r.shape or not (np.all(np.isfinite(phi)) and np.all(np.isfinite(L))):
            raise InvalidInputError("landmarks and bearings must be finite, one bearing per range")
        refine_heading = True
    else:
        L, r = _check(landmarks, ranges, bearings)
        phi = np.asarray(bearings, float).reshape(-1)
        G, _ = trilaterate_eq1(L, r)
        th = heading_eq2(G, L, phi)
        x = np.array([G[0], G[1], th])
    sr = np.broadcast_to(np.asarray(sigma_range, float), r.shape)
    sb = np.broadcast_to(np.asarray(sigma_bearing, float), r.shape)
    wts = np.concatenate([1 / sr**2, 1 / sb**2])

    def jac(x: Array) -> tuple[Array, Array]:
        d = L - x[:2]
        rho = np.maximum(np.linalg.norm(d, axis=1), 1e-9)
        pred_b = np.arctan2(d[:, 1], d[:, 0]) - x[2]
        res = np.concatenate([rho - r, np.angle(np.exp(1j * (pred_b - phi)))])
        Jr = np.column_stack([-d[:, 0] / rho, -d[:, 1] / rho, np.zeros(len(r))])
        Jb = np.column_stack([d[:, 1] / rho**2, -d[:, 0] / rho**2, -np.ones(len(r))])
        return res, np.vstack([Jr, Jb])

    if refine_heading:
        for _ in range(10):
            res, J = jac(x)
            H = J.T @ (wts[:, None] * J)
            step = np.linalg.solve(H, J.T @ (wts * res))
            x = x - step
            if np.linalg.norm(step) < 1e-10:
                break
    x[2] = float(np.angle(np.exp(1j * x[2])))
    res, J = jac(x)
    H = J.T @ (wts[:, None] * J)
    try:
        cov = np.linalg.inv(H)
    except np.linalg.LinAlgError:
        cov = np.diag([1.0, 1.0, 1.0])
    rms = float(np.sqrt(np.mean(res[: len(r)] ** 2)))
    return TrilaterationResult(x, cov, rms, len(r))


@dataclass(frozen=True)
class BiasedTrilateration:
    """:func:`trilaterate_bias`'s answer. ``pose`` (3,) ``[x, y, theta]`` (m, m, rad) of the
    measuring frame, ``bias`` (m) the common range bias, ``cov`` (4, 4) the covariance of
    ``(x, y, theta, b)``, ``bias_info_meas`` (1/m^2) the information on ``b`` the measurements
    alone carry (the posterior precision of ``b`` minus the prior's), ``rms`` the RMS of the
    bias-corrected range residuals (m), ``n`` reflectors."""

    pose: Array
    bias: float
    cov: Array
    bias_info_meas: float
    rms: float
    n: int

    @property
    def pose_cov(self) -> Array:
        """(3, 3) covariance of the pose with the bias marginalized out."""
        return self.cov[:3, :3]


def trilaterate_bias(
    landmarks: Array,
    ranges: Array,
    bearings: Array,
    sigma_range: float | Array,
    sigma_bearing: float | Array,
    bias_mean: float = 0.0,
    bias_sigma: float = 0.02,
    survey_sigma: float | Array = 0.0,
    initial: Array | None = None,
    iters: int = 10,
) -> BiasedTrilateration:
    """Pose and common range bias from reflector ranges and bearings (improvement).

    Model, reflector ``i`` at map position ``L_i`` seen from the pose ``(p, theta)`` of the
    measuring frame (the scanner's own frame, where a range bias is a bias of the range):
    ``r_i = |L_i - p| + b + e_r``, ``phi_i = atan2(L_i - p) - theta + e_phi``, with
    ``var(e_r) = sigma_range_i^2 + survey_sigma^2`` and ``var(e_phi) = sigma_bearing_i^2 +
    (survey_sigma / rho_i)^2`` (``rho_i = |L_i - p|``): an isotropic landmark error of SD
    ``survey_sigma`` per axis (scalar, or one per landmark) moves its range by its radial and
    its bearing by its tangential component over ``rho``. Prior ``b ~ N(bias_mean,
    bias_sigma^2)``. Gauss-Newton on the weighted least squares ``sum e_r^2 / var_r +
    sum e_phi^2 / var_phi + (b - bias_mean)^2 / bias_sigma^2`` from :func:`trilaterate` on
    the ranges less ``bias_mean`` (or from
    ``initial``, which lets two reflectors suffice); ``cov = H^-1`` at the solution. A common
    bias is observable only through the geometry: reflectors around the robot pin it (no pose
    shortens every range at once), reflectors on one side leave it to the prior.

    Units: m, rad. Returns :class:`BiasedTrilateration`."""
    L = np.asarray(landmarks, float).reshape(-1, 2)
    r = np.asarray(ranges, float).reshape(-1)
    phi = np.asarray(bearings, float).reshape(-1)
    if not bias_sigma > 0:
        raise InvalidInputError(f"bias_sigma must be positive, got {bias_sigma}")
    sr = np.broadcast_to(np.asarray(sigma_range, float), r.shape)
    sb = np.broadcast_to(np.asarray(sigma_bearing, float), r.shape)
    ss = np.broadcast_to(np.asarray(survey_sigma, float), r.shape)
    if initial is None:
        x0 = trilaterate(L, r - bias_mean, phi, sr, sb).pose
    else:
        if len(L) < 2 or len(r) != len(L) or phi.shape != r.shape:
            raise InvalidInputError("pose refinement needs >= 2 reflectors with ranges/bearings")
        x0 = np.asarray(initial, float).reshape(-1)
        if x0.shape != (3,) or not np.all(np.isfinite(x0)):
            raise InvalidInputError(f"initial pose must be a finite [x, y, theta], got {x0}")
    if not np.all(np.isfinite(L)):
        raise InvalidInputError("trilateration landmarks contain NaN/inf")
    if not (np.all(np.isfinite(r)) and np.all(np.isfinite(phi)) and np.all(np.isfinite(x0))):
        raise InvalidInputError("trilateration input contains NaN/inf")
    x = np.array([*x0, bias_mean], float)
    prior_info = 1.0 / bias_sigma**2

    def system(x: Array) -> tuple[Array, Array, Array]:
        d = L - x[:2]
        rho = np.maximum(np.linalg.norm(d, axis=1), 1e-9)
        res = np.concatenate(
            [rho + x[3] - r, np.angle(np.exp(1j * (np.arctan2(d[:, 1], d[:, 0]) - x[2] - phi)))]
        )
        one, zero = np.ones(len(r)), np.zeros(len(r))
        Jr = np.column_stack([-d[:, 0] / rho, -d[:, 1] / rho, zero, one])
        Jb = np.column_stack([d[:, 1] / rho**2, -d[:, 0] / rho**2, -one, zero])
        w = np.concatenate([1 / (sr**2 + ss**2), 1 / (sb**2 + (ss / rho) ** 2)])
        return res, np.vstack([Jr, Jb]), w

    prior_H = np.zeros((4, 4))
    prior_H[3, 3] = prior_info
    for _ in range(iters):
        res, J, w = system(x)
        H = J.T @ (w[:, None] * J) + prior_H
        g = J.T @ (w * res)
        g[3] += prior_info * (x[3] - bias_mean)
        step = np.linalg.solve(H, g)
        x = x - step
        if np.linalg.norm(step) < 1e-10:
            break
    x[2] = float(np.angle(np.exp(1j * x[2])))
    res, J, w = system(x)
    H = J.T @ (w[:, None] * J) + prior_H
    cov = np.linalg.inv(H)
    info_meas = max(1.0 / float(cov[3, 3]) - prior_info, 0.0)
    rms = float(np.sqrt(np.mean(res[: len(r)] ** 2)))
    return BiasedTrilateration(x[:3].copy(), float(x[3]), cov, info_meas, rms, len(r))
