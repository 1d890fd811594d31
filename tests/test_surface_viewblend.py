"""View-dependent blending of the input views' Gaussians (``fastgha_core/model/viewblend.py``, issue 17)."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from fastgha_core.cameras import Cameras
from fastgha_core.gaussians import Gaussians
from fastgha_core.model.viewblend import ViewBlend, blend_factors, coverage_masks, min_angle_table, view_directions


def _cams(yaws_deg, size=32, dist=1.0):
    eyes = torch.tensor([[dist * math.sin(math.radians(y)), 0.0, dist * math.cos(math.radians(y))] for y in yaws_deg])
    return Cameras.look_at(eyes, fov_deg=20.0, width=size, height=size)


def _angle_deg(a, b):
    a, b = np.asarray(a, np.float64), np.asarray(b, np.float64)
    return math.degrees(math.acos(np.clip(a @ b / np.linalg.norm(a) / np.linalg.norm(b), -1, 1)))


@pytest.mark.parametrize("v", [1, 3, 8])
def test_min_angle_table_matches_a_loop_over_the_bits(v):
    ang = torch.rand(v, generator=torch.Generator().manual_seed(v)) * 180
    table = min_angle_table(ang)
    assert table.shape == (1 << v,) and math.isinf(float(table[0]))
    for m in range(1, 1 << v):
        assert float(table[m]) == pytest.approx(min(float(ang[i]) for i in range(v) if m >> i & 1))


def test_factors_match_a_plain_per_gaussian_loop():
    yaws = [0.0, 35.0, -35.0, 80.0, -80.0]
    cams, render_cam = _cams(yaws), _cams([20.0])
    gen = torch.Generator().manual_seed(0)
    n = 300
    src = torch.randint(-1, len(yaws), (n,), generator=gen)
    mask = torch.randint(0, 1 << len(yaws), (n,), generator=gen)
    mask[src >= 0] |= 1 << src[src >= 0]  # a source view covers its own point
    f = blend_factors(src, mask.to(torch.uint8), view_directions(cams), render_cam, 20.0)
    # the per-frame path (one gather of a per-(mask, source) table) gives the same
    assert torch.allclose(ViewBlend(src.to(torch.int8), mask.to(torch.uint8), view_directions(cams)).factors(render_cam, 20.0), f, rtol=1e-6)
    c = render_cam.centers[0].numpy()
    for i in range(n):
        if src[i] < 0:
            want = 1.0
        else:
            a = [_angle_deg(cams.centers[k].numpy(), c) for k in range(len(yaws))]
            best = min(a[k] for k in range(len(yaws)) if int(mask[i]) >> k & 1)
            want = math.exp(-(a[int(src[i])] - best) / 20.0)
        assert float(f[i]) == pytest.approx(want, rel=1e-4, abs=1e-6)


def test_the_render_camera_at_a_source_view_keeps_that_views_gaussians():
    yaws = [0.0, 40.0, -40.0]
    cams = _cams(yaws)
    src = torch.tensor([0, 1, 2, 1, 2])
    mask = torch.full((5,), 0b111, dtype=torch.uint8)
    for k in range(3):
        f = blend_factors(src, mask, view_directions(cams), cams[k : k + 1], 20.0)
        assert torch.allclose(f[src == k], torch.ones(int((src == k).sum())), atol=1e-5)
        assert bool((f[src != k] < 0.5).all())  # 40 and 80 degrees away at tau 20


def test_a_gaussian_only_far_views_cover_is_not_faded():
    """The translucency fix: temple hair only the side photos see keeps its best side view opaque
    when the render camera is frontal, where a global minimum over all views would fade it."""
    cams = _cams([0.0, 60.0, -60.0])
    front = _cams([5.0])
    src = torch.tensor([1, 2, 1])
    mask = torch.tensor([0b010, 0b100, 0b110], dtype=torch.uint8)  # side views only; the third both
    f = blend_factors(src, mask, view_directions(cams), front, 20.0)
    assert float(f[0]) == pytest.approx(1.0, abs=1e-5)  # only view 1 covers it: kept
    assert float(f[1]) == pytest.approx(1.0, abs=1e-5)
    # covered by both side views: view 1 (55 degrees) is the nearer one and keeps it; view 2's copy
    # (65 degrees) would be faded, and view 1's copy here is the nearer one
    f2 = blend_factors(torch.tensor([2]), torch.tensor([0b110], dtype=torch.uint8), view_directions(cams), front, 20.0)
    assert float(f[2]) == pytest.approx(1.0, abs=1e-5) and float(f2[0]) == pytest.approx(math.exp(-10.0 / 20.0), rel=1e-3)
    # the global minimum (the frontal view) would have faded all three
    g = math.exp(-55.0 / 20.0)
    assert g < 0.1


def _sphere_depth(cams, r):
    """Camera-space depth ``[V, S, S]`` of a sphere of radius ``r`` at the origin (``inf`` off it)."""
    o, d = cams.pixel_rays()  # [V, H, W, 3]
    b = (o * d).sum(-1)
    disc = b * b - ((o * o).sum(-1) - r * r)
    t = -b - disc.clamp(min=0).sqrt()
    p = o + t[..., None] * d
    z = cams.world_to_camera(p.reshape(len(o), -1, 3))[..., 2].reshape(t.shape)
    return torch.where(disc > 0, z, torch.full_like(z, float("inf"))), (disc > 0).float()


def test_coverage_masks_see_the_near_side_of_a_sphere_only():
    yaws = [0.0, 90.0, 180.0]
    cams = _cams(yaws, size=64)
    r = 0.1
    depth, fg = _sphere_depth(cams, r)
    gen = torch.Generator().manual_seed(1)
    p = torch.nn.functional.normalize(torch.randn(2000, 3, generator=gen), dim=-1) * r
    mask = coverage_masks(p, cams, fg, depth, tol=0.005)
    dirs = view_directions(cams)
    for k in range(3):
        cos = p @ dirs[k] / r
        bit = (mask.long() >> k) & 1
        assert bool((bit[cos > 0.5] == 1).all()), k  # facing the camera (2+ px inside the outline): seen
        assert bool((bit[cos < -0.5] == 0).all()), k  # on the far side: occluded
    # outside every matte: no view
    fg0 = torch.zeros_like(fg)
    assert int(coverage_masks(p, cams, fg0, depth).max()) == 0
    # the source view's bit is always set
    sv = torch.full((len(p),), 2)
    assert bool(((coverage_masks(p, cams, fg0, depth, sv).long() >> 2) & 1).all())


def _avatar(n_rec=40, n_int=5, blend=True):
    from fastgha_core.model.avatar import CanonicalAvatar

    gen = torch.Generator().manual_seed(2)
    n = n_rec + n_int
    g = Gaussians(
        means=torch.randn(n, 3, generator=gen) * 0.05,
        quats=torch.nn.functional.normalize(torch.randn(n, 4, generator=gen), dim=-1),
        scales=torch.full((n, 3), 0.01),
        opacities=torch.rand(n, generator=gen),
        colors=torch.rand(n, 3, generator=gen),
        features=torch.randn(n, 32, generator=gen),
    )
    vb = None
    if blend:
        src = torch.randint(0, 3, (n_rec,), generator=gen).to(torch.int8)
        mask = (torch.randint(0, 8, (n_rec,), generator=gen) | (1 << src.long())).to(torch.uint8)
        vb = ViewBlend(src, mask, view_directions(_cams([0.0, 40.0, -40.0])))
    return CanonicalAvatar(g, "tiny", "ict53", None, n_int, vb)


def test_avatar_files_keep_the_view_data_and_old_files_load_without_it(tmp_path):
    from fastgha_core.model.avatar import CanonicalAvatar

    av = _avatar()
    av.save(tmp_path / "a.safetensors")
    back = CanonicalAvatar.load(tmp_path / "a.safetensors")
    assert torch.equal(back.view_blend.source_view, av.view_blend.source_view)
    assert torch.equal(back.view_blend.mask, av.view_blend.mask)
    assert torch.allclose(back.view_blend.directions, av.view_blend.directions)
    old = _avatar(blend=False)  # written as before view blending: no view.* tensors
    old.save(tmp_path / "old.safetensors")
    from safetensors import safe_open

    with safe_open(str(tmp_path / "old.safetensors"), "pt") as f:
        assert not any(k.startswith("extra.view") or "view." in k for k in f.keys())
    assert CanonicalAvatar.load(tmp_path / "old.safetensors").view_blend is None
    with pytest.raises(ValueError, match="view_blend covers"):
        CanonicalAvatar(av.gaussians, "tiny", "ict53", None, 10, av.view_blend)


@pytest.fixture(scope="module")
def tiny():
    from fastgha_core.model.fastgha import load_model

    model = load_model("tiny")
    model.config.gaussians.mirror_views = False  # the photos' own views (mirrored views and their offsets: tests/test_mirror.py)
    return model


def _reconstructed(model, surface=True):
    from fastgha_core.constants import BACKGROUND_RGB
    from fastgha_core.model.surface import HeadSurface

    s = model.config.input_size
    cams = _cams([0.0, 40.0, -40.0], size=s, dist=0.6)
    g = torch.Generator().manual_seed(3)
    imgs = torch.tensor(BACKGROUND_RGB, dtype=torch.float32).view(1, 3, 1, 1).repeat(3, 1, s, s)
    imgs[:, :, s // 8 : 7 * s // 8, s // 4 : 3 * s // 4] = 0.2 + 0.5 * torch.rand(3, 3, 3 * s // 4, s // 2, generator=g)
    head = HeadSurface(np.zeros(100, np.float32), np.zeros((3, 53), np.float32)) if surface else None
    return model.reconstruct(imgs, cams, surface=head), cams


def test_only_avatars_on_a_tracked_surface_get_view_data_unless_asked(tiny):
    """On the network-depth path blending lowered held-out synthetic PSNR: no per-view data there by default."""
    assert tiny.config.gaussians.view_blend_surface_only
    net, _ = _reconstructed(tiny, surface=False)
    assert net.view_blend is None
    tiny.config.gaussians.view_blend_surface_only = False
    try:
        net2, _ = _reconstructed(tiny, surface=False)
    finally:
        tiny.config.gaussians.view_blend_surface_only = True
    assert net2.view_blend is not None and len(net2.view_blend) == net2.num_reconstructed
    assert torch.equal(net2.gaussians.opacities, net.gaussians.opacities)  # recording changes nothing else


@pytest.mark.parametrize("prior", [True, False])  # the one-pass CPU frame and the general path
def test_frames_with_view_blending_equal_the_plain_reference(tiny, prior):
    model = tiny
    av, cams = _reconstructed(model)
    vb = av.view_blend
    assert vb is not None and len(vb) == av.num_reconstructed
    assert bool((((vb.mask.long() >> vb.source_view.long()) & 1) == 1).all())  # own view always covers
    assert int(vb.source_view.min()) == 0 and int(vb.source_view.max()) == 2
    z = torch.zeros(model.config.expression_dim)
    z[0] = 0.3
    render_cam = _cams([25.0], size=64, dist=0.6)
    old = model.config.gaussians.view_blend_tau_deg
    try:
        model.config.gaussians.view_blend_tau_deg = 0.0
        plain = model.animate(av, z, prior=prior)
        assert torch.equal(model.animate(av, z, prior=prior, camera=render_cam).opacities, plain.opacities)  # off: unchanged
        model.config.gaussians.view_blend_tau_deg = 20.0
        on = model.animate(av, z, prior=prior, camera=render_cam)
    finally:
        model.config.gaussians.view_blend_tau_deg = old
    # reference: a plain loop over the reconstructed Gaussians, the rest untouched
    c = render_cam.centers[0].numpy()
    a = [_angle_deg(cams.centers[k].numpy(), c) for k in range(3)]
    want = plain.opacities.clone()
    for i in range(av.num_reconstructed):
        m, s = int(vb.mask[i]), int(vb.source_view[i])
        if vb.sharp is not None and bool(vb.sharp[i]):  # contradicted by a more head-on view: by its own camera's angle alone (viewblend.ViewBlend.sharp)
            want[i] *= math.exp(-a[s] / (20.0 * vb.sharp_scale))
        else:
            want[i] *= math.exp(-(a[s] - min(a[k] for k in range(3) if m >> k & 1)) / 20.0)
    assert torch.allclose(on.opacities, want, rtol=1e-5, atol=1e-7)
    assert not torch.allclose(on.opacities, plain.opacities)
    for name in ("means", "scales", "quats", "colors"):
        assert torch.equal(getattr(on, name), getattr(plain, name))


def test_the_avatar_budget_counts_the_view_data_a_blended_frame_holds(tiny):
    av, _ = _reconstructed(tiny)
    vb = av.view_blend
    without = tiny.serving_nbytes(type(av)(av.gaussians, av.model_name, av.expression_space, av.prior, av.num_interior))
    assert "_key" not in vb.__dict__
    tiny.animate(av, torch.zeros(tiny.config.expression_dim), camera=_cams([10.0], size=64, dist=0.6))  # tau 20 by default
    held = sum(t.untyped_storage().nbytes() for t in (vb.source_view, vb.mask, vb.directions, vb.__dict__["_key"]))
    held += 0 if vb.sharp is None else vb.sharp.untyped_storage().nbytes()  # the head-on check's flags (gaussians.head_on_colour_tol)
    held += 0 if vb.under is None else vb.under.untyped_storage().nbytes()  # the off-head flags (gaussians.off_head_draw "under")
    held += 0 if vb.expressions is None else vb.expressions.untyped_storage().nbytes()  # the views' expressions (gaussians.view_blend_expr_mm)
    pen = vb.__dict__.get("_expr")  # ... and the penalty's tables, built on the first frame (model/viewblend.py ExpressionPenalty)
    held += 0 if pen is None else pen.nbytes
    anchor = av.__dict__.get("_residual_anchor")  # the MLP's residual at each view's expression (deform.anchor_residual)
    held += 0 if anchor is None else anchor[2].untyped_storage().nbytes()
    assert (anchor is not None) == (vb.expressions is not None)
    assert tiny.serving_nbytes(av) - without == held


def test_refinement_keeps_the_view_data_of_the_gaussians_it_keeps(tiny):
    from fastgha_core.refine import RefineConfig, refine_avatar

    av, cams = _reconstructed(tiny)
    s = tiny.config.input_size
    imgs = torch.rand(3, 3, s, s, generator=torch.Generator().manual_seed(4))
    res = refine_avatar(tiny, av, imgs, cams, config=RefineConfig(steps=2, resolution=64, coarse_resolution=32))
    out = res.avatar
    assert out.view_blend is not None and len(out.view_blend) == out.num_reconstructed
    assert torch.equal(out.view_blend.directions, av.view_blend.directions)


def test_refinement_renders_each_input_as_the_frame_drawn_at_its_camera(tiny, monkeypatch):
    """On a tracked-surface avatar the refinement's render of each input view (first step, no
    corrections yet) is the frame ``animate(..., camera=)`` draws there, view blending and the
    off-head Gaussians pushed under included; the frame drawn without the camera (what refinement
    rendered before) differs. Without the blending, refinement fitted colours to a mix of views that
    frames never show, and real-photo avatars came out speckled in novel views (docs/model-card-log.md,
    test-time refinement)."""
    from test_refine import record_renders

    from fastgha_core.constants import BACKGROUND_RGB
    from fastgha_core.refine import RefineConfig, prepare_targets, refine_avatar
    from fastgha_core.refine.measure import render_inputs
    from fastgha_core.render import render

    av, cams = _reconstructed(tiny)
    assert av.view_blend is not None
    s = tiny.config.input_size
    imgs = torch.rand(3, 3, s, s, generator=torch.Generator().manual_seed(4))
    expr = torch.zeros(3, tiny.config.expression_dim)
    expr[1, 0] = 0.6  # a view whose expression moves the Gaussians
    first = record_renders(monkeypatch)
    refine_avatar(tiny, av, imgs, cams, config=RefineConfig(steps=1, resolution=64, views_per_step=0), expressions=expr)
    tcams = prepare_targets(imgs, cams, None, 64)[2]
    frames = render_inputs(tiny, av, tcams, expr, 64)[0]
    assert len(first) == 3
    for i in range(3):
        assert float((first[i] - frames[i]).abs().max()) < 1e-2, i  # a few pixels differ by ~4e-3 with an expression: the interior gate's cut-off
    plain = render(tiny.animate(av, expr[1]), tcams[1:2], background=BACKGROUND_RGB).rgb[0].clamp(0, 1)
    assert float((plain - frames[1]).abs().max()) > 0.05  # the blending matters for this avatar


def test_fastgha_animate_draws_a_tracked_avatar_as_the_server_does(tiny, tmp_path):
    """`fastgha animate` passes each frame's camera, so its frames carry the view blending the server's do."""
    import json

    from PIL import Image

    from fastgha_core.cameras import cameras_to_json
    from fastgha_core.cli import main
    from fastgha_core.constants import BACKGROUND_RGB
    from fastgha_core.render import render

    av, _ = _reconstructed(tiny)
    assert av.view_blend is not None and tiny.config.gaussians.view_blend_tau_deg > 0
    av.save(tmp_path / "av.safetensors")
    cam = _cams([35.0], size=48, dist=0.6)
    (tmp_path / "cam.json").write_text(json.dumps(cameras_to_json(cam)))
    np.save(tmp_path / "seq.npy", np.zeros((1, tiny.config.expression_dim), np.float32))
    args = ["animate", "--avatar", str(tmp_path / "av.safetensors"), "--model", "tiny", "--expressions", str(tmp_path / "seq.npy"),
            "--cameras", str(tmp_path / "cam.json"), "--size", "48", "--out", str(tmp_path / "frames")]
    assert main(args) == 0
    got = np.asarray(Image.open(tmp_path / "frames" / "frame_00000.png")).astype(np.float32)
    z = torch.zeros(tiny.config.expression_dim)

    def frame(camera):
        rgb = render(tiny.animate(av, z, camera=camera), cam, background=torch.tensor(BACKGROUND_RGB)).rgb[0]
        return rgb.clamp(0, 1).permute(1, 2, 0).numpy() * 255.0

    blended, unweighted = frame(cam), frame(None)
    assert np.abs(got - blended).max() <= 1.0  # PNG rounding
    assert np.abs(blended - unweighted).max() > 4.0  # the blending is visible at this camera
