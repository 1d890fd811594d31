"""Optical-flow registration of the input views' textures (``fastgha_core/model/flowreg.py``, issue 17)."""

from __future__ import annotations

import copy
import math

import numpy as np
import pytest
import torch

from fastgha_core.constants import BACKGROUND_RGB
from fastgha_core.data.headmodel import HeadModel
from fastgha_core.model.flowreg import (
    frontal_view,
    register_views,
    registration_order,
    reproject,
    smooth_flow,
    warp_image,
)
from fastgha_core.model.gaussian_head import foreground_weight
from fastgha_core.model.surface import HeadSurface, surface_ray_depth
from fastgha_core.tracking.camera import pose_to_cameras
from fastgha_core.tracking.fit import FRONTAL_R, default_intrinsics, rodrigues

SIZE = 128


def _cameras(yaws_deg, size=SIZE, dist=0.6, drop_m=0.01):
    """Head-centric cameras looking at the head from ``yaws_deg`` (as tests/test_surface.py)."""
    R = np.stack([FRONTAL_R @ rodrigues(np.array([0.0, np.radians(y), 0.0])) for y in yaws_deg])
    t = np.tile([0.0, drop_m, dist], (len(yaws_deg), 1))
    return pose_to_cameras(R, t, default_intrinsics(size, size, 30.0), size, size)


def _texture(head) -> np.ndarray:
    """``[Nv, 3]`` a smooth pattern fixed on the neutral head (blobs ~1-2 cm across), so that every
    view of one expression sees the same colour at the same surface point."""
    v = head.neutral.astype(np.float64)
    a = np.sin(2 * math.pi * v[:, 0] / 0.021) * np.cos(2 * math.pi * v[:, 1] / 0.017)
    b = np.sin(2 * math.pi * (v[:, 1] + v[:, 2]) / 0.029 + 1.0)
    return np.clip(np.stack([0.55 + 0.3 * a, 0.45 + 0.2 * b, 0.4 + 0.15 * a * b], 1), 0.02, 0.98).astype(np.float32)


def _views(surface, cams):
    """Images ``[V, 3, S, S]`` of the textured head matted on ``BACKGROUND_RGB``."""
    from fastgha_core.data.meshraster import render_mesh

    head = HeadModel.load()
    faces = head.visible_faces(eyelashes=False)
    tex = _texture(head)
    out = []
    flat = cams.flatten()
    for i in range(len(flat.K)):
        w2c, K = flat.w2c[i].double().numpy(), flat.K[i].double().numpy()
        pts = surface.vertices(i, head).astype(np.float64) @ w2c[:3, :3].T + w2c[:3, 3]
        m = render_mesh(pts.astype(np.float32), faces, tex, K, SIZE, SIZE, supersample=2)
        img = m.color + (1 - m.alpha[..., None]) * np.asarray(BACKGROUND_RGB, np.float32)
        out.append(torch.from_numpy(img).permute(2, 0, 1))
    return torch.stack(out).clamp(0, 1)


@pytest.fixture(scope="module")
def scene():
    rng = np.random.default_rng(3)
    ident = np.zeros(100, np.float32)
    ident[:20] = rng.standard_normal(20) * 0.7
    surface = HeadSurface(ident, np.zeros((2, 53), np.float32))
    cams = _cameras([0.0, 30.0])
    return surface, cams, surface_ray_depth(surface, cams), _views(surface, cams)


def _shifted(img: torch.Tensor, shift=(1.5, -1.0)) -> tuple[torch.Tensor, torch.Tensor]:
    """``img`` with its texture moved by a known smooth warp inside its matte (the matte kept): pixel
    ``p`` takes the colour at ``p + g(p)``, ``g`` the constant ``shift`` (pixels) fading to zero
    within 4 pixels of the outline. Returns ``(moved image, g [H, W, 2])``."""
    from scipy.ndimage import distance_transform_edt

    fg = foreground_weight(img)
    d = distance_transform_edt(fg.numpy() >= 1.0)
    fade = torch.from_numpy(np.clip((d - 2.0) / 4.0, 0, 1)).float()
    g = torch.tensor(shift, dtype=torch.float32) * fade[..., None]
    return warp_image(img, g), g


def _agreement(img1, ref_img, scene):
    """Mean absolute colour difference between view 1's image and view 0's image seen through the
    surface at view 1's pixels (``reproject``), over the pixels both see, at least 5 pixels inside
    view 1's matte."""
    from scipy.ndimage import distance_transform_edt

    surface, cams, sd, imgs = scene
    fg = foreground_weight(imgs)
    ref, ok = reproject(ref_img, cams[0], sd.t[0], sd.hit[0], fg[0], cams[1], sd.t[1], sd.hit[1], fg[1])
    inner = torch.from_numpy(distance_transform_edt(fg[1].numpy() >= 1.0) > 5)
    m = ok & inner
    assert int(m.sum()) > 1500
    return float((img1 - ref).abs().mean(0)[m].mean())


