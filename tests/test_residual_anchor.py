"""``deform.anchor_residual`` (``FastGHA.residual_anchor``): on avatars reconstructed on a tracked head
surface, the deformation MLP's residual is taken relative to each Gaussian's own view's expression,
so at its photo's expression every Gaussian lies where reconstruction put it (its pixel's ray)."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from prior_frames import fast_and_plain

from fastgha_core.cameras import Cameras


def _cams(yaws_deg, size, dist=0.6):
    eyes = torch.tensor([[dist * math.sin(math.radians(a)), 0.0, dist * math.cos(math.radians(a))] for a in yaws_deg])
    return Cameras.look_at(eyes, torch.zeros(3), fov_deg=30.0, width=size, height=size)


@pytest.fixture(scope="module")
def tiny():
    from fastgha_core.model.fastgha import load_model

    model = load_model("tiny")
    model.config.gaussians.mirror_views = False
    return model


def _view_codes(model):
    sp = model.expression_space
    return torch.stack([
        torch.as_tensor(sp.parse({"mouthSmile_L": 0.7, "mouthSmile_R": 0.7}), dtype=torch.float32),
        torch.as_tensor(sp.parse({"jawOpen": 0.4}), dtype=torch.float32),
    ])  # fmt: skip


def _reconstructed(model, surface=True):
    from fastgha_core.constants import BACKGROUND_RGB
    from fastgha_core.model.surface import HeadSurface

    s = model.config.input_size
    cams = _cams([0.0, 35.0], s)
    g = torch.Generator().manual_seed(5)
    imgs = torch.tensor(BACKGROUND_RGB, dtype=torch.float32).view(1, 3, 1, 1).repeat(2, 1, s, s)
    imgs[:, :, s // 8 : 7 * s // 8, s // 4 : 3 * s // 4] = 0.2 + 0.5 * torch.rand(2, 3, 3 * s // 4, s // 2, generator=g)
    codes = _view_codes(model)
    if surface:
        head = HeadSurface(np.zeros(100, np.float32), codes.numpy())
        return model.reconstruct(imgs, cams, surface=head), codes
    return model.reconstruct(imgs, cams, codes), codes


@pytest.fixture(scope="module")
def surface_avatar(tiny):
    return _reconstructed(tiny)


def test_the_anchor_is_each_gaussians_residual_at_its_own_views_expression(tiny, surface_avatar):
    """Against a plain per-Gaussian evaluation of the MLP (``deform.forward``) at the Gaussian's view's code."""
    av, codes = surface_avatar
    anchor = tiny.residual_anchor(av)
    nr = av.num_reconstructed
    assert anchor is not None and anchor.shape == (nr, 3)
    sv = av.view_blend.source_view.long()
    assert set(sv.tolist()) == {0, 1}
    g = av.gaussians
    pick = torch.cat([(sv == v).nonzero().squeeze(1)[:50] for v in (0, 1)])
    with torch.no_grad():
        want = torch.stack([tiny.deform(g.features[i : i + 1], g.means[i : i + 1], codes[int(sv[i])])[0][0] for i in pick.tolist()])
    assert torch.allclose(anchor[pick], want, atol=1e-6)
    assert float(anchor.norm(dim=1).median()) > 1e-4  # the MLP does move them: the test can fail
    assert tiny.residual_anchor(av) is anchor  # cached with the MLP's first-layer term


@pytest.mark.parametrize("view", [0, 1])
def test_at_its_photos_expression_each_gaussian_sits_where_reconstruction_put_it(tiny, surface_avatar, view):
    """Animated at view ``view``'s code, that view's Gaussians move by the prior's displacement only
    (the neutralising shift undone: back onto their pixels' rays); both frame paths. With the flag
    off they are off by the MLP's residual, as before."""
    av, codes = surface_avatar
    z = codes[view]
    nr = av.num_reconstructed
    own = (av.view_blend.source_view.long() == view).nonzero().squeeze(1)
    tiny.animate(av, z)  # builds the prior's runtime
    with torch.inference_mode():
        placed = av.gaussians.means[:nr] + av.prior_runtime.displacement(z)[:nr]
    fast, plain = fast_and_plain(tiny, av, z)
    for g in (fast, plain):
        assert torch.allclose(g.means[own], placed[own], atol=2e-6)
    tiny.config.deform.anchor_residual = False
    try:
        off = tiny.animate(av, z)
        with torch.inference_mode():
            mlp = tiny.deform.forward_split(tiny._deform_partial(av), z)[0]
    finally:
        tiny.config.deform.anchor_residual = True
    assert torch.allclose(off.means[own], placed[own] + mlp[own], atol=2e-6)
    assert float((off.means[own] - placed[own]).norm(dim=1).max()) > 1e-4


def test_at_another_expression_the_expression_dependent_part_is_kept(tiny, surface_avatar):
    """Away from the photo's code the frame adds ``MLP(z) - MLP(z_view)``: the plain path's reference."""
    av, codes = surface_avatar
    z = torch.as_tensor(tiny.expression_space.parse({"eyeBlink_L": 1.0}), dtype=torch.float32)
    nr = av.num_reconstructed
    sv = av.view_blend.source_view.long()
    fast, _ = fast_and_plain(tiny, av, z)
    with torch.inference_mode():
        mlp = tiny.deform.forward_split(tiny._deform_partial(av), z)[0]
        ref = torch.zeros(nr, 3)
        for v in (0, 1):
            ref[sv == v] = tiny.deform.forward_split(tiny._deform_partial(av)[sv == v], codes[v])[0]
        want = av.gaussians.means[:nr] + av.prior_runtime.displacement(z)[:nr] + mlp - ref
    assert torch.allclose(fast.means[:nr], want, atol=2e-6)


def test_avatars_without_the_views_expressions_keep_the_plain_residual(tiny):
    """On the network's depth (no per-view data) nothing is anchored: frames are what they were."""
    av, _ = _reconstructed(tiny, surface=False)
    assert av.view_blend is None and tiny.residual_anchor(av) is None
    z = torch.as_tensor(tiny.expression_space.parse({"jawOpen": 0.5}), dtype=torch.float32)
    on = tiny.animate(av, z)
    tiny.config.deform.anchor_residual = False
    try:
        off = tiny.animate(av, z)
    finally:
        tiny.config.deform.anchor_residual = True
    assert torch.equal(on.means, off.means)


def test_view_expressions_of_another_shape_leave_the_residual_plain(tiny, surface_avatar, caplog):
    """A file's ``view.expr`` of another expression dimension loads (``tests/test_exprblend.py``): its
    frames are drawn as before the anchor, with one warning, instead of failing."""
    import dataclasses

    av, _ = surface_avatar
    short = dataclasses.replace(av, view_blend=dataclasses.replace(av.view_blend, expressions=av.view_blend.expressions[:, :52]))
    with caplog.at_level("WARNING"):
        assert tiny.residual_anchor(short) is None
        tiny.residual_anchor(short)
    assert sum("drawn without residual_anchor" in r.getMessage() for r in caplog.records) == 1
    z = torch.as_tensor(tiny.expression_space.parse({"jawOpen": 0.5}), dtype=torch.float32)
    tiny.config.deform.anchor_residual = False
    try:
        plain = tiny.animate(av, z)
    finally:
        tiny.config.deform.anchor_residual = True
    assert torch.equal(tiny.animate(short, z).means, plain.means)
