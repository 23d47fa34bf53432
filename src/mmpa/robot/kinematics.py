"""Arm kinematics over standard Denavit-Hartenberg parameters: FK, Jacobian, analytic UR IK.

Pure numpy/scipy; no simulator imports. Units: m, rad. Frames follow DESIGN.md: every
transform ``T_a_b`` is the pose of ``b`` in ``a``; all results are in the ``arm_base`` frame.

Model (see :class:`mmpa.robot.description.DHParameters`)::

    A_i(q_i) = Rz(q_i + theta_offset_i) Tz(d_i) Tx(a_i) Rx(alpha_i),   i = 1..6
    T_arm_base_flange(q) = A_1 A_2 A_3 A_4 A_5 A_6

The analytic inverse kinematics is the classic closed form for the Universal Robots family
(Hawkins, "Analytic Inverse Kinematics for the Universal Robots UR-5/UR-10 Arms", 2013):
``a_1 = a_4 = a_5 = a_6 = 0`` and ``alpha = [pi/2, 0, 0, pi/2, -pi/2, 0]``, any ``d`` and
``a_2, a_3`` (non-zero ``d_2, d_3`` are allowed; they add to ``d_4``). For that structure it
is exact. A perturbed (calibrated / "true") DH set breaks the structure slightly; then the
closed form gives seeds that :func:`ik_refine` polishes by damped least-squares Newton steps
on the full DH model.
"""

from __future__ import annotations

import itertools

import numpy as np
from numpy.typing import ArrayLike

from mmpa.core.errors import InvalidInputError, UnreachableError
from mmpa.core.geometry import Array, as_transform, inv, log_so3
from mmpa.robot.description import DHParameters

__all__ = [
    "fk",
    "ik",
    "ik_nearest",
    "ik_refine",
    "is_ur_structure",
    "jacobian",
    "link_steps",
    "link_transforms",
    "manipulability",
    "manipulability_q",
]

_TWO_PI = 2.0 * np.pi
_UR_ALPHA = np.array([np.pi / 2, 0.0, 0.0, np.pi / 2, -np.pi / 2, 0.0])
_SINGULAR_S5 = 1e-12  # |sin q5| below this: wrist singular, q6 is free
_DEDUP_TOL = 1e-9  # rad, two solutions closer than this (mod 2 pi) are the same
_EYE4, _EYE6 = np.eye(4), np.eye(6)


# --- input checks ---------------------------------------------------------------------------


def _as_q(q: ArrayLike, name: str = "q") -> Array:
    q = np.asarray(q, dtype=float)
    if q.ndim == 0 or q.shape[-1] != 6:
        raise InvalidInputError(f"{name} must have shape (6,) or (N, 6), got {q.shape}")
    if not np.all(np.isfinite(q)):
        raise InvalidInputError(f"{name} contains NaN or inf")
    return q


def _as_limits(q_min: ArrayLike, q_max: ArrayLike) -> tuple[Array, Array]:
    lo = np.asarray(q_min, dtype=float).reshape(-1)
    hi = np.asarray(q_max, dtype=float).reshape(-1)
    if lo.shape != (6,) or hi.shape != (6,):
        raise InvalidInputError(f"joint limits need 6 values each, got {lo.shape}, {hi.shape}")
    if np.any(np.isnan(lo)) or np.any(np.isnan(hi)) or np.any(lo > hi):
        raise InvalidInputError(f"joint limits must satisfy q_min <= q_max, got {lo}, {hi}")
    return lo, hi


def _tool(T_flange_point: ArrayLike | None) -> Array | None:
    return None if T_flange_point is None else as_transform(T_flange_point, "T_flange_point")


# --- forward kinematics ---------------------------------------------------------------------


def _dh_matrices(theta: Array, d: Array, a: Array, alpha: Array) -> Array:
    """``Rz(theta) Tz(d) Tx(a) Rx(alpha)`` per joint: theta ``(..., 6)`` -> ``(..., 6, 4, 4)``."""
    return _dh_cs(theta, d, a, np.cos(alpha), np.sin(alpha))


