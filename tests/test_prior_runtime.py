"""The expression prior's per-avatar caches and fast paths (``PriorRuntime``): each against its plain
reference (``prior.shading_basis``, ``fastgha._combine``), and rebuilt when the avatar changes."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from fastgha_core.data.headmodel import HeadModel
from fastgha_core.model.prior import PriorRuntime, _moving_vertices, bind, fit_head, load_basis, shading_at, shading_basis


@pytest.fixture(scope="module")
def basis():
    return load_basis("ict53")


@pytest.fixture(scope="module")
def identity(basis):
    rng = np.random.default_rng(5)
    ident = np.zeros(basis.identity_basis.shape[0], np.float32)
    ident[:12] = rng.standard_normal(12).astype(np.float32) * 0.8
    return ident


def test_shading_at_matches_shading_basis(basis, identity):
    """``shading_at`` (normals on only the triangles around the wanted vertices, one numba call) gives
    ``shading_basis``'s columns: moving vertices, vertices no blendshape moves (0) and repeats."""
    ref = shading_basis(identity, basis)  # [E, Nv]
    moving = _moving_vertices(basis)
    rng = np.random.default_rng(0)
    verts = np.concatenate([rng.choice(np.flatnonzero(moving), 500, replace=False), np.flatnonzero(~moving)[:20]])
    verts = np.concatenate([verts, verts[:7]])  # a vertex asked for twice
    got = shading_at(identity, basis, verts)
    assert got.shape == (basis.num_expression, len(verts)) and got.dtype == np.float32
    np.testing.assert_allclose(got, ref[:, verts], rtol=0, atol=1e-6)
    assert np.abs(ref[:, verts]).max() > 0.3  # real relighting among them, not all zeros
    assert np.all(got[:, ~moving[verts]] == 0)
    assert shading_at(identity, basis, np.zeros(0, np.int64)).shape == (basis.num_expression, 0)


def test_runtime_shading_reads_only_what_the_binding_uses(basis):
    """``PriorRuntime.shade_u`` fills the slots its binding reads (``shading_at``); the colour factor
    ``shading(z)`` equals the one from the full ``shading_basis`` for any expression."""
    hm = HeadModel.load()
    rng = np.random.default_rng(2)
    ident = np.zeros(hm.num_identity, np.float32)
    ident[:8] = rng.standard_normal(8) * 0.6
    pts = hm.vertices(ident)[:11248].astype(np.float32)
    fit = fit_head(pts, basis)
    sub = pts[rng.choice(len(pts), 3000, replace=False)] + rng.normal(0, 0.002, (3000, 3)).astype(np.float32)
    b = bind(torch.from_numpy(sub), fit, basis)
    rt = PriorRuntime(b, basis)
    full = np.zeros_like(rt.shade_u.numpy())
    full[:, 1:] = shading_basis(rt.identity, basis)[:, _moving_vertices(basis)]
    used = np.unique(rt.local.numpy())
    np.testing.assert_allclose(rt.shade_u.numpy()[:, used], full[:, used], rtol=0, atol=1e-6)
    assert len(used) < full.shape[1] // 2  # a few thousand points read a fraction of the slots
    w = rt.W
    for k in range(3):
        z = torch.rand(53, generator=torch.Generator().manual_seed(k)) * 0.8
        want = (1.0 + w @ (z @ torch.from_numpy(full))[:, None])[:, 0].clamp(0.5, 1.5)
        torch.testing.assert_close(rt.shading(z), want, rtol=0, atol=1e-5)
        assert float((want - 1).abs().max()) > 0.02


@pytest.fixture(scope="module")
def model_and_head():
    """The ``tiny`` model (random weights, a residual that moves and recolours) and a canonical head:
    the generic ICT skin as Gaussians."""
    from fastgha_core.config import get_preset
    from fastgha_core.gaussians import Gaussians
    from fastgha_core.model.fastgha import FastGHA

    torch.manual_seed(0)
    model = FastGHA(get_preset("tiny")).eval()
    with torch.no_grad():
        model.deform.out.weight.normal_(0.0, 0.02)
    v = torch.from_numpy(HeadModel.load().neutral[:11248:2].copy())
    n = len(v)
    g = Gaussians(v, torch.tensor([1.0, 0, 0, 0]).expand(n, 4).clone(), torch.full((n, 3), 0.002), torch.full((n,), 0.9), torch.full((n, 3), 0.6), torch.randn(n, 32) * 0.1)
    return model, g


