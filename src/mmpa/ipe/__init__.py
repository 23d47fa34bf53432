"""IPE: iterative pose estimation by eye & hand (paper 000 §3.2.2, Fig. 4, eq. 9-11)."""

from mmpa.ipe.core import (
    DEFAULT_ALPHA,
    alpha_vector,
    camera_target,
    converged,
    delta_T_B,
    pose_difference,
    transform_path,
)

__all__ = [
    "DEFAULT_ALPHA",
    "alpha_vector",
    "camera_target",
    "converged",
    "delta_T_B",
    "pose_difference",
    "transform_path",
]
