"""The off-head pixels' distances relaxed between the head's (``model/surface.py``
``smooth_off_head_depth``, ``GaussianHeadConfig.off_head_smooth``; issue 17: the steps of the
nearest-hit field opened slits of background through long hair in other views)."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from fastgha_core.model.surface import HeadSurface, SurfaceDepth, smooth_off_head_depth, surface_ray_depth


def _depth(t: torch.Tensor, hit: torch.Tensor) -> SurfaceDepth:
    return SurfaceDepth(t.clone(), hit.clone(), torch.zeros_like(hit), None)


def test_a_step_between_two_head_rows_becomes_the_membrane_between_them():
    """A column of off-head pixels between a head row at 0.5 m and one at 0.7 m, given the
    nearest-hit field (0.5 m above the middle, 0.7 m below: one 20 cm step), relaxes to the straight
    line between the two (the harmonic interpolation of a linear boundary); the head rows, the
    pixels outside the matte and the ``fixed`` ones keep their values."""
    s = 33
    t = torch.full((1, s, s), 0.6)
    hit = torch.zeros(1, s, s, dtype=torch.bool)
    hit[0, 0], hit[0, -1] = True, True
    t[0, 0], t[0, -1] = 0.5, 0.7
    t[0, 1:17], t[0, 17:-1] = 0.5, 0.7  # nearest-hit: a step in the middle
    fg = torch.zeros(1, s, s)
    fg[0, :, 4:29] = 1.0  # the matte: columns 4..28
    fixed = torch.zeros(1, s, s, dtype=torch.bool)
    fixed[0, 5:9, 20] = True
    sd = _depth(t, hit)
    out = smooth_off_head_depth(sd, fg, length=3.0, fixed=fixed)  # (3 * 33)^2 iterations: converged
    line = torch.linspace(0.5, 0.7, s)
    col = out.t[0, :, 10]
    assert torch.allclose(col, line, atol=2e-3), (col - line).abs().max()
    assert float((out.t[0, 1:, 10] - out.t[0, :-1, 10]).abs().max()) < 0.01  # no step left (it was 0.2 m)
    assert torch.equal(out.t[0, 0], t[0, 0]) and torch.equal(out.t[0, -1], t[0, -1])  # the head holds
    assert torch.equal(out.t[0, :, :4], t[0, :, :4]) and torch.equal(out.t[0, :, 29:], t[0, :, 29:])  # outside the matte: unchanged
    assert torch.equal(out.t[fixed], t[fixed])
    assert out.hit is sd.hit and out.beyond_face is sd.beyond_face


def test_vertical_relaxation_leaves_a_left_right_gradient_alone():
    """``axis="vertical"`` averages only the pixels above and below: an off-head region whose head
    boundary changes from left to right (a turned head's torso, throat to nape) keeps each column's
    value, while ``"both"`` mixes the columns."""
    s = 24
    t = torch.zeros(1, s, s)
    hit = torch.zeros(1, s, s, dtype=torch.bool)
    hit[0, 0] = True
    t[0] = torch.linspace(0.4, 0.8, s)[None, :].expand(s, s)  # every column its head pixel's distance
    fg = torch.ones(1, s, s)
    sd = _depth(t, hit)
    vert = smooth_off_head_depth(sd, fg, length=1.0, axis="vertical")
    assert torch.allclose(vert.t, t)
    t2 = t.clone()
    t2[0, 1:, : s // 2] = 0.4  # nearest-hit steps across the columns below the head row
    t2[0, 1:, s // 2 :] = 0.8
    both = smooth_off_head_depth(_depth(t2, hit), fg, length=1.0, axis="both")
    mid = both.t[0, s // 2, s // 2 - 1 : s // 2 + 1]
    assert float(mid[1] - mid[0]) < 0.2  # the 0.4 m step across the columns is smoothed out
    vert2 = smooth_off_head_depth(_depth(t2, hit), fg, length=1.0, axis="vertical").t
    perm = torch.randperm(s, generator=torch.Generator().manual_seed(0))  # columns shuffled: each column relaxes on its own
    shuffled = smooth_off_head_depth(_depth(t2[..., perm], hit[..., perm]), fg, length=1.0, axis="vertical").t
    assert torch.equal(shuffled, vert2[..., perm])
    shuffled_both = smooth_off_head_depth(_depth(t2[..., perm], hit[..., perm]), fg, length=1.0, axis="both").t
    assert not torch.allclose(shuffled_both, both.t[..., perm], atol=1e-3)  # "both" mixes neighbouring columns


def test_the_band_beside_the_head_keeps_the_nearest_head_distance():
    """With ``hold``, the off-head pixels within ``round(hold * S)`` pixels of the head's outline keep
    their nearest-hit distance (the hair lying against the head, framing the face); beyond the band
    the step is still relaxed, and the band's edge is held like the head."""
    s = 32
    t = torch.full((1, s, s), 0.7)
    hit = torch.zeros(1, s, s, dtype=torch.bool)
    hit[0, :4] = True
    t[0, :4], t[0, 4:12] = 0.5, 0.5  # nearest-hit below the head rows: 0.5, then a 20 cm step at row 12
    fg = torch.ones(1, s, s)
    out = smooth_off_head_depth(_depth(t, hit), fg, length=1.0, hold=4 / s)  # a 4-pixel band: rows 4..7
    assert torch.equal(out.t[0, 4:8], t[0, 4:8])
    assert float((out.t[0, 9:, 5] - out.t[0, 8:-1, 5]).abs().max()) < 0.05  # beyond it, no 20 cm step left
    free = smooth_off_head_depth(_depth(t, hit), fg, length=1.0)
    assert not torch.equal(free.t[0, 11:13], t[0, 11:13]) and float((free.t[0, 4:8] - t[0, 4:8]).abs().max()) < 0.2


def test_zero_length_is_the_identity_and_bad_arguments_are_refused():
    t = torch.rand(2, 8, 8)
    hit = torch.rand(2, 8, 8) > 0.5
    sd = _depth(t, hit)
    assert smooth_off_head_depth(sd, torch.ones(2, 8, 8), 0.0) is sd
    with pytest.raises(ValueError, match="length and hold must be >= 0"):
        smooth_off_head_depth(sd, torch.ones(2, 8, 8), -0.1)
    with pytest.raises(ValueError, match="length and hold must be >= 0"):
        smooth_off_head_depth(sd, torch.ones(2, 8, 8), 0.1, hold=-0.05)
    with pytest.raises(ValueError, match="axis must be one of"):
        smooth_off_head_depth(sd, torch.ones(2, 8, 8), 0.1, axis="diagonal")
    with pytest.raises(ValueError, match=r"must be \[2, 8, 8\]"):
        smooth_off_head_depth(sd, torch.ones(1, 8, 8), 0.1)


def test_the_relaxation_reaches_as_far_at_any_input_size():
    """``length`` is a fraction of the views' side: the same scene at 32² and 64² relaxes to the same
    profile (sampled at the same places), so a model with larger inputs is not smoothed less."""
    profiles = []
    for s in (32, 64):
        t = torch.zeros(1, s, s)
        hit = torch.zeros(1, s, s, dtype=torch.bool)
        hit[0, 0] = True
        t[0, 0], t[0, 1:] = 0.5, 0.7  # an off-head region hanging below a head row, one step at its top
        out = smooth_off_head_depth(_depth(t, hit), torch.ones(1, s, s), length=0.15)
        profiles.append(out.t[0, :, s // 2][torch.arange(0, s, s // 8)])
    assert torch.allclose(profiles[0], profiles[1], atol=0.01), profiles
    assert float(profiles[0][1]) < 0.69  # it did reach the rows below the step


def test_reconstruct_relaxes_only_off_head_gaussians_along_their_rays():
    """On a tracked head, ``gaussians.off_head_smooth`` moves the Gaussians of off-head matte pixels
    along their own pixel rays (their camera sees them where it did) and leaves the head's pixels."""
    from fastgha_core.cameras import Cameras
    from fastgha_core.model.fastgha import load_model
    from fastgha_core.tracking.camera import pose_to_cameras
    from fastgha_core.tracking.fit import FRONTAL_R, default_intrinsics, rodrigues

    model = load_model("tiny")
    s = model.config.input_size
    R = FRONTAL_R @ rodrigues(np.array([0.0, np.radians(10.0), 0.0]))
    cam: Cameras = pose_to_cameras(R[None], np.array([[0.0, 0.01, 0.6]]), default_intrinsics(s, s, 40.0), s, s)
    head = HeadSurface(np.zeros(100, np.float32), np.zeros((1, 53), np.float32), None)
    sd = surface_ray_depth(head, cam)
    img = torch.full((1, 3, s, s), 1.0)
    yy, xx = torch.meshgrid(torch.arange(s), torch.arange(s), indexing="ij")
    blob = ((xx - s / 2) / (0.45 * s)) ** 2 + ((yy - s * 0.55) / (0.5 * s)) ** 2 < 1  # a matte wider than the head: long hair
    img[0, :, blob] = 0.35
    gc = model.config.gaussians
    saved = gc.off_head_smooth, gc.mirror_views, gc.prune_opacity, gc.hair_fit, gc.coverage_target, gc.grazing_stretch
    gc.mirror_views, gc.prune_opacity, gc.hair_fit, gc.coverage_target, gc.grazing_stretch = False, 0.0, False, 0.0, 0.0
    try:
        with torch.no_grad():
            gc.off_head_smooth = 0.0
            a = model.reconstruct(img, cam, surface=head).gaussians[: s * s]
            gc.off_head_smooth = saved[0]
            b = model.reconstruct(img, cam, surface=head).gaussians[: s * s]
    finally:
        gc.off_head_smooth, gc.mirror_views, gc.prune_opacity, gc.hair_fit, gc.coverage_target, gc.grazing_stretch = saved
    moved = (b.means - a.means).norm(dim=-1) > 1e-6
    off_head = (~sd.hit[0] & blob).reshape(-1)
    assert int(moved.sum()) > 50 and not bool((moved & ~off_head).any())  # only off-head matte pixels move
    centre = cam.centers[0].float()
    ra = torch.nn.functional.normalize(a.means[moved] - centre, dim=-1)
    rb = torch.nn.functional.normalize(b.means[moved] - centre, dim=-1)
    assert float((ra - rb).norm(dim=-1).max()) < 1e-4  # along their own rays