def _dh_cs(theta: Array, d: Array, a: Array, ca: Array, sa: Array) -> Array:
    """:func:`_dh_matrices` with ``cos alpha``, ``sin alpha`` given."""
    ct, st = np.cos(theta), np.sin(theta)
    A = np.zeros((*theta.shape, 4, 4))
    A[..., 0, 0] = ct
    A[..., 0, 1] = -st * ca
    A[..., 0, 2] = st * sa
    A[..., 0, 3] = a * ct
    A[..., 1, 0] = st
    A[..., 1, 1] = ct * ca
    A[..., 1, 2] = -ct * sa
    A[..., 1, 3] = a * st
    A[..., 2, 1] = sa
    A[..., 2, 2] = ca
    A[..., 2, 3] = d
    A[..., 3, 3] = 1.0
    return A


def _dh_one_inv(theta: float, d: float, a: float, alpha: float) -> Array:
    """Inverse of one DH link transform, ``(Rz(theta) Tz(d) Tx(a) Rx(alpha))^-1``."""
    ct, st, ca, sa = np.cos(theta), np.sin(theta), np.cos(alpha), np.sin(alpha)
    return np.array(
        [
            [ct, st, 0.0, -a],
            [-st * ca, ct * ca, sa, -d * sa],
            [st * sa, -ct * sa, ca, -d * ca],
            [0.0, 0.0, 0.0, 1.0],
        ]
    )


def link_steps(dh: DHParameters, q: ArrayLike) -> Array:
    """Each link's frame in its parent's: ``A_i(q_i) = T_(i-1)_i`` for ``i = 1..6``.

    ``q``: joint angles (rad), shape ``(6,)`` or batched ``(N, 6)``. Returns ``(6, 4, 4)``
    (or ``(N, 6, 4, 4)``); :func:`link_transforms` is their running product."""
    q = _as_q(q)
    a, d, alpha, off = dh.as_arrays()
    return _dh_matrices(q + off, d, a, alpha)


def link_transforms(dh: DHParameters, q: ArrayLike) -> Array:
    """Frames of all links: ``T_arm_base_i = A_1 ... A_i`` for ``i = 0..6``.

    ``q``: joint angles (rad), shape ``(6,)`` or batched ``(N, 6)``. Returns ``(7, 4, 4)``
    (or ``(N, 7, 4, 4)``); index 0 is the identity (``arm_base``), index 6 the ``flange``.
    Frame ``i`` carries joint ``i + 1``'s axis as its z axis (standard DH).
    """
    A = link_steps(dh, q)
    F = np.empty((*A.shape[:-3], 7, 4, 4))
    F[..., 0, :, :] = np.eye(4)
    for i in range(6):
        F[..., i + 1, :, :] = F[..., i, :, :] @ A[..., i, :, :]
    return F


def fk(dh: DHParameters, q: ArrayLike, T_flange_point: ArrayLike | None = None) -> Array:
    """Forward kinematics ``T_arm_base_flange(q) = A_1 ... A_6`` (m, rad).

    ``q``: ``(6,)`` -> ``(4, 4)``; batched ``(N, 6)`` -> ``(N, 4, 4)``. With
    ``T_flange_point`` (e.g. ``T_flange_tcp``) returns ``T_arm_base_point = T_arm_base_flange
    @ T_flange_point`` instead.
    """
    T = link_transforms(dh, q)[..., 6, :, :]
    tool = _tool(T_flange_point)
    return T if tool is None else T @ tool


# --- differential kinematics ----------------------------------------------------------------


def _jacobian_from_frames(F: Array, tool: Array | None) -> Array:
    T_e = F[..., 6, :, :] if tool is None else F[..., 6, :, :] @ tool
    p_e = T_e[..., :3, 3]
    z = F[..., :6, :3, 2]  # (..., 6, 3): axis of joint i+1 is z of frame i
    o = F[..., :6, :3, 3]
    r = p_e[..., None, :] - o  # z x r, written out (np.cross's own formula, a third its cost)
    Jv = np.stack(
        [
            z[..., 1] * r[..., 2] - z[..., 2] * r[..., 1],
            z[..., 2] * r[..., 0] - z[..., 0] * r[..., 2],
            z[..., 0] * r[..., 1] - z[..., 1] * r[..., 0],
        ],
        axis=-1,
    )
    return np.concatenate([Jv, z], axis=-1).swapaxes(-1, -2)


