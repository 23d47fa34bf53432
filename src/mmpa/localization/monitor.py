"""A localizer that knows when it is lost: :class:`MonitoredLocalizer` wraps any
:class:`~mmpa.localization.localizer.Localizer` and fills every estimate's
:class:`~mmpa.localization.health.Health`, ``ok`` and ``reason``.

Per :meth:`MonitoredLocalizer.update`:

1. the odometry increment since the last call is checked
   (:func:`~mmpa.localization.health.odometry_plausible`, ``dt`` from the scan stamps); an
   implausible one is REFUSED: the wrapped localizer sees odometry shifted so that this
   increment is zero motion (SE(2) correction ``F``: it gets ``F * odom``), and the estimate
   says ``ok=False``, "inconsistent input: odometry jumped ..." for ``odom_hold`` updates;
2. the scan's values are checked (:func:`~mmpa.localization.health.scan_defects`): NaN or
   negative intensities say "inconsistent input" at once (for the reflector methods also
   that the fix fell back to plain AMCL);
3. the wrapped localizer updates; the share of beams the map explains is computed at its
   pose (``pose_at``: the estimate carried by odometry) and appended to a window of the last
   ``window`` updates; with a full window, a median below ``lost_below`` says "lost" until
   the median rises above ``recover_above`` (hysteresis: one scan blocked by people does not
   raise the alarm, a wrong unit, mirrored angles or another building's map do within
   ``window / 2 + 1`` updates); a particle spread above ``spread_max`` says "lost" too;
4. on a map with >= 3 reflectors: a window median distance from the reflector fix to the
   estimate above ``fix_disagree`` says "inconsistent map" (the scan's walls and the map's
   reflector survey disagree: EnhancedAMCL's laser term can pull the estimate onto the
   walls of a wrong map where they explain the scan well, 1-1.5 m from the fix; Hector
   follows walls shifted 1 m). The fix is the wrapped localizer's (``inner.last_fix``)
   where it has one, else the monitor's own
   :class:`~mmpa.localization.enhanced.ReflectorObserver` (amcl, tamcl, hector);
5. an update that moved the estimate against the odometry by more than a filter's
   correction (:func:`~mmpa.localization.health.correction_plausible`; the estimate vs the
   last updated estimate carried by the odometry since) says "inconsistent" on that update.
   The flag is an event, cleared at the next update whose correction is plausible: a jump
   may as well be a filter correcting itself (on the real logs AMCL jumped 0.4-0.7 m back
   from 0.5-0.7 m off and was within 0.2 m one update later), and where the jump went wrong
   the estimate's other figures judge it from then on. At a jump the explained/crossed and
   fix windows restart (their values judged the pose before it); until full again, the
   median of what they hold may clear "lost", not raise it (csail: AMCL jumped 0.69 m back
   from 0.72 m off, and the old window kept it "lost" at 0.17 m).

Any ``ok=False``/``reason`` of the wrapped localizer (Hector's rejected matches) is kept.
Attributes the wrapper does not define are the wrapped localizer's (``loc.particles``,
``loc.observer``, ...).
"""

from __future__ import annotations

import dataclasses
from collections import deque
from typing import Any

import numpy as np

from mmpa.core.geometry import Array, se2_compose, se2_inv
from mmpa.localization.amcl import PoseEstimate, check_scan, finite_pose
from mmpa.localization.enhanced import ObserverConfig, ReflectorObserver
from mmpa.localization.health import (
    Health,
    HealthConfig,
    correction_plausible,
    crossed_share,
    explained_near,
    odometry_correction,
    odometry_plausible,
    position_spread,
    scan_defects,
)
from mmpa.maps.occupancy import OccupancyGrid
from mmpa.robot.interfaces import LaserScan

__all__ = ["MonitoredLocalizer"]


