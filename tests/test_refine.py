"""Test-time refinement (fastgha_core.refine): contract, geometry helpers, and that it fits the inputs better."""

from __future__ import annotations

import math

import pytest
import torch

from fastgha_core import Cameras
from fastgha_core.refine import RefineConfig, corrected_w2c, masked_psnr, prepare_targets, refine_avatar, source_views
from fastgha_core.refine.measure import SAMPLE_REQUEST, read_request, render_inputs


@pytest.fixture(scope="module")
def sample():
    from fastgha_core.model.fastgha import load_model

    model = load_model("tiny")
    images, masks, cams, expr = read_request(SAMPLE_REQUEST)
    imgs, in_cams = model.prepare(list(images), [cams[i : i + 1] for i in range(len(cams.K))], list(masks))
    avatar = model.reconstruct(imgs, in_cams)
    return model, avatar, images, masks, cams, expr


def test_zero_steps_returns_the_avatar_unchanged(sample):
    model, avatar, images, masks, cams, expr = sample
    res = refine_avatar(model, avatar, images, cams, masks, config=RefineConfig(steps=0), expressions=expr)
    assert res.avatar is avatar
    assert torch.equal(res.cameras.w2c, cams.w2c) and res.timings["steps"] == 0
    assert torch.equal(res.rotations, torch.zeros(4, 3))


@pytest.mark.parametrize("smooth_grid", [0, 16])
def test_refinement_fits_the_input_views_better(sample, smooth_grid):
    model, avatar, images, masks, cams, expr = sample
    calls = []
    cfg = RefineConfig(steps=8, resolution=64, coarse_resolution=64, smooth_grid=smooth_grid)
    res = refine_avatar(model, avatar, images, cams, masks, config=cfg, expressions=expr, progress=lambda i, n: calls.append((i, n)))
    assert calls == [(i, 8) for i in range(1, 9)]
    assert cfg.views_per_step == 2  # the default: steps 0 and 6 render the same two of the 4 views
    assert res.losses[6] < res.losses[0]
    targets, tmask, _ = prepare_targets(images, cams, masks, 64)
    before = masked_psnr(render_inputs(model, avatar, prepare_targets(images, cams, masks, 64)[2], expr, 64)[0], targets, tmask)
    after = masked_psnr(render_inputs(model, res.avatar, prepare_targets(images, res.cameras, masks, 64)[2], expr, 64)[0], targets, tmask)
    assert float(after.mean()) > float(before.mean()) + 0.3
    # the refined avatar is an ordinary avatar: features kept, animated like any other
    assert res.avatar.gaussians.features.shape[1] == avatar.gaussians.features.shape[1]
    from fastgha_core.model.prior import cheek_shell_vertices

    k = len(cheek_shell_vertices(model.head_basis()))  # the cheek shell backing what the corrections thinned
    assert res.avatar.num_interior == avatar.num_interior + k  # one mouth interior, not a second one appended
    assert res.avatar.num_reconstructed <= avatar.num_reconstructed  # refinement may prune, never adds
    shown = [len(model.animate(a, expr[0])) - a.num_reconstructed for a in (avatar, res.avatar)]
    assert shown[0] + k == shown[1]  # the same mouth / lid Gaussians shown at this expression, and the shell
    assert res.cameras.w2c.shape == cams.w2c.shape and (res.cameras.width, res.cameras.height) == (cams.width, cams.height)


def test_bad_inputs_raise_clear_errors(sample):
    model, avatar, images, masks, cams, expr = sample
    with pytest.raises(ValueError, match="expressions must have shape"):
        refine_avatar(model, avatar, images, cams, masks, config=RefineConfig(steps=1), expressions=expr[:, :5])
    with pytest.raises(ValueError, match="images must have shape"):
        refine_avatar(model, avatar, images[:3], cams, masks, config=RefineConfig(steps=1))
    with pytest.raises(ValueError, match="resolution must be a multiple of 16"):
        RefineConfig(resolution=100)
    with pytest.raises(ValueError, match="steps must be >= 0"):
        RefineConfig(steps=-1)


