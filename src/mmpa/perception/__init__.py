"""Object detection and 3D location from the wrist RGB-D camera (paper 001 §3.2.1).

- :mod:`.ssd`: a small single-shot multibox detector (PyTorch, CPU), default boxes, box
  coding, multibox loss with hard negative mining, non-maximum suppression;
- :mod:`.preprocess`: the paper's dark-scene preprocessing (histogram equalization, edge
  enhancement, mean filter) in numpy/scipy;
- :mod:`.locate`: box center + depth -> camera frame -> ``arm_base``; grasp axis;
- :mod:`.prune`: channel pruning in the spirit of NetAdapt;
- :mod:`.dataset` / :mod:`.train`: training data rendered by the twin, training, evaluation.

Shipped weights (``weights/``): ``ssd.pt`` (the default), ``ssd_pruned.pt`` (NetAdapt-pruned
from ``ssd.pt``) and ``ssd_workview.pt`` (``ssd.pt`` fine-tuned one epoch on 2500 images, 60 %
working views: better on the robot's pre-grasp view, target detected 0.980 / 0.995 / 0.975 in
dark / normal / high light vs 0.944 / 0.980 / 0.970, but worse on random views, mAP 0.904 vs
0.931; pass it as ``weights`` to the grasp experiments to use it).

PyTorch is an optional extra (``pip install mmpa[perception]``): the core package imports
without it, and :func:`require_torch` names the extra when it is missing.
"""

from __future__ import annotations

from types import ModuleType

from mmpa.errors import MMPAError

__all__ = ["CLASSES", "LIGHTING_CONDITIONS", "require_torch"]

# The seven objects of paper 001 Fig. 11 (names of the bodies in the default scene).
CLASSES: tuple[str, ...] = (
    "cube",
    "tennis_ball",
    "yida_bottle",
    "water_bottle",
    "paper_cup",
    "glue_stick",
    "blue_stick",
)
# Paper 001 Table 3's light conditions.
LIGHTING_CONDITIONS: tuple[str, ...] = ("dark", "normal", "high")


def require_torch() -> ModuleType:
    """Import and return ``torch``; a clear error naming the extra when it is missing."""
    try:
        import torch
    except ImportError as e:  # pragma: no cover - depends on the environment
        raise MMPAError(
            "the object detector needs PyTorch: install the extra with "
            "`pip install -e '.[perception]'` (CPU build: torch==2.13.0)"
        ) from e
    return torch
