"""The input views' depth terms against issue 17's doubled eye: ``input_depth_loss`` (each input
view's depth map against its true depth), ``cross_view_depth_loss`` (the views' maps against each
other) and ``ray_depth_from_z``; checked against plain per-point loops of their definitions, on
outputs and gradients, and on analytic geometry (views of one sphere agree)."""

from __future__ import annotations

import math

import pytest
import torch
from torch.testing import assert_close

from fastgha_core.cameras import Cameras
from fastgha_core.data.sampling import TrainingDataset, collate_samples
from fastgha_core.train.losses import FastGHALoss, LossConfig, cross_view_depth_loss, input_depth_loss, ray_depth_from_z


def _huber(e: torch.Tensor, delta: float) -> torch.Tensor:
    a = e.abs()
    if delta <= 0:
        return a
    return 0.5 * a * a / delta if float(a.detach()) < delta else a - 0.5 * delta


def _cameras(v: int = 3, size: int = 8, fov: float = 30.0, radius: float = 1.0) -> Cameras:
    """``v`` cameras on an arc around the origin (yaw -30..30 degrees, a little pitch), ``size``²."""
    yaws = torch.linspace(-30.0, 30.0, v)
    eyes = torch.stack([torch.sin(torch.deg2rad(yaws)), torch.full((v,), 0.15), torch.cos(torch.deg2rad(yaws))], -1)
    eyes = eyes / eyes.norm(dim=-1, keepdim=True) * radius
    return Cameras.look_at(eyes, fov_deg=fov, width=size, height=size)


def _sphere_depth(cams: Cameras, r: float = 0.12, size: int = 8) -> tuple[torch.Tensor, torch.Tensor]:
    """Distance along each pixel ray to a sphere of radius ``r`` at the origin ``[V, H, W]`` and its mask."""
    o, d = cams.pixel_rays(size, size)  # [V, H, W, 3]
    b = (o * d).sum(-1)
    c = (o * o).sum(-1) - r * r
    disc = b * b - c
    hit = disc > 0
    t = -b - disc.clamp_min(0).sqrt()
    return torch.where(hit, t, torch.full_like(t, 1.0)), hit


# ---------------------------------------------------------------- ray depth
def test_ray_depth_from_z_puts_points_at_the_given_camera_z():
    cams = _cameras(2, size=6)
    z = 0.8 + 0.1 * torch.rand(2, 6, 6, dtype=torch.float64)
    z[0, 0, 0] = 0.0
    t = ray_depth_from_z(z, cams.K.double())
    o, d = cams.to(dtype=torch.float64).pixel_rays()
    pts = o + d * t[..., None]
    pc = Cameras(cams.K.double(), cams.w2c.double(), 6, 6).world_to_camera(pts.flatten(1, 2)).view(2, 6, 6, 3)
    assert_close(pc[..., 2][z > 0], z[z > 0])
    assert float(t[0, 0, 0]) == 0.0
    assert bool((t[z > 0] >= z[z > 0]).all())  # off-axis rays are longer than their z
    with pytest.raises(ValueError):
        ray_depth_from_z(z, torch.eye(4))


# ---------------------------------------------------------------- input depth
def test_input_depth_loss_matches_a_plain_loop_on_outputs_and_gradients():
    torch.manual_seed(0)
    pred = (1.0 + 0.004 * torch.randn(2, 5, 6, dtype=torch.float64)).requires_grad_(True)
    true = 1.0 + 0.004 * torch.randn(2, 5, 6, dtype=torch.float64)
    true[0, :2] = 0.0  # no value there
    mask = torch.rand(2, 5, 6, dtype=torch.float64)
    delta = 0.003
    got = input_depth_loss(pred, true, mask, delta)
    total, n = 0.0, 0
    for i in range(2):
        for y in range(5):
            for x in range(6):
                if true[i, y, x] > 0 and mask[i, y, x] > 0.5:
                    total = total + _huber(pred[i, y, x] - true[i, y, x], delta)
                    n += 1
    ref = total / n
    assert_close(got, ref)
    (g,) = torch.autograd.grad(got, pred)
    (g_ref,) = torch.autograd.grad(ref, pred)
    assert_close(g, g_ref)
    assert float(got.detach()) > 0 and bool((g[0, :2] == 0).all())


def test_input_depth_loss_values_and_empty_case():
    true = torch.full((1, 4, 4), 1.0, dtype=torch.float64)
    assert float(input_depth_loss(true + 0.01, true, None, 0.0)) == pytest.approx(0.01)
    assert float(input_depth_loss(true + 0.01, true, None, 0.002)) == pytest.approx(0.01 - 0.001)
    assert float(input_depth_loss(true + 0.001, true, None, 0.002)) == pytest.approx(0.001**2 / 0.004)
    pred = torch.ones(1, 4, 4, requires_grad=True)
    z = input_depth_loss(pred, torch.zeros(1, 4, 4))
    assert float(z.detach()) == 0.0 and z.requires_grad
    with pytest.raises(ValueError):
        input_depth_loss(pred, torch.zeros(1, 4, 5))
    with pytest.raises(ValueError):
        input_depth_loss(pred, true, torch.ones(4, 4))


