"""The reflector terms of paper 001 Algorithm 1 and their fusion with the laser weight.

- eq. 3, :func:`position_weight`: ``d = (2 pi)^{-3/2} exp(-1/2 e^T S^-1 e)``, ``e = x - mu_G``;
  ``S`` picked by ``position_metric`` from :data:`POSITION_METRICS`: the identity as printed,
  or (improvement) the trilateration covariance plus a floor (the normalizer stays, so eq. 8's
  0.01 threshold keeps its meaning);
- eq. 4, :func:`orientation_weight`: the mean over the identified reflectors of a Gaussian
  (``bearing_sigma``) of observed minus predicted bearing;
- eq. 6, :data:`FUSIONS` by ``fusion``: ``omega_new = alpha s omega + beta d`` as printed, or
  (improvement) the Bayes product ``s omega (d + floor)``;
- eq. 7-8, :func:`injection_probability` (``d`` on eq. 3 as printed, above
  ``injection_threshold``) and :data:`INJECTIONS` by ``injection``: ``lambda Q + mu_G`` as
  printed, or (improvement) ``N(mu_G, Sigma)``.

Units: m, rad; particles and ``mu_G`` ``[x, y, theta]`` in ``map``; bearings in ``base_link``.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from mmpa.core.geometry import Array
from mmpa.localization.config import EnhancedConfig
from mmpa.localization.observer import ReflectorFix
from mmpa.localization.pose import wrap

__all__ = [
    "EQ3_NORM",
    "FUSIONS",
    "INJECTIONS",
    "POSITION_METRICS",
    "Fusion",
    "Injection",
    "PositionMetric",
    "injection_probability",
    "orientation_weight",
    "position_weight",
]

EQ3_NORM = (2 * np.pi) ** -1.5


def position_weight(particles: Array, mu: Array, cov: Array | None = None) -> Array:
    """Eq. 3: ``d = (2 pi)^{-3/2} exp(-1/2 e^T S^-1 e)``, ``e = x - mu_G`` (heading wrapped);
    ``S = I`` as printed unless ``cov`` (3, 3) is given. Returns (N,)."""
    e = particles - mu
    e[:, 2] = wrap(e[:, 2])
    if cov is None:
        m2 = np.einsum("ij,ij->i", e, e)
    else:
        m2 = np.einsum("ij,jk,ik->i", e, np.linalg.inv(cov), e)
    return EQ3_NORM * np.exp(-0.5 * m2)


def orientation_weight(particles: Array, landmarks: Array, bearings: Array, sigma: float) -> Array:
    """Eq. 4: ``s = (1/n) sum_i N(phi_i; mu_i, sigma)`` with ``mu_i`` the bearing of landmark
    ``i`` predicted from each particle (``base_link`` frame). Returns (N,)."""
    dx = landmarks[None, :, 0] - particles[:, 0:1]
    dy = landmarks[None, :, 1] - particles[:, 1:2]
    mu = np.arctan2(dy, dx) - particles[:, 2:3]
    err = wrap(bearings[None, :] - mu)
    g = np.exp(-(err**2) / (2 * sigma**2)) / (sigma * np.sqrt(2 * np.pi))
    return g.mean(axis=1)


# --- eq. 3's metric --------------------------------------------------------------------------
#: ``(fix, cfg, tracked) -> S`` of eq. 3 (None: the identity).
PositionMetric = Callable[[ReflectorFix, EnhancedConfig, bool], "Array | None"]


def identity_metric(fix: ReflectorFix, e: EnhancedConfig, tracked: bool) -> Array | None:
    """Eq. 3 as printed: ``S = I``."""
    return None


def trilateration_metric(fix: ReflectorFix, e: EnhancedConfig, tracked: bool) -> Array | None:
    """The fix's covariance plus ``position_cov_floor``, times ``track_cov_scale`` for a
    tracked or weak fix (improvement)."""
    cov = fix.trilateration.cov + np.diag(e.position_cov_floor)
    if tracked:
        cov = cov * e.track_cov_scale
    return cov


POSITION_METRICS: dict[str, PositionMetric] = {
    "identity": identity_metric,
    "trilateration": trilateration_metric,
}


# --- eq. 6 -----------------------------------------------------------------------------------
#: ``(s, omega, d, cfg) -> omega_new`` (unnormalized), eq. 6.
Fusion = Callable[[Array, Array, Array, EnhancedConfig], Array]


def fuse_paper(s: Array, omega: Array, d: Array, e: EnhancedConfig) -> Array:
    """Eq. 6 as printed: ``alpha s omega + beta d``."""
    return e.alpha * s * omega + e.beta * d


def fuse_product(s: Array, omega: Array, d: Array, e: EnhancedConfig) -> Array:
    """Improvement: all three likelihoods multiplied, ``d`` floored for robustness."""
    return s * omega * (d + e.position_weight_floor * EQ3_NORM)


FUSIONS: dict[str, Fusion] = {"paper": fuse_paper, "product": fuse_product}


# --- eq. 7-8 ---------------------------------------------------------------------------------
def injection_probability(
    particles: Array, mu: Array, threshold: float, scale: float | None
) -> Array:
    """Eq. 8: each particle is replaced with probability ``d`` (eq. 3 as printed, identity
    metric: particles within ~1.9 m / rad of ``mu_G``) where ``d > threshold``, times
    ``scale`` if given (tracked fixes). Returns (N,)."""
    d_new = position_weight(particles, mu, None)
    prob = np.where(d_new > threshold, d_new, 0.0)
    if scale is not None:
        prob = prob * scale
    return prob


#: ``(q, mu, cov, cfg) -> new particles``: eq. 7 from standard normal draws ``q`` (k, 3).
Injection = Callable[[Array, Array, "Array | None", EnhancedConfig], Array]


def inject_paper(q: Array, mu: Array, cov: Array | None, e: EnhancedConfig) -> Array:
    """Eq. 7 as printed: ``lambda Q + mu_G``."""
    return e.injection_lambda * q + mu


def inject_gaussian(q: Array, mu: Array, cov: Array | None, e: EnhancedConfig) -> Array:
    """Improvement: ``N(mu_G, Sigma)`` (``Sigma`` eq. 3's metric, the identity without one)."""
    Lc = np.linalg.cholesky(cov if cov is not None else np.eye(3))
    return q @ Lc.T + mu


INJECTIONS: dict[str, Injection] = {"paper": inject_paper, "trilateration": inject_gaussian}
