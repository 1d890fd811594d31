"""Where the off-head pixels' Gaussians are drawn (``GaussianHeadConfig.off_head_draw``;
``model/coverage.py`` ``in_front_of_other_heads``, ``model/surface.py`` ``off_head_draw_flags``)."""

from __future__ import annotations

import pytest
import torch

from fastgha_core.cameras import Cameras
from fastgha_core.model.coverage import in_front_of_other_heads
from fastgha_core.model.surface import off_head_draw_flags
import test_surface_hull

head_case = test_surface_hull.head_case  # the tracked head seen from 0 / +-60 degrees, its mattes widened by 6 px: one fixture for the off-head tests


def _two_views(size=64):
    """View 0 looks down -z from (0, 0, 1), view 1 down -x from (1, 0, 0); view 1's 'head' is the plane x = 0."""
    cams = Cameras.look_at(torch.tensor([[0.0, 0.0, 1.0], [1.0, 0.0, 0.0]]), fov_deg=20.0, width=size, height=size)
    _, d = cams.pixel_rays()
    t = torch.ones(2, size, size)
    t[1] = 1.0 / (-d[1, ..., 0])  # each of view 1's rays ends on x = 0
    hit = torch.zeros(2, size, size, dtype=torch.bool)
    hit[1] = True
    return cams, t, hit, torch.ones(2, size, size)


def test_a_point_in_front_of_another_views_head_is_flagged_one_behind_it_is_not():
    cams, t, hit, fg = _two_views()
    take = torch.zeros_like(hit)
    y = 32
    take[0, y, [4, 32, 60]] = True  # x < 0 (behind view 1's plane), x = 0 (on it), x > 0 (in front of it)
    o, d = cams.pixel_rays()
    xs = (o[0, y, [4, 32, 60]] + d[0, y, [4, 32, 60]])[:, 0]
    assert float(xs[0]) < -0.1 and abs(float(xs[1])) < 0.01 and float(xs[2]) > 0.1
    out = in_front_of_other_heads(t, hit, take, cams, fg, tol_m=0.01)
    assert out[0, y].nonzero()[:, 0].tolist() == [60]
    assert int(out.sum()) == 1  # nothing else, and view 1 is not judged by anyone here
    # a view that is not among the judges flags nothing; a tolerance beyond the point's lead neither
    assert not bool(in_front_of_other_heads(t, hit, take, cams, fg, views=1).any())
    assert not bool(in_front_of_other_heads(t, hit, take, cams, fg, tol_m=float(xs[2]) + 0.05).any())
    # outside view 1's matte its head does not judge
    fg2 = fg.clone()
    fg2[1] = 0.0
    assert not bool(in_front_of_other_heads(t, hit, take, cams, fg2).any())
    with pytest.raises(ValueError, match="take"):
        in_front_of_other_heads(t, hit, take[:1], cams, fg)


def test_modes_change_only_the_off_head_pixels(head_case):
    _, cams, sd, fg = head_case
    off = ~sd.hit & ~sd.beyond_face & (fg > 0.5)
    assert int(off.sum()) > 100
    same, none = off_head_draw_flags(sd, cams, fg, "off")
    assert same is sd and none is None
    back, none = off_head_draw_flags(sd, cams, fg, "behind", behind_m=0.03)
    assert none is None and torch.equal(back.hit, sd.hit) and torch.equal(back.beyond_face, sd.beyond_face)
    assert torch.allclose(back.t[off], sd.t[off] + 0.03) and torch.equal(back.t[~off], sd.t[~off])
    bad = in_front_of_other_heads(sd.t, sd.hit, off, cams, fg, tol_m=0.01)
    assert bool(bad.any()) and bool((bad & ~off).sum() == 0) and int(bad.sum()) < int(off.sum())  # some, not all
    drop, none = off_head_draw_flags(sd, cams, fg, "drop", tol_m=0.01)
    assert none is None and torch.equal(drop.beyond_face, sd.beyond_face | bad) and torch.equal(drop.t, sd.t)
    s, sharp = off_head_draw_flags(sd, cams, fg, "sharp")
    assert s is sd and torch.equal(sharp, off)
    s, sharp = off_head_draw_flags(sd, cams, fg, "cover_sharp", tol_m=0.01)
    assert s is sd and torch.equal(sharp, bad)
    with pytest.raises(ValueError, match="mode"):
        off_head_draw_flags(sd, cams, fg, "sideways")


def _points(cams, t):
    o, d = cams.pixel_rays()
    return o + t[..., None] * d