def jacobian(dh: DHParameters, q: ArrayLike, T_flange_point: ArrayLike | None = None) -> Array:
    """Geometric Jacobian in the ``arm_base`` frame, rows ``[v; w]``, shape ``(6, 6)``.

    ``[v; w] = J(q) qdot`` with ``v`` (m/s) the linear velocity of the point ``p`` (the flange
    origin, or the origin of ``T_flange_point`` such as the TCP) and ``w`` (rad/s) the angular
    velocity of the flange, both in ``arm_base``. Column ``i``: ``[z_{i-1} x (p - o_{i-1});
    z_{i-1}]`` with ``z_{i-1}, o_{i-1}`` the axis and origin of DH frame ``i-1``. Batched
    ``q (N, 6)`` gives ``(N, 6, 6)``.
    """
    return _jacobian_from_frames(link_transforms(dh, q), _tool(T_flange_point))


def manipulability(J: ArrayLike) -> Array | float:
    """Yoshikawa manipulability ``w = sqrt(det(J J^T))`` (paper 001 eq. 14).

    ``J``: ``(m, n)`` or batched ``(..., m, n)``. Computed as the product of the ``m`` singular
    values of ``J`` (equal to ``sqrt(det(J J^T))`` for ``m <= n``, and to ``|det J|`` when
    square), which stays accurate near singularities where ``det(J J^T)`` drowns in round-off;
    0 for ``m > n``. Mixed units (m and rad rows), as in the paper.
    """
    J = np.asarray(J, dtype=float)
    if J.ndim < 2:
        raise InvalidInputError(f"J must be a matrix (m, n) or a batch (..., m, n), got {J.shape}")
    m, n = J.shape[-2:]
    if m > n:
        w = np.zeros(J.shape[:-2])
    else:
        w = np.prod(np.linalg.svd(J, compute_uv=False), axis=-1)
    return float(w) if np.ndim(w) == 0 else w


def manipulability_q(
    dh: DHParameters, q: ArrayLike, T_flange_point: ArrayLike | None = None
) -> Array | float:
    """``manipulability(jacobian(dh, q, T_flange_point))``."""
    return manipulability(jacobian(dh, q, T_flange_point))


# --- inverse kinematics ---------------------------------------------------------------------


def is_ur_structure(dh: DHParameters, tol: float = 1e-12) -> bool:
    """True if the closed-form UR IK is exact for ``dh``.

    Requires ``a_1 = a_4 = a_5 = a_6 = 0`` and ``alpha = [pi/2, 0, 0, pi/2, -pi/2, 0]``
    (within ``tol``) and ``a_2 a_3 != 0``.
    """
    a, _, alpha, _ = dh.as_arrays()
    return bool(
        np.all(np.abs(a[[0, 3, 4, 5]]) <= tol)
        and np.all(np.abs(alpha - _UR_ALPHA) <= tol)
        and abs(a[1] * a[2]) > 0.0
    )


def _wrap(q: Array) -> Array:
    return (q + np.pi) % _TWO_PI - np.pi


