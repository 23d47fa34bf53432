"""A small single-shot multibox detector (SSD, Liu et al. 2016; paper 001 §3.2.1) in PyTorch.

CPU-friendly: a plain conv backbone (Conv3x3-BN-ReLU layers, ``SSDConfig.channels``) on a
320x240 RGB image, four feature maps (strides 8, 16, 32, 64: 40x30, 20x15, 10x8, 5x4 cells), a
3x3 convolutional head per map predicting, for each default box, 4 box offsets and C + 1 class
scores (0 = background). Default boxes: per cell, ``aspect_ratios`` at the map's size ``s_k``
plus a square of size ``sqrt(s_k s_{k+1})`` (SSD §2.2). Box coding with variances (0.1, 0.2);
multibox loss = smooth-L1 localization on positives + softmax confidence with hard negative
mining (3 negatives per positive), both over the number of positives (SSD eq. 1-3).

Boxes are ``[x1, y1, x2, y2]``; the network works in coordinates normalized by the image size.
Non-maximum suppression is greedy per class (numpy, :func:`nms`). Torch is imported lazily by
callers through :func:`mmpa.perception.require_torch`; this module needs it at import.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from importlib import resources
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F  # noqa: N812
from pydantic import BaseModel, ConfigDict, Field
from torch import nn

from mmpa.core.errors import ConfigError, InvalidInputError
from mmpa.perception import CLASSES

__all__ = [
    "SSD",
    "Detection",
    "Detector",
    "SSDConfig",
    "box_iou",
    "decode",
    "default_boxes",
    "encode",
    "match",
    "multibox_loss",
    "nms",
]

VARIANCES = (0.1, 0.2)


class SSDConfig(BaseModel):
    """Architecture. ``channels``: output channels of the 9 backbone layers (strides
    2, 2, 1, 2, 1, 2, 1, 2, 2); layers 4, 6, 7, 8 feed the heads. ``box_sizes``: default box
    size (pixels of the 240-px image height) per feature map, plus one past the last."""

    model_config = ConfigDict(extra="forbid")
    width: int = 320
    height: int = 240
    classes: tuple[str, ...] = CLASSES
    channels: tuple[int, ...] = (16, 24, 24, 48, 48, 64, 64, 96, 96)
    box_sizes: tuple[float, ...] = (20.0, 40.0, 80.0, 150.0, 220.0)
    aspect_ratios: tuple[float, ...] = (1.0, 2.0, 0.5, 3.0, 1.0 / 3.0)
    score_threshold: float = Field(0.3, ge=0, le=1)
    nms_iou: float = Field(0.45, gt=0, le=1)
    max_detections: int = 20


STRIDES = (2, 2, 1, 2, 1, 2, 1, 2, 2)
TAPS = (4, 6, 7, 8)


def feature_sizes(cfg: SSDConfig) -> list[tuple[int, int]]:
    """(rows, cols) of each tapped feature map (3x3 convs, padding 1)."""
    h, w = cfg.height, cfg.width
    out = []
    for i, s in enumerate(STRIDES):
        h, w = (h + 2 - 3) // s + 1, (w + 2 - 3) // s + 1
        if i in TAPS:
            out.append((h, w))
    return out


def default_boxes(cfg: SSDConfig) -> np.ndarray:
    """Default (prior) boxes ``(P, 4)`` as normalized ``[cx, cy, w, h]``, ordered map by map,
    row-major cells, then boxes per cell (aspect ratios, then the extra square)."""
    out = []
    for k, (rows, cols) in enumerate(feature_sizes(cfg)):
        s = cfg.box_sizes[k]
        s_next = math.sqrt(s * cfg.box_sizes[k + 1])
        shapes = [(s * math.sqrt(a), s / math.sqrt(a)) for a in cfg.aspect_ratios]
        shapes.append((s_next, s_next))
        for r in range(rows):
            for c in range(cols):
                cx, cy = (c + 0.5) / cols, (r + 0.5) / rows
                for bw, bh in shapes:
                    out.append((cx, cy, bw / cfg.width, bh / cfg.height))
    return np.asarray(out, np.float32)


def boxes_per_cell(cfg: SSDConfig) -> int:
    return len(cfg.aspect_ratios) + 1


def _xyxy(b: torch.Tensor) -> torch.Tensor:
    return torch.cat([b[..., :2] - b[..., 2:] / 2, b[..., :2] + b[..., 2:] / 2], -1)


def _cxcywh(b: torch.Tensor) -> torch.Tensor:
    return torch.cat([(b[..., :2] + b[..., 2:]) / 2, b[..., 2:] - b[..., :2]], -1)


def box_iou(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """IoU of ``[x1, y1, x2, y2]`` boxes: (N, 4) x (M, 4) -> (N, M)."""
    lt = torch.maximum(a[:, None, :2], b[None, :, :2])
    rb = torch.minimum(a[:, None, 2:], b[None, :, 2:])
    inter = (rb - lt).clamp(min=0).prod(-1)
    area_a = (a[:, 2:] - a[:, :2]).clamp(min=0).prod(-1)
    area_b = (b[:, 2:] - b[:, :2]).clamp(min=0).prod(-1)
    return inter / (area_a[:, None] + area_b[None, :] - inter).clamp(min=1e-12)


def encode(boxes: torch.Tensor, priors: torch.Tensor) -> torch.Tensor:
    """SSD offsets of ``boxes`` (P, 4) xyxy w.r.t. ``priors`` (P, 4) cxcywh:
    ``((cx - pcx) / (v0 pw), (cy - pcy) / (v0 ph), log(w / pw) / v1, log(h / ph) / v1)``."""
    g = _cxcywh(boxes)
    v0, v1 = VARIANCES
    return torch.cat(
        [
            (g[:, :2] - priors[:, :2]) / (v0 * priors[:, 2:]),
            torch.log(g[:, 2:].clamp(min=1e-9) / priors[:, 2:]) / v1,
        ],
        -1,
    )


def decode(loc: torch.Tensor, priors: torch.Tensor) -> torch.Tensor:
    """Inverse of :func:`encode`: offsets (..., P, 4) -> xyxy boxes (..., P, 4)."""
    v0, v1 = VARIANCES
    c = priors[..., :2] + loc[..., :2] * v0 * priors[..., 2:]
    wh = priors[..., 2:] * torch.exp(loc[..., 2:] * v1)
    return _xyxy(torch.cat([c, wh], -1))


def match(
    gt_boxes: torch.Tensor, gt_labels: torch.Tensor, priors: torch.Tensor, threshold: float = 0.5
) -> tuple[torch.Tensor, torch.Tensor]:
    """SSD matching: each prior takes the ground truth of highest IoU, positive when IoU >=
    ``threshold``; every ground truth also claims its best prior. Returns encoded targets
    (P, 4) and labels (P,) (0 = background, class index + 1 otherwise)."""
    P = priors.shape[0]
    if gt_boxes.numel() == 0:
        return torch.zeros(P, 4), torch.zeros(P, dtype=torch.long)
    iou = box_iou(gt_boxes, _xyxy(priors))  # (G, P)
    best_gt_iou, best_gt = iou.max(0)
    best_prior = iou.argmax(1)
    best_gt_iou[best_prior] = 2.0
    best_gt[best_prior] = torch.arange(len(gt_boxes))
    labels = gt_labels[best_gt] + 1
    labels[best_gt_iou < threshold] = 0
    return encode(gt_boxes[best_gt], priors), labels


def multibox_loss(
    loc: torch.Tensor,
    conf: torch.Tensor,
    loc_t: torch.Tensor,
    labels_t: torch.Tensor,
    neg_pos: int = 3,
) -> tuple[torch.Tensor, torch.Tensor]:
    """SSD loss (eq. 1-3): ``(L_loc, L_conf)``, each summed and divided by the number of
    positives. ``loc`` (B, P, 4), ``conf`` (B, P, C+1), targets from :func:`match`. Hard
    negative mining keeps, per image, the ``neg_pos x #pos`` negatives of highest
    background loss (at least ``neg_pos`` when an image has no positive)."""
    pos = labels_t > 0
    n_pos = pos.sum().clamp(min=1).float()
    l_loc = F.smooth_l1_loss(loc[pos], loc_t[pos], reduction="sum") / n_pos
    ce = F.cross_entropy(conf.reshape(-1, conf.shape[-1]), labels_t.reshape(-1), reduction="none")
    ce = ce.view(labels_t.shape)
    mining = ce.detach().clone()
    mining[pos] = 0.0
    _, idx = mining.sort(1, descending=True)
    _, rank = idx.sort(1)
    n_neg = (neg_pos * pos.sum(1, keepdim=True)).clamp(min=neg_pos, max=pos.shape[1] - 1)
    neg = rank < n_neg
    l_conf = ce[pos | neg].sum() / n_pos
    return l_loc, l_conf


def nms(boxes: np.ndarray, scores: np.ndarray, iou_threshold: float) -> np.ndarray:
    """Greedy non-maximum suppression: indices of kept boxes, by decreasing score. A box is
    dropped when its IoU with an already kept box exceeds ``iou_threshold``."""
    boxes = np.asarray(boxes, np.float64).reshape(-1, 4)
    order = np.argsort(-np.asarray(scores, np.float64), kind="stable")
    area = np.clip(boxes[:, 2] - boxes[:, 0], 0, None) * np.clip(boxes[:, 3] - boxes[:, 1], 0, None)
    keep = []
    while order.size:
        i = order[0]
        keep.append(i)
        rest = order[1:]
        lt = np.maximum(boxes[i, :2], boxes[rest, :2])
        rb = np.minimum(boxes[i, 2:], boxes[rest, 2:])
        inter = np.clip(rb - lt, 0, None).prod(1)
        iou = inter / np.maximum(area[i] + area[rest] - inter, 1e-12)
        order = rest[iou <= iou_threshold]
    return np.asarray(keep, int)


class _ConvBNReLU(nn.Sequential):
    def __init__(self, cin: int, cout: int, stride: int) -> None:
        super().__init__(
            nn.Conv2d(cin, cout, 3, stride, 1, bias=False), nn.BatchNorm2d(cout), nn.ReLU(True)
        )


class SSD(nn.Module):
    """The network: ``forward(x (B, 3, H, W) float in [-0.5, 0.5])`` -> ``(loc (B, P, 4),
    conf (B, P, C + 1))`` with P = number of default boxes."""

    def __init__(self, cfg: SSDConfig) -> None:
        super().__init__()
        if len(cfg.channels) != len(STRIDES):
            raise ConfigError(f"SSDConfig.channels needs {len(STRIDES)} values")
        if len(cfg.box_sizes) != len(TAPS) + 1:
            raise ConfigError(f"SSDConfig.box_sizes needs {len(TAPS) + 1} values")
        self.cfg = cfg
        cin = 3
        layers = []
        for c, s in zip(cfg.channels, STRIDES, strict=True):
            layers.append(_ConvBNReLU(cin, c, s))
            cin = c
        self.layers = nn.ModuleList(layers)
        a = boxes_per_cell(cfg)
        self.n_out = 4 + len(cfg.classes) + 1
        self.heads = nn.ModuleList(
            nn.Conv2d(cfg.channels[t], a * self.n_out, 3, 1, 1) for t in TAPS
        )
        self.register_buffer("priors", torch.from_numpy(default_boxes(cfg)), persistent=False)

    def forward(self, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        outs = []
        k = 0
        for i, layer in enumerate(self.layers):
            x = layer(x)
            if i in TAPS:
                y = self.heads[k](x)  # (B, A * n_out, h, w)
                b = y.shape[0]
                outs.append(y.permute(0, 2, 3, 1).reshape(b, -1, self.n_out))
                k += 1
        out = torch.cat(outs, 1)
        return out[..., :4], out[..., 4:]


@dataclass(frozen=True)
class Detection:
    """One detected object: class index/name, score in [0, 1], ``box`` ``[x1, y1, x2, y2]``
    in pixels of the image given to :meth:`Detector.detect`."""

    label: int
    name: str
    score: float
    box: np.ndarray

    @property
    def center(self) -> np.ndarray:
        return np.array([(self.box[0] + self.box[2]) / 2, (self.box[1] + self.box[3]) / 2])


def to_input(image: np.ndarray, width: int, height: int) -> tuple[np.ndarray, float, float]:
    """Resize (H, W, 3) uint8 to the network size (block mean for integer factors, else
    nearest); returns the resized image and the (sx, sy) scale from network to input pixels.

    The block mean of an ``f x f`` block is rounded half to even (``np.rint`` of the exact
    mean), computed in integers: the block sum ``S``, ``n = f^2``, ``q, r = divmod(S, n)``,
    rounded up iff ``2 r > n`` or ``2 r = n`` and ``q`` is odd."""
    img = np.asarray(image)
    if img.ndim != 3 or img.shape[2] != 3:
        raise InvalidInputError(f"image must be (H, W, 3), got {img.shape}")
    h, w = img.shape[:2]
    if (h, w) == (height, width):
        return img, 1.0, 1.0
    fy, fx = h / height, w / width
    if fy == fx and fy == int(fy):
        return block_mean_u8(img, int(fy)), fx, fy
    rows = np.minimum((np.arange(height) + 0.5) * fy, h - 1).astype(int)
    cols = np.minimum((np.arange(width) + 0.5) * fx, w - 1).astype(int)
    return img[rows][:, cols], fx, fy


def block_mean_u8(image: np.ndarray, f: int) -> np.ndarray:
    """Mean of each ``f x f`` pixel block of a (f H, f W, C) uint8 image, rounded half to even
    exactly (integer arithmetic, see :func:`to_input`); returns (H, W, C) uint8."""
    img = np.asarray(image)
    if img.dtype != np.uint8 or img.ndim != 3 or img.shape[0] % f or img.shape[1] % f:
        raise InvalidInputError(f"need (f H, f W, C) uint8 for f = {f}: {img.shape} {img.dtype}")
    n = f * f
    acc = np.uint16 if 255 * n < 2**16 else np.uint32
    s = np.zeros((img.shape[0] // f, img.shape[1] // f, img.shape[2]), dtype=acc)
    for a in range(f):
        for b in range(f):
            s += img[a::f, b::f]
    if n & (n - 1) == 0:  # a power of two: shift and mask
        k = n.bit_length() - 1
        q, r = s >> k, s & (n - 1)
    else:
        q, r = np.divmod(s, acc(n))
    up = (2 * r > n) | ((2 * r == n) & (q & 1 == 1))
    q += up
    return q.astype(np.uint8)


def image_tensor(images: np.ndarray) -> torch.Tensor:
    """(B, H, W, 3) uint8 -> (B, 3, H, W) float in [-0.5, 0.5]."""
    return torch.from_numpy(np.ascontiguousarray(images)).permute(0, 3, 1, 2).float() / 255.0 - 0.5


class Detector:
    """A trained SSD with post-processing: :meth:`detect` on an RGB image of any size."""

    def __init__(self, model: SSD, meta: dict | None = None) -> None:
        self.model = model.eval()
        self.cfg = model.cfg
        self.meta = meta or {}

    @classmethod
    def load(cls, path: str | Path | None = None) -> Detector:
        """Load weights (default: the shipped model). Missing or corrupt files raise
        :class:`mmpa.core.errors.ConfigError` naming the file."""
        p = Path(path) if path is not None else default_weights_path()
        if not p.is_file():
            raise ConfigError(
                f"detector weight file {p} not found; train one with `mmpa perception train`"
            )
        try:
            blob = torch.load(p, map_location="cpu", weights_only=True)
            cfg = SSDConfig.model_validate(blob["config"])
            model = SSD(cfg)
            model.load_state_dict(blob["state_dict"])
        except Exception as e:
            raise ConfigError(f"detector weight file {p} is corrupt or incompatible: {e}") from None
        return cls(model, blob.get("meta", {}))

    def save(self, path: str | Path) -> None:
        torch.save(
            {
                "config": self.cfg.model_dump(mode="json"),
                "state_dict": self.model.state_dict(),
                "meta": self.meta,
            },
            path,
        )

    @torch.no_grad()
    def detect(self, image: np.ndarray, score_threshold: float | None = None) -> list[Detection]:
        """Detections on one RGB image (H, W, 3) uint8, boxes in its pixels, best first."""
        return self.detect_batch(image[None], score_threshold)[0]

    @torch.no_grad()
    def detect_batch(
        self, images: np.ndarray, score_threshold: float | None = None
    ) -> list[list[Detection]]:
        cfg = self.cfg
        imgs = np.asarray(images)
        if imgs.ndim != 4:
            raise InvalidInputError(f"images must be (B, H, W, 3), got {imgs.shape}")
        small, sx, sy = [], 1.0, 1.0
        for im in imgs:
            s, sx, sy = to_input(im, cfg.width, cfg.height)
            small.append(s)
        loc, conf = self.model(image_tensor(np.stack(small)))
        boxes = decode(loc, self.model.priors).numpy()
        scores = F.softmax(conf, -1).numpy()
        th = cfg.score_threshold if score_threshold is None else score_threshold
        scale = np.array([cfg.width * sx, cfg.height * sy] * 2)
        return [
            postprocess(
                boxes[b], scores[b], th, cfg.nms_iou, cfg.max_detections, cfg.classes, scale
            )
            for b in range(len(imgs))
        ]


def postprocess(
    boxes: np.ndarray,
    scores: np.ndarray,
    threshold: float,
    nms_iou: float,
    max_det: int,
    classes: tuple[str, ...],
    scale: np.ndarray,
) -> list[Detection]:
    """Per-class thresholding and NMS of decoded boxes (P, 4) normalized and softmax scores
    (P, C + 1); returns detections in pixels (``scale`` = [W, H, W, H])."""
    out: list[Detection] = []
    for c in range(1, scores.shape[1]):
        sel = np.nonzero(scores[:, c] >= threshold)[0]
        if sel.size == 0:
            continue
        sel = sel[np.argsort(-scores[sel, c])[:200]]
        keep = nms(boxes[sel], scores[sel, c], nms_iou)
        for k in sel[keep]:
            out.append(Detection(c - 1, classes[c - 1], float(scores[k, c]), boxes[k] * scale))
    out.sort(key=lambda d: -d.score)
    return out[:max_det]


def default_weights_path() -> Path:
    """The shipped detector weights (``mmpa/perception/weights/ssd.pt``)."""

    return Path(str(resources.files("mmpa.perception") / "weights" / "ssd.pt"))
