"""SE(3) / SE(2) helpers, 6D pose vectors and the pose-error metrics of paper 000.

Conventions (DESIGN.md): ``T_a_b`` is a 4x4 homogeneous transform, the pose of frame ``b``
in frame ``a``; it maps points from ``b`` to ``a``. Compose as ``T_a_c = T_a_b @ T_b_c``.
Angles in radians. The 6D vector ``[tx, ty, tz, roll, pitch, yaw]`` uses the fixed-axis
X-Y-Z (ROS RPY) convention ``R = Rz(yaw) @ Ry(pitch) @ Rx(roll)``.
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.spatial.transform import Rotation

from mmpa.core.errors import InvalidInputError

Array = NDArray[np.float64]

__all__ = [
    "R_to_quat_xyzw",
    "R_to_rpy",
    "T_to_se2",
    "T_to_vec6",
    "adjoint",
    "apply",
    "as_transform",
    "exp_se3",
    "exp_so3",
    "hat",
    "inv",
    "is_rotation",
    "log_se3",
    "log_so3",
    "make_T",
    "quat_xyzw_to_R",
    "rot_x",
    "rot_y",
    "rot_z",
    "rotation_error",
    "rpy_to_R",
    "se2_compose",
    "se2_inv",
    "se2_to_T",
    "trans",
    "translation_error",
    "vec6_to_T",
    "wrap_angle",
]


def as_transform(T: ArrayLike, name: str = "T") -> Array:
    """``T`` as a float 4x4 array; InvalidInputError naming ``name`` if malformed or NaN."""
    T = np.asarray(T, dtype=float)
    if T.shape != (4, 4):
        raise InvalidInputError(f"{name} must be a 4x4 homogeneous transform, got shape {T.shape}")
    if not np.all(np.isfinite(T)):
        raise InvalidInputError(f"{name} contains NaN or inf")
    return T


def make_T(R: ArrayLike | None = None, t: ArrayLike | None = None) -> Array:
    """Build ``[[R, t], [0, 1]]`` from a 3x3 rotation and a 3-vector (defaults: I, 0)."""
    T = np.eye(4)
    if R is not None:
        T[:3, :3] = np.asarray(R, dtype=float).reshape(3, 3)
    if t is not None:
        T[:3, 3] = np.asarray(t, dtype=float).reshape(3)
    return T


def trans(x: float = 0.0, y: float = 0.0, z: float = 0.0) -> Array:
    """Pure translation."""
    return make_T(t=(x, y, z))


def rot_x(a: float) -> Array:
    """3x3 rotation about x by ``a`` rad."""
    c, s = np.cos(a), np.sin(a)
    return np.array([[1.0, 0.0, 0.0], [0.0, c, -s], [0.0, s, c]])


def rot_y(a: float) -> Array:
    """3x3 rotation about y by ``a`` rad."""
    c, s = np.cos(a), np.sin(a)
    return np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])


def rot_z(a: float) -> Array:
    """3x3 rotation about z by ``a`` rad."""
    c, s = np.cos(a), np.sin(a)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def inv(T: ArrayLike) -> Array:
    """Inverse of a rigid transform: ``[[R^T, -R^T t], [0, 1]]``."""
    T = np.asarray(T, dtype=float)
    R, t = T[:3, :3], T[:3, 3]
    return make_T(R.T, -R.T @ t)


def apply(T: ArrayLike, points: ArrayLike) -> Array:
    """Transform points ``(N, 3)`` (or one ``(3,)``) by ``T``: ``p_a = R p_b + t``."""
    T = np.asarray(T, dtype=float)
    p = np.asarray(points, dtype=float)
    return p @ T[:3, :3].T + T[:3, 3]


def is_rotation(R: ArrayLike, tol: float = 1e-6) -> bool:
    """True if ``R`` is orthonormal with determinant +1 (within ``tol``)."""
    R = np.asarray(R, dtype=float)
    return (
        R.shape == (3, 3)
        and bool(np.allclose(R.T @ R, np.eye(3), atol=tol))
        and abs(np.linalg.det(R) - 1.0) < tol
    )


def rpy_to_R(roll: float, pitch: float, yaw: float) -> Array:
    """``R = Rz(yaw) Ry(pitch) Rx(roll)`` (fixed axes X, Y, Z; ROS RPY)."""
    return rot_z(yaw) @ rot_y(pitch) @ rot_x(roll)


def R_to_rpy(R: ArrayLike) -> Array:
    """Inverse of :func:`rpy_to_R`; returns ``[roll, pitch, yaw]`` with pitch in [-pi/2, pi/2]."""
    R = np.asarray(R, dtype=float)
    pitch = np.arcsin(np.clip(-R[2, 0], -1.0, 1.0))
    if abs(np.cos(pitch)) < 1e-9:  # gimbal lock: put all of the rotation in yaw
        roll = 0.0
        yaw = np.arctan2(-R[0, 1], R[1, 1])
    else:
        roll = np.arctan2(R[2, 1], R[2, 2])
        yaw = np.arctan2(R[1, 0], R[0, 0])
    return np.array([roll, pitch, yaw])


def vec6_to_T(v: ArrayLike) -> Array:
    """``[tx, ty, tz, roll, pitch, yaw]`` (m, rad) to a 4x4 transform."""
    v = np.asarray(v, dtype=float)
    if v.shape != (6,):
        raise InvalidInputError(f"6D pose vector must have shape (6,), got {v.shape}")
    if not np.all(np.isfinite(v)):
        raise InvalidInputError(f"6D pose vector contains NaN or inf: {v}")
    return make_T(rpy_to_R(*v[3:]), v[:3])


def T_to_vec6(T: ArrayLike) -> Array:
    """4x4 transform to ``[tx, ty, tz, roll, pitch, yaw]`` (m, rad)."""
    T = as_transform(T)
    return np.concatenate([T[:3, 3], R_to_rpy(T[:3, :3])])


def quat_xyzw_to_R(q: ArrayLike) -> Array:
    """Unit quaternion ``(x, y, z, w)`` (ROS order, as printed in paper 000 §4.2) to R."""
    return Rotation.from_quat(np.asarray(q, dtype=float)).as_matrix()


def R_to_quat_xyzw(R: ArrayLike) -> Array:
    """Rotation matrix to unit quaternion ``(x, y, z, w)`` with ``w >= 0``."""
    q = Rotation.from_matrix(np.asarray(R, dtype=float)).as_quat()
    return q if q[3] >= 0 else -q


def hat(w: ArrayLike) -> Array:
    """Skew-symmetric matrix ``[w]x`` such that ``hat(w) @ v == cross(w, v)``."""
    x, y, z = np.asarray(w, dtype=float)
    return np.array([[0.0, -z, y], [z, 0.0, -x], [-y, x, 0.0]])


def _as_twist(xi: ArrayLike) -> Array:
    xi = np.asarray(xi, dtype=float)
    if xi.shape != (6,):
        raise InvalidInputError(f"twist must have shape (6,) as [v, w], got {xi.shape}")
    if not np.all(np.isfinite(xi)):
        raise InvalidInputError("twist contains NaN or inf")
    return xi


def _so3_coeffs(th: float) -> tuple[float, float, float]:
    """``sin(th)/th, (1-cos th)/th^2, (th-sin th)/th^3`` without cancellation near 0."""
    if th < 1e-2:  # Taylor series; the next terms are below 1e-17
        t2 = th * th
        a = 1.0 - t2 / 6.0 + t2 * t2 / 120.0
        b = 0.5 - t2 / 24.0 + t2 * t2 / 720.0
        c = 1.0 / 6.0 - t2 / 120.0 + t2 * t2 / 5040.0
        return a, b, c
    a = np.sin(th) / th
    b = 2.0 * np.sin(0.5 * th) ** 2 / th**2
    c = (th - np.sin(th)) / th**3
    return float(a), float(b), float(c)


def exp_so3(w: ArrayLike) -> Array:
    """Rodrigues' formula: the rotation (3, 3) of the rotation vector ``w`` (3,) (rad),
    ``I + sin(th)/th W + (1 - cos th)/th^2 W^2`` with ``W = hat(w)``, ``th = |w|``."""
    w = np.asarray(w, dtype=float)
    a, b, _ = _so3_coeffs(float(np.linalg.norm(w)))
    W = hat(w)
    return np.eye(3) + a * W + b * W @ W


def log_so3(R: ArrayLike) -> Array:
    """``log(R)`` as a rotation vector (rad), shape (3,), of a rotation matrix ``R`` (3, 3).

    ``cos th = (tr R - 1) / 2``, ``v = (R32 - R23, R13 - R31, R21 - R12) = 2 sin(th) u``,
    ``th = atan2(|v| / 2, cos th)`` and ``log R = th / (2 sin th) v`` (the factor
    ``1/2 + th^2 / 12`` to second order when ``sin th < 1e-8``). Near ``th = pi``
    (``cos th < -0.99``) ``v`` vanishes and the axis is taken from scipy's quaternion route
    instead. A tenth of scipy's cost (the IK refinement's and the tf interpolation's inner
    step).
    """
    R = np.asarray(R, dtype=float)
    c = 0.5 * (R[0, 0] + R[1, 1] + R[2, 2] - 1.0)
    if c < -0.99:
        return Rotation.from_matrix(R).as_rotvec()
    v = np.array([R[2, 1] - R[1, 2], R[0, 2] - R[2, 0], R[1, 0] - R[0, 1]])
    s = 0.5 * math.sqrt(v[0] * v[0] + v[1] * v[1] + v[2] * v[2])
    th = math.atan2(s, c)
    return (0.5 + th * th / 12.0 if s < 1e-8 else 0.5 * th / s) * v


def exp_se3(xi: ArrayLike) -> Array:
    """Exponential map of a twist ``xi = [v, w]`` (6,) to SE(3) (closed-form Rodrigues)."""
    xi = _as_twist(xi)
    v, w = xi[:3], xi[3:]
    th = float(np.linalg.norm(w))
    W = hat(w)
    a, b, c = _so3_coeffs(th)
    R = np.eye(3) + a * W + b * W @ W
    V = np.eye(3) + b * W + c * W @ W
    return make_T(R, V @ v)


def log_se3(T: ArrayLike) -> Array:
    """Logarithm of SE(3): the twist ``[v, w]`` (6,) with ``exp_se3(log_se3(T)) == T``."""
    T = as_transform(T)
    w = Rotation.from_matrix(T[:3, :3]).as_rotvec()
    th = float(np.linalg.norm(w))
    W = hat(w)
    # V^-1 = I - W/2 + k W^2 with k = (1 - (th/2) cot(th/2)) / th^2
    if th < 1e-2:  # Taylor series (the closed form cancels catastrophically near 0)
        t2 = th * th
        k = 1.0 / 12.0 + t2 / 720.0 + t2 * t2 / 30240.0
    else:
        k = (1.0 - 0.5 * th / np.tan(0.5 * th)) / th**2
    V_inv = np.eye(3) - 0.5 * W + k * W @ W
    return np.concatenate([V_inv @ T[:3, 3], w])


def adjoint(T: ArrayLike) -> Array:
    """6x6 adjoint of ``T`` acting on twists ``[v, w]``: ``xi_a = Ad(T_a_b) xi_b``."""
    T = np.asarray(T, dtype=float)
    R, t = T[:3, :3], T[:3, 3]
    Ad = np.zeros((6, 6))
    Ad[:3, :3] = R
    Ad[3:, 3:] = R
    Ad[:3, 3:] = hat(t) @ R
    return Ad


def rotation_error(R_gt: ArrayLike, R_est: ArrayLike) -> float:
    """Paper 000 eq. 12: ``E_R = ||I - R_gt R_est^-1||_F`` (dimensionless, 0 when equal).

    For a residual rotation of angle ``phi`` this equals ``2 sqrt(2) |sin(phi / 2)|``.
    Accepts 3x3 rotations or 4x4 transforms.
    """
    Rg = np.asarray(R_gt, dtype=float)[:3, :3]
    Re = np.asarray(R_est, dtype=float)[:3, :3]
    return float(np.linalg.norm(np.eye(3) - Rg @ Re.T, ord="fro"))


def translation_error(t_gt: ArrayLike, t_est: ArrayLike) -> float:
    """Paper 000 eq. 13: ``E_t = ||t_gt - t_est||`` (m). Accepts 3-vectors or 4x4 transforms."""
    a = np.asarray(t_gt, dtype=float)
    b = np.asarray(t_est, dtype=float)
    a = a[:3, 3] if a.shape == (4, 4) else a
    b = b[:3, 3] if b.shape == (4, 4) else b
    return float(np.linalg.norm(a - b))


def wrap_angle(a: ArrayLike) -> Array | float:
    """Wrap angle(s) to [-pi, pi)."""
    w = (np.asarray(a, dtype=float) + np.pi) % (2.0 * np.pi) - np.pi
    return float(w) if np.ndim(w) == 0 else w


# --- SE(2): poses (x, y, theta) of the base in the plane --------------------------------


def se2_to_T(x: float, y: float, theta: float) -> Array:
    """Planar pose to a 4x4 transform (rotation about z)."""
    return make_T(rot_z(theta), (x, y, 0.0))


def T_to_se2(T: ArrayLike) -> Array:
    """Project a 4x4 transform on the plane: ``[x, y, yaw]`` with yaw of the x axis."""
    T = as_transform(T)
    return np.array([T[0, 3], T[1, 3], np.arctan2(T[1, 0], T[0, 0])])


def se2_compose(a: ArrayLike, b: ArrayLike) -> Array:
    """``a ⊕ b`` for planar poses ``[x, y, theta]``; accepts ``(3,)`` or ``(N, 3)`` arrays."""
    a = np.asarray(a, dtype=float)
    b = np.asarray(b, dtype=float)
    c, s = np.cos(a[..., 2]), np.sin(a[..., 2])
    x = a[..., 0] + c * b[..., 0] - s * b[..., 1]
    y = a[..., 1] + s * b[..., 0] + c * b[..., 1]
    th = wrap_angle(a[..., 2] + b[..., 2])
    return np.stack([x, y, th], axis=-1)


def se2_inv(a: ArrayLike) -> Array:
    """Inverse planar pose ``⊖a`` so that ``se2_compose(a, se2_inv(a)) == 0``."""
    a = np.asarray(a, dtype=float)
    c, s = np.cos(a[..., 2]), np.sin(a[..., 2])
    x = -c * a[..., 0] - s * a[..., 1]
    y = s * a[..., 0] - c * a[..., 1]
    return np.stack([x, y, wrap_angle(-a[..., 2])], axis=-1)
