"""``mmpa perception``: render a labelled data set in the twin, train, prune and evaluate the
object detector (paper 001 §3.2.1). The detector's modules need the optional extra
``perception`` (PyTorch): they are imported inside the functions that use them."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from typing import Any

from mmpa.harness.perception_data import (
    Dataset,
    DatasetConfig,
    load_dataset,
    render_dataset,
    save_dataset,
)
from mmpa.perception import require_torch

__all__ = ["evaluate_detector", "prune_detector", "render", "train_detector"]

Log = Callable[[str], None]


def render(cfg: DatasetConfig, out: Path, log: Log) -> Dataset:
    """Render the data set ``cfg`` in the twin and save it to ``out`` (.npz)."""
    ds = render_dataset(cfg, log=log)
    save_dataset(ds, out)
    return ds


def train_detector(
    out: Path,
    data: list[Path] | None,
    n: int,
    seed: int,
    train_settings: dict[str, Any],
    init: Path | None,
    val: Path | None,
    log: Log,
) -> None:
    """Train the SSD on ``data`` (.npz files; None: ``n`` images rendered from ``seed``) with
    :class:`~mmpa.perception.train.TrainConfig` ``train_settings`` (``seed`` added), from the
    weights ``init`` when given; save to ``out`` after every epoch; with ``val``, choose the
    operating score threshold (max F1 on it)."""
    require_torch()
    from mmpa.perception.ssd import Detector
    from mmpa.perception.train import TrainConfig, choose_threshold, train

    ds = (
        Dataset.concat([load_dataset(p) for p in data])
        if data
        else render_dataset(DatasetConfig(n_images=n, seed=seed))
    )
    cfg = TrainConfig(seed=seed, **train_settings)
    model = Detector.load(init).model.train() if init else None
    out.parent.mkdir(parents=True, exist_ok=True)
    det = train(ds, cfg, model=model, log=log, on_epoch=lambda d: d.save(out))
    det.meta["data"] = [str(p) for p in data] if data else f"rendered n={n} seed={seed}"
    det.meta["train_config"] = cfg.model_dump(mode="json")
    if init:
        det.meta["fine_tuned_from"] = str(init)
    if val:
        th, table = choose_threshold(det, load_dataset(val), threads=cfg.threads)
        det.cfg.score_threshold = th
        det.meta["threshold_choice"] = {"val": str(val), "recall_precision": table}
        log(f"operating threshold {th:.2f} (max F1 on {val})")
    det.save(out)


def prune_detector(
    out: Path, data: list[Path], weights: Path | None, prune_settings: dict[str, Any], log: Log
) -> tuple[list[int], float]:
    """NetAdapt-style channel pruning of the detector ``weights`` (None: shipped) on ``data``
    with :class:`~mmpa.perception.prune.PruneConfig` ``prune_settings``; saved to ``out``.
    Returns the pruned channels and the share of the MACs kept."""
    require_torch()
    from mmpa.perception.prune import PruneConfig, macs, netadapt
    from mmpa.perception.ssd import Detector

    det = Detector.load(weights)
    ds = Dataset.concat([load_dataset(p) for p in data])
    cfg = PruneConfig(**prune_settings)
    model, steps = netadapt(det.model, ds, cfg, log=log)
    m0 = macs(det.cfg)
    pruned = Detector(
        model,
        {
            "pruned_from": str(weights or "shipped"),
            "data": [str(p) for p in data],
            "prune_config": cfg.model_dump(mode="json"),
            "macs_ratio": macs(model.cfg) / m0,
            "steps": [[s.layer, list(s.channels), s.macs, s.val_loss] for s in steps],
        },
    )
    out.parent.mkdir(parents=True, exist_ok=True)
    pruned.save(out)
    return list(model.cfg.channels), macs(model.cfg) / m0


def evaluate_detector(
    weights: Path | None,
    data: Path | None,
    n: int,
    seed: int,
    preprocess_dark: bool,
    threshold: float | None,
) -> tuple[Any, int]:
    """Per-class AP@0.5 and detection success per lighting of the detector ``weights`` (None:
    shipped) on ``data`` (None: ``n`` images rendered from ``seed``). Returns the
    :class:`~mmpa.perception.train` evaluation result and the number of images."""
    require_torch()
    from mmpa.perception.ssd import Detector
    from mmpa.perception.train import evaluate

    det = Detector.load(weights)
    ds = load_dataset(data) if data else render_dataset(DatasetConfig(n_images=n, seed=seed))
    res = evaluate(det, ds, preprocess_dark=preprocess_dark, threshold=threshold)
    return res, len(ds)
