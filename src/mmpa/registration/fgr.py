"""FPFH descriptors and the Fast Global Registration solver in numpy (beyond Open3D's speed).

Both reproduce Open3D's implementations (``compute_fpfh_feature``,
``registration_fgr_based_on_correspondence``; the tests compare them to Open3D to 1e-9),
vectorized: Open3D computes a FPFH with two k-d tree searches per point and a heap-allocated
Eigen product per residual row of FGR, ~15 ms and ~20 ms for the ~900 points of the coarse
level of a 640x480 frame, where this module takes ~3 ms and ~2 ms.

FPFH (Rusu et al. 2009). For a point ``p`` with normal ``n`` and its neighbours ``q_k``
(the ``max_nn`` nearest within ``radius``, the point itself excluded), the Darboux frame of
the pair (``u = n_1``, ``v = d x u / |d x u|``, ``w = u x v`` with ``d = p_2 - p_1``, where
the pair is ordered so that the source normal makes the smaller angle with ``d``) gives three
angles ``alpha = v . n_2``, ``phi = u . d / |d|``, ``theta = atan2(w . n_2, u . n_2)``; the
SPFH of ``p`` is the three 11-bin histograms of (theta, alpha, phi) over its neighbours,
each summing to 100. The FPFH is ``SPFH(p) + sum_k w_k SPFH(q_k) / sum_k w_k`` per
histogram with ``w_k = 1 / |q_k - p|^2`` (Open3D's weighting, squared distance).

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
"""

from __future__ import annotations

import numpy as np
from scipy.linalg.lapack import dgesv as _gesv
from scipy.sparse import csr_matrix
from scipy.spatial import cKDTree

from mmpa.geometry import Array
from mmpa.registration._blas import single_threaded_blas

__all__ = ["fgr_solve", "fpfh"]


def fpfh(
    points: Array, normals: Array, radius: float, max_nn: int, tree: cKDTree | None = None
) -> Array:
    """FPFH descriptors (N, 33) of ``points`` (N, 3) m with unit ``normals`` (N, 3).

    Neighbours: the ``max_nn`` nearest (the point itself included, as in Open3D's hybrid
    search) within ``radius`` m; ``tree`` a :class:`cKDTree` of ``points`` if one exists.
    A point without neighbours gets a zero descriptor.
    """
    P = np.asarray(points, dtype=float)
    N = np.asarray(normals, dtype=float)
    n = len(P)
    if n == 0:
        return np.zeros((0, 33))
    k = min(max_nn, n)
    d, nb = (tree or cKDTree(P)).query(P, k=k, distance_upper_bound=radius)
    d, nb = d.reshape(n, k), nb.reshape(n, k)
    # pairs (i, j): each point with its neighbours after the first (itself, distance 0)
    valid = nb[:, 1:] < n
    rows, cols = np.nonzero(valid)
    i, j = rows, nb[:, 1:][rows, cols]
    d2 = d[:, 1:][rows, cols] ** 2
    cnt = valid.sum(axis=1)
    f0, f1, f2 = _pair_features(P[i], N[i], P[j], N[j])
    # SPFH: 3 histograms of 11 bins, each incremented by 100 / (number of neighbours)
    b0 = np.clip(np.floor(11 * (f0 + np.pi) / (2.0 * np.pi)), 0, 10).astype(np.intp)
    b1 = np.clip(np.floor(11 * (f1 + 1.0) * 0.5), 0, 10).astype(np.intp)
    b2 = np.clip(np.floor(11 * (f2 + 1.0) * 0.5), 0, 10).astype(np.intp)
    incr = 100.0 / np.maximum(cnt, 1)[i]
    spfh = np.zeros(n * 33)
    for off, b in ((0, b0), (11, b1), (22, b2)):
        spfh += np.bincount(i * 33 + off + b, weights=incr, minlength=n * 33)
    spfh = spfh.reshape(n, 33)
    # FPFH: SPFH(p) + per-histogram normalised sum of the neighbours' SPFH weighted 1 / d^2
    nz = d2 > 0
    W = csr_matrix((1.0 / d2[nz], (i[nz], j[nz])), shape=(n, n))
    F = np.asarray(W @ spfh)
    s = F.reshape(n, 3, 11).sum(axis=2)
    s = np.where(s != 0.0, 100.0 / np.where(s != 0.0, s, 1.0), 0.0)
    F = (F.reshape(n, 3, 11) * s[:, :, None]).reshape(n, 33) + spfh
    F[cnt == 0] = 0.0
    return F


def _pair_features(p1: Array, n1: Array, p2: Array, n2: Array) -> tuple[Array, Array, Array]:
    """Open3D's ``ComputePairFeatures`` for arrays of pairs: (theta, alpha, phi), zero for
    coincident points or a degenerate frame."""
    dp = p2 - p1
    dist = np.sqrt(np.einsum("ij,ij->i", dp, dp))
    ok = dist > 0
    inv = 1.0 / np.where(ok, dist, 1.0)
    a1 = np.einsum("ij,ij->i", n1, dp) * inv
    a2 = np.einsum("ij,ij->i", n2, dp) * inv
    swap = np.arccos(np.abs(a1)) > np.arccos(np.abs(a2))
    u = np.where(swap[:, None], n2, n1)
    m = np.where(swap[:, None], n1, n2)
    dp = np.where(swap[:, None], -dp, dp)
    phi = np.where(swap, -a2, a1)
    v = np.cross(dp, u)
    vn = np.sqrt(np.einsum("ij,ij->i", v, v))
    ok &= vn > 0
    v = v / np.where(vn > 0, vn, 1.0)[:, None]
    w = np.cross(u, v)
    alpha = np.einsum("ij,ij->i", v, m)
    theta = np.arctan2(np.einsum("ij,ij->i", w, m), np.einsum("ij,ij->i", u, m))
    z = np.zeros_like(phi)
    return np.where(ok, theta, z), np.where(ok, alpha, z), np.where(ok, phi, z)


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
    Fewer than 10 correspondences give the identity (as Open3D).
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
    # back to metres: T' maps target to source, p_s = R (p_t - mu_t) + D t + mu_s
    T = np.eye(4)
    T[:3, :3] = R.T
    T[:3, 3] = mu_t - R.T @ (scale * t + mu_s)
    return T