def test_reprojection_through_the_surface_matches_the_other_view(scene):
    surface, cams, sd, imgs = scene
    # the two renders agree through the surface to within the rasteriser's resampling
    assert _agreement(imgs[1], imgs[0], scene) < 0.03


def test_a_known_shift_of_one_view_is_undone(scene):
    surface, cams, sd, imgs = scene
    moved, g = _shifted(imgs[1])
    base = _agreement(imgs[1], imgs[0], scene)
    before = _agreement(moved, imgs[0], scene)
    assert before > 2.5 * base  # the shift is visible through the surface
    reg = register_views(torch.stack([imgs[0], moved]), cams, sd, surface)
    assert reg.parent == [-1, 0]
    assert torch.equal(reg.images[0], imgs[0]) and not reg.flow[0].any()  # the root (frontal) is untouched
    after = _agreement(reg.images[1], imgs[0], scene)
    assert after < 0.5 * before and after < 1.6 * base, (base, before, after)
    # the flow found is the inverse of the shift where it was measured
    m = reg.overlap[1] & (g.norm(dim=-1) > 1.7)
    assert int(m.sum()) > 500
    err = (reg.flow[1][m] + g[m]).norm(dim=-1)
    assert float(err.median()) < 0.5, float(err.median())
    # the matte does not move: no pixel sampled beyond it
    assert torch.equal(foreground_weight(reg.images[1]) > 0.5, foreground_weight(moved) > 0.5)


def test_mean_mode_meets_halfway(scene):
    """``mode="mean"``: no root; with two views each moves half way, so they meet in the middle."""
    surface, cams, sd, imgs = scene
    moved, g = _shifted(imgs[1], (2.0, -1.0))
    inp = torch.stack([imgs[0], moved])
    reg = register_views(inp, cams, sd, surface, mode="mean")
    assert reg.parent == [-1, -1] and reg.flow[0].any() and reg.flow[1].any()
    m = reg.overlap[1] & (g.norm(dim=-1) > 2.0)
    assert int(m.sum()) > 500
    assert float((reg.flow[1][m] + 0.5 * g[m]).norm(dim=-1).median()) < 0.4
    before = _agreement(moved, imgs[0], scene)
    after = _agreement(reg.images[1], reg.images[0], scene)
    assert after < 0.6 * before, (before, after)
    with pytest.raises(ValueError, match="mode"):
        register_views(inp, cams, sd, surface, mode="median")


def test_the_flow_is_clipped_and_fades_outside_the_overlap(scene):
    surface, cams, sd, imgs = scene
    moved, _ = _shifted(imgs[1], (3.0, 0.0))
    reg = register_views(torch.stack([imgs[0], moved]), cams, sd, surface, clip_px=2.0)  # 1 px at 128
    mag = reg.flow[1].norm(dim=-1)
    assert float(mag.max()) <= 1.0 + 1e-5 and float(mag.max()) > 0.9
    assert not bool(reg.flow[1][foreground_weight(moved) < 1.0].any())  # nothing moves at the outline or outside it
    # smooth_flow: a measurement continues outside, fading to zero, and nothing is invented without one
    f = np.zeros((40, 40, 2), np.float32)
    f[..., 0] = 2.0
    w = np.zeros((40, 40), np.float32)
    w[15:25, 15:25] = 1
    s = smooth_flow(f, w, 2.0, 3.0)
    assert abs(s[20, 20, 0] - 2.0) < 1e-4 and 0 < s[20, 29, 0] < s[20, 26, 0] < 2.0 and abs(s[20, 39, 0]) < 0.05
    assert not smooth_flow(f, np.zeros_like(w), 2.0, 3.0).any()


def test_order_chains_views_from_the_most_frontal_one():
    cams = _cameras([55.0, 5.0, -70.0, 30.0, 80.0])
    assert frontal_view(cams) == 1
    order = registration_order(cams, 1)
    assert [i for i, _ in order] == [3, 0, 2, 4]
    assert dict(order) == {3: 1, 0: 3, 2: 1, 4: 0}  # each to its nearest already registered view


def test_zero_flow_leaves_the_images_bit_for_bit(scene):
    surface, cams, sd, imgs = scene
    img = imgs[1]
    assert torch.equal(warp_image(img, torch.zeros(SIZE, SIZE, 2)), img)
    zero = lambda a, b: (np.zeros((*a.shape[:2], 2), np.float32),) * 2  # noqa: E731
    reg = register_views(imgs, cams, sd, surface, flow_fn=zero)
    assert torch.equal(reg.images, imgs)


def test_bad_arguments_raise(scene):
    surface, cams, sd, imgs = scene
    with pytest.raises(ValueError, match="clip_px"):
        register_views(imgs, cams, sd, surface, clip_px=0.0)
    with pytest.raises(ValueError, match="expected 1 cameras"):
        register_views(imgs[:1], cams, sd, surface)


