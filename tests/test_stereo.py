"""model/stereo.py: the photo-consistency depth correction of the on-head pixels."""

import math

import pytest
import torch

from fastgha_core.cameras import Cameras
from fastgha_core.model.stereo import (
    StereoConfig,
    _box,
    band_pass,
    ncc_cost_volume,
    stereo_ray_depth,
)

RADIUS = 0.09  # a head-sized sphere at the origin (metres)


def _cameras(yaws_deg, size=128, dist=0.6):
    eyes = torch.tensor([[dist * math.sin(math.radians(y)), 0.0, dist * math.cos(math.radians(y))] for y in yaws_deg])
    return Cameras.look_at(eyes, fov_deg=25.0, width=size, height=size)


def _texture(p: torch.Tensor, flat: bool = False) -> torch.Tensor:
    """RGB [..., 3] of world points p [..., 3]: a fixed pattern of blobs on the sphere (or uniform)."""
    if flat:
        return torch.full(p.shape[:-1] + (3,), 0.6)
    g = torch.Generator().manual_seed(3)
    centres = torch.nn.functional.normalize(torch.randn(300, 3, generator=g), dim=-1) * RADIUS
    amp = torch.rand(300, generator=g) - 0.5
    d2 = ((p[..., None, :] - centres) ** 2).sum(-1)  # [..., 300]
    lum = 0.5 + (amp * torch.exp(-d2 / (2 * 0.006**2))).sum(-1)
    return torch.stack([lum, 0.8 * lum, 0.6 * lum], -1).clamp(0, 1)


def _render(cams: Cameras, flat: bool = False):
    """Ray-cast the sphere: images [V, 3, H, W], true distance t [V, H, W], hit [V, H, W]."""
    o, d = cams.pixel_rays()
    b = (o * d).sum(-1)
    c = (o * o).sum(-1) - RADIUS**2
    disc = b * b - c
    hit = disc > 0
    t = -b - torch.sqrt(disc.clamp_min(0))
    p = o + t[..., None] * d
    img = torch.where(hit[..., None], _texture(p, flat), torch.ones(3)).permute(0, 3, 1, 2)
    return img.contiguous(), torch.where(hit, t, torch.zeros_like(t)), hit


def _inner(hit: torch.Tensor, px: int = 4) -> torch.Tensor:
    """hit pixels at least px from the outline (grazing rays left out of the comparison)."""
    k = 2 * px + 1
    return _box((~hit).float(), k) < 0.5


def test_recovers_true_depth_from_an_offset_surface():
    cams = _cameras([0.0, -25.0, 25.0])
    img, t_true, hit = _render(cams)
    # the "tracked" surface lies 5 mm behind the truth in view 0, 4 mm in front in the others
    t_surf = t_true + torch.tensor([0.005, -0.004, -0.004]).view(3, 1, 1) * hit
    res = stereo_ray_depth(img, cams, t_surf, hit, hit.float(), config=StereoConfig(occlusion_m=0.02))
    m = _inner(hit) & res.accepted
    assert m[0].float().sum() > 0.5 * _inner(hit)[0].float().sum()  # most of the frontal view is corrected
    before = (t_surf - t_true)[0][m[0]].abs().mean()
    after = (res.t - t_true)[0][m[0]].abs().mean()
    assert before > 0.0049
    assert after < 0.0015, f"mean |t - t_true| {after * 1e3:.2f} mm after the correction"
    # off the hit pixels nothing changes
    assert torch.equal(res.t[~hit], t_surf[~hit])


def test_true_surface_stays():
    cams = _cameras([0.0, -25.0, 25.0])
    img, t_true, hit = _render(cams)
    res = stereo_ray_depth(img, cams, t_true, hit, hit.float())
    m = _inner(hit)
    assert (res.t - t_true)[m].abs().mean() < 0.001


