"""The row-parity notch of the predicted depth and the depth-smoothness loss (issue 17's bands).

Both are checked against plain per-pixel loops of their definitions, on outputs and gradients.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from torch.testing import assert_close

from fastgha_core.cameras import orbit_cameras
from fastgha_core.config import GaussianHeadConfig
from fastgha_core.model.gaussian_head import GaussianHead, remove_row_parity, row_parity
from fastgha_core.train.losses import FastGHALoss, LossConfig, depth_parity_loss, depth_smoothness_loss


# ---------------------------------------------------------------- plain references
def _row_parity_reference(d: np.ndarray, m: np.ndarray, sigma: float) -> np.ndarray:
    """Per-pixel loops: demodulated half second difference, normalised Gaussian average."""
    h, w = d.shape
    r = max(1, math.ceil(3 * sigma))
    k = np.exp(-(np.arange(-r, r + 1) ** 2) / (2 * sigma**2))
    k /= k.sum()
    c = np.zeros((h, w))
    valid = np.zeros((h, w))
    for y in range(1, h - 1):
        for x in range(w):
            if m[y - 1, x] and m[y, x] and m[y + 1, x]:
                valid[y, x] = 1.0
                c[y, x] = (-1) ** y * 0.5 * (d[y, x] - 0.5 * (d[y - 1, x] + d[y + 1, x]))
    out = np.zeros((h, w))
    for y in range(h):
        for x in range(w):
            num = den = 0.0
            for dy in range(-r, r + 1):
                for dx in range(-r, r + 1):
                    yy, xx = y + dy, x + dx
                    if 0 <= yy < h and 0 <= xx < w:
                        wt = k[dy + r] * k[dx + r] * valid[yy, xx]
                        num += wt * c[yy, xx]
                        den += wt
            out[y, x] = num / den if den > 1e-6 else 0.0
    return out


def _smoothness_reference(d: np.ndarray, img: np.ndarray, m: np.ndarray, edge: float) -> float:
    n, h, w = d.shape
    total, count = 0.0, 0
    for i in range(n):
        for y in range(h):
            for x in range(w):
                for dy, dx in ((1, 0), (0, 1)):
                    y0, x0, y1, x1 = y - dy, x - dx, y + dy, x + dx
                    if y0 < 0 or x0 < 0 or y1 >= h or x1 >= w:
                        continue
                    if not (m[i, y0, x0] and m[i, y, x] and m[i, y1, x1]):
                        continue
                    change = np.abs(img[i, :, y1, x1] - img[i, :, y0, x0]).mean() / 2
                    total += abs(d[i, y0, x0] - 2 * d[i, y, x] + d[i, y1, x1]) * math.exp(-edge * change)
                    count += 1
    return total / count


def _alternating(h: int, w: int) -> torch.Tensor:
    return ((-1.0) ** torch.arange(h, dtype=torch.float64))[:, None].expand(h, w)


# ---------------------------------------------------------------- the notch
def test_row_parity_matches_a_plain_loop_with_a_mask():
    g = torch.Generator().manual_seed(0)
    d = torch.rand(2, 11, 9, generator=g, dtype=torch.float64)
    m = torch.rand(2, 11, 9, generator=g) > 0.25
    for sigma in (0.7, 1.5):
        got = row_parity(d, m, sigma)
        for i in range(2):
            ref = _row_parity_reference(d[i].numpy(), m[i].numpy(), sigma)
            assert_close(got[i], torch.from_numpy(ref), atol=1e-12, rtol=0)
    assert_close(remove_row_parity(d, m, 1.5), d - _alternating(11, 9) * row_parity(d, m, 1.5))


def test_remove_row_parity_takes_out_a_pure_alternation_and_keeps_planes():
    h, w = 16, 12
    y, x = torch.meshgrid(torch.arange(h, dtype=torch.float64), torch.arange(w, dtype=torch.float64), indexing="ij")
    plane = 1.0 + 0.01 * y - 0.02 * x
    # a plane in y with any content along x: no vertical second difference, left exactly as it was
    rough = plane + torch.rand(w, generator=torch.Generator().manual_seed(1), dtype=torch.float64)[None, :]
    assert_close(remove_row_parity(rough, None, 2.0), rough, atol=1e-12, rtol=0)
    # a constant alternation on top of it goes, on every row (first and last included)
    assert_close(remove_row_parity(rough + 0.004 * _alternating(h, w), None, 2.0), rough, atol=1e-12, rtol=0)
    # inside a mask the same holds; outside it the value is whatever, so compare the mask only
    m = torch.zeros(h, w, dtype=torch.bool)
    m[3:13, 2:10] = True
    out = remove_row_parity(rough - 0.003 * _alternating(h, w), m, 2.0)
    assert_close(out[m], rough[m], atol=1e-12, rtol=0)


def test_remove_row_parity_is_a_narrow_notch():
    h, w = 64, 8
    y = torch.arange(h, dtype=torch.float64)[:, None].expand(h, w)
    inner = slice(16, 48)
    for period in (4.0, 6.0):  # rows of period 4 and 6 keep (almost) all their amplitude
        wave = torch.cos(2 * math.pi * y / period)
        kept = remove_row_parity(wave, None, 2.0)[inner].abs().max() / wave[inner].abs().max()
        assert float(kept) > 0.99, period
    # for contrast: a vertical [1, 2, 1] / 4 blur halves period-4 rows
    wave = torch.cos(2 * math.pi * y / 4.0)
    blur = 0.25 * wave[:-2] + 0.5 * wave[1:-1] + 0.25 * wave[2:]
    assert float(blur[inner].abs().max()) == pytest.approx(0.5, abs=1e-9)


def test_remove_row_parity_gradients_match_finite_differences():
    g = torch.Generator().manual_seed(2)
    d = torch.rand(1, 7, 5, generator=g, dtype=torch.float64, requires_grad=True)
    m = torch.rand(1, 7, 5, generator=g) > 0.2
    assert torch.autograd.gradcheck(lambda z: remove_row_parity(z, m, 1.0), (d,))


def test_row_parity_rejects_bad_arguments():
    with pytest.raises(ValueError, match="mask must have the depth's shape"):
        row_parity(torch.zeros(4, 4), torch.zeros(3, 4))
    with pytest.raises(ValueError, match="sigma must be > 0"):
        row_parity(torch.zeros(4, 4), None, 0.0)
    with pytest.raises(ValueError, match=r"\[\.\.\., H, W\]"):
        row_parity(torch.zeros(4))


def test_gaussian_head_depth_parity_sigma_flattens_alternating_rows():
    cams = orbit_cameras(2, radius=1.2, width=8, height=10)
    maps = torch.zeros(1, 2, 16, 10, 8)
    maps[:, :, 0] = 0.05 * ((-1.0) ** torch.arange(10))[:, None]  # raw depth alternating row by row
    images = torch.full((1, 2, 3, 10, 8), 0.4)  # all foreground

    def dist(cfg):
        (g,) = GaussianHead(cfg)(maps, cams[None], images)
        return (g.means.view(2, 10, 8, 3) - cams.centers[:, None, None]).norm(dim=-1)

    off = dist(GaussianHeadConfig(feature_dim=4))
    on = dist(GaussianHeadConfig(feature_dim=4, depth_parity_sigma=2.0))
    step = 0.35 * math.tanh(0.05)
    assert_close(off[:, 1:] - off[:, :-1], -2 * step * ((-1.0) ** torch.arange(9))[None, :, None].expand(2, 9, 8), atol=1e-5, rtol=0)
    assert_close(on, torch.full_like(on, 1.2), atol=1e-5, rtol=0)  # the alternation around |c| is gone


# ---------------------------------------------------------------- the loss
def test_depth_smoothness_loss_matches_a_plain_loop():
    g = torch.Generator().manual_seed(3)
    d = torch.rand(2, 6, 7, generator=g, dtype=torch.float64)
    img = torch.rand(2, 3, 6, 7, generator=g, dtype=torch.float64)
    m = torch.rand(2, 6, 7, generator=g) > 0.2
    for edge in (0.0, 5.0):
        got = depth_smoothness_loss(d, img, m, edge)
        assert float(got) == pytest.approx(_smoothness_reference(d.numpy(), img.numpy(), m.numpy(), edge), rel=1e-12)
    ones = np.ones((2, 6, 7), dtype=bool)
    assert float(depth_smoothness_loss(d)) == pytest.approx(_smoothness_reference(d.numpy(), img.numpy() * 0, ones, 0.0), rel=1e-12)


def test_depth_smoothness_loss_values_and_gradients():
    h, w = 8, 6
    y, x = torch.meshgrid(torch.arange(h, dtype=torch.float64), torch.arange(w, dtype=torch.float64), indexing="ij")
    plane = (1.0 + 0.003 * y + 0.002 * x)[None]
    assert float(depth_smoothness_loss(plane)) == pytest.approx(0.0, abs=1e-15)
    # c (-1)**y costs 4|c| on each of the (h-2) * w vertical triples, nothing on the h * (w-2) horizontal ones
    c = 0.002
    rows = plane + c * _alternating(h, w)[None]
    n_y, n_x = (h - 2) * w, h * (w - 2)
    assert float(depth_smoothness_loss(rows)) == pytest.approx(4 * c * n_y / (n_y + n_x), rel=1e-12)
    # nothing to average over: an exact zero in the graph
    d = rows.clone().requires_grad_(True)
    z = depth_smoothness_loss(d, None, torch.zeros(1, h, w))
    assert float(z) == 0.0 and z.requires_grad
    g = torch.Generator().manual_seed(4)
    d = (plane + 0.01 * torch.rand(1, h, w, generator=g, dtype=torch.float64)).requires_grad_(True)
    img = torch.rand(1, 3, h, w, generator=g, dtype=torch.float64)
    assert torch.autograd.gradcheck(lambda z: depth_smoothness_loss(z, img, None, 5.0), (d,))
    with pytest.raises(ValueError, match=r"images must have shape \[1, 3, 8, 6\]"):
        depth_smoothness_loss(d, img[:, :2])


def test_loss_module_adds_the_weighted_depth_term():
    g = torch.Generator().manual_seed(5)
    rgb, t_rgb = torch.rand(2, 3, 16, 16, generator=g), torch.rand(2, 3, 16, 16, generator=g)
    alpha, mask = torch.rand(2, 1, 16, 16, generator=g), torch.ones(2, 1, 16, 16)
    depth, t_depth = torch.rand(2, 1, 16, 16, generator=g) + 1, torch.rand(2, 1, 16, 16, generator=g) + 1
    view_depth = (1 + 0.01 * torch.rand(4, 8, 8, generator=g)).requires_grad_(True)
    view_images = torch.rand(4, 3, 8, 8, generator=g) * 0.5  # far from the white background: all foreground
    base = FastGHALoss(LossConfig())(rgb, alpha, depth, t_rgb, mask, t_depth, view_depth=view_depth, view_images=view_images)
    assert float(base["dsmooth"]) == 0.0  # off by default
    terms = FastGHALoss(LossConfig(w_depth_smooth=3.0))(rgb, alpha, depth, t_rgb, mask, t_depth, view_depth=view_depth, view_images=view_images)
    expect = depth_smoothness_loss(view_depth, view_images, None, LossConfig().depth_smooth_edge)
    assert_close(terms["dsmooth"], expect)
    assert_close(terms["total"], base["total"] + 3.0 * expect)
    (grad,) = torch.autograd.grad(terms["total"], view_depth)
    assert grad.abs().sum() > 0


def test_depth_parity_loss_matches_a_plain_loop_and_is_blind_to_smooth_maps():
    g = torch.Generator().manual_seed(6)
    d = torch.rand(2, 9, 8, generator=g, dtype=torch.float64)
    m = torch.rand(2, 9, 8, generator=g) > 0.2
    ref = 0.0
    for i in range(2):
        rows = _row_parity_reference(d[i].numpy(), m[i].numpy(), 1.0)
        cols = _row_parity_reference(d[i].numpy().T, m[i].numpy().T, 1.0).T
        ref += (np.abs(rows) + np.abs(cols))[m[i].numpy()].sum()
    assert float(depth_parity_loss(d, m, 1.0)) == pytest.approx(ref / float(m.sum()), rel=1e-12)
    h, w = 12, 10
    y, x = torch.meshgrid(torch.arange(h, dtype=torch.float64), torch.arange(w, dtype=torch.float64), indexing="ij")
    bowl = (1.0 + 0.02 * ((y - 5) / h) ** 2 + 0.01 * x / w)[None]  # smooth: second differences 2.8e-4 at most
    assert float(depth_parity_loss(bowl)) < 0.005 * float(depth_parity_loss(bowl + 0.003 * _alternating(h, w)[None]))
    assert float(depth_parity_loss(0.003 * _alternating(h, w)[None])) == pytest.approx(0.003, rel=1e-9)
    assert float(depth_parity_loss(0.003 * _alternating(w, h).T[None])) == pytest.approx(0.003, rel=1e-9)  # columns alike
    # Huber: |c| - delta / 2 above delta, c^2 / (2 delta) below
    assert float(depth_parity_loss(0.003 * _alternating(h, w)[None], None, 2.0, 0.001)) == pytest.approx(0.0025, rel=1e-9)
    assert float(depth_parity_loss(0.0004 * _alternating(h, w)[None], None, 2.0, 0.001)) == pytest.approx(0.0004**2 / 0.002, rel=1e-9)
    z = depth_parity_loss(bowl.clone().requires_grad_(True), torch.zeros(1, h, w))
    assert float(z.detach()) == 0.0 and z.requires_grad
    # away from |.|'s kink: both alternations present, plus noise
    wiggle = 0.003 * _alternating(7, 6) + 0.002 * _alternating(6, 7).T + 0.0005 * torch.rand(7, 6, generator=g, dtype=torch.float64)
    dd = (bowl[:, :7, :6] + wiggle).requires_grad_(True)
    assert torch.autograd.gradcheck(lambda z: depth_parity_loss(z, None, 1.0), (dd,))
    assert torch.autograd.gradcheck(lambda z: depth_parity_loss(z, None, 1.0, 0.0025), (dd,))


def test_loss_module_adds_the_weighted_parity_term():
    g = torch.Generator().manual_seed(7)
    rgb = torch.rand(1, 3, 8, 8, generator=g)
    ones = torch.ones(1, 1, 8, 8)
    view_depth = (1 + 0.002 * ((-1.0) ** torch.arange(8))[:, None] + 0.001 * torch.rand(2, 8, 8, generator=g)).requires_grad_(True)
    view_images = torch.rand(2, 3, 8, 8, generator=g) * 0.5
    base = FastGHALoss(LossConfig())(rgb, ones, ones, rgb, ones, ones, view_depth=view_depth, view_images=view_images)
    terms = FastGHALoss(LossConfig(w_depth_parity=2.0))(rgb, ones, ones, rgb, ones, ones, view_depth=view_depth, view_images=view_images)
    expect = depth_parity_loss(view_depth, None, LossConfig().depth_parity_sigma, LossConfig().depth_parity_delta)
    assert float(base["dparity"]) == 0.0 and float(expect) > 0.0015
    assert_close(terms["dparity"], expect)
    assert_close(terms["total"], base["total"] + 2.0 * expect)
