"""Colored point cloud global registration (paper 000 §3.2.2 II): FPFH + FGR, colored ICP.

``register(source, target, cfg, init=None) -> Registration`` estimates ``T_target_source``
(``p_target = T p_source``); ``prepare`` preprocesses a cloud once for reuse. See
:mod:`mmpa.registration.pipeline` for the method and :class:`RegistrationConfig` for the
parameters (:meth:`RegistrationConfig.paper`: the paper's own settings). ``refine_projective``
refines a close pose at full resolution against an organized depth image
(:mod:`mmpa.registration.projective`).
"""

from mmpa.registration.checks import information_matrix
from mmpa.registration.config import IcpScale, ProjectiveConfig, RegistrationConfig
from mmpa.registration.pipeline import Registration, register
from mmpa.registration.preprocess import Prepared, prepare
from mmpa.registration.projective import ProjectiveResult, refine_projective
from mmpa.registration.projective_maps import normal_map, robust_weights, vertex_map

__all__ = [
    "IcpScale",
    "Prepared",
    "ProjectiveConfig",
    "ProjectiveResult",
    "Registration",
    "RegistrationConfig",
    "information_matrix",
    "normal_map",
    "prepare",
    "refine_projective",
    "register",
    "robust_weights",
    "vertex_map",
]