def test_single_view_and_flat_texture_fall_back():
    cams = _cameras([0.0, -25.0, 25.0])
    img, t_true, hit = _render(cams)
    t_surf = t_true + 0.005 * hit
    one = stereo_ray_depth(img[:1], cams[:1], t_surf[:1], hit[:1])
    assert torch.equal(one.t, t_surf[:1]) and not one.accepted.any()
    flat_img, _, _ = _render(cams, flat=True)
    flat = stereo_ray_depth(flat_img, cams, t_surf, hit, hit.float())  # the matte's outline is no texture
    assert torch.equal(flat.t, t_surf) and not flat.accepted.any()


def test_views_that_do_not_see_the_point_fall_back():
    cams = _cameras([0.0, 180.0])  # back to back: no surface point is seen by both
    img, t_true, hit = _render(cams)
    t_surf = t_true + 0.005 * hit
    res = stereo_ray_depth(img, cams, t_surf, hit)
    assert torch.equal(res.t, t_surf)
    assert int(res.seen.max()) == 0


def test_ncc_cost_volume_matches_a_per_pixel_loop():
    g = torch.Generator().manual_seed(0)
    h, w, k, win = 7, 8, 3, 3
    a = torch.rand(h, w, generator=g)
    b = torch.rand(k, h, w, generator=g)
    b[1] = 2.0 * a + 0.3  # a gain and a bias: NCC 1, cost 0
    wt = (torch.rand(k, h, w, generator=g) > 0.2).float()
    cost, sw = ncc_cost_volume(a, b, wt, win)
    r = win // 2
    for kk in range(k):
        for y in range(h):
            for x in range(w):
                ys, xs = slice(max(0, y - r), y + r + 1), slice(max(0, x - r), x + r + 1)
                ww, aa, bb = wt[kk, ys, xs].double(), a[ys, xs].double(), b[kk, ys, xs].double()
                s = ww.sum()
                assert abs(float(sw[kk, y, x]) - float(s)) < 1e-4
                if s < 1:
                    assert float(cost[kk, y, x]) == 1.0
                    continue
                ma, mb = (ww * aa).sum() / s, (ww * bb).sum() / s
                va, vb = (ww * (aa - ma) ** 2).sum() / s, (ww * (bb - mb) ** 2).sum() / s
                if va <= 1e-6 or vb <= 1e-6:
                    assert float(cost[kk, y, x]) == 1.0
                    continue
                ncc = (ww * (aa - ma) * (bb - mb)).sum() / s / torch.sqrt(va * vb)
                assert float(cost[kk, y, x]) == pytest.approx(1.0 - float(ncc.clamp(-1, 1)), abs=2e-4)
    inner = wt[1, 1:-1, 1:-1] > 0  # the gain/bias copy matches wherever its window has weight
    assert float(cost[1, 1:-1, 1:-1][inner].max()) < 1e-3


def test_band_pass_ignores_exposure_offset():
    g = torch.Generator().manual_seed(1)
    img = torch.rand(1, 3, 16, 16, generator=g) * 0.5
    assert torch.allclose(band_pass(img + 0.2, 2.0), band_pass(img, 2.0), atol=1e-5)
    m = torch.zeros(1, 16, 16)
    m[:, 4:12, 4:12] = 1.0
    flat = torch.full((1, 3, 16, 16), 0.3)
    flat[:, :, m[0] > 0] = 0.8  # a uniform patch on another background: its outline is no texture inside the mask
    assert band_pass(flat, 2.0, m).abs().max() < 1e-5


def test_shape_errors():
    cams = _cameras([0.0, 25.0])
    img, t, hit = _render(cams)
    with pytest.raises(ValueError):
        stereo_ray_depth(img, cams, t[:1], hit)
    with pytest.raises(ValueError):
        stereo_ray_depth(img, cams, t, hit, where=hit[:1])
    with pytest.raises(ValueError):
        StereoConfig(window=4)
    with pytest.raises(ValueError):
        StereoConfig(range_m=0.001, step_m=0.002)