def _ik_closed_form(dh: DHParameters, T: Array, q6_singular: float, slack: float) -> Array:
    """Closed-form UR IK (all branches) using ``d, a_2, a_3`` and the nominal structure.

    Returns joint angles ``q = theta - theta_offset`` wrapped to [-pi, pi), shape ``(K, 6)``.
    ``slack`` lets arguments of asin/acos exceed 1 by that much before a branch is dropped
    (tiny for exact solving, larger when the result only seeds :func:`ik_refine`).
    """
    a, d, alpha, off = dh.as_arrays()
    d1, d5, d6 = d[0], d[4], d[5]
    d4 = d[1] + d[2] + d[3]  # offset of the planar 2-3-4 chain along the shoulder axis z_1
    a2, a3 = a[1], a[2]
    X, Y, Z, p6 = T[:3, 0], T[:3, 1], T[:3, 2], T[:3, 3]
    # 1) Wrist centre p5 = origin of frame 5 = p6 - d6 z6. Its coordinate along the shoulder
    #    axis z_1 = (sin q1, -cos q1, 0) is d4:  p5x s1 - p5y c1 = d4.
    p5 = p6 - d6 * Z
    r = float(np.hypot(p5[0], p5[1]))
    if r < 1e-12:  # wrist centre on the base axis (shoulder singular / unreachable)
        if abs(d4) > 1e-12:
            return np.zeros((0, 6))
        th1s = [0.0, np.pi]
    else:
        s = d4 / r
        if abs(s) > 1.0 + slack:
            return np.zeros((0, 6))
        s = float(np.clip(s, -1.0, 1.0))
        psi = float(np.arctan2(p5[1], p5[0]))
        th1s = [psi + np.arcsin(s), psi + np.pi - np.arcsin(s)]
    out = []
    for th1 in th1s:
        s1, c1 = np.sin(th1), np.cos(th1)
        # 2-3) The shoulder axis z_1 = (s1, -c1, 0) seen in the flange frame is
        #      (s5 c6, -s5 s6, c5); atan2 keeps q5 accurate near 0 and pi (acos would not).
        #      (The position condition p6 . z_1 = d4 + d6 c5 then holds by construction of q1.)
        zx = X[0] * s1 - X[1] * c1
        zy = Y[0] * s1 - Y[1] * c1
        zz = Z[0] * s1 - Z[1] * c1
        abs_s5 = float(np.hypot(zx, zy))
        for sg in (1.0, -1.0):  # wrist flipped / not flipped
            th5 = sg * np.arctan2(abs_s5, zz)
            if abs_s5 < _SINGULAR_S5:  # wrist singular: joints 4 and 6 aligned, q6 free
                th6 = q6_singular + off[5]
            else:
                th6 = np.arctan2(-sg * zy, sg * zx)
            # 4) T_1_4 = A2 A3 A4 = [Rz(q2+q3+q4) Rx(pi/2), (a2 c2 + a3 c23, a2 s2 + a3 s23, d4)]
            T14 = (
                _dh_one_inv(th1, d1, a[0], alpha[0])
                @ T
                @ _dh_one_inv(th6, d6, a[5], alpha[5])
                @ _dh_one_inv(th5, d5, a[4], alpha[4])
            )
            px, py = T14[0, 3], T14[1, 3]
            th234 = np.arctan2(T14[1, 0], T14[0, 0])
            c3 = (px * px + py * py - a2 * a2 - a3 * a3) / (2.0 * a2 * a3)
            if abs(c3) > 1.0 + slack:
                continue
            acos3 = float(np.arccos(np.clip(c3, -1.0, 1.0)))
            for th3 in (acos3, -acos3):
                th2 = np.arctan2(py, px) - np.arctan2(a3 * np.sin(th3), a2 + a3 * np.cos(th3))
                th4 = th234 - th2 - th3
                out.append([th1, th2, th3, th4, th5, th6])
    if not out:
        return np.zeros((0, 6))
    return _wrap(np.array(out) - off)


def _dedup(Q: Array) -> Array:
    keep: list[Array] = []
    for q in Q:
        if all(np.max(np.abs(_wrap(q - k))) > _DEDUP_TOL for k in keep):
            keep.append(q)
    return np.array(keep) if keep else np.zeros((0, 6))


def _pose_error(T_target: Array, T: Array) -> Array:
    """``[p_target - p; log(R_target R^T)]`` (m, rad), both in ``arm_base``."""
    e_rot = log_so3(T_target[:3, :3] @ T[:3, :3].T)
    return np.concatenate([T_target[:3, 3] - T[:3, 3], e_rot])


