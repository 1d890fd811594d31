"""Mirrored virtual views of the unseen side of the head (``fastgha_core/model/mirror.py``, issue 17)."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from fastgha_core.cameras import Cameras, look_at_w2c
from fastgha_core.expressions import ICT53_NAMES
from fastgha_core.model.mirror import (
    flip_images,
    flip_surface_depth,
    ict53_mirror_permutation,
    mirror_cameras,
    mirror_expressions,
    mirror_points,
    sagittal_reflection,
    turned_views,
    view_yaw_deg,
)


def _rigid(deg, axis, t):
    a = np.radians(deg)
    c, s = np.cos(a), np.sin(a)
    i, j = [k for k in range(3) if k != axis]
    h = np.eye(4)
    h[i, i], h[i, j], h[j, i], h[j, j] = c, -s, s, c
    h[:3, 3] = t
    return h


def _cameras(yaws_deg, size=40, dist=0.6, skew=0.0, pitch_m=0.05, head_to_world=None):
    """Cameras looking at the head centre from ``yaws_deg`` (+90 = the subject's left, +x), with an
    off-centre principal point (and optional skew) so that ``cx`` matters."""
    eyes = torch.tensor([[dist * math.sin(math.radians(y)), pitch_m, dist * math.cos(math.radians(y))] for y in yaws_deg], dtype=torch.float64)
    w2c = look_at_w2c(eyes).double()
    if head_to_world is not None:  # the same cameras around a head moved into another world
        w2c = w2c @ torch.linalg.inv(torch.as_tensor(head_to_world, dtype=torch.float64))
    K = torch.tensor([[1.3 * size, skew, 0.43 * size], [0.0, 1.25 * size, 0.55 * size], [0.0, 0.0, 1.0]], dtype=torch.float64)
    return Cameras(K.expand(len(yaws_deg), 3, 3).clone(), w2c, size, size)


@pytest.mark.parametrize("h2w", [None, _rigid(20.0, 1, [0.03, -0.02, 0.1]) @ _rigid(-10.0, 0, [0.0, 0.0, 0.0])])
@pytest.mark.parametrize("skew", [0.0, 1.5])
def test_a_point_lands_at_the_flipped_pixel_of_its_mirror_in_the_mirrored_camera(h2w, skew):
    cams = _cameras([55.0, -70.0, 10.0], skew=skew, head_to_world=h2w)
    gen = torch.Generator().manual_seed(0)
    X = torch.randn(200, 3, generator=gen, dtype=torch.float64) * 0.08
    if h2w is not None:
        X = X @ torch.as_tensor(h2w[:3, :3]).T + torch.as_tensor(h2w[:3, 3])
    mc = mirror_cameras(cams, h2w)
    assert torch.allclose(torch.linalg.det(mc.R), torch.ones(3, dtype=torch.float64))  # proper rotations
    for i in range(3):
        uv, z = cams[i].project(X)
        uv2, z2 = mc[i].project(mirror_points(X, h2w))
        assert torch.allclose(uv2[:, 0], cams.width - uv[:, 0], atol=1e-9)  # column j -> W - 1 - j (centres at j + 0.5)
        assert torch.allclose(uv2[:, 1], uv[:, 1], atol=1e-9) and torch.allclose(z2, z, atol=1e-12)
    # pixel rays: the mirrored camera's ray through the flipped pixel is the mirror of the original ray
    o, d = cams.pixel_rays()
    o2, d2 = mc.pixel_rays()
    p = o + 0.5 * d
    assert torch.allclose(flip_images(mirror_points(p, h2w).movedim(-1, 1)).movedim(1, -1), o2 + 0.5 * d2, atol=1e-9)


def test_mirroring_twice_gives_the_view_back():
    h2w = _rigid(15.0, 1, [0.02, 0.0, -0.05])
    cams = _cameras([40.0, -80.0], skew=0.7, head_to_world=h2w)
    back = mirror_cameras(mirror_cameras(cams, h2w), h2w)
    assert torch.allclose(back.K, cams.K) and torch.allclose(back.w2c, cams.w2c, atol=1e-12)
    assert not torch.allclose(mirror_cameras(cams, h2w).w2c, cams.w2c, atol=1e-3)
    s = sagittal_reflection(h2w)
    assert torch.allclose(s @ s, torch.eye(4, dtype=torch.float64), atol=1e-12)
    img = torch.rand(2, 3, 5, 7)
    assert torch.equal(flip_images(flip_images(img)), img) and not torch.equal(flip_images(img), img)
    e = torch.rand(4, 53)
    assert torch.equal(mirror_expressions(mirror_expressions(e)), e) and not torch.equal(mirror_expressions(e), e)
    # yaw flips its sign, so a mirror of a turned view is turned the other way
    assert torch.allclose(view_yaw_deg(mirror_cameras(cams, h2w), h2w), -view_yaw_deg(cams, h2w))
    assert torch.allclose(view_yaw_deg(cams, h2w), torch.tensor([40.0, -80.0], dtype=torch.float64), atol=1e-6)


def test_the_left_right_swap_is_an_involution_mapping_each_name_to_its_twin():
    perm = ict53_mirror_permutation()
    names = list(ICT53_NAMES)
    assert sorted(perm) == list(range(53)) and all(perm[perm[i]] == i for i in range(53))
    twin = {names[i]: names[perm[i]] for i in range(53)}
    for a, b in [("jawLeft", "jawRight"), ("mouthLeft", "mouthRight"), ("eyeBlink_L", "eyeBlink_R"), ("eyeLookIn_L", "eyeLookIn_R"), ("mouthSmile_R", "mouthSmile_L")]:
        assert twin[a] == b and twin[b] == a
    fixed = sorted(n for n in names if twin[n] == n)
    assert fixed == sorted(["jawForward", "jawOpen", "mouthClose", "mouthFunnel", "mouthPucker", "mouthRollLower", "mouthRollUpper", "mouthShrugLower", "mouthShrugUpper"])
    for n in names:  # every other name is an L/R pair
        if n not in fixed:
            assert twin[n] != n and twin[n].rstrip("LRightef_") == n.rstrip("LRightef_")
    with pytest.raises(ValueError, match="no twin"):
        ict53_mirror_permutation(["jawLeft", "jawOpen"])


def test_the_twin_of_each_blendshape_is_its_mirror_on_the_head_model():
    """Geometric check of the permutation: the mirror image of each shape's displacement is its twin's
    (ICT-FaceKit's neutral head is symmetric; a wrong twin would be off by the whole displacement)."""
    from scipy.spatial import cKDTree

    from fastgha_core.data.headmodel import HeadModel

    head = HeadModel.load()
    v = head.neutral
    d, corr = cKDTree(v).query(v * [-1.0, 1.0, 1.0])
    sym = d < 1e-4
    assert sym.mean() > 0.95
    ident = np.zeros(head.num_identity, np.float32)
    perm = ict53_mirror_permutation(head.expression_names)
    for i in range(53):
        e = np.zeros(53, np.float32)
        e[i] = 1.0
        a, b = head.vertices(ident, e), head.vertices(ident, e[perm])
        moved = np.abs(a - v).max()
        err = np.abs((a * [-1.0, 1.0, 1.0])[sym] - b[corr[sym]]).max()
        assert err < 0.3 * moved, head.expression_names[i]


def test_flipped_surface_depth_is_the_mirrored_heads_depth_at_the_mirrored_camera():
    """The mirrored view's ray depths (the real view's, flipped) put its pixels on the mirrored head:
    the same as rasterising the head with the twin expression from the mirrored camera."""
    from fastgha_core.data.headmodel import HeadModel
    from fastgha_core.model.surface import HeadSurface, surface_ray_depth

    names = HeadModel.load().expression_names
    e = np.zeros((2, 53), np.float32)
    e[0, names.index("mouthSmile_L")] = 0.8
    e[1, names.index("jawLeft")] = 0.7
    e[1, names.index("eyeBlink_R")] = 1.0
    cams = _cameras([60.0, -75.0], size=64, pitch_m=0.0)
    sd = surface_ray_depth(HeadSurface(np.zeros(100, np.float32), e), cams)
    flipped = flip_surface_depth(sd)
    direct = surface_ray_depth(HeadSurface(np.zeros(100, np.float32), mirror_expressions(e).numpy()), mirror_cameras(cams))
    both = flipped.hit & direct.hit
    assert float((flipped.hit ^ direct.hit).float().mean()) < 0.01
    assert float((flipped.t - direct.t)[both].abs().median()) < 1e-4 and float((flipped.t - direct.t)[both].abs().max()) < 0.01
    # without the swap the smile / jaw would sit on the wrong side
    wrong = surface_ray_depth(HeadSurface(np.zeros(100, np.float32), e), mirror_cameras(cams))
    assert float((flipped.t - wrong.t)[both & wrong.hit].abs().max()) > 0.003


def test_only_turned_views_are_mirrored_most_turned_first():
    cams = _cameras([5.0, -70.0, 35.0, 29.0, -85.0])
    assert turned_views(cams, 30.0) == [4, 1, 2]
    assert turned_views(cams, 30.0, limit=2) == [4, 1]
    assert turned_views(cams, 90.0) == []


# ------------------------------------------------------------------ reconstruction


@pytest.fixture(scope="module")
def tiny():
    from fastgha_core.model.fastgha import load_model

    return load_model("tiny")


def _inputs(model, yaws):
    from fastgha_core.constants import BACKGROUND_RGB
    from fastgha_core.model.surface import HeadSurface

    s = model.config.input_size
    cams = _cameras(yaws, size=s, pitch_m=0.0)
    g = torch.Generator().manual_seed(3)
    v = len(yaws)
    imgs = torch.tensor(BACKGROUND_RGB, dtype=torch.float32).view(1, 3, 1, 1).repeat(v, 1, s, s)
    imgs[:, :, s // 8 : 7 * s // 8, s // 4 : 3 * s // 4] = 0.2 + 0.5 * torch.rand(v, 3, 3 * s // 4, s // 2, generator=g)
    e = np.zeros((v, 53), np.float32)
    e[:, ICT53_NAMES.index("mouthSmile_L")] = 0.5
    return imgs, cams.to(dtype=torch.float32), HeadSurface(np.zeros(100, np.float32), e)


def _with(model, **changes):
    gc = model.config.gaussians
    old = {k: getattr(gc, k) for k in changes}

    class _Ctx:
        def __enter__(self):
            for k, x in changes.items():
                setattr(gc, k, x)

        def __exit__(self, *a):
            for k, x in old.items():
                setattr(gc, k, x)

    return _Ctx()


def test_reconstruct_adds_mirrored_gaussians_only_for_turned_views(tiny):
    imgs, cams, head = _inputs(tiny, [0.0, 60.0, -10.0])
    with _with(tiny, off_head_extrude_m=0.0, mirror_views=False):
        off = tiny.reconstruct(imgs, cams, surface=head)
    with _with(tiny, off_head_extrude_m=0.0, mirror_views=True, mirror_min_yaw_deg=30.0):
        on = tiny.reconstruct(imgs, cams, surface=head)
    with _with(tiny, off_head_extrude_m=0.0, mirror_views=True, mirror_min_yaw_deg=80.0):
        none_turned = tiny.reconstruct(imgs, cams, surface=head)
    assert torch.equal(none_turned.gaussians.means, off.gaussians.means) and torch.equal(none_turned.gaussians.opacities, off.gaussians.opacities)
    vb_off, vb = off.view_blend, on.view_blend
    assert vb_off.directions.shape[0] == 3 and vb.directions.shape[0] == 4  # one mirrored view: of the 60-degree one
    mirrored = vb.source_view.long() == 3
    assert int(mirrored.sum()) > 100 and on.num_reconstructed == off.num_reconstructed + int(mirrored.sum())
    # the real views' Gaussians are exactly those without mirroring (they come first, in the same order)
    n_real = off.num_reconstructed
    assert torch.equal(vb.source_view[:n_real], vb_off.source_view)
    for name in ("means", "opacities", "colors", "scales"):
        assert torch.allclose(getattr(on.gaussians, name)[:n_real], getattr(off.gaussians, name)[:n_real], atol=1e-6), name
    # its camera direction is the 60-degree view's, mirrored
    assert torch.allclose(vb.directions[3], vb.directions[1] * torch.tensor([-1.0, 1.0, 1.0]), atol=1e-5)
    # mirrored Gaussians lie on the subject's other side (-x here, the real view sees +x)
    assert float(on.gaussians.means[:on.num_reconstructed][mirrored][:, 0].median()) < 0 < float(off.gaussians.means[:n_real][vb_off.source_view.long() == 1][:, 0].median())


def test_without_a_surface_mirroring_changes_nothing(tiny):
    imgs, cams, _ = _inputs(tiny, [0.0, 60.0, -50.0])
    with _with(tiny, mirror_views=False):
        off = tiny.reconstruct(imgs, cams)
    with _with(tiny, mirror_views=True, mirror_min_yaw_deg=30.0):
        on = tiny.reconstruct(imgs, cams)
    assert len(on.gaussians) == len(off.gaussians) and torch.equal(on.gaussians.means, off.gaussians.means)
    assert torch.equal(on.gaussians.opacities, off.gaussians.opacities)


def test_a_mirrored_avatar_saves_loads_and_draws_the_same(tiny, tmp_path):
    from fastgha_core.model.avatar import CanonicalAvatar

    imgs, cams, head = _inputs(tiny, [0.0, 60.0, -50.0])
    with _with(tiny, mirror_views=True, mirror_min_yaw_deg=30.0, mirror_blend_offset_deg=15.0):
        av = tiny.reconstruct(imgs, cams, surface=head)
    assert av.view_blend.directions.shape[0] == 5 and av.view_blend.offsets.tolist() == [0.0, 0.0, 0.0, 15.0, 15.0]
    av.save(tmp_path / "m.safetensors")
    back = CanonicalAvatar.load(tmp_path / "m.safetensors")
    assert torch.equal(back.view_blend.source_view, av.view_blend.source_view) and torch.equal(back.view_blend.mask, av.view_blend.mask)
    assert torch.equal(back.view_blend.directions, av.view_blend.directions) and torch.equal(back.view_blend.offsets, av.view_blend.offsets)
    z = torch.zeros(53)
    z[ICT53_NAMES.index("jawOpen")] = 0.4
    cam = _cameras([-45.0], size=64, pitch_m=0.0).to(dtype=torch.float32)
    a, b = tiny.animate(av, z, camera=cam), tiny.animate(back, z, camera=cam)
    assert torch.equal(a.opacities, b.opacities) and torch.allclose(a.means, b.means)
    # where no real view sees its point, a mirrored Gaussian is drawn fully whatever its offset; where the
    # real -50-degree view (5 degrees from this camera) sees it too, the mirror of the 60-degree view
    # (-60: 15 + 15 degrees) fades
    f = av.view_blend.factors(cam, tiny.config.gaussians.view_blend_tau_deg)
    src, mask = av.view_blend.source_view.long(), av.view_blend.mask.long()
    alone = (src == 3) & ((mask & 0b111) == 0)
    shared = (src == 3) & ((mask >> 2) & 1 == 1)
    assert int(alone.sum()) > 0 and int(shared.sum()) > 0
    assert torch.allclose(f[alone], torch.ones(int(alone.sum()))) and float(f[shared].max()) < 0.5


def test_seen_by_views_needs_the_matte_no_occlusion_and_a_low_incidence():
    from fastgha_core.model.mirror import seen_by_views, surface_normals
    from fastgha_core.model.viewblend import view_depth_maps

    cams = _cameras([0.0], size=64, pitch_m=0.0).to(dtype=torch.float32)
    o, d = cams.pixel_rays()  # a sphere of radius 0.1 at the origin, seen by the frontal camera
    b = (o * d).sum(-1)
    disc = b * b - ((o * o).sum(-1) - 0.01)
    hit = disc > 0
    t = torch.where(hit, -b - disc.clamp(min=0).sqrt(), torch.full_like(b, 0.6))
    p = (o + t[..., None] * d).reshape(-1, 3)
    depth = view_depth_maps(p, cams, hit.reshape(-1))
    n = surface_normals(t, cams)
    radial = torch.nn.functional.normalize(p, dim=-1).reshape(n.shape)
    inner = hit.clone()
    inner[:, :2], inner[:, -2:], inner[:, :, :2], inner[:, :, -2:] = False, False, False, False
    assert float((n * radial).sum(-1)[inner & (torch.roll(hit, 2, 1) & torch.roll(hit, -2, 1) & torch.roll(hit, 2, 2) & torch.roll(hit, -2, 2))].min()) > 0.98
    # points on the sphere: facing the camera -> seen; beyond 60 degrees of incidence, behind, or outside the matte -> not
    ang = torch.deg2rad(torch.tensor([0.0, 30.0, 45.0, 65.0, 150.0]))  # incidence from the camera 0.6 m away: 0, ~33, ~53, ~74 degrees, behind
    q = torch.stack([0.1 * torch.sin(ang), torch.zeros(5), 0.1 * torch.cos(ang)], -1)
    nq = torch.nn.functional.normalize(q, dim=-1)
    fg = hit.float()
    got = seen_by_views(q, nq, cams, fg, depth, 60.0)
    assert got.tolist() == [True, True, True, False, False]
    assert not bool(seen_by_views(q, nq, cams, torch.zeros_like(fg), depth, 60.0).any())
    assert not bool(seen_by_views(q, torch.zeros_like(nq), cams, fg, depth, 89.0).any())


def test_mirrored_gaussians_a_real_view_sees_well_are_dropped(tiny):
    imgs, cams, head = _inputs(tiny, [0.0, 60.0, -10.0])
    with _with(tiny, off_head_extrude_m=0.0, mirror_views=True, mirror_min_yaw_deg=30.0, mirror_drop_seen_deg=0.0):
        keep = tiny.reconstruct(imgs, cams, surface=head)
    with _with(tiny, off_head_extrude_m=0.0, mirror_views=True, mirror_min_yaw_deg=30.0, mirror_drop_seen_deg=60.0):
        drop = tiny.reconstruct(imgs, cams, surface=head)
    k, d = (a.view_blend.source_view.long() == 3 for a in (keep, drop))
    assert 0 < int(d.sum()) < int(k.sum())
    n_real = int((~k).sum())
    assert int((~d).sum()) == n_real and torch.equal(drop.gaussians.opacities[:n_real], keep.gaussians.opacities[:n_real])
    # what stays lies further to the mirrored side (-x) than what went: the frontal views see the face's middle head-on
    mk = keep.gaussians.means[: keep.num_reconstructed][k]
    md = drop.gaussians.means[: drop.num_reconstructed][d]
    assert float(md[:, 0].mean()) < float(mk[:, 0].mean())


@pytest.mark.parametrize("drop_deg, midline_m", [(60.0, 0.0), (0.0, 0.03)])
def test_dropping_mirrored_gaussians_leaves_no_hole_at_the_mirrored_camera(tiny, drop_deg, midline_m):
    """A mirrored view counts as seeing a point only where it kept its Gaussians: otherwise the real
    views' Gaussians would fade towards it at its camera, over a hole."""
    from fastgha_core.render import render

    imgs, cams, head = _inputs(tiny, [0.0, 60.0, -10.0])
    cam = _cameras([-60.0], size=64, pitch_m=0.0).to(dtype=torch.float32)
    z = torch.zeros(53)
    alpha = {}
    for name, on, drop, mid in (("off", False, 0.0, 0.0), ("drop", True, drop_deg, midline_m)):
        with _with(tiny, mirror_views=on, mirror_min_yaw_deg=30.0, mirror_drop_seen_deg=drop, mirror_midline_m=mid):
            av = tiny.reconstruct(imgs, cams, surface=head)
        if on:  # something was dropped
            with _with(tiny, mirror_views=True, mirror_min_yaw_deg=30.0):
                assert tiny.reconstruct(imgs, cams, surface=head).num_reconstructed > av.num_reconstructed
        alpha[name] = render(tiny.animate(av, z, camera=cam), cam).alpha[0, 0]
    head_px = alpha["off"] > 0.5
    assert float(alpha["drop"][head_px].mean()) >= float(alpha["off"][head_px].mean()) - 0.01


def test_near_midline_measures_the_distance_to_the_sagittal_plane_of_the_head_frame():
    from fastgha_core.model.mirror import near_midline

    p = torch.tensor([[0.005, 0.1, 0.05], [-0.015, 0.0, 0.1], [0.03, 0.0, 0.0], [-0.05, 0.02, 0.0]])
    assert near_midline(p, 0.02).tolist() == [True, True, False, False]
    h2w = _rigid(90.0, 1, [0.1, 0.0, 0.0])  # the head turned 90 degrees about y and moved: its x axis is world -z
    pw = p.double() @ torch.as_tensor(h2w[:3, :3]).T + torch.as_tensor(h2w[:3, 3])
    assert near_midline(pw, 0.02, h2w).tolist() == [True, True, False, False]
    assert near_midline(pw, 0.02).tolist() != [True, True, False, False]


def test_blend_offsets_count_a_view_as_further_away_and_survive_a_file(tmp_path):
    """``ViewBlend.offsets`` (mirrored views' precedence): the factors equal a plain loop with each
    view's angle plus its offset, and the offsets travel with the avatar file."""
    from fastgha_core.gaussians import Gaussians
    from fastgha_core.model.avatar import CanonicalAvatar
    from fastgha_core.model.viewblend import ViewBlend, blend_factors, view_directions

    yaws = [0.0, 60.0, -60.0]
    cams = _cameras(yaws, pitch_m=0.0).to(dtype=torch.float32)
    render_cam = _cameras([-50.0], pitch_m=0.0).to(dtype=torch.float32)
    gen = torch.Generator().manual_seed(5)
    n = 200
    src = torch.randint(0, 3, (n,), generator=gen)
    mask = (torch.randint(0, 8, (n,), generator=gen) | (1 << src)).to(torch.uint8)
    off = torch.tensor([0.0, 0.0, 25.0])
    vb = ViewBlend(src.to(torch.int8), mask, view_directions(cams), off)
    f = vb.factors(render_cam, 20.0)
    assert torch.allclose(f, blend_factors(src, mask, view_directions(cams), render_cam, 20.0, off), rtol=1e-6)
    c = render_cam.centers[0].double()
    a = [math.degrees(math.acos(float(cams.centers[k].double() @ c / cams.centers[k].double().norm() / c.norm()))) + float(off[k]) for k in range(3)]
    for i in range(n):
        m, s = int(mask[i]), int(src[i])
        assert float(f[i]) == pytest.approx(math.exp(-(a[s] - min(a[k] for k in range(3) if m >> k & 1)) / 20.0), rel=1e-3, abs=1e-6)
    # the offset view (at 10 degrees from the render camera) no longer wins over the frontal (50 degrees) outright
    both = (mask.long() & 0b101) == 0b101
    plain = ViewBlend(src.to(torch.int8), mask, view_directions(cams)).factors(render_cam, 20.0)
    assert bool((f[both & (src == 0)] > plain[both & (src == 0)]).all())
    with pytest.raises(ValueError, match="offsets"):
        ViewBlend(src.to(torch.int8), mask, view_directions(cams), torch.tensor([0.0, -1.0, 0.0]))
    g = Gaussians(means=torch.zeros(n, 3), quats=torch.tensor([[1.0, 0, 0, 0]]).repeat(n, 1), scales=torch.full((n, 3), 0.01),
                  opacities=torch.rand(n, generator=gen), colors=torch.rand(n, 3, generator=gen), features=torch.zeros(n, 32))
    CanonicalAvatar(g, "tiny", "ict53", None, 0, vb).save(tmp_path / "o.safetensors")
    back = CanonicalAvatar.load(tmp_path / "o.safetensors").view_blend
    assert torch.equal(back.offsets, off) and torch.equal(back.factors(render_cam, 20.0), f)
    CanonicalAvatar(g, "tiny", "ict53", None, 0, ViewBlend(src.to(torch.int8), mask, view_directions(cams))).save(tmp_path / "p.safetensors")
    assert CanonicalAvatar.load(tmp_path / "p.safetensors").view_blend.offsets is None
