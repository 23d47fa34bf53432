"""mmpa.registration on synthetic clouds with a known transform (fast unit tests)."""

from __future__ import annotations

import numpy as np
import pytest

from mmpa.core.errors import ConfigError, InvalidInputError
from mmpa.core.geometry import exp_se3, inv, make_T, rotation_error, rpy_to_R, translation_error
from mmpa.registration import (
    IcpScale,
    Registration,
    RegistrationConfig,
    information_matrix,
    prepare,
    register,
)
from mmpa.registration.checks import _color_gradients
from mmpa.registration.fgr import fgr_correspondences
from mmpa.robot.interfaces import PointCloud

CFG = RegistrationConfig(presample=1)


def _texture(p: np.ndarray) -> np.ndarray:
    """A smooth multi-color pattern over world points (m) -> colors in [0, 1]."""
    r = 0.5 + 0.4 * np.sin(40 * p[:, 0]) * np.cos(35 * p[:, 1])
    g = 0.5 + 0.4 * np.sin(30 * p[:, 1] + 20 * p[:, 2])
    b = 0.5 + 0.4 * np.cos(45 * p[:, 2] + 25 * p[:, 0])
    return np.stack([r, g, b], axis=1)


def _scene(rng: np.random.Generator, n: int = 60000, kind: str = "bench") -> np.ndarray:
    """Random points on a bench-like scene in a camera-ish frame (z forward, 0.45-0.8 m).

    ``bench``: a table plane, a back wall, a box and a ball; ``plane``: the table plane only.
    """
    u = rng.uniform(-1, 1, (n, 2))
    table = np.stack([0.35 * u[:, 0], 0.12 + 0.02 * u[:, 1], 0.62 + 0.17 * u[:, 1]], 1)
    table[:, 1] = 0.12 - 0.5 * (table[:, 2] - 0.62)  # tilted towards the camera
    if kind == "plane":
        return table
    wall = np.stack([0.35 * u[:, 0], -0.1 + 0.12 * u[:, 1], np.full(n, 0.8)], 1)
    # a box (three visible faces) and a ball
    m = n // 4
    a, b = rng.uniform(0, 1, (2, m))
    box = np.concatenate(
        [
            np.stack([-0.15 + 0.08 * a, 0.0 + 0.0 * b, 0.58 + 0.08 * b], 1),
            np.stack([-0.15 + 0.0 * a, -0.08 * b, 0.58 + 0.08 * a], 1),
            np.stack([-0.15 + 0.08 * a, -0.08 * b, np.full(m, 0.58)], 1),
        ]
    )
    v = rng.normal(size=(m, 3))
    v /= np.linalg.norm(v, axis=1, keepdims=True)
    v[:, 2] = -np.abs(v[:, 2])
    ball = np.array([0.15, 0.02, 0.62]) + 0.05 * v
    return np.concatenate([table[: n // 2], wall[: n // 2], box, ball])


def _pair(
    T: np.ndarray, kind: str = "bench", color: str = "texture", seed: int = 0, noise: float = 5e-4
) -> tuple[PointCloud, PointCloud]:
    """Source and target clouds sampled independently from one world; ``p_t = T p_s``."""
    rng = np.random.default_rng(seed)
    ws, wt = _scene(rng, kind=kind), _scene(rng, kind=kind)

    def col(p: np.ndarray) -> np.ndarray:
        if color == "texture":
            return _texture(p)
        return np.full_like(p, 0.6)

    src = ws + rng.normal(0, noise, ws.shape)
    tgt_world = wt + rng.normal(0, noise, wt.shape)
    tgt = tgt_world @ T[:3, :3].T + T[:3, 3]
    return PointCloud(src, col(ws)), PointCloud(tgt, col(wt))


T_TRUE = make_T(rpy_to_R(0.02, -0.015, 0.03), [0.025, -0.015, 0.01])


def _check(r: Registration, T: np.ndarray, et: float = 1.5e-3, er: float = 0.004) -> None:
    assert r.ok, r.reason
    assert translation_error(T, r.T) < et
    assert rotation_error(T, r.T) < er


def test_recovers_known_transform_colored() -> None:
    src, tgt = _pair(T_TRUE)
    paper = RegistrationConfig.paper(presample=1)
    r = register(src, tgt, paper)
    _check(r, T_TRUE)
    assert r.stages["method"] == "colored_icp"
    assert r.fitness > 0.8 and r.rmse < 5e-3 and r.n_correspondences > 1000
    assert r.reason == "" and r.seconds > 0
    # p_target = T p_source: the inverse problem gives the inverse transform
    r2 = register(tgt, src, paper)
    _check(r2, inv(T_TRUE))


def test_auto_uses_geometry_when_it_constrains_the_pose() -> None:
    """``auto``: the bench's geometry pins all six directions, so point-to-plane ICP alone,
    without the photometric term (and without estimating the source's normals)."""
    src, tgt = _pair(T_TRUE)
    r = register(src, tgt, CFG)
    _check(r, T_TRUE)
    assert r.stages["method"] == "point_to_plane_icp"
    assert r.stages["min_information"] >= CFG.geometric_min_information
    assert "colored_icp0_s" not in r.stages


def test_geometric_icp_without_color() -> None:
    src, tgt = _pair(T_TRUE, color="flat")
    r = register(src, tgt, CFG)
    assert r.stages["method"] == "point_to_plane_icp"
    _check(r, T_TRUE)


def test_init_skips_global_stage_and_is_validated() -> None:
    T = make_T(rpy_to_R(0.002, 0.0, -0.003), [0.002, 0.001, -0.002])
    src, tgt = _pair(T, seed=3)
    r = register(src, tgt, CFG, init=np.eye(4))
    _check(r, T)
    assert "coarse_s" not in r.stages
    # an init far from the truth is not silently accepted
    bad = register(src, tgt, CFG, init=make_T(rpy_to_R(0.0, 0.0, 0.5), [0.2, 0.0, 0.0]))
    assert not bad.ok and bad.reason


def test_pure_color_plane_is_refused_textured_plane_is_not() -> None:
    T = make_T(rpy_to_R(0.0, 0.0, 0.004), [0.004, -0.003, 0.0])
    src, tgt = _pair(T, kind="plane", color="flat")
    r = register(src, tgt, CFG, init=np.eye(4))
    assert not r.ok
    assert "degenerate" in r.reason
    r = register(src, tgt, CFG)  # with the global stage too
    assert not r.ok
    # the same plane with rich texture is constrained by color (paper Table A.7 Ex A.3)
    src, tgt = _pair(T, kind="plane", color="texture")
    r = register(src, tgt, CFG, init=np.eye(4))
    _check(r, T, et=2e-3)
    assert r.stages["min_information"] >= CFG.min_information
    # auto: point-to-plane first, found degenerate, then colored ICP
    assert r.stages["method"] == "colored_icp" and "colored_icp0_s" in r.stages
    assert "degenerate" in r.stages["geometric_reason"]
    assert r.stages["geometric_information"] < CFG.min_information
    # ... but not by geometry alone
    geo = CFG.model_copy(update={"color_mode": "geometric"})
    r = register(src, tgt, geo, init=np.eye(4))
    assert not r.ok and "degenerate" in r.reason


def test_failures_have_reasons() -> None:
    src, tgt = _pair(T_TRUE)
    empty = PointCloud(np.zeros((0, 3)), np.zeros((0, 3)))
    r = register(empty, tgt, CFG)
    assert not r.ok and r.reason.startswith("source: too few points")
    # everything out of the depth range
    far = PointCloud(tgt.points + np.array([0, 0, 5.0]), tgt.colors)
    r = register(src, far, CFG)
    assert not r.ok and r.reason.startswith("target: too few points")
    # no overlap: the target sees something else (a heap of balls)
    rng = np.random.default_rng(9)
    v = rng.normal(size=(40000, 3))
    v /= np.linalg.norm(v, axis=1, keepdims=True)
    centers = rng.uniform([-0.3, -0.2, 0.6], [0.3, 0.2, 0.9], (20, 3))
    balls = centers[rng.integers(0, 20, 40000)] + 0.03 * v
    r = register(src, PointCloud(balls, _texture(balls)), CFG)
    assert not r.ok
    assert any(w in r.reason for w in ("fitness", "correspondences", "moved", "RMSE"))


def test_non_finite_points() -> None:
    src, tgt = _pair(T_TRUE)
    pts = tgt.points.copy()
    pts[::10] = np.nan
    nan_tgt = PointCloud(pts, tgt.colors)
    r = register(src, nan_tgt, CFG)  # filtered by default, counted in the diagnostics
    _check(r, T_TRUE)
    assert prepare(nan_tgt, CFG).stats["n_nonfinite"] == len(pts[::10])
    strict = CFG.model_copy(update={"nan_policy": "reject"})
    r = register(src, nan_tgt, strict)
    assert not r.ok and "non-finite" in r.reason
    all_nan = PointCloud(np.full((500, 3), np.nan), np.zeros((500, 3)))
    r = register(src, all_nan, CFG)
    assert not r.ok and "500 non-finite" in r.reason


def test_bad_input_raises() -> None:
    src, tgt = _pair(T_TRUE)

    class Raw:
        points = np.zeros((10, 2))
        colors = None

    with pytest.raises(InvalidInputError, match=r"\(N, 3\)"):
        register(Raw(), tgt, CFG)
    with pytest.raises(InvalidInputError, match="4x4"):
        register(src, tgt, CFG, init=np.eye(3))
    with pytest.raises(InvalidInputError, match="rotation"):
        register(src, tgt, CFG, init=np.diag([1.0, 1.0, -1.0, 1.0]))
    other = CFG.model_copy(update={"coarse_voxel": 0.025})
    with pytest.raises(ConfigError, match="prepared"):
        register(prepare(src, CFG), tgt, other)
    with pytest.raises(ValueError, match="max_depth"):
        RegistrationConfig(min_depth=1.0, max_depth=0.5)


def test_prepared_reuse_and_determinism() -> None:
    src, tgt = _pair(T_TRUE, seed=5)
    a = register(src, tgt, CFG)
    b = register(prepare(src, CFG), prepare(tgt, CFG), CFG)
    c = register(src, tgt, CFG)
    assert a.ok and b.ok
    # same seed, same result (up to the summation order of Open3D's threaded reductions)
    np.testing.assert_allclose(a.T, c.T, atol=1e-12)
    np.testing.assert_allclose(a.T, b.T, atol=1e-9)
    assert a.fitness == c.fitness and a.n_correspondences == c.n_correspondences


def test_colorless_cloud_object_uses_geometry() -> None:
    """A cloud-like object with ``colors=None`` selects point-to-plane ICP."""
    src, tgt = _pair(T_TRUE, color="flat")

    class Bare:
        def __init__(self, p: np.ndarray) -> None:
            self.points, self.colors = p, None

    r = register(Bare(src.points), tgt, CFG)
    assert r.stages["method"] == "point_to_plane_icp"
    _check(r, T_TRUE)


def test_information_matrix_matches_numeric_jacobian() -> None:
    """H = lambda J^T J / N with J the derivative of the point-to-plane residuals, checked
    against finite differences of r_i(xi) = n_i . (exp(xi) about the centroid applied to s_i)."""
    rng = np.random.default_rng(1)
    s = rng.uniform(-0.2, 0.2, (50, 3)) + np.array([0, 0, 0.6])
    n = rng.normal(size=(50, 3))
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    c = s.mean(axis=0)
    L = np.sqrt(((s - c) ** 2).sum(axis=1).mean())

    def resid(xi: np.ndarray) -> np.ndarray:
        w, v = xi[:3] / L, xi[3:]  # rotation scaled by L, as documented
        T = make_T(None, c) @ exp_se3(np.r_[v, w]) @ make_T(None, -c)
        q = s @ T[:3, :3].T + T[:3, 3]
        return ((q - s) * n).sum(axis=1)

    # geometry.exp_se3 takes (v, w); check its convention on a pure translation first
    assert np.allclose(exp_se3(np.r_[1.0, 2.0, 3.0, 0, 0, 0])[:3, 3], [1, 2, 3])
    h = 1e-6
    J = np.stack([(resid(h * e) - resid(-h * e)) / (2 * h) for e in np.eye(6)], axis=1)
    H = information_matrix(s, n, None, 0.9)
    np.testing.assert_allclose(H, 0.9 * J.T @ J / len(s), atol=1e-7)
    # a single plane leaves exactly three unconstrained directions
    plane_n = np.tile([0.0, 0.0, 1.0], (50, 1))
    s_plane = s.copy()
    s_plane[:, 2] = 0.6
    w = np.linalg.eigvalsh(information_matrix(s_plane, plane_n))
    assert np.all(w[:3] < 1e-12) and np.all(w[3:] > 0.1)


def test_color_gradient_of_a_linear_ramp() -> None:
    """Park 2017 eq. 10 on a plane z = 0.6 with intensity 0.2 + 3 x - 2 y: d = (3, -2, 0)."""
    rng = np.random.default_rng(2)
    p = np.c_[rng.uniform(-0.1, 0.1, (3000, 2)), np.full(3000, 0.6)]
    inten = 0.2 + 3 * p[:, 0] - 2 * p[:, 1]
    n = np.tile([0.0, 0.0, 1.0], (3000, 1))
    d = _color_gradients(p, n, inten, np.arange(0, 3000, 7), 0.02, 12)
    np.testing.assert_allclose(d, np.tile([3.0, -2.0, 0.0], (len(d), 1)), atol=1e-6)


def test_config_scales_and_voxels() -> None:
    cfg = RegistrationConfig(
        scales=(IcpScale(voxel=0.03, max_distance=0.04, max_iter=5),),
        init_scales=(IcpScale(voxel=0.015, max_distance=0.02, max_iter=5),),
    )
    assert cfg.fine_voxel == 0.015
    p = prepare(_pair(T_TRUE)[0], cfg)
    assert sorted(p.levels) == [0.015, 0.03]
    spacing = np.asarray(p.levels[0.015].points)
    assert 500 < len(spacing) < 20000


def test_fgr_correspondences_are_mutual_neighbours_passing_the_tuple_test() -> None:
    """Against a brute-force computation: every returned pair is a mutual nearest neighbour in
    descriptor space (k-d tree, float64), every triple passes the edge-length test, and on a
    rigid copy with noisy descriptors most pairs are true matches."""
    from scipy.spatial import cKDTree

    rng = np.random.default_rng(4)
    n = 400
    p_src = rng.uniform(-0.3, 0.3, (n, 3))
    T = make_T(rpy_to_R(0.1, -0.05, 0.3), [0.05, -0.02, 0.01])
    perm = rng.permutation(n)
    p_tgt = (p_src @ T[:3, :3].T + T[:3, 3])[perm]
    f_src = rng.uniform(0, 10, (n, 33))
    f_tgt = f_src[perm] + rng.normal(0, 0.5, (n, 33))
    f_tgt[:40] = rng.uniform(0, 10, (40, 33))  # 10 % of the targets match nothing
    c = fgr_correspondences(f_src, f_tgt, p_src, p_tgt, 200, 0.95, np.random.default_rng(0))
    assert c.shape[1] == 2 and len(c) % 3 == 0 and 0 < len(c) <= 600
    j_of_i = cKDTree(f_tgt).query(f_src)[1]
    i_of_j = cKDTree(f_src).query(f_tgt)[1]
    assert np.all(j_of_i[c[:, 0]] == c[:, 1]) and np.all(i_of_j[c[:, 1]] == c[:, 0])
    for t in c.reshape(-1, 3, 2):
        for e0, e1 in ((0, 1), (1, 2), (2, 0)):
            ls = np.linalg.norm(p_src[t[e0, 0]] - p_src[t[e1, 0]])
            lt = np.linalg.norm(p_tgt[t[e0, 1]] - p_tgt[t[e1, 1]])
            assert 0.95 * ls < lt < ls / 0.95
    true = perm[c[:, 1]] == c[:, 0]
    assert true.mean() > 0.95
    # seeded: same draws, same tuples
    c2 = fgr_correspondences(f_src, f_tgt, p_src, p_tgt, 200, 0.95, np.random.default_rng(0))
    np.testing.assert_array_equal(c, c2)


def test_outlier_filter_and_normals_match_open3d() -> None:
    """The one-search statistical filter and normals against Open3D's own
    ``remove_statistical_outlier`` and ``estimate_normals`` on a voxelized bench with
    flying points."""
    import open3d as o3d

    from mmpa.registration.preprocess import _clean_and_normals

    rng = np.random.default_rng(6)
    pts = _scene(rng, 60000)
    flying = rng.uniform([-0.3, -0.2, 0.5], [0.3, 0.2, 0.9], (300, 3))
    pc = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(np.r_[pts, flying]))
    pc = pc.voxel_down_sample(0.01)
    p = np.asarray(pc.points)
    keep, n = _clean_and_normals(p, 0.01, CFG)
    _, ind = pc.remove_statistical_outlier(CFG.outlier_neighbors, CFG.outlier_std_ratio)
    ref_keep = np.zeros(len(p), bool)
    ref_keep[ind] = True
    assert np.mean(keep == ref_keep) > 0.998 and (~keep).sum() > 50
    kept = pc.select_by_index(np.flatnonzero(keep))
    kept.estimate_normals(
        o3d.geometry.KDTreeSearchParamHybrid(CFG.normal_radius_factor * 0.01, CFG.normal_max_nn)
    )
    kept.orient_normals_towards_camera_location(np.zeros(3))
    cos = np.einsum("ij,ij->i", n, np.asarray(kept.normals))
    assert np.mean(cos > np.cos(np.deg2rad(2.0))) > 0.98
    assert np.all(np.einsum("ij,ij->i", n, np.asarray(kept.points)) <= 0)  # face the camera


def test_smallest_eigenvector_matches_eigh() -> None:
    """The closed-form smallest eigenvector against LAPACK's on random covariances, including
    nearly planar (rank-2) ones as on a surface, and a degenerate all-zero matrix."""
    from mmpa.registration.preprocess import _smallest_eigenvector

    rng = np.random.default_rng(8)
    X = rng.normal(size=(500, 12, 3)) * np.array([0.01, 0.008, 0.0])  # planar neighbourhoods
    X[250:] = rng.normal(size=(250, 12, 3)) * rng.uniform(0.001, 0.01, (250, 1, 3))
    X[::7, :, 2] += rng.normal(0, 1e-5, (len(X[::7]), 12))  # noise off the plane
    R = np.stack([rpy_to_R(*a) for a in rng.uniform(-np.pi, np.pi, (500, 3))])
    X = np.einsum("nij,nkj->nki", R, X)
    X -= X.mean(axis=1, keepdims=True)
    C = np.einsum("nki,nkj->nij", X, X) / 12
    v = _smallest_eigenvector(
        C[:, 0, 0], C[:, 1, 1], C[:, 2, 2], C[:, 0, 1], C[:, 0, 2], C[:, 1, 2]
    )
    w, V = np.linalg.eigh(C)
    ok = w[:, 1] - w[:, 0] > 1e-3 * w[:, 2]  # a well-defined smallest direction
    assert ok.sum() > 400
    cos = np.abs(np.einsum("ni,ni->n", v, V[:, :, 0]))
    assert np.all(cos[ok] > 1 - 1e-6)
    np.testing.assert_allclose(np.linalg.norm(v, axis=1), 1.0, atol=1e-12)
    z = np.zeros(1)
    np.testing.assert_array_equal(_smallest_eigenvector(z, z, z, z, z, z), [[0.0, 0.0, 1.0]])


def _coarse_pair() -> tuple:
    """The coarse clouds of a prepared bench pair and their FGR correspondences."""
    from mmpa.registration.preprocess import feature_matrix as _feature_matrix

    src, tgt = _pair(T_TRUE, seed=2)
    P, Q = prepare(src, CFG), prepare(tgt, CFG)
    ps, pt = np.asarray(P.coarse.points), np.asarray(Q.coarse.points)
    corr = fgr_correspondences(
        _feature_matrix(P, P.fpfh(CFG)),
        _feature_matrix(Q, Q.fpfh(CFG)),
        ps,
        pt,
        CFG.fgr_max_tuples,
        CFG.fgr_tuple_scale,
        np.random.default_rng(0),
    )
    return P, Q, corr


@pytest.mark.parametrize("decrease_mu", [False, True])
def test_fgr_solve_matches_open3d(decrease_mu: bool) -> None:
    """The vectorized FGR solver against Open3D's ``registration_fgr_based_on_correspondence``
    on the same correspondences (its own tuple test off), with and without graduated
    non-convexity, and on a rigidly moved copy with 20 % wrong pairs against the truth."""
    import open3d as o3d

    from mmpa.registration.fgr import fgr_solve

    reg = o3d.pipelines.registration
    P, Q, corr = _coarse_pair()
    assert len(corr) > 100
    dist = CFG.fgr_distance_factor * CFG.coarse_voxel
    opt = reg.FastGlobalRegistrationOption(
        maximum_correspondence_distance=dist,
        iteration_number=CFG.fgr_iterations,
        tuple_test=False,
        decrease_mu=decrease_mu,
    )
    ref = reg.registration_fgr_based_on_correspondence(
        P.coarse, Q.coarse, o3d.utility.Vector2iVector(corr), opt
    ).transformation
    T = fgr_solve(
        np.asarray(P.coarse.points),
        np.asarray(Q.coarse.points),
        corr,
        dist,
        CFG.fgr_iterations,
        decrease_mu=decrease_mu,
    )
    np.testing.assert_allclose(T, np.asarray(ref), atol=1e-9)
    # independent of Open3D: a moved copy, exact pairs plus 20 % random ones
    rng = np.random.default_rng(5)
    p = rng.uniform(-0.3, 0.3, (500, 3)) + np.array([0.0, 0.0, 0.6])
    Tt = make_T(rpy_to_R(0.05, -0.1, 0.2), [0.04, -0.03, 0.02])
    q = p @ Tt[:3, :3].T + Tt[:3, 3]
    c = np.r_[np.stack([np.arange(400)] * 2, 1), rng.integers(0, 500, (100, 2))]
    T2 = fgr_solve(p, q, c, dist, 64, decrease_mu=True)
    assert translation_error(Tt, T2) < 2e-4 and rotation_error(Tt, T2) < 1e-3
    np.testing.assert_array_equal(fgr_solve(p, q, c[:9], dist), np.eye(4))  # < 10 pairs


def test_fine_normals_only_on_use_and_equal_to_the_one_search() -> None:
    """``prepare`` keeps its outlier search; the finest level's normals are computed from it
    only when the cloud is used as an ICP target, equal to :func:`_clean_and_normals`."""
    import open3d as o3d

    from mmpa.registration.preprocess import _clean_and_normals

    src, _ = _pair(T_TRUE)
    P = prepare(src, CFG)
    v = CFG.fine_voxel
    assert not P.levels[v].has_normals()
    n = np.asarray(P.with_normals(v, CFG).normals)
    raw = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(src.points))
    fine = raw.voxel_down_sample(v)
    keep, ref = _clean_and_normals(np.asarray(fine.points), v, CFG)
    np.testing.assert_allclose(np.asarray(P.levels[v].points), np.asarray(fine.points)[keep])
    np.testing.assert_allclose(n, ref, atol=1e-12)
    assert not P.levels[0.02].has_normals()


def test_open3d_thread_cap_is_restored_and_changes_nothing() -> None:
    """``open3d_threads`` caps Open3D's workers only during the call; the pose is the same
    with Open3D's default threads (up to the order of its parallel sums)."""
    import open3d as o3d

    src, tgt = _pair(T_TRUE, seed=7)
    before = o3d.utility.get_max_threads()
    a = register(src, tgt, CFG)
    assert CFG.open3d_threads == 1 and o3d.utility.get_max_threads() == before
    b = register(src, tgt, CFG.model_copy(update={"open3d_threads": None}))
    _check(a, T_TRUE)
    np.testing.assert_allclose(a.T, b.T, atol=1e-6)


def test_color_correlation_matches_numpy_and_ignores_gain_and_offset() -> None:
    from mmpa.registration.checks import color_correlation

    rng = np.random.default_rng(4)
    a = rng.random((500, 3))
    b = 0.7 * a + 0.1 * rng.random((500, 3))
    expected = np.corrcoef(a.mean(axis=1), b.mean(axis=1))[0, 1]
    assert color_correlation(a, b) == pytest.approx(expected, abs=1e-12)
    assert color_correlation(a, 0.3 * b + 0.4) == pytest.approx(expected, abs=1e-12)
    assert color_correlation(a, 1.0 - b) == pytest.approx(-expected, abs=1e-12)
    assert color_correlation(a, np.full_like(a, 0.5)) == np.inf  # untextured: no check
    with pytest.raises(InvalidInputError):
        color_correlation(a, b[:10])


def test_color_correlation_given_the_position_ignores_a_lighting_gradient() -> None:
    from mmpa.registration.checks import color_correlation

    rng = np.random.default_rng(5)
    p = rng.uniform([-0.4, -0.3, 0.6], [0.4, 0.3, 1.2], (800, 3))  # m
    texture = rng.random(800)
    a = np.repeat(texture[:, None], 3, axis=1)
    noisy = texture + 0.05 * rng.standard_normal(800)
    # the repeat's light: exposure, offset and a strong gradient across the scene
    lit = 0.8 * noisy + 0.1 + p @ np.array([1.2, -0.8, 0.4])
    b = np.repeat(lit[:, None], 3, axis=1)
    plain = color_correlation(a, b)
    partial = color_correlation(a, b, points=p)
    # the independent computation: residuals of both on [1, x, y, z], then numpy's Pearson
    X = np.column_stack([np.ones(800), p])
    res = [y - X @ np.linalg.lstsq(X, y, rcond=None)[0] for y in (texture, lit)]
    assert partial == pytest.approx(np.corrcoef(*res)[0, 1], abs=1e-9)
    assert partial > 0.95 and plain < 0.7  # the gradient fooled the plain check
    # a wrong match (the texture of other points) stays refused under the same light
    wrong = np.repeat(rng.permutation(lit)[:, None], 3, axis=1)
    assert abs(color_correlation(a, wrong, points=p)) < 0.15
    with pytest.raises(InvalidInputError):
        color_correlation(a, b, points=p[:10])


def test_fine_motion_gate_lets_the_feature_matches_vote(monkeypatch) -> None:
    """A coarse pose 6 cm off (FGR misled) from which the fine stage reaches the true pose:
    the fixed gate (50 mm from the coarse pose) refuses the fine pose; the ``support`` gate
    accepts it when the feature matches agree with it (the true matches), and refuses it
    when they agree with the coarse pose instead (matches that point where ICP did not go)."""
    import mmpa.registration.pipeline as pl

    src, tgt = _pair(T_TRUE)
    off = T_TRUE @ make_T(rpy_to_R(0.0, 0.0, 0.02), [0.06, 0.0, 0.0])
    monkeypatch.setattr(pl, "fgr_solve", lambda *a, **k: off.copy())
    fixed = register(src, tgt, CFG.model_copy(update={"fine_motion_gate": "fixed"}))
    assert not fixed.ok and "fine stage moved" in fixed.reason
    assert translation_error(T_TRUE, fixed.T) < 1.5e-3  # the fine stage itself was right
    vote = CFG  # the default gate
    assert vote.fine_motion_gate == "support"
    r = register(src, tgt, vote)
    _check(r, T_TRUE)
    assert r.stages["fine_support"] >= 0.5 * r.stages["coarse_support"]

    def matches_of(T: np.ndarray):  # each source point's nearest target point under T
        def corr(pairs, ps, pt, *a, **k):  # in place of FGR's tuple test of the matches
            from scipy.spatial import cKDTree

            d, j = cKDTree(pt).query(ps @ T[:3, :3].T + T[:3, 3])
            keep = np.nonzero(d < 0.01)[0]
            return np.stack([keep, j[keep]], axis=1)

        return corr

    monkeypatch.setattr(pl, "tuple_test", matches_of(off))
    r = register(src, tgt, vote)
    assert not r.ok and "fine stage moved" in r.reason
    assert r.stages["fine_support"] < 0.5 * r.stages["coarse_support"]


def test_feature_support_counts_matches_within_the_radius() -> None:
    from mmpa.registration.fgr import feature_support as _feature_support

    rng = np.random.default_rng(3)
    ps, pt = rng.normal(size=(50, 3)), rng.normal(size=(60, 3))
    corr = np.stack([rng.integers(0, 50, 200), rng.integers(0, 60, 200)], axis=1)
    T = exp_se3(rng.normal(0, 0.3, 6))
    brute = sum(np.linalg.norm(T[:3, :3] @ ps[i] + T[:3, 3] - pt[j]) < 0.8 for i, j in corr)
    assert _feature_support(ps, pt, corr, 0.8)(T) == brute > 0
