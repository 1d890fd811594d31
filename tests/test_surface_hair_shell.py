"""The hair layer kept inside the photos' outlines, and the back-of-head shell under it
(``model/surface.py`` ``hair_carve_fractions``, ``carve_into_mattes``, ``HeadSurface.head_fit(hair_m)``;
``FastGHA.reconstruct``'s ``hair_carve``, ``shell_on_hair``, ``shell_carve``; issue 17)."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from fastgha_core.data.headmodel import HeadModel
from fastgha_core.model.surface import (
    HeadSurface,
    carve_into_mattes,
    hair_carve_fractions,
    hair_vertex_weight,
    surface_ray_depth,
)
from test_mirror import _with  # the config-override context (one definition for the reconstruct tests)
from test_surface import _cameras  # head-centric cameras around the head (one definition for the surface tests)
from test_surface_coverage import _head_masks  # the fitted head's silhouette per view, as mattes


@pytest.fixture(scope="module")
def bald():
    return HeadSurface(np.zeros(100, np.float32), np.zeros((3, 53), np.float32))


def test_hair_the_mattes_hold_is_kept_and_hair_beyond_them_is_carved(bald):
    """Mattes of a head with 2 cm of hair keep 2 cm everywhere; mattes of the bald head carve the
    scalp's outline back (the vertices on it lose their hair) and keep what is inside it."""
    cams = _cameras([0.0, 60.0, -80.0])
    w = hair_vertex_weight(HeadModel.load())
    full = hair_carve_fractions(bald, cams, _head_masks(bald, cams, 0.02), 0.02)
    assert full.shape == (len(w),) and np.all(full[w > 0] == 1.0) and np.all(full[w == 0] == 1.0)
    carved = hair_carve_fractions(bald, cams, _head_masks(bald, cams, 0.0), 0.02)
    assert set(np.unique(carved)) <= {0.0, 0.25, 0.5, 0.75, 1.0}
    assert np.all(carved[w == 0] == 1.0)  # the face keeps its place (no hair there)
    scalp = w > 0.5
    assert 0.5 < float((carved[scalp] < 1).mean()) < 1.0  # three views around the head: most of the scalp is on some outline
    front = hair_carve_fractions(bald.subset([0]), cams[:1], _head_masks(bald.subset([0]), cams[:1], 0.0), 0.02)
    assert 0.2 < float((front[scalp] < 1).mean()) < 0.8  # one frontal view carves only its outline (the back stays inside it)
    # the carved layout stays inside the bald mattes: its outline does not grow beyond them
    grown = _head_masks(bald, cams, 0.02 * carved) - _head_masks(bald, cams, 0.0)
    assert float((grown > 0).float().mean()) < 0.25 * float(((_head_masks(bald, cams, 0.02) - _head_masks(bald, cams, 0.0)) > 0).float().mean())
    with pytest.raises(ValueError, match="foreground"):
        hair_carve_fractions(bald, cams, torch.ones(2, 128, 128), 0.02)
    assert np.all(hair_carve_fractions(bald, cams, torch.zeros(3, 128, 128), 0.0) == 1.0)  # no hair: nothing to carve


def test_per_vertex_hair_lays_out_the_surface_like_one_thickness(bald):
    """``surface_ray_depth`` takes the hair as one thickness or one per vertex; the same numbers
    give the same depths, and a thickness of 0 on some vertices leaves them bald."""
    cams = _cameras([0.0, 45.0, -45.0])
    n = HeadModel.load().num_vertices
    one = surface_ray_depth(bald, cams, 0.02)
    per = surface_ray_depth(bald, cams, np.full(n, 0.02, np.float32))
    assert torch.allclose(one.t, per.t) and torch.equal(one.hit, per.hit)
    none = surface_ray_depth(bald, cams, np.zeros(n, np.float32))
    assert torch.allclose(none.t, surface_ray_depth(bald, cams, 0.0).t)


def test_head_fit_lays_the_scalp_out_and_leaves_the_face():
    from fastgha_core.model.prior import load_basis

    basis = load_basis("ict53")
    s = HeadSurface(np.zeros(100, np.float32), np.zeros((1, 53), np.float32))
    b, h = s.head_fit(basis).vertices, s.head_fit(basis, 0.02).vertices
    w = hair_vertex_weight(HeadModel.load())
    d = np.linalg.norm(h - b, axis=1)
    assert np.allclose(d, 0.02 * w, atol=1e-5)  # the hair weight x thickness, along unit normals
    top = w > 0.99
    assert float(np.mean((h[top] - b[top])[:, 1] > 0)) > 0.4  # outward: up on the crown
    assert np.linalg.norm(h[top], axis=1).mean() > np.linalg.norm(b[top], axis=1).mean() + 0.015  # away from the head centre


