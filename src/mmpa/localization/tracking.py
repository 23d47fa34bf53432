"""Tracking with fewer than three identified reflectors (improvements to paper 001
Algorithm 1, which falls back to plain AMCL there).

- :func:`associate`: detections -> landmarks through the current estimate (gate
  ``track_gate``);
- :func:`tracked_fix`: two or more associated reflectors give a pose by Gauss-Newton on their
  ranges and bearings (:func:`~mmpa.localization.trilateration.trilaterate`, or
  ``trilaterate_bias`` with the honest covariance), used as ``mu_G``;
- :func:`partial_proposal` and :func:`reflector_likelihood`: one reflector draws part of the
  particles on the poses its range and bearing allow and weights them by that range and
  bearing; none spreads them around the odometry prediction;
- :func:`landmark_update` and :func:`landmark_sd`: the surveyed landmark positions refined at
  redundant fixes (a Kalman filter per landmark, information form), used where one or two
  reflectors carry the pose.

Units: m, rad. Detections in ``base_link``; landmarks and poses ``[x, y, theta]`` in ``map``.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from mmpa.core.geometry import Array
from mmpa.localization.config import EnhancedConfig
from mmpa.localization.observer import ReflectorFix, ReflectorObserver
from mmpa.localization.pose import wrap
from mmpa.localization.trilateration import TrilaterationResult, trilaterate, trilaterate_bias

__all__ = [
    "associate",
    "landmark_sd",
    "landmark_update",
    "partial_proposal",
    "reflector_likelihood",
    "tracked_fix",
]


def landmark_update(
    info: Array,
    vec: Array,
    pose: Array,
    landmarks: Array,
    ranges: Array,
    bearings: Array,
    sigma_range: Array,
    sigma_bearing: Array,
    pose_var: float,
    sigma_min: float,
) -> tuple[Array, Array]:
    """One information-form Kalman update of landmark offsets (improvement).

    The reflectors seen at ``ranges`` (n,) m and ``bearings`` (n,) rad from ``pose`` (3,)
    ``[x, y, theta]`` (a redundant fix, computed on the map's positions ``landmarks`` (n, 2))
    lie at ``o_i = pose (+) (r_i cos b_i, r_i sin b_i)`` in ``map``; the residual
    ``z_i = o_i - L_i`` observes the landmark's offset ``delta_i`` (true minus surveyed,
    relative to the fix's consensus frame) with covariance ``R_i = U diag(sigma_r^2,
    (r sigma_b)^2) U^T + pose_var I`` (``U`` the radial/tangential axes). ``info`` (n, 2, 2)
    and ``vec`` (n, 2) are each landmark's information matrix ``Lambda`` and vector ``eta``
    (offset ``delta = Lambda^-1 eta``); returns the updated pair. ``Lambda`` is capped at
    ``I / sigma_min^2`` (both scaled down together, i.e. older scans are forgotten) so that
    static per-pose errors of a parked robot do not become certain."""
    pose = np.asarray(pose, float)
    a = pose[2] + np.asarray(bearings, float)
    u = np.stack([np.cos(a), np.sin(a)], axis=1)  # (n, 2) radial, map frame
    t = np.stack([-u[:, 1], u[:, 0]], axis=1)
    r = np.asarray(ranges, float)
    z = pose[:2] + r[:, None] * u - np.asarray(landmarks, float)
    var_r = np.asarray(sigma_range, float) ** 2 + pose_var
    var_t = (r * np.asarray(sigma_bearing, float)) ** 2 + pose_var
    Rinv = (
        u[:, :, None] * u[:, None, :] / var_r[:, None, None]
        + t[:, :, None] * t[:, None, :] / var_t[:, None, None]
    )
    info = info + Rinv
    vec = vec + np.einsum("nij,nj->ni", Rinv, z)
    cap = 1.0 / sigma_min**2
    top = np.linalg.eigvalsh(info)[:, -1]
    f = np.where(top > cap, cap / top, 1.0)
    return info * f[:, None, None], vec * f[:, None]


def landmark_sd(
    info: Array, ids: np.ndarray, survey_sigma: float, refine: bool, min_reflectors: int
) -> Array:
    """(n,) m: how well the refined positions of the landmarks ``ids`` are known in ``map``
    (isotropic SD), from each landmark's information matrix ``info`` (L, 2, 2). Without
    ``refine`` the survey's ``survey_sigma``; with it the refined offset's SD (largest axis of
    its posterior) combined with the consensus's own error, ``survey_sigma / sqrt(
    min_reflectors)`` (the offsets are relative to the fixes' consensus frame, whose
    translation is the mean of the survey errors of the reflectors in it)."""
    s = survey_sigma
    ids = np.asarray(ids, int)
    if not refine:
        return np.full(len(ids), s)
    post = 1.0 / np.linalg.eigvalsh(info[ids])[:, 0]
    return np.sqrt(np.minimum(post, s**2) + s**2 / min_reflectors)


def associate(
    points: Array, landmarks: Array, pose: Array, gate: float
) -> tuple[np.ndarray, np.ndarray]:
    """Detections ``points`` (n, 2) (base_link) -> landmark ids by proximity to where ``pose``
    predicts the ``landmarks`` (L, 2); returns (detection indices, landmark ids) within
    ``gate`` m, one detection per landmark."""
    if len(points) == 0 or len(landmarks) == 0:
        return np.zeros(0, dtype=np.int64), np.zeros(0, dtype=np.int64)
    c, s_ = np.cos(pose[2]), np.sin(pose[2])
    pm = points @ np.array([[c, s_], [-s_, c]]) + pose[:2]
    d = np.linalg.norm(pm[:, None, :] - landmarks[None, :, :], axis=2)
    nn = d.argmin(axis=1)
    ok = d[np.arange(len(pm)), nn] <= gate
    di, li = np.flatnonzero(ok), nn[ok]
    _, first = np.unique(li, return_index=True)  # one detection per landmark
    return di[first], li[first]


def tracked_fix(
    pose: Array,
    di: np.ndarray,
    li: np.ndarray,
    observer: ReflectorObserver,
    landmarks: Array,
    sd_of: Callable[[np.ndarray], Array],
    e: EnhancedConfig,
) -> tuple[ReflectorFix | None, str]:
    """A fix from the detections ``di`` associated with the landmarks ``li`` (at least two)
    by Gauss-Newton from ``pose``, and the status ("ok" or why not: "pair_distance",
    "degenerate", "jump", "turn", "inconsistent"). ``landmarks`` the tracking positions,
    ``sd_of(ids)`` their SDs (the honest covariance, ``track_honest``)."""
    det = observer.last_detections
    c = observer.cfg
    LM = landmarks
    # rigid check (a two-point "triangle match"): detected and map distances must agree
    P, L = det.points[di], LM[li]
    i, j = np.triu_indices(len(di), 1)
    dd = np.abs(np.linalg.norm(P[i] - P[j], axis=1) - np.linalg.norm(L[i] - L[j], axis=1))
    if dd.max() > e.track_pair_tol:
        return None, "pair_distance"
    sr, sb = observer.sigmas(det.beams[di])
    try:
        if e.track_honest and c.honest_fix:
            # honest covariance: the landmarks' own uncertainty, the per-reflector range
            # walk and what is left of the common bias (the ranges are corrected by it)
            bsd = float(np.sqrt(1.0 / observer.bias_info)) if c.range_bias else 1e-6
            bt = trilaterate_bias(
                LM[li],
                det.ranges[di],
                det.bearings[di],
                np.sqrt(sr**2 + c.range_bias_scatter**2),
                sb,
                0.0,
                bsd,
                sd_of(li),
                initial=pose,
            )
            tri = TrilaterationResult(bt.pose, bt.pose_cov, bt.rms, bt.n)
        else:
            tri = trilaterate(LM[li], det.ranges[di], det.bearings[di], sr, sb, initial=pose)
    except (ValueError, np.linalg.LinAlgError):
        return None, "degenerate"
    if not np.all(np.isfinite(tri.pose)) or np.hypot(*(tri.pose[:2] - pose[:2])) > 0.3:
        return None, "jump"
    if abs(float(wrap(tri.pose[2] - pose[2]))) > e.track_max_turn:
        return None, "turn"
    # consistency: every reflector within outlier_sigmas of the refined pose
    d = LM[li] - tri.pose[:2]
    res_r = (np.linalg.norm(d, axis=1) - det.ranges[di]) / sr
    res_b = wrap(np.arctan2(d[:, 1], d[:, 0]) - tri.pose[2] - det.bearings[di]) / sb
    if max(np.abs(res_r).max(), np.abs(res_b).max()) > c.outlier_sigmas:
        return None, "inconsistent"
    return ReflectorFix(li, det.ranges[di], det.bearings[di], tri, len(det), det.beams[di]), "ok"


def partial_proposal(
    particles: Array,
    prior: Array,
    e: EnhancedConfig,
    rng: np.random.Generator,
    landmark: Array | None = None,
    r_obs: float = 0.0,
    b_obs: float = 0.0,
) -> None:
    """Redraw ``partial_proposal_fraction`` of the ``particles`` (in place), headings
    ``N(prior_theta, partial_heading_sigma)``: with one reflector (``landmark`` (2,), seen at
    ``r_obs``, ``b_obs``) on the circle of poses that see it there, without one around the
    ``prior`` position (``partial_position_sigma``)."""
    k = round(e.partial_proposal_fraction * len(particles))
    if k > 0:
        idx = rng.choice(len(particles), k, replace=False)
        th = prior[2] + e.partial_heading_sigma * rng.standard_normal(k)
        if landmark is not None:  # on the circle of poses that see the landmark at r, b
            r = r_obs + e.track_sigma_range * rng.standard_normal(k)
            b = b_obs + e.track_sigma_bearing * rng.standard_normal(k)
            particles[idx, 0] = landmark[0] - r * np.cos(th + b)
            particles[idx, 1] = landmark[1] - r * np.sin(th + b)
        else:
            particles[idx, :2] = prior[:2] + e.partial_position_sigma * (
                rng.standard_normal((k, 2))
            )
        particles[idx, 2] = wrap(th)


def reflector_likelihood(
    particles: Array,
    landmarks: Array,
    r_obs: Array,
    b_obs: Array,
    sigma_range: float,
    sigma_bearing: float,
) -> Array:
    """Range/bearing likelihood (N,) of the reflectors seen at ``r_obs``, ``b_obs`` (n,) for
    the ``landmarks`` (n, 2) from every particle; 1 without reflectors."""
    P, L = particles, landmarks
    dx = L[None, :, 0] - P[:, 0:1]
    dy = L[None, :, 1] - P[:, 1:2]
    rng_err = np.hypot(dx, dy) - r_obs[None, :]
    brg_err = wrap(np.arctan2(dy, dx) - P[:, 2:3] - b_obs[None, :])
    return np.exp(-0.5 * ((rng_err / sigma_range) ** 2 + (brg_err / sigma_bearing) ** 2)).prod(
        axis=1
    )
