"""IPE math (paper 000 §3.2.2-3.2.3), pure functions over 4x4 transforms.

Notation (DESIGN.md): ``T_Bo_Co`` is the camera pose in the arm base at teaching (eq. 1),
``T_Bk_Ck`` the camera pose in the arm base after the k-th arm movement (eq. 2, from the nominal
forward kinematics and hand-eye transform), ``dT_C`` the registration result with
``p_Ck = dT_C p_Co`` (eq. 3) and ``dT_B`` the relative parking pose of the arm base with
``p_Bk = dT_B p_Bo`` (eq. 4).
"""

from __future__ import annotations

import numpy as np

from mmpa.core.errors import InvalidInputError
from mmpa.core.geometry import Array, T_to_vec6, as_transform, inv

__all__ = [
    "DEFAULT_ALPHA",
    "alpha_vector",
    "camera_target",
    "converged",
    "delta_T_B",
    "pose_difference",
    "transform_path",
]

#: paper 000 §4.3: (2 mm, 2 mm, 2 mm, 0.5°, 0.5°, 0.5°) as (m, m, m, rad, rad, rad)
DEFAULT_ALPHA: tuple[float, ...] = (0.002, 0.002, 0.002, *np.deg2rad([0.5, 0.5, 0.5]).tolist())


def delta_T_B(T_Bk_Ck: Array, dT_C: Array, T_Bo_Co: Array) -> Array:
    """Relative parking pose of the arm base, eq. 9-10 in matrix form.

    ``dT_B = T_Bk_Ck @ dT_C @ inv(T_Bo_Co)``: the rotation block is eq. 9
    (``R_Bk^Ck dR_Ck R_Bo^Co^-1``) and the translation block eq. 10
    (``-R_Bk^Ck dR_Ck R_Bo^Co^-1 t_Bo^Co + R_Bk^Ck dt_Ck + t_Bk^Ck``). All 4x4.
    """
    T_Bk_Ck = as_transform(T_Bk_Ck, "T_Bk_Ck")
    dT_C = as_transform(dT_C, "dT_C")
    T_Bo_Co = as_transform(T_Bo_Co, "T_Bo_Co")
    return T_Bk_Ck @ dT_C @ inv(T_Bo_Co)


def camera_target(dT_B: Array, T_Bo_Co: Array) -> Array:
    """Next sampling pose of the camera in the current arm base, ``dT_B @ T_Bo_Co`` (4x4).

    With ``dT_B`` exact this puts the camera back at its taught pose in the world (Fig. 3):
    a world point seen at ``p_Co`` at teaching is at ``p_Bk = dT_B T_Bo_Co p_Co`` now.
    """
    return as_transform(dT_B, "dT_B") @ as_transform(T_Bo_Co, "T_Bo_Co")


def pose_difference(dT: Array) -> Array:
    """``|[tx, ty, tz, roll, pitch, yaw]|`` of a relative pose (m, rad), shape (6,)."""
    return np.abs(T_to_vec6(as_transform(dT, "dT")))


def alpha_vector(alpha: tuple[float, ...] | Array) -> Array:
    """Check a convergence threshold ``alpha`` (6 positive values, m and rad)."""
    a = np.asarray(alpha, dtype=float).reshape(-1)
    if a.shape != (6,) or not np.all(np.isfinite(a)) or np.any(a <= 0):
        raise InvalidInputError(
            f"alpha must be 6 positive thresholds (m, m, m, rad, rad, rad), got {a}"
        )
    return a


def converged(dT_C: Array, alpha: tuple[float, ...] | Array) -> bool:
    """Fig. 4's exit test: every component of the camera pose difference below ``alpha``."""
    return bool(np.all(pose_difference(dT_C) < alpha_vector(alpha)))


def transform_path(dT_B: Array, T_Bo_tool: Array) -> Array:
    """Adaptive path learning, eq. 11 applied to whole tool poses.

    ``T_Bk_tool[i] = dT_B @ T_Bo_tool[i]``; ``T_Bo_tool`` has shape (N, 4, 4); returns (N, 4, 4).
    The translation part is exactly eq. 11 (``S_Bk = dR_Bk S_Bo + dt_Bk``); the rotation part
    carries the tool orientation along so that the tool meets the work piece as taught.
    """
    dT_B = as_transform(dT_B, "dT_B")
    P = np.asarray(T_Bo_tool, dtype=float)
    if P.ndim != 3 or P.shape[1:] != (4, 4) or not np.all(np.isfinite(P)):
        raise InvalidInputError(f"T_Bo_tool must be finite (N, 4, 4) poses, got {P.shape}")
    return np.einsum("ij,njk->nik", dT_B, P)