def _refine(
    dh: DHParameters,
    T_target: Array,
    q0: Array,
    tool: Array | None,
    tol: float,
    max_iter: int,
    damping: float,
) -> tuple[Array, bool, Array]:
    """Levenberg-Marquardt on the pose error; returns ``(q, converged, e)``."""

    a, d, alpha, off = dh.as_arrays()
    ca, sa = np.cos(alpha), np.sin(alpha)

    def err(q: Array) -> tuple[Array, Array]:  # link_transforms(dh, q), without its checks
        A = _dh_cs(q + off, d, a, ca, sa)
        F = np.empty((7, 4, 4))
        F[0] = _EYE4
        for i in range(6):
            np.matmul(F[i], A[i], out=F[i + 1])
        return _pose_error(T_target, F[6] if tool is None else F[6] @ tool), F

    q = np.array(q0, dtype=float)
    e, F = err(q)
    cost = float(e @ e)
    lam = damping
    for _ in range(max_iter):
        if np.linalg.norm(e[:3]) <= tol and np.linalg.norm(e[3:]) <= tol:
            return q, True, e
        J = _jacobian_from_frames(F, tool)
        JtJ, Jte = J.T @ J, J.T @ e
        while True:
            dq = np.linalg.solve(JtJ + lam * lam * _EYE6, Jte)
            n = float(np.linalg.norm(dq))
            if n > 0.5:  # trust region: far from the solution, take short steps
                dq *= 0.5 / n
            e_new, F_new = err(q + dq)
            cost_new = float(e_new @ e_new)
            if cost_new < cost or lam > 1e3:
                break
            lam *= 10.0  # step made things worse: lean towards gradient descent
        if cost_new >= cost:  # no progress even with heavy damping: stuck
            break
        q, e, F, cost = q + dq, e_new, F_new, cost_new
        lam = max(lam * 0.1, damping)
    ok = bool(np.linalg.norm(e[:3]) <= tol and np.linalg.norm(e[3:]) <= tol)
    return q, ok, e


def ik_refine(
    dh: DHParameters,
    T_arm_base_flange: ArrayLike,
    q0: ArrayLike,
    *,
    T_flange_point: ArrayLike | None = None,
    tol: float = 1e-11,
    max_iter: int = 50,
    damping: float = 1e-6,
) -> Array:
    """Polish a seed ``q0`` (6,) into an exact IK solution of the FULL DH model.

    Damped least-squares Newton (Levenberg-Marquardt): with the pose error
    ``e = [p* - p; log(R* R^T)]`` (m, rad, in ``arm_base``) and the geometric Jacobian ``J``,
    ``dq = (J^T J + lambda^2 I)^-1 J^T e``, steps capped at 0.5 rad; ``lambda`` starts at
    ``damping`` and grows x10 whenever a step would increase ``|e|``. Stops when both
    ``|e_p|`` (m) and ``|e_R|`` (rad) are below ``tol``. Converges quadratically from a
    closed-form seed of a slightly perturbed UR arm. The result stays near ``q0`` (not
    wrapped). With ``T_flange_point`` the target is the pose
    of that point (``T_arm_base_point``).

    Raises :class:`UnreachableError` if it does not converge within ``max_iter`` iterations.
    """
    T = as_transform(T_arm_base_flange, "T_arm_base_flange")
    q0 = _as_q(q0, "q0")
    if q0.shape != (6,):
        raise InvalidInputError(f"q0 must have shape (6,), got {q0.shape}")
    q, ok, e = _refine(dh, T, q0, _tool(T_flange_point), tol, max_iter, damping)
    if not ok:
        raise UnreachableError(
            f"IK refinement did not converge in {max_iter} iterations: residual "
            f"{np.linalg.norm(e[:3]):.3g} m, {np.linalg.norm(e[3:]):.3g} rad (tol {tol:g}); "
            "the pose may be unreachable or the seed too far from a solution"
        )
    return q


def _expand(Q: Array, q_min: Array, q_max: Array, eps: float = 1e-12) -> Array:
    """All ``q + 2 pi k`` variants (per joint) inside ``[q_min, q_max]``."""
    out: list[tuple[float, ...]] = []
    for q in Q:
        per_joint = []
        for i in range(6):
            k_lo = int(np.ceil((q_min[i] - q[i]) / _TWO_PI - eps))
            k_hi = int(np.floor((q_max[i] - q[i]) / _TWO_PI + eps))
            vals = [
                float(np.clip(q[i] + _TWO_PI * k, q_min[i], q_max[i]))
                for k in range(k_lo, k_hi + 1)
            ]
            if not vals:
                break
            per_joint.append(vals)
        else:
            out.extend(itertools.product(*per_joint))
    return np.array(out) if out else np.zeros((0, 6))


