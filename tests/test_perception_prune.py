"""Channel pruning: exactness on dead channels, MAC count against hooks, NetAdapt budget."""

from __future__ import annotations

import numpy as np
import torch

from mmpa.perception.dataset import Dataset
from mmpa.perception.prune import PruneConfig, macs, netadapt, prune_layer
from mmpa.perception.ssd import SSD, SSDConfig

SMALL = SSDConfig(channels=(8, 12, 12, 16, 16, 16, 16, 16, 16))


def test_macs_match_a_hook_count():
    model = SSD(SMALL).eval()
    count = [0]

    def hook(mod, inp, out):
        count[0] += out.shape[2] * out.shape[3] * mod.in_channels * mod.out_channels * 9

    for m in model.modules():
        if isinstance(m, torch.nn.Conv2d):
            m.register_forward_hook(hook)
    with torch.no_grad():
        model(torch.zeros(1, 3, 240, 320))
    assert macs(SMALL) == count[0]


def test_pruning_dead_channels_keeps_the_function():
    torch.manual_seed(0)
    model = SSD(SMALL).eval()
    for i in (2, 4):  # a plain layer and a layer feeding a head
        bn = model.layers[i][1]
        with torch.no_grad():
            bn.weight[:4] = 0.0  # these channels output ReLU(0) = 0: least important
            bn.bias[:4] = 0.0
            bn.running_mean.normal_()
            bn.running_var.uniform_(0.5, 2.0)
    x = torch.randn(2, 3, 240, 320)
    with torch.no_grad():
        ref = model(x)
        small = prune_layer(prune_layer(model, 2, 8), 4, 12).eval()
        got = small(x)
    assert small.cfg.channels[2] == 8 and small.cfg.channels[4] == 12
    for a, b in zip(ref, got, strict=True):
        assert torch.allclose(a, b, atol=1e-5)


def test_netadapt_meets_the_budget():
    rng = np.random.default_rng(0)
    n = 24
    imgs = rng.integers(0, 255, (n, 240, 320, 3), dtype=np.uint8)
    boxes = [np.array([[40.0, 40.0, 90.0, 100.0]], np.float32) for _ in range(n)]
    labels = [np.array([1]) for _ in range(n)]
    data = Dataset(imgs, boxes, labels, np.zeros(n, int))
    model = SSD(SMALL)
    cfg = PruneConfig(
        target_ratio=0.8,
        step_fraction=0.15,
        short_term_batches=0,
        val_images=8,
        long_term_epochs=0,
    )
    pruned, steps = netadapt(model, data, cfg)
    assert macs(pruned.cfg) <= 0.8 * macs(SMALL)
    assert len(steps) >= 1 and steps[-1].macs == macs(pruned.cfg)
    assert all(c >= cfg.min_channels for c in pruned.cfg.channels)
