"""Detector data sets: labelled images (:class:`Dataset`), saved and loaded as ``.npz``.

The twin renders them (:mod:`mmpa.harness.perception_data`: random and working views,
boxes from segmentation rendering); this module holds only the data, so the detector and its
training never import the simulator.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from mmpa.core.errors import ConfigError
from mmpa.core.geometry import Array

__all__ = ["Dataset", "Sample", "load_dataset", "save_dataset"]


@dataclass
class Sample:
    image: np.ndarray  # (H, W, 3) uint8
    boxes: np.ndarray  # (K, 4) float32 [x1, y1, x2, y2] pixels
    labels: np.ndarray  # (K,) int64 class index into CLASSES
    lighting: int  # index into LIGHTING_CONDITIONS


@dataclass
class Dataset:
    """``target``: (N,) class index of the working view's target object, -1 for random views
    (and for data sets saved before working views existed)."""

    images: np.ndarray  # (N, H, W, 3) uint8
    boxes: list[np.ndarray]
    labels: list[np.ndarray]
    lighting: np.ndarray  # (N,) int
    target: np.ndarray | None = None

    def __post_init__(self) -> None:
        if self.target is None:
            self.target = np.full(len(self.images), -1, int)

    def __len__(self) -> int:
        return len(self.images)

    def subset(self, idx: Array) -> Dataset:
        idx = np.asarray(idx, int)
        assert self.target is not None
        return Dataset(
            self.images[idx],
            [self.boxes[i] for i in idx],
            [self.labels[i] for i in idx],
            self.lighting[idx],
            self.target[idx],
        )

    @staticmethod
    def concat(parts: list[Dataset]) -> Dataset:
        return Dataset(
            np.concatenate([p.images for p in parts]),
            [b for p in parts for b in p.boxes],
            [lab for p in parts for lab in p.labels],
            np.concatenate([p.lighting for p in parts]),
            np.concatenate([np.asarray(p.target) for p in parts]),
        )


def save_dataset(ds: Dataset, path: str | Path) -> None:
    n = np.array([len(b) for b in ds.boxes], int)
    np.savez_compressed(
        path,
        images=ds.images,
        boxes=np.concatenate([*ds.boxes, np.zeros((0, 4), np.float32)]),
        labels=np.concatenate([*ds.labels, np.zeros(0, np.int64)]),
        counts=n,
        lighting=ds.lighting,
        target=ds.target,
    )


def load_dataset(path: str | Path) -> Dataset:
    try:
        z = np.load(path)
        counts = z["counts"]
        off = np.concatenate([[0], np.cumsum(counts)])
        boxes, labels = z["boxes"], z["labels"]
        return Dataset(
            z["images"],
            [boxes[off[i] : off[i + 1]] for i in range(len(counts))],
            [labels[off[i] : off[i + 1]] for i in range(len(counts))],
            z["lighting"],
            z["target"] if "target" in z.files else None,
        )
    except (OSError, KeyError, ValueError) as e:
        raise ConfigError(f"cannot read data set {path}: {e}") from None