def test_source_views_finds_the_ray_each_point_came_from():
    cams = Cameras.look_at(torch.tensor([[0.0, 0.0, 1.0], [0.6, 0.1, 0.8], [-0.5, 0.3, 0.8]]), fov_deg=25.0, width=32, height=32)
    g = torch.Generator().manual_seed(0)
    pts, truth = [], []
    for v in range(3):
        origins, dirs = cams[v : v + 1].pixel_rays(16, 16)
        t = 0.9 + 0.2 * torch.rand(16, 16, 1, generator=g)
        pts.append((origins + t * dirs).reshape(-1, 3))
        truth.append(torch.full((256,), v))
    found = source_views(torch.cat(pts), cams, 16)
    assert torch.equal(found, torch.cat(truth))


def test_camera_correction_is_a_rigid_motion_in_the_camera_frame():
    w2c = Cameras.look_at(torch.tensor([[0.2, 0.1, 0.9]]), fov_deg=25.0, width=32, height=32).w2c
    assert torch.allclose(corrected_w2c(w2c, torch.zeros(1, 3), torch.zeros(1, 3)), w2c)
    rot, trans = torch.tensor([[0.0, 0.0, math.pi / 2]]), torch.tensor([[0.01, -0.02, 0.03]])
    out = corrected_w2c(w2c, rot, trans)
    Rz = torch.tensor([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
    assert torch.allclose(out[0, :3, :3], Rz @ w2c[0, :3, :3], atol=1e-6)
    assert torch.allclose(out[0, :3, 3], Rz @ w2c[0, :3, 3] + trans[0], atol=1e-6)
    small = corrected_w2c(w2c, torch.tensor([[1e-6, 0.0, 0.0]]), torch.zeros(1, 3))
    assert torch.isfinite(small).all()


def test_masked_psnr_counts_only_the_mask():
    a = torch.zeros(1, 3, 4, 4)
    b = a.clone()
    b[..., :2] = 1.0  # wrong only on the left half
    m = torch.zeros(1, 1, 4, 4)
    m[..., 2:] = 1.0
    assert float(masked_psnr(a, b, m)[0]) == pytest.approx(100.0)  # clamped at mse 1e-10
    m[..., 0] = 1.0  # 4 wrong of 12 pixels -> mse 1/3
    assert float(masked_psnr(a, b, m)[0]) == pytest.approx(10 * math.log10(3), rel=1e-5)


def test_lr_factor_restarts_at_the_fine_phase_only_when_asked():
    from fastgha_core.refine import lr_factor

    steps, coarse = 20, 10
    one = [lr_factor(s, steps) for s in range(steps)]
    assert one[0] == 1.0 and one[9] == 1.0 and math.isclose(one[-1], 0.1) and one[10] < 1.0
    assert all(a >= b for a, b in zip(one, one[1:]))  # never increases
    two = [lr_factor(s, steps, restart=coarse) for s in range(steps)]
    assert math.isclose(two[coarse - 1], 0.1) and two[coarse] == 1.0 and math.isclose(two[-1], 0.1)
    assert two[:coarse] == [lr_factor(s, coarse) for s in range(coarse)]


def test_views_per_step_renders_the_views_in_turn(sample, monkeypatch):
    import fastgha_core.refine as refine_mod

    model, avatar, images, masks, cams, expr = sample
    seen = []
    real = refine_mod._render_view

    def spy(g, means, colors, opac, K, w2c, size, bg, *rest):
        seen.append(int((cams.w2c.float() - w2c.detach()[None]).abs().flatten(1).sum(1).argmin()))
        return real(g, means, colors, opac, K, w2c, size, bg, *rest)

    monkeypatch.setattr(refine_mod, "_render_view", spy)
    cfg = RefineConfig(steps=3, resolution=64, coarse_resolution=64, views_per_step=2)
    res = refine_avatar(model, avatar, images, cams, masks, config=cfg, expressions=expr)
    assert seen == [0, 1, 2, 3, 0, 1]
    assert len(res.losses) == 3
    seen.clear()
    refine_avatar(model, avatar, images, cams, masks, config=RefineConfig(steps=2, resolution=64, coarse_resolution=64, views_per_step=0), expressions=expr)
    assert seen == [0, 1, 2, 3, 0, 1, 2, 3]  # 0 = every view every step
    with pytest.raises(ValueError, match="views_per_step must be >= 0"):
        RefineConfig(views_per_step=-1)


def test_smooth_preset_keeps_the_previous_schedule(sample, monkeypatch):
    """REFINE_PRESETS['smooth'] (the defaults before 2026-11-30): 75% of the steps coarse, every view every step."""
    import fastgha_core.refine as refine_mod
    from fastgha_core.refine import REFINE_PRESETS

    model, avatar, images, masks, cams, expr = sample
    sizes = []
    real = refine_mod._render_view

    def spy(g, means, colors, opac, K, w2c, size, bg, *rest):
        sizes.append(size)
        return real(g, means, colors, opac, K, w2c, size, bg, *rest)

    monkeypatch.setattr(refine_mod, "_render_view", spy)
    cfg = RefineConfig(**{**REFINE_PRESETS["smooth"].__dict__, "steps": 4, "resolution": 64, "coarse_resolution": 32})
    assert cfg.smooth_grid > 0
    refine_avatar(model, avatar, images, cams, masks, config=cfg, expressions=expr)
    assert sizes == [32] * 12 + [64] * 4
    sizes.clear()
    refine_avatar(model, avatar, images, cams, masks, config=RefineConfig(steps=4, resolution=64, coarse_resolution=32), expressions=expr)
    assert sizes == [64] * 8  # the default: 2 views per step, all at the full resolution


@pytest.mark.parametrize("phase_schedule", [False, True])
def test_phase_schedule_restarts_the_step_size_at_the_fine_phase(sample, monkeypatch, phase_schedule):
    model, avatar, images, masks, cams, expr = sample
    lrs = []
    real_step = torch.optim.Adam.step

    def spy(self, *a, **k):
        lrs.append(self.param_groups[2]["lr"] / 0.3)  # the colour group, relative to its base step size
        return real_step(self, *a, **k)

    monkeypatch.setattr(torch.optim.Adam, "step", spy)
    cfg = RefineConfig(steps=4, resolution=64, coarse_resolution=32, coarse_fraction=0.5, lr_color=0.3, phase_schedule=phase_schedule)
    refine_avatar(model, avatar, images, cams, masks, config=cfg, expressions=expr)
    want = [1.0, 0.1, 1.0, 0.1] if phase_schedule else [1.0, 1.0, 0.7, 0.1]
    assert lrs == pytest.approx(want)


def _small_scene(seed: int, n: int = 300):
    """Float32 Gaussians around the origin seen by one 48x48 camera at z = 1."""
    g = torch.Generator().manual_seed(seed)
    means = torch.randn(n, 3, generator=g) * 0.06
    quats = torch.nn.functional.normalize(torch.randn(n, 4, generator=g), dim=-1)
    scales = torch.exp(torch.rand(n, 3, generator=g) * 1.5 - 5.5)
    opac = torch.rand(n, generator=g) * 0.9 + 0.05
    colors = torch.rand(n, 3, generator=g)
    cams = Cameras.look_at(torch.tensor([[0.05, -0.03, 1.0]]), fov_deg=20.0, width=48, height=48)
    from fastgha_core import Gaussians

    return Gaussians(means, quats, scales, opac, colors), cams


def test_scaled_conics_match_the_projection_of_scaled_gaussians():
    """An isotropic factor exp(d) on the 3D scales: the conics from scaled_conics equal those of the
    full projection of the scaled Gaussians, and so do their gradients with respect to d."""
    from fastgha_core.refine import scaled_conics
    from fastgha_core.render.projection import project_gaussians

    g, cams = _small_scene(1)
    g = g.to(dtype=torch.float64)
    d0 = torch.randn(len(g), dtype=torch.float64, generator=torch.Generator().manual_seed(2)) * 0.3
    ref_d = d0.clone().requires_grad_(True)
    ref = project_gaussians(g.means, g.quats, g.scales * torch.exp(ref_d)[:, None], cams.K.double(), cams.w2c.double(), 48, 48)
    vis = ref.radii[0] > 0
    assert vis.sum() > 100
    # the current projection (at d0, no gradient) + a differentiable increment around it
    with torch.no_grad():
        cur = project_gaussians(g.means, g.quats, g.scales * torch.exp(d0)[:, None], cams.K.double(), cams.w2c.double(), 48, 48)
    d = d0.clone().requires_grad_(True)
    out = scaled_conics(cur.conics[0], d - d.detach())
    torch.testing.assert_close(out[vis], ref.conics[0][vis], rtol=1e-9, atol=1e-9)
    w = torch.rand(out.shape, dtype=torch.float64, generator=torch.Generator().manual_seed(3))
    (out[vis] * w[vis]).sum().backward()
    (ref.conics[0][vis] * w[vis]).sum().backward()
    assert ref_d.grad[vis].abs().max() > 0
    torch.testing.assert_close(d.grad[vis], ref_d.grad[vis], rtol=1e-7, atol=1e-9)
    # a finite increment too: the conics of Gaussians twice as large
    torch.testing.assert_close(
        scaled_conics(cur.conics[0], torch.full_like(d0, math.log(2.0)))[vis],
        project_gaussians(g.means, g.quats, g.scales * (2 * torch.exp(d0))[:, None], cams.K.double(), cams.w2c.double(), 48, 48).conics[0][vis],
        rtol=1e-9, atol=1e-9,
    )


def test_refinement_render_matches_a_plain_reference_on_outputs_and_gradients():
    """``_render_view`` (numba projection without gradients, float32 tile kernels, the centres and the
    isotropic scale correction differentiated in torch) against the dense reference compositor fed by
    the torch projection: the same images, and the same gradients of positions, colours, opacities
    and scale corrections. The reference holds the screen-space covariance fixed with respect to the
    positions, as refinement does (its documented approximation)."""
    from fastgha_core.refine import _render_view
    from fastgha_core.render.projection import Projected, project_gaussians
    from fastgha_core.render.reference import rasterize_reference

    g, cams = _small_scene(4)
    n = len(g)
    bg = torch.tensor([1.0, 1.0, 1.0])
    gen = torch.Generator().manual_seed(5)
    ls0 = torch.randn(n, generator=gen) * 0.2
    w = [torch.rand(s, generator=gen) for s in ((3, 48, 48), (1, 48, 48), (1, 48, 48))]

    def leaves():
        return [t.detach().clone().requires_grad_(True) for t in (g.means, g.colors, g.opacities, ls0)]

    def loss(rgb, alpha, depth):
        return (rgb * w[0]).sum() + (alpha * w[1]).sum() + 0.1 * (depth * alpha * w[2]).sum()

    m, c, o, ls = leaves()
    rgb, alpha, depth, z, uv = _render_view(g, m, c, o, cams.K[0], cams.w2c[0], 48, bg, ls)
    loss(rgb, alpha, depth).backward()
    fast = (rgb.detach(), alpha.detach(), (depth * alpha).detach(), m.grad, c.grad, o.grad, ls.grad)

    m, c, o, ls = leaves()
    pos = project_gaussians(m, g.quats, g.scales.detach(), cams.K, cams.w2c, 48, 48)  # centres and depths
    cov = project_gaussians(m.detach(), g.quats, g.scales * torch.exp(ls)[:, None], cams.K, cams.w2c, 48, 48)
    p = Projected(pos.means2d, cov.conics, pos.depths.detach(), cov.radii)
    acc, a = rasterize_reference(p, o, torch.cat([c, pos.depths[0][:, None]], -1)[None], 48, 48)
    rgb_r = (acc[0, ..., :3] + (1 - a[0])[..., None] * bg).permute(2, 0, 1)
    depth_r = (acc[0, ..., 3] / a[0].clamp_min(1e-6))[None]
    loss(rgb_r, a[0][None], depth_r).backward()
    ref = (rgb_r.detach(), a[0][None].detach(), (depth_r * a[0][None]).detach(), m.grad, c.grad, o.grad, ls.grad)

    names = ("rgb", "alpha", "depth x alpha", "grad means", "grad colors", "grad opacities", "grad log-scale")
    for name, x, y in zip(names, fast, ref):
        assert y.abs().max() > 0, name
        scale = y.abs().max()
        torch.testing.assert_close(x / scale, y / scale, rtol=0, atol=2e-4, msg=name)


def record_renders(monkeypatch) -> list:
    """Patch ``fastgha_core.refine._render_view`` so that every render the refinement makes appends its
    rgb ``[3, S, S]`` (detached) to the returned list, in order (also used by tests/test_surface_viewblend.py)."""
    import fastgha_core.refine as refine_mod

    first = []
    real = refine_mod._render_view

    def spy(*a):
        out = real(*a)
        first.append(out[0].detach())
        return out

    monkeypatch.setattr(refine_mod, "_render_view", spy)
    return first


@pytest.mark.parametrize("match_animation", [True, False])
def test_refinement_renders_the_inputs_as_animate_draws_them(sample, monkeypatch, match_animation):
    """With ``match_animation`` the first step's render of an input view (no corrections yet) is the
    frame ``FastGHA.animate`` + ``render`` draws at that view's expression (the prior's shading, the
    back-of-head shell and gated interior included); without it, it is not."""
    model, avatar, images, masks, cams, expr = sample
    first = record_renders(monkeypatch)
    cfg = RefineConfig(steps=1, resolution=64, views_per_step=1, match_animation=match_animation)
    refine_avatar(model, avatar, images, cams, masks, config=cfg, expressions=expr)
    frame = render_inputs(model, avatar, prepare_targets(images, cams, masks, 64)[2][0:1], expr[0:1], 64)[0][0]
    err = (first[0] - frame).abs().max()
    if match_animation:
        assert float(err) < 2e-3
    else:
        assert float(err) > 0.05


def test_refined_avatar_keeps_the_binding_it_was_refined_with(sample):
    """With zero step sizes the refined avatar animates like the feed-forward one (``keep_binding``);
    refitting the head to it instead (``keep_binding=False``) moves Gaussians (the feed-forward fit was
    made on the cloud before the inputs' expressions were undone, as ``fastgha eval`` reconstructs)."""
    model, _, images, masks, cams, expr = sample
    imgs, in_cams = model.prepare(list(images), [cams[i : i + 1] for i in range(len(cams.K))], list(masks))
    avatar = model.reconstruct(imgs, in_cams, expressions=expr)
    zero = dict(steps=1, resolution=64, lr_opacity=0.0, lr_color=0.0, lr_scale=0.0, prune_opacity=0.0)
    kept = refine_avatar(model, avatar, images, cams, masks, config=RefineConfig(**zero), expressions=expr).avatar
    refit = refine_avatar(model, avatar, images, cams, masks, config=RefineConfig(**zero, keep_binding=False), expressions=expr).avatar
    assert kept.num_interior == avatar.num_interior and len(kept.gaussians) == len(avatar.gaussians)
    for i in range(len(expr)):
        a, k, r = (model.animate(x, expr[i]) for x in (avatar, kept, refit))
        assert len(a) == len(k)
        torch.testing.assert_close(k.means, a.means, rtol=0, atol=1e-6)
        torch.testing.assert_close(k.colors, a.colors, rtol=0, atol=2e-3)  # logit round trip, colours clamped to [1e-3, 1 - 1e-3]
        torch.testing.assert_close(k.opacities, a.opacities, rtol=0, atol=2e-4)
    n = avatar.num_reconstructed
    moved = max(float((model.animate(refit, z).means[:n] - model.animate(avatar, z).means[:n]).norm(dim=-1).max()) for z in expr)
    assert moved > 5e-4  # the refit binding moves some Gaussians by over half a millimetre


def test_realign_to_pixels_undoes_the_mlp_residual_of_the_own_expression(sample):
    """Moved Gaussians, deformed by the MLP's residual at their own view's expression, land back on
    the network's centres (better than before the move); those that would move beyond the cap stay."""
    from fastgha_core.refine import realign_to_pixels

    model, avatar, images, masks, cams, expr = sample
    n = avatar.num_reconstructed
    g = avatar.gaussians[:n]
    tcams = prepare_targets(images, cams, masks, 64)[2]
    src = source_views(g.means, tcams, model.config.input_size)
    cap = 0.006
    m, stay = realign_to_pixels(model, g, src, expr, cap)
    assert 0 < int(stay.sum()) < n
    assert torch.equal(m[stay], g.means[stay])
    assert float((m - g.means).norm(dim=-1).max()) <= cap + 1e-6

    def landed(pos):
        out = torch.empty_like(pos)
        with torch.no_grad():
            for i in range(len(expr)):
                sel = src == i
                out[sel] = pos[sel] + model.deform(g.features[sel], pos[sel], expr[i])[0]
        return (out - g.means).norm(dim=-1)

    moved = ~stay
    before, after = landed(g.means)[moved], landed(m)[moved]
    assert float(after.median()) < 0.25 * float(before.median())


def test_photos_preset_changes_colours_only_and_keeps_every_gaussian(sample):
    """REFINE_PRESETS['photos'] (real photos): opacities, scales, positions and the Gaussian count
    stay exactly the network's; only colours move, and they fit the inputs better."""
    import dataclasses

    from fastgha_core.refine import REFINE_PRESETS

    model, avatar, images, masks, cams, expr = sample
    cfg = dataclasses.replace(REFINE_PRESETS["photos"], steps=6, resolution=64)
    assert cfg.lr_opacity == 0 and cfg.lr_scale == 0 and not cfg.optimize_cameras and cfg.photo_in_mask
    res = refine_avatar(model, avatar, images, cams, masks, config=cfg, expressions=expr)
    g0, g1 = avatar.gaussians, res.avatar.gaussians
    assert len(g1) == len(g0)  # nothing pruned
    for name in ("means", "scales", "quats", "opacities"):
        assert torch.equal(getattr(g1, name), getattr(g0, name)), name
    n = avatar.num_reconstructed
    assert float((g1.colors[:n] - g0.colors[:n]).abs().max()) > 0.01
    assert torch.equal(g1.colors[n:], g0.colors[n:])  # appended Gaussians are not refined
    assert torch.equal(res.cameras.w2c, cams.w2c.float())
    targets, tmask, tcams = prepare_targets(images, cams, masks, 64)
    before = masked_psnr(render_inputs(model, avatar, tcams, expr, 64)[0], targets, tmask)
    after = masked_psnr(render_inputs(model, res.avatar, tcams, expr, 64)[0], targets, tmask)
    assert float(after.mean()) > float(before.mean()) + 0.2


def test_noise_floor_keeps_weak_gradients_from_moving_by_the_full_step(sample):
    """``noise_floor`` (on in REFINE_PRESETS['photos']): Adam's first step moves every colour logit
    by about the step size whatever its gradient; with the floor at the median gradient magnitude,
    the colours with weaker gradients move much less, so fewer colours move by half a step or more."""
    import dataclasses

    from fastgha_core.refine import REFINE_PRESETS

    model, avatar, images, masks, cams, expr = sample
    assert REFINE_PRESETS["photos"].noise_floor > 0
    n = avatar.num_reconstructed
    c0 = torch.logit(avatar.gaussians.colors[:n].float().clamp(1e-3, 1 - 1e-3))
    moved = {}
    for floor in (0.0, 1.0):
        cfg = dataclasses.replace(REFINE_PRESETS["photos"], steps=1, resolution=64, noise_floor=floor, w_reg_color=0.0)
        c1 = torch.logit(refine_avatar(model, avatar, images, cams, masks, config=cfg, expressions=expr).avatar.gaussians.colors[:n].float().clamp(1e-3, 1 - 1e-3))
        d = (c1 - c0).abs().amax(-1)  # [N] largest logit change per Gaussian
        moved[floor] = int((d > 0.5 * cfg.lr_color).sum())
    assert moved[0.0] > 100  # without the floor the Gaussians with any gradient jump by ~ the step size
    assert moved[1.0] < 0.75 * moved[0.0]


def test_default_colour_regulariser_holds_the_colours_the_photos_barely_constrain(sample):
    """``REFINE_PRESETS['default'].w_reg_color``: Adam moves a colour its photos barely constrain (a
    semi-transparent Gaussian behind others) as far as a well-seen one; the regulariser pulls such
    colours back to the network's. With the preset's weight fewer Gaussians end far from their
    feed-forward colour than with the old 1e-4, and the input views still gain over feed-forward."""
    import dataclasses

    from fastgha_core.refine import REFINE_PRESETS

    model, avatar, images, masks, cams, expr = sample
    n = avatar.num_reconstructed
    c0 = avatar.gaussians.colors[:n].float()
    base = dataclasses.replace(REFINE_PRESETS["default"], steps=12, resolution=64, prune_opacity=0.0)  # every Gaussian kept
    far, gain = {}, {}
    targets, tmask, tcams = prepare_targets(images, cams, masks, 64)
    before = float(masked_psnr(render_inputs(model, avatar, tcams, expr, 64)[0], targets, tmask).mean())
    for w in (1e-4, base.w_reg_color):
        res = refine_avatar(model, avatar, images, cams, masks, config=dataclasses.replace(base, w_reg_color=w), expressions=expr)
        c1 = res.avatar.gaussians.colors[: res.avatar.num_reconstructed].float()
        if len(c1) == n:
            far[w] = int(((c1 - c0).abs().amax(-1) > 0.1).sum())
        gain[w] = float(masked_psnr(render_inputs(model, res.avatar, tcams, expr, 64)[0], targets, tmask).mean()) - before
    assert base.w_reg_color > 1e-4 and len(far) == 2, far
    assert far[1e-4] > 50 and far[base.w_reg_color] < 0.8 * far[1e-4], far
    assert gain[base.w_reg_color] > 1.0, gain  # measured: +4.1 dB, against +4.2 with 1e-4


def test_photo_in_mask_ignores_the_pixels_outside_the_mask(sample):
    """With ``photo_in_mask`` the photometric term sees only the pixels with mask > 0.5: repainting
    the photos where the mask is 0.4 changes nothing; without it the same paint changes the colours."""
    model, avatar, images, masks, cams, expr = sample
    m = masks.float().reshape(len(images), 1, *images.shape[-2:])
    m = m / 255.0 if masks.dtype == torch.uint8 else m
    band = torch.zeros_like(m, dtype=torch.bool)
    band[..., : images.shape[-2] // 2, :] = True
    band &= m > 0.5  # the upper half of the head: mask 0.4 there, so it counts only without photo_in_mask
    soft = torch.where(band, torch.full_like(m, 0.4), m)
    imgs = images.float() / 255.0 if images.dtype == torch.uint8 else images.float()
    painted = torch.where(band.expand_as(imgs), torch.tensor([1.0, 0.0, 1.0]).view(1, 3, 1, 1), imgs)
    out = {}
    for in_mask in (True, False):
        # at the photos' own 256² (no resampling that would blend the band into its neighbours)
        cfg = RefineConfig(steps=3, resolution=256, lr_opacity=0.0, lr_scale=0.0, w_silhouette=0.0, w_depth=0.0, photo_in_mask=in_mask)
        out[in_mask] = [refine_avatar(model, avatar, x, cams, soft, config=cfg, expressions=expr).avatar.gaussians.colors for x in (imgs, painted)]
    assert torch.allclose(out[True][0], out[True][1], atol=1e-6)
    assert float((out[False][0] - out[False][1]).abs().max()) > 1e-3


def test_refine_preset_for_picks_colours_only_for_avatars_on_a_tracked_head(sample):
    """Avatars on a tracked head surface (real photos: per-view blending data) get the ``photos``
    preset, avatars on the network's depth the ``default`` one; unknown names are refused."""
    import numpy as np

    from fastgha_core.model.surface import HeadSurface
    from fastgha_core.refine import REFINE_PRESETS, refine_config_for, refine_preset_for

    model, avatar, images, masks, cams, expr = sample
    assert avatar.view_blend is None and refine_preset_for(avatar) == "default"
    imgs, in_cams = model.prepare(list(images), [cams[i : i + 1] for i in range(len(cams.K))], list(masks))
    tracked = model.reconstruct(imgs, in_cams, expressions=expr, surface=HeadSurface(np.zeros(100), expr.numpy()))
    assert tracked.view_blend is not None and refine_preset_for(tracked) == "photos"
    cfg = refine_config_for(tracked, 7)
    assert cfg.steps == 7 and cfg.lr_opacity == 0 and cfg.photo_in_mask
    assert refine_config_for(avatar, 7) == RefineConfig(**{**REFINE_PRESETS["default"].__dict__, "steps": 7})
    assert refine_config_for(tracked, 3, "default", optimize_cameras=True).optimize_cameras
    with pytest.raises(ValueError, match="unknown refinement preset 'nope'"):
        refine_config_for(avatar, 3, "nope")


def test_refinement_that_thins_backs_the_cheeks_with_the_cheek_shell(sample):
    """Opacity and scale corrections thin the cheeks, and from a side the mouth interior then shows
    through them: the refined avatar gets the cheek shell (``model/prior.py`` ``cheek_shell``) after its
    other shells, on the head its binding was fitted to, so the same points ``reconstruct`` lays with
    ``DeformConfig.cheek_shell``; colours-only refinement and ``cheek_shell=False`` leave it out."""
    import dataclasses

    from fastgha_core.model.prior import cheek_shell_vertices, face_shell_vertices
    from fastgha_core.refine import REFINE_PRESETS

    model, avatar, images, masks, cams, expr = sample
    assert not model.config.deform.cheek_shell  # the model does not put it in every avatar
    ids = torch.from_numpy(cheek_shell_vertices(model.head_basis()))
    k, n0, extras = len(ids), avatar.num_reconstructed, len(avatar) - avatar.num_reconstructed
    base = dataclasses.replace(REFINE_PRESETS["default"], steps=1, resolution=64)
    out = refine_avatar(model, avatar, images, cams, masks, config=base, expressions=expr).avatar
    n, at = out.num_reconstructed, out.num_reconstructed + model._shell_count()
    assert len(out) == n + extras + k and out.num_interior == avatar.num_interior + k
    run = slice(at, at + k)
    assert torch.equal(out.prior.vertex_ids[run, 0], ids)
    assert torch.all(out.prior.groups()[run] == -1) and torch.all(out.prior.weight[run] == 1)
    # what came before and after it is the avatar's own: the shells before it, the gated interior after
    torch.testing.assert_close(out.gaussians.means[n:at], avatar.gaussians.means[n0 : n0 + model._shell_count()])
    torch.testing.assert_close(out.gaussians.means[at + k :], avatar.gaussians.means[n0 + model._shell_count() :])
    assert torch.equal(out.prior.groups()[at + k :], avatar.prior.groups()[n0 + model._shell_count() :])
    # the same points reconstruct lays when the model puts the shell in every avatar
    imgs, in_cams = model.prepare(list(images), [cams[i : i + 1] for i in range(len(cams.K))], list(masks))
    model.config.deform.cheek_shell = True
    try:
        every = model.reconstruct(imgs, in_cams)
        # there the cheek shell sits between the chin shell and the face shell (``_prior_extras``' order)
        face = len(face_shell_vertices(model.head_basis(), model.config.deform.face_shell))
        at_e = every.num_reconstructed + model._shell_count() - face - k
        torch.testing.assert_close(out.gaussians.means[run], every.gaussians.means[at_e : at_e + k], atol=1e-6, rtol=0)
    finally:
        model.config.deform.cheek_shell = False
    # refining the refined avatar again does not add a second shell
    again = refine_avatar(model, out, images, cams, masks, config=base, expressions=expr).avatar
    assert again.num_interior == out.num_interior and len(again) == again.num_reconstructed + extras + k
    # the refined avatar animates with it (the shell follows the binding like the chin shell)
    frame = model.animate(out, expr[0])
    assert len(frame) >= at + k
    for cfg in (dataclasses.replace(REFINE_PRESETS["photos"], steps=1, resolution=64), dataclasses.replace(base, cheek_shell=False)):
        other = refine_avatar(model, avatar, images, cams, masks, config=cfg, expressions=expr).avatar
        assert len(other) == other.num_reconstructed + extras and other.num_interior == avatar.num_interior
