"""Off-head pixels on the visual hull of the other views' mattes (``model/surface.py``
``hull_ray_depth``, ``off_head_on_hull``; ``GaussianHeadConfig.off_head_hull``)."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from fastgha_core.cameras import Cameras
from fastgha_core.model.surface import (
    HeadSurface,
    _matte_votes,
    _mattes,
    hull_ray_depth,
    neck_ring_vertices,
    off_head_on_hull,
    surface_ray_depth,
)
from test_surface import _cameras  # head-centric cameras around the head (one definition for the surface tests)

R_SPHERE = 0.1  # metres, at the origin


def _sphere_views(size=256):
    eyes = torch.tensor([[0.0, 0.0, 1.0], [1.0, 0.0, 0.0], [-0.7071, 0.0, 0.7071], [0.0, 0.8, 0.6]])
    return Cameras.look_at(eyes, fov_deg=20.0, width=size, height=size)


def _sphere_mattes(cams):
    """Exact mattes of the sphere: a pixel centre's ray within the silhouette cone's half-angle."""
    o, d = cams.pixel_rays()
    axis = -o / o.norm(dim=-1, keepdim=True)
    cos_half = torch.sqrt(1 - (R_SPHERE / o.norm(dim=-1)) ** 2)
    return ((d * axis).sum(-1) >= cos_half).float()  # [V, H, W]


def _cone_interval(o, d, c):
    """``[P, 2]`` the part of each ray ``o + s d`` (``[P, 3]``, unit ``d``) inside the front nappe of the
    silhouette cone of the sphere from camera centre ``c [3]`` (solved from the quadratic); NaN if none."""
    a = -c / c.norm()
    k = 1 - (R_SPHERE / float(c.norm())) ** 2  # cos^2 of the half-angle
    q = o - c
    qa, da = q @ a, d @ a
    A = da**2 - k
    B = 2 * (qa * da - k * (q * d).sum(-1))
    C = qa**2 - k * (q * q).sum(-1)
    disc = B**2 - 4 * A * C
    r = torch.sqrt(disc.clamp_min(0))
    s1, s2 = (-B - r) / (2 * A), (-B + r) / (2 * A)
    lo, hi = torch.minimum(s1, s2), torch.maximum(s1, s2)
    bad = (disc < 0) | (A >= 0)  # the rays here cross the cone's axis at a steep angle: a bounded interval
    return torch.where(bad[:, None], torch.full_like(torch.stack([lo, hi], 1), float("nan")), torch.stack([lo, hi], 1))


def test_hull_entry_is_where_the_ray_enters_every_other_views_silhouette_cone():
    cams = _sphere_views()
    fg = _sphere_mattes(cams)
    take = torch.zeros_like(fg, dtype=torch.bool)
    take[0] = fg[0] > 0.5  # view 0's sphere pixels
    t = hull_ray_depth(cams, fg, take, step_m=0.0005, dilate_px=0)
    assert torch.isnan(t[1:]).all() and torch.isnan(t[0][~take[0]]).all()  # only the taken pixels
    o, d = cams[0].pixel_rays()
    o, d = o[take[0]], d[take[0]]
    iv = torch.stack([_cone_interval(o, d, cams.centers[j]) for j in (1, 2, 3)])  # [3, P, 2]
    entry, exit_ = iv[..., 0].max(0).values, iv[..., 1].min(0).values
    sure = entry < exit_ - 0.01  # a hull segment longer than 1 cm (not grazing its outline)
    got = t[0][take[0]]
    assert int(sure.sum()) > 1000 and torch.isfinite(got[sure]).all()
    err = (got - entry)[sure].abs()
    # a pixel of 1.4 mm at 1 m, the point's pixel taken by its floor, rays crossing some cones at a grazing angle
    q99 = float(torch.quantile(err, 0.99))
    assert float(err.median()) < 0.001 and q99 < 0.004 and float(err.max()) < 0.01, (float(err.median()), q99, float(err.max()))
    # the hull contains the sphere: its entry is never behind the sphere's own surface
    b = (o * d).sum(-1)
    s_sphere = -b - torch.sqrt((b**2 - ((o * o).sum(-1) - R_SPHERE**2)).clamp_min(0))
    hits = (b**2 - ((o * o).sum(-1) - R_SPHERE**2)) > 0
    assert bool((entry[sure & hits] <= s_sphere[sure & hits] + 1e-5).all())  # (the analytic cones' own check)
    assert float((got - s_sphere)[sure & hits].max()) < 0.01 and float((got <= s_sphere + 0.002)[sure & hits].float().mean()) > 0.99
    # a wider matte (dilated for misregistration) is entered earlier, never later
    t2 = hull_ray_depth(cams, fg, take, step_m=0.0005, dilate_px=2)[0][take[0]]
    both = torch.isfinite(got) & torch.isfinite(t2)
    assert bool((t2[both] <= got[both] + 1e-6).all()) and float((got - t2)[both].mean()) > 0.0005


def test_middle_is_halfway_through_the_hull_and_known_surfaces_carve_the_space_in_front_of_them():
    cams = _sphere_views()
    fg = _sphere_mattes(cams)
    take = torch.zeros_like(fg, dtype=torch.bool)
    take[0, 100:156, 100:156] = True  # the sphere's middle in view 0
    o, d = cams[0].pixel_rays()
    o, d = o[take[0]], d[take[0]]
    iv = torch.stack([_cone_interval(o, d, cams.centers[j]) for j in (1, 2, 3)])
    want = 0.5 * (iv[..., 0].max(0).values + iv[..., 1].min(0).values)
    mid = hull_ray_depth(cams, fg, take, step_m=0.0005, dilate_px=0, middle=True)[0][take[0]]
    assert float((mid - want).abs().max()) < 0.004
    # view 1 sees the sphere's surface: in front of it (from view 1) there is nothing
    o1, d1 = cams[1].pixel_rays()
    b = (o1 * d1).sum(-1)
    disc = b**2 - ((o1 * o1).sum(-1) - R_SPHERE**2)
    solid = torch.zeros_like(take)
    solid[1] = disc > 0
    solid_t = torch.where(solid, -b - torch.sqrt(disc.clamp_min(0)), torch.zeros_like(b))
    entry = hull_ray_depth(cams, fg, take, step_m=0.0005, dilate_px=0)[0][take[0]]
    carved = hull_ray_depth(cams, fg, take, step_m=0.0005, dilate_px=0, solid=solid, solid_t=solid_t, free_tol_m=0.002)[0][take[0]]
    both = torch.isfinite(entry) & torch.isfinite(carved)
    assert int(both.sum()) > 0.9 * len(entry)
    assert bool((carved[both] >= entry[both] - 1e-6).all())  # only ever pushed back
    assert float(((carved - entry)[both] > 0.002).float().mean()) > 0.02  # (where view 1 sees the hull's front beyond the sphere)
    p = o + carved[:, None] * d
    uv, _ = cams[1].project(p[both])
    x, y = uv[:, 0].floor().long().clamp(0, 255), uv[:, 1].floor().long().clamp(0, 255)
    on = solid[1][y, x]
    dist = (p[both] - cams.centers[1]).norm(dim=-1)
    assert bool((dist[on] >= solid_t[1][y, x][on] - 0.002 - 1e-5).all())  # never in front of view 1's surface


def test_prefer_keeps_a_distance_inside_the_hull_and_moves_one_outside_it_to_the_nearest_hull_point():
    cams = _sphere_views()
    fg = _sphere_mattes(cams)
    take = torch.zeros_like(fg, dtype=torch.bool)
    take[0, 120:136, 120:136] = True  # the sphere's centre: the hull segment is long
    entry = hull_ray_depth(cams, fg, take, step_m=0.0005, dilate_px=0)
    inside = entry + 0.03
    kept = hull_ray_depth(cams, fg, take, prefer=inside, step_m=0.0005, dilate_px=0)
    assert torch.equal(kept[take], inside[take])
    in_front = entry - 0.05
    moved = hull_ray_depth(cams, fg, take, prefer=in_front, step_m=0.0005, dilate_px=0)
    assert float((moved[take] - entry[take]).abs().max()) <= 0.0005 + 1e-6


def test_a_pixel_no_other_view_judges_keeps_no_hull_distance():
    cams = _sphere_views()
    fg = _sphere_mattes(cams)
    take = fg > 0.5
    # one view alone: its own matte never judges its own rays
    one = hull_ray_depth(cams[:1], fg[:1], take[:1])
    assert torch.isnan(one).all()
    # a second camera behind the first, looking the same way, never sees the first's rays in front of it
    behind = Cameras.look_at(torch.tensor([[0.0, 0.0, 1.0], [0.0, 0.0, -1.0]]), torch.tensor([[0.0, 0.0, 0.0], [0.0, 0.0, -2.0]]), fov_deg=20.0, width=64, height=64)
    fg2 = torch.ones(2, 64, 64)
    t = hull_ray_depth(behind, fg2, fg2 > 0.5, half_m=0.3)
    assert torch.isnan(t).all()  # (camera 1's own interval around the origin lies behind it: no sample at all)
    # turned round, camera 1 faces camera 0's rays: its all-foreground matte takes them
    facing = Cameras.look_at(torch.tensor([[0.0, 0.0, 1.0], [0.0, 0.0, -1.0]]), fov_deg=20.0, width=64, height=64)
    t = hull_ray_depth(facing, fg2, fg2 > 0.5, half_m=0.3)
    o, d = facing.pixel_rays()
    assert torch.allclose(t, (-o * d).sum(-1) - 0.3, atol=1e-4)  # the interval's first sample: the centre's distance - 0.3 m
    # a matte that holds nothing of the ray: no sample is in the hull either
    empty = fg.clone()
    empty[1:] = 0
    assert torch.isnan(hull_ray_depth(cams, empty, take)[0]).all()
    with pytest.raises(ValueError, match="take"):
        hull_ray_depth(cams, fg, take[:2])
    with pytest.raises(ValueError, match="step_m"):
        hull_ray_depth(cams, fg, take, step_m=0.0)


def test_beyond_the_image_the_matte_continues_from_its_border():
    cams = _sphere_views(size=64)
    fg = torch.zeros(4, 64, 64)
    fg[:, 60:, :] = 1.0  # the bottom rows: a torso cut by the image's edge
    below = torch.tensor([[0.0, -1.0, 0.0]])  # projects below every image but view 3's
    ok_b, judged_b = _matte_votes(below, cams[:3], _mattes(fg[:3], 0), beyond=True)
    ok_a, judged_a = _matte_votes(below, cams[:3], _mattes(fg[:3], 0), beyond=False)
    assert bool(ok_b[0] and judged_b[0]) and bool(ok_a[0] and not judged_a[0])
    beside = torch.tensor([[0.0, 0.0, 0.0]]) + torch.tensor([[0.0, 0.9, 0.0]])  # above every image: the border there is air
    ok, judged = _matte_votes(beside, cams[:3], _mattes(fg[:3], 0), beyond=True)
    assert bool(judged[0]) and not bool(ok[0])


# ---------------------------------------------------------------- on the tracked head


@pytest.fixture(scope="module")
def head_case():
    rng = np.random.default_rng(3)
    ident = np.zeros(100, np.float32)
    ident[:20] = rng.standard_normal(20) * 0.7
    surface = HeadSurface(ident, np.zeros((3, 53), np.float32))
    cams = _cameras([0.0, 60.0, -60.0], dist=0.7, drop_m=-0.06)
    sd = surface_ray_depth(surface, cams)
    # the person: the head, widened by 6 pixels (hair, a scarf: what the mesh does not hold), and in
    # the frontal view a strip below the image's middle too wide for any other view to hold
    fg = _mattes(sd.hit.float(), 6).float()
    return surface, cams, sd, fg


def head_case_photos(fg: torch.Tensor, size: int) -> torch.Tensor:
    """``[3, 3, size, size]`` input photos for ``head_case``: the background colour, and uniform noise
    in [0.25, 0.75) where the matte ``fg [3, size, size]`` > 0.5 (after ``torch.manual_seed(0)``)."""
    from fastgha_core.constants import BACKGROUND_RGB

    imgs = torch.tensor(BACKGROUND_RGB, dtype=torch.float32).view(1, 3, 1, 1).repeat(3, 1, size, size)
    torch.manual_seed(0)
    return torch.where(fg[:, None] > 0.5, torch.rand(3, 3, size, size) * 0.5 + 0.25, imgs)


def _points(cams, t):
    o, d = cams.pixel_rays()
    return o + t[..., None] * d


def test_off_head_pixels_move_into_the_other_views_mattes_and_nothing_else_moves(head_case):
    surface, cams, sd, fg = head_case
    out = off_head_on_hull(sd, surface, cams, fg, "entry", dilate_px=2)
    moved = out.t != sd.t
    off_head = ~sd.hit & ~sd.beyond_face & (fg > 0.5)
    assert not bool((moved & ~off_head).any())  # head pixels and the background keep their distances
    assert int(moved.sum()) > 0.5 * int(off_head.sum())
    assert torch.equal(out.hit, sd.hit) and torch.equal(out.beyond_face, sd.beyond_face)
    m = _mattes(fg, 2)
    p = _points(cams, out.t)
    for i in range(3):
        others = [j for j in range(3) if j != i]
        sel = moved[i]
        ok, judged = _matte_votes(p[i][sel], cams[others], m[others])
        assert bool((ok & judged).all()), i
        # where the ray enters the hull: the sample one step nearer the camera is outside it
        q = _points(cams, out.t - 0.004)[i][sel]
        ok_q, judged_q = _matte_votes(q, cams[others], m[others])
        assert float((ok_q & judged_q).float().mean()) < 0.05
    # "nearest" keeps every nearest-head placement the others' mattes already hold
    near = off_head_on_hull(sd, surface, cams, fg, "nearest", dilate_px=2)
    p0 = _points(cams, sd.t)
    for i in range(3):
        others = [j for j in range(3) if j != i]
        ok, judged = _matte_votes(p0[i][off_head[i]], cams[others], m[others])
        kept = (near.t[i] == sd.t[i])[off_head[i]]
        assert bool(kept[ok & judged].all())
    with pytest.raises(ValueError, match="mode"):
        off_head_on_hull(sd, surface, cams, fg, "exit")


def test_collar_moves_only_head_pixels_below_the_neck_ring_that_the_hull_rejects(head_case):
    from fastgha_core.data.headmodel import HeadModel

    surface, cams, sd, fg = head_case
    p0 = _points(cams, sd.t)
    head = HeadModel.load()
    ring_low = float(surface.vertices(0, head)[neck_ring_vertices(head), 1].min())
    # a person whose neck is narrower than ICT's collar, which the turned views' mattes say: they leave out
    # the mesh's points below the ring more than 1 cm beyond the ring's radius; the frontal matte holds them
    ring = torch.from_numpy(surface.vertices(0, head)[neck_ring_vertices(head)]).float()
    c = ring.mean(0)
    radius = float((ring[:, [0, 2]] - c[[0, 2]]).norm(dim=-1).median())
    wide = (p0[..., 1] < ring_low) & ((p0[..., [0, 2]] - c[[0, 2]]).norm(dim=-1) > radius + 0.01) & sd.hit
    narrow = fg.clone()
    narrow[1:][wide[1:]] = 0.0
    base = off_head_on_hull(sd, surface, cams, narrow, "entry")
    out = off_head_on_hull(sd, surface, cams, narrow, "entry", collar=True)
    changed = (out.t != base.t) & (narrow > 0.5)
    assert bool(changed.any())
    assert bool((sd.hit[changed] & (p0[changed][:, 1] < ring_low)).all())  # only the mesh's pixels below the ring
    m = _mattes(narrow, 2)
    for i in range(3):
        others = [j for j in range(3) if j != i]
        ok_old, _ = _matte_votes(p0[i][changed[i]], cams[others], m[others])
        assert not bool(ok_old.any())  # their mesh points were outside another view's matte
        ok_new, judged = _matte_votes(_points(cams, out.t)[i][changed[i]], cams[others], m[others])
        assert bool((ok_new & judged).all())


def test_reconstruct_with_the_hull_moves_only_off_head_gaussians(head_case):
    from fastgha_core.model.fastgha import load_model

    surface, cams, sd, fg = head_case
    model = load_model("tiny")
    s = model.config.input_size
    assert (cams.width, s) == (128, 128)
    gc = model.config.gaussians
    assert gc.off_head_hull == "off"  # off by default (docs/model-card-log.md)
    imgs = head_case_photos(fg, s)
    saved = gc.coverage_target, gc.mirror_views, gc.prune_opacity, gc.hair_fit, gc.off_head_extrude_m
    gc.coverage_target, gc.mirror_views, gc.prune_opacity, gc.hair_fit, gc.off_head_extrude_m = 0.0, False, 0.0, False, 0.0  # one Gaussian per pixel, on the bald head
    try:
        off = model.reconstruct(imgs, cams, surface=surface)
        gc.off_head_hull = "entry"
        on = model.reconstruct(imgs, cams, surface=surface)
        gc.off_head_hull = "sideways"
        with pytest.raises(ValueError, match="mode"):
            model.reconstruct(imgs, cams, surface=surface)
    finally:
        gc.off_head_hull = "off"
        gc.coverage_target, gc.mirror_views, gc.prune_opacity, gc.hair_fit, gc.off_head_extrude_m = saved
    n = on.num_reconstructed
    assert n == off.num_reconstructed == 3 * s * s
    diff = (on.gaussians.means[:n] - off.gaussians.means[:n]).norm(dim=-1).reshape(3, s, s)
    from fastgha_core.model import fastgha as F
    from fastgha_core.model.gaussian_head import foreground_weight

    want = off_head_on_hull(sd, surface, cams, foreground_weight(imgs), "entry", F.OFF_HEAD_HULL_COLLAR, F.OFF_HEAD_HULL_DILATE_PX, free_tol_m=F.OFF_HEAD_HULL_FREE_TOL_M).t != sd.t
    assert bool(want.any())
    assert torch.equal(diff > 1e-6, want)  # exactly the pixels the hull moves, by their change of distance
    t_on = (on.gaussians.means[:n] - off.gaussians.means[:n]).reshape(3, s, s, 3)
    _, d = cams.pixel_rays()
    assert torch.allclose((t_on * d).sum(-1)[want].abs(), diff[want], atol=1e-5)  # along their own rays
