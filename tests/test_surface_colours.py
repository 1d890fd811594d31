"""``model.surface.sample_photo_colours``: each point takes its own photo's colour where it projects."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from fastgha_core.model.surface import sample_photo_colours
from fastgha_core.tracking.camera import pose_to_cameras
from fastgha_core.tracking.fit import FRONTAL_R, default_intrinsics, rodrigues


def _cameras(yaws_deg, size, dist=0.6):
    R = np.stack([FRONTAL_R @ rodrigues(np.array([0.0, np.radians(y), 0.0])) for y in yaws_deg])
    t = np.tile([0.0, 0.01, dist], (len(yaws_deg), 1))
    return pose_to_cameras(R, t, default_intrinsics(size, size, 30.0), size, size)


def _photos(v, size, seed=0):
    return torch.rand(v, 3, size, size, generator=torch.Generator().manual_seed(seed))


def test_a_point_on_a_pixel_centre_ray_takes_that_pixel_of_its_own_view():
    cams = _cameras([0.0, 40.0], 32).to(dtype=torch.float32)
    photos = _photos(2, 32)
    o, d = cams.pixel_rays()  # [2, 32, 32, 3]
    depth = 0.45 + 0.1 * torch.rand(2, 32, 32, generator=torch.Generator().manual_seed(1))  # any depth along the ray
    pts = (o + depth[..., None] * d).reshape(-1, 3)
    vi = torch.arange(2).repeat_interleave(32 * 32)
    got = sample_photo_colours(pts, cams, photos, vi)
    want = photos.permute(0, 2, 3, 1).reshape(-1, 3)
    assert torch.allclose(got, want, atol=1e-4)
    # the view index decides which photo is read: swapped, the colours are the other view's pixels
    # at the points' projections there, not these
    other = sample_photo_colours(pts, cams, photos, 1 - vi)
    assert (other - want).abs().max() > 0.1


def test_a_coarse_grid_point_takes_the_mean_of_the_fine_photos_2x2_block():
    """A Gaussian laid on a 16-pixel grid samples a 32-pixel photo at the centre of its 2x2 block."""
    fine = _cameras([20.0], 32).to(dtype=torch.float32)
    coarse = fine.resize(16, 16)
    photos = _photos(1, 32, seed=3)
    o, d = coarse.pixel_rays()
    pts = (o + 0.5 * d).reshape(-1, 3)
    got = sample_photo_colours(pts, fine, photos, torch.zeros(len(pts), dtype=torch.long))
    want = torch.nn.functional.avg_pool2d(photos, 2)[0].permute(1, 2, 0).reshape(-1, 3)
    assert torch.allclose(got, want, atol=1e-4)


def test_sample_photo_colours_checks_its_input():
    cams = _cameras([0.0], 8).to(dtype=torch.float32)
    pts = torch.zeros(4, 3)
    vi = torch.zeros(4, dtype=torch.long)
    with pytest.raises(ValueError, match=r"photos must have shape \[1, 3, 8, 8\]"):
        sample_photo_colours(pts, cams, _photos(1, 16), vi)
    with pytest.raises(ValueError, match="view_index must lie in"):
        sample_photo_colours(pts, cams, _photos(1, 8), vi + 1)
    with pytest.raises(ValueError, match=r"points \[N, 3\] and view_index \[N\]"):
        sample_photo_colours(pts, cams, _photos(1, 8), vi[:3])
