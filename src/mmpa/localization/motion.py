"""The odometry motion model of AMCL (Thrun et al., *Probabilistic Robotics* Table 5.6, as
Nav2's ``DifferentialMotionModel``) and SE(2) odometry composition.

An odometry increment is ``(rot1, trans, rot2)``: turn, drive straight, turn. Units: m, rad;
odometry poses ``[x, y, theta]`` in ``odom``, particles ``[x, y, theta]`` in ``map``.
"""

from __future__ import annotations

import numpy as np

from mmpa.core.geometry import Array
from mmpa.localization.pose import wrap

__all__ = ["compose_odom", "moved_enough", "odometry_delta", "sample_motion"]


def odometry_delta(prev: Array, cur: Array) -> tuple[float, float, float]:
    """Odometry increment ``(rot1, trans, rot2)`` between two odometry poses (Table 5.6)."""
    dx, dy = cur[0] - prev[0], cur[1] - prev[1]
    trans = float(np.hypot(dx, dy))
    rot1 = 0.0 if trans < 0.01 else float(wrap(np.arctan2(dy, dx) - prev[2]))
    rot2 = float(wrap(cur[2] - prev[2] - rot1))
    return rot1, trans, rot2


def compose_odom(pose: Array, odom_ref: Array, odom_now: Array) -> Array:
    """``pose`` moved by the odometry increment from ``odom_ref`` to ``odom_now`` (SE(2))."""
    c, s = np.cos(odom_ref[2]), np.sin(odom_ref[2])
    dx, dy = odom_now[0] - odom_ref[0], odom_now[1] - odom_ref[1]
    lx, ly = c * dx + s * dy, -s * dx + c * dy
    c2, s2 = np.cos(pose[2]), np.sin(pose[2])
    th = float(wrap(pose[2] + odom_now[2] - odom_ref[2]))
    return np.array([pose[0] + c2 * lx - s2 * ly, pose[1] + s2 * lx + c2 * ly, th])


def moved_enough(last: Array, now: Array, min_d: float, min_a: float) -> bool:
    """Nav2's update thresholds: the odometry moved ``min_d`` m or turned ``min_a`` rad since
    ``last``."""
    _rot1, trans, _rot2 = odometry_delta(last, now)
    dth = abs(float(wrap(now[2] - last[2])))
    return trans >= min_d or dth >= min_a


def sample_motion(
    particles: Array,
    delta: tuple[float, float, float],
    alphas: tuple[float, float, float, float],
    rng: np.random.Generator,
) -> Array:
    """Nav2 ``DifferentialMotionModel::odometryUpdate`` for all particles (N, 3) at once:
    ``alpha1`` rot noise from rot, ``alpha2`` rot from trans, ``alpha3`` trans from trans,
    ``alpha4`` trans from rot; reverse driving counts the rotations modulo pi."""
    rot1, trans, rot2 = delta
    a1, a2, a3, a4 = alphas
    r1n = min(abs(float(wrap(rot1))), abs(float(wrap(rot1 - np.pi))))
    r2n = min(abs(float(wrap(rot2))), abs(float(wrap(rot2 - np.pi))))
    n = particles.shape[0]
    e = rng.standard_normal((3, n))
    r1 = rot1 - np.sqrt(a1 * r1n**2 + a2 * trans**2) * e[0]
    t = trans - np.sqrt(a3 * trans**2 + a4 * r1n**2 + a4 * r2n**2) * e[1]
    r2 = rot2 - np.sqrt(a1 * r2n**2 + a2 * trans**2) * e[2]
    out = particles.copy()
    out[:, 0] += t * np.cos(particles[:, 2] + r1)
    out[:, 1] += t * np.sin(particles[:, 2] + r1)
    out[:, 2] = wrap(particles[:, 2] + r1 + r2)
    return out
