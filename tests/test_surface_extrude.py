"""Long hair beside the face gets depth: copies of a frontal photo's hair pixels further back along
their rays (``model/surface.py`` ``off_head_extrusion``, ``GaussianHeadConfig.off_head_extrude_m``;
issue 17: seen from the side, the hair behind the ear was left uncovered)."""

from __future__ import annotations

import numpy as np
import pytest
import torch
import torch.nn.functional as F

from fastgha_core.model.gaussian_head import foreground_weight
from fastgha_core.model.surface import (
    BESIDE_FACE_LATERAL_M,
    EXTRUDE_NEAR_M,
    HeadSurface,
    _mirrored,
    midline_reflection,
    off_head_behind_ears,
    off_head_extrusion,
    surface_ray_depth,
)
from fastgha_core.tracking.camera import pose_to_cameras
from fastgha_core.tracking.fit import FRONTAL_R, default_intrinsics, rodrigues

S = 64
HAIR, SKIN, BG = (0.30, 0.20, 0.10), (0.80, 0.60, 0.50), (1.0, 1.0, 1.0)


def _cams(yaws, s=S):
    R = np.stack([FRONTAL_R @ rodrigues(np.array([0.0, np.radians(y), 0.0])) for y in yaws])
    return pose_to_cameras(R, np.tile([0.0, 0.01, 0.6], (len(yaws), 1)), default_intrinsics(s, s, 40.0), s, s)


def _photos(sd, grow_px, band=HAIR, s=S):
    """Matted photos of the mean head: the head's pixels and a band ``grow_px`` wide around them in
    ``band``'s colour, the bare face skin, background outside."""
    from fastgha_core.constants import BACKGROUND_RGB

    hit = sd.hit.float()[:, None]
    person = F.max_pool2d(hit, 2 * grow_px + 1, stride=1, padding=grow_px)[:, 0] > 0.5 if grow_px > 0 else sd.hit
    img = torch.tensor(BACKGROUND_RGB).view(1, 3, 1, 1).repeat(len(hit), 1, s, s)
    img = torch.where(person[:, None], torch.tensor(HAIR).view(1, 3, 1, 1), img)
    img = torch.where((person & ~sd.hit)[:, None], torch.tensor(band).view(1, 3, 1, 1), img)
    return torch.where(sd.face_hit[:, None], torch.tensor(SKIN).view(1, 3, 1, 1), img)


def _setup(yaws=(0.0, 70.0), grow=(8, 8), band=HAIR):
    cams, head = _cams(yaws), HeadSurface(np.zeros(100, np.float32), np.zeros((len(yaws), 53), np.float32))
    sd = off_head_behind_ears(surface_ray_depth(head, cams), head, cams)
    imgs = torch.cat([_photos(sd, g, band)[i : i + 1] for i, g in enumerate(grow)])
    return cams, head, sd, imgs


def test_hair_beside_a_frontal_face_is_copied_further_back_along_its_ray():
    from fastgha_core.data.headmodel import HeadModel

    cams, head, sd, imgs = _setup()
    fg = foreground_weight(imgs)
    src, pts = off_head_extrusion(sd, head, cams, fg, imgs, views=2, depth_m=0.10)
    assert len(src) > 50
    view, pix = src // (S * S), src % (S * S)
    assert bool((view == 0).all())  # only the frontal view's pixels (the side view looks along the ears' plane)
    off = sd.off_head(fg)[0].reshape(-1)
    assert bool(off[pix].all())  # off-head pixels only
    colour = imgs[0].reshape(3, -1)[:, pix].T
    assert torch.allclose(colour, torch.tensor(HAIR).expand_as(colour))  # hair-coloured ones
    o, d = cams[0:1].pixel_rays()
    o, d = o.reshape(-1, 3)[pix], d.reshape(-1, 3)[pix]
    t = ((pts - o) * d).sum(-1)
    assert float((pts - (o + t[:, None] * d)).norm(dim=-1).max()) < 1e-4  # on the pixel's own ray
    assert bool((t > sd.t[0].reshape(-1)[pix] + 1e-3).all())  # behind the pixel's own point
    assert float(pts[:, 2].min()) >= -0.10 - 1e-5  # no more than depth_m behind the ears' plane (world = head frame)
    assert float(pts[:, 0].abs().min()) > BESIDE_FACE_LATERAL_M - 0.02  # beside the head, not across it
    verts = torch.from_numpy(head.vertices(0, HeadModel.load())).float()
    assert float(torch.cdist(pts, verts).min(1).values.max()) <= EXTRUDE_NEAR_M + 1e-5
    fewer, _ = off_head_extrusion(sd, head, cams, fg, imgs, views=2, depth_m=0.03)
    assert 0 < len(fewer) < len(src)  # a shorter depth gives fewer copies


