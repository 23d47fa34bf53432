"""Proposals of the enhanced AMCL (improvements to paper 001 Algorithm 1): where particles
are drawn before they are weighted.

- :func:`mixture_proposal`: a share of the predicted particles redrawn from ``N(mu_G, Sigma)``
  (the reflector fix), so that a cloud spread by the motion model still holds particles where
  the fix is;
- :func:`refine_proposal`: two-stage (adaptive) importance sampling around the first stage's
  posterior, with deterministic-mixture weights (Owen and Zhou 2000);
- :func:`defensive_mixture`: a share of the particles drawn from a Gaussian (AMCL's scan
  refinement: around a scan match), the rest resampled from the predicted cloud, with the
  importance weights of that mixture (defensive importance sampling, Hesterberg 1995);
- :func:`gaussian_fit` and :func:`log_gauss`, the Gaussians these use.

Units: m, rad; particles ``[x, y, theta]`` in ``map`` (heading differences wrapped).
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from mmpa.core.geometry import Array
from mmpa.localization.pose import wrap

__all__ = [
    "defensive_mixture",
    "gaussian_fit",
    "log_gauss",
    "mixture_proposal",
    "refine_proposal",
]


def mixture_proposal(
    particles: Array, fraction: float, mu: Array, cov: Array | None, rng: np.random.Generator
) -> None:
    """Redraw ``round(fraction N)`` of the ``particles`` (N, 3), chosen at random, from
    ``N(mu, cov)`` (``cov`` None: the identity), in place."""
    k = round(fraction * len(particles))
    idx = rng.choice(len(particles), k, replace=False)
    Lc = np.linalg.cholesky(cov if cov is not None else np.eye(3))
    particles[idx] = rng.standard_normal((k, 3)) @ Lc.T + mu
    particles[idx, 2] = wrap(particles[idx, 2])


def gaussian_fit(particles: Array, weights: Array) -> tuple[Array, Array]:
    """Weighted mean ``m`` (3,) (circular mean of the heading) and covariance ``C`` (3, 3) of
    ``particles`` (N, 3) under normalized ``weights`` (N,)."""
    m = np.array(
        [
            float(weights @ particles[:, 0]),
            float(weights @ particles[:, 1]),
            float(np.arctan2(weights @ np.sin(particles[:, 2]), weights @ np.cos(particles[:, 2]))),
        ]
    )
    d = particles - m
    d[:, 2] = wrap(d[:, 2])
    return m, (d * weights[:, None]).T @ d


def log_gauss(particles: Array, mean: Array, cov: Array) -> Array:
    """``log N(x; mean, cov)`` of every particle (N,), heading difference wrapped."""
    d = particles - mean
    d[:, 2] = wrap(d[:, 2])
    L = np.linalg.cholesky(cov)
    z = np.linalg.solve(L, d.T)
    return -0.5 * np.einsum("ij,ij->j", z, z) - np.log(np.diag(L)).sum() - 1.5 * np.log(2 * np.pi)


def refine_proposal(
    prior: Array,
    loglik_prior: Array,
    loglik: Callable[[Array], Array],
    fraction: float,
    inflate: float,
    floor: Array,
    rng: np.random.Generator,
) -> tuple[Array, Array]:
    """Two-stage (adaptive) importance sampling of ``p(x | z) ~ p(z | x) p(x)`` (improvement).

    Stage 1: the predicted particles ``prior`` (N, 3), drawn from ``p(x)``, with weights
    ``w1 ~ p(z | x)`` (``loglik_prior``). Stage 2: ``n2 = fraction N`` particles drawn from
    ``q = N(m1, inflate^2 C1 + diag(floor^2))``, ``(m1, C1)`` the Gaussian fit of stage 1's
    posterior. Both sets are combined by deterministic-mixture weighting (Owen and Zhou 2000)
    with ``p(x)`` approximated by ``N(mp, Cp)`` fitted to ``prior``:
    ``w(x) = p(z | x) p(x) / ((n1 p(x) + n2 q(x)) / (n1 + n2))``, ``n1 = N - n2`` stage-1
    particles kept at random. Returns (particles (N, 3), normalized weights (N,))."""
    n = prior.shape[0]
    n2 = round(fraction * n)
    n1 = n - n2
    w1 = np.exp(loglik_prior - loglik_prior.max())
    w1 /= w1.sum()
    m1, c1 = gaussian_fit(prior, w1)
    mp, cp = gaussian_fit(prior, np.full(n, 1.0 / n))
    fl = np.diag(np.asarray(floor, float) ** 2)
    cq = inflate**2 * c1 + fl
    cp = cp + fl
    x2 = rng.standard_normal((n2, 3)) @ np.linalg.cholesky(cq).T + m1
    x2[:, 2] = wrap(x2[:, 2])
    keep = rng.choice(n, n1, replace=False) if n1 < n else np.arange(n)
    x = np.concatenate([prior[keep], x2])
    ll = np.concatenate([loglik_prior[keep], loglik(x2)])
    lp = log_gauss(x, mp, cp)
    lq = log_gauss(x, m1, cq)
    lmix = np.logaddexp(np.log(n1 / n) + lp, np.log(n2 / n) + lq) if n1 else lq
    lw = ll + lp - lmix
    w = np.exp(lw - lw.max())
    return x, w / w.sum()


def defensive_mixture(
    particles: Array,
    weights: Array,
    mean: Array,
    cov: Array,
    fraction: float,
    rng: np.random.Generator,
    floor: Array = (1e-2, 1e-2, 1e-2),
) -> tuple[Array, Array]:
    """Particles from the mixture ``a p + (1 - a) q`` and their log importance factors.

    ``p``: the predicted cloud ``particles`` (N, 3) with normalized ``weights`` (N,), of
    which ``n1 = N - round(fraction N)`` are drawn by low-variance resampling (unweighted
    draws from ``p``); ``q = N(mean, cov)``: ``n2 = round(fraction N)`` draws. ``a = n1 /
    N``. Returns the N particles (the ``p`` draws first) and ``log(p(x) / (a p(x) + (1 - a)
    q(x)))`` per particle, ``p`` approximated by its Gaussian fit (covariance + diag(
    ``floor^2``), so that a collapsed cloud keeps a density): multiplied by the measurement
    likelihood, these are the importance weights of the posterior ``p(z | x) p(x)``."""
    n = particles.shape[0]
    n2 = round(fraction * n)
    n1 = n - n2
    w = np.asarray(weights, float) / float(np.sum(weights))
    cdf = np.cumsum(w)
    u = (rng.uniform() + np.arange(n1)) / max(n1, 1)
    keep = np.minimum(np.searchsorted(cdf / cdf[-1], u), n - 1)
    cq = 0.5 * (cov + cov.T)
    x2 = rng.standard_normal((n2, 3)) @ np.linalg.cholesky(cq).T + mean
    x2[:, 2] = wrap(x2[:, 2])
    x = np.concatenate([particles[keep], x2])
    mp, cp = gaussian_fit(particles, w)
    cp = cp + np.diag(np.asarray(floor, float) ** 2)
    lp = log_gauss(x, mp, cp)
    if n2 == 0:
        return x, np.zeros(n)
    lq = log_gauss(x, np.asarray(mean, float), cq)
    lmix = np.logaddexp(np.log(n1 / n) + lp, np.log(n2 / n) + lq) if n1 else lq
    return x, lp - lmix
