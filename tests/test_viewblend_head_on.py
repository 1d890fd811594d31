"""Gaussians contradicted by the view that sees their point most head-on
(``model/viewblend.py`` ``contradicted_by_head_on_view``; ``FastGHA.reconstruct``'s
``gaussians.head_on_colour_tol``; issue 17: a pitch-up photo's fringe drawn on the forehead)."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from fastgha_core.cameras import Cameras
from fastgha_core.model.viewblend import contradicted_by_head_on_view

S = 32


def _setup():
    """A frontal camera A and one from below, B; a forehead point X (up and forward of the head centre)."""
    eyes = torch.tensor([[0.0, 0.1, 1.0], [0.0, -0.6, 0.8]])
    cams = Cameras.look_at(eyes, torch.zeros(3), fov_deg=30.0, width=S, height=S)
    imgs = torch.empty(2, 3, S, S)
    imgs[0] = 0.8  # A sees skin
    imgs[1] = 0.2  # B sees the fringe's underside
    x = torch.tensor([[0.0, 0.06, 0.08]])
    return cams, imgs, x


def _run(cams, imgs, means, colour, source, mask, **kw):
    n = len(means)
    return contradicted_by_head_on_view(
        means, torch.full((n, 3), colour), torch.tensor(source), torch.tensor(mask, dtype=torch.uint8), cams, imgs, **kw
    )


def test_the_grazing_views_gaussian_is_contradicted_by_the_head_on_one_and_not_the_reverse():
    cams, imgs, x = _setup()
    both = 0b11
    assert bool(_run(cams, imgs, x, 0.2, [1], [both])[0])  # B's dark Gaussian where A, more head-on, sees light
    assert not bool(_run(cams, imgs, x, 0.8, [0], [both])[0])  # A's own Gaussian: no view sees X more squarely
    assert not bool(_run(cams, imgs, x, 0.75, [1], [both])[0])  # B agreeing with A (within the tolerance)
    assert not bool(_run(cams, imgs, x, 0.2, [1], [0b10])[0])  # A does not see X (occluded / off its matte): no judge
    assert not bool(_run(cams, imgs, x, 0.2, [1], [both], gain_deg=80.0)[0])  # A not squarely enough better
    assert bool(_run(cams, imgs, x, 0.2, [1], [both], colour_tol=0.5)[0]) and not bool(_run(cams, imgs, x, 0.2, [1], [both], colour_tol=0.7)[0])


def test_only_the_leading_views_judge_and_are_judged():
    """Mirrored virtual views (after the real ones) are left alone, and do not judge the real ones."""
    cams, imgs, x = _setup()
    assert not bool(_run(cams, imgs, x, 0.2, [1], [0b11], views=1)[0])  # B is not among the real views
    # A mirrored copy of A (view 2, a third camera) is not a judge of B
    cams3 = Cameras.stack([cams, cams[0:1]])
    imgs3 = torch.cat([imgs, imgs[0:1]])
    assert not bool(_run(cams3, imgs3, x, 0.2, [1], [0b110], views=2)[0])
    assert bool(_run(cams3, imgs3, x, 0.2, [1], [0b111], views=2)[0])


def test_the_judge_is_sampled_where_the_point_projects():
    """The colour compared is the judge's pixel at the point's projection (not an average)."""
    cams, imgs, x = _setup()
    uv, _ = cams[0].project(x)
    u, v = int(uv[0, 0]), int(uv[0, 1])
    imgs = imgs.clone()
    imgs[0] = 0.2
    imgs[0, :, max(v - 2, 0) : v + 3, max(u - 2, 0) : u + 3] = 0.8  # light only around X's pixel in A
    assert bool(_run(cams, imgs, x, 0.2, [1], [0b11])[0])
    imgs[0, :, max(v - 2, 0) : v + 3, max(u - 2, 0) : u + 3] = 0.2
    assert not bool(_run(cams, imgs, x, 0.2, [1], [0b11])[0])


def test_errors_say_what_was_expected():
    cams, imgs, x = _setup()
    with pytest.raises(ValueError, match="images"):
        contradicted_by_head_on_view(x, torch.zeros(1, 3), torch.tensor([1]), torch.tensor([3], dtype=torch.uint8), cams, imgs[:1])
    with pytest.raises(ValueError, match="same N"):
        contradicted_by_head_on_view(x, torch.zeros(2, 3), torch.tensor([1]), torch.tensor([3], dtype=torch.uint8), cams, imgs)


def test_sharp_gaussians_fade_faster_away_from_their_own_camera_and_survive_a_file(tmp_path):
    """``ViewBlend.sharp``: factor ``exp(-a_source / (tau x sharp_scale))`` (the source camera's own
    angle to the render camera), instead of ``exp(-(a_source - a_nearest covering) / tau)``: 1 at its
    own camera, falling fast away from it even where no view is nearer; saved with the avatar."""
    from fastgha_core.model.viewblend import ViewBlend, view_directions

    cams, _, _ = _setup()
    dirs = view_directions(cams)
    src = torch.tensor([1, 1, 0, -1], dtype=torch.int8)
    mask = torch.tensor([0b11, 0b11, 0b11, 0], dtype=torch.uint8)
    sharp = torch.tensor([False, True, True, False])
    vb = ViewBlend(src, mask, dirs, None, sharp, 0.25)
    f = vb.factors(cams[0:1], 20.0)  # rendered from A: B's Gaussians are d degrees from the nearest
    from fastgha_core.model.viewblend import angles_deg

    a = angles_deg(dirs, cams[0:1])
    d = float(a[1] - a[0])
    assert float(f[0]) == pytest.approx(np.exp(-d / 20.0), rel=1e-4)
    assert float(f[1]) == pytest.approx(np.exp(-float(a[1]) / 5.0), rel=1e-4) and float(f[1]) < float(f[0])
    assert float(f[2]) == pytest.approx(np.exp(-float(a[0]) / 5.0), rel=1e-3) and float(f[3]) == 1.0  # A's own at A (its camera ~0 deg off); no source: 1
    mid = Cameras.look_at(torch.tensor([[0.0, -0.25, 1.0]]), torch.zeros(3), fov_deg=30.0, width=S, height=S)  # between A and B
    h = vb.factors(mid, 20.0)
    b = angles_deg(dirs, mid)
    assert float(h[1]) == pytest.approx(np.exp(-float(b[1]) / 5.0), rel=1e-4)  # by B's own angle, not B's minus A's
    g = vb.factors(cams[1:2], 20.0)
    assert float(g[1]) == pytest.approx(1.0)  # at its own camera a sharp Gaussian is drawn fully
    plain = ViewBlend(src, mask, dirs)
    assert torch.equal(plain.factors(cams[0:1], 20.0)[[0, 3]], f[[0, 3]])
    back = ViewBlend.from_tensors(vb.tensors(), 4)
    assert torch.equal(back.sharp, sharp) and back.sharp_scale == pytest.approx(0.25)
    assert torch.allclose(back.factors(cams[0:1], 20.0), f)
    assert ViewBlend.from_tensors(plain.tensors(), 4).sharp is None  # older files: nothing sharp
    assert torch.equal(vb.subset(torch.tensor([1, 2])).sharp, sharp[1:3])
    with pytest.raises(ValueError, match="sharp"):
        ViewBlend(src, mask, dirs, None, torch.ones(3, dtype=torch.bool))
    with pytest.raises(ValueError, match="sharp_scale"):
        ViewBlend(src, mask, dirs, None, sharp, 0.0)


def test_reconstruct_marks_the_contradicted_gaussians_sharp_only_when_asked():
    """``head_on_colour_tol`` 0 leaves the avatar as it was (nothing sharp); > 0 marks Gaussians of
    the real views only (the mirrored views' never), keeps every Gaussian, and does nothing on the
    network-depth path."""
    from fastgha_core.constants import BACKGROUND_RGB
    from fastgha_core.model.fastgha import load_model
    from fastgha_core.model.surface import HeadSurface
    from fastgha_core.tracking.camera import pose_to_cameras
    from fastgha_core.tracking.fit import FRONTAL_R, default_intrinsics, rodrigues

    model = load_model("tiny")
    s = model.config.input_size
    yaws, pitches = [0.0, 0.0, 50.0], [0.0, 30.0, 0.0]
    R = np.stack([FRONTAL_R @ rodrigues(np.array([np.radians(p), np.radians(y), 0.0])) for y, p in zip(yaws, pitches)])
    t = np.tile([0.0, 0.01, 0.6], (3, 1))
    cams = pose_to_cameras(R, t, default_intrinsics(s, s, 30.0), s, s).to(dtype=torch.float32)
    g = torch.Generator().manual_seed(5)
    imgs = torch.tensor(BACKGROUND_RGB, dtype=torch.float32).view(1, 3, 1, 1).repeat(3, 1, s, s)
    imgs[:, :, s // 8 : 7 * s // 8, s // 4 : 3 * s // 4] = 0.1 + 0.8 * torch.rand(3, 3, 3 * s // 4, s // 2, generator=g)  # views disagree everywhere
    surface = HeadSurface(np.zeros(100, np.float32), np.zeros((3, 53), np.float32))
    gc = model.config.gaussians
    saved = gc.head_on_colour_tol
    try:
        gc.head_on_colour_tol = 0.0
        off = model.reconstruct(imgs, cams, surface=surface)
        gc.head_on_colour_tol = 0.25
        on = model.reconstruct(imgs, cams, surface=surface)
        assert off.view_blend.sharp is None or not bool(off.view_blend.sharp.any())
        assert on.num_reconstructed == off.num_reconstructed and torch.equal(on.gaussians.means, off.gaussians.means)
        sharp, src = on.view_blend.sharp, on.view_blend.source_view.long()
        assert int(sharp.sum()) > 100  # random colours: the views contradict each other
        assert not bool(sharp[src >= 3].any())  # mirrored views untouched
        net_on = model.reconstruct(imgs, cams)  # no surface: no per-view data at all
        assert net_on.view_blend is None
    finally:
        gc.head_on_colour_tol = saved
