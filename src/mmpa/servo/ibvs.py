"""Image-based visual servoing (paper 001 §3.2.2, eq. 9-12).

The feature is the detected object center: normalized image coordinates ``x = X / Z``,
``y = Y / Z`` of the object point ``P = (X, Y, Z)`` in the camera optical frame, plus its
depth ``log Z`` from the RGB-D frame. The tracking point (paper: the gripper center between
the fingers) is where that feature must sit when the gripper is ``standoff`` above the object:
``P* = inv(T_flange_camera) T_flange_tcp (0, 0, standoff)``, so ``s* = (X*/Z*, Y*/Z*, log Z*)``.

Eq. 10: ``e = s - s*``. For a static point and camera twist ``(v, w)`` (optical frame),
``ds/dt = L (v, w)`` with the interaction matrix (Chaumette & Hutchinson 2006)::

    L_x = [-1/Z,  0,  x/Z,  x y,    -(1 + x^2),  y]
    L_y = [ 0, -1/Z,  y/Z,  1 + y^2, -x y,      -x]
    L_z = [ 0,    0, -1/Z,  -y,       x,         0]   (row of log Z)

Eq. 11-12: the camera velocity ``v = -lambda L_v^+ e`` (translation; the orientation is held
top-down by a separate proportional term, so the 3x3 translational block ``L_v`` is used), then
joint velocities ``qdot = J^+ [v; w]`` with the camera-point Jacobian ``J`` in ``arm_base`` and
``J^+ = (J^T J)^-1 J^T`` (eq. 12; damped near singularities, an improvement). A moving object
adds its velocity as feed-forward (the predictor's estimate). Joint speeds are scaled to the
limits (direction kept) and the next set-point is clipped inside the joint limits.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from pydantic import BaseModel, ConfigDict, Field
from scipy.spatial.transform import Rotation

from mmpa.core.errors import InvalidInputError
from mmpa.core.geometry import Array, apply, inv

__all__ = [
    "IBVSConfig",
    "ServoCommand",
    "camera_velocity",
    "desired_point",
    "features",
    "interaction_matrix",
    "joint_velocity",
    "limit_velocity",
    "pinv",
]


class IBVSConfig(BaseModel):
    model_config = ConfigDict(extra="forbid")
    gain: float = Field(1.5, gt=0)  # lambda (1/s), static or slow objects
    # lambda (1/s) for an object the predictor sees moving (GraspConfig.track.
    # final_standoff_max_speed; measured: docs/servo.md)
    moving_gain: float = Field(3.0, gt=0)
    orientation_gain: float = Field(2.0, gt=0)  # 1/s
    standoff: float = Field(0.25, gt=0)  # m, tracking height of the TCP above the object
    max_linear_speed: float = Field(0.5, gt=0)  # m/s of the camera
    joint_speed_fraction: float = Field(0.6, gt=0, le=1)  # of the arm's qd_max
    damping: float = Field(1e-3, ge=0)  # damped least squares lambda^2 near singularities


def interaction_matrix(x: float, y: float, Z: float) -> Array:
    """(3, 6) interaction matrix of ``(x, y, log Z)`` for camera twist ``(v, w)``."""
    if not (np.isfinite(Z) and Z > 0):
        raise InvalidInputError(f"feature depth must be positive, got {Z}")
    return np.array(
        [
            [-1 / Z, 0.0, x / Z, x * y, -(1 + x * x), y],
            [0.0, -1 / Z, y / Z, 1 + y * y, -x * y, -x],
            [0.0, 0.0, -1 / Z, -y, x, 0.0],
        ]
    )


def features(P_cam: Array) -> Array:
    """``s = (X/Z, Y/Z, log Z)`` of a point (3,) in the optical frame."""
    P = np.asarray(P_cam, float)
    if P.shape != (3,) or not (P[2] > 0):
        raise InvalidInputError(f"point must be (3,) in front of the camera, got {P}")
    return np.array([P[0] / P[2], P[1] / P[2], np.log(P[2])])


def desired_point(T_flange_camera: Array, T_flange_tcp: Array, standoff: float) -> Array:
    """``P*`` (3,): the point ``standoff`` m below the TCP along the tool z, in the camera."""
    return apply(inv(T_flange_camera) @ np.asarray(T_flange_tcp), np.array([0.0, 0.0, standoff]))


def pinv(J: Array, damping: float = 0.0) -> Array:
    """Eq. 12 ``J^+ = (J^T J)^-1 J^T`` for full column rank; for a wide ``J`` (m < n) the
    right inverse ``J^T (J J^T + d I)^-1``; ``damping`` d > 0 gives damped least squares."""
    J = np.asarray(J, float)
    m, n = J.shape
    if m >= n:
        return np.linalg.solve(J.T @ J + damping * np.eye(n), J.T)
    return J.T @ np.linalg.solve(J @ J.T + damping * np.eye(m), np.eye(m))


def camera_velocity(P_cam: Array, P_star: Array, gain: float) -> Array:
    """Eq. 10-11 in the image: translational camera velocity (3,) m/s (optical frame)
    ``v = -lambda L_v^-1 (s - s*)`` (rotation held by the orientation loop)."""
    s, s_star = features(P_cam), features(P_star)
    L = interaction_matrix(s[0], s[1], float(np.asarray(P_cam)[2]))
    return -gain * np.linalg.solve(L[:, :3], s - s_star)


def limit_velocity(qdot: Array, qd_max: Array) -> Array:
    """Scale ``qdot`` uniformly so that ``|qdot_i| <= qd_max_i`` (direction kept)."""
    qdot = np.asarray(qdot, float)
    r = float(np.max(np.abs(qdot) / np.asarray(qd_max, float)))
    return qdot / r if r > 1 else qdot


@dataclass(frozen=True)
class ServoCommand:
    """One servo step: joint velocity (6,) rad/s, the camera twist (6,) in ``arm_base`` and
    the feature error (3,)."""

    qdot: Array
    twist: Array
    error: Array


def orientation_velocity(R: Array, R_des: Array, gain: float) -> Array:
    """Angular velocity (3,) in the base frame that turns ``R`` toward ``R_des``."""
    return gain * Rotation.from_matrix(np.asarray(R_des) @ np.asarray(R).T).as_rotvec()


def joint_velocity(
    J_cam: Array,
    T_arm_base_camera: Array,
    v_cam: Array,
    w_base: Array,
    damping: float = 1e-3,
    v_feedforward: Array | None = None,
) -> Array:
    """Eq. 11-12: ``qdot = J^+ [R v_cam + v_ff; w]`` with ``J`` the camera-point Jacobian in
    ``arm_base`` (6, 6) and ``v_ff`` (3,) the object's velocity (base frame, feed-forward)."""
    R = np.asarray(T_arm_base_camera)[:3, :3]
    v = R @ np.asarray(v_cam, float)
    if v_feedforward is not None:
        v = v + np.asarray(v_feedforward, float)
    return pinv(J_cam, damping) @ np.concatenate([v, w_base])
