"""Object detection and 3D location from the wrist RGB-D camera (paper 001 §3.2.1).

- :mod:`.ssd`: a small single-shot multibox detector (PyTorch, CPU), default boxes, box
  coding, multibox loss with hard negative mining, non-maximum suppression;
- :mod:`.preprocess`: the paper's dark-scene preprocessing (histogram equalization, edge
  enhancement, mean filter) in numpy/scipy;
- :mod:`.locate`: box center + depth -> camera frame -> ``arm_base``; grasp axis;
- :mod:`.prune`: channel pruning in the spirit of NetAdapt;
- :mod:`.dataset` / :mod:`.train`: training data rendered by the twin, training, evaluation.

Shipped weights (``weights/``): ``ssd.pt`` (the default: 12 epochs from scratch on 2400 random
views, ``mmpa perception dataset --out random_s0.npz --n 2400 --seed 0``), ``ssd_pruned.pt``
(NetAdapt-pruned from it) and ``ssd_workview.pt``: ``ssd.pt`` fine-tuned on those random views
and 2400 working views, half of them servo views, high light weighted double::

    mmpa perception dataset --out work_s1.npz --n 2400 --seed 1 --work-view-prob 1 \
        --work-servo-prob 0.5 --lighting dark=1,normal=1,high=2
    mmpa perception train --out ssd_workview.pt --init ssd.pt --data random_s0.npz \
        --data work_s1.npz --epochs 2 --lr 5e-4 --crop-prob 0.3 --seed 2

Measured at the operating threshold 0.3 (``mmpa perception evaluate``, 300 images each,
``ssd.pt`` in brackets): random views (seed 1000) mAP 0.935 (0.933); target detected in working
views (``--work-view-prob 1 --exact-lighting``, seed 3000) dark / normal / high 0.99 / 0.99 /
0.99 (0.96 / 0.98 / 0.96); in servo views (also ``--work-servo-prob 1``, seed 4000) 1.00 / 0.99
/ 0.98 (0.98 / 0.94 / 0.91). In the grasp experiment it is not better: high light, yida bottle,
water bottle, glue stick and blue stick, 20 trials each at seeds 0 and 1, targets detected /
grasped 150 / 147 of 160 vs 148 / 149 with ``ssd.pt`` (fewer lost tracks, but top-down views of
the upright yida bottle, a saturated white disc, go to the paper cup: 34 vs 36 of 40). Pass it
as ``weights`` to the grasp experiments to use it. The weights' ``meta`` records the data and
training configuration.

PyTorch is an optional extra (``pip install mmpa[perception]``): the core package imports
without it, and :func:`require_torch` names the extra when it is missing.
"""

from __future__ import annotations

from types import ModuleType

from mmpa.core.errors import MMPAError

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
