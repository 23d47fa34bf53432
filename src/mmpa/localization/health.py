"""Localization health: does the estimate still explain what the sensors see?

Pure functions over numpy arrays (no localizer state) and the :class:`Health` record every
method's :class:`~mmpa.localization.amcl.PoseEstimate` carries
(:class:`~mmpa.localization.monitor.MonitoredLocalizer` computes it):

- :func:`explained_share`: the share of valid beams whose endpoint, projected from the
  estimate, lies within ``d_max(r) = explain_dist + r sin(explain_angle)`` of an occupied
  cell (the map's distance field; off the map counts as unexplained). The range term lets a
  heading error of ``explain_angle`` pass on long beams. At the right pose this is the
  share of the scan the map holds (0.8-1 in a mapped building, less behind people and
  furniture that moved); a scan with ranges in the wrong unit, mirrored angles, or a map of
  another building explains a small share wherever the filter goes;
- :func:`position_spread`: ``sqrt`` of the largest eigenvalue of the estimate's position
  covariance (m), the particle cloud's spread;
- :func:`odometry_plausible`: an odometry increment between two updates the base cannot have
  made in the elapsed time (``|dxy| > max_speed dt + slack_xy``, ``|dtheta| > max_turn_rate
  dt + slack_theta``; without a usable ``dt``: ``|dxy| > max_step``);
- :func:`scan_defects`: NaN or negative intensities (which silently hide the reflectors
  from the detector), negative ranges, a majority of NaN ranges;
- :func:`odometry_correction` / :func:`correction_plausible`: how far one update moved the
  estimate against the odometry (the estimate vs the last updated estimate carried by the
  odometry since), and whether that correction is one odometry error and a normal filter
  correction explain (a scan matcher that jumps 0.5 m while the wheels say 1 cm is not).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from pydantic import BaseModel, ConfigDict, Field

from mmpa.core.geometry import Array, se2_compose, se2_inv

__all__ = [
    "Health",
    "HealthConfig",
    "correction_plausible",
    "crossed_share",
    "explained_near",
    "explained_share",
    "odometry_correction",
    "odometry_plausible",
    "position_spread",
    "scan_defects",
]


class HealthConfig(BaseModel):
    """Thresholds of the health figure (units: m, rad, s). Defaults: see the measurements in
    ``benchmarks/audit_lost.py`` and ``tests/test_localization_health.py``."""

    model_config = ConfigDict(extra="forbid")

    #: m, an endpoint this close to an occupied cell center is explained (plus the range term)
    explain_dist: float = Field(0.15, gt=0)
    #: rad, heading tolerance: ``d_max`` grows by ``r sin(explain_angle)`` with the range
    explain_angle: float = Field(np.deg2rad(1.0), ge=0)
    #: updates in the window the decision looks at (median of the explained shares)
    window: int = Field(5, ge=1)
    #: the window median of the explained share below which the localizer says "lost".
    #: Measured at err < 0.2 m (AMCL, benchmarks/audit_lost.py): twin drives >= 0.97; real
    #: CARMEN logs min (1st percentile) intel 0.88 (0.95), csail 0.69 (0.72), freiburg 0.64
    #: (0.93); faults: scale2/reversed/mirrored maps 0.2-0.45, another building 0.3-0.77
    lost_below: float = Field(0.5, ge=0, le=1)
    #: ... and above which a lost localizer is trusted again (hysteresis; recovering also
    #: needs the crossed window <= ``crossed_above``: real logs at err < 0.2 m reach 0.39)
    recover_above: float = Field(0.6, ge=0, le=1)
    #: fewer valid beams than this: no judgement of the explained share this update
    min_beams: int = Field(10, ge=1)
    #: m, particle filters: position spread above this says "lost"
    spread_max: float = Field(1.5, gt=0)
    #: m/s and rad/s, the fastest the base can move; m and rad of slack for timing jitter
    max_speed: float = Field(2.0, gt=0)
    max_turn_rate: float = Field(4.0, gt=0)
    slack_xy: float = Field(0.5, ge=0)
    slack_theta: float = Field(0.8, ge=0)
    #: m, the largest odometry step between updates when the scans carry no usable stamps
    max_step: float = Field(5.0, gt=0)
    #: updates an odometry refusal keeps the estimate flagged
    odom_hold: int = Field(3, ge=1)
    #: a scan with more than this share of NaN ranges is inconsistent input
    max_nan_share: float = Field(0.5, ge=0, le=1)
    #: m, distance field cap (beyond, all the same: unexplained)
    max_dist: float = Field(2.0, gt=0)
    #: m and rad, the explained share is the best over poses this far from the estimate
    search_xy: float = Field(0.2, ge=0)
    search_theta: float = Field(np.deg2rad(5.0), ge=0)
    #: beams judged per scan (evenly subsampled)
    max_beams: int = Field(180, ge=10)
    #: alternative readings of the scan tried when its own share is below ``alt_below``:
    #: mirrored angles, ranges times these factors (a wrong unit)
    alt_scales: tuple[float, ...] = (0.5, 2.0, 0.1, 10.0, 0.01, 100.0, 0.001, 1000.0)
    alt_below: float = Field(0.8, ge=0, le=1)
    #: m and rad, a beam crossing a wall this far before its endpoint saw through it
    cross_margin: float = Field(0.3, ge=0)
    cross_angle: float = Field(np.deg2rad(1.0), ge=0)
    #: the window median of the crossed share above which the localizer says "lost".
    #: Measured at err < 0.2 m: twin <= 0.06; real logs max intel 0.33, csail 0.36,
    #: freiburg 0.39 (margin 0.06); AMCL diverged on freiburg (err > 1 m): 0.5-0.7
    crossed_above: float = Field(0.45, ge=0, le=1)
    #: an alternative reading explaining this much more (window medians) says the input is
    #: inconsistent
    alt_margin: float = Field(0.3, ge=0, le=1)
    #: m, reflector methods: the window median distance between the reflector fix and the
    #: estimate above which the map's walls and its reflector survey disagree. Measured:
    #: consistent maps < 0.1 (the fix is fused); walls shifted 1-3 m or another building:
    #: 1-1.5 (EnhancedAMCL's laser term pulls the estimate onto the wrong walls)
    fix_disagree: float = Field(0.5, gt=0)
    #: one update may move the estimate against the odometry by at most ``jump_xy +
    #: jump_per_m * travelled`` m and ``jump_theta + jump_per_rad * turned`` rad (travelled,
    #: turned: the odometry's path length and summed turn since the last updated estimate).
    #: Measured at err < 0.2 m (benchmarks/audit_lost.py, ``correction_ratio``: the share of
    #: that limit a correction used): twin drives <= 0.57, csail 0.67, intel 0.62, freiburg
    #: 0.70; the faults no other figure sees (reversed angles: Hector 0.43-0.58 m / 20-32 deg,
    #: EnhancedAMCL 0.39 m / 18 deg, a mirrored reflector identification 1.2-1.6 m /
    #: 104-161 deg) 1.26 and up
    jump_xy: float = Field(0.3, gt=0)
    jump_per_m: float = Field(0.2, ge=0)
    jump_theta: float = Field(np.deg2rad(15.0), gt=0)
    jump_per_rad: float = Field(0.2, ge=0)


@dataclass(frozen=True)
class Health:
    """The health figure of one estimate.

    ``explained`` share (0-1) of the valid beams the map explains at the estimate (NaN: too
    few valid beams to judge); ``window`` the median of ``explained`` over the last
    ``HealthConfig.window`` updates; ``crossed`` the share of beams that saw through a
    wall of the map at the best pose near the estimate, ``crossed_window`` its window
    median; ``alternative`` the reading of the scan that explains
    the map best when that beats the scan as given ("mirrored", "ranges x 0.5", ... or ''),
    ``alternative_gain`` its window median gain in explained share; ``fix_offset`` m the
    distance from this update's reflector fix to the estimate (NaN: no fix), ``fix_window``
    its median over the last fixes; ``correction_xy`` m and ``correction_theta`` rad (absolute)
    how far this update moved the estimate against the odometry
    (:func:`odometry_correction`; NaN: no filter update, or the first one),
    ``correction_ratio`` the share of the allowed correction it used (above 1: "jumped",
    :func:`correction_plausible`); ``beams`` the valid
    beams judged; ``spread_xy`` m the position spread (NaN where the method has no
    particles); ``odom_ok`` False when this update's odometry increment was implausible
    (and refused); ``scan_ok`` False when the scan's fields are inconsistent (NaN/negative
    intensities, ...); ``lost`` the decision after the window and hysteresis."""

    explained: float = float("nan")
    window: float = float("nan")
    crossed: float = float("nan")
    crossed_window: float = float("nan")
    alternative: str = ""
    alternative_gain: float = 0.0
    fix_offset: float = float("nan")
    fix_window: float = float("nan")
    correction_xy: float = float("nan")
    correction_theta: float = float("nan")
    correction_ratio: float = float("nan")
    beams: int = 0
    spread_xy: float = float("nan")
    odom_ok: bool = True
    scan_ok: bool = True
    lost: bool = False


def _laser_in_map(pose: Array, laser_pose: Array | None) -> Array:
    """The lidar's pose ``[x, y, theta]`` in ``map``: base pose(s) ``pose`` (3,) or (N, 3)
    composed with the mount ``laser_pose`` (``base_link``; None: at the base origin)."""
    return se2_compose(pose, np.zeros(3) if laser_pose is None else laser_pose)


def explained_share(
    dist: Array,
    resolution: float,
    origin: tuple[float, float],
    pose: Array,
    ranges: Array,
    angles: Array,
    laser_pose: Array | None = None,
    explain_dist: float = 0.15,
    explain_angle: float = 0.0,
) -> tuple[float, int]:
    """Share of the beams ``(ranges, angles)`` (laser frame, all assumed valid and finite)
    explained at base pose ``pose`` ``[x, y, theta]``, and their count.

    ``dist`` (H, W) m distance from each cell center to the nearest occupied cell center
    (:meth:`~mmpa.maps.occupancy.OccupancyGrid.distance_field`), row 0 at ``origin`` ``(x,
    y)``, ``resolution`` m/cell. Beam ``b`` ends at ``p_b = o + r_b [cos(theta + theta_l +
    a_b), sin(...)]`` (``o`` the laser origin, ``theta_l`` the mount yaw) and is explained
    if it falls in a cell with ``dist <= explain_dist + r_b sin(explain_angle)``; outside the
    map it is not. No beams: ``(nan, 0)``."""
    share, _ = explained_near(
        dist, resolution, origin, pose, ranges, angles, laser_pose, explain_dist, explain_angle
    )
    return share, int(np.size(ranges))


def explained_near(
    dist: Array,
    resolution: float,
    origin: tuple[float, float],
    pose: Array,
    ranges: Array,
    angles: Array,
    laser_pose: Array | None = None,
    explain_dist: float = 0.15,
    explain_angle: float = 0.0,
    search_xy: float = 0.0,
    search_theta: float = 0.0,
    steps: int = 2,
) -> tuple[float, Array]:
    """The best :func:`explained_share` over the poses ``pose + (i, j) search_xy / steps``
    and ``theta + k search_theta / steps`` for ``i, j, k`` in ``-steps..steps`` (a grid of
    ``(2 steps + 1)^3`` poses; 0 search: the estimate alone), and the pose that gives it.
    "Is there a pose near the estimate that explains the scan?": an estimate a little off
    (0.2 m, a few degrees) is not judged lost, a scan the map cannot explain anywhere near
    still is. Ties: the pose nearest the estimate."""
    r = np.asarray(ranges, float)
    a = np.asarray(angles, float)
    pose = np.asarray(pose, float)
    if r.size == 0:
        return float("nan"), pose.copy()
    if search_xy == 0 and search_theta == 0:
        steps = 0  # the estimate alone, not (2 steps + 1)^3 copies of it
    k = np.arange(-steps, steps + 1) / max(steps, 1)
    gx, gy, gt = np.meshgrid(k * search_xy, k * search_xy, k * search_theta, indexing="ij")
    offs = np.column_stack([gx.ravel(), gy.ravel(), gt.ravel()])
    offs = offs[np.argsort(np.hypot(offs[:, 0], offs[:, 1]) + np.abs(offs[:, 2]), kind="stable")]
    P = pose[None, :] + offs
    Lp = _laser_in_map(P, laser_pose)  # (N, 3)
    th = a[None, :] + Lp[:, 2:3]
    col = np.floor((Lp[:, 0:1] + r * np.cos(th) - origin[0]) / resolution)
    row = np.floor((Lp[:, 1:2] + r * np.sin(th) - origin[1]) / resolution)
    h, w = dist.shape
    inside = (col >= 0) & (col < w) & (row >= 0) & (row < h)
    d = np.full(col.shape, np.inf)
    d[inside] = dist[row[inside].astype(np.intp), col[inside].astype(np.intp)]
    share = np.mean(d <= explain_dist + r[None, :] * np.sin(explain_angle), axis=1)
    best = int(np.argmax(share))
    return float(share[best]), P[best].copy()


def crossed_share(
    occupied: Array,
    resolution: float,
    origin: tuple[float, float],
    pose: Array,
    ranges: Array,
    angles: Array,
    laser_pose: Array | None = None,
    margin: float = 0.3,
    margin_angle: float = 0.0,
) -> float:
    """Share of the beams whose ray passes through an occupied cell of ``occupied`` (H, W)
    bool more than ``margin + r sin(margin_angle)`` m before its endpoint: the scan saw
    through what the map calls a wall. At the right pose a beam stops at the first wall
    (only an opened door or a moved object lets one through); ranges in the wrong unit,
    mirrored angles, another building's map or an estimate metres off send many beams
    through walls. Samples every ``resolution / 2`` along each ray (a wall one cell thick is
    not jumped over); off the map counts as free. No beams: NaN."""
    r = np.asarray(ranges, float)
    a = np.asarray(angles, float)
    if r.size == 0:
        return float("nan")
    ox, oy, th0 = _laser_in_map(np.asarray(pose, float), laser_pose)
    th = a + th0
    stop = np.maximum(r - margin - r * np.sin(margin_angle), 0.0)
    step = resolution / 2
    n = np.ceil(stop / step).astype(np.int64)
    ray = np.repeat(np.arange(r.size), n)
    t = (np.arange(n.sum()) - np.repeat(np.cumsum(n) - n, n)) * step
    col = np.floor((ox + t * np.cos(th[ray]) - origin[0]) / resolution).astype(np.int64)
    row = np.floor((oy + t * np.sin(th[ray]) - origin[1]) / resolution).astype(np.int64)
    h, w = occupied.shape
    inside = (col >= 0) & (col < w) & (row >= 0) & (row < h)
    hit = np.zeros(ray.shape, dtype=bool)
    hit[inside] = occupied[row[inside], col[inside]]
    crossed = np.zeros(r.size, dtype=bool)
    crossed[ray[hit]] = True
    return float(np.mean(crossed))


def position_spread(cov: Array) -> float:
    """``sqrt(lambda_max)`` (m) of the (2, 2) position block of a (3, 3) covariance; NaN if
    it is not finite."""
    c = np.asarray(cov, float)[:2, :2]
    if not np.all(np.isfinite(c)):
        return float("nan")
    return float(np.sqrt(max(float(np.linalg.eigvalsh(0.5 * (c + c.T)).max()), 0.0)))


def odometry_plausible(delta: Array, dt: float | None, cfg: HealthConfig) -> tuple[bool, str]:
    """Whether the odometry increment ``delta`` ``[dx, dy, dtheta]`` (m, rad; ``dtheta``
    wrapped to ``[-pi, pi)``) over ``dt`` s (None or <= 0: unknown) is one the base can make;
    if not, a sentence saying why."""
    step = float(np.hypot(delta[0], delta[1]))
    turn = abs(float(delta[2]))
    if dt is not None and np.isfinite(dt) and dt > 0:
        lim = cfg.max_speed * dt + cfg.slack_xy
        if step > lim:
            return False, (
                f"odometry jumped {step:.2f} m in {dt:.2f} s (at most {lim:.2f} m: "
                f"{cfg.max_speed} m/s)"
            )
        lim_a = cfg.max_turn_rate * dt + cfg.slack_theta
        if turn > lim_a:
            return False, (
                f"odometry turned {np.rad2deg(turn):.0f} deg in {dt:.2f} s (at most "
                f"{np.rad2deg(lim_a):.0f} deg: {cfg.max_turn_rate} rad/s)"
            )
        return True, ""
    if step > cfg.max_step:
        return False, f"odometry jumped {step:.2f} m between updates (max_step {cfg.max_step} m)"
    return True, ""


def odometry_correction(
    anchor_pose: Array, anchor_odom: Array, pose: Array, odom_pose: Array
) -> Array:
    """The correction ``[dx, dy, dtheta]`` (frame of the prediction; ``dtheta`` wrapped)
    that takes the prediction ``anchor_pose * anchor_odom^-1 * odom_pose`` (the estimate
    ``anchor_pose`` made at odometry pose ``anchor_odom``, carried by the odometry since) to
    the estimate ``pose`` at odometry pose ``odom_pose``. Zero where the estimate moved as
    the odometry did."""
    pred = se2_compose(anchor_pose, se2_compose(se2_inv(anchor_odom), odom_pose))
    return se2_compose(se2_inv(pred), pose)


def correction_plausible(
    corr: Array, travelled: float, turned: float, cfg: HealthConfig
) -> tuple[float, str]:
    """How much of the largest correction a filter makes after the odometry travelled
    ``travelled`` m and turned ``turned`` rad the correction ``corr``
    (:func:`odometry_correction`) uses: the larger of ``|corr_xy| / (jump_xy + jump_per_m
    travelled)`` and ``|corr_theta| / (jump_theta + jump_per_rad turned)``; above 1, a
    sentence saying it jumped ('' if not)."""
    dxy, dth = float(np.hypot(corr[0], corr[1])), abs(float(corr[2]))
    lim = cfg.jump_xy + cfg.jump_per_m * travelled
    lim_a = cfg.jump_theta + cfg.jump_per_rad * turned
    ratio = max(dxy / lim, dth / lim_a)
    if ratio <= 1:
        return ratio, ""
    return ratio, (
        f"the estimate jumped {dxy:.2f} m and {np.rad2deg(dth):.0f} deg against the odometry "
        f"in one update (odometry: {travelled:.2f} m, {np.rad2deg(turned):.0f} deg; at most "
        f"{lim:.2f} m and {np.rad2deg(lim_a):.0f} deg)"
    )


def scan_defects(ranges: Array, intensities: Array, max_nan_share: float = 0.5) -> str:
    """What is wrong with a scan's values ('' if nothing): NaN or negative intensities (the
    reflector detector then sees no reflector), negative finite ranges, more than
    ``max_nan_share`` of the ranges NaN (REP 117 allows some NaN: 'no measurement')."""
    r = np.asarray(ranges, float)
    i = np.asarray(intensities, float)
    out = []
    n_nan_i = int(np.count_nonzero(np.isnan(i)))
    n_neg_i = int(np.count_nonzero(i < 0))
    if n_nan_i:
        out.append(f"{n_nan_i} NaN intensities")
    if n_neg_i:
        out.append(f"{n_neg_i} negative intensities")
    if n_nan_i or n_neg_i:
        out[-1] += " (reflectors on those beams go undetected)"
    n_neg_r = int(np.count_nonzero(np.isfinite(r) & (r < 0)))
    if n_neg_r:
        out.append(f"{n_neg_r} negative ranges")
    n_nan_r = int(np.count_nonzero(np.isnan(r)))
    if r.size and n_nan_r > max_nan_share * r.size:
        out.append(f"{n_nan_r} of {r.size} ranges NaN")
    return "; ".join(out)
