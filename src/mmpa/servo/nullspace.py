"""Null-space manipulability maximization (paper 001 eq. 13-14).

Eq. 14: ``Omega = sqrt(det(J J^T))`` (:func:`mmpa.robot.kinematics.manipulability`). Eq. 13:
``qdot = -lambda J^+ e_dot + N qdot_0`` with the projector ``N = I - J_t^+ J_t`` of the task
Jacobian ``J_t`` and ``qdot_0 = k grad_q Omega``. A full 6-D task on a 6-joint arm has no null
space (N = 0), so the tracking task leaves the rotation about the vertical free for objects
whose grasp does not depend on it (balls, upright cylinders): ``J_t`` is the 5 rows of the
camera Jacobian (3 translations, 2 tilts), and the remaining degree of freedom climbs the
manipulability gradient without moving the camera's position or its viewing axis.
"""

from __future__ import annotations

import numpy as np

from mmpa.core.geometry import Array
from mmpa.robot.description import DHParameters
from mmpa.robot.kinematics import jacobian, manipulability
from mmpa.servo.ibvs import pinv

__all__ = ["manipulability_gradient", "null_space_projector", "null_space_velocity"]


def manipulability_gradient(
    dh: DHParameters, q: Array, T_flange_point: Array | None = None, h: float = 1e-5
) -> Array:
    """``d Omega / d q`` (6,) by central differences of eq. 14."""
    q = np.asarray(q, float)
    g = np.zeros(6)
    for i in range(6):
        dq = np.zeros(6)
        dq[i] = h
        g[i] = (
            manipulability(jacobian(dh, q + dq, T_flange_point))
            - manipulability(jacobian(dh, q - dq, T_flange_point))
        ) / (2 * h)
    return g


def null_space_projector(J_task: Array, damping: float = 0.0) -> Array:
    """``N = I - J^+ J`` (n, n)."""
    J = np.asarray(J_task, float)
    return np.eye(J.shape[1]) - pinv(J, damping) @ J


def null_space_velocity(
    dh: DHParameters,
    q: Array,
    J_task: Array,
    gain: float,
    T_flange_point: Array | None = None,
) -> Array:
    """Eq. 13's ``N qdot_0`` with ``qdot_0 = gain * grad Omega`` (rad/s, (6,))."""
    return null_space_projector(J_task) @ (gain * manipulability_gradient(dh, q, T_flange_point))
