"""Training and evaluation of the detector on rendered data (``mmpa perception train``).

Training: Adam with a one-cycle learning-rate schedule, mini-batches of rendered images with
augmentation (random crop-and-zoom, horizontal flip; brightness, contrast and per-channel gain
jitter), the SSD multibox loss; optionally fine-tuning a trained model.

Evaluation on a separately seeded set: per-class average precision at IoU 0.5 (VOC all-point
interpolation); detection success per lighting condition (a labelled object counts as detected
when a detection of its class with IoU >= 0.5 scores above the operating threshold), over every
labelled object of every image (random views: many objects cut by the image border) and, on
working views, over the target object (paper 001 Table 3's definition: the target detected in
the robot's working view). The operating threshold is chosen on a validation set
(:func:`choose_threshold`). Torch runs with ``threads`` CPU threads.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np
import torch
from pydantic import BaseModel, ConfigDict, Field

from mmpa.perception import CLASSES, LIGHTING_CONDITIONS
from mmpa.perception.dataset import Dataset
from mmpa.perception.locate import box_iou
from mmpa.perception.preprocess import dark_preprocess
from mmpa.perception.ssd import (
    SSD,
    Detection,
    Detector,
    SSDConfig,
    image_tensor,
    match,
    multibox_loss,
)

__all__ = [
    "EvalResult",
    "TrainConfig",
    "average_precision",
    "choose_threshold",
    "crop_zoom",
    "detect_all",
    "evaluate",
    "recall_precision",
    "train",
]


class TrainConfig(BaseModel):
    model_config = ConfigDict(extra="forbid")
    epochs: int = Field(12, ge=1)
    batch_size: int = Field(16, ge=1)
    lr: float = Field(2e-3, gt=0)
    weight_decay: float = Field(1e-4, ge=0)
    seed: int = Field(0, ge=0)  # every random draw flows from it (numpy: >= 0)
    threads: int = Field(2, ge=1)
    max_minutes: float | None = None  # stop early (at an epoch's end) past this time
    dark_preprocess_prob: float = Field(0.0, ge=0, le=1)  # train on preprocessed dark images
    crop_prob: float = Field(0.0, ge=0, le=1)  # random crop-and-zoom (see :func:`augment`)


def crop_zoom(
    img: np.ndarray, boxes: np.ndarray, labels: np.ndarray, rng: np.random.Generator
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Random crop of ``s`` = U(0.6, 1) of each image side, resized back (nearest) to the
    image size: objects look up to 1/0.6 = 1.7x larger and more of them are cut by the border.
    Boxes (K, 4) are shifted, scaled and clipped to the image (a label is the VISIBLE extent);
    boxes keeping less than a quarter of their area or under 2 px a side are dropped."""
    h, w = img.shape[:2]
    s = rng.uniform(0.6, 1.0)
    cw, ch = round(s * w), round(s * h)
    x0, y0 = int(rng.integers(0, w - cw + 1)), int(rng.integers(0, h - ch + 1))
    rows = y0 + np.minimum((np.arange(h) + 0.5) * ch / h, ch - 1).astype(int)
    cols = x0 + np.minimum((np.arange(w) + 0.5) * cw / w, cw - 1).astype(int)
    out = img[rows][:, cols]
    b = (boxes - np.array([x0, y0, x0, y0], np.float32)) * np.array(
        [w / cw, h / ch, w / cw, h / ch], np.float32
    )
    area0 = (b[:, 2] - b[:, 0]) * (b[:, 3] - b[:, 1])
    b = np.clip(b, 0, [w, h, w, h]).astype(np.float32)
    wh = b[:, 2:] - b[:, :2]
    keep = (wh.min(1) >= 2) & (wh.prod(1) >= 0.25 * np.maximum(area0, 1e-9))
    return out, b[keep], labels[keep]


def augment(
    img: np.ndarray, boxes: np.ndarray, rng: np.random.Generator
) -> tuple[np.ndarray, np.ndarray]:
    """Horizontal flip (p = 0.5) and photometric jitter of one (H, W, 3) uint8 image."""
    w = img.shape[1]
    if rng.random() < 0.5:
        img = img[:, ::-1]
        boxes = boxes.copy()
        boxes[:, [0, 2]] = w - boxes[:, [2, 0]]
    f = img.astype(np.float32)
    gain = rng.uniform(0.7, 1.3) * rng.uniform(0.9, 1.1, 3)
    mean = f.mean()
    f = (f - mean) * rng.uniform(0.75, 1.25) + mean
    f = f * gain + rng.uniform(-15, 15)
    return np.clip(f, 0, 255).astype(np.uint8), boxes


