"""SSD pieces against independent computations: box coding, IoU, matching, NMS, the loss."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from mmpa.core.errors import ConfigError, InvalidInputError
from mmpa.perception.ssd import (
    SSD,
    Detector,
    SSDConfig,
    block_mean_u8,
    box_iou,
    decode,
    default_boxes,
    encode,
    feature_sizes,
    match,
    multibox_loss,
    nms,
    to_input,
)


def _random_boxes(rng: np.random.Generator, n: int) -> np.ndarray:
    xy = rng.uniform(0, 0.8, (n, 2))
    wh = rng.uniform(0.02, 0.3, (n, 2))
    return np.concatenate([xy, xy + wh], 1).astype(np.float32)


def test_default_boxes_layout():
    cfg = SSDConfig()
    assert feature_sizes(cfg) == [(30, 40), (15, 20), (8, 10), (4, 5)]
    pri = default_boxes(cfg)
    assert pri.shape == ((1200 + 300 + 80 + 20) * 6, 4)
    # first cell of the first map: centered at (0.5 / 40, 0.5 / 30), square box 20 px
    assert pri[0] == pytest.approx([0.5 / 40, 0.5 / 30, 20 / 320, 20 / 240])
    # aspect ratio 2: w/h (in pixels) = 2, same area as the square
    w, h = pri[1, 2] * 320, pri[1, 3] * 240
    assert w / h == pytest.approx(2.0) and w * h == pytest.approx(400.0)
    model = SSD(cfg)
    loc, conf = model(torch.zeros(2, 3, 240, 320))
    assert loc.shape == (2, len(pri), 4) and conf.shape == (2, len(pri), 8)


def test_encode_decode_round_trip_and_formula():
    rng = np.random.default_rng(0)
    b = torch.from_numpy(_random_boxes(rng, 50))
    pri = torch.from_numpy(default_boxes(SSDConfig())[rng.choice(9600, 50)])
    enc = encode(b, pri)
    assert decode(enc, pri).numpy() == pytest.approx(b.numpy(), abs=1e-5)
    # by hand for one box
    x1, y1, x2, y2 = b[0].tolist()
    pcx, pcy, pw, ph = pri[0].tolist()
    want = [
        ((x1 + x2) / 2 - pcx) / (0.1 * pw),
        ((y1 + y2) / 2 - pcy) / (0.1 * ph),
        np.log((x2 - x1) / pw) / 0.2,
        np.log((y2 - y1) / ph) / 0.2,
    ]
    assert enc[0].numpy() == pytest.approx(want, rel=1e-4)


def test_iou_against_brute_force_rasterization():
    rng = np.random.default_rng(1)
    a = np.round(_random_boxes(rng, 6) * 100)
    b = np.round(_random_boxes(rng, 5) * 100)
    got = box_iou(torch.from_numpy(a), torch.from_numpy(b)).numpy()
    for i in range(6):
        for j in range(5):
            ga = np.zeros((200, 200), bool)
            gb = np.zeros((200, 200), bool)
            ga[int(a[i, 1]) : int(a[i, 3]), int(a[i, 0]) : int(a[i, 2])] = True
            gb[int(b[j, 1]) : int(b[j, 3]), int(b[j, 0]) : int(b[j, 2])] = True
            assert got[i, j] == pytest.approx((ga & gb).sum() / (ga | gb).sum(), abs=1e-6)


def _nms_brute(boxes: np.ndarray, scores: np.ndarray, th: float) -> list[int]:
    idx = sorted(range(len(scores)), key=lambda i: -scores[i])
    keep: list[int] = []
    for i in idx:
        ok = True
        for k in keep:
            iou = box_iou(torch.from_numpy(boxes[i : i + 1]), torch.from_numpy(boxes[k : k + 1]))
            if float(iou) > th:
                ok = False
        if ok:
            keep.append(i)
    return keep


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_nms_matches_brute_force(seed):
    rng = np.random.default_rng(seed)
    centers = rng.uniform(0.2, 0.8, (4, 2))
    boxes = []
    for _ in range(60):  # clusters of overlapping boxes
        c = centers[rng.integers(4)] + rng.normal(0, 0.03, 2)
        wh = rng.uniform(0.05, 0.15, 2)
        boxes.append([*(c - wh / 2), *(c + wh / 2)])
    boxes = np.array(boxes, np.float32)
    scores = rng.random(60)
    for th in (0.3, 0.5, 0.7):
        assert nms(boxes, scores, th).tolist() == _nms_brute(boxes, scores, th)


def test_match_assigns_best_prior_and_threshold():
    pri = torch.from_numpy(default_boxes(SSDConfig()))
    gt = torch.tensor([[0.4, 0.4, 0.5, 0.55], [0.1, 0.1, 0.13, 0.14]])
    loc_t, lab_t = match(gt, torch.tensor([2, 5]), pri)
    iou = box_iou(gt, decode(torch.zeros_like(pri), pri))
    for g, lab in enumerate([3, 6]):
        assert int(lab_t[int(iou[g].argmax())]) == lab
    pos = lab_t > 0
    # every positive prior overlaps its ground truth by >= 0.5 or is its best prior
    dec = decode(loc_t[pos], pri[pos])
    assert set(lab_t[pos].tolist()) == {3, 6}
    assert torch.all(box_iou(dec, gt).max(1).values > 0.999)


def test_loss_decreases_on_a_tiny_set():
    torch.manual_seed(0)
    rng = np.random.default_rng(0)
    cfg = SSDConfig(channels=(8, 8, 8, 16, 16, 16, 16, 16, 16))
    model = SSD(cfg)
    imgs = torch.full((2, 3, 240, 320), -0.3)
    gts = []
    for i in range(2):  # bright squares on a dark background: class 1
        x, y = rng.integers(20, 250), rng.integers(20, 170)
        imgs[i, :, y : y + 40, x : x + 40] = 0.4
        gts.append(
            (torch.tensor([[x / 320, y / 240, (x + 40) / 320, (y + 40) / 240]]), torch.tensor([1]))
        )
    targets = [match(b, lab, model.priors) for b, lab in gts]
    loc_t = torch.stack([t[0] for t in targets])
    lab_t = torch.stack([t[1] for t in targets])
    opt = torch.optim.Adam(model.parameters(), 1e-2)
    losses = []
    for _ in range(15):
        loc, conf = model(imgs)
        a, b = multibox_loss(loc, conf, loc_t, lab_t)
        opt.zero_grad()
        (a + b).backward()
        opt.step()
        losses.append((a + b).item())
    assert losses[-1] < 0.5 * losses[0]


def test_hard_negative_mining_counts():
    B, P = 2, 50
    lab = torch.zeros(B, P, dtype=torch.long)
    lab[0, :2] = 1  # 2 positives in image 0, none in image 1
    conf = torch.zeros(B, P, 3)
    conf[..., 1] = torch.linspace(0, 5, P)  # negatives with rising background loss
    loc = torch.zeros(B, P, 4)
    l_loc, l_conf = multibox_loss(loc, conf, torch.zeros(B, P, 4), lab)
    ce = torch.nn.functional.cross_entropy(conf.reshape(-1, 3), lab.reshape(-1), reduction="none")
    ce = ce.view(B, P)
    # image 0: 2 positives + 6 hardest negatives; image 1: 3 hardest negatives; / 2 positives
    neg0 = ce[0, 2:].sort(descending=True).values[:6].sum()
    neg1 = ce[1].sort(descending=True).values[:3].sum()
    assert float(l_conf) == pytest.approx(float((ce[0, :2].sum() + neg0 + neg1) / 2), rel=1e-5)
    assert float(l_loc) == 0.0


def test_missing_and_corrupt_weights(tmp_path):
    with pytest.raises(ConfigError, match="not found"):
        Detector.load(tmp_path / "nope.pt")
    bad = tmp_path / "bad.pt"
    bad.write_bytes(b"not a torch file")
    with pytest.raises(ConfigError, match="corrupt"):
        Detector.load(bad)


@pytest.mark.parametrize("f", [2, 3, 4, 17])
def test_block_mean_rounds_half_to_even_exactly(f):
    rng = np.random.default_rng(f)
    h, w = 24 // min(f, 4) + 1, 7
    for img in (
        rng.integers(0, 256, (h * f, w * f, 3), dtype=np.uint8),
        (rng.integers(0, 3, (h * f, w * f, 3)) * 2 + 253 * (f % 2)).astype(np.uint8),  # ties
    ):
        ref = np.rint(img.reshape(h, f, w, f, 3).astype(float).mean(axis=(1, 3)))
        np.testing.assert_array_equal(block_mean_u8(img, f), ref.astype(np.uint8))
    full = rng.integers(0, 256, (480, 640, 3), dtype=np.uint8)
    small, sx, sy = to_input(full, 320, 240)
    ref = np.rint(full.reshape(240, 2, 320, 2, 3).astype(float).mean(axis=(1, 3)))
    assert (sx, sy) == (2.0, 2.0)
    np.testing.assert_array_equal(small, ref.astype(np.uint8))
    with pytest.raises(InvalidInputError):
        block_mean_u8(full[:-1], 2)
