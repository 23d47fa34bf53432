"""What every localizer returns and the checks at its boundary.

:class:`PoseEstimate` (pose ``[x, y, theta]`` in ``map``, m and rad, covariance (3, 3)), the
validators :func:`finite_pose`, :func:`finite_cov`, :func:`check_scan`, and :func:`wrap`
(angles to ``[-pi, pi)``).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from mmpa.core.errors import InvalidInputError
from mmpa.core.geometry import Array
from mmpa.localization.health import Health
from mmpa.robot.interfaces import LaserScan

__all__ = ["PoseEstimate", "check_scan", "finite_cov", "finite_pose", "wrap"]


@dataclass(frozen=True)
class PoseEstimate:
    """Filter output: ``pose`` ``[x, y, theta]`` (map), ``cov`` (3, 3), number of particles,
    and whether this call ran a filter update. ``ok`` False (with ``reason``) when the
    localizer knows this estimate failed (e.g. a scan match that fits nothing); ``health``
    the figures behind that judgement (:mod:`mmpa.localization.health`; default: not judged,
    as the bare filters return it)."""

    pose: Array
    cov: Array
    n_particles: int
    updated: bool
    source: str = "amcl"
    ok: bool = True
    reason: str = ""
    health: Health = field(default_factory=Health)


def wrap(a: Array | float) -> Array | float:
    """Angles (rad) wrapped to ``[-pi, pi)``."""
    return (np.asarray(a) + np.pi) % (2 * np.pi) - np.pi


def finite_pose(pose: Array, what: str) -> Array:
    """``pose`` as a (3,) float array ``[x, y, theta]``; raises :class:`InvalidInputError`
    naming ``what`` (e.g. "odometry pose") if it has another size or holds NaN/inf."""
    try:
        p = np.asarray(pose, float).reshape(-1)
    except (TypeError, ValueError):
        raise InvalidInputError(f"{what} must be 3 numbers [x, y, theta], got {pose!r}") from None
    if p.shape != (3,):
        raise InvalidInputError(f"{what} must be [x, y, theta], got shape {np.shape(pose)}")
    if not np.all(np.isfinite(p)):
        raise InvalidInputError(f"{what} must be finite, got {p}")
    return p


def check_scan(scan: object) -> LaserScan:
    """``scan`` if it is a :class:`~mmpa.robot.interfaces.LaserScan`, else
    :class:`InvalidInputError` (None or an array would fail deep inside a localizer)."""
    if not isinstance(scan, LaserScan):
        raise InvalidInputError(f"scan must be a LaserScan, got {type(scan).__name__}")
    return scan


def finite_cov(cov: Array, what: str) -> Array:
    """``cov`` as a (3, 3) symmetric positive semi-definite float array of ``[x, y, theta]``;
    raises :class:`InvalidInputError` naming ``what`` otherwise (NaN, wrong shape, negative)."""
    try:
        c = np.asarray(cov, float)
    except (TypeError, ValueError):
        raise InvalidInputError(f"{what} must be a 3 x 3 matrix of numbers, got {cov!r}") from None
    if c.shape != (3, 3):
        raise InvalidInputError(f"{what} must be 3 x 3 (x, y, theta), got shape {c.shape}")
    if not np.all(np.isfinite(c)):
        raise InvalidInputError(f"{what} must be finite, got {c.tolist()}")
    if not np.allclose(c, c.T, rtol=1e-9, atol=1e-12):
        raise InvalidInputError(f"{what} must be symmetric, got {c.tolist()}")
    low = float(np.linalg.eigvalsh(c).min())
    if low < -1e-12 * max(1.0, float(np.abs(c).max())):
        raise InvalidInputError(
            f"{what} must be positive semi-definite, its smallest eigenvalue is {low:.3g}"
        )
    return c