class MonitoredLocalizer:
    """``inner`` with a health figure on every estimate (see the module docstring).
    ``grid`` the map ``inner`` localizes in, ``laser_pose`` the lidar mount ``[x, y, yaw]``
    in ``base_link``."""

    def __init__(
        self,
        inner: Any,
        grid: OccupancyGrid,
        laser_pose: Array,
        cfg: HealthConfig | None = None,
    ) -> None:
        self.inner = inner
        self.health_cfg = cfg or HealthConfig()
        self.laser_pose = finite_pose(laser_pose, "laser pose")
        self._dist = grid.distance_field(self.health_cfg.max_dist)
        self._occ = grid.occupied
        self._res = float(grid.resolution)
        self._origin = (float(grid.origin[0]), float(grid.origin[1]))
        self._observer = None  # the reflector fix where the wrapped localizer has none
        if not hasattr(inner, "last_fix") and len(grid.reflectors) >= 3:
            cfg_o = ObserverConfig()
            if grid.reflector_radius > 0:
                det = cfg_o.detection.model_copy(update={"radius": grid.reflector_radius})
                cfg_o = cfg_o.model_copy(update={"detection": det})
            self._observer = ReflectorObserver(grid.reflectors, self.laser_pose, cfg_o)
        self._reset()

    def _reset(self) -> None:
        self._shares: deque[float] = deque(maxlen=self.health_cfg.window)
        self._alts: deque[tuple[str, float]] = deque(maxlen=self.health_cfg.window)
        self._crossed: deque[float] = deque(maxlen=self.health_cfg.window)
        self._fix_offsets: deque[float] = deque(maxlen=self.health_cfg.window)
        self._lost = False
        self._fix = np.zeros(3)  # SE(2) correction applied to the raw odometry
        self._raw_prev: Array | None = None
        self._stamp_prev: float | None = None
        self._odom_flag = 0
        self._odom_reason = ""
        self._anchor: tuple[Array, Array] | None = None  # last updated (estimate, odometry)
        self._fed_prev: Array | None = None  # the odometry the wrapped localizer last saw
        self._travelled = np.zeros(2)  # odometry path (m) and turn (rad) since the anchor
        self.refused_odometry = 0  # implausible odometry increments refused so far
        self.last_health = Health()

    def __getattr__(self, name: str) -> Any:
        if name == "inner":  # not yet set (copy, pickling): no recursion
            raise AttributeError(name)
        return getattr(self.inner, name)

    @property
    def name(self) -> str:
        return str(self.inner.name)

    def initialize(self, pose: Array, cov: Array | None = None) -> None:
        """The wrapped localizer's ``initialize``; the health window starts afresh."""
        self.inner.initialize(pose, cov)
        self._reset()

    def _odometry(self, raw: Array) -> Array:
        """``F * raw``: the odometry the wrapped localizer sees."""
        return se2_compose(self._fix, raw)

    def pose_at(self, odom_pose: Array) -> Array:
        return self.inner.pose_at(self._odometry(finite_pose(odom_pose, "odometry pose")))

    def estimate(self) -> PoseEstimate:
        """The wrapped localizer's estimate with the last health figure."""
        est = self.inner.estimate()
        return dataclasses.replace(est, health=self.last_health)

    def _check_odometry(self, raw: Array, stamp: float) -> None:
        """Refuse an implausible increment from the last call's odometry (see module)."""
        if self._raw_prev is not None:
            delta = se2_compose(se2_inv(self._raw_prev), raw)
            dt = None
            if self._stamp_prev is not None and stamp > 0 and self._stamp_prev > 0:
                dt = stamp - self._stamp_prev
            ok, why = odometry_plausible(delta, dt, self.health_cfg)
            if not ok:
                # F_new * raw = F_old * raw_prev: the increment becomes zero motion
                held = se2_compose(self._fix, self._raw_prev)
                self._fix = se2_compose(held, se2_inv(raw))
                self._odom_flag = self.health_cfg.odom_hold
                self._odom_reason = f"{why}; refused (taken as no motion)"
                self.refused_odometry += 1
        self._raw_prev = raw.copy()
        self._stamp_prev = float(stamp)

    def update(self, odom_pose: Array, scan: LaserScan, force: bool = False) -> PoseEstimate:
        """The wrapped localizer's update with the health figure, ``ok`` and ``reason``."""
        raw = finite_pose(odom_pose, "odometry pose")
        scan = check_scan(scan)
        self._check_odometry(raw, float(scan.stamp) if np.isfinite(scan.stamp) else 0.0)
        odom = self._odometry(raw)
        est = self.inner.update(odom, scan, force)
        pose = np.asarray(self.inner.pose_at(odom), float)
        corr, ratio, why = self._correction(est.updated, odom, pose)
        health, reasons = self._judge(est, pose, scan, ratio > 1)
        health = dataclasses.replace(
            health,
            correction_xy=float(np.hypot(*corr[:2])),
            correction_theta=float(abs(corr[2])),
            correction_ratio=ratio,
        )
        if why:
            reasons.append(f"inconsistent: {why}")
        if not est.ok and est.reason:
            reasons.append(est.reason)
        self.last_health = health
        return dataclasses.replace(
            est, ok=est.ok and not reasons, reason="; ".join(reasons), health=health
        )

    def _correction(self, updated: bool, odom: Array, pose: Array) -> tuple[Array, float, str]:
        """This update's correction against the odometry and the share of the allowed one
        it used (NaN where the wrapped localizer ran no update, or at its first), and the
        reason to say ``ok=False`` ('' if none); an updated estimate becomes the anchor the
        next correction is measured from."""
        if self._fed_prev is not None:
            step = se2_compose(se2_inv(self._fed_prev), odom)
            self._travelled += (np.hypot(step[0], step[1]), abs(step[2]))
        self._fed_prev = odom.copy()
        corr, ratio, why = np.full(3, np.nan), float("nan"), ""
        if not updated or not np.all(np.isfinite(pose)):
            return corr, ratio, why
        if self._anchor is not None:
            corr = odometry_correction(*self._anchor, pose, odom)
            ratio, why = correction_plausible(corr, *self._travelled, self.health_cfg)
        self._anchor = (pose.copy(), odom.copy())
        self._travelled[:] = 0.0
        return corr, ratio, why

    def _share(self, pose: Array, ranges: Array, angles: Array) -> tuple[float, Array]:
        c = self.health_cfg
        return explained_near(
            self._dist,
            self._res,
            self._origin,
            pose,
            ranges,
            angles,
            self.laser_pose,
            c.explain_dist,
            c.explain_angle,
            c.search_xy,
            c.search_theta,
        )

    def _explained(self, pose: Array, scan: LaserScan) -> tuple[float, float, int, str, float]:
        """This scan's explained share near ``pose``, its crossed share at the best pose
        there, its beam count, and the best alternative reading (mirrored angles, scaled
        ranges) with its share ('' and NaN if the scan's own share is at least
        ``alt_below``)."""
        c = self.health_cfg
        m = np.flatnonzero(scan.valid() & (scan.ranges > 0))
        if m.size > c.max_beams:
            m = m[np.linspace(0, m.size - 1, c.max_beams).astype(int)]
        if m.size < c.min_beams or not np.all(np.isfinite(pose)):
            return float("nan"), float("nan"), int(m.size), "", float("nan")
        r, a = scan.ranges[m], scan.angles[m]
        share, best_pose = self._share(pose, r, a)
        crossed = crossed_share(
            self._occ,
            self._res,
            self._origin,
            best_pose,
            r,
            a,
            self.laser_pose,
            c.cross_margin,
            c.cross_angle,
        )
        if share >= c.alt_below:
            return share, crossed, int(m.size), "", float("nan")
        alts = {"mirrored angles": (r, scan.angle_min + scan.angle_max - a)}
        for f in c.alt_scales:
            alts[f"ranges x {f:g}"] = (r * f, a)
        best, best_share = "", -1.0
        for name, (ra, aa) in alts.items():
            # beams shorter than 2 explain_dist are "explained" by any wall the robot stands
            # next to (ranges x 0.01 would collapse the scan onto the nearest wall)
            ok = np.isfinite(ra) & (ra > 2 * c.explain_dist) & (ra <= scan.range_max)
            sh = self._share(pose, ra[ok], aa[ok])[0] * ok.mean() if ok.any() else 0.0
            if sh > best_share:
                best, best_share = name, sh
        return share, crossed, int(m.size), best, best_share

    def _window(
        self, share: float, crossed: float, alt: str, alt_share: float, restart: bool = False
    ) -> tuple[float, float, str, float]:
        """Append to the window; its median explained and crossed shares, and the
        alternative reading with its median gain (0 for updates where none was tried or
        another one won). Updates the lost state (hysteresis). ``restart`` (the estimate
        jumped): the window starts afresh, its old shares judged the pose before the jump;
        until it is full again, the median of what it holds may clear "lost" (a filter that
        jumped back onto the right pose), not raise it."""
        c = self.health_cfg
        if restart:
            self._shares.clear()
            self._crossed.clear()
            self._alts.clear()
        if np.isfinite(share):
            self._shares.append(share)
            self._crossed.append(crossed)
            self._alts.append((alt, alt_share - share if alt else 0.0))
        window = float(np.median(self._shares)) if self._shares else float("nan")
        cross = float(np.median(self._crossed)) if self._crossed else float("nan")
        if len(self._shares) == c.window:
            bad = window < c.lost_below or cross > c.crossed_above
            good = window > c.recover_above and cross <= c.crossed_above
            if not self._lost and bad:
                self._lost = True
            elif self._lost and good:
                self._lost = False
        elif self._lost and self._shares:
            self._lost = not (window > c.recover_above and cross <= c.crossed_above)
        names = [n for n, _ in self._alts if n]
        if not names:
            return window, cross, "", 0.0
        top = max(set(names), key=names.count)
        gain = float(np.median([g if n == top else 0.0 for n, g in self._alts]))
        return window, cross, top, gain

    def _fix_check(
        self, pose: Array, scan: LaserScan, restart: bool = False
    ) -> tuple[float, float, str]:
        """The distance from this update's reflector fix (the wrapped localizer's, or the
        monitor's observer's) to the estimate ``pose``, its median over the last ``window``
        fixes (NaN before 3; ``restart``: the estimate jumped, the old distances are
        dropped), and the reason to say ``ok=False`` when that median exceeds
        ``fix_disagree`` ('' if not)."""
        if restart:
            self._fix_offsets.clear()
        if self._observer is not None:
            fix = self._observer.observe(scan)
        else:
            fix = getattr(self.inner, "last_fix", None)
        off = float("nan")
        if fix is not None and np.all(np.isfinite(pose)):
            off = float(np.hypot(*(np.asarray(fix.pose)[:2] - pose[:2])))
            self._fix_offsets.append(off)
        if len(self._fix_offsets) < min(3, self.health_cfg.window):
            return off, float("nan"), ""
        med = float(np.median(self._fix_offsets))
        if med <= self.health_cfg.fix_disagree:
            return off, med, ""
        n, lim = len(self._fix_offsets), self.health_cfg.fix_disagree
        why = (
            f"inconsistent map: the reflector fix lies {med:.2f} m from the estimate (median "
            f"of the last {n} fixes, at most {lim} m): the scan's walls and the map's "
            "reflector survey disagree"
        )
        return off, med, why

    def _judge(
        self, est: PoseEstimate, pose: Array, scan: LaserScan, jumped: bool = False
    ) -> tuple[Health, list[str]]:
        """The health at ``pose`` after this update and the reasons to say ``ok=False``
        (``jumped``: the update's correction was implausible; the windows restart)."""
        c = self.health_cfg
        reasons: list[str] = []
        odom_ok = self._odom_flag == 0
        if self._odom_flag > 0:
            reasons.append(f"inconsistent input: {self._odom_reason}")
            self._odom_flag -= 1
        defects = scan_defects(scan.ranges, scan.intensities, c.max_nan_share)
        if defects:
            msg = f"inconsistent input: scan has {defects}"
            if est.source == "amcl" and hasattr(self.inner, "observer"):
                msg += "; no reflector fix: fell back to plain AMCL"
            reasons.append(msg)
        share, crossed, n, alt, alt_share = self._explained(pose, scan)
        window, cross, alt, gain = self._window(share, crossed, alt, alt_share, jumped)
        full = len(self._shares) == c.window
        if full and gain > c.alt_margin and window < c.alt_below:
            reasons.append(
                f"inconsistent input: the scan fits the map far better with {alt} "
                f"({window + gain:.0%} vs {window:.0%} of beams explained; wrong angle "
                "metadata or range unit?)"
            )
        if self._lost:
            reasons.append(
                f"lost: {window:.0%} of beams explained by the map, {cross:.0%} seen through "
                f"its walls (medians of the last {len(self._shares)} updates; lost below "
                f"{c.lost_below:.0%} or above {c.crossed_above:.0%})"
            )
        fix_off, fix_win, why = self._fix_check(pose, scan, jumped)
        if why:
            reasons.append(why)
        spread = position_spread(est.cov) if est.n_particles > 0 else float("nan")
        if spread > c.spread_max:
            reasons.append(f"lost: particle spread {spread:.2f} m > {c.spread_max} m")
        health = Health(
            explained=share,
            window=window,
            crossed=crossed,
            crossed_window=cross,
            alternative=alt if gain > 0 else "",
            alternative_gain=gain,
            fix_offset=fix_off,
            fix_window=fix_win,
            beams=n,
            spread_xy=spread,
            odom_ok=odom_ok,
            scan_ok=not defects,
            lost=self._lost or spread > c.spread_max,
        )
        return health, reasons