def test_skin_beside_the_face_is_not_copied():
    cams, head, sd, imgs = _setup(band=SKIN)
    src, _ = off_head_extrusion(sd, head, cams, foreground_weight(imgs), imgs, views=2)
    assert len(src) == 0


def test_copies_stay_inside_the_other_photos_mattes_and_so_do_their_mirror_images():
    cams, head, sd, imgs = _setup(grow=(8, 0))  # the side photo's matte is the bald head: no hair hangs behind the ear
    fg = foreground_weight(imgs)
    src, pts = off_head_extrusion(sd, head, cams, fg, imgs, views=2, mirror=False)
    cw, hw, sdw, iw = _setup()  # the same with hair behind the ear in the side photo's matte
    wide, _ = off_head_extrusion(sdw, hw, cw, foreground_weight(iw), iw, views=2, mirror=False)
    assert len(src) < len(wide)  # the tight side matte carved copies away
    uv, z = cams[1].project(pts)
    x, y = uv[:, 0].floor().long(), uv[:, 1].floor().long()
    inside = (x >= 0) & (x < S) & (y >= 0) & (y < S) & (z > 0)
    held = F.max_pool2d((fg[1:2, None] > 0.5).float(), 5, stride=1, padding=2)[0, 0] > 0.5  # the matte dilated by 2 px
    assert bool(held[y[inside], x[inside]].all())
    mirrored, mpts = off_head_extrusion(sd, head, cams, fg, imgs, views=2, mirror=True)
    assert len(mirrored) < len(src)  # the side photo sees the other side: its outline rules out copies whose mirror image leaves it
    m = _mirrored(mpts, midline_reflection(None))
    uv, z = cams[1].project(m)
    x, y = uv[:, 0].floor().long(), uv[:, 1].floor().long()
    inside = (x >= 0) & (x < S) & (y >= 0) & (y < S) & (z > 0)
    assert bool(held[y[inside], x[inside]].all())


def test_it_checks_its_inputs():
    cams, head, sd, imgs = _setup()
    fg = foreground_weight(imgs)
    with pytest.raises(ValueError, match="views must be in"):
        off_head_extrusion(sd, head, cams, fg, imgs, views=3)
    with pytest.raises(ValueError, match="must be > 0"):
        off_head_extrusion(sd, head, cams, fg, imgs, views=2, depth_m=0.0)
    with pytest.raises(ValueError, match="fewer than the 2 real ones"):
        off_head_extrusion(sd, head.subset([0]), cams, fg, imgs, views=2)
    with pytest.raises(ValueError, match="foreground must be"):
        off_head_extrusion(sd, head, cams, fg[:1], imgs, views=2)


def test_reconstruct_appends_the_copies_drawn_under_the_others():
    from fastgha_core.model.fastgha import load_model

    model = load_model("tiny")
    s = model.config.input_size
    cams, head = _cams((0.0, 70.0), s), HeadSurface(np.zeros(100, np.float32), np.zeros((2, 53), np.float32))
    sd = off_head_behind_ears(surface_ray_depth(head, cams), head, cams)
    imgs = torch.cat([_photos(sd, 10, s=s)[:1], _photos(sd, 10, s=s)[1:]])
    gc = model.config.gaussians
    assert gc.off_head_extrude_m > 0  # on by default
    gc.mirror_views, gc.prune_opacity, model.config.deform.prior = False, 0.0, False  # every pixel's Gaussian, in order, then the copies
    on = model.reconstruct(imgs, cams, surface=head)
    gc.off_head_extrude_m = 0.0
    off = model.reconstruct(imgs, cams, surface=head)
    n = 2 * s * s
    assert len(off.gaussians) == n and len(on.gaussians) > n + 50
    assert torch.equal(on.gaussians.means[:n], off.gaussians.means[:n])  # the pixels' own Gaussians are as without
    copies = on.gaussians[n:]
    assert torch.allclose(copies.colors, torch.tensor(HAIR).expand_as(copies.colors), atol=0.35)  # the hair's colour, roughly (the network's)
    assert on.view_blend is not None and on.view_blend.under is not None and bool(on.view_blend.under[n:].all())  # drawn under the head in every frame
    gc.off_head_extrude_m, gc.mirror_views = 0.10, True  # the turned view adds its mirror image, a third view after the real ones
    mirrored = model.reconstruct(imgs, cams, surface=head)
    assert len(mirrored.gaussians) == 3 * s * s + (len(on.gaussians) - n)  # the same copies: only the real views give and judge them
