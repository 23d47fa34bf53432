"""Weighting, resampling and the estimate of AMCL (Thrun et al. ch. 4.3 and 8.3, as Nav2's
``pf`` library).

- :func:`normalize` and :func:`recovery_averages`: the weight update and the short / long-term
  averages ``w_fast`` / ``w_slow`` of the measurement likelihood (Augmented MCL, Table 8.3);
- :func:`low_variance_resample` with random recovery particles, :func:`kld_size` (KLD-sampling,
  Fox 2003; Nav2's histogram bins and its ``pf_z`` quantile, :func:`kld_limit`);
- :func:`cluster_labels` and :func:`cluster_mean`: the estimate is the weighted mean of the
  heaviest cluster of histogram bins, heading axis circular.

Units: m, rad; particles ``[x, y, theta]`` in ``map``.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
from scipy import ndimage, sparse
from scipy.sparse import csgraph

from mmpa.core.geometry import Array
from mmpa.localization.pose import wrap

__all__ = [
    "cluster_labels",
    "cluster_mean",
    "kld_bins",
    "kld_limit",
    "kld_size",
    "low_variance_resample",
    "normalize",
    "recovery_averages",
]


def normalize(weights: Array, p: Array) -> Array | None:
    """``weights * p`` normalized to sum 1, or None if that sum is not a positive number."""
    w = weights * p
    total = float(w.sum())
    if not np.isfinite(total) or total <= 0:
        return None
    return w / total


def recovery_averages(
    w_slow: float, w_fast: float, w_avg: float, alpha_slow: float, alpha_fast: float
) -> tuple[float, float]:
    """``w_slow`` and ``w_fast`` after a measurement of mean likelihood ``w_avg`` (each starts
    at the first ``w_avg``, then follows it with its rate ``alpha``)."""
    if w_slow == 0.0:
        w_slow = w_avg
    else:
        w_slow += alpha_slow * (w_avg - w_slow)
    if w_fast == 0.0:
        w_fast = w_avg
    else:
        w_fast += alpha_fast * (w_avg - w_fast)
    return w_slow, w_fast


def kld_limit(
    k: np.ndarray, pf_err: float, pf_z: float, min_particles: int, max_particles: int
) -> np.ndarray:
    """Nav2 ``pf_resample_limit``: particles needed for ``k`` occupied bins."""
    k = np.asarray(k, float)
    km1 = np.maximum(k - 1, 1e-9)
    b = 2.0 / (9.0 * km1)
    x = 1.0 - b + np.sqrt(b) * pf_z
    n = np.ceil(km1 / (2.0 * pf_err) * x**3)
    n = np.where(k <= 1, max_particles, n)
    return np.clip(n, min_particles, max_particles).astype(int)


def kld_bins(particles: Array, bin_xy: float, bin_theta: float) -> Array:
    """Histogram bin (N, 3) int of every particle (Nav2's ``bin_xy`` x ``bin_xy`` x
    ``bin_theta`` cells)."""
    return np.column_stack(
        [
            np.floor(particles[:, 0] / bin_xy),
            np.floor(particles[:, 1] / bin_xy),
            np.floor(particles[:, 2] / bin_theta),
        ]
    ).astype(np.int64)


def low_variance_resample(
    particles: Array,
    weights: Array,
    m: int,
    w_diff: float,
    rng: np.random.Generator,
    random_poses: Callable[[int], Array],
) -> Array:
    """``m`` particles drawn by low-variance resampling on ``weights``, in a random order,
    each replaced with probability ``w_diff`` by one of ``random_poses(k)`` (recovery)."""
    w = weights
    cdf = np.cumsum(w)
    cdf /= cdf[-1]
    u = (rng.uniform() + np.arange(m)) / m
    idx = np.minimum(np.searchsorted(cdf, u), len(w) - 1)
    new = particles[idx]
    new = new[rng.permutation(m)]  # KLD counts bins along a random order
    if w_diff > 0:
        rand = rng.uniform(size=m) < w_diff
        if rand.any():
            new[rand] = random_poses(int(rand.sum()))
    return new


def kld_size(
    new: Array,
    bin_xy: float,
    bin_theta: float,
    pf_err: float,
    pf_z: float,
    min_particles: int,
    max_particles: int,
) -> int:
    """KLD-sampling: how many of the (randomly ordered) particles ``new`` to keep: the first
    ``n`` whose occupied bins ``k`` need no more than ``n`` (:func:`kld_limit`)."""
    m = max_particles
    b = kld_bins(new, bin_xy, bin_theta)
    b -= b.min(axis=0)
    keys = (b[:, 0] * (b[:, 1].max() + 1) + b[:, 1]) * (b[:, 2].max() + 1) + b[:, 2]
    _, first = np.unique(keys, return_index=True)  # 1D keys: much faster than axis=0
    is_first = np.zeros(m, dtype=bool)
    is_first[first] = True
    k = np.cumsum(is_first)
    limit = kld_limit(k, pf_err, pf_z, min_particles, max_particles)
    n_idx = np.flatnonzero(np.arange(1, m + 1) >= limit)
    n = int(n_idx[0]) + 1 if n_idx.size else m
    return max(min(n, m), min_particles)


def cluster_mean(
    particles: Array, weights: Array, bin_xy: float, bin_theta: float
) -> tuple[Array, Array]:
    """Weighted mean and covariance of the heaviest cluster (:func:`cluster_labels`); the
    heading mean is circular."""
    P, w = particles, weights
    labels = cluster_labels(P, bin_xy, bin_theta)
    sums = np.bincount(labels, weights=w)
    best = int(np.argmax(sums))
    sel = labels == best
    ws = w[sel] / max(float(w[sel].sum()), 1e-300)
    Ps = P[sel]
    mx = float(ws @ Ps[:, 0])
    my = float(ws @ Ps[:, 1])
    cth = float(ws @ np.cos(Ps[:, 2]))
    sth = float(ws @ np.sin(Ps[:, 2]))
    th = float(np.arctan2(sth, cth))
    d = np.column_stack([Ps[:, 0] - mx, Ps[:, 1] - my, wrap(Ps[:, 2] - th)])
    cov = (d * ws[:, None]).T @ d
    return np.array([mx, my, th]), cov


def cluster_labels(
    particles: Array, bin_xy: float, bin_theta: float, max_cells: int = 2_000_000
) -> np.ndarray:
    """Cluster id (N,) int of every particle (N, 3): particles are binned ``bin_xy`` m x
    ``bin_xy`` m x ``bin_theta`` rad (Nav2's pf histogram) and occupied bins that touch
    (26-connectivity) form a cluster. The heading axis is CIRCULAR: the bin holding headings
    just below +pi touches the one just above -pi, so a cloud straddling +-pi is one cluster
    (split in two, the heavier half's mean was off by up to half the cloud's width). A cloud
    spanning more than ``max_cells`` bins is one cluster (0 for all)."""
    P = np.asarray(particles, float)
    n_th = max(1, int(np.ceil(2 * np.pi / bin_theta - 1e-9)))
    bx = np.floor(P[:, 0] / bin_xy).astype(np.int64)
    by = np.floor(P[:, 1] / bin_xy).astype(np.int64)
    bt = np.floor((wrap(P[:, 2]) + np.pi) / bin_theta).astype(np.int64) % n_th
    bx -= bx.min()
    by -= by.min()
    shape = (int(bx.max()) + 1, int(by.max()) + 1, n_th)
    if shape[0] * shape[1] * shape[2] > max_cells:
        return np.zeros(len(P), dtype=np.int64)
    occ = np.zeros(shape, dtype=bool)
    occ[bx, by, bt] = True
    lab, n_lab = ndimage.label(occ, structure=np.ones((3, 3, 3)))
    if n_th > 2 and occ[:, :, 0].any() and occ[:, :, -1].any():
        lab = _join_heading_wrap(lab, n_lab, shape)
    return lab[bx, by, bt].astype(np.int64)


def _join_heading_wrap(lab: np.ndarray, n_lab: int, shape: tuple[int, int, int]) -> np.ndarray:
    """Labels ``lab`` with the clusters that touch across the first and last heading layers
    joined."""
    first = np.pad(lab[:, :, 0], 1)
    last = lab[:, :, -1]
    a_list, b_list = [], []
    for dx in (-1, 0, 1):
        for dy in (-1, 0, 1):
            nb = first[1 + dx : 1 + dx + shape[0], 1 + dy : 1 + dy + shape[1]]
            both = (nb > 0) & (last > 0)
            a_list.append(nb[both])
            b_list.append(last[both])
    a, b = np.concatenate(a_list), np.concatenate(b_list)
    if a.size:
        g = sparse.coo_matrix((np.ones(a.size), (a, b)), shape=(n_lab + 1, n_lab + 1))
        _, comp = csgraph.connected_components(g, directed=False)
        lab = comp[lab]
    return lab