def test_carve_into_mattes_moves_points_in_until_every_view_holds_them():
    cams = _cameras([0.0, 90.0])
    fg = torch.zeros(2, 128, 128)
    fg[:, 32:96, 32:96] = 1.0  # each view: a square of foreground around the head centre
    inside = torch.tensor([[0.0, 0.0, 0.0], [0.01, 0.0, 0.0]])
    outside = torch.tensor([[0.12, 0.0, 0.0], [0.0, 0.0, 0.12]])  # beyond the square in the frontal / the side view
    moved = carve_into_mattes(torch.cat([inside, outside]), cams, fg, step_m=0.005, max_m=0.08)
    assert torch.equal(moved[:2], inside)  # held by every view: unchanged
    for p, q in zip(outside, moved[2:]):
        assert float(q.norm()) < float(p.norm()) - 0.01  # pulled towards the centre
        assert torch.allclose(torch.nn.functional.normalize(q, dim=0), torch.nn.functional.normalize(p, dim=0), atol=1e-5)  # along the radius
        for i in range(2):  # and now inside both mattes
            uv, _ = cams[i].to(dtype=torch.float32).project(q[None])
            x, y = int(uv[0, 0]), int(uv[0, 1])
            assert fg[i, y, x] > 0.5
    far = carve_into_mattes(outside, cams, fg, step_m=0.005, max_m=0.02)  # too far to bring inside: left as it was
    assert torch.equal(far, outside)
    blind = carve_into_mattes(outside[:1], cams[:1].crop(200, 0, 128, 128), fg[:1])  # a view the point falls outside of does not judge it
    assert torch.equal(blind, outside[:1])
    with pytest.raises(ValueError, match="foreground"):
        carve_into_mattes(outside, cams, fg[:1])
    with pytest.raises(ValueError, match="step_m"):
        carve_into_mattes(outside, cams, fg, step_m=0.0)


# ------------------------------------------------------------------ reconstruction


@pytest.fixture(scope="module")
def tiny():
    from fastgha_core.model.fastgha import load_model

    return load_model("tiny")


def _inputs(model, yaws, hair_m=0.03):
    """Photos whose mattes are the tracked (generic) head with ``hair_m`` of hair, random colours inside."""
    from fastgha_core.constants import BACKGROUND_RGB

    s = model.config.input_size
    cams = _cameras(yaws, size=s).to(dtype=torch.float32)
    surface = HeadSurface(np.zeros(100, np.float32), np.zeros((len(yaws), 53), np.float32))
    fg = _head_masks(surface, cams, hair_m)
    g = torch.Generator().manual_seed(4)
    imgs = torch.tensor(BACKGROUND_RGB, dtype=torch.float32).view(1, 3, 1, 1).repeat(len(yaws), 1, s, s)
    col = 0.2 + 0.5 * torch.rand(len(yaws), 3, s, s, generator=g)
    imgs = imgs * (1 - fg[:, None]) + col * fg[:, None]
    return imgs, cams, surface, fg


def _shell(model, av):
    from fastgha_core.model.prior import back_shell_vertices

    k = len(back_shell_vertices(model.head_basis()))
    n = av.num_reconstructed
    return av.gaussians.means[n : n + k]


