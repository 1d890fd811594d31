"""Filling each input view's matte (``fastgha_core/model/coverage.py``, issue 17): low-opacity
Gaussians that only one view has (long hair, shoulders) are raised until that view is covered."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from fastgha_core.gaussians import Gaussians
from fastgha_core.model.coverage import fill_coverage
from fastgha_core.render import render
from fastgha_core.tracking.camera import pose_to_cameras
from fastgha_core.tracking.fit import FRONTAL_R, default_intrinsics, rodrigues

S = 32


def _cameras(yaws_deg, size=S, dist=0.6):
    R = np.stack([FRONTAL_R @ rodrigues(np.array([0.0, np.radians(y), 0.0])) for y in yaws_deg])
    t = np.tile([0.0, 0.0, dist], (len(yaws_deg), 1))
    return pose_to_cameras(R, t, default_intrinsics(size, size, 30.0), size, size)


def _pixel_gaussians(cams, opacity):
    """One small isotropic Gaussian per pixel, on the pixel's ray at 0.6 m, view-major."""
    o, d = cams.pixel_rays()  # [V, H, W, 3]
    means = (o + 0.6 * d).reshape(-1, 3).float()
    n = len(means)
    fx = float(cams.K[0, 0, 0])
    scale = 0.6 / fx * 0.8  # 0.8 px footprints: neighbours overlap a little
    return Gaussians(
        means=means,
        quats=torch.tensor([1.0, 0, 0, 0]).repeat(n, 1),
        scales=torch.full((n, 3), scale),
        opacities=torch.as_tensor(opacity, dtype=torch.float32).reshape(-1).expand(n).clone(),
        colors=torch.full((n, 3), 0.5),
    )


def _disc(v, r=10.0):
    yy, xx = torch.meshgrid(torch.arange(S) + 0.5, torch.arange(S) + 0.5, indexing="ij")
    return ((yy - S / 2) ** 2 + (xx - S / 2) ** 2 < r * r).float().expand(v, S, S).clone()


def test_the_matte_of_every_input_view_ends_up_covered():
    cams = _cameras([0.0, 40.0])
    fg = _disc(2)
    g = _pixel_gaussians(cams, 0.02)
    before = render(g, cams).alpha[:, 0]
    assert float(before[fg > 0.5].mean()) < 0.3  # the setting: faint Gaussians leave the matte uncovered
    out, alpha = fill_coverage(g, cams, fg, target=0.9)
    assert torch.allclose(alpha, before)
    after = render(out, cams).alpha[:, 0]
    inside = fg > 0.5
    assert float(after[inside].min()) > 0.85 and float(after[inside].mean()) > 0.9
    # background pixels keep their Gaussians as they were
    o0, o1 = g.opacities.reshape(2, S, S), out.opacities.reshape(2, S, S)
    assert torch.equal(o0[~inside], o1[~inside])
    assert bool((o1 >= o0).all())  # opacities only go up