def ik(
    dh: DHParameters,
    T_arm_base_flange: ArrayLike,
    *,
    T_flange_point: ArrayLike | None = None,
    expand_limits: tuple[ArrayLike, ArrayLike] | None = None,
    refine: bool | None = None,
    seeds: ArrayLike | None = None,
    q6_singular: float = 0.0,
    tol: float = 1e-11,
) -> Array:
    """All inverse-kinematics solutions of a UR-family arm, shape ``(K, 6)`` (rad), K <= 8.

    Closed form (shoulder left/right x wrist up/down x elbow up/down):

    1. wrist centre ``p5 = p6 - d6 z6``; the shoulder offset fixes
       ``q1 = atan2(p5y, p5x) + {asin(d4 / r), pi - asin(d4 / r)}``, ``r = |p5_xy|``;
    2. the shoulder axis ``z_1 = (s1, -c1, 0)`` seen in the flange frame is
       ``(s5 c6, -s5 s6, c5) = (X . z_1, Y . z_1, Z . z_1)`` with ``X, Y, Z`` the flange axes,
       so ``q5 = +-atan2(hypot(X . z_1, Y . z_1), Z . z_1)`` (equivalently
       ``cos q5 = (p6x s1 - p6y c1 - d4) / d6``);
    3. ``q6 = atan2(-(Y . z_1) / s5, (X . z_1) / s5)``; at the wrist singularity
       (``|sin q5| < 1e-12``) ``q6`` is free and set to ``q6_singular`` (q2..q4 then absorb
       the rest, so the pose is still exact);
    4. ``T_1_4 = A1^-1 T A6^-1 A5^-1`` is a planar 2R chain plus ``q2 + q3 + q4``:
       ``cos q3 = (x^2 + y^2 - a2^2 - a3^2) / (2 a2 a3)``, ``q3 = +-acos(.)``,
       ``q2 = atan2(y, x) - atan2(a3 sin q3, a2 + a3 cos q3)``, ``q4 = q234 - q2 - q3``.

    ``theta_offset`` is subtracted (``q = theta - theta_offset``). Solutions are wrapped to
    [-pi, pi) and duplicates (singular branches) removed. An unreachable pose gives an empty
    ``(0, 6)`` array, never NaN.

    ``refine``: polish every branch with :func:`ik_refine` on the full DH model and keep the
    converged ones; ``None`` (default) refines only when ``dh`` is not exactly UR-structured
    (:func:`is_ur_structure`), e.g. a perturbed "true" arm. ``tol`` (m and rad) is the
    refinement tolerance; ``seeds`` ``(M, 6)`` are extra starting points for the refinement
    (e.g. the current configuration). A perturbed arm is a general 6R chain (up to 16
    solutions): away from singularities each closed-form branch converges to the perturbed
    arm's solution on that branch; near a singularity a branch may be lost or land on a
    neighbouring solution, so pass a nearby seed when continuity matters.

    ``expand_limits=(q_min, q_max)`` replaces each solution by all its per-joint ``+-2 pi``
    variants inside the limits (solutions with a joint that cannot fit are dropped), so K can
    exceed 8. With ``T_flange_point``, the target is the pose of that point
    (``T_arm_base_point``) and the flange target is ``T @ inv(T_flange_point)``.
    """
    T = as_transform(T_arm_base_flange, "T_arm_base_flange")
    tool = _tool(T_flange_point)
    T_flange = T if tool is None else T @ inv(tool)
    if not np.isfinite(q6_singular):
        raise InvalidInputError("q6_singular must be finite")
    if refine is None:
        refine = not is_ur_structure(dh)
    if refine:
        starts = _ik_closed_form(dh, T_flange, q6_singular, slack=1e-2)
        if seeds is not None:
            starts = np.concatenate([_as_q(seeds, "seeds").reshape(-1, 6), starts])
        sols = []
        for s in starts:
            q, ok, _ = _refine(dh, T_flange, s, None, tol, 50, 1e-6)
            if ok:
                sols.append(_wrap(q))
        Q = np.array(sols) if sols else np.zeros((0, 6))
    else:
        Q = _ik_closed_form(dh, T_flange, q6_singular, slack=1e-9)
    Q = _dedup(Q)
    if expand_limits is not None:
        Q = _expand(Q, *_as_limits(*expand_limits))
    return Q


