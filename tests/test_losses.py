"""The paper's loss terms (§3.3): values on crafted inputs, gradients, the perceptual switch."""

from __future__ import annotations

import logging

import pytest
import torch

from fastgha_core.train.losses import FastGHALoss, LossConfig, geometry_loss, silhouette_loss, ssim_loss
from fastgha_core.train.vgg import VGG16Features


def test_geometry_loss_masks_missing_prior_and_background():
    depth = torch.tensor([[[[1.0, 2.0], [3.0, 4.0]]]])  # [1, 1, 2, 2]
    prior = torch.tensor([[[[1.5, 0.0], [2.0, 4.0]]]])  # pixel (0,1) has no prior
    mask = torch.tensor([[[[1.0, 1.0], [1.0, 0.0]]]])  # pixel (1,1) is background
    # valid pixels: (0,0) |1-1.5| = .5 and (1,0) |3-2| = 1 -> mean .75
    assert geometry_loss(depth, prior, mask).item() == pytest.approx(0.75)
    assert geometry_loss(depth, prior).item() == pytest.approx((0.5 + 1.0 + 0.0) / 3)
    d = depth.clone().requires_grad_(True)
    loss = geometry_loss(d, torch.zeros_like(prior), mask)  # no valid pixel: zero, still differentiable
    loss.backward()
    assert loss.item() == 0.0 and torch.equal(d.grad, torch.zeros_like(d))


def test_silhouette_and_ssim_values():
    alpha = torch.tensor([[[[0.0, 1.0], [0.5, 0.25]]]])
    mask = torch.ones_like(alpha)
    assert silhouette_loss(alpha, mask).item() == pytest.approx((1 + 0 + 0.5 + 0.75) / 4)
    img = torch.rand(1, 3, 16, 16)
    assert ssim_loss(img, img).item() == pytest.approx(0.0, abs=1e-5)
    assert ssim_loss(img, 1 - img).item() > 0.5
    with pytest.raises(ValueError, match=r"\[N, 1, H, W\]"):
        silhouette_loss(torch.zeros(1, 3, 4, 4), torch.zeros(1, 3, 4, 4))


def _random_vgg():
    vgg = VGG16Features()
    gen = torch.Generator().manual_seed(0)
    with torch.no_grad():
        for p in vgg.parameters():
            p.copy_(torch.randn(p.shape, generator=gen) * 0.05)
    return vgg


def test_every_term_finite_with_gradients():
    gen = torch.Generator().manual_seed(0)
    n, h, w = 2, 32, 32
    rgb = torch.rand(n, 3, h, w, generator=gen).requires_grad_(True)
    alpha = torch.rand(n, 1, h, w, generator=gen).requires_grad_(True)
    depth = (1 + torch.rand(n, 1, h, w, generator=gen)).requires_grad_(True)
    t_rgb, t_mask = torch.rand(n, 3, h, w, generator=gen), (torch.rand(n, 1, h, w, generator=gen) > 0.3).float()
    t_depth = (1 + torch.rand(n, 1, h, w, generator=gen)) * t_mask
    loss_fn = FastGHALoss(LossConfig(), vgg=_random_vgg())
    terms = loss_fn(rgb, alpha, depth, t_rgb, t_mask, t_depth)
    assert set(terms) == {"rgb", "ssim", "perc", "sil", "geo", "dsmooth", "dparity", "indepth", "xview", "total"}
    assert terms["dsmooth"].item() == terms["dparity"].item() == terms["indepth"].item() == terms["xview"].item() == 0.0  # off by default (tests/test_depth_parity.py, tests/test_view_depth_losses.py)
    c = loss_fn.config
    expected_total = terms["rgb"] + c.w_ssim * terms["ssim"] + c.w_perc * terms["perc"] + c.w_sil * terms["sil"] + c.w_geo * terms["geo"]
    torch.testing.assert_close(terms["total"], expected_total)
    for name in ("rgb", "ssim", "perc", "sil", "geo"):
        t = terms[name]
        assert torch.isfinite(t) and t.item() > 0, name
        wrt = {"rgb": rgb, "ssim": rgb, "perc": rgb, "sil": alpha, "geo": depth}[name]
        (g,) = torch.autograd.grad(t, wrt, retain_graph=True)
        assert torch.isfinite(g).all() and g.abs().sum() > 0, name


def test_perceptual_off_without_weights_logs_once(caplog):
    caplog.set_level(logging.WARNING, logger="fastgha_core.train.losses")
    loss_fn = FastGHALoss(LossConfig())
    x = torch.rand(1, 3, 16, 16)
    for _ in range(3):
        terms = loss_fn(x, torch.ones(1, 1, 16, 16), torch.ones(1, 1, 16, 16), x, torch.ones(1, 1, 16, 16), torch.ones(1, 1, 16, 16))
    assert terms["perc"].item() == 0.0 and not loss_fn.perceptual_enabled
    msgs = [r for r in caplog.records if "perceptual loss is off" in r.getMessage()]
    assert len(msgs) == 1
