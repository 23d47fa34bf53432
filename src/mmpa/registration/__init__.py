"""Colored point cloud global registration (paper 000 §3.2.2 II): FPFH + FGR, colored ICP.

``register(source, target, cfg, init=None) -> Registration`` estimates ``T_target_source``
(``p_target = T p_source``); ``prepare`` preprocesses a cloud once for reuse. See
:mod:`mmpa.registration.pipeline` for the method and :class:`RegistrationConfig` for the
parameters.
"""

from mmpa.registration.config import IcpScale, RegistrationConfig
from mmpa.registration.pipeline import (
    Prepared,
    Registration,
    information_matrix,
    prepare,
    register,
)

__all__ = [
    "IcpScale",
    "Prepared",
    "Registration",
    "RegistrationConfig",
    "information_matrix",
    "prepare",
    "register",
]