def _targets(
    boxes: list[np.ndarray], labels: list[np.ndarray], priors: torch.Tensor, w: int, h: int
) -> tuple[torch.Tensor, torch.Tensor]:
    scale = torch.tensor([w, h, w, h], dtype=torch.float32)
    locs, labs = [], []
    for b, lab in zip(boxes, labels, strict=True):
        lt, ct = match(torch.from_numpy(b).float() / scale, torch.from_numpy(lab).long(), priors)
        locs.append(lt)
        labs.append(ct)
    return torch.stack(locs), torch.stack(labs)


def train(
    data: Dataset,
    cfg: TrainConfig | None = None,
    model_cfg: SSDConfig | None = None,
    model: SSD | None = None,
    log: Callable[[str], None] | None = None,
    on_epoch: Callable[[Detector], None] | None = None,
) -> Detector:
    """Train (or fine-tune ``model``) on ``data``; returns the detector. ``on_epoch`` gets
    the detector after every epoch (checkpoints)."""
    cfg = cfg or TrainConfig()
    torch.set_num_threads(cfg.threads)
    torch.manual_seed(cfg.seed)
    rng = np.random.default_rng(cfg.seed)
    model = model if model is not None else SSD(model_cfg or SSDConfig())
    mc = model.cfg
    opt = torch.optim.Adam(model.parameters(), lr=cfg.lr, weight_decay=cfg.weight_decay)
    n = len(data)
    steps = cfg.epochs * max(n // cfg.batch_size, 1)
    sched = torch.optim.lr_scheduler.OneCycleLR(opt, cfg.lr, total_steps=steps, pct_start=0.1)
    t0 = time.time()
    step = 0
    history = []
    for epoch in range(cfg.epochs):
        model.train()
        perm = rng.permutation(n)
        tot = np.zeros(2)
        nb = 0
        for s in range(0, n - cfg.batch_size + 1, cfg.batch_size):
            idx = perm[s : s + cfg.batch_size]
            imgs, bxs, lbs = [], [], []
            for i in idx:
                im, b, lab = data.images[i], data.boxes[i], data.labels[i]
                if data.lighting[i] == 0 and rng.random() < cfg.dark_preprocess_prob:
                    im = dark_preprocess(im)
                if cfg.crop_prob > 0 and rng.random() < cfg.crop_prob:
                    im, b, lab = crop_zoom(im, b, lab, rng)
                im, b = augment(im, b, rng)
                imgs.append(im)
                bxs.append(b)
                lbs.append(lab)
            loc_t, lab_t = _targets(bxs, lbs, model.priors, mc.width, mc.height)
            loc, conf = model(image_tensor(np.stack(imgs)))
            l_loc, l_conf = multibox_loss(loc, conf, loc_t, lab_t)
            loss = l_loc + l_conf
            opt.zero_grad()
            loss.backward()
            opt.step()
            if step < steps - 1:
                sched.step()
            step += 1
            tot += [l_loc.item(), l_conf.item()]
            nb += 1
            if log and nb % 20 == 0:
                log(
                    f"epoch {epoch + 1}/{cfg.epochs} batch {nb} loc {tot[0] / nb:.3f} "
                    f"conf {tot[1] / nb:.3f} ({time.time() - t0:.0f} s)"
                )
        history.append((tot / max(nb, 1)).tolist())
        if log:
            log(f"epoch {epoch + 1} done: loc {history[-1][0]:.3f} conf {history[-1][1]:.3f}")
        if on_epoch is not None:
            model.eval()
            on_epoch(Detector(model, {"epochs_run": len(history), "loss_history": history}))
        if cfg.max_minutes is not None and time.time() - t0 > 60 * cfg.max_minutes:
            if log:
                log("time budget reached, stopping")
            break
    model.eval()
    meta = {
        "epochs_run": len(history),
        "loss_history": history,
        "train_images": n,
        "train_seconds": round(time.time() - t0, 1),
    }
    return Detector(model, meta)


def average_precision(tp: np.ndarray, scores: np.ndarray, n_gt: int) -> float:
    """VOC all-point interpolated AP from detections' true-positive flags and scores."""
    if n_gt == 0:
        return float("nan")
    if len(tp) == 0:
        return 0.0
    order = np.argsort(-scores, kind="stable")
    tp = np.asarray(tp, float)[order]
    ctp, cfp = np.cumsum(tp), np.cumsum(1 - tp)
    rec = ctp / n_gt
    prec = ctp / np.maximum(ctp + cfp, 1e-12)
    mrec = np.concatenate([[0.0], rec, [1.0]])
    mpre = np.concatenate([[0.0], prec, [0.0]])
    for i in range(len(mpre) - 2, -1, -1):
        mpre[i] = max(mpre[i], mpre[i + 1])
    i = np.nonzero(mrec[1:] != mrec[:-1])[0]
    return float(np.sum((mrec[i + 1] - mrec[i]) * mpre[i + 1]))


@dataclass
class EvalResult:
    """``ap``: per-class AP@0.5; ``success``: detection success per lighting condition and
    class (fraction of labelled objects found at the operating threshold); ``precision`` of
    the detections at that threshold per lighting; ``ms_per_image`` inference time."""

    ap: dict[str, float]
    mean_ap: float
    success: dict[str, dict[str, float]]
    success_all: dict[str, float]
    precision: dict[str, float]
    ms_per_image: float
    counts: dict[str, dict[str, int]] = field(default_factory=dict)
    threshold: float = float("nan")
    # working views (Dataset.target >= 0): the target detected (its class, IoU >= 0.5, score
    # >= threshold) per lighting and class, over all working views (a target hidden behind
    # another object or out of the view counts as a miss; ``work_hidden`` counts those)
    work_success: dict[str, dict[str, float]] = field(default_factory=dict)
    work_success_all: dict[str, float] = field(default_factory=dict)
    work_counts: dict[str, dict[str, int]] = field(default_factory=dict)
    work_hidden: int = 0


def _tp_flags(dets: list[Detection], gt_b: np.ndarray, gt_l: np.ndarray, c: int) -> list[int]:
    g = gt_b[gt_l == c]
    d = [x for x in dets if x.label == c]
    used = np.zeros(len(g), bool)
    flags = []
    for x in d:  # dets are sorted by score
        if len(g):
            iou = box_iou(x.box[None], g)[0]
            j = int(np.argmax(iou))
            if iou[j] >= 0.5 and not used[j]:
                used[j] = True
                flags.append(1)
                continue
        flags.append(0)
    return flags


def detect_all(
    det: Detector, data: Dataset, preprocess_dark: bool = False, batch: int = 16, low: float = 0.02
) -> tuple[list[list[Detection]], float]:
    """Detections (score >= ``low``) on every image of ``data`` and the ms per image."""
    out: list[list[Detection]] = []
    t0 = time.perf_counter()
    for s in range(0, len(data), batch):
        imgs = data.images[s : s + batch]
        if preprocess_dark:
            imgs = np.stack(
                [
                    dark_preprocess(im) if data.lighting[s + k] == 0 else im
                    for k, im in enumerate(imgs)
                ]
            )
        out += det.detect_batch(imgs, score_threshold=low)
    return out, 1000 * (time.perf_counter() - t0) / max(len(data), 1)


def recall_precision(
    low: list[list[Detection]], data: Dataset, threshold: float, n_classes: int
) -> tuple[float, float]:
    """Object-level recall (labelled objects detected, class and IoU >= 0.5) and precision
    (detections matching a labelled object) at ``threshold``."""
    hit = n_det = n_gt = 0
    for dets, b, lab in zip(low, data.boxes, data.labels, strict=True):
        d = [x for x in dets if x.score >= threshold]
        for c in range(n_classes):
            f = _tp_flags(d, b, lab, c)
            hit += sum(f)
            n_det += len(f)
        n_gt += len(lab)
    return hit / max(n_gt, 1), hit / max(n_det, 1)


def choose_threshold(
    det: Detector, val: Dataset, grid: np.ndarray | None = None, threads: int = 2
) -> tuple[float, list[tuple[float, float, float]]]:
    """The operating score threshold: the one of ``grid`` (default 0.10, 0.15, ..., 0.80)
    that maximizes the object-level F1 = 2 R P / (R + P) on a VALIDATION set (never the test
    set). Returns it and ``(threshold, recall, precision)`` per grid value."""
    torch.set_num_threads(threads)
    grid = np.round(np.arange(0.10, 0.801, 0.05), 2) if grid is None else np.asarray(grid)
    low, _ = detect_all(det, val)
    table = [(float(t), *recall_precision(low, val, float(t), len(det.cfg.classes))) for t in grid]
    f1 = [2 * r * p / max(r + p, 1e-12) for _, r, p in table]
    return table[int(np.argmax(f1))][0], table


def evaluate(
    det: Detector,
    data: Dataset,
    preprocess_dark: bool = False,
    batch: int = 16,
    threads: int = 2,
    threshold: float | None = None,
) -> EvalResult:
    """Per-class AP and detection success per lighting on ``data`` at ``threshold``
    (default: the detector's operating threshold)."""
    torch.set_num_threads(threads)
    classes = det.cfg.classes
    low, ms = detect_all(det, data, preprocess_dark, batch)
    th = det.cfg.score_threshold if threshold is None else threshold
    ap = {}
    for c, name in enumerate(classes):
        tps, scs, n_gt = [], [], 0
        for dets, b, lab in zip(low, data.boxes, data.labels, strict=True):
            flags = _tp_flags(dets, b, lab, c)
            tps += flags
            scs += [x.score for x in dets if x.label == c]
            n_gt += int((lab == c).sum())
        ap[name] = average_precision(np.array(tps), np.array(scs), n_gt)
    success: dict[str, dict[str, float]] = {}
    success_all, precision, counts = {}, {}, {}
    for li, cond in enumerate(LIGHTING_CONDITIONS):
        sel = np.nonzero(data.lighting == li)[0]
        if sel.size == 0:
            continue
        hit = np.zeros(len(classes))
        tot = np.zeros(len(classes))
        n_det = n_tp = 0
        for i in sel:
            dets = [x for x in low[i] if x.score >= th]
            for c in range(len(classes)):
                f = _tp_flags(dets, data.boxes[i], data.labels[i], c)
                hit[c] += sum(f)
                n_tp += sum(f)
                n_det += len(f)
                tot[c] += int((data.labels[i] == c).sum())
        success[cond] = {
            classes[c]: float(hit[c] / tot[c]) if tot[c] else float("nan")
            for c in range(len(classes))
        }
        counts[cond] = {classes[c]: int(tot[c]) for c in range(len(classes))}
        success_all[cond] = float(hit.sum() / max(tot.sum(), 1))
        precision[cond] = float(n_tp / max(n_det, 1))
    vals = [v for v in ap.values() if np.isfinite(v)]
    res = EvalResult(
        ap=ap,
        mean_ap=float(np.mean(vals)) if vals else float("nan"),
        success=success,
        success_all=success_all,
        precision=precision,
        ms_per_image=ms,
        counts=counts,
        threshold=th,
    )
    _work_view_success(res, low, data, th, classes)
    return res


def _work_view_success(
    res: EvalResult, low: list[list[Detection]], data: Dataset, th: float, classes: tuple
) -> None:
    """Fill ``res.work_*``: target detection success over the working views."""
    tgt = np.asarray(data.target)
    for li, cond in enumerate(LIGHTING_CONDITIONS):
        sel = np.nonzero((data.lighting == li) & (tgt >= 0))[0]
        if sel.size == 0:
            continue
        hit = np.zeros(len(classes))
        tot = np.zeros(len(classes))
        for i in sel:
            c = int(tgt[i])
            tot[c] += 1
            g = data.boxes[i][data.labels[i] == c]
            if len(g) == 0:
                res.work_hidden += 1
                continue
            d = [x for x in low[i] if x.score >= th and x.label == c]
            if d and box_iou(np.array([x.box for x in d]), g).max() >= 0.5:
                hit[c] += 1
        res.work_success[cond] = {
            classes[c]: float(hit[c] / tot[c]) if tot[c] else float("nan")
            for c in range(len(classes))
        }
        res.work_counts[cond] = {classes[c]: int(tot[c]) for c in range(len(classes))}
        res.work_success_all[cond] = float(hit.sum() / max(tot.sum(), 1))


__all__ += ["CLASSES"]
