"""Reflector fixes: ``LaserReflectorIdentification`` of paper 001 Algorithm 1 and eq. 1-2.

:class:`ReflectorObserver` detects the reflectors in a scan
(:func:`~mmpa.localization.reflectors.detect_reflectors`), identifies them by triangle
matching (:func:`~mmpa.localization.reflectors.identify_reflectors`) and trilaterates the pose
``mu_G`` (eq. 1-2, :func:`~mmpa.localization.trilateration.trilaterate`), dropping the worst
reflector while one is off by more than ``outlier_sigmas``. With ``honest_fix``
(improvement) the fix is :func:`~mmpa.localization.trilateration.trilaterate_bias` in the
scanner's frame, with a range bias common to all reflectors as a fourth unknown
(:func:`update_bias` keeps its running estimate) and each landmark's survey error in the
weights, mapped to ``base_link`` by :func:`sensor_to_base`.

Units: m, rad. Detections and fixes in ``base_link`` (bearings from its x axis), landmarks and
``mu_G`` ``[x, y, theta]`` in ``map``; the lidar mount ``[x, y, yaw]`` in ``base_link``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from mmpa.core.geometry import Array
from mmpa.localization.config import ObserverConfig
from mmpa.localization.pose import wrap
from mmpa.localization.reflectors import (
    ReflectorDetections,
    TriangleLibrary,
    detect_reflectors,
    identify_reflectors,
)
from mmpa.localization.trilateration import (
    BiasedTrilateration,
    TrilaterationResult,
    trilaterate,
    trilaterate_bias,
)
from mmpa.robot.interfaces import LaserScan

__all__ = ["ReflectorFix", "ReflectorObserver", "sensor_to_base", "update_bias"]


@dataclass(frozen=True)
class ReflectorFix:
    """Identified reflectors (in ``base_link``) and the trilateration ``mu_G`` (eq. 1-2)."""

    ids: np.ndarray  # (n,) landmark ids
    ranges: Array  # (n,) m from base_link
    bearings: Array  # (n,) rad in base_link
    trilateration: TrilaterationResult
    detected: int  # reflectors detected (identified or not)
    beams: np.ndarray | None = None  # (n,) returns per identified reflector
    bias_fit: BiasedTrilateration | None = None  # the honest fix (scanner frame), if any

    @property
    def pose(self) -> Array:
        return self.trilateration.pose


def sensor_to_base(pose: Array, cov: Array, mount: Array) -> tuple[Array, Array]:
    """The ``base_link`` pose ``X`` (3,) and its covariance (3, 3) from the pose ``S`` (3,) of
    a sensor mounted at ``mount`` = ``[m_x, m_y, m_theta]`` in ``base_link`` (``S = X (+)
    mount``): ``X_theta = S_theta - m_theta``, ``X_xy = S_xy - R(X_theta) m_xy``; covariance
    ``J cov J^T`` with ``J = [[1, 0, -dR/dtheta m_xy], [0, 1, .], [0, 0, 1]]``. m, rad."""
    S = np.asarray(pose, float).reshape(3)
    mx, my, mt = np.asarray(mount, float).reshape(3)
    th = float(wrap(S[2] - mt))
    c, s_ = np.cos(th), np.sin(th)
    X = np.array([S[0] - (c * mx - s_ * my), S[1] - (s_ * mx + c * my), th])
    J = np.eye(3)
    J[0, 2] = s_ * mx + c * my
    J[1, 2] = -(c * mx - s_ * my)
    return X, J @ np.asarray(cov, float) @ J.T


def update_bias(
    mean: float,
    info: float,
    post_mean: float,
    info_meas: float,
    sigma_min: float,
    gate: float,
) -> tuple[float, float, bool]:
    """One step of the running common range bias estimate (improvement, ``range_bias``).

    The estimate ``N(mean, 1 / info)`` was the prior of a fix that returned the posterior mean
    ``post_mean`` and carried ``info_meas`` (1/m^2) on the bias by itself
    (:class:`~mmpa.localization.trilateration.BiasedTrilateration`). The fix's own estimate is
    ``b_meas = ((info + info_meas) post_mean - info mean) / info_meas``; if its innovation
    ``|b_meas - mean|`` exceeds ``gate sqrt(1 / info + 1 / info_meas)`` (a wrong
    identification, an occluded edge) nothing is learned. Otherwise the posterior becomes the
    estimate, its information capped at ``1 / sigma_min^2`` (the errors of one place, the
    survey and the per-reflector walk, repeat scan after scan: they must not make the bias
    certain). Returns ``(mean, info, learned)`` in m and 1/m^2."""
    if info_meas <= 0 or not np.isfinite(post_mean):
        return mean, info, False
    post_info = info + info_meas
    b_meas = (post_info * post_mean - info * mean) / info_meas
    if abs(b_meas - mean) > gate * np.sqrt(1.0 / info + 1.0 / info_meas):
        return mean, info, False
    return float(post_mean), float(min(post_info, 1.0 / sigma_min**2)), True


class ReflectorObserver:
    """``LaserReflectorIdentification`` of Algorithm 1 plus eq. 1-2 with outlier rejection;
    with ``cfg.honest_fix`` the fix is :func:`trilaterate_bias` (common range bias, survey
    error) in the scanner's frame, mapped to ``base_link`` by :func:`sensor_to_base`."""

    def __init__(
        self, landmarks: Array, laser_pose: Array, cfg: ObserverConfig | None = None
    ) -> None:
        self.cfg = cfg or ObserverConfig()
        self.landmarks = np.asarray(landmarks, float).reshape(-1, 2)
        self.library = TriangleLibrary(self.landmarks)
        self.laser_pose = np.asarray(laser_pose, float).reshape(3)
        self.last_detections: ReflectorDetections = ReflectorDetections.empty()
        self.last_occluded = 0  # detections of the last scan dropped as occluded
        self.last_status = "none"
        #: running estimate of the common range bias (m) and its information (1/m^2)
        self.bias = self.cfg.range_bias_prior if self.cfg.range_bias else 0.0
        self.bias_info = 1.0 / self.cfg.range_bias_sigma**2
        self.bias_updates = 0
        #: rad, lower bound of bearing SDs for the last scan's step (``scale_with_scan``)
        self.step_floor = 0.0

    def sigmas(self, beams: np.ndarray, redundant: bool = False) -> tuple[Array, Array]:
        """Range and bearing SD (m, rad) of reflector centers fitted from ``beams`` (n,) hits:
        ``sigma_r = floor_r + sigma_r_beam / sqrt(k)``, ``sigma_phi = floor_phi +
        sigma_phi_beam / sqrt(k)`` (the fit averages ``k`` beams), plus
        ``bearing_sigma_static`` for a ``redundant`` (3+ reflector) fix; with
        ``scale_with_scan`` the bearing SD is at least :attr:`step_floor` (the last scan's
        angular step, if coarser than ``bearing_reference_step``)."""
        c = self.cfg
        k = np.sqrt(np.maximum(np.asarray(beams, float), 1.0))
        static = c.bearing_sigma_static if redundant else 0.0
        sb = np.maximum(c.bearing_sigma_floor + static + c.bearing_sigma_beam / k, self.step_floor)
        return c.range_sigma_floor + c.range_sigma_beam / k, sb

    def observe(self, scan: LaserScan) -> ReflectorFix | None:
        """The fix of this scan, or None if fewer than ``min_reflectors`` are identified."""
        c = self.cfg
        if c.scale_with_scan and np.isfinite(scan.angle_increment):
            a, a0 = abs(float(scan.angle_increment)), c.bearing_reference_step
            self.step_floor = c.bearing_sigma_floor + float(np.sqrt(max(a * a - a0 * a0, 0) / 24))
        raw = detect_reflectors(scan, c.detection)  # sensor frame
        self.last_occluded = int(raw.cut.sum())
        if c.drop_occluded and self.last_occluded:
            raw = raw.select(~raw.cut)
        if c.range_bias and self.bias != 0.0:
            det = raw.range_corrected(self.bias).transformed(self.laser_pose)
        else:
            det = raw.transformed(self.laser_pose)
        self.last_detections = det
        if len(det) < c.min_reflectors:
            self.last_status = "too_few"
            return None
        ident = identify_reflectors(det.points, self.library, c.identify)
        self.last_status = ident.status
        keep = ident.ids >= 0
        while keep.sum() >= c.min_reflectors:
            k = np.flatnonzero(keep)
            L = self.landmarks[ident.ids[k]]
            sr, sb = self.sigmas(det.beams[k], redundant=True)
            bias_fit: BiasedTrilateration | None = None
            try:
                if c.honest_fix:
                    tri, bias_fit, used, res_r, res_b = self._honest_fix(raw.select(k), L, sr, sb)
                else:
                    used = det.select(k)
                    tri = trilaterate(
                        L, used.ranges, used.bearings, sr, sb, refine_heading=c.joint_refine
                    )
                    d = L - tri.pose[:2]
                    res_r = (np.linalg.norm(d, axis=1) - used.ranges) / sr
                    res_b = wrap(np.arctan2(d[:, 1], d[:, 0]) - tri.pose[2] - used.bearings) / sb
            except (ValueError, np.linalg.LinAlgError):
                self.last_status = "degenerate"
                return None
            worst = int(np.argmax(np.maximum(np.abs(res_r), np.abs(res_b))))
            if max(abs(res_r[worst]), abs(res_b[worst])) <= c.outlier_sigmas:
                if bias_fit is not None and c.range_bias and len(k) >= c.range_bias_min_reflectors:
                    self.bias, self.bias_info, learned = update_bias(
                        self.bias,
                        self.bias_info,
                        bias_fit.bias,
                        bias_fit.bias_info_meas,
                        c.range_bias_sigma_min,
                        c.range_bias_gate,
                    )
                    self.bias_updates += int(learned)
                return ReflectorFix(
                    ident.ids[k], used.ranges, used.bearings, tri, len(det), used.beams, bias_fit
                )
            keep[k[worst]] = False
        self.last_status = "too_few_consistent"
        return None

    def _honest_fix(
        self, raw: ReflectorDetections, L: Array, sr: Array, sb: Array
    ) -> tuple[TrilaterationResult, BiasedTrilateration, ReflectorDetections, Array, Array]:
        """:func:`trilaterate_bias` on the sensor-frame detections ``raw`` of the landmarks
        ``L`` (n, 2) under the running bias (``cfg.honest_fix``): range SD ``sqrt(sr^2 +
        range_bias_scatter^2)``, bearing SD ``sb``, landmark SD ``survey_sigma``. Returns the
        ``base_link`` fix (:func:`sensor_to_base`), the scanner-frame fit, the detections in
        ``base_link`` corrected by the fitted bias, and the range and bearing residuals at the
        solution normalized by their total SDs (n,)."""
        c = self.cfg
        b0, bs = (self.bias, float(np.sqrt(1.0 / self.bias_info))) if c.range_bias else (0.0, 1e-6)
        s_r = np.sqrt(sr**2 + c.range_bias_scatter**2)
        bt = trilaterate_bias(L, raw.ranges, raw.bearings, s_r, sb, b0, bs, c.survey_sigma)
        d = L - bt.pose[:2]
        rho = np.linalg.norm(d, axis=1)
        res_r = (rho + bt.bias - raw.ranges) / np.sqrt(s_r**2 + c.survey_sigma**2)
        s_b = np.sqrt(sb**2 + (c.survey_sigma / rho) ** 2)
        res_b = wrap(np.arctan2(d[:, 1], d[:, 0]) - bt.pose[2] - raw.bearings) / s_b
        X, cov = sensor_to_base(bt.pose, bt.pose_cov, self.laser_pose)
        tri = TrilaterationResult(X, cov, bt.rms, bt.n)
        used = raw.range_corrected(bt.bias).transformed(self.laser_pose)
        return tri, bt, used, res_r, res_b