# ---------------------------------------------------------------- cross-view
def _cross_view_reference(depth, K, w2c, mask, margin, delta, max_range):
    """Per point and pair: explicit projection, bilinear read with zero padding, one-sided Huber."""
    b, v, h, w = depth.shape
    cams = Cameras(K, w2c, w, h)
    o, d = cams.pixel_rays()
    total, n = depth.sum() * 0.0, 0
    for s in range(b):
        for a in range(v):
            for y in range(h):
                for x in range(w):
                    if mask[s, a, y, x] <= 0.5:
                        continue
                    p = o[s, a, y, x] + d[s, a, y, x] * depth[s, a, y, x]
                    for c in range(v):
                        if c == a:
                            continue
                        R, t = w2c[s, c, :3, :3], w2c[s, c, :3, 3]
                        pc = R @ p.detach() + t
                        if float(pc[2]) <= 0:
                            continue
                        q = K[s, c] @ (pc / pc[2])
                        u, vv = float(q[0]), float(q[1])
                        if not (0 < u < w and 0 < vv < h):
                            continue
                        fx, fy = u - 0.5, vv - 0.5
                        x0, y0 = math.floor(fx), math.floor(fy)
                        read, seen, vals = depth.sum() * 0.0, 0.0, []
                        for yy, wy in ((y0, 1 - (fy - y0)), (y0 + 1, fy - y0)):
                            for xx, wx in ((x0, 1 - (fx - x0)), (x0 + 1, fx - x0)):
                                if 0 <= yy < h and 0 <= xx < w:
                                    read = read + wy * wx * depth[s, c, yy, xx]
                                    seen += wy * wx * float(mask[s, c, yy, xx] > 0.5)
                                    vals.append(float(depth[s, c, yy, xx]))
                        if seen <= 0.999 or max(vals) - min(vals) >= max_range:
                            continue
                        r = (p - cams.centers[s, c]).norm() - read
                        if float(r) <= -margin:
                            continue
                        total = total + _huber(torch.clamp(r, max=0.0), delta)
                        n += 1
    return total / n if n else total, n


def test_cross_view_loss_matches_a_plain_loop_on_outputs_and_gradients():
    torch.manual_seed(1)
    cams = _cameras(3, size=8, fov=16.0)
    base, hit = _sphere_depth(cams)
    depth = (base + 0.004 * torch.randn(3, 8, 8)).double()[None].requires_grad_(True)  # views disagree by mm
    mask = hit[None].double()
    K, w2c = cams.K[None].double(), cams.w2c[None].double()
    for delta in (0.0, 0.002):
        got = cross_view_depth_loss(depth, K, w2c, mask, margin=0.03, delta=delta, max_range=0.05)
        ref, n = _cross_view_reference(depth, K, w2c, mask, 0.03, delta, 0.05)
        assert n > 20 and float(ref) > 0
        assert_close(got, ref)
        (g,) = torch.autograd.grad(got, depth)
        (g_ref,) = torch.autograd.grad(ref, depth)
        assert_close(g, g_ref)
        assert g.abs().sum() > 0


def test_cross_view_loss_is_small_for_views_of_one_surface_and_sees_one_moved_view():
    cams = _cameras(3, size=32, fov=16.0)  # 9 mm pixels at the sphere
    depth, hit = _sphere_depth(cams, size=32)
    K, w2c, m = cams.K[None], cams.w2c[None], hit[None].float()
    agree = float(cross_view_depth_loss(depth[None], K, w2c, m, delta=0.0))
    assert agree < 3e-4  # bilinear reads of a curved surface: sub-millimetre (0.2 mm)
    for shift in (-0.005, 0.005):  # one view 5 mm nearer or farther: seen from one side of each pair
        moved = depth.clone()
        moved[1] = moved[1] + shift * hit[1]
        got = float(cross_view_depth_loss(moved[None], K, w2c, m, delta=0.0))
        assert got > 5 * agree and got > 0.0015, (shift, got)  # 1.9 mm
    far = depth.clone()
    far[1] = far[1] - 0.2 * hit[1]  # 20 cm in front of the others: beyond the margin, not the same surface
    assert float(cross_view_depth_loss(far[None], K, w2c, m, delta=0.0, margin=0.03)) < agree


def test_cross_view_loss_one_view_empty_and_bad_shapes():
    cams = _cameras(2, size=8)
    d = torch.ones(1, 1, 8, 8, requires_grad=True)
    z = cross_view_depth_loss(d, cams.K[None, :1], cams.w2c[None, :1])
    assert float(z.detach()) == 0.0 and z.requires_grad
    d2 = torch.ones(1, 2, 8, 8, requires_grad=True)
    z = cross_view_depth_loss(d2, cams.K[None], cams.w2c[None], torch.zeros(1, 2, 8, 8))
    assert float(z.detach()) == 0.0 and z.requires_grad
    with pytest.raises(ValueError):
        cross_view_depth_loss(torch.ones(2, 8, 8), cams.K[None], cams.w2c[None])
    with pytest.raises(ValueError):
        cross_view_depth_loss(d2, cams.K, cams.w2c[None])
    with pytest.raises(ValueError):
        cross_view_depth_loss(d2, cams.K[None], cams.w2c[None], torch.ones(2, 8, 8))