def _same(a, b):
    assert len(a) == len(b)
    for k in ("means", "colors", "opacities", "quats", "scales"):
        assert torch.equal(getattr(a, k), getattr(b, k)), k


def test_frame_caches_are_rebuilt_when_the_avatar_changes(model_and_head, basis):
    """``animate`` keeps per-avatar caches (the MLP's first layer, the prior's runtime with its compact
    basis and shading). Replacing the avatar's binding or Gaussians by others of the same count, or
    animating it with a model whose ``prior_shading`` differs, gives the frame of a fresh avatar, not
    one from the stale caches."""
    import copy

    from fastgha_core.model.avatar import CanonicalAvatar
    from fastgha_core.model.prior import generic_fit

    model, g = model_and_head
    g2, b2, n_int = model.build_prior(g)
    avatar = CanonicalAvatar(g2, "tiny", "ict53", b2, n_int)
    names = HeadModel.load().expression_names
    z = torch.zeros(53)
    z[[names.index("jawOpen"), names.index("mouthSmile_L")]] = torch.tensor([0.7, 0.8])
    first = model.animate(avatar, z)
    rt = avatar.prior_runtime
    assert model.animate(avatar, z) is not None and avatar.prior_runtime is rt  # kept while nothing changes

    # another binding of the same Gaussians (the generic head instead of the fitted one), same count
    g3, b3, n3 = model.build_prior(g, head_fit=generic_fit(basis))
    assert len(g3) == len(g2) and n3 == n_int
    avatar.gaussians, avatar.prior = g3, b3
    got = model.animate(avatar, z)
    _same(got, model.animate(CanonicalAvatar(g3, "tiny", "ict53", b3, n3), z))
    assert float((got.means - first.means[: len(got)]).abs().max()) > 1e-3  # the binding matters here

    # Gaussians moved (the MLP's first layer reads their centres), same count and binding
    g4 = g3.replace(means=g3.means + torch.tensor([0.0, 0.004, 0.0]))
    avatar.gaussians = g4
    got = model.animate(avatar, z)
    _same(got, model.animate(CanonicalAvatar(g4, "tiny", "ict53", b3, n3), z))

    # a model without the expression shading animates the same avatar
    plain = copy.deepcopy(model)
    plain.config.deform.prior_shading = False
    got = plain.animate(avatar, z)
    _same(got, plain.animate(CanonicalAvatar(g4, "tiny", "ict53", b3, n3), z))
    assert float((got.colors - model.animate(avatar, z).colors).abs().max()) > 0.01  # shading on vs off differs


def test_gated_out_gaussians_between_drawn_ones_leave_the_image_unchanged(model_and_head):
    """A blink with closed lips: the mouth interior is gated out (opacity below ``ALPHA_MIN``) but sits
    between drawn Gaussians (the shell before it, the closed lids after), so ``animate`` keeps it in
    the list; the rasterizer skips it, and culling it gives the same image bit for bit (why the frame
    path does not gather the kept Gaussians: ``docs/benchmarks-log.md``, "Where the extra frame time goes")."""
    from fastgha_core.cameras import Cameras
    from fastgha_core.model.avatar import CanonicalAvatar
    from fastgha_core.render import render
    from fastgha_core.render.projection import ALPHA_MIN

    model, g = model_and_head
    g2, b2, n_int = model.build_prior(g)
    avatar = CanonicalAvatar(g2, "tiny", "ict53", b2, n_int)
    names = HeadModel.load().expression_names
    z = torch.zeros(53)
    z[[names.index("eyeBlink_L"), names.index("eyeBlink_R")]] = 1.0
    out = model.animate(avatar, z)
    assert len(out) == len(avatar.gaussians)  # nothing trailing to trim: the lids are drawn
    mouth = b2.groups()[: len(out)] == 0
    faint = out.opacities < ALPHA_MIN
    assert mouth.sum() > 100 and torch.all(faint[mouth]) and not faint[-1]
    cam = Cameras.look_at((0.0, 0.0, 0.6), (0.0, 0.0, 0.0), fov_deg=30.0, width=64, height=64)
    with torch.no_grad():
        a = render(out, cam, background=(1.0, 1.0, 1.0)).rgb
        b = render(out[~faint], cam, background=(1.0, 1.0, 1.0)).rgb
    assert torch.equal(a, b)
    assert float((a - 1.0).abs().max()) > 0.1  # the head is in the picture