def test_the_shell_lies_under_the_hair_and_inside_every_matte(tiny):
    """With 3 cm of hair in the mattes the shell moves out to the hair (``shell_on_hair``) and,
    carved (``shell_carve``), no shell Gaussian stands beyond any input's outline."""
    imgs, cams, surface, fg = _inputs(tiny, [0.0, 60.0, -60.0])
    with _with(tiny, mirror_views=False, shell_on_hair=False, shell_carve=False):
        bald = _shell(tiny, tiny.reconstruct(imgs, cams, surface=surface))
    with _with(tiny, mirror_views=False, shell_carve=False):
        laid = _shell(tiny, tiny.reconstruct(imgs, cams, surface=surface))
    with _with(tiny, mirror_views=False):
        carved = _shell(tiny, tiny.reconstruct(imgs, cams, surface=surface))
    assert len(bald) == len(laid) == len(carved) > 100
    def r(m):  # distance from the head centre (the head frame's origin)
        return m.norm(dim=-1)

    assert float((r(laid) - r(bald)).median()) > 0.01  # the shell under the hair, not on the skull
    assert float((r(carved) - r(bald)).median()) > 0.01  # and it stays there where the mattes hold it

    def outside(m):
        n = 0
        for i in range(len(imgs)):
            uv, z = cams[i].project(m)
            x, y = uv[:, 0].floor().long(), uv[:, 1].floor().long()
            ok = (x >= 0) & (x < fg.shape[-1]) & (y >= 0) & (y < fg.shape[-2]) & (z > 0)
            dil = torch.nn.functional.max_pool2d(fg[i][None, None], 3, 1, 1)[0, 0]
            n += int((ok & (dil[y.clamp(0, fg.shape[-2] - 1), x.clamp(0, fg.shape[-1] - 1)] < 0.5)).sum())
        return n

    # mattes of a narrower head (bald): the laid-out shell stands beyond them, the carved one does not
    imgs_b, _, _, fg_b = _inputs(tiny, [0.0, 60.0, -60.0], hair_m=0.0)
    fg = fg_b
    with _with(tiny, mirror_views=False, shell_carve=False, hair_carve=False, hair_fit=True):
        loose = _shell(tiny, tiny.reconstruct(imgs_b, cams, surface=surface))
    with _with(tiny, mirror_views=False, hair_fit=True):
        tight = _shell(tiny, tiny.reconstruct(imgs_b, cams, surface=surface))
    assert outside(tight) <= max(2, outside(loose) // 10), (outside(loose), outside(tight))


def test_hair_carving_keeps_the_reconstructed_hair_inside_the_outlines(tiny):
    """With one thickness fitted for the whole scalp, the hair pixels of a head whose hair is thin
    at the sides are laid on a scalp wider than the photos; carved, they fall inside the mattes."""
    from fastgha_core.model.surface import fit_hair_thickness

    imgs, cams, surface, fg = _inputs(tiny, [0.0, 60.0, -60.0], hair_m=0.03)
    # thin the frontal matte's sides: the head is narrower there than the fitted hair makes it
    top = fg[0].nonzero()
    rows = top[:, 0]
    half = int(rows.min()) + (int(rows.max()) - int(rows.min())) // 3  # the upper third: the hair
    narrow = fg.clone()
    eroded = -torch.nn.functional.max_pool2d(-fg[0][None, None], (1, 9), 1, (0, 4))[0, 0]  # 4 px off each side of every row
    narrow[0, :half] = eroded[:half]
    from fastgha_core.constants import BACKGROUND_RGB

    bg = torch.tensor(BACKGROUND_RGB).view(3, 1, 1)
    imgs_n = imgs * narrow[:, None] + bg * (1 - narrow[:, None])
    hair = fit_hair_thickness(surface, cams, narrow)
    assert hair > 0
    frac = hair_carve_fractions(surface, cams, narrow, hair)
    assert int((frac < 1).sum()) > 50  # the sides of the scalp carved
    with _with(tiny, mirror_views=False, hair_carve=False):
        a = tiny.reconstruct(imgs_n, cams, surface=surface)
    with _with(tiny, mirror_views=False):
        b = tiny.reconstruct(imgs_n, cams, surface=surface)

    def beyond(av):  # solid reconstructed Gaussians that fall outside the frontal matte
        g = av.gaussians[: av.num_reconstructed]
        solid = g.opacities > 0.3
        uv, _ = cams[0].project(g.means[solid])
        x, y = uv[:, 0].floor().long().clamp(0, 127), uv[:, 1].floor().long().clamp(0, 127)
        return int((narrow[0][y, x] < 0.5).sum())

    assert beyond(b) < beyond(a), (beyond(a), beyond(b))


def test_without_a_surface_nothing_changes(tiny):
    """The network-depth path (synthetic evaluation) has no hair, no shell carving."""
    imgs, cams, _, _ = _inputs(tiny, [0.0, 40.0])
    with _with(tiny, hair_carve=False, shell_on_hair=False, shell_carve=False):
        a = tiny.reconstruct(imgs, cams)
    b = tiny.reconstruct(imgs, cams)
    assert torch.equal(a.gaussians.means, b.gaussians.means) and torch.equal(a.gaussians.opacities, b.gaussians.opacities)
