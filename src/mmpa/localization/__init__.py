"""Localization (paper 001 §3.1): maps, reflectors, trilateration, AMCL, enhanced AMCL.

Build a localizer with :func:`mmpa.localization.localizer.make_localizer` (methods:
``amcl``, ``enhanced``, ``enhanced-paper``, ``trilateration``, ``tamcl``, ``hector``).
"""

from mmpa.localization.amcl import AMCL, AMCLConfig, PoseEstimate
from mmpa.localization.enhanced import EnhancedAMCL, EnhancedConfig
from mmpa.localization.localizer import METHODS, Localizer, make_localizer
from mmpa.maps.map_server import load_map, save_map
from mmpa.maps.occupancy import OccupancyGrid

__all__ = [
    "AMCL",
    "METHODS",
    "AMCLConfig",
    "EnhancedAMCL",
    "EnhancedConfig",
    "Localizer",
    "OccupancyGrid",
    "PoseEstimate",
    "load_map",
    "make_localizer",
    "save_map",
]