def test_covered_pixels_and_excluded_ones_are_left_alone():
    cams = _cameras([0.0])
    fg = torch.ones(1, S, S)
    op = torch.full((1, S, S), 0.95)
    op[0, :, : S // 2] = 0.05  # the left half is faint
    g = _pixel_gaussians(cams, op)
    excl = torch.zeros(1, S, S, dtype=torch.bool)
    excl[0, : S // 2] = True  # ... and the top half must stay as it is (e.g. dropped Gaussians)
    out, alpha = fill_coverage(g, cams, fg, target=0.9, exclude=excl)
    o = out.opacities.reshape(1, S, S)
    assert torch.equal(o[0, : S // 2], op[0, : S // 2])  # excluded
    assert torch.equal(o[0, :, S // 2 + 2 :], op[0, :, S // 2 + 2 :])  # covered already
    faint = o[0, S // 2 + 2 :, 2 : S // 2 - 2]
    assert float(faint.min()) > 0.8  # the faint, allowed part was raised
    assert float(render(out, cams).alpha[0, 0, S // 2 + 2 :, : S // 2].min()) > 0.85


def test_the_raise_is_what_brings_a_pixel_to_the_target():
    """Alpha compositing: with the others at accumulated ``a``, the own Gaussian needs
    ``1 - (1 - target)(1 - o)/(1 - a)``; a lone Gaussian on its own pixel (``a = o``) gets ``target``."""
    cams = _cameras([0.0])
    fg = torch.zeros(1, S, S)
    fg[0, 16, 16] = 1.0
    g = _pixel_gaussians(cams, 0.0)
    g = g.replace(opacities=torch.where(torch.arange(len(g)) == 16 * S + 16, 0.2, 0.0))
    out, alpha = fill_coverage(g, cams, fg, target=0.9)
    a = float(alpha[0, 16, 16])
    assert a == pytest.approx(0.2, abs=0.02)  # the Gaussian's peak sits on its pixel centre
    assert float(out.opacities[16 * S + 16]) == pytest.approx(1 - 0.1 * 0.8 / (1 - a), abs=1e-5)


def test_errors_say_what_was_expected():
    cams = _cameras([0.0, 40.0])
    g = _pixel_gaussians(cams, 0.1)
    with pytest.raises(ValueError, match="target"):
        fill_coverage(g, cams, _disc(2), target=1.0)
    with pytest.raises(ValueError, match="pixel-aligned"):
        fill_coverage(g[: S * S], cams, _disc(2))
    with pytest.raises(ValueError, match="foreground"):
        fill_coverage(g, cams, _disc(1))


def test_reconstruct_on_a_surface_covers_every_input_matte():
    """The tiny network leaves low-opacity Gaussians off the head; on the tracked surface the
    avatar now covers each input's matte from that input's camera (``coverage_target``), and the
    network-depth path (the synthetic evaluation's) is left as it was (``coverage_surface_only``)."""
    from fastgha_core.constants import BACKGROUND_RGB
    from fastgha_core.model.fastgha import load_model
    from fastgha_core.model.surface import HeadSurface

    model = load_model("tiny")
    assert model.config.gaussians.coverage_target == pytest.approx(0.9) and model.config.gaussians.coverage_surface_only
    model.config.gaussians.hair_fit = False  # the fill alone (the hair thickness has its own tests)
    model.config.gaussians.mirror_views = False  # ... and not the turned views' mirror images, which cover too (tests/test_mirror.py)
    s = model.config.input_size
    cams = _cameras([0.0, 40.0, -40.0], size=s)
    surface = HeadSurface(np.zeros(100, np.float32), np.zeros((3, 53), np.float32))
    g = torch.Generator().manual_seed(3)
    imgs = torch.tensor(BACKGROUND_RGB, dtype=torch.float32).view(1, 3, 1, 1).repeat(3, 1, s, s)
    fg = torch.zeros(3, s, s, dtype=torch.bool)
    fg[:, s // 8 : 7 * s // 8, s // 4 : 3 * s // 4] = True  # head, hair and shoulders: wider than the head mesh
    imgs[:, :, s // 8 : 7 * s // 8, s // 4 : 3 * s // 4] = 0.2 + 0.5 * torch.rand(3, 3, 3 * s // 4, s // 2, generator=g)
    zero = torch.zeros(model.config.expression_dim)

    def coverage(av):
        a = render(model.animate(av, zero), cams).alpha[:, 0]
        return float(a[fg].mean()), float((a[fg] < 0.5).float().mean())

    on = model.reconstruct(imgs, cams, surface=surface)
    model.config.gaussians.coverage_target = 0.0
    off = model.reconstruct(imgs, cams, surface=surface)
    (m_on, unc_on), (m_off, unc_off) = coverage(on), coverage(off)
    # 1.5% of the mattes uncovered without the fill (more than 3% before deform.anchor_residual: the
    # MLP's offset also moved Gaussians off the mattes), 0.1% with it
    assert unc_off > 0.01 and unc_on < 0.2 * unc_off, (unc_off, unc_on)
    assert m_on > 0.99 and m_on > m_off + 0.01, (m_on, m_off)  # 0.998 and 0.979
    # without a surface (the network's depth) nothing changes
    net_off = model.reconstruct(imgs, cams)
    model.config.gaussians.coverage_target = 0.9
    net_on = model.reconstruct(imgs, cams)
    assert torch.equal(net_on.gaussians.opacities, net_off.gaussians.opacities)


# ---------------------------------------------------------------- hair thickness (model/surface.py)


def _head_masks(surface, cams, hair_m):
    from fastgha_core.data.headmodel import HeadModel
    from fastgha_core.data.meshraster import render_mesh
    from fastgha_core.model.surface import _view_mesh

    head = HeadModel.load()
    faces = head.visible_faces(eyelashes=False)
    out = []
    for i in range(len(cams.K)):
        w2c, K = cams.w2c[i].double().numpy(), cams.K[i].double().numpy()
        pts = _view_mesh(surface, i, head, faces, hair_m) @ w2c[:3, :3].T + w2c[:3, 3]
        out.append(render_mesh(pts.astype(np.float32), faces, np.ones((len(pts), 1), np.float32), K, cams.width, cams.height, supersample=1).alpha > 0.5)
    return torch.from_numpy(np.stack(out)).float()


def test_hair_thickness_is_recovered_from_the_mattes():
    from fastgha_core.model.surface import HeadSurface, fit_hair_thickness

    surface = HeadSurface(np.zeros(100, np.float32), np.zeros((3, 53), np.float32))
    cams = _cameras([0.0, 50.0, -80.0], size=128)
    for true in (0.0, 0.015, 0.03):
        assert fit_hair_thickness(surface, cams, _head_masks(surface, cams, true)) == pytest.approx(true)
    with pytest.raises(ValueError, match="masks"):
        fit_hair_thickness(surface, cams, torch.ones(2, 128, 128))
    with pytest.raises(ValueError, match="candidates"):
        fit_hair_thickness(surface, cams, torch.ones(3, 128, 128), candidates=(-0.01,))


def test_hair_moves_the_scalp_out_and_leaves_the_face():
    from fastgha_core.model.surface import HeadSurface, surface_ray_depth

    surface = HeadSurface(np.zeros(100, np.float32), np.zeros((1, 53), np.float32))
    cams = _cameras([0.0], size=128)
    bald, hair = surface_ray_depth(surface, cams), surface_ray_depth(surface, cams, hair_m=0.02)
    both = bald.hit[0] & hair.hit[0]
    rows = torch.nonzero(both.any(1))[:, 0]
    crown = (slice(int(rows.min()) + 2, int(rows.min()) + 6), slice(60, 68))  # the top of the head, frontal
    face = (slice(70, 78), slice(60, 68))  # nose and mouth
    d_crown = (bald.t[0][crown] - hair.t[0][crown])[both[crown]]
    assert float(d_crown.median()) > 0.005  # the hair's surface is in front of the scalp
    assert float((bald.t[0][face] - hair.t[0][face]).abs().max()) < 1e-6
    assert int(hair.hit[0].sum()) > int(bald.hit[0].sum())  # and the head's outline grows
