"""AMCL's multi-modal cloud after a global start (issue 34): particles in several clusters,
one per hypothesis, each refined by its own scan match, the clusters' masses from the laser
model at their matches.

Each cluster ``c`` (particles of connected KLD bins, :func:`~.resampling.cluster_labels`) is
a mode of the posterior. Per filter update:

- the cluster's predicted particles ``p_c`` (mass ``M_c``, Gaussian fit ``N(mu_c, S_c)``)
  are matched (Hector, from ``mu_c``); with an accepted match ``m_c`` they are redrawn from
  the cluster's defensive mixture (:func:`~.proposal.defensive_mixture`), else kept;
- within the cluster the particles weigh ``p(z | x) f(x)`` (``f`` the mixture's importance
  factor; 1 for kept ones): the cluster's posterior shape;
- the cluster's mass is ``M_c p(z | x*_c) N(x*_c; mu_c, S_c)``, ``x*_c`` its match (else
  its best particle): Laplace's approximation of ``M_c int p(z | x) p_c(x) dx`` with the
  likelihood's width taken alike for every cluster (the same scan). Summing the particles'
  weights instead (the Monte Carlo estimate of the same integral) leaves it to the few
  particles nearest each peak of a sharp likelihood: two equally good clusters then differ
  by factors of 4-100 per update (measured on a symmetric room) and one dies by chance.

:func:`seed_weights` is the same for the first scan: the clusters drawn around the search's
hypotheses ``h_k`` from ``q_k``, the prior uniform: within a cluster ``p(z | x) / q_k(x)``,
the cluster's mass ``p(z | h_k)``.

Units: m, rad; poses ``[x, y, theta]`` in ``map``.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from mmpa.core.geometry import Array
from mmpa.localization.proposal import defensive_mixture, gaussian_fit, log_gauss
from mmpa.localization.refine import Refinement

__all__ = ["ClusterDraw", "cluster_weights", "draw_clusters", "seed_weights"]


@dataclass
class ClusterDraw:
    """One cluster after its proposal: the particles ``x`` (n, 3), their log factor within
    the cluster ``log_f`` (n,), the log of its prior mass, the Gaussian fit of its predicted
    particles (floored) and its match (None: not tried)."""

    x: Array
    log_f: Array
    log_mass: float
    mean: Array
    cov: Array
    ref: Refinement | None

    @property
    def peak(self) -> Array | None:
        """The accepted match's pose, or None."""
        return self.ref.pose if self.ref is not None and self.ref.ok else None


def draw_clusters(
    particles: Array,
    weights: Array,
    labels: Array,
    match: Callable[[Array, Array, int], Refinement | None],
    proposal_cov: Callable[[Array], Array],
    fraction: float,
    floor: Array,
    rng: np.random.Generator,
) -> list[ClusterDraw]:
    """The proposal of every cluster (module docstring), heaviest first; ``match(mean, cov,
    rank)`` gives the match of the cluster of that rank, mean and covariance (None: not
    tried). ``floor`` (3,): SDs added to every cluster's fit."""
    masses = np.bincount(labels, weights=weights)
    out = []
    for rank, lab in enumerate(np.argsort(-masses, kind="stable")):
        sel = labels == lab
        if not sel.any():
            continue
        x, w = particles[sel], weights[sel]
        mass = float(w.sum())
        mean, cov = gaussian_fit(x, w / mass)
        ref = match(mean, cov, rank)
        cov = cov + np.diag(np.asarray(floor, float) ** 2)
        if ref is not None and ref.ok:
            x, log_f = defensive_mixture(
                x, w / mass, ref.pose, proposal_cov(ref.cov), fraction, rng
            )
        else:
            log_f = np.log(np.maximum(w / mass, 1e-300))
        out.append(ClusterDraw(x, log_f, float(np.log(max(mass, 1e-300))), mean, cov, ref))
    return out


def cluster_weights(draws: list[ClusterDraw], lik: Array) -> Array:
    """Normalized weights of the particles of ``draws`` (concatenated in order), from
    ``lik`` = the laser model at those particles followed by the peaks of the clusters that
    have one (one call, so that clusters compare): module docstring."""
    n = sum(len(d.x) for d in draws)
    p_x, p_peak = lik[:n], lik[n:]
    out, log_mass, i, j = [], [], 0, 0
    for d in draws:
        p = p_x[i : i + len(d.x)]
        i += len(d.x)
        lw = np.log(np.maximum(p, 1e-300)) + d.log_f
        if d.peak is not None:
            at, lp = d.peak, float(p_peak[j])
            j += 1
        else:
            k = int(np.argmax(p))
            at, lp = d.x[k], float(p[k])
        prior = float(log_gauss(at[None, :], d.mean, d.cov)[0])
        log_mass.append(d.log_mass + np.log(max(lp, 1e-300)) + prior)
        w = np.exp(lw - lw.max())
        out.append(w / w.sum())
    lm = np.array(log_mass)
    m = np.exp(lm - lm.max())
    m /= m.sum()
    return np.concatenate([mk * w for mk, w in zip(m, out, strict=True)])


def seed_weights(x: Array, groups: Array, poses: Array, covs: list[Array], lik: Array) -> Array:
    """Normalized weights of particles ``x`` (n, 3) drawn around hypotheses ``poses`` (K, 3)
    (particle ``i`` from ``N(poses[groups[i]], covs[groups[i]])``), ``lik`` the laser model
    at ``x`` then at ``poses``: within hypothesis ``k`` ``lik / q_k``, its mass ``lik(h_k)``
    (module docstring)."""
    n = len(x)
    p_x, p_h = lik[:n], lik[n:]
    out = np.zeros(n)
    for k in range(len(poses)):
        sel = groups == k
        lw = np.log(np.maximum(p_x[sel], 1e-300)) - log_gauss(x[sel], poses[k], covs[k])
        w = np.exp(lw - lw.max())
        out[sel] = p_h[k] * w / w.sum()
    total = out.sum()
    return out / total if total > 0 else np.full(n, 1.0 / n)
