"""``GaussianHeadConfig.photo_shapes`` (``model/surface.py`` ``photo_pixel_shapes``): on a tracked head
surface, each input pixel's Gaussian keeps the photo's colour, is opaque on the matte and (with
``"colour_opacity_scale"``) is smaller; network-depth avatars are untouched."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from fastgha_core.cameras import Cameras
from fastgha_core.config import FastGHAConfig
from fastgha_core.constants import BACKGROUND_RGB
from fastgha_core.gaussians import Gaussians
from fastgha_core.model.gaussian_head import foreground_weight
from fastgha_core.model.surface import PHOTO_SHAPES_SCALE, photo_pixel_shapes


def _cams(yaws_deg, size, dist=0.6):
    eyes = torch.tensor([[dist * math.sin(math.radians(a)), 0.0, dist * math.cos(math.radians(a))] for a in yaws_deg])
    return Cameras.look_at(eyes, torch.zeros(3), fov_deg=30.0, width=size, height=size)


def _images(v, s, seed=5):
    g = torch.Generator().manual_seed(seed)
    imgs = torch.tensor(BACKGROUND_RGB, dtype=torch.float32).view(1, 3, 1, 1).repeat(v, 1, s, s)
    imgs[:, :, s // 8 : 7 * s // 8, s // 4 : 3 * s // 4] = torch.rand(v, 3, 3 * s // 4, s // 2, generator=g)  # includes values beyond [0.01, 0.99]
    bg = imgs.new_tensor(BACKGROUND_RGB)
    imgs[:, :, s // 8, s // 4 : 3 * s // 4] = (bg - 0.01 * torch.sign(bg - 0.5)).view(3, 1)  # an anti-aliased edge row: foreground weight 1/3
    return imgs


def _gaussians(n, seed=1):
    g = torch.Generator().manual_seed(seed)
    return Gaussians(
        means=torch.randn(n, 3, generator=g),
        quats=torch.nn.functional.normalize(torch.randn(n, 4, generator=g), dim=-1),
        scales=torch.rand(n, 3, generator=g) * 0.01 + 1e-4,
        opacities=torch.rand(n, generator=g) * 0.9,
        colors=torch.rand(n, 3, generator=g),
        features=torch.randn(n, 8, generator=g),
    )


def test_photo_pixel_shapes_against_a_plain_per_pixel_reference():
    v, s = 2, 16
    imgs = _images(v, s)
    g = _gaussians(v * s * s)
    for mode in ("colour_opacity", "colour_opacity_scale"):
        out = photo_pixel_shapes(g, imgs, mode)
        assert len(out) == len(g)
        k = 0
        for i in range(v):
            for y in range(s):
                for x in range(s):
                    px = imgs[i, :, y, x]
                    assert torch.allclose(out.colors[k], px.clamp(0.01, 0.99))
                    bg = (px - torch.tensor(BACKGROUND_RGB)).abs().max() / 0.03
                    want_op = 1.0 if float(bg.clamp(0, 1)) > 0.5 else float(g.opacities[k])
                    assert float(out.opacities[k]) == pytest.approx(want_op)
                    f = PHOTO_SHAPES_SCALE if mode == "colour_opacity_scale" else 1.0
                    assert torch.allclose(out.scales[k], g.scales[k] * f)
                    k += 1
        for name in ("means", "quats", "features"):
            assert torch.equal(getattr(out, name), getattr(g, name))
    # the edge row (foreground weight 1/3) keeps its opacity; the interior is opaque
    fg = foreground_weight(imgs).reshape(-1)
    assert bool(((fg > 0) & (fg <= 0.5)).any())
    assert photo_pixel_shapes(g, imgs, "off") is g


def test_photo_pixel_shapes_rejects_bad_arguments():
    imgs = _images(1, 8)
    g = _gaussians(64)
    with pytest.raises(ValueError, match="mode"):
        photo_pixel_shapes(g, imgs, "colour")
    with pytest.raises(ValueError, match="scale"):
        photo_pixel_shapes(g, imgs, "colour_opacity_scale", scale=0.0)
    with pytest.raises(ValueError, match="scale"):
        photo_pixel_shapes(g, imgs, "colour_opacity_scale", scale=float("nan"))
    with pytest.raises(ValueError, match="pixels"):
        photo_pixel_shapes(g[:63], imgs, "colour_opacity")


def test_validate_rejects_an_unknown_mode():
    cfg = FastGHAConfig()
    cfg.gaussians.photo_shapes = "colour_opacity"
    cfg.validate()
    cfg.gaussians.photo_shapes = "on"
    with pytest.raises(ValueError, match="photo_shapes"):
        cfg.validate()
    assert FastGHAConfig().gaussians.photo_shapes == "off"


@pytest.fixture(scope="module")
def tiny():
    from fastgha_core.model.fastgha import load_model

    model = load_model("tiny")
    gc = model.config.gaussians
    gc.mirror_views = False  # one Gaussian per input pixel, in order, first in the avatar:
    gc.prune_opacity = 0.0
    gc.coverage_target = 0.0
    gc.edge_margin_px = 0.0
    gc.grazing_stretch = 0.0  # the pixels' own sizes (the stretch of grazing pixels is tested in test_surface_grazing.py)
    return model


def _reconstruct(model, mode, surface=True):
    from fastgha_core.model.surface import HeadSurface

    s = model.config.input_size
    cams, imgs = _cams([0.0, 35.0], s), _images(2, s)
    sp = model.expression_space
    codes = torch.stack([torch.as_tensor(sp.parse({"jawOpen": 0.3}), dtype=torch.float32), torch.zeros(sp.dim)])
    old = model.config.gaussians.photo_shapes
    model.config.gaussians.photo_shapes = mode
    try:
        if surface:
            return model.reconstruct(imgs, cams, surface=HeadSurface(np.zeros(100, np.float32), codes.numpy())), imgs
        return model.reconstruct(imgs, cams, codes), imgs
    finally:
        model.config.gaussians.photo_shapes = old


def test_reconstruct_on_a_surface_takes_the_photos_colour_opacity_and_size(tiny):
    base, imgs = _reconstruct(tiny, "off")
    n = imgs.shape[0] * imgs.shape[2] * imgs.shape[3]
    fg = foreground_weight(imgs).reshape(-1) > 0.5
    b = base.gaussians
    assert not torch.allclose(b.colors[:n][fg], imgs.clamp(0.01, 0.99).permute(0, 2, 3, 1).reshape(-1, 3)[fg], atol=1e-3)  # the decoder's residual
    assert float(b.opacities[:n][fg].min()) < 0.99
    for mode, f in (("colour_opacity", 1.0), ("colour_opacity_scale", PHOTO_SHAPES_SCALE)):
        av, _ = _reconstruct(tiny, mode)
        g = av.gaussians
        assert len(g) == len(b)
        want = photo_pixel_shapes(b[:n], imgs, mode)
        assert torch.allclose(g.colors[:n], want.colors, atol=1e-6)
        dropped = b.opacities[:n] == 0  # reconstruct drops what lies off the head beside the face (SurfaceDepth.beyond_face) either way
        assert int((fg & ~dropped).sum()) > 1000
        assert torch.allclose(g.opacities[:n], torch.where(dropped, 0.0, torch.where(fg, 1.0, b.opacities[:n])))
        assert torch.allclose(g.scales[:n], b.scales[:n] * f, rtol=1e-5)
        assert torch.allclose(g.means[:n], b.means[:n]) and torch.equal(g.features[:n], b.features[:n])


def test_network_depth_avatars_are_untouched(tiny):
    a, _ = _reconstruct(tiny, "off", surface=False)
    c, _ = _reconstruct(tiny, "colour_opacity_scale", surface=False)
    for name in ("means", "quats", "scales", "opacities", "colors", "features"):
        assert torch.equal(getattr(a.gaussians, name), getattr(c.gaussians, name))


def test_off_never_calls_the_hook(tiny, monkeypatch):
    """"off" (the default) takes the code path of before the option: the hook is not reached."""
    import fastgha_core.model.surface as surface

    def boom(*a, **k):
        raise AssertionError("photo_pixel_shapes called with photo_shapes off")

    monkeypatch.setattr(surface, "photo_pixel_shapes", boom)
    assert tiny.config.gaussians.photo_shapes == "off"
    _reconstruct(tiny, "off")
    with pytest.raises(AssertionError, match="called"):
        _reconstruct(tiny, "colour_opacity")
