"""The localization node's tf buffer (pure numpy, no ``rclpy``): its interpolation between two
stamps against the SE(3) geodesic computed independently (``R0 exp(s log(R0^T R1))`` through
:func:`mmpa.core.geometry.exp_se3` / ``log_se3``, the buffer's former code path), in 3D and in
the regimes where the closed form could go wrong (tiny turns, near a half turn)."""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

from mmpa.backends.ros2.tf_buffer import TfBuffer, _interpolate
from mmpa.core.geometry import exp_se3, log_se3, make_T, se2_to_T


def _geodesic(T0: np.ndarray, T1: np.ndarray, s: float) -> np.ndarray:
    R0, R1 = np.eye(4), np.eye(4)
    R0[:3, :3], R1[:3, :3] = T0[:3, :3], T1[:3, :3]
    out = R0 @ exp_se3(s * log_se3(R0.T @ R1))
    out[:3, 3] = (1 - s) * T0[:3, 3] + s * T1[:3, 3]
    return out


def test_interpolation_is_the_geodesic_in_3d() -> None:
    rng = np.random.default_rng(0)
    for angle in (0.0, 1e-9, 1e-4, 0.3, 1.5, 2.6, 2.8, 3.1, np.pi - 1e-6):
        for _ in range(20):
            R0 = Rotation.random(random_state=int(rng.integers(1 << 31))).as_matrix()
            axis = rng.normal(size=3)
            R1 = R0 @ Rotation.from_rotvec(angle * axis / np.linalg.norm(axis)).as_matrix()
            T0, T1 = make_T(R0, rng.normal(size=3)), make_T(R1, rng.normal(size=3))
            s = float(rng.uniform())
            got = _interpolate(T0, T1, s)
            np.testing.assert_allclose(got, _geodesic(T0, T1, s), atol=1e-12)
            # a rotation turned by s * angle from R0 about the relative axis
            turned = Rotation.from_matrix(R0.T @ got[:3, :3]).magnitude()
            np.testing.assert_allclose(turned, s * angle, atol=1e-7)


def test_the_stamps_themselves_are_returned_exactly() -> None:
    b = TfBuffer()
    A, B = se2_to_T(1.0, 0.0, 0.0), se2_to_T(2.0, 1.0, 0.4)
    b.set(1.0, "odom", "base_link", A)
    b.set(2.0, "odom", "base_link", B)
    np.testing.assert_array_equal(b.lookup("odom", "base_link", 2.0), B)
    np.testing.assert_array_equal(b.lookup("odom", "base_link", 1.0), A)
    mid = b.lookup("odom", "base_link", 1.75)
    np.testing.assert_allclose(mid, se2_to_T(1.75, 0.75, 0.3), atol=1e-12)