def test_where_limits_the_corrected_pixels():
    cams = _cameras([0.0, -25.0, 25.0])
    img, t_true, hit = _render(cams)
    t_surf = t_true + 0.005 * hit
    where = torch.zeros_like(hit)
    where[:, :, :64] = True  # the left half only
    res = stereo_ray_depth(img, cams, t_surf, hit, hit.float(), where=where)
    assert torch.equal(res.t[~where], t_surf[~where])
    m = _inner(hit) & where
    assert (res.t - t_true)[0][m[0]].abs().mean() < (t_surf - t_true)[0][m[0]].abs().mean() - 0.002


def test_reconstruct_moves_only_the_hit_pixels_along_their_rays_when_asked(monkeypatch):
    """The hook in FastGHA.reconstruct: off by default; on, the real views' hit pixels' Gaussians move
    along their own rays by what stereo_ray_depth returns, with the configured range, and nothing else."""
    import numpy as np

    from fastgha_core.constants import BACKGROUND_RGB
    from fastgha_core.model import stereo
    from fastgha_core.model.fastgha import load_model
    from fastgha_core.model.surface import HeadSurface
    from fastgha_core.tracking.camera import pose_to_cameras
    from fastgha_core.tracking.fit import FRONTAL_R, default_intrinsics, rodrigues

    model = load_model("tiny")
    assert model.config.gaussians.stereo_depth_mm == 0.0
    s = model.config.input_size
    yaws = [0.0, 30.0]
    R = np.stack([FRONTAL_R @ rodrigues(np.array([0.0, np.radians(y), 0.0])) for y in yaws])
    cams = pose_to_cameras(R, np.tile([0.0, 0.01, 0.6], (2, 1)), default_intrinsics(s, s, 30.0), s, s)
    head = HeadSurface(np.zeros(100, np.float32), np.zeros((2, 53), np.float32))
    imgs = torch.tensor(BACKGROUND_RGB, dtype=torch.float32).view(1, 3, 1, 1).repeat(2, 1, s, s)
    imgs[:, :, s // 4 : 3 * s // 4, s // 4 : 3 * s // 4] = torch.rand(2, 3, s // 2, s // 2, generator=torch.Generator().manual_seed(0))
    seen = {}

    def fake(images, cameras, t, hit, fg=None, config=None, where=None):
        seen["range"], seen["hit"] = config.range_m, hit.clone()
        return stereo.StereoResult(t=t + 0.005 * hit, offset=0.005 * hit.float(), accepted=hit.clone(), seen=torch.zeros_like(t, dtype=torch.int32))

    monkeypatch.setattr(stereo, "stereo_ray_depth", fake)
    gc = model.config.gaussians
    saved = (gc.mirror_views, gc.prune_opacity, model.config.deform.prior, gc.stereo_depth_mm, gc.off_head_extrude_m)
    try:
        gc.mirror_views = False  # the photos' own Gaussians only
        gc.off_head_extrude_m = 0.0  # ... one per pixel (no copies of long hair further back)
        gc.prune_opacity, model.config.deform.prior = 0.0, False  # keep every pixel's Gaussian, in order
        off = model.reconstruct(imgs, cams, surface=head).gaussians
        assert not seen  # off by default: not called
        gc.stereo_depth_mm = 8.0
        on = model.reconstruct(imgs, cams, surface=head).gaussians
    finally:
        gc.mirror_views, gc.prune_opacity, model.config.deform.prior, gc.stereo_depth_mm, gc.off_head_extrude_m = saved
    assert seen["range"] == pytest.approx(0.008)
    hit = seen["hit"].reshape(-1)
    o, d = cams.pixel_rays()
    step = (on.means - off.means).reshape(-1, 3)
    assert bool(hit.any()) and torch.equal(step[~hit], torch.zeros_like(step[~hit]))
    assert torch.allclose(step[hit], 0.005 * d.reshape(-1, 3)[hit], atol=1e-5)
