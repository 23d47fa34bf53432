"""Simulated wheel odometry: the TRUE planar motion cut into segments and perturbed by the
odometry motion model (Thrun's ``(rot1, trans, rot2)`` increments,
:func:`~mmpa.backends.twin.noise.odometry_increment_noise`). Units: m, rad, s.
"""

from __future__ import annotations

import math

import numpy as np

from mmpa.backends.twin.error_model import OdometryNoise
from mmpa.backends.twin.noise import angle_diff, odometry_increment_noise
from mmpa.core.geometry import Array
from mmpa.robot.description import BaseDescription
from mmpa.robot.interfaces import Odometry

__all__ = ["SimOdometry"]


def _relative(a: Array, b: Array) -> Array:
    """Planar pose ``b`` expressed in the frame of planar pose ``a`` (both ``[x, y, theta]``)."""
    c, s = math.cos(a[2]), math.sin(a[2])
    dx, dy = b[0] - a[0], b[1] - a[1]
    return np.array([c * dx + s * dy, -s * dx + c * dy, angle_diff(b[2], a[2])])


def _compose(a: Array, rel: Array) -> Array:
    """Planar pose ``a`` followed by ``rel`` (expressed in ``a``'s frame)."""
    c, s = math.cos(a[2]), math.sin(a[2])
    return np.array(
        [
            a[0] + c * rel[0] - s * rel[1],
            a[1] + s * rel[0] + c * rel[1],
            angle_diff(a[2] + rel[2], 0),
        ]
    )


class SimOdometry:
    """Wheel odometry: the TRUE planar motion, perturbed by the odometry motion model.

    The world calls :meth:`update` with the true base pose ``[x, y, theta]`` (``map``) and the
    time, as often as it likes. True motion is cut into segments of ``segment_length`` m or
    ``segment_angle`` rad (Nav2 AMCL's ``update_min_d`` / ``update_min_a`` defaults), and each
    finished segment's increment ``(rot1, trans, rot2)`` is perturbed with
    :func:`~mmpa.backends.twin.noise.odometry_increment_noise` and composed onto the odometry pose,
    so
    the error statistics are exactly those AMCL's motion model assumes at its update rate (the
    model's variance is quadratic in the increment, so it depends on where increments are cut).
    Inside a segment the pose follows the true motion exactly; the segment's noise is added
    when it closes. The twist is the true body velocity between the last two updates.

    The odometry frame starts at ``initial_pose`` where the first :meth:`update` finds the base.
    """

    _MIN_TRANS_FOR_HEADING = 0.01  # m; below it rot1's noise is computed as for rot1 = 0 (Nav2)

    def __init__(
        self,
        desc: BaseDescription,
        noise: OdometryNoise,
        rng: np.random.Generator,
        initial_pose: tuple[float, float, float] = (0.0, 0.0, 0.0),
        segment_length: float = 0.25,
        segment_angle: float = 0.2,
    ) -> None:
        self._desc, self._noise, self._rng = desc, noise, rng
        self._seg_len, self._seg_ang = float(segment_length), float(segment_angle)
        self._initial = np.array(initial_pose, dtype=float)
        self._pose = self._initial.copy()  # odometry pose at the start of the open segment
        self._seg_start: Array | None = None  # true pose at the start of the open segment
        self._last: Array | None = None
        self._last_stamp = 0.0
        self._twist = np.zeros(2)

    def reset(self, initial_pose: tuple[float, float, float] = (0.0, 0.0, 0.0)) -> None:
        """Restart: the next :meth:`update` defines the odometry origin anew."""
        self._initial = np.array(initial_pose, dtype=float)
        self._pose = self._initial.copy()
        self._seg_start = self._last = None
        self._twist = np.zeros(2)

    def update(self, true_pose: Array, stamp: float) -> None:
        """Feed the TRUE planar base pose ``[x, y, theta]`` at time ``stamp`` (s)."""
        p = np.asarray(true_pose, dtype=float).reshape(3)
        if self._last is None or self._seg_start is None:
            self._seg_start, self._last, self._last_stamp = p, p, float(stamp)
            return
        step = _relative(self._last, p)
        dt = float(stamp) - self._last_stamp
        if dt > 0:
            self._twist = np.array([step[0] / dt, step[2] / dt])
        self._last, self._last_stamp = p, float(stamp)

        rel = _relative(self._seg_start, p)
        trans = math.hypot(rel[0], rel[1])
        if trans < self._seg_len - 1e-9 and abs(rel[2]) < self._seg_ang - 1e-9:
            return
        # close the segment: exact increment (Thrun's rot1, trans, rot2) plus model noise
        rot1 = math.atan2(rel[1], rel[0]) if trans > 0 else 0.0
        rot2 = angle_diff(rel[2], rot1)
        r1_in = rot1 if trans >= self._MIN_TRANS_FOR_HEADING else 0.0
        r2_in = angle_diff(rel[2], r1_in)
        r1_hat, t_hat, r2_hat = odometry_increment_noise(
            r1_in, trans, r2_in, self._rng, self._noise
        )
        r1 = rot1 + angle_diff(r1_hat, r1_in)
        t = trans + (t_hat - trans)
        r2 = rot2 + angle_diff(r2_hat, r2_in)
        th = self._pose[2]
        self._pose = np.array(
            [
                self._pose[0] + t * math.cos(th + r1),
                self._pose[1] + t * math.sin(th + r1),
                angle_diff(th + r1 + r2, 0.0),
            ]
        )
        self._seg_start = p

    def odometry(self) -> Odometry:
        """The current odometry pose in ``odom`` and body twist ``[v, w]``."""
        pose = self._pose
        if self._seg_start is not None and self._last is not None:
            pose = _compose(self._pose, _relative(self._seg_start, self._last))
        v, w = float(self._twist[0]), float(self._twist[1])
        half = 0.5 * self._desc.track_width
        extra = {
            "wheel_left": (v - w * half) / self._desc.wheel_radius,  # rad/s
            "wheel_right": (v + w * half) / self._desc.wheel_radius,
        }
        return Odometry(
            pose=pose.copy(), twist=self._twist.copy(), stamp=self._last_stamp, extra=extra
        )