def test_flags_match_a_plain_reference(head_case):
    """The flags against a direct reference: each off-head point projected into the other views and
    compared, pixel by pixel, with the nearest head point of the 3x3 pixels around it there."""
    _, cams, sd, fg = head_case
    off = ~sd.hit & ~sd.beyond_face & (fg > 0.5)
    bad = in_front_of_other_heads(sd.t, sd.hit, off, cams, fg, tol_m=0.01)
    p = _points(cams, sd.t)
    z_own = torch.stack([cams[i].world_to_camera(p[i].reshape(-1, 3))[:, 2].reshape(128, 128) for i in range(3)])
    head = sd.hit & (fg > 0.5)
    for i in range(3):
        pts = p[i][off[i]]
        want = torch.zeros(len(pts), dtype=torch.bool)
        for r in range(3):
            if r == i:
                continue
            uv, z = cams[r].project(pts)
            for k in range(len(pts)):
                x, y = int(uv[k, 0].floor()), int(uv[k, 1].floor())
                if not (0 <= x < 128 and 0 <= y < 128 and z[k] > 0 and head[r, y, x]):
                    continue
                near = [float(z_own[r, yy, xx]) for yy in range(max(y - 1, 0), min(y + 2, 128)) for xx in range(max(x - 1, 0), min(x + 2, 128)) if head[r, yy, xx]]
                want[k] |= float(z[k]) < min(near) - 0.01
        assert torch.equal(bad[i][off[i]], want), i
    assert bool(bad.any())


def test_reconstruct_drops_or_sharpens_only_the_off_head_gaussians_in_front_of_another_head(head_case):
    from fastgha_core.model import fastgha as F
    from fastgha_core.model.fastgha import load_model
    from fastgha_core.model.gaussian_head import foreground_weight

    surface, cams, sd, fg = head_case
    model = load_model("tiny")
    s = model.config.input_size
    gc = model.config.gaussians
    assert gc.off_head_draw == "under"  # the default (docs/model-card-log.md)
    default = gc.off_head_draw
    imgs = test_surface_hull.head_case_photos(fg, s)
    saved = gc.coverage_target, gc.mirror_views, gc.prune_opacity, gc.hair_fit, gc.head_on_colour_tol, gc.off_head_behind_ears, gc.off_head_smooth, gc.off_head_extrude_m
    # one Gaussian per pixel, at the nearest head pixel's distance (the fixture's sd)
    gc.coverage_target, gc.mirror_views, gc.prune_opacity, gc.hair_fit, gc.head_on_colour_tol, gc.off_head_behind_ears, gc.off_head_smooth, gc.off_head_extrude_m = 0.0, False, 0.0, False, 0.0, False, 0.0, 0.0
    out = {}
    try:
        for mode in ("off", "drop", "cover_sharp", "behind", "headon_sharp"):
            gc.off_head_draw = mode
            out[mode] = model.reconstruct(imgs, cams, surface=surface)
        gc.off_head_draw = "sideways"
        with pytest.raises(ValueError, match="mode"):
            model.reconstruct(imgs, cams, surface=surface)
    finally:
        gc.off_head_draw = default
        gc.coverage_target, gc.mirror_views, gc.prune_opacity, gc.hair_fit, gc.head_on_colour_tol, gc.off_head_behind_ears, gc.off_head_smooth, gc.off_head_extrude_m = saved
    n = 3 * s * s
    fw = foreground_weight(imgs)
    off = ~sd.hit & ~sd.beyond_face & (fw > 0.5)
    bad = in_front_of_other_heads(sd.t, sd.hit, off, cams, fw, 3, F.OFF_HEAD_COVER_TOL_M).reshape(-1)
    assert bool(bad.any()) and bool((off.reshape(-1) & ~bad).any())
    o_off, o_drop = out["off"].gaussians.opacities[:n], out["drop"].gaussians.opacities[:n]
    assert bool((o_off[bad] > 0).all()) and bool((o_drop[bad] == 0).all())  # the smear is dropped
    assert torch.equal(o_drop[~bad], o_off[~bad])  # the rest, other off-head pixels included, as before
    sharp = out["cover_sharp"].view_blend.sharp
    assert torch.equal(sharp, bad)  # drawn near their own camera only
    assert out["off"].view_blend.sharp is None or not bool(out["off"].view_blend.sharp.any())
    assert torch.equal(out["cover_sharp"].gaussians.opacities[:n], o_off)
    # headon_sharp: off-head Gaussians only, and only those some other view sees more head-on (a 60-degree view beside the frontal one's hair)
    hs = out["headon_sharp"].view_blend.sharp
    assert bool(hs.any()) and not bool((hs & ~off.reshape(-1)).any()) and int(hs.sum()) < int(off.sum())
    assert torch.equal(out["headon_sharp"].gaussians.opacities[:n], o_off)
    # behind: the off-head Gaussians move OFF_HEAD_BEHIND_M back along their own rays, nothing else moves
    dm = out["behind"].gaussians.means[:n] - out["off"].gaussians.means[:n]
    _, d = cams.pixel_rays()
    offf = off.reshape(-1)
    assert torch.allclose((dm * d.reshape(-1, 3)).sum(-1)[offf], torch.full((int(offf.sum()),), F.OFF_HEAD_BEHIND_M), atol=1e-4)
    assert float(dm[~offf].abs().max()) < 1e-6


def _random_gaussians(n, seed, centre, spread):
    from fastgha_core.gaussians import Gaussians

    g = torch.Generator().manual_seed(seed)
    q = torch.randn(n, 4, generator=g)
    return Gaussians(
        means=torch.tensor(centre) + (torch.rand(n, 3, generator=g) - 0.5) * spread,
        quats=q / q.norm(dim=-1, keepdim=True),
        scales=torch.rand(n, 3, generator=g) * 0.01 + 0.004,
        opacities=torch.rand(n, generator=g) * 0.6 + 0.2,
        colors=torch.rand(n, 3, generator=g),
    )


