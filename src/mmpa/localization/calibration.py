"""Lidar mount self-calibration from a turn on the spot (improvement, error model v2).

The localizer places ``base_link`` from the pose ``S`` of the scanner it estimates and the
mount ``m = [m_x, m_y, m_theta]`` (the scanner in ``base_link``): ``X = S (-) m``. A mount
translation error goes straight into the base position (3 mm per axis in the ``realistic``
profile); the mount's yaw only into the heading.

A differential-drive base turning on the spot turns about ``base_link`` (the wheel axle's
midpoint), so the scanner runs on a circle about a fixed center ``c``:
``p_k = c + R(theta_m) m_xy``, ``theta_m`` the base heading; with the scanner's own heading
``theta_k = theta_m + m_theta``: ``p_k = c + R(theta_k) v``, ``v = R(-m_theta) m_xy`` the mount
translation in the SCANNER's frame. Scanner poses ``(p_k, theta_k)`` measured at several
headings (scan matching against the map: :func:`match_scan`) give ``c`` and ``v`` by linear
least squares (:func:`fit_turn_mount`); errors that stay the same at every heading (the map's
offset at that place, the reflectors' survey) go into ``c``, not into ``v``.

``v`` is all the base POSITION needs: ``X_xy = S_xy - R(theta_X) m_xy = S_xy - R(theta_k) v``
for any ``m_theta``, so the calibrated mount is ``[R(m_theta) v, m_theta]`` with the nominal
``m_theta`` (:func:`calibrated_mount`). The yaw itself would need the direction of straight
travel and is left nominal.

Units: m, rad.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.optimize import minimize

from mmpa.core.errors import InvalidInputError
from mmpa.core.geometry import Array
from mmpa.localization.amcl import AMCL

__all__ = ["TurnMountFit", "calibrated_mount", "fit_turn_mount", "match_scan"]


@dataclass(frozen=True)
class TurnMountFit:
    """:func:`fit_turn_mount`'s answer: ``v`` (2,) mount translation in the scanner frame (m),
    ``center`` (2,) the turn's center in ``map`` (m), ``rms`` (m) the position residual,
    ``sd`` (2,) the standard deviation of ``v`` from the residuals (m), ``n`` poses used,
    ``turned`` (rad) the heading range they span."""

    v: Array
    center: Array
    rms: float
    sd: Array
    n: int
    turned: float


def fit_turn_mount(poses: Array) -> TurnMountFit:
    """Mount translation from scanner poses ``poses`` (K, 3) ``[x, y, theta]`` taken while the
    base turned on the spot: least squares on ``p_k = c + R(theta_k) v`` (2K equations, 4
    unknowns ``c``, ``v``); ``sd`` from ``rms^2 (A^T A)^-1``. Needs at least 3 poses spanning
    more than 0.5 rad (the circle's radius and phase are not defined otherwise); the
    precision grows with the span, best over a full turn."""
    P = np.asarray(poses, float).reshape(-1, 3)
    if len(P) < 3 or not np.all(np.isfinite(P)):
        raise InvalidInputError(f"need >= 3 finite scanner poses, got {len(P)}")
    u = np.unwrap(P[:, 2])
    turned = float(u.max() - u.min())
    if turned < 0.5:
        raise InvalidInputError(f"the poses span {turned:.2f} rad of heading; need > 0.5")
    c, s = np.cos(P[:, 2]), np.sin(P[:, 2])
    A = np.zeros((2 * len(P), 4))
    A[0::2, 0] = 1.0
    A[1::2, 1] = 1.0
    A[0::2, 2], A[0::2, 3] = c, -s
    A[1::2, 2], A[1::2, 3] = s, c
    b = P[:, :2].reshape(-1)
    sol, *_ = np.linalg.lstsq(A, b, rcond=None)
    res = b - A @ sol
    dof = max(len(b) - 4, 1)
    rms = float(np.sqrt(res @ res / dof))
    cov = rms**2 * np.linalg.inv(A.T @ A)
    sd = np.sqrt(np.diag(cov)[2:])
    return TurnMountFit(sol[2:].copy(), sol[:2].copy(), rms, sd, len(P), turned)


def calibrated_mount(fit: TurnMountFit, nominal: Array) -> Array:
    """The mount ``[x, y, theta]`` to give the localizer: translation ``R(theta) v`` with the
    ``nominal`` yaw ``theta`` (see the module docstring: the base position does not depend on
    the yaw)."""
    th = float(np.asarray(nominal, float).reshape(3)[2])
    c, s = np.cos(th), np.sin(th)
    v = fit.v
    return np.array([c * v[0] - s * v[1], s * v[0] + c * v[1], th])


def match_scan(
    matcher: AMCL,
    ranges: Array,
    angles: Array,
    initial: Array,
    sigma: float = 0.03,
    offset: float = 0.025,
    tol: float = 1e-5,
) -> Array:
    """Scanner pose ``[x, y, theta]`` in ``map`` that maximizes the product-form likelihood
    field of the beams ``ranges``, ``angles`` (:meth:`AMCL.log_likelihood_field`, signed
    distance to the surfaces ``offset`` m out from the occupied cells, per-beam SD ``sigma``
    m), by Nelder-Mead from ``initial`` (a simplex of 1 cm / 10 mrad; stops at ``tol`` m /
    rad). ``matcher``'s ``laser_pose`` must be zero: the pose found is the scanner's."""
    if np.any(np.asarray(matcher.laser_pose) != 0):
        raise InvalidInputError("match_scan needs a matcher whose laser_pose is [0, 0, 0]")
    x0 = np.asarray(initial, float).reshape(3)
    r, a = np.asarray(ranges, float), np.asarray(angles, float)

    def cost(p: Array) -> float:
        return -float(matcher.log_likelihood_field(p[None, :], r, a, sigma, offset, True)[0])

    simplex = x0 + np.array([[0, 0, 0], [0.01, 0, 0], [0, 0.01, 0], [0, 0, 0.01]])
    res = minimize(
        cost,
        x0,
        method="Nelder-Mead",
        options={"xatol": tol, "fatol": 1e-6, "initial_simplex": simplex, "maxiter": 2000},
    )
    return np.asarray(res.x, float)