def _avatar_inputs():
    from fastgha_core.model.fastgha import load_model

    model = load_model("tiny")
    rng = np.random.default_rng(5)
    ident = np.zeros(100, np.float32)
    ident[:20] = rng.standard_normal(20) * 0.7
    surface = HeadSurface(ident, np.zeros((2, 53), np.float32))
    cams = _cameras([0.0, 30.0])
    return model, surface, cams, _views(surface, cams)


@pytest.fixture(scope="module")
def avatar_inputs():
    return _avatar_inputs()


def _same(a, b) -> bool:
    ga, gb = a.gaussians, b.gaussians
    return all(torch.equal(getattr(ga, f), getattr(gb, f)) for f in ("means", "quats", "scales", "opacities", "colors", "features"))


def test_reconstruct_flag_off_never_registers_and_zero_flow_is_bit_for_bit(avatar_inputs, monkeypatch):
    import fastgha_core.model.flowreg as fr

    model, surface, cams, imgs = avatar_inputs
    model = copy.deepcopy(model)
    def boom(*a, **k):
        raise AssertionError("register_views called with the flag off")

    model.config.gaussians.flow_register = False
    with monkeypatch.context() as mp:
        mp.setattr(fr, "register_views", boom)
        off = model.reconstruct(imgs, cams, surface=surface)  # the old path: no registration at all
    model.config.gaussians.flow_register = True
    zero = lambda a, b: (np.zeros((*a.shape[:2], 2), np.float32),) * 2  # noqa: E731
    with monkeypatch.context() as mp:
        mp.setattr(fr, "dense_flow", zero)
        on0 = model.reconstruct(imgs, cams, surface=surface)
    assert _same(off, on0)
    # with a real flow on a shifted view the avatar changes, only through view 1's colours
    moved, _ = _shifted(imgs[1])
    inp = torch.stack([imgs[0], moved])
    model.config.gaussians.flow_register = False
    a_off = model.reconstruct(inp, cams, surface=surface)
    model.config.gaussians.flow_register = True
    a_on = model.reconstruct(inp, cams, surface=surface)
    assert not _same(a_off, a_on)


def test_reconstruct_registered_view_colours_agree_with_the_reference(avatar_inputs):
    """Each Gaussian of the shifted view takes (through its input pixel) a colour near what view 0
    sees at its point once registered, and not without the registration."""
    model, surface, cams, imgs = avatar_inputs
    model = copy.deepcopy(model)
    model.config.gaussians.mirror_views = False
    moved, _ = _shifted(imgs[1])
    inp = torch.stack([imgs[0], moved])
    errs = {}
    for flag in (False, True):
        model.config.gaussians.flow_register = flag
        av = model.reconstruct(inp, cams, surface=surface)
        src = av.view_blend.source_view.long()
        n = len(src)
        g = av.gaussians[:n]
        # the colour view 0 sees at each of view 1's Gaussians' points (its input pixel's colour)
        uv, _ = cams[0].to(dtype=torch.float32).project(g.means[src == 1].float())
        grid = torch.stack([uv[:, 0] / SIZE * 2 - 1, uv[:, 1] / SIZE * 2 - 1], -1).float()
        ref = torch.nn.functional.grid_sample(imgs[0][None], grid[None, None], align_corners=False)[0, :, 0].T
        uv1, _ = cams[1].to(dtype=torch.float32).project(g.means[src == 1].float())
        sd = surface_ray_depth(surface, cams)
        fg = foreground_weight(imgs)
        ok_ref, ok = reproject(imgs[0], cams[0], sd.t[0], sd.hit[0], fg[0], cams[1], sd.t[1], sd.hit[1], fg[1])
        px = uv1.floor().long().clamp(0, SIZE - 1)
        seen = ok[px[:, 1], px[:, 0]] & (g.opacities[src == 1] > 0.5)
        errs[flag] = float((g.colors[src == 1][seen] - ref[seen]).abs().mean())
    assert errs[True] < 0.3 * errs[False], errs  # measured 0.078 -> 0.008


def test_reconstruct_rejects_bad_config_values(avatar_inputs):
    model, surface, cams, imgs = avatar_inputs
    model = copy.deepcopy(model)
    model.config.gaussians.flow_register = True
    for bad in (0.0, -1.0, float("nan"), float("inf"), "4", True):
        model.config.gaussians.flow_register_clip_px = bad
        with pytest.raises(ValueError, match="flow_register_clip_px"):
            model.reconstruct(imgs, cams, surface=surface)
    model.config.gaussians.flow_register_clip_px = 4.0
    model.config.gaussians.flow_register = "yes"
    with pytest.raises(ValueError, match="flow_register must be"):
        model.reconstruct(imgs, cams, surface=surface)