def test_push_under_draws_the_selected_gaussians_under_the_others_and_looks_the_same_alone():
    """Against a plain reference: two renders composited, C = C_rest + (1 - a_rest) (C_sel + (1 - a_sel) bg)."""
    from fastgha_core.gaussians import Gaussians
    from fastgha_core.model.viewblend import push_under
    from fastgha_core.render import render

    cam = Cameras.look_at(torch.tensor([[0.0, 0.0, 1.0]]), fov_deg=30.0, width=64, height=64)
    rest = _random_gaussians(300, 0, (0.0, 0.0, 0.1), 0.2)  # a blob at the back ...
    sel = _random_gaussians(200, 1, (0.0, 0.0, 0.25), 0.2)  # ... and one nearer the camera, over it
    g = Gaussians.concat([rest, sel])
    pick = torch.arange(len(g)) >= len(rest)
    means, scales = push_under(g.means, g.scales, cam, pick)
    gu = g.replace(means=means, scales=scales)
    assert torch.equal(means[~pick], g.means[~pick]) and torch.equal(scales[~pick], g.scales[~pick])
    z0, z1 = cam.world_to_camera(g.means)[0, :, 2], cam.world_to_camera(means)[0, :, 2]
    assert torch.allclose((z1 - z0)[pick], torch.full((int(pick.sum()),), 1.0), atol=1e-5)
    bg = torch.tensor([1.0, 1.0, 1.0])
    zero = torch.zeros(3)
    # alone, the moved Gaussians draw the same image
    a, b = render(sel, cam, background=bg), render(gu[pick], cam, background=bg)
    assert float((a.rgb - b.rgb).abs().max()) < 2e-3 and float((a.alpha - b.alpha).abs().max()) < 2e-3
    # together, the others are composited over them
    h, o = render(rest, cam, background=zero), render(sel, cam, background=zero)
    want = h.rgb + (1 - h.alpha) * (o.rgb + (1 - o.alpha) * bg.view(1, 3, 1, 1))
    got = render(gu, cam, background=bg)
    plain = render(g, cam, background=bg)
    assert float((got.rgb - want).abs().max()) < 2e-3
    assert float((plain.rgb - want).abs().max()) > 0.05  # without the push the nearer blob draws over the other
    with pytest.raises(ValueError, match="select"):
        push_under(g.means, g.scales, cam, pick[:10])


def test_under_is_recorded_saved_and_applied_per_frame(head_case, tmp_path):
    from fastgha_core.model.fastgha import load_model
    from fastgha_core.model.gaussian_head import foreground_weight
    from fastgha_core.model.viewblend import ViewBlend

    surface, cams, sd, fg = head_case
    model = load_model("tiny")
    s = model.config.input_size
    gc = model.config.gaussians
    imgs = test_surface_hull.head_case_photos(fg, s)
    saved = gc.coverage_target, gc.mirror_views, gc.prune_opacity, gc.hair_fit, gc.off_head_extrude_m
    gc.coverage_target, gc.mirror_views, gc.prune_opacity, gc.hair_fit, gc.off_head_extrude_m = 0.0, False, 0.0, False, 0.0
    default = gc.off_head_draw
    try:
        gc.off_head_draw = "off"
        off = model.reconstruct(imgs, cams, surface=surface)
        gc.off_head_draw = "under"
        on = model.reconstruct(imgs, cams, surface=surface)
    finally:
        gc.off_head_draw = default
        gc.coverage_target, gc.mirror_views, gc.prune_opacity, gc.hair_fit, gc.off_head_extrude_m = saved
    n = 3 * s * s
    want = (~sd.hit & ~sd.beyond_face & (foreground_weight(imgs) > 0.5)).reshape(-1)
    assert off.view_blend.under is None and torch.equal(on.view_blend.under, want)
    assert torch.equal(on.gaussians.means, off.gaussians.means) and torch.equal(on.gaussians.opacities, off.gaussians.opacities)
    # saved and loaded with the avatar's per-view data
    t = on.view_blend.tensors()
    assert torch.equal(ViewBlend.from_tensors(t, n).under, want)
    t.pop("view.under")
    assert ViewBlend.from_tensors(t, n).under is None  # older files: nothing drawn under
    # per frame: exactly the off-head Gaussians move, away from the frame's camera
    z = torch.zeros(model.config.expression_dim)
    cam = cams[0:1]
    g0, g1 = model.animate(off, z, camera=cam), model.animate(on, z, camera=cam)
    moved = (g1.means - g0.means).norm(dim=-1) > 1e-6
    assert torch.equal(moved[:n], want) and not bool(moved[n:].any())
    d0, d1 = cam.world_to_camera(g0.means)[0, :, 2], cam.world_to_camera(g1.means)[0, :, 2]
    assert torch.allclose((d1 - d0)[:n][want], torch.ones(int(want.sum())), atol=1e-4)
    assert torch.equal(g1.opacities, g0.opacities)
