"""The Fast Global Registration solver in numpy (beyond Open3D's speed).

:func:`fgr_solve` reproduces Open3D's ``registration_fgr_based_on_correspondence`` (its
tuple test off; the tests compare the two to 1e-9), vectorized: Open3D builds a
heap-allocated Eigen product per residual row, ~20 ms for the ~3000 correspondences of the
coarse level of a 640x480 frame pair, where one weighted 7 x 7 product per iteration takes
~2-3 ms. (A numpy FPFH that reproduces Open3D's ``compute_fpfh_feature`` was tried: it is
no faster, the k-d tree search and the 40k pair features cost what Open3D's C++ does.)

FGR (Zhou et al. 2016, eq. 6-8). Both clouds are centred on their means and divided by the
largest distance to a mean, ``D``; with correspondences ``(p_i, q_i)`` (source, target) it
minimises ``sum_i rho(|p_i - T q_i|)`` over ``T`` (target to source, as in the paper),
``rho(x) = mu x^2 / (mu + x^2)`` (scaled Geman-McClure), by line processes: weights
``l_i = (mu / (mu + |p_i - T q_i|^2))^2`` and a Gauss-Newton step on
``sum_i l_i |p_i - T q_i|^2`` per iteration with the twist linearised as
``T q ~ q + w x q + t`` and the update applied as ``Rz Ry Rx`` of the twist's angles (as
Open3D). ``mu`` starts at ``D`` (Open3D passes the scale as the starting ``mu``) and, with
``decrease_mu`` (off by default in Open3D, and so here), is divided by ``division_factor``
every 4 iterations while it exceeds ``maximum_correspondence_distance`` (graduated
non-convexity; Open3D compares the normalised ``mu`` with that distance in metres, and so
does this module). The result is returned as ``T_target_source`` (the inverse).

Its correspondences (:func:`fgr_correspondences`): mutual nearest FPFH neighbours and the
tuple test, vectorized (one matrix product instead of Open3D's k-d tree in 33 dimensions,
~2x faster); :func:`feature_support` counts the matches a pose keeps together (the fine
stage's motion gate).
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
from scipy.linalg.lapack import dgesv as _gesv
from scipy.spatial.distance import cdist

from mmpa.core.geometry import Array
from mmpa.registration._blas import single_threaded_blas

__all__ = ["feature_support", "fgr_correspondences", "fgr_solve", "mutual_matches", "tuple_test"]


#: update (rad, normalised length) below which the line-process iteration has converged
_STEP_TOL = 1e-13
_DIAG3 = (np.arange(3), np.arange(3))
# [v]x = [[0, -v2, v1], [v2, 0, -v0], [-v1, v0, 0]]: its off-diagonal entries in A[:3, 3:]
_QX = (np.array([0, 0, 1, 1, 2, 2]), np.array([4, 5, 3, 5, 3, 4]))
_QX_SRC = np.array([2, 1, 2, 0, 1, 0])
_QX_SIGN = np.array([-1.0, 1.0, 1.0, -1.0, -1.0, 1.0])
# (p x q)_k = C[k+1, k+2] - C[k+2, k+1] with C = sum l p q^T
_PXQ = (np.array([1, 2, 0]), np.array([2, 0, 1]))


def _solve6(A: Array, b: Array) -> Array:
    """``A x = b`` for a 6x6 system (LAPACK without numpy.linalg's per-call checks)."""
    return _gesv(A, b)[2]


def _rotation_zyx(x: Array) -> Array:
    """``Rz(x2) Ry(x1) Rx(x0)`` (Open3D's ``TransformVector6dToMatrix4d``)."""
    cx, cy, cz = np.cos(x[:3])
    sx, sy, sz = np.sin(x[:3])
    return np.array(
        [
            [cz * cy, cz * sy * sx - sz * cx, cz * sy * cx + sz * sx],
            [sz * cy, sz * sy * sx + cz * cx, sz * sy * cx - cz * sx],
            [-sy, cy * sx, cy * cx],
        ]
    )


def fgr_solve(
    p_source: Array,
    p_target: Array,
    corr: Array,
    max_correspondence_distance: float,
    iterations: int = 64,
    decrease_mu: bool = False,
    division_factor: float = 1.4,
) -> Array:
    """``T_target_source`` (4, 4) by FGR's graduated-non-convexity solve (module docstring).

    ``p_source`` (N, 3), ``p_target`` (M, 3) m: the whole clouds (their means and extent
    normalise the problem, as in Open3D); ``corr`` (K, 2) int pairs ``(source, target)``.
    Fewer than 10 correspondences give the identity (as Open3D). The iteration stops early
    at a fixed point (every update component below 1e-13, ``mu`` final): Open3D's remaining
    iterations would not move ``T`` (same result to 1e-14 on the benchmark's pairs, ~3x
    less time).
    """
    with single_threaded_blas():  # 7 x K products: a second BLAS thread only costs
        return _fgr_solve(
            p_source,
            p_target,
            corr,
            max_correspondence_distance,
            iterations,
            decrease_mu,
            division_factor,
        )


def _fgr_solve(
    p_source: Array,
    p_target: Array,
    corr: Array,
    max_correspondence_distance: float,
    iterations: int,
    decrease_mu: bool,
    division_factor: float,
) -> Array:
    Ps = np.asarray(p_source, dtype=float)
    Pt = np.asarray(p_target, dtype=float)
    corr = np.asarray(corr, dtype=np.intp).reshape(-1, 2)
    mu_s, mu_t = Ps.mean(axis=0), Pt.mean(axis=0)
    scale = max(
        float(np.sqrt(((Ps - mu_s) ** 2).sum(axis=1)).max()),
        float(np.sqrt(((Pt - mu_t) ** 2).sum(axis=1)).max()),
    )
    if len(corr) < 10 or not scale > 0:
        return np.eye(4)
    # equal pairs contribute equally: sum once, weighted by their multiplicity
    pairs, mult = np.unique(corr, axis=0, return_counts=True)
    p = (Ps[pairs[:, 0]] - mu_s) / scale
    q0 = (Pt[pairs[:, 1]] - mu_t) / scale
    mult = mult.astype(float)
    R, t = np.eye(3), np.zeros(3)
    par = scale  # Open3D passes the global scale as the starting mu
    # X = [q, p, 1]: one weighted product X^T diag(l) X per iteration holds every sum of
    # the normal equations (sum l q q^T, sum l p q^T, sum l q, sum l p, sum l)
    X = np.empty((len(p), 7))
    X[:, 3:6], X[:, 6] = p, 1.0
    A, b = np.zeros((6, 6)), np.zeros(6)
    for it in range(iterations):
        q = X[:, :3]
        np.matmul(q0, R.T, out=q)
        q += t
        r = p - q
        s = (par / (np.einsum("ij,ij->i", r, r) + par)) ** 2 * mult
        M = (X.T * s) @ X
        Sqq, C, Sq, Sp, S0 = M[:3, :3], M[3:6, :3], M[:3, 6], M[3:6, 6], M[6, 6]
        # J_i = [[q_i]x, -I] (rows: residual axes) with r_i = p_i - q_i:
        # sum J^T J = [[tr(Sqq) I - Sqq, [Sq]x], [-[Sq]x, S0 I]],
        # sum J^T r = [sum l r x q, -sum l r] with r x q = p x q
        A[:3, :3] = -Sqq
        A[_DIAG3] += Sqq[_DIAG3].sum()
        A[_QX] = Sq[_QX_SRC] * _QX_SIGN
        A[3:, :3] = -A[:3, 3:]
        A[_DIAG3[0] + 3, _DIAG3[1] + 3] = S0
        b[:3] = C[_PXQ] - C.T[_PXQ]
        b[3:] = Sq - Sp
        x = _solve6(-A, b)
        dR = _rotation_zyx(x)
        R, t = dR @ R, dR @ t + x[3:]
        if decrease_mu and it % 4 == 0 and par > max_correspondence_distance:
            par /= division_factor
        elif np.abs(x).max() < _STEP_TOL and (
            not decrease_mu or par <= max_correspondence_distance
        ):
            break  # a fixed point: the remaining iterations would not move T
    # back to metres: T' maps target to source, p_s = R (p_t - mu_t) + D t + mu_s
    T = np.eye(4)
    T[:3, :3] = R.T
    T[:3, 3] = mu_t - R.T @ (scale * t + mu_s)
    return T


def fgr_correspondences(
    f_src: Array,
    f_tgt: Array,
    p_src: Array,
    p_tgt: Array,
    max_tuples: int,
    tuple_scale: float,
    rng: np.random.Generator,
) -> Array:
    """Correspondences of Fast Global Registration (Zhou et al. 2016, §3 "initial
    correspondences" and the tuple test), vectorized.

    ``f_src`` (N, d), ``f_tgt`` (M, d) descriptors of the points ``p_src`` (N, 3) and
    ``p_tgt`` (M, 3). Mutual nearest neighbours in descriptor space, with the squared
    distances ``|a_i|^2 - 2 a_i . b_j + |b_j|^2`` from one matrix product: pairs ``(i, j)``
    with ``j = argmin_j' |a_i - b_j'|`` and ``i = argmin_i' |a_i' - b_j|``. Tuple test: of
    up to ``100 K`` random triples of the ``K`` mutual pairs (drawn from ``rng``), keep those
    whose three edge lengths agree, ``tuple_scale < l_tgt / l_src < 1 / tuple_scale`` for
    every edge, until ``max_tuples`` triples pass. Returns the (3 T, 2) int32 index pairs
    ``(source, target)`` of the ``T`` accepted triples (the input of Open3D's
    ``registration_fgr_based_on_correspondence`` without its own tuple test).
    """
    return tuple_test(mutual_matches(f_src, f_tgt), p_src, p_tgt, max_tuples, tuple_scale, rng)


def mutual_matches(f_src: Array, f_tgt: Array) -> Array:
    """Mutual nearest neighbours ``(i, j)`` (K, 2) of the descriptors ``f_src`` (N, d) and
    ``f_tgt`` (M, d): ``j = argmin_j' |a_i - b_j'|`` and ``i = argmin_i' |a_i' - b_j|``, the
    squared distances ``|a_i|^2 - 2 a_i . b_j + |b_j|^2`` from one matrix product."""
    a = np.asarray(f_src, np.float32)
    b = np.asarray(f_tgt, np.float32)
    if len(a) == 0 or len(b) == 0:
        return np.zeros((0, 2), np.int64)
    # row-wise argmins of contiguous matrices (a column-wise argmin is ~15x slower)
    with single_threaded_blas():
        j_of_i = ((b * b).sum(axis=1)[None, :] - 2.0 * (a @ b.T)).argmin(axis=1)
        i_of_j = ((a * a).sum(axis=1)[None, :] - 2.0 * (b @ a.T)).argmin(axis=1)
    i = np.flatnonzero(i_of_j[j_of_i] == np.arange(len(a)))
    return np.stack([i, j_of_i[i]], axis=1)


def tuple_test(
    pairs: Array,
    p_src: Array,
    p_tgt: Array,
    max_tuples: int,
    tuple_scale: float,
    rng: np.random.Generator,
) -> Array:
    """FGR's tuple test of the matches ``pairs`` (K, 2) (:func:`fgr_correspondences`)."""
    k = len(pairs)
    if k < 3:
        return np.zeros((0, 2), np.int32)
    ps, pt = np.asarray(p_src, float)[pairs[:, 0]], np.asarray(p_tgt, float)[pairs[:, 1]]
    # edge lengths between all mutual pairs, flattened for the lookups
    d_s = cdist(ps, ps).astype(np.float32).ravel()
    d_t = cdist(pt, pt).astype(np.float32).ravel()
    found: list[Array] = []
    n_found, trials, batch = 0, 100 * k, 20000
    for start in range(0, trials, batch):
        r = rng.integers(0, k, (min(batch, trials - start), 3))
        ok = np.ones(len(r), bool)
        for e0, e1 in ((0, 1), (1, 2), (2, 0)):
            e = r[:, e0] * k + r[:, e1]
            ls, lt = d_s[e], d_t[e]
            ok &= (ls * tuple_scale < lt) & (lt * tuple_scale < ls)
        sel = r[ok][: max_tuples - n_found]
        found.append(sel)
        n_found += len(sel)
        if n_found >= max_tuples:
            break
    return pairs[np.concatenate(found).reshape(-1)].astype(np.int32)


def feature_support(src: Array, tgt: Array, corr: Array, radius: float) -> Callable[[Array], int]:
    """``support(T)``: how many of the feature correspondences ``corr`` (K, 2) between the
    coarse points ``src`` (N, 3) and ``tgt`` (M, 3) a pose ``T`` (4, 4) maps within
    ``radius`` (m) of each other, ``|R p_s + t - p_t| < radius``."""
    c = np.asarray(corr, dtype=np.int64).reshape(-1, 2)
    ps, pt = src[c[:, 0]], tgt[c[:, 1]]

    def support(T: Array) -> int:
        d = ps @ T[:3, :3].T + T[:3, 3] - pt
        return int(np.count_nonzero(np.einsum("ij,ij->i", d, d) < radius * radius))

    return support
