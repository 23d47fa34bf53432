"""Channel pruning in the spirit of NetAdapt (Yang et al. 2018; paper 001 §4.3.2).

NetAdapt shrinks a trained network step by step toward a resource budget: at each step, for
every layer it proposes the network with that layer's output channels reduced just enough to
save ``step_fraction`` of the resource, keeps the filters of largest magnitude (L1 norm of the
conv filter times the BatchNorm scale), briefly fine-tunes each proposal
(``short_term_batches``), measures its accuracy on held-out data (here: the multibox loss on a
validation split, lower is better) and keeps the best proposal; when the budget is met the
result is fine-tuned longer. The resource here is the multiply-accumulate count (MACs) of one
320x240 frame, computed analytically (proportional to CPU latency for this plain conv net).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import torch
from pydantic import BaseModel, ConfigDict, Field

from mmpa.perception.dataset import Dataset
from mmpa.perception.ssd import (
    SSD,
    STRIDES,
    TAPS,
    SSDConfig,
    boxes_per_cell,
    feature_sizes,
    image_tensor,
    multibox_loss,
)
from mmpa.perception.train import TrainConfig, _targets, train

__all__ = ["PruneConfig", "PruneStep", "macs", "netadapt", "prune_layer"]


class PruneConfig(BaseModel):
    model_config = ConfigDict(extra="forbid")
    target_ratio: float = Field(0.5, gt=0, lt=1)  # keep this fraction of the MACs
    step_fraction: float = Field(0.12, gt=0, lt=1)  # MACs saved per step
    short_term_batches: int = Field(8, ge=0)
    val_images: int = Field(96, ge=8)
    long_term_epochs: int = Field(1, ge=0)
    min_channels: int = Field(8, ge=1)
    seed: int = Field(0, ge=0)  # every random draw flows from it (numpy: >= 0)
    threads: int = 2


def _spatial(cfg: SSDConfig) -> list[tuple[int, int]]:
    h, w = cfg.height, cfg.width
    out = []
    for s in STRIDES:
        h, w = (h + 2 - 3) // s + 1, (w + 2 - 3) // s + 1
        out.append((h, w))
    return out


def macs(cfg: SSDConfig) -> int:
    """Multiply-accumulates of one forward pass (convolutions and heads)."""
    total, cin = 0, 3
    sp = _spatial(cfg)
    for (h, w), c in zip(sp, cfg.channels, strict=True):
        total += h * w * cin * c * 9
        cin = c
    n_out = boxes_per_cell(cfg) * (4 + len(cfg.classes) + 1)
    for (h, w), t in zip(feature_sizes(cfg), TAPS, strict=True):
        total += h * w * cfg.channels[t] * n_out * 9
    return int(total)


def _importance(model: SSD, i: int) -> np.ndarray:
    conv, bn = model.layers[i][0], model.layers[i][1]
    l1 = conv.weight.detach().abs().sum((1, 2, 3)).numpy()
    return l1 * bn.weight.detach().abs().numpy()


def prune_layer(model: SSD, i: int, keep: int) -> SSD:
    """A copy of ``model`` with layer ``i`` keeping its ``keep`` most important channels."""
    cfg = model.cfg
    idx = np.sort(np.argsort(-_importance(model, i))[:keep])
    ch = list(cfg.channels)
    ch[i] = keep
    new = SSD(cfg.model_copy(update={"channels": tuple(ch)}))
    sd_old = model.state_dict()
    sd = new.state_dict()
    ti = torch.as_tensor(idx)
    for k in sd:
        v = sd_old[k]
        if k.startswith(f"layers.{i}."):
            v = v[ti] if v.ndim >= 1 and v.shape[0] == cfg.channels[i] else v
        elif k.startswith(f"layers.{i + 1}.0.weight"):
            v = v[:, ti]
        elif i in TAPS and k == f"heads.{TAPS.index(i)}.weight":
            v = v[:, ti]
        sd[k] = v.clone()
    new.load_state_dict(sd)
    return new


@torch.no_grad()
def _val_loss(model: SSD, data: Dataset) -> float:
    model.eval()
    tot = 0.0
    for s in range(0, len(data), 16):
        idx = range(s, min(s + 16, len(data)))
        loc_t, lab_t = _targets(
            [data.boxes[i] for i in idx],
            [data.labels[i] for i in idx],
            model.priors,
            model.cfg.width,
            model.cfg.height,
        )
        loc, conf = model(image_tensor(data.images[list(idx)]))
        a, b = multibox_loss(loc, conf, loc_t, lab_t)
        tot += float(a + b) * len(idx)
    return tot / len(data)


@dataclass
class PruneStep:
    layer: int
    channels: tuple[int, ...]
    macs: int
    val_loss: float


def netadapt(
    model: SSD,
    data: Dataset,
    cfg: PruneConfig | None = None,
    log: Callable[[str], None] | None = None,
) -> tuple[SSD, list[PruneStep]]:
    """Prune ``model`` to ``target_ratio`` of its MACs; returns the model and the steps."""
    cfg = cfg or PruneConfig()
    torch.set_num_threads(cfg.threads)
    rng = np.random.default_rng(cfg.seed)
    perm = rng.permutation(len(data))
    val = data.subset(perm[: cfg.val_images])
    tr = data.subset(perm[cfg.val_images :])
    m0 = macs(model.cfg)
    budget = cfg.target_ratio * m0
    steps: list[PruneStep] = []
    cur = model
    while macs(cur.cfg) > budget:
        need = cfg.step_fraction * m0
        best = None
        for i in range(len(STRIDES)):
            c = cur.cfg.channels[i]
            # channels to drop so that this layer alone saves `need` MACs
            per = macs(cur.cfg) - macs(
                cur.cfg.model_copy(
                    update={
                        "channels": tuple(
                            cur.cfg.channels[j] - (1 if j == i else 0) for j in range(len(STRIDES))
                        )
                    }
                )
            )
            drop = int(np.ceil(need / max(per, 1)))
            keep = max(c - drop, cfg.min_channels)
            if keep >= c:
                continue
            cand = prune_layer(cur, i, keep)
            if cfg.short_term_batches:
                sub = tr.subset(rng.choice(len(tr), 16 * cfg.short_term_batches, replace=False))
                cand = train(
                    sub,
                    TrainConfig(epochs=1, lr=5e-4, seed=cfg.seed, threads=cfg.threads),
                    model=cand,
                ).model
            loss = _val_loss(cand, val)
            if log:
                log(f"  layer {i}: {c} -> {keep} channels, val loss {loss:.3f}")
            if best is None or loss < best[0]:
                best = (loss, i, cand)
        if best is None:
            break
        loss, i, cur = best
        steps.append(PruneStep(i, cur.cfg.channels, macs(cur.cfg), loss))
        if log:
            log(
                f"step {len(steps)}: pruned layer {i} -> {cur.cfg.channels}, "
                f"{macs(cur.cfg) / m0:.2f} of the MACs, val loss {loss:.3f}"
            )
    if cfg.long_term_epochs:
        cur = train(
            tr,
            TrainConfig(epochs=cfg.long_term_epochs, lr=1e-3, seed=cfg.seed, threads=cfg.threads),
            model=cur,
            log=log,
        ).model
    return cur, steps