def _unreachable_message(dh: DHParameters, T_flange: Array) -> str:
    a, d, _, _ = dh.as_arrays()
    d4 = d[1] + d[2] + d[3]
    p5 = T_flange[:3, 3] - d[5] * T_flange[:3, 2]
    dist = float(np.linalg.norm(p5 - np.array([0.0, 0.0, d[0]])))
    reach = float(np.hypot(d4, abs(a[1]) + abs(a[2]) + abs(d[4])))
    r = float(np.hypot(p5[0], p5[1]))
    if dist > reach:
        return (
            f"pose unreachable: the wrist centre is {dist:.4f} m from the shoulder, beyond the "
            f"arm's reach of {reach:.4f} m"
        )
    if r < abs(d4):
        return (
            f"pose unreachable: the wrist centre is {r:.4f} m from the base axis, closer than "
            f"the shoulder offset d4 = {abs(d4):.4f} m"
        )
    return (
        f"pose unreachable with this orientation: the wrist centre is {dist:.4f} m from the "
        f"shoulder (reach {reach:.4f} m) but no wrist/elbow configuration matches"
    )


def ik_nearest(
    dh: DHParameters,
    T_arm_base_flange: ArrayLike,
    q_ref: ArrayLike,
    q_min: ArrayLike,
    q_max: ArrayLike,
    *,
    weights: ArrayLike | None = None,
    T_flange_point: ArrayLike | None = None,
    refine: bool | None = None,
) -> Array:
    """The IK solution closest to ``q_ref`` within the joint limits, shape ``(6,)`` (rad).

    Distance ``sqrt(sum_i w_i (q_i - q_ref_i)^2)`` (``weights`` default 1). For every solution
    of :func:`ik`, each joint takes the ``q_i + 2 pi k`` variant nearest ``q_ref_i`` inside
    ``[q_min_i, q_max_i]`` (the cost is convex in ``k``, so the unconstrained best ``k``
    clipped to the feasible range is optimal). At a wrist singularity ``q6`` is set to
    ``q_ref[5]``; when refining (perturbed DH) ``q_ref`` is also a refinement seed.

    Raises :class:`UnreachableError` when the pose has no IK solution (the message compares
    the wrist centre's distance from the shoulder with the reach) or when all solutions
    violate the joint limits.
    """
    T = as_transform(T_arm_base_flange, "T_arm_base_flange")
    q_ref = _as_q(q_ref, "q_ref")
    if q_ref.shape != (6,):
        raise InvalidInputError(f"q_ref must have shape (6,), got {q_ref.shape}")
    lo, hi = _as_limits(q_min, q_max)
    w = np.ones(6) if weights is None else np.asarray(weights, dtype=float).reshape(-1)
    if w.shape != (6,) or np.any(~np.isfinite(w)) or np.any(w < 0):
        raise InvalidInputError(f"weights must be 6 finite non-negative values, got {w}")
    Q = ik(
        dh,
        T,
        T_flange_point=T_flange_point,
        refine=refine,
        seeds=q_ref,
        q6_singular=float(q_ref[5]),
    )
    if len(Q) == 0:
        tool = _tool(T_flange_point)
        raise UnreachableError(_unreachable_message(dh, T if tool is None else T @ inv(tool)))
    eps = 1e-12
    best, best_cost = None, np.inf
    for q in Q:
        k_lo = np.ceil((lo - q) / _TWO_PI - eps)
        k_hi = np.floor((hi - q) / _TWO_PI + eps)
        if np.any(k_lo > k_hi):
            continue
        k = np.clip(np.round((q_ref - q) / _TWO_PI), k_lo, k_hi)
        cand = np.clip(q + _TWO_PI * k, lo, hi)
        cost = float(np.sqrt(np.sum(w * (cand - q_ref) ** 2)))
        if cost < best_cost:
            best, best_cost = cand, cost
    if best is None:
        raise UnreachableError(
            f"all {len(Q)} IK solutions violate the joint limits "
            f"q_min={np.round(lo, 4).tolist()}, q_max={np.round(hi, 4).tolist()}"
        )
    return best