# ---------------------------------------------------------------- loss module, samples
def test_loss_module_adds_the_weighted_view_depth_terms():
    torch.manual_seed(2)
    cams = _cameras(3, size=16)
    base, hit = _sphere_depth(cams, size=16)
    vd = (base + 0.003 * torch.randn(3, 16, 16)).requires_grad_(True)
    images = torch.where(hit[:, None], torch.tensor([0.8, 0.6, 0.5]).view(3, 1, 1), torch.ones(3, 1, 1)).expand(3, 3, 16, 16).clone()
    x = torch.rand(2, 3, 8, 8)
    args = (x, torch.ones(2, 1, 8, 8), torch.ones(2, 1, 8, 8), x, torch.ones(2, 1, 8, 8), torch.ones(2, 1, 8, 8))
    kw = dict(view_depth=vd, view_images=images, view_true_depth=base, view_K=cams.K[None], view_w2c=cams.w2c[None])
    off = FastGHALoss(LossConfig(w_perc=0.0))(*args, **kw)
    assert float(off["indepth"]) == float(off["xview"]) == 0.0  # off by default
    cfg = LossConfig(w_perc=0.0, w_input_depth=3.0, w_cross_view=5.0)
    on = FastGHALoss(cfg)(*args, **kw)
    from fastgha_core.model.gaussian_head import foreground_weight

    fg = foreground_weight(images)
    assert_close(on["indepth"], input_depth_loss(vd, base, fg, cfg.input_depth_delta))
    assert_close(on["xview"], cross_view_depth_loss(vd[None], cams.K[None], cams.w2c[None], fg[None], cfg.cross_view_margin, cfg.cross_view_delta, cfg.cross_view_range))
    assert float(on["indepth"]) > 0 and float(on["xview"]) > 0
    assert_close(on["total"] - off["total"], 3.0 * on["indepth"] + 5.0 * on["xview"])
    missing = FastGHALoss(cfg)(*args, view_depth=vd, view_images=images)  # no true depth, no cameras: 0
    assert float(missing["indepth"]) == float(missing["xview"]) == 0.0


def test_samples_carry_their_input_views_true_depth():
    from tests.test_sampling import FakeSource

    src = FakeSource(depth_cams=(0, 1, 2, 3, 4, 5))
    ds = TrainingDataset([src], num_inputs=4, num_targets=8, seed=1, length=6)
    for i in range(4):
        s, plan = ds[i], ds.plan(i)
        assert s.input_depths.shape == (4, 1, 16, 20)
        for k, c in enumerate(plan.input_cameras):
            assert float(s.input_depths[k].max()) == pytest.approx(1.0 + c / 100 if c in src.depth_cams else 0.0)
    batch = collate_samples([ds[0], ds[1]])
    assert batch.input_depths.shape == (2, 4, 1, 16, 20)
    s0 = ds[0]
    s0.input_depths = None  # a reader that does not fill the field: the batch has none
    assert collate_samples([s0, ds[1]]).input_depths is None


def test_depth_parity_bench_truth_stats_read_a_known_offset():
    """``bench/depth_parity.py --truth``: a model whose maps are the truth moved 2 mm back reads 2 mm."""
    import importlib.util
    from pathlib import Path
    from types import SimpleNamespace

    from tests.test_sampling import FakeSource

    spec = importlib.util.spec_from_file_location("depth_parity_bench", Path(__file__).resolve().parents[1] / "bench" / "depth_parity.py")
    bench = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(bench)
    src = FakeSource(depth_cams=tuple(range(12)))
    batch = collate_samples([TrainingDataset([src], num_inputs=4, num_targets=8, seed=3, length=2)[0]])
    batch.input_images[:, :, :, 4:12, 5:15] = 0.3  # a foreground patch (the rest is on the background colour)
    batch.input_images[:, :, :, :4] = 1.0
    batch.input_images[:, :, :, 12:] = 1.0
    batch.input_images[:, :, :, :, :5] = 1.0
    batch.input_images[:, :, :, :, 15:] = 1.0

    def model(images, K, w2c, expression, input_expressions):
        return SimpleNamespace(view_depth=ray_depth_from_z(batch.input_depths[:, :, 0], K) + 0.002)

    st = bench.truth_stats(model, [batch])
    assert st["abs_error_mm"][0] == pytest.approx(2.0, abs=1e-3)
    assert st["signed_error_mm"][0] == pytest.approx(2.0, abs=1e-3)
    assert st["cross_view_one_sided_mm"][0] >= 0.0
