"""Colored point cloud global registration (paper 000 §3.2.2 II): FPFH + FGR, then colored ICP.

Given a source cloud ``X_s`` and a target cloud ``X_t`` (both in their camera's optical frame,
metres), estimate ``T = T_target_source`` such that ``p_t = T p_s`` (paper eq. 3 with
``[dR_Ck, dt_Ck] = T`` when the taught cloud X_i(O) is the source and the current X_i(k) the
target). Stages, one module each, composed by :func:`register`:

1. Preprocessing and features (:mod:`~mmpa.registration.preprocess`): crop, voxel pyramid,
   outliers, normals and FPFH (Rusu 2009), computed once per cloud (:func:`prepare`).
2. Coarse: Fast Global Registration (Zhou et al. 2016; :mod:`~mmpa.registration.fgr`):
   mutual FPFH matches and the tuple test (:func:`fgr_correspondences`), then FGR's scaled
   Geman-McClure objective ``sum rho(||q - T p||)`` (:func:`~mmpa.registration.fgr.fgr_solve`).
   Skipped when the caller gives ``init``.
3. Fine: multi-scale colored ICP (Park et al. 2017; :mod:`~mmpa.registration.icp`),
   ``E(T) = (1 - lambda) sum r_C^2 + lambda sum r_G^2``, lambda = 0.968; point-to-plane ICP
   without color (paper Table A.7 Ex A.0/B.0, footnote 14). ``color_mode="auto"`` (default,
   beyond the paper) runs point-to-plane ICP first and colored ICP only when geometry alone
   is weak (information below ``geometric_min_information``) or rejected; ``"paper"``
   (:meth:`RegistrationConfig.paper`) always uses colored ICP when both clouds carry color.
4. Failure detection (:mod:`~mmpa.registration.checks`): the pose is returned with
   ``ok=False`` and a reason unless the clouds are large enough, the fine stage has enough
   inlier correspondences, fitness and RMSE pass, the fine pose stays near the coarse (or
   given) pose, the objective constrains all six degrees of freedom
   (:func:`information_matrix`) and, with color on both sides, the intensities correlate
   over the correspondences (:func:`color_correlation`).
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from mmpa.core.errors import InvalidInputError
from mmpa.core.geometry import Array
from mmpa.registration._blas import open3d_threads
from mmpa.registration.ambiguity import competitors
from mmpa.registration.checks import color_correlation, information_matrix, rmse_gate
from mmpa.registration.config import IcpScale, RegistrationConfig
from mmpa.registration.fgr import (
    feature_support,
    fgr_correspondences,
    fgr_solve,
    mutual_matches,
    tuple_test,
)
from mmpa.registration.icp import Fine, fine_stage
from mmpa.registration.preprocess import Prepared, as_prepared, feature_matrix, prepare

__all__ = [
    "Prepared",
    "Registration",
    "color_correlation",
    "fgr_correspondences",
    "information_matrix",
    "prepare",
    "register",
    "rmse_gate",
]


@dataclass(frozen=True)
class Registration:
    """Result of :func:`register`.

    ``T`` (4, 4) is ``T_target_source`` (``p_target = T p_source``, metres); ``fitness`` the
    inlier fraction of the source at the finest ICP scale; ``rmse`` the inlier RMSE (m) there;
    ``ok`` whether every acceptance check passed, else ``reason`` says which failed (``T`` is
    then the last estimate, for diagnostics only: never act on it); ``n_correspondences`` the
    inlier pairs of the finest scale; ``seconds`` the wall time of the call; ``stages`` the
    per-stage timings and diagnostics (``min_information``, ``coarse_shift``...).
    """

    T: Array
    fitness: float
    rmse: float
    ok: bool
    reason: str
    n_correspondences: int
    seconds: float
    stages: dict[str, Any] = field(default_factory=dict)


def register(
    source: Any,
    target: Any,
    cfg: RegistrationConfig | None = None,
    *,
    init: Array | None = None,
) -> Registration:
    """Estimate ``T_target_source`` (``p_target = T p_source``) between two colored clouds.

    ``source``/``target``: :class:`~mmpa.robot.interfaces.PointCloud` or :class:`Prepared`
    (prepared with the same ``cfg``). Without ``init`` the coarse pose comes from FPFH + FGR;
    with ``init`` (4, 4) the global stage is skipped and the fine stage runs ``init_scales``
    from it. The result is always validated; failures return ``ok=False`` with a reason.
    """
    cfg = cfg or RegistrationConfig()
    with open3d_threads(cfg.open3d_threads):
        return _register(source, target, cfg, init)


def _checked_init(init: Array | None) -> Array | None:
    """``init`` as a (4, 4) float array, checked to be a finite proper rigid transform."""
    if init is not None:
        init = np.asarray(init, dtype=float)
        if init.shape != (4, 4) or not np.isfinite(init).all():
            raise InvalidInputError(f"init must be a finite 4x4 transform, got shape {init.shape}")
        R = init[:3, :3]
        if not np.allclose(R @ R.T, np.eye(3), atol=1e-6) or np.linalg.det(R) < 0:
            raise InvalidInputError("init rotation block is not a proper rotation")
    return init


def _result(
    T: Array,
    ok: bool,
    reason: str,
    stages: dict[str, Any],
    t0: float,
    fit: float = 0.0,
    rmse: float = np.inf,
    n: int = 0,
) -> Registration:
    return Registration(
        T=np.asarray(T, float),
        fitness=float(fit),
        rmse=float(rmse),
        ok=ok,
        reason=reason,
        n_correspondences=int(n),
        seconds=time.perf_counter() - t0,
        stages=stages,
    )


def _methods(cfg: RegistrationConfig, both: bool) -> tuple[bool, ...]:
    """The fine-stage methods to try in turn (True: colored ICP) for ``cfg.color_mode``,
    ``both`` whether both clouds carry color."""
    if cfg.color_mode == "geometric":
        return (False,)
    if cfg.color_mode in ("colored", "paper"):
        return (both,)
    # auto: geometry first, the photometric term only where geometry is weak
    return (False, True) if both else (False,)


def _coarse(
    src: Prepared, tgt: Prepared, cfg: RegistrationConfig, stages: dict[str, Any]
) -> tuple[Array, Callable[[Array], int], Array]:
    """The global stage: FPFH matches, FGR's pose, the matches' vote
    (:func:`~mmpa.registration.fgr.feature_support`) and the mutual matches."""
    t1 = time.perf_counter()
    fs, ft = src.fpfh(cfg), tgt.fpfh(cfg)
    stages["features_s"] = time.perf_counter() - t1
    t1 = time.perf_counter()
    matches = mutual_matches(feature_matrix(src, fs), feature_matrix(tgt, ft))
    corr = tuple_test(
        matches,
        np.asarray(src.coarse.points),
        np.asarray(tgt.coarse.points),
        cfg.fgr_max_tuples,
        cfg.fgr_tuple_scale,
        np.random.default_rng(cfg.seed),
    )
    stages["matching_s"] = time.perf_counter() - t1
    stages["fgr_correspondences"] = len(corr)
    t1 = time.perf_counter()
    T0 = fgr_solve(
        np.asarray(src.coarse.points),
        np.asarray(tgt.coarse.points),
        corr,
        cfg.fgr_distance_factor * cfg.coarse_voxel,
        cfg.fgr_iterations,
    )
    stages["coarse_s"] = time.perf_counter() - t1
    support = feature_support(
        np.asarray(src.coarse.points), np.asarray(tgt.coarse.points), corr, cfg.coarse_voxel
    )
    return T0, support, matches


def _refine(
    src: Prepared,
    tgt: Prepared,
    T0: Array,
    scales: tuple[IcpScale, ...],
    methods: tuple[bool, ...],
    cfg: RegistrationConfig,
    stages: dict[str, Any],
    limits: tuple[float, float, str],
    init: Array | None,
    support: Callable[[Array], int] | None,
) -> Fine:
    """The fine stage by each of ``methods`` in turn until one is accepted with enough
    information (the geometric pass kept when the colored one then fails)."""
    accepted: Fine | None = None
    fine = None
    for j, colored in enumerate(methods):
        stages["method"] = "colored_icp" if colored else "point_to_plane_icp"
        prefix = "colored_" if j else ""
        fine = fine_stage(src, tgt, T0, scales, colored, cfg, stages, prefix, limits, init, support)
        if fine.ok:
            accepted = fine
        if fine.ok and (colored or fine.information >= cfg.geometric_min_information):
            break
        if j + 1 < len(methods):
            stages["geometric_information"] = fine.information
            stages["geometric_reason"] = fine.reason or (
                f"geometric information {fine.information:.2e} < "
                f"{cfg.geometric_min_information:.1e}"
            )
    assert fine is not None
    if accepted is not None and not fine.ok:  # colored ICP failed where geometry passed
        fine = accepted
        stages["method"] = "point_to_plane_icp"
    return fine


def _register(
    source: Any, target: Any, cfg: RegistrationConfig, init: Array | None
) -> Registration:
    t0 = time.perf_counter()
    stages: dict[str, Any] = {}
    init = _checked_init(init)
    need_features = init is None
    src = as_prepared(source, cfg, need_features, "source")
    tgt = as_prepared(target, cfg, need_features, "target")
    stages["prepare_s"] = time.perf_counter() - t0
    for name, p in (("source", src), ("target", tgt)):
        if p.reason:
            return _result(np.eye(4), False, f"{name}: {p.reason}", stages, t0)
    both = src.colored and tgt.colored
    if cfg.color_mode == "colored" and not both:
        return _result(
            np.eye(4), False, "color_mode='colored' but a cloud has no color", stages, t0
        )
    methods = _methods(cfg, both)
    support: Callable[[Array], int] | None
    matches = None
    if init is None:
        T0, support, matches = _coarse(src, tgt, cfg, stages)
        scales = cfg.scales
        limits = (cfg.max_fine_shift, cfg.max_fine_rotation_deg, "coarse")
    else:
        T0 = init
        scales = cfg.init_scales
        limits = (cfg.max_init_shift, cfg.max_init_rotation_deg, "initial")
        support = None
    stages["T_coarse"] = T0
    t1 = time.perf_counter()
    for sc in scales:  # the fine stage needs the target's normals
        tgt.with_normals(sc.voxel, cfg)
    stages["normals_s"] = time.perf_counter() - t1
    fine = _refine(src, tgt, T0, scales, methods, cfg, stages, limits, init, support)
    stages["min_information"] = fine.information
    if fine.ok and (
        cfg.ambiguity_check == "always" or (cfg.ambiguity_check == "global" and init is None)
    ):
        fine = _unique(src, tgt, fine, methods, cfg, stages, matches, support)
    return _result(fine.T, fine.ok, fine.reason, stages, t0, fine.fitness, fine.rmse, fine.n)


def _unique(
    src: Prepared,
    tgt: Prepared,
    fine: Fine,
    methods: tuple[bool, ...],
    cfg: RegistrationConfig,
    stages: dict[str, Any],
    matches: Array | None,
    support: Callable[[Array], int] | None,
) -> Fine:
    """The competing-pose check (:mod:`~mmpa.registration.ambiguity`) of an accepted
    ``fine``: refused when degenerate at the coarse scale or when a distinct pose explains
    nearly as many points that ``fine`` does not as the other way round; replaced (once) by
    one that clearly explains more and passes every check itself."""
    for round_ in range(2):
        found = competitors(src, tgt, fine.T, cfg, matches, stages)
        lam = stages["coarse_information"]
        if lam < cfg.coarse_min_information:
            return fine._replace(
                ok=False,
                reason=f"degenerate geometry at the {cfg.scales[0].voxel * 1e2:.0f} cm scale: "
                f"the direction {stages['coarse_weak_direction']} is not constrained "
                f"(information {lam:.2e} < {cfg.coarse_min_information:.1e}; a corridor, a "
                "plane: the noise of the finer normals hid it)",
            )
        stages["ambiguity_competitors"] = [
            (c.start, round(c.distance * 1e3, 2), c.only_this, c.only_accepted) for c in found
        ]
        rivals = [
            c
            for c in found
            if c.distance > cfg.ambiguity_distance
            and c.color >= cfg.min_color_correlation
            and c.only_this >= cfg.ambiguity_rival_ratio * c.only_accepted
        ]
        better = [c for c in rivals if c.only_accepted < cfg.ambiguity_replace_ratio * c.only_this]
        best = max(rivals, key=lambda c: c.only_this - c.only_accepted, default=None)
        if best is None:
            stages["ambiguity_rounds"] = round_ + 1
            return fine
        what = (
            f"the competing pose {best.start} ({best.distance * 1e3:.1f} mm RMS away) "
            f"explains {best.only_this} points the pose does not, the pose "
            f"{best.only_accepted} it does not"
        )
        if len(better) < len(rivals) or round_ == 1:
            return fine._replace(
                ok=False,
                reason=f"ambiguous pose: {what} (a repeated structure, or the scene slides "
                "along a direction it hardly constrains)",
            )
        # a clearly better pose: it must pass every check itself, then face its own rivals
        limits = (cfg.max_fine_shift, cfg.max_fine_rotation_deg, "competing")
        stages["ambiguity_replaced"] = what
        fine = _refine(
            src, tgt, best.T, cfg.init_scales, methods, cfg, stages, limits, None, support
        )
        if not fine.ok:
            return fine
    return fine
